"""The numba kernels of Moreau's midpoint step (Gehring et al. 2014, Eqn. 6-8), which
:class:`starleth_sim.physics.stepper.MoreauStepper` calls; no Python objects but the typed
records below.

Names as the paper's symbols: M, h, W, G = W^T M^{-1} W, Λ, ξ, r, α. The settings reach the
kernels as one typed record, `StepSettings`; a prepared hard-contact problem is a
`ContactProblem` with the nonzero `prox.Patterns` of its matrices; the contact memory they
update is the state's arrays. Numba types a plain tuple in C but a namedtuple through Python
(≈2 µs per argument and call, measured), so the kernels that Python calls per step
(`solve_hard_contacts`; `prepare_hard_contacts` and `complete_hard_contacts` for a prepared
step) take and return these records as plain tuples of their fields (`StepSettings(*fields)`
inside rebuilds the record; `problem_fields` / `problem_from_fields` convert a
ContactProblem). Inside, they share `contact_problem` and `complete_problem`, which take the
records. The one-kernel step of the minimal coordinates is in
:mod:`starleth_sim.physics.tree_step`.

Profiling (Fig. 7 phases, `PHASES`): the kernels add the time of each phase to a `timings`
array with `t = lap(timings, phase, t)`; when not profiling, every lap is a no-op. The
one-kernel steps pass None, and `clock` and `lap`, chosen by the type of `timings`, compile
them without any clock; the kernels Python calls phase by phase (`solve_hard_contacts`,
`prepare_hard_contacts`, `complete_hard_contacts`) always get an array, empty when not
profiling (`NOT_TIMED`, `kernel_timings`), so that each is compiled once for both uses (a
second signature cost 30-45 s of cold compilation each, measured) at the price of a length
test per lap.
"""
from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np
import numba as nb
from numba.core import types
from numba.extending import overload

from .kernel_cache import KERNEL
from . import prox
from .array_views import arena_floats, arena_ints, borrowed, view2
from .contact import compliant_contact_forces, generalized_contact_force
from .linalg import (cholesky_upper_input, ltdl, ltdl_solve_cols, ltdl_solve_cols_pattern,
                     ltdl_solve_vec)
from .coordinates.forest import integrate_forest

#: Fig. 7 phases, and their indices in StepperStats.timings
PHASES = ("M_and_h", "M_inverse", "G", "prox", "rest")
PHASE_M_AND_H, PHASE_M_INVERSE, PHASE_G, PHASE_PROX, PHASE_REST = range(len(PHASES))


class StepSettings(NamedTuple):
    """The settings of one step as the kernels read them (built once per stepper from the
    PhysicsConfig, see `MoreauStepper.__init__`)."""

    activation_gap: float       # g_act: I = {i | g_N,i(q^M) ≤ g_act} [m]
    mu: float                   # μ, Coulomb friction coefficient of the ground
    alpha: float                # α, prox relaxation: r = α / diag(G) (< 0: adaptive, prox.py)
    tol_rel: float              # T_rel
    tol_abs: float              # T_abs [N s]
    fallback_alpha_factor: float  # a non-converged solve is retried once with α·this (0: no)
    opening_gap: float          # hysteresis: a loaded contact stays in I while g_N ≤ this [m]
    dt: float                   # Δt [s]
    beta_velocity: float        # β_N of the velocity-level penetration correction (or 0)
    beta_projection: float      # β_N of the post-step projection (or 0: no projection)
    jacobian_gap: float         # W of a contact is computed while g_N(q^M) ≤ this [m]
    projection_tolerance: float  # the projection runs below g_N^E = −this [m]
    form: int                   # prox.FORM_DELASSUS | prox.FORM_VELOCITY
    scheme: int                 # prox.SCHEME_JOR | prox.SCHEME_SOR
    max_iterations: int         # prox iteration cap
    criterion: int              # prox.CRITERION_IMPULSE | prox.CRITERION_ENERGY
    warm_start: bool            # Λ^0 = the last step's Λ of the contacts that stay in I
    bilateral_direct: bool      # Λ_B by Eqn. 20 (else prox rows, Eqn. 19)
    hysteresis: bool            # contact.activation "hysteresis" (else the gap test alone)


class ContactProblem(NamedTuple):
    """The torque-independent part of a step's hard-contact problem (prepare_hard_contacts):
    the rows of the active contacts (3 each, normal first) then the bilateral rows."""

    ok: bool                    # M (and G_B) positive definite
    active: np.ndarray          # I: indices of the active contacts, in row order
    Wt: np.ndarray              # W^T (m x nv)
    MinvW: np.ndarray           # M^{-1} W (nv x m)
    b: np.ndarray               # b = [ε W_U^T u^S + gap terms; (β/Δt) g_B]: ξ = W^T u^E + b
    G: np.ndarray               # G = W^T M^{-1} W (Delassus form; 0 x 0 in the velocity form)
    Gdiag: np.ndarray           # diag(G)
    LB: np.ndarray              # Cholesky factor of G_BB (direct bilateral method, else 0 x 0)
    pat: prox.Patterns          # nonzero patterns of W^T, M^{-1}W and G
    opened: int                 # contacts loaded in the last step that left I


@nb.njit(**KERNEL, inline="always")
def problem_fields(p):
    """A ContactProblem as the plain tuple that crosses into Python cheaply."""
    pat = p.pat
    return (p.ok, p.active, p.Wt, p.MinvW, p.b, p.G, p.Gdiag, p.LB,
            (pat.wp_ptr, pat.wp_idx, pat.mp_ptr, pat.mp_idx, pat.gp_ptr, pat.gp_idx,
             pat.lb_first), p.opened)


@nb.njit(**KERNEL, inline="always")
def problem_from_fields(f):
    """The ContactProblem of problem_fields' tuple."""
    return ContactProblem(f[0], f[1], f[2], f[3], f[4], f[5], f[6], f[7],
                          prox.Patterns(*f[8]), f[9])


@nb.njit(**KERNEL)
def _perf_counter():
    with nb.objmode(t="float64"):
        t = time.perf_counter()
    return t


#: the `timings` of a kernel called phase by phase while not profiling
#: (writeable, as the profiling array: numba types a read-only array differently)
NOT_TIMED = np.zeros(0)


def kernel_timings(timings):
    """The `timings` argument of a kernel called phase by phase: the profiling array, or
    NOT_TIMED for None (not profiling)."""
    return NOT_TIMED if timings is None else timings


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


@overload(clock, jit_options=KERNEL)
def _clock_jit(timings):
    """In the kernels, clock and lap are chosen by the type of `timings`: with None the
    compiled kernel holds no clock at all (an object-mode block, even one never run, costs
    about 1 µs per kernel call, measured); with an array, the clock runs when it is not
    empty."""
    if isinstance(timings, types.NoneType):
        return lambda timings: 0.0

    def impl(timings):
        if timings.shape[0] == 0:
            return 0.0
        return _perf_counter()
    return impl


@overload(lap, jit_options=KERNEL)
def _lap_jit(timings, phase, since):
    if isinstance(timings, types.NoneType):
        return lambda timings, phase, since: 0.0

    def impl(timings, phase, since):
        if timings.shape[0] == 0:
            return 0.0
        t = _perf_counter()
        timings[phase] += t - since
        return t
    return impl


@nb.njit(**KERNEL, inline="always")
def free_velocity(h, dt, uS, dof_parent, L, u_free):
    """u_free = u^S + M^{-1} h Δt with the LTDL factor L of M (linalg.ltdl)."""
    for k in range(uS.shape[0]):
        u_free[k] = h[k] * dt
    ltdl_solve_vec(L, dof_parent, u_free)
    for k in range(uS.shape[0]):
        u_free[k] += uS[k]


@nb.njit(**KERNEL)
def solve_compliant(law, M, h, uS, dt, gap, position, Wt_all, closed, slip, anchor, t1, t2,
                    lam, dof_parent, factor, L, u_free, timings):
    """Alg. 1 without bilateral constraints, in one call: the factor of M into L (unless
    factor is False: L holds it), the compliant forces at (q^M, u^S)
    (contact.compliant_contact_forces, `law`: the fields of a CompliantLaw) added to h, and
    u_free = u^S + M^{-1} h Δt, which is u^E. False if M is not positive definite (then
    nothing else was done)."""
    t = clock(timings)
    if factor:
        ok = ltdl(M, dof_parent, L)
        t = lap(timings, PHASE_M_INVERSE, t)
        if not ok:
            return False
    compliant_contact_forces(law, gap, position, Wt_all, uS, closed, slip, anchor, t1, t2,
                             lam)
    generalized_contact_force(Wt_all, lam, h)
    t = lap(timings, PHASE_REST, t)
    free_velocity(h, dt, uS, dof_parent, L, u_free)
    lap(timings, PHASE_M_INVERSE, t)
    return True


@nb.njit(**KERNEL, inline="always")
def active_set(gap, s, last_impulse, last_active, arena=None):
    """The active set I at q^M: g_N,i ≤ s.activation_gap, and with s.hysteresis also every
    contact that carried Λ_N > 0 in the last step while g_N,i ≤ s.opening_gap. Returns
    (indices of I, number of contacts loaded in the last step that are not in I)."""
    activation_gap, hysteresis, opening_gap = s.activation_gap, s.hysteresis, s.opening_gap
    nc = gap.shape[0]
    picked = arena_ints(arena, nc)
    na = 0
    opened = 0
    for i in range(nc):
        loaded = last_active[i] and last_impulse[i, 0] > 0.0
        if gap[i] <= activation_gap or (hysteresis and loaded and gap[i] <= opening_gap):
            picked[na] = i
            na += 1
        elif loaded:
            opened += 1
    return picked[:na], opened


@nb.njit(**KERNEL)
def normal_law_offset(gap, dt, beta_velocity):
    """The gap terms of the normal law's b_N (ξ_N = γ_N^E + ε_N γ_N^S + b_gap):
    g_N⁺/Δt lets a contact above the ground approach it within the step (never pulls, as
    Λ_N ≥ 0), and (β_N/Δt) min(g_N, 0) is the velocity-level penetration correction (0 unless
    contact.penetration_correction is "velocity")."""
    if gap > 0.0:
        return gap / dt
    return beta_velocity * gap / dt


@nb.njit(**KERNEL, inline="always")
def phase_minv(s, M, uS, gap, Wt_all, WtB, bB, eps, dof_parent, factor, L, last_impulse,
               last_active, arena=None):
    """Fig. 7 phase "M^-1" (the part that does not depend on the torques): factor M into
    L (unless factor is False: L already holds the factor of a constant M), the active set
    (see active_set), W^T = [W_U^T of the active contacts; W_B^T], M^{-1} W and
    b = [ε W_U^T u^S + gap terms; b_B] with ε_i = diag(ε_N,i, ε_T,i, ε_T,i) (eps: nc x 2), the
    normal rows' gap terms of normal_law_offset and b_B the bilateral drift stabilisation
    (β/Δt) g_B (zero in the paper's law), and the nonzero patterns of the rows of W^T and
    the columns of M^{-1} W.
    Returns (ok, active, Wt, MinvW, b, patterns, opened), the patterns of G still empty; ok
    is False if M is not positive definite; opened counts the loaded contacts that left the
    active set. The arrays come from the step's arena (array_views.arena_floats)."""
    dt, beta_velocity = s.dt, s.beta_velocity
    nv = uS.shape[0]
    ok = True
    if factor:
        ok = ltdl(M, dof_parent, L)
    active, opened = active_set(gap, s, last_impulse, last_active, arena)
    na = active.shape[0]
    nb_ = WtB.shape[0]
    o = 3 * na
    m = o + nb_
    buf = arena_floats(arena, 2 * m * nv + m)     # (one buffer for W^T, M^{-1}W and b)
    Wt = view2(buf[:m * nv], (m, nv))
    MinvW = view2(buf[m * nv:2 * m * nv], (nv, m))
    bvec = buf[2 * m * nv:]
    bvec[:] = 0.0
    if not ok or m == 0:
        e = np.zeros(1, dtype=np.int64)
        return (ok, active, Wt, MinvW, bvec, prox.Patterns(e, e[:0], e, e[:0], e, e[:0], e[:0]),
                opened)
    for a in range(na):
        i = active[a]
        for r in range(3):
            for j in range(nv):
                Wt[3 * a + r, j] = Wt_all[i, r, j]
    for a in range(nb_):
        for j in range(nv):
            Wt[o + a, j] = WtB[a, j]
    wp_ptr, wp_idx = prox.row_pattern(Wt, arena)
    trees = 1
    for k in range(1, nv):
        if dof_parent[k] == -1:
            trees += 1
    # W = (W^T)^T into MinvW: its nonzeros (the row pattern of W^T) into a zeroed MinvW (a
    # foot's column is zero but on the base and its own leg; a strided copy of every entry
    # was the busiest loop of an HmJ step's kernel, measured with perf)
    MinvW[:, :] = 0.0
    for a in range(m):
        for p in range(wp_ptr[a], wp_ptr[a + 1]):
            MinvW[wp_idx[p], a] = Wt[a, wp_idx[p]]
    if trees > 2:
        # a forest of free bodies (the maximal coordinates): M^{-1}W and the pattern of its
        # columns from the pattern of W's columns (the rows of W^T), without scanning MinvW
        # (the same MinvW and pattern as below: the zeros of W stay out of every sum)
        mp_ptr, mp_idx = ltdl_solve_cols_pattern(L, dof_parent, MinvW, wp_ptr, wp_idx,
                                                 arena)
    else:
        ltdl_solve_cols(L, dof_parent, MinvW, arena)
        mp_ptr, mp_idx = prox.col_pattern(MinvW, arena)
    for a in range(o):
        s = 0.0
        for p in range(wp_ptr[a], wp_ptr[a + 1]):   # (the zeros of a row add nothing)
            s += Wt[a, wp_idx[p]] * uS[wp_idx[p]]
        bvec[a] = eps[active[a // 3], 0 if a % 3 == 0 else 1] * s
    for a in range(na):
        bvec[3 * a] += normal_law_offset(gap[active[a]], dt, beta_velocity)
    for a in range(nb_):
        bvec[o + a] = bB[a]
    # (G's pattern is still to come: wp_ptr[:1] = [0] and an empty index, as placeholders)
    return (ok, active, Wt, MinvW, bvec,
            prox.Patterns(wp_ptr, wp_idx, mp_ptr, mp_idx, wp_ptr[:1], wp_idx[:0], wp_idx[:0]),
            opened)


@nb.njit(**KERNEL, inline="always")
def phase_delassus(form, nc, bilateral_direct, Wt, MinvW, pat, arena=None):
    """Fig. 7 phase "G (and G_B^-1)": G = W^T M^{-1} W (Delassus form) or only diag(G)
    (velocity form), and for the direct bilateral solution (Eqn. 20) the Cholesky factor
    of G_B = W_B^T M^{-1} W_B. Returns (ok, G, diag G, L_B, patterns): `pat` (the
    prox.Patterns of W^T and M^{-1}W) with the pattern of the rows of G and L_B's
    envelope; G, L_B and the patterns from the step's arena (the Delassus form)."""
    wp_ptr, wp_idx, mp_ptr, mp_idx = pat.wp_ptr, pat.wp_idx, pat.mp_ptr, pat.mp_idx
    m, nv = Wt.shape
    o = 3 * nc
    nb_ = m - o
    if form == prox.FORM_DELASSUS:
        buf = arena_floats(arena, m * m + m)      # (one buffer for G and its diagonal)
        G = view2(buf[:m * m], (m, m))
        Gdiag = buf[m * m:]
        prox.delassus(Wt, MinvW, G, wp_ptr, wp_idx, mp_ptr, mp_idx, arena)
        for a in range(m):
            Gdiag[a] = G[a, a]
        gp_ptr, gp_idx = prox.row_pattern(G, arena)
    else:
        Gdiag = np.empty(m)
        G = view2(Gdiag[:0], (0, 0))
        prox.delassus_diagonal(Wt, MinvW, Gdiag, wp_ptr, wp_idx)
        gp_ptr = np.zeros(m + 1, dtype=np.int64)
        gp_idx = np.zeros(0, dtype=np.int64)
    LB = view2(Gdiag[:0], (0, 0))      # (empty views: no allocation)
    lb_first = gp_ptr[:0]
    ok = True
    if bilateral_direct and nb_ > 0:
        if form == prox.FORM_DELASSUS:     # G_BB: G's lower right block, read in place
            GB, ob = G, o
        else:
            GB, ob = np.empty((nb_, nb_)), 0
            for a in range(nb_):
                for b in range(a, nb_):
                    s = 0.0
                    for p in range(wp_ptr[o + a], wp_ptr[o + a + 1]):
                        s += Wt[o + a, wp_idx[p]] * MinvW[wp_idx[p], o + b]
                    GB[a, b] = s
                    GB[b, a] = s
        LB = view2(arena_floats(arena, nb_ * nb_), (nb_, nb_))
        LB[:, :] = 0.0
        lb_first = arena_ints(arena, nb_)
        ok = cholesky_upper_input(GB, ob, LB, lb_first)
    full = prox.Patterns(wp_ptr, wp_idx, mp_ptr, mp_idx, gp_ptr, gp_idx, lb_first)
    return ok, G, Gdiag, LB, full


@nb.njit(**KERNEL, inline="always")
def constraint_velocity(Wt, u_free, bvec, wp_ptr, wp_idx, c):
    """c = W^T u_free + b (Eqn. 15), with the row pattern of W^T."""
    m = Wt.shape[0]
    for a in range(m):
        s = bvec[a]
        for p in range(wp_ptr[a], wp_ptr[a + 1]):
            s += Wt[a, wp_idx[p]] * u_free[wp_idx[p]]
        c[a] = s


@nb.njit(**KERNEL, inline="always")
def phase_prox(s, p, u_free, M, last_impulse, last_active, last_bilateral, timings, t,
               arena=None):
    """c = W^T u_free + b (constraint_velocity, timed as phase "G" from t), then Fig. 7
    phase "u^E" of the problem p (a ContactProblem): warm start (the last step's impulses of
    contacts that stay active, and of the bilateral constraints), the prox iteration, and
    one retry with α·s.fallback_alpha_factor if it did not converge. Returns (u^E, Λ,
    iterations, status, residual, retried, the time at the end of phase "G")."""
    active = p.active
    alpha = s.alpha
    fallback_factor = s.fallback_alpha_factor
    na = active.shape[0]
    o = 3 * na
    m = p.Wt.shape[0]
    nv = u_free.shape[0]
    # (one allocation for Λ^0, Λ, r, u^E, μ per contact and c; borrowed: no reference
    # counting in the prox iteration, the owner held by its use in the return)
    owner = arena_floats(arena, 4 * m + nv + na)
    buf = borrowed(owner)
    c = buf[3 * m + nv + na:]
    constraint_velocity(p.Wt, u_free, p.b, p.pat.wp_ptr, p.pat.wp_idx, c)
    t = lap(timings, PHASE_G, t)
    lam0 = buf[:m]
    lam = buf[m:2 * m]
    r = buf[2 * m:3 * m]
    u = buf[3 * m:3 * m + nv]
    mu_vec = buf[3 * m + nv:3 * m + nv + na]
    lam0[:] = 0.0
    if s.warm_start:
        for a in range(na):
            i = active[a]
            if last_active[i]:
                for k in range(3):
                    lam0[3 * a + k] = last_impulse[i, k]
        for a in range(m - o):
            lam0[o + a] = last_bilateral[a]
    mu_vec[:] = s.mu
    attempts = 2 if fallback_factor > 0.0 else 1
    lam[:] = lam0
    iters = 0
    status = prox.STATUS_CONVERGED
    resid = 0.0
    retried = False
    for attempt in range(attempts):
        prox.prox_parameters(p.Gdiag, na, alpha, r)
        lam[:] = lam0
        it, status, resid = prox.prox_solve(s, p.pat, p.Wt, p.MinvW, u_free, p.b, p.G, c, na,
                                            mu_vec, r, lam, p.LB, M, u, arena)
        iters += it
        if status == prox.STATUS_CONVERGED:
            break
        if attempt + 1 < attempts:
            retried = True
            alpha *= fallback_factor
    # (u^E and Λ as owned views: the caller keeps them)
    return owner[3 * m:3 * m + nv], owner[m:2 * m], iters, status, resid, retried, t


#: the post-step projection runs when a contact's predicted end gap is below
#: −PROJECTION_TOLERANCE [m]: 1 µm, 100x below what the eye or a controller notices, and
#: above the noise of the prox solver's tolerance at rest (at 10 nm it ran on 45 % of the
#: steps of a robot standing still; at 1 µm on none, and on the touchdowns of a trot)
PROJECTION_TOLERANCE = 1e-6
#: contacts up to this far above the ground at q^M are checked for penetration at the end of
#: the step [m] (a foot approaching at 4 m/s moves 5 mm in ½Δt = 1.25 ms)
PROJECTION_LOOKAHEAD = 5e-3


@nb.njit(**KERNEL, inline="always")
def predicted_end_gaps(gap, Wt_all, jacobian_gap, is_active, uE, dt, out):
    """g_N^E ≈ g_N(q^M) + ½Δt W_N^T u^E of every contact whose Jacobian is known (in the
    active set or g_N(q^M) ≤ jacobian_gap); +inf for the others. Returns the smallest."""
    nv = uE.shape[0]
    worst = np.inf
    for i in range(gap.shape[0]):
        if not (is_active[i] or gap[i] <= jacobian_gap):
            out[i] = np.inf
            continue
        s = 0.0
        for j in range(nv):
            s += Wt_all[i, 0, j] * uE[j]
        out[i] = gap[i] + 0.5 * dt * s
        if out[i] < worst:
            worst = out[i]
    return worst


@nb.njit(**KERNEL)
def projection_problem(Wt, MinvW, active, extra, Wt_all, dof_parent, L):
    """W^T and M^{-1}W of the projection when contacts outside the active set (`extra`) are
    predicted to penetrate: the rows of the active contacts and of `extra` (3 each, as the
    prox kernels expect), then the bilateral rows of the velocity problem (their M^{-1}W
    columns are reused). Returns (contacts, Wt, MinvW, prox.Patterns of the rows of Wt and
    the columns of MinvW, that of G still empty)."""
    na = active.shape[0]
    ne = extra.shape[0]
    m0, nv = Wt.shape
    o0 = 3 * na
    nb_ = m0 - o0
    nc = na + ne
    o = 3 * nc
    contacts = np.empty(nc, dtype=np.int64)
    contacts[:na] = active
    contacts[na:] = extra
    Wp = np.empty((o + nb_, nv))
    Mp = np.zeros((nv, o + nb_))
    for a in range(o0):
        for j in range(nv):
            Wp[a, j] = Wt[a, j]
            Mp[j, a] = MinvW[j, a]
    for e in range(ne):
        for r in range(3):
            for j in range(nv):
                Wp[o0 + 3 * e + r, j] = Wt_all[extra[e], r, j]
    cols = np.empty((nv, 3 * ne))
    for c in range(3 * ne):
        for j in range(nv):
            cols[j, c] = Wp[o0 + c, j]
    ltdl_solve_cols(L, dof_parent, cols)
    for c in range(3 * ne):
        for j in range(nv):
            Mp[j, o0 + c] = cols[j, c]
    for a in range(nb_):
        for j in range(nv):
            Wp[o + a, j] = Wt[o0 + a, j]
            Mp[j, o + a] = MinvW[j, o0 + a]
    wp_ptr, wp_idx = prox.row_pattern(Wp)
    mp_ptr, mp_idx = prox.col_pattern(Mp)
    e = np.zeros(1, dtype=np.int64)
    return contacts, Wp, Mp, prox.Patterns(wp_ptr, wp_idx, mp_ptr, mp_idx, e, e[:0], e[:0])


@nb.njit(**KERNEL)
def phase_projection(s, p, is_active, gap, Wt_all, dof_parent, L, M, uE, u_corr, arena=None):
    """Post-step projection (contact.penetration_correction "projection"). With the
    predicted end gaps g_N^E = g_N(q^M) + ½Δt W_N^T u^E of the active contacts and of the
    contacts outside the active set that would end the step below the ground (a foot that
    was above it at q^M), it finds the pseudo-velocity Δu_p = M^{-1}(W_N P_N + W_B P_B) of
        P_N ≥ 0 ⊥ W_N^T Δu_p + (2/Δt)(max(g_N^E, 0) + β_N min(g_N^E, 0)) ≥ 0,
        W_B^T Δu_p = 0  (the bilateral constraints are not disturbed),
    frictionless (μ = 0), with the prox scheme of the velocity solve (problem p, a
    ContactProblem), so that q^E = q^M ⊕ ½Δt (u^E + Δu_p) loses the fraction
    β_N = s.beta_projection of every penetration and no contact is pushed into the ground.
    u_corr receives Δu_p (zero when no predicted end gap is below −s.projection_tolerance).
    Returns (iterations, status); status −1: not needed."""
    dt, beta, tolerance = s.dt, s.beta_projection, s.projection_tolerance
    active = p.active
    nv = uE.shape[0]
    nc = gap.shape[0]
    for k in range(nv):
        u_corr[k] = 0.0
    gE = arena_floats(arena, nc)
    worst = predicted_end_gaps(gap, Wt_all, s.jacobian_gap, is_active, uE, dt, gE)
    if worst >= -tolerance or beta == 0.0:
        return 0, -1
    extra = np.nonzero(~is_active & (gE < -tolerance))[0]
    if extra.shape[0] == 0:
        contacts = active
        Wp, Mp, Gp, Gdp, full = p.Wt, p.MinvW, p.G, p.Gdiag, p.pat
    else:
        contacts, Wp, Mp, part = projection_problem(p.Wt, p.MinvW, active, extra, Wt_all,
                                                    dof_parent, L)
        _, Gp, Gdp, _, f = phase_delassus(s.form, contacts.shape[0], False, Wp, Mp, part)
        # the bilateral rows, G_BB and so L_B are the problem's: L_B's envelope with them
        full = prox.Patterns(f.wp_ptr, f.wp_idx, f.mp_ptr, f.mp_idx, f.gp_ptr, f.gp_idx,
                             p.pat.lb_first)
    m = Wp.shape[0]
    ncp = contacts.shape[0]
    bp = np.zeros(m)
    for a in range(ncp):
        g = gE[contacts[a]]
        bp[3 * a] = (max(g, 0.0) + beta * min(g, 0.0)) / (0.5 * dt)
    r = np.empty(m)
    prox.prox_parameters(Gdp, ncp, s.alpha, r)
    lam = np.zeros(m)
    mu = np.zeros(ncp)
    zero = np.zeros(nv)
    it, status, _ = prox.prox_solve(s, full, Wp, Mp, zero, bp, Gp, bp, ncp, mu, r, lam, p.LB,
                                    M, u_corr)
    if status == prox.STATUS_NONFINITE:
        for k in range(nv):
            u_corr[k] = 0.0
    return it, status


@nb.njit(**KERNEL)
def contact_problem(s, M, uS, gap, Wt_all, WtB, bB, eps, dof_parent, factor, L, last_impulse,
                    last_active, timings, arena=None):
    """The torque-independent part of the hard-contact solve for the StepSettings s: the
    phases "M^-1" and "G" (phase_minv, phase_delassus), timed into `timings` when
    profiling. Returns the ContactProblem, its arrays from `arena` (a one-kernel step's,
    valid until its next reset; None: allocated, for a problem that outlives the call)."""
    t = clock(timings)
    ok, active, Wt, MinvW, bvec, pat, opened = phase_minv(
        s, M, uS, gap, Wt_all, WtB, bB, eps, dof_parent, factor, L, last_impulse, last_active,
        arena)
    t = lap(timings, PHASE_M_INVERSE, t)
    if ok and Wt.shape[0] != 0:
        ok, G, Gdiag, LB, pat = phase_delassus(s.form, active.shape[0], s.bilateral_direct,
                                               Wt, MinvW, pat, arena)
    else:
        G, Gdiag, LB = view2(bvec[:0], (0, 0)), bvec[:0], view2(bvec[:0], (0, 0))
    lap(timings, PHASE_G, t)
    return ContactProblem(ok, active, Wt, MinvW, bvec, G, Gdiag, LB, pat, opened)


@nb.njit(**KERNEL)
def prepare_hard_contacts(settings, M, uS, gap, Wt_all, WtB, bB, eps, dof_parent, factor, L,
                          last_impulse, last_active, timings):
    """contact_problem for a caller that prepares ahead (MoreauStepper.prepare).
    `settings`: the fields of a StepSettings (a plain tuple will do). Returns the
    ContactProblem as problem_fields' tuple, the input of complete_hard_contacts."""
    return problem_fields(contact_problem(StepSettings(*settings), M, uS, gap, Wt_all, WtB,
                                          bB, eps, dof_parent, factor, L, last_impulse,
                                          last_active, timings))


@nb.njit(**KERNEL)
def complete_problem(s, p, h, uS, M, dof_parent, L, gap, Wt_all, last_impulse, last_active,
                     last_bilateral, impulse, is_active, u_free, u, u_corr, remember, timings,
                     arena=None):
    """The torque-dependent rest of the hard-contact solve of the ContactProblem p for the
    StepSettings s: u_free = u^S + M^{-1} h Δt (phase "M^-1"),
    c = W^T u_free + b (phase "G"), the prox iteration (phase_prox) and the post-step
    projection (phase_projection; both phase "prox"), timed into `timings` when
    profiling. Writes Λ_U of every contact point into impulse (nc x 3), the active flags,
    u^E into u and the projection's Δu_p into u_corr; unless the result is non-finite,
    Λ_B is written into last_bilateral, and with `remember` the
    warm-start memory (last_impulse, last_active) is updated (remember_contacts; the
    one-kernel steps pass False and do that once the end of the step is known finite;
    they also pass their arena, array_views.arena_floats).
    Returns (iterations, status, residual, retried, projection iterations, projection
    status)."""
    t = clock(timings)
    free_velocity(h, s.dt, uS, dof_parent, L, u_free)
    t = lap(timings, PHASE_M_INVERSE, t)
    nc = impulse.shape[0]
    for i in range(nc):
        is_active[i] = False
        impulse[i, 0] = 0.0
        impulse[i, 1] = 0.0
        impulse[i, 2] = 0.0
    active = p.active
    na = active.shape[0]
    o = 3 * na
    it, status, resid, retried = 0, prox.STATUS_CONVERGED, 0.0, False
    pit, pstatus = 0, -1
    u_corr[:] = 0.0
    if p.Wt.shape[0] == 0:
        u[:] = u_free
    else:
        uE, lam, it, status, resid, retried, t = phase_prox(s, p, u_free, M, last_impulse,
                                                            last_active, last_bilateral,
                                                            timings, t, arena)
        u[:] = uE
        for a in range(na):
            i = active[a]
            is_active[i] = True
            for k in range(3):
                impulse[i, k] = lam[3 * a + k]
        finite = True
        for k in range(u.shape[0]):
            if not np.isfinite(u[k]):
                finite = False
        if not finite:
            status = prox.STATUS_NONFINITE
        if status != prox.STATUS_NONFINITE:
            for a in range(lam.shape[0] - o):
                last_bilateral[a] = lam[o + a]
        t = lap(timings, PHASE_PROX, t)
    if status != prox.STATUS_NONFINITE and s.beta_projection > 0.0:
        t = clock(timings)
        pit, pstatus = phase_projection(s, p, is_active, gap, Wt_all, dof_parent, L, M, u, u_corr,
                                        arena)
        lap(timings, PHASE_PROX, t)
    if remember and status != prox.STATUS_NONFINITE:
        remember_contacts(is_active, impulse, last_active, last_impulse)
    return it, status, resid, retried, pit, pstatus


@nb.njit(**KERNEL, inline="always")
def remember_contacts(is_active, impulse, last_active, last_impulse):
    """The warm-start memory of a finished step: its active flags and Λ (nc x 3)."""
    for i in range(is_active.shape[0]):
        last_active[i] = is_active[i]
        for k in range(3):
            last_impulse[i, k] = impulse[i, k]




#: contact_problem and complete_problem inlined into the one-kernel steps
#: (tree_step.tree_step_hard, forest_step_hard): there the ContactProblem's twenty-odd arrays
#: need not be passed, returned and reference-counted across calls (≈ 15 % of an HmJ step,
#: measured side by side); the other callers call them (inlining them everywhere cost 70 s
#: more of cold compilation, measured)
contact_problem_inlined = nb.njit(**KERNEL, inline="always")(contact_problem.py_func)
complete_problem_inlined = nb.njit(**KERNEL, inline="always")(complete_problem.py_func)


@nb.njit(**KERNEL)
def complete_hard_contacts(settings, problem, h, uS, M, dof_parent, L, gap, Wt_all, last_impulse,
                           last_active, last_bilateral, impulse, is_active, u_free, u, u_corr,
                           timings):
    """complete_problem of a prepared problem (problem_fields' tuple from
    prepare_hard_contacts; `settings`: the fields of a StepSettings)."""
    return complete_problem(StepSettings(*settings), problem_from_fields(problem), h, uS, M,
                            dof_parent, L, gap, Wt_all, last_impulse, last_active, last_bilateral,
                            impulse, is_active, u_free, u, u_corr, True, timings)


@nb.njit(**KERNEL)
def solve_hard_contacts(settings, M, uS, gap, Wt_all, WtB, bB, eps, dof_parent, factor, L, h,
                        last_impulse, last_active, last_bilateral, impulse, is_active, u_free,
                        u, u_corr, timings):
    """contact_problem and complete_problem in one call, for a step that was not prepared
    ahead: the same arithmetic as prepare_hard_contacts then complete_hard_contacts (so the
    same result bit for bit), without the problem's arrays crossing into Python and back
    (≈1 µs per array, measured). Returns (ok, |I|, opened, iterations, status, residual,
    retried, projection iterations, projection status); with ok False (M or G_B not
    positive definite) nothing else was done."""
    s = StepSettings(*settings)
    p = contact_problem(s, M, uS, gap, Wt_all, WtB, bB, eps, dof_parent, factor, L, last_impulse,
                        last_active, timings)
    if not p.ok:
        return False, 0, 0, 0, prox.STATUS_CONVERGED, 0.0, False, 0, -1
    it, status, resid, retried, pit, pstatus = complete_problem(
        s, p, h, uS, M, dof_parent, L, gap, Wt_all, last_impulse, last_active, last_bilateral,
        impulse, is_active, u_free, u, u_corr, True, timings)
    return True, p.active.shape[0], p.opened, it, status, resid, retried, pit, pstatus


@nb.njit(**KERNEL)
def end_of_step(qM, uE, u_corr, projected, half_dt, jtype, idx_q, idx_v, qE):
    """Eqn. (8): q^E = q^M ⊕ ½Δt F(q^M) (u^E + Δu_p) (Δu_p = u_corr of the post-step
    projection when it ran, else 0) into qE. False if q^E or u^E is not finite."""
    if projected:
        v = uE + u_corr
    else:
        v = uE
    integrate_forest(qM, v, half_dt, jtype, idx_q, idx_v, qE)
    return all_finite(qE, uE)


@nb.njit(**KERNEL)
def all_finite(a, b):
    for k in range(a.shape[0]):
        if not np.isfinite(a[k]):
            return False
    for k in range(b.shape[0]):
        if not np.isfinite(b[k]):
            return False
    return True
