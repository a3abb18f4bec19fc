"""The controller trots over terrain, headless: controller + Simulator in one process, physics
HmJ (hard contacts). The controller knows nothing of the terrain: it takes the ground from
where its feet stood (starleth_controller/csrc/ground_plane.c), a foot's contact from its force
(> contact_force_threshold, as controller_node does), and searches the ground with a foot
that finds none (starleth_controller/step_down.py). One run per course of
starleth_sim/tools/demo/terrain.py (the courses of ``starleth-demo --terrain``): 1 s
standing, then a trot at 0.3 m/s long enough to cross the course (its end x / 0.3 m/s +
TROT_MARGIN); the trunk must cross it (up and down the 10° slope, over the 4 cm step, up
the shipped 3 stairs of 4 cm and 12 cm down off their landing, 12 cm down off a ledge, over
±1.5 cm rough ground) without falling, its clearance (the base's height above the terrain
under it) never below MIN_CLEARANCE, and no hard contact may end a step more than 0.1 mm
inside a surface, a foot in a concave corner (a tread and its riser) included: it has a
contact on each (doc/physics.md, "Terrain")."""
from __future__ import annotations

import math

import numpy as np
import pytest

from starleth_controller import LEGS, Command, RobotState, StarlethController
from starleth_controller import kernels as K
from starleth_sim import Simulator
from starleth_sim.physics.description import urdf_path
from starleth_sim.physics.terrain import pack_terrain, terrain_height
from starleth_sim.tools.demo.terrain import (
    COURSES,
    PAST_EDGE,
    course_end,
    course_overrides,
    course_terrain,
)

FEET = tuple(f"{leg}_foot" for leg in LEGS)
#: the deepest a hard contact may be inside a surface at a step's end [m]
MAX_PENETRATION = 1e-4
#: a foot is in a corner when its sphere comes this close to two surfaces [m]
CORNER = 5e-4
#: the lowest the base may come above the terrain under it while trotting [m]
MIN_CLEARANCE = 0.3
#: the trot lasts the time the course takes at the commanded speed, and this much more [s]
TROT_MARGIN = 2.0


def surface_gaps(c, r, boxes):
    """The gaps of a sphere (centre c, radius r) to the plane z = 0 and to each box
    (axis-aligned: the courses' boxes have no yaw), smallest first."""
    g = [c[2] - r]
    for b in boxes:
        lo = np.subtract(b["centre"], np.multiply(b["size"], 0.5))
        hi = np.add(b["centre"], np.multiply(b["size"], 0.5))
        g.append(float(np.linalg.norm(np.maximum(np.maximum(lo - c, c - hi), 0.0))) - r)
    return sorted(g)


def clearance(sim, packed):
    """The base's height above the terrain under it (the ground plane, a box's top or the
    heightfield, whichever is highest there; `packed`: the terrain packed with the ground's
    height)."""
    x, y, z = sim.base_state()["position"]
    return z - max(terrain_height(packed, x, y), sim.config.ground.height)


def trot_over(terrain, end, stand=1.0, speed=0.3):
    """The record of `stand` s standing, then trotting at `speed` until the trunk should have
    passed x = `end` (+ TROT_MARGIN) on HmJ with the terrain fields `terrain`."""
    trot = end / speed + TROT_MARGIN
    sim = Simulator.from_preset("HmJ", **terrain)
    packed = pack_terrain(sim.config.terrain, sim.config.ground.height)
    ctrl = StarlethController(urdf_path())
    feet = [sim.contact_names.index(f) for f in FEET]
    boxes = sim.config.terrain.all_boxes()
    assert all(b["yaw"] == 0.0 for b in boxes)
    rec = {"x": [], "clearance": [], "tilt": [], "pen": [], "corner_pen": [0.0],
           "fallen": False, "qp_ok": True, "tau_ok": True}
    m = ctrl.model
    R, centre, contact = np.zeros((3, 3)), np.zeros((4, 3)), np.zeros((4, 3))
    Jf, Jc = np.zeros((4, 3, 3)), np.zeros((4, 3, 3))
    for _ in range(int(round((stand + trot) * 400))):
        b = sim.base_state()
        cs = sim.contacts
        st = RobotState(sim.t, sim.joint_positions(), sim.joint_velocities(), b["position"],
                        b["orientation_xyzw"], b["linear_velocity"], b["angular_velocity"],
                        None, np.array([cs[i].force for i in feet]))   # contact: force
        cmd = Command("stand") if sim.t < stand else Command("trot", forward=speed)
        tau = ctrl.update(st, cmd)
        rec["fallen"] |= ctrl.mode == "fallen"
        rec["qp_ok"] &= ctrl.info.get("qp_status") in ("solved", "idle")
        rec["tau_ok"] &= bool(np.all(np.isfinite(tau)) and np.all(np.abs(tau) <= 20.0))
        sim.step(tau)
        x, y, z, w = sim.base_state()["orientation_xyzw"]
        rec["tilt"].append(math.acos(min(1.0, 1.0 - 2.0 * (x * x + y * y))))
        rec["x"].append(sim.base_state()["position"][0])
        rec["clearance"].append(clearance(sim, packed))
        gaps = sim.gaps()
        if boxes:     # the feet in a concave corner (sphere centres from the kinematics),
            # from an independent gap computation (numpy, not csrc/terrain.c)
            b = sim.base_state()
            K.quat_to_rot(*b["orientation_xyzw"], R)
            K.leg_kinematics(sim.joint_positions(), R, b["position"], m.hip, m.geometry,
                             centre, contact, Jf, Jc)
            for j in range(len(feet)):
                near = surface_gaps(centre[j], m.foot_radius[j], boxes)
                if near[1] < CORNER:
                    rec["corner_pen"].append(-min(0.0, near[0]))
        rec["pen"].append(-min(0.0, float(gaps.min())))
    return rec


def check_crossed(name, rec, end):
    """The run `rec` crossed up to x = `end` without falling, tilting beyond 0.2 rad, the
    trunk coming lower than MIN_CLEARANCE above the terrain or a contact deeper than
    MAX_PENETRATION inside a surface (a foot in a corner included)."""
    x, tilt, pen, cpen = rec["x"][-1], max(rec["tilt"]), max(rec["pen"]), max(rec["corner_pen"])
    low = int(np.argmin(rec["clearance"]))
    print(f"\n[{name}] x {x:.2f} m, tilt max {tilt:.3f} rad, trunk clearance min "
          f"{rec['clearance'][low]:.3f} m (at x {rec['x'][low]:.2f} m), penetration max "
          f"{pen * 1e3:.3f} mm (a foot in a corner: {len(rec['corner_pen']) - 1} steps, "
          f"{cpen * 1e3:.3f} mm)")
    assert not rec["fallen"], f"{name}: the controller fell"
    assert rec["qp_ok"] and rec["tau_ok"], f"{name}: QP failure or torque out of range"
    assert tilt < 0.2, f"{name}: tilt reached {tilt:.3f} rad"
    assert rec["clearance"][low] > MIN_CLEARANCE, \
        f"{name}: trunk down to {rec['clearance'][low]:.3f} m above the terrain"
    assert x > end, f"{name}: trunk at x = {x:.2f} m, not across"
    assert pen <= MAX_PENETRATION, f"{name}: a contact {pen * 1e3:.3f} mm inside a surface"
    assert cpen <= MAX_PENETRATION, f"{name}: a foot {cpen * 1e3:.3f} mm inside a " \
        "surface in a concave corner"


@pytest.mark.parametrize("course", list(COURSES))
def test_controller_trots_over_terrain(course):
    rec = trot_over(course_terrain(course), course_end(course))
    check_crossed(course, rec, course_end(course))
    if course in ("step", "stairs"):    # the feet do meet the corners there
        assert len(rec["corner_pen"]) > 10, f"{course}: no foot in a corner"


@pytest.mark.parametrize("edge", [0.5, 0.53, 0.56, 0.59])
def test_steps_down_a_ledge_met_at_any_phase_of_the_trot(edge):
    """The ledge course (12 cm down) with its edge 0.5 to 0.59 m ahead: the feet meet it at
    phases of the trot a quarter of a half cycle apart (the trunk covers about 0.12 m per
    half cycle at 0.3 m/s), front and hind feet alike."""
    terrain = course_terrain("ledge")
    box = terrain["boxes"][0]
    box["centre"][0] += edge - (box["centre"][0] + 0.5 * box["size"][0])
    end = edge + PAST_EDGE
    check_crossed(f"ledge at {edge} m", trot_over(terrain, end), end)


def test_ground_plane_is_the_plane_through_the_footholds():
    """The least-squares plane through four footholds on an inclined plane is that plane;
    collinear footholds give a flat plane at their mean height; slopes are clipped."""
    gx, gy, a = math.tan(math.radians(10.0)), -0.05, 0.3
    xy = np.array([[0.3, 0.2], [0.3, -0.2], [-0.3, 0.2], [-0.3, -0.2]]) + [1.0, 0.5]
    contact = np.column_stack((xy, a + gx * xy[:, 0] + gy * xy[:, 1]))
    stood, plane = np.zeros((4, 3)), np.zeros(3)
    K.update_plane(contact, np.arange(4), 4, stood, plane)
    np.testing.assert_allclose(plane, [a, gx, gy], atol=1e-12)
    np.testing.assert_array_equal(stood, contact)
    # two legs in support: only their footholds move
    moved = contact + [0.1, 0.0, 0.02]
    K.update_plane(moved, np.array([0, 3]), 2, stood, plane)
    np.testing.assert_array_equal(stood[[1, 2]], contact[[1, 2]])
    np.testing.assert_array_equal(stood[[0, 3]], moved[[0, 3]])
    # collinear: flat at the mean height
    line = np.array([[0.0, 0, 0.1], [0.2, 0, 0.2], [0.4, 0, 0.3], [0.6, 0, 0.4]])
    K.update_plane(line, np.arange(4), 4, stood, plane)
    np.testing.assert_allclose(plane, [0.25, 0.0, 0.0], atol=1e-12)
    # steeper than MAX_SLOPE: clipped
    steep = contact.copy()
    steep[:, 2] = 2.0 * xy[:, 0]
    K.update_plane(steep, np.arange(4), 4, stood, plane)
    assert plane[1] == pytest.approx(0.5) and plane[2] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("course", list(COURSES))
def test_demo_passes_each_course_to_sim_node_as_its_physics_overrides(course):
    """``starleth-demo --terrain`` gives sim_node ``-p physics_overrides:="<value>"``: one
    line without double quotes, which sim_node's settings read back as the course's terrain
    and the simulator builds (the robot resting on it)."""
    from starleth_sim.ros.parameters import Settings  # deferred: the ROS side's schema

    value = course_overrides(course)
    assert '"' not in value and "\n" not in value
    assert Settings(physics_overrides=value).physics_override_dict() == course_terrain(course)
    sim = Simulator.from_preset("HmJ", **Settings(physics_overrides=value)
                                .physics_override_dict())
    assert not sim.config.terrain.is_flat
    with pytest.raises(ValueError, match="unknown terrain course"):
        course_terrain("lava")
