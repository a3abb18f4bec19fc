"""``starleth-analyze``: plots and a short summary of recorded runs.

    starleth-analyze runs/demo.mcap
    starleth-analyze compliant.mcap hard.mcap --label compliant hard --tmax 1.0
    starleth-analyze run.mcap --out plots/ --json summary.json

Reads MCAP bags (rosbag2 profile ``ros2``, ``cdr`` messages with ``ros2msg`` schemas: what
``sim_node`` with ``record:=...`` and ``ros2 bag record -s mcap`` write; a rosbag2 bag
directory holding .mcap files is read as one run) in one pass, decoding only the topics it
plots, with ``mcap`` + ``mcap_ros2`` (no ROS installation needed). Several bags are overlaid
in the same plots, labelled with ``--label`` or the file names.

Topics and what is made of them (time axis: sim time = header stamps, relative to the first
message of the bag):

* /starleth/{LF,RF,LH,RH}_foot/wrench (geometry_msgs/WrenchStamped, force.z = normal force
  in the world): ``contact_forces.png``, ``gait.png`` (stance where F_z > ``--threshold``);
* /starleth/base_state (nav_msgs/Odometry): ``base_trajectory.png`` (x-y path, horizontal
  speed, height);
* /joint_states (sensor_msgs/JointState, effort by joint name): ``joint_torques.png``;
* /starleth/solver (diagnostic_msgs/DiagnosticArray, the status holding the key
  'iterations'; also converged, residual, step_time): ``solver_iterations.png``;
* message times and the solver's step_time: ``real_time_factor.png``;
* the URDF (/robot_description or the recording's attachment; else the package's): the
  robot's weight and effort limits for the summary.

With two or more bags, ``normal_force_LF.png`` (``--foot``) overlays one foot's normal
force, as in Fig. 5 of Gehring et al. (2014).

Odometry twist: REP 105 puts it in ``child_frame_id`` (sim_node: 'base'); it is rotated
into the world with the pose's orientation before the horizontal speed |(v_x, v_y)| is
taken. A twist is taken as world-frame when child_frame_id is empty or equal to the header
frame (``--twist-frame`` overrides).

Real-time factor: sim time is the header stamps; the wall clock is the messages'
``publish_time`` (rosbag2: the send time) or ``log_time`` (rosbag2: the receive time) when
it differs from the stamps. sim_node's own recorder writes ``log_time = publish_time =``
the sim stamp, so such a bag holds no wall clock of the loop; then the *physics compute*
real-time factor is shown, from the solver's ``step_time`` key (wall time of the physics of
each control step: an upper bound, without ROS, the controller or pacing), and the realtime
loop's mean period from the ``starleth_sim_summary`` metadata when present.

A missing topic is reported on stderr (naming it) and its plots are skipped; a truncated
or corrupt file ends the program with a message and exit status 1 (``--salvage`` reads a
truncated file up to the damage instead). Messages that cannot be decoded are skipped and
counted on stderr; so are forces and base states holding a NaN, an infinite value or one
beyond 1e9 (``MAX_VALUE``), and such values of joint torques and solver figures are left
out. The real-time factor plot has at most ``MAX_RTF_WINDOWS`` windows per run, whatever
the span of the stamps.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import xml.etree.ElementTree as ET

import numpy as np

from ..physics.description import STARLETH_JOINT_NAMES
from .bag import BagError, stream_bag
from starleth_interface.topics import (TOPIC_BASE_STATE, TOPIC_JOINT_STATES, TOPIC_ROBOT_DESCRIPTION,
                     TOPIC_SOLVER, foot_wrench_topic, namespace_of, resolve)

PROG = "starleth-analyze"
FEET = ("LF", "RF", "LH", "RH")
JOINTS = STARLETH_JOINT_NAMES
G = 9.81


def wrench_topic(foot: str) -> str:
    """The wrench topic of foot 'LF', 'RF', 'LH' or 'RH'."""
    return foot_wrench_topic(f"{foot}_foot")


# topic -> (kind, expected type, what is lost without it)
TOPICS = {wrench_topic(f): (("wrench", f), "geometry_msgs/msg/WrenchStamped",
                            f"the {f} contact force and gait plots") for f in FEET}
TOPICS.update({
    TOPIC_BASE_STATE: (("base", None), "nav_msgs/msg/Odometry", "the base trajectory plot"),
    TOPIC_JOINT_STATES: (("joints", None), "sensor_msgs/msg/JointState",
                         "the joint torque plot"),
    TOPIC_SOLVER: (("solver", None), "diagnostic_msgs/msg/DiagnosticArray",
                   "the solver iteration plot and the compute real-time factor"),
})
OPTIONAL_TOPICS = {TOPIC_ROBOT_DESCRIPTION: "std_msgs/msg/String"}

PLOTS = ("contact_forces", "gait", "base_trajectory", "joint_torques", "solver_iterations",
         "real_time_factor")
#: the largest magnitude of a recorded force [N], position [m], velocity, joint torque [N m]
#: or solver value taken as data; beyond it (or infinite) a value is garbage, left out
MAX_VALUE = 1e9
#: the real-time factor plot's windows per run at most: a run whose stamps span far more
#: than MAX_RTF_WINDOWS windows (garbage stamps: two messages 2e9 s apart) gets wider ones
MAX_RTF_WINDOWS = 100_000


class AnalysisError(BagError):
    """A bag that cannot be analysed: main() prints the message and exits with 1 (as for
    any BagError, a bag that cannot be read)."""


def warn(message: str) -> None:
    print(f"{PROG}: warning: {message}", file=sys.stderr)


# =========================================================================================
# reading
# =========================================================================================
class _Collector:
    """Per-topic lists filled while streaming, turned into arrays by Run."""

    def __init__(self, path: str):
        self.path = path
        self.wrench = {f: [] for f in FEET}          # (stamp, log, pub, fx, fy, fz)
        self.base = []                               # (stamp, log, pub, p3, q4, v3, w3)
        self.base_frames = None                      # (frame_id, child_frame_id)
        self.joint_stamps = []                       # (stamp, log, pub)
        self.joint_effort = []                       # rows in JOINT order (NaN if absent)
        self.joint_names = None                      # names as first seen
        self.solver = []                             # (stamp, log, pub, it, conv, res, st, mx, ac)
        self.urdf = None                             # from robot_description
        self.namespace = None                        # of the first StarlETH topic seen

    def on_channel(self, topic, type_name, make_decoder):
        """stream_bag's channel callback: a handler for the StarlETH topics of the run's
        namespace with the expected type, None for the rest."""
        rel = self.relative_topic(topic)
        if rel in TOPICS:
            kind, expected, _ = TOPICS[rel]
        elif rel in OPTIONAL_TOPICS:
            kind, expected = ("description", None), OPTIONAL_TOPICS[rel]
        else:
            return None
        if type_name != expected:
            warn(f"{self.path}: topic {topic} has type {type_name or '(no schema)'}, expected {expected}; "
                 "ignored")
            return None
        decode = make_decoder()
        return None if decode is None else _make_handler(kind, self, decode)

    def relative_topic(self, topic: str):
        """The relative StarlETH name (a key of TOPICS or OPTIONAL_TOPICS) of a topic of the
        bag, in the run's namespace (that of the first such topic: a bag of one robot under
        /robot1 reads like one at the root), or None."""
        for rel in (*TOPICS, *OPTIONAL_TOPICS):
            ns = namespace_of(topic, rel)
            if ns is None:
                continue
            if self.namespace is None and rel in TOPICS:
                self.namespace = ns
            if ns == self.namespace or (self.namespace is None and rel in OPTIONAL_TOPICS):
                return rel
        return None


def _stamp(msg):
    s = msg.header.stamp
    return s.sec * 1_000_000_000 + s.nanosec


def _to_float(s):
    try:
        return float(s)
    except (TypeError, ValueError, OverflowError):
        return math.nan


def _make_handler(kind, col: _Collector, decode):
    what, foot = kind
    if what == "wrench":
        rows = col.wrench[foot]

        def handle(m):
            msg = decode(m.data)
            f = msg.wrench.force
            rows.append((_stamp(msg), m.log_time, m.publish_time, f.x, f.y, f.z))
    elif what == "base":
        rows = col.base

        def handle(m):
            msg = decode(m.data)
            if col.base_frames is None:
                col.base_frames = (msg.header.frame_id, msg.child_frame_id)
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            v, w = msg.twist.twist.linear, msg.twist.twist.angular
            rows.append((_stamp(msg), m.log_time, m.publish_time,
                         p.x, p.y, p.z, q.x, q.y, q.z, q.w, v.x, v.y, v.z, w.x, w.y, w.z))
    elif what == "joints":
        state = {"names": None, "index": None, "identity": False}
        nan_row = [math.nan] * len(JOINTS)
        order = {n: i for i, n in enumerate(JOINTS)}

        def handle(m):
            msg = decode(m.data)
            names = msg.name
            if names != state["names"]:
                state["names"] = list(names)
                state["index"] = [order.get(n, -1) for n in names]
                state["identity"] = state["index"] == list(range(len(JOINTS)))
                if col.joint_names is None:
                    col.joint_names = list(names)
            col.joint_stamps.append((_stamp(msg), m.log_time, m.publish_time))
            eff = msg.effort
            idx = state["index"]
            if state["identity"] and len(eff) == len(idx):
                col.joint_effort.append(list(eff))
                return
            row = list(nan_row)
            if len(eff) == len(idx):
                for i, e in zip(idx, eff):
                    if i >= 0:
                        row[i] = e
            col.joint_effort.append(row)
    elif what == "solver":
        rows = col.solver

        def handle(m):
            msg = decode(m.data)
            for st in msg.status:
                kv = {v.key: v.value for v in st.values}
                if "iterations" not in kv:
                    continue
                conv = kv.get("converged")
                rows.append((_stamp(msg), m.log_time, m.publish_time,
                             _to_float(kv["iterations"]),
                             math.nan if conv is None else float(conv.strip().lower() in
                                                                 ("true", "1", "yes")),
                             _to_float(kv.get("residual")), _to_float(kv.get("step_time")),
                             _to_float(kv.get("max_iterations_step")),
                             _to_float(kv.get("active_contacts"))))
                return
    elif what == "description":
        def handle(m):
            if col.urdf is None:
                col.urdf = decode(m.data).data
    else:  # pragma: no cover
        raise ValueError(kind)
    return handle


class Run:
    """One bag, decoded: arrays with time in seconds relative to the first message."""

    def __init__(self, path: str, label: str, salvage: bool = False):
        self.path, self.label = path, label
        col = _Collector(path)
        t_read = time.perf_counter()
        bag = stream_bag(path, col.on_channel, salvage, warn)
        self.read_seconds = time.perf_counter() - t_read
        self.truncated = bag.truncated
        self.files = bag.files
        self.file_size = sum(os.path.getsize(p) for p in bag.files)
        self.messages = bag.total
        self.counts = dict(bag.counts)
        self.types = dict(bag.types)
        self.metadata = bag.metadata
        self.urdf = col.urdf
        if self.urdf is None:        # sim_node's recordings carry it as an attachment
            for name, data in bag.attachments.items():
                if name.endswith(".urdf"):
                    try:
                        self.urdf = data.decode("utf-8")
                        break
                    except UnicodeDecodeError:
                        pass
        for topic, (n, err) in bag.decode_errors.items():
            warn(f"{path}: {n} message(s) on {topic} could not be read ({err})")
        #: the namespace of the StarlETH topics ('' at the root, '/robot1') and their names
        self.namespace = col.namespace or ""
        self.topic_names = {rel: resolve(rel, self.namespace) for rel in TOPICS}
        self.missing = [self.topic_names[t] for t in TOPICS
                        if not self.counts.get(self.topic_names[t])]

        def arr(rows, width):
            try:
                a = np.array(rows, dtype=float) if rows else np.zeros((0, width))
            except (ValueError, TypeError, OverflowError) as e:
                raise AnalysisError(f"{path}: messages whose fields are not numbers (the "
                                    f"bag's schema is not the ROS one?): {e}") from None
            return a.reshape(-1, width)

        # raw (stamp ns, log ns, pub ns) per series; int64 for exact comparisons
        def times(rows):
            try:
                a = np.array([r[:3] for r in rows], dtype=np.int64).reshape(-1, 3)
            except (ValueError, TypeError, OverflowError) as e:
                raise AnalysisError(f"{path}: message stamps that are not int64 "
                                    f"nanoseconds: {e}") from None
            stamp = a[:, 0]
            if stamp.size and not stamp.any():   # unstamped messages: use the log time
                stamp = a[:, 1].copy()
            return stamp, a[:, 1], a[:, 2]

        series = {}
        for foot in FEET:
            rows = col.wrench[foot]
            series[("wrench", foot)] = (times(rows), arr([r[3:] for r in rows], 3))
        series[("base", None)] = (times(col.base), arr([r[3:] for r in col.base], 13))
        series[("joints", None)] = (times(col.joint_stamps),
                                    arr(col.joint_effort, len(JOINTS)))
        series[("solver", None)] = (times(col.solver), arr([r[3:] for r in col.solver], 6))
        series = self._drop_unusable(series)
        firsts = [s[0][0].min() for s in series.values() if s[0][0].size]
        self.t0_ns = int(min(firsts)) if firsts else 0
        self._series = {}
        for key, ((stamp, log, pub), data) in series.items():
            order = np.argsort(stamp, kind="stable")
            if not np.all(order == np.arange(order.size)):
                stamp, log, pub, data = stamp[order], log[order], pub[order], data[order]
            self._series[key] = {"stamp": stamp, "log": log, "pub": pub, "data": data,
                                 "t": (stamp - self.t0_ns) * 1e-9}
        self.base_frames = col.base_frames or ("", "")
        self.joint_names = col.joint_names
        self.window = (None, None)

    def _drop_unusable(self, series: dict) -> dict:
        """series without the garbage a bag may hold, with a counted warning per topic: a
        wrench or base state holding a NaN, an infinite value or one beyond MAX_VALUE is
        left out; in joint efforts and solver values (where NaN means 'not recorded') an
        infinite or absurd value becomes NaN (the solver's residual is kept as recorded)."""
        rel = {kind: name for name, (kind, _, _) in TOPICS.items()}
        out = {}
        for key, ((stamp, log, pub), data) in series.items():
            with np.errstate(invalid="ignore"):
                bad = np.abs(data) > MAX_VALUE
            if key[0] == "solver":                   # a residual may be anything
                bad[:, 2] = False
            if key[0] in ("wrench", "base"):
                bad |= np.isnan(data)
            rows = bad.any(axis=1)
            n = int(rows.sum())
            if n:
                if key[0] in ("wrench", "base"):
                    keep = ~rows
                    stamp, log, pub, data = stamp[keep], log[keep], pub[keep], data[keep]
                    what = "left out"
                else:
                    data = np.where(bad, np.nan, data)
                    what = "those values left out"
                warn(f"{self.path}: {n} message(s) on {resolve(rel[key], self.namespace)} "
                     f"hold NaN, infinite or absurd values (beyond {MAX_VALUE:g}); {what}")
            out[key] = ((stamp, log, pub), data)
        return out

    @classmethod
    def from_arrays(cls, label, t, base=None, wrench=None, effort=None,
                    base_frames=("world", "base")):
        """A run made from arrays instead of a bag (e.g. a re-simulation, starleth-replay),
        for the plots: t [s] per row; base rows (position 3, quaternion x y z w, linear
        twist 3, angular twist 3), wrench {foot: rows (f_x, f_y, f_z)}, effort rows in
        JOINTS order; missing ones are empty series."""
        run = cls.__new__(cls)
        run.path, run.label = "", label
        run.truncated, run.files, run.file_size, run.messages = False, [], 0, 0
        run.counts, run.types, run.metadata, run.urdf = {}, {}, {}, None
        run.namespace, run.topic_names, run.missing = "", {}, []
        run.base_frames, run.joint_names, run.window = base_frames, list(JOINTS), (None, None)
        run.t0_ns, run.read_seconds = 0, 0.0
        t = np.asarray(t, dtype=float)
        stamp = np.round(t * 1e9).astype(np.int64)

        def entry(data, width):
            if data is None:
                z = np.zeros(0, dtype=np.int64)
                return {"stamp": z, "log": z, "pub": z, "data": np.zeros((0, width)),
                        "t": np.zeros(0)}
            return {"stamp": stamp, "log": stamp, "pub": stamp,
                    "data": np.asarray(data, dtype=float).reshape(len(t), width), "t": t}
        run._series = {("wrench", f): entry((wrench or {}).get(f), 3) for f in FEET}
        run._series[("base", None)] = entry(base, 13)
        run._series[("joints", None)] = entry(effort, len(JOINTS))
        run._series[("solver", None)] = entry(None, 6)
        return run

    # -- access ------------------------------------------------------------------------------
    def series(self, what, foot=None):
        """dict with t [s], stamp/log/pub [ns] and data rows (time window applied)."""
        return self._series[(what, foot)]

    def apply_window(self, tmin=None, tmax=None):
        if tmin is None and tmax is None:
            return
        self.window = (tmin, tmax)
        for key, s in self._series.items():
            t = s["t"]
            m = np.ones(t.shape, dtype=bool)
            if tmin is not None:
                m &= t >= tmin
            if tmax is not None:
                m &= t <= tmax
            self._series[key] = {k: v[m] for k, v in s.items()}

    def has(self, what, foot=None) -> bool:
        return self._series[(what, foot)]["t"].size > 0

    def normal_force(self, foot):
        s = self.series("wrench", foot)
        return s["t"], s["data"][:, 2]

    @property
    def control_period(self):
        """Control period [s]: from the recording's metadata, else the stamps' median step."""
        md = self.metadata.get("starleth_sim", {})
        cp = _to_float(md.get("control_period"))
        if math.isfinite(cp) and cp > 0:
            return cp
        for key in (("joints", None), ("wrench", "LF"), ("base", None), ("solver", None)):
            t = self._series[key]["t"]
            if t.size > 1:
                d = np.diff(t)
                d = d[d > 0]
                if d.size:
                    return float(np.median(d))
        return math.nan

    def sim_node_parameters(self) -> dict:
        try:
            params = json.loads(self.metadata.get("starleth_sim", {}).get("parameters", "{}"))
        except (ValueError, TypeError, RecursionError):
            return {}
        return params if isinstance(params, dict) else {}

    def sim_node_summary(self) -> dict:
        out = {}
        for k, v in self.metadata.get("starleth_sim_summary", {}).items():
            try:
                out[k] = json.loads(v)
            except (ValueError, TypeError, RecursionError):
                out[k] = v
        return out


# =========================================================================================
# analysis
# =========================================================================================
def quat_rotate(q, v):
    """Rotate vectors v (n, 3) by unit quaternions q (n, 4: x y z w)."""
    u, w = q[:, :3], q[:, 3:4]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def horizontal_velocity(run: Run, twist_frame: str = "auto"):
    """(t, world-frame v_x, v_y) of the base from the Odometry twist."""
    s = run.series("base")
    d = s["data"]
    q, v = d[:, 3:7], d[:, 7:10]
    frame = twist_frame
    if frame == "auto":
        parent, child = run.base_frames
        frame = "parent" if (not child or child == parent) else "child"
    if frame == "child":
        n = np.linalg.norm(q, axis=1, keepdims=True)
        n[n == 0] = 1.0
        v = quat_rotate(q / n, v)
    return s["t"], v[:, 0], v[:, 1], frame


def stance_intervals(t, fz, threshold=5.0, min_phase=0.02):
    """Stance intervals [(t_start, t_end)] where fz > threshold; swing gaps and stance blips
    shorter than min_phase [s] are removed (gaps merged first, also at the ends). Returns
    (intervals, touchdowns) where a touchdown is a stance interval that does not begin at
    the first sample."""
    t = np.asarray(t, dtype=float)
    if t.size == 0:
        return [], 0
    dt = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    s = np.asarray(fz) > threshold
    d = np.diff(np.concatenate(([0], s.astype(np.int8), [0])))
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1
    iv = [[t[a], t[b] + dt, a] for a, b in zip(starts, ends)]
    merged = []
    for x in iv:
        if merged and x[0] - merged[-1][1] < min_phase - 1e-12:
            merged[-1][1] = x[1]
        else:
            merged.append(x)
    # a swing shorter than min_phase at either end (e.g. the first sample of a recording,
    # before any contact force was computed) is no phase of its own either
    if merged and 0 < merged[0][0] - t[0] < min_phase - 1e-12:
        merged[0][0], merged[0][2] = t[0], 0
    if merged and 0 < t[-1] + dt - merged[-1][1] < min_phase - 1e-12:
        merged[-1][1] = t[-1] + dt
    kept = [x for x in merged if x[1] - x[0] >= min_phase - 1e-12 or x[2] == 0
            or x[1] >= t[-1] + dt - 1e-12]
    touchdowns = sum(1 for x in kept if x[2] > 0)
    return [(a, b) for a, b, _ in kept], touchdowns


def urdf_info(urdf: str | None):
    """(total mass [kg], {joint: effort limit [N m]}) from URDF text, or (None, {})."""
    if not urdf:
        return None, {}
    try:
        root = ET.fromstring(urdf)
    except ET.ParseError:
        return None, {}
    mass = 0.0
    for link in root.iter("link"):
        m = link.find("inertial/mass")
        if m is not None:
            mass += _to_float(m.get("value"))
    limits = {}
    for j in root.iter("joint"):
        lim = j.find("limit")
        if lim is not None and lim.get("effort") is not None:
            limits[j.get("name")] = _to_float(lim.get("effort"))
    return (mass if math.isfinite(mass) and mass > 0 else None), limits


def _package_urdf():
    try:
        from ..physics.description import urdf_path
        with open(urdf_path()) as f:
            return f.read()
    except Exception:
        return None


def real_time_factor(run: Run) -> dict:
    """What the bag says about sim time vs wall time (see the module docstring)."""
    out = {"source": None, "value": None}
    ref = None
    for key in (("joints", None), ("wrench", "LF"), ("base", None), ("solver", None)):
        s = run._series[key]
        if s["t"].size > 1:
            ref = s
            break
    if ref is not None:
        stamp = ref["stamp"]
        for name, label in (("pub", "publish_time"), ("log", "log_time")):
            wall = ref[name]
            if wall.any() and not np.array_equal(wall, stamp):
                d_wall = (wall[-1] - wall[0]) * 1e-9
                d_sim = (stamp[-1] - stamp[0]) * 1e-9
                if d_wall > 0 and d_sim > 0:
                    out.update(source=label, value=d_sim / d_wall,
                               sim=(stamp - stamp[0]) * 1e-9, wall=(wall - wall[0]) * 1e-9,
                               t=ref["t"])
                    break
    s = run.series("solver")
    st = s["data"][:, 3] if s["t"].size else np.zeros(0)
    ok = np.isfinite(st)
    cp = run.control_period
    if ok.sum() > 0 and st[ok].sum() > 0 and math.isfinite(cp):
        out["compute"] = {"value": cp * ok.sum() / st[ok].sum(),
                          "mean_step_time": float(st[ok].mean()),
                          "max_step_time": float(st[ok].max()),
                          "t": s["t"][ok], "wall": np.cumsum(st[ok]),
                          "sim": np.arange(1, ok.sum() + 1) * cp}
    summ = run.sim_node_summary()
    pm = _to_float(summ.get("period_mean_ms"))
    if math.isfinite(pm) and pm > 0 and math.isfinite(cp):
        out["loop"] = {"value": cp * 1e3 / pm, "period_mean_ms": pm}
    return out


def _rtf_window(span, window):
    """The window [s] of the real-time factor over `span` s of sim time: `window`, or wider
    where the span would hold more than MAX_RTF_WINDOWS of them."""
    return max(window, span / MAX_RTF_WINDOWS) if math.isfinite(span) else window


def _windowed_rate(t_ref, sim, wall, window):
    """Δsim/Δwall over consecutive windows of `window` seconds of t_ref (a last partial
    window shorter than half a window is left out; at most MAX_RTF_WINDOWS windows: wider
    ones where the stamps span more)."""
    if t_ref.size < 2:
        return np.zeros(0), np.zeros(0)
    window = _rtf_window(float(t_ref[-1] - t_ref[0]), window)
    edges = np.arange(t_ref[0], t_ref[-1], window)
    if t_ref[-1] - edges[-1] >= 0.5 * window or edges.size == 1:
        edges = np.append(edges, t_ref[-1])
    idx = np.unique(np.clip(np.searchsorted(t_ref, edges), 0, t_ref.size - 1))
    if idx.size < 2:
        idx = np.array([0, t_ref.size - 1])
    ds, dw = np.diff(sim[idx]), np.diff(wall[idx])
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(dw > 0, ds / dw, np.nan)
    return 0.5 * (t_ref[idx][1:] + t_ref[idx][:-1]), r


def summarise(run: Run, threshold=5.0, min_phase=0.02, twist_frame="auto") -> dict:
    """The numbers of the text summary (also written by --json)."""
    S = {"label": run.label, "path": run.path, "file_size": run.file_size,
         "messages": run.messages, "read_seconds": round(run.read_seconds, 3),
         "truncated": run.truncated, "missing_topics": list(run.missing),
         "topics": {n: run.counts.get(n, 0) for n in run.topic_names.values()},
         "window": list(run.window)}
    ts = [run._series[k]["t"] for k in run._series if run._series[k]["t"].size]
    if ts:
        t_start, t_end = min(float(t[0]) for t in ts), max(float(t[-1]) for t in ts)
        S["sim_time"] = {"start": t_start, "end": t_end, "duration": t_end - t_start,
                         "t0_stamp": run.t0_ns * 1e-9, "control_period": run.control_period}
    S["control_steps"] = int(run.series("joints")["t"].size)
    urdf, mass_source = run.urdf, "the bag's URDF"
    if urdf is None:
        urdf, mass_source = _package_urdf(), "the package URDF (none in the bag)"
    mass, limits = urdf_info(urdf)
    S.update(_contact_summary(run, threshold, min_phase))
    if mass:
        S["mass"], S["weight"], S["mass_source"] = mass, mass * G, mass_source
    if run.has("base"):
        S["base"] = _base_summary(run, twist_frame)
    if run.series("joints")["t"].size:
        S["joints"] = _joint_summary(run, limits)
    if run.has("solver"):
        S["solver"] = _solver_summary(run)
    S["real_time_factor"] = _rtf_summary(run)
    S.update(_sim_node_summary(run))
    return S


def _contact_summary(run: Run, threshold, min_phase) -> dict:
    """Per foot: normal force, stance fraction, touchdowns; the total mean normal force."""
    feet, total = {}, 0.0
    for foot in FEET:
        if not run.has("wrench", foot):
            continue
        t, fz = run.normal_force(foot)
        iv, td = stance_intervals(t, fz, threshold, min_phase)
        dur = (t[-1] - t[0] + run.control_period) if t.size > 1 else 0.0
        stance = sum(b - a for a, b in iv)
        feet[foot] = {"mean_normal_force": float(fz.mean()), "max_normal_force": float(fz.max()),
                      "stance_fraction": float(stance / dur) if dur > 0 else math.nan,
                      "touchdowns": int(td), "stance_phases": len(iv)}
        total += float(fz.mean())
    if not feet:
        return {}
    return {"feet": feet, "contact_threshold": threshold,
            "total_mean_normal_force": total if len(feet) == 4 else None}


def _base_summary(run: Run, twist_frame) -> dict:
    """Base path: distance, path length, speeds, heights, frames."""
    p = run.series("base")["data"][:, 0:3]
    t, vx, vy, frame = horizontal_velocity(run, twist_frame)
    sp = np.hypot(vx, vy)
    seg = np.hypot(np.diff(p[:, 0]), np.diff(p[:, 1]))
    dur = float(t[-1] - t[0]) if t.size > 1 else 0.0
    net = float(np.hypot(*(p[-1, :2] - p[0, :2])))
    return {"start": p[0].tolist(), "end": p[-1].tolist(), "distance": net,
            "path_length": float(seg.sum()),
            "mean_speed_displacement": net / dur if dur > 0 else math.nan,
            "mean_speed": float(sp.mean()), "max_speed": float(sp.max()),
            "height_min": float(p[:, 2].min()), "height_max": float(p[:, 2].max()),
            "height_mean": float(p[:, 2].mean()), "twist_frame": frame,
            "frames": list(run.base_frames)}


def _joint_summary(run: Run, limits) -> dict:
    """Joint torques: max |τ| and RMS per joint and overall, time at the effort limit."""
    e = run.series("joints")["data"]
    with np.errstate(invalid="ignore"):
        absmax = np.nanmax(np.abs(e), axis=0) if np.isfinite(e).any() else \
            np.full(len(JOINTS), np.nan)
        rms = np.sqrt(np.nanmean(e * e, axis=0)) if np.isfinite(e).any() else absmax
    J = {"max_abs": {n: float(x) for n, x in zip(JOINTS, absmax)},
         "rms": {n: float(x) for n, x in zip(JOINTS, rms)}}
    if np.isfinite(absmax).any():
        i = int(np.nanargmax(absmax))
        J["max_abs_overall"], J["max_abs_joint"] = float(absmax[i]), JOINTS[i]
        J["rms_overall"] = float(np.sqrt(np.nanmean(e * e)))
    if limits and all(n in limits for n in JOINTS):
        lim = np.array([limits[n] for n in JOINTS])
        fin = np.isfinite(e)
        with np.errstate(invalid="ignore"):
            sat = (np.abs(e) >= lim * (1 - 1e-6)) & fin
        J["at_effort_limit_fraction"] = float(sat.sum() / max(fin.sum(), 1))
        J["effort_limit"] = float(lim.max())
    if run.joint_names is not None:
        unknown = [n for n in run.joint_names if n not in JOINTS]
        if unknown:
            J["ignored_joints"] = unknown
    return J


def _solver_summary(run: Run) -> dict:
    """Prox iterations per step (mean, median, p95, max), non-converged steps, residual."""
    d = run.series("solver")["data"]
    it = d[:, 0]
    fin = it[np.isfinite(it)]
    conv = d[:, 1]
    return {"steps": int(it.size), "iterations_mean": float(fin.mean()) if fin.size else None,
            "iterations_median": float(np.median(fin)) if fin.size else None,
            "iterations_p95": float(np.percentile(fin, 95)) if fin.size else None,
            "iterations_max": float(fin.max()) if fin.size else None,
            "nonconverged": int(np.sum(conv[np.isfinite(conv)] == 0)),
            "residual_max": float(np.nanmax(d[:, 2])) if np.isfinite(d[:, 2]).any() else None}


def _rtf_summary(run: Run) -> dict:
    rtf = real_time_factor(run)
    R = {"source": rtf["source"], "value": rtf["value"]}
    if "compute" in rtf:
        c = rtf["compute"]
        R["compute"] = c["value"]
        R["mean_step_time"] = c["mean_step_time"]
        R["max_step_time"] = c["max_step_time"]
    if "loop" in rtf:
        R["loop"] = rtf["loop"]["value"]
        R["loop_period_mean_ms"] = rtf["loop"]["period_mean_ms"]
    return R


def _sim_node_summary(run: Run) -> dict:
    """sim_node's parameters and final counters as recorded in the bag's metadata."""
    out = {}
    params = run.sim_node_parameters()
    if params:
        out["sim_node"] = {k: params.get(k) for k in ("physics", "mode", "real_time_factor")
                           if k in params}
    summ = run.sim_node_summary()
    if summ:
        out.setdefault("sim_node", {}).update(
            {k: summ[k] for k in ("steps", "lockstep_timeouts", "commands_rejected",
                                  "simulation_errors", "overruns") if k in summ})
    return out


# =========================================================================================
# plots
# =========================================================================================
def _color(i):
    return f"C{i % 10}"


def _finish(ax, xlabel, ylabel, title, legend=True):
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    if legend:
        handles, _ = ax.get_legend_handles_labels()
        if handles:
            ax.legend(fontsize="small", loc="best")


def _suffix(runs):
    w = runs[0].window
    if w == (None, None):
        return ""
    a = "start" if w[0] is None else f"{w[0]:g} s"
    b = "end" if w[1] is None else f"{w[1]:g} s"
    return f" ({a} .. {b})"


def plot_contact_forces(plt, runs, opts):
    have = [r for r in runs if any(r.has("wrench", f) for f in FEET)]
    if not have:
        return None
    fig, axes = plt.subplots(2, 2, figsize=(12, 7), sharex=True, squeeze=False)
    for ax, foot in zip(axes.flat, FEET):
        for i, r in enumerate(runs):
            if r.has("wrench", foot):
                t, fz = r.normal_force(foot)
                ax.plot(t, fz, color=_color(i), lw=0.9, label=r.label)
        ax.axhline(opts.threshold, color="0.4", ls=":", lw=0.8,
                   label=f"contact threshold {opts.threshold:g} N")
        _finish(ax, "time [s]", "normal force F_z [N]", f"{foot} foot")
    fig.suptitle("Contact normal force per foot (world z)" + _suffix(runs))
    fig.tight_layout()
    return fig


def plot_single_foot(plt, runs, opts):
    foot = opts.foot
    have = [r for r in runs if r.has("wrench", foot)]
    if not have:
        return None
    fig, ax = plt.subplots(figsize=(9, 4.5))
    for i, r in enumerate(runs):
        if r.has("wrench", foot):
            t, fz = r.normal_force(foot)
            ax.plot(t, fz, color=_color(i), lw=1.0, label=r.label)
    _finish(ax, "time [s]", "normal force F_z [N]",
            f"{foot} foot normal force" + _suffix(runs))
    fig.tight_layout()
    return fig


def plot_gait(plt, runs, opts):
    from matplotlib.patches import Patch
    have = [r for r in runs if any(r.has("wrench", f) for f in FEET)]
    if not have:
        return None
    n = len(runs)
    fig, ax = plt.subplots(figsize=(12, 1.2 + 0.5 * 4 * max(n, 1) + 0.6))
    ticks, labels = [], []
    row_h = 1.0 / n
    for k, foot in enumerate(FEET):
        y0 = (len(FEET) - 1 - k)
        for i, r in enumerate(runs):
            y = y0 + (n - 1 - i) * row_h
            if r.has("wrench", foot):
                t, fz = r.normal_force(foot)
                iv, _ = stance_intervals(t, fz, opts.threshold, opts.min_phase)
                ax.broken_barh([(a, b - a) for a, b in iv], (y + 0.1 * row_h, 0.8 * row_h),
                               facecolors=_color(i))
        if n > 1 and k:
            ax.axhline(y0 + 1, color="0.3", lw=0.8)
        ticks.append(y0 + 0.5)
        labels.append(foot)
    ax.set_yticks(ticks)
    ax.set_yticklabels(labels)
    ax.set_ylim(0, len(FEET))
    tmins = [float(r.normal_force(f)[0][0]) for r in have for f in FEET if r.has("wrench", f)]
    tmaxs = [float(r.normal_force(f)[0][-1]) for r in have for f in FEET if r.has("wrench", f)]
    ax.set_xlim(min(tmins), max(tmaxs) + 1e-9)
    handles = [Patch(color=_color(i), label=f"{r.label}: stance") for i, r in enumerate(runs)]
    ax.legend(handles=handles, fontsize="small", loc="upper right")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("foot (bar = stance, gap = swing)")
    ax.set_title(f"Gait diagram: stance where F_z > {opts.threshold:g} N (phases shorter "
                 f"than {opts.min_phase * 1e3:g} ms merged)" + _suffix(runs))
    ax.grid(True, axis="x", alpha=0.3)
    fig.tight_layout()
    return fig


def plot_base(plt, runs, opts):
    have = [r for r in runs if r.has("base")]
    if not have:
        return None
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    ax_xy, ax_v, ax_h = axes
    for i, r in enumerate(runs):
        if not r.has("base"):
            continue
        p = r.series("base")["data"][:, 0:3]
        t = r.series("base")["t"]
        ax_xy.plot(p[:, 0], p[:, 1], color=_color(i), lw=1.0, label=r.label)
        ax_xy.plot(p[0, 0], p[0, 1], "o", color=_color(i), ms=5,
                   label="start" if i == 0 else None)
        ax_xy.plot(p[-1, 0], p[-1, 1], "x", color=_color(i), ms=7,
                   label="end" if i == 0 else None)
        tv, vx, vy, _ = horizontal_velocity(r, opts.twist_frame)
        ax_v.plot(tv, np.hypot(vx, vy), color=_color(i), lw=0.9, label=r.label)
        ax_h.plot(t, p[:, 2], color=_color(i), lw=0.9, label=r.label)
    ax_xy.set_aspect("equal", adjustable="datalim")
    _finish(ax_xy, "x [m]", "y [m]", "Base trajectory (world x-y)")
    _finish(ax_v, "time [s]", "horizontal speed [m/s]", "Base horizontal speed |(v_x, v_y)|")
    _finish(ax_h, "time [s]", "height z [m]", "Base height")
    fig.suptitle("Base state (/starleth/base_state)" + _suffix(runs))
    fig.tight_layout()
    return fig


def plot_joint_torques(plt, runs, opts):
    have = [r for r in runs if r.has("joints")]
    if not have:
        return None
    fig, axes = plt.subplots(4, 3, figsize=(14, 10), sharex=True, squeeze=False)
    for j, name in enumerate(JOINTS):
        ax = axes[j // 3][j % 3]
        for i, r in enumerate(runs):
            if r.has("joints"):
                s = r.series("joints")
                e = s["data"][:, j]
                if np.isfinite(e).any():
                    ax.plot(s["t"], e, color=_color(i), lw=0.7, label=r.label)
        _finish(ax, "time [s]" if j >= 9 else "", "torque [N m]", name)
        if j < 9:
            ax.set_xlabel("time [s]", fontsize="x-small")
    fig.suptitle("Joint torques (/joint_states effort)" + _suffix(runs))
    fig.tight_layout()
    return fig


def plot_solver(plt, runs, opts):
    have = [r for r in runs if r.has("solver")]
    if not have:
        return None
    fig, (ax_h, ax_t) = plt.subplots(1, 2, figsize=(13, 4.5))
    its = [r.series("solver")["data"][:, 0] for r in have]
    its = [x[np.isfinite(x)] for x in its]
    hi = max((float(x.max()) for x in its if x.size), default=1.0)
    lo = min(min((float(x.min()) for x in its if x.size), default=0.0), 0.0)   # < 0: garbage
    if hi - lo <= 80:
        bins = np.arange(math.floor(lo) - 0.5, max(hi, lo) + 1.5, 1.0)
    else:
        bins = np.linspace(lo, hi * 1.0001 if hi > 0 else hi + 1.0, 61)
    for i, r in enumerate(runs):
        if not r.has("solver"):
            continue
        s = r.series("solver")
        it = s["data"][:, 0]
        ok = np.isfinite(it)
        if ok.any():
            ax_h.hist(it[ok], bins=bins, histtype="stepfilled" if len(have) == 1 else "step",
                      color=_color(i), alpha=0.6 if len(have) == 1 else 1.0, lw=1.2,
                      label=f"{r.label} (mean {it[ok].mean():.1f})")
        ax_t.plot(s["t"][ok], it[ok], color=_color(i), lw=0.6, label=r.label)
    _finish(ax_h, "prox iterations per control step [-]", "control steps [-]",
            "Solver iterations histogram")
    _finish(ax_t, "time [s]", "prox iterations per control step [-]",
            "Solver iterations over time")
    fig.suptitle("Solver (/starleth/solver)" + _suffix(runs))
    fig.tight_layout()
    return fig


def plot_rtf(plt, runs, opts):
    data = [(i, r, real_time_factor(r)) for i, r in enumerate(runs)]
    data = [(i, r, x) for i, r, x in data if x["source"] or "compute" in x]
    if not data:
        return None
    fig, (ax_a, ax_b) = plt.subplots(1, 2, figsize=(13, 4.5))
    top = 0.0
    # windows: --rtf-window, but at least 10 per run for short runs, at most
    # MAX_RTF_WINDOWS for long ones
    span = max((float(r.series(*k)["t"][-1] - r.series(*k)["t"][0])
                for _, r, _ in data for k in (("joints", None), ("wrench", "LF"),
                                              ("base", None), ("solver", None))
                if r.series(*k)["t"].size > 1), default=0.0)
    window = min(opts.rtf_window, span / 10) if span > 0 else opts.rtf_window
    window = _rtf_window(span, window)
    for i, r, x in data:
        if x["source"]:
            ax_a.plot(x["wall"], x["sim"], color=_color(i), lw=1.0,
                      label=f"{r.label} (wall = {x['source']}, RTF {x['value']:.2f})")
            tc, rr = _windowed_rate(x["t"], x["sim"], x["wall"], window)
            ax_b.plot(tc, rr, color=_color(i), lw=1.0, marker=".", label=f"{r.label}")
            top = max(top, float(x["wall"][-1]))
        if "compute" in x:
            c = x["compute"]
            ax_a.plot(c["wall"], c["sim"], color=_color(i), lw=1.0, ls="--",
                      label=f"{r.label} (physics compute only, RTF {c['value']:.1f})")
            tc, rr = _windowed_rate(c["t"], c["sim"], c["wall"], window)
            ax_b.plot(tc, rr, color=_color(i), lw=1.0, ls="--", marker=".",
                      label=f"{r.label} (physics compute only)")
            top = max(top, float(c["wall"][-1]))
    ax_a.plot([0, top], [0, top], color="0.5", ls=":", lw=1.0, label="real time (RTF 1)")
    ax_b.axhline(1.0, color="0.5", ls=":", lw=1.0, label="real time (RTF 1)")
    _finish(ax_a, "wall time [s]", "sim time [s]", "Sim time vs wall time")
    _finish(ax_b, "sim time [s]", "real-time factor [-]",
            f"Real-time factor (Δsim/Δwall per {window:.3g} s of sim time)")
    ax_b.set_yscale("log")
    fig.suptitle("Real-time factor (solid: wall clock of the messages; dashed: solver "
                 "step_time, physics only)" + _suffix(runs), fontsize="medium")
    fig.tight_layout()
    return fig


FIGURES = {"contact_forces": plot_contact_forces, "gait": plot_gait,
           "base_trajectory": plot_base, "joint_torques": plot_joint_torques,
           "solver_iterations": plot_solver, "real_time_factor": plot_rtf}


def _pyplot():
    try:
        import matplotlib
        matplotlib.use("Agg", force=True)
        import matplotlib.pyplot as plt
    except ImportError:
        raise AnalysisError("matplotlib is needed for the plots (pip install matplotlib); "
                            "--no-plots prints the summary only") from None
    return plt


def make_figures(runs, opts) -> dict:
    """{name: matplotlib Figure} of every plot that has data (caller closes them)."""
    plt = _pyplot()
    figs = {}
    for name, fn in FIGURES.items():
        fig = fn(plt, runs, opts)
        if fig is not None:
            figs[name] = fig
    if len(runs) > 1 or opts.foot_given:
        fig = plot_single_foot(plt, runs, opts)
        if fig is not None:
            figs[f"normal_force_{opts.foot}"] = fig
    return figs


def save_figures(runs, opts, out_dir) -> dict:
    plt = _pyplot()
    os.makedirs(out_dir, exist_ok=True)
    written = {}
    for name, fig in make_figures(runs, opts).items():
        path = os.path.join(out_dir, f"{name}.png")
        fig.savefig(path, dpi=opts.dpi)
        plt.close(fig)
        written[name] = path
    return written


# =========================================================================================
# text summary
# =========================================================================================
def _f(x, fmt=".2f", none="n/a"):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return none
    return format(x, fmt)


def format_summary(S: dict) -> str:
    L = []
    mb = S["file_size"] / 1e6
    L.append(f"== {S['label']}: {S['path']} ({mb:.1f} MB, {S['messages']} messages"
             f"{', TRUNCATED' if S['truncated'] else ''}; read in {S['read_seconds']:.2f} s) ==")
    if "sim_node" in S:
        L.append("  sim_node          " + ", ".join(f"{k} {v}" for k, v in S["sim_node"].items()))
    st = S.get("sim_time")
    if st:
        cp = st["control_period"]
        rate = f" at {1 / cp:.0f} Hz" if cp and math.isfinite(cp) and cp > 0 else ""
        L.append(f"  sim time          {st['start']:.3f} .. {st['end']:.3f} s "
                 f"({st['duration']:.3f} s; {S['control_steps']} joint states{rate})")
    if S["missing_topics"]:
        L.append(f"  missing topics    {', '.join(S['missing_topics'])}")
    if "feet" in S:
        L.append(f"  contact           normal force F_z [N], stance = F_z > "
                 f"{S['contact_threshold']:g} N")
        for foot, d in S["feet"].items():
            L.append(f"    {foot}   mean {d['mean_normal_force']:7.1f}   max "
                     f"{d['max_normal_force']:7.1f}   stance {100 * d['stance_fraction']:5.1f} %"
                     f"   touchdowns {d['touchdowns']}")
        tot = S.get("total_mean_normal_force")
        if tot is not None:
            line = f"    sum of means {tot:.1f} N"
            if S.get("weight"):
                line += (f" = {100 * tot / S['weight']:.1f} % of the weight "
                         f"({S['mass']:.2f} kg x {G} m/s^2 = {S['weight']:.1f} N, "
                         f"{S['mass_source']})")
            L.append(line)
    b = S.get("base")
    if b:
        L.append(f"  base              start ({b['start'][0]:.2f}, {b['start'][1]:.2f}, "
                 f"{b['start'][2]:.3f}) m, end ({b['end'][0]:.2f}, {b['end'][1]:.2f}, "
                 f"{b['end'][2]:.3f}) m")
        L.append(f"                    distance {b['distance']:.2f} m (path {b['path_length']:.2f}"
                 f" m), mean speed {b['mean_speed_displacement']:.3f} m/s by displacement, "
                 f"{b['mean_speed']:.3f} m/s by twist (max {b['max_speed']:.3f})")
        L.append(f"                    height {b['height_min']:.3f} .. {b['height_max']:.3f} m"
                 f" (mean {b['height_mean']:.3f}); twist frame: {b['twist_frame']}")
    j = S.get("joints")
    if j and "max_abs_overall" in j:
        line = (f"  joint torques     max |tau| {j['max_abs_overall']:.2f} N m "
                f"({j['max_abs_joint']}), RMS {j['rms_overall']:.2f} N m")
        if "at_effort_limit_fraction" in j:
            line += (f"; at the effort limit ({j['effort_limit']:g} N m) "
                     f"{100 * j['at_effort_limit_fraction']:.2f} % of samples")
        L.append(line)
    s = S.get("solver")
    if s:
        L.append(f"  solver            iterations per control step mean "
                 f"{_f(s['iterations_mean'], '.1f')}, median {_f(s['iterations_median'], '.0f')},"
                 f" p95 {_f(s['iterations_p95'], '.0f')}, max {_f(s['iterations_max'], '.0f')};"
                 f" not converged {s['nonconverged']} of {s['steps']}; max residual "
                 f"{_f(s['residual_max'], '.2e')}")
    r = S["real_time_factor"]
    parts = []
    if r["source"]:
        parts.append(f"{r['value']:.2f} (sim time / wall time, wall = message {r['source']})")
    else:
        parts.append("no wall clock in the bag (message times = sim stamps)")
    if "compute" in r:
        parts.append(f"physics compute only {r['compute']:.1f} (solver step_time mean "
                     f"{r['mean_step_time'] * 1e3:.3f} ms, max {r['max_step_time'] * 1e3:.2f} ms)")
    if "loop" in r:
        parts.append(f"realtime loop {r['loop']:.3f} (mean period "
                     f"{r['loop_period_mean_ms']:.3f} ms)")
    L.append("  real-time factor  " + "; ".join(parts))
    return "\n".join(L)


# =========================================================================================
# command line
# =========================================================================================
def _default_out(paths):
    first = os.path.abspath(paths[0]).rstrip(os.sep)
    stems = [os.path.splitext(os.path.basename(os.path.abspath(p).rstrip(os.sep)))[0]
             for p in paths]
    name = "_vs_".join(stems[:3]) + ("_etc" if len(stems) > 3 else "")
    return os.path.join(os.path.dirname(first), name[:100] + "_analysis")


def _labels(paths, labels):
    if labels:
        return list(labels)
    stems = [os.path.splitext(os.path.basename(os.path.abspath(p).rstrip(os.sep)))[0]
             for p in paths]
    if len(set(stems)) == len(stems):
        return stems
    return [os.path.relpath(p) for p in paths]


def build_parser():
    ap = argparse.ArgumentParser(
        prog=PROG, description="Plots and a summary of recorded StarlETH runs (MCAP bags); "
        "several bags are overlaid in the same plots.",
        epilog="Plots: " + ", ".join(f"{p}.png" for p in PLOTS) + " (and normal_force_FOOT.png "
        "when comparing). Exit status: 0 ok, 1 a bag cannot be analysed, 2 bad arguments.")
    ap.add_argument("bags", nargs="+", metavar="RUN.mcap",
                    help="MCAP bag files (or rosbag2 directories holding .mcap files)")
    ap.add_argument("--out", metavar="DIR",
                    help="directory for the PNGs (default: <first bag>_analysis beside it)")
    ap.add_argument("--label", nargs="+", metavar="NAME",
                    help="legend labels, one per bag (default: the file names)")
    ap.add_argument("--threshold", type=float, default=5.0, metavar="N",
                    help="contact: stance where the normal force exceeds this [N] (default 5)")
    ap.add_argument("--min-phase", type=float, default=0.02, metavar="S",
                    help="gait: stance/swing phases shorter than this are merged away [s] "
                         "(default 0.02; 0 keeps every sample)")
    ap.add_argument("--tmin", type=float, metavar="S",
                    help="analyse from this time [s] (time since the first message)")
    ap.add_argument("--tmax", type=float, metavar="S", help="analyse up to this time [s]")
    ap.add_argument("--foot", choices=FEET, default=None,
                    help="foot of the single-foot normal force plot (default LF; drawn when "
                         "comparing bags or when given)")
    ap.add_argument("--twist-frame", choices=("auto", "child", "parent"), default="auto",
                    help="frame of the Odometry twist: child (REP 105, sim_node), parent "
                         "(world), auto: child unless child_frame_id is empty or the parent")
    ap.add_argument("--rtf-window", type=float, default=1.0, metavar="S",
                    help="real-time factor plot: window of sim time [s] (default 1)")
    ap.add_argument("--dpi", type=int, default=110, help="PNG resolution (default 110)")
    ap.add_argument("--json", metavar="FILE", help="also write the summary as JSON")
    ap.add_argument("--no-plots", action="store_true", help="summary only")
    ap.add_argument("--salvage", action="store_true",
                    help="read a truncated/damaged bag up to the damage instead of failing")
    return ap


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, np.generic):
        return _jsonable(x.item())
    return x


def run(argv=None) -> int:
    ap = build_parser()
    a = ap.parse_args(argv)
    if a.label and len(a.label) != len(a.bags):
        ap.error(f"--label: {len(a.label)} label(s) for {len(a.bags)} bag(s)")
    if a.threshold < 0 or not math.isfinite(a.threshold):
        ap.error("--threshold must be a finite number >= 0")
    if a.min_phase < 0 or a.rtf_window <= 0:
        ap.error("--min-phase must be >= 0 and --rtf-window > 0")
    if a.tmin is not None and a.tmax is not None and a.tmax <= a.tmin:
        ap.error("--tmax must be greater than --tmin")
    a.foot_given = a.foot is not None
    a.foot = a.foot or "LF"
    t_start = time.perf_counter()
    runs = []
    for path, label in zip(a.bags, _labels(a.bags, a.label)):
        r = Run(path, label, salvage=a.salvage)
        if len(r.missing) == len(TOPICS):
            topics = ", ".join(sorted(r.counts)) or "none"
            raise AnalysisError(f"{path}: none of the StarlETH topics ("
                                f"{', '.join(r.topic_names.values())}) has messages; the bag's "
                                f"topics: {topics}")
        relative = {name: rel for rel, name in r.topic_names.items()}
        for t in r.missing:
            kind, typ, lost = TOPICS[relative[t]]
            have = "no messages on" if t in r.counts else "no topic"
            warn(f"{path}: {have} {t} ({typ}); skipping {lost}")
        r.apply_window(a.tmin, a.tmax)
        runs.append(r)
    t_read = time.perf_counter() - t_start
    empty = [r for r in runs if not any(s["t"].size for s in r._series.values())]
    if len(empty) == len(runs) and a.tmin is None and a.tmax is None:
        raise AnalysisError(f"{', '.join(r.path for r in runs)}: none of the messages on the "
                            "StarlETH topics could be read (see the warnings above)")
    if len(empty) == len(runs):
        lo = "the start" if a.tmin is None else f"{a.tmin:g} s"
        hi = "the end" if a.tmax is None else f"{a.tmax:g} s"
        raise AnalysisError(f"no messages between {lo} and {hi} (--tmin/--tmax: time since "
                            "the first message of each bag)")
    summaries = [summarise(r, a.threshold, a.min_phase, a.twist_frame) for r in runs]
    for r in empty:
        warn(f"{r.path}: no messages between --tmin and --tmax")
    for S in summaries:
        print(format_summary(S))
    written = {}
    if not a.no_plots:
        out = a.out or _default_out(a.bags)
        t0 = time.perf_counter()
        written = save_figures(runs, a, out)
        t_plot = time.perf_counter() - t0
        if written:
            print(f"plots ({t_plot:.1f} s) in {out}/: "
                  + ", ".join(os.path.basename(p) for p in written.values()))
        else:
            warn("nothing to plot")
    print(f"read and decoded {sum(r.messages for r in runs)} messages in {t_read:.2f} s")
    if a.json:
        doc = {"runs": summaries, "plots": written}
        d = os.path.dirname(os.path.abspath(a.json))
        os.makedirs(d, exist_ok=True)
        with open(a.json, "w") as f:
            json.dump(_jsonable(doc), f, indent=1)
    return 0


def run_console_script(prog, run, argv, errors=(BagError,)) -> int:
    """Run a bag tool's `run(argv)`: exit status as returned, or 1 with one line
    'prog: error: ...' (no traceback) for `errors` and for OSError (writing the output),
    130 on Ctrl-C; argparse exits with 2 on bad arguments."""
    try:
        return run(argv)
    except (*errors, OSError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130


def main(argv=None) -> int:
    """Console script: exit status 0, or 1 with a one-line message for a bag that cannot be
    analysed (no traceback), 2 for bad arguments."""
    return run_console_script(PROG, run, argv)


if __name__ == "__main__":
    sys.exit(main())
