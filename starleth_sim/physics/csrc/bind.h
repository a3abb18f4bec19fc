/* The Python bindings of the kernels (bind*.c, module.c): argument parsing and checks,
 * shared by the binding files; see module.c. */
#ifndef STARLETH_BIND_H
#define STARLETH_BIND_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <string.h>

#include "step.h"

/* The kinds of arguments */
enum {
    F64 = 1,     /* float64 array, read */
    I64 = 2,     /* int64 array, read */
    BOOL = 3,    /* bool array, read */
    F64W = 4,    /* float64 array, written */
    I64W = 5,    /* int64 array, written */
    BOOLW = 6,   /* bool array, written */
    FLOAT = 7,   /* a number */
    INT = 8,     /* an integer */
    FLAG = 9,    /* truth value */
    OBJ = 10,    /* any object, as it is */
    F64N = 11,   /* float64 array or None (read and written; NULL when None or empty) */
    GROUP = 100, /* GROUP + n: a tuple of n items, parsed by the n entries that follow */
};

typedef struct {
    const char *name;
    int kind;
} spec_t;

typedef struct {
    void *p;        /* data */
    Py_ssize_t len; /* number of items */
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

#define PARSE(fn, spec, n_required, vals, h) \
    parse(args, nargs, fn, spec, (int)(sizeof(spec) / sizeof(spec[0])), n_required, vals, h)

/* Runs the code (the macro's last arguments) with the scratch arena `a` reset and its
 * out-of-memory jump set; `failed` becomes 1 when memory ran out. nogil: without the GIL
 * (RUN_NOGIL), else with it held (RUN: short kernels). */
#define RUN_WITH(a, failed, nogil, ...)                            \
    do {                                                           \
        jmp_buf jb_;                                               \
        arena_reset(a);                                            \
        (a)->oom = &jb_;                                           \
        PyThreadState *ts_ = (nogil) ? PyEval_SaveThread() : NULL; \
        if (setjmp(jb_) == 0) {                                    \
            __VA_ARGS__;                                           \
        } else {                                                   \
            failed = 1;                                            \
        }                                                          \
        if (ts_) PyEval_RestoreThread(ts_);                        \
        (a)->oom = NULL;                                           \
    } while (0)
#define RUN_NOGIL(a, failed, ...) RUN_WITH(a, failed, 1, __VA_ARGS__)
#define RUN(a, failed, ...)       RUN_WITH(a, failed, 0, __VA_ARGS__)

#define FN(name)                                                                       \
    PyObject *py_##name(PyObject *self __attribute__((unused)), PyObject *const *args, \
                        Py_ssize_t nargs)
#define DONE_NONE                        \
    release(&h);                         \
    if (failed) return PyErr_NoMemory(); \
    Py_RETURN_NONE
#define FAIL         \
    do {             \
        release(&h); \
        return NULL; \
    } while (0)

/* the helpers (bind.c): each returns 0 (NULL) with an exception set on error */
extern PyObject *np_empty; /* numpy.empty, set by the module's init */
void release(held_t *h);
int get_array(PyObject *o, int kind, const char *fn, const char *name, held_t *h, val_t *v);
int parse(PyObject *const *args, Py_ssize_t nargs, const char *fn, const spec_t *spec, int n_spec,
          int n_required, val_t *vals, held_t *h);
int need(int ok, const char *fn, const char *what);
PyObject *new_array(const void *data, int base, Py_ssize_t n);
PyObject *reshaped(PyObject *arr, Py_ssize_t r, Py_ssize_t c);
PyObject *pair_of_arrays(const i64 *ptr, Py_ssize_t n_ptr, const i64 *idx, Py_ssize_t n_idx);
int get_settings(PyObject *o, const char *fn, settings_t *s);
int get_patterns(PyObject *o, const char *fn, held_t *h, patterns_t *pat);
int tree_of(const char *fn, const val_t *parent, const val_t *jtype, const val_t *axis,
            const val_t *pl_R, const val_t *pl_p, const val_t *idx_q, const val_t *idx_v,
            const val_t *support, i64 nv, tree_t *t);
int frames_of(const char *fn, const val_t *oR, const val_t *op, i64 nj, frames_t *f);

/* the bindings (bind_geometry.c, bind_prox.c, bind_step.c) */
FN(ltdl);
FN(ltdl_solve_vec);
FN(ltdl_solve_cols);
FN(ltdl_solve_cols_pattern);
FN(cholesky_upper_input);
FN(cholesky_solve_vec);
FN(envelope_columns);
FN(cholesky_solve_envelope);
FN(quat_xyzw_to_rot);
FN(quat_rot);
FN(forward_kinematics);
FN(point_jacobian);
FN(angular_jacobian);
FN(contact_kinematics);
FN(integrate_forest);
FN(to_pin_velocity);
FN(from_pin_dynamics);
FN(tree_dynamics);
FN(midpoint_dynamics);
FN(add_at);
FN(rigid_body_forces);
FN(cut_joints);
FN(gather_joint_values);
FN(cut_joint_torques);
FN(saturate_torque);
FN(impedance_torque);
FN(row_pattern);
FN(col_pattern);
FN(prox_parameters);
FN(delassus);
FN(delassus_diagonal);
FN(auto_spectral_scale);
FN(prox_solve);
FN(free_velocity);
FN(constraint_velocity);
FN(prepare_hard_contacts);
/* packed_of: the TreeStepModel's four buffers (floats, ints, support, workspace) parsed
 * into m; run_tree_step: the tree kernel of parsed arrays, checked against m (bind_step.c) */
int packed_of(const val_t *v, packed_model_t *m);
int run_tree_step(const char *fn, int compliant, i64 options, i64 mode, const val_t *st,
                  const val_t *tau, const val_t *f_ext, const val_t *out, const packed_model_t *m,
                  tree_step_result_t *r);
extern PyTypeObject TreeStepType; /* bind_tree_step.c */
/* TreeStep.step(state, tau, report, is_active, f_ext, mode) of a TreeStep, its result also
 * into out where not NULL (bind_tree_step.c) */
PyObject *tree_step_advance(PyObject *tree, PyObject *state, PyObject *tau, PyObject *report,
                            PyObject *is_active, PyObject *f_ext, long long mode,
                            tree_step_result_t *out);
extern PyTypeObject ControlPeriodType; /* bind_period.c */
FN(tree_step_hard);
FN(tree_step_compliant);
FN(forest_step);
FN(scratch_arena_stats);

/* the ContactProblem type (bind_step.c) */
extern PyTypeObject ProblemType;

#endif
