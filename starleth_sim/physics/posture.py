"""Joint-space PD posture hold: the trivial controller of the drop-test demo, the benchmark
and the standing tests (the locomotion controller lives in ``starleth_controller``).

Gains are per joint type (HAA, HFE, KFE). The derivative gains are bounded by the 400 Hz
zero-order hold: a free shank (I ≈ 3.5e-3 kg m² about the KFE) needs k_d T / I < 2, so
KFE k_d = 0.5 N m s/rad (T = 2.5 ms).
"""
from __future__ import annotations

import numpy as np

DEFAULT_KP = (300.0, 300.0, 300.0)  # HAA, HFE, KFE [N m/rad]
DEFAULT_KD = (3.0, 3.0, 0.5)        # [N m s/rad]


class PostureHold:
    """τ = K_p (φ* − φ) − K_d φ̇ for 4 legs x (HAA, HFE, KFE)."""

    def __init__(self, target, kp=DEFAULT_KP, kd=DEFAULT_KD):
        self.target = np.asarray(target, dtype=float).copy()
        n_legs = self.target.shape[0] // 3
        self.kp = np.tile(np.asarray(kp, dtype=float), n_legs)
        self.kd = np.tile(np.asarray(kd, dtype=float), n_legs)

    def __call__(self, joint_positions, joint_velocities):
        return self.kp * (self.target - joint_positions) - self.kd * joint_velocities

    def torque(self, sim):
        return self(sim.joint_positions(), sim.joint_velocities())
