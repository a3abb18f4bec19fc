"""Moreau's midpoint time-stepping scheme (Gehring et al. 2014, Eqn. 6-8).

One step over Δt = t^E − t^S:
    q^M = q^S ⊕ ½Δt F(q^S) u^S                                  (6)
    M, h, W evaluated at (q^M, u^S); active set I = {i | g_N,i(q^M) ≤ g_act}
    (g_act = contact.activation_gap, 0 in the presets as in the paper; with
    contact.activation "hysteresis" a contact loaded in the last step stays in I while
    g_N,i(q^M) ≤ contact.opening_gap, see `active_set`)
    M (u^E − u^S) − h Δt − W_U Λ_U − W_B Λ_B = 0, (ξ, Λ) ∈ U × B   (7)
    q^E = q^M ⊕ ½Δt F(q^M) u^E                                   (8)
Hard contacts solve (7) with the JOR/SOR prox iterations of :mod:`starleth_sim.physics.prox`;
compliant contacts (Alg. 1) add their forces, evaluated at (q^M, u^S), to h and Λ_U
vanishes. The stepper works for any coordinate set (see :mod:`starleth_sim.physics.coordinates`).

A step runs in two parts: `MoreauStepper.prepare` does everything that depends only on
(q^S, u^S) (q^M, M, h without τ, the kinematics, the factor of M, M^{-1}W, G), and
`MoreauStepper.step` adds the joint torques and external forces to h and solves (7) and (8).
A caller may prepare ahead (sim_node does, while its controller computes); the result is
the same bit for bit. A step that was not prepared ahead runs with few calls from Python:
the midpoint in one kernel (`ForestCoordinates.midpoint`: q^M, M and h by the jitted CRBA /
RNEA of :mod:`starleth_sim.physics.rigid_body`, the contact kinematics), the contact problem
set up and solved in one (`solve_hard_contacts`, or `solve_compliant`), Eqn. (8) in one
(`end_of_step`).

Model, state and workspace (see :mod:`starleth_sim.physics.state`): the stepper holds the
model side (coordinate set, ground, `StepSettings`, ε per contact) and a workspace (the
arrays at q^M, the factor of M, the prepared step, `StepperStats`); the evolving state,
including the contact memory the kernels read and update (warm start, hysteresis, the
compliant contacts' anchors), lives in the `SimState` passed to `prepare` and `step`.

Kernels (names as the paper's symbols: M, h, W, G = W^T M^{-1} W, Λ, ξ, r, α): the
settings reach the numba kernels as one typed record, `StepSettings`; a prepared
hard-contact problem is a `ContactProblem` with the nonzero `prox.Patterns` of its
matrices; the contact memory they update is the state's arrays. Numba types a plain
tuple in C but a namedtuple through Python (≈2 µs per argument and call, measured), so the
kernels that Python calls per step (`solve_hard_contacts`; `prepare_hard_contacts` and
`complete_hard_contacts` for a prepared step) take and return these records as plain
tuples of their fields (`StepSettings(*fields)` inside rebuilds the record;
`problem_fields` / `problem_from_fields` convert a ContactProblem). Inside, they share
`contact_problem` and `complete_problem`, which take the records.

Profiling (Fig. 7 phases, `PHASES`): there is one sequence of phase calls, profiled or not.
The Python orchestration and the kernels add the time of each phase to a `timings` array
(StepperStats.timings) with `t = lap(timings, phase, t)`; when not profiling, timings is
None and every lap is a no-op: in the kernels `clock` and `lap` are chosen by the type of
`timings`, so the unprofiled kernels are compiled without any clock, and the Python side
skips its laps behind `if prof:`. The call overheads between the phases are no phase's.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import numba as nb
from numba.core import types
from numba.extending import overload

from . import prox
from .config import ConfigError
from .contact import (CompliantLaw, GroundPlane, compliant_contact_forces,
                      generalized_contact_force)
from .linalg import (cholesky_blocks, cholesky_blocks_solve_cols, cholesky_blocks_solve_vec,
                     cholesky_upper_input)
from .coordinates.forest import integrate_forest, midpoint_dynamics
from .state import SimState

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


@nb.njit(cache=True, inline="always")
def problem_fields(p):
    """A ContactProblem as the plain tuple that crosses into Python cheaply."""
    pat = p.pat
    return (p.ok, p.active, p.Wt, p.MinvW, p.b, p.G, p.Gdiag, p.LB,
            (pat.wp_ptr, pat.wp_idx, pat.mp_ptr, pat.mp_idx, pat.gp_ptr, pat.gp_idx), p.opened)


@nb.njit(cache=True, inline="always")
def problem_from_fields(f):
    """The ContactProblem of problem_fields' tuple."""
    return ContactProblem(f[0], f[1], f[2], f[3], f[4], f[5], f[6], f[7],
                          prox.Patterns(*f[8]), f[9])


@nb.njit(cache=True)
def _perf_counter():
    with nb.objmode(t="float64"):
        t = time.perf_counter()
    return t


def clock(timings):
    """The profiling clock: time.perf_counter() when profiling (timings is the array the
    phases' times go to), else 0 (timings is None)."""
    return 0.0 if timings is None else time.perf_counter()


def lap(timings, phase, since):
    """Profiling: add the time since `since` to timings[phase] and return the clock; a
    no-op returning 0 when timings is None (not profiling)."""
    if timings is None:
        return 0.0
    t = time.perf_counter()
    timings[phase] += t - since
    return t


@overload(clock, jit_options={"cache": True})
def _clock_jit(timings):
    """In the kernels, clock and lap are chosen by the type of `timings`: with None (not
    profiling) the compiled kernel holds no clock at all (an object-mode block, even one
    never run, costs about 1 µs per kernel call, measured)."""
    if isinstance(timings, types.NoneType):
        return lambda timings: 0.0
    return lambda timings: _perf_counter()


@overload(lap, jit_options={"cache": True})
def _lap_jit(timings, phase, since):
    if isinstance(timings, types.NoneType):
        return lambda timings, phase, since: 0.0

    def impl(timings, phase, since):
        t = _perf_counter()
        timings[phase] += t - since
        return t
    return impl


class SimulationError(RuntimeError):
    """The step could not be completed (non-finite solver output or state); the state was
    left unchanged."""


@nb.njit(cache=True)
def free_velocity(h, dt, uS, blocks, L, u_free):
    """u_free = u^S + M^{-1} h Δt with the block Cholesky factor L of M (one block per
    tree)."""
    for k in range(uS.shape[0]):
        u_free[k] = h[k] * dt
    cholesky_blocks_solve_vec(L, blocks, u_free)
    for k in range(uS.shape[0]):
        u_free[k] += uS[k]


@nb.njit(cache=True)
def solve_compliant(law, M, h, uS, dt, gap, position, Wt_all, closed, slip, anchor, t1, t2,
                    lam, blocks, factor, L, u_free, timings):
    """Alg. 1 without bilateral constraints, in one call: the factor of M into L (unless
    factor is False: L holds it), the compliant forces at (q^M, u^S)
    (contact.compliant_contact_forces, `law`: the fields of a CompliantLaw) added to h, and
    u_free = u^S + M^{-1} h Δt, which is u^E. False if M is not positive definite (then
    nothing else was done)."""
    t = clock(timings)
    if factor:
        ok = cholesky_blocks(M, blocks, L)
        t = lap(timings, PHASE_M_INVERSE, t)
        if not ok:
            return False
    compliant_contact_forces(law, gap, position, Wt_all, uS, closed, slip, anchor, t1, t2,
                             lam)
    generalized_contact_force(Wt_all, lam, h)
    t = lap(timings, PHASE_REST, t)
    free_velocity(h, dt, uS, blocks, L, u_free)
    lap(timings, PHASE_M_INVERSE, t)
    return True


@nb.njit(cache=True)
def active_set(gap, s, last_impulse, last_active):
    """The active set I at q^M: g_N,i ≤ s.activation_gap, and with s.hysteresis also every
    contact that carried Λ_N > 0 in the last step while g_N,i ≤ s.opening_gap. Returns
    (indices of I, number of contacts loaded in the last step that are not in I)."""
    activation_gap, hysteresis, opening_gap = s.activation_gap, s.hysteresis, s.opening_gap
    nc = gap.shape[0]
    flags = np.zeros(nc, dtype=np.bool_)
    na = 0
    opened = 0
    for i in range(nc):
        loaded = last_active[i] and last_impulse[i, 0] > 0.0
        if gap[i] <= activation_gap or (hysteresis and loaded and gap[i] <= opening_gap):
            flags[i] = True
            na += 1
        elif loaded:
            opened += 1
    active = np.empty(na, dtype=np.int64)
    k = 0
    for i in range(nc):
        if flags[i]:
            active[k] = i
            k += 1
    return active, opened


@nb.njit(cache=True)
def normal_law_offset(gap, dt, beta_velocity):
    """The gap terms of the normal law's b_N (ξ_N = γ_N^E + ε_N γ_N^S + b_gap):
    g_N⁺/Δt lets a contact above the ground approach it within the step (never pulls, as
    Λ_N ≥ 0), and (β_N/Δt) min(g_N, 0) is the velocity-level penetration correction (0 unless
    contact.penetration_correction is "velocity")."""
    if gap > 0.0:
        return gap / dt
    return beta_velocity * gap / dt


@nb.njit(cache=True)
def phase_minv(s, M, uS, gap, Wt_all, WtB, bB, eps, blocks, factor, L, last_impulse,
               last_active):
    """Fig. 7 phase "M^-1" (the part that does not depend on the torques): factor M into
    L (unless factor is False: L already holds the factor of a constant M), the active set
    (see active_set), W^T = [W_U^T of the active contacts; W_B^T], M^{-1} W and
    b = [ε W_U^T u^S + gap terms; b_B] with ε_i = diag(ε_N,i, ε_T,i, ε_T,i) (eps: nc x 2), the
    normal rows' gap terms of normal_law_offset and b_B the bilateral drift stabilisation
    (β/Δt) g_B (zero in the paper's law), and the nonzero patterns of the rows of W^T and
    the columns of M^{-1} W.
    Returns (ok, active, Wt, MinvW, b, patterns, opened), the patterns of G still empty; ok
    is False if M is not positive definite; opened counts the loaded contacts that left the
    active set."""
    dt, beta_velocity = s.dt, s.beta_velocity
    nv = uS.shape[0]
    ok = True
    if factor:
        ok = cholesky_blocks(M, blocks, L)
    active, opened = active_set(gap, s, last_impulse, last_active)
    na = active.shape[0]
    nb_ = WtB.shape[0]
    o = 3 * na
    m = o + nb_
    Wt = np.empty((m, nv))
    MinvW = np.empty((nv, m))
    bvec = np.zeros(m)
    e = np.zeros(1, dtype=np.int64)
    if not ok or m == 0:
        return ok, active, Wt, MinvW, bvec, prox.Patterns(e, e[:0], e, e[:0], e, e[:0]), opened
    for a in range(na):
        i = active[a]
        for r in range(3):
            for j in range(nv):
                Wt[3 * a + r, j] = Wt_all[i, r, j]
    for a in range(nb_):
        for j in range(nv):
            Wt[o + a, j] = WtB[a, j]
    for a in range(m):
        for j in range(nv):
            MinvW[j, a] = Wt[a, j]
    cholesky_blocks_solve_cols(L, blocks, MinvW)
    for a in range(o):
        s = 0.0
        for j in range(nv):
            s += Wt[a, j] * uS[j]
        bvec[a] = eps[active[a // 3], 0 if a % 3 == 0 else 1] * s
    for a in range(na):
        bvec[3 * a] += normal_law_offset(gap[active[a]], dt, beta_velocity)
    for a in range(nb_):
        bvec[o + a] = bB[a]
    wp_ptr, wp_idx = prox.row_pattern(Wt)
    mp_ptr, mp_idx = prox.col_pattern(MinvW)
    return (ok, active, Wt, MinvW, bvec, prox.Patterns(wp_ptr, wp_idx, mp_ptr, mp_idx, e, e[:0]),
            opened)


@nb.njit(cache=True)
def phase_delassus(form, nc, bilateral_direct, Wt, MinvW, pat):
    """Fig. 7 phase "G (and G_B^-1)": G = W^T M^{-1} W (Delassus form) or only diag(G)
    (velocity form), and for the direct bilateral solution (Eqn. 20) the Cholesky factor
    of G_B = W_B^T M^{-1} W_B. Returns (ok, G, diag G, L_B, patterns): `pat` (the
    prox.Patterns of W^T and M^{-1}W) with the pattern of the rows of G."""
    wp_ptr, wp_idx, mp_ptr, mp_idx = pat.wp_ptr, pat.wp_idx, pat.mp_ptr, pat.mp_idx
    m, nv = Wt.shape
    o = 3 * nc
    nb_ = m - o
    Gdiag = np.empty(m)
    if form == prox.FORM_DELASSUS:
        G = np.empty((m, m))
        prox.delassus(Wt, MinvW, G, wp_ptr, wp_idx)
        for a in range(m):
            Gdiag[a] = G[a, a]
        gp_ptr, gp_idx = prox.row_pattern(G)
    else:
        G = np.empty((0, 0))
        prox.delassus_diagonal(Wt, MinvW, Gdiag, wp_ptr, wp_idx)
        gp_ptr = np.zeros(m + 1, dtype=np.int64)
        gp_idx = np.zeros(0, dtype=np.int64)
    full = prox.Patterns(wp_ptr, wp_idx, mp_ptr, mp_idx, gp_ptr, gp_idx)
    LB = np.zeros((0, 0))
    ok = True
    if bilateral_direct and nb_ > 0:
        GB = np.empty((nb_, nb_))
        if form == prox.FORM_DELASSUS:
            for a in range(nb_):
                for b in range(nb_):
                    GB[a, b] = G[o + a, o + b]
        else:
            for a in range(nb_):
                for b in range(a, nb_):
                    s = 0.0
                    for p in range(wp_ptr[o + a], wp_ptr[o + a + 1]):
                        s += Wt[o + a, wp_idx[p]] * MinvW[wp_idx[p], o + b]
                    GB[a, b] = s
                    GB[b, a] = s
        LB = np.zeros((nb_, nb_))
        ok = cholesky_upper_input(GB, LB)
    return ok, G, Gdiag, LB, full


@nb.njit(cache=True)
def constraint_velocity(Wt, u_free, bvec, wp_ptr, wp_idx):
    """c = W^T u_free + b (Eqn. 15), with the row pattern of W^T."""
    m = Wt.shape[0]
    c = np.empty(m)
    for a in range(m):
        s = bvec[a]
        for p in range(wp_ptr[a], wp_ptr[a + 1]):
            s += Wt[a, wp_idx[p]] * u_free[wp_idx[p]]
        c[a] = s
    return c


@nb.njit(cache=True)
def phase_prox(s, p, u_free, c, M, last_impulse, last_active, last_bilateral):
    """Fig. 7 phase "u^E" of the problem p (a ContactProblem) with c = W^T u_free + b: warm
    start (the last step's impulses of contacts that stay active, and of the bilateral
    constraints), the prox iteration, and one retry with α·s.fallback_alpha_factor if it
    did not converge. Returns (u^E, Λ, iterations, status, residual, retried)."""
    active = p.active
    alpha = s.alpha
    fallback_factor = s.fallback_alpha_factor
    na = active.shape[0]
    o = 3 * na
    m = c.shape[0]
    nv = u_free.shape[0]
    lam0 = np.zeros(m)
    if s.warm_start:
        for a in range(na):
            i = active[a]
            if last_active[i]:
                for k in range(3):
                    lam0[3 * a + k] = last_impulse[i, k]
        for a in range(m - o):
            lam0[o + a] = last_bilateral[a]
    mu_vec = np.full(na, s.mu)
    attempts = 2 if fallback_factor > 0.0 else 1
    r = np.empty(m)
    u = np.empty(nv)
    lam = lam0.copy()
    iters = 0
    status = prox.STATUS_CONVERGED
    resid = 0.0
    retried = False
    for attempt in range(attempts):
        prox.prox_parameters(p.Gdiag, na, alpha, r)
        lam[:] = lam0
        it, status, resid = prox.prox_solve(s, p.pat, p.Wt, p.MinvW, u_free, p.b, p.G, c, na,
                                            mu_vec, r, lam, p.LB, M, u)
        iters += it
        if status == prox.STATUS_CONVERGED:
            break
        if attempt + 1 < attempts:
            retried = True
            alpha *= fallback_factor
    return u, lam, iters, status, resid, retried


#: the post-step projection runs when a contact's predicted end gap is below
#: −PROJECTION_TOLERANCE [m]: 1 µm, 100x below what the eye or a controller notices, and
#: above the noise of the prox solver's tolerance at rest (at 10 nm it ran on 45 % of the
#: steps of a robot standing still; at 1 µm on none, and on the touchdowns of a trot)
PROJECTION_TOLERANCE = 1e-6
#: contacts up to this far above the ground at q^M are checked for penetration at the end of
#: the step [m] (a foot approaching at 4 m/s moves 5 mm in ½Δt = 1.25 ms)
PROJECTION_LOOKAHEAD = 5e-3


@nb.njit(cache=True)
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


@nb.njit(cache=True)
def projection_problem(Wt, MinvW, active, extra, Wt_all, blocks, L):
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
    cholesky_blocks_solve_cols(L, blocks, cols)
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
    return contacts, Wp, Mp, prox.Patterns(wp_ptr, wp_idx, mp_ptr, mp_idx, e, e[:0])


@nb.njit(cache=True)
def phase_projection(s, p, is_active, gap, Wt_all, blocks, L, M, uE, u_corr):
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
    gE = np.empty(nc)
    worst = predicted_end_gaps(gap, Wt_all, s.jacobian_gap, is_active, uE, dt, gE)
    if worst >= -tolerance or beta == 0.0:
        return 0, -1
    extra = np.nonzero(~is_active & (gE < -tolerance))[0]
    if extra.shape[0] == 0:
        contacts = active
        Wp, Mp, Gp, Gdp, full = p.Wt, p.MinvW, p.G, p.Gdiag, p.pat
    else:
        contacts, Wp, Mp, part = projection_problem(p.Wt, p.MinvW, active, extra, Wt_all,
                                                    blocks, L)
        _, Gp, Gdp, _, full = phase_delassus(s.form, contacts.shape[0], False, Wp, Mp, part)
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


@nb.njit(cache=True)
def contact_problem(s, M, uS, gap, Wt_all, WtB, bB, eps, blocks, factor, L, last_impulse,
                    last_active, timings):
    """The torque-independent part of the hard-contact solve for the StepSettings s: the
    phases "M^-1" and "G" (phase_minv, phase_delassus), timed into `timings` when
    profiling. Returns the ContactProblem."""
    t = clock(timings)
    ok, active, Wt, MinvW, bvec, pat, opened = phase_minv(
        s, M, uS, gap, Wt_all, WtB, bB, eps, blocks, factor, L, last_impulse, last_active)
    t = lap(timings, PHASE_M_INVERSE, t)
    G, Gdiag, LB = np.zeros((0, 0)), np.zeros(0), np.zeros((0, 0))
    if ok and Wt.shape[0] != 0:
        ok, G, Gdiag, LB, pat = phase_delassus(s.form, active.shape[0], s.bilateral_direct,
                                               Wt, MinvW, pat)
    lap(timings, PHASE_G, t)
    return ContactProblem(ok, active, Wt, MinvW, bvec, G, Gdiag, LB, pat, opened)


@nb.njit(cache=True)
def prepare_hard_contacts(settings, M, uS, gap, Wt_all, WtB, bB, eps, blocks, factor, L,
                          last_impulse, last_active, timings):
    """contact_problem for a caller that prepares ahead (MoreauStepper.prepare).
    `settings`: the fields of a StepSettings (a plain tuple will do). Returns the
    ContactProblem as problem_fields' tuple, the input of complete_hard_contacts."""
    return problem_fields(contact_problem(StepSettings(*settings), M, uS, gap, Wt_all, WtB,
                                          bB, eps, blocks, factor, L, last_impulse,
                                          last_active, timings))


@nb.njit(cache=True)
def complete_problem(s, p, h, uS, M, blocks, L, gap, Wt_all, last_impulse, last_active,
                     last_bilateral, impulse, is_active, u_free, u, u_corr, timings):
    """The torque-dependent rest of the hard-contact solve of the ContactProblem p for the
    StepSettings s: u_free = u^S + M^{-1} h Δt (phase "M^-1"),
    c = W^T u_free + b (phase "G"), the prox iteration (phase_prox) and the post-step
    projection (phase_projection; both phase "prox"), timed into `timings` when
    profiling. Writes Λ_U of every contact point into impulse (nc x 3), the active flags,
    Λ_B into last_bilateral, u^E into u and the projection's Δu_p into u_corr; unless the
    result is non-finite, the warm-start memory (last_impulse, last_active) is updated.
    Returns (iterations, status, residual, retried, projection iterations, projection
    status)."""
    t = clock(timings)
    free_velocity(h, s.dt, uS, blocks, L, u_free)
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
        c = constraint_velocity(p.Wt, u_free, p.b, p.pat.wp_ptr, p.pat.wp_idx)
        t = lap(timings, PHASE_G, t)
        uE, lam, it, status, resid, retried = phase_prox(s, p, u_free, c, M, last_impulse,
                                                         last_active, last_bilateral)
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
        pit, pstatus = phase_projection(s, p, is_active, gap, Wt_all, blocks, L, M, u, u_corr)
        lap(timings, PHASE_PROX, t)
    if status != prox.STATUS_NONFINITE:
        for i in range(nc):
            last_active[i] = is_active[i]
            for k in range(3):
                last_impulse[i, k] = impulse[i, k]
    return it, status, resid, retried, pit, pstatus




@nb.njit(cache=True)
def complete_hard_contacts(settings, problem, h, uS, M, blocks, L, gap, Wt_all, last_impulse,
                           last_active, last_bilateral, impulse, is_active, u_free, u, u_corr,
                           timings):
    """complete_problem of a prepared problem (problem_fields' tuple from
    prepare_hard_contacts; `settings`: the fields of a StepSettings)."""
    return complete_problem(StepSettings(*settings), problem_from_fields(problem), h, uS, M,
                            blocks, L, gap, Wt_all, last_impulse, last_active, last_bilateral,
                            impulse, is_active, u_free, u, u_corr, timings)


@nb.njit(cache=True)
def solve_hard_contacts(settings, M, uS, gap, Wt_all, WtB, bB, eps, blocks, factor, L, h,
                        last_impulse, last_active, last_bilateral, impulse, is_active, u_free,
                        u, u_corr, timings):
    """contact_problem and complete_problem in one call, for a step that was not prepared
    ahead: the same arithmetic as prepare_hard_contacts then complete_hard_contacts (so the
    same result bit for bit), without the problem's arrays crossing into Python and back
    (≈1 µs per array, measured). Returns (ok, |I|, opened, iterations, status, residual,
    retried, projection iterations, projection status); with ok False (M or G_B not
    positive definite) nothing else was done."""
    s = StepSettings(*settings)
    p = contact_problem(s, M, uS, gap, Wt_all, WtB, bB, eps, blocks, factor, L, last_impulse,
                        last_active, timings)
    if not p.ok:
        return False, 0, 0, 0, prox.STATUS_CONVERGED, 0.0, False, 0, -1
    it, status, resid, retried, pit, pstatus = complete_problem(
        s, p, h, uS, M, blocks, L, gap, Wt_all, last_impulse, last_active, last_bilateral,
        impulse, is_active, u_free, u, u_corr, timings)
    return True, p.active.shape[0], p.opened, it, status, resid, retried, pit, pstatus


#: tree_step_* outcomes (the first entry of their result)
TREE_STEP_OK, TREE_STEP_NOT_PD, TREE_STEP_NONFINITE_IMPULSE, TREE_STEP_NONFINITE_STATE = range(4)


class TreeStepModel(NamedTuple):
    """The model, ground and workspace arrays of the one-kernel step (tree_step_hard /
    tree_step_compliant) packed into four buffers, so that a call from Python unboxes four
    arrays instead of some thirty (≈0.1 µs each per call, measured). The packing is pure
    layout: the kernels take views of the buffers (unpack_tree_model) and compute exactly
    what the phase-by-phase path computes.

    floats: axis, pl_R, pl_p, oR, op (the forward kinematics' scratch), mass, lever,
    inertia, gravity, c_local, c_radius (the forest's arrays, midpoint_model order), the
    ground's n, t1, t2 and offset, ε per contact (nc x 2); ints: [nj, nc, number of
    actuated joints, number of blocks], then parent, jtype, idx_q, idx_v, c_joint, joint_v
    and the blocks of M (rows of (start, size)); support: the tree's support matrix;
    workspace: g_N (nc), contact points (nc x 3), W^T of every contact (nc x 3 x nv), the
    factor L of M (nv x nv), u_free and Δu_p (nv each)."""

    floats: np.ndarray
    ints: np.ndarray
    support: np.ndarray
    workspace: np.ndarray

    @staticmethod
    def pack(model, ground, eps, joint_v, blocks, nv):
        """Packs midpoint_model()'s arrays, the GroundPlane and ε; returns the record and
        the workspace's views (gap, position, Wt_all, L, u_free, u_corr), which the stepper
        keeps as its own arrays."""
        (parent, jtype, axis, pl_R, pl_p, idx_q, idx_v, support, oR, op, mass, lever,
         inertia, gravity, c_joint, c_local, c_radius) = model
        floats = np.concatenate([np.ravel(a).astype(np.float64) for a in (
            axis, pl_R, pl_p, oR, op, mass, lever, inertia, gravity, c_local, c_radius,
            ground.n, ground.t1, ground.t2, [ground.offset], eps)])
        nj, nc = parent.shape[0], c_joint.shape[0]
        ints = np.concatenate([np.ravel(a).astype(np.int64) for a in (
            [nj, nc, joint_v.shape[0], blocks.shape[0]], parent, jtype, idx_q, idx_v,
            c_joint, joint_v, blocks)])
        sizes = (nc, 3 * nc, 3 * nc * nv, nv * nv, nv, nv)
        workspace = np.zeros(sum(sizes))
        views, o = [], 0
        for n in sizes:
            views.append(workspace[o:o + n])
            o += n
        gap, position, Wt_all, L, u_free, u_corr = views
        return (TreeStepModel(floats, ints, np.ascontiguousarray(support), workspace),
                (gap, position.reshape(nc, 3), Wt_all.reshape(nc, 3, nv), L.reshape(nv, nv),
                 u_free, u_corr))


@nb.njit(cache=True, inline="always")
def _take(buf, o, n):
    return buf[o:o + n], o + n


@nb.njit(cache=True)
def unpack_tree_model(floats, ints, support, workspace, nv):
    """The views of TreeStepModel's buffers: (model (midpoint_model's order), normal,
    tangent1, tangent2, ground_offset, eps, joint_v, blocks, gap, position, Wt_all, L,
    u_free, u_corr)."""
    nj, nc, na, nbk = ints[0], ints[1], ints[2], ints[3]
    o = 0
    axis, o = _take(floats, o, 3 * nj)
    pl_R, o = _take(floats, o, 9 * nj)
    pl_p, o = _take(floats, o, 3 * nj)
    oR, o = _take(floats, o, 9 * nj)
    op, o = _take(floats, o, 3 * nj)
    mass, o = _take(floats, o, nj)
    lever, o = _take(floats, o, 3 * nj)
    inertia, o = _take(floats, o, 9 * nj)
    gravity, o = _take(floats, o, 3)
    c_local, o = _take(floats, o, 3 * nc)
    c_radius, o = _take(floats, o, nc)
    normal, o = _take(floats, o, 3)
    tangent1, o = _take(floats, o, 3)
    tangent2, o = _take(floats, o, 3)
    offset, o = _take(floats, o, 1)
    eps, o = _take(floats, o, 2 * nc)
    k = 4
    parent, k = _take(ints, k, nj)
    jtype, k = _take(ints, k, nj)
    idx_q, k = _take(ints, k, nj)
    idx_v, k = _take(ints, k, nj)
    c_joint, k = _take(ints, k, nc)
    joint_v, k = _take(ints, k, na)
    blocks, k = _take(ints, k, 2 * nbk)
    w = 0
    gap, w = _take(workspace, w, nc)
    position, w = _take(workspace, w, 3 * nc)
    Wt_all, w = _take(workspace, w, 3 * nc * nv)
    L, w = _take(workspace, w, nv * nv)
    u_free, w = _take(workspace, w, nv)
    u_corr, w = _take(workspace, w, nv)
    model = (parent, jtype, axis.reshape((nj, 3)), pl_R.reshape((nj, 3, 3)),
             pl_p.reshape((nj, 3)), idx_q, idx_v, support, oR.reshape((nj, 3, 3)),
             op.reshape((nj, 3)), mass, lever.reshape((nj, 3)), inertia.reshape((nj, 3, 3)),
             gravity, c_joint, c_local.reshape((nc, 3)), c_radius)
    return (model, normal, tangent1, tangent2, offset[0], eps.reshape((nc, 2)), joint_v,
            blocks.reshape((nbk, 2)), gap, position.reshape((nc, 3)),
            Wt_all.reshape((nc, 3, nv)), L.reshape((nv, nv)), u_free, u_corr)


@nb.njit(cache=True, inline="always")
def _midpoint_with_forces(q, u, half_dt, tau, joint_v, f_ext, normal, tangent1, tangent2,
                          ground_offset, jacobian_gap, gap, position, Wt_all, model):
    """q^M, M and h at (q^M, u^S) of a tree without cut joints (midpoint_dynamics), then
    h += Sᵀτ (τ in the public order, joint_v its velocity indices) + f_ext (when given):
    the same arithmetic, in the same order, as ForestCoordinates.midpoint followed by
    add_joint_torques and h += f_ext."""
    nv = u.shape[0]
    qM = np.empty_like(q)
    M = np.empty((nv, nv))
    h = np.empty(nv)
    midpoint_dynamics(q, u, half_dt, *model, normal, tangent1, tangent2, ground_offset,
                      jacobian_gap, qM, M, h, gap, position, Wt_all)
    for k in range(tau.shape[0]):
        h[joint_v[k]] += tau[k]
    for k in range(f_ext.shape[0]):
        h[k] += f_ext[k]
    return qM, M, h


@nb.njit(cache=True)
def tree_step_hard(settings, q, u, tau, f_ext, last_impulse, last_active, last_bilateral,
                   impulse, is_active, qE, uE, floats, ints, support, workspace):
    """One whole step with hard contacts of a coordinate set without bilateral constraints
    and with a configuration-dependent M (the minimal coordinates), in one call from Python:
    Eqn. (6) and M, h, W at the midpoint (_midpoint_with_forces), the contact problem
    (contact_problem, complete_problem) and Eqn. (8) (end_of_step). The same arithmetic as
    the phase-by-phase path of MoreauStepper.step, so the same result bit for bit; it saves
    the calls between the phases and the Python around them. `settings`: the fields of a
    StepSettings; (floats, ints, support, workspace): a TreeStepModel; f_ext: the
    generalized external force or an empty array. Writes q^E, u^E, Λ (impulse), the active
    flags and the workspace; the warm-start memory is updated as by complete_problem, but
    only when the step succeeds (outcome TREE_STEP_OK; no bilateral memory here): a failed
    step leaves the state as it was. Returns (outcome (TREE_STEP_*), |I|, opened, iterations, status, residual, retried,
    projection iterations, projection status)."""
    s = StepSettings(*settings)
    nv = u.shape[0]
    (model, normal, tangent1, tangent2, offset, eps, joint_v, blocks, gap, position, Wt_all,
     L, u_free, u_corr) = unpack_tree_model(floats, ints, support, workspace, nv)
    half_dt = 0.5 * s.dt
    qM, M, h = _midpoint_with_forces(q, u, half_dt, tau, joint_v, f_ext, normal, tangent1,
                                     tangent2, offset, s.jacobian_gap, gap, position,
                                     Wt_all, model)
    p = contact_problem(s, M, u, gap, Wt_all, np.zeros((0, nv)), np.zeros(0), eps, blocks,
                        True, L, last_impulse, last_active, None)
    if not p.ok:
        return TREE_STEP_NOT_PD, 0, 0, 0, prox.STATUS_CONVERGED, 0.0, False, 0, -1
    kept_impulse, kept_active = last_impulse.copy(), last_active.copy()
    it, status, resid, retried, pit, pstatus = complete_problem(
        s, p, h, u, M, blocks, L, gap, Wt_all, last_impulse, last_active, last_bilateral,
        impulse, is_active, u_free, uE, u_corr, None)
    outcome = TREE_STEP_OK
    if status == prox.STATUS_NONFINITE:     # (complete_problem left the memory as it was)
        outcome = TREE_STEP_NONFINITE_IMPULSE
    elif not end_of_step(qM, uE, u_corr, pstatus >= 0, half_dt, model[1], model[5],
                         model[6], qE):
        outcome = TREE_STEP_NONFINITE_STATE     # the memory back to what it was
        last_impulse[:] = kept_impulse
        last_active[:] = kept_active
    return (outcome, p.active.shape[0], p.opened, it, status, resid, retried, pit, pstatus)


@nb.njit(cache=True)
def tree_step_compliant(law, dt, jacobian_gap, q, u, tau, f_ext, closed, slip, anchor, lam,
                        qE, uE, floats, ints, support, workspace):
    """tree_step_hard's counterpart for compliant contacts (Alg. 1; `law`: the fields of a
    CompliantLaw): the midpoint, solve_compliant (u^E = u_free) and Eqn. (8), the same
    arithmetic as the phase-by-phase path; a failed step leaves the contact state as it
    was. Returns an outcome (TREE_STEP_*)."""
    nv = u.shape[0]
    (model, normal, tangent1, tangent2, offset, eps, joint_v, blocks, gap, position, Wt_all,
     L, u_free, u_corr) = unpack_tree_model(floats, ints, support, workspace, nv)
    half_dt = 0.5 * dt
    qM, M, h = _midpoint_with_forces(q, u, half_dt, tau, joint_v, f_ext, normal, tangent1,
                                     tangent2, offset, jacobian_gap, gap, position, Wt_all,
                                     model)
    kept = (closed.copy(), slip.copy(), anchor.copy(), lam.copy())
    if not solve_compliant(law, M, h, u, dt, gap, position, Wt_all, closed, slip, anchor,
                           tangent1, tangent2, lam, blocks, True, L, u_free, None):
        outcome = TREE_STEP_NOT_PD
    else:
        for k in range(nv):
            uE[k] = u_free[k]
        outcome = TREE_STEP_OK
        if not end_of_step(qM, uE, u_corr, False, half_dt, model[1], model[5], model[6], qE):
            outcome = TREE_STEP_NONFINITE_STATE
    if outcome != TREE_STEP_OK:     # the contact state back to what it was
        closed[:] = kept[0]
        slip[:] = kept[1]
        anchor[:] = kept[2]
        lam[:] = kept[3]
    return outcome


@nb.njit(cache=True)
def end_of_step(qM, uE, u_corr, projected, half_dt, jtype, idx_q, idx_v, qE):
    """Eqn. (8): q^E = q^M ⊕ ½Δt F(q^M) (u^E + Δu_p) (Δu_p = u_corr of the post-step
    projection when it ran, else 0) into qE. False if q^E or u^E is not finite."""
    if projected:
        v = uE + u_corr
    else:
        v = uE
    integrate_forest(qM, v, half_dt, jtype, idx_q, idx_v, qE)
    return all_finite(qE, uE)


@nb.njit(cache=True)
def all_finite(a, b):
    for k in range(a.shape[0]):
        if not np.isfinite(a[k]):
            return False
    for k in range(b.shape[0]):
        if not np.isfinite(b[k]):
            return False
    return True


@dataclass(slots=True)
class StepResult:
    """What one physics step did (all arrays over every contact point of the model)."""

    #: bool per contact: hard contacts, in the active set I at q^M (active_set:
    #: g_N ≤ contact.activation_gap, 0 in the presets; with contact.activation
    #: "hysteresis" also loaded in the last step and g_N ≤ contact.opening_gap);
    #: compliant contacts, closed (g_N(q^M) ≤ 0)
    active: np.ndarray
    gap: np.ndarray             # g_N at q^M [m]
    impulse: np.ndarray         # Λ (nc x 3) in the contact frame (N, T1, T2) [N s]
    iterations: int = 0
    status: int = prox.STATUS_CONVERGED
    residual: float = 0.0
    retried: bool = False
    position: np.ndarray | None = None   # contact points at q^M (nc x 3) [m]
    n_active: int = 0                    # contacts in the active set
    opened_loaded: int = 0               # contacts loaded in the last step, not in the set
    projection_iterations: int = 0       # post-step projection (0: it did not run)
    projected: bool = False              # the post-step projection ran


@dataclass
class StepperStats:
    steps: int = 0
    nonconverged: int = 0
    retried: int = 0
    projections: int = 0        # steps with a post-step projection
    timings: np.ndarray = field(default_factory=lambda: np.zeros(len(PHASES)))


class MoreauStepper:
    """Midpoint time-stepper shared by all coordinate sets and both contact models. It
    holds the model side and a workspace; the state it advances is a `SimState`."""

    def __init__(self, coords, config, profile: bool = False):
        self.coords = coords
        self.cfg = config
        self.profile = profile
        self.ground = GroundPlane(config.ground.height, tuple(config.ground.normal),
                                  config.ground.mu)
        self.dt = config.dt
        self.hard = config.contact_model == "hard"
        c = config.contact
        self.activation_gap = c.activation_gap if self.hard else 0.0
        self.hysteresis = self.hard and c.activation == "hysteresis"
        beta_n = c.penetration_stabilization if self.hard else 0.0
        self.beta_velocity = beta_n if c.penetration_correction == "velocity" else 0.0
        self.beta_projection = beta_n if c.penetration_correction == "projection" else 0.0
        #: contact Jacobians are needed up to the largest gap at which a contact can be
        #: active, or be predicted to end the step below the ground (projection)
        self.jacobian_gap = max(self.activation_gap,
                                c.opening_gap if self.hysteresis else 0.0,
                                PROJECTION_LOOKAHEAD if self.beta_projection > 0 else 0.0)
        nc, nv = coords.n_contacts, coords.nv
        self.nc, self.nv = nc, nv
        self.nb = coords.n_bilateral
        # -- workspace: recomputed by every step (see starleth_sim.physics.state)
        self.gap = np.zeros(nc)               # g_N at q^M [m]
        self.position = np.zeros((nc, 3))     # contact points at q^M [m]
        self.Wt_all = np.zeros((nc, 3, nv))   # W^T of every contact (rows n, t1, t2)
        self.L = np.zeros((nv, nv))           # Cholesky factor of M
        self.u_free = np.zeros(nv)            # u^S + M^{-1} h Δt
        self.u_corr = np.zeros(nv)            # Δu_p of the post-step projection
        self.bB = np.zeros(self.nb)           # (β/Δt) g_B
        self._factored = False                # L holds the factor of a constant M
        self._prepared = None                 # see prepare
        # -- model
        self.blocks = coords.blocks
        self.constant_M = coords.constant_mass_matrix
        self.no_bilateral = np.zeros((0, nv))
        self.beta = config.bilateral.stabilization
        s = config.solver
        self.form = prox.FORMS[s.form]
        self.scheme = prox.SCHEMES[s.scheme]
        self.criterion = prox.CRITERIA[s.criterion]
        self.bilateral_direct = config.bilateral.method == "direct"
        #: the kernels' settings (and, for the two kernels Python calls, their fields as a
        #: plain tuple: see the module docstring)
        self.settings = StepSettings(
            activation_gap=float(self.activation_gap), mu=float(config.ground.mu),
            alpha=prox.alpha_setting(s.alpha),      # solver.alpha: auto -> prox.ALPHA_AUTO
            tol_rel=float(s.tol_rel), tol_abs=float(s.tol_abs),
            fallback_alpha_factor=float(s.fallback_alpha_factor),
            opening_gap=float(c.opening_gap), dt=float(self.dt),
            beta_velocity=float(self.beta_velocity),
            beta_projection=float(self.beta_projection),
            jacobian_gap=float(self.jacobian_gap),
            projection_tolerance=float(PROJECTION_TOLERANCE), form=int(self.form),
            scheme=int(self.scheme), max_iterations=int(s.max_iterations),
            criterion=int(self.criterion), warm_start=bool(s.warm_start),
            bilateral_direct=bool(self.bilateral_direct), hysteresis=bool(self.hysteresis))
        self._settings_fields = tuple(self.settings)
        self.compliant_law = CompliantLaw(
            mu=float(config.ground.mu), c_N=float(c.stiffness_normal),
            d_N=float(c.damping_normal), c_T=float(c.stiffness_tangential),
            d_T=float(c.damping_tangential), slip_velocity=float(c.slip_velocity))
        self._compliant_law_fields = tuple(self.compliant_law)
        #: Newton-type impact law per contact: (ε_N, ε_T), defaults overridden by name
        self.eps = np.tile([c.restitution_normal, c.restitution_tangential], (nc, 1))
        names = list(coords.contact_names)
        for name, (en, et) in c.restitution_overrides.items():
            if name not in names:
                raise ConfigError(f"contact.restitution_overrides: unknown contact '{name}' "
                                  f"(contacts: {', '.join(names)})")
            self.eps[names.index(name)] = (en, et)
        self._never_active = np.full(nc, np.inf)
        self.stats = StepperStats()
        #: an unprepared, unprofiled step of a set without bilateral constraints whose M
        #: depends on q (the minimal coordinates) runs as one kernel (tree_step_hard /
        #: tree_step_compliant); the others phase by phase
        self._one_kernel = (not coords.constant_mass_matrix and self.nb == 0
                            and getattr(coords, "n_cut", 1) == 0)
        self._no_force = np.zeros(0)
        if self._one_kernel:    # the workspace arrays become views of the packed buffer
            pack, views = TreeStepModel.pack(coords.midpoint_model(), self.ground, self.eps,
                                             coords.joint_v, coords.blocks, nv)
            self._tree_model = tuple(pack)
            self.gap, self.position, self.Wt_all, self.L, self.u_free, self.u_corr = views

    def initial_state(self, q, u, t: float = 0.0) -> SimState:
        """The state (q, u, t) without contact memory or pending wrenches."""
        return SimState.initial(q, u, t, self.nc, self.nb, self.hard)


    # -- one step -------------------------------------------------------------------------
    def _midpoint(self, q, u, timings):
        """q^M (Eqn. 6), M and h without τ at (q^M, u^S), the contact kinematics (gap,
        position, W^T of the contacts within jacobian_gap) and the bilateral W_B^T, b_B at
        q^M. Returns (q^M, M, h, W_B^T)."""
        dt = self.dt
        coords = self.coords
        t = clock(timings)
        # (the contact kinematics share the forward kinematics of M and h: phase "M and h")
        qM, M, h0 = coords.midpoint(q, u, dt, self.ground, self.gap, self.position,
                                    self.Wt_all, self.jacobian_gap)
        t = lap(timings, PHASE_M_AND_H, t)
        if self.nb:
            WtB, gB = coords.bilateral(qM)
            np.multiply(gB, self.beta / dt, out=self.bB)
        else:
            WtB = self.no_bilateral
        lap(timings, PHASE_REST, t)
        return qM, M, h0, WtB

    def _factor(self, M, timings):
        """The block Cholesky factor of M into L (kept while M is constant). False if M is
        not positive definite."""
        if self.constant_M and self._factored:
            return True
        t = clock(timings)
        ok = cholesky_blocks(M, self.blocks, self.L)
        lap(timings, PHASE_M_INVERSE, t)
        self._factored = ok
        return ok

    def prepare(self, state: SimState):
        """The part of the step from (q^S, u^S) = (state.q, state.u) that does not depend on
        the joint torques or external forces: q^M (Eqn. 6), M and h without τ, the contact
        and bilateral kinematics at q^M, the factor of M and, with hard contacts, M^{-1}W and
        G (the active set reads the state's contact memory). `step` uses it when called with
        a state holding the same q and u objects (which must not be modified in place in
        between), else it does the same arithmetic itself (in one kernel with the rest of
        the step, solve_hard_contacts), so the result is the same bit for bit either way. A
        lockstep node calls this after publishing a state, while the controller works on
        its answer. Never raises: a failure is reported by the step that uses it."""
        q, u = state.q, state.u
        timings = self.stats.timings if self.profile else None
        qM, M, h0, WtB = self._midpoint(q, u, timings)
        problem = None
        if self.hard or self.nb:    # compliant contacts: the prox solve of the bilaterals
            factor = not (self.constant_M and self._factored)
            gap = self.gap if self.hard else self._never_active
            problem = prepare_hard_contacts(self._settings_fields, M, u, gap, self.Wt_all,
                                            WtB, self.bB, self.eps, self.blocks, factor,
                                            self.L, state.last_impulse, state.last_active,
                                            timings)
            ok = problem[0]
            if ok:
                self._factored = True
        else:
            ok = self._factor(M, timings)
        self._prepared = (q, u, qM, M, h0, ok, problem, WtB)

    def step(self, state: SimState, tau, f_ext=None) -> "StepResult":
        """Advance state by Δt with joint torques tau (public joint order) and an optional
        generalized external force f_ext: state.q and state.u become q^E and u^E, and the
        contact memory is updated (state.t is the caller's). Returns the StepResult. On a
        SimulationError, q and u are unchanged but the contact memory may not be (the
        Simulator restores its snapshot)."""
        prof = self.profile
        p = self._prepared
        self._prepared = None
        prepared = p is not None and p[0] is state.q and p[1] is state.u
        if self._one_kernel and not prepared and not prof:
            return self._step_one_kernel(state, tau, f_ext)
        timings = self.stats.timings if prof else None
        if prepared:
            _, u, qM, M, h, ok, problem, WtB = p
        else:   # not prepared ahead: the rest of the step runs in one kernel
            u = state.u
            qM, M, h, WtB = self._midpoint(state.q, u, timings)
            problem = None
            ok = True
        if not ok:
            raise SimulationError("mass matrix (or G_B) not positive definite "
                                  "(non-finite state?)")
        dt = self.dt
        coords = self.coords
        t = clock(timings) if prof else 0.0
        if tau is not None and tau.shape[0]:
            coords.add_joint_torques(qM, u, tau, h)
        if f_ext is not None:
            h += f_ext
        if prof:
            lap(timings, PHASE_M_AND_H, t)
        if self.hard:
            uE, res = self._solve(state, M, h, u, problem, WtB, timings)
        else:
            uE, res = self._solve_compliant(state, M, h, u, problem, WtB, prepared, timings)
        t = clock(timings) if prof else 0.0
        # Eqn. (8); with a post-step projection, the positions move by ½Δt Δu_p more
        qE = np.empty_like(qM)
        tree = coords.tree
        if not end_of_step(qM, uE, self.u_corr, res.projected, 0.5 * dt, tree.jtype,
                           tree.idx_q, tree.idx_v, qE):
            raise SimulationError("non-finite state after the step; state left unchanged")
        state.q, state.u = qE, uE
        self.stats.steps += 1
        if prof:
            lap(timings, PHASE_REST, t)
        return res

    def step_is_transactional(self, state: SimState) -> bool:
        """Whether the next `step` of `state`, should it fail (SimulationError), leaves the
        state as it was: so it does when it runs in one kernel (not prepared ahead, not
        profiling); the phase-by-phase path may have updated the contact memory, so its
        caller keeps a copy to restore."""
        p = self._prepared
        return self._one_kernel and not self.profile and not (
            p is not None and p[0] is state.q and p[1] is state.u)

    def _step_one_kernel(self, state, tau, f_ext):
        """`step` in one kernel call (tree_step_hard / tree_step_compliant): the same
        result bit for bit as the phase-by-phase path, for the sets it serves (see
        _one_kernel)."""
        q, u = state.q, state.u
        qE = np.empty_like(q)
        uE = np.empty_like(u)
        if tau is None:
            tau = self._no_force
        if f_ext is None:
            f_ext = self._no_force
        if self.hard:
            nc = self.nc
            impulse = np.empty((nc, 3))
            is_active = np.empty(nc, dtype=np.bool_)
            outcome, n_active, opened, it, status, resid, retried, pit, pstatus = \
                tree_step_hard(self._settings_fields, q, u, tau, f_ext, state.last_impulse,
                               state.last_active, state.last_bilateral, impulse, is_active,
                               qE, uE, *self._tree_model)
        else:
            outcome = tree_step_compliant(
                self._compliant_law_fields, self.dt, self.jacobian_gap, q, u, tau, f_ext,
                state.closed, state.slip, state.anchor, state.lam_compliant, qE, uE,
                *self._tree_model)
        if outcome == TREE_STEP_NOT_PD:
            raise SimulationError("mass matrix (or G_B) not positive definite "
                                  "(non-finite state?)")
        self._factored = True
        if self.hard:
            if retried:
                self.stats.retried += 1
            if status != prox.STATUS_CONVERGED:
                self.stats.nonconverged += 1
            if outcome == TREE_STEP_NONFINITE_IMPULSE:
                raise SimulationError("prox iteration produced non-finite impulses; "
                                      "state left unchanged")
            if pstatus >= 0:
                self.stats.projections += 1
        if outcome == TREE_STEP_NONFINITE_STATE:
            raise SimulationError("non-finite state after the step; state left unchanged")
        state.q, state.u = qE, uE
        self.stats.steps += 1
        if self.hard:
            return StepResult(is_active, self.gap.copy(), impulse, it, status, resid, retried,
                              self.position.copy(), n_active, opened, pit, pstatus >= 0)
        active = self.gap <= 0.0
        return StepResult(active, self.gap.copy(), state.lam_compliant * self.dt,
                          position=self.position.copy(),
                          n_active=int(np.count_nonzero(active)))

    def _solve_compliant(self, state, M, h, uS, problem, WtB, prepared, timings):
        """Alg. 1: the compliant forces at (q^M, u^S) join h; then u^E by the prox solve of
        the bilateral constraints, or u^E = u_free without them (solve_compliant, which
        also factors M unless the step was prepared)."""
        dt = self.dt
        law = self._compliant_law_fields
        t1, t2 = self.ground.t1, self.ground.t2
        if self.nb:  # bilateral constraints still need the prox solve (no contact rows)
            prof = timings is not None
            t = clock(timings) if prof else 0.0
            compliant_contact_forces(law, self.gap, self.position, self.Wt_all, uS,
                                     state.closed, state.slip, state.anchor, t1, t2,
                                     state.lam_compliant)
            generalized_contact_force(self.Wt_all, state.lam_compliant, h)
            if prof:
                lap(timings, PHASE_REST, t)
            uE, res = self._solve(state, M, h, uS, problem, WtB, timings)
        else:
            factor = not prepared and not (self.constant_M and self._factored)
            if not solve_compliant(law, M, h, uS, dt, self.gap, self.position, self.Wt_all,
                                   state.closed, state.slip, state.anchor, t1, t2,
                                   state.lam_compliant, self.blocks, factor, self.L,
                                   self.u_free, timings):
                raise SimulationError("mass matrix not positive definite (non-finite state?)")
            if factor:
                self._factored = True
            uE, res = self.u_free.copy(), StepResult(None, None, None)
        active = self.gap <= 0.0
        res.active = active
        res.n_active = int(np.count_nonzero(active))
        res.gap = self.gap.copy()
        res.position = self.position.copy()
        res.impulse = state.lam_compliant * dt
        return uE, res

    def _solve(self, state, M, h, uS, problem, WtB, timings):
        """u^E of the hard-contact (or bilateral) problem, prepared (`problem`: the tuple of
        prepare_hard_contacts) or, with problem None, set up and solved in one kernel
        (solve_hard_contacts, with W_B^T of the midpoint); the warm-start memory of `state`
        updated."""
        nc = self.nc
        impulse = np.empty((nc, 3))
        is_active = np.empty(nc, dtype=np.bool_)
        u = np.empty(self.nv)
        gap = self.gap if self.hard else self._never_active
        if problem is None:
            factor = not (self.constant_M and self._factored)
            ok, n_active, opened, it, status, resid, retried, pit, pstatus = \
                solve_hard_contacts(self._settings_fields, M, uS, gap, self.Wt_all, WtB,
                                    self.bB, self.eps, self.blocks, factor, self.L, h,
                                    state.last_impulse, state.last_active,
                                    state.last_bilateral, impulse, is_active, self.u_free, u,
                                    self.u_corr, timings)
            if not ok:
                raise SimulationError("mass matrix (or G_B) not positive definite "
                                      "(non-finite state?)")
            self._factored = True
        else:
            it, status, resid, retried, pit, pstatus = complete_hard_contacts(
                self._settings_fields, problem, h, uS, M, self.blocks, self.L, gap,
                self.Wt_all, state.last_impulse, state.last_active, state.last_bilateral,
                impulse, is_active, self.u_free, u, self.u_corr, timings)
            n_active, opened = problem[1].shape[0], problem[9]
        if retried:
            self.stats.retried += 1
        if status != prox.STATUS_CONVERGED:
            self.stats.nonconverged += 1
        if status == prox.STATUS_NONFINITE:
            raise SimulationError("prox iteration produced non-finite impulses; "
                                  "state left unchanged")
        if pstatus >= 0:
            self.stats.projections += 1
        return u, StepResult(is_active, self.gap.copy(), impulse, it, status, resid, retried,
                             self.position.copy(), n_active if self.hard else 0, opened, pit,
                             pstatus >= 0)
