"""Joint-space PD posture hold: the trivial controller of the drop-test demo, the benchmark
and the standing tests (the locomotion controller lives in ``starleth_controller``).

Gains are per joint of a leg (HAA, HFE, KFE), tuned on StarlETH; :meth:`PostureHold.for_robot`
scales them to another robot by dynamic similarity (starleth_interface.robot.scaling: K_p by
μλ, K_d by μλ^1.5), StarlETH's own unchanged. The derivative gains are bounded by the 400 Hz
zero-order hold: a free shank (I ≈ 3.5e-3 kg m² about the KFE) needs k_d T / I < 2, so KFE
k_d = 0.5 N m s/rad (T = 2.5 ms); the scaled k_d T / I grows as 1/√λ only (I scales as μλ²).
"""
from __future__ import annotations

import numpy as np

from starleth_interface.robot.scaling import robot_scale

DEFAULT_KP = (300.0, 300.0, 300.0)  # HAA, HFE, KFE [N m/rad]
DEFAULT_KD = (3.0, 3.0, 0.5)        # [N m s/rad]


class PostureHold:
    """τ = K_p (φ* − φ) − K_d φ̇; kp and kd per joint, or per leg joint (HAA, HFE, KFE)
    repeated for legs of 3 joints in the public order."""

    def __init__(self, target, kp=DEFAULT_KP, kd=DEFAULT_KD):
        self.target = np.asarray(target, dtype=float).copy()
        n = self.target.shape[0]
        kp, kd = np.asarray(kp, dtype=float), np.asarray(kd, dtype=float)
        self.kp = kp.copy() if kp.shape == (n,) else np.tile(kp, n // 3)
        self.kd = kd.copy() if kd.shape == (n,) else np.tile(kd, n // 3)

    @classmethod
    def for_robot(cls, desc, target, kp=DEFAULT_KP, kd=DEFAULT_KD) -> "PostureHold":
        """The hold of a robot (a RobotDescription): each leg joint gets the gains of its
        place in the leg (hip roll, hip pitch, knee), any other joint the hip pitch's, all
        scaled to the robot (module docstring)."""
        scale = robot_scale(desc.legs, desc.total_mass)
        n = len(desc.joint_names)
        role = np.ones(n, dtype=int)
        for leg in desc.legs:
            role[list(leg.joints)] = (0, 1, 2)
        kp = np.asarray(kp, dtype=float)[role] * scale.stiffness
        kd = np.asarray(kd, dtype=float)[role] * scale.damping
        return cls(target, kp, kd)

    def __call__(self, joint_positions, joint_velocities):
        return self.kp * (self.target - joint_positions) - self.kd * joint_velocities

    def torque(self, sim):
        return self(sim.joint_positions(), sim.joint_velocities())
