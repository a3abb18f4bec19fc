"""Inputs that must not take the simulation down (issue #33, items 4, 5 and 7), at the
ROS-free SimService: pushes beyond max_wrench_force / max_wrench_torque, a step that moves
the base further than physics can (not a state: not published, the service pauses with the
reason), a reset in the middle of a lockstep exchange, and names a megabyte long."""
import numpy as np
import pytest

from starleth_sim.ros.parameters import Settings
from starleth_sim.ros.service import SimService, quoted


@pytest.fixture(scope="module")
def sim():
    from starleth_sim import Simulator
    return Simulator.from_preset("HmJ")


def make(sim, **kw):
    warnings = []
    svc = SimService(sim, Settings(**kw), warn=warnings.append, error=warnings.append)
    return svc, warnings


def test_a_push_beyond_max_wrench_is_rejected_with_a_warning(sim):
    """|F| just over max_wrench_force (or |M| over max_wrench_torque) is refused, counted and
    named in a warning; just under is taken. The limit is on the norm, not per axis."""
    svc, warns = make(sim, warn_throttle_period=0.0)
    f = 5000.0 / np.sqrt(3.0)
    assert svc.submit_wrench("base", (f * 0.999,) * 3, (0, 0, 0))[0]
    ok, why = svc.submit_wrench("base", (f * 1.001,) * 3, (0, 0, 0))
    assert not ok and "max_wrench_force 5000" in why and "5e+03" in why or "5005" in why
    ok, why = svc.submit_wrench("base", (0, 0, 0), (0, 0, 1000.5), persistent=True)
    assert not ok and "max_wrench_torque 1000" in why
    assert svc.counters["wrenches_rejected"] == 2 and svc.counters["wrenches_accepted"] == 1
    assert sum("rejected wrench" in w for w in warns) == 2
    svc2, _ = make(sim, max_wrench_force=1e4)
    assert svc2.submit_wrench("base", (0, 0, 9000.0), (0, 0, 0))[0]
    svc.reset()
    svc2.reset()


def test_a_step_that_moves_the_base_beyond_physics_is_not_a_state(sim):
    """A 1e9 N push (given to the simulator directly: max_wrench_force refuses it) moves the
    base hundreds of metres in 2.5 ms: step() returns None (nothing to publish), k does not
    advance, the service pauses with the reason; it neither resumes nor steps until reset,
    which recovers."""
    svc, warns = make(sim, warn_throttle_period=0.0)
    assert not svc.submit_wrench("base", (0, 0, 1e9), (0, 0, 0))[0]
    x0 = sim.root_position()
    assert svc.step() is not None and svc.k == 1
    sim.apply_wrench("base", (0, 0, 1e9), (0, 0, 0))
    assert svc.step() is None
    assert svc.k == 1 and svc.paused and svc.failed
    assert "the base moved" in svc.pause_reason and "not physics" in svc.pause_reason
    moved = float(svc.pause_reason.split("moved ")[1].split(" m")[0])
    assert moved > SimService.MAX_BASE_SPEED * sim.control_period
    assert any("simulation paused, call ~/reset" in w for w in warns)
    assert svc.step() is None and svc.k == 1          # no stepping on from there
    svc.reset()
    assert not svc.failed and not svc.paused and svc.pause_reason == ""
    assert np.allclose(sim.root_position(), x0)
    d = svc.step()
    assert d is not None and svc.k == 3
    assert abs(sim.root_position()[2] - x0[2]) < 0.01


def test_an_ordinary_fall_is_physics(sim):
    """The check does not trip on real motion: a drop from 2 m lands (z well below 2 m)
    without a pause."""
    svc, _ = make(sim, initial_state="{base_position: [0, 0, 2.0]}")
    from starleth_sim.ros.state_io import parse_initial_state
    q0, u0, _ = parse_initial_state("{base_position: [0, 0, 2.0]}", sim)
    svc = SimService(sim, Settings(), q0=q0, u0=u0)
    for _ in range(400):
        assert svc.step() is not None, svc.pause_reason
    assert sim.root_position()[2] < 0.6 and not svc.paused
    svc.reset()


def test_a_reset_during_a_lockstep_exchange(sim):
    """The documented rule: the reset state (stamp t_(k+1)) needs its own answer; an answer
    to the earlier stamp, before or after the reset, is dropped as stale; a command taken
    but not yet stepped is discarded (the reset zeroes the command)."""
    svc, _ = make(sim, mode="lockstep", real_time_factor=0.0)
    names = list(sim.joint_names)
    assert svc.submit_joint_command(names, [1.0] * 12, stamp_ns=0)[0]
    svc.step()                                           # state 1, t = 2.5 ms
    t1 = svc.stamp_ns
    assert svc.submit_joint_command(names, [2.0] * 12, stamp_ns=t1)[0] and svc.answered
    svc.reset()                                          # before the step: answer discarded
    assert not svc.answered and np.all(svc.command == 0.0) and svc.stamp_ns == 2 * t1
    ok, why = svc.submit_joint_command(names, [3.0] * 12, stamp_ns=t1)   # the old stamp
    assert not ok and why == "stale" and not svc.answered
    assert svc.submit_joint_command(names, [4.0] * 12, stamp_ns=svc.stamp_ns)[0]
    svc.step()
    assert np.all(sim.applied_torque == 4.0)
    svc.reset()


def test_names_a_megabyte_long_make_a_short_warning(sim):
    """A 1 MB joint name (or link name) is cut in the warning: a line of a few hundred
    characters, not a megabyte."""
    svc, warns = make(sim, warn_throttle_period=0.0)
    huge = "j" * 1_000_000
    ok, why = svc.submit_joint_command([huge] + list(sim.joint_names[1:]), [0.0] * 12)
    assert not ok and "unknown joint" in why and "1000000 characters" in why
    assert len(why) < 1500, len(why)
    ok, why = svc.submit_wrench(huge, (0, 0, 1), (0, 0, 0))
    assert not ok and len(why) < 1500
    assert max(len(w) for w in warns) < 1500
    assert quoted(["a"] * 20).endswith("and 15 more")
