"""The controller's own robot model: a Pinocchio model built from the URDF, the public
joint order, the feet, and the analytic leg inverse kinematics.

Nothing here imports the simulator: the model comes from a URDF (path or XML text), so the
same controller drives any simulator or robot that speaks the same interfaces.

Conventions
-----------
* Public joint order (torques, joint states): LF/RF/LH/RH x HAA/HFE/KFE.
* Legs (contact flags, feet): LF, RF, LH, RH.
* A leg of StarlETH: HAA about the trunk x axis at the hip, HFE about y a distance l0 below
  the HAA axis, KFE about y a distance l1 below the HFE, the foot sphere centre l2 below the
  KFE. Front knees point backwards (KFE < 0), hind knees forwards (KFE > 0).
"""
from __future__ import annotations

import os
import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin

from . import kernels as K

LEGS = ("LF", "RF", "LH", "RH")
JOINTS_PER_LEG = ("HAA", "HFE", "KFE")
JOINT_NAMES = tuple(f"{leg}_{j}" for leg in LEGS for j in JOINTS_PER_LEG)


def default_urdf_path() -> str:
    """The StarlETH URDF: the colcon install's share/starleth_sim/urdf, else the source tree
    next to this package."""
    try:  # installed by colcon
        # deferred: a ROS package, absent where ROS is missing (the model needs no ROS)
        from ament_index_python.packages import get_package_share_directory
        p = os.path.join(get_package_share_directory("starleth_sim"), "urdf", "starleth.urdf")
        if os.path.exists(p):
            return p
    except Exception:
        pass
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    p = os.path.join(here, "urdf", "starleth.urdf")
    if os.path.exists(p):
        return p
    raise FileNotFoundError("cannot find starleth.urdf; pass the URDF to the controller")


def _read_urdf(urdf: str | None) -> str:
    if urdf is None:
        urdf = default_urdf_path()
    if urdf.lstrip().startswith("<"):
        return urdf
    with open(urdf) as f:
        return f.read()


def _foot_radius(xml: str, leg: str) -> float:
    """Radius of the <sphere> collision of the foot link (0 without one)."""
    root = ET.fromstring(xml)
    for link in root.findall("link"):
        if link.get("name", "").upper() != f"{leg}_FOOT":
            continue
        for coll in link.findall("collision"):
            sph = coll.find("geometry/sphere")
            if sph is not None:
                return float(sph.get("radius"))
    return 0.0


class RobotModel:
    """Pinocchio model of the robot plus the per-leg data the controller needs."""

    def __init__(self, urdf: str | None = None):
        xml = _read_urdf(urdf)
        self.urdf_xml = xml
        m = pin.buildModelFromXML(xml, pin.JointModelFreeFlyer())
        self.model = m
        self.data = m.createData()
        self.nq, self.nv = m.nq, m.nv
        for n in JOINT_NAMES:
            if not m.existJointName(n):
                raise ValueError(f"joint '{n}' is not in the URDF")
        ids = [m.getJointId(n) for n in JOINT_NAMES]
        #: q / v index (pin layout) of each public joint
        self.iq = np.array([m.joints[j].idx_q for j in ids])
        self.iv = np.array([m.joints[j].idx_v for j in ids])
        #: per leg: the 3 pin velocity columns of its joints (HAA, HFE, KFE)
        self.leg_iv = [self.iv[3 * k:3 * k + 3].copy() for k in range(4)]
        self.effort_limit = np.array(m.effortLimit)[self.iv].copy()
        self.mass = float(sum(i.mass for i in m.inertias))
        self.gravity = float(np.linalg.norm(m.gravity.linear))

        # feet and leg geometry
        self.foot_frame = []
        self.foot_joint = []
        self.foot_local = []
        self.foot_radius = np.zeros(4)
        self.hip = np.zeros((4, 3))       # HAA joint position in the base frame
        self.l0 = np.zeros(4)              # HAA axis to HFE axis (vertical)
        self.l1 = np.zeros(4)              # thigh: HFE to KFE
        self.l2 = np.zeros(4)              # shank: KFE to foot sphere centre
        self.knee_sign = np.zeros(4)       # sign of KFE in the nominal posture
        for k, leg in enumerate(LEGS):
            fname = f"{leg}_FOOT"
            if not m.existFrame(fname):
                raise ValueError(f"frame '{fname}' is not in the URDF")
            fid = m.getFrameId(fname)
            fr = m.frames[fid]
            kfe = m.getJointId(f"{leg}_KFE")
            if fr.parentJoint != kfe:
                raise ValueError(f"{fname} must be rigidly attached to {leg}_KFE")
            self.foot_frame.append(fid)
            self.foot_joint.append(kfe)
            self.foot_local.append(fr.placement.translation.copy())
            self.foot_radius[k] = _foot_radius(xml, leg)
            self.hip[k] = m.jointPlacements[m.getJointId(f"{leg}_HAA")].translation
            self.l0[k] = -m.jointPlacements[m.getJointId(f"{leg}_HFE")].translation[2]
            self.l1[k] = -m.jointPlacements[kfe].translation[2]
            self.l2[k] = -fr.placement.translation[2]
            self.knee_sign[k] = -1.0 if leg[1] == "F" else 1.0
        self.leg_length = float(np.mean(self.l0 + self.l1 + self.l2))
        self._check_leg_structure()

    def _check_leg_structure(self):
        """The analytic kinematics assume StarlETH's legs: HAA about x at the hip, HFE and KFE
        about y, each link offset straight down (-z) with no rotation."""
        m = self.model
        for leg in LEGS:
            for j, kind in zip(JOINTS_PER_LEG, ("JointModelRX", "JointModelRY", "JointModelRY")):
                jid = m.getJointId(f"{leg}_{j}")
                if m.joints[jid].shortname() != kind:
                    raise ValueError(f"{leg}_{j}: expected a revolute joint about "
                                     f"{kind[-1].lower()}, got {m.joints[jid].shortname()}")
                M = m.jointPlacements[jid]
                if abs(M.rotation - np.eye(3)).max() > 1e-9 or \
                        (j != "HAA" and abs(M.translation[:2]).max() > 1e-9):
                    raise ValueError(f"{leg}_{j}: the leg links must be offset along -z only, "
                                     "without rotation")
            fr = m.frames[m.getFrameId(f"{leg}_FOOT")].placement
            if abs(fr.translation[:2]).max() > 1e-9:
                raise ValueError(f"{leg}_FOOT: the foot must lie on the shank's -z axis")

    # -- analytic leg kinematics (the kernels' code, for callers and tests) ---------------
    @property
    def geometry(self):
        """(4, 5): l0, l1, l2, foot radius, knee sign per leg (the kernels' layout)."""
        return np.column_stack((self.l0, self.l1, self.l2, self.foot_radius, self.knee_sign))

    def leg_ik(self, k: int, r):
        """Joint angles (HAA, HFE, KFE) that put the foot sphere centre of leg k at `r`
        (base frame). Out-of-reach targets are pulled onto the workspace boundary."""
        out = np.zeros(3)
        K.leg_ik(k, float(r[0]), float(r[1]), float(r[2]), self.hip, self.geometry, out)
        return out

    def leg_fk(self, k: int, haa, hfe, kfe):
        """Foot sphere centre of leg k in the base frame."""
        out = np.zeros(3)
        K.leg_fk(k, float(haa), float(hfe), float(kfe), self.hip, self.geometry, out)
        return out

    def nominal_joint_positions(self, height: float):
        """Public-order joint angles with every foot straight below its hip, the trunk level
        at `height` above flat ground."""
        out = np.zeros(12)
        for k in range(4):
            r = self.hip[k].copy()
            r[2] = -(height - self.foot_radius[k])
            out[3 * k:3 * k + 3] = self.leg_ik(k, r)
        return out
