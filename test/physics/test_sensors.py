"""The sensor models (starleth_sim.physics.sensors, the config's sensors section): ideal
sensors return the exact values bit for bit; the noise of a run has the configured standard
deviation (within 10 %), the bias random walk its spread (a chi-square band over seeds, and
its increments' σ); the quantum of an encoder is 2π/counts; the filtered velocity is the
sampled step response of its low-pass; the IMU holds and delays its samples, the contact
flags are delayed; one seed gives one run bit for bit; bad files name file and field."""
import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from starleth_sim import ConfigError, Simulator, load_preset
from starleth_sim.physics.impedance import ImpedanceCommand
from starleth_sim.physics.sensors import ImuModel, SensorReading, Sensors
from starleth_sim.tools.analysis.sensor_noise import noise_statistics

PERIOD = 1 / 400


def _holding(sim):
    """The standing posture held by the joint impedance law (the robot stays up)."""
    return ImpedanceCommand.create(sim.joint_names, position=sim.joint_positions(), kp=80.0,
                                   kd=2.0)


def _run(steps=800, **sensors):
    """(measured, truth) {signal: (steps + 1, channels)} of HmJ standing from its initial
    state, `sensors` fields."""
    sim = Simulator.from_preset("HmJ", **{f"sensors.{k}": v for k, v in sensors.items()})
    s, cmd = Sensors(sim), _holding(sim)
    rows = {"measured": [s.measured], "truth": [s.truth]}
    for _ in range(steps):
        sim.step(cmd)
        s.sample()
        rows["measured"].append(s.measured)
        rows["truth"].append(s.truth)
    return tuple(_signals(rows[w]) for w in ("measured", "truth")), sim


def _signals(readings):
    def stack(name):
        return np.array([getattr(r, name) for r in readings])
    return {"gyro": stack("imu_angular_velocity"), "accel": stack("imu_linear_acceleration"),
            "orientation": stack("imu_orientation"), "joint_position": stack("joint_position"),
            "joint_velocity": stack("joint_velocity"), "joint_effort": stack("joint_effort"),
            "contact_force": stack("contact_force"), "contact_flag": stack("contact_flag")}


def test_ideal_sensors_return_the_exact_values_bit_for_bit():
    sim = Simulator.from_preset("HmJ")
    assert sim.config.sensors.is_ideal(400.0)
    # the IMU at a lower rate holds its samples: not ideal; at a higher one it is
    assert not replace(sim.config.sensors, imu_rate=200.0).is_ideal(400.0)
    assert replace(sim.config.sensors, imu_rate=800.0).is_ideal(400.0)
    s, cmd = Sensors(sim), _holding(sim)
    g = np.array([0.0, 0.0, -9.81])
    v_prev = sim.base_state()["linear_velocity"]
    for _ in range(5):
        sim.step(cmd)
        s.sample()
        assert s.measured is s.truth
        m, b = s.measured, sim.base_state()
        for a, exact in ((m.joint_position, sim.joint_positions()),
                         (m.joint_velocity, sim.joint_velocities()),
                         (m.joint_effort, sim.applied_torque),
                         (m.imu_orientation, b["orientation_xyzw"]),
                         (m.imu_angular_velocity, b["angular_velocity"])):
            assert np.array_equal(a, exact)
        x, y, z, w = b["orientation_xyzw"]
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        a_proper = R.T @ ((b["linear_velocity"] - v_prev) / PERIOD - g)
        assert np.allclose(m.imu_linear_acceleration, a_proper, rtol=1e-12, atol=1e-9)
        v_prev = b["linear_velocity"]
        f_n = sim.contact_forces()[:4] @ np.array([0.0, 0.0, 1.0])     # flat ground: n = z
        assert np.allclose(m.contact_force, f_n, rtol=1e-12)
        assert np.array_equal(m.contact_flag, (m.contact_force > 0).astype(float))


NOISE = {"imu_gyro_noise_density": 3e-4, "imu_accel_noise_density": 4e-3,
         "imu_orientation_noise": 0.01, "encoder_noise": 2e-4, "torque_noise": 0.1,
         "contact_force_noise": 5.0, "imu_rate": 200.0, "imu_delay": 0.005,
         "contact_delay": 2, "imu_gyro_initial_bias": [0.01, -0.02, 0.0],
         "imu_accel_initial_bias_sigma": 0.2, "seed": 7}


def test_noise_of_a_run_has_the_configured_sigma():
    """800 steps of HmJ standing (3 x 400 IMU samples at 200 Hz): σ within 10 %, the fixed
    gyro bias as the error's mean; the IMU and contact delays aligned as configured."""
    (measured, truth), sim = _run(800, **NOISE)
    stats = noise_statistics(measured, truth, sim.config.sensors, 400.0)
    figures = {s: (f["sigma"], f["expected_sigma"]) for s, f in stats.items()
               if f["expected_sigma"]}
    assert set(figures) == {"gyro", "accel", "orientation", "joint_position",
                            "joint_effort", "contact_force"}
    assert figures["gyro"][1] == pytest.approx(3e-4 * math.sqrt(200.0))
    for s, (sigma, expected) in figures.items():
        assert abs(sigma / expected - 1) < 0.10, (s, sigma, expected)
    # (the fixed bias is the mean: within 4 standard errors of 400 samples' mean)
    assert np.allclose(stats["gyro"]["mean"], [0.01, -0.02, 0.0],
                       atol=4 * figures["gyro"][1] / math.sqrt(400))
    assert stats["joint_velocity"]["rms"] == 0.0       # exact velocities
    # compared without the delay, the accelerometer's error holds the motion of two steps
    # (the finite-difference acceleration of a standing robot varies from step to step)
    shifted = noise_statistics(measured, truth, replace(sim.config.sensors, imu_delay=0.0),
                               400.0)
    assert shifted["accel"]["sigma"] > 2 * stats["accel"]["sigma"]


def _imu_samples(seed, n, **fields):
    c = SimpleNamespace(**{**load_preset("HmJ").sensors.to_dict(), **fields})
    imu = ImuModel(c, 400.0, np.random.default_rng(seed))
    zero = np.zeros(3)
    truth = SensorReading(None, None, None, np.array([0.0, 0, 0, 1]), zero, zero, None, None)
    for k in range(n):
        imu.sample(k, truth)
    return imu


def test_bias_random_walk_spread_is_in_its_chi_square_band():
    """Bias after n samples: N(0, n σ_b²) per axis, σ_b = walk √(1/rate); over 100
    seeds x 3 axes x (gyro, accel), Σ (b/σ)² is χ²(600): within ±5 standard deviations."""
    n, walk = 400, {"imu_gyro_bias_random_walk": 4e-5, "imu_accel_bias_random_walk": 6e-3}
    chi2 = 0.0
    for seed in range(100):
        imu = _imu_samples(seed, n, **walk)
        for b, w in zip(imu.bias, walk.values(), strict=True):
            chi2 += float(((b / (w * math.sqrt(n / 400.0))) ** 2).sum())
    dof = 600
    assert abs(chi2 - dof) < 5 * math.sqrt(2 * dof), chi2


def test_bias_random_walk_increments_of_a_run():
    """Without white noise, the increments of measured − true gyro of a 1000-step run are
    the walk's: σ_b = walk √(1/rate) within 10 %."""
    (measured, truth), _ = _run(1000, imu_gyro_bias_random_walk=4e-5)
    inc = np.diff(measured["gyro"] - truth["gyro"], axis=0)
    assert abs(inc.std() / (4e-5 * math.sqrt(1 / 400)) - 1) < 0.10


class FakeSim:
    """The simulator's readings the sensors take, set by the test."""

    def __init__(self, **sensors):
        self.config = load_preset("HmJ").with_overrides(
            **{f"sensors.{k}": v for k, v in sensors.items()})
        self.control_period = PERIOD
        self.description = SimpleNamespace(foot_names=("a", "b"), model=None)
        self.n_joints = 2
        self.angle = np.zeros(2)
        self.rate = np.zeros(2)
        self.force = np.zeros(2)
        self.omega = np.zeros(3)
        self.applied_torque = np.zeros(2)

    def base_state(self):
        return {"orientation_xyzw": np.array([0.0, 0.0, 0.0, 1.0]), "angular_velocity":
                self.omega.copy(), "linear_velocity": np.zeros(3)}

    def joint_positions(self):
        return self.angle.copy()

    def joint_velocities(self):
        return self.rate.copy()

    def contact_normal_forces(self):
        return self.force.copy()


def test_encoder_quantum_is_two_pi_over_counts():
    counts = 4096
    sim = FakeSim(encoder_counts=counts)
    s = Sensors(sim)
    seen = []
    for k in range(400):           # a slow sweep: 0.3 quanta per step
        sim.angle = np.array([0.3 * k, -0.7 * k]) * 2 * math.pi / counts
        s.sample()
        seen.append(s.measured.joint_position.copy())
        assert np.all(np.abs(s.measured.joint_position - sim.angle) <= math.pi / counts + 1e-15)
    steps = np.diff(np.unique(np.array(seen)[:, 0]))
    assert np.allclose(steps, 2 * math.pi / counts, rtol=1e-9, atol=0)


def test_filtered_velocity_is_the_low_pass_step_response():
    """A joint at constant rate c from step 0: v_k = c (1 − exp(−2π f_c k T)), the
    first-order low-pass's step response sampled (0 at the first sample)."""
    c, fc = 2.0, 40.0
    sim = FakeSim(encoder_velocity="filtered", encoder_velocity_cutoff=fc)
    s = Sensors(sim)
    assert np.all(s.measured.joint_velocity == 0.0)
    for k in range(1, 60):
        sim.angle = np.array([c, -c]) * k * PERIOD
        s.sample()
        expected = c * (1 - math.exp(-2 * math.pi * fc * k * PERIOD))
        assert np.allclose(s.measured.joint_velocity, [expected, -expected], rtol=1e-9)


def test_contact_flag_threshold_and_delay():
    sim = FakeSim(contact_threshold=20.0, contact_delay=3)
    s = Sensors(sim)
    flags = []
    for k in range(1, 14):
        sim.force = np.array([100.0 if k >= 5 else 0.0, 15.0])
        s.sample()
        flags.append((k, *s.measured.contact_flag, *s.measured.contact_force))
        assert s.truth.contact_flag[1] == 1.0      # the exact flag: any normal force
    first = next(k for k, f, *_ in flags if f == 1.0)
    assert first == 5 + 3
    assert all(f2 == 0.0 for _, _, f2, _, _ in flags)   # 15 N: below the threshold
    assert all(f1 == (100.0 if k >= 8 else 0.0) for k, _, _, f1, _ in flags)


def test_contact_threshold_as_a_share_of_the_weight():
    """contact_threshold_weight: the flag's threshold is that share of m g (a robot of
    10 kg, g = 9.81: 0.1 -> 9.81 N); the threshold in N and the share exclude each other."""
    sim = FakeSim(contact_threshold_weight=0.1)
    sim.description.total_mass = 10.0
    s = Sensors(sim)
    assert s.contact_threshold == pytest.approx(9.81, rel=1e-12)
    sim.force = np.array([9.8, 9.82])
    s.sample()
    assert s.measured.contact_flag.tolist() == [0.0, 1.0]
    with pytest.raises(ConfigError, match="sensors.contact_threshold_weight: .*not both"):
        FakeSim(contact_threshold=20.0, contact_threshold_weight=0.1)


def test_imu_zero_order_hold_and_delay():
    """At a quarter of the control rate with two periods of delay, the gyro at step k is
    the rate of step k − 2 rounded down to a multiple of 4 (the first sample before)."""
    sim = FakeSim(imu_rate=100.0, imu_delay=0.005)
    s = Sensors(sim)
    for k in range(1, 30):
        sim.omega = np.array([k, 0.0, 0.0])
        s.sample()
        j = max(k - 2, 0)
        assert s.measured.imu_angular_velocity[0] == j - j % 4


def test_one_seed_one_run_bit_for_bit():
    fields = {**NOISE, "encoder_counts": 16384, "encoder_velocity": "filtered",
              "imu_gyro_bias_random_walk": 4e-5}
    (a, _), _ = _run(50, **fields)
    (b, _), _ = _run(50, **fields)
    (c, _), _ = _run(50, **{**fields, "seed": 8})
    for s in a:
        assert a[s].tobytes() == b[s].tobytes(), s
    assert not np.array_equal(a["gyro"], c["gyro"])


def test_realistic_file_over_the_presets():
    cfg = load_preset("HmJ").with_overlay("realistic", "sensors")
    assert not cfg.sensors.is_ideal(cfg.control_rate) and cfg.sensors.encoder_counts == 16384
    assert load_preset("Cm").with_overlay("realistic", "sensors").sensors == cfg.sensors
    # the section and its seed are in the recorded configuration
    assert cfg.to_dict()["sensors"]["seed"] == cfg.sensors.seed


@pytest.mark.parametrize("text, message", [
    ("sensors:\n  imu_rate: 300.0\n", "sensors.imu_rate: must be control_rate / m"),
    ("sensors:\n  imu_delay: 0.001\n", "sensors.imu_delay: must be a whole number"),
    ("sensors:\n  encoder_noise: -1\n", "sensors.encoder_noise: must be >= 0"),
    ("sensors:\n  encoder_velocity: smooth\n", "sensors.encoder_velocity: must be one of"),
    ("sensors:\n  imu_gyro_initial_bias: [1, 2]\n", "sensors.imu_gyro_initial_bias: expected"),
    ("sensors:\n  gyro_noise: 1\n", "unknown field 'sensors.gyro_noise'"),
    ("actuator:\n  velocity_limit: derate\n", "expected a mapping with a 'sensors:' section"),
])
def test_bad_sensor_files_name_file_and_field(tmp_path, text, message):
    path = tmp_path / "mine.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_preset("HmJ").with_overlay(str(path), "sensors")
    assert str(e.value).startswith(str(path)) and message in str(e.value), str(e.value)


def test_unknown_sensor_file_names_the_shipped_ones():
    with pytest.raises(ConfigError, match="unknown sensors file 'nosuch'.*realistic"):
        load_preset("HmJ").with_overlay("nosuch", "sensors")


def _imu_run(steps, **fields):
    """(gyro, accelerometer) of `steps` + 1 samples of the FakeSim at rest."""
    s = Sensors(FakeSim(**fields))
    rows = [(s.measured.imu_angular_velocity, s.measured.imu_linear_acceleration)]
    for _ in range(steps):
        s.sample()
        rows.append((s.measured.imu_angular_velocity, s.measured.imu_linear_acceleration))
    return np.array([g for g, _ in rows]), np.array([a for _, a in rows])


def test_imu_faster_than_the_control_rate():
    """At 4 x the control rate the newest of 4 samples per control step: white noise of
    σ = density √1600, the bias walked 4 samples' worth, σ = walk √(4/1600), per step."""
    gyro, _ = _imu_run(2000, imu_rate=1600.0, imu_gyro_noise_density=1e-3)
    assert abs(np.std(gyro) / (1e-3 * 40.0) - 1) < 0.10
    _, acc = _imu_run(2000, imu_rate=1600.0, imu_accel_bias_random_walk=6e-3)
    assert abs(np.diff(acc, axis=0).std() / (6e-3 * math.sqrt(4 / 1600)) - 1) < 0.10
