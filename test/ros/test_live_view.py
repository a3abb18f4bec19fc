"""sim_node's live view (issue #35): a client of the Foxglove WebSocket protocol
(starleth_sim.tools.view.live_log) subscribes to /tf and joint_states of a running sim_node
(lockstep, with controller_node in its process, recording) and decodes what it receives with
the schemas the server advertises to the same values as the recording holds at the same
stamps; the live view off imports no foxglove; without foxglove-sdk, or with the port in
use, one error line and the simulation goes on."""
import os
import socket
import subprocess
import sys

import pytest

pytest.importorskip("rclpy")
pytest.importorskip("foxglove")        # the optional extra: requirements-live.txt
pytest.importorskip("websockets")

from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.reader import read_ros2_messages
from ros_test_nodes import NodeProcess

from starleth_sim.tools.view.live_log import collect

DOMAIN_RANGE = (229, 4)       # first, span (conftest._free_ros_domain)
DOMAIN_ID = 229 + os.getpid() % 4
from repo_root import ROOT


class LinesLog:
    """A node's logger for the live view alone: the lines of each level."""

    def __init__(self):
        self.lines = {"info": [], "warning": [], "error": []}

    def __getattr__(self, level):
        return self.lines[level].append


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _decoder(channel):
    """The CDR decoder of an advertised channel, from the schema the server advertised."""
    assert channel["encoding"] == "cdr" and channel["schemaEncoding"] == "ros2msg"
    schema = Schema(id=1, name=channel["schemaName"], encoding="ros2msg",
                    data=channel["schema"].encode())
    return DecoderFactory().decoder_for("cdr", schema)


@pytest.fixture(scope="module")
def live_run(tmp_path_factory):
    """sim_node in lockstep with controller_node (standing) in its process, recording, the
    live view on a free port; a client subscribes to /tf and joint_states until it has 20
    TF messages and 200 joint states. Returns (client's LiveLog, bag path, node log)."""
    d = tmp_path_factory.mktemp("live")
    bag, port = str(d / "live.mcap"), free_port()
    sim = NodeProcess("starleth_sim.ros.sim_node", str(d / "sim_node.log"), DOMAIN_ID,
                      pre_args=("--composed", "--controller-param", "mode:=stand"),
                      mode="lockstep", real_time_factor=1.0, record=bag, live_view=True,
                      live_view_port=port)
    try:
        log = collect(f"ws://127.0.0.1:{port}", ["/tf", "joint_states"], seconds=60.0,
                      connect_timeout=120.0,
                      until=lambda lg: len(lg.messages.get("/tf", [])) >= 20
                      and len(lg.messages.get("/joint_states", [])) >= 200)
    finally:
        code = sim.stop()
    assert code == 0, sim.log()
    return log, bag, sim.log()


def test_live_view_serves_tf_and_joint_states_as_recorded(live_run):
    log, bag, node_log = live_run
    assert "live view: Foxglove WebSocket server on ws://127.0.0.1:" in node_log
    ch = log.channels
    assert ch["/tf"]["schemaName"] == "tf2_msgs/msg/TFMessage"
    assert ch["/joint_states"]["schemaName"] == "sensor_msgs/msg/JointState"
    # every topic sim_node publishes is advertised (the topics a recording holds as outputs)
    assert {"/tf_static", "/robot_description", "/clock", "/starleth/base_state",
            "/starleth/imu", "/starleth/solver", "/starleth/contact_markers"} <= set(ch)
    live = {t: log.messages.get(t, []) for t in ("/tf", "/joint_states")}
    assert len(live["/tf"]) >= 20 and len(live["/joint_states"]) >= 200
    recorded = {}
    for m in read_ros2_messages(bag, topics=["/tf", "/joint_states"]):
        recorded.setdefault(m.channel.topic, {})[m.log_time_ns] = m.ros_msg
    for topic, msgs in live.items():
        decode = _decoder(ch[topic])
        stamps = [t for t, _ in msgs]
        assert stamps == sorted(stamps), f"{topic}: log times not in order"
        for t, payload in msgs:
            got, want = decode(payload), recorded[topic][t]
            if topic == "/tf":
                assert len(got.transforms) == len(want.transforms) == 13
                for a, b in zip(got.transforms, want.transforms, strict=True):
                    assert (a.header.frame_id, a.child_frame_id) == \
                        (b.header.frame_id, b.child_frame_id)
                    assert a.header.stamp.sec * 10 ** 9 + a.header.stamp.nanosec == t
                    r, s = a.transform, b.transform
                    assert [r.translation.x, r.translation.y, r.translation.z, r.rotation.x,
                            r.rotation.y, r.rotation.z, r.rotation.w] == \
                        [s.translation.x, s.translation.y, s.translation.z, s.rotation.x,
                         s.rotation.y, s.rotation.z, s.rotation.w]
            else:
                assert got.header.stamp.sec * 10 ** 9 + got.header.stamp.nanosec == t
                assert list(got.name) == list(want.name) and len(got.name) == 12
                assert list(got.position) == list(want.position)
                assert list(got.velocity) == list(want.velocity)
                assert list(got.effort) == list(want.effort)
    # the robot stands under the controller: the joints move from the initial posture
    first, last = (_decoder(ch["/joint_states"])(live["/joint_states"][i][1]) for i in (0, -1))
    assert list(first.position) != list(last.position)


_PROBE = """
import socket, sys
import rclpy
from starleth_sim.ros.sim_node import SimNode
mode = sys.argv[1]
if mode == "missing":
    sys.modules["foxglove"] = None            # foxglove-sdk not installed
params = {"live_view": mode != "off"}
if mode == "busy":
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    params["live_view_port"] = busy.getsockname()[1]
ctx = rclpy.Context()
rclpy.init(context=ctx)
node = SimNode(context=ctx, parameter_overrides=params)
node.service.step()
node.publisher.publish_state()
print("LIVE", node.output.live is not None, "FOXGLOVE", sys.modules.get("foxglove") is not None,
      "STEPS", node.service.counters["steps"], flush=True)
node.destroy()
rclpy.shutdown(context=ctx)
"""


def _probe(mode):
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID), PYTHONPATH=ROOT,
               RCUTILS_COLORIZED_OUTPUT="0")
    p = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True, text=True,
                       timeout=180, env=env, cwd=ROOT)
    assert p.returncode == 0, p.stdout + p.stderr
    return p.stdout + p.stderr


@pytest.mark.parametrize("mode,live,foxglove", [("off", False, False), ("on", True, True)])
def test_live_view_off_does_not_import_foxglove(mode, live, foxglove):
    out = _probe(mode)
    assert f"LIVE {live} FOXGLOVE {foxglove} STEPS 1" in out


@pytest.mark.parametrize("mode,message", [
    ("missing", "live_view: foxglove-sdk is not installed; pip install -r "
                "requirements-live.txt"),
    ("busy", "live_view: cannot serve on 127.0.0.1:")])
def test_live_view_failure_is_one_error_line_and_the_simulation_goes_on(mode, message):
    out = _probe(mode)
    assert "LIVE False" in out and "STEPS 1" in out
    errors = [ln for ln in out.splitlines() if "ERROR" in ln]
    assert len(errors) == 1 and message in errors[0], out
    assert "Traceback" not in out


def test_live_view_sends_the_terrain_to_a_client_that_comes_later():
    """The terrain (latched, published once at start) reaches a client that connects after
    it went out, decoded with the advertised schema to the markers of the configuration."""
    import rclpy
    from rclpy.serialization import serialize_message

    from starleth_sim.ros.sim_node import SimNode
    port = free_port()
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN_ID)
    node = SimNode(context=ctx, parameter_overrides={
        "mode": "lockstep", "live_view": True, "live_view_port": port,
        "physics_overrides": "{stairs: {rise: 0.05, run: 0.3, count: 2}}"})
    try:
        log = collect(f"ws://127.0.0.1:{port}", ["/terrain"], seconds=30.0,
                      until=lambda lg: lg.messages.get("/terrain"))
        sent = serialize_message(node.terrain.msg)
    finally:
        node.destroy()
        rclpy.try_shutdown(context=ctx)
    ch = log.channels["/terrain"]
    assert ch["schemaName"] == "visualization_msgs/msg/MarkerArray"
    ((t, payload),) = log.messages["/terrain"]
    assert t == 0 and len(payload) == len(sent)   # (CDR padding bytes are not zeroed)
    got = _decoder(ch)(payload)
    assert [(m.ns, m.type) for m in got.markers] == [("ground", 1), ("boxes", 1), ("boxes", 1)]
    assert got.markers[2].scale.z == pytest.approx(0.1)       # the second step: 2 rises


@pytest.mark.parametrize("subprotocol", ["foxglove.sdk.v1", "foxglove.websocket.v1"])
def test_a_client_offering_either_subprotocol_name_is_served(subprotocol):
    """The live view's server (no node: a LiveView with one topic) serves a client that
    offers foxglove.sdk.v1, as current Foxglove and Lichtblick do, and one that offers only
    foxglove.websocket.v1, as Lichtblick before its December 2025 releases does (the SDK's
    own server answers that one HTTP 400): both get the advertisement and the same bytes,
    the handshake naming the protocol they asked for."""
    import threading
    import time

    import websockets
    import websockets.sync.client as ws_client

    from starleth_sim.ros.live_view import LiveView

    log = LinesLog()
    live = LiveView.open("127.0.0.1", free_port(), [("/chatter", "std_msgs/msg/String", False)],
                         log)
    assert live is not None, log.lines
    assert "foxglove.websocket.v1" in log.lines["info"][-1]
    backend_port = live.server.port
    payload = b"\x00\x01\x00\x00\x06\x00\x00\x00hello\x00"      # CDR of String "hello"
    stop = threading.Event()

    def publish():
        k = 0
        while not stop.is_set():
            live.log("/chatter", payload, k)
            live.flush()
            k += 1
            time.sleep(0.01)

    pub = threading.Thread(target=publish, daemon=True)
    pub.start()
    try:
        with ws_client.connect(f"ws://127.0.0.1:{live.port}", subprotocols=[subprotocol],
                               open_timeout=10) as ws:
            assert ws.subprotocol == subprotocol
            got = collect(f"ws://127.0.0.1:{live.port}", ["/chatter"], seconds=10.0,
                          until=lambda lg: len(lg.messages.get("/chatter", [])) >= 5,
                          subprotocol=subprotocol)
        if subprotocol == "foxglove.websocket.v1":    # what the SDK's server alone answers
            with pytest.raises(websockets.exceptions.InvalidStatus, match="400"):
                ws_client.connect(f"ws://127.0.0.1:{backend_port}", open_timeout=10,
                                  subprotocols=[subprotocol])
    finally:
        stop.set()
        pub.join(5)
        live.stop()
    assert got.channels["/chatter"]["schemaName"] == "std_msgs/msg/String"
    assert len(got.messages["/chatter"]) >= 5
    assert all(m == payload for _, m in got.messages["/chatter"])
    assert live.front.legacy_clients == (2 if subprotocol == "foxglove.websocket.v1" else 0)


def test_a_clients_malformed_frames_are_throttled_warnings_cut_short(capfd):
    """100 malformed frames of 60 kB from a client (under the front's limit; the SDK quotes
    each whole in its log message: frames of 1 MiB went to stderr, 105 MB in 2.5 s):
    warnings on the node's logger, throttled per SDK component, each cut to
    MAX_LOGGED_CHARS; nothing of them on stderr. The server serves on afterwards, and
    stopping it hands the SDK's logging back."""
    import asyncio
    import json
    import logging

    import websockets

    from starleth_sim.ros.live_view import MAX_LOGGED_CHARS, SUBPROTOCOL, LiveView

    log = LinesLog()
    live = LiveView.open("127.0.0.1", 0, [], log, throttle_period=60.0)
    assert live is not None, log.lines
    problems = live.problems
    frame = json.dumps({"op": "subscribe", "subscriptions": "a" * 60_000})

    async def flood():
        async with websockets.connect(f"ws://127.0.0.1:{live.port}", max_size=None,
                                      subprotocols=[SUBPROTOCOL], close_timeout=0.2) as ws:
            for _ in range(100):
                await ws.send(frame)
                await ws.send(b"\xff" + b"b" * 1000)          # an unknown binary opcode
            for _ in range(200):                   # until the server has read them
                if problems.throttle.counts.get("live_view", 0) >= target[0]:
                    break
                await asyncio.sleep(0.05)

    target = [200]
    try:
        asyncio.run(flood())
        assert 1 <= len(log.lines["warning"]) <= 2, log.lines["warning"]
        target[0] = 400
        asyncio.run(flood())                       # a second client: served, throttled
    finally:
        live.stop()
    warnings = log.lines["warning"]
    assert problems.throttle.counts["live_view"] >= 400, problems.throttle.counts
    assert 1 <= len(warnings) <= 2, warnings
    assert "live_view: Invalid message from 127.0.0.1:" in warnings[0]
    assert all(len(w) <= MAX_LOGGED_CHARS + 40 for w in warnings), [len(w) for w in warnings]
    assert f"({len(frame) // 1000}" in warnings[0]   # the length of the message it was cut from
    assert len(capfd.readouterr().err) < 2000
    assert logging.getLogger("foxglove").propagate and not logging.getLogger("foxglove").handlers


def test_a_client_message_over_the_limit_disconnects_that_client():
    """A client message over MAX_CLIENT_MESSAGE (64 KiB, in one frame or in fragments; the
    SDK itself takes up to 16 MiB) closes that client's connection before the SDK reads it,
    with one warning on the node's log; another client is served afterwards. The frame
    reader of the limit follows RFC 6455's lengths (7-bit, 16-bit, 64-bit, fragments)."""
    import asyncio
    import struct

    import websockets

    from starleth_sim.ros.live_view import SUBPROTOCOL, LiveView
    from starleth_sim.ros.live_view_front import MAX_CLIENT_MESSAGE, ClientMessageLimit

    def frame(payload_size, fin=True, opcode=1):
        head = bytes([(0x80 if fin else 0) | opcode])
        if payload_size < 126:
            head += bytes([0x80 | payload_size])
        elif payload_size < 1 << 16:
            head += bytes([0x80 | 126]) + struct.pack(">H", payload_size)
        else:
            head += bytes([0x80 | 127]) + struct.pack(">Q", payload_size)
        return head + b"mask" + b"x" * payload_size

    limit = ClientMessageLimit(1000)
    stream = frame(100) + frame(999) + frame(600, fin=False) + frame(400, opcode=0)
    assert all(limit.feed(stream[i:i + 7]) for i in range(0, len(stream), 7))   # in pieces
    assert ClientMessageLimit(1000).feed(frame(1001)[:10]) is False    # head alone suffices
    fragments = frame(600, fin=False) + frame(401, opcode=0)
    assert ClientMessageLimit(1000).feed(fragments) is False
    assert ClientMessageLimit(1 << 40).feed(frame(70_000)) is True     # a 64-bit length

    log = LinesLog()
    live = LiveView.open("127.0.0.1", 0, [("/chatter", "std_msgs/msg/String", False)], log)
    url = f"ws://127.0.0.1:{live.port}"

    async def oversized():
        async with websockets.connect(url, subprotocols=[SUBPROTOCOL], max_size=None,
                                      close_timeout=0.5) as ws:
            await ws.recv()                                        # serverInfo
            try:
                await ws.send("a" * (MAX_CLIENT_MESSAGE + 1))
                await asyncio.wait_for(ws.recv(), 5.0)
                await asyncio.wait_for(ws.recv(), 5.0)
            except websockets.exceptions.ConnectionClosed:
                return True
            return False

    try:
        closed = asyncio.run(oversized())
        got = collect(url, ["/chatter"], seconds=3.0, until=lambda lg: "/chatter" in
                      lg.channels)
    finally:
        live.stop()
    assert closed and live.front.oversized_clients == 1
    assert [w for w in log.lines["warning"] if f"over {MAX_CLIENT_MESSAGE} bytes" in w], \
        log.lines
    assert "/chatter" in got.channels


def fetch_asset(ws, uri: str, request_id: int):
    """(status, error message, data) of the server's fetchAsset response (binary opcode 4:
    request id u32, status u8 (0 ok), error length u32, error, data; little-endian)."""
    import json
    import struct
    ws.send(json.dumps({"op": "fetchAsset", "uri": uri, "requestId": request_id}))
    while True:
        frame = ws.recv(timeout=10)
        if isinstance(frame, bytes) and frame[0] == 4:
            rid, status, n = struct.unpack_from("<IBI", frame, 1)
            assert rid == request_id
            return status, frame[10:10 + n].decode(), frame[10 + n:]


def test_live_view_serves_the_robots_meshes_and_nothing_else():
    """A Go1's live view (a LiveView with its MeshAssets, no node) advertises the assets
    capability and answers fetchAsset for a mesh its URDF names with that file's bytes
    (package:// under the spec's roots); a file it does not name, an error."""
    import json

    import websockets.sync.client as ws_client

    from starleth_sim.robots import robot_description
    from starleth_sim.robots.meshes import mesh_filenames
    from starleth_sim.ros.live_view import LiveView, MeshAssets
    try:
        go1 = robot_description("go1")
    except Exception as e:   # example-robot-data not installed: make robots
        pytest.skip(str(e))
    assets = MeshAssets.of_robot("go1", go1.urdf_xml)
    uri = "package://example-robot-data/robots/go1_description/meshes/calf.dae"
    assert uri in mesh_filenames(go1.urdf_xml) and set(assets.files) == \
        set(mesh_filenames(go1.urdf_xml)) and not assets.missing
    log = LinesLog()
    live = LiveView.open("127.0.0.1", free_port(), [], log, assets=assets)
    assert live is not None, log.lines
    try:
        with ws_client.connect(f"ws://127.0.0.1:{live.port}", open_timeout=10,
                               subprotocols=["foxglove.sdk.v1"], max_size=None) as ws:
            info = json.loads(ws.recv(timeout=10))
            assert info["op"] == "serverInfo" and "assets" in info["capabilities"]
            status, error, data = fetch_asset(ws, uri, 7)
            assert status == 0 and error == ""
            assert data == open(assets.files[uri], "rb").read()
            other = uri.replace("calf.dae", "../../go1_description/urdf/go1.urdf")
            assert fetch_asset(ws, other, 8)[0] == 1
            assert fetch_asset(ws, "file:///etc/passwd", 9)[0] == 1
    finally:
        live.stop()
    assert not log.lines["warning"] and not log.lines["error"], log.lines
