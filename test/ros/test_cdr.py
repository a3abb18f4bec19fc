"""The CDR fast path of sim_node (starleth_sim.ros.cdr): commands decoded straight from
the bytes rclpy/Fast DDS put on the wire must equal what rclpy's own deserialisation gives,
and everything outside the decoded common case must be handed to the full path (FALLBACK),
never decoded wrongly and never read out of bounds."""
import numpy as np
import pytest

from starleth_sim.physics.description import STARLETH_JOINT_NAMES as JOINTS
from starleth_sim.ros.cdr import CommandDecoder

rclpy_serialization = pytest.importorskip("rclpy.serialization")
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

serialize_message = rclpy_serialization.serialize_message


def random_joint_command(rng):
    """A JointState command; about half are the common case (all joints in order, 12
    finite efforts), the others differ in one way a controller could get wrong."""
    m = JointState()
    m.header.frame_id = "f" * int(rng.integers(0, 9))       # shifts every later alignment
    m.header.stamp.sec = int(rng.integers(0, 2 ** 31 - 1))
    m.header.stamp.nanosec = int(rng.integers(0, 10 ** 9))
    names = list(JOINTS)
    effort = rng.normal(scale=20.0, size=len(JOINTS))
    kind = rng.integers(0, 12)      # 0 and 7-11: the common case
    if kind == 1:
        names = names[::-1]
    elif kind == 2:
        names = names[:-1]
        effort = effort[:-1]
    elif kind == 3:
        names[5] = names[5] + "_"
    elif kind == 4:
        names = []
    elif kind == 5:
        effort[int(rng.integers(len(effort)))] = rng.choice([np.nan, np.inf, -np.inf])
    elif kind == 6:
        effort = effort[:int(rng.integers(0, len(effort)))]
    m.name = names
    # a filled position or velocity makes an impedance command: not the torque fast path
    m.position = list(rng.normal(size=int(rng.integers(0, 13)))) if rng.random() < 0.3 else []
    m.velocity = list(rng.normal(size=int(rng.integers(0, 13)))) if rng.random() < 0.3 else []
    m.effort = list(effort)
    common = names == list(JOINTS) and len(effort) == len(JOINTS) and \
        bool(np.all(np.isfinite(effort))) and not m.position and not m.velocity
    return m, common


def test_joint_commands_decode_exactly_or_fall_back():
    dec = CommandDecoder(JOINTS)
    rng = np.random.default_rng(7)
    n_common = 0
    for _ in range(1500):
        m, common = random_joint_command(rng)
        data = serialize_message(m)
        ok, stamp_ns, effort = dec.joint_command(data)
        assert ok == common, (list(m.name), list(m.effort))
        if ok:
            n_common += 1
            assert stamp_ns == m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
            np.testing.assert_array_equal(effort, np.asarray(m.effort))
        # truncated or garbled bytes: never decoded as valid unless still a whole message
        for cut in rng.integers(0, len(data), 4):
            ok_cut, _, eff_cut = dec.joint_command(data[:cut])
            if ok_cut:
                np.testing.assert_array_equal(eff_cut, np.asarray(m.effort))
        assert not dec.joint_command(b"\x00\x00" + data[2:])[0]      # big endian: fallback
    assert n_common > 250


def test_effort_arrays_decode_exactly_or_fall_back():
    dec = CommandDecoder(JOINTS)
    rng = np.random.default_rng(8)
    for _ in range(1000):
        m = Float64MultiArray()
        m.layout.dim = [MultiArrayDimension(label="l" * int(rng.integers(0, 7)),
                                            size=int(rng.integers(0, 20)), stride=3)
                        for _ in range(int(rng.integers(0, 3)))]
        m.layout.data_offset = int(rng.integers(0, 4))
        n = len(JOINTS) if rng.random() < 0.7 else int(rng.integers(0, 15))
        data_ = rng.normal(size=n)
        if rng.random() < 0.1 and n:
            data_[int(rng.integers(n))] = np.nan
        m.data = list(data_)
        raw = serialize_message(m)
        ok, effort = dec.effort_array(raw)
        assert ok == (n == len(JOINTS) and bool(np.all(np.isfinite(data_))))
        if ok:
            np.testing.assert_array_equal(effort, data_)
        for cut in rng.integers(0, len(raw), 3):
            ok_cut, eff_cut = dec.effort_array(raw[:cut])
            if ok_cut:
                np.testing.assert_array_equal(eff_cut, data_)
