"""Mass matrix M and forces h of a forest of floating trees in the paper's coordinates,
compiled with numba (composite-rigid-body algorithm and recursive Newton-Euler, Featherstone
2008, in the world frame).

Why not Pinocchio on the hot path: ``pin.crba`` and ``pin.nonLinearEffects`` take their
Python arguments and return numpy copies (≈1.5 µs each, measured), and their free-flyer
convention (linear velocity in the body frame) needs a transform of M and h afterwards
(`coordinates.forest.from_pin_dynamics`); here the step's midpoint quantities come from one
jitted call that shares the forward kinematics with the contact kinematics
(`coordinates.forest.midpoint_dynamics`). ``test/test_kinematics_dynamics.py`` checks M
and h against Pinocchio (CRBA, RNEA, ABA) on the minimal tree and the extended forest (the
maximal set has a constant M and needs neither).

Conventions: spatial vectors are Plücker coordinates in the world frame at the world origin,
motion [ω; v_O], force [n_O; f]. A tree root is a free body with the paper's velocities
(Eqn. 21): u_root = [I_v (3, inertial velocity of the root frame's origin), B_ω (3)], so its
motion subspace is S = [[0, R]; [1, p x R]] (p, R: the root frame's position and rotation);
a revolute joint with world axis a through p has S = [a; p x a]. With q̈ = 0 the joint
forces of the RNEA are C(q, u) u + g(q) = −h:
    M u̇ = h + τ + W Λ / Δt   (Eqn. 7 per unit time)
"""
from __future__ import annotations

import numba as nb
import numpy as np
import pinocchio as pin

from .kernel_cache import KERNEL
from .array_views import borrowed, keep_alive, view2, view3
from .kinematics import JT_FREEFLYER


class BodyInertias:
    """The inertial parameters of a pin model's bodies (one per joint: mass, centre of mass
    in the joint frame, rotational inertia about the centre of mass in the joint frame) and
    its gravity, as flat arrays for the kernels."""

    def __init__(self, model: pin.Model):
        nj = model.njoints
        self.mass = np.array([model.inertias[j].mass for j in range(nj)], dtype=float)
        self.lever = np.array([model.inertias[j].lever for j in range(nj)], dtype=float)
        self.inertia = np.array([model.inertias[j].inertia for j in range(nj)], dtype=float)
        self.gravity = np.asarray(model.gravity.linear, dtype=float).copy()
        self.mass[0] = 0.0

    def args(self):
        return self.mass, self.lever, self.inertia, self.gravity


@nb.njit(**KERNEL, inline="always")
def _cross(a0, a1, a2, b0, b1, b2):
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@nb.njit(**KERNEL, inline="always")
def motion_subspace(jtype, axis, idx_v, oR, op, S):
    """S (6 x nv): the world-frame Plücker motion subspace of every joint's velocity
    coordinates (module docstring); forward_kinematics must have been run."""
    for r in range(6):
        for c in range(S.shape[1]):
            S[r, c] = 0.0
    for j in range(1, jtype.shape[0]):
        iv = idx_v[j]
        p0, p1, p2 = op[j, 0], op[j, 1], op[j, 2]
        if jtype[j] == JT_FREEFLYER:
            for i in range(3):
                S[3 + i, iv + i] = 1.0
                a0, a1, a2 = oR[j, 0, i], oR[j, 1, i], oR[j, 2, i]
                S[0, iv + 3 + i] = a0
                S[1, iv + 3 + i] = a1
                S[2, iv + 3 + i] = a2
                S[3, iv + 3 + i], S[4, iv + 3 + i], S[5, iv + 3 + i] = \
                    _cross(p0, p1, p2, a0, a1, a2)
        else:
            a0 = oR[j, 0, 0] * axis[j, 0] + oR[j, 0, 1] * axis[j, 1] + oR[j, 0, 2] * axis[j, 2]
            a1 = oR[j, 1, 0] * axis[j, 0] + oR[j, 1, 1] * axis[j, 1] + oR[j, 1, 2] * axis[j, 2]
            a2 = oR[j, 2, 0] * axis[j, 0] + oR[j, 2, 1] * axis[j, 1] + oR[j, 2, 2] * axis[j, 2]
            S[0, iv], S[1, iv], S[2, iv] = a0, a1, a2
            S[3, iv], S[4, iv], S[5, iv] = _cross(p0, p1, p2, a0, a1, a2)


@nb.njit(**KERNEL, inline="always")
def spatial_inertias(oR, op, mass, lever, inertia, out, scratch):
    """out[j] (6 x 6): body j's spatial inertia in the world frame at the world origin,
    [[I_c − m [c]x², m [c]x]; [m [c]x^T, m 1]] with c its centre of mass and I_c its
    rotational inertia about c, both in the world frame. scratch: 21 floats of work space."""
    RI = view2(scratch[0:9], (3, 3))
    Iw = view2(scratch[9:18], (3, 3))
    c = scratch[18:21]
    for j in range(1, mass.shape[0]):
        m = mass[j]
        R = oR[j]
        for r in range(3):
            c[r] = op[j, r] + R[r, 0] * lever[j, 0] + R[r, 1] * lever[j, 1] + R[r, 2] * lever[j, 2]
        for r in range(3):
            for k in range(3):
                RI[r, k] = R[r, 0] * inertia[j, 0, k] + R[r, 1] * inertia[j, 1, k] \
                    + R[r, 2] * inertia[j, 2, k]
        for r in range(3):
            for k in range(3):
                Iw[r, k] = RI[r, 0] * R[k, 0] + RI[r, 1] * R[k, 1] + RI[r, 2] * R[k, 2]
        # −[c]x² = |c|² 1 − c c^T
        cc = c[0] * c[0] + c[1] * c[1] + c[2] * c[2]
        I6 = out[j]
        for r in range(3):
            for k in range(3):
                I6[r, k] = Iw[r, k] + m * ((cc if r == k else 0.0) - c[r] * c[k])
                I6[3 + r, 3 + k] = m if r == k else 0.0
        mc0, mc1, mc2 = m * c[0], m * c[1], m * c[2]
        # m [c]x (upper right) and its transpose (lower left)
        I6[0, 3], I6[0, 4], I6[0, 5] = 0.0, -mc2, mc1
        I6[1, 3], I6[1, 4], I6[1, 5] = mc2, 0.0, -mc0
        I6[2, 3], I6[2, 4], I6[2, 5] = -mc1, mc0, 0.0
        for r in range(3):
            for k in range(3):
                I6[3 + r, k] = I6[k, 3 + r]


@nb.njit(**KERNEL)
def mass_matrix_and_forces(u, parent, jtype, axis, idx_v, oR, op, mass, lever, inertia,
                           gravity, M, h):
    """M (nv x nv, full) by the composite-rigid-body algorithm and h = −(C(q, u) u + g(q))
    by the recursive Newton-Euler algorithm (q̈ = 0, gravity as a base acceleration), both
    in the paper's coordinates (module docstring); forward_kinematics must have been run at
    q."""
    nj = parent.shape[0]
    nv = u.shape[0]
    # the temporaries in one allocation: I6, V, A, F, S, vj, hv, f, and the work space of
    # spatial_inertias. Every entry of I6, V, A and F is written before it is read but those
    # of the root (body 0, the world: V_0 = 0, A_0 = −g, I6[0] and F[0] never read), so only
    # the root's rows are zeroed (the whole of them cost a 5.6 KB memset per step)
    n_zero = 36 * nj + 18 * nj
    owner = np.empty(n_zero + 6 * nv + 18 + 21)
    scratch = borrowed(owner)       # (no reference counting; held by keep_alive at the end)
    I6 = view3(scratch[0:36 * nj], (nj, 6, 6))
    V = view2(scratch[36 * nj:42 * nj], (nj, 6))
    A = view2(scratch[42 * nj:48 * nj], (nj, 6))
    F = view2(scratch[48 * nj:54 * nj], (nj, 6))
    S = view2(scratch[n_zero:n_zero + 6 * nv], (6, nv))
    o = n_zero + 6 * nv
    vj = scratch[o:o + 6]
    hv = scratch[o + 6:o + 12]
    f = scratch[o + 12:o + 18]
    motion_subspace(jtype, axis, idx_v, oR, op, S)
    spatial_inertias(oR, op, mass, lever, inertia, I6, scratch[o + 18:o + 39])
    for r in range(6):
        V[0, r] = 0.0
        A[0, r] = 0.0
        F[0, r] = 0.0
        for k in range(6):
            I6[0, r, k] = 0.0
    # -- RNEA, forward pass: V_j = V_λ(j) + S_j u_j, A_j = A_λ(j) + Ṡ_j u_j, A_0 = −g
    for r in range(3):
        A[0, 3 + r] = -gravity[r]
    for j in range(1, nj):
        par = parent[j]
        iv = idx_v[j]
        for r in range(6):
            s = 0.0
            for d in range(6 if jtype[j] == JT_FREEFLYER else 1):
                s += S[r, iv + d] * u[iv + d]
            vj[r] = s
            V[j, r] = V[par, r] + s
        w0, w1, w2 = V[j, 0], V[j, 1], V[j, 2]
        if jtype[j] == JT_FREEFLYER:
            # the linear columns are constant in the world, the angular ones move with the
            # body: Ṡ u = V ×ₘ (S_ω ω) = −V ×ₘ [0; ṗ] = [0; −ω × ṗ]
            c0, c1, c2 = _cross(w0, w1, w2, u[iv], u[iv + 1], u[iv + 2])
            for r in range(3):
                A[j, r] = A[par, r]
            A[j, 3] = A[par, 3] - c0
            A[j, 4] = A[par, 4] - c1
            A[j, 5] = A[par, 5] - c2
        else:
            # Ṡ u = V_j ×ₘ (S_j u_j) = [ω × vj_ω; ω × vj_v + v × vj_ω]
            v0, v1, v2 = V[j, 3], V[j, 4], V[j, 5]
            a0, a1, a2 = _cross(w0, w1, w2, vj[0], vj[1], vj[2])
            b0, b1, b2 = _cross(w0, w1, w2, vj[3], vj[4], vj[5])
            d0, d1, d2 = _cross(v0, v1, v2, vj[0], vj[1], vj[2])
            A[j, 0] = A[par, 0] + a0
            A[j, 1] = A[par, 1] + a1
            A[j, 2] = A[par, 2] + a2
            A[j, 3] = A[par, 3] + b0 + d0
            A[j, 4] = A[par, 4] + b1 + d1
            A[j, 5] = A[par, 5] + b2 + d2
        # F_j = I_j A_j + V_j ×* (I_j V_j),  [ω; v] ×* [n; f] = [ω × n + v × f; ω × f]
        Ij = I6[j]
        for r in range(6):
            s = 0.0
            t = 0.0
            for k in range(6):
                s += Ij[r, k] * A[j, k]
                t += Ij[r, k] * V[j, k]
            F[j, r] = s
            hv[r] = t
        v0, v1, v2 = V[j, 3], V[j, 4], V[j, 5]
        a0, a1, a2 = _cross(w0, w1, w2, hv[0], hv[1], hv[2])
        b0, b1, b2 = _cross(v0, v1, v2, hv[3], hv[4], hv[5])
        c0, c1, c2 = _cross(w0, w1, w2, hv[3], hv[4], hv[5])
        F[j, 0] += a0 + b0
        F[j, 1] += a1 + b1
        F[j, 2] += a2 + b2
        F[j, 3] += c0
        F[j, 4] += c1
        F[j, 5] += c2
    # -- backward pass: h_j = −S_j^T F_j, F_λ(j) += F_j; composite inertias
    Ic = I6
    for j in range(nj - 1, 0, -1):
        iv = idx_v[j]
        for d in range(6 if jtype[j] == JT_FREEFLYER else 1):
            s = 0.0
            for r in range(6):
                s += S[r, iv + d] * F[j, r]
            h[iv + d] = -s
        par = parent[j]
        if par > 0:
            for r in range(6):
                F[par, r] += F[j, r]
                for k in range(6):
                    Ic[par, r, k] += Ic[j, r, k]
    # -- CRBA: M[k, j] = S_k^T Ic_j S_j for k = j and the ancestors of j
    for r in range(nv):
        for c in range(nv):
            M[r, c] = 0.0
    for j in range(1, nj):
        iv = idx_v[j]
        Icj = Ic[j]
        for d in range(6 if jtype[j] == JT_FREEFLYER else 1):
            col = iv + d
            for r in range(6):
                s = 0.0
                for k in range(6):
                    s += Icj[r, k] * S[k, col]
                f[r] = s
            a = j
            while a > 0:
                ia = idx_v[a]
                for e in range(6 if jtype[a] == JT_FREEFLYER else 1):
                    row = ia + e
                    if a == j and row > col:
                        continue
                    s = 0.0
                    for r in range(6):
                        s += S[r, row] * f[r]
                    M[row, col] = s
                    M[col, row] = s
                a = parent[a]
    keep_alive(owner)
