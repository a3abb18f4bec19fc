"""Mass matrix M and forces h of a forest of floating trees in the paper's coordinates
(composite-rigid-body algorithm and recursive Newton-Euler, Featherstone 2008, in the world
frame; C kernel ``mass_matrix_and_forces`` in ``csrc/rigid_body.c``).

Why not Pinocchio on the hot path: ``pin.crba`` and ``pin.nonLinearEffects`` take their
Python arguments and return numpy copies (a cost per call: doc/performance.md), and their
free-flyer convention (linear velocity in the body frame) needs a transform of M and h
afterwards (`coordinates.forest.from_pin_dynamics`); here the step's midpoint quantities
come from one kernel call that shares the forward kinematics with the contact kinematics
(`coordinates.forest.midpoint_dynamics`). ``test/test_kinematics_dynamics.py`` checks M and
h against Pinocchio (CRBA, RNEA, ABA) on the minimal tree and the extended forest (the
maximal set has a constant M and needs neither).

Conventions: spatial vectors are Plücker coordinates in the world frame at the world origin,
motion [ω; v_O], force [n_O; f]. A tree root is a free body with the paper's velocities
(Eqn. 21): u_root = [I_v (3, inertial velocity of the root frame's origin), B_ω (3)], so its
motion subspace is S = [[0, R]; [1, p x R]] (p, R: the root frame's position and rotation);
a revolute joint with world axis a through p has S = [a; p x a]. With q̈ = 0 the joint
forces of the RNEA are C(q, u) u + g(q) = −h:
    M u̇ = h + τ + W Λ / Δt   (Eqn. 7 per unit time)
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin


class BodyInertias:
    """The inertial parameters of a pin model's bodies (one per joint: mass, centre of mass
    in the joint frame, rotational inertia about the centre of mass in the joint frame) and
    its gravity, as flat arrays for the kernels."""

    def __init__(self, model: pin.Model):
        nj = model.njoints
        self.mass = np.array([model.inertias[j].mass for j in range(nj)], dtype=float)
        self.lever = np.array([model.inertias[j].lever for j in range(nj)], dtype=float)
        self.inertia = np.array([model.inertias[j].inertia for j in range(nj)], dtype=float)
        self.gravity = np.asarray(model.gravity.linear, dtype=float).copy()
        self.mass[0] = 0.0

    def args(self):
        return self.mass, self.lever, self.inertia, self.gravity
