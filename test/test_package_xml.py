"""package.xml declares what the installed package needs at run time, no more: every ROS
package the code imports (top-level, local and optional imports alike: rosdep installs them
whether or not the import is guarded) and every package the installed launch file needs is an
``exec_depend``, and every ``exec_depend`` is one of those. Python libraries that come from
pip (requirements.txt) are listed here with the reason they are not in package.xml."""
import ast
import os
import sys
import xml.etree.ElementTree as ET

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGES = ("starleth_sim", "starleth_controller", "starleth_interface")
LAUNCH_FILE = os.path.join(ROOT, "launch", "starleth.launch.xml")

#: Python modules whose rosdep key differs from the module name
ROSDEP_KEYS = {"numpy": "python3-numpy", "yaml": "python3-yaml",
               "matplotlib": "python3-matplotlib", "PIL": "python3-pil"}

#: ROS packages imported under their own name that are not message / service packages
ROS_LIBRARIES = {"rclpy", "rcl_interfaces", "ament_index_python"}

#: Python modules from pip (requirements.txt, setup.py's install_requires / extras), not
#: declared in package.xml: their rosdep keys are missing or not uniform across platforms
PIP_ONLY = {
    "pinocchio": "pip wheel `pin` (the ROS package is built differently per distribution)",
    "numba": "pip: no python3-numba key on every platform rosdep supports",
    "mcap": "pip `mcap`: no rosdep key",
    "mcap_ros2": "pip `mcap-ros2-support`: no rosdep key",
    "meshcat": "pip: starleth-view only, no rosdep key",
    "lz4": "optional (bag compression in tools/bag.py), pip",
    "zstandard": "optional (bag compression in tools/bag.py), pip",
    "pyarrow": "optional extra `parquet` (starleth-sweep)",
    "ray": "optional extra `ray` (starleth-sweep / starleth-eval --ray)",
    "mujoco": "optional: starleth-bench's comparison only",
    "foxglove": "optional extra `live` (foxglove-sdk: sim_node's live_view), pip only",
    "websockets": "optional extra `live` (starleth_sim.tools.live_log, a protocol client)",
}

#: the packages each element of the launch file needs: the XML front end (launch_xml) and the
#: launch core for the file itself, `ros2 launch` to run it; launch_ros for its <node> actions
LAUNCH_TAGS = {
    "launch": {"launch", "launch_xml", "ros2launch"},
    "arg": {"launch"},
    "node": {"launch_ros"},
    "param": {"launch_ros"},
    "remap": {"launch_ros"},
}


def imported_modules():
    """{top-level module: a file importing it} over every import of the three packages."""
    found = {}
    for pkg in PACKAGES:
        for dirpath, _, files in os.walk(os.path.join(ROOT, pkg)):
            for name in files:
                if not name.endswith(".py"):
                    continue
                path = os.path.join(dirpath, name)
                with open(path) as f:
                    tree = ast.parse(f.read(), path)
                for node in ast.walk(tree):
                    if isinstance(node, ast.Import):
                        mods = [a.name for a in node.names]
                    elif isinstance(node, ast.ImportFrom) and node.level == 0:
                        mods = [node.module]
                    else:
                        continue
                    for m in mods:
                        found.setdefault(m.split(".")[0], os.path.relpath(path, ROOT))
    return found


def exec_depends():
    root = ET.parse(os.path.join(ROOT, "package.xml")).getroot()
    return {e.text.strip() for e in root.iter("exec_depend")}


def code_dependencies():
    """{rosdep key: why} for the imports; AssertionError for an import not classified."""
    need, unknown = {}, []
    for mod, where in imported_modules().items():
        if mod in sys.stdlib_module_names or mod in PACKAGES or mod in PIP_ONLY:
            continue
        key = ROSDEP_KEYS.get(mod, mod)
        if key == mod and not _is_ros_package(mod):
            unknown.append(f"{mod} ({where})")
            continue
        need[key] = f"imported in {where}"
    assert not unknown, ("imports that are neither ROS packages nor listed in ROSDEP_KEYS / "
                         f"PIP_ONLY: {', '.join(sorted(unknown))}")
    return need


def _is_ros_package(mod):
    """A ROS package by name: the message / service packages, and the ROS client libraries
    this code uses (checked by name: the test machine need not have them all installed)."""
    return mod.endswith(("_msgs", "_srvs")) or mod in ROS_LIBRARIES


def launch_dependencies():
    tree = ET.parse(LAUNCH_FILE)
    need, unknown = {}, []
    for el in tree.getroot().iter():
        if el.tag not in LAUNCH_TAGS:
            unknown.append(el.tag)
            continue
        for key in LAUNCH_TAGS[el.tag]:
            need[key] = f"<{el.tag}> in launch/starleth.launch.xml"
    assert not unknown, f"launch file elements not in LAUNCH_TAGS: {sorted(set(unknown))}"
    return need


def test_every_imported_ros_package_and_the_launch_files_are_exec_depends():
    need = {**code_dependencies(), **launch_dependencies()}
    missing = sorted(f"{k} ({why})" for k, why in need.items() if k not in exec_depends())
    assert not missing, f"missing <exec_depend> in package.xml: {', '.join(missing)}"


def test_every_exec_depend_is_used():
    need = {**code_dependencies(), **launch_dependencies()}
    unused = sorted(exec_depends() - set(need))
    assert not unused, f"<exec_depend> that nothing imports or launches: {unused}"


def test_the_classification_sees_the_imports_it_is_about():
    """The walk finds the optional imports (inside functions, under try) it must see."""
    mods = imported_modules()
    for m in ("tf2_msgs", "visualization_msgs", "ament_index_python", "rclpy", "pinocchio"):
        assert m in mods, m
    assert code_dependencies()["tf2_msgs"].startswith("imported in starleth_sim/ros/")
