/* What the prox sweeps of prox.c and prox_factored.c share: each row's law (the prox of a
 * contact's rows onto the normal cone and the friction disc, a bilateral or joint friction
 * row's), the JOR update, and the impulse criterion's check (Gehring et al. 2014, Eqn. 12-16). */
#ifndef STARLETH_PROX_ROWS_H
#define STARLETH_PROX_ROWS_H

#include "core.h"

/* prox_normal: Λ_N = −prox_{R0−}(−x), projection onto [0, ∞) (NaN gives 0) */
static inline double prox_normal(double x) {
    return x > 0.0 ? x : 0.0;
}

/* prox_disc: projection of (x1, x2) onto the disc of the given radius */
static inline void prox_disc(double x1, double x2, double radius, double *o1, double *o2) {
    double n2 = x1 * x1 + x2 * x2;
    if (n2 <= radius * radius) {
        *o1 = x1;
        *o2 = x2;
        return;
    }
    if (radius <= 0.0) {
        *o1 = 0.0;
        *o2 = 0.0;
        return;
    }
    double s = radius / sqrt(n2);
    *o1 = x1 * s;
    *o2 = x2 * s;
}

/* project_contact: prox of one contact's rows (out may be lam: all reads before writes) */
static inline void project_contact(const double *lam, i64 b, double xi0, double xi1, double xi2,
                                   const double *r, double mu_i, double *out) {
    double ln = prox_normal(lam[b] - r[b] * xi0);
    double t1, t2;
    prox_disc(lam[b + 1] - r[b + 1] * xi1, lam[b + 2] - r[b + 2] * xi2, mu_i * ln, &t1, &t2);
    out[b] = ln;
    out[b + 1] = t1;
    out[b + 2] = t2;
}

/* prox_row: a row after the contacts': a bilateral row's Λ_B as it is (bound NULL), a joint
 * friction row's projected onto [−bound_k, bound_k] (|Λ_f| ≤ τ_c Δt: the joint sticks inside) */
static inline double prox_row(double x, const double *bound, i64 k) {
    if (!bound) return x;
    double b = bound[k];
    return x > b ? b : (x < -b ? -b : x);
}

/* (ok, res, finite) of check / row_check */
typedef struct {
    int ok;
    double res;
    int finite;
} check_t;

/* row_check: one row's test |ΔΛ| ≤ |Λ_old| tol_rel + tol_abs, carried on in c */
static inline void row_check(double old, double new_, check_t *c, double tol_rel, double tol_abs) {
    double d = fabs(new_ - old);
    if (!isfinite(new_)) c->finite = 0;
    if (d > c->res) c->res = d;
    if (d > fabs(old) * tol_rel + tol_abs) c->ok = 0;
}

/* check: (converged by the impulse criterion, max |ΔΛ|, all finite) */
static inline check_t check(const double *lam_old, const double *lam, i64 n, double tol_rel,
                            double tol_abs) {
    check_t c = {1, 0.0, 1};
    for (i64 l = 0; l < n; l++) row_check(lam_old[l], lam[l], &c, tol_rel, tol_abs);
    return c;
}

/* jor_project: a JOR update of Λ into new (Λ_B kept with the direct method) */
static inline void jor_project(const double *lam, const double *xi, const double *r,
                               const double *mu, const double *bound, i64 nc, i64 m,
                               int bilateral_direct, double *new_) {
    for (i64 i = 0; i < nc; i++) {
        i64 b = 3 * i;
        project_contact(lam, b, xi[b], xi[b + 1], xi[b + 2], r, mu[i], new_);
    }
    for (i64 l = 3 * nc; l < m; l++)
        new_[l] = bilateral_direct ? lam[l] : prox_row(lam[l] - r[l] * xi[l], bound, l - 3 * nc);
}

/* result: a solve's (iterations, status, residual) */
static inline prox_result_t result(i64 it, i64 status, double res) {
    prox_result_t out = {it, status, res};
    return out;
}

#endif
