"""Contact points: the spheres (radius 0: points) that touch the ground, and how they are
made of a URDF's collision geometry.

The contact model is spheres against the ground and the terrain, so each collision shape
becomes spheres:

- ``<sphere>``: itself, named after the collision (``<collision name>``; unnamed: the link's
  name when it is the link's only collision, else ``<link>_<k>``, k its index in the link);
- ``<box>``: its 8 corners (radius 0), named ``<name>_<sx><sy><sz>`` with s = p/n the sign
  of each half-extent;
- ``<cylinder>`` and ``<capsule>``: the two spheres of its radius centred on the centres of
  its end faces, ``<name>_p`` (+z end) and ``<name>_n``. They cover each end disk: for a
  capsule they are its ends exactly; a cylinder lying on its side touches where it would,
  at both ends; a cylinder's flat end facing the ground is felt up to one radius early at
  its centre (the sphere bulges beyond the flat face);
- ``<mesh>``: never (no mesh is read); a robot spec says which spheres or box stand for it.

A robot's spheres (check_terrain_reach) must be smaller than BOX_REACH (0.1 m, the reach
of the simulator's terrain boxes: starleth_sim.physics.terrain): beyond it the gaps to the
terrain's boxes are no longer exact.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from ..config_checks import ConfigError
from .urdf import numbers, urdf_origin

#: the URDF collision geometries that become contact points (module docstring)
CONTACT_GEOMETRIES = ("sphere", "box", "cylinder", "capsule")
#: [m] a contact sphere's radius is below this: the simulator's terrain tests a box for the
#: contacts whose centre lies within it (starleth_sim.physics.terrain), so that the gaps to
#: the terrain are exact for every sphere of a robot
BOX_REACH = 0.1


@dataclass(frozen=True)
class ContactPointSpec:
    """A contact point: a sphere of `radius` centred at `local` in the frame of pin joint
    `joint`; `link` is the URDF link it belongs to."""

    name: str
    link: str
    joint: int
    local: np.ndarray
    radius: float


def checked_radius(radius: float, where: str) -> float:
    if not radius > 0.0:
        raise ConfigError(f"{where}: a contact sphere's radius must be > 0, got {radius:g}")
    return float(radius)


def check_terrain_reach(points, where: str):
    """A robot's contact spheres are smaller than terrain.BOX_REACH (0.1 m), within which
    the gaps to the terrain's boxes are exact (a test body on flat ground may be larger)."""
    for p in points:
        if not p.radius < BOX_REACH:
            raise ConfigError(f"{where}: contact '{p.name}' (link '{p.link}'): its radius "
                              f"{p.radius:g} m must be < {BOX_REACH:g} m (terrain.BOX_REACH)")


def sphere_point(name, link, joint, placement: pin.SE3, radius, where) -> ContactPointSpec:
    return ContactPointSpec(name, link, joint, placement.translation.copy(),
                            checked_radius(radius, where))


def box_corners(name, link, joint, placement: pin.SE3, size) -> list:
    """The 8 corners of a box of `size` placed at `placement` (in the joint frame)."""
    half = np.asarray(size, dtype=float) / 2.0
    points = []
    for sx in (1, -1):
        for sy in (1, -1):
            for sz in (1, -1):
                corner = placement.act(half * np.array([sx, sy, sz]))
                tag = "".join("p" if s > 0 else "n" for s in (sx, sy, sz))
                points.append(ContactPointSpec(f"{name}_{tag}", link, joint, corner, 0.0))
    return points


def end_spheres(name, link, joint, placement: pin.SE3, radius, length, where) -> list:
    """The spheres covering the ends of a cylinder (or capsule) along its z axis."""
    r = checked_radius(radius, where)
    return [ContactPointSpec(f"{name}_{tag}", link, joint,
                             placement.act(np.array([0.0, 0.0, s * length / 2.0])), r)
            for tag, s in (("p", 1.0), ("n", -1.0))]


def link_frame(model: pin.Model, link: str, where: str) -> pin.Frame:
    """The pinocchio frame of a URDF link (its body frame: parentJoint and placement)."""
    if not model.existFrame(link, pin.FrameType.BODY):
        raise ConfigError(f"{where}: link '{link}' is not a frame of the pinocchio model")
    return model.frames[model.getFrameId(link, pin.FrameType.BODY)]


def collision_name(link_elem, k: int) -> str:
    """A <collision>'s contact name: its own, else the link's (its only collision), else
    <link>_<k>."""
    coll = link_elem.findall("collision")[k]
    lname = link_elem.get("name")
    return coll.get("name") or (lname if len(link_elem.findall("collision")) == 1
                                else f"{lname}_{k}")


def collision_points(link_elem, k: int, model: pin.Model, source: str, kinds=None) -> list:
    """The contact points of the k-th <collision> of a URDF link (module docstring), in the
    frame of the joint that moves the link; only geometries in `kinds` (the others give
    none). Without `kinds`, every contact geometry, and a mesh is a ConfigError naming the
    collision."""
    lname = link_elem.get("name")
    coll = link_elem.findall("collision")[k]
    name = collision_name(link_elem, k)
    where = f"{source}: link '{lname}' collision '{name}'"
    geom = coll.find("geometry")
    shape = geom[0] if geom is not None and len(geom) else None
    if shape is None:
        raise ConfigError(f"{where}: no <geometry>")
    if kinds is None and shape.tag == "mesh":
        raise ConfigError(f"{where}: a <mesh> cannot be contact geometry (no mesh is read): "
                          "give spheres or a box for it in a robot spec (doc/physics.md)")
    if shape.tag not in (CONTACT_GEOMETRIES if kinds is None else kinds):
        return []
    frame = link_frame(model, lname, where)
    placement = frame.placement * urdf_origin(coll, where)
    j = frame.parentJoint
    if shape.tag == "sphere":
        r = numbers(shape.get("radius"), 1, f"{where} <sphere radius>")[0]
        return [sphere_point(name, lname, j, placement, r, where)]
    if shape.tag == "box":
        size = numbers(shape.get("size"), 3, f"{where} <box size>")
        if not np.all(size > 0):
            raise ConfigError(f"{where} <box size>: must be positive, got {shape.get('size')!r}")
        return box_corners(name, lname, j, placement, size)
    if shape.tag in ("cylinder", "capsule"):
        r = numbers(shape.get("radius"), 1, f"{where} <{shape.tag} radius>")[0]
        length = numbers(shape.get("length"), 1, f"{where} <{shape.tag} length>")[0]
        if not length >= 0:
            raise ConfigError(f"{where} <{shape.tag} length>: must not be negative")
        return end_spheres(name, lname, j, placement, r, length, where)
    raise ConfigError(f"{where}: unknown geometry <{shape.tag}>")


def urdf_contact_points(root, model: pin.Model, source: str) -> list:
    """The contact points of every <collision> of the URDF, in document order (the rule of a
    URDF without a robot spec: a mesh is refused)."""
    points = []
    for link in root.findall("link"):
        for k in range(len(link.findall("collision"))):
            points += collision_points(link, k, model, source)
    return points
