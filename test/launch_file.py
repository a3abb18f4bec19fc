"""The launch files of launch/ read the way `ros2 launch` reads them, for the tests (there is
no `launch` package in the venv to run them): their arguments with their defaults, and for
each node the program and the `--ros-args` that launch_ros would give it (node name,
namespace, every `<param name= value=>` as `-p`, every `<param from=>` as `--params-file`,
every `<remap>` as `-r`) and its `args`, so that a test starts the nodes a launch file
describes and a broken launch file fails it. Only what the files use is understood (`$(var
x)` and `$(find-pkg-share starleth_sim)` substitutions, `<arg>`, `<node>` with `<param>` and
`<remap>`); anything else raises, and so does a program that is neither one of ours nor one
of ROS_PROGRAMS."""
import os
import re
import shlex
import xml.etree.ElementTree as ET

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LAUNCH_FILE = os.path.join(ROOT, "launch", "starleth.launch.xml")
ROS2_CONTROL_LAUNCH_FILE = os.path.join(ROOT, "launch", "starleth_ros2_control.launch.xml")
NODE_ATTRIBUTES = {"pkg", "exec", "name", "namespace", "output", "args"}
#: programs of other ROS packages a launch file may start (ros2_control, ROS 2 Jazzy)
ROS_PROGRAMS = {("controller_manager", "ros2_control_node"), ("controller_manager", "spawner")}


def console_scripts():
    """{console script: module} of setup.py."""
    with open(os.path.join(ROOT, "setup.py")) as f:
        return dict(re.findall(r"['\"]([\w-]+) = ([\w.]+):\w+['\"]", f.read()))


def launch_arguments(path=LAUNCH_FILE):
    """{name: default (None: none)} of the file's <arg>s, as written."""
    root = ET.parse(path).getroot()
    return {a.get("name"): a.get("default") for a in root.iter("arg")}


def _substitute(path, values, text):
    """`text` with $(var x) and $(find-pkg-share starleth_sim) (the source tree, which has
    the layout of the package's share directory) replaced."""
    out = re.sub(r"\$\(var (\w+)\)", lambda m: values[m.group(1)], text or "")
    out = out.replace("$(find-pkg-share starleth_sim)", ROOT)
    if "$(" in out:
        raise ValueError(f"{path}: substitution not understood here: {text!r}")
    return out


def _node_ros_args(path, child, sub):
    name, ns = sub(child.get("name")), sub(child.get("namespace")).strip("/")
    ros_args = (["-r", f"__node:={name}"] if name else []) + \
        (["-r", f"__ns:=/{ns}"] if ns else [])
    for e in child:
        if e.tag == "param" and e.get("from") is not None:
            if set(e.attrib) != {"from"}:
                raise ValueError(f"{path}: <param from> takes no other attribute: {e.attrib}")
            ros_args += ["--params-file", sub(e.get("from"))]
        elif e.tag == "param":
            value = sub(e.get("value"))
            ros_args += ["-p", f"{e.get('name')}:={value if value else repr('')}"]
        elif e.tag == "remap":
            ros_args += ["-r", f"{sub(e.get('from'))}:={sub(e.get('to'))}"]
        else:
            raise ValueError(f"{path}: element <{e.tag}> in a node not understood here")
    return name, ns, ros_args


def launch_nodes(path=LAUNCH_FILE, **arguments):
    """[{pkg, exec, module, name, namespace, ros_args, args}] of the file's <node>s with
    `arguments` given as on the command line of `ros2 launch` (name:=value); module is what
    `python -m` runs for exec (None for ROS_PROGRAMS), ros_args what follows `--ros-args`,
    args the node's `args` split as a shell does."""
    root = ET.parse(path).getroot()
    if root.tag != "launch":
        raise ValueError(f"{path}: root element {root.tag!r}, expected 'launch'")
    defaults = launch_arguments(path)
    unknown = set(arguments) - set(defaults)
    if unknown:
        raise ValueError(f"{path}: no argument(s) {sorted(unknown)}")
    values = {}
    for k, v in defaults.items():          # in order: a default may use an earlier argument
        values[k] = str(arguments[k]) if k in arguments else \
            (None if v is None else _substitute(path, values, v))
    missing = [k for k, v in values.items() if v is None]
    if missing:
        raise ValueError(f"{path}: argument(s) {missing} have no default and were not given")

    def sub(text):
        return _substitute(path, values, text)

    scripts = console_scripts()
    nodes = []
    for child in root:
        if child.tag == "arg":
            continue
        if child.tag != "node":
            raise ValueError(f"{path}: element <{child.tag}> not understood here")
        extra = set(child.attrib) - NODE_ATTRIBUTES
        if extra:
            raise ValueError(f"{path}: node attribute(s) {sorted(extra)} not understood here")
        pkg, exe = child.get("pkg"), child.get("exec")
        ours = pkg == "starleth_sim" and exe in scripts
        if not ours and (pkg, exe) not in ROS_PROGRAMS:
            raise ValueError(f"{path}: {child.attrib} is neither a program of starleth_sim nor "
                             f"one of {sorted(ROS_PROGRAMS)}")
        name, ns, ros_args = _node_ros_args(path, child, sub)
        nodes.append({"pkg": pkg, "exec": exe, "module": scripts[exe] if ours else None,
                      "name": name, "namespace": f"/{ns}" if ns else "",
                      "ros_args": ros_args, "args": shlex.split(sub(child.get("args")))})
    return nodes
