"""The sim side of the ROS benchmark: the child process that ``bench_ros`` starts (``bench_ros
--child``), running sim_node and the pong node of the bare round trips on one executor (or
only the pong node), with the real controller on the same executor in the composed mode;
at its end it prints sim_node's summary (``BENCH_SUMMARY``) and saves the nodes' cycle
timestamps.
"""
from __future__ import annotations

import json
import signal

import numpy as np

from starleth_interface.cycle_times import SIM_CYCLE_FIELDS, CycleTimes
from starleth_interface.ros_helpers import make_executor

from .controllers import make_bench_controller, node_parameters
from .round_trips import add_pong


def _serve_pong_only(args, stop):
    """Only the pong node, until SIGINT / SIGTERM (measure_bare_round_trips)."""
    import rclpy
    from rclpy.node import Node
    pong = Node("bench_pong", context=None)
    add_pong(pong)
    ex = make_executor(args.sim_executor, pong.context)[0]
    ex.add_node(pong)
    while not stop["flag"]:
        ex.spin_once(timeout_sec=0.1)
    pong.destroy_node()
    rclpy.try_shutdown()


def child_main(args):
    """The child process of ``bench_ros`` (its hidden ``--child`` options in `args`)."""
    import rclpy
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    from starleth_sim.ros.sim_node import SimNode  # deferred: imports rclpy

    rclpy.init(args=[], domain_id=args.domain_id,
               signal_handler_options=SignalHandlerOptions.NO)
    stop = {"flag": False}
    signal.signal(signal.SIGINT, lambda *a: stop.__setitem__("flag", True))
    signal.signal(signal.SIGTERM, lambda *a: stop.__setitem__("flag", True))
    if args.pong_only:     # measure_bare_round_trips: only the pong node
        _serve_pong_only(args, stop)
        return
    overrides = {"mode": args.mode, "real_time_factor": args.rtf, "executor": args.sim_executor,
                 "realtime_priority": args.realtime_priority}
    if args.record:
        overrides["record"] = args.record
    if args.mode == "lockstep":
        overrides.update(node_parameters(args.sim_param))
    if args.pong:
        overrides["start_paused"] = True    # the parent unpauses it for each lockstep round
    sim = SimNode(parameter_overrides=overrides)
    ex = make_executor(args.sim_executor, sim.context)[0]
    ex.add_node(sim.node)
    ctl = None
    if args.timing:
        sim.timing = CycleTimes(SIM_CYCLE_FIELDS)
    if args.composed:   # the controller on sim_node's executor, in this process
        ctl = make_bench_controller(sim.context, timing=bool(args.timing),
                                    params=node_parameters(args.controller_param))
        ex.add_node(ctl)
    if args.pong:   # bare round trips, served by the same executor as sim_node
        pong = Node("bench_pong", context=sim.context)
        add_pong(pong)
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
