"""A recorded run read into arrays for ``starleth-analyze``: the StarlETH topics of one bag
(or rosbag2 directory), decoded in one pass and kept as per-series arrays with time in
seconds relative to the first message (:class:`Run`), garbage values counted and left out;
also a run made from arrays (a re-simulation)."""
from __future__ import annotations

import json
import math
import os
import sys
import time

import numpy as np

from starleth_interface.topics import (
    TOPIC_BASE_STATE,
    TOPIC_JOINT_STATES,
    TOPIC_ROBOT_DESCRIPTION,
    TOPIC_SOLVER,
    foot_wrench_topic,
    namespace_of,
    resolve,
    split_foot_wrench_topic,
)

from ...physics.config import ConfigError
from ...robots import recorded_description
from ..common.bag import BagError, recorded_robot, stream_bag

PROG = "starleth-analyze"
FOOT_WRENCH = ("geometry_msgs/msg/WrenchStamped", "the contact force and gait plots")

# topic -> (kind, expected type, what is lost without it); the feet's wrench topics are
# found by starleth_interface.topics.split_foot_wrench_topic
TOPICS = {
    TOPIC_BASE_STATE: (("base", None), "nav_msgs/msg/Odometry", "the base trajectory plot"),
    TOPIC_JOINT_STATES: (("joints", None), "sensor_msgs/msg/JointState",
                         "the joint torque plot"),
    TOPIC_SOLVER: (("solver", None), "diagnostic_msgs/msg/DiagnosticArray",
                   "the solver iteration plot and the compute real-time factor"),
}
OPTIONAL_TOPICS = {TOPIC_ROBOT_DESCRIPTION: "std_msgs/msg/String"}

#: the largest magnitude of a recorded force [N], position [m], velocity, joint torque [N m]
#: or solver value taken as data; beyond it (or infinite) a value is garbage, left out
MAX_VALUE = 1e9


class AnalysisError(BagError):
    """A bag that cannot be analysed: main() prints the message and exits with 1 (as for
    any BagError, a bag that cannot be read)."""


def warn(message: str) -> None:
    print(f"{PROG}: warning: {message}", file=sys.stderr)


class _Collector:
    """Per-topic lists filled while streaming, turned into arrays by Run."""

    def __init__(self, path: str):
        self.path = path
        self.wrench = {}                             # foot -> [(stamp, log, pub, fx, fy, fz)]
        self.base = []                               # (stamp, log, pub, p3, q4, v3, w3)
        self.base_frames = None                      # (frame_id, child_frame_id)
        self.joint_stamps = []                       # (stamp, log, pub)
        self.joint_effort = []                       # rows in joint_names order (NaN if absent)
        self.joint_names = None                      # names as first seen
        self.ignored_joints = []                     # names of later messages not among them
        self.solver = []                             # (stamp, log, pub, it, conv, res, st, mx, ac)
        self.urdf = None                             # from robot_description
        self.namespace = None                        # of the first StarlETH topic seen

    def on_channel(self, topic, type_name, make_decoder):
        """stream_bag's channel callback: a handler for the StarlETH topics of the run's
        namespace with the expected type, None for the rest."""
        rel = self.relative_topic(topic)
        if isinstance(rel, tuple):                   # a foot's wrench
            kind, expected = rel, FOOT_WRENCH[0]
        elif rel in TOPICS:
            kind, expected, _ = TOPICS[rel]
        elif rel in OPTIONAL_TOPICS:
            kind, expected = ("description", None), OPTIONAL_TOPICS[rel]
        else:
            return None
        if type_name != expected:
            warn(f"{self.path}: topic {topic} has type {type_name or '(no schema)'}, "
                 f"expected {expected}; ignored")
            return None
        decode = make_decoder()
        if decode is None:
            return None
        if kind[0] == "wrench":
            self.wrench.setdefault(kind[1], [])
        return _make_handler(kind, self, decode)

    def relative_topic(self, topic: str):
        """The relative StarlETH name (a key of TOPICS or OPTIONAL_TOPICS, or ('wrench',
        foot) for a foot's wrench topic) of a topic of the bag, in the run's namespace (that
        of the first such topic: a bag of one robot under /robot1 reads like one at the
        root), or None."""
        wrench = split_foot_wrench_topic(topic)
        if wrench is not None:
            ns, foot = wrench
            if self.namespace is None:
                self.namespace = ns
            return ("wrench", foot) if ns == self.namespace else None
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


def float_or_nan(s):
    try:
        return float(s)
    except (TypeError, ValueError, OverflowError):
        return math.nan


def _make_handler(kind, col: _Collector, decode):
    """The message handler of a topic of `kind` (('wrench', foot), ('base', None), ...):
    decodes each message and appends its row to the collector."""
    what, foot = kind
    if what not in _HANDLERS:  # pragma: no cover
        raise ValueError(kind)
    return _HANDLERS[what](col, decode, foot)


def _wrench_handler(col, decode, foot):
    rows = col.wrench[foot]

    def handle(m):
        msg = decode(m.data)
        f = msg.wrench.force
        rows.append((_stamp(msg), m.log_time, m.publish_time, f.x, f.y, f.z))
    return handle


def _base_handler(col, decode, _foot):
    rows = col.base

    def handle(m):
        msg = decode(m.data)
        if col.base_frames is None:
            col.base_frames = (msg.header.frame_id, msg.child_frame_id)
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        v, w = msg.twist.twist.linear, msg.twist.twist.angular
        rows.append((_stamp(msg), m.log_time, m.publish_time,
                     p.x, p.y, p.z, q.x, q.y, q.z, q.w, v.x, v.y, v.z, w.x, w.y, w.z))
    return handle


def _joints_handler(col, decode, _foot):
    """/joint_states: the efforts in the columns of the first message's joints, by name
    (NaN where a message lacks one; joints not among them listed as ignored)."""
    state = {"names": None, "index": None, "identity": False, "order": None}

    def new_names(names):
        if col.joint_names is None:
            col.joint_names = list(names)
        if state["order"] is None:      # (a split bag's later file: the first's names)
            state["order"] = {n: i for i, n in enumerate(col.joint_names)}
            state["nan_row"] = [math.nan] * len(col.joint_names)
        state["names"] = list(names)
        state["index"] = [state["order"].get(n, -1) for n in names]
        col.ignored_joints += [n for n in names if n not in state["order"]
                               and n not in col.ignored_joints]
        state["identity"] = state["index"] == list(range(len(col.joint_names)))

    def handle(m):
        msg = decode(m.data)
        if msg.name != state["names"]:
            new_names(msg.name)
        col.joint_stamps.append((_stamp(msg), m.log_time, m.publish_time))
        eff = msg.effort
        idx = state["index"]
        if state["identity"] and len(eff) == len(idx):
            col.joint_effort.append(list(eff))
            return
        row = list(state["nan_row"])
        if len(eff) == len(idx):
            for i, e in zip(idx, eff, strict=True):
                if i >= 0:
                    row[i] = e
        col.joint_effort.append(row)
    return handle


def _solver_handler(col, decode, _foot):
    rows = col.solver

    def handle(m):
        msg = decode(m.data)
        for st in msg.status:
            kv = {v.key: v.value for v in st.values}
            if "iterations" not in kv:
                continue
            conv = kv.get("converged")
            rows.append((_stamp(msg), m.log_time, m.publish_time,
                         float_or_nan(kv["iterations"]),
                         math.nan if conv is None else float(conv.strip().lower() in
                                                             ("true", "1", "yes")),
                         float_or_nan(kv.get("residual")), float_or_nan(kv.get("step_time")),
                         float_or_nan(kv.get("max_iterations_step")),
                         float_or_nan(kv.get("active_contacts"))))
            return
    return handle


def _description_handler(col, decode, _foot):
    def handle(m):
        if col.urdf is None:
            col.urdf = decode(m.data).data
    return handle


_HANDLERS = {"wrench": _wrench_handler, "base": _base_handler, "joints": _joints_handler,
             "solver": _solver_handler, "description": _description_handler}


def _attached_urdf(bag):
    """The URDF attached to the recording (sim_node's carry it so), or None."""
    for name, data in bag.attachments.items():
        if name.endswith(".urdf"):
            try:
                return data.decode("utf-8")
            except UnicodeDecodeError:
                pass
    return None


def _rows(path, rows, width):
    """`rows` as a (n, width) float array."""
    try:
        a = np.array(rows, dtype=float) if rows else np.zeros((0, width))
    except (ValueError, TypeError, OverflowError) as e:
        raise AnalysisError(f"{path}: messages whose fields are not numbers (the "
                            f"bag's schema is not the ROS one?): {e}") from None
    return a.reshape(len(rows), width)


def _times(rows, path):
    """The raw (stamp, log, pub) nanoseconds of `rows`, int64 for exact comparisons; the
    log time stands for the stamp of unstamped messages."""
    try:
        a = np.array([r[:3] for r in rows], dtype=np.int64).reshape(-1, 3)
    except (ValueError, TypeError, OverflowError) as e:
        raise AnalysisError(f"{path}: message stamps that are not int64 "
                            f"nanoseconds: {e}") from None
    stamp = a[:, 0]
    if stamp.size and not stamp.any():
        stamp = a[:, 1].copy()
    return stamp, a[:, 1], a[:, 2]


def _in_stamp_order(times, data, t0_ns):
    """A series' dict, its rows sorted by stamp (stable), t in s from t0_ns."""
    stamp, log, pub = times
    order = np.argsort(stamp, kind="stable")
    if not np.all(order == np.arange(order.size)):
        stamp, log, pub, data = stamp[order], log[order], pub[order], data[order]
    return {"stamp": stamp, "log": log, "pub": pub, "data": data, "t": (stamp - t0_ns) * 1e-9}


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
        self.urdf = col.urdf if col.urdf is not None else _attached_urdf(bag)
        for topic, (n, err) in bag.decode_errors.items():
            warn(f"{path}: {n} message(s) on {topic} could not be read ({err})")
        robot = self._recorded_robot(bag)
        #: the recorded robot's name (None: a bag without it), its feet (their contact
        #: names, in the robot's order; else in the order of the bag's wrench topics)
        self.description = robot
        self.robot = robot.name if robot is not None else None
        ordered = list(robot.foot_names) if robot is not None else []
        self.feet = tuple(ordered + [f for f in col.wrench if f not in ordered])
        #: the relative topics read: TOPICS and the feet's wrench topics
        self.topics = dict(TOPICS)
        self.topics.update({foot_wrench_topic(f): (("wrench", f), FOOT_WRENCH[0],
                                                   f"the {f} {FOOT_WRENCH[1]}")
                            for f in self.feet})
        #: the namespace of the StarlETH topics ('' at the root, '/robot1') and their names
        self.namespace = col.namespace or ""
        self.topic_names = {rel: resolve(rel, self.namespace) for rel in self.topics}
        self.missing = [self.topic_names[t] for t in self.topics
                        if not self.counts.get(self.topic_names[t])]
        self.joint_names, self.ignored_joints = col.joint_names or [], col.ignored_joints
        series = self._drop_unusable(self._series(col, robot))
        firsts = [s[0][0].min() for s in series.values() if s[0][0].size]
        self.t0_ns = int(min(firsts)) if firsts else 0
        #: (kind, foot) -> {t [s], stamp/log/pub [ns], data rows}: 'wrench' per foot,
        #: ('base', None), ('joints', None), ('solver', None)
        self.series_by_key = {key: _in_stamp_order(times, data, self.t0_ns)
                              for key, (times, data) in series.items()}
        self.base_frames = col.base_frames or ("", "")
        self.window = (None, None)

    def _series(self, col, robot):
        """{key: ((stamp, log, pub) [ns], data rows)} of the collected messages, the
        efforts in the robot's joint order."""
        path = self.path
        series = {}
        for foot in self.feet:
            rows = col.wrench.get(foot, [])
            series[("wrench", foot)] = (_times(rows, path), _rows(path, [r[3:] for r in rows], 3))
        series[("base", None)] = (_times(col.base, path),
                                  _rows(path, [r[3:] for r in col.base], 13))
        effort = _rows(path, col.joint_effort, len(self.joint_names))
        if robot is not None and self.joint_names != list(robot.joint_names):
            effort = self._in_robot_order(effort, list(robot.joint_names))
        series[("joints", None)] = (_times(col.joint_stamps, path), effort)
        series[("solver", None)] = (_times(col.solver, path),
                                    _rows(path, [r[3:] for r in col.solver], 6))
        return series

    def _recorded_robot(self, bag):
        """The robot the bag recorded (bag.recorded_robot: no library needed), or None (a
        bag of another recorder; a warning where its description cannot be built)."""
        try:
            robot = recorded_robot(bag, self.path)
            return None if robot is None else recorded_description(
                robot[1], robot[2], robot[0], where=self.path)
        except (BagError, ConfigError) as e:
            warn(f"{e}; feet and joints as the bag's topics give them")
            return None

    def _in_robot_order(self, effort, names):
        """The effort columns in the robot's joint order `names` (NaN for a joint the
        messages lack); the joints the robot lacks are ignored."""
        col = {n: i for i, n in enumerate(self.joint_names)}
        out = np.full((effort.shape[0], len(names)), np.nan)
        for j, n in enumerate(names):
            if n in col:
                out[:, j] = effort[:, col[n]]
        self.ignored_joints += [n for n in self.joint_names if n not in names]
        self.joint_names = names
        return out

    def _drop_unusable(self, series: dict) -> dict:
        """series without the garbage a bag may hold, with a counted warning per topic: a
        wrench or base state holding a NaN, an infinite value or one beyond MAX_VALUE is
        left out; in joint efforts and solver values (where NaN means 'not recorded') an
        infinite or absurd value becomes NaN (the solver's residual is kept as recorded)."""
        rel = {kind: name for name, (kind, _, _) in self.topics.items()}
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
                    base_frames=("world", "base"), feet=(), joint_names=()):
        """A run made from arrays instead of a bag (e.g. a re-simulation, starleth-replay),
        for the plots: t [s] per row; base rows (position 3, quaternion x y z w, linear
        twist 3, angular twist 3), wrench {foot: rows (f_x, f_y, f_z)} of the `feet`,
        effort rows in `joint_names` order; missing ones are empty series."""
        run = cls.__new__(cls)
        run.path, run.label = "", label
        run.truncated, run.files, run.file_size, run.messages = False, [], 0, 0
        run.counts, run.types, run.metadata, run.urdf = {}, {}, {}, None
        run.robot, run.description, run.ignored_joints, run.topics = None, None, [], {}
        run.namespace, run.topic_names, run.missing = "", {}, []
        run.base_frames, run.joint_names, run.window = base_frames, list(joint_names), (None, None)
        run.feet = tuple(feet)
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
        run.series_by_key = {("wrench", f): entry((wrench or {}).get(f), 3) for f in feet}
        run.series_by_key[("base", None)] = entry(base, 13)
        run.series_by_key[("joints", None)] = entry(effort, len(joint_names))
        run.series_by_key[("solver", None)] = entry(None, 6)
        return run

    # -- access ------------------------------------------------------------------------------
    def series(self, what, foot=None):
        """dict with t [s], stamp/log/pub [ns] and data rows (time window applied)."""
        return self.series_by_key[(what, foot)]

    def apply_window(self, tmin=None, tmax=None):
        if tmin is None and tmax is None:
            return
        self.window = (tmin, tmax)
        for key, s in self.series_by_key.items():
            t = s["t"]
            m = np.ones(t.shape, dtype=bool)
            if tmin is not None:
                m &= t >= tmin
            if tmax is not None:
                m &= t <= tmax
            self.series_by_key[key] = {k: v[m] for k, v in s.items()}

    def has(self, what, foot=None) -> bool:
        return self.series_by_key[(what, foot)]["t"].size > 0

    def normal_force(self, foot):
        s = self.series("wrench", foot)
        return s["t"], s["data"][:, 2]

    def timed_series(self) -> tuple:
        """The keys of the series whose stamps give the run's clock, most regular first:
        the joints, the first foot's wrench, the base, the solver."""
        return (("joints", None), *(("wrench", f) for f in self.feet[:1]), ("base", None),
                ("solver", None))

    @property
    def control_period(self):
        """Control period [s]: from the recording's metadata, else the stamps' median step."""
        md = self.metadata.get("starleth_sim", {})
        cp = float_or_nan(md.get("control_period"))
        if math.isfinite(cp) and cp > 0:
            return cp
        for key in self.timed_series():
            t = self.series_by_key[key]["t"]
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

