/* The kernels of a forest of floating trees cut from one kinematic tree
 * (coordinates/forest.py, Eqn. 19-22): integration of q, M and h at the step's midpoint, the
 * free bodies' forces, and the cut joints' bilateral constraints (W_B^T, g_B), angles, rates
 * and actuator torques. */
#include "core.h"

/* integrate_forest: out = q ⊕ Δt F(q) u: r ← r + Δt v, P ← P ⊗ exp(Δt ω/2) per root,
 * φ ← φ + Δt φ̇. */
void integrate_forest(const double *q, const double *u, double dt, const tree_t *t, double *out) {
    for (i64 j = 1; j < t->nj; j++) {
        i64 iq = t->idx_q[j];
        i64 iv = t->idx_v[j];
        if (t->jtype[j] != JT_FREEFLYER) {
            out[iq] = q[iq] + dt * u[iv];
            continue;
        }
        for (int k = 0; k < 3; k++) out[iq + k] = q[iq + k] + dt * u[iv + k];
        double wx = u[iv + 3] * dt, wy = u[iv + 4] * dt, wz = u[iv + 5] * dt;
        double ang = sqrt(wx * wx + wy * wy + wz * wz);
        double s;
        if (ang > 1e-12)
            s = sin(0.5 * ang) / ang;
        else
            s = 0.5 - ang * ang / 48.0;
        double dx = wx * s, dy = wy * s, dz = wz * s, dw = cos(0.5 * ang);
        double x = q[iq + 3], y = q[iq + 4], z = q[iq + 5], w = q[iq + 6];
        double nx = w * dx + x * dw + y * dz - z * dy;
        double ny = w * dy - x * dz + y * dw + z * dx;
        double nz = w * dz + x * dy - y * dx + z * dw;
        double nw = w * dw - x * dx - y * dy - z * dz;
        double n = sqrt(nx * nx + ny * ny + nz * nz + nw * nw);
        out[iq + 3] = nx / n;
        out[iq + 4] = ny / n;
        out[iq + 5] = nz / n;
        out[iq + 6] = nw / n;
    }
}

/* quat_rot: R (3 x 3), the rotation of the root whose coordinates start at q[iq]. */
void quat_rot(const double *q, i64 iq, double *R) {
    quat_xyzw_to_rot(q[iq + 3], q[iq + 4], q[iq + 5], q[iq + 6], R);
}

/* to_pin_velocity: u_pin = T u, each root's linear velocity rotated into its body frame
 * (Rs: n_roots x 3 x 3 receives the roots' rotations). */
void to_pin_velocity(const double *q, const double *u, i64 nv, i64 n_roots, const i64 *root_q,
                     const i64 *root_v, double *Rs, double *u_pin) {
    for (i64 k = 0; k < nv; k++) u_pin[k] = u[k];
    for (i64 r = 0; r < n_roots; r++) {
        double *R = Rs + 9 * r;
        quat_rot(q, root_q[r], R);
        i64 iv = root_v[r];
        for (int a = 0; a < 3; a++)
            u_pin[iv + a] =
                R[0 * 3 + a] * u[iv] + R[1 * 3 + a] * u[iv + 1] + R[2 * 3 + a] * u[iv + 2];
    }
}

/* from_pin_dynamics: M = T^T M_pin T, h = T^T (h_pin + Σ_k M_pin[:, v_k] (ω_k × v_k))
 * (M_pin: n x n, upper triangle read). */
void from_pin_dynamics(const double *M_pin, const double *h_pin, i64 n, const double *Rs,
                       i64 n_roots, const i64 *root_v, const double *u_pin, double *M, double *h) {
    for (i64 i = 0; i < n; i++) {
        for (i64 j = i; j < n; j++) {
            M[i * n + j] = M_pin[i * n + j];
            M[j * n + i] = M_pin[i * n + j];
        }
    }
    for (i64 i = 0; i < n; i++) h[i] = h_pin[i];
    for (i64 r = 0; r < n_roots; r++) {
        i64 iv = root_v[r];
        double vx = u_pin[iv], vy = u_pin[iv + 1], vz = u_pin[iv + 2];
        double wx = u_pin[iv + 3], wy = u_pin[iv + 4], wz = u_pin[iv + 5];
        double cx = wy * vz - wz * vy;
        double cy = wz * vx - wx * vz;
        double cz = wx * vy - wy * vx;
        for (i64 i = 0; i < n; i++)
            h[i] += M[i * n + iv] * cx + M[i * n + iv + 1] * cy + M[i * n + iv + 2] * cz;
    }
    double tmp[3];
    for (i64 r = 0; r < n_roots; r++) {
        i64 iv = root_v[r];
        const double *R = Rs + 9 * r;
        for (i64 j = 0; j < n; j++) {
            for (int a = 0; a < 3; a++)
                tmp[a] = R[a * 3 + 0] * M[iv * n + j] + R[a * 3 + 1] * M[(iv + 1) * n + j] +
                         R[a * 3 + 2] * M[(iv + 2) * n + j];
            for (int a = 0; a < 3; a++) M[(iv + a) * n + j] = tmp[a];
        }
        for (i64 i = 0; i < n; i++) {
            for (int a = 0; a < 3; a++)
                tmp[a] = M[i * n + iv] * R[a * 3 + 0] + M[i * n + iv + 1] * R[a * 3 + 1] +
                         M[i * n + iv + 2] * R[a * 3 + 2];
            for (int a = 0; a < 3; a++) M[i * n + iv + a] = tmp[a];
        }
        for (int a = 0; a < 3; a++)
            tmp[a] = R[a * 3 + 0] * h[iv] + R[a * 3 + 1] * h[iv + 1] + R[a * 3 + 2] * h[iv + 2];
        for (int a = 0; a < 3; a++) h[iv + a] = tmp[a];
    }
}

/* tree_dynamics: M and h at (q, u): forward_kinematics, then mass_matrix_and_forces. */
void tree_dynamics(const double *q, const double *u, const tree_t *t, const frames_t *f,
                   const inertias_t *b, double *M, double *h) {
    forward_kinematics(q, t, f);
    mass_matrix_and_forces(u, t, f, b, M, h);
}

/* midpoint_dynamics: q^M = q ⊕ ½Δt F(q) u (Eqn. 6), M and h at (q^M, u^S) (tree_dynamics)
 * and the contacts' g_N, positions and W^T at q^M (contact_points). */
void midpoint_dynamics(const double *q, const double *u, double half_dt, const tree_t *t,
                       const frames_t *f, const inertias_t *b, const contact_points_t *c,
                       const ground_t *g, double jacobian_gap, double *qM, double *M, double *h,
                       double *gap, double *position, double *Wt) {
    integrate_forest(q, u, half_dt, t, qM);
    tree_dynamics(qM, u, t, f, b, M, h);
    contact_points(t, f, c, g, jacobian_gap, gap, position, Wt);
}

/* add_at: h[idx[k]] += values[k]. */
void add_at(double *h, const i64 *idx, const double *values, i64 n) {
    for (i64 k = 0; k < n; k++) h[idx[k]] += values[k];
}

/* rigid_body_forces: h = [m g ; −ω × Θ ω] per free body (frames at the CoM, inertial linear
 * velocity). */
void rigid_body_forces(const double *q, const double *u, i64 n_roots, const i64 *root_q,
                       const i64 *root_v, const double *mass, const double *inertia,
                       const double *gravity, double *h) {
    (void)q;
    (void)root_q;
    for (i64 r = 0; r < n_roots; r++) {
        i64 iv = root_v[r];
        for (int a = 0; a < 3; a++) h[iv + a] = mass[r] * gravity[a];
        double w0 = u[iv + 3], w1 = u[iv + 4], w2 = u[iv + 5];
        const double *I = inertia + 9 * r;
        double l0 = I[0] * w0 + I[1] * w1 + I[2] * w2;
        double l1 = I[3] * w0 + I[4] * w1 + I[5] * w2;
        double l2 = I[6] * w0 + I[7] * w1 + I[8] * w2;
        h[iv + 3] = -(w1 * l2 - w2 * l1);
        h[iv + 4] = -(w2 * l0 - w0 * l2);
        h[iv + 5] = -(w0 * l1 - w1 * l0);
    }
}

/* angular_jacobian: J (3 x nv) of the world angular velocity of joint frame j (only the
 * supporting joints' columns written; the rest zeroed first when `zero`). */
void angular_jacobian(i64 j, const tree_t *t, const double *oR, double *out, int zero) {
    i64 nv = t->nv, nj = t->nj;
    if (zero)
        for (i64 k = 0; k < 3 * nv; k++) out[k] = 0.0;
    for (i64 k = 1; k < nj; k++) {
        if (!t->support[j * nj + k]) continue;
        i64 iv = t->idx_v[k];
        const double *R = oR + 9 * k;
        if (t->jtype[k] == JT_FREEFLYER) {
            for (int r = 0; r < 3; r++)
                for (int c = 0; c < 3; c++) out[r * nv + iv + 3 + c] = R[r * 3 + c];
        } else {
            const double *ax = t->axis + 3 * k;
            for (int r = 0; r < 3; r++)
                out[r * nv + iv] =
                    R[r * 3 + 0] * ax[0] + R[r * 3 + 1] * ax[1] + R[r * 3 + 2] * ax[2];
        }
    }
}

/* rotate: out = R v */
static inline void rotate(const double *R, const double *v, double *out) {
    for (int r = 0; r < 3; r++)
        out[r] = R[r * 3 + 0] * v[0] + R[r * 3 + 1] * v[1] + R[r * 3 + 2] * v[2];
}

/* cut_columns: the dofs of the joints that support body P or body C, ascending, into cols;
 * returns their number. */
static i64 cut_columns(i64 P, i64 C, const tree_t *t, i64 *cols) {
    i64 n = 0, nj = t->nj;
    for (i64 k = 1; k < nj; k++) {
        if (t->support[P * nj + k] || t->support[C * nj + k]) {
            i64 iv = t->idx_v[k];
            i64 e = iv + (t->jtype[k] == JT_FREEFLYER ? 6 : 1);
            for (i64 c = iv; c < e; c++) cols[n++] = c;
        }
    }
    return n;
}

/* zero_columns: J[:, cols[:n]] = 0 (J: 3 x nv) */
static inline void zero_columns(double *J, i64 nv, const i64 *cols, i64 n) {
    for (int r = 0; r < 3; r++)
        for (i64 p = 0; p < n; p++) J[r * nv + cols[p]] = 0.0;
}

/* hinge_axes: the hinge axis a and P's perpendiculars b1, b2 in the world. */
static inline void hinge_axes(const double *oR_P, const double *a_P, const double *b1_P,
                              const double *b2_P, double *aw, double *b1, double *b2) {
    rotate(oR_P, a_P, aw);
    rotate(oR_P, b1_P, b1);
    rotate(oR_P, b2_P, b2);
}

/* angle_and_rate: φ, the rotation of C's b1 about the hinge axis aw seen in P's (b1, b2)
 * basis, and φ̇ = aw·(ω_C − ω_P) over the columns cols (n) of the angular Jacobians JP, JC
 * (t: scratch). */
static inline void angle_and_rate(const double *oR_C, const double *b1_C, const double *aw,
                                  const double *b1, const double *b2, const double *JP,
                                  const double *JC, i64 nv, const double *u, double *t,
                                  const i64 *cols, i64 n, double *angle, double *rate) {
    rotate(oR_C, b1_C, t); /* b1 carried by C (the joint frames coincide at φ = 0) */
    *angle = atan2(t[0] * b2[0] + t[1] * b2[1] + t[2] * b2[2],
                   t[0] * b1[0] + t[1] * b1[1] + t[2] * b1[2]);
    double s = 0.0;
    for (i64 p = 0; p < n; p++) {
        i64 c = cols[p];
        s += (aw[0] * (JC[c] - JP[c]) + aw[1] * (JC[nv + c] - JP[nv + c]) +
              aw[2] * (JC[2 * nv + c] - JP[2 * nv + c])) *
             u[c];
    }
    *rate = s;
}

/* cut_joints: for every cut joint k, the 5 rows of W_B^T (Wt_B: 5 ncut x nv; only the columns
 * of the velocities the two bodies depend on are written), g_B = [x_P − x_C; −(R_C a_C)·b2;
 * (R_C a_C)·b1], φ, φ̇ and the hinge axis in the world (axis_world: ncut x 3); the forward
 * kinematics of q first when do_fk. */
void cut_joints(const double *q, const double *u, const tree_t *t, const frames_t *f,
                const cuts_t *c, double *Wt_B, double *g_B, double *angle, double *rate,
                double *axis_world, int do_fk, arena_t *a) {
    if (do_fk) forward_kinematics(q, t, f);
    i64 nv = t->nv;
    const double *oR = f->oR, *op = f->op;
    /* the scratch: the two bodies' Jacobians, then the vectors below */
    double *buf = arena_f(a, 6 * nv + 21);
    double *JP = buf, *JC = buf + 3 * nv, *v = buf + 6 * nv;
    double *aw = v, *b1 = v + 3, *b2 = v + 6, *tv = v + 9, *xP = v + 12, *xC = v + 15,
           *acw = v + 18;
    i64 *cols = arena_i(a, nv);
    for (i64 k = 0; k < c->ncut; k++) {
        i64 P = c->P[k];
        i64 C = c->C[k];
        i64 n = cut_columns(P, C, t, cols);
        rotate(oR + 9 * P, c->p_P + 3 * k, tv);
        for (int r = 0; r < 3; r++) xP[r] = op[3 * P + r] + tv[r];
        rotate(oR + 9 * C, c->p_C + 3 * k, tv);
        for (int r = 0; r < 3; r++) xC[r] = op[3 * C + r] + tv[r];
        hinge_axes(oR + 9 * P, c->a_P + 3 * k, c->b1_P + 3 * k, c->b2_P + 3 * k, aw, b1, b2);
        rotate(oR + 9 * C, c->a_C + 3 * k, acw);
        i64 row = 5 * k;
        zero_columns(JP, nv, cols, n);
        zero_columns(JC, nv, cols, n);
        point_jacobian(P, xP, t, f, JP, 0);
        point_jacobian(C, xC, t, f, JC, 0);
        for (int r = 0; r < 3; r++) {
            for (i64 p = 0; p < n; p++) {
                i64 col = cols[p];
                Wt_B[(row + r) * nv + col] = JP[r * nv + col] - JC[r * nv + col];
            }
            g_B[row + r] = xP[r] - xC[r];
        }
        zero_columns(JP, nv, cols, n);
        zero_columns(JC, nv, cols, n);
        angular_jacobian(P, t, oR, JP, 0);
        angular_jacobian(C, t, oR, JC, 0);
        for (i64 p = 0; p < n; p++) {
            i64 col = cols[p];
            double d0 = JC[col] - JP[col];
            double d1 = JC[nv + col] - JP[nv + col];
            double d2 = JC[2 * nv + col] - JP[2 * nv + col];
            Wt_B[(row + 3) * nv + col] = b1[0] * d0 + b1[1] * d1 + b1[2] * d2;
            Wt_B[(row + 4) * nv + col] = b2[0] * d0 + b2[1] * d1 + b2[2] * d2;
        }
        /* d/dt (a_C·b2) = −b1·(ω_C − ω_P), d/dt (a_C·b1) = b2·(ω_C − ω_P) */
        g_B[row + 3] = -(acw[0] * b2[0] + acw[1] * b2[1] + acw[2] * b2[2]);
        g_B[row + 4] = acw[0] * b1[0] + acw[1] * b1[1] + acw[2] * b1[2];
        angle_and_rate(oR + 9 * C, c->b1_C + 3 * k, aw, b1, b2, JP, JC, nv, u, tv, cols, n,
                       angle + k, rate + k);
        for (int r = 0; r < 3; r++) axis_world[3 * k + r] = aw[r];
    }
}

/* cut_joint_motion: φ and φ̇ of every cut joint at (q, u) with the arithmetic of cut_joints
 * (the forward kinematics of q into f). */
void cut_joint_motion(const double *q, const double *u, const tree_t *t, const frames_t *f,
                      const cuts_t *c, double *angle, double *rate, arena_t *a) {
    forward_kinematics(q, t, f);
    i64 nv = t->nv;
    const double *oR = f->oR;
    double *buf = arena_f(a, 6 * nv + 21);
    double *JP = buf, *JC = buf + 3 * nv, *v = buf + 6 * nv;
    double *aw = v, *b1 = v + 3, *b2 = v + 6, *tv = v + 9;
    i64 *cols = arena_i(a, nv);
    for (i64 k = 0; k < c->ncut; k++) {
        i64 P = c->P[k];
        i64 C = c->C[k];
        i64 n = cut_columns(P, C, t, cols);
        hinge_axes(oR + 9 * P, c->a_P + 3 * k, c->b1_P + 3 * k, c->b2_P + 3 * k, aw, b1, b2);
        zero_columns(JP, nv, cols, n);
        zero_columns(JC, nv, cols, n);
        angular_jacobian(P, t, oR, JP, 0);
        angular_jacobian(C, t, oR, JC, 0);
        angle_and_rate(oR + 9 * C, c->b1_C + 3 * k, aw, b1, b2, JP, JC, nv, u, tv, cols, n,
                       angle + k, rate + k);
    }
}

/* gather_joint_values: out[k] = x[index[k]] for a joint inside a tree (cut_index[k] < 0),
 * cut_values[cut_index[k]] for a cut joint. */
void gather_joint_values(const double *x, const i64 *index, const double *cut_values,
                         const i64 *cut_index, i64 n, double *out) {
    for (i64 k = 0; k < n; k++) {
        i64 c = cut_index[k];
        out[k] = c < 0 ? x[index[k]] : cut_values[c];
    }
}

/* cut_joint_torques: h += J_ω,C^T (τ a) − J_ω,P^T (τ a) for the cut joints' actuators, over
 * the velocities the two bodies depend on (h: nv). */
void cut_joint_torques(const double *tau_cut, const cuts_t *c, const double *axis_world,
                       const tree_t *t, const double *oR, double *h, arena_t *a) {
    i64 nv = t->nv;
    double *J = arena_f(a, 3 * nv);
    i64 *cols = arena_i(a, nv);
    for (i64 k = 0; k < c->ncut; k++) {
        double tq = tau_cut[k];
        if (tq == 0.0) continue;
        double f0 = tq * axis_world[3 * k], f1 = tq * axis_world[3 * k + 1],
               f2 = tq * axis_world[3 * k + 2];
        i64 n = cut_columns(c->P[k], c->C[k], t, cols);
        zero_columns(J, nv, cols, n);
        angular_jacobian(c->C[k], t, oR, J, 0);
        for (i64 p = 0; p < n; p++) {
            i64 col = cols[p];
            h[col] += J[col] * f0 + J[nv + col] * f1 + J[2 * nv + col] * f2;
        }
        zero_columns(J, nv, cols, n);
        angular_jacobian(c->P[k], t, oR, J, 0);
        for (i64 p = 0; p < n; p++) {
            i64 col = cols[p];
            h[col] -= J[col] * f0 + J[nv + col] * f1 + J[2 * nv + col] * f2;
        }
    }
}
