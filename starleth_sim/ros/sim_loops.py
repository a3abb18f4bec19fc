"""The loops that step sim_node: lockstep (publish the state of step k, wait for the command
answering it, step; before the first command, re-send state 0 until a controller answers)
and realtime (a wall-clock loop holding the latest valid command; with realtime_start hold,
the default, it runs from the start, the joints holding the initial posture until the first
valid command; with first_command it too re-sends state 0 and its clock starts with the
first valid command); both run until stopped or the ROS context is shut down. The protocol in
words: doc/sim_node.md, "Lockstep" and "Realtime mode"."""
from __future__ import annotations

import gc
import os
import time

import numpy as np


class SimLoops:
    """Steps `service` (a :class:`~.service.SimService`) on the executor given to :meth:`run`
    and publishes each state through `publisher` (a
    :class:`~.state_publisher.StatePublisher`); while paused, /starleth/solver once a second
    from `diagnostics`. `context` is the node's ROS context."""

    SPIN_MARGIN = 0.0006  # realtime: stop waiting in the executor this long before a tick
    MAX_CATCH_UP = 0.1    # realtime: at most this far behind the wall clock, then skip ahead
    CONTEXT_CHECK_PERIOD = 0.01   # s: look at the ROS context at most this often
    REPUBLISH_PERIOD = 0.5        # s: re-send state 0 this often until the first command
    NEW_SUBSCRIBER_CHECK = 0.05   # s: look for new subscribers this often while waiting
    NO_ANSWER_HINT_AFTER = 5.0    # s: lockstep, no first answer: the hint of a timer controller

    def __init__(self, context, sim, settings, service, period_stats, publisher, diagnostics,
                 log):
        self.context, self.sim, self.settings, self.service = context, sim, settings, service
        self.period_stats, self.publisher, self.diagnostics = period_stats, publisher, diagnostics
        self.log = log
        self.stop = False
        self.step_on_answer = False    # set by run() in lockstep mode without pacing
        self._context_ok_until = 0.0
        self._n_state_subs = 0          # subscribers of the state topics at the last look
        self._no_answer_hinted = False

    def running(self):
        """Not stopped and the context not shut down (the context, whose check takes a lock,
        is looked at every CONTEXT_CHECK_PERIOD s; a shut-down context also ends _spin)."""
        if self.stop:
            return False
        now = time.monotonic()
        if now < self._context_ok_until:
            return True
        if not self.context.ok():
            return False
        self._context_ok_until = now + self.CONTEXT_CHECK_PERIOD
        return True

    def _spin(self, executor, timeout):
        try:
            executor.spin_once(timeout_sec=max(0.0, timeout))
        except Exception as e:  # ExternalShutdownException, context shut down
            if not self.context.ok():
                self.stop = True
            else:
                raise e

    def run(self, executor):
        """Run until `stop` is set or the context is shut down."""
        # everything built so far lives for the whole run: move it out of the garbage
        # collector's generations, so that a full collection in the loop stays short
        gc.collect()
        gc.freeze()
        self._n_state_subs = self.publisher.state_subscriber_count()
        self.publisher.publish_state()
        if self.settings.mode == "lockstep":
            self.step_on_answer = self.settings.real_time_factor == 0.0
            self._run_lockstep(executor)
        else:
            self._run_realtime(executor)

    def advance(self):
        """Lockstep without pacing: step as soon as the answer is in, right in the
        subscription callback (saves a trip through the executor on the critical path)."""
        svc = self.service
        if svc.answered and not svc.paused and not self.stop:
            if svc.step() is not None:
                timing = self.publisher.timing
                if timing is not None:
                    timing.row[1] = time.perf_counter()
                self.publisher.publish_state()

    def _republish_for_new_subscribers(self, resend=True) -> bool:
        """While the node waits for a command: when a new subscriber to any state topic
        appeared since the last look, send the current state again on every topic (same
        stamp, not recorded; resend=False only takes the count), so that a controller that
        connects late, or a restarted one, sees a whole state it can answer."""
        n = self.publisher.state_subscriber_count()
        new = n > self._n_state_subs
        self._n_state_subs = n
        if new and resend:
            self.publisher.republish_state()
        return new and resend

    def _before_first_step(self) -> bool:
        svc = self.service
        return not (svc.counters["steps"] or svc.counters["resets"])

    def _while_paused(self, executor):
        """One turn of a loop while paused: a late subscriber gets state 0 (after the first
        step, every stamp goes out once), /starleth/solver once a second."""
        self._republish_for_new_subscribers(resend=self._before_first_step())
        self.diagnostics.publish_paused(self.publisher.output.pubs["solver"][0])
        self._spin(executor, 0.05)

    def _wait_for_first_command(self, executor, last_republish) -> float:
        """One turn of a loop before the first command: re-send the whole state when a new
        subscriber appears and every REPUBLISH_PERIOD s, so that a late controller sees it
        (no timeout, no step); returns the time of the last re-send."""
        now = time.monotonic()
        if self._republish_for_new_subscribers():
            last_republish = now
        elif now - last_republish > self.REPUBLISH_PERIOD:
            last_republish = now
            self.publisher.republish_state()
        self._spin(executor, 0.05)
        return last_republish

    def _hint_if_no_answer(self, waiting_since):
        """Lockstep, before the first answer: once nodes have followed this simulator (read
        its state or its /clock) for NO_ANSWER_HINT_AFTER s and no command came at all, one
        hint (once per run): a controller that runs on a sim-time timer never runs in
        lockstep, where the clock moves only with answers."""
        svc = self.service
        if self._no_answer_hinted or svc.counters["commands_received"] or \
                time.monotonic() - waiting_since < self.NO_ANSWER_HINT_AFTER:
            return
        followers = self._n_state_subs + self.publisher.clock_subscriber_count()
        if followers == 0:
            return
        self._no_answer_hinted = True
        self.log.warning(f"lockstep: {followers} subscription(s) follow state 0 or /clock "
                         f"but no command came in {self.NO_ANSWER_HINT_AFTER:g} s; the clock "
                         "stays at 0 until a controller answers the state it receives. A "
                         "controller that runs on a timer on sim time (ros2_control's "
                         "controller_manager, create_timer with use_sim_time) never runs in "
                         "lockstep: run sim_node with mode:=realtime (doc/sim_node.md, "
                         "\"Lockstep or realtime\")")

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

    def _report_hold(self, was_holding) -> bool:
        """One log line when the drives' hold of the initial posture (realtime_start hold)
        begins (at the start, after a reset) or ends (the first valid command in effect);
        returns whether it holds now."""
        svc = self.service
        if svc.holding and not was_holding:
            kp, kd = svc.kp, svc.kd
            gains = (f"kp {kp[0]:g}, kd {kd[0]:g}" if np.ptp(kp) == 0 and np.ptp(kd) == 0
                     else "default_kp, default_kd")
            self.log.info(f"realtime: the clock runs from t={svc.stamp_ns * 1e-9:.4f} s; until "
                          "the first valid command the joints hold the initial posture "
                          f"(joint impedance, {gains}; realtime_start:=first_command waits "
                          "for a controller instead)")
        elif was_holding and not svc.holding:
            self.log.info(f"realtime: the first command is in effect at t="
                          f"{svc.stamp_ns * 1e-9:.4f} s: the hold of the initial posture ends")
        return svc.holding

    def _run_realtime(self, executor):
        self._set_realtime_priority()
        svc, ps = self.service, self.period_stats
        period = self.sim.control_period / self.settings.real_time_factor
        clock = time.perf_counter
        next_tick = clock() + period
        margin = self.SPIN_MARGIN
        waiting, last_republish = not svc.started, time.monotonic()
        if waiting:
            self.log.info("realtime: waiting for the first command (the clock starts with it; "
                          "realtime_start:=hold runs it from the start)")
        holding = self._report_hold(False)
        while self.running():
            if svc.paused:
                self._while_paused(executor)
                next_tick = clock() + period
                ps.restart()
                continue
            if waiting:
                if not svc.started:
                    last_republish = self._wait_for_first_command(executor, last_republish)
                    continue
                waiting = False
                self.log.info(f"realtime: first command received; the clock starts at t="
                              f"{svc.stamp_ns * 1e-9:.4f} s")
                next_tick = clock() + period
                ps.restart()
            if not self._wait_for_tick(executor, next_tick, margin):
                continue
            ps.tick(clock())
            if svc.step() is not None:
                self.publisher.publish_state()
            if svc.holding is not holding:
                holding = self._report_hold(holding)
            if svc.k % 400 == 0:
                self.diagnostics.update_period_summary()
            next_tick = self._next_tick(next_tick + period, period)

    def _wait_for_tick(self, executor, next_tick, margin) -> bool:
        """Waits in the executor (commands, services) until shortly before the tick, then
        spins on the clock; behind the wall clock, still takes once what has arrived (else a
        loop that stays behind would never see a command). False: paused or stopping."""
        clock, svc = time.perf_counter, self.service
        spun = False
        while True:
            remaining = next_tick - clock()
            if remaining <= margin or not self.running():
                break
            self._spin(executor, min(remaining - margin, 0.05))
            spun = True
            if svc.paused:
                break
        if not spun:
            self._spin(executor, 0.0)
        if svc.paused or not self.running():
            return False
        while clock() < next_tick:
            pass
        return True

    def _next_tick(self, next_tick, period):
        """The next tick's time: `next_tick`, or, too far behind the wall clock (the host
        cannot keep up), one period from now with the missed ticks dropped and said (behind
        by less, the next ticks follow at once until caught up)."""
        lag = time.perf_counter() - next_tick
        if lag > self.MAX_CATCH_UP:
            ps = self.period_stats
            ps.overruns += 1
            self.service.warnings.warn("overrun", f"realtime loop overrun: {lag * 1e3:.1f} ms "
                                       "behind the wall clock; skipping ahead "
                                       f"({ps.overruns} overruns so far)")
            return time.perf_counter() + period
        return next_tick

    def _run_lockstep(self, executor):
        svc, s = self.service, self.settings
        clock = time.monotonic
        pace = self.sim.control_period / s.real_time_factor if s.real_time_factor > 0 else 0.0
        pace_origin = None
        version = svc.state_version
        deadline = clock() + s.lockstep_timeout
        last_republish = waiting_since = clock()
        while self.running():
            if svc.paused:
                self._while_paused(executor)
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
                    while now < due and self.running():
                        if due - now > 0.002:
                            time.sleep(due - now - 0.001)
                        now = time.perf_counter()
                if svc.step(timed_out=timed_out) is not None:
                    self.publisher.publish_state()
                continue
            if not svc.started:
                # before the first command: no timeout (state 0 re-sent for late controllers)
                last_republish = self._wait_for_first_command(executor, last_republish)
                self._hint_if_no_answer(waiting_since)
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
