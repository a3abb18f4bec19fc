/* Bindings of the prox kernels and the step phases. */
#include "bind.h"

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

FN(row_pattern) {
    return pattern_of(args, nargs, 0);
}
FN(col_pattern) {
    return pattern_of(args, nargs, 1);
}

FN(prox_parameters) {
    static const spec_t spec[] = {{"Gdiag", F64}, {"nc", INT}, {"alpha", FLOAT}, {"r", F64W}};
    val_t v[4];
    held_t h = {.n = 0};
    if (!PARSE("prox_parameters", spec, 4, v, &h)) FAIL;
    i64 m = v[0].len;
    if (!need(v[3].len == m && v[1].i >= 0 && 3 * v[1].i <= m, "prox_parameters",
              "r must have Gdiag's length and 3 nc rows fit"))
        FAIL;
    prox_parameters(v[0].p, m, v[1].i, v[2].f, v[3].p);
    release(&h);
    Py_RETURN_NONE;
}

FN(delassus) {
    static const spec_t spec[] = {{"Wt", F64},     {"MinvW", F64},  {"G", F64W},    {"wp_ptr", I64},
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
    return need(MinvW->len == *nv * *m && (s->form != FORM_DELASSUS || G->len == *m * *m), fn,
                "Wt (m x nv), MinvW (nv x m) and G (m x m, Delassus form) do not match");
}

FN(auto_spectral_scale) {
    static const spec_t spec[] = {{"s", OBJ},   {"G", F64},  {"Wt", F64}, {"MinvW", F64},
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
    RUN(a, failed,
        lam = auto_spectral_scale(&s, v[1].p, v[2].p, v[3].p, &pat, m, nv, v[5].i, v[6].p, a));
    release(&h);
    if (failed) return PyErr_NoMemory();
    return PyFloat_FromDouble(lam);
}

FN(prox_solve) {
    static const spec_t spec[] = {{"s", OBJ},
                                  {"pat", OBJ},
                                  {"problem", GROUP + 6},
                                  {"Wt", F64},
                                  {"MinvW", F64},
                                  {"u_free", F64},
                                  {"bvec", F64},
                                  {"G", F64},
                                  {"c", F64},
                                  {"contacts", GROUP + 3},
                                  {"nc", INT},
                                  {"mu", F64},
                                  {"r", F64},
                                  {"lam", F64W},
                                  {"direct", GROUP + 2},
                                  {"LB", F64},
                                  {"M", F64},
                                  {"u", F64W}};
    val_t v[15];
    held_t h = {.n = 0};
    volatile int failed = 0;
    settings_t s;
    patterns_t pat;
    i64 m, nv;
    if (!PARSE("prox_solve", spec, 7, v, &h) || !get_settings(v[0].o, "prox_solve", &s) ||
        !get_patterns(v[1].o, "prox_solve", &h, &pat) ||
        !problem_sizes("prox_solve", &v[2], &v[3], &v[6], &s, &m, &nv))
        FAIL;
    i64 nc = v[8].i;
    i64 nb_LB = v[12].nd == 2 ? v[12].shape[0] : 0;
    if (!need(
            nc >= 0 && 3 * nc <= m && v[4].len == nv && v[5].len == m &&
                (s.form != FORM_DELASSUS || v[7].len == m) && v[9].len >= nc && v[10].len == m &&
                v[11].len == m && v[14].len == nv &&
                (s.criterion != CRITERION_ENERGY || v[13].len == nv * nv) &&
                (!s.bilateral_direct || m == 3 * nc || (nb_LB == m - 3 * nc && pat.n_lb == nb_LB)),
            "prox_solve", "the arrays do not match the problem's m rows and nv velocities"))
        FAIL;
    prox_result_t res = {0, 0, 0.0};
    arena_t *a = scratch_arena();
    RUN(a, failed,
        res = prox_solve(&s, &pat, v[2].p, v[3].p, v[4].p, v[5].p, v[6].p, v[7].p, m, nv, nc,
                         v[9].p, v[10].p, NULL, v[11].p, v[12].p, nb_LB, v[13].p, v[14].p, a));
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
