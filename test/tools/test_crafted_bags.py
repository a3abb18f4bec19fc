"""Crafted bags into starleth-view, starleth-analyze and starleth-replay: what a bag holds
must never size an allocation beyond what is in the file, and what is in the file is read
within bounds (bag.MAX_RECORD_BYTES, the terrain's MAX_GRID).

Each tool runs in a child process whose address space is limited to 1 GB (`ulimit -v
1000000`; a tool takes 250-350 MB of it reading a small bag), so an allocation sized from
bag content (a frame grid over a time span, windows over a span, a chunk's claimed or
declared uncompressed size, a generated terrain) fails there with a MemoryError and a
traceback instead of passing unnoticed on a large machine. The bags: (a) two valid
messages per topic 2e9 s apart (header stamps and log times); (b) garbage payloads (random
bytes: random stamps and sequence lengths); (c) a valid header followed by a sequence
length of 0xFFFFFFF0; NaN, infinite and absurd values; stamps at the ends of their ranges
and log times beyond int64; compressed chunks whose header or frame claims 1 TiB, one that
truthfully declares 3 GiB (98 KB of zstd) and one that declares 4 MiB of its 3 GiB; replay
metadata that is not what sim_node writes (a zero control period, joint names that are not
JSON, a YAML billion-laughs configuration, an initial state that does not fit, a slope
whose grid would take 1.6 GB). Each gives exit status 1 with one line on stderr, or a
short result with counted warnings, never a traceback."""
from __future__ import annotations

import io
import json
import math
import os
import random
import select
import signal
import struct
import subprocess
import sys
import zlib

import numpy as np
import pytest

pytest.importorskip("rclpy")

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import WrenchStamped
from nav_msgs.msg import Odometry
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState

from starleth_sim.physics.description import STARLETH_JOINT_NAMES as JOINTS
from starleth_sim.ros.recording import McapRecorder, message_definition
from starleth_sim.tools.analysis import analysis
from starleth_sim.tools.analysis import plots as analysis_plots
from starleth_sim.tools.common import bag as bagmod
from starleth_sim.tools.view import frames as view_frames
from starleth_sim.tools.view import view

FEET = ("LF", "RF", "LH", "RH")
WRENCH_TOPICS = tuple(f"/starleth/{f}_foot/wrench" for f in FEET)
SPAN_S = 2_000_000_000                       # two messages this far apart [s]
PERIOD_NS = 2_500_000
MEMORY_LIMIT_KIB = 1_000_000                 # the children's address space (ulimit -v)
TiB = 1 << 40
GiB3 = 3 << 30
#: NaN, infinite and absurd values (and a good one)
BAD_VALUES = (math.nan, math.inf, -math.inf, 1e300, -1.7e308, 0.0)
PROGS = {"view": view.PROG, "analysis": analysis.PROG, "replay": "starleth-replay"}


# -- running the tools in a child with bounded memory -----------------------------------------
#: The tools' server: a child under `ulimit -v` that imports the three tools (and the
#: analysis' matplotlib, about 70 MB of the 1 GB) once, then runs each case in a process of
#: its own forked from it (the same limit, a fresh copy of its memory: a few ms instead of
#: the 0.4 s of a new interpreter importing a tool), and answers each request (a JSON line
#: of cases) with a JSON line of results on its own descriptor (the tools' stdout and stderr
#: are captured per case).
SERVER = r"""
import contextlib, importlib, io, json, os, sys, traceback
tools = {t: importlib.import_module(f"starleth_sim.tools.{t}.{t}")
         for t in ("view", "analysis", "replay")}
tools["analysis"].load_pyplot()      # matplotlib on Agg (0.4 s), as the analysis loads it
answers = os.fdopen(os.dup(1), "w")
os.dup2(2, 1)                        # stray output of the tools' libraries: not the answers

def run(tool, argv):
    o, e = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(o), contextlib.redirect_stderr(e):
        try:
            rc = tools[tool].main(argv)
        except SystemExit as x:
            rc = x.code if isinstance(x.code, int) else 1
        except BaseException:
            traceback.print_exc()
            rc = "traceback"
    return {"rc": rc, "out": o.getvalue(), "err": e.getvalue()}

def forked(tool, argv):
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(r)
        with os.fdopen(w, "w") as f:
            f.write(json.dumps(run(tool, argv)))
        os._exit(0)
    os.close(w)
    with os.fdopen(r) as f:
        text = f.read()
    _, status = os.waitpid(pid, 0)
    return json.loads(text) if text else {"rc": f"died (wait status {status})", "out": "",
                                          "err": ""}

for line in sys.stdin:
    answers.write(json.dumps([forked(t, argv) for t, argv in json.loads(line)]) + "\n")
    answers.flush()
"""
_server = None


def _stop_server(wait=10):
    """The tools' server stopped (its end of input; killed with its processes after `wait`
    seconds, or at once with wait=0)."""
    global _server
    if _server is None:
        return
    _server.stdin.close()
    try:
        _server.wait(timeout=wait)
    except subprocess.TimeoutExpired:
        os.killpg(_server.pid, signal.SIGKILL)
        _server.wait()
    _server = None


@pytest.fixture(scope="module", autouse=True)
def tools_server():
    """The tools' server of this module's tests (run_tools starts it), stopped after them."""
    try:
        yield
    finally:
        _stop_server()


def run_tools(*cases, timeout=600):
    """[(tool, argv)] run by their main(), each in its own process forked from the tools'
    server, whose address space is limited to MEMORY_LIMIT_KIB (`ulimit -v`):
    [{'rc', 'out', 'err'}]. A server that does not answer within `timeout` is killed (the
    next call starts another)."""
    global _server
    if _server is None:
        _server = subprocess.Popen(
            ["bash", "-c", f'ulimit -v {MEMORY_LIMIT_KIB} && exec "$0" -c "$1"',
             sys.executable, SERVER], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
            start_new_session=True)
    _server.stdin.write(json.dumps([(t, [str(a) for a in argv]) for t, argv in cases]) + "\n")
    _server.stdin.flush()
    ready, _, _ = select.select([_server.stdout], [], [], timeout)
    if not ready or _server.poll() is not None:
        code = _server.poll()
        _stop_server(wait=0)
        pytest.fail(f"the tools' server: no answer in {timeout} s (exit status {code})")
    return json.loads(_server.stdout.readline())


def assert_one_line_error(result, tool, *expect):
    """Exit status 1 with one 'prog: error: ...' line (warnings may come before it), no
    traceback, no failed allocation; the line holds each of `expect`."""
    err = result["err"]
    assert result["rc"] == 1, (result["rc"], err[-3000:])
    assert "Traceback" not in err and "MemoryError" not in err, err[-3000:]
    assert "allocate" not in err, err[-3000:]
    errors = [ln for ln in err.splitlines() if ln.startswith(f"{PROGS[tool]}: error:")]
    assert len(errors) == 1, err[-3000:]
    others = [ln for ln in err.splitlines()
              if ln.strip() and not ln.startswith(f"{PROGS[tool]}: ")]
    assert not others, err[-3000:]
    for text in expect:
        assert text in errors[0], errors[0]
    return errors[0]


def assert_ok(result, tool):
    err = result["err"]
    assert result["rc"] == 0, (result["rc"], err[-3000:])
    assert "Traceback" not in err and "MemoryError" not in err, err[-3000:]
    assert f"{PROGS[tool]}: error" not in err, err[-3000:]
    return err


# -- crafting bags ----------------------------------------------------------------------------
def stamp(sec=0, nanosec=0):
    return Time(sec=sec, nanosec=nanosec)


def joint_state(st, value=0.1, names=JOINTS):
    m = JointState(name=list(names), position=[value] * len(names),
                   velocity=[0.0] * len(names), effort=[value] * len(names))
    m.header.stamp = st
    return m


def odometry(st, value=0.0):
    o = Odometry()
    o.header.stamp, o.header.frame_id, o.child_frame_id = st, "world", "base"
    p, tl, ta = o.pose.pose.position, o.twist.twist.linear, o.twist.twist.angular
    for axis in "xyz":
        for vec in (p, tl, ta):
            setattr(vec, axis, value)
    p.z = 0.5 if value == 0.0 else value
    o.pose.pose.orientation.w = 1.0 if value == 0.0 else value
    return o


def wrench(st, value=50.0):
    w = WrenchStamped()
    w.header.stamp, w.header.frame_id = st, "world"
    w.wrench.force.x, w.wrench.force.z = 0.0 if value == 50.0 else value, value
    return w


def solver(st, value=10.0):
    d = DiagnosticArray(status=[DiagnosticStatus(
        name="starleth_sim: solver",
        values=[KeyValue(key=k, value=repr(value))
                for k in ("iterations", "residual", "step_time")])])
    d.header.stamp = st
    return d


def recorder(path, solver_topic=False, metadata=None):
    rec = McapRecorder(str(path))
    rec.add_topic("/joint_states", JointState)
    rec.add_topic("/starleth/base_state", Odometry)
    for t in WRENCH_TOPICS:
        rec.add_topic(t, WrenchStamped)
    if solver_topic:
        rec.add_topic("/starleth/solver", DiagnosticArray)
    if metadata:
        rec.add_metadata("starleth_sim", metadata)
    return rec


def write_state(rec, st, log_ns, pub_ns=None, value=None, solver_topic=False):
    """One message on every state topic stamped st (value: that number in every field)."""
    kw = {} if value is None else {"value": value}
    rec.write("/joint_states", joint_state(st, **kw), log_ns, publish_time_ns=pub_ns)
    rec.write("/starleth/base_state", odometry(st, **kw), log_ns, publish_time_ns=pub_ns)
    for t in WRENCH_TOPICS:
        rec.write(t, wrench(st, **kw), log_ns, publish_time_ns=pub_ns)
    if solver_topic:
        rec.write("/starleth/solver", solver(st, **kw), log_ns, publish_time_ns=pub_ns)


def span_bag(path, metadata=None):
    """(a) Two valid messages per topic, 2e9 s apart in header stamps and log times (the
    publish times differ from them: a wall clock, so that the real-time factor is drawn)."""
    rec = recorder(path, metadata=metadata)
    for sec in (0, SPAN_S):
        write_state(rec, stamp(sec), sec * 10 ** 9, pub_ns=sec * 10 ** 9 // 2)
    rec.close()
    return path


def garbage_bag(path, topics=None, seed=1, n=20, metadata=None):
    """(b) Random bytes on the tools' topics (16..200 bytes: random stamps, random sequence
    lengths), log times 2.5 ms apart."""
    rng = random.Random(seed)
    rec = recorder(path, metadata=metadata)
    for k in range(n):
        for t in topics or ("/joint_states", "/starleth/base_state", *WRENCH_TOPICS):
            rec.write(t, bytes(rng.getrandbits(8) for _ in range(rng.randint(16, 200))),
                      k * PERIOD_NS)
    rec.close()
    return path


def huge_sequence(msg) -> bytes:
    """The CDR of msg's header (it comes first) followed by a sequence length of 0xFFFFFFF0
    and 64 zero bytes: JointState.name, DiagnosticArray.status."""
    head = serialize_message(msg.header)
    pad = b"\0" * ((4 - (len(head) - 4) % 4) % 4)
    return head + pad + struct.pack("<I", 0xFFFFFFF0) + b"\0" * 64


def huge_sequence_bag(path, metadata=None):
    """(c) /joint_states (and /starleth/solver) messages whose first sequence claims
    0xFFFFFFF0 elements; the other topics valid."""
    rec = recorder(path, solver_topic=True, metadata=metadata)
    for k in range(3):
        st = stamp(0, k * PERIOD_NS)
        rec.write("/joint_states", huge_sequence(joint_state(st)), k * PERIOD_NS)
        rec.write("/starleth/solver", huge_sequence(solver(st)), k * PERIOD_NS)
        rec.write("/starleth/base_state", odometry(st), k * PERIOD_NS)
        for t in WRENCH_TOPICS:
            rec.write(t, wrench(st), k * PERIOD_NS)
    rec.close()
    return path


def values_bag(path):
    """NaN, infinite and absurd values in every field, one message per value."""
    rec = recorder(path, solver_topic=True)
    for k, v in enumerate(BAD_VALUES):
        write_state(rec, stamp(k), k * 10 ** 9, pub_ns=k * 10 ** 8, value=v, solver_topic=True)
    rec.close()
    return path


def times_bag(path):
    """Header stamps at the ends of their ranges (sec -2**31 and 2**31 - 1, nanosec
    2**32 - 1) and log/publish times up to 2**64 - 1 (beyond the int64 of ROS 2)."""
    rec = recorder(path, solver_topic=True)
    stamps = [(-2 ** 31, 0), (2 ** 31 - 1, 2 ** 32 - 1), (0, 0), (-2 ** 31, 2 ** 32 - 1),
              (5, 5), (2 ** 31 - 1, 0)]
    logs = [0, 2 ** 63 - 1, 2 ** 64 - 1, 1, 2 ** 63, 7]
    for (sec, ns), log in zip(stamps, logs, strict=True):
        write_state(rec, stamp(sec, ns), log, solver_topic=True)
    rec.close()
    return path


# -- MCAP files written record by record (forged chunks) ---------------------------------------
def _record(opcode, body):
    return struct.pack("<BQ", opcode, len(body)) + body


def _string(s):
    b = s.encode()
    return struct.pack("<I", len(b)) + b


def _message(channel, seq, log_ns, data):
    return _record(0x05, struct.pack("<HIQQ", channel, seq, log_ns, log_ns) + data)


def _chunk(records, compression="", uncompressed_size=None, compressed=None):
    data = compressed if compressed is not None else records
    size = len(records) if uncompressed_size is None else uncompressed_size
    return _record(0x06, struct.pack("<QQQI", 0, 0, size, 0) + _string(compression)
                   + struct.pack("<Q", len(data)) + data)


def raw_bag(path, chunks):
    """An MCAP file: header, the schemas and channels of /joint_states and
    /starleth/base_state, `chunks` (bytes of Chunk records), DataEnd and Footer without
    CRCs (0: not checked)."""
    out = bytearray(bagmod.MCAP_MAGIC)
    out += _record(0x01, _string("ros2") + _string("test_crafted_bags"))
    for sid, (typ, topic) in enumerate((("sensor_msgs/msg/JointState", "/joint_states"),
                                        ("nav_msgs/msg/Odometry", "/starleth/base_state")),
                                       start=1):
        d = message_definition(typ).encode()
        out += _record(0x03, struct.pack("<H", sid) + _string(typ) + _string("ros2msg")
                       + struct.pack("<I", len(d)) + d)
        out += _record(0x04, struct.pack("<HH", sid, sid) + _string(topic) + _string("cdr")
                       + struct.pack("<I", 0))
    for c in chunks:
        out += c
    out += _record(0x0F, struct.pack("<I", 0))
    out += _record(0x02, struct.pack("<QQI", 0, 0, 0))
    out += bagmod.MCAP_MAGIC
    path.write_bytes(bytes(out))
    return path


def state_records(k0, n):
    """Message records of n valid control steps from step k0."""
    recs = b""
    for k in range(k0, k0 + n):
        st = stamp(0, k * PERIOD_NS)
        recs += _message(1, k, k * PERIOD_NS, serialize_message(joint_state(st)))
        recs += _message(2, k, k * PERIOD_NS, serialize_message(odometry(st)))
    return recs


def _xxh32(data: bytes, seed=0) -> int:
    """xxHash32 (the LZ4 frame's header checksum)."""
    p1, p2, p3, p4, p5, m = 2654435761, 2246822519, 3266489917, 668265263, 374761393, 0xFFFFFFFF

    def rotl(x, r):
        return ((x << r) | (x >> (32 - r))) & m
    n, i = len(data), 0
    if n >= 16:
        v = [(seed + p1 + p2) & m, (seed + p2) & m, seed, (seed - p1) & m]
        while i + 16 <= n:
            for j in range(4):
                v[j] = (rotl((v[j] + struct.unpack_from("<I", data, i + 4 * j)[0] * p2) & m, 13)
                        * p1) & m
            i += 16
        h = (rotl(v[0], 1) + rotl(v[1], 7) + rotl(v[2], 12) + rotl(v[3], 18)) & m
    else:
        h = (seed + p5) & m
    h = (h + n) & m
    while i + 4 <= n:
        h = (rotl((h + struct.unpack_from("<I", data, i)[0] * p3) & m, 17) * p4) & m
        i += 4
    while i < n:
        h = (rotl((h + data[i] * p5) & m, 11) * p1) & m
        i += 1
    h ^= h >> 15
    h = (h * p2) & m
    h ^= h >> 13
    h = (h * p3) & m
    return h ^ (h >> 16)


def zstd_claiming(records, claimed):
    """A zstd chunk of records without the frame's content size, whose chunk header claims
    `claimed` bytes (mcap's reader allocates that much)."""
    import zstandard
    frame = zstandard.ZstdCompressor(write_content_size=False).compress(records)
    return _chunk(records, "zstd", uncompressed_size=claimed, compressed=frame)


def lz4_claiming(records, claimed):
    """An lz4 chunk of records whose frame header claims `claimed` bytes of content (a valid
    header checksum); the chunk header has the true size."""
    import lz4.frame
    frame = bytearray(lz4.frame.compress(records, store_size=True, content_checksum=False))
    assert frame[4] & 0x08                                  # FLG: content size present
    frame[6:14] = struct.pack("<Q", claimed)
    frame[14] = (_xxh32(bytes(frame[4:14])) >> 8) & 0xFF
    return _chunk(records, "lz4", compressed=bytes(frame))


def zstd_zeros(n):
    """A zstd frame of n zero bytes (records of opcode 0 and length 0, which readers skip)
    whose frame header says n: 98 KB for 3 GiB, made in about a second."""
    import zstandard
    out = io.BytesIO()
    zeros = bytes(1 << 24)
    with zstandard.ZstdCompressor().stream_writer(out, closefd=False, size=n) as w:
        for start in range(0, n, len(zeros)):
            w.write(zeros[:min(len(zeros), n - start)])
    return out.getvalue()


def honest_3gib(frame):
    """A zstd chunk of 3 GiB of records (frame: zstd_zeros(3 GiB)) that says so."""
    return _chunk(b"", "zstd", uncompressed_size=GiB3, compressed=frame)


def under_declared_3gib(frame):
    """The same chunk whose header says 4 MiB: its data decompresses to more."""
    return _chunk(b"", "zstd", uncompressed_size=4 << 20, compressed=frame)


def slope_config(md, **slope):
    """The physics configuration of the replay metadata `md` with a slope terrain."""
    import yaml
    cfg = yaml.safe_load(md["physics_config"])
    cfg["terrain"]["slope"] = dict({"angle": 10.0}, **slope)
    return yaml.safe_dump(cfg, sort_keys=False)


# -- replay metadata ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def replay_md():
    """The starleth_sim metadata record sim_node writes (physics configuration, initial
    state, joint names, control period) for HmJ, and the joint names."""
    import yaml

    from starleth_sim.physics.simulator import Simulator
    from starleth_sim.ros.state_io import initial_state_record
    sim = Simulator.from_preset("HmJ")
    sim.reset()
    md = {"physics_config": yaml.safe_dump(sim.config.to_dict(), sort_keys=False),
          "initial_state": json.dumps(initial_state_record(sim, sim.q, sim.u)),
          "joint_names": json.dumps(list(sim.joint_names)),
          "control_period": repr(sim.control_period), "stamp_period_ns": str(PERIOD_NS),
          "namespace": "/"}
    return md, list(sim.joint_names)


def replay_bag(path, md, names, steps=4, value=0.1, **override):
    """A bag as sim_node records it for starleth-replay: the metadata (with `override`),
    steps joint states and base states 2.5 ms apart (effort = value from step 1)."""
    rec = recorder(path, metadata=dict(md, **override))
    for k in range(steps):
        st = stamp(0, k * PERIOD_NS)
        rec.write("/joint_states", joint_state(st, value if k else 0.0, names), k * PERIOD_NS)
        rec.write("/starleth/base_state", odometry(st), k * PERIOD_NS)
    rec.close()
    return path


def applied_bag(path, md, names, steps=4, bad=None):
    """replay_bag with starleth/applied_torque (1 physics step x 12 joints at t_1..): bad
    "nan": a NaN torque at step 2; "short": 11 values at step 2; "missing": no message at
    step 2."""
    from std_msgs.msg import Float64MultiArray, MultiArrayDimension
    topic = "/starleth/applied_torque"
    rec = recorder(path, metadata=dict(md, applied_torque_topic=topic))
    rec.add_topic(topic, Float64MultiArray)
    for k in range(steps):
        st = stamp(0, k * PERIOD_NS)
        rec.write("/joint_states", joint_state(st, 0.1 if k else 0.0, names), k * PERIOD_NS)
        rec.write("/starleth/base_state", odometry(st), k * PERIOD_NS)
        if k == 0 or (k == 2 and bad == "missing"):
            continue
        data = [0.1] * (11 if k == 2 and bad == "short" else 12)
        if k == 2 and bad == "nan":
            data[3] = math.nan
        m = Float64MultiArray(data=data)
        m.layout.dim = [MultiArrayDimension(label="physics_steps", size=1, stride=12),
                        MultiArrayDimension(label="joints", size=12, stride=12)]
        rec.write(topic, m, k * PERIOD_NS)
    rec.close()
    return path


def billion_laughs():
    """A physics configuration of a few hundred bytes whose aliases (anchored in its free
    'paper' mapping) make the ground normal a nested list of 10**9 numbers."""
    lines = ["paper:", "  a0: &a0 [1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]"]
    for i in range(1, 9):
        lines.append(f"  a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]")
    return "\n".join(lines) + "\nground:\n  normal: *a8\n"


# -- the frame grid and the windows ------------------------------------------------------------
def grid_frames(t_ns, fps):
    """select_frames as first written: every grid time enumerated (the reference)."""
    span = (t_ns[-1] - t_ns[0]) * 1e-9
    k = np.arange(int(math.floor(span * fps + 1e-9)) + 1)
    grid = t_ns[0] + np.round(k * (1e9 / fps)).astype(np.int64)
    idx = np.searchsorted(t_ns, grid, side="right") - 1
    return np.unique(np.concatenate([np.clip(idx, 0, t_ns.size - 1), [t_ns.size - 1]]))


def test_select_frames_is_the_grid_without_enumerating_it():
    """The same frames as the grid definition (random stamps, repeated stamps, rates at and
    above the sample rate), and per sample: two samples 2e9 s apart are 2 frames."""
    rng = np.random.default_rng(0)
    for trial in range(1500):
        n = int(rng.integers(1, 200))
        kind = trial % 5
        fps = float(rng.choice([1, 7, 24, 30, 50, 60, 333.3, 400, 1000, 1e4]))
        if kind == 0:
            t = np.cumsum(rng.integers(0, 5_000_000, n))
        elif kind == 1:
            t = np.arange(n) * PERIOD_NS + int(rng.integers(-10 ** 12, 10 ** 12))
        elif kind == 2:
            t = np.sort(rng.integers(0, 3 * 10 ** 9, n))
        elif kind == 3:
            t = np.cumsum(rng.choice([0, 1, PERIOD_NS, 3_333_333, 20_000_000], n)) + 17 * 10 ** 17
        else:   # nanoseconds apart, at and above a grid time per nanosecond
            t = np.cumsum(rng.integers(0, 5, n))
            fps = float(rng.choice([3e8, 1e9, 3e9]))
        t = t.astype(np.int64)
        assert np.array_equal(view_frames.select_frames(t, fps), grid_frames(t, fps)), (kind, fps)
    far = np.array([0, SPAN_S * 10 ** 9], dtype=np.int64)
    assert view_frames.select_frames(far, 50.0).tolist() == [0, 1]
    ends = np.array([-2 ** 31 * 10 ** 9, 0, 1, (2 ** 31 - 1) * 10 ** 9 + 2 ** 32 - 1],
                    dtype=np.int64)
    assert view_frames.select_frames(ends, 1e12).tolist() == [0, 1, 2, 3]
    assert view_frames.select_frames(ends, 1e-12).tolist() == [0, 3]


def test_windowed_rate_is_bounded():
    """Two samples 2e9 s apart with 1 ms windows: at most MAX_RTF_WINDOWS windows."""
    t = np.array([0.0, float(SPAN_S)])
    tc, r = analysis_plots.windowed_rate(t, t, t / 2, 1e-3)
    assert 1 <= tc.size <= analysis_plots.MAX_RTF_WINDOWS and np.allclose(r, 2.0)


def test_chunk_records_hold_what_the_data_decompresses_to():
    """decompress_chunk: the records of good zstd and lz4 chunks; a chunk claiming 1 TiB
    (chunk header, or lz4 frame header) or more than its data holds is a ValueError, not an
    allocation."""
    from mcap.records import Chunk
    recs = state_records(0, 3)
    import lz4.frame
    import zstandard
    for comp, data in (("zstd", zstandard.compress(recs)), ("lz4", lz4.frame.compress(recs)),
                       ("", recs)):
        c = Chunk(compression=comp, data=data, message_start_time=0, message_end_time=0,
                  uncompressed_crc=zlib.crc32(recs), uncompressed_size=len(recs))
        assert bagmod.decompress_chunk(c) == recs
        assert len(list(bagmod.chunk_records(c))) == 6
    frame = zstandard.ZstdCompressor(write_content_size=False).compress(recs)
    for claimed, match in ((TiB, "declares 1099511627776 bytes of records, more than this "
                                 "reader takes"),
                           (2 * len(recs), f"decompresses to {len(recs)} bytes, its header "
                                           f"says {2 * len(recs)}")):
        c = Chunk(compression="zstd", data=frame, message_start_time=0, message_end_time=0,
                  uncompressed_crc=0, uncompressed_size=claimed)
        with pytest.raises(ValueError, match=match):
            bagmod.decompress_chunk(c)
    forged = lz4_claiming(recs, TiB)
    f = io.BytesIO(bytes(forged))
    f.seek(9)
    from mcap.data_stream import ReadDataStream
    c = Chunk.read(ReadDataStream(f))
    with pytest.raises(ValueError, match="lz4"):
        bagmod.decompress_chunk(c)


def test_records_and_what_is_kept_are_bounded(tmp_path, monkeypatch):
    """A record longer than MAX_RECORD_BYTES is damage (salvage: read up to it); metadata
    and attachments beyond MAX_KEPT_BYTES in all are left out with one warning naming
    them (the bounds made small here: the same code as at 64 MiB)."""
    rec = recorder(tmp_path / "b.mcap", metadata={"physics_config": "x" * 3000})
    for k in range(3):
        rec.add_metadata(f"extra{k}", {"data": "y" * 3000})
    write_state(rec, stamp(0), 0)
    write_state(rec, stamp(0, PERIOD_NS), PERIOD_NS)
    rec.add_attachment("big.bin", "application/octet-stream", b"z" * 20_000)
    rec.close()
    monkeypatch.setattr(bagmod, "MAX_KEPT_BYTES", 7000)
    warnings = []
    bag = bagmod.read_messages(str(tmp_path / "b.mcap"), lambda _topic, _type: True,
                               on_warning=warnings.append)
    assert set(bag.metadata) == {"starleth_sim", "extra0"} and not bag.attachments
    assert bag.kept_bytes <= 7000 and bag.counts["/joint_states"] == 2
    assert len(warnings) == 1 and "4 metadata record(s) or attachment(s) left out " \
        "('extra1', 'extra2', 'big.bin', 'rosbag2'): more than 7000 bytes of them" in warnings[0]
    monkeypatch.setattr(bagmod, "MAX_RECORD_BYTES", 10_000)
    with pytest.raises(bagmod.BagError, match="ATTACHMENT record has length 20"):
        bagmod.read_messages(str(tmp_path / "b.mcap"), lambda _topic, _type: True)
    bag = bagmod.read_messages(str(tmp_path / "b.mcap"), lambda _topic, _type: True, salvage=True,
                               on_warning=warnings.append)
    assert bag.truncated and any("ATTACHMENT record has length 20" in w for w in warnings)


# -- the tools on crafted bags --------------------------------------------------------------------
@pytest.fixture(scope="module")
def bags(tmp_path_factory, zeros_3gib):
    d = tmp_path_factory.mktemp("crafted")
    recs_ok = state_records(0, 4)
    return {
        "span": span_bag(d / "span.mcap"),
        "garbage": garbage_bag(d / "garbage.mcap"),
        "huge_sequence": huge_sequence_bag(d / "huge_sequence.mcap"),
        "values": values_bag(d / "values.mcap"),
        "times": times_bag(d / "times.mcap"),
        "zstd_1tib": raw_bag(d / "zstd_1tib.mcap", [_chunk(recs_ok),
                                                    zstd_claiming(state_records(4, 4), TiB)]),
        "lz4_1tib": raw_bag(d / "lz4_1tib.mcap", [_chunk(recs_ok),
                                                  lz4_claiming(state_records(4, 4), TiB)]),
        "zstd_3gib": raw_bag(d / "zstd_3gib.mcap", [_chunk(recs_ok), honest_3gib(zeros_3gib)]),
        "zstd_3gib_under": raw_bag(d / "zstd_3gib_under.mcap",
                                   [_chunk(recs_ok), under_declared_3gib(zeros_3gib)]),
    }


@pytest.fixture(scope="module")
def zeros_3gib():
    return zstd_zeros(GiB3)


def page_data(path):
    import re
    m = re.search(r'<script type="application/json" id="replay-data">(.*?)</script>',
                  path.read_text(encoding="utf-8"), re.S)
    return json.loads(m.group(1))


def test_view_span(bags, tmp_path):
    """(a) Two samples 2e9 s apart: 2 frames (was 1e11 grid times: 745 GiB)."""
    r, = run_tools(("view", [bags["span"], "-o", tmp_path / "p.html"]))
    assert_ok(r, "view")
    assert "2 frames at 50 fps of 2 samples, 2000000000.00 s" in r["out"]


@pytest.mark.parametrize("case", ["garbage", "huge_sequence"])
def test_view_garbage(bags, tmp_path, case):
    """(b) Random payloads (random stamps: was 1.56 TiB of grid), (c) a sequence length of
    0xFFFFFFF0: one line naming the topic."""
    r, = run_tools(("view", [bags[case], "-o", tmp_path / "p.html"]))
    assert_one_line_error(r, "view", "/joint_states")


def test_view_values(bags, tmp_path):
    """NaN, infinite and absurd values: drawn with the previous value, counted; the page
    holds finite numbers only (was a ValueError from the JSON writer)."""
    r, = run_tools(("view", [bags["values"], "-o", tmp_path / "p.html"]))
    err = assert_ok(r, "view")
    for topic in ("/joint_states", "/starleth/base_state", *WRENCH_TOPICS):
        assert f"5 message(s) on {topic} hold NaN, infinite or absurd values" in err, err
    data = page_data(tmp_path / "p.html")
    robot, = data["robots"]
    assert all(math.isfinite(x) for x in robot["poses"] + robot["arrows"])


def test_view_times(bags, tmp_path):
    """Stamps at the ends of their range; log times beyond int64 skipped, counted."""
    r, = run_tools(("view", [bags["times"], "-o", tmp_path / "p.html"]))
    err = assert_ok(r, "view")
    assert "2 message(s) on /joint_states could not be read (log or publish time beyond" in err
    assert "4 frames" in r["out"]


@pytest.mark.parametrize("case", ["zstd_1tib", "lz4_1tib", "zstd_3gib", "zstd_3gib_under"])
def test_view_forged_chunk(bags, tmp_path, case):
    """A compressed chunk claiming 1 TiB (was an attempt to allocate it), truthfully
    declaring 3 GiB (was 6.4 GB and over a minute), or declaring 4 MiB of its 3 GiB: one
    line; with --salvage, the page of the chunk before it."""
    r, s = run_tools(("view", [bags[case], "-o", tmp_path / "p.html"]),
                     ("view", [bags[case], "-o", tmp_path / "s.html", "--salvage"]))
    assert_one_line_error(r, "view", "corrupt MCAP file", "compressed chunk",
                          *CHUNK_WORDS.get(case, ()))
    err = assert_ok(s, "view")
    assert "of 4 samples" in s["out"] and "reading stopped" in err


def test_view_unreadable_motion(tmp_path):
    """Joint states whose log times are all beyond int64: one line (not an IndexError)."""
    rec = recorder(tmp_path / "late.mcap")
    for k in range(3):
        write_state(rec, stamp(0, k * PERIOD_NS), 2 ** 64 - 1 - k)
    rec.close()
    r, = run_tools(("view", [tmp_path / "late.mcap"]))
    assert_one_line_error(r, "view", "none of the 3 message(s) on /joint_states")


def test_view_billion_laughs_ground(tmp_path):
    """A physics configuration whose ground normal is a YAML billion laughs (10**9 numbers
    from a few hundred bytes): the default ground (was 8 GB for numpy)."""
    rec = recorder(tmp_path / "laughs.mcap", metadata={"physics_config": billion_laughs()})
    for k in range(3):
        write_state(rec, stamp(0, k * PERIOD_NS), k * PERIOD_NS)
    rec.close()
    r, = run_tools(("view", [tmp_path / "laughs.mcap", "-o", tmp_path / "p.html"]))
    assert_ok(r, "view")
    assert page_data(tmp_path / "p.html")["ground"]["normal"] == [0.0, 0.0, 1.0]


def test_view_slope_beyond_the_grid_bound(replay_md, tmp_path):
    """A recorded slope whose grid would be 10003 x 20001 points (1.6 GB; the view took
    1.67 GB): not drawn, with a warning naming the bound; the page of the motion."""
    md, names = replay_md
    bag = replay_bag(tmp_path / "b.mcap", md, names,
                     physics_config=slope_config(md, length=1e-4))
    r, = run_tools(("view", [bag, "-o", tmp_path / "p.html"]))
    err = assert_ok(r, "view")
    assert "the recorded terrain is not valid, not drawn: terrain.slope: its heightfield " \
           "would be 10003 x 20001 points" in err, err
    assert "at most 1024 a side" in err and "4 samples" in r["out"]


def test_analyze_span(bags, tmp_path):
    """(a) Two samples 2e9 s apart: a short result (the real-time factor's windows were
    2e9 of 1 s: 14.9 GiB)."""
    r, = run_tools(("analysis", [bags["span"], "--out", tmp_path]))
    assert_ok(r, "analysis")
    assert "(2000000000.000 s; 2 joint states" in r["out"]
    assert (tmp_path / "real_time_factor.png").exists()


def test_analyze_garbage(bags, tmp_path):
    """(b) Random payloads on every topic: counted, then one line (was 'no messages
    between the start and the end (--tmin/--tmax ...)' without --tmin/--tmax)."""
    r, = run_tools(("analysis", [bags["garbage"], "--out", tmp_path]))
    assert_one_line_error(r, "analysis", "none of the messages")
    assert "20 message(s) on /joint_states could not be read" in r["err"]


def test_analyze_huge_sequence(bags, tmp_path):
    """(c) Sequence lengths of 0xFFFFFFF0 in /joint_states and /starleth/solver: those
    messages skipped, counted; the rest analysed (its real-time factor plot was a
    ValueError: max() of no joint or solver series)."""
    r, = run_tools(("analysis", [bags["huge_sequence"], "--out", tmp_path]))
    err = assert_ok(r, "analysis")
    assert "3 message(s) on /joint_states could not be read" in err
    assert "3 message(s) on /starleth/solver could not be read" in err


def test_analyze_values(bags, tmp_path):
    """NaN, infinite and absurd values: left out, counted (were plotted into a
    LinAlgError)."""
    r, = run_tools(("analysis", [bags["values"], "--out", tmp_path]))
    err = assert_ok(r, "analysis")
    for topic in ("/starleth/base_state", *WRENCH_TOPICS):
        assert f"5 message(s) on {topic} hold NaN, infinite or absurd values" in err, err
    assert "4 message(s) on /joint_states hold NaN, infinite or absurd values" in err


def test_analyze_times(bags, tmp_path):
    """Stamps at the ends of their range; log times beyond int64 skipped, counted (were
    an OverflowError into int64)."""
    r, = run_tools(("analysis", [bags["times"], "--out", tmp_path]))
    err = assert_ok(r, "analysis")
    assert "2 message(s) on /joint_states could not be read (log or publish time" in err


@pytest.mark.parametrize("case", ["zstd_1tib", "lz4_1tib", "zstd_3gib", "zstd_3gib_under"])
def test_analyze_forged_chunk(bags, tmp_path, case):
    r, = run_tools(("analysis", [bags[case], "--out", tmp_path]))
    assert_one_line_error(r, "analysis", "corrupt MCAP file", "compressed chunk",
                          *CHUNK_WORDS.get(case, ()))


#: what the error line says of a chunk of 3 GiB
CHUNK_WORDS = {"zstd_3gib": ("declares 3221225472 bytes of records, more than this reader "
                             "takes (64 MiB)",),
               "zstd_3gib_under": ("decompresses to more than 5242880 bytes, its header says "
                                   "4194304",)}


def _ragged(path, md, names):
    rec = recorder(path, metadata=md)
    for k in range(3):
        st = stamp(0, k * PERIOD_NS)
        m = joint_state(st, names=names)
        m.effort = [0.1] * (12 + k)
        rec.write("/joint_states", m, k * PERIOD_NS)
        rec.write("/starleth/base_state", odometry(st), k * PERIOD_NS)
    rec.close()
    return path


#: case -> (the bag, given (tmp_path, metadata, joint names); what the error line says)
REPLAY_CASES = {
    "span": (lambda d, md, _names: span_bag(d / "b.mcap", metadata=md), ("step 1", "missing")),
    "span_period": (lambda d, md, _names: span_bag(d / "b.mcap", metadata=dict(
        md, stamp_period_ns=str(SPAN_S * 10 ** 9), control_period=repr(float(SPAN_S)))),
        ("control period",)),
    "garbage": (lambda d, md, _names: garbage_bag(d / "b.mcap", metadata=md),
                ("no messages on /joint_states",)),
    "huge_sequence": (lambda d, md, _names: huge_sequence_bag(d / "b.mcap", metadata=md),
                      ("no messages on /joint_states",)),
    "nan_torque": (lambda d, md, names: replay_bag(d / "b.mcap", md, names, value=math.nan),
                   ("effort of step 1", "NaN or infinite")),
    "ragged": (lambda d, md, names: _ragged(d / "b.mcap", md, names),
               ("step 1 holds 13 effort values",)),
    "period0": (lambda d, md, names: replay_bag(d / "b.mcap", md, names, stamp_period_ns="0"),
                ("control period is not a positive number",)),
    "period_text": (lambda d, md, names: replay_bag(
        d / "b.mcap", md, names, stamp_period_ns="abc", control_period="nan"),
        ("control period is not a positive number",)),
    "names": (lambda d, md, names: replay_bag(d / "b.mcap", md, names, joint_names="[[[["),
              ("joint_names is not valid JSON",)),
    "laughs": (lambda d, md, names: replay_bag(d / "b.mcap", md, names,
                                               physics_config=billion_laughs()),
               ("aliases expand it",)),
    "initial": (lambda d, md, names: replay_bag(d / "b.mcap", md, names, initial_state=json.dumps(
        {"coordinates": "minimal", "q": [1.0, 2.0], "u": "x"})),
        ("initial_state does not fit",)),
    "applied_nan": (lambda d, md, names: applied_bag(d / "b.mcap", md, names, bad="nan"),
                    ("/starleth/applied_torque", "t = 0.0050 s", "not applied torques")),
    "applied_short": (lambda d, md, names: applied_bag(d / "b.mcap", md, names, bad="short"),
                      ("holds 11 values",)),
    "applied_missing": (lambda d, md, names: applied_bag(d / "b.mcap", md, names,
                                                         bad="missing"),
                        ("no applied torque for step 1 -> 2",)),
    "zstd_1tib": (lambda d, _md, _names: raw_bag(d / "b.mcap", [
        zstd_claiming(state_records(0, 4), TiB)]), ("compressed chunk",)),
    "zstd_3gib": (lambda d, _md, _names: raw_bag(d / "b.mcap", [
        _chunk(state_records(0, 4)), honest_3gib(zstd_zeros(GiB3))]), CHUNK_WORDS["zstd_3gib"]),
    "slope": (lambda d, md, names: replay_bag(
        d / "b.mcap", md, names, physics_config=slope_config(md, length=1e-4)),
        ("terrain.slope: its heightfield would be 10003 x 20001 points", "at most 1024")),
    "slope_in_range": (lambda d, md, names: replay_bag(
        d / "b.mcap", md, names, physics_config=slope_config(md, length=100, top=100,
                                                            width=100)),
        ("terrain.slope: its heightfield would be 6001 x 2001 points",)),
}


@pytest.mark.parametrize("case", list(REPLAY_CASES))
def test_replay(replay_md, tmp_path, case):
    """(a) Two states 2e9 s apart (also with a 2e9 s control period recorded); (b) garbage;
    (c) a sequence length of 0xFFFFFFF0; NaN torques; ragged joint states; a zero or
    unreadable control period; joint names that are not JSON; a YAML billion-laughs
    configuration; an initial state that does not fit; a chunk claiming 1 TiB or truthfully
    declaring 3 GiB; a slope whose grid would be 4.8 GB (was a MemoryError at 3.2 GB) or
    6001 x 2001 points: one line each."""
    make, expect = REPLAY_CASES[case]
    md, names = replay_md
    r, = run_tools(("replay", [make(tmp_path, md, names), "--no-plots"]))
    assert_one_line_error(r, "replay", *expect)


def test_replay_good_bag_still_runs(replay_md, tmp_path):
    """A small bag with the metadata sim_node writes replays (not bit-identical: its states
    are made up) without an error line."""
    md, names = replay_md
    r, = run_tools(("replay", [replay_bag(tmp_path / "b.mcap", md, names), "--no-plots"]))
    assert r["rc"] == 3, r["err"][-3000:]
    assert "Traceback" not in r["err"] and "error" not in r["err"], r["err"][-3000:]
    assert "NOT bit-identical" in r["out"]


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_compressed_bags_read_as_uncompressed_ones(tmp_path, compression):
    """The chunks decompressed in bounded pieces hold what mcap's own reader gives: the same
    messages, log times and counts as the uncompressed bag, over many small chunks. (Both
    bags get the same CDR bytes: rclpy leaves padding bytes uninitialised, so serialising
    the messages once per bag could make the two bags' messages differ there.)"""
    from mcap.reader import make_reader
    messages = []
    for k in range(300):
        st = stamp(0, k * PERIOD_NS)
        messages.append(("/joint_states", serialize_message(joint_state(st, 0.001 * k)),
                         k * PERIOD_NS))
        messages.append(("/starleth/base_state", serialize_message(odometry(st, 0.01 * k)),
                         k * PERIOD_NS))
    paths = {}
    for comp in ("none", compression):
        paths[comp] = tmp_path / f"{comp}.mcap"
        rec = McapRecorder(str(paths[comp]), chunk_size=4096, compression=comp)
        rec.add_topic("/joint_states", JointState)
        rec.add_topic("/starleth/base_state", Odometry)
        for topic, data, log_time in messages:
            rec.write(topic, data, log_time)
        rec.close()
    got = {c: bagmod.read_messages(str(p), lambda _topic, _type: True, decode=False)
           for c, p in paths.items()}
    with open(paths[compression], "rb") as f:
        theirs = [(ch.topic, m.log_time, m.data) for _, ch, m in make_reader(f).iter_messages(
            log_time_order=False)]
    assert len(theirs) == 600
    for bag in got.values():
        assert bag.counts == {"/joint_states": 300, "/starleth/base_state": 300}
        assert not bag.decode_errors and not bag.truncated
        ours = sorted((t, log, bytes(d)) for t, rows in bag.messages.items() for log, d in rows)
        assert ours == sorted(theirs)


def test_one_stamp_and_negative_iterations(tmp_path):
    """Joint states all at one stamp (the page's sample rate was 1/0: a JSON ValueError) and
    negative solver iterations (a histogram of negative size): short results."""
    rec = recorder(tmp_path / "b.mcap", solver_topic=True)
    for k in range(3):
        write_state(rec, stamp(5), k * PERIOD_NS, pub_ns=3 * k * PERIOD_NS)
        rec.write("/starleth/solver", solver(stamp(5), -5.0), k * PERIOD_NS)
    rec.close()
    v, a = run_tools(("view", [tmp_path / "b.mcap", "-o", tmp_path / "p.html"]),
                     ("analysis", [tmp_path / "b.mcap", "--out", tmp_path / "plots"]))
    assert_ok(v, "view")
    assert "1 frames at 50 fps of 3 samples" in v["out"]
    assert_ok(a, "analysis")
    assert (tmp_path / "plots" / "solver_iterations.png").exists()
