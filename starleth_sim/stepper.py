"""Moreau's midpoint time-stepping scheme (Gehring et al. 2014, Eqn. 6-8).

One step over Δt = t^E − t^S:
    q^M = q^S ⊕ ½Δt F(q^S) u^S                                  (6)
    M, h, W evaluated at (q^M, u^S); active set I = {i | g_N,i(q^M) ≤ g_act}
    (g_act = contact.activation_gap, 10 µm by default; the paper's 0 is allowed)
    M (u^E − u^S) − h Δt − W_U Λ_U − W_B Λ_B = 0, (ξ, Λ) ∈ U × B   (7)
    q^E = q^M ⊕ ½Δt F(q^M) u^E                                   (8)
Hard contacts solve (7) with the JOR/SOR prox iterations of :mod:`starleth_sim.prox`;
compliant contacts (Alg. 1) add their forces, evaluated at (q^M, u^S), to h and Λ_U
vanishes. The stepper works for any coordinate set (see :mod:`starleth_sim.coordinates`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import numba as nb

from . import prox
from .config import ConfigError
from .contact import GroundPlane, compliant_contact_forces, generalized_contact_force
from .linalg import cholesky_upper_input, cholesky_solve_cols, cholesky_solve_vec

#: Fig. 7 phases
PHASES = ("M_and_h", "M_inverse", "G", "prox", "rest")


class SimulationError(RuntimeError):
    """The step could not be completed (non-finite solver output or state); the state was
    left unchanged."""


@nb.njit(cache=True)
def free_velocity(M, h, dt, uS, L, u_free):
    """u_free = u^S + M^{-1} h Δt (Cholesky of M into L). False if M is not SPD."""
    if not cholesky_upper_input(M, L):
        return False
    for k in range(uS.shape[0]):
        u_free[k] = h[k] * dt
    cholesky_solve_vec(L, u_free)
    for k in range(uS.shape[0]):
        u_free[k] += uS[k]
    return True


@nb.njit(cache=True)
def gather_rows(Wt_all, active, Wt):
    """Stack the 3 rows of each active contact: Wt (3 n_active x nv) = W_U^T."""
    nv = Wt_all.shape[2]
    for a in range(active.shape[0]):
        i = active[a]
        for r in range(3):
            for k in range(nv):
                Wt[3 * a + r, k] = Wt_all[i, r, k]


@nb.njit(cache=True)
def minv_w(L, Wt, MinvW):
    """M^{-1} W from the Cholesky factor (MinvW is nv x m)."""
    m, nv = Wt.shape
    for a in range(m):
        for k in range(nv):
            MinvW[k, a] = Wt[a, k]
    cholesky_solve_cols(L, MinvW)


@nb.njit(cache=True)
def phase_minv(M, h, dt, uS, gap, Wt_all, activation_gap, eps, L, u_free):
    """Fig. 7 phase "M^-1": Cholesky of M, u_free = u^S + M^{-1} h Δt, the active set
    {i | g_N,i ≤ activation_gap}, W_U^T of the active contacts, M^{-1} W_U and
    b = ε W_U^T u^S with ε_i = diag(ε_N,i, ε_T,i, ε_T,i) (eps: nc x 2).
    Returns (ok, active, Wt, MinvW, b)."""
    nv = uS.shape[0]
    ok = free_velocity(M, h, dt, uS, L, u_free)
    na = 0
    for i in range(gap.shape[0]):
        if gap[i] <= activation_gap:
            na += 1
    active = np.empty(na, dtype=np.int64)
    k = 0
    for i in range(gap.shape[0]):
        if gap[i] <= activation_gap:
            active[k] = i
            k += 1
    m = 3 * na
    Wt = np.empty((m, nv))
    MinvW = np.empty((nv, m))
    bvec = np.empty(m)
    if not ok or na == 0:
        return ok, active, Wt, MinvW, bvec
    gather_rows(Wt_all, active, Wt)
    minv_w(L, Wt, MinvW)
    for a in range(m):
        s = 0.0
        for j in range(nv):
            s += Wt[a, j] * uS[j]
        bvec[a] = eps[active[a // 3], 0 if a % 3 == 0 else 1] * s
    return ok, active, Wt, MinvW, bvec


@nb.njit(cache=True)
def phase_delassus(form, Wt, MinvW, u_free, bvec):
    """Fig. 7 phase "G": c = W^T u_free + b (Eqn. 15) and G = W^T M^{-1} W (Delassus form),
    or only diag(G) (velocity form, for the r parameters). Returns (G, c, diag(G))."""
    m, nv = Wt.shape
    c = np.empty(m)
    for a in range(m):
        s = bvec[a]
        for j in range(nv):
            s += Wt[a, j] * u_free[j]
        c[a] = s
    Gdiag = np.empty(m)
    if form == prox.FORM_DELASSUS:
        G = np.empty((m, m))
        prox.delassus(Wt, MinvW, G)
        for a in range(m):
            Gdiag[a] = G[a, a]
    else:
        G = np.empty((0, 0))
        prox.delassus_diagonal(Wt, MinvW, Gdiag)
    return G, c, Gdiag


@nb.njit(cache=True)
def phase_prox(form, scheme, Wt, MinvW, u_free, bvec, G, c, Gdiag, active, last_impulse,
               last_active, mu, alpha, tol_rel, tol_abs, max_iter, criterion, M, warm_start,
               fallback_factor):
    """Fig. 7 phase "u^E": warm start from the last step's impulses of contacts that stay
    active, the prox iteration, and one retry with α·fallback_factor if it did not converge.
    Returns (u^E, Λ, iterations, status, residual, retried)."""
    na = active.shape[0]
    m = 3 * na
    nv = u_free.shape[0]
    lam0 = np.zeros(m)
    if warm_start:
        for a in range(na):
            i = active[a]
            if last_active[i]:
                for k in range(3):
                    lam0[3 * a + k] = last_impulse[i, k]
    mu_vec = np.full(na, mu)
    attempts = 2 if fallback_factor > 0.0 else 1
    r = np.empty(m)
    u = np.empty(nv)
    lam = lam0.copy()
    iters = 0
    status = prox.STATUS_CONVERGED
    resid = 0.0
    retried = False
    LB = np.zeros((0, 0))
    for attempt in range(attempts):
        prox.prox_parameters(Gdiag, na, alpha, r)
        lam[:] = lam0
        it, status, resid = prox.prox_solve(form, scheme, Wt, MinvW, u_free, bvec, G, c, na,
                                            mu_vec, r, lam, tol_rel, tol_abs, max_iter, False,
                                            LB, criterion, M, u)
        iters += it
        if status == prox.STATUS_CONVERGED:
            break
        if attempt + 1 < attempts:
            retried = True
            alpha *= fallback_factor
    return u, lam, iters, status, resid, retried


# packed parameters of the fused kernel (fewer arguments to unbox per call)
FP_ACTIVATION, FP_MU, FP_ALPHA, FP_TOL_REL, FP_TOL_ABS, FP_FALLBACK = range(6)
IP_FORM, IP_SCHEME, IP_MAX_ITER, IP_CRITERION, IP_WARM = range(5)


@nb.njit(cache=True)
def solve_hard_contacts(M, h, dt, uS, gap, Wt_all, L, u_free, fp, ip, eps, last_impulse,
                        last_active, impulse, is_active, u):
    """The three phases in one jitted call (the unprofiled hot path). Writes Λ of every
    contact point into impulse (nc x 3), the active flags and u^E; on success (status not
    non-finite) the warm-start memory (last_impulse, last_active) is updated.
    Returns (ok, iterations, status, residual, retried)."""
    ok, active, Wt, MinvW, bvec = phase_minv(M, h, dt, uS, gap, Wt_all, fp[FP_ACTIVATION],
                                             eps, L, u_free)
    nc = gap.shape[0]
    for i in range(nc):
        is_active[i] = False
        impulse[i, 0] = 0.0
        impulse[i, 1] = 0.0
        impulse[i, 2] = 0.0
    if not ok:
        return ok, 0, prox.STATUS_NONFINITE, 0.0, False
    na = active.shape[0]
    it, status, resid, retried = 0, prox.STATUS_CONVERGED, 0.0, False
    if na == 0:
        u[:] = u_free
    else:
        G, c, Gdiag = phase_delassus(ip[IP_FORM], Wt, MinvW, u_free, bvec)
        uE, lam, it, status, resid, retried = phase_prox(
            ip[IP_FORM], ip[IP_SCHEME], Wt, MinvW, u_free, bvec, G, c, Gdiag, active,
            last_impulse, last_active, fp[FP_MU], fp[FP_ALPHA], fp[FP_TOL_REL], fp[FP_TOL_ABS],
            ip[IP_MAX_ITER], ip[IP_CRITERION], M, ip[IP_WARM] != 0, fp[FP_FALLBACK])
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
        for i in range(nc):
            last_active[i] = is_active[i]
            for k in range(3):
                last_impulse[i, k] = impulse[i, k]
    return ok, it, status, resid, retried


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

    active: np.ndarray          # bool, g_N(q^M) ≤ 0
    gap: np.ndarray             # g_N at q^M [m]
    impulse: np.ndarray         # Λ (nc x 3) in the contact frame (N, T1, T2) [N s]
    iterations: int = 0
    status: int = prox.STATUS_CONVERGED
    residual: float = 0.0
    retried: bool = False


@dataclass
class StepperStats:
    steps: int = 0
    nonconverged: int = 0
    retried: int = 0
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
        self.activation_gap = config.contact.activation_gap if self.hard else 0.0
        nc, nv = coords.n_contacts, coords.nv
        self.nc, self.nv = nc, nv
        self.gap = np.zeros(nc)
        self.position = np.zeros((nc, 3))
        self.Wt_all = np.zeros((nc, 3, nv))
        self.L = np.zeros((nv, nv))
        self.u_free = np.zeros(nv)
        s = config.solver
        self.form = prox.FORMS[s.form]
        self.scheme = prox.SCHEMES[s.scheme]
        self.criterion = prox.CRITERIA[s.criterion]
        c = config.contact
        self.fparams = np.array([self.activation_gap, config.ground.mu, s.alpha, s.tol_rel,
                                 s.tol_abs, s.fallback_alpha_factor])
        #: Newton-type impact law per contact: (ε_N, ε_T), defaults overridden by name
        self.eps = np.tile([c.restitution_normal, c.restitution_tangential], (nc, 1))
        names = list(getattr(coords, "contact_names", []))
        for name, (en, et) in c.restitution_overrides.items():
            if name not in names:
                raise ConfigError(f"contact.restitution_overrides: unknown contact '{name}' "
                                  f"(contacts: {', '.join(names)})")
            self.eps[names.index(name)] = (en, et)
        self.iparams = np.array([self.form, self.scheme, s.max_iterations, self.criterion,
                                 int(s.warm_start)], dtype=np.int64)
        self.stats = StepperStats()
        self.reset_contact_state()

    # -- contact memory (warm start, compliant anchors) -----------------------------------
    def reset_contact_state(self):
        nc = self.nc
        self.last_impulse = np.zeros((nc, 3))
        self.last_active = np.zeros(nc, dtype=bool)
        self.closed = np.zeros(nc, dtype=np.bool_)
        self.slip = np.zeros(nc, dtype=np.bool_)
        self.anchor = np.zeros((nc, 3))
        self.lam_compliant = np.zeros((nc, 3))

    # -- one step -------------------------------------------------------------------------
    def step(self, q, u, tau, f_ext=None):
        """Advance (q, u) by Δt with joint torques tau (public joint order) and an optional
        generalized external force f_ext. Returns (q^E, u^E, StepResult)."""
        dt = self.dt
        coords = self.coords
        prof = self.profile
        if prof:
            t0 = time.perf_counter()
        qM = coords.integrate(q, u, 0.5 * dt)
        M, h = coords.dynamics(qM, u, tau)
        if f_ext is not None:
            h += f_ext
        if prof:
            t1 = time.perf_counter()
            self.stats.timings[0] += t1 - t0
        coords.contact_kinematics(qM, self.ground, self.gap, self.position, self.Wt_all,
                                  self.activation_gap)
        if self.hard:
            uE, res = self._solve_hard(M, h, u, dt, prof)
        else:
            uE, res = self._solve_compliant(M, h, u, dt, prof)
        if prof:
            t4 = time.perf_counter()
        qE = coords.integrate(qM, uE, 0.5 * dt)
        if not all_finite(qE, uE):
            raise SimulationError("non-finite state after the step; state left unchanged")
        self.stats.steps += 1
        if prof:
            self.stats.timings[4] += time.perf_counter() - t4
        return qE, uE, res

    def _solve_compliant(self, M, h, uS, dt, prof):
        t = time.perf_counter() if prof else 0.0
        c = self.cfg.contact
        compliant_contact_forces(self.gap, self.position, self.Wt_all, uS, self.closed, self.slip,
                                 self.anchor, self.ground.mu, c.stiffness_normal,
                                 c.damping_normal, c.stiffness_tangential, c.damping_tangential,
                                 c.slip_velocity, self.ground.n, self.ground.t1, self.ground.t2,
                                 self.lam_compliant)
        generalized_contact_force(self.Wt_all, self.lam_compliant, h)
        if prof:
            t2 = time.perf_counter()
            self.stats.timings[4] += t2 - t
        if not free_velocity(M, h, dt, uS, self.L, self.u_free):
            raise SimulationError("mass matrix not positive definite (non-finite state?)")
        if prof:
            self.stats.timings[1] += time.perf_counter() - t2
        res = StepResult(active=self.gap <= 0.0, gap=self.gap.copy(),
                         impulse=self.lam_compliant * dt)
        return self.u_free.copy(), res

    def _solve_hard(self, M, h, uS, dt, prof):
        nc = self.nc
        impulse = np.empty((nc, 3))
        is_active = np.empty(nc, dtype=np.bool_)
        u = np.empty(self.nv)
        if not prof:
            ok, it, status, resid, retried = solve_hard_contacts(
                M, h, dt, uS, self.gap, self.Wt_all, self.L, self.u_free, self.fparams,
                self.iparams, self.eps, self.last_impulse, self.last_active, impulse,
                is_active, u)
        else:  # the same phases, called one by one between timers (Fig. 7)
            s = self.cfg.solver
            t1 = time.perf_counter()
            ok, active, Wt, MinvW, bvec = phase_minv(
                M, h, dt, uS, self.gap, self.Wt_all, self.activation_gap, self.eps, self.L,
                self.u_free)
            t2 = time.perf_counter()
            self.stats.timings[1] += t2 - t1
            impulse[:] = 0.0
            is_active[:] = False
            if ok and active.shape[0]:
                G, cvec, Gdiag = phase_delassus(self.form, Wt, MinvW, self.u_free, bvec)
                t3 = time.perf_counter()
                self.stats.timings[2] += t3 - t2
                u, lam, it, status, resid, retried = phase_prox(
                    self.form, self.scheme, Wt, MinvW, self.u_free, bvec, G, cvec, Gdiag,
                    active, self.last_impulse, self.last_active, self.ground.mu, s.alpha,
                    s.tol_rel, s.tol_abs, s.max_iterations, self.criterion, M, s.warm_start,
                    s.fallback_alpha_factor)
                self.stats.timings[3] += time.perf_counter() - t3
                impulse[active] = lam.reshape(-1, 3)
                is_active[active] = True
            else:
                u, it, status, resid, retried = (self.u_free.copy(), 0, prox.STATUS_CONVERGED,
                                                 0.0, False)
            if not np.all(np.isfinite(u)):
                status = prox.STATUS_NONFINITE
            if ok and status != prox.STATUS_NONFINITE:
                self.last_impulse[:] = impulse
                self.last_active[:] = is_active
        if not ok:
            raise SimulationError("mass matrix not positive definite (non-finite state?)")
        if retried:
            self.stats.retried += 1
        if status != prox.STATUS_CONVERGED:
            self.stats.nonconverged += 1
        if status == prox.STATUS_NONFINITE:
            raise SimulationError("prox iteration produced non-finite impulses; "
                                  "state left unchanged")
        return u, StepResult(is_active, self.gap.copy(), impulse, it, status, resid, retried)
