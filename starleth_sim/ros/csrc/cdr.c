/* starleth_sim.ros._cdr: the parsers of sim_node's command decoder (cdr.py: the layout
 * facts and what falls back to rclpy). They read CDR bytes (XCDR1, little endian) and never
 * outside the buffer; anything but the common valid case returns FALLBACK. */
#include "py_args.h"

#include <math.h>
#include <stdint.h>
#include <string.h>

typedef int64_t i64;

enum { OK = 0, FALLBACK = 1 };

/* the alignment origin: the CDR payload starts after the 4-byte encapsulation header */
#define ORIGIN 4

static inline i64 align(i64 o, i64 a) {
    i64 r = (o - ORIGIN) % a;
    return r == 0 ? o : o + a - r;
}

static inline uint32_t u32(const uint8_t *buf, i64 o) {
    return (uint32_t)buf[o] | (uint32_t)buf[o + 1] << 8 | (uint32_t)buf[o + 2] << 16 |
           (uint32_t)buf[o + 3] << 24;
}

/* n little-endian float64 at buf[o:] into out; 0 if one is not finite. */
static int f64_into(const uint8_t *buf, i64 o, i64 n, double *out) {
    int ok = 1;
    for (i64 k = 0; k < n; k++) {
        uint64_t bits = 0;
        for (int b = 7; b >= 0; b--) bits = bits << 8 | buf[o + 8 * k + b];
        memcpy(&out[k], &bits, 8);
        if (!isfinite(out[k])) ok = 0;
    }
    return ok;
}

/* The offset after an empty float64[] starting at o (aligned to 4), or -1 if it does not
 * fit or is not empty. */
static i64 skip_empty_sequence(const uint8_t *buf, i64 o, i64 nbuf) {
    o = align(o, 4);
    if (o + 4 > nbuf || u32(buf, o) != 0) return -1;
    return o + 4;
}

/* A sensor_msgs/JointState command: OK when the names are exactly `names` (flattened UTF-8
 * bytes, names_ptr the n+1 offsets) in that order, position and velocity are empty and
 * effort holds n finite values (written to effort, with the stamp to *sec, *nsec). */
static int parse_joint_command(const uint8_t *buf, i64 nbuf, const uint8_t *names,
                               const i64 *names_ptr, i64 n, double *effort, int32_t *sec,
                               uint32_t *nsec) {
    if (nbuf < 16 || buf[0] != 0 || buf[1] != 1) return FALLBACK;
    *sec = (int32_t)u32(buf, 4);
    *nsec = u32(buf, 8);
    i64 o = align(16 + (i64)u32(buf, 12), 4); /* after the frame id */
    if (o + 4 > nbuf || (i64)u32(buf, o) != n) return FALLBACK;
    o += 4;
    for (i64 i = 0; i < n; i++) {
        o = align(o, 4);
        if (o + 4 > nbuf) return FALLBACK;
        i64 slen = u32(buf, o);
        o += 4;
        i64 a = names_ptr[i], b = names_ptr[i + 1];
        if (slen != b - a + 1 || o + slen > nbuf) return FALLBACK;
        if (memcmp(buf + o, names + a, (size_t)(b - a)) != 0) return FALLBACK;
        o += slen;
    }
    o = skip_empty_sequence(buf, o, nbuf); /* position */
    if (o < 0) return FALLBACK;
    o = skip_empty_sequence(buf, o, nbuf); /* velocity */
    if (o < 0) return FALLBACK;
    o = align(o, 4);
    if (o + 4 > nbuf || (i64)u32(buf, o) != n) return FALLBACK;
    o = align(o + 4, 8);
    if (o + 8 * n > nbuf || !f64_into(buf, o, n, effort)) return FALLBACK;
    return OK;
}

/* A std_msgs/Float64MultiArray: OK when data holds n finite values (written to effort),
 * whatever the layout says. */
static int parse_effort_array(const uint8_t *buf, i64 nbuf, i64 n, double *effort) {
    if (nbuf < 12 || buf[0] != 0 || buf[1] != 1) return FALLBACK;
    i64 ndim = u32(buf, 4);
    i64 o = 8;
    for (i64 d = 0; d < ndim; d++) { /* label, size, stride */
        o = align(o, 4);
        if (o + 4 > nbuf) return FALLBACK;
        o += 4 + (i64)u32(buf, o);
        o = align(o, 4) + 8;
        if (o > nbuf) return FALLBACK;
    }
    o = align(o, 4) + 4; /* data_offset */
    if (o + 4 > nbuf || (i64)u32(buf, o) != n) return FALLBACK;
    o = align(o + 4, 8);
    if (o + 8 * n > nbuf || !f64_into(buf, o, n, effort)) return FALLBACK;
    return OK;
}

static PyObject *py_parse_joint_command(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    args_t A = {.n = 0, .fn = "parse_joint_command"};
    Py_ssize_t nbuf, nnames, nptr, neff;
    PyObject *result = NULL;
    if (!arg_count(&A, nargs, 4)) return NULL;
    const uint8_t *buf = arg_array(&A, args[0], 'B', 0, 0, "buf", &nbuf);
    const uint8_t *names = buf ? arg_array(&A, args[1], 'B', 0, 0, "names", &nnames) : NULL;
    const i64 *ptr = names ? arg_array(&A, args[2], 'q', 0, 1, "names_ptr", &nptr) : NULL;
    double *effort = ptr ? arg_array(&A, args[3], 'd', 1, nptr - 1, "effort", &neff) : NULL;
    if (effort) {
        int ok = ptr[0] == 0;
        for (Py_ssize_t i = 0; ok && i + 1 < nptr; i++) ok = ptr[i] <= ptr[i + 1];
        if (!ok || ptr[nptr - 1] > nnames) {
            PyErr_SetString(PyExc_ValueError,
                            "parse_joint_command: names_ptr must rise from 0 to len(names)");
        } else {
            int32_t sec = 0;
            uint32_t nsec = 0;
            int status = parse_joint_command(buf, nbuf, names, ptr, nptr - 1, effort, &sec, &nsec);
            if (status != OK) sec = 0, nsec = 0;
            result = Py_BuildValue("(iik)", status, (int)sec, (unsigned long)nsec);
        }
    }
    args_release(&A);
    return result;
}

static PyObject *py_parse_effort_array(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    args_t A = {.n = 0, .fn = "parse_effort_array"};
    Py_ssize_t nbuf, neff;
    PyObject *result = NULL;
    if (!arg_count(&A, nargs, 2)) return NULL;
    const uint8_t *buf = arg_array(&A, args[0], 'B', 0, 0, "buf", &nbuf);
    double *effort = buf ? arg_array(&A, args[1], 'd', 1, 0, "effort", &neff) : NULL;
    if (effort) result = PyLong_FromLong(parse_effort_array(buf, nbuf, neff, effort));
    args_release(&A);
    return result;
}

static PyMethodDef methods[] = {
    {"parse_joint_command", (PyCFunction)(void (*)(void))py_parse_joint_command, METH_FASTCALL,
     "parse_joint_command(buf, names, names_ptr, effort) -> (status, sec, nanosec)."},
    {"parse_effort_array", (PyCFunction)(void (*)(void))py_parse_effort_array, METH_FASTCALL,
     "parse_effort_array(buf, effort) -> status."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    "_cdr",
    "sim_node's command parsers in C (starleth_sim/ros/csrc).",
    -1,
    methods,
    NULL,
    NULL,
    NULL,
    NULL,
};

PyMODINIT_FUNC PyInit__cdr(void) {
    if (!args_init()) return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m && (PyModule_AddIntConstant(m, "OK", OK) < 0 ||
              PyModule_AddIntConstant(m, "FALLBACK", FALLBACK) < 0)) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
