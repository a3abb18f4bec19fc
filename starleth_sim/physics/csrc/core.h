/* The physics kernels of the StarlETH simulator in C: Moreau's midpoint time-stepping
 * (Gehring et al. 2014, Eqn. 6-8), the prox solvers (Eqn. 12-20), the compliant contact law
 * (Alg. 1), the rigid-body algorithms and the kinematics of a forest of floating trees.
 *
 * Built at install time into the extension module starleth_sim.physics.kernels (module.c
 * and bind*.c hold its Python bindings; starleth_sim/physics/kernels/__init__.py loads it and rebuilds
 * it when these sources changed). The Python modules of starleth_sim.physics describe each
 * algorithm; the functions here have the names of the Python functions they implement.
 *
 * Conventions
 *  - Arrays are C-contiguous (row-major); a 2-d array A of n columns is A[r * n + c]. The
 *    dimensions travel as arguments (or in the records below).
 *  - Indices and counts are int64 (i64), flags of numpy bool arrays are bytes (u8).
 *  - Every formula keeps the operation order of the original (Python) formula, with IEEE
 *    double arithmetic and no contraction into fused multiply-adds (-ffp-contract=off): the
 *    results are bit for bit those of the numba kernels these functions replaced.
 *    min / max follow Python's (and numba's) rule: max(a, b) is b only when b > a
 *    (py_max), which decides the sign of a zero and what a NaN gives.
 *  - Work arrays come from an arena (arena_t): a bump allocator that is emptied by the
 *    entry point that owns it. A request that does not fit is served by malloc and counted
 *    (the arena grows to fit next time); if memory runs out, arena_alloc jumps back to the
 *    entry point (arena_t.oom), which reports a MemoryError.
 */
#ifndef STARLETH_CORE_H
#define STARLETH_CORE_H

#include <math.h>
#include <setjmp.h>
#include <stddef.h>
#include <stdint.h>

/* py_max / py_min (Python's rule), quat_xyzw_to_rot: shared with the controller's kernels */
#include "bitexact_math.h"

typedef int64_t i64;
typedef uint8_t u8;

/* ---------------------------------------------------------------------------------------
 * Arena (arena.c)
 * ------------------------------------------------------------------------------------- */
typedef struct arena_chunk arena_chunk;

typedef struct {
    char *base;         /* the block requests are carved from */
    size_t cap;         /* its size [bytes] */
    size_t used;        /* bytes handed out since the last reset */
    size_t wanted;      /* bytes asked since the last reset (fitting or not) */
    arena_chunk *extra; /* malloc'd blocks of the requests that did not fit */
    i64 misses;         /* requests that did not fit, since the arena was made */
    jmp_buf *oom;       /* where arena_alloc jumps when malloc fails (set by the entry) */
} arena_t;

void arena_init(arena_t *a, size_t cap);
void arena_free(arena_t *a);
/* Empties the arena (frees the blocks of misses; when the last use wanted more than the
 * block holds, the block grows to that). Everything handed out before is invalid. */
void arena_reset(arena_t *a);
/* n bytes, 64-byte aligned, uninitialised. */
void *arena_alloc(arena_t *a, size_t n);
static inline double *arena_f(arena_t *a, i64 n) {
    return (double *)arena_alloc(a, (size_t)(n > 0 ? n : 0) * sizeof(double));
}
static inline i64 *arena_i(arena_t *a, i64 n) {
    return (i64 *)arena_alloc(a, (size_t)(n > 0 ? n : 0) * sizeof(i64));
}
static inline double *arena_zeros(arena_t *a, i64 n) {
    double *p = arena_f(a, n);
    for (i64 k = 0; k < n; k++) p[k] = 0.0;
    return p;
}
/* The calling thread's scratch arena (module entry points reset it on entry). */
arena_t *scratch_arena(void);

/* Profiling clock (step_kernels' clock / lap): seconds of CLOCK_MONOTONIC. With timings NULL
 * (not profiling) clock returns 0 and lap does nothing. */
double clock_now(void);
static inline double kclock(double *timings) {
    return timings ? clock_now() : 0.0;
}
static inline double klap(double *timings, int phase, double since) {
    if (!timings) return 0.0;
    double t = clock_now();
    timings[phase] += t - since;
    return t;
}

/* ---------------------------------------------------------------------------------------
 * Records
 * ------------------------------------------------------------------------------------- */

/* prox.py's constants */
enum { SCHEME_JOR = 0, SCHEME_SOR = 1 };
enum { FORM_DELASSUS = 0, FORM_VELOCITY = 1 };
enum { CRITERION_IMPULSE = 0, CRITERION_ENERGY = 1 };
enum { STATUS_CONVERGED = 0, STATUS_MAX_ITER = 1, STATUS_NONFINITE = 2, STATUS_STALLED = 3 };
/* a prox solve stalls when the best residual of a window of stall_window sweeps is not below
 * STALL_FACTOR times the best of the window before (prox.c, stall_seen): 1 % better over a
 * window, so that a slow but steady solve (the maximal coordinates' bilateral prox rows) goes
 * on and only one that cycles (JOR at α = 0.6 on a robot at rest) ends early */
#define STALL_FACTOR 0.99
/* a Delassus-form solve whose last step's solve took LAZY_DELASSUS_LAST sweep (the warm
 * start was its solution: a robot at rest), with the same active set, first tries up to
 * LAZY_DELASSUS_SWEEPS in the velocity form (G not formed), and forms G only when they do not
 * converge (step_kernels.c; a failed try's sweeps are lost: with a last of up to 4 sweeps,
 * HEJP standing at α 0.9 took 6.0 sweeps per step instead of 4.6) */
#define LAZY_DELASSUS_SWEEPS 4
/* the direct bilateral method in the Delassus form: after this many sweeps of a solve, Λ_B =
 * −G_BB^{-1} (G_BU Λ_U + c_B) by the gain X = G_BB^{-1} [G_BU, c_B], solved once for every
 * column, instead of one solve with L_B per sweep (prox.c, direct_bilateral) */
#define DIRECT_GAIN_SWEEPS       3
#define LAZY_DELASSUS_LAST       1
#define ALPHA_AUTO               (-1.0)
#define AUTO_MAX_STEP            1.0e3
#define AUTO_GUARD               1.0e3
#define AUTO_POWER_ITERATIONS    16
#define AUTO_SOR_BILATERAL_OMEGA 1.5
#define DELASSUS_ENVELOPE_ROWS   24

/* Fig. 7 phases (step_kernels.PHASES), indices into a profiling `timings` array */
enum { PHASE_M_AND_H = 0, PHASE_M_INVERSE = 1, PHASE_G = 2, PHASE_PROX = 3, PHASE_REST = 4 };

/* step_kernels.StepSettings (the prox kernels read form, scheme, tol_rel, tol_abs,
 * max_iterations, criterion, bilateral_direct and alpha: prox.ProxSettings) */
typedef struct {
    double activation_gap, mu, alpha, tol_rel, tol_abs, fallback_alpha_factor, opening_gap, dt,
        beta_velocity, beta_projection, jacobian_gap, projection_tolerance, bilateral_relaxation;
    i64 form, scheme, max_iterations, criterion, stall_window, fallback_hold;
    int warm_start, bilateral_direct, hysteresis;
} settings_t;

/* prox.Patterns: CSR nonzero patterns (ptr, idx) of the rows of W^T (wp: m + 1 pointers),
 * the columns of M^{-1}W (mp: m + 1) and the rows of G (gp: m + 1; all zero in the velocity
 * form), and lb_first (n_lb entries): the envelope of L_B (direct bilateral method). */
typedef struct {
    const i64 *wp_ptr, *wp_idx, *mp_ptr, *mp_idx, *gp_ptr, *gp_idx, *lb_first;
    i64 n_lb;
} patterns_t;

/* (iterations, status, residual) of a prox solve */
typedef struct {
    i64 iterations;
    i64 status;
    double residual;
} prox_result_t;

/* A kinematic tree / forest (kinematics.KinematicTree): nj joints (joint 0 the world),
 * nv velocities. */
enum { JT_FREEFLYER = 0, JT_REVOLUTE = 1 };
typedef struct {
    i64 nj, nv;
    const i64 *parent, *jtype, *idx_q, *idx_v; /* nj each */
    const double *axis;                        /* nj x 3, in the joint frame */
    const double *pl_R;                        /* nj x 3 x 3 joint placements */
    const double *pl_p;                        /* nj x 3 */
    const u8 *support;                         /* nj x nj: support[j, k], joint k supports j */
} tree_t;

/* The world placements of the joint frames (forward_kinematics' output). */
typedef struct {
    double *oR; /* nj x 3 x 3 */
    double *op; /* nj x 3 */
} frames_t;

/* rigid_body.BodyInertias */
typedef struct {
    const double *mass;    /* nj */
    const double *lever;   /* nj x 3 */
    const double *inertia; /* nj x 3 x 3 */
    const double *gravity; /* 3 */
} inertias_t;

/* The contact points: sphere i of radius radius[i] at local[i] in the frame of joint[i] */
typedef struct {
    i64 nc;
    const i64 *joint;     /* nc */
    const double *local;  /* nc x 3 */
    const double *radius; /* nc */
} contact_points_t;

/* The ground plane {x | n·x = offset} and its tangents, and the terrain on it (terrain.c):
 * n_terrain floats packed by physics/terrain.py (0: the plane alone). frames (nc x 11, or
 * NULL): where contact_points writes each contact's surface frame (n, t1, t2) and μ. */
typedef struct {
    const double *n, *t1, *t2; /* 3 each */
    double offset;
    i64 n_terrain;
    const double *terrain;
    double *frames;
} ground_t;

/* the per-contact entries of ground_t.frames: n (3), t1 (3), t2 (3), μ, and the surface
 * (terrain.c: 0 none or not known, 1 the plane, 2 the heightfield, 3 + k box k) */
#define FRAME_STRIDE 11

/* The cut joints of a forest (ForestCoordinates / tree_step.CutModel) */
typedef struct {
    i64 ncut;
    const i64 *P, *C;                                         /* ncut each: the bodies */
    const double *p_P, *p_C, *a_P, *b1_P, *b2_P, *a_C, *b1_C; /* ncut x 3 each */
} cuts_t;

/* contact.CompliantLaw */
typedef struct {
    double mu, c_N, d_N, c_T, d_T, slip_velocity;
} compliant_law_t;

/* step_kernels.ContactProblem: the rows of the active contacts (3 each, normal first) then
 * the bilateral rows; m = 3 na + nb rows, nv velocities. */
typedef struct {
    int ok;      /* M (and G_B) positive definite */
    i64 na;      /* |I| */
    i64 *active; /* I, in row order (na) */
    i64 m, nv;
    double *Wt;    /* m x nv */
    double *MinvW; /* nv x m */
    double *b;     /* m */
    double *G;     /* m x m in the Delassus form, else unused */
    double *Gdiag; /* m */
    double *LB;    /* nb x nb with the direct bilateral method, else unused */
    i64 nb_LB;     /* LB's dimension (0: none) */
    patterns_t pat;
    i64 opened;
    const double *mu; /* nc: each contact's μ (a copy, from the arena; NULL: settings_t.mu) */
    /* the rows after the contacts' as the prox projects them (m − 3 na; NULL: bilateral, Λ_B
     * free): Λ onto [−bound, bound]; the last nf are joint friction rows (tree_step.c) */
    const double *bound;
    i64 nf;
    /* G left unformed (Delassus form; contact_problem with a memory that expects a solve of
     * a few sweeps): the solve tries the velocity form first (phase_prox), form_delassus
     * forms G when it is needed; under JOR M^{-1}W too (minv_w_ready 0: the velocity form
     * then solves with the factor L of M, minv_w forms it when it is needed) */
    int lazy_G, minv_w_ready;
    const double *L;       /* the factor of M (L^T D L, tree_step's workspace) */
    const i64 *dof_parent; /* its tree */
} problem_t;

/* ---------------------------------------------------------------------------------------
 * linalg.c (linalg.py)
 * ------------------------------------------------------------------------------------- */
int cholesky_upper_input(const double *A, i64 nA, i64 o, double *L, i64 *first);
void cholesky_solve_vec(const double *L, i64 n, const i64 *first, double *b);
void envelope_columns(const i64 *first, i64 n, arena_t *a, i64 **ptr, i64 **idx);
void cholesky_solve_envelope(const double *L, i64 n, const i64 *first, const i64 *col_ptr,
                             const i64 *col_idx, double *b);
/* (L L^T) X = B for the q columns of X (n x q, row-major) at once, within the envelope */
void cholesky_solve_envelope_cols(const double *L, i64 n, const i64 *first, const i64 *col_ptr,
                                  const i64 *col_idx, double *X, i64 q);
int ltdl(const double *A, i64 n, const i64 *dof_parent, double *L);
void ltdl_solve_vec(const double *L, i64 n, const i64 *dof_parent, double *b);
/* B: n x m, solved in place column by column */
void ltdl_solve_cols(const double *L, const i64 *dof_parent, double *B, i64 n, i64 m, arena_t *a);
/* B: n x m with the row pattern of its columns (ptr: m + 1, idx); returns the pattern of the
 * solution's columns (out_ptr: m + 1, out_idx: out_ptr[m] entries) from the arena */
void ltdl_solve_cols_pattern(const double *L, const i64 *dof_parent, double *B, i64 n, i64 m,
                             const i64 *ptr, const i64 *idx, arena_t *a, i64 **out_ptr,
                             i64 **out_idx);

/* ---------------------------------------------------------------------------------------
 * kinematics.c (kinematics.py)
 * ------------------------------------------------------------------------------------- */
void forward_kinematics(const double *q, const tree_t *t, const frames_t *f);
/* out: 3 x nv; zero: clear it first (else only the supporting joints' columns are written) */
void point_jacobian(i64 j, const double *p, const tree_t *t, const frames_t *f, double *out,
                    int zero);
void contact_points(const tree_t *t, const frames_t *f, const contact_points_t *c,
                    const ground_t *g, double jacobian_gap, double *gap, double *position,
                    double *Wt);
void contact_kinematics(const double *q, const tree_t *t, const frames_t *f,
                        const contact_points_t *c, const ground_t *g, double jacobian_gap,
                        double *gap, double *position, double *Wt);

/* terrain.c (terrain.py): the surface nearest to the sphere of centre c and radius r among
 * the plane of g and its terrain: its gap, and its frame and μ into out (FRAME_STRIDE); with
 * `second` given, the sphere's second surface (a concave corner: terrain.c) too, its frame
 * into second and its gap into *second_gap (SECOND_SURFACE_NONE: none);
 * terrain_is_flat: the terrain holds the plane alone; terrain_has_second_surfaces: the
 * contacts come in two slots per sphere (contact_points) */
int terrain_is_flat(const ground_t *g);
int terrain_has_second_surfaces(const ground_t *g);
double terrain_plane_mu(const ground_t *g);
double terrain_contact(const ground_t *g, const double *c, double r, double *out, double *second,
                       double *second_gap);

/* ---------------------------------------------------------------------------------------
 * rigid_body.c (rigid_body.py)
 * ------------------------------------------------------------------------------------- */
void mass_matrix_and_forces(const double *u, const tree_t *t, const frames_t *f,
                            const inertias_t *b, double *M, double *h);

/* ---------------------------------------------------------------------------------------
 * forest.c (coordinates/forest.py)
 * ------------------------------------------------------------------------------------- */
void integrate_forest(const double *q, const double *u, double dt, const tree_t *t, double *out);
void quat_rot(const double *q, i64 iq, double *R);
void to_pin_velocity(const double *q, const double *u, i64 nv, i64 n_roots, const i64 *root_q,
                     const i64 *root_v, double *Rs, double *u_pin);
void from_pin_dynamics(const double *M_pin, const double *h_pin, i64 n, const double *Rs,
                       i64 n_roots, const i64 *root_v, const double *u_pin, double *M, double *h);
void tree_dynamics(const double *q, const double *u, const tree_t *t, const frames_t *f,
                   const inertias_t *b, double *M, double *h);
void midpoint_dynamics(const double *q, const double *u, double half_dt, const tree_t *t,
                       const frames_t *f, const inertias_t *b, const contact_points_t *c,
                       const ground_t *g, double jacobian_gap, double *qM, double *M, double *h,
                       double *gap, double *position, double *Wt);
void add_at(double *h, const i64 *idx, const double *values, i64 n);
void rigid_body_forces(const double *q, const double *u, i64 n_roots, const i64 *root_q,
                       const i64 *root_v, const double *mass, const double *inertia,
                       const double *gravity, double *h);
void angular_jacobian(i64 j, const tree_t *t, const double *oR, double *out, int zero);
void cut_joints(const double *q, const double *u, const tree_t *t, const frames_t *f,
                const cuts_t *c, double *Wt_B, double *g_B, double *angle, double *rate,
                double *axis_world, int do_fk, arena_t *a);
void cut_joint_motion(const double *q, const double *u, const tree_t *t, const frames_t *f,
                      const cuts_t *c, double *angle, double *rate, arena_t *a);
void gather_joint_values(const double *x, const i64 *index, const double *cut_values,
                         const i64 *cut_index, i64 n, double *out);
/* the cut joints' actuator torques tau_cut (ncut) into h, with the hinge axes axis_world
 * (ncut x 3) and the bodies' rotations oR (nj x 3 x 3) of the configuration they belong to */
void cut_joint_torques(const double *tau_cut, const cuts_t *c, const double *axis_world,
                       const tree_t *t, const double *oR, double *h, arena_t *a);

/* ---------------------------------------------------------------------------------------
 * contact.c (contact.py, actuator.py)
 * ------------------------------------------------------------------------------------- */
void compliant_contact_forces(const compliant_law_t *law, i64 nc, i64 nv, const double *gap,
                              const double *position, const double *Wt, const double *u, u8 *closed,
                              u8 *slip, double *anchor, const double *frames, double *lam);
void generalized_contact_force(const double *Wt, const double *lam, i64 nc, i64 nv, double *out);
int saturate_torque(const double *tau, const double *limit, const double *qd,
                    const double *qd_limit, double *out, i64 n);

/* ---------------------------------------------------------------------------------------
 * prox_delassus.c, prox.c and prox_alpha.c (prox.py)
 * ------------------------------------------------------------------------------------- */
/* prox_delassus.c: r (m) from diag(G) (m) for nc contacts */
void prox_parameters(const double *Gdiag, i64 m, i64 nc, double alpha, double *r);
/* r_B = ω_B scale/G_BB of the rows after the contacts' with a bilateral relaxation ω_B
 * (settings_t.bilateral_relaxation > 0; scale: the α's scale of a fallback try) */
void relax_bilateral_rows(const settings_t *s, const double *Gdiag, i64 m, i64 nc, double scale,
                          double *r);
/* the pattern of the rows of A (m x n) / of its columns, from the arena */
void row_pattern(const double *A, i64 m, i64 n, arena_t *a, i64 **ptr, i64 **idx);
void col_pattern(const double *A, i64 m, i64 n, arena_t *a, i64 **ptr, i64 **idx);
/* G (m x m) = W^T M^{-1} W; Wt: m x nv, MinvW: nv x m */
void delassus(const double *Wt, const double *MinvW, double *G, i64 m, i64 nv, const i64 *wp_ptr,
              const i64 *wp_idx, const i64 *mp_ptr, const i64 *mp_idx, arena_t *a);
void delassus_diagonal(const double *Wt, const double *MinvW, double *d, i64 m, i64 nv,
                       const i64 *wp_ptr, const i64 *wp_idx);
/* JOR in the velocity form with M^{-1} applied by the factor L of M (dof_parent its tree)
 * instead of M^{-1}W (not formed): at most s->max_iterations sweeps from Λ^0 in lam, u^E into
 * u (prox_factored.c; the impulse criterion) */
prox_result_t jor_velocity_factored(const settings_t *s, const patterns_t *pat, const double *Wt,
                                    const double *u_free, const double *bvec, i64 m, i64 nv, i64 nc,
                                    const double *mu, const double *r, const double *bound,
                                    double *lam, const double *L, const i64 *dof_parent, double *u,
                                    arena_t *a);
/* diag(G) = diag(W^T M^{-1} W) with the factor L of M (no M^{-1}W): w^T (L^T D L)^{-1} w =
 * yᵀD^{-1}y with L^T y = w, every row's y at once in Y (nv x m, work) (prox_factored.c) */
void factored_delassus_diagonal(const double *Wt, i64 m, i64 nv, const i64 *wp_ptr,
                                const i64 *wp_idx, const double *L, const i64 *dof_parent,
                                double *d, double *Y);

/* prox_alpha.c: auto_spectral_scale (adaptive α): G is m x m (Delassus form), else unused */
double auto_spectral_scale(const settings_t *s, const double *G, const double *Wt,
                           const double *MinvW, const patterns_t *pat, i64 m, i64 nv, i64 nc,
                           const double *r, arena_t *a);
/* prox.c: one prox solve (prox.prox_solve): Wt m x nv, MinvW nv x m, u_free nv, bvec m,
 * G m x m and c m (Delassus form), mu nc, r m, bound m − 3 nc (the rows after the contacts'
 * projected onto [−bound, bound]: joint friction; NULL: bilateral rows), lam m (warm start in,
 * Λ out), LB nb_LB x nb_LB, M nv x nv (energy criterion), u nv (u^E out). */
prox_result_t prox_solve(const settings_t *s, const patterns_t *pat, const double *Wt,
                         const double *MinvW, const double *u_free, const double *bvec,
                         const double *G, const double *c, i64 m, i64 nv, i64 nc, const double *mu,
                         const double *r, const double *bound, double *lam, const double *LB,
                         i64 nb_LB, const double *M, double *u, arena_t *a);

#endif
