"""Configuration validation and the public API's handling of bad input."""
import math

import numpy as np
import pytest
import yaml

from starleth_sim import ConfigError, Simulator, available_presets, load_preset
from starleth_sim.physics.stepper import SimulationError


def test_paper_presets_load_with_table1_parameters():
    assert {"Cm", "HmJ", "HmS"} <= set(available_presets())
    hmj, hms, cm = load_preset("HmJ"), load_preset("HmS"), load_preset("Cm")
    assert (hmj.solver.scheme, hmj.solver.alpha, hmj.contact_model) == ("jor", 0.6, "hard")
    assert (hms.solver.scheme, hms.solver.alpha) == ("sor", 0.6)
    assert cm.contact_model == "compliant" and cm.steps_per_control == 2
    assert cm.contact.stiffness_normal == 30000 and cm.contact.damping_normal == 50
    for c in (hmj, hms, cm):
        assert c.ground.mu == 0.8 and c.contact.restitution_normal == 0.0
        assert c.solver.tol_rel == 1e-6 and c.solver.tol_abs == 1e-6
        assert c.control_rate == 400.0


def write(tmp_path, data):
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(data) if not isinstance(data, str) else data)
    return str(p)


@pytest.mark.parametrize("change,message", [
    ({"solver": {"alpha": 2.5}}, "solver.alpha"),
    ({"solver": {"alpha": "fast"}}, "solver.alpha: expected a number"),
    ({"solver": {"scheme": "gauss"}}, "solver.scheme: must be one of"),
    ({"solver": {"max_iterations": 0}}, "solver.max_iterations"),
    ({"ground": {"mu": -0.1}}, "ground.mu"),
    ({"ground": {"normal": [0, 0]}}, "ground.normal"),
    ({"ground": {"normal": [0, 0, 0]}}, "ground.normal"),
    ({"contact": {"stiffness_normal": 0}}, "contact.stiffness_normal"),
    ({"contact": {"restitution_normal": 1.5}}, "contact.restitution_normal"),
    ({"contact": {"stifness_normal": 1}}, "unknown field 'contact.stifness_normal'"),
    ({"steps_per_control": 1.5}, "steps_per_control: expected an integer"),
    ({"control_rate": float("nan")}, "control_rate: must be finite"),
    ({"contact_model": "soft"}, "contact_model"),
    ({"bilateral": {"method": "direct"}}, "bilateral.method"),
    ({"solvr": {}}, "unknown field 'solvr'"),
])
def test_malformed_config_names_the_field(tmp_path, change, message):
    data = load_preset("HmJ").to_dict()
    for k, v in change.items():
        if isinstance(v, dict) and isinstance(data.get(k), dict):
            data[k].update(v)
        else:
            data[k] = v
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")) as e:
        load_preset(write(tmp_path, data))
    assert "bad.yaml" in str(e.value)


def test_invalid_yaml_and_unknown_preset_are_clear_errors(tmp_path):
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_preset(write(tmp_path, "solver: [alpha: 1\n"))
    with pytest.raises(ConfigError, match="expected a mapping"):
        load_preset(write(tmp_path, "- 1\n- 2\n"))
    with pytest.raises(ConfigError, match="unknown physics preset 'HmX'.*HmJ"):
        load_preset("HmX")


def test_overrides_flat_and_dotted_and_validated():
    c = load_preset("HmJ").with_overrides(alpha=0.3, **{"ground.mu": 0.5}, control_rate=1000.0)
    assert (c.solver.alpha, c.ground.mu, c.dt) == (0.3, 0.5, 1e-3)
    with pytest.raises(ConfigError, match="override 'alfa'"):
        load_preset("HmJ").with_overrides(alfa=0.3)
    with pytest.raises(ConfigError, match="solver.alpha"):
        Simulator.from_preset("HmJ", alpha=0.0)


@pytest.fixture(scope="module")
def sim():
    return Simulator.from_preset("HmJ")


@pytest.mark.parametrize("tau,message", [
    (np.zeros(11), "12 entries"),
    (np.zeros(13), "12 entries"),
    (np.r_[np.zeros(11), np.nan], "non-finite entries for RH_KFE"),
    (np.r_[np.inf, np.zeros(11)], "non-finite entries for LF_HAA"),
    (np.zeros((3, 4)), r"must be a vector, got an array of shape \(3, 4\)"),
    (np.zeros((1, 12)), r"must be a vector, got an array of shape \(1, 12\)"),
    (np.ones(12, dtype=complex), "must be real numbers, got complex128 values"),
    (np.ones(12, dtype=bool), "must be real numbers, got bool values"),
    ([True] * 12, "must be real numbers, got bool values"),
    (["1"] * 12, "must be real numbers, got <U1 values"),
    ([0.0] * 11 + [[0.0]], "must be real numbers, got a ragged list"),
])
def test_bad_torque_raises_and_leaves_state_unchanged(sim, tau, message):
    sim.reset()
    sim.step(np.zeros(12))
    q, u, t = sim.q, sim.u, sim.t
    with pytest.raises(ValueError, match=message):
        sim.step(tau)
    assert sim.t == t
    np.testing.assert_array_equal(sim.q, q)
    np.testing.assert_array_equal(sim.u, u)
    sim.step(np.zeros(12))  # and it keeps working
    assert sim.t > t


@pytest.mark.parametrize("t,message", [
    (math.nan, "t must be finite, got nan"), (math.inf, "t must be finite, got inf"),
    (-math.inf, "t must be finite, got -inf"),
    pytest.param(10 ** 400, "t must be finite, got inf", id="10**400"),
    ("0.5", "t must be a number of seconds, got '0.5'"),
    (True, "t must be a number of seconds, got True"),
])
def test_reset_refuses_a_time_that_is_not_a_finite_number(sim, t, message):
    """(a NaN time was taken, and stayed NaN at every later step)"""
    sim.reset(t=1.0)
    q = sim.q
    with pytest.raises(ValueError, match=f"^reset: {message}$"):
        sim.reset(q, t=t)
    assert sim.t == 1.0
    sim.reset(q, t=np.float32(0.5))
    sim.step(np.zeros(12))
    assert sim.t == 0.5 + sim.control_period


def test_reset_refuses_a_state_that_is_not_real_numbers(sim):
    q, u = sim.q, sim.u
    with pytest.raises(ValueError, match="reset: q must be real numbers, got complex128"):
        sim.reset(q.astype(complex), u)
    with pytest.raises(ValueError, match=r"reset: u must be a vector, got an array of shape"):
        sim.reset(q, u.reshape(3, -1))


def test_step_applied_and_impedance_commands_refuse_complex_and_bool_arrays(sim):
    from starleth_sim.physics.impedance import ImpedanceCommand
    sim.reset()
    with pytest.raises(ValueError, match="step_applied: torques must be real numbers, got "
                                         "complex128"):
        sim.step_applied(np.zeros((1, 12), dtype=complex))
    with pytest.raises(ValueError, match="ImpedanceCommand: kp must be real numbers, got bool"):
        ImpedanceCommand.create(sim.joint_names, position=np.zeros(12), kp=[True] * 12)
    with pytest.raises(ValueError, match=r"ImpedanceCommand: position must be a number or a "
                                         r"vector, got an array of shape \(3, 4\)"):
        ImpedanceCommand.create(sim.joint_names, position=np.zeros((3, 4)))


def test_timed_wrenches_pending_are_bounded():
    """At most MAX_TIMED_WRENCHES timed wrenches pending (200 000 made the next step take
    7.7 s): the next one is refused naming the bound; those taken act as before (their sum:
    100 pushes of 1 N step as one of 100 N), and once they end there is room again."""
    from starleth_sim.physics.wrenches import MAX_TIMED_WRENCHES
    sims = [Simulator.from_preset("HmJ") for _ in range(2)]
    for s in sims:
        q = s.q
        q[2] = 3.0
        s.reset(q)
    for _ in range(MAX_TIMED_WRENCHES):
        sims[0].apply_wrench("base", (0.0, 1.0, 0.0))
    with pytest.raises(ValueError, match=f"{MAX_TIMED_WRENCHES} timed wrenches are pending, "
                                         f"the most \\(MAX_TIMED_WRENCHES"):
        sims[0].apply_wrench("base", (0.0, 1.0, 0.0))
    sims[1].apply_wrench("base", (0.0, float(MAX_TIMED_WRENCHES), 0.0))
    for s in sims:
        s.step(np.zeros(12))
    np.testing.assert_allclose(sims[0].u, sims[1].u, rtol=0, atol=1e-12)
    assert abs(sims[1].u[1]) > 1e-3
    assert not sims[0].state.pending_wrenches
    sims[0].apply_wrench("base", (0.0, 1.0, 0.0))


@pytest.mark.parametrize("preset", ["HmJ", "Cm", "HEJD"])
def test_rejected_torque_keeps_the_last_steps_reports(preset):
    """The one-kernel step (HmJ) writes its reports into a spare buffer; a rejected step must
    not touch the reports of the last step taken, nor the next step's (same for the
    general path: Cm takes two physics steps per control step, HEJD has cut joints)."""
    sim = Simulator.from_preset(preset)
    sim.step(np.full(12, 5.0))
    sim.step(np.full(12, 30.0))     # saturated at 20 N m
    before = (sim.applied_torque, sim.contact_forces(), sim.gaps(), sim.diagnostics,
              [(c.active, c.gap, c.state, c.position.copy()) for c in sim.contacts])
    with pytest.raises(ValueError, match="non-finite entries for LF_KFE"):
        sim.step(np.r_[0.0, 0.0, np.nan, np.zeros(9)])
    good = sim.snapshot()
    broken = sim.snapshot()
    broken.u[-1] = np.nan           # fails inside the step, after the contacts were computed
    sim.restore(broken)
    with pytest.raises(SimulationError):
        sim.step(np.zeros(12))
    sim.restore(good)
    np.testing.assert_array_equal(sim.applied_torque, before[0])
    np.testing.assert_array_equal(before[0], np.full(12, 20.0))
    np.testing.assert_array_equal(sim.contact_forces(), before[1])
    assert sim.diagnostics is before[3]
    for c, (active, gap, state, position) in zip(sim.contacts, before[4], strict=True):
        assert (c.active, c.gap, c.state) == (active, gap, state)
        np.testing.assert_array_equal(c.position, position)
    sim.step(np.full(12, -1.0))     # the next step reports its own torques and forces
    np.testing.assert_array_equal(sim.applied_torque, np.full(12, -1.0))
    assert not np.array_equal(sim.contact_forces(), before[1])


@pytest.mark.parametrize("preset", ["HmJ", "Cm"])
def test_torque_given_as_list_view_or_float32_steps_like_a_float64_vector(preset):
    """A list, a strided view and float32 give the same step as a contiguous float64 vector
    (the one-kernel step takes a copy of anything else rather than a new compilation)."""
    tau = np.linspace(-3.0, 3.0, 12)
    states = []
    for given in (tau, list(tau), np.repeat(tau, 2)[::2], tau.astype(np.float32)):
        s = Simulator.from_preset(preset)
        s.step(given)
        states.append((s.q, s.u, s.applied_torque))
    for q, u, applied in states[1:3]:
        assert q.tobytes() == states[0][0].tobytes() and u.tobytes() == states[0][1].tobytes()
        assert applied.tobytes() == states[0][2].tobytes()
    np.testing.assert_allclose(states[3][2], tau, atol=1e-6)    # float32's rounding


def test_torque_is_saturated_at_the_effort_limit(sim):
    sim.reset()
    sim.step(np.full(12, 100.0))
    np.testing.assert_array_equal(sim.applied_torque, np.full(12, 20.0))
    assert sim.joint_names[:3] == ("LF_HAA", "LF_HFE", "LF_KFE")
    assert sim.joint_names[9:] == ("RH_HAA", "RH_HFE", "RH_KFE")


def test_unknown_link_and_bad_wrench_are_rejected(sim):
    with pytest.raises(ValueError, match="unknown link 'trunk'"):
        sim.apply_wrench("trunk", (1, 0, 0))
    with pytest.raises(ValueError, match="force must be 3 finite"):
        sim.apply_wrench("base", (np.nan, 0, 0))


def test_push_in_the_air_changes_momentum_by_the_impulse():
    """A 0.1 s push of 150 N on the trunk of a robot in the air: Δp = 15 N s."""
    sim = Simulator.from_preset("HmJ")
    q = sim.q
    q[2] = 3.0
    sim.reset(q)
    mass = sim.description.total_mass
    sim.apply_wrench("base", (0.0, 150.0, 0.0), duration=0.1)
    for _ in range(60):
        sim.step(np.zeros(12))
    # whole-body horizontal momentum = m v_com; with the joints free, use the CoM velocity
    import pinocchio as pin

    from starleth_sim.physics.coordinates.forest import quat_rot
    R = np.zeros((3, 3))
    quat_rot(sim.q, 0, R)
    up = sim.u
    up[0:3] = R.T @ up[0:3]
    pin.centerOfMass(sim.coords.model, sim.coords.data, sim.q, up)
    p_y = mass * sim.coords.data.vcom[0][1]
    assert p_y == pytest.approx(15.0, rel=1e-3)


def test_contacts_report_world_impulse_and_force(sim):
    sim.reset()
    sim.step(np.zeros(12))
    c = sim.contact("LF_foot")
    assert c.active and c.impulse[2] > 0
    np.testing.assert_allclose(c.force, c.impulse / sim.control_period)
    with pytest.raises(KeyError):
        sim.contact("nose")
    names = sim.contact_names
    assert names[:4] == ("LF_foot", "RF_foot", "LH_foot", "RH_foot")
    assert {"LF_knee", "RH_knee"} <= set(names) and sum(n.startswith("trunk") for n in names) == 8


def test_physics_core_does_not_import_ros():
    """The layers of the tree: the physics core, the ROS-free halves of the ROS layer
    (parameters, service, state conversions) and the bag reader import no ROS."""
    import subprocess
    import sys
    code = ("import sys, starleth_sim, starleth_sim.physics.simulator,"
            " starleth_sim.physics.stepper;"
            "import starleth_sim.ros.parameters, starleth_sim.ros.service,"
            " starleth_sim.ros.state_io;"
            "import starleth_sim.tools.common.bag, starleth_interface.topics,"
            " starleth_interface.ros_helpers;"
            "from starleth_sim import Simulator; Simulator.from_preset('HmJ').step();"
            "bad=[m for m in sys.modules if m.split('.')[0] in ('rclpy','rosidl_runtime_py')];"
            "assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True)
