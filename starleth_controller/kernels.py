"""The controller's per-call arithmetic: the C extension module
``starleth_controller._kernels`` (sources in ``csrc/``: kernels.c, ground_plane.c; their
bindings in module.c), loaded here.

Small fixed-size linear algebra that numpy would spend most of its time dispatching, and the
scalar formulas of the state reading, the leg kinematics, the virtual model, the force QP's
inputs, the swing legs and the ground plane (ground_plane.c), which Python would spend most
of its time interpreting. Each formula keeps the operation order (and Python's min / max
semantics) of the code it replaced, built without contraction or reassociation: the torques
are bit for bit those of that code.

An installed package holds the module its ``setup.py`` built; a source checkout builds it on
first import, and again whenever the sources changed (starleth_interface.c_extension, the
build recipe of every C extension: a fraction of a second).

Leg geometry arrays (one row per leg, model.py): ``hip`` (4, 3) HAA position in the base
frame, ``geo`` (4, 12) = l0 (HAA→HFE, vertical), l1 (thigh), l2 (shank to the foot centre),
foot radius, knee sign (−1 backward, +1 forward), o_x (HAA→HFE along x), d_y (the lateral
offset HAA→foot), α and γ (the thigh's angle from −z and the shank's from the thigh), the
signs of the roll axis along x and of the pitch axes along y (model.py's docstring). A
StarlETH leg (zero offsets and angles, signs +1) keeps the arithmetic of its own formulas.
The swing parameters (controller._swing_parameters) are laid out as ``SW_*``.
"""
from __future__ import annotations

from starleth_interface import c_extension

_kernels = c_extension.load(__package__ + "._kernels")
globals().update({name: getattr(_kernels, name) for name in dir(_kernels)
                  if not name.startswith("__")})
