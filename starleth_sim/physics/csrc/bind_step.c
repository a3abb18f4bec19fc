/* Bindings of the prepared contact problem (ContactProblem) and the one-kernel steps. */
#include "bind.h"
#include "numpy_api.h"

/* ---------------------------------------------------------------------------------------
 * ContactProblem: a hard-contact problem prepared ahead (prepare_hard_contacts), in memory
 * of its own, for complete_hard_contacts.
 * ------------------------------------------------------------------------------------- */
typedef struct {
    PyObject_HEAD arena_t arena;
    problem_t p;
    int filled;
    i64 nc, nv, nb;
} ProblemObject;

static void problem_dealloc(ProblemObject *self) {
    arena_free(&self->arena);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

__attribute__((noinline)) static PyObject *problem_new(PyTypeObject *type, PyObject *args,
                                                       PyObject *kw) {
    (void)args;
    (void)kw;
    ProblemObject *self = (ProblemObject *)type->tp_alloc(type, 0);
    if (self) {
        arena_init(&self->arena, 0);
        self->filled = 0;
    }
    return (PyObject *)self;
}

static PyObject *problem_get_ok(ProblemObject *self, void *c) {
    (void)c;
    return PyBool_FromLong(self->filled && self->p.ok);
}
static PyObject *problem_get_n_active(ProblemObject *self, void *c) {
    (void)c;
    return PyLong_FromLongLong(self->filled ? self->p.na : 0);
}
static PyObject *problem_get_opened(ProblemObject *self, void *c) {
    (void)c;
    return PyLong_FromLongLong(self->filled ? self->p.opened : 0);
}

/* copies of the problem's arrays, for inspection: a dict */
static PyObject *problem_arrays(ProblemObject *self, PyObject *unused) {
    (void)unused;
    if (!self->filled) {
        PyErr_SetString(PyExc_ValueError, "ContactProblem: not prepared");
        return NULL;
    }
    problem_t *p = &self->p;
    int full = p->ok && p->m > 0; /* (else the patterns are empty: pointers of one entry) */
    i64 m = p->m, nv = p->nv;
    i64 nnz_w = full ? p->pat.wp_ptr[m] : 0, nnz_m = full ? p->pat.mp_ptr[m] : 0;
    int g = full && p->G;
    PyObject *d = PyDict_New();
    if (!d) return NULL;
    struct {
        const char *k;
        PyObject *v;
    } items[] = {
        {"active", new_array(p->active, I64, p->na)},
        {"Wt", reshaped(new_array(p->Wt, F64, m * nv), m, nv)},
        {"MinvW", reshaped(new_array(p->MinvW, F64, nv * m), nv, m)},
        {"b", new_array(p->b, F64, m)},
        {"G",
         g ? reshaped(new_array(p->G, F64, m * m), m, m) : reshaped(new_array(NULL, F64, 0), 0, 0)},
        {"Gdiag", full ? new_array(p->Gdiag, F64, m) : new_array(NULL, F64, 0)},
        {"LB", reshaped(new_array(p->LB, F64, p->nb_LB * p->nb_LB), p->nb_LB, p->nb_LB)},
        {"wp_ptr", new_array(p->pat.wp_ptr, I64, full ? m + 1 : 1)},
        {"wp_idx", new_array(p->pat.wp_idx, I64, nnz_w)},
        {"mp_ptr", new_array(p->pat.mp_ptr, I64, full ? m + 1 : 1)},
        {"mp_idx", new_array(p->pat.mp_idx, I64, nnz_m)},
        {"gp_ptr", new_array(p->pat.gp_ptr, I64, full ? m + 1 : 1)},
        {"gp_idx", new_array(p->pat.gp_idx, I64, g ? p->pat.gp_ptr[m] : 0)},
        {"lb_first", new_array(p->pat.lb_first, I64, p->pat.n_lb)},
    };
    int n = (int)(sizeof(items) / sizeof(items[0]));
    int ok = 1;
    for (int k = 0; k < n; k++) {
        if (!items[k].v || PyDict_SetItemString(d, items[k].k, items[k].v) != 0) ok = 0;
        Py_XDECREF(items[k].v);
    }
    if (!ok) {
        Py_DECREF(d);
        return NULL;
    }
    return d;
}

static PyGetSetDef problem_getset[] = {
    {"ok", (getter)problem_get_ok, NULL, "M (and G_B) positive definite", NULL},
    {"n_active", (getter)problem_get_n_active, NULL, "|I|, the active contacts", NULL},
    {"opened", (getter)problem_get_opened, NULL,
     "contacts loaded in the last step that left the active set", NULL},
    {NULL, NULL, NULL, NULL, NULL}};

static PyMethodDef problem_methods[] = {
    {"arrays", (PyCFunction)problem_arrays, METH_NOARGS,
     "Copies of the problem's arrays (active, Wt, MinvW, b, G, Gdiag, LB and the patterns)."},
    {NULL, NULL, 0, NULL}};

PyTypeObject ProblemType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "starleth_sim.physics._kernels.ContactProblem",
    .tp_basicsize = sizeof(ProblemObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc =
        "A hard-contact problem prepared ahead (prepare_hard_contacts): the active set, "
        "W^T, M^{-1}W, b, G, L_B and their patterns, in memory of its own.",
    .tp_new = problem_new,
    .tp_dealloc = (destructor)problem_dealloc,
    .tp_getset = problem_getset,
    .tp_methods = problem_methods,
};

/* The sizes shared by the contact-problem kernels */
static int contact_problem_sizes(const char *fn, const val_t *M, const val_t *uS, const val_t *gap,
                                 const val_t *Wt_all, const val_t *WtB, const val_t *bB,
                                 const val_t *eps, const val_t *dof_parent, const val_t *L,
                                 const val_t *last_impulse, const val_t *last_active,
                                 const val_t *timings, i64 *nv, i64 *nc, i64 *nb) {
    *nv = uS->len;
    *nc = gap->len;
    *nb = bB->len;
    return need(M->len == *nv * *nv && Wt_all->len == 3 * *nc * *nv && WtB->len == *nb * *nv &&
                    eps->len == 2 * *nc && dof_parent->len == *nv && L->len == *nv * *nv &&
                    last_impulse->len == 3 * *nc && last_active->len == *nc &&
                    (!timings->p || timings->len >= 5),
                fn, "the arrays do not match the contacts, bilateral rows and velocities");
}

FN(prepare_hard_contacts) {
    static const spec_t spec[] = {
        {"settings", OBJ},     {"state", GROUP + 2},  {"M", F64},
        {"uS", F64},           {"rows", GROUP + 5},   {"gap", F64},
        {"Wt_all", F64},       {"WtB", F64},          {"bB", F64},
        {"eps", F64},          {"factor", GROUP + 3}, {"dof_parent", I64},
        {"factor", FLAG},      {"L", F64W},           {"memory", GROUP + 2},
        {"last_impulse", F64}, {"last_active", BOOL}, {"timings", F64N},
        {"frames", F64N},      {"problem", OBJ}};
    val_t v[16];
    v[14].p = NULL; /* (frames and problem are optional) */
    v[14].len = 0;
    v[15].o = Py_None;
    held_t h = {.n = 0};
    volatile int failed = 0;
    settings_t s;
    i64 nv, nc, nb;
    if (!PARSE("prepare_hard_contacts", spec, 6, v, &h) ||
        !get_settings(v[0].o, "prepare_hard_contacts", &s) ||
        !contact_problem_sizes("prepare_hard_contacts", &v[1], &v[2], &v[3], &v[4], &v[5], &v[6],
                               &v[7], &v[8], &v[10], &v[11], &v[12], &v[13], &nv, &nc, &nb) ||
        !need(!v[14].p || v[14].len == FRAME_STRIDE * nc, "prepare_hard_contacts",
              "frames must be nc x 11"))
        FAIL;
    ProblemObject *pr;
    if (v[15].o == Py_None) {
        pr = (ProblemObject *)problem_new(&ProblemType, NULL, NULL);
        if (!pr) FAIL;
    } else if (Py_IS_TYPE(v[15].o, &ProblemType)) {
        pr = (ProblemObject *)v[15].o;
        Py_INCREF(pr);
    } else {
        release(&h);
        PyErr_SetString(PyExc_TypeError, "prepare_hard_contacts: problem must be a ContactProblem");
        return NULL;
    }
    pr->filled = 0;
    arena_t *a = &pr->arena;
    RUN(a, failed,
        contact_problem(&s, v[1].p, v[2].p, nv, v[3].p, nc, v[4].p, v[5].p, nb, v[6].p, v[7].p,
                        v[14].p, v[8].p, (int)v[9].i, v[10].p, v[11].p, v[12].p, NULL, v[13].p, a,
                        &pr->p));
    release(&h);
    if (failed) {
        Py_DECREF(pr);
        return PyErr_NoMemory();
    }
    pr->filled = 1;
    pr->nc = nc;
    pr->nv = nv;
    pr->nb = nb;
    return (PyObject *)pr;
}

/* ---------------------------------------------------------------------------------------
 * the one-kernel steps
 * ------------------------------------------------------------------------------------- */
int packed_of(const val_t *v, packed_model_t *m) {
    m->floats = v[0].p;
    m->n_floats = v[0].len;
    m->ints = v[1].p;
    m->n_ints = v[1].len;
    m->support = v[2].p;
    m->n_support = v[2].len;
    m->workspace = v[3].p;
    m->n_workspace = v[3].len;
    return 1;
}

/* The step arrays: v = q, u, tau, f_ext, last_impulse, last_active, last_bilateral, report,
 * is_active, qE, uE; checked against the model and the torque mode (TORQUE_*: tau is one
 * torque per joint, or a command of 5 per joint) */
static int step_arrays_of(const char *fn, const val_t *v, const packed_model_t *m, i64 torque_mode,
                          step_arrays_t *x) {
    const char *bad = check_tree_model(m, v[1].len);
    if (bad) {
        PyErr_Format(PyExc_ValueError, "%s: %s", fn, bad);
        return 0;
    }
    tree_model_t t = {0}; /* (zeroed for the compiler: the unpack fills every field) */
    unpack_tree_model(m, &t);
    i64 nc = t.contacts.nc, na = t.na, nv = t.tree.nv;
    x->q = v[0].p;
    x->nq = v[0].len;
    x->u = v[1].p;
    x->nv = v[1].len;
    x->tau = v[2].p;
    x->n_tau = v[2].len;
    x->f_ext = v[3].p;
    x->n_f_ext = v[3].len;
    x->last_impulse = v[4].p;
    x->last_active = v[5].p;
    x->last_bilateral = v[6].p;
    x->nb = v[6].len;
    x->prox_memory = NULL; /* (the caller's, where it has one) */
    x->is_active = v[8].p;
    x->qE = v[9].p;
    x->uE = v[10].p;
    if (!need(m->ints[TREE_STEP_MODEL_NQ] == x->nq, fn, "q does not match the model's nq"))
        return 0;
    /* q: nq ≥ every idx_q + its joint's coordinates (checked by the model's own sizes) */
    for (i64 j = 1; j < t.tree.nj; j++) {
        i64 wq = t.tree.jtype[j] == JT_FREEFLYER ? 7 : 1;
        i64 wv = t.tree.jtype[j] == JT_FREEFLYER ? 6 : 1;
        if (t.tree.idx_q[j] < 0 || t.tree.idx_q[j] + wq > x->nq || t.tree.idx_v[j] < 0 ||
            t.tree.idx_v[j] + wv > nv) {
            PyErr_Format(PyExc_ValueError, "%s: q or u is too short for the model", fn);
            return 0;
        }
    }
    if (torque_mode < TORQUE_AS_GIVEN || torque_mode > TORQUE_REPLAY) {
        PyErr_Format(PyExc_ValueError, "%s: torque_mode must be 0 to 3 (TORQUE_*)", fn);
        return 0;
    }
    if (torque_mode == TORQUE_IMPEDANCE) /* the law reads q at each joint's entry */
        for (i64 k = 0; k < na; k++)
            if (t.joint_q[k] < 0 || t.joint_q[k] >= x->nq) {
                PyErr_Format(PyExc_ValueError, "%s: joint %lld has no entry of q (a cut joint?)",
                             fn, (long long)k);
                return 0;
            }
    i64 n_tau = torque_mode == TORQUE_IMPEDANCE ? impedance_command_length(na)
                : torque_mode == TORQUE_REPLAY  ? 2 * na
                                                : na;
    if (!need(x->n_tau == n_tau && (x->n_f_ext == 0 || x->n_f_ext == nv) && v[4].len == 3 * nc &&
                  v[5].len == nc && v[7].len == report_length(nc, na) && v[8].len == nc &&
                  v[9].len == x->nq && v[10].len == nv,
              fn,
              "the step's arrays do not match the model (tau: one torque per joint, or 5 "
              "per joint for an impedance command, 2 for a replay; f_ext: nv or empty; report: 7 "
              "nc + 3 na)"))
        return 0;
    report_views(v[7].p, nc, na, &x->report);
    return 1;
}

/* last_bilateral of a tree step: Λ_f's memory, one entry per joint friction row */
static int friction_memory_of(const char *fn, const packed_model_t *m, i64 nb) {
    if (!m->ints[TREE_STEP_MODEL_DRIVES] && nb == 0) return 1;
    tree_model_t t = {0};
    unpack_tree_model(m, &t);
    return need(nb == joint_friction_count(&t), fn,
                "last_bilateral must have one entry per joint with Coulomb friction");
}

/* the compliant contact state: v = closed, slip, anchor, lam (nc, nc, 3 nc, 3 nc) */
static int compliant_of(const char *fn, const val_t *v, i64 nc, compliant_state_t *cs) {
    if (!need(v[0].len == nc && v[1].len == nc && v[2].len == 3 * nc && v[3].len == 3 * nc, fn,
              "closed, slip, anchor and lam must match the contacts"))
        return 0;
    cs->closed = v[0].p;
    cs->slip = v[1].p;
    cs->anchor = v[2].p;
    cs->lam = v[3].p;
    return 1;
}

#define COMPLIANT_ARRAYS                                    \
    {"closed", BOOLW}, {"slip", BOOLW}, {"anchor", F64W}, { \
        "lam", F64W                                         \
    }

/* run_tree_step: the tree kernel (tree_step_hard, or tree_step_compliant) of parsed arrays:
 * st = the state's six (hard: q, u, last_impulse, last_active, last_bilateral, prox_memory;
 * compliant: q, u, closed, slip, anchor, lam), tau, f_ext, out = report, is_active, qE, uE;
 * their sizes checked against the model m. 0 with an exception set on error. */
int run_tree_step(const char *fn, int compliant, i64 options, i64 mode, const val_t *st,
                  const val_t *tau, const val_t *f_ext, const val_t *out, const packed_model_t *m,
                  tree_step_result_t *r) {
    step_arrays_t x;
    compliant_state_t cs;
    volatile int failed = 0;
    if (compliant) {
        /* lam and closed stand in for the warm-start memory (of the same lengths), which a
         * compliant step has none of */
        val_t w[11] = {st[0], st[1],  *tau,   *f_ext, st[5], st[2],
                       st[5], out[0], out[1], out[2], out[3]};
        w[6].len = 0;
        if (!step_arrays_of(fn, w, m, mode, &x) ||
            !compliant_of(fn, &st[2], m->ints[TREE_STEP_MODEL_NC], &cs))
            return 0;
    } else {
        val_t w[11] = {st[0], st[1],  *tau,   *f_ext, st[2], st[3],
                       st[4], out[0], out[1], out[2], out[3]};
        if (!step_arrays_of(fn, w, m, mode, &x) || !friction_memory_of(fn, m, x.nb) ||
            !need(st[5].len == 3, fn, "prox_memory must have 3 entries"))
            return 0;
        x.prox_memory = st[5].p;
    }
    tree_step_result_t res = {0, 0, 0, 0, 0, 0.0, 0, 0, -1};
    arena_t *a = scratch_arena();
    if (compliant)
        RUN_NOGIL(a, failed, res = tree_step_compliant((int)options, (int)mode, &x, &cs, m, a));
    else
        RUN_NOGIL(a, failed, res = tree_step_hard((int)options, (int)mode, &x, m, a));
    if (failed) {
        PyErr_NoMemory();
        return 0;
    }
    *r = res;
    return 1;
}

#define STEP_OUT                                                                \
    {"out", GROUP + 4}, {"report", F64W}, {"is_active", BOOLW}, {"qE", F64W}, { \
        "uE", F64W                                                              \
    }
#define MODEL_BUFFERS                                                           \
    {"model", GROUP + 4}, {"floats", F64W}, {"ints", I64}, {"support", BOOL}, { \
        "workspace", F64W                                                       \
    }

/* a tree kernel's binding: v as the spec below, the state's six arrays by `names` */
static PyObject *tree_step_call(const char *fn, int compliant, PyObject *const *args,
                                Py_ssize_t nargs) {
    static const spec_t hard[] = {{"options", INT},
                                  {"torque_mode", INT},
                                  {"state", GROUP + 6},
                                  {"q", F64},
                                  {"u", F64},
                                  {"last_impulse", F64W},
                                  {"last_active", BOOLW},
                                  {"last_bilateral", F64W},
                                  {"prox_memory", F64W},
                                  {"tau", F64},
                                  {"f_ext", F64},
                                  STEP_OUT,
                                  MODEL_BUFFERS};
    static const spec_t soft[] = {
        {"options", INT}, {"torque_mode", INT}, {"state", GROUP + 6}, {"q", F64}, {"u", F64},
        COMPLIANT_ARRAYS, {"tau", F64},         {"f_ext", F64},       STEP_OUT,   MODEL_BUFFERS};
    val_t v[18];
    held_t h = {.n = 0};
    packed_model_t m;
    tree_step_result_t r;
    const spec_t *spec = compliant ? soft : hard;
    int n_spec = (int)(sizeof(hard) / sizeof(hard[0]));
    if (!parse(args, nargs, fn, spec, n_spec, 7, v, &h) || !packed_of(&v[14], &m) ||
        !run_tree_step(fn, compliant, v[0].i, v[1].i, &v[2], &v[8], &v[9], &v[10], &m, &r))
        FAIL;
    release(&h);
    return tree_step_result_to_py(&r);
}

/* tree_step_hard(options, torque_mode, state, tau, f_ext, out, model): state = (q, u,
 * last_impulse, last_active, last_bilateral, prox_memory), out = (report, is_active, qE, uE),
 * model = the TreeStepModel's buffers */
FN(tree_step_hard) {
    return tree_step_call("tree_step_hard", 0, args, nargs);
}

/* tree_step_compliant(options, torque_mode, state, tau, f_ext, out, model): state = (q, u,
 * closed, slip, anchor, lam), out and model as tree_step_hard's */
FN(tree_step_compliant) {
    return tree_step_call("tree_step_compliant", 1, args, nargs);
}

/* the CutModel's buffers (floats, ints, workspace), checked against the TreeStepModel */
static int cut_of(const val_t *v, const packed_model_t *m, i64 nv, packed_model_t *c) {
    c->floats = v[0].p;
    c->n_floats = v[0].len;
    c->ints = v[1].p;
    c->n_ints = v[1].len;
    c->support = NULL;
    c->n_support = 0;
    c->workspace = v[2].p;
    c->n_workspace = v[2].len;
    const char *bad = check_cut_model(c, m->ints[TREE_STEP_MODEL_NA], nv);
    if (bad) PyErr_Format(PyExc_ValueError, "forest_step: %s", bad);
    return bad == NULL;
}

/* forest_step(options, state, tau, f_ext, out, model, cut): state = (q, u, last_impulse,
 * last_active, last_bilateral, prox_memory, closed, slip, anchor, lam: the compliant arrays
 * read with STEP_COMPLIANT only), out = (report, is_active, qE, uE, angle_E, rate_E), model the
 * TreeStepModel's buffers, cut the CutModel's */
FN(forest_step) {
    static const spec_t spec[] = {{"options", INT},
                                  {"state", GROUP + 10},
                                  {"q", F64},
                                  {"u", F64},
                                  {"last_impulse", F64W},
                                  {"last_active", BOOLW},
                                  {"last_bilateral", F64W},
                                  {"prox_memory", F64W},
                                  COMPLIANT_ARRAYS,
                                  {"tau", F64},
                                  {"f_ext", F64},
                                  {"out", GROUP + 6},
                                  {"report", F64W},
                                  {"is_active", BOOLW},
                                  {"qE", F64W},
                                  {"uE", F64W},
                                  {"angle_E", F64W},
                                  {"rate_E", F64W},
                                  MODEL_BUFFERS,
                                  {"cut", GROUP + 3},
                                  {"cut_floats", F64},
                                  {"cut_ints", I64},
                                  {"cut_workspace", F64W}};
    val_t v[26];
    held_t h = {.n = 0};
    volatile int failed = 0;
    packed_model_t m, c;
    step_arrays_t x;
    compliant_state_t cs = {NULL, NULL, NULL, NULL};
    if (!PARSE("forest_step", spec, 7, v, &h) || !packed_of(&v[19], &m)) FAIL;
    val_t w[11] = {v[1], v[2], v[11], v[12], v[3], v[4], v[5], v[13], v[14], v[15], v[16]};
    if (!step_arrays_of("forest_step", w, &m, TORQUE_AS_GIVEN, &x) || !cut_of(&v[23], &m, x.nv, &c))
        FAIL;
    if ((v[0].i & STEP_COMPLIANT) &&
        !compliant_of("forest_step", &v[7], m.ints[TREE_STEP_MODEL_NC], &cs))
        FAIL;
    i64 ncut = c.ints[CUT_MODEL_NCUT];
    if (!need(x.nb == 5 * ncut && v[17].len == ncut && v[18].len == ncut && v[6].len == 3,
              "forest_step",
              "last_bilateral (5 per cut joint), angle_E and rate_E must match the cut joints, "
              "prox_memory have 3 entries"))
        FAIL;
    x.prox_memory = v[6].p;
    tree_step_result_t r = {0, 0, 0, 0, 0, 0.0, 0, 0, -1};
    arena_t *a = scratch_arena();
    RUN_NOGIL(a, failed, r = forest_step((int)v[0].i, &x, &cs, v[17].p, v[18].p, &m, &c, a));
    release(&h);
    if (failed) return PyErr_NoMemory();
    return tree_step_result_to_py(&r);
}

FN(impedance_torque) {
    static const spec_t spec[] = {{"command", F64}, {"q", F64}, {"qd", F64}, {"out", F64W}};
    val_t v[4];
    held_t h = {.n = 0};
    if (!PARSE("impedance_torque", spec, 4, v, &h)) FAIL;
    i64 n = v[3].len;
    if (!need(v[0].len == impedance_command_length(n) && v[1].len == n && v[2].len == n,
              "impedance_torque", "command: 5 entries per joint; q, qd and out: one"))
        FAIL;
    impedance_command_t c;
    impedance_command_views((double *)v[0].p, n, &c); /* (read only) */
    impedance_torque(&c, v[1].p, v[2].p, v[3].p, n);
    release(&h);
    Py_RETURN_NONE;
}

FN(scratch_arena_stats) {
    (void)args;
    (void)nargs;
    arena_t *a = scratch_arena();
    return Py_BuildValue("(LnL)", (long long)a->misses, (Py_ssize_t)a->cap, (long long)a->wanted);
}
