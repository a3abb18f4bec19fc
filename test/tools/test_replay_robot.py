"""starleth-replay on a robot other than StarlETH, from the bag alone: a Go1 run (PD hold)
recorded headless with sim_node's metadata and robot attachments, its URDF changed from the
library's (a heavier trunk), replays bit for bit with the robot library out of reach; the
foot forces are the Go1's feet."""
import json

import pytest
import yaml

pytest.importorskip("rclpy")

from geometry_msgs.msg import WrenchStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import JointState

from starleth_interface.topics import foot_wrench_topic
from starleth_sim import robots
from starleth_sim.physics import robot_build as build
from starleth_sim.physics.config import ConfigError, load_preset
from starleth_sim.physics.simulator import Simulator
from starleth_sim.ros.recording import McapRecorder
from starleth_sim.ros.service import SimService
from starleth_sim.ros.state_io import initial_state_record
from starleth_sim.tools.replay import recording as replay_recording
from starleth_sim.tools.replay import replay
from starleth_sim.tools.replay.resimulation import _snapshot

STEPS = 60


def _stamp(msg, ns):
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)
    return msg


def _write_state(rec, sim, feet, ns):
    s = _snapshot(sim, feet)
    js = JointState(name=list(sim.joint_names), position=s["joint_positions"].tolist(),
                    velocity=s["joint_velocities"].tolist(),
                    effort=[float(x) for x in sim.applied_torque])
    rec.write("/joint_states", _stamp(js, ns), ns)
    o = _stamp(Odometry(), ns)
    p, q = o.pose.pose.position, o.pose.pose.orientation
    p.x, p.y, p.z = map(float, s["base_position"])
    q.x, q.y, q.z, q.w = map(float, s["base_orientation"])
    tl, ta = o.twist.twist.linear, o.twist.twist.angular
    tl.x, tl.y, tl.z = map(float, s["base_linear_velocity"])
    ta.x, ta.y, ta.z = map(float, s["base_angular_velocity"])
    rec.write("/starleth/base_state", o, ns)
    for i, foot in enumerate(feet):
        w = _stamp(WrenchStamped(), ns)
        w.wrench.force.x, w.wrench.force.y, w.wrench.force.z = \
            map(float, s["foot_forces"][3 * i:3 * i + 3])
        rec.write("/" + foot_wrench_topic(foot), w, ns)


@pytest.fixture(scope="module")
def go1_bag(tmp_path_factory):
    """A Go1 whose recorded URDF has a 1 kg heavier trunk than the library's, under a PD
    hold, written as sim_node writes its recordings (metadata and attachments)."""
    try:
        robots.urdf_file(robots.load_robot("go1"))
    except ConfigError as e:      # example-robot-data missing: `make robots`
        pytest.skip(str(e))
    urdf = robots.robot_description("go1").urdf_xml
    heavier = urdf.replace('<mass value="5.204"/>', '<mass value="6.204"/>', 1)
    assert heavier != urdf
    spec = robots.spec_text("go1")
    desc = robots.recorded_description(heavier, spec, "go1")
    cfg = robots.config_with_robot(load_preset("HmJ"), "go1")
    sim = Simulator(cfg, description=desc)
    sim.reset()
    svc = SimService(sim, q0=sim.q.copy(), u0=sim.u.copy())
    path = str(tmp_path_factory.mktemp("go1") / "go1.mcap")
    rec = McapRecorder(path)
    for topic, t in (("/joint_states", JointState), ("/starleth/base_state", Odometry),
                     *(("/" + foot_wrench_topic(f), WrenchStamped) for f in desc.foot_names)):
        rec.add_topic(topic, t)
    init = initial_state_record(sim, svc.q0, svc.u0)
    rec.add_metadata("starleth_sim", {
        "physics_config": yaml.safe_dump(cfg.to_dict(), sort_keys=False),
        "initial_state": json.dumps(init), "joint_names": json.dumps(list(sim.joint_names)),
        "control_period": repr(sim.control_period), "stamp_period_ns": str(svc.period_ns),
        "namespace": "", "robot": "go1", "urdf_attachment": "go1.urdf",
        "robot_spec_attachment": "go1.robot.yaml"})
    rec.add_attachment("go1.urdf", "application/xml", heavier)
    rec.add_attachment("go1.robot.yaml", "application/yaml", spec)
    sim.reset(svc.q0, svc.u0)
    q_ref = sim.joint_positions().copy()
    _write_state(rec, sim, desc.foot_names, 0)
    for _k in range(1, STEPS + 1):
        svc.command = 40.0 * (q_ref - sim.joint_positions()) - 1.0 * sim.joint_velocities()
        assert svc.step() is not None
        _write_state(rec, sim, desc.foot_names, svc.stamp_ns)
    rec.close()
    return path


def test_a_go1_bag_replays_bit_for_bit_without_the_library(go1_bag, monkeypatch, capsys):
    def no_library(*_a, **_k):
        raise AssertionError("the robot library was asked")
    monkeypatch.setattr(build, "load_robot", no_library)
    monkeypatch.setattr(build, "urdf_file", no_library)
    assert replay.main([go1_bag]) == 0
    out = capsys.readouterr().out
    assert f"bit-identical: all {STEPS} steps" in out and "foot forces" in out
    rec = replay_recording.load_recording(go1_bag)
    # the Go1 stands on its four feet: on average over the settling hold they carry its
    # weight
    fz = rec.states["foot_forces"][1:, 2::3]
    assert len(rec.feet) == 4 and (fz[-1] > 0).all()
    mass = rec.description.total_mass
    assert fz.sum(axis=1).mean() == pytest.approx(mass * 9.81, rel=0.1)


def test_the_recorded_urdf_is_the_one_replayed(go1_bag):
    """Replayed on the library's Go1 (a lighter trunk), the run is no longer identical."""
    rec = replay_recording.load_recording(go1_bag)
    assert rec.feet == robots.robot_description("go1").foot_names
    assert rec.description.total_mass == pytest.approx(
        robots.robot_description("go1").total_mass + 1.0)
    from starleth_sim.tools.replay.resimulation import compare_exact, resimulate
    rec.description = robots.robot_description("go1")
    assert not compare_exact(rec, resimulate(rec)).identical


def test_analyze_labels_a_go1_bag_with_its_feet_and_joints(go1_bag, tmp_path):
    from starleth_sim.tools.analysis import analysis
    go1 = robots.robot_description("go1")
    out = tmp_path / "summary.json"
    assert analysis.main([go1_bag, "--no-plots", "--json", str(out),
                          "--foot", go1.foot_names[1][:2]]) == 0
    S = json.loads(out.read_text())["runs"][0]
    assert S["robot"] == "go1" and S["feet_order"] == list(go1.foot_names)
    assert list(S["joints"]["max_abs"]) == list(go1.joint_names)
    # the weight of the recorded robot (its 1 kg heavier trunk), not the library's
    assert S["mass"] == pytest.approx(go1.total_mass + 1.0, rel=1e-12)
    assert analysis.main([go1_bag, "--no-plots", "--foot", "LF"]) == 1   # not a Go1 foot
