/* Bindings of the linear algebra, kinematics, dynamics, forest and contact kernels. */
#include "bind.h"

/* the model's arrays as the bindings take them: tuples grouped like the C structs (tree_t,
 * frames_t, inertias_t, contact_points_t, ground_t) */
#define TREE_ARRAYS                                                                     \
    {"tree", GROUP + 8}, {"parent", I64}, {"jtype", I64}, {"axis", F64}, {"pl_R", F64}, \
        {"pl_p", F64}, {"idx_q", I64}, {"idx_v", I64}, {                                \
        "support", BOOL                                                                 \
    }
#define FRAME_ARRAYS                       \
    {"frames", GROUP + 2}, {"oR", F64W}, { \
        "op", F64W                         \
    }
#define INERTIA_ARRAYS                                                          \
    {"inertias", GROUP + 4}, {"mass", F64}, {"lever", F64}, {"inertia", F64}, { \
        "gravity", F64                                                          \
    }
#define CONTACT_ARRAYS                                             \
    {"contacts", GROUP + 3}, {"c_joint", I64}, {"c_local", F64}, { \
        "c_radius", F64                                            \
    }
#define GROUND_ARRAYS                                                             \
    {"ground", GROUP + 5}, {"normal", F64}, {"tangent1", F64}, {"tangent2", F64}, \
        {"ground_offset", FLOAT}, {                                               \
        "terrain", F64                                                            \
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
    RUN(a, failed,
        ltdl_solve_cols_pattern(v[0].p, v[1].p, v[2].p, n, m, v[3].p, v[4].p, a, &ptr, &idx));
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
    if (!need(v[0].nd == 2 && v[0].shape[1] == nA && n >= 0 && v[2].len == n * n && v[3].len == n,
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
    if (!need(v[0].len == n * n && v[1].len == n && v[2].len == n + 1, "cholesky_solve_envelope",
              "sizes do not match"))
        FAIL;
    cholesky_solve_envelope(v[0].p, n, v[1].p, v[2].p, v[3].p, v[4].p);
    release(&h);
    Py_RETURN_NONE;
}

/* ---------------------------------------------------------------------------------------
 * kinematics, dynamics, forest
 * ------------------------------------------------------------------------------------- */
FN(quat_xyzw_to_rot) {
    static const spec_t spec[] = {
        {"x", FLOAT}, {"y", FLOAT}, {"z", FLOAT}, {"w", FLOAT}, {"R", F64W}};
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
    if (!tree_of("forward_kinematics", &v[1], &v[2], &v[3], &v[4], &v[5], &v[6], NULL, NULL, 0,
                 &t) ||
        !frames_of("forward_kinematics", &v[7], &v[8], t.nj, &f))
        FAIL;
    forward_kinematics(v[0].p, &t, &f);
    release(&h);
    Py_RETURN_NONE;
}

FN(point_jacobian) {
    static const spec_t spec[] = {{"j", INT},     {"p", F64},        {"jtype", I64}, {"axis", F64},
                                  {"idx_v", I64}, {"support", BOOL}, {"oR", F64},    {"op", F64},
                                  {"out", F64W},  {"zero", FLAG}};
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
    static const spec_t spec[] = {{"j", INT},        {"jtype", I64}, {"axis", F64}, {"idx_v", I64},
                                  {"support", BOOL}, {"oR", F64},    {"out", F64W}, {"zero", FLAG}};
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
                     double offset, const val_t *terrain, const val_t *frames, i64 nc,
                     ground_t *g) {
    if (!need(n->len == 3 && t1->len == 3 && t2->len == 3, fn,
              "the ground's n, t1, t2 must be 3-vectors") ||
        !need(terrain->len >= 16, fn, "terrain must be a packed terrain (terrain.pack_terrain)") ||
        !need(!frames->p || frames->len == FRAME_STRIDE * nc, fn, "frames must be nc x 11 or None"))
        return 0;
    g->n = n->p;
    g->t1 = t1->p;
    g->t2 = t2->p;
    g->offset = offset;
    g->n_terrain = terrain->len;
    g->terrain = terrain->p;
    g->frames = frames->p;
    return 1;
}

static int contact_outputs(const char *fn, const val_t *gap, const val_t *position, const val_t *Wt,
                           i64 nc, i64 nv) {
    return need(gap->len == nc && position->len == 3 * nc && Wt->len == 3 * nc * nv, fn,
                "gap (nc), position (nc x 3) and Wt (nc x 3 x nv) do not match the contacts");
}

/* contact_kinematics(q, model, ground, jacobian_gap, out, frames=None): model = (tree,
 * (oR, op), (c_joint, c_local, c_radius)), ground = (n, t1, t2, offset, terrain), out =
 * (gap, position, Wt) */
FN(contact_kinematics) {
    static const spec_t spec[] = {{"q", F64},
                                  {"model", GROUP + 3},
                                  TREE_ARRAYS,
                                  FRAME_ARRAYS,
                                  CONTACT_ARRAYS,
                                  GROUND_ARRAYS,
                                  {"jacobian_gap", FLOAT},
                                  {"out", GROUP + 3},
                                  {"gap", F64W},
                                  {"position", F64W},
                                  {"Wt", F64W},
                                  {"frames", F64N}};
    val_t v[24];
    v[23].p = NULL; /* (frames is optional) */
    v[23].len = 0;
    held_t h = {.n = 0};
    tree_t t;
    frames_t f;
    contact_points_t c;
    ground_t g;
    if (!PARSE("contact_kinematics", spec, 5, v, &h)) FAIL;
    i64 nv = v[22].nd == 3 ? v[22].shape[2] : 0;
    if (!tree_of("contact_kinematics", &v[1], &v[2], &v[3], &v[4], &v[5], &v[6], &v[7], &v[8], nv,
                 &t) ||
        !frames_of("contact_kinematics", &v[9], &v[10], t.nj, &f) ||
        !contacts_of("contact_kinematics", &v[11], &v[12], &v[13], &c) ||
        !ground_of("contact_kinematics", &v[14], &v[15], &v[16], v[17].f, &v[18], &v[23], c.nc,
                   &g) ||
        !contact_outputs("contact_kinematics", &v[20], &v[21], &v[22], c.nc, nv))
        FAIL;
    contact_kinematics(v[0].p, &t, &f, &c, &g, v[19].f, v[20].p, v[21].p, v[22].p);
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
    if (!tree_of("integrate_forest", NULL, &v[3], NULL, NULL, NULL, &v[4], &v[5], NULL, v[1].len,
                 &t) ||
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
    static const spec_t spec[] = {{"M_pin", F64}, {"h_pin", F64}, {"Rs", F64}, {"root_v", I64},
                                  {"u_pin", F64}, {"M", F64W},    {"h", F64W}};
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

static int inertias_of(const char *fn, const val_t *mass, const val_t *lever, const val_t *inertia,
                       const val_t *gravity, i64 nj, inertias_t *b) {
    if (!need(
            mass->len == nj && lever->len == 3 * nj && inertia->len == 9 * nj && gravity->len == 3,
            fn, "mass, lever, inertia and gravity do not match the joints"))
        return 0;
    b->mass = mass->p;
    b->lever = lever->p;
    b->inertia = inertia->p;
    b->gravity = gravity->p;
    return 1;
}

/* tree_dynamics(q, u, model, out): model = (tree, (oR, op), (mass, lever, inertia,
 * gravity)), out = (M, h) */
FN(tree_dynamics) {
    static const spec_t spec[] = {{"q", F64},         {"u", F64},   {"model", GROUP + 3},
                                  TREE_ARRAYS,        FRAME_ARRAYS, INERTIA_ARRAYS,
                                  {"out", GROUP + 2}, {"M", F64W},  {"h", F64W}};
    val_t v[18];
    held_t h = {.n = 0};
    tree_t t;
    frames_t f;
    inertias_t b;
    if (!PARSE("tree_dynamics", spec, 4, v, &h)) FAIL;
    i64 nv = v[1].len;
    if (!tree_of("tree_dynamics", &v[2], &v[3], &v[4], &v[5], &v[6], &v[7], &v[8], NULL, nv, &t) ||
        !frames_of("tree_dynamics", &v[10], &v[11], t.nj, &f) ||
        !inertias_of("tree_dynamics", &v[12], &v[13], &v[14], &v[15], t.nj, &b) ||
        !need(v[16].len == nv * nv && v[17].len == nv, "tree_dynamics", "M must be nv x nv, h nv"))
        FAIL;
    tree_dynamics(v[0].p, v[1].p, &t, &f, &b, v[16].p, v[17].p);
    release(&h);
    Py_RETURN_NONE;
}

/* midpoint_dynamics(q, u, half_dt, model, ground, jacobian_gap, out, frames=None): model =
 * (tree, (oR, op), (mass, lever, inertia, gravity), (c_joint, c_local, c_radius)), ground =
 * (n, t1, t2, offset, terrain), out = (qM, M, h, gap, position, Wt) */
FN(midpoint_dynamics) {
    static const spec_t spec[] = {{"q", F64},         {"u", F64},
                                  {"half_dt", FLOAT}, {"model", GROUP + 4},
                                  TREE_ARRAYS,        FRAME_ARRAYS,
                                  INERTIA_ARRAYS,     CONTACT_ARRAYS,
                                  GROUND_ARRAYS,      {"jacobian_gap", FLOAT},
                                  {"out", GROUP + 6}, {"qM", F64W},
                                  {"M", F64W},        {"h", F64W},
                                  {"gap", F64W},      {"position", F64W},
                                  {"Wt", F64W},       {"frames", F64N}};
    val_t v[33];
    v[32].p = NULL; /* (frames is optional) */
    v[32].len = 0;
    held_t h = {.n = 0};
    tree_t t;
    frames_t f;
    inertias_t b;
    contact_points_t c;
    ground_t g;
    if (!PARSE("midpoint_dynamics", spec, 7, v, &h)) FAIL;
    i64 nv = v[1].len;
    if (!tree_of("midpoint_dynamics", &v[3], &v[4], &v[5], &v[6], &v[7], &v[8], &v[9], &v[10], nv,
                 &t) ||
        !frames_of("midpoint_dynamics", &v[11], &v[12], t.nj, &f) ||
        !inertias_of("midpoint_dynamics", &v[13], &v[14], &v[15], &v[16], t.nj, &b) ||
        !contacts_of("midpoint_dynamics", &v[17], &v[18], &v[19], &c) ||
        !ground_of("midpoint_dynamics", &v[20], &v[21], &v[22], v[23].f, &v[24], &v[32], c.nc,
                   &g) ||
        !need(v[26].len == v[0].len && v[27].len == nv * nv && v[28].len == nv, "midpoint_dynamics",
              "qM, M and h do not match q and u") ||
        !contact_outputs("midpoint_dynamics", &v[29], &v[30], &v[31], c.nc, nv))
        FAIL;
    midpoint_dynamics(v[0].p, v[1].p, v[2].f, &t, &f, &b, &c, &g, v[25].f, v[26].p, v[27].p,
                      v[28].p, v[29].p, v[30].p, v[31].p);
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
    static const spec_t spec[] = {{"q", F64},       {"u", F64},    {"root_q", I64},
                                  {"root_v", I64},  {"mass", F64}, {"inertia", F64},
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

/* cut_joints(q, u, model, cuts, out, do_fk): model = (tree, (oR, op)), cuts = (cut_P, cut_C,
 * p_P, p_C, a_P, b1_P, b2_P, a_C, b1_C), out = (Wt_B, g_B, angle, rate, axis_world) */
FN(cut_joints) {
    static const spec_t spec[] = {
        {"q", F64},           {"u", F64},     {"model", GROUP + 2}, TREE_ARRAYS,     FRAME_ARRAYS,
        {"cuts", GROUP + 9},  {"cut_P", I64}, {"cut_C", I64},       {"p_P", F64},    {"p_C", F64},
        {"a_P", F64},         {"b1_P", F64},  {"b2_P", F64},        {"a_C", F64},    {"b1_C", F64},
        {"out", GROUP + 5},   {"Wt_B", F64W}, {"g_B", F64W},        {"angle", F64W}, {"rate", F64W},
        {"axis_world", F64W}, {"do_fk", FLAG}};
    val_t v[27];
    held_t h = {.n = 0};
    volatile int failed = 0;
    tree_t t;
    frames_t f;
    cuts_t c;
    if (!PARSE("cut_joints", spec, 6, v, &h)) FAIL;
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
    RUN(a, failed,
        cut_joints(v[0].p, v[1].p, &t, &f, &c, v[21].p, v[22].p, v[23].p, v[24].p, v[25].p,
                   (int)v[26].i, a));
    DONE_NONE;
}

FN(gather_joint_values) {
    static const spec_t spec[] = {
        {"x", F64}, {"index", I64}, {"cut_values", F64}, {"cut_index", I64}, {"out", F64W}};
    val_t v[5];
    held_t h = {.n = 0};
    if (!PARSE("gather_joint_values", spec, 5, v, &h)) FAIL;
    i64 n = v[4].len;
    if (!need(v[1].len >= n && v[3].len >= n, "gather_joint_values", "index arrays too short"))
        FAIL;
    gather_joint_values(v[0].p, v[1].p, v[2].p, v[3].p, n, v[4].p);
    release(&h);
    Py_RETURN_NONE;
}

FN(cut_joint_torques) {
    static const spec_t spec[] = {{"tau_cut", F64},  {"cuts", GROUP + 3}, {"cut_P", I64},
                                  {"cut_C", I64},    {"axis_world", F64}, {"tree", GROUP + 4},
                                  {"jtype", I64},    {"axis", F64},       {"idx_v", I64},
                                  {"support", BOOL}, {"oR", F64},         {"h", F64W}};
    val_t v[10];
    held_t h = {.n = 0};
    volatile int failed = 0;
    tree_t t;
    cuts_t c;
    if (!PARSE("cut_joint_torques", spec, 5, v, &h)) FAIL;
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
FN(saturate_torque) {
    static const spec_t spec[] = {
        {"tau", F64}, {"limit", F64}, {"qd", F64}, {"qd_limit", F64}, {"out", F64W}};
    val_t v[5];
    held_t h = {.n = 0};
    if (!PARSE("saturate_torque", spec, 5, v, &h)) FAIL;
    i64 n = v[0].len;
    if (!need(v[1].len >= n && v[2].len >= n && v[3].len >= n && v[4].len >= n, "saturate_torque",
              "limit, qd, qd_limit and out need an entry per torque"))
        FAIL;
    int ok = saturate_torque(v[0].p, v[1].p, v[2].p, v[3].p, v[4].p, n);
    release(&h);
    return PyBool_FromLong(ok);
}
