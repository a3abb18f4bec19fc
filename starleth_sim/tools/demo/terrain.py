"""The terrain courses of ``starleth-demo --terrain NAME`` and of the headless walking tests
(test/controller/test_terrain_walk.py): each a ``terrain:`` section of the physics configuration,
placed ahead of the robot (which starts at x = 0 heading +x), and the x its trunk must pass
to have crossed it (the hind feet beyond the course's last edge).

- ``step``: a 4 cm step, 0.6 m long (up and down again);
- ``stairs``: the shipped course msg_configs/terrain/stairs.yaml as it is: 3 stairs of 4 cm
  rise and 0.3 m run from x = 0.6 m, a 1 m landing, then 12 cm down to the ground;
- ``ledge``: the robot starts on a 12 cm high platform whose edge is 0.6 m ahead (down);
- ``slope``: a 10° ramp up over 0.5 m, a 0.3 m top, the same ramp down;
- ``rough``: ±1.5 cm rough ground (wavelength 0.4 m), 12 m square, from 3 m behind the start.

The demo passes a course to sim_node as ``physics_overrides`` (``{stairs: {...}}``: a
terrain field by its name; ``{terrain: {...}}`` is refused, a section is given by its
fields)."""
from __future__ import annotations

import json
import os

import yaml

from starleth_interface.yaml_files import load_yaml_file

from ...physics.config import config_dir

#: the shipped stairs course (a file of msg_configs/), walked as it is
STAIRS_FILE = "terrain/stairs.yaml"
#: the trunk has crossed an edge when it is this far beyond it (its hind feet too) [m]
PAST_EDGE = 0.35


def _shipped_terrain(name: str) -> dict:
    """The terrain section of the shipped physics file `name` (under msg_configs/)."""
    return load_yaml_file(os.path.join(config_dir(), name))["terrain"]


def _stairs_end(stairs: dict) -> float:
    """The x of the far edge of a stairs generator's landing."""
    return stairs["start"] + stairs["count"] * stairs["run"] + stairs["landing"]


#: name -> (the terrain fields, or the shipped file holding them; the x the trunk must pass [m])
COURSES = {
    "step": ({"boxes": [{"centre": [0.8, 0.0, 0.02], "size": [0.6, 2.0, 0.04]}]}, 1.5),
    "stairs": (STAIRS_FILE, None),
    "ledge": ({"boxes": [{"centre": [-1.2, 0.0, 0.06], "size": [3.6, 2.0, 0.12]}]},
              0.6 + PAST_EDGE),
    "slope": ({"slope": {"angle": 10.0, "length": 0.5, "start": 0.6, "top": 0.3,
                         "width": 2.0}}, 2.2),
    "rough": ({"rough": {"amplitude": 0.015, "wavelength": 0.4, "seed": 1, "size": 12.0,
                         "centre": [3.0, 0.0]}}, 1.5),
}


def course_terrain(name: str) -> dict:
    """The terrain fields of course `name` (physics overrides: Simulator.from_preset(preset,
    **course_terrain(name)))."""
    if name not in COURSES:
        raise ValueError(f"unknown terrain course {name!r} (known: {', '.join(COURSES)})")
    terrain = COURSES[name][0]
    if isinstance(terrain, str):
        terrain = _shipped_terrain(terrain)
    return json.loads(json.dumps(terrain))      # a deep copy


def course_overrides(name: str) -> str:
    """sim_node's ``physics_overrides`` parameter for course `name`: one line of flow YAML
    without quotes (it travels in a double-quoted ``-p name:="..."`` argument)."""
    return yaml.safe_dump(course_terrain(name), default_flow_style=True, width=10_000).strip()


def course_end(name: str) -> float:
    """The x [m] the trunk must pass to have crossed course `name` (the shipped stairs: its
    landing's far edge + PAST_EDGE)."""
    terrain = course_terrain(name)
    end = COURSES[name][1]
    return end if end is not None else _stairs_end(terrain["stairs"]) + PAST_EDGE
