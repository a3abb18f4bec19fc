/* starleth_controller._kernels: the Python bindings of the controller's kernels (kernels.c,
 * ground_plane.c), each with the arguments of the function of the same name in kernels.h
 * (arrays with their sizes, checked: py_args.h). */
#include "py_args.h"

#include "kernels.h"

#define FN(name) static PyObject *py_##name(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
#define BEGIN(name, count)            \
    (void)self;                       \
    args_t A = {.n = 0, .fn = #name}; \
    if (!arg_count(&A, nargs, count)) return NULL
/* argument i as an array (`in`: read, `out`: written) of at least `min` items */
#define IN_F(i, var, min)                                                \
    const double *var = arg_array(&A, args[i], 'd', 0, min, #var, NULL); \
    if (!var) goto fail
#define OUT_F(i, var, min)                                         \
    double *var = arg_array(&A, args[i], 'd', 1, min, #var, NULL); \
    if (!var) goto fail
#define IN_I(i, var, min)                                             \
    const i64 *var = arg_array(&A, args[i], 'q', 0, min, #var, NULL); \
    if (!var) goto fail
#define OUT_I(i, var, min)                                      \
    i64 *var = arg_array(&A, args[i], 'q', 1, min, #var, NULL); \
    if (!var) goto fail
#define DOUBLE(i, var) \
    double var;        \
    if (!arg_double(&A, args[i], #var, &var)) goto fail
#define INT(i, var) \
    i64 var;        \
    if (!arg_int(&A, args[i], #var, &var)) goto fail
#define FLAG(i, var)                    \
    int var = PyObject_IsTrue(args[i]); \
    if (var < 0) goto fail
#define RANGE(cond, what)                                     \
    if (!(cond)) {                                            \
        PyErr_Format(PyExc_ValueError, "%s: %s", A.fn, what); \
        goto fail;                                            \
    }
#define DONE(result)  \
    args_release(&A); \
    return result;    \
    fail:             \
    args_release(&A); \
    return NULL

/* The first n entries of the leg list `legs` (the last array taken) are legs 0-3, n in
 * lo..min(4, its length); 0 with a ValueError naming `what` otherwise. */
static int legs_ok(args_t *a, const i64 *legs, i64 n, i64 lo, const char *what) {
    i64 len = a->v[a->n - 1].len / 8;
    int ok = n >= lo && n <= len && n <= 4;
    for (i64 j = 0; ok && j < n; j++) ok = legs[j] >= 0 && legs[j] < 4;
    if (!ok)
        PyErr_Format(PyExc_ValueError, "%s: %lld legs of %s asked (%lld to %lld), each 0-3", a->fn,
                     (long long)n, what, (long long)lo, (long long)(len < 4 ? len : 4));
    return ok;
}
#define LEGS(legs, n, lo) \
    if (!legs_ok(&A, legs, n, lo, #legs)) goto fail

FN(quat_to_rot) {
    BEGIN(quat_to_rot, 5);
    DOUBLE(0, qx);
    DOUBLE(1, qy);
    DOUBLE(2, qz);
    DOUBLE(3, qw);
    OUT_F(4, R, 9);
    quat_to_rot(qx, qy, qz, qw, R);
    DONE(Py_NewRef(Py_None));
}

FN(squared_norm4) {
    BEGIN(squared_norm4, 1);
    IN_F(0, a, 4);
    double s = squared_norm4(a);
    DONE(PyFloat_FromDouble(s));
}

FN(read_state) {
    BEGIN(read_state, 8);
    Py_ssize_t n[6];
    const double *in[6];
    static const char *names[6] = {"qj", "dqj", "pb", "quat", "vb", "wb"};
    for (int i = 0; i < 6; i++) {
        in[i] = arg_array(&A, args[i], 'd', 0, i == 3 ? 4 : 0, names[i], &n[i]);
        if (!in[i]) goto fail;
    }
    OUT_F(6, quat_n, 4);
    OUT_F(7, R, 9);
    int status = read_state(in[0], n[0], in[1], n[1], in[2], n[2], in[3], n[3], in[4], n[4], in[5],
                            n[5], quat_n, R);
    DONE(PyLong_FromLong(status));
}

FN(node_state) {
    BEGIN(node_state, 14);
    Py_ssize_t np_, nv, nperm;
    const double *position = arg_array(&A, args[0], 'd', 0, 0, "position", &np_);
    if (!position) goto fail;
    const double *velocity = arg_array(&A, args[1], 'd', 0, 0, "velocity", &nv);
    if (!velocity) goto fail;
    const i64 *perm = arg_array(&A, args[2], 'q', 0, 0, "perm", &nperm);
    if (!perm) goto fail;
    for (Py_ssize_t i = 0; i < nperm; i++)
        RANGE(perm[i] >= 0 && perm[i] < np_ && perm[i] < nv, "perm indexes past position");
    IN_F(3, odom, 13);
    IN_F(4, forces, 12);
    DOUBLE(5, threshold);
    OUT_F(6, q, nperm);
    OUT_F(7, dq, nperm);
    OUT_F(8, pb, 3);
    OUT_F(9, quat, 4);
    OUT_F(10, v, 3);
    OUT_F(11, w, 3);
    OUT_F(12, R, 9);
    u8 *contact = arg_array(&A, args[13], '?', 1, 4, "contact", NULL);
    if (!contact) goto fail;
    int status = node_state(position, velocity, perm, nperm, odom, forces, threshold, q, dq, pb,
                            quat, v, w, R, contact);
    DONE(PyLong_FromLong(status));
}

FN(leg_kinematics) {
    BEGIN(leg_kinematics, 9);
    IN_F(0, qj, 12);
    IN_F(1, R, 9);
    IN_F(2, pb, 3);
    IN_F(3, hip, 12);
    IN_F(4, geo, 4 * NGEO);
    OUT_F(5, centre, 12);
    OUT_F(6, contact, 12);
    OUT_F(7, Jf, 36);
    OUT_F(8, Jc, 36);
    leg_kinematics(qj, R, pb, hip, geo, centre, contact, Jf, Jc);
    DONE(Py_NewRef(Py_None));
}

static PyObject *leg_ik_fk(PyObject *self, PyObject *const *args, Py_ssize_t nargs, int ik) {
    BEGIN(leg_ik / leg_fk, 7);
    INT(0, k);
    RANGE(k >= 0 && k < 4, "the leg k must be 0, 1, 2 or 3");
    DOUBLE(1, a);
    DOUBLE(2, b);
    DOUBLE(3, c);
    IN_F(4, hip, 12);
    IN_F(5, geo, 4 * NGEO);
    OUT_F(6, out, 3);
    (ik ? leg_ik : leg_fk)(k, a, b, c, hip, geo, out);
    DONE(Py_NewRef(Py_None));
}

FN(leg_ik) {
    return leg_ik_fk(self, args, nargs, 1);
}
FN(leg_fk) {
    return leg_ik_fk(self, args, nargs, 0);
}

FN(qp_matrices) {
    BEGIN(qp_matrices, 7);
    Py_ssize_t len;
    const double *rh = arg_array(&A, args[0], 'd', 0, 0, "rh", &len);
    if (!rh) goto fail;
    i64 n = arg_dim(&A, 0), m = 3 * n;
    RANGE(len == 3 * n, "rh must be (n, 3)");
    IN_F(1, b, 6);
    IN_F(2, S, 6);
    DOUBLE(3, eps);
    OUT_F(4, Am, 6 * m);
    RANGE(arg_dim(&A, 1) == m, "A must be (6, 3 n)");
    OUT_F(5, H, m * m);
    RANGE(arg_dim(&A, 1) == m, "H must be (3 n, 3 n)");
    OUT_F(6, g, m);
    qp_matrices(rh, n, b, S, eps, Am, H, g);
    DONE(Py_NewRef(Py_None));
}

FN(torque_rows) {
    BEGIN(torque_rows, 7);
    Py_ssize_t len, clen;
    const double *J = arg_array(&A, args[0], 'd', 0, 0, "J", &len);
    if (!J) goto fail;
    i64 n = arg_dim(&A, 0);
    RANGE(len == 9 * n, "J must be (n, 3, 3)");
    IN_F(1, gleg, 3 * n);
    IN_F(2, tmax, 3);
    INT(3, row0);
    double *C = arg_array(&A, args[4], 'd', 1, 0, "C", &clen);
    if (!C) goto fail;
    i64 rows = arg_dim(&A, 0), ncol = arg_dim(&A, 1);
    RANGE(row0 >= 0 && row0 + 3 * n <= rows && 3 * n <= ncol && clen == rows * ncol,
          "C must be (rows, 3 n) with the rows from row0");
    OUT_F(5, lo, rows);
    OUT_F(6, up, rows);
    torque_rows(J, n, gleg, tmax, row0, C, ncol, lo, up);
    DONE(Py_NewRef(Py_None));
}

FN(leg_states) {
    BEGIN(leg_states, 13);
    FLAG(0, trotting);
    DOUBLE(1, t);
    DOUBLE(2, t0);
    DOUBLE(3, T);
    IN_F(4, phase_offsets, 4);
    DOUBLE(5, duty_factor);
    DOUBLE(6, early_touchdown);
    const u8 *grounded = arg_array(&A, args[7], '?', 0, 4, "grounded", NULL);
    if (!grounded) goto fail;
    OUT_F(8, swing_phase, 4);
    OUT_I(9, swing_cycle, 4);
    OUT_I(10, states, 4);
    OUT_F(11, lost_since, 4);
    OUT_I(12, support, 4);
    i64 lift;
    i64 ns = leg_states(trotting, t, t0, T, phase_offsets, duty_factor, early_touchdown, grounded,
                        swing_phase, swing_cycle, states, lost_since, support, &lift);
    DONE(Py_BuildValue("(LL)", (long long)ns, (long long)lift));
}

FN(ground_estimate) {
    BEGIN(ground_estimate, 4);
    DOUBLE(0, ground);
    IN_F(1, contact, 12);
    IN_I(2, support, 0);
    INT(3, ns);
    LEGS(support, ns, 0);
    double g = ground_estimate(ground, contact, support, ns);
    DONE(PyFloat_FromDouble(g));
}

FN(update_plane) {
    BEGIN(update_plane, 5);
    IN_F(0, contact, 12);
    IN_I(1, support, 0);
    INT(2, ns);
    LEGS(support, ns, 0);
    OUT_F(3, footholds, 12);
    OUT_F(4, plane, 3);
    update_plane(contact, support, ns, footholds, plane);
    DONE(Py_NewRef(Py_None));
}

FN(vmc_force) {
    BEGIN(vmc_force, 23);
    IN_I(0, ref, 0);
    INT(1, nr);
    LEGS(ref, nr, 1);
    IN_F(2, contact, 12);
    IN_F(3, pb, 3);
    IN_F(4, vb, 3);
    DOUBLE(5, cy);
    DOUBLE(6, sy);
    DOUBLE(7, z_error);
    DOUBLE(8, max_err);
    IN_F(9, v_cmd, 2);
    IN_F(10, kp, 3);
    IN_F(11, kd, 3);
    IN_F(12, kff, 3);
    FLAG(13, integrate);
    DOUBLE(14, ki);
    DOUBLE(15, lim);
    DOUBLE(16, dt);
    OUT_F(17, f_int, 2);
    DOUBLE(18, mass_g);
    OUT_F(19, e, 3);
    OUT_F(20, vh, 3);
    OUT_F(21, vd, 3);
    OUT_F(22, b, 3);
    vmc_force(ref, nr, contact, pb, vb, cy, sy, z_error, max_err, v_cmd, kp, kd, kff, integrate, ki,
              lim, dt, f_int, mass_g, e, vh, vd, b);
    DONE(Py_NewRef(Py_None));
}

FN(vmc_moment) {
    BEGIN(vmc_moment, 13);
    IN_F(0, er, 3);
    IN_F(1, ww, 3);
    DOUBLE(2, cy);
    DOUBLE(3, sy);
    DOUBLE(4, max_err);
    DOUBLE(5, w_cmd);
    IN_F(6, kp, 3);
    IN_F(7, kd, 3);
    IN_F(8, kff, 3);
    OUT_F(9, eh, 3);
    OUT_F(10, wh, 3);
    OUT_F(11, wd, 3);
    OUT_F(12, b, 6);
    vmc_moment(er, ww, cy, sy, max_err, w_cmd, kp, kd, kff, eh, wh, wd, b);
    DONE(Py_NewRef(Py_None));
}

FN(heading_qp_inputs) {
    BEGIN(heading_qp_inputs, 11);
    IN_I(0, support, 0);
    INT(1, ns);
    LEGS(support, ns, 0);
    IN_F(2, contact, 12);
    IN_F(3, com, 3);
    IN_F(4, Jc, 36);
    IN_F(5, gleg, 12);
    DOUBLE(6, cy);
    DOUBLE(7, sy);
    OUT_F(8, rh, 3 * ns);
    OUT_F(9, Jh, 9 * ns);
    OUT_F(10, gh, 3 * ns);
    heading_qp_inputs(support, ns, contact, com, Jc, gleg, cy, sy, rh, Jh, gh);
    DONE(Py_NewRef(Py_None));
}

FN(support_torques) {
    BEGIN(support_torques, 9);
    IN_I(0, support, 0);
    INT(1, ns);
    LEGS(support, ns, 0);
    IN_F(2, fh, 3 * ns);
    DOUBLE(3, cy);
    DOUBLE(4, sy);
    IN_F(5, Jc, 36);
    IN_F(6, gleg, 12);
    OUT_F(7, fdes, 12);
    OUT_F(8, tau, 12);
    support_torques(support, ns, fh, cy, sy, Jc, gleg, fdes, tau);
    DONE(Py_NewRef(Py_None));
}

FN(position_controlled_torques) {
    BEGIN(position_controlled_torques, 30);
    swing_inputs_t s;
    IN_I(0, states, 4);
    IN_F(1, swing_phase, 4);
    IN_F(2, r_liftoff, 8);
    OUT_F(3, foothold, 8);
    IN_F(4, P, SW_SIZE);
    IN_F(5, foot_radius, 4);
    DOUBLE(6, ground);
    IN_F(7, v_cmd, 2);
    DOUBLE(8, w_cmd);
    IN_F(9, pb, 3);
    IN_F(10, R, 9);
    IN_F(11, vb, 3);
    IN_F(12, ww, 3);
    DOUBLE(13, cy);
    DOUBLE(14, sy);
    IN_F(15, Jf, 36);
    IN_F(16, qj, 12);
    IN_F(17, dqj, 12);
    IN_F(18, gleg, 12);
    IN_F(19, kp, 3);
    IN_F(20, kd, 3);
    IN_F(21, hip, 12);
    IN_F(22, geo, 4 * NGEO);
    OUT_F(23, target, 3);
    OUT_F(24, vt, 3);
    OUT_F(25, tau, 12);
    IN_F(26, liftoff_z, 4);
    IN_F(27, plane, 3);
    OUT_F(28, foothold_z, 4);
    IN_F(29, searching, 16);
    s = (swing_inputs_t){states, swing_phase, r_liftoff, foothold, P,          foot_radius,
                         ground, v_cmd,       w_cmd,     pb,       R,          vb,
                         ww,     cy,          sy,        Jf,       qj,         dqj,
                         gleg,   kp,          kd,        hip,      geo,        target,
                         vt,     tau,         liftoff_z, plane,    foothold_z, searching};
    position_controlled_torques(&s);
    DONE(Py_NewRef(Py_None));
}

#define DEF(name, doc) {#name, (PyCFunction)(void (*)(void))py_##name, METH_FASTCALL, doc}

static PyMethodDef methods[] = {
    DEF(quat_to_rot, "quat_to_rot(qx, qy, qz, qw, R): R of the normalised quaternion."),
    DEF(squared_norm4, "squared_norm4(a) -> |a|² of a 4-vector, summed in order."),
    DEF(read_state, "read_state(qj, dqj, pb, quat, vb, wb, quat_n, R) -> 0, 1 or 2."),
    DEF(node_state,
        "node_state(position, velocity, perm, odom, forces, threshold, q, dq, pb, quat, v, w, R, "
        "contact) -> 0 or 1."),
    DEF(leg_kinematics, "leg_kinematics(qj, R, pb, hip, geo, centre, contact, Jf, Jc)."),
    DEF(leg_ik, "leg_ik(k, r0, r1, r2, hip, geo, out): HAA, HFE, KFE of a foot target."),
    DEF(leg_fk, "leg_fk(k, q0, q1, q2, hip, geo, out): the foot centre (base frame)."),
    DEF(qp_matrices, "qp_matrices(rh, b, S, eps, A, H, g)."),
    DEF(torque_rows, "torque_rows(J, gleg, tmax, row0, C, lo, up)."),
    DEF(leg_states,
        "leg_states(trotting, t, t0, T, phase_offsets, duty_factor, early_touchdown, grounded, "
        "swing_phase, swing_cycle, states, lost_since, support) -> (ns, lift)."),
    DEF(ground_estimate, "ground_estimate(ground, contact, support, ns) -> ground."),
    DEF(update_plane, "update_plane(contact, support, ns, footholds, plane)."),
    DEF(vmc_force,
        "vmc_force(ref, nr, contact, pb, vb, cy, sy, z_error, max_err, v_cmd, kp, kd, kff, "
        "integrate, ki, lim, dt, f_int, mass_g, e, vh, vd, b)."),
    DEF(vmc_moment, "vmc_moment(er, ww, cy, sy, max_err, w_cmd, kp, kd, kff, eh, wh, wd, b)."),
    DEF(heading_qp_inputs,
        "heading_qp_inputs(support, ns, contact, com, Jc, gleg, cy, sy, rh, Jh, gh)."),
    DEF(support_torques, "support_torques(support, ns, fh, cy, sy, Jc, gleg, fdes, tau)."),
    DEF(position_controlled_torques,
        "position_controlled_torques(states, swing_phase, r_liftoff, foothold, P, foot_radius, "
        "ground, v_cmd, w_cmd, pb, R, vb, ww, cy, sy, Jf, qj, dqj, gleg, kp, kd, hip, geo, target, "
        "vt, tau, liftoff_z, plane, foothold_z, searching)."),
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    "_kernels",
    "The controller's per-call arithmetic in C (starleth_controller/csrc).",
    -1,
    methods,
    NULL,
    NULL,
    NULL,
    NULL,
};

PyMODINIT_FUNC PyInit__kernels(void) {
    if (!args_init()) return NULL;
    PyObject *m = PyModule_Create(&module);
    if (!m) return NULL;
    /* the layouts and constants the Python side shares */
    const struct {
        const char *name;
        long value;
    } ints[] = {
        {"SW_T", SW_T},
        {"SW_DUTY", SW_DUTY},
        {"SW_FEEDBACK", SW_FEEDBACK},
        {"SW_MAX", SW_MAX},
        {"SW_INTERP_END", SW_INTERP_END},
        {"SW_HEIGHT", SW_HEIGHT},
        {"SW_DEPTH", SW_DEPTH},
        {"SW_GRAVITY", SW_GRAVITY},
        {"SW_OFFSET_X", SW_OFFSET_X},
        {"SW_STANCE_X", SW_STANCE_X},
        {"SW_STANCE_Y", SW_STANCE_Y},
        {"SW_SIZE", SW_SIZE},
        {"GEOMETRY_COLUMNS", NGEO},
    };
    for (size_t i = 0; i < sizeof(ints) / sizeof(ints[0]); i++)
        if (PyModule_AddIntConstant(m, ints[i].name, ints[i].value) < 0) goto fail;
    if (PyModule_AddObject(m, "LARGE", PyFloat_FromDouble(LARGE)) < 0 ||
        PyModule_AddObject(m, "MAX_SLOPE", PyFloat_FromDouble(MAX_SLOPE)) < 0 ||
        PyModule_AddObject(m, "MIN_SCATTER", PyFloat_FromDouble(MIN_SCATTER)) < 0)
        goto fail;
    return m;
fail:
    Py_DECREF(m);
    return NULL;
}
