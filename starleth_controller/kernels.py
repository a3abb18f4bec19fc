"""Numba kernels of the controller's per-call arithmetic (small fixed-size linear algebra
that numpy would spend most of its time dispatching, and the scalar formulas of the virtual
model, the force QP's inputs and the swing legs, which Python would spend most of its time
interpreting). fastmath stays off and each formula keeps the operation order (and Python's
min / max semantics) of the code it replaced: the torques are bit-identical.

Leg geometry arrays (one row per leg, model.py): ``hip`` (4, 3) HAA position in the base
frame, ``geo`` (4, 12) = l0 (HAA→HFE, vertical), l1 (thigh), l2 (shank to the foot centre),
foot radius, knee sign (−1 backward, +1 forward), o_x (HAA→HFE along x), d_y (the lateral
offset HAA→foot), α and γ (the thigh's angle from −z and the shank's from the thigh), the
signs of the roll axis along x and of the pitch axes along y (model.py's docstring). A
StarlETH leg (zero offsets and angles, signs +1) keeps the arithmetic of its own formulas.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from .ground_plane import plane_height, smoothstep, swing_height

# the columns of geo (model.GEOMETRY)
_L0, _L1, _L2, _RAD, _KNEE, _OX, _DY, _ALPHA, _GAMMA, _ROLL, _S1, _S2 = range(12)

_jit = nb.njit(cache=True, fastmath=False, nogil=True)


@_jit
def quat_to_rot(qx, qy, qz, qw, R):
    n = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    rot_of_unit_quat(qx / n, qy / n, qz / n, qw / n, R)


@nb.njit(cache=True, inline="always")
def rot_of_unit_quat(x, y, z, w, R):
    """R of the unit quaternion (x, y, z, w)."""
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - z * w)
    R[0, 2] = 2 * (x * z + y * w)
    R[1, 0] = 2 * (x * y + z * w)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - x * w)
    R[2, 0] = 2 * (x * z - y * w)
    R[2, 1] = 2 * (y * z + x * w)
    R[2, 2] = 1 - 2 * (x * x + y * y)


#: inputs at least this large (in magnitude) are left to the callers' numpy / math.fsum
#: checks (read_state, node_state: status 2), whose sums could overflow; below it a sum of
#: the few dozen values read here is finite whenever every value is
LARGE = 1e100


@nb.njit(cache=True, inline="always")
def _unfit(x):
    """x is NaN, inf or >= LARGE in magnitude (left to the callers' numpy checks)."""
    return x != x or x - x != 0.0 or abs(x) >= LARGE


@_jit
def squared_norm4(a):
    """|a|² of a 4-vector summed in order, ((a0² + a1²) + a2²) + a3²: the one rounding of the
    quaternion norm on every path (numpy's dot product rounds differently per CPU: BLAS
    kernels with FMA or SIMD partial sums)."""
    s = 0.0
    for i in range(4):
        s += a[i] * a[i]
    return s


@_jit
def _finite_small(a, n):
    """-1 if a[0:n] holds a NaN or inf, 1 if a value is >= LARGE in magnitude, else 0."""
    big = 0
    for i in range(n):
        v = a[i]
        if v != v or v - v != 0.0:
            return -1
        if abs(v) >= LARGE:
            big = 1
    return big


@_jit
def read_state(qj, dqj, pb, quat, vb, wb, quat_n, R):
    """StarlethController._read_state's checks and arithmetic: 1 (no state: a NaN or inf
    among the inputs, or a quaternion of squared norm < 1e-12), 2 (a value >= LARGE: the
    caller decides with its numpy sums), else 0 with quat_n = quat / |quat| (|quat|² summed
    in order: squared_norm4) and R = quat_to_rot(quat_n)."""
    c1 = _finite_small(qj, qj.shape[0])      # one call each: the arrays' layouts may differ
    c2 = _finite_small(dqj, dqj.shape[0])
    c3 = _finite_small(pb, pb.shape[0])
    c4 = _finite_small(quat, quat.shape[0])
    c5 = _finite_small(vb, vb.shape[0])
    c6 = _finite_small(wb, wb.shape[0])
    if min(c1, c2, c3, c4, c5, c6) < 0:
        return 1
    if max(c1, c2, c3, c4, c5, c6) > 0:
        return 2
    nq = squared_norm4(quat)
    if nq < 1e-12:
        return 1
    n = math.sqrt(nq)
    for i in range(4):
        quat_n[i] = quat[i] / n
    quat_to_rot(quat_n[0], quat_n[1], quat_n[2], quat_n[3], R)
    return 0


@_jit
def node_state(position, velocity, perm, odom, forces, threshold, q, dq, pb, quat, v, w, R,
               contact):
    """controller_node's reading of one stamp's messages, in the order of operations of its
    numpy code: q, dq = position, velocity [perm]; from the 13 odometry values (position,
    orientation xyzw, linear and angular velocity) pb, quat / |quat| (|quat|²:
    squared_norm4), v and w as given, R the rotation of the normalised quaternion (the node's
    formula: no second normalisation); contact = |force| > threshold per foot (x² + y² + z²
    summed in order, as numpy's sum over the last axis of a (4, 3) array does). 0: done;
    1: anything that the checks of the numpy code might refuse (a NaN or inf, a value >=
    LARGE, |quat|² outside (0.5, 2)): the caller runs them."""
    for i in range(perm.shape[0]):
        if _unfit(position[perm[i]]) or _unfit(velocity[perm[i]]):
            return 1
    if _finite_small(odom, 13) != 0:
        return 1
    for k in range(4):
        for j in range(3):
            if _unfit(forces[k, j]):
                return 1
    nq = squared_norm4(odom[3:7])
    if not 0.5 < nq < 2.0:
        return 1
    for i in range(perm.shape[0]):
        q[i] = position[perm[i]]
        dq[i] = velocity[perm[i]]
    n = math.sqrt(nq)
    for i in range(3):
        pb[i] = odom[i]
        v[i] = odom[7 + i]
        w[i] = odom[10 + i]
    for i in range(4):
        quat[i] = odom[3 + i] / n
    rot_of_unit_quat(quat[0], quat[1], quat[2], quat[3], R)
    for k in range(4):
        f0, f1, f2 = forces[k, 0], forces[k, 1], forces[k, 2]
        contact[k] = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2) > threshold
    return 0


@_jit
def leg_kinematics(qj, R, pb, hip, geo, centre, contact, Jf, Jc):
    """Foot sphere centres and contact points (world), and the world-frame translational
    Jacobians of the centre (Jf) and of the lowest point of the sphere (Jc) w.r.t. the leg's
    three joints, base fixed. Analytic for a roll-pitch-pitch leg (module docstring)."""
    Jb = np.empty((3, 3))
    Jw = np.empty((3, 3))
    for k in range(4):
        rho, s1g, s2g = geo[k, _ROLL], geo[k, _S1], geo[k, _S2]
        a = rho * qj[3 * k]
        h = s1g * qj[3 * k + 1] + geo[k, _ALPHA]
        kf = s2g * qj[3 * k + 2] + geo[k, _GAMMA]
        l0, l1, l2, rad = geo[k, _L0], geo[k, _L1], geo[k, _L2], geo[k, _RAD]
        dy = geo[k, _DY]
        ca, sa = math.cos(a), math.sin(a)
        s1, c1 = math.sin(h), math.cos(h)
        s12, c12 = math.sin(h + kf), math.cos(h + kf)
        xp = -l1 * s1 - l2 * s12
        zf = -l0 - l1 * c1 - l2 * c12
        rb0 = hip[k, 0] + (geo[k, _OX] + xp)
        rb1 = hip[k, 1] + (ca * dy - sa * zf)
        rb2 = hip[k, 2] + (sa * dy + ca * zf)
        # base-frame Jacobian columns: d/dHAA, d/dHFE, d/dKFE
        dxh = -l1 * c1 - l2 * c12
        dzh = l1 * s1 + l2 * s12
        dxk = -l2 * c12
        dzk = l2 * s12
        Jb[0, 0], Jb[1, 0], Jb[2, 0] = 0.0, rho * (-sa * dy - ca * zf), rho * (ca * dy - sa * zf)
        Jb[0, 1], Jb[1, 1], Jb[2, 1] = s1g * dxh, s1g * (-sa * dzh), s1g * (ca * dzh)
        Jb[0, 2], Jb[1, 2], Jb[2, 2] = s2g * dxk, s2g * (-sa * dzk), s2g * (ca * dzk)
        # joint axes in the base frame: ρ x for HAA, σ R_x(a) y for HFE and KFE
        for i in range(3):
            centre[k, i] = pb[i] + R[i, 0] * rb0 + R[i, 1] * rb1 + R[i, 2] * rb2
            for j in range(3):
                Jf[k, i, j] = R[i, 0] * Jb[0, j] + R[i, 1] * Jb[1, j] + R[i, 2] * Jb[2, j]
            Jw[i, 0] = rho * R[i, 0]
            y_axis = R[i, 1] * ca + R[i, 2] * sa
            Jw[i, 1] = s1g * y_axis
            Jw[i, 2] = s2g * y_axis
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
    are pulled onto the workspace boundary. The roll turns the leg's plane (at the lateral
    offset d_y) through the target; in it, the planar two-link solution of the knee
    direction geo[k, 4]."""
    l0, l1, l2, ks = geo[k, _L0], geo[k, _L1], geo[k, _L2], geo[k, _KNEE]
    dy = geo[k, _DY]
    x = r0 - hip[k, 0] - geo[k, _OX]
    y = r1 - hip[k, 1]
    z = r2 - hip[k, 2]
    rr = y * y + z * z - dy * dy
    rr = 0.0 if rr < 0.0 else rr
    zl = -math.sqrt(rr)
    out[0] = geo[k, _ROLL] * (math.atan2(y, -z) - math.atan2(dy, -zl))
    zp = zl + l0
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
    hfe = math.atan2(-x, -zp) - math.atan2(l2 * math.sin(kfe), l1 + l2 * math.cos(kfe))
    out[1] = geo[k, _S1] * (hfe - geo[k, _ALPHA])
    out[2] = geo[k, _S2] * (kfe - geo[k, _GAMMA])


@_jit
def leg_fk(k, q0, q1, q2, hip, geo, out):
    l0, l1, l2, dy = geo[k, _L0], geo[k, _L1], geo[k, _L2], geo[k, _DY]
    a = geo[k, _ROLL] * q0
    h = geo[k, _S1] * q1 + geo[k, _ALPHA]
    kf = geo[k, _S2] * q2 + geo[k, _GAMMA]
    xp = -l1 * math.sin(h) - l2 * math.sin(h + kf)
    zf = -l0 - l1 * math.cos(h) - l2 * math.cos(h + kf)
    out[0] = hip[k, 0] + (geo[k, _OX] + xp)
    out[1] = hip[k, 1] + (math.cos(a) * dy - math.sin(a) * zf)
    out[2] = hip[k, 2] + (math.sin(a) * dy + math.cos(a) * zf)


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


# -- the controller's per-call steps (controller.py keeps their order of operations: the
#    results are bit-identical to the Python arithmetic they replace) ----------------------
@_jit
def _clip(v, lo, hi):
    """np.clip's value for one float (NaN stays NaN)."""
    if v < lo:
        return lo
    if v > hi:
        return hi
    return v


@_jit
def vmc_force(ref, nr, contact, pb, vb, cy, sy, z_error, max_err, v_cmd, kp, kd, kff,
              integrate, ki, lim, dt, f_int, mass_g, e, vh, vd, b):
    """The force rows b[0:3] of the virtual model's wrench (heading frame): position error
    e from the centre of the `nr` feet `ref` (horizontal) and `z_error` (vertical), clipped
    to ±max_err; F = k_p e + k_d (v* − v) + k_ff v* (+ the velocity integral f_int, clipped
    to ±lim, when `integrate`, else f_int = 0) + m g e_z."""
    rx = 0.0
    ry = 0.0
    for j in range(nr):
        rx += contact[ref[j], 0]
    for j in range(nr):
        ry += contact[ref[j], 1]
    rx = rx / nr - pb[0]
    ry = ry / nr - pb[1]
    e[0] = cy * rx + sy * ry
    e[1] = -sy * rx + cy * ry
    e[2] = z_error
    vh[0] = cy * vb[0] + sy * vb[1]
    vh[1] = -sy * vb[0] + cy * vb[1]
    vh[2] = vb[2]
    vd[0] = v_cmd[0]
    vd[1] = v_cmd[1]
    for i in range(3):
        e[i] = _clip(e[i], -max_err, max_err)
        b[i] = kp[i] * e[i] + kd[i] * (vd[i] - vh[i]) + kff[i] * vd[i]
    if integrate:
        for a in range(2):
            f = f_int[a] + ki * (vd[a] - vh[a]) * dt
            f = f if f > -lim else -lim          # Python's max(-lim, f)
            f_int[a] = f if f < lim else lim     # and min(lim, f)
        b[0] += f_int[0]
        b[1] += f_int[1]
    else:
        f_int[0] = 0.0
        f_int[1] = 0.0
    b[2] += mass_g


@_jit
def vmc_moment(er, ww, cy, sy, max_err, w_cmd, kp, kd, kff, eh, wh, wd, b):
    """The moment rows b[3:6] of the virtual model's wrench (heading frame): the orientation
    error er (rotation vector, world) and the angular velocity ww (world) in the heading
    frame, the error clipped to ±max_err; M = k_p e_R + k_d (ω* − ω) + k_ff ω*, ω* = (0, 0,
    w_cmd)."""
    eh[0] = cy * er[0] + sy * er[1]
    eh[1] = -sy * er[0] + cy * er[1]
    eh[2] = er[2]
    wh[0] = cy * ww[0] + sy * ww[1]
    wh[1] = -sy * ww[0] + cy * ww[1]
    wh[2] = ww[2]
    wd[2] = w_cmd
    for i in range(3):
        eh[i] = _clip(eh[i], -max_err, max_err)
        b[3 + i] = kp[i] * eh[i] + kd[i] * (wd[i] - wh[i]) + kff[i] * wd[i]


@_jit
def heading_qp_inputs(support, ns, contact, com, Jc, gleg, cy, sy, rh, Jh, gh):
    """The force QP's inputs for the `ns` legs `support`, heading frame: lever arms
    rh = R_zᵀ (p_c − com) (z unrotated), Jacobian rows Jh = R_zᵀ J_c and gravity torques
    gh."""
    for j in range(ns):
        k = support[j]
        dx, dy = contact[k, 0] - com[0], contact[k, 1] - com[1]
        rh[j, 0] = cy * dx + sy * dy
        rh[j, 1] = -sy * dx + cy * dy
        rh[j, 2] = contact[k, 2] - com[2]
    for j in range(ns):
        k = support[j]
        for a in range(3):
            Jh[j, 0, a] = cy * Jc[k, 0, a] + sy * Jc[k, 1, a]
            Jh[j, 1, a] = -sy * Jc[k, 0, a] + cy * Jc[k, 1, a]
            Jh[j, 2, a] = Jc[k, 2, a]
            gh[j, a] = gleg[3 * k + a]


@_jit
def support_torques(support, ns, fh, cy, sy, Jc, gleg, fdes, tau):
    """The QP's forces fh (heading frame) of the `ns` legs `support` in the world (fdes)
    and their stance torques τ_k = −J_c,kᵀ f_k + g_leg,k."""
    for j in range(ns):
        k = support[j]
        fdes[k, 0] = cy * fh[j, 0] - sy * fh[j, 1]
        fdes[k, 1] = sy * fh[j, 0] + cy * fh[j, 1]
        fdes[k, 2] = fh[j, 2]
        stance_torques(k, fdes[k], Jc, gleg, tau)


#: leg states (controller.py: SUPPORT, SWING, LOST_CONTACT)
_SUPPORT, _SWING, _LOST_CONTACT = 0, 1, 2


@_jit
def leg_states(trotting, t, t0, T, phase_offsets, duty_factor, early_touchdown, grounded,
               swing_phase, swing_cycle, states, lost_since, support):
    """Each leg's state from its plan and its contact flag (controller._leg_states, in its
    order of operations): while trotting, leg k's gait cycle c = (t − t₀)/T − offset_k
    and phase φ = c − ⌊c⌋; φ < 1 − duty: swing phase s = φ / (1 − duty), swing (support on
    an early touch-down, s > early_touchdown), else support if on the ground, lost contact if
    not. lost_since: the time contact was lost (NaN while not lost). Writes swing_phase (1
    outside the swing), swing_cycle (the cycle of the last lift-off), states and the first
    ns entries of support; returns (ns, lift-off mask: bit k set when leg k starts a new
    swing, whose hip→foot offset the caller takes)."""
    lift = 0
    for k in range(4):
        swing_phase[k] = 1.0
        if trotting:
            c = (t - t0) / T - phase_offsets[k]
            cycle = math.floor(c)
            phi = c - cycle
            if phi < 1.0 - duty_factor:
                sp = phi / (1.0 - duty_factor)
                swing_phase[k] = sp
                if cycle != swing_cycle[k]:
                    swing_cycle[k] = cycle
                    lift |= 1 << k
                states[k] = _SUPPORT if (grounded[k] and sp > early_touchdown) else _SWING
                continue
        states[k] = _SUPPORT if grounded[k] else _LOST_CONTACT
    ns = 0
    for k in range(4):
        if states[k] == _LOST_CONTACT:
            if lost_since[k] != lost_since[k]:     # NaN: just lost
                lost_since[k] = t
        else:
            lost_since[k] = math.nan
        if states[k] == _SUPPORT:
            support[ns] = k
            ns += 1
    return ns, lift


@_jit
def ground_estimate(ground, contact, support, ns):
    """Low-pass (0.05 per call) of the ground height towards the mean height of the first ns
    support legs' contact points, summed in leg order (unchanged without support)."""
    if ns == 0:
        return ground
    g = 0.0
    for j in range(ns):
        g += contact[support[j], 2]
    return ground + 0.05 * (g / ns - ground)


#: layout of the swing parameters (controller.py: _swing_parameters)
(SW_T, SW_DUTY, SW_FEEDBACK, SW_MAX, SW_INTERP_END, SW_HEIGHT, SW_DEPTH, SW_GRAVITY,
 SW_OFFSET_X) = range(9)   # OFFSET_X: 4 values; then the legs' stance points relative to
# their hips (the model's o_x, d_y: below the hip pitch joint, at the leg's lateral offset)
SW_STANCE_X = SW_OFFSET_X + 4
SW_STANCE_Y = SW_STANCE_X + 4


@_jit
def swing_target(k, sp, r0x, r0y, vb, ww, cy, sy, vcx, vcy, wc, ground, rhx_w, rhy_w, rhz_w,
                 hx, hy, hz, P, foot_radius, target, vt, foothold, z0, plane, foothold_z):
    """Swing leg k: foot target from the lift-off offset r₀ (heading frame, relative to
    the hip) to the inverted-pendulum foothold
        Δ = ½ v*_hip T_stance + k_fb (v_hip − v*_hip) √(h/g)
    (clipped to step_max, plus foothold_offset_x), blended with a smoothstep until
    step_interp_end; height from the lift-off height z0 up to swing_height above it (or
    above the foothold) at mid-swing, then down to touchdown_depth below the ground plane's
    height at the foothold (ground_plane.swing_height). r_w: trunk→hip (world), h = (hx,
    hy, hz): the hip; `ground`: the trunk's ground height. Writes `target`, `vt`, the
    foothold (world xy) and its expected height foothold_z[k]. P: the swing parameters
    (SW_*)."""
    T = P[SW_T]
    Tsw = (1.0 - P[SW_DUTY]) * T
    Tst = P[SW_DUTY] * T
    step_max, interp_end, h_swing = P[SW_MAX], P[SW_INTERP_END], P[SW_HEIGHT]
    # inverted-pendulum foothold relative to the hip, heading frame
    vhx_w = vb[0] + ww[1] * rhz_w - ww[2] * rhy_w
    vhy_w = vb[1] + ww[2] * rhx_w - ww[0] * rhz_w
    vx = cy * vhx_w + sy * vhy_w
    vy = -sy * vhx_w + cy * vhy_w
    rx = cy * rhx_w + sy * rhy_w
    ry = -sy * rhx_w + cy * rhy_w
    vdx = vcx - wc * ry
    vdy = vcy + wc * rx
    h = hz - ground
    h = 0.05 if 0.05 > h else h                  # Python's max(h, 0.05)
    sq = math.sqrt(h / P[SW_GRAVITY])
    dx = 0.5 * vdx * Tst + P[SW_FEEDBACK] * (vx - vdx) * sq
    dy = 0.5 * vdy * Tst + P[SW_FEEDBACK] * (vy - vdy) * sq
    dx = -step_max if -step_max > dx else dx     # Python's min(max(d, -step_max), step_max)
    dx = step_max if step_max < dx else dx
    dx = dx + P[SW_OFFSET_X + k] + P[SW_STANCE_X + k]
    dy = -step_max if -step_max > dy else dy
    dy = step_max if step_max < dy else dy
    dy = dy + P[SW_STANCE_Y + k]
    sig, dsig = smoothstep(sp / interp_end)
    ox = r0x + sig * (dx - r0x)
    oy = r0y + sig * (dy - r0y)
    rate = dsig / (interp_end * Tsw)
    dox, doy = rate * (dx - r0x), rate * (dy - r0y)
    target[0] = hx + cy * ox - sy * oy
    target[1] = hy + sy * ox + cy * oy
    vt[0] = vhx_w + cy * dox - sy * doy
    vt[1] = vhy_w + sy * dox + cy * doy
    foothold[k, 0] = hx + cy * dx - sy * dy
    foothold[k, 1] = hy + sy * dx + cy * dy
    z1 = plane_height(plane, foothold[k, 0], foothold[k, 1])
    foothold_z[k] = z1
    z, dz = swing_height(sp, z0, z1, h_swing, P[SW_DEPTH], Tsw)
    target[2] = z + foot_radius[k]
    vt[2] = dz


@_jit
def position_controlled_torques(states, swing_phase, r_liftoff, foothold, P, foot_radius,
                                ground, v_cmd, w_cmd, pb, R, vb, ww, cy, sy, Jf, qj, dqj, gleg,
                                kp, kd, hip, geo, target, vt, tau, liftoff_z, plane,
                                foothold_z, searching):
    """The legs not in support (states: 0 support, 1 swing, 2 lost contact) follow a foot
    target by analytic IK and joint PD with gravity feed-forward (foot_position_control)
    into τ: a swing leg swing_target's (liftoff_z: the legs' lift-off heights, plane: the
    ground plane, foothold_z: the footholds' expected heights), a leg that lost contact its
    row of `searching` (x, y, z, ż: the foot-centre targets of step_down.GroundSearch)."""
    for k in range(4):
        st = states[k]
        if st == 0:
            continue
        if st == 1:
            hx0, hy0, hz0 = hip[k, 0], hip[k, 1], hip[k, 2]
            rhx_w = R[0, 0] * hx0 + R[0, 1] * hy0 + R[0, 2] * hz0     # trunk→hip, world
            rhy_w = R[1, 0] * hx0 + R[1, 1] * hy0 + R[1, 2] * hz0
            rhz_w = R[2, 0] * hx0 + R[2, 1] * hy0 + R[2, 2] * hz0
            hx, hy, hz = pb[0] + rhx_w, pb[1] + rhy_w, pb[2] + rhz_w
            swing_target(k, swing_phase[k], r_liftoff[k, 0], r_liftoff[k, 1], vb, ww, cy, sy,
                         v_cmd[0], v_cmd[1], w_cmd, ground, rhx_w, rhy_w, rhz_w, hx, hy, hz,
                         P, foot_radius, target, vt, foothold, liftoff_z[k], plane,
                         foothold_z)
        else:
            for i in range(3):
                target[i] = searching[k, i]
            vt[0] = 0.0
            vt[1] = 0.0
            vt[2] = searching[k, 3]
        foot_position_control(k, target, vt, pb, R, vb, ww, Jf, qj, dqj, gleg, kp, kd, hip,
                              geo, tau)
