"""The state estimator (starleth_controller.estimator, Bloesch et al. RSS 2012) headless: its
equations against finite differences and closed forms, and the filter on a simulated trot of
StarlETH (preset HmJ) fed as a robot's drivers would feed it (test/support/estimator_run.py:
the IMU's values from the simulator's state plus the test's noise and bias, the measured
joint angles, the contact flags), the controller driving from ground truth or from the
estimate.

Criteria (issue #48): velocity RMS error ≤ 0.05 m/s and horizontal position drift ≤ 5 % of
the distance walked with noisy sensors; yaw and position, unobservable, have a growing
covariance while roll and pitch stay bounded; with ideal sensors the velocity follows the
truth to a few mm/s; the controller walks on its own estimate.
"""
import math
from dataclasses import asdict
from types import SimpleNamespace

import numpy as np
import pinocchio as pin
import pytest
from estimator_run import EstimatorRun, Noise

from starleth_controller import Command, RobotModel
from starleth_controller.estimator import (
    IP0,
    IPHI,
    IR,
    EstimatorParams,
    LegOdometryEKF,
    quat_exp,
    quat_mul,
    quat_to_rot,
    skew,
)
from starleth_controller.estimator_intake import ContactHold, EstimatedState
from starleth_controller.node_parameters import PARAMETERS, check_parameters, estimator_params
from starleth_controller.robot_params import trot_speed
from starleth_interface.robot.scaling import robot_scale

#: per-sample noise at 400 Hz of a MEMS IMU (gyro 2.5e-4 rad/s/√Hz, accelerometer
#: 2.5e-3 m/s²/√Hz) and 12-bit-class encoders, with constant biases
NOISY = Noise(gyro=0.005, accel=0.05, joint=0.001, gyro_bias=(0.002, -0.001, 0.003),
              accel_bias=(0.05, -0.03, 0.04), seed=7)
STAND, TROT, SPEED = 1.0, 6.0, 0.3


def errors(rec):
    """(velocity RMS [m/s], horizontal drift per distance walked, yaw error at the end
    [rad]) of a run's record; drift: the horizontal position error's change from the first
    step to the last over the horizontal path length."""
    ev = rec["v_hat"] - rec["v"]
    rms = float(np.sqrt(np.mean(np.sum(ev * ev, axis=1))))
    er = rec["r_hat"] - rec["r"]
    dist = float(np.sum(np.linalg.norm(np.diff(rec["r"][:, :2], axis=0), axis=1)))
    drift = float(np.linalg.norm(er[-1, :2] - er[0, :2])) / dist
    yaw = math.remainder(rec["yaw_hat"][-1] - rec["yaw"][-1], 2 * math.pi)
    return rms, drift, yaw


def trot(noise, drive="truth", params=None):
    r = EstimatorRun("HmJ", noise, params, drive=drive)
    r.run(Command("stand"), STAND)
    r.run(Command("trot", forward=SPEED), TROT)
    return r.arrays()


@pytest.fixture(scope="module")
def noisy():
    return trot(NOISY)


# -- the equations -------------------------------------------------------------------------
def test_quaternion_helpers_are_rotations():
    """Exp(φ) turns by |φ| about φ (Rodrigues), ⊗ composes as R(a) R(b)."""
    phi = np.array([0.3, -0.2, 0.5])
    a = np.linalg.norm(phi)
    K = skew(phi / a)
    rodrigues = np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K
    assert np.allclose(quat_to_rot(quat_exp(phi)), rodrigues, atol=1e-12)
    b = quat_exp(np.array([-0.1, 0.4, 0.2]))
    assert np.allclose(quat_to_rot(quat_mul(quat_exp(phi), b)),
                       rodrigues @ quat_to_rot(b), atol=1e-12)


def _filter():
    model = RobotModel()
    e = LegOdometryEKF(model)
    q = model.nominal_joint_positions(0.41)
    e.reset(0.0, quat_exp([0.1, -0.05, 0.7]), q, np.ones(4, bool))
    e.r = np.array([0.3, -0.2, 0.45])
    e.feet += np.random.default_rng(3).normal(0.0, 0.02, (4, 3))
    return e


def test_the_leg_measurement_jacobian_is_the_derivative():
    """H of s_i = Rᵀ(p_i − r) (update's rows) against central differences of the error
    state (R = Exp(δφ) R̂)."""
    e = _filter()

    def h(dx):
        R = quat_to_rot(quat_mul(quat_exp(dx[IPHI:IPHI + 3]), e.q))
        r = e.r + dx[IR:IR + 3]
        feet = e.feet + dx[IP0:IP0 + 12].reshape(4, 3)
        return ((feet - r) @ R).reshape(-1)

    H = np.zeros((12, e.n))
    for k in range(4):
        d = e.feet[k] - e.r
        RT = quat_to_rot(e.q).T
        H[3 * k:3 * k + 3, IR:IR + 3] = -RT
        H[3 * k:3 * k + 3, IPHI:IPHI + 3] = RT @ skew(d)
        H[3 * k:3 * k + 3, IP0 + 3 * k:IP0 + 3 * k + 3] = RT
    num = np.zeros_like(H)
    for j in range(e.n):
        dx = np.zeros(e.n)
        dx[j] = 1e-6
        num[:, j] = (h(dx) - h(-dx)) / 2e-6
    assert np.abs(H - num).max() < 1e-8


def test_the_prediction_integrates_a_constant_acceleration_exactly():
    """No bias, constant f and ω = 0: v and r after n steps are the closed forms; P stays
    symmetric and grows."""
    e = _filter()
    R = quat_to_rot(e.q)
    a_w = np.array([0.5, -0.2, 0.1])
    f = R.T @ (a_w - e.g)
    r0, p0 = e.r.copy(), np.trace(e.P)
    for _ in range(400):
        e.predict(0.0025, np.zeros(3), f, np.zeros(4, bool))
    assert np.allclose(e.v, a_w * 1.0, atol=1e-12)
    assert np.allclose(e.r, r0 + 0.5 * a_w * 1.0, atol=1e-12)
    assert np.allclose(e.P, e.P.T) and np.trace(e.P) > p0


# -- on a simulated trot ---------------------------------------------------------------------
def test_noisy_sensors_velocity_rms_and_drift(noisy):
    rms, drift, yaw = errors(noisy)
    print(f"\n[HmJ noisy] velocity RMS {rms:.4f} m/s, drift {100 * drift:.2f} % of "
          f"distance, yaw error {math.degrees(yaw):.2f} deg")
    assert rms <= 0.05 and drift <= 0.05


def test_yaw_and_position_are_unobservable_roll_and_pitch_are_not(noisy):
    """The covariance of yaw and of the horizontal position grows over the run (nothing
    measures them); roll and pitch (gravity) and the velocity stay bounded."""
    P = noisy["P"]
    n = len(P)
    early, late = P[n // 4], P[-1]
    assert late[IPHI + 2] > 1.5 * early[IPHI + 2], (early[IPHI + 2], late[IPHI + 2])
    assert late[IR] > 1.5 * early[IR] and late[IR + 1] > 1.5 * early[IR + 1]
    for i in (IPHI, IPHI + 1, 3, 4, 5):
        assert late[i] < 2.0 * early[i] and math.sqrt(late[i]) < 0.05, (i, early[i], late[i])


def test_without_the_observability_constraint_yaw_information_appears():
    """The plain EKF (Φ at the updated state, H at the predicted one) gains yaw information
    that nothing measures: its yaw variance shrinks over the same run."""
    P = trot(NOISY, params=EstimatorParams(observability_constrained=False))["P"]
    assert P[-1, IPHI + 2] < 0.7 * P[len(P) // 4, IPHI + 2]


def test_ideal_sensors_velocity_tracks_the_truth():
    rms, drift, yaw = errors(trot(Noise()))
    print(f"\n[HmJ ideal] velocity RMS {rms:.5f} m/s, drift {100 * drift:.3f} %, yaw error "
          f"{math.degrees(yaw):.3f} deg")
    assert rms < 0.003 and drift < 0.005 and abs(yaw) < math.radians(0.1)


def test_the_controller_walks_on_its_own_estimate():
    """The controller's state built from the filter alone (noisy sensors): no fall, the
    commanded speed reached, the estimate as good as in the open loop."""
    rec = trot(NOISY, drive="estimate")
    rms, drift, yaw = errors(rec)
    walked = rec["r"][-1, 0] - rec["r"][int(STAND * 400), 0]
    print(f"\n[HmJ on the estimate] walked {walked:.2f} m in {TROT:g} s, velocity RMS "
          f"{rms:.4f} m/s, drift {100 * drift:.2f} %, yaw error {math.degrees(yaw):.2f} deg")
    assert rec["r"][:, 2].min() > 0.3 and rec["tilt"].min() > math.cos(0.25)
    assert walked > 0.8 * SPEED * (TROT - 1.0)
    assert rms <= 0.05 and drift <= 0.05


def test_go1_walks_on_its_estimate_with_the_realistic_sensor_set():
    """Go1 (13 kg: stance feet carry 30-65 N) with the simulator's realistic sensors
    (msg_configs/sensors/realistic.yaml: IMU noise and biases one period late, quantized
    encoders with filtered velocities, contact flags from a noisy force threshold one step
    late), filter and controller on the measured values alone (the controller's flags held
    as controller_node holds them), 1 s stand + 3 s trot: no fall, the commanded speed
    reached, velocity RMS <= 0.05 m/s. Without the hold (contact_hold 0) the controller
    unloaded each leg whose flag dropped, the flags dropped the more, and the robot sat down
    to 0.13 m in the first second."""
    run = EstimatorRun("HmJ", drive="estimate", robot="go1", sensors="realistic")
    d = run.sim.description
    speed = trot_speed(robot_scale(d.legs, d.total_mass))
    run.run(Command("stand"), 1.0)
    run.run(Command("trot", forward=speed), 3.0)
    rec = run.arrays()
    rms, _, _ = errors(rec)
    walked = rec["r"][-1, 0] - rec["r"][400, 0]
    print(f"\n[Go1 realistic sensors, on the estimate] walked {walked:.2f} m, lowest "
          f"{rec['r'][:, 2].min():.3f} m, velocity RMS {rms:.4f} m/s")
    assert rec["r"][:, 2].min() > 0.8 * d.standing_height and rec["tilt"].min() > math.cos(0.25)
    assert walked > 0.8 * speed * 2.0
    assert rms <= 0.05


def test_contact_hold_keeps_a_dropped_flag_for_its_time_and_passes_a_touchdown():
    """ContactHold(hold = 5 ms) at 400 Hz: a flag that drops stays set 2 periods (5 ms)
    and drops at the third; a touch-down passes at once; reset forgets."""
    h = ContactHold(2, 0.005)
    seq = [(0.0, [True, False]), (0.0025, [False, False]), (0.005, [False, True]),
           (0.0075, [False, False]), (0.01, [False, False]), (0.0125, [False, False])]
    out = [h.flags(t, np.array(c)).tolist() for t, c in seq]
    assert out == [[True, False], [True, False], [True, True], [False, True], [False, True],
                   [False, False]]
    h.flags(0.015, np.array([True, True]))
    h.reset()
    assert h.flags(0.0175, np.array([False, False])).tolist() == [False, False]


def test_rolling_feet_turn_with_the_shank_as_pinocchio_says():
    """rolling_velocities = ρ (ω_shank × e_z) with ω_shank the foot link's angular velocity
    (world) that Pinocchio computes for the same base rate and joint rates, on StarlETH and
    on Go1 (other joint axes and order)."""
    rng = np.random.default_rng(5)
    for robot in ("starleth", "go1"):
        model = RobotModel(robot=robot)
        e = LegOdometryEKF(model)
        m, data = model.model, model.data
        q = pin.neutral(m)
        q[3:7] = quat_exp(rng.normal(0.0, 0.3, 3))
        qj = model.nominal_joint_positions(0.7 * model.leg_length) + \
            rng.normal(0.0, 0.1, 12)
        dqj = rng.normal(0.0, 2.0, 12)
        v = np.zeros(m.nv)
        v[3:6] = rng.normal(0.0, 0.5, 3)            # base rate, base frame
        q[model.iq], v[model.iv] = qj, dqj
        pin.forwardKinematics(m, data, q, v)
        pin.updateFramePlacements(m, data)
        e.q, e.w = np.array(q[3:7]), v[3:6].copy()
        roll = e.rolling_velocities(qj, dqj)
        for k in range(4):
            w = pin.getFrameVelocity(m, data, model.foot_frame[k],
                                     pin.ReferenceFrame.LOCAL_WORLD_ALIGNED).angular
            want = model.foot_radius[k] * np.cross(w, [0.0, 0.0, 1.0])
            assert np.allclose(roll[k], want, atol=1e-12), (robot, k, roll[k], want)


def test_the_node_intake_rejects_bad_sensor_messages_with_a_reason():
    """EstimatedState: a missing foot, flags of the wrong length, a NaN joint or IMU value,
    a zero quaternion give (None, key, reason) and leave the filter untouched."""
    model = RobotModel()
    est = EstimatedState(model)
    q = model.nominal_joint_positions(0.41)
    names = model.public_joint_names
    feet = list(model.foot_names)

    def slot(q=q, imu=(0, 0, 0, 1, 0, 0, 0, 0, 0, 9.81), contacts=(feet, [1.0] * 4)):
        return SimpleNamespace(js=(0, 0, names, list(q), [0.0] * 12), imu=imu,
                               contacts=contacts)

    bad = {"foot_contacts": slot(contacts=(feet[:3], [1.0] * 3)),
           "foot_contacts ": slot(contacts=(feet, [1.0] * 3)),
           "joint_states_nan": slot(q=[math.nan] + list(q[1:])),
           "imu_nan": slot(imu=(0, 0, 0, 1, 0, math.nan, 0, 0, 0, 9.81)),
           "imu_quat": slot(imu=(0, 0, 0, 0, 0, 0, 0, 0, 0, 9.81))}
    for key, s in bad.items():
        state, k, reason = est.robot_state(2_500_000, s)
        assert state is None and k == key.strip() and reason, (key, k, reason)
    assert not est.ekf.initialised
    state, _, _ = est.robot_state(2_500_000, slot(contacts=(feet[::-1], [1.0, 0.0, 1.0, 1.0])))
    assert list(state.foot_contact) == [True, True, False, True]     # by name
    assert len(est.odometry_values()) == 13


def test_node_parameters_give_the_filter_and_refuse_the_bundle():
    """controller_node's estimator.* parameters are EstimatorParams' fields with its
    defaults; state_source estimator with state_input bundle (ground truth) is refused."""
    p = {spec.name: spec.default for spec in PARAMETERS}
    want = asdict(EstimatorParams())
    del want["observability_constrained"]           # (a Python option, not a parameter)
    assert {k: v for k, v in asdict(estimator_params(p)).items() if k in want} == want
    assert {s.name[len("estimator."):] for s in PARAMETERS
            if s.name.startswith("estimator.")} == set(want)
    check_parameters(dict(p, state_source="estimator"))
    with pytest.raises(ValueError, match="state_input"):
        check_parameters(dict(p, state_source="estimator", state_input="bundle"))
