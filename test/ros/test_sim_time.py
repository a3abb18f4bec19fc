"""Sim time and several robots as users meet them: each robot of the launch file has its own
clock (two namespaced robots in lockstep, their controllers with use_sim_time:=true, started
with the `--ros-args` the launch file gives them) and its own TF tree (its frames prefixed
with its namespace, `world` shared), and the tools read their bags (starleth-view draws both
in one scene, starleth-layout's layout names what they recorded, starleth-analyze and
starleth-replay read them); and the README's "Write your own controller" example, run as
written, keeps the robot standing. (Realtime mode's start: test_realtime_start.)

Nodes run as child processes on an isolated ROS_DOMAIN_ID; every wait is bounded and every
child is stopped in a finally."""
import json
import os
import re
import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin
import pytest

rclpy = pytest.importorskip("rclpy")

from controller_examples import (
    controllers_page_blocks,
    readme_controller_blocks,
    run_beside_sim_node,
)
from launch_file import launch_nodes
from layout_checks import check_layout
from mcap_ros2.reader import read_ros2_messages
from rcl_interfaces.msg import ParameterEvent
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_test_nodes import NodeProcess, RosTestNode
from sensor_msgs.msg import JointState
from std_srvs.srv import SetBool
from tf_trees import tf_tree, world_poses

from starleth_sim.robots import load_robot
from starleth_sim.tools.analysis import analysis
from starleth_sim.tools.replay import replay
from starleth_sim.tools.view import foxglove_layout, view

STARLETH_STANDING_HEIGHT = load_robot("starleth").standing_height

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
# two robots of the launch file: one clock, one TF tree each
# -----------------------------------------------------------------------------------------
ROBOTS = ("robot1", "robot2")
#: robot2 stands this far to the left of robot1 (the launch file's initial_state)
ROBOT2_Y = 1.0


@pytest.fixture(scope="module")
def two_robots(ros, tmp_path_factory):
    """Two robots started as the launch file starts them (namespace:=robot1 / robot2,
    record:=<tmp>/robotN.mcap, robot2 with initial_state ROBOT2_Y to the left; the file's
    defaults otherwise: lockstep, use_sim_time:=true, publish_clock:=true, frame_prefix
    from the namespace). robot1 is paused at about 0.3 s, robot2 runs on to about 1 s; each
    controller's clock is read (the stamp of the parameter event it sends when a parameter
    is set: rclpy stamps it with the node's clock). Then both are stopped (the bags
    closed). Returns what was seen: sim times, clocks, publisher counts, bags, and the child
    frames on the live /tf (None without tf2_msgs)."""
    tmp = tmp_path_factory.mktemp("two_robots")
    procs, seen = {}, {"bags": {ns: str(tmp / f"{ns}.mcap") for ns in ROBOTS}}
    node = ros.node
    live_tf = _LiveTf(ros)
    try:
        for ns in ROBOTS:
            args = {"namespace": ns, "record": seen["bags"][ns]}
            if ns == "robot2":
                args["initial_state"] = (f"'{{base_position: [0, {ROBOT2_Y}, "
                                         f"{STARLETH_STANDING_HEIGHT}]}}'")
            for spec in launch_nodes(**args):
                assert spec["namespace"] == f"/{ns}"
                procs[f"{ns}_{spec['exec']}"] = NodeProcess(
                    spec["module"], str(tmp / f"{ns}.{spec['exec']}.log"), DOMAIN_ID,
                    ros_args=spec["ros_args"])
        stamps = {ns: Latest(ros, JointState, f"/{ns}/joint_states") for ns in ROBOTS}

        def sim_time(ns):
            m = stamps[ns].msg
            return seconds(m.header.stamp) if m is not None else 0.0
        assert ros.spin_until(lambda: min(sim_time("robot1"), sim_time("robot2")) > 0.1,
                              START_TIMEOUT, procs=procs.values()), \
            "\n".join(p.log()[-1500:] for p in procs.values())
        seen["clock_publishers"] = {t: node.count_publishers(t) for t in
                                    ("/robot1/clock", "/robot2/clock", "/clock")}
        # robot1 stops early (once its /tf has reached this node: DDS discovery can take
        # longer than its 0.3 s on a loaded machine), robot2 goes on
        assert ros.spin_until(lambda: sim_time("robot1") > 0.3 and live_tf.has("robot1/"),
                              30.0, procs=procs.values())
        assert ros.call(SetBool, "/robot1/sim_node/pause", SetBool.Request(data=True)).success
        ros.spin_for(0.2)
        t1 = sim_time("robot1")
        assert ros.spin_until(lambda: sim_time("robot2") > t1 + 0.7, 30.0, procs=procs.values())
        assert ros.call(SetBool, "/robot2/sim_node/pause", SetBool.Request(data=True)).success
        ros.spin_for(0.3)
        seen["t_pause1"] = t1
        seen["robot"] = {ns: sim_time(ns) for ns in ROBOTS}
        seen["events"] = _controller_clocks(ros)
    finally:
        codes = stop_all(procs)
        live_tf.close()
    assert all(c == 0 for c in codes.values()), codes
    seen["live_tf"] = live_tf.children
    return seen


class _LiveTf:
    """The child frames seen on /tf (children None: tf2_msgs is not installed)."""

    def __init__(self, ros):
        self.ros, self.sub, self.children = ros, None, None
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:
            print("tf2_msgs is not installed: the live /tf is not checked (the bags' is)")
            return
        self.children = set()
        self.sub = ros.node.create_subscription(
            TFMessage, "/tf", lambda m: self.children.update(
                t.child_frame_id for t in m.transforms), 100)

    def has(self, prefix):
        """Whether a child frame starting with `prefix` came (True without tf2_msgs)."""
        return self.children is None or any(c.startswith(prefix) for c in self.children)

    def close(self):
        if self.sub is not None:
            self.ros.node.destroy_subscription(self.sub)


def _controller_clocks(ros):
    """{controller node: its clock now}: set a parameter (to its value) and read the
    parameter event it sends."""
    events = {}

    def on_event(msg):
        events.setdefault(msg.node, seconds(msg.stamp))
    sub = ros.node.create_subscription(ParameterEvent, "/parameter_events", on_event, 10)
    for ns in ROBOTS:
        req = SetParameters.Request(
            parameters=[Parameter("mode", value="stand").to_parameter_msg()])
        r = ros.call(SetParameters, f"/{ns}/controller_node/set_parameters", req)
        assert r.results[0].successful, r.results[0].reason
    names = [f"/{ns}/controller_node" for ns in ROBOTS]
    assert ros.spin_until(lambda: all(n in events for n in names), 10.0), events
    ros.node.destroy_subscription(sub)
    return events


def test_each_robot_of_the_launch_file_has_its_own_clock(two_robots):
    """Each robot publishes its own clock and nobody /clock; robot1, paused at about 0.3 s,
    stayed there while robot2 ran on; each controller's clock is its own robot's sim time,
    not the other's."""
    seen = two_robots
    robot, events = seen["robot"], seen["events"]
    print(f"sim time: {robot}; controllers' clocks: {events}")
    assert seen["clock_publishers"] == {"/robot1/clock": 1, "/robot2/clock": 1, "/clock": 0}
    assert robot["robot1"] == pytest.approx(seen["t_pause1"], abs=1e-9)   # paused: it stayed
    # (a lost best-effort clock message would leave a clock a step or two behind)
    assert robot["robot2"] - robot["robot1"] > 0.6, robot
    for ns in ROBOTS:
        assert events[f"/{ns}/controller_node"] == pytest.approx(robot[ns], abs=0.01), \
            (events, robot)


def bag_messages(path):
    """{topic: [mcap_ros2 decoded message]} of a bag."""
    out = {}
    for m in read_ros2_messages(path):
        out.setdefault(m.channel.topic, []).append(m)
    return out


def test_each_robot_has_its_own_tf_tree(two_robots):
    """The launch file prefixes each robot's frames with its namespace: every child frame
    on /tf of the two robots is distinct (robot1/..., robot2/...), both trees hang from the
    one shared `world`, and every frame a robot's messages name (odometry, IMU, wrenches,
    markers) is in its tree; the live /tf too where tf2_msgs is installed."""
    trees, moving = {}, set()
    for ns, path in two_robots["bags"].items():
        msgs = bag_messages(path)
        parent = trees[ns] = tf_tree(msgs)
        urdf = msgs[f"/{ns}/robot_description"][0].ros_msg.data
        links = {lnk.get("name") for lnk in ET.fromstring(urdf).findall("link")}
        assert set(parent) == {f"{ns}/{lnk}" for lnk in links}, sorted(parent)
        assert [c for c, p in parent.items() if not p.startswith(f"{ns}/")] == [f"{ns}/base"]
        assert parent[f"{ns}/base"] == "world"
        frames = set(parent) | {"world"}
        odom = msgs[f"/{ns}/starleth/base_state"][-1].ros_msg
        assert (odom.header.frame_id, odom.child_frame_id) == ("world", f"{ns}/base")
        named = {msgs[f"/{ns}/starleth/imu"][-1].ros_msg.header.frame_id}
        named |= {msgs[f"/{ns}/starleth/{leg}_foot/wrench"][-1].ros_msg.header.frame_id
                  for leg in ("LF", "RF", "LH", "RH")}
        named |= {mk.header.frame_id for m in msgs[f"/{ns}/starleth/contact_markers"][-5:]
                  for mk in m.ros_msg.markers}
        assert named <= frames, named - frames
        moving |= {t.child_frame_id for m in msgs["/tf"] for t in m.ros_msg.transforms}
    assert not set(trees["robot1"]) & set(trees["robot2"])
    live = two_robots["live_tf"]
    print(f"robot1's tree: {len(trees['robot1'])} frames, robot2's: {len(trees['robot2'])}; "
          f"live /tf: {'not checked (no tf2_msgs)' if live is None else sorted(live)}")
    if live is not None:                      # both robots' moving frames, apart
        assert live == moving, live ^ moving


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


def page_data(path):
    """The replay data embedded in a starleth-view page."""
    text = open(path, encoding="utf-8").read()
    m = re.search(r'<script type="application/json" id="replay-data">(.*?)</script>', text, re.S)
    return json.loads(m.group(1))


def tf_at(msgs, stamp_ns):
    """{frame: world pose} from a bag's /tf message at stamp_ns and its /tf_static, or None
    where no /tf message has that stamp."""
    for m in msgs["/tf"]:
        s = m.ros_msg.transforms[0].header.stamp
        if s.sec * 10 ** 9 + s.nanosec == stamp_ns:
            return world_poses(list(m.ros_msg.transforms)
                               + list(msgs["/tf_static"][0].ros_msg.transforms))
    return None


def test_starleth_view_draws_both_robots_side_by_side(two_robots, tmp_path, capsys):
    """starleth-view robot1.mcap robot2.mcap: one page with both robots, each body under its
    frame as on /tf (robot1/base, robot2/LF_SHANK, ...: every one in its bag's TF tree), where
    that bag's /tf puts it at the same stamp (the page: Pinocchio of the recorded joint
    states and base state; 0.1 mm, quaternions 1e-4: the page's rounding); robot2 stands
    ROBOT2_Y to the left of robot1."""
    bags = two_robots["bags"]
    out = tmp_path / "both.html"
    assert view.main([bags["robot1"], bags["robot2"], "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "of 2 robots (robot1/, robot2/)" in printed, printed
    data = page_data(out)
    assert [r["name"] for r in data["robots"]] == ["robot1/", "robot2/"]
    assert [r["namespace"] for r in data["robots"]] == ["/robot1", "/robot2"]
    checked = 0
    for robot in data["robots"]:
        ns = robot["namespace"].strip("/")
        msgs = bag_messages(bags[ns])
        tree = tf_tree(msgs)
        assert set(robot["tf_frames"]) <= set(tree) and len(robot["tf_frames"]) == 13
        assert all(f.startswith(f"{ns}/") for f in robot["tf_frames"])
        poses = np.array(robot["poses"]).reshape(data["frames"], -1, 7)
        for k, t in enumerate(data["t"]):
            world = tf_at(msgs, data["t0_ns"] + round(t * 1e9))
            if world is None:         # (robot1 paused: no /tf of its own at later frames)
                continue
            for b, frame in enumerate(robot["tf_frames"]):
                M = world[frame]
                assert np.abs(poses[k, b, :3] - M.translation).max() <= 0.5e-4 + 1e-9
                quat = pin.Quaternion(M.rotation).coeffs()
                assert min(np.abs(poses[k, b, 3:] - quat).max(),
                           np.abs(poses[k, b, 3:] + quat).max()) <= 0.5e-4 + 1e-9
            checked += 1
        trunk_y = poses[:, robot["trunk"], 1]
        assert np.abs(trunk_y - (ROBOT2_Y if ns == "robot2" else 0.0)).max() < 0.02, ns
    assert checked >= 50 + 15           # robot2's frames to ~1 s, robot1's to ~0.3 s
    print(f"starleth-view: {data['frames']} frames, {checked} robot frames checked against "
          "the recorded /tf")


def test_foxglove_layout_for_the_two_robots(two_robots, tmp_path):
    """starleth-layout robot1 robot2: every topic of its 3D panel and plots is in the
    robots' bags, each robot's URDF layer reads its robot_description with its frame prefix
    (robot1/base, robot2/base on /tf), the camera follows robot1/base; the plots have each
    path once per robot."""
    out = tmp_path / "two_robots.json"
    assert foxglove_layout.main(["robot1", "robot2", "-o", str(out)]) == 0
    layout = json.loads(out.read_text())
    msgs, frames = {}, set()
    for path in two_robots["bags"].values():
        m = bag_messages(path)
        frames |= set(tf_tree(m))
        msgs.update({t: v for t, v in m.items() if t not in ("/tf", "/tf_static")})
    topics, layers, n_paths = check_layout(layout, msgs, frames)
    assert sorted(topics) == [f"/{ns}/{t}" for ns in ROBOTS
                              for t in ("starleth/contact_markers", "terrain")]
    assert [(x["topic"], x["framePrefix"]) for x in layers] == \
        [("/robot1/robot_description", "robot1/"), ("/robot2/robot_description", "robot2/")]
    assert layout["configById"]["3D!starleth"]["followTf"] == "robot1/base"
    assert n_paths == 2 * 5


def test_analyze_and_replay_read_the_namespaced_prefixed_bags(two_robots, tmp_path, capsys):
    """starleth-analyze finds each robot's topics under its namespace and its base frame
    (robot2/base: the twist in the child frame, REP 105); starleth-replay re-simulates
    robot1's bag bit for bit."""
    bags = two_robots["bags"]
    out = tmp_path / "analysis.json"
    assert analysis.main([bags["robot1"], bags["robot2"], "--no-plots", "--json",
                          str(out)]) == 0
    runs = json.loads(out.read_text())["runs"]
    for ns, run in zip(ROBOTS, runs, strict=True):
        base = run["base"]
        assert base["frames"] == ["world", f"{ns}/base"] and base["twist_frame"] == "child"
        assert base["height_mean"] == pytest.approx(STARLETH_STANDING_HEIGHT, abs=0.01)
    assert replay.main([bags["robot1"]]) == 0
    assert "bit-identical: all" in capsys.readouterr().out
