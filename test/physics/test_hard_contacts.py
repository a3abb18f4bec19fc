"""Hard contacts do not sink (issue #11): no loaded contact is dropped by the activation test
alone (contact.activation "hysteresis"), penetrations are projected out after the step
(contact.penetration_correction "projection", β_N = 1), and the impact law is untouched."""
import numpy as np
import pytest

from starleth_controller import Command, RobotState, StarlethController
from starleth_sim import ConfigError, Simulator, load_preset
from starleth_sim.physics.description import RobotDescription, sphere_urdf, urdf_path
from starleth_sim.physics.stepper import PROJECTION_TOLERANCE
from starleth_sim.tools.evaluation.tasks import ball_drop, pd_sag

HARD = ["HmJ", "HmS", "HEJD", "HEJP", "HESD", "HESP", "HMJD", "HMJP", "HMSD", "HMSP"]
#: the paper's rule: the gap test alone (g_N(q^M) ≤ 0), no penetration correction
PAPER_RULE = dict(activation="paper", activation_gap=0.0, penetration_stabilization=0.0)


@pytest.mark.parametrize("preset", HARD)
def test_sagging_posture_keeps_every_foot_out_of_the_ground(preset):
    """reset() under a soft joint PD hold: the robot sags by ~13 mm onto its feet, whose
    sphere contacts the velocity-level law lets drift up by O(Δt²) per step. No foot goes
    below the ground by 0.1 mm (measured: below the 1 µm projection tolerance), no loaded
    foot hovers above it by 1 µm, no loaded contact leaves the active set."""
    sim, out = pd_sag(preset, 2.0)
    penetration, hover, _, opened, kinetic = out.T
    assert penetration.max() < 1e-4
    assert np.nanmax(hover) < 1e-6
    assert opened.sum() == 0 and sim.diagnostics.loaded_contacts_opened_total == 0
    assert sim.diagnostics.nonconverged_steps == 0
    z = sim.base_state()["position"][2]
    assert 0.395 < z < 0.41                  # it sagged from 0.415 m and stands
    assert kinetic[-1] < 1e-6                 # and came to rest


def test_papers_gap_rule_drops_the_loaded_feet_and_they_sink():
    """The scenario is a real test: with the paper's gap test alone and no correction, the
    four loaded feet drift up, all leave the active set at once (step 4), are thrown into the
    ground by the joint torques and stay there (0.45 mm; 3.2 mm with the former 10 µm
    margin); Diagnostics counts the drop."""
    sim, out = pd_sag("HmJ", 0.5, **PAPER_RULE)
    penetration, _, _, opened, _ = out.T
    assert opened.sum() == 4 and sim.diagnostics.loaded_contacts_opened_total == 4
    assert penetration.max() > 2e-4
    assert penetration[-1] > 2e-4             # nothing corrects it


@pytest.mark.parametrize("preset", ["HmJ", "HEJD", "HMSD"])
def test_trotting_feet_stay_out_of_the_ground(preset):
    """Stand 1 s, trot at 0.3 m/s for 5 s with the controller: every foot's penetration
    after every step < 0.5 mm (measured: < 1 µm; 6.4 mm with the plain rule), no loaded
    contact dropped, and the robot trots."""
    sim = Simulator.from_preset(preset)
    ctrl = StarlethController(urdf_path())
    feet = [sim.contact_names.index(f) for f in sim.description.foot_names]
    deepest = 0.0
    projections = 0
    for k in range(int(round(6.0 / sim.control_period))):
        trot = k * sim.control_period >= 1.0
        cmd = Command(mode="trot" if trot else "stand", forward=0.3 if trot else 0.0)
        d = sim.step(ctrl.update(RobotState.from_simulator(sim), cmd))
        deepest = max(deepest, -sim.gaps()[feet].min())
        projections += d.projections
    assert deepest < 5e-4
    assert sim.diagnostics.loaded_contacts_opened_total == 0
    assert sim.diagnostics.nonconverged_steps == 0
    assert projections > 10                    # touchdowns needed the projection
    assert sim.base_state()["position"][0] > 1.2 and sim.base_state()["position"][2] > 0.38


def test_projection_leaves_the_impact_law_alone():
    """The projection moves positions only: a ball dropped from 1 m with ε_N = 0.5 leaves
    the ground with exactly ε_N v⁻ and reaches ε_N² h; a plastic drop (ε_N = 0) does not
    rebound. The velocity-level correction (β_N/Δt) min(g_N, 0) instead adds to the
    rebound velocity: the reason it is not the presets' choice."""
    v_minus, v_plus, apex = ball_drop(0.5, 1.0, {})
    assert v_minus == pytest.approx(-np.sqrt(2 * 9.81 * 1.0), rel=0.01)
    assert -v_plus / v_minus == pytest.approx(0.5, abs=1e-8)
    assert apex == pytest.approx(0.25, abs=0.005)
    _, v_plastic, h_plastic = ball_drop(0.0, 0.2, {})
    assert abs(v_plastic) < 1e-8 and h_plastic < 1e-8
    # with the velocity-level correction the plastic ball pops up
    _, v_pop, h_pop = ball_drop(0.0, 0.2, dict(penetration_correction="velocity",
                                               penetration_stabilization=1.0))
    assert v_pop > 0.1 and h_pop > 1e-4


def ball_gaps(steps, **overrides):
    """g_N after each step of a 1 kg ball (r = 0.1 m) dropped from 1 m at Δt = 1 ms with the
    HmJ contact law and `overrides`."""
    cfg = load_preset("HmJ").with_overrides(control_rate=1000.0, **overrides)
    sim = Simulator(cfg, description=RobotDescription.from_urdf_xml(sphere_urdf(0.1, 1.0)))
    q = sim.q
    q[2] += 1.0
    sim.reset(q)
    gaps = []
    for _ in range(steps):
        sim.step()
        gaps.append(sim.gaps()[0])
    return sim, np.array(gaps)


def test_ball_never_ends_a_step_below_the_ground():
    """A ball falling from 1 m meets the ground between two midpoints; the projection also
    takes in a contact outside the active set that would end the step below the ground, so
    no step ends with a penetration beyond the 1 µm projection tolerance (plus the
    linearisation error)."""
    sim, gaps = ball_gaps(1000, tol_rel=1e-10, tol_abs=1e-12)
    assert gaps.min() > -1.1 * PROJECTION_TOLERANCE
    assert abs(gaps[-1]) < 1.1 * PROJECTION_TOLERANCE and np.linalg.norm(sim.u) < 1e-9


def test_paper_rule_is_still_available():
    """activation "paper", activation_gap 0, β_N = 0 is the paper's law: the active set is
    g_N(q^M) ≤ 0 and nothing corrects a penetration (a ball dropped from 1 m ends its impact
    step below the ground)."""
    sim, gaps = ball_gaps(600, activation="paper", penetration_stabilization=0.0)
    assert sim.config.contact.activation_gap == 0.0
    assert gaps.min() < -1e-4


@pytest.mark.parametrize("field,value,message", [
    ("activation", "sticky", "contact.activation: must be one of"),
    ("penetration_correction", "baumgarte", "contact.penetration_correction: must be one of"),
    ("penetration_stabilization", 1.5, "contact.penetration_stabilization: must be <= 1"),
    ("opening_gap", -1.0, "contact.opening_gap: must be >= 0"),
])
def test_contact_rule_settings_are_validated(field, value, message):
    with pytest.raises(ConfigError, match=message):
        load_preset("HmJ").with_overrides(**{field: value})


def test_opening_gap_below_activation_gap_is_rejected():
    with pytest.raises(ConfigError, match="opening_gap: must be >= activation_gap"):
        load_preset("HmJ").with_overrides(activation_gap=1e-3, opening_gap=1e-4)


def test_motors_give_no_power_beyond_the_velocity_limit():
    """A controller that holds a saturated torque on a lifted leg cannot spin it up without
    bound: beyond the URDF velocity limit v (10 rad/s) the motor's torque in the direction of
    motion falls linearly to zero at 2v (what joint_states publishes as effort is the
    applied torque); braking torque is never derated. (In flight, the knee's rate then
    swings between 2v and ~3v as the spinning shank and the rest of the robot exchange
    momentum, and stays there.)"""
    sim = Simulator.from_preset("HmJ")
    q = sim.q
    q[2] += 10.0                                 # in the air for 1.4 s: legs swing freely
    sim.reset(q)
    tau = np.zeros(12)
    tau[2] = 20.0                                # LF knee, full torque, held
    rates = []
    for _ in range(480):
        qd = sim.joint_velocities()[2]
        sim.step(tau)
        expect = 20.0 * min(1.0, max(0.0, 2.0 - qd / 10.0)) if qd > 0 else 20.0
        assert sim.applied_torque[2] == pytest.approx(expect, abs=1e-12)
        rates.append(sim.joint_velocities()[2])
    assert sim.diagnostics.active_contacts == 0
    vmax = sim.description.velocity_limit[2]
    assert vmax == 10.0
    rates = np.array(rates)
    assert rates[:40].max() > 2 * vmax                         # spun up to about 2v ...
    assert rates[240:].max() < 1.05 * rates[:240].max() < 4 * vmax   # ... and no further
    sim.step(-tau)                               # braking torque is always applied
    assert sim.applied_torque[2] == -20.0


def test_ideal_torque_sources_when_the_velocity_limit_is_ignored():
    """actuator.velocity_limit "ignore" (the paper's ideal torque sources): the held torque
    is applied at any speed."""
    sim = Simulator.from_preset("HmJ", velocity_limit="ignore")
    q = sim.q
    q[2] += 10.0
    sim.reset(q)
    tau = np.zeros(12)
    tau[2] = 20.0
    for _ in range(60):
        sim.step(tau)
        assert sim.applied_torque[2] == 20.0
    assert sim.joint_velocities()[2] > 40.0
    with pytest.raises(ConfigError, match="actuator.velocity_limit: must be one of"):
        load_preset("HmJ").with_overrides(velocity_limit="clip")
