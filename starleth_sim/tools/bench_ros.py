"""Benchmark of the ROS 2 interface of ``sim_node`` (a script, not a test).

    python -m starleth_sim.tools.bench_ros                     # all phases (~90 s)
    python -m starleth_sim.tools.bench_ros --realtime-seconds 0 --lockstep-seconds 10

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
"""
from __future__ import annotations

import argparse
import array
import json
import os
import re
import signal
import subprocess
import sys
import shutil
import tempfile
import time

import numpy as np

from starleth_interface.compile_notice import Deadline
from starleth_interface.cycle_times import CONTROLLER_CYCLE_FIELDS, SIM_CYCLE_FIELDS, CycleTimes

from ..ros.discovery import keep_discovery_local, local_discovery_env

PING, PONG = "/starleth_bench/ping", "/starleth_bench/pong"


# -----------------------------------------------------------------------------------------
# controller side helpers (also used by the integration tests)
# -----------------------------------------------------------------------------------------
class EchoController:
    """Answers every /joint_states with a /joint_commands JointState stamped with the state's
    stamp: PD hold of the first posture it sees (or of `q_ref`). Counts states and stamps.
    The default gains are the posture hold's (`posture.DEFAULT_KP/KD` per joint type), which
    stay stable with a leg in the air (a stiffer knee damping makes a lifted shank flail under
    the 400 Hz zero-order hold)."""

    def __init__(self, node, kp=None, kd=None, q_ref=None, reply=True,
                 topic="joint_commands"):
        from sensor_msgs.msg import JointState
        from rclpy.qos import QoSProfile
        from ..physics.posture import DEFAULT_KD, DEFAULT_KP
        self.node = node
        self.kp = np.tile(DEFAULT_KP, 4) if kp is None else kp
        self.kd = np.tile(DEFAULT_KD, 4) if kd is None else kd
        self.q_ref = None if q_ref is None else np.asarray(q_ref, dtype=float)
        self.reply = reply
        self.stamps = []
        self.recv_times = []
        self._JointState = JointState
        self.pub = node.create_publisher(JointState, topic, QoSProfile(depth=10))
        self.sub = node.create_subscription(JointState, "joint_states", self._on_state,
                                            QoSProfile(depth=10))
        self._cmd = None
        self.closed = False

    def close(self):
        """Stop answering and destroy the subscription and publisher (events already queued
        for them are ignored)."""
        self.closed = True
        self.reply = False
        self.node.destroy_subscription(self.sub)
        self.node.destroy_publisher(self.pub)

    def _on_state(self, msg):
        if self.closed:
            return
        t = time.perf_counter()
        st = msg.header.stamp
        self.stamps.append(st.sec * 1_000_000_000 + st.nanosec)
        self.recv_times.append(t)
        q = np.asarray(msg.position)
        if self.q_ref is None:
            self.q_ref = q.copy()
        if not self.reply:
            return
        tau = self.kp * (self.q_ref - q) - self.kd * np.asarray(msg.velocity)
        cmd = self._cmd
        if cmd is None:
            cmd = self._cmd = self._JointState()
            cmd.name = msg.name
        cmd.header.stamp = msg.header.stamp
        cmd.effort = array.array("d", tau.tobytes())
        self.pub.publish(cmd)


def _make_executor(kind, context):
    from starleth_interface.ros_helpers import make_executor
    return make_executor(kind, context)[0]


# -----------------------------------------------------------------------------------------
# child process: sim_node (and the pong node on the same executor)
# -----------------------------------------------------------------------------------------
def child_main(args):
    import rclpy
    from rclpy.node import Node
    from rclpy.qos import QoSProfile
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import JointState
    from starleth_sim.ros.sim_node import SimNode

    rclpy.init(args=[], domain_id=args.domain_id,
               signal_handler_options=SignalHandlerOptions.NO)
    stop = {"flag": False}
    signal.signal(signal.SIGINT, lambda *a: stop.__setitem__("flag", True))
    signal.signal(signal.SIGTERM, lambda *a: stop.__setitem__("flag", True))
    if args.pong_only:     # measure_bare_round_trips: only the pong node
        pong = Node("bench_pong", context=None)
        pong_pub = pong.create_publisher(JointState, PONG, QoSProfile(depth=10))
        pong.create_subscription(JointState, PING, pong_pub.publish, QoSProfile(depth=10))
        ex = _make_executor(args.sim_executor, pong.context)
        ex.add_node(pong)
        while not stop["flag"]:
            ex.spin_once(timeout_sec=0.1)
        pong.destroy_node()
        rclpy.try_shutdown()
        return
    overrides = {"mode": args.mode, "real_time_factor": args.rtf, "executor": args.sim_executor,
                 "realtime_priority": args.realtime_priority}
    if args.record:
        overrides["record"] = args.record
    if args.mode == "lockstep":
        overrides.update(_controller_params(args.sim_param))
    if args.pong:
        overrides["start_paused"] = True    # the parent unpauses it for each lockstep round
    sim = SimNode(parameter_overrides=overrides)
    ex = _make_executor(args.sim_executor, sim.context)
    ex.add_node(sim.node)
    ctl = None
    if args.timing:
        sim.timing = CycleTimes(SIM_CYCLE_FIELDS)
    if args.composed:   # the controller on sim_node's executor, in this process
        ctl = make_bench_controller(sim.context, timing=bool(args.timing),
                                    params=_controller_params(args.controller_param))
        ex.add_node(ctl)
    if args.pong:   # bare round trips, served by the same executor as sim_node
        pong = Node("bench_pong", context=sim.context)
        pong_pub = pong.create_publisher(JointState, PONG, QoSProfile(depth=10))
        pong.create_subscription(JointState, PING, pong_pub.publish, QoSProfile(depth=10))
        ex.add_node(pong)
    signal.signal(signal.SIGINT, sim.request_stop)
    signal.signal(signal.SIGTERM, sim.request_stop)
    if stop["flag"]:
        sim.request_stop()
    try:
        sim.run(ex)
    finally:
        summary = sim.close()
        if args.timing and getattr(sim, "timing", None) is not None:
            arrays = {"sim_stamp": sim.timing.stamp[:sim.timing.n],
                      "sim_t": sim.timing.t[:sim.timing.n]}
            if ctl is not None:
                arrays.update(ctl_stamp=ctl.timing.stamp[:ctl.timing.n],
                              ctl_t=ctl.timing.t[:ctl.timing.n])
            np.savez(args.timing, **arrays)
        if ctl is not None:
            summary["controller"] = ctl.summary()
            ctl.destroy_node()
        print("BENCH_SUMMARY " + json.dumps(summary), flush=True)
        sim.node.destroy_node()
        rclpy.try_shutdown()


# -----------------------------------------------------------------------------------------
# parent
# -----------------------------------------------------------------------------------------
def _controller_params(items):
    """{name: value} of the ``--controller-param`` / ``--sim-param NAME:=VALUE`` options
    (values read as YAML, as ROS reads -p values)."""
    import yaml
    out = {}
    for item in items or ():
        name, sep, value = item.partition(":=")
        if not sep or not name:
            raise SystemExit(f"bench_ros: parameter {item!r}: expected NAME:=VALUE")
        out[name] = yaml.safe_load(value)
    return out


#: the real controller's run: stand, then trot forward at TROT_SPEED [m/s] from TROT_AT [s]
#: of sim time
TROT_AT, TROT_SPEED = 0.5, 0.3


def make_bench_controller(context, timing=False, trot_at=TROT_AT, speed=TROT_SPEED,
                          params=None):
    """starleth_controller's ControllerNode as the benchmark's real controller: stands, and
    trots at `speed` from sim time `trot_at` on (checked on every command it sends);
    `params`: more parameter overrides of the node."""
    from rclpy.parameter import Parameter
    from starleth_controller import controller_node
    ctl = controller_node.ControllerNode(context=context, parameter_overrides={
        **(params or {}), "mode": "stand"})
    ctl._vel = (speed, 0.0, 0.0)
    if timing:
        ctl.timing = CycleTimes(CONTROLLER_CYCLE_FIELDS)
    publish = ctl._publish

    def publish_and_switch(stamp, effort):
        publish(stamp, effort)
        sec, nsec = (stamp.sec, stamp.nanosec) if hasattr(stamp, "sec") else stamp
        if ctl._mode == "stand" and sec + nsec * 1e-9 >= trot_at:
            ctl.set_parameters([Parameter("mode", value="trot")])
    ctl._publish = publish_and_switch
    return ctl


def _spawn(args, mode, rtf, pong, log, record="", timing=""):
    cmd = [sys.executable, "-m", "starleth_sim.tools.bench_ros", "--child", "--domain-id",
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
    _CHILD_LOGS[:] = [log.name]     # (its compile lines restart _wait's time-outs)
    return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env,
                            preexec_fn=pre)


def _pin_to_one_cpu():
    """(in the child before exec) the child and every thread it starts on one CPU"""
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})


def _stop(proc, log_path, timeout=20):
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    with open(log_path) as f:
        text = f.read()
    m = re.search(r"BENCH_SUMMARY (\{.*\})", text)
    return (json.loads(m.group(1)) if m else None), text


#: the log of the child process running now (_spawn)
_CHILD_LOGS: list = []


def _wait(ex, cond, timeout):
    """Spins until cond() (True) or `timeout` s of silence (False): the child's compile
    lines (CompileNotice) restart the time-out."""
    deadline = Deadline(timeout, _CHILD_LOGS)
    while not cond():
        if deadline.expired():
            return False
        ex.spin_once(timeout_sec=0.01)
    return True


class PingPong:
    """Bare rclpy round trips with the child's pong node: a JointState (12 names, 3 x 12
    values, like /joint_states) goes out, the next is sent when its echo is back."""

    def __init__(self, node, ex, startup=60.0):
        from sensor_msgs.msg import JointState
        from rclpy.qos import QoSProfile
        self.node, self.ex = node, ex
        self.got = 0
        self.pub = node.create_publisher(JointState, PING, QoSProfile(depth=10))
        self.sub = node.create_subscription(JointState, PONG, self._on_pong, QoSProfile(depth=10))
        msg = self.msg = JointState()
        msg.name = [f"j{i}" for i in range(12)]
        msg.position = [0.1] * 12
        msg.velocity = [0.0] * 12
        msg.effort = [0.0] * 12
        if not _wait(ex, lambda: self.pub.get_subscription_count() > 0 and
                     self.sub.get_publisher_count() > 0, startup):
            raise RuntimeError("bench: the pong node did not appear")
        for _ in range(50):     # warm-up: the first messages after matching can be slow
            want = self.got + 1
            self.pub.publish(msg)
            _wait(ex, lambda: self.got >= want, 2.0)

    def _on_pong(self, msg):
        self.got += 1

    def measure(self, seconds):
        rtts = []
        t0 = time.perf_counter()
        t_end = t0 + seconds
        while time.perf_counter() < t_end:
            want = self.got + 1
            t = time.perf_counter()
            self.msg.header.stamp.nanosec = len(rtts) % 1_000_000_000
            self.pub.publish(self.msg)
            while self.got < want:
                self.ex.spin_once(timeout_sec=1.0)
                if time.perf_counter() - t > 2.0:
                    break
            rtts.append(time.perf_counter() - t)
        return len(rtts) / (time.perf_counter() - t0), rtts

    def close(self):
        self.node.destroy_publisher(self.pub)
        self.node.destroy_subscription(self.sub)


def measure_bare_round_trips(domain_id, seconds=2.0, executor="events", startup=60.0):
    """Bare rclpy JointState round trips per second between this process and a child
    running only the pong node (the reference the real loop is compared with); also
    returns the median round trip [s]. Used by starleth-demo right before its run."""
    import rclpy
    from rclpy.node import Node
    keep_discovery_local()
    cmd = [sys.executable, "-m", "starleth_sim.tools.bench_ros", "--child", "--pong-only",
           "--domain-id", str(domain_id), "--sim-executor", executor]
    env = dict(local_discovery_env(), ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, env=env)
    ctx = rclpy.Context()
    rclpy.init(args=[], context=ctx, domain_id=domain_id)
    node = Node("bench_ping", context=ctx)
    try:
        ex = _make_executor(executor, ctx)
        ex.add_node(node)
        pp = PingPong(node, ex, startup)
        rate, rtts = pp.measure(seconds)
        pp.close()
        return rate, float(np.median(rtts))
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _set_paused(node, ex, client, paused, timeout=10.0):
    from std_srvs.srv import SetBool
    fut = client.call_async(SetBool.Request(data=paused))
    if not _wait(ex, fut.done, timeout) or not fut.result().success:
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
        _set_paused(node, ex, pause, False)
        t_start = time.perf_counter() + warmup
        t_end = t_start + lockstep_seconds / rounds
        while time.perf_counter() < t_end:
            ex.spin_once(timeout_sec=0.05)
        _set_paused(node, ex, pause, True)
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


def _pause_client(node, ex):
    """sim_node's ~/pause service (std_srvs/SetBool), once it is up (2 min at most)."""
    from std_srvs.srv import SetBool
    pause = node.create_client(SetBool, "/sim_node/pause")
    if not _wait(ex, pause.service_is_ready, 120):
        raise RuntimeError("bench: sim_node's ~/pause service did not appear")
    return pause


def _task_cpu_ns(pid) -> int:
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
    out = {"controller_side": _task_cpu_ns(os.getpid())}
    if sim_pid:
        out["sim"] = _task_cpu_ns(sim_pid)
        try:
            with open(f"/proc/{sim_pid}/task/{sim_pid}/children") as f:
                kids = [int(x) for x in f.read().split()]
        except (OSError, ValueError):
            kids = []
        out["sim_children"] = sum(_task_cpu_ns(k) for k in kids)
    return out


#: commands the real controller sends in a warm-up run before the measured rounds: its
#: first cycles load its kernels and fill its state (a first round measured without it
#: counted none in its window, and its pause request once timed out)
WARMUP_COMMANDS = 200


def _warm_up_loop(node, ex, pause, ctl, timeout=60.0):
    """Runs the lockstep loop until the controller `ctl` (in this process) has sent
    WARMUP_COMMANDS commands, then pauses the sim again; in the composed mode (ctl None)
    for one second."""
    _set_paused(node, ex, pause, False)
    if ctl is None:
        _wait(ex, lambda: False, 1.0)
    else:
        n0 = ctl.counters["commands"]
        if not _wait(ex, lambda: ctl.counters["commands"] - n0 >= WARMUP_COMMANDS, timeout):
            print(f"  warm-up: only {ctl.counters['commands'] - n0} commands in "
                  f"{timeout:.0f} s", flush=True)
    # (the sim's process answers once its first cycles are done: in the composed mode the
    # controller's kernels load there then, which once took over 10 s on a loaded machine)
    _set_paused(node, ex, pause, True, timeout)


def _rounds_real(node, ex, lockstep_seconds, bare_seconds, rounds, warmup, windows,
                 ctl=None, sim_pid=None):
    pause = _pause_client(node, ex)
    _warm_up_loop(node, ex, pause, ctl)
    pp = PingPong(node, ex)
    all_rtts = []
    for r in range(rounds):
        bare_rate, rtts = pp.measure(bare_seconds / rounds)
        all_rtts += rtts
        _set_paused(node, ex, pause, False)
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
        _set_paused(node, ex, pause, True)
        windows.append((t_start, t_end, bare_rate, n,
                        {k: v - cpu0.get(k, 0) for k, v in cpu1.items()}))
        print(f"  round {r + 1}/{rounds}: bare {bare_rate:.0f}/s", flush=True)
    pp.close()
    return bare_figures(all_rtts), None


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


def controller_phase(node, ex, seconds, warmup=1.0):
    ctl = EchoController(node)
    if not _wait(ex, lambda: len(ctl.stamps) > 0, 120):
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


def parent_main(args):
    import rclpy
    from rclpy.node import Node
    results = {"domain_id": args.domain_id, "controller_executor": args.executor,
               "sim_executor": args.sim_executor, "cpus": os.cpu_count(), "pin": args.pin}
    if args.pin:     # this (controller) process on the last CPU, the sim on the first
        os.sched_setaffinity(0, {max(os.sched_getaffinity(0))})
    ctx = rclpy.Context()
    rclpy.init(args=[], context=ctx, domain_id=args.domain_id)
    node = Node("bench_controller", context=ctx)
    ex = _make_executor(args.executor, ctx)
    ex.add_node(node)
    tmp = tempfile.mkdtemp(prefix="starleth_bench_")
    try:
        if args.lockstep_seconds > 0:
            log_path = os.path.join(tmp, "lockstep.log")
            real = args.controller == "real"
            kind = ("composed" if args.composed else "real") if real else "echo"
            timing = os.path.join(tmp, "timing.npz") if real else ""
            ctl, windows = None, []
            if kind == "real":
                ctl = make_bench_controller(ctx, timing=True,
                                            params=_controller_params(args.controller_param))
                ex.add_node(ctl)
            with open(log_path, "w") as log:
                proc = _spawn(args, "lockstep", 0.0, True, log, args.record, timing)
                try:
                    bare, lock = lockstep_beside_bare(node, ex, args.lockstep_seconds,
                                                      args.bare_seconds, args.rounds,
                                                      controller=kind, windows=windows,
                                                      ctl=ctl, sim_pid=proc.pid)
                except Exception:
                    print(_stop(proc, log_path)[1][-3000:], file=sys.stderr)
                    raise
                finally:
                    summary, text = _stop(proc, log_path)
            if real:
                tm = np.load(timing) if os.path.exists(timing) else \
                    {"sim_stamp": None, "sim_t": None}
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
                      + ", ".join(f"{k} {v:.3f}" for k, v in b.items() if v is not None),
                      flush=True)
                if "cpu_per_cycle_ms" in lock:
                    print("CPU time per cycle (ms, all threads): " + ", ".join(
                        f"{k} {v:.3f}" for k, v in lock["cpu_per_cycle_ms"].items()),
                        flush=True)
        if args.realtime_seconds > 0:
            log_path = os.path.join(tmp, "realtime.log")
            with open(log_path, "w") as log:
                proc = _spawn(args, "realtime", 1.0, False, log)
                try:
                    results["realtime"] = controller_phase(node, ex, args.realtime_seconds)
                except Exception:
                    print(_stop(proc, log_path)[1][-3000:], file=sys.stderr)
                    raise
                finally:
                    summary, text = _stop(proc, log_path)
            results["realtime"]["node_summary"] = summary
            if summary:
                print(f"realtime: node tick period error p50 "
                      f"{summary.get('period_error_p50_ms', float('nan')):.4f} ms, p99 "
                      f"{summary.get('period_error_p99_ms', float('nan')):.4f} ms (goal < 0.25), "
                      f"max {summary.get('period_error_max_ms', float('nan')):.3f} ms, overruns "
                      f"{summary.get('overruns')}", flush=True)
            rr = results["realtime"]
            print(f"realtime: /joint_states received {rr['states_per_s']:.1f}/s, "
                  f"inter-arrival error p99 {rr['interarrival_error_p99_ms']:.3f} ms", flush=True)
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        shutil.rmtree(tmp, ignore_errors=True)     # the child's logs and timing arrays
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    return results


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
