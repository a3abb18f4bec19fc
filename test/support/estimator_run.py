"""A headless run of the controller and the simulator with the state estimator
(starleth_controller.estimator) fed as a robot's drivers would feed it: the IMU's ideal
values from the simulator's state (ω: the base's body rates; f: the proper acceleration
Rᵀ(Δv/Δt − g), the base velocity's backward difference over the control period, as sim_node
computes it) plus Gaussian white noise and a constant bias of the test's choosing, the
measured joint angles (plus noise) and the simulator's foot contact flags; or, with
``sensors`` (a msg_configs/sensors file), everything from the simulator's own sensor models
(starleth_sim.physics.sensors, as sim_node publishes it: noise, biases, delays, contact flags
from a force threshold). The controller drives from ground truth (``drive="truth"``) or from
the estimate (``drive="estimate"``, with the measured joints and the contact flags held as
controller_node holds them: estimator_intake.ContactHold)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from starleth_controller import Command, RobotState, StarlethController
from starleth_controller.estimator import EstimatorParams, LegOdometryEKF, quat_to_rot, yaw_of
from starleth_controller.estimator_intake import ContactHold
from starleth_sim import Simulator
from starleth_sim.physics.config import load_preset
from starleth_sim.physics.robot_build import config_with_robot
from starleth_sim.physics.sensors import Sensors


@dataclass
class Noise:
    """The test's sensor errors: white noise standard deviations per sample and biases."""
    gyro: float = 0.0            # [rad/s]
    accel: float = 0.0           # [m/s²]
    joint: float = 0.0           # [rad]
    gyro_bias: tuple = (0.0, 0.0, 0.0)
    accel_bias: tuple = (0.0, 0.0, 0.0)
    contact_delay: int = 0       # control steps the contact flags come late
    seed: int = 1


class EstimatorRun:
    """Controller + simulator (`preset`) + filter; ``run(command, seconds)`` records per step
    the true and estimated position, velocity (world), yaw and the filter's covariance
    diagonal."""

    def __init__(self, preset="HmJ", noise=None, params: EstimatorParams | None = None,
                 drive="truth", robot=None, sensors=None):
        cfg = load_preset(preset) if robot is None else config_with_robot(load_preset(preset),
                                                                          robot)
        self.sim = Simulator(cfg if sensors is None else cfg.with_overlay(sensors, "sensors"))
        self.sim.reset()
        self.sensors = None if sensors is None else Sensors(self.sim)
        self.ctrl = StarlethController(robot=robot)
        self.ekf = LegOdometryEKF(self.ctrl.model, params)
        self.hold = ContactHold(len(self.ctrl.model.legs), self.ekf.params.contact_hold)
        self.noise, self.drive = noise or Noise(), drive
        self.rng = np.random.default_rng(self.noise.seed)
        self.feet = self.ctrl.model.foot_names
        self.g = np.array([0.0, 0.0, -self.ctrl.model.gravity])
        self.v_prev = None
        self.contacts = []
        self.rec = {k: [] for k in ("t", "r", "r_hat", "v", "v_hat", "yaw", "yaw_hat", "P",
                                    "tilt")}

    def _measure(self):
        """(true RobotState, gyro, accel, measured joint angles, joint velocities, contact
        flags) of the simulator now."""
        st = RobotState.from_simulator(self.sim, self.feet)
        if self.sensors is not None:
            m = self.sensors.measured
            return (st, m.imu_angular_velocity, m.imu_linear_acceleration, m.joint_position,
                    m.joint_velocity, m.contact_flag > 0.5)
        n, rng = self.noise, self.rng
        R = quat_to_rot(st.base_orientation_xyzw)
        v = np.asarray(st.base_linear_velocity, dtype=float)
        dt = self.sim.control_period
        acc = np.zeros(3) if self.v_prev is None else (v - self.v_prev) / dt
        self.v_prev = v.copy()
        accel = R.T @ (acc - self.g) + n.accel_bias + n.accel * rng.standard_normal(3)
        gyro = np.asarray(st.base_angular_velocity) + n.gyro_bias + \
            n.gyro * rng.standard_normal(3)
        q = np.asarray(st.joint_positions) + n.joint * rng.standard_normal(12)
        self.contacts.append(np.array(st.foot_contact))
        contact = self.contacts[max(0, len(self.contacts) - 1 - n.contact_delay)]
        return st, gyro, accel, q, st.joint_velocities, contact

    def run(self, command: Command, seconds: float):
        for _ in range(int(round(seconds / self.sim.control_period))):
            st, gyro, accel, q, dq, contact = self._measure()
            if not self.ekf.initialised:
                self.ekf.reset(st.t, st.base_orientation_xyzw, q, contact)
            else:
                self.ekf.step(st.t, gyro, accel, q, contact, dq)
            self._record(st)
            drive = st if self.drive == "truth" else self.ekf.robot_state(
                st.t, q, dq, self.hold.flags(st.t, contact))
            self.sim.step(self.ctrl.update(drive, command))
            if self.sensors is not None:
                self.sensors.sample()
        return self

    def _record(self, st):
        e, r = self.ekf, self.rec
        r["t"].append(st.t)
        r["r"].append(np.array(st.base_position))
        r["r_hat"].append(e.position.copy())
        r["v"].append(np.array(st.base_linear_velocity))
        r["v_hat"].append(e.velocity.copy())
        r["yaw"].append(yaw_of(st.base_orientation_xyzw))
        r["yaw_hat"].append(yaw_of(e.orientation_xyzw))
        r["P"].append(np.diag(e.P).copy())
        R = quat_to_rot(st.base_orientation_xyzw)
        r["tilt"].append(R[2, 2])

    def arrays(self):
        return {k: np.array(v) for k, v in self.rec.items()}
