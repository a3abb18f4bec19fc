"""Compiling the controller's numba kernels (``kernels.py``) before the first state.

numba compiles a kernel on its first call and keeps the machine code in its on-disk cache
(``cache=True``), so only the first run after an install (or an edit of kernels.py) pays
for it: about 10 s on a 2-core machine. `warm_up` makes that first call happen at start-up,
on synthetic states that take every path a running controller takes (stand, trot with feet
on the ground, in the air, searching the ground, a fall, a non-finite state), instead of in
the middle of a control loop. `compile_kernels` (controller_node calls it before it
subscribes, and ``starleth-precompile`` in its own processes) adds the kernel that reads the
node's states, and says so while it takes long. Every later call of the kernels with the
argument types of a real run then loads or reuses that code (test_controller checks that a
closed-loop trot compiles nothing more).
"""
from __future__ import annotations

import numpy as np

from starleth_interface import state_bundle
from starleth_interface.compile_notice import CompileNotice
from .controller import StarlethController
from .inputs import Command, ControllerParams, RobotState
from .state_intake import state_from_values

#: control period of the synthetic states [s] (sim_node's)
PERIOD = 0.0025


def _tilted(angle):
    """The quaternion (x, y, z, w) of a roll by angle."""
    return np.array([np.sin(0.5 * angle), 0.0, 0.0, np.cos(0.5 * angle)])


def warm_up(urdf: str | None = None, params: ControllerParams | None = None) -> int:
    """Runs a throw-away StarlethController over synthetic states that reach each kernel with
    the argument types of a real run; returns the number of updates."""
    ctrl = StarlethController(urdf, params)
    p = ctrl.params
    q = ctrl.model.nominal_joint_positions(p.height)
    weight = np.array([0.0, 0.0, ctrl.model.mass * 9.81 / 4])
    t = 0.0
    n = 0

    def update(contact, command, quat=(0.0, 0.0, 0.0, 1.0), positions=q):
        nonlocal t, n
        flags = np.array(contact, dtype=bool)
        force = np.where(flags[:, None], weight, 0.0)
        s = RobotState(t, positions.copy(), np.zeros(12), np.array([0.0, 0.0, p.height]),
                       np.asarray(quat, dtype=float), np.zeros(3), np.zeros(3), flags, force)
        ctrl.update(s, command)
        t += PERIOD
        n += 1

    stand, trot = Command("stand"), Command("trot", forward=0.3, lateral=0.05, yaw_rate=0.1)
    for _ in range(40):
        update((True,) * 4, stand)
    cycle = int(round(p.gait_period / PERIOD))
    for _ in range(cycle):                              # trot, every foot on the ground
        update((True,) * 4, trot)
    for k in range(cycle):                              # trot, the planned stance feet only
        first_half = k < cycle // 2
        update((first_half, not first_half, not first_half, first_half), trot)
    for _ in range(cycle // 2):                         # trot, no foot down: searching
        update((False,) * 4, trot)
    for _ in range(10):                                 # fallen
        update((True,) * 4, trot, quat=_tilted(1.2))
    nan = q.copy()
    nan[0] = np.nan
    update((True,) * 4, stand, positions=nan)           # a non-finite state
    return n


def compile_kernels(log=print, threshold: float = ControllerParams.contact_force_threshold):
    """Compiles (or loads from numba's cache) every kernel the node runs before its first
    state: the controller's (warm_up) and the state reader's (node_state, with the
    argument types of a state bundle), saying so while it takes long (CompileNotice: about
    10 s the first time after an install). Returns the seconds taken."""
    with CompileNotice("the controller's kernels", log, estimate=10.0) as notice:
        warm_up()
        v = np.zeros(state_bundle.SIZE)
        v[state_bundle.BASE][6] = 1.0           # (a unit quaternion)
        state_from_values(0, v[state_bundle.SLICES["q"]], v[state_bundle.SLICES["u"]],
                          np.arange(12, dtype=np.int64), np.array(v[state_bundle.BASE]),
                          np.array(v[state_bundle.SLICES["force"]].reshape(4, 3)),
                          float(threshold), True, np.eye(3))
    return notice.seconds
