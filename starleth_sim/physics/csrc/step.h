/* The phases of Moreau's midpoint step (step.c, step_kernels.py) and the one-kernel steps
 * (one_step.c, tree_step.py). */
#ifndef STARLETH_STEP_H
#define STARLETH_STEP_H

#include "core.h"

/* A StepSettings from its 19 fields as floats (the ints and flags small whole numbers) */
void settings_from_fields(const double *f, settings_t *s);

/* u_free = u^S + M^{-1} h Δt with the LTDL factor L of M */
void free_velocity(const double *h, double dt, const double *uS, i64 nv, const i64 *dof_parent,
                   const double *L, double *u_free);

/* Alg. 1 without bilateral constraints (step_kernels.solve_compliant); 0 if M is not
 * positive definite. */
int solve_compliant(const compliant_law_t *law, const double *M, double *h, const double *uS,
                    i64 nv, double dt, i64 nc, const double *gap, const double *position,
                    const double *Wt_all, u8 *closed, u8 *slip, double *anchor,
                    const double *t1, const double *t2, double *lam, const i64 *dof_parent,
                    int factor, double *L, double *u_free, double *timings);

/* c = W^T u_free + b (Eqn. 15) */
void constraint_velocity(const double *Wt, i64 m, i64 nv, const double *u_free,
                         const double *bvec, const i64 *wp_ptr, const i64 *wp_idx, double *c);

/* The torque-independent part of the hard-contact solve (contact_problem): the problem's
 * arrays from the arena. gap, Wt_all: nc contacts; WtB (nb x nv), bB (nb): the bilateral
 * rows; eps: nc x 2; last_impulse nc x 3, last_active nc. */
void contact_problem(const settings_t *s, const double *M, const double *uS, i64 nv,
                     const double *gap, i64 nc, const double *Wt_all, const double *WtB, i64 nb,
                     const double *bB, const double *eps, const i64 *dof_parent, int factor,
                     double *L, const double *last_impulse, const u8 *last_active,
                     double *timings, arena_t *a, problem_t *p);

/* The fields of complete_problem's result */
typedef struct {
    i64 iterations, status;
    double residual;
    int retried;
    i64 projection_iterations, projection_status;
} complete_result_t;

/* The torque-dependent rest of the hard-contact solve (complete_problem); impulse: nc x 3,
 * is_active: nc, last_bilateral: nb (Λ_B: warm start in, solution out). */
complete_result_t complete_problem(const settings_t *s, const problem_t *p, const double *h,
                                   const double *uS, const double *M, const i64 *dof_parent,
                                   const double *L, const double *gap, i64 nc,
                                   const double *Wt_all, double *last_impulse,
                                   u8 *last_active, double *last_bilateral, i64 nb,
                                   double *impulse, u8 *is_active, double *u_free, double *u,
                                   double *u_corr, int remember, double *timings, arena_t *a);

/* The warm-start memory of a finished step */
void remember_contacts(const u8 *is_active, const double *impulse, i64 nc, u8 *last_active,
                       double *last_impulse);

/* Eqn. (8) into qE; 0 if q^E or u^E is not finite. nq: q's length. */
int end_of_step(const double *qM, const double *uE, const double *u_corr, int projected,
                double half_dt, const tree_t *t, i64 nq, double *qE, arena_t *a);

/* one_step.c: outcomes (tree_step.TREE_STEP_*) and the result tuple of the one-kernel steps */
enum {
    TREE_STEP_OK = 0,
    TREE_STEP_NOT_PD = 1,
    TREE_STEP_NONFINITE_IMPULSE = 2,
    TREE_STEP_NONFINITE_STATE = 3,
    TREE_STEP_NONFINITE_TORQUE = 4
};

typedef struct {
    i64 outcome, n_active, opened, iterations, status;
    double residual;
    int retried;
    i64 projection_iterations, projection_status;
} tree_step_result_t;

/* The packed buffers of a tree_step.TreeStepModel / CutModel (with their lengths) */
typedef struct {
    double *floats;
    i64 n_floats;
    const i64 *ints;
    i64 n_ints;
    const u8 *support;
    i64 n_support;
    double *workspace;
    i64 n_workspace;
} packed_model_t;

/* The per-step arrays of a one-kernel step; lengths from the model (nq: q's). */
typedef struct {
    const double *q, *u, *tau, *f_ext;
    i64 nq, nv, n_tau, n_f_ext;
    double *last_impulse;   /* nc x 3 */
    u8 *last_active;        /* nc */
    double *last_bilateral; /* nb */
    i64 nb;
    double *report;         /* 7 nc + na */
    u8 *is_active;          /* nc */
    double *qE, *uE;
} step_arrays_t;

/* Checks a packed TreeStepModel (and CutModel) against the sizes it claims; NULL if it is
 * consistent, else a message. */
const char *check_tree_model(const packed_model_t *m, i64 nv);
const char *check_cut_model(const packed_model_t *cut, i64 na, i64 nv);

tree_step_result_t tree_step_hard(int saturate, const step_arrays_t *x, const packed_model_t *m,
                                  arena_t *a);
tree_step_result_t tree_step_compliant(int saturate, const step_arrays_t *x, u8 *closed,
                                       u8 *slip, double *anchor, double *lam,
                                       const packed_model_t *m, arena_t *a);
tree_step_result_t forest_step_hard(const step_arrays_t *x, int factor, double *angle_E,
                                    double *rate_E, const packed_model_t *m,
                                    const packed_model_t *cut, arena_t *a);

#endif
