"""The state bundle: everything a controller reads of one control step in one message.

sim_node publishes the state of a step on six public topics (``joint_states``, the base
state, four foot wrenches). Every reliable message to another process costs the publisher
60-85 µs in Fast DDS and the subscriber a take, so a controller that needs all six pays
for six. ``starleth/state_bundle`` carries the same numbers in one
``std_msgs/Float64MultiArray``; ``controller_node`` reads it when a simulator sends it
(``state_input:=auto``, the default) and sim_node then sends the public topics only to
their other subscribers (and the recording). The values are the public messages' float64
values, bit for bit, so a controller computes the same torques from either input.

Layout (version 1; ``layout.dim`` is one dimension labelled :data:`LABEL` of size
:data:`SIZE`, ``data_offset`` 0):

    ========  =====  ===============================================================
    slice     field  meaning
    ========  =====  ===============================================================
    0:2       stamp  header stamp of the public messages: sec, nanosec (exact)
    2:14      q      joint positions [rad], public order :data:`JOINT_NAMES`
    14:26     u      joint velocities [rad/s]
    26:38     tau    applied joint torques [N m] (joint_states' effort)
    38:45     pose   base position [m] (world), orientation x, y, z, w
    45:51     twist  base linear velocity (base frame, as the Odometry), angular velocity
    51:63     force  contact force F = Λ/Δt of the feet LF, RF, LH, RH [N] (world frame)
    ========  =====  ===============================================================

The bundle is a transport between the two nodes, not a recorded topic: the recording keeps
the public topics. A message whose label or size is not this layout's is rejected by the
reader (a logged rejection in controller_node), never misread.

rclpy only for :meth:`StateBundleCdr.create` (the template); ROS-free otherwise.
"""
from __future__ import annotations

import struct

import numpy as np

LEGS = ("LF", "RF", "LH", "RH")
JOINTS_PER_LEG = ("HAA", "HFE", "KFE")
#: the joint order of the bundle (the public order of sim_node's /joint_states)
JOINT_NAMES = tuple(f"{leg}_{j}" for leg in LEGS for j in JOINTS_PER_LEG)

LABEL = "starleth_state_v1"
#: (name, start, stop) of each field in the data array
FIELDS = (("stamp", 0, 2), ("q", 2, 14), ("u", 14, 26), ("tau", 26, 38), ("pose", 38, 45),
          ("twist", 45, 51), ("force", 51, 63))
SLICES = {name: slice(a, b) for name, a, b in FIELDS}
SIZE = 63
#: the 13 values of the base state (pose then twist), the Odometry's order
BASE = slice(38, 51)

_U32 = struct.Struct("<I")


def _prefix() -> bytes:
    """The CDR bytes (XCDR1, little endian) of a Float64MultiArray of this layout up to its
    first float: encapsulation header, one dim (label, size, stride), data_offset 0, the
    data count; the floats then start 8-aligned (relative to byte 4)."""
    label = LABEL.encode() + b"\x00"
    out = bytearray(b"\x00\x01\x00\x00")           # CDR_LE, options 0
    out += _U32.pack(1)                             # dim: one MultiArrayDimension
    out += _U32.pack(len(label)) + label
    while (len(out) - 4) % 4:
        out += b"\x00"
    out += _U32.pack(SIZE) + _U32.pack(SIZE)        # size, stride
    out += _U32.pack(0)                             # data_offset
    out += _U32.pack(SIZE)                          # data: count
    while (len(out) - 4) % 8:
        out += b"\x00"
    return bytes(out)


PREFIX = _prefix()
#: length of a bundle in bytes
NBYTES = len(PREFIX) + 8 * SIZE


class StateBundleCdr:
    """Writes bundles: ``build(sec, nsec, q, u, tau, pose, twist, force)`` -> CDR bytes
    (numbers or float arrays; force 12 values, foot by foot)."""

    def __init__(self):
        self._buf = np.empty(SIZE)

    @classmethod
    def create(cls):
        """A writer whose bytes rclpy reads back as this layout (None if the rmw's CDR is
        not the one assumed here: the caller then sends no bundle)."""
        try:
            from rclpy.serialization import deserialize_message
            from std_msgs.msg import Float64MultiArray
            self = cls()
            probe = np.arange(SIZE, dtype=float) / 7.0 - 3.0
            msg = deserialize_message(PREFIX + probe.tobytes(), Float64MultiArray)
            d = msg.layout.dim
            if (len(d) != 1 or d[0].label != LABEL or d[0].size != SIZE or d[0].stride != SIZE
                    or msg.layout.data_offset != 0
                    or np.asarray(msg.data, dtype=float).tobytes() != probe.tobytes()):
                return None
            return self
        except Exception:  # pragma: no cover - unexpected rmw behaviour: no bundle
            return None

    def build(self, sec, nsec, q, u, tau, pose, twist, force) -> bytes:
        b = self._buf
        b[0], b[1] = sec, nsec
        b[2:14], b[14:26], b[26:38] = q, u, tau
        b[38:45], b[45:51], b[51:63] = pose, twist, force
        return PREFIX + b.tobytes()


def decode(data):
    """(sec, nanosec, values) of a bundle's CDR bytes, values a fresh float array of SIZE;
    or a str saying why the bytes are not a bundle of this layout (another label or size,
    undecodable bytes, a stamp that is not two whole numbers in range). Bytes from another
    writer (other padding bytes, big endian) are deserialised by rclpy."""
    if len(data) == NBYTES and data[:len(PREFIX)] == PREFIX:
        v = np.frombuffer(data, dtype="<f8", count=SIZE, offset=len(PREFIX)).copy()
    else:
        v = _deserialised(data)
        if isinstance(v, str):
            return v
    sec, nsec = float(v[0]), float(v[1])
    if not (-2.0 ** 31 <= sec < 2.0 ** 31 and 0.0 <= nsec < 1e9
            and sec == int(sec) and nsec == int(nsec)):
        return f"stamp ({sec!r}, {nsec!r}) is not a ROS time"
    return int(sec), int(nsec), v


def _deserialised(data):
    """The values of a Float64MultiArray of this layout deserialised by rclpy, or a str
    saying why it is not one."""
    try:
        from rclpy.serialization import deserialize_message
        from std_msgs.msg import Float64MultiArray
        msg = deserialize_message(bytes(data), Float64MultiArray)
    except Exception as e:
        return f"undecodable Float64MultiArray ({type(e).__name__}: {e})"
    labels = [d.label for d in msg.layout.dim]
    if labels != [LABEL] or len(msg.data) != SIZE or msg.layout.data_offset != 0:
        return (f"not a {LABEL} bundle of {SIZE} values (layout labels {labels}, "
                f"data_offset {msg.layout.data_offset}, {len(msg.data)} values)")
    return np.array(msg.data, dtype=float)
