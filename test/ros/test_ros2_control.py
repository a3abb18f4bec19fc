"""ros2_control controllers against sim_node through topic_based_ros2_control, in realtime
mode, as launch/starleth_ros2_control.launch.xml starts them: sim_node with its
parameters there, and a stand-in for its ros2_control_node and spawner
(test/support/ros2_control_stand_in.py: the hardware TopicBasedSystem, the sim-time control loop
and a forward_command_controller, as their sources do it) that loads the <ros2_control>
section from the robot_description sim_node publishes and the controllers of the parameter
file the launch file gives (config/starleth_controllers.yaml: update rate, the forward
position controller). A user drives the robot through forward_position_controller/commands:
standing, then a squat. sim_node takes every command the hardware sends, the loop runs once
per sim_node step, and the robot follows within the static error its load makes at kp.

sim_node runs as a child process on an isolated ROS_DOMAIN_ID; every wait is bounded."""
import os
import threading
import time

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip("rclpy")

from launch_file import ROS2_CONTROL_LAUNCH_FILE, launch_nodes
from nav_msgs.msg import Odometry
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile
from ros2_control_stand_in import (
    ForwardCommandController,
    SimTimeControlLoop,
    TopicBasedSystem,
    parse_ros2_control,
    spawner_arguments,
)
from ros_test_nodes import NodeProcess, RosTestNode
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import SetBool

from starleth_sim.physics.description import leg_angles_for_height
from starleth_sim.physics.simulator import Simulator
from starleth_sim.ros.qos import STATE_QOS
from starleth_sim.ros.state_io import parse_initial_state

DOMAIN_RANGE = (229, 4)        # first, span (conftest._free_ros_domain)
DOMAIN_ID = 229 + os.getpid() % 4
START_TIMEOUT = 120.0
KP, KD = 80.0, 2.0             # sim_node's default gains
PERIOD = 0.0025                # s: sim_node's control period (HmJ: one physics step)
SQUAT_HEIGHT = 0.35            # m: the squat's trunk height (standing: 0.415)
# sim time [s] of the phases from the hardware's first command: its initial commands hold
# the posture (as sim_node held it before: realtime_start hold); the user moves the targets
# to the squat (50 Hz, cosine); holds them
SETTLED = 1.0                  # s of sim time: the robot at rest under sim_node's hold
RAMP = (0.3, 0.8)
END = 1.5
WINDOWS = {"stand": (0.05, 0.3), "squat": (1.2, END)}


def squat_targets(sim, q0):
    """The targets of the squat: HFE and KFE of every leg for a trunk at SQUAT_HEIGHT (the
    front leg's angles, mirrored on the hind legs as the standing posture is), HAA kept."""
    hfe, kfe = leg_angles_for_height(SQUAT_HEIGHT, sim.description)
    q = q0.copy()
    for j, name in enumerate(sim.joint_names):
        if name.endswith("HFE"):
            q[j] = np.sign(q0[j]) * abs(hfe)
        elif name.endswith("KFE"):
            q[j] = np.sign(q0[j]) * abs(kfe)
    return q


class User:
    """Sends forward_position_controller/commands at 50 Hz of sim time (on the states'
    stamps), the times counted from t0 (sim time [s], set by the test): nothing before RAMP
    (the hardware holds its initial commands), then targets moving from q0 to q1 on a
    cosine, then q1. Records every state and base height from t0 on."""

    def __init__(self, node, q0, q1):
        self.q0, self.q1 = q0, q1
        self.t0 = None
        self.sim_time = -1.0
        self.pub = node.create_publisher(Float64MultiArray, "forward_position_controller/commands",
                                         10)
        self.states, self.heights, self.sent = [], [], []
        self.last_sent = -1
        self.subs = [node.create_subscription(JointState, "joint_states", self.on_state,
                                              STATE_QOS),
                     node.create_subscription(Odometry, "starleth/base_state", self.on_base,
                                              STATE_QOS)]

    def targets(self, t):
        s = np.clip((t - RAMP[0]) / (RAMP[1] - RAMP[0]), 0.0, 1.0)
        return self.q0 + (self.q1 - self.q0) * 0.5 * (1.0 - np.cos(np.pi * s))

    def since_t0(self, stamp):
        return None if self.t0 is None else stamp.sec + stamp.nanosec * 1e-9 - self.t0

    def on_state(self, msg):
        self.sim_time = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        t = self.since_t0(msg.header.stamp)
        if t is None:
            return
        self.states.append((t, np.array(msg.position), np.array(msg.velocity),
                            np.array(msg.effort)))
        tick = int(round(t * 1e9)) // 20_000_000          # (t0 is a whole period)
        if t >= RAMP[0] and tick != self.last_sent:
            self.last_sent = tick
            q = self.targets(t)
            self.sent.append((t, q))
            self.pub.publish(Float64MultiArray(data=[float(v) for v in q]))

    def on_base(self, msg):
        t = self.since_t0(msg.header.stamp)
        if t is not None:
            self.heights.append((t, msg.pose.pose.position.z))


def wait_for(cond, timeout, sim):
    """Wait (the executor spins on its thread) until cond() or timeout; sim must live."""
    t_end = time.monotonic() + timeout
    while not cond():
        assert sim.alive(), sim.log()[-3000:]
        if time.monotonic() > t_end:
            return False
        time.sleep(0.01)
    return True


@pytest.fixture
def stand_in():
    """The test's node (on sim time) spinning on a thread: the ros2_control_node stand-in
    and the user."""
    ros = RosTestNode(DOMAIN_ID, "ros2_control_stand_in")
    ros.node.set_parameters([Parameter("use_sim_time", Parameter.Type.BOOL, True)])
    thread = threading.Thread(target=ros.executor.spin, daemon=True)
    thread.start()
    try:
        yield ros
    finally:
        ros.executor.shutdown(timeout_sec=1.0)
        thread.join(5.0)
        ros.close()


def stand_in_for(launch, node, description):
    """The ros2_control_node of `launch` (launch_nodes) on `node`: the hardware of the
    <ros2_control> section of `description`, the forward command controllers the spawner
    activates, configured from the parameter file ros2_control_node gets, and its loop at
    that file's update_rate. (hardware, loop)"""
    cm = next(n for n in launch if n["exec"] == "ros2_control_node")
    spawner = spawner_arguments(next(n for n in launch if n["exec"] == "spawner")["args"])
    assert "use_sim_time:=true" in cm["ros_args"] and not spawner.inactive
    params_file = cm["ros_args"][cm["ros_args"].index("--params-file") + 1]
    assert spawner.param_file == [params_file]
    with open(params_file) as f:
        config = yaml.safe_load(f)
    manager = config["/**/controller_manager"]["ros__parameters"]
    (info,) = parse_ros2_control(description)
    hardware = TopicBasedSystem(node, info)
    controllers = []
    for name in spawner.controller_names:
        if manager[name]["type"] == "forward_command_controller/ForwardCommandController":
            controllers.append(ForwardCommandController(
                node, name, config[f"/**/{name}"]["ros__parameters"], hardware))
        else:       # the broadcaster only reads the state interfaces
            assert manager[name]["type"] == "joint_state_broadcaster/JointStateBroadcaster"
    assert len(controllers) == 1
    return hardware, SimTimeControlLoop(node, hardware, controllers, manager["update_rate"])


def check_section(info, sim, q0):
    """The section sim_node published: TopicBasedSystem on every joint of the robot, with
    the launch file's command interfaces, and the initial posture as initial values."""
    assert info.plugin == "topic_based_ros2_control/TopicBasedSystem"
    assert [j.name for j in info.joints] == list(sim.joint_names)
    for j, joint in enumerate(info.joints):
        assert [c.name for c in joint.command_interfaces] == ["position", "velocity", "effort"]
        assert [s.name for s in joint.state_interfaces] == ["position", "velocity", "effort"]
        assert float(joint.state_interfaces[0].initial_value) == q0[j]


def call_pause(node, sim, paused):
    """~/pause of sim_node with data=paused, which must succeed."""
    client = node.create_client(SetBool, "/sim_node/pause")
    assert client.wait_for_service(timeout_sec=10.0)
    fut = client.call_async(SetBool.Request(data=paused))
    assert wait_for(fut.done, 10.0, sim) and fut.result().success
    node.destroy_client(client)


@pytest.mark.serial   # realtime, 400 ticks/s: the Python stand-in keeps up when alone
def test_forward_position_controller_through_topic_based_ros2_control(stand_in, tmp_path):
    """launch/starleth_ros2_control.launch.xml with controller:=forward_position_controller:
    sim_node as it starts it, the stand-in as its ros2_control_node and spawner set up."""
    node = stand_in.node
    sim_ref = Simulator.from_preset("HmJ")
    sim_ref.reset(*parse_initial_state("standing", sim_ref)[:2])
    q0 = sim_ref.joint_positions().copy()
    q1 = squat_targets(sim_ref, q0)
    launch = launch_nodes(ROS2_CONTROL_LAUNCH_FILE, controller="forward_position_controller")
    sim_spec = next(n for n in launch if n["exec"] == "sim_node")
    description = []
    node.create_subscription(String, "robot_description", lambda m: description.append(m.data),
                             QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    user = User(node, q0, q1)
    sim = NodeProcess(sim_spec["module"], str(tmp_path / "sim.log"), DOMAIN_ID,
                      ros_args=sim_spec["ros_args"])
    loop = None
    try:
        assert wait_for(lambda: description, START_TIMEOUT, sim), sim.log()[-2000:]
        hardware, loop = stand_in_for(launch, node, description[0])
        check_section(hardware.info, sim_ref, q0)
        # sim_node runs already, holding the initial posture: once the robot has settled
        # under that hold, the hardware takes over
        assert wait_for(lambda: user.sim_time >= SETTLED, 60.0, sim), sim.log()[-2000:]
        loop.start()
        assert wait_for(lambda: hardware.published, 30.0, sim)
        user.t0 = hardware.published[0][0] * 1e-9
        assert wait_for(lambda: user.states and user.states[-1][0] >= END, 60.0, sim), \
            (user.states[-1][0] if user.states else None, sim.log()[-2000:])
        loop.stop()
        call_pause(node, sim, True)
    finally:
        if loop is not None:
            loop.stop()
        code = sim.stop()
    assert code == 0, sim.log()[-2000:]
    summary = sim.summary()
    print(f"loop: {loop.cycles} cycles, {loop.writes} writes; sim_node: "
          f"{summary['steps']} steps, received {summary['commands_received']}, accepted "
          f"{summary['commands_accepted']}, rejected {summary['commands_rejected']}")
    check_commands(hardware, loop, summary)
    check_tracking(user, sim_ref, q0, q1)


def check_commands(hardware, loop, summary):
    """What the hardware sent: one JointState per cycle (threshold -1), each naming every
    joint of the section in its order with 12 positions, velocities and efforts, stamped
    with sim time; sim_node took every one as an impedance command; the loop runs once per
    sim_node step (update_rate = the control rate, on /clock)."""
    names = [j.name for j in hardware.info.joints]
    sent = hardware.published
    assert loop.writes == loop.cycles == len(sent)
    for _stamp, msg in sent:
        assert list(msg.name) == names
        assert len(msg.position) == len(msg.velocity) == len(msg.effort) == len(names)
    stamps = np.array([s for s, _ in sent])
    assert stamps[-1] < 600e9                                       # sim time, not wall
    period_ns = round(PERIOD * 1e9)
    # one cycle per /clock tick at most, on the tick: stamps on whole control periods,
    # strictly increasing. (The stand-in, Python beside the test's subscriptions, misses
    # ticks on a loaded host, which the C++ loop would not; sim_node holds the last
    # command then.)
    assert (stamps % period_ns == 0).all() and (np.diff(stamps) > 0).all()
    ticks = (stamps[-1] - stamps[0]) // period_ns + 1
    print(f"commands on {len(sent)} of {ticks} ticks")
    assert len(sent) >= 0.3 * ticks
    assert summary["commands_rejected"] == 0
    assert summary["commands_accepted"] == summary["impedance_commands"]
    # reliable, depth 1: a command may be replaced by the next before sim_node takes it
    assert summary["commands_accepted"] >= 0.8 * len(sent)


def leg_reach(desc):
    """Distance from the HAA, HFE and KFE axes to the foot's contact point at full
    stretch [m] (the model's hip offset, thigh and shank, foot radius): the longest lever
    a foot force has on each joint."""
    m = desc.model
    l0 = -m.jointPlacements[m.getJointId("LF_HFE")].translation[2]
    l1 = -m.jointPlacements[m.getJointId("LF_KFE")].translation[2]
    foot = next(c for c in desc.contacts if c.name == "LF_foot")
    l2 = -foot.local[2] + foot.radius
    return {"HAA": l0 + l1 + l2, "HFE": l1 + l2, "KFE": l2}


def trunk_height_of(sim, q):
    """The trunk height at which the feet of a level trunk with joints q touch flat ground:
    minus the mean gap of the feet with the base at the origin."""
    q_sim, u_sim, _ = parse_initial_state({"base_position": [0.0, 0.0, 0.0],
                                           "joint_positions": [float(v) for v in q]}, sim)
    sim.reset(q_sim, u_sim)
    return -float(np.mean(sim.gaps()[:4]))


def check_tracking(user, sim, q0, q1):
    """Standing on the hardware's initial commands (at rest: sim_node held the same
    targets before them), then squatting on the forward controller's: each joint's static
    error is its load torque over kp (q* - q = tau / kp, tau the torque sim_node applied:
    the targets it tracked are those the controller wrote), within the bound of the load
    (the robot's weight shared by four feet, at the longest lever of the joint:
    m g / 4 x reach / kp); the trunk height is the legs' at the measured joints and drops
    by the squat's height."""
    weight = sim.description.total_mass * 9.81
    reach = leg_reach(sim.description)
    bound = np.array([weight / 4 * reach[n[-3:]] / KP for n in sim.joint_names])
    heights = {}
    for name, target in (("stand", q0), ("squat", q1)):
        lo, hi = WINDOWS[name]
        rows = [s for s in user.states if lo <= s[0] <= hi]
        assert len(rows) > 0.5 * (hi - lo) * 400, (name, len(rows))    # (a loaded host)
        q, qd, tau = (np.array([r[i] for r in rows]) for i in (1, 2, 3))
        error = target - q
        assert np.abs(qd).max() < 0.1, (name, np.abs(qd).max())         # settled
        if name == "stand":     # sim_node's hold handed over to the same targets: at rest
            assert np.abs(q - q.mean(axis=0)).max() < 1e-4
        # the law at the step into t_k: tau = kp (q* - q(t_k-1)) - kd qd(t_k), and
        # q(t_k) - q(t_k-1) = qd dt
        residual = np.abs(error - (tau + KD * qd) / KP).max()
        assert residual < np.abs(qd).max() * PERIOD + 1e-4, (name, residual)
        assert (np.abs(error) <= bound).all(), (name, np.abs(error).max(axis=0), bound)
        z = np.array([h for t, h in user.heights if lo <= t <= hi])
        assert len(z) > 0.5 * (hi - lo) * 400
        legs = trunk_height_of(sim, q.mean(axis=0))
        assert abs(z.mean() - legs) < 3e-3, (name, z.mean(), legs)
        heights[name] = z.mean()
        print(f"{name}: error {np.round(np.abs(error).max(axis=0)[:3], 4)} rad "
              f"(bound {np.round(bound[:3], 3)}), residual {residual:.2e}, "
              f"z {z.mean():.4f} m (legs {legs:.4f})")
    drop = trunk_height_of(sim, q0) - trunk_height_of(sim, q1)
    assert abs((heights["stand"] - heights["squat"]) - drop) < 0.01, (heights, drop)
