"""How gains tuned on StarlETH carry over to another robot: dynamic similarity with gravity
fixed (Froude scaling). With λ the robot's leg length (thigh + shank, the mean over its
roll-pitch-pitch legs) over StarlETH's 0.435 m and μ its mass over StarlETH's 26.82 kg,
lengths scale as λ, masses as μ and times as √λ (the pendulum time √(l/g)); so

    forces  μ          torques  μ λ          velocities  √λ
    a joint stiffness [N m/rad]  μ λ         a joint damping [N m s/rad]  μ λ^1.5

A geometrically similar robot λ times larger and μ times heavier then moves like StarlETH
slowed by √λ, its joint errors and sags (angles) the same. The factors are rounded to 6
significant digits, so that StarlETH (and any robot of its size) gets its own numbers bit for
bit. A robot without such legs keeps λ = 1 (mass alone scales).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

#: StarlETH's leg (thigh 0.2 m + shank to the foot centre 0.235 m) and mass: the reference
REFERENCE_LEG_LENGTH = 0.435       # m
REFERENCE_MASS = 26.82             # kg


def _rounded(x: float) -> float:
    return float(f"{x:.6g}")


@dataclass(frozen=True)
class RobotScale:
    """λ (length) and μ (mass) relative to StarlETH (module docstring)."""

    length: float
    mass: float

    @property
    def time(self) -> float:
        return math.sqrt(self.length)

    @property
    def stiffness(self) -> float:
        """Of a joint stiffness [N m/rad] (and a torque)."""
        return self.mass * self.length

    @property
    def damping(self) -> float:
        """Of a joint damping [N m s/rad]."""
        return self.mass * self.length * self.time


def robot_scale(legs, total_mass: float) -> RobotScale:
    """The RobotScale of a robot: its legs (legs.find_legs) and its total mass [kg]."""
    lengths = [leg.plane.length for leg in legs if leg.plane is not None]
    length = sum(lengths) / len(lengths) / REFERENCE_LEG_LENGTH if lengths else 1.0
    return RobotScale(length=_rounded(length), mass=_rounded(total_mass / REFERENCE_MASS))
