"""The cross-check of the three coordinate sets (Table 1) shared by test_coordinates.py and
test_robots.py: the same initial state and torque history replayed open loop in minimal,
extended and maximal coordinates."""
import numpy as np

from starleth_sim import Simulator

TIGHT = dict(tol_rel=1e-12, tol_abs=1e-12, max_iterations=20000)


def replay(preset, q_min, u_min, torques, **overrides):
    """Open loop: the torques as given (ideal torque sources, velocity_limit "ignore": the
    open-loop robot falls and flails its legs beyond the motors' speed limit, where the
    derating would feed each set's own O(Δt) velocities back into the torques)."""
    overrides.setdefault("velocity_limit", "ignore")
    sim = Simulator.from_preset(preset, **TIGHT, **overrides)
    sim.reset(q_min, u_min, minimal=True)
    for tau in torques:
        sim.step(tau)
        assert sim.diagnostics.converged
    b = sim.base_state()
    return sim, np.concatenate([sim.joint_positions(), b["position"]]), b["orientation_xyzw"]


def rotation_angle(qa, qb):
    """Angle [rad] of the rotation between two orientations (quaternions, either sign)."""
    c = min(1.0, abs(float(np.dot(qa, qb))) / (np.linalg.norm(qa) * np.linalg.norm(qb)))
    return 2.0 * np.arccos(c)


def compare_three(q_min, u_min, torques, native_tol, **overrides):
    """Same initial state, same torque history (zero-order hold per control period), three
    coordinate sets. The scheme is first order, so each set's error is C Δt with a constant
    that depends on the coordinates; the sets agree in the limit Δt -> 0, shown by Richardson
    extrapolation 2 x(Δt/8) - x(Δt/4) (to 1e-4 rad / m). At the native Δt = 2.5 ms they
    agree within `native_tol`. overrides: of every run (robot="go1": another robot)."""
    x, quat = {}, {}
    for preset in ("HmJ", "HEJD", "HMJD"):
        for spc in (1, 4, 8):
            sim, x[preset, spc], quat[preset, spc] = replay(preset, q_min, u_min, torques,
                                                            steps_per_control=spc,
                                                            **overrides)
    for preset in ("HEJD", "HMJD"):
        ext = 2 * x[preset, 8] - x[preset, 4]
        ext_ref = 2 * x["HmJ", 8] - x["HmJ", 4]
        np.testing.assert_allclose(ext, ext_ref, atol=1e-4, err_msg=preset)
        q_ext = 2 * quat[preset, 8] - quat[preset, 4]        # same extrapolation (q ≈ q')
        q_ext_ref = 2 * quat["HmJ", 8] - quat["HmJ", 4]
        assert rotation_angle(q_ext, q_ext_ref) < 1e-4, preset
        # first order: the difference at Δt/8 is ~1/8 of the one at Δt
        d1 = np.abs(x[preset, 1] - x["HmJ", 1]).max()
        d8 = np.abs(x[preset, 8] - x["HmJ", 8]).max()
        assert d1 < native_tol[preset], (preset, d1)
        assert d8 < d1 / 4 or d1 < 1e-9, (preset, d1, d8)
    return sim
