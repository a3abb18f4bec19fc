"""A RobotDescription from a robot spec: its URDF (checked, physics/urdf.py), the contact
points the spec chooses (feet first, in the legs' order, then the spec's contacts in their
order, each entry's links in URDF document order), the limits it overrides, and its
standing height (checked by solving the standing posture). And the description and the
physics configuration of a `robot` value (a library name, a spec path or a URDF path)."""
from __future__ import annotations

import os
from dataclasses import fields, is_dataclass

import numpy as np
import pinocchio as pin

from starleth_interface.config_checks import ConfigError
from starleth_interface.robot.contact_points import (
    box_corners,
    check_terrain_reach,
    collision_points,
    link_frame,
    sphere_point,
)
from starleth_interface.robot.feet import foot_points, link_elements
from starleth_interface.robot.library import load_robot, read_text, resolve, urdf_file
from starleth_interface.robot.spec import (
    MAX_EFFORT,
    MAX_VELOCITY,
    ContactEntry,
    RobotSpec,
    mapping,
    match_names,
    override_limits,
    spec_from_dict,
)
from starleth_interface.robot.urdf import checked_model, document_joint_order
from starleth_interface.yaml_files import load_yaml_text

from .config import PhysicsConfig
from .description import RobotDescription


def _entry_points(entry: ContactEntry, root, model, source, label) -> list:
    links = link_elements(root)
    where = f"{label}: {entry.where}"
    points = []
    for name in match_names(entry.links, list(links), f"{where}.links"):
        frame = link_frame(model, name, where)
        j, tag = frame.parentJoint, f"{name}_{entry.name}" if entry.name else name
        if entry.urdf:
            got = [p for k in range(len(links[name].findall("collision")))
                   for p in collision_points(links[name], k, model, source, entry.urdf)]
            if not got:
                raise ConfigError(f"{where}.urdf: link '{name}' has no "
                                  f"{'/'.join(f'<{k}>' for k in entry.urdf)} collision")
            points += got
        elif entry.spheres:
            for k, s in enumerate(entry.spheres):
                at = frame.placement * pin.SE3(np.eye(3), np.array(s.at))
                points.append(sphere_point(tag if len(entry.spheres) == 1 else f"{tag}{k}",
                                           name, j, at, s.radius, f"{where}.spheres[{k}]"))
        else:
            b = entry.box
            at = frame.placement * pin.SE3(pin.rpy.rpyToMatrix(*b.rpy), np.array(b.at))
            points += box_corners(tag if entry.name else f"{name}_box", name, j, at, b.size)
    return points


def _limits(spec: RobotSpec, desc: RobotDescription):
    """The spec's effort and velocity limits over the URDF's; each joint's must then be a
    real one (not a placeholder)."""
    names = list(desc.joint_names)
    for kind, cap, unit in (("effort", MAX_EFFORT, "N m"), ("velocity", MAX_VELOCITY, "rad/s")):
        limit = getattr(desc, f"{kind}_limit")
        override_limits(spec, names, kind, limit)
        for n, x in zip(names, limit, strict=True):
            if not 0 < x < cap:
                why = f"a placeholder (>= {cap:g})" if x >= cap else "not positive"
                raise ConfigError(f"{desc.source}: joint '{n}': its {kind} limit {x:g} {unit} "
                                  f"is {why}: give limits.{kind} in {spec.label}")


def description_from_spec(spec: RobotSpec, urdf_xml: str | None = None,
                          urdf_name: str | None = None) -> RobotDescription:
    """The description of a robot spec (module docstring); ConfigError naming the spec or
    the URDF and the field or element. `urdf_xml` (named `urdf_name` in messages) stands for
    the spec's URDF file: a recording's copy."""
    if urdf_xml is None:
        path = urdf_file(spec)
        xml, urdf_name = read_text(path), os.path.basename(path)
    else:
        xml, urdf_name = urdf_xml, urdf_name or f"{spec.name}.urdf"
    source = f"{urdf_name} ({spec.label})"
    root, model = checked_model(xml, source)
    joint_names = document_joint_order(root)
    feet = foot_points(spec, root, model, source, joint_names)
    contacts = list(feet)
    for entry in spec.contacts:
        contacts += _entry_points(entry, root, model, source, spec.label)
    check_terrain_reach(contacts, source)
    seen = set()
    for c in contacts:
        if c.name in seen:
            raise ConfigError(f"{spec.label}: contacts: two contact points named '{c.name}'")
        seen.add(c.name)
    desc = RobotDescription.from_model(spec.name, xml, model, contacts, source, joint_names,
                                       tuple(p.name for p in feet),
                                       standing_height=spec.standing_height, knees=spec.knees)
    _limits(spec, desc)
    if spec.standing_height is not None:
        try:
            desc.standing_joints()
        except ValueError as e:
            raise ConfigError(f"{spec.label}: standing: {e}") from None
    return desc


def robot_description(robot: str = "starleth") -> RobotDescription:
    """The description a `robot` value names: a library name or a spec path (through its
    spec), or a URDF path (no spec: RobotDescription.from_urdf_xml's rules)."""
    kind, path = resolve(robot)
    if kind == "urdf":
        name = os.path.splitext(os.path.basename(path))[0]
        return RobotDescription.from_urdf_xml(read_text(path), name=name, source=path)
    return description_from_spec(load_robot(path))


def spec_text(robot: str) -> str | None:
    """The YAML text of the spec a `robot` value names (None for a URDF path): what a
    recording keeps so that it rebuilds the robot without the library."""
    kind, path = resolve(robot)
    return read_text(os.path.abspath(path)) if kind == "spec" else None


def recorded_description(urdf_xml: str, spec_yaml: str | None, name: str,
                         where: str = "recording") -> RobotDescription:
    """The description of a recorded robot: its URDF text and its spec's YAML text (None: a
    robot from a URDF alone); ConfigError naming `where` and the field."""
    if spec_yaml is None:
        return RobotDescription.from_urdf_xml(urdf_xml, name=name, source=f"{where}: {name}.urdf")
    spec = spec_from_dict(load_yaml_text(spec_yaml, f"{where}: {name}.robot.yaml"),
                          f"{name}.robot.yaml")
    return description_from_spec(spec, urdf_xml=urdf_xml, urdf_name=f"{name}.urdf")


def starleth_description() -> RobotDescription:
    """StarlETH, the paper's robot (robots/starleth.yaml)."""
    return robot_description("starleth")


def config_with_robot(config: PhysicsConfig, robot: str) -> PhysicsConfig:
    """A copy of `config` for `robot`: its `robot` field, and the spec's physics overrides
    (a robot's own values over the preset's: Solo12's compliant contact)."""
    kind, _ = resolve(robot)
    physics = physics_overrides(load_robot(robot)) if kind == "spec" else {}
    return config.with_overrides(robot=robot, **physics)


def physics_overrides(spec: RobotSpec) -> dict:
    """A spec's `physics:` overrides as dotted names (section.field), checked by applying them
    to the default config; ConfigError naming the spec and the field."""
    where = f"{spec.label}: physics"
    default = PhysicsConfig()
    sections = tuple(f.name for f in fields(default) if is_dataclass(getattr(default, f.name)))
    dotted = {}
    for section, values in mapping(where, spec.physics, sections).items():
        names = tuple(f.name for f in fields(getattr(default, section)))
        for k, x in mapping(f"{where}.{section}", values, names).items():
            dotted[f"{section}.{k}"] = x
    try:
        default.with_overrides(**dotted)
    except ConfigError as e:     # "<config name> (with overrides): <field>: <rule>"
        raise ConfigError(f"{where}.{str(e).split(': ', 1)[-1]}") from None
    return dotted

