"""Model-based stand / trot controller for StarlETH, after Gehring et al., ICRA 2013
("Control of dynamic gaits for a quadrupedal robot") and its open-source descendant loco.

No ROS: ``StarlethController.update(state, command) -> 12 joint torques``; the per-call
arithmetic of the steps below runs in C kernels (kernels.py: csrc/) that keep the order of
operations of the formulas written here (results bit for bit those of plain Python); the
search for the ground of a foot without contact is plain Python (step_down.py).

Structure (one call = one control period):

1. Kinematics: analytic leg kinematics (feet, contact-point Jacobians; geometry read from the
   URDF and checked against Pinocchio in the tests) and, from the controller's own Pinocchio
   model, the legs' gravity torques and the centre of mass.
2. Gait pattern (trot): a clock with period T; diagonal pairs LF+RH and RF+LH half a cycle
   apart, duty factor 0.5. Each leg's plan (swing/stance, phase) is combined with its contact
   flag as in loco's LimbCoordinatorDynamicGait: planned stance + ground contact = support leg;
   planned stance without contact = lost contact (the foot searches the ground below where
   it expected it: step_down.py); planned swing with contact after 60 % of the swing = early
   touch-down (support leg); planned swing with contact before that = late lift-off / bump
   (the swing goes on). A swing that ends without contact holds the clock while its foot
   searches (a step down: the other pair stays in support, the trunk waits and is lowered
   as far as the leg needs to reach).
3. Support legs (torque mode): virtual model control of the trunk (PD on position, velocity
   and orientation in the heading frame, velocity feed-forward, gravity feed-forward of the
   whole robot) gives a desired wrench about the centre of mass, which a QP distributes onto
   the support feet (force_distribution.py); τ = −J_iᵀ f_i + g_leg, J_i the contact point's
   translational Jacobian w.r.t. the leg joints (world axes, trunk fixed) and f_i the force of
   the ground on the robot.
4. Swing legs (position mode): the foothold from the inverted-pendulum rule
   Δ = ½ v* T_stance + k_fb (v − v*) √(h/g) (clipped, plus a default offset), a foot
   trajectory from the lift-off point to the foothold with an apex height, analytic leg IK,
   joint PD with gravity feed-forward.
5. Torques saturated at the joints' effort limits.

Additions of ours to loco's scheme (each a parameter, documented in ControllerParams):
joint-torque rows in the force QP, a velocity integral in the trotting VMC, a yaw P gain,
default footholds shifted towards the knees, the ground plane of the feet's last footholds
(csrc/ground_plane.c), the gait's wait for a foot searching the ground (step_down.py), and a
"fallen" mode (beyond 0.8 rad of tilt the controller stops balancing and holds a compact
posture; it stands again once upright).
"""
from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np
import pinocchio as pin

from . import kernels as K
from .force_distribution import ContactForceDistribution
from .inputs import MODES, Command, ControllerParams, RobotState, VMCGains
from .model import RobotModel
from .robot_params import params_for_robot
from .step_down import GroundSearch

#: the ufunc behind np.clip / ndarray.clip (the same values, without their Python wrapper)
_clip = getattr(np, "_core", np.core).umath.clip

# leg states (per control period)
SUPPORT = 0          # stance, on the ground: torque mode from VMC + QP
SWING = 1            # swing (also late lift-off / bumped): joint PD on the swing trajectory
LOST_CONTACT = 2     # planned stance (or standing) without ground contact: searches it
STATE_NAMES = ("support", "swing", "lost_contact")


class _Sample:
    """The measured state of one control period as the steps of ``StarlethController.update``
    read it: time t and step dt [s]; joints qj, dqj (public order); trunk position pb and
    velocity vb (world), quaternion quat (x, y, z, w, normalised), angular velocity wb (base
    frame) and ww = R wb (world); R (base→world); heading ψ = `yaw`, cy = cos ψ, sy = sin ψ;
    grounded: the 4 feet's contact flags."""
    __slots__ = ("t", "dt", "qj", "dqj", "pb", "quat", "vb", "wb", "R", "yaw", "cy", "sy",
                 "ww", "grounded")

    def __init__(self, t, dt, qj, dqj, pb, quat, vb, wb, R, yaw, cy, sy, ww, grounded):
        self.t, self.dt, self.qj, self.dqj = t, dt, qj, dqj
        self.pb, self.quat, self.vb, self.wb = pb, quat, vb, wb
        self.R, self.yaw, self.cy, self.sy = R, yaw, cy, sy
        self.ww, self.grounded = ww, grounded


class StarlethController:
    """Stand and trot controller. ``update(state, command)`` returns 12 joint torques in the
    public order; ``info`` holds the figures of the last call (leg states, desired contact
    forces, QP status, ...)."""

    def __init__(self, urdf: str | None = None, params: ControllerParams | None = None,
                 robot: str | None = None, model: RobotModel | None = None):
        self.model = model or RobotModel(urdf, robot)
        #: default: StarlETH's parameters scaled to the robot (robot_params.py)
        self.params = params or params_for_robot(self.model)
        p = self.params
        self.cfd = ContactForceDistribution(mu=p.mu, min_normal_force=p.min_normal_force,
                                            weights=p.wrench_weights,
                                            regularization=p.force_regularization,
                                            torque_limit=(None if p.qp_torque_margin is None
                                                          else self.model.effort_limit[:3]
                                                          * p.qp_torque_margin))
        self.command = Command()
        m = self.model
        self._kp3 = np.asarray(p.joint_kp, dtype=float)
        self._kd3 = np.asarray(p.joint_kd, dtype=float)
        self._lim = m.effort_limit.copy()
        self._neg_lim = -self._lim            # lower saturation bound (not negated per call)
        self._geo = m.geometry
        self._gains_trot = self._gain_arrays(p.trot_gains)
        self._gains_stand = self._gain_arrays(p.stand_gains)
        # work arrays (no per-call allocation where it is easy)
        self._tau = np.zeros(12)
        self._R = np.eye(3)
        self._quat_n = np.zeros(4)
        self._Rd = np.eye(3)
        self._q = pin.neutral(m.model)
        self._centre = np.zeros((4, 3))
        self._contact = np.zeros((4, 3))
        self._Jf = np.zeros((4, 3, 3))
        self._Jc = np.zeros((4, 3, 3))
        self._e, self._vh, self._vd = np.zeros(3), np.zeros(3), np.zeros(3)
        self._no_velocity = np.zeros(2)      # the trunk's velocity command while it waits
        self._f_kept = np.zeros(2)           # (vmc_force clears it: the integral is kept)
        self._eh, self._wh, self._wd = np.zeros(3), np.zeros(3), np.zeros(3)
        self._b = np.zeros(6)
        self._rh = {n: np.zeros((n, 3)) for n in range(1, 5)}
        self._Jh = {n: np.zeros((n, 3, 3)) for n in range(1, 5)}
        self._gh = {n: np.zeros((n, 3)) for n in range(1, 5)}
        self._target, self._vtarget = np.zeros(3), np.zeros(3)
        self._swing_phase = np.zeros(4)
        self._support_idx = np.zeros(4, dtype=np.int64)   # the support legs, first ns
        self._all_legs = np.arange(4, dtype=np.int64)
        self._leg_state_arr = np.zeros(4, dtype=np.int64)  # leg_state as an array
        self._swing_p = np.zeros(K.SW_STANCE_Y + 4)
        self._swing_p[K.SW_STANCE_X:K.SW_STANCE_Y] = m.geometry[:, 5]   # the legs' o_x
        self._swing_p[K.SW_STANCE_Y:] = m.geometry[:, 6]                 # and d_y
        self._swing_key = None
        self._phase_offsets = (None, None)   # (array, the parameter it was made from)
        self._mass_g = m.mass * m.gravity
        self._q_nominal = m.nominal_joint_positions(p.height)
        self._search = GroundSearch()
        self._hips = np.zeros((4, 3))              # the hips in the world (while searching)
        self._search_target = np.zeros((4, 4))     # searching feet's targets and rates
        self.reset()

    @staticmethod
    def _gain_arrays(g: VMCGains):
        return [np.asarray(x, dtype=float).copy() for x in
                (g.kp, g.kd, g.kff, g.kp_rot, g.kd_rot, g.kff_rot)]

    # ------------------------------------------------------------------------------------
    def reset(self):
        self.mode = "stand"
        self._require_stand_cmd = False
        self._upright_since = math.nan
        self._initialized = False
        self._t0 = 0.0
        self._stop_requested = False
        self._half_cycle = 0
        self._ground = 0.0
        self._yaw_des = 0.0
        self._v_cmd = np.zeros(2)        # ramped velocity command (heading frame)
        self._w_cmd = 0.0
        self._f_int = np.zeros(2)
        self._t_prev = None
        self._swing_cycle = np.full(4, -1, dtype=np.int64)   # cycle of each leg's last lift-off
        self._r_liftoff = np.zeros((4, 2))   # hip→foot at lift-off, heading frame
        self._foothold = np.zeros((4, 2))    # last swing target (world xy)
        self._foothold_z = np.zeros(4)       # its expected ground height (the plane's)
        self._liftoff_z = np.zeros(4)        # each swing's lift-off height (contact point)
        self._stood = np.zeros((4, 3))       # where each foot last stood (contact point)
        self._plane = np.zeros(3)            # ground plane z = a + g_x x + g_y y (world)
        self._lost_since = np.full(4, np.nan)
        self._search.reset()
        self._trunk_reference = 0.0          # the trunk's height reference (world z)
        self.leg_state = [SUPPORT] * 4
        self.desired_forces = np.zeros((4, 3))   # ground on robot, world [N]
        self.info = {}
        self.call_time = 0.0

    def set_command(self, mode=None, forward=None, lateral=None, yaw_rate=None):
        c = self.command
        if mode is not None:
            if mode not in MODES:
                raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
            c.mode = mode
        if forward is not None:
            c.forward = float(forward)
        if lateral is not None:
            c.lateral = float(lateral)
        if yaw_rate is not None:
            c.yaw_rate = float(yaw_rate)

    def _fallen_torques(self, qj, dqj, pb, quat, t_wall):
        """Fallen: joint PD to the nominal posture (compact legs) with gravity feed-forward,
        no balancing."""
        m = self.model
        q = self._q
        q[0:3] = pb
        q[3:7] = quat
        q[m.iq] = qj
        gleg = pin.computeGeneralizedGravity(m.model, m.data, q)[m.iv]
        tau = self._tau
        tau[:] = (np.tile(self._kp3, 4) * (self._q_nominal - qj) - np.tile(self._kd3, 4) * dqj
                  + gleg)
        _clip(tau, self._neg_lim, self._lim, out=tau)   # np.clip's ufunc, no wrapper
        self.desired_forces[:] = 0.0
        self.call_time = time.perf_counter() - t_wall
        self.info = {"mode": "fallen", "leg_state": ["fallen"] * 4, "support": [],
                     "qp_status": "idle", "qp_iterations": 0, "qp_failures": self.cfd.failures}
        return tau.copy()

    # ------------------------------------------------------------------------------------
    def update(self, s: RobotState, command: Command | None = None) -> np.ndarray:
        """One control period: the 12 joint torques (public order, saturated); joints in
        the public order, feet in the model's (its legs')."""
        order = self.model.joint_order
        if order is None:
            return self._update(s, command)
        s = replace(s, joint_positions=np.asarray(s.joint_positions)[order],
                    joint_velocities=np.asarray(s.joint_velocities)[order])
        tau = np.empty(12)
        tau[order] = self._update(s, command)
        return tau

    def _update(self, s: RobotState, command: Command | None) -> np.ndarray:
        """One control period in the controller's joint order (leg by leg).

        After taking the command, advancing the clock and reading the state (zero torque for
        a non-finite state, the fallen posture after a fall: _fallen_torques), the five steps
        of the module docstring, one method each."""
        t_wall = time.perf_counter()
        self._take_command(command)
        t, dt = self._advance_clock(s.t)
        x = self._read_state(s, t, dt)
        if x is None:
            # never pass NaN on: zero torque, reported in info
            self.info = {"error": "non-finite state", "mode": self.mode}
            self._tau[:] = 0.0
            return self._tau.copy()
        if self._check_fall(x):
            return self._fallen_torques(x.qj, x.dqj, x.pb, x.quat, t_wall)
        gleg, com = self._kinematics(x)                                        # 1.
        trotting, support = self._gait_pattern(x)                              # 2.
        b = self._support_leg_torques(x, trotting, support, gleg, com)         # 3.
        self._position_controlled_leg_torques(x, gleg)                         # 4.
        return self._saturate_and_report(x, support, b, com, t_wall)           # 5.

    # -- reading the inputs ----------------------------------------------------------------
    def _take_command(self, command):
        """Keeps `command` (if given) as the current command, after checking its mode."""
        if command is not None:
            if command.mode not in MODES:
                raise ValueError(f"mode must be one of {MODES}, got {command.mode!r}")
            self.command = command

    def _advance_clock(self, t):
        """(t, dt): the state's time t and the time dt since the last call (0 on the first).
        A time going backwards means the robot / simulator was reset: so is the controller."""
        t = float(t)
        if self._t_prev is not None and t < self._t_prev - 1e-9:
            self.reset()      # time went backwards: the robot / simulator was reset
        dt = 0.0 if self._t_prev is None else t - self._t_prev
        self._t_prev = t
        return t, dt

    def _read_state(self, s: RobotState, t, dt):
        """The measured state as a _Sample, or None when it is not finite (or the quaternion
        is zero): joints qj, dqj; trunk pb, quat (normalised), vb (world), wb (base frame);
        R = R(quat) (base→world), heading ψ = atan2(R₁₀, R₀₀) with cy = cos ψ, sy = sin ψ;
        ww = R wb; the contact flags (given, or foot_force_z > contact_force_threshold)."""
        p = self.params
        qj = np.asarray(s.joint_positions, dtype=float)
        dqj = np.asarray(s.joint_velocities, dtype=float)
        pb = np.asarray(s.base_position, dtype=float)
        quat = np.asarray(s.base_orientation_xyzw, dtype=float)
        vb = np.asarray(s.base_linear_velocity, dtype=float)
        wb = np.asarray(s.base_angular_velocity, dtype=float)
        R = self._R
        # the checks and the normalisation in one kernel; it leaves inputs of 1e100 or more
        # (whose sum below could overflow) to numpy, as before
        status = K.read_state(qj, dqj, pb, quat, vb, wb, self._quat_n, R)
        if status == 2:
            add = np.add.reduce                      # = ndarray.sum, without its wrapper
            if not math.isfinite(float(add(qj) + add(dqj) + add(pb) + add(quat) + add(vb)
                                       + add(wb))) or K.squared_norm4(quat) < 1e-12:
                return None
            quat = quat / math.sqrt(K.squared_norm4(quat))
            K.quat_to_rot(quat[0], quat[1], quat[2], quat[3], R)
        elif status:
            return None
        else:
            quat = self._quat_n
        yaw = math.atan2(R[1, 0], R[0, 0])
        cy, sy = math.cos(yaw), math.sin(yaw)
        ww = R @ wb                                  # angular velocity, world frame

        if s.foot_contact is not None:
            grounded = np.asarray(s.foot_contact, dtype=bool)
        elif s.foot_force is not None:
            grounded = np.asarray(s.foot_force, dtype=float)[:, 2] > p.contact_force_threshold
        else:
            raise ValueError("RobotState needs foot_contact or foot_force")
        if grounded.shape != (4,):
            raise ValueError(f"RobotState: 4 feet expected in foot_contact / foot_force, "
                             f"got {grounded.shape[0] if grounded.ndim == 1 else grounded.shape}")
        return _Sample(t, dt, qj, dqj, pb, quat, vb, wb, R, yaw, cy, sy, ww, grounded)

    def _check_fall(self, x: _Sample) -> bool:
        """Falls: "fallen" once the tilt (cos = R₂₂) exceeds fall_tilt; back to "stand" (trot
        only after a fresh stand command) when below recover_tilt with >= 3 feet on the ground
        for recover_time. True while fallen."""
        p = self.params
        t = x.t
        tilt_cos = x.R[2, 2]
        if self.mode != "fallen" and tilt_cos < math.cos(p.fall_tilt):
            self.mode = "fallen"
            self._upright_since = math.nan
        if self.mode == "fallen":
            if tilt_cos > math.cos(p.recover_tilt) and int(x.grounded.sum()) >= 3:
                if self._upright_since != self._upright_since:
                    self._upright_since = t
                elif t - self._upright_since >= p.recover_time:
                    # back on its feet: stand (trot again only after a fresh stand command)
                    self.mode = "stand"
                    self._require_stand_cmd = True
                    self._initialized = False
            else:
                self._upright_since = math.nan
        return self.mode == "fallen"

    # -- 1. kinematics ---------------------------------------------------------------------
    def _kinematics(self, x: _Sample):
        """Step 1: analytic leg kinematics into the work arrays (hip-frame leg centres
        `_centre`, contact points `_contact` (4 x 3, world), foot and contact-point
        Jacobians `_Jf`, `_Jc` (4 x 3 x 3, world axes)); from Pinocchio the legs' gravity
        torques g_leg (12, public order) and the centre of mass. On the first call (and
        after a reset or a recovery) the ground height and the desired heading ψ* start
        from the lowest contact point and the trunk's heading. Returns (g_leg, com)."""
        m = self.model
        qj, pb, quat = x.qj, x.pb, x.quat
        K.leg_kinematics(qj, x.R, pb, m.hip, self._geo, self._centre, self._contact, self._Jf,
                         self._Jc)
        q = self._q
        q[0:3] = pb
        q[3:7] = quat
        q[m.iq] = qj
        gvec = pin.computeGeneralizedGravity(m.model, m.data, q)
        gleg = gvec[m.iv]                            # public order
        com = pin.centerOfMass(m.model, m.data, q, False)

        if not self._initialized:
            self._ground = float(self._contact[:, 2].min())
            self._stood[:] = self._contact
            self._stood[:, 2] = self._ground
            self._yaw_des = x.yaw
            self._initialized = True
        return gleg, com

    # -- 2. gait pattern -------------------------------------------------------------------
    def _gait_pattern(self, x: _Sample):
        """Step 2: the mode and the trot clock, the ramped velocity command and desired
        heading, each leg's state (self.leg_state) and swing phase, the ground height under
        the support feet, and where the legs without contact search the ground, with the
        trunk's height reference. Returns (trotting, support legs)."""
        trotting = self._switch_mode(x.t)
        self._ramp_command(x.dt, x.yaw, trotting)
        support = self._leg_states(x, trotting)
        self._estimate_ground(support)
        self._search_ground(x, trotting)
        return trotting, support

    def _switch_mode(self, t):
        """Stand → trot on a trot command (not before a stand command after a recovery): the
        clock starts at t₀ = t. Trot → stand on a stand command, at the end of the current
        half cycle ⌊2 (t − t₀) / T⌋ (when the swing pair touches down). True while
        trotting."""
        p = self.params
        cmd = self.command
        T = p.gait_period
        if cmd.mode == "stand":
            self._require_stand_cmd = False
        if self.mode == "stand" and cmd.mode == "trot" and not self._require_stand_cmd:
            self.mode = "trot"
            self._t0 = t
            self._half_cycle = 0
            self._stop_requested = False
            self._swing_cycle[:] = -1
        elif self.mode == "trot":
            self._stop_requested = cmd.mode == "stand"
        trotting = self.mode == "trot"
        if trotting:
            half = int(math.floor(2.0 * (t - self._t0) / T + 1e-9))
            if self._stop_requested and half != self._half_cycle:
                # stop at the end of a half cycle, when the swing pair touches down
                trotting = False
                self.mode = "stand"
                self._stop_requested = False
            self._half_cycle = half
        return trotting

    def _ramp_command(self, dt, yaw, trotting):
        """The velocity command (v*_x, v*_y: self._v_cmd, heading frame; ω*: self._w_cmd)
        ramped towards the command (zero unless trotting) at max_acceleration and
        max_yaw_acceleration; the desired heading ψ* += ω* dt, held within
        max_orientation_error of the heading ψ = `yaw` (no wind-up)."""
        p = self.params
        cmd = self.command
        vx_t, vy_t = (cmd.forward, cmd.lateral) if trotting else (0.0, 0.0)
        w_t = cmd.yaw_rate if trotting else 0.0
        if dt > 0:
            dvx, dvy = vx_t - self._v_cmd[0], vy_t - self._v_cmd[1]
            n = math.hypot(dvx, dvy)
            lim = p.max_acceleration * dt
            if n <= lim:
                self._v_cmd[0], self._v_cmd[1] = vx_t, vy_t
            else:
                self._v_cmd[0] += dvx * lim / n
                self._v_cmd[1] += dvy * lim / n
            dw = w_t - self._w_cmd
            lim = p.max_yaw_acceleration * dt
            self._w_cmd = w_t if abs(dw) <= lim else self._w_cmd + math.copysign(lim, dw)
        wc = self._w_cmd
        self._yaw_des += wc * dt
        e_yaw = (self._yaw_des - yaw + math.pi) % (2 * math.pi) - math.pi
        if abs(e_yaw) > p.max_orientation_error:   # no wind-up while held off the heading
            self._yaw_des = yaw + math.copysign(p.max_orientation_error, e_yaw)

    def _leg_states(self, x: _Sample, trotting):
        """Each leg's state (self.leg_state) from its plan and its contact flag (module
        docstring, step 2), its swing phase s ∈ [0, 1) (1 outside the swing), the time since
        contact was lost (kernels.leg_states), and at a new lift-off the hip→foot offset in
        the heading frame. Returns the support legs."""
        p = self.params
        offsets, key = self._phase_offsets, tuple(p.phase_offsets)
        if offsets[1] != key:      # the array made again only when the parameter changed
            offsets = self._phase_offsets = (np.array(key, dtype=float), key)
        # a swing ending without ground contact holds the clock (step_down.py)
        self._t0 = self._search.hold_clock(p, trotting, x.t, x.dt, self._t0, key,
                                           self._swing_cycle, x.grounded, self._contact[:, 2],
                                           self._foothold_z)
        ns, lift = K.leg_states(bool(trotting), x.t, self._t0, p.gait_period, offsets[0],
                                p.duty_factor, p.early_touchdown_phase, x.grounded,
                                self._swing_phase, self._swing_cycle, self._leg_state_arr,
                                self._lost_since, self._support_idx)
        self._search.mark_waiting(self._leg_state_arr, self._swing_phase, self._lost_since)
        if lift:
            # lift-off of a new swing: remember where the foot starts (heading frame,
            # relative to the hip)
            hip, pb, R, cy, sy, contact_pt = self.model.hip, x.pb, x.R, x.cy, x.sy, self._contact
            for k in range(4):
                if lift >> k & 1:
                    hx, hy = (pb + R @ hip[k])[:2]
                    dx, dy = contact_pt[k, 0] - hx, contact_pt[k, 1] - hy
                    self._r_liftoff[k, 0] = cy * dx + sy * dy
                    self._r_liftoff[k, 1] = -sy * dx + cy * dy
                    self._liftoff_z[k] = contact_pt[k, 2]
        self.leg_state = self._leg_state_arr.tolist()
        return self._support_idx[:ns].tolist()

    def _estimate_ground(self, support):
        """The ground under the trunk: low-pass (0.05 per call) of the mean height of the
        support feet's contact points (kernels.ground_estimate), the reference of the trunk
        height; and the ground plane through where each foot last stood (the support feet's
        contact points, kernels.update_plane), the height expected under a foothold."""
        self._ground = K.ground_estimate(self._ground, self._contact, self._support_idx,
                                         len(support))
        K.update_plane(self._contact, self._support_idx, len(support), self._stood, self._plane)

    def _search_ground(self, x: _Sample, trotting):
        """The trunk's height reference, its ground + height (trot_height while trotting,
        when set); while legs have lost their contact, their targets searching the ground
        below the foothold (trotting) or the hip (standing), and the reference lowered as
        far as a trotting search needs (step_down.py)."""
        p = self.params
        reference = self._ground + (p.trot_height if trotting and p.trot_height else p.height)
        if LOST_CONTACT in self.leg_state:
            hips, R, pb, hip = self._hips, x.R, x.pb, self.model.hip
            for k in range(4):       # pb + R hip_k, summed as the kernels do
                for i in range(3):
                    hips[k, i] = pb[i] + (R[i, 0] * hip[k, 0] + R[i, 1] * hip[k, 1]
                                          + R[i, 2] * hip[k, 2])
            reference = self._search.targets(
                p, trotting, x.t, self.leg_state, self._lost_since, self._foothold,
                self._foothold_z, self._ground, self._contact[:, 2], hips, self._geo, x.cy,
                x.sy, float(pb[2]), reference, self._search_target)
        self._trunk_reference = reference

    # -- 3. support legs -------------------------------------------------------------------
    def _support_leg_torques(self, x: _Sample, trotting, support, gleg, com):
        """Step 3: clears the torques τ and desired forces, then for the support legs the
        VMC wrench b distributed by the QP: τ_k = −J_kᵀ f_k + g_leg,k. Returns b (None
        without support legs)."""
        tau = self._tau
        tau[:] = 0.0
        fdes = self.desired_forces
        fdes[:] = 0.0
        if not support:
            return None
        b = self._vmc_wrench(x, trotting, support)
        self._distribute_wrench(x, support, b, gleg, com)
        return b

    def _vmc_wrench(self, x: _Sample, trotting, support):
        """The virtual model's desired wrench b = [F; M] (heading frame) about the centre of
        mass:
            F = k_p e + k_d (v* − v) + k_ff v* (+ velocity integral when trotting) + m g e_z,
            M = k_p,rot e_R + k_d,rot (ω* − ω) + k_ff,rot ω*,
        e: horizontal offset of the trunk from the centre of the support feet (all feet when
        fewer than 2 (trot) / 3 (stand) support) and height error (to the trunk's height
        reference, _search_ground), clipped; e_R: rotation vector of R_z(ψ*) Rᵀ, clipped.
        While the gait waits for a searching foot, the stand's law with v* = 0 (the velocity
        integral kept for the trot that follows)."""
        p = self.params
        cy, sy = x.cy, x.sy
        # while the gait waits for a foot searching the ground, the trunk waits too: held over
        # its support feet (stand gains, no velocity command), the velocity integral kept
        walking = trotting and not self._search.holding
        kp_t, kd_t, kff_t, kp_r, kd_r, kff_r = \
            self._gains_trot if walking else self._gains_stand
        ns = len(support)
        ref = self._support_idx if ns >= (2 if walking else 3) else self._all_legs
        nr = ns if ns >= (2 if walking else 3) else 4
        b = self._b
        K.vmc_force(ref, nr, self._contact, x.pb, x.vb, cy, sy,
                    self._trunk_reference - x.pb[2], p.max_position_error,
                    self._v_cmd if walking or not trotting else self._no_velocity, kp_t, kd_t,
                    kff_t, bool(walking and p.velocity_ki), p.velocity_ki,
                    p.velocity_integral_max, x.dt,
                    self._f_int if walking or not trotting else self._f_kept, self._mass_g,
                    self._e, self._vh, self._vd, b)
        # orientation error (rotation vector of R_des Rᵀ, world) in the heading frame
        Rd = self._Rd
        cd, sd = math.cos(self._yaw_des), math.sin(self._yaw_des)   # R_des = R_z(ψ*)
        Rd[0, 0], Rd[0, 1], Rd[1, 0], Rd[1, 1] = cd, -sd, sd, cd
        er = pin.log3(Rd @ x.R.T)
        K.vmc_moment(er, x.ww, cy, sy, p.max_orientation_error, self._w_cmd, kp_r, kd_r, kff_r,
                     self._eh, self._wh, self._wd, b)
        return b

    def _distribute_wrench(self, x: _Sample, support, b, gleg, com):
        """The QP (force_distribution.py) in the heading frame: lever arms r_j = p_c,k − com,
        Jacobian rows R_zᵀ J_c,k and gravity torques g_leg,k of the support legs give the
        forces f_j of the ground on the feet; the desired forces (world, self.desired_forces)
        and the stance torques τ_k = −J_c,kᵀ f_k + g_leg,k."""
        ns = len(support)
        idx = self._support_idx
        rh, Jh, gh = self._rh[ns], self._Jh[ns], self._gh[ns]
        K.heading_qp_inputs(idx, ns, self._contact, com, self._Jc, gleg, x.cy, x.sy, rh, Jh, gh)
        fh = self.cfd.solve(rh, b, Jh, gh)
        K.support_torques(idx, ns, fh, x.cy, x.sy, self._Jc, gleg, self.desired_forces,
                          self._tau)

    # -- 4. swing legs ---------------------------------------------------------------------
    def _position_controlled_leg_torques(self, x: _Sample, gleg):
        """Step 4: the legs not in support (swing, lost contact, in the air while standing)
        follow a foot target by analytic IK and joint PD with gravity feed-forward into τ
        (kernels.position_controlled_torques): a swing leg from its lift-off offset to the
        inverted-pendulum foothold (csrc/kernels.c: swing_target), a leg that lost its contact its
        target searching the ground (_search_ground)."""
        m = self.model
        K.position_controlled_torques(
            self._leg_state_arr, self._swing_phase, self._r_liftoff, self._foothold,
            self._swing_parameters(), m.foot_radius, self._ground, self._v_cmd, self._w_cmd,
            x.pb, x.R, x.vb, x.ww, x.cy, x.sy, self._Jf, x.qj, x.dqj, gleg, self._kp3,
            self._kd3, m.hip, self._geo, self._target, self._vtarget, self._tau,
            self._liftoff_z, self._plane, self._foothold_z, self._search_target)

    def _swing_parameters(self):
        """The parameters of kernels.swing_target as one array (layout kernels.SW_*), read
        from self.params on every call (they may be changed)."""
        p = self.params
        key = (p.gait_period, p.duty_factor, p.step_feedback, p.step_max, p.step_interp_end,
               p.swing_height, p.touchdown_depth, self.model.gravity,
               tuple(p.foothold_offset_x))
        P = self._swing_p
        if key != self._swing_key:       # written only when a parameter changed
            P[:K.SW_OFFSET_X] = key[:K.SW_OFFSET_X]
            P[K.SW_OFFSET_X:K.SW_STANCE_X] = p.foothold_offset_x
            self._swing_key = key
        return P

    # -- 5. saturation ---------------------------------------------------------------------
    def _saturate_and_report(self, x: _Sample, support, b, com, t_wall):
        """Step 5: τ clipped to ±effort limit; call_time and info (mode, leg states, support
        legs, contact flags, wrench b, QP status, ground, ψ*, com). Returns a copy of τ."""
        tau = self._tau
        _clip(tau, self._neg_lim, self._lim, out=tau)   # np.clip's ufunc, no wrapper
        ns = len(support)
        self.call_time = time.perf_counter() - t_wall
        self.info = {
            "mode": self.mode,
            "leg_state": [STATE_NAMES[st] for st in self.leg_state],
            "support": support,
            "grounded": x.grounded.tolist(),
            "wrench": None if b is None else b.copy(),
            "qp_status": self.cfd.status if ns else "idle",
            "qp_iterations": self.cfd.iterations if ns else 0,
            "qp_failures": self.cfd.failures,
            "ground": self._ground,
            "ground_plane": self._plane.copy(),
            "yaw_des": self._yaw_des,
            "com": com.copy(),
        }
        return tau.copy()
