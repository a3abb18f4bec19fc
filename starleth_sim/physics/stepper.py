"""Moreau's midpoint time-stepping scheme (Gehring et al. 2014, Eqn. 6-8).

One step over Δt = t^E − t^S:
    q^M = q^S ⊕ ½Δt F(q^S) u^S                                  (6)
    M, h, W evaluated at (q^M, u^S); active set I = {i | g_N,i(q^M) ≤ g_act}
    (g_act = contact.activation_gap, 0 in the presets as in the paper; with
    contact.activation "hysteresis" a contact loaded in the last step stays in I while
    g_N,i(q^M) ≤ contact.opening_gap)
    M (u^E − u^S) − h Δt − W_U Λ_U − W_B Λ_B = 0, (ξ, Λ) ∈ U × B   (7)
    q^E = q^M ⊕ ½Δt F(q^M) u^E                                   (8)
Hard contacts solve (7) with the JOR/SOR prox iterations of :mod:`starleth_sim.physics.prox`;
compliant contacts (Alg. 1) add their forces, evaluated at (q^M, u^S), to h and Λ_U
vanishes. The stepper works for any coordinate set (see :mod:`starleth_sim.physics.coordinates`).

Every step is one call of one C kernel (:mod:`starleth_sim.physics.tree_step`): per
coordinate family one path, tree_step_hard / tree_step_compliant for the minimal
coordinates (a tree: M of q, no bilateral constraint), forest_step for a cut forest (the
extended and maximal coordinates, hard or compliant contacts). Their options (STEP_*) are
the variants of that path: STEP_PREPARE does the torque-independent midpoint ahead (q^M, M,
h without τ, the contact and bilateral kinematics, into the kernel's workspace; `prepare`),
STEP_PREPARED the rest of a step so prepared, STEP_PROFILE adds the time of each Fig. 7
phase (`PHASES`) to the workspace's timings. The joint torques reach the kernel as a mode
(impedance.TORQUE_*): as given, saturated, an impedance command (its law at the state, the
dampers implicit in the tree kernels: M~ = M + Δt K_d, in ``tree_step.c``) or a replay.

Model, state and workspace (see :mod:`starleth_sim.physics.state`): the stepper holds the
model side (coordinate set, ground, `StepSettings`, ε per contact, packed once) and the
kernel's workspace (the arrays at q^M, the factor of M, `StepperStats`); the evolving state,
including the contact memory the kernels read and update (warm start, hysteresis, the
compliant contacts' anchors), lives in the `SimState` passed to `prepare` and `step`. A
failing step leaves the state as it was.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import prox
from .actuator import NonFiniteTorque, saturate_torque
from .config import ConfigError
from .contact import CompliantLaw, GroundPlane
from .impedance import (
    TORQUE_AS_GIVEN,
    TORQUE_IMPEDANCE,
    TORQUE_REPLAY,
    TORQUE_SATURATED,
    command_torques,
)
from .kernels import (
    STEP_COMPLIANT,
    STEP_KEEP_FACTOR,
    STEP_PREPARE,
    STEP_PREPARED,
    STEP_PROFILE,
    TreeStep,
)
from .state import SimState
from .step_kernels import PHASES, PROJECTION_LOOKAHEAD, PROJECTION_TOLERANCE, StepSettings
from .terrain import SECOND_SURFACES, pack_terrain
from .tree_step import (
    TREE_STEP_NONFINITE_IMPULSE,
    TREE_STEP_NONFINITE_STATE,
    TREE_STEP_NONFINITE_TORQUE,
    TREE_STEP_NOT_PD,
    TREE_STEP_OK,
    CutModel,
    TreeStepModel,
    TreeStepResult,
    forest_step,
    report_size,
    report_views,
    tree_step_compliant,
    tree_step_hard,
)

_empty = np.empty


class SimulationError(RuntimeError):
    """The step could not be completed (non-finite solver output or state); the state was
    left unchanged."""


@dataclass
class StepperStats:
    """Counts over the steps, and with profiling the Fig. 7 phases' cumulative times (PHASES
    order) [s]; a caller may replace it by a fresh one to count anew."""

    steps: int = 0
    nonconverged: int = 0
    retried: int = 0
    projections: int = 0        # steps with a post-step projection
    timings: np.ndarray = field(default_factory=lambda: np.zeros(len(PHASES)))


class MoreauStepper:
    """Midpoint time-stepper shared by all coordinate sets and both contact models. It
    holds the model side and a workspace; the state it advances is a `SimState`."""

    def __init__(self, coords, config, profile: bool = False, torque_limits=None,
                 drives=None):
        """torque_limits: (effort, velocity) limits per actuated joint, public order, for
        the torque saturation (actuator.saturate_torque; default: none); drives: the drive
        models (actuator.DriveParameters, the tree kernels only), or None."""
        self.coords = coords
        self.cfg = config
        self.profile = profile
        g = config.ground
        self.ground = GroundPlane(g.height, tuple(g.normal), g.mu,
                                  pack_terrain(config.terrain, g.height, g.mu))
        if coords.second_surfaces != bool(self.ground.terrain[SECOND_SURFACES]):
            raise ValueError("MoreauStepper: a terrain needs coordinates with a second contact "
                             "slot per sphere (make_coordinates(..., second_surfaces=True)), "
                             "the plane alone one slot")
        self.dt = config.dt
        self.hard = config.contact_model == "hard"
        self.nc, self.nv, self.nb = coords.n_contacts, coords.nv, coords.n_bilateral
        self.settings = self._step_settings(config)
        c = config.contact
        self.compliant_law = CompliantLaw(
            mu=float(config.ground.mu), c_N=float(c.stiffness_normal),
            d_N=float(c.damping_normal), c_T=float(c.stiffness_tangential),
            d_T=float(c.damping_tangential), slip_velocity=float(c.slip_velocity))
        self.eps = self._restitution(coords, c)
        self.stats = StepperStats()
        #: the tree kernels step the minimal coordinates (no cut joint, M of q); every other
        #: set is a cut forest (forest_step)
        self._forest = bool(coords.n_cut > 0 or coords.constant_mass_matrix)
        #: joint dampers are implicit where every joint rate is an entry of u (the trees)
        self.implicit_dampers = not self._forest
        na = coords.joint_v.shape[0]
        self._drives(drives, na)
        self._no_force = np.zeros(0)
        #: τ of no torque (one entry per actuated joint), for a step given none
        self._no_torque = np.zeros(na)
        effort, velocity = (np.full(na, np.inf), np.full(na, np.inf)) \
            if torque_limits is None else torque_limits
        self._effort_limit, self._velocity_limit = effort, velocity
        self._pack_model(coords, config)
        self._no_compliant = (np.zeros(0, dtype=np.bool_),) * 2 + (self._no_force,) * 2
        #: tau's length per torque mode of the tree kernels (an impedance command's: checked
        #: by the kernel)
        self._n_tau = {TORQUE_AS_GIVEN: na, TORQUE_SATURATED: na, TORQUE_REPLAY: 2 * na}
        self._unprofiled = self._forest_step if self._forest else \
            self._tree_hard if self.hard else self._tree_compliant
        if self._lagged:
            self._tree_kernel, self._unprofiled = self._unprofiled, self._lagged_step
        self._kernel = self._profiled if profile else self._unprofiled
        self._factored = False      # L holds the factor of a constant M
        self._prepared = None       # the (q, u) of the step prepared ahead (`prepare`)
        self._nq, self._nv = coords.nq, coords.nv
        #: report buffers for `prepare` (the kernel checks their lengths; nothing is written)
        self._spare = (np.empty(report_size(self.nc, na)), np.empty(self.nc, dtype=np.bool_))
        self._bind_tree_step()

    def __reduce__(self):
        """(pickle and copy) Not on its own: its kernels and workspace views are bound to its
        model; a Simulator pickles and copies by making its stepper anew."""
        raise TypeError("MoreauStepper: pickle or copy the Simulator that holds it (a "
                        "stepper is made anew from the configuration, not copied)")

    def _bind_tree_step(self):
        """A tree's step without phase times or a torque lag, bound to its model
        (kernels.TreeStep: `step` and `prepare` below in one C call each, bit for bit), as
        `tree_step`; None for the other steps."""
        self.tree_step = None
        if not self._forest and not self.profile and not self._lagged:
            self.tree_step = TreeStep(self._options, self._tree_model, not self.hard,
                                      self._no_torque, self._no_force, self._spare, self)
            self.step, self.prepare = self.tree_step.step, self.tree_step.prepare

    def _drives(self, drives, na):
        """The drive models' parts the stepper keeps: the joint friction rows (Λ_f's memory
        in SimState.last_bilateral, hard contacts) and whether the torques lag (their state
        SimState.drive_torque: `_lag_state` in, the report's explicit torques out)."""
        if drives is not None and self._forest:
            raise ConfigError("actuator: the drive models (armature, viscous_damping, "
                              "coulomb_friction, torque_bandwidth) need coordinates: minimal")
        self.drives = drives
        self.n_friction = 0 if drives is None or not self.hard else \
            int(np.count_nonzero(drives.coulomb_friction > 0.0))
        self._lagged = drives is not None and bool(np.any(drives.torque_bandwidth > 0.0))
        o = 7 * self.nc + na      # (the report's explicit torques: tree_step.report_views)
        self._explicit = slice(o, o + na)

    def _pack_model(self, coords, config):
        """The kernels' model packed once (TreeStepModel, and a forest's CutModel) and the
        workspace's views: g_N, contact points, W^T, the factor L, u_free, Δu_p, the
        contact.FRAME_STRIDE frames (each contact's (n, t1, t2), μ and surface at q^M, the
        surface being memory) and the phases' timings."""
        pack, views = TreeStepModel.pack(self.settings, self.compliant_law,
                                         coords.midpoint_model(), self.ground, self.eps,
                                         coords.joint_v, coords.tree.dof_parent, self.nv,
                                         self._effort_limit, self._velocity_limit,
                                         coords.joint_q, coords.nq,
                                         None if self.drives is None else
                                         self.drives.packed(config.dt))
        self._tree_model = tuple(pack)
        (self.gap, self.position, self.Wt_all, self.L, self.u_free, self.u_corr,
         self.frames, self._timings, self._lag_state) = views
        self._options = 0
        if self._forest:
            self._cut_model = tuple(CutModel.pack(coords, config.bilateral.stabilization
                                                  / self.dt))
            #: where the kernel writes φ and φ̇ of the cut joints at the end of the step
            self._cut_motion = coords.cut_motion_buffers()
            if not self.hard:
                self._options |= STEP_COMPLIANT
                #: a compliant forest's warm-start memory (never active: stays zero)
                self._no_memory = (np.zeros((self.nc, 3)), np.zeros(self.nc, dtype=np.bool_))

    def _step_settings(self, config) -> StepSettings:
        """The kernels' settings of `config` (StepSettings)."""
        c, s = config.contact, config.solver
        hard = self.hard
        activation_gap = c.activation_gap if hard else 0.0
        hysteresis = hard and c.activation == "hysteresis"
        beta_n = c.penetration_stabilization if hard else 0.0
        beta_velocity = beta_n if c.penetration_correction == "velocity" else 0.0
        beta_projection = beta_n if c.penetration_correction == "projection" else 0.0
        #: contact Jacobians are needed up to the largest gap at which a contact can be
        #: active, or be predicted to end the step below the ground (projection)
        jacobian_gap = max(activation_gap, c.opening_gap if hysteresis else 0.0,
                           PROJECTION_LOOKAHEAD if beta_projection > 0 else 0.0)
        solver = prox.ProxSettings(
            form=int(prox.FORMS[s.form]), scheme=int(prox.SCHEMES[s.scheme]),
            tol_rel=float(s.tol_rel), tol_abs=float(s.tol_abs),
            max_iterations=int(s.max_iterations), criterion=int(prox.CRITERIA[s.criterion]),
            bilateral_direct=config.bilateral.method == "direct",
            alpha=prox.alpha_setting(s.alpha),      # solver.alpha: auto -> prox.ALPHA_AUTO
            stall_window=int(s.stall_window) if s.fallback_alpha_factor > 0 else 0,
            bilateral_relaxation=float(config.bilateral.relaxation)
            if config.bilateral.method == "prox" and s.alpha != "auto" else 0.0)
        return StepSettings(
            prox=solver, activation_gap=float(activation_gap), mu=float(config.ground.mu),
            fallback_alpha_factor=float(s.fallback_alpha_factor),
            fallback_hold=int(s.fallback_hold) if s.fallback_alpha_factor > 0 else 0,
            opening_gap=float(c.opening_gap), dt=float(config.dt),
            beta_velocity=float(beta_velocity), beta_projection=float(beta_projection),
            jacobian_gap=float(jacobian_gap),
            projection_tolerance=float(PROJECTION_TOLERANCE), warm_start=bool(s.warm_start),
            hysteresis=bool(hysteresis))

    @staticmethod
    def _restitution(coords, c):
        """Newton-type impact law per contact: (ε_N, ε_T), defaults overridden by name."""
        eps = np.tile([c.restitution_normal, c.restitution_tangential], (coords.n_contacts, 1))
        names = np.array(coords.contact_names)
        for name, (en, et) in c.restitution_overrides.items():
            if name not in names:
                raise ConfigError(f"contact.restitution_overrides: unknown contact '{name}' "
                                  f"(contacts: {', '.join(dict.fromkeys(names))})")
            eps[names == name] = (en, et)      # (both slots of a sphere on a terrain)
        return eps

    def initial_state(self, q, u, t: float = 0.0) -> SimState:
        """The state (q, u, t) without contact memory or pending wrenches (the drives'
        lagged torques zero)."""
        state = SimState.initial(q, u, t, self.nc, self.nb + self.n_friction, self.hard)
        if self._lagged:
            state.drive_torque = np.zeros(self._no_torque.shape[0])
        return state

    # -- one step -------------------------------------------------------------------------
    def prepare(self, state: SimState):
        """The part of the step from (q^S, u^S) = (state.q, state.u) that does not depend on
        the joint torques or external forces, done now (the kernel with STEP_PREPARE: q^M,
        M and h without τ, the contact and bilateral kinematics at q^M). `step` uses it when
        called with a state holding the same q and u objects (which must not be modified in
        place in between); the result is the same bit for bit either way. A lockstep node
        calls this after publishing a state, while the controller works on its answer."""
        self._prepared = None
        self._kernel(self._options | STEP_PREPARE, TORQUE_AS_GIVEN, state, self._no_torque,
                     self._no_force, *self._spare, _empty(state.q.shape[0]),
                     _empty(state.u.shape[0]))
        self._prepared = (state.q, state.u)

    def step(self, state: SimState, tau, report, is_active, f_ext=None,
             mode=TORQUE_SATURATED) -> TreeStepResult:
        """Advance state by Δt in one kernel call: state.q and state.u become q^E and u^E,
        and the contact memory is updated (state.t is the caller's). tau: the joint torques
        (float64, public joint order; None: none) for mode TORQUE_SATURATED (saturated by
        the torque limits, actuator.saturate_torque) or TORQUE_AS_GIVEN; an impedance
        command's packed buffer for TORQUE_IMPEDANCE (the law at the state, saturated, its
        dampers implicit where `implicit_dampers`); the explicit torques then the dampers'
        kd for TORQUE_REPLAY. f_ext: a generalized external force, or None. Writes the
        report buffer (tree_step.report_views: Λ, g_N and contact points at q^M, the
        applied and explicit torques, the dampers) and the active flags; returns the
        kernel's TreeStepResult. A NonFiniteTorque or SimulationError leaves the state as it
        was."""
        q, u = state.q, state.u
        options = self._options
        if self._prepared is not None:
            p, self._prepared = self._prepared, None
            if p[0] is q and p[1] is u:
                options |= STEP_PREPARED
        if tau is None or tau.shape[0] == 0:
            tau, mode = self._no_torque, TORQUE_AS_GIVEN
        if self._forest:
            tau, mode = self._forest_torques(tau, q, u, mode), TORQUE_AS_GIVEN
        elif mode != TORQUE_IMPEDANCE and tau.shape[0] != self._n_tau[mode]:
            raise ValueError(f"tau must have {self._n_tau[mode]} entries, got {tau.shape[0]}")
        qE, uE = _empty(self._nq), _empty(self._nv)
        r = self._kernel(options, mode, state, tau, self._no_force if f_ext is None else f_ext,
                         report, is_active, qE, uE)
        if r.outcome or r.retried or r.status or r.projection_status >= 0 or \
                not self._factored:
            self._count(r)
        self.stats.steps += 1
        state.q, state.u = qE, uE
        if self._forest:
            self.coords.cut_motion_written(qE, uE)
        return r

    def _tree_hard(self, options, mode, state, tau, f_ext, report, is_active, qE, uE):
        """tree_step_hard of `state`."""
        return tree_step_hard(options, mode, (state.q, state.u, state.last_impulse,
                                              state.last_active, state.last_bilateral,
                                              state.prox_memory),
                              tau, f_ext, (report, is_active, qE, uE), self._tree_model)

    def _tree_compliant(self, options, mode, state, tau, f_ext, report, is_active, qE, uE):
        """tree_step_compliant of `state`."""
        return tree_step_compliant(options, mode, (state.q, state.u, state.closed, state.slip,
                                                   state.anchor, state.lam_compliant),
                                   tau, f_ext, (report, is_active, qE, uE), self._tree_model)

    def _forest_step(self, options, _mode, state, tau, f_ext, report, is_active, qE, uE):
        """forest_step of `state` (tau: the applied torques; mode is not read)."""
        if self._factored and self.coords.constant_mass_matrix:
            options |= STEP_KEEP_FACTOR     # (L holds the factor of a constant M)
        if self.hard:
            memory = (state.last_impulse, state.last_active)
            compliant = self._no_compliant
        else:
            memory = self._no_memory
            compliant = (state.closed, state.slip, state.anchor, state.lam_compliant)
        return forest_step(options, (state.q, state.u, *memory, state.last_bilateral,
                                     state.prox_memory, *compliant), tau, f_ext,
                           (report, is_active, qE, uE, *self._cut_motion), self._tree_model,
                           self._cut_model)

    def _lagged_step(self, options, mode, state, tau, f_ext, report, is_active, qE, uE):
        """The tree kernel with a torque lag: its state (SimState.drive_torque) copied into
        the workspace's lag_state before, and the lag's output (the report's explicit
        torques) back after a successful step."""
        if not options & STEP_PREPARE:
            self._lag_state[:] = state.drive_torque
        r = self._tree_kernel(options, mode, state, tau, f_ext, report, is_active, qE, uE)
        if r.outcome == TREE_STEP_OK and not options & STEP_PREPARE:
            state.drive_torque[:] = report[self._explicit]
        return r

    def _profiled(self, options, *args):
        """The kernel with STEP_PROFILE, its phase times moved into stats.timings (the stats
        may be replaced: see StepperStats)."""
        r = self._unprofiled(options | STEP_PROFILE, *args)
        self.stats.timings += self._timings
        self._timings[:] = 0.0
        return r

    def _forest_torques(self, tau, q, u, mode):
        """The applied torques of a cut forest's step (its dampers stay explicit): the law of
        an impedance command, or tau, saturated at the joint rates of the cut-joint
        kinematics (mode TORQUE_IMPEDANCE / TORQUE_SATURATED), the explicit half of a
        replay, or tau as given."""
        na = self._no_torque.shape[0]
        if mode == TORQUE_IMPEDANCE:
            return self.torques_of_command(tau, q, u)
        if mode == TORQUE_REPLAY:
            if tau.shape[0] != 2 * na:
                raise ValueError(f"a replay needs {2 * na} entries, got {tau.shape[0]}")
            if np.any(tau[na:] != 0.0):
                raise ValueError("a cut forest has no implicit dampers to replay")
            return np.ascontiguousarray(tau[:na])
        if tau.shape[0] != na:
            raise ValueError(f"tau must have {na} entries, got {tau.shape[0]}")
        if mode == TORQUE_AS_GIVEN:
            return tau
        applied = np.empty(na)
        if not saturate_torque(tau, self._effort_limit, self.coords.joint_velocities(q, u),
                               self._velocity_limit, applied):
            raise NonFiniteTorque("tau has non-finite entries")
        return applied

    def _count(self, r):
        """The stats of a kernel's result that did more than converge (and the first's);
        NonFiniteTorque or SimulationError on a failed step (the kernel left the state as
        it was)."""
        outcome = r.outcome
        if outcome == TREE_STEP_NONFINITE_TORQUE:
            raise NonFiniteTorque("tau has non-finite entries")
        if outcome == TREE_STEP_NOT_PD:
            raise SimulationError("mass matrix (or G_B) not positive definite "
                                  "(non-finite state?)")
        self._factored = True
        st = self.stats
        st.retried += bool(r.retried)
        st.nonconverged += r.status != prox.STATUS_CONVERGED
        st.projections += r.projection_status >= 0
        if outcome == TREE_STEP_NONFINITE_IMPULSE:
            raise SimulationError("prox iteration produced non-finite impulses; "
                                  "state left unchanged")
        if outcome == TREE_STEP_NONFINITE_STATE:
            raise SimulationError("non-finite state after the step; state left unchanged")

    def torques_of_command(self, tau, q, u):
        """The applied torques of an impedance command at (q, u) of a cut forest
        (impedance.command_torques with this stepper's limits; its dampers explicit)."""
        return command_torques(tau, q, u, self.coords, self._effort_limit,
                               self._velocity_limit)


__all__ = ["MoreauStepper", "SimulationError", "StepperStats", "PHASES", "report_views"]
