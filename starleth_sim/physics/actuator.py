"""The joints' actuators: the torque a motor applies for the torque a controller asks.

`saturate_torque` (C, ``csrc/contact.c``) is the one definition: the step's kernels apply it
inside the step, and the impedance law and a cut forest's torques call it from here.
`drive_parameters`: the drive models of the `actuator:` section (armature, viscous and
Coulomb joint friction, torque bandwidth) per joint, for the step kernels (doc/drives.md).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from starleth_interface.config_checks import ConfigError

from . import kernels as _kernels

#: ``saturate_torque(tau, limit, qd, qd_limit, out) -> bool``: the torques the motors apply:
#: out = tau clipped to [-limit, limit] (effort limits); a torque that drives its joint
#: faster (τ φ̇ > 0) beyond the velocity limit v is derated like a motor's torque-speed line,
#: linearly from full at |φ̇| = v to zero at 2v (its no-load speed): no motor adds power
#: beyond that, so a misbehaving controller cannot spin a leg up without bound, and the
#: torque stays a continuous function of the state. Braking torques are never derated.
#: False if tau has a non-finite entry (out is then not to be used).
saturate_torque = _kernels.saturate_torque


class NonFiniteTorque(ValueError):
    """The joint torques of a step have a non-finite entry; nothing was done."""


def real_array(value, what: str, ndims=(1,)) -> np.ndarray:
    """`value` as a float64 array (contiguous) of one of `ndims` dimensions; a ValueError
    naming `what` and what was given where it is not real numbers (complex, bool, text,
    objects, ragged lists) or has another number of dimensions: a (3, 4) array is not 12
    torques, and a complex torque is not its real part."""
    try:
        a = np.asarray(value)
    except (TypeError, ValueError):      # ragged nested lists
        a = None
    if a is None or a.dtype.kind not in "fiu":
        got = "a ragged list" if a is None else f"{a.dtype} values"
        raise ValueError(f"{what} must be real numbers, got {got}")
    if a.ndim not in ndims:
        want = " or ".join({0: "a number", 1: "a vector", 2: "a matrix"}[n] for n in ndims)
        raise ValueError(f"{what} must be {want}, got an array of shape {a.shape}")
    return np.ascontiguousarray(a, dtype=np.float64)


class DriveParameters(NamedTuple):
    """The drive models per actuated joint (public order; doc/drives.md): I_a [kg m²], D
    [N m s/rad], τ_c [N m], f [Hz]. The laws are the step kernels' (``csrc/tree_step.c``)."""

    armature: np.ndarray
    viscous_damping: np.ndarray
    coulomb_friction: np.ndarray
    torque_bandwidth: np.ndarray

    def packed(self, dt: float) -> dict:
        """The kernels' fields (kernels.layouts.TREE_STEP_MODEL): I_a, D, the friction
        impulse's bound τ_c Δt and the lag's gain 1 − e^{−2π f Δt} (0: no lag)."""
        return {"armature": self.armature, "viscous": self.viscous_damping,
                "friction_bound": self.coulomb_friction * dt,
                "lag": -np.expm1(-2.0 * np.pi * self.torque_bandwidth * dt)}


def drive_parameters(actuator, joint_names) -> DriveParameters | None:
    """The drive fields of an ActuatorConfig as arrays over `joint_names`, or None when
    every one is off; a ConfigError names the field and a joint the robot does not have."""
    if not actuator.drives_on:
        return None
    arrays = {}
    for name in actuator.DRIVES:
        value = getattr(actuator, name)
        if not isinstance(value, dict):
            arrays[name] = np.full(len(joint_names), float(value))
            continue
        unknown = [k for k in value if k not in joint_names]
        if unknown:
            raise ConfigError(f"actuator.{name}: unknown joint '{unknown[0]}' (joints: "
                              f"{', '.join(joint_names)})")
        arrays[name] = np.array([float(value.get(j, 0.0)) for j in joint_names])
    return DriveParameters(**arrays)
