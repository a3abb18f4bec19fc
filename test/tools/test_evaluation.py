"""`starleth-eval --quick`: the paper's evaluation runs end to end and writes its report."""
import json
import os

import pytest

from starleth_sim.tools.evaluation import evaluation


@pytest.fixture(scope="module")
def quick_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("eval")
    rc = evaluation.main(["--quick", "--out", str(out)])
    return rc, out


def test_quick_evaluation_writes_report_and_figures(quick_report):
    rc, out = quick_report
    assert rc == 0
    report = (out / "report.md").read_text()
    for name in evaluation.TABLE1:
        assert f"| {name} |" in report
    # the paper's figures stand beside ours
    for paper in ("8,900", "5,400", "4,700", "2,700", "1,600", "4.4 mm", "750 µm/min",
                  "0.59 µm/min"):
        assert paper in report
    for fig in ("fig5_contact_force.png", "fig6_iterations_vs_alpha.png",
                "fig7_time_breakdown.png"):
        path = out / fig
        assert path.exists() and path.stat().st_size > 20_000, fig  # a real plot, not empty
        assert f"]({fig})" in report


def test_quick_evaluation_results_are_measurements(quick_report):
    _, out = quick_report
    results = json.loads((out / "results.json").read_text())
    t1 = {r["preset"]: r for r in results if r["kind"] == "table1"}
    assert set(t1) == set(evaluation.TABLE1)
    for r in t1.values():
        assert r["error"] is None and r["steps_per_second"] > 100 and r["min_height"] > 0.3
    assert 2.0 < t1["Cm"]["foot_sink_mean_mm"] < 8.0   # m g / (2 c_N) per stance foot ~ 4.4 mm
    push = {r["preset"]: r for r in results if r["kind"] == "pushover"}
    for r in push.values():
        assert r["completed"] and not r["nonfinite"] and r["fell"]
        assert any("knee" in c for c in r["knee_trunk_contacts"])
        assert any("trunk" in c for c in r["knee_trunk_contacts"])
    drift = [r for r in results if r["kind"] == "bilateral_drift"]
    assert len(drift) == 8
    # the side-by-side speed run (mujoco is a test requirement): the same thing simulated
    speed = [r for r in results if r["kind"] == "vs_mujoco"]
    assert len(speed) == 1 and not speed[0]["missing"]
    assert [row["name"] for row in speed[0]["rows"]] == ["MuJoCo", "MuJoCo noslip", "HmJ", "HmS",
                                                         "Cm"]
    assert speed[0]["problems"] == []
    for row in speed[0]["rows"]:
        assert row["median"] > 100 and abs(row["normal_force_ratio"] - 1.0) < 0.02
    report = (out / "report.md").read_text()
    assert "## Speed beside MuJoCo" in report and "| HmJ | 2.5 |" in report
    # the terrain (quick: HmJ standing on 3 cm stairs, the feet landing from up to 6 cm)
    (terrain,) = [r for r in results if r["kind"] == "terrain"]
    assert (terrain["preset"], terrain["terrain"], terrain["error"]) == ("HmJ", "stairs", None)
    assert not terrain["fell"] and 0.3 < terrain["height"] < 0.45
    assert 0.0 < terrain["penetration_max_mm"] < 5.0 and terrain["steps_per_second"] > 100
    assert terrain["mean_iterations"] > 1.0
    assert "## Terrain" in report and "| stairs | HmJ | no (" in report
    assert os.path.getsize(out / "results.json") > 1000


def test_terrain_section_alone_updates_an_existing_report(tmp_path):
    """python -m starleth_sim.tools.evaluation.terrain: the Terrain section of a report is put
    before the speed beside MuJoCo, then replaced in place (the rest kept, byte for byte),
    and results.json's terrain records with it."""
    from starleth_sim.tools.evaluation.terrain import update_report
    head, tail = "# R\n\n## Robustness\n\n| a |\n", "\n## Speed beside MuJoCo\n\n| b |\n"
    (tmp_path / "report.md").write_text(head + tail)
    (tmp_path / "results.json").write_text(json.dumps([{"kind": "table1"}]))
    rec = dict(kind="terrain", preset="HmJ", terrain="step", seconds=1.0, error=None,
               fell=False, max_tilt_deg=1.0, penetration_max_mm=0.001,
               penetration_mean_mm=0.0005, mean_iterations=5.0, max_iterations=9,
               nonconverged=0, steps_per_second=1000.0)
    update_report(str(tmp_path), [rec])
    first = (tmp_path / "report.md").read_text()
    assert first.startswith(head + "\n## Terrain") and first.endswith("|\n" + tail)
    assert "| step | HmJ | no (1.0°) | 1.00 / 0.500 | 5.0 (9) | 0 | 1000 |" in first
    update_report(str(tmp_path), [dict(rec, terrain="rough")])
    second = (tmp_path / "report.md").read_text()
    assert second == first.replace("| step | HmJ", "| rough | HmJ")
    kinds = [r["kind"] for r in json.loads((tmp_path / "results.json").read_text())]
    assert kinds == ["table1", "terrain"]
