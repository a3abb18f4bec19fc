"""The state of one control step as ``controller_node`` assembles it from its messages: the
slot of a stamp (``StateSlot``: joint state, base state and foot forces as they arrive) and
the ``RobotState`` read from a complete one (``StateAssembler``).

The common case (12 finite joints, finite values below 1e100, a quaternion of squared norm
in (0.5, 2)) is read by one C kernel (``kernels.node_state``) into fresh arrays; anything
else is checked value by value with the same arithmetic, which gives the reason of a
rejection: a message with NaN/inf values, missing joints or wrong array sizes is never
passed on to the controller. No rclpy.
"""
from __future__ import annotations

import math
import time

import numpy as np

from .inputs import RobotState
from .kernels import node_state, squared_norm4
from .model import JOINT_NAMES


class StateSlot:
    """The state of one stamp as read from its messages: joint state (sec, nanosec, names,
    position, velocity), base state (13 floats: position, orientation xyzw, linear and
    angular velocity), 4 wrench forces (3 floats each); or, for the state estimator, the
    IMU (10 floats: orientation xyzw, angular velocity, proper acceleration) and the foot
    contacts (names, flags)."""
    __slots__ = ("js", "odom", "wrench", "imu", "contacts", "n", "t_first")

    def __init__(self):
        self.t_first = time.perf_counter()
        self.js = None
        self.odom = None
        self.wrench = [None, None, None, None]
        self.imu = self.contacts = None
        self.n = 0

    def missing(self, feet, estimator=False) -> list:
        """The names of the messages not in the slot (`feet`: the feet's names; estimator:
        the state estimator's messages)."""
        inputs = ((("imu", self.imu), ("foot contacts", self.contacts)) if estimator else
                  (("base state", self.odom),
                   *zip((f"{foot} wrench" for foot in feet), self.wrench, strict=True)))
        return [name for name, m in (("joint state", self.js), *inputs) if m is None]


def stamp_ns(header) -> int:
    """A message header's stamp in nanoseconds."""
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def all_finite(*values) -> bool:
    """Every value is a finite number (a finite sum: NaN and inf propagate)."""
    try:
        return math.isfinite(math.fsum(values))
    except (TypeError, ValueError, OverflowError):
        return False


def state_from_values(stamp, position, velocity, perm, odom, forces, threshold,
                      twist_in_child, R):
    """The RobotState of one stamp (ns), read by the node_state kernel into fresh arrays: joint
    positions and velocities (perm: their indices in the public order), the 13 odometry
    values (pose; twist, its linear part in the base frame when twist_in_child, else in the
    world), the feet's forces (4 x 3; contact where |force| > threshold); R: the kernel's
    rotation (scratch, 3 x 3). None when the kernel leaves the values to the checks of
    StateAssembler.robot_state_checked (a non-finite or huge value, a quaternion of squared
    norm outside (0.5, 2))."""
    q, dq, pb, quat, v, w = (np.empty(12), np.empty(12), np.empty(3), np.empty(4),
                             np.empty(3), np.empty(3))
    contact = np.empty(4, dtype=bool)
    if node_state(np.asarray(position, dtype=float), np.asarray(velocity, dtype=float), perm,
                  odom, forces, threshold, q, dq, pb, quat, v, w, R, contact) != 0:
        return None
    if twist_in_child:   # base frame -> world frame
        v = R @ v
    return RobotState(stamp * 1e-9, q, dq, pb, quat, v, w, contact, forces)


class StateAssembler:
    """The RobotState of a complete StateSlot (``robot_state``): joint positions and velocities
    in the public order (`permutation` of the names as received, cached), contact where
    |force| > `threshold` [N], the twist's linear velocity turned into the world frame when
    `twist_in_child` (the base frame, REP 105); `joint_names`: the public order (the
    robot's, default StarlETH's)."""

    def __init__(self, threshold: float, twist_in_child: bool, joint_names=JOINT_NAMES):
        self.joint_names = tuple(joint_names)
        self.threshold = threshold
        self.twist_in_child = twist_in_child
        self._perm_cache = {}             # tuple(names) -> index array (public order)
        self._kernel_perm = {}            # the same as int64 arrays for node_state
        self._R = np.eye(3)               # base -> world rotation of the last state

    def permutation(self, names):
        """(perm, None): the indices of the public joint order in `names` (a slice when
        they are in that order already); (None, reason) when a joint is missing or twice."""
        key = tuple(names)
        perm = self._perm_cache.get(key)
        if perm is None:
            if key == self.joint_names:
                perm = slice(None)
            else:
                index = {n: i for i, n in enumerate(key)}
                if len(index) != len(key):
                    return None, "duplicate joint names"
                missing = [n for n in self.joint_names if n not in index]
                if missing:
                    return None, f"missing joints {', '.join(missing)}"
                perm = np.array([index[n] for n in self.joint_names])
            if len(self._perm_cache) < 8:
                self._perm_cache[key] = perm
        return perm, None

    def robot_state(self, stamp, s: StateSlot):
        """RobotState from the messages of one stamp, or (None, key, reason): the common
        case (12 finite joints, finite values below 1e100, a quaternion of squared norm in
        (0.5, 2)) read by one kernel into fresh arrays, with the arithmetic of the checks
        below (robot_state_checked), which run for anything else and give the reason."""
        _, _, names, position, velocity = s.js
        n = len(names)
        if n == 12 and len(position) == 12 and len(velocity) == 12 and s.odom is not None \
                and len(s.odom) == 13:
            perm = self._kernel_perm.get(names)
            if perm is None:
                perm, err = self.permutation(names)
                if err:
                    return self.robot_state_checked(stamp, s)
                perm = (np.arange(12, dtype=np.int64) if isinstance(perm, slice)
                        else np.asarray(perm, dtype=np.int64))
                if len(self._kernel_perm) < 8:
                    self._kernel_perm[names] = perm
            try:
                forces = np.array(s.wrench, dtype=float)
                odom = np.array(s.odom, dtype=float)
            except (TypeError, ValueError):
                return self.robot_state_checked(stamp, s)
            if forces.shape == (4, 3):
                state = state_from_values(stamp, position, velocity, perm, odom, forces,
                                          self.threshold, self.twist_in_child, self._R)
                if state is not None:
                    return state, None, None
        return self.robot_state_checked(stamp, s)

    def robot_state_checked(self, stamp, s: StateSlot):
        """RobotState from the messages of one stamp after checking them one by one, or
        (None, key, reason)."""
        _, _, names, position, velocity = s.js
        n = len(names)
        if len(position) != n or len(velocity) != n:
            return None, "joint_states", (f"/joint_states: {n} names, {len(position)} "
                                          f"positions, {len(velocity)} velocities")
        perm, err = self.permutation(names)
        if err:
            return None, "joint_states", f"/joint_states: {err}"
        q = np.asarray(position, dtype=float)[perm]
        dq = np.asarray(velocity, dtype=float)[perm]
        # a finite sum means every value is finite (NaN and inf propagate); only a sum that
        # is not (non-finite values, or an overflow) is looked at value by value
        add = np.add.reduce
        if not math.isfinite(float(add(q) + add(dq))) and \
                not (np.isfinite(q).all() and np.isfinite(dq).all()):
            return None, "joint_states_nan", "/joint_states: non-finite position or velocity"
        vals = s.odom
        if not all_finite(*vals):
            return None, "base_state_nan", "base state: non-finite values"
        quat = np.array(vals[3:7])
        nq = squared_norm4(quat)
        if not 0.5 < nq < 2.0:
            return None, "base_state_quat", f"base state: orientation norm {math.sqrt(nq):.3g}"
        quat /= math.sqrt(nq)
        v = np.array(vals[7:10])
        if self.twist_in_child:   # base frame -> world frame
            x, y, z, w = quat.tolist()     # Python floats: the same values, faster products
            R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                          [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                          [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
            v = R @ v
        forces = np.array(s.wrench, dtype=float)
        if not math.isfinite(float(add(forces, axis=None))) and not np.isfinite(forces).all():
            return None, "wrench_nan", "foot wrench: non-finite force"
        contact = np.sqrt((forces * forces).sum(axis=1)) > self.threshold
        state = RobotState(stamp * 1e-9, q, dq, np.array(vals[0:3]), quat, v,
                           np.array(vals[10:13]), contact, forces)
        return state, None, None
