"""What the live view costs the lockstep cycle (a benchmark script, not a test; issue #35):
two sim_node processes side by side on one ROS domain, each in lockstep as fast as its
controller answers (``--composed``: controller_node standing, in the sim's process), both
started paused, identical but for the live view: ``/live_off`` without it, ``/live_on`` with
``live_view:=true`` and a client of the Foxglove WebSocket protocol in this process
(:mod:`.live_log`) subscribed to every topic it serves. In each of ``--rounds`` rounds one
of them runs for ``--seconds`` (unpaused and paused again through its ``~/pause``), then
the other (the order alternates between rounds, so that a drift of the machine's load falls
on both); a round's cycle time is its wall time over its steps (the sim time the pause
responses report / 2.5 ms), beside the CPU time the sim process (all its threads, the SDK's
server included) spent per step, which depends much less on the other load of the machine.

    python -m starleth_sim.tools.bench.live                   # 12 rounds of 1.5 s each
    python -m starleth_sim.tools.bench.live --rounds 10 --seconds 3 --port 8799
    python -m starleth_sim.tools.bench.live --client layout   # the layout's topics only
    python -m starleth_sim.tools.bench.live --record          # both record, as the demo

Prints each round's cycle times, their medians, the median of the rounds' pairs' ratios
(the live view's cost in per cent of the cycle without it, goal <= 10 %), the CPU time per
cycle, and what the client received. The figures depend on what
else runs on the machine: run it on an idle one.
"""
from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

from starleth_interface.ros_helpers import service_qos

from ..common.child_process import stop_child
from ..common.discovery import keep_discovery_local, local_discovery_env
from ..view.foxglove_layout import shipped_layout_path
from ..view.live_log import collect
from .round_trips import spin_until

PERIOD_S = 0.0025


def _start(name, domain_id, log, params):
    cmd = [sys.executable, "-m", "starleth_sim.ros.sim_node", "--composed",
           "--controller-param", "mode:=stand", "--ros-args", "-r", f"__ns:=/{name}",
           "-p", "mode:=lockstep", "-p", "real_time_factor:=0.0", "-p", "start_paused:=true",
           "-p", "publish_clock:=false", *[a for k, v in params.items()
                                          for a in ("-p", f"{k}:={v}")]]
    env = dict(local_discovery_env(), ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED="1")
    return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)


class _Pause:
    """The ~/pause service of one sim_node: set(paused) returns the sim time it reports."""

    def __init__(self, node, ex, name):
        from std_srvs.srv import SetBool
        self.node, self.ex, self.SetBool = node, ex, SetBool
        self.client = node.create_client(SetBool, f"/{name}/sim_node/pause",
                                         qos_profile=service_qos())
        if not spin_until(ex, self.client.service_is_ready, 180):
            raise RuntimeError(f"bench_live: /{name}/sim_node/pause did not appear")

    def set(self, paused) -> float:
        fut = self.client.call_async(self.SetBool.Request(data=paused))
        if not spin_until(self.ex, fut.done, 10) or not fut.result().success:
            raise RuntimeError(f"bench_live: ~/pause({paused}) failed")
        return float(re.search(r"sim time ([0-9.]+) s", fut.result().message).group(1))


def _cpu_seconds(pid) -> float:
    """User + system CPU time of process `pid`, all its threads (the SDK's server too)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _run_for(pause, seconds, pid):
    """Unpause for `seconds`, pause: (wall seconds, steps, CPU seconds of the process)."""
    c0, t0, s0 = _cpu_seconds(pid), time.perf_counter(), pause.set(False)
    time.sleep(seconds)
    s1, t1, c1 = pause.set(True), time.perf_counter(), _cpu_seconds(pid)
    return t1 - t0, round((s1 - s0) / PERIOD_S), c1 - c0


def layout_topics(path=None) -> list:
    """The topics the shipped Foxglove layout (foxglove/starleth_layout.json) names, and
    /tf and /tf_static (its 3D panel follows every transform)."""
    path = path or shipped_layout_path()
    with open(path) as f:
        named = re.findall(r'"(/[A-Za-z0-9_/]+)', f.read())
    # relative names (a client matches them in any namespace), the global TF as it is
    return sorted({t.lstrip("/") for t in named} | {"/tf", "/tf_static"})


def bench(rounds, seconds, port, domain_id, topics=None, warmup=1.0, record=False,
          rate=None):
    """`topics`: what the client subscribes to (None: every topic; []: no client);
    record: both sim_nodes record (to a temporary directory), as the demo's does, so
    both build every topic."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    tmp = tempfile.mkdtemp(prefix="starleth_bench_live_")
    logs = {n: open(os.path.join(tmp, n + ".log"), "w") for n in ("live_off", "live_on")}
    rec = {n: {"record": os.path.join(tmp, n + ".mcap")} if record else {} for n in logs}
    procs = {"live_off": _start("live_off", domain_id, logs["live_off"], rec["live_off"]),
             "live_on": _start("live_on", domain_id, logs["live_on"],
                               {"live_view": "true", "live_view_port": port,
                                **({} if rate is None else {"live_view_rate": float(rate)}),
                                **rec["live_on"]})}
    stop, client = threading.Event(), {}

    def listen():
        client["log"] = collect(f"ws://127.0.0.1:{port}", topics, seconds=1e9,
                                connect_timeout=180, until=lambda _log: stop.is_set())

    listener = threading.Thread(target=listen, daemon=True)
    if topics != []:
        listener.start()
    ctx = rclpy.Context()
    rclpy.init(args=[], context=ctx, domain_id=domain_id)
    node = Node("bench_live", context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    try:
        cycles, cpu = _interleaved_rounds(node, ex, procs, rounds, seconds, warmup)
    finally:
        stop.set()
        for p in procs.values():
            p.send_signal(signal.SIGINT)     # both at once, then wait for each
        for p in procs.values():
            stop_child(p, 30.0)
        if listener.is_alive():
            listener.join(10)
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        for f in logs.values():
            f.close()
    result = _print_figures(cycles, cpu, rounds, seconds, topics, client.get("log"))
    result["logs"] = tmp
    return result


def _interleaved_rounds(node, ex, procs, rounds, seconds, warmup):
    """Each sim_node run `seconds` a round, in alternating order: ({name: wall time per
    step [µs] per round}, {name: the sim process's CPU time per step [µs] per round})."""
    cycles = {"live_off": [], "live_on": []}
    cpu = {"live_off": [], "live_on": []}
    pauses = {n: _Pause(node, ex, n) for n in procs}
    for n in pauses:                      # warm-up: the controller's first answers
        _run_for(pauses[n], warmup, procs[n].pid)
    for r in range(rounds):
        order = ("live_off", "live_on") if r % 2 == 0 else ("live_on", "live_off")
        for n in order:
            wall, steps, c = _run_for(pauses[n], seconds, procs[n].pid)
            cycles[n].append(wall / max(steps, 1) * 1e6)
            cpu[n].append(c / max(steps, 1) * 1e6)
        print(f"  round {r + 1:2d}: cycle {cycles['live_off'][-1]:7.1f} us without the "
              f"live view, {cycles['live_on'][-1]:7.1f} us with it; CPU per cycle "
              f"{cpu['live_off'][-1]:6.1f} / {cpu['live_on'][-1]:6.1f} us", flush=True)
    return cycles, cpu


def _print_figures(cycles, cpu, rounds, seconds, topics, log) -> dict:
    """The medians printed and returned."""
    off, on = (float(np.median(cycles[n])) for n in ("live_off", "live_on"))
    pair = float(np.median(np.array(cycles["live_on"]) / np.array(cycles["live_off"])))
    cpu_off, cpu_on = (float(np.median(cpu[n])) for n in ("live_off", "live_on"))
    who = ("no client" if topics == [] else "a client subscribed to " +
           ("every topic" if topics is None else f"{len(topics)} topics"))
    print(f"lockstep cycle (medians of {rounds} rounds of {seconds:g} s): {off:.1f} us without "
          f"the live view, {on:.1f} us with it and {who}; median ratio of a round's pair "
          f"{(pair - 1) * 100:+.1f} % (goal <= 10 %); CPU time of the sim process per cycle "
          f"{cpu_off:.1f} us / {cpu_on:.1f} us ({(cpu_on / cpu_off - 1) * 100:+.1f} %)")
    if log is not None:
        n = sum(len(m) for m in log.messages.values())
        print(f"the client received {n} messages on {len(log.messages)} of "
              f"{len(log.channels)} topics")
    return {"cycle_us_off": off, "cycle_us_on": on, "pair_ratio": pair, "rounds": cycles,
            "cpu_us_off": cpu_off, "cpu_us_on": cpu_on}


def main(argv=None):
    keep_discovery_local()
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=12)
    ap.add_argument("--seconds", type=float, default=1.5, help="per round and node")
    ap.add_argument("--port", type=int, default=8799, help="the live view's port")
    ap.add_argument("--domain-id", type=int, default=os.getpid() % 50 + 30)
    ap.add_argument("--client", default="all", choices=("all", "layout", "none"),
                    help="the client subscribes to every topic (all), to those of the "
                         "shipped Foxglove layout (layout), or there is none (none)")
    ap.add_argument("--record", action="store_true",
                    help="both sim_nodes record (as the demo's does): both build every topic")
    ap.add_argument("--rate", type=float, default=None,
                    help="the live view's live_view_rate (default: sim_node's, 50 Hz)")
    args = ap.parse_args(argv)
    topics = {"all": None, "layout": layout_topics(), "none": []}[args.client]
    bench(args.rounds, args.seconds, args.port, args.domain_id, topics, record=args.record,
          rate=args.rate)
    return 0


if __name__ == "__main__":
    sys.exit(main())
