/* The controller's per-call arithmetic in C (kernels.c, ground_plane.c; the Python bindings
 * in module.c): the extension module starleth_controller._kernels, built like the physics
 * kernels (starleth_interface/c_extension.py: no contraction into fused multiply-adds, no
 * reassociation). Each formula keeps the operation order of the Python it replaced, and
 * min / max follow Python's rule (py_max: the second argument only when strictly larger):
 * the torques are bit for bit those of the numba kernels before them.
 *
 * Arrays are C-contiguous float64 (int64 for indices and states, bytes for bool flags);
 * a (r, c) array A is A[i * c + j]. Leg geometry (one row per leg, model.py): hip (4, 3)
 * HAA position in the base frame, geo (4, 12) with the columns below. */
#ifndef STARLETH_CONTROLLER_KERNELS_H
#define STARLETH_CONTROLLER_KERNELS_H

#include <math.h>
#include <stdint.h>

/* py_max / py_min (Python's rule), quat_xyzw_to_rot: shared with the physics kernels */
#include "bitexact_math.h"

typedef int64_t i64;
typedef uint8_t u8;

/* the columns of geo (model.GEOMETRY) */
enum { L0, L1, L2, RAD, KNEE, OX, DY, ALPHA, GAMMA, ROLL, S1, S2, NGEO };

/* the swing parameters P (controller._swing_parameters): SW_OFFSET_X, SW_STANCE_X and
 * SW_STANCE_Y start 4 values each (the legs') */
enum {
    SW_T,
    SW_DUTY,
    SW_FEEDBACK,
    SW_MAX,
    SW_INTERP_END,
    SW_HEIGHT,
    SW_DEPTH,
    SW_GRAVITY,
    SW_OFFSET_X,
    SW_STANCE_X = SW_OFFSET_X + 4,
    SW_STANCE_Y = SW_STANCE_X + 4,
    SW_SIZE = SW_STANCE_Y + 4
};

/* leg states (controller.py: SUPPORT, SWING, LOST_CONTACT) */
enum { LEG_SUPPORT, LEG_SWING, LEG_LOST_CONTACT };

/* inputs at least this large (in magnitude) are left to the callers' numpy checks */
#define LARGE 1e100
/* the ground plane's slopes are clipped to this (27°) [m/m]; below MIN_SCATTER [m⁴] of
 * the footholds' xy scatter the plane is flat */
#define MAX_SLOPE   0.5
#define MIN_SCATTER 1e-6

/* kernels.c */
void quat_to_rot(double qx, double qy, double qz, double qw, double *R);
double squared_norm4(const double *a);
int read_state(const double *qj, i64 nq, const double *dqj, i64 ndq, const double *pb, i64 npb,
               const double *quat, i64 nquat, const double *vb, i64 nvb, const double *wb, i64 nwb,
               double *quat_n, double *R);
int node_state(const double *position, const double *velocity, const i64 *perm, i64 nperm,
               const double *odom, const double *forces, double threshold, double *q, double *dq,
               double *pb, double *quat, double *v, double *w, double *R, u8 *contact);
void leg_kinematics(const double *qj, const double *R, const double *pb, const double *hip,
                    const double *geo, double *centre, double *contact, double *Jf, double *Jc);
void leg_ik(i64 k, double r0, double r1, double r2, const double *hip, const double *geo,
            double *out);
void leg_fk(i64 k, double q0, double q1, double q2, const double *hip, const double *geo,
            double *out);
void qp_matrices(const double *rh, i64 n, const double *b, const double *S, double eps, double *A,
                 double *H, double *g);
void torque_rows(const double *J, i64 n, const double *gleg, const double *tmax, i64 row0,
                 double *C, i64 ncol, double *lo, double *up);
void vmc_force(const i64 *ref, i64 nr, const double *contact, const double *pb, const double *vb,
               double cy, double sy, double z_error, double max_err, const double *v_cmd,
               const double *kp, const double *kd, const double *kff, int integrate, double ki,
               double lim, double dt, double *f_int, double mass_g, double *e, double *vh,
               double *vd, double *b);
void vmc_moment(const double *er, const double *ww, double cy, double sy, double max_err,
                double w_cmd, const double *kp, const double *kd, const double *kff, double *eh,
                double *wh, double *wd, double *b);
void heading_qp_inputs(const i64 *support, i64 ns, const double *contact, const double *com,
                       const double *Jc, const double *gleg, double cy, double sy, double *rh,
                       double *Jh, double *gh);
void support_torques(const i64 *support, i64 ns, const double *fh, double cy, double sy,
                     const double *Jc, const double *gleg, double *fdes, double *tau);
i64 leg_states(int trotting, double t, double t0, double T, const double *phase_offsets,
               double duty_factor, double early_touchdown, const u8 *grounded, double *swing_phase,
               i64 *swing_cycle, i64 *states, double *lost_since, i64 *support, i64 *lift);
double ground_estimate(double ground, const double *contact, const i64 *support, i64 ns);

/* the inputs of position_controlled_torques (what the legs not in support follow) */
typedef struct {
    const i64 *states;         /* (4,) leg states */
    const double *swing_phase; /* (4,) */
    const double *r_liftoff;   /* (4, 2) hip→foot at lift-off, heading frame */
    double *foothold;          /* (4, 2) written: the swing targets' footholds (world xy) */
    const double *P;           /* (SW_SIZE,) the swing parameters */
    const double *foot_radius; /* (4,) */
    double ground;             /* the trunk's ground height */
    const double *v_cmd;       /* (2,) */
    double w_cmd;
    const double *pb, *R, *vb, *ww; /* (3,), (3, 3), (3,), (3,) */
    double cy, sy;
    const double *Jf;              /* (4, 3, 3) */
    const double *qj, *dqj, *gleg; /* (12,) */
    const double *kp, *kd;         /* (3,) */
    const double *hip, *geo;       /* (4, 3), (4, NGEO) */
    double *target, *vt;           /* (3,) work */
    double *tau;                   /* (12,) written for the legs not in support */
    const double *liftoff_z;       /* (4,) */
    const double *plane;           /* (3,) */
    double *foothold_z;            /* (4,) written */
    const double *searching;       /* (4, 4) the searching feet's x, y, z, ż */
} swing_inputs_t;

void position_controlled_torques(const swing_inputs_t *s);

/* ground_plane.c */
void smoothstep(double x, double *s, double *ds);
void update_plane(const double *contact, const i64 *support, i64 ns, double *footholds,
                  double *plane);
double plane_height(const double *plane, double x, double y);
void swing_height(double sp, double z0, double z1, double h_swing, double depth, double Tsw,
                  double *z, double *dz);

#endif
