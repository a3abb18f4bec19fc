"""The joints' actuators: the torque a motor applies for the torque a controller asks.

`saturate_torque` (C, ``csrc/contact.c``) is the one definition: the step's kernels apply it
inside the step, and the impedance law and a cut forest's torques call it from here.
"""
from __future__ import annotations

import numpy as np

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
