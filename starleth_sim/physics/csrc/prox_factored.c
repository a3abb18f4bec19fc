/* The prox without M^{-1}W (a robot at rest, step_kernels.c's lazy try): diag(G) with the
 * factor L of M (M = L^T D L, the tree's sparsity) and JOR in the velocity form with M^{-1}
 * applied by that factor (Eqn. 17-19), for a solve of a few sweeps where forming M^{-1}W and G
 * would cost more than the sweeps. Layouts: Wt m x nv, L nv x nv (row-major). */
#include <string.h>

#include "prox_rows.h"

void factored_delassus_diagonal(const double *Wt, i64 m, i64 nv, const i64 *wp_ptr,
                                const i64 *wp_idx, const double *L, const i64 *dof_parent,
                                double *d, double *Y) {
    for (i64 k = 0; k < nv * m; k++) Y[k] = 0.0;
    for (i64 r = 0; r < m; r++)
        for (i64 p = wp_ptr[r]; p < wp_ptr[r + 1]; p++)
            Y[wp_idx[p] * m + r] = Wt[r * nv + wp_idx[p]];
    for (i64 k = nv - 1; k >= 0; k--) { /* L^T Y = W: leaves to roots, all columns at once */
        const double *yk = Y + k * m;
        for (i64 j = dof_parent[k]; j != -1; j = dof_parent[j]) {
            double l = L[k * nv + j];
            double *yj = Y + j * m;
            for (i64 c = 0; c < m; c++) yj[c] -= l * yk[c];
        }
    }
    for (i64 c = 0; c < m; c++) d[c] = 0.0;
    for (i64 k = 0; k < nv; k++) { /* d = Σ_k Y_k² / D_k, column by column */
        const double *yk = Y + k * m;
        double dinv = 1.0 / L[k * nv + k];
        for (i64 c = 0; c < m; c++) d[c] += yk[c] * yk[c] * dinv;
    }
}

/* factored_impulse_velocity: f = M^{-1} W d (the rows' W^T by their pattern, then the factor
 * L of M), added to u */
static void factored_impulse_velocity(const double *Wt, const patterns_t *pat, i64 m, i64 nv,
                                      const double *d, const double *L, const i64 *dof_parent,
                                      double *f, double *u) {
    for (i64 k = 0; k < nv; k++) f[k] = 0.0;
    for (i64 l = 0; l < m; l++)
        if (d[l] != 0.0)
            for (i64 p = pat->wp_ptr[l]; p < pat->wp_ptr[l + 1]; p++) {
                i64 k = pat->wp_idx[p];
                f[k] = f[k] + Wt[l * nv + k] * d[l];
            }
    ltdl_solve_vec(L, nv, dof_parent, f);
    for (i64 k = 0; k < nv; k++) u[k] = u[k] + f[k];
}

prox_result_t jor_velocity_factored(const settings_t *s, const patterns_t *pat, const double *Wt,
                                    const double *u_free, const double *bvec, i64 m, i64 nv, i64 nc,
                                    const double *mu, const double *r, const double *bound,
                                    double *lam, const double *L, const i64 *dof_parent, double *u,
                                    arena_t *a) {
    double *buf = arena_f(a, 3 * m + nv);
    double *xi = buf, *new_ = buf + m, *d = buf + 2 * m, *f = buf + 3 * m;
    memcpy(u, u_free, (size_t)nv * sizeof(double));
    factored_impulse_velocity(Wt, pat, m, nv, lam, L, dof_parent, f, u);
    double res = 0.0;
    for (i64 k = 0; k < s->max_iterations; k++) {
        for (i64 a_ = 0; a_ < m; a_++) {
            double sm = bvec[a_];
            for (i64 p = pat->wp_ptr[a_]; p < pat->wp_ptr[a_ + 1]; p++)
                sm = sm + Wt[a_ * nv + pat->wp_idx[p]] * u[pat->wp_idx[p]];
            xi[a_] = sm;
        }
        jor_project(lam, xi, r, mu, bound, nc, m, 0, new_);
        check_t ck = check(lam, new_, m, s->tol_rel, s->tol_abs);
        res = ck.res;
        if (!ck.finite) return result(k + 1, STATUS_NONFINITE, res);
        for (i64 l = 0; l < m; l++) d[l] = new_[l] - lam[l];
        factored_impulse_velocity(Wt, pat, m, nv, d, L, dof_parent, f, u);
        memcpy(lam, new_, (size_t)m * sizeof(double));
        if (ck.ok) return result(k + 1, STATUS_CONVERGED, res);
    }
    return result(s->max_iterations, STATUS_MAX_ITER, res);
}
