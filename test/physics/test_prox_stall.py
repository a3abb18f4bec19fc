"""A robot lying at rest: JOR at the paper's α cycles there; the stall test ends such a try
early and the fallback α solves it (solver.stall_window), while slow but steady solves and
every converging one are left alone (test_bitexact: every preset unchanged); the fallback α
that solved a step starts the next ones while the active set stays the same
(solver.fallback_hold, SimState.prox_memory)."""
import numpy as np
import pytest

from starleth_sim import Simulator
from starleth_sim.physics.config import ConfigError
from starleth_sim.physics.posture import PostureHold

FALL_SECONDS = 3.0       # zero torques from standing: the robot collapses and comes to rest
STEPS = 80               # control steps measured at rest


def fallen(preset, **overrides):
    """A simulator of `preset` whose robot collapsed under zero torques and lies at rest."""
    sim = Simulator.from_preset(preset, **overrides)
    zero = np.zeros(len(sim.joint_names))
    for _ in range(int(round(FALL_SECONDS / sim.control_period))):
        sim.step(zero)
    return sim, zero


def lying(sim, zero, steps=STEPS):
    """(mean prox iterations per step, all converged, retried steps, base position after)
    over `steps` control steps."""
    its, converged, retried = [], True, 0
    for _ in range(steps):
        d = sim.step(zero)
        its.append(d.iterations)
        converged &= bool(d.converged)
        retried += bool(d.retried)
    return float(np.mean(its)), converged, retried, sim.q[:3].copy()


@pytest.mark.parametrize("preset", ["HmJ", "HEJP"])
def test_a_cycling_jor_retries_at_once(preset):
    sim, zero = fallen(preset, fallback_hold=0)     # every step from the paper's α
    assert sim.q[2] < 0.15               # lying on the ground, knees and trunk in contact
    assert sum(c.active for c in sim.contacts) > 4
    start = sim.snapshot()
    its, converged, retried, pos = lying(sim, zero)
    # without the test, the same state at rest: the first try runs to the iteration cap
    capped = Simulator.from_preset(preset, stall_window=0, fallback_hold=0)
    capped.restore(start)
    its_capped, converged_capped, retried_capped, pos_capped = lying(capped, zero)
    cap = sim.config.solver.max_iterations
    assert its_capped > 0.3 * cap and retried_capped > STEPS // 2
    assert its < 0.1 * cap and converged and retried > STEPS // 2
    # the same physics: both find the robot at rest where it lay (impulses within the
    # tolerance of two converged solves)
    assert np.abs(pos - pos_capped).max() < 1e-6
    assert np.abs(pos - start.q[:3]).max() < 1e-4


def test_standing_solves_never_stall():
    sim = Simulator.from_preset("HmJ")
    hold = PostureHold.for_robot(sim.description, sim.joint_positions())
    for _ in range(200):
        d = sim.step(hold.torque(sim))
        assert d.converged and not d.retried


def test_stall_window_is_validated():
    with pytest.raises(ConfigError, match="solver.stall_window"):
        Simulator.from_preset("HmJ", stall_window=-1)


def test_the_fallback_alpha_is_kept_at_rest():
    sim, zero = fallen("HmJ")
    start = sim.snapshot()
    # the memory holds the fallback: one sweep per step from the warm start, no retry but
    # the paper's α tried again once per fallback_hold steps
    its, converged, retried, pos = lying(sim, zero)
    assert its < 3.0 and converged and retried <= 1
    paper = Simulator.from_preset("HmJ", fallback_hold=0)
    paper.restore(start)
    its_paper, converged_paper, retried_paper, pos_paper = lying(paper, zero)
    assert its_paper > 10 * its and converged_paper and retried_paper > STEPS // 4
    # the same physics: both within the tolerance of two converged solves
    assert np.abs(pos - pos_paper).max() < 1e-6
    # the memory is state: a restored snapshot replays bit for bit
    sim.restore(start)
    again = lying(sim, zero)
    assert again[0] == its and np.array_equal(again[3], pos)


def test_the_paper_alpha_again_when_the_contacts_change_or_after_the_hold():
    sim = Simulator.from_preset("HmJ", fallback_hold=5)
    hold = PostureHold.for_robot(sim.description, sim.joint_positions())
    for _ in range(50):
        sim.step(hold.torque(sim))
    start = sim.snapshot()
    assert np.array_equal(start.prox_memory[:2], [1.0, 0.0])  # standing: the paper's α
    start.prox_memory[:2] = (0.5, 2.0)                        # as if a fallback solved it
    sim.restore(start)
    sim.step(hold.torque(sim))                               # the same 4 feet: kept
    assert np.array_equal(sim.state.prox_memory[:2], [0.5, 3.0])
    start.prox_memory[:2] = (0.5, 5.0)                        # held for fallback_hold steps
    sim.restore(start)
    sim.step(hold.torque(sim))
    assert np.array_equal(sim.state.prox_memory[:2], [1.0, 0.0])
    start.prox_memory[:2] = (0.5, 2.0)
    start.last_active[np.flatnonzero(start.last_active)[0]] = False   # another active set
    sim.restore(start)
    sim.step(hold.torque(sim))
    assert np.array_equal(sim.state.prox_memory[:2], [1.0, 0.0])


def test_fallback_hold_is_validated():
    with pytest.raises(ConfigError, match="solver.fallback_hold"):
        Simulator.from_preset("HmJ", fallback_hold=-1)


@pytest.mark.parametrize("preset", ["HmJ", "HmS"])        # JOR (no M⁻¹W either) and SOR
def test_a_solve_of_one_sweep_leaves_g_unformed_with_the_same_physics(preset):
    """With the same active set after a solve of one sweep, the next one tries a few in the
    velocity form first (G = WᵀM⁻¹W and M⁻¹W not formed; SimState.prox_memory[2]: the last
    solve's sweeps): at rest it converges there, to the Delassus form's motion."""
    sim, zero = fallen(preset)
    start = sim.snapshot()
    delassus = Simulator.from_preset(preset)
    delassus.restore(start)
    for _ in range(STEPS):
        sim.step(zero)
        delassus.state.prox_memory[2] = np.inf      # (no probe: G formed every step)
        delassus.step(zero)
    assert sim.state.prox_memory[2] == 1 and sim.diagnostics.converged
    assert np.abs(sim.q - delassus.q).max() < 1e-6
    assert np.abs(sim.contact_impulses() - delassus.contact_impulses()).max() < 1e-5
