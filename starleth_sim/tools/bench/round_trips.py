"""Bare rclpy round trips, the reference of the loop benchmarks (``bench_ros``,
``bench_floor``, starleth-demo): the ping and pong topics, the pong node's echo, the ping
side (:class:`PingPong`), spinning an executor until a condition holds, and the rate of bare
round trips against a child process running only the pong side (:func:`measure_bare_round_trips`).

A JointState with 12 names and 3 x 12 values (like /joint_states) goes out on PING, the
pong side publishes it back on PONG, the next one goes out when the echo is in.
"""
from __future__ import annotations

import subprocess
import sys
import time

import numpy as np

from starleth_interface.compile_notice import Deadline
from starleth_interface.ros_helpers import make_executor

from ..common.child_process import stop_child
from ..common.discovery import keep_discovery_local, local_discovery_env

PING, PONG = "/starleth_bench/ping", "/starleth_bench/pong"

#: the log of the benchmark's child process running now (``bench_ros`` sets it when it
#: starts one): its build lines (compile_notice) restart :func:`spin_until`'s time-outs
CHILD_LOGS: list = []


def add_pong(node):
    """The pong side on `node`: every message on PING published back on PONG."""
    from rclpy.qos import QoSProfile
    from sensor_msgs.msg import JointState
    pong_pub = node.create_publisher(JointState, PONG, QoSProfile(depth=10))
    node.create_subscription(JointState, PING, pong_pub.publish, QoSProfile(depth=10))


def spin_until(ex, cond, timeout):
    """Spins until cond() (True) or `timeout` s of silence (False): the child's compile
    lines (compile_notice.shows_compiling, in CHILD_LOGS) restart the time-out."""
    deadline = Deadline(timeout, CHILD_LOGS)
    while not cond():
        if deadline.expired():
            return False
        ex.spin_once(timeout_sec=0.01)
    return True


class PingPong:
    """Bare rclpy round trips with the child's pong node: a JointState (12 names, 3 x 12
    values, like /joint_states) goes out, the next is sent when its echo is back."""

    def __init__(self, node, ex, startup=60.0):
        from rclpy.qos import QoSProfile
        from sensor_msgs.msg import JointState
        self.node, self.ex = node, ex
        self.got = 0
        self.pub = node.create_publisher(JointState, PING, QoSProfile(depth=10))
        self.sub = node.create_subscription(JointState, PONG, self._on_pong, QoSProfile(depth=10))
        msg = self.msg = JointState()
        msg.name = [f"j{i}" for i in range(12)]
        msg.position = [0.1] * 12
        msg.velocity = [0.0] * 12
        msg.effort = [0.0] * 12
        if not spin_until(ex, lambda: self.pub.get_subscription_count() > 0 and
                          self.sub.get_publisher_count() > 0, startup):
            raise RuntimeError("bench: the pong node did not appear")
        for _ in range(50):     # warm-up: the first messages after matching can be slow
            want = self.got + 1
            self.pub.publish(msg)
            spin_until(ex, lambda want=want: self.got >= want, 2.0)

    def _on_pong(self, _msg):
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
    cmd = [sys.executable, "-m", "starleth_sim.tools.bench.ros", "--child", "--pong-only",
           "--domain-id", str(domain_id), "--sim-executor", executor]
    env = dict(local_discovery_env(), ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, env=env)
    ctx = rclpy.Context()
    rclpy.init(args=[], context=ctx, domain_id=domain_id)
    node = Node("bench_ping", context=ctx)
    try:
        ex = make_executor(executor, ctx)[0]
        ex.add_node(node)
        pp = PingPong(node, ex, startup)
        rate, rtts = pp.measure(seconds)
        pp.close()
        return rate, float(np.median(rtts))
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        stop_child(proc, 10.0)
