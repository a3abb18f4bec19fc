"""The drive models (actuator.armature, viscous_damping, coulomb_friction, torque_bandwidth;
doc/drives.md) against closed forms on a one-joint pendulum of our own (a bob of mass m at l
from a revolute joint on a heavy base), and StarlETH with its series elastic drives
(msg_configs/actuators/starleth_sea.yaml) standing and trotting under the controller.

The pendulum's base is 10⁶ times the bob: resting on the ground (hard contacts) for the
gravity cases, or falling freely (every body falls alike: no gravity torque at the joint) for
the others, so that either contact model can run them."""
import os

import numpy as np
import pytest
import yaml

from starleth_interface.config_checks import ConfigError
from starleth_sim import Simulator, load_preset
from starleth_sim.physics.config import config_dir
from starleth_sim.physics.description import RobotDescription

G = 9.81                    # pinocchio's gravity [m/s²]
M, L = 1.0, 0.5             # the bob [kg], its distance from the joint [m]
I_BOB = 1e-6                # the bob's own inertia [kg m²]
I_J = M * L * L + I_BOB     # about the joint [kg m²]
DT = 1e-3                   # [s]


def pendulum_urdf(axis):
    """The pendulum: a joint about y (the bob below it: gravity acts) or about z (the bob
    beside it: no gravity torque)."""
    bob = f"0 0 {-L}" if axis == "y" else f"{L} 0 0"
    b = 1e6
    return f"""<?xml version="1.0"?>
<robot name="pendulum">
  <link name="base">
    <inertial><mass value="{b}"/>
      <inertia ixx="{b}" ixy="0" ixz="0" iyy="{b}" iyz="0" izz="{b}"/></inertial>
    <collision name="base"><geometry><box size="0.4 0.4 2.0"/></geometry></collision>
  </link>
  <joint name="swing" type="revolute">
    <parent link="base"/><child link="bob"/>
    <origin xyz="0.3 0 0.8"/><axis xyz="{'0 1 0' if axis == 'y' else '0 0 1'}"/>
    <limit effort="1000" velocity="1000" lower="-10" upper="10"/>
  </joint>
  <link name="bob">
    <inertial><origin xyz="{bob}"/><mass value="{M}"/>
      <inertia ixx="{I_BOB}" ixy="0" ixz="0" iyy="{I_BOB}" iyz="0" izz="{I_BOB}"/></inertial>
  </link>
</robot>
"""


def pendulum(preset="HmJ", axis="y", angle=0.0, falling=False, **drives):
    """A pendulum simulator at Δt = 1 ms, at rest at the joint angle `angle`."""
    cfg = load_preset(preset).with_overrides(control_rate=1.0 / DT, steps_per_control=1,
                                             tol_rel=1e-10, tol_abs=1e-12, **drives)
    sim = Simulator(cfg, description=RobotDescription.from_urdf_xml(pendulum_urdf(axis)))
    q = sim.q
    q[-1] = angle
    if falling:
        q[2] = 100.0
    sim.reset(q)
    return sim


def run(sim, tau, n):
    """n control steps at the constant torque tau; the joint angles after each."""
    out = np.empty(n)
    for k in range(n):
        sim.step(np.array([tau]))
        out[k] = sim.q[-1]
    return out


# -- configuration ---------------------------------------------------------------------------
def test_drive_fields_are_validated_with_their_name():
    cfg = load_preset("HmJ")
    with pytest.raises(ConfigError, match=r"actuator.armature: must be >= 0"):
        cfg.with_overrides(armature=-0.1)
    with pytest.raises(ConfigError, match=r"actuator.torque_bandwidth.LF_KFE: must be finite"):
        cfg.with_overrides(torque_bandwidth={"LF_KFE": float("inf")})
    with pytest.raises(ConfigError, match=r"actuator.coulomb_friction: expected a number or"):
        cfg.with_overrides(coulomb_friction=[0.1, 0.2])
    with pytest.raises(ConfigError, match=r"actuator.viscous_damping: unknown joint 'LF_XXX'"):
        Simulator(cfg.with_overrides(viscous_damping={"LF_XXX": 0.1}))
    with pytest.raises(ConfigError, match=r"drive models .* need coordinates: minimal"):
        Simulator.from_preset("HEJD", armature=0.01)
    sim = Simulator(cfg.with_overrides(coulomb_friction={"RH_KFE": 0.5}))
    assert sim.stepper.drives.coulomb_friction.tolist() == [0.0] * 11 + [0.5]


# -- armature and viscous damping ------------------------------------------------------------
@pytest.mark.parametrize("preset", ["HmJ", "Cm"])
def test_armature_adds_to_the_joint_inertia(preset):
    """A free joint under a constant torque: q̈ = τ / (I + I_a)."""
    i_a, tau, n = 0.05, 0.3, 100
    sim = pendulum(preset, axis="z", falling=True, armature=i_a)
    run(sim, tau, n)
    assert sim.u[-1] / (n * DT) == pytest.approx(tau / (I_J + i_a), rel=1e-5)


def test_pendulum_with_armature_and_viscous_damping_decays_as_the_closed_form():
    """Small swings (0.05 rad) about the hanging equilibrium: θ'' (I + I_a) + D θ' + m g l θ =
    0, ω_d = ω_n √(1 − ζ²), ω_n = √(m g l / (I + I_a)), ζ = D / (2 √(m g l (I + I_a))); the
    peaks decay by e^{−π ζ / √(1 − ζ²)} per half period."""
    i_a, d = 0.05, 0.02
    theta = run(pendulum(angle=0.05, armature=i_a, viscous_damping=d), 0.0, 3000)
    k, inertia = M * G * L, I_J + i_a
    zeta = d / (2.0 * np.sqrt(k * inertia))
    omega_d = np.sqrt(k / inertia) * np.sqrt(1.0 - zeta ** 2)
    t = DT * np.arange(1, theta.size + 1)
    z = np.flatnonzero(np.diff(np.sign(theta)) != 0)
    crossings = t[z] - theta[z] * DT / (theta[z + 1] - theta[z])
    assert np.pi / np.mean(np.diff(crossings)) == pytest.approx(omega_d, rel=1e-3)
    peaks = np.array([np.abs(theta[a:b]).max() for a, b in zip(z[:-1], z[1:], strict=True)])
    decrement = np.mean(np.log(peaks[:-1] / peaks[1:]))
    assert decrement == pytest.approx(np.pi * zeta / np.sqrt(1.0 - zeta ** 2), rel=2e-3)


def test_viscous_damping_is_stable_at_any_step():
    """D Δt / I = 40 (an explicit damper is unstable beyond 2): the joint rate decays
    monotonically without changing sign, as the implicit law's 1 / (1 + D Δt / I) per step."""
    sim = pendulum(axis="z", falling=True, viscous_damping=1e4 * I_J)
    u = sim.u
    u[-1] = 1.0
    sim.reset(sim.q, u)
    rates = []
    for _ in range(5):
        sim.step()
        rates.append(sim.u[-1])
    ratio = np.array(rates[1:]) / np.array(rates[:-1])
    assert np.allclose(ratio, 1.0 / (1.0 + 1e4 * DT), rtol=1e-4)


# -- Coulomb friction ------------------------------------------------------------------------
@pytest.mark.parametrize("preset,form", [("HmJ", "delassus"), ("HmS", "delassus"),
                                         ("HmS", "velocity"), ("Cm", "delassus")])
def test_coulomb_friction_sticks_below_and_slips_above_the_breakaway_torque(preset, form):
    """No gravity torque: the joint sticks while |τ| ≤ τ_c (hard contacts: the friction
    impulse Λ_f = −τ Δt), slips above with q̈ = (τ − τ_c) / I, and the breakaway torque found
    by bisection is τ_c; in every prox (JOR, SOR; Delassus and velocity forms)."""
    tc = 0.5
    sim = pendulum(preset, axis="z", falling=True, coulomb_friction=tc, form=form)
    q0 = sim.q
    run(sim, 0.8 * tc, 100)
    assert abs(sim.u[-1]) < 1e-9 and abs(sim.q[-1]) < 1e-9
    if preset != "Cm":
        assert sim.state.last_bilateral[0] == pytest.approx(-0.8 * tc * DT, rel=1e-9)
    sim.reset(q0)
    run(sim, 1.6 * tc, 100)
    assert sim.u[-1] / (100 * DT) == pytest.approx(0.6 * tc / I_J, rel=1e-5)
    assert breakaway(sim, q0, 0.0, 2.0 * tc) == pytest.approx(tc, rel=1e-6)


def breakaway(sim, q0, lo, hi, up=True):
    """The torque at which the joint starts to move from rest at q0 (within 20 steps), by
    bisection of [lo, hi] (up: it moves above; else below)."""
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        sim.reset(q0)
        run(sim, mid, 20)
        if (abs(sim.u[-1]) > 1e-9) == up:
            hi = mid
        else:
            lo = mid
    return 0.5 * (lo + hi)


def test_breakaway_under_a_gravity_load():
    """Held by friction at 0.3 rad from hanging: it sticks while |τ − m g l sin θ| ≤ τ_c."""
    tc, angle = 2.0, 0.3
    sim = pendulum(angle=angle, coulomb_friction=tc)
    q0, load = sim.q, M * G * L * np.sin(angle)
    assert breakaway(sim, q0, load, load + 2 * tc) == pytest.approx(load + tc, rel=1e-6)
    assert breakaway(sim, q0, load - 2 * tc, load, up=False) == \
        pytest.approx(load - tc, rel=1e-6)


# -- torque bandwidth ------------------------------------------------------------------------
@pytest.mark.parametrize("preset", ["HmJ", "Cm"])
def test_torque_step_response_is_the_first_order_lag(preset):
    f = 30.0
    sim = pendulum(preset, axis="z", falling=True, torque_bandwidth=f)
    applied = []
    for _ in range(20):
        sim.step(np.array([1.0]))
        applied.append(sim.applied_torque[0])
    t = DT * np.arange(1, 21)
    assert np.allclose(applied, 1.0 - np.exp(-2 * np.pi * f * t), rtol=0, atol=1e-14)


def test_the_lag_runs_at_the_physics_rate_and_is_state():
    """Four physics steps per control step: each applies the next step of the lag; a
    snapshot carries the lag's state (the run from it is the same bit for bit)."""
    f = 30.0
    cfg = load_preset("HmJ").with_overrides(control_rate=250.0, steps_per_control=4,
                                            torque_bandwidth=f)
    sim = Simulator(cfg, description=RobotDescription.from_urdf_xml(pendulum_urdf("z")))
    sim.step(np.array([1.0]))
    t = DT * np.arange(1, 5)
    assert np.allclose(sim.applied_torques_per_step[:, 0], 1.0 - np.exp(-2 * np.pi * f * t),
                       rtol=0, atol=1e-14)
    snap = sim.snapshot()
    run(sim, -1.0, 5)
    q = sim.q
    sim.restore(snap)
    run(sim, -1.0, 5)
    assert np.array_equal(sim.q, q)


def test_recorded_lagged_torques_replay_the_run_bit_for_bit():
    """step_applied of a lagged run's torques (either record) applies them as they are: the
    replay from the same state is the run, bit for bit."""
    cfg = load_preset("HmJ").with_overrides(control_rate=250.0, steps_per_control=4,
                                            torque_bandwidth=30.0, viscous_damping=0.1)
    sim = Simulator(cfg, description=RobotDescription.from_urdf_xml(pendulum_urdf("z")))
    start, records, states = sim.snapshot(), [], []
    for k in range(10):
        sim.step(np.array([np.sin(k)]))
        records.append((sim.applied_torques_per_step, sim.replay_torques_per_step))
        states.append(sim.q)
    for which in (0, 1):
        sim.restore(start)
        for rec, q in zip(records, states, strict=True):
            sim.step_applied(rec[which])
            assert np.array_equal(sim.q, q), which


# -- StarlETH with its series elastic drives ---------------------------------------------------
def starleth_sea():
    """msg_configs/actuators/starleth_sea.yaml's actuator section, as overrides."""
    with open(os.path.join(config_dir(), "actuators", "starleth_sea.yaml")) as f:
        section = yaml.safe_load(f)["actuator"]
    return {f"actuator.{k}": v for k, v in section.items()}


@pytest.mark.parametrize("preset", ["HmJ", "Cm"])
def test_starleth_with_its_drives_stands_and_trots(preset):
    """1 s standing, then 3 s trotting at 0.3 m/s under the controller, without a fall."""
    from starleth_sim.tools.common.gait_run import run_gait
    r = run_gait(preset, "trot", 4.0, speed=0.3, **starleth_sea())
    assert r["error"] is None and r["nonconverged"] == 0
    assert r["min_height"] > 0.3 and r["max_tilt"] < 0.25
    assert r["distance"] > 0.5 * 0.3 * 3.0
