"""starleth-analyze (starleth_sim.tools.analysis.analysis) on bags written with McapRecorder from
real simulator runs (no ROS graph): plots, summary numbers, overlays, missing topics and damaged
files. A few seconds in all."""
from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("matplotlib")

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import WrenchStamped
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import String

from starleth_sim import Simulator
from starleth_sim.physics.description import STARLETH_JOINT_NAMES
from starleth_sim.physics.posture import PostureHold
from starleth_sim.robots import robot_description, spec_text
from starleth_sim.ros.recording import McapRecorder
from starleth_sim.tools.analysis import analysis
from starleth_sim.tools.analysis import plots as analysis_plots
from starleth_sim.tools.analysis import run as analysis_run
from starleth_sim.tools.common import bag

PERIOD_NS = 2_500_000
FEET = ("LF_foot", "RF_foot", "LH_foot", "RH_foot")
WALL0 = 1_700_000_000_000_000_000
PLOTS = ("contact_forces", "gait", "base_trajectory", "joint_torques", "solver_iterations",
         "real_time_factor")
SOLVER_KEYS = ("iterations", "max_iterations_step", "converged", "status", "residual",
               "active_contacts", "retried", "step_time", "physics_steps", "nonconverged_steps")
ALL_TOPICS = {"/clock": Clock, "/joint_states": JointState, "/starleth/base_state": Odometry,
              "/starleth/solver": DiagnosticArray, "/robot_description": String,
              **{f"/starleth/{f}/wrench": WrenchStamped for f in FEET}}


# -- writing bags like sim_node ---------------------------------------------------------------
def rotation(q):
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def stamp(k):
    return Time(sec=(k * PERIOD_NS) // 10 ** 9, nanosec=(k * PERIOD_NS) % 10 ** 9)


class BagWriter:
    """Writes the state topics the way sim_node does: one message per topic per control
    step, stamp = log time = k * 2.5 ms (publish time = a fake wall clock if wall_rtf)."""

    def __init__(self, path, skip=(), wall_rtf=None, urdf=None, robot=None):
        """robot: a library name whose URDF and spec are recorded as sim_node does."""
        self.rec = McapRecorder(str(path))
        self.skip, self.wall_rtf = set(skip), wall_rtf
        for topic, typ in ALL_TOPICS.items():
            if topic not in self.skip:
                self.rec.add_topic(topic, typ)
        md = {"control_period": "0.0025", "stamp_period_ns": str(PERIOD_NS)}
        if robot:
            md.update(robot=robot, urdf_attachment=f"{robot}.urdf",
                      robot_spec_attachment=f"{robot}.robot.yaml")
            self.rec.add_attachment(f"{robot}.urdf", "application/xml",
                                    robot_description(robot).urdf_xml)
            self.rec.add_attachment(f"{robot}.robot.yaml", "application/yaml", spec_text(robot))
        self.rec.add_metadata("starleth_sim", md)
        if urdf and "/robot_description" not in self.skip:
            self.write("/robot_description", String(data=urdf), 0)

    def write(self, topic, msg, k):
        if topic in self.skip:
            return
        pub = None if self.wall_rtf is None else WALL0 + int(k * PERIOD_NS / self.wall_rtf)
        self.rec.write(topic, msg, k * PERIOD_NS, publish_time_ns=pub)

    def state(self, sim, k):
        st = stamp(k)
        self.write("/clock", Clock(clock=st), k)
        js = JointState(name=list(sim.joint_names), position=list(sim.joint_positions()),
                        velocity=list(sim.joint_velocities()), effort=list(sim.applied_torque))
        js.header.stamp = st
        self.write("/joint_states", js, k)
        for c in sim.contacts:
            foot = c.name.split("_")[0]
            if c.name.endswith("_foot"):
                m = WrenchStamped()
                m.header.stamp, m.header.frame_id = st, "world"
                m.wrench.force.x, m.wrench.force.y, m.wrench.force.z = (float(x) for x in c.force)
                self.write(f"/starleth/{foot}_foot/wrench", m, k)
        b = sim.base_state()
        self.odometry(k, b["position"], b["orientation_xyzw"], b["linear_velocity"],
                      b["angular_velocity"])
        d = sim.diagnostics
        vals = (d.iterations, d.max_iterations_step, d.converged, d.status, repr(d.residual),
                d.active_contacts, d.retried, repr(d.step_time), d.physics_steps,
                d.nonconverged_steps)
        status = DiagnosticStatus(name="starleth_sim: solver", hardware_id="starleth_sim",
                                  message=str(d.status),
                                  values=[KeyValue(key=key, value=str(v))
                                          for key, v in zip(SOLVER_KEYS, vals, strict=True)])
        da = DiagnosticArray(status=[status])
        da.header.stamp = st
        self.write("/starleth/solver", da, k)

    def odometry(self, k, p, q, v_world, w_body, child="base"):
        """Odometry as sim_node writes it: pose in 'world', twist in the base frame."""
        o = Odometry()
        o.header.stamp, o.header.frame_id, o.child_frame_id = stamp(k), "world", child
        v = rotation(q).T @ np.asarray(v_world, dtype=float) if child == "base" else v_world
        pp, po = o.pose.pose.position, o.pose.pose.orientation
        pp.x, pp.y, pp.z = (float(x) for x in p)
        po.x, po.y, po.z, po.w = (float(x) for x in q)
        tl, ta = o.twist.twist.linear, o.twist.twist.angular
        tl.x, tl.y, tl.z = (float(x) for x in v)
        ta.x, ta.y, ta.z = (float(x) for x in w_body)
        self.write("/starleth/base_state", o, k)

    def close(self):
        self.rec.close()


def run_sim(path, preset="HmJ", steps=400, controller="posture", drop=0.0, skip=(),
            wall_rtf=None, forward=0.3, stand_steps=200):
    """Simulate and record; returns a dict of reference figures from the simulator itself."""
    Simulator.from_preset(preset).step()  # warm-up: compiled code loaded before timing
    sim = Simulator.from_preset(preset)
    sim.reset()
    if drop:
        q = sim.q
        q[2] += drop
        sim.reset(q=q)
    if controller == "posture":
        ph = PostureHold(sim.joint_positions())

        def torque(_k):
            return ph.torque(sim)
    else:
        from starleth_controller import Command, RobotState, StarlethController
        from starleth_sim.physics.description import urdf_path
        ctrl = StarlethController(urdf_path())

        def torque(k):
            cmd = Command("stand") if k < stand_steps else Command("trot", forward=forward)
            return ctrl.update(RobotState.from_simulator(sim), cmd)
    w = BagWriter(path, skip=skip, wall_rtf=wall_rtf, urdf=sim.description.urdf_xml,
                  robot="starleth")
    ref = {"iterations": [], "v_xy": [], "mass": sim.description.total_mass}
    for k in range(steps + 1):
        if k:
            sim.step(torque(k))
        w.state(sim, k)
        ref["iterations"].append(sim.diagnostics.iterations)
        ref["v_xy"].append(np.hypot(*sim.base_state()["linear_velocity"][:2]))
    w.close()
    return ref


def analyse(tmp_path, bags, *extra, name="out"):
    out, js = tmp_path / name, tmp_path / f"{name}.json"
    rc = analysis.main([str(b) for b in bags] + ["--out", str(out), "--json", str(js),
                                                 *extra])
    doc = json.loads(js.read_text()) if js.exists() else None
    return rc, out, doc


@pytest.fixture(scope="module")
def stand_bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("bags") / "stand.mcap"
    ref = run_sim(path, steps=400)
    return path, ref


# -- tests ------------------------------------------------------------------------------------
def test_standing_summary_and_plots(stand_bag, tmp_path, capsys):
    path, ref = stand_bag
    rc, out, doc = analyse(tmp_path, [path])
    assert rc == 0
    for name in PLOTS:
        png = out / f"{name}.png"
        assert png.exists() and png.stat().st_size > 10_000, name
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    S = doc["runs"][0]
    assert S["label"] == "stand" and S["missing_topics"] == []
    assert S["control_steps"] == 401 and S["sim_time"]["duration"] == pytest.approx(1.0)
    weight = ref["mass"] * 9.81
    assert S["weight"] == pytest.approx(weight, rel=1e-9)
    for foot in FEET:
        f = S["feet"][foot]
        assert f["mean_normal_force"] == pytest.approx(weight / 4, rel=0.02), foot
        assert f["touchdowns"] == 0 and f["stance_fraction"] > 0.99
    assert S["total_mean_normal_force"] == pytest.approx(weight, rel=0.01)
    assert S["base"]["distance"] < 1e-3 and S["base"]["mean_speed"] < 0.01
    assert 0.40 < S["base"]["height_mean"] < 0.42
    assert S["solver"]["steps"] == 401
    assert S["solver"]["iterations_mean"] == pytest.approx(np.mean(ref["iterations"]))
    assert S["solver"]["iterations_max"] == max(ref["iterations"])
    assert S["joints"]["max_abs_overall"] > 1.0
    # sim_node-style bag: no wall clock, the compute-only factor from step_time
    rtf = S["real_time_factor"]
    assert rtf["source"] is None and rtf["compute"] > 1.0
    text = capsys.readouterr().out
    assert "% of the weight" in text and "touchdowns 0" in text
    assert "no wall clock in the bag" in text and "physics compute only" in text


def test_numbers_match_an_independent_reader(stand_bag, tmp_path):
    """The LF mean force and the iteration count, decoded by rosbags instead."""
    rosbags = pytest.importorskip("rosbags.highlevel")
    from rosbags.typesys import Stores, get_typestore
    path, _ = stand_bag
    rc, _, doc = analyse(tmp_path, [path], "--no-plots")
    assert rc == 0
    fz, its = [], []
    with rosbags.AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as r:
        conns = [c for c in r.connections if c.topic in ("/starleth/LF_foot/wrench",
                                                         "/starleth/solver")]
        for c, _, raw in r.messages(connections=conns):
            m = r.deserialize(raw, c.msgtype)
            if c.topic == "/starleth/solver":
                its.append(float({kv.key: kv.value for kv in m.status[0].values}["iterations"]))
            else:
                fz.append(m.wrench.force.z)
    S = doc["runs"][0]
    assert S["feet"]["LF_foot"]["mean_normal_force"] == pytest.approx(np.mean(fz), rel=1e-12)
    assert S["solver"]["iterations_mean"] == pytest.approx(np.mean(its), rel=1e-12)


def test_trot_gait_speed_and_wall_clock(tmp_path):
    """Controller trot (0.8 s gait period): touchdowns, diagonal pairs in phase, horizontal
    speed from the base-frame twist; publish_time as a wall clock at RTF 2."""
    pytest.importorskip("starleth_controller")
    path = tmp_path / "trot.mcap"
    ref = run_sim(path, steps=1000, controller="trot", wall_rtf=2.0)   # 0.5 s stand, 2 s trot
    rc, out, doc = analyse(tmp_path, [path], "--label", "trot")
    assert rc == 0
    S = doc["runs"][0]
    td = {f: S["feet"][f]["touchdowns"] for f in FEET}
    assert all(2 <= n <= 4 for n in td.values()), td       # 2 s of trot at 1.25 Hz
    assert abs(td["LF_foot"] - td["RH_foot"]) <= 1 and abs(td["RF_foot"] - td["LH_foot"]) <= 1
    for f in FEET:
        assert 0.4 < S["feet"][f]["stance_fraction"] < 0.9
    # diagonal pairs: LF and RH stance overlap almost entirely, LF and RF much less
    r = analysis_run.Run(str(path), "trot")
    t, lf = r.normal_force("LF_foot")
    _, rh = r.normal_force("RH_foot")
    _, rf = r.normal_force("RF_foot")
    trot = t > 0.7
    same = np.mean((lf[trot] > 5) == (rh[trot] > 5))
    other = np.mean((lf[trot] > 5) == (rf[trot] > 5))
    assert same > 0.85 and other < 0.6, (same, other)
    # speed: the simulator's own world velocity
    assert S["base"]["twist_frame"] == "child"
    assert S["base"]["mean_speed"] == pytest.approx(np.mean(ref["v_xy"]), rel=1e-6)
    assert S["base"]["distance"] > 0.3
    rtf = S["real_time_factor"]
    assert rtf["source"] == "publish_time" and rtf["value"] == pytest.approx(2.0, rel=1e-6)
    assert (out / "real_time_factor.png").stat().st_size > 10_000


def test_twist_frame_rotation(tmp_path):
    """Base yawed 90 deg and pitched: the body-frame twist is rotated to the world before the
    horizontal speed is taken (the vertical velocity does not count)."""
    path = tmp_path / "odom.mcap"
    w = BagWriter(path, skip=set(ALL_TOPICS) - {"/starleth/base_state"})
    half = math.radians(90) / 2
    qz = np.array([0.0, 0.0, math.sin(half), math.cos(half)])
    pitch = math.radians(30) / 2
    qy = np.array([0.0, math.sin(pitch), 0.0, math.cos(pitch)])
    x, y, z, ww = qz
    a, b, c, d = qy
    q = np.array([ww * a + x * d + y * c - z * b, ww * b - x * c + y * d + z * a,
                  ww * c + x * b - y * a + z * d, ww * d - x * a - y * b - z * c])  # qz * qy
    v_world = np.array([0.3, 0.4, 0.2])
    for k in range(200):
        w.odometry(k, [0.5 * k * 0.0025, 0.0, 0.4], q, v_world, [0, 0, 0])
    w.close()
    rc, _, doc = analyse(tmp_path, [path], "--no-plots")
    assert rc == 0
    base = doc["runs"][0]["base"]
    assert base["mean_speed"] == pytest.approx(0.5, rel=1e-9)
    assert base["max_speed"] == pytest.approx(0.5, rel=1e-9)
    # the same twist read as world-frame gives another value: the frame matters
    rc, _, doc = analyse(tmp_path, [path], "--no-plots", "--twist-frame", "parent", name="p")
    assert doc["runs"][0]["base"]["mean_speed"] != pytest.approx(0.5, rel=1e-3)


def test_gait_counting_on_a_square_wave(tmp_path):
    """Synthetic LF force: 0.1 s swing, then 5 x (0.3 s stance with a 5 ms bounce just after
    touchdown, 0.2 s swing). 5 touchdowns; 10 when short phases are kept (--min-phase 0)."""
    path = tmp_path / "square.mcap"
    w = BagWriter(path, skip=set(ALL_TOPICS) - {f"/starleth/{f}/wrench" for f in FEET})
    n = 40 + 5 * 200
    fz = np.zeros(n)
    for i in range(5):
        s = 40 + 200 * i
        fz[s:s + 120] = 60.0
        fz[s + 2:s + 4] = 0.0          # bounce: 2 samples
    for k in range(n):
        for foot in FEET:
            m = WrenchStamped()
            m.header.stamp, m.header.frame_id = stamp(k), "world"
            m.wrench.force.z = float(fz[k]) if foot == "LF_foot" else 50.0
            w.write(f"/starleth/{foot}/wrench", m, k)
    w.close()
    rc, out, doc = analyse(tmp_path, [path])
    assert rc == 0
    lf = doc["runs"][0]["feet"]["LF_foot"]
    assert lf["touchdowns"] == 5 and lf["stance_phases"] == 5
    assert lf["stance_fraction"] == pytest.approx(5 * 120 / n)
    assert doc["runs"][0]["feet"]["RF_foot"]["touchdowns"] == 0
    assert (out / "gait.png").exists() and (out / "contact_forces.png").exists()
    rc, _, doc = analyse(tmp_path, [path], "--no-plots", "--min-phase", "0", name="raw")
    assert doc["runs"][0]["feet"]["LF_foot"]["touchdowns"] == 10


def test_two_bag_overlay(tmp_path):
    """Fig. 5 style: a compliant (Cm) and a hard-contact (HmJ) drop, overlaid."""
    soft, hard = tmp_path / "soft.mcap", tmp_path / "hard.mcap"
    run_sim(soft, preset="Cm", steps=200, drop=0.05)
    run_sim(hard, preset="HmJ", steps=200, drop=0.05)
    rc, out, doc = analyse(tmp_path, [soft, hard], "--label", "compliant", "hard contact")
    assert rc == 0
    assert [S["label"] for S in doc["runs"]] == ["compliant", "hard contact"]
    for name in PLOTS + ("normal_force_LF_foot",):
        assert (out / f"{name}.png").stat().st_size > 10_000, name
    # both runs in the plots' legends; every plot has axis labels with units, a title, a legend
    opts = analysis.build_parser().parse_args([str(soft), str(hard)])
    opts.foot_given, opts.foot = False, "LF_foot"
    runs = [analysis_run.Run(str(soft), "compliant"), analysis_run.Run(str(hard), "hard contact")]
    figs = analysis_plots.make_figures(runs, opts)
    assert set(figs) == set(PLOTS) | {"normal_force_LF_foot"}
    try:
        for name, fig in figs.items():
            for ax in fig.axes:
                assert ax.get_title(), name
                assert "[" in ax.get_xlabel() and "]" in ax.get_xlabel(), (name, ax.get_xlabel())
                ylabel = ax.get_ylabel()
                assert ylabel and ("[" in ylabel or name == "gait"), (name, ylabel)
                legend = ax.get_legend()
                assert legend is not None, (name, ax.get_title())
                texts = " ".join(t.get_text() for t in legend.get_texts())
                if name != "real_time_factor" or "Sim time" in ax.get_title():
                    assert "compliant" in texts and "hard contact" in texts, (name, texts)
    finally:
        import matplotlib.pyplot as plt
        for fig in figs.values():
            plt.close(fig)
    # the runs differ (compliant penetration vs hard contact): both touch down once at ~0.1 s
    for S in doc["runs"]:
        lf = S["feet"]["LF_foot"]
        assert lf["touchdowns"] >= 1 and lf["max_normal_force"] > 100
    assert doc["runs"][0]["feet"]["LF_foot"] != doc["runs"][1]["feet"]["LF_foot"]


def test_time_window(stand_bag, tmp_path, capsys):
    path, _ = stand_bag
    rc, _, doc = analyse(tmp_path, [path], "--no-plots", "--tmin", "0.5", "--tmax", "0.75")
    assert rc == 0
    S = doc["runs"][0]
    assert S["sim_time"]["start"] == pytest.approx(0.5) and S["sim_time"]["end"] == \
        pytest.approx(0.75)
    assert S["control_steps"] == 101
    rc, _, _ = analyse(tmp_path, [path], "--no-plots", "--tmin", "5", name="empty")
    assert rc == 1 and "no messages between 5 s and the end" in capsys.readouterr().err


def test_missing_topic_warns_and_plots_the_rest(tmp_path, capsys):
    path = tmp_path / "nosolver.mcap"
    run_sim(path, steps=100, skip={"/starleth/solver", "/starleth/RH_foot/wrench"})
    rc, out, doc = analyse(tmp_path, [path])
    assert rc == 0
    err = capsys.readouterr().err
    assert "/starleth/solver" in err and "/starleth/RH_foot/wrench" in err
    assert "warning" in err
    assert sorted(doc["runs"][0]["missing_topics"]) == ["/starleth/RH_foot/wrench",
                                                        "/starleth/solver"]
    for name in ("contact_forces", "gait", "base_trajectory", "joint_torques"):
        assert (out / f"{name}.png").stat().st_size > 10_000
    assert not (out / "solver_iterations.png").exists()
    assert not (out / "real_time_factor.png").exists()   # no wall clock, no step_time
    assert set(doc["runs"][0]["feet"]) == {"LF_foot", "RF_foot", "LH_foot"}


def test_bag_without_our_topics_fails(tmp_path, capsys):
    path = tmp_path / "clock.mcap"
    w = BagWriter(path, skip=set(ALL_TOPICS) - {"/clock"})
    for k in range(10):
        w.write("/clock", Clock(clock=stamp(k)), k)
    w.close()
    rc, _, _ = analyse(tmp_path, [path])
    assert rc == 1
    err = capsys.readouterr().err
    assert "none of the StarlETH topics" in err and "/clock" in err


def test_truncated_file(stand_bag, tmp_path, capsys):
    path, _ = stand_bag
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:len(data) // 2])
    rc, out, _ = analyse(tmp_path, [cut])
    assert rc == 1
    err = capsys.readouterr().err
    assert "truncated" in err and str(cut) in err and "--salvage" in err
    assert "Traceback" not in err
    assert not out.exists()
    # --salvage: the messages before the cut
    rc, _, doc = analyse(tmp_path, [cut], "--salvage", "--no-plots", name="salvaged")
    assert rc == 0
    assert "reading stopped" in capsys.readouterr().err
    S = doc["runs"][0]
    assert S["truncated"] and 0 < S["messages"] < 9 * 401
    assert 0.1 < S["sim_time"]["duration"] < 0.9


def test_corrupt_files(stand_bag, tmp_path, capsys):
    path, _ = stand_bag
    rng = np.random.default_rng(1)
    noise = tmp_path / "noise.mcap"
    noise.write_bytes(rng.bytes(100_000))
    assert analysis.main([str(noise), "--no-plots"]) == 1
    err = capsys.readouterr().err
    assert "not an MCAP file" in err and "Traceback" not in err
    # damaged in the middle, header and footer intact: the chunk CRC catches it
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 64] = rng.bytes(64)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    assert analysis.main([str(bad), "--no-plots"]) == 1
    err = capsys.readouterr().err
    assert "corrupt MCAP file" in err and "Traceback" not in err
    # empty and missing files
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    assert analysis.main([str(empty), "--no-plots"]) == 1
    assert "empty" in capsys.readouterr().err
    assert analysis.main([str(tmp_path / "nope.mcap"), "--no-plots"]) == 1
    assert "no such file" in capsys.readouterr().err
    # magic bytes, then garbage
    fake = tmp_path / "fake.mcap"
    fake.write_bytes(bag.MCAP_MAGIC + rng.bytes(5000) + bag.MCAP_MAGIC)
    assert analysis.main([str(fake), "--no-plots"]) == 1
    assert "corrupt MCAP file" in capsys.readouterr().err


def test_console_script_exit_status(tmp_path):
    """The command line: a clear one-line error, exit status 1, no traceback."""
    noise = tmp_path / "noise.mcap"
    noise.write_bytes(os.urandom(20_000))
    p = subprocess.run([sys.executable, "-m", "starleth_sim.tools.analysis.analysis", str(noise)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 1
    assert "Traceback" not in p.stderr and "not an MCAP file" in p.stderr
    assert p.stderr.strip().count("\n") == 0
    p = subprocess.run([sys.executable, "-m", "starleth_sim.tools.analysis.analysis", str(noise),
                        str(noise), "--label", "one"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "--label" in p.stderr


def test_bag_directory(stand_bag, tmp_path):
    """A rosbag2 directory holding the .mcap file is read as one run."""
    path, _ = stand_bag
    d = tmp_path / "rosbag2_dir"
    d.mkdir()
    shutil.copy(path, d / "rosbag2_dir_0.mcap")
    rc, _, doc = analyse(tmp_path, [d], "--no-plots")
    assert rc == 0 and doc["runs"][0]["control_steps"] == 401
    assert doc["runs"][0]["label"] == "rosbag2_dir"


def test_joint_states_by_name(tmp_path):
    """A user's /joint_states: other order, an extra joint; efforts are matched by name."""
    path = tmp_path / "js.mcap"
    w = BagWriter(path, skip=set(ALL_TOPICS) - {"/joint_states"})
    names = list(reversed(STARLETH_JOINT_NAMES)) + ["sensor_joint"]
    for k in range(20):
        js = JointState(name=names, effort=[float(i + 1) for i in range(len(names))])
        js.header.stamp = stamp(k)
        w.write("/joint_states", js, k)
    w.close()
    rc, out, doc = analyse(tmp_path, [path])
    assert rc == 0
    J = doc["runs"][0]["joints"]
    assert J["max_abs"]["RH_KFE"] == 1.0 and J["max_abs"]["LF_HAA"] == 12.0
    # (no robot recorded: the joints are those /joint_states names)
    assert J["max_abs"]["sensor_joint"] == 13.0 and "ignored_joints" not in J
    assert (out / "joint_torques.png").exists()


def test_state_estimate_error_against_ground_truth(tmp_path, capsys):
    """A bag with estimator/odometry: the truth walks 0.3 m/s along x for 4 s (1.2 m) while
    the estimate runs 0.01 m/s fast in y from a 5 cm offset and turns 0.5 deg/s: velocity
    RMS 0.01 m/s, drift 4 cm / 1.2 m = 3.33 %, yaw drift 2 deg (the closed forms), and the
    plot (with --no-plots the figures alone)."""
    path = tmp_path / "estimate.mcap"
    w = BagWriter(path, skip=set(ALL_TOPICS) - {"/starleth/base_state"})
    w.rec.add_topic("/estimator/odometry", Odometry)
    n = 1601
    for k in range(n):
        t = k * PERIOD_NS * 1e-9
        yaw = math.radians(0.5) * t
        q = (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
        w.odometry(k, (0.3 * t, 0.0, 0.4), (0, 0, 0, 1), (0.3, 0.0, 0.0), (0.0, 0.0, 0.0))
        o = Odometry()
        o.header.stamp, o.header.frame_id, o.child_frame_id = stamp(k), "odom", "base"
        o.pose.pose.position.x, o.pose.pose.position.y = 0.3 * t + 0.05, 0.01 * t
        o.pose.pose.orientation.z, o.pose.pose.orientation.w = q[2], q[3]
        v = rotation(q).T @ np.array([0.3, 0.01, 0.0])
        o.twist.twist.linear.x, o.twist.twist.linear.y = float(v[0]), float(v[1])
        w.write("/estimator/odometry", o, k)
    w.close()
    rc, out, doc = analyse(tmp_path, [path])
    assert rc == 0
    e = doc["estimator"]["estimate"]
    assert e["velocity_rms"] == pytest.approx(0.01, rel=1e-6)
    assert e["distance"] == pytest.approx(1.2, rel=1e-9)
    assert e["drift"] == pytest.approx(0.04 / 1.2, rel=1e-6)
    assert e["yaw_drift_deg"] == pytest.approx(2.0, rel=1e-6)
    assert "velocity RMS 0.0100 m/s, position drift 3.33 %" in capsys.readouterr().out
    assert (out / "estimator_error.png").stat().st_size > 0
    rc, _, doc = analyse(tmp_path, [path], "--no-plots", name="plain")
    assert rc == 0 and doc["estimator"]["estimate"]["stamps"] == n
