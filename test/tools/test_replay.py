"""starleth-replay: a lockstep run of sim_node (PD echo controller, a push and a persistent
wrench) re-simulated from its bag is bit-identical to the recording; the wrenches are part
of it (without them the replay differs from the push on); other configurations give overlay
plots and a divergence report; bags without the metadata, or truncated, give one line and
exit status 1."""
import json
import os
import shutil
import signal

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip("rclpy")

from geometry_msgs.msg import WrenchStamped
from rclpy.qos import QoSProfile
from ros_test_nodes import NodeProcess, RosTestNode, run_lockstep
from sensor_msgs.msg import JointState

from starleth_sim.tools.bench.controllers import EchoController
from starleth_sim.tools.replay import recording as replay_recording
from starleth_sim.tools.replay import replay
from starleth_sim.tools.replay import resimulation as replay_resimulation

# test_sim_node 50..89, controller tests 10..49, conventions 90..98, tf 199..228
DOMAIN_RANGE = (140, 40)      # first, span
DOMAIN_ID = 140 + os.getpid() % 40  # conftest._free_ros_domain: a free one of the range
START_TIMEOUT = 120.0
N_STATES = 240
K_PUSH, K_PERSIST_ON, K_PERSIST_OFF = 60, 120, 160


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A lockstep run with tf_frame_prefix robot/: PD hold; a 300 N lateral push on the
    base (named by its frame, robot/base) answering state K_PUSH; a persistent 40 N forward
    pull (on the link name, base) from K_PERSIST_ON to K_PERSIST_OFF."""
    tmp = tmp_path_factory.mktemp("replay")
    ros = RosTestNode(DOMAIN_ID, "replay_test", events=True)
    node = ros.node
    ctl = EchoController(node)
    push = node.create_publisher(WrenchStamped, "/sim_node/wrench", 10)
    persist = node.create_publisher(WrenchStamped, "/sim_node/wrench/persistent", 10)
    orig = ctl._on_state

    def wrench(pub, fx, fy, frame="base"):
        w = WrenchStamped()
        w.header.frame_id = frame
        w.wrench.force.x, w.wrench.force.y = fx, fy
        pub.publish(w)

    def on_state(msg):
        if ctl.closed:
            return
        k = len(ctl.stamps)
        if k == K_PUSH:
            wrench(push, 0.0, 300.0, "robot/base")
        elif k == K_PERSIST_ON:
            wrench(persist, 40.0, 0.0)
        elif k == K_PERSIST_OFF:
            wrench(persist, 0.0, 0.0)
        orig(msg)

    node.destroy_subscription(ctl.sub)
    ctl.sub = node.create_subscription(JointState, "/joint_states", on_state, QoSProfile(depth=10))
    mcap = str(tmp / "run.mcap")
    sim = NodeProcess("starleth_sim.ros.sim_node", tmp / "sim.log", DOMAIN_ID, mode="lockstep",
                      real_time_factor=0.0, record=mcap, tf_frame_prefix="robot/")
    try:
        ok = ros.spin_until(lambda: len(ctl.stamps) >= N_STATES or not sim.alive(),
                            START_TIMEOUT)
        assert ok and sim.alive(), sim.log()[-3000:]
    finally:
        rc = sim.stop(signal.SIGINT)
        ctl.close()
        node.destroy_publisher(push)
        node.destroy_publisher(persist)
        ros.close()
    assert rc == 0, sim.log()[-3000:]
    return mcap, tmp


def test_lockstep_run_and_its_replay_are_bit_identical(recorded, capsys):
    mcap, tmp = recorded
    out = tmp / "exact.json"
    assert replay.main([mcap, "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "bit-identical: all" in text
    doc = json.loads(out.read_text())
    assert doc["bit_identical"] and doc["steps"] >= N_STATES - 1
    rec = replay_recording.load_recording(mcap)
    assert rec.package_version and rec.package_version != ""
    # the three wrenches were recorded with the step after which they were applied
    ks = sorted(rec.wrenches)
    assert len(ks) == 3 and [w[3] for k in ks for w in rec.wrenches[k]] == [False, True, True]
    # (the push named the base by its frame: replayed with the recorded frame prefix)
    assert [w[0] for k in ks for w in rec.wrenches[k]] == ["robot/base", "base", "base"]
    assert rec.frame_prefix == "robot/"
    assert all(K_PUSH - 1 <= k <= K_PUSH + 1 for k in ks[:1])
    # the robot moved: the push shows in the base velocity
    vy = rec.states["base_linear_velocity"][:, 1]
    assert np.abs(vy).max() > 0.5 * 300.0 * 0.0025 / 26.82     # Δv = F Δt / m


def test_replay_without_the_wrenches_differs_from_the_push_on(recorded):
    mcap, _ = recorded
    rec = replay_recording.load_recording(mcap)
    k_push = min(rec.wrenches)
    rec.wrenches = {}
    rep = replay_resimulation.resimulate(rec)
    c = replay_resimulation.compare_exact(rec, rep)
    assert not c.identical
    assert c.first_step == k_push + 1            # the state after the pushed step
    assert c.first_quantities["base_linear_velocity"] > 1e-3


def test_open_loop_replay_through_other_configurations(recorded, capsys):
    mcap, tmp = recorded
    out = tmp / "overlay"
    rc = replay.main([mcap, "--preset", "HmS", "--preset", "Cm", "--out", str(out),
                      "--steps", "120", "--json", str(tmp / "presets.json")])
    assert rc == 0
    text = capsys.readouterr().out
    assert "open loop" in text and "diverge" in text and "| Cm |" in text
    for name in ("contact_forces.png", "base_trajectory.png", "joint_angles.png"):
        assert (out / name).stat().st_size > 20_000, name
    doc = json.loads((tmp / "presets.json").read_text())
    hms, cm = doc["presets"]["HmS"], doc["presets"]["Cm"]
    # SOR and JOR solve the same contact problem: HmS stays on the recorded run far longer
    # than the compliant model, whose feet sink millimetres at once
    assert hms["base_max_m"] < cm["base_max_m"]
    assert cm["joint_max_rad"] > 0 and cm["foot_force_rms_n"] > 0


def test_bag_without_metadata_gives_one_line(tmp_path, capsys):
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState as JS

    from starleth_sim.ros.recording import McapRecorder
    path = str(tmp_path / "foreign.mcap")
    rec = McapRecorder(path)
    rec.add_topic("/joint_states", JS)
    rec.write("/joint_states", serialize_message(JS(name=["a"], position=[0.0])), 0)
    rec.close()
    assert replay.main([path]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("starleth-replay: error:") \
        and "not recorded by sim_node" in err[0]


def test_truncated_bag_gives_one_line(recorded, tmp_path, capsys):
    mcap, _ = recorded
    cut = tmp_path / "cut.mcap"
    shutil.copy(mcap, cut)
    with open(cut, "r+b") as f:
        f.truncate(os.path.getsize(cut) // 2)      # as if the recorder was SIGKILLed
    assert replay.main([str(cut)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "truncated" in err[0]


#: a child process: the messages of a recording (argv[1]) written again in their order by an
#: McapRecorder (one chunk per message) to argv[2] until the applied torque of state argv[3],
#: which a file-size limit (RLIMIT_FSIZE, SIGXFSZ ignored: as `ulimit -f` and sim_node) set
#: just before it makes fail with EFBIG: the recorder closes the file at the last whole
#: chunk, the state's joint states in it and its applied torque not
CUT_WRITER = r"""
import os, resource, signal, sys
from mcap.reader import make_reader
from starleth_sim.ros.recording import McapRecorder, RecordingError, register_msg_text
from starleth_sim.ros.tf import TF_MSG_TEXT, TF_TYPE
register_msg_text(TF_TYPE, TF_MSG_TEXT)          # (as sim_node: tf2_msgs may be missing)
src, dst, k_cut = sys.argv[1], sys.argv[2], int(sys.argv[3])
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
rec = McapRecorder(dst, chunk_size=1)
with open(src, "rb") as f:
    reader = make_reader(f)
    md = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    period = int(md["starleth_sim"]["stamp_period_ns"])
    rec.add_metadata("starleth_sim", md["starleth_sim"])
    f.seek(0)
    for schema, channel, m in make_reader(f).iter_messages(log_time_order=False):
        rec.add_topic(channel.topic, schema.name)
        if channel.topic.endswith("applied_torque") and m.log_time == k_cut * period:
            _, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
            resource.setrlimit(resource.RLIMIT_FSIZE, (os.path.getsize(dst) + 250, hard))
        try:
            rec.write(channel.topic, m.data, m.log_time, m.publish_time)
        except RecordingError as e:
            print(e)
            break
"""
K_CUT = 150


@pytest.fixture(scope="module")
def cut_recording(recorded):
    """The recording cut by a file-size limit within the messages of state K_CUT (its
    joint states written, its applied torque not); and the same file as its writer left it
    without the ending the recorder added (a writer killed, a file truncated)."""
    import subprocess
    import sys

    from starleth_sim.ros.recording.mcap_sink import ending
    from starleth_sim.tools.common.bag import read_messages
    mcap, tmp = recorded
    cut = tmp / "cut.mcap"
    p = subprocess.run([sys.executable, "-c", CUT_WRITER, mcap, str(cut), str(K_CUT)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and "[Errno 27] File too large" in p.stdout, p.stdout + p.stderr
    bag = read_messages(str(cut), lambda _topic, _type: True, decode=False)
    fault = bag.metadata["starleth_recording_fault"]
    assert fault["cause"].startswith("[Errno 27] File too large: the file reached the "
                                     "file-size limit of this process (ulimit -f: "), fault
    # what today's recorder leaves: the joint states of K_CUT, no applied torque for it
    assert bag.counts["/joint_states"] == K_CUT + 1
    assert bag.counts["/starleth/applied_torque"] == K_CUT - 1
    data = cut.read_bytes()
    tail = ending(fault)
    assert data.endswith(tail)
    unended = tmp / "unended.mcap"
    unended.write_bytes(data[:-len(tail)])
    return cut, unended, fault["cause"]


@pytest.mark.parametrize("case", ["file_size_limit", "killed_writer", "truncated"])
def test_a_recording_cut_by_a_failure_replays_its_complete_steps(recorded, cut_recording,
                                                                 tmp_path, case, capsys):
    """A recording its recorder closed after a failure replays its complete steps bit for
    bit (they are those of the whole recording), and says how many states it left out and
    why: cut by a file-size limit (the recorder's fault note), its writer killed (closed by
    recording.repair, as sim_node does) or truncated (read with --salvage)."""
    from starleth_sim.ros.recording import repair
    cut, unended, cause = cut_recording
    path, args = str(cut), []
    if case == "killed_writer":
        path = str(tmp_path / "killed.mcap")
        shutil.copy(unended, path)
        cause = "the recording process ended (killed by signal 9)"
        assert repair(path, {"cause": cause}) == "repaired"
    elif case == "truncated":
        path, args, cause = str(unended), ["--salvage"], "the file is truncated"
    out = tmp_path / "r.json"
    assert replay.main([path, "--json", str(out), *args]) == 0
    cap = capsys.readouterr()
    assert f"bit-identical: all {K_CUT - 1} steps" in cap.out, cap.out + cap.err
    warning = [ln for ln in cap.err.splitlines() if "the recording was cut" in ln]
    assert len(warning) == 1, cap.err
    assert f"cut ({cause}): replaying its {K_CUT - 1} complete steps; left out the last 1 " \
           f"state(s) (from t = {K_CUT * 0.0025:.4f} s: no applied torques" in warning[0]
    doc = json.loads(out.read_text())
    assert doc["bit_identical"] and doc["steps"] == K_CUT - 1 and doc["recording_cut"] == cause
    whole = replay_recording.load_recording(recorded[0])
    part = replay_recording.load_recording(path, salvage=bool(args))
    for q, a in part.states.items():          # the states of the whole recording
        assert np.array_equal(a, whole.states[q][:K_CUT], equal_nan=True), q


def lockstep_run(tmp_path, name, n_states, **params):
    """A recorded lockstep run of sim_node (its `params`) under the PD echo controller, for
    n_states states; the bag's path."""
    ros = RosTestNode(DOMAIN_ID, f"replay_{name}_test", events=True)
    mcap = str(tmp_path / f"{name}.mcap")
    run_lockstep(ros, EchoController(ros.node), tmp_path / "sim.log", DOMAIN_ID, n_states,
                 START_TIMEOUT, record=mcap, **params)
    return mcap


# a 1 cm plate under the LF foot (yawed) and rough ground (+-6 mm) under the hind feet
TERRAIN = ("{boxes: [{centre: [0.252, 0.185, 0.005], size: [0.2, 0.2, 0.01], yaw: 0.3}], "
           "rough: {amplitude: 0.006, wavelength: 0.35, size: 1.4, seed: 2, "
           "centre: [-0.3, 0.0]}}")


def test_lockstep_run_on_a_terrain_and_its_replay_are_bit_identical(tmp_path):
    """A lockstep run (PD hold) on a terrain given by physics_overrides: the bag's physics
    configuration carries the terrain (the heightfield inline), the feet stand on it (the
    recorded contact markers: LF on the plate, the hind feet on the rough ground), and
    starleth-replay re-simulates it bit for bit."""
    from starleth_sim.physics.terrain import pack_terrain, terrain_height
    from starleth_sim.tools.common.bag import read_messages
    mcap = lockstep_run(tmp_path, "terrain", 160, physics_overrides=TERRAIN,
                        contact_markers_rate=400.0)
    rec = replay_recording.load_recording(mcap)
    terrain = rec.config().terrain
    assert len(terrain.boxes) == 1 and terrain.rough is not None
    markers = read_messages(mcap, lambda t, _: t == "/starleth/contact_markers").messages
    last = markers["/starleth/contact_markers"][-1][1].markers
    p = {m.id: m.pose.position for m in last if m.ns == "contacts"}
    packed = pack_terrain(terrain)
    for i in range(4):        # each foot on the highest surface under it (the plane: 0)
        assert p[i].z == pytest.approx(max(0.0, terrain_height(packed, p[i].x, p[i].y)),
                                       abs=1e-3), i
    assert p[0].z == pytest.approx(0.01, abs=1e-3)                  # LF_foot on the plate
    assert max(p[2].z, p[3].z) > 2e-4                               # a hind foot: rough
    out = tmp_path / "exact.json"
    assert replay.main([mcap, "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["bit_identical"] and doc["steps"] >= 159
    # the terrain is part of it: re-simulated on the plane alone, the run differs
    cfg = yaml.safe_load(rec.config_yaml)
    cfg["terrain"] = {}
    rec.config_yaml = yaml.safe_dump(cfg)
    assert not replay_resimulation.compare_exact(rec, replay_resimulation.resimulate(rec)) \
        .identical


def test_lockstep_run_with_drive_models_and_its_replay_are_bit_identical(tmp_path):
    """A lockstep run (PD hold) with StarlETH's drive models (armature, viscous and Coulomb
    joint friction, the torque lag, whose state the replay carries from the reset): the bag's
    configuration holds them, and starleth-replay re-simulates the run bit for bit."""
    drives = "{armature: 0.0012, viscous_damping: 0.05, coulomb_friction: 0.2, " \
             "torque_bandwidth: 25.0}"
    mcap = lockstep_run(tmp_path, "drives", 120, physics_overrides=drives)
    rec = replay_recording.load_recording(mcap)
    assert rec.config().actuator.torque_bandwidth == 25.0
    out = tmp_path / "exact.json"
    assert replay.main([mcap, "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["bit_identical"] and doc["steps"] >= 119
    # the drives are part of it: re-simulated without them, the run differs
    cfg = yaml.safe_load(rec.config_yaml)
    cfg["actuator"] = {"velocity_limit": cfg["actuator"]["velocity_limit"]}
    rec.config_yaml = yaml.safe_dump(cfg)
    assert not replay_resimulation.compare_exact(rec, replay_resimulation.resimulate(rec)) \
        .identical
