/* One whole physics step in one call (tree_step.py): tree_step_hard / tree_step_compliant
 * for the minimal coordinates, forest_step_hard for a cut forest (the extended and maximal
 * coordinates). The same phases, in the same order, as the phase-by-phase path (so the same
 * result bit for bit); a failing step leaves the state as it was. The model travels in the
 * packed buffers of tree_step.TreeStepModel and CutModel, unpacked by the code that the build
 * generates from their declaration (kernel_layouts.py: tree_model_t, unpack_tree_model, ...). */
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
void impedance_torque(const impedance_command_t *c, const double *q, const double *qd,
                      double *tau, i64 n) {
    for (i64 k = 0; k < n; k++) {
        double t = isnan(c->effort[k]) ? 0.0 : c->effort[k];
        if (!isnan(c->position[k])) t += c->kp[k] * (c->position[k] - q[k]);
        if (!isnan(c->velocity[k])) t += c->kd[k] * (c->velocity[k] - qd[k]);
        tau[k] = t;
    }
}

/* _applied_torque: the torques the motors apply for tau (torque_mode TORQUE_*: as given,
 * saturate_torque at the joint rates of u, the impedance law of the command tau at (q, u)
 * saturated, or a replay) into the report's explicit_torque, and the kd of the implicit
 * dampers into its damper: with an impedance command, the joints with a damper term whose
 * law at (q^S, u^S) is not saturated; 0 if the torques have a non-finite entry */
static int applied_torque(int torque_mode, const double *tau, i64 n, const double *q,
                          const double *u, const tree_model_t *t, const report_t *r,
                          arena_t *a) {
    double *applied = r->explicit_torque;
    for (i64 k = 0; k < t->na; k++) r->damper[k] = 0.0;
    if (torque_mode == TORQUE_AS_GIVEN || torque_mode == TORQUE_REPLAY) {
        for (i64 k = 0; k < t->na; k++) {
            applied[k] = tau[k];
            if (torque_mode == TORQUE_REPLAY) r->damper[k] = tau[t->na + k];
            if (!isfinite(applied[k]) || !isfinite(r->damper[k])) return 0;
        }
        return 1;
    }
    double *qd = arena_f(a, t->na);
    for (i64 k = 0; k < t->na; k++) qd[k] = u[t->joint_v[k]];
    impedance_command_t c;  /* (the views are read only) */
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
    return 1;
}

/* _damped: M~ = M + Δt K_d (K_d: the dampers on the actuated joints' diagonal entries) into
 * Md, from M; 0 if no joint has an implicit damper (Md then unused) */
static int damped(const double *M, const tree_model_t *t, const double *damper, i64 nv,
                  double *Md) {
    int any = 0;
    for (i64 k = 0; k < t->na; k++) any |= damper[k] > 0.0;
    if (!any) return 0;
    for (i64 k = 0; k < nv * nv; k++) Md[k] = M[k];
    for (i64 k = 0; k < t->na; k++) {
        i64 j = t->joint_v[k];
        Md[j * nv + j] += t->s.dt * damper[k];
    }
    return 1;
}

/* _implicit_torques: the applied torques after the step: τ = τ_explicit − kd (q̇^E − q̇^S) on
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

/* _report_contacts: g_N and the contact points at q^M into the report buffer */
static void report_contacts(const double *gap, const double *position, const report_t *report,
                            i64 nc) {
    for (i64 i = 0; i < nc; i++) {
        report->gap[i] = gap[i];
        for (i64 k = 0; k < 3; k++) report->position[3 * i + k] = position[3 * i + k];
    }
}

/* _midpoint_with_forces: q^M, M and h at (q^M, u^S) (midpoint_dynamics), then h += Sᵀτ and
 * f_ext */
static void midpoint_with_forces(const step_arrays_t *x, double half_dt, const double *tau,
                                 const tree_model_t *t, double *qM, double *M, double *h) {
    midpoint_dynamics(x->q, x->u, half_dt, &t->tree, &t->frames, &t->inertias, &t->contacts,
                      &t->ground, t->s.jacobian_gap, qM, M, h, t->gap, t->position, t->Wt_all);
    for (i64 k = 0; k < t->na; k++) h[t->joint_v[k]] += tau[k];
    for (i64 k = 0; k < x->n_f_ext; k++) h[k] += x->f_ext[k];
}

static tree_step_result_t result_of(i64 outcome) {
    tree_step_result_t r = {outcome, 0, 0, 0, STATUS_CONVERGED, 0.0, 0, 0, -1};
    return r;
}

/* _complete_step: complete_problem (Λ into the report buffer, Λ_B into bilateral_E, which
 * comes in with the last step's Λ_B) and Eqn. (8); the warm-start memory is updated only
 * when the step ends finite */
static void complete_step(const settings_t *s, const problem_t *p, const double *h,
                          const double *M, const tree_model_t *t, const step_arrays_t *x,
                          double *bilateral_E, const double *qM, double half_dt,
                          tree_step_result_t *res, arena_t *a) {
    i64 nc = t->contacts.nc;
    double *impulse = x->report.impulse;
    for (i64 k = 0; k < x->nb; k++) bilateral_E[k] = x->last_bilateral[k];
    complete_result_t c = complete_problem(s, p, h, x->u, M, t->dof_parent, t->L, t->gap, nc,
                                           t->Wt_all, x->last_impulse, x->last_active,
                                           bilateral_E, x->nb, impulse, x->is_active, t->u_free,
                                           x->uE, t->u_corr, 0, NULL, a);
    i64 outcome = TREE_STEP_OK;
    if (c.status == STATUS_NONFINITE) {
        outcome = TREE_STEP_NONFINITE_IMPULSE;
    } else if (!end_of_step(qM, x->uE, t->u_corr, c.projection_status >= 0, half_dt, &t->tree,
                            x->nq, x->qE, a)) {
        outcome = TREE_STEP_NONFINITE_STATE;
    } else {
        remember_contacts(x->is_active, impulse, nc, x->last_active, x->last_impulse);
        for (i64 k = 0; k < x->nb; k++) x->last_bilateral[k] = bilateral_E[k];
    }
    res->outcome = outcome;
    res->iterations = c.iterations;
    res->status = c.status;
    res->residual = c.residual;
    res->retried = c.retried;
    res->projection_iterations = c.projection_iterations;
    res->projection_status = c.projection_status;
}

/* tree_step_hard: the applied torques (of the step's start state), Eqn. (6) and M, h, W at
 * the midpoint, the contact problem (with M~ = M + Δt K_d of the implicit dampers) and its
 * solution, Eqn. (8); a damped joint whose torque at u^E would be saturated loses its damper,
 * and the step is solved once more from the same memory */
tree_step_result_t tree_step_hard(int torque_mode, const step_arrays_t *x,
                                  const packed_model_t *m, arena_t *a) {
    tree_model_t t;
    unpack_tree_model(m, &t);
    i64 nv = x->nv, nq = x->nq, nc = t.contacts.nc;
    if (!applied_torque(torque_mode, x->tau, x->n_tau, x->q, x->u, &t, &x->report, a))
        return result_of(TREE_STEP_NONFINITE_TORQUE);
    double half_dt = 0.5 * t.s.dt;
    double *out = arena_f(a, nq + 2 * nv * nv + nv + 4 * nc);
    double *qM = out, *M = out + nq, *h = out + nq + nv * nv, *Md = h + nv;
    double *kept = Md + nv * nv;    /* the warm-start memory, for a second solve */
    midpoint_with_forces(x, half_dt, x->report.explicit_torque, &t, qM, M, h);
    int implicit = damped(M, &t, x->report.damper, nv, Md);
    for (i64 k = 0; k < 3 * nc; k++) kept[k] = x->last_impulse[k];
    for (i64 k = 0; k < nc; k++) kept[3 * nc + k] = x->last_active[k];
    problem_t p;
    tree_step_result_t res;
    for (int pass = 0; pass < 2; pass++) {
        contact_problem(&t.s, implicit ? Md : M, x->u, nv, t.gap, nc, t.Wt_all, NULL, 0, NULL,
                        t.eps, t.ground.frames, t.dof_parent, 1, t.L, x->last_impulse,
                        x->last_active, NULL, a, &p);
        if (!p.ok) return result_of(TREE_STEP_NOT_PD);
        res = result_of(TREE_STEP_OK);
        /* (no bilateral rows: Λ_B is empty, last_bilateral its own buffer) */
        complete_step(&t.s, &p, h, implicit ? Md : M, &t, x, x->last_bilateral, qM, half_dt,
                      &res, a);
        if (!implicit || res.outcome != TREE_STEP_OK ||
            !implicit_torques(&t, x->u, x->uE, &x->report, pass == 0 &&
                              torque_mode == TORQUE_IMPEDANCE))
            break;
        for (i64 k = 0; k < 3 * nc; k++) x->last_impulse[k] = kept[k];
        for (i64 k = 0; k < nc; k++) x->last_active[k] = kept[3 * nc + k] != 0.0;
        implicit = damped(M, &t, x->report.damper, nv, Md);
    }
    if (!implicit) implicit_torques(&t, x->u, x->uE, &x->report, 0);
    report_contacts(t.gap, t.position, &x->report, nc);
    res.n_active = p.na;
    res.opened = p.opened;
    return res;
}

/* _restore_contacts: the compliant contact state back to what kept holds */
static void restore_contacts(const u8 *kept_flags, const double *kept, i64 nc, u8 *closed,
                             u8 *slip, double *anchor, double *lam) {
    for (i64 i = 0; i < nc; i++) {
        closed[i] = kept_flags[i] != 0;
        slip[i] = kept_flags[nc + i] != 0;
        for (i64 k = 0; k < 3; k++) {
            anchor[3 * i + k] = kept[3 * i + k];
            lam[3 * i + k] = kept[3 * nc + 3 * i + k];
        }
    }
}

/* tree_step_compliant: the applied torques, the midpoint, solve_compliant (u^E = u_free,
 * with M~ = M + Δt K_d and the second solve of tree_step_hard) and Eqn. (8); the report's
 * Λ is the compliant force Δt, is_active the closed flags (g_N(q^M) ≤ 0). A failed step
 * leaves the contact state as it was. */
tree_step_result_t tree_step_compliant(int torque_mode, const step_arrays_t *x, u8 *closed,
                                       u8 *slip, double *anchor, double *lam,
                                       const packed_model_t *m, arena_t *a) {
    tree_model_t t;
    unpack_tree_model(m, &t);
    i64 nv = x->nv, nq = x->nq, nc = t.contacts.nc;
    double dt = t.s.dt;
    if (!applied_torque(torque_mode, x->tau, x->n_tau, x->q, x->u, &t, &x->report, a))
        return result_of(TREE_STEP_NONFINITE_TORQUE);
    double half_dt = 0.5 * dt;
    double *out = arena_f(a, nq + 2 * nv * nv + 2 * nv);
    double *qM = out, *M = out + nq, *h = out + nq + nv * nv, *h0 = h + nv, *Md = h0 + nv;
    midpoint_with_forces(x, half_dt, x->report.explicit_torque, &t, qM, M, h);
    int implicit = damped(M, &t, x->report.damper, nv, Md);
    for (i64 k = 0; k < nv; k++) h0[k] = h[k];   /* (solve_compliant adds the contacts) */
    /* the contact state kept, for a failed step */
    u8 *kept_flags = arena_alloc(a, (size_t)(2 * nc));
    double *kept = arena_f(a, 6 * nc);
    for (i64 i = 0; i < nc; i++) {
        kept_flags[i] = closed[i];
        kept_flags[nc + i] = slip[i];
        for (i64 k = 0; k < 3; k++) {
            kept[3 * i + k] = anchor[3 * i + k];
            kept[3 * nc + 3 * i + k] = lam[3 * i + k];
        }
    }
    i64 outcome;
    for (int pass = 0; pass < 2; pass++) {
        if (!solve_compliant(&t.law, implicit ? Md : M, h, x->u, nv, dt, nc, t.gap, t.position,
                             t.Wt_all, closed, slip, anchor, t.ground.frames, lam, t.dof_parent,
                             1, t.L, t.u_free, NULL)) {
            outcome = TREE_STEP_NOT_PD;
            break;
        }
        for (i64 k = 0; k < nv; k++) x->uE[k] = t.u_free[k];
        outcome = TREE_STEP_OK;
        if (!implicit || !implicit_torques(&t, x->u, x->uE, &x->report, pass == 0 &&
                                           torque_mode == TORQUE_IMPEDANCE))
            break;
        restore_contacts(kept_flags, kept, nc, closed, slip, anchor, lam);
        for (i64 k = 0; k < nv; k++) h[k] = h0[k];
        implicit = damped(M, &t, x->report.damper, nv, Md);
    }
    if (outcome == TREE_STEP_OK) {
        if (!implicit) implicit_torques(&t, x->u, x->uE, &x->report, 0);
        if (!end_of_step(qM, x->uE, t.u_corr, 0, half_dt, &t.tree, nq, x->qE, a))
            outcome = TREE_STEP_NONFINITE_STATE;
    }
    if (outcome != TREE_STEP_OK) /* the contact state back to what it was */
        restore_contacts(kept_flags, kept, nc, closed, slip, anchor, lam);
    i64 n_active = 0;
    for (i64 i = 0; i < nc; i++) {
        for (i64 k = 0; k < 3; k++) x->report.impulse[3 * i + k] = lam[3 * i + k] * dt;
        x->is_active[i] = t.gap[i] <= 0.0;
        n_active += x->is_active[i];
    }
    report_contacts(t.gap, t.position, &x->report, nc);
    tree_step_result_t res = result_of(outcome);
    res.n_active = n_active;
    return res;
}

/* _forest_midpoint: q^M, M and h (without τ) and the contact kinematics at q^M; for a
 * constant M (free bodies) q^M, rigid_body_forces and contact_kinematics. Returns M. */
static const double *forest_midpoint(const step_arrays_t *x, double half_dt,
                                     const tree_model_t *t, const cut_model_t *c, double *qM,
                                     double *h, double *M_buf) {
    if (c->constant) {
        integrate_forest(x->q, x->u, half_dt, &t->tree, qM);
        rigid_body_forces(qM, x->u, c->nr, c->root_q, c->root_v, c->body_mass, c->body_inertia,
                          c->body_gravity, h);
        contact_kinematics(qM, &t->tree, &t->frames, &t->contacts, &t->ground,
                           t->s.jacobian_gap, t->gap, t->position, t->Wt_all);
        return c->M;
    }
    midpoint_dynamics(x->q, x->u, half_dt, &t->tree, &t->frames, &t->inertias, &t->contacts,
                      &t->ground, t->s.jacobian_gap, qM, M_buf, h, t->gap, t->position,
                      t->Wt_all);
    return M_buf;
}

/* _add_forest_torques: h += Sᵀτ inside the trees, the cut joints' body torques
 * (cut_joint_torques with the kinematics of the last cut_joints call), + f_ext */
static void add_forest_torques(const double *applied, const tree_model_t *t,
                               const cut_model_t *c, const step_arrays_t *x, double *h,
                               arena_t *a) {
    double *tau_cut = arena_zeros(a, c->cuts.ncut);
    for (i64 k = 0; k < t->na; k++) {
        if (c->joint_cut[k] < 0)
            h[t->joint_v[k]] += applied[k];
        else
            tau_cut[c->joint_cut[k]] = applied[k];
    }
    cut_joint_torques(tau_cut, &c->cuts, c->axis_world, &t->tree, t->frames.oR, h, a);
    for (i64 k = 0; k < x->n_f_ext; k++) h[k] += x->f_ext[k];
}

/* forest_step_hard: tree_step_hard for a cut forest: the midpoint, the bilateral constraints
 * of the cut joints at q^M (W_B^T, g_B, b_B = (β/Δt) g_B), the joint torques and f_ext, the
 * contact and bilateral problem and Eqn. (8); a successful step also writes the cut joints'
 * φ and φ̇ at (q^E, u^E) into angle_E and rate_E */
tree_step_result_t forest_step_hard(const step_arrays_t *x, int factor, double *angle_E,
                                    double *rate_E, const packed_model_t *m,
                                    const packed_model_t *cm, arena_t *a) {
    tree_model_t t;
    unpack_tree_model(m, &t);
    cut_model_t c;
    unpack_cut_model(cm, t.na, x->nv, &c);
    i64 nv = x->nv, nq = x->nq, nc = t.contacts.nc, na = t.na;
    double *applied = x->report.applied_torque;
    for (i64 k = 0; k < na; k++) {  /* (a cut forest's dampers stay explicit) */
        if (!isfinite(x->tau[k])) return result_of(TREE_STEP_NONFINITE_TORQUE);
        applied[k] = x->report.explicit_torque[k] = x->tau[k];
        x->report.damper[k] = 0.0;
    }
    double half_dt = 0.5 * t.s.dt;
    i64 nM = c.constant ? 0 : nv * nv;
    double *out = arena_f(a, nq + nv + nM);
    double *qM = out, *h = out + nq;
    const double *M = forest_midpoint(x, half_dt, &t, &c, qM, h, out + nq + nv);
    double *u_zero = arena_zeros(a, nv); /* (the rates at q^M are not needed: u = 0) */
    cut_joints(qM, u_zero, &t.tree, &t.frames, &c.cuts, c.WtB, c.gB, c.angle, c.rate,
               c.axis_world, 1, a);
    i64 nB = 5 * c.cuts.ncut;
    for (i64 k = 0; k < nB; k++) c.bB[k] = c.gB[k] * c.beta_over_dt;
    add_forest_torques(applied, &t, &c, x, h, a);
    problem_t p;
    contact_problem(&t.s, M, x->u, nv, t.gap, nc, t.Wt_all, c.WtB, nB, c.bB, t.eps,
                    t.ground.frames, t.dof_parent, factor, t.L, x->last_impulse, x->last_active, NULL, a, &p);
    if (!p.ok) return result_of(TREE_STEP_NOT_PD);
    tree_step_result_t res = result_of(TREE_STEP_OK);
    complete_step(&t.s, &p, h, M, &t, x, c.bilateral_E, qM, half_dt, &res, a);
    if (res.outcome == TREE_STEP_OK)
        cut_joint_motion(x->qE, x->uE, &t.tree, &t.frames, &c.cuts, angle_E, rate_E, a);
    report_contacts(t.gap, t.position, &x->report, nc);
    res.n_active = p.na;
    res.opened = p.opened;
    return res;
}
