"""The control period of one C call (kernels.ControlPeriod.step) against the general path
(Simulator._control_period, one MoreauStepper.step per physics step, the record written from
Python): the same states, Λ, commands and Diagnostics bit for bit, the cumulative counts
continued across the two, and bad torques rejected by both with the state unchanged."""
import numpy as np
import pytest

from starleth_sim.physics.posture import PostureHold
from starleth_sim.physics.simulator import Simulator

FIELDS = ("iterations", "max_iterations_step", "converged", "status", "residual",
          "active_contacts", "retried", "loaded_contacts_opened", "projection_iterations",
          "projections", "physics_steps", "nonconverged_steps", "loaded_contacts_opened_total")


def general_path(sim):
    """A simulator whose periods all take the general path: a pending wrench of zero for the
    whole run (its generalized force J^T 0 adds nothing) makes a period more than one kernel
    call."""
    sim.apply_wrench(sim.coords.link_names()[0], (0.0, 0.0, 0.0), duration=1e6)
    return sim


def figures(d):
    return tuple(getattr(d, f) for f in FIELDS)


@pytest.mark.parametrize("preset", ["HmJ", "Cm"])
def test_one_call_and_general_periods_agree_bit_for_bit(preset):
    one, general = Simulator.from_preset(preset), general_path(Simulator.from_preset(preset))
    hold = PostureHold.for_robot(one.description, one.joint_positions())
    active = set()
    for k in range(300):
        tau = hold.torque(one)
        if k % 50 == 7:
            tau = tau + 40.0 * np.sin(np.arange(tau.size) + k)    # a kick: contacts open
        d1, d2 = one.step(tau), general.step(tau.copy())
        assert figures(d1) == figures(d2), k
        active.add(d1.active_contacts)
        assert one.state.q.tobytes() == general.state.q.tobytes(), k
        assert one.state.u.tobytes() == general.state.u.tobytes(), k
        assert one.t == general.t
    assert len(active) > 1                     # the kicks opened and closed contacts
    assert not one.state.pending_wrenches and general.state.pending_wrenches
    np.testing.assert_array_equal(one.contact_impulses(), general.contact_impulses())
    np.testing.assert_array_equal(one.last_command, general.last_command)
    assert one.diagnostics.physics_steps == 300 * one.config.steps_per_control


def test_the_command_is_a_copy_taken_before_the_step():
    sim = Simulator.from_preset("HmJ")
    tau = np.zeros(len(sim.joint_names))
    sim.step(tau)
    recorded = sim.last_command
    tau[:] = 5.0                                  # the caller reuses its buffer
    assert not np.shares_memory(recorded, tau)
    np.testing.assert_array_equal(sim.last_command, np.zeros(len(sim.joint_names)))


def test_counts_continue_across_the_two_paths():
    """Periods alternating between one call and the general path (a wrench applied for one
    period) count every physics step once, and the report of each is its own."""
    sim = Simulator.from_preset("HmJ")
    hold = PostureHold.for_robot(sim.description, sim.joint_positions())
    link = sim.coords.link_names()[0]
    for k in range(40):
        if k % 3 == 0:
            sim.apply_wrench(link, (0.0, 0.0, -20.0), duration=sim.control_period)
        d = sim.step(hold.torque(sim))
        assert d.physics_steps == k + 1
    assert sim.diagnostics.nonconverged_steps == 0


def test_other_torque_types_take_the_same_result():
    """A list, float32 or a strided view give what the float64 vector gives (the general
    path converts them; the one call takes only a plain float64 vector)."""
    sims = [Simulator.from_preset("HmJ") for _ in range(5)]
    hold = PostureHold.for_robot(sims[0].description, sims[0].joint_positions())
    for _ in range(20):
        tau = hold.torque(sims[0])
        wide = np.repeat(tau, 2)
        sims[0].step(tau)
        sims[1].step(list(tau))
        sims[2].step(wide[::2])
        sims[3].step(tau.astype(np.float32))                  # (converted exactly)
        sims[4].step(tau.astype(np.float32).astype(np.float64))
    for s in sims[1:3]:
        assert s.state.q.tobytes() == sims[0].state.q.tobytes()
    assert sims[3].state.q.tobytes() == sims[4].state.q.tobytes()


@pytest.mark.parametrize("bad", [
    lambda n: np.full(n, np.nan), lambda n: np.r_[np.zeros(n - 1), np.inf],
    lambda n: np.zeros(n + 1), lambda n: np.zeros((n, 1)), lambda n: "twelve" * n])
def test_bad_torques_raise_with_the_state_unchanged(bad):
    sim = Simulator.from_preset("HmJ")
    sim.step(np.zeros(len(sim.joint_names)))
    q, u, t, steps = sim.state.q.copy(), sim.state.u.copy(), sim.t, sim.diagnostics.physics_steps
    with pytest.raises(ValueError):
        sim.step(bad(len(sim.joint_names)))
    assert sim.state.q.tobytes() == q.tobytes() and sim.state.u.tobytes() == u.tobytes()
    assert sim.t == t and sim.diagnostics.physics_steps == steps
    sim.step(np.zeros(len(sim.joint_names)))     # and it goes on
    assert sim.diagnostics.physics_steps == steps + 1


@pytest.mark.parametrize("preset", ["HmJ", "Cm", "HMJD"])
@pytest.mark.parametrize("how", ["pickle", "deepcopy"])
def test_a_copied_simulator_goes_on_as_the_original(preset, how):
    """A Simulator pickled or deep-copied mid-run (a timed wrench pending) has the original's
    last reports and record, and steps on bit for bit as the original does."""
    import copy
    import pickle
    sim = Simulator.from_preset(preset)
    hold = PostureHold.for_robot(sim.description, sim.joint_positions())
    for _ in range(30):
        sim.step(hold.torque(sim))
    sim.apply_wrench(sim.coords.link_names()[0], (5.0, 0.0, 0.0), duration=0.05)
    sim.step(hold.torque(sim))
    other = pickle.loads(pickle.dumps(sim)) if how == "pickle" else copy.deepcopy(sim)
    np.testing.assert_array_equal(other.contact_impulses(), sim.contact_impulses())
    np.testing.assert_array_equal(other.contact_points(), sim.contact_points())
    assert figures(other.diagnostics) == figures(sim.diagnostics)
    for _ in range(30):
        d1, d2 = sim.step(hold.torque(sim)), other.step(hold.torque(other))
        assert figures(d1) == figures(d2)
    assert other.state.q.tobytes() == sim.state.q.tobytes()
    np.testing.assert_array_equal(other.contact_forces(), sim.contact_forces())
    np.testing.assert_array_equal(other.joint_velocities(), sim.joint_velocities())


def test_a_stepper_alone_is_not_copied():
    import copy
    sim = Simulator.from_preset("HmJ")
    with pytest.raises(TypeError, match="Simulator"):
        copy.deepcopy(sim.stepper)
