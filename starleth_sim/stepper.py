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
def restitution_and_rhs(Wt, uS, u_free, eps, bvec, c):
    """b = ε W^T u^S and c = W^T u_free + b (= W^T M^{-1} h Δt + (I + ε) W^T u^S, Eqn. 15)."""
    m, nv = Wt.shape
    for a in range(m):
        s0 = 0.0
        s1 = 0.0
        for k in range(nv):
            s0 += Wt[a, k] * uS[k]
            s1 += Wt[a, k] * u_free[k]
        bvec[a] = eps[a] * s0
        c[a] = s1 + bvec[a]


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
        self.mu_all = np.full(nc, config.ground.mu)
        self.eps_all = np.tile([config.contact.restitution_normal,
                                config.contact.restitution_tangential,
                                config.contact.restitution_tangential], nc)
        s = config.solver
        self.form = prox.FORMS[s.form]
        self.scheme = prox.SCHEMES[s.scheme]
        self.criterion = prox.CRITERIA[s.criterion]
        self.empty_LB = np.zeros((0, 0))
        self.empty_M = np.zeros((0, 0))
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
        coords.contact_kinematics(qM, self.ground, self.gap, self.position, self.Wt_all)
        if self.hard:
            uE, res = self._solve_hard(M, h, u, dt, prof)
        else:
            uE, res = self._solve_compliant(M, h, u, dt, prof)
        if prof:
            t4 = time.perf_counter()
        qE = coords.integrate(qM, uE, 0.5 * dt)
        if not (np.all(np.isfinite(qE)) and np.all(np.isfinite(uE))):
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
        s = self.cfg.solver
        if prof:
            t1 = time.perf_counter()
        if not free_velocity(M, h, dt, uS, self.L, self.u_free):
            raise SimulationError("mass matrix not positive definite (non-finite state?)")
        is_active = self.gap <= self.activation_gap
        active = np.flatnonzero(is_active)
        na = active.shape[0]
        impulse = np.zeros((self.nc, 3))
        res = StepResult(active=is_active, gap=self.gap.copy(), impulse=impulse)
        if na == 0:
            if prof:
                self.stats.timings[1] += time.perf_counter() - t1
            self.last_active[:] = False
            return self.u_free.copy(), res
        m = 3 * na
        Wt = np.empty((m, self.nv))
        gather_rows(self.Wt_all, active, Wt)
        MinvW = np.empty((self.nv, m))
        minv_w(self.L, Wt, MinvW)
        if prof:
            t2 = time.perf_counter()
            self.stats.timings[1] += t2 - t1
        eps = self.eps_all[:m]
        bvec = np.empty(m)
        c = np.empty(m)
        restitution_and_rhs(Wt, uS, self.u_free, eps, bvec, c)
        if self.form == prox.FORM_DELASSUS:
            G = np.empty((m, m))
            prox.delassus(Wt, MinvW, G)
            Gdiag = np.diag(G).copy()
        else:
            G = self.empty_M
            Gdiag = np.empty(m)
            prox.delassus_diagonal(Wt, MinvW, Gdiag)
        mu = self.mu_all[:na]
        Msym = M if self.criterion == prox.CRITERION_ENERGY else self.empty_M
        if prof:
            t3 = time.perf_counter()
            self.stats.timings[2] += t3 - t2
        lam0 = np.zeros(m)
        if s.warm_start:
            warm = self.last_active[active]
            if warm.any():
                lam0.reshape(na, 3)[warm] = self.last_impulse[active[warm]]
        alpha = s.alpha
        r = np.empty(m)
        u = np.empty(self.nv)
        attempts = 2 if s.fallback_alpha_factor > 0 else 1
        for attempt in range(attempts):
            prox.prox_parameters(Gdiag, na, alpha, r)
            lam = lam0.copy()
            it, status, resid = prox.prox_solve(
                self.form, self.scheme, Wt, MinvW, self.u_free, bvec, G, c, na, mu, r, lam,
                s.tol_rel, s.tol_abs, s.max_iterations, False, self.empty_LB, self.criterion,
                Msym, u)
            res.iterations += it
            if status == prox.STATUS_CONVERGED:
                break
            if attempt + 1 < attempts:
                res.retried = True
                self.stats.retried += 1
                alpha *= s.fallback_alpha_factor
        res.status = status
        res.residual = resid
        if status != prox.STATUS_CONVERGED:
            self.stats.nonconverged += 1
        if status == prox.STATUS_NONFINITE or not np.all(np.isfinite(u)):
            raise SimulationError("prox iteration produced non-finite impulses; "
                                  "state left unchanged")
        impulse[active] = lam.reshape(na, 3)
        self.last_impulse[:] = impulse
        self.last_active[:] = res.active
        if prof:
            self.stats.timings[3] += time.perf_counter() - t3
        return u, res
