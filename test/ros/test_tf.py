"""TF and contact markers in sim_node's recordings (issue #12): the CDR of TFMessage against
rosbags' serialiser, the frame tree of a recorded bag, its transforms against Pinocchio's
forward kinematics, the markers against the recorded wrenches."""
import os

import numpy as np
import pinocchio as pin
import pytest

rclpy = pytest.importorskip("rclpy")

from mcap_ros2.reader import read_ros2_messages
from repo_root import ROOT
from rosbags.typesys import Stores, get_typestore
from tf_trees import world_poses

from starleth_sim.robots import starleth_description
from starleth_sim.ros.tf import FrameTree, TfMessageCdr, urdf_joint_edges

DOMAIN_RANGE = (199, 30)      # first, span
DOMAIN_ID = 199 + os.getpid() % 30  # conftest._free_ros_domain: a free one of the range
def test_tf_message_cdr_is_what_rosbags_serialises():
    ts = get_typestore(Stores.ROS2_JAZZY)
    T = ts.types
    frames = [("world", "base"), ("base", "LF_HIP"), ("", "x"), ("a_long_parent_name", "c")]
    rng = np.random.default_rng(0)
    poses = rng.standard_normal((len(frames), 7))
    data = TfMessageCdr(frames).build(12, 345_000_000, poses)
    msg = T["tf2_msgs/msg/TFMessage"](transforms=[
        T["geometry_msgs/msg/TransformStamped"](
            header=T["std_msgs/msg/Header"](
                stamp=T["builtin_interfaces/msg/Time"](sec=12, nanosec=345_000_000),
                frame_id=p),
            child_frame_id=c,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=x[0], y=x[1], z=x[2]),
                rotation=T["geometry_msgs/msg/Quaternion"](x=x[3], y=x[4], z=x[5], w=x[6])))
        for (p, c), x in zip(frames, poses, strict=True)])
    ref = bytes(ts.serialize_cdr(msg, "tf2_msgs/msg/TFMessage"))
    assert data == ref
    back = ts.deserialize_cdr(data, "tf2_msgs/msg/TFMessage")
    assert back.transforms[3].header.frame_id == "a_long_parent_name"
    assert back.transforms[1].transform.rotation.w == poses[1, 6]


def test_frame_tree_is_the_urdf_joint_tree():
    desc = starleth_description()
    edges = urdf_joint_edges(desc.urdf_xml)
    tree = FrameTree(desc.model, desc.urdf_xml)
    assert tree.root == "base"
    assert len(tree.dynamic) == 1 + 12 and len(tree.static) == 4
    assert {c for _, c in tree.static} == {f"{leg}_FOOT" for leg in ("LF", "RF", "LH", "RH")}
    assert {e.child for e in edges} | {"base"} == {c for _, c in tree.dynamic + tree.static}


def record_headless(path, parameters, steps, before_step=None):
    """A headless sim_node (in this process, its own ROS context) with `parameters`,
    recording to `path` while it takes `steps` steps (`before_step(service, k)` first, if
    given); returns the node and the bag's messages by topic."""
    from starleth_sim.ros.sim_node import SimNode
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN_ID)
    node = SimNode(context=ctx, parameter_overrides={"mode": "lockstep", "record": path,
                                                     **parameters})
    try:
        svc = node.service
        node.publisher.publish_state()
        for k in range(steps):
            if before_step is not None:
                before_step(svc, k)
            svc.step()
            node.publisher.publish_state()
    finally:
        node.destroy()
        rclpy.try_shutdown(context=ctx)
    msgs = {}
    for m in read_ros2_messages(path):
        msgs.setdefault(m.channel.topic, []).append(m)
    return node, msgs


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """200 steps recorded: the robot collapses under zero torques (every joint moves), then a
    push."""
    def push(svc, k):
        if k == 150:
            svc.submit_wrench("base", (0.0, 400.0, 0.0), (0.0, 0.0, 0.0), False)
    return record_headless(str(tmp_path_factory.mktemp("tf") / "tf.mcap"),
                           {"tf_rate": 100.0, "contact_markers_rate": 400.0}, 200, push)


def _stamp(msg):
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def test_recorded_frame_tree_connects_world_to_every_link(recorded):
    node, msgs = recorded
    assert len(msgs["/tf"]) == 200 // 4 + 1 and len(msgs["/tf_static"]) == 1   # k = 0, 4, ...
    assert msgs["/tf"][0].schema.name == "tf2_msgs/msg/TFMessage"
    parent = {}
    for m in (msgs["/tf_static"][0], msgs["/tf"][0]):
        for t in m.ros_msg.transforms:
            assert t.child_frame_id not in parent
            parent[t.child_frame_id] = t.header.frame_id
    links = {lnk.get("name") for lnk in
             __import__("xml.etree.ElementTree", fromlist=["x"]).fromstring(
                 node.sim.description.urdf_xml).findall("link")}
    assert set(parent) == links
    for link in links:
        seen, f = set(), link
        while f != "world":
            assert f not in seen and f in parent, f"{link} is not connected to world"
            seen.add(f)
            f = parent[f]
    qos = msgs["/tf_static"][0].channel.metadata["offered_qos_profiles"]
    assert "durability: transient_local" in qos


def test_recorded_transforms_agree_with_pinocchio_forward_kinematics(recorded):
    node, msgs = recorded
    desc = node.sim.description
    model, data = desc.model, desc.model.createData()
    joints = {_stamp(m.ros_msg): m.ros_msg for m in msgs["/joint_states"]}
    bases = {_stamp(m.ros_msg): m.ros_msg for m in msgs["/starleth/base_state"]}
    checked = 0
    for m in msgs["/tf"][::5]:
        tfs = m.ros_msg.transforms
        stamp = _stamp(tfs[0])
        js, base = joints[stamp], bases[stamp]
        q = np.zeros(model.nq)
        p, o = base.pose.pose.position, base.pose.pose.orientation
        q[:7] = [p.x, p.y, p.z, o.x, o.y, o.z, o.w]
        for name, angle in zip(js.name, js.position, strict=True):
            q[model.joints[model.getJointId(name)].idx_q] = angle
        pin.framesForwardKinematics(model, data, q)
        world = world_poses(list(tfs) + list(msgs["/tf_static"][0].ros_msg.transforms))
        assert len(world) == 1 + len(tfs) + len(msgs["/tf_static"][0].ros_msg.transforms)
        for link, M in world.items():
            if link == "world":
                continue
            ref = data.oMf[model.getFrameId(link)]
            assert np.abs(M.translation - ref.translation).max() < 1e-9, link
            assert np.abs(M.rotation - ref.rotation).max() < 1e-9, link
        checked += 1
    assert checked >= 10
    # the robot moved: the LF shank frame is not where it started
    first = {t.child_frame_id: t for t in msgs["/tf"][0].ros_msg.transforms}
    last = {t.child_frame_id: t for t in msgs["/tf"][-1].ros_msg.transforms}
    assert abs(first["LF_SHANK"].transform.rotation.x - last["LF_SHANK"].transform.rotation.x) \
        + abs(first["base"].transform.translation.z - last["base"].transform.translation.z) > 1e-3


def test_contact_markers_show_the_recorded_wrenches(recorded):
    node, msgs = recorded
    scale = node.settings.contact_marker_scale
    names = node.sim.contact_names
    wrenches = {f: {_stamp(m.ros_msg): m.ros_msg.wrench.force
                    for m in msgs[f"/starleth/{f}/wrench"]}
                for f in node.sim.description.foot_names}
    states_seen = set()
    n_arrows = 0
    assert len(msgs["/starleth/contact_markers"]) == 201
    for m in msgs["/starleth/contact_markers"]:
        markers = m.ros_msg.markers
        assert len(markers) == 2 * len(names)
        spheres = {mk.id: mk for mk in markers if mk.ns == "contacts"}
        arrows = {mk.id: mk for mk in markers if mk.ns == "contact_forces"}
        for foot in node.sim.description.foot_names:
            i = names.index(foot)
            f = wrenches[foot][_stamp(arrows[i])]
            sphere, arrow = spheres[i], arrows[i]
            colour = (round(sphere.color.r, 2), round(sphere.color.g, 2), round(sphere.color.b, 2))
            states_seen.add(colour)
            if f.z > 0:
                assert arrow.action == 0 and arrow.type == 0          # ADD, ARROW
                a, b = arrow.points
                np.testing.assert_allclose([b.x - a.x, b.y - a.y, b.z - a.z],
                                           [scale * f.x, scale * f.y, scale * f.z], atol=1e-12)
                assert (a.x, a.y, a.z) == (sphere.pose.position.x, sphere.pose.position.y,
                                           sphere.pose.position.z)
                n_arrows += 1
            else:
                assert arrow.action == 2                              # DELETE
                assert colour == (0.6, 0.6, 0.6)                      # open: grey
    assert n_arrows > 100
    assert (0.1, 0.75, 0.2) in states_seen                            # stick: green


def test_foxglove_layout_shows_what_sim_node_records(recorded):
    """The shipped layout: a 3D panel following `base` with the URDF and the contact markers,
    plots of the four foot normal forces and of the solver iterations; every topic it names
    is in a recording and every field path exists on the recorded messages; starleth-layout
    without a namespace gives it as it is."""
    import json

    from layout_checks import check_layout

    from starleth_sim.tools.view import foxglove_layout
    root = ROOT
    layout = json.load(open(os.path.join(root, "foxglove", "starleth_layout.json")))
    node, msgs = recorded
    three_d = layout["configById"]["3D!starleth"]
    assert three_d["followTf"] == "base"
    tf_children = {t.child_frame_id for m in msgs["/tf"][:1] + msgs["/tf_static"]
                   for t in m.ros_msg.transforms}
    topics, layers, n_paths = check_layout(layout, msgs, tf_children)
    assert sorted(topics) == ["/robot_description", "/starleth/contact_markers", "/terrain"]
    assert "/terrain" not in msgs and layers == [] and n_paths == 5
    assert foxglove_layout.namespaced_layout(layout, foxglove_layout.robots([])) == layout


def test_starleth_layout_refuses_what_is_not_a_namespace_or_a_prefix(tmp_path, capsys):
    """Bad arguments: one usage line and exit 2; a layout with a panel it cannot rewrite:
    one line and exit 1."""
    import json

    from starleth_sim.tools.view import foxglove_layout
    for args, words in ((["robot 1"], "not a ROS namespace"),
                        (["robot1", "/robot1"], "named twice"),
                        (["robot1", "--frame-prefix", "/r1/"], "must not start with '/'"),
                        (["--frame-prefix", "r1/"], "1 --frame-prefix for 0 namespace")):
        with pytest.raises(SystemExit) as e:
            foxglove_layout.main(args)
        assert e.value.code == 2 and words in capsys.readouterr().err, args
    odd = tmp_path / "odd.json"
    odd.write_text(json.dumps({"configById": {"Map!x": {}}, "layout": "Map!x"}))
    assert foxglove_layout.main(["robot1", "--layout", str(odd)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "a Map panel is not handled here" in err, err


@pytest.fixture(scope="module")
def prefixed(tmp_path_factory):
    """20 steps of a sim_node with tf_frame_prefix robot1/ (TF and markers every step),
    pushed at step 5 on its frame robot1/base, on the link name LF_SHANK and on robot2/base
    (another robot's frame); returns the node, the bag's messages and the pushes' answers."""
    answers = []

    def push(svc, k):
        if k == 5:
            for frame in ("robot1/base", "LF_SHANK", "robot2/base"):
                answers.append(svc.submit_wrench(frame, (0.0, 50.0, 0.0), (0.0, 0.0, 0.0)))
    node, msgs = record_headless(str(tmp_path_factory.mktemp("prefix") / "prefixed.mcap"),
                                 {"tf_frame_prefix": "robot1/", "tf_rate": 400.0,
                                  "contact_markers_rate": 400.0}, 20, push)
    return node, msgs, answers


def test_a_frame_prefix_names_every_frame_of_the_robot(prefixed):
    """tf_frame_prefix robot1/: every link's frame on /tf and /tf_static is robot1/<link>,
    world (unprefixed, shared) the parent of robot1/base; the odometry's child frame and the
    IMU's frame are robot1/base, the foot wrenches and the contact markers in world: every
    frame a message names is in the tree. A wrench names its link by its frame or by the
    URDF's name; another robot's frame is rejected."""
    import json
    import xml.etree.ElementTree as ET
    node, msgs, answers = prefixed
    links = {lnk.get("name") for lnk in ET.fromstring(node.sim.description.urdf_xml)
             .findall("link")}
    parent = {t.child_frame_id: t.header.frame_id
              for m in msgs["/tf_static"][:1] + msgs["/tf"][:1] for t in m.ros_msg.transforms}
    assert set(parent) == {f"robot1/{lnk}" for lnk in links}
    assert parent.pop("robot1/base") == "world"
    assert all(p.startswith("robot1/") for p in parent.values())
    tree = set(parent) | {"robot1/base", "world"}
    odom = msgs["/starleth/base_state"][-1].ros_msg
    assert (odom.header.frame_id, odom.child_frame_id) == ("world", "robot1/base")
    assert msgs["/starleth/imu"][-1].ros_msg.header.frame_id == "robot1/base"
    named = {m.ros_msg.header.frame_id for f in node.sim.description.foot_names
             for m in msgs[f"/starleth/{f}/wrench"]}
    named |= {mk.header.frame_id for m in msgs["/starleth/contact_markers"]
              for mk in m.ros_msg.markers}
    assert named == {"world"} and named <= tree
    assert [ok for ok, _ in answers] == [True, True, False]
    assert "unknown link 'robot2/base'" in answers[2][1] and "robot1/<link>" in answers[2][1]
    assert node.service.counters["wrenches_accepted"] == 2
    from mcap.reader import make_reader
    with open(node.settings.record, "rb") as f:
        md = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert json.loads(md["starleth_sim"]["parameters"])["tf_frame_prefix"] == "robot1/"


def test_frames_are_checked_at_start(capfd):
    """base_frame must be the URDF's root link, a frame name must not start with '/' nor
    hold white space: a ConfigError naming the parameter. A namespaced sim_node without a
    prefix says how to set one (the launch file's convention)."""
    from starleth_sim.physics.config import ConfigError
    from starleth_sim.ros.sim_node import SimNode
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN_ID, args=["--ros-args", "-r", "__ns:=/robot9"])
    try:
        for bad, words in (({"base_frame": "base_link"}, ("base_frame", "'base_link'",
                                                           "root link", "('base')")),
                           ({"tf_frame_prefix": "/robot9/"}, ("tf_frame_prefix", "'/'")),
                           ({"world_frame": "my world"}, ("world_frame", "white space"))):
            with pytest.raises(ConfigError) as e:
                SimNode(context=ctx, parameter_overrides={"mode": "lockstep", **bad})
            assert all(w in str(e.value) for w in words), (words, str(e.value))
        capfd.readouterr()
        SimNode(context=ctx, parameter_overrides={"mode": "lockstep"}).destroy()
        err = capfd.readouterr().err
        assert "namespace /robot9 without tf_frame_prefix" in err, err
        assert "tf_frame_prefix:=robot9/" in err
    finally:
        rclpy.try_shutdown(context=ctx)


# a terrain away from the robot's feet: two steps in front, a box beside, rough ground behind
TERRAIN = ("{stairs: {rise: 0.04, run: 0.3, count: 2, start: 0.7}, "
           "boxes: [{centre: [0.0, 1.2, 0.05], size: [0.2, 0.3, 0.1], yaw: 0.5}], "
           "rough: {amplitude: 0.01, wavelength: 0.5, size: 1.5, seed: 3, centre: [-1.8, 0.0]}}")


@pytest.fixture(scope="module")
def terrain_recorded(tmp_path_factory):
    """A headless sim_node on TERRAIN (physics_overrides) recording 20 steps."""
    return record_headless(str(tmp_path_factory.mktemp("terrain") / "terrain.mcap"),
                           {"physics_overrides": TERRAIN}, 20)


def test_terrain_is_recorded_once_at_start_as_the_physics_sees_it(terrain_recorded):
    """/terrain: one latched MarkerArray at t = 0 in the world frame; each box (the stairs'
    included) a cube with the configured centre, size and yaw; the heightfield a triangle
    list whose every vertex lies on the surface the contact query uses (physics.terrain's
    terrain_height of the packed terrain); the plane a thin cube just below z = 0."""
    from starleth_sim.physics.terrain import pack_terrain, terrain_height
    from starleth_sim.ros.terrain_markers import GROUND_DROP
    node, msgs = terrain_recorded
    assert len(msgs["/terrain"]) == 1
    m = msgs["/terrain"][0]
    assert m.log_time_ns == 0 and m.schema.name == "visualization_msgs/msg/MarkerArray"
    assert "durability: transient_local" in m.channel.metadata["offered_qos_profiles"]
    markers = m.ros_msg.markers
    by_ns = {}
    for mk in markers:
        assert mk.header.frame_id == "world" and mk.action == 0
        by_ns.setdefault(mk.ns, []).append(mk)
    assert sorted((k, len(v)) for k, v in by_ns.items()) == \
        [("boxes", 3), ("ground", 1), ("heightfield", 1)]
    (ground,) = by_ns["ground"]
    assert ground.type == 1 and ground.scale.x >= 10.0
    assert ground.pose.position.z + 0.5 * ground.scale.z == pytest.approx(-GROUND_DROP, abs=1e-12)
    cfg = node.sim.config
    boxes = cfg.terrain.all_boxes(cfg.ground.height)
    assert [b["centre"][0] for b in boxes] == [0.0, 0.7 + 0.15, 0.7 + 0.3 + 0.65]
    for mk, b in zip(by_ns["boxes"], boxes, strict=True):
        assert mk.type == 1
        p, o, sc = mk.pose.position, mk.pose.orientation, mk.scale
        assert [p.x, p.y, p.z] == b["centre"] and [sc.x, sc.y, sc.z] == b["size"]
        assert 2 * np.arctan2(o.z, o.w) == pytest.approx(b["yaw"], abs=1e-12)
    (hf,) = by_ns["heightfield"]
    assert hf.type == 11 and len(hf.points) == len(hf.colors) > 0 and len(hf.points) % 3 == 0
    packed = pack_terrain(cfg.terrain, cfg.ground.height, cfg.ground.mu)
    pts = np.array([[q.x, q.y, q.z] for q in hf.points])
    assert pts[:, 0].min() == pytest.approx(-2.55) and pts[:, 0].max() == pytest.approx(-1.05)
    assert np.abs(pts[:, 2]).max() > 0.005
    for x, y, z in pts[::7]:
        assert z == pytest.approx(terrain_height(packed, x, y), abs=1e-12)


def test_shipped_terrain_presets_run_in_sim_node():
    """-p physics:=terrain/stairs.yaml finds the shipped file (msg_configs/terrain/) from any
    directory: HmJ's physics with the stairs; the topic is added with a terrain only."""
    from starleth_sim.ros.sim_node import SimNode
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN_ID)
    cwd = os.getcwd()
    try:
        os.chdir("/")
        node = SimNode(context=ctx, parameter_overrides={"physics": "terrain/stairs.yaml",
                                                         "mode": "lockstep"})
        try:
            assert node.sim.config.name == "stairs" and node.sim.config.solver.alpha == 0.6
            assert len(node.sim.config.terrain.all_boxes()) == 3
            assert "terrain" in node.output.pubs and len(node.terrain.msg.markers) == 4
        finally:
            node.destroy()
    finally:
        os.chdir(cwd)
        rclpy.try_shutdown(context=ctx)
