"""The controller's own robot model: a Pinocchio model built from the robot's URDF (and its
robot spec, through starleth_interface.robot: feet, effort limits, standing height), the legs
found from the kinematic tree, and the analytic leg kinematics of roll-pitch-pitch legs.

Nothing here imports the simulator: the model comes from a robot of the library, a robot
spec, or a URDF (path or XML text), so the same controller drives any simulator or robot
that speaks the same interfaces.

Conventions
-----------
* Legs in the order of their first joint in the URDF's joint order (StarlETH: LF, RF, LH,
  RH); the controller's joint order is leg by leg, hip roll, hip pitch, knee
  (``joint_order``: their places in the public order; None when it is the public order).
* A leg (starleth_interface.robot.legs): a hip roll joint about ±x at ``hip``, then two pitch
  joints about ±y. At the neutral configuration, in the base frame: HAA→HFE offset
  (o_x, ·, −l0), thigh and shank (HFE→KFE, KFE→foot sphere centre) in the x-z plane at the
  angles α and α + γ from −z, l1 and l2 long, and a lateral offset d_y (HAA→foot, summed)
  that the roll carries. The leg is then StarlETH's planar leg with the hip pitch angle
  σ₁ q_HFE + α and the knee angle σ₂ q_KFE + γ (σ: the signs of the pitch axes along +y,
  ρ: of the roll axis along +x); StarlETH's own (α = γ = o_x = d_y = 0, signs +1) is the
  same arithmetic as before, bit for bit.
"""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

from starleth_interface.package_data import package_share_dir
from starleth_interface.robot.contact_points import urdf_contact_points
from starleth_interface.robot.feet import foot_points
from starleth_interface.robot.legs import KNEE_SIGNS, find_legs, knee_sign
from starleth_interface.robot.library import load_robot, read_text, resolve, urdf_file
from starleth_interface.robot.scaling import robot_scale
from starleth_interface.robot.spec import override_limits
from starleth_interface.robot.urdf import checked_model, document_joint_order

from . import kernels as K

#: StarlETH's legs and joint names (its URDF's), for what still names them
LEGS = ("LF", "RF", "LH", "RH")
JOINTS_PER_LEG = ("HAA", "HFE", "KFE")
JOINT_NAMES = tuple(f"{leg}_{j}" for leg in LEGS for j in JOINTS_PER_LEG)
#: the columns of ``RobotModel.geometry`` (kernels.py)
GEOMETRY = ("l0", "l1", "l2", "foot_radius", "knee_sign", "o_x", "d_y", "alpha", "gamma",
            "roll_sign", "hfe_sign", "kfe_sign")


def default_urdf_path() -> str:
    """The StarlETH URDF (the package data's urdf/starleth.urdf)."""
    return f"{package_share_dir()}/urdf/starleth.urdf"


class NotAQuadruped(ValueError):
    """The robot is not a four-legged tree of 3-joint roll-pitch-pitch legs."""


def _robot_source(robot: str | None, urdf: str | None):
    """(URDF text, robot spec or None, source for messages) of a `robot` value (library
    name, spec path, URDF path) or a `urdf` (path or XML text)."""
    if urdf is None:
        kind, path = resolve(robot or "starleth")
        if kind == "urdf":
            return read_text(path), None, path
        spec = load_robot(path)
        path = urdf_file(spec)
        return read_text(path), spec, f"{path.rsplit('/', 1)[-1]} ({spec.label})"
    if urdf.lstrip().startswith("<"):
        return urdf, None, "URDF text"
    return read_text(urdf), None, urdf


def _turn(u, v) -> float:
    """The angle about +y turning the x-z vector u onto v's direction (+0.0 when parallel)."""
    return math.atan2(u[1] * v[0] - u[0] * v[1], u[0] * v[0] + u[1] * v[1]) + 0.0


class RobotModel:
    """Pinocchio model of the robot plus the per-leg data the controller needs. `robot`: a
    library name, a robot spec or a URDF path; or `urdf`: a URDF path or XML text (no spec).
    starleth_interface's ConfigError for a bad description, NotAQuadruped for one the
    controller cannot drive."""

    def __init__(self, urdf: str | None = None, robot: str | None = None):
        xml, spec, source = _robot_source(robot, urdf)
        self.urdf_xml = xml
        root, m = checked_model(xml, source)
        self.model = m
        self.data = m.createData()
        self.nq, self.nv = m.nq, m.nv
        names = document_joint_order(root)
        if spec is not None:
            feet = foot_points(spec, root, m, source, names)
            legs = find_legs(m, names, feet, {f.name for f in feet})
        else:
            feet = urdf_contact_points(root, m, source)
            legs = find_legs(m, names, feet)
        self._check_legs(legs, names, source)
        self.legs = legs
        self.public_joint_names = tuple(names)
        order = [j for leg in legs for j in leg.joints]
        #: the public index of each controller joint (None: the same order)
        self.joint_order = None if order == list(range(12)) else np.array(order)
        ids = [m.getJointId(names[i]) for i in order]
        #: q / v index (pin layout) of each joint (controller order)
        self.iq = np.array([m.joints[j].idx_q for j in ids])
        self.iv = np.array([m.joints[j].idx_v for j in ids])
        #: per leg: the 3 pin velocity columns of its joints (HAA, HFE, KFE)
        self.leg_iv = [self.iv[3 * k:3 * k + 3].copy() for k in range(4)]
        effort = np.array(m.effortLimit)[[m.joints[j].idx_v for j in
                                          (m.getJointId(n) for n in names)]].copy()
        if spec is not None:
            override_limits(spec, names, "effort", effort)
        self.effort_limit = effort[order].copy()
        self.mass = float(sum(i.mass for i in m.inertias))
        self.gravity = float(np.linalg.norm(m.gravity.linear))
        self.scale = robot_scale(legs, self.mass)
        self.standing_height = spec.standing_height if spec is not None else None
        self.knees = spec.knees if spec is not None else "auto"
        by_name = {f.name: f for f in feet}
        self.foot_names = tuple(leg.foot for leg in legs)
        self.foot_link = tuple(by_name[n].link for n in self.foot_names)
        self.foot_frame = [m.getFrameId(link, pin.FrameType.BODY) for link in self.foot_link]
        self.foot_joint = [m.getJointId(leg.joint_names[2]) for leg in legs]
        self.foot_local = [by_name[n].local.copy() for n in self.foot_names]
        self._leg_geometry(legs, by_name)

    @staticmethod
    def _check_legs(legs, names, source):
        """NotAQuadruped unless 12 joints make 4 legs, one at each corner, of a hip roll
        (about ±x) and two pitch joints (about ±y)."""
        why = None
        if len(names) != 12 or len(legs) != 4:
            why = f"{len(names)} moving joints, {len(legs)} 3-joint legs with a foot"
        elif legs[0].fore is None:
            why = "its legs are not one at each corner"
        else:
            bad = [leg for leg in legs if leg.plane is None or leg.roll == 0.0]
            if bad:
                why = (f"leg {'/'.join(bad[0].joint_names)} is not a roll-pitch-pitch leg "
                       "(hip roll about x, hip and knee pitch about y)")
        if why:
            raise NotAQuadruped(f"{source}: not a four-legged robot of 3-joint legs the "
                                f"controller drives: {why}")

    def _leg_geometry(self, legs, feet):
        """hip (4, 3) and the geometry rows (4, len(GEOMETRY)) of the module docstring."""
        m, data = self.model, self.data
        pin.forwardKinematics(m, data, pin.neutral(m))
        self.hip = np.array([leg.hip for leg in legs])
        geo = np.zeros((4, len(GEOMETRY)))
        for k, leg in enumerate(legs):
            haa, hfe, kfe = (m.getJointId(n) for n in leg.joint_names)
            o = data.oMi[haa].rotation @ m.jointPlacements[hfe].translation
            t = data.oMi[hfe].rotation @ m.jointPlacements[kfe].translation
            s = data.oMi[kfe].rotation @ feet[leg.foot].local
            l1 = abs(t[2]) if t[0] == 0.0 else math.hypot(t[0], t[2])
            l2 = abs(s[2]) if s[0] == 0.0 else math.hypot(s[0], s[2])
            sign = self._knee_sign(leg, geo[k, 0] + l1 + l2)
            geo[k] = (-o[2], l1, l2, feet[leg.foot].radius, sign, o[0], o[1] + t[1] + s[1],
                      math.atan2(-t[0], -t[2]) + 0.0, _turn((t[0], t[2]), (s[0], s[2])),
                      leg.roll, leg.plane.signs[0], leg.plane.signs[1])
        self.geometry = geo
        self.l0, self.l1, self.l2 = geo[:, 0], geo[:, 1], geo[:, 2]
        self.foot_radius, self.knee_sign = geo[:, 3], geo[:, 4]
        self.leg_length = float(np.mean(self.l0 + self.l1 + self.l2))

    def _knee_sign(self, leg, reach):
        """The knee direction of a leg's standing posture (legs.knee_sign): the spec's at its
        standing height; without a spec the one within the joint limits at 3/4 of the leg's
        reach, else the common one (front knees backward, hind knees forward)."""
        if self.standing_height is not None:
            return knee_sign(leg, self.knees, self.standing_height)
        try:
            return knee_sign(leg, "auto", 0.75 * reach)
        except ValueError:
            return KNEE_SIGNS["backward"] if leg.fore else KNEE_SIGNS["forward"]

    # -- analytic leg kinematics (the kernels' code, for callers and tests) ---------------
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
        """Joint angles (controller order) with every foot straight below its hip pitch
        joint (hip roll at 0), the trunk level at `height` above flat ground."""
        out = np.zeros(12)
        for k in range(4):
            r = self.hip[k].copy()
            r[0] += self.geometry[k, 5]
            r[1] += self.geometry[k, 6]
            r[2] = -(height - self.foot_radius[k])
            out[3 * k:3 * k + 3] = self.leg_ik(k, r)
        return out

