"""The demo's figures (``starleth-demo``): :class:`DemoResult` with what makes a run fail
(`problems`: a node's exit status, a missing step, a fall, too short a trot, the course not
crossed, the state estimate off the ground truth), read from the run's recording
(:func:`read_bag`) and printed (:func:`print_summary`)."""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

from starleth_interface.topics import (
    TOPIC_BASE_STATE,
    TOPIC_ESTIMATOR_ODOMETRY,
    TOPIC_JOINT_COMMANDS,
    TOPIC_JOINT_STATES,
    TOPIC_SOLVER,
    resolve,
)

from ..analysis.estimator_error import error_series, odometry_arrays
from ..common.bag import BagError, stream_bag
from .terrain import course_end

PERIOD_NS = 2_500_000            # sim_node's stamp period (400 Hz)
#: StarlETH's: a base height below FALL_HEIGHT is a fall, from its standing height
#: REFERENCE_STANDING (robots/starleth.yaml); another robot's in proportion to its own [m]
FALL_HEIGHT, REFERENCE_STANDING = 0.3, 0.415
#: the issue's acceptance: the trot covers at least this fraction of the commanded distance
ACCEPT_FRACTION = 0.8
MIN_TROT_CHECKED = 4.0           # shorter trots (start-up dominated) are not checked [s]
#: the state estimate's acceptance (issue #48): velocity RMS error [m/s], position drift as a
#: share of the distance walked
ESTIMATE_VELOCITY_RMS, ESTIMATE_DRIFT = 0.05, 0.05


class DemoError(RuntimeError):
    """The demo could not run to the end (a node died, a timeout, no bag, ...)."""


@dataclass
class DemoResult:
    bag: str
    domain_id: int
    physics: str
    stand: float
    trot: float
    speed: float
    t_trot: float = math.nan             # sim time when the trot was requested [s]
    t_end: float = math.nan              # last recorded stamp [s]
    wall: float = math.nan               # wall time of the stepping [s]
    sim_elapsed: float = math.nan        # sim time over the same interval [s]
    distance: float = math.nan           # start -> end, horizontal [m]
    trot_distance: float = math.nan      # over the trot phase, horizontal [m]
    trot_speed: float = math.nan         # mean speed while trotting [m/s]
    displacement: tuple = (math.nan, math.nan)
    min_height: float = math.nan
    max_height: float = math.nan
    solver_iterations_mean: float = math.nan
    solver_iterations_max: int = 0
    messages: int = 0
    topic_counts: dict = field(default_factory=dict)
    joint_states: int = 0
    steps_expected: int = 0
    missing_steps: int = 0
    joint_commands: int = 0
    bag_bytes: int = 0
    html: str = ""                       # the 3D replay (starleth-view) of the recording
    html_frames: int = 0
    html_bytes: int = 0
    html_error: str = ""
    exit_codes: dict = field(default_factory=dict)
    logs: dict = field(default_factory=dict)
    in_process: bool = False             # both nodes in one process (sim_node --composed)
    bare_round_trips: float = math.nan   # bare rclpy round trips / s, measured just before
    bare_error: str = ""
    terrain: str = ""                    # the terrain course (demo/terrain.py), "" flat
    robot: str = "starleth"
    fall_height: float = FALL_HEIGHT     # a base height below this is a fall [m]
    sensors: str = ""                    # sim_node's sensors file ("" ideal)
    drives: str = ""                     # sim_node's actuators file ("" none)
    state_source: str = "ground_truth"   # controller_node's: ground_truth | estimator
    estimate: dict | None = None         # the estimate's errors (estimator_error.error_series)

    @property
    def cycles_per_s(self) -> float:
        """Lockstep control cycles per wall second (one cycle = one control period)."""
        return self.sim_elapsed / (PERIOD_NS * 1e-9) / self.wall if self.wall > 0 else math.nan

    @property
    def rtf(self) -> float:
        return self.sim_elapsed / self.wall if self.wall > 0 else math.nan

    @property
    def fell(self) -> bool:
        return not self.min_height > self.fall_height

    @property
    def complete(self) -> bool:
        return self.joint_states > 0 and self.missing_steps == 0

    @property
    def required_distance(self) -> float:
        return ACCEPT_FRACTION * self.trot * self.speed

    def problems(self) -> list:
        p = []
        for name, rc in self.exit_codes.items():
            if rc != 0:
                p.append(f"{name} exited with status {rc}" if rc is not None else
                         f"{name} did not stop on SIGINT and was killed")
        if not self.complete:
            p.append(f"the bag misses {self.missing_steps} of {self.steps_expected} control "
                     "steps")
        if self.fell:
            p.append(f"the robot fell (base height down to {self.min_height:.3f} m)")
        if self.terrain and not self.displacement[0] > course_end(self.terrain):
            p.append(f"the trunk did not cross the {self.terrain} course (x "
                     f"{self.displacement[0]:+.2f} m, needed > {course_end(self.terrain):g} m)")
        if self.html_error:
            p.append(f"the 3D replay could not be written: {self.html_error}")
        if self.trot >= MIN_TROT_CHECKED and not self.trot_distance >= self.required_distance:
            p.append(f"trotted {self.trot_distance:.2f} m, expected >= "
                     f"{self.required_distance:.2f} m")
        return p + self.estimate_problems()

    def estimate_problems(self) -> list:
        """The estimator's acceptance (state_source estimator): the recording carries the
        estimate, its velocity RMS error and its position drift per metre walked within
        ESTIMATE_VELOCITY_RMS and ESTIMATE_DRIFT."""
        if self.state_source != "estimator":
            return []
        e = self.estimate
        if e is None:
            return ["the recording holds no estimator/odometry"]
        p = []
        if not e["velocity_rms"] <= ESTIMATE_VELOCITY_RMS:
            p.append(f"the estimate's velocity error {e['velocity_rms']:.3f} m/s RMS exceeds "
                     f"{ESTIMATE_VELOCITY_RMS:g} m/s")
        if self.trot >= MIN_TROT_CHECKED and not e["drift"] <= ESTIMATE_DRIFT:
            p.append(f"the estimate drifted {100 * e['drift']:.1f} % of the distance walked "
                     f"(at most {100 * ESTIMATE_DRIFT:g} %)")
        return p


def _step_figures(result: DemoResult, stamps):
    """The control steps' figures from the joint states' stamps [ns] (and the counts)."""
    result.joint_states = len(stamps)
    result.joint_commands = result.topic_counts.get(resolve(TOPIC_JOINT_COMMANDS), 0)
    last = int(stamps.max()) if len(stamps) else 0
    result.steps_expected = last // PERIOD_NS + 1
    result.missing_steps = result.steps_expected - len(np.unique(stamps))
    result.t_end = last * 1e-9


def _trajectory_figures(result: DemoResult, t, pos):
    """The base trajectory's figures: heights, displacement, the trot's distance and speed
    (t: the base states' times [s], pos: their positions)."""
    result.min_height, result.max_height = float(pos[:, 2].min()), float(pos[:, 2].max())
    d = pos[-1, :2] - pos[0, :2]
    result.displacement = (float(d[0]), float(d[1]))
    result.distance = float(np.hypot(*d))
    if math.isfinite(result.t_trot):
        i0 = min(int(np.searchsorted(t, result.t_trot)), len(t) - 1)
        dt = t[-1] - t[i0]
        result.trot_distance = float(np.hypot(*(pos[-1, :2] - pos[i0, :2])))
        result.trot_speed = result.trot_distance / dt if dt > 0 else math.nan


def read_bag(path, result: DemoResult):
    """Fill `result` from the recording (read once): base trajectory, solver iterations,
    counts, and with state_source estimator the estimate's errors against the ground truth
    (estimator_error.error_series of estimator/odometry against the base state)."""
    if not os.path.exists(path):
        raise DemoError(f"the recording {path} does not exist")
    result.bag_bytes = os.path.getsize(path)
    js, base, solver = (resolve(t) for t in (TOPIC_JOINT_STATES, TOPIC_BASE_STATE,
                                              TOPIC_SOLVER))
    stamps, t, pos, its = [], [], [], []
    estimating = result.state_source == "estimator"
    estimator = resolve(TOPIC_ESTIMATOR_ODOMETRY)
    odometry = {base: [], estimator: []}       # the messages the estimate is checked with

    def on_base(rec, decode):
        m = decode(rec.data)
        p = m.pose.pose.position
        t.append(rec.log_time * 1e-9)
        pos.append((p.x, p.y, p.z))
        if estimating:
            odometry[base].append(m)

    def on_estimate(rec, decode):
        odometry[estimator].append(decode(rec.data))

    def on_solver(rec, decode):
        if rec.log_time == 0:
            return                # the initial state: no step yet
        for st in decode(rec.data).status:
            if st.name.endswith("solver"):
                its.extend(int(kv.value) for kv in st.values if kv.key == "iterations")

    def on_channel(topic, _type_name, make_decoder):
        if topic == js:
            return lambda rec: stamps.append(rec.log_time)
        handler = {base: on_base, solver: on_solver,
                   estimator: on_estimate if estimating else None}.get(topic)
        decode = make_decoder() if handler else None
        return None if decode is None else (lambda rec: handler(rec, decode))

    try:
        bag = stream_bag(path, on_channel)
    except BagError as e:
        raise DemoError(f"cannot read the recording: {e}") from None
    result.topic_counts = dict(bag.counts)
    result.messages = bag.total
    for topic in (js, base, solver):
        if topic not in bag.counts:
            raise DemoError(f"the recording {path} has no {topic}")
    _step_figures(result, np.array(stamps, dtype=np.int64))
    if len(t) == 0:
        raise DemoError(f"the recording {path} holds no base state")
    _trajectory_figures(result, np.array(t), np.array(pos))
    if its:
        result.solver_iterations_mean = float(np.mean(its))
        result.solver_iterations_max = int(np.max(its))
    if estimating and odometry[estimator]:
        result.estimate = error_series(odometry_arrays(odometry[base]),
                                       odometry_arrays(odometry[estimator]))
    return result


def print_summary(r: DemoResult, echo=print):
    echo(f"  stand {r.stand:g} s, then trot {r.trot:g} s at {r.speed:g} m/s "
         f"(trot requested at t = {r.t_trot:.3f} s; last step t = {r.t_end:.3f} s)")
    echo(f"  distance travelled   {r.distance:6.2f} m   (x {r.displacement[0]:+.2f}, "
         f"y {r.displacement[1]:+.2f}); while trotting {r.trot_distance:.2f} m")
    echo(f"  mean speed (trot)    {r.trot_speed:6.3f} m/s (commanded {r.speed:g})")
    echo("  falls                " + ("none" if not r.fell else "FELL") +
         f" (base height {r.min_height:.3f} .. {r.max_height:.3f} m; a fall is < "
         f"{r.fall_height:.3g} m)")
    echo(f"  real-time factor     {r.rtf:6.2f}   (lockstep, from /clock: {r.sim_elapsed:.2f} s "
         f"sim in {r.wall:.2f} s wall)")
    echo(f"  control cycles       {r.cycles_per_s:6.0f} /s " +
         (f"({r.cycles_per_s / r.bare_round_trips:.2f}x the bare rclpy round-trip rate "
          f"{r.bare_round_trips:.0f}/s measured before; "
          if r.bare_round_trips > 0 else "(") +
         ("both nodes in one process)" if r.in_process else "two processes)"))
    echo(f"  solver iterations    {r.solver_iterations_mean:6.1f} per control step on average "
         f"(max {r.solver_iterations_max})")
    echo(f"  messages             {r.messages} in the bag; /joint_states {r.joint_states} of "
         f"{r.steps_expected} steps, /joint_commands {r.joint_commands}")
    echo(f"  recording            {r.bag} ({r.bag_bytes / 1e6:.1f} MB); logs "
         + ", ".join(r.logs.values()))
    if r.estimate is not None:
        e = r.estimate
        echo(f"  state estimate       velocity error {e['velocity_rms']:.4f} m/s RMS, drift "
             f"{100 * e['drift']:.2f} % of {e['distance']:.2f} m walked, yaw drift "
             f"{e['yaw_drift_deg']:+.2f} deg (against the ground truth, {e['stamps']} stamps)")
    if r.html:
        echo(f"  3D replay            {r.html} ({r.html_frames} frames, "
             f"{r.html_bytes / 1e6:.1f} MB): open it in a browser")
    problems = r.problems()
    if problems:
        echo("  result: FAILED: " + "; ".join(problems))
    else:
        echo("  result: OK (" + (f">= {r.required_distance:.1f} m, " if r.trot >= MIN_TROT_CHECKED
                                 else "") + "no fall, whole run recorded)")
    return not problems
