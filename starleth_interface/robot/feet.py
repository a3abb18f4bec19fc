"""A robot's foot contact spheres, from its spec and its URDF: the spec's foot links (a
sphere of the spec's radius on each, or the link's one URDF <sphere>), else the legs' feet
found among the URDF's spheres (legs.find_legs); in the legs' order when every foot ends a
leg."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pinocchio as pin

from ..config_checks import ConfigError
from .contact_points import collision_points, link_frame, sphere_point
from .legs import find_legs
from .spec import RobotSpec, match_names


def link_elements(root) -> dict:
    """The URDF's <link> elements by name."""
    return {link.get("name"): link for link in root.findall("link")}


def link_spheres(link, model, source) -> list:
    """A link's URDF sphere collisions as contact points; an unnamed one alone on its link
    is named after the link (a foot: 'LF_FOOT', not 'LF_FOOT_1')."""
    colls = link.findall("collision")
    points = [p for k in range(len(colls))
              for p in collision_points(link, k, model, source, ("sphere",))]
    unnamed = [c for c in colls if c.find("geometry/sphere") is not None and not c.get("name")]
    if len(points) == 1 and unnamed:
        points = [replace(points[0], name=link.get("name"))]
    return points


def foot_points(spec: RobotSpec, root, model, source, joint_names) -> list:
    """The foot contact points, in the legs' order when every foot ends a leg (module
    docstring); ConfigError naming the spec and the field."""
    links = link_elements(root)
    feet = spec.feet
    where = f"{spec.label}: feet"
    if feet.links is None:       # found on the legs among the URDF's spheres
        spheres = [p for link in links.values() for p in link_spheres(link, model, source)]
        legs = find_legs(model, joint_names, spheres)
        return [next(p for p in spheres if p.name == leg.foot) for leg in legs]
    points = []
    for name in match_names(feet.links, list(links), f"{where}.links"):
        if feet.radius is not None:
            frame = link_frame(model, name, where)
            points.append(sphere_point(name, name, frame.parentJoint,
                                       frame.placement * pin.SE3(np.eye(3), np.array(feet.at)),
                                       feet.radius, f"{where}.radius"))
            continue
        found = link_spheres(links[name], model, source)
        if len(found) != 1:
            raise ConfigError(f"{where}.links: link '{name}' has {len(found) or 'no'} <sphere> "
                              "collision(s): give feet.radius (and feet.at)")
        points += found
    legs = find_legs(model, joint_names, points, {p.name for p in points})
    if {leg.foot for leg in legs} == {p.name for p in points}:
        points = [next(p for p in points if p.name == leg.foot) for leg in legs]
    return points
