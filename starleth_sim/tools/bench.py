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

``--vs-mujoco``: the same robot (``urdf/starleth.urdf`` compiled by MuJoCo, free base joint,
ground plane, Δt = 2.5 ms, Newton solver, elliptic cones, μ as in the preset) standing under
the same joint PD hold from the same standing state, beside `Simulator` on the given presets
(default HmJ HmS Cm), in interleaved rounds of physics steps in one process: steps/s per
preset (median of the rounds) and the ratio to MuJoCo, plus a check that both simulate the
same thing (total normal force ≈ weight, base heights within a few mm). mujoco is an
optional benchmark dependency (``requirements-bench.txt``, installed by ``make bench``).
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass

import numpy as np

from ..physics.config import PRESETS as DEFAULT_PRESETS   # the paper's Table 1
from ..physics.config import ConfigError, load_preset
from ..physics.impedance import ImpedanceCommand
from ..physics.posture import PostureHold
from ..physics.simulator import Simulator
from ..physics.stepper import PHASES, StepperStats
from ..robots import robot_urdf
from .bench_terrain import print_terrain_rounds
from .bench_timing import timed_steps


def measure(preset: str, seconds: float, repeats: int = 3):
    """(steps/s samples, rtf samples, mean prox iterations per step) for `seconds` of
    simulated standing, repeated."""
    rates, rtfs, iters = [], [], []
    for _ in range(repeats):
        sim = Simulator.from_preset(preset)
        hold = PostureHold(sim.joint_positions())
        n = int(round(seconds / sim.control_period))
        sim.step(hold.torque(sim))  # warm-up (first calls, caches)
        wall, it = timed_steps(sim, n, hold)
        steps = n * sim.config.steps_per_control
        rates.append(steps / wall)
        rtfs.append(n * sim.control_period / wall)
        iters.append(it / steps)
    return np.array(rates), np.array(rtfs), float(np.mean(iters))


def breakdown(preset: str, seconds: float):
    """Mean time per physics step and phase [µs] (profiled run, includes timer overhead)."""
    sim = Simulator.from_preset(preset, profile=True)
    hold = PostureHold(sim.joint_positions())
    for _ in range(20):  # warm-up: first calls of the profiled path load compiled code
        sim.step(hold.torque(sim))
    sim.reset()
    sim.stepper.stats = StepperStats()
    n = int(round(seconds / sim.control_period))
    for _ in range(n):
        sim.step(hold.torque(sim))
    steps = sim.stepper.stats.steps
    return {k: 1e6 * v / steps for k, v in zip(PHASES, sim.stepper.stats.timings)}


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


#: --vs-mujoco: the presets compared by default, and the like-with-like tolerances
VS_MUJOCO_PRESETS = ("HmJ", "HmS", "Cm")
HEIGHT_TOLERANCE = 5e-3     # base heights of the two simulators after the rounds [m]
FORCE_TOLERANCE = 0.02      # |Σ F_N − m g| / (m g) of each simulator, standing still


def mujoco_model(robot: str, dt: float, mu: float):
    """MuJoCo's model of the robot's URDF (a preset's `robot`: robots.robot_urdf): the URDF
    compiled by MuJoCo (fixed joints fused, masses and inertias from the URDF's inertials
    only), a free joint on the base, a ground plane at z = 0, Δt, Newton solver, elliptic
    friction cones, μ on every geom; the robot's geoms collide with the ground only (as the
    simulator's contact points). Returns (mujoco, model); mujoco is None if not installed."""
    try:
        import mujoco
    except ImportError:
        return None, None
    spec = mujoco.MjSpec.from_file(robot_urdf(robot))
    # the URDF's inertials only: by default MuJoCo gives a link without one (the feet) the
    # mass of its collision geoms at 1000 kg/m³ (+65 g per foot sphere)
    spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_FALSE
    spec.body("base").add_freejoint()
    ground = spec.worldbody.add_geom()
    ground.type = mujoco.mjtGeom.mjGEOM_PLANE
    ground.size = [0.0, 0.0, 1.0]
    for g in spec.geoms:
        g.friction = [mu, 0.005, 0.0001]
        g.contype, g.conaffinity = (0, 1) if g is ground or g.type == \
            mujoco.mjtGeom.mjGEOM_PLANE else (1, 0)
    spec.option.timestep = dt
    spec.option.solver = mujoco.mjtSolver.mjSOL_NEWTON
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
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
        self.hold = PostureHold(sim.joint_positions())
        self.limit = np.asarray(sim.description.effort_limit, dtype=float).reshape(-1)
        self.weight = float(np.sum(model.body_mass)) * float(-model.opt.gravity[2])

    def run(self, steps: int) -> float:
        """`steps` physics steps with the PD law (effort-limited) each step; wall time [s]."""
        mj, m, d, hold = self.mj, self.model, self.data, self.hold
        qadr, vadr, limit = self.qadr, self.vadr, self.limit
        t0 = time.perf_counter()
        for _ in range(steps):
            tau = hold(d.qpos[qadr], d.qvel[vadr])
            d.qfrc_applied[vadr] = np.clip(tau, -limit, limit)
            mj.mj_step(m, d)
        return time.perf_counter() - t0

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


class SimulatorStanding:
    """A preset's Simulator under the PD hold from its standing state."""

    def __init__(self, preset: str):
        self.sim = Simulator.from_preset(preset)
        self.hold = PostureHold(self.sim.joint_positions())
        self.per_control = self.sim.config.steps_per_control
        d = self.sim.description
        self.weight = float(sum(i.mass for i in d.model.inertias)) * \
            float(np.linalg.norm(d.model.gravity.linear))

    def run(self, steps: int) -> float:
        """At least `steps` physics steps (whole control periods, the PD law once per control
        period); wall time [s]."""
        sim, hold = self.sim, self.hold
        n = -(-steps // self.per_control)
        t0 = time.perf_counter()
        for _ in range(n):
            sim.step(hold.torque(sim))
        return time.perf_counter() - t0

    def physics_steps(self, steps: int) -> int:
        return -(-steps // self.per_control) * self.per_control

    def normal_force(self) -> float:
        """Σ F_N over the contacts in the last control period [N] (world z: the ground is
        horizontal)."""
        return float(sum(c.force[2] for c in self.sim.contacts))

    def height(self) -> float:
        return float(self.sim.base_state()["position"][2])


@dataclass
class VsMujocoRow:
    """One simulator of the side-by-side run."""

    name: str                  # "MuJoCo" or a preset
    dt: float                  # physics step [s]
    rates: list                # steps/s per round
    normal_force_ratio: float  # Σ F_N / mg at the end
    height: float              # base height at the end [m]

    @property
    def median(self) -> float:
        return float(np.median(self.rates))


@dataclass
class VsMujoco:
    """The side-by-side run (`measure_vs_mujoco`)."""

    mujoco_version: str
    timestep: float
    mu: float
    rounds: int
    steps: int
    rows: list                 # VsMujocoRow, MuJoCo first
    problems: list             # what is not like with like (empty: the same thing simulated)

    def ratio(self, row: VsMujocoRow) -> float:
        return row.median / self.rows[0].median

    def header(self) -> str:
        return (f"StarlETH standing under the joint PD hold: MuJoCo {self.mujoco_version} "
                f"(URDF compiled by MuJoCo, free base, Δt = {self.timestep * 1e3:g} ms, Newton, "
                f"elliptic cones, μ = {self.mu:g}) beside Simulator; {self.rounds} interleaved "
                f"rounds of {self.steps} physics steps; Python {sys.version.split()[0]}")

    def like_with_like(self) -> str:
        return ("yes (total normal force = weight, base heights within "
                f"{HEIGHT_TOLERANCE * 1e3:g} mm)" if not self.problems else "NO (see above)")


def measure_vs_mujoco(presets, rounds: int, steps: int) -> VsMujoco | None:
    """The side-by-side comparison (module docstring); None if mujoco is missing."""
    runners = {p: SimulatorStanding(p) for p in presets}
    first = next(iter(runners.values())).sim
    mujoco, model = mujoco_model(first.config.robot, 2.5e-3, first.config.ground.mu)
    if mujoco is None:
        return None
    mj = MujocoStanding(mujoco, model, first)
    runners = {"MuJoCo": mj, **runners}
    for r in runners.values():   # warm-up (first calls, caches)
        r.run(50)
    rates = {n: [] for n in runners}
    for _ in range(rounds):
        for n, r in runners.items():
            wall = r.run(steps)
            done = steps if r is mj else r.physics_steps(steps)
            rates[n].append(done / wall)
    rows, problems = [], []
    for n, r in runners.items():
        row = VsMujocoRow(n, model.opt.timestep if r is mj else r.sim.dt, rates[n],
                          r.normal_force() / r.weight, r.height())
        rows.append(row)
        if abs(row.normal_force_ratio - 1.0) > FORCE_TOLERANCE:
            problems.append(f"{n}: total normal force {row.normal_force_ratio:.4f} mg, not the "
                            f"weight (±{FORCE_TOLERANCE:g})")
        if r is not mj and abs(row.height - mj.height()) > HEIGHT_TOLERANCE:
            problems.append(f"{n}: base height {row.height * 1e3:.2f} mm differs from MuJoCo's "
                            f"by more than {HEIGHT_TOLERANCE * 1e3:g} mm")
    return VsMujoco(mujoco.__version__, float(model.opt.timestep),
                    float(model.geom_friction[0, 0]), rounds, steps, rows, problems)


def vs_mujoco(presets, rounds: int, steps: int) -> int:
    """Prints the side-by-side comparison; exit status 0, 1 if the two do not simulate the
    same thing, 2 if mujoco is missing."""
    result = measure_vs_mujoco(presets, rounds, steps)
    if result is None:
        print("starleth-bench --vs-mujoco: mujoco is not installed (it is an optional "
              "benchmark dependency: pip install -r requirements-bench.txt, or make bench)")
        return 2
    print(result.header())
    print(f"{'':8s} {'Δt [ms]':>7s} {'steps/s (median)':>17s} {'min':>8s} {'max':>8s} "
          f"{'ratio':>6s} {'Σ F_N / mg':>10s} {'base z [mm]':>11s}")
    for row in result.rows:
        print(f"{row.name:8s} {row.dt * 1e3:7.3g} {row.median:17.0f} {min(row.rates):8.0f} "
              f"{max(row.rates):8.0f} {result.ratio(row):6.2f} {row.normal_force_ratio:10.4f} "
              f"{row.height * 1e3:11.2f}")
    for problem in result.problems:
        print("  " + problem)
    print("like with like: " + result.like_with_like())
    return 0 if not result.problems else 1


def main(argv=None):
    ap = argparse.ArgumentParser(prog="starleth-bench", description=__doc__.split("\n")[0])
    ap.add_argument("presets", nargs="*", default=None,
                    help=f"configurations (default: all of Table 1; with --vs-mujoco "
                         f"{' '.join(VS_MUJOCO_PRESETS)})")
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
    ap.add_argument("--rounds", type=int, default=None,
                    help="--vs-mujoco, --impedance, --terrain: interleaved rounds (default 5, "
                         "5, 21)")
    ap.add_argument("--steps", type=int, default=2000,
                    help="--vs-mujoco: physics steps per round; --impedance: control steps")
    args = ap.parse_args(argv)
    terrain_preset = args.presets[0] if args.presets else "HmJ"
    if not args.presets:
        args.presets = list(VS_MUJOCO_PRESETS if args.vs_mujoco else IMPEDANCE_PRESETS
                            if args.impedance else DEFAULT_PRESETS)
    try:
        configs = {p: load_preset(p) for p in args.presets}
    except ConfigError as e:
        ap.error(str(e))
    if args.terrain:
        if args.rounds is not None and args.rounds < 1:
            ap.error("--rounds must be positive")
        return print_terrain_rounds(terrain_preset, args.rounds or 21)
    if args.vs_mujoco:
        args.rounds = 5 if args.rounds is None else args.rounds
        if args.rounds < 1 or args.steps < 1:
            ap.error("--rounds and --steps must be positive")
        return vs_mujoco(args.presets, args.rounds, args.steps)
    if args.impedance:
        args.rounds = 5 if args.rounds is None else args.rounds
        if args.rounds < 1 or args.steps < 1:
            ap.error("--rounds and --steps must be positive")
        return impedance(args.presets, args.rounds, args.steps)

    print(f"StarlETH standing under a joint PD hold, {args.seconds:g} s simulated x "
          f"{args.repeats} runs per configuration; Python {sys.version.split()[0]}")
    print(f"{'config':7s} {'steps/s':>16s} {'paper':>7s} {'ratio':>6s} {'RTF':>7s} "
          f"{'paper':>6s} {'iter/step':>9s}")
    for p in args.presets:
        cfg = configs[p]
        rates, rtfs, it = measure(p, args.seconds, args.repeats)
        paper = cfg.paper.get("steps_per_second")
        prtf = cfg.paper.get("realtime_factor")
        ratio = rates.mean() / paper if paper else float("nan")
        print(f"{p:7s} {rates.mean():9.0f} ± {rates.std():4.0f} {paper or '-':>7} "
              f"{ratio:6.2f} {rtfs.mean():7.1f} {prtf or '-':>6} {it:9.2f}", flush=True)
    print("\nPer-step time by phase (Fig. 7), µs, profiled run:")
    print(f"{'config':7s} " + " ".join(f"{k:>9s}" for k in PHASES) + f" {'total':>9s}")
    for p in args.presets:
        b = breakdown(p, min(args.seconds, 2.0))
        print(f"{p:7s} " + " ".join(f"{b[k]:9.2f}" for k in PHASES) +
              f" {sum(b.values()):9.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
