"""``sim_node``: one StarlETH ``Simulator`` behind the ROS 2 interfaces users know from
mujoco_ros2_control / gz_ros2_control. A thin adapter: no physics in here.

    ros2 run starleth_sim sim_node --ros-args -p mode:=lockstep -p record:=run.mcap
    python -m starleth_sim.ros.sim_node --ros-args --params-file my_sim.yaml

Parameters and their defaults: msg_configs/sim_node.yaml (physics, physics_overrides, mode,
real_time_factor, lockstep_timeout, timeout_policy, record, record_compression,
record_max_duration, record_max_size, initial_state, start_paused, realtime_priority,
executor, warn_throttle_period, frames, publish_clock).

Names are relative (REP 135 style): ``--ros-args -r __ns:=/robot1`` (or the launch file's
``namespace``) moves every topic and service below, so several robots share a ROS domain;
/clock is global (``publish_clock:=false`` on all but one simulator of a domain). The node
is the source of /clock: its loops run on the wall clock whatever ``use_sim_time`` says,
and its stamps are always sim time.

Published; stamps are sim time t_k = k * 2.5 ms; one message per control step (a topic
nobody subscribes to is skipped unless recording):

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

Subscribed (reliable, depth 10):

  joint_group_effort_controller/commands  std_msgs/Float64MultiArray   12 torques, joint order
  joint_commands                          sensor_msgs/JointState       efforts by joint name
  ~/wrench, ~/wrench/persistent           geometry_msgs/WrenchStamped  frame_id = link name,
                                                                       world axes, at the link
                                                                       origin; zero clears
Services: ``~/reset`` (Trigger), ``~/pause`` (SetBool), ``~/step`` (Trigger, while paused).

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
period, so stamps stay strictly increasing and answers to the old state are stale).

Lockstep critical path (command in -> step -> state out): commands are taken as CDR bytes
and the common valid case is decoded without an rclpy message object (:mod:`.cdr`; the
rest is deserialised and validated in full), /joint_states goes out from a CDR template
before any other topic, and right after publishing the node prepares the torque-independent
part of the next step (``Simulator.prepare``) while the controller computes its answer.

The ROS-free part (command validation, lockstep bookkeeping, counters, stepping) is
:class:`SimService`; :class:`SimNode` is the rclpy plumbing.
"""
from __future__ import annotations

import array
import gc
import json
import math
import os
import signal
import sys
import time
from collections import deque
from dataclasses import dataclass, asdict, fields

import numpy as np
import yaml

from .. import Simulator, ConfigError, SimulationError
from ..physics.description import STARLETH_FEET as FEET
from ..physics.kinematics import quat_xyzw_to_rot
from .cdr import CommandDecoder, JointStateCdr
from .recording import register_msg_text
from starleth_interface.topics import (TOPIC_BASE_STATE, TOPIC_CLOCK, TOPIC_CONTACT_MARKERS,
                      TOPIC_EFFORT_COMMANDS, TOPIC_IMU, TOPIC_JOINT_COMMANDS,
                      TOPIC_JOINT_STATES, TOPIC_ROBOT_DESCRIPTION, TOPIC_SOLVER, TOPIC_TF,
                      TOPIC_TF_STATIC, TOPIC_WRENCH, TOPIC_WRENCH_PERSISTENT,
                      foot_wrench_topic)
from .tf import TF_MSG_TEXT, TF_TYPE, FrameTree, TfMessageCdr


# =========================================================================================
# settings
# =========================================================================================
@dataclass
class Settings:
    physics: str = "HmJ"
    physics_overrides: str = ""
    mode: str = "realtime"
    real_time_factor: float = 1.0
    lockstep_timeout: float = 1.0
    timeout_policy: str = "hold"
    record: str = ""
    record_compression: str = "none"
    record_max_duration: float = 0.0
    record_max_size: int = 0
    initial_state: str = "standing"
    start_paused: bool = False
    realtime_priority: int = 0
    executor: str = "events"
    warn_throttle_period: float = 2.0
    world_frame: str = "world"
    base_frame: str = "base"
    publish_clock: bool = True
    tf_rate: float = 50.0
    tf_frame_prefix: str = ""
    contact_markers_rate: float = 50.0
    contact_marker_scale: float = 0.002

    def validate(self) -> "Settings":
        def num(name, lo, lo_open):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ConfigError(f"parameter {name}: expected a finite number, got {v!r}")
            if v < lo or (lo_open and v == lo):
                raise ConfigError(f"parameter {name}: must be {'>' if lo_open else '>='} {lo}, "
                                  f"got {v}")
            setattr(self, name, float(v))

        for name in ("physics", "physics_overrides", "mode", "timeout_policy", "record",
                     "record_compression", "initial_state", "executor", "world_frame",
                     "base_frame", "tf_frame_prefix"):
            if not isinstance(getattr(self, name), str):
                raise ConfigError(f"parameter {name}: expected a string, got "
                                  f"{getattr(self, name)!r}")
        if self.mode not in ("realtime", "lockstep"):
            raise ConfigError(f"parameter mode: must be 'realtime' or 'lockstep', got "
                              f"{self.mode!r}")
        num("real_time_factor", 0.0, False)
        if self.mode == "realtime" and self.real_time_factor == 0.0:
            raise ConfigError("parameter real_time_factor: 0 (as fast as possible) is only legal "
                              "in lockstep mode; realtime mode needs a factor > 0")
        num("lockstep_timeout", 0.0, True)
        num("warn_throttle_period", 0.0, False)
        prio = self.realtime_priority
        if isinstance(prio, bool) or not isinstance(prio, int) or not 0 <= prio <= 99:
            raise ConfigError(f"parameter realtime_priority: expected an integer in 0..99, got "
                              f"{self.realtime_priority!r}")
        for name in ("start_paused", "publish_clock"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"parameter {name}: expected true or false, got "
                                  f"{getattr(self, name)!r}")
        num("record_max_duration", 0.0, False)
        num("tf_rate", 0.0, False)
        num("contact_markers_rate", 0.0, False)
        num("contact_marker_scale", 0.0, True)
        size = self.record_max_size
        if isinstance(size, bool) or not isinstance(size, int) or size < 0:
            raise ConfigError(f"parameter record_max_size: expected an integer >= 0 (bytes), "
                              f"got {size!r}")
        if self.timeout_policy not in ("hold", "zero"):
            raise ConfigError(f"parameter timeout_policy: must be 'hold' or 'zero', got "
                              f"{self.timeout_policy!r}")
        if self.record_compression not in ("none", "lz4", "zstd"):
            raise ConfigError(f"parameter record_compression: must be none, lz4 or zstd, got "
                              f"{self.record_compression!r}")
        if self.executor not in ("events", "single_threaded"):
            raise ConfigError(f"parameter executor: must be 'events' or 'single_threaded', got "
                              f"{self.executor!r}")
        return self

    def physics_override_dict(self) -> dict:
        if not self.physics_overrides.strip():
            return {}
        try:
            d = yaml.safe_load(self.physics_overrides)
        except yaml.YAMLError as e:
            raise ConfigError(f"parameter physics_overrides: not valid YAML: {e}") from None
        if not isinstance(d, dict):
            raise ConfigError("parameter physics_overrides: expected a mapping such as "
                              f"'{{mu: 0.0}}', got {self.physics_overrides!r}")
        return d


def default_settings_file() -> str:
    from ..physics.description import package_share_dir
    return os.path.join(package_share_dir(), "msg_configs", "sim_node.yaml")


def load_default_parameters(path: str | None = None) -> dict:
    """The ros__parameters of msg_configs/sim_node.yaml (node key 'sim_node' or '/**'),
    falling back to the Settings defaults for anything missing."""
    defaults = asdict(Settings())
    try:
        path = path or default_settings_file()
        with open(path) as f:
            data = yaml.safe_load(f) or {}
    except (OSError, FileNotFoundError):
        return defaults
    for key in ("sim_node", "/sim_node", "/**"):
        params = (data.get(key) or {}).get("ros__parameters") if isinstance(data, dict) else None
        if isinstance(params, dict):
            for k, v in params.items():
                if k in defaults:
                    defaults[k] = v
            break
    return defaults


# =========================================================================================
# initial state
# =========================================================================================
_PUBLIC_KEYS = ("base_position", "base_orientation", "joint_positions", "base_linear_velocity",
                "base_angular_velocity", "joint_velocities")
_STATE_KEYS = _PUBLIC_KEYS + ("q_minimal", "u_minimal", "q", "u", "coordinates")
# keys of a recorded initial_state.json that carry no state of their own
_STATE_INFO_KEYS = ("t", "note", "joint_names", "parameter")


def _read_state_spec(spec):
    if not isinstance(spec, str):
        return spec or {}
    s = spec.strip()
    if s in ("", "standing", "default"):
        return {}
    if s.endswith((".yaml", ".yml", ".json")) and not s.startswith("{"):
        try:
            with open(s) as f:
                return yaml.safe_load(f) or {}
        except OSError as e:
            raise ConfigError(f"parameter initial_state: cannot read {s}: {e}") from None
        except yaml.YAMLError as e:
            raise ConfigError(f"parameter initial_state: {s} is not valid YAML: {e}") from None
    try:
        return yaml.safe_load(s)
    except yaml.YAMLError as e:
        raise ConfigError(f"parameter initial_state: not valid YAML: {e}") from None


def public_state(sim: Simulator) -> dict:
    """The simulator's current state in convention-free public quantities."""
    b = sim.base_state()
    return {"base_position": np.array(b["position"], dtype=float),
            "base_orientation": np.array(b["orientation_xyzw"], dtype=float),
            "base_linear_velocity": np.array(b["linear_velocity"], dtype=float),
            "base_angular_velocity": np.array(b["angular_velocity"], dtype=float),
            "joint_positions": np.array(sim.joint_positions(), dtype=float),
            "joint_velocities": np.array(sim.joint_velocities(), dtype=float)}


def minimal_state(sim: Simulator, pub: dict):
    """(q, u) in minimal coordinates (the URDF's pin model on a free flyer: position,
    quaternion x y z w, joint angles; world linear velocity, body angular velocity, joint
    rates), as taken by ``Simulator.reset(q, u, minimal=True)``."""
    model = sim.description.model
    q = np.zeros(model.nq)
    u = np.zeros(model.nv)
    q[0:3] = pub["base_position"]
    q[3:7] = pub["base_orientation"]
    u[0:3] = pub["base_linear_velocity"]
    u[3:6] = pub["base_angular_velocity"]
    for i, name in enumerate(sim.joint_names):
        j = model.joints[model.getJointId(name)]
        q[j.idx_q] = pub["joint_positions"][i]
        u[j.idx_v] = pub["joint_velocities"][i]
    return q, u


def parse_initial_state(spec, sim: Simulator):
    """(q, u, description) from the `initial_state` parameter, q and u in the simulator's
    own coordinates (for ``sim.reset(q, u)``).

    spec: 'standing' / '' (``sim.default_state()`` at rest), a YAML mapping (string or
    dict) or the path of a YAML/JSON file with any of base_position, base_orientation
    (x y z w), joint_positions (list in joint order, or {name: angle}),
    base_linear_velocity (world), base_angular_velocity (base frame), joint_velocities;
    missing ones are those of the standing state. A recorded ``initial_state.json`` is
    accepted as is: its q/u are used when its coordinates match, else q_minimal/u_minimal.
    Uses the simulator (resets it)."""
    data = _read_state_spec(spec)
    if not isinstance(data, dict):
        raise ConfigError(f"parameter initial_state: expected 'standing', a mapping or a YAML "
                          f"file, got {spec!r}")
    if "joint_names" in data and list(data["joint_names"]) != list(sim.joint_names):
        raise ConfigError("parameter initial_state: joint_names differ from the simulator's")
    data = {k: v for k, v in data.items() if k not in _STATE_INFO_KEYS}
    unknown = set(data) - set(_STATE_KEYS)
    if unknown:
        raise ConfigError(f"parameter initial_state: unknown keys {sorted(unknown)} (known: "
                          f"{', '.join(_PUBLIC_KEYS)})")
    nj = sim.n_joints

    def vec(key, n):
        v = data[key]
        if isinstance(v, dict) and key.startswith("joint_"):
            unknown_j = set(v) - set(sim.joint_names)
            if unknown_j:
                raise ConfigError(f"parameter initial_state: {key}: unknown joints "
                                  f"{sorted(unknown_j)}")
            return v
        try:
            a = np.asarray(v, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            raise ConfigError(f"parameter initial_state: {key}: expected {n} numbers, got {v!r}") \
                from None
        if a.shape != (n,) or not np.all(np.isfinite(a)):
            raise ConfigError(f"parameter initial_state: {key}: expected {n} finite numbers, "
                              f"got {v!r}")
        return a

    def reset_checked(q, u, minimal=False):
        try:
            sim.reset(q=q, u=u, minimal=minimal)
        except ValueError as e:
            raise ConfigError(f"parameter initial_state: {e}") from None
        return sim.q, sim.u

    if "q" in data and data.get("coordinates", sim.config.coordinates) == sim.config.coordinates:
        q, u = reset_checked(vec("q", sim.q.shape[0]),
                             vec("u", sim.u.shape[0]) if "u" in data else None)
        return q, u, {"spec": {"q": q.tolist(), "u": u.tolist(),
                               "coordinates": sim.config.coordinates}}
    if "q_minimal" in data:
        model = sim.description.model
        q, u = reset_checked(vec("q_minimal", model.nq),
                             vec("u_minimal", model.nv) if "u_minimal" in data else None,
                             minimal=True)
        return q, u, {"spec": {"q_minimal": data["q_minimal"],
                               "u_minimal": data.get("u_minimal")}}
    public = {k: v for k, v in data.items() if k in _PUBLIC_KEYS}
    sim.reset()
    if not public:
        return sim.q, sim.u, {"spec": "standing"}
    pub = public_state(sim)
    for key in ("base_position", "base_linear_velocity", "base_angular_velocity"):
        if key in public:
            pub[key] = vec(key, 3)
    if "base_orientation" in public:
        quat = vec("base_orientation", 4)
        if np.linalg.norm(quat) < 1e-9:
            raise ConfigError("parameter initial_state: base_orientation must not be zero")
        pub["base_orientation"] = quat / np.linalg.norm(quat)
    for key in ("joint_positions", "joint_velocities"):
        if key in public:
            v = vec(key, nj)
            if isinstance(v, dict):
                for name, val in v.items():
                    try:
                        x = float(val)
                    except (TypeError, ValueError):
                        x = float("nan")
                    if not math.isfinite(x):
                        raise ConfigError(f"parameter initial_state: {key}.{name}: expected a "
                                          f"finite number, got {val!r}")
                    pub[key][sim.joint_names.index(name)] = x
            else:
                pub[key] = v
    q, u = reset_checked(*minimal_state(sim, pub), minimal=True)
    return q, u, {"spec": {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                           for k, v in public.items()}}


def initial_state_record(sim: Simulator, q0, u0, spec=None) -> dict:
    """The initial state as stored in recordings (and accepted back by the initial_state
    parameter): the simulator's q/u, the minimal-coordinate q/u and the public quantities.
    Uses the simulator (resets it to q0, u0)."""
    sim.reset(q=q0, u=u0)
    pub = public_state(sim)
    qm, um = minimal_state(sim, pub)
    rec = {"coordinates": sim.config.coordinates,
           "q": [float(x) for x in q0], "u": [float(x) for x in u0], "t": 0.0,
           "q_minimal": qm.tolist(), "u_minimal": um.tolist(),
           "note": "q, u: Simulator.reset(q, u) in these coordinates; q_minimal, u_minimal: "
                   "Simulator.reset(q, u, minimal=True) (pin free-flyer order: position, "
                   "quaternion x y z w, joint angles; world linear velocity, body angular "
                   "velocity, joint rates)",
           "joint_names": list(sim.joint_names),
           "parameter": spec if spec is not None else "standing"}
    rec.update({k: v.tolist() for k, v in pub.items()})
    return rec


# =========================================================================================
# ROS-free core
# =========================================================================================
class ThrottledWarnings:
    """At most one warning per `period` seconds per kind of problem; the next one says how
    many were suppressed."""

    def __init__(self, log, period: float = 2.0, clock=time.monotonic):
        self._log, self.period, self._clock = log, period, clock
        self._last: dict = {}
        self._suppressed: dict = {}
        self.counts: dict = {}

    def warn(self, key: str, message: str) -> bool:
        self.counts[key] = self.counts.get(key, 0) + 1
        now = self._clock()
        last = self._last.get(key)
        if last is not None and now - last < self.period:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return False
        n = self._suppressed.pop(key, 0)
        self._last[key] = now
        if n:
            message += f" ({n} more like this suppressed in the last {now - last:.1f} s)"
        if self._log is not None:
            self._log(message)
        return True


class SimService:
    """Command validation, lockstep bookkeeping and stepping, without any ROS.

    Time: step k has stamp ``k * period_ns`` [ns] (integer, so equal stamps compare exact).
    ``command`` is the last valid torque command (joint order), applied with zero-order hold.
    Every ``submit_*`` returns ``(accepted, reason)`` and never raises on bad input."""

    COUNTERS = ("commands_received", "commands_accepted", "commands_rejected", "late_commands",
                "stale_commands", "lockstep_timeouts", "wrenches_accepted", "wrenches_rejected",
                "simulation_errors", "resets", "steps")

    def __init__(self, sim: Simulator, settings: Settings | None = None, q0=None, u0=None,
                 warn=None, error=None):
        self.sim = sim
        self.settings = (settings or Settings()).validate()
        self.lockstep = self.settings.mode == "lockstep"
        self.q0 = sim.q if q0 is None else np.array(q0, dtype=float)
        self.u0 = sim.u if u0 is None else np.array(u0, dtype=float)
        self.period_ns = int(round(sim.control_period * 1e9))
        self.joint_names = tuple(sim.joint_names)
        self.joint_index = {n: i for i, n in enumerate(self.joint_names)}
        self._joint_name_list = list(self.joint_names)
        self.links = frozenset(sim.coords.link_names())
        self.n = len(self.joint_names)
        self.warnings = ThrottledWarnings(warn, self.settings.warn_throttle_period)
        self.errors = ThrottledWarnings(error or warn, self.settings.warn_throttle_period)
        self.counters = dict.fromkeys(self.COUNTERS, 0)
        self.command = np.zeros(self.n)
        self.k = 0
        self.paused = self.settings.start_paused
        self.started = not self.lockstep     # lockstep: set by the first answer
        self.answered = False                # lockstep: the current state has its command
        self.last_step_timed_out = False
        self.failed = False                  # paused after the physics failed twice
        self.state_version = 0               # bumped whenever a new state exists
        self._timed_out_stamps = deque(maxlen=256)
        # warm up (numba dispatch, first solve) so that the first real step is not slow;
        # reset() then restores the initial state and clears the solver's contact memory
        sim.reset(q=self.q0, u=self.u0, t=0.0)
        try:
            sim.step(np.zeros(self.n))
        except (SimulationError, ValueError):
            pass
        sim.reset(q=self.q0, u=self.u0, t=0.0)

    # -- time ------------------------------------------------------------------------------
    @property
    def stamp_ns(self) -> int:
        return self.k * self.period_ns

    @property
    def control_period(self) -> float:
        return self.sim.control_period

    # -- commands --------------------------------------------------------------------------
    def _reject(self, key, message):
        self.counters["commands_rejected"] += 1
        self.warnings.warn(key, message)
        return False, message

    def _accept(self, tau):
        self.command = tau
        self.counters["commands_accepted"] += 1
        if self.lockstep:
            self.answered = True
            self.started = True
        return True, "ok"

    def _check_values(self, values, what):
        try:
            a = np.array(values, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            return None, f"{what}: values are not numbers"
        return a, None

    def submit_effort_array(self, data):
        """A Float64MultiArray's data: n torques in joint order. In lockstep it answers the
        latest published state (the message has no stamp)."""
        self.counters["commands_received"] += 1
        a, err = self._check_values(data, "effort command")
        if err:
            return self._reject("effort_type", f"rejected effort command: {err}")
        if a.shape[0] != self.n:
            return self._reject("effort_length",
                                f"rejected effort command on {TOPIC_EFFORT_COMMANDS}: "
                                f"{a.shape[0]} values, expected {self.n} (joint order "
                                f"{', '.join(self.joint_names)}); keeping the last valid command")
        bad = ~np.isfinite(a)
        if bad.any():
            names = [self.joint_names[i] for i in np.flatnonzero(bad)]
            return self._reject("effort_nonfinite",
                                f"rejected effort command on {TOPIC_EFFORT_COMMANDS}: non-finite "
                                f"torque for {', '.join(names)}; keeping the last valid command")
        if self.lockstep and self.answered:
            self.counters["stale_commands"] += 1
            self.warnings.warn("stale", "dropped an extra effort command: the current state "
                               "was already answered")
            return False, "state already answered"
        return self._accept(a)

    def submit_joint_command(self, names, efforts, stamp_ns=None):
        """A JointState command: efforts by joint name. All names must be known and unique;
        joints not named keep their last command. Empty names with n efforts = joint order.
        In lockstep the stamp must equal the stamp of the state being answered."""
        self.counters["commands_received"] += 1
        names = list(names)
        a, err = self._check_values(efforts, "joint command")
        if err:
            return self._reject("joint_type", f"rejected joint command: {err}")
        if names == self._joint_name_list and a.shape[0] == self.n and np.isfinite(a).all() \
                and (not self.lockstep or self._stamp_ok(stamp_ns)):
            return self._accept(a)   # fast path: every joint in joint order, valid
        if not names:
            if a.shape[0] != self.n:
                return self._reject("joint_length",
                                    f"rejected joint command on {TOPIC_JOINT_COMMANDS}: no joint "
                                    f"names and {a.shape[0]} efforts (give names, or {self.n} "
                                    "efforts in joint order)")
            names = list(self.joint_names)
        if a.shape[0] != len(names):
            return self._reject("joint_length",
                                f"rejected joint command on {TOPIC_JOINT_COMMANDS}: {len(names)} "
                                f"names but {a.shape[0]} efforts (this simulator takes effort "
                                "commands only)")
        unknown = [n for n in names if n not in self.joint_index]
        if unknown:
            return self._reject("unknown_joint",
                                f"rejected joint command on {TOPIC_JOINT_COMMANDS}: unknown joint "
                                f"name(s) {', '.join(map(repr, unknown))} (joints: "
                                f"{', '.join(self.joint_names)})")
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            return self._reject("duplicate_joint",
                                f"rejected joint command on {TOPIC_JOINT_COMMANDS}: duplicate "
                                f"joint name(s) {', '.join(dup)}")
        bad = ~np.isfinite(a)
        if bad.any():
            return self._reject("joint_nonfinite",
                                f"rejected joint command on {TOPIC_JOINT_COMMANDS}: non-finite "
                                f"effort for {', '.join(names[i] for i in np.flatnonzero(bad))}; "
                                "keeping the last valid command")
        if self.lockstep and not self._stamp_ok(stamp_ns):
            return self._stale(stamp_ns)
        tau = self.command.copy()
        for n, v in zip(names, a):
            tau[self.joint_index[n]] = v
        return self._accept(tau)

    def submit_ordered_joint_command(self, efforts, stamp_ns):
        """submit_joint_command for a command already known to name every joint in joint
        order with n finite efforts (decoded by cdr.CommandDecoder): only the lockstep
        stamp is left to check."""
        self.counters["commands_received"] += 1
        if self.lockstep and not self._stamp_ok(stamp_ns):
            return self._stale(stamp_ns)
        return self._accept(efforts)

    def _stamp_ok(self, stamp_ns):
        return not self.answered and (stamp_ns is None or int(stamp_ns) == self.stamp_ns)

    def _stale(self, stamp_ns):
        """Lockstep: count and drop a JointState command that does not answer the current
        state: 'late' if it answers a state stepped on the timeout policy, else 'stale'."""
        stamp = self.stamp_ns if stamp_ns is None else int(stamp_ns)
        if stamp in self._timed_out_stamps:
            self.counters["late_commands"] += 1
            self.warnings.warn("late", f"late command for t={stamp * 1e-9:.4f} s: that state "
                               "was already stepped on the timeout policy (now waiting for "
                               f"t={self.stamp_ns * 1e-9:.4f} s)")
            return False, "late"
        self.counters["stale_commands"] += 1
        what = "the state was already answered" if stamp == self.stamp_ns else \
            f"stamp t={stamp * 1e-9:.4f} s does not match"
        self.warnings.warn("stale", f"dropped a stale command on {TOPIC_JOINT_COMMANDS}: {what}; "
                           "lockstep expects header.stamp = the stamp of the /joint_states it "
                           f"answers (t={self.stamp_ns * 1e-9:.4f} s)")
        return False, "stale"

    def submit_wrench(self, link, force, torque, persistent=False):
        """A push on `link` (world axes, at the link origin): one control period, or until
        replaced/cleared (zero wrench) when persistent."""
        topic = TOPIC_WRENCH_PERSISTENT if persistent else TOPIC_WRENCH
        if link not in self.links:
            self.counters["wrenches_rejected"] += 1
            msg = (f"rejected wrench on {topic}: unknown link {link!r} in header.frame_id "
                   f"(links: {', '.join(sorted(self.links))})")
            self.warnings.warn("unknown_link", msg)
            return False, msg
        f = np.array(force, dtype=float).reshape(-1)
        m = np.array(torque, dtype=float).reshape(-1)
        if f.shape != (3,) or m.shape != (3,) or not (np.all(np.isfinite(f)) and
                                                       np.all(np.isfinite(m))):
            self.counters["wrenches_rejected"] += 1
            msg = f"rejected wrench on {topic} for {link!r}: force and torque must be finite"
            self.warnings.warn("bad_wrench", msg)
            return False, msg
        try:
            if persistent:
                self.sim.set_persistent_wrench(link, f, m)
            else:
                self.sim.apply_wrench(link, f, m)
        except ValueError as e:
            self.counters["wrenches_rejected"] += 1
            self.warnings.warn("bad_wrench", f"rejected wrench on {topic}: {e}")
            return False, str(e)
        self.counters["wrenches_accepted"] += 1
        return True, "ok"

    # -- stepping --------------------------------------------------------------------------
    def on_timeout(self):
        """Lockstep: no answer for the current state within lockstep_timeout."""
        self.counters["lockstep_timeouts"] += 1
        self._timed_out_stamps.append(self.stamp_ns)
        pol = self.settings.timeout_policy
        self.warnings.warn("timeout", f"lockstep: no command for t={self.stamp_ns * 1e-9:.4f} s "
                           f"within {self.settings.lockstep_timeout:g} s; stepping with "
                           f"{'the last command held' if pol == 'hold' else 'zero torques'} "
                           f"({self.counters['lockstep_timeouts']} timeouts so far)")
        if pol == "zero":
            self.command = np.zeros(self.n)

    def step(self, timed_out: bool = False):
        """One control period with the current command; returns the Diagnostics (or None
        when the physics failed twice and the simulation was paused)."""
        if timed_out:
            self.on_timeout()
        self.last_step_timed_out = timed_out
        tau = self.command
        try:
            d = self.sim.step(tau)
        except (SimulationError, ValueError) as e:
            self.counters["simulation_errors"] += 1
            self.warnings.warn("simulation_error", f"physics step failed at t="
                               f"{self.sim.t:.4f} s ({e}); retrying with zero torques")
            try:
                d = self.sim.step(np.zeros(self.n))
            except (SimulationError, ValueError) as e2:
                self.paused = self.failed = True
                self.errors.warn("simulation_paused", f"physics step failed twice at t="
                                 f"{self.sim.t:.4f} s ({e2}); simulation paused, call ~/reset")
                return None
        self.k += 1
        self.counters["steps"] += 1
        self.answered = False
        self.state_version += 1
        return d

    def reset(self):
        """Back to the initial state, wrenches cleared, zero command; sim time advances by one
        control period (stamps stay strictly increasing). A pause caused by a physics
        failure ends; a pause asked for with ~/pause stays."""
        if self.failed:
            self.failed = self.paused = False
        self.k += 1
        self.sim.clear_wrenches()
        self.sim.reset(q=self.q0, u=self.u0, t=self.k * self.control_period)
        self.command = np.zeros(self.n)
        self.answered = False
        self.counters["resets"] += 1
        self.state_version += 1

    def summary(self) -> dict:
        d = dict(self.counters)
        d["sim_time"] = self.stamp_ns * 1e-9
        d["warnings_by_kind"] = dict(self.warnings.counts)
        return d


class PeriodStats:
    """Wall-clock tick intervals of the realtime loop: |interval - nominal| in a histogram
    of 1 us bins (O(1) per tick, percentiles in microseconds, cheap enough to run in the
    loop), plus count, mean and maximum."""

    BIN = 1e-6
    NBINS = 20000          # up to 20 ms; larger errors go to the last bin (max is exact)

    def __init__(self, nominal: float):
        self.nominal = nominal
        self.hist = np.zeros(self.NBINS, dtype=np.int64)
        self.n = 0
        self.total = 0.0
        self.max_err = 0.0
        self.last = None
        self.overruns = 0

    def tick(self, t: float):
        last = self.last
        self.last = t
        if last is None:
            return
        iv = t - last
        err = abs(iv - self.nominal)
        i = int(err / self.BIN)
        self.hist[i if i < self.NBINS else self.NBINS - 1] += 1
        self.n += 1
        self.total += iv
        if err > self.max_err:
            self.max_err = err

    def restart(self):
        self.last = None

    def percentile_ms(self, p: float) -> float:
        c = np.cumsum(self.hist)
        i = int(np.searchsorted(c, p / 100.0 * c[-1]))
        return (i + 1) * self.BIN * 1e3          # upper edge of the bin

    def summary(self) -> dict:
        if self.n == 0:
            return {"ticks": 0}
        return {"ticks": self.n, "period_mean_ms": self.total / self.n * 1e3,
                "period_error_p50_ms": self.percentile_ms(50),
                "period_error_p99_ms": self.percentile_ms(99),
                "period_error_max_ms": self.max_err * 1e3, "overruns": self.overruns}


# =========================================================================================
# math helpers
# =========================================================================================
def quat_to_matrix(qx, qy, qz, qw):
    """Rotation matrix of the unit quaternion (x, y, z, w) (kinematics.quat_xyzw_to_rot)."""
    R = np.empty((3, 3))
    quat_xyzw_to_rot(float(qx), float(qy), float(qz), float(qw), R)
    return R


def _dbl(a) -> array.array:
    return array.array("d", np.ascontiguousarray(a, dtype=float).tobytes())


# =========================================================================================
# rclpy node
# =========================================================================================
def _import_ros():
    global rclpy, Node, QoSProfile, ReliabilityPolicy, DurabilityPolicy, HistoryPolicy
    global ParameterDescriptor, serialize_message, deserialize_message
    global Clock, JointState, Imu, WrenchStamped, Odometry, DiagnosticArray, DiagnosticStatus
    global KeyValue, Float64MultiArray, String, Trigger, SetBool
    import rclpy  # noqa: F401
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy, DurabilityPolicy, HistoryPolicy
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.serialization import serialize_message, deserialize_message
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import JointState, Imu
    from geometry_msgs.msg import WrenchStamped
    from nav_msgs.msg import Odometry
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from std_msgs.msg import Float64MultiArray, String
    from std_srvs.srv import Trigger, SetBool
    return Node


def make_executor(kind: str, context):
    """rclpy's EventsExecutor (C++, much cheaper spin_once) when asked for and available,
    else the SingleThreadedExecutor."""
    import rclpy.executors
    if kind == "events":
        try:
            from rclpy.experimental import EventsExecutor
            return EventsExecutor(context=context), "events"
        except Exception:  # pragma: no cover - rclpy without the EventsExecutor
            pass
    return rclpy.executors.SingleThreadedExecutor(context=context), "single_threaded"


class SimNode:
    """The rclpy side: parameters, publishers, subscriptions, services, recording, and the
    lockstep / realtime loops. Created by :func:`main`; usable in-process (tests, bench)."""

    SPIN_MARGIN = 0.0006  # realtime: stop waiting in the executor this long before a tick
    MAX_CATCH_UP = 0.1    # realtime: at most this far behind the wall clock, then skip ahead

    def __init__(self, context=None, parameter_overrides=None, node_name="sim_node",
                 settings_file=None):
        _import_ros()
        from rclpy.parameter import Parameter
        defaults = load_default_parameters(settings_file)
        self.node = Node(node_name, context=context,
                         parameter_overrides=[Parameter(k, value=v) for k, v in
                                              (parameter_overrides or {}).items()])
        node = self.node
        self.log = node.get_logger()
        values = {}
        for name, default in defaults.items():
            desc = ParameterDescriptor(dynamic_typing=True, read_only=True)
            values[name] = node.declare_parameter(name, default, desc).value
        for name in ("real_time_factor", "lockstep_timeout", "warn_throttle_period",
                     "record_max_duration", "tf_rate", "contact_markers_rate",
                     "contact_marker_scale"):
            if isinstance(values[name], int) and not isinstance(values[name], bool):
                values[name] = float(values[name])
        for name in ("physics", "physics_overrides", "record", "initial_state",
                     "tf_frame_prefix"):
            if values[name] is None:
                values[name] = ""
        self.settings = Settings(**{k: v for k, v in values.items()
                                    if k in {f.name for f in fields(Settings)}}).validate()
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
        self._step_on_answer = False   # set by run() in lockstep mode without pacing
        self._n_state_subs = 0          # subscribers of the state topics at the last look
        self._counts_k = -10 ** 9
        self._counts = {}
        self.period_stats = PeriodStats(self.sim.control_period / max(s.real_time_factor, 1e-12))
        self._gravity = self._model_gravity()
        self._v_prev = None    # (step, world linear velocity) for the IMU
        self._acc = None       # (step, acceleration) of the last IMU message
        self._setup_messages()
        self._setup_interfaces()
        self._setup_visualisation()
        self.recorder = None
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
        self.solver_keys = ("iterations", "max_iterations_step", "converged", "status",
                            "residual", "active_contacts", "retried", "step_time",
                            "physics_steps", "nonconverged_steps", "loaded_contacts_opened",
                            "loaded_contacts_opened_total", "projections",
                            "projection_iterations")
        self.iface_keys = ("mode", "real_time_factor", "sim_time", "step", "paused",
                           "waiting_for_first_command", *SimService.COUNTERS,
                           "period_error_p50_ms", "period_error_p99_ms", "period_error_max_ms",
                           "overruns", "recorded_messages")
        self.diag_msg = DiagnosticArray()
        self.solver_status = DiagnosticStatus(name="starleth_sim: solver",
                                              hardware_id="starleth_sim")
        self.solver_status.values = [KeyValue(key=k, value="") for k in self.solver_keys]
        self.iface_status = DiagnosticStatus(name="starleth_sim: interface",
                                             hardware_id="starleth_sim")
        self.iface_status.values = [KeyValue(key=k, value="") for k in self.iface_keys]
        self._diag_solver_only = [self.solver_status]
        self._diag_both = [self.solver_status, self.iface_status]
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
        self.srv_reset = node.create_service(Trigger, "~/reset", self._srv_reset)
        self.srv_pause = node.create_service(SetBool, "~/pause", self._srv_pause)
        self.srv_step = node.create_service(Trigger, "~/step", self._srv_step)

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
        self.marker_msg = None
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

    def _fill_contact_markers(self, sec, nsec):
        """Spheres at the contact points coloured by state; arrows from each closed contact
        point along its force, contact_marker_scale [m/N] long."""
        sim, Marker = self.sim, self._Marker
        n = len(sim.contact_names)
        scale = self.settings.contact_marker_scale
        for c, sphere, arrow in zip(sim.contacts, self.marker_msg.markers[:n],
                                    self.marker_msg.markers[n:]):
            p = c.position
            for m in (sphere, arrow):
                m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
            sphere.pose.position.x, sphere.pose.position.y, sphere.pose.position.z = (
                float(p[0]), float(p[1]), float(p[2]))
            col = sphere.color
            col.r, col.g, col.b, col.a = self.MARKER_COLOURS[c.state]
            if c.state == "open":
                arrow.action = Marker.DELETE
                continue
            arrow.action = Marker.ADD
            a, b = arrow.points
            a.x, a.y, a.z = float(p[0]), float(p[1]), float(p[2])
            f = c.force
            b.x, b.y, b.z = (float(p[0] + scale * f[0]), float(p[1] + scale * f[1]),
                             float(p[2] + scale * f[2]))

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
            q, _ = minimal_state(self.sim, public_state(self.sim))
            poses = self.frames.transforms(q, self.frames.dynamic)
            self._emit_tf("tf", self._tf_cdr.build(sec, nsec, poses), svc.stamp_ns)
        if self._markers_every and k % self._markers_every == 0 and \
                self._wanted("contact_markers", True):
            self._fill_contact_markers(sec, nsec)
            self._emit("contact_markers", self.marker_msg, True)

    def _publish_static_transforms(self):
        """/tf_static once (transient local): the fixed joints."""
        if not self._tf_every or not self.frames.static:
            return
        q, _ = minimal_state(self.sim, public_state(self.sim))
        poses = self.frames.transforms(q, self.frames.static)   # do not depend on q
        self._emit_tf("tf_static", self._tf_static_cdr.build(0, 0, poses),
                      self.service.stamp_ns)

    def _open_recorder(self, path):
        from .recording import McapRecorder, SplitRecorder
        s, sim = self.settings, self.sim
        common = dict(compression=s.record_compression,
                      custom_data={"generator": "starleth_sim sim_node"})
        if s.record_max_duration > 0 or s.record_max_size > 0:
            # a rosbag2 bag directory of numbered files, each complete on its own
            self.recorder = rec = SplitRecorder(
                path, max_duration_ns=int(round(s.record_max_duration * 1e9)),
                max_size=s.record_max_size, **common)
        else:
            self.recorder = rec = McapRecorder(path, **common)
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
            "urdf_attachment": "starleth.urdf"})
        rec.add_attachment("starleth.urdf", "application/xml", sim.description.urdf_xml)
        rec.add_attachment("physics_config.yaml", "application/yaml", cfg_yaml)
        rec.add_attachment("initial_state.json", "application/json", json.dumps(init, indent=1))
        rec.add_attachment("sim_node_parameters.yaml", "application/yaml",
                           yaml.safe_dump({"/**": {"ros__parameters": params}}, sort_keys=False))

    def _publish_robot_description(self):
        msg = String(data=self.sim.description.urdf_xml)
        self._emit("robot_description", msg, True)

    # -- publishing ------------------------------------------------------------------------
    def _log_warning(self, message):
        self.log.warning(message)

    def _log_error(self, message):
        self.log.error(message)

    def _emit(self, key, msg, record):
        p, topic, _, _ = self.pubs[key]
        rec = self.recorder
        if record and rec is not None and not rec.closed:
            data = serialize_message(msg)
            p.publish(data)
            rec.write(topic, data, self.service.stamp_ns)
        else:
            p.publish(msg)

    SUBSCRIBER_REFRESH = 10   # steps between two looks at the subscriber counts

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
        svc, sim = self.service, self.sim
        sec, nsec = divmod(svc.stamp_ns, 1_000_000_000)
        wanted = self._wanted
        # /joint_states first: it is what a lockstep controller waits for
        if svc.counters["steps"] or svc.counters["resets"]:
            send = wanted("joint_states", record)
        else:   # state 0: the exact count
            send = (self.pubs["joint_states"][0].get_subscription_count() > 0
                    or (record and self.recorder is not None))
        if send:
            cdr = self._js_cdr
            if cdr is not None:    # CDR bytes from a template: no per-step Python->C copy
                data = cdr.build(sec, nsec, sim.joint_positions(), sim.joint_velocities(),
                                 sim.applied_torque)
                self.pubs["joint_states"][0].publish(data)
                rec = self.recorder
                if record and rec is not None and not rec.closed:
                    rec.write(self.pubs["joint_states"][1], data, svc.stamp_ns)
            else:
                js = self.js_msg
                js.header.stamp.sec, js.header.stamp.nanosec = sec, nsec
                js.position = _dbl(sim.joint_positions())
                js.velocity = _dbl(sim.joint_velocities())
                js.effort = _dbl(sim.applied_torque)
                self._emit("joint_states", js, record)
        if "clock" in self.pubs and wanted("clock", record):
            c = self.clock_msg.clock
            c.sec, c.nanosec = sec, nsec
            self._emit("clock", self.clock_msg, record)
        feet = [f for f in FEET if wanted(f, record)]
        if feet:
            for c in sim.contacts[:len(FEET)]:
                if c.name not in feet:
                    continue
                m = self.wrench_msgs[c.name]
                m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
                f = m.wrench.force
                f.x, f.y, f.z = float(c.force[0]), float(c.force[1]), float(c.force[2])
                self._emit(c.name, m, record)
        want_odom, want_imu = wanted("base_state", record), wanted("imu", record)
        if want_odom or want_imu:
            b = sim.base_state()
            p, quat, v, w = (b["position"], b["orientation_xyzw"], b["linear_velocity"],
                             b["angular_velocity"])
            R = quat_to_matrix(*quat)
            quat = [float(x) for x in quat]
            w = [float(x) for x in w]
        if want_odom:
            v_body = R.T @ v
            o = self.odom_msg
            o.header.stamp.sec, o.header.stamp.nanosec = sec, nsec
            pp, po = o.pose.pose.position, o.pose.pose.orientation
            pp.x, pp.y, pp.z = float(p[0]), float(p[1]), float(p[2])
            po.x, po.y, po.z, po.w = quat
            tl, ta = o.twist.twist.linear, o.twist.twist.angular
            tl.x, tl.y, tl.z = float(v_body[0]), float(v_body[1]), float(v_body[2])
            ta.x, ta.y, ta.z = w
            self._emit("base_state", o, record)
        if want_imu:
            # IMU at the base origin: proper acceleration R^T (dv/dt - g), body rates; dv/dt
            # by the difference with the previous step's velocity (zero on the first state
            # and the first message after a reset or after nobody listened)
            k = svc.k
            if self._v_prev is not None and self._v_prev[0] == k - 1:
                acc = (v - self._v_prev[1]) / sim.control_period
                self._acc = (k, acc)
            elif self._acc is not None and self._acc[0] == k:    # re-sent state
                acc = self._acc[1]
            else:
                acc = np.zeros(3)
            if self._v_prev is None or self._v_prev[0] != k:
                self._v_prev = (k, np.array(v, dtype=float))
            a_proper = R.T @ (acc - self._gravity)
            imu = self.imu_msg
            imu.header.stamp.sec, imu.header.stamp.nanosec = sec, nsec
            io_ = imu.orientation
            io_.x, io_.y, io_.z, io_.w = quat
            iw, ia = imu.angular_velocity, imu.linear_acceleration
            iw.x, iw.y, iw.z = w
            ia.x, ia.y, ia.z = float(a_proper[0]), float(a_proper[1]), float(a_proper[2])
            self._emit("imu", imu, record)
        if wanted("solver", record):
            self._fill_diagnostics(sec, nsec)
            self._emit("solver", self.diag_msg, record)
        if record:
            self._prepare_next_step()
            self._publish_visualisation()
        # subscriber counts for the next state, taken now that this one is out (off the
        # lockstep critical path): /joint_states every step, the others every
        # SUBSCRIBER_REFRESH steps
        if not (0 <= svc.k - self._counts_k < self.SUBSCRIBER_REFRESH):
            self._refresh_counts()
        else:
            self._counts["joint_states"] = \
                self.pubs["joint_states"][0].get_subscription_count()

    def _prepare_next_step(self):
        """The controller now works on its answer to the state just published: do the
        torque-independent part of the next step meanwhile (Simulator.prepare), which takes
        it off the lockstep critical path (command in -> step -> state out). The result of
        the step is the same with or without it."""
        try:
            self.sim.prepare()
        except Exception as e:   # pragma: no cover - the step redoes it and reports
            self.service.warnings.warn("prepare", f"preparing the next step failed: {e}")

    INTERFACE_STATUS_EVERY = 40   # steps (10 Hz at 400 Hz); also on every lockstep timeout

    def _fill_diagnostics(self, sec, nsec):
        svc = self.service
        d = self.sim.diagnostics
        self.diag_msg.header.stamp.sec, self.diag_msg.header.stamp.nanosec = sec, nsec
        st = self.solver_status
        st.level = DiagnosticStatus.OK if d.converged else DiagnosticStatus.WARN
        st.message = d.status
        vals = (d.iterations, d.max_iterations_step, d.converged, d.status, repr(d.residual),
                d.active_contacts, d.retried, repr(d.step_time), d.physics_steps,
                d.nonconverged_steps, d.loaded_contacts_opened, d.loaded_contacts_opened_total,
                d.projections, d.projection_iterations)
        for kv, v in zip(st.values, vals):
            kv.value = str(v)
        if not (svc.k % self.INTERFACE_STATUS_EVERY == 0 or svc.last_step_timed_out
                or svc.paused):
            self.diag_msg.status = self._diag_solver_only
            return
        self.diag_msg.status = self._diag_both
        it = self.iface_status
        it.level = DiagnosticStatus.WARN if svc.last_step_timed_out else DiagnosticStatus.OK
        it.message = ("lockstep timeout" if svc.last_step_timed_out else
                      "paused" if svc.paused else "running")
        ps = self._period_summary
        c = svc.counters
        vals = (self.settings.mode, self.settings.real_time_factor, svc.stamp_ns * 1e-9, svc.k,
                svc.paused, not svc.started, *(c[k] for k in SimService.COUNTERS),
                ps.get("period_error_p50_ms", ""), ps.get("period_error_p99_ms", ""),
                ps.get("period_error_max_ms", ""), self.period_stats.overruns,
                self.recorder.message_count if self.recorder is not None else 0)
        for kv, v in zip(it.values, vals):
            kv.value = str(v)

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
        self._v_prev = self._acc = None
        self.publish_state()
        self.log.info(f"reset to the initial state at t={self.service.stamp_ns * 1e-9:.4f} s")
        response.success = True
        response.message = f"reset; sim time {self.service.stamp_ns * 1e-9:.4f} s"
        return response

    def _srv_pause(self, request, response):
        svc = self.service
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
            response.message = "the physics step failed; simulation paused, call ~/reset"
            return response
        self.publish_state()
        response.success = True
        response.message = f"stepped to sim time {svc.stamp_ns * 1e-9:.4f} s"
        return response

    # -- loops -----------------------------------------------------------------------------
    def request_stop(self, *_):
        self._stop = True

    def _running(self):
        return not self._stop and self.context.ok()

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
    STATE_TOPICS = ("joint_states", "base_state", *FEET)

    def _state_subscriber_count(self) -> int:
        return sum(self.pubs[k][0].get_subscription_count() for k in self.STATE_TOPICS)

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
        if self.recorder is not None:
            d["recorded_messages"] = self.recorder.message_count
        return d

    def close(self):
        """Finalise the recording (idempotent) and log a summary."""
        summary = self.summary()
        rec = self.recorder
        if rec is not None and not rec.closed:
            rec.add_metadata("starleth_sim_summary", {k: json.dumps(v) for k, v in summary.items()})
            rec.close()
            self.log.info(f"recording finalised: {rec.path} ({rec.message_count} messages)")
        self.log.info("summary: " + json.dumps(summary))
        return summary

    def destroy(self):
        self.close()
        self.node.destroy_node()


def main(args=None):
    """Console script ``sim_node``. SIGINT/SIGTERM stop the loop and finalise the recording
    (exit 0); a bad parameter exits with 2 before any physics is set up."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    argv = sys.argv if args is None else args
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    state = {"signals": 0, "node": None}

    def on_signal(signum, frame):
        state["signals"] += 1
        if state["node"] is not None:
            state["node"].request_stop()
        if state["signals"] > 2:   # third signal: give up on a clean exit
            raise KeyboardInterrupt

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        try:
            sim_node = state["node"] = SimNode()
        except (ConfigError, ValueError, OSError) as e:
            print(f"sim_node: configuration error: {e}", file=sys.stderr)
            return 2
        if state["signals"]:
            sim_node.request_stop()
        executor, kind = make_executor(sim_node.settings.executor, sim_node.context)
        executor.add_node(sim_node.node)
        sim_node.log.info(f"executor: {kind}; ready")
        try:
            sim_node.run(executor)
        finally:
            # ignore further signals while the file is finalised
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
            sim_node.close()
            try:
                executor.shutdown(timeout_sec=0.1)
            except Exception:
                pass
        return 0
    finally:
        if state["node"] is not None:
            try:
                state["node"].node.destroy_node()
            except Exception:
                pass
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
