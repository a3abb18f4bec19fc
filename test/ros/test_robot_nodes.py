"""A robot other than StarlETH through the nodes: ``starleth-demo --robot go1`` (sim_node in
lockstep + controller_node, both given the robot, recorded) stands, trots at least 0.8x its
commanded distance without a fall, and the bag carries Go1's names on every topic (joint
states in the URDF's joint order, a wrench topic per foot of the description, /tf frames
and the odometry's child frame the URDF's links) and Go1 itself (URDF and spec, rebuilt
without the library). A short run: 1 s standing, 4 s of trot (the demo's shortest checked
trot), as on hardware: realistic sensors (measured joint_states, IMU and foot contacts, the
exact ones on ground_truth/...) and controller_node walking on its own state estimate
(``--sensors realistic --state-source estimator``: no base_state read), whose error against
the ground truth stays within the issue's bounds (velocity ≤ 0.05 m/s RMS, drift ≤ 5 %)."""
import os

import pytest

rclpy = pytest.importorskip("rclpy")

from starleth_interface.topics import (
    TOPIC_BASE_STATE,
    TOPIC_JOINT_STATES,
    foot_wrench_topic,
    resolve,
)
from starleth_sim.physics.config import ConfigError
from starleth_sim.robots import recorded_description, robot_description
from starleth_sim.ros.tf import base_link
from starleth_sim.tools.common.bag import read_messages, recorded_robot
from starleth_sim.tools.demo.demo import run_demo
from starleth_sim.tools.demo.result import MIN_TROT_CHECKED, print_summary

# shares the controller tests' range (conftest._free_ros_domain: one after another)
DOMAIN_RANGE = (10, 40)       # first, span
DOMAIN_ID = 10 + os.getpid() % 40
ROBOT = "go1"


def test_go1_stands_trots_and_records_its_names_through_the_nodes(tmp_path):
    try:
        desc = robot_description(ROBOT)
    except ConfigError as e:          # its URDF not installed: says `make robots`
        pytest.skip(str(e))
    lines = []
    r = run_demo(stand=1.0, trot=MIN_TROT_CHECKED, physics="HmJ", robot=ROBOT,
                 record=str(tmp_path / "go1.mcap"), domain_id=DOMAIN_ID, echo=lines.append,
                 startup_timeout=120.0, run_timeout=120.0, bare_seconds=0.0,
                 sensors="realistic", state_source="estimator")
    ok = print_summary(r, echo=lines.append)
    report = "\n".join(lines)
    print("\n" + report)
    assert ok and r.exit_codes == {"controller_node": 0, "sim_node": 0}, report
    # the robot's own figures: speed 0.3 m/s x sqrt(lambda), a fall below its scale
    assert 0.0 < r.speed < 0.3 and r.fall_height < 0.3 * desc.standing_height / 0.415 + 1e-9
    assert r.trot_distance >= 0.8 * r.speed * r.trot, report
    # walked on its estimate: one of every step, within the bounds (print_summary's check)
    e = r.estimate
    assert e["stamps"] == r.joint_states and e["velocity_rms"] <= 0.05, report
    assert e["drift"] <= 0.05 and "state estimate       velocity error" in report, report
    assert r.topic_counts.get("/ground_truth/joint_states") == r.joint_states, report

    feet = {resolve(foot_wrench_topic(f)): f for f in desc.foot_names}
    joint_states, base_state = resolve(TOPIC_JOINT_STATES), resolve(TOPIC_BASE_STATE)
    bag = read_messages(r.bag, lambda topic, _: topic in (joint_states, base_state, "/tf"))
    assert set(feet) <= set(bag.counts), sorted(bag.counts)
    assert all(bag.counts[t] == r.joint_states for t in feet)
    assert {tuple(m.name) for _, m in bag.messages[joint_states]} == {tuple(desc.joint_names)}
    root = base_link(desc.urdf_xml)
    assert {m.child_frame_id for _, m in bag.messages[base_state]} == {root}
    frames = {(t.header.frame_id, t.child_frame_id) for _, m in bag.messages["/tf"]
              for t in m.transforms}
    links = {link.name for link in desc.model.frames}
    assert ("world", root) in frames and all(c in links for _, c in frames), frames
    # the bag keeps the robot: rebuilt from its attachments alone, it is Go1
    name, urdf, spec = recorded_robot(bag, r.bag)
    assert name == ROBOT and spec is not None
    again = recorded_description(urdf, spec, name)
    assert again.joint_names == desc.joint_names and again.foot_names == desc.foot_names
