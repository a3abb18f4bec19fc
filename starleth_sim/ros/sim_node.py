"""``sim_node``: one StarlETH ``Simulator`` behind the ROS 2 interfaces users know from
mujoco_ros2_control / gz_ros2_control. A thin adapter: no physics in here.

    ros2 run starleth_sim sim_node --ros-args -p mode:=lockstep -p record:=run.mcap
    python -m starleth_sim.ros.sim_node --ros-args --params-file my_sim.yaml

Every topic, service and parameter, the lockstep protocol, bad input and recording:
doc/sim_node.md. This module is the node itself (its parameters, subscriptions, services
and their callbacks) and its two console scripts, ``sim_node`` (:func:`main`) and
``sim_node_composed`` (:func:`main_composed`). The parts it wires together: the publishing of
the state (:mod:`.state_publisher` through :mod:`.topic_output`, with :mod:`.solver_diagnostics`
and :mod:`.visualisation`), the terrain (:mod:`.terrain_markers`), the live view
(:mod:`.live_view`), the recording (:mod:`.node_recording`), the loops (:mod:`.sim_loops`)
and the ROS-free core (:class:`~.service.SimService`, :mod:`.state_io`, :mod:`.parameters`).
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import replace

import yaml
from geometry_msgs.msg import WrenchStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import SetBool, Trigger

from starleth_interface.ros_helpers import (
    StopSignals,
    UnknownParameterError,
    capture_python_warnings,
    check_parameter_names,
    declare_parameters,
    init_ros,
    make_executor,
    parameter_override_names,
    route_python_logging,
    set_cpu_scheduling,
    shutdown_ros,
)
from starleth_interface.topics import (
    TOPIC_CLOCK,
    TOPIC_EFFORT_COMMANDS,
    TOPIC_ESTIMATOR_ODOMETRY,
    TOPIC_JOINT_COMMANDS,
    TOPIC_POSITION_COMMANDS,
    TOPIC_VELOCITY_COMMANDS,
    TOPIC_WRENCH,
    TOPIC_WRENCH_PERSISTENT,
)

from ..physics.config import ConfigError, load_preset
from ..physics.simulator import Simulator
from ..robots import config_with_robot
from .cdr import CommandDecoder
from .live_view import LiveView, MeshAssets
from .node_recording import NodeRecording, describe_run, make_recorder
from .parameters import (
    COMMAND_DELAY,
    GAIN_PARAMETERS,
    SEED,
    SIM_NODE_PARAMETERS,
    Settings,
    load_default_parameters,
    namespace_frame_prefix,
    robot_default_gains,
)
from .period_stats import PeriodStats
from .qos import COMMAND_QOS, LATCHED_QOS, SERVICE_QOS
from .service import SimService
from .sim_loops import SimLoops
from .solver_diagnostics import SolverDiagnostics
from .state_io import parse_initial_state
from .state_publisher import StatePublisher
from .terrain_markers import TerrainTopic
from .tf import TF_TYPE, base_link
from .topic_output import TopicOutput
from .visualisation import steps_between


class SimNode:
    """The rclpy node: parameters, subscriptions, services, and the parts that publish,
    record and step. Created by :func:`main`; usable in-process (tests, bench)."""

    def __init__(self, context=None, parameter_overrides=None, node_name="sim_node",
                 settings_file=None):
        defaults = load_default_parameters(settings_file)
        self.node = Node(node_name, context=context,
                         parameter_overrides=[Parameter(k, value=v) for k, v in
                                              (parameter_overrides or {}).items()])
        node = self.node
        self.log = node.get_logger()
        specs = [replace(p, default=defaults[p.name]) for p in SIM_NODE_PARAMETERS]
        values = declare_parameters(node, specs)
        try:
            check_parameter_names(node, specs)      # a mistyped name: an error, not ignored
        except UnknownParameterError:
            node.destroy_node()
            raise
        self.settings = Settings(**values).validate()
        # the physics core's Python logging (e.g. "prox iteration did not converge") in
        # this node's log
        self._unroute_logging = route_python_logging(self.log, ("starleth_sim",
                                                                "starleth_interface"))
        s = self.settings
        self.sim = sim = self._make_simulator()
        self._check_frames()
        self._scale_default_gains(defaults)
        q0, u0, init_desc = parse_initial_state(s.initial_state, sim)
        self.initial_state_desc = init_desc
        # two call sites: rclpy refuses one call site that logs at two severities
        self.service = SimService(sim, s, q0, u0, warn=self._log_warning,
                                  error=self._log_error)
        self.context = node.context
        self.period_stats = PeriodStats(sim.control_period / max(s.real_time_factor, 1e-12))
        self.decoder = CommandDecoder(sim.joint_names)
        self.recording = NodeRecording(self.service.warnings.warn, self.log)
        self.output = TopicOutput(node, self.service, self.recording)
        self.diagnostics = SolverDiagnostics(sim, s, self.service, self.period_stats,
                                             self.recording)
        self.publisher = StatePublisher(node, sim, s, self.service, self.output,
                                        self.diagnostics, self.log)
        self.loops = SimLoops(self.context, sim, s, self.service, self.period_stats,
                              self.publisher, self.diagnostics, self.log)
        # (its publisher before the recording and the live view, which take the topics)
        self.terrain = TerrainTopic.create(self.output, sim.config, s.world_frame, self.log)
        self._setup_subscriptions()
        self._setup_services()
        node.add_on_set_parameters_callback(self._on_set_parameters)
        self._start_outputs()

    def _start_outputs(self):
        """The CPU scheduling, the recording and the live view, then the first messages
        (robot_description, /tf_static, the terrain) and the start line."""
        s, sim = self.settings, self.sim
        err = set_cpu_scheduling(s.cpu_scheduling)     # before the writer process starts
        if err:
            self.log.warning(f"cpu_scheduling {s.cpu_scheduling}: {err}")
        if s.record:
            self._open_recording(s.record)
        if s.live_view:
            self._start_live_view()
        self.publisher.publish_robot_description()
        self.publisher.visualisation.publish_static_transforms()
        if self.terrain is not None:
            self.terrain.publish()
        self.log.info(f"{s.physics} physics, {s.mode} mode"
                      + (f", real-time factor {s.real_time_factor:g}" if s.real_time_factor else
                         ", as fast as the controller") +
                      (f", recording to {s.record}" if s.record else "") +
                      f"; {sim.n_joints} joints, control period "
                      f"{sim.control_period * 1e3:g} ms" +
                      (f"; {self.service.delay_text}" if self.service.delay.steps or
                       s.command_delay else ""))

    @property
    def timing(self):
        """A :class:`~starleth_interface.cycle_times.CycleTimes` that times each part of a
        cycle (benchmarks only; None: not timed)."""
        return self.publisher.timing

    @timing.setter
    def timing(self, value):
        self.publisher.timing = value

    # -- setup -----------------------------------------------------------------------------
    def _make_simulator(self) -> Simulator:
        """The simulator of the physics preset for the robot parameter's robot (a bad
        robot: ConfigError naming the parameter), with the sensors and actuators files,
        the physics overrides and the seed applied in that order."""
        s = self.settings
        try:
            config = config_with_robot(load_preset(s.physics), s.robot)
        except ConfigError as e:
            text = str(e)
            raise ConfigError(f"parameter {text}" if text.startswith("robot: ") else
                              f"parameter robot: {text}") from None
        for kind in ("sensors", "actuators"):
            if getattr(s, kind):
                try:
                    config = config.with_overlay(getattr(s, kind), kind)
                except ConfigError as e:
                    raise ConfigError(f"parameter {kind}: {e}") from None
        config = config.with_overrides(**s.physics_override_dict())
        if s.seed != SEED.off_value:
            config = config.with_overrides(**{"sensors.seed": s.seed})
        return Simulator(config)

    def _scale_default_gains(self, defaults):
        """default_kp and default_kd, where neither given nor set in the settings file, are
        StarlETH's scaled to the robot (parameters.robot_default_gains); the node's
        parameters then say the values in use."""
        given = set(parameter_override_names(self.node))
        unset = [name for name, spec in GAIN_PARAMETERS.items()
                 if name not in given and defaults[name] == spec.default]
        gains = robot_default_gains(self.sim.description, unset)
        if gains:
            for name, value in gains.items():
                setattr(self.settings, name, value)
            self.node.set_parameters([Parameter(k, value=v) for k, v in gains.items()])

    def _check_frames(self):
        """base_frame must name the URDF's root link (the odometry's child frame is that
        link's frame on /tf); a namespaced node without tf_frame_prefix is told how to keep
        its frames apart from another robot's (the prefix is not derived from the namespace,
        as robot_state_publisher does not: the frame names stay what the user set)."""
        s = self.settings
        root = base_link(self.sim.description.urdf_xml)
        if not s.base_frame:
            s.base_frame = root
        if s.base_frame != root:
            raise ConfigError(f"parameter base_frame: {s.base_frame!r} is not the root link "
                              f"of the robot's URDF ({root!r}), whose frame on /tf is the "
                              "odometry's child frame; use base_frame:=" + root)
        ns = self.node.get_namespace()
        if ns != "/" and not s.tf_frame_prefix:
            self.log.info(
                f"namespace {ns} without tf_frame_prefix: this robot's frames ({s.world_frame} "
                f"-> {root}, {root} -> its links) are those of any other robot on /tf; with "
                f"several robots set tf_frame_prefix:={namespace_frame_prefix(ns)} (the launch "
                "file does)")

    def _setup_subscriptions(self):
        node = self.node
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
                        topic = self.subs[key][1]
                        self.service.warnings.warn("bad_cdr", f"dropped an undecodable "
                                                   f"message on {topic}: {e}", topic)
                        return
                    handler(msg)
            sobj = node.create_subscription(typ, topic, cb, COMMAND_QOS,
                                            raw=raw or fast is not None)
            self.subs[key] = (sobj, sobj.topic_name, typ, COMMAND_QOS)

        sub("effort", Float64MultiArray, TOPIC_EFFORT_COMMANDS, self._on_effort,
            self._on_effort_cdr)
        sub("joint_commands", JointState, TOPIC_JOINT_COMMANDS, self._on_joint_command,
            self._on_joint_command_cdr)
        sub("position", Float64MultiArray, TOPIC_POSITION_COMMANDS,
            lambda msg: self._on_array("position", msg))
        sub("velocity", Float64MultiArray, TOPIC_VELOCITY_COMMANDS,
            lambda msg: self._on_array("velocity", msg))
        sub("wrench", WrenchStamped, TOPIC_WRENCH, self._on_wrench)
        sub("wrench_persistent", WrenchStamped, TOPIC_WRENCH_PERSISTENT,
            self._on_wrench_persistent)
        if raw:     # a controller's state estimate: recorded for the analysis, not read
            sub("estimator_odometry", Odometry, TOPIC_ESTIMATOR_ODOMETRY, None,
                lambda _: True)

    def _setup_services(self):
        node = self.node
        self.srv_reset = node.create_service(Trigger, "~/reset", self._srv_reset,
                                             qos_profile=SERVICE_QOS)
        self.srv_pause = node.create_service(SetBool, "~/pause", self._srv_pause,
                                             qos_profile=SERVICE_QOS)
        self.srv_step = node.create_service(Trigger, "~/step", self._srv_step,
                                            qos_profile=SERVICE_QOS)

    def _open_recording(self, path):
        rec = make_recorder(path, self.settings, self.recording.failed, self.log)
        self.recording.start(rec)
        describe_run(rec, sim=self.sim, settings=self.settings, service=self.service,
                     initial_state_spec=self.initial_state_desc["spec"],
                     namespace=self.node.get_namespace(), pubs=self.output.pubs,
                     subs=self.subs,
                     tf_topics=self.publisher.visualisation.tf_topics_recorded())

    def _start_live_view(self):
        """The live view (:mod:`.live_view`) of every published topic and the TF topics
        (None after one error line if it cannot start)."""
        s = self.settings
        topics = [(topic, typ, qos == LATCHED_QOS)
                  for _, topic, typ, qos in self.output.pubs.values()]
        topics += [(self.node.resolve_topic_name(topic), TF_TYPE, qos == LATCHED_QOS)
                   for topic, qos in self.publisher.visualisation.tf_topics_recorded().values()]
        self.output.live = LiveView.open(
            s.live_view_host, s.live_view_port, topics, self.log,
            name=self.node.get_fully_qualified_name(),
            every=steps_between(s.live_view_rate, self.sim.control_period) or 1,
            throttle_period=s.warn_throttle_period,
            assets=MeshAssets.of_robot(self.sim.config.robot, self.sim.description.urdf_xml))

    # -- callbacks -------------------------------------------------------------------------
    def _log_warning(self, message):
        self.log.warning(message)

    def _log_error(self, message):
        self.log.error(message)

    def _record_input(self, key, data):
        self.recording.write_input(self.subs[key][1], data, self.service.stamp_ns)

    def _on_effort(self, msg):
        if self.service.submit_effort_array(msg.data)[0] and self.loops.step_on_answer:
            self.loops.advance()

    def _on_effort_cdr(self, data) -> bool:
        ok, tau = self.decoder.effort_array(data)
        if not ok:
            return False
        if self.service.submit_effort_array(tau)[0] and self.loops.step_on_answer:
            self.loops.advance()
        return True

    def _on_joint_command_cdr(self, data) -> bool:
        timing = self.publisher.timing
        if timing is not None:
            timing.row[0] = time.perf_counter()
        ok, stamp_ns, tau = self.decoder.joint_command(data)
        if not ok:
            return False
        if self.service.submit_ordered_joint_command(tau, stamp_ns)[0] and \
                self.loops.step_on_answer:
            self.loops.advance()
        return True

    def _on_joint_command(self, msg):
        st = msg.header.stamp
        if self.service.submit_joint_command(msg.name, msg.effort,
                                             st.sec * 1_000_000_000 + st.nanosec,
                                             msg.position, msg.velocity)[0] \
                and self.loops.step_on_answer:
            self.loops.advance()

    def _on_array(self, kind, msg):
        """joint_group_{position,velocity}_controller/commands: targets in joint order."""
        if self.service.submit_array(kind, msg.data)[0] and self.loops.step_on_answer:
            self.loops.advance()

    def _on_set_parameters(self, params):
        """default_kp, default_kd and command_delay at run time (the other parameters are
        read only): checked (a rejection is warned of, and gains counted in
        gains_rejected), then the gains taken by the held command at once, the delay by the
        commands received from then on."""
        gains, delay = {}, None
        for prm in params:
            if prm.name == COMMAND_DELAY.name:
                delay = COMMAND_DELAY.coerce(prm.value)
                try:
                    COMMAND_DELAY.check(delay)
                except ValueError as e:
                    self.service.warnings.warn("command_delay", f"rejected {e}")
                    return SetParametersResult(successful=False, reason=str(e))
                continue
            spec = GAIN_PARAMETERS.get(prm.name)
            if spec is None:
                continue
            value = spec.coerce(prm.value)
            try:
                spec.check(value)
            except ValueError as e:
                self.service.reject_gains(prm.name, str(e))
                return SetParametersResult(successful=False, reason=str(e))
            gains[prm.name] = value
        if gains:
            ok, why = self.service.set_gains(gains.get("default_kp"), gains.get("default_kd"))
            if not ok:
                return SetParametersResult(successful=False, reason=why)
            self.log.info("gains: " + ", ".join(f"{k} {v}" for k, v in gains.items()))
        if delay is not None:
            self.log.info(self.service.set_command_delay(delay)[1])
        return SetParametersResult(successful=True)

    def _wrench(self, msg, persistent):
        f, m = msg.wrench.force, msg.wrench.torque
        self.service.submit_wrench(msg.header.frame_id, (f.x, f.y, f.z), (m.x, m.y, m.z),
                                   persistent)

    def _on_wrench(self, msg):
        self._wrench(msg, False)

    def _on_wrench_persistent(self, msg):
        self._wrench(msg, True)

    # -- services ------------------------------------------------------------------------
    def _srv_reset(self, _request, response):
        self.service.reset()
        self.publisher.publish_state()
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

    def _srv_step(self, _request, response):
        svc = self.service
        if not svc.paused:
            response.success = False
            response.message = "not paused: call ~/pause with data=true first"
            return response
        if svc.step() is None:
            response.success = False
            response.message = f"no step: {svc.pause_reason}; call ~/reset"
            return response
        self.publisher.publish_state()
        response.success = True
        response.message = f"stepped to sim time {svc.stamp_ns * 1e-9:.4f} s"
        return response

    # -- running and shutdown --------------------------------------------------------------
    def request_stop(self, *_):
        self.loops.stop = True

    def run(self, executor):
        """Run until request_stop() or the context is shut down (:class:`.SimLoops`)."""
        self.loops.run(executor)

    def summary(self) -> dict:
        d = self.service.summary()
        if self.settings.mode == "realtime":
            d.update(self.period_stats.summary())
        if self.recording.stats is not None:
            d["recorded_messages"], d["recording_dropped"] = self.recording.counts()
            d["recording"] = self.recording.state()
        return d

    def close(self):
        """Finalise the recording (idempotent; at most NodeRecording.CLOSE_TIMEOUT s) and
        log a summary."""
        self.recording.close(self.summary)
        if self.output.live is not None:
            self.output.live.stop()
        summary = self.summary()
        self.log.info("summary: " + json.dumps(summary))
        return summary

    def destroy(self):
        self.close()
        self._unroute_logging()
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
    record:=run.mcap``; its robot is sim_node's unless one is given. Exit status as
    ``sim_node``'s."""
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
        except UnknownParameterError as e:
            print(f"sim_node: {e}", file=sys.stderr)
            return 2
        except (ConfigError, ValueError, OSError) as e:
            print(f"sim_node: configuration error: {e}", file=sys.stderr)
            return 2
        capture_python_warnings(sim_node.log)   # numpy's warnings: the node's log
        if signals.requested:
            sim_node.request_stop()
        executor, kind = make_executor(sim_node.settings.executor, sim_node.context)
        executor.add_node(sim_node.node)
        if controller_params is not None:
            from starleth_controller.controller_node import ControllerNode  # deferred: composed
            # the controller follows the clock sim_node publishes (/clock remapped, e.g.
            # into the namespace, applies to both nodes, as it would in two processes)
            clock = sim_node.node.resolve_topic_name(TOPIC_CLOCK)
            # the robot simulated, unless --controller-param robot:= says otherwise
            controller_params = {"robot": sim_node.settings.robot, **controller_params}
            try:
                ctl = holder["controller"] = ControllerNode(
                    context=sim_node.context, parameter_overrides=controller_params,
                    namespace=sim_node.node.get_namespace(), use_global_arguments=False,
                    cli_args=["--ros-args", "-r", f"{TOPIC_CLOCK}:={clock}"])
            except ValueError as e:
                print(f"controller_node: "
                      f"{'' if isinstance(e, UnknownParameterError) else 'configuration error: '}"
                      f"{e}", file=sys.stderr)
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
