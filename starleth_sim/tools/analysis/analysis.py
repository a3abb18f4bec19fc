"""``starleth-analyze``: plots and a short summary of recorded runs.

    starleth-analyze runs/demo.mcap
    starleth-analyze compliant.mcap hard.mcap --label compliant hard --tmax 1.0
    starleth-analyze run.mcap --out plots/ --json summary.json

Reads MCAP bags (rosbag2 profile ``ros2``, ``cdr`` messages with ``ros2msg`` schemas: what
``sim_node`` with ``record:=...`` and ``ros2 bag record -s mcap`` write; a rosbag2 bag
directory holding .mcap files is read as one run) in one pass, decoding only the topics it
plots, with ``mcap`` + ``mcap_ros2`` (no ROS installation needed). Several bags are overlaid
in the same plots, labelled with ``--label`` or the file names.

Topics and what is made of them (time axis: sim time = header stamps, relative to the first
message of the bag):

* /starleth/{LF,RF,LH,RH}_foot/wrench (geometry_msgs/WrenchStamped, force.z = normal force
  in the world): ``contact_forces.png``, ``gait.png`` (stance where F_z > ``--threshold``);
* /starleth/base_state (nav_msgs/Odometry): ``base_trajectory.png`` (x-y path, horizontal
  speed, height);
* /joint_states (sensor_msgs/JointState, effort by joint name): ``joint_torques.png``;
* /starleth/solver (diagnostic_msgs/DiagnosticArray, the status holding the key
  'iterations'; also converged, residual, step_time): ``solver_iterations.png``;
* message times and the solver's step_time: ``real_time_factor.png``;
* the URDF (/robot_description or the recording's attachment; else the package's): the
  robot's weight and effort limits for the summary;
* with noisy sensors, the measured topics against the ground_truth/ ones: per signal the
  error's standard deviation and mean against the recorded configuration
  (:mod:`.sensor_noise`).

With two or more bags, ``normal_force_LF.png`` (``--foot``) overlays one foot's normal
force, as in Fig. 5 of Gehring et al. (2014).

Odometry twist: REP 105 puts it in ``child_frame_id`` (sim_node: 'base'); it is rotated
into the world with the pose's orientation before the horizontal speed |(v_x, v_y)| is
taken. A twist is taken as world-frame when child_frame_id is empty or equal to the header
frame (``--twist-frame`` overrides).

Real-time factor: sim time is the header stamps; the wall clock is the messages'
``publish_time`` (rosbag2: the send time) or ``log_time`` (rosbag2: the receive time) when
it differs from the stamps. sim_node's own recorder writes ``log_time = publish_time =``
the sim stamp, so such a bag holds no wall clock of the loop; then the *physics compute*
real-time factor is shown, from the solver's ``step_time`` key (wall time of the physics of
each control step: an upper bound, without ROS, the controller or pacing), and the realtime
loop's mean period from the ``starleth_sim_summary`` metadata when present.

A missing topic is reported on stderr (naming it) and its plots are skipped; a truncated
or corrupt file ends the program with a message and exit status 1 (``--salvage`` reads a
truncated file up to the damage instead). Messages that cannot be decoded are skipped and
counted on stderr; so are forces and base states holding a NaN, an infinite value or one
beyond 1e9 (``MAX_VALUE``), and such values of joint torques and solver figures are left
out. The real-time factor plot has at most ``MAX_RTF_WINDOWS`` windows per run, whatever
the span of the stamps.

A bag with a state estimate (``estimator/odometry``) also gets one line of the estimate's
error against ``starleth/base_state`` (velocity RMS, position drift per metre walked, yaw
drift) and the plot ``estimator_error.png`` (:mod:`.estimator_error`).

This module is the command line; the run is read by :mod:`.run`, summarised by
:mod:`.summary` and plotted by :mod:`.plots`.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

from ..common.console import run_console_script
from . import estimator_error
from .plots import PLOTS, feet_of, load_pyplot, save_figures
from .run import PROG, AnalysisError, Run, warn
from .sensor_noise import bag_noise, format_noise
from .summary import format_summary, jsonable, summarise


def _default_out(paths):
    first = os.path.abspath(paths[0]).rstrip(os.sep)
    stems = [os.path.splitext(os.path.basename(os.path.abspath(p).rstrip(os.sep)))[0]
             for p in paths]
    name = "_vs_".join(stems[:3]) + ("_etc" if len(stems) > 3 else "")
    return os.path.join(os.path.dirname(first), name[:100] + "_analysis")


def _labels(paths, labels):
    if labels:
        return list(labels)
    stems = [os.path.splitext(os.path.basename(os.path.abspath(p).rstrip(os.sep)))[0]
             for p in paths]
    if len(set(stems)) == len(stems):
        return stems
    return [os.path.relpath(p) for p in paths]


def build_parser():
    ap = argparse.ArgumentParser(
        prog=PROG, description="Plots and a summary of recorded StarlETH runs (MCAP bags); "
        "several bags are overlaid in the same plots.",
        epilog="Plots: " + ", ".join(f"{p}.png" for p in PLOTS) + " (and normal_force_FOOT.png "
        "when comparing). Exit status: 0 ok, 1 a bag cannot be analysed, 2 bad arguments.")
    ap.add_argument("bags", nargs="+", metavar="RUN.mcap",
                    help="MCAP bag files (or rosbag2 directories holding .mcap files)")
    ap.add_argument("--out", metavar="DIR",
                    help="directory for the PNGs (default: <first bag>_analysis beside it)")
    ap.add_argument("--label", nargs="+", metavar="NAME",
                    help="legend labels, one per bag (default: the file names)")
    ap.add_argument("--threshold", type=float, default=5.0, metavar="N",
                    help="contact: stance where the normal force exceeds this [N] (default 5)")
    ap.add_argument("--min-phase", type=float, default=0.02, metavar="S",
                    help="gait: stance/swing phases shorter than this are merged away [s] "
                         "(default 0.02; 0 keeps every sample)")
    ap.add_argument("--tmin", type=float, metavar="S",
                    help="analyse from this time [s] (time since the first message)")
    ap.add_argument("--tmax", type=float, metavar="S", help="analyse up to this time [s]")
    ap.add_argument("--foot", default=None, metavar="NAME",
                    help="foot of the single-foot normal force plot: a foot contact name of "
                         "the bag's robot, or its start if that names one foot (LF for "
                         "LF_foot; default: the first foot; drawn when comparing bags or "
                         "when given)")
    ap.add_argument("--twist-frame", choices=("auto", "child", "parent"), default="auto",
                    help="frame of the Odometry twist: child (REP 105, sim_node), parent "
                         "(world), auto: child unless child_frame_id is empty or the parent")
    ap.add_argument("--rtf-window", type=float, default=1.0, metavar="S",
                    help="real-time factor plot: window of sim time [s] (default 1)")
    ap.add_argument("--dpi", type=int, default=110, help="PNG resolution (default 110)")
    ap.add_argument("--json", metavar="FILE", help="also write the summary as JSON")
    ap.add_argument("--no-plots", action="store_true", help="summary only")
    ap.add_argument("--salvage", action="store_true",
                    help="read a truncated/damaged bag up to the damage instead of failing")
    return ap


def _chosen_foot(name, runs):
    """The foot of --foot among the runs' feet (a contact name, or the start of exactly
    one); the first foot without --foot; AnalysisError naming the feet otherwise."""
    feet = feet_of(runs)
    if name is None:
        return feet[0] if feet else None
    if name in feet:
        return name
    starts = [f for f in feet if f.startswith(name)]
    if len(starts) == 1:
        return starts[0]
    raise AnalysisError(f"--foot {name}: not a foot of the bag's robot (its feet: "
                        f"{', '.join(feet) or 'none recorded'})")


def run(argv=None) -> int:
    ap = build_parser()
    a = ap.parse_args(argv)
    _check_arguments(ap, a)
    t_start = time.perf_counter()
    runs = [_read_run(path, label, a.salvage, a.tmin, a.tmax)
            for path, label in zip(a.bags, _labels(a.bags, a.label), strict=True)]
    t_read = time.perf_counter() - t_start
    a.foot = _chosen_foot(a.foot, runs)
    empty = _empty_runs(runs, a.tmin, a.tmax)
    summaries = [summarise(r, a.threshold, a.min_phase, a.twist_frame) for r in runs]
    for r in empty:
        warn(f"{r.path}: no messages between --tmin and --tmax")
    for S, path in zip(summaries, a.bags, strict=True):
        print(format_summary(S))
        noise = bag_noise(path, a.salvage)      # measured against true (noisy sensors)
        if noise is not None:
            S["sensor_noise"] = noise
            print(format_noise(noise))
    written = {}
    if not a.no_plots:
        out = a.out or _default_out(a.bags)
        t0 = time.perf_counter()
        written = save_figures(runs, a, out)
        t_plot = time.perf_counter() - t0
        if written:
            print(f"plots ({t_plot:.1f} s) in {out}/: "
                  + ", ".join(os.path.basename(p) for p in written.values()))
        else:
            warn("nothing to plot")
    estimates, plots = estimator_error.report(      # bags with estimator/odometry
        runs, None if a.no_plots else a.out or _default_out(a.bags), a.dpi, load_pyplot,
        a.salvage)
    written.update(plots)
    print(f"read and decoded {sum(r.messages for r in runs)} messages in {t_read:.2f} s")
    if a.json:
        doc = {"runs": summaries, "plots": written, "estimator": estimates}
        d = os.path.dirname(os.path.abspath(a.json))
        os.makedirs(d, exist_ok=True)
        with open(a.json, "w") as f:
            json.dump(jsonable(doc), f, indent=1)
    return 0


def _check_arguments(ap, a):
    """The flags' values checked (argparse's error: usage and exit 2)."""
    if a.label and len(a.label) != len(a.bags):
        ap.error(f"--label: {len(a.label)} label(s) for {len(a.bags)} bag(s)")
    if a.threshold < 0 or not math.isfinite(a.threshold):
        ap.error("--threshold must be a finite number >= 0")
    if a.min_phase < 0 or a.rtf_window <= 0:
        ap.error("--min-phase must be >= 0 and --rtf-window > 0")
    if a.tmin is not None and a.tmax is not None and a.tmax <= a.tmin:
        ap.error("--tmax must be greater than --tmin")
    a.foot_given = a.foot is not None


def _read_run(path, label, salvage, tmin, tmax) -> Run:
    """One bag read, its missing topics said, its window applied; a bag without any of
    the StarlETH topics is an AnalysisError."""
    r = Run(path, label, salvage=salvage)
    if len(r.missing) == len(r.topics):
        topics = ", ".join(sorted(r.counts)) or "none"
        raise AnalysisError(f"{path}: none of the StarlETH topics ("
                            f"{', '.join(r.topic_names.values())}) has messages; the bag's "
                            f"topics: {topics}")
    relative = {name: rel for rel, name in r.topic_names.items()}
    for t in r.missing:
        kind, typ, lost = r.topics[relative[t]]
        have = "no messages on" if t in r.counts else "no topic"
        warn(f"{path}: {have} {t} ({typ}); skipping {lost}")
    r.apply_window(tmin, tmax)
    return r


def _empty_runs(runs, tmin, tmax) -> list:
    """The runs with no message in the window; all of them is an AnalysisError."""
    empty = [r for r in runs if not any(s["t"].size for s in r.series_by_key.values())]
    if len(empty) == len(runs) and tmin is None and tmax is None:
        raise AnalysisError(f"{', '.join(r.path for r in runs)}: none of the messages on the "
                            "StarlETH topics could be read (see the warnings above)")
    if len(empty) == len(runs):
        lo = "the start" if tmin is None else f"{tmin:g} s"
        hi = "the end" if tmax is None else f"{tmax:g} s"
        raise AnalysisError(f"no messages between {lo} and {hi} (--tmin/--tmax: time since "
                            "the first message of each bag)")
    return empty


def main(argv=None) -> int:
    """Console script: exit status 0, or 1 with a one-line message for a bag that cannot be
    analysed (no traceback), 2 for bad arguments."""
    return run_console_script(PROG, run, argv)


if __name__ == "__main__":
    sys.exit(main())
