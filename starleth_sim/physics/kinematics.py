"""Contact-point kinematics of a Pinocchio kinematic tree, compiled with numba.

Why not pin's frame API on the hot path: reading ``data.oMf[i].translation`` from Python
costs about 1.2 µs per frame (measured), i.e. ~20 µs per step for the 16 contact points
of StarlETH, more than CRBA and RNEA together. The tree below is extracted once from the
``pinocchio.Model`` (parents, joint placements, joint types and axes) and evaluated in one
jitted call; ``test/test_kinematics.py`` checks positions and Jacobians against
``pin.framesForwardKinematics`` / ``pin.getFrameJacobian`` to 1e-12.

Conventions (the paper's minimal set, Eqn. 21, with Pinocchio's quaternion storage order):
    q = [I_r_OB (3), quaternion (x, y, z, w), joint angles]
    u = [I_v_B (3, trunk linear velocity in the *inertial* frame), B_ω_IB (3), joint rates]
The Jacobians returned here map u to velocities in the world frame.
"""
from __future__ import annotations

import numpy as np
import numba as nb
import pinocchio as pin

from .kernel_cache import KERNEL
from .array_views import arena_floats, view2

JT_FREEFLYER = 0
JT_REVOLUTE = 1  # axis given in the joint frame

_REVOLUTE_AXES = {
    "JointModelRX": (1.0, 0.0, 0.0),
    "JointModelRY": (0.0, 1.0, 0.0),
    "JointModelRZ": (0.0, 0.0, 1.0),
}


class KinematicTree:
    """Flat arrays describing a pin model's joints, for the jitted kernels."""

    def __init__(self, model: pin.Model):
        nj = model.njoints
        self.njoints = nj
        self.nv = model.nv
        self.parent = np.zeros(nj, dtype=np.int64)
        self.jtype = np.full(nj, -1, dtype=np.int64)
        self.axis = np.zeros((nj, 3))
        self.pl_R = np.zeros((nj, 3, 3))
        self.pl_p = np.zeros((nj, 3))
        self.idx_q = np.zeros(nj, dtype=np.int64)
        self.idx_v = np.zeros(nj, dtype=np.int64)
        self.support = np.zeros((nj, nj), dtype=np.bool_)
        self.pl_R[0] = np.eye(3)
        for j in range(1, nj):
            jm = model.joints[j]
            name = jm.shortname()
            if name == "JointModelFreeFlyer":
                if model.parents[j] != 0:
                    raise ValueError("a free-flyer joint is only supported at the root")
                self.jtype[j] = JT_FREEFLYER
            elif name in _REVOLUTE_AXES:
                self.jtype[j] = JT_REVOLUTE
                self.axis[j] = _REVOLUTE_AXES[name]
            elif name == "JointModelRevoluteUnaligned":
                self.jtype[j] = JT_REVOLUTE
                self.axis[j] = np.asarray(jm.extract().axis, dtype=float)
            else:
                raise ValueError(f"joint '{model.names[j]}' has unsupported type {name}; "
                                 "supported: free-flyer root and revolute joints")
            self.parent[j] = model.parents[j]
            self.pl_R[j] = model.jointPlacements[j].rotation
            self.pl_p[j] = model.jointPlacements[j].translation
            self.idx_q[j] = jm.idx_q
            self.idx_v[j] = jm.idx_v
            for k in model.supports[j]:
                self.support[j, k] = True
        self.support[:, 0] = False
        #: the dof each velocity index hangs from (−1 at a root): the previous dof of its
        #: joint, or the last dof of the parent joint; parents come first (idx_v order)
        self.dof_parent = np.full(model.nv, -1, dtype=np.int64)
        for j in range(1, nj):
            p = int(self.parent[j])
            first = int(self.idx_v[j])
            if p > 0:
                self.dof_parent[first] = model.joints[p].idx_v + model.joints[p].nv - 1
            for k in range(1, model.joints[j].nv):
                self.dof_parent[first + k] = first + k - 1
        self.oR = np.zeros((nj, 3, 3))
        self.op = np.zeros((nj, 3))

    def args(self):
        return (self.parent, self.jtype, self.axis, self.pl_R, self.pl_p, self.idx_q,
                self.idx_v, self.support, self.oR, self.op)


@nb.njit(**KERNEL, inline="always")
def quat_xyzw_to_rot(x, y, z, w, R):
    """Rotation matrix of the unit quaternion (x, y, z, w) (Pinocchio order), written into R."""
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - z * w)
    R[0, 2] = 2 * (x * z + y * w)
    R[1, 0] = 2 * (x * y + z * w)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - x * w)
    R[2, 0] = 2 * (x * z - y * w)
    R[2, 1] = 2 * (y * z + x * w)
    R[2, 2] = 1 - 2 * (x * x + y * y)


@nb.njit(**KERNEL, inline="always")
def axis_angle_to_rot(a, theta, R):
    c = np.cos(theta)
    s = np.sin(theta)
    t = 1.0 - c
    x, y, z = a[0], a[1], a[2]
    R[0, 0] = t * x * x + c
    R[0, 1] = t * x * y - s * z
    R[0, 2] = t * x * z + s * y
    R[1, 0] = t * x * y + s * z
    R[1, 1] = t * y * y + c
    R[1, 2] = t * y * z - s * x
    R[2, 0] = t * x * z - s * y
    R[2, 1] = t * y * z + s * x
    R[2, 2] = t * z * z + c


@nb.njit(**KERNEL, inline="always")
def _matmul3(A, B, out):
    """out = A B for 3x3 matrices (explicit loops: BLAS calls cost more than the flops)."""
    for r in range(3):
        for c in range(3):
            out[r, c] = A[r, 0] * B[0, c] + A[r, 1] * B[1, c] + A[r, 2] * B[2, c]


@nb.njit(**KERNEL, inline="always")
def forward_kinematics(q, parent, jtype, axis, pl_R, pl_p, idx_q, oR, op, arena=None):
    """World placements (oR[j], op[j]) of all joint frames: oM_j = oM_parent · placement_j · M_j(q)
    (its scratch from a step's arena, array_views.arena_floats, or new)."""
    nj = parent.shape[0]
    for r in range(3):
        for c in range(3):
            oR[0, r, c] = 1.0 if r == c else 0.0
        op[0, r] = 0.0
    scratch = arena_floats(arena, 21)      # (one buffer for the three temporaries)
    scratch[:] = 0.0
    Rq = view2(scratch[0:9], (3, 3))
    tmp = view2(scratch[9:18], (3, 3))
    pq = scratch[18:21]
    for j in range(1, nj):
        iq = idx_q[j]
        if jtype[j] == JT_FREEFLYER:
            quat_xyzw_to_rot(q[iq + 3], q[iq + 4], q[iq + 5], q[iq + 6], Rq)
            pq[0] = q[iq]
            pq[1] = q[iq + 1]
            pq[2] = q[iq + 2]
        else:
            axis_angle_to_rot(axis[j], q[iq], Rq)
            pq[0] = 0.0
            pq[1] = 0.0
            pq[2] = 0.0
        par = parent[j]
        # p_local = placement.p + placement.R pq ; op = op_par + oR_par p_local
        for r in range(3):
            pl = pl_p[j, r] + pl_R[j, r, 0] * pq[0] + pl_R[j, r, 1] * pq[1] + pl_R[j, r, 2] * pq[2]
            tmp[0, r] = pl
        for r in range(3):
            op[j, r] = (op[par, r] + oR[par, r, 0] * tmp[0, 0] + oR[par, r, 1] * tmp[0, 1]
                        + oR[par, r, 2] * tmp[0, 2])
        _matmul3(pl_R[j], Rq, tmp)
        _matmul3(oR[par], tmp, oR[j])


@nb.njit(**KERNEL)
def point_jacobian(j, p, jtype, axis, idx_v, support, oR, op, out, zero=True):
    """Jacobian (3 x nv) of the world velocity of the material point at world position p that
    is rigidly attached to joint frame j; forward_kinematics must have been run. Only the
    columns of the joints that support j are written; the others are zeroed first unless
    `zero` is False (the caller zeroed what it reads)."""
    nv = out.shape[1]
    if zero:
        for r in range(3):
            for c in range(nv):
                out[r, c] = 0.0
    nj = jtype.shape[0]
    for k in range(1, nj):
        if not support[j, k]:
            continue
        iv = idx_v[k]
        d0 = p[0] - op[k, 0]
        d1 = p[1] - op[k, 1]
        d2 = p[2] - op[k, 2]
        if jtype[k] == JT_FREEFLYER:
            R = oR[k]
            for c in range(3):
                # linear velocity of the root in the inertial frame
                out[c, iv + c] = 1.0
                # angular velocity in the root (body) frame: (R e_c) x d
                a0, a1, a2 = R[0, c], R[1, c], R[2, c]
                out[0, iv + 3 + c] = a1 * d2 - a2 * d1
                out[1, iv + 3 + c] = a2 * d0 - a0 * d2
                out[2, iv + 3 + c] = a0 * d1 - a1 * d0
        else:
            a0 = oR[k, 0, 0] * axis[k, 0] + oR[k, 0, 1] * axis[k, 1] + oR[k, 0, 2] * axis[k, 2]
            a1 = oR[k, 1, 0] * axis[k, 0] + oR[k, 1, 1] * axis[k, 1] + oR[k, 1, 2] * axis[k, 2]
            a2 = oR[k, 2, 0] * axis[k, 0] + oR[k, 2, 1] * axis[k, 1] + oR[k, 2, 2] * axis[k, 2]
            out[0, iv] = a1 * d2 - a2 * d1
            out[1, iv] = a2 * d0 - a0 * d2
            out[2, iv] = a0 * d1 - a1 * d0


@nb.njit(**KERNEL)
def contact_kinematics(q, parent, jtype, axis, pl_R, pl_p, idx_q, idx_v, support, oR, op,
                       c_joint, c_local, c_radius, normal, tangent1, tangent2, ground_offset,
                       jacobian_gap, gap, position, Wt):
    """Gaps g_N, contact-point positions and contact-frame Jacobians of all contact points
    at q: forward_kinematics, then contact_points."""
    forward_kinematics(q, parent, jtype, axis, pl_R, pl_p, idx_q, oR, op)
    contact_points(parent, jtype, axis, idx_v, support, oR, op, c_joint, c_local, c_radius,
                   normal, tangent1, tangent2, ground_offset, jacobian_gap, gap, position, Wt)


@nb.njit(**KERNEL, inline="always")
def contact_points(parent, jtype, axis, idx_v, support, oR, op, c_joint, c_local, c_radius,
                   normal, tangent1, tangent2, ground_offset, jacobian_gap, gap, position, Wt):
    """Gaps g_N, contact-point positions and contact-frame Jacobians of all contact points
    from the joint placements (oR, op) of forward_kinematics.

    Contact point i is a sphere of radius c_radius[i] centred at c_local[i] in the frame of
    joint c_joint[i] (radius 0: a point). Against the plane {x | n·x = ground_offset}:
        g_N,i = n·c_i − ground_offset − r_i,    P_i = c_i − r_i n  (the closest point),
        Wt[i] = [n, t1, t2]^T J_P,i  (3 x nv), so that γ_i = Wt[i] u = [γ_N, γ_T1, γ_T2].
    Wt[i] is W_{U,i}^T of Eqn. (1). It is only computed for contacts with
    g_N,i ≤ jacobian_gap (the others' rows are left as they were).
    """
    nc = c_joint.shape[0]
    nv = Wt.shape[2]
    scratch = np.empty(3 * nv + 3)      # (one allocation for J and c)
    J = view2(scratch[:3 * nv], (3, nv))
    c = scratch[3 * nv:]
    for i in range(nc):
        j = c_joint[i]
        for k in range(3):
            c[k] = (oR[j, k, 0] * c_local[i, 0] + oR[j, k, 1] * c_local[i, 1]
                    + oR[j, k, 2] * c_local[i, 2] + op[j, k])
        r = c_radius[i]
        gap[i] = normal[0] * c[0] + normal[1] * c[1] + normal[2] * c[2] - ground_offset - r
        for k in range(3):
            position[i, k] = c[k] - r * normal[k]
        if gap[i] > jacobian_gap:
            continue
        point_jacobian(j, position[i], jtype, axis, idx_v, support, oR, op, J)
        for col in range(nv):
            Wt[i, 0, col] = normal[0] * J[0, col] + normal[1] * J[1, col] + normal[2] * J[2, col]
            Wt[i, 1, col] = tangent1[0] * J[0, col] + tangent1[1] * J[1, col] + tangent1[2] * J[2, col]
            Wt[i, 2, col] = tangent2[0] * J[0, col] + tangent2[1] * J[1, col] + tangent2[2] * J[2, col]
