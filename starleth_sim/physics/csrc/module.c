/* starleth_sim.physics._kernels: the Python bindings of the C kernels.
 *
 * Each function takes the arguments of the Python function of the same name that
 * starleth_sim.physics documents (numpy arrays, C-contiguous, of float64, int64 or bool,
 * and scalars), checks their kinds, and calls the kernel. Arrays are read through the buffer
 * protocol (no numpy C API: the extension builds with Python's headers alone); the few
 * results that are new arrays are made by numpy.empty. The one-kernel steps, which run for
 * every physics step, check the sizes of everything they touch and release the GIL. Work
 * arrays come from the calling thread's scratch arena, emptied on every call. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <string.h>

#include "step.h"

static PyObject *np_empty; /* numpy.empty */

/* ---------------------------------------------------------------------------------------
 * Arguments
 * ------------------------------------------------------------------------------------- */
enum {
    F64 = 1,      /* float64 array, read */
    I64 = 2,      /* int64 array, read */
    BOOL = 3,     /* bool array, read */
    F64W = 4,     /* float64 array, written */
    I64W = 5,     /* int64 array, written */
    BOOLW = 6,    /* bool array, written */
    FLOAT = 7,    /* a number */
    INT = 8,      /* an integer */
    FLAG = 9,     /* truth value */
    OBJ = 10,     /* any object, as it is */
    F64N = 11,    /* float64 array or None (read and written; NULL when None or empty) */
};

typedef struct {
    const char *name;
    int kind;
} spec_t;

typedef struct {
    void *p;         /* data */
    Py_ssize_t len;  /* number of items */
    int nd;
    Py_ssize_t shape[4];
    double f;
    i64 i;
    PyObject *o;
} val_t;

#define MAX_BUFFERS 48

typedef struct {
    Py_buffer v[MAX_BUFFERS];
    int n;
} held_t;

static void release(held_t *h) {
    for (int k = 0; k < h->n; k++) PyBuffer_Release(&h->v[k]);
    h->n = 0;
}

static int format_ok(const Py_buffer *b, int base) {
    const char *f = b->format ? b->format : "B";
    if (*f == '@' || *f == '=' || *f == '<') f++;
    if (f[0] == 0 || f[1] != 0) return 0;
    switch (base) {
    case F64: return f[0] == 'd' && b->itemsize == 8;
    case I64: return (f[0] == 'l' || f[0] == 'q') && b->itemsize == 8;
    case BOOL: return f[0] == '?' && b->itemsize == 1;
    }
    return 0;
}

static const char *kind_name(int base) {
    return base == F64 ? "float64" : base == I64 ? "int64" : "bool";
}

/* An array argument into v (its buffer kept in h); 0 with an exception set on error. */
static int get_array(PyObject *o, int kind, const char *fn, const char *name, held_t *h,
                     val_t *v) {
    int writable = kind == F64W || kind == I64W || kind == BOOLW || kind == F64N;
    int base = (kind == F64 || kind == F64W || kind == F64N) ? F64
               : (kind == I64 || kind == I64W)               ? I64
                                                             : BOOL;
    if (h->n >= MAX_BUFFERS) {
        PyErr_Format(PyExc_RuntimeError, "%s: too many arrays", fn);
        return 0;
    }
    Py_buffer *b = &h->v[h->n];
    int flags = PyBUF_FORMAT | PyBUF_C_CONTIGUOUS | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(o, b, flags) != 0) {
        PyErr_Clear();
        PyErr_Format(PyExc_ValueError,
                     "%s: %s must be a C-contiguous%s numpy array of %s, got %.100s", fn, name,
                     writable ? ", writeable" : "", kind_name(base), Py_TYPE(o)->tp_name);
        return 0;
    }
    h->n++;
    if (!format_ok(b, base)) {
        PyErr_Format(PyExc_ValueError, "%s: %s must be an array of %s (format '%s')", fn, name,
                     kind_name(base), b->format ? b->format : "B");
        return 0;
    }
    if (b->ndim > 4) {
        PyErr_Format(PyExc_ValueError, "%s: %s has more than 4 dimensions", fn, name);
        return 0;
    }
    v->p = b->buf;
    v->len = b->itemsize ? b->len / b->itemsize : 0;
    v->nd = b->ndim;
    for (int k = 0; k < b->ndim; k++) v->shape[k] = b->shape[k];
    return 1;
}

/* Parses the positional arguments args[0:nargs] by spec (the first n_required required, the
 * others keep the defaults the caller put into vals). */
static int parse(PyObject *const *args, Py_ssize_t nargs, const char *fn, const spec_t *spec,
                 int n_spec, int n_required, val_t *vals, held_t *h) {
    if (nargs < n_required || nargs > n_spec) {
        PyErr_Format(PyExc_TypeError, "%s takes %d%s arguments (%zd given)", fn, n_required,
                     n_required == n_spec ? "" : " or more", nargs);
        return 0;
    }
    for (Py_ssize_t k = 0; k < nargs; k++) {
        PyObject *o = args[k];
        val_t *v = &vals[k];
        const char *name = spec[k].name;
        switch (spec[k].kind) {
        case FLOAT:
            v->f = PyFloat_AsDouble(o);
            if (v->f == -1.0 && PyErr_Occurred()) {
                PyErr_Format(PyExc_TypeError, "%s: %s must be a number", fn, name);
                return 0;
            }
            break;
        case INT: {
            PyObject *idx = PyNumber_Index(o);
            if (!idx) {
                PyErr_Format(PyExc_TypeError, "%s: %s must be an integer", fn, name);
                return 0;
            }
            v->i = PyLong_AsLongLong(idx);
            Py_DECREF(idx);
            if (v->i == -1 && PyErr_Occurred()) return 0;
            break;
        }
        case FLAG: {
            int t = PyObject_IsTrue(o);
            if (t < 0) return 0;
            v->i = t;
            break;
        }
        case OBJ:
            v->o = o;
            break;
        case F64N:
            if (o == Py_None) {
                v->p = NULL;
                v->len = 0;
                break;
            }
            if (!get_array(o, F64N, fn, name, h, v)) return 0;
            if (v->len == 0) v->p = NULL;
            break;
        default:
            if (!get_array(o, spec[k].kind, fn, name, h, v)) return 0;
        }
    }
    return 1;
}

#define PARSE(fn, spec, n_required, vals, h)                                                  \
    parse(args, nargs, fn, spec, (int)(sizeof(spec) / sizeof(spec[0])), n_required, vals, h)

static int need(int ok, const char *fn, const char *what) {
    if (!ok) PyErr_Format(PyExc_ValueError, "%s: %s", fn, what);
    return ok;
}

/* A new numpy array of n items (kind F64 or I64) copied from data, 1-d */
static PyObject *new_array(const void *data, int base, Py_ssize_t n) {
    PyObject *arr = PyObject_CallFunction(np_empty, "(n)s", n, base == F64 ? "float64" : "int64");
    if (!arr) return NULL;
    Py_buffer b;
    if (PyObject_GetBuffer(arr, &b, PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS) != 0) {
        Py_DECREF(arr);
        return NULL;
    }
    if (n) memcpy(b.buf, data, (size_t)n * 8);
    PyBuffer_Release(&b);
    return arr;
}

/* the reshaped view arr.reshape(shape) (a new reference; arr's reference is taken) */
static PyObject *reshaped(PyObject *arr, Py_ssize_t r, Py_ssize_t c) {
    if (!arr) return NULL;
    PyObject *out = PyObject_CallMethod(arr, "reshape", "(nn)", r, c);
    Py_DECREF(arr);
    return out;
}

static PyObject *pair_of_arrays(const i64 *ptr, Py_ssize_t n_ptr, const i64 *idx, Py_ssize_t n_idx) {
    PyObject *a = new_array(ptr, I64, n_ptr);
    PyObject *b = a ? new_array(idx, I64, n_idx) : NULL;
    if (!b) {
        Py_XDECREF(a);
        return NULL;
    }
    return Py_BuildValue("(NN)", a, b);
}

/* The settings: a StepSettings (19 fields) or a prox.ProxSettings (8 fields) */
static int get_settings(PyObject *o, const char *fn, settings_t *s) {
    PyObject *seq = PySequence_Fast(o, "settings must be a sequence");
    if (!seq) return 0;
    Py_ssize_t n = PySequence_Fast_GET_SIZE(seq);
    PyObject **it = PySequence_Fast_ITEMS(seq);
    double f[19];
    int ok = n == 19 || n == 8;
    for (Py_ssize_t k = 0; ok && k < n; k++) {
        f[k] = PyFloat_AsDouble(it[k]);
        if (f[k] == -1.0 && PyErr_Occurred()) ok = 0;
    }
    Py_DECREF(seq);
    if (!ok) {
        PyErr_Clear();
        PyErr_Format(PyExc_ValueError,
                     "%s: settings must be the 19 numbers of a StepSettings or the 8 of a "
                     "ProxSettings",
                     fn);
        return 0;
    }
    memset(s, 0, sizeof(*s));
    if (n == 19) {
        settings_from_fields(f, s);
    } else { /* form, scheme, tol_rel, tol_abs, max_iterations, criterion, direct, alpha */
        s->form = (i64)f[0];
        s->scheme = (i64)f[1];
        s->tol_rel = f[2];
        s->tol_abs = f[3];
        s->max_iterations = (i64)f[4];
        s->criterion = (i64)f[5];
        s->bilateral_direct = f[6] != 0.0;
        s->alpha = f[7];
    }
    if (s->form != FORM_DELASSUS && s->form != FORM_VELOCITY) {
        PyErr_Format(PyExc_ValueError, "%s: settings: unknown form %lld", fn, (long long)s->form);
        return 0;
    }
    return 1;
}

/* A prox.Patterns (7 arrays of int64) */
static int get_patterns(PyObject *o, const char *fn, held_t *h, patterns_t *pat) {
    static const char *names[7] = {"wp_ptr", "wp_idx", "mp_ptr", "mp_idx",
                                   "gp_ptr", "gp_idx", "lb_first"};
    PyObject *seq = PySequence_Fast(o, "patterns must be a sequence");
    if (!seq) return 0;
    if (PySequence_Fast_GET_SIZE(seq) != 7) {
        Py_DECREF(seq);
        PyErr_Format(PyExc_ValueError, "%s: pat must be a prox.Patterns (7 arrays)", fn);
        return 0;
    }
    const i64 *p[7];
    Py_ssize_t n_lb = 0;
    for (int k = 0; k < 7; k++) {
        val_t v;
        if (!get_array(PySequence_Fast_GET_ITEM(seq, k), I64, fn, names[k], h, &v)) {
            Py_DECREF(seq);
            return 0;
        }
        p[k] = v.p;
        if (k == 6) n_lb = v.len;
    }
    Py_DECREF(seq);
    pat->wp_ptr = p[0];
    pat->wp_idx = p[1];
    pat->mp_ptr = p[2];
    pat->mp_idx = p[3];
    pat->gp_ptr = p[4];
    pat->gp_idx = p[5];
    pat->lb_first = p[6];
    pat->n_lb = n_lb;
    return 1;
}

static int get_law(PyObject *o, const char *fn, compliant_law_t *law) {
    PyObject *seq = PySequence_Fast(o, "law must be a sequence");
    if (!seq) return 0;
    double f[6];
    int ok = PySequence_Fast_GET_SIZE(seq) == 6;
    for (int k = 0; ok && k < 6; k++) {
        f[k] = PyFloat_AsDouble(PySequence_Fast_GET_ITEM(seq, k));
        if (f[k] == -1.0 && PyErr_Occurred()) ok = 0;
    }
    Py_DECREF(seq);
    if (!ok) {
        PyErr_Clear();
        PyErr_Format(PyExc_ValueError, "%s: law must be the 6 numbers of a CompliantLaw", fn);
        return 0;
    }
    law->mu = f[0];
    law->c_N = f[1];
    law->d_N = f[2];
    law->c_T = f[3];
    law->d_T = f[4];
    law->slip_velocity = f[5];
    return 1;
}

/* Runs the code (the macro's last arguments) without the GIL, with the scratch arena `a`
 * reset and its out-of-memory jump set; `failed` becomes 1 when memory ran out. */
#define RUN_NOGIL(a, failed, ...)                                                             \
    do {                                                                                      \
        jmp_buf jb_;                                                                          \
        arena_reset(a);                                                                       \
        (a)->oom = &jb_;                                                                      \
        PyThreadState *ts_ = PyEval_SaveThread();                                             \
        if (setjmp(jb_) == 0) {                                                               \
            __VA_ARGS__;                                                                      \
        } else {                                                                              \
            failed = 1;                                                                       \
        }                                                                                     \
        PyEval_RestoreThread(ts_);                                                            \
        (a)->oom = NULL;                                                                      \
    } while (0)

/* the same with the GIL held (short kernels) */
#define RUN(a, failed, ...)                                                                   \
    do {                                                                                      \
        jmp_buf jb_;                                                                          \
        arena_reset(a);                                                                       \
        (a)->oom = &jb_;                                                                      \
        if (setjmp(jb_) == 0) {                                                               \
            __VA_ARGS__;                                                                      \
        } else {                                                                              \
            failed = 1;                                                                       \
        }                                                                                     \
        (a)->oom = NULL;                                                                      \
    } while (0)

#define FN(name)                                                                              \
    static PyObject *py_##name(PyObject *self __attribute__((unused)), PyObject *const *args,   \
                               Py_ssize_t nargs)
#define DONE_NONE                                                                             \
    release(&h);                                                                              \
    if (failed) return PyErr_NoMemory();                                                      \
    Py_RETURN_NONE
#define FAIL                                                                                  \
    do {                                                                                      \
        release(&h);                                                                          \
        return NULL;                                                                          \
    } while (0)

/* The tree's arrays (kinematics.KinematicTree); sizes from parent / jtype (nj) */
static int tree_of(const char *fn, const val_t *parent, const val_t *jtype, const val_t *axis,
                   const val_t *pl_R, const val_t *pl_p, const val_t *idx_q,
                   const val_t *idx_v, const val_t *support, i64 nv, tree_t *t) {
    i64 nj = jtype->len;
    if (!need((!parent || parent->len == nj) && (!axis || axis->len == 3 * nj) &&
                  (!pl_R || pl_R->len == 9 * nj) && (!pl_p || pl_p->len == 3 * nj) &&
                  (!idx_q || idx_q->len == nj) && (!idx_v || idx_v->len == nj) &&
                  (!support || support->len == nj * nj),
              fn, "the tree's arrays do not have one entry per joint"))
        return 0;
    t->nj = nj;
    t->nv = nv;
    t->parent = parent ? parent->p : NULL;
    t->jtype = jtype->p;
    t->axis = axis ? axis->p : NULL;
    t->pl_R = pl_R ? pl_R->p : NULL;
    t->pl_p = pl_p ? pl_p->p : NULL;
    t->idx_q = idx_q ? idx_q->p : NULL;
    t->idx_v = idx_v ? idx_v->p : NULL;
    t->support = support ? support->p : NULL;
    return 1;
}

static int frames_of(const char *fn, const val_t *oR, const val_t *op, i64 nj, frames_t *f) {
    if (!need((!oR || oR->len == 9 * nj) && (!op || op->len == 3 * nj), fn,
              "oR / op must have one entry per joint"))
        return 0;
    f->oR = oR ? oR->p : NULL;
    f->op = op ? op->p : NULL;
    return 1;
}

/* ---------------------------------------------------------------------------------------
 * linalg
 * ------------------------------------------------------------------------------------- */
FN(ltdl) {
    static const spec_t spec[] = {{"A", F64}, {"dof_parent", I64}, {"L", F64W}};
    val_t v[3];
    held_t h = {.n = 0};
    if (!PARSE("ltdl", spec, 3, v, &h)) FAIL;
    i64 n = v[1].len;
    if (!need(v[0].len == n * n && v[2].len == n * n, "ltdl", "A and L must be n x n")) FAIL;
    int ok = ltdl(v[0].p, n, v[1].p, v[2].p);
    release(&h);
    return PyBool_FromLong(ok);
}

FN(ltdl_solve_vec) {
    static const spec_t spec[] = {{"L", F64}, {"dof_parent", I64}, {"b", F64W}};
    val_t v[3];
    held_t h = {.n = 0};
    if (!PARSE("ltdl_solve_vec", spec, 3, v, &h)) FAIL;
    i64 n = v[2].len;
    if (!need(v[0].len == n * n && v[1].len == n, "ltdl_solve_vec", "sizes do not match")) FAIL;
    ltdl_solve_vec(v[0].p, n, v[1].p, v[2].p);
    release(&h);
    Py_RETURN_NONE;
}

FN(ltdl_solve_cols) {
    static const spec_t spec[] = {{"L", F64}, {"dof_parent", I64}, {"B", F64W}};
    val_t v[3];
    held_t h = {.n = 0};
    volatile int failed = 0;
    if (!PARSE("ltdl_solve_cols", spec, 3, v, &h)) FAIL;
    i64 n = v[1].len;
    if (!need(v[2].nd == 2 && v[2].shape[0] == n && v[0].len == n * n, "ltdl_solve_cols",
              "B must be n x m and L n x n"))
        FAIL;
    arena_t *a = scratch_arena();
    RUN(a, failed, ltdl_solve_cols(v[0].p, v[1].p, v[2].p, n, v[2].shape[1], a));
    DONE_NONE;
}

FN(ltdl_solve_cols_pattern) {
    static const spec_t spec[] = {
        {"L", F64}, {"dof_parent", I64}, {"B", F64W}, {"ptr", I64}, {"idx", I64}};
    val_t v[5];
    held_t h = {.n = 0};
    volatile int failed = 0;
    if (!PARSE("ltdl_solve_cols_pattern", spec, 5, v, &h)) FAIL;
    i64 n = v[1].len;
    if (!need(v[2].nd == 2 && v[2].shape[0] == n && v[0].len == n * n &&
                  v[3].len == v[2].shape[1] + 1,
              "ltdl_solve_cols_pattern", "B must be n x m, L n x n and ptr m + 1 long"))
        FAIL;
    i64 m = v[2].shape[1];
    i64 *ptr = NULL, *idx = NULL;
    arena_t *a = scratch_arena();
    RUN(a, failed, ltdl_solve_cols_pattern(v[0].p, v[1].p, v[2].p, n, m, v[3].p, v[4].p, a, &ptr, &idx));
    release(&h);
    if (failed) return PyErr_NoMemory();
    return pair_of_arrays(ptr, m + 1, idx, ptr[m]);
}

FN(cholesky_upper_input) {
    static const spec_t spec[] = {{"A", F64}, {"o", INT}, {"L", F64W}, {"first", I64W}};
    val_t v[4];
    held_t h = {.n = 0};
    if (!PARSE("cholesky_upper_input", spec, 4, v, &h)) FAIL;
    i64 nA = v[0].nd == 2 ? v[0].shape[0] : 0, n = nA - v[1].i;
    if (!need(v[0].nd == 2 && v[0].shape[1] == nA && n >= 0 && v[2].len == n * n &&
                  v[3].len == n,
              "cholesky_upper_input", "A must be square, L (n x n) and first (n) for its block"))
        FAIL;
    int ok = cholesky_upper_input(v[0].p, nA, v[1].i, v[2].p, v[3].p);
    release(&h);
    return PyBool_FromLong(ok);
}

FN(cholesky_solve_vec) {
    static const spec_t spec[] = {{"L", F64}, {"first", I64}, {"b", F64W}};
    val_t v[3];
    held_t h = {.n = 0};
    if (!PARSE("cholesky_solve_vec", spec, 3, v, &h)) FAIL;
    i64 n = v[2].len;
    if (!need(v[0].len == n * n && v[1].len == n, "cholesky_solve_vec", "sizes do not match")) FAIL;
    cholesky_solve_vec(v[0].p, n, v[1].p, v[2].p);
    release(&h);
    Py_RETURN_NONE;
}

FN(envelope_columns) {
    static const spec_t spec[] = {{"first", I64}};
    val_t v[1];
    held_t h = {.n = 0};
    volatile int failed = 0;
    if (!PARSE("envelope_columns", spec, 1, v, &h)) FAIL;
    i64 n = v[0].len;
    i64 *ptr = NULL, *idx = NULL;
    arena_t *a = scratch_arena();
    RUN(a, failed, envelope_columns(v[0].p, n, a, &ptr, &idx));
    release(&h);
    if (failed) return PyErr_NoMemory();
    return pair_of_arrays(ptr, n + 1, idx, ptr[n]);
}

FN(cholesky_solve_envelope) {
    static const spec_t spec[] = {
        {"L", F64}, {"first", I64}, {"col_ptr", I64}, {"col_idx", I64}, {"b", F64W}};
    val_t v[5];
    held_t h = {.n = 0};
    if (!PARSE("cholesky_solve_envelope", spec, 5, v, &h)) FAIL;
    i64 n = v[4].len;
    if (!need(v[0].len == n * n && v[1].len == n && v[2].len == n + 1,
              "cholesky_solve_envelope", "sizes do not match"))
        FAIL;
    cholesky_solve_envelope(v[0].p, n, v[1].p, v[2].p, v[3].p, v[4].p);
    release(&h);
    Py_RETURN_NONE;
}

/* ---------------------------------------------------------------------------------------
 * kinematics, dynamics, forest
 * ------------------------------------------------------------------------------------- */
FN(quat_xyzw_to_rot) {
    static const spec_t spec[] = {{"x", FLOAT}, {"y", FLOAT}, {"z", FLOAT}, {"w", FLOAT}, {"R", F64W}};
    val_t v[5];
    held_t h = {.n = 0};
    if (!PARSE("quat_xyzw_to_rot", spec, 5, v, &h)) FAIL;
    if (!need(v[4].len == 9, "quat_xyzw_to_rot", "R must be 3 x 3")) FAIL;
    quat_xyzw_to_rot(v[0].f, v[1].f, v[2].f, v[3].f, v[4].p);
    release(&h);
    Py_RETURN_NONE;
}

FN(quat_rot) {
    static const spec_t spec[] = {{"q", F64}, {"iq", INT}, {"R", F64W}};
    val_t v[3];
    held_t h = {.n = 0};
    if (!PARSE("quat_rot", spec, 3, v, &h)) FAIL;
    if (!need(v[2].len == 9 && v[1].i >= 0 && v[1].i + 7 <= v[0].len, "quat_rot",
              "R must be 3 x 3 and q[iq:iq + 7] a root's coordinates"))
        FAIL;
    quat_rot(v[0].p, v[1].i, v[2].p);
    release(&h);
    Py_RETURN_NONE;
}

FN(forward_kinematics) {
    static const spec_t spec[] = {{"q", F64},     {"parent", I64}, {"jtype", I64},
                                  {"axis", F64},  {"pl_R", F64},   {"pl_p", F64},
                                  {"idx_q", I64}, {"oR", F64W},    {"op", F64W}};
    val_t v[9];
    held_t h = {.n = 0};
    tree_t t;
    frames_t f;
    if (!PARSE("forward_kinematics", spec, 9, v, &h)) FAIL;
    if (!tree_of("forward_kinematics", &v[1], &v[2], &v[3], &v[4], &v[5], &v[6], NULL, NULL, 0, &t) ||
        !frames_of("forward_kinematics", &v[7], &v[8], t.nj, &f))
        FAIL;
    forward_kinematics(v[0].p, &t, &f);
    release(&h);
    Py_RETURN_NONE;
}

FN(point_jacobian) {
    static const spec_t spec[] = {{"j", INT},     {"p", F64},       {"jtype", I64},
                                  {"axis", F64},  {"idx_v", I64},   {"support", BOOL},
                                  {"oR", F64},    {"op", F64},      {"out", F64W},
                                  {"zero", FLAG}};
    val_t v[10];
    v[9].i = 1;
    held_t h = {.n = 0};
    tree_t t;
    frames_t f;
    if (!PARSE("point_jacobian", spec, 9, v, &h)) FAIL;
    i64 nv = v[8].nd == 2 ? v[8].shape[1] : 0;
    if (!need(v[8].nd == 2 && v[8].shape[0] == 3 && v[1].len == 3, "point_jacobian",
              "out must be 3 x nv and p a 3-vector") ||
        !tree_of("point_jacobian", NULL, &v[2], &v[3], NULL, NULL, NULL, &v[4], &v[5], nv, &t) ||
        !frames_of("point_jacobian", &v[6], &v[7], t.nj, &f) ||
        !need(v[0].i >= 0 && v[0].i < t.nj, "point_jacobian", "j is not a joint"))
        FAIL;
    point_jacobian(v[0].i, v[1].p, &t, &f, v[8].p, (int)v[9].i);
    release(&h);
    Py_RETURN_NONE;
}

FN(angular_jacobian) {
    static const spec_t spec[] = {{"j", INT},       {"jtype", I64}, {"axis", F64},
                                  {"idx_v", I64},   {"support", BOOL}, {"oR", F64},
                                  {"out", F64W},    {"zero", FLAG}};
    val_t v[8];
    v[7].i = 1;
    held_t h = {.n = 0};
    tree_t t;
    if (!PARSE("angular_jacobian", spec, 7, v, &h)) FAIL;
    i64 nv = v[6].nd == 2 ? v[6].shape[1] : 0;
    if (!need(v[6].nd == 2 && v[6].shape[0] == 3, "angular_jacobian", "out must be 3 x nv") ||
        !tree_of("angular_jacobian", NULL, &v[1], &v[2], NULL, NULL, NULL, &v[3], &v[4], nv, &t) ||
        !need(v[5].len == 9 * t.nj && v[0].i >= 0 && v[0].i < t.nj, "angular_jacobian",
              "oR must have one entry per joint and j be a joint"))
        FAIL;
    angular_jacobian(v[0].i, &t, v[5].p, v[6].p, (int)v[7].i);
    release(&h);
    Py_RETURN_NONE;
}

static int contacts_of(const char *fn, const val_t *c_joint, const val_t *c_local,
                       const val_t *c_radius, contact_points_t *c) {
    i64 nc = c_joint->len;
    if (!need(c_local->len == 3 * nc && c_radius->len == nc, fn,
              "c_joint, c_local and c_radius must have one entry per contact"))
        return 0;
    c->nc = nc;
    c->joint = c_joint->p;
    c->local = c_local->p;
    c->radius = c_radius->p;
    return 1;
}

static int ground_of(const char *fn, const val_t *n, const val_t *t1, const val_t *t2,
                     double offset, ground_t *g) {
    if (!need(n->len == 3 && t1->len == 3 && t2->len == 3, fn, "the ground's n, t1, t2 must be 3-vectors"))
        return 0;
    g->n = n->p;
    g->t1 = t1->p;
    g->t2 = t2->p;
    g->offset = offset;
    return 1;
}

static int contact_outputs(const char *fn, const val_t *gap, const val_t *position,
                           const val_t *Wt, i64 nc, i64 nv) {
    return need(gap->len == nc && position->len == 3 * nc && Wt->len == 3 * nc * nv, fn,
                "gap (nc), position (nc x 3) and Wt (nc x 3 x nv) do not match the contacts");
}

FN(contact_points) {
    static const spec_t spec[] = {
        {"parent", I64},   {"jtype", I64},       {"axis", F64},      {"idx_v", I64},
        {"support", BOOL}, {"oR", F64},          {"op", F64},        {"c_joint", I64},
        {"c_local", F64},  {"c_radius", F64},    {"normal", F64},    {"tangent1", F64},
        {"tangent2", F64}, {"ground_offset", FLOAT}, {"jacobian_gap", FLOAT}, {"gap", F64W},
        {"position", F64W}, {"Wt", F64W}};
    val_t v[18];
    held_t h = {.n = 0};
    tree_t t;
    frames_t f;
    contact_points_t c;
    ground_t g;
    if (!PARSE("contact_points", spec, 18, v, &h)) FAIL;
    i64 nv = v[17].nd == 3 ? v[17].shape[2] : 0;
    if (!tree_of("contact_points", &v[0], &v[1], &v[2], NULL, NULL, NULL, &v[3], &v[4], nv, &t) ||
        !frames_of("contact_points", &v[5], &v[6], t.nj, &f) ||
        !contacts_of("contact_points", &v[7], &v[8], &v[9], &c) ||
        !ground_of("contact_points", &v[10], &v[11], &v[12], v[13].f, &g) ||
        !contact_outputs("contact_points", &v[15], &v[16], &v[17], c.nc, nv))
        FAIL;
    contact_points(&t, &f, &c, &g, v[14].f, v[15].p, v[16].p, v[17].p);
    release(&h);
    Py_RETURN_NONE;
}

FN(contact_kinematics) {
    static const spec_t spec[] = {
        {"q", F64},        {"parent", I64},     {"jtype", I64},     {"axis", F64},
        {"pl_R", F64},     {"pl_p", F64},       {"idx_q", I64},     {"idx_v", I64},
        {"support", BOOL}, {"oR", F64W},        {"op", F64W},       {"c_joint", I64},
        {"c_local", F64},  {"c_radius", F64},   {"normal", F64},    {"tangent1", F64},
        {"tangent2", F64}, {"ground_offset", FLOAT}, {"jacobian_gap", FLOAT}, {"gap", F64W},
        {"position", F64W}, {"Wt", F64W}};
    val_t v[22];
    held_t h = {.n = 0};
    tree_t t;
    frames_t f;
    contact_points_t c;
    ground_t g;
    if (!PARSE("contact_kinematics", spec, 22, v, &h)) FAIL;
    i64 nv = v[21].nd == 3 ? v[21].shape[2] : 0;
    if (!tree_of("contact_kinematics", &v[1], &v[2], &v[3], &v[4], &v[5], &v[6], &v[7], &v[8], nv, &t) ||
        !frames_of("contact_kinematics", &v[9], &v[10], t.nj, &f) ||
        !contacts_of("contact_kinematics", &v[11], &v[12], &v[13], &c) ||
        !ground_of("contact_kinematics", &v[14], &v[15], &v[16], v[17].f, &g) ||
        !contact_outputs("contact_kinematics", &v[19], &v[20], &v[21], c.nc, nv))
        FAIL;
    contact_kinematics(v[0].p, &t, &f, &c, &g, v[18].f, v[19].p, v[20].p, v[21].p);
    release(&h);
    Py_RETURN_NONE;
}

FN(integrate_forest) {
    static const spec_t spec[] = {{"q", F64},     {"u", F64},     {"dt", FLOAT}, {"jtype", I64},
                                  {"idx_q", I64}, {"idx_v", I64}, {"out", F64W}};
    val_t v[7];
    held_t h = {.n = 0};
    tree_t t;
    if (!PARSE("integrate_forest", spec, 7, v, &h)) FAIL;
    if (!tree_of("integrate_forest", NULL, &v[3], NULL, NULL, NULL, &v[4], &v[5], NULL, v[1].len, &t) ||
        !need(v[6].len == v[0].len, "integrate_forest", "out must have q's length"))
        FAIL;
    integrate_forest(v[0].p, v[1].p, v[2].f, &t, v[6].p);
    release(&h);
    Py_RETURN_NONE;
}

FN(to_pin_velocity) {
    static const spec_t spec[] = {{"q", F64},      {"u", F64},   {"roots", OBJ}, {"root_q", I64},
                                  {"root_v", I64}, {"Rs", F64W}, {"u_pin", F64W}};
    val_t v[7];
    held_t h = {.n = 0};
    if (!PARSE("to_pin_velocity", spec, 7, v, &h)) FAIL;
    i64 nr = v[3].len;
    if (!need(v[4].len == nr && v[5].len == 9 * nr && v[6].len == v[1].len, "to_pin_velocity",
              "sizes do not match"))
        FAIL;
    to_pin_velocity(v[0].p, v[1].p, v[1].len, nr, v[3].p, v[4].p, v[5].p, v[6].p);
    release(&h);
    Py_RETURN_NONE;
}

FN(from_pin_dynamics) {
    static const spec_t spec[] = {{"M_pin", F64},  {"h_pin", F64}, {"Rs", F64}, {"root_v", I64},
                                  {"u_pin", F64},  {"M", F64W},    {"h", F64W}};
    val_t v[7];
    held_t h = {.n = 0};
    if (!PARSE("from_pin_dynamics", spec, 7, v, &h)) FAIL;
    i64 n = v[1].len, nr = v[3].len;
    if (!need(v[0].len == n * n && v[5].len == n * n && v[6].len == n && v[2].len == 9 * nr,
              "from_pin_dynamics", "sizes do not match"))
        FAIL;
    from_pin_dynamics(v[0].p, v[1].p, n, v[2].p, nr, v[3].p, v[4].p, v[5].p, v[6].p);
    release(&h);
    Py_RETURN_NONE;
}

static int inertias_of(const char *fn, const val_t *mass, const val_t *lever,
                       const val_t *inertia, const val_t *gravity, i64 nj, inertias_t *b) {
    if (!need(mass->len == nj && lever->len == 3 * nj && inertia->len == 9 * nj &&
                  gravity->len == 3,
              fn, "mass, lever, inertia and gravity do not match the joints"))
        return 0;
    b->mass = mass->p;
    b->lever = lever->p;
    b->inertia = inertia->p;
    b->gravity = gravity->p;
    return 1;
}

FN(tree_dynamics) {
    static const spec_t spec[] = {
        {"q", F64},      {"u", F64},      {"parent", I64},  {"jtype", I64},  {"axis", F64},
        {"pl_R", F64},   {"pl_p", F64},   {"idx_q", I64},   {"idx_v", I64},  {"oR", F64W},
        {"op", F64W},    {"mass", F64},   {"lever", F64},   {"inertia", F64}, {"gravity", F64},
        {"M", F64W},     {"h", F64W}};
    val_t v[17];
    held_t h = {.n = 0};
    tree_t t;
    frames_t f;
    inertias_t b;
    if (!PARSE("tree_dynamics", spec, 17, v, &h)) FAIL;
    i64 nv = v[1].len;
    if (!tree_of("tree_dynamics", &v[2], &v[3], &v[4], &v[5], &v[6], &v[7], &v[8], NULL, nv, &t) ||
        !frames_of("tree_dynamics", &v[9], &v[10], t.nj, &f) ||
        !inertias_of("tree_dynamics", &v[11], &v[12], &v[13], &v[14], t.nj, &b) ||
        !need(v[15].len == nv * nv && v[16].len == nv, "tree_dynamics", "M must be nv x nv, h nv"))
        FAIL;
    tree_dynamics(v[0].p, v[1].p, &t, &f, &b, v[15].p, v[16].p);
    release(&h);
    Py_RETURN_NONE;
}

FN(midpoint_dynamics) {
    static const spec_t spec[] = {
        {"q", F64},         {"u", F64},        {"half_dt", FLOAT}, {"parent", I64},
        {"jtype", I64},     {"axis", F64},     {"pl_R", F64},      {"pl_p", F64},
        {"idx_q", I64},     {"idx_v", I64},    {"support", BOOL},  {"oR", F64W},
        {"op", F64W},       {"mass", F64},     {"lever", F64},     {"inertia", F64},
        {"gravity", F64},   {"c_joint", I64},  {"c_local", F64},   {"c_radius", F64},
        {"normal", F64},    {"tangent1", F64}, {"tangent2", F64},  {"ground_offset", FLOAT},
        {"jacobian_gap", FLOAT}, {"qM", F64W}, {"M", F64W},        {"h", F64W},
        {"gap", F64W},      {"position", F64W}, {"Wt", F64W}};
    val_t v[31];
    held_t h = {.n = 0};
    tree_t t;
    frames_t f;
    inertias_t b;
    contact_points_t c;
    ground_t g;
    if (!PARSE("midpoint_dynamics", spec, 31, v, &h)) FAIL;
    i64 nv = v[1].len;
    if (!tree_of("midpoint_dynamics", &v[3], &v[4], &v[5], &v[6], &v[7], &v[8], &v[9], &v[10], nv, &t) ||
        !frames_of("midpoint_dynamics", &v[11], &v[12], t.nj, &f) ||
        !inertias_of("midpoint_dynamics", &v[13], &v[14], &v[15], &v[16], t.nj, &b) ||
        !contacts_of("midpoint_dynamics", &v[17], &v[18], &v[19], &c) ||
        !ground_of("midpoint_dynamics", &v[20], &v[21], &v[22], v[23].f, &g) ||
        !need(v[25].len == v[0].len && v[26].len == nv * nv && v[27].len == nv,
              "midpoint_dynamics", "qM, M and h do not match q and u") ||
        !contact_outputs("midpoint_dynamics", &v[28], &v[29], &v[30], c.nc, nv))
        FAIL;
    midpoint_dynamics(v[0].p, v[1].p, v[2].f, &t, &f, &b, &c, &g, v[24].f, v[25].p, v[26].p,
                      v[27].p, v[28].p, v[29].p, v[30].p);
    release(&h);
    Py_RETURN_NONE;
}

FN(add_at) {
    static const spec_t spec[] = {{"h", F64W}, {"idx", I64}, {"values", F64}};
    val_t v[3];
    held_t h = {.n = 0};
    if (!PARSE("add_at", spec, 3, v, &h)) FAIL;
    if (!need(v[1].len == v[2].len, "add_at", "idx and values must have one length")) FAIL;
    const i64 *idx = v[1].p;
    for (i64 k = 0; k < v[1].len; k++)
        if (idx[k] < 0 || idx[k] >= v[0].len) {
            release(&h);
            PyErr_SetString(PyExc_IndexError, "add_at: index out of range");
            return NULL;
        }
    add_at(v[0].p, idx, v[2].p, v[1].len);
    release(&h);
    Py_RETURN_NONE;
}

FN(rigid_body_forces) {
    static const spec_t spec[] = {{"q", F64},      {"u", F64},       {"root_q", I64},
                                  {"root_v", I64}, {"mass", F64},    {"inertia", F64},
                                  {"gravity", F64}, {"h", F64W}};
    val_t v[8];
    held_t h = {.n = 0};
    if (!PARSE("rigid_body_forces", spec, 8, v, &h)) FAIL;
    i64 nr = v[3].len;
    if (!need(v[2].len == nr && v[4].len == nr && v[5].len == 9 * nr && v[6].len == 3 &&
                  v[7].len == v[1].len,
              "rigid_body_forces", "sizes do not match"))
        FAIL;
    rigid_body_forces(v[0].p, v[1].p, nr, v[2].p, v[3].p, v[4].p, v[5].p, v[6].p, v[7].p);
    release(&h);
    Py_RETURN_NONE;
}

static int cuts_of(const char *fn, const val_t *P, const val_t *C, const val_t *const *arr,
                   int n_arr, cuts_t *c) {
    i64 ncut = P->len;
    int ok = C->len == ncut;
    for (int k = 0; k < n_arr; k++) ok = ok && (!arr[k] || arr[k]->len == 3 * ncut);
    if (!need(ok, fn, "the cut joints' arrays must have one entry per cut joint")) return 0;
    c->ncut = ncut;
    c->P = P->p;
    c->C = C->p;
    const double **dst[7] = {&c->p_P, &c->p_C, &c->a_P, &c->b1_P, &c->b2_P, &c->a_C, &c->b1_C};
    for (int k = 0; k < 7; k++) *dst[k] = (k < n_arr && arr[k]) ? arr[k]->p : NULL;
    return 1;
}

FN(cut_joints) {
    static const spec_t spec[] = {
        {"q", F64},       {"u", F64},        {"parent", I64},  {"jtype", I64},  {"axis", F64},
        {"pl_R", F64},    {"pl_p", F64},     {"idx_q", I64},   {"idx_v", I64},  {"support", BOOL},
        {"oR", F64W},     {"op", F64W},      {"cut_P", I64},   {"cut_C", I64},  {"p_P", F64},
        {"p_C", F64},     {"a_P", F64},      {"b1_P", F64},    {"b2_P", F64},   {"a_C", F64},
        {"b1_C", F64},    {"Wt_B", F64W},    {"g_B", F64W},    {"angle", F64W}, {"rate", F64W},
        {"axis_world", F64W}, {"do_fk", FLAG}};
    val_t v[27];
    held_t h = {.n = 0};
    volatile int failed = 0;
    tree_t t;
    frames_t f;
    cuts_t c;
    if (!PARSE("cut_joints", spec, 27, v, &h)) FAIL;
    i64 nv = v[1].len;
    const val_t *arrs[7] = {&v[14], &v[15], &v[16], &v[17], &v[18], &v[19], &v[20]};
    if (!tree_of("cut_joints", &v[2], &v[3], &v[4], &v[5], &v[6], &v[7], &v[8], &v[9], nv, &t) ||
        !frames_of("cut_joints", &v[10], &v[11], t.nj, &f) ||
        !cuts_of("cut_joints", &v[12], &v[13], arrs, 7, &c) ||
        !need(v[21].len == 5 * c.ncut * nv && v[22].len == 5 * c.ncut && v[23].len == c.ncut &&
                  v[24].len == c.ncut && v[25].len == 3 * c.ncut,
              "cut_joints", "the outputs do not match the cut joints"))
        FAIL;
    arena_t *a = scratch_arena();
    RUN(a, failed, cut_joints(v[0].p, v[1].p, &t, &f, &c, v[21].p, v[22].p, v[23].p, v[24].p, v[25].p, (int)v[26].i, a));
    DONE_NONE;
}

FN(gather_joint_values) {
    static const spec_t spec[] = {
        {"x", F64}, {"index", I64}, {"cut_values", F64}, {"cut_index", I64}, {"out", F64W}};
    val_t v[5];
    held_t h = {.n = 0};
    if (!PARSE("gather_joint_values", spec, 5, v, &h)) FAIL;
    i64 n = v[4].len;
    if (!need(v[1].len >= n && v[3].len >= n, "gather_joint_values", "index arrays too short")) FAIL;
    gather_joint_values(v[0].p, v[1].p, v[2].p, v[3].p, n, v[4].p);
    release(&h);
    Py_RETURN_NONE;
}

FN(cut_joint_torques) {
    static const spec_t spec[] = {{"tau_cut", F64}, {"cut_P", I64},  {"cut_C", I64},
                                  {"axis_world", F64}, {"jtype", I64}, {"axis", F64},
                                  {"idx_v", I64},   {"support", BOOL}, {"oR", F64},
                                  {"h", F64W}};
    val_t v[10];
    held_t h = {.n = 0};
    volatile int failed = 0;
    tree_t t;
    cuts_t c;
    if (!PARSE("cut_joint_torques", spec, 10, v, &h)) FAIL;
    i64 nv = v[9].len;
    const val_t *arrs[1] = {&v[3]};
    if (!tree_of("cut_joint_torques", NULL, &v[4], &v[5], NULL, NULL, NULL, &v[6], &v[7], nv, &t) ||
        !cuts_of("cut_joint_torques", &v[1], &v[2], arrs, 1, &c) ||
        !need(v[0].len == c.ncut && v[8].len == 9 * t.nj, "cut_joint_torques",
              "tau_cut or oR do not match"))
        FAIL;
    arena_t *a = scratch_arena();
    RUN(a, failed, cut_joint_torques(v[0].p, &c, v[3].p, &t, v[8].p, v[9].p, a));
    DONE_NONE;
}

/* ---------------------------------------------------------------------------------------
 * contact, actuator
 * ------------------------------------------------------------------------------------- */
FN(compliant_contact_forces) {
    static const spec_t spec[] = {{"law", OBJ},      {"gap", F64},     {"position", F64},
                                  {"Wt", F64},       {"u", F64},       {"closed", BOOLW},
                                  {"slip", BOOLW},   {"anchor", F64W}, {"tangent1", F64},
                                  {"tangent2", F64}, {"lam", F64W}};
    val_t v[11];
    held_t h = {.n = 0};
    compliant_law_t law;
    if (!PARSE("compliant_contact_forces", spec, 11, v, &h) || !get_law(v[0].o, "compliant_contact_forces", &law)) FAIL;
    i64 nc = v[1].len, nv = v[4].len;
    if (!need(v[2].len == 3 * nc && v[3].len == 3 * nc * nv && v[5].len == nc && v[6].len == nc &&
                  v[7].len == 3 * nc && v[8].len == 3 && v[9].len == 3 && v[10].len == 3 * nc,
              "compliant_contact_forces", "sizes do not match the contacts"))
        FAIL;
    compliant_contact_forces(&law, nc, nv, v[1].p, v[2].p, v[3].p, v[4].p, v[5].p, v[6].p, v[7].p,
                             v[8].p, v[9].p, v[10].p);
    release(&h);
    Py_RETURN_NONE;
}

FN(generalized_contact_force) {
    static const spec_t spec[] = {{"Wt", F64}, {"lam", F64}, {"out", F64W}};
    val_t v[3];
    held_t h = {.n = 0};
    if (!PARSE("generalized_contact_force", spec, 3, v, &h)) FAIL;
    i64 nc = v[1].len / 3, nv = v[2].len;
    if (!need(v[1].len == 3 * nc && v[0].len == 3 * nc * nv, "generalized_contact_force",
              "sizes do not match"))
        FAIL;
    generalized_contact_force(v[0].p, v[1].p, nc, nv, v[2].p);
    release(&h);
    Py_RETURN_NONE;
}

FN(saturate_torque) {
    static const spec_t spec[] = {
        {"tau", F64}, {"limit", F64}, {"qd", F64}, {"qd_limit", F64}, {"out", F64W}};
    val_t v[5];
    held_t h = {.n = 0};
    if (!PARSE("saturate_torque", spec, 5, v, &h)) FAIL;
    i64 n = v[0].len;
    if (!need(v[1].len >= n && v[2].len >= n && v[3].len >= n && v[4].len >= n,
              "saturate_torque", "limit, qd, qd_limit and out need an entry per torque"))
        FAIL;
    int ok = saturate_torque(v[0].p, v[1].p, v[2].p, v[3].p, v[4].p, n);
    release(&h);
    return PyBool_FromLong(ok);
}

/* ---------------------------------------------------------------------------------------
 * prox
 * ------------------------------------------------------------------------------------- */
static PyObject *pattern_of(PyObject *const *args, Py_ssize_t nargs, int by_columns) {
    const char *fn = by_columns ? "col_pattern" : "row_pattern";
    static const spec_t spec[] = {{"A", F64}};
    val_t v[1];
    held_t h = {.n = 0};
    volatile int failed = 0;
    if (!parse(args, nargs, fn, spec, 1, 1, v, &h)) FAIL;
    if (!need(v[0].nd == 2, fn, "A must be 2-d")) FAIL;
    i64 r = v[0].shape[0], c = v[0].shape[1], n = by_columns ? c : r;
    i64 *ptr = NULL, *idx = NULL;
    arena_t *a = scratch_arena();
    if (by_columns)
        RUN(a, failed, col_pattern(v[0].p, r, c, a, &ptr, &idx));
    else
        RUN(a, failed, row_pattern(v[0].p, r, c, a, &ptr, &idx));
    release(&h);
    if (failed) return PyErr_NoMemory();
    return pair_of_arrays(ptr, n + 1, idx, ptr[n]);
}

FN(row_pattern) { return pattern_of(args, nargs, 0); }
FN(col_pattern) { return pattern_of(args, nargs, 1); }

FN(prox_parameters) {
    static const spec_t spec[] = {{"Gdiag", F64}, {"nc", INT}, {"alpha", FLOAT}, {"r", F64W}};
    val_t v[4];
    held_t h = {.n = 0};
    if (!PARSE("prox_parameters", spec, 4, v, &h)) FAIL;
    i64 m = v[0].len;
    if (!need(v[3].len == m && v[1].i >= 0 && 3 * v[1].i <= m, "prox_parameters",
              "r must have Gdiag's length and 3 nc rows fit")) FAIL;
    prox_parameters(v[0].p, m, v[1].i, v[2].f, v[3].p);
    release(&h);
    Py_RETURN_NONE;
}

FN(delassus) {
    static const spec_t spec[] = {{"Wt", F64},     {"MinvW", F64},  {"G", F64W},  {"wp_ptr", I64},
                                  {"wp_idx", I64}, {"mp_ptr", I64}, {"mp_idx", I64}};
    val_t v[7];
    held_t h = {.n = 0};
    volatile int failed = 0;
    if (!PARSE("delassus", spec, 7, v, &h)) FAIL;
    i64 m = v[0].nd == 2 ? v[0].shape[0] : -1, nv = v[0].nd == 2 ? v[0].shape[1] : -1;
    if (!need(m >= 0 && v[1].len == nv * m && v[2].len == m * m && v[3].len == m + 1 &&
                  v[5].len == m + 1,
              "delassus", "Wt must be m x nv, MinvW nv x m, G m x m, the pointers m + 1"))
        FAIL;
    arena_t *a = scratch_arena();
    RUN(a, failed, delassus(v[0].p, v[1].p, v[2].p, m, nv, v[3].p, v[4].p, v[5].p, v[6].p, a));
    DONE_NONE;
}

FN(delassus_diagonal) {
    static const spec_t spec[] = {
        {"Wt", F64}, {"MinvW", F64}, {"d", F64W}, {"wp_ptr", I64}, {"wp_idx", I64}};
    val_t v[5];
    held_t h = {.n = 0};
    if (!PARSE("delassus_diagonal", spec, 5, v, &h)) FAIL;
    i64 m = v[0].nd == 2 ? v[0].shape[0] : -1, nv = v[0].nd == 2 ? v[0].shape[1] : -1;
    if (!need(m >= 0 && v[1].len == nv * m && v[2].len == m && v[3].len == m + 1,
              "delassus_diagonal", "sizes do not match"))
        FAIL;
    delassus_diagonal(v[0].p, v[1].p, v[2].p, m, nv, v[3].p, v[4].p);
    release(&h);
    Py_RETURN_NONE;
}

/* the sizes of a problem given as arrays: m rows, nv velocities; 0 if they do not match */
static int problem_sizes(const char *fn, const val_t *Wt, const val_t *MinvW, const val_t *G,
                         const settings_t *s, i64 *m, i64 *nv) {
    if (!need(Wt->nd == 2, fn, "Wt must be 2-d")) return 0;
    *m = Wt->shape[0];
    *nv = Wt->shape[1];
    return need(MinvW->len == *nv * *m &&
                    (s->form != FORM_DELASSUS || G->len == *m * *m),
                fn, "Wt (m x nv), MinvW (nv x m) and G (m x m, Delassus form) do not match");
}

FN(auto_spectral_scale) {
    static const spec_t spec[] = {{"s", OBJ},  {"G", F64},   {"Wt", F64}, {"MinvW", F64},
                                  {"pat", OBJ}, {"nc", INT}, {"r", F64}};
    val_t v[7];
    held_t h = {.n = 0};
    volatile int failed = 0;
    settings_t s;
    patterns_t pat;
    i64 m, nv;
    if (!PARSE("auto_spectral_scale", spec, 7, v, &h) ||
        !get_settings(v[0].o, "auto_spectral_scale", &s) ||
        !get_patterns(v[4].o, "auto_spectral_scale", &h, &pat) ||
        !problem_sizes("auto_spectral_scale", &v[2], &v[3], &v[1], &s, &m, &nv) ||
        !need(v[6].len == m && 3 * v[5].i <= m && v[5].i >= 0, "auto_spectral_scale",
              "r must have m entries"))
        FAIL;
    double lam = 0.0;
    arena_t *a = scratch_arena();
    RUN(a, failed, lam = auto_spectral_scale(&s, v[1].p, v[2].p, v[3].p, &pat, m, nv, v[5].i, v[6].p, a));
    release(&h);
    if (failed) return PyErr_NoMemory();
    return PyFloat_FromDouble(lam);
}

FN(prox_solve) {
    static const spec_t spec[] = {{"s", OBJ},      {"pat", OBJ}, {"Wt", F64},   {"MinvW", F64},
                                  {"u_free", F64}, {"bvec", F64}, {"G", F64},   {"c", F64},
                                  {"nc", INT},     {"mu", F64},  {"r", F64},    {"lam", F64W},
                                  {"LB", F64},     {"M", F64},   {"u", F64W}};
    val_t v[15];
    held_t h = {.n = 0};
    volatile int failed = 0;
    settings_t s;
    patterns_t pat;
    i64 m, nv;
    if (!PARSE("prox_solve", spec, 15, v, &h) || !get_settings(v[0].o, "prox_solve", &s) ||
        !get_patterns(v[1].o, "prox_solve", &h, &pat) ||
        !problem_sizes("prox_solve", &v[2], &v[3], &v[6], &s, &m, &nv))
        FAIL;
    i64 nc = v[8].i;
    i64 nb_LB = v[12].nd == 2 ? v[12].shape[0] : 0;
    if (!need(nc >= 0 && 3 * nc <= m && v[4].len == nv && v[5].len == m &&
                  (s.form != FORM_DELASSUS || v[7].len == m) && v[9].len >= nc &&
                  v[10].len == m && v[11].len == m && v[14].len == nv &&
                  (s.criterion != CRITERION_ENERGY || v[13].len == nv * nv) &&
                  (!s.bilateral_direct || m == 3 * nc || (nb_LB == m - 3 * nc && pat.n_lb == nb_LB)),
              "prox_solve", "the arrays do not match the problem's m rows and nv velocities"))
        FAIL;
    prox_result_t res = {0, 0, 0.0};
    arena_t *a = scratch_arena();
    RUN(a, failed, res = prox_solve(&s, &pat, v[2].p, v[3].p, v[4].p, v[5].p, v[6].p, v[7].p, m, nv, nc,
                                    v[9].p, v[10].p, v[11].p, v[12].p, nb_LB, v[13].p, v[14].p, a));
    release(&h);
    if (failed) return PyErr_NoMemory();
    return Py_BuildValue("(LLd)", (long long)res.iterations, (long long)res.status, res.residual);
}

/* ---------------------------------------------------------------------------------------
 * step phases
 * ------------------------------------------------------------------------------------- */
FN(free_velocity) {
    static const spec_t spec[] = {{"h", F64},          {"dt", FLOAT}, {"uS", F64},
                                  {"dof_parent", I64}, {"L", F64},    {"u_free", F64W}};
    val_t v[6];
    held_t h = {.n = 0};
    if (!PARSE("free_velocity", spec, 6, v, &h)) FAIL;
    i64 nv = v[2].len;
    if (!need(v[0].len == nv && v[3].len == nv && v[4].len == nv * nv && v[5].len == nv,
              "free_velocity", "sizes do not match"))
        FAIL;
    free_velocity(v[0].p, v[1].f, v[2].p, nv, v[3].p, v[4].p, v[5].p);
    release(&h);
    Py_RETURN_NONE;
}

FN(constraint_velocity) {
    static const spec_t spec[] = {{"Wt", F64},     {"u_free", F64}, {"bvec", F64},
                                  {"wp_ptr", I64}, {"wp_idx", I64}, {"c", F64W}};
    val_t v[6];
    held_t h = {.n = 0};
    if (!PARSE("constraint_velocity", spec, 6, v, &h)) FAIL;
    i64 m = v[0].nd == 2 ? v[0].shape[0] : -1, nv = v[0].nd == 2 ? v[0].shape[1] : -1;
    if (!need(m >= 0 && v[1].len == nv && v[2].len == m && v[3].len == m + 1 && v[5].len == m,
              "constraint_velocity", "sizes do not match"))
        FAIL;
    constraint_velocity(v[0].p, m, nv, v[1].p, v[2].p, v[3].p, v[4].p, v[5].p);
    release(&h);
    Py_RETURN_NONE;
}

FN(solve_compliant) {
    static const spec_t spec[] = {
        {"law", OBJ},      {"M", F64},        {"h", F64W},      {"uS", F64},     {"dt", FLOAT},
        {"gap", F64},      {"position", F64}, {"Wt_all", F64},  {"closed", BOOLW}, {"slip", BOOLW},
        {"anchor", F64W},  {"t1", F64},       {"t2", F64},      {"lam", F64W},   {"dof_parent", I64},
        {"factor", FLAG},  {"L", F64W},       {"u_free", F64W}, {"timings", F64N}};
    val_t v[19];
    held_t h = {.n = 0};
    compliant_law_t law;
    if (!PARSE("solve_compliant", spec, 19, v, &h) || !get_law(v[0].o, "solve_compliant", &law)) FAIL;
    i64 nv = v[3].len, nc = v[5].len;
    if (!need(v[1].len == nv * nv && v[2].len == nv && v[6].len == 3 * nc &&
                  v[7].len == 3 * nc * nv && v[8].len == nc && v[9].len == nc &&
                  v[10].len == 3 * nc && v[11].len == 3 && v[12].len == 3 && v[13].len == 3 * nc &&
                  v[14].len == nv && v[16].len == nv * nv && v[17].len == nv &&
                  (!v[18].p || v[18].len >= 5),
              "solve_compliant", "sizes do not match"))
        FAIL;
    int ok = solve_compliant(&law, v[1].p, v[2].p, v[3].p, nv, v[4].f, nc, v[5].p, v[6].p, v[7].p,
                             v[8].p, v[9].p, v[10].p, v[11].p, v[12].p, v[13].p, v[14].p,
                             (int)v[15].i, v[16].p, v[17].p, v[18].p);
    release(&h);
    return PyBool_FromLong(ok);
}

FN(end_of_step) {
    static const spec_t spec[] = {{"qM", F64},   {"uE", F64},      {"u_corr", F64},
                                  {"projected", FLAG}, {"half_dt", FLOAT}, {"jtype", I64},
                                  {"idx_q", I64}, {"idx_v", I64},  {"qE", F64W}};
    val_t v[9];
    held_t h = {.n = 0};
    volatile int failed = 0;
    tree_t t;
    if (!PARSE("end_of_step", spec, 9, v, &h)) FAIL;
    i64 nv = v[1].len;
    if (!tree_of("end_of_step", NULL, &v[5], NULL, NULL, NULL, &v[6], &v[7], NULL, nv, &t) ||
        !need(v[2].len == nv && v[8].len == v[0].len, "end_of_step", "sizes do not match"))
        FAIL;
    int ok = 0;
    arena_t *a = scratch_arena();
    RUN(a, failed, ok = end_of_step(v[0].p, v[1].p, v[2].p, (int)v[3].i, v[4].f, &t, v[0].len, v[8].p, a));
    release(&h);
    if (failed) return PyErr_NoMemory();
    return PyBool_FromLong(ok);
}

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

static PyTypeObject ProblemType;

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
    struct { const char *k; PyObject *v; } items[] = {
        {"active", new_array(p->active, I64, p->na)},
        {"Wt", reshaped(new_array(p->Wt, F64, m * nv), m, nv)},
        {"MinvW", reshaped(new_array(p->MinvW, F64, nv * m), nv, m)},
        {"b", new_array(p->b, F64, m)},
        {"G", g ? reshaped(new_array(p->G, F64, m * m), m, m) : reshaped(new_array(NULL, F64, 0), 0, 0)},
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

static PyTypeObject ProblemType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "starleth_sim.physics._kernels.ContactProblem",
    .tp_basicsize = sizeof(ProblemObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "A hard-contact problem prepared ahead (prepare_hard_contacts): the active set, "
              "W^T, M^{-1}W, b, G, L_B and their patterns, in memory of its own.",
    .tp_new = problem_new,
    .tp_dealloc = (destructor)problem_dealloc,
    .tp_getset = problem_getset,
    .tp_methods = problem_methods,
};

/* The sizes shared by the contact-problem kernels */
static int contact_problem_sizes(const char *fn, const val_t *M, const val_t *uS,
                                 const val_t *gap, const val_t *Wt_all, const val_t *WtB,
                                 const val_t *bB, const val_t *eps, const val_t *dof_parent,
                                 const val_t *L, const val_t *last_impulse,
                                 const val_t *last_active, const val_t *timings, i64 *nv,
                                 i64 *nc, i64 *nb) {
    *nv = uS->len;
    *nc = gap->len;
    *nb = bB->len;
    return need(M->len == *nv * *nv && Wt_all->len == 3 * *nc * *nv &&
                    WtB->len == *nb * *nv && eps->len == 2 * *nc && dof_parent->len == *nv &&
                    L->len == *nv * *nv && last_impulse->len == 3 * *nc &&
                    last_active->len == *nc && (!timings->p || timings->len >= 5),
                fn, "the arrays do not match the contacts, bilateral rows and velocities");
}

FN(prepare_hard_contacts) {
    static const spec_t spec[] = {
        {"settings", OBJ}, {"M", F64},          {"uS", F64},          {"gap", F64},
        {"Wt_all", F64},   {"WtB", F64},        {"bB", F64},          {"eps", F64},
        {"dof_parent", I64}, {"factor", FLAG},  {"L", F64W},          {"last_impulse", F64},
        {"last_active", BOOL}, {"timings", F64N}, {"problem", OBJ}};
    val_t v[15];
    v[14].o = Py_None;
    held_t h = {.n = 0};
    volatile int failed = 0;
    settings_t s;
    i64 nv, nc, nb;
    if (!PARSE("prepare_hard_contacts", spec, 14, v, &h) ||
        !get_settings(v[0].o, "prepare_hard_contacts", &s) ||
        !contact_problem_sizes("prepare_hard_contacts", &v[1], &v[2], &v[3], &v[4], &v[5], &v[6],
                               &v[7], &v[8], &v[10], &v[11], &v[12], &v[13], &nv, &nc, &nb))
        FAIL;
    ProblemObject *pr;
    if (v[14].o == Py_None) {
        pr = (ProblemObject *)problem_new(&ProblemType, NULL, NULL);
        if (!pr) FAIL;
    } else if (Py_IS_TYPE(v[14].o, &ProblemType)) {
        pr = (ProblemObject *)v[14].o;
        Py_INCREF(pr);
    } else {
        release(&h);
        PyErr_SetString(PyExc_TypeError, "prepare_hard_contacts: problem must be a ContactProblem");
        return NULL;
    }
    pr->filled = 0;
    arena_t *a = &pr->arena;
    RUN(a, failed, contact_problem(&s, v[1].p, v[2].p, nv, v[3].p, nc, v[4].p, v[5].p, nb, v[6].p,
                                   v[7].p, v[8].p, (int)v[9].i, v[10].p, v[11].p, v[12].p, v[13].p,
                                   a, &pr->p));
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

FN(complete_hard_contacts) {
    static const spec_t spec[] = {
        {"settings", OBJ},    {"problem", OBJ},      {"h", F64},          {"uS", F64},
        {"M", F64},           {"dof_parent", I64},   {"L", F64},          {"gap", F64},
        {"Wt_all", F64},      {"last_impulse", F64W}, {"last_active", BOOLW}, {"last_bilateral", F64W},
        {"impulse", F64W},    {"is_active", BOOLW},  {"u_free", F64W},    {"u", F64W},
        {"u_corr", F64W},     {"timings", F64N}};
    val_t v[18];
    held_t h = {.n = 0};
    settings_t s;
    if (!PARSE("complete_hard_contacts", spec, 18, v, &h) ||
        !get_settings(v[0].o, "complete_hard_contacts", &s))
        FAIL;
    if (!Py_IS_TYPE(v[1].o, &ProblemType) || !((ProblemObject *)v[1].o)->filled ||
        !((ProblemObject *)v[1].o)->p.ok) {
        release(&h);
        PyErr_SetString(PyExc_ValueError,
                        "complete_hard_contacts: problem must be a ContactProblem prepared with ok");
        return NULL;
    }
    ProblemObject *pr = (ProblemObject *)v[1].o;
    i64 nv = pr->nv, nc = pr->nc, nb = pr->nb;
    if (!need(v[2].len == nv && v[3].len == nv && v[4].len == nv * nv && v[5].len == nv &&
                  v[6].len == nv * nv && v[7].len == nc && v[8].len == 3 * nc * nv &&
                  v[9].len == 3 * nc && v[10].len == nc && v[11].len == nb &&
                  v[12].len == 3 * nc && v[13].len == nc && v[14].len == nv && v[15].len == nv &&
                  v[16].len == nv && (!v[17].p || v[17].len >= 5),
              "complete_hard_contacts", "the arrays do not match the prepared problem"))
        FAIL;
    /* the solve's work in the scratch arena: the problem stays as prepared */
    volatile int failed = 0;
    complete_result_t r = {0, 0, 0.0, 0, 0, -1};
    arena_t *a = scratch_arena();
    RUN(a, failed, r = complete_problem(&s, &pr->p, v[2].p, v[3].p, v[4].p, v[5].p, v[6].p, v[7].p, nc,
                                        v[8].p, v[9].p, v[10].p, v[11].p, nb, v[12].p, v[13].p,
                                        v[14].p, v[15].p, v[16].p, 1, v[17].p, a));
    release(&h);
    if (failed) return PyErr_NoMemory();
    return Py_BuildValue("(LLdOLL)", (long long)r.iterations, (long long)r.status, r.residual,
                         r.retried ? Py_True : Py_False, (long long)r.projection_iterations,
                         (long long)r.projection_status);
}

FN(solve_hard_contacts) {
    static const spec_t spec[] = {
        {"settings", OBJ},   {"M", F64},           {"uS", F64},          {"gap", F64},
        {"Wt_all", F64},     {"WtB", F64},         {"bB", F64},          {"eps", F64},
        {"dof_parent", I64}, {"factor", FLAG},     {"L", F64W},          {"h", F64},
        {"last_impulse", F64W}, {"last_active", BOOLW}, {"last_bilateral", F64W}, {"impulse", F64W},
        {"is_active", BOOLW}, {"u_free", F64W},    {"u", F64W},          {"u_corr", F64W},
        {"timings", F64N}};
    val_t v[21];
    held_t h = {.n = 0};
    volatile int failed = 0;
    settings_t s;
    i64 nv, nc, nb;
    if (!PARSE("solve_hard_contacts", spec, 21, v, &h) ||
        !get_settings(v[0].o, "solve_hard_contacts", &s) ||
        !contact_problem_sizes("solve_hard_contacts", &v[1], &v[2], &v[3], &v[4], &v[5], &v[6],
                               &v[7], &v[8], &v[10], &v[12], &v[13], &v[20], &nv, &nc, &nb) ||
        !need(v[11].len == nv && v[14].len == nb && v[15].len == 3 * nc && v[16].len == nc &&
                  v[17].len == nv && v[18].len == nv && v[19].len == nv,
              "solve_hard_contacts", "the arrays do not match the problem"))
        FAIL;
    problem_t p = {0};
    complete_result_t r = {0, STATUS_CONVERGED, 0.0, 0, 0, -1};
    arena_t *a = scratch_arena();
    RUN(a, failed, {
        contact_problem(&s, v[1].p, v[2].p, nv, v[3].p, nc, v[4].p, v[5].p, nb, v[6].p, v[7].p,
                        v[8].p, (int)v[9].i, v[10].p, v[12].p, v[13].p, v[20].p, a, &p);
        if (p.ok)
            r = complete_problem(&s, &p, v[11].p, v[2].p, v[1].p, v[8].p, v[10].p, v[3].p, nc,
                                 v[4].p, v[12].p, v[13].p, v[14].p, nb, v[15].p, v[16].p,
                                 v[17].p, v[18].p, v[19].p, 1, v[20].p, a);
    });
    release(&h);
    if (failed) return PyErr_NoMemory();
    if (!p.ok)
        return Py_BuildValue("(OLLLLdOLL)", Py_False, 0LL, 0LL, 0LL, (long long)STATUS_CONVERGED,
                             0.0, Py_False, 0LL, -1LL);
    return Py_BuildValue("(OLLLLdOLL)", Py_True, (long long)p.na, (long long)p.opened,
                         (long long)r.iterations, (long long)r.status, r.residual,
                         r.retried ? Py_True : Py_False, (long long)r.projection_iterations,
                         (long long)r.projection_status);
}

/* ---------------------------------------------------------------------------------------
 * the one-kernel steps
 * ------------------------------------------------------------------------------------- */
static int packed_of(const val_t *v, packed_model_t *m) {
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
 * is_active, qE, uE; checked against the model */
static int step_arrays_of(const char *fn, const val_t *v, const packed_model_t *m,
                          step_arrays_t *x) {
    const char *bad = check_tree_model(m, v[1].len);
    if (bad) {
        PyErr_Format(PyExc_ValueError, "%s: %s", fn, bad);
        return 0;
    }
    i64 nc = m->ints[1], na = m->ints[2], nv = m->ints[3];
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
    x->report = v[7].p;
    x->is_active = v[8].p;
    x->qE = v[9].p;
    x->uE = v[10].p;
    /* q: nq ≥ every idx_q + its joint's coordinates (checked by the model's own sizes) */
    const i64 *jtype = m->ints + 4 + m->ints[0], *idx_q = m->ints + 4 + 2 * m->ints[0],
              *idx_v = m->ints + 4 + 3 * m->ints[0];
    for (i64 j = 1; j < m->ints[0]; j++) {
        i64 wq = jtype[j] == JT_FREEFLYER ? 7 : 1, wv = jtype[j] == JT_FREEFLYER ? 6 : 1;
        if (idx_q[j] < 0 || idx_q[j] + wq > x->nq || idx_v[j] < 0 || idx_v[j] + wv > nv) {
            PyErr_Format(PyExc_ValueError, "%s: q or u is too short for the model", fn);
            return 0;
        }
    }
    return need(x->n_tau == na && (x->n_f_ext == 0 || x->n_f_ext == nv) &&
                    v[4].len == 3 * nc && v[5].len == nc && v[7].len == 7 * nc + na &&
                    v[8].len == nc && v[9].len == x->nq && v[10].len == nv,
                fn, "the step's arrays do not match the model (tau: one torque per joint, "
                    "f_ext: nv or empty, report: 7 nc + na)");
}

static PyObject *step_result(const tree_step_result_t *r) {
    return Py_BuildValue("(LLLLLdOLL)", (long long)r->outcome, (long long)r->n_active,
                         (long long)r->opened, (long long)r->iterations, (long long)r->status,
                         r->residual, r->retried ? Py_True : Py_False,
                         (long long)r->projection_iterations, (long long)r->projection_status);
}

#define STEP_ARRAYS                                                                           \
    {"q", F64}, {"u", F64}, {"tau", F64}, {"f_ext", F64}, {"last_impulse", F64W},             \
        {"last_active", BOOLW}, {"last_bilateral", F64W}, {"report", F64W},                  \
        {"is_active", BOOLW}, {"qE", F64W}, {"uE", F64W}
#define MODEL_BUFFERS                                                                         \
    {"floats", F64W}, {"ints", I64}, {"support", BOOL}, {"workspace", F64W}

FN(tree_step_hard) {
    static const spec_t spec[] = {{"saturate", FLAG}, STEP_ARRAYS, MODEL_BUFFERS};
    val_t v[16];
    held_t h = {.n = 0};
    volatile int failed = 0;
    packed_model_t m;
    step_arrays_t x;
    if (!PARSE("tree_step_hard", spec, 16, v, &h) || !packed_of(&v[12], &m) ||
        !step_arrays_of("tree_step_hard", &v[1], &m, &x))
        FAIL;
    tree_step_result_t r = {0, 0, 0, 0, 0, 0.0, 0, 0, -1};
    arena_t *a = scratch_arena();
    RUN_NOGIL(a, failed, r = tree_step_hard((int)v[0].i, &x, &m, a));
    release(&h);
    if (failed) return PyErr_NoMemory();
    return step_result(&r);
}

FN(tree_step_compliant) {
    static const spec_t spec[] = {{"saturate", FLAG}, {"q", F64}, {"u", F64}, {"tau", F64},
                                  {"f_ext", F64}, {"closed", BOOLW}, {"slip", BOOLW},
                                  {"anchor", F64W}, {"lam", F64W}, {"report", F64W},
                                  {"is_active", BOOLW}, {"qE", F64W}, {"uE", F64W},
                                  MODEL_BUFFERS};
    val_t v[17];
    held_t h = {.n = 0};
    volatile int failed = 0;
    packed_model_t m;
    step_arrays_t x;
    if (!PARSE("tree_step_compliant", spec, 17, v, &h) || !packed_of(&v[13], &m)) FAIL;
    /* the step arrays in tree_step_hard's order: lam and closed stand in for the warm-start
     * memory (of the same lengths), which a compliant step has none of */
    val_t w[11] = {v[1], v[2], v[3], v[4], v[8], v[5], v[8], v[9], v[10], v[11], v[12]};
    w[6].len = 0;
    if (!step_arrays_of("tree_step_compliant", w, &m, &x)) FAIL;
    i64 nc = m.ints[1];
    if (
        !need(v[5].len == nc && v[6].len == nc && v[7].len == 3 * nc && v[8].len == 3 * nc,
              "tree_step_compliant", "closed, slip, anchor and lam must match the contacts"))
        FAIL;
    tree_step_result_t r = {0, 0, 0, 0, 0, 0.0, 0, 0, -1};
    arena_t *a = scratch_arena();
    RUN_NOGIL(a, failed, r = tree_step_compliant((int)v[0].i, &x, v[5].p, v[6].p, v[7].p, v[8].p, &m, a));
    release(&h);
    if (failed) return PyErr_NoMemory();
    return step_result(&r);
}

FN(forest_step_hard) {
    static const spec_t spec[] = {{"q", F64},           {"u", F64},
                                  {"applied_tau", F64}, {"f_ext", F64},
                                  {"factor", FLAG},     {"last_impulse", F64W},
                                  {"last_active", BOOLW}, {"last_bilateral", F64W},
                                  {"report", F64W},     {"is_active", BOOLW},
                                  {"qE", F64W},         {"uE", F64W},
                                  {"angle_E", F64W},    {"rate_E", F64W},
                                  MODEL_BUFFERS,        {"cut_floats", F64},
                                  {"cut_ints", I64},    {"cut_workspace", F64W}};
    val_t v[21];
    held_t h = {.n = 0};
    volatile int failed = 0;
    packed_model_t m, c;
    step_arrays_t x;
    if (!PARSE("forest_step_hard", spec, 21, v, &h) || !packed_of(&v[14], &m)) FAIL;
    val_t w[11] = {v[0], v[1], v[2], v[3], v[5], v[6], v[7], v[8], v[9], v[10], v[11]};
    if (!step_arrays_of("forest_step_hard", w, &m, &x)) FAIL;
    c.floats = v[18].p;
    c.n_floats = v[18].len;
    c.ints = v[19].p;
    c.n_ints = v[19].len;
    c.support = NULL;
    c.n_support = 0;
    c.workspace = v[20].p;
    c.n_workspace = v[20].len;
    const char *bad = check_cut_model(&c, m.ints[2], x.nv);
    if (bad) {
        release(&h);
        PyErr_Format(PyExc_ValueError, "forest_step_hard: %s", bad);
        return NULL;
    }
    i64 ncut = c.ints[0];
    if (!need(x.nb == 5 * ncut && v[12].len == ncut && v[13].len == ncut, "forest_step_hard",
              "last_bilateral (5 per cut joint), angle_E and rate_E must match the cut joints"))
        FAIL;
    tree_step_result_t r = {0, 0, 0, 0, 0, 0.0, 0, 0, -1};
    arena_t *a = scratch_arena();
    RUN_NOGIL(a, failed, r = forest_step_hard(&x, (int)v[4].i, v[12].p, v[13].p, &m, &c, a));
    release(&h);
    if (failed) return PyErr_NoMemory();
    return step_result(&r);
}

FN(scratch_arena_stats) {
    (void)args;
    (void)nargs;
    arena_t *a = scratch_arena();
    return Py_BuildValue("(LnL)", (long long)a->misses, (Py_ssize_t)a->cap, (long long)a->wanted);
}

/* ---------------------------------------------------------------------------------------
 * the module
 * ------------------------------------------------------------------------------------- */
#define DEF(name, doc) {#name, (PyCFunction)(void (*)(void))py_##name, METH_FASTCALL, doc}

static PyMethodDef methods[] = {
    DEF(ltdl, "ltdl(A, dof_parent, L) -> bool: the LTDL factor of M (linalg.ltdl)."),
    DEF(ltdl_solve_vec, "ltdl_solve_vec(L, dof_parent, b): (LᵀDL) x = b in place."),
    DEF(ltdl_solve_cols, "ltdl_solve_cols(L, dof_parent, B): (LᵀDL) X = B in place."),
    DEF(ltdl_solve_cols_pattern, "ltdl_solve_cols_pattern(L, dof_parent, B, ptr, idx) -> (ptr, idx)."),
    DEF(cholesky_upper_input, "cholesky_upper_input(A, o, L, first) -> bool."),
    DEF(cholesky_solve_vec, "cholesky_solve_vec(L, first, b)."),
    DEF(envelope_columns, "envelope_columns(first) -> (ptr, idx)."),
    DEF(cholesky_solve_envelope, "cholesky_solve_envelope(L, first, col_ptr, col_idx, b)."),
    DEF(quat_xyzw_to_rot, "quat_xyzw_to_rot(x, y, z, w, R)."),
    DEF(quat_rot, "quat_rot(q, iq, R): the rotation of the root at q[iq]."),
    DEF(forward_kinematics, "forward_kinematics(q, parent, jtype, axis, pl_R, pl_p, idx_q, oR, op)."),
    DEF(point_jacobian, "point_jacobian(j, p, jtype, axis, idx_v, support, oR, op, out, zero=True)."),
    DEF(angular_jacobian, "angular_jacobian(j, jtype, axis, idx_v, support, oR, out, zero=True)."),
    DEF(contact_points, "contact_points(...): kinematics.contact_points."),
    DEF(contact_kinematics, "contact_kinematics(...): kinematics.contact_kinematics."),
    DEF(integrate_forest, "integrate_forest(q, u, dt, jtype, idx_q, idx_v, out)."),
    DEF(to_pin_velocity, "to_pin_velocity(q, u, roots, root_q, root_v, Rs, u_pin)."),
    DEF(from_pin_dynamics, "from_pin_dynamics(M_pin, h_pin, Rs, root_v, u_pin, M, h)."),
    DEF(tree_dynamics, "tree_dynamics(...): M and h at (q, u)."),
    DEF(midpoint_dynamics, "midpoint_dynamics(...): q^M, M, h and the contacts at q^M."),
    DEF(add_at, "add_at(h, idx, values): h[idx[k]] += values[k]."),
    DEF(rigid_body_forces, "rigid_body_forces(q, u, root_q, root_v, mass, inertia, gravity, h)."),
    DEF(cut_joints, "cut_joints(...): W_B^T, g_B, φ, φ̇ and the hinge axes of the cut joints."),
    DEF(gather_joint_values, "gather_joint_values(x, index, cut_values, cut_index, out)."),
    DEF(cut_joint_torques, "cut_joint_torques(tau_cut, cut_P, cut_C, axis_world, jtype, axis, idx_v, support, oR, h)."),
    DEF(compliant_contact_forces, "compliant_contact_forces(law, gap, position, Wt, u, closed, slip, anchor, t1, t2, lam)."),
    DEF(generalized_contact_force, "generalized_contact_force(Wt, lam, out): out += Σ W_i λ_i."),
    DEF(saturate_torque, "saturate_torque(tau, limit, qd, qd_limit, out) -> bool."),
    DEF(row_pattern, "row_pattern(A) -> (ptr, idx)."),
    DEF(col_pattern, "col_pattern(A) -> (ptr, idx)."),
    DEF(prox_parameters, "prox_parameters(Gdiag, nc, alpha, r)."),
    DEF(delassus, "delassus(Wt, MinvW, G, wp_ptr, wp_idx, mp_ptr, mp_idx): G = W^T M^{-1} W."),
    DEF(delassus_diagonal, "delassus_diagonal(Wt, MinvW, d, wp_ptr, wp_idx)."),
    DEF(auto_spectral_scale, "auto_spectral_scale(s, G, Wt, MinvW, pat, nc, r) -> float."),
    DEF(prox_solve, "prox_solve(s, pat, Wt, MinvW, u_free, bvec, G, c, nc, mu, r, lam, LB, M, u) -> (iterations, status, residual)."),
    DEF(free_velocity, "free_velocity(h, dt, uS, dof_parent, L, u_free)."),
    DEF(constraint_velocity, "constraint_velocity(Wt, u_free, bvec, wp_ptr, wp_idx, c)."),
    DEF(solve_compliant, "solve_compliant(law, M, h, uS, dt, gap, position, Wt_all, closed, slip, anchor, t1, t2, lam, dof_parent, factor, L, u_free, timings) -> bool."),
    DEF(end_of_step, "end_of_step(qM, uE, u_corr, projected, half_dt, jtype, idx_q, idx_v, qE) -> bool."),
    DEF(prepare_hard_contacts, "prepare_hard_contacts(settings, M, uS, gap, Wt_all, WtB, bB, eps, dof_parent, factor, L, last_impulse, last_active, timings, problem=None) -> ContactProblem."),
    DEF(complete_hard_contacts, "complete_hard_contacts(settings, problem, h, uS, M, dof_parent, L, gap, Wt_all, last_impulse, last_active, last_bilateral, impulse, is_active, u_free, u, u_corr, timings) -> (iterations, status, residual, retried, projection iterations, projection status)."),
    DEF(solve_hard_contacts, "solve_hard_contacts(...) -> (ok, |I|, opened, iterations, status, residual, retried, projection iterations, projection status)."),
    DEF(tree_step_hard, "tree_step_hard(saturate, q, u, tau, f_ext, last_impulse, last_active, last_bilateral, report, is_active, qE, uE, floats, ints, support, workspace) -> result."),
    DEF(tree_step_compliant, "tree_step_compliant(saturate, q, u, tau, f_ext, closed, slip, anchor, lam, report, is_active, qE, uE, floats, ints, support, workspace) -> result."),
    DEF(forest_step_hard, "forest_step_hard(q, u, applied_tau, f_ext, factor, last_impulse, last_active, last_bilateral, report, is_active, qE, uE, angle_E, rate_E, floats, ints, support, workspace, cut_floats, cut_ints, cut_workspace) -> result."),
    DEF(scratch_arena_stats, "scratch_arena_stats() -> (misses, capacity [bytes], bytes the last call wanted) of this thread's scratch arena."),
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_kernels",
                                    "The physics kernels of the StarlETH simulator, in C.", -1,
                                    methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__kernels(void) {
    if (PyType_Ready(&ProblemType) < 0) return NULL;
    PyObject *numpy = PyImport_ImportModule("numpy");
    if (!numpy) return NULL;
    np_empty = PyObject_GetAttrString(numpy, "empty");
    Py_DECREF(numpy);
    if (!np_empty) return NULL;
    PyObject *m = PyModule_Create(&module);
    if (!m) return NULL;
    static const struct {
        const char *name;
        long long value;
    } ints[] = {
        {"JT_FREEFLYER", JT_FREEFLYER}, {"JT_REVOLUTE", JT_REVOLUTE},
        {"SCHEME_JOR", SCHEME_JOR}, {"SCHEME_SOR", SCHEME_SOR},
        {"FORM_DELASSUS", FORM_DELASSUS}, {"FORM_VELOCITY", FORM_VELOCITY},
        {"CRITERION_IMPULSE", CRITERION_IMPULSE}, {"CRITERION_ENERGY", CRITERION_ENERGY},
        {"STATUS_CONVERGED", STATUS_CONVERGED}, {"STATUS_MAX_ITER", STATUS_MAX_ITER},
        {"STATUS_NONFINITE", STATUS_NONFINITE},
        {"AUTO_POWER_ITERATIONS", AUTO_POWER_ITERATIONS},
        {"DELASSUS_ENVELOPE_ROWS", DELASSUS_ENVELOPE_ROWS},
        {"PHASE_M_AND_H", PHASE_M_AND_H}, {"PHASE_M_INVERSE", PHASE_M_INVERSE},
        {"PHASE_G", PHASE_G}, {"PHASE_PROX", PHASE_PROX}, {"PHASE_REST", PHASE_REST},
        {"TREE_STEP_OK", TREE_STEP_OK}, {"TREE_STEP_NOT_PD", TREE_STEP_NOT_PD},
        {"TREE_STEP_NONFINITE_IMPULSE", TREE_STEP_NONFINITE_IMPULSE},
        {"TREE_STEP_NONFINITE_STATE", TREE_STEP_NONFINITE_STATE},
        {"TREE_STEP_NONFINITE_TORQUE", TREE_STEP_NONFINITE_TORQUE},
    };
    static const struct {
        const char *name;
        double value;
    } floats[] = {
        {"ALPHA_AUTO", ALPHA_AUTO}, {"AUTO_MAX_STEP", AUTO_MAX_STEP},
        {"AUTO_GUARD", AUTO_GUARD}, {"AUTO_SOR_BILATERAL_OMEGA", AUTO_SOR_BILATERAL_OMEGA},
    };
    for (size_t k = 0; k < sizeof(ints) / sizeof(ints[0]); k++)
        if (PyModule_AddIntConstant(m, ints[k].name, (long)ints[k].value) < 0) {
            Py_DECREF(m);
            return NULL;
        }
    for (size_t k = 0; k < sizeof(floats) / sizeof(floats[0]); k++) {
        PyObject *f = PyFloat_FromDouble(floats[k].value);
        if (!f || PyModule_AddObject(m, floats[k].name, f) < 0) {
            Py_XDECREF(f);
            Py_DECREF(m);
            return NULL;
        }
    }
    Py_INCREF(&ProblemType);
    if (PyModule_AddObject(m, "ContactProblem", (PyObject *)&ProblemType) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
