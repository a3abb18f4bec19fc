/* One whole physics step in one call (tree_step.py): tree_step_hard / tree_step_compliant
 * for the minimal coordinates, forest_step_hard for a cut forest (the extended and maximal
 * coordinates). The same phases, in the same order, as the phase-by-phase path (so the same
 * result bit for bit); a failing step leaves the state as it was. The model travels in the
 * packed buffers of tree_step.TreeStepModel and CutModel (layout in their docstrings). */
#include "step.h"

#include <string.h>

#define N_SETTINGS 19

/* The views of a TreeStepModel's buffers (tree_step.unpack_tree_model) */
typedef struct {
    settings_t s;
    compliant_law_t law;
    tree_t tree;
    frames_t frames;
    inertias_t inertias;
    contact_points_t contacts;
    ground_t ground;
    const double *eps, *effort_limit, *velocity_limit; /* nc x 2, na, na */
    i64 na;
    const i64 *joint_v, *dof_parent;
    double *gap, *position, *Wt_all, *L, *u_free, *u_corr;
} tree_model_t;

/* The views of a CutModel's buffers (tree_step.unpack_cut_model) */
typedef struct {
    double beta_over_dt;
    cuts_t cuts;
    const i64 *joint_cut; /* na */
    int constant;
    const double *M; /* nv x nv when constant */
    i64 nr;
    const i64 *root_q, *root_v;
    const double *body_mass, *body_inertia, *body_gravity;
    double *WtB, *gB, *bB, *angle, *rate, *axis_world, *bilateral_E;
} cut_model_t;


/* A cursor over a packed buffer of `len` entries: at(c, n) is the offset of its next n
 * entries; a request past the end marks it bad (and gives offset 0, so that no pointer
 * leaves the buffer). One layout serves the unpacking and the check of the lengths. */
typedef struct {
    i64 o, len;
    int bad;
} cursor_t;

static i64 at(cursor_t *c, i64 n) {
    if (n < 0 || c->o + n > c->len) {
        c->bad = 1;
        return 0;
    }
    i64 start = c->o;
    c->o += n;
    return start;
}

/* unpack_tree_model: the views of a TreeStepModel's buffers; 0 if the buffers' lengths are
 * not the layout's for the sizes in ints[0:4] = (nj, nc, na, nv) (checked by
 * check_tree_model first: then nothing is read out of bounds) */
static int unpack_tree_model(const packed_model_t *pm, tree_model_t *t) {
    const i64 *ints = pm->ints;
    i64 nj = ints[0], nc = ints[1], na = ints[2], nv = ints[3];
    double *f = pm->floats;
    cursor_t cf = {0, pm->n_floats, 0}, ci = {4, pm->n_ints, 0};
    cursor_t cw = {0, pm->n_workspace, 0};
    i64 settings = at(&cf, N_SETTINGS), law = at(&cf, 6);
    t->tree.nj = nj;
    t->tree.nv = nv;
    t->tree.axis = f + at(&cf, 3 * nj);
    t->tree.pl_R = f + at(&cf, 9 * nj);
    t->tree.pl_p = f + at(&cf, 3 * nj);
    t->frames.oR = f + at(&cf, 9 * nj); /* (the forward kinematics' scratch) */
    t->frames.op = f + at(&cf, 3 * nj);
    t->inertias.mass = f + at(&cf, nj);
    t->inertias.lever = f + at(&cf, 3 * nj);
    t->inertias.inertia = f + at(&cf, 9 * nj);
    t->inertias.gravity = f + at(&cf, 3);
    t->contacts.nc = nc;
    t->contacts.local = f + at(&cf, 3 * nc);
    t->contacts.radius = f + at(&cf, nc);
    t->ground.n = f + at(&cf, 3);
    t->ground.t1 = f + at(&cf, 3);
    t->ground.t2 = f + at(&cf, 3);
    i64 offset = at(&cf, 1);
    t->eps = f + at(&cf, 2 * nc);
    t->effort_limit = f + at(&cf, na);
    t->velocity_limit = f + at(&cf, na);
    t->tree.parent = ints + at(&ci, nj);
    t->tree.jtype = ints + at(&ci, nj);
    t->tree.idx_q = ints + at(&ci, nj);
    t->tree.idx_v = ints + at(&ci, nj);
    t->contacts.joint = ints + at(&ci, nc);
    t->na = na;
    t->joint_v = ints + at(&ci, na);
    t->dof_parent = ints + at(&ci, nv);
    t->tree.support = pm->support;
    double *w = pm->workspace;
    t->gap = w + at(&cw, nc);
    t->position = w + at(&cw, 3 * nc);
    t->Wt_all = w + at(&cw, 3 * nc * nv);
    t->L = w + at(&cw, nv * nv);
    t->u_free = w + at(&cw, nv);
    t->u_corr = w + at(&cw, nv);
    if (cf.bad || ci.bad || cw.bad || cf.o != cf.len || ci.o != ci.len ||
        pm->n_support != nj * nj)
        return 0;
    settings_from_fields(f + settings, &t->s);
    const double *l = f + law;
    t->law.mu = l[0];
    t->law.c_N = l[1];
    t->law.d_N = l[2];
    t->law.c_T = l[3];
    t->law.d_T = l[4];
    t->law.slip_velocity = l[5];
    t->ground.offset = f[offset];
    return 1;
}

const char *check_tree_model(const packed_model_t *m, i64 nv) {
    if (m->n_ints < 4) return "TreeStepModel: ints too short";
    const i64 *ints = m->ints;
    if (ints[0] < 1 || ints[1] < 0 || ints[2] < 0 || ints[3] != nv)
        return "TreeStepModel: sizes (nj, nc, na, nv) do not match the state";
    tree_model_t t;
    if (!unpack_tree_model(m, &t)) return "TreeStepModel: buffer lengths do not match its sizes";
    return NULL;
}

/* unpack_cut_model: the views of a CutModel's buffers; 0 if their lengths are not the
 * layout's for its sizes ints[0:3] = (ncut, constant, nr) (check_cut_model) */
static int unpack_cut_model(const packed_model_t *pm, i64 na, i64 nv, cut_model_t *c) {
    const i64 *ints = pm->ints;
    i64 ncut = ints[0], nr = ints[2];
    c->constant = ints[1] != 0;
    c->nr = nr;
    const double *f = pm->floats;
    cursor_t cf = {0, pm->n_floats, 0}, ci = {3, pm->n_ints, 0};
    cursor_t cw = {0, pm->n_workspace, 0};
    i64 beta = at(&cf, 1);
    c->cuts.ncut = ncut;
    c->cuts.p_P = f + at(&cf, 3 * ncut);
    c->cuts.p_C = f + at(&cf, 3 * ncut);
    c->cuts.a_P = f + at(&cf, 3 * ncut);
    c->cuts.b1_P = f + at(&cf, 3 * ncut);
    c->cuts.b2_P = f + at(&cf, 3 * ncut);
    c->cuts.a_C = f + at(&cf, 3 * ncut);
    c->cuts.b1_C = f + at(&cf, 3 * ncut);
    c->M = f + at(&cf, c->constant ? nv * nv : 0);
    c->body_mass = f + at(&cf, nr);
    c->body_inertia = f + at(&cf, 9 * nr);
    c->body_gravity = f + at(&cf, c->constant ? 3 : 0);
    c->cuts.P = ints + at(&ci, ncut);
    c->cuts.C = ints + at(&ci, ncut);
    c->joint_cut = ints + at(&ci, na);
    c->root_q = ints + at(&ci, nr);
    c->root_v = ints + at(&ci, nr);
    i64 nB = 5 * ncut;
    double *w = pm->workspace;
    c->WtB = w + at(&cw, nB * nv);
    c->gB = w + at(&cw, nB);
    c->bB = w + at(&cw, nB);
    c->angle = w + at(&cw, ncut);
    c->rate = w + at(&cw, ncut);
    c->axis_world = w + at(&cw, 3 * ncut);
    c->bilateral_E = w + at(&cw, nB);
    if (cf.bad || ci.bad || cw.bad || cf.o != cf.len || ci.o != ci.len || cw.o != cw.len)
        return 0;
    c->beta_over_dt = f[beta];
    return 1;
}

const char *check_cut_model(const packed_model_t *c, i64 na, i64 nv) {
    if (c->n_ints < 3) return "CutModel: ints too short";
    i64 ncut = c->ints[0], constant = c->ints[1] != 0, nr = c->ints[2];
    if (ncut < 0 || nr < 0 || (!constant && nr != 0))
        return "CutModel: sizes (ncut, constant, nr) are not valid";
    cut_model_t cm;
    if (!unpack_cut_model(c, na, nv, &cm)) return "CutModel: buffer lengths do not match its sizes";
    return NULL;
}

/* _applied_torque: the torques the motors apply for tau (saturate_torque at the joint rates
 * of u), or tau as given; 0 if tau has a non-finite entry */
static int applied_torque(int saturate, const double *tau, i64 n, const double *u,
                          const tree_model_t *t, double *applied, arena_t *a) {
    if (!saturate) {
        for (i64 k = 0; k < n; k++) applied[k] = tau[k];
        return 1;
    }
    double *qd = arena_f(a, t->na);
    for (i64 k = 0; k < t->na; k++) qd[k] = u[t->joint_v[k]];
    return saturate_torque(tau, t->effort_limit, qd, t->velocity_limit, applied, n);
}

/* _report_contacts: g_N and the contact points at q^M into the report buffer */
static void report_contacts(const double *gap, const double *position, double *report, i64 nc) {
    for (i64 i = 0; i < nc; i++) {
        report[3 * nc + i] = gap[i];
        for (i64 k = 0; k < 3; k++) report[4 * nc + 3 * i + k] = position[3 * i + k];
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
    double *impulse = x->report;
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

/* tree_step_hard: the applied torques, Eqn. (6) and M, h, W at the midpoint, the contact
 * problem and its solution, Eqn. (8) */
tree_step_result_t tree_step_hard(int saturate, const step_arrays_t *x, const packed_model_t *m,
                                  arena_t *a) {
    tree_model_t t;
    unpack_tree_model(m, &t);
    i64 nv = x->nv, nq = x->nq, nc = t.contacts.nc;
    double *applied = x->report + 7 * nc;
    if (!applied_torque(saturate, x->tau, x->n_tau, x->u, &t, applied, a))
        return result_of(TREE_STEP_NONFINITE_TORQUE);
    double half_dt = 0.5 * t.s.dt;
    double *out = arena_f(a, nq + nv * nv + nv);
    double *qM = out, *M = out + nq, *h = out + nq + nv * nv;
    midpoint_with_forces(x, half_dt, applied, &t, qM, M, h);
    problem_t p;
    contact_problem(&t.s, M, x->u, nv, t.gap, nc, t.Wt_all, NULL, 0, NULL, t.eps, t.dof_parent,
                    1, t.L, x->last_impulse, x->last_active, NULL, a, &p);
    if (!p.ok) return result_of(TREE_STEP_NOT_PD);
    tree_step_result_t res = result_of(TREE_STEP_OK);
    /* (no bilateral rows: Λ_B is empty, last_bilateral its own buffer) */
    complete_step(&t.s, &p, h, M, &t, x, x->last_bilateral, qM, half_dt, &res, a);
    report_contacts(t.gap, t.position, x->report, nc);
    res.n_active = p.na;
    res.opened = p.opened;
    return res;
}

/* tree_step_compliant: the applied torques, the midpoint, solve_compliant (u^E = u_free) and
 * Eqn. (8); the report's Λ is the compliant force Δt, is_active the closed flags
 * (g_N(q^M) ≤ 0). A failed step leaves the contact state as it was. */
tree_step_result_t tree_step_compliant(int saturate, const step_arrays_t *x, u8 *closed,
                                       u8 *slip, double *anchor, double *lam,
                                       const packed_model_t *m, arena_t *a) {
    tree_model_t t;
    unpack_tree_model(m, &t);
    i64 nv = x->nv, nq = x->nq, nc = t.contacts.nc;
    double dt = t.s.dt;
    double *applied = x->report + 7 * nc;
    if (!applied_torque(saturate, x->tau, x->n_tau, x->u, &t, applied, a))
        return result_of(TREE_STEP_NONFINITE_TORQUE);
    double half_dt = 0.5 * dt;
    double *out = arena_f(a, nq + nv * nv + nv);
    double *qM = out, *M = out + nq, *h = out + nq + nv * nv;
    midpoint_with_forces(x, half_dt, applied, &t, qM, M, h);
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
    if (!solve_compliant(&t.law, M, h, x->u, nv, dt, nc, t.gap, t.position, t.Wt_all, closed,
                         slip, anchor, t.ground.t1, t.ground.t2, lam, t.dof_parent, 1, t.L,
                         t.u_free, NULL)) {
        outcome = TREE_STEP_NOT_PD;
    } else {
        for (i64 k = 0; k < nv; k++) x->uE[k] = t.u_free[k];
        outcome = TREE_STEP_OK;
        if (!end_of_step(qM, x->uE, t.u_corr, 0, half_dt, &t.tree, nq, x->qE, a))
            outcome = TREE_STEP_NONFINITE_STATE;
    }
    if (outcome != TREE_STEP_OK) { /* the contact state back to what it was */
        for (i64 i = 0; i < nc; i++) {
            closed[i] = kept_flags[i] != 0;
            slip[i] = kept_flags[nc + i] != 0;
            for (i64 k = 0; k < 3; k++) {
                anchor[3 * i + k] = kept[3 * i + k];
                lam[3 * i + k] = kept[3 * nc + 3 * i + k];
            }
        }
    }
    i64 n_active = 0;
    for (i64 i = 0; i < nc; i++) {
        for (i64 k = 0; k < 3; k++) x->report[3 * i + k] = lam[3 * i + k] * dt;
        x->is_active[i] = t.gap[i] <= 0.0;
        n_active += x->is_active[i];
    }
    report_contacts(t.gap, t.position, x->report, nc);
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
    double *applied = x->report + 7 * nc;
    for (i64 k = 0; k < na; k++) {
        if (!isfinite(x->tau[k])) return result_of(TREE_STEP_NONFINITE_TORQUE);
        applied[k] = x->tau[k];
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
                    t.dof_parent, factor, t.L, x->last_impulse, x->last_active, NULL, a, &p);
    if (!p.ok) return result_of(TREE_STEP_NOT_PD);
    tree_step_result_t res = result_of(TREE_STEP_OK);
    complete_step(&t.s, &p, h, M, &t, x, c.bilateral_E, qM, half_dt, &res, a);
    if (res.outcome == TREE_STEP_OK)
        cut_joint_motion(x->qE, x->uE, &t.tree, &t.frames, &c.cuts, angle_E, rate_E, a);
    report_contacts(t.gap, t.position, x->report, nc);
    res.n_active = p.na;
    res.opened = p.opened;
    return res;
}
