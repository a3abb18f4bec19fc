"""Bad robot descriptions and specs: each is refused with one line naming the file and the
element or field (a ConfigError, from Simulator.from_preset as a user meets it), never a
traceback; and what a `robot` may name (a library name, a spec path, a URDF path; the
presets' starleth.urdf), the spec's physics overrides, a robot without four 3-joint legs."""
import numpy as np
import pytest
from robot_cases import ankle_urdf

from starleth_sim import ConfigError, Simulator
from starleth_sim.physics.description import urdf_path
from starleth_sim.physics.impedance import ImpedanceCommand
from starleth_sim.robots import INSTALL_HINT, robot_description

with open(urdf_path()) as _f:
    STARLETH_URDF = _f.read()
SPEC = """name: bad
urdf: {{path: {urdf}}}
feet: {{links: [LF_FOOT, RF_FOOT, LH_FOOT, RH_FOOT]{feet}}}
contacts:
  - {{links: ["*_SHANK"], urdf: [sphere]}}
  - {{links: [base], urdf: [box]}}
standing: {{height: 0.415, knees: auto}}
{extra}"""


def write(tmp_path, urdf=STARLETH_URDF, feet="", extra="", spec=None):
    """A StarlETH-like spec (bad.yaml) over `urdf` (bad.urdf); its path."""
    (tmp_path / "bad.urdf").write_text(urdf)
    text = spec if spec is not None else SPEC.format(urdf="bad.urdf", feet=feet, extra=extra)
    (tmp_path / "bad.yaml").write_text(text)
    return str(tmp_path / "bad.yaml")


def refused(robot, *parts, preset="HmJ"):
    """The one-line ConfigError of building `robot`; it names every one of `parts`."""
    with pytest.raises(ConfigError) as e:
        Simulator.from_preset(preset, robot=robot)
    message = str(e.value)
    assert "\n" not in message, message
    for p in parts:
        assert p in message, (p, message)
    return message


def test_a_good_spec_copy_builds_what_the_library_does(tmp_path):
    """The baseline of the cases below: the copy builds StarlETH itself."""
    sim = Simulator.from_preset("HmJ", robot=write(tmp_path))
    ref = Simulator.from_preset("HmJ")
    assert sim.contact_names == ref.contact_names
    np.testing.assert_array_equal(sim.q, ref.q)


SHANK_INERTIAL = STARLETH_URDF[STARLETH_URDF.index("<link name=\"LF_SHANK\">"):]
SHANK_INERTIAL = SHANK_INERTIAL[SHANK_INERTIAL.index("<inertial>"):
                                SHANK_INERTIAL.index("</inertial>") + len("</inertial>")]


@pytest.mark.parametrize("edit,parts", [
    (lambda x: x.replace(SHANK_INERTIAL, "", 1),
     ("bad.urdf (bad.yaml)", "link 'LF_SHANK'", "joint 'LF_KFE'", "no mass")),
    (lambda x: x.replace('<mass value="0.32"/>', '<mass value="0"/>', 1),
     ("bad.urdf", "link 'LF_SHANK'", "no mass")),
    (lambda x: x.replace('<mass value="0.31"/>', '<mass value="-0.31"/>', 1),
     ("bad.urdf", "link 'LF_THIGH' <mass>", "must not be negative")),
    (lambda x: x.replace('<joint name="LF_KFE" type="revolute">',
                         '<joint name="LF_KFE" type="prismatic">'),
     ("bad.urdf", "joint 'LF_KFE'", "'prismatic' is not supported")),
    (lambda x: x.replace('<joint name="RH_HAA" type="revolute">',
                         '<joint name="RH_HAA" type="continuous">'),
     ("bad.urdf", "joint 'RH_HAA'", "'continuous' is not supported")),
    (lambda x: x.replace("</robot>", '<joint name="strut" type="fixed"><parent link="base"/>'
                                     '<child link="LF_SHANK"/></joint></robot>'),
     ("bad.urdf", "joint 'strut'", "closed loop", "link 'LF_SHANK'")),
    (lambda x: x.replace("</robot>", '<link name="stray"/></robot>'),
     ("bad.urdf", "'stray'", "one tree")),
    (lambda x: x.replace('<axis xyz="0 1 0"/>', '<axis xyz="0 0 0"/>', 1),
     ("bad.urdf", "joint 'LF_HFE'", "a zero axis")),
    (lambda x: x.replace('<origin xyz="0 0 -0.2" rpy="0 0 0"/>',
                         '<origin xyz="0 zero -0.2" rpy="0 0 0"/>', 1),
     ("bad.urdf", "joint 'LF_KFE' <origin xyz>", "expected 3 numbers")),
    (lambda x: x.replace('effort="20"', 'effort="1000"', 1),
     ("bad.urdf", "joint 'LF_HAA'", "placeholder", "limits.effort in bad.yaml")),
    (lambda x: x[:200], ("bad.urdf", "not valid XML")),
    (lambda x: x.replace('<sphere radius="0.03"/>', '<sphere radius="0.13"/>', 1),
     ("bad.urdf (bad.yaml)", "contact 'LF_knee'", "must be < 0.1 m")),
    (lambda x: x.replace('<sphere radius="0.03"/>', '<sphere radius="-0.03"/>', 1),
     ("bad.urdf", "collision 'LF_knee'", "must be > 0")),
])
def test_a_bad_urdf_is_one_line_naming_the_file_and_element(tmp_path, edit, parts):
    refused(write(tmp_path, urdf=edit(STARLETH_URDF)), *parts)


MESH = '<collision name="shell"><geometry><mesh filename="shell.stl"/></geometry></collision>'


@pytest.mark.parametrize("feet,extra,parts", [
    (", radius: 0.2", "", ("bad.yaml", "feet.radius", "must be < 0.1")),
    ("", "limits: {effort: {'*_KFE': 5000}}", ("bad.yaml", "limits.effort.*_KFE", "< 1000")),
    ("", "limits: {effort: {'*_ANKLE': 5}}", ("bad.yaml", "limits.effort", "'*_ANKLE'",
                                              "matches no moving joint")),
    ("", "colour: red", ("bad.yaml", "unknown field 'colour'")),
    ("", "physics: {contact: {stiffnes_normal: 1.0}}",
     ("bad.yaml", "physics.contact", "unknown field 'stiffnes_normal'")),
    ("", "physics: {contact: {stiffness_normal: -1.0}}",
     ("bad.yaml", "physics.contact.stiffness_normal", "must be > 0")),
])
def test_a_spec_field_out_of_range_is_one_line_naming_the_field(tmp_path, feet, extra, parts):
    refused(write(tmp_path, feet=feet, extra=extra), *parts)


@pytest.mark.parametrize("spec,parts", [
    (SPEC.format(urdf="bad.urdf", feet="", extra="").replace("0.415", "2.0"),
     ("bad.yaml", "standing", "2.0 m is out of reach")),
    (SPEC.format(urdf="bad.urdf", feet="", extra="").replace("*_SHANK", "*_SHIN"),
     ("bad.yaml", "contacts[0].links", "'*_SHIN' matches no link")),
    (SPEC.format(urdf="bad.urdf", feet="", extra="").replace("urdf: [box]", "urdf: [mesh]"),
     ("bad.yaml", "contacts[1].urdf[0]", "a mesh cannot be contact geometry")),
    (SPEC.format(urdf="bad.urdf", feet="", extra="").replace("urdf: [box]", "urdf: [sphere]"),
     ("bad.yaml", "contacts[1].urdf", "link 'base' has no <sphere> collision")),
    (SPEC.format(urdf="bad.urdf", feet="", extra="").replace("LF_FOOT, ", "LF_SHANK, "),
     ("bad.yaml", "contacts", "two contact points named 'LF_knee'")),
    (SPEC.format(urdf="elsewhere.urdf", feet="", extra=""),
     ("bad.yaml", "urdf.path", "no such file")),
    (SPEC.format(urdf="bad.urdf", feet="", extra="").replace(
        "urdf: {path: bad.urdf}", "urdf: {distribution: no-such-robot-data, path: r.urdf}"),
     ("bad.yaml", "no-such-robot-data", "is not installed", INSTALL_HINT)),
    ("name: bad\nname: worse\n", ("bad.yaml", "duplicate key 'name'")),
    ("name: bad\n", ("bad.yaml", "missing field 'urdf'")),
])
def test_a_bad_spec_is_one_line_naming_the_file_and_field(tmp_path, spec, parts):
    refused(write(tmp_path, spec=spec), *parts)


def test_both_knee_directions_fitting_the_limits_need_the_spec_to_choose(tmp_path):
    free = STARLETH_URDF.replace('lower="-2.41" upper="-0.15"', 'lower="-3" upper="3"')
    free = free.replace('lower="0.15" upper="2.41"', 'lower="-3" upper="3"')
    free = free.replace('lower="-0.55" upper="1.24"', 'lower="-3" upper="3"')
    free = free.replace('lower="-1.24" upper="0.55"', 'lower="-3" upper="3"')
    refused(write(tmp_path, urdf=free), "bad.yaml", "standing", "both knee direction",
            "standing.knees")
    chosen = SPEC.format(urdf="bad.urdf", feet="", extra="").replace(
        "knees: auto", "knees: {front: backward, hind: forward}")
    sim = Simulator.from_preset("HmJ", robot=write(tmp_path, urdf=free, spec=chosen))
    np.testing.assert_array_equal(sim.joint_positions(),
                                  Simulator.from_preset("HmJ").joint_positions())


def test_a_mesh_collision_without_a_spec_is_refused_naming_it(tmp_path):
    path = tmp_path / "meshy.urdf"
    path.write_text(STARLETH_URDF.replace('<collision name="trunk">', MESH + '<collision '
                                          'name="trunk">'))
    refused(str(path), "meshy.urdf", "link 'base' collision 'shell'",
            "a <mesh> cannot be contact geometry")


def test_unknown_robot_names_the_library():
    message = refused("robodog", "robot: unknown robot 'robodog'", "starleth", "go1")
    assert "a robot spec" in message
    refused("/no/such/robot.yaml", "robot: no such robot spec file")


# -- what `robot` names --------------------------------------------------------------------
def test_a_urdf_without_a_spec_takes_every_primitive_and_finds_its_legs():
    """robot = a URDF path: every sphere and box a contact (document order), the legs and
    feet found on the tree, no standing height: the neutral posture resting on the ground."""
    desc = robot_description(urdf_path())
    assert len(desc.contacts) == 16 and desc.contact_names()[0].startswith("trunk_")
    assert desc.foot_names == ("LF_foot", "RF_foot", "LH_foot", "RH_foot")
    assert [leg.fore for leg in desc.legs] == [True, True, False, False]
    assert [leg.left for leg in desc.legs] == [True, False, True, False]
    sim = Simulator.from_preset("HmJ", robot=urdf_path())
    np.testing.assert_array_equal(sim.joint_positions(), np.zeros(12))
    assert min(sim.gaps()) == pytest.approx(-Simulator.REST_OVERLAP, abs=1e-12)


def test_the_spec_physics_overrides_apply_under_the_callers(tmp_path):
    spec = write(tmp_path, extra="physics: {contact: {stiffness_normal: 12345.0}}")
    assert Simulator.from_preset("Cm", robot=spec).config.contact.stiffness_normal == 12345.0
    assert Simulator.from_preset("Cm", robot=spec, stiffness_normal=999.0) \
        .config.contact.stiffness_normal == 999.0
    assert Simulator.from_preset("Cm").config.contact.stiffness_normal == 30000.0


def test_a_robot_without_four_3_joint_legs_still_simulates(tmp_path):
    """StarlETH with an ankle joint on one leg (13 joints; that leg is no 3-joint chain, so
    the legs' sides are unknown): it rests in its neutral posture and steps under torques
    and impedance commands, its joints in the URDF's document order."""
    path = ankle_urdf(tmp_path)
    for preset in ("HmJ", "HEJD", "HMSP"):
        sim = Simulator.from_preset(preset, robot=str(path))
        assert sim.joint_names[:4] == ("LF_HAA", "LF_HFE", "LF_KFE", "LF_ANKLE")
        assert len(sim.description.legs) == 3 and sim.description.legs[0].fore is None
        np.testing.assert_array_equal(sim.joint_positions(), np.zeros(13))
        hold, kp = np.zeros(13), 20.0
        kd = np.where(np.array(sim.joint_names) == "LF_ANKLE", 0.05, 0.5)   # the ZOH bound
        for _ in range(40):
            sim.step(-kp * (sim.joint_positions() - hold) - kd * sim.joint_velocities())
        for _ in range(40):
            sim.step(ImpedanceCommand.create(sim.joint_names, position=hold, kp=kp, kd=kd))
        assert sim.diagnostics.converged and np.all(np.isfinite(sim.q))
        assert np.abs(sim.bilateral_violation()).max(initial=0.0) < 1e-6
        assert np.abs(sim.joint_positions()).max() < 0.5
