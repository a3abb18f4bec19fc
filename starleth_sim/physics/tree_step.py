"""One whole physics step in one kernel call (`MoreauStepper` uses it for a step that was not
prepared ahead and is not profiled): tree_step_hard / tree_step_compliant for coordinate sets
without bilateral constraints whose M depends on q (the minimal coordinates), forest_step_hard
for hard contacts in a cut forest (the extended and maximal coordinates: bilateral
constraints of the cut joints, M of the trees or constant). C kernels in
``csrc/one_step.c``.

They run the same phases, in the same order, as the phase-by-phase path of
:mod:`starleth_sim.physics.step_kernels` (so the same result bit for bit) and save what lies
between them: the calls from Python and the Python around them. The model, ground and
workspace arrays travel packed in four buffers (`TreeStepModel`, and `CutModel` for the cut
joints). A failing step leaves the state as it was; the kernels release the GIL.

The kernels, each returning (outcome (TREE_STEP_*), |I|, opened, iterations, status,
residual, retried, projection iterations, projection status):

- ``tree_step_hard(saturate, q, u, tau, f_ext, last_impulse, last_active, last_bilateral,
  report, is_active, qE, uE, floats, ints, support, workspace)``: the applied torques
  (actuator.saturate_torque unless `saturate` is False), Eqn. (6) and M, h, W at the
  midpoint, the contact problem and its solution, Eqn. (8). f_ext: the generalized external
  force or an empty array. Writes q^E, u^E, the report buffer (Λ, g_N, contact points,
  applied torques: report_views), the active flags and the workspace; the warm-start
  memory is updated only when the step succeeds (TREE_STEP_OK), and a non-finite τ
  (TREE_STEP_NONFINITE_TORQUE) is found before anything is done.
- ``tree_step_compliant(saturate, q, u, tau, f_ext, closed, slip, anchor, lam, report,
  is_active, qE, uE, floats, ints, support, workspace)``: the same for compliant contacts
  (Alg. 1, the CompliantLaw packed in the model): the report's Λ is the compliant force Δt
  and is_active the closed flags (g_N(q^M) ≤ 0); a failed step leaves the contact state as
  it was.
- ``forest_step_hard(q, u, applied_tau, f_ext, factor, last_impulse, last_active,
  last_bilateral, report, is_active, qE, uE, angle_E, rate_E, floats, ints, support,
  workspace, cut_floats, cut_ints, cut_workspace)``: tree_step_hard for a cut forest: the
  bilateral constraints of the cut joints at q^M (W_B^T, g_B, b_B = (β/Δt) g_B), the joint
  torques (saturated by the caller: a cut joint's rate needs the cut-joint kinematics of
  the state), the contact and bilateral problem (factor: whether to factor M, False to reuse
  a constant M's factor in L); Λ_B joins the warm-start memory, and a successful step also
  writes the cut joints' φ and φ̇ at (q^E, u^E) into angle_E and rate_E.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .kernels import (TREE_STEP_NONFINITE_IMPULSE, TREE_STEP_NONFINITE_STATE,  # noqa: F401
                      TREE_STEP_NONFINITE_TORQUE, TREE_STEP_NOT_PD, TREE_STEP_OK,
                      forest_step_hard, tree_step_compliant, tree_step_hard)


class TreeStepModel(NamedTuple):
    """The model, ground and workspace arrays of the one-kernel step (tree_step_hard /
    tree_step_compliant) packed into four buffers, so that a call from Python passes four
    arrays instead of some thirty. The packing is pure layout (csrc/one_step.c reads it,
    unpack_tree_model): the kernels compute exactly what the phase-by-phase path computes.

    floats: the StepSettings (its 19 fields as floats, see _step_settings) and the
    CompliantLaw (6) of the step, axis, pl_R, pl_p, oR, op (the forward kinematics'
    scratch), mass, lever, inertia, gravity, c_local, c_radius (the forest's arrays,
    midpoint_model order), the ground's n, t1, t2 and offset, ε per contact (nc x 2), the
    actuators' effort and velocity limits (one per actuated joint, public order); ints:
    [nj, nc, number of actuated joints, nv], then parent, jtype, idx_q, idx_v, c_joint,
    joint_v and the dofs' parents (KinematicTree.dof_parent, the structure of M's LTDL
    factor); support: the tree's support matrix; workspace: g_N (nc), contact points
    (nc x 3), W^T of every contact (nc x 3 x nv), the factor L of M (nv x nv), u_free and
    Δu_p (nv each). The kernels check these lengths against ints[0:4] on every call."""

    floats: np.ndarray
    ints: np.ndarray
    support: np.ndarray
    workspace: np.ndarray

    @staticmethod
    def pack(settings, law, model, ground, eps, joint_v, dof_parent, nv, effort_limit,
             velocity_limit):
        """Packs the StepSettings and CompliantLaw, midpoint_model()'s arrays, the
        GroundPlane, ε and the torque limits (see actuator.saturate_torque); returns the
        record and the workspace's views (gap, position, Wt_all, L, u_free, u_corr), which
        the stepper keeps as its own arrays."""
        (parent, jtype, axis, pl_R, pl_p, idx_q, idx_v, support, oR, op, mass, lever,
         inertia, gravity, c_joint, c_local, c_radius) = model
        floats = np.concatenate([np.ravel(a).astype(np.float64) for a in (
            [float(v) for v in settings], [float(v) for v in law], axis, pl_R, pl_p, oR,
            op, mass, lever, inertia, gravity, c_local, c_radius, ground.n, ground.t1,
            ground.t2, [ground.offset], eps, effort_limit, velocity_limit)])
        nj, nc = parent.shape[0], c_joint.shape[0]
        ints = np.concatenate([np.ravel(a).astype(np.int64) for a in (
            [nj, nc, joint_v.shape[0], nv], parent, jtype, idx_q, idx_v, c_joint, joint_v,
            dof_parent)])
        sizes = (nc, 3 * nc, 3 * nc * nv, nv * nv, nv, nv)
        workspace = np.zeros(sum(sizes))
        views, o = [], 0
        for n in sizes:
            views.append(workspace[o:o + n])
            o += n
        gap, position, Wt_all, L, u_free, u_corr = views
        return (TreeStepModel(floats, ints, np.ascontiguousarray(support), workspace),
                (gap, position.reshape(nc, 3), Wt_all.reshape(nc, 3, nv), L.reshape(nv, nv),
                 u_free, u_corr))


def report_size(nc, na):
    """The length of a one-kernel step's report buffer (see report_views)."""
    return 7 * nc + na


def report_views(report, nc, na):
    """The views of a one-kernel step's report buffer (float64, report_size(nc, na)):
    (Λ (nc x 3, contact frame), g_N at q^M (nc), contact points at q^M (nc x 3), the
    applied torques (na)): what the step reports, written by the kernel in one buffer so
    that a caller allocates nothing per step."""
    return (report[:3 * nc].reshape(nc, 3), report[3 * nc:4 * nc],
            report[4 * nc:7 * nc].reshape(nc, 3), report[7 * nc:7 * nc + na])


class CutModel(NamedTuple):
    """What forest_step_hard needs beyond the TreeStepModel: the cut joints, the actuators'
    place (tree joint or cut joint), a constant M and its free bodies, and the workspace of
    the bilateral constraints, packed like TreeStepModel.

    floats: β/Δt (β: bilateral.stabilization, b_B = (β/Δt) g_B), then per cut joint p_P,
    p_C, a_P, b1_P, b2_P, a_C, b1_C (ForestCoordinates' arrays, ncut x 3 each), then for a
    constant M: M (nv x nv) and the free bodies' masses, inertias (nr x 3 x 3) and gravity;
    ints: [ncut, constant M (0/1), nr], cut_P, cut_C, joint_cut (one per actuated joint,
    public order: its cut joint, -1 inside a tree), root_q, root_v; workspace: W_B^T
    (5 ncut x nv), g_B and b_B (5 ncut each), φ, φ̇ (ncut each; φ̇ at zero velocity, not
    used), the hinge axes in the world (ncut x 3) and the step's Λ_B (5 ncut, kept there
    until the step is known to end finite)."""

    floats: np.ndarray
    ints: np.ndarray
    workspace: np.ndarray

    @staticmethod
    def pack(coords, beta_over_dt):
        """The CutModel of ForestCoordinates `coords` (β/Δt: the factor of b_B)."""
        c = coords
        ncut, nv = c.n_cut, c.nv
        constant = bool(c.constant_mass_matrix)
        arrays = [[float(beta_over_dt)], c.p_P, c.p_C, c.a_P, c.b1_P, c.b2_P, c.a_C, c.b1_C]
        if constant:
            arrays += [c._M_const, c._mass, c._inertia, c._gravity]
        floats = np.concatenate([np.ravel(np.asarray(a, dtype=np.float64)) for a in arrays])
        nr = c.roots.shape[0] if constant else 0
        ints = np.concatenate([np.ravel(np.asarray(a, dtype=np.int64)) for a in (
            [ncut, int(constant), nr], c.cut_P, c.cut_C, c.joint_cut,
            c.root_q if constant else [], c.root_v if constant else [])])
        nB = 5 * ncut
        workspace = np.zeros(nB * nv + 2 * nB + 2 * ncut + 3 * ncut + nB)
        return CutModel(floats, ints, workspace)
