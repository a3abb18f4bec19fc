"""``starleth-replay``: re-simulate a recorded run open loop from its bag.

    starleth-replay runs/demo.mcap                       # bit-identical to the recording?
    starleth-replay runs/demo.mcap --preset HMJD --preset Cm --out replay/

A bag written by ``sim_node record:=...`` holds everything a headless re-run needs (the
``starleth_sim`` metadata record): the physics configuration as resolved (YAML), the initial
state (q, u in the simulator's coordinates, and in minimal coordinates), the control period,
the package version, and the topic names. The torque applied over step k -> k+1 is the
effort of the ``/joint_states`` message stamped t_(k+1) (saturated at the effort limit and
derated at the velocity limit: what the motors applied), and every external wrench the node
took is recorded on its input topic with the log time t_k of the state after which it was
applied: it acts from step k -> k+1.

The replay makes the same calls on a ``Simulator`` as sim_node did (``SimService``: warm-up,
reset to the initial state, ``submit_wrench``, ``step``). With the recorded configuration it
feeds the recorded applied torques with the actuator model off (``actuator.velocity_limit:
ignore``: the torques are already those the motors applied; clipping them again at the
effort limit changes nothing, derating them twice would), and it must reproduce the recording
bit for bit: every step's joint positions and velocities, base pose and twist (as
/starleth/base_state holds them) and the foot forces are compared exactly; the output says
"bit-identical" or gives the first step that differs and by how much (exit status 0 or 3).

``--preset NAME`` (repeatable, or a YAML path) runs the same torque stream through other
configurations (the initial state converted through minimal coordinates; their motors
derate a torque beyond the velocity limit, so a leg in the air does not spin up without
bound once the run has left the recorded one) and writes overlay
plots (foot normal forces and base path by ``starleth-analyze``'s plotting, joint angles)
and a table of differences against the recording. The recorded run was closed loop: its
controller reacted to the recorded physics. Replayed open loop through other physics, the
robot follows the torques of a state it is no longer in: the runs diverge (the robot may
fall); the output says from when (base more than ``--diverge-position`` from the recorded
path, or a joint more than ``--diverge-angle`` from its recorded angle).

A bag without the metadata (not recorded by sim_node), a truncated or damaged one
(``--salvage`` reads up to the damage), one whose joint states skip steps, or whose
metadata or messages are not what sim_node writes (a control period that is not a positive
number, joint names or an initial state that are not JSON or do not fit, a configuration
whose YAML aliases expand it beyond its size, joint states of the wrong length, a NaN or
infinite torque) gives one line on stderr and exit status 1.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field

import numpy as np
import yaml

from .bag import BagError, read_messages

PROG = "starleth-replay"
FEET = ("LF", "RF", "LH", "RH")
#: the quantities compared step by step, as the recording holds them
QUANTITIES = ("joint_positions", "joint_velocities", "base_position", "base_orientation",
              "base_linear_velocity", "base_angular_velocity", "foot_forces")
STATE_QUANTITIES = QUANTITIES[:-1]


class ReplayError(BagError):
    """A bag that cannot be replayed: one line, exit status 1."""


def warn(message: str) -> None:
    print(f"{PROG}: warning: {message}", file=sys.stderr)


# =========================================================================================
# reading the recording
# =========================================================================================
@dataclass
class Recording:
    """What a replay needs from a bag, as arrays over the recorded states k = 0..N
    (stamp k * period_ns)."""

    path: str
    config_yaml: str
    initial: dict                  # the recorded initial_state.json
    joint_names: list
    control_period: float
    period_ns: int
    namespace: str
    package_version: str
    states: dict                   # quantity -> (N+1, width) float64, as recorded
    effort: np.ndarray             # (N+1, 12): effort[k+1] = torque applied over k -> k+1
    wrenches: dict = field(default_factory=dict)   # k -> [(link, force, torque, persistent)]
    summary: dict = field(default_factory=dict)    # sim_node's closing summary, if any

    @property
    def steps(self) -> int:
        return self.effort.shape[0] - 1

    def config(self):
        from ..physics.config import PhysicsConfig
        what = f"{self.path}: physics_config"
        return PhysicsConfig.from_dict(bounded_yaml(self.config_yaml, what), source=what)


def _cut(text: str, n: int = 300) -> str:
    """text, cut to about n characters (a metadata value may be megabytes)."""
    return text if len(text) <= n else text[:n] + "..."


def _short(value, n=60) -> str:
    """repr(value), cut to about n characters."""
    return _cut(repr(value), n)


def bounded_yaml(text: str, what: str):
    """YAML text from a bag, loaded; a ReplayError where it is not YAML or where its aliases
    expand it beyond its size (a few hundred bytes of nested aliases make a billion-element
    list, which the configuration's checks would then walk)."""
    try:
        data = yaml.safe_load(text)
    except (yaml.YAMLError, RecursionError, ValueError) as e:
        raise ReplayError(f"{what}: not valid YAML ({type(e).__name__}: "
                          f"{_cut(str(e), 200)})") from None
    budget = 2 * len(text) + 16          # nodes: fewer than characters without aliases
    stack = [data]
    while stack:
        x = stack.pop()
        budget -= 1
        if budget < 0:
            raise ReplayError(f"{what}: its YAML aliases expand it far beyond its "
                              f"{len(text)} characters")
        if isinstance(x, dict):
            stack.extend(x.keys())
            stack.extend(x.values())
        elif isinstance(x, (list, tuple)):
            stack.extend(x)
    return data


def _json(md, key, path):
    """A JSON value of the starleth_sim metadata; ReplayError where it is not JSON."""
    try:
        return json.loads(md[key])
    except (ValueError, TypeError, RecursionError):
        raise ReplayError(f"{path}: the recorded {key} is not valid JSON "
                          f"({_short(md[key])})") from None


def _metadata(bag, path):
    md = bag.metadata.get("starleth_sim")
    need = ("physics_config", "initial_state", "joint_names", "control_period")
    if not md or any(k not in md for k in need):
        missing = need if not md else [k for k in need if k not in md]
        raise ReplayError(f"{path}: no replay metadata (starleth_sim record lacks "
                          f"{', '.join(missing)}): the bag was not recorded by sim_node "
                          "(record:=...), so its physics configuration and initial state "
                          "are unknown")
    return md


def _body_twist(quat, v_world):
    """The linear twist as sim_node publishes it: in the base frame, R^T v."""
    from ..ros.state_io import quat_to_matrix
    return quat_to_matrix(*quat).T @ v_world


def load_recording(path: str, salvage: bool = False) -> Recording:
    """Read the metadata, the states, the applied torques and the wrenches of a bag."""
    from starleth_interface.topics import foot_wrench_topic, resolve
    # the metadata comes first (sim_node writes it when the recording opens); a bag without
    # it is refused before its messages are decoded
    probe = read_messages(path, lambda t, ty: False, salvage=salvage, on_warning=warn)
    md = _metadata(probe, path)
    ns = md.get("namespace", "")
    ns = "" if ns in ("", "/") else ns
    topics = {
        "joints": md.get("joint_states_topic") or resolve("joint_states", ns),
        "base": md.get("base_state_topic") or resolve("starleth/base_state", ns),
        **{f: resolve(foot_wrench_topic(f"{f}_foot"), ns) for f in FEET}}
    wrench_topics = {md.get("wrench_topic"): False, md.get("wrench_persistent_topic"): True}
    wrench_topics.pop(None, None)
    if not wrench_topics:   # bags of before the topic names were recorded
        for t in probe.types:
            if t.endswith("/wrench/persistent"):
                wrench_topics[t] = True
            elif t.endswith("/wrench") and "/starleth/" not in t:
                wrench_topics[t] = False
    wanted = set(topics.values()) | set(wrench_topics)
    bag = read_messages(path, lambda t, ty: t in wanted, salvage=salvage, on_warning=warn)
    for key in ("joints", "base"):
        if not bag.messages.get(topics[key]):
            raise ReplayError(f"{path}: no messages on {topics[key]}: nothing to replay")
    try:
        control_period = float(md["control_period"])
        period_ns = int(md.get("stamp_period_ns") or round(control_period * 1e9))
    except (ValueError, TypeError, OverflowError):
        period_ns, control_period = 0, math.nan
    if period_ns <= 0 or not (math.isfinite(control_period) and control_period > 0):
        raise ReplayError(f"{path}: the recorded control period is not a positive number "
                          f"(control_period {_short(md['control_period'])}, stamp_period_ns "
                          f"{_short(md.get('stamp_period_ns'))})")
    joint_names = _json(md, "joint_names", path)
    if not (isinstance(joint_names, list) and all(isinstance(n, str) for n in joint_names)):
        raise ReplayError(f"{path}: the recorded joint_names is not a list of names "
                          f"({_short(md['joint_names'])})")

    def by_step(topic, what):
        rows = {}
        for _, m in bag.messages.get(topic, ()):
            s = m.header.stamp
            ns_ = s.sec * 1_000_000_000 + s.nanosec
            k, r = divmod(ns_, period_ns)
            if r:
                raise ReplayError(f"{path}: {topic}: stamp {ns_} ns is not a multiple of the "
                                  f"control period ({period_ns} ns)")
            rows.setdefault(k, m)       # a re-sent state has the same stamp and values
        if not rows:
            return rows
        ks = sorted(rows)
        if ks[0] != 0 or ks[-1] != len(ks) - 1:
            gap = next((a + 1 for a, b in zip([-1] + ks, ks) if b != a + 1), ks[-1])
            raise ReplayError(f"{path}: {what} of step {gap} (t = {gap * period_ns * 1e-9:.4f} s) "
                              "is missing from the recording: cannot replay it")
        return rows

    js = by_step(topics["joints"], "/joint_states")
    base = by_step(topics["base"], "the base state")
    n = min(len(js), len(base))
    if len(js) != len(base):
        warn(f"{path}: {len(js)} joint states but {len(base)} base states; comparing the "
             f"first {n}")
    if n < 2:
        raise ReplayError(f"{path}: fewer than two recorded states: nothing to replay")
    names = list(js[0].name)
    if names != joint_names:
        raise ReplayError(f"{path}: /joint_states names {_short(names, 400)} differ from the "
                          f"recorded joint_names {_short(joint_names, 400)}")
    for k in range(n):
        for field_ in ("position", "velocity", "effort"):
            have = len(getattr(js[k], field_))
            if have != len(joint_names):
                raise ReplayError(f"{path}: the /joint_states of step {k} holds {have} "
                                  f"{field_} values for {len(joint_names)} joints")
    states = {
        "joint_positions": np.array([js[k].position for k in range(n)], dtype=float),
        "joint_velocities": np.array([js[k].velocity for k in range(n)], dtype=float),
    }
    effort = np.array([js[k].effort for k in range(n)], dtype=float)
    bad = np.flatnonzero(~np.isfinite(effort[1:]).all(axis=1)) + 1   # [0]: not applied
    if bad.size:
        raise ReplayError(f"{path}: the /joint_states effort of step {bad[0]} (the torque "
                          "applied over the step before it) is NaN or infinite: not a torque "
                          "the simulator applied; cannot replay it")
    p, o, v, w = [], [], [], []
    for k in range(n):
        m = base[k]
        pp, po = m.pose.pose.position, m.pose.pose.orientation
        tl, ta = m.twist.twist.linear, m.twist.twist.angular
        p.append((pp.x, pp.y, pp.z))
        o.append((po.x, po.y, po.z, po.w))
        v.append((tl.x, tl.y, tl.z))
        w.append((ta.x, ta.y, ta.z))
    states.update(base_position=np.array(p), base_orientation=np.array(o),
                  base_linear_velocity=np.array(v), base_angular_velocity=np.array(w))
    forces = np.full((n, 3 * len(FEET)), np.nan)
    for i, f in enumerate(FEET):
        rows = by_step(topics[f], f"the {f} foot wrench")
        for k, m in rows.items():
            if k < n:
                fm = m.wrench.force
                forces[k, 3 * i:3 * i + 3] = (fm.x, fm.y, fm.z)
    states["foot_forces"] = forces
    wrenches = {}
    for topic, persistent in wrench_topics.items():
        for log_ns, m in bag.messages.get(topic, ()):
            k = int(log_ns) // period_ns
            f, t = m.wrench.force, m.wrench.torque
            wrenches.setdefault(k, []).append(
                (log_ns, m.header.frame_id, (f.x, f.y, f.z), (t.x, t.y, t.z), persistent))
    for k in wrenches:   # in the order they were taken
        wrenches[k] = [w_[1:] for w_ in sorted(wrenches[k], key=lambda x: x[0])]
    summary = {}
    for k, val in bag.metadata.get("starleth_sim_summary", {}).items():
        try:
            summary[k] = json.loads(val)
        except (ValueError, RecursionError):
            summary[k] = val
    initial = _json(md, "initial_state", path)
    if not isinstance(initial, dict):
        raise ReplayError(f"{path}: the recorded initial_state is not a JSON object "
                          f"({_short(md['initial_state'])})")
    if bag.truncated:
        warn(f"{path}: truncated: replaying the {n - 1} steps before the damage")
    return Recording(path=path, config_yaml=md["physics_config"], initial=initial,
                     joint_names=joint_names, control_period=control_period,
                     period_ns=period_ns, namespace=ns,
                     package_version=md.get("package_version", "unknown"), states=states,
                     effort=effort, wrenches=wrenches, summary=summary)


# =========================================================================================
# re-simulation
# =========================================================================================
@dataclass
class Replay:
    """A re-simulated run: the same quantities as Recording.states, for states 0..steps."""

    label: str
    config_name: str
    states: dict
    steps: int                       # steps taken (fewer than asked for if the physics failed)
    requested: int = 0               # steps asked for (all recorded ones, or --steps)
    error: str | None = None
    wall: float = 0.0
    iterations: np.ndarray = field(default_factory=lambda: np.zeros(0))


def _snapshot(sim):
    from ..ros.state_io import public_state
    pub = public_state(sim)
    quat = [float(x) for x in pub["base_orientation"]]
    cs = {c.name: c for c in sim.contacts}
    forces = np.concatenate([cs[f"{f}_foot"].force for f in FEET]).astype(float)
    return {"joint_positions": pub["joint_positions"],
            "joint_velocities": pub["joint_velocities"],
            "base_position": pub["base_position"],
            "base_orientation": np.array(quat),
            "base_linear_velocity": _body_twist(quat, pub["base_linear_velocity"]),
            "base_angular_velocity": pub["base_angular_velocity"],
            "foot_forces": forces}


def resimulate(rec: Recording, config=None, label=None, steps=None) -> Replay:
    """Run the recorded torques and wrenches through `config` (default: the recorded one)
    from the recorded initial state, with sim_node's own calls (SimService)."""
    from ..physics.config import ConfigError
    from ..physics.simulator import Simulator
    from ..ros.parameters import Settings
    from ..ros.service import SimService
    own = config is None
    cfg = rec.config() if own else config
    if abs(cfg.control_period - rec.control_period) > 1e-12:
        raise ReplayError(f"{cfg.name}: control period {cfg.control_period * 1e3:g} ms, the "
                          f"recording's is {rec.control_period * 1e3:g} ms: the torque stream "
                          "does not fit (override control_rate)")
    if own:   # the recorded torques are the applied ones: derating them again would differ
        cfg = cfg.with_overrides(**{"actuator.velocity_limit": "ignore"})
    try:
        sim = Simulator(cfg)
    except ConfigError:
        raise
    except Exception as e:   # the robot's URDF (a path in the recorded configuration)
        raise ReplayError(f"{cfg.name}: no simulator of this configuration: "
                          f"{type(e).__name__}: {_cut(str(e))}") from None
    init = rec.initial
    warnings = []
    try:
        if init.get("coordinates") == cfg.coordinates and "q" in init:
            q0, u0 = np.array(init["q"], dtype=float), np.array(init["u"], dtype=float)
        else:   # another set of coordinates: through the minimal ones
            sim.reset(init["q_minimal"], init["u_minimal"], minimal=True)
            q0, u0 = sim.q, sim.u
        # the longest throttle period sim_node's parameter allows: one warning per kind
        svc = SimService(sim, Settings(mode="lockstep", warn_throttle_period=3600.0), q0, u0,
                         warn=warnings.append)
    except (ValueError, TypeError, KeyError, IndexError) as e:
        raise ReplayError(f"{rec.path}: the recorded initial_state does not fit "
                          f"{cfg.name}: {type(e).__name__}: {_cut(str(e))}") from None
    n = rec.steps if steps is None else min(steps, rec.steps)
    out = {q: np.full((n + 1,) + rec.states[q].shape[1:], np.nan) for q in QUANTITIES}
    first = _snapshot(sim)
    for q in QUANTITIES:
        out[q][0] = first[q]
    its = np.zeros(n)
    error = None
    t0 = time.perf_counter()
    k = 0
    for k in range(n):
        for link, f, m, persistent in rec.wrenches.get(k, ()):
            svc.submit_wrench(link, f, m, persistent)
        svc.command = rec.effort[k + 1]
        d = svc.step()
        if d is None:
            error = warnings[-1] if warnings else f"the physics failed at step {k}"
            break
        its[k] = d.iterations
        snap = _snapshot(sim)
        for q in QUANTITIES:
            out[q][k + 1] = snap[q]
    else:
        k = n
    done = k
    return Replay(label=label or (cfg.name + (" (replay)" if own else "")),
                  config_name=cfg.name, states={q: a[:done + 1] for q, a in out.items()},
                  steps=done, requested=n, error=error, wall=time.perf_counter() - t0,
                  iterations=its[:done])


@dataclass
class Comparison:
    identical: bool
    steps: int                        # steps compared
    first_step: int | None = None     # first state k (1..steps) where a state quantity differs
    first_quantities: dict = field(default_factory=dict)   # quantity -> max |Δ| at that step
    max_abs: dict = field(default_factory=dict)            # quantity -> max |Δ| over the run
    forces_identical: bool = True


def compare_exact(rec: Recording, rep: Replay) -> Comparison:
    """Bit for bit, state by state (NaN equals NaN: a foot wrench missing in both)."""
    n = rep.steps
    first, maxabs = None, {}
    for q in QUANTITIES:
        a, b = rec.states[q][:n + 1], rep.states[q][:n + 1]
        same = (a.view(np.int64) == b.view(np.int64)) | (np.isnan(a) & np.isnan(b))
        bad = np.flatnonzero(~same.all(axis=1))
        diff = np.abs(a - b)
        maxabs[q] = float(np.nanmax(diff)) if diff.size and np.isfinite(diff).any() else 0.0
        if q in STATE_QUANTITIES and bad.size and (first is None or bad[0] < first):
            first = int(bad[0])
    forces_same = np.array_equal(rec.states["foot_forces"][:n + 1],
                                 rep.states["foot_forces"][:n + 1], equal_nan=True)
    at = {}
    if first is not None:
        for q in STATE_QUANTITIES:
            d = np.abs(rec.states[q][first] - rep.states[q][first])
            if np.any(d > 0) or np.any(np.isnan(d)):
                at[q] = float(np.nanmax(d))
    identical = first is None and rep.steps == rep.requested and rep.error is None
    return Comparison(identical=identical, steps=n, first_step=first, first_quantities=at,
                      max_abs=maxabs, forces_identical=forces_same)


def divergence(rec: Recording, rep: Replay, position=0.01, angle=0.05) -> dict:
    """Where an open-loop replay leaves the recorded run: the first time the base is more
    than `position` [m] from its recorded position or a joint more than `angle` [rad] from
    its recorded angle; with the largest differences, the final ones and whether the
    replayed robot fell (base below 0.3 m or tilted more than 60°)."""
    n = rep.steps
    dp = np.linalg.norm(rec.states["base_position"][:n + 1] - rep.states["base_position"][:n + 1],
                        axis=1)
    dq = np.abs(rec.states["joint_positions"][:n + 1]
                - rep.states["joint_positions"][:n + 1]).max(axis=1)
    off = np.flatnonzero((dp > position) | (dq > angle))
    o = rep.states["base_orientation"][:n + 1]
    tilt = np.degrees(np.arccos(np.clip(1 - 2 * (o[:, 0] ** 2 + o[:, 1] ** 2), -1, 1)))
    z = rep.states["base_position"][:n + 1, 2]
    fallen = np.flatnonzero((z < 0.3) | (tilt > 60.0))
    fz_rec = rec.states["foot_forces"][:n + 1, 2::3]
    fz_rep = rep.states["foot_forces"][:n + 1, 2::3]
    return {"steps": n, "diverges_at": float(off[0] * rec.control_period) if off.size else None,
            "fell_at": float(fallen[0] * rec.control_period) if fallen.size else None,
            "base_max_m": float(dp.max()), "base_final_m": float(dp[-1]),
            "joint_max_rad": float(dq.max()), "joint_rms_rad": float(np.sqrt(np.mean(
                (rec.states["joint_positions"][:n + 1]
                 - rep.states["joint_positions"][:n + 1]) ** 2))),
            "foot_force_rms_n": float(np.sqrt(np.nanmean((fz_rec - fz_rep) ** 2))),
            "iterations_mean": float(rep.iterations.mean()) if rep.iterations.size else 0.0,
            "error": rep.error}


# =========================================================================================
# plots (starleth-analyze's, on runs built from arrays)
# =========================================================================================
def _as_run(label, states, control_period):
    from .analysis import Run
    n = states["joint_positions"].shape[0]
    t = np.arange(n) * control_period
    base = np.hstack([states["base_position"], states["base_orientation"],
                      states["base_linear_velocity"], states["base_angular_velocity"]])
    wrench = {f: states["foot_forces"][:, 3 * i:3 * i + 3] for i, f in enumerate(FEET)}
    run = Run.from_arrays(label, t, base=base, wrench=wrench, base_frames=("world", "base"))
    run.joint_positions = states["joint_positions"]
    return run


def plot_joint_angles(plt, runs, opts):
    from .analysis import JOINTS, _color, _finish, _suffix
    fig, axes = plt.subplots(4, 3, figsize=(14, 10), sharex=True, squeeze=False)
    for j, name in enumerate(JOINTS):
        ax = axes[j // 3][j % 3]
        for i, r in enumerate(runs):
            t = r.series("base")["t"]
            ax.plot(t, r.joint_positions[:, j], color=_color(i), lw=0.8, label=r.label)
        _finish(ax, "time [s]" if j >= 9 else "", "angle [rad]", name, legend=j == 0)
    fig.suptitle("Joint angles" + _suffix(runs))
    fig.tight_layout()
    return fig


def write_overlays(rec: Recording, replays, out_dir, dpi=110) -> list:
    """contact_forces.png, base_trajectory.png (starleth-analyze's plots) and
    joint_angles.png: the recording and the replays overlaid."""
    from .analysis import _pyplot, plot_base, plot_contact_forces
    plt = _pyplot()
    runs = [_as_run("recorded", rec.states, rec.control_period)]
    runs += [_as_run(r.label, r.states, rec.control_period) for r in replays]
    opts = argparse.Namespace(threshold=5.0, twist_frame="child", min_phase=0.02)
    os.makedirs(out_dir, exist_ok=True)
    written = []
    for name, fn in (("contact_forces", plot_contact_forces), ("base_trajectory", plot_base),
                     ("joint_angles", plot_joint_angles)):
        fig = fn(plt, runs, opts)
        if fig is None:
            continue
        path = os.path.join(out_dir, f"{name}.png")
        fig.savefig(path, dpi=dpi)
        plt.close(fig)
        written.append(path)
    return written


# =========================================================================================
# command line
# =========================================================================================
def _fmt_t(x):
    return "never" if x is None else f"t = {x:.3f} s"


def format_comparison(rec: Recording, rep: Replay, c: Comparison) -> list:
    cp = rec.control_period
    if c.identical:
        some = f" (the first {c.steps} of {rec.steps})" if c.steps < rec.steps else ""
        lines = [f"  bit-identical: all {c.steps} steps{some} (joint positions and velocities, "
                 "base pose and twist" + (", foot forces" if c.forces_identical else "") + ")"]
        if not c.forces_identical:
            lines.append(f"  (foot forces differ by up to {c.max_abs['foot_forces']:.3g} N)")
        return lines
    if c.first_step is None:
        return [f"  NOT complete: the replay stopped after {rep.steps} of {rep.requested} "
                f"steps ({rep.error}); identical up to there"]
    diffs = ", ".join(f"{q} {v:.3g}" for q, v in c.first_quantities.items())
    return [f"  NOT bit-identical: first difference at step {c.first_step} "
            f"(t = {c.first_step * cp:.4f} s): max |Δ| {diffs}",
            "  largest over the run: " + ", ".join(f"{q} {v:.3g}"
                                                   for q, v in c.max_abs.items())]


def build_parser():
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("bag", help="an MCAP file or rosbag2 directory recorded by sim_node")
    ap.add_argument("--preset", action="append", default=[],
                    help="also run the torque stream through this configuration (a preset "
                         "name or YAML path; repeatable)")
    ap.add_argument("--out", default=None,
                    help="directory of the overlay plots and table (default: <bag>_replay/)")
    ap.add_argument("--steps", type=int, default=None, help="replay only the first N steps")
    ap.add_argument("--diverge-position", type=float, default=0.01,
                    help="base distance [m] from the recorded path counted as divergence")
    ap.add_argument("--diverge-angle", type=float, default=0.05,
                    help="joint angle difference [rad] counted as divergence")
    ap.add_argument("--no-plots", action="store_true")
    ap.add_argument("--json", default=None, help="write the results as JSON")
    ap.add_argument("--salvage", action="store_true",
                    help="replay a truncated bag up to the damage")
    return ap


def run(argv=None) -> int:
    from ..physics.config import ConfigError, load_preset
    a = build_parser().parse_args(argv)
    if a.steps is not None and a.steps < 1:
        build_parser().error("--steps must be >= 1")
    try:
        configs = [load_preset(p) for p in a.preset]
    except ConfigError as e:
        raise ReplayError(f"--preset: {e}") from None
    t0 = time.perf_counter()
    rec = load_recording(a.bag, salvage=a.salvage)
    try:
        rec_cfg = rec.config()
    except ConfigError as e:
        raise ReplayError(str(e)) from None
    print(f"== {a.bag}: {rec.steps} steps of {rec.control_period * 1e3:g} ms "
          f"({rec.steps * rec.control_period:.3f} s), physics {rec_cfg.name}, recorded by "
          f"starleth_sim {rec.package_version}; {sum(map(len, rec.wrenches.values()))} external "
          f"wrench(es); read in {time.perf_counter() - t0:.2f} s ==")
    resets = rec.summary.get("resets", 0)
    if isinstance(resets, int) and resets > 0:
        warn(f"the run was reset {resets} time(s) (~/reset); a replay does not reset: it "
             "differs from the first reset on")
    rep = resimulate(rec, label=f"{rec_cfg.name} (replay)", steps=a.steps)
    c = compare_exact(rec, rep)
    print(f"replay with the recorded configuration ({rep.wall:.2f} s):")
    for line in format_comparison(rec, rep, c):
        print(line)
    doc = {"bag": a.bag, "steps": rec.steps, "config": rec_cfg.name,
           "package_version": rec.package_version,
           "bit_identical": c.identical, "first_difference_step": c.first_step,
           "first_difference": c.first_quantities, "max_abs_difference": c.max_abs,
           "presets": {}}
    replays = []
    if configs:
        print("open-loop replays through other configurations: the recorded run was closed "
              "loop (its controller reacted to the recorded physics); the same torques "
              "applied open loop to other physics make the runs diverge, and the robot may "
              "fall. Divergence: base more than "
              f"{a.diverge_position:g} m off the recorded path or a joint more than "
              f"{a.diverge_angle:g} rad off its recorded angle.")
        rows = []
        for cfg in configs:
            r = resimulate(rec, cfg, label=cfg.name, steps=a.steps)
            replays.append(r)
            dv = divergence(rec, r, a.diverge_position, a.diverge_angle)
            doc["presets"][cfg.name] = dv
            rows.append((cfg.name, dv))
            tail = f"; stopped: {r.error}" if r.error else ""
            print(f"  {cfg.name:8s} diverges {_fmt_t(dv['diverges_at'])}, falls "
                  f"{_fmt_t(dv['fell_at'])} ({r.steps} steps in {r.wall:.2f} s{tail})")
        print("\n| config | diverges at | falls at | base Δ max / final [m] | joint Δ max / RMS "
              "[rad] | foot F_z Δ RMS [N] | iterations / step |")
        print("|---|---|---|---|---|---|---|")
        for name, dv in rows:
            print(f"| {name} | {_fmt_t(dv['diverges_at'])} | {_fmt_t(dv['fell_at'])} | "
                  f"{dv['base_max_m']:.4f} / {dv['base_final_m']:.4f} | "
                  f"{dv['joint_max_rad']:.4f} / {dv['joint_rms_rad']:.4f} | "
                  f"{dv['foot_force_rms_n']:.2f} | {dv['iterations_mean']:.1f} |")
    if configs and not a.no_plots:
        base = a.bag.rstrip("/")
        out = a.out or (os.path.splitext(base)[0] if base.endswith(".mcap") else base) + "_replay"
        written = write_overlays(rec, replays, out)
        doc["plots"] = written
        print(f"plots in {out}/: " + ", ".join(os.path.basename(p) for p in written))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(doc, f, indent=1)
    return 0 if c.identical else 3


def main(argv=None) -> int:
    """Console script: 0 bit-identical, 3 not bit-identical, 1 a bag that cannot be replayed
    (one line), 2 bad arguments."""
    from .analysis import run_console_script
    from ..physics.config import ConfigError
    return run_console_script(PROG, run, argv, errors=(BagError, ConfigError))


if __name__ == "__main__":
    sys.exit(main())
