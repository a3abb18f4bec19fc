"""The evolving state of a simulation, apart from the model (as MuJoCo's mjModel/mjData or
Pinocchio's Model/Data split them).

What is what:

* **Model / settings** (fixed while stepping, never rolled back): the robot description and
  its coordinate set, the `PhysicsConfig`, the kernels' typed settings
  (`stepper.StepSettings`, `contact.CompliantLaw`), the ground plane, the joint limits, and
  the *persistent* external wrenches (`Simulator.set_persistent_wrench`): they are an input
  the user sets, like the torques, not something a step evolves.
* **State** (`SimState`, this module): everything a step reads *and* writes, so that the
  next step depends on it — q, u, t, the hard contacts' memory (the last step's impulses Λ
  and active flags, which warm-start the prox iteration and decide the activation
  hysteresis, Λ_B of the bilateral constraints, and the α the prox starts with), the
  compliant contacts' state of Alg. 1
  (closed, slip, anchor P0, and the last forces λ), the drives' lagged torques and the
  *timed* external wrenches
  (`Simulator.apply_wrench`), whose remaining durations a step counts down. A copy of it is
  a snapshot; restoring one is an assignment (`Simulator.snapshot` / `Simulator.restore`).
* **Workspace** (Data-like scratch, recomputed by every step, never part of a snapshot):
  the stepper's arrays at q^M (g_N, contact points, W^T of every contact, the factor L of
  M, u_free, Δu_p, b_B), its "prepared step" cache (`MoreauStepper.prepare`, valid only
  for the very q and u objects it was made from), its counters (`StepperStats`), and the
  Simulator's reports of the last control step (contacts, applied torques, diagnostics)
  and its cache of the joint velocities of the current state.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class SimState:
    """One simulation state (see the module docstring for what is not in it).

    Arrays run over every contact point of the model (nc) and every bilateral constraint row
    (nb); the contact frame is (n, t1, t2) of the ground plane."""

    q: np.ndarray                  # generalized coordinates (coordinate set's layout)
    u: np.ndarray                  # generalized velocities [m/s, rad/s]
    t: float = 0.0                 # simulated time [s]
    #: hard contacts (None with compliant ones): Λ = (Λ_N, Λ_T1, Λ_T2) of the last physics
    #: step (nc x 3) [N s] and whether each contact was in the active set I (warm start;
    #: hysteresis of I)
    last_impulse: np.ndarray | None = None
    last_active: np.ndarray | None = None
    #: Λ_B of the bilateral constraints in the last physics step (nb) [N s] (warm start);
    #: with Coulomb joint friction (hard contacts), then the joints' friction impulses Λ_f
    last_bilateral: np.ndarray | None = None
    #: the prox's memory (3): the scale of the paper's α (solver.alpha) the last solve
    #: converged with, when it needed the fallback (1: the paper's α), and the steps it has
    #: started the solves since (the next solve starts there while the active set stays the
    #: same: solver.fallback_hold); the last solve's sweeps (inf: none yet; a few, with the
    #: same active set: the next one tries the velocity form before forming G)
    prox_memory: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, np.inf]))
    #: compliant contacts (Alg. 1; None with hard ones): closed (g_N ≤ 0), slipping,
    #: anchor P0 (nc x 3) [m] and the last forces λ = (λ_N, λ_T1, λ_T2) (nc x 3) [N]
    closed: np.ndarray | None = None
    slip: np.ndarray | None = None
    anchor: np.ndarray | None = None
    lam_compliant: np.ndarray | None = None
    #: timed external wrenches still to apply: [link, force, torque, remaining time [s]]
    pending_wrenches: list = field(default_factory=list)
    #: on a terrain, the surface each contact slot held at the last step (nc; the stepper
    #: keeps it in its frames, column 10: Simulator.snapshot / restore carry it), else None
    surfaces: np.ndarray | None = None
    #: with a torque bandwidth (actuator.torque_bandwidth), the lagged torques the drives
    #: applied in the last physics step (one per actuated joint) [N m], else None
    drive_torque: np.ndarray | None = None

    @classmethod
    def initial(cls, q, u, t: float, n_contacts: int, n_bilateral: int,
                hard: bool) -> "SimState":
        """The state (q, u, t) with no contact memory and no pending wrench; the memory of
        the other contact model (hard: the compliant one, and vice versa) is None."""
        nc = n_contacts
        if hard:
            return cls(q, u, float(t), last_impulse=np.zeros((nc, 3)),
                       last_active=np.zeros(nc, dtype=np.bool_),
                       last_bilateral=np.zeros(n_bilateral))
        return cls(q, u, float(t), last_bilateral=np.zeros(n_bilateral),
                   closed=np.zeros(nc, dtype=np.bool_), slip=np.zeros(nc, dtype=np.bool_),
                   anchor=np.zeros((nc, 3)), lam_compliant=np.zeros((nc, 3)))

    def copy(self, share_qu: bool = False) -> "SimState":
        """A deep copy (a snapshot): nothing is shared with this state. With share_qu the
        copy holds the same q and u arrays (Simulator.step's rollback point: a step replaces
        q and u by new arrays and never writes into them). (Simulator.step takes one per
        control step, so this is written for speed.)"""
        new = object.__new__(SimState)
        new.q = self.q if share_qu else self.q.copy()
        new.u = self.u if share_qu else self.u.copy()
        new.t = self.t
        a = self.last_impulse
        new.last_impulse = None if a is None else a.copy()
        a = self.last_active
        new.last_active = None if a is None else a.copy()
        new.last_bilateral = self.last_bilateral.copy()
        new.prox_memory = self.prox_memory.copy()
        a = self.closed
        if a is None:
            new.closed = new.slip = new.anchor = new.lam_compliant = None
        else:
            new.closed = a.copy()
            new.slip = self.slip.copy()
            new.anchor = self.anchor.copy()
            new.lam_compliant = self.lam_compliant.copy()
        pending = self.pending_wrenches
        new.pending_wrenches = [[link, f.copy(), m.copy(), remaining]
                                for link, f, m, remaining in pending] if pending else []
        a = self.surfaces
        new.surfaces = None if a is None else a.copy()
        a = self.drive_torque
        new.drive_torque = None if a is None else a.copy()
        return new

    def restore_memory(self, other: "SimState"):
        """The contact memory of `other` (a copy of this state) copied back into this
        state's arrays, in place (a step solved again from the same memory)."""
        for name in ("last_impulse", "last_active", "last_bilateral", "prox_memory", "closed",
                     "slip", "anchor", "lam_compliant", "drive_torque"):
            a = getattr(self, name)
            if a is not None:
                a[...] = getattr(other, name)


def finite_time(t, what: str = "t") -> float:
    """A state's time t [s] as a float; ValueError naming it (`what`) where it is not a
    finite real number (a NaN time would stay NaN at every later step)."""
    if isinstance(t, (bool, np.bool_)) or not isinstance(t, (int, float, np.integer,
                                                              np.floating)):
        raise ValueError(f"{what} must be a number of seconds, got {t!r:.60}")
    try:
        x = float(t)
    except OverflowError:            # an integer beyond the floats
        x = math.inf
    if not math.isfinite(x):
        raise ValueError(f"{what} must be finite, got {x!r}")
    return x
