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

ROS-free: numpy + numba only.
"""
from __future__ import annotations

import numba as nb
import numpy as np

OK = 0
FALLBACK = 1

_ORIGIN = 4   # alignment origin: the CDR payload starts after the encapsulation header


@nb.njit(cache=True, inline="always")
def _align(o, a):
    r = (o - _ORIGIN) % a
    return o if r == 0 else o + a - r


@nb.njit(cache=True, inline="always")
def _u32(buf, o):
    return (np.uint32(buf[o]) | (np.uint32(buf[o + 1]) << 8) | (np.uint32(buf[o + 2]) << 16)
            | (np.uint32(buf[o + 3]) << 24))


@nb.njit(cache=True)
def _f64_into(buf, o, n, out):
    """n little-endian float64 at buf[o:] into out; False if one is not finite."""
    ok = True
    v = buf[o:o + 8 * n].view(np.float64)
    for k in range(n):
        out[k] = v[k]
        if not np.isfinite(v[k]):
            ok = False
    return ok


@nb.njit(cache=True)
def _skip_empty_sequence(buf, o, nbuf):
    """Offset after an empty float64[] starting at o (aligned to 4), or -1 if it does not
    fit or is not empty."""
    o = _align(o, 4)
    if o + 4 > nbuf or _u32(buf, o) != 0:
        return -1
    return o + 4


@nb.njit(cache=True)
def parse_joint_command(buf, names, names_ptr, effort):
    """A sensor_msgs/JointState command in CDR bytes (uint8 array). Returns
    (status, sec, nanosec): OK when the names are exactly names (flattened UTF-8 bytes,
    names_ptr the n+1 offsets) in that order and effort holds n finite values (written to
    effort) and position and velocity are empty; FALLBACK otherwise (an impedance command
    among them)."""
    nbuf = buf.shape[0]
    n = names_ptr.shape[0] - 1
    if nbuf < 16 or buf[0] != 0 or buf[1] != 1:
        return FALLBACK, 0, 0
    sec = np.int32(_u32(buf, 4))
    nsec = _u32(buf, 8)
    flen = np.int64(_u32(buf, 12))
    o = 16 + flen
    o = _align(o, 4)
    if o + 4 > nbuf:
        return FALLBACK, 0, 0
    if np.int64(_u32(buf, o)) != n:
        return FALLBACK, 0, 0
    o += 4
    for i in range(n):
        o = _align(o, 4)
        if o + 4 > nbuf:
            return FALLBACK, 0, 0
        slen = np.int64(_u32(buf, o))
        o += 4
        a, b = names_ptr[i], names_ptr[i + 1]
        if slen != b - a + 1 or o + slen > nbuf:
            return FALLBACK, 0, 0
        for k in range(b - a):
            if buf[o + k] != names[a + k]:
                return FALLBACK, 0, 0
        o += slen
    o = _skip_empty_sequence(buf, o, nbuf)        # position
    if o < 0:
        return FALLBACK, 0, 0
    o = _skip_empty_sequence(buf, o, nbuf)        # velocity
    if o < 0:
        return FALLBACK, 0, 0
    o = _align(o, 4)
    if o + 4 > nbuf or np.int64(_u32(buf, o)) != n:
        return FALLBACK, 0, 0
    o = _align(o + 4, 8)
    if o + 8 * n > nbuf or not _f64_into(buf, o, n, effort):
        return FALLBACK, 0, 0
    return OK, sec, nsec


@nb.njit(cache=True)
def parse_effort_array(buf, effort):
    """A std_msgs/Float64MultiArray in CDR bytes: OK when data holds len(effort) finite
    values (written to effort), whatever the layout says; FALLBACK otherwise."""
    nbuf = buf.shape[0]
    n = effort.shape[0]
    if nbuf < 12 or buf[0] != 0 or buf[1] != 1:
        return FALLBACK
    ndim = np.int64(_u32(buf, 4))
    o = 8
    for _ in range(ndim):                     # MultiArrayDimension: label, size, stride
        o = _align(o, 4)
        if o + 4 > nbuf:
            return FALLBACK
        o += 4 + np.int64(_u32(buf, o))
        o = _align(o, 4) + 8
        if o > nbuf:
            return FALLBACK
    o = _align(o, 4) + 4                      # data_offset
    if o + 4 > nbuf or np.int64(_u32(buf, o)) != n:
        return FALLBACK
    o = _align(o + 4, 8)
    if o + 8 * n > nbuf or not _f64_into(buf, o, n, effort):
        return FALLBACK
    return OK


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
        # compile (or load from numba's cache) now, not on the first command: a first
        # compile inside a running 400 Hz loop stalls it for up to a second
        self.joint_command(bytes(16))
        self.effort_array(bytes(16))

    def joint_command(self, data):
        effort = np.empty(self.n)
        status, sec, nsec = parse_joint_command(np.frombuffer(data, np.uint8), self.names,
                                                self.names_ptr, effort)
        if status != OK:
            return False, 0, effort
        return True, int(sec) * 1_000_000_000 + int(nsec), effort

    def effort_array(self, data):
        effort = np.empty(self.n)
        return parse_effort_array(np.frombuffer(data, np.uint8), effort) == OK, effort
