/* One whole physics step in one call (tree_step.py): tree_step_hard / tree_step_compliant
 * for the minimal coordinates, forest_step_hard for a cut forest (the extended and maximal
 * coordinates). The same phases, in the same order, as the phase-by-phase path (so the same
 * result bit for bit); a failing step leaves the state as it was. The model travels in the
 * packed buffers of tree_step.TreeStepModel and CutModel, unpacked by the code that the build
 * generates from their declaration (kernels.layouts.py: tree_model_t, unpack_tree_model, ...). */
#include "step.h"

#include <string.h>

const char *check_tree_model(const packed_model_t *m, i64 nv) {
    if (m->n_ints < TREE_STEP_MODEL_HEADER) return "TreeStepModel: ints too short";
    const i64 *ints = m->ints;
    if (ints[TREE_STEP_MODEL_NJ] < 1 || ints[TREE_STEP_MODEL_NC] < 0 ||
        ints[TREE_STEP_MODEL_NA] < 0 || ints[TREE_STEP_MODEL_NV] != nv)
        return "TreeStepModel: sizes (nj, nc, na, nv) do not match the state";
    if (ints[TREE_STEP_MODEL_NT] < 14) return "TreeStepModel: the packed terrain lacks its header";
    tree_model_t t;
    if (!unpack_tree_model(m, &t)) return "TreeStepModel: buffer lengths do not match its sizes";
    return NULL;
}

const char *check_cut_model(const packed_model_t *c, i64 na, i64 nv) {
    if (c->n_ints < CUT_MODEL_HEADER) return "CutModel: ints too short";
    i64 ncut = c->ints[CUT_MODEL_NCUT], constant = c->ints[CUT_MODEL_CONSTANT] != 0,
        nr = c->ints[CUT_MODEL_NR];
    if (ncut < 0 || nr < 0 || (!constant && nr != 0))
        return "CutModel: sizes (ncut, constant, nr) are not valid";
    cut_model_t cm;
    if (!unpack_cut_model(c, na, nv, &cm)) return "CutModel: buffer lengths do not match its sizes";
    return NULL;
}

/* impedance_torque: the law term by term in this order (τ_ff, then the kp term, then the kd
 * term), which impedance.py's description and its tests follow */
void impedance_torque(const impedance_command_t *c, const double *q, const double *qd, double *tau,
                      i64 n) {
    for (i64 k = 0; k < n; k++) {
        double t = isnan(c->effort[k]) ? 0.0 : c->effort[k];
        if (!isnan(c->position[k])) t += c->kp[k] * (c->position[k] - q[k]);
        if (!isnan(c->velocity[k])) t += c->kd[k] * (c->velocity[k] - qd[k]);
        tau[k] = t;
    }
}

/* lag_torques: the drives' torque bandwidth, a first-order lag at the physics rate: τ_a =
 * τ_a^S + (1 − e^{−2π f Δt}) (τ − τ_a^S) of the torques τ in explicit_torque, from the
 * lag's state τ_a^S (lag_state); a lagged joint's damper is explicit (its law lags too) */
static void lag_torques(const tree_model_t *t, const report_t *r) {
    if (!t->drives) return;
    for (i64 k = 0; k < t->na; k++)
        if (t->lag[k] > 0.0) {
            double s = t->lag_state[k];
            r->explicit_torque[k] = s + t->lag[k] * (r->explicit_torque[k] - s);
            r->damper[k] = 0.0;
        }
}

/* applied_torque: the torques the motors apply for tau (torque_mode TORQUE_*: as given,
 * saturate_torque at the joint rates of u, the impedance law of the command tau at (q, u)
 * saturated, or a replay; then the drives' lag of the latter two: as given and a replay
 * are applied torques) into the report's explicit_torque, and the kd of the implicit
 * dampers into its damper: with an impedance command, the joints with a damper term whose
 * law at (q^S, u^S) is not saturated; 0 if the torques have a non-finite entry */
static int applied_torque(int torque_mode, const double *tau, i64 n, const double *q,
                          const double *u, const tree_model_t *t, const report_t *r, arena_t *a) {
    double *applied = r->explicit_torque;
    for (i64 k = 0; k < t->na; k++) r->damper[k] = 0.0;
    if (torque_mode == TORQUE_AS_GIVEN || torque_mode == TORQUE_REPLAY) {
        for (i64 k = 0; k < t->na; k++) {
            applied[k] = tau[k];
            if (torque_mode == TORQUE_REPLAY) r->damper[k] = tau[t->na + k];
            if (!isfinite(applied[k]) || !isfinite(r->damper[k])) return 0;
        }
        return 1; /* (applied torques: a replay's are lagged already) */
    }
    double *qd = arena_f(a, t->na);
    for (i64 k = 0; k < t->na; k++) qd[k] = u[t->joint_v[k]];
    impedance_command_t c; /* (the views are read only) */
    if (torque_mode == TORQUE_IMPEDANCE) {
        impedance_command_views((double *)tau, t->na, &c);
        double *qj = arena_f(a, t->na), *law = arena_f(a, t->na);
        for (i64 k = 0; k < t->na; k++) qj[k] = q[t->joint_q[k]];
        impedance_torque(&c, qj, qd, law, t->na);
        tau = law;
        n = t->na;
    }
    if (!saturate_torque(tau, t->effort_limit, qd, t->velocity_limit, applied, n)) return 0;
    if (torque_mode == TORQUE_IMPEDANCE)
        for (i64 k = 0; k < t->na; k++)
            if (!isnan(c.velocity[k]) && c.kd[k] > 0.0 && applied[k] == tau[k])
                r->damper[k] = c.kd[k];
    lag_torques(t, r);
    return 1;
}

/* damped: M~ = M + Δt K_d (K_d: the dampers on the actuated joints' diagonal entries) into
 * Md, from M; with the drive models M~ = M + I_a + Δt (K_d + D) (the armature I_a and the
 * viscous friction D on the same entries: D as implicit as the dampers); 0 if no joint has
 * an implicit damper and the drives are off (Md then unused) */
static int damped(const double *M, const tree_model_t *t, const double *damper, i64 nv,
                  double *Md) {
    int any = (int)t->drives;
    for (i64 k = 0; k < t->na; k++) any |= damper[k] > 0.0;
    if (!any) return 0;
    for (i64 k = 0; k < nv * nv; k++) Md[k] = M[k];
    for (i64 k = 0; k < t->na; k++) {
        i64 j = t->joint_v[k];
        if (t->drives)
            Md[j * nv + j] += t->armature[k] + t->s.dt * (damper[k] + t->viscous[k]);
        else
            Md[j * nv + j] += t->s.dt * damper[k];
    }
    return 1;
}

/* implicit_torques: the applied torques after the step: τ = τ_explicit − kd (q̇^E − q̇^S) on
 * the implicitly damped joints (the law at q̇^E), τ_explicit on the others. With check (an
 * impedance command): a damped joint whose τ would be saturated at q̇^E loses its damper
 * (and keeps its explicit torque, the law at u^S, unsaturated there); 1 if one did. */
static int implicit_torques(const tree_model_t *t, const double *uS, const double *uE,
                            const report_t *r, int check) {
    int dropped = 0;
    for (i64 k = 0; k < t->na; k++) {
        i64 j = t->joint_v[k];
        double tk = r->explicit_torque[k];
        if (r->damper[k] > 0.0) {
            tk -= r->damper[k] * (uE[j] - uS[j]);
            double lim = t->effort_limit[k], v = t->velocity_limit[k], w = fabs(uE[j]);
            if (check && (fabs(tk) > lim || (w > v && tk * uE[j] > 0.0))) {
                r->damper[k] = 0.0;
                tk = r->explicit_torque[k];
                dropped = 1;
            }
        }
        r->applied_torque[k] = tk;
    }
    return dropped;
}

/* The joint friction rows of a tree step (Coulomb friction, set-valued): W_f^T, a unit row
 * at the entry of u of each joint with τ_c > 0 (ξ_f = q̇_j^E), b_f = 0 and the bounds τ_c Δt
 * (|Λ_f| ≤ τ_c Δt: prox.c's prox_row); n = 0: none */
typedef struct {
    i64 n;
    double *Wt, *b, *bound;
} friction_t;

i64 joint_friction_count(const tree_model_t *t) {
    i64 n = 0;
    if (t->drives)
        for (i64 k = 0; k < t->na; k++) n += t->friction_bound[k] > 0.0;
    return n;
}

static friction_t friction_rows(const tree_model_t *t, i64 nv, arena_t *a) {
    friction_t f = {joint_friction_count(t), NULL, NULL, NULL};
    if (!f.n) return f;
    f.Wt = arena_zeros(a, f.n * nv);
    f.b = arena_zeros(a, f.n);
    f.bound = arena_f(a, f.n);
    for (i64 k = 0, r = 0; k < t->na; k++)
        if (t->friction_bound[k] > 0.0) {
            f.Wt[r * nv + t->joint_v[k]] = 1.0;
            f.bound[r++] = t->friction_bound[k];
        }
    return f;
}

/* compliant_friction: the compliant step's joint friction (its contacts are forces in h):
 * the friction rows' own problem with M (its factor in L), their prox from Λ_f^0 = 0, u^E
 * into x->uE; a TREE_STEP_* outcome, the prox's iterations and status into res */
static i64 compliant_friction(const tree_model_t *t, const step_arrays_t *x, const double *M,
                              const friction_t *f, tree_step_result_t *res, arena_t *a) {
    i64 nc = t->contacts.nc, nv = x->nv;
    double *never = arena_f(a, nc), *no_impulse = arena_zeros(a, 3 * nc);
    u8 *no_active = arena_alloc(a, (size_t)nc);
    for (i64 i = 0; i < nc; i++) {
        never[i] = INFINITY; /* (no contact row) */
        no_active[i] = 0;
    }
    problem_t p;
    contact_problem(&t->s, M, x->u, nv, never, nc, t->Wt_all, f->Wt, f->n, f->b, t->eps, NULL,
                    t->dof_parent, 0, t->L, no_impulse, no_active, NULL, NULL, a, &p);
    p.bound = f->bound;
    p.nf = f->n;
    double *lam = arena_zeros(a, f->n);
    res->status = joint_friction_prox(&t->s, &p, t->u_free, M, lam, x->uE, &res->iterations, a);
    return res->status == STATUS_NONFINITE ? TREE_STEP_NONFINITE_IMPULSE : TREE_STEP_OK;
}

/* report_contacts: g_N and the contact points at q^M into the report buffer */
static void report_contacts(const double *gap, const double *position, const report_t *report,
                            i64 nc) {
    for (i64 i = 0; i < nc; i++) {
        report->gap[i] = gap[i];
        for (i64 k = 0; k < 3; k++) report->position[3 * i + k] = position[3 * i + k];
    }
}

/* tree_midpoint: q^M (Eqn. 6), M and h at (q^M, u^S) without τ and the contact kinematics
 * into the workspace (midpoint_dynamics), unless prepared ahead (STEP_PREPARED) */
static void tree_midpoint(const step_arrays_t *x, const tree_model_t *t, int options,
                          double *timings) {
    if (options & STEP_PREPARED) return;
    double t0 = kclock(timings);
    midpoint_dynamics(x->q, x->u, 0.5 * t->s.dt, &t->tree, &t->frames, &t->inertias, &t->contacts,
                      &t->ground, t->s.jacobian_gap, t->qM, t->M, t->h, t->gap, t->position,
                      t->Wt_all);
    klap(timings, PHASE_M_AND_H, t0);
}

/* with_forces: h + Sᵀτ + f_ext (the midpoint's h, without τ, stays in the workspace); with
 * the drive models also the viscous friction's −D q̇^S (its −D (q̇^E − q̇^S): damped's M~) */
static double *with_forces(const step_arrays_t *x, const double *tau, const tree_model_t *t,
                           double *timings, arena_t *a) {
    double t0 = kclock(timings);
    double *h = arena_f(a, x->nv);
    for (i64 k = 0; k < x->nv; k++) h[k] = t->h[k];
    for (i64 k = 0; k < t->na; k++) h[t->joint_v[k]] += tau[k];
    if (t->drives)
        for (i64 k = 0; k < t->na; k++)
            if (t->viscous[k] > 0.0) h[t->joint_v[k]] -= t->viscous[k] * x->u[t->joint_v[k]];
    for (i64 k = 0; k < x->n_f_ext; k++) h[k] += x->f_ext[k];
    klap(timings, PHASE_M_AND_H, t0);
    return h;
}

static tree_step_result_t result_of(i64 outcome) {
    tree_step_result_t r = {outcome, 0, 0, 0, STATUS_CONVERGED, 0.0, 0, 0, -1};
    return r;
}

/* complete_step: complete_problem (Λ into the report buffer, Λ_B into bilateral_E, which
 * comes in with the last step's Λ_B) and Eqn. (8); the warm-start and α memory are updated
 * only when the step ends finite */
static void complete_step(problem_t *p, const double *h, const double *M, const tree_model_t *t,
                          const step_arrays_t *x, double *bilateral_E, tree_step_result_t *res,
                          double *timings, arena_t *a) {
    i64 nc = t->contacts.nc;
    double *impulse = x->report.impulse;
    for (i64 k = 0; k < x->nb; k++) bilateral_E[k] = x->last_bilateral[k];
    double alpha_E[3];
    complete_result_t c = complete_problem(p, h, M, t, x, bilateral_E, alpha_E, timings, a);
    double t0 = kclock(timings);
    i64 outcome = TREE_STEP_OK;
    if (c.status == STATUS_NONFINITE) {
        outcome = TREE_STEP_NONFINITE_IMPULSE;
    } else if (!end_of_step(t->qM, x->uE, t->u_corr, c.projection_status >= 0, 0.5 * t->s.dt,
                            &t->tree, x->nq, x->qE, a)) {
        outcome = TREE_STEP_NONFINITE_STATE;
    } else {
        remember_contacts(x->is_active, impulse, nc, x->last_active, x->last_impulse);
        for (i64 k = 0; k < x->nb; k++) x->last_bilateral[k] = bilateral_E[k];
        if (x->prox_memory) memcpy(x->prox_memory, alpha_E, sizeof alpha_E);
    }
    klap(timings, PHASE_REST, t0);
    res->outcome = outcome;
    res->iterations = c.iterations;
    res->status = c.status;
    res->residual = c.residual;
    res->retried = c.retried;
    res->projection_iterations = c.projection_iterations;
    res->projection_status = c.projection_status;
}

/* tree_step_start: what a tree step does first, hard or compliant: the model unpacked into
 * t, the timings (STEP_PROFILE; else NULL), then either only the midpoint (STEP_PREPARE:
 * returns 1, *outcome TREE_STEP_OK) or the applied torques (non-finite: returns 1, *outcome
 * TREE_STEP_NONFINITE_TORQUE), the midpoint (or its prepared values: STEP_PREPARED) and *h
 * = h + Sᵀτ + f_ext; returns 0 when the step goes on. */
static int tree_step_start(int options, int torque_mode, const step_arrays_t *x,
                           const packed_model_t *m, tree_model_t *t, double **timings, double **h,
                           i64 *outcome, arena_t *a) {
    unpack_tree_model(m, t);
    *timings = options & STEP_PROFILE ? t->timings : NULL;
    if (options & STEP_PREPARE) {
        tree_midpoint(x, t, 0, *timings);
        *outcome = TREE_STEP_OK;
        return 1;
    }
    if (!applied_torque(torque_mode, x->tau, x->n_tau, x->q, x->u, t, &x->report, a)) {
        *outcome = TREE_STEP_NONFINITE_TORQUE;
        return 1;
    }
    tree_midpoint(x, t, options, *timings);
    *h = with_forces(x, x->report.explicit_torque, t, *timings, a);
    return 0;
}

/* tree_step_hard: the applied torques (of the step's start state), Eqn. (6) and M, h, W at
 * the midpoint, the contact problem (with M~ = M + Δt K_d of the implicit dampers) and its
 * solution, Eqn. (8); a damped joint whose torque at u^E would be saturated loses its damper,
 * and the step is solved once more from the same memory. options (STEP_*): STEP_PREPARE
 * only the midpoint (into the workspace), STEP_PREPARED the rest after it, STEP_PROFILE the
 * phases' times added to the workspace's timings. */
tree_step_result_t tree_step_hard(int options, int torque_mode, const step_arrays_t *x,
                                  const packed_model_t *m, arena_t *a) {
    tree_model_t t;
    double *timings, *h;
    i64 outcome;
    if (tree_step_start(options, torque_mode, x, m, &t, &timings, &h, &outcome, a))
        return result_of(outcome);
    i64 nv = x->nv, nc = t.contacts.nc;
    friction_t f = friction_rows(&t, nv, a);
    double *Md = arena_f(a, nv * nv), *friction_E = arena_f(a, f.n);
    double *kept = arena_f(a, 4 * nc + f.n + 3); /* the warm-start and α memory, for a second
                                                    solve */
    int implicit = damped(t.M, &t, x->report.damper, nv, Md);
    for (i64 k = 0; k < 3 * nc; k++) kept[k] = x->last_impulse[k];
    for (i64 k = 0; k < nc; k++) kept[3 * nc + k] = x->last_active[k];
    for (i64 k = 0; k < f.n; k++) kept[4 * nc + k] = x->last_bilateral[k];
    for (i64 k = 0; k < 3; k++) kept[4 * nc + f.n + k] = x->prox_memory[k];
    problem_t p;
    tree_step_result_t res;
    for (int pass = 0; pass < 2; pass++) {
        /* (the joint friction rows, if any, in the place of the bilateral rows: Λ_f's memory
         * is last_bilateral) */
        contact_problem(&t.s, implicit ? Md : t.M, x->u, nv, t.gap, nc, t.Wt_all, f.Wt, f.n, f.b,
                        t.eps, t.ground.frames, t.dof_parent, 1, t.L, x->last_impulse,
                        x->last_active, x->prox_memory, timings, a, &p);
        if (!p.ok) return result_of(TREE_STEP_NOT_PD);
        p.bound = f.bound;
        p.nf = f.n;
        res = result_of(TREE_STEP_OK);
        complete_step(&p, h, implicit ? Md : t.M, &t, x, friction_E, &res, timings, a);
        if (!implicit || res.outcome != TREE_STEP_OK ||
            !implicit_torques(&t, x->u, x->uE, &x->report,
                              pass == 0 && torque_mode == TORQUE_IMPEDANCE))
            break;
        for (i64 k = 0; k < 3 * nc; k++) x->last_impulse[k] = kept[k];
        for (i64 k = 0; k < nc; k++) x->last_active[k] = kept[3 * nc + k] != 0.0;
        for (i64 k = 0; k < f.n; k++) x->last_bilateral[k] = kept[4 * nc + k];
        for (i64 k = 0; k < 3; k++) x->prox_memory[k] = kept[4 * nc + f.n + k];
        implicit = damped(t.M, &t, x->report.damper, nv, Md);
    }
    if (!implicit) implicit_torques(&t, x->u, x->uE, &x->report, 0);
    report_contacts(t.gap, t.position, &x->report, nc);
    res.n_active = p.na;
    res.opened = p.opened;
    return res;
}

/* keep_contacts: a copy of the compliant contact state (flags, then anchors and Λ) */
static void keep_contacts(const compliant_state_t *cs, i64 nc, u8 **kept_flags, double **kept,
                          arena_t *a) {
    *kept_flags = arena_alloc(a, (size_t)(2 * nc));
    *kept = arena_f(a, 6 * nc);
    for (i64 i = 0; i < nc; i++) {
        (*kept_flags)[i] = cs->closed[i];
        (*kept_flags)[nc + i] = cs->slip[i];
        for (i64 k = 0; k < 3; k++) {
            (*kept)[3 * i + k] = cs->anchor[3 * i + k];
            (*kept)[3 * nc + 3 * i + k] = cs->lam[3 * i + k];
        }
    }
}

/* restore_contacts: the compliant contact state back to what keep_contacts kept */
static void restore_contacts(const u8 *kept_flags, const double *kept, i64 nc,
                             const compliant_state_t *cs) {
    for (i64 i = 0; i < nc; i++) {
        cs->closed[i] = kept_flags[i] != 0;
        cs->slip[i] = kept_flags[nc + i] != 0;
        for (i64 k = 0; k < 3; k++) {
            cs->anchor[3 * i + k] = kept[3 * i + k];
            cs->lam[3 * i + k] = kept[3 * nc + 3 * i + k];
        }
    }
}

/* report_compliant: the report's Λ (the compliant force Δt) and the closed flags
 * (g_N(q^M) ≤ 0) into is_active; the number closed */
static i64 report_compliant(const step_arrays_t *x, const tree_model_t *t,
                            const compliant_state_t *cs) {
    i64 n_active = 0, nc = t->contacts.nc;
    for (i64 i = 0; i < nc; i++) {
        for (i64 k = 0; k < 3; k++) x->report.impulse[3 * i + k] = cs->lam[3 * i + k] * t->s.dt;
        x->is_active[i] = t->gap[i] <= 0.0;
        n_active += x->is_active[i];
    }
    report_contacts(t->gap, t->position, &x->report, nc);
    return n_active;
}

/* tree_step_compliant: the applied torques, the midpoint, solve_compliant (u^E = u_free,
 * with M~ = M + Δt K_d and the second solve of tree_step_hard) and Eqn. (8); the report's
 * Λ is the compliant force Δt, is_active the closed flags (g_N(q^M) ≤ 0). A failed step
 * leaves the contact state as it was. options: as tree_step_hard's. */
tree_step_result_t tree_step_compliant(int options, int torque_mode, const step_arrays_t *x,
                                       const compliant_state_t *cs, const packed_model_t *m,
                                       arena_t *a) {
    tree_model_t t;
    double *timings, *h;
    i64 outcome;
    if (tree_step_start(options, torque_mode, x, m, &t, &timings, &h, &outcome, a))
        return result_of(outcome);
    i64 nv = x->nv, nc = t.contacts.nc;
    double dt = t.s.dt;
    friction_t f = friction_rows(&t, nv, a);
    tree_step_result_t solved = result_of(TREE_STEP_OK);
    double *h0 = arena_f(a, nv), *Md = arena_f(a, nv * nv);
    int implicit = damped(t.M, &t, x->report.damper, nv, Md);
    for (i64 k = 0; k < nv; k++) h0[k] = h[k]; /* (solve_compliant adds the contacts) */
    u8 *kept_flags;
    double *kept;
    keep_contacts(cs, nc, &kept_flags, &kept, a);
    outcome = TREE_STEP_NOT_PD;
    for (int pass = 0; pass < 2; pass++) {
        if (!solve_compliant(&t.law, implicit ? Md : t.M, h, x->u, nv, dt, nc, t.gap, t.position,
                             t.Wt_all, cs->closed, cs->slip, cs->anchor, t.ground.frames, cs->lam,
                             t.dof_parent, 1, t.L, t.u_free, timings)) {
            outcome = TREE_STEP_NOT_PD;
            break;
        }
        for (i64 k = 0; k < nv; k++) x->uE[k] = t.u_free[k];
        outcome =
            f.n ? compliant_friction(&t, x, implicit ? Md : t.M, &f, &solved, a) : TREE_STEP_OK;
        if (outcome != TREE_STEP_OK) break;
        if (!implicit || !implicit_torques(&t, x->u, x->uE, &x->report,
                                           pass == 0 && torque_mode == TORQUE_IMPEDANCE))
            break;
        restore_contacts(kept_flags, kept, nc, cs);
        for (i64 k = 0; k < nv; k++) h[k] = h0[k];
        implicit = damped(t.M, &t, x->report.damper, nv, Md);
    }
    double t0 = kclock(timings);
    if (outcome == TREE_STEP_OK) {
        if (!implicit) implicit_torques(&t, x->u, x->uE, &x->report, 0);
        if (!end_of_step(t.qM, x->uE, t.u_corr, 0, 0.5 * dt, &t.tree, x->nq, x->qE, a))
            outcome = TREE_STEP_NONFINITE_STATE;
    }
    if (outcome != TREE_STEP_OK) /* the contact state back to what it was */
        restore_contacts(kept_flags, kept, nc, cs);
    tree_step_result_t res = result_of(outcome);
    res.iterations = solved.iterations;
    res.status = solved.status;
    res.n_active = report_compliant(x, &t, cs);
    klap(timings, PHASE_REST, t0);
    return res;
}

/* forest_midpoint: q^M, M and h (without τ) and the contact kinematics at q^M into the
 * workspace (a constant M: q^M, rigid_body_forces and contact_kinematics), then the
 * bilateral constraints of the cut joints at q^M (W_B^T, g_B, b_B = (β/Δt) g_B); nothing
 * when prepared ahead. Returns M. */
static const double *forest_midpoint(const step_arrays_t *x, const tree_model_t *t,
                                     const cut_model_t *c, int options, double *timings,
                                     arena_t *a) {
    const double *M = c->constant ? c->M : t->M;
    if (options & STEP_PREPARED) return M;
    double half_dt = 0.5 * t->s.dt, t0 = kclock(timings);
    if (c->constant) {
        integrate_forest(x->q, x->u, half_dt, &t->tree, t->qM);
        rigid_body_forces(t->qM, x->u, c->nr, c->root_q, c->root_v, c->body_mass, c->body_inertia,
                          c->body_gravity, t->h);
        contact_kinematics(t->qM, &t->tree, &t->frames, &t->contacts, &t->ground, t->s.jacobian_gap,
                           t->gap, t->position, t->Wt_all);
    } else {
        midpoint_dynamics(x->q, x->u, half_dt, &t->tree, &t->frames, &t->inertias, &t->contacts,
                          &t->ground, t->s.jacobian_gap, t->qM, t->M, t->h, t->gap, t->position,
                          t->Wt_all);
    }
    t0 = klap(timings, PHASE_M_AND_H, t0);
    double *u_zero = arena_zeros(a, x->nv); /* (the rates at q^M are not needed: u = 0) */
    cut_joints(t->qM, u_zero, &t->tree, &t->frames, &c->cuts, c->WtB, c->gB, c->angle, c->rate,
               c->axis_world, 1, a);
    for (i64 k = 0; k < 5 * c->cuts.ncut; k++) c->bB[k] = c->gB[k] * c->beta_over_dt;
    klap(timings, PHASE_REST, t0);
    return M;
}

/* forest_forces: h + Sᵀτ inside the trees, the cut joints' body torques (cut_joint_torques
 * with the kinematics of the midpoint's cut_joints call), + f_ext */
static double *forest_forces(const double *applied, const tree_model_t *t, const cut_model_t *c,
                             const step_arrays_t *x, double *timings, arena_t *a) {
    double t0 = kclock(timings);
    double *h = arena_f(a, x->nv);
    for (i64 k = 0; k < x->nv; k++) h[k] = t->h[k];
    double *tau_cut = arena_zeros(a, c->cuts.ncut);
    for (i64 k = 0; k < t->na; k++) {
        if (c->joint_cut[k] < 0)
            h[t->joint_v[k]] += applied[k];
        else
            tau_cut[c->joint_cut[k]] = applied[k];
    }
    cut_joint_torques(tau_cut, &c->cuts, c->axis_world, &t->tree, t->frames.oR, h, a);
    for (i64 k = 0; k < x->n_f_ext; k++) h[k] += x->f_ext[k];
    klap(timings, PHASE_M_AND_H, t0);
    return h;
}

/* forest_compliant: Alg. 1 in a cut forest: the compliant forces at (q^M, u^S) join h, then
 * u^E by the prox solve of the bilateral constraints alone (no contact row: the gaps seen by
 * the active set are +inf, the warm-start memory the caller's scratch, which stays zero) and
 * Eqn. (8); a failed step leaves the contact state as it was */
static tree_step_result_t forest_compliant(int options, const step_arrays_t *x,
                                           const compliant_state_t *cs, const double *M, double *h,
                                           const tree_model_t *t, const cut_model_t *c,
                                           double *timings, arena_t *a) {
    i64 nv = x->nv, nc = t->contacts.nc;
    u8 *kept_flags;
    double *kept;
    keep_contacts(cs, nc, &kept_flags, &kept, a);
    double t0 = kclock(timings);
    compliant_contact_forces(&t->law, nc, nv, t->gap, t->position, t->Wt_all, x->u, cs->closed,
                             cs->slip, cs->anchor, t->ground.frames, cs->lam);
    generalized_contact_force(t->Wt_all, cs->lam, nc, nv, h);
    klap(timings, PHASE_REST, t0);
    double *never = arena_f(a, nc);
    for (i64 i = 0; i < nc; i++) never[i] = INFINITY;
    problem_t p;
    contact_problem(&t->s, M, x->u, nv, never, nc, t->Wt_all, c->WtB, 5 * c->cuts.ncut, c->bB,
                    t->eps, t->ground.frames, t->dof_parent, !(options & STEP_KEEP_FACTOR), t->L,
                    x->last_impulse, x->last_active, x->prox_memory, timings, a, &p);
    tree_step_result_t res = result_of(p.ok ? TREE_STEP_OK : TREE_STEP_NOT_PD);
    if (p.ok) complete_step(&p, h, M, t, x, c->bilateral_E, &res, timings, a);
    if (res.outcome != TREE_STEP_OK) restore_contacts(kept_flags, kept, nc, cs);
    res.n_active = report_compliant(x, t, cs);
    return res;
}

/* forest_step: the step of a cut forest (the extended and maximal coordinates): the
 * midpoint, the bilateral constraints of the cut joints at q^M, the joint torques (applied
 * as given: saturated by the caller, a cut joint's rate needing the cut-joint kinematics of
 * the state; its dampers stay explicit) and f_ext, then with hard contacts the contact and
 * bilateral problem and Eqn. (8), with STEP_COMPLIANT forest_compliant. STEP_KEEP_FACTOR:
 * reuse a constant M's factor in L. A successful step also writes the cut joints' φ and φ̇
 * at (q^E, u^E) into angle_E and rate_E. options otherwise as tree_step_hard's. */
tree_step_result_t forest_step(int options, const step_arrays_t *x, const compliant_state_t *cs,
                               double *angle_E, double *rate_E, const packed_model_t *m,
                               const packed_model_t *cm, arena_t *a) {
    tree_model_t t;
    unpack_tree_model(m, &t);
    cut_model_t c;
    unpack_cut_model(cm, t.na, x->nv, &c);
    double *timings = options & STEP_PROFILE ? t.timings : NULL;
    if (options & STEP_PREPARE) {
        forest_midpoint(x, &t, &c, 0, timings, a);
        return result_of(TREE_STEP_OK);
    }
    i64 nv = x->nv, nc = t.contacts.nc, na = t.na;
    double *applied = x->report.applied_torque;
    for (i64 k = 0; k < na; k++) {
        if (!isfinite(x->tau[k])) return result_of(TREE_STEP_NONFINITE_TORQUE);
        applied[k] = x->report.explicit_torque[k] = x->tau[k];
        x->report.damper[k] = 0.0;
    }
    const double *M = forest_midpoint(x, &t, &c, options, timings, a);
    double *h = forest_forces(applied, &t, &c, x, timings, a);
    tree_step_result_t res;
    if (options & STEP_COMPLIANT) {
        res = forest_compliant(options, x, cs, M, h, &t, &c, timings, a);
    } else {
        problem_t p;
        contact_problem(&t.s, M, x->u, nv, t.gap, nc, t.Wt_all, c.WtB, 5 * c.cuts.ncut, c.bB, t.eps,
                        t.ground.frames, t.dof_parent, !(options & STEP_KEEP_FACTOR), t.L,
                        x->last_impulse, x->last_active, x->prox_memory, timings, a, &p);
        if (!p.ok) return result_of(TREE_STEP_NOT_PD);
        res = result_of(TREE_STEP_OK);
        complete_step(&p, h, M, &t, x, c.bilateral_E, &res, timings, a);
        report_contacts(t.gap, t.position, &x->report, nc);
        res.n_active = p.na;
        res.opened = p.opened;
    }
    if (res.outcome == TREE_STEP_OK)
        cut_joint_motion(x->qE, x->uE, &t.tree, &t.frames, &c.cuts, angle_E, rate_E, a);
    return res;
}
