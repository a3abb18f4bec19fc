"""/starleth/solver: the diagnostics of sim_node (a DiagnosticArray): the solver status of
every step and the interface status (mode, counters, period errors, recording) every
INTERFACE_STATUS_EVERY steps, on a lockstep timeout and while paused; written as CDR bytes
field by field, or as message objects where that writer is not available."""
from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from starleth_interface.msg_cdr import DiagnosticArrayCdr

from .service import SimService

SOLVER_KEYS = ("iterations", "max_iterations_step", "converged", "status", "residual",
               "active_contacts", "retried", "step_time", "physics_steps",
               "nonconverged_steps", "loaded_contacts_opened", "loaded_contacts_opened_total",
               "projections", "projection_iterations")
INTERFACE_KEYS = ("mode", "real_time_factor", "sim_time", "step", "paused",
                  "waiting_for_first_command", "holding_initial_posture",
                  *SimService.COUNTERS,
                  "period_error_p50_ms", "period_error_p99_ms", "period_error_max_ms",
                  "overruns", "recorded_messages", "recording_dropped", "recording")


class SolverDiagnostics:
    """The statuses of /starleth/solver from the simulator's diagnostics, `service` (the
    lockstep bookkeeping and counters), `period_stats` (realtime period errors) and
    `recording` (a :class:`~.node_recording.NodeRecording`)."""

    INTERFACE_STATUS_EVERY = 40   # steps (10 Hz at 400 Hz); also on every lockstep timeout
    #: s (wall clock) between two /starleth/solver messages while paused: a monitor tells
    #: a paused simulator from a dead one
    PAUSED_DIAGNOSTICS_PERIOD = 1.0

    def __init__(self, sim, settings, service, period_stats, recording):
        self.sim, self.settings, self.service = sim, settings, service
        self.period_stats, self.recording = period_stats, recording
        self.diag_msg = DiagnosticArray()
        self.solver_status = DiagnosticStatus(name="starleth_sim: solver",
                                              hardware_id="starleth_sim")
        self.solver_status.values = [KeyValue(key=k, value="") for k in SOLVER_KEYS]
        self.iface_status = DiagnosticStatus(name="starleth_sim: interface",
                                             hardware_id="starleth_sim")
        self.iface_status.values = [KeyValue(key=k, value="") for k in INTERFACE_KEYS]
        self._solver_only = [self.solver_status]
        self._both = [self.solver_status, self.iface_status]
        # /starleth/solver written as CDR bytes field by field (None: message objects)
        self.cdr = DiagnosticArrayCdr("", [
            (st.name, st.hardware_id, [kv.key for kv in st.values]) for st in self._both])
        self.diag_msg.status = self._both
        self.period_summary = {}
        self._paused_at = 0.0        # publish_paused

    def update_period_summary(self):
        """The realtime period errors shown in the interface status (rounded)."""
        self.period_summary = {k: round(v, 4) if isinstance(v, float) else v
                               for k, v in self.period_stats.summary().items()}

    def statuses(self):
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
        out.append(self.interface_status())
        return out

    def interface_status(self):
        """The interface status of /starleth/solver: (1, level, message, values as str);
        ERROR with the reason while paused on a step that was not physics, WARN on a
        lockstep timeout or a failed recording."""
        svc = self.service
        ps = self.period_summary
        c = svc.counters
        vals = (self.settings.mode, self.settings.real_time_factor, svc.stamp_ns * 1e-9, svc.k,
                svc.paused, not svc.started, svc.holding, *(c[k] for k in SimService.COUNTERS),
                ps.get("period_error_p50_ms", ""), ps.get("period_error_p99_ms", ""),
                ps.get("period_error_max_ms", ""), self.period_stats.overruns,
                *self.recording.counts(), self.recording.state())
        if svc.failed:
            level, message = DiagnosticStatus.ERROR, f"paused: {svc.pause_reason}"
        elif svc.last_step_timed_out:
            level, message = DiagnosticStatus.WARN, "lockstep timeout"
        else:
            level = DiagnosticStatus.WARN if self.recording.failure is not None else \
                DiagnosticStatus.OK
            message = "paused" if svc.paused else "running"
        return (1, level, message, [str(v) for v in vals])

    def fill(self, sec, nsec, statuses):
        """The DiagnosticArray message object from statuses() (when the CDR writer is not
        available)."""
        self.diag_msg.header.stamp.sec, self.diag_msg.header.stamp.nanosec = sec, nsec
        objs = (self.solver_status, self.iface_status)
        for index, level, message, values in statuses:
            st = objs[index]
            st.level, st.message = level, message
            for kv, v in zip(st.values, values, strict=True):
                kv.value = v
        self.diag_msg.status = self._both if len(statuses) > 1 else self._solver_only

    def publish(self, output, sec, nsec, record):
        """/starleth/solver of the current state through `output` (a TopicOutput)."""
        statuses = self.statuses()
        if self.cdr is not None:
            output.emit_cdr("solver", self.cdr.build(sec, nsec, statuses), record)
        else:
            self.fill(sec, nsec, statuses)
            output.emit("solver", self.diag_msg, record)

    def publish_paused(self, publisher):
        """While paused: /starleth/solver on `publisher` every PAUSED_DIAGNOSTICS_PERIOD s
        with the interface status (stamp: the current sim time; published, not recorded:
        the bag keeps one message per step)."""
        now = time.monotonic()
        if now - self._paused_at < self.PAUSED_DIAGNOSTICS_PERIOD:
            return
        self._paused_at = now
        if publisher.get_subscription_count() == 0:
            return
        sec, nsec = divmod(self.service.stamp_ns, 1_000_000_000)
        statuses = self.statuses()           # paused: the interface status too
        if self.cdr is not None:
            publisher.publish(self.cdr.build(sec, nsec, statuses))
        else:
            self.fill(sec, nsec, statuses)
            publisher.publish(self.diag_msg)
