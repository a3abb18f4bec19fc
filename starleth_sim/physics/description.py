"""Robot descriptions: a robot's pinocchio model on a free-flyer root, its public joint
order, its contact points, its legs and its standing height; and generic test bodies
(sphere, box).

A description is built from a URDF (:meth:`RobotDescription.from_urdf_xml`: the checks of
:mod:`starleth_interface.robot.urdf`, contact points of
:mod:`starleth_interface.robot.contact_points`, legs of :mod:`starleth_interface.robot.legs`),
usually through a robot spec of the robot library
(``starleth_sim.robots``), which chooses the contacts, the feet, the standing height and the
limits the URDF lacks. Without a spec every sphere, box and cylinder collision of the URDF is
a contact (a mesh is refused) and the feet are found on the legs.

The public joint order (torques, joint states, commands) is the URDF's document order of its
moving joints.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from starleth_interface.config_checks import ConfigError
from starleth_interface.package_data import package_share_dir
from starleth_interface.robot.contact_points import urdf_contact_points
from starleth_interface.robot.legs import find_legs, standing_joint_positions
from starleth_interface.robot.urdf import checked_model, document_joint_order

__all__ = ["RobotDescription", "urdf_path",
           "leg_angles_for_height", "sphere_urdf", "box_urdf"]

#: StarlETH's names, for the layers that do not take them from the description yet (the
#: ROS state publisher, the analysis tools): legs LF/RF/LH/RH x HAA/HFE/KFE, feet
LEGS = ("LF", "RF", "LH", "RH")
JOINTS_PER_LEG = ("HAA", "HFE", "KFE")
STARLETH_JOINT_NAMES = tuple(f"{leg}_{j}" for leg in LEGS for j in JOINTS_PER_LEG)
STARLETH_FEET = tuple(f"{leg}_foot" for leg in LEGS)


def urdf_path(name: str = "starleth.urdf") -> str:
    return os.path.join(package_share_dir(), "urdf", name)


@dataclass
class RobotDescription:
    """A pin model on a free-flyer root, its actuated joints (public order), its contact
    points (feet first when it has feet), its legs, and the standing posture's height and
    knee directions (legs.standing_joint_positions). `source` names the URDF in messages."""

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
    legs: tuple = ()
    knees: str | dict = "auto"
    source: str = ""

    @classmethod
    def from_urdf_xml(cls, urdf_xml: str, name: str = "robot", joint_names=None,
                      source: str | None = None, contacts=None, foot_names=None, **kw):
        """The description of a URDF text (ConfigError naming `source` and the element when
        the simulator cannot use it: starleth_interface/robot/urdf.py). joint_names: the public
        joint order (default: the URDF's document order of its moving joints); contacts: the contact
        points (default: every sphere, box and cylinder collision); foot_names: the feet
        among them (default: found on the legs, starleth_interface/robot/legs.py)."""
        source = source or f"URDF of '{name}'"
        root, model = checked_model(urdf_xml, source)
        if contacts is None:
            contacts = urdf_contact_points(root, model, source)
        return cls.from_model(name, urdf_xml, model, contacts, source,
                              document_joint_order(root) if joint_names is None
                              else joint_names, foot_names, **kw)

    @classmethod
    def from_model(cls, name, urdf_xml, model, contacts, source, joint_names,
                   foot_names=None, **kw):
        """The description of a checked model (urdf.checked_model) with its contact points,
        public joint order and feet (default: found on the legs)."""
        for jn in joint_names:
            if not model.existJointName(jn):
                raise ConfigError(f"{source}: joint '{jn}' is not in the URDF")
        legs = find_legs(model, joint_names, contacts, foot_names)
        if foot_names is None:
            foot_names = tuple(leg.foot for leg in legs)
        ids = [model.getJointId(jn) for jn in joint_names]
        iq = [model.joints[j].idx_q for j in ids]
        iv = [model.joints[j].idx_v for j in ids]
        return cls(name=name, urdf_xml=urdf_xml, model=model, contacts=list(contacts),
                   joint_names=tuple(joint_names),
                   effort_limit=np.array(model.effortLimit)[iv].copy(),
                   velocity_limit=np.array(model.velocityLimit)[iv].copy(),
                   position_lower=np.array(model.lowerPositionLimit)[iq].copy(),
                   position_upper=np.array(model.upperPositionLimit)[iq].copy(),
                   foot_names=tuple(foot_names), legs=legs, source=source, **kw)

    @property
    def total_mass(self) -> float:
        return float(sum(inertia.mass for inertia in self.model.inertias))

    def contact_names(self):
        return [c.name for c in self.contacts]

    def standing_joints(self, height: float | None = None) -> np.ndarray:
        """The joint angles (public order) of the standing posture at `height` (default:
        the standing height): legs.standing_joint_positions. ValueError where there is none
        (no standing height, no legs, a height out of reach)."""
        height = self.standing_height if height is None else height
        if height is None or not self.legs:
            raise ValueError(f"{self.name}: no standing posture ("
                             f"{'no standing height' if height is None else 'no legs'})")
        return standing_joint_positions(self.legs, len(self.joint_names), height, self.knees)


def leg_angles_for_height(height: float, desc: RobotDescription):
    """Hip pitch and knee angles (HFE, KFE) of the first leg in the standing posture at trunk
    height `height` (the foot below the hip pitch joint, hip roll 0, on flat ground)."""
    joints = desc.standing_joints(height)
    leg = desc.legs[0]
    return float(joints[leg.joints[1]]), float(joints[leg.joints[2]])


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
