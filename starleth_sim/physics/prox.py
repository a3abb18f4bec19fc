"""Proximal-point solvers for the discretised normal-cone inclusions (Gehring et al. 2014,
Eqn. 12-20), C kernels in ``csrc/prox.c``.

Problem layout: m = 3 nc + nb constraint rows. Rows 3i, 3i+1, 3i+2 are contact i's normal
and two tangential directions (Λ_N, Λ_T1, Λ_T2); the last nb rows are bilateral
constraints (one row per constrained direction).

Delassus form (Eqn. 12-16):
    ξ = G Λ + c,   G = W^T M^{-1} W,   c = W^T M^{-1} h Δt + (I + ε) W^T u^S
    Λ_N   ← max(Λ_N − r_N ξ_N, 0)                    (= −prox_{R0−}(−Λ_N + r_N ξ_N))
    Λ_T   ← prox_{disc(μ Λ_N)}(Λ_T − r_T ξ_T)          (= −prox_{C_T}(−Λ_T + r_T ξ_T))
    Λ_B   ← Λ_B − r_B ξ_B                             (prox onto R^d is the identity)
with r_N = α / G_NN, r_T = α / max(G_T1T1, G_T2T2), r_B = α / G_BB (row-wise).
Velocity form (Eqn. 17-19): the same fixed point iterated in u^k = u_free + M^{-1} W Λ^k,
ξ_i = W_i^T u^k + b_i with b_i = ε_i W_i^T u^S, never forming G.
JOR: all rows are projected from the same iterate, then Λ (and u) are updated.
SOR: contacts are processed one after the other, each using the values already updated.
Direct bilateral (Eqn. 20): after each sweep over the contacts, Λ_B solves γ_B^E = 0 for
the current Λ_U: Λ_B = −G_BB^{-1} (G_BU Λ_U + c_B).

Termination (paper): |Λ_(l)^{k+1} − Λ_(l)^k| ≤ |Λ_(l)^k| T_rel + T_abs for all rows l, or
optionally the kinetic-energy criterion |T^{k+1} − T^k| ≤ |T^k| T_rel + T_abs with
T = ½ u^T M u.

Sparsity: W^T rows touch only the bodies a contact or hinge acts on (few columns in the
extended and maximal coordinates), so the kernels take the nonzero patterns of the rows of
W^T (`wp`), of the columns of M^{-1}W (`mp`) and of the rows of G (`gp`), each as a CSR pair
(ptr, idx) made by :func:`row_pattern` / :func:`col_pattern`, bundled in a `Patterns`
record. Dense problems just have full patterns (:func:`dense_problem_patterns`).

Settings: the kernels read form, scheme, T_rel, T_abs, the iteration cap, the termination
criterion and the bilateral method from one typed record `s` with the fields of
`ProxSettings` (the stepper passes its `StepSettings`, which holds one: `prox`).

Adaptive α (``solver.alpha: auto``, the settings' α = ALPHA_AUTO < 0): the paper's α must
be tuned per configuration (Fig. 6; too large diverges). With α < 0 the kernels choose it
themselves, per step and per iteration:
  * spectral step: r_s = r / λ_max, the parameters r = |α| / diag(G) scaled by the largest
    eigenvalue of the scaled Delassus matrix R^{1/2} G R^{1/2} / |α| (a few power
    iterations; JOR: the whole G (G_UU with the direct bilateral method, the contact rows
    only), SOR: its per-contact 3x3 blocks and bilateral diagonal, the part that bounds SOR's
    step). α = 1/λ_max is half the linear stability limit 2/λ_max of JOR, and ω = 1 of SOR;
  * convergence history: every other sweep takes the Barzilai-Borwein step of the last
    increment d = Λ^{k+1} − Λ^k, r = r_s θ with θ = (dᵀ R_s^{-1} d) / (dᵀ G d) (the inverse
    Rayleigh quotient of d: a long step along the slow, low-eigenvalue modes that the
    spectral step leaves; with the direct method dᵀGd is the Schur complement's form, as
    Λ_B follows Λ_U), clamped to [1, AUTO_MAX_STEP]; the sweeps in between take the spectral
    step, which damps the high modes a long step excites. JOR gets Gd for free as
    ξ^{k+1} − ξ^k, which the next sweep computes anyway (so its long step is set there). SOR
    with bilateral prox rows takes the long steps on its contact rows only (its Gauss-Seidel
    sweep over the bilateral rows is not a gradient step: long steps there slowed HMSP 7x);
    its bilateral rows are over-relaxed instead, r_B = |α| ω / G_BB with
    ω = AUTO_SOR_BILATERAL_OMEGA;
  * divergence guard: when the increment grows to AUTO_GUARD times the smallest one of
    the solve, or a value becomes non-finite (then from the warm start again), the rest of
    the solve takes the spectral step only (monotone, convergent for linear problems).
|α| scales r_s: the stepper's divergence fallback retries a failed solve with α·factor.

Every kernel returns (iterations, status, residual) with status 0 = converged,
1 = iteration cap reached, 2 = non-finite values (the caller must not accept the result),
and residual = max_l |Λ_(l)^{k+1} − Λ_(l)^k| of the last iteration.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .kernels import (  # noqa: F401  (the constants are the kernels' own)
    ALPHA_AUTO,
    AUTO_GUARD,
    AUTO_MAX_STEP,
    AUTO_POWER_ITERATIONS,
    AUTO_SOR_BILATERAL_OMEGA,
    CRITERION_ENERGY,
    CRITERION_IMPULSE,
    DELASSUS_ENVELOPE_ROWS,
    FORM_DELASSUS,
    FORM_VELOCITY,
    SCHEME_JOR,
    SCHEME_SOR,
    STATUS_CONVERGED,
    STATUS_MAX_ITER,
    STATUS_NONFINITE,
    STATUS_STALLED,
    auto_spectral_scale,
    col_pattern,
    delassus,
    delassus_diagonal,
    prox_parameters,
    prox_solve,
    row_pattern,
)
from .kernels.layouts import PROX_SETTINGS

SCHEMES = {"jor": SCHEME_JOR, "sor": SCHEME_SOR}
FORMS = {"delassus": FORM_DELASSUS, "velocity": FORM_VELOCITY}
CRITERIA = {"impulse": CRITERION_IMPULSE, "energy": CRITERION_ENERGY}

# The kernels (csrc/prox.c):
#   prox_solve(s, pat, (Wt, MinvW, u_free, bvec, G, c), (nc, mu, r), lam, (LB, M), u)
#       -> (iterations, status, residual): one prox solve with the scheme and form of the
#       settings `s` (a StepSettings or ProxSettings). Problem: W^T (Wt, m x nv), M^{-1}W
#       (MinvW, nv x m), u_free = u^S + M^{-1} h Δt, b, G = W^T M^{-1} W and c = W^T u_free + b
#       (Delassus form only), nc contacts with friction coefficients μ (mu), the prox
#       parameters r, the Cholesky factor L_B of G_BB (direct bilateral method), M (energy
#       criterion). lam: Λ, warm start in, solution out; u: u^E out. `pat`: the Patterns.
#   prox_parameters(Gdiag, nc, alpha, r): r_N = α/G_NN, r_T = α/max(G_T1T1, G_T2T2) per
#       contact, r_B = α/G_ll per bilateral row (|α| for the adaptive α).
#   delassus(Wt, MinvW, G, wp_ptr, wp_idx, mp_ptr, mp_idx): G = W^T M^{-1} W, both triangles;
#       row by row, each entry's terms in the order of the entry-by-entry sum from +0.0 (with
#       more than DELASSUS_ENVELOPE_ROWS rows, each nonzero of a row of W^T adds only over
#       the envelope of its row of M^{-1}W: the other terms are ±0), so G is that sum bit
#       for bit.
#   delassus_diagonal(Wt, MinvW, d, wp_ptr, wp_idx): diag(G) without forming G.
#   row_pattern(A) / col_pattern(A) -> (ptr, idx): the nonzero pattern of A's rows / columns.
#   auto_spectral_scale(s, G, Wt, MinvW, pat, nc, r): λ_max of R^{1/2} G R^{1/2} that bounds
#       the step of the settings' scheme (adaptive α, above).


def alpha_setting(value) -> float:
    """The settings' α of a validated ``solver.alpha``: the number, or ALPHA_AUTO for
    ``auto``."""
    return ALPHA_AUTO if value == "auto" else float(value)


class Patterns(NamedTuple):
    """Nonzero patterns of a problem, each a CSR pair (ptr, idx): the rows of W^T (wp), the
    columns of M^{-1}W (mp) and the rows of G (gp; empty rows in the velocity form); and
    the envelope of L_B, the Cholesky factor of G_BB (lb_first: the first nonzero column
    of each row, linalg.cholesky_upper_input; empty without the direct bilateral method)."""

    wp_ptr: np.ndarray
    wp_idx: np.ndarray
    mp_ptr: np.ndarray
    mp_idx: np.ndarray
    gp_ptr: np.ndarray
    gp_idx: np.ndarray
    lb_first: np.ndarray


#: The settings the prox kernels read, in the order kernels.layouts.PROX_SETTINGS declares
#: (a StepSettings holds one, its field `prox`)
ProxSettings = PROX_SETTINGS.named_tuple(
    "The settings the prox kernels read (any sequence of these numbers in this order will "
    "do).", __name__)


def dense_problem_patterns(Wt, MinvW, G):
    """The `Patterns` of a problem given densely (tests, tools)."""
    wp = row_pattern(Wt)
    mp = col_pattern(MinvW)
    gp = row_pattern(G) if G.size else (np.zeros(Wt.shape[0] + 1, dtype=np.int64),
                                        np.zeros(0, dtype=np.int64))
    return Patterns(*wp, *mp, *gp, np.zeros(0, dtype=np.int64))
