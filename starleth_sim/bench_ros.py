"""Benchmark of the ROS 2 interface of ``sim_node`` (a script, not a test).

    python -m starleth_sim.bench_ros                     # all phases (~90 s)
    python -m starleth_sim.bench_ros --realtime-seconds 0 --lockstep-seconds 10

Two processes: this one (the controller side) and a child process that first answers bare
rclpy ping-pongs and then, in the same process, runs ``SimNode``:

1. bare round trips: JointState ping -> pong between the two processes, one in flight,
   for ``--bare-seconds``: round trips per second and median round-trip time;
2. lockstep: the child runs sim_node in lockstep mode with real_time_factor 0; this
   process is a trivial echo controller (joint PD hold of the first posture, answering every
   /joint_states with a /joint_commands stamped with the state's stamp): control cycles per
   second, and the ratio to the bare rate (goal >= 0.75);
3. realtime: a fresh child runs sim_node in realtime mode (400 Hz) for
   ``--realtime-seconds`` with the same controller: the node's own tick-period error
   (p50/p99/max; goal p99 < 0.25 ms) and the inter-arrival jitter of /joint_states here.

Options: ``--executor`` / ``--sim-executor`` (events | single_threaded) for the two sides
(the bare phase uses the same ones), ``--record PATH`` to record the lockstep phase,
``--realtime-priority N`` for sim_node's SCHED_FIFO option in the realtime phase.
The two processes use an isolated ROS_DOMAIN_ID (``--domain-id``, default from the pid).
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
import tempfile
import time

import numpy as np

PING, PONG = "/starleth_bench/ping", "/starleth_bench/pong"


# -----------------------------------------------------------------------------------------
# controller side helpers (also used by the integration tests)
# -----------------------------------------------------------------------------------------
class EchoController:
    """Answers every /joint_states with a /joint_commands JointState stamped with the state's
    stamp: PD hold of the first posture it sees (or of `q_ref`). Counts states and stamps."""

    def __init__(self, node, kp=200.0, kd=5.0, q_ref=None, reply=True, topic="/joint_commands"):
        from sensor_msgs.msg import JointState
        from rclpy.qos import QoSProfile
        self.node = node
        self.kp, self.kd = kp, kd
        self.q_ref = None if q_ref is None else np.asarray(q_ref, dtype=float)
        self.reply = reply
        self.stamps = []
        self.recv_times = []
        self._JointState = JointState
        self.pub = node.create_publisher(JointState, topic, QoSProfile(depth=10))
        self.sub = node.create_subscription(JointState, "/joint_states", self._on_state,
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
    from starleth_sim.nodes.sim_node import make_executor
    return make_executor(kind, context)[0]


# -----------------------------------------------------------------------------------------
# child process: pong, then sim_node
# -----------------------------------------------------------------------------------------
def child_main(args):
    import rclpy
    from rclpy.node import Node
    from rclpy.qos import QoSProfile
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import JointState
    from starleth_sim.nodes.sim_node import SimNode

    rclpy.init(args=[], domain_id=args.domain_id,
               signal_handler_options=SignalHandlerOptions.NO)
    stop = {"flag": False}
    signal.signal(signal.SIGINT, lambda *a: stop.__setitem__("flag", True))
    signal.signal(signal.SIGTERM, lambda *a: stop.__setitem__("flag", True))
    if args.pong:
        node = Node("bench_pong")
        ex = _make_executor(args.sim_executor, node.context)
        ex.add_node(node)
        pub = node.create_publisher(JointState, PONG, QoSProfile(depth=10))
        done = {"flag": False}

        def on_ping(msg):
            if msg.name and msg.name[0] == "__done__":
                done["flag"] = True
                return
            pub.publish(msg)

        node.create_subscription(JointState, PING, on_ping, QoSProfile(depth=10))
        t_end = time.monotonic() + 120
        while not done["flag"] and not stop["flag"] and time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.05)
        ex.remove_node(node)
        node.destroy_node()
        try:
            ex.shutdown(timeout_sec=0.1)
        except Exception:
            pass
    overrides = {"mode": args.mode, "real_time_factor": args.rtf, "executor": args.sim_executor,
                 "realtime_priority": args.realtime_priority}
    if args.record:
        overrides["record"] = args.record
    sim = SimNode(parameter_overrides=overrides)
    ex = _make_executor(args.sim_executor, sim.context)
    ex.add_node(sim.node)
    signal.signal(signal.SIGINT, sim.request_stop)
    signal.signal(signal.SIGTERM, sim.request_stop)
    if stop["flag"]:
        sim.request_stop()
    try:
        sim.run(ex)
    finally:
        summary = sim.close()
        print("BENCH_SUMMARY " + json.dumps(summary), flush=True)
        sim.node.destroy_node()
        rclpy.try_shutdown()


# -----------------------------------------------------------------------------------------
# parent
# -----------------------------------------------------------------------------------------
def _spawn(args, mode, rtf, pong, log, record=""):
    cmd = [sys.executable, "-m", "starleth_sim.bench_ros", "--child", "--domain-id",
           str(args.domain_id), "--mode", mode, "--rtf", str(rtf), "--sim-executor",
           args.sim_executor]
    if pong:
        cmd.append("--pong")
    if record:
        cmd += ["--record", record]
    if mode == "realtime" and args.realtime_priority:
        cmd += ["--realtime-priority", str(args.realtime_priority)]
    env = dict(os.environ, ROS_DOMAIN_ID=str(args.domain_id), PYTHONUNBUFFERED="1")
    return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)


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


def _wait(ex, cond, timeout):
    t_end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > t_end:
            return False
        ex.spin_once(timeout_sec=0.01)
    return True


def bare_round_trips(node, ex, seconds):
    from sensor_msgs.msg import JointState
    from rclpy.qos import QoSProfile
    got = {"n": 0}
    pub = node.create_publisher(JointState, PING, QoSProfile(depth=10))

    def on_pong(msg):
        got["n"] += 1

    sub = node.create_subscription(JointState, PONG, on_pong, QoSProfile(depth=10))
    if not _wait(ex, lambda: pub.get_subscription_count() > 0 and
                 sub.get_publisher_count() > 0, 60):
        raise RuntimeError("bench: the pong process did not appear")
    msg = JointState()
    msg.name = [f"j{i}" for i in range(12)]
    msg.position = [0.1] * 12
    msg.velocity = [0.0] * 12
    msg.effort = [0.0] * 12
    # warm-up: the first messages after matching can be slow
    for _ in range(50):
        want = got["n"] + 1
        pub.publish(msg)
        _wait(ex, lambda: got["n"] >= want, 2.0)
    rtts = []
    t_end = time.perf_counter() + seconds
    t0 = time.perf_counter()
    while time.perf_counter() < t_end:
        want = got["n"] + 1
        t = time.perf_counter()
        msg.header.stamp.nanosec = len(rtts) % 1_000_000_000
        pub.publish(msg)
        while got["n"] < want:
            ex.spin_once(timeout_sec=1.0)
            if time.perf_counter() - t > 2.0:
                break
        rtts.append(time.perf_counter() - t)
    wall = time.perf_counter() - t0
    done = JointState()
    done.name = ["__done__"]
    pub.publish(done)
    for _ in range(5):
        ex.spin_once(timeout_sec=0.01)
    node.destroy_publisher(pub)
    node.destroy_subscription(sub)
    rtts = np.array(rtts)
    return {"round_trips_per_s": len(rtts) / wall, "rtt_median_ms": float(np.median(rtts) * 1e3),
            "rtt_p99_ms": float(np.percentile(rtts, 99) * 1e3), "n": int(len(rtts))}


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
               "sim_executor": args.sim_executor, "cpus": os.cpu_count()}
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=args.domain_id)
    node = Node("bench_controller", context=ctx)
    ex = _make_executor(args.executor, ctx)
    ex.add_node(node)
    tmp = tempfile.mkdtemp(prefix="starleth_bench_")
    try:
        if args.lockstep_seconds > 0:
            log_path = os.path.join(tmp, "lockstep.log")
            with open(log_path, "w") as log:
                proc = _spawn(args, "lockstep", 0.0, True, log, args.record)
                try:
                    results["bare"] = bare_round_trips(node, ex, args.bare_seconds)
                    print(f"bare rclpy round trips: {results['bare']['round_trips_per_s']:.0f}/s, "
                          f"median {results['bare']['rtt_median_ms']:.3f} ms", flush=True)
                    results["lockstep"] = controller_phase(node, ex, args.lockstep_seconds)
                except Exception:
                    print(_stop(proc, log_path)[1][-3000:], file=sys.stderr)
                    raise
                finally:
                    summary, text = _stop(proc, log_path)
            results["lockstep"]["node_summary"] = summary
            r = results["lockstep"]["states_per_s"] / results["bare"]["round_trips_per_s"]
            results["lockstep"]["ratio_to_bare"] = r
            print(f"lockstep control cycles: {results['lockstep']['states_per_s']:.0f}/s "
                  f"({r:.2f}x bare; goal >= 0.75), sim/wall "
                  f"{results['lockstep']['sim_time_per_wall']:.2f}", flush=True)
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
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    return results


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--bare-seconds", type=float, default=5.0)
    p.add_argument("--lockstep-seconds", type=float, default=10.0)
    p.add_argument("--realtime-seconds", type=float, default=60.0)
    p.add_argument("--executor", default="single_threaded", choices=["events", "single_threaded"],
                   help="executor of this (controller) process")
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
    args = p.parse_args(argv)
    if args.child:
        child_main(args)
        return 0
    parent_main(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
