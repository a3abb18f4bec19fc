"""The terrain part of ``starleth-eval``: the robot standing on each terrain of TERRAINS (a
step under its left feet, stairs under all four, a 5° slope, rough ground) with each
preset, under the controller's stand mode (its walking on terrain: test_terrain_walk.py):
whether it fell, the deepest foot below the surface under it after each step (hard presets;
``Simulator.gaps``, which measures against the nearest surface), prox iterations per step and
physics steps per second. The task (:func:`task_terrain`) and its report section
(:func:`terrain_section`); ``starleth-eval`` runs them with the rest. Alone, to refresh only
this section of an existing report (and its records in results.json)::

    python -m starleth_sim.tools.evaluation.terrain --out eval [--seconds 5] [--jobs N]

Every run starts from ``Simulator.default_state()``, the standing posture lowered (or raised)
until its lowest contact rests on the terrain: on uneven ground the other feet are in the air
and land within the first steps.
"""
from __future__ import annotations

import argparse
import json
import math
import os

import numpy as np

from ...physics.config import PRESETS as TABLE1
from ...physics.terrain import pack_terrain, terrain_height
from ..common.falls import fall_height
from ..common.gait_run import run_gait
from ..common.task_pool import execute

#: the terrains of the evaluation (physics overrides; the feet stand at x = ±0.25 m,
#: y = ±0.185 m)
TERRAINS = {
    # a 4 cm step under the left feet (the edge 3.5 cm inside of them)
    "step": {"boxes": [{"centre": [0.0, 0.35, 0.02], "size": [1.2, 0.4, 0.04]}]},
    # 3 cm stairs: the hind feet on the first step, the front feet on the third
    "stairs": {"stairs": {"rise": 0.03, "run": 0.25, "count": 4, "start": -0.4}},
    # the robot on a 5° ramp (2 m up from x = -1 m), facing uphill
    "slope": {"slope": {"angle": 5.0, "length": 2.0, "start": -1.0, "top": 1.0}},
    # ±1.5 cm, 0.4 m wavelength, 4 m x 4 m round the robot
    "rough": {"rough": {"amplitude": 0.015, "wavelength": 0.4, "seed": 1, "size": 4.0}},
}
#: fell: the trunk tilted more than this [rad] at some step, or it ended lower than
#: FALL_HEIGHT above the terrain under it (StarlETH's, standing at 0.415 m; scaled to the
#: robot's standing height: falls.fall_height)
FALL_TILT = math.radians(30.0)
FALL_HEIGHT = 0.25


def task_terrain(preset, terrain, seconds):
    """The robot standing on `terrain` (a key of TERRAINS) for `seconds` with `preset`."""
    kept = {}

    def keep(sim):
        kept["sim"] = sim
    r = run_gait(preset, "stand", seconds, perturb=keep, **TERRAINS[terrain])
    sim = kept["sim"]
    cfg = sim.config
    x, y, z = sim.base_state()["position"]
    ground = max(0.0, terrain_height(pack_terrain(cfg.terrain), x, y)) + cfg.ground.height
    wall = float(np.sum(r["wall"]))
    hard = cfg.contact_model == "hard"
    pen = np.asarray(r["foot_penetration"])
    return dict(kind="terrain", preset=preset, terrain=terrain, seconds=seconds,
                steps=r["steps"], error=r["error"], nonfinite=r["nonfinite"],
                fell=bool(r["error"] or r["max_tilt"] > FALL_TILT
                          or z - ground < fall_height(sim.description, FALL_HEIGHT)),
                max_tilt_deg=math.degrees(r["max_tilt"]), height=float(z - ground),
                penetration_max_mm=float(1e3 * pen.max()) if hard and len(pen) else None,
                penetration_mean_mm=float(1e3 * pen.mean()) if hard and len(pen) else None,
                mean_iterations=float(np.mean(r["iterations"])) / r["steps_per_control"]
                if r["iterations"] else float("nan"),
                max_iterations=int(np.max(r["iterations"])) if r["iterations"] else 0,
                nonconverged=r["nonconverged"],
                steps_per_second=r["physics_steps"] / wall if wall > 0 else float("nan"))


def terrain_tasks(quick, configs, seconds):
    """The terrain tasks of the plan: every preset of `configs` on every terrain; quick:
    HmJ (if selected) on the stairs alone (the quick evaluation stays quick)."""
    if quick:
        return [(task_terrain, dict(preset="HmJ", terrain="stairs", seconds=seconds))
                for c in configs if c == "HmJ"]
    return [(task_terrain, dict(preset=c, terrain=t, seconds=seconds))
            for c in configs for t in TERRAINS]


def _fmt(x, fmt):
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else fmt % x


def terrain_section(results):
    """The report's "Terrain" section (none without terrain records)."""
    rows = [r for r in results if r["kind"] == "terrain"]
    if not rows:
        return []
    seconds = rows[0]["seconds"]
    lines = ["", "## Terrain: standing on a step, stairs, a slope, rough ground", "",
             f"The controller's stand mode for {seconds:g} s on each terrain, from the "
             "standing posture resting on the "
             "terrain by its lowest contact (the other feet land in the first steps). "
             "step: 4 cm under the left feet; stairs: 3 cm steps, the hind feet on the first, "
             "the front feet on the third; slope: 5°, facing uphill; rough: ±1.5 cm, "
             "wavelength 0.4 m (`starleth_sim/tools/evaluation/terrain.py`). Fell: tilt "
             f"> {math.degrees(FALL_TILT):.0f}° or the trunk below {FALL_HEIGHT} m above the "
             "terrain at the end. Penetration: the deepest foot below the surface under it "
             "after each step, landing included (hard presets; the compliant model sinks by "
             "design). Steps/s: physics steps per second of `Simulator.step`.", "",
             "| terrain | config | fell (max tilt) | penetration max / mean [µm] | "
             "iterations / step (max) | non-converged steps | steps/s |",
             "|---|---|---|---|---|---|---|"]
    order = list(TERRAINS)
    for r in sorted(rows, key=lambda r: (order.index(r["terrain"]), TABLE1.index(r["preset"]))):
        fell = "yes" if r["fell"] else "no"
        if r["error"]:
            fell += f" ({r['error'][:60]})"
        pen = "-" if r["penetration_max_mm"] is None else \
            f"{1e3 * r['penetration_max_mm']:.2f} / {1e3 * r['penetration_mean_mm']:.3f}"
        lines.append(f"| {r['terrain']} | {r['preset']} | {fell} ({r['max_tilt_deg']:.1f}°) | "
                     f"{pen} | {_fmt(r['mean_iterations'], '%.1f')} ({r['max_iterations']}) | "
                     f"{r['nonconverged']} | {_fmt(r['steps_per_second'], '%.0f')} |")
    return lines


def update_report(out_dir, results):
    """Replace the terrain section of `out_dir`/report.md (or put it before the speed beside
    MuJoCo, or at the end) and the terrain records of results.json by `results`."""
    path = os.path.join(out_dir, "report.md")
    lines = open(path).read().rstrip("\n").split("\n")
    heads = [i for i, x in enumerate(lines) if x.startswith("## ")]

    def before(i):       # the index of heading i's blank line before it (or of the heading)
        return len(lines) if i is None else (i - 1 if i and not lines[i - 1] else i)
    start = next((i for i in heads if lines[i].startswith("## Terrain")), None)
    if start is not None:
        at = before(start)
        del lines[at:before(next((i for i in heads if i > start), None))]
    else:
        at = before(next((i for i in heads if lines[i].startswith("## Speed beside")), None))
    lines[at:at] = terrain_section(results)
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")
    rpath = os.path.join(out_dir, "results.json")
    old = json.load(open(rpath)) if os.path.exists(rpath) else []
    with open(rpath, "w") as f:
        json.dump([r for r in old if r.get("kind") != "terrain"] + results, f, indent=1)


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m starleth_sim.tools.evaluation.terrain",
                                 description="starleth-eval's terrain part alone: update the "
                                             "Terrain section of an existing report.")
    ap.add_argument("--out", default="eval", help="the report's directory (default: eval/)")
    ap.add_argument("--seconds", type=float, default=5.0, help="seconds of each run")
    ap.add_argument("--jobs", type=int, default=None, help="worker processes (default: all)")
    ap.add_argument("--configs", nargs="*", default=list(TABLE1), help="configurations")
    args = ap.parse_args(argv)
    if not os.path.isfile(os.path.join(args.out, "report.md")):
        ap.error(f"no report in {args.out}/: run starleth-eval first")
    unknown = [c for c in args.configs if c not in TABLE1]
    if unknown:
        ap.error(f"unknown configurations {unknown}; known: {list(TABLE1)}")
    results = execute(terrain_tasks(False, tuple(args.configs), args.seconds),
                      args.jobs or os.cpu_count() or 1)
    update_report(args.out, results)
    print(f"report: {os.path.join(args.out, 'report.md')} ({len(results)} terrain runs)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
