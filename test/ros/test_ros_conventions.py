"""ROS 2 conventions (issue #17): relative names (robots in namespaces), any start order of
sim and controller, the launch file, split recordings, discovery kept on this host.

Nodes run as child processes on an isolated ROS_DOMAIN_ID; every wait is bounded and every
child is stopped in a finally."""
import os
import re
import signal
import time
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip("rclpy")

from geometry_msgs.msg import Twist
from launch_file import Substitutions, launch_nodes, launch_values
from rclpy.qos import QoSProfile, ReliabilityPolicy
from repo_root import ROOT
from ros_test_nodes import NodeProcess, RosTestNode
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_srvs.srv import SetBool

from starleth_sim.tools.analysis import run as analysis_run

DOMAIN_RANGE = (90, 9)        # first, span; test_sim_node: 50..89, controller tests 10..49
DOMAIN_ID = 90 + os.getpid() % 9    # conftest._free_ros_domain: a free one of the range
START_TIMEOUT = 120.0
PERIOD_NS = 2_500_000


def sim_process(tmp_path, tag, **params):
    params.setdefault("mode", "lockstep")
    params.setdefault("real_time_factor", 0.0)
    return NodeProcess("starleth_sim.ros.sim_node", str(tmp_path / f"{tag}.sim.log"),
                       DOMAIN_ID, **params)


def controller_process(tmp_path, tag, **params):
    return NodeProcess("starleth_controller.controller_node",
                       str(tmp_path / f"{tag}.controller.log"), DOMAIN_ID, **params)


def ns_process(module, log_path, ns, **params):
    """A node as a child process under namespace `ns`."""
    return NodeProcess(module, log_path, DOMAIN_ID, namespace=ns, **params)


@pytest.fixture(scope="module")
def ros():
    node = RosTestNode(DOMAIN_ID, "conventions_test")
    try:
        yield node
    finally:
        node.close()


class ClockWatch:
    def __init__(self, ros):
        self.t = None
        self.sub = ros.node.create_subscription(
            Clock, "/clock", self._cb, QoSProfile(depth=1,
                                                  reliability=ReliabilityPolicy.BEST_EFFORT))

    def _cb(self, msg):
        self.t = msg.clock.sec + msg.clock.nanosec * 1e-9


def _log_times(path, topic):
    """Log times [ns] of the messages on `topic` in an MCAP file."""
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        return [m.log_time for _, ch, m in make_reader(f).iter_messages(topics=[topic])]


def stop_all(*procs):
    codes = []
    for p in procs:
        if p is not None:
            codes.append(p.stop())
    return codes


# -----------------------------------------------------------------------------------------
# two robots in one domain
# -----------------------------------------------------------------------------------------
def test_two_namespaced_robots_trot_in_one_domain(ros, tmp_path):
    """sim_node + controller_node under /robot1 and under /robot2, one ROS domain, both in
    lockstep and trotting; each controller answers only its own simulator (no stale or late
    command, one publisher per command topic); a bag per robot, read as one run each.
    (long: two robots' nodes started once, checked together)"""
    procs = {}
    try:
        for i, ns in enumerate(("/robot1", "/robot2")):
            tag = ns.strip("/")
            procs[tag + "_sim"] = ns_process(
                "starleth_sim.ros.sim_node", str(tmp_path / f"{tag}.sim.log"), ns,
                mode="lockstep", real_time_factor=0.0, record=str(tmp_path / f"{tag}.mcap"),
                publish_clock=(i == 0), start_paused=True)
            procs[tag + "_ctl"] = ns_process(
                "starleth_controller.controller_node", str(tmp_path / f"{tag}.ctl.log"), ns,
                mode="trot")
        node = ros.node

        def graph_ready():
            names = dict(node.get_topic_names_and_types())
            return node.count_publishers("/clock") >= 1 and all(
                f"/robot{i}/joint_commands" in names and
                node.count_publishers(f"/robot{i}/joint_commands") == 1 and
                node.count_subscribers(f"/robot{i}/joint_commands") == 1
                for i in (1, 2))
        assert ros.spin_until(graph_ready, START_TIMEOUT, procs=procs.values()), \
            "\n".join(p.log()[-2000:] for p in procs.values())
        # /clock comes from robot1's simulator only
        assert node.count_publishers("/clock") == 1
        assert "/joint_states" not in dict(node.get_topic_names_and_types())
        # let both trot forward for a while: each robot's sim time from its joint states'
        # stamps (the two lockstep loops run at their own pace on a shared machine, so
        # /clock, robot1's, says nothing of robot2's)
        cmd_vel = {i: node.create_publisher(Twist, f"/robot{i}/cmd_vel", 10) for i in (1, 2)}
        twist = Twist()
        twist.linear.x = 0.3
        clock = ClockWatch(ros)
        # the simulators start paused and go once their controllers hear /cmd_vel (in
        # lockstep at several times real time, a robot would otherwise be past its first
        # seconds before this node's publishers match)
        assert ros.spin_until(lambda: all(p.get_subscription_count() == 1
                                          for p in cmd_vel.values()), START_TIMEOUT,
                              procs=procs.values())
        for i in (1, 2):
            r = ros.call(SetBool, f"/robot{i}/sim_node/pause", SetBool.Request(data=False))
            assert r.success and "running" in r.message, r.message
        sim_time = {1: 0.0, 2: 0.0}
        best_effort = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
        stamp_subs = [node.create_subscription(
            JointState, f"/robot{i}/joint_states",
            lambda m, i=i: sim_time.__setitem__(i, m.header.stamp.sec
                                                + m.header.stamp.nanosec * 1e-9), best_effort)
            for i in (1, 2)]

        def trotted():
            for pub in cmd_vel.values():
                pub.publish(twist)
            return min(sim_time.values()) > 2.5
        assert ros.spin_until(trotted, 180, procs=procs.values(), step=0.05), \
            f"the robots did not both reach t = 2.5 s: {sim_time}"
        # robot1's /clock went along (its first message may come after the joint states:
        # the robots may pass 2.5 s before this node's subscriptions match)
        assert ros.spin_until(lambda: clock.t is not None and clock.t > 2.0, 10.0,
                              procs=procs.values()), clock.t
        for sub in stamp_subs:
            node.destroy_subscription(sub)
        for tag in ("robot1", "robot2"):
            r = ros.call(SetBool, f"/{tag}/sim_node/pause", SetBool.Request(data=True))
            assert r.success, r.message
    finally:
        codes = {k: p.stop() for k, p in procs.items()}
    assert all(c == 0 for c in codes.values()), codes
    for tag in ("robot1", "robot2"):
        summary = procs[tag + "_sim"].summary()
        assert summary["lockstep_timeouts"] == 0, summary
        assert summary["stale_commands"] == 0 and summary["late_commands"] == 0, summary
        assert summary["steps"] > 800, summary
        run = analysis_run.Run(str(tmp_path / f"{tag}.mcap"), tag)
        assert run.namespace == f"/{tag}" and not run.missing, (run.namespace, run.missing)
        assert set(run.counts) >= {f"/{tag}/joint_states", f"/{tag}/joint_commands"}
        assert not any(t.startswith("/robot1" if tag == "robot2" else "/robot2")
                       for t in run.counts)
        # both trotted: the base moved forward in its own bag
        base = run.series("base")["data"]
        assert base[-1, 0] - base[0, 0] > 0.2, tag
    # /clock only in robot1's bag
    assert "/clock" in analysis_run.Run(str(tmp_path / "robot1.mcap"), "1").counts
    assert "/clock" not in analysis_run.Run(str(tmp_path / "robot2.mcap"), "2").counts


# -----------------------------------------------------------------------------------------
# any start order
# -----------------------------------------------------------------------------------------
def test_controller_started_3_s_after_sim_node_gets_going_without_reset(ros, tmp_path):
    sim = ctl = None
    try:
        sim = sim_process(tmp_path, "late", record=str(tmp_path / "late.mcap"))
        clock = ClockWatch(ros)
        assert ros.spin_until(lambda: clock.t is not None, START_TIMEOUT, procs=[sim])
        ros.spin_for(3.0)
        assert clock.t == 0.0                      # waiting for its first command
        ctl = controller_process(tmp_path, "late")
        assert ros.spin_until(lambda: clock.t is not None and clock.t > 1.0, START_TIMEOUT,
                              procs=[sim, ctl]), sim.log()[-2000:] + ctl.log()[-2000:]
        assert ros.call(SetBool, "/sim_node/pause", SetBool.Request(data=True)).success
    finally:
        codes = stop_all(ctl, sim)
    assert codes == [0, 0]
    s = sim.summary()
    assert s["resets"] == 0 and s["lockstep_timeouts"] == 0, s
    run = analysis_run.Run(str(tmp_path / "late.mcap"), "late")
    js = run.series("joints")["t"]
    assert run.counts["/joint_commands"] >= len(js) - 1     # every state answered
    assert abs(js[0]) < 1e-12 and np.all(np.diff(js) > 0)   # from t = 0, no state twice


def test_controller_killed_and_restarted_mid_run_is_followed_without_reset(ros, tmp_path):
    """The controller dies (SIGKILL) while trotting; sim_node steps on its timeout policy
    (hold, 0.3 s per step); a new controller starts and the sim follows it at once (the
    current state is sent again to the new subscriber), no reset."""
    sim = ctl = ctl2 = None
    try:
        sim = sim_process(tmp_path, "restart", lockstep_timeout=0.3, timeout_policy="hold",
                          record=str(tmp_path / "restart.mcap"))
        ctl = controller_process(tmp_path, "restart1")
        clock = ClockWatch(ros)
        assert ros.spin_until(lambda: clock.t is not None and clock.t > 1.0, START_TIMEOUT,
                              procs=[sim, ctl])
        ctl.stop(signal.SIGKILL)
        t_kill = clock.t
        # a few steps on the timeout policy (0.3 s each; counted in steps, not wall time:
        # a loaded machine may run the sim slower)
        assert ros.spin_until(lambda: clock.t >= t_kill + 4.5 * PERIOD_NS * 1e-9, 30.0,
                              procs=[sim])
        t_dead = clock.t
        ctl2 = controller_process(tmp_path, "restart2")
        assert ros.spin_until(lambda: clock.t > t_dead + 2.0, START_TIMEOUT,
                              procs=[sim, ctl2]), sim.log()[-3000:]
        assert ros.call(SetBool, "/sim_node/pause", SetBool.Request(data=True)).success
    finally:
        codes = stop_all(ctl2, sim)
        if ctl is not None:
            ctl.stop()
    assert codes == [0, 0]
    s = sim.summary()
    assert s["resets"] == 0, s
    run = analysis_run.Run(str(tmp_path / "restart.mcap"), "restart")
    states = run.series("joints")["stamp"]
    # the recorder logs a command at the stamp of the state it answers
    answered = set(_log_times(tmp_path / "restart.mcap", "/joint_commands"))
    unanswered = [k for k, st in enumerate(states[:-1]) if int(st) not in answered]
    assert s["lockstep_timeouts"] == len(unanswered), s
    # while no controller ran: a run of consecutive steps taken on the timeout policy (a
    # loaded machine may add a single late answer elsewhere)
    runs = np.split(np.array(unanswered), np.flatnonzero(np.diff(unanswered) != 1) + 1)
    gap = max(runs, key=len)
    assert len(gap) >= 3, (unanswered, s, sim.log()[-3000:])
    after = len(states) - 1 - (gap[-1] + 1)
    assert after > 400                               # the new controller drove > 1 s ...
    late = sum(k > gap[-1] for k in unanswered)
    assert late <= 0.01 * after, unanswered          # ... answering (nearly) every state
    z = run.series("base")["data"][:, 2]
    assert z.min() > 0.35                            # held on its feet throughout


# -----------------------------------------------------------------------------------------
# the launch file
# -----------------------------------------------------------------------------------------
def _console_scripts():
    text = open(os.path.join(ROOT, "setup.py")).read()
    return dict(re.findall(r"'([\w-]+) = ([\w.]+):main'", text))


def _declared_parameters(executable):
    """{name: default} of the parameters a node declares (rclpy adds use_sim_time)."""
    if executable == "sim_node":
        from dataclasses import asdict

        from starleth_sim.ros.parameters import Settings
        params = asdict(Settings())
    else:
        from starleth_controller.node_parameters import PARAMETERS
        params = {p.name: p.default for p in PARAMETERS}
    params["use_sim_time"] = False
    return params


def _compatible(value, default):
    if isinstance(default, bool):
        return isinstance(value, bool)
    if isinstance(default, float):
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if isinstance(default, int):
        return isinstance(value, int) and not isinstance(value, bool)
    if isinstance(default, str):
        return isinstance(value, str) or value is None     # '' loads as None in launch
    return type(value) is type(default)


def test_launch_file_names_our_executables_and_declared_parameters():
    path = os.path.join(ROOT, "launch", "starleth.launch.xml")
    root = ET.parse(path).getroot()
    assert root.tag == "launch"
    args = {a.get("name"): a.get("default") for a in root.iter("arg")}
    assert {"physics", "mode", "record", "namespace", "use_sim_time"} <= set(args)
    scripts = _console_scripts()
    nodes = list(root.iter("node"))
    assert {n.get("exec") for n in nodes} == {"sim_node", "controller_node"}

    sub = Substitutions(launch_values(path), path).evaluate

    def value(text):
        # the substitutions with the arguments' defaults; launch then reads it as YAML
        text = sub(text)
        return yaml.safe_load(text) if text != "" else ""

    for n in nodes:
        assert n.get("pkg") == "starleth_sim" and n.get("exec") in scripts, n.attrib
        assert n.get("namespace") == "$(var namespace)"
        declared = _declared_parameters(n.get("exec"))
        for p in n.iter("param"):
            name = p.get("name")
            assert name in declared, f"{n.get('exec')} does not declare {name}"
            v = value(p.get("value"))
            assert _compatible(v, declared[name]), (name, v, declared[name])
    # every argument is used
    text = open(path).read()
    for a in args:
        assert f"$(var {a})" in text, a


def test_launch_file_prefixes_the_frames_with_the_namespace():
    """frame_prefix's default ($(eval ...), evaluated as launch does) is robot_state_
    publisher's convention, namespace_frame_prefix: robot1/ for robot1 or /robot1/, none at
    the root; it goes to sim_node's tf_frame_prefix, and frame_prefix:=... overrides it."""
    from starleth_sim.ros.parameters import namespace_frame_prefix

    def sim_node_prefix(**args):
        spec = next(n for n in launch_nodes(**args) if n["exec"] == "sim_node")
        args = spec["ros_args"]
        return next(a.split(":=", 1)[1] for a in args if a.startswith("tf_frame_prefix:="))
    for ns in ("", "/", "robot1", "/robot1/", "fleet/robot_7"):
        want = namespace_frame_prefix(ns)
        assert launch_values(namespace=ns)["frame_prefix"] == want, ns
        assert sim_node_prefix(namespace=ns) == (want or "''"), ns
    assert namespace_frame_prefix("/fleet/robot_7") == "fleet/robot_7/"
    assert sim_node_prefix(namespace="robot1", frame_prefix="r1_") == "r1_"


# -----------------------------------------------------------------------------------------
# split recordings
# -----------------------------------------------------------------------------------------
def test_sim_node_splits_long_recordings_into_a_bag_directory(ros, tmp_path):
    """record_max_duration: a rosbag2 bag directory of numbered files, each complete on its
    own, a metadata.yaml listing them, and starleth-analyze reads it as one run."""
    from starleth_sim.tools.bench.controllers import EchoController
    bag = tmp_path / "split"
    sim = None
    ctl = EchoController(ros.node)
    try:
        sim = sim_process(tmp_path, "split", record=str(bag), record_max_duration=1.0)
        clock = ClockWatch(ros)
        assert ros.spin_until(lambda: clock.t is not None and clock.t > 3.2, START_TIMEOUT,
                              procs=[sim]), sim.log()[-2000:]
        assert ros.call(SetBool, "/sim_node/pause", SetBool.Request(data=True)).success
    finally:
        ctl.close()
        code = sim.stop() if sim is not None else None
    assert code == 0
    files = sorted(p.name for p in bag.glob("*.mcap"))
    assert len(files) >= 4, files
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["relative_file_paths"] == [f"split_{i}.mcap" for i in range(len(files))]
    assert meta["storage_identifier"] == "mcap"
    total = 0
    for f in meta["files"]:
        one = analysis_run.Run(str(bag / f["path"]), f["path"])      # complete on its own
        assert not one.truncated and one.urdf and "starleth_sim" in one.metadata
        assert one.messages == f["message_count"]
        total += f["message_count"]
        assert f["duration"]["nanoseconds"] < 1e9
    assert total == meta["message_count"]
    run = analysis_run.Run(str(bag), "split")
    js = run.series("joints")["t"]
    assert np.allclose(np.diff(js), PERIOD_NS * 1e-9)          # one run, no step missing
    assert js[-1] - js[0] > 3.1


# -----------------------------------------------------------------------------------------
# discovery on this host
# -----------------------------------------------------------------------------------------
def _environ(pid, timeout=10.0):
    """The environment of process pid. Read while the child is still in execve it can be
    empty (the new image's environment not set up yet: a KeyError in CI once), so an empty
    one is read again until the timeout."""
    t_end = time.monotonic() + timeout
    while True:
        with open(f"/proc/{pid}/environ", "rb") as f:
            env = dict(kv.split("=", 1) for kv in f.read().decode().split("\0") if "=" in kv)
        if env or time.monotonic() > t_end:
            return env
        time.sleep(0.02)


def test_children_discover_on_this_host_only_unless_the_user_chose(tmp_path, monkeypatch):
    """The demo's, the benchmark's and the tests' child processes run with
    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST unless the user set a range."""
    from starleth_sim.tools.common.discovery import local_discovery_env
    from starleth_sim.tools.demo.demo import NodeProcess as DemoNodeProcess
    assert local_discovery_env({})["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert local_discovery_env({"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"})[
        "ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET"
    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"   # this test process
    for value, expect in (("", "LOCALHOST"), ("SUBNET", "SUBNET")):
        monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", value)
        procs = [DemoNodeProcess("sim_node", "starleth_sim.ros.sim_node",
                                 {"mode": "lockstep"}, DOMAIN_ID,
                                 str(tmp_path / f"demo_child{expect}.log")),
                 sim_process(tmp_path, f"test_child{expect}")]
        try:
            for p in procs:
                assert _environ(p.proc.pid)["ROS_AUTOMATIC_DISCOVERY_RANGE"] == expect
        finally:
            for p in procs:
                p.stop()
