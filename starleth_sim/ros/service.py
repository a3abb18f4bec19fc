"""The ROS-free half of sim_node: command validation, lockstep bookkeeping, counters and
stepping (:class:`SimService`). :mod:`.sim_node` is the rclpy plumbing around it."""
from __future__ import annotations

from collections import Counter, deque

import numpy as np

from starleth_interface.ros_helpers import ThrottledLog
from starleth_interface.topics import (
    TOPIC_EFFORT_COMMANDS,
    TOPIC_JOINT_COMMANDS,
    TOPIC_POSITION_COMMANDS,
    TOPIC_VELOCITY_COMMANDS,
    TOPIC_WRENCH,
    TOPIC_WRENCH_PERSISTENT,
)

from ..physics.impedance import FIELDS as IMPEDANCE_FIELDS
from ..physics.impedance import ImpedanceCommand
from ..physics.sensors import Sensors
from ..physics.simulator import Simulator
from ..physics.stepper import SimulationError
from .command_delay import DelayLine, delay_periods
from .parameters import COMMAND_DELAY, Settings


def quoted(names, most=5, longest=64) -> str:
    """Names from a message, for a log line: at most `most` of them, each cut at `longest`
    characters (a 1 MB joint name makes a short line, not a 1 MB one)."""
    names = list(names)
    out = [repr(n) if len(n) <= longest else
           f"{n[:longest]!r}... ({len(n)} characters)" for n in names[:most]]
    if len(names) > most:
        out.append(f"and {len(names) - most} more")
    return ", ".join(out)


#: the hint of a lockstep node whose commands answer no state (SimService._answers_no_state;
#: sim_loops has its own for a node that waits long for its first answer)
TIMER_CONTROLLER_HINT = (
    "lockstep: the commands arriving answer no state. In lockstep each command answers the "
    "state it was sent for (a JointState stamped with that state's stamp, sent from the "
    "state's callback); a controller that runs on its own timer (ros2_control's "
    "controller_manager, a create_timer loop on sim time) belongs in realtime mode "
    "(mode:=realtime), where the clock runs on its own (doc/sim_node.md, \"Lockstep or "
    "realtime\")")


class SimService:
    """Command validation, lockstep bookkeeping and stepping, without any ROS.

    Time: step k has stamp ``k * period_ns`` [ns] (integer, so equal stamps compare exact).
    ``command`` is the command in effect, the last valid command, held until the next:
    joint torques (joint order, zero-order hold), an ImpedanceCommand (its law evaluated at
    every physics step), or (replay only) the applied torques of each physics step,
    (steps_per_control x n). With a command delay of d control periods (``command_delay``,
    :mod:`.command_delay`) a valid command waits in ``delay`` and is in effect from the d-th
    step after the state it was received at on.
    ``kp``, ``kd``: the gains of position and velocity targets (default_kp, default_kd;
    ``set_gains``). Every ``submit_*`` returns ``(accepted, reason)`` and never raises on
    bad input. Realtime mode with realtime_start hold (the default): the clock runs from
    the start and, until the first valid command is in effect, the command is the drives'
    hold of the initial posture (``holding``; :meth:`_start_hold`).

    A step whose result cannot be physical -- the physics failed twice (non-finite state,
    a mass matrix not positive definite: the stepper refuses those), or the base moved
    faster than MAX_BASE_SPEED over the control period -- is not a state: ``step`` returns
    None (nothing to publish or record), the service pauses with ``failed`` set and the
    reason in ``pause_reason``; only ``reset`` goes on from there."""

    #: m/s: the base moving faster than this over one control period is not physics (the
    #: robot walks at < 1 m/s; a fall from 10 m reaches 14 m/s; the largest push accepted,
    #: 5 kN on its 25 kg for a whole second, 200 m/s)
    MAX_BASE_SPEED = 300.0

    COUNTERS = ("commands_received", "commands_accepted", "commands_rejected", "late_commands",
                "stale_commands", "lockstep_timeouts", "wrenches_accepted", "wrenches_rejected",
                "simulation_errors", "resets", "steps", "impedance_commands", "gains_rejected")

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
        self.warnings = ThrottledLog(warn, self.settings.warn_throttle_period)
        self.errors = ThrottledLog(error or warn, self.settings.warn_throttle_period)
        self.counters = dict.fromkeys(self.COUNTERS, 0)
        self.command = np.zeros(self.n)
        self.delay = DelayLine()
        self.delay_text = self.set_command_delay(self.settings.command_delay)[1]
        self.kp = self.kd = None
        ok, why = self.set_gains(self.settings.default_kp, self.settings.default_kd)
        if not ok:
            raise ValueError(why)
        self.k = 0
        self.paused = self.settings.start_paused
        start = "lockstep" if self.lockstep else self.settings.realtime_start
        # set by the first valid command (lockstep: the first answer; realtime_start
        # first_command: the clock starts then); realtime_start hold or immediately: the
        # clock runs from the start
        self.started = start in ("hold", "immediately")
        #: realtime_start hold: until the first valid command (and after each reset) the
        #: joints hold the initial posture (_start_hold); cleared by a valid command
        self.hold_at_start = start == "hold"
        self.holding = False
        self.hold_position = None            # the initial joint angles q* of the hold
        self.answered = False                # lockstep: the current state has its command
        self.last_step_timed_out = False
        self.failed = False                  # paused: the physics failed (pause_reason)
        self.pause_reason = ""
        self.state_version = 0               # bumped whenever a new state exists
        self._timed_out_stamps = deque(maxlen=256)
        self._unanswering = 0                # lockstep: commands in a row that answer no state
        # warm up (first calls, first solve) so that the first real step is not slow;
        # reset() then restores the initial state and clears the solver's contact memory
        sim.reset(q=self.q0, u=self.u0, t=0.0)
        try:
            sim.step(np.zeros(self.n))
        except (SimulationError, ValueError):
            pass
        sim.reset(q=self.q0, u=self.u0, t=0.0)
        #: the sensors' readings of every state (physics/sensors.py): sampled after every
        #: step, whoever listens, so that the seeded stream replays bit for bit
        self.sensors = Sensors(sim)
        if self.hold_at_start:
            self.hold_position = sim.joint_positions().copy()
            self._start_hold()

    def _start_hold(self):
        """realtime_start hold: the command in effect becomes the drives' hold of the
        initial posture, the joint impedance law with q* = the initial joint angles, q̇* = 0
        and the gains default_kp, default_kd (as position-controlled drives hold at power-up),
        until the next valid command."""
        self.command = self.impedance_command(self.hold_position, 0.0, None)
        self.holding = True

    # -- time ------------------------------------------------------------------------------
    @property
    def stamp_ns(self) -> int:
        return self.k * self.period_ns

    @property
    def control_period(self) -> float:
        return self.sim.control_period

    # -- commands --------------------------------------------------------------------------
    def _reject(self, kind, message, detail=""):
        """Count and log (throttled per kind and detail) a rejected command."""
        self.counters["commands_rejected"] += 1
        self.warnings.warn(kind, message, detail)
        return False, message

    def _accept(self, tau):
        self._unanswering = 0
        self._hold(tau)
        self.counters["commands_accepted"] += 1
        self.started = True
        if self.lockstep:
            self.answered = True
        return True, "ok"

    def _hold(self, tau):
        """`tau` in effect from now on, or with a command delay from d steps on."""
        if self.delay.steps or self.delay.pending:
            self.delay.put(self.k, tau)
        else:
            self.command = tau
            self.holding = False

    def set_command_delay(self, seconds):
        """The command delay: `seconds` (the parameter command_delay's range) as a whole
        number of control periods, for the commands received from now on (pending ones keep
        their step). (accepted, a line saying what it is, or why not.)"""
        try:
            COMMAND_DELAY.check(COMMAND_DELAY.coerce(seconds))
        except ValueError as e:
            return False, str(e)
        self.delay.steps, text = delay_periods(float(seconds), self.control_period)
        return True, text

    def _check_values(self, values, what):
        try:
            a = np.array(values, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            return None, f"{what}: values are not numbers"
        return a, None

    #: the Float64MultiArray command topics: key -> (topic, what its values are)
    ARRAY_TOPICS = {"effort": (TOPIC_EFFORT_COMMANDS, "torque"),
                    "position": (TOPIC_POSITION_COMMANDS, "position target"),
                    "velocity": (TOPIC_VELOCITY_COMMANDS, "velocity target")}

    def submit_effort_array(self, data):
        """A Float64MultiArray's data: n torques in joint order. In lockstep it answers the
        latest published state (the message has no stamp)."""
        return self.submit_array("effort", data)

    def submit_array(self, kind, data):
        """A Float64MultiArray's data on the `kind` topic of ARRAY_TOPICS: n finite values in
        joint order; effort: torques; position: targets q* tracked with kp, kd (q̇* = 0);
        velocity: targets q̇* tracked with kd (no spring), as ros2_control's
        forward_command_controllers. In lockstep it answers the latest published state."""
        self.counters["commands_received"] += 1
        topic, what = self.ARRAY_TOPICS[kind]
        a, err = self._check_values(data, f"{kind} command")
        if err:
            return self._reject(f"{kind}_type", f"rejected {kind} command on {topic}: {err}")
        if a.shape[0] != self.n:
            return self._reject(f"{kind}_length",
                                f"rejected {kind} command on {topic}: "
                                f"{a.shape[0]} values, expected {self.n} (joint order "
                                f"{', '.join(self.joint_names)}); keeping the last valid command",
                                str(a.shape[0]))
        bad = ~np.isfinite(a)
        if bad.any():
            which = ", ".join(self.joint_names[i] for i in np.flatnonzero(bad))
            return self._reject(f"{kind}_nonfinite",
                                f"rejected {kind} command on {topic}: non-finite "
                                f"{what} for {which}; keeping the last valid command", which)
        if self.lockstep and self.answered:
            self.counters["stale_commands"] += 1
            self.warnings.warn("stale", f"dropped an extra {kind} command: the current state "
                               "was already answered")
            self._answers_no_state()
            return False, "state already answered"
        if kind == "effort":
            return self._accept(a)
        if kind == "position":
            return self._accept_impedance(a, 0.0, None)
        return self._accept_impedance(None, a, None)

    def submit_joint_command(self, names, efforts, stamp_ns=None, position=(), velocity=()):
        """A JointState command: efforts by joint name (position and velocity empty), or an
        impedance command (:meth:`_joint_impedance`) when position or velocity holds values.
        The names must be the simulator's
        joints, each once and all of them, in any order; an empty name list means joint
        order (then n efforts). A command naming some joints but not all is rejected (one
        line naming the missing ones): holding the others at their last command would
        keep a torque the sender may no longer know it is applying. In lockstep the stamp
        must equal the stamp of the state being answered. The names are checked first
        (:meth:`_joint_order`), then the fields."""
        self.counters["commands_received"] += 1
        names = list(names)
        if len(position) or len(velocity):
            return self._joint_impedance(names, position, velocity, efforts, stamp_ns)
        a, err = self._check_values(efforts, "joint command")
        if err:
            return self._reject("joint_type", f"rejected joint command: {err}")
        if names == self._joint_name_list and a.shape[0] == self.n and np.isfinite(a).all() \
                and (not self.lockstep or self._stamp_ok(stamp_ns)):
            return self._accept(a)   # fast path: every joint in joint order, valid
        order, problem = self._joint_order(names)
        if order is None:
            return self._reject(*problem)
        if a.shape[0] != self.n:
            return self._reject("joint_length",
                                f"rejected joint command on {TOPIC_JOINT_COMMANDS}: "
                                + (f"{len(names)} names but {a.shape[0]} efforts" if names else
                                   f"no joint names and {a.shape[0]} efforts (give the names, "
                                   f"or {self.n} efforts in joint order)"),
                                f"{len(names)}/{a.shape[0]}")
        bad = ~np.isfinite(a)
        if bad.any():
            which = ", ".join(self.joint_names[order[i]] for i in np.flatnonzero(bad))
            return self._reject("joint_nonfinite",
                                f"rejected joint command on {TOPIC_JOINT_COMMANDS}: non-finite "
                                f"effort for {which}; keeping the last valid command", which)
        if self.lockstep and not self._stamp_ok(stamp_ns):
            return self._stale(stamp_ns)
        tau = np.empty(self.n)
        tau[order] = a
        return self._accept(tau)

    def _joint_impedance(self, names, position, velocity, efforts, stamp_ns):
        """A JointState whose position or velocity holds values: targets q*, q̇* and the
        feed-forward τ_ff by name, tracked with the gains kp, kd at every physics step. An
        empty field: position, no spring; velocity, q̇* = 0 (the damper pulls to rest) when a
        position is given, else no damper; effort, no τ_ff. NaN in a field: that term off
        for that joint. A filled field holds one value per name (n in joint order without
        names); infinities are rejected."""
        if names == self._joint_name_list:
            order = slice(None)            # every joint in joint order: the common case
        else:
            order, problem = self._joint_order(names)
            if order is None:
                return self._reject(*problem)
        topic, m = TOPIC_JOINT_COMMANDS, (len(names) if names else self.n)
        fields = {}
        for field, values in (("position", position), ("velocity", velocity),
                              ("effort", efforts)):
            a, err = self._check_values(values, f"joint command {field}")
            if err:
                return self._reject("joint_type", f"rejected joint command on {topic}: {err}")
            if a.shape[0] == 0:
                fields[field] = None
                continue
            if a.shape[0] != m:
                return self._reject("joint_length",
                                    f"rejected joint command on {topic}: {m} joints but "
                                    f"{a.shape[0]} {field} values (a field holds one value per "
                                    "joint, or none); keeping the last valid command",
                                    f"{field} {m}/{a.shape[0]}")
            v = np.empty(self.n)
            v[order] = a
            inf = np.isinf(v)
            if inf.any():
                which = ", ".join(self.joint_names[i] for i in np.flatnonzero(inf))
                return self._reject("joint_infinite",
                                    f"rejected joint command on {topic}: infinite {field} for "
                                    f"{which} (NaN turns a term off); keeping the last valid "
                                    "command", f"{field} {which}")
            fields[field] = v
        if self.lockstep and not self._stamp_ok(stamp_ns):
            return self._stale(stamp_ns)
        velocity = fields["velocity"]
        if velocity is None:
            velocity = 0.0 if fields["position"] is not None else None
        return self._accept_impedance(fields["position"], velocity, fields["effort"])

    def _accept_impedance(self, position, velocity, effort):
        """Hold an ImpedanceCommand of these (checked) targets with the current gains."""
        self.counters["impedance_commands"] += 1
        return self._accept(self.impedance_command(position, velocity, effort))

    def impedance_command(self, position, velocity, effort):
        """The ImpedanceCommand of targets already checked (n values, a number, or None:
        NaN, that term off) with the current gains (checked by set_gains), packed straight
        into the layout of ImpedanceCommand.create (impedance.FIELDS), without create's
        validation again: in lockstep a slow controller's targets come with every state.
        test_impedance_commands checks it equals create's command."""
        n = self.n
        packed = np.empty(len(IMPEDANCE_FIELDS) * n)
        values = {"position": position, "velocity": velocity, "kp": self.kp, "kd": self.kd,
                  "effort": effort}
        for i, name in enumerate(IMPEDANCE_FIELDS):
            v = values[name]
            packed[i * n:(i + 1) * n] = np.nan if v is None else v
        packed.flags.writeable = False
        return ImpedanceCommand(packed=packed, joint_names=self.joint_names,
                                **{name: packed[i * n:(i + 1) * n]
                                   for i, name in enumerate(IMPEDANCE_FIELDS)})

    def set_gains(self, kp=None, kd=None):
        """The gains of position and velocity targets: each one number for every joint or n
        (joint order), finite and >= 0 (None: unchanged). A held impedance command takes
        the new gains at once. (accepted, reason); rejected gains are counted
        (gains_rejected), warned of and change nothing."""
        new = {}
        for name, value in (("default_kp", kp), ("default_kd", kd)):
            if value is None:
                new[name] = self.kp if name == "default_kp" else self.kd
                continue
            try:
                a = np.array(value, dtype=float).reshape(-1)
            except (TypeError, ValueError):
                return self.reject_gains(name, f"{name}: not numbers ({value!r})")
            if a.shape[0] == 1:
                a = np.repeat(a, self.n)
            if a.shape[0] != self.n:
                return self.reject_gains(name, f"{name}: {a.shape[0]} values, expected 1 or "
                                          f"{self.n} (joint order {', '.join(self.joint_names)})")
            bad = ~(np.isfinite(a) & (a >= 0.0))
            if bad.any():
                which = ", ".join(f"{self.joint_names[i]} ({a[i]:g})"
                                  for i in np.flatnonzero(bad))
                return self.reject_gains(name, f"{name}: must be finite and >= 0: {which}")
            new[name] = a
        self.kp, self.kd = new["default_kp"], new["default_kd"]
        self.command = self._with_gains(self.command)
        if self.delay.pending:
            self.delay.update(self._with_gains)
        return True, "ok"

    def _with_gains(self, c):
        """An impedance command `c` with the current gains (any other command as it is)."""
        if type(c) is ImpedanceCommand:
            return self.impedance_command(c.position, c.velocity, c.effort)
        return c

    def reject_gains(self, name, message):
        self.counters["gains_rejected"] += 1
        self.warnings.warn("gains", f"rejected gains {message}; keeping the previous gains",
                           name)
        return False, message

    def _joint_order(self, names):
        """(index in joint order of each name, None), or (None, (kind, message, detail)) when
        the names are not every joint once: unknown, repeated or missing names. No names:
        joint order."""
        if not names:
            return np.arange(self.n), None
        topic = TOPIC_JOINT_COMMANDS
        unknown = [n for n in names if n not in self.joint_index]
        if unknown:
            which = quoted(unknown)
            return None, ("unknown_joint", f"rejected joint command on {topic}: unknown joint "
                          f"name(s) {which} (joints: {', '.join(self.joint_names)}); keeping "
                          "the last valid command", which)
        order = [self.joint_index[n] for n in names]
        if len(set(order)) != len(order):
            dup = ", ".join(sorted(n for n, c in Counter(names).items() if c > 1))
            return None, ("duplicate_joint", f"rejected joint command on {topic}: duplicate "
                          f"joint name(s) {dup}; keeping the last valid command", dup)
        if len(order) != self.n:
            given = set(order)
            missing = ", ".join(n for i, n in enumerate(self.joint_names) if i not in given)
            return None, ("missing_joint", f"rejected joint command on {topic}: no effort "
                          f"for {missing} (a command names all {self.n} joints, or none for "
                          "joint order); keeping the last valid command", missing)
        return np.array(order), None

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
        self._answers_no_state()
        return False, "stale"

    #: lockstep: this many commands in a row that answer no state give the hint (once)
    UNANSWERING_HINT = 3

    def _answers_no_state(self):
        """Lockstep: a command that answers no state (stale, or one more for a state already
        answered). Once UNANSWERING_HINT come in a row (a reset's stale answer is one), the
        log gets one hint, once per run: such commands come from a controller that runs on
        its own timer, which belongs in realtime mode."""
        self._unanswering += 1
        if self._unanswering == self.UNANSWERING_HINT and \
                not self.warnings.counts.get("timer_controller"):
            self.warnings.warn("timer_controller", TIMER_CONTROLLER_HINT)

    def link_of_frame(self, frame_id: str) -> str:
        """The link a wrench's header.frame_id names: its frame on /tf (tf_frame_prefix +
        link) or the URDF's link name."""
        prefix = self.settings.tf_frame_prefix
        if prefix and frame_id.startswith(prefix) and frame_id[len(prefix):] in self.links:
            return frame_id[len(prefix):]
        return frame_id

    def submit_wrench(self, frame_id, force, torque, persistent=False):
        """A push on the link `frame_id` names (link_of_frame; world axes, at the link
        origin): one control period, or until replaced/cleared (zero wrench) when
        persistent."""
        topic = TOPIC_WRENCH_PERSISTENT if persistent else TOPIC_WRENCH
        link = self.link_of_frame(frame_id)
        detail = f"{topic} {quoted([link])}"     # each topic and link is warned of apart
        if link not in self.links:
            self.counters["wrenches_rejected"] += 1
            prefix = self.settings.tf_frame_prefix
            msg = (f"rejected wrench on {topic}: unknown link {quoted([link])} in header.frame_id "
                   f"(links: {', '.join(sorted(self.links))}"
                   + (f", each also as its frame {prefix}<link>" if prefix else "") + ")")
            self.warnings.warn("unknown_link", msg, detail)
            return False, msg
        f = np.array(force, dtype=float).reshape(-1)
        m = np.array(torque, dtype=float).reshape(-1)
        if f.shape != (3,) or m.shape != (3,) or not (np.all(np.isfinite(f)) and
                                                       np.all(np.isfinite(m))):
            self.counters["wrenches_rejected"] += 1
            msg = (f"rejected wrench on {topic} for {quoted([link])}: force and torque must be "
                   "finite")
            self.warnings.warn("bad_wrench", msg, detail)
            return False, msg
        s = self.settings
        f_norm, m_norm = float(np.linalg.norm(f)), float(np.linalg.norm(m))
        if f_norm > s.max_wrench_force or m_norm > s.max_wrench_torque:
            self.counters["wrenches_rejected"] += 1
            msg = (f"rejected wrench on {topic} for {quoted([link])}: |force| {f_norm:.4g} N, "
                   f"|torque| {m_norm:.4g} N m; the limits are max_wrench_force "
                   f"{s.max_wrench_force:g} N and max_wrench_torque {s.max_wrench_torque:g} N m")
            self.warnings.warn("wrench_too_large", msg, detail)
            return False, msg
        try:
            if persistent:
                self.sim.set_persistent_wrench(link, f, m)
            else:
                self.sim.apply_wrench(link, f, m)
        except ValueError as e:
            self.counters["wrenches_rejected"] += 1
            self.warnings.warn("bad_wrench", f"rejected wrench on {topic}: {e}", detail)
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
        if pol == "zero":       # the missing answer (with a command delay: in d steps)
            self._hold(np.zeros(self.n))

    def step(self, timed_out: bool = False):
        """One control period with the current command; returns the Diagnostics (or None
        when the physics failed twice and the simulation was paused)."""
        if timed_out:
            self.on_timeout()
        self.last_step_timed_out = timed_out
        if self.delay.pending:
            due = self.delay.due(self.k)
            if due is not None:
                self.command = due
                self.holding = False
        tau = self.command
        sim = self.sim
        if self.failed:
            return None
        x0, y0, z0 = sim.root_position()
        try:
            # (a 2-d array: the recorded applied torques of each physics step, a replay)
            d = sim.step_applied(tau) if type(tau) is np.ndarray and tau.ndim == 2 else \
                sim.step(tau)
        except (SimulationError, ValueError) as e:
            self.counters["simulation_errors"] += 1
            self.warnings.warn("simulation_error", f"physics step failed at t="
                               f"{sim.t:.4f} s ({e}); retrying with zero torques")
            try:
                d = sim.step(np.zeros(self.n))
            except (SimulationError, ValueError) as e2:
                return self._fail(f"physics step failed twice at t={sim.t:.4f} s ({e2})")
        x1, y1, z1 = sim.root_position()
        moved = ((x1 - x0) ** 2 + (y1 - y0) ** 2 + (z1 - z0) ** 2) ** 0.5
        if not moved <= self.MAX_BASE_SPEED * self.control_period:     # also NaN
            self.counters["simulation_errors"] += 1
            return self._fail(f"the base moved {moved:.4g} m in one control period at t="
                              f"{self.stamp_ns * 1e-9:.4f} s (more than {self.MAX_BASE_SPEED:g}"
                              f" m/s: not physics); that state is not published")
        self.sensors.sample()
        self.k += 1
        self.counters["steps"] += 1
        self.answered = False
        self.state_version += 1
        return d

    def _fail(self, reason):
        """Pause on a step that is not physics (see the class docstring); returns None."""
        self.paused = self.failed = True
        self.pause_reason = reason
        self.errors.warn("simulation_paused", f"{reason}; simulation paused, call ~/reset")
        return None

    def reset(self):
        """Back to the initial state, wrenches cleared, zero command (realtime_start hold: the
        hold of the initial posture, until the next valid command); sim time advances by one
        control period (stamps stay strictly increasing). A pause caused by a physics
        failure ends; a pause asked for with ~/pause stays."""
        if self.failed:
            self.failed = self.paused = False
            self.pause_reason = ""
        self.k += 1
        self.sim.clear_wrenches()
        self.sim.reset(q=self.q0, u=self.u0, t=self.k * self.control_period)
        self.sensors.restart()
        self.command = np.zeros(self.n)
        self.delay.clear()
        if self.hold_at_start:        # the drives hold the initial posture again
            self._start_hold()
        self.answered = False
        self.counters["resets"] += 1
        self.state_version += 1

    def summary(self) -> dict:
        d = dict(self.counters)
        d["sim_time"] = self.stamp_ns * 1e-9
        d["warnings_by_kind"] = dict(self.warnings.counts)
        return d
