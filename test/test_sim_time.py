"""Sim time as users meet it (issue #35): each robot of the launch file has its own clock
(two namespaced robots in lockstep, their controllers with use_sim_time:=true, started with
the `--ros-args` the launch file gives them), and the README's "Write your own controller"
example, run as written, keeps the robot standing. (Realtime mode's start: test_realtime_start.)

Nodes run as child processes on an isolated ROS_DOMAIN_ID; every wait is bounded and every
child is stopped in a finally."""
import os

import pytest

rclpy = pytest.importorskip("rclpy")

from launch_file import launch_nodes  # noqa: E402
from controller_examples import (controllers_page_blocks, readme_controller_blocks,  # noqa: E402
                                 run_beside_sim_node)  # noqa: E402
from ros_test_nodes import NodeProcess, RosTestNode  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from rcl_interfaces.msg import ParameterEvent  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_srvs.srv import SetBool  # noqa: E402

from starleth_sim.physics.description import STARLETH_STANDING_HEIGHT  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOMAIN_RANGE = (200, 20)       # first, span (conftest._free_ros_domain)
DOMAIN_ID = 200 + os.getpid() % 20
START_TIMEOUT = 120.0          # of silence: a node's compile lines restart it (ros_test_nodes)
BEST_EFFORT = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)


def seconds(stamp):
    return stamp.sec + stamp.nanosec * 1e-9


@pytest.fixture(scope="module")
def ros():
    node = RosTestNode(DOMAIN_ID, "sim_time_test", events=True)
    try:
        yield node
    finally:
        node.close()


class Latest:
    """The latest message of a topic, and how many came."""

    def __init__(self, ros, typ, topic, qos=10):
        self.msg, self.n = None, 0
        self.sub = ros.node.create_subscription(typ, topic, self._cb, qos)
        self.ros = ros

    def _cb(self, msg):
        self.msg, self.n = msg, self.n + 1

    def close(self):
        self.ros.node.destroy_subscription(self.sub)


def stop_all(procs):
    return {k: p.stop() for k, p in procs.items()}


# -----------------------------------------------------------------------------------------
# one clock per robot
# -----------------------------------------------------------------------------------------
def test_each_robot_of_the_launch_file_has_its_own_clock(ros, tmp_path):
    """Two robots started as the launch file starts them (namespace:=robot1 / robot2, its
    defaults otherwise: lockstep, use_sim_time:=true, publish_clock:=true). robot1 is paused
    at about 0.3 s, robot2 runs on to about 1 s: each controller's clock (the stamp of the
    parameter event it sends when a parameter is set: rclpy stamps it with the node's clock)
    is its own robot's sim time, not the other's."""
    procs = {}
    node = ros.node
    try:
        for ns in ("robot1", "robot2"):
            for spec in launch_nodes(namespace=ns):
                assert spec["namespace"] == f"/{ns}"
                procs[f"{ns}_{spec['exec']}"] = NodeProcess(
                    spec["module"], str(tmp_path / f"{ns}.{spec['exec']}.log"), DOMAIN_ID,
                    ros_args=spec["ros_args"])
        stamps = {ns: Latest(ros, JointState, f"/{ns}/joint_states") for ns in ("robot1",
                                                                               "robot2")}

        def sim_time(ns):
            m = stamps[ns].msg
            return seconds(m.header.stamp) if m is not None else 0.0
        assert ros.spin_until(lambda: min(sim_time("robot1"), sim_time("robot2")) > 0.1,
                              START_TIMEOUT, procs=procs.values()), \
            "\n".join(p.log()[-1500:] for p in procs.values())
        # each robot publishes its own clock; nobody publishes /clock
        assert node.count_publishers("/robot1/clock") == 1
        assert node.count_publishers("/robot2/clock") == 1
        assert node.count_publishers("/clock") == 0
        # robot1 stops early, robot2 goes on
        assert ros.spin_until(lambda: sim_time("robot1") > 0.3, 30.0, procs=procs.values())
        assert ros.call(SetBool, "/robot1/sim_node/pause", SetBool.Request(data=True)).success
        ros.spin_for(0.2)
        t1 = sim_time("robot1")
        assert ros.spin_until(lambda: sim_time("robot2") > t1 + 0.7, 30.0, procs=procs.values())
        assert ros.call(SetBool, "/robot2/sim_node/pause", SetBool.Request(data=True)).success
        ros.spin_for(0.3)
        robot = {ns: sim_time(ns) for ns in ("robot1", "robot2")}
        assert robot["robot1"] == pytest.approx(t1, abs=1e-9)   # paused: it stayed
        # each controller's clock now: set a parameter (to its value) and read the event
        events = {}

        def on_event(msg):
            events.setdefault(msg.node, seconds(msg.stamp))
        sub = node.create_subscription(ParameterEvent, "/parameter_events", on_event, 10)
        for ns in ("robot1", "robot2"):
            req = SetParameters.Request(
                parameters=[Parameter("mode", value="stand").to_parameter_msg()])
            r = ros.call(SetParameters, f"/{ns}/controller_node/set_parameters", req)
            assert r.results[0].successful, r.results[0].reason
        names = ("/robot1/controller_node", "/robot2/controller_node")
        assert ros.spin_until(lambda: all(n in events for n in names), 10.0), events
        node.destroy_subscription(sub)
    finally:
        codes = stop_all(procs)
    assert all(c == 0 for c in codes.values()), codes
    print(f"sim time: {robot}; controllers' clocks: {events}")
    # (a lost best-effort clock message would leave a clock a step or two behind)
    assert robot["robot2"] - robot["robot1"] > 0.6, robot
    for ns in ("robot1", "robot2"):
        assert events[f"/{ns}/controller_node"] == pytest.approx(robot[ns], abs=0.01), \
            (events, robot)


# -----------------------------------------------------------------------------------------
# the README's controller, as written
# -----------------------------------------------------------------------------------------
def readme_controller():
    """The python block of README.md's "Write your own controller" section (the first of
    doc/controllers.md too)."""
    blocks = readme_controller_blocks()
    assert len(blocks) == 1 and blocks[0] == controllers_page_blocks()[0], blocks
    return blocks[0]


def test_readme_controller_is_at_most_20_lines():
    assert readme_controller().count("\n") <= 20


def test_readme_controller_keeps_the_robot_standing(ros, tmp_path):
    """The example as the README says to run it: beside `sim_node --ros-args -p
    mode:=lockstep`, as a script with no arguments. 1.5 s of sim time: the base stays at its
    standing height (within a few mm), every state answered. (It settles within 0.5 s: the
    base's range over 0.25 s is 0.7 mm at 0.5 s, 0.04 mm at 1.25 s, so 1.5 s tells a settled
    robot from a swaying one as well as the 3 s run before did.)"""
    t, z, summary = run_beside_sim_node(ros, tmp_path, readme_controller(), DOMAIN_ID, 1.5)
    z = z[t > 0]
    sag = STARLETH_STANDING_HEIGHT - min(z)
    print(f"README controller: {len(z)} states, base height {min(z):.4f} to {max(z):.4f} m")
    assert 0.0 <= sag < 0.01, sag                 # holds itself up: gives a few mm at most
    assert max(z[-100:]) - min(z[-100:]) < 0.001  # settled: at rest over the last 0.25 s
    s = summary
    assert s["lockstep_timeouts"] == 0 and s["stale_commands"] == 0, s
