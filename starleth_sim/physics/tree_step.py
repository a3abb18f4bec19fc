"""One whole physics step in one kernel call (`MoreauStepper` uses it for a step that was not
prepared ahead and is not profiled): tree_step_hard / tree_step_compliant for coordinate sets
without bilateral constraints whose M depends on q (the minimal coordinates), forest_step_hard
for hard contacts in a cut forest (the extended and maximal coordinates: bilateral
constraints of the cut joints, M of the trees or constant).

It runs the same kernels, in the same order, as the phase-by-phase path of
:mod:`starleth_sim.physics.step_kernels` (so the same result bit for bit) and saves what lies
between them: the calls from Python (≈0.1 µs per array argument and call, measured) and the
Python around them. The model, ground and workspace arrays travel packed in four buffers
(`TreeStepModel`). A failing step leaves the state as it was.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numba as nb

from .kernel_cache import KERNEL
from . import prox
from .array_views import (ARENA_ALIGN, arena_floats, arena_ints, borrowed, keep_alive,
                          view2, view3)
from .actuator import saturate_torque
from .coordinates.forest import (cut_joint_motion, cut_joint_torques, cut_joints,
                                 integrate_forest, midpoint_dynamics, rigid_body_forces)
from .kinematics import contact_kinematics
from .step_kernels import (ContactProblem, StepSettings, complete_problem_inlined,
                           contact_problem_inlined, end_of_step, remember_contacts,
                           solve_compliant)


#: tree_step_* outcomes (the first entry of their result)
(TREE_STEP_OK, TREE_STEP_NOT_PD, TREE_STEP_NONFINITE_IMPULSE, TREE_STEP_NONFINITE_STATE,
 TREE_STEP_NONFINITE_TORQUE) = range(5)


class TreeStepModel(NamedTuple):
    """The model, ground and workspace arrays of the one-kernel step (tree_step_hard /
    tree_step_compliant) packed into four buffers, so that a call from Python unboxes four
    arrays instead of some thirty (≈0.1 µs each per call, measured). The packing is pure
    layout: the kernels take views of the buffers (unpack_tree_model) and compute exactly
    what the phase-by-phase path computes.

    floats: the StepSettings (its 19 fields as floats, see _step_settings) and the
    CompliantLaw (6) of the step, axis, pl_R, pl_p, oR, op (the forward kinematics'
    scratch), mass, lever, inertia, gravity, c_local, c_radius (the forest's arrays,
    midpoint_model order), the ground's n, t1, t2 and offset, ε per contact (nc x 2), the
    actuators' effort and velocity limits (one per actuated joint, public order); ints:
    [nj, nc, number of actuated joints, nv], then parent, jtype, idx_q, idx_v, c_joint,
    joint_v and the dofs' parents (KinematicTree.dof_parent, the structure of M's LTDL
    factor), and the sizes of the step's arena (arena_size); support: the tree's support
    matrix; workspace: g_N (nc), contact points (nc x 3), W^T of every contact
    (nc x 3 x nv), the factor L of M (nv x nv), u_free and Δu_p (nv each), then the step's
    arena (step_arena)."""

    floats: np.ndarray
    ints: np.ndarray
    support: np.ndarray
    workspace: np.ndarray

    @staticmethod
    def pack(settings, law, model, ground, eps, joint_v, dof_parent, nv, effort_limit,
             velocity_limit, n_bilateral=0):
        """Packs the StepSettings and CompliantLaw, midpoint_model()'s arrays, the
        GroundPlane, ε and the torque limits (see actuator.saturate_torque), with a step's
        arena (step_arena) sized for n_bilateral bilateral rows; returns the record and the
        workspace's views (gap, position, Wt_all, L, u_free, u_corr), which the stepper
        keeps as its own arrays."""
        (parent, jtype, axis, pl_R, pl_p, idx_q, idx_v, support, oR, op, mass, lever,
         inertia, gravity, c_joint, c_local, c_radius) = model
        floats = np.concatenate([np.ravel(a).astype(np.float64) for a in (
            [float(v) for v in settings], [float(v) for v in law], axis, pl_R, pl_p, oR,
            op, mass, lever, inertia, gravity, c_local, c_radius, ground.n, ground.t1, ground.t2, [ground.offset], eps, effort_limit,
            velocity_limit)])
        nj, nc = parent.shape[0], c_joint.shape[0]
        n_floats, n_ints = arena_size(nc, nv, n_bilateral)
        ints = np.concatenate([np.ravel(a).astype(np.int64) for a in (
            [nj, nc, joint_v.shape[0], nv], parent, jtype, idx_q, idx_v, c_joint, joint_v,
            dof_parent, [n_floats, n_ints])])
        sizes = (nc, 3 * nc, 3 * nc * nv, nv * nv, nv, nv)
        workspace = np.zeros(sum(sizes) + n_floats + n_ints)
        views, o = [], 0
        for n in sizes:
            views.append(workspace[o:o + n])
            o += n
        gap, position, Wt_all, L, u_free, u_corr = views
        return (TreeStepModel(floats, ints, np.ascontiguousarray(support), workspace),
                (gap, position.reshape(nc, 3), Wt_all.reshape(nc, 3, nv), L.reshape(nv, nv),
                 u_free, u_corr))


def arena_size(nc, nv, nb):
    """(floats, ints) of a one-kernel step's arena (step_arena) for nc contact points, nv
    velocities and nb bilateral rows: what a step takes from it with every contact active
    (m = 3 nc + nb rows): the midpoint's q^M, M and h; contact_problem's active set, W^T,
    M^{-1}W and b, G and its diagonal, L_B, the patterns of W^T, M^{-1}W and G, the
    envelopes of M^{-1}W's rows, the columns of ltdl_solve_cols and L_B's envelope; the
    prox's buffers; the projection's gaps; the compliant step's copy of the contact state
    (the int64 entries stored in float64 slots, 3 more for the arena's positions and
    misses); for a cut forest, the scratch of cut_joints, cut_joint_torques and
    cut_joint_motion and the work of ltdl_solve_cols_pattern. A request beyond it
    allocates (and is counted: arena_usage)."""
    m = 3 * nc + nb
    floats = ((2 * m * nv + m) + (m * m + m) + nb * nb
              + (2 * nv + nv * nv + nv)    # q^M (nq ≤ 2 nv), M and h of the midpoint
              + (4 * m + nv + nc)          # the prox phase's Λ^0, Λ, r, u^E, μ and c
              + (2 * m + nb)               # the Delassus-form prox's work
              + nc                         # the projection's predicted gaps
              + 6 * nc                     # the compliant contact state kept
              + 2 * (6 * nv + 42) + 3 * nv + nb + nv   # the cut joints' scratch
              + nv * m)                    # ltdl_solve_cols_pattern's blocks
    ints = (nc + (m + 1 + m * nv) + m + (nv + 1 + nv * m) + (m + 1 + m * m) + nb
            + 2 * nc + 3
            + 2 * nv                       # the envelopes of M^{-1}W's rows (delassus)
            + (4 * nv + 3 + (m + 1) + 2 * m * nv) + (m + 1)   # ltdl_solve_cols_pattern
            + 3 * nv)                      # the cut joints' columns
    # (each part rounded up to ARENA_ALIGN entries, the starts aligned: 30 parts at most)
    slack = 31 * ARENA_ALIGN
    return floats + slack, ints + slack


@nb.njit(**KERNEL, inline="always")
def step_arena(ints, workspace, nc, nv):
    """The arena (array_views.arena_floats) of a one-kernel step, emptied: the workspace
    from _arena_start on, its sizes (arena_size) the last two entries of `ints`; borrowed
    (the caller holds the buffers for the call)."""
    ints, workspace = borrowed(ints), borrowed(workspace)
    n = ints.shape[0]
    n_floats, n_ints = ints[n - 2], ints[n - 1]
    w = _arena_start(workspace, nc, nv)
    floats = workspace[w:w + n_floats]
    pos = _arena_positions(workspace, w, n_floats)
    pos[0] = 0
    pos[1] = 0
    ints = workspace[w + n_floats + 3:w + n_floats + n_ints].view(np.int64)
    a = _to_aligned(ints, 0)
    return floats, ints[a:], pos


def arena_usage(model) -> tuple:
    """(floats, ints) the last one-kernel step took from the arena (step_arena) of `model`
    (a TreeStepModel or its tuple), and the requests that did not fit since it was packed
    (each allocated instead)."""
    ints, workspace = model[1], model[3]
    w = _arena_start(workspace, int(ints[1]), int(ints[3]))
    pos = _arena_positions(workspace, w, int(ints[-2]))
    return int(pos[0]), int(pos[1]), int(pos[2])


@nb.njit(**KERNEL, inline="always")
def _arena_start(workspace, nc, nv):
    """Where a TreeStepModel's arena starts in its workspace: after the views of
    unpack_tree_model (gap, position, Wt_all, L, u_free, u_corr), at a 64-byte boundary."""
    w = 4 * nc + 3 * nc * nv + nv * nv + 2 * nv
    return w + _to_aligned(workspace, w)


@nb.njit(**KERNEL, inline="always")
def _arena_positions(workspace, w, n_floats):
    """The arena's pos (array_views): the first 3 int64 slots after its floats."""
    return workspace[w + n_floats:w + n_floats + 3].view(np.int64)


@nb.njit(**KERNEL, inline="always")
def _to_aligned(buf, o):
    """The entries (8 bytes each) from buf[o] to the next 64-byte boundary."""
    return (-(buf.ctypes.data // 8 + o)) % ARENA_ALIGN


#: StepSettings' fields: 12 floats, then 4 ints (form, scheme, max_iterations, criterion),
#: then 3 flags (warm_start, bilateral_direct, hysteresis)
N_SETTINGS = len(StepSettings._fields)


@nb.njit(**KERNEL, inline="always")
def _step_settings(a):
    """The StepSettings of its fields packed as floats (TreeStepModel.pack): exact, the
    ints and flags being small whole numbers. (A tuple of 19 fields costs ≈0.3 µs per call to
    unbox; one array of them nothing more.)"""
    return StepSettings(a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7], a[8], a[9], a[10],
                        a[11], int(a[12]), int(a[13]), int(a[14]), int(a[15]), a[16] != 0.0,
                        a[17] != 0.0, a[18] != 0.0)


@nb.njit(**KERNEL, inline="always")
def _take(buf, o, n):
    return buf[o:o + n], o + n


@nb.njit(**KERNEL, inline="always")
def unpack_tree_model(floats, ints, support, workspace, nv):
    """The views of TreeStepModel's buffers: (StepSettings, CompliantLaw's fields, model
    (midpoint_model's order), normal, tangent1, tangent2, ground_offset, eps, effort_limit,
    velocity_limit, joint_v, dof_parent, gap, position, Wt_all, L, u_free, u_corr), all
    borrowed (array_views.borrowed: the caller holds the buffers for the whole call)."""
    floats, ints, support, workspace = (borrowed(floats), borrowed(ints), borrowed(support),
                                        borrowed(workspace))
    nj, nc, na = ints[0], ints[1], ints[2]
    settings, o = _take(floats, 0, N_SETTINGS)
    law, o = _take(floats, o, 6)
    axis, o = _take(floats, o, 3 * nj)
    pl_R, o = _take(floats, o, 9 * nj)
    pl_p, o = _take(floats, o, 3 * nj)
    oR, o = _take(floats, o, 9 * nj)
    op, o = _take(floats, o, 3 * nj)
    mass, o = _take(floats, o, nj)
    lever, o = _take(floats, o, 3 * nj)
    inertia, o = _take(floats, o, 9 * nj)
    gravity, o = _take(floats, o, 3)
    c_local, o = _take(floats, o, 3 * nc)
    c_radius, o = _take(floats, o, nc)
    normal, o = _take(floats, o, 3)
    tangent1, o = _take(floats, o, 3)
    tangent2, o = _take(floats, o, 3)
    offset, o = _take(floats, o, 1)
    eps, o = _take(floats, o, 2 * nc)
    effort_limit, o = _take(floats, o, na)
    velocity_limit, o = _take(floats, o, na)
    k = 4
    parent, k = _take(ints, k, nj)
    jtype, k = _take(ints, k, nj)
    idx_q, k = _take(ints, k, nj)
    idx_v, k = _take(ints, k, nj)
    c_joint, k = _take(ints, k, nc)
    joint_v, k = _take(ints, k, na)
    dof_parent, k = _take(ints, k, nv)
    w = 0
    gap, w = _take(workspace, w, nc)
    position, w = _take(workspace, w, 3 * nc)
    Wt_all, w = _take(workspace, w, 3 * nc * nv)
    L, w = _take(workspace, w, nv * nv)
    u_free, w = _take(workspace, w, nv)
    u_corr, w = _take(workspace, w, nv)
    model = (parent, jtype, view2(axis, (nj, 3)), view3(pl_R, (nj, 3, 3)),
             view2(pl_p, (nj, 3)), idx_q, idx_v, support, view3(oR, (nj, 3, 3)),
             view2(op, (nj, 3)), mass, view2(lever, (nj, 3)), view3(inertia, (nj, 3, 3)),
             gravity, c_joint, view2(c_local, (nc, 3)), c_radius)
    return (_step_settings(settings), (law[0], law[1], law[2], law[3], law[4], law[5]),
            model, normal, tangent1, tangent2, offset[0], view2(eps, (nc, 2)), effort_limit,
            velocity_limit, joint_v, dof_parent, gap, view2(position, (nc, 3)),
            view3(Wt_all, (nc, 3, nv)), view2(L, (nv, nv)), u_free, u_corr)


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


@nb.njit(**KERNEL, inline="always")
def _applied_torque(saturate, tau, u, joint_v, effort_limit, velocity_limit, applied):
    """applied = the torques the motors apply for tau (actuator.saturate_torque at the
    joint rates of u; with saturate False, tau as given: the caller saturated it). False if
    tau has a non-finite entry."""
    if not saturate:
        for k in range(tau.shape[0]):
            applied[k] = tau[k]
        return True
    qd = np.empty(joint_v.shape[0])
    for k in range(joint_v.shape[0]):
        qd[k] = u[joint_v[k]]
    return saturate_torque(tau, effort_limit, qd, velocity_limit, applied)


@nb.njit(**KERNEL, inline="always")
def _report_contacts(gap, position, report, nc):
    """Copies g_N and the contact points at q^M into the report buffer (report_views)."""
    for i in range(nc):
        report[3 * nc + i] = gap[i]
        for k in range(3):
            report[4 * nc + 3 * i + k] = position[i, k]


@nb.njit(**KERNEL, inline="always")
def _midpoint_with_forces(q, u, half_dt, tau, joint_v, f_ext, normal, tangent1, tangent2,
                          ground_offset, jacobian_gap, gap, position, Wt_all, model, arena):
    """q^M, M and h at (q^M, u^S) of a tree without cut joints (midpoint_dynamics), then
    h += Sᵀτ (τ in the public order, joint_v its velocity indices) + f_ext (when given):
    the same arithmetic, in the same order, as ForestCoordinates.midpoint followed by
    add_joint_torques and h += f_ext. Returns (the owner of their memory, q^M, M, h), the
    three borrowed (array_views.borrowed): the caller holds the owner (keep_alive) while it
    uses them; their memory from the step's arena."""
    nv = u.shape[0]
    nq = q.shape[0]
    owner = arena_floats(arena, nq + nv * nv + nv)     # (one buffer for q^M, M and h)
    out = borrowed(owner)
    qM = out[:nq]
    M = view2(out[nq:nq + nv * nv], (nv, nv))
    h = out[nq + nv * nv:]
    midpoint_dynamics(q, u, half_dt, *model, normal, tangent1, tangent2, ground_offset,
                      jacobian_gap, qM, M, h, gap, position, Wt_all)
    for k in range(tau.shape[0]):
        h[joint_v[k]] += tau[k]
    for k in range(f_ext.shape[0]):
        h[k] += f_ext[k]
    return owner, qM, M, h


@nb.njit(**KERNEL, inline="always")
def _borrowed_step_arrays(q, u, tau, f_ext, report, is_active, qE, uE):
    """A one-kernel step's per-step arguments, borrowed (array_views.borrowed: the caller
    holds them for the call)."""
    return (borrowed(q), borrowed(u), borrowed(tau), borrowed(f_ext), borrowed(report),
            borrowed(is_active), borrowed(qE), borrowed(uE))


@nb.njit(**KERNEL, inline="always")
def _borrowed_problem(p):
    """The ContactProblem p with every array borrowed (array_views.borrowed): the kernel
    that made p holds it (keep_alive(p)) until its last use of the result."""
    f = p.pat
    return ContactProblem(p.ok, borrowed(p.active), borrowed(p.Wt), borrowed(p.MinvW),
                          borrowed(p.b), borrowed(p.G), borrowed(p.Gdiag), borrowed(p.LB),
                          prox.Patterns(borrowed(f.wp_ptr), borrowed(f.wp_idx),
                                        borrowed(f.mp_ptr), borrowed(f.mp_idx),
                                        borrowed(f.gp_ptr), borrowed(f.gp_idx),
                                        borrowed(f.lb_first)), p.opened)


@nb.njit(**KERNEL, inline="always")
def _complete_step(s, p, h, u, M, dof_parent, L, gap, Wt_all, last_impulse, last_active,
                   last_bilateral, bilateral_E, report, is_active, u_free, uE, u_corr, qM,
                   half_dt, jtype, idx_q, idx_v, qE, arena):
    """The rest of a one-kernel hard-contact step once its ContactProblem p is set up:
    complete_problem (Λ into the report buffer, Λ_B into bilateral_E, which comes in with
    the last step's Λ_B for the warm start; both nb long) and Eqn. (8) (end_of_step); only
    when the step ends finite is the warm-start memory (Λ, active flags, Λ_B) updated,
    else it stays as it was. Returns (outcome (TREE_STEP_*), iterations, status, residual,
    retried, projection iterations, projection status)."""
    nc = gap.shape[0]
    impulse = view2(report[:3 * nc], (nc, 3))
    for a in range(last_bilateral.shape[0]):
        bilateral_E[a] = last_bilateral[a]
    it, status, resid, retried, pit, pstatus = complete_problem_inlined(
        s, p, h, u, M, dof_parent, L, gap, Wt_all, last_impulse, last_active, bilateral_E,
        impulse, is_active, u_free, uE, u_corr, False, None, arena)
    outcome = TREE_STEP_OK
    if status == prox.STATUS_NONFINITE:
        outcome = TREE_STEP_NONFINITE_IMPULSE
    elif not end_of_step(qM, uE, u_corr, pstatus >= 0, half_dt, jtype, idx_q, idx_v, qE):
        outcome = TREE_STEP_NONFINITE_STATE
    else:
        remember_contacts(is_active, impulse, last_active, last_impulse)
        for a in range(last_bilateral.shape[0]):
            last_bilateral[a] = bilateral_E[a]
    return outcome, it, status, resid, retried, pit, pstatus


@nb.njit(**KERNEL)
def tree_step_hard(saturate, q, u, tau, f_ext, last_impulse, last_active, last_bilateral,
                   report, is_active, qE, uE, floats, ints, support, workspace):
    """One whole step with hard contacts of a coordinate set without bilateral constraints
    and with a configuration-dependent M (the minimal coordinates), in one call from Python:
    the applied torques (_applied_torque: saturated unless `saturate` is False), Eqn. (6)
    and M, h, W at the midpoint (_midpoint_with_forces), the contact problem
    (contact_problem, complete_problem) and Eqn. (8) (end_of_step). The same arithmetic as
    the phase-by-phase path of MoreauStepper.step, so the same result bit for bit; it saves
    the calls between the phases and the Python around them. (floats, ints, support,
    workspace): a TreeStepModel (with the StepSettings); f_ext: the
    generalized external force or an empty array. Writes q^E, u^E, the report buffer (Λ,
    g_N, contact points, applied torques: report_views), the active flags and the
    workspace; the warm-start memory is updated as by complete_problem, but only when the
    step succeeds (outcome TREE_STEP_OK; no bilateral memory here): a failed step leaves
    the state as it was, and a non-finite τ (TREE_STEP_NONFINITE_TORQUE) is found before
    anything is done. Returns (outcome (TREE_STEP_*), |I|, opened, iterations, status,
    residual, retried, projection iterations, projection status)."""
    q, u, tau, f_ext, report, is_active, qE, uE = _borrowed_step_arrays(
        q, u, tau, f_ext, report, is_active, qE, uE)
    last_impulse, last_active = borrowed(last_impulse), borrowed(last_active)
    last_bilateral = borrowed(last_bilateral)
    nv = u.shape[0]
    (s, _, model, normal, tangent1, tangent2, offset, eps, effort_limit, velocity_limit, joint_v,
     dof_parent, gap, position, Wt_all, L, u_free, u_corr) = unpack_tree_model(
        floats, ints, support, workspace, nv)
    nc = gap.shape[0]
    applied = report[7 * nc:7 * nc + joint_v.shape[0]]
    if not _applied_torque(saturate, tau, u, joint_v, effort_limit, velocity_limit, applied):
        return TREE_STEP_NONFINITE_TORQUE, 0, 0, 0, prox.STATUS_CONVERGED, 0.0, False, 0, -1
    half_dt = 0.5 * s.dt
    arena = step_arena(ints, workspace, nc, nv)
    # (the step's own arrays are borrowed too, their owners held by keep_alive to the end)
    qMh = _midpoint_with_forces(q, u, half_dt, applied, joint_v, f_ext, normal, tangent1,
                                tangent2, offset, s.jacobian_gap, gap, position, Wt_all, model,
                                arena)
    _, qM, M, h = qMh
    no_rows = u_corr[:0]        # (no bilateral rows: empty views, not allocations)
    owned = contact_problem_inlined(s, M, u, gap, Wt_all, view2(no_rows, (0, nv)), no_rows,
                                    eps, dof_parent, True, L, last_impulse, last_active, None,
                                    arena)
    p = _borrowed_problem(owned)
    if not p.ok:
        keep_alive(qMh)
        keep_alive(owned)
        return TREE_STEP_NOT_PD, 0, 0, 0, prox.STATUS_CONVERGED, 0.0, False, 0, -1
    outcome, it, status, resid, retried, pit, pstatus = _complete_step(
        s, p, h, u, M, dof_parent, L, gap, Wt_all, last_impulse, last_active, last_bilateral,
        last_bilateral, report, is_active, u_free, uE, u_corr, qM, half_dt, model[1],
        model[5], model[6], qE, arena)     # (no bilateral rows: Λ_B is empty)
    _report_contacts(gap, position, report, nc)
    keep_alive(qMh)
    keep_alive(owned)
    return (outcome, p.active.shape[0], p.opened, it, status, resid, retried, pit, pstatus)


@nb.njit(**KERNEL, inline="always")
def _kept_contact_state(closed, slip, anchor, lam, arena):
    """A copy of the compliant contact state (the closed and slip flags as ints, the anchors
    and forces) in the step's arena, for _restore_contact_state after a failed step."""
    nc = closed.shape[0]
    flags = arena_ints(arena, 2 * nc)
    values = arena_floats(arena, 6 * nc)
    for i in range(nc):
        flags[i] = closed[i]
        flags[nc + i] = slip[i]
        for k in range(3):
            values[3 * i + k] = anchor[i, k]
            values[3 * nc + 3 * i + k] = lam[i, k]
    return flags, values


@nb.njit(**KERNEL, inline="always")
def _restore_contact_state(kept, closed, slip, anchor, lam):
    """The compliant contact state back from _kept_contact_state's copy."""
    flags, values = kept
    nc = closed.shape[0]
    for i in range(nc):
        closed[i] = flags[i] != 0
        slip[i] = flags[nc + i] != 0
        for k in range(3):
            anchor[i, k] = values[3 * i + k]
            lam[i, k] = values[3 * nc + 3 * i + k]


@nb.njit(**KERNEL)
def tree_step_compliant(saturate, q, u, tau, f_ext, closed, slip, anchor, lam, report,
                        is_active, qE, uE, floats, ints, support, workspace):
    """tree_step_hard's counterpart for compliant contacts (Alg. 1, the CompliantLaw and Δt
    packed in the TreeStepModel): the applied torques, the midpoint, solve_compliant (u^E = u_free) and
    Eqn. (8), the same arithmetic as the phase-by-phase path; writes the report buffer (Λ =
    the compliant force Δt) and the closed flags (g_N(q^M) ≤ 0) into is_active. A failed
    step leaves the contact state as it was. Returns tree_step_hard's tuple (no prox
    figures)."""
    q, u, tau, f_ext, report, is_active, qE, uE = _borrowed_step_arrays(
        q, u, tau, f_ext, report, is_active, qE, uE)
    closed, slip, anchor, lam = borrowed(closed), borrowed(slip), borrowed(anchor), borrowed(lam)
    nv = u.shape[0]
    (s, law, model, normal, tangent1, tangent2, offset, eps, effort_limit, velocity_limit,
     joint_v, dof_parent, gap, position, Wt_all, L, u_free, u_corr) = unpack_tree_model(
        floats, ints, support, workspace, nv)
    dt, jacobian_gap = s.dt, s.jacobian_gap
    nc = gap.shape[0]
    applied = report[7 * nc:7 * nc + joint_v.shape[0]]
    if not _applied_torque(saturate, tau, u, joint_v, effort_limit, velocity_limit, applied):
        return TREE_STEP_NONFINITE_TORQUE, 0, 0, 0, prox.STATUS_CONVERGED, 0.0, False, 0, -1
    half_dt = 0.5 * dt
    arena = step_arena(ints, workspace, nc, nv)
    qMh = _midpoint_with_forces(q, u, half_dt, applied, joint_v, f_ext, normal, tangent1,
                                tangent2, offset, jacobian_gap, gap, position, Wt_all, model,
                                arena)
    _, qM, M, h = qMh   # (held to the end)
    kept = _kept_contact_state(closed, slip, anchor, lam, arena)
    if not solve_compliant(law, M, h, u, dt, gap, position, Wt_all, closed, slip, anchor,
                           tangent1, tangent2, lam, dof_parent, True, L, u_free, None):
        outcome = TREE_STEP_NOT_PD
    else:
        for k in range(nv):
            uE[k] = u_free[k]
        outcome = TREE_STEP_OK
        if not end_of_step(qM, uE, u_corr, False, half_dt, model[1], model[5], model[6], qE):
            outcome = TREE_STEP_NONFINITE_STATE
    if outcome != TREE_STEP_OK:     # the contact state back to what it was
        _restore_contact_state(kept, closed, slip, anchor, lam)
    n_active = 0
    for i in range(nc):
        for k in range(3):
            report[3 * i + k] = lam[i, k] * dt
        is_active[i] = gap[i] <= 0.0
        n_active += is_active[i]
    _report_contacts(gap, position, report, nc)
    keep_alive(qMh)
    return outcome, n_active, 0, 0, prox.STATUS_CONVERGED, 0.0, False, 0, -1


# --------------------------------------------------------------------------------------------
# the cut forest: bilateral constraints of the cut joints, M of the trees or constant
# --------------------------------------------------------------------------------------------
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


@nb.njit(**KERNEL, inline="always")
def unpack_cut_model(floats, ints, workspace, na, nv):
    """The views of CutModel's buffers: (β/Δt, cut_P, cut_C, p_P, p_C, a_P, b1_P, b2_P, a_C,
    b1_C, joint_cut, constant, M, root_q, root_v, body masses, inertias, gravity, W_B^T,
    g_B, b_B, φ, φ̇, hinge axes, the step's Λ_B); M and the bodies' arrays empty unless M is
    constant."""
    floats, ints, workspace = borrowed(floats), borrowed(ints), borrowed(workspace)
    ncut, constant, nr = ints[0], ints[1] != 0, ints[2]
    beta_over_dt = floats[0]
    o = 1
    p_P, o = _take(floats, o, 3 * ncut)
    p_C, o = _take(floats, o, 3 * ncut)
    a_P, o = _take(floats, o, 3 * ncut)
    b1_P, o = _take(floats, o, 3 * ncut)
    b2_P, o = _take(floats, o, 3 * ncut)
    a_C, o = _take(floats, o, 3 * ncut)
    b1_C, o = _take(floats, o, 3 * ncut)
    nM = nv * nv if constant else 0
    M, o = _take(floats, o, nM)
    body_mass, o = _take(floats, o, nr)
    body_inertia, o = _take(floats, o, 9 * nr)
    body_gravity, o = _take(floats, o, 3 if constant else 0)
    k = 3
    cut_P, k = _take(ints, k, ncut)
    cut_C, k = _take(ints, k, ncut)
    joint_cut, k = _take(ints, k, na)
    root_q, k = _take(ints, k, nr)
    root_v, k = _take(ints, k, nr)
    nB = 5 * ncut
    w = 0
    WtB, w = _take(workspace, w, nB * nv)
    gB, w = _take(workspace, w, nB)
    bB, w = _take(workspace, w, nB)
    angle, w = _take(workspace, w, ncut)
    rate, w = _take(workspace, w, ncut)
    axis_world, w = _take(workspace, w, 3 * ncut)
    bilateral_E, w = _take(workspace, w, nB)
    return (beta_over_dt, cut_P, cut_C, view2(p_P, (ncut, 3)), view2(p_C, (ncut, 3)),
            view2(a_P, (ncut, 3)), view2(b1_P, (ncut, 3)), view2(b2_P, (ncut, 3)),
            view2(a_C, (ncut, 3)), view2(b1_C, (ncut, 3)), joint_cut, constant,
            view2(M, (nv if constant else 0, nv if constant else 0)), root_q, root_v,
            body_mass, view3(body_inertia, (nr, 3, 3)), body_gravity,
            view2(WtB, (nB, nv)), gB, bB, angle, rate, view2(axis_world, (ncut, 3)),
            bilateral_E)


@nb.njit(**KERNEL, inline="always")
def _forest_midpoint(q, u, half_dt, constant, M_const, root_q, root_v, body_mass,
                     body_inertia, body_gravity, normal, tangent1, tangent2, ground_offset,
                     jacobian_gap, gap, position, Wt_all, model, arena):
    """q^M, M and h (without τ) at (q^M, u^S) and the contact kinematics at q^M, as
    ForestCoordinates.midpoint: one midpoint_dynamics for M of the trees; for a constant M
    (free bodies) q^M, rigid_body_forces and contact_kinematics. Returns
    _midpoint_with_forces' tuple (owner, q^M, M, h)."""
    (parent, jtype, axis, pl_R, pl_p, idx_q, idx_v, support, oR, op, _, _, _, _, c_joint,
     c_local, c_radius) = model
    nv = u.shape[0]
    nq = q.shape[0]
    nM = 0 if constant else nv * nv
    owner = arena_floats(arena, nq + nv + nM)       # (one buffer for q^M, h and M)
    out = borrowed(owner)
    qM = out[:nq]
    h = out[nq:nq + nv]
    if constant:
        integrate_forest(q, u, half_dt, jtype, idx_q, idx_v, qM)
        rigid_body_forces(qM, u, root_q, root_v, body_mass, body_inertia, body_gravity, h)
        contact_kinematics(qM, parent, jtype, axis, pl_R, pl_p, idx_q, idx_v, support, oR, op,
                           c_joint, c_local, c_radius, normal, tangent1, tangent2,
                           ground_offset, jacobian_gap, gap, position, Wt_all)
        return owner, qM, M_const, h
    M = view2(out[nq + nv:], (nv, nv))
    midpoint_dynamics(q, u, half_dt, *model, normal, tangent1, tangent2, ground_offset,
                      jacobian_gap, qM, M, h, gap, position, Wt_all)
    return owner, qM, M, h


@nb.njit(**KERNEL, inline="always")
def _add_forest_torques(applied, joint_v, joint_cut, axis_world, cut_P, cut_C, f_ext, model,
                        h, arena):
    """h += the generalized force of the applied joint torques (Sᵀτ inside the trees, the
    cut joints' equal and opposite body torques about their hinge axes: cut_joint_torques,
    with the kinematics of the last cut_joints call) + f_ext: the arithmetic, in its order,
    of ForestCoordinates.add_joint_torques followed by h += f_ext (scratch from the step's
    arena)."""
    tau_cut = arena_floats(arena, cut_P.shape[0])
    tau_cut[:] = 0.0
    for k in range(applied.shape[0]):
        if joint_cut[k] < 0:
            h[joint_v[k]] += applied[k]
        else:
            tau_cut[joint_cut[k]] = applied[k]
    cut_joint_torques(tau_cut, cut_P, cut_C, axis_world, model[1], model[2], model[6],
                      model[7], model[8], h, arena)
    for k in range(f_ext.shape[0]):
        h[k] += f_ext[k]


@nb.njit(**KERNEL)
def forest_step_hard(q, u, applied_tau, f_ext, factor, last_impulse, last_active,
                     last_bilateral, report, is_active, qE, uE, angle_E, rate_E, floats, ints,
                     support, workspace, cut_floats, cut_ints, cut_workspace):
    """tree_step_hard's counterpart for a cut forest (the extended and maximal
    coordinates), hard contacts: Eqn. (6) with M, h, W at the midpoint (_forest_midpoint),
    the bilateral constraints of the cut joints at q^M (cut_joints: W_B^T, g_B, b_B =
    (β/Δt) g_B), h += the joint torques and f_ext (_add_forest_torques), the contact and
    bilateral problem (contact_problem, complete_problem; factor: whether to factor M,
    False to reuse a constant M's factor in L) and Eqn. (8): the arithmetic, in its order,
    of MoreauStepper.step's phase-by-phase path, so the same result bit for bit. (floats,
    ints, support, workspace): a TreeStepModel; (cut_floats, cut_ints, cut_workspace): a
    CutModel. applied_tau: the torques the motors apply (saturated by the caller: a cut
    joint's rate needs the cut-joint kinematics of the state). Writes what tree_step_hard
    writes; the warm-start memory, Λ_B's included, is updated only when the step succeeds;
    a successful step also writes the cut joints' φ and φ̇ at (q^E, u^E) into angle_E and
    rate_E (cut_joint_motion: what a controller asks for next, at the cost of one forward
    kinematics and the cut joints' angular Jacobians here rather than a call from Python
    later). Returns tree_step_hard's tuple."""
    q, u, applied_tau, f_ext, report, is_active, qE, uE = _borrowed_step_arrays(
        q, u, applied_tau, f_ext, report, is_active, qE, uE)
    last_impulse, last_active = borrowed(last_impulse), borrowed(last_active)
    last_bilateral = borrowed(last_bilateral)
    angle_E, rate_E = borrowed(angle_E), borrowed(rate_E)
    nv = u.shape[0]
    (s, _, model, normal, tangent1, tangent2, offset, eps, _, _, joint_v, dof_parent, gap,
     position, Wt_all, L, u_free, u_corr) = unpack_tree_model(floats, ints, support,
                                                               workspace, nv)
    na = joint_v.shape[0]
    (beta_over_dt, cut_P, cut_C, p_P, p_C, a_P, b1_P, b2_P, a_C, b1_C, joint_cut, constant,
     M_const, root_q, root_v, body_mass, body_inertia, body_gravity, WtB, gB, bB, angle,
     rate, axis_world, bilateral_E) = unpack_cut_model(cut_floats, cut_ints, cut_workspace,
                                                       na, nv)
    nc = gap.shape[0]
    applied = report[7 * nc:7 * nc + na]
    for k in range(na):
        if not np.isfinite(applied_tau[k]):
            return TREE_STEP_NONFINITE_TORQUE, 0, 0, 0, prox.STATUS_CONVERGED, 0.0, False, 0, -1
        applied[k] = applied_tau[k]
    half_dt = 0.5 * s.dt
    arena = step_arena(ints, workspace, nc, nv)
    qMh = _forest_midpoint(q, u, half_dt, constant, M_const, root_q, root_v, body_mass,
                           body_inertia, body_gravity, normal, tangent1, tangent2, offset,
                           s.jacobian_gap, gap, position, Wt_all, model, arena)
    _, qM, M, h = qMh   # (held to the end)
    (parent, jtype, axis, pl_R, pl_p, idx_q, idx_v, sup, oR, op) = model[:10]
    u_zero = arena_floats(arena, nv)    # (the rates at q^M are not needed: u = 0)
    u_zero[:] = 0.0
    cut_joints(qM, u_zero, parent, jtype, axis, pl_R, pl_p, idx_q, idx_v, sup, oR, op,
               cut_P, cut_C, p_P, p_C, a_P, b1_P, b2_P, a_C, b1_C, WtB, gB, angle, rate,
               axis_world, True, arena)
    for k in range(gB.shape[0]):
        bB[k] = gB[k] * beta_over_dt
    _add_forest_torques(applied, joint_v, joint_cut, axis_world, cut_P, cut_C, f_ext, model,
                        h, arena)
    owned = contact_problem_inlined(s, M, u, gap, Wt_all, WtB, bB, eps, dof_parent, factor, L,
                                    last_impulse, last_active, None, arena)
    p = _borrowed_problem(owned)
    if not p.ok:
        keep_alive(qMh)
        keep_alive(owned)
        return TREE_STEP_NOT_PD, 0, 0, 0, prox.STATUS_CONVERGED, 0.0, False, 0, -1
    outcome, it, status, resid, retried, pit, pstatus = _complete_step(
        s, p, h, u, M, dof_parent, L, gap, Wt_all, last_impulse, last_active, last_bilateral,
        bilateral_E, report, is_active, u_free, uE, u_corr, qM, half_dt, jtype, idx_q, idx_v,
        qE, arena)
    if outcome == TREE_STEP_OK:
        cut_joint_motion(qE, uE, parent, jtype, axis, pl_R, pl_p, idx_q, idx_v, sup, oR, op,
                         cut_P, cut_C, a_P, b1_P, b2_P, b1_C, angle_E, rate_E, arena)
    _report_contacts(gap, position, report, nc)
    keep_alive(qMh)
    keep_alive(owned)
    return (outcome, p.active.shape[0], p.opened, it, status, resid, retried, pit, pstatus)
