/* Contact-point kinematics of a kinematic tree (kinematics.py): forward kinematics, point
 * Jacobians in the world frame, and the contacts' gaps g_N, positions and W^T. */
#include "core.h"

/* axis_angle_to_rot: R (3 x 3) of the rotation by theta about the unit axis a. */
static void axis_angle_to_rot(const double *a, double theta, double *R) {
    double c = cos(theta);
    double s = sin(theta);
    double t = 1.0 - c;
    double x = a[0], y = a[1], z = a[2];
    R[0] = t * x * x + c;
    R[1] = t * x * y - s * z;
    R[2] = t * x * z + s * y;
    R[3] = t * x * y + s * z;
    R[4] = t * y * y + c;
    R[5] = t * y * z - s * x;
    R[6] = t * x * z - s * y;
    R[7] = t * y * z + s * x;
    R[8] = t * z * z + c;
}

/* matmul3: out = A B for 3 x 3 matrices. */
static void matmul3(const double *A, const double *B, double *out) {
    for (int r = 0; r < 3; r++)
        for (int c = 0; c < 3; c++)
            out[r * 3 + c] = A[r * 3 + 0] * B[0 * 3 + c] + A[r * 3 + 1] * B[1 * 3 + c] +
                             A[r * 3 + 2] * B[2 * 3 + c];
}

/* forward_kinematics: world placements (oR[j], op[j]) of all joint frames,
 * oM_j = oM_parent · placement_j · M_j(q). */
void forward_kinematics(const double *q, const tree_t *t, const frames_t *f) {
    double *oR = f->oR, *op = f->op;
    for (int r = 0; r < 3; r++) {
        for (int c = 0; c < 3; c++) oR[r * 3 + c] = r == c ? 1.0 : 0.0;
        op[r] = 0.0;
    }
    double scratch[21] = {0.0}; /* Rq, tmp, pq */
    double *Rq = scratch, *tmp = scratch + 9, *pq = scratch + 18;
    for (i64 j = 1; j < t->nj; j++) {
        i64 iq = t->idx_q[j];
        if (t->jtype[j] == JT_FREEFLYER) {
            quat_xyzw_to_rot(q[iq + 3], q[iq + 4], q[iq + 5], q[iq + 6], Rq);
            pq[0] = q[iq];
            pq[1] = q[iq + 1];
            pq[2] = q[iq + 2];
        } else {
            axis_angle_to_rot(t->axis + 3 * j, q[iq], Rq);
            pq[0] = 0.0;
            pq[1] = 0.0;
            pq[2] = 0.0;
        }
        i64 par = t->parent[j];
        const double *plR = t->pl_R + 9 * j, *plp = t->pl_p + 3 * j;
        const double *oRp = oR + 9 * par;
        /* p_local = placement.p + placement.R pq ; op = op_par + oR_par p_local */
        for (int r = 0; r < 3; r++) {
            double pl =
                plp[r] + plR[r * 3 + 0] * pq[0] + plR[r * 3 + 1] * pq[1] + plR[r * 3 + 2] * pq[2];
            tmp[r] = pl;
        }
        for (int r = 0; r < 3; r++)
            op[3 * j + r] = op[3 * par + r] + oRp[r * 3 + 0] * tmp[0] + oRp[r * 3 + 1] * tmp[1] +
                            oRp[r * 3 + 2] * tmp[2];
        matmul3(plR, Rq, tmp);
        matmul3(oRp, tmp, oR + 9 * j);
    }
}

/* point_jacobian: J (3 x nv) of the world velocity of the point at world position p attached
 * to joint frame j; only the supporting joints' columns are written (the rest zeroed first
 * when `zero`). */
void point_jacobian(i64 j, const double *p, const tree_t *t, const frames_t *f, double *out,
                    int zero) {
    i64 nv = t->nv, nj = t->nj;
    const double *oR = f->oR, *op = f->op;
    if (zero)
        for (i64 k = 0; k < 3 * nv; k++) out[k] = 0.0;
    for (i64 k = 1; k < nj; k++) {
        if (!t->support[j * nj + k]) continue;
        i64 iv = t->idx_v[k];
        double d0 = p[0] - op[3 * k + 0];
        double d1 = p[1] - op[3 * k + 1];
        double d2 = p[2] - op[3 * k + 2];
        if (t->jtype[k] == JT_FREEFLYER) {
            const double *R = oR + 9 * k;
            for (int c = 0; c < 3; c++) {
                /* linear velocity of the root in the inertial frame */
                out[c * nv + iv + c] = 1.0;
                /* angular velocity in the root (body) frame: (R e_c) x d */
                double a0 = R[0 * 3 + c], a1 = R[1 * 3 + c], a2 = R[2 * 3 + c];
                out[0 * nv + iv + 3 + c] = a1 * d2 - a2 * d1;
                out[1 * nv + iv + 3 + c] = a2 * d0 - a0 * d2;
                out[2 * nv + iv + 3 + c] = a0 * d1 - a1 * d0;
            }
        } else {
            const double *R = oR + 9 * k, *ax = t->axis + 3 * k;
            double a0 = R[0] * ax[0] + R[1] * ax[1] + R[2] * ax[2];
            double a1 = R[3] * ax[0] + R[4] * ax[1] + R[5] * ax[2];
            double a2 = R[6] * ax[0] + R[7] * ax[1] + R[8] * ax[2];
            out[0 * nv + iv] = a1 * d2 - a2 * d1;
            out[1 * nv + iv] = a2 * d0 - a0 * d2;
            out[2 * nv + iv] = a0 * d1 - a1 * d0;
        }
    }
}

/* slot i of the contacts: its surface frame fr (n, t1, t2, μ) into g->frames when given,
 * P_i = c − r n and, for g_N,i ≤ jacobian_gap, Wt[i] = [n, t1, t2]^T J_P,i at P_i on joint j */
static void contact_slot(const tree_t *t, const frames_t *f, const ground_t *g, i64 i, i64 j,
                         const double *ci, double r, const double *fr, double gap,
                         double jacobian_gap, double *position, double *Wt, double *J) {
    i64 nv = t->nv;
    const double *n = fr, *t1 = fr + 3, *t2 = fr + 6;
    if (g->frames)
        for (int k = 0; k < FRAME_STRIDE; k++) g->frames[FRAME_STRIDE * i + k] = fr[k];
    for (int k = 0; k < 3; k++) position[3 * i + k] = ci[k] - r * n[k];
    if (gap > jacobian_gap) return;
    point_jacobian(j, position + 3 * i, t, f, J, 1);
    double *W0 = Wt + (3 * i + 0) * nv, *W1 = Wt + (3 * i + 1) * nv, *W2 = Wt + (3 * i + 2) * nv;
    for (i64 col = 0; col < nv; col++) {
        W0[col] = n[0] * J[col] + n[1] * J[nv + col] + n[2] * J[2 * nv + col];
        W1[col] = t1[0] * J[col] + t1[1] * J[nv + col] + t1[2] * J[2 * nv + col];
        W2[col] = t2[0] * J[col] + t2[1] * J[nv + col] + t2[2] * J[2 * nv + col];
    }
}

/* contact_points: g_N,i = n·c_i − offset − r_i, P_i = c_i − r_i n and, for g_N,i ≤
 * jacobian_gap, Wt[i] = [n, t1, t2]^T J_P,i (nc x 3 x nv; the other rows left as they were),
 * from the placements of forward_kinematics; (n, t1, t2) the plane's, or on a terrain those
 * of the contact's surface (terrain_contact), written with μ into g->frames when given.
 * On a terrain with second surfaces (terrain_has_second_surfaces) the nc contacts are two
 * slots per sphere, i and nc/2 + i (i < nc/2; c_joint, c_local, c_radius repeat): its
 * nearest surface and its second one (terrain_contact), in that order unless the slots held
 * them the other way round at the last call with g->frames (entry 10: the surface). */
void contact_points(const tree_t *t, const frames_t *f, const contact_points_t *c,
                    const ground_t *g, double jacobian_gap, double *gap, double *position,
                    double *Wt) {
    i64 nv = t->nv;
    const double *oR = f->oR, *op = f->op;
    int flat = terrain_is_flat(g);
    int two = !flat && terrain_has_second_surfaces(g);
    i64 ns = two ? c->nc / 2 : c->nc;
    double J[3 * nv + 1]; /* (+1: never a zero-length array) */
    double ci[3], fr[FRAME_STRIDE], fr2[FRAME_STRIDE];
    if (flat) {
        for (int k = 0; k < 3; k++) {
            fr[k] = g->n[k];
            fr[3 + k] = g->t1[k];
            fr[6 + k] = g->t2[k];
        }
        fr[9] = terrain_plane_mu(g);
        fr[10] = 1.0;
    }
    for (i64 i = 0; i < ns; i++) {
        i64 j = c->joint[i];
        const double *R = oR + 9 * j, *loc = c->local + 3 * i;
        for (int k = 0; k < 3; k++)
            ci[k] = R[k * 3 + 0] * loc[0] + R[k * 3 + 1] * loc[1] + R[k * 3 + 2] * loc[2] +
                    op[3 * j + k];
        double r = c->radius[i];
        if (flat) {
            const double *n = g->n;
            gap[i] = n[0] * ci[0] + n[1] * ci[1] + n[2] * ci[2] - g->offset - r;
        } else if (!two) {
            double g2;
            gap[i] = terrain_contact(g, ci, r, fr, NULL, &g2);
        } else {
            /* a slot keeps its surface while the sphere keeps it (its memory, warm start,
             * hysteresis, Alg. 1's anchor, is that surface's): the two swap when the one the
             * second slot held at the last step (g->frames) is now the nearest */
            double g1, g2;
            g1 = terrain_contact(g, ci, r, fr, fr2, &g2);
            double was0 = g->frames ? g->frames[FRAME_STRIDE * i + 10] : 0.0;
            double was1 = g->frames ? g->frames[FRAME_STRIDE * (ns + i) + 10] : 0.0;
            double s1 = fr[10], s2 = fr2[10];
            int swap = (s1 == was1 && s1 != was0) || (s2 != 0.0 && s2 == was0 && s2 != was1);
            const double *a = swap ? fr2 : fr, *b = swap ? fr : fr2;
            gap[i] = swap ? g2 : g1;
            gap[ns + i] = swap ? g1 : g2;
            contact_slot(t, f, g, ns + i, j, ci, r, b, gap[ns + i], jacobian_gap, position, Wt, J);
            contact_slot(t, f, g, i, j, ci, r, a, gap[i], jacobian_gap, position, Wt, J);
            continue;
        }
        contact_slot(t, f, g, i, j, ci, r, fr, gap[i], jacobian_gap, position, Wt, J);
    }
}

/* contact_kinematics: forward_kinematics at q, then contact_points. */
void contact_kinematics(const double *q, const tree_t *t, const frames_t *f,
                        const contact_points_t *c, const ground_t *g, double jacobian_gap,
                        double *gap, double *position, double *Wt) {
    forward_kinematics(q, t, f);
    contact_points(t, f, c, g, jacobian_gap, gap, position, Wt);
}
