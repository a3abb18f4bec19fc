import os
import sys

import pytest

# The tests live in one folder per layer (physics, controller, ros, tools, rules), their
# shared helpers in support/ (robot_cases, ros_test_nodes, repo_root, ...). Every folder goes
# on sys.path, so that a helper, or a test module another one borrows from (test_bitexact's
# reference states, test_analysis's runs), is imported by its name from any folder.
HERE = os.path.dirname(os.path.abspath(__file__))
for _folder in sorted(os.listdir(HERE)):
    if os.path.isdir(os.path.join(HERE, _folder)) and not _folder.startswith(("_", ".")):
        sys.path.insert(0, os.path.join(HERE, _folder))


@pytest.fixture(scope="session")
def starleth_hmj():
    from starleth_sim import Simulator
    return Simulator.from_preset("HmJ")


# How `make test` runs the suite on two cores (pytest-xdist, `-n 2 --ros-apart`):
# * the tests of ROS_MODULES start ROS 2 nodes or other child processes: they run one after
#   another on one worker (one unit of work, "ros": two such tests at once would share the
#   CPU their nodes need and the ROS graph), while the other worker runs the CPU-bound tests
#   (physics, controller, tools) file by file (a file is a unit, so its module fixtures run
#   once);
# * the tests marked `serial` in their files (they measure rates, deadlines or latencies,
#   or drive a browser) run afterwards, alone: a worker beside them would take the CPU their
#   timing depends on.
# The ros unit is collected first and the slowest files next (SLOW_FIRST), so that each
# worker starts a long unit first and the run does not end on one long file started late.
# (xdist's own --dist loadgroup would do the grouping, but with pytest 9 its group marks
# no longer reach the scheduler, hence the scheduler here.)
ROS_MODULES = {
    "test_compile_notice", "test_controller_node", "test_impedance_ros", "test_live_view",
    "test_realtime_start", "test_recording_faults", "test_replay", "test_robot_nodes",
    "test_ros2_control",
    "test_ros_conventions", "test_sim_node", "test_sim_node_faults", "test_sim_time",
    "test_strict_inputs", "test_tf", "test_tf_publishing",
}
# (test_analysis, test_view, test_cdr and test_sim_service start no nodes: they write and
# read bags or serialise messages; nor do test_recording (its recorders write bags, from
# writer processes too) and test_install_layout (it builds the package and runs what it
# installed); test_compile_notice starts none either, but its watcher looks every 0.05 s,
# which the CPU-bound worker beside it could delay)
SLOW_FIRST = ("test_evaluation", "test_analysis", "test_precompile", "test_sweep",
              "test_coordinates", "test_controller", "test_crafted_bags", "test_install_layout")


def pytest_addoption(parser):
    parser.addoption("--ros-apart", action="store_true",
                     help="with -n: the tests of conftest.ROS_MODULES one after another on "
                          "one worker, the other files each as a unit (see conftest.py)")


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "serial: measures rates, deadlines or latencies, or drives a browser: "
                   "`make test` runs it after the others, alone (see conftest.py)")
    if not hasattr(config, "workerinput"):      # once, in the process that started pytest
        _require_rclpy()


#: set to 1 to run without ROS 2 on purpose (the physics, controller and tool tests): the
#: test modules that need rclpy are then skipped instead of failing the run
ALLOW_NO_ROS = "STARLETH_ALLOW_NO_ROS"


def _require_rclpy():
    """A missing or broken rclpy fails the run with one line: the ROS tests (test/ros and
    the tools' tests on recorded bags) skip without it, and a broken ROS install would pass
    by skipping them. STARLETH_ALLOW_NO_ROS=1 allows it (they skip, with their reason)."""
    if os.environ.get(ALLOW_NO_ROS) == "1":
        return
    try:
        import rclpy  # noqa: F401
    except ImportError as e:
        raise pytest.UsageError(
            f"rclpy cannot be imported ({e}): the ROS tests would be skipped. Install ROS 2's "
            f"Python packages (`make venv`), or set {ALLOW_NO_ROS}=1 to run without them.") from e


def _module_of(nodeid: str) -> str:
    return os.path.splitext(os.path.basename(nodeid.split("::", 1)[0]))[0]


def pytest_xdist_make_scheduler(config, log):
    """With --ros-apart: xdist's load-scope scheduling, a scope being "ros" for the tests of
    ROS_MODULES and the file for the others, in collection order."""
    if not config.getoption("ros_apart"):
        return None
    from xdist.scheduler import LoadScopeScheduling  # deferred: only under pytest-xdist

    class RosApartScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid):
            return "ros" if _module_of(nodeid) in ROS_MODULES else nodeid.split("::", 1)[0]

    config.option.loadscopereorder = False
    return RosApartScheduling(config, log)


def pytest_collection_modifyitems(items):
    def rank(item):
        mod = _module_of(item.nodeid)
        if mod in ROS_MODULES:
            return 0
        return 1 + SLOW_FIRST.index(mod) if mod in SLOW_FIRST else 1 + len(SLOW_FIRST)
    items.sort(key=rank)       # stable: the order within a rank is the collection's


#: DOMAIN_RANGE -> the free domain chosen for the modules with that range, in this process
_DOMAINS = {}


@pytest.fixture(scope="module", autouse=True)
def _free_ros_domain(request):
    """A test module that sets DOMAIN_RANGE = (first, span) runs its ROS nodes on a domain of
    that range on which no other process runs nodes (ros_test_nodes.free_domain: a leftover
    node of another run there would answer or disturb them): its DOMAIN_ID is set here,
    before its own fixtures and tests. The ranges of every collected module are probed at
    once, when the first of them starts (one wait of 1.5 s per process, not one per module);
    the modules of one range share its domain, one after another."""
    span = getattr(request.module, "DOMAIN_RANGE", None)
    if span is None:
        return
    span = tuple(span)
    if span not in _DOMAINS:
        from ros_test_nodes import domain_candidates, free_domains
        spans = {span} | {tuple(m.DOMAIN_RANGE) for m in
                          {getattr(item, "module", None) for item in request.session.items}
                          if hasattr(m, "DOMAIN_RANGE")}
        spans = sorted(s for s in spans if s not in _DOMAINS)
        _DOMAINS.update(zip(spans, free_domains([domain_candidates(*s) for s in spans]),
                            strict=True))
    request.module.DOMAIN_ID = _DOMAINS[span]
