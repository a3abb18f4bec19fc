"""/tf and /tf_static on DDS and on the live view: tf2_msgs (a full ROS install's, or the one
`make venv` generates from venv_interfaces/) has the type hash of Jazzy's, so a full ROS 2 on
another machine subscribes to it; a subscription typed tf2_msgs/msg/TFMessage receives world
-> base and every link, equal to what the bag holds for the same stamps; before any command
(lockstep: state 0 re-sent until a controller answers) a DDS subscriber and a live view client
get /tf and /tf_static, and the re-sends reach a DDS subscriber once, not every time."""
import json
import os
import socket
import sys
import xml.etree.ElementTree as ET

import pytest

rclpy = pytest.importorskip("rclpy")

from mcap.reader import make_reader
from rclpy.qos import DurabilityPolicy, QoSProfile
from rclpy.serialization import deserialize_message
from ros_test_nodes import NodeProcess, RosTestNode

DOMAIN_RANGE = (199, 30)      # first, span (conftest._free_ros_domain; shared with test_tf)
DOMAIN_ID = 199 + os.getpid() % 30
#: tf2_msgs/msg/TFMessage's type hash on a ROS 2 Jazzy install (`ros2 topic info /tf -v`)
JAZZY_TF_MESSAGE_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
TF_STATIC_QOS = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def tf2_msgs_or_skip():
    """tf2_msgs' TFMessage, or a skip that says where it comes from."""
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        pytest.skip("tf2_msgs is not installed: `make venv` generates it into the venv "
                    "(venv_interfaces/generate.py; a full ROS install provides it)")
    return TFMessage


class TfListener:
    """A test node subscribing to /tf and /tf_static typed tf2_msgs/msg/TFMessage."""

    def __init__(self, name, subscriptions=1):
        TFMessage = tf2_msgs_or_skip()
        self.ros = RosTestNode(DOMAIN_ID, name)
        self.got = {"/tf_static": []}
        node = self.ros.node
        node.create_subscription(TFMessage, "/tf_static", self.got["/tf_static"].append,
                                 TF_STATIC_QOS)
        for i in range(subscriptions):       # /tf, /tf#1, ...: one list per subscription
            key = "/tf" + (f"#{i}" if i else "")
            self.got[key] = []
            node.create_subscription(TFMessage, "/tf", self.got[key].append, 100)

    def subscribe_one_more(self):
        key = f"/tf#{len(self.got) - 1}"
        self.got[key] = []
        self.ros.node.create_subscription(tf2_msgs_or_skip(), "/tf", self.got[key].append, 100)
        return key


def _links(urdf_xml):
    return {lnk.get("name") for lnk in ET.fromstring(urdf_xml).findall("link")}


def _parents(messages):
    """{child frame: parent frame} over the transforms of `messages` (each child once)."""
    parent = {}
    for m in messages:
        for t in m.transforms:
            assert t.child_frame_id not in parent, t.child_frame_id
            parent[t.child_frame_id] = t.header.frame_id
    return parent


def test_tf2_msgs_has_the_type_hash_of_jazzy():
    """The type hash in the installed package's type description (share/tf2_msgs/msg/
    TFMessage.json, written by the rosidl generator) is Jazzy's."""
    tf2_msgs_or_skip()
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    paths = [os.path.join(p, "share", "tf2_msgs", "msg", "TFMessage.json")
             for p in prefixes + [sys.prefix]]       # (the venv: where `make venv` puts it)
    path = next((p for p in paths if os.path.isfile(p)), None)
    assert path is not None, f"no share/tf2_msgs/msg/TFMessage.json in {paths}"
    with open(path) as f:
        hashes = {h["type_name"]: h["hash_string"] for h in json.load(f)["type_hashes"]}
    assert hashes["tf2_msgs/msg/TFMessage"] == JAZZY_TF_MESSAGE_HASH
    # the types it is made of are the wheels' own (geometry_msgs, std_msgs, builtin_interfaces)
    assert set(hashes) == {"tf2_msgs/msg/TFMessage", "geometry_msgs/msg/TransformStamped",
                           "geometry_msgs/msg/Transform", "geometry_msgs/msg/Vector3",
                           "geometry_msgs/msg/Quaternion", "std_msgs/msg/Header",
                           "builtin_interfaces/msg/Time"}


def test_a_tf_message_subscriber_receives_what_the_bag_holds(tmp_path):
    """An in-process sim_node records 40 steps (/tf at 100 Hz: every 4th step) while a
    subscription typed TFMessage listens: it receives every /tf of the bag and the /tf_static,
    each equal, field by field, to the
    bag's message at its stamp; together they connect world to every link of the
    URDF; the publisher advertises Jazzy's type hash on the graph."""
    from starleth_sim.ros.sim_node import SimNode
    listener = TfListener("tf_listener")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN_ID)
    bag = str(tmp_path / "tf.mcap")
    node = SimNode(context=ctx, parameter_overrides={"mode": "lockstep", "record": bag,
                                                     "tf_rate": 100.0})
    try:
        pubs = node.publisher.visualisation.tf_pubs
        assert set(pubs) == {"tf", "tf_static"}
        assert listener.ros.spin_until(lambda: pubs["tf"].get_subscription_count() > 0 and
                                       listener.got["/tf_static"], 30.0), "not matched"
        node.publisher.publish_state()
        for _ in range(40):
            node.service.step()
            node.publisher.publish_state()
        assert listener.ros.spin_until(lambda: len(listener.got["/tf"]) >= 11, 10.0), \
            f"{len(listener.got['/tf'])} /tf received"
        info = listener.ros.node.get_publishers_info_by_topic("/tf")
        assert [(i.topic_type, str(i.topic_type_hash)) for i in info] == \
            [("tf2_msgs/msg/TFMessage", JAZZY_TF_MESSAGE_HASH)]
        urdf = node.sim.description.urdf_xml
    finally:
        node.destroy()
        rclpy.try_shutdown(context=ctx)
        listener.ros.close()
    with open(bag, "rb") as f:
        recorded = {}
        for _, channel, message in make_reader(f).iter_messages(topics=["/tf", "/tf_static"]):
            recorded.setdefault(channel.topic, []).append((message.log_time, message.data))
    assert len(recorded["/tf"]) == 11 and len(recorded["/tf_static"]) == 1   # k = 0, 4, .., 40
    for topic in ("/tf", "/tf_static"):
        got = listener.got[topic]
        assert len(got) == len(recorded[topic]), topic
        for msg, (log_time, data) in zip(got, recorded[topic], strict=True):
            assert msg == deserialize_message(data, type(msg)), topic     # every field
            if topic == "/tf":
                stamp = msg.transforms[0].header.stamp
                assert stamp.sec * 10 ** 9 + stamp.nanosec == log_time
    first = listener.got["/tf"][0].transforms[0]
    assert (first.header.frame_id, first.child_frame_id) == ("world", "base")
    parent = _parents([listener.got["/tf"][-1], listener.got["/tf_static"][0]])
    assert set(parent) == _links(urdf)                 # every link, each once
    for link in parent:                                # ... connected to world
        f, seen = link, set()
        while f != "world":
            assert f in parent and f not in seen, f"{link} is not connected to world"
            seen.add(f)
            f = parent[f]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def waiting_sim(tmp_path_factory):
    """sim_node in lockstep with no controller (state 0 re-sent until one answers), the live
    view on a free port where foxglove-sdk is installed."""
    d = tmp_path_factory.mktemp("tf_waiting")
    params = {"mode": "lockstep"}
    try:
        import foxglove  # noqa: F401  optional: requirements-live.txt
        params.update(live_view=True, live_view_port=_free_port())
    except ImportError:
        pass
    sim = NodeProcess("starleth_sim.ros.sim_node", str(d / "sim_node.log"), DOMAIN_ID,
                      **params)
    try:
        yield sim, params
    finally:
        code = sim.stop()
    assert code == 0, sim.log()
    assert sim.summary()["steps"] == 0, "a step was taken without a command"


def test_tf_reaches_a_dds_subscriber_before_any_command(waiting_sim):
    """A subscriber that comes after sim_node started, with no command sent: /tf_static (kept
    by transient local) and /tf of state 0 (re-sent to it), world -> base and every link;
    the next re-sends do not repeat it (a tf2 buffer warns of a repeated stamp), a second
    subscription gets its own at once (the first then one more)."""
    sim, _ = waiting_sim
    listener = TfListener("tf_listener_early")
    ros, got = listener.ros, listener.got
    try:
        assert ros.spin_until(lambda: got["/tf"] and got["/tf_static"], 60.0, procs=[sim]), \
            f"no /tf or /tf_static before a command: {sim.log()[-2000:]}"
        ros.spin_for(1.2)                     # two re-sends of state 0 (every 0.5 s)
        assert len(got["/tf"]) == 1 and len(got["/tf_static"]) == 1
        stamps = {(t.header.stamp.sec, t.header.stamp.nanosec) for t in got["/tf"][0].transforms}
        assert stamps == {(0, 0)}
        second = listener.subscribe_one_more()
        assert ros.spin_until(lambda: got[second], 5.0, procs=[sim]), "newcomer not served"
        ros.spin_for(0.3)
        assert len(got[second]) == 1 and len(got["/tf"]) == 2
        assert got[second][0] == got["/tf"][0]
        parent = _parents([got["/tf"][0], got["/tf_static"][0]])
        assert parent["base"] == "world" and len(parent) == 17      # the 17 links of StarlETH
    finally:
        ros.close()


def test_live_view_serves_tf_before_any_command(waiting_sim):
    """The live view's client gets /tf (state 0, with every re-send: Foxglove draws the
    robot before the first command) and /tf_static, with joint_states."""
    sim, params = waiting_sim
    if "live_view_port" not in params:
        pytest.skip("foxglove-sdk is not installed (requirements-live.txt): no live view")
    from starleth_sim.tools.view.live_log import collect
    log = collect(f"ws://127.0.0.1:{params['live_view_port']}",
                  ["/tf", "/tf_static", "/joint_states"], seconds=30.0, connect_timeout=60.0,
                  until=lambda lg: len(lg.messages.get("/tf", [])) >= 3)
    tf = log.messages.get("/tf", [])
    assert len(tf) >= 3, {t: len(m) for t, m in log.messages.items()}
    assert {t for t, _ in tf} == {0}                  # state 0, log time = its stamp
    assert len(log.messages.get("/tf_static", [])) >= 1
    assert len(log.messages.get("/joint_states", [])) >= 3


class _Log:
    def __init__(self):
        self.lines = []

    def info(self, text):
        self.lines.append(("info", text))

    def warning(self, text):
        self.lines.append(("warning", text))


def test_without_a_usable_tf2_msgs_one_line_says_tf_is_not_published(monkeypatch):
    """sim_node's one line where tf2_msgs is missing (info: where it comes from) or its type
    support does not load (a warning with the cause); no publisher then, no crash."""
    from starleth_sim.ros.visualisation import tf_message_type
    monkeypatch.setitem(sys.modules, "tf2_msgs", None)
    monkeypatch.setitem(sys.modules, "tf2_msgs.msg", None)
    log = _Log()
    assert tf_message_type(log) is None
    assert len(log.lines) == 1 and log.lines[0][0] == "info"
    assert "`make venv` generates it" in log.lines[0][1]
    assert log.lines[0][1].endswith("recorded (and served by the live view, live_view:=true) "
                                    "but not published")
    monkeypatch.undo()
    assert tf_message_type(_Log()) is tf2_msgs_or_skip()      # (skips where it is missing)
    import rclpy.type_support

    def broken(_type):
        raise ImportError("libtf2_msgs__rosidl_typesupport_c.so: cannot open shared object")
    monkeypatch.setattr(rclpy.type_support, "check_for_type_support", broken)
    log = _Log()
    assert tf_message_type(log) is None
    assert log.lines == [("warning", "tf2_msgs is installed but its type support does not "
                          "load (libtf2_msgs__rosidl_typesupport_c.so: cannot open shared "
                          "object): /tf and /tf_static are recorded (and served by the live "
                          "view, live_view:=true) but not published")]
