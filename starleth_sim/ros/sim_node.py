"""``sim_node``: one StarlETH ``Simulator`` behind the ROS 2 interfaces users know from
mujoco_ros2_control / gz_ros2_control. A thin adapter: no physics in here.

    ros2 run starleth_sim sim_node --ros-args -p mode:=lockstep -p record:=run.mcap
    python -m starleth_sim.ros.sim_node --ros-args --params-file my_sim.yaml

Parameters: one schema, ``SIM_NODE_PARAMETERS`` in :mod:`.parameters` (type, default, bounds,
description: ``ros2 param describe /sim_node mode``), rendered into msg_configs/sim_node.yaml.

Names are relative (REP 135 style): ``--ros-args -r __ns:=/robot1`` (or the launch file's
``namespace``) moves every topic and service below, so several robots share a ROS domain;
/clock is global (``publish_clock:=false`` on all but one simulator of a domain). The node
is the source of /clock: its loops run on the wall clock whatever ``use_sim_time`` says,
and its stamps are always sim time.

Published; stamps are sim time t_k = k * 2.5 ms; one message per control step (a topic
nobody subscribes to is not published; while recording it is only recorded):

  joint_states                            sensor_msgs/JointState       effort = the torque
                                                                       applied (saturated) over
                                                                       the step into t_k
  /clock                                  rosgraph_msgs/Clock          ClockQoS (best effort);
                                                                       with publish_clock
  starleth/{LF,RF,LH,RH}_foot/wrench      geometry_msgs/WrenchStamped  F = impulse/dt, 'world'
  starleth/base_state                     nav_msgs/Odometry            pose in 'world', twist in
                                                                       'base' (child frame)
  starleth/imu                            sensor_msgs/Imu              proper acceleration and
                                                                       body rates at the base
  starleth/solver                         diagnostic_msgs/DiagnosticArray  solver status every
                                                                       step, interface counters
                                                                       every 40 steps
  robot_description                       std_msgs/String              URDF, transient local
  starleth/state_bundle                   std_msgs/Float64MultiArray   the state of a step in
                                                                       one message, for
                                                                       controller_node (not
                                                                       recorded; layout:
                                                                       starleth_interface.
                                                                       state_bundle)

Subscribed (reliable, depth 10):

  joint_group_effort_controller/commands  std_msgs/Float64MultiArray   12 torques, joint order
  joint_commands                          sensor_msgs/JointState       efforts by joint name
  ~/wrench, ~/wrench/persistent           geometry_msgs/WrenchStamped  frame_id = link name,
                                                                       world axes, at the link
                                                                       origin; zero clears
Services: ``~/reset`` (Trigger), ``~/pause`` (SetBool), ``~/step`` (Trigger, while paused).
Each keeps SERVICE_QUEUE requests and responses, so 100 callers at once are all answered
(with Fast DDS a client also receives the other callers' responses: a process that makes
many calls at once gives its clients a depth of at least their number).

Lockstep protocol: the state of step k (stamp t_k) is published, then the node waits for a
command answering it: a ``/joint_commands`` JointState whose header stamp equals t_k, or any
Float64MultiArray (it has no stamp, so in lockstep it is taken as the answer to the latest
state). A JointState command with another stamp is dropped and counted as *late* (it answers
a state that was already stepped on the timeout policy) or *stale* (any other stamp). Without
an answer within ``lockstep_timeout`` the node steps with ``timeout_policy`` (hold the last
command or zero torques), logs it and counts it. Before the first step the node waits for
the first command without timeout, re-sending the whole state 0 (every state topic, same stamp, not
recorded) every 0.5 s and whenever a new subscriber to a state topic appears, so that the
start order of sim and controller does not matter and two runs with the same controller
are bit-identical. A controller that dies later leaves the sim stepping on its timeout
policy; while it waits for an answer, a new subscriber (a restarted controller) gets the
current state again at once.

Recording: ``record`` names an MCAP file (rosbag2 layout, read by ros2 bag, rosbags,
Foxglove); with ``record_max_duration`` / ``record_max_size`` a rosbag2 bag directory of
numbered files with a metadata.yaml, each file complete on its own.

Realtime mode: a wall-clock loop (sleep in the executor until 0.6 ms before the tick, then
spin on the clock); the latest valid command is held. Behind by more than 0.1 s, the loop
drops the missed ticks (counted as overruns).

Bad input (wrong length, NaN/inf, unknown or duplicate joint names, unknown link, malformed
CDR) is rejected with a throttled warning naming the problem; the last valid command stays.

``~/reset`` restores the initial state; sim time keeps running (the reset takes one control
period, so stamps stay strictly increasing and answers to the old state are stale). A reset
during a lockstep exchange: the state being answered is gone; the reset state (stamp
t_(k+1)) is published and needs an answer of its own; an answer to the earlier stamp,
arriving before or after the reset, is dropped as stale (counted); a command already taken
for the old state but not yet stepped on is discarded (the reset zeroes the command).

Faults that do not take the node down: a push over ``max_wrench_force`` /
``max_wrench_torque`` is rejected with a warning. A step that is not physics (the physics
failed twice, or the base moved faster than ``SimService.MAX_BASE_SPEED``) is neither
published nor recorded: the node pauses, says why on /starleth/solver (the interface status,
ERROR), and goes on only after ``~/reset``. While paused, /starleth/solver still comes once
a second. The recording can fail (disk full, file-size limit, I/O error, the writer process
killed): the node logs one error naming the file and the cause, the file is closed as a
complete bag up to the last message written (:mod:`.mcap_sink`), /starleth/solver says
``recording: failed (...)``, and the simulation goes on. The node never waits for its
writer: SIGINT ends it within 2 s, and what the writer has not taken by then is dropped
(counted) or written by the writer after the node has gone (said in the log).

Lockstep critical path (command in -> step -> state out): commands are taken as CDR bytes
and the common valid case is decoded without an rclpy message object (:mod:`.cdr`; the
rest is deserialised and validated in full); the state goes out as CDR bytes patched into
templates (:mod:`starleth_interface.msg_cdr`: each message is serialised once, for
publishing and recording alike). What a controller waits for goes first: with a
subscriber to ``starleth/state_bundle`` (controller_node) that one message, and the public
topics after it, while the controller computes (published only to their other
subscribers: controller_node then reads the bundle alone); otherwise the foot wrenches,
the base state, then /joint_states (a controller answers on the joint state and finds the
rest of the state already there; controller_node takes it from its queues, one wake-up
per state); then /clock, /starleth/imu, /starleth/solver; the recorder only
takes the bytes over (:class:`~.recording.ProcessRecorder`: a writer process adds them to
the file, outside this interpreter, handed over every ``HAND_OVER_STEPS`` steps;
:class:`~.recording.QueuedRecorder`, a writer thread, where no process can be started;
SIGINT still leaves a complete file), and
the node prepares the torque-independent part of the next step (``Simulator.prepare``)
while the controller computes its answer. The base state and the foot forces are read
through ``Simulator.base_state`` and ``Simulator.contact_forces`` (no per-contact records),
the contact markers written as CDR bytes too
(``msg_cdr.SlotCdr``). ``SimNode.timing`` (a :class:`~starleth_interface.cycle_times.CycleTimes`,
benchmarks only) times each part.

The ROS-free parts: :class:`~.service.SimService` (command validation, lockstep bookkeeping,
counters, stepping), :mod:`.state_io` (initial state, public state, IMU) and
:mod:`.parameters`; :class:`SimNode` here is the rclpy plumbing.
"""
from __future__ import annotations

import array
import gc
import json
import os
import sys
import time
from dataclasses import asdict, replace

import numpy as np
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import WrenchStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import SetBool, Trigger

from starleth_interface.compile_notice import CompileNotice
from starleth_interface.cycle_times import CycleTimes  # noqa: F401  (SimNode.timing)
from starleth_interface.msg_cdr import (IMU_FIELDS, ODOM_FIELDS, WRENCH_FIELDS, DiagnosticArrayCdr,
                                       FixedCdr, JointStateCdr, SlotCdr)
from starleth_interface.state_bundle import JOINT_NAMES as BUNDLE_JOINT_NAMES
from starleth_interface.state_bundle import StateBundleCdr
from starleth_interface.ros_helpers import (StopSignals, declare_parameters, init_ros,
                                            make_executor, set_cpu_scheduling, shutdown_ros)
from starleth_interface.topics import (TOPIC_BASE_STATE, TOPIC_CLOCK, TOPIC_CONTACT_MARKERS,
                                       TOPIC_EFFORT_COMMANDS, TOPIC_IMU, TOPIC_JOINT_COMMANDS,
                                       TOPIC_JOINT_STATES, TOPIC_ROBOT_DESCRIPTION, TOPIC_SOLVER,
                                       TOPIC_STATE_BUNDLE, TOPIC_TF, TOPIC_TF_STATIC, TOPIC_WRENCH,
                                       TOPIC_WRENCH_PERSISTENT, foot_wrench_topic)
from ..physics.config import ConfigError
from ..physics.description import STARLETH_FEET as FEET
from ..physics.simulator import CONTACT_STATES, Simulator
from .cdr import CommandDecoder
from .parameters import SIM_NODE_PARAMETERS, Settings, load_default_parameters
from .recording import RecordingError, register_msg_text
from .service import PeriodStats, SimService
from .state_io import (ImuEstimate, base_values, initial_state_record, joint_indices,
                       joint_values, parse_initial_state, state_bundle_bytes)
from .tf import TF_MSG_TEXT, TF_TYPE, FrameTree, TfMessageCdr


def _package_version() -> str:
    """The installed starleth_sim version (recorded with every bag), or 'unknown'."""
    try:
        from importlib.metadata import version
        return version("starleth_sim")
    except Exception:   # not installed (run from a source tree)
        return "unknown"


def _dbl(a) -> array.array:
    return array.array("d", np.ascontiguousarray(a, dtype=float).tobytes())


class SimNode:
    """The rclpy side: parameters, publishers, subscriptions, services, recording, and the
    lockstep / realtime loops. Created by :func:`main`; usable in-process (tests, bench)."""

    SPIN_MARGIN = 0.0006  # realtime: stop waiting in the executor this long before a tick
    MAX_CATCH_UP = 0.1    # realtime: at most this far behind the wall clock, then skip ahead

    def __init__(self, context=None, parameter_overrides=None, node_name="sim_node",
                 settings_file=None):
        defaults = load_default_parameters(settings_file)
        self.node = Node(node_name, context=context,
                         parameter_overrides=[Parameter(k, value=v) for k, v in
                                              (parameter_overrides or {}).items()])
        node = self.node
        self.log = node.get_logger()
        specs = [replace(p, default=defaults[p.name]) for p in SIM_NODE_PARAMETERS]
        self.settings = Settings(**declare_parameters(node, specs)).validate()
        s = self.settings
        overrides = s.physics_override_dict()
        self.sim = Simulator.from_preset(s.physics, **overrides)
        q0, u0, init_desc = parse_initial_state(s.initial_state, self.sim)
        self.initial_state_desc = init_desc
        # two call sites: rclpy refuses one call site that logs at two severities
        self.service = SimService(self.sim, s, q0, u0, warn=self._log_warning,
                                  error=self._log_error)
        self.context = node.context
        self._stop = False
        self._context_ok_until = 0.0
        self._step_on_answer = False   # set by run() in lockstep mode without pacing
        self._n_state_subs = 0          # subscribers of the state topics at the last look
        self._counts_k = -10 ** 9
        self._counts = {}
        self._paused_diag_at = 0.0       # _publish_paused_diagnostics
        self.period_stats = PeriodStats(self.sim.control_period / max(s.real_time_factor, 1e-12))
        self.imu = ImuEstimate(self._model_gravity(), self.sim.control_period)
        self._feet_first = tuple(self.sim.contact_names[:len(FEET)]) == tuple(FEET)
        self._setup_messages()
        self._setup_interfaces()
        self._setup_visualisation()
        err = set_cpu_scheduling(s.cpu_scheduling)     # before the writer process starts
        if err:
            self.log.warning(f"cpu_scheduling {s.cpu_scheduling}: {err}")
        self.recorder = None             # the recorder while it records (None: off or failed)
        self._recorder_stats = None      # the recorder, also after it failed
        self.recording_failure = None    # why the recording stopped early
        self._dropped_seen = 0           # recorded messages dropped, as last reported
        if s.record:
            self._open_recorder(s.record)
        self._publish_robot_description()
        self._publish_static_transforms()
        self.log.info(f"{s.physics} physics, {s.mode} mode"
                      + (f", real-time factor {s.real_time_factor:g}" if s.real_time_factor else
                         ", as fast as the controller") +
                      (f", recording to {s.record}" if s.record else "") +
                      f"; {self.sim.n_joints} joints, control period "
                      f"{self.sim.control_period * 1e3:g} ms")

    # -- setup -----------------------------------------------------------------------------
    def _model_gravity(self):
        try:
            g = np.array(self.sim.description.model.gravity.linear, dtype=float)
            if g.shape == (3,) and np.all(np.isfinite(g)):
                return g
        except Exception:  # pragma: no cover
            pass
        return np.array([0.0, 0.0, -9.81])

    def _setup_messages(self):
        s, sim = self.settings, self.sim
        self.clock_msg = Clock()
        self.js_msg = JointState()
        self.js_msg.name = list(sim.joint_names)
        self._js_cdr = JointStateCdr.create(list(sim.joint_names))
        # (numba: compiled on a first run after an install, else loaded from its cache)
        with CompileNotice("sim_node's command parsers", self.log.info, estimate=3.0):
            self.decoder = CommandDecoder(sim.joint_names)
        self.wrench_msgs = {}
        for foot in FEET:
            m = WrenchStamped()
            m.header.frame_id = s.world_frame
            self.wrench_msgs[foot] = m
        self.odom_msg = Odometry()
        self.odom_msg.header.frame_id = s.world_frame
        self.odom_msg.child_frame_id = s.base_frame
        self.imu_msg = Imu()
        self.imu_msg.header.frame_id = s.base_frame
        # the state topics of every step go out as CDR bytes patched into templates
        # (starleth_interface.msg_cdr; None: as message objects)
        w = WrenchStamped()
        w.header.frame_id = s.world_frame
        self._wrench_cdr = FixedCdr.create(w, WRENCH_FIELDS)
        o = Odometry()
        o.header.frame_id, o.child_frame_id = s.world_frame, s.base_frame
        self._odom_cdr = FixedCdr.create(o, ODOM_FIELDS)
        i = Imu()
        i.header.frame_id = s.base_frame
        self._imu_cdr = FixedCdr.create(i, IMU_FIELDS)
        self._clock_cdr = FixedCdr.create(Clock(), (), stamp="clock")
        # the state bundle (starleth_interface.state_bundle): only for the robot whose
        # joints and feet are in the bundle's order
        self._bundle_cdr = (StateBundleCdr.create()
                            if tuple(sim.joint_names) == BUNDLE_JOINT_NAMES
                            and self._feet_first else None)
        self.timing = None           # a CycleTimes, set by benchmarks
        self.solver_keys = ("iterations", "max_iterations_step", "converged", "status",
                            "residual", "active_contacts", "retried", "step_time",
                            "physics_steps", "nonconverged_steps", "loaded_contacts_opened",
                            "loaded_contacts_opened_total", "projections",
                            "projection_iterations")
        self.iface_keys = ("mode", "real_time_factor", "sim_time", "step", "paused",
                           "waiting_for_first_command", *SimService.COUNTERS,
                           "period_error_p50_ms", "period_error_p99_ms", "period_error_max_ms",
                           "overruns", "recorded_messages", "recording_dropped",
                           "recording")
        self.diag_msg = DiagnosticArray()
        self.solver_status = DiagnosticStatus(name="starleth_sim: solver",
                                              hardware_id="starleth_sim")
        self.solver_status.values = [KeyValue(key=k, value="") for k in self.solver_keys]
        self.iface_status = DiagnosticStatus(name="starleth_sim: interface",
                                             hardware_id="starleth_sim")
        self.iface_status.values = [KeyValue(key=k, value="") for k in self.iface_keys]
        self._diag_solver_only = [self.solver_status]
        self._diag_both = [self.solver_status, self.iface_status]
        # /starleth/solver written as CDR bytes field by field (None: message objects)
        self._diag_cdr = DiagnosticArrayCdr("", [
            (st.name, st.hardware_id, [kv.key for kv in st.values])
            for st in self._diag_both])
        self.diag_msg.status = self._diag_both
        self._period_summary = {}

    def _setup_interfaces(self):
        node = self.node
        state_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                               durability=DurabilityPolicy.VOLATILE,
                               history=HistoryPolicy.KEEP_LAST)
        clock_qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT,
                               durability=DurabilityPolicy.VOLATILE,
                               history=HistoryPolicy.KEEP_LAST)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             history=HistoryPolicy.KEEP_LAST)
        cmd_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE,
                             history=HistoryPolicy.KEEP_LAST)
        self.qos = {"state": state_qos, "clock": clock_qos, "latched": latched, "cmd": cmd_qos}
        # (publisher, topic name resolved, type, qos)
        self.pubs = {}

        def pub(key, typ, topic, qos):
            p = node.create_publisher(typ, topic, qos)
            self.pubs[key] = (p, p.topic_name, typ, qos)

        if self.settings.publish_clock:
            pub("clock", Clock, TOPIC_CLOCK, clock_qos)
        pub("joint_states", JointState, TOPIC_JOINT_STATES, state_qos)
        for foot in FEET:
            pub(foot, WrenchStamped, foot_wrench_topic(foot), state_qos)
        pub("base_state", Odometry, TOPIC_BASE_STATE, state_qos)
        pub("imu", Imu, TOPIC_IMU, state_qos)
        pub("solver", DiagnosticArray, TOPIC_SOLVER, state_qos)
        pub("robot_description", String, TOPIC_ROBOT_DESCRIPTION, latched)
        if self._bundle_cdr is not None:
            pub("state_bundle", Float64MultiArray, TOPIC_STATE_BUNDLE, state_qos)
        self.subs = {}
        # when recording, inputs are taken as CDR bytes: the recording holds exactly what
        # arrived (as rosbag2 does), and the callback deserialises them. Joint commands are
        # always taken as bytes: the common valid case is decoded straight from the CDR
        # (cdr.CommandDecoder), anything else is deserialised and validated in full.
        raw = bool(self.settings.record)

        def sub(key, typ, topic, cb, fast=None):
            if raw or fast is not None:
                handler = cb

                def cb(data, key=key, typ=typ, fast=fast):
                    self._record_input(key, data)
                    if fast is not None and fast(data):
                        return
                    try:
                        msg = deserialize_message(data, typ)
                    except Exception as e:   # malformed CDR: reject, never die
                        self.service.warnings.warn("bad_cdr", f"dropped an undecodable "
                                                   f"message on {self.subs[key][1]}: {e}")
                        return
                    handler(msg)
            sobj = node.create_subscription(typ, topic, cb, cmd_qos,
                                            raw=raw or fast is not None)
            self.subs[key] = (sobj, sobj.topic_name, typ, cmd_qos)

        sub("effort", Float64MultiArray, TOPIC_EFFORT_COMMANDS, self._on_effort,
            self._on_effort_cdr)
        sub("joint_commands", JointState, TOPIC_JOINT_COMMANDS, self._on_joint_command,
            self._on_joint_command_cdr)
        sub("wrench", WrenchStamped, TOPIC_WRENCH, self._on_wrench)
        sub("wrench_persistent", WrenchStamped, TOPIC_WRENCH_PERSISTENT,
            self._on_wrench_persistent)
        # services: requests and responses kept until served (100 callers at once are all
        # answered; the default depth of 10 loses the rest, and callers wait forever)
        srv_qos = QoSProfile(depth=self.SERVICE_QUEUE, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE,
                             history=HistoryPolicy.KEEP_LAST)
        self.srv_reset = node.create_service(Trigger, "~/reset", self._srv_reset,
                                             qos_profile=srv_qos)
        self.srv_pause = node.create_service(SetBool, "~/pause", self._srv_pause,
                                             qos_profile=srv_qos)
        self.srv_step = node.create_service(Trigger, "~/step", self._srv_step,
                                            qos_profile=srv_qos)

    #: requests (and responses) a service keeps while they wait to be served
    SERVICE_QUEUE = 1000

    def _every(self, rate):
        """Steps between two messages at `rate` Hz (0: never)."""
        if rate <= 0:
            return 0
        return max(1, int(round(1.0 / (rate * self.sim.control_period))))

    def _setup_visualisation(self):
        """/tf and /tf_static (global, as tf2 defines them; written as CDR bytes: see
        nodes/tf.py) and the contact markers (starleth/contact_markers), each at its rate."""
        s, sim = self.settings, self.sim
        desc = sim.description
        self.frames = FrameTree(desc.model, desc.urdf_xml, s.world_frame, s.tf_frame_prefix)
        self._tf_joint_q = None      # the joints' indices in the model's q (_tf_configuration)
        self._tf_every = self._every(s.tf_rate)
        self._markers_every = self._every(s.contact_markers_rate)
        self._tf_cdr = TfMessageCdr(self.frames.names(self.frames.dynamic))
        self._tf_static_cdr = TfMessageCdr(self.frames.names(self.frames.static))
        register_msg_text(TF_TYPE, TF_MSG_TEXT)
        tf_qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.VOLATILE,
                            history=HistoryPolicy.KEEP_LAST)
        self.tf_topics = {"tf": (TOPIC_TF, tf_qos), "tf_static": (TOPIC_TF_STATIC,
                                                                  self.qos["latched"])}
        self.tf_pubs = {}
        if self._tf_every:
            try:
                from tf2_msgs.msg import TFMessage
            except ImportError:
                self.log.info("tf2_msgs is not installed (no full ROS install): /tf and "
                              "/tf_static are recorded but not published")
            else:
                for key, (topic, qos) in self.tf_topics.items():
                    self.tf_pubs[key] = self.node.create_publisher(TFMessage, topic, qos)
        self.marker_msg = self._marker_cdr = None
        if self._markers_every:
            try:
                from visualization_msgs.msg import Marker, MarkerArray
            except ImportError:
                self._markers_every = 0
                self.log.warning("visualization_msgs is not installed: no contact markers")
            else:
                self._Marker = Marker
                p = self.node.create_publisher(MarkerArray, TOPIC_CONTACT_MARKERS,
                                               self.qos["state"])
                self.pubs["contact_markers"] = (p, p.topic_name, MarkerArray,
                                                self.qos["state"])
                self.marker_msg = self._contact_marker_template(MarkerArray)
                # written as CDR bytes (SlotCdr: stamps, sphere positions and colours, arrow
                # actions and points patched into a template; None: message objects)
                self._marker_cdr = self._contact_marker_cdr(MarkerArray)
                self._marker_slots = self._contact_marker_slots(self.marker_msg)
                n = len(self.sim.contact_names)
                self._marker_points = [[0.0] * 6 for _ in range(n)]
                self._marker_colours = [self.MARKER_COLOURS[name] for name in CONTACT_STATES]

    #: colours (r, g, b, a) of the contact states (ContactInfo.state)
    MARKER_COLOURS = {"open": (0.6, 0.6, 0.6, 0.5), "stick": (0.1, 0.75, 0.2, 1.0),
                      "slip": (0.9, 0.15, 0.1, 1.0)}
    MARKER_SPHERE = 0.02         # sphere diameter [m]
    MARKER_SHAFT = 0.008         # arrow shaft diameter [m]

    def _contact_marker_template(self, MarkerArray):
        """One sphere per contact point (namespace 'contacts') and one arrow per contact
        point (namespace 'contact_forces', deleted while the contact is open), ids by
        contact index."""
        Marker = self._Marker
        msg = MarkerArray()
        frame = self.settings.world_frame
        for ns, typ in (("contacts", Marker.SPHERE), ("contact_forces", Marker.ARROW)):
            for i, name in enumerate(self.sim.contact_names):
                m = Marker()
                m.header.frame_id = frame
                m.ns, m.id, m.type, m.action = ns, i, typ, Marker.ADD
                m.pose.orientation.w = 1.0
                if typ == Marker.SPHERE:
                    m.scale.x = m.scale.y = m.scale.z = self.MARKER_SPHERE
                else:
                    m.scale.x, m.scale.y, m.scale.z = (self.MARKER_SHAFT,
                                                       2 * self.MARKER_SHAFT,
                                                       3 * self.MARKER_SHAFT)
                    m.color.r, m.color.g, m.color.b, m.color.a = 0.1, 0.35, 0.95, 1.0
                    m.points = [type(m.pose.position)(), type(m.pose.position)()]
                msg.markers.append(m)
        return msg

    def _contact_marker_slots(self, msg):
        """The fields of a contact-marker message that change per step, as (object,
        attribute, format): per sphere its stamp, position and colour, per arrow its stamp,
        action and two points (the order of _contact_marker_values)."""
        n = len(self.sim.contact_names)
        slots = []
        for m in msg.markers[:n]:
            p, c = m.pose.position, m.color
            slots += [(m.header.stamp, "sec", "i"), (m.header.stamp, "nanosec", "I"),
                      (p, "x", "d"), (p, "y", "d"), (p, "z", "d"),
                      (c, "r", "f"), (c, "g", "f"), (c, "b", "f"), (c, "a", "f")]
        for m in msg.markers[n:]:
            a, b = m.points
            slots += [(m.header.stamp, "sec", "i"), (m.header.stamp, "nanosec", "I"),
                      (m, "action", "i"), (a, "x", "d"), (a, "y", "d"), (a, "z", "d"),
                      (b, "x", "d"), (b, "y", "d"), (b, "z", "d")]
        return slots

    def _contact_marker_cdr(self, MarkerArray):
        """SlotCdr of the contact markers' slots (on a template of its own, which
        SlotCdr.create probes)."""
        msg = self._contact_marker_template(MarkerArray)
        return SlotCdr.create(msg, self._contact_marker_slots(msg))

    def _contact_marker_values(self, sec, nsec):
        """The values of the contact markers' slots: spheres at the contact points coloured
        by state; arrows from each closed contact point along its force,
        contact_marker_scale [m/N] long (an open contact's arrow is deleted and keeps its
        points)."""
        sim, Marker = self.sim, self._Marker
        scale = self.settings.contact_marker_scale
        colours = self._marker_colours
        # the contacts' points, forces and states as arrays (the values of sim.contacts'
        # records, without building them)
        positions, forces = sim.contact_points(), sim.contact_forces()
        spheres, arrows = [], []
        for p, f, state, pts in zip(positions.tolist(), forces.tolist(),
                                    sim.contact_states().tolist(), self._marker_points):
            x, y, z = p
            spheres += (sec, nsec, x, y, z, *colours[state])
            if state == 0:     # open
                arrows += (sec, nsec, Marker.DELETE, *pts)
                continue
            pts[:] = (x, y, z, x + scale * f[0], y + scale * f[1], z + scale * f[2])
            arrows += (sec, nsec, Marker.ADD, *pts)
        return spheres + arrows

    def _fill_contact_markers(self, sec, nsec):
        """The message objects of the contact markers (where no SlotCdr could be made)
        filled with _contact_marker_values."""
        for (obj, attr, _), v in zip(self._marker_slots, self._contact_marker_values(sec, nsec)):
            setattr(obj, attr, v)

    def _emit_tf(self, key, data, stamp_ns):
        pub = self.tf_pubs.get(key)
        if pub is not None:
            pub.publish(data)
        rec = self.recorder
        if rec is not None and not rec.closed:
            rec.write(self.tf_topics[key][0], data, stamp_ns)

    def _publish_visualisation(self):
        """/tf (every tf_rate-th step) and the contact markers, after the state (off the
        lockstep critical path: the controller is computing its answer meanwhile)."""
        svc = self.service
        k = svc.k
        sec, nsec = divmod(svc.stamp_ns, 1_000_000_000)
        if self._tf_every and k % self._tf_every == 0 and \
                (self.recorder is not None or self.tf_pubs):
            poses = self.frames.transforms(self._tf_configuration(), self.frames.dynamic)
            self._emit_tf("tf", self._tf_cdr.build(sec, nsec, poses), svc.stamp_ns)
        if self._markers_every and k % self._markers_every == 0 and \
                self._wanted("contact_markers", True):
            if self._marker_cdr is not None:
                self._emit_cdr("contact_markers", self._marker_cdr.build(
                    self._contact_marker_values(sec, nsec)), True)
            else:
                self._fill_contact_markers(sec, nsec)
                self._emit("contact_markers", self.marker_msg, True)

    def _tf_configuration(self):
        """q of the current state in the minimal coordinates of the URDF's model (free flyer:
        position, quaternion x y z w, joint angles), the configuration FrameTree.transforms
        takes: state_io.minimal_state's q, gathered with the joints' indices
        (state_io.joint_indices) found once."""
        sim = self.sim
        idx = self._tf_joint_q
        if idx is None:
            idx = self._tf_joint_q = joint_indices(sim.description.model, sim.joint_names)[0]
        b = sim.base_state()
        q = np.zeros(sim.description.model.nq)
        q[0:3] = b["position"]
        q[3:7] = b["orientation_xyzw"]
        q[idx] = sim.joint_positions()
        return q

    def _publish_static_transforms(self):
        """/tf_static once (transient local): the fixed joints."""
        if not self._tf_every or not self.frames.static:
            return
        poses = self.frames.transforms(self._tf_configuration(),
                                       self.frames.static)   # do not depend on q
        self._emit_tf("tf_static", self._tf_static_cdr.build(0, 0, poses),
                      self.service.stamp_ns)

    def _open_recorder(self, path):
        from .recording import McapRecorder, ProcessRecorder, QueuedRecorder, SplitRecorder
        s, sim = self.settings, self.sim
        common = dict(compression=s.record_compression,
                      custom_data={"generator": "starleth_sim sim_node"})
        # with record_max_duration / record_max_size: a rosbag2 bag directory of numbered
        # files, each complete on its own
        split = dict(max_duration_ns=int(round(s.record_max_duration * 1e9)),
                     max_size=s.record_max_size)
        try:
            # written by a process of its own: nothing of the writing on this interpreter
            self.recorder = rec = ProcessRecorder(path, **split, **common,
                                                  on_failure=self._recording_failed)
        except RecordingError as e:      # the file cannot be written: one line, exit 2
            raise ConfigError(f"parameter record: cannot record to {e}") from None
        except OSError as e:
            # no child process: a thread of this one, mostly while the controller computes
            self.log.warning(f"recording in this process (no recording process: {e})")
            try:
                file_rec = (SplitRecorder(path, **split, **common)
                            if s.record_max_duration > 0 or s.record_max_size > 0
                            else McapRecorder(path, **common))
            except OSError as e:
                raise ConfigError(f"parameter record: cannot record to {path}: "
                                  f"{e.strerror or e}") from None
            self.recorder = rec = QueuedRecorder(file_rec, on_failure=self._recording_failed)
        self._recorder_stats = rec
        for key, (p, topic, typ, qos) in self.pubs.items():
            rec.add_topic(topic, typ, qos)
        for key, (sobj, topic, typ, qos) in self.subs.items():
            rec.add_topic(topic, typ, qos)
        if self._tf_every:
            for topic, qos in self.tf_topics.values():
                rec.add_topic(topic, TF_TYPE, qos)
        cfg_yaml = yaml.safe_dump(sim.config.to_dict(), sort_keys=False)
        q0, u0 = self.service.q0, self.service.u0
        init = initial_state_record(sim, q0, u0, self.initial_state_desc["spec"])
        params = asdict(s)
        rec.add_metadata("starleth_sim", {
            "physics_config": cfg_yaml, "initial_state": json.dumps(init),
            "parameters": json.dumps(params), "joint_names": json.dumps(list(sim.joint_names)),
            "control_period": repr(sim.control_period),
            "stamp_period_ns": str(self.service.period_ns),
            "namespace": self.node.get_namespace(),
            "urdf_attachment": "starleth.urdf",
            # for starleth-replay: what re-runs this recording open loop, bit for bit
            "package_version": _package_version(),
            "joint_states_topic": self.pubs["joint_states"][1],
            "base_state_topic": self.pubs["base_state"][1],
            "wrench_topic": self.subs["wrench"][1],
            "wrench_persistent_topic": self.subs["wrench_persistent"][1],
            "replay": "torques: /joint_states effort at stamp t_(k+1) = the torque applied "
                      "over step k -> k+1 (saturated, derated; joint order joint_names); "
                      "inputs (commands, wrenches): log time t_k = the stamp of the state "
                      "after which they were taken: a wrench acts from step k -> k+1"})
        rec.add_attachment("starleth.urdf", "application/xml", sim.description.urdf_xml)
        rec.add_attachment("physics_config.yaml", "application/yaml", cfg_yaml)
        rec.add_attachment("initial_state.json", "application/json", json.dumps(init, indent=1))
        rec.add_attachment("sim_node_parameters.yaml", "application/yaml",
                           yaml.safe_dump({"/**": {"ros__parameters": params}}, sort_keys=False))

    def _publish_robot_description(self):
        msg = String(data=self.sim.description.urdf_xml)
        self._emit("robot_description", msg, True)

    def _recording_failed(self, message):
        """The recorder failed (disk full, file-size limit, I/O error, its process gone);
        it has closed the file as far as it could (message: file, cause, how to read it).
        The simulation goes on without recording; /starleth/solver says
        ``recording: failed (...)``. Called once, from the thread that found out."""
        self.recording_failure = message
        self.recorder = None
        self.log.error(f"recording failed: {message}. The simulation goes on without "
                       "recording.")

    def recording_state(self) -> str:
        """'off', 'on' or 'failed (<file>: <cause>; ...)' (/starleth/solver's recording)."""
        if self.recording_failure is not None:
            return f"failed ({self.recording_failure})"
        return "on" if self.recorder is not None else "off"

    def _check_recording_drops(self, rec):
        dropped = rec.dropped
        if dropped != self._dropped_seen:
            self._dropped_seen = dropped
            self.service.warnings.warn(
                "record_dropped", f"recording {rec.path}: the recording process is behind; "
                f"{dropped} messages dropped so far")

    # -- publishing ------------------------------------------------------------------------
    def _log_warning(self, message):
        self.log.warning(message)

    def _log_error(self, message):
        self.log.error(message)

    def _emit(self, key, msg, record):
        """Publish (and record) a message object; while recording, a topic nobody
        subscribes to is only recorded."""
        p, topic, _, _ = self.pubs[key]
        rec = self.recorder
        if record and rec is not None and not rec.closed:
            data = serialize_message(msg)
            if self._counts.get(key, 1) > 0:
                p.publish(data)
            rec.write(topic, data, self.service.stamp_ns)
        else:
            p.publish(msg)

    def _emit_cdr(self, key, data, record):
        """The same for CDR bytes."""
        p, topic, _, _ = self.pubs[key]
        rec = self.recorder
        if record and rec is not None and not rec.closed:
            if self._counts.get(key, 1) > 0:
                p.publish(data)
            rec.write(topic, data, self.service.stamp_ns)
        else:
            p.publish(data)

    SUBSCRIBER_REFRESH = 10   # steps between two looks at the subscriber counts
    #: steps between two hand-overs of the recorded messages to the writer process (a pipe
    #: write and a wake-up of that process each; SIGINT / close send the rest, a sim
    #: process killed outright loses at most these last steps, the file stays complete)
    HAND_OVER_STEPS = 8

    def _wanted(self, key, record):
        """Build and publish a topic only if it is recorded or someone subscribes (an
        unmatched publish is invisible; skipping it keeps the lockstep cycle short). The
        counts are taken after the previous state went out (publish_state): /joint_states
        every step, the other topics every SUBSCRIBER_REFRESH steps, so a new subscriber
        gets its first message at most one step (/joint_states) or that many steps late."""
        if record and self.recorder is not None:
            return True
        if self._counts_k < 0:      # no counts yet, or asked for fresh ones
            self._refresh_counts()
        return self._counts.get(key, 0) > 0

    def _refresh_counts(self):
        self._counts_k = self.service.k
        self._counts = {key: p[0].get_subscription_count() for key, p in self.pubs.items()}

    def publish_state(self, record=True):
        """Publish the state of the current step (stamp t_k) on every state topic;
        record=False: a re-send of a state already published (not recorded again)."""
        svc = self.service
        sec, nsec = divmod(svc.stamp_ns, 1_000_000_000)
        wanted = self._wanted
        timing = self.timing
        first = not (svc.counters["steps"] or svc.counters["resets"])
        base = joints = forces = None    # read from the simulator once, for every topic
        bundle = self._bundle_wanted(first)
        if bundle:
            # what controller_node waits for, in one message; the public topics follow
            # while it computes
            base, joints = base_values(self.sim), joint_values(self.sim)
            forces = self.sim.contact_forces()
            self._publish_bundle(sec, nsec, base, joints, forces)
            if timing is not None:
                timing.row[2] = time.perf_counter()
        # the public topics: what a controller waits for first, the foot wrenches and the
        # base state, then /joint_states, the message a controller answers on
        # (controller_node takes the others when it arrives: one wake-up of its executor
        # per state), then the others
        feet = [f for f in FEET if wanted(f, record)]
        if feet:
            self._publish_foot_wrenches(sec, nsec, feet, record, forces)
        want_odom, want_imu = wanted("base_state", record), wanted("imu", record)
        if (want_odom or want_imu) and base is None:
            base = base_values(self.sim)
        if want_odom:
            self._publish_odometry(sec, nsec, base, record)
        if first:   # state 0: the exact count
            send = (self.pubs["joint_states"][0].get_subscription_count() > 0
                    or (record and self.recorder is not None))
        else:
            send = wanted("joint_states", record)
        if send:
            self._publish_joint_states(
                sec, nsec, record, joints if joints is not None else joint_values(self.sim))
        if timing is not None and not bundle:
            timing.row[2] = time.perf_counter()
        if "clock" in self.pubs and wanted("clock", record):
            if self._clock_cdr is not None:
                self._emit_cdr("clock", self._clock_cdr.build(sec, nsec, ()), record)
            else:
                c = self.clock_msg.clock
                c.sec, c.nanosec = sec, nsec
                self._emit("clock", self.clock_msg, record)
        if want_imu:
            self._publish_imu(sec, nsec, base, record)
        if wanted("solver", record):
            statuses = self._diagnostics()
            if self._diag_cdr is not None:
                self._emit_cdr("solver", self._diag_cdr.build(sec, nsec, statuses), record)
            else:
                self._fill_diagnostics(sec, nsec, statuses)
                self._emit("solver", self.diag_msg, record)
        if timing is not None:
            timing.row[3] = time.perf_counter()
        if record:
            self._prepare_next_step()
            self._publish_visualisation()
            rec = self.recorder
            if rec is not None and svc.k % self.HAND_OVER_STEPS == 0:
                if hasattr(rec, "hand_over"):
                    rec.hand_over()   # the last steps' messages to the writer process
                if rec.dropped and self.recorder is not None:   # (not: it just failed)
                    self._check_recording_drops(rec)
        if timing is not None and record:
            timing.row[4] = time.perf_counter()
            timing.commit(svc.stamp_ns)
        # subscriber counts for the next state, taken now that this one is out (off the
        # lockstep critical path): /joint_states and the bundle every step, the others
        # every SUBSCRIBER_REFRESH steps
        if not (0 <= svc.k - self._counts_k < self.SUBSCRIBER_REFRESH):
            self._refresh_counts()
        else:
            for key in self.EVERY_STEP_COUNTS:
                if key in self.pubs:
                    self._counts[key] = self.pubs[key][0].get_subscription_count()

    #: the topics whose subscriber counts are taken after every step: a controller that
    #: switches between them (controller_node from /joint_states to the bundle) is
    #: followed at once
    EVERY_STEP_COUNTS = ("joint_states", "state_bundle")

    def _bundle_wanted(self, first) -> bool:
        """Send the state bundle: someone subscribes to it (the exact count for state 0 and
        for a re-send; else the count taken after the previous step). Never recorded: the
        recording has the public topics."""
        if self._bundle_cdr is None:
            return False
        if first or self._counts_k < 0:
            return self.pubs["state_bundle"][0].get_subscription_count() > 0
        return self._counts.get("state_bundle", 0) > 0

    def _publish_bundle(self, sec, nsec, base, joints, forces):
        """starleth/state_bundle: the values of joint_states, base_state and the four foot
        wrenches of this step in one Float64MultiArray (state_io.state_bundle_bytes)."""
        self.pubs["state_bundle"][0].publish(
            state_bundle_bytes(self._bundle_cdr, sec, nsec, base, joints, forces))

    def _publish_joint_states(self, sec, nsec, record, joints):
        """joint_states: position, velocity and the applied torque as effort (joints:
        state_io.joint_values)."""
        cdr = self._js_cdr
        if cdr is not None:    # CDR bytes from a template: no per-step Python->C copy
            self._emit_cdr("joint_states", cdr.build(sec, nsec, *joints), record)
            return
        js = self.js_msg
        js.header.stamp.sec, js.header.stamp.nanosec = sec, nsec
        js.position, js.velocity, js.effort = (_dbl(x) for x in joints)
        self._emit("joint_states", js, record)

    def _publish_foot_wrenches(self, sec, nsec, feet, record, forces=None):
        """starleth/<foot>/wrench: the contact force F = Λ/Δt of each foot in `feet`
        (forces: Simulator.contact_forces() where already read)."""
        cdr = self._wrench_cdr
        if cdr is not None and self._feet_first:
            if forces is None:
                forces = self.sim.contact_forces()
            for name, f in zip(FEET, forces[:len(FEET)].tolist()):
                if name in feet:
                    self._emit_cdr(name, cdr.build(sec, nsec, f), record)
            return
        for c in self.sim.contacts[:len(FEET)]:
            if c.name not in feet:
                continue
            m = self.wrench_msgs[c.name]
            m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
            f = m.wrench.force
            f.x, f.y, f.z = float(c.force[0]), float(c.force[1]), float(c.force[2])
            self._emit(c.name, m, record)

    def _publish_odometry(self, sec, nsec, base, record):
        """starleth/base_state: pose in the world, twist in the base frame."""
        p, quat, _, w, _, v_body = base
        if self._odom_cdr is not None:
            self._emit_cdr("base_state", self._odom_cdr.build(
                sec, nsec, (*p, *quat, *v_body, *w)), record)
            return
        o = self.odom_msg
        o.header.stamp.sec, o.header.stamp.nanosec = sec, nsec
        pp, po = o.pose.pose.position, o.pose.pose.orientation
        pp.x, pp.y, pp.z = p
        po.x, po.y, po.z, po.w = quat
        tl, ta = o.twist.twist.linear, o.twist.twist.angular
        tl.x, tl.y, tl.z = v_body
        ta.x, ta.y, ta.z = w
        self._emit("base_state", o, record)

    def _publish_imu(self, sec, nsec, base, record):
        """starleth/imu: orientation, body rates, proper acceleration."""
        p, quat, v, w, R, _ = base
        a_proper = self.imu.proper_acceleration(self.service.k, v, R)
        if self._imu_cdr is not None:
            self._emit_cdr("imu", self._imu_cdr.build(
                sec, nsec, (*quat, *w, float(a_proper[0]), float(a_proper[1]),
                            float(a_proper[2]))), record)
            return
        imu = self.imu_msg
        imu.header.stamp.sec, imu.header.stamp.nanosec = sec, nsec
        io_ = imu.orientation
        io_.x, io_.y, io_.z, io_.w = quat
        iw, ia = imu.angular_velocity, imu.linear_acceleration
        iw.x, iw.y, iw.z = w
        ia.x, ia.y, ia.z = float(a_proper[0]), float(a_proper[1]), float(a_proper[2])
        self._emit("imu", imu, record)

    def _prepare_next_step(self):
        """The controller now works on its answer to the state just published: do the
        torque-independent part of the next step meanwhile (Simulator.prepare), which takes
        it off the lockstep critical path (command in -> step -> state out), unless the next
        step runs in one kernel call (the common case: no wrench), which is faster than the
        rest of a prepared step. The result of the step is the same with or without it."""
        if self.sim.next_step_in_one_kernel():
            return
        try:
            self.sim.prepare()
        except Exception as e:   # pragma: no cover - the step redoes it and reports
            self.service.warnings.warn("prepare", f"preparing the next step failed: {e}")

    INTERFACE_STATUS_EVERY = 40   # steps (10 Hz at 400 Hz); also on every lockstep timeout

    def _diagnostics(self):
        """The statuses of /starleth/solver: [(0 = solver | 1 = interface, level, message,
        values as str)]; the interface status every INTERFACE_STATUS_EVERY steps, on a
        lockstep timeout and while paused."""
        svc = self.service
        d = self.sim.diagnostics
        vals = (d.iterations, d.max_iterations_step, d.converged, d.status, repr(d.residual),
                d.active_contacts, d.retried, repr(d.step_time), d.physics_steps,
                d.nonconverged_steps, d.loaded_contacts_opened, d.loaded_contacts_opened_total,
                d.projections, d.projection_iterations)
        out = [(0, DiagnosticStatus.OK if d.converged else DiagnosticStatus.WARN, d.status,
                [str(v) for v in vals])]
        if not (svc.k % self.INTERFACE_STATUS_EVERY == 0 or svc.last_step_timed_out
                or svc.paused):
            return out
        out.append(self._interface_status())
        return out

    def _interface_status(self):
        """The interface status of /starleth/solver: (1, level, message, values as str);
        ERROR with the reason while paused on a step that was not physics, WARN on a
        lockstep timeout or a failed recording."""
        svc = self.service
        ps = self._period_summary
        c = svc.counters
        vals = (self.settings.mode, self.settings.real_time_factor, svc.stamp_ns * 1e-9, svc.k,
                svc.paused, not svc.started, *(c[k] for k in SimService.COUNTERS),
                ps.get("period_error_p50_ms", ""), ps.get("period_error_p99_ms", ""),
                ps.get("period_error_max_ms", ""), self.period_stats.overruns,
                *self._recording_counts(), self.recording_state())
        if svc.failed:
            level, message = DiagnosticStatus.ERROR, f"paused: {svc.pause_reason}"
        elif svc.last_step_timed_out:
            level, message = DiagnosticStatus.WARN, "lockstep timeout"
        else:
            level = DiagnosticStatus.WARN if self.recording_failure is not None else \
                DiagnosticStatus.OK
            message = "paused" if svc.paused else "running"
        return (1, level, message, [str(v) for v in vals])

    #: s (wall clock) between two /starleth/solver messages while paused: a monitor tells
    #: a paused simulator from a dead one
    PAUSED_DIAGNOSTICS_PERIOD = 1.0

    def _publish_paused_diagnostics(self):
        """While paused: /starleth/solver every PAUSED_DIAGNOSTICS_PERIOD s with the
        interface status (stamp: the current sim time; published, not recorded: the bag
        keeps one message per step)."""
        now = time.monotonic()
        if now - self._paused_diag_at < self.PAUSED_DIAGNOSTICS_PERIOD:
            return
        self._paused_diag_at = now
        pub = self.pubs["solver"][0]
        if pub.get_subscription_count() == 0:
            return
        sec, nsec = divmod(self.service.stamp_ns, 1_000_000_000)
        statuses = self._diagnostics()           # paused: the interface status too
        if self._diag_cdr is not None:
            pub.publish(self._diag_cdr.build(sec, nsec, statuses))
        else:
            self._fill_diagnostics(sec, nsec, statuses)
            pub.publish(self.diag_msg)

    def _recording_counts(self):
        """(messages recorded, dropped) -- (0, 0) without a recording."""
        rec = self._recorder_stats
        if rec is None:
            return 0, 0
        return rec.message_count - rec.dropped, rec.dropped

    def _fill_diagnostics(self, sec, nsec, statuses):
        """The DiagnosticArray message object from _diagnostics() (when the CDR writer is
        not available)."""
        self.diag_msg.header.stamp.sec, self.diag_msg.header.stamp.nanosec = sec, nsec
        objs = (self.solver_status, self.iface_status)
        for index, level, message, values in statuses:
            st = objs[index]
            st.level, st.message = level, message
            for kv, v in zip(st.values, values):
                kv.value = v
        self.diag_msg.status = self._diag_both if len(statuses) > 1 else self._diag_solver_only

    # -- callbacks -------------------------------------------------------------------------
    def _record_input(self, key, data):
        rec = self.recorder
        if rec is not None and not rec.closed:
            rec.write(self.subs[key][1], data, self.service.stamp_ns)

    def _on_effort(self, msg):
        if self.service.submit_effort_array(msg.data)[0] and self._step_on_answer:
            self._advance()

    def _on_effort_cdr(self, data) -> bool:
        ok, tau = self.decoder.effort_array(data)
        if not ok:
            return False
        if self.service.submit_effort_array(tau)[0] and self._step_on_answer:
            self._advance()
        return True

    def _on_joint_command_cdr(self, data) -> bool:
        if self.timing is not None:
            self.timing.row[0] = time.perf_counter()
        ok, stamp_ns, tau = self.decoder.joint_command(data)
        if not ok:
            return False
        if self.service.submit_ordered_joint_command(tau, stamp_ns)[0] and self._step_on_answer:
            self._advance()
        return True

    def _on_joint_command(self, msg):
        st = msg.header.stamp
        if self.service.submit_joint_command(msg.name, msg.effort,
                                             st.sec * 1_000_000_000 + st.nanosec)[0] \
                and self._step_on_answer:
            self._advance()

    def _advance(self):
        """Lockstep without pacing: step as soon as the answer is in, right in the
        subscription callback (saves a trip through the executor on the critical path)."""
        svc = self.service
        if svc.answered and not svc.paused and not self._stop:
            if svc.step() is not None:
                if self.timing is not None:
                    self.timing.row[1] = time.perf_counter()
                self.publish_state()

    def _wrench(self, key, msg, persistent):
        f, m = msg.wrench.force, msg.wrench.torque
        self.service.submit_wrench(msg.header.frame_id, (f.x, f.y, f.z), (m.x, m.y, m.z),
                                   persistent)

    def _on_wrench(self, msg):
        self._wrench("wrench", msg, False)

    def _on_wrench_persistent(self, msg):
        self._wrench("wrench_persistent", msg, True)

    def _srv_reset(self, request, response):
        self.service.reset()
        self.imu.restart()
        self.publish_state()
        self.log.info(f"reset to the initial state at t={self.service.stamp_ns * 1e-9:.4f} s")
        response.success = True
        response.message = f"reset; sim time {self.service.stamp_ns * 1e-9:.4f} s"
        return response

    def _srv_pause(self, request, response):
        svc = self.service
        if svc.failed and not request.data:
            response.success = False
            response.message = f"cannot resume: {svc.pause_reason}; call ~/reset"
            return response
        was = svc.paused
        svc.paused = bool(request.data)
        response.success = True
        response.message = ("paused" if svc.paused else "running") + \
            f" at sim time {svc.stamp_ns * 1e-9:.4f} s"
        if was != svc.paused:
            self.log.info(response.message)
        return response

    def _srv_step(self, request, response):
        svc = self.service
        if not svc.paused:
            response.success = False
            response.message = "not paused: call ~/pause with data=true first"
            return response
        if svc.step() is None:
            response.success = False
            response.message = f"no step: {svc.pause_reason}; call ~/reset"
            return response
        self.publish_state()
        response.success = True
        response.message = f"stepped to sim time {svc.stamp_ns * 1e-9:.4f} s"
        return response

    # -- loops -----------------------------------------------------------------------------
    def request_stop(self, *_):
        self._stop = True

    CONTEXT_CHECK_PERIOD = 0.01   # s: look at the ROS context at most this often

    def _running(self):
        """Not stopped and the context not shut down (the context, whose check takes a lock,
        is looked at every CONTEXT_CHECK_PERIOD s; a shut-down context also ends _spin)."""
        if self._stop:
            return False
        now = time.monotonic()
        if now < self._context_ok_until:
            return True
        if not self.context.ok():
            return False
        self._context_ok_until = now + self.CONTEXT_CHECK_PERIOD
        return True

    def _spin(self, executor, timeout):
        try:
            executor.spin_once(timeout_sec=max(0.0, timeout))
        except Exception as e:  # ExternalShutdownException, context shut down
            if not self.context.ok():
                self._stop = True
            else:
                raise e

    def run(self, executor):
        """Run until request_stop() or the context is shut down."""
        # everything built so far lives for the whole run: move it out of the garbage
        # collector's generations, so that a full collection in the loop stays short
        gc.collect()
        gc.freeze()
        self._n_state_subs = self._state_subscriber_count()
        self.publish_state()
        if self.settings.mode == "lockstep":
            self._step_on_answer = self.settings.real_time_factor == 0.0
            self._run_lockstep(executor)
        else:
            self._run_realtime(executor)

    def _republish_state(self):
        """Send the current state again on every topic with subscribers (not recorded)."""
        self._counts_k = -10 ** 9       # fresh subscriber counts
        self.publish_state(record=False)

    #: the topics a controller waits for before it answers a state
    STATE_TOPICS = ("joint_states", "base_state", *FEET, "state_bundle")

    def _state_subscriber_count(self) -> int:
        return sum(self.pubs[k][0].get_subscription_count() for k in self.STATE_TOPICS
                   if k in self.pubs)

    def _republish_for_new_subscribers(self, resend=True) -> bool:
        """While the node waits for a command: when a new subscriber to any state topic
        appeared since the last look, send the current state again on every topic (same
        stamp, not recorded; resend=False only takes the count), so that a controller that
        connects late, or a restarted one, sees a whole state it can answer."""
        n = self._state_subscriber_count()
        new = n > self._n_state_subs
        self._n_state_subs = n
        if new and resend:
            self._republish_state()
        return new and resend

    def _before_first_step(self) -> bool:
        svc = self.service
        return not (svc.counters["steps"] or svc.counters["resets"])

    def _update_period_summary(self):
        self._period_summary = {k: round(v, 4) if isinstance(v, float) else v
                                for k, v in self.period_stats.summary().items()}

    def _set_realtime_priority(self):
        """realtime_priority > 0: SCHED_FIFO for the stepping thread (needs CAP_SYS_NICE or
        an rtprio limit); on failure the loop runs at normal priority, with a warning."""
        prio = self.settings.realtime_priority
        if prio <= 0:
            return
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
            self.log.info(f"stepping thread runs with SCHED_FIFO priority {prio}")
        except (OSError, AttributeError) as e:
            self.log.warning(f"realtime_priority {prio}: cannot switch to SCHED_FIFO ({e}); "
                             "running at normal priority")

    def _run_realtime(self, executor):
        self._set_realtime_priority()
        svc, ps = self.service, self.period_stats
        period = self.sim.control_period / self.settings.real_time_factor
        clock = time.perf_counter
        next_tick = clock() + period
        margin = self.SPIN_MARGIN
        while self._running():
            if svc.paused:
                # started paused: a late subscriber gets state 0 (after the first step,
                # every stamp goes out once)
                self._republish_for_new_subscribers(resend=self._before_first_step())
                self._publish_paused_diagnostics()
                self._spin(executor, 0.05)
                next_tick = clock() + period
                ps.restart()
                continue
            # wait in the executor (commands, services) until shortly before the tick,
            # then spin on the clock
            while True:
                remaining = next_tick - clock()
                if remaining <= margin or not self._running():
                    break
                self._spin(executor, min(remaining - margin, 0.05))
                if svc.paused:
                    break
            if svc.paused or not self._running():
                continue
            while clock() < next_tick:
                pass
            t = clock()
            ps.tick(t)
            if svc.step() is not None:
                self.publish_state()
            if svc.k % 400 == 0:
                self._update_period_summary()
            next_tick += period
            lag = clock() - next_tick
            if lag > 0.0:
                # behind the wall clock: the next ticks follow at once until caught up; too
                # far behind (the host cannot keep up), drop the missed ticks and say so
                if lag > self.MAX_CATCH_UP:
                    ps.overruns += 1
                    svc.warnings.warn("overrun", f"realtime loop overrun: {lag * 1e3:.1f} ms "
                                      "behind the wall clock; skipping ahead "
                                      f"({ps.overruns} overruns so far)")
                    next_tick = clock() + period

    REPUBLISH_PERIOD = 0.5        # s: re-send state 0 this often until the first command
    NEW_SUBSCRIBER_CHECK = 0.05   # s: look for new subscribers this often while waiting

    def _run_lockstep(self, executor):
        svc, s = self.service, self.settings
        clock = time.monotonic
        pace = self.sim.control_period / s.real_time_factor if s.real_time_factor > 0 else 0.0
        pace_origin = None
        version = svc.state_version
        deadline = clock() + s.lockstep_timeout
        last_republish = clock()
        while self._running():
            if svc.paused:
                self._republish_for_new_subscribers(resend=self._before_first_step())
                self._publish_paused_diagnostics()
                self._spin(executor, 0.05)
                pace_origin = None
                version = -1
                continue
            if svc.state_version != version:   # a new state was published (step/reset)
                version = svc.state_version
                deadline = clock() + s.lockstep_timeout
            if svc.answered or (svc.started and clock() >= deadline):
                timed_out = not svc.answered
                if pace:
                    now = time.perf_counter()
                    if pace_origin is None:
                        pace_origin = (now, svc.k)
                    due = pace_origin[0] + (svc.k - pace_origin[1]) * pace
                    while now < due and self._running():
                        if due - now > 0.002:
                            time.sleep(due - now - 0.001)
                        now = time.perf_counter()
                if svc.step(timed_out=timed_out) is not None:
                    self.publish_state()
                continue
            if not svc.started:
                # before the first command: no timeout; re-send the whole state when a new
                # subscriber appears and every 0.5 s, so a late controller sees it
                now = clock()
                if self._republish_for_new_subscribers():
                    last_republish = now
                elif now - last_republish > self.REPUBLISH_PERIOD:
                    last_republish = now
                    self._republish_state()
                self._spin(executor, 0.05)
                continue
            # waiting for the answer to a state: a controller that is slow to answer may be
            # a new one (restarted); re-send the state when new subscribers appear (looked
            # at only after NEW_SUBSCRIBER_CHECK s, off the fast lockstep cycle)
            now = clock()
            if now - (deadline - s.lockstep_timeout) > self.NEW_SUBSCRIBER_CHECK and \
                    now - last_republish > self.NEW_SUBSCRIBER_CHECK:
                last_republish = now
                self._republish_for_new_subscribers()
            self._spin(executor, min(deadline - clock(), 0.05))

    # -- shutdown --------------------------------------------------------------------------
    def summary(self) -> dict:
        d = self.service.summary()
        if self.settings.mode == "realtime":
            d.update(self.period_stats.summary())
        if self._recorder_stats is not None:
            d["recorded_messages"], d["recording_dropped"] = self._recording_counts()
            d["recording"] = self.recording_state()
        return d

    #: s: SIGINT / SIGTERM end the node within 2 s whatever the recorder has queued (what
    #: the writer has not taken by then is dropped, counted in the log)
    CLOSE_TIMEOUT = 1.0

    def close(self):
        """Finalise the recording (idempotent; at most CLOSE_TIMEOUT s) and log a summary."""
        rec = self.recorder
        if rec is not None and not rec.closed:
            summary = self.summary()
            try:
                rec.close(timeout=self.CLOSE_TIMEOUT, metadata={"starleth_sim_summary": {
                    k: json.dumps(v) for k, v in summary.items()}})
            except (RecordingError, OSError) as e:   # the file is closed as far as it could
                if self.recording_failure is None:
                    self.recording_failure = str(e)
                    self.log.error(f"recording failed while closing: {e}")
            else:
                note = f"; {rec.close_note}" if rec.close_note else ""
                self.log.info(f"recording finalised: {rec.path} "
                              f"({rec.message_count - rec.dropped} messages){note}")
        summary = self.summary()
        self.log.info("summary: " + json.dumps(summary))
        return summary

    def destroy(self):
        self.close()
        self.node.destroy_node()


def _split_controller_params(argv):
    """(argv without them, {name: value}) of the ``--controller-param NAME:=VALUE`` options
    before ``--ros-args`` (values read as YAML, as ROS reads -p values); ``--composed``
    is dropped."""
    out, params = [], {}
    it = iter(argv)
    for a in it:
        if a == "--ros-args":
            out.append(a)
            out.extend(it)
            break
        if a == "--composed":        # python -m starleth_sim.ros.sim_node --composed
            continue
        if a == "--controller-param" or a.startswith("--controller-param="):
            kv = a.split("=", 1)[1] if "=" in a else next(it, "")
            if ":=" not in kv:
                raise ValueError(f"--controller-param {kv!r}: expected NAME:=VALUE")
            k, v = kv.split(":=", 1)
            params[k] = yaml.safe_load(v) if v else ""
            continue
        out.append(a)
    return out, params


def main_composed(args=None):
    """Console script ``sim_node_composed``: sim_node and controller_node
    (starleth_controller) in one process on one executor, with the same topics, services
    and parameters as the two processes (speed over process isolation: no trip between
    processes through the operating system). ``--ros-args`` go to sim_node (its node name,
    namespace, parameters); the controller, named ``controller_node`` in the same
    namespace, takes its parameters from ``--controller-param NAME:=VALUE`` options given
    before them, e.g. ``sim_node_composed --controller-param mode:=trot --ros-args -p
    record:=run.mcap``. Exit status as ``sim_node``'s."""
    argv = list(sys.argv if args is None else args)
    try:
        argv, ctl_params = _split_controller_params(argv)
    except ValueError as e:
        print(f"sim_node_composed: {e}", file=sys.stderr)
        return 2
    return main(argv, controller_params=ctl_params)


def main(args=None, controller_params=None):
    """Console script ``sim_node``. SIGINT/SIGTERM stop the loop and finalise the recording
    (exit 0); a bad parameter exits with 2 before any physics is set up.
    `controller_params` (a dict): also run starleth_controller's ControllerNode with these
    parameters on the same executor (:func:`main_composed`)."""
    if not init_ros("sim_node", sys.argv if args is None else args):
        return 2
    holder = {}
    signals = StopSignals(lambda: holder["node"].request_stop() if "node" in holder else None)
    executor = None
    try:
        try:
            sim_node = holder["node"] = SimNode()
        except (ConfigError, ValueError, OSError) as e:
            print(f"sim_node: configuration error: {e}", file=sys.stderr)
            return 2
        if signals.requested:
            sim_node.request_stop()
        executor, kind = make_executor(sim_node.settings.executor, sim_node.context)
        executor.add_node(sim_node.node)
        if controller_params is not None:
            from starleth_controller.controller_node import ControllerNode
            try:
                ctl = holder["controller"] = ControllerNode(
                    context=sim_node.context, parameter_overrides=controller_params,
                    namespace=sim_node.node.get_namespace(), use_global_arguments=False)
            except ValueError as e:
                print(f"controller_node: configuration error: {e}", file=sys.stderr)
                return 2
            executor.add_node(ctl)
            kind += ", with controller_node in this process"
        sim_node.log.info(f"executor: {kind}; ready")
        try:
            sim_node.run(executor)
        finally:
            signals.ignore()          # no further signals while the file is finalised
            sim_node.close()
        if "controller" in holder:
            holder["controller"].log.info(f"stopped; {holder['controller'].summary()}")
        return 0
    finally:
        if "controller" in holder:
            try:
                holder["controller"].destroy_node()
            except Exception:
                pass
        shutdown_ros(holder["node"].node if "node" in holder else None, executor)


if __name__ == "__main__":
    sys.exit(main_composed() if "--controller-param" in sys.argv[1:2] or
             "--composed" in sys.argv[1:2] else main())
