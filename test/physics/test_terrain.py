"""Terrain (issue #37): the config section, the generators' surfaces, the contact query
against boxes and heightfields, and bodies and the robot on them (analytic cross-checks
against the plane, which the terrain must reproduce)."""
import math
import subprocess
import sys

import numpy as np
import pytest
import yaml

from starleth_sim import Simulator, load_preset
from starleth_sim.physics.config import ConfigError, PhysicsConfig
from starleth_sim.physics.description import RobotDescription, box_urdf, sphere_urdf
from starleth_sim.physics.posture import PostureHold
from starleth_sim.physics.terrain import (
    SECOND_SURFACE_NONE,
    TERRAIN_HEADER,
    TerrainConfig,
    pack_terrain,
    terrain_height,
)
from starleth_sim.tools.bench.terrain import terrain_rounds, terrains
from starleth_sim.tools.view.recording import terrain_from_metadata
from starleth_sim.tools.view.scene import terrain_objects

R = 0.1    # the test sphere's radius [m]
#: the corner tests' sphere: a box's gap is exact within terrain.BOX_REACH (0.1 m) − r of it
RC = 0.05


def body_sim(urdf, preset="HmJ", **overrides):
    cfg = load_preset(preset).with_overrides(control_rate=1000.0, steps_per_control=1,
                                             **overrides)
    return Simulator(cfg, description=RobotDescription.from_urdf_xml(urdf))


def packed(**terrain):
    t = TerrainConfig(**terrain)
    t.validate("terrain")
    return pack_terrain(t)


# -- the generators produce the surfaces they claim ---------------------------------------

def test_stairs_heights_at_chosen_points():
    p = packed(stairs={"rise": 0.04, "run": 0.3, "count": 3, "start": 0.5})
    assert terrain_height(p, 0.4, 0.0) == -math.inf          # before the stairs: the plane
    for k in (1, 2, 3):
        assert terrain_height(p, 0.5 + (k - 0.5) * 0.3, 0.3) == pytest.approx(0.04 * k)
    assert terrain_height(p, 0.5 + 3 * 0.3 + 0.9, 0.0) == pytest.approx(0.12)   # landing
    assert terrain_height(p, 0.5 + 3 * 0.3 + 1.1, 0.0) == -math.inf
    assert terrain_height(p, 0.6, 1.1) == -math.inf           # beside (width 2 m)


def test_slope_heights_at_chosen_points():
    angle, length, start, top = 10.0, 2.0, 0.5, 1.0
    p = packed(slope={"angle": angle, "length": length, "start": start, "top": top})
    t = math.tan(math.radians(angle))
    for x in (0.5, 0.8, 1.37, 2.5):
        assert terrain_height(p, x, 0.2) == pytest.approx((x - start) * t, abs=1e-12)
    assert terrain_height(p, start + length + 0.5 * top, 0.0) == pytest.approx(length * t)
    down = start + 2 * length + top
    assert terrain_height(p, down - 0.3, -0.5) == pytest.approx(0.3 * t, abs=1e-12)


def test_rough_heights_stay_within_the_amplitude_and_follow_the_seed():
    cfg = {"amplitude": 0.015, "wavelength": 0.3, "seed": 7, "size": 3.0}
    p = packed(rough=cfg)
    nx, ny = int(p[1]), int(p[2])
    h = p[TERRAIN_HEADER:].reshape(nx, ny)
    assert np.abs(h).max() <= 0.015 + 1e-15
    assert np.abs(h).max() > 0.9 * 0.015                     # scaled to the amplitude
    assert np.all(h[0] == 0) and np.all(h[:, -1] == 0)        # faded out at the border
    assert np.array_equal(packed(rough=cfg), p)              # the seed decides
    assert not np.array_equal(packed(rough=dict(cfg, seed=8)), p)
    # the heights between grid points are the bilinear surface's
    x0, y0, cell = p[3:6]
    assert terrain_height(p, x0 + 10.5 * cell, y0 + 20 * cell) == \
        pytest.approx(0.5 * (h[10, 20] + h[11, 20]), abs=1e-15)


def test_the_c_query_reads_the_packed_terrain_where_python_packs_it():
    """Simulator.gaps of a sphere over each step of a stair and over a heightfield: the
    distance to the surface the generator claims (the packed layout read by csrc/terrain.c
    is the one terrain.py writes); more than BOX_REACH above the terrain's top, the plane's
    (terrain.TOP: gaps are exact within BOX_REACH − r of the terrain)."""
    sim = body_sim(sphere_urdf(R, 1.0), stairs={"rise": 0.04, "run": 0.3, "count": 3,
                                                "start": 0.5, "mu": 0.5})
    for k, x in ((0, 0.2), (1, 0.65), (2, 0.95), (3, 1.25)):
        q = sim.q
        q[:3] = [x, 0.1, 0.04 * k + R + 0.05]     # (nearer the step below than the next)
        sim.reset(q)
        assert sim.gaps()[0] == pytest.approx(0.05, abs=1e-15)
    grid = np.add.outer(np.arange(5) * 0.01, np.zeros(4))     # h = 0.1 x (cells of 0.1)
    sim = body_sim(sphere_urdf(R, 1.0), heightfield={"origin": [0.0, 0.0], "cell": 0.1,
                                                     "heights": grid.tolist()})
    q = sim.q
    q[:3] = [0.25, 0.1, 0.2]
    sim.reset(q)
    n = np.array([-0.1, 0.0, 1.0]) / math.hypot(0.1, 1.0)
    assert sim.gaps()[0] == pytest.approx((0.2 - 0.025) * n[2] - R, abs=1e-15)
    # more than BOX_REACH (0.1 m) above the terrain's top (0.04 m): the plane alone
    q[2] = R + 0.04 + 0.1 + 1e-6
    sim.reset(q)
    assert sim.gaps()[0] == q[2] - R
    q[2] -= 2e-6
    sim.reset(q)
    assert sim.gaps()[0] < q[2] - R - 0.02          # the heightfield (h = 0.025 m here)


# -- bodies on the terrain: cross-checks against the plane --------------------------------

def test_sphere_on_a_slope_terrain_is_the_sphere_on_the_inclined_plane():
    """Resting on it, then rolling (μ = 0.8: a = 5/7 g sin θ) or sliding (μ = 0.05 <
    2/7 tan θ: a = g (sin θ − μ cos θ)) down: the slope generator's heightfield and today's
    inclined plane through the same points give the same motion to 1e-12."""
    theta = math.radians(10.0)
    n = np.array([-math.sin(theta), 0.0, math.cos(theta)])
    results = []
    for mu in (0.8, 0.05):
        runs = []
        for terrain in (False, True):
            kw = {"slope": {"angle": 10.0, "length": 3.0, "start": 0.0}} if terrain \
                else {"normal": tuple(n)}
            sim = body_sim(sphere_urdf(R, 1.0), mu=mu, tol_rel=1e-12, tol_abs=1e-14, **kw)
            q = sim.q
            surface = np.array([1.5, 0.0, 1.5 * math.tan(theta)])
            q[:3] = surface + (R - 1e-9) * n
            sim.reset(q)
            traj = []
            for _ in range(300):
                sim.step()
                traj.append(np.concatenate([sim.q, sim.u]))
            runs.append(np.array(traj))
            assert sim.gaps()[0] == pytest.approx(-1e-9, abs=1e-6)
        np.testing.assert_allclose(runs[1], runs[0], rtol=0, atol=1e-12)
        results.append(runs[0])
    g, t = 9.81, 0.3
    for traj, a in zip(results, (5 / 7 * g * math.sin(theta),
                                 g * (math.sin(theta) - 0.05 * math.cos(theta))), strict=True):
        travelled = np.linalg.norm(traj[-1, :3] - traj[0, :3])
        assert travelled == pytest.approx(0.5 * a * t ** 2, rel=0.02)


def test_ball_dropped_on_a_flat_heightfield_bounces_exactly_as_on_the_plane():
    H = 0.3
    grid = np.full((41, 41), H)
    runs = []
    for kw in ({"height": H}, {"heightfield": {"origin": [-2.0, -2.0], "cell": 0.1,
                                               "heights": grid.tolist()}}):
        sim = body_sim(sphere_urdf(R, 1.0), restitution_normal=0.5, tol_rel=1e-10,
                       tol_abs=1e-12, **kw)
        q = sim.q
        q[:3] = [0.123, -0.456, H + R + 0.5]
        sim.reset(q)
        traj = []
        for _ in range(900):
            sim.step()
            traj.append(np.concatenate([sim.q, sim.u, sim.contact_impulses().ravel()]))
        runs.append(np.array(traj))
    assert np.array_equal(runs[0], runs[1])
    assert runs[0][:, 9].max() > 1.0          # it did bounce (v_z up after the impact)


def test_box_resting_across_two_step_edges_stays_at_rest():
    """A box bridging the gap between two steps, its corners 1 mm inside the edges: at rest
    for 2 s, its loaded corners' gaps within 1 µm."""
    steps = [{"centre": [-0.3, 0.0, 0.05], "size": [0.4, 1.0, 0.1]},
             {"centre": [0.3, 0.0, 0.05], "size": [0.4, 1.0, 0.1]}]
    sim = body_sim(box_urdf((0.2 + 0.002, 0.3, 0.05), 2.0), boxes=steps)
    q = sim.q
    q[:3] = [0.0, 0.0, 0.1 + 0.025 - 1e-9]
    sim.reset(q)
    p0 = sim.q[:3]
    for _ in range(2000):
        d = sim.step()
        assert d.converged
    assert np.linalg.norm(sim.q[:3] - p0) < 1e-6
    gaps = sim.gaps()
    loaded = np.array([c.force[2] > 0 for c in sim.contacts])
    assert loaded.sum() == 4 and np.all(np.abs(gaps[loaded]) <= 1e-6)


def test_foot_resting_at_a_step_edge_does_not_chatter():
    """The rule: a sphere takes the surface with the smallest gap, and a box's normal turns
    continuously round its edge. A sphere resting 1 mm inside a step's edge keeps one
    surface and one normal at every step; rolled over the edge its normal turns smoothly
    (no jump between the step's top and its riser)."""
    step = [{"centre": [-0.5, 0.0, 0.02], "size": [1.0, 1.0, 0.04], "mu": 0.9}]
    sim = body_sim(sphere_urdf(R, 1.0), boxes=step)
    q = sim.q
    q[:3] = [-0.001, 0.0, 0.04 + R - 1e-9]
    sim.reset(q)
    for _ in range(2000):
        sim.step()
        frame = sim.stepper.frames[0]
        assert np.array_equal(frame[:3], [0.0, 0.0, 1.0]) and frame[9] == 0.9
        assert sim.contacts[0].active
    assert abs(sim.gaps()[0]) <= 1e-6 and np.linalg.norm(sim.u) < 1e-9
    # over the edge: pushed to +x, it rolls off; the normal turns with no jump
    q = sim.q
    q[:3] = [-0.001, 0.0, 0.04 + R - 1e-9]
    sim.reset(q, u=np.array([0.3, 0, 0, 0, 0, 0]))
    normals = []
    for _ in range(300):
        sim.step()
        if not sim.contacts[0].active:      # (it leaves the edge, and then the floor is
            break                           # its nearest surface)
        normals.append(sim.stepper.frames[0, :3].copy())
    normals = np.array(normals)
    assert normals[:, 0].max() > 0.3                          # it went round the edge
    assert np.abs(np.diff(normals, axis=0)).max() < 0.05      # continuously


@pytest.mark.parametrize("preset,terrain", [("HmJ", "stairs"), ("Cm", "rough"),
                                            ("HESD", "step"), ("HMJP", "slope")])
def test_every_step_path_gives_the_same_terrain_run_bit_for_bit(preset, terrain):
    """On a terrain, the one-kernel step, the profiled phase-by-phase step and the prepared
    step (Simulator.prepare, then a push) carry each contact's surface frame and μ alike:
    the same run, bit for bit (a dropped robot: impacts on the terrain, then standing)."""
    runs = []
    for mode in ("kernel", "profile", "prepare"):
        sim = Simulator.from_preset(preset, profile=mode == "profile", **TERRAINS[terrain])
        q = sim.q
        q[2] += 0.03
        sim.reset(q)
        hold = PostureHold(sim.joint_positions())
        impulses = []
        for k in range(150):
            if mode == "prepare":
                sim.prepare()
            if k == 60:
                sim.apply_wrench("base", [30.0, -10.0, 0.0], [0.0, 2.0, 1.0])
            sim.step(hold.torque(sim))
            impulses.append(sim.contact_impulses())
        runs.append((sim.q, sim.u, np.array(impulses), sim.stepper.frames.copy()))
    for other in runs[1:]:
        for a, b in zip(runs[0], other, strict=True):
            np.testing.assert_array_equal(a, b)
    assert np.abs(runs[0][2]).sum() > 0       # on the terrain


def test_png_heightfield_is_read_with_its_scale(tmp_path):
    """A grey PNG (8 bits): rows are x, columns y; white is `scale` metres, black 0."""
    from PIL import Image  # deferred: Pillow is optional (it comes with matplotlib)
    grey = np.array([[0, 255, 51], [102, 0, 255]], dtype=np.uint8)
    Image.fromarray(grey, mode="L").save(tmp_path / "h.png")
    t = TerrainConfig(heightfield={"origin": [0, 0], "cell": 0.5,
                                   "heights": str(tmp_path / "h.png"), "scale": 0.1})
    t.validate("terrain")
    np.testing.assert_allclose(t.heightfield["heights"], grey / 255 * 0.1, rtol=1e-15)
    t = TerrainConfig(heightfield={"origin": [0, 0], "cell": 0.5,
                                   "heights": str(tmp_path / "h.png")})
    with pytest.raises(ConfigError, match="a PNG needs heightfield.scale"):
        t.validate("terrain")


@pytest.mark.parametrize("preset", ["HmJ", "HMJD", "Cm"])
def test_sphere_pressed_into_a_concave_corner_is_held_by_both_surfaces(preset):
    """Where two surfaces meet in a concave corner (the floor and a step's riser) a contact
    sphere has a contact on each (csrc/terrain.c, the second surface): a sphere of 1 kg
    pushed into the riser by 20 N for 2 s stays in the corner (hard: within 1 µm of both
    surfaces; compliant: neither spring deflected more than the whole load would, |F| / c_N),
    and at rest the two surfaces together carry the load, (−20 N, 0, m g). (How they share
    it is statically indeterminate with friction: the floor's friction may take part of the
    20 N.)"""
    sim = body_sim(sphere_urdf(RC, 1.0), preset,
                   boxes=[{"centre": [0.5, 0.0, 0.15], "size": [1.0, 1.0, 0.3]}])
    assert sim.coords.n_contacts == 2 * len(sim.contact_names)       # two slots per sphere
    q = sim.q
    q[:3] = [-RC + 1e-9, 0.0, RC - 1e-9]
    sim.reset(q)
    sim.set_persistent_wrench(sim.coords.link_names()[-1], [20.0, 0.0, 0.0])
    riser, floor = [], []
    for _ in range(2000):
        sim.step()
        riser.append(-(sim.q[0] + RC))       # the distance to the riser's plane x = 0
        floor.append(sim.q[2] - RC)
    g = 9.81
    if sim.config.contact_model == "hard":
        assert min(riser) >= -1e-6 and min(floor) >= -1e-6
        assert max(floor) <= 1e-6 and max(riser) <= 1e-6
    else:                                   # Alg. 1's springs: deflection = force / c_N
        most = math.hypot(20.0, g) / sim.config.contact.stiffness_normal
        assert -most * 1.02 <= riser[-1] < 0.0 and -most * 1.02 <= floor[-1] < 0.0
    force = sim.contact_forces()[0]         # both surfaces' forces, summed (world)
    # (to the prox's accuracy: it stops on a relative change of 1e-6 per iteration, which
    # JOR's slow contraction in a corner leaves at a few 1e-5 of the load)
    np.testing.assert_allclose(force, [-20.0, 0.0, g], rtol=1e-4, atol=1e-9)
    c = sim.contacts[0]
    assert c.active and c.state == "stick"


def test_a_sphere_has_a_second_surface_only_in_a_concave_corner():
    """The second contact slot of a sphere: in the corner of the floor and a riser, the
    riser (normal −x) beside the floor; on the floor far from the step, on the step's top,
    and over its convex edge, none (SECOND_SURFACE_NONE); on a flat heightfield lying on
    the plane (the same surface twice), none."""
    sim = body_sim(sphere_urdf(RC, 1.0),
                   boxes=[{"centre": [0.5, 0.0, 0.15], "size": [1.0, 1.0, 0.3]}])
    c = sim.coords

    def slots(x, z):
        q = sim.q
        q[:3] = [x, 0.0, z]
        gap, frames = np.zeros(2), np.zeros((2, 11))
        c.contact_kinematics(q, sim.stepper.ground, gap, np.zeros((2, 3)),
                             np.zeros((2, 3, c.nv)), np.inf, frames)
        return gap, frames[:, :3]

    gap, n = slots(-RC + 0.002, RC + 0.001)       # the corner, 2 mm into the riser
    np.testing.assert_allclose(gap, [-0.002, 0.001], atol=1e-12)
    np.testing.assert_allclose(n, [[-1, 0, 0], [0, 0, 1]], atol=1e-15)
    gap, n = slots(-RC, RC - 0.001)               # touching the riser, 1 mm into the floor
    np.testing.assert_allclose(gap, [-0.001, 0.0], atol=1e-12)
    np.testing.assert_allclose(n, [[0, 0, 1], [-1, 0, 0]], atol=1e-15)
    for x, z in ((-0.5, RC), (0.5, 0.3 + RC), (1.0 + 0.03, 0.3 + RC)):   # floor, top, edge
        gap, n = slots(x, z)
        assert gap[1] == SECOND_SURFACE_NONE, (x, z, gap)
    flat = body_sim(sphere_urdf(RC, 1.0), heightfield={"origin": [-1, -1], "cell": 0.5,
                                                      "heights": [[0.0] * 5] * 5})
    q = flat.q
    gap = np.zeros(2)
    flat.coords.contact_kinematics(q, flat.stepper.ground, gap, np.zeros((2, 3)),
                                   np.zeros((2, 3, flat.coords.nv)))
    assert gap[1] == SECOND_SURFACE_NONE and abs(gap[0]) < 1e-8


# -- the configuration -------------------------------------------------------------------

def test_terrain_config_round_trips_through_the_recorded_dict_bit_for_bit(tmp_path):
    """What recording stores (config.to_dict as YAML) re-creates the terrain: a run from the
    reloaded configuration is the same bit for bit (a .npy heightfield is inlined)."""
    heights = np.random.default_rng(3).uniform(0.0, 0.01, (16, 16))
    np.save(tmp_path / "hf.npy", heights)
    data = load_preset("HmJ").to_dict()
    data["terrain"] = {"boxes": [{"centre": [0.6, 0.0, 0.02], "size": [0.3, 1.0, 0.04],
                                  "yaw": 0.1, "mu": 0.7}],
                       "heightfield": {"origin": [-0.5, -0.5], "cell": 0.07,
                                       "heights": "hf.npy", "mu": 0.6}}
    (tmp_path / "t.yaml").write_text(yaml.safe_dump(data))
    cfg = PhysicsConfig.from_yaml(str(tmp_path / "t.yaml"))
    text = yaml.safe_dump(cfg.to_dict(), sort_keys=False)
    again = PhysicsConfig.from_dict(yaml.safe_load(text), source="bag")
    assert np.array_equal(again.terrain.heightfield["heights"], heights)
    runs = []
    for c in (cfg, again):
        sim = Simulator(c)
        hold = PostureHold(sim.joint_positions())
        for _ in range(100):
            sim.step(hold.torque(sim))
        runs.append(np.concatenate([sim.q, sim.u]))
    assert np.array_equal(runs[0], runs[1])


@pytest.mark.parametrize("terrain,message", [
    ({"boxes": [{"centre": [0, 0], "size": [1, 1, 1]}]},
     "terrain.boxes[0].centre: expected a list of 3 numbers"),
    ({"boxes": [{"centre": [0, 0, 0], "size": [1, 0, 1]}]},
     "terrain.boxes[0].size[1]: must be > 0, got 0"),
    ({"boxes": [{"centre": [0, 0, 0], "size": [1, 1, 1], "colour": 1}]},
     "terrain.boxes[0]: unknown field 'colour'"),
    ({"stairs": {"rise": 0.04, "run": 0.3}}, "terrain.stairs.count: missing"),
    ({"slope": {"angle": 60, "length": 2}}, "terrain.slope.angle: must be <= 45, got 60"),
    ({"rough": {"amplitude": 0.01, "wavelength": 0.3, "seed": -1}},
     "terrain.rough.seed: must be >= 0"),
    ({"heightfield": {"origin": [0, 0], "cell": 0.1, "heights": [[0, 1], [2]]}},
     "terrain.heightfield.heights: the rows must have one length"),
    ({"heightfield": {"origin": [0, 0], "cell": 0.1, "heights": "nope.npy"}},
     "terrain.heightfield.heights: no such file"),
    ({"slope": {"angle": 10, "length": 2}, "rough": {"amplitude": 0.01, "wavelength": 1}},
     "terrain: slope and rough are each a heightfield"),
])
def test_bad_terrain_is_one_line_naming_the_field(terrain, message):
    data = load_preset("HmJ").to_dict()
    data["terrain"] = terrain
    with pytest.raises(ConfigError) as e:
        PhysicsConfig.from_dict(data, source="t.yaml")
    assert str(e.value).startswith("t.yaml: " + message), str(e.value)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("slope,message", [
    ({"length": 1e-4}, "would be 10003 x 20001 points (cell 0.0001 m = length / 1); at most "
                       "1024 a side: 2 x length + top and width must be <= 0.1023 m"),
    ({"length": 100, "top": 100, "width": 100},
     "would be 6001 x 2001 points (cell 0.05 m = length / 2000); at most 1024 a side: "
     "2 x length + top and width must be <= 51.15 m"),
    ({"length": 2, "width": 51.2}, "would be 101 x 1025 points"),
])
def test_a_slope_beyond_the_grid_bound_is_refused_before_it_is_made(slope, message):
    """The slope's grid follows from its length, top and width at a cell of about
    SLOPE_CELL; beyond MAX_GRID points a side it is refused on load (a 1e-4 m ramp asked
    for 4.8 GB), as a given heightfield is."""
    with pytest.raises(ConfigError) as e:
        packed(slope=dict({"angle": 10}, **slope))
    assert str(e.value).startswith("terrain.slope: its heightfield " + message), str(e.value)
    assert "\n" not in str(e.value)


def test_the_slopes_grid_is_the_shape_it_is_checked_at():
    """slope_shape (the check) and slope_grid (the heights) agree, for random slopes and at
    the bound: the largest slope accepted has MAX_GRID points a side."""
    from starleth_sim.physics.terrain import MAX_GRID, slope_grid, slope_shape
    rng = np.random.default_rng(3)
    for _ in range(200):
        s = {"angle": 10.0, "length": float(rng.uniform(0.01, 20)), "top":
             float(rng.uniform(0, 10)), "width": float(rng.uniform(0.01, 20)), "start": 0.0,
             "mu": None}
        n, cell, n_top, ny = slope_shape(s)
        _, c, heights, _ = slope_grid(s)
        assert heights.shape == (2 * n + n_top + 1, ny) and c == cell
    t = TerrainConfig(slope={"angle": 10, "length": 1.0, "top": 49.15, "width": 51.15})
    t.validate("terrain")
    assert t.grid()[2].shape == (MAX_GRID, MAX_GRID)


def test_rough_ground_needs_two_grid_points_per_wavelength():
    """On at most MAX_GRID points a side, rough ground of more than 511.5 wavelengths a side
    would alias its waves: refused; at the bound it has 1024 points a side."""
    ok = packed(rough={"amplitude": 0.01, "wavelength": 4.0 / 511.5, "size": 4.0})
    assert (ok[1], ok[2]) == (1024, 1024)
    with pytest.raises(ConfigError, match=r"terrain.rough: size / wavelength must be <= "
                                          r"511.5 \(at least 2 of its 1024 grid points a side "
                                          r"per wavelength\), got 4 / 0.0078"):
        packed(rough={"amplitude": 0.01, "wavelength": 4.0 / 512, "size": 4.0})


def test_the_boxes_bins_are_bounded_and_still_find_every_box():
    """Boxes that span many bins (5 plates of 1000 m: 1.3 million (bin, box) entries; 10 000
    of them were 2.6e9) get larger bins: at most MAX_BIN_ITEMS entries, and the contact
    query still meets the plates and a small box on them at the exact gap."""
    from starleth_sim.physics.terrain import MAX_BIN_ITEMS
    plates = [{"centre": [0.0, 0.0, 0.005 * k], "size": [1000.0, 1000.0, 0.01 * k]}
              for k in range(1, 6)]
    small = {"centre": [3.0, 4.0, 0.05], "size": [0.2, 0.2, 0.1]}
    p = packed(boxes=plates + [small])
    assert 0 < p[13] <= MAX_BIN_ITEMS and p[10] > 1000.0 / 512      # fewer, larger bins
    sim = body_sim(sphere_urdf(R, 1.0), boxes=plates + [small])
    for x, y, top in ((3.0, 4.0, 0.1), (-400.0, 300.0, 0.05), (0.0, 0.0, 0.05)):
        q = sim.q
        q[:3] = [x, y, top + R + 0.03]
        sim.reset(q)
        assert sim.gaps()[0] == pytest.approx(0.03, abs=1e-12), (x, y)


def test_bad_terrain_file_on_the_command_line_exits_2_with_one_line(tmp_path):
    data = load_preset("HmJ").to_dict()
    data["terrain"] = {"stairs": {"rise": -0.04, "run": 0.3, "count": 3}}
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    r = subprocess.run([sys.executable, "-m", "starleth_sim.tools.bench.bench", str(path)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    last = r.stderr.strip().splitlines()[-1]
    assert f"{path}: terrain.stairs.rise: must be > 0, got -0.04" in last, r.stderr


# -- the robot standing on each terrain --------------------------------------------------

TERRAINS = {
    "step": {"boxes": [{"centre": [0.5, 0.0, 0.02], "size": [0.6, 1.0, 0.04]}]},
    "stairs": {"stairs": {"rise": 0.04, "run": 0.25, "count": 3, "start": 0.0}},
    "slope": {"slope": {"angle": 10.0, "length": 2.0, "start": -1.0}},
    "rough": {"rough": {"amplitude": 0.015, "wavelength": 0.4, "seed": 1}},
}
PRESETS = ("Cm", "HmJ", "HmS", "HEJD", "HEJP", "HESD", "HESP", "HMJD", "HMJP", "HMSD", "HMSP")


def stand_on(preset, terrain, seconds):
    sim = Simulator.from_preset(preset, **TERRAINS[terrain])
    hold = PostureHold(sim.joint_positions())
    worst, n = 0.0, int(round(seconds / sim.control_period))
    support = []          # the total normal force over the last second [N]
    for k in range(n):
        sim.step(hold.torque(sim))
        worst = min(worst, sim.gaps().min())
        if k >= n - int(round(1.0 / sim.control_period)):
            support.append(sim.contact_forces().sum(axis=0)[2])
    return sim, worst, np.mean(support)


#: every preset on every terrain, 2 s each (the acceptance matrix of issue #37: 44 runs, ~6 s)
MATRIX = [(p, t) for p in PRESETS for t in TERRAINS]


@pytest.mark.parametrize("preset,terrain", MATRIX)
def test_robot_stands_on_terrain(preset, terrain):
    """2 s under the posture hold from resting on the terrain (the lowest foot touching,
    the others dropping onto it): standing still, carrying its weight (over the last
    second), a hard contact never more than 0.1 mm inside a surface."""
    sim, worst, support = stand_on(preset, terrain, 2.0)
    base = sim.base_state()
    assert np.linalg.norm(base["linear_velocity"]) < 0.02          # settled, standing
    assert sim.root_position()[2] > 0.3                              # not fallen
    weight = sum(i.mass for i in sim.description.model.inertias) * 9.81
    assert support == pytest.approx(weight, rel=0.03)
    if sim.config.contact_model == "hard":
        assert worst >= -1e-4, f"penetration {-worst * 1e3:.3f} mm"


def test_terrain_bench_runs_the_three_grounds():
    """starleth-bench --terrain's measurement (its figures go to doc/performance.md): the
    three grounds, each standing the same (the tiles and the heightfield are flat, 1 cm up)."""
    figures = terrain_rounds(rounds=1, steps=5)
    assert list(figures) == list(terrains()) and all(v > 0 for v in figures.values())


# -- starleth-view draws the recorded terrain --------------------------------------------

class _Bag:
    """What terrain_from_metadata reads of a bag: its metadata."""

    def __init__(self, config):
        text = yaml.safe_dump(config.to_dict(), sort_keys=False)
        self.metadata = {"starleth_sim": {"physics_config": text}}


def test_view_draws_the_recorded_terrain(capsys):
    """The bag's physics YAML (what sim_node records) gives starleth-view the terrain: each
    box of the stairs where the generator puts it, the heightfield as a mesh through its
    grid points (every other point of a 150 x 150 grid: at most 128 a side); a recorded terrain
    that is not valid is not drawn, with a warning."""
    heights = np.random.default_rng(0).uniform(0.0, 0.02, (150, 150))
    cfg = load_preset("HmJ").with_overrides(
        stairs={"rise": 0.04, "run": 0.25, "count": 3, "start": 0.5},
        heightfield={"origin": [-3.0, -3.0], "cell": 0.02, "heights": heights})
    terrain = terrain_from_metadata(_Bag(cfg), "bag.mcap")
    objects = dict(terrain_objects(terrain))
    assert [k for k in objects if k.startswith("box")] == ["box0", "box1", "box2"]
    box = objects["box1"]
    assert box["geometries"][0]["depth"] == pytest.approx(0.08)
    assert box["object"]["matrix"][12:15] == pytest.approx([0.5 + 1.5 * 0.25, 0.0, 0.04])
    mesh = objects["heightfield"]["geometries"][0]["data"]
    pts = np.array(mesh["attributes"]["position"]["array"]).reshape(-1, 3)
    assert len(pts) <= 128 ** 2 and len(mesh["index"]["array"]) % 3 == 0
    ix = np.round((pts[:, 0] + 3.0) / 0.02).astype(int)
    iy = np.round((pts[:, 1] + 3.0) / 0.02).astype(int)
    np.testing.assert_allclose(pts[:, 2], heights[ix, iy], atol=1e-5)
    assert {ix.min(), ix.max(), iy.max()} == {0, 149}                # the grid's corners
    bad = _Bag(cfg)
    bad.metadata["starleth_sim"]["physics_config"] = yaml.safe_dump(
        {"terrain": {"stairs": {"rise": -1, "run": 0.3, "count": 2}}})
    assert terrain_from_metadata(bad, "bag.mcap") is None
    assert "terrain is not valid, not drawn" in capsys.readouterr().err
