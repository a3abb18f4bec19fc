"""The state sim_node publishes after every step, one publish path per topic: the state
bundle, the foot wrenches, the base state, /joint_states, /clock, the IMU, the foot contacts
(with noisy sensors also the ground-truth joint states, IMU and foot contacts) and
/starleth/solver, in the order a controller waits for them, then (off the lockstep critical
path) the preparation of the next step, TF and markers, and the hand-over to the recorder. Each
message is written as CDR bytes patched into a template (:mod:`starleth_interface.msg_cdr`),
or filled in a message object where no template could be made."""
from __future__ import annotations

import array
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import WrenchStamped
from nav_msgs.msg import Odometry
from rclpy.serialization import serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension, String

from starleth_interface.msg_cdr import (
    IMU_FIELDS,
    ODOM_FIELDS,
    WRENCH_FIELDS,
    FixedCdr,
    JointStateCdr,
)
from starleth_interface.state_bundle import BundleLayout, StateBundleCdr
from starleth_interface.topics import (
    TOPIC_APPLIED_TORQUE,
    TOPIC_BASE_STATE,
    TOPIC_CLOCK,
    TOPIC_FOOT_CONTACTS,
    TOPIC_GROUND_TRUTH_FOOT_CONTACTS,
    TOPIC_GROUND_TRUTH_IMU,
    TOPIC_GROUND_TRUTH_JOINT_STATES,
    TOPIC_IMU,
    TOPIC_JOINT_STATES,
    TOPIC_ROBOT_DESCRIPTION,
    TOPIC_SOLVER,
    TOPIC_STATE_BUNDLE,
    foot_wrench_topic,
)

from .qos import CLOCK_QOS, LATCHED_QOS, STATE_QOS
from .ros2_control_description import parse_command_interfaces, simulator_section, with_ros2_control
from .state_io import base_values, state_bundle_bytes
from .visualisation import Visualisation


def float_array(a) -> array.array:
    """`a` as an array('d') (what rclpy's float64[] fields take without a copy per item)."""
    return array.array("d", np.ascontiguousarray(a, dtype=float).tobytes())


class StatePublisher:
    """The state topics of `sim` through `output` (a :class:`~.topic_output.TopicOutput`:
    their publishers are made here), at the stamps of `service`; /starleth/solver from
    `diagnostics` (a :class:`~.solver_diagnostics.SolverDiagnostics`), the sensor topics
    (joint_states, the IMU, the foot contacts) from the service's sensors
    (:class:`~starleth_sim.physics.sensors.Sensors`: measured, and with noisy sensors the
    exact values on the ground_truth/ topics), TF and markers from a
    :class:`~.visualisation.Visualisation` made here. ``timing`` (a
    :class:`~starleth_interface.cycle_times.CycleTimes`, benchmarks only) times each
    part."""

    #: the sensor topics: (key, ground truth key) of joint_states, the IMU, foot contacts
    SENSOR_KEYS = (("joint_states", "gt_joint_states"), ("imu", "gt_imu"),
                   ("foot_contacts", "gt_foot_contacts"))

    def __init__(self, node, sim, settings, service, output, diagnostics, log):
        self.sim, self.settings, self.service = sim, settings, service
        self.output, self.diagnostics = output, diagnostics
        self.sensors = service.sensors
        #: with noisy sensors the exact values go out on the ground_truth/ topics too
        self.ground_truth = not self.sensors.ideal
        self.recording = output.recording
        self.timing = None           # a CycleTimes, set by benchmarks
        #: the robot's feet (contact names, the description's order): a wrench topic each
        self.feet = feet = tuple(sim.description.foot_names)
        #: the topics a controller waits for before it answers a state
        self.state_topics = ("joint_states", "base_state", *feet, "state_bundle")
        self._feet_first = tuple(sim.contact_names[:len(feet)]) == feet
        self._make_templates()
        self._make_publishers()
        self.visualisation = Visualisation(node, sim, settings, service, output, log)

    def _make_templates(self):
        s, sim = self.settings, self.sim
        self.clock_msg = Clock()
        self.js_msg = JointState()
        self.js_msg.name = list(sim.joint_names)
        self._js_cdr = JointStateCdr.create(list(sim.joint_names))
        self.contacts_msg = JointState()
        self.contacts_msg.name = list(self.feet)
        self._contacts_cdr = JointStateCdr.create(list(self.feet), ("position", "effort"))
        self.wrench_msgs = {}
        for foot in self.feet:
            m = WrenchStamped()
            m.header.frame_id = s.world_frame
            self.wrench_msgs[foot] = m
        base = s.robot_frame(s.base_frame)        # the base's frame on /tf (prefixed)
        self.odom_msg = Odometry()
        self.odom_msg.header.frame_id = s.world_frame
        self.odom_msg.child_frame_id = base
        self.imu_msg = Imu()
        self.imu_msg.header.frame_id = base
        # the state topics of every step go out as CDR bytes patched into templates
        # (starleth_interface.msg_cdr; None: as message objects)
        w = WrenchStamped()
        w.header.frame_id = s.world_frame
        self._wrench_cdr = FixedCdr.create(w, WRENCH_FIELDS)
        o = Odometry()
        o.header.frame_id, o.child_frame_id = s.world_frame, base
        self._odom_cdr = FixedCdr.create(o, ODOM_FIELDS)
        i = Imu()
        i.header.frame_id = base
        self._imu_cdr = FixedCdr.create(i, IMU_FIELDS)
        self._clock_cdr = FixedCdr.create(Clock(), (), stamp="clock")
        # the state bundle (starleth_interface.state_bundle) of the robot's joints and feet
        # (the feet the first contact points, as every description has them)
        self.bundle_cdr = (StateBundleCdr.create(BundleLayout(sim.n_joints, len(self.feet)))
                           if self._feet_first else None)

    def _make_publishers(self):
        add = self.output.add
        if self.settings.publish_clock:
            add("clock", Clock, TOPIC_CLOCK, CLOCK_QOS)
        add("joint_states", JointState, TOPIC_JOINT_STATES, STATE_QOS)
        for foot in self.feet:
            add(foot, WrenchStamped, foot_wrench_topic(foot), STATE_QOS)
        add("base_state", Odometry, TOPIC_BASE_STATE, STATE_QOS)
        add("imu", Imu, TOPIC_IMU, STATE_QOS)
        add("foot_contacts", JointState, TOPIC_FOOT_CONTACTS, STATE_QOS)
        if self.ground_truth:
            add("gt_joint_states", JointState, TOPIC_GROUND_TRUTH_JOINT_STATES, STATE_QOS)
            add("gt_imu", Imu, TOPIC_GROUND_TRUTH_IMU, STATE_QOS)
            add("gt_foot_contacts", JointState, TOPIC_GROUND_TRUTH_FOOT_CONTACTS, STATE_QOS)
        add("solver", DiagnosticArray, TOPIC_SOLVER, STATE_QOS)
        add("robot_description", String, TOPIC_ROBOT_DESCRIPTION, LATCHED_QOS)
        if self.bundle_cdr is not None:
            add("state_bundle", Float64MultiArray, TOPIC_STATE_BUNDLE, STATE_QOS)
        add("applied_torque", Float64MultiArray, TOPIC_APPLIED_TORQUE, STATE_QOS)
        # its CDR bytes: a fixed prefix (the layout, the data length) and the float64 data
        n_steps, n = self.sim.config.steps_per_control, self.sim.n_joints
        m = Float64MultiArray(data=[0.0] * (n_steps * 3 * n))
        m.layout.dim = [
            MultiArrayDimension(label="physics_steps", size=n_steps, stride=n_steps * 3 * n),
            MultiArrayDimension(label="applied_explicit_kd", size=3, stride=3 * n),
            MultiArrayDimension(label="joints", size=n, stride=n)]
        raw = serialize_message(m)
        self._torque_prefix = raw[:len(raw) - 8 * n_steps * 3 * n]

    # -- the state of a step ---------------------------------------------------------------
    def publish_state(self, record=True):
        """Publish the state of the current step (stamp t_k) on every state topic;
        record=False: a re-send of a state already published (not recorded again)."""
        svc, out = self.service, self.output
        sec, nsec = divmod(svc.stamp_ns, 1_000_000_000)
        wanted = out.wanted
        timing = self.timing
        first = not (svc.counters["steps"] or svc.counters["resets"])
        base = forces = None    # read from the simulator once, for every topic
        m = self.sensors.measured
        joints = (m.joint_position, m.joint_velocity, m.joint_effort)
        bundle = self._bundle_wanted(first)
        if bundle:
            # what controller_node waits for, in one message; the public topics follow
            # while it computes
            base = base_values(self.sim, self.sensors.base)
            forces = self.sim.contact_forces()
            self.publish_bundle(sec, nsec, base, joints, forces)
            if timing is not None:
                timing.row[2] = time.perf_counter()
        # the public topics: what a controller waits for first, the foot wrenches and the
        # base state, then /joint_states, the message a controller answers on
        # (controller_node takes the others when it arrives: one wake-up of its executor
        # per state), then the others
        feet = [f for f in self.feet if wanted(f, record)]
        if feet:
            self._publish_foot_wrenches(sec, nsec, feet, record, forces)
        if wanted("base_state", record):
            self._publish_odometry(sec, nsec, base or base_values(self.sim, self.sensors.base),
                                   record)
        if self._joint_states_wanted(first, record):
            self._publish_joint_states(sec, nsec, record, joints)
        if timing is not None and not bundle:
            timing.row[2] = time.perf_counter()
        if "clock" in out.pubs and wanted("clock", record):
            self._publish_clock(sec, nsec, record)
        self._publish_sensors(sec, nsec, record)
        if wanted("solver", record):
            self.diagnostics.publish(out, sec, nsec, record)
        if not first and wanted("applied_torque", record):
            self._publish_applied_torque(record)
        if timing is not None:
            timing.row[3] = time.perf_counter()
        self._after_state(record)

    def _joint_states_wanted(self, first, record) -> bool:
        """Whether /joint_states goes out: state 0 on the exact subscriber count, later on
        TopicOutput.wanted's."""
        out = self.output
        if first:
            return (out.subscription_count("joint_states") > 0
                    or (record and self.recording.recorder is not None)
                    or out.live_wants("joint_states"))
        return out.wanted("joint_states", record)

    def _after_state(self, record):
        """After a state's topics: the next step prepared, /tf and the markers, the
        recording's step (a re-send: /tf again only), the timing row, the counts, the live
        view's messages of this step at once."""
        svc, out, timing = self.service, self.output, self.timing
        if record:
            self._prepare_next_step()
            self.visualisation.publish()
            self.recording.after_state(svc.k)
        else:
            self.visualisation.republish()     # /tf with the re-sent state
        if timing is not None and record:
            timing.row[4] = time.perf_counter()
            timing.commit(svc.stamp_ns)
        out.update_counts()
        if out.live is not None:
            out.live.flush()

    def republish_state(self):
        """Send the current state again on every topic with subscribers, /tf included (not
        recorded)."""
        self.output.forget_counts()       # fresh subscriber counts
        self.publish_state(record=False)

    def state_subscriber_count(self) -> int:
        """The subscribers of the topics a controller waits for (state_topics), now."""
        pubs = self.output.pubs
        return sum(pubs[k][0].get_subscription_count() for k in self.state_topics
                   if k in pubs)

    def clock_subscriber_count(self) -> int:
        """The subscribers of /clock (nodes on sim time), now (0 without publish_clock)."""
        pub = self.output.pubs.get("clock")
        return pub[0].get_subscription_count() if pub is not None else 0

    def publish_robot_description(self):
        """The URDF on robot_description (latched), with the <ros2_control> section that
        ros2_control_command_interfaces asks for (its initial values: the simulator's
        joint positions now, at the initial state)."""
        urdf = self.sim.description.urdf_xml
        interfaces = parse_command_interfaces(self.settings.ros2_control_command_interfaces)
        if interfaces:
            urdf = with_ros2_control(urdf, simulator_section(self.sim, interfaces))
        self.output.emit("robot_description", String(data=urdf), True)

    # -- one path per topic ----------------------------------------------------------------
    def _bundle_wanted(self, first) -> bool:
        """Send the state bundle: someone subscribes to it (the exact count for state 0 and
        for a re-send; else the count taken after the previous step). Never recorded: the
        recording has the public topics."""
        if self.bundle_cdr is None:
            return False
        out = self.output
        if first or out.counts_k < 0:
            return out.subscription_count("state_bundle") > 0 or out.live_wants("state_bundle")
        return out.counts.get("state_bundle", 0) > 0 or out.live_wants("state_bundle")

    def publish_bundle(self, sec, nsec, base, joints, forces):
        """starleth/state_bundle: the values of joint_states, base_state and the foot
        wrenches of this step in one Float64MultiArray (state_io.state_bundle_bytes)."""
        p, topic, _, _ = self.output.pubs["state_bundle"]
        data = state_bundle_bytes(self.bundle_cdr, sec, nsec, base, joints,
                                  forces[:len(self.feet)])
        p.publish(data)
        if self.output.live_wants("state_bundle"):
            self.output.live.log(topic, data, self.service.stamp_ns)

    def _publish_joint_states(self, sec, nsec, record, joints, key="joint_states"):
        """joint_states (or `key`'s topic): position, velocity and the torque as effort
        (joints: the sensors' φ, φ̇, τ: measured, or the applied torque where exact)."""
        cdr = self._js_cdr
        if cdr is not None:    # CDR bytes from a template: no per-step Python->C copy
            self.output.emit_cdr(key, cdr.build(sec, nsec, *joints), record)
            return
        js = self.js_msg
        js.header.stamp.sec, js.header.stamp.nanosec = sec, nsec
        js.position, js.velocity, js.effort = (float_array(x) for x in joints)
        self.output.emit(key, js, record)

    def _publish_sensors(self, sec, nsec, record):
        """The IMU and the foot contacts (measured), and with noisy sensors the exact
        joint states, IMU and foot contacts on the ground_truth/ topics."""
        wanted = self.output.wanted
        readings = ((self.sensors.measured, 0), (self.sensors.truth, 1)) \
            if self.ground_truth else ((self.sensors.measured, 0),)
        for r, i in readings:
            (js, imu, contacts) = (keys[i] for keys in self.SENSOR_KEYS)
            if i and wanted(js, record):
                self._publish_joint_states(
                    sec, nsec, record, (r.joint_position, r.joint_velocity, r.joint_effort),
                    js)
            if wanted(imu, record):
                self._publish_imu(sec, nsec, r, record, imu)
            if wanted(contacts, record):
                self._publish_foot_contacts(sec, nsec, r, record, contacts)

    def _publish_foot_contacts(self, sec, nsec, r, record, key):
        """starleth/foot_contacts (or `key`'s topic): per foot the contact flag as position
        (1.0 contact, 0.0 none) and the normal force [N] as effort."""
        cdr = self._contacts_cdr
        if cdr is not None:
            self.output.emit_cdr(key, cdr.build(sec, nsec, r.contact_flag, r.contact_force),
                                 record)
            return
        m = self.contacts_msg
        m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
        m.position, m.effort = float_array(r.contact_flag), float_array(r.contact_force)
        self.output.emit(key, m, record)

    def _publish_applied_torque(self, record):
        """starleth/applied_torque: the saturated torque of every physics step of the step
        that led to this state, with the explicit torques and the kd of the implicit dampers
        (physics_steps x 3 x joints, joint order; no header: recorded at this state's
        stamp). What starleth-replay re-applies (Simulator.step_applied)."""
        sim = self.sim
        rows = np.concatenate((sim.applied_torques_per_step[:, None],
                               sim.replay_torques_per_step.reshape(-1, 2, sim.n_joints)), 1)
        data = np.ascontiguousarray(rows, dtype="<f8").tobytes()
        self.output.emit_cdr("applied_torque", self._torque_prefix + data, record)

    def _publish_foot_wrenches(self, sec, nsec, feet, record, forces=None):
        """starleth/<foot>/wrench: the contact force F = Λ/Δt of each foot in `feet`
        (forces: Simulator.contact_forces() where already read)."""
        cdr = self._wrench_cdr
        if cdr is not None and self._feet_first:
            if forces is None:
                forces = self.sim.contact_forces()
            for name, f in zip(self.feet, forces[:len(self.feet)].tolist(), strict=False):
                if name in feet:
                    self.output.emit_cdr(name, cdr.build(sec, nsec, f), record)
            return
        for c in self.sim.contacts:
            if c.name not in feet:
                continue
            m = self.wrench_msgs[c.name]
            m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
            f = m.wrench.force
            f.x, f.y, f.z = float(c.force[0]), float(c.force[1]), float(c.force[2])
            self.output.emit(c.name, m, record)

    def _publish_odometry(self, sec, nsec, base, record):
        """starleth/base_state: pose in the world, twist in the base frame."""
        p, quat, _, w, _, v_body = base
        if self._odom_cdr is not None:
            self.output.emit_cdr("base_state", self._odom_cdr.build(
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
        self.output.emit("base_state", o, record)

    def _publish_clock(self, sec, nsec, record):
        """/clock: the sim time."""
        if self._clock_cdr is not None:
            self.output.emit_cdr("clock", self._clock_cdr.build(sec, nsec, ()), record)
        else:
            c = self.clock_msg.clock
            c.sec, c.nanosec = sec, nsec
            self.output.emit("clock", self.clock_msg, record)

    def _publish_imu(self, sec, nsec, r, record, key="imu"):
        """starleth/imu (or `key`'s topic) of the reading `r`: orientation, body rates
        (gyro), proper acceleration (accelerometer), base frame."""
        quat, w, a = (x.tolist() for x in (r.imu_orientation, r.imu_angular_velocity,
                                           r.imu_linear_acceleration))
        if self._imu_cdr is not None:
            self.output.emit_cdr(key, self._imu_cdr.build(sec, nsec, (*quat, *w, *a)), record)
            return
        imu = self.imu_msg
        imu.header.stamp.sec, imu.header.stamp.nanosec = sec, nsec
        io_ = imu.orientation
        io_.x, io_.y, io_.z, io_.w = quat
        iw, ia = imu.angular_velocity, imu.linear_acceleration
        iw.x, iw.y, iw.z = w
        ia.x, ia.y, ia.z = a
        self.output.emit(key, imu, record)

    def _prepare_next_step(self):
        """The controller now works on its answer to the state just published: do the
        torque-independent part of the next step meanwhile (Simulator.prepare: the
        midpoint, q^M, M, h and the kinematics), which takes it off the lockstep critical
        path (command in -> step -> state out). The result of the step is the same with or
        without it."""
        try:
            self.sim.prepare()
        except Exception as e:   # pragma: no cover - the step redoes it and reports
            self.service.warnings.warn("prepare", f"preparing the next step failed: {e}")
