"""The robot library (robots/*.yaml, starleth_sim.robots) on every robot: it builds (legs and
sides from the tree and the geometry, joints in URDF document order), the standing posture
puts every foot on the ground at the spec's height, it stands under the scaled posture hold
on HmJ (end-of-step foot penetration at most 1 µm, the weight on the feet), all 11 presets
run and its three coordinate sets agree within 1e-4. StarlETH's description from its spec is
the one the simulator always had, field by field and bit for bit. The scaling rule is checked
on a StarlETH twice as large.

The robots of example-robot-data skip, saying so, where that package is missing
(`make robots`)."""
import os
import re
import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin
import pytest
from coordinate_checks import TIGHT, compare_three
from robot_cases import needs_data

from starleth_interface.robot.scaling import robot_scale
from starleth_sim import PRESETS, Simulator
from starleth_sim.physics.description import STARLETH_FEET, STARLETH_JOINT_NAMES, urdf_path
from starleth_sim.physics.posture import DEFAULT_KD, DEFAULT_KP, PostureHold
from starleth_sim.robots import (
    available_robots,
    load_robot,
    robot_description,
    starleth_description,
)

ROBOTS = available_robots()
G = 9.81
OLD_STANDING_HEIGHT = 0.415


def test_the_library_holds_starleth_and_the_example_robot_data_quadrupeds():
    assert set(ROBOTS) == {"starleth", "a1", "anymal_b", "anymal_c", "b1", "go1", "go2", "hyq",
                           "solo12"}


# -- StarlETH: the description the simulator always had --------------------------------------
def old_contacts(xml, model):
    """The contact points as the simulator always read them: every <collision> sphere (its
    centre, radius) and box (8 corners) in document order, then sorted feet, knees, rest."""
    points = []
    for link in ET.fromstring(xml).findall("link"):
        for coll in link.findall("collision"):
            frame = model.frames[model.getFrameId(link.get("name"))]
            o = coll.find("origin")
            xyz = np.array([float(v) for v in o.get("xyz").split()]) if o is not None \
                else np.zeros(3)
            placement = frame.placement * pin.SE3(np.eye(3), xyz)
            shape = coll.find("geometry")[0]
            if shape.tag == "sphere":
                points.append((coll.get("name"), link.get("name"), frame.parentJoint,
                               placement.translation.copy(), float(shape.get("radius"))))
                continue
            half = np.array([float(v) for v in shape.get("size").split()]) / 2.0
            for sx in (1, -1):
                for sy in (1, -1):
                    for sz in (1, -1):
                        tag = "".join("p" if s > 0 else "n" for s in (sx, sy, sz))
                        points.append((f"{coll.get('name')}_{tag}", link.get("name"),
                                       frame.parentJoint,
                                       placement.act(half * np.array([sx, sy, sz])), 0.0))
    order = list(STARLETH_FEET) + [f"{leg}_knee" for leg in ("LF", "RF", "LH", "RH")]
    return sorted(points, key=lambda p: order.index(p[0]) if p[0] in order else len(order))


def old_leg_angles(height, model, foot):
    """The arithmetic the standing posture always had (front leg; the hind leg mirrors)."""
    l0 = -model.jointPlacements[model.getJointId("LF_HFE")].translation[2]
    l1 = -model.jointPlacements[model.getJointId("LF_KFE")].translation[2]
    l2, r = -foot[3][2], foot[4]
    d = height - l0 - r
    cos_k = (d * d - l1 * l1 - l2 * l2) / (2 * l1 * l2)
    kfe = -np.arccos(np.clip(cos_k, -1.0, 1.0))
    hfe = np.arctan2(l2 * np.sin(-kfe), l1 + l2 * np.cos(kfe))
    return float(hfe), float(kfe)


def test_starleth_from_its_spec_equals_the_old_description_field_by_field():
    desc = starleth_description()
    with open(urdf_path()) as f:
        xml = f.read()
    model = pin.buildModelFromXML(xml, pin.JointModelFreeFlyer())
    assert (desc.name, desc.urdf_xml, desc.joint_names, desc.foot_names) == \
        ("starleth", xml, STARLETH_JOINT_NAMES, STARLETH_FEET)
    assert desc.standing_height == OLD_STANDING_HEIGHT
    assert desc.total_mass == float(sum(i.mass for i in model.inertias))
    assert list(desc.model.names) == list(model.names)
    old = old_contacts(xml, model)
    assert [(c.name, c.link, c.joint, c.radius) for c in desc.contacts] == \
        [(n, link, j, r) for n, link, j, _, r in old]
    for c, o in zip(desc.contacts, old, strict=True):
        assert c.local.tobytes() == o[3].tobytes(), c.name
    ids = [model.getJointId(n) for n in STARLETH_JOINT_NAMES]
    iv = [model.joints[j].idx_v for j in ids]
    iq = [model.joints[j].idx_q for j in ids]
    for got, want in ((desc.effort_limit, model.effortLimit[iv]),
                      (desc.velocity_limit, model.velocityLimit[iv]),
                      (desc.position_lower, model.lowerPositionLimit[iq]),
                      (desc.position_upper, model.upperPositionLimit[iq])):
        assert got.tobytes() == np.asarray(want, dtype=float).tobytes()
    # the standing posture: the old arithmetic's bits, at the standing height and others
    for h in (OLD_STANDING_HEIGHT, 0.30, 0.35, 0.38, 0.42, 0.45):
        hfe, kfe = old_leg_angles(h, model, old[0])
        want = np.array([0.0, hfe, kfe] * 2 + [0.0, -hfe, -kfe] * 2)
        assert desc.standing_joints(h).tobytes() == want.tobytes(), h
    # the configuration names it both ways
    assert robot_description("starleth.urdf").contact_names() == desc.contact_names()


def test_starleth_posture_hold_for_the_robot_keeps_its_gains():
    desc = starleth_description()
    hold = PostureHold.for_robot(desc, np.zeros(12))
    assert robot_scale(desc.legs, desc.total_mass).length == 1.0 and \
        robot_scale(desc.legs, desc.total_mass).mass == 1.0
    assert hold.kp.tobytes() == np.tile(DEFAULT_KP, 4).tobytes()
    assert hold.kd.tobytes() == np.tile(DEFAULT_KD, 4).tobytes()


# -- every robot ---------------------------------------------------------------------------
def urdf_joint_order(xml):
    return tuple(j.get("name") for j in ET.fromstring(xml).findall("joint")
                 if j.get("type") != "fixed")


@pytest.mark.parametrize("name", ROBOTS)
def test_every_robot_builds_with_legs_and_sides_from_its_geometry(name):
    needs_data(name)
    desc = robot_description(name)
    assert desc.joint_names == urdf_joint_order(desc.urdf_xml)
    assert len(desc.joint_names) == 12 and len(desc.legs) == 4
    assert desc.foot_names == tuple(leg.foot for leg in desc.legs)
    assert desc.contact_names()[:4] == list(desc.foot_names)      # feet first
    assert 12 <= len(desc.contacts) <= 24           # feet, knees, trunk: not every primitive
    data = desc.model.createData()
    pin.forwardKinematics(desc.model, data, pin.neutral(desc.model))
    corners = set()
    for leg in desc.legs:
        assert leg.plane is not None and abs(leg.roll) == 1.0     # roll-pitch-pitch
        foot = next(c for c in desc.contacts if c.name == leg.foot)
        p = data.oMi[foot.joint].act(foot.local)
        assert (p[0] > 0) == leg.fore and (p[1] > 0) == leg.left, leg     # foot's side
        corners.add((leg.fore, leg.left))
        assert all(0 < desc.effort_limit[j] < 1000 and 0 < desc.velocity_limit[j] < 1000
                   for j in leg.joints)
    assert len(corners) == 4


@pytest.mark.parametrize("name", ROBOTS)
def test_the_standing_posture_puts_every_foot_on_the_ground_at_the_specs_height(name):
    needs_data(name)
    spec = load_robot(name)
    sim = Simulator.from_preset("HmJ", robot=name)
    desc = sim.description
    gaps = sim.gaps()
    feet = [sim.contact_names.index(f) for f in desc.foot_names]
    # all four feet touch (not only the lowest), the base at the spec's height
    np.testing.assert_allclose(gaps[feet], -Simulator.REST_OVERLAP, atol=1e-12)
    assert sim.base_state()["position"][2] == pytest.approx(
        spec.standing_height - Simulator.REST_OVERLAP, abs=1e-12)
    others = np.delete(gaps, feet)
    assert others.min() > 0.05                      # knees and trunk well above the ground
    # each foot straight below its hip pitch joint, the joints within their limits
    q = sim.q
    data = desc.model.createData()
    pin.forwardKinematics(desc.model, data, q)
    for leg in desc.legs:
        foot = next(c for c in desc.contacts if c.name == leg.foot)
        hfe = desc.model.getJointId(leg.joint_names[1])
        assert data.oMi[foot.joint].act(foot.local)[0] == pytest.approx(
            data.oMi[hfe].translation[0], abs=1e-9)
    phi = sim.joint_positions()
    assert np.all(phi >= desc.position_lower) and np.all(phi <= desc.position_upper)


def stand(name, preset, seconds):
    """(sim, worst end-of-step foot gap, Σ F_z of the feet / m g per step, max tilt [°])
    under PostureHold.for_robot from the standing posture."""
    sim = Simulator.from_preset(preset, robot=name)
    hold = PostureHold.for_robot(sim.description, sim.joint_positions())
    feet = [sim.contact_names.index(f) for f in sim.description.foot_names]
    mg = sim.description.total_mass * G
    worst, load, tilt = 0.0, [], 0.0
    for _ in range(int(round(seconds / sim.control_period))):
        d = sim.step(hold.torque(sim))
        assert d.converged
        worst = min(worst, float(sim.gaps()[feet].min()))
        load.append(sim.contact_forces()[feet, 2].sum() / mg)
        x, y = sim.base_state()["orientation_xyzw"][:2]
        tilt = max(tilt, float(np.degrees(2 * np.arcsin(np.hypot(x, y)))))
    return sim, worst, np.array(load), tilt


@pytest.mark.parametrize("name", ROBOTS)
def test_every_robot_stands_on_hmj_under_the_scaled_hold(name):
    needs_data(name)
    sim, worst, load, tilt = stand(name, "HmJ", 2.0)
    assert worst >= -1e-6                            # end-of-step penetration <= 1 µm
    assert load[-200:].mean() == pytest.approx(1.0, abs=0.02)   # the feet carry m g
    assert tilt < 2.0
    h = load_robot(name).standing_height
    assert sim.base_state()["position"][2] > 0.97 * h
    assert not any(c.active for c in sim.contacts if c.name not in sim.description.foot_names)


@pytest.mark.parametrize("name", ROBOTS)
def test_every_robot_runs_all_11_presets(name):
    """Each preset builds (the extended and maximal sets from the robot's own tree) and
    holds the robot up for 0.5 s (Cm: with the spec's physics overrides)."""
    needs_data(name)
    h = load_robot(name).standing_height
    for preset in PRESETS:
        sim, worst, load, tilt = stand(name, preset, 0.5)
        assert tilt < 3.0 and sim.base_state()["position"][2] > 0.95 * h, preset
        assert load[-80:].mean() == pytest.approx(1.0, abs=0.1), preset
        if sim.stepper.hard:
            assert worst >= -1e-6, preset


@pytest.mark.parametrize("name", ROBOTS)
def test_the_three_coordinate_sets_agree_on_every_robot(name):
    """0.25 s of standing under the hold plus a small sinusoidal torque on every joint (2 %
    of its effort limit), replayed open loop in minimal, extended and maximal coordinates
    (coordinate_checks.compare_three: within 1e-4 at the native Δt and extrapolated)."""
    needs_data(name)
    base = Simulator.from_preset("HmJ", robot=name, **TIGHT)
    hold = PostureHold.for_robot(base.description, base.joint_positions())
    q0, u0 = base.q, base.u
    wiggle = 0.02 * base.description.effort_limit
    torques = []
    for k in range(100):
        torques.append(hold.torque(base) + wiggle * np.sin(0.1 * k + np.arange(base.n_joints)))
        base.step(torques[-1])
    compare_three(q0, u0, torques, {"HEJD": 1e-4, "HMJD": 1e-4}, robot=name)


# -- the scaling rule ----------------------------------------------------------------------
def scaled_starleth(tmp_path, lam, mu):
    """StarlETH's URDF λ times larger (lengths) and μ times heavier (masses; inertias μλ²,
    efforts μλ, speeds 1/√λ) and its spec, standing λ times higher."""
    with open(urdf_path()) as f:
        xml = f.read()

    def times(k):
        return lambda m: " ".join(repr(float(v) * k) for v in m.group(1).split())
    for attr, k in (("xyz", lam), ("size", lam), ("radius", lam), ("length", lam),
                    ("value", mu), ("effort", mu * lam), ("velocity", lam ** -0.5)):
        xml = re.sub(rf'{attr}="([^"]*)"', lambda m, k=k, a=attr: f'{a}="{times(k)(m)}"', xml)
    for attr in ("ixx", "iyy", "izz", "ixy", "ixz", "iyz"):
        xml = re.sub(rf'{attr}="([^"]*)"', lambda m, a=attr: f'{a}="{times(mu * lam ** 2)(m)}"',
                     xml)
    (tmp_path / "big.urdf").write_text(xml)
    with open(os.path.join(os.path.dirname(urdf_path()), "..", "robots", "starleth.yaml")) as f:
        spec = f.read()
    spec = spec.replace("name: starleth", "name: big").replace(
        "path: ../urdf/starleth.urdf", "path: big.urdf").replace(
        "height: 0.415", f"height: {0.415 * lam!r}")
    (tmp_path / "big.yaml").write_text(spec)
    return str(tmp_path / "big.yaml")


def test_the_hold_scales_by_dynamic_similarity(tmp_path):
    """A StarlETH twice as long and 8 times heavier: λ = 2, μ = 8, K_p x16, K_d x16√2; it
    settles to StarlETH's joint errors (a static equilibrium: the gravity torques scale as
    μλ, as the stiffness does) with its base sagging twice as far."""
    big = robot_description(scaled_starleth(tmp_path, 2.0, 8.0))
    scale = robot_scale(big.legs, big.total_mass)
    assert (scale.length, scale.mass) == (2.0, 8.0)
    hold = PostureHold.for_robot(big, np.zeros(12))
    np.testing.assert_allclose(hold.kp, np.tile(DEFAULT_KP, 4) * 16.0, rtol=1e-12)
    np.testing.assert_allclose(hold.kd, np.tile(DEFAULT_KD, 4) * 16.0 * np.sqrt(2.0),
                               rtol=1e-12)
    errors, sags = [], []
    for robot in ("starleth", str(tmp_path / "big.yaml")):
        sim, _, _, _ = stand(robot, "HmJ", 4.0)
        target = sim.description.standing_joints()
        errors.append(sim.joint_positions() - target)
        sags.append(sim.description.standing_height - sim.base_state()["position"][2])
    np.testing.assert_allclose(errors[1], errors[0], atol=0.02 * np.abs(errors[0]).max())
    assert sags[1] == pytest.approx(2.0 * sags[0], rel=0.02)
