"""The robot spec: one YAML file per robot of the library (``robots/<name>.yaml``), validated
on load; every refusal is one line naming the file and the field, e.g.
``go2.yaml: feet.radius: must be < 0.1, got 0.2``. doc/physics.md describes the schema:

    name: go1                                  # the robot's library name
    description: Unitree Go1                   # optional
    urdf:
      distribution: example-robot-data         # optional: a Python distribution holding it
      path: cmeel.prefix/share/.../go1.urdf    # in the distribution, else relative to the spec
      packages: cmeel.prefix/share             # optional: the root of package:// URIs
    feet:                                      # optional
      links: [FL_foot, FR_foot, RL_foot, RR_foot]   # default: found on the legs
      radius: 0.02                             # a sphere on each foot link (default: the URDF's)
      at: [0, 0, 0]                            # its centre in the link frame
    contacts:                                  # what else touches the ground, in this order
      - {links: [trunk], urdf: [box]}          # the links' URDF boxes: their 8 corners
      - {links: ["*_calf"], name: knee, spheres: [{at: [0, 0, 0], radius: 0.017}]}
      - {links: [base], name: trunk, box: {size: [0.4, 0.2, 0.1], at: [0, 0, 0]}}
    standing: {height: 0.27, knees: auto}      # knees: auto|backward|forward|{front:, hind:}
    limits: {effort: {"*_calf_joint": 35.55}, velocity: {}}   # joint-name globs
    physics: {contact: {stiffness_normal: 3000.0}}            # this robot's preset overrides
"""
from __future__ import annotations

import fnmatch
import os
from dataclasses import dataclass, field

from ..config_checks import ConfigError, check_number, check_str, short_repr
from ..yaml_files import load_yaml_file
from .contact_points import BOX_REACH
from .legs import check_knees

#: limits at or above these are a URDF's placeholders (Solo12's 1000 N m, 1000 rad/s): the
#: spec must give real ones
MAX_EFFORT = 1000.0          # N m
MAX_VELOCITY = 1000.0        # rad/s
MAX_SIZE = 10.0              # m: positions and box sizes on a robot's scale
URDF_KINDS = ("sphere", "box", "cylinder", "capsule")


@dataclass(frozen=True)
class UrdfSource:
    path: str
    distribution: str | None = None
    packages: str | None = None


@dataclass(frozen=True)
class Sphere:
    at: tuple
    radius: float


@dataclass(frozen=True)
class Box:
    size: tuple
    at: tuple = (0.0, 0.0, 0.0)
    rpy: tuple = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class ContactEntry:
    """Links (names or globs) and what of them touches the ground: their URDF primitives
    of the given kinds, spheres, or a box (module docstring); `where` names the entry."""

    links: tuple
    where: str
    name: str | None = None
    urdf: tuple = ()
    spheres: tuple = ()
    box: Box | None = None


@dataclass(frozen=True)
class Feet:
    links: tuple | None = None
    radius: float | None = None
    at: tuple = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class RobotSpec:
    name: str
    file: str
    urdf: UrdfSource
    description: str = ""
    feet: Feet = field(default_factory=Feet)
    contacts: tuple = ()
    standing_height: float | None = None
    knees: str | dict = "auto"
    effort: dict = field(default_factory=dict)
    velocity: dict = field(default_factory=dict)
    #: the preset overrides of this robot, as written ({contact: {stiffness_normal: 3000}});
    #: the simulator checks them (starleth_sim.physics.robot_build.physics_overrides)
    physics: dict = field(default_factory=dict)

    @property
    def label(self) -> str:
        """The spec's file name, for messages."""
        return os.path.basename(self.file)


def mapping(where, v, known, required=()):
    """The mapping `v` of the fields `known` (and the `required` ones); ConfigError naming
    `where` and the field."""
    if not isinstance(v, dict):
        raise ConfigError(f"{where}: expected a mapping, got {short_repr(v)}")
    for k in v:
        if k not in known:
            raise ConfigError(f"{where}: unknown field {short_repr(k)} (known: "
                              f"{', '.join(known)})")
    for k in required:
        if k not in v:
            raise ConfigError(f"{where}: missing field '{k}'")
    return v


def _list(where, v, nonempty=True):
    if not isinstance(v, list) or (nonempty and not v):
        raise ConfigError(f"{where}: expected a{' non-empty' if nonempty else ''} list, got "
                          f"{short_repr(v)}")
    return v


def _names(where, v):
    names = tuple(check_str(f"{where}[{i}]", x) for i, x in enumerate(_list(where, v)))
    if any(not n for n in names):
        raise ConfigError(f"{where}: an empty name")
    return names


def _vector(where, v, lo=-MAX_SIZE, hi=MAX_SIZE, lo_open=False):
    if not isinstance(v, list) or len(v) != 3:
        raise ConfigError(f"{where}: expected a list of 3 numbers, got {short_repr(v)}")
    return tuple(check_number(f"{where}[{i}]", x, lo, hi, lo_open=lo_open)
                 for i, x in enumerate(v))


def _radius(where, v):
    return check_number(where, v, 0.0, BOX_REACH, lo_open=True, hi_open=True)


def _urdf(where, v):
    v = mapping(where, v, ("path", "distribution", "packages"), ("path",))
    return UrdfSource(path=check_str(f"{where}.path", v["path"]),
                      distribution=None if v.get("distribution") is None
                      else check_str(f"{where}.distribution", v["distribution"]),
                      packages=None if v.get("packages") is None
                      else check_str(f"{where}.packages", v["packages"]))


def _feet(where, v):
    v = mapping(where, v, ("links", "radius", "at"))
    links = _names(f"{where}.links", v["links"]) if "links" in v else None
    radius = _radius(f"{where}.radius", v["radius"]) if "radius" in v else None
    if radius is not None and links is None:
        raise ConfigError(f"{where}.radius: give feet.links too (the links the spheres are on)")
    if "at" in v and radius is None:
        raise ConfigError(f"{where}.at: only with feet.radius (a sphere the spec makes)")
    return Feet(links, radius, _vector(f"{where}.at", v["at"]) if "at" in v else (0.0,) * 3)


def _contact(where, v):
    v = mapping(where, v, ("links", "name", "urdf", "spheres", "box"), ("links",))
    given = [k for k in ("urdf", "spheres", "box") if k in v]
    if len(given) != 1:
        raise ConfigError(f"{where}: give exactly one of urdf, spheres, box (got "
                          f"{', '.join(given) or 'none'})")
    links = _names(f"{where}.links", v["links"])
    name = check_str(f"{where}.name", v["name"]) if "name" in v else None
    if "urdf" in v:
        kinds = _names(f"{where}.urdf", v["urdf"])
        for i, k in enumerate(kinds):
            if k == "mesh":
                raise ConfigError(f"{where}.urdf[{i}]: a mesh cannot be contact geometry (no "
                                  "mesh is read): give spheres or a box for it")
            if k not in URDF_KINDS:
                raise ConfigError(f"{where}.urdf[{i}]: must be one of {list(URDF_KINDS)}, got "
                                  f"{short_repr(k)}")
        return ContactEntry(links, where, name, urdf=kinds)
    if "spheres" in v:
        spheres = []
        for i, s in enumerate(_list(f"{where}.spheres", v["spheres"])):
            w = f"{where}.spheres[{i}]"
            s = mapping(w, s, ("at", "radius"), ("radius",))
            spheres.append(Sphere(_vector(f"{w}.at", s.get("at", [0.0, 0.0, 0.0])),
                                  _radius(f"{w}.radius", s["radius"])))
        return ContactEntry(links, where, name, spheres=tuple(spheres))
    b = mapping(f"{where}.box", v["box"], ("size", "at", "rpy"), ("size",))
    box = Box(_vector(f"{where}.box.size", b["size"], 0.0, MAX_SIZE, lo_open=True),
              _vector(f"{where}.box.at", b.get("at", [0.0, 0.0, 0.0])),
              _vector(f"{where}.box.rpy", b.get("rpy", [0.0, 0.0, 0.0]), -7.0, 7.0))
    return ContactEntry(links, where, name, box=box)


def _limits(where, v):
    v = mapping(where, v, ("effort", "velocity"))
    out = {}
    for kind, hi in (("effort", MAX_EFFORT), ("velocity", MAX_VELOCITY)):
        m = v.get(kind) or {}
        mapping(f"{where}.{kind}", m, tuple(m))
        out[kind] = {check_str(f"{where}.{kind}: a joint name", k):
                     check_number(f"{where}.{kind}.{k}", x, 0.0, hi, lo_open=True, hi_open=True)
                     for k, x in m.items()}
    return out["effort"], out["velocity"]


def _physics(where, v):
    """The physics overrides as written: a mapping (the simulator checks its fields)."""
    return dict(mapping(where, v, tuple(v) if isinstance(v, dict) else ()))


def _standing(where, v):
    v = mapping(where, v, ("height", "knees"), ("height",))
    return (check_number(f"{where}.height", v["height"], 0.0, MAX_SIZE, lo_open=True),
            check_knees(v.get("knees", "auto"), f"{where}.knees"))


def spec_from_dict(data, file: str) -> RobotSpec:
    """A RobotSpec of the YAML document `data` read from `file` (ConfigError naming the file
    and the field)."""
    label = os.path.basename(file)
    known = ("name", "description", "urdf", "feet", "contacts", "standing", "limits", "physics")
    try:
        d = mapping("spec", data, known, ("name", "urdf"))
        name = check_str("name", d["name"])
        if not name or not all(c.isalnum() or c in "_-" for c in name):
            raise ConfigError(f"name: letters, digits, '_' and '-' only, got {short_repr(name)}")
        height, knees = _standing("standing", d["standing"]) if "standing" in d \
            else (None, "auto")
        effort, velocity = _limits("limits", d["limits"]) if "limits" in d else ({}, {})
        return RobotSpec(
            name=name, file=file, urdf=_urdf("urdf", d["urdf"]),
            description=check_str("description", d.get("description", "")),
            feet=_feet("feet", d["feet"]) if "feet" in d else Feet(),
            contacts=tuple(_contact(f"contacts[{i}]", c)
                           for i, c in enumerate(_list("contacts", d.get("contacts", []),
                                                       nonempty=False))),
            standing_height=height, knees=knees, effort=effort, velocity=velocity,
            physics=_physics("physics", d["physics"]) if "physics" in d else {})
    except ConfigError as e:
        raise ConfigError(f"{label}: {str(e).removeprefix('spec: ')}") from None


def match_names(patterns, names, where, what="link"):
    """The names (in their order) matching any of the patterns (names or globs) of a spec
    field `where`; each pattern must match one."""
    for p in patterns:
        if not fnmatch.filter(names, p):
            raise ConfigError(f"{where}: '{p}' matches no {what} of the URDF")
    return [n for n in names if any(fnmatch.fnmatchcase(n, p) for p in patterns)]


def override_limits(spec: RobotSpec, joint_names, kind: str, limit) -> None:
    """The spec's `kind` ('effort' or 'velocity') limits written over `limit` (an array in
    the order of `joint_names`), each glob onto the joints it matches; ConfigError naming
    the spec where a glob matches no joint."""
    names = list(joint_names)
    for pattern, value in getattr(spec, kind).items():
        for n in match_names([pattern], names, f"{spec.label}: limits.{kind}", "moving joint"):
            limit[names.index(n)] = value


def read_spec(path: str) -> RobotSpec:
    """The robot spec of a YAML file (project's YAML loader: duplicate keys, size)."""
    return spec_from_dict(load_yaml_file(path, os.path.basename(path)), path)
