"""The step's kernels and their packed model: every physics step is one call of one of them
(`MoreauStepper.step`), C in ``csrc/tree_step.c``:

- ``tree_step_hard(options, torque_mode, state, tau, f_ext, out, model)``: a tree without
  bilateral constraints whose M depends on q (the minimal coordinates), hard contacts. The
  applied torques (`torque_mode`: as given, saturated by actuator.saturate_torque, the
  impedance law at the state, or replayed; the implicit joint dampers inside), Eqn. (6):
  q^M and M, h, W at the midpoint, the contact problem and its prox solution, Eqn. (8):
  u^E and q^E, the post-step projection. state = (q, u, Λ memory, active memory, Λ_B
  memory, α memory (SimState.prox_memory)): the memory is updated only when the step
  succeeds (TREE_STEP_OK);
  out = (report, is_active, q^E, u^E): the report buffer (report_views: Λ, g_N and contact
  points at q^M, the torques) and the active flags.
- ``tree_step_compliant(options, torque_mode, state, tau, f_ext, out, model)``: the same
  with the compliant law of Alg. 1 (state = (q, u, closed, slip, anchor, λ)); the report's
  Λ is the compliant force times Δt, is_active the closed flags (g_N(q^M) ≤ 0).
- ``forest_step(options, state, tau, f_ext, out, model, cut)``: a cut forest (the extended
  and maximal coordinates): the bilateral constraints of the cut joints at q^M (W_B, g_B,
  b_B = (β/Δt) g_B) with the contacts, hard or compliant (STEP_COMPLIANT; state = (q, u,
  the hard contacts' memory as above, closed, slip, anchor, λ)); tau the applied
  torques (a cut joint's rate needs the cut-joint kinematics of the state:
  MoreauStepper._forest_torques); out also receives the cut joints' φ and φ̇ at (q^E, u^E).

`options`: STEP_PREPARE (only the midpoint, into the workspace) then STEP_PREPARED (the rest
of a step so prepared), STEP_PROFILE (the Fig. 7 phases' times added to the workspace's
timings), STEP_KEEP_FACTOR (a constant M's factor kept). Each returns a `TreeStepResult`
(outcome TREE_STEP_*, n_active |I|, opened, iterations, status, residual, retried, the
projection's iterations and status). A failing step leaves the state as it was; the kernels
release the GIL. The model (`TreeStepModel`, and `CutModel` for the cut joints) travels
packed in a few buffers laid out as :mod:`starleth_sim.physics.kernels.layouts` declares;
the kernels unpack them by the C code the build generates from the same declaration.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .kernels import (  # noqa: F401
    TREE_STEP_NONFINITE_IMPULSE,
    TREE_STEP_NONFINITE_STATE,
    TREE_STEP_NONFINITE_TORQUE,
    TREE_STEP_NOT_PD,
    TREE_STEP_OK,
    TreeStepResult,
    forest_step,
    tree_step_compliant,
    tree_step_hard,
)
from .kernels.layouts import (
    CUT_MODEL,
    STEP_REPORT,
    STEP_SETTINGS,
    TREE_STEP_MODEL,
    describe,
    evaluate,
    length,
    offsets,
)

_DTYPES = {"float64": np.float64, "int64": np.int64, "bool": np.bool_}


def pack_buffer(layout, buffer, values, sizes):
    """One buffer of a layout (kernels.layouts), its fields in the declared order: values maps
    each field's name to its array (a record field: the record's fields; header fields come
    from `sizes`). A ValueError names a field whose size is not the declared one."""
    dtype = _DTYPES[layout.buffer(buffer).dtype]
    parts = []
    for f, _, n in offsets(layout, buffer, sizes):
        value = sizes[f.name] if f.kind in ("header", "flag") else values[f.name]
        a = np.ravel(np.asarray(value, dtype=np.float64 if f.kind == "record" else None))
        if a.shape[0] != n:
            raise ValueError(f"{layout.name}.{buffer}: {f.name} has {a.shape[0]} entries, "
                             f"the layout {n}")
        parts.append(a.astype(dtype))
    return np.concatenate(parts) if parts else np.zeros(0, dtype=dtype)


def buffer_views(layout, buffer, array, sizes):
    """{field: its view of `array`} for one buffer of a layout (shaped as declared)."""
    out = {}
    for f, o, n in offsets(layout, buffer, sizes):
        v = array[o:o + n]
        out[f.name] = v.reshape([evaluate(e, sizes) for e in f.shape]) if f.shape else v
    return out


class TreeStepModel(NamedTuple):
    """The model, ground and workspace arrays of the one-kernel step (tree_step_hard /
    tree_step_compliant) packed into four buffers, so that a call from Python passes four
    arrays instead of some thirty. The packing is pure layout: the kernels compute exactly
    what the phase-by-phase path computes, and check the buffers' lengths against the sizes
    in their header on every call. The layout (kernels.layouts.TREE_STEP_MODEL):

    """

    floats: np.ndarray
    ints: np.ndarray
    support: np.ndarray
    workspace: np.ndarray

    @staticmethod
    def pack(settings, law, model, ground, eps, joint_v, dof_parent, nv, effort_limit,
             velocity_limit, joint_q, nq, drives=None):
        """Packs the StepSettings and CompliantLaw, midpoint_model()'s arrays, the
        GroundPlane, ε, the torque limits (see actuator.saturate_torque), the actuated
        joints' entries of u and q (joint_v, joint_q: the impedance law reads q and u
        there), nq and the drive models (DriveParameters.packed, or None: off); returns the
        record and the workspace's views (gap, position, Wt_all, L, u_free, u_corr, frames,
        timings, lag_state), which the stepper keeps as its own arrays."""
        ((parent, jtype, axis, pl_R, pl_p, idx_q, idx_v, support), (oR, op),
         (mass, lever, inertia, gravity), (c_joint, c_local, c_radius)) = model
        sizes = {"nj": parent.shape[0], "nc": c_joint.shape[0], "na": joint_v.shape[0],
                 "nv": nv, "nt": ground.terrain.shape[0], "nq": nq,
                 "drives": int(drives is not None)}
        values = dict(
            settings=STEP_SETTINGS.flatten(settings), law=[float(v) for v in law], axis=axis,
            pl_R=pl_R, pl_p=pl_p, oR=oR, op=op, mass=mass, lever=lever, inertia=inertia,
            gravity=gravity, c_local=c_local, c_radius=c_radius, ground_n=ground.n,
            ground_t1=ground.t1, ground_t2=ground.t2, ground_offset=[ground.offset],
            terrain=ground.terrain, eps=eps,
            effort_limit=effort_limit, velocity_limit=velocity_limit, parent=parent,
            jtype=jtype, idx_q=idx_q, idx_v=idx_v, c_joint=c_joint, joint_v=joint_v,
            joint_q=joint_q, dof_parent=dof_parent, support=support,
            **(drives or dict.fromkeys(("armature", "viscous", "friction_bound", "lag"), [])))
        L = TREE_STEP_MODEL
        workspace = np.zeros(length(L, "workspace", sizes))
        views = buffer_views(L, "workspace", workspace, sizes)
        return (TreeStepModel(pack_buffer(L, "floats", values, sizes),
                              pack_buffer(L, "ints", values, sizes),
                              np.ascontiguousarray(pack_buffer(L, "support", values, sizes)),
                              workspace),
                tuple(views[name] for name in ("gap", "position", "Wt_all", "L", "u_free",
                                               "u_corr", "frames", "timings",
                                               "lag_state")))


TreeStepModel.__doc__ = TreeStepModel.__doc__.rstrip(" ") + describe(TREE_STEP_MODEL)


def report_size(nc, na):
    """The length of a one-kernel step's report buffer (see report_views)."""
    return length(STEP_REPORT, "report", {"nc": nc, "na": na})


def report_views(report, nc, na):
    """The views of a one-kernel step's report buffer (float64, report_size(nc, na)):
    (Λ (nc x 3, contact frame), g_N at q^M (nc), contact points at q^M (nc x 3), the
    applied torques (na)), the fields of kernels.layouts.STEP_REPORT in order: what the step
    reports, written by the kernel in one buffer so that a caller allocates nothing per
    step."""
    return tuple(buffer_views(STEP_REPORT, "report", report, {"nc": nc, "na": na}).values())


class CutModel(NamedTuple):
    """What forest_step_hard needs beyond the TreeStepModel: the cut joints, the actuators'
    place (tree joint or cut joint), a constant M and its free bodies, and the workspace of
    the bilateral constraints, packed like TreeStepModel (na and nv: the TreeStepModel's).
    The layout (kernels.layouts.CUT_MODEL):

    """

    floats: np.ndarray
    ints: np.ndarray
    workspace: np.ndarray

    @staticmethod
    def pack(coords, beta_over_dt):
        """The CutModel of ForestCoordinates `coords` (β/Δt: the factor of b_B)."""
        c = coords
        constant = bool(c.constant_mass_matrix)
        sizes = {"ncut": c.n_cut, "constant": int(constant),
                 "nr": c.roots.shape[0] if constant else 0, "na": c.joint_v.shape[0],
                 "nv": c.nv}
        values = dict(beta_over_dt=[float(beta_over_dt)], p_P=c.p_P, p_C=c.p_C, a_P=c.a_P,
                      b1_P=c.b1_P, b2_P=c.b2_P, a_C=c.a_C, b1_C=c.b1_C, cut_P=c.cut_P,
                      cut_C=c.cut_C, joint_cut=c.joint_cut)
        if constant:
            values.update(M=c.M_const, body_mass=c.body_mass, body_inertia=c.body_inertia,
                          body_gravity=c.body_gravity, root_q=c.root_q, root_v=c.root_v)
        else:
            values.update({k: [] for k in ("M", "body_mass", "body_inertia", "body_gravity",
                                           "root_q", "root_v")})
        L = CUT_MODEL
        return CutModel(pack_buffer(L, "floats", values, sizes),
                        pack_buffer(L, "ints", values, sizes),
                        np.zeros(length(L, "workspace", sizes)))


CutModel.__doc__ = CutModel.__doc__.rstrip(" ") + describe(CUT_MODEL)
