"""The records and constants of Moreau's midpoint step (Gehring et al. 2014, Eqn. 6-8) that
the stepper and the kernels share, and the contact-problem kernels of ``csrc/step_kernels.c`` that a
test calls alone.

Names as the paper's symbols: M, h, W, G = W^T M^{-1} W, Λ, ξ, r, α. The settings reach the
kernels as one record, `StepSettings` (a plain tuple of its fields will do), declared in
:mod:`starleth_sim.physics.kernels.layouts` with the kernels' results. The step itself is one
kernel call (:mod:`starleth_sim.physics.tree_step`, through
:class:`starleth_sim.physics.stepper.MoreauStepper`); profiled (STEP_PROFILE), it adds the
time of each Fig. 7 phase to a `timings` array of five floats in the order `PHASES`.

The phases of the step, as ``csrc/step_kernels.c`` writes them: phase "M^-1" (the factor of M into
L; the active set I = {i | g_N,i(q^M) ≤ activation_gap}, with hysteresis also the contacts
loaded in the last step while g_N,i ≤ opening_gap; W^T = [W_U^T of the active contacts;
W_B^T], M^{-1}W and b = [ε W_U^T u^S + gap terms; b_B] with ε_i = diag(ε_N,i, ε_T,i, ε_T,i)
and the normal rows' gap terms g_N⁺/Δt + (β_N/Δt) min(g_N, 0); u_free = u^S + M^{-1} h Δt),
phase "G" (G = W^T M^{-1} W, or diag(G) in the velocity form, and the Cholesky factor L_B of
G_BB for the direct bilateral method; c = W^T u_free + b), phase "prox" (the prox iteration
with the warm start, the last step's Λ of the contacts that stay active and Λ_B, one retry
with α·fallback_alpha_factor; the post-step projection: with the predicted end gaps g_N^E =
g_N(q^M) + ½Δt W_N^T u^E, the pseudo-velocity Δu_p = M^{-1}(W_N P_N + W_B P_B) of P_N ≥ 0 ⊥
W_N^T Δu_p + (2/Δt)(max(g_N^E, 0) + β_N min(g_N^E, 0)) ≥ 0, W_B^T Δu_p = 0, frictionless,
so that q^E = q^M ⊕ ½Δt (u^E + Δu_p) loses the fraction β_N of every penetration).

The kernels a test calls alone, as an independent cross-check of the step's phases against
dense linear algebra and Pinocchio's solver (test_solvers; the step does not call them):

- ``prepare_hard_contacts(settings, (M, uS), (gap, Wt_all, WtB, bB, eps), (dof_parent,
  factor, L), (last_impulse, last_active), timings, frames=None, problem=None) ->
  ContactProblem``: phases
  "M^-1" and "G" of a contact problem, with the nonzero patterns of W^T, M^{-1}W and G (a
  `ContactProblem`: the kernels' own object, `ContactProblem.arrays()` copies its arrays).
- ``free_velocity(h, dt, uS, dof_parent, L, u_free)`` and ``constraint_velocity(Wt, u_free,
  bvec, wp_ptr, wp_idx, c)``: u_free and c = W^T u_free + b (Eqn. 15).
"""
from __future__ import annotations

from .kernels import (  # noqa: F401  # noqa: F401
                      PHASE_G,
                      PHASE_M_AND_H,
                      PHASE_M_INVERSE,
                      PHASE_PROX,
                      PHASE_REST,
                      ContactProblem,
                      constraint_velocity,
                      free_velocity,
                      prepare_hard_contacts,
)
from .kernels.layouts import STEP_SETTINGS

#: Fig. 7 phases, and their indices in StepperStats.timings
PHASES = ("M_and_h", "M_inverse", "G", "prox", "rest")


#: The settings of one step as the kernels read them (built once per stepper from the
#: PhysicsConfig, see `MoreauStepper._step_settings`), in the order
#: kernels.layouts.STEP_SETTINGS declares
StepSettings = STEP_SETTINGS.named_tuple(
    "The settings of one step as the kernels read them (a plain tuple of the same numbers "
    "will do).", __name__)


#: the post-step projection runs when a contact's predicted end gap is below
#: −PROJECTION_TOLERANCE [m]: 1 µm, 100x below what the eye or a controller notices, and
#: above the noise of the prox solver's tolerance at rest
PROJECTION_TOLERANCE = 1e-6
#: contacts up to this far above the ground at q^M are checked for penetration at the end of
#: the step [m] (a foot approaching at 4 m/s moves 5 mm in ½Δt = 1.25 ms)
PROJECTION_LOOKAHEAD = 5e-3
