"""Numba kernels of the controller's per-call arithmetic (small fixed-size linear algebra
that numpy would spend most of its time dispatching).

Leg geometry arrays (one row per leg LF, RF, LH, RH): ``hip`` (4, 3) HAA position in the base
frame, ``geo`` (4, 5) = l0 (HAA→HFE, vertical), l1 (thigh), l2 (shank to the foot centre),
foot radius, knee sign (−1 front, +1 hind).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

_jit = nb.njit(cache=True, fastmath=False, nogil=True)


@_jit
def quat_to_rot(qx, qy, qz, qw, R):
    n = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    x, y, z, w = qx / n, qy / n, qz / n, qw / n
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - z * w)
    R[0, 2] = 2 * (x * z + y * w)
    R[1, 0] = 2 * (x * y + z * w)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - x * w)
    R[2, 0] = 2 * (x * z - y * w)
    R[2, 1] = 2 * (y * z + x * w)
    R[2, 2] = 1 - 2 * (x * x + y * y)


@_jit
def leg_kinematics(qj, R, pb, hip, geo, centre, contact, Jf, Jc):
    """Foot sphere centres and contact points (world), and the world-frame translational
    Jacobians of the centre (Jf) and of the lowest point of the sphere (Jc) w.r.t. the leg's
    three joints, base fixed. Analytic for the StarlETH leg (HAA about x, HFE/KFE about y)."""
    Jb = np.empty((3, 3))
    Jw = np.empty((3, 3))
    for k in range(4):
        a = qj[3 * k]
        h = qj[3 * k + 1]
        kf = qj[3 * k + 2]
        l0, l1, l2, rad = geo[k, 0], geo[k, 1], geo[k, 2], geo[k, 3]
        ca, sa = math.cos(a), math.sin(a)
        s1, c1 = math.sin(h), math.cos(h)
        s12, c12 = math.sin(h + kf), math.cos(h + kf)
        xp = -l1 * s1 - l2 * s12
        zf = -l0 - l1 * c1 - l2 * c12
        rb0 = hip[k, 0] + xp
        rb1 = hip[k, 1] - sa * zf
        rb2 = hip[k, 2] + ca * zf
        # base-frame Jacobian columns: d/dHAA, d/dHFE, d/dKFE
        dxh = -l1 * c1 - l2 * c12
        dzh = l1 * s1 + l2 * s12
        dxk = -l2 * c12
        dzk = l2 * s12
        Jb[0, 0], Jb[1, 0], Jb[2, 0] = 0.0, -ca * zf, -sa * zf
        Jb[0, 1], Jb[1, 1], Jb[2, 1] = dxh, -sa * dzh, ca * dzh
        Jb[0, 2], Jb[1, 2], Jb[2, 2] = dxk, -sa * dzk, ca * dzk
        # joint axes in the base frame: x for HAA, R_x(a) y for HFE and KFE
        for i in range(3):
            centre[k, i] = pb[i] + R[i, 0] * rb0 + R[i, 1] * rb1 + R[i, 2] * rb2
            for j in range(3):
                Jf[k, i, j] = R[i, 0] * Jb[0, j] + R[i, 1] * Jb[1, j] + R[i, 2] * Jb[2, j]
            Jw[i, 0] = R[i, 0]
            Jw[i, 1] = R[i, 1] * ca + R[i, 2] * sa
            Jw[i, 2] = Jw[i, 1]
        contact[k, 0] = centre[k, 0]
        contact[k, 1] = centre[k, 1]
        contact[k, 2] = centre[k, 2] - rad
        # lowest point p_c = centre − r e_z:  J_c = J_f − [p_c − centre]× J_ω = J_f + r [e_z]× J_ω
        for j in range(3):
            Jc[k, 0, j] = Jf[k, 0, j] - rad * Jw[1, j]
            Jc[k, 1, j] = Jf[k, 1, j] + rad * Jw[0, j]
            Jc[k, 2, j] = Jf[k, 2, j]


@_jit
def leg_ik(k, r0, r1, r2, hip, geo, out):
    """HAA, HFE, KFE putting the foot centre of leg k at r (base frame); out-of-reach targets
    are pulled onto the workspace boundary."""
    l0, l1, l2, ks = geo[k, 0], geo[k, 1], geo[k, 2], geo[k, 4]
    x = r0 - hip[k, 0]
    y = r1 - hip[k, 1]
    z = r2 - hip[k, 2]
    out[0] = math.atan2(y, -z)
    zp = -math.sqrt(y * y + z * z) + l0
    d = math.sqrt(x * x + zp * zp)
    dmax = 0.995 * (l1 + l2)
    dmin = 1.02 * abs(l1 - l2) + 1e-3
    if d > dmax or d < dmin:
        lim = dmax if d > dmax else dmin
        s = lim / max(d, 1e-9)
        x *= s
        zp *= s
        d = lim
    c = (d * d - l1 * l1 - l2 * l2) / (2.0 * l1 * l2)
    c = min(1.0, max(-1.0, c))
    kfe = ks * math.acos(c)
    out[1] = math.atan2(-x, -zp) - math.atan2(l2 * math.sin(kfe), l1 + l2 * math.cos(kfe))
    out[2] = kfe


@_jit
def leg_fk(k, q0, q1, q2, hip, geo, out):
    l0, l1, l2 = geo[k, 0], geo[k, 1], geo[k, 2]
    xp = -l1 * math.sin(q1) - l2 * math.sin(q1 + q2)
    zf = -l0 - l1 * math.cos(q1) - l2 * math.cos(q1 + q2)
    out[0] = hip[k, 0] + xp
    out[1] = hip[k, 1] - math.sin(q0) * zf
    out[2] = hip[k, 2] + math.cos(q0) * zf


@_jit
def foot_position_control(k, target, vtarget, pb, R, vb, ww, Jf, qj, dqj, gleg, kp, kd,
                          hip, geo, tau):
    """Joint PD of leg k towards the IK of a world foot-centre target, desired joint rates
    from the target velocity relative to the trunk (damped J⁻¹), plus gravity feed-forward."""
    d0, d1, d2 = target[0] - pb[0], target[1] - pb[1], target[2] - pb[2]
    r0 = R[0, 0] * d0 + R[1, 0] * d1 + R[2, 0] * d2
    r1 = R[0, 1] * d0 + R[1, 1] * d1 + R[2, 1] * d2
    r2 = R[0, 2] * d0 + R[1, 2] * d1 + R[2, 2] * d2
    qd = np.empty(3)
    leg_ik(k, r0, r1, r2, hip, geo, qd)
    # foot velocity wanted relative to a trunk-fixed frame (world axes)
    v0 = vtarget[0] - vb[0] - (ww[1] * d2 - ww[2] * d1)
    v1 = vtarget[1] - vb[1] - (ww[2] * d0 - ww[0] * d2)
    v2 = vtarget[2] - vb[2] - (ww[0] * d1 - ww[1] * d0)
    J = Jf[k]
    A = J @ J.T
    for i in range(3):
        A[i, i] += 1e-4
    y = np.linalg.solve(A, np.array([v0, v1, v2]))
    for j in range(3):
        dqd = J[0, j] * y[0] + J[1, j] * y[1] + J[2, j] * y[2]
        i = 3 * k + j
        tau[i] = kp[j] * (qd[j] - qj[i]) + kd[j] * (dqd - dqj[i]) + gleg[i]


@_jit
def stance_torques(k, f, Jc, gleg, tau):
    """τ = −J_cᵀ f + g_leg for the force f of the ground on the foot (world)."""
    for j in range(3):
        tau[3 * k + j] = -(Jc[k, 0, j] * f[0] + Jc[k, 1, j] * f[1] + Jc[k, 2, j] * f[2]) \
            + gleg[3 * k + j]


@_jit
def qp_matrices(rh, b, S, eps, A, H, g):
    """A = [I…; [r_i]×…], H = AᵀSA + εI, g = −AᵀSb for n = len(rh) feet."""
    n = rh.shape[0]
    for i in range(n):
        x, y, z = rh[i, 0], rh[i, 1], rh[i, 2]
        c = 3 * i
        A[3, c + 1], A[3, c + 2] = -z, y
        A[4, c + 0], A[4, c + 2] = z, -x
        A[5, c + 0], A[5, c + 1] = -y, x
    m = 3 * n
    for i in range(m):
        for j in range(i, m):
            s = 0.0
            for r in range(6):
                s += A[r, i] * S[r] * A[r, j]
            H[i, j] = s
            H[j, i] = s
        H[i, i] += eps
        s = 0.0
        for r in range(6):
            s += A[r, i] * S[r] * b[r]
        g[i] = -s


@_jit
def torque_rows(J, gleg, tmax, row0, C, lo, up):
    """Joint-torque rows of the force QP: g − τ_max ≤ J_iᵀ f_i ≤ g + τ_max per support foot
    (τ = −J_iᵀ f_i + g_i), starting at row `row0`."""
    n = J.shape[0]
    for i in range(n):
        for j in range(3):
            r = row0 + 3 * i + j
            for a in range(3):
                C[r, 3 * i + a] = J[i, a, j]
            lo[r] = gleg[i, j] - tmax[j]
            up[r] = gleg[i, j] + tmax[j]
