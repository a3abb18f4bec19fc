"""``starleth-view``: a recorded run replayed in 3D, as one self-contained HTML file.

    starleth-view runs/demo.mcap                    # writes runs/demo.html
    starleth-view run.mcap -o replay.html --fps 30
    starleth-view rosbag2_dir/ --namespace /robot1

The page needs no server and no network: meshcat's three.js viewer
(``meshcat/viewer/dist/main.min.js`` of the ``meshcat`` package, MIT licence) and the replay
data are inlined. Open it in a browser; play / pause (space), step (arrow keys), scrub with
the slider, pick a speed; the camera follows the trunk (drag to orbit, scroll to zoom).
``?t=1.5&paused=1`` in the URL shows t = 1.5 s paused (also ``speed=0.5``, ``follow=0``).

What is drawn, from the bag (an MCAP file written by ``sim_node``, or a rosbag2 directory of
.mcap files; topics are matched by suffix, so ``/joint_states`` and ``/robot1/joint_states``
both work):

* the robot's URDF visuals (boxes, spheres, cylinders), from the bag's ``robot_description``
  topic, else its ``starleth.urdf`` attachment (``sim_node``'s recorder), else the package's
  ``urdf/starleth.urdf``;
* link poses from Pinocchio forward kinematics of a free-flyer model of that URDF, at the
  recorded ``joint_states`` (sensor_msgs/JointState, positions by joint name) and
  ``starleth/base_state`` (nav_msgs/Odometry: pose of the base in the world);
* the ground plane, a 0.5 m checkerboard (height and normal from the recording's physics
  configuration, if any);
* contact forces as arrows from the foot contact points (sphere centre minus radius along
  the ground normal), ``starleth/{LF,RF,LH,RH}_foot/wrench`` (geometry_msgs/WrenchStamped,
  force in the world frame), scaled by ``--force-scale`` [m/N].

Frames: one every 1/fps s of sim time (header stamps) from the first joint state, each the
latest recorded sample at or before that time (sample and hold, no interpolation), plus the
last sample; the base pose and foot forces are the latest at or before the frame's joint
state. Frames are worked out per sample, so that memory goes with the samples in the bag,
whatever the span of their stamps (two samples 2e9 s apart: 2 frames). A recorded value
that is NaN, infinite or beyond 1e9 is garbage: the previous value is drawn instead (a
force: no arrow), with a warning counting the messages. Numbers are rounded: positions and
arrows to 0.1 mm, quaternions to 1e-4, times to 0.1 ms. A 20 s run at 400 Hz gives a 1.7 MB
page at the default 50 fps (0.85 MB of it the viewer), 7.3 MB with every sample.

A bag that cannot be read (not MCAP, truncated, corrupt; ``--salvage`` reads a truncated one
up to the damage), one without (readable) joint states or base state, or a shown message
that cannot be decoded, ends the program with a one-line message on stderr and exit
status 1.
"""
from __future__ import annotations

import argparse
import base64
import html
import json
import math
import os
import re
import struct
import sys
import time
import xml.etree.ElementTree as ET
import zlib
from dataclasses import dataclass

import numpy as np

from .analysis import run_console_script
from .bag import BagError, read_messages
from ..physics.description import LEGS, RobotDescription, _origin, urdf_path
from starleth_interface.topics import (TOPIC_BASE_STATE, TOPIC_JOINT_STATES, TOPIC_ROBOT_DESCRIPTION,
                     foot_wrench_topic, namespace_of)

PROG = "starleth-view"
FEET = LEGS
DEFAULT_FPS = 50.0
#: arrow length per newton of contact force [m/N]: 1 m = 500 N
DEFAULT_FORCE_SCALE = 0.002
FORMAT = "starleth-view/1"
#: decimals of the numbers in the page: positions/arrows [m], quaternions, times [s]
POSITION_DECIMALS = 4
QUATERNION_DECIMALS = 4
TIME_DECIMALS = 4
ROUNDING_TEXT = "positions and arrows to 0.1 mm, quaternions to 1e-4, times to 0.1 ms"

#: colours (0xRRGGBB): a distinctive orange robot, green arrows, grey ground, blue-grey sky
ROBOT_COLOR = 0xF07818      # boxes (the trunk)
LEG_COLOR = 0xD2600C        # cylinders (hips, thighs, shanks)
FOOT_COLOR = 0x303030       # spheres (feet)
ARROW_COLOR = 0x18B43C
GROUND_COLORS = ((0xD6, 0xD6, 0xCC), (0xBC, 0xBC, 0xB2))   # unlit 0.5 m checkerboard
GROUND_SQUARE = 0.5         # [m]
SKY_TOP, SKY_BOTTOM = (0.84, 0.89, 0.95), (0.62, 0.69, 0.78)
#: camera position relative to the followed trunk point, world axes [m]
CAMERA_OFFSET = (0.9, -1.35, 0.42)
#: the camera target's height follows the trunk height averaged over +-this [s]
CAMERA_HEIGHT_WINDOW = 0.5
ARROW_HEAD = 0.05           # length of an arrow's cone [m]
#: the largest magnitude of a recorded position [m], joint angle [rad] or force [N] drawn;
#: a sample beyond it (or NaN, infinite) is garbage: the previous value is drawn instead
MAX_VALUE = 1e9
ARROW_RADIUS = 0.011        # of its shaft [m] (the cone: 2.5 times that)

#: kind -> (relative topic name, message type)
TOPICS = {"joints": (TOPIC_JOINT_STATES, "sensor_msgs/msg/JointState"),
          "base": (TOPIC_BASE_STATE, "nav_msgs/msg/Odometry"),
          "description": (TOPIC_ROBOT_DESCRIPTION, "std_msgs/msg/String"),
          **{foot: (foot_wrench_topic(f"{foot}_foot"),
                    "geometry_msgs/msg/WrenchStamped") for foot in FEET}}


class ViewError(Exception):
    """A run that cannot be replayed: main() prints the message and exits with 1."""


def warn(message: str) -> None:
    print(f"{PROG}: warning: {message}", file=sys.stderr)


# =========================================================================================
# reading the run
# =========================================================================================
def match_topic(topic: str):
    """(kind, namespace) of a bag topic that is one of TOPICS under some namespace
    ('/joint_states' -> ('joints', ''), '/robot1/starleth/base_state' -> ('base', '/robot1')),
    or None."""
    for kind, (rel, _) in TOPICS.items():
        ns = namespace_of(topic, rel)
        if ns is not None:
            return kind, ns
    return None


def _select(topic: str, type_name: str) -> bool:
    m = match_topic(topic)
    return m is not None and TOPICS[m[0]][1] == type_name


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
    wrenches: dict                 # foot -> Series (feet without messages left out)
    urdf: str
    urdf_source: str
    ground_height: float = 0.0
    ground_normal: tuple = (0.0, 0.0, 1.0)
    truncated: bool = False


def _choose_namespace(found: dict, requested, path: str, bag) -> str:
    """The namespace whose joint states and base state the bag holds (requested, the only
    one, or the first in sorted order, with a warning)."""
    complete = sorted(ns for ns, kinds in found.items()
                      if bag.counts.get(kinds.get("joints"), 0)
                      and bag.counts.get(kinds.get("base"), 0))
    if requested is not None:
        ns = "/" + requested.strip("/") if requested.strip("/") else ""
        if ns in complete:
            return ns
        have = ", ".join(repr(n or "/") for n in complete) or "none"
        raise ViewError(f"{path}: no {TOPIC_JOINT_STATES} and {TOPIC_BASE_STATE} messages under the namespace "
                        f"{ns or '/'!r} (namespaces with both: {have})")
    if not complete:
        missing = []
        for kind in ("joints", "base"):
            rel, typ = TOPICS[kind]
            if not any(bag.counts.get(k.get(kind), 0) for k in found.values()):
                missing.append(f"{rel} ({typ})")
        topics = ", ".join(f"{t} ({ty or 'no schema'})" for t, ty in sorted(bag.types.items()))
        if not missing:
            raise ViewError(f"{path}: {TOPIC_JOINT_STATES} and {TOPIC_BASE_STATE} are in different namespaces; "
                            f"the bag's topics: {topics or 'none'}")
        raise ViewError(f"{path}: no messages on {' nor '.join(missing)}, so there is no robot "
                        f"motion to replay; the bag's topics: {topics or 'none'}")
    if len(complete) > 1:
        warn(f"{path}: robots under the namespaces {', '.join(n or '/' for n in complete)}; "
             f"replaying {complete[0] or '/'} (--namespace picks another)")
    return complete[0]


def _urdf_from_bag(bag, topics: dict, path: str):
    """(URDF text, where it came from): the namespace's robot_description topic, the
    starleth.urdf attachment (sim_node's recorder), another .urdf attachment, or the
    package's URDF."""
    topic = topics.get("description")
    if topic and bag.messages.get(topic):
        try:
            return bag.decoders[topic](bag.messages[topic][0][1]).data, f"topic {topic}"
        except Exception as e:   # a damaged message: try the attachments
            warn(f"{path}: cannot decode {topic} ({e}); using another URDF")
    names = sorted(bag.attachments, key=lambda n: (n != "starleth.urdf", n))
    for name in names:
        if name.endswith(".urdf"):
            try:
                return bag.attachments[name].decode("utf-8"), f"attachment {name}"
            except UnicodeDecodeError:
                continue
    with open(urdf_path()) as f:
        return f.read(), "package urdf/starleth.urdf (none in the bag)"


def _ground_from_metadata(bag):
    """(height, unit normal) of the ground from the recording's physics configuration
    (sim_node's 'starleth_sim' metadata), else the default flat ground z = 0."""
    import yaml
    text = bag.metadata.get("starleth_sim", {}).get("physics_config")
    try:
        ground = (yaml.safe_load(text) or {}).get("ground", {}) if text else {}
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
    except (ValueError, TypeError, AttributeError, OverflowError, RecursionError,
            yaml.YAMLError):
        return 0.0, (0.0, 0.0, 1.0)
    n = n / np.linalg.norm(n)
    return h, tuple(float(x) for x in n)


def read_recording(path: str, namespace: str | None = None, salvage: bool = False):
    """The Recording of one robot of a bag. Raises BagError for a bag that cannot be
    read, ViewError for one without joint states or base state."""
    bag = read_messages(path, _select, salvage=salvage, decode=False,
                                 on_warning=warn)
    found = {}                                   # namespace -> {kind: topic}
    for topic in bag.types:
        m = match_topic(topic)
        if m is not None and _select(topic, bag.types[topic]):
            found.setdefault(m[1], {})[m[0]] = topic
        elif m is not None:
            warn(f"{path}: topic {topic} has type {bag.types[topic] or '(no schema)'}, "
                 f"expected {TOPICS[m[0]][1]}; ignored")
    ns = _choose_namespace(found, namespace, path, bag)
    topics = found[ns]
    urdf, source = _urdf_from_bag(bag, topics, path)
    rec = Recording(path=path, namespace=ns, joints=Series.from_bag(bag, topics["joints"]),
                    base=Series.from_bag(bag, topics["base"]), wrenches={}, urdf=urdf,
                    urdf_source=source, truncated=bag.truncated)
    for foot in FEET:
        if topics.get(foot) and bag.messages.get(topics[foot]):
            rec.wrenches[foot] = Series.from_bag(bag, topics[foot])
        else:
            warn(f"{path}: no messages on {ns}/{TOPICS[foot][0]}; no {foot} force arrow")
    for series in (rec.joints, rec.base):
        if not len(series):
            n = bag.counts.get(series.topic, 0)
            raise ViewError(f"{path}: none of the {n} message(s) on {series.topic} could be "
                            "read, so there is no robot motion to replay")
    rec.ground_height, rec.ground_normal = _ground_from_metadata(bag)
    return rec


# =========================================================================================
# frames and kinematics
# =========================================================================================
def select_frames(t_ns: np.ndarray, fps: float) -> np.ndarray:
    """Indices of the samples (times t_ns, sorted) shown at fps: for each time
    t_0 + k/fps (k = 0 .. span * fps, rounded to the nanosecond) the latest sample at or
    before it, each once, plus the last sample.

    Worked out per sample, not per grid time: sample i is shown when the first grid time at
    or after it comes before the next sample. Memory and time go with the number of samples,
    whatever the span of their stamps (two samples 2e9 s apart at 50 fps are 2 frames, not
    1e11 grid times)."""
    n = t_ns.size
    if n == 0:
        return np.zeros(0, dtype=int)
    rel = t_ns - t_ns[0]                                     # int64: exact
    after = np.append(rel[1:], np.iinfo(np.int64).max)       # the next sample's time
    step = 1e9 / fps                                         # [ns] between grid times
    if step <= 1.0:   # a grid time at every nanosecond: each distinct stamp is a frame
        shown = rel < after
        shown[-1] = True
        return np.flatnonzero(shown)
    last_k = math.floor((t_ns[-1] - t_ns[0]) * 1e-9 * fps + 1e-9)

    def grid(k):                                             # the grid times, t_0 relative
        return np.clip(np.round(k * step), -2.0 ** 62, 2.0 ** 62).astype(np.int64)

    # k: the first grid index whose time is at or after each sample (the estimate
    # rel / step is off by one or two where the grid's rounding bites)
    k = np.ceil(rel / step)
    for _ in range(8):
        down = (k > 0) & (grid(k - 1) >= rel)
        up = grid(k) < rel
        if not (down.any() or up.any()):
            break
        k = k - down + up
    shown = (k <= last_k) & (grid(k) < after)
    shown[-1] = True
    return np.flatnonzero(shown)


def load_description(urdf: str, source: str) -> RobotDescription:
    """The project's free-flyer model of a URDF (RobotDescription.from_urdf_xml)."""
    try:
        return RobotDescription.from_urdf_xml(urdf, name="robot")
    except Exception as e:   # pin's parser and the contact reader raise several kinds
        raise ViewError(f"the URDF ({source}) cannot be used: {type(e).__name__}: {e}") from None


def _joint_indices(desc: RobotDescription):
    """{joint name: (idx_q, nq)} of the model's joints after the free-flyer root."""
    m = desc.model
    out = {}
    for name in desc.joint_names:
        j = m.joints[m.getJointId(name)]
        out[name] = (j.idx_q, j.nq)
    return out


def _usable(*values) -> bool:
    """Whether recorded numbers can be drawn: finite, at most MAX_VALUE in magnitude."""
    try:
        return all(math.isfinite(v) and abs(v) <= MAX_VALUE for v in values)
    except (TypeError, ValueError, OverflowError):    # not numbers at all
        return False


def _fields(series: Series, i: int, read):
    """read(message i of series): its fields, or a ViewError where the message lacks them
    (a bag whose schema for the type is not the ROS one)."""
    msg = series.message(i)
    try:
        return read(msg)
    except (AttributeError, TypeError) as e:
        raise ViewError(f"message {i} on {series.topic} lacks the fields of its type "
                        f"({type(e).__name__}: {e})") from None


def _warn_unusable(rec: Recording, unusable: dict, what: str) -> None:
    for topic, idx in unusable.items():
        warn(f"{rec.path}: {len(idx)} message(s) on {topic} hold NaN, infinite or absurd "
             f"values (beyond {MAX_VALUE:g}); {what}")


def configurations(rec: Recording, desc: RobotDescription, frames: np.ndarray):
    """(N, nq) pin configurations at the joint-state samples `frames`: base pose from the
    latest base state at or before each, joint positions by name (a joint a message lacks
    keeps its previous value, neutral at first; so does a value that is NaN, infinite or
    beyond MAX_VALUE, and a base pose holding one, with a warning)."""
    import pinocchio as pin
    model = desc.model
    index = _joint_indices(desc)
    q = np.tile(pin.neutral(model), (frames.size, 1))
    seen = set()
    unusable = {}                                 # topic -> indices of such messages
    prev = q[0].copy()
    bases = rec.base.latest(rec.joints.t_ns[frames])
    for row, (i, b) in enumerate(zip(frames, bases)):
        q[row] = prev
        names, positions = _fields(rec.joints, i, lambda m: (list(m.name), list(m.position)))
        if len(positions) == len(names):
            for name, value in zip(names, positions):
                slot = index.get(name) if isinstance(name, str) else None
                if slot is None:
                    continue
                if not _usable(value):
                    unusable.setdefault(rec.joints.topic, set()).add(int(i))
                    continue
                seen.add(name)
                if slot[1] == 1:
                    q[row, slot[0]] = value
                else:   # continuous joint: (cos, sin)
                    q[row, slot[0]:slot[0] + 2] = (math.cos(value), math.sin(value))
        pose = _fields(rec.base, b, lambda m: (
            m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z,
            m.pose.pose.orientation.x, m.pose.pose.orientation.y, m.pose.pose.orientation.z,
            m.pose.pose.orientation.w))
        if _usable(*pose):
            quat = np.array(pose[3:], dtype=float)
            n = np.linalg.norm(quat)
            q[row, 0:3] = pose[:3]
            q[row, 3:7] = quat / n if n > 1e-9 else (0.0, 0.0, 0.0, 1.0)
        else:
            unusable.setdefault(rec.base.topic, set()).add(int(b))
        prev = q[row]
    _warn_unusable(rec, unusable, "drawn with the previous value")
    never = [n for n in desc.joint_names if n not in seen]
    if never:
        warn(f"{rec.path}: joint(s) {', '.join(never)} of the URDF are in no joint state; "
             "drawn at 0")
    return q


def body_poses(desc: RobotDescription, q: np.ndarray, joint_ids):
    """(N, nb, 7) world poses (x y z qx qy qz qw) of the pin joints joint_ids (forward
    kinematics at each configuration), and the (N, njoints) list of oMi for reuse."""
    import pinocchio as pin
    model = desc.model
    data = model.createData()
    poses = np.zeros((q.shape[0], len(joint_ids), 7))
    placements = []
    for k in range(q.shape[0]):
        pin.forwardKinematics(model, data, q[k])
        oMi = [data.oMi[j].copy() for j in range(model.njoints)]
        placements.append(oMi)
        for b, j in enumerate(joint_ids):
            poses[k, b, :3] = oMi[j].translation
            poses[k, b, 3:] = pin.Quaternion(oMi[j].rotation).coeffs()   # x y z w
    return poses, placements


def contact_arrows(rec: Recording, desc: RobotDescription, frames, placements, force_scale):
    """(N, 4, 6) arrows (origin xyz, vector xyz [m]) per frame and foot: from the foot
    contact point (centre of the foot's contact sphere minus its radius along the ground
    normal) along force * force_scale; zeros for a foot without force messages, and no
    arrow (a zero vector, with a warning) for a force that is NaN, infinite or beyond
    MAX_VALUE."""
    arrows = np.zeros((frames.size, len(FEET), 6))
    normal = np.asarray(rec.ground_normal)
    contacts = {c.name: c for c in desc.contacts}
    t_frames = rec.joints.t_ns[frames]
    unusable = {}                                 # topic -> indices of such messages
    for f, foot in enumerate(FEET):
        spec = contacts.get(f"{foot}_foot")
        series = rec.wrenches.get(foot)
        if series is None:
            continue
        if spec is None:
            warn(f"{rec.path}: the URDF has no contact '{foot}_foot'; no {foot} force arrow")
            continue
        for row, i in enumerate(series.latest(t_frames)):
            centre = placements[row][spec.joint].act(spec.local)
            force = _fields(series, i, lambda m: (m.wrench.force.x, m.wrench.force.y,
                                                  m.wrench.force.z))
            arrows[row, f, :3] = centre - spec.radius * normal
            if _usable(*force):
                arrows[row, f, 3:] = np.array(force, dtype=float) * force_scale
            else:
                unusable.setdefault(series.topic, set()).add(int(i))
    _warn_unusable(rec, unusable, "no arrow drawn for them")
    return arrows


# =========================================================================================
# the scene (meshcat set_object commands)
# =========================================================================================
def _matrix(M4) -> list:
    """A 4x4 homogeneous matrix as meshcat/three.js want it: 16 numbers, column-major."""
    return [float(round(x, 6)) + 0.0 for x in np.asarray(M4, dtype=float).T.reshape(16)]


def _mesh(uid: str, name: str, geometry: dict, color: int, matrix, **material) -> dict:
    """A three.js JSON object (format 4.5, what meshcat's set_object takes): one Mesh."""
    mat = {"uuid": f"{uid}/material", "type": "MeshLambertMaterial", "color": color,
           "side": 2, **material}
    return {"metadata": {"version": 4.5, "type": "Object"},
            "geometries": [dict(geometry, uuid=f"{uid}/geometry")],
            "materials": [mat],
            "object": {"uuid": uid, "type": "Mesh", "name": name,
                       "geometry": f"{uid}/geometry", "material": f"{uid}/material",
                       "matrix": _matrix(matrix)}}


_ROT_Y_TO_Z = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])


def _visual_geometry(geom):
    """(three.js geometry dict, extra 4x4 intrinsic transform, colour) of a URDF <geometry>
    element, or None for a mesh or an unknown shape."""
    box, sphere, cyl = geom.find("box"), geom.find("sphere"), geom.find("cylinder")
    if box is not None:
        x, y, z = (float(v) for v in box.get("size").split())
        return {"type": "BoxGeometry", "width": x, "height": y, "depth": z}, np.eye(4), \
            ROBOT_COLOR
    if sphere is not None:
        return {"type": "SphereGeometry", "radius": float(sphere.get("radius")),
                "widthSegments": 20, "heightSegments": 14}, np.eye(4), FOOT_COLOR
    if cyl is not None:   # three.js cylinders lie along y, URDF ones along z
        r = float(cyl.get("radius"))
        return {"type": "CylinderGeometry", "radiusTop": r, "radiusBottom": r,
                "height": float(cyl.get("length")), "radialSegments": 20}, _ROT_Y_TO_Z, \
            LEG_COLOR
    return None


def robot_visuals(desc: RobotDescription):
    """[(pin joint id, visual name, three.js object)] of the URDF's <visual> elements, each
    placed in the frame of the joint that moves it (fixed joints merged by pin)."""
    import pinocchio as pin
    model = desc.model
    out = []
    for link in ET.fromstring(desc.urdf_xml).findall("link"):
        lname = link.get("name")
        for k, vis in enumerate(link.findall("visual")):
            geom = vis.find("geometry")
            try:
                shape = _visual_geometry(geom) if geom is not None else None
            except (TypeError, ValueError, AttributeError):   # missing/odd attributes
                shape = None
            if shape is None:
                warn(f"link {lname}: visual {k} is not a box, sphere or cylinder; not drawn")
                continue
            if not model.existFrame(lname):
                continue
            frame = model.frames[model.getFrameId(lname)]
            placement = frame.placement * _origin(vis)
            geometry, intrinsic, color = shape
            name = f"{lname}_{k}" if len(link.findall("visual")) > 1 else lname
            obj = _mesh(f"robot/{name}", name, geometry, color,
                        pin.SE3(placement).homogeneous @ intrinsic)
            out.append((int(frame.parentJoint), name, obj))
    return out


def _ground_pose(height, normal, centre_xy):
    """4x4 pose of the ground plane: z axis along the normal, origin on the plane below
    centre_xy."""
    n = np.asarray(normal, dtype=float)
    z = np.array([0.0, 0.0, 1.0])
    axis, c = np.cross(z, n), float(np.dot(z, n))
    R = np.eye(3)
    if np.linalg.norm(axis) > 1e-9:
        K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        R = np.eye(3) + K + K @ K / (1.0 + c)
    x, y = centre_xy
    pz = (height - n[0] * x - n[1] * y) / n[2] if abs(n[2]) > 0.1 else 0.0
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, ((x, y, pz) if abs(n[2]) > 0.1 else height * n)
    return M


def _png_rgb(pixels) -> bytes:
    """A PNG file of an (h, w, 3) uint8 RGB image."""
    pixels = np.asarray(pixels, dtype=np.uint8)
    h, w, _ = pixels.shape
    raw = b"".join(b"\x00" + pixels[r].tobytes() for r in range(h))

    def chunk(tag, data):
        return (struct.pack(">I", len(data)) + tag + data
                + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def _ground_object(size: float, tile: float) -> dict:
    """The ground: a size x size plane (in its xy plane), unlit, with a checkerboard
    texture (a 2x2 PNG repeated every `tile` m)."""
    a, b = GROUND_COLORS
    png = base64.b64encode(_png_rgb([[a, b], [b, a]])).decode("ascii")
    obj = _mesh("ground", "ground", {"type": "PlaneGeometry", "width": size, "height": size},
                0xFFFFFF, np.eye(4), type="MeshBasicMaterial", map="ground/texture")
    obj["images"] = [{"uuid": "ground/image", "url": "data:image/png;base64," + png}]
    obj["textures"] = [{"uuid": "ground/texture", "image": "ground/image",
                        "wrap": [1000, 1000],                 # RepeatWrapping
                        "repeat": [size / tile, size / tile],
                        "magFilter": 1003}]                   # NearestFilter
    return obj


def scene_commands(desc, visuals, rec: Recording, trunk_xy) -> list:
    """meshcat commands that build the scene: background, a checkerboard ground plane (in
    place of meshcat's grid), the robot's visuals under /world/starleth/<joint>, the force
    arrows under /world/forces/<foot>, the camera. The page follows the trunk by moving
    /world so that the trunk stays at the origin, which meshcat's orbit controls turn the
    camera around."""
    model = desc.model
    lo, hi = trunk_xy.min(axis=0), trunk_xy.max(axis=0)
    tile = 2 * GROUND_SQUARE
    centre = np.round((lo + hi) / 2 / tile) * tile         # squares on multiples of 0.5 m
    size = tile * 2 * math.ceil((float(np.max(hi - lo)) + 40.0) / (2 * tile))
    cmds = [
        {"type": "set_property", "path": "/Background", "property": "top_color",
         "value": list(SKY_TOP)},
        {"type": "set_property", "path": "/Background", "property": "bottom_color",
         "value": list(SKY_BOTTOM)},
        {"type": "set_property", "path": "/Axes", "property": "visible", "value": False},
        {"type": "set_property", "path": "/Grid", "property": "visible", "value": False},
        {"type": "set_object", "path": "/world/ground", "object": _ground_object(size, tile)},
        {"type": "set_transform", "path": "/world/ground", "matrix": _matrix(
            _ground_pose(rec.ground_height, rec.ground_normal, centre))},
    ]
    for joint, name, obj in visuals:
        cmds.append({"type": "set_object", "path": f"/world/starleth/{model.names[joint]}/{name}",
                     "object": obj})
    shaft = np.eye(4)
    shaft[1, 3] = 0.5                                      # unit cylinder from y=0 to y=1
    head = np.eye(4)
    head[1, 3] = ARROW_HEAD / 2                            # cone from y=0 to the tip
    for foot in FEET:
        if foot not in rec.wrenches:
            continue
        cmds.append({"type": "set_object", "path": f"/world/forces/{foot}/shaft",
                     "object": _mesh(f"forces/{foot}/shaft", f"{foot} force", {
                         "type": "CylinderGeometry", "radiusTop": ARROW_RADIUS,
                         "radiusBottom": ARROW_RADIUS, "height": 1.0, "radialSegments": 12},
                         ARROW_COLOR, shaft)})
        cmds.append({"type": "set_object", "path": f"/world/forces/{foot}/head",
                     "object": _mesh(f"forces/{foot}/head", f"{foot} force head", {
                         "type": "ConeGeometry", "radius": 2.5 * ARROW_RADIUS, "height": ARROW_HEAD,
                         "radialSegments": 12}, ARROW_COLOR, head)})
    # the camera's position relative to the point it orbits (the origin), given in the
    # Y-up frame of /Cameras/default/rotated: (x, z, -y) of the world
    ox, oy, oz = CAMERA_OFFSET
    cmds.append({"type": "set_property", "path": "/Cameras/default/rotated/<object>",
                 "property": "position", "value": [ox, oz, -oy]})
    return cmds


# =========================================================================================
# the page
# =========================================================================================
def _rounded(a, decimals) -> list:
    """A flat list of numbers rounded to `decimals` (no negative zeros)."""
    return (np.round(np.asarray(a, dtype=float).reshape(-1), decimals) + 0.0).tolist()


def _script_json(obj) -> str:
    """JSON that is safe inside a <script> element."""
    text = json.dumps(obj, separators=(",", ":"), allow_nan=False)
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


def meshcat_bundle() -> tuple:
    """(main.min.js text, its licence notices) of the installed meshcat package."""
    try:
        import meshcat
    except ImportError:
        raise ViewError("the Python package 'meshcat' is not installed (pip install meshcat): "
                        "its bundled three.js viewer is inlined into the page") from None
    base = os.path.join(os.path.dirname(meshcat.__file__), "viewer")
    js_path = os.path.join(base, "dist", "main.min.js")
    try:
        with open(js_path, encoding="utf-8") as f:
            js = f.read()
    except OSError as e:
        raise ViewError(f"cannot read meshcat's viewer {js_path}: {e.strerror or e}") from None
    notices = []
    for name in ("LICENSE", os.path.join("dist", "main.min.js.LICENSE.txt")):
        try:
            with open(os.path.join(base, name), encoding="utf-8") as f:
                notices.append(f.read().strip())
        except OSError:
            pass
    try:
        with open(os.path.join(base, "dist", "main.min.js.THIRD_PARTY_LICENSES.json")) as f:
            third = json.load(f)
        notices.append("Bundled packages: " + ", ".join(
            f"{p.get('name')} {p.get('version', '')} ({p.get('license', '?')})" for p in third))
    except (OSError, ValueError, AttributeError):
        pass
    if "</script" in js.lower():
        raise ViewError(f"{js_path} contains '</script' and cannot be inlined")
    return js, "\n\n".join(notices).replace("*/", "* /")


def replay_data(rec: Recording, desc: RobotDescription, fps: float, force_scale: float):
    """The page's data: frame times, body poses, force arrows and what they mean; and the
    scene commands."""
    frames = select_frames(rec.joints.t_ns, fps)
    q = configurations(rec, desc, frames)
    visuals = robot_visuals(desc)
    joint_ids = sorted({j for j, _, _ in visuals} | {1})   # 1: the free-flyer (trunk)
    poses, placements = body_poses(desc, q, joint_ids)
    arrows = contact_arrows(rec, desc, frames, placements, force_scale)
    if not np.isfinite(np.round(arrows, POSITION_DECIMALS)).all():
        raise ViewError(f"force scale {force_scale:g} m/N: the force arrows are too long to "
                        "write down")
    t0 = min(rec.joints.t_ns[0], rec.base.t_ns[0])
    t = (rec.joints.t_ns[frames] - t0) * 1e-9
    n = rec.joints.t_ns.size
    span = float(rec.joints.t_ns[-1] - rec.joints.t_ns[0]) * 1e-9
    rate = (n - 1) / span if n > 1 and span > 0 else 0.0     # all at one stamp: no rate
    step = int(np.median(np.diff(frames))) if frames.size > 1 else 1
    data = {
        "format": FORMAT, "source": os.path.basename(os.path.abspath(rec.path).rstrip(os.sep)),
        "namespace": rec.namespace, "frames": int(frames.size), "fps": fps,
        "samples": n, "sample_rate": round(rate, 3), "duration": round(float(t[-1]), 4),
        "t0_ns": int(t0), "t": _rounded(t, TIME_DECIMALS),     # t: seconds after t0_ns
        "bodies": [desc.model.names[j] for j in joint_ids], "trunk": joint_ids.index(1),
        "poses": [], "feet": list(FEET),
        "has_force": [foot in rec.wrenches for foot in FEET],
        "arrows": _rounded(arrows, POSITION_DECIMALS), "force_scale": force_scale,
        "arrow_head": ARROW_HEAD,
        "rounding": {"position": 10.0 ** -POSITION_DECIMALS,
                     "quaternion": 10.0 ** -QUATERNION_DECIMALS,
                     "time": 10.0 ** -TIME_DECIMALS},
        "camera": {"offset": list(CAMERA_OFFSET), "height_window": CAMERA_HEIGHT_WINDOW},
        "urdf_source": rec.urdf_source,
        "ground": {"height": rec.ground_height, "normal": list(rec.ground_normal)},
        "subsampling": f"1 in {step} samples" if step > 1 else "every sample",
    }
    poses[:, :, :3] = np.round(poses[:, :, :3], POSITION_DECIMALS)
    poses[:, :, 3:] = np.round(poses[:, :, 3:], QUATERNION_DECIMALS)
    data["poses"] = (poses.reshape(-1) + 0.0).tolist()
    scene = scene_commands(desc, visuals, rec, poses[:, data["trunk"], :2])
    return data, scene


def _info_lines(data: dict) -> tuple:
    """The page's explanation: (always shown: frames and subsampling, the force scale;
    under 'more': rounding, URDF, controls)."""
    ns = f" · namespace {data['namespace']}" if data["namespace"] else ""
    rate = f" at {data['sample_rate']:g} Hz" if data["sample_rate"] else ""
    scale = data["force_scale"]
    shown = [
        f"{data['duration']:.2f} s{ns} · {data['frames']} frames at {data['fps']:g} fps: "
        f"{data['subsampling']} of the {data['samples']} joint states{rate}",
        f"green arrows: foot contact forces, {scale:g} m/N (1 m = {1 / scale:g} N)",
    ]
    more = [
        "Each frame shows the latest recorded sample at or before its time (sample and "
        "hold, no interpolation); the last sample is always a frame.",
        f"Link poses: Pinocchio forward kinematics of the recorded joint_states and "
        f"starleth/base_state; rounded: {ROUNDING_TEXT}.",
        "Arrows start at the foot contact points (sphere centre minus radius along the "
        "ground normal); forces in the world frame.",
        f"URDF: {data['urdf_source']}.",
        "Mouse: drag to orbit, scroll to zoom, right-drag to pan. Keys: space play/pause, "
        "←/→ step.",
        "URL options: ?t=1.5&paused=1&speed=0.5&follow=0.",
    ]
    return shown, more


def _info_html(shown, more) -> str:
    return ("<br>".join(html.escape(line, quote=False) for line in shown)
            + "<details><summary>more</summary>"
            + "<br>".join(html.escape(line, quote=False) for line in more) + "</details>")


def render_html(data: dict, scene: list) -> str:
    """The self-contained page: meshcat's viewer, the data, the player."""
    js, notices = meshcat_bundle()
    fills = {
        "TITLE": html.escape(f"StarlETH replay: {data['source']}"),
        "INFO": _info_html(*_info_lines(data)),
        "LAST": str(data["frames"] - 1),
        "MESHCAT": (f"/*! meshcat's viewer (meshcat {_meshcat_version()}, "
                    f"meshcat/viewer/dist/main.min.js), inlined by {PROG}.\n\n{notices}\n*/\n"
                    + js),
        "DATA": _script_json(data),
        "SCENE": _script_json(scene),
    }
    # one pass over the template, so that nothing inside the fills is taken for a marker
    with open(PAGE_TEMPLATE, encoding="utf-8") as f:
        page = f.read()
    pieces = re.split(r"__(TITLE|INFO|LAST|MESHCAT|DATA|SCENE)__", page)
    return "".join(p if i % 2 == 0 else fills[p] for i, p in enumerate(pieces))


def _meshcat_version() -> str:
    try:
        from importlib.metadata import version
        return version("meshcat")
    except Exception:
        return "?"


#: the page template (HTML + the player's JavaScript), beside this module; __NAME__ markers
#: are filled by render_html
PAGE_TEMPLATE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "view_page.html")


# =========================================================================================
# entry points
# =========================================================================================
def default_output(bag_path: str) -> str:
    """run.mcap -> run.html beside it; a bag directory d/ -> d.html beside it."""
    p = os.path.abspath(bag_path).rstrip(os.sep)
    stem = os.path.splitext(p)[0] if os.path.isfile(p) else p
    return stem + ".html"


def write_html(bag_path: str, out_path: str | None = None, fps: float = DEFAULT_FPS,
               force_scale: float = DEFAULT_FORCE_SCALE, namespace: str | None = None,
               salvage: bool = False) -> dict:
    """Write the replay page of a bag. Returns {'path', 'frames', 'bytes', 'duration',
    'fps', 'samples', 'namespace', 'urdf_source', 'seconds'}. Raises BagError (a bag
    that cannot be read) or ViewError (nothing to replay, bad options, unusable URDF)."""
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise ViewError(f"fps must be a positive number, got {fps!r}")
    if not (isinstance(force_scale, (int, float)) and math.isfinite(force_scale)
            and force_scale > 0):
        raise ViewError(f"force scale must be a positive number [m/N], got {force_scale!r}")
    t_start = time.perf_counter()
    rec = read_recording(bag_path, namespace=namespace, salvage=salvage)
    desc = load_description(rec.urdf, rec.urdf_source)
    data, scene = replay_data(rec, desc, float(fps), float(force_scale))
    page = render_html(data, scene)
    out = out_path or default_output(bag_path)
    d = os.path.dirname(os.path.abspath(out))
    os.makedirs(d, exist_ok=True)
    tmp = out + ".part"
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(page)
    os.replace(tmp, out)
    return {"path": out, "frames": data["frames"], "bytes": os.path.getsize(out),
            "duration": data["duration"], "fps": float(fps), "samples": data["samples"],
            "namespace": rec.namespace, "urdf_source": rec.urdf_source,
            "seconds": round(time.perf_counter() - t_start, 3)}


def build_parser():
    ap = argparse.ArgumentParser(
        prog=PROG,
        description="Replay a recorded StarlETH run (MCAP bag) in 3D in the browser: writes "
        "one self-contained HTML file (meshcat's three.js viewer and the data inlined; no "
        "server, no network). The robot from the bag's URDF, poses from Pinocchio forward "
        "kinematics of the recorded joint_states and starleth/base_state, the ground, and "
        "the foot contact forces as arrows; play/pause, scrub, speed, camera following the "
        "trunk.",
        epilog=f"Subsampling: one frame every 1/FPS s of sim time, each the latest recorded "
        f"sample at or before it (no interpolation), plus the last sample. Rounding: "
        f"{ROUNDING_TEXT}. In the page, ?t=1.5&paused=1 shows t = 1.5 s paused (also "
        f"speed=X, follow=0). Exit status: 0 ok, 1 a bag that cannot be read or holds no "
        f"joint states / base state, 2 bad arguments.")
    ap.add_argument("bag", metavar="RUN.mcap",
                    help="MCAP bag file, or a rosbag2 directory holding .mcap files")
    ap.add_argument("-o", "--output", metavar="RUN.html",
                    help="the HTML file to write (default: the bag's name with .html, "
                         "beside it)")
    ap.add_argument("--fps", type=float, default=DEFAULT_FPS,
                    help=f"frames per second of sim time kept in the page (default "
                         f"{DEFAULT_FPS:g}; at or above the recording's rate: every sample)")
    ap.add_argument("--force-scale", type=float, default=DEFAULT_FORCE_SCALE, metavar="M_PER_N",
                    help=f"arrow length per newton of contact force [m/N] (default "
                         f"{DEFAULT_FORCE_SCALE:g}: 1 m = {1 / DEFAULT_FORCE_SCALE:g} N)")
    ap.add_argument("--namespace", metavar="NS",
                    help="the robot's namespace in a bag with several (e.g. /robot1; default: "
                         "the only one, or the first)")
    ap.add_argument("--salvage", action="store_true",
                    help="read a truncated/damaged bag up to the damage instead of failing")
    return ap


def run(argv=None) -> int:
    ap = build_parser()
    a = ap.parse_args(argv)
    if not (math.isfinite(a.fps) and a.fps > 0):
        ap.error("--fps must be a positive number")
    if not (math.isfinite(a.force_scale) and a.force_scale > 0):
        ap.error("--force-scale must be a positive number [m/N]")
    info = write_html(a.bag, a.output, fps=a.fps, force_scale=a.force_scale,
                      namespace=a.namespace, salvage=a.salvage)
    print(f"wrote {info['path']}: {info['frames']} frames at {info['fps']:g} fps of "
          f"{info['samples']} samples, {info['duration']:.2f} s, "
          f"{info['bytes'] / 1e6:.2f} MB ({info['seconds']:.1f} s)")
    return 0


def main(argv=None) -> int:
    """Console script: exit status 0, or 1 with a one-line message (no traceback) for a bag
    that cannot be replayed, 2 for bad arguments."""
    return run_console_script(PROG, run, argv, (BagError, ViewError))


if __name__ == "__main__":
    sys.exit(main())
