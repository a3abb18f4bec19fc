"""Per-cycle timestamps for the benchmarks of the two nodes (``SimNode.timing``,
``ControllerNode.timing``; off unless a benchmark sets them).

Times are ``time.perf_counter`` (CLOCK_MONOTONIC), comparable across the processes of one
host, so that ``starleth-bench-ros`` can put a cycle's sim-side and controller-side
instants on one axis.
"""
from __future__ import annotations

import numpy as np

#: sim_node's instants of one lockstep cycle: command in, stepped, the state a controller
#: waits for out (the bundle; without a bundle subscriber the foot wrenches, the base state
#: and /joint_states), the other state topics out, the post-publish work done (prepare,
#: visualisation, hand-over to the recorder)
SIM_CYCLE_FIELDS = ("command_in", "stepped", "state_out", "public_out", "done")
#: controller_node's instants of one cycle: first and last message of a stamp in, torques
#: computed, command published
CONTROLLER_CYCLE_FIELDS = ("first_in", "complete", "computed", "sent")


class CycleTimes:
    """One row of instants (`fields`) per cycle, keyed by the cycle's stamp (ns), up to
    `capacity` cycles (later ones are not kept). Fill `row` and `commit(stamp)`, or
    `add(stamp, *instants)` in one call."""

    def __init__(self, fields=SIM_CYCLE_FIELDS, capacity=200_000):
        self.FIELDS = tuple(fields)
        self.stamp = np.zeros(capacity, np.int64)
        self.t = np.zeros((capacity, len(self.FIELDS)))
        self.n = 0
        self.row = np.zeros(len(self.FIELDS))

    def commit(self, stamp: int) -> None:
        """Keeps `row` as the instants of the cycle `stamp`."""
        if self.n < len(self.stamp):
            self.stamp[self.n] = stamp
            self.t[self.n] = self.row
            self.n += 1

    def add(self, stamp: int, *instants: float) -> None:
        """Keeps `instants` (one per field) as the instants of the cycle `stamp`."""
        self.row[:] = instants
        self.commit(stamp)
