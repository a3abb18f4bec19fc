"""Searching the ground: what the controller does with a foot that finds none where it
expected it (a ledge, a stair down, a hole), read from its own inputs only: the contact flags
(the foot forces against contact_force_threshold) and the leg kinematics. Plain Python /
numpy: its arithmetic runs only while a foot searches.

A leg in LOST_CONTACT (controller.py: planned stance, or standing, without contact) searches:
its foot goes down from where the search began, at the lower of the height expected there
(less touchdown_depth) and the foot's own height, at a bounded speed to a bounded depth
below the expected height, never beyond the leg's reach (the HFE-to-foot distance at most
leg_reach of the stretched leg):

- trotting, above the foothold its swing aimed at, below the height the ground plane
  expected there (csrc/ground_plane.c), at step_down_speed to step_down_depth;
- standing, under its hip, below the trunk's ground, at lost_contact_speed to
  lost_contact_depth.

A trotting swing that ends without contact (no force at the foot when its stance should
begin) starts such a search, and until the foot touches, or has searched as deep as it may,
the gait waits for it: the clock stays at the end of that swing (the other pair stays in
support instead of lifting off and leaving the trunk on one leg), and the trunk waits too
(controller.py: the virtual model holds it over its support feet, no velocity command); its
height reference is lowered as far as the search needs to stay within the leg's reach. Once
the foot touches, it is a support leg: where it stands enters the trunk's ground estimate and
the ground plane, so the stance height follows the new ground.
"""
from __future__ import annotations

import math

import numpy as np

#: leg state (controller.py: LOST_CONTACT)
_LOST_CONTACT = 2
#: a searching foot this close to its deepest target [m] has reached it
REACHED = 0.01


def leg_reach(geo, dx, reach):
    """How far below its hip a leg's foot centre reaches with the foot dx [m] ahead of or
    behind the hip: l0 + √((e (l1 + l2))² − dx²), e = `reach` the share of the stretched leg
    allowed (geo: l0, l1, l2, foot radius, knee sign)."""
    l0, l1, l2 = geo[0], geo[1], geo[2]
    d = reach * (l1 + l2)
    return l0 + math.sqrt(max(d * d - dx * dx, 0.0))


def _search_law(p, trotting):
    """(speed, deepest): the lowering speed [m/s] and the deepest target below the expected
    height [m] of a search, trotting or standing."""
    if trotting:
        return p.step_down_speed, p.step_down_depth
    return p.lost_contact_speed, p.lost_contact_depth


class GroundSearch:
    """The legs' searches for the ground and the gait's wait for them (module docstring).

    Per control period: `hold_clock` before the legs' states are taken from the clock
    (t − t₀), `mark_waiting` right after, `targets` once the ground estimate is current."""

    def __init__(self):
        # per leg, Python lists (read on every trotting call: cheaper than numpy items)
        self.waiting = [False] * 4                 # legs the gait clock waits for
        self.holding = False                       # ... any
        self.in_swing = [False] * 4                # planned swing at the last call
        self.held_swing = [-2] * 4                 # the swing (cycle) the clock last waited for
        self.since = [math.nan] * 4                # each search's start [s]
        self.expected_z = [0.0] * 4                # the ground height it expects [m]
        self.offset = [0.0] * 4                    # its start below that height [m]

    def reset(self):
        self.holding = False
        self.waiting = [False] * 4
        self.in_swing = [False] * 4
        self.held_swing = [-2] * 4
        self.since = [math.nan] * 4

    # -- the gait's wait ---------------------------------------------------------------------
    def hold_clock(self, p, trotting, t, dt, t0, phase_offsets, swing_cycle, grounded,
                   contact_z, foothold_z):
        """The gait clock's start t₀ for this call: t₀ + dt (the phases stay those of the
        last call) while a leg whose planned swing the clock would now end has no contact
        and has not searched as deep as it may (`_searched`), once per swing (a foot that
        touches and loses its contact again searches while the gait goes on); contact_z:
        the feet's contact points' heights, foothold_z: the heights their swings expected.
        Scalar code: it runs on every trotting call, on four legs."""
        if not trotting:
            if self.holding or self.held_swing != [-2] * 4:
                self.reset()
            return t0
        if dt <= 0.0:
            return t0
        period, stance = p.gait_period, 1.0 - p.duty_factor
        self.holding = False
        for k in range(4):
            waits = self.in_swing[k] and not grounded[k]
            if waits and not self.waiting[k]:
                c = (t - t0) / period - phase_offsets[k]
                cycle = math.floor(c)
                # the swing ends now: a new search, unless the clock waited for it once
                waits = (cycle > swing_cycle[k] or c - cycle >= stance) and \
                    self.held_swing[k] != swing_cycle[k]
                if waits:
                    self.held_swing[k] = swing_cycle[k]
                    self._begin(k, t, foothold_z[k], contact_z[k], p.touchdown_depth)
            elif waits:
                # waiting (whatever the round-off of the held clock: t − t₀ at the swing's
                # end or a hair before it), until searched as deep as it may
                waits = not self._searched(p, k, t, contact_z[k])
            self.waiting[k] = waits
            self.holding |= waits
        return t0 + dt if self.holding else t0

    def _searched(self, p, k, t, contact_z):
        """Leg k has searched as deep as it may: its contact point within REACHED of
        step_down_depth below the expected height, or searching for twice the time its
        target takes to get there (the trunk could not lower enough)."""
        return contact_z <= self.expected_z[k] - p.step_down_depth + REACHED or \
            t - self.since[k] >= 2.0 * (p.step_down_depth - self.offset[k]) \
            / p.step_down_speed

    def mark_waiting(self, states, swing_phase, lost_since):
        """After the legs' states are taken from the clock: which legs are in a planned swing
        (for the next call), and the legs the clock waits for (in their swing by the held
        clock) searching: LOST_CONTACT, outside the swing, lost since their swing's end."""
        self.in_swing = (swing_phase < 1.0).tolist()
        if self.holding:
            for k in range(4):
                if self.waiting[k]:
                    states[k] = _LOST_CONTACT
                    swing_phase[k] = 1.0
                    lost_since[k] = self.since[k]

    # -- the searching feet --------------------------------------------------------------------
    def _begin(self, k, t, expected_z, contact_z, touchdown_depth):
        """A search of leg k from time t, expecting the ground at expected_z, from the lower
        of touchdown_depth below it and the foot's contact point (contact_z)."""
        self.since[k] = t
        self.expected_z[k] = expected_z
        self.offset[k] = max(touchdown_depth, expected_z - contact_z)

    def targets(self, p, trotting, t, states, lost_since, foothold, foothold_z, ground,
                contact_z, hips, geo, cy, sy, base_z, reference, target):
        """The foot-centre targets of the legs in LOST_CONTACT and their rates, rows
        (x, y, z, ż) of `target`, and the trunk's height reference: `reference`, lowered
        while a trotting leg searches so that the leg reaches its target (module docstring;
        hips: the hips in the world, 4 x 3; cy, sy: the heading; base_z: the trunk's
        height; geo: the legs' geometry rows, l0, l1, l2, foot radius, knee sign)."""
        speed, deepest = _search_law(p, trotting)
        for k in np.flatnonzero(np.asarray(states) == _LOST_CONTACT):
            if trotting:
                x, y, expected = foothold[k, 0], foothold[k, 1], foothold_z[k]
            else:
                x, y, expected = hips[k, 0], hips[k, 1], ground
            if lost_since[k] != self.since[k]:     # lost in stance, or standing: a new search
                self._begin(k, lost_since[k], expected, contact_z[k], p.touchdown_depth)
            if trotting:                           # where the swing expected the ground
                expected = self.expected_z[k]
            depth = self.offset[k] + speed * (t - self.since[k])
            # a trotting search's rate is fed forward (fast: damping would hold it back)
            rate = speed if trotting else 0.0
            if not depth < deepest:
                depth, rate = deepest, 0.0
            z = expected + geo[k, 3] - depth       # the foot centre
            dx = cy * (x - hips[k, 0]) + sy * (y - hips[k, 1])
            reach = leg_reach(geo[k], dx, p.leg_reach)
            if trotting:                           # the trunk low enough to reach z
                reference = min(reference, z + reach - (hips[k, 2] - base_z))
            if z < hips[k, 2] - reach:
                z, rate = hips[k, 2] - reach, 0.0
            target[k] = x, y, z, -rate
        return reference
