"""The ``<ros2_control>`` section that lets ros2_control controllers drive sim_node through
``topic_based_ros2_control`` (its hardware TopicBasedSystem exchanges sensor_msgs/JointState
over two topics): generated from the robot's joints, with sim_node's own topics, so that
``ros2_control_node`` can load it from the ``robot_description`` sim_node publishes
(parameter ``ros2_control_command_interfaces``), or a bringup of the user's own can paste
it (``urdf/starleth_ros2_control.xml``, generated with the defaults; another robot's with
``--robot NAME``, a library name or a spec or URDF path):

    python -m starleth_sim.ros.ros2_control_description > urdf/starleth_ros2_control.xml

test/ros/test_ros2_control_files.py checks that the file is up to date).

What the hardware does with the section (doc/sim_node.md, "ros2_control controllers"):
every control cycle it publishes one JointState naming every joint of the section, with one
field per command interface the joints declare (so every joint declares the same ones, or
the fields would not line up with the names); the command values start at the initial
values, here the initial joint positions with zero velocity and effort, so before any
controller writes, the hardware asks sim_node to hold the initial posture. ROS-free."""
from __future__ import annotations

import argparse
import math
import sys
from xml.sax.saxutils import quoteattr

from starleth_interface.topics import TOPIC_JOINT_COMMANDS, TOPIC_JOINT_STATES

from ..physics.config import ConfigError

#: the joint interfaces sim_node serves: command (JointState fields it reads on
#: joint_commands) and state (fields of its joint_states)
INTERFACES = ("position", "velocity", "effort")
#: the default command interfaces: a joint impedance command with feed-forward torque
DEFAULT_COMMAND_INTERFACES = INTERFACES
HARDWARE_PLUGIN = "topic_based_ros2_control/TopicBasedSystem"
#: hardware parameters: sim_node's topics (relative: resolved in the namespace of
#: ros2_control_node, the robot's), and a threshold below any difference, so that the
#: hardware publishes every cycle (its default 1e-5 skips a cycle whose position commands
#: equal the joint positions within 1e-5 rad in sum)
HARDWARE_PARAMETERS = (("joint_commands_topic", TOPIC_JOINT_COMMANDS),
                       ("joint_states_topic", TOPIC_JOINT_STATES),
                       ("trigger_joint_command_threshold", "-1"))


def parse_command_interfaces(text: str, what="parameter ros2_control_command_interfaces"):
    """The command interfaces of a comma-separated list of position, velocity, effort (each
    at most once, in INTERFACES order); () for an empty text. ConfigError naming `what`
    otherwise."""
    items = [s.strip() for s in text.split(",")] if text.strip() else []
    unknown = [s for s in items if s not in INTERFACES]
    if unknown or len(set(items)) != len(items) or (text.strip() and not items):
        raise ConfigError(f"{what}: expected a comma-separated list of {', '.join(INTERFACES)}"
                          f" (each once), or empty for none; got {text!r}")
    return tuple(i for i in INTERFACES if i in items)


def ros2_control_section(name: str, joint_names, initial_positions,
                         command_interfaces=DEFAULT_COMMAND_INTERFACES, limits=None) -> str:
    """The <ros2_control> element (text, indented for the end of a URDF) of system `name`
    with hardware TopicBasedSystem: every joint in `joint_names` with `command_interfaces`
    and the state interfaces position, velocity and effort. Initial values: the position
    state and command from `initial_positions` (joint order), the velocity and effort
    commands 0, i.e. sim_node's hold of the initial posture (TopicBasedSystem starts its
    commands from the state interfaces' initial values; ros2_control's own handles, as its
    successor joint_state_topic_hardware_interface uses them, from the command interfaces',
    else NaN). `limits`: per joint {interface: (min, max)} (joint_limits), each command
    interface's min and max params where given (ros2_control's joint limiter takes them
    with the URDF's <limit> tags, which lack the limits a robot spec adds)."""
    limits = limits or [{}] * len(joint_names)
    if not command_interfaces:
        raise ValueError("a ros2_control section needs at least one command interface")
    params = "".join(f"\n      <param name={quoteattr(k)}>{v}</param>"
                     for k, v in HARDWARE_PARAMETERS)
    lines = [f"  <ros2_control name={quoteattr(name)} type=\"system\">",
             "    <hardware>",
             f"      <plugin>{HARDWARE_PLUGIN}</plugin>{params}",
             "    </hardware>"]
    for joint, q0, bounds in zip(joint_names, initial_positions, limits, strict=True):
        initial = {"position": float(q0), "velocity": 0.0, "effort": 0.0}
        lines.append(f"    <joint name={quoteattr(joint)}>")
        lines += [_interface("command", i, initial[i], bounds.get(i))
                  for i in command_interfaces]
        lines.append(_interface("state", "position", initial["position"]))
        lines += [f"      <state_interface name=\"{i}\"/>" for i in INTERFACES[1:]]
        lines.append("    </joint>")
    lines.append("  </ros2_control>")
    return "\n".join(lines) + "\n"


def _interface(kind, name, initial_value, bounds=None) -> str:
    params = "".join(f"<param name=\"{k}\">{float(v)!r}</param>"
                     for k, v in zip(("min", "max"), bounds or (), strict=False))
    return (f"      <{kind}_interface name=\"{name}\"><param name=\"initial_value\">"
            f"{initial_value!r}</param>{params}</{kind}_interface>")


def joint_limits(desc) -> list:
    """Per joint of description `desc` {interface: (min, max)}: its position range, and
    its velocity and effort bounds (symmetric), each where finite and set (a bound of 0 is
    a URDF's "no limit")."""
    out = []
    for j in range(len(desc.joint_names)):
        bounds = {}
        lo, hi = float(desc.position_lower[j]), float(desc.position_upper[j])
        if math.isfinite(lo) and math.isfinite(hi) and lo < hi:
            bounds["position"] = (lo, hi)
        for itf, limit in (("velocity", desc.velocity_limit), ("effort", desc.effort_limit)):
            v = float(limit[j])
            if math.isfinite(v) and v > 0:
                bounds[itf] = (-v, v)
        out.append(bounds)
    return out


def with_ros2_control(urdf_xml: str, section: str) -> str:
    """The URDF text with `section` inserted before its closing </robot> tag."""
    end = urdf_xml.rfind("</robot>")
    if end < 0:
        raise ValueError("not a URDF: no </robot> closing tag")
    return urdf_xml[:end] + section + urdf_xml[end:]


def simulator_section(sim, command_interfaces=DEFAULT_COMMAND_INTERFACES) -> str:
    """The section of simulator `sim` in its current state: its robot's joints, named after
    its robot, the initial values its current joint positions, the command limits its
    description's (URDF and spec)."""
    return ros2_control_section(sim.description.name, sim.joint_names,
                                sim.joint_positions(), command_interfaces,
                                joint_limits(sim.description))


def main(argv=None) -> int:
    """Print the <ros2_control> section of the robot as sim_node starts it."""
    ap = argparse.ArgumentParser(
        prog="python -m starleth_sim.ros.ros2_control_description",
        description="Print the <ros2_control> section (topic_based_ros2_control) of the "
                    "robot in the initial state sim_node starts from.")
    ap.add_argument("--command-interfaces", default=",".join(DEFAULT_COMMAND_INTERFACES),
                    help="comma-separated subset of position, velocity, effort")
    ap.add_argument("--robot", default=None,
                    help="a library robot name, or the path of a robot spec .yaml or a URDF "
                         "(default: the physics preset's, StarlETH)")
    ap.add_argument("--physics", default="HmJ", help="physics preset (or YAML path)")
    ap.add_argument("--initial-state", default="standing",
                    help="as sim_node's initial_state parameter")
    args = ap.parse_args(argv)
    from ..physics.simulator import Simulator  # deferred: --help stays quick
    from .state_io import parse_initial_state  # deferred: --help stays quick
    try:
        interfaces = parse_command_interfaces(args.command_interfaces, "--command-interfaces")
        if not interfaces:
            raise ConfigError("--command-interfaces: at least one is needed")
        sim = Simulator.from_preset(args.physics, robot=args.robot)
        q0, u0, _ = parse_initial_state(args.initial_state, sim)
        sim.reset(q0, u0)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    sys.stdout.write(simulator_section(sim, interfaces))
    return 0


if __name__ == "__main__":
    sys.exit(main())
