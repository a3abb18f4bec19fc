import os
import sys

import pytest

# make helper modules in test/ (e.g. pin_pgs_reference) importable
sys.path.insert(0, os.path.dirname(__file__))


@pytest.fixture(scope="session")
def starleth_hmj():
    from starleth_sim import Simulator
    return Simulator.from_preset("HmJ")


# Tests that start ROS 2 nodes or other processes with deadlines, measure rates, or render in
# a browser run one at a time (`make test` runs them after the others, on their own): a second
# pytest worker beside them would take the CPU their timing depends on. The rest (physics,
# controller, tools) is CPU-bound without deadlines and runs on two workers (pytest-xdist).
SERIAL_MODULES = {
    "test_analysis", "test_cdr", "test_compile_notice", "test_controller_node",
    "test_impedance_ros",
    "test_install_layout",
    "test_recording", "test_recording_faults", "test_replay", "test_ros_conventions",
    "test_sim_node", "test_sim_node_faults",
    "test_sim_service", "test_sim_time", "test_strict_inputs", "test_tf", "test_view",
}


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "serial: starts ROS nodes or processes with deadlines; run alone "
                   "(conftest.SERIAL_MODULES)")


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.module.__name__ in SERIAL_MODULES:
            item.add_marker(pytest.mark.serial)


@pytest.fixture(scope="module", autouse=True)
def _free_ros_domain(request):
    """A test module that sets DOMAIN_RANGE = (first, span) runs its ROS nodes on a domain of
    that range on which no other process runs nodes (ros_test_nodes.free_domain: a leftover
    node of another run there would answer or disturb them): its DOMAIN_ID is set here,
    before its own fixtures and tests."""
    span = getattr(request.module, "DOMAIN_RANGE", None)
    if span is not None:
        from ros_test_nodes import domain_candidates, free_domain
        request.module.DOMAIN_ID = free_domain(domain_candidates(*span))
