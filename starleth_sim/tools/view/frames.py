"""The frames of a ``starleth-view`` page and their kinematics: which recorded samples are
shown at a frame rate, the robot's configuration at each (garbage values held at the
previous one), the bodies' world poses by forward kinematics, and the foot force arrows."""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin

from ...physics.description import RobotDescription
from ...robots import recorded_description
from .recording import Recording, Series, ViewError, attach_feet, warn

#: the largest magnitude of a recorded position [m], joint angle [rad] or force [N] drawn;
#: a sample beyond it (or NaN, infinite) is garbage: the previous value is drawn instead
MAX_VALUE = 1e9


def select_frames(t_ns: np.ndarray, fps: float) -> np.ndarray:
    """Indices of the samples (times t_ns, sorted) shown at fps: for each time
    t_0 + k/fps (k = 0 .. span * fps, rounded to the nanosecond) the latest sample at or
    before it, each once, plus the last sample.

    Worked out per sample, not per grid time: sample i is shown when the first grid time at
    or after it comes before the next sample. Memory and time go with the number of samples,
    whatever the span of their stamps (two samples 2e9 s apart at 50 fps are 2 frames, not
    1e11 grid times)."""
    n = t_ns.size
    if n == 0:
        return np.zeros(0, dtype=int)
    rel = t_ns - t_ns[0]                                     # int64: exact
    after = np.append(rel[1:], np.iinfo(np.int64).max)       # the next sample's time
    step = 1e9 / fps                                         # [ns] between grid times
    if step <= 1.0:   # a grid time at every nanosecond: each distinct stamp is a frame
        shown = rel < after
        shown[-1] = True
        return np.flatnonzero(shown)
    last_k = math.floor((t_ns[-1] - t_ns[0]) * 1e-9 * fps + 1e-9)

    def grid(k):                                             # the grid times, t_0 relative
        return np.clip(np.round(k * step), -2.0 ** 62, 2.0 ** 62).astype(np.int64)

    # k: the first grid index whose time is at or after each sample (the estimate
    # rel / step is off by one or two where the grid's rounding bites)
    k = np.ceil(rel / step)
    for _ in range(8):
        down = (k > 0) & (grid(k - 1) >= rel)
        up = grid(k) < rel
        if not (down.any() or up.any()):
            break
        k = k - down + up
    shown = (k <= last_k) & (grid(k) < after)
    shown[-1] = True
    return np.flatnonzero(shown)


def load_description(rec: Recording) -> RobotDescription:
    """The project's free-flyer model of a recording's robot: from its URDF and spec
    (robots.recorded_description: the recorded robot, no library needed), or from its URDF
    alone (RobotDescription.from_urdf_xml); its feet's wrench series attached to `rec`."""
    try:
        if rec.spec is not None:
            desc = recorded_description(rec.urdf, rec.spec, rec.robot, where=rec.path)
        else:
            name = rec.robot or ET.fromstring(rec.urdf).get("name") or "robot"
            desc = RobotDescription.from_urdf_xml(rec.urdf, name=name)
    except Exception as e:   # pin's parser and the contact reader raise several kinds
        raise ViewError(f"the URDF ({rec.urdf_source}) cannot be used: "
                        f"{type(e).__name__}: {e}") from None
    attach_feet(rec, desc.foot_names)
    return desc


def _joint_indices(desc: RobotDescription):
    """{joint name: (idx_q, nq)} of the model's joints after the free-flyer root."""
    m = desc.model
    out = {}
    for name in desc.joint_names:
        j = m.joints[m.getJointId(name)]
        out[name] = (j.idx_q, j.nq)
    return out


def _usable(*values) -> bool:
    """Whether recorded numbers can be drawn: finite, at most MAX_VALUE in magnitude."""
    try:
        return all(math.isfinite(v) and abs(v) <= MAX_VALUE for v in values)
    except (TypeError, ValueError, OverflowError):    # not numbers at all
        return False


def _fields(series: Series, i: int, read):
    """read(message i of series): its fields, or a ViewError where the message lacks them
    (a bag whose schema for the type is not the ROS one)."""
    msg = series.message(i)
    try:
        return read(msg)
    except (AttributeError, TypeError) as e:
        raise ViewError(f"message {i} on {series.topic} lacks the fields of its type "
                        f"({type(e).__name__}: {e})") from None


def _warn_unusable(rec: Recording, unusable: dict, what: str) -> None:
    for topic, idx in unusable.items():
        warn(f"{rec.path}: {len(idx)} message(s) on {topic} hold NaN, infinite or absurd "
             f"values (beyond {MAX_VALUE:g}); {what}")


def configurations(rec: Recording, desc: RobotDescription, frames: np.ndarray):
    """(N, nq) pin configurations at the joint-state samples `frames`: base pose from the
    latest base state at or before each, joint positions by name (a joint a message lacks
    keeps its previous value, neutral at first; so does a value that is NaN, infinite or
    beyond MAX_VALUE, and a base pose holding one, with a warning)."""
    model = desc.model
    index = _joint_indices(desc)
    q = np.tile(pin.neutral(model), (frames.size, 1))
    seen = set()
    unusable = {}                                 # topic -> indices of such messages
    prev = q[0].copy()
    bases = rec.base.latest(rec.joints.t_ns[frames])
    for row, (i, b) in enumerate(zip(frames, bases, strict=True)):
        q[row] = prev
        names, positions = _fields(rec.joints, i, lambda m: (list(m.name), list(m.position)))
        if len(positions) == len(names):
            for name, value in zip(names, positions, strict=True):
                slot = index.get(name) if isinstance(name, str) else None
                if slot is None:
                    continue
                if not _usable(value):
                    unusable.setdefault(rec.joints.topic, set()).add(int(i))
                    continue
                seen.add(name)
                if slot[1] == 1:
                    q[row, slot[0]] = value
                else:   # continuous joint: (cos, sin)
                    q[row, slot[0]:slot[0] + 2] = (math.cos(value), math.sin(value))
        pose = _fields(rec.base, b, lambda m: (
            m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z,
            m.pose.pose.orientation.x, m.pose.pose.orientation.y, m.pose.pose.orientation.z,
            m.pose.pose.orientation.w))
        if _usable(*pose):
            quat = np.array(pose[3:], dtype=float)
            n = np.linalg.norm(quat)
            q[row, 0:3] = pose[:3]
            q[row, 3:7] = quat / n if n > 1e-9 else (0.0, 0.0, 0.0, 1.0)
        else:
            unusable.setdefault(rec.base.topic, set()).add(int(b))
        prev = q[row]
    _warn_unusable(rec, unusable, "drawn with the previous value")
    never = [n for n in desc.joint_names if n not in seen]
    if never:
        warn(f"{rec.path}: joint(s) {', '.join(never)} of the URDF are in no joint state; "
             "drawn at 0")
    return q


def body_poses(desc: RobotDescription, q: np.ndarray, joint_ids):
    """(N, nb, 7) world poses (x y z qx qy qz qw) of the pin joints joint_ids (forward
    kinematics at each configuration), and the (N, njoints) list of oMi for reuse."""
    model = desc.model
    data = model.createData()
    poses = np.zeros((q.shape[0], len(joint_ids), 7))
    placements = []
    for k in range(q.shape[0]):
        pin.forwardKinematics(model, data, q[k])
        oMi = [data.oMi[j].copy() for j in range(model.njoints)]
        placements.append(oMi)
        for b, j in enumerate(joint_ids):
            poses[k, b, :3] = oMi[j].translation
            poses[k, b, 3:] = pin.Quaternion(oMi[j].rotation).coeffs()   # x y z w
    return poses, placements


def contact_arrows(rec: Recording, desc: RobotDescription, frames, placements, force_scale):
    """(N, feet, 6) arrows (origin xyz, vector xyz [m]) per frame and foot (desc.foot_names):
    from the foot contact point (centre of the foot's contact sphere minus its radius along
    the ground normal) along force * force_scale; zeros for a foot without force messages, and no
    arrow (a zero vector, with a warning) for a force that is NaN, infinite or beyond
    MAX_VALUE."""
    arrows = np.zeros((frames.size, len(desc.foot_names), 6))
    normal = np.asarray(rec.ground_normal)
    contacts = {c.name: c for c in desc.contacts}
    t_frames = rec.joints.t_ns[frames]
    unusable = {}                                 # topic -> indices of such messages
    for f, foot in enumerate(desc.foot_names):
        spec = contacts.get(foot)
        series = rec.wrenches.get(foot)
        if series is None:
            continue
        for row, i in enumerate(series.latest(t_frames)):
            centre = placements[row][spec.joint].act(spec.local)
            force = _fields(series, i, lambda m: (m.wrench.force.x, m.wrench.force.y,
                                                  m.wrench.force.z))
            arrows[row, f, :3] = centre - spec.radius * normal
            if _usable(*force):
                arrows[row, f, 3:] = np.array(force, dtype=float) * force_scale
            else:
                unusable.setdefault(series.topic, set()).add(int(i))
    _warn_unusable(rec, unusable, "no arrow drawn for them")
    return arrows

