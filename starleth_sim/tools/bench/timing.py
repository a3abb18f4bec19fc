"""The timed loop of the step benchmarks (starleth-bench's rates, its --impedance and
--terrain rounds): a simulator stepped under the posture hold's torques (or a fixed
command), the controller's part untimed, only `Simulator.step` on the clock."""
from __future__ import annotations

import time


def timed_steps(sim, n: int, hold=None, command=None):
    """Step `sim` n control steps with `hold.torque(sim)` (computed untimed) or the fixed
    `command`; returns (wall seconds spent in Simulator.step, prox iterations summed)."""
    wall = 0.0
    iterations = 0
    for _ in range(n):
        u = hold.torque(sim) if hold is not None else command
        t0 = time.perf_counter()
        d = sim.step(u)
        wall += time.perf_counter() - t0
        iterations += d.iterations
    return wall, iterations
