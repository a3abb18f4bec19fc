"""Joint impedance commands in sim_node's ROS-free core (issue #36, items 1, 2 and 4):
SimService reads a JointState command's filled fields as its mode (effort only: torques as
before; position (+ velocity, effort): targets tracked at every physics step with the gains
default_kp, default_kd), the position and velocity forwarding arrays, the gains at run time,
and bad input (one throttled warning, counted, the last valid command kept). The second-order
check of a position-forwarding controller, and the measured stability limit of kd on Cm.
(The law inside the step, to 1e-12 at every physics step: test_impedance.py; the ROS
nodes: test_impedance_ros.py.)"""
import numpy as np
import pytest

from starleth_sim.physics.impedance import ImpedanceCommand
from starleth_sim.physics.simulator import Simulator
from starleth_sim.ros.parameters import GAIN_PARAMETERS, Settings
from starleth_sim.ros.service import SimService
from starleth_sim.ros.state_io import parse_initial_state

_SIMS = {}


def service(preset="HmJ", mode="lockstep", initial_state="standing", **settings):
    """A SimService on a fresh state of a (cached) simulator of `preset`, and its warnings."""
    sim = _SIMS.get(preset) or _SIMS.setdefault(preset, Simulator.from_preset(preset))
    sim.clear_wrenches()
    sim.reset()
    q0, u0, _ = parse_initial_state(initial_state, sim)
    warnings = []
    svc = SimService(sim, Settings(mode=mode, realtime_start="immediately", **settings),
                     q0, u0, warn=warnings.append)
    return svc, warnings


def test_effort_only_joint_state_stays_a_torque_command():
    """position and velocity empty: today's torque command, the same array."""
    svc, _ = service()
    tau = np.linspace(-3.0, 3.0, 12)
    assert svc.submit_joint_command(list(svc.joint_names), tau, 0) == (True, "ok")
    assert type(svc.command) is np.ndarray and np.array_equal(svc.command, tau)
    assert svc.counters["impedance_commands"] == 0


def test_position_targets_by_name_are_tracked_with_the_gains_at_every_step():
    """A JointState with positions (names shuffled, no velocity, no effort): q* by name,
    q̇* = 0, no τ_ff, kp and kd of the parameters; held, it keeps tracking: every later step
    applies the law at that step's state, its damper at the step's end rates (HmJ: one
    physics step per control period)."""
    svc, _ = service(mode="realtime", default_kp=[80.0] * 6 + [60.0] * 6, default_kd=2.0)
    sim = svc.sim
    q_star = sim.joint_positions() + np.linspace(-0.05, 0.05, 12)
    perm = np.random.default_rng(3).permutation(12)
    names = [svc.joint_names[i] for i in perm]
    ok, _ = svc.submit_joint_command(names, [], None, position=q_star[perm])
    assert ok and type(svc.command) is ImpedanceCommand
    c = svc.command
    assert np.array_equal(c.position, q_star) and np.all(c.velocity == 0.0)
    assert np.all(np.isnan(c.effort)) and np.array_equal(c.kp, [80.0] * 6 + [60.0] * 6)
    assert np.all(c.kd == 2.0)
    for _ in range(5):         # no new message: the held command tracks
        q = sim.joint_positions()
        svc.step()
        qd = sim.joint_velocities()     # (the damper is implicit: the step's end rates)
        expected = c.kp * (q_star - q) + c.kd * (0.0 - qd)
        np.testing.assert_allclose(sim.applied_torque, expected, rtol=0, atol=1e-12)


def test_nan_turns_a_term_off_and_effort_is_feed_forward():
    svc, _ = service(default_kp=80.0, default_kd=2.0)
    q = svc.sim.joint_positions()
    pos, vel, eff = q.copy(), np.zeros(12), np.full(12, 1.5)
    pos[0] = np.nan                    # LF_HAA: no spring
    vel[1] = np.nan                    # LF_HFE: no damper
    eff[2] = np.nan                    # LF_KFE: no τ_ff
    assert svc.submit_joint_command([], eff, 0, position=pos, velocity=vel)[0]
    c = svc.command
    tau = c.torque(q + 0.1, np.full(12, 0.5))
    assert tau[0] == pytest.approx(1.5 + 2.0 * (0.0 - 0.5))
    assert tau[1] == pytest.approx(1.5 + 80.0 * (q[1] - q[1] - 0.1))
    assert tau[2] == pytest.approx(80.0 * -0.1 + 2.0 * -0.5)
    # velocity alone: a damper towards q̇*, no spring
    svc.step()
    assert svc.submit_joint_command([], [], svc.stamp_ns, velocity=np.full(12, 0.3))[0]
    assert np.all(np.isnan(svc.command.position)) and np.all(svc.command.velocity == 0.3)


def test_forwarding_arrays_are_position_and_velocity_targets():
    """joint_group_position_controller/commands: q* (q̇* = 0), velocity: q̇* (no spring),
    as forward_command_controllers with MuJoCo's position / velocity actuators."""
    svc, _ = service()
    q = svc.sim.joint_positions()
    assert svc.submit_array("position", q)[0]
    assert np.array_equal(svc.command.position, q) and np.all(svc.command.velocity == 0)
    svc.step()
    assert svc.submit_array("velocity", np.full(12, -0.2))[0]
    assert np.all(np.isnan(svc.command.position)) and np.all(svc.command.velocity == -0.2)
    svc.step()
    assert svc.submit_array("effort", np.ones(12))[0] and type(svc.command) is np.ndarray


def test_bad_impedance_input_is_one_warning_counted_and_the_last_command_kept():
    svc, warnings = service()
    q = svc.sim.joint_positions()
    names = list(svc.joint_names)
    assert svc.submit_joint_command(names, [], 0, position=q)[0]
    good = svc.command
    svc.step()
    bad_pos = q.copy()
    bad_pos[4] = np.inf
    nan_pos = q.copy()
    nan_pos[3] = np.nan
    cases = [
        dict(names=names, efforts=[], position=q[:11]),                    # length
        dict(names=names, efforts=np.ones(3), position=q),                 # effort length
        dict(names=names[:-1] + ["XX_KFE"], efforts=[], position=q),       # unknown joint
        dict(names=names, efforts=[], position=bad_pos),                   # infinite target
        dict(names=names, efforts=[], position=q, velocity=np.ones(5)),    # velocity length
    ]
    for case in cases:
        for _ in range(3):        # repeated: counted each time, warned of once
            ok, why = svc.submit_joint_command(case["names"], case["efforts"], svc.stamp_ns,
                                               case["position"], case.get("velocity", ()))
            assert not ok and svc.command is good, why
    assert svc.counters["commands_rejected"] == 3 * len(cases)
    assert len(warnings) == len(cases), warnings
    assert "RF_HFE" in warnings[3] and "infinite position" in warnings[3]
    for kind, data in (("position", nan_pos), ("velocity", np.ones(13))):
        assert not svc.submit_array(kind, data)[0] and svc.command is good
    assert "non-finite position target for RF_HAA" in warnings[-2], warnings[-2]
    # gains: negative, non-finite, wrong length -> refused, counted, previous gains kept
    for kp in (-1.0, [80.0] * 11 + [np.nan], [1.0] * 5):
        assert not svc.set_gains(kp=kp)[0]
    assert svc.counters["gains_rejected"] == 3 and np.all(svc.kp == 80.0)
    assert svc.command is good and "default_kp" in warnings[-1]


def test_new_gains_apply_to_the_held_command():
    svc, _ = service()
    q = svc.sim.joint_positions()
    assert svc.submit_array("position", q + 0.1)[0]
    assert svc.set_gains(kp=40.0, kd=[0.5] * 12) == (True, "ok")
    assert np.all(svc.command.kp == 40.0) and np.all(svc.command.kd == 0.5)
    assert np.array_equal(svc.command.position, q + 0.1)


def test_gain_parameters_accept_a_number_or_a_list():
    spec = GAIN_PARAMETERS["default_kp"]
    assert not spec.read_only
    for good in (80, 0.0, [1, 2.5] * 6):
        spec.check(spec.coerce(good))
    for bad in (-1.0, float("inf"), [], [1.0, -2.0], "80", True):
        with pytest.raises(ValueError, match="default_kp"):
            spec.check(spec.coerce(bad))
    with pytest.raises(ValueError, match="default_kd: 3 values, expected 1 or 12"):
        service(default_kd=[1.0, 1.0, 1.0])


def test_position_forwarding_tracks_a_sine_as_the_second_order_model_predicts():
    """A forward position controller (MuJoCo's position actuator: kp 80, kv 2, q̇* = 0) sends
    q*(t) = q0 + A sin(2π t) to one knee at the 400 Hz control rate. The robot falls freely
    (from 10 m: the internal motion feels no gravity), so the joint follows
    I q̈ = kp (q* − q) − kd q̇, sampled: q* held over each control period T (a delay T/2),
    the law held over each physics step Δt at its start state (a delay Δt/2 of the
    feedback): q/q* = kp e^(−jωT/2) / (−I ω² + (kp + j kd ω) e^(−jωΔt/2)). At 1 Hz I ω²
    (I ≈ 3e-3 kg m²) is 0.1 of kp = 80, so the tracking error is |1 − G| A ≈ kd ω / kp · A
    ≈ 0.155 A: the measured amplitude of q* − q over the second half of 1 s is the model's
    within 3 %."""
    svc, _ = service(mode="realtime", initial_state="{base_position: [0, 0, 10.0]}",
                     default_kp=80.0, default_kd=2.0)
    sim = svc.sim
    knee = svc.joint_names.index("LF_KFE")
    q0 = sim.joint_positions()
    amp, w, T = 0.2, 2 * np.pi, svc.control_period
    t_all, err = [], []
    for k in range(400):
        target = q0.copy()
        target[knee] += amp * np.sin(w * k * T)
        assert svc.submit_array("position", target)[0]
        svc.step()
        t = (k + 1) * T
        t_all.append(t)
        err.append(q0[knee] + amp * np.sin(w * t) - sim.joint_positions()[knee])
    t_all, err = np.array(t_all[200:]), np.array(err[200:])
    basis = np.column_stack([np.sin(w * t_all), np.cos(w * t_all), np.ones_like(t_all)])
    coef = np.linalg.lstsq(basis, err, rcond=None)[0]
    measured = float(np.hypot(coef[0], coef[1]))
    inertia = 1.0 / 362.5        # the knee's entry of M⁻¹ (floating base), kg m²
    g = 80.0 * np.exp(-0.5j * w * T) / (-inertia * w * w + (80.0 + 2.0j * w)
                                         * np.exp(-0.5j * w * sim.dt))
    predicted = float(abs(1.0 - g) * amp)
    print(f"1 Hz sine, amplitude {amp} rad: tracking error {measured:.5f} rad, "
          f"second-order model {predicted:.5f} rad")
    assert measured == pytest.approx(predicted, rel=0.03)


def test_cm_holds_the_stand_on_kp_80_kd_2():
    """Issue #36 (doc/physics.md, "Joint impedance", Stability): on Cm the law's damper and
    the compliant contact's damper (d_N = d_T = 50 N s/m) shared one stability budget while
    both were explicit, and kp 80 / kd 2 made the standing legs chatter (the torque jumping
    by 15 N m from one 1.25 ms physics step to the next, the knees at their 20 N m limit).
    With the implicit damper the stand holds for 2 s: the torque changes by < 0.05 N m
    between physics steps once settled (measured 0.012), stays far from the limits, and the
    base stays put (< 1 mm over the last second; measured 0.016 mm). kd 1 still holds."""
    for kd, jump_bound in ((1.0, 0.1), (2.0, 0.05)):
        sim = _SIMS.get("Cm") or _SIMS.setdefault("Cm", Simulator.from_preset("Cm"))
        sim.reset()
        cmd = ImpedanceCommand.create(sim.joint_names, position=sim.joint_positions(),
                                      kp=80.0, kd=kd)
        rows, heights = [], []
        for k in range(800):
            sim.step(cmd)
            heights.append(sim.root_position()[2])
            if k >= 160:
                rows.append(sim.applied_torques_per_step)
        rows = np.concatenate(rows)
        jump = float(np.abs(np.diff(rows, axis=0)).max())
        print(f"Cm, kp 80, kd {kd}: largest torque change between physics steps {jump:.4f}, "
              f"base over the last 1 s {np.ptp(heights[400:]) * 1e3:.4f} mm")
        assert jump < jump_bound, (kd, jump)
        assert np.abs(rows).max() < 0.5 * 20.0         # far below the 20 N m limits
        assert np.ptp(heights[400:]) < 1e-3
        assert (sim.replay_torques_per_step[:, 12:] == kd).all()   # every damper implicit


def test_gain_lists_as_rclpy_hands_them_over():
    """A parameter message's double_array_value / integer_array_value is an array.array."""
    import array
    spec = GAIN_PARAMETERS["default_kd"]
    assert spec.coerce(array.array("d", [1.5] * 12)) == [1.5] * 12
    assert spec.coerce(array.array("q", [2] * 12)) == [2.0] * 12
    spec.check(spec.coerce(array.array("q", [2] * 12)))


def test_the_intake_packs_commands_as_create_does():
    """SimService.impedance_command (no second validation) gives create's command."""
    svc, _ = service(default_kp=[float(i) for i in range(12)], default_kd=0.5)
    rng = np.random.default_rng(5)
    q, v, e = (rng.normal(size=12) for _ in range(3))
    q[2] = np.nan
    for args in ((q, v, e), (q, 0.0, None), (None, v, None), (None, None, e)):
        mine = svc.impedance_command(*args)
        ref = ImpedanceCommand.create(svc.joint_names, *args[:2], svc.kp, svc.kd, args[2])
        assert np.array_equal(mine.packed, ref.packed, equal_nan=True)
        assert mine.joint_names == ref.joint_names and not mine.packed.flags.writeable
        for name in ("position", "velocity", "kp", "kd", "effort"):
            assert np.array_equal(getattr(mine, name), getattr(ref, name), equal_nan=True)


def test_absurd_gains_are_refused_with_their_range():
    """kp above 1e5 N m/rad or kd above 1e3 N m s/rad (the torques saturate at 20 N m) is
    refused like a negative one, the message giving the range."""
    for name, bad in (("default_kp", 1e6), ("default_kd", [2.0] * 11 + [1e4])):
        spec = GAIN_PARAMETERS[name]
        with pytest.raises(ValueError, match=rf"parameter {name}: must be >= 0 and <= "):
            spec.check(spec.coerce(bad))
    GAIN_PARAMETERS["default_kp"].check(1e5)
