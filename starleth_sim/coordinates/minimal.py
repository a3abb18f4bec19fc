"""Minimal set of generalized coordinates (Eqn. 21-22): floating base + joint angles.

The paper's set (Eqn. 21), stored in Pinocchio's layout:
    q = [I_r_OB (3), quaternion (x, y, z, w), φ (joints in pin order)]      nq = 7 + nj
    u = [I_v_B (3), B_ω_IB (3), φ̇]                                         nv = 6 + nj
i.e. the trunk's linear velocity in the *inertial* frame and its angular velocity in the
*body* frame. The quaternion is stored (x, y, z, w) as Pinocchio does; the paper writes
(p0, p1, p2, p3) = (w, x, y, z). Public accessors name the order explicitly.

Pinocchio's free-flyer uses the body-frame linear velocity u_pin = T u, T = diag(Rᵀ, I, I).
M and h come from pin's CRBA/RNEA and are transformed once per step:
    M = Tᵀ M_pin T,   h = Tᵀ (h_pin + M_pin[:, 0:3] (ω × Rᵀ v))      (u̇_pin = T u̇ + Ṫ u)
With the inertial velocity, a free body's translation is integrated exactly and does not
pick up the O((ω Δt)²) per-step energy error that explicit steps in the body-frame velocity
suffer for spinning bodies.

q̇ = F(q) u (Eqn. 22) is integrated on the manifold: r ← r + Δt v, P ← P ⊗ exp(Δt ω/2)
(exact for constant body rate), φ ← φ + Δt φ̇; the quaternion is re-normalised, so its
norm stays 1 to machine precision.
"""
from __future__ import annotations

import numba as nb
import numpy as np
import pinocchio as pin

from ..description import RobotDescription
from ..kinematics import KinematicTree, contact_kinematics


@nb.njit(cache=True)
def integrate_minimal(q, u, dt, out):
    """out = q ⊕ Δt F(q) u for a free-flyer root followed by 1-DOF joints."""
    for k in range(3):
        out[k] = q[k] + dt * u[k]
    wx, wy, wz = u[3] * dt, u[4] * dt, u[5] * dt
    ang = np.sqrt(wx * wx + wy * wy + wz * wz)
    if ang > 1e-12:
        s = np.sin(0.5 * ang) / ang
    else:
        s = 0.5 - ang * ang / 48.0
    dx, dy, dz, dw = wx * s, wy * s, wz * s, np.cos(0.5 * ang)
    x, y, z, w = q[3], q[4], q[5], q[6]
    # P ⊗ dP (Hamilton product, body-frame increment on the right)
    nx = w * dx + x * dw + y * dz - z * dy
    ny = w * dy - x * dz + y * dw + z * dx
    nz = w * dz + x * dy - y * dx + z * dw
    nw = w * dw - x * dx - y * dy - z * dz
    n = np.sqrt(nx * nx + ny * ny + nz * nz + nw * nw)
    out[3] = nx / n
    out[4] = ny / n
    out[5] = nz / n
    out[6] = nw / n
    for k in range(7, q.shape[0]):
        out[k] = q[k] + dt * u[k - 1]


@nb.njit(cache=True)
def base_rotation(q, R):
    x, y, z, w = q[3], q[4], q[5], q[6]
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - z * w)
    R[0, 2] = 2 * (x * z + y * w)
    R[1, 0] = 2 * (x * y + z * w)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - x * w)
    R[2, 0] = 2 * (x * z - y * w)
    R[2, 1] = 2 * (y * z + x * w)
    R[2, 2] = 1 - 2 * (x * x + y * y)


@nb.njit(cache=True)
def to_pin_velocity(q, u, R, u_pin):
    """u_pin = T u: the base linear velocity rotated into the body frame."""
    base_rotation(q, R)
    for k in range(u.shape[0]):
        u_pin[k] = u[k]
    for a in range(3):
        u_pin[a] = R[0, a] * u[0] + R[1, a] * u[1] + R[2, a] * u[2]


@nb.njit(cache=True)
def from_pin_dynamics(M_pin, h_pin, R, u_pin, M, h):
    """M = Tᵀ M_pin T and h = Tᵀ (h_pin + M_pin[:, :3] (ω × v_body)); M_pin upper triangle only."""
    n = M_pin.shape[0]
    for i in range(n):
        for j in range(i, n):
            M[i, j] = M_pin[i, j]
            M[j, i] = M_pin[i, j]
    wx, wy, wz = u_pin[3], u_pin[4], u_pin[5]
    vx, vy, vz = u_pin[0], u_pin[1], u_pin[2]
    cx = wy * vz - wz * vy
    cy = wz * vx - wx * vz
    cz = wx * vy - wy * vx
    for i in range(n):
        h[i] = h_pin[i] + M[i, 0] * cx + M[i, 1] * cy + M[i, 2] * cz
    # rows 0..2: left-multiply by R; columns 0..2: right-multiply by Rᵀ
    tmp = np.empty(3)
    for j in range(n):
        for a in range(3):
            tmp[a] = R[a, 0] * M[0, j] + R[a, 1] * M[1, j] + R[a, 2] * M[2, j]
        for a in range(3):
            M[a, j] = tmp[a]
    for i in range(n):
        for a in range(3):
            tmp[a] = M[i, 0] * R[a, 0] + M[i, 1] * R[a, 1] + M[i, 2] * R[a, 2]
        for a in range(3):
            M[i, a] = tmp[a]
    for a in range(3):
        tmp[a] = R[a, 0] * h[0] + R[a, 1] * h[1] + R[a, 2] * h[2]
    for a in range(3):
        h[a] = tmp[a]


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
        self.contact_names = [c.name for c in cs]
        if self.model.joints[1].shortname() != "JointModelFreeFlyer" or \
                any(self.model.joints[j].nq != 1 for j in range(2, self.model.njoints)):
            raise ValueError("minimal coordinates need a free-flyer root and 1-DOF joints")
        self._R = np.zeros((3, 3))
        self._u_pin = np.zeros(self.nv)
        self._M = np.zeros((self.nv, self.nv))
        self._h = np.zeros(self.nv)
        self._q_dyn = None

    # -- configuration space --------------------------------------------------------------
    def neutral(self):
        return pin.neutral(self.model)

    def integrate(self, q, u, dt):
        """q ⊕ Δt F(q) u (Eqn. 22) on the configuration manifold, quaternion re-normalised."""
        out = np.empty_like(q)
        integrate_minimal(q, u, dt, out)
        return out

    # -- dynamics -------------------------------------------------------------------------
    def dynamics(self, q, u, tau):
        """(M, h) at (q, u): M by CRBA, h = Sᵀτ − (C(q, u) u + g(q)) by RNEA (pin), both
        transformed to the inertial base velocity. Returns new arrays (full symmetric M)."""
        to_pin_velocity(q, u, self._R, self._u_pin)
        M_pin = pin.crba(self.model, self.data, q)
        h_pin = -pin.nonLinearEffects(self.model, self.data, q, self._u_pin)
        if tau is not None and tau.shape[0]:
            h_pin[self.joint_v] += tau
        M = np.empty((self.nv, self.nv))
        h = np.empty(self.nv)
        from_pin_dynamics(M_pin, h_pin, self._R, self._u_pin, M, h)
        return M, h

    def contact_kinematics(self, q, ground, gap, position, Wt, jacobian_gap=np.inf):
        """Fill gap (nc) and position (nc x 3) of all contact points, and Wt (nc x 3 x nv)
        of those with g_N ≤ jacobian_gap."""
        t = self.tree
        contact_kinematics(q, t.parent, t.jtype, t.axis, t.pl_R, t.pl_p, t.idx_q, t.idx_v,
                           t.support, t.oR, t.op, self.c_joint, self.c_local, self.c_radius,
                           ground.n, ground.t1, ground.t2, ground.offset, jacobian_gap, gap,
                           position, Wt)

    def wrench_generalized_force(self, q, frame: str, force, torque):
        """Jᵀ [f; τ] for a wrench (world axes) applied at the origin of `frame` (a link)."""
        fid = self.model.getFrameId(frame)
        pin.framesForwardKinematics(self.model, self.data, q)
        J = pin.computeFrameJacobian(self.model, self.data, q, fid, pin.LOCAL_WORLD_ALIGNED)
        base_rotation(q, self._R)
        J[:, 0:3] = J[:, 0:3] @ self._R.T  # pin's body-frame linear velocity -> inertial
        return J.T @ np.concatenate([force, torque])

    # -- public state mapping -------------------------------------------------------------
    def joint_positions(self, q):
        return q[self.joint_q].copy()

    def joint_velocities(self, u):
        return u[self.joint_v].copy()

    def base_state(self, q, u):
        """(position, quaternion_xyzw, linear velocity in the world frame,
        angular velocity in the base frame)."""
        return q[0:3].copy(), q[3:7].copy(), u[0:3].copy(), u[3:6].copy()

    def make_state(self, position, quat_xyzw, joints=None):
        q = self.neutral()
        q[0:3] = position
        quat = np.asarray(quat_xyzw, dtype=float)
        q[3:7] = quat / np.linalg.norm(quat)
        if joints is not None:
            q[self.joint_q] = joints
        return q

    def kinetic_energy(self, q, u):
        M, _ = self.dynamics(q, u, None)
        return 0.5 * float(u @ M @ u)

    def potential_energy(self, q):
        return float(pin.computePotentialEnergy(self.model, self.data, q))

    def link_names(self):
        return [f.name for f in self.model.frames if f.type == pin.FrameType.BODY]
