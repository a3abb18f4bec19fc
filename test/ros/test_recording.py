"""McapRecorder (starleth_sim.ros.recording): the rosbag2 MCAP layout, read back with independent
readers (rosbags, mcap_ros2). No ROS graph, no processes: fast."""
import itertools
import json
import os
import sys

import pytest
import yaml

pytest.importorskip("rclpy")
rosbags_reader = pytest.importorskip("rosbags.rosbag2")

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import WrenchStamped
from nav_msgs.msg import Odometry
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray, String

from starleth_sim.ros.recording import (
    SEPARATOR,
    McapRecorder,
    generated_msg_text,
    message_definition,
    msg_text,
    qos_profiles_yaml,
    type_name,
)

TYPES = [JointState, Imu, DiagnosticArray, WrenchStamped, Odometry, Clock, Float64MultiArray,
         String]


def test_type_names():
    assert type_name(JointState) == "sensor_msgs/msg/JointState"
    assert type_name("sensor_msgs/JointState") == "sensor_msgs/msg/JointState"
    assert type_name("nav_msgs/msg/Odometry") == "nav_msgs/msg/Odometry"


def test_message_definition_layout():
    text = message_definition(DiagnosticArray)
    # root text first, then each dependency once after an 80 '=' line and 'MSG: pkg/Type'
    assert text.startswith(msg_text("diagnostic_msgs/msg/DiagnosticArray"))
    deps = [line[5:] for line in text.splitlines() if line.startswith("MSG: ")]
    assert sorted(deps) == sorted({"diagnostic_msgs/DiagnosticStatus", "diagnostic_msgs/KeyValue",
                                   "std_msgs/Header", "builtin_interfaces/Time"})
    assert text.count(SEPARATOR + "\nMSG: ") == 4
    odom = message_definition(Odometry)
    for dep in ("geometry_msgs/PoseWithCovariance", "geometry_msgs/Pose", "geometry_msgs/Point",
                "geometry_msgs/Quaternion", "geometry_msgs/TwistWithCovariance",
                "geometry_msgs/Twist", "geometry_msgs/Vector3", "std_msgs/Header"):
        assert f"MSG: {dep}\n" in odom


def test_generated_definition_matches_fields():
    text = generated_msg_text("diagnostic_msgs/msg/DiagnosticStatus")
    assert "byte OK=0" in text and "diagnostic_msgs/KeyValue[] values" in text
    assert "float64[9] orientation_covariance" in generated_msg_text("sensor_msgs/msg/Imu")
    assert "string[] name" in generated_msg_text("sensor_msgs/msg/JointState")


def test_qos_yaml():
    q = yaml.safe_load(qos_profiles_yaml(QoSProfile(
        depth=1, reliability=ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL)))
    assert q[0]["reliability"] == "best_effort" and q[0]["durability"] == "transient_local"
    assert q[0]["history"] == "keep_last" and q[0]["depth"] == 1
    assert q[0]["liveliness"] == "automatic"


def _sample_messages():
    js = JointState()
    js.header.stamp.sec, js.header.stamp.nanosec = 1, 2_500_000
    js.name = ["LF_HAA", "LF_HFE"]
    js.position, js.velocity, js.effort = [0.1, -0.2], [1.0, 2.0], [3.0, -4.0]
    imu = Imu()
    imu.header.frame_id = "base"
    imu.linear_acceleration.z = 9.81
    imu.orientation.w = 1.0
    d = DiagnosticArray()
    d.status = [DiagnosticStatus(level=DiagnosticStatus.WARN, name="solver",
                                 values=[KeyValue(key="iterations", value="12")])]
    w = WrenchStamped()
    w.header.frame_id = "world"
    w.wrench.force.z = 65.7
    o = Odometry()
    o.child_frame_id = "base"
    o.pose.pose.position.z = 0.41
    c = Clock()
    c.clock.sec = 1
    f = Float64MultiArray(data=[1.0] * 12)
    s = String(data="<robot name='x'/>")
    return [js, imu, d, w, o, c, f, s]


def _record(path, n=5, close=True):
    rec = McapRecorder(str(path))
    msgs = _sample_messages()
    topics = [f"/t{i}" for i in range(len(msgs))]
    qos = QoSProfile(depth=10)
    for t, m in zip(topics, msgs, strict=True):
        rec.add_topic(t, type(m), qos)
    rec.add_metadata("starleth_sim", {"physics_config": "name: HmJ\n", "n": 3})
    rec.add_attachment("robot.urdf", "application/xml", "<robot/>")
    for k in range(n):
        for i, (t, m) in enumerate(zip(topics, msgs, strict=True)):
            data = serialize_message(m) if i % 2 else m   # bytes and message objects
            assert rec.write(t, data, 1_000_000_000 + k * 2_500_000)
    if close:
        rec.close()
    return rec, topics, msgs


def test_rosbags_reads_the_file(tmp_path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
    path = tmp_path / "run.mcap"
    rec, topics, msgs = _record(path)
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = {c.topic: c for c in reader.connections}
        assert set(conns) == set(topics)
        for t, m in zip(topics, msgs, strict=True):
            c = conns[t]
            assert c.msgtype == type_name(type(m))
            assert c.msgcount == 5
            qos = c.ext.offered_qos_profiles
            assert len(qos) == 1 and qos[0].reliability.name == "RELIABLE"
            assert c.ext.serialization_format == "cdr"
        seen = {}
        for conn, timestamp, raw in reader.messages():
            seen.setdefault(conn.topic, []).append(timestamp)
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.msgtype == "sensor_msgs/msg/JointState":
                assert list(msg.name) == ["LF_HAA", "LF_HFE"]
                assert list(msg.effort) == [3.0, -4.0]
            if conn.msgtype == "diagnostic_msgs/msg/DiagnosticArray":
                assert msg.status[0].values[0].value == "12"
        for t in topics:
            ts = seen[t]
            assert len(ts) == 5 and all(b > a for a, b in itertools.pairwise(ts))


def test_rosbags_parses_embedded_definitions(tmp_path):
    """The schema text alone (no type store) is enough to decode: rosbags' msg parser."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    path = tmp_path / "run.mcap"
    _record(path, n=2)
    store = get_typestore(Stores.EMPTY)
    with Reader(path) as reader:
        for c in reader.connections:
            store.register(get_types_from_msg(c.msgdef.data, c.msgtype))
        for c, _, raw in reader.messages():
            store.deserialize_cdr(raw, c.msgtype)


def test_mcap_ros2_decodes_and_metadata(tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    path = tmp_path / "run.mcap"
    _record(path, n=3)
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        assert header.profile == "ros2"
        summary = reader.get_summary()
        assert summary.statistics.message_count == 3 * len(TYPES)
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        for c in summary.channels.values():
            assert "offered_qos_profiles" in c.metadata
        n = 0
        for schema, _channel, _message, decoded in reader.iter_decoded_messages():
            n += 1
            if schema.name == "nav_msgs/msg/Odometry":
                assert decoded.child_frame_id == "base"
                assert decoded.pose.pose.position.z == pytest.approx(0.41)
        assert n == 3 * len(TYPES)
        md = {m.name: m.metadata for m in reader.iter_metadata()}
        assert md["starleth_sim"]["physics_config"] == "name: HmJ\n"
        assert json.loads(md["starleth_sim"]["n"]) == 3
        bag = yaml.safe_load(md["rosbag2"]["serialized_metadata"])
        assert bag["version"] == 9 and bag["storage_identifier"] == "mcap"
        assert bag["message_count"] == 3 * len(TYPES)
        assert {t["topic_metadata"]["name"]: t["message_count"]
                for t in bag["topics_with_message_count"]} == {f"/t{i}": 3 for i in range(8)}
        assert md["rosbag2"]["ROS_DISTRO"]
        att = list(reader.iter_attachments())
        assert [a.name for a in att] == ["robot.urdf"] and att[0].data == b"<robot/>"


def test_close_is_idempotent_and_write_after_close_is_ignored(tmp_path):
    path = tmp_path / "run.mcap"
    rec, topics, msgs = _record(path, n=1)
    rec.close()
    assert rec.write(topics[0], msgs[0], 5) is False
    with McapRecorder(str(tmp_path / "ctx.mcap")) as r2:
        r2.add_topic("/x", String)
        r2.write("/x", String(data="a"), 1)
    from mcap.reader import make_reader
    with open(tmp_path / "ctx.mcap", "rb") as f:
        assert make_reader(f).get_summary().statistics.message_count == 1


def test_generated_schema_is_decodable():
    """Types without a .msg file get a generated definition; it must decode the same CDR."""
    from mcap.records import Schema
    from mcap_ros2.decoder import DecoderFactory
    text = generated_msg_text("sensor_msgs/msg/JointState")
    # dependencies in the generated text are full 'pkg/Type' names
    full = text
    for dep in ("std_msgs/Header", "builtin_interfaces/Time"):
        full += f"\n{SEPARATOR}\nMSG: {dep}\n" + generated_msg_text(dep)
    schema = Schema(id=1, name="sensor_msgs/msg/JointState", encoding="ros2msg",
                    data=full.encode())
    decode = DecoderFactory().decoder_for("cdr", schema)
    msg = _sample_messages()[0]
    out = decode(serialize_message(msg))
    assert list(out.name) == list(msg.name) and list(out.velocity) == [1.0, 2.0]
    assert out.header.stamp.nanosec == 2_500_000


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_compressed_chunks_are_readable(tmp_path, compression):
    from rosbags.highlevel import AnyReader
    path = tmp_path / f"{compression}.mcap"
    with McapRecorder(str(path), compression=compression) as rec:
        rec.add_topic("/js", JointState)
        for k in range(100):
            rec.write("/js", _sample_messages()[0], k + 1)
    with AnyReader([path]) as reader:
        assert sum(1 for _ in reader.messages()) == 100
    with pytest.raises(ValueError, match="compression"):
        McapRecorder(str(tmp_path / "x.mcap"), compression="gzip")


def test_split_recorder_by_size_gives_complete_files_and_a_rosbag2_directory(tmp_path):
    """SplitRecorder (record_max_size): a new file when the current one holds max_size bytes;
    each file is a complete bag (rosbags reads it alone, with the metadata record and the
    attachment), the directory is a rosbag2 bag (metadata.yaml listing the files) that
    rosbags reads as one bag with every message once and in order."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    from starleth_sim.ros.recording import SplitRecorder
    path = tmp_path / "run.mcap"            # the .mcap suffix names the directory "run"
    rec = SplitRecorder(str(path), max_size=200_000, chunk_size=32 * 1024)
    rec.add_topic("/joint_states", JointState, QoSProfile(depth=10))
    rec.add_metadata("starleth_sim", {"physics_config": "name: x"})
    rec.add_attachment("starleth.urdf", "application/xml", "<robot name='x'/>")
    js = JointState(name=[f"j{i}" for i in range(12)], position=[0.5] * 12)
    n = 5000
    for k in range(n):
        js.header.stamp.sec, js.header.stamp.nanosec = divmod(k * 2_500_000, 1_000_000_000)
        rec.write("/joint_states", js, k * 2_500_000)
    rec.close()
    bag = tmp_path / "run"
    files = sorted(bag.glob("*.mcap"), key=lambda p: int(p.stem.split("_")[-1]))
    assert len(files) >= 3 and rec.message_count == n
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["relative_file_paths"] == [p.name for p in files]
    assert meta["message_count"] == n
    assert meta["topics_with_message_count"][0]["message_count"] == n
    store = get_typestore(Stores.ROS2_JAZZY)
    for f in files[:-1]:
        assert f.stat().st_size < 200_000 + 64 * 1024      # one chunk past the limit at most
    seen = []
    for f in files:
        with AnyReader([f], default_typestore=store) as r:   # each file on its own
            seen += [ts for _, ts, _ in r.messages()]
        from mcap.reader import make_reader
        with open(f, "rb") as fh:
            reader = make_reader(fh)
            assert {m.name for m in reader.iter_metadata()} >= {"starleth_sim", "rosbag2"}
            assert [a.name for a in reader.iter_attachments()] == ["starleth.urdf"]
    assert seen == [k * 2_500_000 for k in range(n)]
    with AnyReader([bag], default_typestore=store) as r:     # the directory as one bag
        assert [ts for _, ts, _ in r.messages()] == seen
    with pytest.raises(FileExistsError):
        SplitRecorder(str(bag))                              # never into a non-empty directory


# -----------------------------------------------------------------------------------------
# QueuedRecorder (sim_node's recorder: written by a thread of its own)
# -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["thread", "process"])
def test_queued_and_process_recorders_keep_every_message_in_order(tmp_path, kind):
    """sim_node's recorders (a writer process; a writer thread where no process can be
    started): every message handed over is in the file(s), in order, after close."""
    from mcap.reader import make_reader

    from starleth_sim.ros.recording import ProcessRecorder, QueuedRecorder, SplitRecorder
    n = 3000
    for split in (False, True):
        path = tmp_path / ("split" if split else "one.mcap")
        if kind == "process":
            rec = ProcessRecorder(str(path), max_size=60_000 if split else 0)
        else:
            rec = QueuedRecorder(SplitRecorder(str(path), max_size=60_000) if split
                                 else McapRecorder(str(path)))
        rec.add_topic("/a", WrenchStamped, QoSProfile(depth=10))
        rec.add_topic("/b", Clock)
        m = WrenchStamped()
        for k in range(n):                   # handed over much faster than written
            m.header.stamp.sec, m.header.stamp.nanosec = divmod(k * 2_500_000, 10 ** 9)
            m.wrench.force.z = float(k)
            assert rec.write("/a", serialize_message(m), k * 2_500_000)
            assert rec.write("/b", Clock(), k * 2_500_000)      # objects are serialised
        rec.add_metadata("late", {"k": "v"})  # waits for the queue: after every message
        rec.close()                          # at once: close writes what is still queued
        assert rec.closed and not rec.write("/a", serialize_message(m), 0)
        rec.close()                          # idempotent
        files = sorted(path.glob("*.mcap")) if split else [path]
        assert len(files) > 1 or not split
        forces, times = [], []
        for f in files:
            with open(f, "rb") as fh:
                reader = make_reader(fh)
                for _schema, channel, msg in reader.iter_messages(log_time_order=False):
                    if channel.topic == "/a":
                        from rclpy.serialization import deserialize_message
                        forces.append(deserialize_message(msg.data, WrenchStamped).wrench.force.z)
                    times.append(msg.log_time)
        assert forces == [float(k) for k in range(n)]          # all of them, in order
        assert len(times) == 2 * n and times == sorted(times)
        assert rec.message_count == 2 * n


# -----------------------------------------------------------------------------------------
# starleth_interface.msg_cdr: the per-cycle messages as CDR bytes, both ways
# -----------------------------------------------------------------------------------------
def _values(rng, n):
    return [float(x) for x in rng.normal(size=n) * 10.0 ** rng.integers(-8, 8, size=n)]


def test_fixed_cdr_templates_give_rclpys_bytes():
    """What sim_node publishes from templates is the message rclpy serialises when filled
    with the same values (the recorded bags hold the same messages)."""
    import numpy as np
    from rclpy.serialization import deserialize_message

    from starleth_interface.msg_cdr import IMU_FIELDS, ODOM_FIELDS, WRENCH_FIELDS, FixedCdr, _set
    rng = np.random.default_rng(1)
    cases = [(WrenchStamped, WRENCH_FIELDS, ("world",)), (Odometry, ODOM_FIELDS, ("world", "base")),
             (Imu, IMU_FIELDS, ("base",))]
    for typ, fields, frames in cases:
        def fresh(typ=typ, frames=frames):
            m = typ()
            m.header.frame_id = frames[0]
            if len(frames) > 1:
                m.child_frame_id = frames[1]
            return m
        cdr = FixedCdr.create(fresh(), fields)
        assert cdr is not None, typ
        for _ in range(20):
            vals = _values(rng, len(fields))
            sec, nsec = int(rng.integers(0, 2 ** 31)), int(rng.integers(0, 10 ** 9))
            m = fresh()
            m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
            for f, v in zip(fields, vals, strict=True):
                _set(m, f, v)
            data = cdr.build(sec, nsec, vals)
            # the same message, the same size (bytes may differ in padding only, which
            # rclpy does not zero)
            assert deserialize_message(data, typ) == m, typ
            assert len(data) == len(serialize_message(m))
    clock = FixedCdr.create(Clock(), (), stamp="clock")
    back = deserialize_message(clock.build(12, 345, ()), Clock)
    assert (back.clock.sec, back.clock.nanosec) == (12, 345)


def test_readers_decode_rclpys_bytes_and_fall_back_on_anything_else():
    import numpy as np

    from starleth_interface.msg_cdr import (
        ODOM_FIELDS,
        WRENCH_FIELDS,
        JointStateCdr,
        JointStateReader,
        StampedReader,
        _set,
    )
    rng = np.random.default_rng(2)
    ro = StampedReader(Odometry, ODOM_FIELDS, n_strings=2)
    rw = StampedReader(WrenchStamped, WRENCH_FIELDS)
    for frame, child in (("world", "base"), ("odom", "base_link"), ("w", "a_much_longer_frame")):
        for _ in range(5):
            o = Odometry()
            o.header.frame_id, o.child_frame_id = frame, child
            o.header.stamp.sec, o.header.stamp.nanosec = 3, 7
            vals = _values(rng, len(ODOM_FIELDS))
            for f, v in zip(ODOM_FIELDS, vals, strict=True):
                _set(o, f, v)
            o.pose.covariance = rng.normal(size=36).tolist()      # ignored, skipped over
            assert ro.decode(serialize_message(o)) == (3, 7, vals)
            w = WrenchStamped()
            w.header.frame_id = frame
            w.wrench.force.x, w.wrench.force.y, w.wrench.force.z = vals[:3]
            w.wrench.torque.z = 99.0
            assert rw.decode(serialize_message(w)) == (0, 0, vals[:3])
    nan = Odometry()
    nan.header.frame_id, nan.child_frame_id = "world", "base"
    nan.pose.pose.position.x = float("nan")
    assert np.isnan(ro.decode(serialize_message(nan))[2][0])    # values as they are
    good = serialize_message(nan)
    assert ro.decode(good[:40]) is None                         # truncated
    assert ro.decode(b"\x01\x00" + good[2:]) is None            # big endian
    assert rw.decode(b"") is None

    names = [f"{leg}_{j}" for leg in ("LF", "RF", "LH", "RH") for j in ("HAA", "HFE", "KFE")]
    rj = JointStateReader()
    tmpl = JointStateCdr.create(names)
    for order in (names, names[::-1], names):
        js = JointState()
        js.name = list(order)
        js.header.stamp.sec, js.header.stamp.nanosec = 1, 2_500_000
        js.position, js.velocity, js.effort = (_values(rng, 12) for _ in range(3))
        sec, nsec, got_names, pos, vel = rj.decode(serialize_message(js))
        assert (sec, nsec, list(got_names)) == (1, 2_500_000, list(order))
        assert pos.tolist() == list(js.position) and vel.tolist() == list(js.velocity)
    a = rj.decode(tmpl.build(0, 0, *np.zeros((3, 12))))[2]
    assert a is rj.decode(tmpl.build(0, 5, *np.ones((3, 12))))[2]   # one tuple: caches hold
    short = JointState()
    short.name, short.position, short.velocity = list(names), [0.0] * 11, [0.0] * 12
    assert rj.decode(serialize_message(short)) is None           # sizes differ: rclpy's path
    no_vel = JointState()
    no_vel.name, no_vel.position = list(names), [0.0] * 12
    assert rj.decode(serialize_message(no_vel)) is None
    assert rj.decode(serialize_message(short)[:30]) is None


def test_diagnostic_array_writer_gives_rclpys_message():
    import numpy as np
    from rclpy.serialization import deserialize_message

    from starleth_interface.msg_cdr import DiagnosticArrayCdr
    rng = np.random.default_rng(3)
    layouts = [("starleth_sim: solver", "starleth_sim", [f"k{i}" for i in range(14)]),
               ("starleth_sim: interface", "hw", ["mode", "ü", "x" * 9])]
    cdr = DiagnosticArrayCdr("", layouts)
    for n_status in (1, 2, 1, 2):
        statuses, msg = [], DiagnosticArray()
        msg.header.stamp.sec, msg.header.stamp.nanosec = 5, 123
        for index in range(n_status):
            name, hw, keys = layouts[index]
            values = ["".join(rng.choice(list("abcé0123 .-"), size=rng.integers(0, 12)))
                      for _ in keys]
            level = (DiagnosticStatus.OK, DiagnosticStatus.WARN, 2)[int(rng.integers(0, 3))]
            message = "running" if index else ""
            statuses.append((index, level, message, values))
            msg.status.append(DiagnosticStatus(
                level=level if isinstance(level, bytes) else bytes([level]), name=name,
                message=message, hardware_id=hw,
                values=[KeyValue(key=k, value=v) for k, v in zip(keys, values, strict=True)]))
        data = cdr.build(5, 123, statuses)
        # the same message (bytes differ only in padding, which rclpy does not zero)
        assert deserialize_message(data, DiagnosticArray) == msg
        assert len(data) == len(serialize_message(msg))


def test_process_recorder_finalises_the_file_when_its_parent_is_gone(tmp_path):
    """The writer process finalises the file when its input ends (the parent killed
    outright, SIGKILL): every message handed over is in a complete file."""
    from rclpy.serialization import deserialize_message

    from starleth_sim.ros.recording import ProcessRecorder
    path = tmp_path / "orphan.mcap"
    rec = ProcessRecorder(str(path))
    rec.add_topic("/clock", Clock)
    for k in range(500):
        m = Clock()
        m.clock.sec = k
        rec.write("/clock", serialize_message(m), k)
    rec.hand_over()
    rec._proc.stdin.close()          # what the parent's death does to the pipe
    assert rec._proc.wait(30) == 0
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        reader = make_reader(f)
        secs = [deserialize_message(m.data, Clock).clock.sec
                for _, _, m in reader.iter_messages(log_time_order=False)]
        assert reader.get_summary() is not None              # finished: summary written
        md = {m.name: m.metadata for m in reader.iter_metadata()}
    assert secs == list(range(500)) and "rosbag2" in md


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux scheduling and pipes")
def test_process_recorder_writer_stays_in_the_background(tmp_path):
    """The writer process runs under SCHED_BATCH (a hand-over does not hand it the CPU of
    the simulator that wrote it) and its pipe holds many hand-overs (a hand-over does not
    wait for the writer)."""
    from starleth_sim.ros.recording import ProcessRecorder
    rec = ProcessRecorder(str(tmp_path / "bg.mcap"))
    try:
        assert os.sched_getscheduler(rec._proc.pid) == os.SCHED_BATCH
        with open("/proc/sys/fs/pipe-max-size") as f:
            expected = min(ProcessRecorder.PIPE_SIZE, int(f.read()))
        assert rec.pipe_size >= expected > 64 * 1024
    finally:
        rec.close()


# -----------------------------------------------------------------------------------------
# the Recorder protocol, StorageOptions and open_recorder (sim_node's writer chain)
# -----------------------------------------------------------------------------------------
def test_every_recorder_implements_the_protocol_and_closes_with_metadata(tmp_path):
    """McapRecorder, SplitRecorder, QueuedRecorder and ProcessRecorder are Recorders:
    hand_over, close(timeout, metadata) (the records land in the file), dropped, failure."""
    from mcap.reader import make_reader

    from starleth_sim.ros.recording import ProcessRecorder, QueuedRecorder, Recorder, SplitRecorder
    makers = {"mcap": lambda p: McapRecorder(str(p) + ".mcap"),
              "split": lambda p: SplitRecorder(str(p), max_size=1 << 20),
              "queued": lambda p: QueuedRecorder(McapRecorder(str(p) + ".mcap")),
              "process": lambda p: ProcessRecorder(str(p) + ".mcap")}
    # every writer implements what the protocol only declares (hand_over and the context
    # manager have defaults there)
    declared = ("add_topic", "add_metadata", "add_attachment", "write", "counts", "close",
                "closed", "topics")
    for cls in (McapRecorder, SplitRecorder, QueuedRecorder, ProcessRecorder):
        missing = [m for m in declared if getattr(cls, m) is getattr(Recorder, m)]
        assert not missing, (cls.__name__, missing)
    for kind, make in makers.items():
        rec = make(tmp_path / kind)
        assert isinstance(rec, Recorder), kind
        rec.add_topic("/clock", Clock)
        assert rec.topics == {"/clock": "rosgraph_msgs/msg/Clock"}, kind
        for k in range(10):
            assert rec.write("/clock", Clock(), k + 1)
        rec.hand_over()
        assert rec.counts() == {"/clock": 10} and rec.message_count == 10, kind
        rec.close(timeout=5.0, metadata={"summary": {"k": "v"}})
        assert rec.closed and rec.failure is None and rec.dropped == 0, kind
        assert not rec.write("/clock", Clock(), 99)
        path = tmp_path / "split" / "split_0.mcap" if kind == "split" else \
            tmp_path / f"{kind}.mcap"
        with open(path, "rb") as f:
            reader = make_reader(f)
            md = {m.name: m.metadata for m in reader.iter_metadata()}
            assert sum(1 for _ in reader.iter_messages()) == 10, kind
        assert md["summary"] == {"k": "v"}, kind


def test_storage_options_choose_the_file_writer(tmp_path):
    from starleth_sim.ros.recording import SplitRecorder, StorageOptions, open_file_recorder
    one = StorageOptions(uri=str(tmp_path / "one.mcap"), compression="zstd")
    assert not one.split and one.storage_id == "mcap"
    rec = open_file_recorder(one)
    assert isinstance(rec, McapRecorder)
    rec.close()
    split = StorageOptions(uri=str(tmp_path / "bag.mcap"), max_bagfile_duration_ns=10 ** 9,
                           custom_data={"generator": "test"})
    rec = open_file_recorder(split)
    assert split.split and isinstance(rec, SplitRecorder)
    assert rec.path == str(tmp_path / "bag") and rec.max_duration_ns == 10 ** 9
    rec.close()
    info = yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text())
    assert info["rosbag2_bagfile_information"]["custom_data"] == {"generator": "test"}
    with pytest.raises(ValueError, match="storage_id"):
        StorageOptions(uri="x.db3", storage_id="sqlite3")


def test_open_recorder_is_a_process_else_a_thread_of_this_one(tmp_path, monkeypatch):
    """sim_node's chain: a ProcessRecorder; where no process can be started, one warning
    and a QueuedRecorder over the file's writer; a file that cannot be written: one
    RecordingError naming it, either way."""
    import subprocess

    from starleth_sim.ros.recording import (
        ProcessRecorder,
        QueuedRecorder,
        RecordingError,
        SplitRecorder,
        StorageOptions,
        open_recorder,
    )
    warnings = []
    rec = open_recorder(StorageOptions(uri=str(tmp_path / "p.mcap")), warn=warnings.append)
    assert isinstance(rec, ProcessRecorder) and not warnings
    rec.close()
    with pytest.raises(RecordingError, match=r"^/proc/x.mcap: \[Errno \d+\]"):
        open_recorder(StorageOptions(uri="/proc/x.mcap"), warn=warnings.append)
    assert not warnings

    def no_process(*args, **kwargs):
        raise OSError(11, "Resource temporarily unavailable")

    monkeypatch.setattr(subprocess, "Popen", no_process)
    failures = []
    rec = open_recorder(StorageOptions(uri=str(tmp_path / "q"), max_bagfile_size=1 << 20),
                        on_failure=failures.append, warn=warnings.append)
    assert isinstance(rec, QueuedRecorder) and isinstance(rec.inner, SplitRecorder)
    assert warnings == ["recording in this process (no recording process: [Errno 11] "
                        "Resource temporarily unavailable)"]
    rec.close()
    with pytest.raises(RecordingError, match=r"^/proc/x.mcap: "):
        open_recorder(StorageOptions(uri="/proc/x.mcap"), warn=warnings.append)


@pytest.mark.parametrize("under", ["x.mcap", "sub/x.mcap", "bag_dir"])
def test_a_recording_under_a_file_says_that_the_file_is_not_a_directory(tmp_path, under):
    """record:= under a path whose parent (or an ancestor) is a regular file: one line that
    names that file as not a directory (was '[Errno 17] File exists'), from sim_node's
    recorder (a writer process), a split one and the file writer alike."""
    from starleth_sim.ros.recording import RecordingError, StorageOptions, open_recorder
    blocker = tmp_path / "runs"
    blocker.write_text("a file")
    split = {"max_bagfile_size": 1 << 20} if under == "bag_dir" else {}
    uri = str(blocker / under)
    with pytest.raises(RecordingError) as e:
        open_recorder(StorageOptions(uri=uri, **split))
    assert str(e.value).startswith(f"{uri}: [Errno ")
    assert str(e.value).endswith(f": {blocker} is a file, not a directory"), str(e.value)
    with pytest.raises(RecordingError, match=f"{blocker} is a file, not a directory$"):
        McapRecorder(uri)


@pytest.mark.parametrize("err,words", [
    (28, "No space left on device: no space left where it is written ({d}): free some or "
         "record elsewhere"),
    (30, "Read-only file system: {d} is on a read-only file system"),
    (13, "Permission denied: {d} is not writable"),
    (27, "File too large: the file reached the file-size limit of this process (ulimit -f: "),
    (122, "Disk quota exceeded: the disk quota where it is written ({d}) is used up"),
    (5, "Input/output error: the disk reported an I/O error"),
    (11, "Resource temporarily unavailable"),
])
def test_a_failed_recording_says_the_cause_a_user_can_act_on(tmp_path, err, words):
    from starleth_sim.ros.recording.mcap_sink import failure_cause
    cause = failure_cause(OSError(err, os.strerror(err)), str(tmp_path / "x.mcap"))
    assert cause.startswith(f"[Errno {err}] " + words.format(d=tmp_path)), cause
