"""Legs found from the kinematic tree and the geometry (never from names), and the standing
posture by inverse kinematics.

A leg is a subtree of the floating base that is a chain of 3 revolute joints (hip roll,
hip pitch, knee: HAA, HFE, KFE) whose last body carries a foot contact sphere (the robot
spec's foot, else the sphere of that body farthest from its joint). Its side comes from the
geometry at the neutral configuration: fore when its first joint lies ahead of the base
origin (x > 0), left when to the left (y > 0); a joint on the axis (|x| or |y| < 1 µm)
takes the side of its foot. Sides are known only when there are 4 legs, one at each corner.

The leg is a roll-pitch-pitch leg when, at the neutral configuration, its second and third
joint axes are parallel to the base's y axis (either sign): the foot then moves in a
vertical plane through the hip pitch joint, whatever the offsets of the links (lateral
offsets, rotated joint frames, axes that point along -y). The standing posture puts, with
the hip roll at 0 and the base level at the standing height, each foot sphere's centre
straight below its hip pitch axis, its lowest point on the ground: a planar two-link
problem (thigh: hip pitch to knee; shank: knee to foot centre) with its two solutions, the
knee ahead of (``forward``) or behind (``backward``) the line from the hip to the foot.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from ..config_checks import ConfigError
from .urdf import revolute_axis

#: the knee directions of the standing posture (module docstring): sign of the knee angle
#: about +y (behind the hip-to-foot line: negative)
KNEE_SIGNS = {"backward": -1.0, "forward": 1.0}
_ON_AXIS = 1e-6       # m: a hip this close to the base's x or y axis takes its foot's side
_PARALLEL = 1e-9      # 1 - |cos| of two axes taken as parallel


@dataclass(frozen=True)
class PitchPlane:
    """The sagittal geometry of a roll-pitch-pitch leg at the neutral configuration, in the
    base frame's x-z plane: the hip pitch joint's origin, the thigh (hip pitch to knee) and
    shank (knee to foot centre) vectors, the signs of the two pitch axes along +y, the foot
    radius and the joints' position limits."""

    hfe: tuple
    thigh: tuple
    shank: tuple
    signs: tuple
    radius: float
    limits: tuple     # ((HFE lower, upper), (KFE lower, upper))

    @property
    def length(self) -> float:
        """Thigh plus shank [m]."""
        return math.sqrt(self.thigh[0] ** 2 + self.thigh[1] ** 2) + \
            math.sqrt(self.shank[0] ** 2 + self.shank[1] ** 2)


@dataclass(frozen=True)
class Leg:
    """A leg: its joints (indices into the public joint order, hip to knee, and names), its
    foot contact, its side (fore, left: None when unknown), the hip (first joint) position
    and the sign of its axis along the base's x (0 when not along x) at the neutral
    configuration, and its sagittal geometry (None unless a roll-pitch-pitch leg)."""

    joints: tuple
    joint_names: tuple
    foot: str
    fore: bool | None
    left: bool | None
    hip: tuple
    roll: float
    plane: PitchPlane | None


def _axis(model, j) -> np.ndarray | None:
    return revolute_axis(model.joints[j])


def _chains(model):
    """The root subtrees that are chains of 3 revolute joints: [(j1, j2, j3)]."""
    children = {j: [] for j in range(model.njoints)}
    for j in range(2, model.njoints):
        children[model.parents[j]].append(j)
    chains = []
    for first in children[1]:
        chain, j = [first], first
        while len(children[j]) == 1 and len(chain) < 4:
            j = children[j][0]
            chain.append(j)
        if len(chain) == 3 and not children[chain[-1]] and \
                all(_axis(model, k) is not None for k in chain):
            chains.append(tuple(chain))
    return chains


def _foot_of(chain, contacts, foot_names):
    """The foot contact of a chain: among foot_names (if given) the one on its last body,
    else the sphere on its last body farthest from the joint; None if none."""
    last = chain[-1]
    if foot_names is not None:
        on = [c for c in contacts if c.name in foot_names and c.joint == last]
        return on[0] if on else None
    spheres = [c for c in contacts if c.joint == last and c.radius > 0]
    return max(spheres, key=lambda c: float(np.linalg.norm(c.local)), default=None)


def _side(hip, foot, k):
    v = hip[k] if abs(hip[k]) >= _ON_AXIS else foot[k]
    return bool(v > 0)


def _plane(model, data, chain, foot, lower, upper):
    """The PitchPlane of a chain whose 2nd and 3rd axes are along ±y, else None."""
    a2 = data.oMi[chain[1]].rotation @ _axis(model, chain[1])
    a3 = data.oMi[chain[2]].rotation @ _axis(model, chain[2])
    if min(abs(a2[1]), abs(a3[1])) < 1.0 - _PARALLEL:
        return None
    hfe = data.oMi[chain[1]]
    thigh = hfe.rotation @ model.jointPlacements[chain[2]].translation
    shank = data.oMi[chain[2]].rotation @ foot.local
    iq = [model.joints[j].idx_q for j in chain[1:]]
    return PitchPlane(hfe=(float(hfe.translation[0]), float(hfe.translation[2])),
                      thigh=(float(thigh[0]), float(thigh[2])),
                      shank=(float(shank[0]), float(shank[2])),
                      signs=(float(np.sign(a2[1])), float(np.sign(a3[1]))),
                      radius=float(foot.radius),
                      limits=tuple((float(lower[i]), float(upper[i])) for i in iq))


def find_legs(model: pin.Model, joint_names, contacts, foot_names=None) -> tuple:
    """The legs of a free-flyer model (module docstring), ordered by their first joint's
    place in `joint_names`; () when there is no leg."""
    data = model.createData()
    q0 = pin.neutral(model)
    pin.forwardKinematics(model, data, q0)
    index = {n: i for i, n in enumerate(joint_names)}
    found = []
    for chain in _chains(model):
        foot = _foot_of(chain, contacts, foot_names)
        names = tuple(model.names[j] for j in chain)
        if foot is None or any(n not in index for n in names):
            continue
        world_foot = data.oMi[chain[2]].act(foot.local)
        hip = data.oMi[chain[0]].translation
        roll = (data.oMi[chain[0]].rotation @ _axis(model, chain[0]))[0]
        found.append(dict(
            joints=tuple(index[n] for n in names), joint_names=names, foot=foot.name,
            fore=_side(hip, world_foot, 0), left=_side(hip, world_foot, 1),
            hip=tuple(float(x) for x in hip),
            roll=float(np.sign(roll)) if abs(roll) >= 1.0 - _PARALLEL else 0.0,
            plane=_plane(model, data, chain, foot, model.lowerPositionLimit,
                         model.upperPositionLimit)))
    corners = {(f["fore"], f["left"]) for f in found}
    if len(found) != 4 or len(corners) != 4:
        for f in found:
            f["fore"] = f["left"] = None
    return tuple(Leg(**f) for f in sorted(found, key=lambda f: f["joints"][0]))


def _turn(u, v) -> float:
    """The angle [rad] that turns the x-z vector u onto v's direction about +y (x = sin,
    z = cos of a direction's angle): 0 exactly for parallel vectors."""
    return math.atan2(u[1] * v[0] - u[0] * v[1], u[0] * v[0] + u[1] * v[1])


def pitch_leg_angles(plane: PitchPlane, height: float, knee: float):
    """(hip pitch, knee) joint angles that put the foot sphere's centre straight below the
    hip pitch joint, its lowest point on the ground, with the base level at `height` and
    the hip roll at 0; knee: -1 backward, +1 forward (module docstring). ValueError when
    out of reach."""
    hz = plane.hfe[1]
    (tx, tz), (sx, sz) = plane.thigh, plane.shank
    l1 = np.sqrt(tx * tx + tz * tz)
    l2 = np.sqrt(sx * sx + sz * sz)
    dz = height + hz - plane.radius     # hip pitch joint to foot centre, vertically
    dx = 0.0                            # the foot straight below the hip pitch joint
    d = np.sqrt(dx * dx + dz * dz)
    if not (abs(l1 - l2) < d < l1 + l2 and dz > 0):
        raise ValueError(f"standing height {height} m is out of reach of the legs (hip to "
                         f"foot {float(dz):.3f} m, thigh {float(l1):.3f} m, shank "
                         f"{float(l2):.3f} m)")
    # the knee from the law of cosines; the thigh so that the foot is below the hip
    cos_k = (d * d - l1 * l1 - l2 * l2) / (2 * l1 * l2)
    b = knee * np.arccos(np.clip(cos_k, -1.0, 1.0))
    # the thigh turned onto the hip-to-foot line, less the triangle's angle at the hip; the
    # knee angle less the shank's own angle to the thigh at 0
    a = _turn((tx, tz), (dx, -dz)) + np.arctan2(l2 * np.sin(-b), l1 + l2 * np.cos(b))
    k = b - _turn((tx, tz), (sx, sz))
    return float(plane.signs[0] * a), float(plane.signs[1] * k)


def _within(plane, angles) -> bool:
    return all(lo <= x <= hi for x, (lo, hi) in zip(angles, plane.limits, strict=True))


def knee_sign(leg: Leg, knees, height) -> float:
    """The knee direction of a leg: from `knees` ('backward', 'forward', {'front': ...,
    'hind': ...}), or with 'auto' the one solution within the joint limits."""
    if isinstance(knees, dict):
        if leg.fore is None:
            raise ValueError("knees given for front and hind legs, but the legs' sides are "
                             "not known (4 legs, one at each corner)")
        knees = knees["front" if leg.fore else "hind"]
    if knees != "auto":
        return KNEE_SIGNS[knees]
    fits = [s for s in (-1.0, 1.0) if _within(leg.plane, pitch_leg_angles(leg.plane, height, s))]
    if len(fits) != 1:
        raise ValueError(f"leg {'/'.join(leg.joint_names)}: {'both' if fits else 'neither'} "
                         "knee direction(s) fit the joint limits at the standing height: "
                         "say backward or forward (standing.knees)")
    return fits[0]


def standing_joint_positions(legs, n_joints: int, height: float, knees="auto") -> np.ndarray:
    """The joint angles (public order) of the standing posture at `height` (module
    docstring): every joint outside the legs' pitch joints at 0. ValueError when a leg is not
    a roll-pitch-pitch leg, the height is out of reach or the knees' solution leaves the
    joint limits."""
    joints = np.zeros(n_joints)
    for leg in legs:
        if leg.plane is None:
            raise ValueError(f"leg {'/'.join(leg.joint_names)}: not a roll-pitch-pitch leg "
                             "(its 2nd and 3rd joint axes are not along the base's y axis)")
        sign = knee_sign(leg, knees, height)
        hfe, kfe = pitch_leg_angles(leg.plane, height, sign)
        if not _within(leg.plane, (hfe, kfe)):
            raise ValueError(f"leg {'/'.join(leg.joint_names)}: the standing posture "
                             f"({hfe:.3f}, {kfe:.3f}) rad leaves the joint limits "
                             f"{leg.plane.limits}")
        joints[leg.joints[1]] = hfe
        joints[leg.joints[2]] = kfe
    return joints


def check_knees(knees, where: str):
    """The standing knee directions of a robot spec (module docstring); ConfigError."""
    choices = ("auto", "backward", "forward")
    if isinstance(knees, dict):
        if set(knees) != {"front", "hind"} or not all(v in KNEE_SIGNS for v in knees.values()):
            raise ConfigError(f"{where}: expected {{front: backward|forward, hind: "
                              f"backward|forward}}, got {knees!r}")
        return dict(knees)
    if knees not in choices:
        raise ConfigError(f"{where}: must be one of {list(choices)} or {{front: ..., hind: "
                          f"...}}, got {knees!r}")
    return knees
