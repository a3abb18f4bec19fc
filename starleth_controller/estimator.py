"""State estimation from the robot's own sensors: the extended Kalman filter of Bloesch et
al., "State Estimation for Legged Robots: Consistent Fusion of Leg Kinematics and IMU"
(RSS 2012), which fuses an IMU with the leg kinematics of the feet on the ground.

The filter (``LegOdometryEKF``) reads what a robot's drivers deliver each control step:
the IMU's angular rate ω̃ and proper acceleration f̃ (base frame, the IMU at the base
origin), the measured joint angles and a contact flag per foot. It needs no ground truth.
Doc: doc/estimator.md (model, equations, parameters, figures). numpy only; no ROS.

State x (world frame W = odometry frame, z up; base frame B):
    r      base position in W [m]
    v      base velocity in W [m/s]
    q      orientation, base → world (C = R(q)ᵀ is the paper's world → base rotation);
           quaternion in the ROS order (x, y, z, w)
    p_i    foot i's sphere centre in W [m], one per leg (the model's leg order)
    b_f    accelerometer bias (base frame) [m/s²]
    b_ω    gyroscope bias (base frame) [rad/s]

Process model (continuous, w_*: white noise of the densities in ``EstimatorParams``):
    ṙ = v,   v̇ = R (f̃ − b_f − w_f) + g,   Ṙ = R [ω̃ − b_ω − w_ω]×,
    ṗ_i = ρ ω_shank × e_z + w_p,i  (the foot sphere rolls; σ_contact in contact, σ_swing ≫
    without: a foot in the air is free),   ḃ_f = w_bf,  ḃ_ω = w_bω.
Measurement of each foot in contact (forward kinematics of the measured joint angles):
    s_i = Rᵀ (p_i − r) + n_s.
Error state δx = (δr, δv, δφ, δp_i, δb_f, δb_ω) with the orientation error a rotation vector
in the world frame: R = Exp(δφ) R̂. Beyond the paper's equations: the rolling feet and Φ
constrained to keep yaw unobservable (``LegOdometryEKF._constrain``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .inputs import RobotState

#: error-state blocks: r, v, φ, then the feet, then b_f, b_ω (3 each)
IR, IV, IPHI, IP0 = 0, 3, 6, 9


@dataclass
class EstimatorParams:
    """Noise densities and initial standard deviations of ``LegOdometryEKF`` (their meaning:
    ESTIMATOR_PARAMETERS; controller_node's ``estimator.<name>`` parameters).

    Defaults: an ADIS16448-class MEMS IMU (msg_configs/sensors/realistic.yaml: gyroscope
    3.4e-4 rad/s/√Hz, accelerometer 4e-3 m/s²/√Hz, turn-on biases 8.7e-3 rad/s and
    0.2 m/s², bias walk 6e-3 m/s³/√Hz), the white-noise densities raised to cover what the
    model leaves out (vibration, the control period's discretisation of f̃ and ω̃); leg
    kinematics good to ~1 cm; feet on hard ground that slip a few mm per stance.
    doc/estimator.md gives the reasoning."""
    accel_noise: float = 0.02
    gyro_noise: float = 0.002
    accel_bias_walk: float = 6e-3
    gyro_bias_walk: float = 1e-4
    foot_contact_walk: float = 0.005
    foot_swing_walk: float = 10.0
    kinematics_noise: float = 0.01
    init_position: float = 1e-3
    init_velocity: float = 0.1
    init_orientation: float = 0.05
    init_foot: float = 0.01
    init_accel_bias: float = 0.2
    init_gyro_bias: float = 0.01
    #: the controller's contact flag of a foot stays set this long after the sensor's drops
    #: [s] (estimator_intake.ContactHold; the filter itself takes the sensor's flags)
    contact_hold: float = 0.005
    #: the feet in contact roll with their shanks (the sphere's centre moves ρ ω × e_z)
    rolling_feet: bool = True
    #: Φ keeps yaw and position unobservable (LegOdometryEKF._constrain)
    observability_constrained: bool = True


#: the numbers of EstimatorParams: name, meaning (controller_node's estimator.<name>)
ESTIMATOR_PARAMETERS = (
    ("accel_noise", "σ_f, accelerometer white noise density [m/s²/√Hz]"),
    ("gyro_noise", "σ_ω, gyroscope white noise density [rad/s/√Hz]"),
    ("accel_bias_walk", "σ_bf, accelerometer bias random walk [m/s³/√Hz]"),
    ("gyro_bias_walk", "σ_bω, gyroscope bias random walk [rad/s²/√Hz]"),
    ("foot_contact_walk", "σ_contact, random walk of a foot in contact (slip) [m/√Hz]"),
    ("foot_swing_walk", "σ_swing, random walk of a foot in the air (free) [m/√Hz]"),
    ("kinematics_noise", "σ_s, noise of a foot position the legs measure [m]"),
    ("init_position", "initial standard deviation of the base position [m]"),
    ("init_velocity", "initial standard deviation of the base velocity [m/s]"),
    ("init_orientation", "initial standard deviation of the orientation [rad]"),
    ("init_foot", "initial standard deviation of the foot positions [m]"),
    ("init_accel_bias", "initial standard deviation of the accelerometer bias [m/s²]"),
    ("init_gyro_bias", "initial standard deviation of the gyroscope bias [rad/s]"),
    ("contact_hold", "the controller's contact flag stays set this long after the sensor's "
     "drops [s]"),
)


def quat_to_rot(q) -> np.ndarray:
    """R (base → world) of a unit quaternion (x, y, z, w)."""
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def quat_exp(phi) -> np.ndarray:
    """The unit quaternion (x, y, z, w) of the rotation vector φ (Exp)."""
    a = math.sqrt(phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2])
    if a < 1e-8:
        return np.array([0.5 * phi[0], 0.5 * phi[1], 0.5 * phi[2], 1.0])
    s = math.sin(0.5 * a) / a
    return np.array([s * phi[0], s * phi[1], s * phi[2], math.cos(0.5 * a)])


def quat_mul(a, b) -> np.ndarray:
    """The Hamilton product a ⊗ b of quaternions (x, y, z, w): R(a ⊗ b) = R(a) R(b)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz])


def skew(a) -> np.ndarray:
    """[a]×: skew(a) @ b = a × b."""
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def yaw_of(q) -> float:
    """The heading ψ of a quaternion (x, y, z, w) [rad]."""
    x, y, z, w = q
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


class LegOdometryEKF:
    """Bloesch et al.'s EKF for the robot of `model` (a RobotModel: its legs' kinematics).

    ``reset`` once (orientation from the AHRS, position from the legs), then ``step`` every
    control period; read ``position``, ``velocity`` (world), ``orientation_xyzw``,
    ``angular_velocity`` (base frame, ω̃ − b̂_ω), ``P`` (the error-state covariance,
    27 × 27 for four legs). Joint angles in the public order, contacts in the legs' order."""

    def __init__(self, model, params: EstimatorParams | None = None):
        self.model = model
        self.params = params or EstimatorParams()
        self.n_feet = len(model.legs)
        self.n = IP0 + 3 * self.n_feet + 6
        self.ibf, self.ibw = self.n - 6, self.n - 3
        self.g = np.array([0.0, 0.0, -model.gravity])
        self._order = model.joint_order
        self._s = np.zeros((self.n_feet, 3))     # the legs' foot positions (base frame)
        self.initialised = False
        self.t = None

    # -- the legs ----------------------------------------------------------------------------
    def foot_positions(self, joint_positions) -> np.ndarray:
        """s_i: each foot's sphere centre in the base frame (n_feet, 3), from the joint
        angles (public order) by the model's forward kinematics."""
        q = np.asarray(joint_positions, dtype=float)
        return self._fk(q if self._order is None else q[self._order]).copy()

    def _fk(self, q) -> np.ndarray:
        """foot_positions of joint angles in the controller's order (in a buffer the next
        call overwrites)."""
        fk = self.model.leg_fk
        for k in range(self.n_feet):
            self._s[k] = fk(k, q[3 * k], q[3 * k + 1], q[3 * k + 2])
        return self._s

    # -- start -------------------------------------------------------------------------------
    def reset(self, t, orientation_xyzw, joint_positions, contact, position=None):
        """Start at time `t` [s]: orientation from the AHRS (x, y, z, w), at rest, feet from
        the legs; `position` (world) by default above the origin, the height the feet in
        contact give (their sphere centres one foot radius above z = 0)."""
        p = self.params
        self.q = np.asarray(orientation_xyzw, dtype=float) / np.linalg.norm(orientation_xyzw)
        R = quat_to_rot(self.q)
        s = self.foot_positions(joint_positions) @ R.T          # R s_i, world
        if position is None:
            c = np.asarray(contact, dtype=bool)
            below = s[c] if c.any() else s
            radius = float(np.mean(self.model.foot_radius))
            position = (0.0, 0.0, radius - float(np.mean(below[:, 2])))
        self.r = np.array(position, dtype=float)
        self.v = np.zeros(3)
        self.feet = self.r + s
        self.bf = np.zeros(3)
        self.bw = np.zeros(3)
        sig = [p.init_position] * 3 + [p.init_velocity] * 3 + [p.init_orientation] * 3 + \
            [p.init_foot] * (3 * self.n_feet) + [p.init_accel_bias] * 3 + [p.init_gyro_bias] * 3
        self.P = np.diag(np.square(sig))
        self.t = float(t)
        self.w = np.zeros(3)
        self._prior = None
        self.initialised = True

    # -- one control period ------------------------------------------------------------------
    def step(self, t, gyro, accel, joint_positions, contact, joint_velocities=None):
        """Advance to time `t` [s] with the IMU sample of this step (gyro ω̃ [rad/s], proper
        acceleration f̃ [m/s²], base frame: the means over the period since the last step,
        as a driver's backward difference gives them), then correct with the legs whose
        `contact` flag is set. With `joint_velocities` (public order) the feet in contact
        roll (``rolling_velocities``)."""
        dt = float(t) - self.t
        self.t = float(t)
        contact = np.asarray(contact, dtype=bool)
        q = np.asarray(joint_positions, dtype=float)
        if self._order is not None:
            q = q[self._order]
        self.w = np.asarray(gyro, dtype=float) - self.bw
        if dt > 0.0:
            roll = None
            if joint_velocities is not None and self.params.rolling_feet:
                dq = np.asarray(joint_velocities, dtype=float)
                roll = self.rolling_velocities(q, dq if self._order is None else
                                               dq[self._order])
                roll[~contact] = 0.0
            self.predict(dt, self.w + self.bw, np.asarray(accel, dtype=float), contact, roll)
        if contact.any():
            self.update(self._fk(q), contact)

    def rolling_velocities(self, q, dq) -> np.ndarray:
        """The velocity (world) of each foot sphere's centre as it rolls on level ground
        without slipping: ρ (ω_shank × e_z), ω_shank = R (ω + ω_leg) with the leg's own rate
        ω_leg = σ_r q̇_HAA e_x + Rx(σ_r q_HAA) (σ₁ q̇_HFE + σ₂ q̇_KFE) e_y (joints in the
        controller's order; σ: the axis signs of model.py)."""
        g = self.model.geometry
        q3, dq3 = q.reshape(-1, 3), dq.reshape(-1, 3)
        roll = g[:, 9] * q3[:, 0]
        wy = g[:, 10] * dq3[:, 1] + g[:, 11] * dq3[:, 2]
        w_leg = np.stack((g[:, 9] * dq3[:, 0], np.cos(roll) * wy, np.sin(roll) * wy), axis=1)
        ww = (w_leg + self.w) @ quat_to_rot(self.q).T
        rho = g[:, 3]
        return np.stack((rho * ww[:, 1], -rho * ww[:, 0], np.zeros(len(rho))), axis=1)

    def predict(self, dt, gyro, accel, contact, foot_velocity=None):
        """The IMU's prediction over dt: the mean (R ← R Exp(ω dt), v ← v + (R f + g) dt,
        r ← r + (v₀ + v) dt / 2, p_i ← p_i + ṗ_i dt with `foot_velocity` ṗ, world) and the
        covariance P ← Φ P Φᵀ + Q (module docstring)."""
        w = gyro - self.bw
        f = accel - self.bf
        self.w = w
        self.q = quat_mul(self.q, quat_exp(w * dt))
        self.q /= math.sqrt(float(self.q @ self.q))
        R = quat_to_rot(self.q)
        a = R @ f
        r0, v0, feet0 = self.r, self.v, self.feet
        self.v = v0 + (a + self.g) * dt
        self.r = r0 + 0.5 * (v0 + self.v) * dt
        if foot_velocity is not None:
            self.feet = feet0 + foot_velocity * dt
        Phi = self._transition(dt, R, a)
        if self._prior is not None and self.params.observability_constrained:
            self._constrain(Phi, dt, r0, v0)
        self._prior = None
        self.P = Phi @ self.P @ Phi.T + self._process_noise(dt, contact)

    def _constrain(self, Phi, dt, r0, v0):
        """The observability constraint (Huang et al.'s OC-EKF, the remedy of Bloesch et
        al. §V for the filter's spurious yaw information): Φ must carry the unobservable
        direction N(x) = (δr, δv, δφ, δp_i) = ([e]× r, [e]× v, e, [e]× p_i) (a turn about
        gravity e = e_z) of the predicted state the last update linearised at, x_{k|k−1},
        onto the one of the next prediction, x_{k+1|k}: the yaw columns of the r, v and p
        rows get ([e]× Δ) eᵀ, Δ the update's correction (r: plus its velocity's dt), the
        least change of Φ that does it."""
        r_p, v_p, feet_p = self._prior
        dv = v0 - v_p
        for row, d in ((IR, r0 - r_p + dv * dt), (IV, dv)):
            Phi[row:row + 2, IPHI + 2] += (-d[1], d[0])
        dp = self.feet - feet_p
        for k in range(self.n_feet):
            b = IP0 + 3 * k
            Phi[b:b + 2, IPHI + 2] += (-dp[k, 1], dp[k, 0])

    def _transition(self, dt, R, a):
        """Φ = exp(F dt) to the order that matters (F: the error dynamics δṙ = δv,
        δv̇ = −[R f]× δφ − R δb_f, δφ̇ = −R δb_ω)."""
        Phi = np.eye(self.n)
        A = skew(a)
        i, j = self.ibf, self.ibw
        dt2 = 0.5 * dt * dt
        Phi[IR:IR + 3, IV:IV + 3] = np.eye(3) * dt
        Phi[IR:IR + 3, IPHI:IPHI + 3] = -A * dt2
        Phi[IR:IR + 3, i:i + 3] = -R * dt2
        Phi[IR:IR + 3, j:j + 3] = A @ R * (dt2 * dt / 3.0)
        Phi[IV:IV + 3, IPHI:IPHI + 3] = -A * dt
        Phi[IV:IV + 3, i:i + 3] = -R * dt
        Phi[IV:IV + 3, j:j + 3] = A @ R * dt2
        Phi[IPHI:IPHI + 3, j:j + 3] = -R * dt
        return Phi

    def _process_noise(self, dt, contact):
        """Q of one period (isotropic densities, so R Σ Rᵀ = Σ): the accelerometer noise
        twice integrated into r and v (with their correlation), the gyroscope's into δφ,
        each foot's walk (σ_contact or σ_swing), the bias walks."""
        p = self.params
        Q = np.zeros((self.n, self.n))
        sf2 = p.accel_noise ** 2
        eye = np.eye(3)
        Q[IR:IR + 3, IR:IR + 3] = eye * (sf2 * dt ** 3 / 3.0)
        Q[IR:IR + 3, IV:IV + 3] = Q[IV:IV + 3, IR:IR + 3] = eye * (sf2 * dt * dt / 2.0)
        Q[IV:IV + 3, IV:IV + 3] = eye * (sf2 * dt)
        Q[IPHI:IPHI + 3, IPHI:IPHI + 3] = eye * (p.gyro_noise ** 2 * dt)
        for k in range(self.n_feet):
            s = p.foot_contact_walk if contact[k] else p.foot_swing_walk
            b = IP0 + 3 * k
            Q[b:b + 3, b:b + 3] = eye * (s * s * dt)
        Q[self.ibf:self.ibf + 3, self.ibf:self.ibf + 3] = eye * (p.accel_bias_walk ** 2 * dt)
        Q[self.ibw:self.ibw + 3, self.ibw:self.ibw + 3] = eye * (p.gyro_bias_walk ** 2 * dt)
        return Q

    def update(self, s, contact):
        """The legs' correction: y_i = s_i − R̂ᵀ(p̂_i − r̂) of the feet in contact, with
        H_r = −R̂ᵀ, H_φ = R̂ᵀ [p̂_i − r̂]×, H_p_i = R̂ᵀ; δx = K y, P ← (I − K H) P."""
        R = quat_to_rot(self.q)
        feet = np.flatnonzero(contact)
        m = 3 * len(feet)
        H = np.zeros((m, self.n))
        y = np.empty(m)
        for row, k in enumerate(feet):
            d = self.feet[k] - self.r
            b = 3 * row
            y[b:b + 3] = s[k] - R.T @ d
            H[b:b + 3, IR:IR + 3] = -R.T
            H[b:b + 3, IPHI:IPHI + 3] = R.T @ skew(d)
            H[b:b + 3, IP0 + 3 * k:IP0 + 3 * k + 3] = R.T
        self._prior = (self.r, self.v, self.feet)      # x_{k|k−1}: the constraint's
        PHt = self.P @ H.T
        S = H @ PHt
        S[np.diag_indices(m)] += self.params.kinematics_noise ** 2
        K = np.linalg.solve(S, PHt.T).T
        dx = K @ y
        P = self.P - K @ PHt.T
        self.P = 0.5 * (P + P.T)
        self._correct(dx)

    def _correct(self, dx):
        """Adds the error-state estimate δx to the state (R ← Exp(δφ) R)."""
        self.r = self.r + dx[IR:IR + 3]
        self.v = self.v + dx[IV:IV + 3]
        q = quat_mul(quat_exp(dx[IPHI:IPHI + 3]), self.q)
        self.q = q / math.sqrt(float(q @ q))
        self.feet = self.feet + dx[IP0:self.ibf].reshape(self.n_feet, 3)
        self.bf = self.bf + dx[self.ibf:self.ibf + 3]
        self.bw = self.bw + dx[self.ibw:self.ibw + 3]

    # -- outputs -----------------------------------------------------------------------------
    @property
    def position(self) -> np.ndarray:
        return self.r

    @property
    def velocity(self) -> np.ndarray:
        """v̂ in the world frame [m/s]."""
        return self.v

    @property
    def orientation_xyzw(self) -> np.ndarray:
        return self.q

    @property
    def angular_velocity(self) -> np.ndarray:
        """ω̃ − b̂_ω of the last step, base frame [rad/s]."""
        return self.w

    def robot_state(self, t, joint_positions, joint_velocities, contact) -> RobotState:
        """The controller's RobotState of the estimate (fresh arrays) with the measured
        joints (public order) and the contact flags (legs' order)."""
        return RobotState(float(t), np.array(joint_positions, dtype=float),
                          np.array(joint_velocities, dtype=float), self.r.copy(),
                          self.q.copy(), self.v.copy(), self.w.copy(),
                          np.array(contact, dtype=bool), None)
