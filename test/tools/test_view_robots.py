"""starleth-view for the robots of the library (issue #46, item 8): a bag recorded like
sim_node records another robot (its URDF and spec attachments named in the 'starleth_sim'
metadata) is drawn from that robot alone: its bodies and feet from its URDF and spec, its
visual meshes (package:// under the spec's package roots) within the page's triangle
budget, the page titled with its name; a mesh that cannot be read is one warning line and
the link's primitives. Small synthetic bags (a few states), so each test costs seconds."""
from __future__ import annotations

import json
import math
import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("meshcat")

from geometry_msgs.msg import WrenchStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import JointState
from test_analysis import stamp

from starleth_interface.robot.scaling import robot_scale
from starleth_interface.topics import foot_wrench_topic
from starleth_sim.robots import load_robot, package_dirs, robot_description, spec_text, urdf_file
from starleth_sim.robots.meshes import read_mesh, resolve_mesh, simplified
from starleth_sim.ros.recording import McapRecorder
from starleth_sim.ros.tf import base_link
from starleth_sim.tools.view import scene as view_scene
from starleth_sim.tools.view import view


def robot_or_skip(name):
    try:
        return robot_description(name)
    except Exception as e:   # example-robot-data not installed: make robots
        pytest.skip(f"{name}: {e}")


def write_robot_bag(path, robot, urdf=None, steps=10):
    """A bag of `robot` (a library name) standing still with its URDF (or `urdf`) and spec
    attached as sim_node attaches them, its feet pushing 10 N * (k + 1) each."""
    desc = robot_or_skip(robot)
    urdf = urdf or desc.urdf_xml
    rec = McapRecorder(str(path))
    rec.add_metadata("starleth_sim", {"robot": robot, "urdf_attachment": f"{robot}.urdf",
                                      "robot_spec_attachment": f"{robot}.robot.yaml"})
    rec.add_attachment(f"{robot}.urdf", "application/xml", urdf)
    rec.add_attachment(f"{robot}.robot.yaml", "application/yaml", spec_text(robot))
    rec.add_topic("/joint_states", JointState)
    rec.add_topic("/starleth/base_state", Odometry)
    for foot in desc.foot_names:
        rec.add_topic("/" + foot_wrench_topic(foot), WrenchStamped)
    q = desc.standing_joints()
    for k in range(steps):
        js = JointState(name=list(desc.joint_names), position=[float(x) for x in q])
        js.header.stamp = stamp(k)
        rec.write("/joint_states", js, k * 2_500_000)
        o = Odometry()
        o.header.stamp, o.child_frame_id = stamp(k), base_link(urdf)
        o.pose.pose.position.z, o.pose.pose.orientation.w = desc.standing_height, 1.0
        rec.write("/starleth/base_state", o, k * 2_500_000)
        for f, foot in enumerate(desc.foot_names):
            w = WrenchStamped()
            w.header.stamp = stamp(k)
            w.wrench.force.z = 10.0 * (f + 1)
            rec.write("/" + foot_wrench_topic(foot), w, k * 2_500_000)
    rec.close()
    return desc


def page(path):
    text = path.read_text(encoding="utf-8")
    parts = {}
    for element in ("replay-data", "replay-scene"):
        m = re.search(r'<script type="application/json" id="%s">(.*?)</script>' % element,
                      text, re.S)
        parts[element] = json.loads(m.group(1))
    return text, parts["replay-data"], parts["replay-scene"]


def mesh_triangles(scene) -> list:
    """[(path, triangles)] of the page's mesh objects (BufferGeometry with an index)."""
    out = []
    for cmd in scene:
        if cmd["type"] == "set_object" and cmd["path"].startswith("/world/robots/"):
            g = cmd["object"]["geometries"][0]
            if g["type"] == "BufferGeometry":
                out.append((cmd["path"], len(g["data"]["index"]["array"]) // 3))
    return out


# go2: meshes only; anymal_c: a link and a joint of one name
@pytest.mark.parametrize("robot", ["go1", "go2", "anymal_c"])
def test_a_robot_bag_is_drawn_with_its_meshes_within_the_budget(robot, tmp_path, capsys):
    desc = write_robot_bag(tmp_path / "run.mcap", robot)
    assert view.main([str(tmp_path / "run.mcap")]) == 0
    err = capsys.readouterr().err
    assert "warning" not in err, err
    text, data, scene = page(tmp_path / "run.html")
    assert f"<title>{robot} replay: run.mcap</title>" in text
    r = data["robots"][0]
    assert r["robot"] == robot and r["feet"] == list(desc.foot_names)
    assert r["has_force"] == [True] * len(desc.foot_names)
    meshes = mesh_triangles(scene)
    # every visual of the URDF is a mesh: each drawn as one, the whole within the budget
    visuals = re.findall(r"<visual>.*?</visual>", desc.urdf_xml, re.S)
    assert len(meshes) == sum("<mesh" in v for v in visuals) > 0
    assert sum(n for _, n in meshes) <= view_scene.PAGE_TRIANGLES
    # sized to the robot: its weight's arrow as long against its legs as StarlETH's, the
    # camera as far against them (λ, μ: leg length and mass over StarlETH's)
    s = robot_scale(desc.legs, desc.total_mass)
    starleth = robot_description("starleth")
    assert desc.total_mass * data["force_scale"] / s.length == pytest.approx(
        starleth.total_mass * view.DEFAULT_FORCE_SCALE, rel=0.05)
    assert data["camera"]["offset"] == pytest.approx(
        [s.length * c for c in view_scene.CAMERA_OFFSET])
    # the arrows: the recorded forces times the scale, from each foot in the URDF's order
    arrows = np.array(r["arrows"]).reshape(-1, len(desc.foot_names), 6)
    assert arrows[0, :, 5] == pytest.approx([10.0 * (f + 1) * data["force_scale"]
                                             for f in range(len(desc.foot_names))], abs=1e-4)


def test_simplification_keeps_the_mesh_within_its_share_and_its_extent():
    spec = load_robot("go1") if robot_or_skip("go1") else None
    path = resolve_mesh("package://example-robot-data/robots/go1_description/meshes/trunk.dae",
                        package_dirs(spec))
    v, t = read_mesh(path)
    for budget in (50_000, 2_000, 100):
        sv, st = simplified(v, t, budget)
        assert 0 < len(st) <= budget and st.max() < len(sv)
        # clustering moves vertices to their cell's mean: inside the original bounds
        assert np.all(sv.min(axis=0) >= v.min(axis=0) - 1e-9)
        assert np.all(sv.max(axis=0) <= v.max(axis=0) + 1e-9)
    assert urdf_file(spec).endswith("go1.urdf")


def test_an_unreadable_mesh_is_one_warning_and_primitives(tmp_path, capsys):
    go1 = robot_or_skip("go1")
    bad = tmp_path / "broken.stl"
    bad.write_bytes(b"solid nothing\nthis is not an STL file\n")
    uri = "package://example-robot-data/robots/go1_description/meshes/calf.dae"
    assert go1.urdf_xml.count(uri) == 4
    write_robot_bag(tmp_path / "run.mcap", "go1", urdf=go1.urdf_xml.replace(uri, str(bad)))
    assert view.main([str(tmp_path / "run.mcap")]) == 0
    lines = [x for x in capsys.readouterr().err.splitlines() if "warning" in x]
    assert len(lines) == 1 and str(bad) in lines[0] and "primitives" in lines[0], lines
    assert all(f"{leg}_calf" in lines[0] for leg in ("FL", "FR", "RL", "RR"))
    _, _, scene = page(tmp_path / "run.html")
    calf = [c["object"]["geometries"][0]["type"] for c in scene if c["type"] == "set_object"
            and re.search(r"/world/robots/\w\w_calf/\w\w_calf(_\d+)?$", c["path"])]
    # each calf: its collision primitives instead of its mesh
    link = ET.fromstring(go1.urdf_xml).find("link[@name='FL_calf']")
    primitives = [c.find("geometry")[0].tag for c in link.findall("collision")]
    assert len(calf) == 4 * len(primitives) > 0 and "BufferGeometry" not in calf
    assert sorted(set(calf)) == sorted({f"{p.capitalize()}Geometry" for p in primitives})


def test_a_recorded_robot_is_drawn_without_the_library_packages(tmp_path, capsys,
                                                                 monkeypatch):
    """Meshes that are not on this machine: one warning per file, the robot still drawn
    (its primitives) and named."""
    robot_or_skip("go1")
    write_robot_bag(tmp_path / "run.mcap", "go1")
    monkeypatch.setattr("starleth_sim.tools.view.page.spec_package_roots",
                        lambda _spec, _name: [str(tmp_path)])
    monkeypatch.setattr("starleth_sim.robots.meshes._package_share", lambda _package: None)
    assert view.main([str(tmp_path / "run.mcap")]) == 0
    lines = capsys.readouterr().err.splitlines()
    files = {re.search(r"mesh (\S+):", x).group(1) for x in lines if "warning" in x}
    assert len(lines) == len(files) > 0 and all("no such file" in x for x in lines)
    text, data, scene = page(tmp_path / "run.html")
    assert "<title>go1 replay" in text and not mesh_triangles(scene)
    r = data["robots"][0]
    assert math.isclose(r["poses"][r["trunk"] * 7 + 2], robot_or_skip("go1").standing_height,
                        abs_tol=1e-4)


def test_the_foxglove_layout_of_go1_follows_its_base_and_plots_its_feet(tmp_path, capsys):
    """starleth-layout --robot go1: the camera on Go1's root link, one force path per Go1
    foot (its topic as the simulator names it); everything else as shipped; StarlETH's
    layout unchanged; an unknown robot: one line, exit 2."""
    from starleth_sim.tools.view import foxglove_layout
    go1 = robot_or_skip("go1")
    shipped = json.load(open(foxglove_layout.shipped_layout_path()))
    out = tmp_path / "go1.json"
    assert foxglove_layout.main(["--robot", "go1", "-o", str(out)]) == 0
    layout = json.loads(out.read_text())
    three_d = layout["configById"]["3D!starleth"]
    assert three_d["followTf"] == base_link(go1.urdf_xml)
    forces = layout["configById"]["Plot!footforces"]["paths"]
    assert [p["value"] for p in forces] == [f"/{foot_wrench_topic(f)}.wrench.force.z"
                                            for f in go1.foot_names]
    assert [p["label"] for p in forces] == list(go1.foot_names)
    for key in ("Plot!solver", "layout"):
        assert layout.get(key, layout["configById"].get(key)) == \
            shipped.get(key, shipped["configById"].get(key))
    assert foxglove_layout.robot_layout(shipped, "starleth") == shipped
    with pytest.raises(SystemExit) as e:
        foxglove_layout.main(["--robot", "no_such_robot"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "unknown robot 'no_such_robot'" in err.splitlines()[-1]
