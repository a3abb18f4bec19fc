"""Moreau's midpoint time-stepping scheme (Gehring et al. 2014, Eqn. 6-8).

One step over Δt = t^E − t^S:
    q^M = q^S ⊕ ½Δt F(q^S) u^S                                  (6)
    M, h, W evaluated at (q^M, u^S); active set I = {i | g_N,i(q^M) ≤ g_act}
    (g_act = contact.activation_gap, 10 µm by default; the paper's 0 is allowed)
    M (u^E − u^S) − h Δt − W_U Λ_U − W_B Λ_B = 0, (ξ, Λ) ∈ U × B   (7)
    q^E = q^M ⊕ ½Δt F(q^M) u^E                                   (8)
Hard contacts solve (7) with the JOR/SOR prox iterations of :mod:`starleth_sim.physics.prox`;
compliant contacts (Alg. 1) add their forces, evaluated at (q^M, u^S), to h and Λ_U
vanishes. The stepper works for any coordinate set (see :mod:`starleth_sim.physics.coordinates`).

A step runs in two parts: `MoreauStepper.prepare` does everything that depends only on
(q^S, u^S) (q^M, M, h without τ, the kinematics, the factor of M, M^{-1}W, G), and
`MoreauStepper.step` adds the joint torques and external forces to h and solves (7) and (8).
A caller may prepare ahead (sim_node does, while its controller computes); the result is
the same bit for bit.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import numba as nb

from . import prox
from .config import ConfigError
from .contact import GroundPlane, compliant_contact_forces, generalized_contact_force
from .linalg import (cholesky_blocks, cholesky_blocks_solve_cols, cholesky_blocks_solve_vec,
                     cholesky_upper_input)

#: Fig. 7 phases
PHASES = ("M_and_h", "M_inverse", "G", "prox", "rest")


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
def active_set(gap, activation_gap, hysteresis, opening_gap, last_impulse, last_active):
    """The active set I at q^M: g_N,i ≤ activation_gap, and with `hysteresis` also every
    contact that carried Λ_N > 0 in the last step while g_N,i ≤ opening_gap. Returns
    (indices of I, number of contacts loaded in the last step that are not in I)."""
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
def phase_minv(M, uS, gap, Wt_all, WtB, bB, activation_gap, eps, blocks, factor, L,
               hysteresis, opening_gap, last_impulse, last_active, dt, beta_velocity):
    """Fig. 7 phase "M^-1" (the part that does not depend on the torques): factor M into
    L (unless factor is False: L already holds the factor of a constant M), the active set
    (see active_set), W^T = [W_U^T of the active contacts; W_B^T], M^{-1} W and
    b = [ε W_U^T u^S + gap terms; b_B] with ε_i = diag(ε_N,i, ε_T,i, ε_T,i) (eps: nc x 2), the
    normal rows' gap terms of normal_law_offset and b_B the bilateral drift stabilisation
    (β/Δt) g_B (zero in the paper's law), and the nonzero patterns of the rows of W^T and
    the columns of M^{-1} W.
    Returns (ok, active, Wt, MinvW, b, (wp_ptr, wp_idx, mp_ptr, mp_idx), opened); ok is
    False if M is not positive definite; opened counts the loaded contacts that left the
    active set."""
    nv = uS.shape[0]
    ok = True
    if factor:
        ok = cholesky_blocks(M, blocks, L)
    active, opened = active_set(gap, activation_gap, hysteresis, opening_gap, last_impulse,
                                last_active)
    na = active.shape[0]
    nb_ = WtB.shape[0]
    o = 3 * na
    m = o + nb_
    Wt = np.empty((m, nv))
    MinvW = np.empty((nv, m))
    bvec = np.zeros(m)
    if not ok or m == 0:
        e = np.zeros(1, dtype=np.int64)
        return ok, active, Wt, MinvW, bvec, (e, e[:0], e, e[:0]), opened
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
    return ok, active, Wt, MinvW, bvec, (wp_ptr, wp_idx, mp_ptr, mp_idx), opened


@nb.njit(cache=True)
def phase_delassus(form, nc, bilateral_direct, Wt, MinvW, pat):
    """Fig. 7 phase "G (and G_B^-1)": G = W^T M^{-1} W (Delassus form) or only diag(G)
    (velocity form), and for the direct bilateral solution (Eqn. 20) the Cholesky factor
    of G_B = W_B^T M^{-1} W_B. Returns (ok, G, diag G, L_B, patterns) with the pattern of
    the rows of G appended to `pat`."""
    wp_ptr, wp_idx, mp_ptr, mp_idx = pat
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
    full = (wp_ptr, wp_idx, mp_ptr, mp_idx, gp_ptr, gp_idx)
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
def phase_prox(form, scheme, Wt, MinvW, u_free, bvec, G, c, Gdiag, LB, bilateral_direct, pat,
               active, last_impulse, last_active, last_bilateral, mu, alpha, tol_rel, tol_abs,
               max_iter, criterion, M, warm_start, fallback_factor):
    """Fig. 7 phase "u^E": warm start (the last step's impulses of contacts that stay
    active, and of the bilateral constraints), the prox iteration, and one retry with
    α·fallback_factor if it did not converge. Returns (u^E, Λ, iterations, status,
    residual, retried)."""
    na = active.shape[0]
    o = 3 * na
    m = c.shape[0]
    nv = u_free.shape[0]
    lam0 = np.zeros(m)
    if warm_start:
        for a in range(na):
            i = active[a]
            if last_active[i]:
                for k in range(3):
                    lam0[3 * a + k] = last_impulse[i, k]
        for a in range(m - o):
            lam0[o + a] = last_bilateral[a]
    mu_vec = np.full(na, mu)
    attempts = 2 if fallback_factor > 0.0 else 1
    r = np.empty(m)
    u = np.empty(nv)
    lam = lam0.copy()
    iters = 0
    status = prox.STATUS_CONVERGED
    resid = 0.0
    retried = False
    for attempt in range(attempts):
        prox.prox_parameters(Gdiag, na, alpha, r)
        lam[:] = lam0
        it, status, resid = prox.prox_solve(form, scheme, Wt, MinvW, u_free, bvec, G, c, na,
                                            mu_vec, r, lam, tol_rel, tol_abs, max_iter,
                                            bilateral_direct, LB, criterion, M, u,
                                            pat[0], pat[1], pat[2], pat[3], pat[4], pat[5])
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
    columns are reused). Returns (contacts, Wt, MinvW, patterns of the rows of Wt and the
    columns of MinvW)."""
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
    return contacts, Wp, Mp, (wp_ptr, wp_idx, mp_ptr, mp_idx)


@nb.njit(cache=True)
def phase_projection(form, scheme, Wt, MinvW, G, Gdiag, LB, bilateral_direct, pat, active,
                     is_active, gap, Wt_all, jacobian_gap, blocks, L, uE, dt, beta, alpha,
                     tol_rel, tol_abs, max_iter, criterion, M, u_corr, tolerance):
    """Post-step projection (contact.penetration_correction "projection"). With the
    predicted end gaps g_N^E = g_N(q^M) + ½Δt W_N^T u^E of the active contacts and of the
    contacts outside the active set that would end the step below the ground (a foot that
    was above it at q^M), it finds the pseudo-velocity Δu_p = M^{-1}(W_N P_N + W_B P_B) of
        P_N ≥ 0 ⊥ W_N^T Δu_p + (2/Δt)(max(g_N^E, 0) + β_N min(g_N^E, 0)) ≥ 0,
        W_B^T Δu_p = 0  (the bilateral constraints are not disturbed),
    frictionless (μ = 0), with the prox scheme of the velocity solve, so that
    q^E = q^M ⊕ ½Δt (u^E + Δu_p) loses the fraction β_N of every penetration and no contact
    is pushed into the ground. u_corr receives Δu_p (zero when no predicted end gap is
    below −tolerance). Returns (iterations, status); status −1: not needed."""
    nv = uE.shape[0]
    nc = gap.shape[0]
    for k in range(nv):
        u_corr[k] = 0.0
    gE = np.empty(nc)
    worst = predicted_end_gaps(gap, Wt_all, jacobian_gap, is_active, uE, dt, gE)
    if worst >= -tolerance or beta == 0.0:
        return 0, -1
    extra = np.nonzero(~is_active & (gE < -tolerance))[0]
    if extra.shape[0] == 0:
        contacts = active
        Wp, Mp, Gp, Gdp, full = Wt, MinvW, G, Gdiag, pat
    else:
        contacts, Wp, Mp, part = projection_problem(Wt, MinvW, active, extra, Wt_all,
                                                    blocks, L)
        _, Gp, Gdp, _, full = phase_delassus(form, contacts.shape[0], False, Wp, Mp, part)
    m = Wp.shape[0]
    ncp = contacts.shape[0]
    bp = np.zeros(m)
    for a in range(ncp):
        g = gE[contacts[a]]
        bp[3 * a] = (max(g, 0.0) + beta * min(g, 0.0)) / (0.5 * dt)
    r = np.empty(m)
    prox.prox_parameters(Gdp, ncp, alpha, r)
    lam = np.zeros(m)
    mu = np.zeros(ncp)
    zero = np.zeros(nv)
    it, status, _ = prox.prox_solve(form, scheme, Wp, Mp, zero, bp, Gp, bp, ncp, mu, r, lam,
                                    tol_rel, tol_abs, max_iter, bilateral_direct, LB,
                                    criterion, M, u_corr, full[0], full[1], full[2], full[3],
                                    full[4], full[5])
    if status == prox.STATUS_NONFINITE:
        for k in range(nv):
            u_corr[k] = 0.0
    return it, status


# packed parameters of the fused kernel (fewer arguments to unbox per call)
(FP_ACTIVATION, FP_MU, FP_ALPHA, FP_TOL_REL, FP_TOL_ABS, FP_FALLBACK, FP_OPENING, FP_DT,
 FP_BETA_VELOCITY, FP_BETA_PROJECTION, FP_JACOBIAN_GAP, FP_PROJECTION_TOLERANCE) = range(12)
IP_FORM, IP_SCHEME, IP_MAX_ITER, IP_CRITERION, IP_WARM, IP_DIRECT, IP_HYSTERESIS = range(7)


@nb.njit(cache=True)
def prepare_hard_contacts(M, uS, gap, Wt_all, WtB, bB, blocks, factor, L, fp, ip, eps,
                          last_impulse, last_active):
    """The torque-independent part of the hard-contact solve in one jitted call: the
    phases "M^-1" and "G" (phase_minv, phase_delassus). Returns (ok, active, Wt, MinvW, b,
    G, diag G, L_B, patterns, opened), the input of complete_hard_contacts."""
    ok, active, Wt, MinvW, bvec, pat, opened = phase_minv(
        M, uS, gap, Wt_all, WtB, bB, fp[FP_ACTIVATION], eps, blocks, factor, L,
        ip[IP_HYSTERESIS] != 0, fp[FP_OPENING], last_impulse, last_active, fp[FP_DT],
        fp[FP_BETA_VELOCITY])
    if not ok or Wt.shape[0] == 0:
        e = np.zeros(1, dtype=np.int64)
        return (ok, active, Wt, MinvW, bvec, np.zeros((0, 0)), np.zeros(0), np.zeros((0, 0)),
                (pat[0], pat[1], pat[2], pat[3], e, e[:0]), opened)
    ok, G, Gdiag, LB, full = phase_delassus(ip[IP_FORM], active.shape[0], ip[IP_DIRECT] != 0,
                                            Wt, MinvW, pat)
    return ok, active, Wt, MinvW, bvec, G, Gdiag, LB, full, opened


@nb.njit(cache=True)
def complete_hard_contacts(h, dt, uS, blocks, L, M, active, Wt, MinvW, bvec, G, Gdiag, LB,
                           full, fp, ip, last_impulse, last_active, last_bilateral, impulse,
                           is_active, u_free, u, gap, Wt_all, u_corr):
    """The torque-dependent rest of the hard-contact solve (the unprofiled hot path after
    prepare_hard_contacts): u_free = u^S + M^{-1} h Δt, c = W^T u_free + b, the prox
    iteration (phase_prox) and the post-step projection (phase_projection). Writes Λ_U of
    every contact point into impulse (nc x 3), the active flags, Λ_B into last_bilateral,
    u^E into u and the projection's Δu_p into u_corr; unless the result is non-finite, the
    warm-start memory is updated. Returns (iterations, status, residual, retried,
    projection iterations, projection status)."""
    free_velocity(h, dt, uS, blocks, L, u_free)
    nc = impulse.shape[0]
    for i in range(nc):
        is_active[i] = False
        impulse[i, 0] = 0.0
        impulse[i, 1] = 0.0
        impulse[i, 2] = 0.0
    na = active.shape[0]
    o = 3 * na
    it, status, resid, retried = 0, prox.STATUS_CONVERGED, 0.0, False
    pit, pstatus = 0, -1
    u_corr[:] = 0.0
    if Wt.shape[0] == 0:
        u[:] = u_free
    else:
        c = constraint_velocity(Wt, u_free, bvec, full[0], full[1])
        uE, lam, it, status, resid, retried = phase_prox(
            ip[IP_FORM], ip[IP_SCHEME], Wt, MinvW, u_free, bvec, G, c, Gdiag, LB,
            ip[IP_DIRECT] != 0, full, active, last_impulse, last_active, last_bilateral,
            fp[FP_MU], fp[FP_ALPHA], fp[FP_TOL_REL], fp[FP_TOL_ABS], ip[IP_MAX_ITER],
            ip[IP_CRITERION], M, ip[IP_WARM] != 0, fp[FP_FALLBACK])
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
    if status != prox.STATUS_NONFINITE and fp[FP_BETA_PROJECTION] > 0.0:
        pit, pstatus = phase_projection(
            ip[IP_FORM], ip[IP_SCHEME], Wt, MinvW, G, Gdiag, LB, ip[IP_DIRECT] != 0, full,
            active, is_active, gap, Wt_all, fp[FP_JACOBIAN_GAP], blocks, L, u, dt,
            fp[FP_BETA_PROJECTION], fp[FP_ALPHA], fp[FP_TOL_REL], fp[FP_TOL_ABS],
            ip[IP_MAX_ITER], ip[IP_CRITERION], M, u_corr, fp[FP_PROJECTION_TOLERANCE])
    if status != prox.STATUS_NONFINITE:
        for i in range(nc):
            last_active[i] = is_active[i]
            for k in range(3):
                last_impulse[i, k] = impulse[i, k]
    return it, status, resid, retried, pit, pstatus


@nb.njit(cache=True)
def all_finite(a, b):
    for k in range(a.shape[0]):
        if not np.isfinite(a[k]):
            return False
    for k in range(b.shape[0]):
        if not np.isfinite(b[k]):
            return False
    return True


@dataclass
class StepResult:
    """What one physics step did (all arrays over every contact point of the model)."""

    active: np.ndarray          # bool, in the active set at q^M (contact.activation)
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
    """Midpoint time-stepper shared by all coordinate sets and both contact models."""

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
        self.gap = np.zeros(nc)
        self.position = np.zeros((nc, 3))
        self.Wt_all = np.zeros((nc, 3, nv))
        self.L = np.zeros((nv, nv))
        self.u_free = np.zeros(nv)
        self.u_corr = np.zeros(nv)
        self.blocks = coords.blocks
        self.constant_M = coords.constant_mass_matrix
        self._factored = False
        self.no_bilateral = np.zeros((0, nv))
        self.bB = np.zeros(self.nb)
        self.beta = config.bilateral.stabilization
        s = config.solver
        self.form = prox.FORMS[s.form]
        self.scheme = prox.SCHEMES[s.scheme]
        self.criterion = prox.CRITERIA[s.criterion]
        self.bilateral_direct = config.bilateral.method == "direct"
        self.fparams = np.array([self.activation_gap, config.ground.mu, s.alpha, s.tol_rel,
                                 s.tol_abs, s.fallback_alpha_factor, c.opening_gap, self.dt,
                                 self.beta_velocity, self.beta_projection,
                                 self.jacobian_gap, PROJECTION_TOLERANCE])
        #: Newton-type impact law per contact: (ε_N, ε_T), defaults overridden by name
        self.eps = np.tile([c.restitution_normal, c.restitution_tangential], (nc, 1))
        names = list(coords.contact_names)
        for name, (en, et) in c.restitution_overrides.items():
            if name not in names:
                raise ConfigError(f"contact.restitution_overrides: unknown contact '{name}' "
                                  f"(contacts: {', '.join(names)})")
            self.eps[names.index(name)] = (en, et)
        self.iparams = np.array([self.form, self.scheme, s.max_iterations, self.criterion,
                                 int(s.warm_start), int(self.bilateral_direct),
                                 int(self.hysteresis)], dtype=np.int64)
        self._never_active = np.full(nc, np.inf)
        self._prepared = None
        self.stats = StepperStats()
        self.reset_contact_state()

    # -- contact memory (warm start, compliant anchors) -----------------------------------
    def reset_contact_state(self):
        nc = self.nc
        self.last_impulse = np.zeros((nc, 3))
        self.last_active = np.zeros(nc, dtype=bool)
        self.last_bilateral = np.zeros(self.nb)
        self.closed = np.zeros(nc, dtype=np.bool_)
        self.slip = np.zeros(nc, dtype=np.bool_)
        self.anchor = np.zeros((nc, 3))
        self.lam_compliant = np.zeros((nc, 3))

    def memory(self):
        """A copy of the contact memory that a step changes (warm start of the hard
        contacts, or the compliant contacts' state), to restore it if a control step
        fails."""
        if self.hard:
            return (self.last_impulse.copy(), self.last_active.copy(),
                    self.last_bilateral.copy())
        return (self.last_bilateral.copy(), self.closed.copy(), self.slip.copy(),
                self.anchor.copy())

    def restore(self, mem):
        if self.hard:
            self.last_impulse[:], self.last_active[:], self.last_bilateral[:] = mem
        else:
            self.last_bilateral[:], self.closed[:], self.slip[:], self.anchor[:] = mem

    # -- one step -------------------------------------------------------------------------
    def prepare(self, q, u):
        """The part of the step from (q^S, u^S) that does not depend on the joint torques
        or external forces: q^M (Eqn. 6), M and h without τ, the contact and bilateral
        kinematics at q^M, the factor of M and, with hard contacts, M^{-1}W and G. `step`
        uses it when called with the same q and u objects (which must not be modified in
        place in between), else it prepares itself, so the result is the same either way.
        A lockstep node calls this after publishing a state, while the controller works
        on its answer. Never raises: a failure is reported by the step that uses it."""
        dt = self.dt
        coords = self.coords
        prof = self.profile
        if prof:
            t0 = time.perf_counter()
        qM = coords.integrate(q, u, 0.5 * dt)
        M, h0 = coords.dynamics(qM, u, None)
        if prof:
            t1 = time.perf_counter()
            self.stats.timings[0] += t1 - t0
        coords.contact_kinematics(qM, self.ground, self.gap, self.position, self.Wt_all,
                                  self.jacobian_gap)
        if self.nb:
            WtB, gB = coords.bilateral(qM)
            np.multiply(gB, self.beta / dt, out=self.bB)
        else:
            WtB = self.no_bilateral
        if prof:
            t2 = time.perf_counter()
            self.stats.timings[4] += t2 - t1
        factor = not (self.constant_M and self._factored)
        hard = None
        if self.hard or self.nb:    # compliant contacts: the prox solve of the bilaterals
            gap = self.gap if self.hard else self._never_active
            if not prof:
                hard = prepare_hard_contacts(M, u, gap, self.Wt_all, WtB, self.bB,
                                             self.blocks, factor, self.L, self.fparams,
                                             self.iparams, self.eps, self.last_impulse,
                                             self.last_active)
            else:  # the same phases between timers (Fig. 7)
                ok, active, Wt, MinvW, bvec, pat, opened = phase_minv(
                    M, u, gap, self.Wt_all, WtB, self.bB, self.fparams[FP_ACTIVATION],
                    self.eps, self.blocks, factor, self.L, self.hysteresis,
                    self.fparams[FP_OPENING], self.last_impulse, self.last_active, self.dt,
                    self.beta_velocity)
                t3 = time.perf_counter()
                self.stats.timings[1] += t3 - t2
                e = np.zeros(1, dtype=np.int64)
                G, Gdiag, LB, full = (np.zeros((0, 0)), np.zeros(0), np.zeros((0, 0)),
                                      (*pat, e, e[:0]))
                if ok and Wt.shape[0]:
                    ok, G, Gdiag, LB, full = phase_delassus(self.form, active.shape[0],
                                                            self.bilateral_direct, Wt, MinvW,
                                                            pat)
                self.stats.timings[2] += time.perf_counter() - t3
                hard = (ok, active, Wt, MinvW, bvec, G, Gdiag, LB, full, opened)
            ok = hard[0]
        else:
            ok = cholesky_blocks(M, self.blocks, self.L) if factor else True
            if prof:
                self.stats.timings[1] += time.perf_counter() - t2
        if ok:
            self._factored = True
        self._prepared = (q, u, qM, M, h0, ok, hard)

    def step(self, q, u, tau, f_ext=None):
        """Advance (q, u) by Δt with joint torques tau (public joint order) and an optional
        generalized external force f_ext. Returns (q^E, u^E, StepResult)."""
        p = self._prepared
        if p is None or p[0] is not q or p[1] is not u:
            self.prepare(q, u)
            p = self._prepared
        self._prepared = None
        _, _, qM, M, h, ok, hard = p
        if not ok:
            raise SimulationError("mass matrix (or G_B) not positive definite "
                                  "(non-finite state?)")
        dt = self.dt
        coords = self.coords
        prof = self.profile
        if prof:
            t0 = time.perf_counter()
        if tau is not None and tau.shape[0]:
            coords.add_joint_torques(qM, u, tau, h)
        if f_ext is not None:
            h += f_ext
        if prof:
            self.stats.timings[0] += time.perf_counter() - t0
        if self.hard:
            uE, res = self._solve(M, h, u, dt, prof, hard)
        else:
            uE, res = self._solve_compliant(M, h, u, dt, prof, hard)
        if prof:
            t4 = time.perf_counter()
        # Eqn. (8); with a post-step projection, the positions move by ½Δt Δu_p more
        qE = coords.integrate(qM, uE + self.u_corr if res.projected else uE, 0.5 * dt)
        if not all_finite(qE, uE):
            raise SimulationError("non-finite state after the step; state left unchanged")
        self.stats.steps += 1
        if prof:
            self.stats.timings[4] += time.perf_counter() - t4
        return qE, uE, res

    def _solve_compliant(self, M, h, uS, dt, prof, hard):
        t = time.perf_counter() if prof else 0.0
        c = self.cfg.contact
        compliant_contact_forces(self.gap, self.position, self.Wt_all, uS, self.closed, self.slip,
                                 self.anchor, self.ground.mu, c.stiffness_normal,
                                 c.damping_normal, c.stiffness_tangential, c.damping_tangential,
                                 c.slip_velocity, self.ground.n, self.ground.t1, self.ground.t2,
                                 self.lam_compliant)
        generalized_contact_force(self.Wt_all, self.lam_compliant, h)
        if prof:
            self.stats.timings[4] += time.perf_counter() - t
        active = self.gap <= 0.0
        if self.nb:  # bilateral constraints still need the prox solve (no contact rows)
            uE, res = self._solve(M, h, uS, dt, prof, hard)
        else:
            t2 = time.perf_counter() if prof else 0.0
            free_velocity(h, dt, uS, self.blocks, self.L, self.u_free)
            if prof:
                self.stats.timings[1] += time.perf_counter() - t2
            uE, res = self.u_free.copy(), StepResult(active, None, None)
        res.active = active
        res.n_active = int(np.count_nonzero(active))
        res.gap = self.gap.copy()
        res.position = self.position.copy()
        res.impulse = self.lam_compliant * dt
        return uE, res

    def _solve(self, M, h, uS, dt, prof, hard):
        nc = self.nc
        impulse = np.empty((nc, 3))
        is_active = np.empty(nc, dtype=np.bool_)
        u = np.empty(self.nv)
        _, active, Wt, MinvW, bvec, G, Gdiag, LB, full, opened = hard
        gap = self.gap if self.hard else self._never_active
        if not prof:
            it, status, resid, retried, pit, pstatus = complete_hard_contacts(
                h, dt, uS, self.blocks, self.L, M, active, Wt, MinvW, bvec, G, Gdiag, LB,
                full, self.fparams, self.iparams, self.last_impulse, self.last_active,
                self.last_bilateral, impulse, is_active, self.u_free, u, gap, self.Wt_all,
                self.u_corr)
        else:  # the same phases, called one by one between timers (Fig. 7)
            s = self.cfg.solver
            t1 = time.perf_counter()
            free_velocity(h, dt, uS, self.blocks, self.L, self.u_free)
            t2 = time.perf_counter()
            self.stats.timings[1] += t2 - t1
            impulse[:] = 0.0
            is_active[:] = False
            it, status, resid, retried = 0, prox.STATUS_CONVERGED, 0.0, False
            pit, pstatus = 0, -1
            self.u_corr[:] = 0.0
            u = self.u_free.copy()
            if Wt.shape[0]:
                cvec = constraint_velocity(Wt, self.u_free, bvec, full[0], full[1])
                t3 = time.perf_counter()
                self.stats.timings[2] += t3 - t2
                u, lam, it, status, resid, retried = phase_prox(
                    self.form, self.scheme, Wt, MinvW, self.u_free, bvec, G, cvec, Gdiag,
                    LB, self.bilateral_direct, full, active, self.last_impulse,
                    self.last_active,
                    self.last_bilateral, self.ground.mu, s.alpha, s.tol_rel, s.tol_abs,
                    s.max_iterations, self.criterion, M, s.warm_start,
                    s.fallback_alpha_factor)
                o = 3 * active.shape[0]
                impulse[active] = lam[:o].reshape(-1, 3)
                is_active[active] = True
                if not np.all(np.isfinite(u)):
                    status = prox.STATUS_NONFINITE
                if status != prox.STATUS_NONFINITE:
                    self.last_bilateral[:] = lam[o:]
                self.stats.timings[3] += time.perf_counter() - t3
            if status != prox.STATUS_NONFINITE and self.beta_projection > 0.0:
                t5 = time.perf_counter()
                pit, pstatus = phase_projection(
                    self.form, self.scheme, Wt, MinvW, G, Gdiag, LB, self.bilateral_direct,
                    full, active, is_active, gap, self.Wt_all, self.jacobian_gap, self.blocks,
                    self.L, u, dt, self.beta_projection, s.alpha, s.tol_rel, s.tol_abs,
                    s.max_iterations, self.criterion, M, self.u_corr,
                    self.fparams[FP_PROJECTION_TOLERANCE])
                self.stats.timings[3] += time.perf_counter() - t5
            if status != prox.STATUS_NONFINITE:
                self.last_impulse[:] = impulse
                self.last_active[:] = is_active
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
                             self.position.copy(), active.shape[0] if self.hard else 0,
                             opened, pit, pstatus >= 0)
