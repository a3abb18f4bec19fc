"""External wrenches on the robot's links: `ExternalWrenches` holds the persistent ones (an
input like the torques, not evolving state) and turns them, with the timed wrenches of a
`SimState` (its pending_wrenches, which it counts down), into the generalized force of a
physics step. `Simulator.apply_wrench`, `set_persistent_wrench` and `clear_wrenches` are
the public face.
"""
from __future__ import annotations

import numpy as np

#: the timed wrenches pending at most (each is summed into every physics step until it ends:
#: ~40 us a wrench and step; 200 000 of them made a step take 7.7 s)
MAX_TIMED_WRENCHES = 100


def _vec3(name, v):
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be 3 finite numbers, got {v!r}")
    return a


class ExternalWrenches:
    """The persistent wrenches {link: (force, torque)} (world axes, at the link's origin) of
    one coordinate set, and the generalized force of all wrenches over a physics step."""

    def __init__(self, coords):
        self.coords = coords
        self.persistent = {}

    def checked(self, link, force, torque):
        """(force, torque) as two 3-vectors; ValueError on an unknown link or a vector that
        is not 3 finite numbers."""
        if link not in self.coords.link_names():
            raise ValueError(f"unknown link '{link}' "
                             f"(links: {', '.join(self.coords.link_names())})")
        return _vec3("force", force), _vec3("torque", torque)

    def set_persistent(self, link, force, torque):
        """A wrench on `link` at every step until cleared (a zero wrench clears it)."""
        f, m = self.checked(link, force, torque)
        if not f.any() and not m.any():
            self.persistent.pop(link, None)
        else:
            self.persistent[link] = (f, m)

    def none_to_apply(self, state) -> bool:
        """Neither a timed wrench of `state` nor a persistent one acts in the next step."""
        return not state.pending_wrenches and not self.persistent

    def generalized_force(self, state, dt):
        """The generalized force of the wrenches over the next physics step at state.q;
        counts the timed wrenches of `state` down (None: no wrench)."""
        pending = state.pending_wrenches
        if not self.persistent and not pending:
            return None
        q = state.q
        f_ext = np.zeros(self.coords.nv)
        for link, (f, m) in self.persistent.items():
            f_ext += self.coords.wrench_generalized_force(q, link, f, m)
        for w in pending:
            link, f, m, remaining = w
            frac = min(remaining, dt) / dt
            f_ext += frac * self.coords.wrench_generalized_force(q, link, f, m)
            w[3] = remaining - dt
        pending[:] = [w for w in pending if w[3] > 1e-12]
        return f_ext
