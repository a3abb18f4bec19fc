"""``starleth-sweep``: a grid of headless runs (Simulator + StarlethController in one process
per run, no ROS) over presets x overrides x scenarios x seeds, on a local process pool or
on Ray, with one results table and summary plots.

    starleth-sweep sweeps/push_recovery.yaml                 # process pool, all cores
    starleth-sweep sweeps/alpha.yaml --jobs 2 --out sweep_out/
    starleth-sweep sweeps/push_recovery.yaml --ray auto      # a running Ray cluster
    starleth-sweep sweeps/push_recovery.yaml --ray local     # a Ray instance on this host

The spec (YAML, validated on load; a bad field is reported with the file and field):

    name: push_recovery
    robots: [starleth, go1]           # optional: library names or paths, or `all`; or
                                      # robot: go1 (default: the presets' robot, StarlETH)
    presets: [HmJ, Cm]                # preset names (msg_configs/) or YAML paths
    overrides:                        # physics overrides, each a list: the grid is their product
      alpha: [0.4, 0.6]               # any key Simulator.from_preset(**overrides) takes
    scenarios:
      - kind: stand                   # stand | trot | push
        seconds: 2.0
      - kind: trot
        seconds: 3.0
        speed: [0.2, 0.4]             # a list in a scenario expands the grid too
      - kind: push                    # standing robot pushed on the base
        seconds: 2.0
        at: 0.5                       # s
        duration: 0.1                 # s
        direction: [0, 1, 0]          # world axes (normalised)
        magnitude: [100, 300, 700]    # N
    seeds: [0, 1, 2]                  # initial perturbations (seed 0 included)
    perturbation:                     # standard deviations of the initial perturbation
      joint_angles: 0.02              # rad, every joint
      base_velocity: 0.05             # m/s, world linear velocity of the base

The scenarios' numbers are StarlETH's; each robot runs them scaled by the one rule of
``starleth_interface/robot/scaling.py`` (λ its leg length, μ its mass relative to
StarlETH's): trot speeds and the base velocity perturbation x √λ, push forces x μ and push
durations x √λ (an impulse x μ √λ); the table has the values used, with λ and μ. A run
"fell" below FALL_HEIGHT scaled to the robot's standing height (:mod:`..common.falls`).

Every run is one task (:func:`run_one` of a :class:`RunSpec`); results stream back as
they finish (a progress bar with ETA on stderr) and the table is in grid order whatever the
order of completion, so the process pool and Ray give the same table (timing columns
aside). Outputs in ``--out`` (default ``<spec>_sweep/``): ``results.csv`` (and
``results.parquet`` where pyarrow is installed), ``push_falls.png`` (fall fraction against
push magnitude per preset) and ``iterations_vs_<override>.png`` (prox iterations per step
against each numeric override with several values, e.g. α), and a printed summary.

Ray is an optional extra (``pip install .[ray]``, or ``make ray``). ``--ray auto`` joins
the cluster started with ``ray start --head`` (``ADDRESS`` e.g. ``ray://host:10001`` another
one; its workers need starleth_sim installed), ``--ray local`` starts one on this host. The
same :func:`starleth_sim.tools.common.task_pool.execute` runs ``starleth-eval``'s tasks, runs of the
same :func:`starleth_sim.tools.common.gait_run.run_gait`.
"""
from __future__ import annotations

import argparse
import csv
import itertools
import math
import os
import sys
import time
from dataclasses import dataclass, field, replace

import numpy as np

from starleth_interface.robot.scaling import robot_scale
from starleth_interface.yaml_files import load_yaml_file

from ...physics.config import ConfigError, load_preset
from ...robots import available_robots, config_with_robot, robot_description
from ...ros.state_io import minimal_state, public_state
from ..common.falls import fall_height
from ..common.gait_run import run_gait
from ..common.task_pool import SweepError, execute

PROG = "starleth-sweep"
SCENARIOS = ("stand", "trot", "push")
#: scenario fields: name -> (default, kind); 'num' fields may be lists (grid), 'vec' not
SCENARIO_FIELDS = {"kind": (None, "str"), "seconds": (2.0, "num"), "speed": (0.3, "num"),
                   "stand_time": (1.0, "num"), "at": (0.5, "num"), "duration": (0.1, "num"),
                   "magnitude": (0.0, "num"), "direction": ((0.0, 1.0, 0.0), "vec")}
#: the range of each number of a spec: name -> (low, high, low excluded). Times up to an
#: hour of simulated time per run; speeds up to 10 m/s either way (StarlETH trots < 1 m/s);
#: pushes up to 1 MN (StarlETH weighs ~250 N); seeds as numpy's generators take them
#: (unsigned 32 bits); perturbations up to 1 rad and 10 m/s (standard deviations).
SCENARIO_RANGES = {"seconds": (0.0, 3600.0, True), "speed": (-10.0, 10.0, False),
                   "stand_time": (0.0, 3600.0, False), "at": (0.0, 3600.0, False),
                   "duration": (0.0, 3600.0, True), "magnitude": (0.0, 1e6, False),
                   "direction": (-1e6, 1e6, False)}
SEED_RANGE = (0, 2 ** 32 - 1)
PERTURBATION_RANGES = {"joint_angles": (0.0, 1.0), "base_velocity": (0.0, 10.0)}
#: the most runs a spec may expand into (presets x overrides x scenarios x seeds)
MAX_RUNS = 100_000
SPEC_FIELDS = ("name", "robot", "robots", "presets", "overrides", "scenarios", "seeds",
               "perturbation")
PERTURBATION_FIELDS = ("joint_angles", "base_velocity")
#: a run "fell" when the trunk tilted more than this [rad] or sank below FALL_HEIGHT [m]
#: (StarlETH's; scaled to the robot's standing height: falls.fall_height)
FALL_TILT, FALL_HEIGHT = 1.0, 0.2
#: columns that are wall-clock measurements (they differ between any two executions)
TIMING_COLUMNS = ("wall_s", "steps_per_s")


# =========================================================================================
# the spec
# =========================================================================================
@dataclass(frozen=True)
class Scenario:
    kind: str                       # stand | trot | push
    seconds: float = 2.0            # length of the run [s]
    speed: float = 0.3              # trot: forward speed [m/s]
    stand_time: float = 1.0         # trot: standing before it [s]
    at: float = 0.5                 # push: time [s]
    duration: float = 0.1           # push: [s]
    magnitude: float = 0.0          # push: [N]
    direction: tuple = (0.0, 1.0, 0.0)   # push: world axes, unit

    def label(self) -> str:
        if self.kind == "push":
            return f"push {self.magnitude:g} N"
        if self.kind == "trot":
            return f"trot {self.speed:g} m/s"
        return "stand"


@dataclass(frozen=True)
class RunSpec:
    """One run of the grid (picklable: it travels to a worker process or a Ray task)."""

    index: int
    preset: str
    overrides: tuple                # ((key, value), ...)
    scenario: Scenario
    seed: int = 0
    perturbation: tuple = ()        # ((field, std), ...), scaled to the robot
    robot: str | None = None        # None: the preset's (StarlETH)
    scale: tuple = (1.0, 1.0)       # (λ, μ) of the robot (the scaling rule)


@dataclass
class Sweep:
    name: str
    runs: list
    override_keys: list = field(default_factory=list)
    source: str = ""


def _num_list(where, v, integer=False, bounds=None):
    """`v` (one number or a list) as a list of finite numbers (integers), each within
    bounds = (low, high, low excluded) when given."""
    vals = v if isinstance(v, list) else [v]
    out = []
    for x in vals:
        ok = not isinstance(x, bool) and isinstance(x, (int, float))
        if ok:     # an int is finite, but float(x) overflows beyond ~1e308
            ok = abs(x) < 2 ** 1000 if isinstance(x, int) else math.isfinite(x)
        if not ok or (integer and int(x) != x):
            text = repr(x) if len(repr(x)) <= 60 else repr(x)[:57] + "..."
            raise SweepError(f"{where}: expected {'integers' if integer else 'finite numbers'}"
                             f", got {text}")
        x = int(x) if integer else float(x)
        if bounds is not None:
            lo, hi, lo_open = bounds
            if x < lo or x > hi or (lo_open and x == lo):
                raise SweepError(f"{where}: must be in {'(' if lo_open else '['}{lo:g}, "
                                 f"{hi:g}], got {x:g}")
        out.append(x)
    if not out:
        raise SweepError(f"{where}: empty list")
    return out


def _scenarios(src, items, runs_per_scenario=1):
    """The scenarios' list expanded (a list of values in a field is a grid); SweepError when
    the sweep would have more than MAX_RUNS runs (`runs_per_scenario` of each)."""
    if not isinstance(items, list) or not items:
        raise SweepError(f"{src}: scenarios: expected a non-empty list of mappings")
    out = []
    for i, sc in enumerate(items):
        w = f"{src}: scenarios[{i}]"
        if not isinstance(sc, dict):
            raise SweepError(f"{w}: expected a mapping, got {sc!r}")
        unknown = set(sc) - set(SCENARIO_FIELDS)
        if unknown:
            raise SweepError(f"{w}: unknown field(s) {sorted(unknown)} (known: "
                             f"{', '.join(SCENARIO_FIELDS)})")
        kind = sc.get("kind")
        if kind not in SCENARIOS:
            raise SweepError(f"{w}.kind: expected one of {', '.join(SCENARIOS)}, got {kind!r}")
        grid = {}
        for k, (_default, typ) in SCENARIO_FIELDS.items():
            if k == "kind" or k not in sc:
                continue
            if typ == "vec":
                d = np.asarray(_num_list(f"{w}.{k}", sc[k], bounds=SCENARIO_RANGES[k]),
                               dtype=float)
                if d.shape != (3,) or not np.linalg.norm(d) > 0:
                    raise SweepError(f"{w}.{k}: expected a non-zero 3-vector, got {sc[k]!r}")
                grid[k] = [tuple(float(x) for x in d / np.linalg.norm(d))]
            else:
                grid[k] = _num_list(f"{w}.{k}", sc[k], bounds=SCENARIO_RANGES[k])
        keys = list(grid)
        n = len(out) + math.prod(len(v) for v in grid.values())
        if n * runs_per_scenario > MAX_RUNS:
            raise SweepError(f"{w}: the sweep would have {n * runs_per_scenario} runs or more, "
                             f"more than {MAX_RUNS}")
        for combo in itertools.product(*(grid[k] for k in keys)):
            out.append(Scenario(kind=kind, **dict(zip(keys, combo, strict=True))))
    return out


def _robots(src, data) -> dict:
    """The spec's robots {name: description}: {None: None} (the presets' robot) without
    `robot` / `robots`; each one checked by building its description (SweepError naming the
    file and field)."""
    if "robot" in data and "robots" in data:
        raise SweepError(f"{src}: robot, robots: give one of them")
    key = "robot" if "robot" in data else "robots"
    value = data.get(key)
    if value is None:
        return {None: None}
    if key == "robots" and value == "all":
        value = list(available_robots())
    names = [value] if key == "robot" else value
    if not isinstance(names, list) or not names or \
            not all(isinstance(n, str) and n for n in names):
        what = "a robot name or path" if key == "robot" else "a list of robot names or `all`"
        raise SweepError(f"{src}: {key}: expected {what}, got {value!r}")
    out = {}
    for i, n in enumerate(names):
        try:
            out[n] = robot_description(n)
        except ConfigError as e:
            raise SweepError(f"{src}: {key}{'' if key == 'robot' else f'[{i}]'}: "
                             f"{e}") from None
    return out


def scaled(sc: Scenario, pert: tuple, scale: tuple):
    """The scenario and perturbation (StarlETH's numbers) for a robot of scale (λ, μ):
    speeds and velocities x √λ, forces x μ, push durations x √λ."""
    length, mass = scale
    if (length, mass) == (1.0, 1.0):
        return sc, pert
    t = math.sqrt(length)
    sc = replace(sc, speed=sc.speed * t, magnitude=sc.magnitude * mass,
                 duration=sc.duration * t)
    pert = tuple((k, v * t if k == "base_velocity" else v) for k, v in pert)
    return sc, pert


def load_spec(path: str) -> Sweep:
    """Read and validate a sweep spec; expand it into the runs of the grid (presets x
    overrides x scenarios x seeds, in that nesting order)."""
    src = os.path.basename(path)
    try:       # duplicate keys, binary files, bad YAML: ConfigError naming the file
        data = load_yaml_file(path, src)
    except ConfigError as e:
        raise SweepError(str(e)) from None
    if not isinstance(data, dict):
        raise SweepError(f"{src}: expected a mapping at the top level")
    unknown = set(data) - set(SPEC_FIELDS)
    if unknown:
        raise SweepError(f"{src}: unknown field(s) {sorted(unknown)} (known: "
                         f"{', '.join(SPEC_FIELDS)})")
    presets = _presets(src, data)
    name = data.get("name")
    if name is not None and not isinstance(name, (str, int)):
        raise SweepError(f"{src}: name: expected a string")
    ov_keys, combos = _override_combos(src, data, len(presets))
    robots = _robots(src, data)
    for p, robot in itertools.product(presets, robots):   # each with every override, checked
        try:
            cfg = load_preset(p) if robot is None else config_with_robot(load_preset(p), robot)
            for c in combos:
                cfg.with_overrides(**dict(c))
        except ConfigError as e:
            raise SweepError(f"{src}: presets/overrides: {e}") from None
    seeds = _num_list(f"{src}: seeds", data.get("seeds", [0]), integer=True,
                      bounds=(*SEED_RANGE, False))
    scenarios = _scenarios(src, data.get("scenarios"), len(presets) * len(combos) * len(seeds))
    pert_t = _perturbation_spec(src, data)
    if len(robots) * len(presets) * len(combos) * len(scenarios) * len(seeds) > MAX_RUNS:
        raise SweepError(f"{src}: robots x presets x overrides x scenarios x seeds: more than "
                         f"the {MAX_RUNS} runs a sweep may have")
    runs = []
    for robot, desc in robots.items():
        rs = robot_scale(desc.legs, desc.total_mass) if desc is not None else None
        scale = (rs.length, rs.mass) if rs else (1.0, 1.0)
        for p, c, sc0, seed in itertools.product(presets, combos, scenarios, seeds):
            sc, pert = scaled(sc0, pert_t, scale)
            runs.append(RunSpec(len(runs), p, c, sc, seed, pert, robot, scale))
    name = str(name or os.path.splitext(src)[0])
    return Sweep(name=name, runs=runs, override_keys=ov_keys, source=path)


def _presets(src, data):
    """The spec's `presets`: a name or a non-empty list of names."""
    presets = data.get("presets")
    if isinstance(presets, str):
        presets = [presets]
    if not isinstance(presets, list) or not presets or \
            not all(isinstance(p, str) for p in presets):
        raise SweepError(f"{src}: presets: expected a non-empty list of preset names")
    return presets


def _override_combos(src, data, n_presets):
    """(the override fields, every combination of their values as ((field, value), ...)):
    the spec's `overrides`, field: value or [values]; at most MAX_RUNS with the presets."""
    overrides = data.get("overrides") or {}
    if not isinstance(overrides, dict):
        raise SweepError(f"{src}: overrides: expected a mapping of field: [values]")
    ov_grid = {}
    for k, v in overrides.items():
        if not isinstance(k, str):
            raise SweepError(f"{src}: overrides: expected field names as keys, got {k!r}")
        vals = v if isinstance(v, list) else [v]
        if not vals:
            raise SweepError(f"{src}: overrides.{k}: empty list")
        ov_grid[k] = vals
    ov_keys = list(ov_grid)
    n_combos = math.prod(len(v) for v in ov_grid.values())
    if n_presets * n_combos > MAX_RUNS:
        raise SweepError(f"{src}: presets x overrides: {n_presets * n_combos} combinations, "
                         f"more than the {MAX_RUNS} runs a sweep may have")
    return ov_keys, [tuple(zip(ov_keys, c, strict=True))
                     for c in itertools.product(*(ov_grid[k] for k in ov_keys))]


def _perturbation_spec(src, data):
    """The spec's `perturbation` as ((field, value), ...) in PERTURBATION_FIELDS order."""
    pert = data.get("perturbation") or {}
    if not isinstance(pert, dict) or set(pert) - set(PERTURBATION_FIELDS):
        raise SweepError(f"{src}: perturbation: expected a mapping with "
                         f"{', '.join(PERTURBATION_FIELDS)}")
    for k, v in pert.items():
        if isinstance(v, list):
            raise SweepError(f"{src}: perturbation.{k}: expected one number >= 0")
        _num_list(f"{src}: perturbation.{k}", v, bounds=(*PERTURBATION_RANGES[k], False))
    return tuple((k, float(pert[k])) for k in PERTURBATION_FIELDS if k in pert)


# =========================================================================================
# one run
# =========================================================================================
def _perturbation(seed, perturbation):
    """perturb(sim) for run_gait: random offsets (seeded) of the joint angles and the base
    velocity of the standing state, applied through the minimal coordinates."""
    sizes = dict(perturbation)
    if not any(sizes.values()):
        return None

    def perturb(sim):
        rng = np.random.default_rng(seed)
        sim.reset()
        pub = public_state(sim)
        pub["joint_positions"] = pub["joint_positions"] + \
            rng.normal(0.0, sizes.get("joint_angles", 0.0), sim.n_joints)
        pub["base_linear_velocity"] = pub["base_linear_velocity"] + \
            rng.normal(0.0, sizes.get("base_velocity", 0.0), 3)
        sim.reset(*minimal_state(sim, pub), minimal=True)
    return perturb


def run_one(spec: RunSpec) -> dict:
    """One headless run with the controller in the loop: a row of the results table."""
    sc = spec.scenario
    push = None
    if sc.kind == "push":
        push = (sc.at, tuple(sc.magnitude * x for x in sc.direction), sc.duration)
    gait = "trot" if sc.kind == "trot" else "stand"
    perturb, kept = _perturbation(spec.seed, spec.perturbation), {}

    def start(sim):
        kept["sim"] = sim
        if perturb is not None:
            perturb(sim)
    robot = {} if spec.robot is None else {"robot": spec.robot}
    t0 = time.perf_counter()
    r = run_gait(spec.preset, gait, sc.seconds, push=push, stand_time=sc.stand_time,
                 speed=sc.speed, perturb=start, **robot, **dict(spec.overrides))
    wall = time.perf_counter() - t0
    it = np.asarray(r["iterations"], dtype=float) / r["steps_per_control"]
    desc = kept["sim"].description
    row = {"index": spec.index, "robot": desc.name, "lambda": spec.scale[0],
           "mu": spec.scale[1], "preset": spec.preset}
    row.update({k: v for k, v in spec.overrides})
    row.update(scenario=sc.kind, seconds=sc.seconds,
               speed=sc.speed if sc.kind == "trot" else None,
               push_magnitude=sc.magnitude if sc.kind == "push" else None,
               push_direction=" ".join(f"{x:g}" for x in sc.direction)
               if sc.kind == "push" else None,
               seed=spec.seed, steps=r["steps"], completed=r["error"] is None,
               error=r["error"] or "",
               fell=bool(r["max_tilt"] > FALL_TILT
                         or r["min_height"] < fall_height(desc, FALL_HEIGHT)),
               max_tilt_deg=math.degrees(r["max_tilt"]), min_height=r["min_height"],
               distance_x=r["distance"],
               mean_iterations=float(it.mean()) if it.size else 0.0,
               max_iterations=int(max(r["iterations"])) if r["iterations"] else 0,
               nonconverged=r["nonconverged"],
               wall_s=wall, steps_per_s=r["steps"] / wall if wall > 0 else 0.0)
    return row


# =========================================================================================
# execution (task_pool: a process pool or Ray, the same tasks, results streamed back)
# =========================================================================================
def run_sweep(sweep: Sweep, jobs=None, ray=None, ray_init=None, show_progress=True) -> list:
    """The rows of the results table, in grid order."""
    return execute([(run_one, {"spec": s}) for s in sweep.runs], jobs, ray, ray_init,
                   show_progress, what="runs")


# =========================================================================================
# outputs
# =========================================================================================
def columns(rows) -> list:
    cols = []
    for r in rows:
        cols += [k for k in r if k not in cols]
    return cols


def write_table(rows, out_dir) -> list:
    """results.csv, and results.parquet where pyarrow is installed."""
    os.makedirs(out_dir, exist_ok=True)
    cols = columns(rows)
    path = os.path.join(out_dir, "results.csv")
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in cols})
    written = [path]
    try:
        import pyarrow as pa  # deferred: optional (results.parquet where it is installed)
        import pyarrow.parquet as pq  # deferred: optional, as above
    except ImportError:
        return written
    table = pa.Table.from_pylist([{k: r.get(k) for k in cols} for r in rows])
    pq.write_table(table, os.path.join(out_dir, "results.parquet"))
    return written + [os.path.join(out_dir, "results.parquet")]


def config_label(r, rows) -> str:
    """A row's preset, after its robot where the rows hold several robots."""
    several = len({x.get("robot") for x in rows}) > 1
    return f"{r['robot']} {r['preset']}" if several else r["preset"]


def push_fall_curves(rows) -> dict:
    """{preset (robot and preset): [(magnitude, fraction of runs that fell)]} over the push
    runs."""
    out = {}
    for r in rows:
        if r["scenario"] == "push":
            out.setdefault(config_label(r, rows), {}).setdefault(
                r["push_magnitude"], []).append(r["fell"])
    return {p: sorted((m, float(np.mean(v))) for m, v in d.items()) for p, d in out.items()}


def first_fall(curve):
    """The smallest push magnitude at which at least half of the runs fell (None: none)."""
    return next((m for m, frac in curve if frac >= 0.5), None)


def make_plots(rows, sweep: Sweep, out_dir) -> list:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    written = []
    curves = push_fall_curves(rows)
    if any(len(c) > 1 for c in curves.values()):
        fig, ax = plt.subplots(figsize=(7, 4))
        for i, (p, c) in enumerate(sorted(curves.items())):
            m, frac = zip(*c, strict=True)
            lim = first_fall(c)
            ax.plot(m, frac, marker="o", color=f"C{i % 10}",
                    label=f"{p} (falls from {lim:g} N)" if lim is not None else f"{p} (no fall)")
        ax.set_xlabel("push magnitude [N]")
        ax.set_ylabel("fraction of runs that fell")
        ax.set_ylim(-0.05, 1.05)
        ax.set_title(f"{sweep.name}: falls against push magnitude")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = os.path.join(out_dir, "push_falls.png")
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    for key in sweep.override_keys:
        vals = sorted({r[key] for r in rows if isinstance(r.get(key), (int, float))})
        if len(vals) < 2:
            continue
        fig, ax = plt.subplots(figsize=(7, 4))
        groups = sorted({(config_label(r, rows), r["scenario"]) for r in rows})
        for i, (p, s) in enumerate(groups):
            pts = [(v, np.mean([r["mean_iterations"] for r in rows if r[key] == v and
                                config_label(r, rows) == p and r["scenario"] == s
                                and r["completed"]
                                and not r["nonconverged"]] or [np.nan])) for v in vals]
            ax.plot(*zip(*pts, strict=True), marker="o", color=f"C{i % 10}", label=f"{p}, {s}")
        ax.set_xlabel(key)
        ax.set_ylabel("prox iterations per step (mean)")
        ax.set_yscale("log")
        ax.set_title(f"{sweep.name}: iterations against {key} (converged runs)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = os.path.join(out_dir, f"iterations_vs_{key}.png")
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    return written


def format_summary(rows, sweep: Sweep) -> list:
    lines = [f"{sweep.name}: {len(rows)} runs, {sum(r['fell'] for r in rows)} fell, "
             f"{sum(not r['completed'] for r in rows)} stopped by the physics, "
             f"{sum(r['nonconverged'] > 0 for r in rows)} with non-converged steps"]
    for p, c in sorted(push_fall_curves(rows).items()):
        lim = first_fall(c)
        lines.append(f"  {p}: falls from a push of {lim:g} N" if lim is not None else
                     f"  {p}: no fall up to {c[-1][0]:g} N")
    return lines


def build_parser():
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n")[0])
    ap.add_argument("spec", help="sweep spec (YAML)")
    ap.add_argument("--out", default=None, help="output directory (default: <spec>_sweep/)")
    ap.add_argument("--jobs", type=int, default=None,
                    help="worker processes of the local pool (default: all cores)")
    ap.add_argument("--ray", default=None, metavar="auto|local|ADDRESS",
                    help="run on Ray: 'auto' (the running cluster), 'local' (start one here) "
                         "or a cluster address")
    ap.add_argument("--no-plots", action="store_true")
    return ap


def run(argv=None) -> int:
    a = build_parser().parse_args(argv)
    if a.jobs is not None and a.jobs < 1:
        build_parser().error("--jobs must be >= 1")
    sweep = load_spec(a.spec)
    out = a.out or os.path.splitext(a.spec)[0] + "_sweep"
    where = f"Ray ({a.ray})" if a.ray else f"{a.jobs or os.cpu_count()} processes"
    print(f"{sweep.name}: {len(sweep.runs)} runs on {where}")
    t0 = time.time()
    rows = run_sweep(sweep, a.jobs, a.ray)
    written = write_table(rows, out)
    if not a.no_plots:
        written += make_plots(rows, sweep, out)
    for line in format_summary(rows, sweep):
        print(line)
    print(f"{time.time() - t0:.0f} s; written: " + ", ".join(written))
    return 0


def main(argv=None) -> int:
    """Console script: 0, or 1 with one line for a bad spec (file and field named)."""
    try:
        return run(argv)
    except (SweepError, OSError) as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
