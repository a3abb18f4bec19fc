"""A stand-in for `ros2_control_node` running the hardware
`topic_based_ros2_control/TopicBasedSystem` and forward_command_controllers, for the tests
(there is no ros2_control in the venv). It does what those programs do, as read in their
sources (topic_based_ros2_control 0.3.0; controller_manager's ros2_control_node and
forward_command_controller of ROS 2 Jazzy), so that a test sees sim_node receive what a
ros2_control stack sends:

* the hardware is set up from the <ros2_control> section of the robot_description
  (:func:`parse_ros2_control`, as hardware_interface's component parser reads it): per joint
  the command and state interfaces; storage for the standard interfaces of every joint, 0.0
  unless the joint's *state* interface of that name has an ``initial_value``, which sets
  both the state and the command value; hardware parameters ``joint_commands_topic``
  (default /robot_joint_commands), ``joint_states_topic`` (default /robot_joint_states),
  ``trigger_joint_command_threshold`` (default 1e-5), ``sum_wrapped_joint_states``;
* it publishes sensor_msgs/JointState with QoS depth 1, reliable, volatile, and subscribes
  to the states with the sensor-data QoS (best effort, depth 5), keeping the latest;
* read(): for each name of the latest state message that is a joint of the section, its
  position, and its velocity and effort where those fields are not empty;
* write(): nothing when the sum over joints of |position state - position command| is at
  most the threshold; else one JointState naming every joint of the section in its order,
  stamped with the node's clock (sim time under use_sim_time), with one value in a field for
  each joint that declares that command interface (position, velocity, effort);
* the control loop on sim time (ros2_control_node with use_sim_time): wait until the clock
  has started, sleep one period of sim time, then read, update, write and sleep until the
  previous cycle's start plus one period (1 / update_rate) of sim time;
* a ForwardCommandController holds the last Float64MultiArray received on
  ``<name>/commands`` (one value per joint of its ``joints``) and writes it into the
  ``interface_name`` command interface of those joints every update, nothing before the
  first message;
* the spawner's command line (:func:`spawner_arguments`: the options of ROS 2 Jazzy's
  spawner that these tests meet).
"""
from __future__ import annotations

import argparse
import threading
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.time import Time
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

#: hardware_interface's standard interfaces, in TopicBasedSystem's storage order
STANDARD_INTERFACES = ("position", "velocity", "acceleration", "effort")
COMMANDED_FIELDS = ("position", "velocity", "effort")      # what write() puts in a message


@dataclass
class InterfaceInfo:
    name: str
    initial_value: str = ""
    min: str = ""
    max: str = ""


@dataclass
class JointInfo:
    name: str
    command_interfaces: list = field(default_factory=list)
    state_interfaces: list = field(default_factory=list)
    parameters: dict = field(default_factory=dict)


@dataclass
class HardwareInfo:
    name: str
    type: str
    plugin: str
    hardware_parameters: dict
    joints: list


def _params(elem) -> dict:
    return {p.get("name"): (p.text or "").strip() for p in elem.findall("param")}


def _interface(elem) -> InterfaceInfo:
    params = _params(elem)
    return InterfaceInfo(elem.get("name"), params.get("initial_value", ""),
                         params.get("min", ""), params.get("max", ""))


def parse_ros2_control(urdf_xml: str) -> list:
    """The HardwareInfo of every <ros2_control> element of a robot description."""
    out = []
    for rc in ET.fromstring(urdf_xml).findall("ros2_control"):
        hw = rc.find("hardware")
        joints = [JointInfo(j.get("name"),
                            [_interface(c) for c in j.findall("command_interface")],
                            [_interface(s) for s in j.findall("state_interface")],
                            _params(j))
                  for j in rc.findall("joint")]
        out.append(HardwareInfo(rc.get("name"), rc.get("type"),
                                (hw.findtext("plugin") or "").strip(), _params(hw), joints))
    return out


class TopicBasedSystem:
    """TopicBasedSystem on `node` for `info`: on_init here, then read() and write()."""

    def __init__(self, node, info: HardwareInfo):
        self.node, self.info = node, info
        n = len(info.joints)
        self.commands = {i: [0.0] * n for i in STANDARD_INTERFACES}
        self.states = {i: [0.0] * n for i in STANDARD_INTERFACES}
        for j, joint in enumerate(info.joints):
            if "mimic" in joint.parameters:
                raise NotImplementedError("mimic joints are not part of this stand-in")
            for itf in joint.command_interfaces + joint.state_interfaces:
                if itf.name not in STANDARD_INTERFACES:       # export_*_interfaces throw
                    raise RuntimeError("Interface is not found in the standard list.")
            for itf in joint.state_interfaces:
                if itf.initial_value:
                    self.states[itf.name][j] = float(itf.initial_value)
                    self.commands[itf.name][j] = float(itf.initial_value)
        params = info.hardware_parameters
        if params.get("sum_wrapped_joint_states", "false") == "true":
            raise NotImplementedError("sum_wrapped_joint_states is not part of this stand-in")
        self.threshold = float(params.get("trigger_joint_command_threshold", "1e-5"))
        self.index = {joint.name: j for j, joint in enumerate(info.joints)}
        self.latest = JointState()
        self._lock = threading.Lock()
        self.publisher = node.create_publisher(
            JointState, params.get("joint_commands_topic", "/robot_joint_commands"),
            QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE))
        self.subscription = node.create_subscription(
            JointState, params.get("joint_states_topic", "/robot_joint_states"),
            self._on_state, qos_profile_sensor_data)
        self.published = []        # (stamp ns, JointState) of every write that published

    def _on_state(self, msg):
        with self._lock:
            self.latest = msg

    def read(self):
        with self._lock:
            msg = self.latest
        for i, name in enumerate(msg.name):
            j = self.index.get(name)
            if j is None:
                continue
            self.states["position"][j] = msg.position[i]
            if len(msg.velocity):
                self.states["velocity"][j] = msg.velocity[i]
            if len(msg.effort):
                self.states["effort"][j] = msg.effort[i]

    def write(self) -> bool:
        diff = sum(abs(s - c) for s, c in zip(self.states["position"],
                                              self.commands["position"], strict=True))
        if diff <= self.threshold:
            return False
        msg = JointState()
        msg.header.stamp = self.node.get_clock().now().to_msg()
        for j, joint in enumerate(self.info.joints):
            msg.name.append(joint.name)
            for itf in joint.command_interfaces:
                if itf.name in COMMANDED_FIELDS:
                    getattr(msg, itf.name).append(self.commands[itf.name][j])
        self.publisher.publish(msg)
        self.published.append((Time.from_msg(msg.header.stamp).nanoseconds, msg))
        return True


class ForwardCommandController:
    """forward_command_controller/ForwardCommandController `name` with `params` (joints,
    interface_name) on the hardware's command interfaces."""

    def __init__(self, node, name, params, hardware: TopicBasedSystem):
        self.joints = [hardware.index[j] for j in params["joints"]]
        self.values = hardware.commands[params["interface_name"]]
        self.command = None
        self.subscription = node.create_subscription(Float64MultiArray, f"{name}/commands",
                                                     self._on_command, 10)

    def _on_command(self, msg):
        if len(msg.data) == len(self.joints):
            self.command = list(msg.data)

    def update(self):
        command = self.command
        if command is not None:
            for j, value in zip(self.joints, command, strict=True):
                self.values[j] = value


class SimTimeControlLoop:
    """ros2_control_node's loop under use_sim_time on a thread: read, update the
    controllers, write, at `update_rate` Hz of the node's (sim) clock. `cycles` counts the
    cycles, `writes` the cycles whose write published."""

    def __init__(self, node, hardware, controllers, update_rate):
        self.node, self.hardware, self.controllers = node, hardware, controllers
        self.period_ns = 1_000_000_000 // int(update_rate)
        self.cycles = self.writes = 0
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def start(self):
        self.thread.start()

    def stop(self):
        self._stop.set()
        self.thread.join(5.0)

    def _sleep_until(self, ns):
        clock = self.node.get_clock()
        clock.sleep_until(Time(nanoseconds=ns, clock_type=clock.clock_type),
                          context=self.node.context)

    def _run(self):
        clock = self.node.get_clock()
        while not self._stop.is_set() and clock.now().nanoseconds == 0:   # wait_until_started
            time.sleep(0.001)
        self._sleep_until(clock.now().nanoseconds + self.period_ns)
        time.sleep(self.period_ns * 1e-9)
        while not self._stop.is_set() and rclpy.ok(context=self.node.context):
            previous = clock.now().nanoseconds
            self.hardware.read()
            for c in self.controllers:
                c.update()
            self.writes += self.hardware.write()
            self.cycles += 1
            self._sleep_until(previous + self.period_ns)


def spawner_arguments(args):
    """The spawner's command line parsed as controller_manager's spawner (Jazzy) parses it:
    controller_names, controller_manager, param_file (a list), inactive, ... An option it
    does not have is an error (SystemExit), as there."""
    p = argparse.ArgumentParser(prog="spawner", exit_on_error=False)
    p.add_argument("controller_names", nargs="+")
    p.add_argument("-c", "--controller-manager", default="controller_manager")
    p.add_argument("-p", "--param-file", action="append", default=None)
    p.add_argument("-n", "--namespace", default=None)
    p.add_argument("--load-only", action="store_true")
    p.add_argument("--inactive", action="store_true")
    p.add_argument("-u", "--unload-on-kill", action="store_true")
    p.add_argument("--controller-manager-timeout", type=float, default=0.0)
    p.add_argument("--switch-timeout", type=float, default=5.0)
    p.add_argument("--service-call-timeout", type=float, default=10.0)
    p.add_argument("--activate-as-group", action="store_true")
    p.add_argument("--switch-asap", action=argparse.BooleanOptionalAction, default=True)
    p.add_argument("--controller-ros-args", action="append", default=None)
    return p.parse_args(args)
