"""``controller_node``: the StarlETH stand / trot controller (``StarlethController``) behind
ROS 2 topics. A thin adapter: no control law in here.

    ros2 run starleth_sim controller_node
    python -m starleth_controller.controller_node --ros-args -p mode:=trot

Subscribed (topic names are the defaults, relative: ``--ros-args -r __ns:=/robot1`` puts
them under /robot1, beside that robot's sim_node; remap them for another robot):

    starleth/state_bundle                std_msgs/Float64MultiArray   sim_node's state of a step
                                                                      in one message
    joint_states                         sensor_msgs/JointState       by name: position, velocity
    starleth/base_state                  nav_msgs/Odometry            ground-truth base state
    starleth/{LF,RF,LH,RH}_foot/wrench   geometry_msgs/WrenchStamped  contact: |force| > threshold
    cmd_vel                              geometry_msgs/Twist          linear.x, linear.y, angular.z
    robot_description                    std_msgs/String              with robot_description:=true

Published:

    joint_commands                       sensor_msgs/JointState       names + effort; header.stamp
                                                                      = the state's stamp
    (effort_array_topic, off by default) std_msgs/Float64MultiArray   12 torques, joint order

Service ``~/trot`` (std_srvs/SetBool): true = trot, false = stand (sets the ``mode`` parameter).

Time: with ``use_sim_time:=true`` the node's clock follows /clock, and ``cmd_vel_timeout``
counts sim time; the controller's own time is always the state's stamp. The 0.1 s after
which a repeated state is answered again is wall time (it is about messages in flight, and
a lockstep simulator's clock stands still while it waits for the answer).

The base state is taken from ``/starleth/base_state`` as *ground truth* (the simulator's
Odometry: pose in the world frame, twist in the child (base) frame as REP 105 says; set
``twist_frame:=parent`` for a source that gives the linear velocity in the world frame). A
state estimator is out of scope.

State input (``state_input``): ``auto`` (the default) subscribes to the state bundle
(:mod:`starleth_interface.state_bundle`: sim_node's joint state, base state and foot forces
of one step in one message, the same floats) and to the public state topics; the first
valid bundle makes the node unsubscribe from the public ones and read bundles alone (one
message per step instead of six: sim_node then sends the public topics only to their other
subscribers). Any start order works: the bundle is looked for as long as the node runs. A
source that sends no bundle (a robot driver, a bag) is read from the public topics;
after a bundle source, restart the node (or set ``state_input:=topics``) to read one.
``bundle`` / ``topics`` read only that input.

Synchronisation: a simulator (or robot driver) publishes the state of one control step on
all state topics with the same header stamp. The node keeps the messages of the last few
stamps; as soon as the joint state, the base state and the four foot wrenches of one stamp
have all arrived (in any order), it runs one controller update with t = that stamp and
publishes the torques stamped with it, so a lockstep simulator steps on the answer. A
/joint_states repeating the stamp last answered, more than 0.1 s after the answer, gets the
same answer again (a simulator re-sending its first state because the first answer went out
before the topics matched).

The base state and the foot wrenches are subscribed on a hidden helper node
(``_controller_node_side_inputs``) that no executor spins; their messages are taken from the
subscriptions' queues when a joint state arrives (and, while a joint state waits for the
rest of its stamp, every 0.5 ms by a steady-clock timer): the executor wakes once per
state, not six times. A simulator that sends /joint_states last (sim_node) is answered
at once; any other order works too.

The state topics are taken as CDR bytes and the floats of the common case are read
straight from them (``starleth_interface.msg_cdr``; anything else is deserialised by rclpy
and validated as before); the command goes out as CDR bytes patched into a template.
``ControllerNode.timing`` (a :class:`CycleTimes`, benchmarks only) times each cycle.

Robustness: a message with NaN/inf values, missing joints or wrong array sizes is logged
(throttled) and ignored; no command is published for its stamp. Exceptions in the controller
are logged and answered with nothing; the node never exits on bad input.

Nothing here is specific to the StarlETH simulator beyond the default topic names and the
URDF; the node does not import ``starleth_sim``.
"""
from __future__ import annotations

import array
import math
import sys
import time

import numpy as np

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy, DurabilityPolicy, HistoryPolicy
from rclpy.serialization import deserialize_message
from rcl_interfaces.msg import SetParametersResult
from sensor_msgs.msg import JointState
from nav_msgs.msg import Odometry
from geometry_msgs.msg import WrenchStamped, Twist
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import SetBool

from starleth_interface.compile_notice import CompileNotice
from starleth_interface.ros_helpers import (CPU_SCHEDULING, CPU_SCHEDULING_HELP, EXECUTORS,
                                            ParameterSpec, StopSignals, ThrottledLog,
                                            declare_parameters, init_ros, make_executor,
                                            set_cpu_scheduling, shutdown_ros)
from starleth_interface.cycle_times import CONTROLLER_CYCLE_FIELDS, CycleTimes  # noqa: F401
from starleth_interface.msg_cdr import (ODOM_FIELDS, WRENCH_FIELDS, JointStateCdr,
                                       JointStateReader, StampedReader)
from starleth_interface import state_bundle
from starleth_interface.topics import (TOPIC_BASE_STATE, TOPIC_JOINT_COMMANDS,
                                       TOPIC_JOINT_STATES, TOPIC_STATE_BUNDLE,
                                       foot_wrench_topic)
from .controller import StarlethController
from .inputs import MODES, Command, ControllerParams, RobotState
from .kernels import node_state, squared_norm4
from .warmup import warm_up
from .model import JOINT_NAMES, LEGS, default_urdf_path

_sum = np.add.reduce     # = ndarray.sum, without its wrapper (a finite sum: all finite)

DEFAULT_WRENCH_TOPICS = tuple(foot_wrench_topic(f"{leg}_foot") for leg in LEGS)


def state_from_values(stamp_ns, position, velocity, perm, odom, forces, threshold,
                      twist_in_child, R):
    """The RobotState of one stamp, read by the node_state kernel into fresh arrays: joint
    positions and velocities (perm: their indices in the public order), the 13 odometry
    values (pose; twist, its linear part in the base frame when twist_in_child, else in the
    world), the feet's forces (4 x 3; contact where |force| > threshold); R: the kernel's
    rotation (scratch, 3 x 3). None when the kernel leaves the values to the node's checks
    (a non-finite or huge value, a quaternion of squared norm outside (0.5, 2))."""
    q, dq, pb, quat, v, w = (np.empty(12), np.empty(12), np.empty(3), np.empty(4),
                             np.empty(3), np.empty(3))
    contact = np.empty(4, dtype=bool)
    if node_state(np.asarray(position, dtype=float), np.asarray(velocity, dtype=float), perm,
                  odom, forces, threshold, q, dq, pb, quat, v, w, R, contact) != 0:
        return None
    if twist_in_child:   # base frame -> world frame
        v = R @ v
    return RobotState(stamp_ns * 1e-9, q, dq, pb, quat, v, w, contact, forces)


def compile_kernels(log=print, threshold: float = ControllerParams.contact_force_threshold):
    """Compiles (or loads from numba's cache) every kernel the node runs before its first
    state: the controller's (warmup.warm_up) and the state reader's (node_state, with the
    argument types of a state bundle), saying so while it takes long (CompileNotice: about
    10 s the first time after an install). Returns the seconds taken."""
    with CompileNotice("the controller's kernels", log, estimate=10.0) as notice:
        warm_up()
        v = np.zeros(state_bundle.SIZE)
        v[state_bundle.BASE][6] = 1.0           # (a unit quaternion)
        state_from_values(0, v[state_bundle.SLICES["q"]], v[state_bundle.SLICES["u"]],
                          np.arange(12, dtype=np.int64), np.array(v[state_bundle.BASE]),
                          np.array(v[state_bundle.SLICES["force"]].reshape(4, 3)),
                          float(threshold), True, np.eye(3))
    return notice.seconds


P = ParameterSpec
#: the node's parameters: type, default, description, bounds (one schema: it gives the
#: declare_parameter descriptors and the checks). Every number has a range: the contact
#: threshold up to 1000 N (StarlETH weighs ~250 N: a higher one never sees a contact), the
#: velocity clips up to 10 m/s and 10 rad/s (the trot is < 1 m/s), the periods up to 1 hour.
PARAMETERS = (
    P("mode", str, "stand", "stand | trot; settable at runtime (also through the ~/trot "
      "service)", read_only=False, choices=MODES),
    P("urdf", str, "", "URDF path or XML text for the controller's model; empty = the "
      "package's starleth.urdf"),
    P("robot_description", bool, False, "true: build the model from the robot_description "
      "topic (transient local) instead of `urdf`"),
    P("joint_commands_topic", str, TOPIC_JOINT_COMMANDS, "sensor_msgs/JointState command "
      "topic (names + effort, stamped with the state answered); empty = off"),
    P("effort_array_topic", str, "", "also publish a std_msgs/Float64MultiArray of the 12 "
      "torques on this topic (e.g. /joint_group_effort_controller/commands); empty = off. Do "
      "not send both to a lockstep simulator."),
    P("state_input", str, "auto", "auto: the public state topics until a state bundle "
      "arrives, then the bundle alone | bundle | topics", choices=("auto", "bundle", "topics")),
    P("state_bundle_topic", str, TOPIC_STATE_BUNDLE, "std_msgs/Float64MultiArray state "
      "bundle input (sim_node's; layout in starleth_interface.state_bundle)"),
    P("joint_states_topic", str, TOPIC_JOINT_STATES, "sensor_msgs/JointState input"),
    P("base_state_topic", str, TOPIC_BASE_STATE, "nav_msgs/Odometry input (ground truth)"),
    P("foot_wrench_topics", list, list(DEFAULT_WRENCH_TOPICS), "geometry_msgs/WrenchStamped "
      "inputs, feet in the order LF, RF, LH, RH"),
    P("cmd_vel_topic", str, "cmd_vel", "geometry_msgs/Twist velocity command"),
    P("twist_frame", str, "child", "frame of the Odometry twist's linear velocity: child "
      "(base, REP 105) | parent (world)", choices=("child", "parent")),
    P("contact_force_threshold", float, ControllerParams.contact_force_threshold,
      "a foot is in contact when |force| exceeds this "
      "[N]", read_only=False, minimum=0.0, maximum=1000.0),
    P("max_linear_speed", float, 0.6, "clip of |(linear.x, linear.y)| of /cmd_vel [m/s]",
      read_only=False, minimum=0.0, maximum=10.0),
    P("max_yaw_rate", float, 1.0, "clip of |angular.z| of /cmd_vel [rad/s]", read_only=False,
      minimum=0.0, maximum=10.0),
    P("cmd_vel_timeout", float, 0.0, "seconds (the node's clock: sim time with use_sim_time) "
      "after the last cmd_vel when the velocity command falls back to zero; 0 = never",
      read_only=False, minimum=0.0, maximum=3600.0),
    P("state_reliability", str, "reliable", "QoS reliability of the state subscriptions: "
      "reliable | best_effort", choices=("reliable", "best_effort")),
    P("warn_throttle_period", float, 2.0, "minimum seconds between two warnings of the same "
      "kind", read_only=False, minimum=0.0, maximum=3600.0),
    P("executor", str, "events", "events (rclpy's C++ EventsExecutor) | single_threaded",
      choices=EXECUTORS),
    P("cpu_scheduling", str, "default", CPU_SCHEDULING_HELP, choices=CPU_SCHEDULING),
)
PARAMETERS_BY_NAME = {p.name: p for p in PARAMETERS}


class _Slot:
    """The state of one stamp as read from its messages: joint state (sec, nanosec, names,
    position, velocity), base state (13 floats: position, orientation xyzw, linear and
    angular velocity), 4 wrench forces (3 floats each)."""
    __slots__ = ("js", "odom", "wrench", "n", "t_first")

    def __init__(self):
        self.t_first = time.perf_counter()
        self.js = None
        self.odom = None
        self.wrench = [None, None, None, None]
        self.n = 0


def _stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def _finite(*values) -> bool:
    try:
        return math.isfinite(math.fsum(values))
    except (TypeError, ValueError, OverflowError):
        return False


class ControllerNode(Node):
    """The rclpy node. ``ControllerNode()`` inside an initialised rclpy context; spin it with
    any executor (``main`` uses the EventsExecutor)."""

    MAX_PENDING = 16   # stamps kept while waiting for the rest of a state
    REPEAT_AFTER = 0.1  # s: a repeated state this long after its answer is answered again

    def __init__(self, node_name="controller_node", context=None, parameter_overrides=None,
                 **kwargs):
        super().__init__(node_name, context=context,
                         parameter_overrides=[Parameter(k, value=v) for k, v in
                                              (parameter_overrides or {}).items()], **kwargs)
        self.log = self.get_logger()
        p = declare_parameters(self, PARAMETERS)
        self._check_static(p)
        self._warn = ThrottledLog(self.log.warning, float(p["warn_throttle_period"]))
        self._mode = p["mode"]
        self._threshold = float(p["contact_force_threshold"])
        self._max_v = float(p["max_linear_speed"])
        self._max_w = float(p["max_yaw_rate"])
        self._cmd_vel_timeout = float(p["cmd_vel_timeout"])
        self._twist_in_child = p["twist_frame"] == "child"
        self.executor_kind = p["executor"]
        err = set_cpu_scheduling(p["cpu_scheduling"])
        if err:
            self.log.warning(f"cpu_scheduling {p['cpu_scheduling']}: {err}")
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self._vel = (0.0, 0.0, 0.0)
        self._vel_time = None
        self.command = Command(self._mode)
        self.counters = {"states": 0, "commands": 0, "rejected": 0, "repeated": 0,
                         "dropped_incomplete": 0, "controller_errors": 0}
        self._pending: dict[int, _Slot] = {}
        self._last_answer = None          # (stamp_ns, (sec, nanosec), effort, monotonic time)
        self._perm_cache = {}             # tuple(names) -> index array (public order)
        self._kernel_perm = {}            # the same as int64 arrays for node_state
        self._R_node = np.eye(3)          # base -> world rotation of the last state
        self._ctrl_mode = None
        self.controller = None
        self._waiting_state = None        # the last state that came before the model

        # publishers
        cmd_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE,
                             history=HistoryPolicy.KEEP_LAST)
        self.pub_cmd = (self.create_publisher(JointState, p["joint_commands_topic"], cmd_qos)
                        if p["joint_commands_topic"] else None)
        self.pub_array = (self.create_publisher(Float64MultiArray, p["effort_array_topic"],
                                                cmd_qos) if p["effort_array_topic"] else None)
        self._cmd_msg = JointState()
        self._cmd_msg.name = list(JOINT_NAMES)
        # commands go out as CDR bytes patched into a template (None: as message objects)
        self._cmd_cdr = JointStateCdr.create(JOINT_NAMES, ("effort",))
        self._js_reader = JointStateReader()
        self._odom_reader = StampedReader(Odometry, ODOM_FIELDS, n_strings=2)
        self._wrench_reader = StampedReader(WrenchStamped, WRENCH_FIELDS)
        self.timing = None                # a CycleTimes, set by benchmarks
        self._array_msg = Float64MultiArray()

        # the kernels before the first state (a first run after an install compiles them)
        compile_kernels(self.log.info, self._threshold)

        # the model
        if p["robot_description"]:
            latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL,
                                 history=HistoryPolicy.KEEP_LAST)
            self.sub_description = self.create_subscription(String, "robot_description",
                                                            self._on_description, latched)
            self.log.info(f"waiting for {self.sub_description.topic_name}")
        else:
            try:
                urdf = p["urdf"] or default_urdf_path()
            except FileNotFoundError as e:
                raise ValueError(str(e)) from None
            if not self._make_controller(urdf, urdf if not urdf.lstrip().startswith("<")
                                         else "the urdf parameter (XML)"):
                raise ValueError(f"urdf: cannot build the controller model from {urdf[:200]!r}")

        # subscriptions
        rel = (ReliabilityPolicy.BEST_EFFORT if p["state_reliability"] == "best_effort"
               else ReliabilityPolicy.RELIABLE)
        state_qos = QoSProfile(depth=10, reliability=rel, durability=DurabilityPolicy.VOLATILE,
                               history=HistoryPolicy.KEEP_LAST)
        # the state topics are taken as CDR bytes: the common case is read straight from
        # them (starleth_interface.msg_cdr), anything else deserialised by rclpy
        self.state_input = p["state_input"]
        self._bundled = False     # reading the bundle alone (auto: after the first one)
        self.sub_bundle = (self.create_subscription(
            Float64MultiArray, p["state_bundle_topic"], self._on_bundle_cdr, state_qos,
            raw=True) if self.state_input != "topics" else None)
        self.sub_js = self._side_node = None
        self._side_inputs = []
        if self.state_input != "bundle":
            self.sub_js = self.create_subscription(JointState, p["joint_states_topic"],
                                                   self._on_joint_states_cdr, state_qos,
                                                   raw=True)
            self._setup_side_inputs(p, state_qos)
        self.sub_cmd_vel = self.create_subscription(Twist, p["cmd_vel_topic"], self._on_cmd_vel,
                                                    QoSProfile(depth=10))
        self.srv_trot = self.create_service(SetBool, "~/trot", self._srv_trot)
        self.log.info(f"mode {self._mode}; joint commands on "
                      f"{p['joint_commands_topic'] or '(off)'}"
                      + (f", effort arrays on {p['effort_array_topic']}"
                         if p["effort_array_topic"] else ""))

    #: s: while a joint state waits for the other messages of its stamp, the side inputs
    #: are looked at this often (steady clock)
    SIDE_POLL_PERIOD = 0.0005

    def _setup_side_inputs(self, p, state_qos):
        """The base state and the four foot wrenches ("side inputs") are subscribed on a
        hidden helper node (``_<name>_side_inputs``) that no executor spins: their messages
        wait in the subscriptions' queues and are taken when the joint state of a stamp
        arrives (_take_side_inputs), so the executor thread wakes once per state instead
        of six times (a simulator that sends /joint_states last, as sim_node does, gets its
        answer without any wait). Until a stamp is complete, a steady-clock timer takes
        them every SIDE_POLL_PERIOD (any order of arrival still works). Topic names are
        resolved by this node (its namespace and remappings)."""
        self._side_node = Node(f"_{self.get_name()}_side_inputs", context=self.context,
                               namespace=self.get_namespace(), use_global_arguments=False,
                               enable_rosout=False, start_parameter_services=False)
        side = self._side_node

        def sub(typ, topic):
            return side.create_subscription(typ, self.resolve_topic_name(topic),
                                            lambda _: None, state_qos, raw=True)
        self.sub_odom = sub(Odometry, p["base_state_topic"])
        self.sub_wrench = [sub(WrenchStamped, topic) for topic in p["foot_wrench_topics"]]
        self._side_inputs = [(self.sub_odom, self._on_base_state_cdr)] + [
            (s, (lambda data, k=k: self._on_wrench_cdr(k, data)))
            for k, s in enumerate(self.sub_wrench)]
        self._side_poll = self.create_timer(self.SIDE_POLL_PERIOD, self._poll_side_inputs,
                                            clock=Clock(clock_type=ClockType.STEADY_TIME),
                                            autostart=False)

    def _take_side_inputs(self, drain=True):
        """The messages waiting in the side inputs' queues (drain=False: at most one of
        each), into the slots of their stamps (which may complete a stamp and run the
        controller)."""
        for sub, on_data in self._side_inputs:
            while True:
                with sub.handle:
                    taken = sub.handle.take_message(sub.msg_type, True)
                if taken is None:
                    break
                on_data(taken[0])
                if not drain:
                    break

    def _poll_side_inputs(self):
        """The timer's callback: take the side inputs; stop polling once no joint state
        waits for them."""
        self._take_side_inputs()
        if not any(s.js is not None for s in self._pending.values()):
            self._side_poll.cancel()

    def destroy_node(self):
        if self._side_node is not None:
            self._side_node.destroy_node()
        return super().destroy_node()

    def _read_bundles_only(self):
        """auto: the first bundle arrived; unsubscribe from the public state topics (the
        simulator then stops sending them to this node) and forget their partial stamps."""
        self._bundled = True
        if self.sub_js is not None:
            self.destroy_subscription(self.sub_js)
            self.sub_js = None
            for sub, _ in self._side_inputs:
                self._side_node.destroy_subscription(sub)
            self._side_inputs = []
            self._side_poll.cancel()
            self._pending.clear()
        self.log.info(f"state from {self.sub_bundle.topic_name} (one message per step)"
                      + ("; unsubscribed from the public state topics"
                         if self.state_input == "auto" else ""))

    def _clock_seconds(self) -> float:
        """The node's clock [s]: /clock with use_sim_time, else the system clock."""
        return self.get_clock().now().nanoseconds * 1e-9

    # -- parameters ------------------------------------------------------------------------
    def _check_static(self, p):
        """ValueError listing every parameter that breaks its schema."""
        errors = []
        for spec in PARAMETERS:
            try:
                spec.check(p[spec.name])
            except ValueError as e:
                errors.append(str(e))
        topics = p["foot_wrench_topics"]
        if not errors and (len(topics) != 4 or not all(isinstance(t, str) and t for t in topics)):
            errors.append(f"parameter foot_wrench_topics: expected 4 topic names (LF, RF, LH, "
                          f"RH), got {topics!r}")
        if errors:
            raise ValueError("; ".join(errors))

    def _on_set_parameters(self, params):
        for prm in params:
            spec = PARAMETERS_BY_NAME.get(prm.name)
            if spec is None:
                continue
            try:
                spec.check(spec.coerce(prm.value))
            except ValueError as e:
                return SetParametersResult(successful=False, reason=str(e))
        for prm in params:
            if prm.name == "mode" and prm.value != self._mode:
                self._mode = prm.value
                self.log.info(f"mode -> {prm.value}")
            elif prm.name == "contact_force_threshold":
                self._threshold = float(prm.value)
            elif prm.name == "max_linear_speed":
                self._max_v = float(prm.value)
            elif prm.name == "max_yaw_rate":
                self._max_w = float(prm.value)
            elif prm.name == "cmd_vel_timeout":
                self._cmd_vel_timeout = float(prm.value)
            elif prm.name == "warn_throttle_period":
                self._warn.period = float(prm.value)
        return SetParametersResult(successful=True)

    def _srv_trot(self, request, response):
        mode = "trot" if request.data else "stand"
        result = self.set_parameters([Parameter("mode", value=mode)])[0]
        response.success = bool(result.successful)
        response.message = (f"mode {mode}" if result.successful else result.reason)
        if self._last_answer is not None:
            response.message += f" (last state answered: t={self._last_answer[0] * 1e-9:.4f} s)"
        return response

    # -- model -----------------------------------------------------------------------------
    def _make_controller(self, urdf, what):
        try:
            ctrl = StarlethController(urdf, ControllerParams(
                contact_force_threshold=self._threshold))
        except Exception as e:  # a bad URDF: keep running, answer nothing
            self.log.error(f"cannot build the controller model from {what}: {e}")
            return False
        self.controller = ctrl
        self.log.info(f"controller model from {what}: {ctrl.model.mass:.2f} kg")
        return True

    def _on_description(self, msg):
        if self.controller is None and msg.data:
            if self._make_controller(msg.data, self.sub_description.topic_name) and \
                    self._waiting_state is not None:
                stamp, s = self._waiting_state
                self._waiting_state = None
                self.counters["states"] -= 1
                self._complete(stamp, s)

    # -- inputs ----------------------------------------------------------------------------
    def _slot(self, stamp):
        s = self._pending.get(stamp)
        if s is None:
            if len(self._pending) >= self.MAX_PENDING:
                oldest = min(self._pending)
                self._drop_incomplete(oldest, self._pending.pop(oldest))
            s = self._pending[stamp] = _Slot()
        return s

    def _drop_incomplete(self, stamp, slot):
        self.counters["dropped_incomplete"] += 1
        missing = [name for name, m in (("joint state", slot.js), ("base state", slot.odom),
                                        *zip((f"{leg} wrench" for leg in LEGS), slot.wrench))
                   if m is None]
        self._warn("incomplete", f"dropped the incomplete state of t={stamp * 1e-9:.4f} s "
                   f"(missing: {', '.join(missing)})")

    def _deserialise(self, data, typ, what):
        try:
            return deserialize_message(data, typ)
        except Exception as e:   # malformed CDR: ignore it, never die
            self.counters["rejected"] += 1
            self._warn("bad_cdr", f"ignored an undecodable {what}: {e}")
            return None

    def _on_bundle_cdr(self, data):
        """A state bundle: the whole state of its stamp (starleth_interface.state_bundle),
        answered at once."""
        r = state_bundle.decode(data)
        if isinstance(r, str):
            self.counters["rejected"] += 1
            self._warn("bundle", f"ignored a message on {self.sub_bundle.topic_name}: {r}")
            return
        if not self._bundled:
            self._read_bundles_only()
        sec, nsec, v = r
        stamp = sec * 1_000_000_000 + nsec
        if self._answered_before(stamp):
            return
        s = _Slot()
        s.js = (sec, nsec, state_bundle.JOINT_NAMES, v[state_bundle.SLICES["q"]],
                v[state_bundle.SLICES["u"]])
        s.odom = v[state_bundle.BASE]
        s.wrench = v[state_bundle.SLICES["force"]].reshape(4, 3)
        s.n = 6
        self._complete(stamp, s)

    def _answered_before(self, stamp) -> bool:
        """`stamp` is the state answered last: a simulator re-sending a state it got no
        answer for (its first one, sent before the topics matched) gets the same answer
        again; a copy that crossed the answer in flight (within REPEAT_AFTER) is ignored."""
        last = self._last_answer
        if last is None or last[0] != stamp:
            return False
        if time.monotonic() - last[3] > self.REPEAT_AFTER:
            self.counters["repeated"] += 1
            self._publish(last[1], last[2])
        return True

    def _on_joint_states_cdr(self, data):
        if self._bundled:       # a public message still queued after the switch
            return
        # the rest of this state first (one message of each side input), then the joint
        # state, which completes it and gets the answer out; then anything else waiting
        self._take_side_inputs(drain=False)
        r = self._js_reader.decode(data)
        if r is None:
            msg = self._deserialise(data, JointState, "joint state")
            if msg is not None:
                self._on_joint_states(msg)
        else:
            sec, nsec, names, pos, vel = r
            self._joint_state(sec * 1_000_000_000 + nsec, (sec, nsec, names, pos, vel))
        self._take_side_inputs()

    def _on_base_state_cdr(self, data):
        r = self._odom_reader.decode(data)
        if r is None:
            msg = self._deserialise(data, Odometry, "base state")
            if msg is not None:
                self._on_base_state(msg)
            return
        sec, nsec, vals = r
        self._base_state(sec * 1_000_000_000 + nsec, vals)

    def _on_wrench_cdr(self, k, data):
        r = self._wrench_reader.decode(data)
        if r is None:
            msg = self._deserialise(data, WrenchStamped, "foot wrench")
            if msg is not None:
                self._on_wrench(k, msg)
            return
        sec, nsec, vals = r
        self._foot_wrench(k, sec * 1_000_000_000 + nsec, vals)

    def _on_joint_states(self, msg):
        st = msg.header.stamp
        self._joint_state(_stamp_ns(msg.header), (st.sec, st.nanosec, tuple(msg.name),
                                                  msg.position, msg.velocity))

    def _joint_state(self, stamp, js):
        if self._answered_before(stamp):
            return
        s = self._slot(stamp)
        new = s.js is None
        s.js = js
        self._received(stamp, s, new)
        if stamp in self._pending and self._side_poll.is_canceled():
            self._side_poll.reset()       # the rest of this stamp is still to come

    def _on_base_state(self, msg):
        o = msg.pose.pose
        pp, po = o.position, o.orientation
        tl, ta = msg.twist.twist.linear, msg.twist.twist.angular
        self._base_state(_stamp_ns(msg.header), (pp.x, pp.y, pp.z, po.x, po.y, po.z, po.w,
                                                 tl.x, tl.y, tl.z, ta.x, ta.y, ta.z))

    def _base_state(self, stamp, vals):
        s = self._slot(stamp)
        new = s.odom is None
        s.odom = vals
        self._received(stamp, s, new)

    def _on_wrench(self, k, msg):
        f = msg.wrench.force
        self._foot_wrench(k, _stamp_ns(msg.header), (f.x, f.y, f.z))

    def _foot_wrench(self, k, stamp, force):
        s = self._slot(stamp)
        new = s.wrench[k] is None
        s.wrench[k] = force
        self._received(stamp, s, new)

    def _received(self, stamp, s, new):
        """One of the 6 messages of the state `stamp` arrived (new: not a repeat of one
        already in the slot); the controller runs once all 6 are in."""
        if new:
            s.n += 1
        if s.n == 6:
            self._complete(stamp, s)

    def _on_cmd_vel(self, msg):
        vx, vy, wz = msg.linear.x, msg.linear.y, msg.angular.z
        if not _finite(vx, vy, wz):
            self.counters["rejected"] += 1
            self._warn("cmd_vel", "ignored a /cmd_vel with non-finite values")
            return
        n = math.hypot(vx, vy)
        if n > self._max_v:
            vx, vy = vx * self._max_v / n, vy * self._max_v / n
        wz = min(max(wz, -self._max_w), self._max_w)
        self._vel = (vx, vy, wz)
        self._vel_time = self._clock_seconds()

    # -- one control period ----------------------------------------------------------------
    def _permutation(self, names):
        key = tuple(names)
        perm = self._perm_cache.get(key)
        if perm is None:
            if key == JOINT_NAMES:
                perm = slice(None)
            else:
                index = {n: i for i, n in enumerate(key)}
                if len(index) != len(key):
                    return None, "duplicate joint names"
                missing = [n for n in JOINT_NAMES if n not in index]
                if missing:
                    return None, f"missing joints {', '.join(missing)}"
                perm = np.array([index[n] for n in JOINT_NAMES])
            if len(self._perm_cache) < 8:
                self._perm_cache[key] = perm
        return perm, None

    def _state(self, stamp, s: _Slot):
        """RobotState from the messages of one stamp, or (None, key, reason): the common
        case (12 finite joints, finite values below 1e100, a quaternion of squared norm in
        (0.5, 2)) read by one kernel into fresh arrays, with the arithmetic of the checks
        below (_state_checked), which run for anything else and give the reason."""
        _, _, names, position, velocity = s.js
        n = len(names)
        if n == 12 and len(position) == 12 and len(velocity) == 12 and s.odom is not None \
                and len(s.odom) == 13:
            perm = self._kernel_perm.get(names)
            if perm is None:
                perm, err = self._permutation(names)
                if err:
                    return self._state_checked(stamp, s)
                perm = (np.arange(12, dtype=np.int64) if isinstance(perm, slice)
                        else np.asarray(perm, dtype=np.int64))
                if len(self._kernel_perm) < 8:
                    self._kernel_perm[names] = perm
            try:
                forces = np.array(s.wrench, dtype=float)
                odom = np.array(s.odom, dtype=float)
            except (TypeError, ValueError):
                return self._state_checked(stamp, s)
            if forces.shape == (4, 3):
                state = state_from_values(stamp, position, velocity, perm, odom, forces,
                                          self._threshold, self._twist_in_child,
                                          self._R_node)
                if state is not None:
                    return state, None, None
        return self._state_checked(stamp, s)

    def _state_checked(self, stamp, s: _Slot):
        """RobotState from the messages of one stamp after checking them one by one, or
        (None, key, reason)."""
        _, _, names, position, velocity = s.js
        n = len(names)
        if len(position) != n or len(velocity) != n:
            return None, "joint_states", (f"/joint_states: {n} names, {len(position)} "
                                          f"positions, {len(velocity)} velocities")
        perm, err = self._permutation(names)
        if err:
            return None, "joint_states", f"/joint_states: {err}"
        q = np.asarray(position, dtype=float)[perm]
        dq = np.asarray(velocity, dtype=float)[perm]
        # a finite sum means every value is finite (NaN and inf propagate); only a sum that
        # is not (non-finite values, or an overflow) is looked at value by value
        add = np.add.reduce
        if not math.isfinite(float(add(q) + add(dq))) and \
                not (np.isfinite(q).all() and np.isfinite(dq).all()):
            return None, "joint_states_nan", "/joint_states: non-finite position or velocity"
        vals = s.odom
        if not _finite(*vals):
            return None, "base_state_nan", "base state: non-finite values"
        quat = np.array(vals[3:7])
        nq = squared_norm4(quat)
        if not 0.5 < nq < 2.0:
            return None, "base_state_quat", f"base state: orientation norm {math.sqrt(nq):.3g}"
        quat /= math.sqrt(nq)
        v = np.array(vals[7:10])
        if self._twist_in_child:   # base frame -> world frame
            x, y, z, w = quat.tolist()     # Python floats: the same values, faster products
            R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                          [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                          [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
            v = R @ v
        forces = np.array(s.wrench, dtype=float)
        if not math.isfinite(float(add(forces, axis=None))) and not np.isfinite(forces).all():
            return None, "wrench_nan", "foot wrench: non-finite force"
        contact = np.sqrt((forces * forces).sum(axis=1)) > self._threshold
        state = RobotState(stamp * 1e-9, q, dq, np.array(vals[0:3]), quat, v,
                           np.array(vals[10:13]), contact, forces)
        return state, None, None

    def _complete(self, stamp, s):
        # drop this stamp and every older one still waiting
        for st in [st for st in self._pending if st <= stamp]:
            slot = self._pending.pop(st)
            if st != stamp:
                self._drop_incomplete(st, slot)
        self.counters["states"] += 1
        t_complete = time.perf_counter()
        if self.controller is None:
            # kept: answered as soon as the model is there (a lockstep simulator waits)
            self._waiting_state = (stamp, s)
            self._warn("no_model", "state received but no controller model yet (waiting for "
                       "/robot_description)")
            return
        state, key, reason = self._state(stamp, s)
        if state is None:
            self.counters["rejected"] += 1
            self._warn(key, f"ignored the state of t={stamp * 1e-9:.4f} s: {reason}")
            return
        vx, vy, wz = self._vel
        if self._cmd_vel_timeout > 0 and self._vel_time is not None and \
                self._clock_seconds() - self._vel_time > self._cmd_vel_timeout:
            vx = vy = wz = 0.0
        c = self.command
        c.mode, c.forward, c.lateral, c.yaw_rate = self._mode, vx, vy, wz
        try:
            tau = self.controller.update(state, c)
        except Exception as e:
            self.counters["controller_errors"] += 1
            self._warn("controller", f"controller update failed at t={stamp * 1e-9:.4f} s: "
                       f"{type(e).__name__}: {e}")
            return
        if not math.isfinite(float(_sum(tau))) and not np.isfinite(tau).all():
            self.counters["controller_errors"] += 1
            self._warn("controller_nan", "controller returned non-finite torques; not sent")
            return
        mode = self.controller.mode
        if mode != self._ctrl_mode:
            self.log.info(f"t={stamp * 1e-9:.4f} s: controller mode {mode}")
            self._ctrl_mode = mode
        if "error" in self.controller.info:
            self._warn("controller_info", f"controller: {self.controller.info['error']}")
        t_computed = time.perf_counter()
        effort = array.array("d", np.ascontiguousarray(tau, dtype=float).tobytes())
        sec_nsec = s.js[:2]
        self._last_answer = (stamp, sec_nsec, effort, time.monotonic())
        self._publish(sec_nsec, effort)
        if self.timing is not None:
            self.timing.add(stamp, s.t_first, t_complete, t_computed, time.perf_counter())

    def _publish(self, sec_nsec, effort):
        self.counters["commands"] += 1
        if self.pub_cmd is not None:
            if self._cmd_cdr is not None:
                self.pub_cmd.publish(self._cmd_cdr.build(*sec_nsec, effort))
            else:
                m = self._cmd_msg
                m.header.stamp.sec, m.header.stamp.nanosec = sec_nsec
                m.effort = effort
                self.pub_cmd.publish(m)
        if self.pub_array is not None:
            self._array_msg.data = effort
            self.pub_array.publish(self._array_msg)

    def summary(self) -> dict:
        d = dict(self.counters)
        d["warnings_by_kind"] = dict(self._warn.counts)
        return d


def main(args=None):
    """Console script ``controller_node``. Stops on SIGINT / SIGTERM."""
    if not init_ros("controller_node", sys.argv if args is None else args):
        return 2
    signals = StopSignals()
    node = executor = None
    try:
        try:
            node = ControllerNode()
        except ValueError as e:
            print(f"controller_node: configuration error: {e}", file=sys.stderr)
            return 2
        executor, kind = make_executor(node.executor_kind, node.context)
        executor.add_node(node)
        node.log.info(f"executor: {kind}; ready")
        while not signals.requested and node.context.ok():
            try:
                executor.spin_once(timeout_sec=0.1)
            except Exception as e:  # context shut down, ExternalShutdownException
                if not node.context.ok():
                    break
                node.log.error(f"executor: {type(e).__name__}: {e}")
        node.log.info(f"stopped; {node.summary()}")
        return 0
    finally:
        shutdown_ros(node, executor)


if __name__ == "__main__":
    sys.exit(main())
