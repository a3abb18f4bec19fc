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
