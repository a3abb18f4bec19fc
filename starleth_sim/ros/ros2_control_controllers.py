"""The ros2_control controllers file of a robot (``config/<robot>_controllers.yaml``): the
controller manager's loop at sim_node's control rate, joint_state_broadcaster, two
forward_command_controllers (position, effort) and joint_trajectory_controller, each on the
robot's joints, i.e. its URDF's actuated joints in sim_node's joint order. Generated, never
written by hand:

    starleth-ros2-controllers --robot go1 > config/go1_controllers.yaml

(``make ros2-control-configs`` regenerates the files of every library robot;
test/ros/test_ros2_control_files.py checks that they are up to date). Text, not yaml.dump, so
that the file keeps its comments. ROS-free."""
from __future__ import annotations

import argparse
import sys
import textwrap

from ..physics.config import ConfigError, load_preset
from ..robots import config_with_robot, robot_description

#: the joint lists' lines: indent of the continuation lines, and width of the names' text
JOINTS_INDENT = " " * 13
JOINTS_WIDTH = 51

HEADER = """\
# ros2_control controllers for {name} in sim_node, through topic_based_ros2_control
# (ROS 2 Jazzy; doc/ros2_control.md). Generated from the robot's URDF, do not edit:
#   starleth-ros2-controllers --robot {robot} > {name}_controllers.yaml
# Started by
#   ros2 launch starleth_sim starleth_ros2_control.launch.xml robot:={robot}
# which gives this file to ros2_control_node and to the spawners.
"""

BODY = """\
#
# The hardware (the <ros2_control> section sim_node puts in its robot_description,
# parameter ros2_control_command_interfaces) declares on every joint the command interfaces
# position, velocity and effort, and the state interfaces position, velocity and effort.
# Every cycle it sends all three to sim_node, which applies
#   tau = effort + kp (position - q) + kd (velocity - qd)    (kp, kd: sim_node's
#   default_kp, default_kd)
# so a controller that claims the position interfaces gets a position servo, and one that
# claims the effort interfaces adds its torques to the spring at the last position command.
# Only one active controller may claim an interface: activate one of the three below at a
# time (ros2 control switch_controllers).
#
# The keys start with /**/ so that the file works in any namespace (launch argument
# namespace). Do not name a controller joint_group_{{position,velocity,effort}}_controller:
# sim_node subscribes to those controllers' command topics itself.

/**/controller_manager:
  ros__parameters:
    # one cycle per sim_node step ({rate} Hz control period); on sim time the loop waits for
    # /clock, so it runs at sim_node's pace
    update_rate: {rate}

    joint_state_broadcaster:
      type: joint_state_broadcaster/JointStateBroadcaster
    forward_position_controller:
      type: forward_command_controller/ForwardCommandController
    forward_effort_controller:
      type: forward_command_controller/ForwardCommandController
    joint_trajectory_controller:
      type: joint_trajectory_controller/JointTrajectoryController

/**/joint_state_broadcaster:
  ros__parameters:
    # publish on joint_state_broadcaster/joint_states: joint_states is sim_node's own topic
    # (the state the hardware reads), which a second publisher would echo into
    use_local_topics: true

/**/forward_position_controller:
  ros__parameters:
    # std_msgs/Float64MultiArray on forward_position_controller/commands, {n} angles [rad]
    joints: {joints}
    interface_name: position

/**/forward_effort_controller:
  ros__parameters:
    # std_msgs/Float64MultiArray on forward_effort_controller/commands, {n} torques [N m]
    joints: {joints}
    interface_name: effort

/**/joint_trajectory_controller:
  ros__parameters:
    # trajectory_msgs/JointTrajectory on joint_trajectory_controller/joint_trajectory, or
    # the action joint_trajectory_controller/follow_joint_trajectory
    joints: {joints}
    # position and velocity of the trajectory: sim_node's targets q* and qd*
    command_interfaces: [position, velocity]
    state_interfaces: [position, velocity]
    # the joints follow their targets with a static error (load / kp: a few hundredths of a
    # radian standing at the default gains): start new trajectories from the last targets,
    # not from the measured (sagged) joints (ros2_controllers >= 4.22; before:
    # open_loop_control: true), and on activation hold the last targets
    interpolate_from_desired_state: true
    set_last_command_interface_value_as_state_on_activation: true
    allow_partial_joints_goal: false
    constraints:
      stopped_velocity_tolerance: 0.05
      goal_time: 0.0
"""


def joints_list(names) -> str:
    """A YAML flow list of the joint names, wrapped for a `joints:` key at indent 4."""
    lines = textwrap.wrap(", ".join(names), JOINTS_WIDTH, break_long_words=False,
                          break_on_hyphens=False)
    return "[" + ("\n" + JOINTS_INDENT).join(lines) + "]"


def controllers_yaml(name: str, robot: str, joint_names, control_period: float) -> str:
    """The controllers file (text) of the robot `name` (`robot`: the value of the robot
    argument that names it) with joints `joint_names` and sim_node's control period [s]."""
    if not joint_names:
        raise ConfigError(f"robot: '{robot}' has no actuated joint")
    return HEADER.format(name=name, robot=robot) + BODY.format(
        rate=round(1.0 / control_period), n=len(joint_names), joints=joints_list(joint_names))


def robot_controllers_yaml(robot: str, physics: str = "HmJ") -> str:
    """The controllers file of a `robot` value (library name, spec or URDF path) as sim_node
    runs it with the physics preset `physics`; ConfigError naming the field."""
    desc = robot_description(robot)
    period = config_with_robot(load_preset(physics), robot).control_period
    return controllers_yaml(desc.name, robot, desc.joint_names, period)


def main(argv=None) -> int:
    """Print the controllers file of a robot."""
    ap = argparse.ArgumentParser(
        prog="starleth-ros2-controllers",
        description="Print the ros2_control controllers file (controller_manager, "
                    "joint_state_broadcaster, forward position / effort controllers, "
                    "joint_trajectory_controller) of a robot's joints, for "
                    "launch/starleth_ros2_control.launch.xml (argument controllers_file).")
    ap.add_argument("--robot", default="starleth",
                    help="a library robot name, or the path of a robot spec .yaml or a URDF")
    ap.add_argument("--physics", default="HmJ",
                    help="physics preset (or YAML path): sim_node's control rate")
    args = ap.parse_args(argv)
    try:
        text = robot_controllers_yaml(args.robot, args.physics)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
