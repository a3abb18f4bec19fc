"""Robot descriptions: the StarlETH URDF, generic test bodies (sphere, box), and the contact
points read from URDF <collision> elements.

A sphere collision gives one contact point (centre and radius); a box gives its 8 corners
(radius 0). The contact point names are `<collision name>` (spheres) and
`<collision name>_<sx><sy><sz>` with s = p/n for the sign of each box half-extent.
"""
from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
import pinocchio as pin

LEGS = ("LF", "RF", "LH", "RH")
JOINTS_PER_LEG = ("HAA", "HFE", "KFE")
#: Joint order of every public interface (torques, joint states): LF/RF/LH/RH x HAA/HFE/KFE.
STARLETH_JOINT_NAMES = tuple(f"{leg}_{j}" for leg in LEGS for j in JOINTS_PER_LEG)
STARLETH_FEET = tuple(f"{leg}_foot" for leg in LEGS)
#: Nominal standing trunk height of our StarlETH model, with the feet below the hips [m].
STARLETH_STANDING_HEIGHT = 0.415


def package_share_dir() -> str:
    """Directory holding `urdf/` and `msg_configs/`: the source tree, or the colcon install's
    share/starleth_sim when running from an install."""
    here = os.path.dirname(os.path.abspath(__file__))          # starleth_sim/physics
    src = os.path.dirname(os.path.dirname(here))
    if os.path.isdir(os.path.join(src, "urdf")) and os.path.isdir(os.path.join(src, "msg_configs")):
        return src
    try:  # installed by colcon
        from ament_index_python.packages import get_package_share_directory
        return get_package_share_directory("starleth_sim")
    except Exception:  # pragma: no cover - only without a source tree and without ament
        pass
    raise FileNotFoundError("cannot find the starleth_sim data directory (urdf/, msg_configs/)")


def urdf_path(name: str = "starleth.urdf") -> str:
    return os.path.join(package_share_dir(), "urdf", name)


@dataclass(frozen=True)
class ContactPointSpec:
    """A contact point: a sphere of `radius` centred at `local` in the frame of pin joint
    `joint`."""

    name: str
    link: str
    joint: int
    local: np.ndarray
    radius: float


def urdf_origin(elem):
    """The placement (pin.SE3) of a URDF element's <origin> (xyz, rpy); identity without one."""
    o = elem.find("origin") if elem is not None else None
    xyz = np.zeros(3)
    rpy = np.zeros(3)
    if o is not None:
        if o.get("xyz"):
            xyz = np.array([float(v) for v in o.get("xyz").split()])
        if o.get("rpy"):
            rpy = np.array([float(v) for v in o.get("rpy").split()])
    return pin.SE3(pin.rpy.rpyToMatrix(*rpy), xyz)


def contact_points_from_urdf(urdf_xml: str, model: pin.Model) -> list[ContactPointSpec]:
    root = ET.fromstring(urdf_xml)
    specs = []
    for link in root.findall("link"):
        lname = link.get("name")
        colls = link.findall("collision")
        if not colls:
            continue
        if not model.existFrame(lname):
            raise ValueError(f"link '{lname}' of the URDF is not a frame of the pin model")
        frame = model.frames[model.getFrameId(lname)]
        for k, coll in enumerate(colls):
            cname = coll.get("name") or f"{lname}_{k}"
            placement = frame.placement * urdf_origin(coll)
            geom = coll.find("geometry")
            sphere = geom.find("sphere") if geom is not None else None
            box = geom.find("box") if geom is not None else None
            if sphere is not None:
                specs.append(ContactPointSpec(cname, lname, frame.parentJoint,
                                              placement.translation.copy(),
                                              float(sphere.get("radius"))))
            elif box is not None:
                half = np.array([float(v) for v in box.get("size").split()]) / 2.0
                for sx in (1, -1):
                    for sy in (1, -1):
                        for sz in (1, -1):
                            corner = placement.act(half * np.array([sx, sy, sz]))
                            tag = "".join("p" if s > 0 else "n" for s in (sx, sy, sz))
                            specs.append(ContactPointSpec(f"{cname}_{tag}", lname,
                                                          frame.parentJoint, corner, 0.0))
            else:
                raise ValueError(f"collision '{cname}' of link '{lname}': only <sphere> and "
                                 "<box> geometries are supported as contact geometry")
    return specs


@dataclass
class RobotDescription:
    """A pin model on a free-flyer root, its actuated joints and its contact points."""

    name: str
    urdf_xml: str
    model: pin.Model
    contacts: list
    joint_names: tuple = ()
    effort_limit: np.ndarray = field(default_factory=lambda: np.zeros(0))
    velocity_limit: np.ndarray = field(default_factory=lambda: np.zeros(0))
    position_lower: np.ndarray = field(default_factory=lambda: np.zeros(0))
    position_upper: np.ndarray = field(default_factory=lambda: np.zeros(0))
    foot_names: tuple = ()
    standing_height: float | None = None

    @classmethod
    def from_urdf_xml(cls, urdf_xml: str, name: str = "robot", joint_names=None, **kw):
        model = pin.buildModelFromXML(urdf_xml, pin.JointModelFreeFlyer())
        if joint_names is None:
            joint_names = tuple(model.names[j] for j in range(2, model.njoints))
        for jn in joint_names:
            if not model.existJointName(jn):
                raise ValueError(f"joint '{jn}' is not in the URDF")
        ids = [model.getJointId(jn) for jn in joint_names]
        iq = [model.joints[j].idx_q for j in ids]
        iv = [model.joints[j].idx_v for j in ids]
        desc = cls(name=name, urdf_xml=urdf_xml, model=model,
                   contacts=contact_points_from_urdf(urdf_xml, model),
                   joint_names=tuple(joint_names),
                   effort_limit=np.array(model.effortLimit)[iv].copy(),
                   velocity_limit=np.array(model.velocityLimit)[iv].copy(),
                   position_lower=np.array(model.lowerPositionLimit)[iq].copy(),
                   position_upper=np.array(model.upperPositionLimit)[iq].copy(), **kw)
        return desc

    @property
    def total_mass(self) -> float:
        return float(sum(inertia.mass for inertia in self.model.inertias))

    def contact_names(self):
        return [c.name for c in self.contacts]


@lru_cache(maxsize=None)
def _read(path):
    with open(path) as f:
        return f.read()


def starleth_description(path: str | None = None) -> RobotDescription:
    """StarlETH from `urdf/starleth.urdf` (or the given URDF with the same joint names)."""
    xml = _read(path or urdf_path())
    desc = RobotDescription.from_urdf_xml(xml, name="starleth", joint_names=STARLETH_JOINT_NAMES,
                                          foot_names=STARLETH_FEET,
                                          standing_height=STARLETH_STANDING_HEIGHT)
    # public contact order: feet (LF, RF, LH, RH), knees, then everything else (trunk)
    order = [f"{leg}_foot" for leg in LEGS] + [f"{leg}_knee" for leg in LEGS]
    rank = {n: k for k, n in enumerate(order)}
    desc.contacts.sort(key=lambda c: rank.get(c.name, len(order)))
    return desc


def leg_angles_for_height(height: float, desc: RobotDescription):
    """HFE, KFE (front leg; the hind leg mirrors both) that put the foot contact point
    straight below the HFE axis at trunk height `height` with HAA = 0, on flat ground.

    Uses the model's own geometry (HFE offset, thigh and shank lengths, foot radius)."""
    m = desc.model
    def trans(name):
        return m.jointPlacements[m.getJointId(name)].translation
    l0 = -trans("LF_HFE")[2]
    l1 = -trans("LF_KFE")[2]
    foot = next(c for c in desc.contacts if c.name == "LF_foot")
    l2 = -foot.local[2]
    r = foot.radius
    d = height - l0 - r  # vertical HFE-to-foot-centre distance, foot below the HFE
    if not (abs(l1 - l2) < d < l1 + l2):
        raise ValueError(f"standing height {height} m is out of reach of the legs")
    # knee angle from the law of cosines; X configuration: front KFE < 0
    cos_k = (d * d - l1 * l1 - l2 * l2) / (2 * l1 * l2)
    kfe = -np.arccos(np.clip(cos_k, -1.0, 1.0))
    # thigh angle so that the foot is straight below: l1 sin(h) + l2 sin(h + k) = 0
    hfe = np.arctan2(l2 * np.sin(-kfe), l1 + l2 * np.cos(kfe))
    return float(hfe), float(kfe)


def sphere_urdf(radius: float = 0.1, mass: float = 1.0, name: str = "ball") -> str:
    """A solid sphere (I = 2/5 m r^2) whose collision is the sphere itself."""
    i = 0.4 * mass * radius ** 2
    return f"""<?xml version="1.0"?>
<robot name="{name}">
  <link name="body">
    <inertial><mass value="{mass!r}"/>
      <inertia ixx="{i!r}" ixy="0" ixz="0" iyy="{i!r}" iyz="0" izz="{i!r}"/></inertial>
    <collision name="{name}"><geometry><sphere radius="{radius!r}"/></geometry></collision>
  </link>
</robot>
"""


def box_urdf(size=(0.2, 0.2, 0.2), mass: float = 1.0, name: str = "box") -> str:
    """A solid box; its 8 corners are contact points."""
    a, b, c = size
    ixx = mass * (b * b + c * c) / 12
    iyy = mass * (a * a + c * c) / 12
    izz = mass * (a * a + b * b) / 12
    return f"""<?xml version="1.0"?>
<robot name="{name}">
  <link name="body">
    <inertial><mass value="{mass!r}"/>
      <inertia ixx="{ixx!r}" ixy="0" ixz="0" iyy="{iyy!r}" iyz="0" izz="{izz!r}"/></inertial>
    <collision name="{name}"><geometry><box size="{a!r} {b!r} {c!r}"/></geometry></collision>
  </link>
</robot>
"""
