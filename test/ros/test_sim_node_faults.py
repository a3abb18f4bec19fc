"""sim_node under faults that must not take it down (issue #33, items 3, 5 and 7): 100
service calls at once, diagnostics while paused, SIGINT with a writer that is far behind,
and recording targets that cannot be written (/dev/full, /proc). The node runs as a child
process on a ROS domain of its own (ros_test_nodes)."""
import os
import signal
import subprocess
import sys
import time

import pytest

rclpy = pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.qos import QoSProfile
from ros_test_nodes import NodeProcess, RosTestNode
from sensor_msgs.msg import JointState
from std_srvs.srv import SetBool, Trigger

from starleth_interface.ros_helpers import service_qos
from starleth_sim.tools.common.discovery import local_discovery_env

DOMAIN_RANGE = (120, 20)      # first, span (conftest._free_ros_domain)
DOMAIN_ID = 120 + os.getpid() % 20
START_TIMEOUT = 120.0


@pytest.fixture(scope="module")
def ros():
    r = RosTestNode(DOMAIN_ID, "sim_node_faults_test", events=True)
    yield r
    r.close()


def _sim(tmp_path, tag, **params):
    return NodeProcess("starleth_sim.ros.sim_node", str(tmp_path / f"{tag}.log"), DOMAIN_ID,
                       **params)


@pytest.mark.serial   # a realtime node's answers within deadlines
def test_paused_it_still_reports_and_answers_a_hundred_concurrent_calls(ros, tmp_path):
    """Paused, /starleth/solver still comes about once a second with the interface status
    'paused' (a monitor tells a paused simulator from a dead one) and sim time stands
    still. Then 100 callers (one client each) call ~/reset at once, then ~/step, then
    ~/pause: every call is answered (the services keep SERVICE_QUEUE requests and
    responses; with rclpy's default depth of 10 about 11 were), and the node counts 100
    resets. The clients are made with service_qos (SERVICE_QUEUE deep): with Fast DDS every
    client of a service also receives the responses to the others, so a client of the
    default depth 10 loses its own (33, 15 and 21 of 100 arrive)."""
    sim = _sim(tmp_path, "sim", mode="realtime", start_paused=True)
    got = []

    def on_diag(msg):
        for st in msg.status:
            if st.name == "starleth_sim: interface":
                got.append((st.message, {kv.key: kv.value for kv in st.values}))

    sub = ros.node.create_subscription(DiagnosticArray, "/starleth/solver", on_diag,
                                       QoSProfile(depth=50))
    calls = (("reset", Trigger, Trigger.Request()), ("step", Trigger, Trigger.Request()),
             ("pause", SetBool, SetBool.Request(data=True)))
    clients = [[ros.node.create_client(typ, f"/sim_node/{name}", qos_profile=service_qos())
                for _ in range(100)] for name, typ, _ in calls]
    try:
        assert ros.spin_until(lambda: len(got) >= 1, START_TIMEOUT, [sim]), sim.log()
        ros.spin_for(3.2)
        assert 3 <= len(got) <= 6, len(got)
        assert all(m == "paused" and v["paused"] == "True" and v["sim_time"] == "0.0"
                   for m, v in got)
        for (name, _, request), cs in zip(calls, clients, strict=True):
            assert ros.spin_until(lambda cs=cs: all(c.service_is_ready() for c in cs), 30, [sim])
            futures = [c.call_async(request) for c in cs]
            assert ros.spin_until(lambda futures=futures: all(f.done() for f in futures), 60,
                                  [sim]), \
                f"~/{name}: {sum(f.done() for f in futures)} of 100 answered"
            assert all(f.result().success for f in futures), name
        assert ros.call(SetBool, "/sim_node/pause", SetBool.Request(data=False)).success
    finally:
        ros.node.destroy_subscription(sub)
        for c in (c for cs in clients for c in cs):
            ros.node.destroy_client(c)
        code = sim.stop()
    assert code == 0
    assert sim.summary()["resets"] == 100


@pytest.mark.serial   # a deadline of 2 s
def test_sigint_ends_the_node_within_two_seconds_whatever_is_queued(ros, tmp_path):
    """The recording process stopped (SIGSTOP: stuck on a slow disk) while the node runs:
    the node never waits for it (it keeps publishing), SIGINT ends it within ~2 s and its
    log says that the writer finishes on its own; resumed, the writer finalises a complete
    file."""
    path = tmp_path / "slow.mcap"
    sim = _sim(tmp_path, "sim", mode="realtime", realtime_start="immediately",   # no controller
               record=str(path))
    count = [0]
    sub = ros.node.create_subscription(JointState, "/joint_states",
                                       lambda _msg: count.__setitem__(0, count[0] + 1),
                                       QoSProfile(depth=100))
    writer = None
    try:
        assert ros.spin_until(lambda: count[0] > 40, START_TIMEOUT, [sim]), sim.log()
        out = subprocess.run(["pgrep", "-P", str(sim.proc.pid), "-f", "recording --writer"],
                             capture_output=True, text=True)
        writer = int(out.stdout.split()[0])
        os.kill(writer, signal.SIGSTOP)
        before = count[0]
        ros.spin_for(2.0)                          # ~4 MB queued: more than the pipe holds
        assert count[0] - before > 400, "the node waited for its recording process"
        t = time.monotonic()
        sim.proc.send_signal(signal.SIGINT)
        sim.proc.wait(10)
        took = time.monotonic() - t
    finally:
        ros.node.destroy_subscription(sub)
        if writer is not None:
            os.kill(writer, signal.SIGCONT)
        code = sim.stop()
    assert code == 0, sim.log()
    print(f"SIGINT to exit: {took:.2f} s")
    assert took < 2.5, f"SIGINT took {took:.2f} s"
    log = sim.log()
    assert "finalises" in log and str(path) in log, log[-2000:]
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and os.path.exists(f"/proc/{writer}"):
        time.sleep(0.1)
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        reader = make_reader(f)
        n = sum(1 for _ in reader.iter_messages())
        assert reader.get_summary() is not None and n > 1000


def test_a_recording_that_cannot_be_written_is_one_line_and_exit_2():
    """record:=/dev/full: sim_node exits with 2 and one line naming the file and the cause,
    without a traceback and without first trying in-process; /proc/x.mcap (no file can be
    made there) is refused the same way by the recorder."""
    from starleth_sim.ros.recording import ProcessRecorder, RecordingError
    with pytest.raises(RecordingError, match=r"^/proc/x.mcap: \[Errno \d+\]"):
        ProcessRecorder("/proc/x.mcap")
    target, cause = "/dev/full", "No space left on device"
    env = dict(local_discovery_env(), ROS_DOMAIN_ID=str(DOMAIN_ID))
    out = subprocess.run([sys.executable, "-m", "starleth_sim.ros.sim_node", "--ros-args",
                          "-p", f"record:={target}"], capture_output=True, text=True,
                         timeout=180, env=env, stdin=subprocess.DEVNULL)
    assert out.returncode == 2, out.stdout + out.stderr
    err = [x for x in out.stderr.splitlines() if x.strip() and not x.startswith("[INFO]")]
    assert len(err) == 1 and target in err[0] and cause in err[0], out.stderr
    assert "Traceback" not in out.stdout + out.stderr
    assert "recording in this process" not in out.stdout + out.stderr


def assert_one_line_exit_2(args, want):
    """sim_node --ros-args *args exits 2 with one line (beside [INFO] lines) holding every
    string of `want`, and no traceback."""
    env = dict(local_discovery_env(), ROS_DOMAIN_ID=str(DOMAIN_ID))
    out = subprocess.run([sys.executable, "-m", "starleth_sim.ros.sim_node", "--ros-args",
                          *args], capture_output=True, text=True, timeout=180, env=env,
                         stdin=subprocess.DEVNULL)
    assert out.returncode == 2, out.stdout + out.stderr
    err = [x for x in out.stderr.splitlines() if x.strip() and not x.startswith("[INFO]")]
    assert len(err) == 1 and all(w in err[0] for w in want), out.stderr
    assert "Traceback" not in out.stdout + out.stderr


@pytest.mark.parametrize("how", ["file", "overrides"])
def test_a_bad_terrain_is_one_line_and_exit_2(tmp_path, how):
    """A terrain that is not valid, in a physics file (-p physics:=FILE) or in
    physics_overrides: exit 2 and one line naming the file (or the overrides) and the field,
    without a traceback."""
    if how == "file":
        bad = tmp_path / "bad_stairs.yaml"
        bad.write_text("contact_model: hard\nterrain:\n  stairs: {rise: -0.04, run: 0.3, "
                       "count: 2}\n")
        args, want = ["-p", f"physics:={bad}"], [str(bad), "terrain.stairs.rise", "-0.04"]
    else:
        args = ["-p", "physics_overrides:='{boxes: [{centre: [0, 0], size: [1, 1, 1]}]}'"]
        want = ["with overrides", "terrain.boxes[0].centre", "3 numbers"]
    assert_one_line_exit_2(args, want)


@pytest.mark.parametrize("args, want", [
    (["-p", "robot:=no_such_robot"], ["parameter robot", "'no_such_robot'", "go1"]),
    (["-p", "physics_overrides:='{robot: go1}'"], ["physics_overrides", "robot:=go1"])])
def test_a_bad_robot_is_one_line_and_exit_2(args, want):
    """A robot the library does not have, or a robot inside physics_overrides (the robot
    parameter's place): exit 2 and one line naming the parameter, without a traceback."""
    assert_one_line_exit_2(args, want)


def test_a_bad_sensors_file_is_one_line_and_exit_2(tmp_path):
    """A sensors file with a field out of range: exit 2, one line naming the parameter, the
    file and the field; an unknown name lists the shipped ones."""
    bad = tmp_path / "noisy.yaml"
    bad.write_text("sensors:\n  imu_delay: 0.001\n")
    assert_one_line_exit_2(["-p", f"sensors:={bad}"],
                           ["parameter sensors", str(bad), "sensors.imu_delay"])
    assert_one_line_exit_2(["-p", "sensors:=nosuch"], ["parameter sensors", "realistic"])
