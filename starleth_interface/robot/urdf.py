"""Reading a robot's URDF: the checks that turn a description the simulator cannot use into
one line naming the file and the element (a :class:`ConfigError`, before pinocchio sees the
file), and the pinocchio model on a free-flyer root.

What is refused, and why:

- text that is not XML, or whose root element is not ``<robot>``;
- a joint of a type other than ``revolute`` and ``fixed`` (``continuous``, ``prismatic``,
  ``planar``, ``floating``: the kernels integrate revolute angles only), a revolute joint
  with a zero axis;
- a joint naming a link that does not exist, two links or two joints of one name;
- a closed loop (a link that is the child of two joints, or joints that lead back to where
  they started) and a forest (more than one link without a parent joint): a URDF is one
  tree, its root the floating base;
- a number that is not one (``xyz="0 a 0"``) or not finite;
- a negative mass; a body (a link moved by a joint, with the links fixed to it) without
  mass, or whose rotational inertia is not positive semi-definite: its row of the mass
  matrix would be singular. A link without ``<inertial>`` is fine when it is fixed to one
  that has mass (sensor frames, the feet of many robots).
"""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin

from ..config_checks import ConfigError

#: the joint types the simulator moves (fixed joints merge their child into the parent body)
SUPPORTED_JOINTS = ("revolute", "fixed")
URDF_JOINT_TYPES = ("revolute", "continuous", "prismatic", "fixed", "floating", "planar")


def parse_urdf(urdf_xml: str, source: str) -> ET.Element:
    """The <robot> element of a URDF text; ConfigError naming `source` if it is none."""
    try:
        root = ET.fromstring(urdf_xml)
    except ET.ParseError as e:
        raise ConfigError(f"{source}: not valid XML: {e}") from None
    if root.tag != "robot":
        raise ConfigError(f"{source}: not a URDF: the root element is <{root.tag}>, not <robot>")
    return root


def numbers(text, count: int, where: str) -> np.ndarray:
    """`count` finite numbers of an attribute's text; ConfigError naming `where` otherwise."""
    parts = (text or "").split()
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ConfigError(f"{where}: expected {count} numbers, got {text!r}") from None
    if len(values) != count:
        raise ConfigError(f"{where}: expected {count} numbers, got {text!r}")
    if not all(math.isfinite(v) for v in values):
        raise ConfigError(f"{where}: must be finite, got {text!r}")
    return np.array(values)


def urdf_origin(elem, where: str = "URDF") -> pin.SE3:
    """The placement of an element's <origin> (xyz, rpy); identity without one."""
    o = elem.find("origin") if elem is not None else None
    xyz, rpy = np.zeros(3), np.zeros(3)
    if o is not None:
        if o.get("xyz") is not None:
            xyz = numbers(o.get("xyz"), 3, f"{where} <origin xyz>")
        if o.get("rpy") is not None:
            rpy = numbers(o.get("rpy"), 3, f"{where} <origin rpy>")
    return pin.SE3(pin.rpy.rpyToMatrix(*rpy), xyz)


def check_tree(root: ET.Element, source: str) -> str:
    """Checks the links and joints form one tree of supported joints (module docstring);
    returns the root link's name."""
    links = _link_names(root, source)
    parent_of, seen = {}, set()
    for joint in root.findall("joint"):
        name, parent, child = _checked_joint(joint, links, seen, source)
        if child in parent_of:
            raise ConfigError(f"{source}: joint '{name}': closed loop: link '{child}' is "
                              f"already the child of joint '{parent_of[child][0]}' (a URDF is "
                              "a tree)")
        parent_of[child] = (name, parent)
    return _root_of(links, parent_of, source)


def _link_names(root, source):
    """The <link> names, in order: each named, once; at least one."""
    links = []
    for link in root.findall("link"):
        name = link.get("name")
        if not name:
            raise ConfigError(f"{source}: a <link> without a name")
        if name in links:
            raise ConfigError(f"{source}: link '{name}' is defined twice")
        links.append(name)
    if not links:
        raise ConfigError(f"{source}: the URDF has no <link>")
    return links


def _checked_joint(joint, links, seen, source):
    """(name, parent link, child link) of a <joint> whose name is new (added to `seen`),
    type supported, ends links of the URDF, origin, limits and axis well formed."""
    name, kind = joint.get("name"), joint.get("type")
    where = f"{source}: joint '{name}'"
    if not name:
        raise ConfigError(f"{source}: a <joint> without a name")
    if name in seen:
        raise ConfigError(f"{where}: defined twice")
    seen.add(name)
    if kind not in SUPPORTED_JOINTS:
        what = f"type '{kind}'" if kind in URDF_JOINT_TYPES else f"unknown type {kind!r}"
        raise ConfigError(f"{where}: {what} is not supported (revolute and fixed joints "
                          "only)")
    ends = []
    for end in ("parent", "child"):
        e = joint.find(end)
        link = e.get("link") if e is not None else None
        if link not in links:
            raise ConfigError(f"{where}: its {end} link {link!r} is not a link of the URDF")
        ends.append(link)
    urdf_origin(joint, where)
    limit = joint.find("limit")
    for k in ("lower", "upper", "effort", "velocity"):
        if limit is not None and limit.get(k) is not None:
            numbers(limit.get(k), 1, f"{where} <limit {k}>")
    if kind == "revolute":
        axis = joint.find("axis")
        a = numbers(axis.get("xyz"), 3, f"{where} <axis xyz>") if axis is not None \
            else np.array([1.0, 0.0, 0.0])
        if not np.linalg.norm(a) > 1e-9:
            raise ConfigError(f"{where}: <axis xyz>: a zero axis")
    return name, ends[0], ends[1]


def _root_of(links, parent_of, source):
    """The one root link of the tree {child: (joint, parent)}; a second root or a loop that
    does not reach the root is refused."""
    roots = [link for link in links if link not in parent_of]
    if not roots:
        raise ConfigError(f"{source}: closed loop: every link is the child of a joint (a URDF "
                          "is a tree)")
    if len(roots) > 1:
        raise ConfigError(f"{source}: links {', '.join(repr(r) for r in roots[:4])} have no "
                          "parent joint: a URDF is one tree (one root link, the base)")
    for link in links:     # a cycle that does not reach the root
        path, at = [], link
        while at in parent_of:
            if at in path:
                raise ConfigError(f"{source}: closed loop: joint '{parent_of[at][0]}' leads "
                                  f"back to link '{at}' (a URDF is a tree)")
            path.append(at)
            at = parent_of[at][1]
    return roots[0]


def check_inertials(root: ET.Element, source: str):
    """No negative or non-finite mass on any link (whether a zero mass matters is known once
    fixed links are merged: check_bodies), every <origin> of a link readable."""
    for link in root.findall("link"):
        for part in ("inertial", "visual", "collision"):
            for k, elem in enumerate(link.findall(part)):
                urdf_origin(elem, f"{source}: link '{link.get('name')}' <{part}> {k}")
        mass = link.find("inertial/mass")
        if mass is None:
            continue
        where = f"{source}: link '{link.get('name')}' <mass>"
        value = numbers(mass.get("value"), 1, where)[0]
        if value < 0:
            raise ConfigError(f"{where}: must not be negative, got {value:g}")
        inertia = link.find("inertial/inertia")
        if inertia is not None:
            for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz"):
                numbers(inertia.get(k, "0"), 1, f"{source}: link '{link.get('name')}' "
                                                f"<inertia {k}>")


def body_link(model: pin.Model, j: int) -> str:
    """The name of the link that joint j moves (its body's first link frame)."""
    for f in model.frames:
        if f.parentJoint == j and f.type == pin.FrameType.BODY:
            return f.name
    return model.names[j]


def check_bodies(model: pin.Model, source: str):
    """Every moving body (with its fixed links) has a positive mass and a positive
    semi-definite rotational inertia."""
    for j in range(1, model.njoints):
        inertia = model.inertias[j]
        link = body_link(model, j)
        moved = "the floating base" if j == 1 else f"moved by joint '{model.names[j]}'"
        if not inertia.mass > 0:
            raise ConfigError(f"{source}: link '{link}' ({moved}): no mass: give it an "
                              "<inertial> with a positive <mass> (no link fixed to it has one)")
        eig = np.linalg.eigvalsh(0.5 * (inertia.inertia + inertia.inertia.T))
        if eig.min() < -1e-9 * max(1.0, abs(eig).max()):
            raise ConfigError(f"{source}: link '{link}' ({moved}): its rotational inertia is "
                              f"not positive semi-definite (eigenvalues {eig.min():.3g} .. "
                              f"{eig.max():.3g} kg m^2)")


def checked_model(urdf_xml: str, source: str) -> tuple[ET.Element, pin.Model]:
    """The URDF's <robot> element and its pinocchio model on a free-flyer root, after the
    checks of the module docstring; ConfigError naming `source` and the element."""
    root = parse_urdf(urdf_xml, source)
    check_tree(root, source)
    check_inertials(root, source)
    try:
        model = pin.buildModelFromXML(urdf_xml, pin.JointModelFreeFlyer())
    except Exception as e:     # pinocchio's own refusal (the checks above miss it)
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ConfigError(f"{source}: pinocchio cannot read the URDF: {first}") from None
    check_bodies(model, source)
    return root, model


_ALIGNED_AXES = {"JointModelRX": (1.0, 0.0, 0.0), "JointModelRY": (0.0, 1.0, 0.0),
                 "JointModelRZ": (0.0, 0.0, 1.0)}


def revolute_axis(jm) -> np.ndarray | None:
    """The axis (in its joint frame) of a revolute pinocchio joint model: RX, RY, RZ, or
    RevoluteUnaligned (a URDF axis not along x, y or z, or along -x: ANYmal C); None for any
    other joint."""
    name = jm.shortname()
    if name in _ALIGNED_AXES:
        return np.array(_ALIGNED_AXES[name])
    if name == "JointModelRevoluteUnaligned":
        return np.asarray(jm.extract().axis, dtype=float)
    return None


def document_joint_order(root: ET.Element) -> tuple:
    """The names of the URDF's moving (non-fixed) joints in document order: the public
    joint order of every interface (torques, joint states)."""
    return tuple(j.get("name") for j in root.findall("joint") if j.get("type") != "fixed")
