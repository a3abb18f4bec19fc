"""The terrain courses of ``starleth-demo --terrain NAME`` and of the headless walking tests
(test/test_terrain_walk.py): each a ``terrain:`` section of the physics configuration,
placed ahead of the robot (which starts at x = 0 heading +x), and the x its trunk must pass
to have crossed it (the hind feet beyond the course's last edge).

- ``step``: a 4 cm step, 0.6 m long (up and down again);
- ``stairs``: 3 stairs of 4 cm rise and 0.25 m run, onto a 6 m landing (the demo trots on it);
- ``slope``: a 10° ramp up over 0.5 m, a 0.3 m top, the same ramp down;
- ``rough``: ±1.5 cm rough ground (wavelength 0.4 m), 12 m square, from 3 m behind the start.

The demo passes a course to sim_node as ``physics_overrides`` (``{stairs: {...}}``: a
terrain field by its name; ``{terrain: {...}}`` is refused, a section is given by its
fields)."""
from __future__ import annotations

import json

import yaml

#: name -> (the terrain fields, the x the trunk must pass [m])
COURSES = {
    "step": ({"boxes": [{"centre": [0.8, 0.0, 0.02], "size": [0.6, 2.0, 0.04]}]}, 1.5),
    "stairs": ({"stairs": {"rise": 0.04, "run": 0.25, "count": 3, "start": 0.6,
                           "width": 2.0, "landing": 6.0}}, 1.5),
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
    return json.loads(json.dumps(COURSES[name][0]))      # a deep copy


def course_overrides(name: str) -> str:
    """sim_node's ``physics_overrides`` parameter for course `name`: one line of flow YAML
    without quotes (it travels in a double-quoted ``-p name:="..."`` argument)."""
    return yaml.safe_dump(course_terrain(name), default_flow_style=True, width=10_000).strip()


def course_end(name: str) -> float:
    """The x [m] the trunk must pass to have crossed course `name`."""
    course_terrain(name)
    return COURSES[name][1]
