"""TF for sim_node (ROS-free): the robot's frame tree, its transforms from Pinocchio's
forward kinematics, and ``tf2_msgs/msg/TFMessage`` written as CDR bytes.

Viewers such as Foxglove and Lichtblick draw the URDF from ``robot_description`` but move its
links only through TF (they do not apply ``joint_states``), so a recording needs ``/tf``: the
base pose in the world frame and, as ``robot_state_publisher`` does, one transform per
movable URDF joint (parent link -> child link at the joint's angle); the fixed joints go once
to ``/tf_static``.

There is no tf2_msgs Python package outside a full ROS install, so the message is written
here (little-endian CDR, XCDR1, as rmw_fastrtps writes it) from a template whose stamps and
numbers are patched per message; ``test_tf.py`` checks the bytes against rosbags' own
serialiser. Layout of ``TFMessage``: a uint32 count, then per ``TransformStamped``:
header (int32 sec, uint32 nanosec, string frame_id), string child_frame_id, translation
(3 float64, 8-byte aligned relative to the payload) and rotation (x, y, z, w float64).
"""
from __future__ import annotations

import struct
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

TF_TYPE = "tf2_msgs/msg/TFMessage"
#: the .msg text of tf2_msgs/msg/TFMessage (not installed without a full ROS install); the
#: recorder appends the definitions it depends on from geometry_msgs
TF_MSG_TEXT = "geometry_msgs/TransformStamped[] transforms\n"
_ORIGIN = 4     # the CDR payload starts after the 4-byte encapsulation header


@dataclass(frozen=True)
class JointEdge:
    """One URDF joint as an edge of the frame tree."""

    name: str
    type: str          # revolute | continuous | prismatic | fixed | floating | planar
    parent: str        # link names
    child: str

    @property
    def static(self) -> bool:
        return self.type == "fixed"


def urdf_joint_edges(urdf_xml: str) -> list[JointEdge]:
    """The joints of a URDF in file order (parent and child link of each)."""
    root = ET.fromstring(urdf_xml)
    edges = []
    for j in root.findall("joint"):
        parent, child = j.find("parent"), j.find("child")
        if parent is None or child is None:
            raise ValueError(f"URDF joint '{j.get('name')}' without parent or child link")
        edges.append(JointEdge(j.get("name"), j.get("type", "fixed"), parent.get("link"),
                               child.get("link")))
    return edges


def root_link(edges) -> str:
    children = {e.child for e in edges}
    roots = {e.parent for e in edges} - children
    if len(roots) != 1:
        raise ValueError(f"the URDF's links do not form one tree (roots: {sorted(roots)})")
    return roots.pop()


def base_link(urdf_xml: str) -> str:
    """The URDF's root link: the floating base, the child of world on /tf."""
    return root_link(urdf_joint_edges(urdf_xml))


class FrameTree:
    """The TF edges of a robot: world -> root link (the floating base) and one per URDF joint,
    each (parent frame, child frame); `transforms(q)` gives their poses from Pinocchio's
    forward kinematics of the minimal-coordinate configuration q (free flyer first)."""

    def __init__(self, model, urdf_xml: str, world_frame: str = "world", prefix: str = ""):
        self.model = model
        self.data = model.createData()
        edges = urdf_joint_edges(urdf_xml)
        self.root = root_link(edges)
        self.world_frame = world_frame
        self.prefix = prefix
        self.dynamic = [(None, self.root)] + [(e.parent, e.child) for e in edges
                                              if not e.static]
        self.static = [(e.parent, e.child) for e in edges if e.static]
        links = {self.root} | {e.child for e in edges}
        self._frame_id = {}
        for link in links:
            # (a link's body frame: a joint may have the link's name, as ANYmal C's do)
            if not model.existFrame(link, pin.FrameType.BODY):
                raise ValueError(f"link '{link}' is not a frame of the model")
            self._frame_id[link] = model.getFrameId(link, pin.FrameType.BODY)

    def frame_name(self, link: str | None) -> str:
        return self.world_frame if link is None else self.prefix + link

    def names(self, edges):
        return [(self.frame_name(p), self.frame_name(c)) for p, c in edges]

    def transforms(self, q, edges) -> np.ndarray:
        """(len(edges), 7) [x, y, z, qx, qy, qz, qw] of each edge's child frame in its parent
        frame at configuration q (minimal coordinates: pin's free flyer + joint angles)."""
        pin.framesForwardKinematics(self.model, self.data, np.asarray(q, dtype=float))
        oMf = self.data.oMf
        frame_id = self._frame_id
        xyzquat = pin.SE3ToXYZQUAT     # translation, then Eigen's quaternion of the rotation
        out = np.empty((len(edges), 7))
        for k, (parent, child) in enumerate(edges):
            M = oMf[frame_id[child]]
            if parent is not None:
                M = oMf[frame_id[parent]].actInv(M)
            out[k] = xyzquat(M)                                    # x, y, z, qx, qy, qz, qw
        return out


def _pad(buf: bytearray, align: int):
    while (len(buf) - _ORIGIN) % align:
        buf.append(0)


def _string(buf: bytearray, s: str):
    _pad(buf, 4)
    data = s.encode("utf-8") + b"\0"
    buf += struct.pack("<I", len(data))
    buf += data


class TfMessageCdr:
    """CDR bytes of a TFMessage with a fixed list of (parent, child) frame names: a template
    built once, whose stamps and poses are patched per message."""

    def __init__(self, frames):
        buf = bytearray(b"\x00\x01\x00\x00")
        buf += struct.pack("<I", len(frames))
        self._stamp_at, self._pose_at = [], []
        for parent, child in frames:
            _pad(buf, 4)
            self._stamp_at.append(len(buf))
            buf += struct.pack("<iI", 0, 0)
            _string(buf, parent)
            _string(buf, child)
            _pad(buf, 8)
            self._pose_at.append(len(buf))
            buf += struct.pack("<7d", 0, 0, 0, 0, 0, 0, 1)
        self._template = bytes(buf)
        self._stamp_at = np.array(self._stamp_at)
        self._pose_at = np.array(self._pose_at)
        self.n = len(frames)

    def build(self, sec: int, nanosec: int, poses) -> bytes:
        """poses: (n, 7) [x, y, z, qx, qy, qz, qw] per transform."""
        buf = bytearray(self._template)
        stamp = struct.pack("<iI", int(sec), int(nanosec))
        p = np.ascontiguousarray(poses, dtype="<f8").reshape(self.n, 7)
        for k in range(self.n):
            s, o = self._stamp_at[k], self._pose_at[k]
            buf[s:s + 8] = stamp
            buf[o:o + 56] = p[k].tobytes()
        return bytes(buf)
