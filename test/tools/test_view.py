"""starleth-view (starleth_sim.tools.view.view): the self-contained HTML replay of a recorded run.

Bags are written like sim_node writes them (test_analysis.run_sim: a headless Simulator run
recorded with McapRecorder), here a drop from 15 cm; plus small synthetic bags under ROS
namespaces. The page's embedded data is parsed back and checked against Pinocchio's forward
kinematics of the recorded joint states and against the recorded foot wrenches. The browser
tests (``-k browser``; ``make browser-test`` installs chromium) render the page in headless
Chromium with SwiftShader and compare screenshots at two times, of two robots, and of a
mesh robot (Go2) with and without its meshes."""
from __future__ import annotations

import json
import math
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("meshcat")

import pinocchio as pin
from geometry_msgs.msg import WrenchStamped
from mcap_ros2.reader import read_ros2_messages
from nav_msgs.msg import Odometry
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from test_analysis import run_sim, stamp

from starleth_sim.physics.description import STARLETH_JOINT_NAMES, RobotDescription, urdf_path
from starleth_sim.ros.recording import McapRecorder
from starleth_sim.tools.view import page as view_page
from starleth_sim.tools.view import view

FEET = ("LF", "RF", "LH", "RH")
DROP_STEPS = 200            # 0.5 s at 400 Hz
DROP_HEIGHT = 0.15          # run_sim's drop [m]
POS_TOL = 0.5e-4 + 1e-9     # half the rounding step (0.1 mm), plus float noise
QUAT_TOL = 0.5e-4 + 1e-9
# a frame of the landed robot (touchdown at about 0.1 s) and the first frame (in the air)
T_AIR, T_LANDED = 0.0, 0.2


# -- helpers -----------------------------------------------------------------------------
def page_json(html_text: str, element_id: str):
    """The JSON of the <script type="application/json" id=element_id> of a page."""
    m = re.search(r'<script type="application/json" id="%s">(.*?)</script>' % element_id,
                  html_text, re.S)
    assert m, element_id
    return json.loads(m.group(1))


def recorded(path):
    """{topic: {stamp ns: message}} of a bag, read with mcap_ros2 (not starleth_sim)."""
    out = {}
    for m in read_ros2_messages(str(path)):
        s = m.ros_msg.header.stamp if hasattr(m.ros_msg, "header") else None
        key = s.sec * 10 ** 9 + s.nanosec if s is not None else m.log_time_ns
        out.setdefault(m.channel.topic, {})[key] = m.ros_msg
    return out


def configuration(model, js, odom):
    """pin q of a JointState and an Odometry."""
    q = pin.neutral(model)
    for name, value in zip(js.name, js.position, strict=True):
        q[model.joints[model.getJointId(name)].idx_q] = value
    p, o = odom.pose.pose.position, odom.pose.pose.orientation
    q[:7] = (p.x, p.y, p.z, o.x, o.y, o.z, o.w)
    return q


def quat_to_rot(qx, qy, qz, qw):
    return pin.Quaternion(qw, qx, qy, qz).normalized().toRotationMatrix()


def run_view(capsys, *args):
    """view.main(args): (exit status, stdout, stderr)."""
    rc = view.main([str(a) for a in args])
    out, err = capsys.readouterr()
    return rc, out, err


# -- fixtures ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def drop(tmp_path_factory):
    """A 0.5 s drop from 15 cm recorded like sim_node, its page (default options) and the
    page's data."""
    d = tmp_path_factory.mktemp("view")
    bag = d / "drop.mcap"
    run_sim(bag, steps=DROP_STEPS, drop=DROP_HEIGHT)
    info = view.write_html(str(bag))
    text = (d / "drop.html").read_text(encoding="utf-8")
    return {"bag": bag, "html": d / "drop.html", "info": info, "text": text,
            "data": page_json(text, "replay-data"), "scene": page_json(text, "replay-scene"),
            "rec": recorded(bag)}


def write_synthetic_bag(path, namespaces=("/robot1",), steps=40, urdf=None,
                        description=True):
    """A small bag with the StarlETH state topics under each namespace: joints swinging,
    the base moving along x (offset 1 m in y per namespace), constant foot forces."""
    rec = McapRecorder(str(path))
    for ns in namespaces:
        rec.add_topic(f"{ns}/joint_states", JointState)
        rec.add_topic(f"{ns}/starleth/base_state", Odometry)
        for foot in FEET:
            rec.add_topic(f"{ns}/starleth/{foot}_foot/wrench", WrenchStamped)
        if description:
            rec.add_topic(f"{ns}/robot_description", String)
            rec.write(f"{ns}/robot_description", String(data=urdf or open(urdf_path()).read()),
                      0)
    for k in range(steps + 1):
        t = k * 0.0025
        for n, ns in enumerate(namespaces):
            js = JointState(name=list(reversed(STARLETH_JOINT_NAMES)),
                            position=[0.3 * math.sin(20 * t + i) for i in range(12)])
            js.header.stamp = stamp(k)
            rec.write(f"{ns}/joint_states", js, k * 2_500_000)
            o = Odometry()
            o.header.stamp, o.header.frame_id, o.child_frame_id = stamp(k), "world", "base"
            o.pose.pose.position.x, o.pose.pose.position.y = t, float(n)
            o.pose.pose.position.z = 0.45
            o.pose.pose.orientation.z, o.pose.pose.orientation.w = math.sin(t), math.cos(t)
            rec.write(f"{ns}/starleth/base_state", o, k * 2_500_000)
            for f, foot in enumerate(FEET):
                w = WrenchStamped()
                w.header.stamp, w.header.frame_id = stamp(k), "world"
                w.wrench.force.x, w.wrench.force.z = 1.0 * f, 50.0 + k
                rec.write(f"{ns}/starleth/{foot}_foot/wrench", w, k * 2_500_000)
    rec.close()
    return path


# -- the page ----------------------------------------------------------------------------
def test_page_is_self_contained_with_expected_frames(drop):
    text, data, info = drop["text"], drop["data"], drop["info"]
    # meshcat's viewer inlined, nothing loaded from elsewhere
    assert "MeshCat" in text and "new MeshCat.Viewer(" in text and len(text) > 800_000
    assert "meshcat/viewer/dist/main.min.js" in text
    assert not re.search(r"<script[^>]+src=|<link[^>]+href=|@import", text)
    assert "handle_command" in text
    # 0.5 s at 50 fps: 26 frames, one every 8th of the 201 samples
    assert data["format"] == view_page.FORMAT
    assert data["frames"] == info["frames"] == 26 and data["samples"] == 201
    assert data["t"] == pytest.approx([k * 0.02 for k in range(26)], abs=1e-9)
    robot, = data["robots"]
    assert robot["sample_rate"] == pytest.approx(400.0) and robot["samples"] == 201
    assert len(robot["poses"]) == 26 * len(robot["bodies"]) * 7
    assert len(robot["arrows"]) == 26 * 4 * 6
    assert robot["bodies"][robot["trunk"]] == "root_joint"
    assert robot["tf_frames"][robot["trunk"]] == "base" and robot["name"] == ""
    assert info["bytes"] == drop["html"].stat().st_size and info["namespaces"] == [""]
    assert robot["urdf_source"] == "topic /robot_description"
    # the page says how it subsamples, rounds and scales
    for phrase in ("1 in 8 samples", "latest recorded sample at or before", "0.1 mm",
                   "0.002 m/N (1 m = 500 N)", "?t=1.5&amp;paused=1"):
        assert phrase in text, phrase
    # the scene: every URDF visual under the joint that moves it, arrows, ground
    paths = [c["path"] for c in drop["scene"] if c["type"] == "set_object"]
    assert "/world/robots/base/base" in paths              # frame base, visual base
    assert "/world/robots/LF_SHANK/LF_FOOT" in paths       # the foot, merged into the shank
    assert sum(p.startswith("/world/robots/") for p in paths) == 17
    assert {f"/world/forces/{f}_foot/shaft" for f in FEET} <= set(paths)
    assert "/world/ground" in paths


def test_poses_are_forward_kinematics_of_the_recorded_states(drop):
    """Every frame: the body transforms in the page are pin's FK of the joint state recorded
    at the frame's time, to the rounding (0.1 mm, quaternions 1e-4)."""
    data, rec = drop["data"], drop["rec"]
    robot, = data["robots"]
    model = RobotDescription.from_urdf_xml(open(urdf_path()).read()).model
    fk = model.createData()
    poses = np.array(robot["poses"]).reshape(data["frames"], len(robot["bodies"]), 7)
    ids = [model.getJointId(b) for b in robot["bodies"]]
    for k, t in enumerate(data["t"]):
        key = data["t0_ns"] + round(t * 1e9)
        q = configuration(model, rec["/joint_states"][key], rec["/starleth/base_state"][key])
        pin.forwardKinematics(model, fk, q)
        for b, j in enumerate(ids):
            M = fk.oMi[j]
            assert np.abs(poses[k, b, :3] - M.translation).max() <= POS_TOL, (k, b)
            quat = pin.Quaternion(M.rotation).coeffs()
            err = min(np.abs(poses[k, b, 3:] - quat).max(), np.abs(poses[k, b, 3:] + quat).max())
            assert err <= QUAT_TOL, (k, b)
            R = quat_to_rot(*poses[k, b, 3:])
            assert np.abs(R - M.rotation).max() < 5e-4
    # the robot moves: in the air at first, landed 15 cm lower later
    trunk = poses[:, robot["trunk"], 2]
    landed = data["t"].index(T_LANDED)
    assert trunk[0] - trunk[landed] > 0.1


def test_arrows_are_recorded_wrenches_times_scale(drop, tmp_path):
    data, rec = drop["data"], drop["rec"]
    scale = data["force_scale"]
    assert scale == view.DEFAULT_FORCE_SCALE
    arrows = np.array(data["robots"][0]["arrows"]).reshape(data["frames"], 4, 6)
    desc = RobotDescription.from_urdf_xml(open(urdf_path()).read())
    model, fk = desc.model, desc.model.createData()
    contacts = {c.name: c for c in desc.contacts}
    loaded = 0
    for k, t in enumerate(data["t"]):
        key = data["t0_ns"] + round(t * 1e9)
        q = configuration(model, rec["/joint_states"][key], rec["/starleth/base_state"][key])
        pin.forwardKinematics(model, fk, q)
        for f, foot in enumerate(FEET):
            force = rec[f"/starleth/{foot}_foot/wrench"][key].wrench.force
            F = np.array([force.x, force.y, force.z])
            assert np.abs(arrows[k, f, 3:] - F * scale).max() <= POS_TOL, (k, foot)
            c = contacts[f"{foot}_foot"]
            point = fk.oMi[c.joint].act(c.local) - np.array([0, 0, c.radius])
            assert np.abs(arrows[k, f, :3] - point).max() <= POS_TOL, (k, foot)
            loaded += F[2] > 50
    assert loaded > 20                    # the landed robot stands on its feet
    assert np.all(arrows[0, :, 3:] == 0)  # in the air at t = 0
    # --force-scale: the arrows scale with it
    out = tmp_path / "half.html"
    assert view.main([str(drop["bag"]), "-o", str(out), "--force-scale", "0.001"]) == 0
    half = page_json(out.read_text(), "replay-data")
    a2 = np.array(half["robots"][0]["arrows"]).reshape(arrows.shape)
    assert np.abs(a2[:, :, 3:] * 2 - arrows[:, :, 3:]).max() <= 4 * POS_TOL
    assert "0.001 m/N (1 m = 1000 N)" in out.read_text()


def test_fps_subsampling(drop, tmp_path):
    bag = drop["bag"]
    every = view.write_html(str(bag), str(tmp_path / "all.html"), fps=1000)
    assert every["frames"] == 201                       # above the 400 Hz: every sample
    data = page_json((tmp_path / "all.html").read_text(), "replay-data")
    assert data["t"] == pytest.approx([k * 0.0025 for k in range(201)], abs=1e-9)
    assert every["bytes"] > drop["info"]["bytes"]
    # 30 fps does not divide 400 Hz: the latest sample at or before each k/30 s
    r = view.write_html(str(bag), str(tmp_path / "30.html"), fps=30)
    t = page_json((tmp_path / "30.html").read_text(), "replay-data")["t"]
    assert r["frames"] == len(t) == 16
    for k, tk in enumerate(t):
        assert k / 30 - 0.0025 < tk <= k / 30 + 1e-9
    with pytest.raises(SystemExit) as e:
        view.main([str(bag), "--fps", "0"])
    assert e.value.code == 2


def test_namespaced_bags_and_urdf_sources(tmp_path, capsys):
    """Topics under namespaces are found by suffix; every robot of a bag is drawn, or those
    picked with --namespace; robots recorded without a frame prefix are drawn under their
    namespaces (with a warning); the URDF comes from the namespace's robot_description,
    else the package."""
    narrow = open(urdf_path()).read().replace('<box size="0.60 0.37 0.16"/></geometry></visual>',
                                              '<box size="0.50 0.37 0.16"/></geometry></visual>')
    assert narrow != open(urdf_path()).read()
    bag = write_synthetic_bag(tmp_path / "two.mcap", ("/robot1", "/robot2"), urdf=narrow)
    rc, out, err = run_view(capsys, bag, "-o", tmp_path / "both.html")
    assert rc == 0 and "2 robots (robot1/, robot2/)" in out, out
    assert "recorded without tf_frame_prefix" in err and "robot1/, robot2/" in err, err
    text = (tmp_path / "both.html").read_text()
    data, scene = page_json(text, "replay-data"), page_json(text, "replay-scene")
    assert [r["namespace"] for r in data["robots"]] == ["/robot1", "/robot2"]
    assert [r["name"] for r in data["robots"]] == ["robot1/", "robot2/"]
    assert data["frames"] == 6                                             # 0.1 s at 50 fps
    assert data["robots"][0]["urdf_source"] == "topic /robot1/robot_description"
    trunk = next(c for c in scene if c["path"] == "/world/robots/robot2/base/base")
    assert trunk["object"]["geometries"][0]["width"] == 0.5
    rc, _, _ = run_view(capsys, bag, "-o", tmp_path / "two.html", "--namespace", "robot2")
    assert rc == 0
    data2 = page_json((tmp_path / "two.html").read_text(), "replay-data")
    robot, = data2["robots"]
    poses = np.array(robot["poses"]).reshape(6, len(robot["bodies"]), 7)
    assert robot["namespace"] == "/robot2" and np.allclose(poses[:, robot["trunk"], 1], 1.0)
    # FK of the synthetic joint states (names in another order than the model's)
    model = RobotDescription.from_urdf_xml(narrow).model
    fk = model.createData()
    rec = recorded(bag)
    for k, t in enumerate(data2["t"]):
        key = data2["t0_ns"] + round(t * 1e9)
        pin.forwardKinematics(model, fk, configuration(
            model, rec["/robot2/joint_states"][key], rec["/robot2/starleth/base_state"][key]))
        for b, name in enumerate(robot["bodies"]):
            assert np.abs(poses[k, b, :3] - fk.oMi[model.getJointId(name)].translation).max() \
                <= POS_TOL
    rc, _, err = run_view(capsys, bag, "--namespace", "/robot3")
    assert rc == 1 and "/robot3" in err and err.count("\n") == 1
    # no URDF in the bag: the package's
    plain = write_synthetic_bag(tmp_path / "plain.mcap", ("",), description=False)
    info = view.write_html(str(plain))
    assert info["namespaces"] == [""] and info["urdf_sources"][0].startswith("package")
    assert (tmp_path / "plain.html").exists()


def test_bad_bags_exit_1_with_one_line(drop, tmp_path, capsys):
    data = drop["bag"].read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:len(data) // 2])
    rng = np.random.default_rng(3)
    noise = tmp_path / "noise.mcap"
    noise.write_bytes(rng.bytes(50_000))
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    wrench_only = tmp_path / "wrench_only.mcap"
    rec = McapRecorder(str(wrench_only))
    rec.add_topic("/starleth/LF_foot/wrench", WrenchStamped)
    for k in range(5):
        rec.write("/starleth/LF_foot/wrench", WrenchStamped(), k)
    rec.close()
    cases = {cut: "truncated MCAP file", noise: "not an MCAP file", empty: "empty",
             tmp_path / "missing.mcap": "no such file",
             wrench_only: "no messages on joint_states (sensor_msgs/msg/JointState) nor "
                          "starleth/base_state"}
    for path, message in cases.items():
        rc, out, err = run_view(capsys, path, "-o", tmp_path / "x.html")
        assert rc == 1, path
        assert message in err and err.startswith("starleth-view: error: "), err
        assert err.count("\n") == 1 and "Traceback" not in err, err
    assert not (tmp_path / "x.html").exists()
    # --salvage replays what comes before the damage (here the bag is one chunk: cut in
    # its summary, after the messages)
    end_cut = tmp_path / "end_cut.mcap"
    end_cut.write_bytes(data[:len(data) - 200])
    rc, out, err = run_view(capsys, end_cut, "-o", tmp_path / "cut.html")
    assert rc == 1 and "truncated" in err and "--salvage" in err
    rc, out, err = run_view(capsys, end_cut, "-o", tmp_path / "cut.html", "--salvage")
    assert rc == 0 and "starleth-view: warning:" in err and "reading stopped" in err
    assert page_json((tmp_path / "cut.html").read_text(), "replay-data")["frames"] == 26
    # the console script: one line on stderr, exit status 1
    p = subprocess.run([sys.executable, "-m", "starleth_sim.tools.view.view", str(noise)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 1 and p.stderr.count("\n") == 1 and "not an MCAP" in p.stderr


def test_help_says_how_frames_are_made(capsys):
    with pytest.raises(SystemExit) as e:
        view.main(["--help"])
    assert e.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for phrase in ("--fps", "latest recorded sample at or before it", "no interpolation",
                   "0.1 mm", "quaternions to 1e-4", "--force-scale", "?t=1.5&paused=1"):
        assert phrase in text, phrase


# -- in a real browser -------------------------------------------------------------------
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
                  "--use-angle=swiftshader", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--no-first-run",
                  "--window-size=800,600"]


def chromium(tmp_path, url, *args):
    """Run headless chromium on url; returns the CompletedProcess."""
    exe = shutil.which("chromium")
    profile = tmp_path / "chromium-profile"
    return subprocess.run([exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}",
                           "--virtual-time-budget=5000", *args, url],
                          capture_output=True, text=True, timeout=180)


def robot_mask(png):
    """Pixels of the robot's orange (view_scene.ROBOT_COLOR / LEG_COLOR, shaded) in a screenshot:
    red-dominant, green about half of red, little blue; the ground and sky are grey/blue,
    the force arrows green."""
    import matplotlib.image as mpimg
    im = mpimg.imread(str(png))[..., :3]
    r, g, b = im[..., 0], im[..., 1], im[..., 2]
    return im, (r > 0.35) & (g > 0.25 * r) & (g < 0.75 * r) & (b < 0.5 * g)


@pytest.mark.serial   # a browser
def test_browser_renders_the_robot_moving(drop, tmp_path):
    if shutil.which("chromium") is None:
        reason = ("chromium not installed: run `make browser-test` (installs Debian's "
                  "chromium with apt-get, then runs these tests)")
        print(reason)
        pytest.skip(reason)
    url = drop["html"].resolve().as_uri()
    shots, dom = {}, {}
    for t in (T_AIR, T_LANDED):                  # (one run: the screenshot and the DOM)
        png = tmp_path / f"t{t}.png"
        p = chromium(tmp_path, f"{url}?t={t}&paused=1", f"--screenshot={png}", "--dump-dom")
        assert p.returncode == 0 and png.exists(), p.stderr[-2000:]
        shots[t], dom[t] = robot_mask(png), p.stdout
    (im0, m0), (im1, m1) = shots[T_AIR], shots[T_LANDED]
    assert im0.shape == (600, 800, 3)
    assert m0.sum() > 2000 and m1.sum() > 2000          # the robot is drawn
    # it moved: the orange region changed and, landing, went down in the image
    ys, xs = np.nonzero(m0 | m1)
    box = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
    assert np.abs(im0[box] - im1[box]).mean() > 0.02
    assert (m0 ^ m1).sum() > 1000
    assert np.nonzero(m1)[0].mean() - np.nonzero(m0)[0].mean() > 5
    # the page reports the frame it shows, and no script error
    body = re.search(r"<body[^>]*>", dom[T_LANDED]).group(0)
    assert 'data-ready="1"' in body and 'data-error' not in body, body
    assert f'data-frame="{drop["data"]["t"].index(T_LANDED)}"' in body, body
    assert 'data-playing="0"' in body


@pytest.mark.serial   # a browser
def test_browser_renders_two_robots_side_by_side(tmp_path):
    """Two robots of one bag (robot2 1 m to the left of robot1) in one page, with the camera
    held (follow=0, looking from the front right): the robot of the page of robot1 alone is
    drawn at the same pixels, and robot2 adds a robot of its own behind it, to its right in
    the image (partly hidden by robot1); no script error."""
    if shutil.which("chromium") is None:
        reason = ("chromium not installed: run `make browser-test` (installs Debian's "
                  "chromium with apt-get, then runs these tests)")
        print(reason)
        pytest.skip(reason)
    bag = write_synthetic_bag(tmp_path / "two.mcap", ("/robot1", "/robot2"))
    masks = {}
    for name, only in (("both", []), ("one", ["--namespace", "/robot1"])):
        page = tmp_path / f"{name}.html"
        assert view.main([str(bag), "-o", str(page), *only]) == 0
        png = tmp_path / f"{name}.png"
        url = f"{page.resolve().as_uri()}?t=0.05&paused=1&follow=0"
        p = chromium(tmp_path, url, f"--screenshot={png}", "--dump-dom")
        assert p.returncode == 0 and png.exists(), p.stderr[-2000:]
        masks[name] = robot_mask(png)[1]
        body = re.search(r"<body[^>]*>", p.stdout).group(0)
        assert 'data-ready="1"' in body and "data-error" not in body, body
    one, both = masks["one"], masks["both"]
    print(f"robot pixels: robot1 alone {one.sum()}, both robots {both.sum()}")
    assert one.sum() > 2000
    assert (one & both).sum() > 0.9 * one.sum()          # robot1 where it was
    added = both & ~one                                    # and robot2 beside it
    assert added.sum() > 1000
    assert np.nonzero(added)[1].mean() > np.nonzero(one)[1].mean() + 50


def components(mask):
    """Sizes of the 4-connected components of a boolean image, largest first (labels
    spread as each pixel's smallest neighbour label until nothing changes)."""
    big = mask.size + 1
    lab = np.where(mask, np.arange(mask.size).reshape(mask.shape), big)
    while True:
        m = lab.copy()
        m[1:] = np.minimum(m[1:], lab[:-1])
        m[:-1] = np.minimum(m[:-1], lab[1:])
        m[:, 1:] = np.minimum(m[:, 1:], lab[:, :-1])
        m[:, :-1] = np.minimum(m[:, :-1], lab[:, 1:])
        m = np.where(mask, m, big)
        if np.array_equal(m, lab):
            break
        lab = m
    return sorted(np.unique(lab[mask], return_counts=True)[1], reverse=True)


@pytest.mark.serial   # a browser
def test_browser_draws_a_mesh_robot_whole(tmp_path):
    """Go2 (visual meshes of several materials each) standing: the pixels its meshes cover
    (the page against the same page without them) are one piece, trunk, legs and feet
    joined (its DAE parts read with their own vertices: coal's loader left the thighs out
    and the calves apart, 93% in one piece)."""
    if shutil.which("chromium") is None:
        reason = ("chromium not installed: run `make browser-test` (installs Debian's "
                  "chromium with apt-get, then runs these tests)")
        print(reason)
        pytest.skip(reason)
    from test_view_robots import write_robot_bag
    write_robot_bag(tmp_path / "go2.mcap", "go2")
    assert view.main([str(tmp_path / "go2.mcap")]) == 0
    text = (tmp_path / "go2.html").read_text(encoding="utf-8")
    scene = page_json(text, "replay-scene")
    bare = [c for c in scene if not c["path"].startswith("/world/robots/")]
    assert len(bare) < len(scene)
    m = re.search(r'<script type="application/json" id="replay-scene">(.*?)</script>', text,
                  re.S)
    (tmp_path / "bare.html").write_text(text[:m.start(1)] + view_page._script_json(bare)
                                        + text[m.end(1):], encoding="utf-8")
    import matplotlib.image as mpimg
    shots = {}
    for name in ("go2", "bare"):
        png = tmp_path / f"{name}.png"
        url = f"{(tmp_path / f'{name}.html').resolve().as_uri()}?t=0&paused=1"
        p = chromium(tmp_path, url, f"--screenshot={png}")
        assert p.returncode == 0 and png.exists(), p.stderr[-2000:]
        shots[name] = mpimg.imread(str(png))[..., :3]
    robot = np.abs(shots["go2"] - shots["bare"]).max(axis=2) > 0.01   # the same renderer
    sizes = components(robot)
    print(f"robot pixels {robot.sum()}, pieces {sizes[:5]}")
    assert robot.sum() > 3000
    assert sizes[0] > 0.98 * robot.sum()
