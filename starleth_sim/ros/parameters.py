"""The parameters of ``sim_node``: one schema (:data:`SIM_NODE_PARAMETERS`) gives each
parameter's type, default, bounds and description. It feeds the node's
``declare_parameter`` descriptors (``ros2 param describe /sim_node mode``), the validation of
:class:`Settings`, and ``msg_configs/sim_node.yaml``, which is generated from it:

    python -m starleth_sim.ros.parameters > msg_configs/sim_node.yaml

(test/ros/test_sim_service.py checks that the file is up to date).
"""
from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass, make_dataclass

from starleth_interface.package_data import package_share_dir
from starleth_interface.robot.scaling import robot_scale
from starleth_interface.ros_helpers import (
    CPU_SCHEDULING,
    CPU_SCHEDULING_HELP,
    EXECUTORS,
    ROS_PARAMETERS,
    ParameterSpec,
    parameter_defaults,
    render_parameters_yaml,
    unknown_parameters_text,
    with_parameter_table,
)
from starleth_interface.yaml_files import load_yaml_file, load_yaml_text

from ..physics.config import ConfigError
from .command_delay import MAX_COMMAND_DELAY
from .ros2_control_description import INTERFACES, parse_command_interfaces

P = ParameterSpec


@dataclass(frozen=True)
class GainSpec(ParameterSpec):
    """A gain of the joints: one number for every joint, or one per joint (a list, in
    joint order; its length is checked against the robot's joints by SimService), each
    finite and >= 0. Settable while the node runs (read_only False)."""

    read_only: bool = False

    def range_text(self) -> str:
        return f">= 0 and <= {self.maximum:g}: one number for every joint, or a list of one " \
               "per joint in joint order"

    def coerce(self, value):
        # a list as rclpy hands it over: a list, or an array('d') / array('q') from a
        # parameter message (ros2 param set, the command line)
        if not isinstance(value, (str, bytes)) and hasattr(value, "__iter__"):
            return [float(v) if isinstance(v, int) and not isinstance(v, bool) else v
                    for v in value]
        if isinstance(value, int) and not isinstance(value, bool):
            return float(value)
        return value

    def check(self, value):
        values = value if isinstance(value, list) else [value]
        if not values or not all(isinstance(v, float) and math.isfinite(v)
                                 and 0.0 <= v <= self.maximum for v in values):
            raise ValueError(f"parameter {self.name}: must be {self.range_text()}, got "
                             f"{value!r}")


@dataclass(frozen=True)
class InterfaceListSpec(ParameterSpec):
    """A string naming joint interfaces: empty, or a comma-separated list of position,
    velocity, effort, each at most once."""

    def range_text(self) -> str:
        return f"empty (none) or a comma-separated list of {', '.join(INTERFACES)}"

    def check(self, value):
        super().check(value)
        try:
            parse_command_interfaces(value, f"parameter {self.name}")
        except ConfigError as e:
            raise ValueError(str(e)) from None


def frame_name_problem(name: str, empty_ok: bool = False) -> str:
    """Why `name` cannot be (the start of) a TF frame id, or '' if it can: tf2 refuses a
    leading '/', and a frame id is one word (no white space)."""
    if not name:
        return "" if empty_ok else "must not be empty"
    if name.startswith("/"):
        return "must not start with '/' (tf2 refuses such frame ids)"
    if any(c.isspace() for c in name):
        return "must not contain white space"
    return ""


@dataclass(frozen=True)
class FrameSpec(ParameterSpec):
    """A TF frame name (with `empty_ok` or empty), or with `prefix` the start of one (may be
    empty)."""

    prefix: bool = False
    empty_ok: bool = False

    def range_text(self) -> str:
        return ("empty, or the start of a frame name" if self.prefix else
                "empty, or a frame name" if self.empty_ok else "a frame name") + \
            ": not starting with '/', no white space"

    def check(self, value):
        super().check(value)
        problem = frame_name_problem(value, empty_ok=self.prefix or self.empty_ok)
        if problem:
            raise ValueError(f"parameter {self.name}: {problem}, got {value!r}")


SIM_NODE_PARAMETERS = (
    P("robot", str, "starleth",
      "The robot: a name of the robot library (robots/*.yaml: starleth, anymal_b, anymal_c, "
      "go1, go2, a1, solo12, hyq, b1; all but starleth need `make robots`), the path of a "
      "robot spec .yaml, or the path of a URDF (its sphere, box and cylinder collisions are "
      "the contacts, its legs found from the tree). Joint, link and foot names on every "
      "topic are the URDF's."),
    P("physics", str, "HmJ",
      "Physics preset in msg_configs/ (the 11 configurations of the paper's Table 1: Cm, HmJ, "
      "HmS, HEJD, HEJP, HESD, HESP, HMJD, HMJP, HMSD, HMSP) or the path of a preset YAML "
      "file."),
    P("sensors", str, "",
      "Sensor models over the preset's (ideal: every measured topic exact): a file of "
      "msg_configs/sensors/ by name (realistic: an ADIS16448-class IMU, 14-bit encoders, "
      "doc/sensors.md) or the path of a YAML file with a sensors: section; empty = the "
      "preset's. With noisy sensors the exact values go out on ground_truth/joint_states, "
      "ground_truth/imu and ground_truth/foot_contacts."),
    P("actuators", str, "",
      "Drive models over the preset's: a file of msg_configs/actuators/ by name or the path "
      "of a YAML file with an actuator: section; empty = the preset's."),
    P("seed", int, -1,
      "The seed of the sensors' one random stream (sensors.seed): a noisy run replays bit "
      "for bit from it (recorded with the physics configuration); -1 = the sensors "
      "configuration's.", minimum=0, maximum=2 ** 63 - 1, off_value=-1,
      off_meaning="the sensors configuration's seed"),
    P("physics_overrides", str, "",
      'Overrides of physics fields, a YAML mapping in a string, e.g. {mu: 0.0, alpha: 0.4}. '
      "On the command line quote it twice, so that ROS reads a string and not a mapping: "
      "-p \"physics_overrides:='{control_rate: 1000.0, mu: 0.5}'\"; in a parameter file: "
      "physics_overrides: '{mu: 0.0}'. The robot is set by the robot parameter, not here."),
    P("mode", str, "realtime",
      "realtime: a wall-clock loop at 400 Hz x real_time_factor, zero-order hold of the "
      "latest valid command. lockstep: publish the state of step k, wait for the command "
      "stamped t_k, then step.", choices=("realtime", "lockstep")),
    P("real_time_factor", float, 1.0,
      "Realtime: wall-clock speed (0.001 to 1000). Lockstep: upper bound on the speed; 0 = "
      "as fast as the controller answers (0 is only legal in lockstep).",
      minimum=0.001, maximum=1000.0, off_value=0.0,
      off_meaning="lockstep: as fast as the controller answers"),
    P("lockstep_timeout", float, 1.0,
      "Lockstep: seconds to wait for the command of a state before applying timeout_policy "
      "(1 ms to 1 hour).", minimum=0.001, maximum=3600.0),
    P("timeout_policy", str, "hold",
      "hold: keep the last valid command; zero: zero torques. Every timeout is logged and "
      "counted.", choices=("hold", "zero")),
    P("record", str, "", "MCAP file to record to (empty = no recording)."),
    P("record_compression", str, "none", "Chunk compression of the recording.",
      choices=("none", "lz4", "zstd")),
    P("record_max_duration", float, 0.0,
      "Split the recording like `ros2 bag record --max-bag-duration`: with this or "
      "record_max_size > 0, `record` names a bag directory of numbered .mcap files (each "
      "complete on its own) with a rosbag2 metadata.yaml, so the memory of an all-day "
      "recording stays flat. Seconds of sim time per file: 0 = no limit (no split by "
      "duration), else 1 s (400 steps at 400 Hz; shorter ones cut a run into thousands "
      "of files) to 1e6 s.",
      minimum=1.0, maximum=1e6, off_value=0.0, off_meaning="no split"),
    P("record_max_size", int, 0,
      "Split the recording like `ros2 bag record --max-bag-size`: bytes per file: 0 = no "
      "limit (no split by size), else at least 1 MiB = 1048576 bytes (smaller ones would "
      "hold a few messages each) and at most 1 TiB.", minimum=1024 ** 2, maximum=1024 ** 4,
      off_value=0, off_meaning="no split"),
    P("max_wrench_force", float, 5000.0,
      "Largest force of a push on ~/wrench or ~/wrench/persistent, newtons; a larger one is "
      "rejected with a warning (StarlETH weighs about 25 kg: 5 kN is 20 g).", minimum=0.0,
      minimum_exclusive=True, maximum=1e6),
    P("max_wrench_torque", float, 1000.0,
      "Largest torque of a push on ~/wrench or ~/wrench/persistent, newton metres; a larger "
      "one is rejected with a warning.", minimum=0.0, minimum_exclusive=True, maximum=1e6),
    P("initial_state", str, "standing",
      '"standing" (feet on the ground), a YAML mapping or the path of a YAML file with any of '
      "base_position, base_orientation (x y z w), joint_positions, base_linear_velocity "
      "(world), base_angular_velocity (base frame), joint_velocities; e.g. "
      '"{base_position: [0, 0, 1.5]}" for the standing posture 1.5 m above the ground. A '
      "recording's initial_state.json is accepted as is."),
    P("start_paused", bool, False,
      "Start paused (call ~/pause with data=false, or ~/step): lets a controller connect "
      "first."),
    P("realtime_start", str, "hold",
      "Realtime mode: hold: physics and /clock run from the start, and until the first valid "
      "command the joints hold the initial posture through the joint impedance law (q* = the "
      "initial joint angles, default_kp, default_kd), as position-controlled drives do at "
      "power-up (again after each ~/reset); controllers on sim-time timers (ros2_control's "
      "controller_manager) run from the start. first_command: the clock starts with the "
      "first valid command (until then the initial state is published, again for each new "
      "subscriber and every 0.5 s, /clock stays at 0 and the robot does not move); "
      "immediately: the clock runs from the start with zero torques until a command (the "
      "robot falls).",
      choices=("hold", "first_command", "immediately")),
    P("realtime_priority", int, 0,
      "Realtime mode: > 0 runs the stepping thread with SCHED_FIFO at this priority (needs "
      "CAP_SYS_NICE or an rtprio limit; falls back to normal priority with a warning). Makes "
      "the 400 Hz period robust against other load on the machine.", minimum=0, maximum=99),
    P("executor", str, "events",
      "events (rclpy's C++ EventsExecutor, lower latency) | single_threaded.",
      choices=EXECUTORS),
    P("cpu_scheduling", str, "default", CPU_SCHEDULING_HELP, choices=CPU_SCHEDULING),
    P("warn_throttle_period", float, 2.0,
      "Minimum seconds between two warnings about the same problem (a kind of bad input "
      "and what it names: the joint, the link, the topic).", minimum=0.0,
      maximum=3600.0),
    FrameSpec("world_frame", str, "world",
      "Frame id of the world (the parent of the base pose), shared by every robot: "
      "tf_frame_prefix is not put before it."),
    FrameSpec("base_frame", str, "",
      "The base link: the root link of the URDF (the floating base; checked at start), the "
      "child frame of the odometry, the frame of the IMU; tf_frame_prefix is put before it. "
      "Empty (the default): the URDF's root link (StarlETH's: base).", empty_ok=True),
    P("publish_clock", bool, True,
      "Publish the sim time on /clock. Several robots in one ROS domain: remap it into each "
      "robot's namespace (--ros-args -r /clock:=clock on both nodes, as the launch file "
      "does), so that each robot's nodes follow its own sim time; without that remap, let "
      "only one simulator publish /clock."),
    P("tf_rate", float, 50.0,
      "/tf (world -> base, and parent -> child link of every movable joint) and /tf_static "
      "(the fixed joints), recorded, and published where tf2_msgs is importable (a ROS "
      "install's, or the one `make venv` generates); Hz, 0 = off. "
      "Foxglove and Lichtblick move the URDF's links only through TF (they keep 10,000 "
      "transforms per frame: 50 Hz x 13 transforms fits); at most 1000 Hz (above the "
      "control rate it is every step).", minimum=0.1, maximum=1000.0, off_value=0.0),
    FrameSpec("tf_frame_prefix", str, "",
      'Put before every frame of the robot (robot_state_publisher\'s frame_prefix): the link '
      "frames of /tf and /tf_static, the odometry's child frame, the IMU's frame; not before "
      'world_frame. "robot1/" for several robots on one /tf (the launch file sets '
      "namespace + '/'). Not derived from the node's namespace (a namespaced node without it "
      "says so at start).", prefix=True),
    P("contact_markers_rate", float, 50.0,
      "visualization_msgs/MarkerArray on starleth/contact_markers: a sphere per contact "
      "point coloured by state (grey open, green stick, red slip) and an arrow along the "
      "force of each closed contact; Hz, 0 = off; at most 1000 Hz.", minimum=0.1,
      maximum=1000.0, off_value=0.0),
    GainSpec("default_kp", float, 80.0,
             "Stiffness kp [N m/rad] of joint position targets: a JointState on "
             "joint_commands with positions, and joint_group_position_controller/commands; "
             "tau = tau_ff + kp (q* - q) + kd (qd* - qd) at every physics step. One number "
             "for every joint or one per joint in joint order; settable at run time (ros2 "
             "param set). At most 1e5 (StarlETH's torques saturate at 20 N m: 0.2 mrad of "
             "error). Not set: 80 for StarlETH, for another robot 80 x mu lambda (its mass and "
             "leg length over StarlETH's: starleth_interface/robot/scaling.py).",
             maximum=1e5),
    GainSpec("default_kd", float, 2.0,
             "Damping kd [N m s/rad] of joint velocity targets (qd* = 0 with a position "
             "target and no velocity), as default_kp; also the gain of "
             "joint_group_velocity_controller/commands. At most 1e3. Not set: 2 for StarlETH, "
             "for another robot 2 x mu lambda^1.5.", maximum=1e3),
    P("command_delay", float, 0.0,
      "Latency of every command, seconds of sim time (a controller's transport and loop "
      "latency on the robot, as Isaac Lab's DelayedPDActuator models it): a command "
      "received while the state of time t is the latest (lockstep: the answer to it) takes "
      "effect at t + command_delay, the command in effect holding until then. On every "
      "command topic: a torque acts late as a whole; an impedance command's targets act "
      "late, its law still acts at every physics step on the current state. A whole number "
      "of control periods (else rounded to the nearest, logged); 0 = none (bit for bit as "
      "without it). Settable at run time (the commands received before keep their time).",
      read_only=False, minimum=0.0, maximum=MAX_COMMAND_DELAY),
    InterfaceListSpec(
        "ros2_control_command_interfaces", str, "",
        "Realtime mode: add a <ros2_control> section to the robot_description this node "
        "publishes (and records), for ros2_control_node with the hardware "
        "topic_based_ros2_control/TopicBasedSystem on this node's joint_commands and "
        "joint_states: every joint with these command interfaces (e.g. "
        "position,velocity,effort: an impedance command with feed-forward torque; effort: "
        "torques), the state interfaces position, velocity and effort, and the initial "
        "position commands = the initial joint positions; empty: no section. See "
        "launch/starleth_ros2_control.launch.xml."),
    P("contact_marker_scale", float, 0.002,
      "Length of the contact force arrows, metres per newton (at most 1 m/N).", minimum=0.0,
      minimum_exclusive=True, maximum=1.0),
    P("live_view", bool, False,
      "Serve every topic sim_node publishes, /tf and /tf_static included, over the Foxglove "
      "WebSocket protocol (open it in Foxglove or Lichtblick). Needs foxglove-sdk (pip "
      "install -r requirements-live.txt); without it, or with the port in use, one error "
      "line and the simulation goes on without the live view."),
    P("live_view_rate", float, 50.0,
      "Live view: Hz (sim time) of the topics served, each at most at its own rate; 0 = "
      "every step (400 Hz: costs the lockstep cycle more, doc/performance.md). /tf keeps "
      "tf_rate; latched topics are always served.", minimum=1.0, maximum=1000.0,
      off_value=0.0, off_meaning="every step"),
    P("live_view_port", int, 8765, "Live view: TCP port of the WebSocket server.", minimum=1,
      maximum=65535),
    P("live_view_host", str, "127.0.0.1",
      "Live view: address to bind (127.0.0.1: this machine only; 0.0.0.0 opens it to the "
      "network)."),
)

#: the parameters settable while the node runs: the gains, by name
GAIN_PARAMETERS = {p.name: p for p in SIM_NODE_PARAMETERS if isinstance(p, GainSpec)}
#: the other one settable while the node runs
COMMAND_DELAY = next(p for p in SIM_NODE_PARAMETERS if p.name == "command_delay")
#: the seed parameter (its off_value: the configuration's seed)
SEED = next(p for p in SIM_NODE_PARAMETERS if p.name == "seed")

YAML_HEADER = """\
Default parameters of sim_node (a ROS 2 parameter file: pass it, or a copy, with
  ros2 run starleth_sim sim_node --ros-args --params-file sim_node.yaml
and override single values with `-p name:=value`). Not a physics preset: the presets are the
YAML files of this directory that have a `contact_model` key.
Generated from starleth_sim/ros/parameters.py (python -m starleth_sim.ros.parameters)."""


def _validate(self) -> "Settings":
    """Check every field against the schema (ConfigError naming the parameter), bring
    numbers to their type, and the rules between fields; returns self."""
    for p in SIM_NODE_PARAMETERS:
        value = p.coerce(getattr(self, p.name))
        try:
            p.check(value)
        except ValueError as e:
            raise ConfigError(str(e)) from None
        setattr(self, p.name, value)
    if "robot" in self.physics_override_dict():
        raise ConfigError("parameter physics_overrides: 'robot' is not set here: use the "
                          "robot parameter (-p robot:=go1)")
    if self.mode == "realtime" and self.real_time_factor == 0.0:
        raise ConfigError("parameter real_time_factor: 0 (as fast as possible) is only legal "
                          "in lockstep mode; realtime mode needs a factor > 0")
    if self.mode == "lockstep" and self.ros2_control_command_interfaces:
        raise ConfigError("parameter ros2_control_command_interfaces: topic_based_ros2_control"
                          " needs realtime mode (its commands answer no state: they carry "
                          "the time they were sent and come every control cycle)")
    return self


def robot_default_gains(description, unset) -> dict:
    """The gains of `unset` (names among default_kp, default_kd: those neither given nor in
    the settings file) for the robot of `description`: the schema's StarlETH values scaled
    by the robot's size and mass (starleth_interface.robot.scaling: kp by mu lambda, kd by
    mu lambda^1.5: dynamic similarity; its sag per robot: doc/performance.md)."""
    scale = robot_scale(description.legs, description.total_mass)
    factor = {"default_kp": scale.stiffness, "default_kd": scale.damping}
    return {name: GAIN_PARAMETERS[name].default * factor[name] for name in unset}


def namespace_frame_prefix(namespace: str) -> str:
    """The frame prefix of a robot under `namespace` by the launch file's convention
    (robot_state_publisher's): 'robot1/' for /robot1 (or robot1, /robot1/), '' at the
    root."""
    ns = (namespace or "").strip("/")
    return ns + "/" if ns else ""


def _robot_frame(self, link: str) -> str:
    """The frame id of a link of this robot: tf_frame_prefix + link."""
    return self.tf_frame_prefix + link


def _physics_override_dict(self) -> dict:
    """The physics_overrides parameter as a mapping (ConfigError if it is not one)."""
    if not self.physics_overrides.strip():
        return {}
    d = load_yaml_text(self.physics_overrides, "parameter physics_overrides")
    if not isinstance(d, dict):
        raise ConfigError("parameter physics_overrides: expected a mapping such as "
                          f"'{{mu: 0.0}}', got {self.physics_overrides!r}")
    return d


#: The node's settings as a typed record, one field per parameter of the schema, with its
#: default; ``validate()`` checks them, ``physics_override_dict()`` parses the overrides,
#: ``robot_frame(link)`` names a link's frame.
Settings = make_dataclass(
    "Settings", [(p.name, p.kind, p.default) for p in SIM_NODE_PARAMETERS],
    namespace={"validate": _validate, "physics_override_dict": _physics_override_dict,
               "robot_frame": _robot_frame,
               "__module__": __name__, "__doc__": "sim_node's settings (see "
               "SIM_NODE_PARAMETERS for each field's meaning)."})


def default_settings_file() -> str:
    return os.path.join(package_share_dir(), "msg_configs", "sim_node.yaml")


def load_default_parameters(path: str | None = None) -> dict:
    """The ros__parameters of msg_configs/sim_node.yaml (node key 'sim_node', '/sim_node' or
    '/**'), falling back to the schema's defaults for anything missing (and for all of them
    when there is no such file). ConfigError naming the file if it is not YAML text, repeats
    a key, names a parameter sim_node does not have or has a value out of its parameter's
    range (the rules between parameters are ``Settings.validate``'s)."""
    defaults = parameter_defaults(SIM_NODE_PARAMETERS)
    try:
        path = path or default_settings_file()
    except OSError:
        return defaults
    if not os.path.isfile(path):
        return defaults
    data = load_yaml_file(path) or {}
    specs = {p.name: p for p in SIM_NODE_PARAMETERS}
    for key in ("sim_node", "/sim_node", "/**"):
        node = data.get(key) if isinstance(data, dict) else None
        params = node.get("ros__parameters") if isinstance(node, dict) else None
        if isinstance(params, dict):
            unknown = [k for k in params if k not in specs and k not in ROS_PARAMETERS]
            if unknown:
                raise ConfigError(f"{os.path.basename(path)}: {key}: "
                                  f"{unknown_parameters_text(unknown, list(specs))}")
            for k, v in params.items():
                if k in specs:
                    v = specs[k].coerce(v)
                    try:
                        specs[k].check(v)
                    except ValueError as e:
                        raise ConfigError(f"{os.path.basename(path)}: {key}: {e}") from None
                    defaults[k] = v
            break
    return defaults


def render_yaml() -> str:
    """msg_configs/sim_node.yaml as generated from the schema."""
    return render_parameters_yaml(SIM_NODE_PARAMETERS, YAML_HEADER)


def update_doc_table(path: str) -> None:
    """Render the rows of the parameter table of doc/sim_node.md (`path`) from the schema."""
    with open(path, encoding="utf-8") as f:
        page = f.read()
    with open(path, "w", encoding="utf-8") as f:
        f.write(with_parameter_table(page, SIM_NODE_PARAMETERS))


if __name__ == "__main__":
    # no argument: msg_configs/sim_node.yaml on stdout; --doc PAGE: that page's table rows
    if sys.argv[1:2] == ["--doc"] and len(sys.argv) == 3:
        update_doc_table(sys.argv[2])
    else:
        sys.stdout.write(render_yaml())
