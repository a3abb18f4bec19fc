"""Recorded /tf and /tf_static read back for the tests: the tree (child -> parent) and the
world pose of every frame, composed along it."""
import numpy as np
import pinocchio as pin


def tf_tree(msgs):
    """{child frame: parent frame} of a bag's /tf and /tf_static messages (msgs: {topic:
    [mcap_ros2 decoded message]}); a child named with two parents fails."""
    parent = {}
    for topic in ("/tf_static", "/tf"):
        for m in msgs.get(topic, ()):
            for t in m.ros_msg.transforms:
                assert parent.setdefault(t.child_frame_id, t.header.frame_id) == \
                    t.header.frame_id, t.child_frame_id
    return parent


def world_poses(transforms, world="world"):
    """{frame: pose in `world` (pin.SE3)} of TransformStamped messages (in any order),
    composed from `world` down the tree."""
    poses = {world: pin.SE3.Identity()}
    pending = list(transforms)
    while pending:
        t = pending.pop(0)
        if t.header.frame_id not in poses:
            pending.append(t)
            continue
        p, r = t.transform.translation, t.transform.rotation
        poses[t.child_frame_id] = poses[t.header.frame_id] * pin.SE3(
            pin.Quaternion(r.w, r.x, r.y, r.z).matrix(), np.array([p.x, p.y, p.z]))
    return poses
