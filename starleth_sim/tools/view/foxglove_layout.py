"""``starleth-layout``: the Foxglove / Lichtblick layout of robots under ROS namespaces, made
from the shipped one (``foxglove/starleth_layout.json``: one robot at the root) with its
topics and frames rewritten.

    starleth-layout robot1 -o robot1_layout.json            # one robot under /robot1
    starleth-layout robot1 robot2 -o two_robots.json        # both in one layout
    starleth-layout robot1 --frame-prefix r1_ -o r1.json    # a prefix of its own
    starleth-layout --robot go1 -o go1_layout.json          # another robot (any namespace)

Each robot's frames carry the prefix the launch file gives it (``namespace:=robot1``:
``robot1/base``, ...; ``--frame-prefix`` for a robot started otherwise). In the layout:

* the 3D panel: every robot's topics (its contact markers, its terrain) under its
  namespace; its URDF as a URDF layer on its ``robot_description`` topic with its frame
  prefix (Foxglove's built-in URDF entry reads ``/robot_description`` only, unprefixed: kept
  for a robot at the root without a prefix); the camera follows the first robot's base;
  ``world`` (the grid's frame) is shared;
* the plots: each path once per robot, under its namespace, labelled with it when there
  are several.

``--robot NAME`` (a library name or the path of a robot spec or URDF; default: StarlETH,
the shipped layout's robot): the camera follows that robot's base (its URDF's root link) and
the foot force plot has one path per foot of the robot (its foot contact names, their
topics foot_wrench_topic(foot)), in place of the shipped robot's feet; the robots under the
namespaces are all that robot.

Without a namespace and a robot it writes the shipped layout as it is. A namespace that is
not a ROS namespace, a prefix that is not a frame prefix, a robot that is not there or
cannot be read, or a shipped layout with a panel of a kind not handled here: one line on
stderr, exit status 2 (bad arguments) or 1.
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import re
import sys

from starleth_interface.config_checks import ConfigError
from starleth_interface.package_data import package_share_dir
from starleth_interface.topics import (
    TOPIC_ROBOT_DESCRIPTION,
    foot_wrench_topic,
    normalize_namespace,
    resolve,
)

from ...robots import robot_description
from ...ros.parameters import frame_name_problem, namespace_frame_prefix
from ...ros.tf import base_link
from ..common.console import run_console_script

PROG = "starleth-layout"
#: the robot the shipped layout shows (its followed frame and its feet's force plot)
SHIPPED_ROBOT = "starleth"
#: the URDF layer of Foxglove's and Lichtblick's 3D panel
URDF_LAYER = "foxglove.Urdf"
#: a ROS namespace: names of letters, digits and underscores (not starting with a digit)
NAMESPACE = re.compile(r"/?([A-Za-z_][A-Za-z0-9_]*/)*[A-Za-z_][A-Za-z0-9_]*/?")


class LayoutError(Exception):
    """A shipped layout this tool cannot rewrite: one line, exit status 1."""


def shipped_layout_path() -> str:
    """foxglove/starleth_layout.json of the installed package (or of the checkout)."""
    return os.path.join(package_share_dir(), "foxglove", "starleth_layout.json")


def robots(namespaces, frame_prefixes=None) -> list:
    """[(namespace, frame prefix)] of the robots: the namespaces normalised ('/robot1'), the
    prefixes given (in order) or the launch file's (robot1/); no namespace: one robot at
    the root, unprefixed (the shipped layout's). ValueError naming what is wrong."""
    prefixes = list(frame_prefixes or [])
    if len(prefixes) > len(namespaces):
        raise ValueError(f"{len(prefixes)} --frame-prefix for {len(namespaces)} namespace(s)")
    if not namespaces:
        return [("", "")]
    out = []
    for k, ns in enumerate(namespaces):
        if not NAMESPACE.fullmatch(ns):
            raise ValueError(f"{ns!r} is not a ROS namespace (names of letters, digits and "
                             "underscores apart by '/', e.g. robot1)")
        prefix = prefixes[k] if k < len(prefixes) else namespace_frame_prefix(ns)
        problem = frame_name_problem(prefix, empty_ok=True)
        if problem:
            raise ValueError(f"frame prefix {prefix!r}: {problem}")
        out.append((normalize_namespace(ns), prefix))
    if len({ns for ns, _ in out}) < len(out):
        raise ValueError("a namespace is named twice")
    return out


def _topic(template_topic: str, ns: str) -> str:
    """A topic of the shipped layout (a root robot's: /starleth/solver) under `ns`."""
    return resolve(template_topic.lstrip("/"), ns)


def _three_d(panel: dict, robots_: list) -> dict:
    """A 3D panel for the robots: their topics, their URDF layers, the first one's base
    followed."""
    out = copy.deepcopy(panel)
    ns0, prefix0 = robots_[0]
    if out.get("followTf"):
        out["followTf"] = prefix0 + out["followTf"]
    topics, layers = {}, out.setdefault("layers", {})
    order = max([layer.get("order", 0) for layer in layers.values()] + [0])
    description = resolve(TOPIC_ROBOT_DESCRIPTION, "")
    for topic, opts in panel.get("topics", {}).items():
        for ns, prefix in robots_:
            if topic != description:
                topics[_topic(topic, ns)] = copy.deepcopy(opts)
            elif not ns and not prefix:      # the built-in entry: /robot_description as is
                topics[topic] = copy.deepcopy(opts)
            else:
                order += 1
                name = ns.strip("/") or "root"
                layers[f"urdf-{name}"] = {
                    "layerId": URDF_LAYER, "instanceId": f"urdf-{name}",
                    "label": f"{ns or '/'} URDF", "visible": opts.get("visible", True),
                    "sourceType": "topic", "topic": _topic(topic, ns),
                    "framePrefix": prefix, "displayMode": "auto", "order": order}
    out["topics"] = topics
    return out


def _plot(panel: dict, robots_: list) -> dict:
    """A plot with each path once per robot (labelled with its namespace if several)."""
    out = copy.deepcopy(panel)
    paths = []
    for ns, _ in robots_:
        for path in panel.get("paths", []):
            p = copy.deepcopy(path)
            topic, dot, fields = p["value"].partition(".")
            p["value"] = _topic(topic, ns) + dot + fields
            if len(robots_) > 1 and "label" in p:
                p["label"] = f"{ns.strip('/') or 'root'} {p['label']}"
            paths.append(p)
    out["paths"] = paths
    return out


PANELS = {"3D": _three_d, "Plot": _plot}


def _foot_paths(paths: list, shipped_feet, feet) -> list:
    """A plot's paths with those on the shipped robot's foot wrench topics replaced, at the
    first of them, by one per foot of `feet` (the same fields, labelled with the foot)."""
    topics = {"/" + foot_wrench_topic(f) for f in shipped_feet}
    out, done = [], False
    for path in paths:
        topic, dot, fields = path["value"].partition(".")
        if topic not in topics:
            out.append(path)
        elif not done:
            done = True
            out += [dict(copy.deepcopy(path), value="/" + foot_wrench_topic(f) + dot + fields,
                         label=f) for f in feet]
    return out


def robot_layout(layout: dict, robot: str) -> dict:
    """The layout `layout` (the shipped robot's) for the robot `robot` names (a library name,
    a spec or URDF path): its base followed, its feet's forces plotted. ConfigError naming
    what is wrong with the robot."""
    if robot == SHIPPED_ROBOT:
        return layout
    shipped, desc = robot_description(SHIPPED_ROBOT), robot_description(robot)
    shipped_base, base = base_link(shipped.urdf_xml), base_link(desc.urdf_xml)
    out = copy.deepcopy(layout)
    for panel in out.get("configById", {}).values():
        if panel.get("followTf") == shipped_base:
            panel["followTf"] = base
        if "paths" in panel:
            panel["paths"] = _foot_paths(panel["paths"], shipped.foot_names, desc.foot_names)
    return out


def namespaced_layout(layout: dict, robots_: list) -> dict:
    """The layout `layout` (the shipped one: a root robot's) for `robots_` ([(namespace,
    frame prefix)], robots()). LayoutError for a panel kind not handled here."""
    out = copy.deepcopy(layout)
    for key, panel in layout.get("configById", {}).items():
        kind = key.split("!", 1)[0]
        if kind not in PANELS:
            raise LayoutError(f"the layout's panel {key!r}: a {kind} panel is not handled "
                              f"here (only {', '.join(PANELS)})")
        out["configById"][key] = PANELS[kind](panel, robots_)
    return out


def build_parser():
    ap = argparse.ArgumentParser(
        prog=PROG,
        description="Write the Foxglove / Lichtblick layout of StarlETH robots under ROS "
        "namespaces (the launch file's namespace:=robot1), made from the shipped "
        "foxglove/starleth_layout.json: every robot's topics under its namespace, its URDF "
        "on its robot_description with its frame prefix (robot1/), the plots once per "
        "robot, the camera following the first robot's base, world shared. Import it "
        "with Layouts -> Import from file.",
        epilog="Exit status: 0 written, 1 the shipped layout cannot be rewritten or the "
        "file cannot be written, 2 bad arguments.")
    ap.add_argument("namespace", nargs="*",
                    help="the robots' namespaces (robot1 robot2); none: the shipped layout")
    ap.add_argument("--frame-prefix", action="append", metavar="PREFIX",
                    help="the frame prefix of the n-th robot, for one started without the "
                         "launch file's (default: the namespace and '/': robot1/)")
    ap.add_argument("-o", "--output", metavar="LAYOUT.json",
                    help="the file to write (default: standard output)")
    ap.add_argument("--robot", default=SHIPPED_ROBOT, metavar="NAME",
                    help="the robot: a library name (go1, anymal_c, ...) or the path of a "
                         "robot spec or URDF; its base followed, its feet's forces plotted "
                         f"(default: {SHIPPED_ROBOT}, the shipped layout's)")
    ap.add_argument("--layout", metavar="LAYOUT.json",
                    help="the layout to rewrite (default: the shipped one, "
                         "foxglove/starleth_layout.json)")
    return ap


def run(argv=None) -> int:
    ap = build_parser()
    a = ap.parse_args(argv)
    try:
        robots_ = robots(a.namespace, a.frame_prefix)
    except ValueError as e:
        ap.error(str(e))
    path = a.layout or shipped_layout_path()
    try:
        with open(path, encoding="utf-8") as f:
            layout = json.load(f)
    except ValueError as e:
        raise LayoutError(f"{path}: not a JSON layout ({e})") from None
    try:
        layout = robot_layout(layout, a.robot)
    except ConfigError as e:
        ap.error(str(e))
    text = json.dumps(namespaced_layout(layout, robots_), indent=2, ensure_ascii=False) + "\n"
    if a.output:
        with open(a.output, "w", encoding="utf-8") as f:
            f.write(text)
        print(f"wrote {a.output}: the layout of {a.robot} robots: "
              + ", ".join(f"{ns or '/'} (frames {prefix or 'unprefixed'})"
                          for ns, prefix in robots_), file=sys.stderr)
    else:
        sys.stdout.write(text)
    return 0


def main(argv=None) -> int:
    """Console script: exit status 0, 1 (one line on stderr) or 2 (bad arguments)."""
    return run_console_script(PROG, run, argv, (LayoutError,))


if __name__ == "__main__":
    sys.exit(main())
