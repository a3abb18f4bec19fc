/* starleth_sim.physics.kernels: the Python bindings of the C kernels.
 *
 * Each function takes the arguments of the Python function of the same name that
 * starleth_sim.physics documents (numpy arrays, C-contiguous, of float64, int64 or bool,
 * and scalars), checks their kinds, and calls the kernel. A numpy array is read from the
 * array itself where the build found numpy's headers (numpy_api.h), any other argument and
 * every array of a build without them through the buffer protocol (bind.c); the few results
 * that are new arrays are made by numpy.empty. The one-kernel steps, which run for
 * every physics step, check the sizes of everything they touch and release the GIL. Work
 * arrays come from the calling thread's scratch arena, emptied on every call. The argument
 * helpers are in bind.c (bind.h). */
#define KERNEL_LAYOUTS_DEFINE_TYPES /* the result types' definitions (kernel_layouts.h) */
#include "bind.h"

#define STARLETH_NUMPY_IMPORT
#include "numpy_api.h"

/* The module: its functions (the bindings of bind_geometry.c, bind_prox.c and bind_step.c),
 * the constants the Python side shares with the kernels, the ContactProblem type. */
#define DEF(name, doc) {#name, (PyCFunction)(void (*)(void))py_##name, METH_FASTCALL, doc}

static PyMethodDef methods[] = {
    DEF(ltdl, "ltdl(A, dof_parent, L) -> bool: the LTDL factor of M (linalg.ltdl)."),
    DEF(ltdl_solve_vec, "ltdl_solve_vec(L, dof_parent, b): (LᵀDL) x = b in place."),
    DEF(ltdl_solve_cols, "ltdl_solve_cols(L, dof_parent, B): (LᵀDL) X = B in place."),
    DEF(ltdl_solve_cols_pattern,
        "ltdl_solve_cols_pattern(L, dof_parent, B, ptr, idx) -> (ptr, idx)."),
    DEF(cholesky_upper_input, "cholesky_upper_input(A, o, L, first) -> bool."),
    DEF(cholesky_solve_vec, "cholesky_solve_vec(L, first, b)."),
    DEF(envelope_columns, "envelope_columns(first) -> (ptr, idx)."),
    DEF(cholesky_solve_envelope, "cholesky_solve_envelope(L, first, col_ptr, col_idx, b)."),
    DEF(quat_xyzw_to_rot, "quat_xyzw_to_rot(x, y, z, w, R)."),
    DEF(quat_rot, "quat_rot(q, iq, R): the rotation of the root at q[iq]."),
    DEF(forward_kinematics,
        "forward_kinematics(q, parent, jtype, axis, pl_R, pl_p, idx_q, oR, op)."),
    DEF(point_jacobian,
        "point_jacobian(j, p, jtype, axis, idx_v, support, oR, op, out, zero=True)."),
    DEF(angular_jacobian, "angular_jacobian(j, jtype, axis, idx_v, support, oR, out, zero=True)."),
    DEF(contact_kinematics,
        "contact_kinematics(q, model, ground, jacobian_gap, out, frames=None): model (tree, "
        "frames, contacts), ground (n, t1, t2, offset, terrain), out (gap, position, Wt)."),
    DEF(integrate_forest, "integrate_forest(q, u, dt, jtype, idx_q, idx_v, out)."),
    DEF(to_pin_velocity, "to_pin_velocity(q, u, roots, root_q, root_v, Rs, u_pin)."),
    DEF(from_pin_dynamics, "from_pin_dynamics(M_pin, h_pin, Rs, root_v, u_pin, M, h)."),
    DEF(tree_dynamics,
        "tree_dynamics(q, u, model, out): model (tree, frames, inertias), out (M, h)."),
    DEF(midpoint_dynamics,
        "midpoint_dynamics(q, u, half_dt, model, ground, jacobian_gap, out, frames=None): model "
        "(tree, frames, inertias, contacts), out (qM, M, h, gap, position, Wt)."),
    DEF(add_at, "add_at(h, idx, values): h[idx[k]] += values[k]."),
    DEF(rigid_body_forces, "rigid_body_forces(q, u, root_q, root_v, mass, inertia, gravity, h)."),
    DEF(cut_joints,
        "cut_joints(q, u, model, cuts, out, do_fk): model (tree, frames), cuts (cut_P, cut_C, p_P, "
        "p_C, a_P, b1_P, b2_P, a_C, b1_C), out (Wt_B, g_B, angle, rate, axis_world)."),
    DEF(gather_joint_values, "gather_joint_values(x, index, cut_values, cut_index, out)."),
    DEF(cut_joint_torques,
        "cut_joint_torques(tau_cut, (cut_P, cut_C, axis_world), (jtype, axis, idx_v, support), oR, "
        "h)."),
    DEF(saturate_torque, "saturate_torque(tau, limit, qd, qd_limit, out) -> bool."),
    DEF(row_pattern, "row_pattern(A) -> (ptr, idx)."),
    DEF(col_pattern, "col_pattern(A) -> (ptr, idx)."),
    DEF(prox_parameters, "prox_parameters(Gdiag, nc, alpha, r)."),
    DEF(delassus, "delassus(Wt, MinvW, G, wp_ptr, wp_idx, mp_ptr, mp_idx): G = W^T M^{-1} W."),
    DEF(delassus_diagonal, "delassus_diagonal(Wt, MinvW, d, wp_ptr, wp_idx)."),
    DEF(auto_spectral_scale, "auto_spectral_scale(s, G, Wt, MinvW, pat, nc, r) -> float."),
    DEF(prox_solve,
        "prox_solve(s, pat, (Wt, MinvW, u_free, bvec, G, c), (nc, mu, r), lam, (LB, M), u) -> "
        "(iterations, status, residual)."),
    DEF(free_velocity, "free_velocity(h, dt, uS, dof_parent, L, u_free)."),
    DEF(constraint_velocity, "constraint_velocity(Wt, u_free, bvec, wp_ptr, wp_idx, c)."),
    DEF(prepare_hard_contacts,
        "prepare_hard_contacts(settings, (M, uS), (gap, Wt_all, WtB, bB, eps), (dof_parent, "
        "factor, L), (last_impulse, last_active), timings, frames=None, problem=None) -> "
        "ContactProblem."),
    DEF(impedance_torque, "impedance_torque(command, q, qd, out): the joint impedance law."),
    DEF(tree_step_hard,
        "tree_step_hard(options, torque_mode, state, tau, f_ext, out, model) -> TreeStepResult: "
        "state (q, u, last_impulse, last_active, last_bilateral), out (report, is_active, qE, uE), "
        "model (floats, ints, support, workspace)."),
    DEF(tree_step_compliant,
        "tree_step_compliant(options, torque_mode, state, tau, f_ext, out, model) -> "
        "TreeStepResult: state (q, u, closed, slip, anchor, lam)."),
    DEF(forest_step,
        "forest_step(options, state, tau, f_ext, out, model, cut) -> TreeStepResult: state (q, u, "
        "last_impulse, last_active, last_bilateral, closed, slip, anchor, lam), out (report, "
        "is_active, qE, uE, angle_E, rate_E), cut (cut_floats, cut_ints, cut_workspace)."),
    DEF(scratch_arena_stats,
        "scratch_arena_stats() -> (misses, capacity [bytes], bytes the last call wanted) of this "
        "thread's scratch arena."),
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT,
                                    "_kernels",
                                    "The physics kernels of the StarlETH simulator, in C.",
                                    -1,
                                    methods,
                                    NULL,
                                    NULL,
                                    NULL,
                                    NULL};

PyMODINIT_FUNC PyInit__kernels(void) {
    if (PyType_Ready(&ProblemType) < 0 || PyType_Ready(&TreeStepType) < 0 ||
        PyType_Ready(&ControlPeriodType) < 0)
        return NULL;
#ifdef STARLETH_NUMPY_C_API
    import_array();
#endif
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
        {"JT_FREEFLYER", JT_FREEFLYER},
        {"JT_REVOLUTE", JT_REVOLUTE},
        {"SCHEME_JOR", SCHEME_JOR},
        {"SCHEME_SOR", SCHEME_SOR},
        {"FORM_DELASSUS", FORM_DELASSUS},
        {"FORM_VELOCITY", FORM_VELOCITY},
        {"CRITERION_IMPULSE", CRITERION_IMPULSE},
        {"CRITERION_ENERGY", CRITERION_ENERGY},
        {"STATUS_CONVERGED", STATUS_CONVERGED},
        {"STATUS_MAX_ITER", STATUS_MAX_ITER},
        {"STATUS_NONFINITE", STATUS_NONFINITE},
        {"STATUS_STALLED", STATUS_STALLED},
        {"AUTO_POWER_ITERATIONS", AUTO_POWER_ITERATIONS},
        {"DELASSUS_ENVELOPE_ROWS", DELASSUS_ENVELOPE_ROWS},
        {"PHASE_M_AND_H", PHASE_M_AND_H},
        {"PHASE_M_INVERSE", PHASE_M_INVERSE},
        {"PHASE_G", PHASE_G},
        {"PHASE_PROX", PHASE_PROX},
        {"PHASE_REST", PHASE_REST},
        {"TREE_STEP_OK", TREE_STEP_OK},
        {"TREE_STEP_NOT_PD", TREE_STEP_NOT_PD},
        {"TREE_STEP_NONFINITE_IMPULSE", TREE_STEP_NONFINITE_IMPULSE},
        {"TREE_STEP_NONFINITE_STATE", TREE_STEP_NONFINITE_STATE},
        {"TREE_STEP_NONFINITE_TORQUE", TREE_STEP_NONFINITE_TORQUE},
        {"TORQUE_AS_GIVEN", TORQUE_AS_GIVEN},
        {"TORQUE_SATURATED", TORQUE_SATURATED},
        {"TORQUE_IMPEDANCE", TORQUE_IMPEDANCE},
        {"TORQUE_REPLAY", TORQUE_REPLAY},
        {"STEP_PROFILE", STEP_PROFILE},
        {"STEP_PREPARE", STEP_PREPARE},
        {"STEP_PREPARED", STEP_PREPARED},
        {"STEP_COMPLIANT", STEP_COMPLIANT},
        {"STEP_KEEP_FACTOR", STEP_KEEP_FACTOR},
#ifdef STARLETH_NUMPY_C_API /* numpy arrays read without the buffer protocol (bind.c) */
        {"NUMPY_C_API", 1},
#else
        {"NUMPY_C_API", 0},
#endif
    };
    static const struct {
        const char *name;
        double value;
    } floats[] = {
        {"ALPHA_AUTO", ALPHA_AUTO},
        {"AUTO_MAX_STEP", AUTO_MAX_STEP},
        {"AUTO_GUARD", AUTO_GUARD},
        {"AUTO_SOR_BILATERAL_OMEGA", AUTO_SOR_BILATERAL_OMEGA},
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
    if (add_result_types(m) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    Py_INCREF(&ProblemType);
    if (PyModule_AddObject(m, "ContactProblem", (PyObject *)&ProblemType) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    Py_INCREF(&TreeStepType);
    Py_INCREF(&ControlPeriodType);
    if (PyModule_AddObject(m, "TreeStep", (PyObject *)&TreeStepType) < 0 ||
        PyModule_AddObject(m, "ControlPeriod", (PyObject *)&ControlPeriodType) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
