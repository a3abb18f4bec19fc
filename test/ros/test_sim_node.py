"""Integration tests of sim_node: the node runs as a separate process
(`python -m starleth_sim.ros.sim_node --ros-args -p ...`) on an isolated ROS_DOMAIN_ID and
is driven from a test node in this process. Every child process is stopped in a fixture
teardown or a finally; every wait is bounded."""
import gc
import itertools
import json
import os
import signal
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("rosbags")

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import WrenchStamped
from nav_msgs.msg import Odometry
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from ros_test_nodes import NodeProcess, RosTestNode
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import SetBool, Trigger

from starleth_sim.tools.bench.controllers import EchoController

# one ROS domain per test module and process (other modules use other ranges)
DOMAIN_RANGE = (50, 40)       # first, span
DOMAIN_ID = 50 + os.getpid() % 40   # conftest._free_ros_domain: a free one of the range
START_TIMEOUT = 120.0     # of silence: a node's compile lines restart it (ros_test_nodes)
PERIOD_NS = 2_500_000
FEET = ("LF_foot", "RF_foot", "LH_foot", "RH_foot")
STATE_TOPICS = {
    "/clock": "rosgraph_msgs/msg/Clock",
    "/joint_states": "sensor_msgs/msg/JointState",
    **{f"/starleth/{f}/wrench": "geometry_msgs/msg/WrenchStamped" for f in FEET},
    "/starleth/base_state": "nav_msgs/msg/Odometry",
    "/starleth/imu": "sensor_msgs/msg/Imu",
    "/starleth/solver": "diagnostic_msgs/msg/DiagnosticArray",
}
INPUT_TOPICS = {
    "/joint_group_effort_controller/commands": "std_msgs/msg/Float64MultiArray",
    "/joint_commands": "sensor_msgs/msg/JointState",
    "/sim_node/wrench": "geometry_msgs/msg/WrenchStamped",
    "/sim_node/wrench/persistent": "geometry_msgs/msg/WrenchStamped",
}
ALL_TOPICS = {**STATE_TOPICS, "/robot_description": "std_msgs/msg/String", **INPUT_TOPICS}


# -----------------------------------------------------------------------------------------
# helpers
# -----------------------------------------------------------------------------------------
def SimProcess(log_path, **params):
    """sim_node as a child process on DOMAIN_ID; log in a file; always stopped by stop()."""
    return NodeProcess("starleth_sim.ros.sim_node", log_path, DOMAIN_ID, **params)


class Collector:
    """Keeps every message of a topic with its receive time."""

    def __init__(self, ros, typ, topic, qos=None):
        self.msgs, self.times = [], []
        self.sub = ros.node.create_subscription(typ, topic, self._cb, qos or QoSProfile(depth=100))
        self.ros = ros

    def _cb(self, msg):
        self.msgs.append(msg)
        self.times.append(time.monotonic())

    def close(self):
        self.ros.node.destroy_subscription(self.sub)


def stamp_ns(msg):
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


class DiagWatcher:
    """Latest values of the 'starleth_sim: interface' diagnostic status."""

    def __init__(self, ros):
        self.values = {}
        self.sub = ros.node.create_subscription(DiagnosticArray, "/starleth/solver", self._cb,
                                                QoSProfile(depth=50))

    def _cb(self, msg):
        for st in msg.status:
            if st.name == "starleth_sim: interface":
                self.values = {kv.key: kv.value for kv in st.values}

    def get(self, key, default=0):
        try:
            return int(self.values.get(key, default))
        except ValueError:
            return default


@pytest.fixture(scope="module")
def ros():
    r = RosTestNode(DOMAIN_ID, "sim_node_test", events=True)
    yield r
    r.close()


def read_mcap(path):
    """{topic: [(log_time, msg)]}, {topic: connection} with rosbags (an independent reader)."""
    from pathlib import Path

    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
    out, conns = {}, {}
    with AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        for c in reader.connections:
            conns[c.topic] = c
        for c, t, raw in reader.messages():
            out.setdefault(c.topic, []).append((t, reader.deserialize(raw, c.msgtype)))
    return out, conns


FEET_ORDER = ("LF", "RF", "LH", "RH")      # the public joint order


def total_mass():
    from starleth_sim.robots import starleth_description
    return starleth_description().total_mass


# -----------------------------------------------------------------------------------------
# realtime node: topics, rate, bad input, pause/step/reset, recording + SIGINT
# -----------------------------------------------------------------------------------------
class RealtimeRun:
    def __init__(self, ros, tmp):
        self.mcap = str(tmp / "realtime.mcap")
        self.ros = ros
        self.ctl = EchoController(ros.node)    # keeps the robot standing
        # started paused: the controller connects and sees state 0 (its PD reference, the
        # standing posture) before the robot moves
        self.sim = SimProcess(tmp / "realtime.log", mode="realtime", real_time_factor=1.0,
                              record=self.mcap, start_paused=True)
        self.t_start = time.monotonic()
        #: messages the tests published per input topic (what the recording must hold)
        self.sent = {topic: 0 for topic in INPUT_TOPICS}


@pytest.fixture(scope="class")
def rt(ros, tmp_path_factory):
    run = RealtimeRun(ros, tmp_path_factory.mktemp("realtime"))
    try:
        ok = ros.spin_until(lambda: len(run.ctl.stamps) > 0 or not run.sim.alive(), START_TIMEOUT)
        assert ok and run.sim.alive(), "sim_node did not start:\n" + run.sim.log()
        assert run.ctl.stamps[0] == 0
        assert ros.call(SetBool, "/sim_node/pause", SetBool.Request(data=False)).success
        run.t_start = time.monotonic()
        yield run
    finally:
        run.sim.stop()
        run.ctl.close()


@pytest.mark.serial   # a realtime node: its rate and wall-clock timing
class TestRealtime:
    """One realtime node for these tests, in order: graph, rate, bad input, services, and
    finally SIGINT and the recording it leaves."""

    @pytest.mark.usefixtures("rt")
    def test_topics_types_and_services(self, ros):
        node = ros.node

        def graph_ok():
            have = dict(node.get_topic_names_and_types())
            if not all(t in have and typ in have[t] for t, typ in ALL_TOPICS.items()):
                return False
            pubs = all(any(i.node_name == "sim_node"
                               for i in node.get_publishers_info_by_topic(t))
                       for t in list(STATE_TOPICS) + ["/robot_description"])
            subs = all(any(i.node_name == "sim_node"
                               for i in node.get_subscriptions_info_by_topic(t))
                       for t in INPUT_TOPICS)
            services = dict(node.get_service_names_and_types())
            srv = (services.get("/sim_node/reset") == ["std_srvs/srv/Trigger"]
                   and services.get("/sim_node/pause") == ["std_srvs/srv/SetBool"]
                   and services.get("/sim_node/step") == ["std_srvs/srv/Trigger"])
            return pubs and subs and srv

        assert ros.spin_until(graph_ok, 30), (dict(node.get_topic_names_and_types()),
                                              dict(node.get_service_names_and_types()))

        # one message of every state topic, with the documented frames and physics
        best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        cols = {"/clock": Collector(ros, Clock, "/clock", best_effort),
                "/robot_description": Collector(ros, String, "/robot_description", latched),
                "/starleth/base_state": Collector(ros, Odometry, "/starleth/base_state"),
                "/starleth/imu": Collector(ros, Imu, "/starleth/imu"),
                "/starleth/solver": Collector(ros, DiagnosticArray, "/starleth/solver")}
        for f in FEET:
            cols[f] = Collector(ros, WrenchStamped, f"/starleth/{f}/wrench")
        try:
            assert ros.spin_until(lambda: all(len(c.msgs) >= 5 for c in cols.values()
                                              if c is not cols["/robot_description"])
                                  and cols["/robot_description"].msgs, 20)
            assert "<robot" in cols["/robot_description"].msgs[0].data
            assert cols["/clock"].msgs[-1].clock.sec >= 0
            odom = cols["/starleth/base_state"].msgs[-1]
            assert odom.header.frame_id == "world" and odom.child_frame_id == "base"
            assert cols["/starleth/imu"].msgs[-1].header.frame_id == "base"
            for f in FEET:
                assert cols[f].msgs[-1].header.frame_id == "world"
            # (the physics of these topics is checked in lockstep, where the controller's
            # delay does not depend on how busy this test process is)
            def names():
                return {st.name for m in cols["/starleth/solver"].msgs for st in m.status}

            assert ros.spin_until(lambda: {"starleth_sim: solver", "starleth_sim: interface"}
                                  <= names(), 5), names()
        finally:
            for c in cols.values():
                c.close()


    @pytest.mark.usefixtures("rt")
    def test_realtime_rate_400hz(self, ros):
        # a deep queue and no garbage collection in this (test) process during the window:
        # a pause here must not lose messages that the node did publish
        col = Collector(ros, JointState, "/joint_states", QoSProfile(depth=4000))
        try:
            ros.spin_for(0.5)
            gc.collect()
            gc.disable()
            ros.spin_for(0.3)      # drain what queued up here during the collection
            n0, t0 = len(col.msgs), time.monotonic()
            ros.spin_for(5.0)
            t1 = time.monotonic()
            gc.enable()
            msgs = col.msgs[n0:]
            rate = len(msgs) / (t1 - t0)
            stamps = np.array([stamp_ns(m) for m in msgs])
            sim_rate = (stamps[-1] - stamps[0]) * 1e-9 / (col.times[-1] - col.times[n0])
        finally:
            gc.enable()
            col.close()
        assert abs(rate / 400.0 - 1.0) < 0.02, f"{rate:.1f} Hz (sim/wall {sim_rate:.4f})"
        assert abs(sim_rate - 1.0) < 0.02, f"sim/wall {sim_rate:.4f}"
        assert np.all(np.diff(stamps) == PERIOD_NS)


    def test_bad_input_is_rejected_and_node_keeps_publishing(self, ros, rt):
        """Each kind of bad input (commands, wrenches, parameters) is rejected with its logged
        reason and counted, and the node keeps publishing (long: the class's one realtime node
        fed the inputs in turn; split, each part would wait for the node again)."""
        node = ros.node
        diag = DiagWatcher(ros)
        col = Collector(ros, JointState, "/joint_states")
        eff = node.create_publisher(Float64MultiArray,
                                    "/joint_group_effort_controller/commands", 10)
        cmd = node.create_publisher(JointState, "/joint_commands", 10)
        push = node.create_publisher(WrenchStamped, "/sim_node/wrench", 10)
        try:
            assert ros.spin_until(lambda: eff.get_subscription_count()
                                  and push.get_subscription_count()
                                  and cmd.get_subscription_count(), 10)
            rt.ctl.reply = False
            ros.spin_for(0.1)
            eff.publish(Float64MultiArray(data=[1.5] * 12))
            rt.sent[eff.topic_name] += 1
            assert ros.spin_until(lambda: col.msgs and np.allclose(col.msgs[-1].effort, 1.5), 5)
            assert ros.spin_until(lambda: "commands_rejected" in diag.values, 5)
            rejected0 = diag.get("commands_rejected")
            n_bad = 0

            def send_until_logged(pub, msg, text):
                """Publish until the node has logged `text` (a message lost on a loaded
                machine is sent again: this test is about the rejection, not the DDS);
                text None: send once (its warning is throttled behind an earlier one)."""
                nonlocal n_bad
                n_bad += 1                   # (a retry only replaces a lost message)
                for _ in range(10):
                    pub.publish(msg)
                    rt.sent[pub.topic_name] += 1
                    if text is None:
                        ros.spin_for(0.02)
                        return
                    if ros.spin_until(lambda: text in rt.sim.log(), 0.5):
                        return
                raise AssertionError(f"the node never logged {text!r}")
            for data, text in (([1.0] * 11, "11 values, expected 12"),
                               ([float("nan")] + [0.0] * 11, "non-finite torque for LF_HAA"),
                               ([float("inf")] * 12, None)):
                send_until_logged(eff, Float64MultiArray(data=data), text)
            joints = [f"{leg}_{j}" for leg in FEET_ORDER for j in ("HAA", "HFE", "KFE")]
            for names, efforts, text in (
                    (["LF_HAA", "FOO"], [1.0, 2.0], "unknown joint name(s) 'FOO'"),
                    (joints[:-1], [1.0] * 11, "no effort for RH_KFE (a command names all "
                                              "12 joints"),
                    (joints, [1.0] * 11, "12 names but 11 efforts"),
                    (joints, [0.0, float("nan")] + [0.0] * 10, "non-finite effort for LF_HFE"),
                    (["LF_HFE", "LF_HFE"], [1.0, 1.0], "duplicate joint name(s) LF_HFE")):
                send_until_logged(cmd, JointState(name=names, effort=efforts), text)
            for _ in range(30):                                     # a flood: warnings throttled
                eff.publish(Float64MultiArray(data=[1.0] * 13))
                rt.sent[eff.topic_name] += 1
                n_bad += 1
            w = WrenchStamped()
            w.header.frame_id = "nope"
            w.wrench.force.z = 100.0
            push.publish(w)
            w2 = WrenchStamped()
            w2.header.frame_id = "base"
            w2.wrench.force.x = float("nan")
            push.publish(w2)
            rt.sent[push.topic_name] += 2
            n_before = len(col.msgs)
            ros.spin_for(1.0)
            assert rt.sim.alive()
            assert len(col.msgs) - n_before > 300                   # still publishing at 400 Hz
            # the last valid command is kept: applied as 1.5 N m, derated on a joint that
            # started the step beyond its velocity limit (10 rad/s) moving in the torque's
            # direction (to zero at 20 rad/s)
            for prev, m in itertools.pairwise(col.msgs[n_before - 1:]):
                v = np.array(prev.velocity)
                expect = np.where(v > 10.0, 1.5 * np.clip(2.0 - v / 10.0, 0.0, 1.0), 1.5)
                assert np.allclose(expect, m.effort), (m.effort, prev.velocity)
            assert all(np.all(np.isfinite(m.position)) for m in col.msgs[n_before:])
            # (the flood may overflow the depth-10 queues: at least one of it arrives)
            assert ros.spin_until(lambda: diag.get("commands_rejected") - rejected0 >= n_bad - 29
                                  and diag.get("wrenches_rejected") >= 2, 5), diag.values
            log = rt.sim.log()
            for text in ("11 values, expected 12", "non-finite torque for LF_HAA",
                         "unknown joint name(s) 'FOO'", "12 names but 11 efforts",
                         "no effort for RH_KFE", "non-finite effort for LF_HFE",
                         "duplicate joint name(s) LF_HFE",
                         "unknown link 'nope'", "force and torque must be finite"):
                assert text in log, text
            assert log.count("13 values, expected 12") <= 2        # throttled
        finally:
            rt.ctl.reply = True
            for p in (eff, cmd, push):
                node.destroy_publisher(p)
            col.close()
            node.destroy_subscription(diag.sub)


    def test_pause_step_reset(self, ros, rt):
        col = Collector(ros, JointState, "/joint_states")
        try:
            assert ros.spin_until(lambda: len(col.msgs) > 0, 5)   # subscribed and matched
            r = ros.call(SetBool, "/sim_node/pause", SetBool.Request(data=True))
            assert r.success
            ros.spin_for(0.2)
            n = len(col.msgs)
            last = stamp_ns(col.msgs[-1])
            ros.spin_for(0.3)
            assert len(col.msgs) == n                               # paused: nothing new
            for i in (1, 2):
                r = ros.call(Trigger, "/sim_node/step", Trigger.Request())
                assert r.success, r.message
                assert ros.spin_until(lambda i=i: len(col.msgs) == n + i, 5)
                assert stamp_ns(col.msgs[-1]) == last + i * PERIOD_NS
            r = ros.call(Trigger, "/sim_node/reset", Trigger.Request())
            assert r.success
            assert ros.spin_until(lambda: len(col.msgs) == n + 3, 5)
            m = col.msgs[-1]
            assert stamp_ns(m) == last + 3 * PERIOD_NS              # time keeps running
            assert np.all(np.array(m.velocity) == 0.0) and np.all(np.array(m.effort) == 0.0)
            assert np.allclose(m.position, rt.ctl.q_ref, atol=0.05)  # the standing posture
            ros.spin_for(0.2)
            assert len(col.msgs) == n + 3                           # still paused
            r = ros.call(SetBool, "/sim_node/pause", SetBool.Request(data=False))
            assert r.success
            r = ros.call(Trigger, "/sim_node/step", Trigger.Request())
            assert not r.success and "not paused" in r.message
            assert ros.spin_until(lambda: len(col.msgs) > n + 50, 5)
            d = np.diff([stamp_ns(x) for x in col.msgs])
            assert np.all(d == PERIOD_NS), d[d != PERIOD_NS]
        finally:
            col.close()


    def test_sigint_finalises_the_recording(self, ros, rt):
        assert rt.sim.alive()
        # the run has lasted > 5 s (rate test); interrupt it mid-run
        ros.spin_for(max(0.0, 6.0 - (time.monotonic() - rt.t_start)))
        rc = rt.sim.stop(signal.SIGINT)
        assert rc == 0, rt.sim.log()[-3000:]
        assert "recording finalised" in rt.sim.log()
        msgs, conns = read_mcap(rt.mcap)
        for topic, typ in ALL_TOPICS.items():
            assert topic in conns and conns[topic].msgtype == typ, topic
            qos = conns[topic].ext.offered_qos_profiles[0]
            want = "BEST_EFFORT" if topic == "/clock" else "RELIABLE"
            assert qos.reliability.name == want, topic
            durability = "TRANSIENT_LOCAL" if topic == "/robot_description" else "VOLATILE"
            assert qos.durability.name == durability, topic
        counts = {t: len(msgs.get(t, [])) for t in STATE_TOPICS}
        n = counts["/joint_states"]
        assert n >= 5 * 400, counts
        assert set(counts.values()) == {n}, counts                  # one message per step each
        for topic in STATE_TOPICS:
            times = np.array([t for t, _ in msgs[topic]])
            assert np.all(np.diff(times) > 0), topic                # strictly increasing
        js = msgs["/joint_states"]
        assert all(t == stamp_ns(m) for t, m in js)                 # log time = sim time
        assert np.all(np.diff([t for t, _ in js]) == PERIOD_NS)
        assert len(msgs["/robot_description"]) == 1
        # the PD controller's commands, recorded as received (how many the test process
        # answered depends on the machine's load)
        assert len(msgs["/joint_commands"]) > 100
        # what the earlier tests of the class published (the flood may overflow)
        effort = "/joint_group_effort_controller/commands"
        assert len(msgs.get(effort, [])) >= min(5, rt.sent[effort]), rt.sent
        assert len(msgs.get("/sim_node/wrench", [])) == rt.sent["/sim_node/wrench"], rt.sent
        # what is needed to re-simulate the run
        from mcap.reader import make_reader
        with open(rt.mcap, "rb") as f:
            reader = make_reader(f)
            md = {m.name: m.metadata for m in reader.iter_metadata()}
            att = {a.name: a.data for a in reader.iter_attachments()}
        assert "contact_model" in md["starleth_sim"]["physics_config"]
        init = json.loads(md["starleth_sim"]["initial_state"])
        assert len(init["joint_positions"]) == 12 and "q" in init and "q_minimal" in init
        from starleth_sim.physics.description import urdf_path
        with open(urdf_path(), "rb") as f:
            assert att["starleth.urdf"] == f.read()
        # the robot rebuilds from the recording alone: its URDF and its spec as loaded
        from starleth_sim.robots import recorded_description, robot_description
        assert md["starleth_sim"]["robot"] == "starleth"
        recorded = recorded_description(att["starleth.urdf"].decode(),
                                        att["starleth.robot.yaml"].decode(), "starleth")
        assert recorded.contact_names() == robot_description("starleth").contact_names()
        assert {"physics_config.yaml", "initial_state.json", "sim_node_parameters.yaml"} <= set(att)
        import yaml
        bag = yaml.safe_load(md["rosbag2"]["serialized_metadata"])
        assert bag["message_count"] == sum(len(v) for v in msgs.values())


# -----------------------------------------------------------------------------------------
# lockstep
# -----------------------------------------------------------------------------------------
def run_lockstep(ros, tmp, name, n_states, **params):
    """A lockstep run with the PD echo controller until it has answered n_states states;
    returns (SimProcess after SIGINT, mcap path, controller)."""
    mcap = str(tmp / f"{name}.mcap")
    ctl = EchoController(ros.node)
    sim = SimProcess(tmp / f"{name}.log", mode="lockstep", real_time_factor=0.0, record=mcap,
                     **params)
    try:
        ok = ros.spin_until(lambda: len(ctl.stamps) >= n_states or not sim.alive(),
                            START_TIMEOUT)
        assert ok and sim.alive(), sim.log()[-3000:]
    finally:
        sim.stop(signal.SIGINT)
        ctl.close()
    return sim, mcap, ctl


def test_lockstep_runs_are_bit_identical(ros, tmp_path):
    n = 600
    runs = []
    for i in range(2):
        sim, mcap, ctl = run_lockstep(ros, tmp_path, f"lockstep{i}", n)
        assert sim.proc.returncode == 0, sim.log()[-3000:]
        summary = sim.summary()
        assert summary["lockstep_timeouts"] == 0, summary
        msgs, _ = read_mcap(mcap)
        js = msgs["/joint_states"][:n]
        assert len(js) == n
        assert [t for t, _ in js] == [k * PERIOD_NS for k in range(n)]
        runs.append(np.array([np.concatenate([m.position, m.velocity, m.effort]) for _, m in js]))
        # the controller's reply to each state is stamped with that state's stamp
        cmds = msgs["/joint_commands"]
        assert all(t == stamp_ns(m) for t, m in cmds)
    a, b = runs
    assert a.tobytes() == b.tobytes()                           # bit-identical
    assert np.ptp(a[:, 0:12], axis=0).max() > 1e-6              # and the robot did move
    # the state topics of the last run, standing under PD control after the start transient
    last = slice(n - 200, n)
    z = [m.pose.pose.position.z for _, m in msgs["/starleth/base_state"][last]]
    assert 0.3 < min(z) and max(z) < 0.5
    imu = [m.linear_acceleration.z for _, m in msgs["/starleth/imu"][last]]
    assert abs(np.mean(imu) - 9.81) < 0.1                      # proper acceleration at rest
    fz = sum(np.mean([m.wrench.force.z for _, m in msgs[f"/starleth/{f}/wrench"][last]])
             for f in FEET)
    assert abs(fz / (total_mass() * 9.81) - 1.0) < 0.02         # the feet carry the robot
    diag = msgs["/starleth/solver"][n - 1][1].status[0]
    assert diag.name == "starleth_sim: solver"
    values = {kv.key: kv.value for kv in diag.values}
    assert set(values) >= {"iterations", "converged", "residual", "step_time",
                           "loaded_contacts_opened", "loaded_contacts_opened_total",
                           "projections", "projection_iterations"}
    assert values["loaded_contacts_opened_total"] == "0"       # no loaded foot was dropped


def test_lockstep_stale_late_and_dead_controller(ros, tmp_path):
    node = ros.node
    ctl = EchoController(node)
    diag = DiagWatcher(ros)
    mcap = str(tmp_path / "policy.mcap")
    sim = SimProcess(tmp_path / "policy.log", mode="lockstep", real_time_factor=0.0,
                     lockstep_timeout=0.2, timeout_policy="zero", record=mcap)
    try:
        assert ros.spin_until(lambda: len(ctl.stamps) >= 100 or not sim.alive(), START_TIMEOUT)
        assert sim.alive(), sim.log()[-3000:]
        # a command with a wrong stamp is dropped and counted; the controller then "dies"
        ctl.reply = False
        ros.spin_for(0.05)
        k_dead = len(ctl.stamps)
        wrong = JointState(name=list(ctl._cmd.name), effort=[0.0] * 12)
        wrong.header.stamp.sec = 999
        ctl.pub.publish(wrong)
        ros.spin_for(1.5)
        # the sim keeps stepping on its timeout policy (zero torque), ~1 step per 0.2 s
        stepped = len(ctl.stamps) - k_dead
        assert 3 <= stepped <= 10, stepped
        assert sim.alive()
        assert ros.spin_until(lambda: diag.get("lockstep_timeouts") >= 3
                              and diag.get("stale_commands") >= 1, 3), diag.values
        # a late answer (to a state already stepped on the timeout policy)
        late = JointState(name=list(ctl._cmd.name), effort=[0.0] * 12)
        late.header.stamp.sec, late.header.stamp.nanosec = divmod(ctl.stamps[-2], 1_000_000_000)
        ctl.pub.publish(late)
        # the controller comes back: full speed again
        ctl.reply = True
        n0 = len(ctl.stamps)
        assert ros.spin_until(lambda: len(ctl.stamps) > n0 + 200, 10)
        assert ros.spin_until(lambda: diag.get("late_commands") >= 1, 3), diag.values
    finally:
        rc = sim.stop(signal.SIGTERM)
        ctl.close()
        node.destroy_subscription(diag.sub)
    assert rc == 0
    # SIGTERM finalises the recording too; the zero-torque policy is in the joint states
    msgs, _ = read_mcap(mcap)
    js = msgs["/joint_states"]
    assert np.all(np.diff([t for t, _ in js]) == PERIOD_NS)
    assert any(np.all(np.array(m.effort) == 0.0) for _, m in js[k_dead + 2:k_dead + 5])
    log = sim.log()
    assert "lockstep: no command for" in log and "zero torques" in log
    assert "dropped a stale command" in log and "late command" in log
    s = sim.summary()
    assert s["lockstep_timeouts"] >= 3 and s["stale_commands"] >= 1 and s["late_commands"] >= 1


def test_push_on_trunk_changes_velocity_by_impulse_over_mass(ros, tmp_path):
    """Robot in the air (standing posture, 3 m up, joints held by PD); a vertical push on the
    trunk origin for one control period: the base velocity changes by F dt / m."""
    node = ros.node
    force = 2000.0
    k_push = 40
    ctl = EchoController(node, kp=100.0, kd=2.0)   # (kd 5 is too stiff for the legs in flight)
    push = node.create_publisher(WrenchStamped, "/sim_node/wrench", 10)
    odom = Collector(ros, Odometry, "/starleth/base_state", QoSProfile(depth=500))
    orig = ctl._on_state

    def on_state(msg):
        if ctl.closed:
            return
        if len(ctl.stamps) == k_push:       # push, then answer state k_push
            w = WrenchStamped()
            w.header.stamp = msg.header.stamp
            w.header.frame_id = "base"
            w.wrench.force.z = force
            push.publish(w)
        orig(msg)

    node.destroy_subscription(ctl.sub)
    ctl.sub = node.create_subscription(JointState, "/joint_states", on_state, QoSProfile(depth=10))
    sim = SimProcess(tmp_path / "push.log", mode="lockstep", real_time_factor=0.0,
                     initial_state="{base_position: [0.0, 0.0, 3.0]}")
    try:
        assert ros.spin_until(lambda: len(odom.msgs) >= k_push + 120 or not sim.alive(),
                              START_TIMEOUT)
        assert sim.alive(), sim.log()[-3000:]
    finally:
        sim.stop()
        ctl.close()
        node.destroy_publisher(push)
        odom.close()
    by_stamp = {}
    for m in odom.msgs:
        by_stamp.setdefault(stamp_ns(m), m)
    stamps = sorted(by_stamp)
    t = np.array(stamps) * 1e-9
    from starleth_sim.ros.state_io import quat_to_matrix
    vz = []
    for s in stamps:
        m = by_stamp[s]
        q = m.pose.pose.orientation
        R = quat_to_matrix(q.x, q.y, q.z, q.w)
        v = m.twist.twist.linear                                # base frame
        vz.append((R @ np.array([v.x, v.y, v.z]))[2])
    vz = np.array(vz)
    assert np.all([by_stamp[s].pose.pose.position.z > 1.0 for s in stamps])   # in the air
    # free fall before the push: v_z(k) = v_z(0) - g t
    expected = vz[1] - 9.81 * (t - t[1])
    resid = vz - expected
    dv = force * 0.0025 / total_mass()
    jump = int(np.argmax(resid > 0.5 * dv))
    assert jump > 5 and np.all(np.abs(resid[1:jump]) < 0.02 * dv)
    measured = resid[jump + 20:jump + 60].mean()
    assert abs(measured / dv - 1.0) < 0.05, (measured, dv)


def test_contact_markers_cdr_equals_the_message_objects():
    """The contact markers go out as CDR bytes patched into a template (SlotCdr): over a
    collapse under zero torques (contacts close, stick, slip, open again), the bytes
    deserialise to the message sim_node's object path fills (an open contact's arrow is
    deleted and keeps its last points, as there)."""
    from rclpy.serialization import deserialize_message, serialize_message
    from visualization_msgs.msg import MarkerArray

    from starleth_sim.ros.contact_markers import MARKER_COLOURS
    from starleth_sim.ros.sim_node import SimNode
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN_ID)
    node = SimNode(context=ctx, parameter_overrides={"mode": "lockstep",
                                                     "contact_markers_rate": 400.0})
    try:
        markers = node.publisher.visualisation.markers
        assert markers.cdr is not None
        # made again in this process (the serializer leaves CDR's padding bytes as its buffer
        # held them, so they can hold probe values of an earlier SlotCdr.create: it refused
        # the same layout from the second or third time on, 2,999 times in 3,000)
        made = [markers.make_cdr() for _ in range(50)]
        assert all(m is not None for m in made), sum(m is None for m in made)
        svc = node.service
        actions = set()
        for k in range(150):
            if k == 100:
                svc.submit_wrench("base", (0.0, 0.0, 900.0), (0.0, 0.0, 0.0), False)
            svc.step()
            sec, nsec = divmod(svc.stamp_ns, 1_000_000_000)
            back = deserialize_message(markers.cdr.build(markers.values(sec, nsec)),
                                       MarkerArray)
            markers.fill(sec, nsec)
            assert back == deserialize_message(serialize_message(markers.msg),
                                               MarkerArray), f"step {k}"
            # and both are the simulator's contacts: spheres at the contact points in the
            # colour of their state, arrows along F (contact_marker_scale m/N) unless open
            scale = node.settings.contact_marker_scale
            contacts = node.sim.contacts
            spheres = [m for m in back.markers if m.ns == "contacts"]
            arrows = [m for m in back.markers if m.ns == "contact_forces"]
            for c, sphere, arrow in zip(contacts, spheres, arrows, strict=True):
                pos = sphere.pose.position
                assert (pos.x, pos.y, pos.z) == tuple(float(x) for x in c.position)
                col = MARKER_COLOURS[c.state]
                assert [sphere.color.r, sphere.color.g, sphere.color.b, sphere.color.a] == \
                    pytest.approx(col, abs=1e-7)                       # float32 fields
                assert (sphere.header.stamp.sec, sphere.header.stamp.nanosec) == (sec, nsec)
                if c.state == "open":
                    assert arrow.action == 2
                    continue
                tip = arrow.points[1]
                assert arrow.action == 0 and (tip.x, tip.y, tip.z) == pytest.approx(
                    tuple(c.position + scale * c.force), abs=1e-12)
            actions |= {m.action for m in arrows}
        assert actions == {0, 2}                   # both ADD and DELETE arrows were compared
    finally:
        node.destroy()
        rclpy.try_shutdown(context=ctx)
