"""The recording ``starleth-replay`` re-simulates, read from a bag written by sim_node: the
physics configuration, initial state and control period of its metadata, the recorded states
step by step (the quantities compared), the applied torques and the external wrenches, with
every check that the bag holds what sim_node writes; the tool's warnings and its error."""
from __future__ import annotations

import itertools
import json
import math
import sys
from dataclasses import dataclass, field

import numpy as np

from starleth_interface.topics import foot_wrench_topic, resolve
from starleth_interface.yaml_files import load_yaml_text

from ...physics.config import ConfigError, PhysicsConfig
from ...physics.description import RobotDescription
from ...robots import recorded_description, robot_description
from ...ros.parameters import frame_name_problem
from ..common.bag import BagError, read_messages, recorded_robot

PROG = "starleth-replay"
#: the quantities compared step by step, as the recording holds them
QUANTITIES = ("joint_positions", "joint_velocities", "base_position", "base_orientation",
              "base_linear_velocity", "base_angular_velocity", "foot_forces")
STATE_QUANTITIES = QUANTITIES[:-1]
#: the sensor topics, compared bit for bit where the bag has them: joint_states as measured
#: (position, velocity, effort), the IMU (orientation x y z w, rates, proper acceleration),
#: the foot contacts (flags, normal forces)
MEASURED_QUANTITIES = ("measured_joint_states", "imu", "foot_contacts")


class ReplayError(BagError):
    """A bag that cannot be replayed: one line, exit status 1."""


def warn(message: str) -> None:
    print(f"{PROG}: warning: {message}", file=sys.stderr)


@dataclass
class Recording:
    """What a replay needs from a bag, as arrays over the recorded states k = 0..N
    (stamp k * period_ns)."""

    path: str
    config_yaml: str
    #: the robot as recorded (its URDF and spec from the bag; StarlETH's of the library for
    #: bags of before the robot was recorded)
    description: RobotDescription
    initial: dict                  # the recorded initial_state.json
    joint_names: list
    control_period: float
    period_ns: int
    namespace: str
    package_version: str
    states: dict                   # quantity -> (N+1, width) float64, as recorded
    effort: np.ndarray             # (N+1, 12): effort[k+1] = torque applied over k -> k+1
    #: (N+1, physics steps, 12): applied[k+1] = the torques of each physics step of k -> k+1
    #: (starleth/applied_torque); None in bags recorded without it
    applied: np.ndarray | None = None
    #: (N+1, physics steps, 24): per physics step the explicit torques, then the kd of the
    #: implicit dampers (Simulator.replay_torques_per_step); None in bags without them
    replay: np.ndarray | None = None
    wrenches: dict = field(default_factory=dict)   # k -> [(frame, force, torque, persistent)]
    #: sim_node's tf_frame_prefix: a wrench's frame may name its link with it
    frame_prefix: str = ""
    summary: dict = field(default_factory=dict)    # sim_node's closing summary, if any
    #: why the recording ends early (cut_cause: a failed write, a truncated file), or None
    cut: str | None = None

    @property
    def steps(self) -> int:
        return self.effort.shape[0] - 1

    @property
    def feet(self) -> tuple:
        """The foot contact names of the recorded robot, in its order."""
        return self.description.foot_names

    def config(self):
        what = f"{self.path}: physics_config"
        return PhysicsConfig.from_dict(load_yaml_text(self.config_yaml, what), source=what)


def shortened(text: str, n: int = 300) -> str:
    """text, cut to about n characters (a metadata value may be megabytes)."""
    return text if len(text) <= n else text[:n] + "..."


def _short(value, n=60) -> str:
    """repr(value), cut to about n characters."""
    return shortened(repr(value), n)


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


def _topics(md, probe, feet):
    """The namespace, the state topics {joints, base, foot: topic} (`feet`: the robot's foot
    contact names; joints: the exact ones, on ground_truth/joint_states with noisy sensors),
    the sensor topics {measured quantity: topic}, the wrench input topics {topic:
    persistent} and the applied torque topic (or None) of a recording."""
    ns = md.get("namespace", "")
    ns = "" if ns in ("", "/") else ns
    measured = {"measured_joint_states": md.get("joint_states_topic")
                or resolve("joint_states", ns),
                "imu": md.get("imu_topic") or resolve("starleth/imu", ns),
                "foot_contacts": md.get("foot_contacts_topic")}
    topics = {
        "joints": md.get("ground_truth_joint_states_topic") or
        measured["measured_joint_states"],
        "base": md.get("base_state_topic") or resolve("starleth/base_state", ns),
        **{f: resolve(foot_wrench_topic(f), ns) for f in feet}}
    wrench_topics = {md.get("wrench_topic"): False, md.get("wrench_persistent_topic"): True}
    wrench_topics.pop(None, None)
    if not wrench_topics:   # bags of before the topic names were recorded
        for t in probe.types:
            if t.endswith("/wrench/persistent"):
                wrench_topics[t] = True
            elif t.endswith("/wrench") and "/starleth/" not in t:
                wrench_topics[t] = False
    return ns, topics, measured, wrench_topics, md.get("applied_torque_topic")


def _control_period(md, path):
    """(control period [s], stamp period [ns]) of the metadata; ReplayError where they are
    not positive numbers."""
    try:
        control_period = float(md["control_period"])
        period_ns = int(md.get("stamp_period_ns") or round(control_period * 1e9))
    except (ValueError, TypeError, OverflowError):
        period_ns, control_period = 0, math.nan
    if period_ns <= 0 or not (math.isfinite(control_period) and control_period > 0):
        raise ReplayError(f"{path}: the recorded control period is not a positive number "
                          f"(control_period {_short(md['control_period'])}, stamp_period_ns "
                          f"{_short(md.get('stamp_period_ns'))})")
    return control_period, period_ns


def _by_step(rows_, period_ns, path, topic, what):
    """{step k: message} of the messages of `topic` (header stamp k * period_ns); a
    ReplayError where a stamp is not on the grid or a step is missing between others."""
    rows = {}
    for _, m in rows_:
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
        gap = next((a + 1 for a, b in itertools.pairwise([-1] + ks) if b != a + 1), ks[-1])
        raise ReplayError(f"{path}: {what} of step {gap} (t = {gap * period_ns * 1e-9:.4f} s) "
                          "is missing from the recording: cannot replay it")
    return rows


def cut_cause(bag) -> str | None:
    """Why a recording ends early, or None: the fault its recorder wrote when a write
    failed (a file-size limit, a full disk) or when its writer process ended (the
    'starleth_recording_fault' metadata: recording.mcap_sink), or a truncated file read
    with --salvage."""
    fault = bag.metadata.get("starleth_recording_fault")
    if fault is not None:
        return shortened(str(fault.get("cause", "a write failed")), 200)
    return "the file is truncated" if bag.truncated else None


def _complete_states(path, states, applied_steps, cut, period_ns):
    """The states to replay, of `states` ({what: states recorded}, each 0..count - 1) and
    `applied_steps` (the first step k without an applied torque for k - 1 -> k, or None
    without the topic): the fewest of them. A recording cut by a failure (`cut`) ends
    within a step's messages, which come one topic after another: its last states may lack
    some; they are left out, and a warning says how many and why. A complete recording
    whose joint and base states differ in number is compared over the first ones."""
    counts = dict(states)
    if cut is not None and applied_steps is not None:
        counts["applied torques"] = applied_steps
    n = min(counts.values())
    if cut is not None:
        left = max(counts.values()) - n
        short = ", ".join(what for what, c in counts.items() if c == n)
        warn(f"{path}: the recording was cut ({cut}): replaying its {max(n - 1, 0)} complete "
             f"steps" + (f"; left out the last {left} state(s) (from t = "
                         f"{n * period_ns * 1e-9:.4f} s: no {short} for them)" if left else ""))
    elif states["joint states"] != states["base states"]:
        warn(f"{path}: {states['joint states']} joint states but {states['base states']} "
             f"base states; comparing the first {n}")
    if n < 2:
        raise ReplayError(f"{path}: fewer than two recorded states: nothing to replay")
    return n


def _first_missing_step(rows, period_ns):
    """The first step k >= 1 without a message of log time t_k in rows (None: no rows)."""
    if not rows:
        return None
    have = {int(log_ns) // period_ns for log_ns, _ in rows}
    k = 1
    while k in have:
        k += 1
    return k


def _frame_prefix(md, path) -> str:
    """The recorded tf_frame_prefix ('' in bags without it, with a warning where it is not
    a frame prefix)."""
    try:
        params = json.loads(md.get("parameters") or "{}")
    except (ValueError, TypeError, RecursionError):
        params = None
    prefix = params.get("tf_frame_prefix", "") if isinstance(params, dict) else ""
    problem = frame_name_problem(prefix, empty_ok=True) if isinstance(prefix, str) else \
        "not a string"
    if problem:
        warn(f"{path}: the recorded tf_frame_prefix {_short(prefix)} {problem}; wrenches are "
             "taken on unprefixed link names")
        return ""
    return prefix


def _description(probe, path, config_yaml) -> RobotDescription:
    """The recorded robot (its URDF and spec attachments: no library needed); for a bag
    without them, the robot its physics configuration names (StarlETH)."""
    robot = recorded_robot(probe, path)
    try:
        if robot is not None:
            name, urdf, spec = robot
            return recorded_description(urdf, spec, name, where=path)
        what = f"{path}: physics_config"
        return robot_description(
            PhysicsConfig.from_dict(load_yaml_text(config_yaml, what), source=what).robot)
    except ConfigError as e:
        raise ReplayError(str(e)) from None


def load_recording(path: str, salvage: bool = False) -> Recording:
    """Read the metadata, the robot, the states, the applied torques and the wrenches of a
    bag."""
    # the metadata comes first (sim_node writes it when the recording opens); a bag without
    # it is refused before its messages are decoded
    probe = read_messages(path, lambda _topic, _type: False, salvage=salvage, on_warning=warn)
    md = _metadata(probe, path)
    desc = _description(probe, path, md["physics_config"])
    feet = desc.foot_names
    ns, topics, measured, wrench_topics, applied_topic = _topics(md, probe, feet)
    wanted = set(topics.values()) | set(measured.values()) | set(wrench_topics) | \
        {applied_topic}
    bag = read_messages(path, lambda t, _type: t in wanted, salvage=salvage, on_warning=warn)
    for key in ("joints", "base"):
        if not bag.messages.get(topics[key]):
            raise ReplayError(f"{path}: no messages on {topics[key]}: nothing to replay")
    control_period, period_ns = _control_period(md, path)
    joint_names = _json(md, "joint_names", path)
    if not (isinstance(joint_names, list) and all(isinstance(n, str) for n in joint_names)):
        raise ReplayError(f"{path}: the recorded joint_names is not a list of names "
                          f"({_short(md['joint_names'])})")
    rows = {key: _by_step(bag.messages.get(topic, ()), period_ns, path, topic, what)
            for key, topic, what in (
                ("joints", topics["joints"], "/joint_states"),
                ("base", topics["base"], "the base state"),
                *((f, topics[f], f"the {f} wrench") for f in feet))}
    cut = cut_cause(bag)
    counted = {"joint states": len(rows["joints"]), "base states": len(rows["base"])}
    if cut is not None:
        counted.update({f"{f} wrenches": len(rows[f]) for f in feet if rows[f]})
    applied_rows = bag.messages.get(applied_topic, ())
    n = _complete_states(path, counted, _first_missing_step(applied_rows, period_ns), cut,
                         period_ns)
    states, effort = _states(path, rows, n, joint_names, feet)
    states.update(_measured_states(bag, measured, n, period_ns, path))
    applied, replay = _applied_torques(applied_rows, period_ns, n, len(joint_names), path,
                                       applied_topic)
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
    return Recording(path=path, config_yaml=md["physics_config"], description=desc,
                     initial=initial,
                     joint_names=joint_names, control_period=control_period,
                     period_ns=period_ns, namespace=ns,
                     package_version=md.get("package_version", "unknown"), states=states,
                     effort=effort, applied=applied, replay=replay,
                     wrenches=_wrenches(bag, wrench_topics, period_ns), summary=summary,
                     cut=cut, frame_prefix=_frame_prefix(md, path))


def _states(path, rows, n, joint_names, feet):
    """(the recorded states {quantity: (n, width)}, the /joint_states effort (n, joints)) of
    the first n steps of `rows` ({joints, base, foot: {k: message}}); ReplayError where the
    joint states do not fit the joints or hold a torque that is not finite."""
    js, base = rows["joints"], rows["base"]
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
    forces = np.full((n, 3 * len(feet)), np.nan)
    for i, f in enumerate(feet):
        for k, m in rows[f].items():
            if k < n:
                fm = m.wrench.force
                forces[k, 3 * i:3 * i + 3] = (fm.x, fm.y, fm.z)
    states["foot_forces"] = forces
    return states, effort


def _measured_states(bag, topics, n, period_ns, path) -> dict:
    """{quantity: (n, width)} of the sensor topics the bag has (MEASURED_QUANTITIES; NaN
    where a step has no message)."""
    def joints(m):
        return (*m.position, *m.velocity, *m.effort)

    def imu(m):
        o, w, a = m.orientation, m.angular_velocity, m.linear_acceleration
        return (o.x, o.y, o.z, o.w, w.x, w.y, w.z, a.x, a.y, a.z)

    def contacts(m):
        return (*m.position, *m.effort)

    out = {}
    for q, values in (("measured_joint_states", joints), ("imu", imu),
                      ("foot_contacts", contacts)):
        msgs = bag.messages.get(topics[q]) if topics[q] else None
        if not msgs:
            continue
        rows = _by_step(msgs, period_ns, path, topics[q], f"the {q} message")
        width = len(values(rows[0]))
        a = np.full((n, width), np.nan)
        for k, m in rows.items():
            if k < n and len(values(m)) == width:
                a[k] = values(m)
        out[q] = a
    return out


def _wrenches(bag, wrench_topics, period_ns):
    """{k: [(link, force, torque, persistent)]}: the external wrenches taken after state k,
    in the order they were taken."""
    wrenches = {}
    for topic, persistent in wrench_topics.items():
        for log_ns, m in bag.messages.get(topic, ()):
            k = int(log_ns) // period_ns
            f, t = m.wrench.force, m.wrench.torque
            wrenches.setdefault(k, []).append(
                (log_ns, m.header.frame_id, (f.x, f.y, f.z), (t.x, t.y, t.z), persistent))
    for k in wrenches:   # in the order they were taken
        wrenches[k] = [w_[1:] for w_ in sorted(wrenches[k], key=lambda x: x[0])]
    return wrenches


def _applied_torques(rows, period_ns, n, n_joints, path, topic):
    """(n, physics steps, n_joints) from the starleth/applied_torque messages (log time
    t_(k+1): the step k -> k+1), and with the layout physics_steps x 3 x joints (applied,
    explicit torques, kd of the implicit dampers) the replay rows (n, physics steps, 2
    n_joints; else None); (None, None) when the bag has none; ReplayError on a message
    that is not such torques or a step without one."""
    if not rows:
        return None, None
    by_step = {}
    for log_ns, m in rows:
        k = int(log_ns) // period_ns
        if 0 < k < n:
            by_step.setdefault(k, m)
    dims = list(rows[0][1].layout.dim)
    steps = dims[0].size if dims else 0
    terms = dims[1].size if len(dims) == 3 else 1
    out = replay = None
    for k in range(1, n):
        m = by_step.get(k)
        if m is None:
            raise ReplayError(f"{path}: {topic}: no applied torque for step {k - 1} -> {k} "
                              f"(t = {k * period_ns * 1e-9:.4f} s): cannot replay it")
        a = np.array(m.data, dtype=float)
        if steps < 1 or terms not in (1, 3) or a.shape[0] != steps * terms * n_joints or \
                not np.isfinite(a).all():
            raise ReplayError(f"{path}: {topic}: the message of t = {k * period_ns * 1e-9:.4f} s "
                              f"holds {a.shape[0]} values (layout {steps} physics steps x "
                              f"{n_joints} joints expected, all finite): not applied torques")
        if out is None:
            out = np.zeros((n, steps, n_joints))
            replay = np.zeros((n, steps, 2 * n_joints)) if terms == 3 else None
        a = a.reshape(steps, terms, n_joints)
        out[k] = a[:, 0]
        if replay is not None:
            replay[k] = a[:, 1:].reshape(steps, 2 * n_joints)
    return out, replay
