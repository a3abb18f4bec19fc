"""The simulation state (starleth_sim.physics.state.SimState): a snapshot is a deep copy,
restoring one replays the same steps bit for bit, and a SimulationError rolls the state
back; the profiled step (per-phase timings) runs the same code path as the plain one."""
import numpy as np
import pytest

from starleth_sim import Simulator, SimulationError


def pd(sim, q_stand):
    return 120.0 * (q_stand - sim.joint_positions()) - 3.0 * sim.joint_velocities()


def run(sim, q_stand, n):
    out = []
    for _ in range(n):
        sim.step(pd(sim, q_stand))
        out.append(np.concatenate([sim.q, sim.u, np.ravel([c.impulse for c in sim.contacts])]))
    return np.array(out)


@pytest.mark.parametrize("preset", ["HmJ", "Cm", "HEJD"])
def test_restore_replays_bit_for_bit(preset):
    sim = Simulator.from_preset(preset)
    q_stand = sim.joint_positions().copy()
    run(sim, q_stand, 20)
    sim.apply_wrench("base", (30.0, 0.0, 0.0), duration=0.02)   # a timed wrench in flight
    run(sim, q_stand, 2)
    snap = sim.snapshot()
    t0, qd0 = sim.t, sim.joint_velocities()
    first = run(sim, q_stand, 15)
    assert snap.t == t0 and not np.shares_memory(snap.q, sim.state.q)
    sim.restore(snap)
    assert sim.t == t0
    np.testing.assert_array_equal(sim.joint_velocities(), qd0)   # no stale φ̇ cache
    np.testing.assert_array_equal(run(sim, q_stand, 15), first)
    sim.restore(snap)                                             # a snapshot is reusable
    np.testing.assert_array_equal(run(sim, q_stand, 15), first)


def test_failed_step_restores_the_state():
    sim = Simulator.from_preset("HmJ")
    q_stand = sim.joint_positions().copy()
    run(sim, q_stand, 10)
    before = sim.snapshot()
    sim.state.u[:] = np.nan        # poison the state: the step must fail and roll back
    poisoned = sim.snapshot()
    with pytest.raises(SimulationError):
        sim.step(np.zeros(12))
    np.testing.assert_array_equal(sim.state.q, poisoned.q)
    assert sim.t == before.t
    np.testing.assert_array_equal(sim.state.last_impulse, before.last_impulse)


@pytest.mark.parametrize("preset", ["HmJ", "Cm", "HEJD"])
def test_profiled_step_is_the_same_step(preset):
    plain = Simulator.from_preset(preset)
    prof = Simulator.from_preset(preset, profile=True)
    q_stand = plain.joint_positions().copy()
    np.testing.assert_array_equal(run(prof, q_stand, 30), run(plain, q_stand, 30))
    timings = prof.diagnostics.timings
    assert set(timings) == {"M_and_h", "M_inverse", "G", "prox", "rest"}
    assert timings["M_and_h"] > 0 and timings["M_inverse"] > 0 and timings["rest"] > 0
    if preset != "Cm":
        assert timings["G"] > 0 and timings["prox"] > 0
    assert not plain.diagnostics.timings
