/* The bindings' argument helpers: arrays, their kinds and sizes checked, read directly from
 * numpy arrays where the build has numpy's C API (numpy_api.h) and through the buffer
 * protocol otherwise (any buffer object, and every argument that is not a numpy array of the
 * kind asked, whose error the buffer path gives); the records (settings, patterns, the tree,
 * the contacts, ...) read from them; new numpy arrays for the few results that are new. */
#include "bind.h"

#include "buffer_format.h"
#include "numpy_api.h"

PyObject *np_empty;

void release(held_t *h) {
    for (int k = 0; k < h->n; k++) PyBuffer_Release(&h->v[k]);
    h->n = 0;
}

/* the item type of a base kind (buffer_format.h) */
static char type_of(int base) {
    return base == F64 ? 'd' : base == I64 ? 'q' : '?';
}

/* numpy_view: v of a numpy array (not a subclass) of the base kind, C-contiguous, aligned,
 * writeable where asked and of at most 4 dimensions; 0 (nothing set) for anything else. The
 * arguments' references keep the array for the call (a resize needs it unreferenced). */
static int numpy_view(PyObject *o, int base, int writable, val_t *v) {
#ifdef STARLETH_NUMPY_C_API
    if (!PyArray_CheckExact(o)) return 0;
    PyArrayObject *arr = (PyArrayObject *)o;
    int type = base == F64 ? NPY_FLOAT64 : base == I64 ? NPY_INT64 : NPY_BOOL;
    if (PyArray_TYPE(arr) != type || !PyArray_IS_C_CONTIGUOUS(arr) || !PyArray_ISALIGNED(arr) ||
        (writable && !PyArray_ISWRITEABLE(arr)) || PyArray_NDIM(arr) > 4)
        return 0;
    v->p = PyArray_DATA(arr);
    v->len = PyArray_SIZE(arr);
    v->nd = PyArray_NDIM(arr);
    for (int k = 0; k < v->nd; k++) v->shape[k] = PyArray_DIM(arr, k);
    return 1;
#else
    (void)o, (void)base, (void)writable, (void)v;
    return 0;
#endif
}

/* An array argument into v (a buffer it needed kept in h); 0 with an exception set on
 * error. */
int get_array(PyObject *o, int kind, const char *fn, const char *name, held_t *h, val_t *v) {
    int writable = kind == F64W || kind == I64W || kind == BOOLW || kind == F64N;
    int base = (kind == F64 || kind == F64W || kind == F64N) ? F64
               : (kind == I64 || kind == I64W)               ? I64
                                                             : BOOL;
    if (numpy_view(o, base, writable, v)) return 1;
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
                     writable ? ", writeable" : "", dtype_of(type_of(base)), Py_TYPE(o)->tp_name);
        return 0;
    }
    h->n++;
    if (!format_is(b, type_of(base))) {
        PyErr_Format(PyExc_ValueError, "%s: %s must be an array of %s (format '%s')", fn, name,
                     dtype_of(type_of(base)), b->format ? b->format : "B");
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

/* parse_one: one argument o by its spec entry into v */
static int parse_one(PyObject *o, const spec_t *sp, const char *fn, val_t *v, held_t *h) {
    const char *name = sp->name;
    switch (sp->kind) {
        case FLOAT:
            v->f = PyFloat_AsDouble(o);
            if (v->f == -1.0 && PyErr_Occurred()) {
                PyErr_Format(PyExc_TypeError, "%s: %s must be a number", fn, name);
                return 0;
            }
            return 1;
        case INT: {
            PyObject *idx = PyNumber_Index(o);
            if (!idx) {
                PyErr_Format(PyExc_TypeError, "%s: %s must be an integer", fn, name);
                return 0;
            }
            v->i = PyLong_AsLongLong(idx);
            Py_DECREF(idx);
            return !(v->i == -1 && PyErr_Occurred());
        }
        case FLAG: {
            int t = PyObject_IsTrue(o);
            if (t < 0) return 0;
            v->i = t;
            return 1;
        }
        case OBJ:
            v->o = o;
            return 1;
        case F64N:
            if (o == Py_None) {
                v->p = NULL;
                v->len = 0;
                return 1;
            }
            if (!get_array(o, F64N, fn, name, h, v)) return 0;
            if (v->len == 0) v->p = NULL;
            return 1;
        default:
            return get_array(o, sp->kind, fn, name, h, v);
    }
}

/* span: the spec entries (*ns) and vals (*nv) an entry covers (a GROUP + n: its n items',
 * which may be groups themselves) */
static void span(const spec_t *sp, int *ns, int *nv) {
    *ns = 1;
    *nv = sp->kind >= GROUP ? 0 : 1;
    if (sp->kind < GROUP) return;
    for (int j = 0; j < sp->kind - GROUP; j++) {
        int a, b;
        span(sp + *ns, &a, &b);
        *ns += a;
        *nv += b;
    }
}

/* parse_entry: one argument by its spec entry: a GROUP + n is a tuple of n items, parsed by
 * the entries after it (nested groups: nested tuples) */
static int parse_entry(PyObject *o, const spec_t *sp, const char *fn, val_t *vals, held_t *h) {
    if (sp->kind < GROUP) return parse_one(o, sp, fn, vals, h);
    int n = sp->kind - GROUP;
    if (!PyTuple_Check(o) || PyTuple_GET_SIZE(o) != n) {
        PyErr_Format(PyExc_TypeError, "%s: %s must be a tuple of %d items", fn, sp->name, n);
        return 0;
    }
    const spec_t *item = sp + 1;
    for (int j = 0; j < n; j++) {
        int a, b;
        if (!parse_entry(PyTuple_GET_ITEM(o, j), item, fn, vals, h)) return 0;
        span(item, &a, &b);
        item += a;
        vals += b;
    }
    return 1;
}

/* Parses the positional arguments args[0:nargs] by spec (the first n_required required, the
 * others keep the defaults the caller put into vals). A GROUP entry takes one argument, a
 * tuple, whose items the entries after it parse: vals has one entry per non-GROUP entry, in
 * spec order (a model's arrays grouped like the C structs passed by pointer). */
int parse(PyObject *const *args, Py_ssize_t nargs, const char *fn, const spec_t *spec, int n_spec,
          int n_required, val_t *vals, held_t *h) {
    int n_args = 0;
    for (int si = 0, a, b; si < n_spec; si += a, n_args++) span(&spec[si], &a, &b);
    if (nargs < n_required || nargs > n_args) {
        PyErr_Format(PyExc_TypeError, "%s takes %d%s arguments (%zd given)", fn, n_required,
                     n_required == n_args ? "" : " or more", nargs);
        return 0;
    }
    const spec_t *sp = spec;
    for (Py_ssize_t k = 0; k < nargs; k++) {
        int a, b;
        if (!parse_entry(args[k], sp, fn, vals, h)) return 0;
        span(sp, &a, &b);
        sp += a;
        vals += b;
    }
    return 1;
}

int need(int ok, const char *fn, const char *what) {
    if (!ok) PyErr_Format(PyExc_ValueError, "%s: %s", fn, what);
    return ok;
}

/* A new numpy array of n items (kind F64 or I64) copied from data, 1-d */
PyObject *new_array(const void *data, int base, Py_ssize_t n) {
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
PyObject *reshaped(PyObject *arr, Py_ssize_t r, Py_ssize_t c) {
    if (!arr) return NULL;
    PyObject *out = PyObject_CallMethod(arr, "reshape", "(nn)", r, c);
    Py_DECREF(arr);
    return out;
}

PyObject *pair_of_arrays(const i64 *ptr, Py_ssize_t n_ptr, const i64 *idx, Py_ssize_t n_idx) {
    PyObject *a = new_array(ptr, I64, n_ptr);
    PyObject *b = a ? new_array(idx, I64, n_idx) : NULL;
    if (!b) {
        Py_XDECREF(a);
        return NULL;
    }
    return Py_BuildValue("(NN)", a, b);
}

/* The settings: a StepSettings or a prox.ProxSettings (their fields: kernels.layouts) */
/* flatten_numbers: the numbers of a sequence into f (a nested sequence's in place, in
 * order), at most cap; their count, or -1 if an item is neither a number nor a sequence */
static Py_ssize_t flatten_numbers(PyObject *o, double *f, Py_ssize_t cap) {
    PyObject *seq = PySequence_Fast(o, "settings must be a sequence");
    if (!seq) return -1;
    Py_ssize_t n = 0, len = PySequence_Fast_GET_SIZE(seq);
    PyObject **it = PySequence_Fast_ITEMS(seq);
    for (Py_ssize_t k = 0; n >= 0 && k < len; k++) {
        if (PyTuple_Check(it[k]) || PyList_Check(it[k])) {
            Py_ssize_t m = flatten_numbers(it[k], f + n, cap - n);
            n = m < 0 ? -1 : n + m;
        } else if (n < cap) {
            f[n] = PyFloat_AsDouble(it[k]);
            n = f[n] == -1.0 && PyErr_Occurred() ? -1 : n + 1;
        } else {
            n = cap + 1; /* (too many: the caller refuses) */
            break;
        }
    }
    Py_DECREF(seq);
    return n;
}

/* A StepSettings (with its ProxSettings inside) or a ProxSettings, as numbers */
int get_settings(PyObject *o, const char *fn, settings_t *s) {
    double f[STEP_SETTINGS_LENGTH + 1];
    Py_ssize_t n = flatten_numbers(o, f, STEP_SETTINGS_LENGTH + 1);
    if (n != STEP_SETTINGS_LENGTH && n != PROX_SETTINGS_LENGTH) {
        PyErr_Clear();
        PyErr_Format(PyExc_ValueError,
                     "%s: settings must be the %d numbers of a StepSettings or the %d of a "
                     "ProxSettings",
                     fn, STEP_SETTINGS_LENGTH, PROX_SETTINGS_LENGTH);
        return 0;
    }
    memset(s, 0, sizeof(*s));
    if (n == STEP_SETTINGS_LENGTH)
        settings_from_fields(f, s);
    else
        prox_settings_from_fields(f, s);
    if (s->form != FORM_DELASSUS && s->form != FORM_VELOCITY) {
        PyErr_Format(PyExc_ValueError, "%s: settings: unknown form %lld", fn, (long long)s->form);
        return 0;
    }
    return 1;
}

/* A prox.Patterns (7 arrays of int64) */
int get_patterns(PyObject *o, const char *fn, held_t *h, patterns_t *pat) {
    static const char *names[7] = {"wp_ptr", "wp_idx", "mp_ptr",  "mp_idx",
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

/* The tree's arrays (kinematics.KinematicTree); sizes from parent / jtype (nj) */
int tree_of(const char *fn, const val_t *parent, const val_t *jtype, const val_t *axis,
            const val_t *pl_R, const val_t *pl_p, const val_t *idx_q, const val_t *idx_v,
            const val_t *support, i64 nv, tree_t *t) {
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

int frames_of(const char *fn, const val_t *oR, const val_t *op, i64 nj, frames_t *f) {
    if (!need((!oR || oR->len == 9 * nj) && (!op || op->len == 3 * nj), fn,
              "oR / op must have one entry per joint"))
        return 0;
    f->oR = oR ? oR->p : NULL;
    f->op = op ? op->p : NULL;
    return 1;
}
