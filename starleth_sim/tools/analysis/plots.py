"""The plots of ``starleth-analyze`` (matplotlib, an optional dependency, imported only
here and only when plotting): contact forces, gait diagram, base trajectory, joint torques,
solver iterations, real-time factor, one foot's normal force; several runs overlaid."""
from __future__ import annotations

import math
import os

import numpy as np

from .run import AnalysisError
from .summary import horizontal_velocity, real_time_factor, stance_intervals

PLOTS = ("contact_forces", "gait", "base_trajectory", "joint_torques", "solver_iterations",
         "real_time_factor")
#: the real-time factor plot's windows per run at most: a run whose stamps span far more
#: than MAX_RTF_WINDOWS windows (garbage stamps: two messages 2e9 s apart) gets wider ones
MAX_RTF_WINDOWS = 100_000


def rtf_window(span, window):
    """The window [s] of the real-time factor over `span` s of sim time: `window`, or wider
    where the span would hold more than MAX_RTF_WINDOWS of them."""
    return max(window, span / MAX_RTF_WINDOWS) if math.isfinite(span) else window


def windowed_rate(t_ref, sim, wall, window):
    """Δsim/Δwall over consecutive windows of `window` seconds of t_ref (a last partial
    window shorter than half a window is left out; at most MAX_RTF_WINDOWS windows: wider
    ones where the stamps span more)."""
    if t_ref.size < 2:
        return np.zeros(0), np.zeros(0)
    window = rtf_window(float(t_ref[-1] - t_ref[0]), window)
    edges = np.arange(t_ref[0], t_ref[-1], window)
    if t_ref[-1] - edges[-1] >= 0.5 * window or edges.size == 1:
        edges = np.append(edges, t_ref[-1])
    idx = np.unique(np.clip(np.searchsorted(t_ref, edges), 0, t_ref.size - 1))
    if idx.size < 2:
        idx = np.array([0, t_ref.size - 1])
    ds, dw = np.diff(sim[idx]), np.diff(wall[idx])
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(dw > 0, ds / dw, np.nan)
    return 0.5 * (t_ref[idx][1:] + t_ref[idx][:-1]), r


def run_color(i):
    """The colour of the i-th overlaid run."""
    return f"C{i % 10}"


def finish_axes(ax, xlabel, ylabel, title, legend=True):
    """Labels, title, grid and (where something is labelled) the legend of an axes."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    if legend:
        handles, _ = ax.get_legend_handles_labels()
        if handles:
            ax.legend(fontsize="small", loc="best")


def window_suffix(runs):
    """' (A .. B)' for a title when --tmin/--tmax cut the runs, else ''."""
    w = runs[0].window
    if w == (None, None):
        return ""
    a = "start" if w[0] is None else f"{w[0]:g} s"
    b = "end" if w[1] is None else f"{w[1]:g} s"
    return f" ({a} .. {b})"


def feet_of(runs) -> list:
    """The feet of the runs (each run's in its robot's order), the first run's first."""
    feet = []
    for r in runs:
        feet += [f for f in r.feet if f not in feet]
    return feet


def _has_foot(r, foot):
    return foot in r.feet and r.has("wrench", foot)


def plot_contact_forces(plt, runs, opts):
    feet = feet_of(runs)
    have = [r for r in runs if any(_has_foot(r, f) for f in feet)]
    if not have:
        return None
    cols = 2 if len(feet) <= 4 else 3
    fig, axes = plt.subplots(-(-len(feet) // cols), cols, figsize=(12, 7), sharex=True,
                             squeeze=False)
    for ax, foot in zip(axes.flat, feet, strict=False):
        for i, r in enumerate(runs):
            if _has_foot(r, foot):
                t, fz = r.normal_force(foot)
                ax.plot(t, fz, color=run_color(i), lw=0.9, label=r.label)
        ax.axhline(opts.threshold, color="0.4", ls=":", lw=0.8,
                   label=f"contact threshold {opts.threshold:g} N")
        finish_axes(ax, "time [s]", "normal force F_z [N]", foot)
    fig.suptitle("Contact normal force per foot (world z)" + window_suffix(runs))
    fig.tight_layout()
    return fig


def plot_single_foot(plt, runs, opts):
    foot = opts.foot
    have = [r for r in runs if _has_foot(r, foot)]
    if not have:
        return None
    fig, ax = plt.subplots(figsize=(9, 4.5))
    for i, r in enumerate(runs):
        if _has_foot(r, foot):
            t, fz = r.normal_force(foot)
            ax.plot(t, fz, color=run_color(i), lw=1.0, label=r.label)
    finish_axes(ax, "time [s]", "normal force F_z [N]",
            f"{foot} normal force" + window_suffix(runs))
    fig.tight_layout()
    return fig


def plot_gait(plt, runs, opts):
    from matplotlib.patches import Patch
    feet = feet_of(runs)
    have = [r for r in runs if any(_has_foot(r, f) for f in feet)]
    if not have:
        return None
    n = len(runs)
    fig, ax = plt.subplots(figsize=(12, 1.2 + 0.5 * len(feet) * max(n, 1) + 0.6))
    ticks, labels = [], []
    row_h = 1.0 / n
    for k, foot in enumerate(feet):
        y0 = (len(feet) - 1 - k)
        for i, r in enumerate(runs):
            y = y0 + (n - 1 - i) * row_h
            if _has_foot(r, foot):
                t, fz = r.normal_force(foot)
                iv, _ = stance_intervals(t, fz, opts.threshold, opts.min_phase)
                ax.broken_barh([(a, b - a) for a, b in iv], (y + 0.1 * row_h, 0.8 * row_h),
                               facecolors=run_color(i))
        if n > 1 and k:
            ax.axhline(y0 + 1, color="0.3", lw=0.8)
        ticks.append(y0 + 0.5)
        labels.append(foot)
    ax.set_yticks(ticks)
    ax.set_yticklabels(labels)
    ax.set_ylim(0, len(feet))
    tmins = [float(r.normal_force(f)[0][0]) for r in have for f in feet if _has_foot(r, f)]
    tmaxs = [float(r.normal_force(f)[0][-1]) for r in have for f in feet if _has_foot(r, f)]
    ax.set_xlim(min(tmins), max(tmaxs) + 1e-9)
    handles = [Patch(color=run_color(i), label=f"{r.label}: stance") for i, r in enumerate(runs)]
    ax.legend(handles=handles, fontsize="small", loc="upper right")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("foot (bar = stance, gap = swing)")
    ax.set_title(f"Gait diagram: stance where F_z > {opts.threshold:g} N (phases shorter "
                 f"than {opts.min_phase * 1e3:g} ms merged)" + window_suffix(runs))
    ax.grid(True, axis="x", alpha=0.3)
    fig.tight_layout()
    return fig


def plot_base(plt, runs, opts):
    have = [r for r in runs if r.has("base")]
    if not have:
        return None
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    ax_xy, ax_v, ax_h = axes
    for i, r in enumerate(runs):
        if not r.has("base"):
            continue
        p = r.series("base")["data"][:, 0:3]
        t = r.series("base")["t"]
        ax_xy.plot(p[:, 0], p[:, 1], color=run_color(i), lw=1.0, label=r.label)
        ax_xy.plot(p[0, 0], p[0, 1], "o", color=run_color(i), ms=5,
                   label="start" if i == 0 else None)
        ax_xy.plot(p[-1, 0], p[-1, 1], "x", color=run_color(i), ms=7,
                   label="end" if i == 0 else None)
        tv, vx, vy, _ = horizontal_velocity(r, opts.twist_frame)
        ax_v.plot(tv, np.hypot(vx, vy), color=run_color(i), lw=0.9, label=r.label)
        ax_h.plot(t, p[:, 2], color=run_color(i), lw=0.9, label=r.label)
    ax_xy.set_aspect("equal", adjustable="datalim")
    finish_axes(ax_xy, "x [m]", "y [m]", "Base trajectory (world x-y)")
    finish_axes(ax_v, "time [s]", "horizontal speed [m/s]", "Base horizontal speed |(v_x, v_y)|")
    finish_axes(ax_h, "time [s]", "height z [m]", "Base height")
    fig.suptitle("Base state (/starleth/base_state)" + window_suffix(runs))
    fig.tight_layout()
    return fig


def plot_joint_torques(plt, runs, _opts):
    have = [r for r in runs if r.has("joints")]
    if not have:
        return None
    names = []
    for r in have:
        names += [n for n in r.joint_names if n not in names]
    rows = -(-len(names) // 3)
    fig, axes = plt.subplots(rows, 3, figsize=(14, 2.5 * rows), sharex=True, squeeze=False)
    for j, name in enumerate(names):
        ax = axes[j // 3][j % 3]
        for r in have:
            if name in r.joint_names:
                s = r.series("joints")
                e = s["data"][:, r.joint_names.index(name)]
                if np.isfinite(e).any():
                    ax.plot(s["t"], e, color=run_color(runs.index(r)), lw=0.7,
                            label=r.label)
        last = j >= len(names) - 3
        finish_axes(ax, "time [s]" if last else "", "torque [N m]", name)
        if not last:
            ax.set_xlabel("time [s]", fontsize="x-small")
    fig.suptitle("Joint torques (/joint_states effort)" + window_suffix(runs))
    fig.tight_layout()
    return fig


def plot_solver(plt, runs, _opts):
    have = [r for r in runs if r.has("solver")]
    if not have:
        return None
    fig, (ax_h, ax_t) = plt.subplots(1, 2, figsize=(13, 4.5))
    its = [r.series("solver")["data"][:, 0] for r in have]
    its = [x[np.isfinite(x)] for x in its]
    hi = max((float(x.max()) for x in its if x.size), default=1.0)
    lo = min(min((float(x.min()) for x in its if x.size), default=0.0), 0.0)   # < 0: garbage
    if hi - lo <= 80:
        bins = np.arange(math.floor(lo) - 0.5, max(hi, lo) + 1.5, 1.0)
    else:
        bins = np.linspace(lo, hi * 1.0001 if hi > 0 else hi + 1.0, 61)
    for i, r in enumerate(runs):
        if not r.has("solver"):
            continue
        s = r.series("solver")
        it = s["data"][:, 0]
        ok = np.isfinite(it)
        if ok.any():
            ax_h.hist(it[ok], bins=bins, histtype="stepfilled" if len(have) == 1 else "step",
                      color=run_color(i), alpha=0.6 if len(have) == 1 else 1.0, lw=1.2,
                      label=f"{r.label} (mean {it[ok].mean():.1f})")
        ax_t.plot(s["t"][ok], it[ok], color=run_color(i), lw=0.6, label=r.label)
    finish_axes(ax_h, "prox iterations per control step [-]", "control steps [-]",
            "Solver iterations histogram")
    finish_axes(ax_t, "time [s]", "prox iterations per control step [-]",
            "Solver iterations over time")
    fig.suptitle("Solver (/starleth/solver)" + window_suffix(runs))
    fig.tight_layout()
    return fig


def plot_rtf(plt, runs, opts):
    data = [(i, r, real_time_factor(r)) for i, r in enumerate(runs)]
    data = [(i, r, x) for i, r, x in data if x["source"] or "compute" in x]
    if not data:
        return None
    fig, (ax_a, ax_b) = plt.subplots(1, 2, figsize=(13, 4.5))
    top = 0.0
    # windows: --rtf-window, but at least 10 per run for short runs, at most
    # MAX_RTF_WINDOWS for long ones
    span = max((float(r.series(*k)["t"][-1] - r.series(*k)["t"][0])
                for _, r, _ in data for k in r.timed_series()
                if r.series(*k)["t"].size > 1), default=0.0)
    window = min(opts.rtf_window, span / 10) if span > 0 else opts.rtf_window
    window = rtf_window(span, window)
    for i, r, x in data:
        if x["source"]:
            ax_a.plot(x["wall"], x["sim"], color=run_color(i), lw=1.0,
                      label=f"{r.label} (wall = {x['source']}, RTF {x['value']:.2f})")
            tc, rr = windowed_rate(x["t"], x["sim"], x["wall"], window)
            ax_b.plot(tc, rr, color=run_color(i), lw=1.0, marker=".", label=f"{r.label}")
            top = max(top, float(x["wall"][-1]))
        if "compute" in x:
            c = x["compute"]
            ax_a.plot(c["wall"], c["sim"], color=run_color(i), lw=1.0, ls="--",
                      label=f"{r.label} (physics compute only, RTF {c['value']:.1f})")
            tc, rr = windowed_rate(c["t"], c["sim"], c["wall"], window)
            ax_b.plot(tc, rr, color=run_color(i), lw=1.0, ls="--", marker=".",
                      label=f"{r.label} (physics compute only)")
            top = max(top, float(c["wall"][-1]))
    ax_a.plot([0, top], [0, top], color="0.5", ls=":", lw=1.0, label="real time (RTF 1)")
    ax_b.axhline(1.0, color="0.5", ls=":", lw=1.0, label="real time (RTF 1)")
    finish_axes(ax_a, "wall time [s]", "sim time [s]", "Sim time vs wall time")
    finish_axes(ax_b, "sim time [s]", "real-time factor [-]",
            f"Real-time factor (Δsim/Δwall per {window:.3g} s of sim time)")
    ax_b.set_yscale("log")
    fig.suptitle("Real-time factor (solid: wall clock of the messages; dashed: solver "
                 "step_time, physics only)" + window_suffix(runs), fontsize="medium")
    fig.tight_layout()
    return fig


FIGURES = {"contact_forces": plot_contact_forces, "gait": plot_gait,
           "base_trajectory": plot_base, "joint_torques": plot_joint_torques,
           "solver_iterations": plot_solver, "real_time_factor": plot_rtf}


def load_pyplot():
    """matplotlib.pyplot on the Agg backend; AnalysisError where matplotlib is missing."""
    try:
        import matplotlib
        matplotlib.use("Agg", force=True)
        import matplotlib.pyplot as plt
    except ImportError:
        raise AnalysisError("matplotlib is needed for the plots (pip install matplotlib); "
                            "--no-plots prints the summary only") from None
    return plt


def make_figures(runs, opts) -> dict:
    """{name: matplotlib Figure} of every plot that has data (caller closes them)."""
    plt = load_pyplot()
    figs = {}
    for name, fn in FIGURES.items():
        fig = fn(plt, runs, opts)
        if fig is not None:
            figs[name] = fig
    if len(runs) > 1 or opts.foot_given:
        fig = plot_single_foot(plt, runs, opts)
        if fig is not None:
            figs[f"normal_force_{opts.foot}"] = fig
    return figs


def save_figures(runs, opts, out_dir) -> dict:
    plt = load_pyplot()
    os.makedirs(out_dir, exist_ok=True)
    written = {}
    for name, fig in make_figures(runs, opts).items():
        path = os.path.join(out_dir, f"{name}.png")
        fig.savefig(path, dpi=opts.dpi)
        plt.close(fig)
        written[name] = path
    return written

