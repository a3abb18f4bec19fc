/* Argument helpers of the small C extensions (starleth_controller._kernels,
 * starleth_sim.ros._cdr; built by starleth_interface/c_extension.py): numpy arrays through
 * the buffer protocol (no numpy C API: Python's headers alone), their type and size checked.
 * An input array that is not C-contiguous or not of the type is converted
 * (numpy.ascontiguousarray, as numba took any layout); an output must be a C-contiguous,
 * writable array of its type. Each failure is a ValueError naming the function and the
 * argument. */
#ifndef STARLETH_PY_ARGS_H
#define STARLETH_PY_ARGS_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <stdint.h>

#include "buffer_format.h"

#define MAX_ARGS 40

typedef struct {
    Py_buffer v[MAX_ARGS];
    int n;
    const char *fn; /* the function's name, for the messages */
} args_t;

/* numpy.ascontiguousarray, set by the module's init (args_init) */
static PyObject *np_ascontiguousarray;

static inline int args_init(void) {
    PyObject *np = PyImport_ImportModule("numpy");
    if (!np) return 0;
    np_ascontiguousarray = PyObject_GetAttrString(np, "ascontiguousarray");
    Py_DECREF(np);
    return np_ascontiguousarray != NULL;
}

static inline void args_release(args_t *a) {
    for (int k = 0; k < a->n; k++) PyBuffer_Release(&a->v[k]);
    a->n = 0;
}

/* The data of argument o (`name`) of at least min_len items of `type`; *len (if not NULL)
 * its number of items. NULL with a ValueError set when it is not such an array. */
static inline void *arg_array(args_t *a, PyObject *o, char type, int writable, Py_ssize_t min_len,
                              const char *name, Py_ssize_t *len) {
    if (a->n >= MAX_ARGS) {
        PyErr_Format(PyExc_RuntimeError, "%s: too many arrays", a->fn);
        return NULL;
    }
    Py_buffer *b = &a->v[a->n];
    int flags = PyBUF_FORMAT | PyBUF_C_CONTIGUOUS | (writable ? PyBUF_WRITABLE : 0);
    int ok = PyObject_GetBuffer(o, b, flags) == 0;
    if (!ok) PyErr_Clear();
    if (ok && !format_is(b, type)) {
        PyBuffer_Release(b);
        ok = 0;
    }
    if (!ok && !writable) { /* an input of another layout or type: converted */
        PyObject *c = PyObject_CallFunction(np_ascontiguousarray, "Os", o, dtype_of(type));
        if (c) {
            ok = PyObject_GetBuffer(c, b, PyBUF_FORMAT | PyBUF_C_CONTIGUOUS) == 0;
            Py_DECREF(c); /* the buffer keeps the array alive */
            if (ok && !format_is(b, type)) {
                PyBuffer_Release(b);
                ok = 0;
            }
        }
        PyErr_Clear();
    }
    if (!ok) {
        PyErr_Format(PyExc_ValueError, "%s: %s must be a %snumpy array of %s, got %.100s", a->fn,
                     name, writable ? "C-contiguous, writable " : "", dtype_of(type),
                     Py_TYPE(o)->tp_name);
        return NULL;
    }
    a->n++;
    Py_ssize_t n = b->len / b->itemsize;
    if (n < min_len) {
        PyErr_Format(PyExc_ValueError, "%s: %s has %zd items, %zd needed", a->fn, name, n, min_len);
        return NULL;
    }
    if (len) *len = n;
    return b->buf;
}

/* the shape of the last array taken (dimension d; 1 beyond its dimensions) */
static inline Py_ssize_t arg_dim(const args_t *a, int d) {
    const Py_buffer *b = &a->v[a->n - 1];
    return d < b->ndim ? b->shape[d] : 1;
}

static inline int arg_double(args_t *a, PyObject *o, const char *name, double *out) {
    *out = PyFloat_AsDouble(o);
    if (*out == -1.0 && PyErr_Occurred()) {
        PyErr_Clear();
        PyErr_Format(PyExc_ValueError, "%s: %s must be a number, got %.100s", a->fn, name,
                     Py_TYPE(o)->tp_name);
        return 0;
    }
    return 1;
}

static inline int arg_int(args_t *a, PyObject *o, const char *name, int64_t *out) {
    *out = PyLong_AsLongLong(o);
    if (*out == -1 && PyErr_Occurred()) {
        PyErr_Clear();
        PyErr_Format(PyExc_ValueError, "%s: %s must be an integer, got %.100s", a->fn, name,
                     Py_TYPE(o)->tp_name);
        return 0;
    }
    return 1;
}

static inline int arg_count(args_t *a, Py_ssize_t nargs, Py_ssize_t want) {
    if (nargs != want) {
        PyErr_Format(PyExc_TypeError, "%s takes %zd arguments (%zd given)", a->fn, want, nargs);
        return 0;
    }
    return 1;
}

#endif
