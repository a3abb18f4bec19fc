"""Moreau's midpoint time-stepping scheme (Gehring et al. 2014, Eqn. 6-8).

One step over Δt = t^E − t^S:
    q^M = q^S ⊕ ½Δt F(q^S) u^S                                  (6)
    M, h, W evaluated at (q^M, u^S); active set I = {i | g_N,i(q^M) ≤ g_act}
    (g_act = contact.activation_gap, 0 in the presets as in the paper; with
    contact.activation "hysteresis" a contact loaded in the last step stays in I while
    g_N,i(q^M) ≤ contact.opening_gap, see `active_set`)
    M (u^E − u^S) − h Δt − W_U Λ_U − W_B Λ_B = 0, (ξ, Λ) ∈ U × B   (7)
    q^E = q^M ⊕ ½Δt F(q^M) u^E                                   (8)
Hard contacts solve (7) with the JOR/SOR prox iterations of :mod:`starleth_sim.physics.prox`;
compliant contacts (Alg. 1) add their forces, evaluated at (q^M, u^S), to h and Λ_U
vanishes. The stepper works for any coordinate set (see :mod:`starleth_sim.physics.coordinates`).

A step runs in two parts: `MoreauStepper.prepare` does everything that depends only on
(q^S, u^S) (q^M, M, h without τ, the kinematics, the factor of M, M^{-1}W, G), and
`MoreauStepper.step` adds the joint torques and external forces to h and solves (7) and (8).
A caller may prepare ahead (sim_node does, while its controller computes); the result is
the same bit for bit. A step that was not prepared ahead runs as one kernel
(:mod:`starleth_sim.physics.tree_step`: the midpoint, the bilateral constraints of the cut
joints, the contact problem and its solution, Eqn. 8): tree_step_hard / tree_step_compliant
for the minimal coordinates, forest_step_hard for the extended and maximal coordinates with
hard contacts. The phase-by-phase path (a prepared or profiled step, and compliant contacts
with bilateral constraints) runs the same kernels from Python: the midpoint
(`ForestCoordinates.midpoint`: q^M, M and h by the jitted CRBA / RNEA of
:mod:`starleth_sim.physics.rigid_body`, the contact kinematics), the contact problem set up
and solved (`solve_hard_contacts`, or `solve_compliant`), Eqn. (8) (`end_of_step`). The
kernels, their typed records (`StepSettings`, `ContactProblem`) and the
Fig. 7 phases (`PHASES`) are in :mod:`starleth_sim.physics.step_kernels`.

Model, state and workspace (see :mod:`starleth_sim.physics.state`): the stepper holds the
model side (coordinate set, ground, `StepSettings`, ε per contact) and a workspace (the
arrays at q^M, the factor of M, the prepared step, `StepperStats`); the evolving state,
including the contact memory the kernels read and update (warm start, hysteresis, the
compliant contacts' anchors), lives in the `SimState` passed to `prepare` and `step`.

Profiling: there is one sequence of phase calls, profiled or not (the one-kernel step is
not used when profiling). The Python orchestration and the kernels add the time of each
phase to StepperStats.timings; when not profiling, the Python side skips its laps behind
`if prof:`. The call overheads between the phases are no phase's.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import prox
from .actuator import NonFiniteTorque, saturate_torque
from .config import ConfigError
from .contact import (FRAME_STRIDE, CompliantLaw, GroundPlane, compliant_contact_forces,
                      generalized_contact_force)
from .impedance import (TORQUE_AS_GIVEN, TORQUE_IMPEDANCE, TORQUE_REPLAY, TORQUE_SATURATED,
                        command_torques)
from .linalg import ltdl
from .state import SimState
from .terrain import SECOND_SURFACES, pack_terrain
from .step_kernels import (PHASES, PHASE_M_AND_H, PHASE_M_INVERSE, PHASE_REST,
                           PROJECTION_LOOKAHEAD, PROJECTION_TOLERANCE, ContactProblem,
                           StepSettings, clock,
                           complete_hard_contacts, end_of_step, lap,
                           prepare_hard_contacts, solve_compliant, solve_hard_contacts)
from .tree_step import (TREE_STEP_NONFINITE_IMPULSE, TREE_STEP_NONFINITE_STATE,
                        TREE_STEP_NONFINITE_TORQUE, TREE_STEP_NOT_PD, CutModel, TreeStepModel,
                        TreeStepResult, forest_step_hard, report_size, report_views,
                        tree_step_compliant, tree_step_hard)


_empty = np.empty


class SimulationError(RuntimeError):
    """The step could not be completed (non-finite solver output or state); the state was
    left unchanged."""


@dataclass(slots=True)
class StepResult:
    """What one physics step did (all arrays over every contact point of the model)."""

    #: bool per contact: hard contacts, in the active set I at q^M (active_set:
    #: g_N ≤ contact.activation_gap, 0 in the presets; with contact.activation
    #: "hysteresis" also loaded in the last step and g_N ≤ contact.opening_gap);
    #: compliant contacts, closed (g_N(q^M) ≤ 0)
    active: np.ndarray
    gap: np.ndarray             # g_N at q^M [m]
    impulse: np.ndarray         # Λ (nc x 3) in the contact frame (N, T1, T2) [N s]
    iterations: int = 0
    status: int = prox.STATUS_CONVERGED
    residual: float = 0.0
    retried: bool = False
    position: np.ndarray | None = None   # contact points at q^M (nc x 3) [m]
    n_active: int = 0                    # contacts in the active set
    opened: int = 0                      # contacts loaded in the last step, not in the set
    projection_iterations: int = 0       # post-step projection (0: it did not run)
    projection_status: int = -1          # its prox.STATUS_*, −1: it did not run

    # (n_active, opened, iterations, status, residual, retried, projection_iterations and
    # projection_status: the figures a TreeStepResult of the one-kernel step has too)

    @property
    def projected(self) -> bool:
        """The post-step projection ran."""
        return self.projection_status >= 0


@dataclass
class StepperStats:
    steps: int = 0
    nonconverged: int = 0
    retried: int = 0
    projections: int = 0        # steps with a post-step projection
    timings: np.ndarray = field(default_factory=lambda: np.zeros(len(PHASES)))


class MoreauStepper:
    """Midpoint time-stepper shared by all coordinate sets and both contact models. It
    holds the model side and a workspace; the state it advances is a `SimState`."""

    def __init__(self, coords, config, profile: bool = False, torque_limits=None):
        """torque_limits: (effort, velocity) limits per actuated joint, public order, for
        the torque saturation of the one-kernel step (actuator.saturate_torque; default:
        none)."""
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
        c = config.contact
        self.activation_gap = c.activation_gap if self.hard else 0.0
        self.hysteresis = self.hard and c.activation == "hysteresis"
        beta_n = c.penetration_stabilization if self.hard else 0.0
        self.beta_velocity = beta_n if c.penetration_correction == "velocity" else 0.0
        self.beta_projection = beta_n if c.penetration_correction == "projection" else 0.0
        #: contact Jacobians are needed up to the largest gap at which a contact can be
        #: active, or be predicted to end the step below the ground (projection)
        self.jacobian_gap = max(self.activation_gap,
                                c.opening_gap if self.hysteresis else 0.0,
                                PROJECTION_LOOKAHEAD if self.beta_projection > 0 else 0.0)
        nc, nv = coords.n_contacts, coords.nv
        self.nc, self.nv = nc, nv
        self.nb = coords.n_bilateral
        # -- workspace: recomputed by every step (see starleth_sim.physics.state)
        self.gap = np.zeros(nc)               # g_N at q^M [m]
        self.position = np.zeros((nc, 3))     # contact points at q^M [m]
        self.Wt_all = np.zeros((nc, 3, nv))   # W^T of every contact (rows n, t1, t2)
        self.L = np.zeros((nv, nv))           # LTDL factor of M (linalg.ltdl)
        self.u_free = np.zeros(nv)            # u^S + M^{-1} h Δt
        self.u_corr = np.zeros(nv)            # Δu_p of the post-step projection
        #: each contact's (n, t1, t2, μ, surface) at q^M (contact.FRAME_STRIDE; the surface: memory)
        self.frames = np.zeros((nc, FRAME_STRIDE))
        self.bB = np.zeros(self.nb)           # (β/Δt) g_B
        self._factored = False                # L holds the factor of a constant M
        self._prepared = None                 # see prepare
        # -- model
        self.dof_parent = coords.tree.dof_parent
        self.constant_M = coords.constant_mass_matrix
        self.no_bilateral = np.zeros((0, nv))
        self.beta = config.bilateral.stabilization
        s = config.solver
        self.form = prox.FORMS[s.form]
        self.scheme = prox.SCHEMES[s.scheme]
        self.criterion = prox.CRITERIA[s.criterion]
        self.bilateral_direct = config.bilateral.method == "direct"
        #: the kernels' settings (and, for the two kernels Python calls, their fields as a
        #: plain tuple: see the module docstring)
        self.settings = StepSettings(
            activation_gap=float(self.activation_gap), mu=float(config.ground.mu),
            alpha=prox.alpha_setting(s.alpha),      # solver.alpha: auto -> prox.ALPHA_AUTO
            tol_rel=float(s.tol_rel), tol_abs=float(s.tol_abs),
            fallback_alpha_factor=float(s.fallback_alpha_factor),
            opening_gap=float(c.opening_gap), dt=float(self.dt),
            beta_velocity=float(self.beta_velocity),
            beta_projection=float(self.beta_projection),
            jacobian_gap=float(self.jacobian_gap),
            projection_tolerance=float(PROJECTION_TOLERANCE), form=int(self.form),
            scheme=int(self.scheme), max_iterations=int(s.max_iterations),
            criterion=int(self.criterion), warm_start=bool(s.warm_start),
            bilateral_direct=bool(self.bilateral_direct), hysteresis=bool(self.hysteresis))
        self._settings_fields = tuple(self.settings)
        self.compliant_law = CompliantLaw(
            mu=float(config.ground.mu), c_N=float(c.stiffness_normal),
            d_N=float(c.damping_normal), c_T=float(c.stiffness_tangential),
            d_T=float(c.damping_tangential), slip_velocity=float(c.slip_velocity))
        self._compliant_law_fields = tuple(self.compliant_law)
        #: Newton-type impact law per contact: (ε_N, ε_T), defaults overridden by name
        self.eps = np.tile([c.restitution_normal, c.restitution_tangential], (nc, 1))
        names = np.array(coords.contact_names)
        for name, (en, et) in c.restitution_overrides.items():
            if name not in names:
                raise ConfigError(f"contact.restitution_overrides: unknown contact '{name}' "
                                  f"(contacts: {', '.join(dict.fromkeys(names))})")
            self.eps[names == name] = (en, et)      # (both slots of a sphere on a terrain)
        self._never_active = np.full(nc, np.inf)
        #: the memory of a hard-contact problem prepared ahead (prepare), filled again each time
        self._problem = ContactProblem()
        self.stats = StepperStats()
        #: an unprepared, unprofiled step runs as one kernel: of a set without bilateral
        #: constraints whose M depends on q (the minimal coordinates) in tree_step_hard /
        #: tree_step_compliant, of a cut forest (the extended and maximal coordinates) with
        #: hard contacts in forest_step_hard; the others (compliant contacts with bilateral
        #: constraints) phase by phase
        n_cut = getattr(coords, "n_cut", None)
        self._forest_kernel = bool(self.hard and n_cut is not None
                                   and (n_cut > 0 or coords.constant_mass_matrix))
        self._one_kernel = self._forest_kernel or (
            not coords.constant_mass_matrix and self.nb == 0 and n_cut == 0)
        self._no_force = np.zeros(0)
        #: τ of no torque (one entry per actuated joint), for a step given none
        self._no_torque = np.zeros(coords.joint_v.shape[0])
        self._one_kernel_unprofiled = self._one_kernel and not profile
        #: joint dampers are implicit where every joint rate is an entry of u and M is
        #: factored with the step (the tree kernels' sets: the minimal coordinates)
        self.implicit_dampers = self._one_kernel and not self._forest_kernel
        #: (applied τ, explicit τ, kd of the implicit dampers) of the last `step`
        self.last_torques = None
        na = coords.joint_v.shape[0]
        effort, velocity = (np.full(na, np.inf), np.full(na, np.inf)) \
            if torque_limits is None else torque_limits
        self._effort_limit, self._velocity_limit = effort, velocity
        if self._one_kernel:    # the workspace arrays become views of the packed buffer
            pack, views = TreeStepModel.pack(self.settings, self.compliant_law,
                                             coords.midpoint_model(), self.ground, self.eps,
                                             coords.joint_v, coords.tree.dof_parent, nv, effort,
                                             velocity, coords.joint_q)
            self._tree_model = tuple(pack)
            (self.gap, self.position, self.Wt_all, self.L, self.u_free, self.u_corr,
             self.frames) = views
            if self._forest_kernel:
                self._cut_model = tuple(CutModel.pack(coords, self.beta / self.dt))
                #: where the kernel writes φ and φ̇ of the cut joints at the end of the step
                self._cut_motion = coords.cut_motion_buffers()

    def initial_state(self, q, u, t: float = 0.0) -> SimState:
        """The state (q, u, t) without contact memory or pending wrenches."""
        return SimState.initial(q, u, t, self.nc, self.nb, self.hard)


    # -- one step -------------------------------------------------------------------------
    def _midpoint(self, q, u, timings):
        """q^M (Eqn. 6), M and h without τ at (q^M, u^S), the contact kinematics (gap,
        position, W^T of the contacts within jacobian_gap) and the bilateral W_B^T, b_B at
        q^M. Returns (q^M, M, h, W_B^T)."""
        dt = self.dt
        coords = self.coords
        t = clock(timings)
        # (the contact kinematics share the forward kinematics of M and h: phase "M and h")
        qM, M, h0 = coords.midpoint(q, u, dt, self.ground, self.gap, self.position,
                                    self.Wt_all, self.jacobian_gap, self.frames)
        t = lap(timings, PHASE_M_AND_H, t)
        if self.nb:
            WtB, gB = coords.bilateral(qM)
            np.multiply(gB, self.beta / dt, out=self.bB)
        else:
            WtB = self.no_bilateral
        lap(timings, PHASE_REST, t)
        return qM, M, h0, WtB

    def _factor(self, M, timings):
        """The LTDL factor of M (linalg.ltdl) into L (kept while M is constant). False if M is
        not positive definite."""
        if self.constant_M and self._factored:
            return True
        t = clock(timings)
        ok = ltdl(M, self.dof_parent, self.L)
        lap(timings, PHASE_M_INVERSE, t)
        self._factored = ok
        return ok

    def prepare(self, state: SimState):
        """The part of the step from (q^S, u^S) = (state.q, state.u) that does not depend on
        the joint torques or external forces: q^M (Eqn. 6), M and h without τ, the contact
        and bilateral kinematics at q^M, the factor of M and, with hard contacts, M^{-1}W and
        G (the active set reads the state's contact memory). `step` uses it when called with
        a state holding the same q and u objects (which must not be modified in place in
        between), else it does the same arithmetic itself (in one kernel with the rest of
        the step, solve_hard_contacts), so the result is the same bit for bit either way. A
        lockstep node calls this after publishing a state, while the controller works on
        its answer. Never raises: a failure is reported by the step that uses it."""
        q, u = state.q, state.u
        timings = self.stats.timings if self.profile else None
        qM, M, h0, WtB = self._midpoint(q, u, timings)
        problem = None
        if self.hard or self.nb:    # compliant contacts: the prox solve of the bilaterals
            factor = not (self.constant_M and self._factored)
            gap = self.gap if self.hard else self._never_active
            problem = prepare_hard_contacts(self._settings_fields, M, u, gap, self.Wt_all,
                                            WtB, self.bB, self.eps, self.dof_parent, factor,
                                            self.L, state.last_impulse, state.last_active,
                                            timings, self.frames, self._problem)
            ok = problem.ok
            if ok:
                self._factored = True
        else:
            ok = self._factor(M, timings)
        self._prepared = (q, u, qM, M, h0, ok, problem, WtB)

    def step(self, state: SimState, tau, f_ext=None, mode=TORQUE_AS_GIVEN) -> "StepResult":
        """Advance state by Δt with joint torques tau (public joint order) and an optional
        generalized external force f_ext: state.q and state.u become q^E and u^E, and the
        contact memory is updated (state.t is the caller's). mode TORQUE_IMPEDANCE: tau is
        an impedance command's packed buffer (the law at the state, saturated, its dampers
        implicit where `implicit_dampers`: see `torques_of_command`); TORQUE_REPLAY: tau is
        the explicit torques then the dampers' kd (2 per joint). `last_torques` then holds
        the applied, explicit torques and dampers. Returns the StepResult. On a
        SimulationError, q and u are unchanged but the contact memory may not be (the
        Simulator restores its snapshot)."""
        prof = self.profile
        p = self._prepared
        self._prepared = None
        prepared = p is not None and p[0] is state.q and p[1] is state.u
        if self._one_kernel and not prof and (
                not prepared or (mode != TORQUE_AS_GIVEN and self.implicit_dampers)):
            return self._step_one_kernel(state, tau, f_ext, mode)
        damper = None
        if mode != TORQUE_AS_GIVEN:
            tau, damper = self.torques_of_command(tau, state.q, state.u, mode)
            if damper.any():
                prepared = False    # (prepare factored M, not M~)
            else:
                damper = None
        if damper is not None:
            return self._step_implicit(state, tau, f_ext, damper, mode == TORQUE_IMPEDANCE)
        self.last_torques = None if tau is None else (tau, tau, np.zeros(tau.shape[0]))
        timings = self.stats.timings if prof else None
        if prepared:
            _, u, qM, M, h, ok, problem, WtB = p
        else:   # not prepared ahead: the rest of the step runs in one kernel
            u = state.u
            qM, M, h, WtB = self._midpoint(state.q, u, timings)
            problem = None
            ok = True
        if not ok:
            raise SimulationError("mass matrix (or G_B) not positive definite "
                                  "(non-finite state?)")
        coords = self.coords
        t = clock(timings) if prof else 0.0
        if tau is not None and tau.shape[0]:
            coords.add_joint_torques(qM, u, tau, h)
        if f_ext is not None:
            h += f_ext
        if prof:
            lap(timings, PHASE_M_AND_H, t)
        if self.hard:
            uE, res = self._solve(state, M, h, u, problem, WtB, timings)
        else:
            uE, res = self._solve_compliant(state, M, h, u, problem, WtB, prepared, timings)
        t = clock(timings) if prof else 0.0
        self._end_of_step(state, qM, uE, res)
        if prof:
            lap(timings, PHASE_REST, t)
        return res

    def _end_of_step(self, state, qM, uE, res):
        """Eqn. (8) into state (q^E, u^E); with a post-step projection, the positions move
        by ½Δt Δu_p more. SimulationError if the result is not finite."""
        qE = np.empty_like(qM)
        tree = self.coords.tree
        if not end_of_step(qM, uE, self.u_corr, res.projected, 0.5 * self.dt, tree.jtype,
                           tree.idx_q, tree.idx_v, qE):
            raise SimulationError("non-finite state after the step; state left unchanged")
        state.q, state.u = qE, uE
        self.stats.steps += 1

    def step_is_transactional(self, state: SimState) -> bool:
        """Whether the next `step` of `state`, should it fail (SimulationError), leaves the
        state as it was: so it does when it runs in one kernel (not prepared ahead, not
        profiling); the phase-by-phase path may have updated the contact memory, so its
        caller keeps a copy to restore."""
        p = self._prepared
        return self._one_kernel_unprofiled and (
            p is None or not (p[0] is state.q and p[1] is state.u))

    def _step_one_kernel(self, state, tau, f_ext, mode=TORQUE_AS_GIVEN):
        """`step` in one kernel call (tau as given, not saturated again, or a command of
        `mode`): its StepResult."""
        na = self._no_torque.shape[0]
        report = np.empty(report_size(self.nc, na))
        is_active = np.empty(self.nc, dtype=np.bool_)
        r = self.step_in_one_kernel(state, tau, report, is_active, f_ext, saturate=False,
                                    impedance=mode == TORQUE_IMPEDANCE,
                                    replay=mode == TORQUE_REPLAY)
        impulse, gap, position, applied, explicit, damper = report_views(report, self.nc, na)
        self.last_torques = (applied, explicit, damper)
        return StepResult(is_active, gap, impulse, r.iterations, r.status, r.residual,
                          r.retried, position, r.n_active, r.opened, r.projection_iterations,
                          r.projection_status)

    def step_in_one_kernel(self, state: SimState, tau, report, is_active, f_ext=None,
                           saturate: bool = True, impedance: bool = False,
                           replay: bool = False) -> TreeStepResult:
        """`step` in one kernel call (tree_step_hard / tree_step_compliant /
        forest_step_hard), for a state that `step_is_transactional` approves: the same
        result bit for bit as the phase-by-phase path. tau: the torques asked (float64, one
        per actuated joint), saturated by the torque_limits (actuator.saturate_torque) unless
        saturate is False: in the kernel, or for a cut forest before it (a cut joint's rate
        comes from the cut-joint kinematics of the state, ForestCoordinates'
        joint_velocities, which a controller has usually asked for already). With impedance
        True, tau is an ImpedanceCommand's packed buffer: the law at the joint angles and
        rates of (state.q, state.u), then saturated (`saturate` is not read), its dampers
        implicit (tree kernels; a cut forest's stay explicit); with replay True, tau holds
        the explicit torques then the dampers' kd (report_views' explicit_torque, damper).
        Writes the report buffer (tree_step.report_views: Λ, g_N and contact points at q^M,
        the applied torques) and the active flags; returns the kernel's TreeStepResult
        (its outcome TREE_STEP_OK). A NonFiniteTorque or SimulationError leaves the state as
        it was."""
        self._prepared = None       # (a step prepared for another state is stale now)
        q, u = state.q, state.u
        mode = TORQUE_SATURATED if saturate else TORQUE_AS_GIVEN
        if impedance:
            if self._forest_kernel:     # the law at φ, φ̇ of the cut-joint kinematics
                tau = self.torques_of_command(tau, q, u, TORQUE_IMPEDANCE)[0]
                saturate = False
            else:
                mode = TORQUE_IMPEDANCE
        elif replay:
            na = self._no_torque.shape[0]
            if tau.shape[0] != 2 * na:
                raise ValueError(f"a replay needs {2 * na} entries, got {tau.shape[0]}")
            if self._forest_kernel:
                if np.any(tau[na:] != 0.0):
                    raise ValueError("a cut forest has no implicit dampers to replay")
                tau = np.ascontiguousarray(tau[:na])
            else:
                mode = TORQUE_REPLAY
        elif tau is None or tau.shape[0] == 0:  # no torques, as in the phase-by-phase step
            tau = self._no_torque
        elif tau.shape[0] != self._no_torque.shape[0]:  # (the kernel reads one per joint)
            raise ValueError(f"tau must have {self._no_torque.shape[0]} entries, "
                             f"got {tau.shape[0]}")
        qE = _empty(q.shape[0])     # (np.empty: a third of np.empty_like's call)
        uE = _empty(u.shape[0])
        if f_ext is None:
            f_ext = self._no_force
        if self._forest_kernel:
            if saturate:    # (a cut joint's rate comes from the cut-joint kinematics)
                applied = np.empty(tau.shape[0])
                if not saturate_torque(tau, self._effort_limit,
                                       self.coords.joint_velocities(q, u),
                                       self._velocity_limit, applied):
                    raise NonFiniteTorque("tau has non-finite entries")
                tau = applied
            factor = not (self.constant_M and self._factored)
            r = forest_step_hard(q, u, tau, f_ext, factor, state.last_impulse,
                                 state.last_active, state.last_bilateral, report, is_active,
                                 qE, uE, *self._cut_motion, *self._tree_model, *self._cut_model)
        elif self.hard:
            r = tree_step_hard(mode, q, u, tau, f_ext, state.last_impulse,
                               state.last_active, state.last_bilateral, report, is_active, qE,
                               uE, *self._tree_model)
        else:
            r = tree_step_compliant(mode, q, u, tau, f_ext, state.closed, state.slip,
                                    state.anchor, state.lam_compliant, report, is_active, qE,
                                    uE, *self._tree_model)
        outcome = r.outcome
        if outcome == TREE_STEP_NONFINITE_TORQUE:
            raise NonFiniteTorque("tau has non-finite entries")
        if outcome == TREE_STEP_NOT_PD:
            raise SimulationError("mass matrix (or G_B) not positive definite "
                                  "(non-finite state?)")
        self._factored = True
        if r.retried:
            self.stats.retried += 1
        if r.status != prox.STATUS_CONVERGED:
            self.stats.nonconverged += 1
        if r.projection_status >= 0:
            self.stats.projections += 1
        if outcome == TREE_STEP_NONFINITE_IMPULSE:
            raise SimulationError("prox iteration produced non-finite impulses; "
                                  "state left unchanged")
        if outcome == TREE_STEP_NONFINITE_STATE:
            raise SimulationError("non-finite state after the step; state left unchanged")
        state.q, state.u = qE, uE
        if self._forest_kernel:
            self.coords.cut_motion_written(qE, uE)
        self.stats.steps += 1
        return r

    def torques_of_command(self, tau, q, u, mode):
        """(explicit torques, kd of the implicit dampers) of a command of `mode` at (q, u)
        (impedance.command_torques with this stepper's limits)."""
        return command_torques(tau, q, u, mode, self.coords, self._effort_limit,
                               self._velocity_limit, self.implicit_dampers)

    def _step_implicit(self, state, tau, f_ext, damper, check):
        """The phase-by-phase step with implicit dampers, as the tree kernels do it: M~ = M +
        Δt K_d, the applied torques τ − kd (q̇^E − q̇^S); with check, a damped joint whose
        torque would be saturated at q̇^E loses its damper and the step is solved once more
        from the same contact memory."""
        u = state.u
        qM, M, h, WtB = self._midpoint(state.q, u, None)
        self.coords.add_joint_torques(qM, u, tau, h)
        if f_ext is not None:
            h += f_ext
        jv = self.coords.joint_v
        kept = state.copy()
        h0 = h.copy()
        damper = damper.copy()
        for attempt in (0, 1):
            Md = M.copy()
            Md[jv, jv] += self.dt * damper
            if self.hard:
                uE, res = self._solve(state, Md, h, u, None, WtB, None)
            else:
                uE, res = self._solve_compliant(state, Md, h, u, None, WtB, False, None)
            applied = tau - damper * (uE[jv] - u[jv])
            over = (damper > 0.0) & ((np.abs(applied) > self._effort_limit) | (
                (np.abs(uE[jv]) > self._velocity_limit) & (applied * uE[jv] > 0.0)))
            if attempt or not check or not over.any():
                break
            damper[over] = 0.0
            state.restore_memory(kept)
            h = h0.copy()
        self.last_torques = (np.where(damper > 0.0, applied, tau), tau, damper)
        self._end_of_step(state, qM, uE, res)
        return res

    def _solve_compliant(self, state, M, h, uS, problem, WtB, prepared, timings):
        """Alg. 1: the compliant forces at (q^M, u^S) join h; then u^E by the prox solve of
        the bilateral constraints, or u^E = u_free without them (solve_compliant, which
        also factors M unless the step was prepared)."""
        dt = self.dt
        law = self._compliant_law_fields
        frames = self.frames
        if self.nb:  # bilateral constraints still need the prox solve (no contact rows)
            prof = timings is not None
            t = clock(timings) if prof else 0.0
            compliant_contact_forces(law, self.gap, self.position, self.Wt_all, uS,
                                     state.closed, state.slip, state.anchor, frames,
                                     state.lam_compliant)
            generalized_contact_force(self.Wt_all, state.lam_compliant, h)
            if prof:
                lap(timings, PHASE_REST, t)
            uE, res = self._solve(state, M, h, uS, problem, WtB, timings)
        else:
            factor = not prepared and not (self.constant_M and self._factored)
            if not solve_compliant(law, M, h, uS, dt, self.gap, self.position, self.Wt_all,
                                   state.closed, state.slip, state.anchor, frames,
                                   state.lam_compliant, self.dof_parent, factor, self.L,
                                   self.u_free, timings):
                raise SimulationError("mass matrix not positive definite (non-finite state?)")
            if factor:
                self._factored = True
            uE, res = self.u_free.copy(), StepResult(None, None, None)
        active = self.gap <= 0.0
        res.active = active
        res.n_active = int(np.count_nonzero(active))
        res.gap = self.gap.copy()
        res.position = self.position.copy()
        res.impulse = state.lam_compliant * dt
        return uE, res

    def _solve(self, state, M, h, uS, problem, WtB, timings):
        """u^E of the hard-contact (or bilateral) problem, prepared (`problem`: the
        ContactProblem of prepare_hard_contacts) or, with problem None, set up and solved in
        one kernel (solve_hard_contacts, with W_B^T of the midpoint); the warm-start memory
        of `state` updated."""
        nc = self.nc
        impulse = np.empty((nc, 3))
        is_active = np.empty(nc, dtype=np.bool_)
        u = np.empty(self.nv)
        gap = self.gap if self.hard else self._never_active
        if problem is None:
            factor = not (self.constant_M and self._factored)
            r = solve_hard_contacts(self._settings_fields, M, uS, gap, self.Wt_all, WtB,
                                    self.bB, self.eps, self.dof_parent, factor, self.L, h,
                                    state.last_impulse, state.last_active,
                                    state.last_bilateral, impulse, is_active, self.u_free, u,
                                    self.u_corr, timings, self.frames)
            if not r.ok:
                raise SimulationError("mass matrix (or G_B) not positive definite "
                                      "(non-finite state?)")
            self._factored = True
            n_active, opened = r.n_active, r.opened
        else:
            r = complete_hard_contacts(
                self._settings_fields, problem, h, uS, M, self.dof_parent, self.L, gap,
                self.Wt_all, state.last_impulse, state.last_active, state.last_bilateral,
                impulse, is_active, self.u_free, u, self.u_corr, timings)
            n_active, opened = problem.n_active, problem.opened
        if r.retried:
            self.stats.retried += 1
        if r.status != prox.STATUS_CONVERGED:
            self.stats.nonconverged += 1
        if r.status == prox.STATUS_NONFINITE:
            raise SimulationError("prox iteration produced non-finite impulses; "
                                  "state left unchanged")
        if r.projection_status >= 0:
            self.stats.projections += 1
        return u, StepResult(is_active, self.gap.copy(), impulse, r.iterations, r.status,
                             r.residual, r.retried, self.position.copy(),
                             n_active if self.hard else 0, opened, r.projection_iterations,
                             r.projection_status)
