"""``starleth-eval`` (``make eval``): the paper's evaluation, headless, controller in the loop.

Writes ``eval/report.md``, ``eval/results.json`` and PNG figures:
  * Table 1 - steps/s and real-time factor per configuration while trotting (mean ± std over
    the gait cycles of the run), beside the paper's figures, and the ratio;
  * Fig. 5  - normal contact force of the LF foot over one trot cycle: compliant (Cm), hard
    (HmJ), and Cm with 10x damping at a 4x smaller step;
  * Fig. 6  - prox iterations per step against α, per configuration and gait, and the
    largest α for which every step converged (the "upper limit");
  * Fig. 7  - time per step by phase (M and h, M^-1, G (and G_B^-1), u^E (prox), rest);
  * accuracy - foot sink while trotting (Cm), unilateral drift while standing, bilateral drift
    while trotting, for every configuration where they apply;
  * robustness - the push-over stress test per configuration;
  * terrain - standing on a step, stairs, a slope and rough ground per configuration: falls,
    penetration, iterations, steps/s (``evaluation_terrain``; ``--quick``: HmJ on the stairs);
  * speed beside MuJoCo - ``starleth-bench --vs-mujoco`` (HmJ, HmS, Cm; run alone after the
    other tasks; skipped with a note where mujoco is not installed).
Runs are independent tasks, a predefined sweep executed by starleth-sweep's machinery
(:func:`starleth_sim.tools.common.task_pool.execute`: a process pool, ``--jobs``, default all cores,
or Ray with ``--ray auto|local|ADDRESS``; progress with ETA); starleth-sweep's runs are
:func:`starleth_sim.tools.common.gait_run.run_gait`, the one headless run of both. ``--quick``
shortens every run (for CI); the figures are then noisier but complete.

This module: the plan of the tasks and the command line; the tasks are in
``evaluation_tasks``, the figures and the report in ``evaluation_report``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from ...physics.config import PRESETS as TABLE1  # the paper's Table 1, in its order
from ..bench import bench
from ..common.task_pool import SweepError, execute
from .report import make_figures, write_report
from .tasks import (
    CONTACT_VARIANTS,
    task_bilateral_drift,
    task_contact_variant,
    task_fig5_damped,
    task_fig6,
    task_fig7,
    task_pushover,
    task_table1,
    task_unilateral_drift,
)
from .terrain import terrain_tasks

FIG6_CONFIGS = TABLE1[1:]      # the hard-contact ones


def plan(quick: bool, configs):
    s = dict(table1=3.0 if quick else 21.0, fig5=3.0 if quick else 4.0,
             fig7=2.0 if quick else 5.0, fig6=1.2 if quick else 4.0,
             drift=3.0 if quick else 60.0, push=2.0 if quick else 4.0,
             variants=2.0 if quick else 5.0, terrain=1.0 if quick else 5.0)
    alphas = (0.2, 0.6, 1.0, 1.4, 1.8) if quick else tuple(np.round(np.arange(0.1, 2.0, 0.1), 2))
    fig6_configs = [c for c in (("HmJ", "HmS", "HMJP", "HMSP") if quick else FIG6_CONFIGS)
                    if c in configs]
    tasks = [(task_table1, dict(preset=c, seconds=s["table1"])) for c in configs]
    if "Cm" in configs:
        tasks.append((task_fig5_damped, dict(seconds=s["fig5"])))
    tasks += [(task_fig7, dict(preset=c, seconds=s["fig7"])) for c in configs]
    tasks += [(task_fig6, dict(preset=c, gait=g, alpha=float(a), seconds=s["fig6"]))
              for c in fig6_configs for g in ("stand", "trot") for a in alphas]
    tasks += [(task_fig6, dict(preset=c, gait=g, alpha="auto", seconds=s["fig6"]))
              for c in fig6_configs for g in (("trot",) if quick else ("stand", "trot"))]
    tasks += [(task_unilateral_drift, dict(preset=c, seconds=s["drift"]))
              for c in configs if c != "Cm"]
    tasks += [(task_bilateral_drift, dict(preset=c, seconds=s["drift"]))
              for c in configs if c[:2] in ("HE", "HM")]
    tasks += [(task_pushover, dict(preset=c, seconds=s["push"])) for c in configs]
    if "HmJ" in configs:
        tasks += [(task_contact_variant, dict(label=lab, overrides=ov, seconds=s["variants"]))
                  for lab, ov in CONTACT_VARIANTS]
    tasks += terrain_tasks(quick, configs, s["terrain"])
    return tasks


def run_all(quick=False, jobs=None, configs=TABLE1, ray=None):
    """Every task of the plan on starleth-sweep's machinery (a process pool of `jobs`, or
    Ray), with its progress bar; returns (results, elapsed seconds)."""
    t0 = time.time()
    results = execute(plan(quick, configs), jobs or os.cpu_count() or 1, ray)
    return results, time.time() - t0


def vs_mujoco(quick=False, configs=TABLE1):
    """`starleth-bench --vs-mujoco` on the presets of its default set that are in `configs`,
    alone in this process after the other tasks (a speed comparison must not share the
    machine with them): a result record {"kind": "vs_mujoco", ...}, None when no such
    preset is selected. mujoco is optional: without it the record says so."""
    presets = [p for p in bench.VS_MUJOCO_PRESETS if p in configs]
    if not presets:
        return None
    rounds, steps = (2, 500) if quick else (5, 2000)
    r = bench.measure_vs_mujoco(presets, rounds, steps)
    if r is None:
        return {"kind": "vs_mujoco", "missing": True}
    return {"kind": "vs_mujoco", "missing": False, "header": r.header(),
            "rows": [{"name": row.name, "dt_ms": row.dt * 1e3, "median": row.median,
                      "min": min(row.rates), "max": max(row.rates), "ratio": r.ratio(row),
                      "normal_force_ratio": row.normal_force_ratio,
                      "height_mm": row.height * 1e3} for row in r.rows],
            "problems": r.problems, "like_with_like": r.like_with_like()}


def main(argv=None):
    ap = argparse.ArgumentParser(prog="starleth-eval", description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="short runs (CI)")
    ap.add_argument("--jobs", type=int, default=None, help="worker processes (default: all cores)")
    ap.add_argument("--out", default="eval", help="output directory (default: eval/)")
    ap.add_argument("--configs", nargs="*", default=list(TABLE1), help="configurations")
    ap.add_argument("--ray", default=None, metavar="auto|local|ADDRESS",
                    help="run the tasks on Ray instead of local processes (see starleth-sweep)")
    args = ap.parse_args(argv)
    unknown = [c for c in args.configs if c not in TABLE1]
    if unknown:
        ap.error(f"unknown configurations {unknown}; known: {list(TABLE1)}")
    os.makedirs(args.out, exist_ok=True)
    jobs = args.jobs or os.cpu_count() or 1
    try:
        results, elapsed = run_all(args.quick, jobs, tuple(args.configs), args.ray)
    except SweepError as e:      # --ray without Ray, or no cluster to join
        print(f"starleth-eval: error: {e}", file=sys.stderr)
        return 1
    speed = vs_mujoco(args.quick, tuple(args.configs))
    if speed is not None:
        results.append(speed)
    figs = make_figures(results, args.out)
    with open(os.path.join(args.out, "results.json"), "w") as f:
        json.dump([{k: v for k, v in r.items() if k not in ("lf_t", "lf_force")}
                   for r in results], f, indent=1)
    write_report(results, figs, args.out, args.quick, elapsed, jobs)
    print(f"report: {os.path.join(args.out, 'report.md')} ({len(results)} runs, {elapsed:.0f} s)")
    failed = [r for r in results if r.get("kind") == "table1" and r.get("error")]
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
