"""The floor of the real loop (a script, not a test): what the two-process lockstep loop of
``bench_ros --controller real`` costs without the nodes.

    python -m starleth_sim.tools.bench.floor                  # 3 rounds, ~40 s
    python -m starleth_sim.tools.bench.floor --rounds 5 --bare-seconds 5 --floor-seconds 10

The same two processes as ``bench_ros`` (this one the controller side, a child the sim
side, on an isolated ROS domain), the same messages, QoS and executors, but none of the
nodes' work around them:

- the child's callback on a command (``sensor_msgs/JointState``, the bytes controller_node
  sends) reads its efforts with sim_node's decoder, runs ``Simulator.step`` (the preset of
  sim_node's default, HmJ) and publishes the new state as one state bundle (the bytes
  sim_node sends: :func:`bundle_bytes`);
- this process's callback on a bundle reads it as controller_node does (the
  ``node_state`` kernel), runs ``StarlethController.update`` (stand, then trot at 0.3 m/s
  from 0.5 s of sim time, as bench_ros) and publishes the command (:class:`FloorController`).

No recording, no public topics, no diagnostics, no timeouts, re-sends or checks beyond the
decoders'. The rounds interleave bare rclpy round trips (``bench_round_trips.PingPong``,
served by the child) with floor cycles, so each round's ratio compares the two under one
load of the machine. Printed: cycles per second and their ratio to the bare round trips (the figure
bench_ros gives the real loop), and the medians of the step, the state's way out (bundle
built and published), and the controller's part (bundle read, update, command published).

``bench_ros --controller real`` beside this on the same machine says how much of a cycle
the nodes and the recording add; this says how much a cycle of this physics and this
controller costs at all. The figures depend on what else runs on the machine.
"""
from __future__ import annotations

import argparse
import array
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np

from starleth_controller import Command, StarlethController
from starleth_controller.state_intake import state_from_values
from starleth_interface import state_bundle
from starleth_interface.msg_cdr import JointStateCdr
from starleth_interface.ros_helpers import make_executor
from starleth_interface.state_bundle import JOINT_NAMES, StateBundleCdr

from ...physics.config import PRESETS
from ...physics.simulator import Simulator
from ...ros.cdr import CommandDecoder
from ...ros.state_io import base_values, joint_values, state_bundle_bytes
from ..common.discovery import keep_discovery_local, local_discovery_env
from .controllers import TROT_AT, TROT_SPEED
from .loop_figures import bare_figures, lockstep_figures, print_rates, process_cpu_ns
from .round_trips import PingPong, add_pong, spin_until

BUNDLE_TOPIC = "/starleth_floor/state_bundle"
COMMAND_TOPIC = "/starleth_floor/joint_commands"


def bundle_bytes(bundle_cdr, sim, stamp_ns):
    """The state bundle (starleth_interface.state_bundle) of `sim`'s current state, stamped
    `stamp_ns`, as sim_node sends it (state_io.state_bundle_bytes), through `bundle_cdr`
    (a StateBundleCdr)."""
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return state_bundle_bytes(bundle_cdr, sec, nsec, base_values(sim), joint_values(sim),
                              sim.contact_forces()[:len(sim.description.foot_names)])


class FloorSim:
    """The sim side: on each command, its efforts into one ``Simulator.step``, then the new
    state out as a bundle. ``start()`` sends state 0 (again, until the first command).
    ``times``: (decode + step, bundle out) [s] per command."""

    def __init__(self, node, preset="HmJ"):
        from rclpy.qos import QoSProfile
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64MultiArray
        self.sim = Simulator.from_preset(preset)
        self.k = 0
        self.bundle = StateBundleCdr.create()
        if self.bundle is None:
            raise RuntimeError("bench_floor: this rmw's Float64MultiArray bytes are not the "
                               "state bundle's layout")
        self.decoder = CommandDecoder(JOINT_NAMES)
        self.pub = node.create_publisher(Float64MultiArray, BUNDLE_TOPIC, QoSProfile(depth=10))
        self.sub = node.create_subscription(JointState, COMMAND_TOPIC, self._on_command,
                                            QoSProfile(depth=10), raw=True)
        self.times = []
        self.rejected = 0

    def start(self):
        if self.k == 0:
            self.pub.publish(bundle_bytes(self.bundle, self.sim, 0))

    def _on_command(self, data):
        t0 = time.perf_counter()
        ok, stamp, effort = self.decoder.joint_command(data)
        if not ok or stamp != self.k * 2_500_000:
            self.rejected += 1       # not the answer to the state out (or undecodable)
            return
        self.sim.step(effort)
        self.k += 1
        t1 = time.perf_counter()
        self.pub.publish(bundle_bytes(self.bundle, self.sim, self.k * 2_500_000))
        self.times.append((t1 - t0, time.perf_counter() - t1))


class FloorController:
    """The controller side: each bundle read as controller_node reads it
    (starleth_controller.state_intake.state_from_values: twist in the base frame, contact =
    |F| > the contact threshold), one ``StarlethController.update``, the torques out as
    controller_node's JointState. Answers only while ``running``; ``last`` keeps the newest
    bundle (answered when a round starts). ``times``: bundle in to command out [s];
    ``commands``: sent so far."""

    def __init__(self, node, urdf=None, threshold=None):
        from rclpy.qos import QoSProfile
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64MultiArray
        self.controller = StarlethController(urdf)
        self.command = Command(mode="stand")
        self.threshold = float(self.controller.params.contact_force_threshold
                               if threshold is None else threshold)
        self._perm = np.arange(12, dtype=np.int64)
        self._R = np.eye(3)
        self.cdr = JointStateCdr.create(JOINT_NAMES, ("effort",))
        self.pub = node.create_publisher(JointState, COMMAND_TOPIC, QoSProfile(depth=10))
        self.sub = node.create_subscription(Float64MultiArray, BUNDLE_TOPIC, self._on_bundle,
                                            QoSProfile(depth=10), raw=True)
        self.running = False
        self.last = None
        self.commands = 0
        self.times = []

    def torques(self, data):
        """(sec, nsec, 12 torques) answering a bundle's bytes, or None for a bundle that
        does not decode or whose state the kernel refuses."""
        r = state_bundle.decode(data)
        if isinstance(r, str):
            return None
        sec, nsec, v = r
        parts = state_bundle.SLICES
        state = state_from_values(
            sec * 1_000_000_000 + nsec, v[parts["q"]], v[parts["u"]], self._perm,
            v[state_bundle.BASE], v[parts["force"]].reshape(4, 3), self.threshold, True,
            self._R)
        if state is None:
            return None
        if self.command.mode == "stand" and state.t >= TROT_AT:
            self.command.mode, self.command.forward = "trot", TROT_SPEED
        return sec, nsec, self.controller.update(state, self.command)

    def _on_bundle(self, data):
        self.last = data
        if self.running:
            self.answer(data)

    def answer(self, data):
        t0 = time.perf_counter()
        r = self.torques(data)
        if r is None:
            return
        sec, nsec, tau = r
        self.pub.publish(self.cdr.build(sec, nsec, array.array("d", tau.tobytes())))
        self.commands += 1
        self.times.append(time.perf_counter() - t0)


# -----------------------------------------------------------------------------------------
def child_main(args):
    """The sim side and the pong side of the bare round trips on one executor, until
    SIGINT / SIGTERM; prints its timing medians as one JSON line."""
    import rclpy
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions
    rclpy.init(args=[], domain_id=args.domain_id,
               signal_handler_options=SignalHandlerOptions.NO)
    stop = []
    signal.signal(signal.SIGINT, lambda *a: stop.append(1))
    signal.signal(signal.SIGTERM, lambda *a: stop.append(1))
    node = Node("bench_floor_sim")
    floor = FloorSim(node, args.preset)
    add_pong(node)
    ex = make_executor(args.sim_executor, node.context)[0]
    ex.add_node(node)
    last_start = 0.0
    parent = os.getppid()
    while not stop and os.getppid() == parent:     # (a parent killed outright: stop too)
        if floor.k == 0 and time.monotonic() - last_start > 0.2:
            floor.start()            # state 0 until the controller side answers it
            last_start = time.monotonic()
        ex.spin_once(timeout_sec=0.05)
    t = np.asarray(floor.times[len(floor.times) // 10:]).reshape(-1, 2) * 1e3
    print("FLOOR_CHILD " + json.dumps({
        "steps": floor.k, "rejected": floor.rejected,
        "base_position": floor.sim.base_state()["position"].round(3).tolist(),
        "step_ms": float(np.median(t[:, 0])) if len(t) else None,
        "state_out_ms": float(np.median(t[:, 1])) if len(t) else None}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


def _rounds(ex, ctl, pp, args, sim_pid):
    per, rtts_all, cpu = [], [], {}
    n_total, t_total = 0, 0.0
    for r in range(-1, args.rounds):           # round -1: warm-up, not counted
        bare_rate, rtts = pp.measure(args.bare_seconds / max(args.rounds, 1))
        ctl.running = True
        if ctl.last is not None:
            ctl.answer(ctl.last)                 # the state the last round left unanswered
        t_start = time.perf_counter() + 0.1
        t_end = t_start + (args.floor_seconds / max(args.rounds, 1) if r >= 0 else 1.0)
        n0 = cpu0 = None
        while time.perf_counter() < t_end:
            ex.spin_once(timeout_sec=0.05)
            if n0 is None and time.perf_counter() >= t_start:
                n0, cpu0, t_start = ctl.commands, process_cpu_ns(sim_pid), time.perf_counter()
        n, t_end = ctl.commands - n0, time.perf_counter()
        cpu1 = process_cpu_ns(sim_pid)
        ctl.running = False
        spin_until(ex, lambda: False, 0.05)      # the answer in flight comes back
        if r < 0:
            continue
        rtts_all += rtts
        rate = n / (t_end - t_start)
        per.append({"bare_round_trips_per_s": bare_rate, "lockstep_cycles_per_s": rate,
                    "ratio": rate / bare_rate})
        for k, v in cpu1.items():
            cpu[k] = cpu.get(k, 0) + v - cpu0.get(k, 0)
        n_total += n
        t_total += t_end - t_start
        print(f"  round {r + 1}/{args.rounds}: bare {bare_rate:.0f}/s, floor {rate:.0f}/s, "
              f"ratio {rate / bare_rate:.2f}", flush=True)
    return per, rtts_all, n_total, t_total, cpu


def parent_main(args):
    import rclpy
    from rclpy.node import Node
    keep_discovery_local()
    env = dict(local_discovery_env(), ROS_DOMAIN_ID=str(args.domain_id), PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "starleth_sim.tools.bench.floor", "--child", "--domain-id",
           str(args.domain_id), "--preset", args.preset, "--sim-executor", args.sim_executor]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=None, env=env, text=True)
    ctx = rclpy.Context()
    rclpy.init(args=[], context=ctx, domain_id=args.domain_id)
    node = Node("bench_floor_controller", context=ctx)
    try:
        ex = make_executor(args.executor, ctx)[0]
        ex.add_node(node)
        ctl = FloorController(node)
        if not spin_until(ex, lambda: ctl.last is not None and
                          ctl.pub.get_subscription_count() > 0, 120):
            raise RuntimeError("bench_floor: no state from the sim side")
        pp = PingPong(node, ex)
        per, rtts, n, t, cpu = _rounds(ex, ctl, pp, args, proc.pid)
        pp.close()
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        proc.send_signal(signal.SIGINT)
        try:
            out, _ = proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
    child = next((json.loads(line.split(" ", 1)[1]) for line in out.splitlines()
                  if line.startswith("FLOOR_CHILD ")), {})
    bare = bare_figures(rtts)
    floor = lockstep_figures(per, n, t, 0, bare)
    ctl_t = np.asarray(ctl.times[len(ctl.times) // 10:]) * 1e3
    floor["breakdown_median_ms"] = {"step": child.get("step_ms"),
                                    "state_out": child.get("state_out_ms"),
                                    "controller": float(np.median(ctl_t)) if len(ctl_t) else None}
    floor["cpu_per_cycle_ms"] = {**{k: v * 1e-6 / n for k, v in cpu.items()},
                                 "all": sum(cpu.values()) * 1e-6 / n} if n else {}
    floor["sim_side"] = child
    print_rates(bare, floor, "floor cycles", f") [Simulator.step {args.preset} + "
                "StarlethController.update, one message each way, no nodes]")
    print("per cycle (medians, ms): " + ", ".join(
        f"{k} {v:.3f}" for k, v in floor["breakdown_median_ms"].items() if v is not None)
        + "; CPU time per cycle (ms, all threads): " + ", ".join(
        f"{k} {v:.3f}" for k, v in floor["cpu_per_cycle_ms"].items()), flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"bare": bare, "floor": floor}, f, indent=1)
    return bare, floor


def main(argv=None):
    keep_discovery_local()
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--bare-seconds", type=float, default=6.0,
                   help="bare round trips, in all rounds together")
    p.add_argument("--floor-seconds", type=float, default=18.0,
                   help="floor cycles, in all rounds together")
    p.add_argument("--rounds", type=int, default=3, help="interleaved bare/floor rounds")
    p.add_argument("--preset", default="HmJ", choices=PRESETS,
                   help="the physics (a Table 1 preset)")
    p.add_argument("--executor", default="events", choices=["events", "single_threaded"])
    p.add_argument("--sim-executor", default="events", choices=["events", "single_threaded"])
    p.add_argument("--domain-id", type=int, default=os.getpid() % 30 + 100)
    p.add_argument("--json", default="")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.rounds < 1:
        p.error("--rounds must be >= 1")
    if args.child:
        child_main(args)
    else:
        parent_main(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
