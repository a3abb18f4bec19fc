"""bench_floor, the floor of the real loop: it is a fair floor only if it sends what the nodes
send and computes what they compute. Checked against sim_node's state bundle and
controller_node's answers over a closed-loop stand and trot, and over DDS in one process.
Speed is the benchmark's business, not a test's."""
import os
import time
import types

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

DOMAIN_RANGE = (180, 18)              # first, span (conftest._free_ros_domain)
DOMAIN_ID = 180 + os.getpid() % 18


@pytest.fixture
def ctx():
    c = rclpy.Context()
    rclpy.init(context=c, domain_id=DOMAIN_ID)
    yield c
    rclpy.try_shutdown(context=c)


def test_floor_sends_the_nodes_bytes_and_answers_as_controller_node(ctx):
    """Over 400 closed-loop steps (stand, then trot from 0.5 s): the floor's bundle bytes
    equal sim_node's (StatePublisher.publish_bundle) for the same state, and the floor
    controller's torques equal controller_node's answer (_on_bundle_cdr) to those bytes, bit
    for bit."""
    from starleth_controller.controller_node import ControllerNode
    from starleth_sim.ros.sim_node import SimNode
    from starleth_sim.ros.state_io import base_values, joint_values
    from starleth_sim.tools.bench.controllers import TROT_AT, TROT_SPEED
    from starleth_sim.tools.bench.floor import FloorController, bundle_bytes
    sim_node = SimNode(context=ctx, parameter_overrides={"mode": "lockstep"})
    ctl_node = ControllerNode(context=ctx, parameter_overrides={"mode": "stand"})
    helper = rclpy.create_node("floor_test", context=ctx)
    try:
        floor = FloorController(helper)
        sent, answers = [], []
        pubs = sim_node.output.pubs
        _, *rest = pubs["state_bundle"]
        pubs["state_bundle"] = (types.SimpleNamespace(publish=sent.append), *rest)
        ctl_node._publish = lambda sec_nsec, effort: answers.append(
            (tuple(sec_nsec), np.frombuffer(effort, dtype=float).copy()))
        ctl_node._vel = (TROT_SPEED, 0.0, 0.0)
        svc, sim = sim_node.service, sim_node.sim
        modes = set()
        for k in range(400):
            sec, nsec = divmod(svc.stamp_ns, 1_000_000_000)
            sim_node.publisher.publish_bundle(sec, nsec, base_values(sim), joint_values(sim),
                                              sim.contact_forces())
            data = bundle_bytes(sim_node.publisher.bundle_cdr, sim, svc.stamp_ns)
            assert data == sent[-1], f"step {k}: the bundle differs from sim_node's"
            if sec + nsec * 1e-9 >= TROT_AT:
                ctl_node._mode = "trot"
            ctl_node._on_bundle_cdr(data)
            f_sec, f_nsec, tau = floor.torques(data)
            assert answers[-1][0] == (f_sec, f_nsec) == (sec, nsec)
            assert tau.tobytes() == answers[-1][1].tobytes(), f"step {k}"
            modes.add(floor.controller.mode)
            svc.submit_ordered_joint_command(tau, svc.stamp_ns)
            assert svc.step() is not None
        assert modes == {"stand", "trot"}
        assert sim.base_state()["position"][2] > 0.3        # on its feet
        assert sim.base_state()["position"][0] > 0.05       # and trotting forward
    finally:
        helper.destroy_node()
        ctl_node.destroy_node()
        sim_node.destroy()


def test_floor_loop_runs_over_dds_one_answer_per_state(ctx):
    """The floor's two sides on one executor: every state is answered once, in order
    (no command rejected, the stamps one period apart), and the robot trots."""
    from starleth_interface.ros_helpers import make_executor
    from starleth_sim.tools.bench.floor import FloorController, FloorSim
    node = rclpy.create_node("floor_loop_test", context=ctx)
    ex, _ = make_executor("events", ctx)
    ex.add_node(node)
    try:
        floor_sim, ctl = FloorSim(node), FloorController(node)
        ctl.running = True
        t_end = time.monotonic() + 90
        while not (ctl.sub.get_publisher_count() and floor_sim.sub.get_publisher_count()):
            assert time.monotonic() < t_end, "the floor's topics did not match"
            ex.spin_once(timeout_sec=0.05)
        floor_sim.start()
        while ctl.commands < 600 and time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.05)
        assert ctl.commands >= 600, ctl.commands
        assert floor_sim.rejected == 0
        assert floor_sim.k in (ctl.commands, ctl.commands - 1)
        assert floor_sim.sim.t == pytest.approx(floor_sim.k * 0.0025, abs=1e-9)
        assert ctl.controller.mode == "trot"
        p = floor_sim.sim.base_state()["position"]
        assert p[2] > 0.3 and p[0] > 0.05, p
    finally:
        ex.shutdown()
        node.destroy_node()
