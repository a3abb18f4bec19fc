"""Contact-point kinematics of a Pinocchio kinematic tree (C kernels, ``csrc/kinematics.c``).

Why not pin's frame API on the hot path: reading ``data.oMf[i].translation`` from Python
costs per frame, and over the 16 contact points of StarlETH more than CRBA and RNEA
together (doc/performance.md). The tree below is extracted once from the
``pinocchio.Model`` (parents, joint placements, joint types and axes) and evaluated in one
kernel call; ``test/test_kinematics_dynamics.py`` checks positions and Jacobians against
``pin.framesForwardKinematics`` / ``pin.getFrameJacobian`` to 1e-12.

Conventions (the paper's minimal set, Eqn. 21, with Pinocchio's quaternion storage order):
    q = [I_r_OB (3), quaternion (x, y, z, w), joint angles]
    u = [I_v_B (3, trunk linear velocity in the *inertial* frame), B_ω_IB (3), joint rates]
The Jacobians returned here map u to velocities in the world frame.

The kernels (the arrays of `KinematicTree`):

- ``forward_kinematics(q, parent, jtype, axis, pl_R, pl_p, idx_q, oR, op)``: world
  placements (oR[j], op[j]) of all joint frames, oM_j = oM_parent · placement_j · M_j(q).
- ``point_jacobian(j, p, jtype, axis, idx_v, support, oR, op, out, zero=True)``: the 3 x nv
  Jacobian of the world velocity of the material point at world position p attached to
  joint frame j (forward_kinematics first); only the supporting joints' columns are
  written, the others zeroed first unless `zero` is False.
- ``contact_kinematics(q, (tree, frames, contacts), ground, jacobian_gap, (gap, position,
  Wt), surface_frames=None)``: forward_kinematics, then the contact points (tree, frames:
  `KinematicTree.args`; contacts: (c_joint, c_local, c_radius); ground:
  contact.GroundPlane.kernel_args): contact point i is a sphere of radius c_radius[i]
  centred at c_local[i] in the frame of joint c_joint[i] (radius 0: a point). Against the
  plane {x | n·x = ground_offset}: g_N,i = n·c_i − ground_offset − r_i, P_i = c_i − r_i n
  (the closest point) and Wt[i] = [n, t1, t2]^T J_P,i (3 x nv), W_{U,i}^T of Eqn. (1), so
  that γ_i = Wt[i] u; Wt[i] is computed only for contacts with g_N,i ≤ jacobian_gap (the
  others' rows are left as they were).
- ``quat_xyzw_to_rot(x, y, z, w, R)``: the rotation matrix of a unit quaternion (Pinocchio
  order) into R.
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from starleth_interface.robot.urdf import revolute_axis

from .kernels import (  # noqa: F401
    JT_FREEFLYER,
    JT_REVOLUTE,
    contact_kinematics,
    forward_kinematics,
    point_jacobian,
    quat_xyzw_to_rot,
)


class KinematicTree:
    """Flat arrays describing a pin model's joints, for the kernels (joint types JT_FREEFLYER
    and JT_REVOLUTE, whose axis is given in the joint frame)."""

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
            elif revolute_axis(jm) is not None:
                self.jtype[j] = JT_REVOLUTE
                self.axis[j] = revolute_axis(jm)
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
        """The tree and its kinematics' scratch as the kernels take them: ((parent, jtype,
        axis, pl_R, pl_p, idx_q, idx_v, support), (oR, op)), like the C tree_t and
        frames_t."""
        return ((self.parent, self.jtype, self.axis, self.pl_R, self.pl_p, self.idx_q,
                 self.idx_v, self.support), (self.oR, self.op))
