"""Strict inputs of the two nodes (issue #35, item 3), the way a user hits them: a mistyped
parameter name on the command line or in a parameter file is one line naming it and the
closest known name, exit status 2 (rclpy alone would ignore it); ROS's own parameters stay
accepted; a parameter set at runtime under an unknown name is refused (by rclpy); the physics
core's Python logging comes out in the node's log format. (Partial joint commands and the
throttling per problem: test_sim_service.py and test_sim_node.py.)"""
import logging
import os
import subprocess
import sys
import time

import pytest

rclpy = pytest.importorskip("rclpy")

from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter
from repo_root import ROOT
from robot_cases import ankle_urdf
from ros_test_nodes import NodeProcess

from starleth_controller.node_parameters import PARAMETERS
from starleth_interface.ros_helpers import (
    RosLogHandler,
    UnknownParameterError,
    check_parameter_names,
    declare_parameters,
    route_python_logging,
)
from starleth_sim.ros.parameters import SIM_NODE_PARAMETERS
from starleth_sim.tools.common.discovery import local_discovery_env

DOMAIN_RANGE = (160, 20)      # first, span (conftest._free_ros_domain)
DOMAIN_ID = 160 + os.getpid() % 20


def run_node(module, *ros_args):
    """`python -m module --ros-args ...` to its end: (exit status, its output)."""
    env = dict(local_discovery_env(), ROS_DOMAIN_ID=str(DOMAIN_ID), PYTHONPATH=ROOT,
               RCUTILS_COLORIZED_OUTPUT="0")
    r = subprocess.run([sys.executable, "-m", module, "--ros-args", *ros_args],
                       capture_output=True, text=True, timeout=120, env=env, cwd=ROOT)
    return r.returncode, r.stdout + r.stderr


@pytest.mark.parametrize("module, args, line", [
    ("starleth_sim.ros.sim_node", ["-p", "recrod:=x.mcap"],
     "sim_node: unknown parameter 'recrod' (did you mean 'record'?)"),
    # ROS's own parameters pass; only the unknown ones are named, each with its match
    ("starleth_sim.ros.sim_node", ["-p", "use_sim_time:=true", "-p",
                                   "qos_overrides./clock.publisher.depth:=5", "-p",
                                   "mdoe:=lockstep", "-p", "zzz:=1"],
     "sim_node: unknown parameters 'mdoe' (did you mean 'mode'?), 'zzz'"),
    ("starleth_controller.controller_node", ["-p", "mdoe:=trot", "-p", "use_sim_time:=true"],
     "controller_node: unknown parameter 'mdoe' (did you mean 'mode'?)"),
])
def test_an_unknown_parameter_is_one_line_and_exit_2(module, args, line):
    rc, out = run_node(module, *args)
    assert (rc, out.strip()) == (2, line)


def test_a_robot_the_controller_cannot_drive_is_one_line_and_exit_2(tmp_path):
    """controller_node -p robot:=... with a robot that is not four 3-joint legs (StarlETH with
    an ankle on one leg: 13 joints, 3 legs), or that is not in the library."""
    path = ankle_urdf(tmp_path)
    rc, out = run_node("starleth_controller.controller_node", "-p", f"robot:={path}")
    assert (rc, out.strip()) == (2, f"controller_node: configuration error: {path}: not a "
                                    "four-legged robot of 3-joint legs the controller drives: "
                                    "13 moving joints, 3 3-joint legs with a foot")
    rc, out = run_node("starleth_controller.controller_node", "-p", "robot:=robodog")
    assert rc == 2 and len(out.strip().splitlines()) == 1 and "unknown robot 'robodog'" in out


def test_an_unknown_key_of_a_parameter_file_is_one_line_and_exit_2(tmp_path):
    f = tmp_path / "my_sim.yaml"
    f.write_text("/**:\n  ros__parameters:\n    use_sim_time: true\n"
                 "sim_node:\n  ros__parameters:\n    mode: lockstep\n"
                 "    real_time_factr: 2.0\n")
    rc, out = run_node("starleth_sim.ros.sim_node", "--params-file", str(f))
    assert (rc, out.strip()) == (2, "sim_node: unknown parameter 'real_time_factr' (did you "
                                    "mean 'real_time_factor'?)")


@pytest.fixture
def context():
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN_ID)
    yield ctx
    rclpy.try_shutdown(context=ctx)


def test_ros_parameters_and_the_schemas_are_known(context):
    """Every name of the schema and ROS's own (use_sim_time, start_type_description_service,
    qos_overrides.*) pass the check; an unknown one does not, in either schema."""
    for specs in (SIM_NODE_PARAMETERS, PARAMETERS):
        good = {p.name: p.default for p in specs}
        good.update({"use_sim_time": True, "start_type_description_service": False,
                     "qos_overrides./clock.publisher.depth": 5})
        node = Node("strict_check", context=context, parameter_overrides=[
            Parameter(k, value=v) for k, v in good.items()])
        declare_parameters(node, specs)
        check_parameter_names(node, specs)
        node.destroy_node()
        node = Node("strict_check", context=context,
                    parameter_overrides=[Parameter("warn_throttle_perod", value=1.0)])
        declare_parameters(node, specs)
        with pytest.raises(UnknownParameterError, match=r"^unknown parameter "
                           r"'warn_throttle_perod' \(did you mean 'warn_throttle_period'\?\)$"):
            check_parameter_names(node, specs)
        node.destroy_node()


def test_setting_an_unknown_parameter_at_runtime_is_refused(context):
    """`ros2 param set /controller_node recrod x` (the SetParameters service): rclpy refuses
    a name the node has not declared; the node goes on and takes the other, valid one."""
    from rclpy.executors import SingleThreadedExecutor
    node = Node("strict_runtime", context=context)
    declare_parameters(node, PARAMETERS)
    client_node = Node("strict_runtime_client", context=context)
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(node)
    ex.add_node(client_node)
    try:
        cli = client_node.create_client(SetParameters, "/strict_runtime/set_parameters")
        deadline = time.monotonic() + 10
        while not cli.service_is_ready() and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        value = ParameterType.PARAMETER_STRING
        req = SetParameters.Request(parameters=[ParameterMsg(name="mdoe"),
                                                ParameterMsg(name="mode")])
        req.parameters[0].value.type = req.parameters[1].value.type = value
        req.parameters[0].value.string_value = req.parameters[1].value.string_value = "trot"
        fut = cli.call_async(req)
        ex.spin_until_future_complete(fut, timeout_sec=10)
        bad, good = fut.result().results
        # (rclpy's reason does not name the parameter: "... undeclared parameter(s): []")
        assert not bad.successful and "undeclared parameter" in bad.reason
        assert good.successful and node.get_parameter("mode").value == "trot"
    finally:
        ex.shutdown(timeout_sec=0.1)
        node.destroy_node()
        client_node.destroy_node()


class FakeRosLogger:
    def __init__(self, level=20):
        self.lines, self.level = [], level

    def get_effective_level(self):
        return self.level

    def debug(self, m):
        self.lines.append(("DEBUG", m))

    def info(self, m):
        self.lines.append(("INFO", m))

    def warning(self, m):
        self.lines.append(("WARN", m))

    def error(self, m):
        self.lines.append(("ERROR", m))

    def fatal(self, m):
        self.lines.append(("FATAL", m))


def test_python_logging_goes_to_the_node_logger_with_its_level():
    ros = FakeRosLogger(level=20)
    restore = route_python_logging(ros, ("starleth_test_route",))
    try:
        log = logging.getLogger("starleth_test_route.physics")   # a child logger
        log.debug("hidden")                      # below the node logger's level
        log.info("i %d", 1)
        log.warning("w")
        log.error("e")
        log.critical("c")
        assert ros.lines == [("INFO", "i 1"), ("WARN", "w"), ("ERROR", "e"), ("FATAL", "c")]
        # a second node of this process: the logger stays with the first
        other = FakeRosLogger()
        restore_other = route_python_logging(other, ("starleth_test_route",))
        log.warning("again")
        assert other.lines == [] and ros.lines[-1] == ("WARN", "again")
        restore_other()
    finally:
        restore()
    assert not any(isinstance(h, RosLogHandler)
                   for h in logging.getLogger("starleth_test_route").handlers)


def test_the_physics_warning_is_in_the_node_log_format(tmp_path):
    """A prox iteration capped at one iteration does not converge on the first step (the
    warm-up in the node's constructor): the physics core's warning comes out as a line of
    sim_node's log, `[WARN] [<time>] [sim_node]: t=0.0025 s: prox iteration did not
    converge ...`, not as a bare line on stderr."""
    sim = NodeProcess("starleth_sim.ros.sim_node", str(tmp_path / "sim.log"), DOMAIN_ID,
                      mode="lockstep", physics_overrides="{max_iterations: 1, tol_rel: "
                      "1.0e-12, tol_abs: 1.0e-12}")
    try:
        deadline = time.monotonic() + 60
        while "ready" not in sim.log() and sim.alive() and time.monotonic() < deadline:
            time.sleep(0.1)
    finally:
        sim.stop()
    lines = [ln for ln in sim.log().splitlines() if "prox iteration did not converge" in ln]
    assert lines, sim.log()
    assert lines[0].startswith("[WARN] [") and \
        "] [sim_node]: t=0.0025 s: prox iteration did not converge" in lines[0], lines
