"""The launch files of launch/ read the way `ros2 launch` reads them, for the tests (there is
no `launch` package in the venv to run them): their arguments with their defaults, and for
each node the program and the `--ros-args` that launch_ros would give it (node name,
namespace, every `<param name= value=>` as `-p`, every `<param from=>` as `--params-file`,
every `<remap>` as `-r`) and its `args`, so that a test starts the nodes a launch file
describes and a broken launch file fails it. Only what the files use is understood (`<arg>`,
`<node>` with `<param>` and `<remap>`; the substitutions `$(var x)`, `$(find-pkg-share
starleth_sim)` (the source tree, which has the layout of the package's share directory) and
`$(eval 'python expression')`, parsed with launch's grammar: arguments apart by one space,
quoted or not, substitutions nested in them, a backslash escaping the next character; an
argument's default may use the arguments declared before it); anything else raises, and so
does a program that is neither one of ours nor one of ROS_PROGRAMS."""
import math
import os
import re
import shlex
import xml.etree.ElementTree as ET

from repo_root import ROOT

LAUNCH_FILE = os.path.join(ROOT, "launch", "starleth.launch.xml")
ROS2_CONTROL_LAUNCH_FILE = os.path.join(ROOT, "launch", "starleth_ros2_control.launch.xml")
NODE_ATTRIBUTES = {"pkg", "exec", "name", "namespace", "output", "args"}
#: programs of other ROS packages a launch file may start (ros2_control, ROS 2 Jazzy)
ROS_PROGRAMS = {("controller_manager", "ros2_control_node"), ("controller_manager", "spawner")}


def console_scripts():
    """{console script: module} of setup.py."""
    with open(os.path.join(ROOT, "setup.py")) as f:
        return dict(re.findall(r"['\"]([\w-]+) = ([\w.]+):\w+['\"]", f.read()))


class Substitutions:
    """Launch's substitution text (launch/frontend/grammar.lark) over the argument values
    `values`: `evaluate(text)` is the text with its `$(var x)`, `$(find-pkg-share
    starleth_sim)` and `$(eval '...')` done (the expression evaluated as launch's
    PythonExpression does, with math's names)."""

    def __init__(self, values, where):
        self.values, self.where = values, where

    def evaluate(self, text):
        self.text, self.pos = text or "", 0
        out = []
        while self.pos < len(self.text):
            out.append(self._substitution() if self._at("$(") else self._char())
        return "".join(out)

    def _at(self, token):
        return self.text.startswith(token, self.pos)

    def _fail(self, why):
        raise ValueError(f"{self.where}: {why} at character {self.pos} of {self.text!r}")

    def _char(self):
        """One character of text, a backslash escaping the next one."""
        c = self.text[self.pos]
        if c == "\\" and self.pos + 1 < len(self.text):
            self.pos += 1
            c = self.text[self.pos]
        self.pos += 1
        return c

    def _substitution(self):
        m = re.compile(r"\$\(([A-Za-z][\w-]*)").match(self.text, self.pos)
        if not m:
            self._fail("a substitution without a name")
        self.pos = m.end()
        args = []
        while self._at(" "):
            self.pos += 1
            args.append(self._argument())
        if not self._at(")"):
            self._fail("a substitution not closed")
        self.pos += 1
        return self._perform(m.group(1), args)

    def _argument(self):
        """One argument: a quoted text (substitutions in it) or an unquoted word."""
        quote = self.text[self.pos] if self._at("'") or self._at('"') else None
        self.pos += quote is not None
        out = []
        while self.pos < len(self.text):
            c = self.text[self.pos]
            if quote is not None and c == quote:
                self.pos += 1
                return "".join(out)
            if quote is None and c in " )":
                return "".join(out)
            if quote is None and c in "'\"(":
                self._fail(f"{c!r} in an unquoted argument")
            out.append(self._substitution() if self._at("$(") else self._char())
        self._fail("an argument not closed")

    def _perform(self, name, args):
        if name == "var" and len(args) == 1:
            if args[0] not in self.values:
                self._fail(f"no argument {args[0]!r} declared before")
            return self.values[args[0]]
        if name == "eval" and len(args) == 1:
            return str(eval(args[0], {}, {**vars(math), "math": math}))
        if name == "find-pkg-share" and args == ["starleth_sim"]:
            return ROOT
        self._fail(f"substitution $({name}) with {len(args)} argument(s) not understood here")


def launch_values(path=LAUNCH_FILE, **arguments):
    """{argument: value} of the file's <arg>s as `ros2 launch` takes them: those given
    (name:=value, taken as they are), the others' defaults evaluated in order."""
    root = ET.parse(path).getroot()
    declared = [a.get("name") for a in root.iter("arg")]
    unknown = set(arguments) - set(declared)
    if unknown:
        raise ValueError(f"{path}: no argument(s) {sorted(unknown)}")
    values = {}
    subs = Substitutions(values, path)
    for a in root.iter("arg"):
        name = a.get("name")
        if name in arguments:
            values[name] = str(arguments[name])
        elif a.get("default") is None:
            raise ValueError(f"{path}: argument {name!r} has no default and was not given")
        else:
            values[name] = subs.evaluate(a.get("default"))
    return values


def launch_arguments(path=LAUNCH_FILE):
    """{name: default (None: none)} of the file's <arg>s, as written."""
    root = ET.parse(path).getroot()
    return {a.get("name"): a.get("default") for a in root.iter("arg")}


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
    sub = Substitutions(launch_values(path, **arguments), path).evaluate
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
