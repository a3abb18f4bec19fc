"""The recorded runs ``starleth-view`` replays: the joint states, base state and foot wrenches
of each robot of a bag (kept as CDR bytes, sorted by stamp, decoded only where shown), with
the robot (URDF and spec), the frame prefix and the ground it was recorded with; the tool's
warnings and its error."""
from __future__ import annotations

import math
import struct
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import numpy as np

from starleth_interface.topics import (
    TOPIC_BASE_STATE,
    TOPIC_JOINT_STATES,
    TOPIC_ROBOT_DESCRIPTION,
    foot_wrench_topic,
    namespace_of,
    split_foot_wrench_topic,
)
from starleth_interface.yaml_files import load_yaml_text

from ...physics.config import ConfigError
from ...physics.description import urdf_path
from ...physics.terrain import TerrainConfig
from ...ros.tf import base_link
from ..common.bag import read_messages, recorded_robot

PROG = "starleth-view"

#: kind -> (relative topic name, message type)
TOPICS = {"joints": (TOPIC_JOINT_STATES, "sensor_msgs/msg/JointState"),
          "base": (TOPIC_BASE_STATE, "nav_msgs/msg/Odometry"),
          "description": (TOPIC_ROBOT_DESCRIPTION, "std_msgs/msg/String")}
WRENCH_TYPE = "geometry_msgs/msg/WrenchStamped"


class ViewError(Exception):
    """A run that cannot be replayed: main() prints the message and exits with 1."""


class NamespaceNotFound(ViewError):
    """A bag without a robot under the namespaces asked for."""


def warn(message: str) -> None:
    print(f"{PROG}: warning: {message}", file=sys.stderr)


def match_topic(topic: str):
    """(kind, namespace) of a bag topic that is one of TOPICS under some namespace
    ('/joint_states' -> ('joints', ''), '/robot1/starleth/base_state' -> ('base', '/robot1')),
    or a foot's wrench topic ('/robot1/starleth/FL_foot/wrench' -> ('starleth/FL_foot/wrench',
    '/robot1'): its kind is its relative name, which foot_wrench_topic gives a foot), or
    None."""
    for kind, (rel, _) in TOPICS.items():
        ns = namespace_of(topic, rel)
        if ns is not None:
            return kind, ns
    foot = split_foot_wrench_topic(topic)
    if foot is not None:
        ns, token = foot
        return foot_wrench_topic(token), ns
    return None


def topic_type(kind: str) -> str:
    """The message type of a kind of topic (match_topic)."""
    return TOPICS[kind][1] if kind in TOPICS else WRENCH_TYPE


def _select(topic: str, type_name: str) -> bool:
    m = match_topic(topic)
    return m is not None and topic_type(m[0]) == type_name


def cdr_stamp_ns(data) -> int:
    """Header stamp [ns] of a CDR-serialised message whose first field is a std_msgs/Header
    (JointState, Odometry, WrenchStamped), read without decoding the message."""
    if len(data) < 12:
        raise ValueError(f"{len(data)} bytes: too short for a message with a header")
    fmt = "<iI" if data[1] & 1 else ">iI"   # encapsulation id: odd = little-endian
    sec, nanosec = struct.unpack_from(fmt, data, 4)
    return sec * 1_000_000_000 + nanosec


@dataclass
class Series:
    """Messages of one topic sorted by time: t [ns] (header stamps, or the log times when
    the messages are unstamped), the CDR bytes and the decoder."""

    topic: str
    t_ns: np.ndarray
    raw: list
    decode: object

    @classmethod
    def from_bag(cls, bag, topic):
        rows = bag.messages.get(topic, [])
        try:
            stamps = np.array([cdr_stamp_ns(d) for _, d in rows], dtype=np.int64)
        except ValueError as e:
            raise ViewError(f"{bag.path}: a message on {topic} is damaged ({e})") from None
        if stamps.size and not stamps.any():
            stamps = np.array([log for log, _ in rows], dtype=np.int64)
        order = np.argsort(stamps, kind="stable")
        return cls(topic, stamps[order], [rows[i][1] for i in order], bag.decoders.get(topic))

    def __len__(self):
        return self.t_ns.size

    def message(self, i):
        """Message i, decoded."""
        try:
            return self.decode(self.raw[i])
        except Exception as e:   # a message the schema does not describe
            raise ViewError(f"message {i} on {self.topic} cannot be decoded: "
                            f"{type(e).__name__}: {e}") from None

    def latest(self, t_ns):
        """Index of the latest message at or before each of t_ns (the first one before it)."""
        return np.clip(np.searchsorted(self.t_ns, t_ns, side="right") - 1, 0, len(self) - 1)


@dataclass
class Recording:
    """The series of one robot of a bag, and where its URDF and ground come from."""

    path: str
    namespace: str
    joints: Series
    base: Series
    #: {relative topic (starleth/FL_foot/wrench): Series} of the foot wrench topics
    wrench_topics: dict
    urdf: str
    urdf_source: str
    #: the recorded robot's name and its spec's YAML text (None: a URDF alone)
    robot: str = ""
    spec: str | None = None
    #: {foot contact name: Series} of the robot's feet with force messages (attach_feet)
    wrenches: dict = field(default_factory=dict)
    ground_height: float = 0.0
    ground_normal: tuple = (0.0, 0.0, 1.0)
    truncated: bool = False
    #: the terrain on the ground (physics.terrain.TerrainConfig, validated), or None
    terrain: object = None
    #: put before the robot's frames on /tf (sim_node's tf_frame_prefix): what its base
    #: state's child frame has before the URDF's root link ('' where it has nothing more)
    frame_prefix: str = ""


def normalised_namespace(ns: str) -> str:
    """'robot1', '/robot1/' -> '/robot1'; '', '/' -> ''."""
    return "/" + ns.strip("/") if ns.strip("/") else ""


def complete_namespaces(found: dict, bag) -> list:
    """The namespaces (sorted) under which the bag has both joint states and base states."""
    return sorted(ns for ns, kinds in found.items()
                  if bag.counts.get(kinds.get("joints"), 0)
                  and bag.counts.get(kinds.get("base"), 0))


def _choose_namespaces(found: dict, requested, path: str, bag) -> list:
    """The namespaces of the robots to replay: every one whose joint states and base state
    the bag holds, or those of `requested` (a list) among them. ViewError where there is
    none."""
    complete = complete_namespaces(found, bag)
    if requested is not None:
        wanted = [normalised_namespace(r) for r in requested]
        chosen = [ns for ns in complete if ns in wanted]
        if chosen:
            return chosen
        have = ", ".join(repr(n or "/") for n in complete) or "none"
        names = ", ".join(repr(n or "/") for n in wanted)
        raise NamespaceNotFound(f"{path}: no {TOPIC_JOINT_STATES} and {TOPIC_BASE_STATE} "
                                f"messages under the namespace(s) {names} (namespaces with "
                                f"both: {have})")
    if not complete:
        missing = []
        for kind in ("joints", "base"):
            rel, typ = TOPICS[kind]
            if not any(bag.counts.get(k.get(kind), 0) for k in found.values()):
                missing.append(f"{rel} ({typ})")
        topics = ", ".join(f"{t} ({ty or 'no schema'})" for t, ty in sorted(bag.types.items()))
        if not missing:
            raise ViewError(f"{path}: {TOPIC_JOINT_STATES} and {TOPIC_BASE_STATE} are in "
                            f"different namespaces; the bag's topics: {topics or 'none'}")
        raise ViewError(f"{path}: no messages on {' nor '.join(missing)}, so there is no robot "
                        f"motion to replay; the bag's topics: {topics or 'none'}")
    return complete


def _urdf_from_bag(bag, topics: dict, path: str):
    """(URDF text, where it came from, robot name, spec YAML text or None): the namespace's
    robot_description topic, the robot sim_node recorded (its URDF and spec attachments,
    bag.recorded_robot; its spec goes with a topic's URDF that is the same), the
    starleth.urdf attachment (older recordings), another .urdf attachment, or the package's
    URDF."""
    robot = recorded_robot(bag, path)
    topic = topics.get("description")
    if topic and bag.messages.get(topic):
        try:
            text = bag.decoders[topic](bag.messages[topic][0][1]).data
            same = robot is not None and robot[1] == text
            return (text, f"topic {topic}", robot[0] if same else "",
                    robot[2] if same else None)
        except Exception as e:   # a damaged message: try the attachments
            warn(f"{path}: cannot decode {topic} ({e}); using another URDF")
    if robot is not None:
        name = bag.metadata["starleth_sim"]["urdf_attachment"]
        return robot[1], f"attachment {name}", robot[0], robot[2]
    names = sorted(bag.attachments, key=lambda n: (n != "starleth.urdf", n))
    for name in names:
        if name.endswith(".urdf"):
            try:
                return bag.attachments[name].decode("utf-8"), f"attachment {name}", "", None
            except UnicodeDecodeError:
                continue
    with open(urdf_path()) as f:
        return f.read(), "package urdf/starleth.urdf (none in the bag)", "", None


def _recorded_config(bag, path):
    """The recording's physics configuration (sim_node's 'starleth_sim' metadata) as YAML
    data (load_yaml_text: bounded), or None; ConfigError where it cannot be read."""
    text = bag.metadata.get("starleth_sim", {}).get("physics_config")
    return load_yaml_text(text, f"{path}: physics_config") if text else None


def _ground_from_metadata(bag):
    """(height, unit normal) of the ground from the recording's physics configuration
    (sim_node's 'starleth_sim' metadata), else the default flat ground z = 0."""
    try:
        ground = (_recorded_config(bag, "") or {}).get("ground", {})
        normal = ground.get("normal", (0.0, 0.0, 1.0))
        # three numbers, checked before numpy walks it (YAML aliases can nest a list
        # a billion elements deep in a few hundred bytes)
        if not (isinstance(normal, (list, tuple)) and len(normal) == 3
                and all(isinstance(x, (int, float)) for x in normal)):
            raise ValueError("bad ground normal")
        n = np.array(normal, dtype=float)
        h = float(ground.get("height", 0.0))
        if np.linalg.norm(n) < 1e-9 or not np.all(np.isfinite(n)) or not math.isfinite(h):
            raise ValueError("bad ground")
    except (ValueError, TypeError, AttributeError, OverflowError, RecursionError):
        return 0.0, (0.0, 0.0, 1.0)
    n = n / np.linalg.norm(n)
    return h, tuple(float(x) for x in n)


def terrain_from_metadata(bag, path):
    """The recording's terrain (its physics configuration's `terrain` section, validated),
    or None: none recorded, or one that is not valid (with a warning: not drawn)."""
    try:
        data = _recorded_config(bag, path)
    except ConfigError as e:
        warn(f"{e}; no terrain drawn")
        return None
    section = data.get("terrain") if isinstance(data, dict) else None
    if not section:
        return None
    try:
        terrain = TerrainConfig(**section)
        terrain.validate("terrain")
    except (TypeError, ConfigError) as e:
        warn(f"{path}: the recorded terrain is not valid, not drawn: {e}")
        return None
    return None if terrain.is_flat else terrain


def frame_prefix(rec: Recording) -> str:
    """What the robot's base state names its child frame with before the URDF's root link
    (sim_node's tf_frame_prefix); '' where the child frame is that link (or, with a
    warning, another frame, or a message that cannot be read: its error comes where the
    message is drawn)."""
    try:
        child = rec.base.message(0).child_frame_id
        root = base_link(rec.urdf)
    except (ViewError, ValueError, AttributeError, ET.ParseError):
        return ""
    if isinstance(child, str) and child.endswith(root):
        return child[:len(child) - len(root)]
    warn(f"{rec.path}: the base state's child frame {child!r} is not the URDF's root link "
         f"{root!r} (with a prefix); the robot's frames are named without a prefix")
    return ""


def read_recordings(path: str, namespaces=None, salvage: bool = False) -> list:
    """The Recordings of the robots of a bag: all of them, or those under `namespaces` (a
    list). Raises BagError for a bag that cannot be read, ViewError for one without joint
    states or base state (under those namespaces)."""
    bag = read_messages(path, _select, salvage=salvage, decode=False, on_warning=warn)
    found = {}                                   # namespace -> {kind: topic}
    for topic in bag.types:
        m = match_topic(topic)
        if m is not None and _select(topic, bag.types[topic]):
            found.setdefault(m[1], {})[m[0]] = topic
        elif m is not None:
            warn(f"{path}: topic {topic} has type {bag.types[topic] or '(no schema)'}, "
                 f"expected {topic_type(m[0])}; ignored")
    ground = _ground_from_metadata(bag)
    terrain = terrain_from_metadata(bag, path)
    return [_robot(bag, path, ns, found[ns], ground, terrain)
            for ns in _choose_namespaces(found, namespaces, path, bag)]


def _robot(bag, path, ns, topics, ground, terrain) -> Recording:
    """The Recording of the robot under `ns` (its topics: {kind: topic})."""
    urdf, source, robot, spec = _urdf_from_bag(bag, topics, path)
    wrench_topics = {kind: Series.from_bag(bag, topic) for kind, topic in topics.items()
                     if kind not in TOPICS and bag.messages.get(topic)}
    rec = Recording(path=path, namespace=ns, joints=Series.from_bag(bag, topics["joints"]),
                    base=Series.from_bag(bag, topics["base"]), wrench_topics=wrench_topics,
                    urdf=urdf, urdf_source=source, robot=robot, spec=spec,
                    truncated=bag.truncated, terrain=terrain)
    rec.ground_height, rec.ground_normal = ground
    for series in (rec.joints, rec.base):
        if not len(series):
            n = bag.counts.get(series.topic, 0)
            raise ViewError(f"{path}: none of the {n} message(s) on {series.topic} could be "
                            "read, so there is no robot motion to replay")
    rec.frame_prefix = frame_prefix(rec)
    return rec



def attach_feet(rec: Recording, foot_names) -> None:
    """rec.wrenches: the wrench series of the robot's feet (foot contact names, in their
    order) on their topics (foot_wrench_topic), with a warning for each foot without
    messages."""
    rec.wrenches = {}
    for foot in foot_names:
        series = rec.wrench_topics.get(foot_wrench_topic(foot))
        if series is not None:
            rec.wrenches[foot] = series
        else:
            warn(f"{rec.path}: no messages on {rec.namespace}/{foot_wrench_topic(foot)}; "
                 f"no {foot} force arrow")
