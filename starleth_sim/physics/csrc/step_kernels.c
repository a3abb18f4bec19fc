/* The phases of Moreau's midpoint step (step_kernels.py): the contact problem set up at the
 * midpoint (Fig. 7 phases "M^-1" and "G"), its solution (phase "prox", with the post-step
 * projection) and Eqn. (8). */
#include "step.h"

#include <string.h>

/* free_velocity: u_free = u^S + M^{-1} h Δt with the LTDL factor L of M */
void free_velocity(const double *h, double dt, const double *uS, i64 nv, const i64 *dof_parent,
                   const double *L, double *u_free) {
    for (i64 k = 0; k < nv; k++) u_free[k] = h[k] * dt;
    ltdl_solve_vec(L, nv, dof_parent, u_free);
    for (i64 k = 0; k < nv; k++) u_free[k] += uS[k];
}

/* solve_compliant: the factor of M into L (unless factor is 0), the compliant forces at
 * (q^M, u^S) added to h, and u_free = u^S + M^{-1} h Δt (= u^E) */
int solve_compliant(const compliant_law_t *law, const double *M, double *h, const double *uS,
                    i64 nv, double dt, i64 nc, const double *gap, const double *position,
                    const double *Wt_all, u8 *closed, u8 *slip, double *anchor,
                    const double *frames, double *lam, const i64 *dof_parent, int factor, double *L,
                    double *u_free, double *timings) {
    double t = kclock(timings);
    if (factor) {
        int ok = ltdl(M, nv, dof_parent, L);
        t = klap(timings, PHASE_M_INVERSE, t);
        if (!ok) return 0;
    }
    compliant_contact_forces(law, nc, nv, gap, position, Wt_all, uS, closed, slip, anchor, frames,
                             lam);
    generalized_contact_force(Wt_all, lam, nc, nv, h);
    t = klap(timings, PHASE_REST, t);
    free_velocity(h, dt, uS, nv, dof_parent, L, u_free);
    klap(timings, PHASE_M_INVERSE, t);
    return 1;
}

/* active_set: I = {i | g_N,i ≤ g_act}, with hysteresis also the contacts loaded in the last
 * step while g_N,i ≤ opening_gap; *opened counts the loaded contacts left out */
static i64 *active_set(const double *gap, i64 nc, const settings_t *s, const double *last_impulse,
                       const u8 *last_active, arena_t *a, i64 *na, i64 *opened) {
    i64 *picked = arena_i(a, nc);
    i64 n = 0, op = 0;
    for (i64 i = 0; i < nc; i++) {
        int loaded = last_active[i] && last_impulse[3 * i] > 0.0;
        if (gap[i] <= s->activation_gap || (s->hysteresis && loaded && gap[i] <= s->opening_gap))
            picked[n++] = i;
        else if (loaded)
            op++;
    }
    *na = n;
    *opened = op;
    return picked;
}

/* normal_law_offset: the gap terms of b_N */
static double normal_law_offset(double gap, double dt, double beta_velocity) {
    if (gap > 0.0) return gap / dt;
    return beta_velocity * gap / dt;
}

/* An empty pattern (np.zeros(1) as every ptr, empty indices) */
static void empty_patterns(patterns_t *pat, arena_t *a) {
    i64 *e = arena_i(a, 1);
    e[0] = 0;
    pat->wp_ptr = pat->mp_ptr = pat->gp_ptr = e;
    pat->wp_idx = pat->mp_idx = pat->gp_idx = pat->lb_first = e;
    pat->n_lb = 0;
}

/* same_active_set: I of p is the last step's (last_active, nc flags) */
static int same_active_set(const problem_t *p, const u8 *last_active, i64 nc) {
    i64 n = 0;
    for (i64 i = 0; i < nc; i++) n += last_active[i] != 0;
    if (n != p->na) return 0;
    for (i64 r = 0; r < p->na; r++)
        if (!last_active[p->active[r]]) return 0;
    return 1;
}

/* lazy_delassus: G may be left unformed (problem_t.lazy_G): the prox memory says the last
 * solve took a few sweeps with the same active set, and the velocity form iterates the same
 * rows (a fixed α, no direct bilateral method, no JOR bilateral sweep, the impulse
 * criterion) */
static int lazy_delassus(const settings_t *s, const double *memory, const problem_t *p,
                         const u8 *last_active, i64 nc) {
    if (!memory || s->form != FORM_DELASSUS || s->bilateral_direct || !(s->alpha > 0.0)) return 0;
    if (s->scheme == SCHEME_JOR && s->bilateral_relaxation > 0.0) return 0;
    if (s->criterion != CRITERION_IMPULSE) return 0;
    return memory[2] <= (double)LAZY_DELASSUS_LAST && same_active_set(p, last_active, nc);
}

/* minv_w: M^{-1}W of p (from its W^T, with the factor p->L of M) and the pattern of its
 * columns, unless formed already */
static void minv_w(problem_t *p, arena_t *a) {
    if (p->minv_w_ready) return;
    i64 m = p->m, nv = p->nv;
    const double *Wt = p->Wt, *L = p->L;
    const i64 *dof_parent = p->dof_parent, *wp_ptr = p->pat.wp_ptr, *wp_idx = p->pat.wp_idx;
    double *MinvW = p->MinvW;
    i64 *mp_ptr, *mp_idx;
    i64 trees = 1;
    for (i64 k = 1; k < nv; k++)
        if (dof_parent[k] == -1) trees++;
    /* W = (W^T)^T into a zeroed M^{-1}W: its nonzeros only */
    for (i64 k = 0; k < nv * m; k++) MinvW[k] = 0.0;
    for (i64 r = 0; r < m; r++)
        for (i64 q = wp_ptr[r]; q < wp_ptr[r + 1]; q++)
            MinvW[wp_idx[q] * m + r] = Wt[r * nv + wp_idx[q]];
    if (trees > 2) {
        ltdl_solve_cols_pattern(L, dof_parent, MinvW, nv, m, wp_ptr, wp_idx, a, &mp_ptr, &mp_idx);
    } else {
        ltdl_solve_cols(L, dof_parent, MinvW, nv, m, a);
        col_pattern(MinvW, nv, m, a, &mp_ptr, &mp_idx);
    }
    p->pat.mp_ptr = mp_ptr;
    p->pat.mp_idx = mp_idx;
    p->minv_w_ready = 1;
}

/* phase_minv: the factor of M (unless factor is 0), the active set, W^T = [W_U^T of the
 * active contacts; W_B^T], M^{-1}W (left to minv_w where G is lazy under JOR: lazy_delassus
 * with the prox memory), b = [ε W_U^T u^S + gap terms; b_B] and the patterns of W^T's rows and
 * M^{-1}W's columns (G's still empty) into p */
static void phase_minv(const settings_t *s, const double *M, const double *uS, i64 nv,
                       const double *gap, i64 nc, const double *Wt_all, const double *WtB, i64 nb,
                       const double *bB, const double *eps, const i64 *dof_parent, int factor,
                       double *L, const double *last_impulse, const u8 *last_active,
                       const double *memory, arena_t *a, problem_t *p) {
    double dt = s->dt, beta_velocity = s->beta_velocity;
    int ok = 1;
    if (factor) ok = ltdl(M, nv, dof_parent, L);
    i64 na, opened;
    i64 *active = active_set(gap, nc, s, last_impulse, last_active, a, &na, &opened);
    i64 o = 3 * na;
    i64 m = o + nb;
    double *buf = arena_f(a, 2 * m * nv + m); /* W^T, M^{-1}W and b */
    double *Wt = buf, *MinvW = buf + m * nv, *bvec = buf + 2 * m * nv;
    for (i64 k = 0; k < m; k++) bvec[k] = 0.0;
    p->ok = ok;
    p->na = na;
    p->active = active;
    p->m = m;
    p->nv = nv;
    p->Wt = Wt;
    p->MinvW = MinvW;
    p->b = bvec;
    p->opened = opened;
    p->G = p->Gdiag = p->LB = NULL;
    p->nb_LB = 0;
    p->bound = NULL;
    p->nf = 0;
    p->lazy_G = 0;
    p->minv_w_ready = 1;
    if (!ok || m == 0) {
        empty_patterns(&p->pat, a);
        return;
    }
    for (i64 r = 0; r < na; r++) {
        i64 i = active[r];
        for (i64 k = 0; k < 3; k++)
            for (i64 j = 0; j < nv; j++) Wt[(3 * r + k) * nv + j] = Wt_all[(3 * i + k) * nv + j];
    }
    for (i64 r = 0; r < nb; r++)
        for (i64 j = 0; j < nv; j++) Wt[(o + r) * nv + j] = WtB[r * nv + j];
    i64 *wp_ptr, *wp_idx;
    row_pattern(Wt, m, nv, a, &wp_ptr, &wp_idx);
    p->pat.wp_ptr = wp_ptr;
    p->pat.wp_idx = wp_idx;
    p->L = L;
    p->dof_parent = dof_parent;
    p->lazy_G = lazy_delassus(s, memory, p, last_active, nc);
    p->minv_w_ready = 0;
    if (!(p->lazy_G && s->scheme == SCHEME_JOR)) minv_w(p, a);
    for (i64 r = 0; r < o; r++) {
        double sum = 0.0;
        for (i64 q = wp_ptr[r]; q < wp_ptr[r + 1]; q++)
            sum += Wt[r * nv + wp_idx[q]] * uS[wp_idx[q]];
        bvec[r] = eps[2 * active[r / 3] + (r % 3 == 0 ? 0 : 1)] * sum;
    }
    for (i64 r = 0; r < na; r++)
        bvec[3 * r] += normal_law_offset(gap[active[r]], dt, beta_velocity);
    for (i64 r = 0; r < nb; r++) bvec[o + r] = bB[r];
    p->pat.gp_ptr = wp_ptr; /* (G's pattern is still to come) */
    p->pat.gp_idx = wp_idx;
    p->pat.lb_first = wp_idx;
    p->pat.n_lb = 0;
}

/* phase_delassus: G = W^T M^{-1} W (Delassus form) or only diag(G) (velocity form), and for
 * the direct bilateral method the Cholesky factor L_B of G_BB; G's pattern and L_B's
 * envelope into *full (from pat). Returns 0 if G_BB is not positive definite. */
static int phase_delassus(i64 form, i64 nc, int bilateral_direct, const double *Wt,
                          const double *MinvW, i64 m, i64 nv, const patterns_t *pat, arena_t *a,
                          double **G_out, double **Gdiag_out, double **LB_out, i64 *nb_LB,
                          patterns_t *full) {
    i64 o = 3 * nc;
    i64 nb = m - o;
    double *G = NULL, *Gdiag;
    i64 *gp_ptr, *gp_idx;
    if (form == FORM_DELASSUS) {
        double *buf = arena_f(a, m * m + m);
        G = buf;
        Gdiag = buf + m * m;
        delassus(Wt, MinvW, G, m, nv, pat->wp_ptr, pat->wp_idx, pat->mp_ptr, pat->mp_idx, a);
        for (i64 r = 0; r < m; r++) Gdiag[r] = G[r * m + r];
        row_pattern(G, m, m, a, &gp_ptr, &gp_idx);
    } else {
        Gdiag = arena_f(a, m);
        delassus_diagonal(Wt, MinvW, Gdiag, m, nv, pat->wp_ptr, pat->wp_idx);
        gp_ptr = arena_i(a, m + 1);
        for (i64 r = 0; r <= m; r++) gp_ptr[r] = 0;
        gp_idx = gp_ptr;
    }
    double *LB = NULL;
    i64 *lb_first = gp_idx;
    i64 n_lb = 0;
    int ok = 1;
    if (bilateral_direct && nb > 0) {
        const double *GB;
        i64 nA, ob;
        if (form == FORM_DELASSUS) { /* G_BB: G's lower right block, read in place */
            GB = G;
            nA = m;
            ob = o;
        } else {
            double *W = arena_f(a, nb * nb);
            for (i64 r = 0; r < nb; r++)
                for (i64 c = r; c < nb; c++) {
                    double sum = 0.0;
                    for (i64 q = pat->wp_ptr[o + r]; q < pat->wp_ptr[o + r + 1]; q++)
                        sum +=
                            Wt[(o + r) * nv + pat->wp_idx[q]] * MinvW[pat->wp_idx[q] * m + o + c];
                    W[r * nb + c] = sum;
                    W[c * nb + r] = sum;
                }
            GB = W;
            nA = nb;
            ob = 0;
        }
        LB = arena_zeros(a, nb * nb);
        lb_first = arena_i(a, nb);
        n_lb = nb;
        ok = cholesky_upper_input(GB, nA, ob, LB, lb_first);
    }
    full->wp_ptr = pat->wp_ptr;
    full->wp_idx = pat->wp_idx;
    full->mp_ptr = pat->mp_ptr;
    full->mp_idx = pat->mp_idx;
    full->gp_ptr = gp_ptr;
    full->gp_idx = gp_idx;
    full->lb_first = lb_first;
    full->n_lb = n_lb;
    *G_out = G;
    *Gdiag_out = Gdiag;
    *LB_out = LB;
    *nb_LB = LB ? nb : 0;
    return ok;
}

/* constraint_velocity: c = W^T u_free + b (Eqn. 15) */
void constraint_velocity(const double *Wt, i64 m, i64 nv, const double *u_free, const double *bvec,
                         const i64 *wp_ptr, const i64 *wp_idx, double *c) {
    for (i64 r = 0; r < m; r++) {
        double sum = bvec[r];
        for (i64 q = wp_ptr[r]; q < wp_ptr[r + 1]; q++)
            sum += Wt[r * nv + wp_idx[q]] * u_free[wp_idx[q]];
        c[r] = sum;
    }
}

/* alpha_start: the scale of the paper's α the solve starts with, from the α memory
 * (SimState.prox_memory: [scale, steps held], NULL: none): the scale of the last step's
 * converged fallback while I stays the same and it was held for fewer than fallback_hold
 * steps, else 1 */
static double alpha_start(const settings_t *s, const double *memory, const problem_t *p,
                          const u8 *last_active, i64 nc) {
    if (!memory || s->fallback_hold <= 0 || !(memory[0] < 1.0)) return 1.0;
    if (memory[1] >= (double)s->fallback_hold || !same_active_set(p, last_active, nc)) return 1.0;
    return memory[0];
}

/* form_delassus: G of a problem left lazy (problem_t.lazy_G), its rows' pattern and diag(G)
 * from it, as phase_delassus forms them */
static void form_delassus(problem_t *p, arena_t *a) {
    if (!p->lazy_G) return;
    minv_w(p, a);
    i64 m = p->m;
    double *G = arena_f(a, m * m);
    delassus(p->Wt, p->MinvW, G, m, p->nv, p->pat.wp_ptr, p->pat.wp_idx, p->pat.mp_ptr,
             p->pat.mp_idx, a);
    for (i64 r = 0; r < m; r++) p->Gdiag[r] = G[r * m + r];
    row_pattern(G, m, m, a, &p->pat.gp_ptr, &p->pat.gp_idx);
    p->G = G;
    p->lazy_G = 0;
}

/* lazy_probe: a problem whose G is unformed tries LAZY_DELASSUS_SWEEPS sweeps of the velocity
 * form (the same rows on u^k = u_free + M^{-1}WΛ^k, Eqn. 17-19; M^{-1} by the factor of M
 * where M^{-1}W is unformed too) from Λ^0 in lam with r; 1 when they converge (*res), else G
 * is formed (the solve then starts again in the Delassus form) and 0 */
static int lazy_probe(const settings_t *s, problem_t *p, const double *u_free, const double *M,
                      const double *mu, const double *r, double *lam, double *u, arena_t *a,
                      prox_result_t *res) {
    settings_t probe = *s;
    probe.form = FORM_VELOCITY;
    probe.max_iterations = LAZY_DELASSUS_SWEEPS;
    probe.stall_window = 0;
    if (p->minv_w_ready)
        *res = prox_solve(&probe, &p->pat, p->Wt, p->MinvW, u_free, p->b, NULL, NULL, p->m, p->nv,
                          p->na, mu, r, p->bound, lam, p->LB, p->nb_LB, M, u, a);
    else
        *res = jor_velocity_factored(&probe, &p->pat, p->Wt, u_free, p->b, p->m, p->nv, p->na, mu,
                                     r, p->bound, lam, p->L, p->dof_parent, u, a);
    if (res->status == STATUS_CONVERGED) return 1;
    form_delassus(p, a);
    return 0;
}

/* phase_prox: c (timed as phase "G" from t), the warm start, lazy_probe where G is unformed,
 * the prox iteration from α times scale (alpha_start) and one retry with α·fallback_alpha_factor.
 * *uE, *lam point into the arena. With memory (the prox memory; NULL: none) its next value into
 * alpha_E: [the converged try's scale, steps held] ([1, 0]: the paper's α or not converged), the
 * solve's sweeps. Returns the time at the end of phase "G". (long: the tries, many outputs) */
static double phase_prox(const settings_t *s, problem_t *p, const u8 *last_active, double scale,
                         const double *memory, const double *u_free, const double *M,
                         const double *last_impulse, const double *last_bilateral, double *timings,
                         double t, arena_t *a, double **uE, double **lam_out,
                         complete_result_t *out, double *alpha_E) {
    const i64 *active = p->active;
    double alpha = s->alpha * scale;
    double fallback_factor = s->fallback_alpha_factor;
    i64 na = p->na, o = 3 * na, m = p->m, nv = p->nv;
    double *buf = arena_f(a, 4 * m + nv + na);
    double *c = buf + 3 * m + nv + na;
    constraint_velocity(p->Wt, m, nv, u_free, p->b, p->pat.wp_ptr, p->pat.wp_idx, c);
    t = klap(timings, PHASE_G, t);
    double *lam0 = buf, *lam = buf + m, *r = buf + 2 * m, *u = buf + 3 * m;
    double *mu_vec = buf + 3 * m + nv;
    for (i64 k = 0; k < m; k++) lam0[k] = 0.0;
    if (s->warm_start) {
        for (i64 r_ = 0; r_ < na; r_++) {
            i64 i = active[r_];
            if (last_active[i])
                for (i64 k = 0; k < 3; k++) lam0[3 * r_ + k] = last_impulse[3 * i + k];
        }
        for (i64 r_ = 0; r_ < m - o; r_++) lam0[o + r_] = last_bilateral[r_];
    }
    for (i64 k = 0; k < na; k++) mu_vec[k] = p->mu ? p->mu[active[k]] : s->mu;
    int attempts = fallback_factor > 0.0 ? 2 : 1;
    memcpy(lam, lam0, (size_t)m * sizeof(double));
    i64 it_sum = 0;
    prox_result_t res = {0, STATUS_CONVERGED, 0.0};
    int again = 0;
    settings_t try_s = *s;
    if (p->lazy_G) {
        prox_parameters(p->Gdiag, m, na, alpha, r);
        relax_bilateral_rows(s, p->Gdiag, m, na, scale, r);
        if (lazy_probe(s, p, u_free, M, mu_vec, r, lam, u, a, &res)) attempts = 0;
        it_sum = res.iterations;
    }
    for (int attempt = 0; attempt < attempts; attempt++) {
        prox_parameters(p->Gdiag, m, na, alpha, r);
        relax_bilateral_rows(s, p->Gdiag, m, na, scale, r);
        memcpy(lam, lam0, (size_t)m * sizeof(double));
        if (attempt + 1 == attempts) try_s.stall_window = 0; /* the last try runs to the cap */
        res = prox_solve(&try_s, &p->pat, p->Wt, p->MinvW, u_free, p->b, p->G, c, m, nv, na, mu_vec,
                         r, p->bound, lam, p->LB, p->nb_LB, M, u, a);
        it_sum += res.iterations;
        if (res.status == STATUS_CONVERGED) break;
        if (attempt + 1 < attempts) {
            again = 1;
            alpha *= fallback_factor;
            scale *= fallback_factor;
        }
    }
    if (memory) {
        int kept = res.status == STATUS_CONVERGED && scale < 1.0;
        alpha_E[0] = kept ? scale : 1.0;
        alpha_E[1] = kept && !again && scale == memory[0] ? memory[1] + 1.0 : 0.0;
        alpha_E[2] = (double)it_sum;
    }
    *uE = u;
    *lam_out = lam;
    out->iterations = it_sum;
    out->status = res.status;
    out->residual = res.residual;
    out->retried = again;
    return t;
}

/* joint_friction_prox: Λ_f of a problem p of joint friction rows alone (the compliant step,
 * whose contacts are forces in h; p->bound their bounds τ_c Δt), from Λ_f^0 in lam_f (out:
 * Λ_f); u^E = u_free + M^{-1} W_f Λ_f into uE. The prox's status (STATUS_*), *iters its
 * iterations. */
i64 joint_friction_prox(const settings_t *s, problem_t *p, const double *u_free, const double *M,
                        double *lam_f, double *uE, i64 *iters, arena_t *a) {
    double *u, *lam;
    complete_result_t res;
    phase_prox(s, p, NULL, 1.0, NULL, u_free, M, NULL, lam_f, NULL, 0.0, a, &u, &lam, &res, NULL);
    i64 status = res.status;
    *iters = res.iterations;
    memcpy(uE, u, (size_t)p->nv * sizeof(double));
    memcpy(lam_f, lam, (size_t)p->m * sizeof(double));
    for (i64 k = 0; k < p->nv; k++)
        if (!isfinite(uE[k])) status = STATUS_NONFINITE;
    return status;
}

/* predicted_end_gaps: g_N^E ≈ g_N(q^M) + ½Δt W_N^T u^E of the contacts whose Jacobian is
 * known, +inf for the others; returns the smallest */
static double predicted_end_gaps(const double *gap, i64 nc, const double *Wt_all, i64 nv,
                                 double jacobian_gap, const u8 *is_active, const double *uE,
                                 double dt, double *out) {
    double worst = INFINITY;
    for (i64 i = 0; i < nc; i++) {
        if (!(is_active[i] || gap[i] <= jacobian_gap)) {
            out[i] = INFINITY;
            continue;
        }
        double sum = 0.0;
        for (i64 j = 0; j < nv; j++) sum += Wt_all[3 * i * nv + j] * uE[j];
        out[i] = gap[i] + 0.5 * dt * sum;
        if (out[i] < worst) worst = out[i];
    }
    return worst;
}

/* projection_problem: W^T and M^{-1}W of the projection with the contacts `extra` added
 * after the active ones (then the bilateral rows); the contacts in row order into
 * *contacts, the patterns of W^T's rows and M^{-1}W's columns into *pat. Returns the rows. */
static i64 projection_problem(const problem_t *p, const i64 *extra, i64 ne, const double *Wt_all,
                              const i64 *dof_parent, const double *L, arena_t *a,
                              i64 **contacts_out, double **Wp_out, double **Mp_out,
                              patterns_t *pat) {
    i64 na = p->na, m0 = p->m, nv = p->nv;
    i64 o0 = 3 * na;
    i64 nb = m0 - o0 - p->nf; /* (the joint friction rows left out: no position law) */
    i64 nc = na + ne;
    i64 o = 3 * nc;
    i64 m = o + nb;
    i64 *contacts = arena_i(a, nc);
    for (i64 k = 0; k < na; k++) contacts[k] = p->active[k];
    for (i64 k = 0; k < ne; k++) contacts[na + k] = extra[k];
    double *Wp = arena_f(a, m * nv);
    double *Mp = arena_zeros(a, nv * m);
    for (i64 r = 0; r < o0; r++)
        for (i64 j = 0; j < nv; j++) {
            Wp[r * nv + j] = p->Wt[r * nv + j];
            Mp[j * m + r] = p->MinvW[j * m0 + r];
        }
    for (i64 e = 0; e < ne; e++)
        for (i64 r = 0; r < 3; r++)
            for (i64 j = 0; j < nv; j++)
                Wp[(o0 + 3 * e + r) * nv + j] = Wt_all[(3 * extra[e] + r) * nv + j];
    i64 nx = 3 * ne;
    double *cols = arena_f(a, nv * nx);
    for (i64 c = 0; c < nx; c++)
        for (i64 j = 0; j < nv; j++) cols[j * nx + c] = Wp[(o0 + c) * nv + j];
    ltdl_solve_cols(L, dof_parent, cols, nv, nx, a);
    for (i64 c = 0; c < nx; c++)
        for (i64 j = 0; j < nv; j++) Mp[j * m + o0 + c] = cols[j * nx + c];
    for (i64 r = 0; r < nb; r++)
        for (i64 j = 0; j < nv; j++) {
            Wp[(o + r) * nv + j] = p->Wt[(o0 + r) * nv + j];
            Mp[j * m + o + r] = p->MinvW[j * m0 + o0 + r];
        }
    i64 *wp_ptr, *wp_idx, *mp_ptr, *mp_idx;
    row_pattern(Wp, m, nv, a, &wp_ptr, &wp_idx);
    col_pattern(Mp, nv, m, a, &mp_ptr, &mp_idx);
    empty_patterns(pat, a);
    pat->wp_ptr = wp_ptr;
    pat->wp_idx = wp_idx;
    pat->mp_ptr = mp_ptr;
    pat->mp_idx = mp_idx;
    *contacts_out = contacts;
    *Wp_out = Wp;
    *Mp_out = Mp;
    return m;
}

/* phase_projection: the post-step projection (contact.penetration_correction
 * "projection"); u_corr receives Δu_p. Returns the iterations, *status the prox status
 * (−1: not needed). */
static i64 phase_projection(const settings_t *s, problem_t *p, const u8 *is_active,
                            const double *gap, i64 nc, const double *Wt_all, const i64 *dof_parent,
                            const double *L, const double *M, const double *uE, double *u_corr,
                            arena_t *a, i64 *status) {
    double dt = s->dt, beta = s->beta_projection, tolerance = s->projection_tolerance;
    i64 nv = p->nv;
    for (i64 k = 0; k < nv; k++) u_corr[k] = 0.0;
    double *gE = arena_f(a, nc);
    double worst = predicted_end_gaps(gap, nc, Wt_all, nv, s->jacobian_gap, is_active, uE, dt, gE);
    if (worst >= -tolerance || beta == 0.0) {
        *status = -1;
        return 0;
    }
    minv_w(p, a);
    i64 *extra = arena_i(a, nc);
    i64 ne = 0;
    for (i64 i = 0; i < nc; i++)
        if (!is_active[i] && gE[i] < -tolerance) extra[ne++] = i;
    const i64 *contacts;
    const double *Wp, *Mp, *Gp, *Gdp;
    patterns_t full;
    i64 m, ncp;
    if (ne == 0 && p->nf == 0) {
        form_delassus(p, a);
        contacts = p->active;
        ncp = p->na;
        Wp = p->Wt;
        Mp = p->MinvW;
        Gp = p->G;
        Gdp = p->Gdiag;
        full = p->pat;
        m = p->m;
    } else {
        i64 *cs;
        double *W_, *M_, *G_, *Gd_, *LB_;
        patterns_t part, f;
        i64 nb_;
        m = projection_problem(p, extra, ne, Wt_all, dof_parent, L, a, &cs, &W_, &M_, &part);
        ncp = p->na + ne;
        phase_delassus(s->form, ncp, 0, W_, M_, m, nv, &part, a, &G_, &Gd_, &LB_, &nb_, &f);
        /* the bilateral rows, G_BB and so L_B are the problem's: L_B's envelope with them */
        full = f;
        full.lb_first = p->pat.lb_first;
        full.n_lb = p->pat.n_lb;
        contacts = cs;
        Wp = W_;
        Mp = M_;
        Gp = G_;
        Gdp = Gd_;
    }
    double *bp = arena_zeros(a, m);
    for (i64 r = 0; r < ncp; r++) {
        double g = gE[contacts[r]];
        bp[3 * r] = (py_max(g, 0.0) + beta * py_min(g, 0.0)) / (0.5 * dt);
    }
    double *r = arena_f(a, m);
    prox_parameters(Gdp, m, ncp, s->alpha, r);
    relax_bilateral_rows(s, Gdp, m, ncp, 1.0, r);
    double *lam = arena_zeros(a, m);
    double *mu = arena_zeros(a, ncp);
    double *zero = arena_zeros(a, nv);
    settings_t proj_s = *s;
    proj_s.stall_window = 0; /* no retry here: the projection's solve runs to the cap */
    prox_result_t res = prox_solve(&proj_s, &full, Wp, Mp, zero, bp, Gp, bp, m, nv, ncp, mu, r,
                                   NULL, lam, p->LB, p->nb_LB, M, u_corr, a);
    if (res.status == STATUS_NONFINITE)
        for (i64 k = 0; k < nv; k++) u_corr[k] = 0.0;
    *status = res.status;
    return res.iterations;
}

/* lazy_diagonal: diag(G) alone of a problem whose G is left unformed (from M^{-1}W, or with
 * the factor of M where that is unformed too), G's pattern empty */
static void lazy_diagonal(problem_t *p, arena_t *a) {
    i64 m = p->m;
    p->Gdiag = arena_f(a, m);
    if (p->minv_w_ready)
        delassus_diagonal(p->Wt, p->MinvW, p->Gdiag, m, p->nv, p->pat.wp_ptr, p->pat.wp_idx);
    else
        factored_delassus_diagonal(p->Wt, m, p->nv, p->pat.wp_ptr, p->pat.wp_idx, p->L,
                                   p->dof_parent, p->Gdiag, p->MinvW); /* (its buffer as work:
                                                                          minv_w forms it anew) */
    i64 *none = arena_i(a, m + 1);
    for (i64 r = 0; r <= m; r++) none[r] = 0;
    p->pat.gp_ptr = p->pat.gp_idx = p->pat.lb_first = none;
    p->pat.n_lb = 0;
    p->G = p->LB = NULL;
    p->nb_LB = 0;
}

/* contact_problem: phases "M^-1" and "G" (phase_minv, phase_delassus; G left to the solve
 * where lazy_delassus) */
void contact_problem(const settings_t *s, const double *M, const double *uS, i64 nv,
                     const double *gap, i64 nc, const double *Wt_all, const double *WtB, i64 nb,
                     const double *bB, const double *eps, const double *frames,
                     const i64 *dof_parent, int factor, double *L, const double *last_impulse,
                     const u8 *last_active, const double *memory, double *timings, arena_t *a,
                     problem_t *p) {
    double t = kclock(timings);
    phase_minv(s, M, uS, nv, gap, nc, Wt_all, WtB, nb, bB, eps, dof_parent, factor, L, last_impulse,
               last_active, memory, a, p);
    p->mu = NULL;
    if (frames) { /* (copied: a prepared problem outlives the call) */
        double *mu = arena_f(a, nc);
        for (i64 i = 0; i < nc; i++) mu[i] = frames[FRAME_STRIDE * i + 9];
        p->mu = mu;
    }
    t = klap(timings, PHASE_M_INVERSE, t);
    if (p->ok && p->m != 0 && p->lazy_G) {
        lazy_diagonal(p, a);
    } else if (p->ok && p->m != 0) {
        patterns_t full;
        p->ok = phase_delassus(s->form, p->na, s->bilateral_direct, p->Wt, p->MinvW, p->m, nv,
                               &p->pat, a, &p->G, &p->Gdiag, &p->LB, &p->nb_LB, &full);
        p->pat = full;
    } else {
        p->G = p->Gdiag = p->LB = NULL;
        p->nb_LB = 0;
    }
    klap(timings, PHASE_G, t);
}

/* remember_contacts: the warm-start memory of a finished step */
void remember_contacts(const u8 *is_active, const double *impulse, i64 nc, u8 *last_active,
                       double *last_impulse) {
    for (i64 i = 0; i < nc; i++) {
        last_active[i] = is_active[i];
        for (i64 k = 0; k < 3; k++) last_impulse[3 * i + k] = impulse[3 * i + k];
    }
}

/* no_contact_impulses: Λ and the active flags of every contact zeroed */
static void no_contact_impulses(i64 nc, double *impulse, u8 *is_active) {
    for (i64 i = 0; i < nc; i++) {
        is_active[i] = 0;
        impulse[3 * i] = 0.0;
        impulse[3 * i + 1] = 0.0;
        impulse[3 * i + 2] = 0.0;
    }
}

/* complete_problem: u_free (phase "M^-1"), c (phase "G"), the prox iteration and the
 * post-step projection (phase "prox") of the prepared problem p with h and M (M or M~): the
 * model and workspace t, the state x (its u^S, warm-start and α memory; Λ into its report,
 * u^E into uE), Λ_B into bilateral_E (which comes in with the warm start), the α memory
 * after the solve into alpha_E (2) */
complete_result_t complete_problem(problem_t *p, const double *h, const double *M,
                                   const tree_model_t *t, const step_arrays_t *x,
                                   double *bilateral_E, double *alpha_E, double *timings,
                                   arena_t *a) {
    const settings_t *s = &t->s;
    i64 nv = p->nv, nc = t->contacts.nc;
    double *impulse = x->report.impulse, *u = x->uE;
    double t0 = kclock(timings);
    free_velocity(h, s->dt, x->u, nv, t->dof_parent, t->L, t->u_free);
    t0 = klap(timings, PHASE_M_INVERSE, t0);
    no_contact_impulses(nc, impulse, x->is_active);
    i64 na = p->na, o = 3 * na;
    complete_result_t res = {0, STATUS_CONVERGED, 0.0, 0, 0, -1};
    for (i64 k = 0; k < nv; k++) t->u_corr[k] = 0.0;
    alpha_E[0] = 1.0;
    alpha_E[1] = 0.0;
    alpha_E[2] = 0.0;
    if (p->m == 0) {
        memcpy(u, t->u_free, (size_t)nv * sizeof(double));
    } else {
        double *uE, *lam;
        double scale = alpha_start(s, x->prox_memory, p, x->last_active, nc);
        t0 = phase_prox(s, p, x->last_active, scale, x->prox_memory, t->u_free, M, x->last_impulse,
                        bilateral_E, timings, t0, a, &uE, &lam, &res, alpha_E);
        memcpy(u, uE, (size_t)nv * sizeof(double));
        for (i64 r = 0; r < na; r++) {
            i64 i = p->active[r];
            x->is_active[i] = 1;
            for (i64 k = 0; k < 3; k++) impulse[3 * i + k] = lam[3 * r + k];
        }
        int finite = 1;
        for (i64 k = 0; k < nv; k++)
            if (!isfinite(u[k])) finite = 0;
        if (!finite) res.status = STATUS_NONFINITE;
        if (res.status != STATUS_NONFINITE)
            for (i64 r = 0; r < p->m - o; r++) bilateral_E[r] = lam[o + r];
        t0 = klap(timings, PHASE_PROX, t0);
    }
    if (res.status != STATUS_NONFINITE && s->beta_projection > 0.0) {
        t0 = kclock(timings);
        res.projection_iterations =
            phase_projection(s, p, x->is_active, t->gap, nc, t->Wt_all, t->dof_parent, t->L, M, u,
                             t->u_corr, a, &res.projection_status);
        klap(timings, PHASE_PROX, t0);
    }
    return res;
}

/* all_finite */
static int all_finite(const double *a_, i64 na, const double *b, i64 nb) {
    for (i64 k = 0; k < na; k++)
        if (!isfinite(a_[k])) return 0;
    for (i64 k = 0; k < nb; k++)
        if (!isfinite(b[k])) return 0;
    return 1;
}

/* end_of_step: Eqn. (8), q^E = q^M ⊕ ½Δt F(q^M) (u^E + Δu_p) */
int end_of_step(const double *qM, const double *uE, const double *u_corr, int projected,
                double half_dt, const tree_t *t, i64 nq, double *qE, arena_t *a) {
    i64 nv = t->nv;
    const double *v = uE;
    if (projected) {
        double *w = arena_f(a, nv);
        for (i64 k = 0; k < nv; k++) w[k] = uE[k] + u_corr[k];
        v = w;
    }
    integrate_forest(qM, v, half_dt, t, qE);
    return all_finite(qE, nq, uE, nv);
}
