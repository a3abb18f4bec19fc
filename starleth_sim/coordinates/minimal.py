"""Minimal set of generalized coordinates (Eqn. 21-22): floating base + joint angles.

Convention (Pinocchio's free-flyer, kept internally everywhere):
    q = [I_r_IB (3), quaternion (x, y, z, w), φ (joints in pin order)]       nq = 7 + nj
    u = [B_v_B (3), B_ω_IB (3), φ̇]                                          nv = 6 + nj
The paper's minimal set uses the inertial linear velocity I_v_B and (p0, p1, p2, p3); both
sets describe the same physics (u differs by the rotation of the first three components,
which changes M and h consistently). Conversions happen only at the public boundary:
``base_state`` returns the world-frame linear velocity and the body angular velocity, and
names its quaternion order explicitly.

q̇ = F(q) u is integrated on the manifold with ``pin.integrate`` (the SE(3) exponential of
the base twist), and the quaternion is re-normalised after each half step, so its norm
stays 1 to machine precision.
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from ..description import RobotDescription
from ..kinematics import KinematicTree, contact_kinematics


class MinimalCoordinates:
    """q, u, F(q), M, h and the contact force directions of a tree on a free-flyer root."""

    name = "minimal"
    n_bilateral = 0
    constant_mass_matrix = False

    def __init__(self, desc: RobotDescription):
        self.desc = desc
        self.model = desc.model
        self.data = self.model.createData()
        self.nq = self.model.nq
        self.nv = self.model.nv
        self.tree = KinematicTree(self.model)
        ids = [self.model.getJointId(n) for n in desc.joint_names]
        #: indices in q / u of the actuated joints, in the public joint order
        self.joint_q = np.array([self.model.joints[j].idx_q for j in ids], dtype=np.int64)
        self.joint_v = np.array([self.model.joints[j].idx_v for j in ids], dtype=np.int64)
        cs = desc.contacts
        self.c_joint = np.array([c.joint for c in cs], dtype=np.int64)
        self.c_local = np.array([c.local for c in cs], dtype=float).reshape(-1, 3)
        self.c_radius = np.array([c.radius for c in cs], dtype=float)
        self.n_contacts = len(cs)
        self._gravity_only = None

    # -- configuration space --------------------------------------------------------------
    def neutral(self):
        return pin.neutral(self.model)

    def integrate(self, q, u, dt):
        """q ⊕ dt·u on the configuration manifold, quaternion re-normalised."""
        out = pin.integrate(self.model, q, u * dt)
        quat = out[3:7]
        out[3:7] = quat / np.sqrt(quat @ quat)
        return out

    # -- dynamics -------------------------------------------------------------------------
    def mass_matrix(self, q):
        """M(q) by CRBA; only the upper triangle is filled (as pin does)."""
        return pin.crba(self.model, self.data, q)

    def forces(self, q, u, tau):
        """h(q, u) = S^T τ − (C(q, u) u + g(q)) (actuated joints in the public order)."""
        h = -pin.nonLinearEffects(self.model, self.data, q, u)
        if tau is not None and tau.shape[0]:
            h[self.joint_v] += tau
        return h

    def contact_kinematics(self, q, ground, gap, position, Wt):
        """Fill gap (nc), position (nc x 3) and Wt (nc x 3 x nv) for all contact points."""
        t = self.tree
        contact_kinematics(q, t.parent, t.jtype, t.axis, t.pl_R, t.pl_p, t.idx_q, t.idx_v,
                           t.support, t.oR, t.op, self.c_joint, self.c_local, self.c_radius,
                           ground.n, ground.t1, ground.t2, ground.offset, gap, position, Wt)

    def wrench_generalized_force(self, q, frame: str, force, torque):
        """J^T [f; τ] for a wrench (world axes) applied at the origin of `frame` (a link)."""
        fid = self.model.getFrameId(frame)
        pin.framesForwardKinematics(self.model, self.data, q)
        J = pin.computeFrameJacobian(self.model, self.data, q, fid, pin.LOCAL_WORLD_ALIGNED)
        return J.T @ np.concatenate([force, torque])

    # -- public state mapping -------------------------------------------------------------
    def joint_positions(self, q):
        return q[self.joint_q].copy()

    def joint_velocities(self, u):
        return u[self.joint_v].copy()

    def base_state(self, q, u):
        """(position, quaternion_xyzw, linear velocity in the world frame,
        angular velocity in the base frame)."""
        quat = q[3:7].copy()
        R = pin.Quaternion(quat[3], quat[0], quat[1], quat[2]).toRotationMatrix()
        return q[0:3].copy(), quat, R @ u[0:3], u[3:6].copy()

    def set_base_velocity_world(self, q, u, v_world, omega_body):
        """Write a world-frame linear velocity and body angular velocity into u."""
        quat = q[3:7]
        R = pin.Quaternion(quat[3], quat[0], quat[1], quat[2]).toRotationMatrix()
        u[0:3] = R.T @ np.asarray(v_world, dtype=float)
        u[3:6] = omega_body

    def make_state(self, position, quat_xyzw, joints=None):
        q = self.neutral()
        q[0:3] = position
        quat = np.asarray(quat_xyzw, dtype=float)
        q[3:7] = quat / np.linalg.norm(quat)
        if joints is not None:
            q[self.joint_q] = joints
        return q

    def kinetic_energy(self, q, u):
        M = self.mass_matrix(q).copy()
        M = np.triu(M) + np.triu(M, 1).T
        return 0.5 * float(u @ M @ u)

    def potential_energy(self, q):
        return float(pin.computePotentialEnergy(self.model, self.data, q))

    def link_names(self):
        return [f.name for f in self.model.frames if f.type == pin.FrameType.BODY]
