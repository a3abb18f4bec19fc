"""The recorder can fail; the simulation goes on (issue #33, item 1, and the bounded hot
path of item 3). A file-size limit (``RLIMIT_FSIZE``, as a full disk acts), the writer
process killed, and a really full filesystem (a 2 MB tmpfs in a user namespace, where the
kernel allows one): sim_node logs one error naming the file and the cause, keeps stepping
and publishing, says ``recording: failed (...)`` on /starleth/solver, and its bag reads as
a complete bag up to the last message written. Below that, the recorders themselves: a
failed write closes the file as a complete MCAP file every reader reads; a writer that is
behind never makes the caller wait; metadata.yaml costs O(1) per split; close keeps to its
time limit."""
import itertools
import os
import resource
import shutil
import signal
import subprocess
import sys
import time

import pytest

rclpy = pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.qos import QoSProfile
from rclpy.serialization import serialize_message
from ros_test_nodes import NodeProcess, RosTestNode
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from starleth_sim.ros.recording import McapRecorder, ProcessRecorder, QueuedRecorder, SplitRecorder
from starleth_sim.ros.recording.mcap_sink import RecordingError, repair
from starleth_sim.tools.common.bag import read_messages

DOMAIN_RANGE = (100, 20)      # first, span (conftest._free_ros_domain)
DOMAIN_ID = 100 + os.getpid() % 20
START_TIMEOUT = 120.0         # of silence (compile lines restart it)
PERIOD_NS = 2_500_000


def _clock(k):
    m = Clock()
    m.clock.sec, m.clock.nanosec = divmod(k * PERIOD_NS, 1_000_000_000)
    return serialize_message(m)


def _readers_agree(path):
    """Messages per topic as the mcap library, rosbags and this package's reader see the
    file (all three must read it without --salvage)."""
    from pathlib import Path

    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader
    with open(path, "rb") as f:
        n_mcap = sum(1 for _ in make_reader(f).iter_messages())
    with AnyReader([Path(path)]) as r:
        n_rosbags = sum(1 for _ in r.messages())
    bag = read_messages(str(path), lambda _topic, _type: True, decode=False)
    n_ours = sum(len(v) for v in bag.messages.values())
    assert n_mcap == n_rosbags == n_ours, (n_mcap, n_rosbags, n_ours)
    return n_mcap, bag


# -----------------------------------------------------------------------------------------
# the recorders
# -----------------------------------------------------------------------------------------
FSIZE_SCRIPT = r"""
import resource, sys
resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[2]), int(sys.argv[2])))
from rclpy.serialization import serialize_message
from rosgraph_msgs.msg import Clock
from starleth_sim.ros.recording import McapRecorder, RecordingError
rec = McapRecorder(sys.argv[1], chunk_size=64 * 1024)
rec.add_topic("/clock", Clock)
n = 0
try:
    for k in range(10 ** 6):
        m = Clock()
        m.clock.sec = k
        rec.write("/clock", serialize_message(m), k)
        n += 1
except RecordingError as e:
    print("FAILED", n, rec.messages_on_disk, e)
"""


def test_a_write_beyond_the_file_size_limit_leaves_a_complete_bag(tmp_path):
    """EFBIG mid-recording: RecordingError names the file and the cause; the file ends
    after the last whole chunk with a footer, and mcap, rosbags and bag.py read the same
    messages, 0, 1, 2, ... without a gap, as many as the error says."""
    path = tmp_path / "limited.mcap"
    out = subprocess.run([sys.executable, "-c", FSIZE_SCRIPT, str(path), "500000"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    line = out.stdout.strip()
    assert line.startswith("FAILED"), line
    _, handed, on_disk, msg = line.split(" ", 3)
    assert str(path) in msg and "File too large" in msg and "complete up to" in msg, msg
    assert 0 < int(on_disk) <= int(handed)
    assert os.path.getsize(path) <= 500000
    n, bag = _readers_agree(path)
    assert n == int(on_disk)
    from rclpy.serialization import deserialize_message
    secs = [deserialize_message(d, Clock).clock.sec for _, d in bag.messages["/clock"]]
    assert secs == list(range(n))
    assert "starleth_recording_fault" in bag.metadata


def test_repair_closes_a_file_cut_anywhere(tmp_path):
    """A file cut at any byte (a writer killed mid-write) is closed at its last whole
    record: every reader reads it, and it holds a prefix of the messages."""
    full = tmp_path / "full.mcap"
    with McapRecorder(str(full), chunk_size=4096) as rec:
        rec.add_topic("/clock", Clock)
        for k in range(2000):
            rec.write("/clock", _clock(k), k)
    data = full.read_bytes()
    counts = []
    for cut in (9, 100, len(data) // 3, len(data) // 2 + 17, len(data) - 200):
        p = tmp_path / f"cut{cut}.mcap"
        p.write_bytes(data[:cut])
        assert repair(str(p)) in ("repaired", "unreadable")
        if cut < 100:
            continue
        n, _ = _readers_agree(p)
        counts.append(n)
    assert counts == sorted(counts) and counts[-1] > counts[0] >= 0
    assert repair(str(full)) == "complete" and full.read_bytes() == data


def test_process_recorder_reports_a_killed_writer_once_and_repairs_its_file(tmp_path):
    """The writer process killed: the next hand-over finds out (nothing raises), the
    failure names the file and the signal, on_failure is called once, writes return False,
    and the file reads as a complete bag."""
    path = tmp_path / "killed.mcap"
    failures = []
    rec = ProcessRecorder(str(path), chunk_size=8192, on_failure=failures.append)
    rec.add_topic("/clock", Clock)
    for k in range(3000):
        rec.write("/clock", _clock(k), k)
        if k % 20 == 0:
            rec.hand_over()
    time.sleep(0.5)                         # the writer has written some chunks
    rec._proc.kill()
    rec._proc.wait(10)
    for k in range(3000, 3100):
        rec.write("/clock", _clock(k), k)
        rec.hand_over()
    assert len(failures) == 1, failures
    assert str(path) in failures[0] and "SIGKILL" in failures[0], failures[0]
    assert "complete up to the last message written" in failures[0]
    assert rec.closed and rec.write("/clock", _clock(0), 0) is False
    n, _ = _readers_agree(path)
    assert 0 < n <= 3000
    with pytest.raises(RecordingError):
        rec.close()


def test_queued_recorder_stops_on_a_failed_write(tmp_path):
    """The in-process writer thread under a failing file: on_failure once, later writes
    refused, the file complete up to its last chunk."""
    path = tmp_path / "queued.mcap"
    failures = []
    inner = McapRecorder(str(path), chunk_size=4096)
    rec = QueuedRecorder(inner, on_failure=failures.append)
    rec.add_topic("/clock", Clock)
    for k in range(500):
        rec.write("/clock", _clock(k), k)
    rec.flush()
    os.close(inner._file.fd)                # every later write fails (EBADF)
    inner._file.fd = os.open(os.devnull, os.O_RDONLY)
    for k in range(500, 2000):
        rec.write("/clock", _clock(k), k)
    rec.flush(10)
    assert len(failures) == 1 and str(path) in failures[0], failures
    assert rec.closed and rec.write("/clock", _clock(0), 0) is False


@pytest.mark.serial   # latencies / a realtime node's rate
def test_a_writer_that_is_behind_never_makes_the_caller_wait(tmp_path):
    """The writer process stopped (SIGSTOP: as a writer stuck on a slow disk): hand_over
    returns at once however much is queued; beyond MAX_BACKLOG messages are dropped and
    counted; a close with a time limit keeps to it and says the writer finishes on its
    own; resumed, the writer finalises a complete file holding what it got."""
    path = tmp_path / "behind.mcap"
    rec = ProcessRecorder(str(path))
    rec.MAX_BACKLOG = 4 << 20
    rec.add_topic("/clock", Clock)
    payload = bytes(2000)          # ~2 kB messages (the bytes are not decoded)
    os.kill(rec._proc.pid, signal.SIGSTOP)
    try:
        worst = 0.0
        for k in range(6000):          # 12 MB: more than the pipe and the backlog hold
            rec.write("/clock", payload, k)
            if k % 8 == 0:
                t = time.perf_counter()
                rec.hand_over()
                worst = max(worst, time.perf_counter() - t)
        assert worst < 0.05, f"a hand-over waited {worst:.3f} s"
        assert rec.dropped > 0 and rec.backlog <= rec.MAX_BACKLOG
        t = time.monotonic()
        rec.close(timeout=0.5)
        assert time.monotonic() - t < 1.5
        assert "finalises" in rec.close_note and str(path) in rec.close_note, rec.close_note
    finally:
        os.kill(rec._proc.pid, signal.SIGCONT)
    rec._proc.wait(60)
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        reader = make_reader(f)
        n = sum(1 for _ in reader.iter_messages())
        assert reader.get_summary() is not None
    assert 0 < n <= 6000 - rec.dropped


def test_metadata_yaml_costs_constant_work_per_split(tmp_path):
    """64 splits write metadata.yaml 7 times (at 1, 2, 4, ..., 64 files) plus once at
    close, not 64 times with 64 growing lists; the final one lists every file."""
    import yaml
    rec = SplitRecorder(str(tmp_path / "bag"), max_duration_ns=10 * PERIOD_NS)
    rec.add_topic("/clock", Clock)
    for k in range(10 * 64 + 5):
        rec.write("/clock", _clock(k), k * PERIOD_NS)
    assert len(rec.files) == 65
    assert rec.metadata_writes == 7
    rec.close()
    assert rec.metadata_writes == 8
    meta = yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text())
    info = meta["rosbag2_bagfile_information"]
    assert len(info["files"]) == 65 and info["message_count"] == 10 * 64 + 5


def test_a_split_bag_whose_file_fails_keeps_its_closed_files(tmp_path):
    """A failure in the fourth file of a split bag: the first three stay complete, the
    fourth is closed up to its last chunk, metadata.yaml lists all four."""
    import yaml
    rec = SplitRecorder(str(tmp_path / "bag"), max_duration_ns=200 * PERIOD_NS,
                        chunk_size=2048)
    rec.add_topic("/clock", Clock)
    k = 0
    while len(rec.files) < 4 or k % 200 < 150:
        rec.write("/clock", _clock(k), k * PERIOD_NS)
        k += 1
    cur = rec._current
    os.close(cur._file.fd)
    cur._file.fd = os.open(os.devnull, os.O_RDONLY)
    with pytest.raises(RecordingError):
        for j in range(k, k + 100):
            rec.write("/clock", _clock(j), j * PERIOD_NS)
    assert rec.closed and rec.failure
    info = yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text())[
        "rosbag2_bagfile_information"]
    assert len(info["files"]) == 4
    assert [f["message_count"] for f in info["files"][:3]] == [200, 200, 200]


# -----------------------------------------------------------------------------------------
# sim_node
# -----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ros():
    r = RosTestNode(DOMAIN_ID, "recording_faults_test", events=True)
    yield r
    r.close()


class _Watch:
    """Counts /joint_states and keeps the interface status of /starleth/solver."""

    def __init__(self, ros):
        self.joint_states = 0
        self.interface = {}
        self.ros = ros
        self._subs = [
            ros.node.create_subscription(JointState, "/joint_states", self._js,
                                         QoSProfile(depth=100)),
            ros.node.create_subscription(DiagnosticArray, "/starleth/solver", self._diag,
                                         QoSProfile(depth=100))]

    def _js(self, _msg):
        self.joint_states += 1

    def _diag(self, msg):
        for st in msg.status:
            if st.name == "starleth_sim: interface":
                self.interface = {kv.key: kv.value for kv in st.values}

    def close(self):
        for s in self._subs:
            self.ros.node.destroy_subscription(s)


def _run_until_the_recording_fails(ros, sim, watch, kill_writer=False):
    """Wait for the node, (kill its writer), wait for 'recording failed', then check that
    it goes on publishing and says so on /starleth/solver. Returns the log."""
    assert ros.spin_until(lambda: watch.joint_states > 40, START_TIMEOUT, [sim]), sim.log()
    if kill_writer:
        # after a second of recording: the writer has written a few 256 kB chunks
        assert ros.spin_until(lambda: watch.joint_states > 400, 30, [sim]), sim.log()
        out = subprocess.run(["pgrep", "-P", str(sim.proc.pid), "-f", "recording --writer"],
                             capture_output=True, text=True)
        pids = [int(p) for p in out.stdout.split()]
        assert len(pids) == 1, (out.stdout, sim.log())
        os.kill(pids[0], signal.SIGKILL)
    assert ros.spin_until(lambda: "recording failed" in sim.log(), 60, [sim]), sim.log()
    before = watch.joint_states
    ros.spin_for(1.0)
    assert watch.joint_states - before > 100, "the node stopped publishing"
    assert ros.spin_until(lambda: watch.interface.get("recording", "").startswith("failed ("),
                          10, [sim]), watch.interface
    assert sim.alive()
    return sim.log()


def _check_bag_after_failure(path, log, copy=None):
    """One error line naming the file; the bag (or its copy) complete, without a gap."""
    assert log.count("recording failed") == 1, log
    line = next(x for x in log.splitlines() if "recording failed" in x)
    assert "[ERROR]" in line and str(path) in line and "goes on" in line
    n, bag = _readers_agree(copy or path)
    stamps = [t for t, _ in bag.messages["/joint_states"]]
    assert len(stamps) > 40
    assert all(b - a == PERIOD_NS for a, b in itertools.pairwise(stamps)), "a gap in the bag"
    assert "Traceback" not in log


@pytest.mark.serial   # latencies / a realtime node's rate
def test_sim_node_keeps_publishing_when_the_recording_hits_a_file_size_limit(ros, tmp_path):
    """sim_node under `ulimit -f` (RLIMIT_FSIZE 1.5 MB, inherited by its writer process):
    the recording fails after a second or two; the node logs one error naming the file and
    the cause, goes on publishing /joint_states, reports recording: failed (...), exits 0
    on SIGINT; the bag reads as a complete bag up to the last message written."""
    path = tmp_path / "limited.mcap"
    limit = 1_500_000

    def limit_file_size():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    sim = NodeProcess("starleth_sim.ros.sim_node", str(tmp_path / "sim.log"), DOMAIN_ID,
                      preexec_fn=limit_file_size, mode="realtime",
                      realtime_start="immediately", record=str(path))   # runs uncommanded
    watch = _Watch(ros)
    try:
        log = _run_until_the_recording_fails(ros, sim, watch)
        assert "File too large" in log
        assert "File too large" in watch.interface["recording"]
    finally:
        watch.close()
        code = sim.stop()
    assert code == 0, sim.log()
    _check_bag_after_failure(path, sim.log())
    assert os.path.getsize(path) <= limit
    assert sim.summary()["recording"].startswith("failed (")


@pytest.mark.serial   # latencies / a realtime node's rate
def test_sim_node_keeps_publishing_when_its_writer_is_killed(ros, tmp_path):
    """The writer process killed (SIGKILL): the node repairs the file, logs one error
    (file, signal), goes on publishing; the bag is complete up to the last whole chunk."""
    path = tmp_path / "killed.mcap"
    sim = NodeProcess("starleth_sim.ros.sim_node", str(tmp_path / "sim.log"), DOMAIN_ID,
                      mode="realtime", realtime_start="immediately", record=str(path))
    watch = _Watch(ros)
    try:
        log = _run_until_the_recording_fails(ros, sim, watch, kill_writer=True)
        assert "SIGKILL" in log
    finally:
        watch.close()
        code = sim.stop()
    assert code == 0, sim.log()
    _check_bag_after_failure(path, sim.log())


def _user_namespace_tmpfs():
    """Why a tmpfs cannot be mounted in a user namespace here ('' if it can)."""
    if shutil.which("unshare") is None:
        return "no unshare(1)"
    out = subprocess.run(["unshare", "-rm", "sh", "-c", "mount -t tmpfs -o size=1m none /mnt"],
                         capture_output=True, text=True)
    return "" if out.returncode == 0 else \
        f"unprivileged user namespaces cannot mount a tmpfs here ({out.stderr.strip()})"


@pytest.mark.serial   # latencies / a realtime node's rate
def test_sim_node_keeps_publishing_when_the_disk_is_full(ros, tmp_path):
    """A really full filesystem (ENOSPC): sim_node runs in a user namespace of its own
    (`unshare -rm`: no root needed) with a 1 MB tmpfs mounted over a directory, and
    records there."""
    why = _user_namespace_tmpfs()
    if why:
        print(f"SKIP reason: {why}")
        pytest.skip(why)
    disk = tmp_path / "disk"
    disk.mkdir()
    path = disk / "full.mcap"
    copy = tmp_path / "full.mcap"
    # the node runs as a child of the shell, which passes SIGTERM on and copies the bag
    # out of the tmpfs before the namespace (and its mount) ends
    script = (f'mount -t tmpfs -o size=1m none {disk} || exit 3; "$@" & pid=$!; '
              "trap 'kill -TERM $pid' TERM INT; wait $pid; code=$?; "
              'while kill -0 $pid 2>/dev/null; do wait $pid; code=$?; done; '
              f'cp {path} {copy}; exit $code')
    sim = NodeProcess("starleth_sim.ros.sim_node", str(tmp_path / "sim.log"), DOMAIN_ID,
                      wrapper=("unshare", "-rm", "sh", "-c", script, "sh"),
                      mode="realtime", realtime_start="immediately", record=str(path))
    watch = _Watch(ros)
    try:
        log = _run_until_the_recording_fails(ros, sim, watch)
        assert "No space left on device" in log
    finally:
        watch.close()
        code = sim.stop(signal.SIGTERM)
    assert code == 0, sim.log()
    _check_bag_after_failure(path, sim.log(), copy)
