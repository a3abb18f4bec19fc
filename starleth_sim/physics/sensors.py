"""Sensor models (ROS-free): what the robot's drivers report of the simulated state at each
control step -- the IMU, the joint encoders and torque sensors, the foot contact switches --
made from the exact values (the truth) by the models of the physics configuration's
``sensors:`` section (:class:`~.config.SensorConfig`; the models, units and sources:
doc/sensors.md).

    sensors = Sensors(sim)            # samples the current state (call after sim.reset)
    sim.step(tau); sensors.sample()   # after every control step
    sensors.measured, sensors.truth   # SensorReading of the current state
    sensors.restart()                 # after sim.reset(): filters and delays start again

Every random number comes from one numpy Generator (PCG64) seeded with ``sensors.seed``
(the initial IMU biases drawn first, where their σ > 0), then per control step two draws in
a fixed layout: the IMU's sample (white noise of the gyro and accelerometer, their bias
steps, the orientation's rotation vector) and the joints' and feet's (encoder noise, torque
noise, contact force noise), each part only where its σ > 0; so a run replays bit for bit
from its seed and configuration. With the ideal configuration (the default) nothing is drawn and
``measured`` is ``truth``, bit for bit.

Timing (doc/sim_node.md's contract): the reading of control step k is delivered at step k;
its content is the newest sample at least `delay` old (zero-order hold when a sensor is
slower than the control rate); until a sample is that old, the first sample after the
(re)start. A restart (the simulator's reset) empties the delays and the velocity filter;
the random stream and the IMU biases go on.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass

import numpy as np

from starleth_interface.config_checks import ConfigError
from starleth_interface.config_checks import check_choice as _choice
from starleth_interface.config_checks import check_int as _int
from starleth_interface.config_checks import check_number as _num
from starleth_interface.config_checks import fmt_bound as _fmt

from .kinematics import quat_xyzw_to_rot

# =========================================================================================
# the sensors section of the physics configuration (config.py's table of ranges)
# =========================================================================================
MAX_RATE = 100_000.0              # Hz: the highest control rate (config.MAX_CONTROL_RATE)

#: the numbers of the sensors section: field -> (lowest, highest) (the table above; the
#: lower bound of encoder_velocity_cutoff is open)
SENSOR_RANGES = {
    "imu_rate": (0.0, MAX_RATE),                # Hz, 0: the control rate
    "imu_delay": (0.0, 1.0),                            # s
    "imu_gyro_noise_density": (0.0, 1.0),               # rad/s/√Hz
    "imu_gyro_bias_random_walk": (0.0, 1.0),            # rad/s²/√Hz
    "imu_gyro_initial_bias_sigma": (0.0, 10.0),         # rad/s
    "imu_gyro_range": (0.0, 1000.0),                    # rad/s, 0: unlimited
    "imu_accel_noise_density": (0.0, 10.0),             # m/s²/√Hz
    "imu_accel_bias_random_walk": (0.0, 10.0),          # m/s³/√Hz
    "imu_accel_initial_bias_sigma": (0.0, 100.0),       # m/s²
    "imu_accel_range": (0.0, 10_000.0),                 # m/s², 0: unlimited
    "imu_orientation_noise": (0.0, math.pi),            # rad
    "encoder_noise": (0.0, 1.0),                        # rad
    "encoder_velocity_cutoff": (0.0, MAX_RATE),  # Hz (> 0)
    "torque_noise": (0.0, 1000.0),                      # N m
    "contact_threshold": (0.0, 1e5),                    # N
    "contact_threshold_weight": (0.0, 1.0),             # share of the robot's weight m g
    "contact_force_noise": (0.0, 1e5),                  # N
}
#: initial biases: 3 numbers, each within +- this (rad/s, m/s²)
SENSOR_BIAS_BOUND = {"imu_gyro_initial_bias": 10.0, "imu_accel_initial_bias": 100.0}
MAX_SEED = 2 ** 63 - 1            # a ROS integer parameter (int64)
MAX_ENCODER_COUNTS = 2 ** 32      # counts per revolution (a 32-bit counter)
MAX_CONTACT_DELAY = 1000          # control steps


@dataclass
class SensorConfig:
    """The sensors' models (physics/sensors.py; doc/sensors.md): all zero / off (the
    default) is ideal, every measured value the exact one bit for bit."""

    #: the one random stream of every sensor (numpy PCG64 seeded with it)
    seed: int = 0
    #: IMU sample rate [Hz]: 0 = the control rate; else control_rate / m or m x control_rate
    imu_rate: float = 0.0
    #: a sample is delivered this late [s]: a whole number of control periods
    imu_delay: float = 0.0
    imu_gyro_noise_density: float = 0.0        # white noise [rad/s/√Hz]: σ = density √rate
    imu_gyro_bias_random_walk: float = 0.0     # [rad/s²/√Hz]: per sample σ = it √(1/rate)
    imu_gyro_initial_bias: tuple = (0.0, 0.0, 0.0)   # [rad/s], base frame axes
    imu_gyro_initial_bias_sigma: float = 0.0   # [rad/s], drawn once per axis, added
    imu_gyro_range: float = 0.0                # clipped at +- this [rad/s]; 0: unlimited
    imu_accel_noise_density: float = 0.0       # [m/s²/√Hz]
    imu_accel_bias_random_walk: float = 0.0    # [m/s³/√Hz]
    imu_accel_initial_bias: tuple = (0.0, 0.0, 0.0)  # [m/s²]
    imu_accel_initial_bias_sigma: float = 0.0  # [m/s²]
    imu_accel_range: float = 0.0               # [m/s²]; 0: unlimited
    imu_orientation_noise: float = 0.0         # the AHRS's: a white rotation vector's σ [rad]
    encoder_counts: int = 0                    # counts per revolution; 0: exact angles
    encoder_noise: float = 0.0                 # σ of the angle [rad], before quantization
    encoder_velocity: str = "exact"            # or "filtered": the angles' low-passed difference
    encoder_velocity_cutoff: float = 100.0     # [Hz]
    torque_noise: float = 0.0                  # σ of the measured joint torque [N m]
    contact_threshold: float = 0.0             # a foot in contact: measured F_N > this [N]
    contact_threshold_weight: float = 0.0      # or as a share of the weight m g (not both)
    contact_force_noise: float = 0.0           # σ of the measured normal force [N]
    contact_delay: int = 0                     # control steps

    def validate(self, p):
        self.seed = _int(f"{p}.seed", self.seed, 0, MAX_SEED)
        for n, (lo, hi) in SENSOR_RANGES.items():
            setattr(self, n, _num(f"{p}.{n}", getattr(self, n), lo, hi,
                                  lo_open=n == "encoder_velocity_cutoff"))
        for n, bound in SENSOR_BIAS_BOUND.items():
            v = getattr(self, n)
            if not isinstance(v, (list, tuple)) or len(v) != 3:
                raise ConfigError(f"{p}.{n}: expected a list of 3 numbers, got {v!r:.60}")
            setattr(self, n, tuple(_num(f"{p}.{n}[{i}]", x, -bound, bound)
                                   for i, x in enumerate(v)))
        self.encoder_counts = _int(f"{p}.encoder_counts", self.encoder_counts, 0,
                                   MAX_ENCODER_COUNTS)
        self.encoder_velocity = _choice(f"{p}.encoder_velocity", self.encoder_velocity,
                                        {"exact", "filtered"})
        self.contact_delay = _int(f"{p}.contact_delay", self.contact_delay, 0,
                                  MAX_CONTACT_DELAY)
        if self.contact_threshold and self.contact_threshold_weight:
            raise ConfigError(f"{p}.contact_threshold_weight: a threshold in N "
                              f"(contact_threshold) or a share of the weight, not both")

    def check_rates(self, control_rate: float):
        """The rules with the control rate: the IMU samples at control steps or m per
        control step, and delivers a sample a whole number of control periods late."""
        r = self.imu_rate
        if r:
            ratio = max(r, control_rate) / min(r, control_rate)
            if abs(ratio - round(ratio)) > 1e-9 * ratio:
                raise ConfigError(f"sensors.imu_rate: must be control_rate / m or m x "
                                  f"control_rate (m a whole number; control_rate "
                                  f"{_fmt(control_rate)} Hz), got {_fmt(r)}")
        steps = self.imu_delay * control_rate
        if abs(steps - round(steps)) > 1e-9 * max(steps, 1.0):
            raise ConfigError(f"sensors.imu_delay: must be a whole number of control periods "
                              f"({_fmt(1e3 / control_rate)} ms), got {_fmt(self.imu_delay)} s")

    def is_ideal(self, control_rate: float) -> bool:
        """Every measured value is the exact one: no noise, bias, quantization, filter,
        clipping, threshold or delay, and the IMU samples at every control step (at the
        control rate or faster)."""
        zero = [getattr(self, n) for n in SENSOR_RANGES if n not in
                ("imu_rate", "encoder_velocity_cutoff")]
        return (not any(zero) and not self.encoder_counts and not self.contact_delay
                and self.encoder_velocity == "exact"
                and (not self.imu_rate or self.imu_rate >= control_rate * (1 - 1e-9))
                and not any(self.imu_gyro_initial_bias + self.imu_accel_initial_bias))

    def to_dict(self) -> dict:
        d = asdict(self)
        for n in SENSOR_BIAS_BOUND:
            d[n] = list(d[n])
        return d



@dataclass
class SensorReading:
    """One control step's sensor values, measured or exact (public joint order; the feet in
    the description's foot order)."""

    joint_position: np.ndarray           # φ [rad]
    joint_velocity: np.ndarray           # φ̇ [rad/s]
    joint_effort: np.ndarray             # τ [N m] (the applied torque of the last step)
    imu_orientation: np.ndarray          # base in the world, quaternion x y z w
    imu_angular_velocity: np.ndarray     # ω, base frame [rad/s]
    imu_linear_acceleration: np.ndarray  # proper acceleration Rᵀ(dv/dt − g), base frame
    contact_flag: np.ndarray             # 1.0 contact, 0.0 none
    contact_force: np.ndarray            # normal force F_N [N]


class ExactImu:
    """The exact IMU at the base origin, axes the base frame: proper acceleration
    a = Rᵀ (dv/dt − g), dv/dt the difference of the world linear velocity v with the
    previous control step's over the control period (zero at the first state after a
    restart)."""

    def __init__(self, gravity, control_period: float):
        self.gravity = np.asarray(gravity, dtype=float)
        self.dt = control_period
        self._v_prev = None

    def restart(self):
        """Forget the previous velocity (after a reset)."""
        self._v_prev = None

    def proper_acceleration(self, v, R) -> np.ndarray:
        acc = np.zeros(3) if self._v_prev is None else (v - self._v_prev) / self.dt
        self._v_prev = np.array(v, dtype=float)
        return R.T @ (acc - self.gravity)


def model_gravity(description) -> np.ndarray:
    """g of the robot's model [m/s²] (pin's; −9.81 z where it has none)."""
    try:
        g = np.array(description.model.gravity.linear, dtype=float)
        if g.shape == (3,) and np.all(np.isfinite(g)):
            return g
    except AttributeError:   # a description without a pin model
        pass
    return np.array([0.0, 0.0, -9.81])


def exact_reading(sim, imu: ExactImu, n_feet: int):
    """(the exact values of `sim`'s current state, its base state, R): `imu` gives the
    proper acceleration (called once per control step); a foot is in contact when it
    carries a normal force; the base state (Simulator.base_state) and its rotation matrix R
    for whoever publishes them too."""
    b = sim.base_state()
    quat = b["orientation_xyzw"]
    R = np.empty((3, 3))
    quat_xyzw_to_rot(float(quat[0]), float(quat[1]), float(quat[2]), float(quat[3]), R)
    f_n = sim.contact_normal_forces()[:n_feet]
    return SensorReading(
        np.asarray(sim.joint_positions(), dtype=float),
        np.asarray(sim.joint_velocities(), dtype=float), sim.applied_torque,
        np.asarray(quat, dtype=float), np.asarray(b["angular_velocity"], dtype=float),
        imu.proper_acceleration(b["linear_velocity"], R),
        (f_n > 0.0).astype(float), f_n), b, R


def contact_threshold(c, description) -> float:
    """The contact flag's force threshold [N]: `contact_threshold`, or
    `contact_threshold_weight` times the robot's weight m g."""
    if not c.contact_threshold_weight:
        return c.contact_threshold
    g = float(np.linalg.norm(model_gravity(description)))
    return c.contact_threshold_weight * description.total_mass * g


class DelayLine:
    """Samples (step, value) in step order; `get(k)` the newest at least `delay` steps old
    at step k (steps asked for never decrease), else the oldest."""

    def __init__(self, delay: int):
        self.delay = delay
        self._q = deque()

    def clear(self):
        self._q.clear()

    def put(self, k: int, value):
        self._q.append((k, value))

    def get(self, k: int):
        q, due = self._q, k - self.delay
        while len(q) > 1 and q[1][0] <= due:
            q.popleft()
        return q[0][1]


def quat_times_rotvec(q, theta) -> np.ndarray:
    """q ⊗ exp(θ/2) (x y z w): q turned by the rotation vector θ in its own frame."""
    angle = math.sqrt(float(theta @ theta))
    if angle < 1e-300:
        return q.copy()
    s = math.sin(angle / 2) / angle
    bx, by, bz, bw = theta[0] * s, theta[1] * s, theta[2] * s, math.cos(angle / 2)
    x, y, z, w = q
    out = np.array([w * bx + x * bw + y * bz - z * by, w * by - x * bz + y * bw + z * bx,
                    w * bz + x * by - y * bx + z * bw, w * bw - x * bx - y * by - z * bz])
    return out / np.linalg.norm(out)


class ImuModel:
    """Gyro and accelerometer (rows 0 and 1 of a 2 x 3 array): white noise of σ = density
    √rate, a bias that starts at the initial bias (a fixed vector plus one draw of σ per
    axis) and walks by σ_b = walk √(1/rate) after each sample, clipping at the range; the
    orientation (an AHRS's) the exact one turned by a white rotation vector. Samples every
    `every` control steps (a rate below the control rate), or the newest of m per control
    step (above it: the noise at the rate, the bias walked m samples)."""

    def __init__(self, c, control_rate: float, rng):
        rate = c.imu_rate or control_rate
        self.every = max(1, round(control_rate / rate))
        m = max(1, round(rate / control_rate))
        self.sigma = np.array([[c.imu_gyro_noise_density], [c.imu_accel_noise_density]]) \
            * math.sqrt(rate)
        self.walk = np.array([[c.imu_gyro_bias_random_walk], [c.imu_accel_bias_random_walk]]) \
            * math.sqrt(m / rate)
        self.range = np.array([[c.imu_gyro_range or np.inf], [c.imu_accel_range or np.inf]])
        self.orientation_noise = c.imu_orientation_noise
        #: the numbers drawn per sample: white noise, bias steps, orientation
        self.draws = (6 if self.sigma.any() else 0, 6 if self.walk.any() else 0,
                      3 if self.orientation_noise else 0)
        self.rng = rng
        self.bias = np.array([c.imu_gyro_initial_bias, c.imu_accel_initial_bias], dtype=float)
        drawn = np.array([[c.imu_gyro_initial_bias_sigma], [c.imu_accel_initial_bias_sigma]])
        if drawn.any():
            self.bias += drawn * rng.standard_normal((2, 3))
        self.line = DelayLine(round(c.imu_delay * control_rate))

    def sample(self, k: int, truth: SensorReading):
        """Take the sample of step k (if the IMU samples at it) into the delay line: one
        draw of the white noise, the bias steps and the orientation's rotation vector."""
        if k % self.every:
            return
        n_white, n_walk, n_turn = self.draws
        z = self.rng.standard_normal(n_white + n_walk + n_turn)
        y = np.array([truth.imu_angular_velocity, truth.imu_linear_acceleration]) + self.bias
        if n_white:
            y += self.sigma * z[:6].reshape(2, 3)
        if n_walk:
            self.bias = self.bias + self.walk * z[n_white:n_white + 6].reshape(2, 3)
        y = np.clip(y, -self.range, self.range)
        quat = truth.imu_orientation
        if n_turn:
            quat = quat_times_rotvec(quat, self.orientation_noise * z[n_white + n_walk:])
        self.line.put(k, (quat, y[0], y[1]))


class Sensors:
    """The sensors of one simulator `sim` (its config.sensors), sampled at its current
    state now and after every control step (:meth:`sample`); ``measured`` and ``truth``
    the readings of the current state, ``base`` its base state and rotation matrix
    (Simulator.base_state, R: read once for every topic of the state)."""

    def __init__(self, sim):
        self.sim = sim
        self.config = c = sim.config.sensors
        self.ideal = c.is_ideal(sim.config.control_rate)
        self.n_feet = len(sim.description.foot_names)
        self.period = sim.control_period
        self.rng = np.random.default_rng(c.seed)
        self.exact_imu = ExactImu(model_gravity(sim.description), self.period)
        self.imu = None if self.ideal else ImuModel(c, sim.config.control_rate, self.rng)
        self.step_size = 2 * math.pi / c.encoder_counts if c.encoder_counts else 0.0
        self.alpha = 1.0 - math.exp(-2 * math.pi * c.encoder_velocity_cutoff * self.period)
        self.contacts = DelayLine(c.contact_delay)
        self.contact_threshold = contact_threshold(c, sim.description)
        self._draw_layout(sim.n_joints)
        self.restart()

    def restart(self):
        """After the simulator's reset: the delays, the velocity filter and the exact
        IMU's previous velocity start again; then the current state is sampled."""
        self.k = 0
        self.exact_imu.restart()
        self.contacts.clear()
        if self.imu is not None:
            self.imu.line.clear()
        self._angle_prev = self._velocity = None
        self.sample()

    def sample(self):
        """The readings of the simulator's current state (once per control step)."""
        t, b, R = exact_reading(self.sim, self.exact_imu, self.n_feet)
        self.truth, self.base = t, (b, R)
        if self.ideal:
            self.measured = t
        else:
            self.measured = self._measure(t)
        self.k += 1

    def _measure(self, t: SensorReading) -> SensorReading:
        c, k = self.config, self.k
        self.imu.sample(k, t)
        quat, gyro, acc = self.imu.line.get(k)
        # one draw for the encoders, the torques and the contact forces (those with σ > 0)
        sigma = self._sigma
        z = self.rng.standard_normal(self._draws) if self._draws else None
        angle, effort, force = (t.joint_position, t.joint_effort, t.contact_force)
        if sigma[0]:
            angle = angle + sigma[0] * z[self._at[0]]
        if self.step_size:
            angle = np.round(angle / self.step_size) * self.step_size
        velocity = t.joint_velocity if c.encoder_velocity == "exact" else \
            self._filtered_velocity(angle)
        if sigma[1]:
            effort = effort + sigma[1] * z[self._at[1]]
        if sigma[2]:
            force = force + sigma[2] * z[self._at[2]]
        self.contacts.put(k, ((force > self.contact_threshold).astype(float), force))
        flag, force = self.contacts.get(k)
        return SensorReading(angle, velocity, effort, quat, gyro, acc, flag, force)

    def _draw_layout(self, n_joints: int):
        """Where the encoders', torques' and contact forces' numbers sit in a step's draw
        (only those with σ > 0 are drawn)."""
        c = self.config
        self._sigma = (c.encoder_noise, c.torque_noise, c.contact_force_noise)
        self._at, i = [], 0
        for s, n in zip(self._sigma, (n_joints, n_joints, self.n_feet), strict=True):
            self._at.append(slice(i, i + n if s else i))
            i += n if s else 0
        self._draws = i

    def _filtered_velocity(self, angle) -> np.ndarray:
        """v_k = v_(k−1) + α ((φ_k − φ_(k−1))/T − v_(k−1)), α = 1 − exp(−2π f_c T): the
        finite difference of the measured angles through a first-order low-pass (its
        step response sampled exactly); 0 at the first sample."""
        if self._angle_prev is None:
            v = np.zeros_like(angle)
        else:
            d = (angle - self._angle_prev) / self.period
            v = self._velocity + self.alpha * (d - self._velocity)
        self._angle_prev, self._velocity = angle, v
        return v
