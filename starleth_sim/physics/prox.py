"""Proximal-point solvers for the discretised normal-cone inclusions (Gehring et al. 2014,
Eqn. 12-20), compiled with numba.

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
`ProxSettings` (the stepper passes its `StepSettings`, which has them all).

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
    ξ^{k+1} − ξ^k, which the next sweep computes anyway (so its long step is set there). SOR with bilateral prox rows
    takes the long steps on its contact rows only (its Gauss-Seidel sweep over the
    bilateral rows is not a gradient step: long steps there slowed HMSP 7x); its bilateral
    rows are over-relaxed instead, r_B = |α| ω / G_BB with ω = AUTO_SOR_BILATERAL_OMEGA;
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
import numba as nb

from .kernel_cache import KERNEL
from .array_views import arena_floats, arena_ints, borrowed, keep_alive
from .linalg import cholesky_solve_envelope, cholesky_solve_vec, envelope_columns

SCHEME_JOR = 0
SCHEME_SOR = 1
FORM_DELASSUS = 0
FORM_VELOCITY = 1
CRITERION_IMPULSE = 0
CRITERION_ENERGY = 1
STATUS_CONVERGED = 0
STATUS_MAX_ITER = 1
STATUS_NONFINITE = 2

SCHEMES = {"jor": SCHEME_JOR, "sor": SCHEME_SOR}
FORMS = {"delassus": FORM_DELASSUS, "velocity": FORM_VELOCITY}
CRITERIA = {"impulse": CRITERION_IMPULSE, "energy": CRITERION_ENERGY}

#: the settings' α of ``solver.alpha: auto`` (any α < 0 is adaptive, |α| scales the step)
ALPHA_AUTO = -1.0
#: adaptive α: largest Barzilai-Borwein step, as a multiple of the spectral step 1/λ_max
AUTO_MAX_STEP = 1.0e3
#: adaptive α: an increment this many times the smallest of the solve ends the long steps
AUTO_GUARD = 1.0e3
#: adaptive α: power iterations of the λ_max estimate
AUTO_POWER_ITERATIONS = 16
#: adaptive α, SOR with bilateral prox rows: their relaxation ω, r_B = |α| ω / G_BB (each row
#: is a scalar Gauss-Seidel update, convergent for ω < 2)
AUTO_SOR_BILATERAL_OMEGA = 1.5


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


class ProxSettings(NamedTuple):
    """The settings the prox kernels read (any record with these fields will do)."""

    form: int                  # FORM_DELASSUS (Eqn. 12-16) | FORM_VELOCITY (Eqn. 17-19)
    scheme: int                # SCHEME_JOR | SCHEME_SOR
    tol_rel: float             # T_rel
    tol_abs: float             # T_abs [N s]
    max_iterations: int
    criterion: int             # CRITERION_IMPULSE | CRITERION_ENERGY (½ uᵀMu)
    bilateral_direct: bool     # Λ_B by Eqn. 20 after each sweep (else prox rows, Eqn. 19)
    alpha: float = 0.5         # α > 0: r as given; < 0 (ALPHA_AUTO): adaptive α, see above


@nb.njit(**KERNEL, inline="always")
def prox_normal(x):
    """Λ_N = −prox_{R0−}(−x): projection of x onto [0, ∞)."""
    return x if x > 0.0 else 0.0


@nb.njit(**KERNEL, inline="always")
def prox_disc(x1, x2, radius):
    """Projection of (x1, x2) onto the disc of the given radius centred at 0."""
    n2 = x1 * x1 + x2 * x2
    if n2 <= radius * radius:
        return x1, x2
    if radius <= 0.0:
        return 0.0, 0.0
    s = radius / np.sqrt(n2)
    return x1 * s, x2 * s


@nb.njit(**KERNEL, inline="always")
def row_pattern(A, arena=None):
    """Nonzero pattern of the rows of A as CSR (ptr, idx), in one pass over A (its buffer
    from the step's arena, array_views.arena_ints)."""
    m, n = A.shape
    buf = arena_ints(arena, m + 1 + m * n)   # (one buffer for ptr and idx)
    ptr = buf[:m + 1]
    idx = buf[m + 1:]
    cnt = 0
    for a in range(m):
        ptr[a] = cnt
        for k in range(n):
            if A[a, k] != 0.0:
                idx[cnt] = k
                cnt += 1
    ptr[m] = cnt
    return ptr, idx[:cnt]


@nb.njit(**KERNEL, inline="always")
def col_pattern(A, arena=None):
    """Nonzero pattern of the columns of A as CSR (ptr, idx)."""
    return row_pattern(A.T, arena)


#: with more rows than this, delassus sums each row of G only over the columns that each
#: nonzero of its row of W^T can reach (_row_envelopes)
DELASSUS_ENVELOPE_ROWS = 24


@nb.njit(**KERNEL, inline="always")
def _row_envelopes(mp_ptr, mp_idx, nv, arena=None):
    """(first, end): for each row k of M^{-1}W, its first nonzero column and one past its
    last (first ≥ end for a row of zeros), from the pattern of its columns (mp_ptr,
    mp_idx); one buffer from the step's arena."""
    buf = arena_ints(arena, 2 * nv)
    first = buf[:nv]
    end = buf[nv:]
    n = mp_ptr.shape[0] - 1
    for k in range(nv):
        first[k] = n
        end[k] = 0
    for b in range(n):
        for p in range(mp_ptr[b], mp_ptr[b + 1]):
            k = mp_idx[p]
            if b < first[k]:
                first[k] = b
            end[k] = b + 1      # (the columns come in ascending order)
    return first, end


@nb.njit(**KERNEL, inline="always")
def delassus(Wt, MinvW, G, wp_ptr, wp_idx, mp_ptr, mp_idx, arena=None):
    """G = W^T M^{-1} W (symmetric; both triangles written). Wt: m x nv, MinvW: nv x m,
    (wp_ptr, wp_idx): nonzero pattern of the rows of Wt, (mp_ptr, mp_idx): of the columns
    of MinvW. Row by row (_delassus_rows); with more than DELASSUS_ENVELOPE_ROWS rows each
    row of W^T adds its nonzero k only over row k of M^{-1}W's envelope (_row_envelopes),
    which is short when M^{-1} is block-diagonal over many trees (the maximal coordinates:
    a bilateral row touches two of 13 bodies): the entries outside it would only add ±0
    products to sums from +0.0, so G is the same bit for bit (HMJP standing, 72 rows: 6.3
    µs against 12.2 for the entry-by-entry sums of before)."""
    m, nv = Wt.shape
    if m <= DELASSUS_ENVELOPE_ROWS:
        _delassus_rows(Wt, MinvW, G, wp_ptr, wp_idx)
        return
    first, end = _row_envelopes(mp_ptr, mp_idx, nv, arena)
    Gf = G.ravel()
    for t in range(m * m):
        Gf[t] = 0.0
    for a in range(m):
        row = G[a]
        lo = m       # (the stretch of row a that the envelopes reach, lo to hi)
        hi = a + 1
        for p in range(wp_ptr[a], wp_ptr[a + 1]):
            k = wp_idx[p]
            b0 = max(a, first[k])
            b1 = end[k]
            if b1 <= b0:
                continue
            lo = min(lo, b0)
            hi = max(hi, b1)
            w = Wt[a, k]
            part = row[b0:b1]
            mk = MinvW[k, b0:b1]
            for t in range(b1 - b0):
                part[t] += w * mk[t]
        for b in range(max(a + 1, lo), hi):
            G[b, a] = row[b]


@nb.njit(**KERNEL, inline="always")
def _delassus_rows(Wt, MinvW, G, wp_ptr, wp_idx):
    """delassus of a few rows, row by row: the upper part of row a of G accumulates
    Wt[a, k] · M^{-1}W[k, a:] over the nonzeros k of row a of W^T, along contiguous rows
    (vectorized). Each entry gets the same terms in the same order, from +0.0, as the sum
    of the entry-by-entry loop: the same G bit for bit."""
    m = Wt.shape[0]
    for a in range(m):
        row = G[a]
        for b in range(a, m):
            row[b] = 0.0
        for p in range(wp_ptr[a], wp_ptr[a + 1]):
            k = wp_idx[p]
            w = Wt[a, k]
            mk = MinvW[k]
            for b in range(a, m):
                row[b] += w * mk[b]
        for b in range(a + 1, m):
            G[b, a] = row[b]


@nb.njit(**KERNEL)
def delassus_diagonal(Wt, MinvW, d, wp_ptr, wp_idx):
    """diag(G) without forming G (velocity form)."""
    m = Wt.shape[0]
    for a in range(m):
        s = 0.0
        for p in range(wp_ptr[a], wp_ptr[a + 1]):
            k = wp_idx[p]
            s += Wt[a, k] * MinvW[k, a]
        d[a] = s


@nb.njit(**KERNEL, inline="always")
def prox_parameters(Gdiag, nc, alpha, r):
    """r_N = α/G_NN, r_T = α/max(G_T1T1, G_T2T2) per contact, r_B = α/G_ll per bilateral row.
    α < 0 (adaptive α, ALPHA_AUTO) gives the same with |α|; the kernels then rescale r."""
    m = Gdiag.shape[0]
    alpha = abs(alpha)
    for i in range(nc):
        b = 3 * i
        r[b] = alpha / Gdiag[b]
        rt = alpha / max(Gdiag[b + 1], Gdiag[b + 2])
        r[b + 1] = rt
        r[b + 2] = rt
    for l in range(3 * nc, m):
        r[l] = alpha / Gdiag[l]


@nb.njit(**KERNEL, inline="always")
def _project_contact(lam, b, xi0, xi1, xi2, r, mu_i, out):
    """Prox update of one contact's three rows (normal first, the disc uses the new Λ_N)."""
    ln = prox_normal(lam[b] - r[b] * xi0)
    t1, t2 = prox_disc(lam[b + 1] - r[b + 1] * xi1, lam[b + 2] - r[b + 2] * xi2, mu_i * ln)
    out[b] = ln
    out[b + 1] = t1
    out[b + 2] = t2


@nb.njit(**KERNEL)
def _kinetic_energy(M, u):
    nv = u.shape[0]
    s = 0.0
    for i in range(nv):
        row = 0.0
        for j in range(nv):
            row += M[i, j] * u[j]
        s += u[i] * row
    return 0.5 * s


@nb.njit(**KERNEL)
def _add_impulse_columns(MinvW, lam, u, mp_ptr, mp_idx, ncols):
    """u += M^{-1} W[:, :ncols] Λ[:ncols], with the column pattern of M^{-1} W."""
    for l in range(ncols):
        x = lam[l]
        if x != 0.0:
            for p in range(mp_ptr[l], mp_ptr[l + 1]):
                k = mp_idx[p]
                u[k] += MinvW[k, l] * x


@nb.njit(**KERNEL)
def _velocity_from_impulses(u_free, MinvW, lam, u, mp_ptr, mp_idx):
    """u = u_free + M^{-1} W Λ (Eqn. 17)."""
    u[:] = u_free
    _add_impulse_columns(MinvW, lam, u, mp_ptr, mp_idx, MinvW.shape[1])


@nb.njit(**KERNEL)
def _bilateral_direct_delassus(G, c, nc, LB, lam, gp_ptr, gp_idx, lb_first, direct):
    """Λ_B = −G_BB^{-1} (G_BU Λ_U + c_B) for the current Λ_U (Eqn. 20, Delassus form), with
    delassus_prox's `direct` work: L_B's envelope by columns (col_ptr, col_idx) and the
    right-hand side's buffer."""
    col_ptr, col_idx, rhs = direct
    m = c.shape[0]
    o = 3 * nc
    nb_ = m - o
    for a in range(nb_):
        s = c[o + a]
        for p in range(gp_ptr[o + a], gp_ptr[o + a + 1]):
            l = gp_idx[p]
            if l >= o:      # (G_BU: the row's pattern is ascending, the contact rows first)
                break
            s += G[o + a, l] * lam[l]
        rhs[a] = -s
    cholesky_solve_envelope(LB, lb_first, col_ptr, col_idx, rhs)
    for a in range(nb_):
        lam[o + a] = rhs[a]


@nb.njit(**KERNEL)
def _bilateral_direct_velocity(Wt, MinvW, u_free, nc, LB, lam, wp_ptr, wp_idx, mp_ptr, mp_idx,
                               lb_first):
    """Λ_B = −G_BB^{-1} W_B^T (u^S + M^{-1}(h Δt + W_U Λ_U)) (Eqn. 20, velocity form)."""
    m = Wt.shape[0]
    o = 3 * nc
    nb_ = m - o
    uu = u_free.copy()
    _add_impulse_columns(MinvW, lam, uu, mp_ptr, mp_idx, o)      # W_U Λ_U only
    rhs = np.empty(nb_)
    for a in range(nb_):
        s = 0.0
        for p in range(wp_ptr[o + a], wp_ptr[o + a + 1]):
            k = wp_idx[p]
            s += Wt[o + a, k] * uu[k]
        rhs[a] = -s
    cholesky_solve_vec(LB, lb_first, rhs)
    for a in range(nb_):
        lam[o + a] = rhs[a]


@nb.njit(**KERNEL, inline="always")
def _check(lam_old, lam, tol_rel, tol_abs):
    """(converged by the impulse criterion, max |ΔΛ|, all finite)."""
    ok = True
    res = 0.0
    finite = True
    for l in range(lam.shape[0]):
        ok, res, finite = _row_check(lam_old[l], lam[l], ok, res, finite, tol_rel, tol_abs)
    return ok, res, finite


@nb.njit(**KERNEL, inline="always")
def _row_check(old, new, ok, res, finite, tol_rel, tol_abs):
    """_check's test of one row, (ok, max |ΔΛ|, finite) carried on: |ΔΛ| ≤ |Λ_old| tol_rel
    + tol_abs."""
    d = abs(new - old)
    if not np.isfinite(new):
        finite = False
    if d > res:
        res = d
    if d > abs(old) * tol_rel + tol_abs:
        ok = False
    return ok, res, finite


# -- adaptive α (solver.alpha: auto) ------------------------------------------------------------
@nb.njit(**KERNEL)
def _delassus_entry(form, G, Wt, MinvW, pat, a, l):
    """G_al: from G (Delassus form) or W_a^T (M^{-1}W)_l (velocity form)."""
    if form == FORM_DELASSUS:
        return G[a, l]
    s = 0.0
    for p in range(pat.wp_ptr[a], pat.wp_ptr[a + 1]):
        k = pat.wp_idx[p]
        s += Wt[a, k] * MinvW[k, l]
    return s


@nb.njit(**KERNEL)
def _scaled_apply(form, G, Wt, MinvW, pat, sq, x, y, n, tmp):
    """y = S x with S = R^{1/2} G R^{1/2} restricted to the first n rows (sq = r^{1/2})."""
    if form == FORM_DELASSUS:
        for a in range(n):
            acc = 0.0
            for p in range(pat.gp_ptr[a], pat.gp_ptr[a + 1]):
                l = pat.gp_idx[p]
                if l < n:
                    acc += G[a, l] * sq[l] * x[l]
            y[a] = sq[a] * acc
        return
    tmp[:] = 0.0
    for l in range(n):
        v = sq[l] * x[l]
        if v != 0.0:
            for p in range(pat.mp_ptr[l], pat.mp_ptr[l + 1]):
                k = pat.mp_idx[p]
                tmp[k] += MinvW[k, l] * v
    for a in range(n):
        acc = 0.0
        for p in range(pat.wp_ptr[a], pat.wp_ptr[a + 1]):
            k = pat.wp_idx[p]
            acc += Wt[a, k] * tmp[k]
        y[a] = sq[a] * acc


@nb.njit(**KERNEL)
def _power_lambda_max(S3, n_power):
    """λ_max of a symmetric positive semi-definite 3x3 matrix S3 by power iteration."""
    x0, x1, x2 = 1.0, 0.9, 0.8
    lam = 0.0
    for _ in range(n_power):
        y0 = S3[0, 0] * x0 + S3[0, 1] * x1 + S3[0, 2] * x2
        y1 = S3[1, 0] * x0 + S3[1, 1] * x1 + S3[1, 2] * x2
        y2 = S3[2, 0] * x0 + S3[2, 1] * x1 + S3[2, 2] * x2
        nx = x0 * x0 + x1 * x1 + x2 * x2
        lam = (x0 * y0 + x1 * y1 + x2 * y2) / nx
        ny = np.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
        if ny == 0.0:
            return lam
        x0, x1, x2 = y0 / ny, y1 / ny, y2 / ny
    return lam


@nb.njit(**KERNEL)
def auto_spectral_scale(s, G, Wt, MinvW, pat, nc, r):
    """λ_max of the scaled Delassus matrix S = R^{1/2} G R^{1/2} (r = |α|/diag(G)) that bounds
    the step of the settings' scheme: JOR, S itself (its contact rows S_UU with the direct
    bilateral method, where Λ_B follows Λ_U); SOR, the largest eigenvalue of its per-contact
    3x3 blocks and bilateral diagonal entries. Returns 0 for an empty problem."""
    m = r.shape[0]
    o = 3 * nc
    n = o if s.bilateral_direct else m
    if n == 0:
        return 0.0
    sq = np.sqrt(r)
    if s.scheme == SCHEME_SOR:
        best = 0.0
        S3 = np.empty((3, 3))
        for i in range(nc):
            b = 3 * i
            for a in range(3):
                for l in range(3):
                    S3[a, l] = sq[b + a] * sq[b + l] * _delassus_entry(s.form, G, Wt, MinvW,
                                                                       pat, b + a, b + l)
            best = max(best, _power_lambda_max(S3, 3 * AUTO_POWER_ITERATIONS))
        for l in range(o, n):
            best = max(best, r[l] * _delassus_entry(s.form, G, Wt, MinvW, pat, l, l))
        return best
    x = np.empty(n)
    for a in range(n):
        x[a] = 1.0 + 0.1 * ((a * 7) % 5)      # generic start: not orthogonal to the top mode
    y = np.empty(n)
    tmp = np.empty(MinvW.shape[0])
    lam = 0.0
    for _ in range(AUTO_POWER_ITERATIONS):
        _scaled_apply(s.form, G, Wt, MinvW, pat, sq, x, y, n, tmp)
        nx = 0.0
        xy = 0.0
        ny = 0.0
        for a in range(n):
            nx += x[a] * x[a]
            xy += x[a] * y[a]
            ny += y[a] * y[a]
        lam = xy / nx
        if ny == 0.0:
            break
        ny = np.sqrt(ny)
        for a in range(n):
            x[a] = y[a] / ny
    return lam


@nb.njit(**KERNEL)
def auto_spectral_parameters(s, G, Wt, MinvW, pat, nc, r, rs):
    """The spectral step of the adaptive α: rs = r / λ_max(R^{1/2} G R^{1/2} / |α|), i.e.
    r_l = |α| / (λ_max G_ll) with λ_max of the diagonally scaled G (see
    `auto_spectral_scale`), |α| = r_0 G_00. Returns the factor rs / r (1: no estimate)."""
    m = r.shape[0]
    rs[:] = r
    if m == 0:
        return 1.0
    lam = auto_spectral_scale(s, G, Wt, MinvW, pat, nc, r)
    a_abs = r[0] * _delassus_entry(s.form, G, Wt, MinvW, pat, 0, 0)
    if not (lam > 0.0 and np.isfinite(lam) and a_abs > 0.0):
        return 1.0
    f = a_abs / lam
    for l in range(m):
        rs[l] = r[l] * f
    return f


@nb.njit(**KERNEL)
def auto_step_factor(s, G, Wt, MinvW, pat, nc, old, new, rs, tmp1, tmp2, n):
    """θ of the Barzilai-Borwein step of the increment d = new − old: (dᵀ R_s^{-1} d) over
    the first n rows (those the long step applies to: the contact rows with the direct
    bilateral method, where dᵀGd over all rows is the Schur complement's form) / (dᵀ G d),
    clamped to [1, AUTO_MAX_STEP]; 1 when d is 0 or dᵀGd is not positive."""
    m = old.shape[0]
    p_ = 0.0
    for l in range(n):
        d = new[l] - old[l]
        p_ += d * d / rs[l]
    if p_ == 0.0:
        return 1.0
    q = 0.0
    if s.form == FORM_DELASSUS:
        for a in range(m):
            da = new[a] - old[a]
            if da != 0.0:
                acc = 0.0
                for p in range(pat.gp_ptr[a], pat.gp_ptr[a + 1]):
                    l = pat.gp_idx[p]
                    acc += G[a, l] * (new[l] - old[l])
                q += da * acc
    else:
        tmp1[:] = 0.0      # W d
        tmp2[:] = 0.0      # M^{-1} W d
        for l in range(m):
            d = new[l] - old[l]
            if d != 0.0:
                for p in range(pat.wp_ptr[l], pat.wp_ptr[l + 1]):
                    k = pat.wp_idx[p]
                    tmp1[k] += Wt[l, k] * d
                for p in range(pat.mp_ptr[l], pat.mp_ptr[l + 1]):
                    k = pat.mp_idx[p]
                    tmp2[k] += MinvW[k, l] * d
        for k in range(tmp1.shape[0]):
            q += tmp1[k] * tmp2[k]
    return _clamp_step(p_, q)


@nb.njit(**KERNEL)
def _clamp_step(p_, q):
    """θ = p/q clamped to [1, AUTO_MAX_STEP]; 1 when p is 0 or q is not positive."""
    if p_ == 0.0 or not q > 0.0:
        return 1.0
    theta = p_ / q
    if not np.isfinite(theta):
        return 1.0
    return min(max(theta, 1.0), AUTO_MAX_STEP)


@nb.njit(**KERNEL)
def _auto_guard(res, hist):
    """Tracks the smallest increment of the solve; an increment AUTO_GUARD times larger
    ends the long steps (hist[1] = 1). Returns whether long steps may follow."""
    if hist[1] != 1.0:
        if res < hist[0]:
            hist[0] = res
        elif res > AUTO_GUARD * hist[0]:
            hist[1] = 1.0
    return hist[1] != 1.0


@nb.njit(**KERNEL, inline="always")
def _auto_restart(hist, lam, lam0, rk, rs):
    """Adaptive α after a non-finite sweep: once per step (hist[1] marks it), Λ back to the
    warm start and the steps r back to the spectral ones."""
    hist[1] = 1.0
    lam[:] = lam0
    rk[:] = rs


@nb.njit(**KERNEL)
def _auto_jor_save(k, old, new, xi, res, rs, rk, hist, dsave, xsave):
    """JOR's adaptive α after sweep k: the spectral step rs for the next sweep; after even
    sweeps also d = new − old and ξ^k saved, for the long step that the next sweep takes once
    it has ξ^{k+1} (Gd = ξ^{k+1} − ξ^k: no extra product with G). Returns whether it will."""
    rk[:] = rs
    if not _auto_guard(res, hist) or k % 2 == 1:
        return False
    for l in range(old.shape[0]):
        dsave[l] = new[l] - old[l]
        xsave[l] = xi[l]
    return True


@nb.njit(**KERNEL)
def _auto_jor_long_step(s, nc, xi, rs, rk, dsave, xsave):
    """The long step of JOR from the saved increment d and Gd = ξ − ξ_saved (see
    auto_step_factor): rk = rs θ on the contact rows (and the bilateral prox rows)."""
    m = xi.shape[0]
    n = 3 * nc if s.bilateral_direct else m
    p_ = 0.0
    for l in range(n):
        p_ += dsave[l] * dsave[l] / rs[l]
    q = 0.0
    for l in range(m):
        q += dsave[l] * (xi[l] - xsave[l])
    theta = _clamp_step(p_, q)
    for l in range(n):
        rk[l] = rs[l] * theta


@nb.njit(**KERNEL)
def _auto_next(s, G, Wt, MinvW, pat, nc, k, old, new, res, rs, rk, hist, tmp1, tmp2):
    """The parameters rk of the sweep after sweep k (increment new − old, max |ΔΛ| = res) of
    the adaptive α: the Barzilai-Borwein step after even sweeps, the spectral step rs after
    odd ones, and for good once the guard tripped. hist: [smallest increment, mode (0: long
    steps, 1: spectral steps only, 2: long steps on the contact rows only), rs / r]."""
    rk[:] = rs
    if not _auto_guard(res, hist) or k % 2 == 1:
        return
    # long steps on the contact rows (and the bilateral prox rows of JOR)
    n = 3 * nc if s.bilateral_direct or hist[1] == 2.0 else rk.shape[0]
    theta = auto_step_factor(s, G, Wt, MinvW, pat, nc, old, new, rs, tmp1, tmp2, n)
    for l in range(n):
        rk[l] = rs[l] * theta


@nb.njit(**KERNEL, inline="always")
def _auto_setup(s, G, Wt, MinvW, pat, nc, r, lam):
    """Work arrays of a kernel: (rk, rs, Λ^0, hist, tmp1, tmp2, dsave, xsave) with rk the parameters of the
    first sweep: r itself (no copies with a fixed α), or with the adaptive α (s.alpha < 0)
    its spectral step rs."""
    if s.alpha >= 0.0:     # (empty views for the arrays that only the adaptive α reads)
        none = r[:0]
        return r, r, none, none, none, none, none, none
    hist = np.array([np.inf, 0.0, 1.0])
    rs = r.copy()
    hist[2] = auto_spectral_parameters(s, G, Wt, MinvW, pat, nc, r, rs)
    m = r.shape[0]
    if s.scheme == SCHEME_SOR and not s.bilateral_direct and m > 3 * nc:
        hist[1] = 2.0      # SOR's sweep over bilateral prox rows: long steps on the
        for l in range(3 * nc, m):     # contact rows only, over-relaxed bilateral rows
            rs[l] *= AUTO_SOR_BILATERAL_OMEGA / hist[2]    # r_B = |α| ω / G_BB
    nv = MinvW.shape[0]
    return rs.copy(), rs, lam.copy(), hist, np.empty(nv), np.empty(nv), np.empty(m), np.empty(m)


@nb.njit(**KERNEL, inline="always")
def delassus_prox(jor, s, pat, G, c, nc, mu, r, lam, LB, M, u_free, MinvW, u, arena=None):
    """The prox on ξ = GΛ + c (Delassus form), JOR (jor True) or SOR: _jor_prox_delassus or
    _sor_prox_delassus on borrowed arrays (array_views.borrowed: no reference counting in
    the iteration) with their work buffer, the owners held to the end. lam: warm start in,
    solution out; u: end velocity out; the work buffer from `arena` (a one-kernel step's,
    array_views.arena_floats). Returns (iterations, status, residual)."""
    m = c.shape[0]
    nd = m - 3 * nc if s.bilateral_direct else 0
    nw = 2 * m if jor else m
    # (JOR: ξ and the new Λ; SOR: Λ of the last sweep; then Λ_B's rhs; from the step's arena)
    owner = arena_floats(arena, nw + nd)
    work = borrowed(owner)
    columns = _envelope_columns(pat.lb_first, nd)
    direct = (borrowed(columns[0]), borrowed(columns[1]), work[nw:])
    if jor:
        result = _jor_prox_delassus(s, pat, G, borrowed(c), nc, borrowed(mu), borrowed(r),
                                    borrowed(lam), LB, M, u_free, MinvW, borrowed(u),
                                    work[:nw], direct)
    else:
        result = _sor_prox_delassus(s, pat, G, borrowed(c), nc, borrowed(mu), borrowed(r),
                                    borrowed(lam), LB, M, u_free, MinvW, borrowed(u),
                                    work[:nw], direct)
    keep_alive((c, mu, r, lam, u, owner, columns))
    return result


@nb.njit(**KERNEL, inline="always")
def _envelope_columns(lb_first, nd):
    """The columns of L_B's envelope (linalg.envelope_columns) for the direct bilateral
    method's backward solves (nd > 0 bilateral rows), else empty views."""
    if nd > 0:
        return envelope_columns(lb_first)
    return lb_first[:0], lb_first[:0]


@nb.njit(**KERNEL, inline="always")
def _delassus_apply(G, c, lam, xi, gp_ptr, gp_idx, n):
    """ξ_a = c_a + Σ_l G_al Λ_l for the first n rows (a < n), column by column of the
    symmetric G (column l is row l): each ξ_a gets the terms of its nonzeros in the order of
    ascending l, as the row-by-row sum over its pattern does, plus +0.0·Λ_l for the zeros
    inside column l's envelope (from its first to its last nonzero). Those leave a sum as it
    is (x + ±0 = x but for x = -0.0; G's zeros are +0.0 and Λ is finite in a sweep that goes
    on), so ξ is the row-by-row sum's bit for bit; the contiguous stretches vectorize where the
    row-by-row sum is a chain of dependent additions (JOR sweep of HMJP, 72 rows, 1,156
    nonzeros: 1.23 -> 0.68 µs)."""
    for a in range(n):
        xi[a] = c[a]
    for l in range(lam.shape[0]):
        first, last = gp_ptr[l], gp_ptr[l + 1]
        if first == last:
            continue
        a0 = gp_idx[first]
        a1 = min(gp_idx[last - 1] + 1, n)
        x = lam[l]
        xs = xi[a0:a1]
        gs = G[l, a0:a1]
        for t in range(a1 - a0):
            xs[t] += gs[t] * x


@nb.njit(**KERNEL, inline="always")
def _jor_project(lam, xi, r, mu, nc, bilateral_direct, new):
    """A JOR update of Λ into `new`: each contact's three rows by _project_contact; the
    bilateral rows by the prox (Eqn. 19), Λ_B − r_B ξ_B, or, for the direct method (Eqn. 20,
    solved by the caller), Λ_B as it is."""
    for i in range(nc):
        b = 3 * i
        _project_contact(lam, b, xi[b], xi[b + 1], xi[b + 2], r, mu[i], new)
    for l in range(3 * nc, lam.shape[0]):
        new[l] = lam[l] if bilateral_direct else lam[l] - r[l] * xi[l]


@nb.njit(**KERNEL, inline="always")
def _jor_update_in_place(lam, xi, r, mu, nc, tol_rel, tol_abs):
    """One JOR update with a fixed α and the bilateral rows by the prox (Eqn. 19), in place:
    Λ ← prox(Λ − r ξ) contact by contact (_project_contact reads a contact's three rows
    before it writes them, and a row's update reads only its own Λ once ξ is formed), with
    _check's test of each row on the way. The same values and the same (converged, max |ΔΛ|,
    all finite) as _project_contact into a second buffer, _check and a copy back, in one pass
    over Λ instead of three."""
    ok = True
    res = 0.0
    finite = True
    for i in range(nc):
        b = 3 * i
        old0, old1, old2 = lam[b], lam[b + 1], lam[b + 2]
        _project_contact(lam, b, xi[b], xi[b + 1], xi[b + 2], r, mu[i], lam)
        ok, res, finite = _row_check(old0, lam[b], ok, res, finite, tol_rel, tol_abs)
        ok, res, finite = _row_check(old1, lam[b + 1], ok, res, finite, tol_rel, tol_abs)
        ok, res, finite = _row_check(old2, lam[b + 2], ok, res, finite, tol_rel, tol_abs)
    for l in range(3 * nc, lam.shape[0]):
        v = lam[l] - r[l] * xi[l]
        ok, res, finite = _row_check(lam[l], v, ok, res, finite, tol_rel, tol_abs)
        lam[l] = v
    return ok, res, finite


@nb.njit(**KERNEL, inline="always")
def _jor_prox_delassus(s, pat, G, c, nc, mu, r, lam, LB, M, u_free, MinvW, u, buf, direct):
    """JOR prox on ξ = GΛ + c with its work buffer buf (2m: ξ and the new Λ) and the direct
    bilateral method's work `direct`; see delassus_prox."""
    tol_rel, tol_abs, max_iter = s.tol_rel, s.tol_abs, s.max_iterations
    bilateral_direct, criterion = s.bilateral_direct, s.criterion
    gp_ptr, gp_idx, mp_ptr, mp_idx = pat.gp_ptr, pat.gp_idx, pat.mp_ptr, pat.mp_idx
    m = c.shape[0]
    o = 3 * nc
    xi = buf[:m]
    new = buf[m:]
    auto = s.alpha < 0.0
    ps = s      # (the loops below reuse the name s for sums)
    rk, rs, lam0, hist, tmp1, tmp2, dsave, xsave = _auto_setup(s, G, G, MinvW, pat, nc, r, lam)
    long_step = False
    T_old = 0.0
    if criterion == CRITERION_ENERGY:
        _velocity_from_impulses(u_free, MinvW, lam, u, mp_ptr, mp_idx)
        T_old = _kinetic_energy(M, u)
    # ξ of the rows the sweep reads: with the direct bilateral method and a fixed α only the
    # contact rows' (Λ_B is solved for; only the adaptive α's long step reads ξ_B)
    m_xi = o if bilateral_direct and not auto else m
    res = 0.0
    for k in range(max_iter):
        _delassus_apply(G, c, lam, xi, gp_ptr, gp_idx, m_xi)
        if long_step:
            _auto_jor_long_step(ps, nc, xi, rs, rk, dsave, xsave)
            long_step = False
        if not (auto or bilateral_direct):     # (Λ updated and tested in one pass)
            ok, res, finite = _jor_update_in_place(lam, xi, rk, mu, nc, tol_rel, tol_abs)
        else:
            _jor_project(lam, xi, rk, mu, nc, bilateral_direct, new)
            if bilateral_direct:
                _bilateral_direct_delassus(G, c, nc, LB, new, gp_ptr, gp_idx, pat.lb_first,
                                           direct)
            ok, res, finite = _check(lam, new, tol_rel, tol_abs)
            if auto:
                if not finite and hist[1] != 1.0:   # from the warm start again, spectral steps
                    _auto_restart(hist, lam, lam0, rk, rs)
                    long_step = False
                    if criterion == CRITERION_ENERGY:
                        _velocity_from_impulses(u_free, MinvW, lam, u, mp_ptr, mp_idx)
                        T_old = _kinetic_energy(M, u)
                    continue
                long_step = _auto_jor_save(k, lam, new, xi, res, rs, rk, hist, dsave, xsave)
            lam[:] = new
        if not finite:
            return k + 1, STATUS_NONFINITE, res
        if criterion == CRITERION_ENERGY:
            _velocity_from_impulses(u_free, MinvW, lam, u, mp_ptr, mp_idx)
            T = _kinetic_energy(M, u)
            ok = abs(T - T_old) <= abs(T_old) * tol_rel + tol_abs
            T_old = T
        if ok:
            _velocity_from_impulses(u_free, MinvW, lam, u, mp_ptr, mp_idx)
            return k + 1, STATUS_CONVERGED, res
    _velocity_from_impulses(u_free, MinvW, lam, u, mp_ptr, mp_idx)
    return max_iter, STATUS_MAX_ITER, res


@nb.njit(**KERNEL, inline="always")
def _sor_prox_delassus(s, pat, G, c, nc, mu, r, lam, LB, M, u_free, MinvW, u, old, direct):
    """SOR prox on ξ = GΛ + c, contact after contact reusing the updated impulses, with its
    work buffer old (m: Λ of the last sweep) and the direct bilateral method's work
    `direct`; see delassus_prox."""
    tol_rel, tol_abs, max_iter = s.tol_rel, s.tol_abs, s.max_iterations
    bilateral_direct, criterion = s.bilateral_direct, s.criterion
    gp_ptr, gp_idx, mp_ptr, mp_idx = pat.gp_ptr, pat.gp_idx, pat.mp_ptr, pat.mp_idx
    m = c.shape[0]
    o = 3 * nc
    auto = s.alpha < 0.0
    ps = s      # (the loops below reuse the name s for sums)
    rk, rs, lam0, hist, tmp1, tmp2, dsave, xsave = _auto_setup(s, G, G, MinvW, pat, nc, r, lam)
    T_old = 0.0
    if criterion == CRITERION_ENERGY:
        _velocity_from_impulses(u_free, MinvW, lam, u, mp_ptr, mp_idx)
        T_old = _kinetic_energy(M, u)
    res = 0.0
    for k in range(max_iter):
        old[:] = lam
        for i in range(nc):
            b = 3 * i
            x0 = c[b]
            x1 = c[b + 1]
            x2 = c[b + 2]
            for p in range(gp_ptr[b], gp_ptr[b + 1]):
                l = gp_idx[p]
                x0 += G[b, l] * lam[l]
            for p in range(gp_ptr[b + 1], gp_ptr[b + 2]):
                l = gp_idx[p]
                x1 += G[b + 1, l] * lam[l]
            for p in range(gp_ptr[b + 2], gp_ptr[b + 3]):
                l = gp_idx[p]
                x2 += G[b + 2, l] * lam[l]
            _project_contact(lam, b, x0, x1, x2, rk, mu[i], lam)
        if bilateral_direct:
            _bilateral_direct_delassus(G, c, nc, LB, lam, gp_ptr, gp_idx, pat.lb_first, direct)
        else:
            for a in range(o, m):
                s = c[a]
                for p in range(gp_ptr[a], gp_ptr[a + 1]):
                    l = gp_idx[p]
                    s += G[a, l] * lam[l]
                lam[a] -= rk[a] * s
        ok, res, finite = _check(old, lam, tol_rel, tol_abs)
        if auto:
            if not finite and hist[1] != 1.0:   # from the warm start again, spectral steps
                _auto_restart(hist, lam, lam0, rk, rs)
                if criterion == CRITERION_ENERGY:
                    _velocity_from_impulses(u_free, MinvW, lam, u, mp_ptr, mp_idx)
                    T_old = _kinetic_energy(M, u)
                continue
            _auto_next(ps, G, G, MinvW, pat, nc, k, old, lam, res, rs, rk, hist, tmp1, tmp2)
        if not finite:
            return k + 1, STATUS_NONFINITE, res
        if criterion == CRITERION_ENERGY:
            _velocity_from_impulses(u_free, MinvW, lam, u, mp_ptr, mp_idx)
            T = _kinetic_energy(M, u)
            ok = abs(T - T_old) <= abs(T_old) * tol_rel + tol_abs
            T_old = T
        if ok:
            _velocity_from_impulses(u_free, MinvW, lam, u, mp_ptr, mp_idx)
            return k + 1, STATUS_CONVERGED, res
    _velocity_from_impulses(u_free, MinvW, lam, u, mp_ptr, mp_idx)
    return max_iter, STATUS_MAX_ITER, res


@nb.njit(**KERNEL)
def jor_prox_velocity(s, pat, Wt, MinvW, u_free, bvec, nc, mu, r, lam, LB, M, u):
    """JOR prox iterating in the end velocity u^k (Eqn. 17-19); G is never formed."""
    tol_rel, tol_abs, max_iter = s.tol_rel, s.tol_abs, s.max_iterations
    bilateral_direct, criterion = s.bilateral_direct, s.criterion
    wp_ptr, wp_idx, mp_ptr, mp_idx = pat.wp_ptr, pat.wp_idx, pat.mp_ptr, pat.mp_idx
    m = Wt.shape[0]
    buf = np.empty(2 * m)      # (one allocation for ξ and the new Λ)
    xi = buf[:m]
    new = buf[m:]
    auto = s.alpha < 0.0
    ps = s      # (the loops below reuse the name s for sums)
    rk, rs, lam0, hist, tmp1, tmp2, dsave, xsave = _auto_setup(s, Wt, Wt, MinvW, pat, nc, r, lam)
    long_step = False
    _velocity_from_impulses(u_free, MinvW, lam, u, mp_ptr, mp_idx)
    T_old = _kinetic_energy(M, u) if criterion == CRITERION_ENERGY else 0.0
    res = 0.0
    for k in range(max_iter):
        for a in range(m):
            s = bvec[a]
            for p in range(wp_ptr[a], wp_ptr[a + 1]):
                j = wp_idx[p]
                s += Wt[a, j] * u[j]
            xi[a] = s
        if long_step:
            _auto_jor_long_step(ps, nc, xi, rs, rk, dsave, xsave)
            long_step = False
        _jor_project(lam, xi, rk, mu, nc, bilateral_direct, new)
        if bilateral_direct:
            _bilateral_direct_velocity(Wt, MinvW, u_free, nc, LB, new, wp_ptr, wp_idx, mp_ptr,
                                       mp_idx, pat.lb_first)
        ok, res, finite = _check(lam, new, tol_rel, tol_abs)
        if auto:
            if not finite and hist[1] != 1.0:   # from the warm start again, spectral steps
                _auto_restart(hist, lam, lam0, rk, rs)
                long_step = False
                _velocity_from_impulses(u_free, MinvW, lam, u, mp_ptr, mp_idx)
                if criterion == CRITERION_ENERGY:
                    T_old = _kinetic_energy(M, u)
                continue
            long_step = _auto_jor_save(k, lam, new, xi, res, rs, rk, hist, dsave, xsave)
        for l in range(m):
            d = new[l] - lam[l]
            if d != 0.0:
                for p in range(mp_ptr[l], mp_ptr[l + 1]):
                    j = mp_idx[p]
                    u[j] += MinvW[j, l] * d
        lam[:] = new
        if not finite:
            return k + 1, STATUS_NONFINITE, res
        if criterion == CRITERION_ENERGY:
            T = _kinetic_energy(M, u)
            ok = abs(T - T_old) <= abs(T_old) * tol_rel + tol_abs
            T_old = T
        if ok:
            return k + 1, STATUS_CONVERGED, res
    return max_iter, STATUS_MAX_ITER, res


@nb.njit(**KERNEL)
def sor_prox_velocity(s, pat, Wt, MinvW, u_free, bvec, nc, mu, r, lam, LB, M, u):
    """SOR prox in the end velocity: after each contact's projection u is updated (Eqn. 18),
    then the bilateral rows (Eqn. 19, or Eqn. 20 when direct)."""
    tol_rel, tol_abs, max_iter = s.tol_rel, s.tol_abs, s.max_iterations
    bilateral_direct, criterion = s.bilateral_direct, s.criterion
    wp_ptr, wp_idx, mp_ptr, mp_idx = pat.wp_ptr, pat.wp_idx, pat.mp_ptr, pat.mp_idx
    m = Wt.shape[0]
    o = 3 * nc
    old = np.empty(m)
    auto = s.alpha < 0.0
    ps = s      # (the loops below reuse the name s for sums)
    rk, rs, lam0, hist, tmp1, tmp2, dsave, xsave = _auto_setup(s, Wt, Wt, MinvW, pat, nc, r, lam)
    _velocity_from_impulses(u_free, MinvW, lam, u, mp_ptr, mp_idx)
    T_old = _kinetic_energy(M, u) if criterion == CRITERION_ENERGY else 0.0
    res = 0.0
    for k in range(max_iter):
        old[:] = lam
        for i in range(nc):
            b = 3 * i
            x0 = bvec[b]
            for p in range(wp_ptr[b], wp_ptr[b + 1]):
                x0 += Wt[b, wp_idx[p]] * u[wp_idx[p]]
            x1 = bvec[b + 1]
            for p in range(wp_ptr[b + 1], wp_ptr[b + 2]):
                x1 += Wt[b + 1, wp_idx[p]] * u[wp_idx[p]]
            x2 = bvec[b + 2]
            for p in range(wp_ptr[b + 2], wp_ptr[b + 3]):
                x2 += Wt[b + 2, wp_idx[p]] * u[wp_idx[p]]
            l0, l1, l2 = lam[b], lam[b + 1], lam[b + 2]
            _project_contact(lam, b, x0, x1, x2, rk, mu[i], lam)
            for rr in range(3):
                d_ = lam[b + rr] - (l0 if rr == 0 else (l1 if rr == 1 else l2))
                if d_ != 0.0:
                    for p in range(mp_ptr[b + rr], mp_ptr[b + rr + 1]):
                        j = mp_idx[p]
                        u[j] += MinvW[j, b + rr] * d_
        if bilateral_direct:
            if m > o:
                _bilateral_direct_velocity(Wt, MinvW, u_free, nc, LB, lam, wp_ptr, wp_idx,
                                           mp_ptr, mp_idx, pat.lb_first)
                _velocity_from_impulses(u_free, MinvW, lam, u, mp_ptr, mp_idx)
        else:
            for a in range(o, m):
                s = bvec[a]
                for p in range(wp_ptr[a], wp_ptr[a + 1]):
                    j = wp_idx[p]
                    s += Wt[a, j] * u[j]
                d_ = -rk[a] * s
                lam[a] += d_
                for p in range(mp_ptr[a], mp_ptr[a + 1]):
                    j = mp_idx[p]
                    u[j] += MinvW[j, a] * d_
        ok, res, finite = _check(old, lam, tol_rel, tol_abs)
        if auto:
            if not finite and hist[1] != 1.0:   # from the warm start again, spectral steps
                _auto_restart(hist, lam, lam0, rk, rs)
                _velocity_from_impulses(u_free, MinvW, lam, u, mp_ptr, mp_idx)
                if criterion == CRITERION_ENERGY:
                    T_old = _kinetic_energy(M, u)
                continue
            _auto_next(ps, Wt, Wt, MinvW, pat, nc, k, old, lam, res, rs, rk, hist, tmp1, tmp2)
        if not finite:
            return k + 1, STATUS_NONFINITE, res
        if criterion == CRITERION_ENERGY:
            T = _kinetic_energy(M, u)
            ok = abs(T - T_old) <= abs(T_old) * tol_rel + tol_abs
            T_old = T
        if ok:
            return k + 1, STATUS_CONVERGED, res
    return max_iter, STATUS_MAX_ITER, res


@nb.njit(**KERNEL, inline="always")
def prox_solve(s, pat, Wt, MinvW, u_free, bvec, G, c, nc, mu, r, lam, LB, M, u, arena=None):
    """One prox solve with the scheme and form of the settings `s` (a `ProxSettings`-like
    record; one jitted call from the stepper). Problem: W^T (Wt), M^{-1}W (MinvW),
    u_free = u^S + M^{-1} h Δt, b, G = W^T M^{-1} W and c = W^T u_free + b (Delassus form
    only), nc contacts with friction coefficients μ (mu), the prox parameters r, the
    Cholesky factor L_B of G_BB (direct bilateral method), M (energy criterion). lam: Λ,
    warm start in, solution out; u: u^E out. `pat`: the problem's `Patterns`. (The
    Delassus-form kernels, those of every preset, and _auto_setup are inlined into the
    callers: their calls, with some twenty arrays in and out, cost ≈ 0.5 µs of a one-sweep
    solve of 1.8 µs, measured; the velocity-form kernels stay calls.)"""
    if s.form == FORM_DELASSUS:
        return delassus_prox(s.scheme == SCHEME_JOR, s, pat, G, c, nc, mu, r, lam, LB, M,
                             u_free, MinvW, u, arena)
    if s.scheme == SCHEME_JOR:
        return jor_prox_velocity(s, pat, Wt, MinvW, u_free, bvec, nc, mu, r, lam, LB, M, u)
    return sor_prox_velocity(s, pat, Wt, MinvW, u_free, bvec, nc, mu, r, lam, LB, M, u)


def dense_problem_patterns(Wt, MinvW, G):
    """The `Patterns` of a problem given densely (tests, tools)."""
    wp = row_pattern(Wt)
    mp = col_pattern(MinvW)
    gp = row_pattern(G) if G.size else (np.zeros(Wt.shape[0] + 1, dtype=np.int64),
                                        np.zeros(0, dtype=np.int64))
    return Patterns(*wp, *mp, *gp, np.zeros(0, dtype=np.int64))
