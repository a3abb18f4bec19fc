"""sim_node's recording: the recorder made from the settings (:func:`make_recorder`, the one
place that chooses the writer), what a bag holds besides the messages (topics, metadata,
attachments: :func:`describe_run`), and the recording's life in the node
(:class:`NodeRecording`: inputs, hand-overs, drops, a failure, the close). What is recorded
and what happens when the recorder fails: doc/sim_node.md, "Recording"."""
from __future__ import annotations

import json
from dataclasses import asdict
from importlib.metadata import version

import yaml

from ..physics.config import ConfigError
from ..robots import load_robot, spec_text
from .recording import RecordingError, StorageOptions, open_recorder
from .state_io import initial_state_record
from .tf import TF_TYPE


def package_version() -> str:
    """The installed starleth_sim version (recorded with every bag), or 'unknown'."""
    try:
        return version("starleth_sim")
    except Exception:   # not installed (run from a source tree)
        return "unknown"


def robot_spec_text(sim) -> str | None:
    """The YAML text of the robot spec `sim` was built from (None: a robot from a URDF, or a
    description given to the simulator directly)."""
    try:
        if load_robot(sim.config.robot).name == sim.description.name:
            return spec_text(sim.config.robot)
    except ConfigError:
        pass
    return None


def make_recorder(path, settings, on_failure, log):
    """The recorder of sim_node's `settings` writing to `path`
    (:func:`~.recording.open_recorder`: a writer process of its own, or where no process can
    be started, a writer thread of this one; with record_max_duration / record_max_size a
    rosbag2 bag directory of numbered files, each complete on its own). `on_failure(message)`
    is called once if the recording fails later. ConfigError (exit 2) if `path` cannot be
    written."""
    s = settings
    options = StorageOptions(
        uri=path, compression=s.record_compression,
        custom_data={"generator": "starleth_sim sim_node"},
        max_bagfile_duration_ns=int(round(s.record_max_duration * 1e9)),
        max_bagfile_size=s.record_max_size)
    try:
        return open_recorder(options, on_failure=on_failure, warn=log.warning)
    except RecordingError as e:      # the file cannot be written: one line, exit 2
        raise ConfigError(f"parameter record: cannot record to {e}") from None


def sensor_metadata(sim, pubs) -> dict:
    """The sensors' part of the metadata (their configuration and seed are physics_config's
    sensors section): the sensor topics; with noisy sensors joint_states is measured and the
    exact values are on the ground_truth/ topics ('' with ideal ones: joint_states is
    exact)."""
    def topic(key):
        return pubs[key][1] if key in pubs else ""
    return {"imu_topic": topic("imu"), "foot_contacts_topic": topic("foot_contacts"),
            "sensors_seed": str(sim.config.sensors.seed),
            "ground_truth_joint_states_topic": topic("gt_joint_states"),
            "ground_truth_imu_topic": topic("gt_imu"),
            "ground_truth_foot_contacts_topic": topic("gt_foot_contacts")}


def describe_run(rec, *, sim, settings, service, initial_state_spec, namespace, pubs, subs,
                 tf_topics):
    """Declare the topics of a new recording `rec` (`pubs` and `subs`: {key: (endpoint,
    topic, type, qos)}; `tf_topics`: {key: (topic, qos)} of TF_TYPE, may be empty) and add
    what re-runs it (starleth-replay) and reads it: the metadata 'starleth_sim' (physics,
    initial state, parameters, topics, stamps) and the attachments (URDF, physics preset,
    initial state, parameter file)."""
    for _p, topic, typ, qos in pubs.values():
        rec.add_topic(topic, typ, qos)
    for _sobj, topic, typ, qos in subs.values():
        rec.add_topic(topic, typ, qos)
    for topic, qos in tf_topics.values():
        rec.add_topic(topic, TF_TYPE, qos)
    cfg_yaml = yaml.safe_dump(sim.config.to_dict(), sort_keys=False)
    spec = robot_spec_text(sim)
    init = initial_state_record(sim, service.q0, service.u0, initial_state_spec)
    params = asdict(settings)
    rec.add_metadata("starleth_sim", {
        "physics_config": cfg_yaml, "initial_state": json.dumps(init),
        "parameters": json.dumps(params), "joint_names": json.dumps(list(sim.joint_names)),
        "control_period": repr(sim.control_period),
        "stamp_period_ns": str(service.period_ns),
        "namespace": namespace,
        # the robot: its URDF and its spec as loaded (starleth_sim.robots.recorded_description)
        "robot": sim.description.name,
        "urdf_attachment": f"{sim.description.name}.urdf",
        "robot_spec_attachment": f"{sim.description.name}.robot.yaml" if spec else "",
        # for starleth-replay: what re-runs this recording open loop, bit for bit
        "package_version": package_version(),
        "joint_states_topic": pubs["joint_states"][1],
        "base_state_topic": pubs["base_state"][1],
        "wrench_topic": subs["wrench"][1],
        "wrench_persistent_topic": subs["wrench_persistent"][1],
        "applied_torque_topic": pubs["applied_torque"][1],
        **sensor_metadata(sim, pubs),
        "replay": "torques: applied_torque_topic at log time t_(k+1) = the torques of each "
                  "physics step of step k -> k+1 (physics_steps x 3 x joints: the torques "
                  "applied, saturated, derated; the explicit torques; the kd of the implicit "
                  "dampers: Simulator.step_applied of the last two); in bags without it, "
                  "/joint_states effort at stamp t_(k+1) = the "
                  "torque applied over step k -> k+1 (joint order joint_names); "
                  "inputs (commands, wrenches): log time t_k = the stamp of the state "
                  "after which they were taken: a wrench acts from step k -> k+1"})
    rec.add_attachment(f"{sim.description.name}.urdf", "application/xml",
                       sim.description.urdf_xml)
    if spec:
        rec.add_attachment(f"{sim.description.name}.robot.yaml", "application/yaml", spec)
    rec.add_attachment("physics_config.yaml", "application/yaml", cfg_yaml)
    rec.add_attachment("initial_state.json", "application/json", json.dumps(init, indent=1))
    rec.add_attachment("sim_node_parameters.yaml", "application/yaml",
                       yaml.safe_dump({"/**": {"ros__parameters": params}}, sort_keys=False))


class NodeRecording:
    """The recording of one sim_node run: ``recorder`` while it records (None: off, or it
    failed), ``failure`` why it stopped early. `warn(key, message)` is the node's throttled
    warning, `log` its logger."""

    #: steps between two hand-overs of the recorded messages to the writer process (a pipe
    #: write and a wake-up of that process each; SIGINT / close send the rest, a sim
    #: process killed outright loses at most these last steps, the file stays complete)
    HAND_OVER_STEPS = 8
    #: s: SIGINT / SIGTERM end the node within 2 s whatever the recorder has queued (what
    #: the writer has not taken by then is dropped, counted in the log)
    CLOSE_TIMEOUT = 1.0

    def __init__(self, warn, log):
        self.warn = warn
        self.log = log
        self.recorder = None     # the recorder while it records (None: off or failed)
        self.stats = None        # the recorder, also after it failed (None: never opened)
        self.failure = None      # why the recording stopped early
        self.dropped_seen = 0    # recorded messages dropped, as last reported

    def start(self, recorder):
        self.recorder = self.stats = recorder

    def failed(self, message):
        """The recorder failed (disk full, file-size limit, I/O error, its process gone);
        it has closed the file as far as it could (message: file, cause, how to read it).
        The simulation goes on without recording; /starleth/solver says
        ``recording: failed (...)``. Called once, from the thread that found out."""
        self.failure = message
        self.recorder = None
        self.log.error(f"recording failed: {message}. The simulation goes on without "
                       "recording.")

    def state(self) -> str:
        """'off', 'on' or 'failed (<file>: <cause>; ...)' (/starleth/solver's recording)."""
        if self.failure is not None:
            return f"failed ({self.failure})"
        return "on" if self.recorder is not None else "off"

    def counts(self):
        """(messages recorded, dropped) -- (0, 0) without a recording."""
        rec = self.stats
        if rec is None:
            return 0, 0
        return rec.message_count - rec.dropped, rec.dropped

    def write_input(self, topic, data, stamp_ns):
        """Record an input as it arrived (CDR bytes), at the stamp of the current state."""
        rec = self.recorder
        if rec is not None and not rec.closed:
            rec.write(topic, data, stamp_ns)

    def after_state(self, k):
        """After the state of step `k` went out: every HAND_OVER_STEPS steps, hand the last
        steps' messages to the writer process and report new drops."""
        rec = self.recorder
        if rec is not None and k % self.HAND_OVER_STEPS == 0:
            rec.hand_over()   # the last steps' messages to the writer process (if any)
            if rec.dropped and self.recorder is not None:   # (not: it just failed)
                self._check_drops(rec)

    def _check_drops(self, rec):
        dropped = rec.dropped
        if dropped != self.dropped_seen:
            self.dropped_seen = dropped
            self.warn("record_dropped", f"recording {rec.path}: the recording process is "
                      f"behind; {dropped} messages dropped so far")

    def close(self, summary):
        """Finalise the recording (at most CLOSE_TIMEOUT s; nothing if it is off, failed or
        closed): `summary()` gives the run's summary, stored as metadata."""
        rec = self.recorder
        if rec is None or rec.closed:
            return
        try:
            rec.close(timeout=self.CLOSE_TIMEOUT, metadata={"starleth_sim_summary": {
                k: json.dumps(v) for k, v in summary().items()}})
        except (RecordingError, OSError) as e:   # the file is closed as far as it could
            if self.failure is None:
                self.failure = str(e)
                self.log.error(f"recording failed while closing: {e}")
        else:
            note = f"; {rec.close_note}" if rec.close_note else ""
            self.log.info(f"recording finalised: {rec.path} "
                          f"({rec.message_count - rec.dropped} messages){note}")
