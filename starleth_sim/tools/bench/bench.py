"""``starleth-bench``: simulation speed per configuration, beside the paper's Table 1.

The robot stands under the joint PD posture hold; only ``Simulator.step`` is timed. Figures
are physics steps per second (the paper's "evaluations per second") and the real-time factor
(simulated time / wall time). A second, profiled run breaks one step down like Fig. 7.
All configurations run in the same process, one after the other, so their ratios are
comparable on a shared machine.

``--impedance``: the joint impedance step (``ImpedanceCommand``, its law evaluated at every
physics step inside the kernels) beside the torque step of the same PD hold (the torques
computed in Python once per control step), on the given presets (default HmJ Cm), in
interleaved rounds in one process: µs per control step (median of the rounds) and the ratio.

``--robot NAME|all``: the robot (a library name, a spec or URDF path; `all`: each robot of
the library in turn; default the presets', StarlETH), held by the PD hold scaled to it
(``PostureHold.for_robot``).

``--vs-mujoco``: the same robot (its URDF compiled by MuJoCo, free base joint, our contact
points as its only collision spheres, ground plane, Δt = 2.5 ms, Newton solver, elliptic
cones, μ as in the preset: :func:`mujoco_model`) standing under the same joint PD hold from
the same standing state, beside `Simulator` on the given presets
(default HmJ HmS Cm), in interleaved rounds of physics steps in one process: steps/s per
preset (median of the rounds) and the ratio to MuJoCo, plus a check that both simulate the
same thing: total normal force ≈ weight, and against MuJoCo run again with its feet sticking
(noslip; its default friction is regularised and lets standing feet creep) the base height
above the feet's contact depth within 2 mm; with several robots, a table per robot
(doc/performance.md). mujoco is an
optional benchmark dependency (``requirements-bench.txt``, installed by ``make bench``).
"""
from __future__ import annotations

import argparse
import sys
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import numpy as np

from ...physics.config import PRESETS as DEFAULT_PRESETS  # the paper's Table 1
from ...physics.config import ConfigError, load_preset
from ...physics.impedance import ImpedanceCommand
from ...physics.posture import PostureHold
from ...physics.simulator import Simulator
from ...physics.stepper import PHASES, StepperStats
from ...robots import available_robots, robot_description
from .states import print_states
from .terrain import print_terrain_rounds
from .timing import timed_steps


def measure(preset: str, seconds: float, repeats: int = 3, robot: str | None = None):
    """(steps/s samples, rtf samples, mean prox iterations per step) for `seconds` of
    simulated standing of `robot` (default: the preset's), repeated."""
    rates, rtfs, iters = [], [], []
    for _ in range(repeats):
        sim = Simulator.from_preset(preset, robot=robot)
        hold = PostureHold.for_robot(sim.description, sim.joint_positions())
        n = int(round(seconds / sim.control_period))
        sim.step(hold.torque(sim))  # warm-up (first calls, caches)
        wall, it = timed_steps(sim, n, hold)
        steps = n * sim.config.steps_per_control
        rates.append(steps / wall)
        rtfs.append(n * sim.control_period / wall)
        iters.append(it / steps)
    return np.array(rates), np.array(rtfs), float(np.mean(iters))


def breakdown(preset: str, seconds: float, robot: str | None = None):
    """Mean time per physics step and phase [µs] (profiled run, includes timer overhead)."""
    sim = Simulator.from_preset(preset, profile=True, robot=robot)
    hold = PostureHold.for_robot(sim.description, sim.joint_positions())
    for _ in range(20):  # warm-up: first calls of the profiled path load compiled code
        sim.step(hold.torque(sim))
    sim.reset()
    sim.stepper.stats = StepperStats()
    n = int(round(seconds / sim.control_period))
    for _ in range(n):
        sim.step(hold.torque(sim))
    steps = sim.stepper.stats.steps
    return {k: 1e6 * v / steps for k, v in zip(PHASES, sim.stepper.stats.timings, strict=True)}


#: --impedance: the presets compared by default
IMPEDANCE_PRESETS = ("HmJ", "Cm")


def measure_impedance(preset: str, rounds: int, steps: int):
    """(µs per control step of the torque step, of the impedance step): the median of
    `rounds` interleaved rounds of `steps` control steps each, both simulators standing
    under the PostureHold gains (the torque one with τ computed from the published state,
    untimed; the impedance one with a fixed command). Only Simulator.step is timed."""
    torque_sim, imp_sim = Simulator.from_preset(preset), Simulator.from_preset(preset)
    hold = PostureHold(torque_sim.joint_positions())
    command = ImpedanceCommand.create(imp_sim.joint_names, position=hold.target, kp=hold.kp,
                                      kd=hold.kd)
    torque_sim.step(hold.torque(torque_sim))    # warm-up (first calls, caches)
    imp_sim.step(command)
    times = {"torque": [], "impedance": []}
    for _ in range(rounds):
        times["torque"].append(timed_steps(torque_sim, steps, hold)[0] / steps)
        times["impedance"].append(timed_steps(imp_sim, steps, command=command)[0] / steps)
    return tuple(1e6 * float(np.median(times[k])) for k in ("torque", "impedance"))


def impedance(presets, rounds: int, steps: int) -> int:
    print(f"Impedance step against torque step, {rounds} interleaved rounds x {steps} "
          f"control steps, µs per control step (median); Python {sys.version.split()[0]}")
    print(f"{'config':7s} {'phys/ctl':>8s} {'torque':>9s} {'impedance':>9s} {'ratio':>6s}")
    for p in presets:
        torque, imp = measure_impedance(p, rounds, steps)
        n = load_preset(p).steps_per_control
        print(f"{p:7s} {n:8d} {torque:9.2f} {imp:9.2f} {imp / torque:6.2f}", flush=True)
    return 0


#: --vs-mujoco: the presets compared by default, and the like-with-like tolerances. The
#: heights compared are each base's height above its feet's contact depth (base z + sink):
#: the two contact laws sink differently (hard: 0, Cm and MuJoCo: a few mm), the legs'
#: posture under the same PD hold must agree; 2 mm: a link length or mass off by a few %
#: (measured residual ≤ 0.6 mm, Cm's compliant feet)
VS_MUJOCO_PRESETS = ("HmJ", "HmS", "Cm")
HEIGHT_TOLERANCE = 2e-3     # base heights above the feet, against MuJoCo's stick-matched [m]
CREEP_TOLERANCE = 1e-3      # how far MuJoCo noslip's loaded feet move over the rounds [m]
FORCE_TOLERANCE = 0.02      # |Σ F_N − m g| / (m g) of each simulator, standing still
#: MuJoCo's noslip solver iterations for the stick-matched model (its regularised friction
#: lets standing feet creep; the noslip pass removes that slip, as our Coulomb law sticks)
NOSLIP_ITERATIONS = 10
SETTLE_STEPS = 400          # physics steps before the rounds (the start's transient)
#: physics steps under zero torques before the fallen round: the collapse comes to rest
FALL_STEPS = 1200


#: the radius MuJoCo gives a contact point of radius 0 (a box corner) [m]: a sphere needs one
CORNER_RADIUS = 1e-3


#: the least principal moment of inertia MuJoCo is given [kg m²]: its compiler refuses a
#: singular inertia (Go1's 1 mg placeholder base link has every entry 1e-6)
MIN_INERTIA = 1e-9
INERTIA_KEYS = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")


def _positive_inertia(inertia) -> None:
    """An <inertia> element whose matrix is not positive definite, made so (eigenvalues at
    least MIN_INERTIA): a negligible change to a placeholder link."""
    xx, xy, xz, yy, yz, zz = (float(inertia.get(k, 0.0)) for k in INERTIA_KEYS)
    m = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    w, v = np.linalg.eigh(m)
    if w.min() >= MIN_INERTIA:
        return
    m = (v * np.maximum(w, MIN_INERTIA)) @ v.T
    for k, x in zip(INERTIA_KEYS, (m[0, 0], m[0, 1], m[0, 2], m[1, 1], m[1, 2], m[2, 2]),
                    strict=True):
        inertia.set(k, repr(float(x)))


def bare_urdf(urdf_xml: str) -> str:
    """The URDF without its visual and collision elements (MuJoCo would load their meshes,
    and collide with all of them): the kinematic tree and the inertials (singular ones made
    positive definite)."""
    root = ET.fromstring(urdf_xml)
    for link in root.iter("link"):
        for tag in ("visual", "collision"):
            for e in link.findall(tag):
                link.remove(e)
        inertia = link.find("inertial/inertia")
        if inertia is not None:
            _positive_inertia(inertia)
    return ET.tostring(root, encoding="unicode")


def mujoco_model(desc, dt: float, mu: float, noslip_iterations: int = 0):
    """MuJoCo's model of a robot (a RobotDescription) from the same URDF: the tree compiled
    by MuJoCo (fixed joints fused, masses and inertias from the URDF's inertials only), a
    free joint on the root body, and as collision geometry our contact points only (a
    sphere per point, in the body of its joint; box corners CORNER_RADIUS), colliding with
    a ground plane at z = 0; Δt, Newton solver, elliptic friction cones, μ on every geom,
    MuJoCo's default soft contact (solref, solimp) and `noslip_iterations`; no joint
    limits, as ours (the collapse of the fallen round then ends where ours does).
    Returns (mujoco, model); mujoco is None if not installed."""
    try:
        import mujoco
    except ImportError:
        return None, None
    spec = mujoco.MjSpec.from_string(bare_urdf(desc.urdf_xml))
    # the URDF's inertials only: by default MuJoCo gives a link without one (the feet) the
    # mass of its collision geoms at 1000 kg/m³
    spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_FALSE
    spec.compiler.balanceinertia = True      # the triangle inequality, as pinocchio does not
    root = spec.worldbody.first_body()
    root.add_freejoint()
    names = desc.model.names
    for c in desc.contacts:
        body = root if desc.model.joints[c.joint].nq == 7 else spec.joint(names[c.joint]).parent
        g = body.add_geom()
        g.type = mujoco.mjtGeom.mjGEOM_SPHERE
        g.size = [max(c.radius, CORNER_RADIUS), 0.0, 0.0]
        g.pos = np.asarray(c.local, dtype=float)
        g.contype, g.conaffinity = 1, 0
    ground = spec.worldbody.add_geom()
    ground.type = mujoco.mjtGeom.mjGEOM_PLANE
    ground.size = [0.0, 0.0, 1.0]
    ground.contype, ground.conaffinity = 0, 1
    for g in spec.geoms:
        g.friction = [mu, 0.005, 0.0001]
    spec.option.timestep = dt
    spec.option.solver = mujoco.mjtSolver.mjSOL_NEWTON
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.noslip_iterations = noslip_iterations
    for j in spec.joints:          # the URDF's joint ranges are not simulated by ours (nor by
        j.limited = mujoco.mjtLimited.mjLIMITED_FALSE    # the paper): a fallen robot's legs
    return mujoco, spec.compile()


class MujocoStanding:
    """MuJoCo's robot under the PD hold from the simulator's standing state (joints mapped
    by name, quaternion reordered to MuJoCo's (w, x, y, z))."""

    def __init__(self, mujoco, model, sim):
        self.mj = mujoco
        self.model = model
        self.data = mujoco.MjData(model)
        names = sim.joint_names
        self.qadr = np.array([model.joint(n).qposadr[0] for n in names])
        self.vadr = np.array([model.joint(n).dofadr[0] for n in names])
        b = sim.base_state()
        x, y, z, w = b["orientation_xyzw"]
        self.data.qpos[0:3] = b["position"]
        self.data.qpos[3:7] = (w, x, y, z)
        self.data.qpos[self.qadr] = sim.joint_positions()
        mujoco.mj_forward(model, self.data)
        self.hold = PostureHold.for_robot(sim.description, sim.joint_positions())
        self.limit = np.asarray(sim.description.effort_limit, dtype=float).reshape(-1)
        self.weight = float(np.sum(model.body_mass)) * float(-model.opt.gravity[2])
        self.dt = float(model.opt.timestep)
        self.spheres = np.flatnonzero(model.geom_type == mujoco.mjtGeom.mjGEOM_SPHERE)
        self.limp = False           # zero torques (the fallen round) instead of the PD law

    def run(self, steps: int) -> float:
        """`steps` physics steps with the PD law (effort-limited) each step, or none when
        limp; wall time [s]."""
        mj, m, d, hold = self.mj, self.model, self.data, self.hold
        qadr, vadr, limit = self.qadr, self.vadr, self.limit
        if self.limp:
            d.qfrc_applied[:] = 0.0
            t0 = time.perf_counter()
            for _ in range(steps):
                mj.mj_step(m, d)
            return time.perf_counter() - t0
        t0 = time.perf_counter()
        for _ in range(steps):
            tau = hold(d.qpos[qadr], d.qvel[vadr])
            d.qfrc_applied[vadr] = np.clip(tau, -limit, limit)
            mj.mj_step(m, d)
        return time.perf_counter() - t0

    def physics_steps(self, steps: int) -> int:
        return steps

    def normal_force(self) -> float:
        """Σ F_N over the contacts (mj_contactForce, contact frame: normal first) [N]."""
        f = np.zeros(6)
        total = 0.0
        for i in range(self.data.ncon):
            self.mj.mj_contactForce(self.model, self.data, i, f)
            total += f[0]
        return total

    def height(self) -> float:
        return float(self.data.qpos[2])

    def contact_points(self):
        """The contact spheres' centres (world; over a flat ground their contact points'
        horizontal position) [m]."""
        return self.data.geom_xpos[self.spheres].copy()

    def loaded(self):
        """Per contact sphere: touching the ground."""
        d = self.data
        touching = {int(g) for i in range(d.ncon) for g in d.contact.geom[i]}
        return np.isin(self.spheres, list(touching))

    def sink(self) -> float:
        """Mean penetration of the contacts [m]."""
        d = self.data
        return -float(np.mean(d.contact.dist[:d.ncon])) if d.ncon else 0.0


class SimulatorStanding:
    """A preset's Simulator (for `robot`, default the preset's) under the PD hold from its
    standing state."""

    def __init__(self, preset: str, robot: str | None = None):
        self.sim = Simulator.from_preset(preset, robot=robot)
        self.hold = PostureHold.for_robot(self.sim.description, self.sim.joint_positions())
        self.per_control = self.sim.config.steps_per_control
        self.dt = self.sim.dt
        d = self.sim.description
        self.weight = float(sum(i.mass for i in d.model.inertias)) * \
            float(np.linalg.norm(d.model.gravity.linear))
        self.limp = False           # zero torques (the fallen round) instead of the PD law

    def run(self, steps: int) -> float:
        """At least `steps` physics steps (whole control periods, the PD law once per control
        period, or zero torques when limp); wall time [s]."""
        sim, hold = self.sim, self.hold
        n = -(-steps // self.per_control)
        zero = np.zeros(len(sim.joint_names))
        t0 = time.perf_counter()
        for _ in range(n):
            sim.step(zero if self.limp else hold.torque(sim))
        return time.perf_counter() - t0

    def physics_steps(self, steps: int) -> int:
        return -(-steps // self.per_control) * self.per_control

    def normal_force(self) -> float:
        """Σ F_N over the contacts in the last control period [N] (world z: the ground is
        horizontal)."""
        return float(sum(c.force[2] for c in self.sim.contacts))

    def height(self) -> float:
        return float(self.sim.base_state()["position"][2])

    def contact_points(self):
        return self.sim.contact_points()

    def loaded(self):
        return self.sim.contact_states() != 0

    def sink(self) -> float:
        """Mean penetration of the loaded contacts [m]."""
        loaded = self.loaded()
        return -float(np.mean(self.sim.gaps()[loaded])) if loaded.any() else 0.0


def creep(runner, start) -> float:
    """The farthest a loaded contact point moved horizontally from `start` [m]."""
    moved = np.linalg.norm((runner.contact_points() - start)[:, :2], axis=1)[runner.loaded()]
    return float(moved.max()) if moved.size else 0.0


@dataclass
class VsMujocoRow:
    """One simulator of the side-by-side run."""

    name: str                  # "MuJoCo", "MuJoCo noslip" or a preset
    dt: float                  # physics step [s]
    rates: list                # steps/s per round
    normal_force_ratio: float  # Σ F_N / mg at the end
    height: float              # base height at the end [m]
    sink: float                # mean penetration of the loaded contacts at the end [m]
    creep: float               # farthest a loaded contact moved over the rounds [m]
    #: the fallen round: steps/s per round lying at rest after a collapse, base height [m]
    fallen_rates: list = field(default_factory=list)
    fallen_height: float = float("nan")

    @property
    def fallen_median(self) -> float:
        return float(np.median(self.fallen_rates)) if self.fallen_rates else float("nan")

    @property
    def above_feet(self) -> float:
        """The base's height above its feet's contact depth [m]: the legs' posture."""
        return self.height + self.sink

    @property
    def median(self) -> float:
        return float(np.median(self.rates))


@dataclass
class VsMujoco:
    """The side-by-side run (`measure_vs_mujoco`)."""

    robot: str
    mujoco_version: str
    timestep: float
    mu: float
    rounds: int
    steps: int
    rows: list                 # VsMujocoRow: MuJoCo, MuJoCo noslip, the presets
    problems: list             # what is not like with like (empty: the same thing simulated)

    def ratio(self, row: VsMujocoRow) -> float:
        """steps/s against MuJoCo with its default contact settings."""
        return row.median / self.rows[0].median

    @property
    def reference(self) -> VsMujocoRow:
        """MuJoCo with its feet sticking (noslip): the height and creep reference."""
        return self.rows[1]

    def header(self) -> str:
        return (f"{self.robot} standing under the joint PD hold: MuJoCo {self.mujoco_version} "
                f"(URDF compiled by MuJoCo, free base, our contact points as spheres, Δt = "
                f"{self.timestep * 1e3:g} ms, Newton, elliptic cones, μ = {self.mu:g}; "
                f"default contact, and with {NOSLIP_ITERATIONS} noslip iterations) beside "
                f"Simulator; {SETTLE_STEPS} steps to settle, then {self.rounds} interleaved "
                f"rounds of {self.steps} physics steps; Python {sys.version.split()[0]}")

    def like_with_like(self) -> str:
        return (f"yes (total normal force = weight, MuJoCo noslip's feet stick (creep < "
                f"{CREEP_TOLERANCE * 1e3:g} mm), base heights above the feet within "
                f"{HEIGHT_TOLERANCE * 1e3:g} mm of MuJoCo noslip's)"
                if not self.problems else "NO (see above)")


def measure_vs_mujoco(presets, rounds: int, steps: int, robot: str | None = None
                      ) -> VsMujoco | None:
    """The side-by-side comparison (module docstring) for `robot` (default: the presets');
    None if mujoco is missing."""
    runners = {p: SimulatorStanding(p, robot) for p in presets}
    first = next(iter(runners.values())).sim
    desc, mu = first.description, first.config.ground.mu
    mujoco, model = mujoco_model(desc, 2.5e-3, mu)
    if mujoco is None:
        return None
    _, stick = mujoco_model(desc, 2.5e-3, mu, NOSLIP_ITERATIONS)
    runners = {"MuJoCo": MujocoStanding(mujoco, model, first),
               "MuJoCo noslip": MujocoStanding(mujoco, stick, first), **runners}
    start = {}
    for n, r in runners.items():   # settle (and warm up: first calls, caches)
        r.run(SETTLE_STEPS)
        start[n] = r.contact_points()
    rates = interleaved_rates(runners, rounds, steps)
    rows = [VsMujocoRow(n, r.dt, rates[n], r.normal_force() / r.weight, r.height(), r.sink(),
                        creep(r, start[n])) for n, r in runners.items()]
    for r in runners.values():      # the fallen round: limp, collapsed, at rest
        r.limp = True
        r.run(FALL_STEPS)
    fallen = interleaved_rates(runners, rounds, steps)
    for row, r in zip(rows, runners.values(), strict=True):
        row.fallen_rates, row.fallen_height = fallen[row.name], r.height()
    return VsMujoco(desc.name, mujoco.__version__, float(model.opt.timestep),
                    float(model.geom_friction[0, 0]), rounds, steps, rows, _problems(rows))


def interleaved_rates(runners, rounds: int, steps: int) -> dict:
    """{name: steps/s per round} of `rounds` rounds of `steps` physics steps, the runners
    in turn in each round."""
    rates = {n: [] for n in runners}
    for _ in range(rounds):
        for n, r in runners.items():
            wall = r.run(steps)
            rates[n].append(r.physics_steps(steps) / wall)
    return rates


def _problems(rows) -> list:
    """What is not like with like: a total normal force off the weight; MuJoCo noslip's
    feet creeping (the reference must stick as our hard contacts do; Cm's compliant feet
    may creep); a preset's base height above its feet off MuJoCo noslip's."""
    problems, ref = [], rows[1]
    for row in rows:
        if abs(row.normal_force_ratio - 1.0) > FORCE_TOLERANCE:
            problems.append(f"{row.name}: total normal force {row.normal_force_ratio:.4f} mg, "
                            f"not the weight (±{FORCE_TOLERANCE:g})")
    if ref.creep > CREEP_TOLERANCE:
        problems.append(f"{ref.name}: a loaded foot moved {ref.creep * 1e3:.2f} mm while "
                        f"standing (more than {CREEP_TOLERANCE * 1e3:g} mm)")
    for row in rows[2:]:
        if abs(row.above_feet - ref.above_feet) > HEIGHT_TOLERANCE:
            problems.append(f"{row.name}: base height above the feet "
                            f"{row.above_feet * 1e3:.2f} mm differs from {ref.name}'s "
                            f"{ref.above_feet * 1e3:.2f} mm by more than "
                            f"{HEIGHT_TOLERANCE * 1e3:g} mm")
    return problems


def print_vs_mujoco(result: VsMujoco) -> None:
    """The rows: steps/s, the ratio to MuJoCo (default contact), Σ F_N / mg, base z, the
    feet's sink, base z above the feet, the feet's creep over the rounds."""
    print(result.header())
    print(f"{'':13s} {'Δt [ms]':>7s} {'steps/s (median)':>17s} {'min':>8s} {'max':>8s} "
          f"{'ratio':>6s} {'Σ F_N / mg':>10s} {'base z [mm]':>11s} {'sink':>5s} "
          f"{'z above feet':>12s} {'creep':>6s}")
    for row in result.rows:
        print(f"{row.name:13s} {row.dt * 1e3:7.3g} {row.median:17.0f} {min(row.rates):8.0f} "
              f"{max(row.rates):8.0f} {result.ratio(row):6.2f} {row.normal_force_ratio:10.4f} "
              f"{row.height * 1e3:11.2f} {row.sink * 1e3:5.2f} {row.above_feet * 1e3:12.2f} "
              f"{row.creep * 1e3:6.2f}")
    for problem in result.problems:
        print("  " + problem)
    print("like with like: " + result.like_with_like())
    print(f"fallen: zero torques for {FALL_STEPS} steps (the robot collapses onto knees and "
          f"trunk and comes to rest), then {result.rounds} interleaved rounds of "
          f"{result.steps} physics steps")
    print(f"{'':13s} {'steps/s (median)':>17s} {'ratio':>6s} {'vs standing':>11s} "
          f"{'base z [mm]':>11s}")
    for row in result.rows:
        print(f"{row.name:13s} {row.fallen_median:17.0f} "
              f"{row.fallen_median / result.rows[0].fallen_median:6.2f} "
              f"{row.median / row.fallen_median:11.2f} {row.fallen_height * 1e3:11.1f}")


def robots_table(results) -> list:
    """The per-robot table (doc/performance.md): steps/s of MuJoCo (default contact, then
    noslip) and of each preset with its ratios to both, our base height above the feet minus
    MuJoCo noslip's, the feet's creep, the check."""
    presets = [row.name for row in results[0].rows[2:]]
    lines = ["| robot | MuJoCo steps/s | MuJoCo noslip steps/s (ratio) | " +
             " | ".join(f"{p} steps/s (ratio to MuJoCo / noslip)" for p in presets) +
             " | base z above feet, ours − noslip [mm] | feet creep [mm] (MuJoCo, noslip, "
             + ", ".join(presets) + ") | like with like |",
             "|---" * (len(presets) + 6) + "|"]
    for r in results:
        mj, ref = r.rows[0], r.reference
        cells = [f"{row.median:,.0f} ({r.ratio(row):.2f} / {row.median / ref.median:.2f})"
                 for row in r.rows[2:]]
        dz = ", ".join(f"{(row.above_feet - ref.above_feet) * 1e3:+.2f}" for row in r.rows[2:])
        creeps = ", ".join(f"{row.creep * 1e3:.2f}" for row in r.rows)
        lines.append(f"| {r.robot} | {mj.median:,.0f} | {ref.median:,.0f} ({r.ratio(ref):.2f}) | "
                     + " | ".join(cells) + f" | {dz} | {creeps} | "
                     f"{'yes' if not r.problems else 'NO'} |")
    return lines


def vs_mujoco(presets, rounds: int, steps: int, robots=(None,)) -> int:
    """Prints the side-by-side comparison per robot (and the per-robot table for several);
    exit status 0, 1 if the two do not simulate the same thing, 2 if mujoco is missing."""
    results = []
    for robot in robots:
        result = measure_vs_mujoco(presets, rounds, steps, robot)
        if result is None:
            print("starleth-bench --vs-mujoco: mujoco is not installed (it is an optional "
                  "benchmark dependency: pip install -r requirements-bench.txt, or make bench)")
            return 2
        print_vs_mujoco(result)
        results.append(result)
    if len(results) > 1:
        print()
        for line in robots_table(results):
            print(line)
    return 0 if not any(r.problems for r in results) else 1


def _robots(value) -> list:
    """The robots of --robot (a name or path, or `all`: the library); ConfigError naming a
    bad one."""
    if value is None:
        return [None]
    names = list(available_robots()) if value == "all" else [value]
    for n in names:
        robot_description(n)       # checked: one line naming the file and field
    return names


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="starleth-bench", description=__doc__.split("\n")[0])
    ap.add_argument("presets", nargs="*", default=None,
                    help=f"configurations (default: all of Table 1; with --vs-mujoco "
                         f"{' '.join(VS_MUJOCO_PRESETS)})")
    ap.add_argument("--robot", default=None, metavar="NAME|all",
                    help="the robot (a library name, a spec or URDF path, or `all`: every "
                         "robot of the library; default: the presets', StarlETH)")
    ap.add_argument("--seconds", type=float, default=5.0, help="simulated seconds per run")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--vs-mujoco", action="store_true",
                    help="side by side with MuJoCo on the same robot (needs mujoco)")
    ap.add_argument("--impedance", action="store_true",
                    help="the impedance step beside the torque step (default HmJ Cm)")
    ap.add_argument("--terrain", action="store_true",
                    help="the cost of the terrain's contact query (50 boxes, a 256x256 "
                         "heightfield) against the flat ground, interleaved (first preset, "
                         "default HmJ)")
    ap.add_argument("--states", action="store_true",
                    help="the step's cost standing, trotting and fallen (lying on the ground "
                         "after a collapse), interleaved, per preset")
    ap.add_argument("--rounds", type=int, default=None,
                    help="--vs-mujoco, --impedance, --terrain, --states: interleaved rounds "
                         "(default 5, 5, 21, 5)")
    ap.add_argument("--steps", type=int, default=None,
                    help="--vs-mujoco: physics steps per round (default 2000); --impedance: "
                         "control steps (2000); --states: control steps (400)")
    return ap


def main(argv=None):
    ap = _parser()
    args = ap.parse_args(argv)
    terrain_preset = args.presets[0] if args.presets else "HmJ"
    if not args.presets:
        args.presets = list(VS_MUJOCO_PRESETS if args.vs_mujoco else IMPEDANCE_PRESETS
                            if args.impedance else DEFAULT_PRESETS)
    try:
        configs = {p: load_preset(p) for p in args.presets}
        robots = _robots(args.robot)
    except ConfigError as e:
        print(f"starleth-bench: error: {e}", file=sys.stderr)
        return 2
    if args.terrain:
        if args.rounds is not None and args.rounds < 1:
            ap.error("--rounds must be positive")
        return print_terrain_rounds(terrain_preset, args.rounds or 21)
    if args.states:
        rounds = 5 if args.rounds is None else args.rounds
        steps = 400 if args.steps is None else args.steps
        if rounds < 1 or steps < 1:
            ap.error("--rounds and --steps must be positive")
        for robot in robots:
            print_states(args.presets, rounds, steps, robot)
        return 0
    args.steps = 2000 if args.steps is None else args.steps
    if args.vs_mujoco:
        args.rounds = 5 if args.rounds is None else args.rounds
        if args.rounds < 1 or args.steps < 1:
            ap.error("--rounds and --steps must be positive")
        return vs_mujoco(args.presets, args.rounds, args.steps, robots)
    if args.impedance:
        args.rounds = 5 if args.rounds is None else args.rounds
        if args.rounds < 1 or args.steps < 1:
            ap.error("--rounds and --steps must be positive")
        return impedance(args.presets, args.rounds, args.steps)

    for robot in robots:
        table(args, configs, robot)
    return 0


def table(args, configs, robot):
    """The speed table (beside the paper's) and the per-phase breakdown of one robot."""
    name = robot or "StarlETH"
    print(f"{name} standing under a joint PD hold, {args.seconds:g} s simulated x "
          f"{args.repeats} runs per configuration; Python {sys.version.split()[0]}")
    print(f"{'config':7s} {'steps/s':>16s} {'paper':>7s} {'ratio':>6s} {'RTF':>7s} "
          f"{'paper':>6s} {'iter/step':>9s}")
    for p in args.presets:
        cfg = configs[p]
        rates, rtfs, it = measure(p, args.seconds, args.repeats, robot)
        paper = cfg.paper.get("steps_per_second") if robot in (None, "starleth") else None
        prtf = cfg.paper.get("realtime_factor") if paper else None
        ratio = rates.mean() / paper if paper else float("nan")
        print(f"{p:7s} {rates.mean():9.0f} ± {rates.std():4.0f} {paper or '-':>7} "
              f"{ratio:6.2f} {rtfs.mean():7.1f} {prtf or '-':>6} {it:9.2f}", flush=True)
    print(f"\nPer-step time by phase (Fig. 7), µs, profiled run ({name}):")
    print(f"{'config':7s} " + " ".join(f"{k:>9s}" for k in PHASES) + f" {'total':>9s}")
    for p in args.presets:
        b = breakdown(p, min(args.seconds, 2.0), robot)
        print(f"{p:7s} " + " ".join(f"{b[k]:9.2f}" for k in PHASES) +
              f" {sum(b.values()):9.2f}")
    print()


if __name__ == "__main__":
    sys.exit(main())
