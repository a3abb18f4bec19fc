"""sim_node's command delay (parameter command_delay; starleth_sim/ros/command_delay.py) in
its ROS-free core, SimService: a command received at the state of step k is in effect from
step k + d on (d control periods), the previous one holding until then, on every command
interface; a delayed run is the undelayed run of the same commands shifted by d steps, bit
for bit; 0 is no delay; the rounding, the bounds, a change at run time, the gains, a reset
and the timeout policy. (Through ROS, the relay against the impedance law with the delay,
and the delayed run's replay: test_impedance_ros.py.)"""
import numpy as np
import pytest

from starleth_sim.physics.config import ConfigError
from starleth_sim.physics.impedance import ImpedanceCommand
from starleth_sim.physics.simulator import Simulator
from starleth_sim.ros.command_delay import DelayLine, delay_periods
from starleth_sim.ros.parameters import Settings
from starleth_sim.ros.service import SimService

_SIMS = {}


def service(preset="HmJ", **settings):
    sim = _SIMS.get(preset) or _SIMS.setdefault(preset, Simulator.from_preset(preset))
    sim.clear_wrenches()
    sim.reset()
    settings.setdefault("mode", "lockstep")
    return SimService(sim, Settings(realtime_start="immediately", **settings))


def commands(svc, n):
    """n distinct valid commands for every interface: torques by JointState, the effort and
    position arrays, impedance JointStates (targets about the standing posture)."""
    q0 = svc.sim.joint_positions().copy()
    out = []
    for i in range(n):
        kind = ("torque", "effort", "position", "impedance")[i % 4]
        v = np.sin(np.arange(12) + i)
        out.append((kind, 2.0 * v if kind in ("torque", "effort") else q0 + 0.05 * v))
    return out


def submit(svc, kind, values):
    if kind == "torque":
        return svc.submit_joint_command(list(svc.joint_names), values, svc.stamp_ns)
    if kind == "impedance":
        return svc.submit_joint_command([], [], svc.stamp_ns, position=values)
    return svc.submit_array(kind, values)


def run(preset, delay, sequence, steps):
    """The state (q, u) after each step of a lockstep run answering state k with
    sequence[k]."""
    svc = service(preset, command_delay=delay)
    out = []
    for k in range(steps):
        assert submit(svc, *sequence[k])[0]
        svc.step()
        out.append(np.concatenate([svc.sim.q, svc.sim.u]))
    return np.array(out)


@pytest.mark.parametrize("preset", ["HmJ", "Cm"])
def test_a_delayed_run_is_the_undelayed_run_of_its_commands_shifted(preset):
    """d = 2 (5 ms) on every command interface (Cm: two physics steps per control period):
    the states equal, bit for bit, those of a run without delay whose first two answers
    are the zero command (the command in effect before the first) and whose later answers
    are the delayed run's, two states later."""
    svc = service(preset)
    seq = commands(svc, 24)
    zero = ("effort", np.zeros(12))
    delayed = run(preset, 0.005, seq, 24)
    shifted = run(preset, 0.0, [zero, zero] + seq[:22], 24)
    assert np.array_equal(delayed, shifted)
    assert not np.array_equal(delayed, run(preset, 0.0, seq, 24))   # the delay acts


def test_the_command_in_effect_and_the_pending_ones():
    """Lockstep, d = 1: svc.command (the command in effect) changes one step after the
    answer; realtime, d = 2: of several commands received at one state the last one acts,
    two steps later."""
    svc = service(command_delay=0.0025)
    assert svc.delay.steps == 1 and svc.delay_text == "command delay 1 control period (2.5 ms)"
    tau = np.full(12, 0.5)
    assert svc.submit_array("effort", tau)[0]
    assert np.all(svc.command == 0.0) and len(svc.delay.pending) == 1
    svc.step()                                         # step 0: still the zero command
    assert np.all(svc.sim.applied_torque == 0.0) and np.all(svc.command == 0.0)
    assert svc.submit_array("effort", 2 * tau)[0]
    svc.step()                                         # step 1: the answer to state 0
    assert np.array_equal(svc.command, tau) and np.allclose(svc.sim.applied_torque, tau)

    svc = service(mode="realtime", command_delay=0.005)
    for i in range(3):
        assert svc.submit_array("effort", np.full(12, float(i)))[0]
    assert len(svc.delay.pending) == 1                 # the last one supersedes the others
    for k in range(3):
        svc.step()
        assert np.all(svc.command == (2.0 if k == 2 else 0.0)), k


def test_the_delay_in_control_periods_and_its_bounds():
    """A whole number of control periods (2.5 ms): the nearest, with a note when rounded;
    0 to 0.1 s, refused outside (at the start: the parameter's error; at run time:
    (False, reason), nothing changed)."""
    assert delay_periods(0.0, 0.0025) == (0, "command delay 0 control periods (0 ms)")
    assert delay_periods(0.0075, 0.0025)[0] == 3
    d, text = delay_periods(0.004, 0.0025)
    assert d == 2 and "5 ms" in text and "rounded" in text
    assert delay_periods(0.001, 0.0025)[0] == 0
    svc = service(command_delay=0.1)
    assert svc.delay.steps == 40
    for bad in (-0.001, 0.1001, float("nan"), "0.01"):
        ok, why = svc.set_command_delay(bad)
        assert not ok and "command_delay" in why and svc.delay.steps == 40, bad
        with pytest.raises(ConfigError, match="command_delay"):
            Settings(command_delay=bad).validate()


def test_a_change_at_run_time_keeps_the_received_commands_times():
    """Raised, the pending commands keep their steps; lowered to 0, the next command is in
    effect at once and supersedes the pending ones (a newer command never acts before an
    older one)."""
    svc = service(mode="realtime", command_delay=0.0075)        # d = 3
    assert svc.submit_array("effort", np.full(12, 1.0))[0]      # for step 3
    assert svc.set_command_delay(0.0125)[0]                     # d = 5
    svc.step()
    assert svc.submit_array("effort", np.full(12, 2.0))[0]      # received at 1: for step 6
    for k in range(1, 7):
        svc.step()
        assert np.all(svc.command == (0.0 if k < 3 else 1.0 if k < 6 else 2.0)), k
    assert svc.submit_array("effort", np.full(12, 3.0))[0]      # for step 12
    assert svc.set_command_delay(0.0)[0]
    assert svc.submit_array("effort", np.full(12, 4.0))[0]      # now, superseding 3
    svc.step()
    assert np.all(svc.command == 4.0) and not svc.delay.pending
    for _ in range(6):
        svc.step()
        assert np.all(svc.command == 4.0)


def test_gains_reset_and_timeout_with_commands_pending():
    """New gains reach the pending impedance commands too (they act with the gains of the
    time they act); a reset drops the pending commands (zero command); the timeout policy
    zero is the missing answer, delayed as an answer would be."""
    svc = service(command_delay=0.005, default_kp=80.0, default_kd=2.0)
    q = svc.sim.joint_positions().copy()
    assert svc.submit_joint_command([], [], svc.stamp_ns, position=q)[0]
    assert svc.set_gains(40.0, 1.0)[0]
    svc.step()
    svc.step(timed_out=True)
    svc.step()                                                  # step 2: the answer to 0
    c = svc.command
    assert type(c) is ImpedanceCommand and np.all(c.kp == 40.0) and np.all(c.kd == 1.0)
    assert svc.submit_array("effort", np.ones(12))[0]
    svc.reset()
    assert np.all(svc.command == 0.0) and not svc.delay.pending
    for _ in range(3):
        svc.step(timed_out=True)
        assert np.all(svc.command == 0.0)

    svc = service(command_delay=0.0025, timeout_policy="zero")
    assert svc.submit_array("effort", np.ones(12))[0]
    svc.step()
    svc.step(timed_out=True)                                    # acts: the answer to 0
    assert np.all(svc.command == 1.0)
    svc.step()                                                  # the zero of the timeout
    assert np.all(svc.command == 0.0)


def test_the_line_keeps_at_most_d_plus_one_commands():
    line = DelayLine(3)
    for k in range(100):
        line.put(k, k)
        line.put(k, -k)                 # a second command at the same state supersedes
        assert line.due(k) == (-(k - 3) if k >= 3 else None)
        assert len(line.pending) <= 4
