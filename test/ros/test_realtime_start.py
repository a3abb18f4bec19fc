"""Realtime mode as ROS controllers meet it: the clock runs from the start with the drives
holding the initial posture (realtime_start hold, the default), so a controller on a sim-time
timer runs from the start (doc/controllers.md's timer example, run as written, trots the robot in
place), the robot stands for 20 s with no controller, and a controller that connects
late takes over without a jump; realtime_start first_command still waits with the clock at
0; in lockstep a timer controller gets a hint in sim_node's log.

Nodes run as child processes on an isolated ROS_DOMAIN_ID; every wait is bounded and every
child is stopped in a finally. The figures are read from sim_node's recording."""
import os

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from controller_examples import controllers_page_blocks, start_script, stop_script  # noqa: E501
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_test_nodes import NodeProcess, RosTestNode
from rosgraph_msgs.msg import Clock

from starleth_sim.robots import load_robot
from starleth_sim.tools.common.bag import read_messages

STARLETH_STANDING_HEIGHT = load_robot("starleth").standing_height

DOMAIN_RANGE = (180, 20)       # first, span (conftest._free_ros_domain)
DOMAIN_ID = 180 + os.getpid() % 20
START_TIMEOUT = 120.0          # of silence: a node's compile lines restart it (ros_test_nodes)
BEST_EFFORT = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
FEET = ("LF", "RF", "LH", "RH")
COMMAND_TOPIC = "joint_group_position_controller/commands"


@pytest.fixture(scope="module")
def ros():
    node = RosTestNode(DOMAIN_ID, "realtime_start_test", events=True)
    try:
        yield node
    finally:
        node.close()


class SimClock:
    """The latest sim time on /clock [s] (None before the first)."""

    def __init__(self, ros):
        self.t = None
        self.ros = ros
        self.sub = ros.node.create_subscription(Clock, "/clock", self._cb, BEST_EFFORT)

    def _cb(self, msg):
        self.t = msg.clock.sec + msg.clock.nanosec * 1e-9

    def wait_for(self, t, procs):
        assert self.ros.spin_until(lambda: self.t is not None and self.t >= t, START_TIMEOUT,
                                   procs=procs), (self.t, procs[0].log()[-3000:])

    def close(self):
        self.ros.node.destroy_subscription(self.sub)


def recorded(path):
    """From a sim_node recording: the states' times t [s] and base heights z [m], the foot
    normal forces (len(t), 4) [N], and the sim times [s] of the commands received (any
    command topic), in order."""
    bag = read_messages(str(path), lambda topic, _: topic == "/starleth/base_state"
                        or topic.endswith("_foot/wrench") or "commands" in topic)
    base = bag.messages["/starleth/base_state"]
    t = np.array([ns * 1e-9 for ns, _ in base])
    z = np.array([m.pose.pose.position.z for _, m in base])
    forces = np.column_stack([[m.wrench.force.z for _, m in
                               bag.messages[f"/starleth/{foot}_foot/wrench"]] for foot in FEET])
    commands = sorted(ns * 1e-9 for topic, rows in bag.messages.items() if "commands" in topic
                      for ns, _ in rows)
    return t, z, forces, np.array(commands)


def timer_controller():
    """The third python block of doc/controllers.md: the 50 Hz sim-time timer that trots
    the robot in place."""
    blocks = controllers_page_blocks()
    assert len(blocks) == 3 and "create_timer" in blocks[2], blocks
    return blocks[2]


@pytest.mark.serial   # realtime nodes
def test_timer_controller_example_trots_from_the_start(ros, tmp_path):
    """The timer controller example, as written, beside `sim_node --ros-args -p
    default_kp:=300.0` (realtime, the default): sim time runs before it starts, so its timer
    fires; sim_node receives its first command within 2 s of sim time after the node's
    publisher is discovered (3 s after the node appears: DDS discovery), and the robot trots
    in place (each diagonal pair alone on the ground over a third of the time, the other pair
    in the air; the trunk above 0.37 m)."""
    sim = NodeProcess("starleth_sim.ros.sim_node", str(tmp_path / "sim.log"), DOMAIN_ID,
                      default_kp=300.0, record=str(tmp_path / "timer.mcap"))
    clock = SimClock(ros)
    ctl = None
    try:
        clock.wait_for(0.5, [sim])                       # the clock runs with no controller
        ctl, log = start_script(timer_controller(), tmp_path, "timer_controller", DOMAIN_ID)
        assert ros.spin_until(lambda: "trot_in_place" in ros.node.get_node_names(),
                              START_TIMEOUT, procs=[sim]), (tmp_path / "timer_controller.log"
                                                            ).read_text()
        t_appeared = clock.t
        assert ros.spin_until(lambda: ros.node.count_publishers(COMMAND_TOPIC) > 0,
                              START_TIMEOUT, procs=[sim])
        t_discovered = clock.t
        clock.wait_for(t_appeared + 5.0, [sim])
        assert ctl.poll() is None, (tmp_path / "timer_controller.log").read_text()
    finally:
        clock.close()
        if ctl is not None:
            stop_script(ctl, log)
        code = sim.stop()
    assert code == 0, sim.log()[-3000:]
    t, z, forces, commands = recorded(tmp_path / "timer.mcap")
    assert len(commands) > 0, "no command reached sim_node"
    later = t > commands[0] + 2.0                      # the gait from 2 s after its start
    on = forces[later] > 1.0
    pair_a = (on[:, 0] & on[:, 3] & ~on[:, 1] & ~on[:, 2]).mean()    # LF + RH only
    pair_b = (on[:, 1] & on[:, 2] & ~on[:, 0] & ~on[:, 3]).mean()    # RF + LH only
    rate = np.diff(commands[commands > commands[0] + 1.0]).mean()
    print(f"timer controller: appeared at sim t={t_appeared:.3f} s, its publisher "
          f"discovered at {t_discovered:.3f} s, first command at "
          f"{commands[0]:.3f} s, {len(commands)} commands (every {rate * 1e3:.1f} ms of sim "
          f"time); diagonal pairs alone {pair_a:.2f} / {pair_b:.2f} of the time; trunk "
          f"{z[later].min():.3f} to {z[later].max():.3f} m")
    # from the start (the clock ran before it): within Fast DDS's announcement period (3 s) of
    # its publisher being known on the network (1 s on an idle machine; its subscriptions
    # still have to discover /clock and the state: once 2.5 s on 2 loaded cores), not stuck
    # waiting for a clock that only its commands would start
    assert t_appeared > 0.5 and commands[0] - t_discovered <= 3.0
    assert commands[0] - t_appeared <= 3.0
    assert rate == pytest.approx(0.02, rel=0.1)         # 50 Hz of sim time
    assert pair_a > 0.33 and pair_b > 0.33
    assert z[later].min() > 0.37


#: sim seconds of the hold without a controller: the trunk settles within 1 s (0.4022 m, 1.3
#: cm below standing) and stays there to 10 µm through 60 s, so 20 s show the same figures
HOLD_SECONDS = 20.0


def test_robot_holds_its_posture_without_controller(ros, tmp_path):
    """sim_node in realtime mode with no controller for HOLD_SECONDS of sim time
    (real_time_factor 50, as fast as it goes): the drives hold the initial posture, the trunk
    within 2 cm of its standing height throughout and still in the last second; the log says
    so once, and /starleth/solver reports holding_initial_posture."""
    from diagnostic_msgs.msg import DiagnosticArray
    sim = NodeProcess("starleth_sim.ros.sim_node", str(tmp_path / "sim.log"), DOMAIN_ID,
                      real_time_factor=50.0, record=str(tmp_path / "hold.mcap"),
                      tf_rate=0.0, contact_markers_rate=0.0)     # (only what is read here)
    clock = SimClock(ros)
    status = {}
    sub = ros.node.create_subscription(
        DiagnosticArray, "starleth/solver",
        lambda m: status.update({kv.key: kv.value for s in m.status for kv in s.values}), 10)
    try:
        clock.wait_for(HOLD_SECONDS, [sim])
    finally:
        clock.close()
        ros.node.destroy_subscription(sub)
        code = sim.stop()
    assert code == 0, sim.log()[-3000:]
    t, z, _, commands = recorded(tmp_path / "hold.mcap")
    last = z[t >= t[-1] - 1.0]
    print(f"{HOLD_SECONDS:.0f} s without a controller: trunk {z.min():.4f} to {z.max():.4f} m "
          f"(standing {STARLETH_STANDING_HEIGHT} m; the last second {np.ptp(last) * 1e6:.1f} µm "
          f"apart), {len(t)} states to t={t[-1]:.2f} s")
    assert t[-1] >= HOLD_SECONDS and len(commands) == 0
    assert np.all(np.abs(z - STARLETH_STANDING_HEIGHT) < 0.02)
    assert np.ptp(last) < 1e-4                        # settled: no slow sag left
    assert status.get("holding_initial_posture") == "True", status
    assert sim.log().count("the joints hold the initial posture") == 1


#: sim seconds of the hold before the late controller starts (the hold has settled by 1 s)
LATE_START = 4.0


@pytest.mark.serial   # a realtime node and controller
def test_late_controller_takes_over_without_a_jump(ros, tmp_path):
    """controller_node (stand) started once LATE_START s of sim time have run with the drives
    holding (real_time_factor 4): it takes over a standing robot, the trunk moving no further
    from where the hold left it than the hold's own tracking error (its sag below the
    standing height) plus 2 mm, within the 3 s after its first command."""
    sim = NodeProcess("starleth_sim.ros.sim_node", str(tmp_path / "sim.log"), DOMAIN_ID,
                      real_time_factor=4.0, record=str(tmp_path / "late.mcap"))
    clock = SimClock(ros)
    ctl = None
    try:
        clock.wait_for(LATE_START, [sim])
        ctl = NodeProcess("starleth_controller.controller_node", str(tmp_path / "ctl.log"),
                          DOMAIN_ID, use_sim_time=True)
        clock.wait_for(LATE_START, [sim, ctl])
        assert ros.spin_until(lambda: "first command is in effect" in sim.log(),
                              START_TIMEOUT, procs=[sim, ctl]), sim.log()[-3000:]
        t_now = clock.t
        clock.wait_for(t_now + 3.5, [sim, ctl])
    finally:
        clock.close()
        codes = [p.stop() for p in (ctl, sim) if p is not None]
    assert codes == [0, 0], sim.log()[-3000:]
    t, z, _, commands = recorded(tmp_path / "late.mcap")
    t_first = commands[0]
    held = z[t < t_first]
    z_takeover = held[-1]
    hold_error = STARLETH_STANDING_HEIGHT - z_takeover
    after = z[(t >= t_first) & (t <= t_first + 3.0)]
    jump = np.abs(after - z_takeover).max()
    print(f"held until t={t_first:.3f} s (trunk {held.min():.4f} to {held.max():.4f} m, "
          f"{hold_error * 1e3:.1f} mm below standing at the takeover); after it the trunk "
          f"{after.min():.4f} to {after.max():.4f} m: {jump * 1e3:.1f} mm from the takeover")
    assert t_first >= LATE_START and len(after) > 1000
    assert np.all(np.abs(held - STARLETH_STANDING_HEIGHT) < 0.02)
    assert jump <= hold_error + 0.002


def test_first_command_start_keeps_the_clock_at_zero(ros, tmp_path):
    """realtime_start:=first_command: without a controller the initial state is re-sent
    stamped 0, /clock stays at 0 and the robot does not move."""
    from nav_msgs.msg import Odometry
    sim = NodeProcess("starleth_sim.ros.sim_node", str(tmp_path / "sim.log"), DOMAIN_ID,
                      realtime_start="first_command")
    states = []
    sub = ros.node.create_subscription(Odometry, "starleth/base_state", states.append, 10)
    clock = SimClock(ros)
    try:
        assert ros.spin_until(lambda: states, START_TIMEOUT, procs=[sim]), sim.log()[-3000:]
        ros.spin_for(1.5)
    finally:
        clock.close()
        ros.node.destroy_subscription(sub)
        code = sim.stop()
    assert code == 0
    assert len(states) >= 2                          # state 0, re-sent every 0.5 s
    assert all(s.header.stamp.sec == s.header.stamp.nanosec == 0 for s in states)
    assert all(s.pose.pose.position.z == pytest.approx(STARLETH_STANDING_HEIGHT, abs=1e-6)
               for s in states)
    assert clock.t in (None, 0.0)
    assert "waiting for the first command" in sim.log()


def test_timer_controller_in_lockstep_gets_a_hint(ros, tmp_path):
    """The timer controller example beside a lockstep sim_node: its sim-time clock never
    moves (nothing answers state 0), so it sends nothing; after 5 s sim_node logs one hint
    that such a controller belongs in realtime mode."""
    sim = NodeProcess("starleth_sim.ros.sim_node", str(tmp_path / "sim.log"), DOMAIN_ID,
                      mode="lockstep")
    ctl = None
    try:
        ctl, log = start_script(timer_controller(), tmp_path, "timer_controller", DOMAIN_ID)
        assert ros.spin_until(lambda: "belongs in realtime" in sim.log() or
                              "run sim_node with mode:=realtime" in sim.log(),
                              START_TIMEOUT, procs=[sim]), sim.log()[-3000:]
        ros.spin_for(1.0)
    finally:
        if ctl is not None:
            stop_script(ctl, log)
        code = sim.stop()
    assert code == 0
    summary = sim.summary()
    assert summary["commands_received"] == 0 and summary["steps"] == 0, summary
    assert sim.log().count("mode:=realtime") == 1
