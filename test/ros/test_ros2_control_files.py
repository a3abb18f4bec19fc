"""The ros2_control files the package ships, checked without ros2_control (no node starts
here): the <ros2_control> section (urdf/starleth_ros2_control.xml, and sim_node's
robot_description with ros2_control_command_interfaces) names exactly the URDF's actuated
joints with interfaces sim_node serves; what TopicBasedSystem sends for each choice of
command interfaces is a command sim_node takes, with the meaning the docs give it;
config/<robot>_controllers.yaml, generated for every library robot, names real Jazzy
controller types and parameters, exactly the robot's URDF's actuated joints and interfaces of
its section; launch/starleth_ros2_control.launch.xml starts only sim_node and ros2_control's
programs, with parameters and spawner options they have, and the robot's controllers file;
for Go1 a forward controller of that file drives the hardware of Go1's section, and sim_node
takes what it sends.
test_ros2_control.py runs the whole path with ROS nodes."""
import io
import itertools
import os
import xml.etree.ElementTree as ET
from contextlib import redirect_stdout
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

pytest.importorskip("rclpy")

from launch_file import ROS2_CONTROL_LAUNCH_FILE, launch_arguments, launch_nodes
from rclpy.time import Time
from repo_root import ROOT
from ros2_control_stand_in import (
    ForwardCommandController,
    HardwareInfo,
    TopicBasedSystem,
    parse_ros2_control,
    spawner_arguments,
)
from std_msgs.msg import Float64MultiArray

from starleth_controller.model import RobotModel
from starleth_interface.ros_helpers import ROS_PARAMETERS
from starleth_interface.topics import (
    TOPIC_EFFORT_COMMANDS,
    TOPIC_JOINT_COMMANDS,
    TOPIC_JOINT_STATES,
    TOPIC_POSITION_COMMANDS,
    TOPIC_VELOCITY_COMMANDS,
)
from starleth_sim.physics.config import ConfigError
from starleth_sim.physics.description import RobotDescription, urdf_path
from starleth_sim.physics.simulator import Simulator
from starleth_sim.robots import available_robots, robot_urdf
from starleth_sim.ros import ros2_control_controllers as rcc
from starleth_sim.ros import ros2_control_description as rcd
from starleth_sim.ros.parameters import SIM_NODE_PARAMETERS, Settings
from starleth_sim.ros.service import SimService
from starleth_sim.ros.state_io import parse_initial_state
from starleth_sim.tools.analysis.summary import urdf_info

SECTION_FILE = os.path.join(ROOT, "urdf", "starleth_ros2_control.xml")
CONFIG_DIR = os.path.join(ROOT, "config")
ROBOTS = available_robots()
# What ROS 2 Jazzy's ros2_control has (controller_manager's, forward_command_controller's,
# joint_state_broadcaster's and joint_trajectory_controller's parameter definitions and
# plugin descriptions, ros2_control 4.x / ros2_controllers 4.x): the types and parameter
# names a controllers file may use. "*" stands for a joint name.
CONTROLLER_PARAMETERS = {
    "forward_command_controller/ForwardCommandController": {"joints", "interface_name"},
    "joint_state_broadcaster/JointStateBroadcaster": {
        "use_local_topics", "joints", "extra_joints", "interfaces",
        "map_interface_to_joint_state.position", "map_interface_to_joint_state.velocity",
        "map_interface_to_joint_state.effort", "use_urdf_to_filter", "frame_id",
        "publish_dynamic_joint_states"},
    "joint_trajectory_controller/JointTrajectoryController": {
        "joints", "command_joints", "command_interfaces", "state_interfaces",
        "speed_scaling.initial_scaling_factor", "speed_scaling.state_interface",
        "speed_scaling.command_interface", "allow_partial_joints_goal", "open_loop_control",
        "interpolate_from_desired_state", "allow_integration_in_goal_trajectories",
        "set_last_command_interface_value_as_state_on_activation", "action_monitor_rate",
        "interpolation_method", "allow_nonzero_velocity_at_trajectory_end", "cmd_timeout",
        "constraints.stopped_velocity_tolerance", "constraints.goal_time",
        "constraints.decelerate_on_cancel", "constraints.*.trajectory", "constraints.*.goal",
        "constraints.*.max_deceleration_on_cancel", "gains.*.p", "gains.*.i", "gains.*.d",
        "gains.*.i_clamp_max", "gains.*.i_clamp_min", "gains.*.ff_velocity_scale"},
}
CONTROLLER_MANAGER_PARAMETERS = {"update_rate", "enforce_command_limits", "handle_exceptions",
                                 "use_sim_time"}
#: joint_trajectory_controller's legal command interface sets (its parameter validation)
JTC_COMMAND_INTERFACES = [["position"], ["position", "velocity"],
                          ["position", "velocity", "acceleration"], ["velocity"], ["effort"],
                          ["position", "effort"]]


def flat_keys(d, prefix=""):
    """The dotted names of a ROS parameter mapping's leaves (lists are values)."""
    for k, v in d.items():
        if isinstance(v, dict):
            yield from flat_keys(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}"


def urdf_actuated_joints(path=None):
    """The names of the URDF's joints that move (not fixed), in document order (default:
    StarlETH's URDF)."""
    root = ET.parse(path or urdf_path()).getroot()
    return [j.get("name") for j in root.findall("joint") if j.get("type") != "fixed"]


@pytest.fixture(scope="module")
def standing():
    """A simulator at sim_node's initial state ("standing")."""
    sim = Simulator.from_preset("HmJ")
    sim.reset(*parse_initial_state("standing", sim)[:2])
    return sim


def section_info(text) -> HardwareInfo:
    (info,) = parse_ros2_control(f"<robot name='r'>{text}</robot>")
    return info


def test_shipped_section_is_generated():
    """urdf/starleth_ros2_control.xml is the generator's output with its defaults."""
    out = io.StringIO()
    with redirect_stdout(out):
        assert rcd.main([]) == 0
    with open(SECTION_FILE) as f:
        assert f.read() == out.getvalue(), \
            "regenerate: python -m starleth_sim.ros.ros2_control_description > " \
            "urdf/starleth_ros2_control.xml"


def test_section_names_the_urdf_joints_with_interfaces_sim_node_serves(standing):
    """Exactly the URDF's actuated joints, each with the same command interfaces (the
    JointState fields sim_node reads on joint_commands) and the state interfaces of its
    joint_states; the hardware on sim_node's topics, publishing every cycle; initial values
    = the posture sim_node starts in, at rest, without feed-forward."""
    with open(SECTION_FILE) as f:
        info = section_info(f.read())
    assert info.type == "system" and info.plugin == rcd.HARDWARE_PLUGIN
    assert [j.name for j in info.joints] == urdf_actuated_joints() == list(standing.joint_names)
    for j, joint in enumerate(info.joints):
        assert [c.name for c in joint.command_interfaces] == ["position", "velocity", "effort"]
        assert [s.name for s in joint.state_interfaces] == ["position", "velocity", "effort"]
        q0 = standing.joint_positions()[j]
        assert float(joint.state_interfaces[0].initial_value) == q0
        # (ros2_control's own handles start from these; TopicBasedSystem from the state's)
        assert [float(c.initial_value) for c in joint.command_interfaces] == [q0, 0.0, 0.0]
    params = info.hardware_parameters
    assert params["joint_commands_topic"] == TOPIC_JOINT_COMMANDS
    assert params["joint_states_topic"] == TOPIC_JOINT_STATES
    assert float(params["trigger_joint_command_threshold"]) < 0
    assert "sum_wrapped_joint_states" not in params        # sim_node's angles are not wrapped


@pytest.mark.parametrize("robot", ["starleth", "go1", "solo12"])
def test_section_limits_are_the_urdf_limits(robot):
    """Each command interface's min and max: the position range of the joint's URDF
    <limit> tag (read here from the file), velocity and effort symmetric about 0 at the
    limits sim_node's robot has (its spec's over the URDF's: Solo12's URDF says 1000 rad/s,
    its spec 83.8); the initial position within its range."""
    sim = Simulator.from_preset("HmJ", robot=robot)
    sim.reset(*parse_initial_state("standing", sim)[:2])
    info = section_info(rcd.simulator_section(sim))
    tags = {j.get("name"): j.find("limit") for j in ET.parse(robot_urdf(robot)).getroot()
            .findall("joint") if j.get("type") == "revolute"}
    desc = sim.description
    for j, joint in enumerate(info.joints):
        bounds = {c.name: (float(c.min), float(c.max)) for c in joint.command_interfaces}
        tag = tags[joint.name]
        assert bounds["position"] == (float(tag.get("lower")), float(tag.get("upper")))
        lo, hi = bounds["position"]
        assert lo <= float(joint.state_interfaces[0].initial_value) <= hi
        for itf, limit in (("velocity", desc.velocity_limit), ("effort", desc.effort_limit)):
            assert bounds[itf] == (-limit[j], limit[j]) and limit[j] > 0
            if robot == "starleth":         # its URDF has every limit, its spec none
                assert limit[j] == float(tag.get(itf)), (joint.name, itf)


def test_description_with_section_loads_as_before(standing):
    """A URDF with the section is the same robot for every reader of robot_description
    here: the simulator's description, the controller's model, the bag summary."""
    urdf = standing.description.urdf_xml
    full = rcd.with_ros2_control(urdf, rcd.simulator_section(standing))
    assert full.count("<ros2_control") == 1 and ET.fromstring(full).tag == "robot"
    a, b = RobotDescription.from_urdf_xml(urdf), RobotDescription.from_urdf_xml(full)
    assert a.joint_names == b.joint_names and a.total_mass == b.total_mass
    assert RobotModel(full).nq == RobotModel(urdf).nq
    assert urdf_info(full) == urdf_info(urdf)


class StubNode:
    """What TopicBasedSystem needs of a node, without ROS: its messages in `sent`."""

    def __init__(self):
        self.sent = []

    def create_publisher(self, *args, **kw):
        return SimpleNamespace(publish=self.sent.append)

    def create_subscription(self, *args, **kw):
        return None

    def get_clock(self):
        return SimpleNamespace(now=lambda: Time(nanoseconds=7_500_000))


@pytest.fixture(scope="module")
def service(standing):
    q0, u0, _ = parse_initial_state("standing", standing)
    return SimService(standing, Settings(mode="realtime"), q0, u0)


def sent_by_hardware(sim, interfaces, values):
    """The JointState TopicBasedSystem publishes for a section with `interfaces` after a
    controller wrote `values` ({interface: 12 values}) into its command interfaces."""
    info = section_info(rcd.simulator_section(sim, interfaces))
    node = StubNode()
    hw = TopicBasedSystem(node, info)
    for itf, v in values.items():
        hw.commands[itf][:] = list(v)
    assert hw.write()
    (msg,) = node.sent
    return msg


@pytest.mark.parametrize("interfaces", [("position",), ("position", "velocity"),
                                        ("position", "velocity", "effort"), ("effort",),
                                        ("velocity",), ("position", "effort")])
def test_what_the_hardware_sends_is_what_sim_node_takes(standing, service, interfaces):
    """Every joint, every interface the section declares, in the section's order: sim_node
    accepts it; effort alone is a torque command, anything with a position or velocity an
    impedance command tau = effort + kp (position - q) + kd (velocity - qd), a field the
    section does not declare being no term (a velocity: 0 with a position)."""
    n = standing.n_joints
    rng = np.random.default_rng(len(interfaces))
    values = {"position": standing.joint_positions() + rng.uniform(-0.1, 0.1, n),
              "velocity": rng.uniform(-1, 1, n), "effort": rng.uniform(-5, 5, n)}
    msg = sent_by_hardware(standing, interfaces, values)
    assert list(msg.name) == list(standing.joint_names)
    assert msg.header.stamp.nanosec == 7_500_000
    ok, why = service.submit_joint_command(msg.name, msg.effort, None, position=msg.position,
                                           velocity=msg.velocity)
    assert ok, why
    command = service.command
    if interfaces == ("effort",):
        np.testing.assert_array_equal(command, values["effort"])
        return
    expect = {"position": values["position"] if "position" in interfaces else np.nan,
              "velocity": values["velocity"] if "velocity" in interfaces else
              (0.0 if "position" in interfaces else np.nan),
              "effort": values["effort"] if "effort" in interfaces else np.nan}
    for field, v in expect.items():
        np.testing.assert_array_equal(getattr(command, field), np.broadcast_to(v, n), field)
    np.testing.assert_array_equal(command.kp, 80.0)


def test_joints_with_different_command_interfaces_are_rejected(standing, service):
    """TopicBasedSystem puts one value per joint that declares an interface: joints with
    different interfaces give fields that do not line up with the names, which sim_node
    rejects (one line) instead of guessing; hence the same interfaces on every joint."""
    text = rcd.simulator_section(standing, ("effort",)).replace(
        '<command_interface name="effort">', '<command_interface name="position">', 1)
    node = StubNode()
    TopicBasedSystem(node, section_info(text)).write()
    (msg,) = node.sent
    assert len(msg.position) == 1 and len(msg.effort) == standing.n_joints - 1
    ok, why = service.submit_joint_command(msg.name, msg.effort, None, position=msg.position,
                                           velocity=msg.velocity)
    assert not ok and "12 joints but 1 position values" in why


def test_the_threshold_keeps_the_hardware_publishing(standing):
    """TopicBasedSystem skips a cycle when its position commands equal the joint positions
    within trigger_joint_command_threshold in sum (default 1e-5): at the initial posture,
    before any state, it sends nothing; the section's -1 sends every cycle."""
    text = rcd.simulator_section(standing)
    default = text.replace('<param name="trigger_joint_command_threshold">-1</param>', "")
    assert default != text
    for section, publishes in ((default, False), (text, True)):
        node = StubNode()
        assert TopicBasedSystem(node, section_info(section)).write() is publishes
        assert len(node.sent) == int(publishes)


def test_the_parameter_is_checked():
    """ros2_control_command_interfaces: a subset of position, velocity, effort (empty:
    none), in realtime mode only; anything else names the parameter."""
    assert Settings(ros2_control_command_interfaces=" effort, position").validate()
    assert rcd.parse_command_interfaces("effort, position") == ("position", "effort")
    for bad in ("torque", "position,position", ",", "position;velocity"):
        with pytest.raises(ConfigError, match="parameter ros2_control_command_interfaces"):
            Settings(ros2_control_command_interfaces=bad).validate()
    with pytest.raises(ConfigError, match="needs realtime mode"):
        Settings(mode="lockstep", ros2_control_command_interfaces="position").validate()


def controllers_file(robot="starleth"):
    return os.path.join(CONFIG_DIR, f"{robot}_controllers.yaml")


def controllers(robot="starleth"):
    with open(controllers_file(robot)) as f:
        return yaml.safe_load(f)


def test_shipped_controllers_files_are_generated():
    """config/ holds a controllers file for every library robot, and each is the
    generator's output for that robot."""
    shipped = sorted(f[:-len("_controllers.yaml")] for f in os.listdir(CONFIG_DIR)
                     if f.endswith("_controllers.yaml"))
    assert shipped == ROBOTS
    for robot in ROBOTS:
        out = io.StringIO()
        with redirect_stdout(out):
            assert rcc.main(["--robot", robot]) == 0
        with open(controllers_file(robot)) as f:
            assert f.read() == out.getvalue(), f"regenerate: make ros2-control-configs ({robot})"


@pytest.mark.parametrize("tool", [rcc.main, rcd.main])
@pytest.mark.parametrize("robot", ["go7", "robots/nowhere.urdf"])
def test_a_bad_robot_is_one_line(tool, robot, capsys):
    """Both generators: an unknown robot is one line naming the field, exit status 2."""
    assert tool(["--robot", robot]) == 2
    out = capsys.readouterr()
    assert out.out == "" and out.err.count("\n") == 1 and out.err.startswith("error: robot: ")


@pytest.mark.parametrize("robot", ROBOTS)
def test_controllers_file_names_real_types_parameters_joints_and_interfaces(robot):
    """Every controller: a Jazzy type, its parameters among that type's, its joints exactly
    the actuated joints of the robot's URDF (read here from the file) as the section of
    sim_node's robot_description names them, the interfaces it claims declared there (the
    JTC's a legal set); the manager's loop at sim_node's control rate; no controller on a
    topic sim_node serves itself; the broadcaster off sim_node's joint_states."""
    sim = Simulator.from_preset("HmJ", robot=robot)
    config = controllers(robot)
    manager = config["/**/controller_manager"]["ros__parameters"]
    assert manager["update_rate"] == round(1.0 / sim.control_period)
    names = {k for k, v in manager.items() if isinstance(v, dict)}
    assert set(flat_keys(manager)) - {f"{n}.type" for n in names} <= \
        CONTROLLER_MANAGER_PARAMETERS
    assert set(config) == {"/**/controller_manager"} | {f"/**/{n}" for n in names}
    own_topics = {t.split("/")[0] for t in (TOPIC_EFFORT_COMMANDS, TOPIC_POSITION_COMMANDS,
                                            TOPIC_VELOCITY_COMMANDS)}
    assert not names & own_topics
    info = section_info(rcd.simulator_section(sim))
    assert [j.name for j in info.joints] == urdf_actuated_joints(robot_urdf(robot))
    declared = {j.name: {c.name for c in j.command_interfaces} for j in info.joints}
    states = {j.name: {s.name for s in j.state_interfaces} for j in info.joints}
    for name in names:
        kind = manager[name]["type"]
        params = config[f"/**/{name}"]["ros__parameters"]
        keys = {".".join("*" if p in declared else p for p in k.split("."))
                for k in flat_keys(params)}
        assert keys <= CONTROLLER_PARAMETERS[kind], (name, keys - CONTROLLER_PARAMETERS[kind])
        joints = params.get("joints", [])
        assert joints in ([], list(declared)), name
        claimed = [params["interface_name"]] if "interface_name" in params else \
            params.get("command_interfaces", [])
        assert all(set(claimed) <= declared[j] for j in joints), name
        assert all(set(params.get("state_interfaces", [])) <= states[j] for j in joints)
    jtc = config["/**/joint_trajectory_controller"]["ros__parameters"]
    assert jtc["command_interfaces"] in JTC_COMMAND_INTERFACES
    assert config["/**/joint_state_broadcaster"]["ros__parameters"]["use_local_topics"]


def sim_node_parameters(ros_args):
    """{name: value} of the -p arguments, each value read as YAML (as rcl reads it)."""
    out = {}
    for flag, arg in itertools.pairwise(ros_args):
        if flag == "-p":
            name, value = arg.split(":=", 1)
            out[name] = yaml.safe_load(value)
    return out


@pytest.mark.parametrize("arguments", [{}, {"namespace": "robot1"},
                                       {"controller": "forward_position_controller"},
                                       {"controller": "forward_effort_controller",
                                        "command_interfaces": "position,effort"},
                                       {"robot": "go1"}])
def test_launch_file_starts_sim_node_and_ros2_control(arguments):
    """sim_node in realtime with the section, its parameters real and legal;
    ros2_control_node with the controllers file on sim time; the spawner with options it
    has, activating the broadcaster and a controller of the file; every node in the
    namespace, on the robot's clock."""
    nodes = {n["exec"]: n for n in launch_nodes(ROS2_CONTROL_LAUNCH_FILE, **arguments)}
    assert set(nodes) == {"sim_node", "ros2_control_node", "spawner"}
    ns = arguments.get("namespace", "")
    assert all(n["namespace"] == (f"/{ns}" if ns else "") for n in nodes.values())
    sim = sim_node_parameters(nodes["sim_node"]["ros_args"])
    known = {p.name for p in SIM_NODE_PARAMETERS} | set(ROS_PARAMETERS)
    assert set(sim) <= known and sim["use_sim_time"] is True
    settings = Settings(**{k: v for k, v in sim.items() if k not in ROS_PARAMETERS})
    assert settings.validate().mode == "realtime"
    assert rcd.parse_command_interfaces(settings.ros2_control_command_interfaces)
    cm = nodes["ros2_control_node"]["ros_args"]
    assert set(sim_node_parameters(cm)) <= CONTROLLER_MANAGER_PARAMETERS
    assert sim_node_parameters(cm)["use_sim_time"] is True
    params_file = cm[cm.index("--params-file") + 1]
    robot = arguments.get("robot", "starleth")
    assert sim["robot"] == robot
    assert os.path.samefile(params_file, controllers_file(robot))
    for node in nodes.values():
        assert "/clock:=clock" in node["ros_args"] or node["exec"] == "spawner"
    spawner = spawner_arguments(nodes["spawner"]["args"])
    assert spawner.param_file == [params_file] and not spawner.inactive
    manager = controllers(robot)["/**/controller_manager"]["ros__parameters"]
    assert spawner.controller_names[0] == "joint_state_broadcaster"
    assert spawner.controller_names[1] == arguments.get("controller",
                                                        "joint_trajectory_controller")
    assert all(n in manager for n in spawner.controller_names)
    # the controller's interfaces are in the section
    params = controllers(robot)[f"/**/{spawner.controller_names[1]}"]["ros__parameters"]
    claimed = [params["interface_name"]] if "interface_name" in params else \
        params["command_interfaces"]
    assert set(claimed) <= set(settings.ros2_control_command_interfaces.split(","))
    assert launch_arguments(ROS2_CONTROL_LAUNCH_FILE)["command_interfaces"] == \
        ",".join(rcd.DEFAULT_COMMAND_INTERFACES)



def test_go1_forward_position_controller_drives_sim_node_through_the_hardware():
    """The stand-in path for Go1, without nodes: the launch file with robot:=go1 gives
    sim_node the robot and ros2_control_node Go1's controllers file; the hardware of the
    section sim_node publishes for Go1 and forward_position_controller configured from that
    file: after a command on the controller's topic and one cycle, the hardware sends every
    Go1 joint (its URDF's) with the commanded positions, which sim_node takes as targets."""
    launch = launch_nodes(ROS2_CONTROL_LAUNCH_FILE, robot="go1",
                          controller="forward_position_controller")
    args = sim_node_parameters(next(n for n in launch if n["exec"] == "sim_node")["ros_args"])
    sim = Simulator.from_preset(args["physics"], robot=args["robot"])
    q0, u0, _ = parse_initial_state("standing", sim)
    sim.reset(q0, u0)
    service = SimService(sim, Settings(mode="realtime", robot=args["robot"]), q0, u0)
    cm = next(n for n in launch if n["exec"] == "ros2_control_node")["ros_args"]
    with open(cm[cm.index("--params-file") + 1]) as f:
        config = yaml.safe_load(f)
    interfaces = rcd.parse_command_interfaces(args["ros2_control_command_interfaces"])
    node = StubNode()
    hardware = TopicBasedSystem(node, section_info(rcd.simulator_section(sim, interfaces)))
    controller = ForwardCommandController(
        node, "forward_position_controller",
        config["/**/forward_position_controller"]["ros__parameters"], hardware)
    target = sim.joint_positions() + np.random.default_rng(1).uniform(-0.1, 0.1, sim.n_joints)
    controller._on_command(Float64MultiArray(data=[float(v) for v in target]))
    controller.update()
    assert hardware.write()
    (msg,) = node.sent
    assert list(msg.name) == urdf_actuated_joints(robot_urdf("go1")) == list(sim.joint_names)
    ok, why = service.submit_joint_command(msg.name, msg.effort, None, position=msg.position,
                                           velocity=msg.velocity)
    assert ok, why
    np.testing.assert_array_equal(service.command.position, target)
    np.testing.assert_array_equal(service.command.velocity, 0.0)
    np.testing.assert_array_equal(service.command.effort, 0.0)
