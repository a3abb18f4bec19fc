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

Every kernel returns (iterations, status, residual) with status 0 = converged,
1 = iteration cap reached, 2 = non-finite values (the caller must not accept the result),
and residual = max_l |Λ_(l)^{k+1} − Λ_(l)^k| of the last iteration.
"""
from __future__ import annotations

import numpy as np
import numba as nb

from .linalg import cholesky_solve_vec

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


@nb.njit(cache=True, inline="always")
def prox_normal(x):
    """Λ_N = −prox_{R0−}(−x): projection of x onto [0, ∞)."""
    return x if x > 0.0 else 0.0


@nb.njit(cache=True, inline="always")
def prox_disc(x1, x2, radius):
    """Projection of (x1, x2) onto the disc of the given radius centred at 0."""
    n2 = x1 * x1 + x2 * x2
    if n2 <= radius * radius:
        return x1, x2
    if radius <= 0.0:
        return 0.0, 0.0
    s = radius / np.sqrt(n2)
    return x1 * s, x2 * s


@nb.njit(cache=True)
def delassus(Wt, MinvW, G):
    """G = W^T M^{-1} W (symmetric; both triangles written). Wt: m x nv, MinvW: nv x m."""
    m, nv = Wt.shape
    for a in range(m):
        for b in range(a, m):
            s = 0.0
            for k in range(nv):
                s += Wt[a, k] * MinvW[k, b]
            G[a, b] = s
            G[b, a] = s


@nb.njit(cache=True)
def delassus_diagonal(Wt, MinvW, d):
    """diag(G) without forming G (velocity form)."""
    m, nv = Wt.shape
    for a in range(m):
        s = 0.0
        for k in range(nv):
            s += Wt[a, k] * MinvW[k, a]
        d[a] = s


@nb.njit(cache=True)
def prox_parameters(Gdiag, nc, alpha, r):
    """r_N = α/G_NN, r_T = α/max(G_T1T1, G_T2T2) per contact, r_B = α/G_ll per bilateral row."""
    m = Gdiag.shape[0]
    for i in range(nc):
        b = 3 * i
        r[b] = alpha / Gdiag[b]
        rt = alpha / max(Gdiag[b + 1], Gdiag[b + 2])
        r[b + 1] = rt
        r[b + 2] = rt
    for l in range(3 * nc, m):
        r[l] = alpha / Gdiag[l]


@nb.njit(cache=True, inline="always")
def _project_contact(lam, b, xi0, xi1, xi2, r, mu_i, out):
    """Prox update of one contact's three rows (normal first, the disc uses the new Λ_N)."""
    ln = prox_normal(lam[b] - r[b] * xi0)
    t1, t2 = prox_disc(lam[b + 1] - r[b + 1] * xi1, lam[b + 2] - r[b + 2] * xi2, mu_i * ln)
    out[b] = ln
    out[b + 1] = t1
    out[b + 2] = t2


@nb.njit(cache=True)
def _kinetic_energy(M, u):
    nv = u.shape[0]
    s = 0.0
    for i in range(nv):
        row = 0.0
        for j in range(nv):
            row += M[i, j] * u[j]
        s += u[i] * row
    return 0.5 * s


@nb.njit(cache=True)
def _velocity_from_impulses(u_free, MinvW, lam, u):
    """u = u_free + M^{-1} W Λ (Eqn. 17)."""
    nv, m = MinvW.shape
    for k in range(nv):
        s = u_free[k]
        for l in range(m):
            s += MinvW[k, l] * lam[l]
        u[k] = s


@nb.njit(cache=True)
def _bilateral_direct_delassus(G, c, nc, LB, lam):
    """Λ_B = −G_BB^{-1} (G_BU Λ_U + c_B) for the current Λ_U (Eqn. 20, Delassus form)."""
    m = c.shape[0]
    o = 3 * nc
    nb_ = m - o
    rhs = np.empty(nb_)
    for a in range(nb_):
        s = c[o + a]
        for l in range(o):
            s += G[o + a, l] * lam[l]
        rhs[a] = -s
    cholesky_solve_vec(LB, rhs)
    for a in range(nb_):
        lam[o + a] = rhs[a]


@nb.njit(cache=True)
def _bilateral_direct_velocity(Wt, MinvW, u_free, nc, LB, lam):
    """Λ_B = −G_BB^{-1} W_B^T (u^S + M^{-1}(h Δt + W_U Λ_U)) (Eqn. 20, velocity form)."""
    m, nv = Wt.shape
    o = 3 * nc
    nb_ = m - o
    uu = u_free.copy()
    for k in range(nv):
        s = 0.0
        for l in range(o):
            s += MinvW[k, l] * lam[l]
        uu[k] += s
    rhs = np.empty(nb_)
    for a in range(nb_):
        s = 0.0
        for k in range(nv):
            s += Wt[o + a, k] * uu[k]
        rhs[a] = -s
    cholesky_solve_vec(LB, rhs)
    for a in range(nb_):
        lam[o + a] = rhs[a]


@nb.njit(cache=True)
def _check(lam_old, lam, tol_rel, tol_abs):
    """(converged by the impulse criterion, max |ΔΛ|, all finite)."""
    ok = True
    res = 0.0
    finite = True
    for l in range(lam.shape[0]):
        d = abs(lam[l] - lam_old[l])
        if not np.isfinite(lam[l]):
            finite = False
        if d > res:
            res = d
        if d > abs(lam_old[l]) * tol_rel + tol_abs:
            ok = False
    return ok, res, finite


@nb.njit(cache=True)
def jor_prox_delassus(G, c, nc, mu, r, lam, tol_rel, tol_abs, max_iter,
                      bilateral_direct, LB, criterion, M, u_free, MinvW, u):
    """JOR prox on ξ = GΛ + c. lam: warm start in, solution out. u: end velocity out."""
    m = c.shape[0]
    o = 3 * nc
    xi = np.empty(m)
    new = np.empty(m)
    T_old = 0.0
    if criterion == CRITERION_ENERGY:
        _velocity_from_impulses(u_free, MinvW, lam, u)
        T_old = _kinetic_energy(M, u)
    res = 0.0
    for k in range(max_iter):
        for a in range(m):
            s = c[a]
            for l in range(m):
                s += G[a, l] * lam[l]
            xi[a] = s
        for i in range(nc):
            b = 3 * i
            _project_contact(lam, b, xi[b], xi[b + 1], xi[b + 2], r, mu[i], new)
        if bilateral_direct:
            for l in range(o, m):
                new[l] = lam[l]
            _bilateral_direct_delassus(G, c, nc, LB, new)
        else:
            for l in range(o, m):
                new[l] = lam[l] - r[l] * xi[l]
        ok, res, finite = _check(lam, new, tol_rel, tol_abs)
        lam[:] = new
        if not finite:
            return k + 1, STATUS_NONFINITE, res
        if criterion == CRITERION_ENERGY:
            _velocity_from_impulses(u_free, MinvW, lam, u)
            T = _kinetic_energy(M, u)
            ok = abs(T - T_old) <= abs(T_old) * tol_rel + tol_abs
            T_old = T
        if ok:
            _velocity_from_impulses(u_free, MinvW, lam, u)
            return k + 1, STATUS_CONVERGED, res
    _velocity_from_impulses(u_free, MinvW, lam, u)
    return max_iter, STATUS_MAX_ITER, res


@nb.njit(cache=True)
def sor_prox_delassus(G, c, nc, mu, r, lam, tol_rel, tol_abs, max_iter,
                      bilateral_direct, LB, criterion, M, u_free, MinvW, u):
    """SOR prox on ξ = GΛ + c: contact after contact, reusing the updated impulses."""
    m = c.shape[0]
    o = 3 * nc
    old = np.empty(m)
    T_old = 0.0
    if criterion == CRITERION_ENERGY:
        _velocity_from_impulses(u_free, MinvW, lam, u)
        T_old = _kinetic_energy(M, u)
    res = 0.0
    for k in range(max_iter):
        old[:] = lam
        for i in range(nc):
            b = 3 * i
            x0 = c[b]
            x1 = c[b + 1]
            x2 = c[b + 2]
            for l in range(m):
                x0 += G[b, l] * lam[l]
                x1 += G[b + 1, l] * lam[l]
                x2 += G[b + 2, l] * lam[l]
            _project_contact(lam, b, x0, x1, x2, r, mu[i], lam)
        if bilateral_direct:
            _bilateral_direct_delassus(G, c, nc, LB, lam)
        else:
            for a in range(o, m):
                s = c[a]
                for l in range(m):
                    s += G[a, l] * lam[l]
                lam[a] -= r[a] * s
        ok, res, finite = _check(old, lam, tol_rel, tol_abs)
        if not finite:
            return k + 1, STATUS_NONFINITE, res
        if criterion == CRITERION_ENERGY:
            _velocity_from_impulses(u_free, MinvW, lam, u)
            T = _kinetic_energy(M, u)
            ok = abs(T - T_old) <= abs(T_old) * tol_rel + tol_abs
            T_old = T
        if ok:
            _velocity_from_impulses(u_free, MinvW, lam, u)
            return k + 1, STATUS_CONVERGED, res
    _velocity_from_impulses(u_free, MinvW, lam, u)
    return max_iter, STATUS_MAX_ITER, res


@nb.njit(cache=True)
def jor_prox_velocity(Wt, MinvW, u_free, bvec, nc, mu, r, lam, tol_rel, tol_abs, max_iter,
                      bilateral_direct, LB, criterion, M, u):
    """JOR prox iterating in the end velocity u^k (Eqn. 17-19); G is never formed."""
    m, nv = Wt.shape
    o = 3 * nc
    xi = np.empty(m)
    new = np.empty(m)
    _velocity_from_impulses(u_free, MinvW, lam, u)
    T_old = _kinetic_energy(M, u) if criterion == CRITERION_ENERGY else 0.0
    res = 0.0
    for k in range(max_iter):
        for a in range(m):
            s = bvec[a]
            for j in range(nv):
                s += Wt[a, j] * u[j]
            xi[a] = s
        for i in range(nc):
            b = 3 * i
            _project_contact(lam, b, xi[b], xi[b + 1], xi[b + 2], r, mu[i], new)
        if bilateral_direct:
            for l in range(o, m):
                new[l] = lam[l]
            _bilateral_direct_velocity(Wt, MinvW, u_free, nc, LB, new)
        else:
            for l in range(o, m):
                new[l] = lam[l] - r[l] * xi[l]
        ok, res, finite = _check(lam, new, tol_rel, tol_abs)
        for l in range(m):
            d = new[l] - lam[l]
            if d != 0.0:
                for j in range(nv):
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


@nb.njit(cache=True)
def sor_prox_velocity(Wt, MinvW, u_free, bvec, nc, mu, r, lam, tol_rel, tol_abs, max_iter,
                      bilateral_direct, LB, criterion, M, u):
    """SOR prox in the end velocity: after each contact's projection u is updated (Eqn. 18),
    then the bilateral rows (Eqn. 19, or Eqn. 20 when direct)."""
    m, nv = Wt.shape
    o = 3 * nc
    old = np.empty(m)
    tmp = np.empty(3)
    _velocity_from_impulses(u_free, MinvW, lam, u)
    T_old = _kinetic_energy(M, u) if criterion == CRITERION_ENERGY else 0.0
    res = 0.0
    for k in range(max_iter):
        old[:] = lam
        for i in range(nc):
            b = 3 * i
            x0 = bvec[b]
            x1 = bvec[b + 1]
            x2 = bvec[b + 2]
            for j in range(nv):
                x0 += Wt[b, j] * u[j]
                x1 += Wt[b + 1, j] * u[j]
                x2 += Wt[b + 2, j] * u[j]
            tmp[0] = lam[b]
            tmp[1] = lam[b + 1]
            tmp[2] = lam[b + 2]
            _project_contact(lam, b, x0, x1, x2, r, mu[i], lam)
            d0 = lam[b] - tmp[0]
            d1 = lam[b + 1] - tmp[1]
            d2 = lam[b + 2] - tmp[2]
            for j in range(nv):
                u[j] += MinvW[j, b] * d0 + MinvW[j, b + 1] * d1 + MinvW[j, b + 2] * d2
        if bilateral_direct:
            if m > o:
                _bilateral_direct_velocity(Wt, MinvW, u_free, nc, LB, lam)
                _velocity_from_impulses(u_free, MinvW, lam, u)
        else:
            for a in range(o, m):
                s = bvec[a]
                for j in range(nv):
                    s += Wt[a, j] * u[j]
                d = -r[a] * s
                lam[a] += d
                for j in range(nv):
                    u[j] += MinvW[j, a] * d
        ok, res, finite = _check(old, lam, tol_rel, tol_abs)
        if not finite:
            return k + 1, STATUS_NONFINITE, res
        if criterion == CRITERION_ENERGY:
            T = _kinetic_energy(M, u)
            ok = abs(T - T_old) <= abs(T_old) * tol_rel + tol_abs
            T_old = T
        if ok:
            return k + 1, STATUS_CONVERGED, res
    return max_iter, STATUS_MAX_ITER, res


@nb.njit(cache=True)
def prox_solve(form, scheme, Wt, MinvW, u_free, bvec, G, c, nc, mu, r, lam,
               tol_rel, tol_abs, max_iter, bilateral_direct, LB, criterion, M, u):
    """Dispatch to one of the four schemes (one jitted call from the stepper)."""
    if form == FORM_DELASSUS:
        if scheme == SCHEME_JOR:
            return jor_prox_delassus(G, c, nc, mu, r, lam, tol_rel, tol_abs, max_iter,
                                     bilateral_direct, LB, criterion, M, u_free, MinvW, u)
        return sor_prox_delassus(G, c, nc, mu, r, lam, tol_rel, tol_abs, max_iter,
                                 bilateral_direct, LB, criterion, M, u_free, MinvW, u)
    if scheme == SCHEME_JOR:
        return jor_prox_velocity(Wt, MinvW, u_free, bvec, nc, mu, r, lam, tol_rel, tol_abs,
                                 max_iter, bilateral_direct, LB, criterion, M, u)
    return sor_prox_velocity(Wt, MinvW, u_free, bvec, nc, mu, r, lam, tol_rel, tol_abs,
                             max_iter, bilateral_direct, LB, criterion, M, u)
