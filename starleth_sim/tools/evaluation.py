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
  * speed beside MuJoCo - ``starleth-bench --vs-mujoco`` (HmJ, HmS, Cm; run alone after the
    other tasks; skipped with a note where mujoco is not installed).
Runs are independent tasks, a predefined sweep executed by starleth-sweep's machinery
(:func:`starleth_sim.tools.sweep.execute`: a process pool, ``--jobs``, default all cores, or
Ray with ``--ray auto|local|ADDRESS``; progress with ETA); starleth-sweep's runs are
:func:`run_gait`, the one headless run of both. ``--quick`` shortens every run (for CI); the
figures are then noisier but complete.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import numpy as np

from ..physics.config import PRESETS as TABLE1   # the paper's Table 1, in its order
from ..physics.stepper import PHASES

PHASE_LABELS = {"M_and_h": "M and h", "M_inverse": "M⁻¹ (and M⁻¹W)", "G": "G (and G_B⁻¹)",
                "prox": "u^E (prox)", "rest": "rest"}

FIG6_CONFIGS = TABLE1[1:]      # the hard-contact ones
TROT_SPEED = 0.3       # m/s
STAND_BEFORE_TROT = 1.0  # s
GAIT_PERIOD = 0.8      # s (1.25 Hz)
#: iteration cap of the α sweep: a run "converges" if no step needs more (slow convergence at
#: small α is not divergence, so the cap is generous)
FIG6_MAX_ITERATIONS = 5000
PAPER_ACCURACY = {"foot_sink_mm": 4.4, "unilateral_drift_um_per_min": 750.0,
                  "bilateral_drift_um_per_min": 0.59}


# ----------------------------------------------------------------------------------------------
# one simulation run with the controller in the loop
# ----------------------------------------------------------------------------------------------
def _controller():
    from starleth_controller import StarlethController
    from ..physics.description import urdf_path
    return StarlethController(urdf_path())


def run_gait(preset, gait, seconds, profile=False, record_lf=False, push=None,
             stand_time=STAND_BEFORE_TROT, stop_on_nonconvergence=False, speed=TROT_SPEED,
             perturb=None, **overrides):
    """Stand (and trot at `speed` after `stand_time` s if gait == 'trot') for `seconds`;
    push = (time [s], force (world) [N], duration [s]) on the base; perturb(sim) may change
    the initial state. Returns per-step wall times of sim.step, iterations, and the
    measurements of the report. The one headless run of starleth-eval and starleth-sweep."""
    from starleth_controller import Command, RobotState
    from ..physics.simulator import Simulator
    from ..physics.stepper import SimulationError
    sim = Simulator.from_preset(preset, profile=profile, **overrides)
    if perturb is not None:
        perturb(sim)
    ctrl = _controller()
    n = int(round(seconds / sim.control_period))
    feet = [sim.contact_names.index(f) for f in sim.description.foot_names]
    wall = np.zeros(n)
    iters = np.zeros(n, dtype=np.int64)
    lf_force, lf_t = [], []
    foot_gap, drift_t, drift_g = [], [], []
    foot_penetration = np.zeros(n)   # deepest foot below the ground after each step [m]
    min_height, max_tilt = 1.0, 0.0
    knee_trunk = set()
    error = None
    nonfinite = False
    k_done = 0
    for k in range(n):
        trot = gait == "trot" and k * sim.control_period >= stand_time
        cmd = Command(mode="trot" if trot else "stand", forward=speed if trot else 0.0)
        tau = ctrl.update(RobotState.from_simulator(sim), cmd)
        if push is not None and k == int(round(push[0] / sim.control_period)):
            sim.apply_wrench("base", push[1], duration=push[2])
        t0 = time.perf_counter()
        try:
            d = sim.step(tau)
        except SimulationError as e:  # reported, the run ends here
            error = str(e)
            nonfinite = "non-finite" in error
            break
        wall[k] = time.perf_counter() - t0
        iters[k] = d.iterations
        k_done = k + 1
        if stop_on_nonconvergence and not d.converged:
            break
        gaps = sim.gaps()[feet]
        foot_penetration[k] = max(0.0, -float(gaps.min()))
        b = sim.base_state()
        min_height = min(min_height, float(b["position"][2]))
        x, y, z, w = b["orientation_xyzw"]
        tilt = math.acos(max(-1.0, min(1.0, 1 - 2 * (x * x + y * y))))
        max_tilt = max(max_tilt, tilt)
        if record_lf:
            lf_t.append(sim.t)
            lf_force.append(float(sim.contacts[feet[0]].force[2]))
        if push is not None:
            for c in sim.contacts:
                if c.active and not c.name.endswith("_foot"):
                    knee_trunk.add(c.name)
        if k % 10 == 0:
            act = np.array([sim.contacts[i].active for i in feet])
            if act.any():
                foot_gap.append((sim.t, float(gaps[act].mean()), float(gaps[act].min())))
            if sim.coords.n_bilateral:
                drift_t.append(sim.t)
                drift_g.append(float(np.abs(sim.bilateral_violation()).max()))
    out = dict(preset=preset, gait=gait, seconds=seconds, steps=k_done,
               physics_steps=k_done * sim.config.steps_per_control, error=error,
               nonfinite=nonfinite or not np.all(np.isfinite(sim.q)),
               wall=wall[:k_done].tolist(), iterations=iters[:k_done].tolist(),
               nonconverged=int(sim.diagnostics.nonconverged_steps),
               min_height=min_height, max_tilt=max_tilt, knee_trunk_contacts=sorted(knee_trunk),
               distance=float(sim.base_state()["position"][0]),
               control_period=sim.control_period,
               steps_per_control=sim.config.steps_per_control,
               foot_gap=foot_gap, drift_t=drift_t, drift_g=drift_g,
               foot_penetration=foot_penetration[:k_done].tolist(),
               loaded_contacts_opened=int(sim.diagnostics.loaded_contacts_opened_total),
               projections=int(sim.stepper.stats.projections))
    if record_lf:
        out["lf_t"], out["lf_force"] = lf_t, lf_force
    if profile:
        st = sim.stepper.stats
        out["phases_us"] = (1e6 * st.timings / max(st.steps, 1)).tolist()
    return out


def _steps_per_second(r, window):
    """Physics steps per second per gait cycle: mean and std over the cycles of the run."""
    wall = np.asarray(r["wall"])
    per = int(round(window / r["control_period"]))
    n = len(wall) // per
    if n == 0:
        return float("nan"), float("nan")
    rates = [per * r["steps_per_control"] / wall[i * per:(i + 1) * per].sum() for i in range(n)]
    return float(np.mean(rates)), float(np.std(rates))


# ----------------------------------------------------------------------------------------------
# tasks (each runs in a worker process)
# ----------------------------------------------------------------------------------------------
def task_table1(preset, seconds):
    r = run_gait(preset, "trot", seconds, record_lf=preset in ("Cm", "HmJ"))
    trot_wall = r["wall"][int(STAND_BEFORE_TROT / r["control_period"]):]
    sps, sps_std = _steps_per_second(dict(r, wall=trot_wall), GAIT_PERIOD)
    res = dict(kind="table1", preset=preset, steps_per_second=sps, steps_per_second_std=sps_std,
               rtf=sps / (r["steps_per_control"] / r["control_period"]),
               rtf_std=sps_std / (r["steps_per_control"] / r["control_period"]),
               mean_iterations=float(np.mean(r["iterations"])) / r["steps_per_control"],
               max_iterations=int(np.max(r["iterations"])) if r["iterations"] else 0,
               nonconverged=r["nonconverged"], min_height=r["min_height"],
               distance=r["distance"], error=r["error"])
    gaps = np.array([g for g in r["foot_gap"] if g[0] > STAND_BEFORE_TROT + 1.0])
    pen = np.asarray(r["foot_penetration"][int(round(STAND_BEFORE_TROT / r["control_period"])):])
    if r["preset"] != "Cm" and len(pen):
        res["foot_penetration_mean_mm"] = float(1e3 * pen.mean())
        res["foot_penetration_max_mm"] = float(1e3 * pen.max())
        res["loaded_contacts_opened"] = r["loaded_contacts_opened"]
        res["projections"] = r["projections"]
    if len(gaps):
        res["foot_sink_mean_mm"] = float(-1e3 * gaps[:, 1].mean())
        res["foot_sink_max_mm"] = float(-1e3 * gaps[:, 2].min())
    if r["drift_t"]:
        t, g = np.array(r["drift_t"]), np.array(r["drift_g"])
        sel = t > STAND_BEFORE_TROT + 1.0
        if sel.sum() > 2:
            res["bilateral_drift_um_per_min"] = float(np.polyfit(t[sel], g[sel], 1)[0] * 60e6)
            res["bilateral_violation_max_um"] = float(g[sel].max() * 1e6)
    if "lf_t" in r:
        res["lf_t"], res["lf_force"] = r["lf_t"], r["lf_force"]
    return res


def task_fig5_damped(seconds):
    """Cm with 10x normal damping; the step must shrink 4x (paper): 8 steps per control update
    (at 4 steps the run diverges). Only d_N is raised: with d_T = 500 N s/m as well, the
    explicit tangential damper chatters on the light feet even at Δt/4."""
    r = run_gait("Cm", "trot", seconds, record_lf=True, damping_normal=500.0,
                 steps_per_control=8)
    return dict(kind="fig5", preset="Cm_d10", lf_t=r["lf_t"], lf_force=r["lf_force"],
                error=r["error"])


def task_fig7(preset, seconds):
    r = run_gait(preset, "trot", seconds, profile=True)
    return dict(kind="fig7", preset=preset, phases_us=r["phases_us"], error=r["error"])


def task_fig6(preset, gait, alpha, seconds):
    r = run_gait(preset, gait, seconds, alpha=alpha, fallback_alpha_factor=0.0,
                 max_iterations=FIG6_MAX_ITERATIONS, stand_time=0.2,
                 stop_on_nonconvergence=True)
    it = np.asarray(r["iterations"], dtype=float)
    ok = r["error"] is None and r["nonconverged"] == 0 and r["min_height"] > 0.3
    return dict(kind="fig6", preset=preset, gait=gait, alpha=alpha,
                mean_iterations=float(it.mean()) if len(it) else float("nan"),
                converged=ok, nonconverged=r["nonconverged"], error=r["error"])


def task_unilateral_drift(preset, seconds):
    """Vertical drift of the unilateral foot constraints while standing (µm/min)."""
    r = run_gait(preset, "stand", seconds)
    g = np.array(r["foot_gap"])
    sel = g[:, 0] > 2.0
    slope = float(np.polyfit(g[sel, 0], g[sel, 1], 1)[0] * 60e6) if sel.sum() > 2 else float("nan")
    return dict(kind="unilateral_drift", preset=preset, drift_um_per_min=slope,
                min_gap_um=float(1e6 * g[sel, 2].min()) if sel.any() else float("nan"))


def task_bilateral_drift(preset, seconds):
    """Growth of the bilateral constraint violation while trotting (µm/min)."""
    r = run_gait(preset, "trot", seconds)
    t, g = np.array(r["drift_t"]), np.array(r["drift_g"])
    sel = t > STAND_BEFORE_TROT + 1.0
    return dict(kind="bilateral_drift", preset=preset,
                drift_um_per_min=float(np.polyfit(t[sel], g[sel], 1)[0] * 60e6),
                violation_max_um=float(g[sel].max() * 1e6), seconds=seconds)


def task_pushover(preset, seconds):
    """The paper's stress test: a push on the standing robot's trunk throws it on its side."""
    r = run_gait(preset, "stand", seconds, push=(0.5, (0.0, 700.0, 0.0), 0.1))
    it = np.asarray(r["iterations"])
    return dict(kind="pushover", preset=preset, fell=r["max_tilt"] > 1.0,
                max_tilt_deg=math.degrees(r["max_tilt"]), nonfinite=r["nonfinite"],
                error=r["error"], max_iterations=int(it.max()) if len(it) else 0,
                all_converged=r["nonconverged"] == 0, nonconverged=r["nonconverged"],
                knee_trunk_contacts=r["knee_trunk_contacts"], completed=r["error"] is None)


# ----------------------------------------------------------------------------------------------
# hard-contact rule: the sagging-posture scenario and the comparison of the contact-law variants
# ----------------------------------------------------------------------------------------------
#: the soft joint PD hold under which StarlETH sags onto its feet: τ = K_p (φ₀ − φ) − K_d φ̇,
#: clipped at ±SAG_TORQUE_LIMIT
SAG_KP, SAG_KD, SAG_TORQUE_LIMIT = 80.0, 2.0, 20.0


def pd_sag(preset, seconds=2.0, **overrides):
    """StarlETH from `reset()` under the soft joint PD hold (it sags by ~15 mm onto its
    feet). Returns the simulator and per control step: the deepest foot penetration
    max(0, −min g_N) after the step [m], the largest gap of a foot that carried a normal
    impulse in the step (a "hovering" loaded foot) [m], prox iterations, loaded contacts
    opened, and the kinetic energy [J]."""
    from ..physics.simulator import Simulator
    sim = Simulator.from_preset(preset, **overrides)
    sim.reset()
    q0 = sim.joint_positions()
    feet = [sim.contact_names.index(f) for f in sim.description.foot_names]
    n = int(round(seconds / sim.control_period))
    out = np.zeros((n, 5))
    for k in range(n):
        tau = np.clip(SAG_KP * (q0 - sim.joint_positions()) - SAG_KD * sim.joint_velocities(),
                      -SAG_TORQUE_LIMIT, SAG_TORQUE_LIMIT)
        d = sim.step(tau)
        g = sim.gaps()[feet]
        cs = sim.contacts
        loaded = [g[j] for j, i in enumerate(feet) if cs[i].impulse @ sim.stepper.ground.n > 0]
        out[k] = (max(0.0, -g.min()), max(loaded) if loaded else np.nan, d.iterations,
                  d.loaded_contacts_opened, sim.coords.kinetic_energy(sim.q, sim.u))
    return sim, out


def ball_drop(restitution, height, overrides, seconds=1.0):
    """A 1 kg ball of radius 0.1 m dropped from `height` onto the ground at Δt = 1 ms with
    the HmJ contact law (and `overrides`). Returns (v⁻, v⁺ of the impact step, highest
    rebound above the rest height [m])."""
    from ..physics.config import load_preset
    from ..physics.description import RobotDescription, sphere_urdf
    from ..physics.simulator import Simulator
    cfg = load_preset("HmJ").with_overrides(control_rate=1000.0, restitution_normal=restitution,
                                            tol_rel=1e-10, tol_abs=1e-12, **overrides)
    sim = Simulator(cfg, description=RobotDescription.from_urdf_xml(sphere_urdf(0.1, 1.0)))
    z_rest = sim.q[2]
    q = sim.q
    q[2] += height
    sim.reset(q)
    vz, z = [], []
    for _ in range(int(round(seconds / sim.control_period))):
        sim.step()
        vz.append(sim.u[2])
        z.append(sim.q[2] - z_rest)
    vz, z = np.array(vz), np.array(z)
    k = int(np.argmax(np.diff(vz) > 0.5))
    return float(vz[k]), float(vz[k + 1]), float(z[k + 1:].max())


#: the rules compared in the report: (label, overrides of the HmJ preset)
CONTACT_VARIANTS = (
    ("paper: g_N ≤ 0, no correction", dict(activation="paper", activation_gap=0.0,
                                           penetration_stabilization=0.0)),
    ("paper's rule, g_act = 10 µm", dict(activation="paper", activation_gap=1e-5,
                                          penetration_stabilization=0.0)),
    ("hysteresis, no correction", dict(penetration_stabilization=0.0)),
    ("hysteresis + velocity β_N = 0.2", dict(penetration_correction="velocity",
                                             penetration_stabilization=0.2)),
    ("hysteresis + velocity β_N = 1", dict(penetration_correction="velocity",
                                           penetration_stabilization=1.0)),
    ("hysteresis + projection β_N = 1 (presets)", dict()),
)


def task_contact_variant(label, overrides, seconds):
    """One contact-law variant on HmJ: the sagging posture (2 s), trotting (stand 1 s, trot
    `seconds`), and the energy of impacts (plastic and ε_N = 0.5 ball drops)."""
    _, sag = pd_sag("HmJ", 2.0, **overrides)
    r = run_gait("HmJ", "trot", STAND_BEFORE_TROT + seconds, **overrides)
    k0 = int(round(STAND_BEFORE_TROT / r["control_period"]))
    pen = np.asarray(r["foot_penetration"][k0:])
    wall = np.asarray(r["wall"])
    _, v_plastic, h_plastic = ball_drop(0.0, 0.2, overrides)
    v_minus, v_plus, apex = ball_drop(0.5, 1.0, overrides)
    return dict(kind="contact_variant", label=label, overrides=overrides,
                sag_penetration_max_mm=float(1e3 * sag[:, 0].max()),
                sag_hover_max_um=float(1e6 * np.nanmax(sag[:, 1])),
                sag_opened=int(sag[:, 3].sum()), sag_iterations=float(sag[:, 2].mean()),
                sag_final_kinetic_energy=float(sag[-1, 4]),
                trot_penetration_mean_mm=float(1e3 * pen.mean()) if len(pen) else float("nan"),
                trot_penetration_max_mm=float(1e3 * pen.max()) if len(pen) else float("nan"),
                trot_iterations=float(np.mean(r["iterations"])),
                trot_opened=r["loaded_contacts_opened"], trot_projections=r["projections"],
                trot_steps_per_second=float(len(wall) / wall.sum()) if wall.sum() else 0.0,
                trot_distance=r["distance"], error=r["error"],
                plastic_rebound_velocity=v_plastic, plastic_rebound_height_mm=1e3 * h_plastic,
                restitution_ratio=-v_plus / v_minus, restitution_apex_ratio=apex / 1.0)


# ----------------------------------------------------------------------------------------------
def plan(quick: bool, configs):
    s = dict(table1=3.0 if quick else 21.0, fig5=3.0 if quick else 4.0,
             fig7=2.0 if quick else 5.0, fig6=1.2 if quick else 4.0,
             drift=3.0 if quick else 60.0, push=2.0 if quick else 4.0,
             variants=2.0 if quick else 5.0)
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
    return tasks


def run_all(quick=False, jobs=None, configs=TABLE1, ray=None):
    """Every task of the plan on starleth-sweep's machinery (a process pool of `jobs`, or
    Ray), with its progress bar; returns (results, elapsed seconds)."""
    from .sweep import execute
    t0 = time.time()
    results = execute(plan(quick, configs), jobs or os.cpu_count() or 1, ray)
    return results, time.time() - t0


def vs_mujoco(quick=False, configs=TABLE1):
    """`starleth-bench --vs-mujoco` on the presets of its default set that are in `configs`,
    alone in this process after the other tasks (a speed comparison must not share the
    machine with them): a result record {"kind": "vs_mujoco", ...}, None when no such
    preset is selected. mujoco is optional: without it the record says so."""
    from . import bench
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


# ----------------------------------------------------------------------------------------------
# report
# ----------------------------------------------------------------------------------------------
def _by(results, kind):
    return [r for r in results if r["kind"] == kind]


def alpha_limits(fig6):
    """Per (config, gait): the largest α of the grid at which every step converged (small α
    may also fail, by needing more than the iteration cap: slow, not divergent), and whether
    it is the top of the grid. Returns {(config, gait): (limit or None, at_top)}."""
    out = {}
    fig6 = [r for r in fig6 if r["alpha"] != "auto"]
    for key in sorted({(r["preset"], r["gait"]) for r in fig6}):
        rs = sorted((r for r in fig6 if (r["preset"], r["gait"]) == key), key=lambda r: r["alpha"])
        ok = [r["alpha"] for r in rs if r["converged"]]
        limit = max(ok) if ok else None
        out[key] = (limit, limit is not None and limit == rs[-1]["alpha"])
    return out


def alpha_auto_rows(fig6):
    """Per (config, gait) with an α = auto run: (best fixed α of the grid, its mean
    iterations, auto's mean iterations, auto converged on every step)."""
    out = {}
    for r in fig6:
        if r["alpha"] != "auto":
            continue
        key = (r["preset"], r["gait"])
        fixed = [f for f in fig6 if (f["preset"], f["gait"]) == key and f["alpha"] != "auto"
                 and f["converged"]]
        best = min(fixed, key=lambda f: f["mean_iterations"]) if fixed else None
        out[key] = (best["alpha"] if best else None,
                    best["mean_iterations"] if best else float("nan"),
                    r["mean_iterations"], r["converged"])
    return out


def _touchdown(t, f, after):
    """Time of the first LF touchdown (force rising from 0) after `after` seconds."""
    idx = np.flatnonzero((t[1:] > after) & (f[:-1] <= 0.0) & (f[1:] > 0.0))
    return float(t[idx[0] + 1]) if len(idx) else None


def make_figures(results, out_dir):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    figs = {}
    # Fig. 5
    t1 = {r["preset"]: r for r in _by(results, "table1")}
    f5 = [r for r in _by(results, "fig5")]
    series = []
    if "Cm" in t1 and "lf_t" in t1["Cm"]:
        series.append(("Cm (compliant, d = 50 N s/m, Δt = 1.25 ms)", t1["Cm"], "C0", "-"))
    if "HmJ" in t1 and "lf_t" in t1["HmJ"]:
        series.append(("HmJ (hard, Δt = 2.5 ms)", t1["HmJ"], "C3", "-"))
    for r in f5:
        series.append(("Cm, 10x normal damping, Δt = 0.3125 ms", r, "C2", "--"))
    if series:
        fig, ax = plt.subplots(figsize=(7, 4))
        for label, r, color, ls in series:
            t = np.asarray(r["lf_t"])
            f = np.asarray(r["lf_force"])
            t0 = _touchdown(t, f, STAND_BEFORE_TROT + GAIT_PERIOD)
            if t0 is None:
                continue
            sel = (t >= t0 - 0.02) & (t < t0 + GAIT_PERIOD - 0.02)
            ax.plot(t[sel] - t0, f[sel], color=color, ls=ls, label=label)
        ax.set_xlabel("time since LF touchdown [s]")
        ax.set_ylabel("LF foot normal force F = Λ/Δt [N]")
        ax.set_title("Fig. 5: normal contact force of the LF foot, one trot cycle")
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
        fig.tight_layout()
        figs["fig5"] = "fig5_contact_force.png"
        fig.savefig(os.path.join(out_dir, figs["fig5"]), dpi=120)
        plt.close(fig)
    # Fig. 6
    f6 = _by(results, "fig6")
    if f6:
        fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
        auto = {(r["preset"], r["gait"]): r for r in f6 if r["alpha"] == "auto"}
        f6 = [r for r in f6 if r["alpha"] != "auto"]
        for ax, gait in zip(axes, ("stand", "trot")):
            for i, preset in enumerate(sorted({r["preset"] for r in f6})):
                rs = sorted((r for r in f6 if r["preset"] == preset and r["gait"] == gait),
                            key=lambda r: r["alpha"])
                a = [r["alpha"] for r in rs if r["converged"]]
                it = [r["mean_iterations"] for r in rs if r["converged"]]
                ax.plot(a, it, marker="o", ms=3, label=preset, color=f"C{i}")
                ra = auto.get((preset, gait))
                if ra is not None and ra["converged"]:    # α = auto: a star right of the grid
                    ax.plot([2.1], [ra["mean_iterations"]], marker="*", ms=9, color=f"C{i}",
                            ls="none")
            if auto:
                ax.set_xticks([0.0, 0.5, 1.0, 1.5, 2.1], ["0", "0.5", "1", "1.5", "auto"])
            ax.set_xlabel("relaxation α")
            ax.set_title(f"{gait}")
            ax.set_yscale("log")
            ax.grid(alpha=0.3)
        axes[0].set_ylabel("prox iterations per step (mean)")
        axes[1].legend(fontsize=7, ncol=2)
        fig.suptitle("Fig. 6: prox iterations against α (points only where every step "
                     "converged; ★ α = auto)")
        fig.tight_layout()
        figs["fig6"] = "fig6_iterations_vs_alpha.png"
        fig.savefig(os.path.join(out_dir, figs["fig6"]), dpi=120)
        plt.close(fig)
    # Fig. 7
    f7 = sorted(_by(results, "fig7"), key=lambda r: TABLE1.index(r["preset"]))
    if f7:
        labels = [PHASE_LABELS[p] for p in PHASES]
        fig, ax = plt.subplots(figsize=(9, 4))
        bottom = np.zeros(len(f7))
        for i, lab in enumerate(labels):
            v = np.array([r["phases_us"][i] for r in f7])
            ax.bar([r["preset"] for r in f7], v, bottom=bottom, label=lab, color=f"C{i}")
            bottom += v
        ax.set_ylabel("time per physics step [µs]")
        ax.set_title("Fig. 7: computation time of one step by phase (trotting, profiled run)")
        ax.legend(fontsize=8)
        ax.grid(axis="y", alpha=0.3)
        fig.tight_layout()
        figs["fig7"] = "fig7_time_breakdown.png"
        fig.savefig(os.path.join(out_dir, figs["fig7"]), dpi=120)
        plt.close(fig)
    return figs


def _fmt(x, nd=0):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:,.{nd}f}"


def _contact_variant_section(results):
    rows = {r["label"]: r for r in _by(results, "contact_variant")}
    if not rows:
        return []
    lines = ["", "## Hard contacts: activation rule and penetration correction (HmJ)", "",
             "Why the presets use `activation: hysteresis` and `penetration_correction: "
             "projection` with β_N = 1 (see `contact` in `config.py`). Sagging posture: "
             "`reset()` under a soft joint PD hold (80 N m/rad, 2 N m s/rad, ±20 N m), 2 s. "
             "Trot: the controller, 0.3 m/s, after 1 s of standing. Penetration: the deepest "
             "foot below the ground after a step. Ball: 1 kg, r = 0.1 m, Δt = 1 ms, dropped "
             "from 0.2 m with ε_N = 0 (any rebound is energy the correction added) and from "
             "1 m with ε_N = 0.5 (exact: v⁺/v⁻ = 0.5, apex ε² h = 0.25 m); its height is the "
             "highest point after the impact relative to the resting height (negative: it "
             "stays below the ground). Every row has the normal law's g_N⁺/Δt term (it is "
             "what keeps the loaded feet of the 10 µm-margin row from drifting out of the "
             "margin; without it that rule dropped them after 29 steps and they sank 3.2 mm).",
             "",
             "| rule | sag: max penetration | sag: loaded contacts dropped | trot: penetration "
             "mean / max | trot: dropped | trot: iterations / step (projections) | trot: "
             "steps/s | plastic drop: rebound | ε = 0.5: v⁺/v⁻, apex [m] |",
             "|---|---|---|---|---|---|---|---|---|"]
    for label, _ in CONTACT_VARIANTS:
        r = rows.get(label)
        if r is None:
            continue
        lines.append(
            f"| {label} | {r['sag_penetration_max_mm']:.4f} mm | {r['sag_opened']} | "
            f"{r['trot_penetration_mean_mm']:.4f} / {r['trot_penetration_max_mm']:.4f} mm | "
            f"{r['trot_opened']} | {r['trot_iterations']:.1f} ({r['trot_projections']}) | "
            f"{_fmt(r['trot_steps_per_second'])} | {r['plastic_rebound_velocity']:.3f} m/s, "
            f"{r['plastic_rebound_height_mm']:.3f} mm | {r['restitution_ratio']:.4f}, "
            f"{r['restitution_apex_ratio']:.4f} |")
    return lines


def _vs_mujoco_section(results):
    """The report's "Speed beside MuJoCo" section from the vs_mujoco record (none: none)."""
    rec = next(iter(_by(results, "vs_mujoco")), None)
    if rec is None:
        return []
    lines = ["", "## Speed beside MuJoCo (`starleth-bench --vs-mujoco`)", ""]
    if rec["missing"]:
        return lines + ["Not measured: mujoco is not installed (an optional benchmark "
                        "dependency: `make bench` or `pip install -r requirements-bench.txt`)."]
    lines += [rec["header"] + ". Run alone after the other tasks; both loops include the same "
              "Python PD law per step (per control period for the presets); see the README's "
              "[Speed beside MuJoCo](../README.md#speed-beside-mujoco-starleth-bench---vs-mujoco) "
              "for the setup and the history before and after issue #16.", "",
              "| simulator | Δt [ms] | steps/s (median) | min | max | ratio to MuJoCo | "
              "Σ F_N / mg | base z [mm] |", "|---|---|---|---|---|---|---|---|"]
    for row in rec["rows"]:
        lines.append(f"| {row['name']} | {row['dt_ms']:.3g} | {_fmt(row['median'])} | "
                     f"{_fmt(row['min'])} | {_fmt(row['max'])} | {row['ratio']:.2f} | "
                     f"{row['normal_force_ratio']:.4f} | {row['height_mm']:.2f} |")
    lines += ["", f"Like with like: {rec['like_with_like']}."]
    lines += [f"- {p}" for p in rec["problems"]]
    return lines


def write_report(results, figs, out_dir, quick, elapsed, jobs):
    from ..physics.config import load_preset
    import platform
    t1 = sorted(_by(results, "table1"), key=lambda r: TABLE1.index(r["preset"]))
    lines = ["# StarlETH simulator: evaluation against Gehring et al. 2014", ""]
    lines.append(f"Generated by `starleth-eval{' --quick' if quick else ''}` in {elapsed:.0f} s "
                 f"with {jobs} worker processes on {platform.processor() or platform.machine()}"
                 f", Python {platform.python_version()}. The paper's figures are C++ on a 3.3 GHz "
                 "Xeon E31245. Our runs time `Simulator.step` only (physics, not the "
                 "controller), while the controller trots at 0.3 m/s; parallel workers share "
                 "the machine, so absolute rates are lower than in `starleth-bench`.")
    if quick:
        lines += ["", "**Quick mode**: every run is shortened; figures are indicative only."]
    lines += ["", "## Table 1: simulation speed while trotting", "",
              "| config | contact | coords | prox | bilateral | α | steps/s (ours) | steps/s (paper) "
              "| ratio | RTF (ours) | RTF (paper) | iterations/step | non-converged steps |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in t1:
        c = load_preset(r["preset"])
        ps, pr = c.paper.get("steps_per_second"), c.paper.get("realtime_factor")
        hard = c.contact_model == "hard"
        lines.append(
            f"| {r['preset']} | {c.contact_model} | {c.coordinates} | "
            f"{c.solver.scheme.upper() if hard else '-'} | "
            f"{c.bilateral.method if c.bilateral.method != 'none' else '-'} | "
            f"{c.solver.alpha if hard else '-'} | "
            f"{_fmt(r['steps_per_second'])} ± {_fmt(r['steps_per_second_std'])} | {_fmt(ps)} | "
            f"{r['steps_per_second'] / ps:.2f} | {r['rtf']:.1f} ± {r['rtf_std']:.1f} | {pr} | "
            f"{r['mean_iterations']:.1f} | {r['nonconverged']} |")
    lines += ["", "## Accuracy", "", "| measure | config | ours | paper |", "|---|---|---|---|"]
    for r in t1:
        if "foot_sink_mean_mm" in r and r["preset"] == "Cm":
            lines.append(f"| foot sink while trotting (mean / max over stance) | Cm | "
                         f"{r['foot_sink_mean_mm']:.2f} / {r['foot_sink_max_mm']:.2f} mm | 4.4 mm |")
    for r in t1:
        if "foot_penetration_mean_mm" in r:
            lines.append(f"| foot penetration while trotting (mean / max over the steps; "
                         f"loaded contacts dropped) | {r['preset']} | "
                         f"{1e3 * r['foot_penetration_mean_mm']:.3f} / "
                         f"{1e3 * r['foot_penetration_max_mm']:.3f} µm "
                         f"({r['loaded_contacts_opened']}) | - |")
    for r in sorted(_by(results, "unilateral_drift"), key=lambda r: TABLE1.index(r["preset"])):
        lines.append(f"| unilateral (foot) drift while standing | {r['preset']} | "
                     f"{r['drift_um_per_min']:.3f} µm/min (lowest foot gap "
                     f"{r['min_gap_um']:.2f} µm) | 750 µm/min |")
    for r in sorted(_by(results, "bilateral_drift"), key=lambda r: TABLE1.index(r["preset"])):
        lines.append(f"| bilateral drift while trotting ({r['seconds']:.0f} s) | {r['preset']} | "
                     f"{r['drift_um_per_min']:.3f} µm/min (max violation "
                     f"{r['violation_max_um']:.2f} µm) | 0.59 µm/min |")
    lines += _contact_variant_section(results)
    lims = alpha_limits(_by(results, "fig6"))
    if lims:
        lines += ["", "## Fig. 6: upper limit of α", "",
                  "Largest α of the grid for which every step of the run converged (with "
                  f"`max_iterations` {FIG6_MAX_ITERATIONS} and no fallback), per gait; the paper "
                  "chose α as half of this limit. (At very small α a run can also fail by "
                  "needing more iterations than the cap.)", "", "| config | stand | trot | Table 1 α |", "|---|---|---|---|"]
        for preset in sorted({k[0] for k in lims}, key=TABLE1.index):
            row = []
            for gait in ("stand", "trot"):
                lim, top = lims.get((preset, gait), (None, None))
                row.append("none" if lim is None else (f"≥ {lim}" if top else f"{lim}"))
            lines.append(f"| {preset} | {row[0]} | {row[1]} | {load_preset(preset).solver.alpha} |")
    auto = alpha_auto_rows(_by(results, "fig6"))
    if auto:
        lines += ["", "## Fig. 6: α = auto against the best fixed α", "",
                  "`solver.alpha: auto` (adaptive α, no fallback) beside the fixed α of the "
                  "grid with the fewest mean iterations per step.", "",
                  "| config | gait | best fixed α | its mean iterations | auto: mean "
                  "iterations | auto: every step converged |", "|---|---|---|---|---|---|"]
        for (preset, gait), (a, it_best, it_auto, ok) in sorted(
                auto.items(), key=lambda kv: (TABLE1.index(kv[0][0]), kv[0][1])):
            lines.append(f"| {preset} | {gait} | {a} | {it_best:.1f} | {it_auto:.1f} | "
                         f"{'yes' if ok else 'no'} |")
    lines += ["", "## Robustness: push-over stress test", "",
              "Standing robot, lateral push of 70 N s (700 N for 0.1 s) on the trunk, 0.5 s "
              "into the run; the controller keeps standing.", "",
              "| config | fell on its side (max tilt) | knee/trunk contacts | non-finite | "
              "max iterations | every step converged | completed |",
              "|---|---|---|---|---|---|---|"]
    for r in sorted(_by(results, "pushover"), key=lambda r: TABLE1.index(r["preset"])):
        kt = r["knee_trunk_contacts"]
        lines.append(f"| {r['preset']} | {'yes' if r['fell'] else 'no'} ({r['max_tilt_deg']:.0f}°) | "
                     f"{len(kt)} ({', '.join(kt[:4])}{'…' if len(kt) > 4 else ''}) | "
                     f"{'yes' if r['nonfinite'] else 'no'} | {r['max_iterations']} | "
                     f"{'yes' if r['all_converged'] else 'no (' + str(r['nonconverged']) + ' steps)'} | "
                     f"{'yes' if r['completed'] else 'no: ' + str(r['error'])} |")
    lines += _vs_mujoco_section(results)
    for key, title in (("fig5", "Fig. 5: LF normal contact force over one trot cycle"),
                       ("fig6", "Fig. 6: prox iterations against α"),
                       ("fig7", "Fig. 7: time per step by phase")):
        if key in figs:
            lines += ["", f"## {title}", "", f"![{title}]({figs[key]})"]
    f7 = sorted(_by(results, "fig7"), key=lambda r: TABLE1.index(r["preset"]))
    if f7:
        lines += ["", "| config | M and h | M⁻¹ | G (G_B⁻¹) | u^E (prox) | rest | total [µs] |",
                  "|---|---|---|---|---|---|---|"]
        for r in f7:
            p = r["phases_us"]
            lines.append(f"| {r['preset']} | " + " | ".join(f"{x:.1f}" for x in p) +
                         f" | {sum(p):.1f} |")
    with open(os.path.join(out_dir, "report.md"), "w") as f:
        f.write("\n".join(lines) + "\n")


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
    from .sweep import SweepError
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
