"""Contact geometry (ground plane, gaps) and the compliant contact law of Alg. 1.

The hard contact laws (unilateral contact, spatial Coulomb friction, Newton-type impacts)
are solved by the prox iterations in :mod:`starleth_sim.physics.prox`; this module holds what both
models share: the plane, its tangent basis, and per-contact bookkeeping, and the contact
reports of a control step (`ContactInfo`, `contact_states`).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .kernels.layouts import COMPLIANT_LAW
from .terrain import TOP, pack_terrain


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
    """The plane {x | n·x = n·p0}; p0 = (0, 0, height) so `height` is its height at the origin;
    and the terrain on it, packed (terrain.pack_terrain; None: the plane alone). The kernels
    read the plane and the terrain; `terrain` is the packed array they get."""

    height: float = 0.0
    normal: tuple = (0.0, 0.0, 1.0)
    mu: float = 0.8
    terrain: np.ndarray | None = field(default=None, compare=False, repr=False)

    def __post_init__(self):
        packed = pack_terrain(None, self.height, self.mu) if self.terrain is None \
            else np.ascontiguousarray(self.terrain, dtype=float)
        packed.setflags(write=False)
        object.__setattr__(self, "terrain", packed)
        #: the plane alone (no box, no heightfield): every contact's frame is the plane's
        object.__setattr__(self, "flat", bool(packed[0] == 0 and packed[1] == 0))
        n, t1, t2 = tangent_basis(self.normal)
        object.__setattr__(self, "n", n)
        object.__setattr__(self, "t1", t1)
        object.__setattr__(self, "t2", t2)
        object.__setattr__(self, "offset", float(n[2] * self.height))
        #: the ground as the kernels take it: (n, t1, t2, offset, packed terrain)
        object.__setattr__(self, "kernel_args", (n, t1, t2, self.offset, packed))
        frame = np.vstack([n, t1, t2])
        frame.setflags(write=False)      # made once: a ROS node reads it every step
        object.__setattr__(self, "_frame", frame)

    @property
    def frame(self):
        """3x3 matrix whose rows are n, t1, t2 (contact frame -> world: frame.T); read-only."""
        return self._frame


#: The parameters of the compliant contact law (Alg. 1), in the order
#: kernels.layouts.COMPLIANT_LAW declares
CompliantLaw = COMPLIANT_LAW.named_tuple(
    "The parameters of the compliant contact law (Alg. 1).", __name__)


# The compliant contact law of Alg. 1 for all contact points, at (q^M, u^S), is written once,
# in C (csrc/contact.c: compliant_contact_forces, which the step kernels call with the
# fields of a `CompliantLaw`). Each closed contact (g_N ≤ 0) is a spring-damper between its
# current point P and the point P0 (`anchor`) where it was first detected or last re-anchored:
#     λ_N = max(−c_N g_N − d_N γ_N, 0)
#     stick: λ_T = −c_T g_T − d_T γ_T, g_T = tangential part of P − P0; if ‖λ_T‖ ≥ μλ_N it
#            becomes λ_T = −μλ_N γ_T/‖γ_T‖ and the contact slips;
#     slip:  λ_T = −μλ_N γ_T/‖γ_T‖; it sticks again (P0 reset to P) once ‖γ_T‖ ≈ 0 or the
#            force the re-anchored spring-damper would give, −d_T γ_T, is inside the cone.
# Opening contacts (g_N > 0) forget their anchor. `lam` (nc x 3) receives (λ_N, λ_T1, λ_T2)
# in each contact's frame (n, t1, t2), `frames` (nc x FRAME_STRIDE) holding that frame and
# its μ per contact (written by the contact kinematics: the plane's, or the terrain
# surface's); the state arrays are updated in place. generalized_contact_force then adds Σ_i W_i λ_i
# (W_i = Wt[i]^T), the compliant forces' contribution, to h.

#: the entries per contact of a frames array (csrc/core.h): n (3), t1 (3), t2 (3), μ and the
#: surface (0 none or not known, 1 the plane, 2 the heightfield, 3 + k box k)
FRAME_STRIDE = 11


#: contact states: no normal force, inside the friction cone, on its boundary
CONTACT_STATES = ("open", "stick", "slip")
#: a hard contact slips when |Λ_T| ≥ (1 − this) μ Λ_N (the prox projects onto the cone)
SLIP_TOLERANCE = 1e-6



@dataclass
class ContactInfo:
    name: str
    active: bool            # at the last step's midpoint: hard contacts in the active set
                            # (g_N ≤ activation_gap, or loaded and g_N ≤ opening_gap with
                            # contact.activation "hysteresis"); compliant ones closed
                            # (g_N ≤ 0)
    gap: float              # g_N at the last step's midpoint [m] (negative: penetration)
    impulse: np.ndarray     # Λ in the world frame, summed over the control period [N s]
    force: np.ndarray       # impulse / control period [N]
    position: np.ndarray    # contact point in the world frame [m]
    state: str = "open"     # open | stick | slip (CONTACT_STATES), see Simulator.contact_states


def contact_states(impulse, hard: bool, mu: float, slip):
    """Per contact point, an index into CONTACT_STATES from its Λ (nc x 3, contact frame):
    0 open (no normal impulse), 1 stick, 2 slip. Hard contacts: slip when the tangential
    impulse is on the boundary of the friction cone, |Λ_T| ≥ (1 − SLIP_TOLERANCE) μ Λ_N;
    compliant contacts: `slip`, the slip flags of Alg. 1."""
    lam = impulse
    normal = lam[:, 0] > 0.0
    if hard:
        tangential = np.hypot(lam[:, 1], lam[:, 2])
        slip = tangential >= (1.0 - SLIP_TOLERANCE) * mu * lam[:, 0]
    return np.where(normal, np.where(slip, 2, 1), 0)


class SphereSlots:
    """The public, per-sphere view of the contact slots (on a terrain a contact sphere has
    two, i and ns + i: csrc/kinematics.c; on the plane one, and every view is the array
    itself): a sphere's gap is its slots' smallest, its point that of that slot, its force
    their sum (world frame), it is active when either is, and its state is that of the slot
    with the larger normal impulse."""

    def __init__(self, n_spheres: int, n_slots: int):
        self.ns, self.two = n_spheres, n_slots != n_spheres

    def gaps(self, gap):
        ns = self.ns
        return np.minimum(gap[:ns], gap[ns:]) if self.two else gap

    def points(self, gap, position):
        ns = self.ns
        if not self.two:
            return position
        return np.where((gap[ns:] < gap[:ns])[:, None], position[ns:], position[:ns])

    def sums(self, world):
        return world[:self.ns] + world[self.ns:] if self.two else world

    def active(self, active):
        return active[:self.ns] | active[self.ns:] if self.two else active

    def states(self, states, impulse):
        ns = self.ns
        if not self.two:
            return states
        return np.where(impulse[ns:, 0] > impulse[:ns, 0], states[ns:], states[:ns])


def rest_on_ground(coords, ground, q, overlap, iterations=8):
    """Moves q (in place) so that its lowest contact rests on the ground with g_N = −overlap:
    on the plane every floating body along n at once; on a terrain vertically, in a few
    rounds (the surfaces' normals are not vertical)."""
    c = coords
    gap, pos = np.zeros(c.n_contacts), np.zeros((c.n_contacts, 3))
    Wt, frames = np.zeros((c.n_contacts, 3, c.nv)), np.zeros((c.n_contacts, FRAME_STRIDE))
    if ground.flat:
        c.contact_kinematics(q, ground, gap, pos, Wt)
        for iq in c.root_q:  # every floating body of the coordinate set
            q[iq:iq + 3] -= ground.n * (gap.min() + overlap)
        return
    # (the gaps of every height exact: not the plane alone above terrain.TOP + BOX_REACH, so
    # that a first round that overshoots upwards still sees the terrain)
    packed = ground.terrain.copy()
    packed[TOP] = np.inf
    ground = replace(ground, terrain=packed)
    for _ in range(iterations):
        c.contact_kinematics(q, ground, gap, pos, Wt, np.inf, frames)
        i = int(np.argmin(gap))
        dz = (gap[i] + overlap) / max(frames[i, 2], 0.1)
        for iq in c.root_q:
            q[iq + 2] -= dz
        if abs(gap[i] + overlap) < 1e-12:
            break
