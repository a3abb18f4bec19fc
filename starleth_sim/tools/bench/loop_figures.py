"""The figures of the loop benchmarks (``bench_ros``, ``bench_floor``): the bare round
trips' rate and percentiles, a loop's rate and its ratio to them per round and over all
rounds, the real loop's per-cycle breakdown from the two nodes' timestamps, the CPU time of
the two processes, and the lines that print them.
"""
from __future__ import annotations

import os

import numpy as np

from starleth_interface.cycle_times import SIM_CYCLE_FIELDS


def bare_figures(rtts):
    """Rate, median and p99 of the bare round trips (seconds each)."""
    rtts = np.asarray(rtts)
    return {"round_trips_per_s": len(rtts) / float(rtts.sum()),
            "rtt_median_ms": float(np.median(rtts) * 1e3),
            "rtt_p99_ms": float(np.percentile(rtts, 99) * 1e3), "n": int(len(rtts))}


def lockstep_figures(per, n_total, t_total, stamps_bad, bare):
    """The lockstep figures of all rounds: rate, its ratio to the bare round trips."""
    ratios = [p["ratio"] for p in per]
    return {"states": n_total, "wall_s": t_total, "states_per_s": n_total / t_total,
            "sim_time_per_wall": n_total * 0.0025 / t_total,
            "stamp_steps_not_one_period": stamps_bad, "rounds": per,
            "ratio_to_bare": (n_total / t_total) / bare["round_trips_per_s"],
            "ratio_median_of_rounds": float(np.median(ratios)),
            "ratio_min_of_rounds": float(np.min(ratios))}


def print_rates(bare, lock, what, tail):
    """Prints the bare round trips (bare_figures) and, beside them, the loop's cycles
    (lockstep_figures) as `what`, its ratio to the bare rate over all rounds and per round,
    then `tail`."""
    print(f"bare rclpy round trips: {bare['round_trips_per_s']:.0f}/s, median "
          f"{bare['rtt_median_ms']:.3f} ms", flush=True)
    print(f"{what}: {lock['states_per_s']:.0f}/s ({lock['ratio_to_bare']:.2f}x bare; rounds: "
          f"median {lock['ratio_median_of_rounds']:.2f}x, min "
          f"{lock['ratio_min_of_rounds']:.2f}x{tail}", flush=True)


def task_cpu_ns(pid) -> int:
    """CPU time [ns] of every thread of process `pid` (/proc/PID/task/*/schedstat; 0 where
    there is no /proc)."""
    total = 0
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return 0
    for t in tasks:
        try:
            with open(f"/proc/{pid}/task/{t}/schedstat") as f:
                total += int(f.read().split()[0])
        except (OSError, ValueError, IndexError):
            pass
    return total


def process_cpu_ns(sim_pid) -> dict:
    """CPU time [ns] so far of this process ("controller side"), the sim process and its
    child processes (the recording's writer process)."""
    out = {"controller_side": task_cpu_ns(os.getpid())}
    if sim_pid:
        out["sim"] = task_cpu_ns(sim_pid)
        try:
            with open(f"/proc/{sim_pid}/task/{sim_pid}/children") as f:
                kids = [int(x) for x in f.read().split()]
        except (OSError, ValueError):
            kids = []
        out["sim_children"] = sum(task_cpu_ns(k) for k in kids)
    return out


def real_loop_figures(windows, sim_stamp, sim_t, ctl_stamp, ctl_t, bare):
    """Rates per round (commands the controller sent in the round's window, or states
    whose topics went out in it) and the per-cycle breakdown (medians over all rounds, ms)
    from the two nodes' timestamps (none if the nodes have no timers)."""
    F = {f: i for i, f in enumerate(SIM_CYCLE_FIELDS)}
    if sim_t is None or not len(sim_t):
        sim_t, sim_stamp = np.zeros((0, max(F.values()) + 1)), np.zeros(0, np.int64)
    out_t = sim_t[:, F["state_out"]]
    per, n_total, t_total, bad = [], 0, 0.0, 0
    cpu = {}
    for t0, t1, bare_rate, n_cmd, *rest in windows:
        sel = (out_t >= t0) & (out_t <= t1)
        n = int(sel.sum()) if n_cmd is None else n_cmd
        bad += int(np.sum(np.diff(sim_stamp[sel]) != 2_500_000))
        rate = n / (t1 - t0)
        per.append({"bare_round_trips_per_s": bare_rate, "lockstep_cycles_per_s": rate,
                    "ratio": rate / bare_rate})
        n_total += n
        t_total += t1 - t0
        for k, v in (rest[0] if rest else {}).items():
            cpu[k] = cpu.get(k, 0) + v
    lock = lockstep_figures(per, n_total, t_total, bad, bare)
    # CPU time per cycle of each process (all its threads), and all together
    if cpu and n_total:
        lock["cpu_per_cycle_ms"] = {**{k: v * 1e-6 / n_total for k, v in cpu.items()},
                                    "all": sum(cpu.values()) * 1e-6 / n_total}
    # breakdown: state k (sim row k), the controller's answer to k (ctl row), the command
    # that arrives for k (sim row k+1: command_in), all inside a round
    in_round = np.zeros(len(sim_stamp), bool)
    for t0, t1, *_ in windows:
        in_round |= (out_t >= t0) & (out_t <= t1)
    sim_row = {int(s): i for i, s in enumerate(sim_stamp)}
    ctl_row = {int(s): i for i, s in enumerate(ctl_stamp)}
    seg = {k: [] for k in ("step", "sim_publish", "controller_first_in",
                           "controller_receive", "controller_compute", "command_back",
                           "of_which_command_publish", "cycle", "public_topics_parallel",
                           "prepare_record_visualisation_parallel")}
    for i, st in enumerate(sim_stamp):
        j, c = sim_row.get(int(st) + 2_500_000), ctl_row.get(int(st))
        if not in_round[i] or j is None or c is None or not in_round[j]:
            continue
        a, b, cr = sim_t[i], sim_t[j], ctl_t[c]     # cr: first in, complete, computed, sent
        seg["step"].append(a[F["stepped"]] - a[F["command_in"]])
        seg["sim_publish"].append(a[F["state_out"]] - a[F["stepped"]])
        seg["controller_first_in"].append(cr[0] - a[F["stepped"]])
        seg["controller_receive"].append(cr[1] - a[F["state_out"]])
        seg["controller_compute"].append(cr[2] - cr[1])
        seg["command_back"].append(b[F["command_in"]] - cr[2])
        seg["of_which_command_publish"].append(cr[3] - cr[2])
        seg["cycle"].append(b[F["command_in"]] - a[F["command_in"]])
        seg["public_topics_parallel"].append(a[F["public_out"]] - a[F["state_out"]])
        seg["prepare_record_visualisation_parallel"].append(a[F["done"]] - a[F["public_out"]])
    lock["breakdown_median_ms"] = {k: float(np.median(v) * 1e3) if v else None
                                   for k, v in seg.items()}
    lock["breakdown_cycles"] = len(seg["cycle"])
    return lock
