"""package.xml declares what the installed package needs at run time, no more: every ROS
package the code imports (top-level, local and optional imports alike: rosdep installs them
whether or not the import is guarded) and every package the installed launch files need is an
``exec_depend`` (for the ros2_control launch file: ros2_control's programs, the controllers
of config/ and the hardware plugin of the <ros2_control> section), and every ``exec_depend``
is one of those. Python libraries that come from
pip (requirements.txt) are listed here with the reason they are not in package.xml."""
import ast
import glob
import os
import sys
import xml.etree.ElementTree as ET

import yaml
from repo_root import ROOT

from starleth_sim.ros.ros2_control_description import HARDWARE_PLUGIN

PACKAGES = ("starleth_sim", "starleth_controller", "starleth_interface")
LAUNCH_FILES = sorted(glob.glob(os.path.join(ROOT, "launch", "*.launch.xml")))
CONTROLLER_FILES = sorted(glob.glob(os.path.join(ROOT, "config", "*.yaml")))

#: Python modules whose rosdep key differs from the module name
ROSDEP_KEYS = {"numpy": "python3-numpy", "yaml": "python3-yaml",
               "matplotlib": "python3-matplotlib", "PIL": "python3-pil"}

#: ROS packages imported under their own name that are not message / service packages
ROS_LIBRARIES = {"rclpy", "rcl_interfaces", "ament_index_python"}

#: Python modules from pip (requirements.txt, setup.py's install_requires / extras), not
#: declared in package.xml: their rosdep keys are missing or not uniform across platforms
PIP_ONLY = {
    "pinocchio": "pip wheel `pin` (the ROS package is built differently per distribution)",
    "mcap": "pip `mcap`: no rosdep key",
    "mcap_ros2": "pip `mcap-ros2-support`: no rosdep key",
    "meshcat": "pip: starleth-view only, no rosdep key",
    "coal": "pip `coal`, installed with the `pin` wheel: the loader of the view's meshes",
    "lz4": "optional (bag compression in tools/common/bag.py), pip",
    "zstandard": "optional (bag compression in tools/common/bag.py), pip",
    "pyarrow": "optional extra `parquet` (starleth-sweep)",
    "ray": "optional extra `ray` (starleth-sweep / starleth-eval --ray)",
    "mujoco": "optional: starleth-bench's comparison only",
    "foxglove": "optional extra `live` (foxglove-sdk: sim_node's live_view), pip only",
    "websockets": "optional extra `live` (starleth_sim.tools.view.live_log, a protocol client)",
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
    """{package: why} of the launch files: what each element needs, the packages of the
    programs they start, and for ros2_control the packages of the controller types in
    config/ and of the hardware plugin sim_node's section names."""
    need, unknown = {}, []
    for path in LAUNCH_FILES:
        name = os.path.relpath(path, ROOT)
        for el in ET.parse(path).getroot().iter():
            if el.tag not in LAUNCH_TAGS:
                unknown.append(el.tag)
                continue
            for key in LAUNCH_TAGS[el.tag]:
                need[key] = f"<{el.tag}> in {name}"
            if el.tag == "node" and el.get("pkg") != "starleth_sim":
                need[el.get("pkg")] = f"a program started by {name}"
                if el.get("exec") == "ros2_control_node":
                    need[HARDWARE_PLUGIN.split("/")[0]] = f"the hardware of {name}"
    assert not unknown, f"launch file elements not in LAUNCH_TAGS: {sorted(set(unknown))}"
    for path in CONTROLLER_FILES:
        with open(path) as f:
            for key, section in yaml.safe_load(f).items():
                if key.endswith("controller_manager"):
                    for c in section["ros__parameters"].values():
                        if isinstance(c, dict) and "type" in c:
                            need[c["type"].split("/")[0]] = f"a controller of {path}"
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
