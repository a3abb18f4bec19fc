/* The controller's own terrain estimate (no terrain oracle, no map): the ground plane
 * through the contact points where each foot last stood, and the swing foot's height
 * profile from its lift-off height to the plane's height at its foothold.
 *
 * Each call, the support legs' contact points (from the joint angles and the trunk state:
 * leg_kinematics) are kept as the legs' last footholds; a least-squares plane
 * z = a + g_x x + g_y y (world) through the four footholds gives the height expected under
 * a new foothold (slopes clipped to ±MAX_SLOPE; flat at the mean height when the footholds
 * are nearly collinear). On flat ground the plane is the ground; on a slope it is the
 * slope; on stairs it is the mean incline under the feet, and a foot that meets a higher
 * tread than expected touches down early (leg_states), one that finds none searches it
 * further down (step_down.py). */
#include "kernels.h"

/* Smoothstep on [0, 1] (*s) and its derivative (*ds). */
void smoothstep(double x, double *s, double *ds) {
    if (x <= 0.0) {
        *s = 0.0, *ds = 0.0;
    } else if (x >= 1.0) {
        *s = 1.0, *ds = 0.0;
    } else {
        *s = x * x * (3.0 - 2.0 * x), *ds = 6.0 * x * (1.0 - x);
    }
}

/* Keeps the contact points of the first ns legs `support` as their footholds (4 x 3,
 * world) and fits plane = (a, g_x, g_y), z = a + g_x x + g_y y, to the four footholds by
 * least squares (slopes clipped to ±MAX_SLOPE; g = 0 at the mean height when the
 * footholds' xy scatter has a determinant below MIN_SCATTER). */
void update_plane(const double *contact, const i64 *support, i64 ns, double *footholds,
                  double *plane) {
    for (i64 j = 0; j < ns; j++) {
        i64 k = support[j];
        for (int i = 0; i < 3; i++) footholds[3 * k + i] = contact[3 * k + i];
    }
    double mx = 0.0, my = 0.0, mz = 0.0;
    for (int k = 0; k < 4; k++) {
        mx += footholds[3 * k];
        my += footholds[3 * k + 1];
        mz += footholds[3 * k + 2];
    }
    mx /= 4.0, my /= 4.0, mz /= 4.0;
    double sxx = 0.0, sxy = 0.0, syy = 0.0, sxz = 0.0, syz = 0.0;
    for (int k = 0; k < 4; k++) {
        double dx = footholds[3 * k] - mx, dy = footholds[3 * k + 1] - my,
               dz = footholds[3 * k + 2] - mz;
        sxx += dx * dx;
        sxy += dx * dy;
        syy += dy * dy;
        sxz += dx * dz;
        syz += dy * dz;
    }
    double det = sxx * syy - sxy * sxy;
    double gx = 0.0, gy = 0.0;
    if (det > MIN_SCATTER) {
        gx = (syy * sxz - sxy * syz) / det;
        gy = (sxx * syz - sxy * sxz) / det;
        gx = py_min(py_max(gx, -MAX_SLOPE), MAX_SLOPE);
        gy = py_min(py_max(gy, -MAX_SLOPE), MAX_SLOPE);
    }
    plane[0] = mz - gx * mx - gy * my;
    plane[1] = gx;
    plane[2] = gy;
}

/* The plane's height at (x, y). */
double plane_height(const double *plane, double x, double y) {
    return plane[0] + plane[1] * x + plane[2] * y;
}

/* The swing foot's contact-point height (*z) and its rate (*dz) at swing phase sp: from the
 * lift-off height z0 up to max(z0, z1) + h_swing at mid-swing, then down to `depth` below
 * the expected foothold height z1 (smoothsteps; Tsw the swing time). */
void swing_height(double sp, double z0, double z1, double h_swing, double depth, double Tsw,
                  double *z, double *dz) {
    double top = py_max(z0, z1) + h_swing, a, da;
    if (sp < 0.5) {
        smoothstep(2.0 * sp, &a, &da);
        *z = z0 + (top - z0) * a, *dz = (top - z0) * da * 2.0 / Tsw;
        return;
    }
    smoothstep(2.0 * sp - 1.0, &a, &da);
    double span = z1 - depth - top;
    *z = top + span * a, *dz = span * da * 2.0 / Tsw;
}
