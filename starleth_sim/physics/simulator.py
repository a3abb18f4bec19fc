"""The public headless API: ``Simulator`` (no ROS anywhere in here).

    from starleth_sim import Simulator
    sim = Simulator.from_preset("HmJ")           # or "Cm", "HmS", a YAML path; **overrides
    sim = Simulator.from_preset("HmJ", robot="go1")   # a robot of the library (robots/)
    sim.reset()                                   # standing on the ground
    sim.step(tau)                                 # one control period (1/400 s), n torques
    sim.step(ImpedanceCommand.create(sim.joint_names, position=q_star, kp=80.0, kd=2.0))
    sim.q, sim.u, sim.t, sim.contacts, sim.diagnostics
    snap = sim.snapshot(); ...; sim.restore(snap) # back to a saved state

The evolving state is one `SimState` (``sim.state``: q, u, t, the contact memory, the timed
wrenches); the model and settings (description, config, persistent wrenches) and the
workspace (the stepper's arrays, the reports of the last step) are not part of it, see
:mod:`starleth_sim.physics.state`.

Torques are in the public joint order (the URDF's document order of its moving joints,
StarlETH's LF/RF/LH/RH x HAA/HFE/KFE: ``sim.joint_names``) and saturated at the
URDF effort limits; beyond the URDF velocity limit v a torque that drives its joint faster
is derated linearly to zero at 2v (the torque actually applied is ``applied_torque``). A
joint impedance command (:mod:`starleth_sim.physics.impedance`) is evaluated at every
physics step, its damper implicit (``applied_torques_per_step``; ``step_applied`` of
``replay_torques_per_step`` replays a step bit for bit). Contact impulses are reported in
the world frame, summed over the physics steps of the control period; forces are impulse /
control period (F = Λ/Δt with one step per control update, as in the paper's Fig. 5).
"""
from __future__ import annotations

import logging
from time import perf_counter

import numpy as np

from .actuator import NonFiniteTorque, drive_parameters, real_array
from .config import PhysicsConfig, load_preset
from .contact import CONTACT_STATES, ContactInfo, SphereSlots, contact_states, rest_on_ground
from .coordinates import make_coordinates
from .description import RobotDescription
from .diagnostics import NO_TIMINGS, NO_TOTALS, Diagnostics, StepWarnings
from .impedance import (
    TORQUE_AS_GIVEN,
    TORQUE_IMPEDANCE,
    TORQUE_REPLAY,
    TORQUE_SATURATED,
    ImpedanceCommand,
    replay_rows,
)
from .kernels import ControlPeriod
from .robot_build import config_with_robot, robot_description
from .state import SimState, finite_time
from .stepper import PHASES, MoreauStepper, SimulationError
from .tree_step import report_size, report_views
from .wrenches import MAX_TIMED_WRENCHES, ExternalWrenches

log = logging.getLogger("starleth_sim")


#: float64 (numpy's built-in dtypes are singletons: `is` is the cheap test)
_FLOAT64 = np.dtype(np.float64)


class Simulator:
    """One simulated robot (or body) on a ground plane."""

    REST_OVERLAP = 1e-9  # [m]

    def __init__(self, config: PhysicsConfig, description: RobotDescription | None = None,
                 profile: bool = False):
        self.config = config
        if description is None:
            description = robot_description(config.robot)
        self.description = description
        self.coords = make_coordinates(config.coordinates, description,
                                       second_surfaces=not config.terrain.is_flat)
        #: the reports per contact sphere (on a terrain a sphere has two contact slots)
        self._spheres = SphereSlots(self.coords.n_contact_spheres, self.coords.n_contacts)
        self._root_q0 = int(self.coords.root_q[0])     # root_position
        self.joint_names = tuple(description.joint_names)
        self.n_joints = len(self.joint_names)
        lim = np.array(description.effort_limit, dtype=float).reshape(-1)
        self._effort_limit = lim if lim.shape == (self.n_joints,) else \
            np.full(self.n_joints, np.inf)     # the description gives no limits
        vlim = np.array(description.velocity_limit, dtype=float).reshape(-1)
        if vlim.shape != (self.n_joints,):
            vlim = np.full(self.n_joints, np.inf)
        #: joint velocity limits (URDF <limit velocity>; none where not positive and finite)
        self._velocity_limit = np.where(np.isfinite(vlim) & (vlim > 0), vlim, np.inf)
        if config.actuator.velocity_limit == "ignore":
            self._velocity_limit[:] = np.inf
        self.stepper = MoreauStepper(self.coords, config, profile=profile,
                                     torque_limits=(self._effort_limit, self._velocity_limit),
                                     drives=drive_parameters(config.actuator, self.joint_names))
        #: the reports of the one-kernel steps of a control period are written into one of
        #: two sets of report buffers (one buffer per physics step, tree_step.report_views),
        #: the other set holding the last period's: nothing allocated per step, and a failed
        #: step leaves the reports as they were
        nc = self.coords.n_contacts
        self._report_buffers = tuple(
            [(b, np.empty(nc, dtype=np.bool_), report_views(b, nc, self.n_joints))
             for b in (np.zeros(report_size(nc, self.n_joints))
                       for _ in range(config.steps_per_control))]
            for _ in "ab")
        #: joint angles and rates are q's and u's entries (no cut joints): one gather each,
        #: nothing to cache
        self._joint_rates_in_u = getattr(self.coords, "n_cut", 1) == 0
        self._joint_q, self._joint_v = self.coords.joint_q, self.coords.joint_v
        #: φ̇ of the state whose u is the first (a step, reset and restore give u anew)
        self._joint_velocity_cache = (None, None)
        self.contact_names = tuple(description.contact_names())
        self.control_period = config.control_period
        #: the persistent wrenches: an input like the torques (not evolving state)
        self._wrenches = ExternalWrenches(self.coords)
        self.state: SimState | None = None
        self._log_step = StepWarnings(log, config.contact.activation)
        #: what the last control period left (the report set in use, Λ, the command, the
        #: cumulative counts, the Diagnostics), and a period of one physics step of a tree
        #: without wrenches in one C call (kernels.ControlPeriod; _control_period: the rest)
        one_kernel = config.steps_per_control == 1 and not profile
        self._period = ControlPeriod(self._report_buffers, self.control_period, self.n_joints,
                                     self.stepper.tree_step if one_kernel else None,
                                     self._wrenches.persistent, Diagnostics, NO_TIMINGS,
                                     self._log_step)
        self.reset()

    # -- construction ---------------------------------------------------------------------
    @classmethod
    def from_preset(cls, name: str = "HmJ", description: RobotDescription | None = None,
                    profile: bool = False, robot: str | None = None,
                    **overrides) -> "Simulator":
        """A simulator of a preset (a name or a YAML path) for `robot` (a library name, a
        spec or URDF path; default: the preset's), with the robot spec's physics overrides,
        then `overrides` (flat or dotted field names)."""
        cfg = load_preset(name)
        if robot is not None:
            cfg = config_with_robot(cfg, robot)
        if overrides:
            cfg = cfg.with_overrides(**overrides)
        return cls(cfg, description=description, profile=profile)

    # -- state ----------------------------------------------------------------------------
    def default_state(self):
        """A robot with legs and a standing height: the standing posture (hip rolls at 0,
        each foot below its hip pitch joint at the standing height:
        starleth_interface/robot/legs.py), feet on the ground. Any other body: the neutral
        configuration resting with its lowest contact point on the ground.
        Resting means a 1 nm overlap (g_N = −1e-9 m at q), so that round-off cannot leave a
        touching contact open: a hard contact enters the active set when g_N(q^M) ≤
        contact.activation_gap (0 in the presets; with contact.activation "hysteresis" a
        contact loaded in the last step stays in it while g_N(q^M) ≤ contact.opening_gap,
        but a new one must reach activation_gap), and a compliant contact closes when
        g_N(q^M) ≤ 0."""
        c = self.coords
        d = self.description
        if d.standing_height is not None and d.legs:
            q = c.make_state([0.0, 0.0, d.standing_height], [0, 0, 0, 1], d.standing_joints())
        else:   # (the minimal neutral configuration: a cut forest's bodies where they belong)
            q = c.make_state([0.0, 0.0, 0.0], [0, 0, 0, 1])
        if c.n_contacts:
            rest_on_ground(c, self.stepper.ground, q, self.REST_OVERLAP)
        return q

    def reset(self, q=None, u=None, t: float = 0.0, minimal: bool = False):
        """Set the state (default: `default_state()` at rest). With minimal=True, q and u are
        given in minimal coordinates (19/18 for StarlETH) and converted to this simulator's
        coordinate set."""
        t = finite_time(t, "reset: t")
        if minimal:
            if q is None:
                raise ValueError("reset(minimal=True) needs q")
            q_min = real_array(q, "reset: q")
            u_min = np.zeros(self.description.model.nv) if u is None else \
                real_array(u, "reset: u")
            if q_min.shape != (self.description.model.nq,) or \
                    u_min.shape != (self.description.model.nv,):
                raise ValueError("reset(minimal=True): q and u must be minimal coordinates")
            q, u = self.coords.from_minimal(q_min, u_min)
        q = self.default_state() if q is None else real_array(q, "reset: q").copy()
        u = np.zeros(self.coords.nv) if u is None else real_array(u, "reset: u").copy()
        if q.shape != (self.coords.nq,) or u.shape != (self.coords.nv,):
            raise ValueError(f"reset: q must have {self.coords.nq} and u {self.coords.nv} "
                             f"entries, got {q.shape} and {u.shape}")
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(u))):
            raise ValueError("reset: q and u must be finite")
        for iq in self.coords.root_q:
            q[iq + 3:iq + 7] /= np.linalg.norm(q[iq + 3:iq + 7])
        self.state = self.stepper.initial_state(q, u, t)
        self.stepper.frames[:, 10] = 0.0     # (no slot holds a surface yet)
        p = self._period        # (the reports of the last period: zero before the first)
        for report, active, _ in p.current:
            report[:] = 0.0
            active[:] = False
        p.impulse, p.command = p.current[0][2][0], None
        p.diagnostics, p.totals = Diagnostics(), NO_TOTALS

    def snapshot(self) -> SimState:
        """A copy of the current state (q, u, t, contact memory, timed wrenches), for
        `restore`. The persistent wrenches are settings, not state: a snapshot keeps none."""
        s = self.state.copy()
        if self.coords.second_surfaces:
            s.surfaces = self.stepper.frames[:, 10].copy()
        return s

    def restore(self, snapshot: SimState):
        """Continue from a state taken by `snapshot` (which stays usable: the simulator
        takes a copy). The reports of the last step (contacts, diagnostics,
        applied_torque) stay those of the last step taken."""
        memory = snapshot.last_impulse if self.stepper.hard else snapshot.anchor
        if snapshot.q.shape != (self.coords.nq,) or snapshot.u.shape != (self.coords.nv,) \
                or memory is None or memory.shape != (self.coords.n_contacts, 3):
            raise ValueError("restore: the snapshot is not a state of this simulator")
        self.state = snapshot.copy()
        if self.coords.second_surfaces:
            self.stepper.frames[:, 10] = 0.0 if snapshot.surfaces is None else snapshot.surfaces

    def __reduce__(self):
        """(pickle and copy.deepcopy) A simulator made anew from its configuration and
        description, then given this one's state, wrenches, last reports and record (the
        stepper's and the period's C objects and the views into their buffers are made by
        the constructor, not copied)."""
        p = self._period
        reports = [(report.copy(), active.copy()) for report, active, _ in p.current]
        record = (reports, np.array(p.impulse), p.command, p.diagnostics, p.totals,
                  self.stepper.stats)
        return (_unpickled_simulator, (self.config, self.description, self.stepper.profile,
                                       self.snapshot(), dict(self._wrenches.persistent),
                                       record))

    def _restore_period(self, record):
        """The last period's reports and record (`__reduce__`'s) taken over."""
        reports, impulse, command, diagnostics, totals, stats = record
        p = self._period
        for (report, active, _), (r, a) in zip(p.current, reports, strict=True):
            report[:] = r
            active[:] = a
        p.impulse, p.command, p.diagnostics, p.totals = impulse, command, diagnostics, totals
        self.stepper.stats = stats

    @property
    def diagnostics(self) -> Diagnostics:
        """The solver figures of the last control step (what `step` returned)."""
        return self._period.diagnostics

    @property
    def _reports(self):
        """The report buffers of the last control step (one per physics step)."""
        return self._period.current

    @property
    def _impulse(self):
        """Λ of the last control step (nc x 3, contact frames), summed over its steps."""
        return self._period.impulse

    @property
    def q(self):
        return self.state.q.copy()

    @property
    def u(self):
        return self.state.u.copy()

    @property
    def t(self) -> float:
        return self.state.t

    @property
    def dt(self) -> float:
        return self.stepper.dt

    @property
    def applied_torque(self):
        """The saturated torques applied during the last control step (of an impedance
        command, those of the period's first physics step; all in applied_torques_per_step;
        with a torque bandwidth the lag's output: doc/drives.md)."""
        return self._reports[0][2][3].copy()

    @property
    def applied_torques_per_step(self):
        """The saturated torques applied at each physics step of the last control step,
        (steps_per_control x n_joints; with torques, every row is applied_torque; an
        implicit damper's at the step's end rates: replay_torques_per_step replays them)."""
        return np.array([v[3] for _, _, v in self._reports])

    @property
    def replay_torques_per_step(self):
        """What `step_applied` takes to replay the last control step bit for bit with the
        implicit dampers (steps_per_control x 2 n_joints): per physics step the explicit
        torques (a damped joint's: its law at the start state), then the dampers' kd."""
        return np.array([np.concatenate((v[4], v[5])) for _, _, v in self._reports])

    @property
    def last_command(self):
        """The command of the last control step as validated: an ImpedanceCommand, the
        joint torques (a copy), or the per-step torques of step_applied; None after reset."""
        c = self._period.command
        return c if c is None or isinstance(c, ImpedanceCommand) else c.copy()

    def joint_positions(self):
        if self._joint_rates_in_u:     # (one gather: a controller asks at every step)
            return self.state.q[self._joint_q]
        return self.coords.joint_positions(self.state.q, self.state.u)

    def joint_velocities(self):
        if self._joint_rates_in_u:
            return self.state.u[self._joint_v]
        return self._joint_velocities().copy()

    def _joint_velocities(self):
        """φ̇ of the current state (computed once per state: the maximal coordinates recover
        it from the bodies' velocities, and both a controller and the torque saturation of
        the next step ask for it)."""
        u, qd = self._joint_velocity_cache
        if u is not self.state.u:
            u = self.state.u
            qd = self.coords.joint_velocities(self.state.q, u)
            self._joint_velocity_cache = (u, qd)
        return qd

    def bilateral_violation(self):
        """g_B at the current state: the position-level violation of the bilateral
        constraints (empty for the minimal coordinates) [m, and rad for the 2 angle rows]."""
        if not self.coords.n_bilateral:
            return np.zeros(0)
        return self.coords.bilateral(self.state.q)[1].copy()

    def base_state(self):
        """dict: position, orientation (x, y, z, w), linear_velocity (world),
        angular_velocity (base frame)."""
        p, quat, v, w = self.coords.base_state(self.state.q, self.state.u)
        return {"position": p, "orientation_xyzw": quat, "linear_velocity": v,
                "angular_velocity": w}

    def root_position(self):
        """(x, y, z) of the first floating body's frame in the world [m] (the trunk: its
        origin in minimal coordinates, its centre of mass in the maximal ones), read
        straight from q: a cheap look at where the base is, e.g. to check how far a step
        moved it (base_state gives the trunk frame itself)."""
        iq = self._root_q0
        q = self.state.q
        return q[iq], q[iq + 1], q[iq + 2]

    def gaps(self):
        """g_N of every contact point at the current configuration q (on a terrain: to its
        nearest surface, the smallest of its gaps)."""
        c = self.coords
        gap = np.zeros(c.n_contacts)
        c.contact_kinematics(self.state.q, self.stepper.ground, gap, np.zeros((c.n_contacts, 3)),
                             np.zeros((c.n_contacts, 3, c.nv)))
        return self._spheres.gaps(gap)

    def contact_impulses(self) -> np.ndarray:
        """Λ of every contact point (order of contact_names) in the world frame, summed over
        the last control period (nc x 3) [N s]. On a terrain each contact's impulse is turned
        by the frame of its surface at the last physics step (with several physics steps
        per control period, their impulses are summed in that frame; a sphere's two
        surfaces' impulses are summed in the world frame)."""
        ground = self.stepper.ground
        if ground.flat:
            return self._impulse @ ground.frame     # frame rows: n, t1, t2
        frames = self.stepper.frames[:, :9].reshape(-1, 3, 3)
        return self._spheres.sums(np.einsum("ik,ikj->ij", self._impulse, frames))

    def contact_forces(self) -> np.ndarray:
        """F = Λ/Δt of every contact point in the world frame over the last control period
        (nc x 3) [N]: the forces of `contacts` as one array, without building the records
        (a ROS node reads them every step)."""
        return self.contact_impulses() / self.control_period

    def contact_normal_forces(self) -> np.ndarray:
        """F_N = Λ_N/T of every contact point over the last control period (nc) [N]: the
        normal impulse along its surface's normal (a sphere's two surfaces' summed)."""
        return self._spheres.sums(self._impulse[:, 0]) / self.control_period

    @property
    def contacts(self):
        world = self.contact_impulses()
        sp = self._spheres
        _, is_active, (_, g, p, *_) = self._reports[-1]
        pos, gap = sp.points(g, p), sp.gaps(g)
        states, active = self.contact_states(), sp.active(is_active)
        return [ContactInfo(n, bool(active[i]), float(gap[i]), world[i].copy(),
                            world[i] / self.control_period, pos[i].copy(),
                            CONTACT_STATES[states[i]])
                for i, n in enumerate(self.contact_names)]

    def contact_points(self) -> np.ndarray:
        """The contact points (nc x 3, world) of the last control step: the positions of
        `contacts`, without building the records."""
        _, _, (_, g, p, *_) = self._reports[-1]
        return self._spheres.points(g, p).copy()

    def contact_states(self) -> np.ndarray:
        """Per contact point after the last control step, an index into CONTACT_STATES:
        0 open (no normal impulse), 1 stick, 2 slip. Hard contacts: slip when the tangential
        impulse is on the boundary of the friction cone, |Λ_T| ≥ (1 − 1e-6) μ Λ_N; compliant
        contacts: the slip flag of Alg. 1."""
        ground = self.stepper.ground
        return self._spheres.states(
            contact_states(self._impulse, self.stepper.hard,
                           ground.mu if ground.flat else self.stepper.frames[:, 9],
                           self.state.slip), self._impulse)

    def contact(self, name: str) -> ContactInfo:
        try:
            i = self.contact_names.index(name)
        except ValueError:
            raise KeyError(f"unknown contact '{name}'") from None
        return self.contacts[i]

    # -- external wrenches ----------------------------------------------------------------
    def apply_wrench(self, link: str, force, torque=(0.0, 0.0, 0.0), duration: float | None = None):
        """Apply a wrench (world axes, at the origin of `link`) for `duration` seconds
        (default: one control period) starting with the next step."""
        f, m = self._wrenches.checked(link, force, torque)
        duration = self.control_period if duration is None else float(duration)
        if not (duration > 0 and np.isfinite(duration)):
            raise ValueError("duration must be positive")
        pending = self.state.pending_wrenches
        if len(pending) >= MAX_TIMED_WRENCHES:
            raise ValueError(f"apply_wrench: {len(pending)} timed wrenches are pending, the "
                             f"most (MAX_TIMED_WRENCHES {MAX_TIMED_WRENCHES}): each acts in "
                             "every physics step until it ends")
        pending.append([link, f, m, duration])

    def set_persistent_wrench(self, link: str, force, torque=(0.0, 0.0, 0.0)):
        """Apply a wrench on `link` at every step until cleared (a zero wrench clears it)."""
        self._wrenches.set_persistent(link, force, torque)

    def clear_wrenches(self):
        self._wrenches.persistent.clear()
        self.state.pending_wrenches.clear()

    # -- stepping -------------------------------------------------------------------------
    def _torque_array(self, tau):
        """tau as a float64 vector of n_joints entries (zeros for None); a ValueError names
        the joint order if its length is wrong."""
        if tau is None:
            return np.zeros(self.n_joints)
        # (the kernels are compiled for contiguous float64 vectors: anything else is
        # copied into one, rather than compiled for again)
        a = tau if type(tau) is np.ndarray and tau.dtype is _FLOAT64 and tau.ndim == 1 \
            and tau.flags.c_contiguous else real_array(tau, "tau")
        if a.shape[0] != self.n_joints:
            raise ValueError(f"tau must have {self.n_joints} entries (joint order "
                             f"{', '.join(self.joint_names)}), got {a.shape[0]}")
        return a

    def _non_finite_torque(self, a) -> ValueError:
        """The error of a torque vector with non-finite entries, naming their joints."""
        n = self.n_joints       # (a: a vector, or rows of a replay: n or 2 n per step)
        bad = dict.fromkeys(self.joint_names[i % n] for i in np.flatnonzero(~np.isfinite(a)))
        return ValueError(f"tau has non-finite entries for {', '.join(bad)}")

    def prepare(self):
        """Do now the part of the next step that does not depend on the torques (q^M, M, h,
        the contact and bilateral kinematics; see MoreauStepper.prepare), e.g. while a
        controller computes its answer to the current state: the next `step` then only does
        the rest. Optional, and the next step gives the same result with or without it."""
        self.stepper.prepare(self.state)

    def step(self, tau=None):
        """Advance one control period with joint torques `tau` (zero-order hold), or with
        an ImpedanceCommand (its law evaluated at every physics step, see
        :mod:`starleth_sim.physics.impedance`). On a bad `tau` (wrong length, NaN/inf) a
        ValueError is raised and the state is unchanged; on a SimulationError the state is
        restored to what it was before the step."""
        try:        # the usual case first: a float64 vector, one kernel call (ControlPeriod)
            d = self._period.step(self.state, tau)
        except NonFiniteTorque:
            raise self._non_finite_torque(tau) from None
        if d is not NotImplemented:
            return d
        if type(tau) is ImpedanceCommand:      # (cheaper than isinstance, on every step)
            if tau.joint_names != self.joint_names:
                raise ValueError("ImpedanceCommand: made for the joints "
                                 f"{', '.join(tau.joint_names)}, not {', '.join(self.joint_names)}")
            return self._control_period(tau.packed, tau, TORQUE_IMPEDANCE)
        a = self._torque_array(tau)
        return self._control_period(a, a.copy(), TORQUE_SATURATED)

    def _timings(self):
        """Diagnostics.timings: the cumulative phase times when profiling."""
        if not self.stepper.profile:
            return NO_TIMINGS
        return dict(zip(PHASES, self.stepper.stats.timings.tolist(), strict=True))

    def step_applied(self, torques):
        """Advance one control period applying recorded torques at its physics steps as
        given (NOT saturated again: a derated torque would be derated twice):
        replay_torques_per_step (explicit torques, then the implicit dampers' kd), which
        replays the step bit for bit from the same state, or torques (steps_per_control x
        n_joints, or n_joints for every step). ValueError on a wrong shape or value."""
        a = replay_rows(torques, self.config.steps_per_control, self.joint_names,
                        self.stepper.implicit_dampers)
        return self._control_period(a, a, TORQUE_REPLAY if a.shape[1] > self.n_joints
                                    else TORQUE_AS_GIVEN)

    def _control_period(self, torques, command, mode):
        """The physics steps of a control period, each one MoreauStepper.step (one kernel
        call) with the torques of `mode`: tau saturated once, at the period's start state
        (TORQUE_SATURATED; the later steps apply the first one's torques as given), an
        impedance command's law at each step's start state (TORQUE_IMPEDANCE), or rows,
        torques[i] at step i (TORQUE_AS_GIVEN, TORQUE_REPLAY); the wrenches' generalized
        force at each. The reports are written into the spare set of report buffers, which
        then becomes the current one. A failed step leaves the state as it was."""
        try:
            d = self._period.step(self.state, torques, mode, command)   # one kernel call
        except NonFiniteTorque:
            raise self._torque_error(mode, torques) from None
        if d is not NotImplemented:
            return d
        t_wall = perf_counter()
        figures, impulse = self._physics_steps(
            self.state, torques, self._report_buffers[self._period.next_report], mode)
        # t, the record of the period and the log, as ControlPeriod.step writes them
        return self._period.finish(self.state, figures, impulse, command,
                                   perf_counter() - t_wall, self._timings())

    def _physics_steps(self, state, torques, buffers, mode):
        """The physics steps of a control period (_control_period), the state restored from
        a copy taken before when one fails: (their TreeStepResults, Λ summed over them)."""
        stepper = self.stepper
        wrenches = self._wrenches
        force = None if wrenches.none_to_apply(state) else wrenches.generalized_force
        # (a failing kernel leaves the state as it was: one step without wrenches needs no copy)
        before = None if len(buffers) == 1 and force is None else state.copy(share_qu=True)
        try:
            figures = []
            for report, active, views in buffers:
                tau = torques if torques.ndim == 1 else torques[len(figures)]
                figures.append(stepper.step(state, tau, report, active, None if force is None
                                            else force(state, stepper.dt), mode))
                if mode == TORQUE_SATURATED and not stepper.drives:
                    torques, mode = views[3], TORQUE_AS_GIVEN   # (saturated once per period;
                    # with drives at every step: a lag's torques are not the command's)
        except NonFiniteTorque:
            if before is not None:
                self.restore(before)
            raise self._torque_error(mode, torques) from None
        except SimulationError:
            if before is not None:
                self.restore(before)
            raise
        impulse = buffers[0][2][0]
        for _, _, views in buffers[1:]:     # in step order (the sum's round-off)
            impulse = impulse + views[0]
        return figures, impulse

    def _torque_error(self, mode, torques) -> ValueError:
        """The error of a step given non-finite torques (or whose impedance law gave them)."""
        if mode == TORQUE_IMPEDANCE:
            return ValueError("the impedance law gave non-finite torques")
        return self._non_finite_torque(torques)


def _unpickled_simulator(config, description, profile, snapshot, persistent, record):
    """A Simulator from what `Simulator.__reduce__` keeps."""
    sim = Simulator(config, description, profile)
    sim.restore(snapshot)
    sim._wrenches.persistent.update(persistent)
    sim._restore_period(record)
    return sim
