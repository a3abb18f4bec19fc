"""Joint impedance commands through sim_node as users send them (issue #36): an external
rclpy controller that sends only joint position targets at 50 Hz (kp 80) holds the stand on
HmJ and Cm, in lockstep and in realtime; the same targets sent as torques by a 400 Hz relay
(τ = kp (q* − q) − kd q̇ at every state) track worse by a measured margin when every command
arrives a control period late (command_delay), and as well without it (printed); the
position forwarding topic; the recording of the delayed impedance run replays bit for bit
(starleth/applied_torque); bad input, a negative gain and a delay out of range at run time
are refused.

Lockstep protocol of a slow controller (doc/sim_node.md): it answers every state, with the
targets it holds (recomputed at 50 Hz); in realtime it sends at 50 Hz only and the simulator
keeps tracking the held command. Gains: kp 80, kd 2 on HmJ and Cm (on Cm the implicit
damper makes kd 2 stable beside the compliant contact's explicit damper: doc/physics.md,
"Joint impedance"; test_impedance_commands.py::test_cm_holds_the_stand_on_kp_80_kd_2).

sim_node runs as a child process on an isolated ROS_DOMAIN_ID; every wait is bounded."""
import dataclasses
import os
import re

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from controller_examples import controllers_page_blocks, run_beside_sim_node
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import SetParameters
from ros_test_nodes import NodeProcess, RosTestNode
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import SetBool, Trigger

from starleth_sim.physics.simulator import Simulator
from starleth_sim.robots import load_robot
from starleth_sim.ros.parameters import Settings
from starleth_sim.ros.qos import COMMAND_QOS, STATE_QOS
from starleth_sim.ros.service import SimService
from starleth_sim.ros.state_io import parse_initial_state
from starleth_sim.tools.replay.recording import load_recording
from starleth_sim.tools.replay.resimulation import compare_exact, resimulate

STARLETH_STANDING_HEIGHT = load_robot("starleth").standing_height

DOMAIN_RANGE = (229, 4)        # first, span (conftest._free_ros_domain)
DOMAIN_ID = 229 + os.getpid() % 4
START_TIMEOUT = 120.0
PERIOD_NS = 2_500_000
SLOW = 8                       # 400 Hz / 50 Hz
KP = 80.0
STATES = 320                   # per phase: 0.8 s of sim time
DELAY = 0.0025                 # s: one control period, a ROS hop and a loop


def ns_of(stamp):
    return stamp.sec * 1_000_000_000 + stamp.nanosec


class TargetController:
    """The external controller: position targets q* (the standing posture, plus 0.05 rad
    at 1 Hz on the knees), recomputed at 50 Hz. Modes: "impedance" (a JointState of
    positions: every state in lockstep, every 8th in realtime), "forward" (the same on
    joint_group_position_controller/commands), "relay" (τ = kp (q* − q) − kd q̇ as effort,
    every state: a 400 Hz torque loop)."""

    def __init__(self, ros, kd, lockstep):
        node = ros.node
        self.kd, self.lockstep = kd, lockstep
        self.pub = node.create_publisher(JointState, "joint_commands", COMMAND_QOS)
        self.pub_fwd = node.create_publisher(Float64MultiArray,
                                             "joint_group_position_controller/commands",
                                             COMMAND_QOS)
        self.subs = [node.create_subscription(JointState, "joint_states", self.on_state,
                                              STATE_QOS),
                     node.create_subscription(Odometry, "starleth/base_state", self.on_base,
                                              STATE_QOS)]
        self.mode = self.phase_ns = self.latest = self.q0 = self.held = None
        self.names = None
        self.states, self.z = [], []

    def targets(self, k):
        q = self.q0.copy()
        q[2::3] += 0.05 * np.sin(2 * np.pi * k * PERIOD_NS * 1e-9)
        return q

    def start(self, mode, phase_ns):
        self.mode, self.phase_ns = mode, phase_ns
        self.states, self.z = [], []
        if self.latest is not None and ns_of(self.latest.header.stamp) == phase_ns:
            self.on_state(self.latest)

    def on_base(self, msg):
        if self.phase_ns is not None and ns_of(msg.header.stamp) >= self.phase_ns:
            self.z.append(msg.pose.pose.position.z)

    def on_state(self, msg):
        self.latest = msg
        if self.q0 is None:
            self.q0, self.names = np.array(msg.position), list(msg.name)
        ns = ns_of(msg.header.stamp)
        if self.mode is None or ns < self.phase_ns:
            return
        k = (ns - self.phase_ns) // PERIOD_NS
        q, qd = np.array(msg.position), np.array(msg.velocity)
        if k % SLOW == 0 or self.held is None:
            self.held = self.targets(k)
        self.states.append((k, q, self.held))
        if self.mode == "relay":
            self.send(msg.header.stamp, effort=KP * (self.held - q) - self.kd * qd)
        elif self.lockstep or k % SLOW == 0:
            if self.mode == "forward":
                self.pub_fwd.publish(Float64MultiArray(data=list(self.held)))
            else:
                self.send(msg.header.stamp, position=self.held)

    def send(self, stamp, position=(), effort=()):
        m = JointState(name=self.names, position=list(position), effort=list(effort))
        m.header.stamp = stamp
        self.pub.publish(m)

    def error(self):
        """RMS of q − q* over the phase's states, and the states (k -> q)."""
        e = np.array([q - h for _, q, h in self.states[:STATES]])
        return float(np.sqrt(np.mean(e ** 2))), {k: q for k, q, _ in self.states[:STATES]}


@pytest.fixture(scope="module")
def ros():
    node = RosTestNode(DOMAIN_ID, "impedance_test", events=True)
    try:
        yield node
    finally:
        node.close()


def run_phase(ros, sim, ctl, mode, first, stand=True):
    """Pause, reset (not the first phase), start the controller's `mode`, resume; STATES
    states later: the phase's tracking error, states and lowest base height; stand: the
    base stayed at the standing height (within 3 cm) and the error is small."""
    if not first:
        ctl.mode = None          # no answer of the old mode to the reset state
        assert ros.call(SetBool, "/sim_node/pause", SetBool.Request(data=True)).success
        r = ros.call(Trigger, "/sim_node/reset", Trigger.Request())
        phase_ns = round(float(re.search(r"sim time ([0-9.]+)", r.message)[1]) * 1e9)
        assert ros.spin_until(lambda: ctl.latest is not None and
                              ns_of(ctl.latest.header.stamp) == phase_ns, 10.0, procs=[sim])
    else:
        assert ros.spin_until(lambda: ctl.latest is not None, START_TIMEOUT, procs=[sim]), \
            sim.log()[-2000:]
        phase_ns = ns_of(ctl.latest.header.stamp)
    ctl.start(mode, phase_ns)
    assert ros.call(SetBool, "/sim_node/pause", SetBool.Request(data=False)).success
    assert ros.spin_until(lambda: len(ctl.states) >= STATES, 60.0, procs=[sim]), \
        (mode, len(ctl.states), sim.log()[-2000:])
    err, states = ctl.error()
    z = np.array(ctl.z[:STATES])
    if stand:
        assert STARLETH_STANDING_HEIGHT - z.min() < 0.03, (mode, z.min(), z.max())
        assert z.max() < STARLETH_STANDING_HEIGHT + 1e-3 and err < 0.12, (mode, z.max(), err)
    return err, states, float(z.min())


def undelayed_run(preset, mode, kd):
    """{k: q} of TargetController's `mode` ("impedance" or "relay") answering every state
    at once, without delay, for a phase from the standing posture: in process, through
    sim_node's core (SimService, lockstep), deterministic."""
    sim = Simulator.from_preset(preset)
    q0, u0, _ = parse_initial_state("standing", sim)
    svc = SimService(sim, Settings(mode="lockstep", default_kp=KP, default_kd=kd), q0, u0)
    svc.reset()                   # as a phase after the first (the first: the same state)
    ctl = TargetController.__new__(TargetController)
    ctl.q0, names, out = sim.joint_positions().copy(), list(svc.joint_names), {}
    for k in range(STATES):
        q, qd = sim.joint_positions().copy(), sim.joint_velocities().copy()
        held = ctl.targets(k - k % SLOW)
        out[k] = q
        ok = svc.submit_joint_command(names, KP * (held - q) - kd * qd, svc.stamp_ns) \
            if mode == "relay" else \
            svc.submit_joint_command(names, [], svc.stamp_ns, position=held)
        assert ok[0] and svc.step() is not None, (k, ok)
    return out


def delay_added(delayed, undelayed):
    """RMS over the states and joints of q_delayed − q_undelayed, state by state: the
    tracking error the delay adds (the static sag and the lag both runs share cancel)."""
    common = sorted(set(delayed) & set(undelayed))
    assert len(common) >= 0.9 * STATES, len(common)
    return float(np.sqrt(np.mean([(delayed[k] - undelayed[k]) ** 2 for k in common])))


def target_shift_error():
    """What targets late by DELAY add to the error: DELAY x the RMS of q̇* (the 1 Hz sine of
    TargetController.targets on the 4 knees of 12 joints), over a phase's states."""
    t = np.arange(STATES) * PERIOD_NS * 1e-9
    rate = 0.05 * 2 * np.pi * np.cos(2 * np.pi * t)
    return DELAY * float(np.sqrt(np.mean(rate ** 2) * 4 / 12))


def set_parameter(ros, name, value):
    p = ParameterMsg(name=name)
    if isinstance(value, list):
        p.value.type = ParameterType.PARAMETER_DOUBLE_ARRAY
        p.value.double_array_value = value
    else:
        p.value.type = ParameterType.PARAMETER_DOUBLE
        p.value.double_value = value
    r = ros.call(SetParameters, "/sim_node/set_parameters",
                 SetParameters.Request(parameters=[p]))
    return r.results[0]


# (realtime: a wall-clock loop and the transport's delay: alone in `make test`'s pass 2)
@pytest.mark.parametrize("preset, mode", [
    ("HmJ", "lockstep"), ("Cm", "lockstep"),
    pytest.param("HmJ", "realtime", marks=pytest.mark.serial),
    pytest.param("Cm", "realtime", marks=pytest.mark.serial)])
def test_50hz_position_targets_hold_the_stand(ros, tmp_path, preset, mode):
    """Four phases of 0.8 s from the standing posture: position targets (impedance) and
    their 400 Hz torque relay, each with every command a control period late
    (command_delay 2.5 ms, a ROS hop and a loop) and without (command_delay set at run
    time between them).

    The metric, the error the latency adds: the RMS of q − q* is 0.058 rad in every phase,
    nearly all of it the static sag under gravity (kp 80) and the lag behind the sine that
    all phases share (with the delay the relay's is 0.2 % larger than the impedance's:
    measurable in lockstep, no margin), and the RMS about its mean keeps the lag. Each run
    against the same controller answering every state at once, without delay (in process,
    through SimService: undelayed_run; the node's undelayed lockstep runs equal it bit for
    bit), state by state, keeps only what the latency changes: the delay, and in realtime
    also a command that missed its tick (the transport's latency; printed).

    Physics: (1) the impedance's targets come DELAY late, its law still acts at every
    physics step on the current state: the error added is the targets' time shift,
    DELAY·|q̇*| (target_shift_error, 0.31 mrad; lockstep: within 0.8 to 1.5 of it, measured
    1.16). (2) The relay's torque comes DELAY late as a whole: its feedback loop closes
    late, losing ωd·DELAY of phase at the stand's ringing (ωd ≈ 24 rad/s: the legs ring at
    3.6-3.9 Hz after the reset, measured from the runs' spectra), a change of order
    sag·ωd·DELAY = 0.056 rad · 0.06 = 3.4 mrad at the sag transient after the reset (which
    decays within about 0.3 s of the 0.8 s), several times the targets' shift, to which the
    relay's loop adds nothing at 1 Hz (a delayed loop of unit gain tracks a slow ramp with
    the lag of the undelayed one). Asserted: the relay's added error at least twice the
    impedance's (measured in lockstep: HmJ 1.190 / 0.361 mrad, Cm 1.259 / 0.361, ratios
    3.3 and 3.5; realtime, on a 2-core host loaded by other work, 2.8 to 3.8). Without the
    delay the relay equals the law up to the damper's discretisation (printed: errors
    within 0.2 %).
    (long: four phases of one node's run, each compared with the in-process reference)"""
    kd = 2.0
    lockstep = mode == "lockstep"
    bag = tmp_path / "run.mcap"
    sim = NodeProcess("starleth_sim.ros.sim_node", str(tmp_path / "sim.log"), DOMAIN_ID,
                      physics=preset, mode=mode, start_paused=True, default_kp=KP,
                      default_kd=kd, command_delay=DELAY if lockstep else 0.0, record=str(bag),
                      contact_markers_rate=0.0, tf_rate=0.0)
    ctl = TargetController(ros, kd, lockstep)
    try:
        errors, states, low = {}, {}, {}

        def phase(key, mode, first=False, stand=True):
            errors[key], states[key], low[key] = run_phase(ros, sim, ctl, mode, first, stand)

        # lockstep: the delayed phases first, the recording's start (replayed below) the
        # delayed impedance run; realtime: the undelayed first, where the late ticks of the
        # node's start (a late command adds its tick to the delay) fall on phases that are
        # not asserted. The relay: in realtime its torque also comes late at times.
        order = (("delayed", DELAY), ("", 0.0)) if lockstep else (("", 0.0), ("delayed", DELAY))
        for i, (suffix, delay) in enumerate(order):
            if i:
                assert set_parameter(ros, "command_delay", delay).successful
            phase(f"impedance {suffix}".strip(), "impedance", first=not i)
            phase(f"relay {suffix}".strip(), "relay", stand=lockstep)
        if preset == "HmJ" and lockstep:
            phase("forward", "forward")
            # bad input, a negative gain, a delay out of range: refused; the simulator goes on
            ctl.send(ctl.latest.header.stamp, position=[float("inf")] + [0.0] * 11)
            result = set_parameter(ros, "default_kp", -1.0)
            assert not result.successful and "default_kp" in result.reason
            assert set_parameter(ros, "default_kd", 1.5).successful
            assert set_parameter(ros, "default_kp", [70.0] * 12).successful
            assert not set_parameter(ros, "default_kp", [70.0] * 11).successful
            result = set_parameter(ros, "command_delay", 0.5)
            assert not result.successful and "command_delay" in result.reason
        # the latency's error: each run against the same mode answered in process at once
        ref = {m: undelayed_run(preset, m, kd) for m in ("impedance", "relay")}
        added = {key: delay_added(states[key], ref[key.split()[0]]) for key in
                 ("impedance delayed", "relay delayed", "impedance", "relay")}
        print(f"{preset} {mode}: RMS tracking error (rad) of 50 Hz position targets and of "
              f"their 400 Hz torque relay: " +
              ", ".join(f"{k} {v:.5f}" for k, v in errors.items()) + "; lowest base (m): " +
              ", ".join(f"{k} {v:.4f}" for k, v in low.items()) +
              "; added by the latency (mrad; a command delay of "
              f"{DELAY * 1e3:g} ms, and the transport's in realtime): " +
              ", ".join(f"{k} {v * 1e3:.3f}" for k, v in added.items()) +
              f" (ratio {added['relay delayed'] / added['impedance delayed']:.2f}; the "
              f"targets' shift {target_shift_error() * 1e3:.3f})")
        assert added["relay delayed"] > 2.0 * added["impedance delayed"], added
        impedance, relay = states["impedance"], states["relay"]
        common = sorted(set(impedance) & set(relay))
        same = all(np.array_equal(impedance[k], relay[k]) for k in common)
        if lockstep:
            # without the delay, the node's runs are the in-process ones, bit for bit
            assert added["impedance"] == added["relay"] == 0.0, added
            assert 0.8 < added["impedance delayed"] / target_shift_error() < 1.5, added
            assert len(common) == STATES
            # the relay's torque is the law with the damper at the state the simulator
            # starts the step from (explicit); the impedance's damper is implicit (and on Cm
            # the law runs at 800 Hz): the runs differ
            assert not same
            if preset == "HmJ":
                assert all(np.array_equal(impedance[k], states["forward"][k])
                           for k in common)
        # realtime without the delay: no assertion on the relay's error. On an idle host
        # its answer lands within the 2.5 ms tick, so it acts on the same step as the law
        # would and the two errors agree to 0.2 % (measured 2026-12-02: HmJ 0.05801 /
        # 0.05809 rad, Cm 0.05851 / 0.05839); only a loaded host makes it late (4 falls in
        # 6 runs at load 9, the impedance commands none; measured before the damper was
        # implicit). The comparison is printed above.
        assert ros.call(SetBool, "/sim_node/pause", SetBool.Request(data=True)).success
    finally:
        for s in ctl.subs:
            ros.node.destroy_subscription(s)
        code = sim.stop()
    assert code == 0, sim.log()[-3000:]
    s = sim.summary()
    assert s["impedance_commands"] > 0 and s["lockstep_timeouts"] == 0, s
    if preset == "HmJ" and lockstep:
        assert s["commands_rejected"] == 1 and s["gains_rejected"] == 2, s
        assert "infinite position for LF_HAA" in sim.log()
    else:
        assert s["commands_rejected"] == 0, s
    assert "command delay 1 control period (2.5 ms)" in sim.log()
    # the recording replays the first impedance phase (lockstep: the delayed one) bit for
    # bit (the explicit torques and the implicit dampers of every physics step,
    # Simulator.step_applied re-solving them; the torques applied are those of the commands
    # in effect, after their delay)
    rec = load_recording(str(bag))
    assert rec.applied is not None and rec.applied.shape[1] == (1 if preset == "HmJ" else 2)
    assert rec.replay is not None and rec.replay.shape[1:] == (rec.applied.shape[1], 24)
    c = compare_exact(rec, resimulate(rec, steps=STATES - 20))
    assert c.identical, (c.first_step, c.first_quantities)
    # the applied torques replayed as torques (bags of before held only these): close but
    # not exact, as a damped joint's torque is that of the step's end rate, and the
    # /joint_states effort (the period's first physics step) no closer
    for replay in (dataclasses.replace(rec, replay=None), dataclasses.replace(rec, applied=None)):
        old = compare_exact(rec, resimulate(replay, steps=STATES - 20))
        assert not old.identical, preset
        if preset == "HmJ":     # (one physics step: the same torques, other round-off)
            assert old.first_quantities["joint_positions"] < 1e-6, old.first_quantities


def position_controller_example():
    """The 50 Hz position controller of doc/controllers.md (its second python block)."""
    blocks = controllers_page_blocks()
    assert len(blocks) == 3 and "squat" in blocks[1], blocks
    return blocks[1]


def test_position_controller_example_squats_and_stands(ros, tmp_path):
    """doc/controllers.md's 50 Hz position controller as written (20 lines), beside `sim_node
    --ros-args -p mode:=lockstep`, for 2.5 s of sim time: every state answered, the base
    goes down with the squat (the targets are tracked) and back up, and never falls."""
    code = position_controller_example()
    assert code.count("\n") <= 20
    t, z, s = run_beside_sim_node(ros, tmp_path, code, DOMAIN_ID, 2.5)
    low = z[(t > 0.8) & (t < 1.2)].min()     # the deepest squat at t = 1 s
    up = z[(t > 1.9) & (t < 2.1)].max()      # standing again at t = 2 s
    print(f"position controller example: base {z.min():.4f} to {z.max():.4f} m, at the "
          f"bottom of the squat {low:.4f} m, back up {up:.4f} m")
    assert STARLETH_STANDING_HEIGHT - 0.03 < up and low < up - 0.02 and z.min() > 0.3
    assert s["lockstep_timeouts"] == 0 and s["stale_commands"] == 0, s
    assert s["impedance_commands"] >= s["steps"] > 0, s   # every state: position targets
