"""``controller_node``'s state from its sensors (``state_source:=estimator``): the joint
state, the IMU (sensor_msgs/Imu: orientation x, y, z, w as an AHRS reports it, angular
velocity and proper acceleration in the base frame) and the foot contact flags
(sensor_msgs/JointState: name = the feet's contact names, position = 1.0 contact / 0.0
none) of one stamp, run through the state estimator (estimator.LegOdometryEKF) into the
controller's RobotState. No ground truth is read. No rclpy.

A message with NaN/inf values, missing joints or feet, or wrong array sizes is rejected
with a reason (the node logs it) and never reaches the filter.
"""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

from .estimator import LegOdometryEKF, quat_to_rot
from .state_intake import StateAssembler, all_finite


class ContactHold:
    """The controller's contact flags from the sensor's: a foot's flag stays set for `hold`
    seconds after the sensor's drops. The controller unloads a stance leg whose flag drops
    (lost contact), and a sensor that thresholds the force one step late then drops it the
    next steps too: a loop that, at a threshold near a light robot's stance loads (Go1
    standing, 32 N a foot, under a 20 N threshold with 5 N of noise), sat the robot down
    (doc/estimator.md, "Contact flags for the controller"). Holding the flag through such a
    dropout breaks the loop; a touch-down is passed at once."""

    def __init__(self, n_feet: int, hold: float):
        self.hold = hold
        self.last = np.full(n_feet, -np.inf)     # when each flag was last set [s]

    def reset(self):
        self.last[:] = -np.inf

    def flags(self, t: float, contact) -> np.ndarray:
        """The held flags at time t [s] of the sensor's `contact` (bools)."""
        self.last[contact] = t
        return (t - self.last) <= self.hold + 1e-9


class EstimatedState:
    """The RobotState of a stamp's joint state, IMU values (10: orientation x, y, z, w,
    angular velocity, proper acceleration) and foot contacts ((names, flags)) through the
    filter; the filter starts (``reset``: orientation from the IMU, position above the
    origin) on the first complete stamp. `model`: the controller's RobotModel."""

    def __init__(self, model, params=None):
        self.model = model
        self.ekf = LegOdometryEKF(model, params)
        self.hold = ContactHold(len(model.legs), self.ekf.params.contact_hold)
        self._joints = StateAssembler(0.0, True, model.public_joint_names)
        self._feet = {}                     # tuple(names) -> index array (the legs' order)
        #: the base link's name (the Odometry's child frame)
        self.base_frame = next(f.name for f in model.model.frames
                               if f.type == pin.FrameType.BODY and f.parentJoint == 1)

    def _foot_index(self, names):
        """(index of each foot in `names`, None) or (None, reason)."""
        key = tuple(names)
        idx = self._feet.get(key)
        if idx is None:
            where = {n: i for i, n in enumerate(key)}
            missing = [f for f in self.model.foot_names if f not in where]
            if missing:
                return None, f"missing feet {', '.join(missing)}"
            idx = np.array([where[f] for f in self.model.foot_names])
            if len(self._feet) < 8:
                self._feet[key] = idx
        return idx, None

    def _inputs(self, s):
        """((q, dq, imu, contact), None, None) of a slot, or (None, key, reason)."""
        _, _, names, position, velocity = s.js
        if len(position) != len(names) or len(velocity) != len(names):
            return None, "joint_states", (
                f"/joint_states: {len(names)} names, {len(position)} positions, "
                f"{len(velocity)} velocities")
        perm, err = self._joints.permutation(names)
        if err:
            return None, "joint_states", f"/joint_states: {err}"
        q = np.asarray(position, dtype=float)[perm]
        dq = np.asarray(velocity, dtype=float)[perm]
        if not (np.isfinite(q).all() and np.isfinite(dq).all()):
            return None, "joint_states_nan", \
                "/joint_states: non-finite position or velocity"
        imu = np.asarray(s.imu, dtype=float)
        if imu.shape != (10,) or not all_finite(*imu):
            return None, "imu_nan", "imu: non-finite values"
        n = float(imu[:4] @ imu[:4])
        if not 0.5 < n < 2.0:
            return None, "imu_quat", f"imu: orientation norm {math.sqrt(n):.3g}"
        names, flags = s.contacts
        idx, err = self._foot_index(names)
        if err or len(flags) != len(names):
            return None, "foot_contacts", \
                f"foot contacts: {err or f'{len(names)} names, {len(flags)} positions'}"
        contact = np.asarray(flags, dtype=float)[idx] > 0.5
        return (q, dq, imu, contact), None, None

    def robot_state(self, stamp, s):
        """(RobotState, None, None) of the estimate at `stamp` (ns), or (None, key, reason)."""
        values, key, reason = self._inputs(s)
        if values is None:
            return None, key, reason
        q, dq, imu, contact = values
        t = stamp * 1e-9
        e = self.ekf
        if not e.initialised or t < e.t - 1e-9:      # the first state, or time went back
            e.reset(t, imu[:4], q, contact)
            e.w = imu[4:7].copy()
            self.hold.reset()
        elif t > e.t:
            e.step(t, imu[4:7], imu[7:10], q, contact, dq)
        return e.robot_state(t, q, dq, self.hold.flags(t, contact)), None, None

    def odometry_values(self) -> tuple:
        """The estimate as nav_msgs/Odometry's 13 values (starleth_interface.msg_cdr
        ODOM_FIELDS): position, orientation x, y, z, w (world), linear velocity in the base
        frame (REP 105, as starleth/base_state), angular velocity (base frame)."""
        e = self.ekf
        v_body = quat_to_rot(e.q).T @ e.v
        return (*e.r.tolist(), *e.q.tolist(), *v_body.tolist(), *e.w.tolist())
