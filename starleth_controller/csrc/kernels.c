/* The controller's per-call arithmetic (kernels.h): small fixed-size linear algebra and
 * the scalar formulas of the state reading, the leg kinematics, the virtual model, the
 * force QP's inputs and the swing legs, in the order of operations of the Python formulas
 * they implement (controller.py's docstrings). */
#include "kernels.h"

void quat_to_rot(double qx, double qy, double qz, double qw, double *R) {
    double n = sqrt(qx * qx + qy * qy + qz * qz + qw * qw);
    quat_xyzw_to_rot(qx / n, qy / n, qz / n, qw / n, R);
}

/* |a|² of a 4-vector summed in order, ((a0² + a1²) + a2²) + a3²: the one rounding of the
 * quaternion norm on every path (numpy's dot product rounds differently per CPU). */
double squared_norm4(const double *a) {
    double s = 0.0;
    for (int i = 0; i < 4; i++) s += a[i] * a[i];
    return s;
}

/* x is NaN, inf or >= LARGE in magnitude (left to the callers' numpy checks). */
static inline int unfit(double x) {
    return x != x || x - x != 0.0 || fabs(x) >= LARGE;
}

/* -1 if a[0:n] holds a NaN or inf, 1 if a value is >= LARGE in magnitude, else 0. */
static int finite_small(const double *a, i64 n) {
    int big = 0;
    for (i64 i = 0; i < n; i++) {
        double v = a[i];
        if (v != v || v - v != 0.0) return -1;
        if (fabs(v) >= LARGE) big = 1;
    }
    return big;
}

/* StarlethController._read_state's checks and arithmetic: 1 (no state: a NaN or inf among
 * the inputs, or a quaternion of squared norm < 1e-12), 2 (a value >= LARGE: the caller
 * decides with its numpy sums), else 0 with quat_n = quat / |quat| (squared_norm4) and
 * R = quat_to_rot(quat_n). */
int read_state(const double *qj, i64 nq, const double *dqj, i64 ndq, const double *pb, i64 npb,
               const double *quat, i64 nquat, const double *vb, i64 nvb, const double *wb, i64 nwb,
               double *quat_n, double *R) {
    int c[6] = {finite_small(qj, nq),      finite_small(dqj, ndq), finite_small(pb, npb),
                finite_small(quat, nquat), finite_small(vb, nvb),  finite_small(wb, nwb)};
    int lo = c[0], hi = c[0];
    for (int i = 1; i < 6; i++) {
        lo = c[i] < lo ? c[i] : lo;
        hi = c[i] > hi ? c[i] : hi;
    }
    if (lo < 0) return 1;
    if (hi > 0) return 2;
    double nq2 = squared_norm4(quat);
    if (nq2 < 1e-12) return 1;
    double n = sqrt(nq2);
    for (int i = 0; i < 4; i++) quat_n[i] = quat[i] / n;
    quat_to_rot(quat_n[0], quat_n[1], quat_n[2], quat_n[3], R);
    return 0;
}

/* controller_node's reading of one stamp's messages (state_intake.state_from_values): q, dq
 * = position, velocity [perm]; from the 13 odometry values (position, orientation xyzw,
 * linear and angular velocity) pb, quat / |quat| (squared_norm4), v and w as given, R the
 * rotation of the normalised quaternion (no second normalisation); contact = |force| >
 * threshold per foot (x² + y² + z² in order). 0: done; 1: anything the checks of the numpy
 * code might refuse (a NaN or inf, a value >= LARGE, |quat|² outside (0.5, 2)). */
int node_state(const double *position, const double *velocity, const i64 *perm, i64 nperm,
               const double *odom, const double *forces, double threshold, double *q, double *dq,
               double *pb, double *quat, double *v, double *w, double *R, u8 *contact) {
    for (i64 i = 0; i < nperm; i++)
        if (unfit(position[perm[i]]) || unfit(velocity[perm[i]])) return 1;
    if (finite_small(odom, 13) != 0) return 1;
    for (int k = 0; k < 12; k++)
        if (unfit(forces[k])) return 1;
    double nq = squared_norm4(odom + 3);
    if (!(0.5 < nq && nq < 2.0)) return 1;
    for (i64 i = 0; i < nperm; i++) {
        q[i] = position[perm[i]];
        dq[i] = velocity[perm[i]];
    }
    double n = sqrt(nq);
    for (int i = 0; i < 3; i++) {
        pb[i] = odom[i];
        v[i] = odom[7 + i];
        w[i] = odom[10 + i];
    }
    for (int i = 0; i < 4; i++) quat[i] = odom[3 + i] / n;
    quat_xyzw_to_rot(quat[0], quat[1], quat[2], quat[3], R);
    for (int k = 0; k < 4; k++) {
        double f0 = forces[3 * k], f1 = forces[3 * k + 1], f2 = forces[3 * k + 2];
        contact[k] = sqrt(f0 * f0 + f1 * f1 + f2 * f2) > threshold;
    }
    return 0;
}

/* Foot sphere centres and contact points (world), and the world-frame translational
 * Jacobians of the centre (Jf) and of the lowest point of the sphere (Jc) w.r.t. the leg's
 * three joints, base fixed. Analytic for a roll-pitch-pitch leg (model.py). */
void leg_kinematics(const double *qj, const double *R, const double *pb, const double *hip,
                    const double *geo, double *centre, double *contact, double *Jf, double *Jc) {
    double Jb[9], Jw[9];
    for (int k = 0; k < 4; k++) {
        const double *g = geo + NGEO * k;
        double rho = g[ROLL], s1g = g[S1], s2g = g[S2];
        double a = rho * qj[3 * k];
        double h = s1g * qj[3 * k + 1] + g[ALPHA];
        double kf = s2g * qj[3 * k + 2] + g[GAMMA];
        double l0 = g[L0], l1 = g[L1], l2 = g[L2], rad = g[RAD], dy = g[DY];
        double ca = cos(a), sa = sin(a);
        double s1 = sin(h), c1 = cos(h);
        double s12 = sin(h + kf), c12 = cos(h + kf);
        double xp = -l1 * s1 - l2 * s12;
        double zf = -l0 - l1 * c1 - l2 * c12;
        double rb0 = hip[3 * k] + (g[OX] + xp);
        double rb1 = hip[3 * k + 1] + (ca * dy - sa * zf);
        double rb2 = hip[3 * k + 2] + (sa * dy + ca * zf);
        /* base-frame Jacobian columns: d/dHAA, d/dHFE, d/dKFE */
        double dxh = -l1 * c1 - l2 * c12;
        double dzh = l1 * s1 + l2 * s12;
        double dxk = -l2 * c12;
        double dzk = l2 * s12;
        Jb[0] = 0.0, Jb[3] = rho * (-sa * dy - ca * zf), Jb[6] = rho * (ca * dy - sa * zf);
        Jb[1] = s1g * dxh, Jb[4] = s1g * (-sa * dzh), Jb[7] = s1g * (ca * dzh);
        Jb[2] = s2g * dxk, Jb[5] = s2g * (-sa * dzk), Jb[8] = s2g * (ca * dzk);
        /* joint axes in the base frame: ρ x for HAA, σ R_x(a) y for HFE and KFE */
        double *F = Jf + 9 * k, *C = Jc + 9 * k;
        for (int i = 0; i < 3; i++) {
            const double *Ri = R + 3 * i;
            centre[3 * k + i] = pb[i] + Ri[0] * rb0 + Ri[1] * rb1 + Ri[2] * rb2;
            for (int j = 0; j < 3; j++)
                F[3 * i + j] = Ri[0] * Jb[j] + Ri[1] * Jb[3 + j] + Ri[2] * Jb[6 + j];
            Jw[3 * i] = rho * Ri[0];
            double y_axis = Ri[1] * ca + Ri[2] * sa;
            Jw[3 * i + 1] = s1g * y_axis;
            Jw[3 * i + 2] = s2g * y_axis;
        }
        contact[3 * k] = centre[3 * k];
        contact[3 * k + 1] = centre[3 * k + 1];
        contact[3 * k + 2] = centre[3 * k + 2] - rad;
        /* lowest point p_c = centre − r e_z: J_c = J_f − [p_c − centre]× J_ω = J_f + r [e_z]× J_ω */
        for (int j = 0; j < 3; j++) {
            C[j] = F[j] - rad * Jw[3 + j];
            C[3 + j] = F[3 + j] + rad * Jw[j];
            C[6 + j] = F[6 + j];
        }
    }
}

/* HAA, HFE, KFE putting the foot centre of leg k at r (base frame); out-of-reach targets
 * are pulled onto the workspace boundary. The roll turns the leg's plane (at the lateral
 * offset d_y) through the target; in it, the planar two-link solution of the knee
 * direction geo[k, KNEE]. */
void leg_ik(i64 k, double r0, double r1, double r2, const double *hip, const double *geo,
            double *out) {
    const double *g = geo + NGEO * k;
    double l0 = g[L0], l1 = g[L1], l2 = g[L2], ks = g[KNEE], dy = g[DY];
    double x = r0 - hip[3 * k] - g[OX];
    double y = r1 - hip[3 * k + 1];
    double z = r2 - hip[3 * k + 2];
    double rr = y * y + z * z - dy * dy;
    rr = rr < 0.0 ? 0.0 : rr;
    double zl = -sqrt(rr);
    out[0] = g[ROLL] * (atan2(y, -z) - atan2(dy, -zl));
    double zp = zl + l0;
    double d = sqrt(x * x + zp * zp);
    double dmax = 0.995 * (l1 + l2);
    double dmin = 1.02 * fabs(l1 - l2) + 1e-3;
    if (d > dmax || d < dmin) {
        double lim = d > dmax ? dmax : dmin;
        double s = lim / py_max(d, 1e-9);
        x *= s;
        zp *= s;
        d = lim;
    }
    double c = (d * d - l1 * l1 - l2 * l2) / (2.0 * l1 * l2);
    c = py_min(1.0, py_max(-1.0, c));
    double kfe = ks * acos(c);
    double hfe = atan2(-x, -zp) - atan2(l2 * sin(kfe), l1 + l2 * cos(kfe));
    out[1] = g[S1] * (hfe - g[ALPHA]);
    out[2] = g[S2] * (kfe - g[GAMMA]);
}

/* The foot sphere centre of leg k at the joint angles (q0, q1, q2), base frame. */
void leg_fk(i64 k, double q0, double q1, double q2, const double *hip, const double *geo,
            double *out) {
    const double *g = geo + NGEO * k;
    double l0 = g[L0], l1 = g[L1], l2 = g[L2], dy = g[DY];
    double a = g[ROLL] * q0;
    double h = g[S1] * q1 + g[ALPHA];
    double kf = g[S2] * q2 + g[GAMMA];
    double xp = -l1 * sin(h) - l2 * sin(h + kf);
    double zf = -l0 - l1 * cos(h) - l2 * cos(h + kf);
    out[0] = hip[3 * k] + (g[OX] + xp);
    out[1] = hip[3 * k + 1] + (cos(a) * dy - sin(a) * zf);
    out[2] = hip[3 * k + 2] + (sin(a) * dy + cos(a) * zf);
}

/* y = (J Jᵀ + 1e-4 I)⁻¹ v for a 3 x 3 J: the damped least-squares joint rates of a foot
 * velocity. Rounded as the numpy code it replaced (J @ J.T, np.linalg.solve: BLAS dgemm
 * and LAPACK dgesv, as OpenBLAS computes them): the products summed by fused multiply-adds
 * in order; LU with partial pivoting by columns (getf2: the column below a pivot scaled by
 * its reciprocal); forward and back substitution (trsv) by fused multiply-adds. */
static void damped_solve(const double *J, const double *v, double *y) {
    double a[3][3];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            const double *p = J + 3 * i, *q = J + 3 * j;
            a[i][j] = fma(p[2], q[2], fma(p[1], q[1], p[0] * q[0]));
        }
    for (int i = 0; i < 3; i++) a[i][i] += 1e-4;
    int piv[3];
    double t;
    for (int j = 0; j < 3; j++) {
        for (int i = 0; i < j; i++) { /* the earlier row swaps, on column j */
            t = a[i][j], a[i][j] = a[piv[i]][j], a[piv[i]][j] = t;
        }
        if (j == 1) {
            a[1][1] -= a[1][0] * a[0][1];
            a[2][1] -= a[2][0] * a[0][1];
        } else if (j == 2) {
            a[1][2] -= a[1][0] * a[0][2];
            a[2][2] -= fma(a[2][1], a[1][2], a[2][0] * a[0][2]);
        }
        int p = j; /* the first of the largest magnitudes */
        for (int i = j + 1; i < 3; i++)
            if (fabs(a[i][j]) > fabs(a[p][j])) p = i;
        piv[j] = p;
        double r = 1.0 / a[p][j];
        for (int c = 0; c <= j && p != j; c++) {
            t = a[j][c], a[j][c] = a[p][c], a[p][c] = t;
        }
        for (int i = j + 1; i < 3; i++) a[i][j] *= r;
    }
    double b[3] = {v[0], v[1], v[2]};
    for (int i = 0; i < 3; i++) {
        t = b[i], b[i] = b[piv[i]], b[piv[i]] = t;
    }
    b[1] = fma(-b[0], a[1][0], b[1]);
    b[2] = fma(-b[0], a[2][0], b[2]);
    b[2] = fma(-b[1], a[2][1], b[2]);
    b[2] /= a[2][2];
    b[0] = fma(-b[2], a[0][2], b[0]);
    b[1] = fma(-b[2], a[1][2], b[1]);
    b[1] /= a[1][1];
    b[0] = fma(-b[1], a[0][1], b[0]);
    b[0] /= a[0][0];
    y[0] = b[0], y[1] = b[1], y[2] = b[2];
}

/* Joint PD of leg k towards the IK of a world foot-centre target, desired joint rates from
 * the target velocity relative to the trunk (damped J⁻¹), plus gravity feed-forward. */
static void foot_position_control(int k, const double *target, const double *vtarget,
                                  const swing_inputs_t *s) {
    const double *pb = s->pb, *R = s->R, *vb = s->vb, *ww = s->ww;
    double d0 = target[0] - pb[0], d1 = target[1] - pb[1], d2 = target[2] - pb[2];
    double r0 = R[0] * d0 + R[3] * d1 + R[6] * d2;
    double r1 = R[1] * d0 + R[4] * d1 + R[7] * d2;
    double r2 = R[2] * d0 + R[5] * d1 + R[8] * d2;
    double qd[3];
    leg_ik(k, r0, r1, r2, s->hip, s->geo, qd);
    /* foot velocity wanted relative to a trunk-fixed frame (world axes) */
    double v[3] = {vtarget[0] - vb[0] - (ww[1] * d2 - ww[2] * d1),
                   vtarget[1] - vb[1] - (ww[2] * d0 - ww[0] * d2),
                   vtarget[2] - vb[2] - (ww[0] * d1 - ww[1] * d0)};
    const double *J = s->Jf + 9 * k;
    double y[3];
    damped_solve(J, v, y);
    for (int j = 0; j < 3; j++) {
        double dqd = J[j] * y[0] + J[3 + j] * y[1] + J[6 + j] * y[2];
        int i = 3 * k + j;
        s->tau[i] = s->kp[j] * (qd[j] - s->qj[i]) + s->kd[j] * (dqd - s->dqj[i]) + s->gleg[i];
    }
}

/* τ = −J_cᵀ f + g_leg for the force f of the ground on foot k (world). */
static void stance_torques(i64 k, const double *f, const double *Jc, const double *gleg,
                           double *tau) {
    const double *C = Jc + 9 * k;
    for (int j = 0; j < 3; j++)
        tau[3 * k + j] = -(C[j] * f[0] + C[3 + j] * f[1] + C[6 + j] * f[2]) + gleg[3 * k + j];
}

/* A = [I…; [r_i]×…] (6 x 3n), H = AᵀSA + εI, g = −AᵀSb for the n lever arms rh. */
void qp_matrices(const double *rh, i64 n, const double *b, const double *S, double eps, double *A,
                 double *H, double *g) {
    i64 m = 3 * n;
    for (i64 i = 0; i < n; i++) {
        double x = rh[3 * i], y = rh[3 * i + 1], z = rh[3 * i + 2];
        i64 c = 3 * i;
        A[3 * m + c + 1] = -z, A[3 * m + c + 2] = y;
        A[4 * m + c + 0] = z, A[4 * m + c + 2] = -x;
        A[5 * m + c + 0] = -y, A[5 * m + c + 1] = x;
    }
    for (i64 i = 0; i < m; i++) {
        for (i64 j = i; j < m; j++) {
            double s = 0.0;
            for (int r = 0; r < 6; r++) s += A[r * m + i] * S[r] * A[r * m + j];
            H[i * m + j] = s;
            H[j * m + i] = s;
        }
        H[i * m + i] += eps;
        double s = 0.0;
        for (int r = 0; r < 6; r++) s += A[r * m + i] * S[r] * b[r];
        g[i] = -s;
    }
}

/* Joint-torque rows of the force QP: g − τ_max ≤ J_iᵀ f_i ≤ g + τ_max per support foot
 * (τ = −J_iᵀ f_i + g_i), from row `row0` of C (ncol columns). */
void torque_rows(const double *J, i64 n, const double *gleg, const double *tmax, i64 row0,
                 double *C, i64 ncol, double *lo, double *up) {
    for (i64 i = 0; i < n; i++)
        for (int j = 0; j < 3; j++) {
            i64 r = row0 + 3 * i + j;
            for (int a = 0; a < 3; a++) C[r * ncol + 3 * i + a] = J[9 * i + 3 * a + j];
            lo[r] = gleg[3 * i + j] - tmax[j];
            up[r] = gleg[3 * i + j] + tmax[j];
        }
}

/* np.clip's value for one float (NaN stays NaN). */
static inline double clip(double v, double lo, double hi) {
    return v < lo ? lo : v > hi ? hi : v;
}

/* The force rows b[0:3] of the virtual model's wrench (heading frame): position error e
 * from the centre of the nr feet `ref` (horizontal) and z_error (vertical), clipped to
 * ±max_err; F = k_p e + k_d (v* − v) + k_ff v* (+ the velocity integral f_int, clipped to
 * ±lim, when `integrate`, else f_int = 0) + m g e_z. */
void vmc_force(const i64 *ref, i64 nr, const double *contact, const double *pb, const double *vb,
               double cy, double sy, double z_error, double max_err, const double *v_cmd,
               const double *kp, const double *kd, const double *kff, int integrate, double ki,
               double lim, double dt, double *f_int, double mass_g, double *e, double *vh,
               double *vd, double *b) {
    double rx = 0.0, ry = 0.0;
    for (i64 j = 0; j < nr; j++) rx += contact[3 * ref[j]];
    for (i64 j = 0; j < nr; j++) ry += contact[3 * ref[j] + 1];
    rx = rx / (double)nr - pb[0];
    ry = ry / (double)nr - pb[1];
    e[0] = cy * rx + sy * ry;
    e[1] = -sy * rx + cy * ry;
    e[2] = z_error;
    vh[0] = cy * vb[0] + sy * vb[1];
    vh[1] = -sy * vb[0] + cy * vb[1];
    vh[2] = vb[2];
    vd[0] = v_cmd[0];
    vd[1] = v_cmd[1];
    for (int i = 0; i < 3; i++) {
        e[i] = clip(e[i], -max_err, max_err);
        b[i] = kp[i] * e[i] + kd[i] * (vd[i] - vh[i]) + kff[i] * vd[i];
    }
    if (integrate) {
        for (int a = 0; a < 2; a++) {
            double f = f_int[a] + ki * (vd[a] - vh[a]) * dt;
            f = f > -lim ? f : -lim;      /* Python's max(-lim, f) */
            f_int[a] = f < lim ? f : lim; /* and min(lim, f) */
        }
        b[0] += f_int[0];
        b[1] += f_int[1];
    } else {
        f_int[0] = 0.0;
        f_int[1] = 0.0;
    }
    b[2] += mass_g;
}

/* The moment rows b[3:6] of the virtual model's wrench (heading frame): the orientation
 * error er (rotation vector, world) and the angular velocity ww (world) in the heading
 * frame, the error clipped to ±max_err; M = k_p e_R + k_d (ω* − ω) + k_ff ω*, ω* = (0, 0,
 * w_cmd). */
void vmc_moment(const double *er, const double *ww, double cy, double sy, double max_err,
                double w_cmd, const double *kp, const double *kd, const double *kff, double *eh,
                double *wh, double *wd, double *b) {
    eh[0] = cy * er[0] + sy * er[1];
    eh[1] = -sy * er[0] + cy * er[1];
    eh[2] = er[2];
    wh[0] = cy * ww[0] + sy * ww[1];
    wh[1] = -sy * ww[0] + cy * ww[1];
    wh[2] = ww[2];
    wd[2] = w_cmd;
    for (int i = 0; i < 3; i++) {
        eh[i] = clip(eh[i], -max_err, max_err);
        b[3 + i] = kp[i] * eh[i] + kd[i] * (wd[i] - wh[i]) + kff[i] * wd[i];
    }
}

/* The force QP's inputs for the ns legs `support`, heading frame: lever arms rh = R_zᵀ
 * (p_c − com) (z unrotated), Jacobian rows Jh = R_zᵀ J_c and gravity torques gh. */
void heading_qp_inputs(const i64 *support, i64 ns, const double *contact, const double *com,
                       const double *Jc, const double *gleg, double cy, double sy, double *rh,
                       double *Jh, double *gh) {
    for (i64 j = 0; j < ns; j++) {
        i64 k = support[j];
        double dx = contact[3 * k] - com[0], dy = contact[3 * k + 1] - com[1];
        rh[3 * j] = cy * dx + sy * dy;
        rh[3 * j + 1] = -sy * dx + cy * dy;
        rh[3 * j + 2] = contact[3 * k + 2] - com[2];
    }
    for (i64 j = 0; j < ns; j++) {
        i64 k = support[j];
        const double *C = Jc + 9 * k;
        double *H = Jh + 9 * j;
        for (int a = 0; a < 3; a++) {
            H[a] = cy * C[a] + sy * C[3 + a];
            H[3 + a] = -sy * C[a] + cy * C[3 + a];
            H[6 + a] = C[6 + a];
            gh[3 * j + a] = gleg[3 * k + a];
        }
    }
}

/* The QP's forces fh (heading frame) of the ns legs `support` in the world (fdes) and their
 * stance torques τ_k = −J_c,kᵀ f_k + g_leg,k. */
void support_torques(const i64 *support, i64 ns, const double *fh, double cy, double sy,
                     const double *Jc, const double *gleg, double *fdes, double *tau) {
    for (i64 j = 0; j < ns; j++) {
        i64 k = support[j];
        double *f = fdes + 3 * k;
        f[0] = cy * fh[3 * j] - sy * fh[3 * j + 1];
        f[1] = sy * fh[3 * j] + cy * fh[3 * j + 1];
        f[2] = fh[3 * j + 2];
        stance_torques(k, f, Jc, gleg, tau);
    }
}

/* Each leg's state from its plan and its contact flag (controller._leg_states): while
 * trotting, leg k's gait cycle c = (t − t₀)/T − offset_k and phase φ = c − ⌊c⌋; φ < 1 −
 * duty: swing phase s = φ / (1 − duty), swing (support on an early touch-down, s >
 * early_touchdown), else support if on the ground, lost contact if not. lost_since: the
 * time contact was lost (NaN while not lost). Writes swing_phase (1 outside the swing),
 * swing_cycle (the cycle of the last lift-off), states and the first ns entries of support;
 * returns ns, and in *lift the lift-off mask (bit k: leg k starts a new swing). */
i64 leg_states(int trotting, double t, double t0, double T, const double *phase_offsets,
               double duty_factor, double early_touchdown, const u8 *grounded, double *swing_phase,
               i64 *swing_cycle, i64 *states, double *lost_since, i64 *support, i64 *lift) {
    *lift = 0;
    for (int k = 0; k < 4; k++) {
        swing_phase[k] = 1.0;
        if (trotting) {
            double c = (t - t0) / T - phase_offsets[k];
            double cycle = floor(c);
            double phi = c - cycle;
            if (phi < 1.0 - duty_factor) {
                double sp = phi / (1.0 - duty_factor);
                swing_phase[k] = sp;
                if (cycle != (double)swing_cycle[k]) {
                    swing_cycle[k] = (i64)cycle;
                    *lift |= (i64)1 << k;
                }
                states[k] = (grounded[k] && sp > early_touchdown) ? LEG_SUPPORT : LEG_SWING;
                continue;
            }
        }
        states[k] = grounded[k] ? LEG_SUPPORT : LEG_LOST_CONTACT;
    }
    i64 ns = 0;
    for (int k = 0; k < 4; k++) {
        if (states[k] == LEG_LOST_CONTACT) {
            if (lost_since[k] != lost_since[k]) lost_since[k] = t; /* NaN: just lost */
        } else {
            lost_since[k] = NAN;
        }
        if (states[k] == LEG_SUPPORT) support[ns++] = k;
    }
    return ns;
}

/* Low-pass (0.05 per call) of the ground height towards the mean height of the first ns
 * support legs' contact points, summed in leg order (unchanged without support). */
double ground_estimate(double ground, const double *contact, const i64 *support, i64 ns) {
    if (ns == 0) return ground;
    double g = 0.0;
    for (i64 j = 0; j < ns; j++) g += contact[3 * support[j] + 2];
    return ground + 0.05 * (g / (double)ns - ground);
}

/* Swing leg k: foot target from the lift-off offset r₀ (heading frame, relative to the hip)
 * to the inverted-pendulum foothold
 *     Δ = ½ v*_hip T_stance + k_fb (v_hip − v*_hip) √(h/g)
 * (clipped to step_max, plus foothold_offset_x), blended with a smoothstep until
 * step_interp_end; height from the lift-off height z0 up to swing_height above it (or
 * above the foothold) at mid-swing, then down to touchdown_depth below the ground plane's
 * height at the foothold (swing_height). rw: trunk→hip (world), h: the hip (world). Writes
 * target, vt, the foothold (world xy) and its expected height foothold_z[k]. */
static void swing_target(int k, const double *rw, const double *h, const swing_inputs_t *s,
                         double *target, double *vt) {
    const double *P = s->P, *vb = s->vb, *ww = s->ww;
    double cy = s->cy, sy = s->sy;
    double sp = s->swing_phase[k], r0x = s->r_liftoff[2 * k], r0y = s->r_liftoff[2 * k + 1];
    double T = P[SW_T];
    double Tsw = (1.0 - P[SW_DUTY]) * T;
    double Tst = P[SW_DUTY] * T;
    double step_max = P[SW_MAX], interp_end = P[SW_INTERP_END], h_swing = P[SW_HEIGHT];
    /* inverted-pendulum foothold relative to the hip, heading frame */
    double vhx_w = vb[0] + ww[1] * rw[2] - ww[2] * rw[1];
    double vhy_w = vb[1] + ww[2] * rw[0] - ww[0] * rw[2];
    double vx = cy * vhx_w + sy * vhy_w;
    double vy = -sy * vhx_w + cy * vhy_w;
    double rx = cy * rw[0] + sy * rw[1];
    double ry = -sy * rw[0] + cy * rw[1];
    double vdx = s->v_cmd[0] - s->w_cmd * ry;
    double vdy = s->v_cmd[1] + s->w_cmd * rx;
    double hh = h[2] - s->ground;
    hh = 0.05 > hh ? 0.05 : hh; /* Python's max(h, 0.05) */
    double sq = sqrt(hh / P[SW_GRAVITY]);
    double dx = 0.5 * vdx * Tst + P[SW_FEEDBACK] * (vx - vdx) * sq;
    double dy = 0.5 * vdy * Tst + P[SW_FEEDBACK] * (vy - vdy) * sq;
    dx = -step_max > dx ? -step_max : dx; /* Python's min(max(d, -step_max), step_max) */
    dx = step_max < dx ? step_max : dx;
    dx = dx + P[SW_OFFSET_X + k] + P[SW_STANCE_X + k];
    dy = -step_max > dy ? -step_max : dy;
    dy = step_max < dy ? step_max : dy;
    dy = dy + P[SW_STANCE_Y + k];
    double sig, dsig;
    smoothstep(sp / interp_end, &sig, &dsig);
    double ox = r0x + sig * (dx - r0x);
    double oy = r0y + sig * (dy - r0y);
    double rate = dsig / (interp_end * Tsw);
    double dox = rate * (dx - r0x), doy = rate * (dy - r0y);
    target[0] = h[0] + cy * ox - sy * oy;
    target[1] = h[1] + sy * ox + cy * oy;
    vt[0] = vhx_w + cy * dox - sy * doy;
    vt[1] = vhy_w + sy * dox + cy * doy;
    double *fh = s->foothold + 2 * k;
    fh[0] = h[0] + cy * dx - sy * dy;
    fh[1] = h[1] + sy * dx + cy * dy;
    double z1 = plane_height(s->plane, fh[0], fh[1]);
    s->foothold_z[k] = z1;
    double z, dz;
    swing_height(sp, s->liftoff_z[k], z1, h_swing, P[SW_DEPTH], Tsw, &z, &dz);
    target[2] = z + s->foot_radius[k];
    vt[2] = dz;
}

/* The legs not in support (swing, lost contact) follow a foot target by analytic IK and
 * joint PD with gravity feed-forward (foot_position_control) into τ: a swing leg
 * swing_target's, a leg that lost contact its row of `searching` (x, y, z, ż: the foot-centre
 * targets of step_down.GroundSearch). */
void position_controlled_torques(const swing_inputs_t *s) {
    const double *R = s->R, *pb = s->pb;
    double *target = s->target, *vt = s->vt;
    for (int k = 0; k < 4; k++) {
        i64 st = s->states[k];
        if (st == LEG_SUPPORT) continue;
        if (st == LEG_SWING) {
            const double *hp = s->hip + 3 * k;
            double rw[3], h[3];
            for (int i = 0; i < 3; i++) /* trunk→hip, world */
                rw[i] = R[3 * i] * hp[0] + R[3 * i + 1] * hp[1] + R[3 * i + 2] * hp[2];
            for (int i = 0; i < 3; i++) h[i] = pb[i] + rw[i];
            swing_target(k, rw, h, s, target, vt);
        } else {
            for (int i = 0; i < 3; i++) target[i] = s->searching[4 * k + i];
            vt[0] = 0.0;
            vt[1] = 0.0;
            vt[2] = s->searching[4 * k + 3];
        }
        foot_position_control(k, target, vt, s);
    }
}
