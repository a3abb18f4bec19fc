/* The prox iterations (prox.py, Gehring et al. 2014, Eqn. 12-20): JOR and SOR on ξ = GΛ + c
 * (Delassus form; G from prox_delassus.c) or in the velocity (G never formed), the direct bilateral
 * method (Eqn. 20), the energy criterion; the rows' laws: prox_rows.h; the adaptive α's steps:
 * prox_alpha.c (prox.h); JOR with the factor of M instead of M^{-1}W: prox_factored.c.
 * Layouts: Wt m x nv, MinvW nv x m, G m x m, M nv x nv, LB nb_LB x nb_LB (row-major). */
#include "prox.h"
#include "prox_rows.h"

#include <string.h>

/* kinetic_energy: ½ uᵀ M u */
static double kinetic_energy(const double *M, const double *u, i64 nv) {
    double s = 0.0;
    for (i64 i = 0; i < nv; i++) {
        double row = 0.0;
        for (i64 j = 0; j < nv; j++) row = row + M[i * nv + j] * u[j];
        s = s + u[i] * row;
    }
    return 0.5 * s;
}

/* add_impulse_columns: u += M^{-1} W[:, :ncols] Λ[:ncols] */
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

/* velocity_from_impulses: u = u_free + M^{-1} W Λ (Eqn. 17) */
static void velocity_from_impulses(const double *u_free, const double *MinvW, i64 nv, i64 m,
                                   const double *lam, double *u, const i64 *mp_ptr,
                                   const i64 *mp_idx) {
    for (i64 k = 0; k < nv; k++) u[k] = u_free[k];
    add_impulse_columns(MinvW, m, lam, u, mp_ptr, mp_idx, m);
}

/* bilateral_direct_delassus: Λ_B = −G_BB^{-1} (G_BU Λ_U + c_B) (Eqn. 20), with L_B's
 * envelope columns (col_ptr, col_idx) and the right-hand side's buffer rhs */
static void bilateral_direct_delassus(const double *G, const double *c, i64 m, i64 nc,
                                      const double *LB, i64 nb_LB, double *lam, const i64 *gp_ptr,
                                      const i64 *gp_idx, const i64 *lb_first, const i64 *col_ptr,
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

/* bilateral_direct_velocity: Λ_B = −G_BB^{-1} W_B^T (u_free + M^{-1} W_U Λ_U) (Eqn. 20);
 * uu (nv) and rhs (m − 3nc) are the caller's work buffers (the Python's copy / np.empty) */
static void bilateral_direct_velocity(const double *Wt, const double *MinvW, const double *u_free,
                                      i64 m, i64 nv, i64 nc, const double *LB, i64 nb_LB,
                                      double *lam, const patterns_t *pat, double *uu, double *rhs) {
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

/* delassus_apply: ξ_a = c_a + Σ_l G_al Λ_l (a < n), column by column over each column's
 * envelope (its zeros inside included, as the Python) */
static void delassus_apply(const double *G, const double *c, i64 m, const double *lam, double *xi,
                           const i64 *gp_ptr, const i64 *gp_idx, i64 n) {
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

/* jor_update_in_place: fixed-α JOR update (bilateral prox rows) in place, with check */
static check_t jor_update_in_place(double *lam, const double *xi, const double *r, const double *mu,
                                   const double *bound, i64 nc, i64 m, double tol_rel,
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
        double v = prox_row(lam[l] - r[l] * xi[l], bound, l - 3 * nc);
        row_check(lam[l], v, &c, tol_rel, tol_abs);
        lam[l] = v;
    }
    return c;
}

/* bilateral_gauss_seidel: the rows after the contacts' (o = 3 nc to m) swept one after the
 * other on ξ = GΛ + c with the Λ already updated (r_B = ω_B/G_BB: relax_bilateral_rows), with
 * their check carried on in c: a linear bilateral system with G_BB positive definite converges
 * so for any ω_B in (0, 2), whatever its condition (the maximal coordinates' chains: JOR's rate
 * is 1 − α λ_min(R G_BB)) */
static void bilateral_gauss_seidel(const double *G, const double *c, i64 m, i64 o, double *lam,
                                   const double *r, const double *bound, const i64 *gp_ptr,
                                   const i64 *gp_idx, check_t *ck, double tol_rel, double tol_abs) {
    for (i64 a = o; a < m; a++) {
        double sm = c[a];
        for (i64 p = gp_ptr[a]; p < gp_ptr[a + 1]; p++) {
            i64 l = gp_idx[p];
            sm = sm + G[a * m + l] * lam[l];
        }
        double v = prox_row(lam[a] - r[a] * sm, bound, a - o);
        row_check(lam[a], v, ck, tol_rel, tol_abs);
        lam[a] = v;
    }
}

/* the direct bilateral method's work of delassus_prox: L_B's envelope columns, rhs */
typedef struct {
    const i64 *col_ptr, *col_idx;
    double *rhs;
    double *gain; /* X = G_BB^{-1} [G_BU, c_B] (nb x (3 nc + 1)) once formed, else NULL */
} direct_t;

/* The stall test of a solve (stall_seen): the best residual so far, the best at the end of
 * the last window, the sweep count that ends the current window */
typedef struct {
    i64 window, next;
    double best, mark;
} stall_t;

static stall_t stall_start(const settings_t *s) {
    stall_t t = {s->stall_window, s->stall_window, INFINITY, INFINITY};
    return t;
}

/* stall_seen: after sweep k with residual res (max |ΔΛ|), 1 when a window of sweeps ended
 * without its best residual getting below STALL_FACTOR x the last window's: the iteration
 * cycles, as JOR at the paper's α does on a robot lying at rest; the caller ends the solve
 * and the step retries with a smaller α at once instead of at the iteration cap */
static inline int stall_seen(stall_t *t, i64 k, double res) {
    if (t->window <= 0) return 0;
    if (res < t->best) t->best = res;
    if (k + 1 < t->next) return 0;
    if (isfinite(t->mark) && !(t->best <= STALL_FACTOR * t->mark)) return 1;
    t->mark = t->best;
    t->next += t->window;
    return 0;
}

/* The energy criterion: |T^{k+1} − T^k| ≤ |T^k| T_rel + T_abs with T = ½ uᵀMu; T^k in *T_old,
 * replaced by T^{k+1} */
static int energy_converged(const double *M, const double *u, i64 nv, double *T_old, double tol_rel,
                            double tol_abs) {
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
    const double *G, *c, *mu, *r, *bound, *LB;
    double *lam; /* Λ: warm start in, solution out */
    i64 m, nc, nb_LB;
    dop_t D;         /* G as the adaptive α reads it */
    velocity_t v;    /* u^E = u_free + M^{-1}WΛ and its energy */
    direct_t direct; /* the direct bilateral method's work */
    arena_t *ar;
} delassus_t;

/* direct_bilateral: Λ_B of Eqn. 20 into lam after sweep k: by one solve with L_B for the
 * first DIRECT_GAIN_SWEEPS sweeps, then by the gain X = G_BB^{-1} [G_BU, c_B] (formed once:
 * every column solved at once), Λ_B = −(X_U Λ_U + X_c) */
static void direct_bilateral(delassus_t *P, double *lam, i64 k) {
    i64 m = P->m, o = 3 * P->nc, nb = m - o, q = o + 1;
    const double *G = P->G;
    if (!P->direct.gain && k < DIRECT_GAIN_SWEEPS) {
        bilateral_direct_delassus(G, P->c, m, P->nc, P->LB, P->nb_LB, lam, P->pat->gp_ptr,
                                  P->pat->gp_idx, P->pat->lb_first, P->direct.col_ptr,
                                  P->direct.col_idx, P->direct.rhs);
        return;
    }
    if (!P->direct.gain) {
        double *X = arena_f(P->ar, nb * q);
        for (i64 a = 0; a < nb; a++) {
            for (i64 u = 0; u < o; u++) X[a * q + u] = G[u * m + o + a];
            X[a * q + o] = P->c[o + a];
        }
        cholesky_solve_envelope_cols(P->LB, nb, P->pat->lb_first, P->direct.col_ptr,
                                     P->direct.col_idx, X, q);
        P->direct.gain = X;
    }
    const double *X = P->direct.gain;
    for (i64 a = 0; a < nb; a++) {
        const double *xa = X + a * q;
        double s = xa[o];
        for (i64 u = 0; u < o; u++) s += xa[u] * lam[u];
        lam[o + a] = -s;
    }
}

/* jor_prox_delassus: JOR on ξ = GΛ + c, work buf (2m: ξ and the new Λ); with a bilateral
 * relaxation (fixed α) the bilateral prox rows are swept after the contacts'
 * (bilateral_gauss_seidel) */
static prox_result_t jor_prox_delassus(delassus_t *P, double *buf) {
    const settings_t *s = P->s;
    const double *G = P->G, *c = P->c, *mu = P->mu, *bound = P->bound;
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
    int sweep_b = s->bilateral_relaxation > 0.0 && !bilateral_direct && !autoa;
    i64 m_xi = ((bilateral_direct && !autoa) || sweep_b) ? o : m;
    double res = 0.0;
    stall_t stall = stall_start(s);
    for (i64 k = 0; k < max_iter; k++) {
        check_t ck;
        delassus_apply(G, c, m, lam, xi, gp_ptr, gp_idx, m_xi);
        if (long_step) {
            auto_jor_long_step(s, nc, xi, rs, rk, w.dsave, w.xsave, m);
            long_step = 0;
        }
        if (!(autoa || bilateral_direct)) {
            ck = jor_update_in_place(lam, xi, rk, mu, bound, nc, sweep_b ? o : m, tol_rel, tol_abs);
            if (sweep_b)
                bilateral_gauss_seidel(G, c, m, o, lam, rk, bound, gp_ptr, gp_idx, &ck, tol_rel,
                                       tol_abs);
        } else {
            jor_project(lam, xi, rk, mu, bound, nc, m, bilateral_direct, new_);
            if (bilateral_direct) direct_bilateral(P, new_, k);
            ck = check(lam, new_, m, tol_rel, tol_abs);
            if (autoa) {
                if (!ck.finite && hist[1] != 1.0) { /* from Λ^0 again, spectral steps */
                    res = ck.res;
                    auto_restart(hist, lam, w.lam0, rk, rs, m);
                    long_step = 0;
                    T_old = initial_energy(&P->v, lam, criterion);
                    continue;
                }
                long_step =
                    auto_jor_save(k, lam, new_, xi, ck.res, rs, rk, hist, w.dsave, w.xsave, m);
            }
            memcpy(lam, new_, (size_t)m * sizeof(double));
        }
        res = ck.res;
        prox_result_t out;
        if (delassus_sweep_end(&P->v, lam, ck, k, criterion, &T_old, tol_rel, tol_abs, &out))
            return out;
        if (stall_seen(&stall, k, res)) {
            velocity_of(&P->v, lam);
            return result(k + 1, STATUS_STALLED, res);
        }
    }
    velocity_of(&P->v, lam);
    return result(max_iter, STATUS_MAX_ITER, res);
}

/* sor_prox_delassus: SOR on ξ = GΛ + c, work buffer old (m: Λ of the last sweep) */
static prox_result_t sor_prox_delassus(delassus_t *P, double *old) {
    const settings_t *s = P->s;
    const double *G = P->G, *c = P->c, *mu = P->mu, *bound = P->bound;
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
    stall_t stall = stall_start(s);
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
            direct_bilateral(P, lam, k);
        } else {
            for (i64 a = o; a < m; a++) {
                double sm = c[a];
                for (i64 p = gp_ptr[a]; p < gp_ptr[a + 1]; p++) {
                    i64 l = gp_idx[p];
                    sm = sm + G[a * m + l] * lam[l];
                }
                lam[a] = prox_row(lam[a] - rk[a] * sm, bound, a - o);
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
        if (stall_seen(&stall, k, res)) {
            velocity_of(&P->v, lam);
            return result(k + 1, STATUS_STALLED, res);
        }
    }
    velocity_of(&P->v, lam);
    return result(max_iter, STATUS_MAX_ITER, res);
}

/* envelope_columns: L_B's envelope by columns (nd > 0 bilateral rows), else empty */
static void envelope_columns_of(const patterns_t *pat, i64 nd, arena_t *ar, i64 **ptr, i64 **idx) {
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
                                   const double *mu, const double *r, const double *bound,
                                   double *lam, const double *LB, i64 nb_LB, const double *M,
                                   const double *u_free, const double *MinvW, i64 nv, double *u,
                                   arena_t *ar) {
    i64 nd = s->bilateral_direct ? m - 3 * nc : 0;
    i64 nw = jor ? 2 * m : m;
    double *work = arena_f(ar, nw + nd);
    i64 *col_ptr, *col_idx;
    envelope_columns_of(pat, nd, ar, &col_ptr, &col_idx);
    delassus_t P = {s,
                    pat,
                    G,
                    c,
                    mu,
                    r,
                    bound,
                    LB,
                    lam,
                    m,
                    nc,
                    nb_LB,
                    {s->form, G, G, MinvW, pat, m, nv},
                    {u_free, MinvW, M, pat->mp_ptr, pat->mp_idx, nv, m, u},
                    {col_ptr, col_idx, work + nw, NULL},
                    ar};
    return jor ? jor_prox_delassus(&P, work) : sor_prox_delassus(&P, work);
}

/* jor_prox_velocity: JOR in the end velocity u^k (Eqn. 17-19), G never formed */
static prox_result_t jor_prox_velocity(const settings_t *s, const patterns_t *pat, const double *Wt,
                                       const double *MinvW, const double *u_free,
                                       const double *bvec, i64 m, i64 nv, i64 nc, const double *mu,
                                       const double *r, const double *bound, double *lam,
                                       const double *LB, i64 nb_LB, const double *M, double *u,
                                       arena_t *ar) {
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
    /* bilateral_direct_velocity's copy of u_free and rhs, allocated once */
    double *uu = NULL, *rhs = NULL;
    if (bilateral_direct) {
        uu = arena_f(ar, nv);
        rhs = arena_f(ar, m - 3 * nc);
    }
    int long_step = 0;
    velocity_from_impulses(u_free, MinvW, nv, m, lam, u, mp_ptr, mp_idx);
    double T_old = criterion == CRITERION_ENERGY ? kinetic_energy(M, u, nv) : 0.0;
    double res = 0.0;
    stall_t stall = stall_start(s);
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
        jor_project(lam, xi, rk, mu, bound, nc, m, bilateral_direct, new_);
        if (bilateral_direct)
            bilateral_direct_velocity(Wt, MinvW, u_free, m, nv, nc, LB, nb_LB, new_, pat, uu, rhs);
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
            long_step = auto_jor_save(k, lam, new_, xi, ck.res, rs, rk, hist, w.dsave, w.xsave, m);
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
        if (stall_seen(&stall, k, res)) return result(k + 1, STATUS_STALLED, res);
    }
    return result(max_iter, STATUS_MAX_ITER, res);
}

/* sor_prox_velocity: SOR in the end velocity, u updated after each contact (Eqn. 18), then
 * the bilateral rows (Eqn. 19, or Eqn. 20 when direct) */
static prox_result_t sor_prox_velocity(const settings_t *s, const patterns_t *pat, const double *Wt,
                                       const double *MinvW, const double *u_free,
                                       const double *bvec, i64 m, i64 nv, i64 nc, const double *mu,
                                       const double *r, const double *bound, double *lam,
                                       const double *LB, i64 nb_LB, const double *M, double *u,
                                       arena_t *ar) {
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
    stall_t stall = stall_start(s);
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
                bilateral_direct_velocity(Wt, MinvW, u_free, m, nv, nc, LB, nb_LB, lam, pat, uu,
                                          rhs);
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
                if (bound) d_ = prox_row(lam[a] + d_, bound, a - o) - lam[a];
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
        if (stall_seen(&stall, k, res)) return result(k + 1, STATUS_STALLED, res);
    }
    return result(max_iter, STATUS_MAX_ITER, res);
}

/* prox_solve: one prox solve with the settings' form and scheme */
prox_result_t prox_solve(const settings_t *s, const patterns_t *pat, const double *Wt,
                         const double *MinvW, const double *u_free, const double *bvec,
                         const double *G, const double *c, i64 m, i64 nv, i64 nc, const double *mu,
                         const double *r, const double *bound, double *lam, const double *LB,
                         i64 nb_LB, const double *M, double *u, arena_t *a) {
    if (s->form == FORM_DELASSUS)
        return delassus_prox(s->scheme == SCHEME_JOR, s, pat, G, c, m, nc, mu, r, bound, lam, LB,
                             nb_LB, M, u_free, MinvW, nv, u, a);
    if (s->scheme == SCHEME_JOR)
        return jor_prox_velocity(s, pat, Wt, MinvW, u_free, bvec, m, nv, nc, mu, r, bound, lam, LB,
                                 nb_LB, M, u, a);
    return sor_prox_velocity(s, pat, Wt, MinvW, u_free, bvec, m, nv, nc, mu, r, bound, lam, LB,
                             nb_LB, M, u, a);
}
