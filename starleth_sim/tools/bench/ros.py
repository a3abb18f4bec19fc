"""Benchmark of the ROS 2 interface of ``sim_node`` (a script, not a test): its command
line, and the parent process that starts the sim child, runs the phases and prints the figures.

    python -m starleth_sim.tools.bench.ros                     # all phases (~90 s)
    python -m starleth_sim.tools.bench.ros --realtime-seconds 0 --lockstep-seconds 10

Two processes: this one (the controller side) and a child process that runs ``SimNode``
and, on the same executor, a bare rclpy "pong" node:

1. lockstep beside bare round trips, interleaved: sim_node runs in lockstep mode with
   real_time_factor 0, starting paused. In each of ``--rounds`` rounds this process first
   measures bare rclpy round trips (JointState ping -> pong, one in flight) for
   ``--bare-seconds / rounds``, then unpauses sim_node (``~/pause``) and acts as a trivial
   echo controller (joint PD hold of the first posture, answering every /joint_states
   with a /joint_commands stamped with the state's stamp) for
   ``--lockstep-seconds / rounds``, then pauses it again. Reported: control cycles per
   second beside the bare round-trip rate, and their ratio (goal >= 0.75) per round and
   over all rounds. Interleaving keeps a drift of the machine's load out of the ratio;
2. realtime: a fresh child runs sim_node in realtime mode (400 Hz) for
   ``--realtime-seconds`` with the same controller: the node's own tick-period error
   (p50/p99/max; goal p99 < 0.25 ms) and the inter-arrival jitter of /joint_states here.

The real loop (``--controller real``): the same interleaved rounds with
``starleth_controller``'s ``ControllerNode`` (stand 0.5 s of sim time, then trot at
0.3 m/s) in this process instead of the echo controller, so it receives the joint state,
base state and four foot wrenches of every stamp; ``--composed`` runs it in the sim's
process instead, on sim_node's executor (the composed mode), and this process only pings
and pauses. Both nodes time their part of every cycle (``SimNode.timing``,
``ControllerNode.timing``: CLOCK_MONOTONIC, one clock for both processes) and the cycle is
broken down into step, sim publish (the state topics a controller waits for; of which the
five before /joint_states), controller receive (until its sixth message is in), controller
compute, command back (publish to the
sim's callback), beside what runs in parallel (recording hand-over, prepare, /tf). The
cycle rate of a round is counted from sim_node's timestamps.

Options: ``--executor`` / ``--sim-executor`` (events | single_threaded) for the two sides
(the bare round trips use the same ones), ``--record PATH`` to record the lockstep phase,
``--realtime-priority N`` for sim_node's SCHED_FIFO option in the realtime phase.
The two processes use an isolated ROS_DOMAIN_ID (``--domain-id``, default from the pid).
``bench_floor`` measures the same loop without the nodes (its floor), in the same way.
Prints the figures and, with ``--json PATH``, writes them with the node's own summaries.
The figures depend on what else runs on the machine: run it on an idle one.

Its parts: the child process (``bench_ros_sim``), the controller side's phases
(``bench_ros_phases``), the controllers (``bench_controllers``), the bare round trips
(``bench_round_trips``) and the figures (``bench_loop_figures``).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile

import numpy as np

from starleth_interface.ros_helpers import make_executor

from ..common.child_process import stop_child
from ..common.discovery import keep_discovery_local, local_discovery_env
from .controllers import make_bench_controller, node_parameters
from .loop_figures import print_rates, real_loop_figures
from .ros_phases import controller_phase, lockstep_beside_bare
from .ros_sim import child_main
from .round_trips import CHILD_LOGS


# -----------------------------------------------------------------------------------------
# the child process
# -----------------------------------------------------------------------------------------
def _spawn(args, mode, rtf, pong, log, record="", timing=""):
    cmd = [sys.executable, "-m", "starleth_sim.tools.bench.ros", "--child", "--domain-id",
           str(args.domain_id), "--mode", mode, "--rtf", str(rtf), "--sim-executor",
           args.sim_executor]
    if timing:
        cmd += ["--timing", timing]
    if mode == "lockstep":
        for item in getattr(args, "sim_param", None) or ():
            cmd += ["--sim-param", item]
    if getattr(args, "composed", False) and mode == "lockstep":
        cmd.append("--composed")
        for item in args.controller_param or ():
            cmd += ["--controller-param", item]
    if pong:
        cmd.append("--pong")
    if record:
        cmd += ["--record", record]
    if mode == "realtime" and args.realtime_priority:
        cmd += ["--realtime-priority", str(args.realtime_priority)]
    env = dict(local_discovery_env(), ROS_DOMAIN_ID=str(args.domain_id), PYTHONUNBUFFERED="1")
    pre = _pin_to_one_cpu if getattr(args, "pin", False) else None
    CHILD_LOGS[:] = [log.name]     # (its compile lines restart spin_until's time-outs)
    return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env,
                            preexec_fn=pre)


def _pin_to_one_cpu():
    """(in the child before exec) the child and every thread it starts on one CPU"""
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})


def _stop(proc, log_path, timeout=20):
    stop_child(proc, timeout)
    with open(log_path) as f:
        text = f.read()
    m = re.search(r"BENCH_SUMMARY (\{.*\})", text)
    return (json.loads(m.group(1)) if m else None), text


# -----------------------------------------------------------------------------------------
# parent
# -----------------------------------------------------------------------------------------
def parent_main(args):
    """The benchmark's parent: this process is the controller side; sim_node runs as a
    child, first in lockstep (beside a bare loop), then in realtime."""
    import rclpy
    from rclpy.node import Node
    results = {"domain_id": args.domain_id, "controller_executor": args.executor,
               "sim_executor": args.sim_executor, "cpus": os.cpu_count(), "pin": args.pin}
    if args.pin:     # this (controller) process on the last CPU, the sim on the first
        os.sched_setaffinity(0, {max(os.sched_getaffinity(0))})
    ctx = rclpy.Context()
    rclpy.init(args=[], context=ctx, domain_id=args.domain_id)
    node = Node("bench_controller", context=ctx)
    ex = make_executor(args.executor, ctx)[0]
    ex.add_node(node)
    tmp = tempfile.mkdtemp(prefix="starleth_bench_")
    try:
        if args.lockstep_seconds > 0:
            _lockstep_phase(args, ctx, node, ex, tmp, results)
        if args.realtime_seconds > 0:
            _realtime_phase(args, node, ex, tmp, results)
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        shutil.rmtree(tmp, ignore_errors=True)     # the child's logs and timing arrays
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    return results


def _run_child(args, mode, rtf, lockstep, tmp, run, *spawn_args):
    """sim_node as a child in `mode` while `run()` measures; its log printed if `run`
    fails. Returns (run's result, the node's summary)."""
    log_path = os.path.join(tmp, f"{mode}.log")
    with open(log_path, "w") as log:
        proc = _spawn(args, mode, rtf, lockstep, log, *spawn_args)
        try:
            result = run(proc)
        except Exception:
            print(_stop(proc, log_path)[1][-3000:], file=sys.stderr)
            raise
        finally:
            summary, _ = _stop(proc, log_path)
    return result, summary


def _lockstep_phase(args, ctx, node, ex, tmp, results):
    """Lockstep control cycles beside the bare loop, with an echo, real or composed
    controller; with the real one, the per-cycle breakdown from both sides' timings."""
    real = args.controller == "real"
    kind = ("composed" if args.composed else "real") if real else "echo"
    timing = os.path.join(tmp, "timing.npz") if real else ""
    ctl, windows = None, []
    if kind == "real":
        ctl = make_bench_controller(ctx, timing=True,
                                    params=node_parameters(args.controller_param))
        ex.add_node(ctl)
    (bare, lock), summary = _run_child(
        args, "lockstep", 0.0, True, tmp,
        lambda proc: lockstep_beside_bare(node, ex, args.lockstep_seconds, args.bare_seconds,
                                          args.rounds, controller=kind, windows=windows,
                                          ctl=ctl, sim_pid=proc.pid),
        args.record, timing)
    if real:
        lock = _real_controller_figures(ex, ctl, timing, windows, bare, results)
    results["controller"] = kind
    results["bare"], results["lockstep"] = bare, lock
    lock["node_summary"] = summary
    print_rates(bare, lock, "lockstep control cycles",
                f"; goal >= {0.4 if real else 0.75}), sim/wall "
                f"{lock['sim_time_per_wall']:.2f} [{kind} controller"
                f"{', recording' if args.record else ''}]")
    if real:
        b = lock["breakdown_median_ms"]
        print("per cycle (medians, ms; " + str(lock["breakdown_cycles"]) + " cycles): "
              + ", ".join(f"{k} {v:.3f}" for k, v in b.items() if v is not None), flush=True)
        if "cpu_per_cycle_ms" in lock:
            print("CPU time per cycle (ms, all threads): " + ", ".join(
                f"{k} {v:.3f}" for k, v in lock["cpu_per_cycle_ms"].items()), flush=True)


def _real_controller_figures(ex, ctl, timing, windows, bare, results):
    """The lockstep figures of a real controller from the sim's and the controller's
    timing rows (in this process, or the composed child's file); printed per round."""
    tm = np.load(timing) if os.path.exists(timing) else {"sim_stamp": None, "sim_t": None}
    if ctl is not None:
        tmg = getattr(ctl, "timing", None)
        ct, cs = ((tmg.t[:tmg.n], tmg.stamp[:tmg.n]) if tmg is not None
                  else (np.zeros((0, 4)), np.zeros(0, np.int64)))
        results["controller_summary"] = ctl.summary()
        ex.remove_node(ctl)
        ctl.destroy_node()
    else:
        ct, cs = tm["ctl_t"], tm["ctl_stamp"]
    lock = real_loop_figures(windows, tm["sim_stamp"], tm["sim_t"], cs, ct, bare)
    for r, p in enumerate(lock["rounds"]):
        print(f"  round {r + 1}: lockstep {p['lockstep_cycles_per_s']:.0f}/s, "
              f"ratio {p['ratio']:.2f}", flush=True)
    return lock


def _realtime_phase(args, node, ex, tmp, results):
    """sim_node in realtime: its tick period error and the /joint_states arrivals here."""
    rr, summary = _run_child(args, "realtime", 1.0, False, tmp,
                             lambda _proc: controller_phase(node, ex, args.realtime_seconds))
    results["realtime"] = rr
    rr["node_summary"] = summary
    if summary:
        print(f"realtime: node tick period error p50 "
              f"{summary.get('period_error_p50_ms', float('nan')):.4f} ms, p99 "
              f"{summary.get('period_error_p99_ms', float('nan')):.4f} ms (goal < 0.25), "
              f"max {summary.get('period_error_max_ms', float('nan')):.3f} ms, overruns "
              f"{summary.get('overruns')}", flush=True)
    print(f"realtime: /joint_states received {rr['states_per_s']:.1f}/s, "
          f"inter-arrival error p99 {rr['interarrival_error_p99_ms']:.3f} ms", flush=True)


def main(argv=None):
    keep_discovery_local()      # this process and the sim child: this host only
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--bare-seconds", type=float, default=10.0,
                   help="bare round trips, in all rounds together")
    p.add_argument("--lockstep-seconds", type=float, default=10.0,
                   help="lockstep cycles, in all rounds together")
    p.add_argument("--rounds", type=int, default=10,
                   help="interleaved bare/lockstep rounds")
    p.add_argument("--realtime-seconds", type=float, default=60.0)
    p.add_argument("--executor", default=None, choices=["events", "single_threaded"],
                   help="executor of this (controller) process (default: single_threaded with "
                        "the echo controller, events with the real one, as controller_node)")
    p.add_argument("--controller", default="echo", choices=["echo", "real"],
                   help="lockstep phase: the PD echo controller, or starleth_controller's "
                        "controller_node (trotting)")
    p.add_argument("--pin", action="store_true",
                   help="pin the sim process to the first CPU and this one to the last (a "
                        "woken subscriber then cannot preempt its publisher)")
    p.add_argument("--composed", action="store_true",
                   help="with --controller real: controller_node in sim_node's process, on "
                        "its executor")
    p.add_argument("--controller-param", action="append", default=[], metavar="NAME:=VALUE",
                   help="with --controller real: a parameter of controller_node (repeatable), "
                        "e.g. state_reliability:=best_effort")
    p.add_argument("--sim-param", action="append", default=[], metavar="NAME:=VALUE",
                   help="lockstep phase: a parameter of sim_node (repeatable), e.g. "
                        "cpu_scheduling:=batch")
    p.add_argument("--sim-executor", default="events", choices=["events", "single_threaded"],
                   help="executor of the sim process (pong and sim_node)")
    p.add_argument("--domain-id", type=int, default=os.getpid() % 50 + 30)
    p.add_argument("--json", default="")
    p.add_argument("--record", default="", help="lockstep phase: record to this MCAP file")
    p.add_argument("--realtime-priority", type=int, default=0,
                   help="realtime phase: sim_node's realtime_priority (SCHED_FIFO)")
    # child options
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--pong", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--mode", default="lockstep", help=argparse.SUPPRESS)
    p.add_argument("--rtf", type=float, default=0.0, help=argparse.SUPPRESS)
    p.add_argument("--timing", default="", help=argparse.SUPPRESS)
    p.add_argument("--pong-only", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.executor is None:
        args.executor = "events" if args.controller == "real" else "single_threaded"
    if args.composed and args.controller != "real" and not args.child:
        p.error("--composed needs --controller real")
    if args.child:
        child_main(args)
        return 0
    parent_main(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
