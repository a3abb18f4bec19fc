"""Every command-line form the docs show parses as written: each `-p name:=value` rule in
README.md, doc/*.md, the launch file's comments and the parameter descriptions of sim_node
and controller_node (shell-split as a shell would, the quotes included) goes through rcl's
own argument parser (rclpy.init, as `ros2 run` does) and gives a value the node's schema
accepts; sim_node's physics_overrides parses to a mapping the physics validates. And the
form that rcl refuses, a mapping unquoted, gets one line saying how to quote it."""
import glob
import itertools
import os
import re
import shlex

import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.node import Node
from repo_root import ROOT

from starleth_controller.node_parameters import PARAMETERS as CONTROLLER_PARAMETERS
from starleth_interface.ros_helpers import init_ros
from starleth_sim import Simulator
from starleth_sim.ros.parameters import SIM_NODE_PARAMETERS, Settings

PAGES = ["README.md", *sorted(os.path.relpath(p, ROOT) for p in
                              glob.glob(os.path.join(ROOT, "doc", "*.md"))),
         "launch/starleth.launch.xml"]
SCHEMAS = {"sim_node": {p.name: p for p in SIM_NODE_PARAMETERS},
           "controller_node": {p.name: p for p in CONTROLLER_PARAMETERS}}


#: names shown on purpose as mistakes (the docs show how a typo is refused)
SHOWN_AS_MISTAKES = {"mdoe", "recrod"}
#: ROS's own parameters of every node
ROS_PARAMETERS = {"use_sim_time"}


def command_lines(text, prose=False):
    """The command lines of a text: the lines of its code blocks (fenced or indented) and
    its `inline code` spans (prose=True: the text itself, a description), each holding a
    `-p` rule, from its first `-p` or `--ros-args` to its end (a trailing # comment cut)."""
    if prose:
        pieces = [text]
    else:
        pieces = re.findall(r"```[a-z]*\n(.*?)```", text, re.S)
        pieces = [line for block in pieces for line in block.splitlines()]
        pieces += [line for line in text.splitlines() if line.startswith("    ")]  # indented
        prose_only = re.sub(r"```.*?```", "", text, flags=re.S)
        pieces += [span.replace("\n", " ") for span in re.findall(r"`([^`]+)`", prose_only)]
    out = []
    for piece in pieces:
        m = re.search(r"(?:--ros-args|(?<!\S)-p) ", piece)
        if m and ":=" in piece:
            out.append(re.split(r"\s#\s", piece[m.start():])[0])
    return out


def rules(line):
    """The `-p` rules of a command line, split as a shell splits it (quotes removed; ';'
    ends a command)."""
    lexer = shlex.shlex(line, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    try:
        words = list(lexer)
    except ValueError:          # an unbalanced quote: the text around cut the line
        return []
    return [rule for flag, rule in itertools.pairwise(words)
            if flag in ("-p", "--param") and re.match(r"[a-z_]+:=", rule)]


def forms():
    """{rule: where it is shown} of every `-p` rule shown in the docs and descriptions."""
    found = {}
    texts = [(page, open(os.path.join(ROOT, page), encoding="utf-8").read(), False)
             for page in PAGES]
    texts += [(f"{node} parameter {p.name}", p.description, True)
              for node, schema in SCHEMAS.items() for p in schema.values()]
    for where, text, prose in texts:
        for line in command_lines(text, prose):
            for rule in rules(line):
                found.setdefault(rule, where)
    return found


FORMS = forms()


def test_the_docs_show_command_line_forms():
    """The collection works: the forms the docs are known to show are among them."""
    assert "mode:=lockstep" in FORMS and "physics:=terrain/stairs.yaml" in FORMS
    assert "physics_overrides:='{control_rate: 1000.0, mu: 0.5}'" in FORMS, sorted(FORMS)
    assert "default_kp:=300.0" in FORMS and len(FORMS) >= 15, sorted(FORMS)


@pytest.mark.parametrize("rule", sorted(FORMS))
def test_every_form_shown_parses_as_written(rule):
    """rcl parses the rule; where the parameter is sim_node's or controller_node's, its
    schema accepts the value (and physics_overrides builds a simulator)."""
    where = FORMS[rule]
    context = rclpy.Context()
    rclpy.init(args=["prog", "--ros-args", "-p", rule], context=context)
    try:
        node = Node("forms", context=context,
                    automatically_declare_parameters_from_overrides=True)
        name = rule.split(":=", 1)[0]
        value = node.get_parameter(name).value
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    specs = [schema[name] for schema in SCHEMAS.values() if name in schema]
    if not specs:
        assert name in SHOWN_AS_MISTAKES | ROS_PARAMETERS, f"{where}: -p {rule}: no node has {name}"
    errors = []
    for spec in specs:             # (mode is both nodes'; one of them takes the value)
        try:
            spec.check(spec.coerce(value))
        except ValueError as e:
            errors.append(str(e))
    assert len(errors) < len(specs) or not specs, f"{where}: -p {rule}: {errors}"
    if name == "physics_overrides":
        overrides = Settings(physics_overrides=value).physics_override_dict()
        Simulator.from_preset("HmJ", **overrides)


def test_an_unquoted_mapping_gets_a_line_saying_how_to_quote_it(capsys):
    argv = ["sim_node", "--ros-args", "-p", "physics_overrides:={control_rate: 1000.0}"]
    assert not init_ros("sim_node", argv)
    err = capsys.readouterr().err
    assert "Unknown YAML event" in err, err
    assert "-p \"physics_overrides:='{control_rate: 1000.0}'\"" in err, err
    context = rclpy.Context()
    rclpy.init(args=["prog", "--ros-args", "-p", "physics_overrides:='{control_rate: 1000.0}'"],
               context=context)
    rclpy.try_shutdown(context=context)
