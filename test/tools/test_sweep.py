"""starleth-sweep: a spec expands into its grid, a bad spec gives one line naming the file and
field, a tiny sweep writes its table and plots, and the same sweep on a local Ray instance
(ray.init(num_cpus=2)) gives the same table as the process pool."""
import csv

import pytest

from starleth_sim.tools.sweep import sweep

TINY = """\
name: tiny
presets: [HmJ]
overrides:
  alpha: [0.6, 1.0]
scenarios:
  - kind: push
    seconds: 0.1
    at: 0.02
    duration: 0.05
    direction: [0, 2, 0]
    magnitude: [600]
seeds: [1]
perturbation:
  joint_angles: 0.01
"""


def _spec(tmp_path, text, name="spec.yaml"):
    p = tmp_path / name
    p.write_text(text)
    return str(p)


def test_spec_expands_into_the_grid(tmp_path):
    s = sweep.load_spec(_spec(tmp_path, """\
presets: [HmJ, Cm]
overrides: {alpha: [0.4, 0.6, 0.8]}
scenarios:
  - {kind: stand, seconds: 1}
  - {kind: push, magnitude: [100, 200], direction: [0, 0, -3]}
  - {kind: trot, speed: [0.2, 0.4]}
seeds: [0, 1]
"""))
    assert s.name == "spec" and s.override_keys == ["alpha"]
    assert len(s.runs) == 2 * 3 * (1 + 2 + 2) * 2
    assert [r.index for r in s.runs] == list(range(len(s.runs)))
    push = [r.scenario for r in s.runs if r.scenario.kind == "push"]
    assert {p.magnitude for p in push} == {100.0, 200.0}
    assert push[0].direction == (0.0, 0.0, -1.0)        # normalised
    assert {r.seed for r in s.runs} == {0, 1}


def test_robots_run_the_scenarios_scaled_to_their_size(tmp_path):
    """StarlETH's numbers for a Go1 (legs of thigh 0.213 m + calf 0.213 m, URDF): speeds
    x √λ, forces x μ, push durations x √λ (the scaling rule)."""
    from starleth_sim.physics.config import ConfigError
    from starleth_sim.robots import load_robot, robot_description, urdf_file
    try:
        urdf_file(load_robot("go1"))
    except ConfigError as e:
        pytest.skip(str(e))
    s = sweep.load_spec(_spec(tmp_path, """robots: [starleth, go1]
presets: [HmJ]
scenarios:
  - {kind: trot, speed: 0.3}
  - {kind: push, magnitude: 500, duration: 0.1}
perturbation: {base_velocity: 0.02, joint_angles: 0.01}
"""))
    by = {(r.robot, r.scenario.kind): r for r in s.runs}
    assert len(s.runs) == 4 and by["starleth", "trot"].scenario.speed == 0.3
    lam, mu = by["go1", "trot"].scale
    assert lam == pytest.approx((0.213 + 0.213) / 0.435, rel=1e-3)
    assert mu == pytest.approx(robot_description("go1").total_mass / 26.82, rel=1e-5)
    assert by["go1", "trot"].scenario.speed == pytest.approx(0.3 * lam ** 0.5, rel=1e-12)
    push = by["go1", "push"]
    assert push.scenario.magnitude == pytest.approx(500 * mu, rel=1e-12)
    assert push.scenario.duration == pytest.approx(0.1 * lam ** 0.5, rel=1e-12)
    assert dict(push.perturbation) == pytest.approx({"base_velocity": 0.02 * lam ** 0.5,
                                                     "joint_angles": 0.01})
    assert dict(by["starleth", "push"].perturbation)["base_velocity"] == 0.02


def test_a_go1_run_of_a_sweep_stands_under_its_own_controller(tmp_path):
    """robot: go1 runs the Go1 (run_gait(robot=)): it stands at its own height, below its
    spec's standing height and above the fall height scaled to it (0.2 m x 0.274 / 0.415)."""
    from starleth_sim.physics.config import ConfigError
    from starleth_sim.robots import load_robot, robot_description, urdf_file
    from starleth_sim.tools.common.falls import fall_height
    try:
        urdf_file(load_robot("go1"))
    except ConfigError as e:
        pytest.skip(str(e))
    s = sweep.load_spec(_spec(tmp_path, "robot: go1\npresets: [HmJ]\n"
                                        "scenarios: [{kind: stand, seconds: 0.3}]\n"))
    row = sweep.run_one(s.runs[0])
    desc = robot_description("go1")
    assert row["robot"] == "go1" and row["completed"] and not row["fell"]
    assert fall_height(desc, sweep.FALL_HEIGHT) < row["min_height"] <= desc.standing_height


def test_fall_height_scales_with_the_standing_height():
    from types import SimpleNamespace

    from starleth_sim.tools.common.falls import fall_height
    assert fall_height(SimpleNamespace(standing_height=0.415), 0.2) == 0.2
    assert fall_height(SimpleNamespace(standing_height=0.2075), 0.2) == pytest.approx(0.1)
    assert fall_height(SimpleNamespace(standing_height=None), 0.2) == 0.2


@pytest.mark.parametrize("text, words", [
    ("robots: [starleth, nope]\npresets: [HmJ]\nscenarios: [{kind: stand}]\n",
     ("spec.yaml", "robots[1]", "nope")),
    ("robot: starleth\nrobots: [go1]\npresets: [HmJ]\nscenarios: [{kind: stand}]\n",
     ("spec.yaml", "robot, robots")),
    ("robot: [go1]\npresets: [HmJ]\nscenarios: [{kind: stand}]\n", ("spec.yaml", "robot:")),
    ("presets: [HmJ]\nscenarios: [{kind: jump}]\n", ("spec.yaml", "scenarios[0].kind")),
    ("presets: [HmJ]\nscenarios: [{kind: stand, seconds: -1}]\n", ("scenarios[0].seconds",)),
    ("presets: [HmJ]\noverrides: {alpha: [2.5]}\nscenarios: [{kind: stand}]\n",
     ("spec.yaml", "alpha")),
    ("presets: [Nope]\nscenarios: [{kind: stand}]\n", ("unknown physics preset",)),
    ("presets: [HmJ]\nscenario: []\n", ("unknown field", "scenario")),
])
def test_bad_spec_gives_one_line(tmp_path, capsys, text, words):
    assert sweep.main([_spec(tmp_path, text)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("starleth-sweep: error:")
    for w in words:
        assert w in err[0], err[0]


def _same_table(a, b):
    """Equal rows of two results.csv, bit for bit but for the wall times: the simulator and
    the controller (ProxQP's portable build, force_distribution) are bit-reproducible across
    processes."""
    assert len(a) == len(b) and a and a[0].keys() == b[0].keys()
    for ra, rb in zip(a, b, strict=True):
        for k in ra:
            if k in sweep.TIMING_COLUMNS:
                continue
            assert ra[k] == rb[k], (k, ra[k], rb[k])


def _read(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def test_tiny_sweep_on_the_pool_and_on_ray_give_the_same_table(tmp_path):
    spec = _spec(tmp_path, TINY)
    out = tmp_path / "pool"
    assert sweep.main([spec, "--jobs", "2", "--out", str(out)]) == 0
    pool = _read(out / "results.csv")
    assert [r["alpha"] for r in pool] == ["0.6", "1.0"]
    assert (out / "iterations_vs_alpha.png").stat().st_size > 10_000
    for r in pool:
        assert r["steps"] == "40" and r["completed"] == "True" and r["push_direction"] == "0 1 0"
    # the push (30 N s lateral) tilts the robot (the initial perturbation alone: < 0.05°);
    # α changes the solver's work, not the physics (the same answer to the tolerance)
    tilt = [float(r["max_tilt_deg"]) for r in pool]
    assert tilt[0] > 0.3 and tilt[0] == pytest.approx(tilt[1], rel=1e-3)
    assert pool[0]["mean_iterations"] != pool[1]["mean_iterations"]
    ray = pytest.importorskip("ray", reason="Ray is an optional extra: pip install '.[ray]'")
    try:
        rows = sweep.run_sweep(sweep.load_spec(spec), ray="local",
                               ray_init=dict(num_cpus=2), show_progress=False)
    finally:
        ray.shutdown()
    sweep.write_table(rows, str(tmp_path / "ray"))
    _same_table(pool, _read(tmp_path / "ray" / "results.csv"))
