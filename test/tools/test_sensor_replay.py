"""A noisy run through the nodes (sim_node lockstep, sensors:=realistic, seed 5, recorded):
its measured topics differ from the ground_truth/ ones by the configured noise (σ within
10 %, starleth-analyze's sensor_noise); starleth-replay regenerates every measured message
bit for bit from the recorded seed and configuration, and another seed does not; so does a
realtime run."""
import os
import signal
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from repo_root import ROOT
from ros_test_nodes import NodeProcess, RosTestNode, run_lockstep

from starleth_sim.tools.analysis import analysis
from starleth_sim.tools.analysis.sensor_noise import bag_noise
from starleth_sim.tools.bench.controllers import EchoController
from starleth_sim.tools.replay import recording as replay_recording
from starleth_sim.tools.replay import replay
from starleth_sim.tools.replay import resimulation as replay_resimulation

DOMAIN_RANGE = (140, 40)      # first, span (shared with test_replay, one after the other)
DOMAIN_ID = 140 + os.getpid() % 40  # conftest._free_ros_domain: a free one of the range
START_TIMEOUT = 120.0
N_STATES = 240
SEED = 5


@pytest.fixture(scope="module")
def noisy(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("noisy")
    ros = RosTestNode(DOMAIN_ID, "sensor_replay_test", events=True)
    mcap = str(tmp / "noisy.mcap")
    run_lockstep(ros, EchoController(ros.node), tmp / "sim.log", DOMAIN_ID, N_STATES,
                 START_TIMEOUT, record=mcap, sensors="realistic", seed=SEED)
    return mcap


def test_noisy_run_replays_bit_for_bit(noisy, capsys):
    assert replay.main([noisy]) == 0
    assert "bit-identical: all" in capsys.readouterr().out
    rec = replay_recording.load_recording(noisy)
    assert {"measured_joint_states", "imu", "foot_contacts"} <= set(rec.states)
    # the state compared is the exact one (ground_truth/joint_states), not the measured
    measured = rec.states["measured_joint_states"][:, :12]
    assert not np.array_equal(measured, rec.states["joint_positions"])
    assert np.abs(measured - rec.states["joint_positions"]).max() < 2e-3
    # the seed regenerates the measured messages: another one does not
    rec.config_yaml = rec.config_yaml.replace(f"seed: {SEED}\n", f"seed: {SEED + 1}\n")
    assert rec.config().sensors.seed == SEED + 1
    rep = replay_resimulation.resimulate(rec, steps=5)
    c = replay_resimulation.compare_exact(rec, rep)
    assert not c.identical and c.first_step == 0
    assert "imu" in c.first_quantities and "joint_positions" not in c.first_quantities


def test_noisy_run_noise_matches_the_configuration(noisy, capsys):
    doc = bag_noise(noisy)
    assert doc["seed"] == SEED
    stats = doc["signals"]
    for s in ("gyro", "accel", "orientation", "joint_effort", "contact_force"):
        f = stats[s]
        assert f["n"] >= 3 * N_STATES and abs(f["sigma"] / f["expected_sigma"] - 1) < 0.10, \
            (s, f)
    quantum, sigma = 2 * np.pi / 16384, 1e-4
    assert stats["joint_position"]["rms"] < quantum / 2 + 4 * sigma
    # starleth-analyze prints them
    assert analysis.main([noisy, "--no-plots"]) == 0
    out = capsys.readouterr().out
    assert f"sensors (measured - true, seed {SEED})" in out and "contact_force" in out


def test_noisy_realtime_run_replays_bit_for_bit(tmp_path, capsys):
    """The realtime loop (the drives holding the posture, no controller) with noisy sensors:
    the ground_truth/ topics are recorded and the replay regenerates every measured one."""
    mcap = str(tmp_path / "realtime.mcap")
    sim = NodeProcess("starleth_sim.ros.sim_node", tmp_path / "sim.log", DOMAIN_ID,
                      mode="realtime", real_time_factor=2.0, record=mcap, sensors="realistic")
    try:
        time.sleep(2.5)
        assert sim.alive(), sim.log()[-3000:]
    finally:
        rc = sim.stop(signal.SIGINT)
    assert rc == 0, sim.log()[-3000:]
    assert replay.main([mcap]) == 0
    out = capsys.readouterr().out
    assert "bit-identical: all" in out and "IMU, foot contacts" in out
    doc = bag_noise(mcap)
    assert doc is not None and doc["signals"]["contact_force"]["n"] > 400


#: a bias walk strong enough to stand out of the white noise in a short run (realistic's
#: white noise; its walks x ~1000), and the run's length in states
WALK_GYRO, WALK_ACCEL, WALK_STATES = 0.05, 0.5, 1260
#: the 99.9 % band of the chi-square estimate q̂ / q of 36 window differences (3 axes x 12
#: disjoint pairs of 0.125 s windows in 3 s): √(χ²₃₆(0.0005) / 36), √(χ²₃₆(0.9995) / 36)
WALK_BAND = (0.63, 1.40)


def test_recorded_bias_walk_matches_the_configuration(tmp_path):
    """The IMU biases walk at the configured density: measured from a recorded lockstep run
    (sensor_noise.bias_walk: window means of measured − true), within its chi-square band."""
    with open(os.path.join(ROOT, "msg_configs", "sensors", "realistic.yaml")) as f:
        text = f.read()
    text = text.replace("imu_gyro_bias_random_walk: 3.8785e-5",
                        f"imu_gyro_bias_random_walk: {WALK_GYRO}")
    text = text.replace("imu_accel_bias_random_walk: 6.0e-3",
                        f"imu_accel_bias_random_walk: {WALK_ACCEL}")
    sensors = tmp_path / "walking.yaml"
    sensors.write_text(text)
    ros = RosTestNode(DOMAIN_ID, "sensor_walk_test", events=True)
    mcap = str(tmp_path / "walk.mcap")
    run_lockstep(ros, EchoController(ros.node), tmp_path / "sim.log", DOMAIN_ID, WALK_STATES,
                 START_TIMEOUT, record=mcap, sensors=str(sensors), seed=SEED)
    stats = bag_noise(mcap)["signals"]
    for s, q in (("gyro", WALK_GYRO), ("accel", WALK_ACCEL)):
        walk = stats[s]["walk"]
        assert walk["expected_density"] == q and walk["resolved"], (s, walk)
        assert walk["differences"] >= 36, (s, walk)
        print(s, walk["density"] / q)
        assert WALK_BAND[0] < walk["density"] / q < WALK_BAND[1], (s, walk)
