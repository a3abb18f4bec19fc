"""The controller's search for the ground (starleth_controller/step_down.py), piece by piece:
the leg's reach against the leg's inverse kinematics, the gait clock's wait for a foot that
finds no ground at the end of its swing (driven by the controller's own leg-state kernel),
and the searching feet's targets and the trunk's height reference against their formulas.
The walks down stairs and ledges are in test_terrain_walk.py."""
from __future__ import annotations

import math

import numpy as np
import pytest

from starleth_controller import LOST_CONTACT, SUPPORT, SWING, ControllerParams, RobotModel
from starleth_controller import kernels as K
from starleth_controller.step_down import REACHED, GroundSearch, leg_reach
from starleth_sim.physics.description import urdf_path

DT = 0.0025                      # control period [s]
OFFSETS = np.array([0.0, 0.5, 0.5, 0.0])    # LF, RF, LH, RH: LF + RH swing first


@pytest.fixture(scope="module")
def model():
    return RobotModel(urdf_path())


@pytest.mark.parametrize("dx", [0.0, 0.12, -0.2])
def test_leg_reach_is_what_the_leg_reaches(model, dx):
    """A foot centre leg_reach below the hip (dx ahead) is reached by the leg's IK with its
    HFE-to-foot distance at the allowed share of the stretched leg; beyond the IK's own
    limit (0.995 of it) a target is pulled back."""
    geo = model.geometry
    for k in range(4):
        l0, l1, l2 = geo[k, :3]
        for share in (0.9, 0.98):
            r = model.hip[k] + [dx, 0.0, -leg_reach(geo[k], dx, share)]
            q = model.leg_ik(k, r)
            np.testing.assert_allclose(model.leg_fk(k, *q), r, atol=1e-9)
            hfe = model.hip[k] + [0.0, 0.0, -l0]
            assert np.linalg.norm(r - hfe) == pytest.approx(share * (l1 + l2), abs=1e-12)
        r = model.hip[k] + [dx, 0.0, -leg_reach(geo[k], dx, 1.0)]
        assert np.linalg.norm(model.leg_fk(k, *model.leg_ik(k, r)) - r) > 1e-3


class Gait:
    """The gait clock and leg states as StarlethController._leg_states runs them (hold_clock,
    kernels.leg_states, mark_waiting), trotting from t = 0."""

    def __init__(self, params):
        self.p, self.search = params, GroundSearch()
        self.t, self.t0 = 0.0, 0.0
        self.phase, self.cycle = np.zeros(4), np.full(4, -1, dtype=np.int64)
        self.states = np.zeros(4, dtype=np.int64)
        self.lost_since, self.support = np.full(4, np.nan), np.zeros(4, dtype=np.int64)
        self.foothold_z, self.contact_z = np.zeros(4), np.zeros(4)

    def step(self, grounded):
        p = self.p
        self.t += DT
        self.t0 = self.search.hold_clock(p, True, self.t, DT, self.t0, OFFSETS, self.cycle,
                                         np.asarray(grounded), self.contact_z, self.foothold_z)
        K.leg_states(True, self.t, self.t0, p.gait_period, OFFSETS, p.duty_factor,
                     p.early_touchdown_phase, np.asarray(grounded), self.phase, self.cycle,
                     self.states, self.lost_since, self.support)
        self.search.mark_waiting(self.states, self.phase, self.lost_since)
        return self.states.tolist()

    def run_to(self, t, grounded):
        while self.t < t - 1e-9:
            states = self.step(grounded)
        return states


def test_the_gait_waits_for_a_foot_that_finds_no_ground():
    """LF's swing (the first half cycle, 0.4 s) ends without contact: the clock stops, LF
    searches (LOST_CONTACT since the swing's end) while RF and LH stay in support instead
    of lifting off; 60 ms later LF touches and the trot goes on from where it stopped."""
    g = Gait(ControllerParams())
    half = 0.5 * g.p.gait_period
    swing_pair = [False, True, True, False]
    assert g.run_to(half - DT, swing_pair) == [SWING, SUPPORT, SUPPORT, SWING]
    states = g.run_to(half + 0.06, [False, True, True, True])       # RH lands, LF does not
    assert states == [LOST_CONTACT, SUPPORT, SUPPORT, SUPPORT]
    assert g.search.waiting == [True, False, False, False]
    assert g.lost_since[0] == pytest.approx(half, abs=DT)
    assert g.t0 == pytest.approx(0.06 + DT, abs=1e-9)              # the clock stood still
    states = g.step([True, True, True, True])                      # LF finds the ground
    assert not g.search.holding
    assert states == [SUPPORT, SWING, SWING, SUPPORT]              # and the trot goes on
    assert g.t0 == pytest.approx(0.06 + DT, abs=1e-9)


def test_the_gait_waits_once_per_swing_and_at_most_the_search_time():
    """A foot that never finds the ground: the clock waits twice the time its target takes
    to step_down_depth, then goes on (the leg goes on searching in its stance). A foot that
    touched and lost the contact again at its swing's end holds the clock once only, and a
    foot already as deep as it may search does not hold it."""
    p = ControllerParams()
    g = Gait(p)
    half = 0.5 * p.gait_period
    g.run_to(half - DT, [False, True, True, False])
    g.foothold_z[:] = 0.1
    g.contact_z[:] = 0.1 - p.touchdown_depth
    g.run_to(half + 0.5, [False, True, True, True])
    waited = g.t0
    assert waited == pytest.approx(2 * (p.step_down_depth - p.touchdown_depth)
                                   / p.step_down_speed, abs=2 * DT)
    assert g.states[0] == LOST_CONTACT and g.states[1] == SWING

    g = Gait(p)
    g.run_to(half - DT, [False, True, True, False])
    g.run_to(half + 0.02, [False, True, True, True])     # waits 20 ms ...
    assert g.search.waiting[0]
    g.step([True, True, True, True])                     # ... touches ...
    g.step([False, True, True, True])                    # ... and loses it again
    assert not g.search.holding and g.states[0] == LOST_CONTACT
    assert g.states[1] == SWING

    g = Gait(p)
    g.run_to(half - DT, [False, True, True, False])
    g.contact_z[0] = -p.step_down_depth + REACHED        # foothold_z 0: searched
    g.step([False, True, True, True])
    g.step([False, True, True, True])
    assert not g.search.holding and g.states[1] == SWING


def test_standing_or_on_flat_ground_the_clock_never_waits():
    """Standing, nothing holds a clock; trotting with every foot landing in time neither."""
    p = ControllerParams()
    s = GroundSearch()
    assert s.hold_clock(p, False, 1.0, DT, 0.3, OFFSETS, np.zeros(4, dtype=np.int64),
                        np.zeros(4, dtype=bool), np.zeros(4), np.zeros(4)) == 0.3
    g = Gait(p)
    for _ in range(int(2 * p.gait_period / DT)):
        swing = g.phase < 1.0
        g.step(~swing | (g.phase > 0.9))                 # each foot lands late in its swing
        assert not g.search.holding
    assert g.t0 == 0.0


def test_search_targets_and_the_trunk_height_reference(model):
    """A trotting search: the foot centre above the foothold, starting touchdown_depth below
    the expected height (or at the foot, when it is lower), going down at step_down_speed
    (fed forward) to step_down_depth below it, never beyond the leg's reach below its hip;
    the trunk's reference lowered by what the leg lacks to reach the search target. A
    standing search: under the hip, at lost_contact_speed, at rest, below the trunk's
    ground."""
    p = ControllerParams()
    geo, r = model.geometry, model.foot_radius[0]
    hips = np.array([[0.25, 0.18, 0.5], [0.25, -0.18, 0.5], [-0.25, 0.18, 0.5],
                     [-0.25, -0.18, 0.5]])
    base_z = 0.5
    foothold = hips[:, :2] + [0.05, 0.0]
    foothold_z, contact_z = np.full(4, 0.1), np.full(4, 0.12)
    states = [LOST_CONTACT, SUPPORT, SUPPORT, SUPPORT]
    lost_since = np.array([1.0, np.nan, np.nan, np.nan])
    target = np.zeros((4, 4))
    s = GroundSearch()
    reach = leg_reach(geo[0], 0.05, p.leg_reach)
    for t, depth in ((1.0, p.touchdown_depth), (1.05, p.touchdown_depth + 0.05),
                     (2.0, p.step_down_depth)):
        ref = s.targets(p, True, t, states, lost_since, foothold, foothold_z, 0.0, contact_z,
                        hips, geo, 1.0, 0.0, base_z, 0.6, target)
        z = 0.1 + r - depth
        assert target[0, :2].tolist() == foothold[0].tolist()
        assert target[0, 2] == pytest.approx(max(z, 0.5 - reach), abs=1e-12)
        rate = -p.step_down_speed if depth < p.step_down_depth and z > 0.5 - reach else 0.0
        assert target[0, 3] == rate
        assert ref == pytest.approx(min(0.6, z + reach), abs=1e-12)
    assert ref < 0.5 and target[0, 2] == pytest.approx(0.5 - reach)   # reach-bound, lowered

    s = GroundSearch()                                   # the foot below the expected height
    contact_z[0] = 0.05
    s.targets(p, True, 1.0, states, lost_since, foothold, foothold_z, 0.0, contact_z, hips,
              geo, 1.0, 0.0, base_z, 0.6, target)
    assert target[0, 2] == pytest.approx(0.05 + r)

    s = GroundSearch()                                   # standing
    hips[:, 2] = base_z = 0.45
    ref = s.targets(p, False, 1.5, states, lost_since, foothold, foothold_z, 0.02, contact_z,
                    hips, geo, 1.0, 0.0, base_z, 0.6, target)
    assert ref == 0.6
    depth = min(p.touchdown_depth + 0.5 * p.lost_contact_speed, p.lost_contact_depth)
    assert target[0].tolist() == pytest.approx([0.25, 0.18, 0.02 + r - depth, 0.0])
    assert math.isclose(depth, p.lost_contact_depth)
