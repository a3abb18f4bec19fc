"""Joint impedance commands: the typed record `ImpedanceCommand` and its law, evaluated by
the simulator at every physics step (not once per control message).

Per actuated joint i (public joint order LF, RF, LH, RH x HAA, HFE, KFE), at each physics
step from (q^S, u^S) to u^E:

    τ_i = τ_ff,i + kp_i (q*_i − q^S_i) + kd_i (q̇*_i − q̇^E_i)

the spring explicit, the damper implicit where the coordinates allow it (the minimal ones:
every joint rate an entry of u): the law at the start state, τ_S, goes into h and
M + Δt·diag(kd) replaces M in the step's solve, so τ = τ_S − kd (q̇^E − q̇^S) (as MuJoCo
integrates joint damping). Saturation (actuator.saturate_torque: the effort limit, and the
velocity derating): a joint whose τ_S is saturated takes it saturated, explicitly; a damped
joint whose τ would be saturated at q̇^E loses its damper in one second solve. The extended
and maximal coordinates keep the damper explicit (at q̇^S). q*, q̇*: the position and
velocity targets, kp, kd ≥ 0 (finite) the stiffness and damping, τ_ff the feed-forward
torque. A NaN in q*_i, q̇*_i or τ_ff,i leaves that term out for joint i (NaN q* with a kp:
no spring; NaN q̇*: no damper; NaN τ_ff: none), so one record carries pure torque, pure
damping, or full impedance, joint by joint. The sum is formed in this order, term by term
(τ_ff, then the kp term, then the kd term), by the one C function `impedance_torque` that
every path calls. See doc/physics.md, "Joint impedance", for the stability it buys.

Which state for the spring: the start of each physics step, (q^S, u^S): the state at which
the step's torque saturation already reads q̇, and the state a controller publishing at the
physics rate would have measured. The midpoint q^M (where h(q^M, u^S) is evaluated) would
add an implicit damping ½Δt·kp to the law, a property of the step size rather than of the
command, and for the cut joints of the extended and maximal coordinates it would need the
cut-joint kinematics at q^M.

Validation (`ImpedanceCommand.create`): a ValueError naming the field and the joints, for a
wrong length, a negative or non-finite gain, or an infinite target or τ_ff (NaN is allowed
there: it means "term off"); the ROS layer turns that into a throttled warning and keeps
the last valid command.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import kernels as _kernels
from .actuator import NonFiniteTorque, real_array, saturate_torque
from .kernels.layouts import IMPEDANCE_COMMAND

#: the command's fields, in the order of the packed layout (kernels.layouts.IMPEDANCE_COMMAND)
FIELDS = tuple(f.name for f in IMPEDANCE_COMMAND.buffers[0].fields)
#: the gains: finite and ≥ 0
GAINS = ("kp", "kd")
#: the fields in which NaN means "this term off"
OPTIONAL_TERMS = ("position", "velocity", "effort")

#: how a one-kernel step reads its torque argument (tree_step_hard, tree_step_compliant):
#: as given, saturated, or an impedance command (5 per joint) whose law is then saturated
TORQUE_AS_GIVEN = _kernels.TORQUE_AS_GIVEN
TORQUE_SATURATED = _kernels.TORQUE_SATURATED
TORQUE_IMPEDANCE = _kernels.TORQUE_IMPEDANCE
#: a replay of implicit dampers: per joint the explicit torque, then the damper's kd
TORQUE_REPLAY = _kernels.TORQUE_REPLAY

#: ``impedance_torque(command, q, qd, out)``: out = the law of the packed command
#: (ImpedanceCommand.packed, flat) at the joint angles q and rates qd (float64, one per joint)
impedance_torque = _kernels.impedance_torque


@dataclass(frozen=True, eq=False)
class ImpedanceCommand:
    """A joint impedance command (see the module docstring), one entry per actuated joint in
    the public joint order. Build it with `create`, which validates; its arrays are read
    only. Fields (paper-style symbols): position q* [rad], velocity q̇* [rad/s], kp [N m/rad],
    kd [N m s/rad], effort τ_ff [N m]; `packed` holds them as one float64 buffer in the
    order FIELDS, as the kernels read it."""

    position: np.ndarray
    velocity: np.ndarray
    kp: np.ndarray
    kd: np.ndarray
    effort: np.ndarray
    packed: np.ndarray
    joint_names: tuple

    @classmethod
    def create(cls, joint_names, position=None, velocity=0.0, kp=0.0, kd=0.0,
               effort=0.0) -> "ImpedanceCommand":
        """A validated command for the joints `joint_names` (their order). Each field is a
        number (the same for every joint) or one value per joint; position None: no spring
        (NaN), velocity 0: the damper pulls q̇ to rest (MuJoCo's position actuator), None:
        no damper; effort None: no τ_ff. ValueError naming the field and the joints on a
        wrong length, a negative or non-finite gain, or an infinite target or τ_ff."""
        names = tuple(joint_names)
        n = len(names)
        given = dict(position=position, velocity=velocity, kp=kp, kd=kd, effort=effort)
        arrays = {}
        for name in FIELDS:
            value = np.nan if given[name] is None else given[name]
            a = real_array(value, f"ImpedanceCommand: {name}", (0, 1)).reshape(-1)
            if a.shape[0] == 1:
                a = np.repeat(a, n)
            if a.shape[0] != n:
                raise ValueError(f"ImpedanceCommand: {name} must have {n} entries (joint "
                                 f"order {', '.join(names)}) or one, got {a.shape[0]}")
            if name in GAINS:
                bad = ~(np.isfinite(a) & (a >= 0.0))
                rule = "finite and >= 0"
            else:
                bad = np.isinf(a)
                rule = "finite, or NaN for no such term"
            if bad.any():
                which = ", ".join(f"{names[i]} ({a[i]:g})" for i in np.flatnonzero(bad))
                raise ValueError(f"ImpedanceCommand: {name} must be {rule}: {which}")
            arrays[name] = a
        packed = np.concatenate([arrays[name] for name in FIELDS])
        packed.flags.writeable = False
        views = {name: packed[k * n:(k + 1) * n] for k, name in enumerate(FIELDS)}
        return cls(packed=packed, joint_names=names, **views)

    def torque(self, q, qd) -> np.ndarray:
        """The law's torques (before saturation) at joint angles q and rates qd (public
        order), by the kernels' own function: what a step applies, bit for bit, before
        actuator.saturate_torque."""
        n = len(self.joint_names)
        q = np.ascontiguousarray(q, dtype=np.float64).reshape(-1)
        qd = np.ascontiguousarray(qd, dtype=np.float64).reshape(-1)
        if q.shape[0] != n or qd.shape[0] != n:
            raise ValueError(f"ImpedanceCommand.torque: q and qd need {n} entries")
        out = np.empty(n)
        impedance_torque(self.packed, q, qd, out)
        return out


def command_torques(tau, q, u, coords, effort_limit, velocity_limit):
    """The applied torques of an ImpedanceCommand's packed buffer `tau` at (q, u) of the
    coordinate set `coords` (a cut forest: a cut joint's φ and φ̇ come from its
    kinematics): the law (impedance_torque, the kernels' own), saturated
    (actuator.saturate_torque at the same rates by the limits). NonFiniteTorque if the law
    overflows. (The tree kernels evaluate the law inside, with their implicit dampers.)"""
    na = coords.joint_v.shape[0]
    qd = coords.joint_velocities(q, u)
    law = np.empty(na)
    impedance_torque(tau, coords.joint_positions(q, u), qd, law)
    applied = np.empty(na)
    if not saturate_torque(law, effort_limit, qd, velocity_limit, applied):
        raise NonFiniteTorque("the impedance law gave non-finite torques")
    return applied


def replay_rows(torques, n, joint_names, implicit):
    """The rows of Simulator.step_applied, validated: n physics steps x nj torques (one row
    for every step), or x 2 nj (explicit torques, then the implicit dampers' kd ≥ 0, nonzero
    only where `implicit`). ValueError naming the joints on a wrong shape or value."""
    nj = len(joint_names)
    a = real_array(torques, "step_applied: torques", (1, 2)).copy()
    if a.ndim == 1:
        a = np.tile(a, (n, 1))
    if a.shape not in ((n, nj), (n, 2 * nj)):
        raise ValueError(f"step_applied: torques must be {n} x {nj} (physics steps x joints "
                         f"{', '.join(joint_names)}), or {n} x {2 * nj} "
                         f"(replay_torques_per_step), got {a.shape}")
    bad = ~np.isfinite(a).all(axis=0)
    if bad.any():
        bad = bad[:nj] | bad[nj:] if a.shape[1] > nj else bad
        raise ValueError("tau has non-finite entries for "
                         f"{', '.join(joint_names[i] for i in np.flatnonzero(bad))}")
    if a.shape[1] > nj:
        if np.any(a[:, nj:] < 0.0):
            raise ValueError("step_applied: the dampers' kd must be >= 0")
        if not implicit and np.any(a[:, nj:] != 0.0):
            raise ValueError("step_applied: these coordinates have no implicit dampers")
    return a
