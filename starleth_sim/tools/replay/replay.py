"""``starleth-replay``: re-simulate a recorded run open loop from its bag.

    starleth-replay runs/demo.mcap                       # bit-identical to the recording?
    starleth-replay runs/demo.mcap --preset HMJD --preset Cm --out replay/

A bag written by ``sim_node record:=...`` holds everything a headless re-run needs (the
``starleth_sim`` metadata record): the physics configuration as resolved (YAML), the initial
state (q, u in the simulator's coordinates, and in minimal coordinates), the control period,
the package version, and the topic names. The torques applied at each physics step of step
k -> k+1 are the ``starleth/applied_torque`` message at t_(k+1) (saturated at the effort limit
and derated at the velocity limit: what the motors applied; an impedance command's torque
changes within a control period; with the explicit torques and the implicit dampers' kd
that ``Simulator.step_applied`` re-solves), replayed with ``Simulator.step_applied``; in bags
without
that topic, the effort of the ``/joint_states`` message stamped t_(k+1), and every external
wrench the node
took is recorded on its input topic with the log time t_k of the state after which it was
applied: it acts from step k -> k+1.

The replay makes the same calls on a ``Simulator`` as sim_node did (``SimService``: warm-up,
reset to the initial state, ``submit_wrench``, ``step``). With the recorded configuration it
feeds the recorded applied torques with the actuator model off (``actuator.velocity_limit:
ignore``: the torques are already those the motors applied; clipping them again at the
effort limit changes nothing, derating them twice would), and it must reproduce the recording
bit for bit: every step's joint positions and velocities (exact: ground_truth/joint_states
with noisy sensors), base pose and twist (as /starleth/base_state holds them) and the foot
forces are compared exactly, and so are the sensor topics (joint_states as measured,
starleth/imu, starleth/foot_contacts), which the replay's sensors regenerate from the
recorded configuration and seed (physics/sensors.py); the output says "bit-identical" or
gives the first step that differs and by how much (exit status 0 or 3).

``--preset NAME`` (repeatable, or a YAML path) runs the same torque stream through other
configurations (the initial state converted through minimal coordinates; their motors
derate a torque beyond the velocity limit, so a leg in the air does not spin up without
bound once the run has left the recorded one) and writes overlay
plots (foot normal forces and base path by ``starleth-analyze``'s plotting, joint angles)
and a table of differences against the recording. The recorded run was closed loop: its
controller reacted to the recorded physics. Replayed open loop through other physics, the
robot follows the torques of a state it is no longer in: the runs diverge (the robot may
fall); the output says from when (base more than ``--diverge-position`` from the recorded
path, or a joint more than ``--diverge-angle`` from its recorded angle).

A recording its recorder closed after a failure (a file-size limit, a full disk, its writer
process killed: the bag's ``starleth_recording_fault`` metadata), or a truncated one read
with ``--salvage``, ends within the messages of its last step: its complete steps are
replayed, and a warning says how many states were left out and why.

A bag without the metadata (not recorded by sim_node), a truncated or damaged one
(``--salvage`` reads up to the damage), one whose joint states skip steps, or whose
metadata or messages are not what sim_node writes (a control period that is not a positive
number, joint names or an initial state that are not JSON or do not fit, a configuration
whose YAML aliases expand it beyond its size, joint states of the wrong length, a NaN or
infinite torque) gives one line on stderr and exit status 1.

This module is the command line and the overlay plots; the recording is read by
:mod:`.recording`, re-simulated and compared by :mod:`.resimulation`.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from ...physics.config import ConfigError, load_preset
from ..analysis.plots import (
    finish_axes,
    load_pyplot,
    plot_base,
    plot_contact_forces,
    run_color,
    window_suffix,
)
from ..analysis.run import Run
from ..common.bag import BagError
from ..common.console import run_console_script
from .recording import PROG, Recording, ReplayError, load_recording, warn
from .resimulation import Comparison, Replay, compare_exact, divergence, resimulate


# =========================================================================================
# plots (starleth-analyze's, on runs built from arrays)
# =========================================================================================
def _as_run(label, states, rec):
    n = states["joint_positions"].shape[0]
    t = np.arange(n) * rec.control_period
    base = np.hstack([states["base_position"], states["base_orientation"],
                      states["base_linear_velocity"], states["base_angular_velocity"]])
    wrench = {f: states["foot_forces"][:, 3 * i:3 * i + 3] for i, f in enumerate(rec.feet)}
    run = Run.from_arrays(label, t, base=base, wrench=wrench, base_frames=("world", "base"),
                          feet=rec.feet, joint_names=rec.joint_names)
    run.joint_positions = states["joint_positions"]
    return run


def plot_joint_angles(plt, runs, _opts):
    names = runs[0].joint_names
    rows = -(-len(names) // 3)
    fig, axes = plt.subplots(rows, 3, figsize=(14, 2.5 * rows), sharex=True, squeeze=False)
    for j, name in enumerate(names):
        ax = axes[j // 3][j % 3]
        for i, r in enumerate(runs):
            t = r.series("base")["t"]
            ax.plot(t, r.joint_positions[:, j], color=run_color(i), lw=0.8, label=r.label)
        finish_axes(ax, "time [s]" if j >= len(names) - 3 else "", "angle [rad]", name,
                    legend=j == 0)
    fig.suptitle("Joint angles" + window_suffix(runs))
    fig.tight_layout()
    return fig


def write_overlays(rec: Recording, replays, out_dir, dpi=110) -> list:
    """contact_forces.png, base_trajectory.png (starleth-analyze's plots) and
    joint_angles.png: the recording and the replays overlaid."""
    plt = load_pyplot()
    runs = [_as_run("recorded", rec.states, rec)]
    runs += [_as_run(r.label, r.states, rec) for r in replays]
    opts = argparse.Namespace(threshold=5.0, twist_frame="child", min_phase=0.02)
    os.makedirs(out_dir, exist_ok=True)
    written = []
    for name, fn in (("contact_forces", plot_contact_forces), ("base_trajectory", plot_base),
                     ("joint_angles", plot_joint_angles)):
        fig = fn(plt, runs, opts)
        if fig is None:
            continue
        path = os.path.join(out_dir, f"{name}.png")
        fig.savefig(path, dpi=dpi)
        plt.close(fig)
        written.append(path)
    return written


# =========================================================================================
# command line
# =========================================================================================
def _fmt_t(x):
    return "never" if x is None else f"t = {x:.3f} s"


def format_comparison(rec: Recording, rep: Replay, c: Comparison) -> list:
    cp = rec.control_period
    if c.identical:
        some = f" (the first {c.steps} of {rec.steps})" if c.steps < rec.steps else ""
        sensors = [name for q, name in (("measured_joint_states", "joint_states as measured"),
                                          ("imu", "IMU"), ("foot_contacts", "foot contacts"))
                   if q in rep.states]
        lines = [f"  bit-identical: all {c.steps} steps{some} (joint positions and velocities, "
                 "base pose and twist" + (", foot forces" if c.forces_identical else "") +
                 "".join(f", {name}" for name in sensors) + ")"]
        if not c.forces_identical:
            lines.append(f"  (foot forces differ by up to {c.max_abs['foot_forces']:.3g} N)")
        return lines
    if c.first_step is None:
        return [f"  NOT complete: the replay stopped after {rep.steps} of {rep.requested} "
                f"steps ({rep.error}); identical up to there"]
    diffs = ", ".join(f"{q} {v:.3g}" for q, v in c.first_quantities.items())
    return [f"  NOT bit-identical: first difference at step {c.first_step} "
            f"(t = {c.first_step * cp:.4f} s): max |Δ| {diffs}",
            "  largest over the run: " + ", ".join(f"{q} {v:.3g}"
                                                   for q, v in c.max_abs.items())]


def build_parser():
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("bag", help="an MCAP file or rosbag2 directory recorded by sim_node")
    ap.add_argument("--preset", action="append", default=[],
                    help="also run the torque stream through this configuration (a preset "
                         "name or YAML path; repeatable)")
    ap.add_argument("--out", default=None,
                    help="directory of the overlay plots and table (default: <bag>_replay/)")
    ap.add_argument("--steps", type=int, default=None, help="replay only the first N steps")
    ap.add_argument("--diverge-position", type=float, default=0.01,
                    help="base distance [m] from the recorded path counted as divergence")
    ap.add_argument("--diverge-angle", type=float, default=0.05,
                    help="joint angle difference [rad] counted as divergence")
    ap.add_argument("--no-plots", action="store_true")
    ap.add_argument("--json", default=None, help="write the results as JSON")
    ap.add_argument("--salvage", action="store_true",
                    help="replay a truncated bag up to the damage")
    return ap


def run(argv=None) -> int:
    a = build_parser().parse_args(argv)
    if a.steps is not None and a.steps < 1:
        build_parser().error("--steps must be >= 1")
    try:
        configs = [load_preset(p) for p in a.preset]
    except ConfigError as e:
        raise ReplayError(f"--preset: {e}") from None
    t0 = time.perf_counter()
    rec = load_recording(a.bag, salvage=a.salvage)
    try:
        rec_cfg = rec.config()
    except ConfigError as e:
        raise ReplayError(str(e)) from None
    print(f"== {a.bag}: {rec.steps} steps of {rec.control_period * 1e3:g} ms "
          f"({rec.steps * rec.control_period:.3f} s), robot {rec.description.name}, physics "
          f"{rec_cfg.name}, recorded by "
          f"starleth_sim {rec.package_version}; {sum(map(len, rec.wrenches.values()))} external "
          f"wrench(es); read in {time.perf_counter() - t0:.2f} s ==")
    resets = rec.summary.get("resets", 0)
    if isinstance(resets, int) and resets > 0:
        warn(f"the run was reset {resets} time(s) (~/reset); a replay does not reset: it "
             "differs from the first reset on")
    rep = resimulate(rec, label=f"{rec_cfg.name} (replay)", steps=a.steps)
    c = compare_exact(rec, rep)
    print(f"replay with the recorded configuration ({rep.wall:.2f} s):")
    for line in format_comparison(rec, rep, c):
        print(line)
    doc = {"bag": a.bag, "steps": rec.steps, "recording_cut": rec.cut, "config": rec_cfg.name,
           "package_version": rec.package_version,
           "bit_identical": c.identical, "first_difference_step": c.first_step,
           "first_difference": c.first_quantities, "max_abs_difference": c.max_abs,
           "presets": {}}
    replays = _open_loop_replays(rec, configs, a, doc) if configs else []
    if configs and not a.no_plots:
        base = a.bag.rstrip("/")
        out = a.out or (os.path.splitext(base)[0] if base.endswith(".mcap") else base) + "_replay"
        written = write_overlays(rec, replays, out)
        doc["plots"] = written
        print(f"plots in {out}/: " + ", ".join(os.path.basename(p) for p in written))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(doc, f, indent=1)
    return 0 if c.identical else 3


def _open_loop_replays(rec, configs, a, doc) -> list:
    """The recorded torques through each of `configs`, open loop: where each diverges from
    the recording and falls, printed and into doc["presets"]; the replays."""
    print("open-loop replays through other configurations: the recorded run was closed "
          "loop (its controller reacted to the recorded physics); the same torques "
          "applied open loop to other physics make the runs diverge, and the robot may "
          "fall. Divergence: base more than "
          f"{a.diverge_position:g} m off the recorded path or a joint more than "
          f"{a.diverge_angle:g} rad off its recorded angle.")
    replays, rows = [], []
    for cfg in configs:
        r = resimulate(rec, cfg, label=cfg.name, steps=a.steps)
        replays.append(r)
        dv = divergence(rec, r, a.diverge_position, a.diverge_angle)
        doc["presets"][cfg.name] = dv
        rows.append((cfg.name, dv))
        tail = f"; stopped: {r.error}" if r.error else ""
        print(f"  {cfg.name:8s} diverges {_fmt_t(dv['diverges_at'])}, falls "
              f"{_fmt_t(dv['fell_at'])} ({r.steps} steps in {r.wall:.2f} s{tail})")
    print("\n| config | diverges at | falls at | base Δ max / final [m] | joint Δ max / RMS "
          "[rad] | foot F_z Δ RMS [N] | iterations / step |")
    print("|---|---|---|---|---|---|---|")
    for name, dv in rows:
        print(f"| {name} | {_fmt_t(dv['diverges_at'])} | {_fmt_t(dv['fell_at'])} | "
              f"{dv['base_max_m']:.4f} / {dv['base_final_m']:.4f} | "
              f"{dv['joint_max_rad']:.4f} / {dv['joint_rms_rad']:.4f} | "
              f"{dv['foot_force_rms_n']:.2f} | {dv['iterations_mean']:.1f} |")
    return replays


def main(argv=None) -> int:
    """Console script: 0 bit-identical, 3 not bit-identical, 1 a bag that cannot be replayed
    (one line), 2 bad arguments."""
    return run_console_script(PROG, run, argv, errors=(BagError, ConfigError))


if __name__ == "__main__":
    sys.exit(main())
