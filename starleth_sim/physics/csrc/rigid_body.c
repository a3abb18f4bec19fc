/* Mass matrix M and forces h of a forest of floating trees in the paper's coordinates
 * (rigid_body.py): composite-rigid-body algorithm and recursive Newton-Euler (Featherstone
 * 2008) in the world frame, Plücker coordinates at the world origin, motion [ω; v_O],
 * force [n_O; f]. */
#include "core.h"

/* cross3: (a0, a1, a2) x (b0, b1, b2) into o */
static inline void cross3(double a0, double a1, double a2, double b0, double b1, double b2,
                          double *o) {
    o[0] = a1 * b2 - a2 * b1;
    o[1] = a2 * b0 - a0 * b2;
    o[2] = a0 * b1 - a1 * b0;
}

/* motion_subspace: S (6 x nv), the world-frame motion subspace of every joint's velocities;
 * a root: S = [[0, R]; [1, p x R]], a revolute joint: S = [a; p x a]. */
static void motion_subspace(const tree_t *t, const frames_t *f, double *S) {
    i64 nv = t->nv;
    const double *oR = f->oR, *op = f->op;
    for (i64 k = 0; k < 6 * nv; k++) S[k] = 0.0;
    for (i64 j = 1; j < t->nj; j++) {
        i64 iv = t->idx_v[j];
        double p0 = op[3 * j], p1 = op[3 * j + 1], p2 = op[3 * j + 2];
        const double *R = oR + 9 * j;
        double x[3];
        if (t->jtype[j] == JT_FREEFLYER) {
            for (int i = 0; i < 3; i++) {
                S[(3 + i) * nv + iv + i] = 1.0;
                double a0 = R[0 * 3 + i], a1 = R[1 * 3 + i], a2 = R[2 * 3 + i];
                S[0 * nv + iv + 3 + i] = a0;
                S[1 * nv + iv + 3 + i] = a1;
                S[2 * nv + iv + 3 + i] = a2;
                cross3(p0, p1, p2, a0, a1, a2, x);
                S[3 * nv + iv + 3 + i] = x[0];
                S[4 * nv + iv + 3 + i] = x[1];
                S[5 * nv + iv + 3 + i] = x[2];
            }
        } else {
            const double *ax = t->axis + 3 * j;
            double a0 = R[0] * ax[0] + R[1] * ax[1] + R[2] * ax[2];
            double a1 = R[3] * ax[0] + R[4] * ax[1] + R[5] * ax[2];
            double a2 = R[6] * ax[0] + R[7] * ax[1] + R[8] * ax[2];
            S[0 * nv + iv] = a0;
            S[1 * nv + iv] = a1;
            S[2 * nv + iv] = a2;
            cross3(p0, p1, p2, a0, a1, a2, x);
            S[3 * nv + iv] = x[0];
            S[4 * nv + iv] = x[1];
            S[5 * nv + iv] = x[2];
        }
    }
}

/* A spatial inertia at the world origin, [[Ī, m [c]x]; [m [c]x^T, m 1]] with Ī = I_c − m [c]x²,
 * held by its entries that are not zero by construction: Ī (3 x 3), mc = m c and m (a sum of
 * such inertias, the composite one, keeps the zeros exact). INERTIA_STRIDE floats: Ī, mc, m. */
enum { INERTIA_STRIDE = 13 };

/* spatial_inertias: out[j] (INERTIA_STRIDE), body j's spatial inertia in the world frame at
 * the world origin. scratch: 21 floats. */
static void spatial_inertias(const tree_t *t, const frames_t *f, const inertias_t *b, double *out,
                             double *scratch) {
    const double *oR = f->oR, *op = f->op;
    double *RI = scratch, *Iw = scratch + 9, *c = scratch + 18;
    for (i64 j = 1; j < t->nj; j++) {
        double m = b->mass[j];
        const double *R = oR + 9 * j, *lev = b->lever + 3 * j, *in = b->inertia + 9 * j;
        for (int r = 0; r < 3; r++)
            c[r] = op[3 * j + r] + R[r * 3 + 0] * lev[0] + R[r * 3 + 1] * lev[1] +
                   R[r * 3 + 2] * lev[2];
        for (int r = 0; r < 3; r++)
            for (int k = 0; k < 3; k++)
                RI[r * 3 + k] = R[r * 3 + 0] * in[0 * 3 + k] + R[r * 3 + 1] * in[1 * 3 + k] +
                                R[r * 3 + 2] * in[2 * 3 + k];
        for (int r = 0; r < 3; r++)
            for (int k = 0; k < 3; k++)
                Iw[r * 3 + k] = RI[r * 3 + 0] * R[k * 3 + 0] + RI[r * 3 + 1] * R[k * 3 + 1] +
                                RI[r * 3 + 2] * R[k * 3 + 2];
        /* −[c]x² = |c|² 1 − c c^T */
        double cc = c[0] * c[0] + c[1] * c[1] + c[2] * c[2];
        double *I = out + INERTIA_STRIDE * j;
        for (int r = 0; r < 3; r++)
            for (int k = 0; k < 3; k++)
                I[r * 3 + k] = Iw[r * 3 + k] + m * ((r == k ? cc : 0.0) - c[r] * c[k]);
        I[9] = m * c[0];
        I[10] = m * c[1];
        I[11] = m * c[2];
        I[12] = m;
    }
}

/* inertia_times: y = I x for a spatial inertia I (INERTIA_STRIDE) and a motion x, the products
 * with I's zero entries left out (the sums' order that of the full 6 x 6 product's rows) */
static inline void inertia_times(const double *I, const double *x, double *y) {
    double mc0 = I[9], mc1 = I[10], mc2 = I[11], m = I[12];
    y[0] = I[0] * x[0] + I[1] * x[1] + I[2] * x[2] + -mc2 * x[4] + mc1 * x[5];
    y[1] = I[3] * x[0] + I[4] * x[1] + I[5] * x[2] + mc2 * x[3] + -mc0 * x[5];
    y[2] = I[6] * x[0] + I[7] * x[1] + I[8] * x[2] + -mc1 * x[3] + mc0 * x[4];
    y[3] = mc2 * x[1] + -mc1 * x[2] + m * x[3];
    y[4] = -mc2 * x[0] + mc0 * x[2] + m * x[4];
    y[5] = mc1 * x[0] + -mc0 * x[1] + m * x[5];
}

/* inertia_times_column: inertia_times of x = column col of S (6 x nv) */
static inline void inertia_times_column(const double *I, const double *S, i64 nv, i64 col,
                                        double *y) {
    double x[6];
    for (int r = 0; r < 6; r++) x[r] = S[r * nv + col];
    inertia_times(I, x, y);
}

/* mass_matrix_and_forces: M (nv x nv, full) by the CRBA and h = −(C(q, u) u + g(q)) by the
 * RNEA (q̈ = 0, gravity as a base acceleration); forward_kinematics must have been run. */
void mass_matrix_and_forces(const double *u, const tree_t *t, const frames_t *f,
                            const inertias_t *b, double *M, double *h) {
    i64 nj = t->nj, nv = t->nv;
    const i64 *parent = t->parent, *jtype = t->jtype, *idx_v = t->idx_v;
    /* I (INERTIA_STRIDE each), V, A, F, S, vj, hv, f and spatial_inertias' work space in one
     * block; every entry is written before it is read but those of body 0 (the world),
     * zeroed below */
    double scratch[(INERTIA_STRIDE + 18) * nj + 6 * nv + 39];
    double *I = scratch, *V = scratch + INERTIA_STRIDE * nj, *A = V + 6 * nj, *F = A + 6 * nj,
           *S = F + 6 * nj;
    double *vj = S + 6 * nv, *hv = vj + 6, *fv = vj + 12, *work = vj + 18;
    motion_subspace(t, f, S);
    spatial_inertias(t, f, b, I, work);
    for (int r = 0; r < 6; r++) {
        V[r] = 0.0;
        A[r] = 0.0;
        F[r] = 0.0;
    }
    for (int r = 0; r < INERTIA_STRIDE; r++) I[r] = 0.0;
    /* -- RNEA, forward pass: V_j = V_λ(j) + S_j u_j, A_j = A_λ(j) + Ṡ_j u_j, A_0 = −g */
    for (int r = 0; r < 3; r++) A[3 + r] = -b->gravity[r];
    double x[3], y[3], z[3];
    for (i64 j = 1; j < nj; j++) {
        i64 par = parent[j];
        i64 iv = idx_v[j];
        int nd = jtype[j] == JT_FREEFLYER ? 6 : 1;
        double *Vj = V + 6 * j, *Aj = A + 6 * j, *Fj = F + 6 * j;
        const double *Vp = V + 6 * par, *Ap = A + 6 * par;
        for (int r = 0; r < 6; r++) {
            double s = 0.0;
            for (int d = 0; d < nd; d++) s += S[r * nv + iv + d] * u[iv + d];
            vj[r] = s;
            Vj[r] = Vp[r] + s;
        }
        double w0 = Vj[0], w1 = Vj[1], w2 = Vj[2];
        if (jtype[j] == JT_FREEFLYER) {
            /* Ṡ u = [0; −ω × ṗ] */
            cross3(w0, w1, w2, u[iv], u[iv + 1], u[iv + 2], x);
            for (int r = 0; r < 3; r++) Aj[r] = Ap[r];
            Aj[3] = Ap[3] - x[0];
            Aj[4] = Ap[4] - x[1];
            Aj[5] = Ap[5] - x[2];
        } else {
            /* Ṡ u = V_j ×ₘ (S_j u_j) = [ω × vj_ω; ω × vj_v + v × vj_ω] */
            double v0 = Vj[3], v1 = Vj[4], v2 = Vj[5];
            cross3(w0, w1, w2, vj[0], vj[1], vj[2], x);
            cross3(w0, w1, w2, vj[3], vj[4], vj[5], y);
            cross3(v0, v1, v2, vj[0], vj[1], vj[2], z);
            Aj[0] = Ap[0] + x[0];
            Aj[1] = Ap[1] + x[1];
            Aj[2] = Ap[2] + x[2];
            Aj[3] = Ap[3] + y[0] + z[0];
            Aj[4] = Ap[4] + y[1] + z[1];
            Aj[5] = Ap[5] + y[2] + z[2];
        }
        /* F_j = I_j A_j + V_j ×* (I_j V_j),  [ω; v] ×* [n; f] = [ω × n + v × f; ω × f] */
        const double *Ij = I + INERTIA_STRIDE * j;
        inertia_times(Ij, Aj, Fj);
        inertia_times(Ij, Vj, hv);
        double v0 = Vj[3], v1 = Vj[4], v2 = Vj[5];
        double c[3];
        cross3(w0, w1, w2, hv[0], hv[1], hv[2], x);
        cross3(v0, v1, v2, hv[3], hv[4], hv[5], y);
        cross3(w0, w1, w2, hv[3], hv[4], hv[5], c);
        Fj[0] += x[0] + y[0];
        Fj[1] += x[1] + y[1];
        Fj[2] += x[2] + y[2];
        Fj[3] += c[0];
        Fj[4] += c[1];
        Fj[5] += c[2];
    }
    /* -- backward pass: h_j = −S_j^T F_j, F_λ(j) += F_j; composite inertias Ic (in I) */
    double *Ic = I;
    for (i64 j = nj - 1; j > 0; j--) {
        i64 iv = idx_v[j];
        int nd = jtype[j] == JT_FREEFLYER ? 6 : 1;
        for (int d = 0; d < nd; d++) {
            double s = 0.0;
            for (int r = 0; r < 6; r++) s += S[r * nv + iv + d] * F[6 * j + r];
            h[iv + d] = -s;
        }
        i64 par = parent[j];
        if (par > 0) {
            for (int r = 0; r < 6; r++) F[6 * par + r] += F[6 * j + r];
            for (int r = 0; r < INERTIA_STRIDE; r++)
                Ic[INERTIA_STRIDE * par + r] += Ic[INERTIA_STRIDE * j + r];
        }
    }
    /* -- CRBA: M[k, j] = S_k^T Ic_j S_j for k = j and the ancestors of j */
    for (i64 k = 0; k < nv * nv; k++) M[k] = 0.0;
    for (i64 j = 1; j < nj; j++) {
        i64 iv = idx_v[j];
        const double *Icj = Ic + INERTIA_STRIDE * j;
        int nd = jtype[j] == JT_FREEFLYER ? 6 : 1;
        for (int d = 0; d < nd; d++) {
            i64 col = iv + d;
            inertia_times_column(Icj, S, nv, col, fv);
            i64 a = j;
            while (a > 0) {
                i64 ia = idx_v[a];
                int ne = jtype[a] == JT_FREEFLYER ? 6 : 1;
                for (int e = 0; e < ne; e++) {
                    i64 row = ia + e;
                    if (a == j && row > col) continue;
                    double s = 0.0;
                    for (int r = 0; r < 6; r++) s += S[r * nv + row] * fv[r];
                    M[row * nv + col] = s;
                    M[col * nv + row] = s;
                }
                a = parent[a];
            }
        }
    }
}
