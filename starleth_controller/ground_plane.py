"""The controller's own terrain estimate (no terrain oracle, no map): the ground plane
through the contact points where each foot last stood, and the swing foot's height profile
from its lift-off height to the plane's height at its foothold.

Each call, the support legs' contact points (from the joint angles and the trunk state: the
kinematics of controller.py) are kept as the legs' last footholds; a least-squares plane
z = a + g_x x + g_y y (world) through the four footholds gives the height expected under a
new foothold (slopes clipped to ±MAX_SLOPE; flat at the mean height when the footholds are
nearly collinear). On flat ground the plane is the ground; on a slope it is the slope; on
stairs it is the mean incline under the feet, and a foot that meets a higher tread than
expected touches down early (the leg states of kernels.leg_states), one that finds none
searches it further down (step_down.py). numba kernels like kernels.py (fastmath off)."""
from __future__ import annotations

import numba as nb

_jit = nb.njit(cache=True, fastmath=False, nogil=True)

#: the plane's slopes are clipped to this (27°) [m/m]
MAX_SLOPE = 0.5
#: below this determinant of the footholds' xy scatter [m⁴] the plane is flat
MIN_SCATTER = 1e-6


@_jit
def smoothstep(x):
    """Smoothstep on [0, 1] and its derivative."""
    if x <= 0.0:
        return 0.0, 0.0
    if x >= 1.0:
        return 1.0, 0.0
    return x * x * (3.0 - 2.0 * x), 6.0 * x * (1.0 - x)


@_jit
def update_plane(contact, support, ns, footholds, plane):
    """Keeps the contact points of the first ns legs `support` as their footholds (4 x 3,
    world) and fits plane = (a, g_x, g_y), z = a + g_x x + g_y y, to the four footholds by
    least squares (slopes clipped to ±MAX_SLOPE; g = 0 at the mean height when the
    footholds' xy scatter has a determinant below MIN_SCATTER)."""
    for j in range(ns):
        k = support[j]
        for i in range(3):
            footholds[k, i] = contact[k, i]
    mx = 0.0
    my = 0.0
    mz = 0.0
    for k in range(4):
        mx += footholds[k, 0]
        my += footholds[k, 1]
        mz += footholds[k, 2]
    mx, my, mz = mx / 4.0, my / 4.0, mz / 4.0
    sxx = sxy = syy = sxz = syz = 0.0
    for k in range(4):
        dx, dy, dz = footholds[k, 0] - mx, footholds[k, 1] - my, footholds[k, 2] - mz
        sxx += dx * dx
        sxy += dx * dy
        syy += dy * dy
        sxz += dx * dz
        syz += dy * dz
    det = sxx * syy - sxy * sxy
    gx = gy = 0.0
    if det > MIN_SCATTER:
        gx = (syy * sxz - sxy * syz) / det
        gy = (sxx * syz - sxy * sxz) / det
        gx = min(max(gx, -MAX_SLOPE), MAX_SLOPE)
        gy = min(max(gy, -MAX_SLOPE), MAX_SLOPE)
    plane[0] = mz - gx * mx - gy * my
    plane[1] = gx
    plane[2] = gy


@_jit
def plane_height(plane, x, y):
    """The plane's height at (x, y)."""
    return plane[0] + plane[1] * x + plane[2] * y


@_jit
def swing_height(sp, z0, z1, h_swing, depth, Tsw):
    """The swing foot's contact-point height and its rate at swing phase sp: from the
    lift-off height z0 up to max(z0, z1) + h_swing at mid-swing, then down to `depth` below
    the expected foothold height z1 (smoothsteps; Tsw the swing time)."""
    top = max(z0, z1) + h_swing
    if sp < 0.5:
        a, da = smoothstep(2.0 * sp)
        return z0 + (top - z0) * a, (top - z0) * da * 2.0 / Tsw
    a, da = smoothstep(2.0 * sp - 1.0)
    span = z1 - depth - top
    return top + span * a, span * da * 2.0 / Tsw
