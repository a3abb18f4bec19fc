"""The command delay of sim_node (parameter ``command_delay``): the latency between a
controller and its robot's drives, modelled in sim time, as simulators for legged robots
model it (Isaac Lab's DelayedPDActuator, legged_gym's action delay), so that a controller
meets in simulation the delay it will meet on the robot.

A command received while the state of step k is the latest (lockstep: the answer to state
k; realtime: one arriving between the ticks k and k + 1) takes effect at step k + d, d =
``command_delay`` in control periods; until then the command in effect holds. It delays
the *command*, whatever it carries: a torque (a torque relay's feedback loop then closes
d periods late) or an impedance command (its targets come d periods late; the law's
feedback stays at every physics step on the current state). d = 0 is sim_node without a
delay, bit for bit. ROS-free: :class:`~.service.SimService` holds one
:class:`DelayLine`."""
from __future__ import annotations

from collections import deque

#: s: the largest command_delay (40 control periods at 400 Hz)
MAX_COMMAND_DELAY = 0.1


def delay_periods(seconds: float, control_period: float) -> tuple[int, str]:
    """(d, text): `seconds` of command delay as a whole number d of control periods (the
    nearest), and a line saying so, with a note when that rounded the value."""
    d = int(round(seconds / control_period))
    text = f"command delay {d} control period{'' if d == 1 else 's'} " \
           f"({d * control_period * 1e3:g} ms)"
    if abs(d * control_period - seconds) > 1e-9:
        text += f": command_delay {seconds:g} s rounded to a whole number of control periods"
    return d, text


class DelayLine:
    """The commands received but not yet in effect: ``pending``, (step, command) in the order
    of their steps; ``steps`` = d. :meth:`put` queues a command received at step k for
    step k + d, :meth:`due` gives the one in effect from step k on. A command supersedes
    the pending ones due at its step or later (only after d was lowered at run time can an
    older one be due later), so at most d + 1 commands are pending."""

    def __init__(self, steps: int = 0):
        self.steps = steps
        self.pending = deque()

    def put(self, k: int, command) -> None:
        at = k + self.steps
        pending = self.pending
        while pending and pending[-1][0] >= at:
            pending.pop()
        pending.append((at, command))

    def due(self, k: int):
        """The newest pending command due at step k or earlier (taken out of the line, with
        the older ones), or None when none is due."""
        pending = self.pending
        command = None
        while pending and pending[0][0] <= k:
            command = pending.popleft()[1]
        return command

    def update(self, fn) -> None:
        """Replace each pending command c by fn(c) (new gains for impedance commands)."""
        self.pending = deque((at, fn(c)) for at, c in self.pending)

    def clear(self) -> None:
        self.pending.clear()
