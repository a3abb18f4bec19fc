"""Analytic checks of the time-stepper on generic bodies (same code path as the robot)."""
import numpy as np
import pinocchio as pin
import pytest

from starleth_sim import Simulator, load_preset
from starleth_sim.physics.description import RobotDescription, box_urdf, sphere_urdf

G = 9.81  # pin's default gravity


def body_sim(urdf, **overrides):
    cfg = load_preset("HmJ").with_overrides(control_rate=1000.0, steps_per_control=1, **overrides)
    return Simulator(cfg, description=RobotDescription.from_urdf_xml(urdf))


def test_ball_rebound_follows_newton_restitution():
    eps, h = 0.5, 1.0
    sim = body_sim(sphere_urdf(0.1, 1.0), restitution_normal=eps, tol_rel=1e-10, tol_abs=1e-12)
    assert sim.dt == pytest.approx(1e-3)
    q = sim.q
    q[2] += h
    sim.reset(q)
    vz = []
    for _ in range(700):
        sim.step()
        vz.append(sim.base_state()["linear_velocity"][2])
    vz = np.array(vz)
    k = int(np.argmax(np.diff(vz) > 1.0))  # the impact step
    v_minus, v_plus = vz[k], vz[k + 1]
    assert v_minus == pytest.approx(-np.sqrt(2 * G * h), rel=0.01)
    assert v_plus == pytest.approx(-eps * v_minus, rel=0.01)
    # the rebound is free flight again: apex at ε² h, up to the overlap the impact step
    # starts from (at most one step's travel, v⁻ Δt)
    z = []
    for _ in range(400):
        sim.step()
        z.append(sim.q[2] - 0.1)
    assert max(z) == pytest.approx(eps ** 2 * h, abs=1.2 * abs(v_minus) * sim.dt)


def test_ball_inelastic_rests_with_weight_impulse_and_no_drift():
    m = 2.0
    sim = body_sim(sphere_urdf(0.1, m), restitution_normal=0.0, tol_rel=1e-12, tol_abs=1e-14)
    z0 = sim.q[2]
    for _k in range(2000):
        d = sim.step()
        lam = sim.contacts[0].impulse
        assert lam[2] == pytest.approx(m * G * sim.dt, rel=1e-6)
        assert abs(lam[0]) < 1e-12 and abs(lam[1]) < 1e-12
        assert d.converged
    assert abs(sim.q[2] - z0) < 1e-9
    assert np.linalg.norm(sim.u) < 1e-9


INCLINE = np.deg2rad(30.0)      # incline_sim's slope


def incline_sim(mu, scheme, alpha, theta=INCLINE):
    normal = (-np.sin(theta), 0.0, np.cos(theta))
    sim = body_sim(box_urdf((0.2, 0.2, 0.2), 1.0), normal=normal, mu=mu, scheme=scheme,
                   alpha=alpha, tol_rel=1e-8, tol_abs=1e-10)
    R = pin.utils.rotate("y", -theta)  # box bottom face parallel to the plane
    quat = pin.Quaternion(R)
    q = sim.q
    q[3:7] = [quat.x, quat.y, quat.z, quat.w]
    q[0:3] = np.array(normal) * (0.1 - 1e-9)  # resting on the plane (1 nm overlap)
    sim.reset(q)
    downhill = np.array([-np.cos(theta), 0.0, -np.sin(theta)])
    return sim, downhill


@pytest.mark.parametrize("scheme,alpha", [("sor", 1.0), ("jor", 0.3)])
def test_box_on_incline_sticks_when_mu_exceeds_tan_theta(scheme, alpha):
    sim, _ = incline_sim(0.6, scheme, alpha)  # tan 30° = 0.577 < 0.6
    p0 = sim.q[:3]
    for _ in range(2000):  # 2 s
        d = sim.step()
        assert d.converged
    assert np.linalg.norm(sim.q[:3] - p0) < 1e-6


@pytest.mark.parametrize("scheme,alpha", [("sor", 1.0), ("jor", 0.3)])
def test_box_on_incline_slides_with_coulomb_acceleration(scheme, alpha):
    theta, mu = np.deg2rad(30.0), 0.5
    sim, downhill = incline_sim(mu, scheme, alpha, theta)
    p0 = sim.q[:3]
    s, t = [], []
    for _ in range(2000):
        sim.step()
        s.append((sim.q[:3] - p0) @ downhill)
        t.append(sim.t)
    a_fit = 2 * np.polyfit(t[100:], s[100:], 2)[0]
    a_exact = G * (np.sin(theta) - mu * np.cos(theta))
    assert a_exact == pytest.approx(0.6572, abs=1e-4)
    assert a_fit == pytest.approx(a_exact, rel=0.01)


def test_box_sliding_on_flat_ground_stops_after_coulomb_distance():
    v0, mu = 1.0, 0.3
    sim = body_sim(box_urdf((0.2, 0.2, 0.2), 1.0), mu=mu, scheme="sor", alpha=1.0,
                   tol_rel=1e-8, tol_abs=1e-10)
    q = sim.q
    q[2] -= 1e-9
    u = np.zeros(6)
    u[0] = v0
    sim.reset(q, u)
    x0 = sim.q[0]
    for _ in range(1000):
        sim.step()
    distance = sim.q[0] - x0
    assert distance == pytest.approx(v0 ** 2 / (2 * mu * G), rel=0.01)
    assert v0 ** 2 / (2 * mu * G) == pytest.approx(0.1699, abs=1e-4)
    assert abs(sim.u[0]) < 1e-9  # at rest, held by static friction


def test_sphere_starts_rolling_at_five_sevenths():
    v0, mu, r = 1.0, 0.3, 0.1
    sim = body_sim(sphere_urdf(r, 1.0), mu=mu, tol_rel=1e-10, tol_abs=1e-12)
    u = np.zeros(6)
    u[0] = v0
    sim.reset(None, u)
    for _ in range(300):  # rolling starts at t = 2 v0 / (7 μ g) = 0.097 s
        sim.step()
    st = sim.base_state()
    v, w = st["linear_velocity"][0], st["angular_velocity"][1]
    assert v == pytest.approx(5.0 / 7.0 * v0, rel=0.01)
    assert w * r == pytest.approx(v, rel=1e-6)  # rolling without slipping


def test_per_contact_restitution_overrides_the_default():
    """Two balls, identical but for the per-contact ε: rebound at ε_i v⁻ each."""
    for eps in (0.2, 0.8):
        sim = body_sim(sphere_urdf(0.1, 1.0), restitution_normal=0.5, tol_rel=1e-10,
                       tol_abs=1e-12, restitution_overrides={"ball": [eps, 0.0]})
        q = sim.q
        q[2] += 0.5
        sim.reset(q)
        vz = []
        for _ in range(400):
            sim.step()
            vz.append(sim.base_state()["linear_velocity"][2])
        k = int(np.argmax(np.diff(vz) > 0.5))
        assert vz[k + 1] == pytest.approx(-eps * vz[k], rel=1e-6)


def test_restitution_override_of_unknown_contact_is_rejected():
    from starleth_sim import ConfigError
    with pytest.raises(ConfigError, match="unknown contact 'nose'"):
        body_sim(sphere_urdf(), restitution_overrides={"nose": [0.5, 0.0]})


def compliant_box(**overrides):
    cfg = load_preset("Cm").with_overrides(control_rate=1000.0, steps_per_control=1, **overrides)
    box = RobotDescription.from_urdf_xml(box_urdf((0.2, 0.2, 0.2), 1.0))
    return Simulator(cfg, description=box)


def test_compliant_box_slides_and_stops_near_the_coulomb_distance():
    """Alg. 1 on a sliding box: slip with λ_T = μ λ_N, then stick (anchor reset)."""
    v0, mu = 1.0, 0.3
    sim = compliant_box(mu=mu)
    for _ in range(500):  # settle on the springs (sink m g / (4 c_N) per corner)
        sim.step()
    u = sim.u
    u[0] = v0
    sim.reset(sim.q, u)
    x0 = sim.q[0]
    slipping = []
    for _ in range(1000):
        sim.step()
        slipping.append(sim.state.slip[[n.endswith("n") for n in sim.contact_names]].any())
    d = sim.q[0] - x0
    assert d == pytest.approx(v0 ** 2 / (2 * mu * G), rel=0.05)
    assert slipping[0] and not slipping[-1]   # it slipped, then stuck
    assert abs(sim.u[0]) < 1e-3


def test_compliant_box_on_incline_sticks_on_its_springs():
    """μ = 0.8: the tangential springs hold it. (With μ = 0.6, barely above tan 30°, the
    compliant model creeps: its springs share the load equally, so the lightly loaded uphill
    corners slip first; the hard contact model finds the sticking solution, see above.)"""
    theta, mu = np.deg2rad(30.0), 0.8
    normal = (-np.sin(theta), 0.0, np.cos(theta))
    sim = compliant_box(mu=mu, normal=normal)
    R = pin.utils.rotate("y", -theta)
    quat = pin.Quaternion(R)
    q = sim.q
    q[3:7] = [quat.x, quat.y, quat.z, quat.w]
    q[0:3] = np.array(normal) * 0.1
    sim.reset(q)
    for _ in range(1000):
        sim.step()
    p1 = sim.q[:3]
    for _ in range(2000):
        sim.step()
    # the tangential springs hold it: no creep after settling
    assert np.linalg.norm(sim.q[:3] - p1) < 1e-6
    assert not sim.state.slip.any()
