/* The prox solvers (prox.py): Gehring et al. 2014, Eqn. 12-20, and the adaptive α.
 * Layouts: Wt m x nv, MinvW nv x m, G m x m, M nv x nv, LB nb_LB x nb_LB (row-major). */
#include "core.h"

#include <string.h>

/* prox_normal: Λ_N = −prox_{R0−}(−x), projection onto [0, ∞) (NaN gives 0) */
static inline double prox_normal(double x) { return x > 0.0 ? x : 0.0; }

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

/* The CSR pattern of the rows of the m x n matrix whose entry (r, k) is A[r * rs + k * ks]
 * (row_pattern's loop; col_pattern = row_pattern(A.T) with the strides swapped), one arena
 * buffer for ptr and idx */
static void strided_row_pattern(const double *A, i64 m, i64 n, i64 rs, i64 ks, arena_t *a,
                                i64 **ptr, i64 **idx) {
    i64 *buf = arena_i(a, m + 1 + m * n);
    i64 *p = buf, *ix = buf + m + 1;
    i64 cnt = 0;
    for (i64 r = 0; r < m; r++) {
        p[r] = cnt;
        for (i64 k = 0; k < n; k++)
            if (A[r * rs + k * ks] != 0.0) ix[cnt++] = k;
    }
    p[m] = cnt;
    *ptr = p;
    *idx = ix;
}

/* row_pattern: CSR pattern of the rows of A (m x n) */
void row_pattern(const double *A, i64 m, i64 n, arena_t *a, i64 **ptr, i64 **idx) {
    strided_row_pattern(A, m, n, n, 1, a, ptr, idx);
}

/* col_pattern: row_pattern(A.T), the pattern of the n columns of A (m x n) */
void col_pattern(const double *A, i64 m, i64 n, arena_t *a, i64 **ptr, i64 **idx) {
    strided_row_pattern(A, n, m, 1, n, a, ptr, idx);
}

/* _row_envelopes: first / one past the last nonzero column of each row k of M^{-1}W (nv
 * rows, n columns), from its column pattern */
static void row_envelopes(const i64 *mp_ptr, const i64 *mp_idx, i64 nv, i64 n, arena_t *a,
                          i64 **first_out, i64 **end_out) {
    i64 *buf = arena_i(a, 2 * nv);
    i64 *first = buf, *end = buf + nv;
    for (i64 k = 0; k < nv; k++) {
        first[k] = n;
        end[k] = 0;
    }
    for (i64 b = 0; b < n; b++)
        for (i64 p = mp_ptr[b]; p < mp_ptr[b + 1]; p++) {
            i64 k = mp_idx[p];
            if (b < first[k]) first[k] = b;
            end[k] = b + 1;
        }
    *first_out = first;
    *end_out = end;
}

/* _delassus_rows: G = W^T M^{-1} W row by row (upper part, then mirrored) */
static void delassus_rows(const double *Wt, const double *MinvW, double *G, i64 m, i64 nv,
                          const i64 *wp_ptr, const i64 *wp_idx) {
    for (i64 a = 0; a < m; a++) {
        double *row = G + a * m;
        for (i64 b = a; b < m; b++) row[b] = 0.0;
        for (i64 p = wp_ptr[a]; p < wp_ptr[a + 1]; p++) {
            i64 k = wp_idx[p];
            double w = Wt[a * nv + k];
            const double *mk = MinvW + k * m;
            for (i64 b = a; b < m; b++) row[b] = row[b] + w * mk[b];
        }
        for (i64 b = a + 1; b < m; b++) G[b * m + a] = row[b];
    }
}

/* delassus: G = W^T M^{-1} W (both triangles); over M^{-1}W's row envelopes for m > 24 */
void delassus(const double *Wt, const double *MinvW, double *G, i64 m, i64 nv,
              const i64 *wp_ptr, const i64 *wp_idx, const i64 *mp_ptr, const i64 *mp_idx,
              arena_t *a) {
    if (m <= DELASSUS_ENVELOPE_ROWS) {
        delassus_rows(Wt, MinvW, G, m, nv, wp_ptr, wp_idx);
        return;
    }
    i64 *first, *end;
    row_envelopes(mp_ptr, mp_idx, nv, m, a, &first, &end);
    for (i64 t = 0; t < m * m; t++) G[t] = 0.0;
    for (i64 r = 0; r < m; r++) {
        double *row = G + r * m;
        i64 lo = m, hi = r + 1;
        for (i64 p = wp_ptr[r]; p < wp_ptr[r + 1]; p++) {
            i64 k = wp_idx[p];
            i64 b0 = py_maxi(r, first[k]);
            i64 b1 = end[k];
            if (b1 <= b0) continue;
            lo = py_mini(lo, b0);
            hi = py_maxi(hi, b1);
            double w = Wt[r * nv + k];
            const double *mk = MinvW + k * m;
            for (i64 b = b0; b < b1; b++) row[b] = row[b] + w * mk[b];
        }
        for (i64 b = py_maxi(r + 1, lo); b < hi; b++) G[b * m + r] = row[b];
    }
}

/* delassus_diagonal: diag(G) without forming G */
void delassus_diagonal(const double *Wt, const double *MinvW, double *d, i64 m, i64 nv,
                       const i64 *wp_ptr, const i64 *wp_idx) {
    for (i64 a = 0; a < m; a++) {
        double s = 0.0;
        for (i64 p = wp_ptr[a]; p < wp_ptr[a + 1]; p++) {
            i64 k = wp_idx[p];
            s = s + Wt[a * nv + k] * MinvW[k * m + a];
        }
        d[a] = s;
    }
}

/* prox_parameters: r_N = |α|/G_NN, r_T = |α|/max(G_T1T1, G_T2T2), r_B = |α|/G_BB */
void prox_parameters(const double *Gdiag, i64 m, i64 nc, double alpha, double *r) {
    alpha = fabs(alpha);
    for (i64 i = 0; i < nc; i++) {
        i64 b = 3 * i;
        r[b] = alpha / Gdiag[b];
        double rt = alpha / py_max(Gdiag[b + 1], Gdiag[b + 2]);
        r[b + 1] = rt;
        r[b + 2] = rt;
    }
    for (i64 l = 3 * nc; l < m; l++) r[l] = alpha / Gdiag[l];
}

/* _project_contact: prox of one contact's rows (out may be lam: all reads before writes) */
static inline void project_contact(const double *lam, i64 b, double xi0, double xi1,
                                   double xi2, const double *r, double mu_i, double *out) {
    double ln = prox_normal(lam[b] - r[b] * xi0);
    double t1, t2;
    prox_disc(lam[b + 1] - r[b + 1] * xi1, lam[b + 2] - r[b + 2] * xi2, mu_i * ln, &t1, &t2);
    out[b] = ln;
    out[b + 1] = t1;
    out[b + 2] = t2;
}

/* _kinetic_energy: ½ uᵀ M u */
static double kinetic_energy(const double *M, const double *u, i64 nv) {
    double s = 0.0;
    for (i64 i = 0; i < nv; i++) {
        double row = 0.0;
        for (i64 j = 0; j < nv; j++) row = row + M[i * nv + j] * u[j];
        s = s + u[i] * row;
    }
    return 0.5 * s;
}

/* _add_impulse_columns: u += M^{-1} W[:, :ncols] Λ[:ncols] */
static void add_impulse_columns(const double *MinvW, i64 m, const double *lam, double *u,
                                const i64 *mp_ptr, const i64 *mp_idx, i64 ncols) {
    for (i64 l = 0; l < ncols; l++) {
        double x = lam[l];
        if (x != 0.0)
            for (i64 p = mp_ptr[l]; p < mp_ptr[l + 1]; p++) {
                i64 k = mp_idx[p];
                u[k] = u[k] + MinvW[k * m + l] * x;
            }
    }
}

/* _velocity_from_impulses: u = u_free + M^{-1} W Λ (Eqn. 17) */
static void velocity_from_impulses(const double *u_free, const double *MinvW, i64 nv, i64 m,
                                   const double *lam, double *u, const i64 *mp_ptr,
                                   const i64 *mp_idx) {
    for (i64 k = 0; k < nv; k++) u[k] = u_free[k];
    add_impulse_columns(MinvW, m, lam, u, mp_ptr, mp_idx, m);
}

/* _bilateral_direct_delassus: Λ_B = −G_BB^{-1} (G_BU Λ_U + c_B) (Eqn. 20), with L_B's
 * envelope columns (col_ptr, col_idx) and the right-hand side's buffer rhs */
static void bilateral_direct_delassus(const double *G, const double *c, i64 m, i64 nc,
                                      const double *LB, i64 nb_LB, double *lam,
                                      const i64 *gp_ptr, const i64 *gp_idx,
                                      const i64 *lb_first, const i64 *col_ptr,
                                      const i64 *col_idx, double *rhs) {
    i64 o = 3 * nc;
    i64 nb_ = m - o;
    for (i64 a = 0; a < nb_; a++) {
        double s = c[o + a];
        for (i64 p = gp_ptr[o + a]; p < gp_ptr[o + a + 1]; p++) {
            i64 l = gp_idx[p];
            if (l >= o) break;
            s = s + G[(o + a) * m + l] * lam[l];
        }
        rhs[a] = -s;
    }
    cholesky_solve_envelope(LB, nb_LB, lb_first, col_ptr, col_idx, rhs);
    for (i64 a = 0; a < nb_; a++) lam[o + a] = rhs[a];
}

/* _bilateral_direct_velocity: Λ_B = −G_BB^{-1} W_B^T (u_free + M^{-1} W_U Λ_U) (Eqn. 20);
 * uu (nv) and rhs (m − 3nc) are the caller's work buffers (the Python's copy / np.empty) */
static void bilateral_direct_velocity(const double *Wt, const double *MinvW,
                                      const double *u_free, i64 m, i64 nv, i64 nc,
                                      const double *LB, i64 nb_LB, double *lam,
                                      const patterns_t *pat, double *uu, double *rhs) {
    i64 o = 3 * nc;
    i64 nb_ = m - o;
    for (i64 k = 0; k < nv; k++) uu[k] = u_free[k];
    add_impulse_columns(MinvW, m, lam, uu, pat->mp_ptr, pat->mp_idx, o);
    for (i64 a = 0; a < nb_; a++) {
        double s = 0.0;
        for (i64 p = pat->wp_ptr[o + a]; p < pat->wp_ptr[o + a + 1]; p++) {
            i64 k = pat->wp_idx[p];
            s = s + Wt[(o + a) * nv + k] * uu[k];
        }
        rhs[a] = -s;
    }
    cholesky_solve_vec(LB, nb_LB, pat->lb_first, rhs);
    for (i64 a = 0; a < nb_; a++) lam[o + a] = rhs[a];
}

/* (ok, res, finite) of _check / _row_check */
typedef struct {
    int ok;
    double res;
    int finite;
} check_t;

/* _row_check: one row's test |ΔΛ| ≤ |Λ_old| tol_rel + tol_abs, carried on in c */
static inline void row_check(double old, double new_, check_t *c, double tol_rel,
                             double tol_abs) {
    double d = fabs(new_ - old);
    if (!isfinite(new_)) c->finite = 0;
    if (d > c->res) c->res = d;
    if (d > fabs(old) * tol_rel + tol_abs) c->ok = 0;
}

/* _check: (converged by the impulse criterion, max |ΔΛ|, all finite) */
static check_t check(const double *lam_old, const double *lam, i64 n, double tol_rel,
                     double tol_abs) {
    check_t c = {1, 0.0, 1};
    for (i64 l = 0; l < n; l++) row_check(lam_old[l], lam[l], &c, tol_rel, tol_abs);
    return c;
}

/* ---- adaptive α --------------------------------------------------------------------- */

/* The Delassus operator the adaptive α reads: (form, G, Wt, MinvW, pat) of the Python; the
 * Delassus-form kernels pass G for Wt, the velocity-form ones Wt for G, as the Python does. */
typedef struct {
    i64 form;
    const double *G, *Wt, *MinvW;
    const patterns_t *pat;
    i64 m, nv;
} dop_t;

/* _delassus_entry: G_al from G or W_a^T (M^{-1}W)_l */
static double delassus_entry(const dop_t *D, i64 a, i64 l) {
    if (D->form == FORM_DELASSUS) return D->G[a * D->m + l];
    double s = 0.0;
    for (i64 p = D->pat->wp_ptr[a]; p < D->pat->wp_ptr[a + 1]; p++) {
        i64 k = D->pat->wp_idx[p];
        s = s + D->Wt[a * D->nv + k] * D->MinvW[k * D->m + l];
    }
    return s;
}

/* _scaled_apply: y = S x, S = R^{1/2} G R^{1/2} on the first n rows (sq = r^{1/2}) */
static void scaled_apply(const dop_t *D, const double *sq, const double *x, double *y, i64 n,
                         double *tmp) {
    const patterns_t *pat = D->pat;
    i64 m = D->m, nv = D->nv;
    if (D->form == FORM_DELASSUS) {
        for (i64 a = 0; a < n; a++) {
            double acc = 0.0;
            for (i64 p = pat->gp_ptr[a]; p < pat->gp_ptr[a + 1]; p++) {
                i64 l = pat->gp_idx[p];
                if (l < n) acc = acc + D->G[a * m + l] * sq[l] * x[l];
            }
            y[a] = sq[a] * acc;
        }
        return;
    }
    for (i64 k = 0; k < nv; k++) tmp[k] = 0.0;
    for (i64 l = 0; l < n; l++) {
        double v = sq[l] * x[l];
        if (v != 0.0)
            for (i64 p = pat->mp_ptr[l]; p < pat->mp_ptr[l + 1]; p++) {
                i64 k = pat->mp_idx[p];
                tmp[k] = tmp[k] + D->MinvW[k * m + l] * v;
            }
    }
    for (i64 a = 0; a < n; a++) {
        double acc = 0.0;
        for (i64 p = pat->wp_ptr[a]; p < pat->wp_ptr[a + 1]; p++) {
            i64 k = pat->wp_idx[p];
            acc = acc + D->Wt[a * nv + k] * tmp[k];
        }
        y[a] = sq[a] * acc;
    }
}

/* _power_lambda_max: λ_max of a symmetric PSD 3x3 S3 by power iteration */
static double power_lambda_max(const double *S3, i64 n_power) {
    double x0 = 1.0, x1 = 0.9, x2 = 0.8;
    double lam = 0.0;
    for (i64 it = 0; it < n_power; it++) {
        double y0 = S3[0] * x0 + S3[1] * x1 + S3[2] * x2;
        double y1 = S3[3] * x0 + S3[4] * x1 + S3[5] * x2;
        double y2 = S3[6] * x0 + S3[7] * x1 + S3[8] * x2;
        double nx = x0 * x0 + x1 * x1 + x2 * x2;
        lam = (x0 * y0 + x1 * y1 + x2 * y2) / nx;
        double ny = sqrt(y0 * y0 + y1 * y1 + y2 * y2);
        if (ny == 0.0) return lam;
        x0 = y0 / ny;
        x1 = y1 / ny;
        x2 = y2 / ny;
    }
    return lam;
}

/* auto_spectral_scale on a dop_t */
static double spectral_scale(const settings_t *s, const dop_t *D, i64 nc, const double *r,
                             arena_t *ar) {
    i64 m = D->m;
    i64 o = 3 * nc;
    i64 n = s->bilateral_direct ? o : m;
    if (n == 0) return 0.0;
    double *sq = arena_f(ar, m);
    for (i64 l = 0; l < m; l++) sq[l] = sqrt(r[l]);
    if (s->scheme == SCHEME_SOR) {
        double best = 0.0;
        double S3[9];
        for (i64 i = 0; i < nc; i++) {
            i64 b = 3 * i;
            for (i64 a = 0; a < 3; a++)
                for (i64 l = 0; l < 3; l++)
                    S3[a * 3 + l] = sq[b + a] * sq[b + l] * delassus_entry(D, b + a, b + l);
            best = py_max(best, power_lambda_max(S3, 3 * AUTO_POWER_ITERATIONS));
        }
        for (i64 l = o; l < n; l++) best = py_max(best, r[l] * delassus_entry(D, l, l));
        return best;
    }
    double *x = arena_f(ar, n);
    for (i64 a = 0; a < n; a++) x[a] = 1.0 + 0.1 * (double)((a * 7) % 5);
    double *y = arena_f(ar, n);
    double *tmp = arena_f(ar, D->nv);
    double lam = 0.0;
    for (i64 it = 0; it < AUTO_POWER_ITERATIONS; it++) {
        scaled_apply(D, sq, x, y, n, tmp);
        double nx = 0.0, xy = 0.0, ny = 0.0;
        for (i64 a = 0; a < n; a++) {
            nx = nx + x[a] * x[a];
            xy = xy + x[a] * y[a];
            ny = ny + y[a] * y[a];
        }
        lam = xy / nx;
        if (ny == 0.0) break;
        ny = sqrt(ny);
        for (i64 a = 0; a < n; a++) x[a] = y[a] / ny;
    }
    return lam;
}

/* auto_spectral_scale: λ_max of R^{1/2} G R^{1/2} that bounds the scheme's step */
double auto_spectral_scale(const settings_t *s, const double *G, const double *Wt,
                           const double *MinvW, const patterns_t *pat, i64 m, i64 nv, i64 nc,
                           const double *r, arena_t *a) {
    dop_t D = {s->form, G, Wt, MinvW, pat, m, nv};
    return spectral_scale(s, &D, nc, r, a);
}

/* auto_spectral_parameters: rs = r |α| / λ_max; returns rs / r (1: no estimate) */
static double auto_spectral_parameters(const settings_t *s, const dop_t *D, i64 nc,
                                       const double *r, double *rs, arena_t *ar) {
    i64 m = D->m;
    for (i64 l = 0; l < m; l++) rs[l] = r[l];
    if (m == 0) return 1.0;
    double lam = spectral_scale(s, D, nc, r, ar);
    double a_abs = r[0] * delassus_entry(D, 0, 0);
    if (!(lam > 0.0 && isfinite(lam) && a_abs > 0.0)) return 1.0;
    double f = a_abs / lam;
    for (i64 l = 0; l < m; l++) rs[l] = r[l] * f;
    return f;
}

/* _clamp_step: θ = p/q clamped to [1, AUTO_MAX_STEP]; 1 when p = 0 or q ≤ 0 */
static double clamp_step(double p_, double q) {
    if (p_ == 0.0 || !(q > 0.0)) return 1.0;
    double theta = p_ / q;
    if (!isfinite(theta)) return 1.0;
    return py_min(py_max(theta, 1.0), AUTO_MAX_STEP);
}

/* auto_step_factor: Barzilai-Borwein θ = (dᵀ R_s^{-1} d) / (dᵀ G d), d = new − old */
static double auto_step_factor(const settings_t *s, const dop_t *D, const double *old,
                               const double *new_, const double *rs, double *tmp1,
                               double *tmp2, i64 n) {
    const patterns_t *pat = D->pat;
    i64 m = D->m, nv = D->nv;
    double p_ = 0.0;
    for (i64 l = 0; l < n; l++) {
        double d = new_[l] - old[l];
        p_ = p_ + d * d / rs[l];
    }
    if (p_ == 0.0) return 1.0;
    double q = 0.0;
    if (s->form == FORM_DELASSUS) {
        for (i64 a = 0; a < m; a++) {
            double da = new_[a] - old[a];
            if (da != 0.0) {
                double acc = 0.0;
                for (i64 p = pat->gp_ptr[a]; p < pat->gp_ptr[a + 1]; p++) {
                    i64 l = pat->gp_idx[p];
                    acc = acc + D->G[a * m + l] * (new_[l] - old[l]);
                }
                q = q + da * acc;
            }
        }
    } else {
        for (i64 k = 0; k < nv; k++) tmp1[k] = 0.0; /* W d */
        for (i64 k = 0; k < nv; k++) tmp2[k] = 0.0; /* M^{-1} W d */
        for (i64 l = 0; l < m; l++) {
            double d = new_[l] - old[l];
            if (d != 0.0) {
                for (i64 p = pat->wp_ptr[l]; p < pat->wp_ptr[l + 1]; p++) {
                    i64 k = pat->wp_idx[p];
                    tmp1[k] = tmp1[k] + D->Wt[l * nv + k] * d;
                }
                for (i64 p = pat->mp_ptr[l]; p < pat->mp_ptr[l + 1]; p++) {
                    i64 k = pat->mp_idx[p];
                    tmp2[k] = tmp2[k] + D->MinvW[k * m + l] * d;
                }
            }
        }
        for (i64 k = 0; k < nv; k++) q = q + tmp1[k] * tmp2[k];
    }
    return clamp_step(p_, q);
}

/* _auto_guard: tracks the smallest increment (hist[0]); AUTO_GUARD times it ends the long
 * steps (hist[1] = 1). Whether long steps may follow. */
static int auto_guard(double res, double *hist) {
    if (hist[1] != 1.0) {
        if (res < hist[0])
            hist[0] = res;
        else if (res > AUTO_GUARD * hist[0])
            hist[1] = 1.0;
    }
    return hist[1] != 1.0;
}

/* _auto_restart: after a non-finite sweep, Λ back to Λ^0 and rk back to rs */
static void auto_restart(double *hist, double *lam, const double *lam0, double *rk,
                         const double *rs, i64 m) {
    hist[1] = 1.0;
    for (i64 l = 0; l < m; l++) lam[l] = lam0[l];
    for (i64 l = 0; l < m; l++) rk[l] = rs[l];
}

/* _auto_jor_save: rk = rs; after even sweeps d and ξ^k saved for the next long step */
static int auto_jor_save(i64 k, const double *old, const double *new_, const double *xi,
                         double res, const double *rs, double *rk, double *hist,
                         double *dsave, double *xsave, i64 m) {
    for (i64 l = 0; l < m; l++) rk[l] = rs[l];
    if (!auto_guard(res, hist) || k % 2 == 1) return 0;
    for (i64 l = 0; l < m; l++) {
        dsave[l] = new_[l] - old[l];
        xsave[l] = xi[l];
    }
    return 1;
}

/* _auto_jor_long_step: rk = rs θ from the saved d and Gd = ξ − ξ_saved */
static void auto_jor_long_step(const settings_t *s, i64 nc, const double *xi,
                               const double *rs, double *rk, const double *dsave,
                               const double *xsave, i64 m) {
    i64 n = s->bilateral_direct ? 3 * nc : m;
    double p_ = 0.0;
    for (i64 l = 0; l < n; l++) p_ = p_ + dsave[l] * dsave[l] / rs[l];
    double q = 0.0;
    for (i64 l = 0; l < m; l++) q = q + dsave[l] * (xi[l] - xsave[l]);
    double theta = clamp_step(p_, q);
    for (i64 l = 0; l < n; l++) rk[l] = rs[l] * theta;
}

/* _auto_next: rk of the sweep after sweep k: BB step after even sweeps, else rs */
static void auto_next(const settings_t *s, const dop_t *D, i64 nc, i64 k, const double *old,
                      const double *new_, double res, const double *rs, double *rk,
                      double *hist, double *tmp1, double *tmp2) {
    i64 m = D->m;
    for (i64 l = 0; l < m; l++) rk[l] = rs[l];
    if (!auto_guard(res, hist) || k % 2 == 1) return;
    i64 n = (s->bilateral_direct || hist[1] == 2.0) ? 3 * nc : m;
    double theta = auto_step_factor(s, D, old, new_, rs, tmp1, tmp2, n);
    for (i64 l = 0; l < n; l++) rk[l] = rs[l] * theta;
}

/* _auto_setup's work arrays */
typedef struct {
    double *rk, *rs, *lam0, *hist, *tmp1, *tmp2, *dsave, *xsave;
} auto_t;

/* _auto_setup: with a fixed α, rk and rs are r itself (no copies, never written); adaptive:
 * rk a copy of the spectral step rs, Λ^0, hist = [inf, 0, rs/r] and work arrays */
static auto_t auto_setup(const settings_t *s, const dop_t *D, i64 nc, const double *r,
                         const double *lam, arena_t *ar) {
    auto_t w;
    if (s->alpha >= 0.0) {
        w.rk = w.rs = (double *)r; /* (aliases r; only the adaptive α writes rk) */
        w.lam0 = w.hist = w.tmp1 = w.tmp2 = w.dsave = w.xsave = NULL;
        return w;
    }
    i64 m = D->m, nv = D->nv;
    double *hist = arena_f(ar, 3);
    hist[0] = INFINITY;
    hist[1] = 0.0;
    hist[2] = 1.0;
    double *rs = arena_f(ar, m);
    for (i64 l = 0; l < m; l++) rs[l] = r[l];
    hist[2] = auto_spectral_parameters(s, D, nc, r, rs, ar);
    if (s->scheme == SCHEME_SOR && !s->bilateral_direct && m > 3 * nc) {
        hist[1] = 2.0;
        for (i64 l = 3 * nc; l < m; l++) rs[l] = rs[l] * (AUTO_SOR_BILATERAL_OMEGA / hist[2]);
    }
    w.rk = arena_f(ar, m);
    for (i64 l = 0; l < m; l++) w.rk[l] = rs[l];
    w.rs = rs;
    w.lam0 = arena_f(ar, m);
    for (i64 l = 0; l < m; l++) w.lam0[l] = lam[l];
    w.hist = hist;
    w.tmp1 = arena_f(ar, nv);
    w.tmp2 = arena_f(ar, nv);
    w.dsave = arena_f(ar, m);
    w.xsave = arena_f(ar, m);
    return w;
}

/* ---- the kernels ---------------------------------------------------------------------- */

/* _delassus_apply: ξ_a = c_a + Σ_l G_al Λ_l (a < n), column by column over each column's
 * envelope (its zeros inside included, as the Python) */
static void delassus_apply(const double *G, const double *c, i64 m, const double *lam,
                           double *xi, const i64 *gp_ptr, const i64 *gp_idx, i64 n) {
    for (i64 a = 0; a < n; a++) xi[a] = c[a];
    for (i64 l = 0; l < m; l++) {
        i64 first = gp_ptr[l], last = gp_ptr[l + 1];
        if (first == last) continue;
        i64 a0 = gp_idx[first];
        i64 a1 = py_mini(gp_idx[last - 1] + 1, n);
        double x = lam[l];
        const double *gs = G + l * m;
        for (i64 t = a0; t < a1; t++) xi[t] = xi[t] + gs[t] * x;
    }
}

/* _jor_project: a JOR update of Λ into new (Λ_B kept with the direct method) */
static void jor_project(const double *lam, const double *xi, const double *r,
                        const double *mu, i64 nc, i64 m, int bilateral_direct, double *new_) {
    for (i64 i = 0; i < nc; i++) {
        i64 b = 3 * i;
        project_contact(lam, b, xi[b], xi[b + 1], xi[b + 2], r, mu[i], new_);
    }
    for (i64 l = 3 * nc; l < m; l++) new_[l] = bilateral_direct ? lam[l] : lam[l] - r[l] * xi[l];
}

/* _jor_update_in_place: fixed-α JOR update (bilateral prox rows) in place, with _check */
static check_t jor_update_in_place(double *lam, const double *xi, const double *r,
                                   const double *mu, i64 nc, i64 m, double tol_rel,
                                   double tol_abs) {
    check_t c = {1, 0.0, 1};
    for (i64 i = 0; i < nc; i++) {
        i64 b = 3 * i;
        double old0 = lam[b], old1 = lam[b + 1], old2 = lam[b + 2];
        project_contact(lam, b, xi[b], xi[b + 1], xi[b + 2], r, mu[i], lam);
        row_check(old0, lam[b], &c, tol_rel, tol_abs);
        row_check(old1, lam[b + 1], &c, tol_rel, tol_abs);
        row_check(old2, lam[b + 2], &c, tol_rel, tol_abs);
    }
    for (i64 l = 3 * nc; l < m; l++) {
        double v = lam[l] - r[l] * xi[l];
        row_check(lam[l], v, &c, tol_rel, tol_abs);
        lam[l] = v;
    }
    return c;
}

/* the direct bilateral method's work of delassus_prox: L_B's envelope columns, rhs */
typedef struct {
    const i64 *col_ptr, *col_idx;
    double *rhs;
} direct_t;

static prox_result_t result(i64 it, i64 status, double res) {
    prox_result_t out = {it, status, res};
    return out;
}

/* The energy criterion: |T^{k+1} − T^k| ≤ |T^k| T_rel + T_abs with T = ½ uᵀMu; T^k in *T_old,
 * replaced by T^{k+1} */
static int energy_converged(const double *M, const double *u, i64 nv, double *T_old,
                            double tol_rel, double tol_abs) {
    double T = kinetic_energy(M, u, nv);
    int ok = fabs(T - *T_old) <= fabs(*T_old) * tol_rel + tol_abs;
    *T_old = T;
    return ok;
}

/* What a Delassus-form solve needs for u = u_free + M^{-1} W Λ (Eqn. 17) and its energy */
typedef struct {
    const double *u_free, *MinvW, *M;
    const i64 *mp_ptr, *mp_idx;
    i64 nv, m;
    double *u;
} velocity_t;

static void velocity_of(const velocity_t *v, const double *lam) {
    velocity_from_impulses(v->u_free, v->MinvW, v->nv, v->m, lam, v->u, v->mp_ptr, v->mp_idx);
}

/* The end of sweep k of a Delassus-form solve, ck the check of its Λ: 1 when the solve ends
 * (*out: non-finite Λ; or converged by the impulse criterion or by the energy one (T^k in
 * *T_old), with u = u_free + M^{-1}WΛ), else 0 */
static int delassus_sweep_end(const velocity_t *v, const double *lam, check_t ck, i64 k,
                              i64 criterion, double *T_old, double tol_rel, double tol_abs,
                              prox_result_t *out) {
    int ok = ck.ok;
    if (!ck.finite) {
        *out = result(k + 1, STATUS_NONFINITE, ck.res);
        return 1;
    }
    if (criterion == CRITERION_ENERGY) {
        velocity_of(v, lam);
        ok = energy_converged(v->M, v->u, v->nv, T_old, tol_rel, tol_abs);
    }
    if (ok) {
        velocity_of(v, lam);
        *out = result(k + 1, STATUS_CONVERGED, ck.res);
        return 1;
    }
    return 0;
}

/* T^0 of the energy criterion (u from Λ^0), 0 for the impulse criterion */
static double initial_energy(const velocity_t *v, const double *lam, i64 criterion) {
    if (criterion != CRITERION_ENERGY) return 0.0;
    velocity_of(v, lam);
    return kinetic_energy(v->M, v->u, v->nv);
}

/* A Delassus-form problem, ξ = GΛ + c, as its JOR and SOR sweeps read it (delassus_prox) */
typedef struct {
    const settings_t *s;
    const patterns_t *pat;
    const double *G, *c, *mu, *r, *LB;
    double *lam;        /* Λ: warm start in, solution out */
    i64 m, nc, nb_LB;
    dop_t D;            /* G as the adaptive α reads it */
    velocity_t v;       /* u^E = u_free + M^{-1}WΛ and its energy */
    direct_t direct;    /* the direct bilateral method's work */
    arena_t *ar;
} delassus_t;

/* _jor_prox_delassus: JOR on ξ = GΛ + c, work buf (2m: ξ and the new Λ) */
static prox_result_t jor_prox_delassus(const delassus_t *P, double *buf) {
    const settings_t *s = P->s;
    const double *G = P->G, *c = P->c, *mu = P->mu;
    double *lam = P->lam;
    i64 m = P->m, nc = P->nc;
    double tol_rel = s->tol_rel, tol_abs = s->tol_abs;
    i64 max_iter = s->max_iterations, criterion = s->criterion;
    int bilateral_direct = s->bilateral_direct;
    const i64 *gp_ptr = P->pat->gp_ptr, *gp_idx = P->pat->gp_idx;
    i64 o = 3 * nc;
    double *xi = buf, *new_ = buf + m;
    int autoa = s->alpha < 0.0;
    auto_t w = auto_setup(s, &P->D, nc, P->r, lam, P->ar);
    double *rk = w.rk, *rs = w.rs, *hist = w.hist;
    int long_step = 0;
    double T_old = initial_energy(&P->v, lam, criterion);
    i64 m_xi = (bilateral_direct && !autoa) ? o : m;
    double res = 0.0;
    for (i64 k = 0; k < max_iter; k++) {
        check_t ck;
        delassus_apply(G, c, m, lam, xi, gp_ptr, gp_idx, m_xi);
        if (long_step) {
            auto_jor_long_step(s, nc, xi, rs, rk, w.dsave, w.xsave, m);
            long_step = 0;
        }
        if (!(autoa || bilateral_direct)) {
            ck = jor_update_in_place(lam, xi, rk, mu, nc, m, tol_rel, tol_abs);
        } else {
            jor_project(lam, xi, rk, mu, nc, m, bilateral_direct, new_);
            if (bilateral_direct)
                bilateral_direct_delassus(G, c, m, nc, P->LB, P->nb_LB, new_, gp_ptr, gp_idx,
                                          P->pat->lb_first, P->direct.col_ptr,
                                          P->direct.col_idx, P->direct.rhs);
            ck = check(lam, new_, m, tol_rel, tol_abs);
            if (autoa) {
                if (!ck.finite && hist[1] != 1.0) { /* from Λ^0 again, spectral steps */
                    res = ck.res;
                    auto_restart(hist, lam, w.lam0, rk, rs, m);
                    long_step = 0;
                    T_old = initial_energy(&P->v, lam, criterion);
                    continue;
                }
                long_step = auto_jor_save(k, lam, new_, xi, ck.res, rs, rk, hist, w.dsave,
                                          w.xsave, m);
            }
            memcpy(lam, new_, (size_t)m * sizeof(double));
        }
        res = ck.res;
        prox_result_t out;
        if (delassus_sweep_end(&P->v, lam, ck, k, criterion, &T_old, tol_rel, tol_abs, &out))
            return out;
    }
    velocity_of(&P->v, lam);
    return result(max_iter, STATUS_MAX_ITER, res);
}

/* _sor_prox_delassus: SOR on ξ = GΛ + c, work buffer old (m: Λ of the last sweep) */
static prox_result_t sor_prox_delassus(const delassus_t *P, double *old) {
    const settings_t *s = P->s;
    const double *G = P->G, *c = P->c, *mu = P->mu;
    double *lam = P->lam;
    i64 m = P->m, nc = P->nc;
    double tol_rel = s->tol_rel, tol_abs = s->tol_abs;
    i64 max_iter = s->max_iterations, criterion = s->criterion;
    int bilateral_direct = s->bilateral_direct;
    const i64 *gp_ptr = P->pat->gp_ptr, *gp_idx = P->pat->gp_idx;
    i64 o = 3 * nc;
    int autoa = s->alpha < 0.0;
    auto_t w = auto_setup(s, &P->D, nc, P->r, lam, P->ar);
    double *rk = w.rk, *rs = w.rs, *hist = w.hist;
    double T_old = initial_energy(&P->v, lam, criterion);
    double res = 0.0;
    for (i64 k = 0; k < max_iter; k++) {
        memcpy(old, lam, (size_t)m * sizeof(double));
        for (i64 i = 0; i < nc; i++) {
            i64 b = 3 * i;
            double x0 = c[b], x1 = c[b + 1], x2 = c[b + 2];
            for (i64 p = gp_ptr[b]; p < gp_ptr[b + 1]; p++) {
                i64 l = gp_idx[p];
                x0 = x0 + G[b * m + l] * lam[l];
            }
            for (i64 p = gp_ptr[b + 1]; p < gp_ptr[b + 2]; p++) {
                i64 l = gp_idx[p];
                x1 = x1 + G[(b + 1) * m + l] * lam[l];
            }
            for (i64 p = gp_ptr[b + 2]; p < gp_ptr[b + 3]; p++) {
                i64 l = gp_idx[p];
                x2 = x2 + G[(b + 2) * m + l] * lam[l];
            }
            project_contact(lam, b, x0, x1, x2, rk, mu[i], lam);
        }
        if (bilateral_direct) {
            bilateral_direct_delassus(G, c, m, nc, P->LB, P->nb_LB, lam, gp_ptr, gp_idx,
                                      P->pat->lb_first, P->direct.col_ptr, P->direct.col_idx,
                                      P->direct.rhs);
        } else {
            for (i64 a = o; a < m; a++) {
                double sm = c[a];
                for (i64 p = gp_ptr[a]; p < gp_ptr[a + 1]; p++) {
                    i64 l = gp_idx[p];
                    sm = sm + G[a * m + l] * lam[l];
                }
                lam[a] = lam[a] - rk[a] * sm;
            }
        }
        check_t ck = check(old, lam, m, tol_rel, tol_abs);
        res = ck.res;
        if (autoa) {
            if (!ck.finite && hist[1] != 1.0) { /* from Λ^0 again, spectral steps */
                auto_restart(hist, lam, w.lam0, rk, rs, m);
                T_old = initial_energy(&P->v, lam, criterion);
                continue;
            }
            auto_next(s, &P->D, nc, k, old, lam, ck.res, rs, rk, hist, w.tmp1, w.tmp2);
        }
        prox_result_t out;
        if (delassus_sweep_end(&P->v, lam, ck, k, criterion, &T_old, tol_rel, tol_abs, &out))
            return out;
    }
    velocity_of(&P->v, lam);
    return result(max_iter, STATUS_MAX_ITER, res);
}

/* _envelope_columns: L_B's envelope by columns (nd > 0 bilateral rows), else empty */
static void envelope_columns_of(const patterns_t *pat, i64 nd, arena_t *ar, i64 **ptr,
                                i64 **idx) {
    if (nd > 0) {
        envelope_columns(pat->lb_first, pat->n_lb, ar, ptr, idx);
        return;
    }
    *ptr = (i64 *)pat->lb_first; /* (empty: never read) */
    *idx = (i64 *)pat->lb_first;
}

/* delassus_prox: JOR or SOR on ξ = GΛ + c with its work buffer from the arena */
static prox_result_t delassus_prox(int jor, const settings_t *s, const patterns_t *pat,
                                   const double *G, const double *c, i64 m, i64 nc,
                                   const double *mu, const double *r, double *lam,
                                   const double *LB, i64 nb_LB, const double *M,
                                   const double *u_free, const double *MinvW, i64 nv,
                                   double *u, arena_t *ar) {
    i64 nd = s->bilateral_direct ? m - 3 * nc : 0;
    i64 nw = jor ? 2 * m : m;
    double *work = arena_f(ar, nw + nd);
    i64 *col_ptr, *col_idx;
    envelope_columns_of(pat, nd, ar, &col_ptr, &col_idx);
    delassus_t P = {s, pat, G, c, mu, r, LB, lam, m, nc, nb_LB,
                    {s->form, G, G, MinvW, pat, m, nv},
                    {u_free, MinvW, M, pat->mp_ptr, pat->mp_idx, nv, m, u},
                    {col_ptr, col_idx, work + nw}, ar};
    return jor ? jor_prox_delassus(&P, work) : sor_prox_delassus(&P, work);
}

/* jor_prox_velocity: JOR in the end velocity u^k (Eqn. 17-19), G never formed */
static prox_result_t jor_prox_velocity(const settings_t *s, const patterns_t *pat,
                                       const double *Wt, const double *MinvW,
                                       const double *u_free, const double *bvec, i64 m,
                                       i64 nv, i64 nc, const double *mu, const double *r,
                                       double *lam, const double *LB, i64 nb_LB,
                                       const double *M, double *u, arena_t *ar) {
    double tol_rel = s->tol_rel, tol_abs = s->tol_abs;
    i64 max_iter = s->max_iterations, criterion = s->criterion;
    int bilateral_direct = s->bilateral_direct;
    const i64 *wp_ptr = pat->wp_ptr, *wp_idx = pat->wp_idx, *mp_ptr = pat->mp_ptr,
              *mp_idx = pat->mp_idx;
    double *buf = arena_f(ar, 2 * m); /* ξ and the new Λ */
    double *xi = buf, *new_ = buf + m;
    int autoa = s->alpha < 0.0;
    dop_t D = {s->form, Wt, Wt, MinvW, pat, m, nv};
    auto_t w = auto_setup(s, &D, nc, r, lam, ar);
    double *rk = w.rk, *rs = w.rs, *hist = w.hist;
    /* _bilateral_direct_velocity's copy of u_free and rhs, allocated once */
    double *uu = NULL, *rhs = NULL;
    if (bilateral_direct) {
        uu = arena_f(ar, nv);
        rhs = arena_f(ar, m - 3 * nc);
    }
    int long_step = 0;
    velocity_from_impulses(u_free, MinvW, nv, m, lam, u, mp_ptr, mp_idx);
    double T_old = criterion == CRITERION_ENERGY ? kinetic_energy(M, u, nv) : 0.0;
    double res = 0.0;
    for (i64 k = 0; k < max_iter; k++) {
        for (i64 a = 0; a < m; a++) {
            double sm = bvec[a];
            for (i64 p = wp_ptr[a]; p < wp_ptr[a + 1]; p++) {
                i64 j = wp_idx[p];
                sm = sm + Wt[a * nv + j] * u[j];
            }
            xi[a] = sm;
        }
        if (long_step) {
            auto_jor_long_step(s, nc, xi, rs, rk, w.dsave, w.xsave, m);
            long_step = 0;
        }
        jor_project(lam, xi, rk, mu, nc, m, bilateral_direct, new_);
        if (bilateral_direct)
            bilateral_direct_velocity(Wt, MinvW, u_free, m, nv, nc, LB, nb_LB, new_, pat, uu,
                                      rhs);
        check_t ck = check(lam, new_, m, tol_rel, tol_abs);
        res = ck.res;
        if (autoa) {
            if (!ck.finite && hist[1] != 1.0) { /* from Λ^0 again, spectral steps */
                auto_restart(hist, lam, w.lam0, rk, rs, m);
                long_step = 0;
                velocity_from_impulses(u_free, MinvW, nv, m, lam, u, mp_ptr, mp_idx);
                if (criterion == CRITERION_ENERGY) T_old = kinetic_energy(M, u, nv);
                continue;
            }
            long_step = auto_jor_save(k, lam, new_, xi, ck.res, rs, rk, hist, w.dsave,
                                      w.xsave, m);
        }
        for (i64 l = 0; l < m; l++) {
            double d = new_[l] - lam[l];
            if (d != 0.0)
                for (i64 p = mp_ptr[l]; p < mp_ptr[l + 1]; p++) {
                    i64 j = mp_idx[p];
                    u[j] = u[j] + MinvW[j * m + l] * d;
                }
        }
        memcpy(lam, new_, (size_t)m * sizeof(double));
        int ok = ck.ok;
        if (!ck.finite) return result(k + 1, STATUS_NONFINITE, res);
        if (criterion == CRITERION_ENERGY)
            ok = energy_converged(M, u, nv, &T_old, tol_rel, tol_abs);
        if (ok) return result(k + 1, STATUS_CONVERGED, res);
    }
    return result(max_iter, STATUS_MAX_ITER, res);
}

/* sor_prox_velocity: SOR in the end velocity, u updated after each contact (Eqn. 18), then
 * the bilateral rows (Eqn. 19, or Eqn. 20 when direct) */
static prox_result_t sor_prox_velocity(const settings_t *s, const patterns_t *pat,
                                       const double *Wt, const double *MinvW,
                                       const double *u_free, const double *bvec, i64 m,
                                       i64 nv, i64 nc, const double *mu, const double *r,
                                       double *lam, const double *LB, i64 nb_LB,
                                       const double *M, double *u, arena_t *ar) {
    double tol_rel = s->tol_rel, tol_abs = s->tol_abs;
    i64 max_iter = s->max_iterations, criterion = s->criterion;
    int bilateral_direct = s->bilateral_direct;
    const i64 *wp_ptr = pat->wp_ptr, *wp_idx = pat->wp_idx, *mp_ptr = pat->mp_ptr,
              *mp_idx = pat->mp_idx;
    i64 o = 3 * nc;
    double *old = arena_f(ar, m);
    int autoa = s->alpha < 0.0;
    dop_t D = {s->form, Wt, Wt, MinvW, pat, m, nv};
    auto_t w = auto_setup(s, &D, nc, r, lam, ar);
    double *rk = w.rk, *rs = w.rs, *hist = w.hist;
    double *uu = NULL, *rhs = NULL;
    if (bilateral_direct && m > o) {
        uu = arena_f(ar, nv);
        rhs = arena_f(ar, m - o);
    }
    velocity_from_impulses(u_free, MinvW, nv, m, lam, u, mp_ptr, mp_idx);
    double T_old = criterion == CRITERION_ENERGY ? kinetic_energy(M, u, nv) : 0.0;
    double res = 0.0;
    for (i64 k = 0; k < max_iter; k++) {
        memcpy(old, lam, (size_t)m * sizeof(double));
        for (i64 i = 0; i < nc; i++) {
            i64 b = 3 * i;
            double x0 = bvec[b];
            for (i64 p = wp_ptr[b]; p < wp_ptr[b + 1]; p++)
                x0 = x0 + Wt[b * nv + wp_idx[p]] * u[wp_idx[p]];
            double x1 = bvec[b + 1];
            for (i64 p = wp_ptr[b + 1]; p < wp_ptr[b + 2]; p++)
                x1 = x1 + Wt[(b + 1) * nv + wp_idx[p]] * u[wp_idx[p]];
            double x2 = bvec[b + 2];
            for (i64 p = wp_ptr[b + 2]; p < wp_ptr[b + 3]; p++)
                x2 = x2 + Wt[(b + 2) * nv + wp_idx[p]] * u[wp_idx[p]];
            double l0 = lam[b], l1 = lam[b + 1], l2 = lam[b + 2];
            project_contact(lam, b, x0, x1, x2, rk, mu[i], lam);
            for (i64 rr = 0; rr < 3; rr++) {
                double d_ = lam[b + rr] - (rr == 0 ? l0 : (rr == 1 ? l1 : l2));
                if (d_ != 0.0)
                    for (i64 p = mp_ptr[b + rr]; p < mp_ptr[b + rr + 1]; p++) {
                        i64 j = mp_idx[p];
                        u[j] = u[j] + MinvW[j * m + b + rr] * d_;
                    }
            }
        }
        if (bilateral_direct) {
            if (m > o) {
                bilateral_direct_velocity(Wt, MinvW, u_free, m, nv, nc, LB, nb_LB, lam, pat,
                                          uu, rhs);
                velocity_from_impulses(u_free, MinvW, nv, m, lam, u, mp_ptr, mp_idx);
            }
        } else {
            for (i64 a = o; a < m; a++) {
                double sm = bvec[a];
                for (i64 p = wp_ptr[a]; p < wp_ptr[a + 1]; p++) {
                    i64 j = wp_idx[p];
                    sm = sm + Wt[a * nv + j] * u[j];
                }
                double d_ = -rk[a] * sm;
                lam[a] = lam[a] + d_;
                for (i64 p = mp_ptr[a]; p < mp_ptr[a + 1]; p++) {
                    i64 j = mp_idx[p];
                    u[j] = u[j] + MinvW[j * m + a] * d_;
                }
            }
        }
        check_t ck = check(old, lam, m, tol_rel, tol_abs);
        res = ck.res;
        if (autoa) {
            if (!ck.finite && hist[1] != 1.0) { /* from Λ^0 again, spectral steps */
                auto_restart(hist, lam, w.lam0, rk, rs, m);
                velocity_from_impulses(u_free, MinvW, nv, m, lam, u, mp_ptr, mp_idx);
                if (criterion == CRITERION_ENERGY) T_old = kinetic_energy(M, u, nv);
                continue;
            }
            auto_next(s, &D, nc, k, old, lam, ck.res, rs, rk, hist, w.tmp1, w.tmp2);
        }
        int ok = ck.ok;
        if (!ck.finite) return result(k + 1, STATUS_NONFINITE, res);
        if (criterion == CRITERION_ENERGY)
            ok = energy_converged(M, u, nv, &T_old, tol_rel, tol_abs);
        if (ok) return result(k + 1, STATUS_CONVERGED, res);
    }
    return result(max_iter, STATUS_MAX_ITER, res);
}

/* prox_solve: one prox solve with the settings' form and scheme */
prox_result_t prox_solve(const settings_t *s, const patterns_t *pat, const double *Wt,
                         const double *MinvW, const double *u_free, const double *bvec,
                         const double *G, const double *c, i64 m, i64 nv, i64 nc,
                         const double *mu, const double *r, double *lam, const double *LB,
                         i64 nb_LB, const double *M, double *u, arena_t *a) {
    if (s->form == FORM_DELASSUS)
        return delassus_prox(s->scheme == SCHEME_JOR, s, pat, G, c, m, nc, mu, r, lam, LB,
                             nb_LB, M, u_free, MinvW, nv, u, a);
    if (s->scheme == SCHEME_JOR)
        return jor_prox_velocity(s, pat, Wt, MinvW, u_free, bvec, m, nv, nc, mu, r, lam, LB,
                                 nb_LB, M, u, a);
    return sor_prox_velocity(s, pat, Wt, MinvW, u_free, bvec, m, nv, nc, mu, r, lam, LB,
                             nb_LB, M, u, a);
}
