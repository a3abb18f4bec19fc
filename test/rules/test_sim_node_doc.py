"""doc/sim_node.md against the one parameter schema of sim_node (SIM_NODE_PARAMETERS): its
parameter table lists every parameter of the schema, in the schema's order, with the
schema's type, default, legal values and description, and the page sets no parameter the
schema lacks."""
import os
import re

from repo_root import ROOT

from starleth_interface.ros_helpers import ROS_TYPE_NAMES, parameter_table_row
from starleth_sim.ros.parameters import SIM_NODE_PARAMETERS

DOC = os.path.join(ROOT, "doc",
                   "sim_node.md")


def doc_text():
    with open(DOC, encoding="utf-8") as f:
        return f.read()


def parameter_rows(text):
    """{name: [type, default, legal values, description]} of the table of the section
    '## Parameters' (cells split on unescaped '|', '\\|' read as '|')."""
    section = text.split("\n## Parameters\n", 1)[1].split("\n## ", 1)[0]
    rows = {}
    for line in section.splitlines():
        m = re.match(r"\| `([^`]+)` \|", line)
        if not m:
            continue
        cells = [c.strip().replace("\\|", "|")
                 for c in re.split(r"(?<!\\)\|", line.strip().strip("|"))]
        assert m.group(1) not in rows, f"{m.group(1)} twice in the table"
        rows[m.group(1)] = cells[1:]
    return rows


def test_the_parameter_table_is_the_schema():
    """The rows are the schema's, in its order, each as the schema renders it (type,
    default, legal values, description)."""
    rows = parameter_rows(doc_text())
    assert list(rows) == [p.name for p in SIM_NODE_PARAMETERS], \
        "doc/sim_node.md's parameter table: names or order differ from SIM_NODE_PARAMETERS"
    lines = {line[3:].split("`", 1)[0]: line for line in doc_text().splitlines()
             if line.startswith("| `")}
    for p in SIM_NODE_PARAMETERS:
        assert lines[p.name] == parameter_table_row(p), \
            f"{p.name}: render it with python -m starleth_sim.ros.parameters --doc {DOC}"
        typ, default, legal, description = rows[p.name]
        assert typ == ROS_TYPE_NAMES[p.kind] and description == p.description, p.name


def test_the_page_sets_no_parameter_the_schema_lacks():
    """Every `name:=value` of the page (command lines and text) is a parameter of the
    schema, except the remapping __ns, remaps of absolute names (`/clock:=clock`), the
    controller's --controller-param options and, on a `ros2 launch` line, the launch file's
    arguments."""
    from launch_file import launch_values
    text = doc_text()
    names = {p.name for p in SIM_NODE_PARAMETERS}
    pattern = r"(?<![\w/-])(?<!--controller-param )([A-Za-z_]\w*):="
    launch_lines = [x for x in text.splitlines() if x.startswith("ros2 launch starleth_sim")]
    assert set(re.findall(pattern, "\n".join(launch_lines))) <= set(launch_values())
    text = "\n".join(x for x in text.splitlines() if x not in launch_lines)
    set_here = set(re.findall(pattern, text))
    assert set_here - {"__ns"} <= names, sorted(set_here - {"__ns"} - names)
    assert set_here & names, "no parameter set on the page at all: the pattern is stale"
