"""The controller's parameters for a robot: StarlETH's (ControllerParams' defaults) carried over
by the scaling rule (starleth_interface.robot.scaling: dynamic similarity with gravity fixed,
λ = leg length / StarlETH's, μ = mass / StarlETH's, times as √λ), one rule for every robot
(doc/controllers.md):

    lengths [m] λ · speeds [m/s] √λ · times [s] √λ · accelerations [m/s²] 1
    angular accelerations [rad/s²] 1/λ · forces [N] μ · force gains [N/m] μ/λ, [N s/m] μ/√λ
    moment gains [N m/rad] μλ, [N m s/rad] μλ^1.5 · joint gains likewise (μλ, μλ^1.5)
    the force QP's weights: of its moment rows 1/λ² (a moment is a force times a length),
    of its force rows unchanged; angles and shares unchanged

The trunk height is the robot's standing height (its spec's) less StarlETH's margin, scaled:
0.41 m · h_stand / 0.415 m (a URDF without a spec: 0.41 m · λ). The gait's phases and
the default footholds follow each leg's side (diagonal pairs; fore feet behind, hind feet
ahead of their hips). StarlETH gets its own numbers bit for bit.
"""
from __future__ import annotations

from dataclasses import fields, replace

from .inputs import ControllerParams, VMCGains

#: StarlETH's standing height (robots/starleth.yaml), the reference of the trunk height
REFERENCE_STANDING_HEIGHT = 0.415      # m
#: the trot speed of StarlETH-sized legs; a robot trots at TROT_SPEED · √λ
TROT_SPEED = 0.3                       # m/s
_LENGTHS = ("swing_height", "touchdown_depth", "step_max", "max_position_error",
            "lost_contact_depth", "step_down_depth")
_SPEEDS = ("lost_contact_speed", "step_down_speed")
_TIMES = ("gait_period", "recover_time")
_FORCES = ("velocity_integral_max", "min_normal_force", "contact_force_threshold")


def trot_speed(scale) -> float:
    """The trot speed [m/s] of a robot of RobotScale `scale`: 0.3 m/s · √λ."""
    return TROT_SPEED * scale.time


def _scaled_gains(g: VMCGains, s) -> VMCGains:
    lam, mu = s.length, s.mass
    return VMCGains(kp=tuple(x * mu / lam for x in g.kp),
                    kd=tuple(x * mu / s.time for x in g.kd),
                    kff=tuple(x * mu / s.time for x in g.kff),
                    kp_rot=tuple(x * s.stiffness for x in g.kp_rot),
                    kd_rot=tuple(x * s.damping for x in g.kd_rot),
                    kff_rot=tuple(x * s.stiffness for x in g.kff_rot))


def _sides(model, base: ControllerParams) -> dict:
    """The phases and default footholds of each leg from its side: the trot's diagonal pairs
    (LF+RH at StarlETH's LF phase, RF+LH at its RF phase) and the fore / hind offsets."""
    fore_x, hind_x = base.foothold_offset_x[0], base.foothold_offset_x[2]
    lam = model.scale.length
    return dict(phase_offsets=tuple(base.phase_offsets[0] if leg.fore == leg.left
                                    else base.phase_offsets[1] for leg in model.legs),
                foothold_offset_x=tuple((fore_x if leg.fore else hind_x) * lam
                                        for leg in model.legs))


def params_for_robot(model, base: ControllerParams | None = None) -> ControllerParams:
    """`base` (default: StarlETH's ControllerParams) scaled to the robot of a RobotModel
    (module docstring)."""
    base = base or ControllerParams()
    s = model.scale
    changes = _sides(model, base)
    h = model.standing_height
    ratio = float(f"{h / REFERENCE_STANDING_HEIGHT:.6g}") if h is not None else s.length
    if s.length == 1.0 and s.mass == 1.0 and ratio == 1.0:
        return replace(base, **changes)
    lam, mu = s.length, s.mass
    names = {f.name for f in fields(base)}
    for n in _LENGTHS:
        changes[n] = getattr(base, n) * lam
    for n in _SPEEDS + _TIMES:
        changes[n] = getattr(base, n) * s.time
    for n in _FORCES:
        changes[n] = getattr(base, n) * mu
    changes.update(
        height=base.height * ratio,
        trot_height=None if base.trot_height is None else base.trot_height * ratio,
        max_yaw_acceleration=base.max_yaw_acceleration / lam,
        wrench_weights=tuple(base.wrench_weights[:3])
        + tuple(w / (lam * lam) for w in base.wrench_weights[3:]),
        velocity_ki=base.velocity_ki * mu / lam,
        trot_gains=_scaled_gains(base.trot_gains, s),
        stand_gains=_scaled_gains(base.stand_gains, s),
        joint_kp=tuple(x * s.stiffness for x in base.joint_kp),
        joint_kd=tuple(x * s.damping for x in base.joint_kd))
    assert set(changes) <= names
    return replace(base, **changes)

