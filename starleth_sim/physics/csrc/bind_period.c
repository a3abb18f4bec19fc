/* ControlPeriod: what the last control period of a Simulator left (the set of report
 * buffers in use, Λ summed over its physics steps, its command, the cumulative counts of
 * Diagnostics and its Diagnostics), and `step`, a control period of one physics step of a
 * tree without wrenches in one call: the kernel (TreeStep), the state's t, this record and
 * the Diagnostics; `finish` writes the same record after every other period, whose physics
 * steps Simulator._control_period runs. */
#include <time.h>

#include "bind.h"
#include "numpy_api.h"

typedef struct {
    PyObject_HEAD PyObject *sets; /* the two sets of report buffers, each one (report,
                                     is_active, views) per physics step */
    int next;                     /* the set the next period writes */
    PyObject *impulse;            /* Λ of the last period (nc x 3), summed over its steps */
    PyObject *command;            /* the last period's command (None after a reset) */
    PyObject *diagnostics;        /* the last period's Diagnostics */
    long long totals[3];       /* physics_steps, nonconverged_steps, loaded_contacts_opened_total */
    PyObject *tree;            /* the TreeStep of the one-kernel periods, or None: none */
    PyObject *persistent;      /* the persistent wrenches (a dict) */
    double period;             /* [s] */
    Py_ssize_t n_joints;       /* the length of a torque vector */
    PyObject *diagnostics_new; /* Diagnostics.__new__'s type, made without __init__ */
    PyObject *no_timings;      /* Diagnostics.timings when not profiling */
    PyObject *log_step;        /* log_step(d, t) -> d: the log of a step that did more than
                                  converge */
} ControlPeriodObject;

static PyObject *s_t, *s_pending, *s_pending_wrenches, *s_status, *s_opened, *empty_tuple;

static int period_names(void) {
    if (s_t) return 1;
    s_t = PyUnicode_InternFromString("t");
    s_pending = PyUnicode_InternFromString("_pending");
    s_pending_wrenches = PyUnicode_InternFromString("pending_wrenches");
    s_status = PyUnicode_InternFromString("status");
    s_opened = PyUnicode_InternFromString("opened");
    empty_tuple = PyTuple_New(0);
    return s_t && s_pending && s_pending_wrenches && s_status && s_opened && empty_tuple;
}

#define PERIOD_OBJECTS(X) \
    X(sets)               \
    X(impulse)            \
    X(command) X(diagnostics) X(tree) X(persistent) X(diagnostics_new) X(no_timings) X(log_step)

static int period_traverse(ControlPeriodObject *self, visitproc visit, void *arg) {
#define VISIT(f) Py_VISIT(self->f);
    PERIOD_OBJECTS(VISIT)
#undef VISIT
    return 0;
}

static int period_clear(ControlPeriodObject *self) {
#define CLEAR(f) Py_CLEAR(self->f);
    PERIOD_OBJECTS(CLEAR)
#undef CLEAR
    return 0;
}

static void period_dealloc(ControlPeriodObject *self) {
    PyObject_GC_UnTrack(self);
    period_clear(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* ControlPeriod(sets, period, n_joints, tree, persistent, diagnostics_type, no_timings,
 * log_step) */
static int period_init(ControlPeriodObject *self, PyObject *args, PyObject *kw) {
    PyObject *sets, *tree, *persistent, *dtype, *no_timings, *log_step;
    double period;
    Py_ssize_t n_joints;
    if (kw && PyDict_GET_SIZE(kw)) {
        PyErr_SetString(PyExc_TypeError, "ControlPeriod takes positional arguments only");
        return -1;
    }
    if (!period_names() ||
        !PyArg_ParseTuple(args, "OdnOOOOO:ControlPeriod", &sets, &period, &n_joints, &tree,
                          &persistent, &dtype, &no_timings, &log_step))
        return -1;
    if (!PyTuple_Check(sets) || PyTuple_GET_SIZE(sets) != 2 ||
        (tree != Py_None && !Py_IS_TYPE(tree, &TreeStepType)) || !PyDict_Check(persistent) ||
        !PyType_Check(dtype) || !PyCallable_Check(log_step)) {
        PyErr_SetString(PyExc_TypeError,
                        "ControlPeriod: sets (a pair), a TreeStep or None, the persistent "
                        "wrenches (a dict), the Diagnostics type and a callable log_step");
        return -1;
    }
    period_clear(self);
    PyObject **fields[] = {&self->sets,       &self->tree,
                           &self->persistent, &self->diagnostics_new,
                           &self->no_timings, &self->log_step};
    PyObject *values[] = {sets, tree, persistent, dtype, no_timings, log_step};
    for (int k = 0; k < 6; k++) {
        Py_INCREF(values[k]);
        *fields[k] = values[k];
    }
    Py_INCREF(Py_None);
    self->impulse = Py_None;
    Py_INCREF(Py_None);
    self->command = Py_None;
    Py_INCREF(Py_None);
    self->diagnostics = Py_None;
    self->next = 0;
    self->period = period;
    self->n_joints = n_joints;
    for (int k = 0; k < 3; k++) self->totals[k] = 0;
    return 0;
}

/* whether `tau` is a torque vector the kernel takes as it is: a float64 numpy array (not a
 * subclass) of n entries, one-dimensional and C-contiguous (anything else: the Python path,
 * which converts it or says what is wrong) */
static int plain_torques(PyObject *tau, Py_ssize_t n) {
#ifdef STARLETH_NUMPY_C_API
    if (!PyArray_CheckExact(tau)) return 0;
    PyArrayObject *a = (PyArrayObject *)tau;
    return PyArray_TYPE(a) == NPY_FLOAT64 && PyArray_NDIM(a) == 1 && PyArray_DIM(a, 0) == n &&
           PyArray_IS_C_CONTIGUOUS(a) && PyArray_ISALIGNED(a);
#else
    (void)tau, (void)n;
    return 0;
#endif
}

/* whether the next period is one kernel call: a TreeStep and no wrench to apply */
static int one_kernel(ControlPeriodObject *self, PyObject *state) {
    if (self->tree == Py_None || PyDict_GET_SIZE(self->persistent)) return 0;
    PyObject *pending = PyObject_GetAttr(state, s_pending_wrenches);
    if (!pending) return -1;
    Py_ssize_t n = PyObject_Length(pending);
    Py_DECREF(pending);
    return n < 0 ? -1 : n == 0;
}

/* (physics_steps, nonconverged_steps, loaded_contacts_opened_total) as a tuple */
static PyObject *totals_tuple(const long long *totals) {
    PyObject *t = PyTuple_New(3);
    for (int k = 0; t && k < 3; k++) {
        PyObject *n = PyLong_FromLongLong(totals[k]);
        if (!n) {
            Py_CLEAR(t);
            break;
        }
        PyTuple_SET_ITEM(t, k, n);
    }
    return t;
}

static double seconds(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

/* The record after a period: t, the set in use, Λ (impulse), the command, the counts
 * (steps physics steps, nonconverged of them not converged, opened loaded contacts
 * opened); its Diagnostics of figures (a TreeStepResult or a list of them: pending, worked
 * out when read, diagnostics.Diagnostics), logged when a step did more than converge */
static PyObject *period_record(ControlPeriodObject *self, PyObject *state, PyObject *figures,
                               const long long counts[3], PyObject *impulse, PyObject *command,
                               double wall, PyObject *timings) {
    PyObject *t = PyObject_GetAttr(state, s_t);
    double t_end = t ? PyFloat_AsDouble(t) + self->period : -1.0;
    Py_XDECREF(t);
    if (PyErr_Occurred()) return NULL;
    PyObject *t_new = PyFloat_FromDouble(t_end);
    int ok = t_new && PyObject_SetAttr(state, s_t, t_new) == 0;
    Py_XDECREF(t_new);
    if (!ok) return NULL;
    self->next ^= 1;
    Py_INCREF(impulse);
    Py_SETREF(self->impulse, impulse);
    Py_INCREF(command);
    Py_SETREF(self->command, command);
    PyObject *before = totals_tuple(self->totals);
    for (int k = 0; k < 3; k++) self->totals[k] += counts[k];
    int quiet = counts[1] == 0 && counts[2] == 0;
    PyObject *w = before ? PyFloat_FromDouble(wall) : NULL;
    PyObject *pending = w ? PyTuple_Pack(4, before, figures, w, timings) : NULL;
    Py_XDECREF(before);
    Py_XDECREF(w);
    PyTypeObject *type = (PyTypeObject *)self->diagnostics_new;
    PyObject *d = pending ? type->tp_new(type, empty_tuple, NULL) : NULL;
    ok = d && PyObject_SetAttr(d, s_pending, pending) == 0;
    Py_XDECREF(pending);
    if (!ok) {
        Py_XDECREF(d);
        return NULL;
    }
    Py_INCREF(d);
    Py_SETREF(self->diagnostics, d);
    if (quiet) return d;
    PyObject *logged = PyObject_CallFunction(self->log_step, "Od", d, t_end);
    Py_DECREF(d);
    return logged;
}

/* finish(state, figures, impulse, command, wall, timings) -> Diagnostics: the record after
 * a period of the Python path (Simulator._control_period: several physics steps, wrenches,
 * a cut forest, profiling), figures its physics steps' TreeStepResults (a list) */
static PyObject *period_finish(ControlPeriodObject *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 6 || !PyList_Check(args[1])) {
        PyErr_SetString(PyExc_TypeError,
                        "ControlPeriod.finish(state, figures (a list), "
                        "impulse, command, wall, timings)");
        return NULL;
    }
    double wall = PyFloat_AsDouble(args[4]);
    if (wall == -1.0 && PyErr_Occurred()) return NULL;
    long long counts[3] = {PyList_GET_SIZE(args[1]), 0, 0};
    for (Py_ssize_t k = 0; k < PyList_GET_SIZE(args[1]); k++) {
        PyObject *f = PyList_GET_ITEM(args[1], k);
        PyObject *status = PyObject_GetAttr(f, s_status);
        PyObject *opened = status ? PyObject_GetAttr(f, s_opened) : NULL;
        long long st = status ? PyLong_AsLongLong(status) : -1;
        long long op = opened ? PyLong_AsLongLong(opened) : -1;
        Py_XDECREF(status);
        Py_XDECREF(opened);
        if (PyErr_Occurred()) return NULL;
        counts[1] += st != STATUS_CONVERGED;
        counts[2] += op;
    }
    return period_record(self, args[0], args[1], counts, args[2], args[3], wall, args[5]);
}

/* step(state, tau, mode=TORQUE_SATURATED, command=None) -> Diagnostics, or NotImplemented
 * where the period is not one kernel call. command None: tau is the caller's torque vector
 * (NotImplemented unless plain_torques), the command a copy of it; else tau is what the
 * kernel takes for mode, checked by the caller (Simulator._control_period). */
static PyObject *period_step(ControlPeriodObject *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs < 2 || nargs > 4) {
        PyErr_Format(PyExc_TypeError, "ControlPeriod.step takes 2 to 4 arguments (%zd given)",
                     nargs);
        return NULL;
    }
    PyObject *state = args[0], *tau = args[1];
    long long mode = TORQUE_SATURATED;
    if (nargs > 2 && (mode = PyLong_AsLongLong(args[2])) == -1 && PyErr_Occurred()) return NULL;
    PyObject *command = nargs > 3 ? args[3] : Py_None;
    int one = one_kernel(self, state);
    if (one < 0) return NULL;
    if (!one || (command == Py_None && !plain_torques(tau, self->n_joints)))
        Py_RETURN_NOTIMPLEMENTED;
    double t0 = seconds();
    PyObject *steps = PyTuple_GET_ITEM(self->sets, self->next);
    PyObject *buffers = PySequence_Check(steps) ? PySequence_GetItem(steps, 0) : NULL;
    if (!buffers || !PyTuple_Check(buffers) || PyTuple_GET_SIZE(buffers) != 3 ||
        !PyTuple_Check(PyTuple_GET_ITEM(buffers, 2))) {
        Py_XDECREF(buffers);
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_TypeError,
                            "ControlPeriod: a report set holds (report, "
                            "is_active, views) per physics step");
        return NULL;
    }
    /* the command: a copy of the caller's torques, taken before the step */
#ifdef STARLETH_NUMPY_C_API
    PyObject *copy = command == Py_None ? PyArray_NewCopy((PyArrayObject *)tau, NPY_CORDER) : NULL;
#else
    PyObject *copy = NULL; /* (not reached: plain_torques is false) */
#endif
    PyObject *r = NULL, *d = NULL;
    tree_step_result_t res;
    if (command != Py_None || copy)
        r = tree_step_advance(self->tree, state, tau, PyTuple_GET_ITEM(buffers, 0),
                              PyTuple_GET_ITEM(buffers, 1), Py_None, mode, &res);
    if (r)
        d = period_record(self, state, r,
                          (long long[3]){1, res.status != STATUS_CONVERGED, res.opened},
                          PyTuple_GET_ITEM(PyTuple_GET_ITEM(buffers, 2), 0), copy ? copy : command,
                          seconds() - t0, self->no_timings);
    Py_XDECREF(r);
    Py_XDECREF(copy);
    Py_DECREF(buffers);
    return d;
}

static PyObject *period_get_next(ControlPeriodObject *self, void *c) {
    (void)c;
    return PyLong_FromLong(self->next);
}

static int period_set_next(ControlPeriodObject *self, PyObject *v, void *c) {
    (void)c;
    long k = v ? PyLong_AsLong(v) : -1;
    if (k != 0 && k != 1) {
        if (!PyErr_Occurred()) PyErr_SetString(PyExc_ValueError, "next_report is 0 or 1");
        return -1;
    }
    self->next = (int)k;
    return 0;
}

static PyObject *period_get_current(ControlPeriodObject *self, void *c) {
    (void)c;
    PyObject *s = PyTuple_GET_ITEM(self->sets, self->next ^ 1);
    Py_INCREF(s);
    return s;
}

static PyObject *period_get_totals(ControlPeriodObject *self, void *c) {
    (void)c;
    return totals_tuple(self->totals);
}

static int period_set_totals(ControlPeriodObject *self, PyObject *v, void *c) {
    (void)c;
    long long t[3];
    if (!v || !PyArg_ParseTuple(v, "LLL:totals", &t[0], &t[1], &t[2])) {
        if (!PyErr_Occurred()) PyErr_SetString(PyExc_TypeError, "totals cannot be deleted");
        return -1;
    }
    for (int k = 0; k < 3; k++) self->totals[k] = t[k];
    return 0;
}

/* the record's objects: read and written by the Python path of the other periods */
#define OBJECT_FIELD(f)                                                          \
    static PyObject *period_get_##f(ControlPeriodObject *self, void *c) {        \
        (void)c;                                                                 \
        Py_INCREF(self->f);                                                      \
        return self->f;                                                          \
    }                                                                            \
    static int period_set_##f(ControlPeriodObject *self, PyObject *v, void *c) { \
        (void)c;                                                                 \
        if (!v) {                                                                \
            PyErr_SetString(PyExc_TypeError, #f " cannot be deleted");           \
            return -1;                                                           \
        }                                                                        \
        Py_INCREF(v);                                                            \
        Py_SETREF(self->f, v);                                                   \
        return 0;                                                                \
    }
OBJECT_FIELD(impulse)
OBJECT_FIELD(command)
OBJECT_FIELD(diagnostics)
#undef OBJECT_FIELD

static PyGetSetDef period_getset[] = {
    {"next_report", (getter)period_get_next, (setter)period_set_next,
     "the set of report buffers the next period writes (0 or 1)", NULL},
    {"current", (getter)period_get_current, NULL, "the set of report buffers of the last period",
     NULL},
    {"totals", (getter)period_get_totals, (setter)period_set_totals,
     "(physics_steps, nonconverged_steps, loaded_contacts_opened_total) so far", NULL},
    {"impulse", (getter)period_get_impulse, (setter)period_set_impulse,
     "Λ of the last period (nc x 3), summed over its physics steps", NULL},
    {"command", (getter)period_get_command, (setter)period_set_command,
     "the last period's command (None after a reset)", NULL},
    {"diagnostics", (getter)period_get_diagnostics, (setter)period_set_diagnostics,
     "the last period's Diagnostics", NULL},
    {NULL, NULL, NULL, NULL, NULL}};

static PyMethodDef period_methods[] = {
    {"step", (PyCFunction)(void (*)(void))period_step, METH_FASTCALL,
     "step(state, tau, mode=TORQUE_SATURATED, command=None) -> Diagnostics, or NotImplemented "
     "where the period is not one kernel call."},
    {"finish", (PyCFunction)(void (*)(void))period_finish, METH_FASTCALL,
     "finish(state, figures, impulse, command, wall, timings) -> Diagnostics: the record after "
     "a period of the Python path (figures: its physics steps' TreeStepResults)."},
    {NULL, NULL, 0, NULL}};

PyTypeObject ControlPeriodType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "starleth_sim.physics._kernels.ControlPeriod",
    .tp_basicsize = sizeof(ControlPeriodObject),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
    .tp_doc =
        "ControlPeriod(sets, period, n_joints, tree, persistent, diagnostics_type, "
        "no_timings, log_step): what a Simulator's last control period left, and a "
        "period of one physics step of a tree in one call (step).",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)period_init,
    .tp_dealloc = (destructor)period_dealloc,
    .tp_traverse = (traverseproc)period_traverse,
    .tp_clear = (inquiry)period_clear,
    .tp_getset = period_getset,
    .tp_methods = period_methods,
};
