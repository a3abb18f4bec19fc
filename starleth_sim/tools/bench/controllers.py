"""The controllers the ROS benchmark runs against sim_node: the PD echo controller
(:class:`EchoController`, also the node tests' way to keep the robot standing) and
starleth_controller's ControllerNode as the real one (:func:`make_bench_controller`:
stand, then trot), and the ``NAME:=VALUE`` node parameters of the command line.
"""
from __future__ import annotations

import array
import time

import numpy as np
import yaml

from starleth_interface.cycle_times import CONTROLLER_CYCLE_FIELDS, CycleTimes

from ...physics.posture import DEFAULT_KD, DEFAULT_KP


class EchoController:
    """Answers every /joint_states with a /joint_commands JointState stamped with the state's
    stamp: PD hold of the first posture it sees (or of `q_ref`). Counts states and stamps.
    The default gains are the posture hold's (`posture.DEFAULT_KP/KD` per joint type), which
    stay stable with a leg in the air (a stiffer knee damping makes a lifted shank flail under
    the 400 Hz zero-order hold)."""

    def __init__(self, node, kp=None, kd=None, q_ref=None, reply=True,
                 topic="joint_commands"):
        from rclpy.qos import QoSProfile
        from sensor_msgs.msg import JointState
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


def node_parameters(items):
    """{name: value} of the ``--controller-param`` / ``--sim-param NAME:=VALUE`` options
    (values read as YAML, as ROS reads -p values)."""
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

    from starleth_controller import controller_node  # deferred: imports rclpy
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
