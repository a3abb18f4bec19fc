"""What the stand / trot controller reads: the command (``Command``, the commanded ``MODES``),
the measured robot state (``RobotState``) and the controller's parameters (``ControllerParams``
with its virtual model gains ``VMCGains``). No ROS, no control law (controller.py)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

MODES = ("stand", "trot")          # commanded modes; the controller may also be "fallen"


@dataclass
class Command:
    """Desired motion. Velocities are in the heading (yaw) frame of the trunk."""
    mode: str = "stand"       # "stand" | "trot"
    forward: float = 0.0      # [m/s]
    lateral: float = 0.0      # [m/s]
    yaw_rate: float = 0.0     # [rad/s]


@dataclass
class RobotState:
    """What the controller reads. Joint arrays in the public order (the URDF's; StarlETH:
    LF/RF/LH/RH x HAA/HFE/KFE); feet in the order of the legs (RobotModel.foot_names;
    StarlETH: LF, RF, LH, RH)."""
    t: float
    joint_positions: np.ndarray
    joint_velocities: np.ndarray
    base_position: np.ndarray
    base_orientation_xyzw: np.ndarray
    base_linear_velocity: np.ndarray      # world frame
    base_angular_velocity: np.ndarray     # base frame
    foot_contact: np.ndarray | None = None   # 4 bools; if None, taken from foot_force
    foot_force: np.ndarray | None = None     # (4, 3) force of the ground on the feet [N]

    @classmethod
    def from_simulator(cls, sim, feet=None):
        """From any object with the starleth_sim public API (t, joint_positions(),
        joint_velocities(), base_state(), contacts, description.foot_names: the default
        `feet`)."""
        feet = sim.description.foot_names if feet is None else feet
        b = sim.base_state()
        contacts = {c.name: c for c in sim.contacts}
        flags = np.array([contacts[f].active for f in feet], dtype=bool)
        forces = np.array([contacts[f].force for f in feet], dtype=float)
        return cls(sim.t, sim.joint_positions(), sim.joint_velocities(), b["position"],
                   b["orientation_xyzw"], b["linear_velocity"], b["angular_velocity"],
                   flags, forces)


@dataclass
class VMCGains:
    """Virtual model gains, heading frame. Translation: (heading, lateral, vertical);
    rotation: (roll, pitch, yaw)."""
    kp: tuple = (0.0, 640.0, 600.0)
    kd: tuple = (150.0, 100.0, 120.0)
    kff: tuple = (60.0, 0.0, 0.0)
    kp_rot: tuple = (400.0, 200.0, 100.0)   # yaw kp: ours, holds the commanded heading
    kd_rot: tuple = (6.0, 9.0, 100.0)
    kff_rot: tuple = (0.0, 0.0, 0.0)


def _stand_gains():
    return VMCGains(kp=(640.0, 640.0, 600.0), kd=(100.0, 100.0, 120.0), kff=(0.0, 0.0, 0.0),
                    kp_rot=(400.0, 200.0, 100.0), kd_rot=(6.0, 9.0, 20.0))


@dataclass
class ControllerParams:
    height: float = 0.41                 # desired trunk height above the ground [m]
    # gait
    gait_period: float = 0.8             # T [s] (1.25 Hz)
    duty_factor: float = 0.5
    phase_offsets: tuple = (0.0, 0.5, 0.5, 0.0)   # LF, RF, LH, RH (diagonal pairs)
    swing_height: float = 0.09           # apex [m]
    touchdown_depth: float = 0.01        # the swing ends this far below the ground [m]
    early_touchdown_phase: float = 0.6   # contact after this swing phase = touch-down
    step_feedback: float = 1.1           # k_fb of the inverted-pendulum rule
    step_max: float = 0.25               # clip of the foothold offset [m]
    step_interp_end: float = 0.75        # swing phase at which the foot is above its foothold
    #: default foothold relative to the hip (heading frame, x) per leg LF, RF, LH, RH:
    #: fore feet a little behind, hind feet a little ahead of their hips (towards the knees),
    #: which shares the support torque between HFE and KFE (loco: Offset Fore/Hind heading)
    foothold_offset_x: tuple = (-0.04, -0.04, 0.04, 0.04)
    trot_height: float | None = None     # trunk height while trotting (None: `height`)
    max_acceleration: float = 1.0        # ramp of the velocity command [m/s^2]
    max_yaw_acceleration: float = 2.0    # [rad/s^2]
    # virtual model control
    trot_gains: VMCGains = field(default_factory=VMCGains)
    stand_gains: VMCGains = field(default_factory=_stand_gains)
    #: velocity integral of the trotting VMC (ours; heading and lateral): on a diagonal
    #: support the force QP trades horizontal force for pitch/roll moments, which leaves a
    #: steady speed deficit; F_xy += ki ∫(v* − v) dt, clipped to ±velocity_integral_max
    velocity_ki: float = 250.0           # [N/m]
    velocity_integral_max: float = 40.0  # [N]
    max_position_error: float = 0.1      # clip of the VMC position error [m]
    max_orientation_error: float = 0.4   # clip of the VMC orientation error [rad]
    # contact force distribution
    mu: float = 0.7
    min_normal_force: float = 2.0
    wrench_weights: tuple = (1.0, 1.0, 1.0, 20.0, 20.0, 5.0)
    force_regularization: float = 1e-4
    qp_torque_margin: float | None = 0.95   # joint torque rows at this share of the limit
    # swing / position-controlled legs: HAA, HFE, KFE
    joint_kp: tuple = (70.0, 70.0, 26.0)
    joint_kd: tuple = (3.1, 3.2, 0.2)
    # a leg without the contact it should have searches the ground (step_down.py)
    lost_contact_speed: float = 0.2      # standing: its lowering rate [m/s]
    lost_contact_depth: float = 0.06     # standing: at most this far below the ground [m]
    #: trotting: the lowering rate of a foot that found no ground at the end of its swing
    #: (a step down; the gait clock waits for it) [m/s]
    step_down_speed: float = 1.0
    #: trotting: at most this far below the height the ground plane expected at its foothold
    #: (a ledge of up to about this height is stepped down) [m]
    step_down_depth: float = 0.18
    #: a searching foot stays within this share of the stretched leg's length (l1 + l2) from
    #: its HFE joint; the trunk is lowered for a search that needs more
    leg_reach: float = 0.98
    contact_force_threshold: float = 5.0  # grounded from forces when no flags are given [N]
    # falls: beyond this tilt the controller gives up balancing and holds a compact posture
    fall_tilt: float = 0.8               # [rad]
    recover_tilt: float = 0.3            # upright again below this tilt ...
    recover_time: float = 1.0            # ... for this long, with >= 3 feet on the ground [s]
