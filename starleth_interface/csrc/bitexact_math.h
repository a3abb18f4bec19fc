/* Scalar formulas the physics kernels (starleth_sim/physics/csrc) and the controller's
 * kernels (starleth_controller/csrc) both compute, written once: each keeps the operation
 * order of the Python it implements, so that both sides round alike (built with
 * starleth_interface/c_extension.py's flags: no contraction, no reassociation). */
#ifndef STARLETH_BITEXACT_MATH_H
#define STARLETH_BITEXACT_MATH_H

#include <stdint.h>

/* max(a, b) / min(a, b) as Python and numba evaluate them: the second argument only when it
 * is strictly larger / smaller (which decides the sign of a zero and what a NaN gives). */
static inline double py_max(double a, double b) {
    return b > a ? b : a;
}
static inline double py_min(double a, double b) {
    return b < a ? b : a;
}
static inline int64_t py_maxi(int64_t a, int64_t b) {
    return b > a ? b : a;
}
static inline int64_t py_mini(int64_t a, int64_t b) {
    return b < a ? b : a;
}

/* quat_xyzw_to_rot: R (3 x 3, row-major) of the unit quaternion (x, y, z, w) (Pinocchio
 * order). */
static inline void quat_xyzw_to_rot(double x, double y, double z, double w, double *R) {
    R[0] = 1.0 - 2.0 * (y * y + z * z);
    R[1] = 2.0 * (x * y - z * w);
    R[2] = 2.0 * (x * z + y * w);
    R[3] = 2.0 * (x * y + z * w);
    R[4] = 1.0 - 2.0 * (x * x + z * z);
    R[5] = 2.0 * (y * z - x * w);
    R[6] = 2.0 * (x * z - y * w);
    R[7] = 2.0 * (y * z + x * w);
    R[8] = 1.0 - 2.0 * (x * x + y * y);
}

#endif
