"""``controller_node``: the StarlETH stand / trot controller (``StarlethController``) behind
ROS 2 topics. A thin adapter: no control law in here.

    ros2 run starleth_sim controller_node
    python -m starleth_controller.controller_node --ros-args -p mode:=trot -p robot:=go1

The robot (``robot``: a library name, a robot spec or a URDF path; default starleth) gives
the model, the joint names and order, the feet and the gains scaled to its size
(doc/controllers.md). A robot that is not four 3-joint roll-pitch-pitch legs (or a bad
description) ends the node at start with one line and exit status 2.

Subscribed (topic names are the defaults, relative: ``--ros-args -r __ns:=/robot1`` puts
them under /robot1, beside that robot's sim_node; remap them for another robot):

    starleth/state_bundle                std_msgs/Float64MultiArray   sim_node's state of a step
                                                                      in one message
    joint_states                         sensor_msgs/JointState       by name: position, velocity
    starleth/base_state                  nav_msgs/Odometry            ground-truth base state
    starleth/<foot>/wrench               geometry_msgs/WrenchStamped  contact: |force| > thr. μ;
                                                                      <foot>: each foot contact's
                                                                      name (topics.topic_token)
    cmd_vel                              geometry_msgs/Twist          linear.x, linear.y, angular.z
    robot_description                    std_msgs/String              with robot_description:=true
    starleth/imu, starleth/foot_contacts sensor_msgs/Imu, JointState  state_source:=estimator,
                                                                      instead of the base state,
                                                                      wrenches and bundle

Published:

    joint_commands                       sensor_msgs/JointState       names + effort; header.stamp
                                                                      = the state's stamp
    (effort_array_topic, off by default) std_msgs/Float64MultiArray   12 torques, joint order
    estimator/odometry                   nav_msgs/Odometry            state_source:=estimator:
                                                                      the estimate of each step

Service ``~/trot`` (std_srvs/SetBool): true = trot, false = stand (sets the ``mode`` parameter).

Time: with ``use_sim_time:=true`` the node's clock follows /clock (the launch file remaps it
to the robot's ``<namespace>/clock``, beside its sim_node: ``-r /clock:=clock``), and
``cmd_vel_timeout`` counts sim time; the controller's own time is always the state's stamp.
The 0.1 s after which a repeated state is answered again is wall time (it is about messages
in flight, and a lockstep simulator's clock stands still while it waits for the answer).

The base state is taken from ``/starleth/base_state`` as *ground truth* (the simulator's
Odometry: pose in the world frame, twist in the child (base) frame as REP 105 says; set
``twist_frame:=parent`` for a source that gives the linear velocity in the world frame).
With ``state_source:=estimator`` the node reads no ground truth: the joint state, the IMU and
the foot contact flags of a stamp (three messages) go through the state estimator
(estimator.py, Bloesch et al. RSS 2012; doc/estimator.md), whose estimate is the
controller's base state and is published on ``estimator/odometry``.

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
``ControllerNode.timing`` (a ``starleth_interface.cycle_times.CycleTimes``, benchmarks only)
times each cycle.

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
from geometry_msgs.msg import Twist, WrenchStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import SetBool

from starleth_interface import state_bundle
from starleth_interface.config_checks import ConfigError
from starleth_interface.msg_cdr import (
    ODOM_FIELDS,
    WRENCH_FIELDS,
    JointStateCdr,
    JointStateReader,
    StampedReader,
)
from starleth_interface.ros_helpers import (
    StopSignals,
    ThrottledLog,
    UnknownParameterError,
    capture_python_warnings,
    check_parameter_names,
    declare_parameters,
    init_ros,
    make_executor,
    route_python_logging,
    service_qos,
    set_cpu_scheduling,
    shutdown_ros,
)

from .controller import StarlethController
from .estimator_topics import EstimatorTopics
from .inputs import Command
from .model import NotAQuadruped, RobotModel
from .node_parameters import (
    PARAMETERS,
    PARAMETERS_BY_NAME,
    check_parameters,
    default_wrench_topics,
    estimator_params,
)
from .side_inputs import SideInputs
from .state_intake import StateAssembler, StateSlot, all_finite, stamp_ns

_sum = np.add.reduce     # = ndarray.sum, without its wrapper (a finite sum: all finite)


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
        try:
            check_parameter_names(self, PARAMETERS)   # a mistyped name: an error, not ignored
        except UnknownParameterError:
            super().destroy_node()            # (nothing of this class is set up yet)
            raise
        check_parameters(p)
        self._unroute_logging = route_python_logging(self.log, ("starleth_controller",
                                                                "starleth_interface"))
        self._warn = ThrottledLog(self.log.warning, float(p["warn_throttle_period"]))
        self._mode = p["mode"]
        self._max_v = float(p["max_linear_speed"])
        self._max_w = float(p["max_yaw_rate"])
        self._cmd_vel_timeout = float(p["cmd_vel_timeout"])
        self.executor_kind = p["executor"]
        err = set_cpu_scheduling(p["cpu_scheduling"])
        if err:
            self.log.warning(f"cpu_scheduling {p['cpu_scheduling']}: {err}")
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self._init_state(p)
        self._init_publishers(p)
        wrench_topics = self._init_robot(p)
        self._init_subscriptions(p, wrench_topics)
        self.log.info(f"mode {self._mode}; joint commands on "
                      f"{p['joint_commands_topic'] or '(off)'}"
                      + (f", effort arrays on {p['effort_array_topic']}"
                         if p["effort_array_topic"] else ""))

    def _init_state(self, p):
        """The node's state before any message: the command, counters, the state assembly."""
        self._vel = (0.0, 0.0, 0.0)
        self._vel_time = None
        self.command = Command(self._mode)
        self.counters = {"states": 0, "commands": 0, "rejected": 0, "repeated": 0,
                         "dropped_incomplete": 0, "controller_errors": 0}
        self._pending: dict[int, StateSlot] = {}
        self._last_answer = None          # (stamp_ns, (sec, nanosec), effort, monotonic time)
        self._assembler = StateAssembler(float(p["contact_force_threshold"]),
                                         p["twist_frame"] == "child")
        self._ctrl_mode = None
        self.controller = None
        self._waiting_state = None        # the last state that came before the model
        self._threshold = float(p["contact_force_threshold"])   # StarlETH's; times μ
        self._joint_names = self._foot_names = ()
        self._js_reader = JointStateReader()
        self._odom_reader = StampedReader(Odometry, ODOM_FIELDS, n_strings=2)
        self._wrench_reader = StampedReader(WrenchStamped, WRENCH_FIELDS)
        # state_source estimator: its topics and the filter (made with the model)
        self._estimating = p["state_source"] == "estimator"
        self._needed = 3 if self._estimating else 6     # messages of a complete stamp
        self._estimator = None
        self.timing = None                # a CycleTimes, set by benchmarks

    def _init_publishers(self, p):
        """The joint command and effort array publishers (an empty topic: none)."""
        cmd_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE,
                             history=HistoryPolicy.KEEP_LAST)
        self.pub_cmd = (self.create_publisher(JointState, p["joint_commands_topic"], cmd_qos)
                        if p["joint_commands_topic"] else None)
        self.pub_array = (self.create_publisher(Float64MultiArray, p["effort_array_topic"],
                                                cmd_qos) if p["effort_array_topic"] else None)
        self._cmd_msg = JointState()
        self._cmd_cdr = None
        self._array_msg = Float64MultiArray()
        if self._estimating:
            self._estimator = EstimatorTopics(self, estimator_params(p),
                                              p["estimator_odometry_topic"], cmd_qos,
                                              self._deserialise)

    def _init_robot(self, p):
        """The robot: from its parameters now, or from robot_description when it comes (a
        bad one: one line); returns the foot wrench topics to read."""
        model = None if p["robot_description"] else self._robot_model(p)
        # the model (its joint names, feet and size: the command template, the wrench topics)
        wrench_topics = p["foot_wrench_topics"]
        if p["robot_description"]:
            if not wrench_topics:
                wrench_topics = default_wrench_topics(
                    self._robot_model(dict(p, urdf="")).foot_names)
            latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL,
                                 history=HistoryPolicy.KEEP_LAST)
            self.sub_description = self.create_subscription(String, "robot_description",
                                                            self._on_description, latched)
            self.log.info(f"waiting for {self.sub_description.topic_name}")
        else:
            what = ("the urdf parameter (XML)" if p["urdf"].lstrip().startswith("<")
                    else p["urdf"] or f"robot {p['robot']}")
            self._use_controller(StarlethController(model=model), what)
            wrench_topics = wrench_topics or default_wrench_topics(self._foot_names)
        return wrench_topics

    def _init_subscriptions(self, p, wrench_topics):
        """The state topics (taken as CDR bytes: the common case read straight from them,
        starleth_interface.msg_cdr, anything else deserialised by rclpy), cmd_vel, ~/trot."""
        rel = (ReliabilityPolicy.BEST_EFFORT if p["state_reliability"] == "best_effort"
               else ReliabilityPolicy.RELIABLE)
        state_qos = QoSProfile(depth=10, reliability=rel, durability=DurabilityPolicy.VOLATILE,
                               history=HistoryPolicy.KEEP_LAST)
        # the state bundle carries ground truth: the estimator reads the public topics
        self.state_input = "topics" if self._estimating else p["state_input"]
        self._bundled = False     # reading the bundle alone (auto: after the first one)
        self.sub_bundle = (self.create_subscription(
            Float64MultiArray, p["state_bundle_topic"], self._on_bundle_cdr, state_qos,
            raw=True) if self.state_input != "topics" else None)
        self.sub_js = self._side = None
        if self.state_input != "bundle":
            self.sub_js = self.create_subscription(JointState, p["joint_states_topic"],
                                                   self._on_joint_states_cdr, state_qos,
                                                   raw=True)
            self._side = SideInputs(self, state_qos, self._side_inputs(p, wrench_topics),
                                    self._joint_state_waiting)
        self.sub_cmd_vel = self.create_subscription(Twist, p["cmd_vel_topic"], self._on_cmd_vel,
                                                    QoSProfile(depth=10))
        self.srv_trot = self.create_service(SetBool, "~/trot", self._srv_trot,
                                            qos_profile=service_qos())

    def _side_inputs(self, p, wrench_topics):
        """(type, topic, callback) of the inputs read beside the joint state: the IMU and the
        foot contacts (state_source estimator), else the base state and the foot wrenches."""
        if self._estimating:
            e = self._estimator
            return [(Imu, p["imu_topic"], lambda d: self._side_value("imu", e.imu(d))),
                    (JointState, p["foot_contacts_topic"],
                     lambda d: self._side_value("contacts", e.contacts(d)))]
        return [(Odometry, p["base_state_topic"], self._on_base_state_cdr)] + [
            (WrenchStamped, topic, (lambda data, k=k: self._on_wrench_cdr(k, data)))
            for k, topic in enumerate(wrench_topics)]

    def destroy_node(self):
        self._unroute_logging()
        if self._side is not None:
            self._side.destroy()
        return super().destroy_node()

    def _read_bundles_only(self):
        """auto: the first bundle arrived; unsubscribe from the public state topics (the
        simulator then stops sending them to this node) and forget their partial stamps."""
        self._bundled = True
        if self.sub_js is not None:
            self.destroy_subscription(self.sub_js)
            self.sub_js = None
            self._side.unsubscribe()
            self._pending.clear()
        self.log.info(f"state from {self.sub_bundle.topic_name} (one message per step)"
                      + ("; unsubscribed from the public state topics"
                         if self.state_input == "auto" else ""))

    def _joint_state_waiting(self) -> bool:
        """A joint state waits for the other messages of its stamp."""
        return any(s.js is not None for s in self._pending.values())

    def _clock_seconds(self) -> float:
        """The node's clock [s]: /clock with use_sim_time, else the system clock."""
        return self.get_clock().now().nanoseconds * 1e-9

    # -- parameters ------------------------------------------------------------------------
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
                if self.controller is not None:
                    self._assembler.threshold = self._threshold * self.controller.model.scale.mass
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
    @staticmethod
    def _robot_model(p):
        """The RobotModel of the `urdf` parameter, else of the `robot` parameter; ValueError
        in one line for a bad description or one that is not four 3-joint legs."""
        try:
            return RobotModel(urdf=p["urdf"]) if p["urdf"] else RobotModel(robot=p["robot"])
        except (ConfigError, NotAQuadruped, OSError) as e:
            raise ValueError(str(e)) from None

    def _use_controller(self, ctrl, what):
        """Drive `ctrl`: its robot's joint names (commands, joint states by name), feet and
        contact threshold (times μ)."""
        m = ctrl.model
        self.controller = ctrl
        self._joint_names, self._foot_names = m.public_joint_names, m.foot_names
        self._assembler = StateAssembler(self._threshold * m.scale.mass,
                                         self._assembler.twist_in_child, self._joint_names)
        self._cmd_msg.name = list(self._joint_names)
        # commands go out as CDR bytes patched into a template (None: as message objects)
        self._cmd_cdr = JointStateCdr.create(self._joint_names, ("effort",))
        if self._estimating:
            self._estimator.use_model(m)
        self.log.info(f"controller model from {what}: {m.mass:.2f} kg, legs "
                      f"{m.leg_length:.3f} m (scale λ {m.scale.length:g}, μ {m.scale.mass:g})")

    def _make_controller(self, urdf, what):
        """The controller of a robot_description's URDF; False (logged) when it cannot be
        built: the node keeps running and answers nothing."""
        try:
            ctrl = StarlethController(urdf=urdf)
        except Exception as e:  # a bad URDF: keep running, answer nothing
            self.log.error(f"cannot build the controller model from {what}: {e}")
            return False
        self._use_controller(ctrl, what)
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
            s = self._pending[stamp] = StateSlot()
        return s

    def _drop_incomplete(self, stamp, slot):
        self.counters["dropped_incomplete"] += 1
        missing = ", ".join(slot.missing(self._foot_names or ("foot",) * 4, self._estimating))
        self._warn("incomplete", f"dropped the incomplete state of t={stamp * 1e-9:.4f} s "
                   f"(missing: {missing})", missing)

    def _deserialise(self, data, typ, what):
        try:
            return deserialize_message(data, typ)
        except Exception as e:   # malformed CDR: ignore it, never die
            self._bad_message(what, e)
            return None

    def _bad_message(self, what, e):
        self.counters["rejected"] += 1
        self._warn("bad_cdr", f"ignored an undecodable {what}: {e}", what)

    def _on_bundle_cdr(self, data):
        """A state bundle: the whole state of its stamp (starleth_interface.state_bundle),
        answered at once."""
        r = state_bundle.decode(data)
        if isinstance(r, str):
            self.counters["rejected"] += 1
            self._warn("bundle", f"ignored a message on {self.sub_bundle.topic_name}: {r}",
                       r.split(" (")[0])       # the problem without its values
            return
        if not self._bundled:
            self._read_bundles_only()
        sec, nsec, v = r
        stamp = sec * 1_000_000_000 + nsec
        if self._answered_before(stamp):
            return
        s = StateSlot()
        s.js = (sec, nsec, self._joint_names, v[state_bundle.SLICES["q"]],
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
        self._side.take(drain=False)
        r = self._js_reader.decode(data)
        if r is None:
            msg = self._deserialise(data, JointState, "joint state")
            if msg is not None:
                self._on_joint_states(msg)
        else:
            sec, nsec, names, pos, vel = r
            self._joint_state(sec * 1_000_000_000 + nsec, (sec, nsec, names, pos, vel))
        self._side.take()

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
        self._joint_state(stamp_ns(msg.header), (st.sec, st.nanosec, tuple(msg.name),
                                                  msg.position, msg.velocity))

    def _joint_state(self, stamp, js):
        if self._answered_before(stamp):
            return
        s = self._slot(stamp)
        new = s.js is None
        s.js = js
        self._received(stamp, s, new)
        poll = self._side.poll
        if stamp in self._pending and poll.is_canceled():
            poll.reset()                  # the rest of this stamp is still to come

    def _on_base_state(self, msg):
        o = msg.pose.pose
        pp, po = o.position, o.orientation
        tl, ta = msg.twist.twist.linear, msg.twist.twist.angular
        self._base_state(stamp_ns(msg.header), (pp.x, pp.y, pp.z, po.x, po.y, po.z, po.w,
                                                 tl.x, tl.y, tl.z, ta.x, ta.y, ta.z))

    def _base_state(self, stamp, vals):
        s = self._slot(stamp)
        new = s.odom is None
        s.odom = vals
        self._received(stamp, s, new)

    def _side_value(self, field, r):
        """A value of the state estimator's inputs: `field` ('imu', 'contacts') of its
        stamp's slot; r = (stamp, value), None for a message that could not be read."""
        if r is not None:
            s = self._slot(r[0])
            new = getattr(s, field) is None
            setattr(s, field, r[1])
            self._received(r[0], s, new)

    def _on_wrench(self, k, msg):
        f = msg.wrench.force
        self._foot_wrench(k, stamp_ns(msg.header), (f.x, f.y, f.z))

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
        if s.n == self._needed:
            self._complete(stamp, s)

    def _on_cmd_vel(self, msg):
        vx, vy, wz = msg.linear.x, msg.linear.y, msg.angular.z
        if not all_finite(vx, vy, wz):
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
        if self._estimator is not None:
            state, key, reason = self._estimator.estimate.robot_state(stamp, s)
            if state is not None:
                self._estimator.publish(s.js[:2])
        else:
            state, key, reason = self._assembler.robot_state(stamp, s)
        if state is None:
            self.counters["rejected"] += 1
            self._warn(key, f"ignored the state of t={stamp * 1e-9:.4f} s: {reason}",
                       reason if key == "joint_states" else "")   # the others hold values
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
                       f"{type(e).__name__}: {e}", type(e).__name__)
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
        except UnknownParameterError as e:
            print(f"controller_node: {e}", file=sys.stderr)
            return 2
        except ValueError as e:
            print(f"controller_node: configuration error: {e}", file=sys.stderr)
            return 2
        capture_python_warnings(node.log)   # numpy's warnings: the node's log
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
