"""The offered QoS profiles of a recorded topic in rosbag2's metadata-v9 spelling (the
``offered_qos_profiles`` channel metadata and the topics of ``metadata.yaml``)."""
from __future__ import annotations

import yaml

RMW_DURATION_INFINITE = {"sec": 9223372036854775807, "nsec": 999999999}


def _duration(d):
    """rclpy Duration / nanoseconds / {'sec','nsec'} -> {'sec', 'nsec'}; 0 = infinite."""
    if isinstance(d, dict):
        return {"sec": int(d["sec"]), "nsec": int(d["nsec"])}
    ns = getattr(d, "nanoseconds", d)
    ns = int(ns or 0)
    if ns <= 0 or ns >= RMW_DURATION_INFINITE["sec"]:
        return dict(RMW_DURATION_INFINITE)
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _policy(value, default):
    name = getattr(value, "name", value)
    if name is None:
        return default
    name = str(name).lower()
    return default if name in ("system_default", "unknown") else name


def qos_to_dict(qos) -> dict:
    """An rclpy QoSProfile (or a dict with the same keys) in rosbag2's metadata-v9 spelling."""
    if isinstance(qos, dict):
        g = qos.get
    else:
        def g(k, default=None):
            return getattr(qos, k, default)
    return {
        "history": _policy(g("history"), "keep_last"),
        "depth": int(g("depth", 0) or 0),
        "reliability": _policy(g("reliability"), "reliable"),
        "durability": _policy(g("durability"), "volatile"),
        "deadline": _duration(g("deadline", 0)),
        "lifespan": _duration(g("lifespan", 0)),
        "liveliness": _policy(g("liveliness"), "automatic"),
        "liveliness_lease_duration": _duration(g("liveliness_lease_duration", 0)),
        "avoid_ros_namespace_conventions": bool(g("avoid_ros_namespace_conventions", False)),
    }


def qos_profiles_yaml(profiles) -> str:
    """The ``offered_qos_profiles`` channel metadata string: a YAML list."""
    if profiles is None:
        profiles = [{}]
    elif not isinstance(profiles, (list, tuple)):
        profiles = [profiles]
    return yaml.safe_dump([qos_to_dict(p) for p in profiles], sort_keys=False).strip()
