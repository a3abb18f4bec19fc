"""State conversions between the simulator and the ROS interface: the ``initial_state``
parameter (YAML, a file, or a recording's initial_state.json) to (q, u), the record of the
initial state stored in recordings, the public (convention-free) state, and the IMU's
proper acceleration by finite differences. ROS-free."""
from __future__ import annotations

import math

import numpy as np
import yaml

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
        try:
            with open(s) as f:
                return yaml.safe_load(f) or {}
        except OSError as e:
            raise ConfigError(f"parameter initial_state: cannot read {s}: {e}") from None
        except yaml.YAMLError as e:
            raise ConfigError(f"parameter initial_state: {s} is not valid YAML: {e}") from None
    try:
        return yaml.safe_load(s)
    except yaml.YAMLError as e:
        raise ConfigError(f"parameter initial_state: not valid YAML: {e}") from None


def public_state(sim: Simulator, base: dict | None = None) -> dict:
    """The simulator's current state in convention-free public quantities (`base`: the
    values of sim.base_state() if the caller has them)."""
    b = sim.base_state() if base is None else base
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
    q = np.zeros(model.nq)
    u = np.zeros(model.nv)
    q[0:3] = pub["base_position"]
    q[3:7] = pub["base_orientation"]
    u[0:3] = pub["base_linear_velocity"]
    u[3:6] = pub["base_angular_velocity"]
    for i, name in enumerate(sim.joint_names):
        j = model.joints[model.getJointId(name)]
        q[j.idx_q] = pub["joint_positions"][i]
        u[j.idx_v] = pub["joint_velocities"][i]
    return q, u


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


class ImuEstimate:
    """The IMU at the base origin: proper acceleration a = Rᵀ (dv/dt − g) in the base frame,
    dv/dt by the difference of the world linear velocity with the previous step's (zero on
    the first state, and on the first state after a reset or after nobody listened; a
    re-sent state gets the same value again)."""

    def __init__(self, gravity, control_period: float):
        self.gravity = np.asarray(gravity, dtype=float)
        self.dt = control_period
        self._v_prev = None    # (step, world linear velocity)
        self._acc = None       # (step, dv/dt) of the last estimate

    def restart(self):
        """Forget the previous velocity (after a reset)."""
        self._v_prev = self._acc = None

    def proper_acceleration(self, k: int, v, R) -> np.ndarray:
        if self._v_prev is not None and self._v_prev[0] == k - 1:
            acc = (v - self._v_prev[1]) / self.dt
            self._acc = (k, acc)
        elif self._acc is not None and self._acc[0] == k:    # re-sent state
            acc = self._acc[1]
        else:
            acc = np.zeros(3)
        if self._v_prev is None or self._v_prev[0] != k:
            self._v_prev = (k, np.array(v, dtype=float))
        return R.T @ (acc - self.gravity)


class FastStateReader:
    """What sim_node reads from the simulator every step, with the step-invariant parts
    computed once: ``base_state()`` gives the values of ``sim.base_state()`` (position,
    quaternion xyzw, world linear velocity, base angular velocity) and ``foot_forces(n)``
    the forces F = Λ/Δt of the first n contact points, as ``sim.contacts[i].force``.

    Same operations on the same operands as the simulator's own accessors, bit for bit:
    the base state of forest coordinates whose trunk frame has the root body's exact
    orientation (the trunk's transform Y in the root body, its inverse and the check that
    its rotation is the identity are taken once, instead of every step); the forces from
    the same world impulse product, without building the ContactInfo records. Where the
    simulator is of another kind (other coordinates, other internals), or the check at
    construction finds a difference, the simulator's accessors are used; every CHECK_EVERY
    calls the fast values are compared with the accessors' again, and a difference switches
    to the accessors for good (``on_mismatch(message)`` is told)."""

    CHECK_EVERY = 400      # calls (1 s of sim time at 400 Hz)

    def __init__(self, sim: Simulator, on_mismatch=None):
        self.sim = sim
        self.on_mismatch = on_mismatch
        self._calls = {"base": 0, "forces": 0}
        self._base = None
        self._forces = None
        try:
            from ..physics.coordinates.forest import ForestCoordinates, _quat_rot
            c = sim.coords
            if type(c).base_state is ForestCoordinates.base_state:
                Y = c.joint_map[1][1].inverse()
                rot = Y.rotation
                if np.array_equal(rot, np.eye(3)):
                    self._base = (c.root_q[0], c.root_v[0], Y.translation, rot.T, _quat_rot)
                    self._keep = (Y, rot)    # the arrays may view Y's memory
        except Exception:   # other internals: the simulator's own accessor
            self._base = None
        try:
            sim._impulse @ sim.stepper.ground.frame   # noqa: B018 - the internals exist
            self._forces = True
        except Exception:
            self._forces = None
        if self._base is not None and not _same_values(self._base_fast(), sim.base_state()):
            self._base = None
        if self._forces and not all(np.array_equal(f, c.force) for f, c in
                                    zip(self._forces_fast(len(sim.contacts)), sim.contacts)):
            self._forces = None

    def _base_fast(self):
        sim = self.sim
        iq, iv, t, rot_t, quat_rot = self._base
        q, u = sim.state.q, sim.state.u
        R = np.zeros((3, 3))
        quat_rot(q, iq, R)
        d = R @ t
        pos = q[iq:iq + 3] + d
        w_body = u[iv + 3:iv + 6]
        a0, a1, a2 = (R @ w_body).tolist()
        b0, b1, b2 = d.tolist()
        # np.cross(R w, d) written out: the same products and differences, bit for bit
        v = u[iv:iv + 3] + np.array((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0))
        return {"position": pos, "orientation_xyzw": q[iq + 3:iq + 7].copy(),
                "linear_velocity": v, "angular_velocity": rot_t @ w_body}

    def _checked(self, kind) -> bool:
        """True on every CHECK_EVERY-th call of `kind`."""
        n = self._calls[kind] = self._calls[kind] + 1
        return n % self.CHECK_EVERY == 0

    def _mismatch(self, what):
        if self.on_mismatch is not None:
            self.on_mismatch(f"FastStateReader: the fast {what} differs from the simulator's "
                             "accessor; using the accessor from now on")

    def base_state(self) -> dict:
        """sim.base_state()"""
        if self._base is None:
            return self.sim.base_state()
        fast = self._base_fast()
        if self._checked("base"):
            ref = self.sim.base_state()
            if not _same_values(fast, ref):
                self._base = None
                self._mismatch("base state")
                return ref
        return fast

    def _forces_fast(self, n):
        sim = self.sim
        world = sim._impulse @ sim.stepper.ground.frame
        return world[:n] / sim.control_period        # row i: world[i] / Δt, as ContactInfo

    def foot_forces(self, n) -> np.ndarray:
        """n x 3: row i = sim.contacts[i].force"""
        if self._forces:
            fast = self._forces_fast(n)
            if not self._checked("forces"):
                return fast
            ref = np.array([c.force for c in self.sim.contacts[:n]], dtype=float)
            if fast.tobytes() == ref.tobytes():
                return fast
            self._forces = None
            self._mismatch("foot forces")
        return np.array([c.force for c in self.sim.contacts[:n]], dtype=float)


def _same_values(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(
        np.asarray(a[k]).tobytes() == np.asarray(b[k]).tobytes() for k in a)
