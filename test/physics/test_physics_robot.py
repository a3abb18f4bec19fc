"""StarlETH standing on flat ground under a joint PD posture hold, for each contact model."""
import numpy as np
import pytest

from starleth_sim import Simulator
from starleth_sim.physics.posture import PostureHold

G = 9.81


def stand(preset, seconds, **overrides):
    sim = Simulator.from_preset(preset, **overrides)
    hold = PostureHold(sim.joint_positions())
    weight = sim.description.total_mass * G
    feet = [sim.contact_names.index(f) for f in sim.description.foot_names]
    history = []
    for _ in range(int(round(seconds / sim.control_period))):
        d = sim.step(hold.torque(sim))
        cs = sim.contacts
        history.append((sim.t, sum(c.impulse[2] for c in cs), min(sim.gaps()[feet]),
                        np.linalg.norm(sim.q[3:7]), d.converged, sim.q[2]))
    return sim, np.array(history), weight


@pytest.mark.parametrize("preset", ["HmJ", "HmS"])
def test_hard_contact_standing_balances_weight_without_penetration(preset):
    sim, hist, weight = stand(preset, 6.0)
    t, impulse_z, min_gap, qnorm, conv, z = hist.T
    settled = t > 4.0  # the posture PD's sway has decayed
    assert conv.all()
    # Σ Λ_N per step = m g Δt once the trunk is at rest
    np.testing.assert_allclose(impulse_z[settled], weight * sim.dt, rtol=1e-4)
    assert min_gap.min() > -1e-4          # penetration < 0.1 mm over 6 s
    assert np.abs(qnorm - 1.0).max() < 1e-12
    assert z[-1] > 0.39                   # still standing
    # only the four feet touch
    active = [c.name for c in sim.contacts if c.active]
    assert sorted(active) == sorted(sim.description.foot_names)


def test_compliant_standing_sinks_by_weight_over_four_springs():
    sim, hist, weight = stand("Cm", 6.0)
    t, impulse_z, min_gap, qnorm, conv, z = hist.T
    c_n = sim.config.contact.stiffness_normal
    feet = [sim.contact_names.index(f) for f in sim.description.foot_names]
    sink = -sim.gaps()[feet]
    assert sink.mean() == pytest.approx(weight / (4 * c_n), rel=0.2)
    # force balance (averaged over the control period)
    np.testing.assert_allclose(impulse_z[t > 5.0] / sim.control_period, weight, rtol=1e-3)
    assert sim.config.steps_per_control == 2 and sim.dt == pytest.approx(1.25e-3)


@pytest.mark.parametrize("preset", ["HmJ", "HmS", "Cm"])
def test_profiled_and_fused_paths_give_identical_trajectories(preset):
    """The Fig. 7 timing path calls the solver phases one by one; the hot path calls them in
    one jitted function. Both must produce the same state, bit for bit."""
    runs = []
    for profile in (False, True):
        sim = Simulator.from_preset(preset, profile=profile)
        q = sim.q
        q[2] += 0.05  # a drop: impacts, then standing
        sim.reset(q)
        hold = PostureHold(sim.joint_positions())
        for _ in range(200):
            sim.step(hold.torque(sim))
        runs.append((sim.q, sim.u, [c.impulse for c in sim.contacts]))
        if profile:
            assert sum(sim.diagnostics.timings.values()) > 0
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    np.testing.assert_array_equal(runs[0][1], runs[1][1])
    np.testing.assert_array_equal(np.array(runs[0][2]), np.array(runs[1][2]))


@pytest.mark.parametrize("preset", ["HmJ", "Cm", "HESD", "HMSP"])
def test_prepared_step_gives_the_same_trajectory_bit_for_bit(preset):
    """Simulator.prepare() does the torque-independent part of the next step ahead (the
    lockstep node calls it while the controller works). A step after prepare() must give
    exactly the state a step without it gives, also with a push and a torque that differs
    from the one in effect when preparing; a prepare() for a state that was then replaced
    (reset) must not be used."""
    runs = []
    for prepare in (False, True):
        sim = Simulator.from_preset(preset)
        q = sim.q
        q[2] += 0.03  # a drop: impacts, then standing
        sim.reset(q)
        hold = PostureHold(sim.joint_positions())
        rng = np.random.default_rng(3)
        for k in range(120):
            tau = hold.torque(sim) + 5.0 * rng.standard_normal(sim.n_joints)
            if prepare:
                sim.prepare()
            if k == 40:
                sim.apply_wrench("base", [30.0, -10.0, 0.0], [0.0, 2.0, 1.0])
            if k == 80:       # prepared for a state that reset() then replaces
                q_now, u_now = sim.q, sim.u
                sim.reset(q_now, u_now * 0.5, t=sim.t)
                u_half = sim.u
                sim.reset(q_now, u_half, t=sim.t)
            sim.step(tau)
        runs.append((sim.q, sim.u, np.array([c.impulse for c in sim.contacts]),
                     np.array([c.position for c in sim.contacts])))
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)
    assert np.abs(runs[0][2]).sum() > 0     # the feet were in contact


def test_contact_arrays_equal_the_contact_records():
    """Simulator.contact_points(), contact_forces() and contact_states() (what sim_node's
    contact markers read every few steps) give the values of the ContactInfo records of
    `contacts`, bit for bit, standing and after a push."""
    from starleth_sim.physics.simulator import CONTACT_STATES
    sim = Simulator.from_preset("HmJ")
    hold = PostureHold(sim.joint_positions())
    seen = set()
    for k in range(200):
        if k == 100:
            sim.apply_wrench("base", [150.0, 0.0, 0.0], duration=0.05)
        sim.step(hold.torque(sim))
        records = sim.contacts
        np.testing.assert_array_equal(sim.contact_points(), [c.position for c in records])
        np.testing.assert_array_equal(sim.contact_forces(), [c.force for c in records])
        states = [CONTACT_STATES[i] for i in sim.contact_states()]
        assert states == [c.state for c in records]
        seen.update(states)
    assert {"open", "stick"} <= seen
