/* The adaptive α of the prox iterations (prox.py, solver.alpha "auto"): the spectral step
 * from λ_max of R^{1/2} G R^{1/2} (power iteration), the Barzilai-Borwein long steps every
 * other sweep, the divergence guard and the restart from Λ^0 (prox.h: what prox.c calls). */
#include "prox.h"

/* delassus_entry: G_al from G or W_a^T (M^{-1}W)_l */
static double delassus_entry(const dop_t *D, i64 a, i64 l) {
    if (D->form == FORM_DELASSUS) return D->G[a * D->m + l];
    double s = 0.0;
    for (i64 p = D->pat->wp_ptr[a]; p < D->pat->wp_ptr[a + 1]; p++) {
        i64 k = D->pat->wp_idx[p];
        s = s + D->Wt[a * D->nv + k] * D->MinvW[k * D->m + l];
    }
    return s;
}

/* scaled_apply: y = S x, S = R^{1/2} G R^{1/2} on the first n rows (sq = r^{1/2}) */
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

/* power_lambda_max: λ_max of a symmetric PSD 3x3 S3 by power iteration */
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
static double auto_spectral_parameters(const settings_t *s, const dop_t *D, i64 nc, const double *r,
                                       double *rs, arena_t *ar) {
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

/* clamp_step: θ = p/q clamped to [1, AUTO_MAX_STEP]; 1 when p = 0 or q ≤ 0 */
static double clamp_step(double p_, double q) {
    if (p_ == 0.0 || !(q > 0.0)) return 1.0;
    double theta = p_ / q;
    if (!isfinite(theta)) return 1.0;
    return py_min(py_max(theta, 1.0), AUTO_MAX_STEP);
}

/* auto_step_factor: Barzilai-Borwein θ = (dᵀ R_s^{-1} d) / (dᵀ G d), d = new − old */
static double auto_step_factor(const settings_t *s, const dop_t *D, const double *old,
                               const double *new_, const double *rs, double *tmp1, double *tmp2,
                               i64 n) {
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

/* auto_guard: tracks the smallest increment (hist[0]); AUTO_GUARD times it ends the long
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

/* auto_restart: after a non-finite sweep, Λ back to Λ^0 and rk back to rs */
void auto_restart(double *hist, double *lam, const double *lam0, double *rk, const double *rs,
                  i64 m) {
    hist[1] = 1.0;
    for (i64 l = 0; l < m; l++) lam[l] = lam0[l];
    for (i64 l = 0; l < m; l++) rk[l] = rs[l];
}

/* auto_jor_save: rk = rs; after even sweeps d and ξ^k saved for the next long step */
int auto_jor_save(i64 k, const double *old, const double *new_, const double *xi, double res,
                  const double *rs, double *rk, double *hist, double *dsave, double *xsave, i64 m) {
    for (i64 l = 0; l < m; l++) rk[l] = rs[l];
    if (!auto_guard(res, hist) || k % 2 == 1) return 0;
    for (i64 l = 0; l < m; l++) {
        dsave[l] = new_[l] - old[l];
        xsave[l] = xi[l];
    }
    return 1;
}

/* auto_jor_long_step: rk = rs θ from the saved d and Gd = ξ − ξ_saved */
void auto_jor_long_step(const settings_t *s, i64 nc, const double *xi, const double *rs, double *rk,
                        const double *dsave, const double *xsave, i64 m) {
    i64 n = s->bilateral_direct ? 3 * nc : m;
    double p_ = 0.0;
    for (i64 l = 0; l < n; l++) p_ = p_ + dsave[l] * dsave[l] / rs[l];
    double q = 0.0;
    for (i64 l = 0; l < m; l++) q = q + dsave[l] * (xi[l] - xsave[l]);
    double theta = clamp_step(p_, q);
    for (i64 l = 0; l < n; l++) rk[l] = rs[l] * theta;
}

/* auto_next: rk of the sweep after sweep k: BB step after even sweeps, else rs */
void auto_next(const settings_t *s, const dop_t *D, i64 nc, i64 k, const double *old,
               const double *new_, double res, const double *rs, double *rk, double *hist,
               double *tmp1, double *tmp2) {
    i64 m = D->m;
    for (i64 l = 0; l < m; l++) rk[l] = rs[l];
    if (!auto_guard(res, hist) || k % 2 == 1) return;
    i64 n = (s->bilateral_direct || hist[1] == 2.0) ? 3 * nc : m;
    double theta = auto_step_factor(s, D, old, new_, rs, tmp1, tmp2, n);
    for (i64 l = 0; l < n; l++) rk[l] = rs[l] * theta;
}

/* auto_setup: with a fixed α, rk and rs are r itself (no copies, never written); adaptive:
 * rk a copy of the spectral step rs, Λ^0, hist = [inf, 0, rs/r] and work arrays */
auto_t auto_setup(const settings_t *s, const dop_t *D, i64 nc, const double *r, const double *lam,
                  arena_t *ar) {
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
