"""launch/starleth.launch.xml read the way `ros2 launch` reads it, for the tests (there is no
`launch` package in the venv to run it): its arguments with their defaults, and for each node
the program and the `--ros-args` that launch_ros would give it (node name, namespace, every
`<param>` as `-p`, every `<remap>` as `-r`), so that a test starts the nodes the launch file
describes and a broken launch file fails it. Only what the file uses is understood (`$(var
x)` substitutions, `<arg>`, `<node>` with `<param>` and `<remap>`); anything else raises."""
import os
import re
import xml.etree.ElementTree as ET

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LAUNCH_FILE = os.path.join(ROOT, "launch", "starleth.launch.xml")
NODE_ATTRIBUTES = {"pkg", "exec", "name", "namespace", "output"}


def console_scripts():
    """{console script: module} of setup.py."""
    with open(os.path.join(ROOT, "setup.py")) as f:
        return dict(re.findall(r"['\"]([\w-]+) = ([\w.]+):\w+['\"]", f.read()))


def launch_arguments(path=LAUNCH_FILE):
    """{name: default (None: none)} of the file's <arg>s."""
    root = ET.parse(path).getroot()
    return {a.get("name"): a.get("default") for a in root.iter("arg")}


def launch_nodes(path=LAUNCH_FILE, **arguments):
    """[{exec, module, name, namespace, ros_args}] of the file's <node>s with `arguments`
    given as on the command line of `ros2 launch` (name:=value); module is what `python -m`
    runs for exec, ros_args what follows `--ros-args`."""
    root = ET.parse(path).getroot()
    if root.tag != "launch":
        raise ValueError(f"{path}: root element {root.tag!r}, expected 'launch'")
    values = launch_arguments(path)
    unknown = set(arguments) - set(values)
    if unknown:
        raise ValueError(f"{path}: no argument(s) {sorted(unknown)}")
    values.update({k: str(v) for k, v in arguments.items()})
    missing = [k for k, v in values.items() if v is None]
    if missing:
        raise ValueError(f"{path}: argument(s) {missing} have no default and were not given")

    def sub(text):
        out = re.sub(r"\$\(var (\w+)\)", lambda m: values[m.group(1)], text or "")
        if "$(" in out:
            raise ValueError(f"{path}: substitution not understood here: {text!r}")
        return out

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
        if child.get("pkg") != "starleth_sim" or child.get("exec") not in scripts:
            raise ValueError(f"{path}: {child.attrib} is not a program of starleth_sim")
        name, ns = sub(child.get("name")), sub(child.get("namespace")).strip("/")
        ros_args = (["-r", f"__node:={name}"] if name else []) + \
            (["-r", f"__ns:=/{ns}"] if ns else [])
        for e in child:
            if e.tag == "param":
                value = sub(e.get("value"))
                ros_args += ["-p", f"{e.get('name')}:={value if value else repr('')}"]
            elif e.tag == "remap":
                ros_args += ["-r", f"{sub(e.get('from'))}:={sub(e.get('to'))}"]
            else:
                raise ValueError(f"{path}: element <{e.tag}> in a node not understood here")
        nodes.append({"exec": child.get("exec"), "module": scripts[child.get("exec")],
                      "name": name, "namespace": f"/{ns}" if ns else "",
                      "ros_args": ros_args})
    return nodes
