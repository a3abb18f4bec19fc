"""Contact geometry (ground plane, gaps) and the compliant contact law of Alg. 1.

The hard contact laws (unilateral contact, spatial Coulomb friction, Newton-type impacts)
are solved by the prox iterations in :mod:`starleth_sim.physics.prox`; this module holds what both
models share: the plane, its tangent basis, and per-contact bookkeeping.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import numba as nb

from .kernel_cache import KERNEL


def tangent_basis(normal):
    """Unit tangents t1, t2 with (n, t1, t2) right-handed; t1 is the projection of the world
    x axis (or y if n is nearly parallel to x) onto the plane."""
    n = np.asarray(normal, dtype=float)
    n = n / np.linalg.norm(n)
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t1 = ref - n * (ref @ n)
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)
    return n, t1, t2


@dataclass(frozen=True)
class GroundPlane:
    """The plane {x | n·x = n·p0}; p0 = (0, 0, height) so `height` is its height at the origin."""

    height: float = 0.0
    normal: tuple = (0.0, 0.0, 1.0)
    mu: float = 0.8

    def __post_init__(self):
        n, t1, t2 = tangent_basis(self.normal)
        object.__setattr__(self, "n", n)
        object.__setattr__(self, "t1", t1)
        object.__setattr__(self, "t2", t2)
        object.__setattr__(self, "offset", float(n[2] * self.height))
        frame = np.vstack([n, t1, t2])
        frame.setflags(write=False)      # made once: a ROS node reads it every step
        object.__setattr__(self, "_frame", frame)

    @property
    def frame(self):
        """3x3 matrix whose rows are n, t1, t2 (contact frame -> world: frame.T); read-only."""
        return self._frame


class CompliantLaw(NamedTuple):
    """The parameters of the compliant contact law (Alg. 1)."""

    mu: float              # μ, Coulomb friction coefficient
    c_N: float             # normal stiffness [N/m]
    d_N: float             # normal damping [N s/m]
    c_T: float             # tangential stiffness [N/m]
    d_T: float             # tangential damping [N s/m]
    slip_velocity: float   # ‖γ_T‖ below which a slipping contact counts as stopped [m/s]


@nb.njit(**KERNEL)
def compliant_contact_forces(law, gap, position, Wt, u, closed, slip, anchor, tangent1,
                             tangent2, lam):
    """Compliant contact law of Alg. 1 for all contact points, at (q^M, u^S), with the
    parameters `law` (the fields of a CompliantLaw; a plain tuple will do, as it crosses
    from Python cheaper than a namedtuple) and the plane's tangents t1, t2.

    Each closed contact (g_N ≤ 0) is a spring-damper between its current point P and the
    point P0 (`anchor`) where it was first detected or last re-anchored:
        λ_N = max(−c_N g_N − d_N γ_N, 0)
        stick: λ_T = −c_T g_T − d_T γ_T, g_T = tangential part of P − P0; if ‖λ_T‖ ≥ μλ_N
               it becomes λ_T = −μλ_N γ_T/‖γ_T‖ and the contact slips;
        slip:  λ_T = −μλ_N γ_T/‖γ_T‖; it sticks again (P0 reset to P) once ‖γ_T‖ ≈ 0 or the
               force the re-anchored spring-damper would give, −d_T γ_T, is inside the cone.
    Opening contacts (g_N > 0) forget their anchor. `lam` (nc x 3) receives (λ_N, λ_T1, λ_T2)
    in the contact frame (n, t1, t2); the state arrays are updated in place.
    """
    p = CompliantLaw(*law)
    mu, c_n, d_n, c_t, d_t = p.mu, p.c_N, p.d_N, p.c_T, p.d_T
    slip_velocity = p.slip_velocity
    nc = gap.shape[0]
    nv = u.shape[0]
    for i in range(nc):
        if gap[i] > 0.0:
            closed[i] = False
            slip[i] = False
            lam[i, 0] = 0.0
            lam[i, 1] = 0.0
            lam[i, 2] = 0.0
            continue
        if not closed[i]:
            closed[i] = True
            slip[i] = False
            for k in range(3):
                anchor[i, k] = position[i, k]
        gn = 0.0
        g1 = 0.0
        g2 = 0.0
        for j in range(nv):
            gn += Wt[i, 0, j] * u[j]
            g1 += Wt[i, 1, j] * u[j]
            g2 += Wt[i, 2, j] * u[j]
        # γ_N = gn, γ_T = (g1, g2)
        ln = -c_n * gap[i] - d_n * gn
        if ln < 0.0:
            ln = 0.0
        vt = np.sqrt(g1 * g1 + g2 * g2)
        lim = mu * ln
        if slip[i]:
            if vt > 0.0:
                l1 = -lim * g1 / vt
                l2 = -lim * g2 / vt
            else:
                l1 = 0.0
                l2 = 0.0
            if vt <= slip_velocity or d_t * vt <= lim:
                slip[i] = False
                for k in range(3):
                    anchor[i, k] = position[i, k]
        else:
            dx0 = position[i, 0] - anchor[i, 0]
            dx1 = position[i, 1] - anchor[i, 1]
            dx2 = position[i, 2] - anchor[i, 2]
            gt1 = tangent1[0] * dx0 + tangent1[1] * dx1 + tangent1[2] * dx2
            gt2 = tangent2[0] * dx0 + tangent2[1] * dx1 + tangent2[2] * dx2
            l1 = -c_t * gt1 - d_t * g1
            l2 = -c_t * gt2 - d_t * g2
            if l1 * l1 + l2 * l2 >= lim * lim:
                if vt > 0.0:
                    l1 = -lim * g1 / vt
                    l2 = -lim * g2 / vt
                else:
                    s = lim / np.sqrt(l1 * l1 + l2 * l2) if (l1 != 0.0 or l2 != 0.0) else 0.0
                    l1 *= s
                    l2 *= s
                slip[i] = True
        lam[i, 0] = ln
        lam[i, 1] = l1
        lam[i, 2] = l2


@nb.njit(**KERNEL)
def generalized_contact_force(Wt, lam, out):
    """out += Σ_i W_i λ_i  (W_i = Wt[i]^T), the contribution of the compliant forces to h."""
    nc = lam.shape[0]
    nv = out.shape[0]
    for i in range(nc):
        a, b, c = lam[i, 0], lam[i, 1], lam[i, 2]
        if a == 0.0 and b == 0.0 and c == 0.0:
            continue
        for j in range(nv):
            out[j] += Wt[i, 0, j] * a + Wt[i, 1, j] * b + Wt[i, 2, j] * c
