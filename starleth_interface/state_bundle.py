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
2 + 3 n + 13 + 3 m for a robot of n joints and m feet, ``data_offset`` 0; StarlETH's, n = 12,
m = 4, :data:`SIZE` = 63 values):

    ===========  =====  ============================================================
    slice        field  meaning
    ===========  =====  ============================================================
    0:2          stamp  header stamp of the public messages: sec, nanosec (exact)
    2:2+n        q      joint positions [rad], the public joint order (the URDF's)
    +n           u      joint velocities [rad/s]
    +n           tau    applied joint torques [N m] (joint_states' effort)
    +7           pose   base position [m] (world), orientation x, y, z, w
    +6           twist  base linear velocity (base frame, as the Odometry), angular velocity
    +3m          force  contact force F = Λ/Δt of the feet (the robot's foot order) [N]
                        (world frame)
    ===========  =====  ============================================================

:class:`BundleLayout` gives a robot's slices (``BundleLayout(n, m)``); the module's
:data:`FIELDS`, :data:`SLICES`, :data:`SIZE`, :data:`BASE`, :data:`PREFIX` and
:data:`NBYTES` are StarlETH's (:data:`STARLETH`).

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
#: StarlETH's joint order (the public order of its sim_node's /joint_states)
JOINT_NAMES = tuple(f"{leg}_{j}" for leg in LEGS for j in JOINTS_PER_LEG)

LABEL = "starleth_state_v1"
_U32 = struct.Struct("<I")


class BundleLayout:
    """The layout of a robot of `n_joints` joints and `n_feet` feet (module docstring):
    ``fields`` ((name, start, stop) each), ``slices``, ``size``, ``base`` (the 13 values of
    the base state, pose then twist: the Odometry's order), ``prefix`` (the CDR bytes up to
    the first float) and ``nbytes`` (a bundle's length)."""

    def __init__(self, n_joints: int = 12, n_feet: int = 4):
        self.n_joints, self.n_feet = n_joints, n_feet
        n = n_joints
        self.fields = (("stamp", 0, 2), ("q", 2, 2 + n), ("u", 2 + n, 2 + 2 * n),
                       ("tau", 2 + 2 * n, 2 + 3 * n), ("pose", 2 + 3 * n, 9 + 3 * n),
                       ("twist", 9 + 3 * n, 15 + 3 * n),
                       ("force", 15 + 3 * n, 15 + 3 * n + 3 * n_feet))
        self.slices = {name: slice(a, b) for name, a, b in self.fields}
        self.size = self.fields[-1][2]
        self.base = slice(2 + 3 * n, 15 + 3 * n)
        self.prefix = _prefix(self.size)
        self.nbytes = len(self.prefix) + 8 * self.size


def _prefix(size: int) -> bytes:
    """The CDR bytes (XCDR1, little endian) of a Float64MultiArray of `size` values of this
    layout up to its first float: encapsulation header, one dim (label, size, stride),
    data_offset 0, the data count; the floats then start 8-aligned (relative to byte 4)."""
    label = LABEL.encode() + b"\x00"
    out = bytearray(b"\x00\x01\x00\x00")           # CDR_LE, options 0
    out += _U32.pack(1)                             # dim: one MultiArrayDimension
    out += _U32.pack(len(label)) + label
    while (len(out) - 4) % 4:
        out += b"\x00"
    out += _U32.pack(size) + _U32.pack(size)        # size, stride
    out += _U32.pack(0)                             # data_offset
    out += _U32.pack(size)                          # data: count
    while (len(out) - 4) % 8:
        out += b"\x00"
    return bytes(out)


#: StarlETH's layout, and its figures as module constants
STARLETH = BundleLayout(12, 4)
FIELDS, SLICES, SIZE, BASE = STARLETH.fields, STARLETH.slices, STARLETH.size, STARLETH.base
PREFIX, NBYTES = STARLETH.prefix, STARLETH.nbytes


class StateBundleCdr:
    """Writes bundles of a layout (default StarlETH's): ``build(sec, nsec, q, u, tau, pose,
    twist, force)`` -> CDR bytes (numbers or float arrays; force 3 m values, foot by foot)."""

    def __init__(self, layout: BundleLayout = STARLETH):
        self.layout = layout
        self._buf = np.empty(layout.size)

    @classmethod
    def create(cls, layout: BundleLayout = STARLETH):
        """A writer whose bytes rclpy reads back as this layout (None if the rmw's CDR is
        not the one assumed here: the caller then sends no bundle)."""
        try:
            from rclpy.serialization import deserialize_message
            from std_msgs.msg import Float64MultiArray
            self = cls(layout)
            size = layout.size
            probe = np.arange(size, dtype=float) / 7.0 - 3.0
            msg = deserialize_message(layout.prefix + probe.tobytes(), Float64MultiArray)
            d = msg.layout.dim
            if (len(d) != 1 or d[0].label != LABEL or d[0].size != size or d[0].stride != size
                    or msg.layout.data_offset != 0
                    or np.asarray(msg.data, dtype=float).tobytes() != probe.tobytes()):
                return None
            return self
        except Exception:  # pragma: no cover - unexpected rmw behaviour: no bundle
            return None

    def build(self, sec, nsec, q, u, tau, pose, twist, force) -> bytes:
        b, sl = self._buf, self.layout.slices
        b[0], b[1] = sec, nsec
        b[sl["q"]], b[sl["u"]], b[sl["tau"]] = q, u, tau
        b[sl["pose"]], b[sl["twist"]], b[sl["force"]] = pose, twist, force
        return self.layout.prefix + b.tobytes()


def decode(data, layout: BundleLayout = STARLETH):
    """(sec, nanosec, values) of a bundle's CDR bytes, values a fresh float array of the
    layout's size; or a str saying why the bytes are not a bundle of this layout (another
    label or size, undecodable bytes, a stamp that is not two whole numbers in range). Bytes
    from another writer (other padding bytes, big endian) are deserialised by rclpy."""
    if len(data) == layout.nbytes and data[:len(layout.prefix)] == layout.prefix:
        v = np.frombuffer(data, dtype="<f8", count=layout.size,
                          offset=len(layout.prefix)).copy()
    else:
        v = _deserialised(data, layout.size)
        if isinstance(v, str):
            return v
    sec, nsec = float(v[0]), float(v[1])
    if not (-2.0 ** 31 <= sec < 2.0 ** 31 and 0.0 <= nsec < 1e9
            and sec == int(sec) and nsec == int(nsec)):
        return f"stamp ({sec!r}, {nsec!r}) is not a ROS time"
    return int(sec), int(nsec), v


def _deserialised(data, size):
    """The values of a Float64MultiArray of this layout (`size` values) deserialised by
    rclpy, or a str saying why it is not one."""
    try:
        from rclpy.serialization import deserialize_message
        from std_msgs.msg import Float64MultiArray
        msg = deserialize_message(bytes(data), Float64MultiArray)
    except Exception as e:
        return f"undecodable Float64MultiArray ({type(e).__name__}: {e})"
    labels = [d.label for d in msg.layout.dim]
    if labels != [LABEL] or len(msg.data) != size or msg.layout.data_offset != 0:
        return (f"not a {LABEL} bundle of {size} values (layout labels {labels}, "
                f"data_offset {msg.layout.data_offset}, {len(msg.data)} values)")
    return np.array(msg.data, dtype=float)
