"""Bare rclpy round trips, the reference of the loop benchmarks (``bench_ros``,
``bench_floor``, starleth-demo): the ping and pong topics, the pong node's echo, the ping
side (:class:`PingPong`), and spinning an executor until a condition holds.

A JointState with 12 names and 3 x 12 values (like /joint_states) goes out on PING, the
pong side publishes it back on PONG, the next one goes out when the echo is in.
"""
from __future__ import annotations

import time

from starleth_interface.compile_notice import Deadline

PING, PONG = "/starleth_bench/ping", "/starleth_bench/pong"

#: the log of the benchmark's child process running now (``bench_ros`` sets it when it
#: starts one): its compile lines (CompileNotice) restart :func:`spin_until`'s time-outs
CHILD_LOGS: list = []


def add_pong(node):
    """The pong side on `node`: every message on PING published back on PONG."""
    from rclpy.qos import QoSProfile
    from sensor_msgs.msg import JointState
    pong_pub = node.create_publisher(JointState, PONG, QoSProfile(depth=10))
    node.create_subscription(JointState, PING, pong_pub.publish, QoSProfile(depth=10))


def spin_until(ex, cond, timeout):
    """Spins until cond() (True) or `timeout` s of silence (False): the child's compile
    lines (CompileNotice, in CHILD_LOGS) restart the time-out."""
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
        if not spin_until(ex, lambda: self.pub.get_subscription_count() > 0 and
                          self.sub.get_publisher_count() > 0, startup):
            raise RuntimeError("bench: the pong node did not appear")
        for _ in range(50):     # warm-up: the first messages after matching can be slow
            want = self.got + 1
            self.pub.publish(msg)
            spin_until(ex, lambda: self.got >= want, 2.0)

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
