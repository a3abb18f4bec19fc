/* The Python binding of a tree's step bound to its model (TreeStep). */
#include "bind.h"
#include "numpy_api.h"

/* ---------------------------------------------------------------------------------------
 * TreeStep: the one-kernel step of a tree bound to its model, MoreauStepper.step and
 * prepare of the minimal coordinates in one call from Python: the model's buffers parsed
 * once, the state read from its SimState record (its q and u replaced by new arrays q^E and
 * u^E after a successful step, its contact memory updated in place by the kernel), a result
 * that did more than converge handed to the stepper's count (MoreauStepper._count, which
 * raises on a failed step: the state is then as it was).
 * ------------------------------------------------------------------------------------- */
typedef struct {
    PyObject_HEAD int compliant;
    i64 options, nq, nv, n_tau;
    PyObject *model; /* the TreeStepModel (4 arrays), parsed into m */
    packed_model_t m;
    PyObject *no_torque; /* τ of no torque; f_ext of none */
    PyObject *no_force;
    PyObject *spare;                   /* (report, is_active) for prepare: written, not read */
    PyObject *stepper;                 /* its stats.steps counted, its _count called */
    PyObject *prepared_q, *prepared_u; /* the state prepared ahead (prepare) */
    int factored;                      /* a step went through (the stepper's first is counted) */
} TreeStepObject;

/* the SimState fields a tree kernel reads, hard and compliant (interned at first use) */
static PyObject *state_names[2][6];
static PyObject *s_q, *s_u, *s_stats, *s_steps, *s_count, *one;

static int intern_names(void) {
    static const char *names[2][6] = {
        {"q", "u", "last_impulse", "last_active", "last_bilateral", "prox_memory"},
        {"q", "u", "closed", "slip", "anchor", "lam_compliant"}};
    if (s_q) return 1;
    for (int k = 0; k < 2; k++)
        for (int j = 0; j < 6; j++)
            if (!(state_names[k][j] = PyUnicode_InternFromString(names[k][j]))) return 0;
    s_q = state_names[0][0];
    s_u = state_names[0][1];
    s_stats = PyUnicode_InternFromString("stats");
    s_steps = PyUnicode_InternFromString("steps");
    s_count = PyUnicode_InternFromString("_count");
    one = PyLong_FromLong(1);
    return s_stats && s_steps && s_count && one;
}

/* a new float64 vector of n entries (not initialized) */
static PyObject *empty_vector(i64 n) {
#ifdef STARLETH_NUMPY_C_API
    npy_intp dims[1] = {(npy_intp)n};
    return PyArray_EMPTY(1, dims, NPY_FLOAT64, 0);
#else
    return PyObject_CallFunction(np_empty, "(L)", (long long)n);
#endif
}

static int tree_step_traverse(TreeStepObject *self, visitproc visit, void *arg) {
    Py_VISIT(self->model);
    Py_VISIT(self->no_torque);
    Py_VISIT(self->no_force);
    Py_VISIT(self->spare);
    Py_VISIT(self->stepper);
    Py_VISIT(self->prepared_q);
    Py_VISIT(self->prepared_u);
    return 0;
}

static int tree_step_clear(TreeStepObject *self) {
    Py_CLEAR(self->model);
    Py_CLEAR(self->no_torque);
    Py_CLEAR(self->no_force);
    Py_CLEAR(self->spare);
    Py_CLEAR(self->stepper);
    Py_CLEAR(self->prepared_q);
    Py_CLEAR(self->prepared_u);
    return 0;
}

static void tree_step_dealloc(TreeStepObject *self) {
    PyObject_GC_UnTrack(self);
    tree_step_clear(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* TreeStep(options, model, compliant, no_torque, no_force, spare, stepper) */
static int tree_step_init(TreeStepObject *self, PyObject *args, PyObject *kw) {
    long long options;
    int compliant;
    PyObject *model, *no_torque, *no_force, *spare, *stepper;
    if (kw && PyDict_GET_SIZE(kw)) {
        PyErr_SetString(PyExc_TypeError, "TreeStep takes positional arguments only");
        return -1;
    }
    if (!intern_names() || !PyArg_ParseTuple(args, "LOpOOOO:TreeStep", &options, &model, &compliant,
                                             &no_torque, &no_force, &spare, &stepper))
        return -1;
    static const spec_t spec[] = {{"model", GROUP + 4},
                                  {"floats", F64W},
                                  {"ints", I64},
                                  {"support", BOOL},
                                  {"workspace", F64W}};
    val_t v[4], t;
    held_t h = {.n = 0};
    PyObject *const a[1] = {model};
    int ok = parse(a, 1, "TreeStep", spec, 5, 1, v, &h) &&
             get_array(no_torque, F64, "TreeStep", "no_torque", &h, &t);
    /* (the arrays stay alive, and so their data, while the TreeStep holds them) */
    release(&h);
    if (!ok || !packed_of(v, &self->m)) return -1;
    const char *bad = self->m.n_ints < TREE_STEP_MODEL_HEADER
                          ? "TreeStepModel: ints too short"
                          : check_tree_model(&self->m, self->m.ints[TREE_STEP_MODEL_NV]);
    if (bad) {
        PyErr_Format(PyExc_ValueError, "TreeStep: %s", bad);
        return -1;
    }
    tree_step_clear(self);
    self->compliant = compliant;
    self->options = options;
    self->nq = self->m.ints[TREE_STEP_MODEL_NQ];
    self->nv = self->m.ints[TREE_STEP_MODEL_NV];
    self->n_tau = t.len;
    self->factored = 0;
    Py_INCREF(model);
    self->model = model;
    Py_INCREF(no_torque);
    self->no_torque = no_torque;
    Py_INCREF(no_force);
    self->no_force = no_force;
    Py_INCREF(spare);
    self->spare = spare;
    Py_INCREF(stepper);
    self->stepper = stepper;
    return 0;
}

/* The kernel on `state` (its six arrays into st, new references in held_o), q^E and u^E
 * new arrays (into qE, uE); the result, or NULL with an exception set */
static int tree_step_run(TreeStepObject *self, PyObject *state, i64 options, i64 mode,
                         PyObject *tau, PyObject *f_ext, PyObject *report, PyObject *is_active,
                         PyObject **held_o, PyObject **qE, PyObject **uE, tree_step_result_t *r) {
    static const char *fn = "TreeStep.step";
    static const int kinds[2][6] = {{F64, F64, F64W, BOOLW, F64W, F64W},
                                    {F64, F64, BOOLW, BOOLW, F64W, F64W}};
    val_t st[6], t, f, out[4];
    held_t h = {.n = 0};
    int ok = 1;
    for (int k = 0; k < 6 && ok; k++) {
        PyObject *o = PyObject_GetAttr(state, state_names[self->compliant][k]);
        held_o[k] = o;
        ok = o && get_array(o, kinds[self->compliant][k], fn,
                            PyUnicode_AsUTF8(state_names[self->compliant][k]), &h, &st[k]);
    }
    ok = ok && get_array(tau, F64, fn, "tau", &h, &t) &&
         get_array(f_ext == Py_None ? self->no_force : f_ext, F64, fn, "f_ext", &h, &f);
    if (ok && t.len == 0) { /* (no torque) */
        ok = get_array(self->no_torque, F64, fn, "tau", &h, &t);
        mode = TORQUE_AS_GIVEN;
    }
    if (ok && mode != TORQUE_IMPEDANCE) {
        i64 n = mode == TORQUE_REPLAY ? 2 * self->n_tau : self->n_tau;
        if (t.len != n) {
            PyErr_Format(PyExc_ValueError, "tau must have %lld entries, got %lld", (long long)n,
                         (long long)t.len);
            ok = 0;
        }
    }
    ok = ok && (*qE = empty_vector(self->nq)) && (*uE = empty_vector(self->nv)) &&
         get_array(report, F64W, fn, "report", &h, &out[0]) &&
         get_array(is_active, BOOLW, fn, "is_active", &h, &out[1]) &&
         get_array(*qE, F64W, fn, "qE", &h, &out[2]) &&
         get_array(*uE, F64W, fn, "uE", &h, &out[3]) &&
         run_tree_step(fn, self->compliant, options, mode, st, &t, &f, out, &self->m, r);
    release(&h);
    return ok;
}

/* tree_step_advance: TreeStep.step of parsed arguments (bind.h) */
PyObject *tree_step_advance(PyObject *tree, PyObject *state, PyObject *tau, PyObject *report,
                            PyObject *is_active, PyObject *f_ext, long long mode,
                            tree_step_result_t *out) {
    TreeStepObject *self = (TreeStepObject *)tree;
    if (tau == Py_None) tau = self->no_torque;
    i64 options = self->options;
    if (self->prepared_q) { /* a step prepared ahead for this state's q and u */
        PyObject *q = PyObject_GetAttr(state, s_q), *u = PyObject_GetAttr(state, s_u);
        if (q == self->prepared_q && u == self->prepared_u) options |= STEP_PREPARED;
        Py_XDECREF(q);
        Py_XDECREF(u);
        Py_CLEAR(self->prepared_q);
        Py_CLEAR(self->prepared_u);
        if (PyErr_Occurred()) return NULL;
    }
    PyObject *held_o[6] = {NULL}, *qE = NULL, *uE = NULL, *result = NULL;
    tree_step_result_t r;
    if (!tree_step_run(self, state, options, mode, tau, f_ext, report, is_active, held_o, &qE, &uE,
                       &r))
        goto done;
    result = tree_step_result_to_py(&r);
    if (!result) goto done;
    if (r.outcome || r.retried || r.status || r.projection_status >= 0 || !self->factored) {
        PyObject *counted = PyObject_CallMethodOneArg(self->stepper, s_count, result);
        if (!counted) {
            Py_CLEAR(result);
            goto done;
        }
        Py_DECREF(counted);
        self->factored = 1;
    }
    /* stats.steps += 1, then the state's new q and u */
    PyObject *stats = PyObject_GetAttr(self->stepper, s_stats);
    PyObject *steps = stats ? PyObject_GetAttr(stats, s_steps) : NULL;
    PyObject *more = steps ? PyNumber_Add(steps, one) : NULL;
    int ok = more && PyObject_SetAttr(stats, s_steps, more) == 0 &&
             PyObject_SetAttr(state, s_q, qE) == 0 && PyObject_SetAttr(state, s_u, uE) == 0;
    Py_XDECREF(stats);
    Py_XDECREF(steps);
    Py_XDECREF(more);
    if (!ok) Py_CLEAR(result);
    if (out) *out = r;
done:
    for (int k = 0; k < 6; k++) Py_XDECREF(held_o[k]);
    Py_XDECREF(qE);
    Py_XDECREF(uE);
    return result;
}

/* TreeStep.step(state, tau, report, is_active, f_ext=None, mode=TORQUE_SATURATED): as
 * MoreauStepper.step */
static PyObject *tree_step_step(TreeStepObject *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs < 4 || nargs > 6) {
        PyErr_Format(PyExc_TypeError, "TreeStep.step takes 4 to 6 arguments (%zd given)", nargs);
        return NULL;
    }
    long long mode = TORQUE_SATURATED;
    if (nargs > 5 && (mode = PyLong_AsLongLong(args[5])) == -1 && PyErr_Occurred()) return NULL;
    return tree_step_advance((PyObject *)self, args[0], args[1], args[2], args[3],
                             nargs > 4 ? args[4] : Py_None, mode, NULL);
}

/* TreeStep.prepare(state): as MoreauStepper.prepare */
static PyObject *tree_step_prepare(TreeStepObject *self, PyObject *state) {
    Py_CLEAR(self->prepared_q);
    Py_CLEAR(self->prepared_u);
    PyObject *held_o[6] = {NULL}, *qE = NULL, *uE = NULL;
    tree_step_result_t r;
    int ok = PyTuple_Check(self->spare) && PyTuple_GET_SIZE(self->spare) == 2 &&
             tree_step_run(self, state, self->options | STEP_PREPARE, TORQUE_AS_GIVEN,
                           self->no_torque, Py_None, PyTuple_GET_ITEM(self->spare, 0),
                           PyTuple_GET_ITEM(self->spare, 1), held_o, &qE, &uE, &r);
    if (ok) { /* (held_o[0] and [1]: the state's q and u) */
        Py_INCREF(held_o[0]);
        Py_INCREF(held_o[1]);
        self->prepared_q = held_o[0];
        self->prepared_u = held_o[1];
    } else if (!PyErr_Occurred())
        PyErr_SetString(PyExc_TypeError, "TreeStep: spare must be (report, is_active)");
    for (int k = 0; k < 6; k++) Py_XDECREF(held_o[k]);
    Py_XDECREF(qE);
    Py_XDECREF(uE);
    if (!ok) return NULL;
    Py_RETURN_NONE;
}

static PyMethodDef tree_step_methods[] = {
    {"step", (PyCFunction)(void (*)(void))tree_step_step, METH_FASTCALL,
     "step(state, tau, report, is_active, f_ext=None, mode=TORQUE_SATURATED) -> TreeStepResult: "
     "MoreauStepper.step of a tree."},
    {"prepare", (PyCFunction)tree_step_prepare, METH_O,
     "prepare(state): MoreauStepper.prepare of a tree."},
    {NULL, NULL, 0, NULL}};

PyTypeObject TreeStepType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "starleth_sim.physics._kernels.TreeStep",
    .tp_basicsize = sizeof(TreeStepObject),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
    .tp_doc =
        "TreeStep(options, model, compliant, no_torque, no_force, spare, stepper): the "
        "one-kernel step of a tree (tree_step_hard or tree_step_compliant) bound to its "
        "TreeStepModel: MoreauStepper.step and prepare in one call.",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)tree_step_init,
    .tp_dealloc = (destructor)tree_step_dealloc,
    .tp_traverse = (traverseproc)tree_step_traverse,
    .tp_clear = (inquiry)tree_step_clear,
    .tp_methods = tree_step_methods,
};
