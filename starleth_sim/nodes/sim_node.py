"""``sim_node``: one StarlETH ``Simulator`` behind the ROS 2 interfaces users know from
mujoco_ros2_control / gz_ros2_control. A thin adapter: no physics in here.

    ros2 run starleth_sim sim_node --ros-args -p mode:=lockstep -p record:=run.mcap
    python -m starleth_sim.nodes.sim_node --ros-args --params-file my_sim.yaml

Published (stamps are sim time t_k = k / 400 s; one message per control step):

    /clock                                   rosgraph_msgs/Clock            ClockQoS (best effort, depth 1)
    /joint_states                            sensor_msgs/JointState         effort = applied (saturated) torque
    /starleth/{LF,RF,LH,RH}_foot/wrench      geometry_msgs/WrenchStamped    F = Λ/Δt, world axes, frame 'world'
    /starleth/base_state                     nav_msgs/Odometry              pose in 'world', twist in 'base'
    /starleth/imu                            sensor_msgs/Imu                proper acceleration, body rates
    /starleth/solver                         diagnostic_msgs/DiagnosticArray solver + interface counters
    /robot_description                       std_msgs/String                URDF, transient local, once

Subscribed:

    /joint_group_effort_controller/commands  std_msgs/Float64MultiArray     12 torques, joint order
    /joint_commands                          sensor_msgs/JointState         effort by joint name
    ~/wrench, ~/wrench/persistent            geometry_msgs/WrenchStamped    frame_id = link name

Services: ``~/reset`` (Trigger), ``~/pause`` (SetBool), ``~/step`` (Trigger, while paused).

Lockstep protocol: the state of step k (stamp t_k) is published, then the node waits for a
command answering it: a ``/joint_commands`` JointState whose header stamp equals t_k, or any
Float64MultiArray (it has no stamp, so in lockstep it is taken as the answer to the latest
state). A JointState command with another stamp is dropped and counted as *late* (it answers
a state that was already stepped on the timeout policy) or *stale* (any other stamp). Without
an answer within ``lockstep_timeout`` the node steps with ``timeout_policy`` (hold the last
command or zero torques), logs it and counts it. The node waits for the first command
before the first step, without timeout, so that two runs with the same controller are
bit-identical; a controller that dies later leaves the sim stepping on its timeout policy.

``~/reset`` restores the initial state; sim time keeps running (the reset takes one control
period, so stamps stay strictly increasing and answers to the old state are stale).

The ROS-free part (command validation, lockstep bookkeeping, counters, stepping) is
:class:`SimService`; :class:`SimNode` is the rclpy plumbing.
"""
from __future__ import annotations

import array
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

PERIOD_NS_ROUND = 1  # stamps are integer nanoseconds: t_k = k * period_ns
FEET = ("LF_foot", "RF_foot", "LH_foot", "RH_foot")

TOPIC_CLOCK = "/clock"
TOPIC_JOINT_STATES = "/joint_states"
TOPIC_BASE_STATE = "/starleth/base_state"
TOPIC_IMU = "/starleth/imu"
TOPIC_SOLVER = "/starleth/solver"
TOPIC_ROBOT_DESCRIPTION = "/robot_description"
TOPIC_EFFORT_COMMANDS = "/joint_group_effort_controller/commands"
TOPIC_JOINT_COMMANDS = "/joint_commands"
TOPIC_WRENCH = "~/wrench"
TOPIC_WRENCH_PERSISTENT = "~/wrench/persistent"


def foot_wrench_topic(foot: str) -> str:
    return f"/starleth/{foot}/wrench"


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
    initial_state: str = "standing"
    executor: str = "events"
    warn_throttle_period: float = 2.0
    world_frame: str = "world"
    base_frame: str = "base"

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
                     "base_frame"):
            if not isinstance(getattr(self, name), str):
                raise ConfigError(f"parameter {name}: expected a string, got "
                                  f"{getattr(self, name)!r}")
        if self.mode not in ("realtime", "lockstep"):
            raise ConfigError(f"parameter mode: must be 'realtime' or 'lockstep', got {self.mode!r}")
        num("real_time_factor", 0.0, False)
        if self.mode == "realtime" and self.real_time_factor == 0.0:
            raise ConfigError("parameter real_time_factor: 0 (as fast as possible) is only legal "
                              "in lockstep mode; realtime mode needs a factor > 0")
        num("lockstep_timeout", 0.0, True)
        num("warn_throttle_period", 0.0, False)
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
    from ..description import package_share_dir
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
_STATE_KEYS = ("base_position", "base_orientation", "joint_positions", "base_linear_velocity",
               "base_angular_velocity", "joint_velocities")


def parse_initial_state(spec, sim: Simulator):
    """(q, u, description dict) from the `initial_state` parameter: 'standing' / '' (the
    simulator's default state), a YAML mapping (string or dict), or a YAML file path."""
    if isinstance(spec, str):
        s = spec.strip()
        if s in ("", "standing", "default"):
            data = {}
        elif s.endswith((".yaml", ".yml")) and not s.startswith("{"):
            try:
                with open(s) as f:
                    data = yaml.safe_load(f) or {}
            except OSError as e:
                raise ConfigError(f"parameter initial_state: cannot read {s}: {e}") from None
        else:
            try:
                data = yaml.safe_load(s)
            except yaml.YAMLError as e:
                raise ConfigError(f"parameter initial_state: not valid YAML: {e}") from None
    else:
        data = spec or {}
    if not isinstance(data, dict):
        raise ConfigError(f"parameter initial_state: expected 'standing', a mapping or a YAML "
                          f"file, got {spec!r}")
    unknown = set(data) - set(_STATE_KEYS)
    if unknown:
        raise ConfigError(f"parameter initial_state: unknown keys {sorted(unknown)} (known: "
                          f"{', '.join(_STATE_KEYS)})")
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

    coords = sim.coords
    q = sim.default_state()
    u = np.zeros(coords.nv)
    if "base_position" in data:
        q[0:3] = vec("base_position", 3)
    if "base_orientation" in data:
        quat = vec("base_orientation", 4)
        if np.linalg.norm(quat) < 1e-9:
            raise ConfigError("parameter initial_state: base_orientation must not be zero")
        q[3:7] = quat / np.linalg.norm(quat)
    for key, idx, target in (("joint_positions", coords.joint_q, q),
                             ("joint_velocities", coords.joint_v, u)):
        if key in data:
            v = vec(key, nj)
            if isinstance(v, dict):
                for name, val in v.items():
                    x = float(val)
                    if not math.isfinite(x):
                        raise ConfigError(f"parameter initial_state: {key}.{name} not finite")
                    target[idx[sim.joint_names.index(name)]] = x
            else:
                target[idx] = v
    if "base_linear_velocity" in data or "base_angular_velocity" in data:
        v = vec("base_linear_velocity", 3) if "base_linear_velocity" in data else np.zeros(3)
        w = vec("base_angular_velocity", 3) if "base_angular_velocity" in data else np.zeros(3)
        coords.set_base_velocity_world(q, u, v, w)
    return q, u, {"spec": data if data else "standing"}


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
        self.links = frozenset(sim.coords.link_names())
        self.n = len(self.joint_names)
        self.warnings = ThrottledWarnings(warn, self.settings.warn_throttle_period)
        self._error = error or warn
        self.counters = dict.fromkeys(self.COUNTERS, 0)
        self.command = np.zeros(self.n)
        self.k = 0
        self.paused = False
        self.started = not self.lockstep     # lockstep: set by the first answer
        self.answered = False                # lockstep: the current state has its command
        self.last_step_timed_out = False
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
        if self.lockstep:
            stamp = self.stamp_ns if stamp_ns is None else int(stamp_ns)
            if stamp != self.stamp_ns or self.answered:
                if stamp in self._timed_out_stamps:
                    self.counters["late_commands"] += 1
                    self.warnings.warn("late", f"late command for t={stamp * 1e-9:.4f} s: that "
                                       "state was already stepped on the timeout policy "
                                       f"(now waiting for t={self.stamp_ns * 1e-9:.4f} s)")
                    return False, "late"
                self.counters["stale_commands"] += 1
                what = "already answered" if stamp == self.stamp_ns else \
                    f"stamp t={stamp * 1e-9:.4f} s does not match"
                self.warnings.warn("stale", f"dropped a stale command on {TOPIC_JOINT_COMMANDS}: "
                                   f"{what}; lockstep expects header.stamp = the stamp of the "
                                   f"/joint_states it answers (t={self.stamp_ns * 1e-9:.4f} s)")
                return False, "stale"
        tau = self.command.copy()
        for n, v in zip(names, a):
            tau[self.joint_index[n]] = v
        return self._accept(tau)

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
                self.paused = True
                if self._error:
                    self._error(f"physics step failed twice at t={self.sim.t:.4f} s ({e2}); "
                                "simulation paused, call ~/reset")
                return None
        self.k += 1
        self.counters["steps"] += 1
        self.answered = False
        self.state_version += 1
        return d

    def reset(self):
        """Back to the initial state, wrenches cleared, zero command; sim time advances by one
        control period (stamps stay strictly increasing)."""
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
        d["rejections_by_kind"] = dict(self.warnings.counts)
        return d


class PeriodStats:
    """Wall-clock tick intervals of the realtime loop (ring buffer)."""

    def __init__(self, nominal: float, size: int = 1 << 16):
        self.nominal = nominal
        self.buf = np.zeros(size)
        self.n = 0
        self.last = None
        self.overruns = 0

    def tick(self, t: float):
        if self.last is not None:
            self.buf[self.n % self.buf.shape[0]] = t - self.last
            self.n += 1
        self.last = t

    def restart(self):
        self.last = None

    def summary(self) -> dict:
        m = min(self.n, self.buf.shape[0])
        if m == 0:
            return {"ticks": 0}
        err = np.abs(self.buf[:m] - self.nominal)
        iv = self.buf[:m]
        return {"ticks": self.n, "period_mean_ms": float(iv.mean() * 1e3),
                "period_error_p50_ms": float(np.percentile(err, 50) * 1e3),
                "period_error_p99_ms": float(np.percentile(err, 99) * 1e3),
                "period_error_max_ms": float(err.max() * 1e3), "overruns": self.overruns}


# =========================================================================================
# math helpers
# =========================================================================================
def quat_to_matrix(qx, qy, qz, qw):
    return np.array([
        [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
        [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
        [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)]])


def _dbl(a) -> array.array:
    return array.array("d", np.ascontiguousarray(a, dtype=float).tobytes())


# =========================================================================================
# rclpy node
# =========================================================================================
def _import_ros():
    global rclpy, Node, QoSProfile, ReliabilityPolicy, DurabilityPolicy, HistoryPolicy
    global ParameterDescriptor, serialize_message
    global Clock, JointState, Imu, WrenchStamped, Odometry, DiagnosticArray, DiagnosticStatus
    global KeyValue, Float64MultiArray, String, Trigger, SetBool
    import rclpy  # noqa: F401
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy, DurabilityPolicy, HistoryPolicy
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.serialization import serialize_message
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
        for name in ("real_time_factor", "lockstep_timeout", "warn_throttle_period"):
            if isinstance(values[name], int) and not isinstance(values[name], bool):
                values[name] = float(values[name])
        for name in ("physics", "physics_overrides", "record", "initial_state"):
            if values[name] is None:
                values[name] = ""
        self.settings = Settings(**{k: v for k, v in values.items()
                                    if k in {f.name for f in fields(Settings)}}).validate()
        s = self.settings
        overrides = s.physics_override_dict()
        self.sim = Simulator.from_preset(s.physics, **overrides)
        q0, u0, init_desc = parse_initial_state(s.initial_state, self.sim)
        self.initial_state_desc = init_desc
        self.service = SimService(self.sim, s, q0, u0, warn=self.log.warning, error=self.log.error)
        self.context = node.context
        self._stop = False
        self.period_stats = PeriodStats(self.sim.control_period / max(s.real_time_factor, 1e-12))
        self._gravity = self._model_gravity()
        self._v_prev = None
        self._setup_messages()
        self._setup_interfaces()
        self.recorder = None
        if s.record:
            self._open_recorder(s.record)
        self._publish_robot_description()
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
                            "physics_steps", "nonconverged_steps")
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
        self.diag_msg.status = [self.solver_status, self.iface_status]
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

        pub("clock", Clock, TOPIC_CLOCK, clock_qos)
        pub("joint_states", JointState, TOPIC_JOINT_STATES, state_qos)
        for foot in FEET:
            pub(foot, WrenchStamped, foot_wrench_topic(foot), state_qos)
        pub("base_state", Odometry, TOPIC_BASE_STATE, state_qos)
        pub("imu", Imu, TOPIC_IMU, state_qos)
        pub("solver", DiagnosticArray, TOPIC_SOLVER, state_qos)
        pub("robot_description", String, TOPIC_ROBOT_DESCRIPTION, latched)
        self.subs = {}

        def sub(key, typ, topic, cb):
            sobj = node.create_subscription(typ, topic, cb, cmd_qos)
            self.subs[key] = (sobj, sobj.topic_name, typ, cmd_qos)

        sub("effort", Float64MultiArray, TOPIC_EFFORT_COMMANDS, self._on_effort)
        sub("joint_commands", JointState, TOPIC_JOINT_COMMANDS, self._on_joint_command)
        sub("wrench", WrenchStamped, TOPIC_WRENCH, self._on_wrench)
        sub("wrench_persistent", WrenchStamped, TOPIC_WRENCH_PERSISTENT,
            self._on_wrench_persistent)
        self.srv_reset = node.create_service(Trigger, "~/reset", self._srv_reset)
        self.srv_pause = node.create_service(SetBool, "~/pause", self._srv_pause)
        self.srv_step = node.create_service(Trigger, "~/step", self._srv_step)

    def _open_recorder(self, path):
        from ..recording import McapRecorder
        s, sim = self.settings, self.sim
        self.recorder = rec = McapRecorder(path, compression=s.record_compression,
                                           custom_data={"generator": "starleth_sim sim_node"})
        for key, (p, topic, typ, qos) in self.pubs.items():
            rec.add_topic(topic, typ, qos)
        for key, (sobj, topic, typ, qos) in self.subs.items():
            rec.add_topic(topic, typ, qos)
        cfg_yaml = yaml.safe_dump(sim.config.to_dict(), sort_keys=False)
        q0, u0 = self.service.q0, self.service.u0
        init = {"q": q0.tolist(), "u": u0.tolist(), "t": 0.0,
                "q_layout": "base position (3), base quaternion x y z w (4), joint angles "
                            "(pinocchio order)",
                "u_layout": "base linear velocity in the base frame (3), base angular velocity "
                            "in the base frame (3), joint velocities (pinocchio order)",
                "joint_positions": {n: float(v) for n, v in
                                    zip(sim.joint_names, sim.coords.joint_positions(q0))},
                "parameter": self.initial_state_desc["spec"]}
        params = asdict(s)
        rec.add_metadata("starleth_sim", {
            "physics_config": cfg_yaml, "initial_state": json.dumps(init),
            "parameters": json.dumps(params), "joint_names": json.dumps(list(sim.joint_names)),
            "control_period": repr(sim.control_period), "stamp_period_ns": str(self.service.period_ns),
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
    def _emit(self, key, msg, record):
        p, topic, _, _ = self.pubs[key]
        rec = self.recorder
        if record and rec is not None and not rec.closed:
            data = serialize_message(msg)
            p.publish(data)
            rec.write(topic, data, self.service.stamp_ns)
        else:
            p.publish(msg)

    def publish_state(self, record=True, only_joint_states=False):
        """Publish the state of the current step (stamp t_k) on every state topic."""
        svc, sim = self.service, self.sim
        sec, nsec = divmod(svc.stamp_ns, 1_000_000_000)
        if not only_joint_states:
            c = self.clock_msg.clock
            c.sec, c.nanosec = sec, nsec
            self._emit("clock", self.clock_msg, record)
        js = self.js_msg
        js.header.stamp.sec, js.header.stamp.nanosec = sec, nsec
        js.position = _dbl(sim.joint_positions())
        js.velocity = _dbl(sim.joint_velocities())
        js.effort = _dbl(sim.applied_torque)
        self._emit("joint_states", js, record)
        if only_joint_states:
            return
        for c in sim.contacts[:len(FEET)]:
            m = self.wrench_msgs.get(c.name)
            if m is None:
                continue
            m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
            f = m.wrench.force
            f.x, f.y, f.z = (float(x) for x in c.force)
            self._emit(c.name, m, record)
        b = sim.base_state()
        p, quat, v, w = (b["position"], b["orientation_xyzw"], b["linear_velocity"],
                         b["angular_velocity"])
        R = quat_to_matrix(*quat)
        v_body = R.T @ v
        o = self.odom_msg
        o.header.stamp.sec, o.header.stamp.nanosec = sec, nsec
        pp, po = o.pose.pose.position, o.pose.pose.orientation
        pp.x, pp.y, pp.z = float(p[0]), float(p[1]), float(p[2])
        po.x, po.y, po.z, po.w = (float(x) for x in quat)
        tl, ta = o.twist.twist.linear, o.twist.twist.angular
        tl.x, tl.y, tl.z = (float(x) for x in v_body)
        ta.x, ta.y, ta.z = (float(x) for x in w)
        self._emit("base_state", o, record)
        # IMU at the base origin: proper acceleration R^T (dv/dt - g), body rates
        if self._v_prev is None:
            acc = np.zeros(3)
        else:
            acc = (v - self._v_prev) / sim.control_period
        self._v_prev = v.copy()
        a_proper = R.T @ (acc - self._gravity)
        imu = self.imu_msg
        imu.header.stamp.sec, imu.header.stamp.nanosec = sec, nsec
        io_ = imu.orientation
        io_.x, io_.y, io_.z, io_.w = (float(x) for x in quat)
        iw, ia = imu.angular_velocity, imu.linear_acceleration
        iw.x, iw.y, iw.z = (float(x) for x in w)
        ia.x, ia.y, ia.z = (float(x) for x in a_proper)
        self._emit("imu", imu, record)
        self._fill_diagnostics(sec, nsec)
        self._emit("solver", self.diag_msg, record)

    def _fill_diagnostics(self, sec, nsec):
        svc = self.service
        d = self.sim.diagnostics
        self.diag_msg.header.stamp.sec, self.diag_msg.header.stamp.nanosec = sec, nsec
        st = self.solver_status
        st.level = DiagnosticStatus.OK if d.converged else DiagnosticStatus.WARN
        st.message = d.status
        vals = (d.iterations, d.max_iterations_step, d.converged, d.status, repr(d.residual),
                d.active_contacts, d.retried, repr(d.step_time), d.physics_steps,
                d.nonconverged_steps)
        for kv, v in zip(st.values, vals):
            kv.value = str(v)
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
    def _record_input(self, key, msg):
        rec = self.recorder
        if rec is not None and not rec.closed:
            rec.write(self.subs[key][1], serialize_message(msg), self.service.stamp_ns)

    def _on_effort(self, msg):
        self._record_input("effort", msg)
        self.service.submit_effort_array(msg.data)

    def _on_joint_command(self, msg):
        self._record_input("joint_commands", msg)
        st = msg.header.stamp
        self.service.submit_joint_command(msg.name, msg.effort,
                                          st.sec * 1_000_000_000 + st.nanosec)

    def _wrench(self, key, msg, persistent):
        self._record_input(key, msg)
        f, m = msg.wrench.force, msg.wrench.torque
        self.service.submit_wrench(msg.header.frame_id, (f.x, f.y, f.z), (m.x, m.y, m.z),
                                   persistent)

    def _on_wrench(self, msg):
        self._wrench("wrench", msg, False)

    def _on_wrench_persistent(self, msg):
        self._wrench("wrench_persistent", msg, True)

    def _srv_reset(self, request, response):
        self.service.reset()
        self._v_prev = None
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
        self.publish_state()
        if self.settings.mode == "lockstep":
            self._run_lockstep(executor)
        else:
            self._run_realtime(executor)

    def _update_period_summary(self):
        self._period_summary = {k: round(v, 4) if isinstance(v, float) else v
                                for k, v in self.period_stats.summary().items()}

    def _run_realtime(self, executor):
        svc, ps = self.service, self.period_stats
        period = self.sim.control_period / self.settings.real_time_factor
        clock = time.perf_counter
        next_tick = clock() + period
        margin = self.SPIN_MARGIN
        while self._running():
            if svc.paused:
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
            if lag > 2 * period:   # too far behind: drop the missed ticks, count an overrun
                ps.overruns += 1
                svc.warnings.warn("overrun", f"realtime loop overrun: {lag * 1e3:.1f} ms behind "
                                  "the wall clock; skipping ahead "
                                  f"({ps.overruns} overruns so far)")
                next_tick = clock() + period

    def _run_lockstep(self, executor):
        svc, s = self.service, self.settings
        clock = time.monotonic
        pace = self.sim.control_period / s.real_time_factor if s.real_time_factor > 0 else 0.0
        pace_origin = None
        version = svc.state_version
        deadline = clock() + s.lockstep_timeout
        last_republish = clock()
        n_subs = self.pubs["joint_states"][0].get_subscription_count()
        while self._running():
            if svc.paused:
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
                # before the first command: no timeout; re-send the state when a new
                # subscriber appears or every 0.5 s so a late controller sees it
                now = clock()
                n = self.pubs["joint_states"][0].get_subscription_count()
                if n != n_subs or now - last_republish > 0.5:
                    n_subs = n
                    last_republish = now
                    self.publish_state(record=False, only_joint_states=True)
                self._spin(executor, 0.05)
                continue
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
    """Console script ``sim_node``."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    argv = sys.argv if args is None else args
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    sim_node = None
    try:
        try:
            sim_node = SimNode()
        except (ConfigError, ValueError) as e:
            print(f"sim_node: configuration error: {e}", file=sys.stderr)
            return 2
        stops = {"n": 0}

        def on_signal(signum, frame):
            stops["n"] += 1
            sim_node.request_stop()
            if stops["n"] > 2:   # third signal: give up on a clean exit
                raise KeyboardInterrupt

        signal.signal(signal.SIGINT, on_signal)
        signal.signal(signal.SIGTERM, on_signal)
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
        if sim_node is not None:
            try:
                sim_node.node.destroy_node()
            except Exception:
                pass
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
