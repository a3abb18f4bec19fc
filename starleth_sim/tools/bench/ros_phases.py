"""The controller side of the ROS benchmark's phases, in the parent process against the
sim child: the interleaved rounds of bare round trips and lockstep cycles (sim_node paused
and unpaused through its ~/pause service between them) with the echo controller or the real
one, and the realtime phase's reception of /joint_states.
"""
from __future__ import annotations

import time

import numpy as np

from starleth_interface.ros_helpers import service_qos

from .controllers import EchoController
from .loop_figures import bare_figures, lockstep_figures, process_cpu_ns
from .round_trips import PingPong, spin_until


def _pause_client(node, ex):
    """sim_node's ~/pause service (std_srvs/SetBool), once it is up (2 min at most)."""
    from std_srvs.srv import SetBool
    pause = node.create_client(SetBool, "/sim_node/pause", qos_profile=service_qos())
    if not spin_until(ex, pause.service_is_ready, 120):
        raise RuntimeError("bench: sim_node's ~/pause service did not appear")
    return pause


def _set_paused(ex, client, paused, timeout=10.0):
    from std_srvs.srv import SetBool
    fut = client.call_async(SetBool.Request(data=paused))
    if not spin_until(ex, fut.done, timeout) or not fut.result().success:
        raise RuntimeError(f"bench: ~/pause({paused}) failed")


def lockstep_beside_bare(node, ex, lockstep_seconds, bare_seconds, rounds, warmup=0.2,
                         controller="echo", windows=None, ctl=None, sim_pid=None):
    """The interleaved rounds of phase 1 (sim_node starts paused): per round, bare round
    trips, then lockstep cycles with the echo controller (controller="echo"), the real
    ControllerNode `ctl` in this process ("real", a node added to `ex`) or in the sim's
    process ("composed"): `windows` gets (t_start, t_end, bare rate, commands sent by
    `ctl` or None) per round; in the composed mode the cycles are counted afterwards from
    the sim's timestamps."""
    if controller != "echo":
        return _rounds_real(node, ex, lockstep_seconds, bare_seconds, rounds, warmup, windows,
                            ctl, sim_pid)
    ctl = EchoController(node)
    pause = _pause_client(node, ex)
    pp = PingPong(node, ex)
    per = []
    all_rtts = []
    n_total, t_total, stamps_bad = 0, 0.0, 0
    for r in range(rounds):
        bare_rate, rtts = pp.measure(bare_seconds / rounds)
        all_rtts += rtts
        _set_paused(ex, pause, False)
        t_start = time.perf_counter() + warmup
        t_end = t_start + lockstep_seconds / rounds
        while time.perf_counter() < t_end:
            ex.spin_once(timeout_sec=0.05)
        _set_paused(ex, pause, True)
        rt, st = np.array(ctl.recv_times), np.array(ctl.stamps)
        sel = (rt >= t_start) & (rt <= t_end)
        n = int(sel.sum())
        stamps_bad += int(np.sum(np.diff(st[sel]) != 2_500_000))
        rate = n / (t_end - t_start)
        per.append({"bare_round_trips_per_s": bare_rate, "lockstep_cycles_per_s": rate,
                    "ratio": rate / bare_rate})
        n_total += n
        t_total += t_end - t_start
        print(f"  round {r + 1}/{rounds}: bare {bare_rate:.0f}/s, lockstep {rate:.0f}/s, "
              f"ratio {rate / bare_rate:.2f}", flush=True)
    pp.close()
    ctl.close()
    bare = bare_figures(all_rtts)
    return bare, lockstep_figures(per, n_total, t_total, stamps_bad, bare)


#: commands the real controller sends in a warm-up run before the measured rounds: its
#: first cycles load its kernels and fill its state (a first round measured without it
#: counted none in its window, and its pause request once timed out)
WARMUP_COMMANDS = 200


def _warm_up_loop(ex, pause, ctl, timeout=60.0):
    """Runs the lockstep loop until the controller `ctl` (in this process) has sent
    WARMUP_COMMANDS commands, then pauses the sim again; in the composed mode (ctl None)
    for one second."""
    _set_paused(ex, pause, False)
    if ctl is None:
        spin_until(ex, lambda: False, 1.0)
    else:
        n0 = ctl.counters["commands"]
        if not spin_until(ex, lambda: ctl.counters["commands"] - n0 >= WARMUP_COMMANDS,
                          timeout):
            print(f"  warm-up: only {ctl.counters['commands'] - n0} commands in "
                  f"{timeout:.0f} s", flush=True)
    # (the sim's process answers once its first cycles are done: in the composed mode the
    # controller's kernels load there then, which once took over 10 s on a loaded machine)
    _set_paused(ex, pause, True, timeout)


def _rounds_real(node, ex, lockstep_seconds, bare_seconds, rounds, warmup, windows,
                 ctl=None, sim_pid=None):
    pause = _pause_client(node, ex)
    _warm_up_loop(ex, pause, ctl)
    pp = PingPong(node, ex)
    all_rtts = []
    for r in range(rounds):
        bare_rate, rtts = pp.measure(bare_seconds / rounds)
        all_rtts += rtts
        _set_paused(ex, pause, False)
        t_start = time.perf_counter() + warmup
        t_end = t_start + lockstep_seconds / rounds
        n0 = cpu0 = None
        while time.perf_counter() < t_end:
            ex.spin_once(timeout_sec=0.05)
            if cpu0 is None and time.perf_counter() >= t_start:
                cpu0, t_start = process_cpu_ns(sim_pid), time.perf_counter()
                if ctl is not None:
                    n0 = ctl.counters["commands"]
        n = ctl.counters["commands"] - n0 if ctl is not None else None
        t_end = time.perf_counter()
        cpu1 = process_cpu_ns(sim_pid)
        _set_paused(ex, pause, True)
        windows.append((t_start, t_end, bare_rate, n,
                        {k: v - cpu0.get(k, 0) for k, v in cpu1.items()}))
        print(f"  round {r + 1}/{rounds}: bare {bare_rate:.0f}/s", flush=True)
    pp.close()
    return bare_figures(all_rtts), None


def controller_phase(node, ex, seconds, warmup=1.0):
    """The realtime phase: the echo controller answers /joint_states for `seconds` (after
    `warmup`); the states' rate, sim time per wall time and inter-arrival jitter here."""
    ctl = EchoController(node)
    if not spin_until(ex, lambda: len(ctl.stamps) > 0, 120):
        raise RuntimeError("bench: no /joint_states from sim_node")
    t_start = time.perf_counter() + warmup
    t_end = t_start + seconds
    while time.perf_counter() < t_end:
        ex.spin_once(timeout_sec=0.05)
    st = np.array(ctl.stamps)
    rt = np.array(ctl.recv_times)
    sel = (rt >= t_start) & (rt <= t_end)
    n = int(sel.sum())
    ctl.close()
    iv = np.diff(rt[sel])
    ds = np.diff(st[sel])
    return {"states": n, "wall_s": seconds, "states_per_s": n / seconds,
            "sim_time_per_wall":
                float((st[sel][-1] - st[sel][0]) * 1e-9 / seconds) if n > 1 else 0.0,
            "stamp_steps_not_one_period": int(np.sum(ds != 2_500_000)) if n > 1 else 0,
            "interarrival_median_ms": float(np.median(iv) * 1e3) if n > 1 else None,
            "interarrival_p99_ms": float(np.percentile(iv, 99) * 1e3) if n > 1 else None,
            "interarrival_error_p99_ms": float(np.percentile(np.abs(iv - 0.0025), 99) * 1e3)
            if n > 1 else None}
