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
    "test_analysis", "test_cdr", "test_controller_node", "test_install_layout",
    "test_recording", "test_replay", "test_ros_conventions", "test_sim_node",
    "test_sim_service", "test_tf", "test_view",
}


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "serial: starts ROS nodes or processes with deadlines; run alone "
                   "(conftest.SERIAL_MODULES)")


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.module.__name__ in SERIAL_MODULES:
            item.add_marker(pytest.mark.serial)
