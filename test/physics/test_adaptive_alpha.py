"""solver.alpha: auto (prox.py, "Adaptive α"): the same physics as a fixed α, in fewer
iterations, without tuning, and bad values of solver.alpha rejected with file and field."""
import numpy as np
import pytest
import yaml
from pin_pgs_reference import pin_pgs_solve
from test_physics_analytic import G, body_sim, incline_sim
from test_solvers import SCHEMES, robot_problem, solve

from starleth_sim import Simulator, load_preset
from starleth_sim.physics import prox
from starleth_sim.physics.config import ConfigError
from starleth_sim.physics.description import RobotDescription, box_urdf, sphere_urdf


def test_alpha_auto_is_accepted_and_bad_values_name_file_and_field(tmp_path):
    assert load_preset("HmJ").with_overrides(alpha="auto").solver.alpha == "auto"
    data = load_preset("HmJ").to_dict()
    data["solver"]["alpha"] = "auto"
    path = tmp_path / "auto.yaml"
    path.write_text(yaml.safe_dump(data))
    assert load_preset(str(path)).solver.alpha == "auto"
    for bad, message in [("fast", "expected a number or auto, got 'fast'"),
                         (0, "must be > 0"), (-0.5, "must be > 0"), (2.0, "must be < 2"),
                         (True, "expected a number")]:
        data["solver"]["alpha"] = bad
        path = tmp_path / "bad.yaml"
        path.write_text(yaml.safe_dump(data))
        with pytest.raises(ConfigError, match="solver.alpha: " + message) as e:
            load_preset(str(path))
        assert str(e.value).startswith(f"{path}: solver.alpha")
    assert prox.alpha_setting("auto") == prox.ALPHA_AUTO < 0 and prox.alpha_setting(0.6) == 0.6


@pytest.mark.parametrize("u_scale,seed", [(0.0, 0), (0.05, 1), (0.5, 2)])
def test_auto_solves_the_robot_problems_like_pinocchio_in_fewer_iterations(u_scale, seed):
    """Every scheme and form with α = auto reaches Pinocchio's PGS solution (stick and slip
    contacts, see test_solvers) from a cold start, in fewer iterations than the fixed α of
    the presets (0.6) and than the best fixed α of the trot (0.9)."""
    p = robot_problem(u_scale, seed)
    ref = pin_pgs_solve(p["G"], p["c"], p["mu"], tol=1e-14)
    for form, scheme in SCHEMES:
        lam, u, it, status = solve(p, form, scheme, alpha=prox.ALPHA_AUTO)
        assert status == prox.STATUS_CONVERGED, (form, scheme, it)
        np.testing.assert_allclose(lam, ref, atol=1e-8, rtol=0, err_msg=f"{form}/{scheme}")
        np.testing.assert_allclose(u, p["u_free"] + p["MinvW"] @ lam, atol=1e-10)
        for alpha in (0.6, 0.9):
            _, _, it_fixed, _ = solve(p, form, scheme, alpha=alpha)
            assert it < it_fixed, (form, scheme, alpha, it, it_fixed)


def test_auto_spectral_step_is_one_over_the_largest_scaled_eigenvalue():
    """The spectral step r_s = r / λ_max: the power iteration's λ_max is that of the
    diagonally scaled G (JOR; within 1 %: four feet give four eigenvalues within 1 % of
    each other), of its 3x3 contact blocks (SOR)."""
    p = robot_problem(0.5, 2)
    G, na = p["G"], p["na"]
    r = np.empty(3 * na)
    prox.prox_parameters(np.diag(G).copy(), na, 1.0, r)
    S = np.sqrt(np.outer(r, r)) * G
    pat = prox.dense_problem_patterns(p["Wt"], p["MinvW"], G)
    for form in (prox.FORM_DELASSUS, prox.FORM_VELOCITY):
        jor = prox.ProxSettings(form, prox.SCHEME_JOR, 1e-6, 1e-6, 10, 0, False, -1.0)
        sor = jor._replace(scheme=prox.SCHEME_SOR)
        lam_jor = prox.auto_spectral_scale(jor, G, p["Wt"], p["MinvW"], pat, na, r)
        lam_sor = prox.auto_spectral_scale(sor, G, p["Wt"], p["MinvW"], pat, na, r)
        top = np.linalg.eigvalsh(S)[-1]     # a Rayleigh quotient: at most λ_max, and close
        assert 0.99 * top <= lam_jor <= top * (1 + 1e-12)
        blocks = max(np.linalg.eigvalsh(S[3 * i:3 * i + 3, 3 * i:3 * i + 3])[-1]
                     for i in range(na))
        assert lam_sor == pytest.approx(blocks, rel=1e-6)


def test_auto_rebound_is_the_fixed_alpha_rebound():
    """Ball dropped 1 m with ε_N = 0.5: the same velocities as α = 0.6 within the solver
    tolerance, and Newton's law."""
    vz = {}
    for alpha in (0.6, "auto"):
        sim = body_sim(sphere_urdf(0.1, 1.0), restitution_normal=0.5, tol_rel=1e-10,
                       tol_abs=1e-12, alpha=alpha)
        q = sim.q
        q[2] += 1.0
        sim.reset(q)
        v = []
        for _ in range(520):
            assert sim.step().converged
            v.append(sim.base_state()["linear_velocity"][2])
        vz[alpha] = np.array(v)
    np.testing.assert_allclose(vz["auto"], vz[0.6], atol=1e-8)
    k = int(np.argmax(np.diff(vz["auto"]) > 1.0))
    assert vz["auto"][k] == pytest.approx(-np.sqrt(2 * G), rel=0.01)
    assert vz["auto"][k + 1] == pytest.approx(-0.5 * vz["auto"][k], rel=0.01)


@pytest.mark.parametrize("scheme", ["jor", "sor"])
def test_auto_incline_sticks_and_slides_like_the_fixed_alpha(scheme):
    """Box on a 30° incline: sticks at μ = 0.6 > tan 30°, slides at μ = 0.5 with
    a = g (sin θ − μ cos θ), the same trajectory as the fixed α of the analytic tests."""
    fixed = 1.0 if scheme == "sor" else 0.3
    sim, _ = incline_sim(0.6, scheme, "auto")
    p0 = sim.q[:3]
    for _ in range(500):
        assert sim.step().converged
    assert np.linalg.norm(sim.q[:3] - p0) < 1e-6
    theta = np.deg2rad(30.0)
    s = {}
    for alpha in (fixed, "auto"):
        sim, downhill = incline_sim(0.5, scheme, alpha, theta)
        p0 = sim.q[:3]
        s[alpha] = []
        for _ in range(600):
            assert sim.step().converged
            s[alpha].append((sim.q[:3] - p0) @ downhill)
    np.testing.assert_allclose(s["auto"], s[fixed], atol=1e-7)
    t = sim.dt * np.arange(1, 601)
    a_fit = 2 * np.polyfit(t[100:], s["auto"][100:], 2)[0]
    assert a_fit == pytest.approx(G * (np.sin(theta) - 0.5 * np.cos(theta)), rel=0.01)


def test_auto_converges_where_a_fixed_alpha_must_be_tuned():
    """Box resting on 4 corners (rank-deficient G): α = 1.9 cycles (test_solvers); auto needs
    no tuning and no fallback, and gives the weight impulse."""
    cfg = load_preset("HmJ").with_overrides(alpha="auto", max_iterations=200,
                                            fallback_alpha_factor=0.0, tol_abs=1e-12)
    sim = Simulator(cfg, description=RobotDescription.from_urdf_xml(box_urdf()))
    q = sim.q
    q[2] -= 1e-9
    sim.reset(q)
    mass = 1.0     # box_urdf's default
    for _ in range(20):
        d = sim.step()
        assert d.converged and not d.retried
    total = sum(c.impulse[2] for c in sim.contacts)
    assert total == pytest.approx(mass * G * sim.dt, rel=1e-6)


@pytest.mark.parametrize("preset,best_fixed", [("HmJ", 0.9)])
def test_auto_trots_in_fewer_iterations_than_the_best_fixed_alpha(preset, best_fixed):
    """Standing 0.2 s then trotting 0.8 s (one gait cycle), controller in the loop, no
    fallback: every step converges, in fewer mean iterations than the best fixed α of the
    Fig. 6 sweep (eval/report.md) of the configuration."""
    from starleth_sim.tools.evaluation.tasks import task_fig6
    auto = task_fig6(preset, "trot", "auto", 1.0)
    fixed = task_fig6(preset, "trot", best_fixed, 1.0)
    assert auto["converged"] and auto["nonconverged"] == 0 and auto["error"] is None
    assert fixed["converged"]
    assert auto["mean_iterations"] < fixed["mean_iterations"]


def test_relaxed_bilateral_rows_trot_in_fewer_iterations_than_auto():
    """HMJP's bilateral rows swept Gauss-Seidel at ω_B = 1.5 (bilateral.relaxation; auto
    relaxes them its own way) at the best fixed α of the Fig. 6 sweep beat auto (issue #49:
    ~47 against ~108 mean iterations), which beat the paper's α/G_BB rows there."""
    from starleth_sim.tools.evaluation.tasks import task_fig6
    auto = task_fig6("HMJP", "trot", "auto", 1.0)
    fixed = task_fig6("HMJP", "trot", 0.7, 1.0)
    assert auto["converged"] and fixed["converged"] and fixed["nonconverged"] == 0
    assert fixed["mean_iterations"] < 0.7 * auto["mean_iterations"]
