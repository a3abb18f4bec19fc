"""State conversions between the simulator and the ROS interface: the ``initial_state``
parameter (YAML, a file, or a recording's initial_state.json) to (q, u), the record of the
initial state stored in recordings, the public (convention-free) state and the values of
the state topics. ROS-free (the IMU's exact values: physics/sensors.py)."""
from __future__ import annotations

import math

import numpy as np

from starleth_interface.yaml_files import load_yaml_file, load_yaml_text

from ..physics.config import ConfigError
from ..physics.kinematics import quat_xyzw_to_rot
from ..physics.simulator import Simulator

_PUBLIC_KEYS = ("base_position", "base_orientation", "joint_positions", "base_linear_velocity",
                "base_angular_velocity", "joint_velocities")
_STATE_KEYS = _PUBLIC_KEYS + ("q_minimal", "u_minimal", "q", "u", "coordinates")
# keys of a recorded initial_state.json that carry no state of their own
_STATE_INFO_KEYS = ("t", "note", "joint_names", "parameter")

def read_state_spec(spec):
    """The initial_state parameter as a mapping ({} for the standing state)."""
    if not isinstance(spec, str):
        return spec or {}
    s = spec.strip()
    if s in ("", "standing", "default"):
        return {}
    if s.endswith((".yaml", ".yml", ".json")) and not s.startswith("{"):
        # the project's YAML loader: duplicate keys, binary files, bad YAML name the file
        try:
            return load_yaml_file(s, s) or {}
        except ConfigError as e:
            raise ConfigError(f"parameter initial_state: {e}") from None
    return load_yaml_text(s, "parameter initial_state")


def public_state(sim: Simulator) -> dict:
    """The simulator's current state in convention-free public quantities."""
    b = sim.base_state()
    return {"base_position": np.array(b["position"], dtype=float),
            "base_orientation": np.array(b["orientation_xyzw"], dtype=float),
            "base_linear_velocity": np.array(b["linear_velocity"], dtype=float),
            "base_angular_velocity": np.array(b["angular_velocity"], dtype=float),
            "joint_positions": np.array(sim.joint_positions(), dtype=float),
            "joint_velocities": np.array(sim.joint_velocities(), dtype=float)}


def minimal_state(sim: Simulator, pub: dict):
    """(q, u) in minimal coordinates (the URDF's pin model on a free flyer: position,
    quaternion x y z w, joint angles; world linear velocity, body angular velocity, joint
    rates), as taken by ``Simulator.reset(q, u, minimal=True)``."""
    model = sim.description.model
    idx_q, idx_v = joint_indices(model, sim.joint_names)
    q = np.zeros(model.nq)
    u = np.zeros(model.nv)
    q[0:3] = pub["base_position"]
    q[3:7] = pub["base_orientation"]
    u[0:3] = pub["base_linear_velocity"]
    u[3:6] = pub["base_angular_velocity"]
    q[idx_q] = pub["joint_positions"]
    u[idx_v] = pub["joint_velocities"]
    return q, u


def joint_indices(model, joint_names):
    """(idx_q, idx_v): where each named (one-dof) joint's angle and rate sit in the q and u
    of the pin model `model` (minimal_state's layout)."""
    joints = [model.joints[model.getJointId(name)] for name in joint_names]
    return (np.array([j.idx_q for j in joints], dtype=np.int64),
            np.array([j.idx_v for j in joints], dtype=np.int64))


def parse_initial_state(spec, sim: Simulator):
    """(q, u, description) from the `initial_state` parameter, q and u in the simulator's
    own coordinates (for ``sim.reset(q, u)``).

    spec: 'standing' / '' (``sim.default_state()`` at rest), a YAML mapping (string or
    dict) or the path of a YAML/JSON file with any of base_position, base_orientation
    (x y z w), joint_positions (list in joint order, or {name: angle}),
    base_linear_velocity (world), base_angular_velocity (base frame), joint_velocities;
    missing ones are those of the standing state. A recorded ``initial_state.json`` is
    accepted as is: its q/u are used when its coordinates match, else q_minimal/u_minimal.
    Uses the simulator (resets it)."""
    data = read_state_spec(spec)
    if not isinstance(data, dict):
        raise ConfigError(f"parameter initial_state: expected 'standing', a mapping or a YAML "
                          f"file, got {spec!r}")
    if "joint_names" in data and list(data["joint_names"]) != list(sim.joint_names):
        raise ConfigError("parameter initial_state: joint_names differ from the simulator's")
    data = {k: v for k, v in data.items() if k not in _STATE_INFO_KEYS}
    unknown = set(data) - set(_STATE_KEYS)
    if unknown:
        raise ConfigError(f"parameter initial_state: unknown keys {sorted(unknown)} (known: "
                          f"{', '.join(_PUBLIC_KEYS)})")
    if "q" in data and data.get("coordinates", sim.config.coordinates) == sim.config.coordinates:
        return _state_from_own_coordinates(data, sim)
    if "q_minimal" in data:
        return _state_from_minimal_coordinates(data, sim)
    return _state_from_public_quantities(data, sim)


def _vector(data, key, n, sim):
    """data[key] as n finite numbers, or (joint_*) a {joint name: value} mapping."""
    v = data[key]
    if isinstance(v, dict) and key.startswith("joint_"):
        unknown_j = set(v) - set(sim.joint_names)
        if unknown_j:
            raise ConfigError(f"parameter initial_state: {key}: unknown joints "
                              f"{sorted(unknown_j)}")
        return v
    try:
        a = np.asarray(v, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ConfigError(f"parameter initial_state: {key}: expected {n} numbers, got {v!r}") \
            from None
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise ConfigError(f"parameter initial_state: {key}: expected {n} finite numbers, "
                          f"got {v!r}")
    return a


def _reset_checked(sim, q, u, minimal=False):
    try:
        sim.reset(q=q, u=u, minimal=minimal)
    except ValueError as e:
        raise ConfigError(f"parameter initial_state: {e}") from None
    return sim.q, sim.u


def _state_from_own_coordinates(data, sim):
    """q (and u) given in the simulator's own coordinate set."""
    q, u = _reset_checked(sim, _vector(data, "q", sim.q.shape[0], sim),
                          _vector(data, "u", sim.u.shape[0], sim) if "u" in data else None)
    return q, u, {"spec": {"q": q.tolist(), "u": u.tolist(),
                           "coordinates": sim.config.coordinates}}


def _state_from_minimal_coordinates(data, sim):
    """q_minimal (and u_minimal): pin's free-flyer model of the URDF."""
    model = sim.description.model
    q, u = _reset_checked(sim, _vector(data, "q_minimal", model.nq, sim),
                          _vector(data, "u_minimal", model.nv, sim)
                          if "u_minimal" in data else None, minimal=True)
    return q, u, {"spec": {"q_minimal": data["q_minimal"],
                           "u_minimal": data.get("u_minimal")}}


def _state_from_public_quantities(data, sim):
    """Base pose and velocities, joint angles and rates; the rest from the standing state."""
    public = {k: v for k, v in data.items() if k in _PUBLIC_KEYS}
    sim.reset()
    if not public:
        return sim.q, sim.u, {"spec": "standing"}
    pub = public_state(sim)
    for key in ("base_position", "base_linear_velocity", "base_angular_velocity"):
        if key in public:
            pub[key] = _vector(data, key, 3, sim)
    if "base_orientation" in public:
        quat = _vector(data, "base_orientation", 4, sim)
        if np.linalg.norm(quat) < 1e-9:
            raise ConfigError("parameter initial_state: base_orientation must not be zero")
        pub["base_orientation"] = quat / np.linalg.norm(quat)
    for key in ("joint_positions", "joint_velocities"):
        if key in public:
            v = _vector(data, key, sim.n_joints, sim)
            if isinstance(v, dict):
                for name, val in v.items():
                    try:
                        x = float(val)
                    except (TypeError, ValueError):
                        x = float("nan")
                    if not math.isfinite(x):
                        raise ConfigError(f"parameter initial_state: {key}.{name}: expected a "
                                          f"finite number, got {val!r}")
                    pub[key][sim.joint_names.index(name)] = x
            else:
                pub[key] = v
    q, u = _reset_checked(sim, *minimal_state(sim, pub), minimal=True)
    return q, u, {"spec": {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                           for k, v in public.items()}}


def initial_state_record(sim: Simulator, q0, u0, spec=None) -> dict:
    """The initial state as stored in recordings (and accepted back by the initial_state
    parameter): the simulator's q/u, the minimal-coordinate q/u and the public quantities.
    Uses the simulator (resets it to q0, u0)."""
    sim.reset(q=q0, u=u0)
    pub = public_state(sim)
    qm, um = minimal_state(sim, pub)
    rec = {"coordinates": sim.config.coordinates,
           "q": [float(x) for x in q0], "u": [float(x) for x in u0], "t": 0.0,
           "q_minimal": qm.tolist(), "u_minimal": um.tolist(),
           "note": "q, u: Simulator.reset(q, u) in these coordinates; q_minimal, u_minimal: "
                   "Simulator.reset(q, u, minimal=True) (pin free-flyer order: position, "
                   "quaternion x y z w, joint angles; world linear velocity, body angular "
                   "velocity, joint rates)",
           "joint_names": list(sim.joint_names),
           "parameter": spec if spec is not None else "standing"}
    rec.update({k: v.tolist() for k, v in pub.items()})
    return rec


def quat_to_matrix(qx, qy, qz, qw):
    """Rotation matrix of the unit quaternion (x, y, z, w) (kinematics.quat_xyzw_to_rot)."""
    R = np.empty((3, 3))
    quat_xyzw_to_rot(float(qx), float(qy), float(qz), float(qw), R)
    return R


def base_values(sim: Simulator, base=None):
    """(position, orientation xyzw, world linear velocity, body rates, R, linear velocity in
    the base frame) of the base, as the state topics carry them (lists of floats; the world
    velocity and R as arrays); `base`: (Simulator.base_state(), R) of the current state
    where already read (Sensors.base)."""
    if base is None:
        b = sim.base_state()
        xyzw = b["orientation_xyzw"].tolist()
        R = quat_to_matrix(*xyzw)
    else:
        b, R = base
        xyzw = b["orientation_xyzw"].tolist()
    v = b["linear_velocity"]
    return (b["position"].tolist(), xyzw, v, b["angular_velocity"].tolist(), R,
            (R.T @ v).tolist())


def joint_values(sim: Simulator):
    """(φ, φ̇, applied τ) of the current state, public joint order."""
    return sim.joint_positions(), sim.joint_velocities(), sim.applied_torque


def state_bundle_bytes(bundle_cdr, sec, nsec, base, joints, forces) -> bytes:
    """The state bundle (starleth_interface.state_bundle, through `bundle_cdr`, a
    StateBundleCdr) of one step from base_values, joint_values and the contact forces
    F = Λ/Δt of the feet (the first rows of Simulator.contact_forces(), one per foot of the
    description): the floats of the public state topics, bit for bit."""
    p, quat, _, w, _, v_body = base
    return bundle_cdr.build(sec, nsec, *joints, (*p, *quat), (*v_body, *w),
                            forces.reshape(-1))
