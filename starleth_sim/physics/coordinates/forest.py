"""Generalized coordinates of a robot described as a *forest* of floating trees, cut from
one kinematic tree at a chosen set of revolute joints (paper Eqn. 19-22, Table 1):

* minimal  - no cut: one tree on a free-flyer root (a 12-joint quadruped: 19 coordinates,
             18 DOF);
* extended - the subtrees of the root cut free at their first joints (a quadruped: trunk + 4
             floating legs, 38 DOF, 20 bilateral constraints);
* maximal  - every joint cut: one free body per body (a quadruped: 13), each with its frame at
             its centre of mass so that its mass matrix diag(m I, Θ) is constant (78 DOF, 60
             bilateral constraints).

Any tree of revolute joints (axes along x, y, z or unaligned: pin's RX, RY, RZ and
RevoluteUnaligned) on a free-flyer root.

Every tree root is a free body with the paper's coordinates (Eqn. 21):
    q_root = [I_r (3), quaternion (x, y, z, w)],   u_root = [I_v (3), B_ω (3)]
(inertial velocity of the root frame's origin, body-frame angular velocity; Pinocchio's
quaternion storage order), followed by the angles/rates of the tree's revolute joints.
M and h come from the CRBA and RNEA of :mod:`starleth_sim.physics.rigid_body`, which
work in these coordinates directly (checked against Pinocchio's, whose roots use body-frame
linear velocities: M = Tᵀ M_pin T, h = Tᵀ (h_pin + Σ_k M_pin[:, v_k] (ω_k × v_k,body)),
T = diag(R_kᵀ, I), see from_pin_dynamics). For the maximal set M is constant and
h = [m g; −ω × Θ ω] per body.

A cut revolute joint between bodies P (parent side) and C (child side) becomes a 5-row
bilateral constraint (3 translational, 2 rotational; Eqn. 4, ε_B = 0):
    g_B = [x_P − x_C ; −(R_C a_C)·b2 ; (R_C a_C)·b1],  b1, b2 = a x b1 ⟂ the axis in P
    γ_B = W_Bᵀ u = [v_P − v_C ; b1·(ω_C − ω_P) ; b2·(ω_C − ω_P)]
Its actuator torque τ enters as equal and opposite generalized forces on the two bodies,
and its angle φ is recovered from the relative rotation of P and C.
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from starleth_interface.robot.urdf import revolute_axis

from ..description import RobotDescription
from ..kernels import (  # noqa: F401
    add_at,
    angular_jacobian,
    cut_joint_torques,
    cut_joints,
    from_pin_dynamics,
    gather_joint_values,
    integrate_forest,
    midpoint_dynamics,
    quat_rot,
    rigid_body_forces,
    to_pin_velocity,
    tree_dynamics,
)
from ..kinematics import KinematicTree, contact_kinematics, forward_kinematics, point_jacobian
from ..rigid_body import BodyInertias

_ALIGNED = {"JointModelRX": pin.JointModelRX, "JointModelRY": pin.JointModelRY,
            "JointModelRZ": pin.JointModelRZ}


def copy_revolute(jm):
    """A new pin joint model of the same revolute type and axis (for the forest)."""
    name = jm.shortname()
    if name in _ALIGNED:
        return _ALIGNED[name]()
    return pin.JointModelRevoluteUnaligned(revolute_axis(jm))


# --------------------------------------------------------------------------------------------
# the kernels over the forest arrays (C, csrc/forest.c):
#   integrate_forest(q, u, dt, jtype, idx_q, idx_v, out): out = q ⊕ Δt F(q) u: r ← r + Δt v,
#       P ← P ⊗ exp(Δt ω/2) per root, φ ← φ + Δt φ̇;
#   quat_rot(q, iq, R): the rotation of the root whose coordinates start at q[iq];
#   to_pin_velocity / from_pin_dynamics: Pinocchio's free-flyer convention and the
#       transform of its M and h into ours (the cross-check of rigid_body in
#       test/test_kinematics_dynamics.py);
#   tree_dynamics(q, u, (<tree>, <frames>, <inertias>), (M, h)): M and h at (q, u);
#   midpoint_dynamics(q, u, half_dt, <midpoint_model>, <ground>, jacobian_gap,
#       (qM, M, h, gap, position, Wt), frames): what a step needs at its midpoint,
#       over one forward kinematics: q^M = q ⊕ ½Δt F(q) u (Eqn. 6), M and h at (q^M, u^S),
#       the contacts' g_N, positions, W^T and surface frames (with μ) at q^M;
#   add_at(h, idx, values): h[idx[k]] += values[k];
#   rigid_body_forces(q, u, root_q, root_v, mass, inertia, gravity, h): h = [m g; −ω × Θ ω]
#       per free body (frames at the CoM, inertial linear velocity);
#   angular_jacobian(j, jtype, axis, idx_v, support, oR, out, zero=True);
#   cut_joints(q, u, (<tree>, <frames>), (cut_P, cut_C, p_P, p_C, a_P, b1_P, b2_P, a_C,
#       b1_C), (Wt_B, g_B, angle, rate, axis_world), do_fk): for every cut joint the 5 rows
#       of W_Bᵀ, g_B, φ, φ̇ and the hinge axis in the world; only the columns of the
#       velocities the two bodies depend on are written (Wt_B's others stay the zeros they
#       were made with);
#   gather_joint_values(x, index, cut_values, cut_index, out): the joints' φ (x = q) or φ̇
#       (x = u) in the public order;
#   cut_joint_torques(tau_cut, (cut_P, cut_C, axis_world), (jtype, axis, idx_v, support), oR,
#       h):
#       h += J_ω,Cᵀ (τ a) − J_ω,Pᵀ (τ a) for the cut joints' actuators.


# --------------------------------------------------------------------------------------------
def _checked_cut(src, cut):
    """The source joint ids of the joints to cut (names or ids), sorted, after checking that
    each is a revolute joint and that the model has a free-flyer root."""
    cut_ids = sorted(src.getJointId(n) if isinstance(n, str) else int(n) for n in cut)
    for j in cut_ids:
        if revolute_axis(src.joints[j]) is None:
            raise ValueError(f"only revolute joints can be cut, not "
                             f"'{src.names[j]}' ({src.joints[j].shortname()})")
    if src.joints[1].shortname() != "JointModelFreeFlyer":
        raise ValueError("the robot model needs a free-flyer root")
    return cut_ids


# --------------------------------------------------------------------------------------------
class ForestCoordinates:
    """q, u, F(q), M, h, contact and bilateral force directions of a cut kinematic tree."""

    def __init__(self, desc: RobotDescription, cut=(), com_frames=False, name="minimal"):
        self.name = name
        self.desc = desc
        src = desc.model
        cut_ids = _checked_cut(src, cut)
        self.src = src
        roots = [1] + cut_ids
        single_body_trees = self._build_forest(roots, cut_ids, com_frames)
        self._index_trees(roots, bool(com_frames and single_body_trees))
        self._init_cut_constraints(cut_ids)
        self._map_actuated_joints(cut_ids)
        self._init_contacts()
        if self.constant_mass_matrix:
            self._init_constant_mass_matrix()

    def _build_forest(self, roots, cut_ids, com_frames):
        """The forest model (self.model, self.data): one free-flyer tree per root (source
        joint 1 and every cut joint), holding the root's body and the bodies below it down to
        the next cut; with `com_frames` each root body's frame at its centre of mass.
        Fills self.joint_map (source joint j -> (forest joint, off), F = J_j · off). True
        when every tree is a single body."""
        src = self.src
        forest = pin.Model()
        forest.gravity = src.gravity
        #: source joint j -> (forest joint, off) with F = J_j · off: `off` places the forest
        #: body frame F in the source joint frame (identity except CoM frames)
        self.joint_map = {}
        children = {j: [] for j in range(src.njoints)}
        for j in range(2, src.njoints):
            children[src.parents[j]].append(j)

        def subtree(j):
            out = [j]
            for c in children[j]:
                if c not in cut_ids:
                    out += subtree(c)
            return out

        single_body_trees = True
        for root in roots:
            members = subtree(root)
            single_body_trees &= len(members) == 1
            inertia = src.inertias[root]
            offset = pin.SE3.Identity()
            if com_frames:
                if len(members) != 1:
                    raise ValueError("com_frames needs every tree to be a single body")
                offset = pin.SE3(np.eye(3), inertia.lever.copy())
                inertia = pin.Inertia(inertia.mass, np.zeros(3), inertia.inertia.copy())
            fj = forest.addJoint(0, pin.JointModelFreeFlyer(), pin.SE3.Identity(),
                                 f"{src.names[root]}_root" if root != 1 else src.names[1])
            forest.appendBodyToJoint(fj, inertia, pin.SE3.Identity())
            self.joint_map[root] = (fj, offset)
            for j in members[1:]:
                pf, poff = self.joint_map[src.parents[j]]
                jm = copy_revolute(src.joints[j])
                fjj = forest.addJoint(pf, jm, poff.inverse() * src.jointPlacements[j],
                                      src.names[j])
                forest.appendBodyToJoint(fjj, src.inertias[j], pin.SE3.Identity())
                self.joint_map[j] = (fjj, pin.SE3.Identity())
        self.model = forest
        self.data = forest.createData()
        return single_body_trees

    def _index_trees(self, roots, constant_mass_matrix):
        """Sizes and index arrays of the forest: nq, nv, the kinematic tree arrays (self.tree),
        each tree's root joint and its q / v offsets and the bodies' inertias of the
        CRBA / RNEA."""
        forest = self.model
        self.nq, self.nv = forest.nq, forest.nv
        self.tree = KinematicTree(forest)
        t = self.tree
        self.roots = np.array([self.joint_map[r][0] for r in roots], dtype=np.int64)
        self.root_q = t.idx_q[self.roots].copy()
        self.root_v = t.idx_v[self.roots].copy()
        # M's LTDL factor follows the trees (self.tree.dof_parent); linalg.ltdl_solve_cols
        # solves tree by tree, so each tree's dofs must be contiguous, starting at its root
        start = 0
        for k, p in enumerate(t.dof_parent):
            start = k if p == -1 else start
            if not start <= p < k and p != -1:
                raise ValueError("the forest's trees must have contiguous velocity indices, "
                                 "parents first")
        self.constant_mass_matrix = constant_mass_matrix
        #: the bodies' inertias for the CRBA / RNEA (rigid_body)
        self.inertias = BodyInertias(forest)
        self._midpoint_model = None     # see midpoint
        self._trunk = None              # see _trunk_frame

    def _init_cut_constraints(self, cut_ids):
        """Cut joints -> 5-row bilateral constraints (module docstring): for cut k the parent
        and child bodies (cut_P, cut_C), the joint's origin in each (p_P, p_C), its axis a in
        each (a_P, a_C) and the directions b1, b2 = a x b1 ⟂ a in P (b1_P, b2_P) and b1 in C
        (b1_C); plus the work arrays of the cut-joint kinematics."""
        src = self.src
        ncut = len(cut_ids)
        self.n_cut = ncut
        self.n_bilateral = 5 * ncut
        self.cut_P = np.zeros(ncut, dtype=np.int64)
        self.cut_C = np.zeros(ncut, dtype=np.int64)
        self.p_P, self.p_C = np.zeros((ncut, 3)), np.zeros((ncut, 3))
        self.a_P, self.a_C = np.zeros((ncut, 3)), np.zeros((ncut, 3))
        self.b1_P, self.b2_P = np.zeros((ncut, 3)), np.zeros((ncut, 3))
        self.b1_C = np.zeros((ncut, 3))
        for k, c in enumerate(cut_ids):
            a = revolute_axis(src.joints[c])
            b1 = np.array([0, 1.0, 0]) if abs(a[1]) < 0.9 else np.array([0, 0, 1.0])
            b1 = b1 - a * (a @ b1)
            b1 /= np.linalg.norm(b1)
            b2 = np.cross(a, b1)
            pf, poff = self.joint_map[src.parents[c]]
            X = poff.inverse() * src.jointPlacements[c]  # joint frame (φ = 0) in P's frame
            cf, coff = self.joint_map[c]
            Y = coff.inverse()                           # joint frame in C's frame
            self.cut_P[k], self.cut_C[k] = pf, cf
            self.p_P[k], self.p_C[k] = X.translation, Y.translation
            self.a_P[k] = X.rotation @ a
            self.b1_P[k], self.b2_P[k] = X.rotation @ b1, X.rotation @ b2
            self.a_C[k] = Y.rotation @ a
            self.b1_C[k] = Y.rotation @ b1
        self._angle = np.zeros(ncut)
        self._rate = np.zeros(ncut)
        self._axis_world = np.zeros((ncut, 3))
        self._WtB = np.zeros((self.n_bilateral, self.nv))
        self._cut_q = None
        self._torque_map = None
        #: the (q, u) objects of the last evaluation of the cut joints (see _cut_state)
        self._cut_state_at = (None, None)
        self._gB = np.zeros(self.n_bilateral)

    def _map_actuated_joints(self, cut_ids):
        """The actuated joints (desc.joint_names, public order): forest joints (joint_q,
        joint_v: their q / v indices, -1 for cut joints) or cut joints (joint_cut: index into
        the cut list, -1 for forest joints), and the masks / work arrays of
        add_joint_torques."""
        forest = self.model
        self.joint_q, self.joint_v, self.joint_cut = [], [], []
        for n in self.desc.joint_names:
            sj = self.src.getJointId(n)
            if sj in cut_ids:
                self.joint_q.append(-1)
                self.joint_v.append(-1)
                self.joint_cut.append(cut_ids.index(sj))
            else:
                fj = self.joint_map[sj][0]
                self.joint_q.append(forest.joints[fj].idx_q)
                self.joint_v.append(forest.joints[fj].idx_v)
                self.joint_cut.append(-1)
        self.joint_q = np.array(self.joint_q, dtype=np.int64)
        self.joint_v = np.array(self.joint_v, dtype=np.int64)
        # the joints' velocity indices as a slice when they are one contiguous block (the
        # minimal coordinates): h[slice] += τ is much cheaper than fancy indexing
        jv = self.joint_v
        self._joint_v_block = (slice(int(jv[0]), int(jv[-1]) + 1)
                               if jv.shape[0] and np.all(np.diff(jv) == 1) else None)
        self.joint_cut = np.array(self.joint_cut, dtype=np.int64)
        self._act_tree = self.joint_cut < 0
        self._act_cut = ~self._act_tree
        self._tau_cut = np.zeros(len(cut_ids))

    def _init_contacts(self):
        """The contact points (desc.contacts) in forest frames: their forest joint
        (c_joint), position in that joint's body frame (c_local) and radius (c_radius)."""
        cs = self.desc.contacts
        #: contact slots (the kernels' contacts: one per sphere, two on a terrain)
        self.n_contacts = len(cs)
        #: the contact spheres (desc.contacts): slots i and n_contact_spheres + i are sphere i's
        self.n_contact_spheres = len(cs)
        self.contact_names = [c.name for c in cs]
        self.c_joint = np.array([self.joint_map[c.joint][0] for c in cs], dtype=np.int64)
        self.c_local = np.array([self.joint_map[c.joint][1].actInv(c.local) for c in cs],
                                dtype=float).reshape(-1, 3)
        self.c_radius = np.array([c.radius for c in cs], dtype=float)

    @property
    def second_surfaces(self) -> bool:
        """Whether each contact sphere has a second slot (add_second_surface_slots)."""
        return self.n_contacts != self.n_contact_spheres

    def add_second_surface_slots(self):
        """Two contact slots per sphere (before anything uses the contacts): slot i its
        nearest surface, slot n_contact_spheres + i its second surface, the other side of a
        concave corner of a terrain (csrc/terrain.c). The slots of a sphere share its name,
        joint, point and radius."""
        if self.second_surfaces or self._midpoint_model is not None:
            raise RuntimeError("add_second_surface_slots: once, before the contacts are used")
        ns = self.n_contact_spheres
        self.n_contacts = 2 * ns
        self.contact_names = self.contact_names * 2
        self.c_joint = np.tile(self.c_joint, 2)
        self.c_local = np.tile(self.c_local, (2, 1))
        self.c_radius = np.tile(self.c_radius, 2)

    def _init_constant_mass_matrix(self):
        """Single free bodies with frames at their centres of mass: the constant mass matrix
        M = diag(m_k I, Θ_k) and the masses, inertias and gravity of rigid_body_forces."""
        forest = self.model
        self.body_mass = np.array([forest.inertias[int(r)].mass for r in self.roots])
        self.body_inertia = np.array([forest.inertias[int(r)].inertia for r in self.roots])
        self.body_gravity = np.asarray(forest.gravity.linear, dtype=float).copy()
        M = np.zeros((self.nv, self.nv))
        for i, _r in enumerate(self.roots):
            v = self.root_v[i]
            M[v:v + 3, v:v + 3] = self.body_mass[i] * np.eye(3)
            M[v + 3:v + 6, v + 3:v + 6] = self.body_inertia[i]
        self.M_const = M

    # -- configuration space ------------------------------------------------------------------
    def neutral(self):
        return pin.neutral(self.model)

    def integrate(self, q, u, dt):
        """q ⊕ Δt F(q) u (Eqn. 22) for every root and joint, quaternions re-normalised."""
        out = np.empty_like(q)
        t = self.tree
        integrate_forest(q, u, dt, t.jtype, t.idx_q, t.idx_v, out)
        return out

    # -- dynamics -----------------------------------------------------------------------------
    def _kinematics_for_cuts(self, q, u):
        self._cut_q = q  # W_B and g_B below belong to this configuration (see bilateral)
        self._cut_state_at = (q, u)
        t = self.tree
        cut_joints(q, u, t.args(), (self.cut_P, self.cut_C, self.p_P, self.p_C, self.a_P,
                                    self.b1_P, self.b2_P, self.a_C, self.b1_C),
                   (self._WtB, self._gB, self._angle, self._rate, self._axis_world), True)
        # what add_joint_torques needs of these kinematics, as copies: the tree buffers
        # (t.oR) are shared with every other kinematics call (contacts, pushes, ...)
        self._torque_map = (q, self._axis_world.copy(), t.oR.copy())

    def dynamics(self, q, u, tau=None):
        """(M, h) at (q, u); h includes the joint torques τ (public order) unless tau is None
        (see add_joint_torques)."""
        if self.constant_mass_matrix:
            M = self.M_const
            h = np.empty(self.nv)
            rigid_body_forces(q, u, self.root_q, self.root_v, self.body_mass, self.body_inertia,
                              self.body_gravity, h)
        else:
            M = np.empty((self.nv, self.nv))
            h = np.empty(self.nv)
            tree_dynamics(q, u, (*self.tree.args(), self.inertias.args()), (M, h))
        if tau is not None and tau.shape[0]:
            self.add_joint_torques(q, u, tau, h)
        return M, h

    def midpoint(self, q, u, dt, ground, gap, position, Wt, jacobian_gap=np.inf, frames=None):
        """(q^M, M, h) of a step of Δt from (q, u), h without the joint torques: q^M = q ⊕
        ½Δt F(q) u (Eqn. 6), M and h at (q^M, u); and gap, position, Wt (and frames) filled at
        q^M as by contact_kinematics. One kernel call unless M is constant."""
        if self.constant_mass_matrix:
            qM = self.integrate(q, u, 0.5 * dt)
            M, h = self.dynamics(qM, u, None)
            self.contact_kinematics(qM, ground, gap, position, Wt, jacobian_gap, frames)
            return qM, M, h
        qM = np.empty_like(q)
        M = np.empty((self.nv, self.nv))
        h = np.empty(self.nv)
        midpoint_dynamics(q, u, 0.5 * dt, self.midpoint_model(), ground.kernel_args,
                          jacobian_gap, (qM, M, h, gap, position, Wt), frames)
        return qM, M, h

    def midpoint_model(self):
        """The model as midpoint_dynamics takes it, gathered once: (tree, frames, inertias,
        contacts), the tree's and its scratch's arrays as `KinematicTree.args`, the
        inertias' (mass, lever, inertia, gravity), the contacts' (c_joint, c_local,
        c_radius)."""
        model = self._midpoint_model
        if model is None:
            model = self._midpoint_model = (*self.tree.args(), self.inertias.args(),
                                            (self.c_joint, self.c_local, self.c_radius))
        return model

    def add_joint_torques(self, q, u, tau, h):
        """h += the generalized force of the joint torques τ (public order) at q: Sᵀτ for
        joints inside a tree, equal and opposite body torques about the hinge axis for cut
        joints (the hinge axes and body orientations at q are reused when the last
        evaluation of the cut joints, e.g. `bilateral(q)`, was at this q object)."""
        if self.n_cut == 0:
            if self._joint_v_block is not None:
                h[self._joint_v_block] += tau
            else:
                add_at(h, self.joint_v, tau)
            return
        h[self.joint_v[self._act_tree]] += tau[self._act_tree]
        self._tau_cut[self.joint_cut[self._act_cut]] = tau[self._act_cut]
        if self._torque_map is None or self._torque_map[0] is not q:
            self._kinematics_for_cuts(q, u)
        _, axis_world, oR = self._torque_map
        t = self.tree
        cut_joint_torques(self._tau_cut, (self.cut_P, self.cut_C, axis_world),
                          (t.jtype, t.axis, t.idx_v, t.support), oR, h)

    def bilateral(self, q, u=None):
        """(W_Bᵀ (n_B x nv), g_B (n_B)) at q; arrays are reused between calls. The stepper
        asks for them at the midpoint right after `dynamics` evaluated the cut joints there
        (for their torques), so the same configuration object is not evaluated twice
        (configurations are never modified in place)."""
        if q is not self._cut_q or u is not None:
            self._kinematics_for_cuts(q, np.zeros(self.nv) if u is None else u)
        return self._WtB, self._gB

    def contact_kinematics(self, q, ground, gap, position, Wt, jacobian_gap=np.inf,
                           frames=None):
        """Fill gap (nc) and position (nc x 3) of all contact points, and Wt (nc x 3 x nv)
        of those with g_N ≤ jacobian_gap, against the ground plane and its terrain (a
        contact.GroundPlane); frames (nc x 11, optional): each contact's surface frame
        (n, t1, t2) and μ."""
        contact_kinematics(q, (*self.tree.args(), (self.c_joint, self.c_local, self.c_radius)),
                           ground.kernel_args, jacobian_gap, (gap, position, Wt), frames)

    def _link_point(self, frame):
        src = self.src
        if not src.existFrame(frame, pin.FrameType.BODY):   # (a joint may share its name)
            raise ValueError(f"unknown link '{frame}'")
        f = src.frames[src.getFrameId(frame, pin.FrameType.BODY)]
        fj, off = self.joint_map[f.parentJoint] if f.parentJoint in self.joint_map else (None, None)
        if fj is None:  # frame on the universe
            raise ValueError(f"link '{frame}' is not part of the robot")
        return fj, off.inverse() * f.placement

    def wrench_generalized_force(self, q, frame: str, force, torque):
        """Jᵀ [f; τ] for a wrench (world axes) applied at the origin of link `frame`."""
        fj, X = self._link_point(frame)
        t = self.tree
        forward_kinematics(q, t.parent, t.jtype, t.axis, t.pl_R, t.pl_p, t.idx_q, t.oR, t.op)
        p = t.oR[fj] @ X.translation + t.op[fj]
        Jv = np.empty((3, self.nv))
        Jw = np.empty((3, self.nv))
        point_jacobian(fj, p, t.jtype, t.axis, t.idx_v, t.support, t.oR, t.op, Jv)
        angular_jacobian(fj, t.jtype, t.axis, t.idx_v, t.support, t.oR, Jw)
        return Jv.T @ np.asarray(force, float) + Jw.T @ np.asarray(torque, float)

    # -- public state mapping -----------------------------------------------------------------
    def _cut_state(self, q, u):
        """The cut joints' angles and rates (self._angle, self._rate) at (q, u), with u None
        when only the angles are wanted; not evaluated again for the same q and u objects
        (states are never modified in place): a controller asking for the joint positions
        and velocities of one state costs one evaluation."""
        if not self.n_cut:
            return
        at_q, at_u = self._cut_state_at
        if at_q is q and (u is None or at_u is u):
            return
        self._kinematics_for_cuts(q, np.zeros(self.nv) if u is None else u)

    def cut_motion_buffers(self):
        """(φ, φ̇): the arrays of the cut joints' angles and rates that joint_positions and
        joint_velocities read; a one-kernel step writes those of its end state into them
        and then calls cut_motion_written."""
        return self._angle, self._rate

    def cut_motion_written(self, q, u):
        """The cut_motion_buffers now hold φ and φ̇ at (q, u) (a one-kernel step wrote them,
        with the arithmetic of cut_joints)."""
        self._cut_state_at = (q, u)

    def joint_positions(self, q, u=None):
        """φ at q; u: the velocities of the same state where known (the cut joints'
        kinematics then serve joint_velocities(q, u) too)."""
        if self.n_cut == 0:     # one gather (a new array), no masks
            return q[self.joint_q]
        self._cut_state(q, u)
        out = np.empty(self.joint_q.shape[0])
        gather_joint_values(q, self.joint_q, self._angle, self.joint_cut, out)
        return out

    def joint_velocities(self, q, u):
        if self.n_cut == 0:
            return u[self.joint_v]
        self._cut_state(q, u)
        out = np.empty(self.joint_v.shape[0])
        gather_joint_values(u, self.joint_v, self._rate, self.joint_cut, out)
        return out

    def _trunk_frame(self):
        """(Y's translation, Y's rotation, its transpose, whether it is the identity) of the
        trunk frame Y in the first root body's frame, taken once (base_state runs every
        step of a ROS node)."""
        trunk = self._trunk
        if trunk is None:
            Y = self.joint_map[1][1].inverse()
            rot = np.array(Y.rotation)
            trunk = self._trunk = (np.array(Y.translation), rot, np.ascontiguousarray(rot.T),
                                   bool(np.allclose(rot, np.eye(3))))
        return trunk

    def base_state(self, q, u):
        """(position, quaternion_xyzw, linear velocity (world), angular velocity (base frame))
        of the trunk (the first root); for com_frames the trunk frame is offset from its CoM:
        with the trunk frame Y in the root body and R the root's rotation, d = R Y_p,
        position = x + d, v = v_root + (R ω) × d, orientation R Y_R, ω_trunk = Y_Rᵀ ω."""
        iq, iv = self.root_q[0], self.root_v[0]
        t, rot, rot_t, identity = self._trunk_frame()
        R = np.zeros((3, 3))
        quat_rot(q, iq, R)
        d = R @ t
        pos = q[iq:iq + 3] + d
        w_body = u[iv + 3:iv + 6]
        a0, a1, a2 = (R @ w_body).tolist()
        b0, b1, b2 = d.tolist()
        v = u[iv:iv + 3] + np.array((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0))
        if identity:
            qxyzw = q[iq + 3:iq + 7].copy()
        else:
            quat = pin.Quaternion(R @ rot)
            qxyzw = np.array([quat.x, quat.y, quat.z, quat.w])
        return pos, qxyzw, v, rot_t @ w_body

    def make_state(self, position, quat_xyzw, joints=None):
        """A state from the trunk pose and the joint angles (public order), at rest."""
        src = self.src
        q_min = pin.neutral(src)
        q_min[0:3] = position
        quat = np.asarray(quat_xyzw, dtype=float)
        q_min[3:7] = quat / np.linalg.norm(quat)
        if joints is not None:
            for n, v in zip(self.desc.joint_names, joints, strict=True):
                q_min[src.joints[src.getJointId(n)].idx_q] = v
        return self.from_minimal(q_min, np.zeros(src.nv))[0]

    def from_minimal(self, q_min, u_min):
        """The state of this forest equal to a state of the uncut model (minimal coordinates):
        each root gets the pose and velocity of its body, the joints inside trees their
        angles and rates."""
        src = self.src
        data = src.createData()
        R0 = pin.Quaternion(q_min[6], q_min[3], q_min[4], q_min[5]).toRotationMatrix()
        v_pin = u_min.copy()
        v_pin[0:3] = R0.T @ u_min[0:3]
        pin.forwardKinematics(src, data, q_min, v_pin)
        q = self.neutral()
        u = np.zeros(self.nv)
        for sj, (fj, off) in self.joint_map.items():
            jm = self.model.joints[fj]
            if jm.shortname() == "JointModelFreeFlyer":
                oM = data.oMi[sj] * off
                quat = pin.Quaternion(oM.rotation)
                q[jm.idx_q:jm.idx_q + 3] = oM.translation
                q[jm.idx_q + 3:jm.idx_q + 7] = [quat.x, quat.y, quat.z, quat.w]
                vel = off.actInv(data.v[sj])           # body-frame twist at the new origin
                u[jm.idx_v:jm.idx_v + 3] = oM.rotation @ vel.linear
                u[jm.idx_v + 3:jm.idx_v + 6] = vel.angular
            else:
                sjm = src.joints[sj]
                q[jm.idx_q] = q_min[sjm.idx_q]
                u[jm.idx_v] = u_min[sjm.idx_v]
        return q, u

    def kinetic_energy(self, q, u):
        M, _ = self.dynamics(q, u, None)
        return 0.5 * float(u @ M @ u)

    def potential_energy(self, q):
        return float(pin.computePotentialEnergy(self.model, self.data, q))

    def link_names(self):
        return [f.name for f in self.src.frames if f.type == pin.FrameType.BODY]
