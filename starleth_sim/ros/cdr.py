"""CDR (XCDR1, little endian, as rmw_fastrtps writes it) for the hot lockstep path of
``sim_node``: incoming commands are read straight from the serialised bytes of a raw
subscription, without building an rclpy message object (~15-25 µs per JointState with 12
names in Python). The outgoing templates (/joint_states and the other per-cycle topics)
are in :mod:`starleth_interface.msg_cdr`, shared with controller_node.

Only the common, valid case is decoded here: a ``sensor_msgs/JointState`` whose names are
exactly the simulator's joints in joint order, with empty position and velocity (a torque
command) and n finite efforts, or a ``std_msgs/Float64MultiArray`` with n values, all
finite. Anything else (other names or order, wrong lengths, NaN, big endian,
truncated data) returns FALLBACK and the node deserialises the message with rclpy and
runs the full validation, which produces the detailed rejection messages. The parsers
never read outside the buffer.

Layout facts (checked against rclpy's serialize_message in test_sim_service.py): a 4-byte
encapsulation header (00 01 00 00 = CDR_LE), then the fields with alignment relative to
byte 4; strings are uint32 length (with the terminating NUL) + bytes; sequences are a
uint32 count, then elements aligned to their size (no alignment when the count is 0);
padding bytes are not zeroed.

The parsers are C (csrc/cdr.c, the extension module ``starleth_sim.ros._cdr``, built like the
controller's kernels by starleth_interface.c_extension: at install, or on first import in a
source checkout). ROS-free: numpy and the parsers only.
"""
from __future__ import annotations

import numpy as np

from starleth_interface import c_extension

_cdr = c_extension.load(__package__ + "._cdr")
OK, FALLBACK = _cdr.OK, _cdr.FALLBACK
#: parse_joint_command(buf, names, names_ptr, effort) -> (status, sec, nanosec): a
#: sensor_msgs/JointState command in CDR bytes, OK when the names are exactly `names`
#: (flattened UTF-8 bytes, names_ptr the n+1 offsets) in that order, effort holds n finite
#: values (written to effort) and position and velocity are empty; FALLBACK otherwise (an
#: impedance command among them)
parse_joint_command = _cdr.parse_joint_command
#: parse_effort_array(buf, effort) -> status: a std_msgs/Float64MultiArray in CDR bytes, OK
#: when data holds len(effort) finite values (written to effort), whatever the layout says
parse_effort_array = _cdr.parse_effort_array


class CommandDecoder:
    """Decodes the common valid commands of one simulator (its joint names) from CDR
    bytes: ``joint_command(data)`` -> (ok, stamp_ns, efforts) and
    ``effort_array(data)`` -> (ok, efforts); efforts is a fresh array."""

    def __init__(self, joint_names):
        encoded = [str(n).encode("utf-8") for n in joint_names]
        self.names = np.frombuffer(b"".join(encoded), dtype=np.uint8).copy() if encoded \
            else np.zeros(0, np.uint8)
        self.names_ptr = np.concatenate([[0], np.cumsum([len(e) for e in encoded])]).astype(
            np.int64)
        self.n = len(encoded)

    def joint_command(self, data):
        effort = np.empty(self.n)
        status, sec, nsec = parse_joint_command(data, self.names, self.names_ptr, effort)
        if status != OK:
            return False, 0, effort
        return True, int(sec) * 1_000_000_000 + int(nsec), effort

    def effort_array(self, data):
        effort = np.empty(self.n)
        return parse_effort_array(data, effort) == OK, effort
