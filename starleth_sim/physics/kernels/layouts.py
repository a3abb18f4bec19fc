"""The packed layouts the one-kernel steps read and the records the kernels return, declared
once: :mod:`~starleth_sim.physics.kernels.codegen` generates the C side from these
declarations (`c_header`: the structs, the unpacking of every buffer and the named results,
into the header ``kernel_layouts.h`` that `kernels.build` writes for the build), and
:mod:`starleth_sim.physics.tree_step` packs the buffers by them.

A layout is a list of buffers (float64, int64 or bool arrays), each an ordered list of fields.
A field's size is an expression over the layout's sizes: those its header holds (the first
entries of its ``ints`` buffer) and those the caller gives (`context`); the expressions use
names, whole numbers, ``+``, ``*`` and parentheses only, so that C and Python read them alike
(``constant * nv * nv``: nv x nv when the flag ``constant`` is 1, else nothing). A field's
`target` is where the C unpacking puts it: a member of the layout's C struct (a name alone,
declared by the generator) or a member of one of its aggregates (``tree.axis``, the
aggregates of `Layout.members`, types of ``csrc/core.h``), so that the compiler checks the
names; a `view` field becomes a pointer into the buffer, a `value` its one number, a
`record` its fields (`Record`, e.g. the 19 numbers of a StepSettings).

Standard library only: `kernels.build`, which setup.py loads before anything is installed,
loads this file by its path.
"""
from __future__ import annotations

import collections
import re
from typing import NamedTuple

#: the C types of the kinds of numbers, in records and results
C_TYPES = {"double": "double", "i64": "i64", "bool": "int"}
_SIZE_EXPR = re.compile(r"^[A-Za-z_0-9 +*()]+$")


class Number(NamedTuple):
    """One named number of a record or a result: kind "double", "i64" or "bool"."""

    name: str
    kind: str
    doc: str
    default: float | None = None    # a record's default (the last fields only)


class Nested(NamedTuple):
    """A record inside a record (its fields travel first, in its own order); the C struct
    is the outer record's, which the inner decoder fills too."""

    name: str
    record: "Record"
    doc: str
    default: None = None
    kind: str = "record"


class Record(NamedTuple):
    """Named numbers that travel as floats (a Python NamedTuple, a C struct)."""

    name: str           # the Python record
    c_struct: str       # the C struct (core.h) its decoder fills
    c_decoder: str      # the generated C function: (const double *f, c_struct *out)
    fields: tuple       # Number, or Nested: a record inside it

    @property
    def length(self) -> int:
        """The number of floats it travels as (a nested record's all)."""
        return sum(f.record.length if isinstance(f, Nested) else 1 for f in self.fields)

    def flatten(self, values) -> list:
        """The floats of a record's values (a nested record's in place, in order)."""
        out = []
        for f, v in zip(self.fields, values, strict=True):
            out += f.record.flatten(v) if isinstance(f, Nested) else [float(v)]
        return out

    def named_tuple(self, doc: str, module: str):
        """The Python record: a named tuple of the fields, its docstring `doc` followed by
        the fields' descriptions."""
        defaults = [f.default for f in self.fields if f.default is not None]
        cls = collections.namedtuple(self.name, [f.name for f in self.fields],
                                     defaults=defaults or None, module=module)
        kinds = {'double': 'float', 'i64': 'int', 'bool': 'bool'}
        cls.__doc__ = doc + "\n\nFields (kernels.layouts):\n\n" + "\n".join(
            f"- {f.name} ({f.record.name if isinstance(f, Nested) else kinds[f.kind]}): "
            f"{f.doc}" for f in self.fields)
        return cls


class Field(NamedTuple):
    """One field of a buffer: `size` entries (an expression over the layout's sizes)."""

    name: str
    size: str
    target: str         # the C member it unpacks into ("" : none)
    doc: str
    shape: tuple = ()   # the Python view's shape (expressions), () for a flat view
    #: "view" | "value" | "record" | "header" (an entry of the header) | "flag" (a header
    #: entry read as 0 or 1)
    kind: str = "view"
    record: Record | None = None


class Buffer(NamedTuple):
    """One packed array of a layout. exact: its length must be the layout's, else at least."""

    name: str
    dtype: str          # "float64" | "int64" | "bool"
    fields: tuple
    exact: bool = True


class Layout(NamedTuple):
    """The packed buffers of one kernel model (or of one standalone buffer)."""

    name: str           # the Python name
    c_name: str         # its C struct is c_name_t, its unpacking unpack_c_name
    context: tuple      # sizes the caller gives (not in the header)
    members: tuple      # (C type, member): the aggregates the targets may reach into
    buffers: tuple

    def header(self) -> tuple:
        """The header's fields (the first entries of the ints buffer)."""
        return tuple(f for b in self.buffers for f in b.fields if f.kind in HEADER_KINDS)

    def buffer(self, name) -> Buffer:
        return next(b for b in self.buffers if b.name == name)


HEADER_KINDS = ("header", "flag")


def field_size(f: Field) -> str:
    """A field's size expression (a record's: its number of fields; a header entry's: 1)."""
    if f.kind == "record":
        return str(f.record.length)
    return "1" if f.kind in HEADER_KINDS else f.size


def evaluate(size: str, sizes: dict) -> int:
    """A size expression's value for the sizes given."""
    if not _SIZE_EXPR.match(size):
        raise ValueError(f"size expression {size!r}: names, numbers, +, * and () only")
    return int(eval(size, {"__builtins__": {}}, dict(sizes)))


def offsets(layout: Layout, buffer: str, sizes: dict) -> list:
    """[(field, offset, length)] of a buffer for the sizes given (header fields included)."""
    out, o = [], 0
    for f in layout.buffer(buffer).fields:
        n = evaluate(field_size(f), sizes)
        out.append((f, o, n))
        o += n
    return out


def length(layout: Layout, buffer: str, sizes: dict) -> int:
    """The buffer's length for the sizes given."""
    return sum(n for _, _, n in offsets(layout, buffer, sizes))


def describe(layout: Layout, indent: str = "    ") -> str:
    """The layout in words, for a docstring (each line indented by `indent`): each buffer's
    fields, in order, with sizes."""
    lines = []
    for b in layout.buffers:
        lines.append(f"{b.name} ({b.dtype}{'' if b.exact else ', at least this long'}):")
        for f in b.fields:
            size = field_size(f)
            if f.kind == "record":
                size += f" ({f.record.name}'s fields)"
            shape = f" as ({', '.join(f.shape)})" if f.shape else ""
            lines.append(f"    {f.name} [{size}{shape}]: {f.doc}")
    return "\n".join(indent + line for line in lines) + "\n"


# -- the records -------------------------------------------------------------------------

PROX_SETTINGS = Record("ProxSettings", "settings_t", "prox_settings_from_fields", (
    Number("form", "i64", "FORM_DELASSUS (Eqn. 12-16) | FORM_VELOCITY (Eqn. 17-19)"),
    Number("scheme", "i64", "SCHEME_JOR | SCHEME_SOR"),
    Number("tol_rel", "double", "T_rel"),
    Number("tol_abs", "double", "T_abs [N s]"),
    Number("max_iterations", "i64", "prox iteration cap"),
    Number("criterion", "i64", "CRITERION_IMPULSE | CRITERION_ENERGY (½ uᵀMu)"),
    Number("bilateral_direct", "bool",
           "Λ_B by Eqn. 20 after each sweep (else prox rows, Eqn. 19)"),
    Number("alpha", "double", "α > 0: r as given; < 0 (ALPHA_AUTO): adaptive α", 0.5),
    Number("stall_window", "i64",
           "sweeps per window of the stall test: a solve whose best residual of a window is "
           "not below STALL_FACTOR (0.99) x the window's before ends as STATUS_STALLED (0: no "
           "test)",
           0),
    Number("bilateral_relaxation", "double",
           "ω_B of the bilateral prox rows (0: the paper's, rows as the contacts' with α): "
           "r_B = ω_B/G_BB, swept Gauss-Seidel after the contacts' rows (prox.c)",
           0.0),
))

STEP_SETTINGS = Record("StepSettings", "settings_t", "settings_from_fields", (
    Nested("prox", PROX_SETTINGS, "the prox solver's settings (a ProxSettings)"),
    Number("activation_gap", "double", "g_act: I = {i | g_N,i(q^M) ≤ g_act} [m]"),
    Number("mu", "double", "μ, Coulomb friction coefficient of the ground"),
    Number("fallback_alpha_factor", "double",
           "a non-converged solve is retried once with α·this (0: no)"),
    Number("opening_gap", "double",
           "hysteresis: a loaded contact stays in I while g_N ≤ this [m]"),
    Number("dt", "double", "Δt [s]"),
    Number("beta_velocity", "double", "β_N of the velocity-level penetration correction (or 0)"),
    Number("beta_projection", "double",
           "β_N of the post-step projection (or 0: no projection)"),
    Number("jacobian_gap", "double", "W of a contact is computed while g_N(q^M) ≤ this [m]"),
    Number("projection_tolerance", "double", "the projection runs below g_N^E = −this [m]"),
    Number("warm_start", "bool", "Λ^0 = the last step's Λ of the contacts that stay in I"),
    Number("hysteresis", "bool",
           'contact.activation "hysteresis" (else the gap test alone)'),
    Number("fallback_hold", "i64",
           "steps a converged fallback α starts the solves while I stays the same (0: none; "
           "SimState.prox_memory)",
           0),
))

COMPLIANT_LAW = Record("CompliantLaw", "compliant_law_t", "compliant_law_from_fields", (
    Number("mu", "double", "μ, Coulomb friction coefficient"),
    Number("c_N", "double", "normal stiffness [N/m]"),
    Number("d_N", "double", "normal damping [N s/m]"),
    Number("c_T", "double", "tangential stiffness [N/m]"),
    Number("d_T", "double", "tangential damping [N s/m]"),
    Number("slip_velocity", "double",
           "‖γ_T‖ below which a slipping contact counts as stopped [m/s]"),
))


# -- the packed models -------------------------------------------------------------------

def _header(name, target, doc):
    return Field(name, "1", target, doc, kind="header")


TREE_STEP_MODEL = Layout(
    "TreeStepModel", "tree_model", (),
    (("tree_t", "tree"), ("frames_t", "frames"), ("inertias_t", "inertias"),
     ("contact_points_t", "contacts"), ("ground_t", "ground")),
    (Buffer("floats", "float64", (
        Field("settings", "", "s", "the step's settings", kind="record",
              record=STEP_SETTINGS),
        Field("law", "", "law", "the compliant contact law of the step", kind="record",
              record=COMPLIANT_LAW),
        Field("axis", "3 * nj", "tree.axis", "the joint axes, in the joint frames", ("nj", "3")),
        Field("pl_R", "9 * nj", "tree.pl_R", "the joint placements' rotations",
              ("nj", "3", "3")),
        Field("pl_p", "3 * nj", "tree.pl_p", "the joint placements' translations",
              ("nj", "3")),
        Field("oR", "9 * nj", "frames.oR", "the forward kinematics' scratch: rotations",
              ("nj", "3", "3")),
        Field("op", "3 * nj", "frames.op", "the forward kinematics' scratch: origins",
              ("nj", "3")),
        Field("mass", "nj", "inertias.mass", "the bodies' masses"),
        Field("lever", "3 * nj", "inertias.lever", "the bodies' centres of mass",
              ("nj", "3")),
        Field("inertia", "9 * nj", "inertias.inertia", "the bodies' rotational inertias",
              ("nj", "3", "3")),
        Field("gravity", "3", "inertias.gravity", "the gravity vector"),
        Field("c_local", "3 * nc", "contacts.local",
              "the contact spheres' centres in their joints' frames", ("nc", "3")),
        Field("c_radius", "nc", "contacts.radius", "the contact spheres' radii"),
        Field("ground_n", "3", "ground.n", "the ground's normal"),
        Field("ground_t1", "3", "ground.t1", "the ground's first tangent"),
        Field("ground_t2", "3", "ground.t2", "the ground's second tangent"),
        Field("ground_offset", "1", "ground.offset", "the ground plane n·x = this",
              kind="value"),
        Field("terrain", "nt", "ground.terrain",
              "the terrain, packed (terrain.pack_terrain; the plane alone: its header)"),
        Field("eps", "2 * nc", "eps", "(ε_N, ε_T) per contact", ("nc", "2")),
        Field("effort_limit", "na", "effort_limit",
              "the actuators' effort limits (public joint order)"),
        Field("velocity_limit", "na", "velocity_limit",
              "the actuators' velocity limits (public joint order)"),
        Field("armature", "drives * na", "armature",
              "the drives' reflected rotor inertias I_a [kg m²] (drives only)"),
        Field("viscous", "drives * na", "viscous",
              "the drives' viscous friction D [N m s/rad] (drives only)"),
        Field("friction_bound", "drives * na", "friction_bound",
              "the bound τ_c Δt of each joint's Coulomb friction impulse [N m s]"),
        Field("lag", "drives * na", "lag",
              "the torque lag's gain 1 − e^{−2π f Δt} (0: no lag; drives only)"),
    )),
     Buffer("ints", "int64", (
         _header("nj", "tree.nj", "joints (joint 0 the world)"),
         _header("nc", "contacts.nc", "contact points"),
         _header("na", "na", "actuated joints"),
         _header("nv", "tree.nv", "velocities"),
         _header("nt", "ground.n_terrain", "the packed terrain's floats"),
         _header("nq", "nq", "positions (q)"),
         Field("drives", "1", "drives", "1 with the drive models (actuator.py), else 0",
               kind="flag"),
         Field("parent", "nj", "tree.parent", "each joint's parent"),
         Field("jtype", "nj", "tree.jtype", "each joint's type (JT_*)"),
         Field("idx_q", "nj", "tree.idx_q", "each joint's first entry of q"),
         Field("idx_v", "nj", "tree.idx_v", "each joint's first entry of u"),
         Field("c_joint", "nc", "contacts.joint", "each contact point's joint"),
         Field("joint_v", "na", "joint_v", "each actuated joint's entry of u"),
         Field("joint_q", "na", "joint_q",
               "each actuated joint's entry of q (-1: a cut joint, whose φ is not in q)"),
         Field("dof_parent", "nv", "dof_parent",
               "the dofs' parents (KinematicTree.dof_parent: the structure of M's factor)"),
     )),
     Buffer("support", "bool", (
         Field("support", "nj * nj", "tree.support", "support[j, k]: joint k supports j",
               ("nj", "nj")),
     )),
     Buffer("workspace", "float64", (
         Field("gap", "nc", "gap", "g_N at q^M"),
         Field("position", "3 * nc", "position", "the contact points at q^M", ("nc", "3")),
         Field("Wt_all", "3 * nc * nv", "Wt_all", "W^T of every contact",
               ("nc", "3", "nv")),
         Field("L", "nv * nv", "L", "the LTDL factor of M", ("nv", "nv")),
         Field("u_free", "nv", "u_free", "u^S + M^{-1} h Δt"),
         Field("u_corr", "nv", "u_corr", "Δu_p of the post-step projection"),
         Field("frames", "11 * nc", "ground.frames",
               "each contact's surface frame (n, t1, t2), μ and surface at q^M", ("nc", "11")),
         Field("qM", "nq", "qM", "q^M (Eqn. 6), kept for the step when prepared ahead"),
         Field("M", "nv * nv", "M", "M at q^M (a constant M: unused)", ("nv", "nv")),
         Field("h", "nv", "h", "h at (q^M, u^S) without τ and f_ext"),
         Field("timings", "5", "timings",
               "the Fig. 7 phases' cumulative times when profiling (PHASES order) [s]"),
         Field("lag_state", "drives * na", "lag_state",
               "the lagged torques at the step's start (SimState.drive_torque, copied in)"),
     ), exact=False)))

CUT_MODEL = Layout(
    "CutModel", "cut_model", ("na", "nv"), (("cuts_t", "cuts"),),
    (Buffer("floats", "float64", (
        Field("beta_over_dt", "1", "beta_over_dt", "β/Δt, the factor of b_B = (β/Δt) g_B",
              kind="value"),
        Field("p_P", "3 * ncut", "cuts.p_P", "the joint's origin in the parent body",
              ("ncut", "3")),
        Field("p_C", "3 * ncut", "cuts.p_C", "the joint's origin in the child body",
              ("ncut", "3")),
        Field("a_P", "3 * ncut", "cuts.a_P", "the joint's axis in the parent", ("ncut", "3")),
        Field("b1_P", "3 * ncut", "cuts.b1_P", "b1 ⟂ a in the parent", ("ncut", "3")),
        Field("b2_P", "3 * ncut", "cuts.b2_P", "b2 = a × b1 in the parent", ("ncut", "3")),
        Field("a_C", "3 * ncut", "cuts.a_C", "the joint's axis in the child", ("ncut", "3")),
        Field("b1_C", "3 * ncut", "cuts.b1_C", "b1 in the child", ("ncut", "3")),
        Field("M", "constant * nv * nv", "M", "a constant M", ("constant * nv", "nv")),
        Field("body_mass", "nr", "body_mass", "a constant M's free bodies' masses"),
        Field("body_inertia", "9 * nr", "body_inertia", "their inertias", ("nr", "3", "3")),
        Field("body_gravity", "3 * constant", "body_gravity", "and gravity"),
    )),
     Buffer("ints", "int64", (
         _header("ncut", "cuts.ncut", "cut joints"),
         Field("constant", "1", "constant", "1 for a constant M, else 0", kind="flag"),
         _header("nr", "nr", "free bodies of a constant M (0 otherwise)"),
         Field("cut_P", "ncut", "cuts.P", "each cut joint's parent body"),
         Field("cut_C", "ncut", "cuts.C", "each cut joint's child body"),
         Field("joint_cut", "na", "joint_cut",
               "each actuated joint's cut joint (public order; -1 inside a tree)"),
         Field("root_q", "nr", "root_q", "each free body's first entry of q"),
         Field("root_v", "nr", "root_v", "each free body's first entry of u"),
     )),
     Buffer("workspace", "float64", (
         Field("WtB", "5 * ncut * nv", "WtB", "W_B^T", ("5 * ncut", "nv")),
         Field("gB", "5 * ncut", "gB", "g_B"),
         Field("bB", "5 * ncut", "bB", "b_B = (β/Δt) g_B"),
         Field("angle", "ncut", "angle", "φ"),
         Field("rate", "ncut", "rate", "φ̇ (at zero velocity, not used)"),
         Field("axis_world", "3 * ncut", "axis_world", "the hinge axes in the world",
               ("ncut", "3")),
         Field("bilateral_E", "5 * ncut", "bilateral_E",
               "the step's Λ_B (kept there until the step is known to end finite)"),
     ))))

#: what a one-kernel step reports, in one buffer that the caller allocates once
STEP_REPORT = Layout(
    "StepReport", "report", ("nc", "na"), (),
    (Buffer("report", "float64", (
        Field("impulse", "3 * nc", "impulse", "Λ in the contact frame (N, T1, T2)",
              ("nc", "3")),
        Field("gap", "nc", "gap", "g_N at q^M"),
        Field("position", "3 * nc", "position", "the contact points at q^M", ("nc", "3")),
        Field("applied_torque", "na", "applied_torque", "the torques applied"),
        Field("explicit_torque", "na", "explicit_torque",
              "the torques added to h (an implicit damper's joint: the law at u^S)"),
        Field("damper", "na", "damper", "kd of the implicit dampers (0: none)"),
    )),))

#: a joint impedance command (impedance.ImpedanceCommand.packed), one row per term, one
#: entry per actuated joint (public order): τ = τ_ff + kp (q* − q) + kd (q̇* − q̇), a NaN target
#: (or τ_ff) leaving its term out
IMPEDANCE_COMMAND = Layout(
    "ImpedanceCommand", "impedance_command", ("na",), (),
    (Buffer("command", "float64", (
        Field("position", "na", "position", "q*, the position targets [rad] (NaN: no kp term)"),
        Field("velocity", "na", "velocity",
              "q̇*, the velocity targets [rad/s] (NaN: no kd term)"),
        Field("kp", "na", "kp", "the stiffnesses [N m/rad], finite, ≥ 0"),
        Field("kd", "na", "kd", "the dampings [N m s/rad], finite, ≥ 0"),
        Field("effort", "na", "effort", "τ_ff, the feed-forward torques [N m] (NaN: none)"),
    )),))

LAYOUTS = (TREE_STEP_MODEL, CUT_MODEL, STEP_REPORT, IMPEDANCE_COMMAND)
RECORDS = (PROX_SETTINGS, STEP_SETTINGS, COMPLIANT_LAW)   # (a nested record first)


# -- the named results -------------------------------------------------------------------

class Result(NamedTuple):
    """A kernel's named result: a C struct, returned to Python as an object of its own type
    whose fields are read-only attributes (and whose type's _fields names them)."""

    name: str           # the Python type, an attribute of the kernels' module
    c_struct: str
    doc: str
    fields: tuple


_SOLVE_FIELDS = (
    Number("iterations", "i64", "prox iterations"),
    Number("status", "i64", "the prox solve's STATUS_*"),
    Number("residual", "double", "max |Λ^{k+1} − Λ^k| of the last sweep [N s]"),
    Number("retried", "bool", "the solve was retried with the fallback α"),
    Number("projection_iterations", "i64", "iterations of the post-step projection"),
    Number("projection_status", "i64", "its STATUS_*, or −1: it was not needed"),
)
_SET_FIELDS = (
    Number("n_active", "i64", "|I|, the active contacts"),
    Number("opened", "i64", "contacts loaded in the last step that left the active set"),
)

TREE_STEP_RESULT = Result(
    "TreeStepResult", "tree_step_result_t",
    "What a step did (tree_step_hard, tree_step_compliant, forest_step).",
    (Number("outcome", "i64", "TREE_STEP_*"),) + _SET_FIELDS + _SOLVE_FIELDS)
COMPLETION_RESULT = Result(
    "CompletionResult", "complete_result_t",
    "What complete_problem (step_kernels.c) did: the solve of a prepared contact problem.",
    _SOLVE_FIELDS)

RESULTS = (TREE_STEP_RESULT, COMPLETION_RESULT)
