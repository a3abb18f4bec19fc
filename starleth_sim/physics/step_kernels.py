"""Moreau's midpoint step phase by phase (Gehring et al. 2014, Eqn. 6-8), the C kernels of
``csrc/step.c`` that :class:`starleth_sim.physics.stepper.MoreauStepper` calls, and their
records.

Names as the paper's symbols: M, h, W, G = W^T M^{-1} W, Λ, ξ, r, α. The settings reach the
kernels as one record, `StepSettings` (a plain tuple of its fields will do); a hard-contact
problem prepared ahead is a `ContactProblem` (the kernels' own object: its arrays in memory
of its own, `ContactProblem.arrays()` copies them for inspection); the kernels' results are
records with named fields, declared in :mod:`starleth_sim.physics.kernel_layouts` with the
settings' fields. The one-kernel steps of the minimal and cut-forest coordinates are in
:mod:`starleth_sim.physics.tree_step`.

The kernels:

- ``prepare_hard_contacts(settings, M, uS, gap, Wt_all, WtB, bB, eps, dof_parent, factor, L,
  last_impulse, last_active, timings, problem=None) -> ContactProblem``: the
  torque-independent part of the hard-contact solve: Fig. 7 phase "M^-1" (the factor of M
  into L unless `factor` is False; the active set I = {i | g_N,i(q^M) ≤ activation_gap},
  with hysteresis also the contacts loaded in the last step while g_N,i ≤ opening_gap;
  W^T = [W_U^T of the active contacts; W_B^T], M^{-1}W and b = [ε W_U^T u^S + gap terms;
  b_B] with ε_i = diag(ε_N,i, ε_T,i, ε_T,i) and the normal rows' gap terms g_N⁺/Δt +
  (β_N/Δt) min(g_N, 0)) and phase "G" (G = W^T M^{-1} W, or diag(G) in the velocity form,
  and the Cholesky factor L_B of G_BB for the direct bilateral method), with the nonzero
  patterns of W^T, M^{-1}W and G. `problem`: a ContactProblem to fill again (its memory
  reused).
- ``complete_hard_contacts(settings, problem, h, uS, M, dof_parent, L, gap, Wt_all,
  last_impulse, last_active, last_bilateral, impulse, is_active, u_free, u, u_corr,
  timings) -> CompletionResult`` (named fields: iterations, status, residual, retried,
  projection_iterations, projection_status): the torque-dependent rest: u_free = u^S +
  M^{-1} h Δt (phase "M^-1"), c = W^T u_free + b (phase "G"), the prox iteration with the
  warm start (the last step's Λ of the contacts that stay active, and Λ_B) and one retry
  with α·fallback_alpha_factor (phase "prox"), and the post-step projection (phase
  "prox"): with the predicted end gaps g_N^E = g_N(q^M) + ½Δt W_N^T u^E of the active
  contacts and of those outside I that would end below the ground, the pseudo-velocity
  Δu_p = M^{-1}(W_N P_N + W_B P_B) of P_N ≥ 0 ⊥ W_N^T Δu_p + (2/Δt)(max(g_N^E, 0) + β_N
  min(g_N^E, 0)) ≥ 0, W_B^T Δu_p = 0, frictionless, so that q^E = q^M ⊕ ½Δt (u^E + Δu_p)
  loses the fraction β_N of every penetration (projection status −1: not needed). Writes
  Λ_U of every contact (nc x 3), the active flags, u^E, Δu_p into u_corr; unless the
  result is non-finite, Λ_B into last_bilateral and the warm-start memory (last_impulse,
  last_active).
- ``solve_hard_contacts(settings, M, uS, gap, Wt_all, WtB, bB, eps, dof_parent, factor, L, h,
  last_impulse, last_active, last_bilateral, impulse, is_active, u_free, u, u_corr, timings)
  -> HardContactsResult`` (ok, n_active (|I|), opened, then CompletionResult's fields): both
  in one call (the same arithmetic, so the same result bit for
  bit); with ok False (M or G_B not positive definite) nothing else was done.
- ``solve_compliant(law, M, h, uS, dt, gap, position, Wt_all, closed, slip, anchor, t1, t2,
  lam, dof_parent, factor, L, u_free, timings) -> bool``: Alg. 1 without bilateral
  constraints: the factor of M into L (unless factor is False), the compliant forces at
  (q^M, u^S) (contact.compliant_contact_forces) added to h, and u_free = u^S + M^{-1} h Δt,
  which is u^E. False if M is not positive definite.
- ``end_of_step(qM, uE, u_corr, projected, half_dt, jtype, idx_q, idx_v, qE) -> bool``:
  Eqn. (8), q^E = q^M ⊕ ½Δt F(q^M) (u^E + Δu_p) (Δu_p = u_corr when the projection ran);
  False if q^E or u^E is not finite.
- ``free_velocity(h, dt, uS, dof_parent, L, u_free)`` and ``constraint_velocity(Wt, u_free,
  bvec, wp_ptr, wp_idx, c)``: u_free and c = W^T u_free + b (Eqn. 15).

Profiling (Fig. 7 phases, `PHASES`): the kernels add the time of each phase to a `timings`
array (five floats); None (or an empty array) means not profiling. The stepper's own Python
between the kernels times itself with `clock` and `lap`.
"""
from __future__ import annotations

import time

from .kernel_layouts import STEP_SETTINGS
from .kernels import (ContactProblem, complete_hard_contacts,  # noqa: F401
                      constraint_velocity, end_of_step, free_velocity, prepare_hard_contacts,
                      solve_compliant, solve_hard_contacts)
from .kernels import (PHASE_G, PHASE_M_AND_H, PHASE_M_INVERSE, PHASE_PROX,  # noqa: F401
                      PHASE_REST)

#: Fig. 7 phases, and their indices in StepperStats.timings
PHASES = ("M_and_h", "M_inverse", "G", "prox", "rest")


#: The settings of one step as the kernels read them (built once per stepper from the
#: PhysicsConfig, see `MoreauStepper.__init__`), in the order kernel_layouts.STEP_SETTINGS
#: declares
StepSettings = STEP_SETTINGS.named_tuple(
    "The settings of one step as the kernels read them (a plain tuple of the same numbers "
    "will do).", __name__)


def _timed(timings) -> bool:
    return timings is not None and len(timings) != 0


def clock(timings):
    """The profiling clock: time.perf_counter() when profiling (timings is the array the
    phases' times go to), else 0 (timings is None or empty)."""
    return time.perf_counter() if _timed(timings) else 0.0


def lap(timings, phase, since):
    """Profiling: add the time since `since` to timings[phase] and return the clock; a
    no-op returning 0 when timings is None or empty (not profiling)."""
    if not _timed(timings):
        return 0.0
    t = time.perf_counter()
    timings[phase] += t - since
    return t


#: the post-step projection runs when a contact's predicted end gap is below
#: −PROJECTION_TOLERANCE [m]: 1 µm, 100x below what the eye or a controller notices, and
#: above the noise of the prox solver's tolerance at rest (at 10 nm it ran on 45 % of the
#: steps of a robot standing still; at 1 µm on none, and on the touchdowns of a trot)
PROJECTION_TOLERANCE = 1e-6
#: contacts up to this far above the ground at q^M are checked for penetration at the end of
#: the step [m] (a foot approaching at 4 m/s moves 5 mm in ½Δt = 1.25 ms)
PROJECTION_LOOKAHEAD = 5e-3
