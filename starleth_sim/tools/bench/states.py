"""``starleth-bench --states``: the cost of a physics step in the three states a simulated
robot spends its time in, per preset, side by side in one process.

- standing: the robot on its feet under the joint PD posture hold (``PostureHold``);
- trotting: the controller (``StarlethController``) trotting at its speed, one second into
  the trot;
- fallen: the robot lying on the ground after a collapse under zero torques (feet, knees and
  trunk corners in contact, at rest), what every fall of a push-recovery sweep, a controller
  under development or a learning rollout leaves behind.

Each state starts from its own saved start (simulator snapshot, and the controller's copy
when trotting), made once; every round restores it and times `steps` control steps, only
``Simulator.step`` on the clock (the controller and the hold untimed). The rounds go preset
by preset and state by state in turn, so that the machine's drift spreads over all of them;
the figure of a cell is the median of its rounds: µs per physics step, and the mean prox
iterations per physics step. ``fallen / standing`` is the ratio the issue bounds (≤ 3).
"""
from __future__ import annotations

import copy
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from starleth_controller import Command, RobotState, StarlethController
from starleth_controller.robot_params import trot_speed

from ...physics.posture import PostureHold
from ...physics.simulator import Simulator

STATES = ("standing", "trotting", "fallen")
#: simulated seconds before a state's start is saved: the hold settles, the trot is one
#: second old (after a second of standing), the collapse has come to rest
STANDING_SETTLE, TROT_STAND, TROT_WARM, FALL_SETTLE = 0.25, 1.0, 1.0, 3.0


@dataclass
class StateStart:
    """A state's start: the simulator, its snapshot and the torque source of each step
    (`torque(sim)`; for the trot a fresh copy of the saved controller every round)."""

    sim: Simulator
    snapshot: object
    make_torque: object        # () -> (sim -> torques)


def _settle(sim, torque, seconds):
    for _ in range(int(round(seconds / sim.control_period))):
        sim.step(torque(sim))


def standing_start(preset, robot=None) -> StateStart:
    sim = Simulator.from_preset(preset, robot=robot)
    hold = PostureHold.for_robot(sim.description, sim.joint_positions())
    _settle(sim, hold.torque, STANDING_SETTLE)
    return StateStart(sim, sim.snapshot(), lambda: hold.torque)


def fallen_start(preset, robot=None) -> StateStart:
    sim = Simulator.from_preset(preset, robot=robot)
    zero = np.zeros(len(sim.joint_names))
    _settle(sim, lambda _sim: zero, FALL_SETTLE)
    return StateStart(sim, sim.snapshot(), lambda: (lambda _sim: zero))


def trotting_start(preset, robot=None) -> StateStart:
    sim = Simulator.from_preset(preset, robot=robot)
    ctrl = StarlethController(robot=robot or "starleth")
    stand = Command(mode="stand")
    trot = Command(mode="trot", forward=trot_speed(ctrl.model.scale))
    _settle(sim, lambda s: ctrl.update(RobotState.from_simulator(s), stand), TROT_STAND)
    _settle(sim, lambda s: ctrl.update(RobotState.from_simulator(s), trot), TROT_WARM)
    saved = copy.deepcopy(ctrl)

    def make_torque():
        c = copy.deepcopy(saved)
        return lambda s: c.update(RobotState.from_simulator(s), trot)
    return StateStart(sim, sim.snapshot(), make_torque)


STARTS = {"standing": standing_start, "trotting": trotting_start, "fallen": fallen_start}


def time_round(start: StateStart, steps: int) -> tuple[float, float]:
    """(µs per physics step, prox iterations per physics step) of `steps` control steps
    from `start` (only Simulator.step timed)."""
    sim = start.sim
    sim.restore(start.snapshot)
    torque = start.make_torque()
    wall, iterations = 0.0, 0
    for _ in range(steps):
        tau = torque(sim)
        t0 = time.perf_counter()
        d = sim.step(tau)
        wall += time.perf_counter() - t0
        iterations += d.iterations
    n = steps * sim.config.steps_per_control
    return 1e6 * wall / n, iterations / n


@dataclass
class StateCell:
    us: list = field(default_factory=list)
    iterations: list = field(default_factory=list)

    @property
    def median_us(self) -> float:
        return float(np.median(self.us)) if self.us else float("nan")

    @property
    def median_iterations(self) -> float:
        return float(np.median(self.iterations)) if self.iterations else float("nan")


def measure_states(presets, rounds: int, steps: int, robot=None, states=STATES):
    """{preset: {state: StateCell}} over `rounds` interleaved rounds."""
    starts = {p: {s: STARTS[s](p, robot) for s in states} for p in presets}
    for start in (st for by_state in starts.values() for st in by_state.values()):
        time_round(start, 5)        # warm-up: first calls, caches
    cells = {p: {s: StateCell() for s in states} for p in presets}
    for _ in range(rounds):
        for p in presets:
            for s in states:
                us, it = time_round(starts[p][s], steps)
                cells[p][s].us.append(us)
                cells[p][s].iterations.append(it)
    return cells


def print_states(presets, rounds: int, steps: int, robot=None) -> int:
    """The table of --states; exit status 0."""
    name = robot or "StarlETH"
    print(f"{name}: µs per physics step standing / trotting / fallen, {rounds} interleaved "
          f"rounds x {steps} control steps (median), prox iterations per step in brackets; "
          f"Python {sys.version.split()[0]}")
    print(f"{'config':7s} {'standing':>16s} {'trotting':>16s} {'fallen':>16s} "
          f"{'fallen/standing':>15s}")
    cells = {}
    for p in presets:         # one preset at a time: its rounds interleave its states
        cells.update(measure_states([p], rounds, steps, robot))
        row = cells[p]
        text = " ".join(f"{row[s].median_us:7.1f} ({row[s].median_iterations:6.1f})"
                        for s in STATES)
        ratio = row["fallen"].median_us / row["standing"].median_us
        print(f"{p:7s} {text} {ratio:15.2f}", flush=True)
    return 0
