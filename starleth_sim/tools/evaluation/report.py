"""The report of ``starleth-eval`` from its tasks' result records: the figures (Fig. 5, 6
and 7, PNG) and ``report.md`` (Table 1, accuracy, the hard-contact rule, the α limits, the
push-over test, the terrain, the speed beside MuJoCo), beside the paper's figures.
"""
from __future__ import annotations

import math
import os
import platform

import numpy as np

from ...physics.config import PRESETS as TABLE1  # the paper's Table 1, in its order
from ...physics.config import load_preset
from ...physics.stepper import PHASES
from ..common.gait_run import GAIT_PERIOD, STAND_BEFORE_TROT
from .tasks import CONTACT_VARIANTS, FIG6_MAX_ITERATIONS
from .terrain import terrain_section

PHASE_LABELS = {"M_and_h": "M and h", "M_inverse": "M⁻¹ (and M⁻¹W)", "G": "G (and G_B⁻¹)",
                "prox": "u^E (prox)", "rest": "rest"}
PAPER_ACCURACY = {"foot_sink_mm": 4.4, "unilateral_drift_um_per_min": 750.0,
                  "bilateral_drift_um_per_min": 0.59}


def results_of_kind(results, kind):
    """The result records of one kind (a task's "kind")."""
    return [r for r in results if r["kind"] == kind]


def in_table1_order(results, kind):
    """The result records of one kind, in the order of their presets in Table 1."""
    return sorted(results_of_kind(results, kind), key=lambda r: TABLE1.index(r["preset"]))


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
    """The paper's Fig. 5, 6 and 7 from our runs, as PNG files in `out_dir`: {key: file}
    of those the results hold."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    figs = {}
    for key, name, draw in (("fig5", "fig5_contact_force.png", _fig5),
                            ("fig6", "fig6_iterations_vs_alpha.png", _fig6),
                            ("fig7", "fig7_time_breakdown.png", _fig7)):
        fig = draw(plt, results)
        if fig is not None:
            fig.tight_layout()
            fig.savefig(os.path.join(out_dir, name), dpi=120)
            plt.close(fig)
            figs[key] = name
    return figs


def _fig5(plt, results):
    """Fig. 5: the LF foot's normal force over one trot cycle (None: no run to draw)."""
    t1 = {r["preset"]: r for r in results_of_kind(results, "table1")}
    f5 = [r for r in results_of_kind(results, "fig5")]
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
        return fig
    return None


def _fig6(plt, results):
    """Fig. 6: prox iterations against α, standing and trotting (None: no run)."""
    f6 = results_of_kind(results, "fig6")
    if f6:
        fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
        auto = {(r["preset"], r["gait"]): r for r in f6 if r["alpha"] == "auto"}
        f6 = [r for r in f6 if r["alpha"] != "auto"]
        for ax, gait in zip(axes, ("stand", "trot"), strict=True):
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
        return fig
    return None


def _fig7(plt, results):
    """Fig. 7: the time per step by phase (None: no profiled run)."""
    f7 = in_table1_order(results, "fig7")
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
        return fig
    return None


def _fmt(x, nd=0):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:,.{nd}f}"


def _contact_variant_section(results):
    rows = {r["label"]: r for r in results_of_kind(results, "contact_variant")}
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
    rec = next(iter(results_of_kind(results, "vs_mujoco")), None)
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
    """report.md in `out_dir`: the paper's tables and figures beside ours, section by
    section."""
    lines = _header(quick, elapsed, jobs)
    lines += _table1_section(results)
    lines += _accuracy_section(results)
    lines += _contact_variant_section(results)
    lines += _fig6_sections(results)
    lines += _pushover_section(results)
    lines += terrain_section(results)
    lines += _vs_mujoco_section(results)
    lines += _figures_section(results, figs)
    with open(os.path.join(out_dir, "report.md"), "w") as f:
        f.write("\n".join(lines) + "\n")


def _header(quick, elapsed, jobs):
    lines = ["# StarlETH simulator: evaluation against Gehring et al. 2014", ""]
    lines.append(f"Generated by `starleth-eval{' --quick' if quick else ''}` in {elapsed:.0f} s "
                 f"with {jobs} worker processes on {platform.processor() or platform.machine()}"
                 f", Python {platform.python_version()}. The paper's figures are C++ on a 3.3 GHz "
                 "Xeon E31245. Our runs time `Simulator.step` only (physics, not the "
                 "controller), while the controller trots at 0.3 m/s; parallel workers share "
                 "the machine, so absolute rates are lower than in `starleth-bench`.")
    if quick:
        lines += ["", "**Quick mode**: every run is shortened; figures are indicative only."]
    return lines


def _table1_section(results):
    lines = ["", "## Table 1: simulation speed while trotting", "",
             "| config | contact | coords | prox | bilateral | α | steps/s (ours) | "
             "steps/s (paper) | ratio | RTF (ours) | RTF (paper) | iterations/step | "
             "non-converged steps |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in in_table1_order(results, "table1"):
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
    return lines


def _accuracy_section(results):
    t1 = in_table1_order(results, "table1")
    lines = ["", "## Accuracy", "", "| measure | config | ours | paper |", "|---|---|---|---|"]
    for r in t1:
        if "foot_sink_mean_mm" in r and r["preset"] == "Cm":
            lines.append(f"| foot sink while trotting (mean / max over stance) | Cm | "
                         f"{r['foot_sink_mean_mm']:.2f} / {r['foot_sink_max_mm']:.2f} mm "
                         "| 4.4 mm |")
    for r in t1:
        if "foot_penetration_mean_mm" in r:
            lines.append(f"| foot penetration while trotting (mean / max over the steps; "
                         f"loaded contacts dropped) | {r['preset']} | "
                         f"{1e3 * r['foot_penetration_mean_mm']:.3f} / "
                         f"{1e3 * r['foot_penetration_max_mm']:.3f} µm "
                         f"({r['loaded_contacts_opened']}) | - |")
    for r in in_table1_order(results, "unilateral_drift"):
        lines.append(f"| unilateral (foot) drift while standing | {r['preset']} | "
                     f"{r['drift_um_per_min']:.3f} µm/min (lowest foot gap "
                     f"{r['min_gap_um']:.2f} µm) | 750 µm/min |")
    for r in in_table1_order(results, "bilateral_drift"):
        lines.append(f"| bilateral drift while trotting ({r['seconds']:.0f} s) | {r['preset']} | "
                     f"{r['drift_um_per_min']:.3f} µm/min (max violation "
                     f"{r['violation_max_um']:.2f} µm) | 0.59 µm/min |")
    return lines


def _fig6_sections(results):
    """Fig. 6: the upper limit of α per gait, and α = auto against the best fixed α."""
    lines = []
    lims = alpha_limits(results_of_kind(results, "fig6"))
    if lims:
        lines += ["", "## Fig. 6: upper limit of α", "",
                  "Largest α of the grid for which every step of the run converged (with "
                  f"`max_iterations` {FIG6_MAX_ITERATIONS} and no fallback), per gait; the paper "
                  "chose α as half of this limit. (At very small α a run can also fail by "
                  "needing more iterations than the cap.)", "",
                  "| config | stand | trot | Table 1 α |", "|---|---|---|---|"]
        for preset in sorted({k[0] for k in lims}, key=TABLE1.index):
            row = []
            for gait in ("stand", "trot"):
                lim, top = lims.get((preset, gait), (None, None))
                row.append("none" if lim is None else (f"≥ {lim}" if top else f"{lim}"))
            lines.append(f"| {preset} | {row[0]} | {row[1]} | {load_preset(preset).solver.alpha} |")
    auto = alpha_auto_rows(results_of_kind(results, "fig6"))
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
    return lines


def _pushover_section(results):
    lines = ["", "## Robustness: push-over stress test", "",
             "Standing robot, lateral push of 70 N s (700 N for 0.1 s) on the trunk, 0.5 s "
             "into the run; the controller keeps standing.", "",
             "| config | fell on its side (max tilt) | knee/trunk contacts | non-finite | "
             "max iterations | every step converged | completed |",
             "|---|---|---|---|---|---|---|"]
    for r in in_table1_order(results, "pushover"):
        kt = r["knee_trunk_contacts"]
        converged = "yes" if r["all_converged"] else f"no ({r['nonconverged']} steps)"
        lines.append(f"| {r['preset']} | {'yes' if r['fell'] else 'no'} "
                     f"({r['max_tilt_deg']:.0f}°) | "
                     f"{len(kt)} ({', '.join(kt[:4])}{'…' if len(kt) > 4 else ''}) | "
                     f"{'yes' if r['nonfinite'] else 'no'} | {r['max_iterations']} | "
                     f"{converged} | "
                     f"{'yes' if r['completed'] else 'no: ' + str(r['error'])} |")
    return lines


def _figures_section(results, figs):
    """The figures (Fig. 5, 6, 7) and the Fig. 7 phase table."""
    lines = []
    for key, title in (("fig5", "Fig. 5: LF normal contact force over one trot cycle"),
                       ("fig6", "Fig. 6: prox iterations against α"),
                       ("fig7", "Fig. 7: time per step by phase")):
        if key in figs:
            lines += ["", f"## {title}", "", f"![{title}]({figs[key]})"]
    f7 = in_table1_order(results, "fig7")
    if f7:
        lines += ["", "| config | M and h | M⁻¹ | G (G_B⁻¹) | u^E (prox) | rest | total [µs] |",
                  "|---|---|---|---|---|---|---|"]
        for r in f7:
            p = r["phases_us"]
            lines.append(f"| {r['preset']} | " + " | ".join(f"{x:.1f}" for x in p) +
                         f" | {sum(p):.1f} |")
    return lines
