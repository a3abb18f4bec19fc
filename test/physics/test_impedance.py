"""Joint impedance commands in the physics core (issue #36; starleth_sim.physics.impedance):
the law τ = τ_ff + kp (q* − q) + kd (q̇* − q̇), then the effort limit and the velocity
derating, evaluated at the start state of every physics step. The numbers checked here come
from outside the code under test: the formula and the saturation written out in numpy from
the per-step states, the torque path of the simulator (pinned by test_bitexact), and the
steady-state response of a second-order system."""
import numpy as np
import pinocchio as pin
import pytest

from starleth_sim import Simulator
from starleth_sim.physics.impedance import ImpedanceCommand


def command(sim, **fields):
    return ImpedanceCommand.create(sim.joint_names, **fields)


def formula(cmd, q, qd):
    """The law in numpy, a NaN target or τ_ff leaving its term out."""
    tau = np.where(np.isnan(cmd.effort), 0.0, cmd.effort)
    tau = tau + np.where(np.isnan(cmd.position), 0.0, cmd.kp * (cmd.position - q))
    return tau + np.where(np.isnan(cmd.velocity), 0.0, cmd.kd * (cmd.velocity - qd))


def saturated(sim, tau, qd):
    """actuator.saturate_torque written out: clip to the URDF effort limit, then a torque
    driving its joint beyond the velocity limit v derated linearly to zero at 2v."""
    limit = np.asarray(sim.description.effort_limit, dtype=float)
    v = np.asarray(sim.description.velocity_limit, dtype=float)
    t = np.clip(tau, -limit, limit)
    w = np.abs(qd)
    derate = (w > v) & (t * qd > 0)
    return np.where(derate, t * np.maximum(0.0, 2.0 - w / v), t)


def swaying_command(sim, q0, k, kp=80.0, kd=2.0):
    """Targets swaying around q0 at 2 Hz, a feed-forward torque, and some terms off."""
    t = k * sim.control_period
    pos = q0 + 0.2 * np.sin(2 * np.pi * 2.0 * t + np.arange(12))
    vel = 0.3 * np.cos(2 * np.pi * 2.0 * t + np.arange(12))
    pos[0] = np.nan             # LF_HAA: no spring
    vel[4] = np.nan             # RF_HFE: no damper
    ff = np.full(12, 1.5)
    ff[8] = np.nan              # LH_KFE: no feed-forward
    gains = np.full(12, kp)
    gains[11] = 5000.0          # RH_KFE: pushed into its effort limit
    pos[11] = q0[11] + 0.5
    return command(sim, position=pos, velocity=vel, kp=gains, kd=kd, effort=ff)


def test_the_torque_of_every_physics_step_of_cm_is_the_law_with_an_implicit_damper():
    """Cm runs 2 physics steps per control period: each step's applied torque is τ_ff +
    kp (q* − q^S) + kd (q̇* − q̇^E), the damper at the step's END rates (implicit), on every
    joint whose law at the start state is not saturated and whose torque at q̇^E is not
    either (those lose it in a second solve); the others take the law at the start state,
    saturated (1e-12). The per-step
    states come from a twin with one physics step per control step at the same Δt, fed the
    recorded replay rows: it must pass through the main run's states bit for bit."""
    sim = Simulator.from_preset("Cm")
    assert sim.config.steps_per_control == 2
    twin = Simulator.from_preset("Cm", control_rate=2 * sim.config.control_rate,
                                 steps_per_control=1)
    assert twin.dt == sim.dt
    twin.reset(sim.q, sim.u)
    q0 = sim.joint_positions()
    clipped = damped = dropped = 0
    for k in range(120):
        cmd = swaying_command(sim, q0, k)
        sim.step(cmd)
        per_step = sim.applied_torques_per_step
        replay = sim.replay_torques_per_step
        assert per_step.shape == (2, 12) and replay.shape == (2, 24)
        assert np.array_equal(sim.applied_torque, per_step[0])
        assert sim.last_command is cmd
        for row, rec in zip(per_step, replay, strict=True):
            q, qd = twin.joint_positions(), twin.joint_velocities()
            law = formula(cmd, q, qd)
            explicit = saturated(sim, law, qd)
            twin.step_applied(rec)
            qd_end = twin.joint_velocities()
            implicit = formula(cmd, q, qd_end)
            dampers = rec[12:] > 0.0
            assert np.array_equal(rec[12:][dampers], cmd.kd[dampers])
            # a damper only where the law at the start is unsaturated and has a kd term
            assert not np.any(dampers & ((explicit != law) | np.isnan(cmd.velocity)))
            assert np.abs(rec[:12] - explicit).max() <= 1e-12
            want = np.where(dampers, implicit, explicit)
            assert np.abs(row - want).max() <= 1e-12, (k, row - want)
            assert np.array_equal(saturated(sim, row, qd_end)[dampers], row[dampers])
            clipped += int(np.isclose(abs(row[11]), sim.description.effort_limit[11]))
            damped += int(dampers.sum())
            # a joint that could be damped but was not: its torque at q̇^E was saturated
            dropped += int(np.sum(~dampers & (explicit == law) & ~np.isnan(cmd.velocity)))
        assert np.array_equal(twin.q, sim.q) and np.array_equal(twin.u, sim.u), k
    assert clipped > 100        # the saturation was exercised
    assert damped > 1500        # and the implicit dampers (10 joints can have one)
    assert dropped > 0          # and the second solve (measured: 2 joint-steps)


def test_a_nan_target_turns_its_term_off_for_that_joint_only():
    sim = Simulator.from_preset("HmJ")
    q, qd = sim.joint_positions(), sim.joint_velocities()
    pos, vel, ff = q + 0.05, np.full(12, 0.1), np.full(12, 2.0)
    pos[0] = vel[1] = ff[2] = np.nan
    cmd = command(sim, position=pos, velocity=vel, kp=100.0, kd=3.0, effort=ff)
    sim.step(cmd)
    got = sim.applied_torque
    qd = sim.joint_velocities()     # (the dampers are implicit: the step's end rates)
    assert got[0] == pytest.approx(2.0 + 3.0 * (0.1 - qd[0]), abs=1e-12)      # no spring
    assert got[1] == pytest.approx(2.0 + 100.0 * (pos[1] - q[1]), abs=1e-12)  # no damper
    assert got[2] == pytest.approx(100.0 * (pos[2] - q[2]) + 3.0 * (0.1 - qd[2]),
                                   abs=1e-12)                               # no τ_ff
    assert got[3] == pytest.approx(2.0 + 100.0 * 0.05 + 3.0 * (0.1 - qd[3]), abs=1e-12)
    off = command(sim, position=None, velocity=None, kp=100.0, kd=3.0, effort=None)
    sim.step(off)
    assert np.array_equal(sim.applied_torque, np.zeros(12))


@pytest.mark.parametrize("fields, field, joints", [
    (dict(kp=[-1.0] + [80.0] * 11), "kp", ["LF_HAA"]),
    (dict(kd=np.r_[np.full(4, 2.0), np.inf, np.full(7, 2.0)]), "kd", ["RF_HFE"]),
    (dict(kp=np.r_[np.full(11, 1.0), np.nan]), "kp", ["RH_KFE"]),
    (dict(position=np.r_[np.full(7, 0.0), -np.inf, np.full(4, 0.0)]), "position",
     ["LH_HFE"]),
    (dict(effort=np.r_[np.full(3, 0.0), np.inf, np.inf, np.full(7, 0.0)]), "effort",
     ["RF_HAA", "RF_HFE"]),
    (dict(velocity=np.zeros(11)), "velocity", ["joint order"]),
    (dict(kd=np.zeros(13)), "kd", ["joint order"]),
])
def test_a_bad_command_is_a_value_error_naming_the_field_and_the_joints(fields, field,
                                                                       joints):
    sim = Simulator.from_preset("HmJ")
    with pytest.raises(ValueError) as e:
        command(sim, **fields)
    assert field in str(e.value) and all(j in str(e.value) for j in joints), str(e.value)


def test_a_command_for_other_joints_and_bad_replay_torques_leave_the_state_unchanged():
    sim = Simulator.from_preset("HmJ")
    q, t = sim.q, sim.t
    other = ImpedanceCommand.create(("a", "b"), position=[0.0, 0.0], kp=1.0)
    with pytest.raises(ValueError, match="joints"):
        sim.step(other)
    with pytest.raises(ValueError, match="1 x 12"):
        sim.step_applied(np.zeros((2, 12)))
    bad = np.zeros(12)
    bad[5] = np.nan
    with pytest.raises(ValueError, match="RF_KFE"):
        sim.step_applied(bad)
    huge = command(sim, position=sim.joint_positions() + 10.0, kp=1e308)
    with pytest.raises(ValueError, match="non-finite"):
        sim.step(huge)
    assert np.array_equal(sim.q, q) and sim.t == t and sim.last_command is None


def test_with_one_physics_step_an_impedance_step_is_the_torque_step_of_the_formula():
    """HmJ: without a damper (kd 0) the law inside the kernel gives, bit for bit, the run of
    the torque path fed the formula computed here (in the law's order: τ_ff, then the kp
    term); with kd 3, the implicit damper's explicit part is the formula at the start state
    (τ_ff, kp, kd terms) and the step that of step_applied with it and kd."""
    a, b = Simulator.from_preset("HmJ"), Simulator.from_preset("HmJ")
    q0 = a.joint_positions()
    for k in range(200):
        t = k * a.control_period
        pos = q0 + 0.3 * np.sin(2 * np.pi * 1.5 * t + np.arange(12))
        vel = np.full(12, 0.2)
        ff = np.full(12, -1.0)
        kd = 3.0 * (k % 2)
        cmd = command(a, position=pos, velocity=vel, kp=120.0, kd=kd, effort=ff)
        a.step(cmd)
        tau = ff + 120.0 * (pos - b.joint_positions())
        if kd:
            qd = b.joint_velocities()
            law = tau + kd * (vel - qd)
            explicit = saturated(a, law, qd)
            row = a.replay_torques_per_step[0]
            assert np.array_equal(row[:12], explicit)
            assert np.all((row[12:] == kd) | (row[12:] == 0.0))
            assert np.all(row[12:][explicit != law] == 0.0) and (row[12:] == kd).sum() >= 4
            b.step_applied(row)
        else:
            b.step(tau)
        assert np.array_equal(a.q, b.q) and np.array_equal(a.u, b.u), k
        assert np.array_equal(a.applied_torque, b.applied_torque)


@pytest.mark.parametrize("preset", ["Cm", "HmJ", "HEJD", "HMSD"])
def test_the_kernel_and_the_phase_by_phase_paths_give_the_same_run(preset):
    """The one-kernel steps (law in C inside the kernel, or, for a cut forest, before it)
    and the general path (profiling: the law through MoreauStepper.impedance_torque and the
    phase-by-phase step; a step prepared ahead, whose first physics step uses what
    `prepare` did) agree bit for bit; so does replaying the recorded per-step torques
    (step_applied) from the same initial state."""
    fast = Simulator.from_preset(preset)
    general = Simulator.from_preset(preset, profile=True)
    prepared = Simulator.from_preset(preset)
    replay = Simulator.from_preset(preset)
    q0 = fast.joint_positions()
    start = fast.snapshot()
    recorded = []
    for k in range(60):
        cmd = swaying_command(fast, q0, k, kp=150.0, kd=4.0)
        fast.step(cmd)
        general.step(cmd)
        prepared.prepare()
        prepared.step(cmd)
        recorded.append(fast.replay_torques_per_step)
        for other in (general, prepared):
            assert np.array_equal(fast.q, other.q) and np.array_equal(fast.u, other.u), k
            assert np.array_equal(fast.applied_torques_per_step,
                                  other.applied_torques_per_step), k
            assert np.array_equal(recorded[-1], other.replay_torques_per_step), k
    replay.restore(start)
    for torques in recorded:
        replay.step_applied(torques)
    assert np.array_equal(replay.q, fast.q) and np.array_equal(replay.u, fast.u)


def test_a_torque_command_reports_the_same_torque_at_every_physics_step():
    sim = Simulator.from_preset("Cm")
    tau = np.linspace(-5.0, 5.0, 12)
    sim.step(tau)
    assert np.array_equal(sim.applied_torques_per_step, np.tile(sim.applied_torque, (2, 1)))
    assert np.array_equal(sim.last_command, tau)


def test_a_joint_tracks_a_1hz_sine_with_the_gain_and_phase_of_its_second_order_system():
    """MuJoCo-style position forwarding (q* = A sin ωt, q̇* = 0, kp 80, kd 2) on the left
    front knee of the robot falling freely far above the ground (uniform gravity does not
    act on the joints of a free-falling body), the other joints held stiffly (kp 500, kd 3:
    they move < 1e-4 rad). The knee
    then obeys I q̈ + kd q̇ + kp q = kp q*, I its inertia with the base free and the other
    joints locked (from M), integrated as the step does it: the spring at the step's start,
    the damper implicit (at its end), q by the midpoint rule,
        (I + Δt kd) u⁺ = I u + Δt kp (q* − q),   q⁺ = q + ½Δt (u + u⁺),
    whose steady-state response at z = e^{iωΔt} is G(z) = Δt kp / (2 (z − 1) (z (I + Δt kd)
    − I) / (Δt (z + 1)) + Δt kp); the phase less the half step ωΔt/2 (3.9 mrad) by which the
    target, held over the control period's two physics steps, lags. The fitted response
    agrees to 2e-4 in gain and 0.05 mrad in phase (measured: 7e-6 and 0.001 mrad); the
    explicit damper's G (I (z − 1) + Δt kd in place of z (I + Δt kd) − I) is 1.2e-3 off in
    gain and 0.18 mrad in phase, the continuous kp / (kp − Iω² + i kd ω) 1.2e-3 in gain, a
    missing or doubled kd term 0.16 rad in phase, no lag 3.9 mrad. (At 1 Hz the inertia term
    Iω² = 0.13 N m/rad is small beside kp: the test pins the law and its timing, not I.)"""
    sim = Simulator.from_preset("Cm")
    q = sim.q
    q[2] = 50.0                     # 50 m up: 3 s of free fall stay well clear
    sim.reset(q)
    j, amplitude, omega, kp, kd = 2, 0.2, 2 * np.pi, 80.0, 2.0
    q0 = sim.joint_positions()
    kps, kds = np.full(12, 500.0), np.full(12, 3.0)    # the others: stiff, quiet
    kps[j], kds[j] = kp, kd
    times, angles = [], []
    for k in range(1200):
        t = k * sim.control_period
        target = q0.copy()
        target[j] += amplitude * np.sin(omega * t)
        sim.step(command(sim, position=target, velocity=0.0, kp=kps, kd=kds))
        times.append(t + sim.control_period)
        angles.append(sim.joint_positions()[j] - q0[j])
    assert min(c.gap for c in sim.contacts) > 1.0
    assert np.abs(np.delete(sim.joint_positions() - q0, j)).max() < 1e-4
    t, y = np.array(times), np.array(angles)
    keep = t >= 1.0             # the transient (decay time 2I/kd) is long gone
    basis = np.column_stack([np.sin(omega * t[keep]), np.cos(omega * t[keep]),
                             np.ones(keep.sum())])
    (s, c, _), *_ = np.linalg.lstsq(basis, y[keep], rcond=None)
    gain, phase = np.hypot(s, c) / amplitude, np.arctan2(c, s)
    # I: the knee's inertia with the base free and the other joints locked, from
    # Pinocchio's M (the minimal coordinates' q is Pinocchio's)
    model = sim.description.model
    M = pin.crba(model, model.createData(), sim.q)
    M = np.triu(M) + np.triu(M, 1).T
    dofs = list(range(6)) + [model.joints[model.getJointId(sim.joint_names[j])].idx_v]
    inertia = 1.0 / np.linalg.inv(M[np.ix_(dofs, dofs)])[-1, -1]
    dt = sim.dt
    z = np.exp(1j * omega * dt)
    G = dt * kp / (2 * (z - 1) * (z * (inertia + dt * kd) - inertia) / (dt * (z + 1))
                   + dt * kp) * np.exp(-0.5j * omega * dt)
    print(f"gain {gain:.5f} (predicted {abs(G):.5f}), phase {phase:.5f} rad (predicted "
          f"{np.angle(G):.5f}), I = {inertia:.3e} kg m²")
    assert gain == pytest.approx(abs(G), rel=2e-4), (gain, abs(G), inertia)
    assert phase == pytest.approx(np.angle(G), abs=5e-5), (phase, np.angle(G), inertia)


def standing_torques(preset, kp, kd):
    """The joint torques that hold the robot up near its standing posture: those applied
    at rest after 2 s of the impedance (kp, kd) towards it (the robot sags until its
    springs carry it)."""
    sim = Simulator.from_preset(preset)
    q0 = sim.joint_positions()
    sag = command(sim, position=q0, kp=kp, kd=kd)
    for _ in range(800):
        sim.step(sag)
    assert np.abs(sim.joint_velocities()).max() < 0.01
    return q0, sim.applied_torque


@pytest.mark.parametrize("preset, kd, feed_forward, sag", [("HmJ", 2.0, True, 2e-3),
                                                          ("HmJ", 2.0, False, 2e-2),
                                                          ("Cm", 2.0, False, 3e-2)])
def test_the_robot_stands_for_2s_on_mujoco_style_gains(preset, kd, feed_forward, sag):
    """kp 80 and kd towards the standing posture (MuJoCo's position actuator), with the
    standing torques as τ_ff or without: the base sags by less than `sag` (without τ_ff
    the springs carry the weight: 13 mm on HmJ, 15 mm on Cm after a 26 mm dip; with it,
    < 2 mm) and then stays (< 1 mm over the last 1 s), the trunk level, the feet put.
    Cm: kd 2 too (the implicit damper; explicit, kd 2 made the legs chatter on the
    compliant ground, doc/physics.md, "Joint impedance"); and no τ_ff, which
    kicks the unloaded compliant feet apart in the first milliseconds (the torque path
    too)."""
    q0, ff = standing_torques(preset, 80.0, kd)
    sim = Simulator.from_preset(preset)
    z0 = sim.root_position()[2]
    cmd = command(sim, position=q0, kp=80.0, kd=kd, effort=ff if feed_forward else 0.0)
    heights, feet = [], None
    for k in range(800):
        sim.step(cmd)
        heights.append(sim.root_position()[2])
        if k == 399:
            feet = sim.contact_points()[:4]
    heights = np.array(heights)
    assert np.abs(heights - z0).max() < sag, np.abs(heights - z0).max()
    assert np.ptp(heights[400:]) < 1e-3, np.ptp(heights[400:])
    quat = sim.base_state()["orientation_xyzw"]
    assert abs(quat[3]) > np.cos(0.5 * np.radians(1.0))        # tilted < 1°
    assert np.abs(sim.contact_points()[:4] - feet).max() < 1e-3
