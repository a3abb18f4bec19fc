"""SimService: the ROS-free core of sim_node (command validation, lockstep bookkeeping,
timeout policy, pushes, reset) and the node's settings / initial-state parsing; inputs that
must not take the simulation down (pushes over max_wrench, a step that is not physics, a
reset during a lockstep exchange, megabyte names). No ROS graph."""
import numpy as np
import pytest

from starleth_interface.ros_helpers import ThrottledLog
from starleth_sim import ConfigError
from starleth_sim.physics.impedance import ImpedanceCommand
from starleth_sim.ros.parameters import Settings, load_default_parameters, render_yaml
from starleth_sim.ros.service import SimService, quoted
from starleth_sim.ros.state_io import initial_state_record, parse_initial_state


@pytest.fixture(scope="module")
def sim():
    from starleth_sim import Simulator
    return Simulator.from_preset("HmJ")


def make(sim, **kw):
    warnings = []
    svc = SimService(sim, Settings(**kw), warn=warnings.append, error=warnings.append)
    return svc, warnings


def test_settings_validation():
    Settings(mode="lockstep", real_time_factor=0.0).validate()
    with pytest.raises(ConfigError, match="only legal in lockstep"):
        Settings(mode="realtime", real_time_factor=0.0).validate()
    with pytest.raises(ConfigError, match="mode"):
        Settings(mode="fast").validate()
    with pytest.raises(ConfigError, match="timeout_policy"):
        Settings(timeout_policy="panic").validate()
    with pytest.raises(ConfigError, match="lockstep_timeout"):
        Settings(lockstep_timeout=0).validate()
    with pytest.raises(ConfigError, match="realtime_priority"):
        Settings(realtime_priority=120).validate()
    with pytest.raises(ConfigError, match="start_paused"):
        Settings(start_paused="yes").validate()
    with pytest.raises(ConfigError, match="physics_overrides"):
        Settings(physics_overrides="[1, 2]").physics_override_dict()
    assert Settings(physics_overrides="{mu: 0.0}").physics_override_dict() == {"mu": 0.0}


def test_default_parameter_file():
    d = load_default_parameters()
    assert d["physics"] == "HmJ" and d["mode"] in ("realtime", "lockstep")
    Settings(**d).validate()
    # the node YAML must not look like a physics preset
    from starleth_sim import available_presets
    assert "sim_node" not in available_presets()


def test_parameter_file_is_generated_from_the_schema():
    """msg_configs/sim_node.yaml is the schema's rendering (regenerate it with
    `python -m starleth_sim.ros.parameters > msg_configs/sim_node.yaml`)."""
    import yaml

    from starleth_sim.ros.parameters import SIM_NODE_PARAMETERS, default_settings_file
    with open(default_settings_file()) as f:
        text = f.read()
    assert text == render_yaml()
    params = yaml.safe_load(text)["/**"]["ros__parameters"]
    assert params == {p.name: p.default for p in SIM_NODE_PARAMETERS}
    assert all(p.description for p in SIM_NODE_PARAMETERS)


def test_effort_array_validation(sim):
    svc, warns = make(sim)
    ok, _ = svc.submit_effort_array([1.0] * 12)
    assert ok and np.all(svc.command == 1.0)
    for bad, word in (([1.0] * 11, "11 values"), ([float("nan")] + [0.0] * 11, "non-finite"),
                      ([float("inf")] * 12, "non-finite"), (["a"] * 12, "not numbers")):
        ok, why = svc.submit_effort_array(bad)
        assert not ok and word in why
    assert np.all(svc.command == 1.0)            # the last valid command stays
    assert svc.counters["commands_rejected"] == 4
    assert any("LF_HAA" in w for w in warns)     # names the joint with the NaN


def test_joint_command_validation(sim):
    svc, warns = make(sim)
    names = list(sim.joint_names)
    assert svc.submit_joint_command(names, np.arange(12.0))[0]
    # every joint by name in another order: each effort goes to its joint
    assert svc.submit_joint_command(names[::-1], np.arange(12.0))[0]
    assert np.array_equal(svc.command, np.arange(12.0)[::-1])
    assert svc.submit_joint_command([], [0.5] * 12)[0]                       # joint order
    assert np.all(svc.command == 0.5)
    before = svc.command.copy()
    for n, e, word in ((["LF_HAA", "FOO"], [1, 2], "'FOO'"),
                       (["LF_HAA", "LF_HAA"], [1, 2], "duplicate"),
                       (names, [1.0] * 11, "12 names but 11 efforts"),
                       ([], [1.0] * 3, "no joint names"),
                       (names, [0.0] + [float("nan")] + [0.0] * 10,
                        f"non-finite effort for {names[1]}")):
        ok, why = svc.submit_joint_command(n, e)
        assert not ok and word in why, why
    assert np.array_equal(svc.command, before)
    assert svc.counters["commands_rejected"] == 5


def test_a_command_naming_some_joints_but_not_all_is_rejected(sim):
    """11 of the 12 joints: rejected with one line naming the missing joint, counted, and
    the last valid command kept (the missing joint does not silently get 0 N m)."""
    svc, warns = make(sim)
    names = list(sim.joint_names)
    assert svc.submit_joint_command(names, [3.0] * 12)[0]
    ok, why = svc.submit_joint_command(names[:7] + names[8:], [1.0] * 11)
    assert not ok
    assert why == (f"rejected joint command on joint_commands: no effort for {names[7]} (a "
                   "command names all 12 joints, or none for joint order); keeping the last "
                   "valid command")
    assert warns == [why]
    assert svc.counters["commands_rejected"] == 1 and np.all(svc.command == 3.0)
    ok, why = svc.submit_joint_command(["RH_KFE", "LF_HAA"], [5.0, -5.0])
    assert not ok and "no effort for " + ", ".join(names[1:-1]) + " (" in why
    assert np.all(svc.command == 3.0)
    # the same problem again is throttled, another missing joint is a new problem: printed
    svc.submit_joint_command(names[:7] + names[8:], [1.0] * 11)
    svc.submit_joint_command(names[1:], [1.0] * 11)
    assert len(warns) == 3 and warns[-1].startswith(f"rejected joint command on "
                                                    f"joint_commands: no effort for {names[0]} ")
    assert svc.counters["commands_rejected"] == 4
    assert svc.summary()["warnings_by_kind"] == {"missing_joint": 4}


def test_throttled_warnings():
    t = [0.0]
    out = []
    w = ThrottledLog(out.append, period=1.0, clock=lambda: t[0])
    for _ in range(10):
        w.warn("a", "bad a")
    w.warn("b", "bad b")
    t[0] = 1.5
    w.warn("a", "bad a")
    assert out == ["bad a", "bad b", "bad a (9 more like this suppressed in the last 1.5 s)"]
    assert w.counts == {"a": 11, "b": 1}


def test_throttled_warnings_by_kind_and_detail():
    """Two different problems of one kind (a bad wrench on two links) are both printed; the
    same one again is suppressed; the counts stay by kind."""
    t = [0.0]
    out = []
    w = ThrottledLog(out.append, period=1.0, clock=lambda: t[0])
    assert w("bad_wrench", "bad wrench on base", "base")
    assert not w("bad_wrench", "bad wrench on base", "base")
    assert w("bad_wrench", "bad wrench on LF_THIGH", "LF_THIGH")
    t[0] = 1.5
    assert w("bad_wrench", "bad wrench on base", "base")
    assert out == ["bad wrench on base", "bad wrench on LF_THIGH",
                   "bad wrench on base (1 more like this suppressed in the last 1.5 s)"]
    assert w.counts == {"bad_wrench": 4}


def test_a_flood_of_distinct_problems_is_throttled_after_max_details():
    """1000 distinct unknown names within one period: MAX_DETAILS lines, then one saying
    that the further ones are throttled together, then nothing until the period is over."""
    out = []
    w = ThrottledLog(out.append, period=10.0, clock=lambda: 0.0)
    for i in range(1000):
        w("unknown_joint", f"unknown joint j{i}", f"j{i}")
    m = ThrottledLog.MAX_DETAILS
    assert len(out) == m + 1
    assert out[m] == (f"unknown joint j{m} (more than {m} distinct problems of this kind: "
                      "the further ones are throttled together)")
    assert w.counts == {"unknown_joint": 1000}
    w("unknown_joint", "unknown joint j0", "j0")           # one of the first: still apart
    assert len(out) == m + 1


def test_a_second_different_bad_wrench_is_printed(sim):
    """The issue's case: two different bad wrenches within the throttle period are both
    printed (before, the second was counted but never shown)."""
    svc, warns = make(sim, warn_throttle_period=60.0)
    svc.submit_wrench("base", (1e9, 0, 0), (0, 0, 0))
    svc.submit_wrench("base", (1e9, 0, 0), (0, 0, 0))
    svc.submit_wrench("LF_THIGH", (1e9, 0, 0), (0, 0, 0))
    svc.submit_wrench("base", (1e9, 0, 0), (0, 0, 0), persistent=True)
    assert [w.split(":")[0] for w in warns] == [
        "rejected wrench on ~/wrench for 'base'",
        "rejected wrench on ~/wrench for 'LF_THIGH'",
        "rejected wrench on ~/wrench/persistent for 'base'"]
    assert svc.counters["wrenches_rejected"] == 4


def test_realtime_start_first_command_and_immediately(sim):
    """realtime_start first_command: not started until a command is accepted (a rejected
    one does not start it); immediately: started from the outset, with zero torques."""
    svc, _ = make(sim, mode="realtime", realtime_start="first_command")
    assert not svc.started and not svc.holding
    assert not svc.submit_effort_array([float("nan")] * 12)[0] and not svc.started
    assert not svc.submit_joint_command(["no_such_joint"], [1.0])[0] and not svc.started
    assert svc.submit_effort_array([0.5] * 12)[0] and svc.started
    svc, _ = make(sim, mode="realtime", realtime_start="immediately")
    assert svc.started and not svc.holding and np.all(svc.command == 0.0)
    with pytest.raises(ConfigError, match="realtime_start"):
        Settings(realtime_start="later").validate()


def test_realtime_start_hold_until_the_first_valid_command(sim):
    """realtime_start hold (the default): the clock runs from the start and the command in
    effect is the joint impedance law toward the initial joint angles with default_kp /
    default_kd; gains set at run time reach it; a rejected command leaves it, the first
    valid one ends it (with a command delay: when that command comes into effect); a reset
    brings it back. Lockstep never holds (the controller answers before every step)."""
    svc, _ = make(sim, mode="realtime", default_kp=60.0, default_kd=1.5)
    assert Settings().realtime_start == "hold"
    c = svc.command
    assert svc.started and svc.holding and type(c) is ImpedanceCommand
    np.testing.assert_array_equal(c.position, sim.joint_positions())
    np.testing.assert_array_equal(c.velocity, 0.0)
    assert np.all(c.kp == 60.0) and np.all(c.kd == 1.5) and np.all(np.isnan(c.effort))
    assert svc.set_gains(kp=90.0)[0] and np.all(svc.command.kp == 90.0)
    assert not svc.submit_effort_array([float("nan")] * 12)[0] and svc.holding
    svc.step()
    assert svc.holding and svc.k == 1
    assert svc.submit_effort_array([0.5] * 12)[0] and not svc.holding
    np.testing.assert_array_equal(svc.command, 0.5)
    svc.reset()
    assert svc.holding and np.all(svc.command.kp == 90.0)
    svc, _ = make(sim, mode="realtime", command_delay=0.005)     # two control periods
    assert svc.submit_effort_array([0.5] * 12)[0] and svc.holding
    svc.step()
    svc.step()
    assert svc.holding
    svc.step()
    assert not svc.holding and np.all(svc.command == 0.5)
    svc, _ = make(sim, mode="lockstep")
    assert not svc.started and not svc.holding


def test_lockstep_commands_that_answer_no_state_get_one_hint(sim):
    """Lockstep: a stale answer after a reset is one command answering no state, no hint;
    three in a row (a controller on its own timer, stamping its own time) give one hint,
    once per run, naming realtime mode."""
    svc, warns = make(sim, mode="lockstep", warn_throttle_period=0.0)
    names = list(sim.joint_names)
    assert not svc.submit_joint_command(names, [0.0] * 12, stamp_ns=1)[0]
    assert svc.submit_joint_command(names, [0.0] * 12, stamp_ns=0)[0]      # resets the count
    svc.step()
    for stamp in (7, 8, 9, 10, 11, 12):
        assert not svc.submit_joint_command(names, [0.0] * 12, stamp_ns=stamp)[0]
    hints = [w for w in warns if "mode:=realtime" in w]
    assert len(hints) == 1 and "answer no state" in hints[0], warns
    assert svc.counters["stale_commands"] == 7


def test_hold_sags_as_the_joint_stiffness_predicts(sim):
    """The hold of the initial posture (default_kp 80, default_kd 2, HmJ) settles where the
    joints' stiffness puts it: at rest kp (q* - q) = τ = -Jᵀ F per stance leg, so each foot
    moves J kp⁻¹ Jᵀ F relative to the trunk, and the trunk sinks by the mean of those
    vertical displacements (F: the settled ground forces, J: the foot point's Jacobian in
    the leg's joints, Pinocchio). The simulated sag matches that prediction within 5 %, and
    stays within 2 cm of the standing height for 60 s."""
    import pinocchio as pin
    svc, _ = make(sim, mode="realtime")
    z0 = sim.base_state()["position"][2]
    heights = np.empty(60 * 400)
    for k in range(heights.size):
        assert svc.step() is not None
        heights[k] = sim.base_state()["position"][2]
    assert np.all(np.abs(heights - z0) < 0.02), (heights.min(), heights.max())
    desc, kp = sim.description, svc.kp
    model, data = desc.model, desc.model.createData()
    q = pin.neutral(model)
    q[[model.joints[model.getJointId(n)].idx_q for n in sim.joint_names]] = svc.hold_position
    pin.computeJointJacobians(model, data, q)
    forces = sim.contact_forces()
    sag = []
    for foot in desc.foot_names:
        c = next(c for c in desc.contacts if c.name == foot)
        jac = pin.getJointJacobian(model, data, c.joint, pin.LOCAL_WORLD_ALIGNED)
        r = data.oMi[c.joint].rotation @ c.local
        leg = [j for j in model.supports[c.joint] if j > 1]     # after the free flyer
        cols = [model.joints[j].idx_v for j in leg]
        stiffness = [kp[sim.joint_names.index(model.names[j])] for j in leg]
        j_leg = (jac[:3] - pin.skew(r) @ jac[3:])[:, cols]
        f = forces[desc.contact_names().index(foot)]
        sag.append((j_leg @ np.diag(1.0 / np.array(stiffness)) @ j_leg.T @ f)[2])
    predicted, simulated = float(np.mean(sag)), z0 - heights[-1]
    print(f"hold at kp {kp[0]:g}: sag predicted {predicted * 1e3:.2f} mm, simulated "
          f"{simulated * 1e3:.2f} mm; lowest {(z0 - heights.min()) * 1e3:.2f} mm below")
    assert len(sag) == 4 and all(len(model.supports[c.joint]) == 5 for c in desc.contacts[:4])
    assert predicted > 0.005
    assert simulated == pytest.approx(predicted, rel=0.05)


def test_lockstep_bookkeeping(sim):
    svc, warns = make(sim, mode="lockstep", real_time_factor=0.0, timeout_policy="hold")
    names = list(sim.joint_names)
    assert not svc.started and not svc.answered
    assert not svc.submit_joint_command(names, [1.0] * 12, stamp_ns=12345)[0]   # wrong stamp
    assert svc.counters["stale_commands"] == 1 and not svc.started
    assert svc.submit_joint_command(names, [1.0] * 12, stamp_ns=0)[0]
    assert svc.started and svc.answered
    assert not svc.submit_joint_command(names, [2.0] * 12, stamp_ns=0)[0]       # duplicate
    assert svc.counters["stale_commands"] == 2 and np.all(svc.command == 1.0)
    assert not svc.submit_effort_array([3.0] * 12)[0]                         # already answered
    svc.step()
    assert svc.k == 1 and svc.stamp_ns == 2_500_000 and not svc.answered
    # Float64MultiArray has no stamp: it answers the latest state
    assert svc.submit_effort_array([2.0] * 12)[0] and svc.answered
    svc.step()
    # no answer for state 2: timeout, hold the last command
    svc.step(timed_out=True)
    assert svc.counters["lockstep_timeouts"] == 1 and np.all(sim.applied_torque == 2.0)
    # the answer for state 2 arrives late
    ok, why = svc.submit_joint_command(names, [9.0] * 12, stamp_ns=2 * 2_500_000)
    assert not ok and why == "late" and svc.counters["late_commands"] == 1
    assert any("lockstep: no command" in w for w in warns)


def test_timeout_policy_zero(sim):
    svc, _ = make(sim, mode="lockstep", real_time_factor=0.0, timeout_policy="zero")
    svc.submit_effort_array([1.0] * 12)
    svc.step()
    svc.step(timed_out=True)
    assert np.all(sim.applied_torque == 0.0)


def test_wrench_validation(sim):
    svc, warns = make(sim)
    assert svc.submit_wrench("base", (0, 0, 10), (0, 0, 0))[0]
    ok, why = svc.submit_wrench("nope", (0, 0, 10), (0, 0, 0))
    assert not ok and "unknown link 'nope'" in why
    ok, why = svc.submit_wrench("base", (0, float("nan"), 1), (0, 0, 0))
    assert not ok and "finite" in why
    assert svc.submit_wrench("LF_THIGH", (1, 0, 0), (0, 0, 0), persistent=True)[0]
    assert svc.submit_wrench("LF_THIGH", (0, 0, 0), (0, 0, 0), persistent=True)[0]   # clears
    assert svc.counters["wrenches_accepted"] == 3 and svc.counters["wrenches_rejected"] == 2


def test_reset_advances_time_and_restores_state(sim):
    svc, _ = make(sim)
    q0 = sim.q
    svc.submit_effort_array([5.0] * 12)
    for _ in range(10):
        svc.step()
    assert not np.allclose(sim.q, q0)
    svc.reset()
    assert svc.k == 11 and sim.t == pytest.approx(11 * sim.control_period)
    assert np.array_equal(sim.q, q0) and svc.holding       # realtime_start hold (default)
    svc, _ = make(sim, realtime_start="first_command")
    svc.submit_effort_array([5.0] * 12)
    svc.step()
    svc.reset()
    assert np.array_equal(sim.q, q0) and np.all(svc.command == 0.0)


def test_initial_state_parsing(sim):
    from starleth_sim.ros.state_io import public_state
    q, u, _ = parse_initial_state("standing", sim)
    assert np.array_equal(q, sim.default_state()) and not u.any()
    q, u, _ = parse_initial_state("{base_position: [0.1, 0, 1.5], base_linear_velocity: "
                                  "[1, 0, 0], base_angular_velocity: [0, 0, 0.5], "
                                  "joint_positions: {LF_KFE: -1.0}}", sim)
    sim.reset(q=q, u=u)
    pub = public_state(sim)
    assert np.allclose(pub["base_position"], [0.1, 0, 1.5])
    assert np.allclose(pub["base_linear_velocity"], [1, 0, 0])
    assert np.allclose(pub["base_angular_velocity"], [0, 0, 0.5])
    assert pub["joint_positions"][sim.joint_names.index("LF_KFE")] == pytest.approx(-1.0)
    # a recorded initial state round-trips exactly
    rec = initial_state_record(sim, q, u)
    q2, u2, _ = parse_initial_state(rec, sim)
    assert np.array_equal(q, q2) and np.array_equal(u, u2)
    # and through the minimal coordinates when the coordinate sets differ
    rec["coordinates"] = "other"
    q3, u3, _ = parse_initial_state(rec, sim)
    assert np.allclose(q, q3, atol=1e-12) and np.allclose(u, u3, atol=1e-12)
    for bad, word in (("{foo: 1}", "unknown keys"), ("{base_position: [0, 0]}", "3 finite"),
                      ("{joint_positions: {XX: 1}}", "unknown joints"), ("[1, 2]", "mapping"),
                      ("{base_orientation: [0, 0, 0, 0]}", "zero"),
                      ("{joint_positions: {LF_HAA: .nan}}", "finite")):
        with pytest.raises(ConfigError, match=word):
            parse_initial_state(bad, sim)


def test_physics_failure_pauses_and_reset_recovers(sim, monkeypatch):
    from starleth_sim import SimulationError
    svc, warns = make(sim)
    real_step = sim.step

    def failing(_tau=None):
        raise SimulationError("non-finite state after the step")

    monkeypatch.setattr(sim, "step", failing)
    assert svc.step() is None                     # retried with zero torque, then paused
    assert svc.paused and svc.failed and svc.k == 0
    assert svc.counters["simulation_errors"] == 1
    assert any("simulation paused" in w for w in warns)
    monkeypatch.setattr(sim, "step", real_step)
    svc.reset()
    assert not svc.paused and svc.k == 1
    assert svc.step() is not None and svc.k == 2


# -- inputs that must not take the simulation down (issue #33) -------------------------------
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


def test_a_command_of_a_hundred_thousand_names_is_refused_at_once(sim):
    """100 000 joint names (one joint's, repeated; or 10 000 of each): one short line naming
    the repeated joints (they were counted by scanning the list once per name: 0.7 s for
    30 000 names, 8 s for 100 000; now once in all)."""
    svc, warns = make(sim, warn_throttle_period=0.0)
    for names in (["LF_HAA"] * 100_000, list(sim.joint_names) * 10_000):
        ok, why = svc.submit_joint_command(names, [0.0] * len(names))
        assert not ok and "duplicate joint name(s) " in why and len(why) < 400, why
    assert why.split("duplicate joint name(s) ")[1].startswith(", ".join(sorted(sim.joint_names)))
    assert svc.counters["commands_rejected"] == 2


def test_the_hold_gains_are_starleths_scaled_to_the_robot():
    """default_kp, default_kd left unset: StarlETH's 80 and 2 as they are for StarlETH; for
    Go1 80 mu lambda and 2 mu lambda^1.5, mu its mass and lambda its mean leg length (hip
    pitch to knee to foot centre, from the model's placements) over StarlETH's."""
    import pinocchio as pin

    from starleth_sim.robots import robot_description
    from starleth_sim.ros.parameters import robot_default_gains
    both = ("default_kp", "default_kd")
    assert robot_default_gains(robot_description("starleth"), both) == \
        {"default_kp": 80.0, "default_kd": 2.0}
    try:
        go1 = robot_description("go1")
    except ConfigError as e:
        pytest.skip(str(e))
    model = go1.model
    lengths = []
    for leg in go1.legs:
        kfe = model.getJointId(leg.joint_names[2])
        foot = model.frames[model.getFrameId(leg.foot, pin.FrameType.BODY)]
        lengths.append(np.linalg.norm(model.jointPlacements[kfe].translation[[0, 2]])
                       + np.linalg.norm(foot.placement.translation))
    lam, mu = np.mean(lengths) / 0.435, go1.total_mass / 26.82
    gains = robot_default_gains(go1, ["default_kp"])
    assert list(gains) == ["default_kp"]
    assert gains["default_kp"] == pytest.approx(80.0 * mu * lam, rel=1e-4)
    assert robot_default_gains(go1, ["default_kd"])["default_kd"] == \
        pytest.approx(2.0 * mu * lam ** 1.5, rel=1e-4)
