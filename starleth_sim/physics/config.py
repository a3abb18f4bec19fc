"""Physics configuration: one YAML file per configuration of the paper's Table 1
(``msg_configs/<name>.yaml``), validated on load.

Every field has a unique name across sections, so overrides can be flat
(``Simulator.from_preset("HmJ", alpha=0.4)``) or dotted (``{"solver.alpha": 0.4}``).
A bad file or override raises :class:`ConfigError` naming the file and the field, e.g.
``HmJ.yaml: solver.alpha: must be < 2, got 2.5``.

Every number has a physical range (NaN and infinities are refused everywhere); the ranges
and their reasons:

=============================  ===========================  ================================
field                          range                        why
=============================  ===========================  ================================
control_rate                   [1, 100 000] Hz              a controller's loop: slower than
                                                            1 Hz is no control, faster than
                                                            100 kHz no robot's
steps_per_control              integer [1, 10 000]          and Δt = 1/(control_rate ·
                                                            steps_per_control) >= 1 µs: at
                                                            most 10⁶ steps per simulated
                                                            second (Δt <= the control period
                                                            follows from N >= 1)
ground.height                  [-1000, 1000] m              a floor near the robot; far away
                                                            the positions lose precision
ground.normal                  3 finite numbers, not zero,  normalised on load; z > 0: a
                               z > 0 after normalising      floor under the robot (gravity is
                                                            -z), not a wall or a ceiling
ground.mu                      [0, 10]                      real materials < 2; 10 is already
                                                            "never slips"
contact.restitution_*          [0, 1]                       Newton's impact law: 1 is elastic,
(and restitution_overrides)                                 > 1 would create energy
contact.stiffness_*            (0, 1e9] N/m                 a spring, stiffer than any foot
contact.damping_*              [0, 1e6] N s/m               a damper (explicit: beyond, any
                                                            Δt is unstable)
contact.slip_velocity          [0, 1] m/s                   "stopped" threshold (paper ~1e-4)
contact.activation_gap,        [0, 0.1] m                   gaps near the ground (opening_gap
contact.opening_gap                                         >= activation_gap)
contact.penetration_           [0, 1]                       the fraction of the penetration
stabilization                                               removed per step
solver.alpha                   (0, 2) or auto               the prox iteration's convergence
solver.tol_rel                 [0, 1]                       a relative change; 1 = anything
solver.tol_abs                 [0, 1000] N s                an impulse (and tol_rel or
                                                            tol_abs > 0)
solver.max_iterations          integer [1, 1 000 000]       a cap per solve that still ends
solver.fallback_alpha_factor   [0, 1)                       a smaller α on a retry, 0 = none
solver.stall_window           integer [0, 1 000 000]       sweeps per stall test (0 = none)
solver.fallback_hold          integer [0, 1 000 000]       steps a fallback α is kept (0 = none)
bilateral.stabilization        [0, 1]                       β of the drift correction
bilateral.relaxation           [0, 2)                       ω_B: SOR converges in (0, 2)
actuator.armature              [0, 100] kg m²               a reflected rotor inertia: a
                                                            big drive's is < 10 (StarlETH's
                                                            ~0.02, a 1 t excavator's ~10)
actuator.viscous_damping       [0, 1e4] N m s/rad           implicit: stable at any Δt; more
                                                            locks a joint
actuator.coulomb_friction      [0, 1e4] N m                 a joint's breakaway torque; more
                                                            than any drive's torque
actuator.torque_bandwidth      [0, 1e5] Hz, 0 = off         a torque loop's; beyond the
                                                            physics rate the lag is none
(each also {joint: value})     joint names of the robot     checked at Simulator build
terrain.boxes                  <= 10 000; centre within     positions near the robot; a box
                               +-1000 m, size (0, 1000] m,  has a volume; μ as ground.mu
                               yaw [-2π, 2π], μ [0, 10]
terrain.heightfield            2 to 1024 points a side,     a recorded configuration stays
                               cell (0, 100] m, heights     < 16 MiB (MAX_CONFIG_BYTES); cell
                               within +-1000 m              and heights on the robot's scale
terrain.stairs / slope /       rise (0, 1] m, run (0, 10]   steps a legged robot meets;
rough                          m, count [1, 100]; angle     slopes up to 45°; amplitude up
                               (0, 45]°, length (0, 100] m; to 0.5 m (physics/terrain.py)
                               amplitude (0, 0.5] m,
                               wavelength (0, 100] m
                               slope and rough grids <=     a heightfield's bound (the
                               1024 points a side; rough:   slope's grid is checked before
                               size/wavelength <= 511.5     it is made); 2 points per wave
sensors.seed                   integer [0, 2⁶³-1]           a ROS int64 parameter (seed)
sensors.imu_rate               [0, 100 000] Hz; 0 or        samples at control steps (m per
                               control_rate/m, m·control_   step above it): no state between
                               rate (m whole)               control steps is kept
sensors.imu_delay              [0, 1] s, whole control      delivered at a control step
                               periods                      (the stamp contract)
sensors.imu_gyro_*             density [0, 1] rad/s/√Hz,    beyond any MEMS or FOG gyro's
                               walk [0, 1] rad/s²/√Hz, bias figures by orders of magnitude;
                               σ [0, 10] and ±10 rad/s,     0 = unlimited range
                               range [0, 1000] rad/s
sensors.imu_accel_*            density [0, 10] m/s²/√Hz,    as the gyro's (100 m/s² = 10 g
                               walk [0, 10] m/s³/√Hz, bias  of bias is no working sensor)
                               σ [0, 100] and ±100 m/s²,
                               range [0, 10 000] m/s²
sensors.imu_orientation_       [0, π] rad                   a rotation vector's σ
noise
sensors.encoder_counts         integer [0, 2³²]             a 32-bit counter; 0 = exact
sensors.encoder_noise          [0, 1] rad                   a radian of noise is no encoder
sensors.encoder_velocity_      (0, 100 000] Hz              a low-pass cutoff; far above the
cutoff                                                      control rate it is the raw
                                                            difference
sensors.torque_noise           [0, 1000] N m                above any drive's torque
sensors.contact_threshold(_    [0, 1e5] N; _weight: [0, 1]  a force sensor's scale (StarlETH
weight), contact_force_noise   x m g (one of the two)       weighs 250 N)
sensors.contact_delay          integer [0, 1000] steps      2.5 s at 400 Hz
paper                          names: finite numbers or     figures for reports only
                               strings
=============================  ===========================  ================================

YAML files are read with ``starleth_interface.yaml_files.load_yaml_file``, the project's
one loader of configuration YAML (duplicate keys, binary files, sizes: its docstring).
"""
from __future__ import annotations

import copy
import math
import os
from dataclasses import asdict, dataclass, field, fields

from starleth_interface.config_checks import ConfigError
from starleth_interface.config_checks import check_bool as _bool
from starleth_interface.config_checks import check_choice as _choice
from starleth_interface.config_checks import check_int as _int
from starleth_interface.config_checks import check_number as _num
from starleth_interface.config_checks import check_str as _str
from starleth_interface.config_checks import fmt_bound as _fmt
from starleth_interface.package_data import package_share_dir
from starleth_interface.yaml_files import load_yaml_file

from .sensors import SensorConfig
from .terrain import TerrainConfig

# =========================================================================================
# the ranges (see the table above)
# =========================================================================================
MIN_CONTROL_RATE, MAX_CONTROL_RATE = 1.0, 100_000.0     # Hz
MAX_STEPS_PER_CONTROL = 10_000
MIN_DT = 1e-6                                           # s: the smallest physics step
MAX_ITERATIONS = 1_000_000
MAX_MU = 10.0
MAX_GROUND_HEIGHT = 1000.0                              # m
MAX_STIFFNESS = 1e9                                     # N/m
MAX_DAMPING = 1e6                                       # N s/m
MAX_SLIP_VELOCITY = 1.0                                 # m/s
MAX_GAP = 0.1                                           # m
MAX_TOL_ABS = 1000.0                                    # N s
MAX_ARMATURE = 100.0                                    # kg m²
MAX_VISCOUS_DAMPING = 1e4                               # N m s/rad
MAX_COULOMB_FRICTION = 1e4                              # N m
MAX_BANDWIDTH = 1e5                                     # Hz


@dataclass
class GroundConfig:
    height: float = 0.0
    normal: tuple = (0.0, 0.0, 1.0)
    mu: float = 0.8

    def validate(self, p):
        self.height = _num(f"{p}.height", self.height, -MAX_GROUND_HEIGHT, MAX_GROUND_HEIGHT)
        n = self.normal
        if not isinstance(n, (list, tuple)) or len(n) != 3:
            raise ConfigError(f"{p}.normal: expected a list of 3 numbers, got {n!r}")
        n = tuple(_num(f"{p}.normal[{i}]", x) for i, x in enumerate(n))
        norm = math.hypot(*n)          # no overflow of the squares
        if norm < 1e-9:
            raise ConfigError(f"{p}.normal: must not be the zero vector")
        n = tuple(x / norm for x in n)
        if not n[2] > 0.0:
            raise ConfigError(f"{p}.normal: must point up (z > 0: a floor under the robot, "
                              f"gravity is -z), got {list(self.normal)!r}")
        self.normal = n
        self.mu = _num(f"{p}.mu", self.mu, 0.0, MAX_MU)


@dataclass
class ContactConfig:
    #: Newton-type impact law ε_N, ε_T (hard contacts; the paper uses 0)
    restitution_normal: float = 0.0
    restitution_tangential: float = 0.0
    #: per-contact impact law: {contact name: [ε_N, ε_T]} (names checked by the Simulator)
    restitution_overrides: dict = field(default_factory=dict)
    #: compliant model (Alg. 1): c_N, d_N, c_T, d_T
    stiffness_normal: float = 30000.0
    damping_normal: float = 50.0
    stiffness_tangential: float = 30000.0
    damping_tangential: float = 50.0
    #: |γ_T| below which a slipping compliant contact counts as stopped (‖γ_T‖ ≈ 0)
    slip_velocity: float = 1e-4
    #: hard contacts, the active set I at the midpoint q^M (Eqn. 7):
    #:   "paper":      I = {i | g_N,i(q^M) ≤ activation_gap}
    #:   "hysteresis": the same, plus every contact that carried a normal impulse Λ_N > 0 in
    #:                 the last step while g_N,i(q^M) ≤ opening_gap. A loaded contact is then
    #:                 never dropped by the gap test alone (the velocity-level law lets a
    #:                 loaded sphere foot drift up by O(Δt²) per step); the contact law
    #:                 decides whether it opens (Λ_N = 0, γ_N > 0).
    activation: str = "hysteresis"
    #: g_act [m]; the paper's 0. A contact in the active set above the ground (0 < g_N) may
    #: approach it within the step: the normal law acts on γ_N^E + ε_N γ_N^S + g_N⁺/Δt, so
    #: nothing is stopped above the ground and a loaded contact that drifted up is let down
    #: again by its load (Λ_N ≥ 0 still: the term never pulls).
    activation_gap: float = 0.0
    #: "hysteresis" only: a loaded contact stays active while g_N(q^M) ≤ this [m]
    opening_gap: float = 5e-3
    #: penetration correction of the unilateral contacts, β_N ∈ [0, 1] (0: the paper's law):
    #:   "projection": after the velocity step, the end positions are projected so that the
    #:                 active contacts' predicted end gaps g_N(q^E) lose the fraction β_N of
    #:                 their penetration (Acary 2013's post-step projection): q^E = q^M ⊕
    #:                 ½Δt (u^E + Δu_p), Δu_p = M^{-1}(W_N P_N + W_B P_B), P_N ≥ 0 pushes only,
    #:                 W_B^T Δu_p = 0; the velocities u^E, hence the impact law, are untouched.
    #:   "velocity":   Baumgarte-like, in the normal law: ξ_N += (β_N/Δt) min(g_N(q^M), 0)
    #:                 (adds kinetic energy and changes the rebound of an impact).
    penetration_correction: str = "projection"
    penetration_stabilization: float = 1.0

    def validate(self, p):
        self.restitution_normal = _num(f"{p}.restitution_normal", self.restitution_normal, 0, 1)
        self.restitution_tangential = _num(f"{p}.restitution_tangential",
                                           self.restitution_tangential, 0, 1)
        ro = self.restitution_overrides
        if not isinstance(ro, dict):
            raise ConfigError(f"{p}.restitution_overrides: expected a mapping "
                              f"{{contact: [eps_N, eps_T]}}, got {ro!r}")
        clean = {}
        for name, v in ro.items():
            if not isinstance(v, (list, tuple)) or len(v) != 2:
                raise ConfigError(f"{p}.restitution_overrides.{name}: expected [eps_N, eps_T], "
                                  f"got {v!r}")
            _str(f"{p}.restitution_overrides: contact name", name)
            clean[name] = tuple(_num(f"{p}.restitution_overrides.{name}[{k}]", x, 0, 1)
                                     for k, x in enumerate(v))
        self.restitution_overrides = clean
        for n in ("stiffness_normal", "stiffness_tangential"):
            setattr(self, n, _num(f"{p}.{n}", getattr(self, n), 0.0, MAX_STIFFNESS,
                                  lo_open=True))
        for n, hi in (("damping_normal", MAX_DAMPING), ("damping_tangential", MAX_DAMPING),
                      ("slip_velocity", MAX_SLIP_VELOCITY), ("activation_gap", MAX_GAP),
                      ("opening_gap", MAX_GAP)):
            setattr(self, n, _num(f"{p}.{n}", getattr(self, n), 0.0, hi))
        self.activation = _choice(f"{p}.activation", self.activation, {"hysteresis", "paper"})
        if self.activation == "hysteresis" and self.opening_gap < self.activation_gap:
            raise ConfigError(f"{p}.opening_gap: must be >= activation_gap "
                              f"({self.activation_gap:g}), got {self.opening_gap:g}")
        self.penetration_correction = _choice(f"{p}.penetration_correction",
                                              self.penetration_correction,
                                              {"projection", "velocity"})
        self.penetration_stabilization = _num(f"{p}.penetration_stabilization",
                                              self.penetration_stabilization, 0.0, 1.0)


@dataclass
class SolverConfig:
    scheme: str = "jor"          # jor | sor
    form: str = "delassus"       # delassus (Eqn. 12-16) | velocity (Eqn. 17-19)
    #: relaxation α ∈ (0, 2), or "auto": chosen per step and iteration from G and the
    #: convergence history (prox.py, "Adaptive α")
    alpha: float | str = 0.6
    tol_rel: float = 1e-6        # T_rel
    tol_abs: float = 1e-6        # T_abs [N s]
    max_iterations: int = 1000
    criterion: str = "impulse"   # impulse (paper) | energy (½ uᵀMu)
    warm_start: bool = True      # start from the last step's impulses of the same contacts
    #: on a non-converged solve, retry once with α·factor (0 disables)
    fallback_alpha_factor: float = 0.5
    #: a try whose best residual does not improve by 1 % over this many sweeps cycles (as JOR
    #: at α = 0.6 does on a robot lying at rest) and is retried at once with the fallback α
    #: instead of at max_iterations (0: only the cap ends a try; no test without a fallback)
    stall_window: int = 32
    #: a step whose solve needed the fallback α starts the next one at that α while the
    #: active set stays the same, for up to this many steps, then tries the paper's α again
    #: (the α a contact configuration converges with is its own, Fig. 6: a robot lying at
    #: rest cycles at the paper's α step after step; each try costs ~2 stall windows, so it
    #: is seldom: 1000 steps = 2.5 s at 400 Hz); 0: every step starts at the paper's α
    fallback_hold: int = 1000

    def validate(self, p):
        self.scheme = _choice(f"{p}.scheme", self.scheme, {"jor", "sor"})
        self.form = _choice(f"{p}.form", self.form, {"delassus", "velocity"})
        if isinstance(self.alpha, str) and self.alpha != "auto":
            raise ConfigError(f"{p}.alpha: expected a number or auto, got {self.alpha!r}")
        if self.alpha != "auto":
            self.alpha = _num(f"{p}.alpha", self.alpha, 0.0, 2.0, lo_open=True, hi_open=True)
        self.tol_rel = _num(f"{p}.tol_rel", self.tol_rel, 0.0, 1.0)
        self.tol_abs = _num(f"{p}.tol_abs", self.tol_abs, 0.0, MAX_TOL_ABS)
        if self.tol_rel == 0 and self.tol_abs == 0:
            raise ConfigError(f"{p}.tol_rel/tol_abs: at least one tolerance must be > 0")
        self.max_iterations = _int(f"{p}.max_iterations", self.max_iterations, 1,
                                   MAX_ITERATIONS)
        self.criterion = _choice(f"{p}.criterion", self.criterion, {"impulse", "energy"})
        self.warm_start = _bool(f"{p}.warm_start", self.warm_start)
        self.fallback_alpha_factor = _num(f"{p}.fallback_alpha_factor",
                                          self.fallback_alpha_factor, 0.0, 1.0, hi_open=True)
        self.stall_window = _int(f"{p}.stall_window", self.stall_window, 0, MAX_ITERATIONS)
        self.fallback_hold = _int(f"{p}.fallback_hold", self.fallback_hold, 0, MAX_ITERATIONS)


@dataclass
class BilateralConfig:
    method: str = "none"  # none (minimal coordinates) | prox (Eqn. 19) | direct (Eqn. 20)
    #: drift stabilisation β ∈ [0, 1]: the bilateral law becomes γ_B^E + (β/Δt) g_B(q^M) = 0,
    #: which removes a position-level violation g_B over a few steps. β = 0 is the paper's law
    #: (ξ_B = γ_B^E), whose violation drifts at first order in Δt.
    stabilization: float = 0.0
    #: ω_B ∈ (0, 2) of the bilateral prox rows, r_B = ω_B/G_BB, swept Gauss-Seidel after the
    #: contacts' rows in either scheme (SOR on the linear bilateral system converges for any
    #: ω_B in (0, 2), whatever its condition: the maximal coordinates' chains make JOR at the
    #: paper's α crawl); 0: the paper's, the bilateral rows as the contacts' with α. Used by
    #: bilateral prox rows at a fixed α only (the direct method has none; solver.alpha: auto
    #: relaxes them itself)
    relaxation: float = 0.0

    def validate(self, p):
        self.method = _choice(f"{p}.method", self.method, {"none", "prox", "direct"})
        self.stabilization = _num(f"{p}.stabilization", self.stabilization, 0.0, 1.0)
        self.relaxation = _num(f"{p}.relaxation", self.relaxation, 0.0, 2.0, hi_open=True)


@dataclass
class ActuatorConfig:
    #: the motors at the URDF velocity limit v: "derate" (a torque that drives its joint
    #: faster is derated linearly from full at |φ̇| = v to zero at 2v, like a motor's
    #: torque-speed line, so a misbehaving controller cannot spin a leg up without bound) |
    #: "ignore" (ideal torque sources at any speed, as in the paper)
    velocity_limit: str = "derate"
    #: the drive models (doc/drives.md; 0 = off), each a number for every actuated joint or
    #: a mapping {joint name: value} (joints not named: 0; names checked by the Simulator):
    #: I_a, the rotor's reflected inertia on M's joint diagonal [kg m²]
    armature: float | dict = 0.0
    #: D, viscous joint friction τ = −D q̇, implicit like the joint dampers [N m s/rad]
    viscous_damping: float | dict = 0.0
    #: τ_c, Coulomb joint friction |τ_f| ≤ τ_c, set-valued (sticks below τ_c) [N m]
    coulomb_friction: float | dict = 0.0
    #: f, the torque bandwidth: a first-order lag of the applied torque [Hz]
    torque_bandwidth: float | dict = 0.0

    #: the drive fields and their ranges (the table in the module docstring)
    DRIVES = {"armature": MAX_ARMATURE, "viscous_damping": MAX_VISCOUS_DAMPING,
              "coulomb_friction": MAX_COULOMB_FRICTION, "torque_bandwidth": MAX_BANDWIDTH}

    def validate(self, p):
        self.velocity_limit = _choice(f"{p}.velocity_limit", self.velocity_limit,
                                      {"derate", "ignore"})
        for name, hi in self.DRIVES.items():
            setattr(self, name, _per_joint(f"{p}.{name}", getattr(self, name), hi))

    @property
    def drives_on(self) -> bool:
        """Whether any drive model is on (a nonzero value for some joint)."""
        return any(any(v.values()) if isinstance(v, dict) else v != 0.0
                   for v in (getattr(self, n) for n in self.DRIVES))


def _per_joint(path, value, hi):
    """A drive field: a number in [0, hi], or a mapping {joint name: number in [0, hi]}."""
    if isinstance(value, dict):
        return {_str(f"{path}: joint name", k): _num(f"{path}.{k}", v, 0.0, hi)
                for k, v in value.items()}
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return _num(path, value, 0.0, hi)
    raise ConfigError(f"{path}: expected a number or a mapping {{joint: number}}, got "
                      f"{value!r:.60}")


@dataclass
class PhysicsConfig:
    name: str = "custom"
    description: str = ""
    #: the robot: a library name (robots/<name>.yaml: starleth, go1, ...), the path of a robot
    #: spec or of a URDF; starleth.urdf (the presets' and older recordings') is starleth
    robot: str = "starleth.urdf"
    coordinates: str = "minimal"   # minimal | extended | maximal
    contact_model: str = "hard"    # hard | compliant
    control_rate: float = 400.0    # [Hz]; sim.step() advances 1/control_rate
    steps_per_control: int = 1     # N: Δt = 1 / (N · control_rate)
    ground: GroundConfig = field(default_factory=GroundConfig)
    contact: ContactConfig = field(default_factory=ContactConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    bilateral: BilateralConfig = field(default_factory=BilateralConfig)
    actuator: ActuatorConfig = field(default_factory=ActuatorConfig)
    #: boxes and a heightfield on the ground plane (physics/terrain.py)
    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    #: the sensors' models (physics/sensors.py): ideal by default
    sensors: SensorConfig = field(default_factory=SensorConfig)
    #: paper's figures for this configuration (Table 1), for benchmarks and reports
    paper: dict = field(default_factory=dict)

    _SECTIONS = ("ground", "contact", "solver", "bilateral", "actuator", "terrain", "sensors")

    @property
    def dt(self) -> float:
        return 1.0 / (self.control_rate * self.steps_per_control)

    @property
    def control_period(self) -> float:
        return 1.0 / self.control_rate

    def validate(self, source="config"):
        p = source
        if not isinstance(self.name, str) or not self.name:
            raise ConfigError(f"{p}: name: expected a non-empty string, got {self.name!r}")
        if not isinstance(self.robot, str) or not self.robot:
            raise ConfigError(f"{p}: robot: expected a robot name or a path, got "
                              f"{self.robot!r}")
        if not isinstance(self.description, str):
            raise ConfigError(f"{p}: description: expected a string, got "
                              f"{self.description!r}")
        try:
            self.coordinates = _choice("coordinates", self.coordinates,
                                       {"minimal", "extended", "maximal"})
            self.contact_model = _choice("contact_model", self.contact_model,
                                         {"hard", "compliant"})
            self.control_rate = _num("control_rate", self.control_rate, MIN_CONTROL_RATE,
                                     MAX_CONTROL_RATE)
            self.steps_per_control = _int("steps_per_control", self.steps_per_control, 1,
                                          MAX_STEPS_PER_CONTROL)
            if self.control_rate * self.steps_per_control > 1.0 / MIN_DT:
                raise ConfigError(
                    f"steps_per_control: the physics step 1/(control_rate x steps_per_control)"
                    f" = {1e6 / (self.control_rate * self.steps_per_control):.3g} us must be "
                    f">= {_fmt(MIN_DT * 1e6)} us (control_rate {_fmt(self.control_rate)} Hz x "
                    f"steps_per_control {self.steps_per_control} must be <= "
                    f"{_fmt(1.0 / MIN_DT)} steps/s)")
            for s in self._SECTIONS:
                getattr(self, s).validate(s)
            self.sensors.check_rates(self.control_rate)
            if self.coordinates == "minimal" and self.bilateral.method != "none":
                raise ConfigError("bilateral.method: the minimal coordinates have no bilateral "
                                  "constraints; use 'none'")
            if self.coordinates != "minimal" and self.bilateral.method == "none":
                raise ConfigError(f"bilateral.method: coordinates '{self.coordinates}' need "
                                  "'prox' or 'direct'")
            self._check_relaxation()
            if not isinstance(self.paper, dict):
                raise ConfigError(f"paper: expected a mapping, got {self.paper!r}")
            for k, v in self.paper.items():
                if not isinstance(k, str):
                    raise ConfigError(f"paper: expected names as keys, got {k!r}")
                if not isinstance(v, str):
                    _num(f"paper.{k}", v)
        except ConfigError as e:
            raise ConfigError(f"{p}: {e}") from None
        return self

    def _check_relaxation(self):
        """bilateral.relaxation under JOR needs the Delassus form (whose velocity form has no
        sweep over single rows)."""
        s = self.solver
        if self.bilateral.relaxation and s.scheme == "jor" and s.form == "velocity":
            raise ConfigError("bilateral.relaxation: JOR needs solver.form: delassus")

    # -- construction ---------------------------------------------------------------------
    @classmethod
    def from_dict(cls, data: dict, source="config") -> "PhysicsConfig":
        if not isinstance(data, dict):
            raise ConfigError(f"{source}: expected a mapping at the top level, got "
                              f"{type(data).__name__}")
        cfg = cls()
        top = {f.name for f in fields(cls)}
        for key, value in data.items():
            if key not in top or key.startswith("_"):
                raise ConfigError(f"{source}: unknown field '{key}' (known: "
                                  f"{', '.join(sorted(t for t in top if not t.startswith('_')))})")
            if key in cls._SECTIONS:
                if value is None:
                    continue
                if not isinstance(value, dict):
                    raise ConfigError(f"{source}: {key}: expected a mapping, got {value!r}")
                section = getattr(cfg, key)
                names = {f.name for f in fields(section)}
                for k, v in value.items():
                    if k not in names:
                        raise ConfigError(f"{source}: unknown field '{key}.{k}' (known: "
                                          f"{', '.join(sorted(names))})")
                    setattr(section, k, v)
            else:
                setattr(cfg, key, value)
        return cfg.validate(source)

    @classmethod
    def from_yaml(cls, path: str) -> "PhysicsConfig":
        data = load_yaml_file(path)
        grid = data.get("terrain", None) if isinstance(data, dict) else None
        grid = grid.get("heightfield") if isinstance(grid, dict) else None
        if isinstance(grid, dict) and isinstance(grid.get("heights"), str):
            # (a heightfield file is found next to the configuration)
            grid["heights"] = os.path.join(os.path.dirname(str(path)), grid["heights"])
        return cls.from_dict(data, source=str(path))

    def with_overrides(self, **overrides) -> "PhysicsConfig":
        """A validated copy with fields replaced; keys are unique field names (`alpha`) or
        dotted paths (`solver.alpha`)."""
        cfg = copy.deepcopy(self)
        index = {}
        for s in self._SECTIONS:
            for f in fields(getattr(cfg, s)):
                index.setdefault(f.name, []).append(s)
        for key, value in overrides.items():
            if "." in key:
                sec, _, name = key.partition(".")
                names = {f.name for f in fields(getattr(cfg, sec))} \
                    if sec in self._SECTIONS else ()
                if name not in names:
                    raise ConfigError(f"override '{key}': no such field")
                setattr(getattr(cfg, sec), name, value)
            elif key in {f.name for f in fields(cfg)} and not key.startswith("_"):
                if key in self._SECTIONS:
                    raise ConfigError(f"override '{key}': give the section's fields instead")
                setattr(cfg, key, value)
            elif key in index:
                if len(index[key]) > 1:
                    raise ConfigError(f"override '{key}': ambiguous, use one of "
                                      f"{[s + '.' + key for s in index[key]]}")
                setattr(getattr(cfg, index[key][0]), key, value)
            else:
                raise ConfigError(f"override '{key}': no such field")
        return cfg.validate(f"{cfg.name} (with overrides)")

    def with_overlay(self, name_or_path: str, kind: str) -> "PhysicsConfig":
        """A validated copy with an overlay file's section applied over this configuration
        (the fields it gives replace these; the others stay): kind "sensors"
        (msg_configs/sensors/<name>.yaml, a `sensors:` section) or "actuators"
        (msg_configs/actuators/<name>.yaml, an `actuator:` section); a name of those or a
        path. ConfigError naming the file and the field."""
        if kind not in OVERLAY_SECTIONS:
            raise ConfigError(f"overlay kind {kind!r}: expected one of "
                              f"{', '.join(OVERLAY_SECTIONS)}")
        path = overlay_path(name_or_path, kind)
        section = OVERLAY_SECTIONS[kind]
        data = load_yaml_file(path)
        if not isinstance(data, dict) or not isinstance(data.get(section), dict) or \
                set(data) - {section, "description"}:
            raise ConfigError(f"{path}: expected a mapping with a '{section}:' section (and "
                              f"optionally a description), got keys "
                              f"{sorted(data) if isinstance(data, dict) else data!r:.80}")
        cfg = copy.deepcopy(self)
        target = getattr(cfg, section)
        names = {f.name for f in fields(target)}
        for k, v in data[section].items():
            if k not in names:
                raise ConfigError(f"{path}: unknown field '{section}.{k}' (known: "
                                  f"{', '.join(sorted(names))})")
            setattr(target, k, v)
        return cfg.validate(path)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["ground"]["normal"] = list(d["ground"]["normal"])
        d["contact"]["restitution_overrides"] = {k: list(v) for k, v in
                                                 d["contact"]["restitution_overrides"].items()}
        d["terrain"] = self.terrain.to_dict()
        d["sensors"] = self.sensors.to_dict()
        return d


def config_dir() -> str:
    return os.path.join(package_share_dir(), "msg_configs")


#: the overlay files (PhysicsConfig.with_overlay): kind -> the section they hold; a kind's
#: shipped files are msg_configs/<kind>/<name>.yaml
OVERLAY_SECTIONS = {"sensors": "sensors", "actuators": "actuator"}


def overlay_path(name_or_path: str, kind: str) -> str:
    """The file of an overlay: a path (a relative one that is not a file here is looked for
    in msg_configs/<kind>/), or the name of a shipped one (ConfigError naming those)."""
    d = os.path.join(config_dir(), kind)
    if os.path.sep in name_or_path or name_or_path.endswith((".yaml", ".yml")):
        shipped = os.path.join(d, name_or_path)
        if not os.path.isabs(name_or_path) and not os.path.exists(name_or_path) and \
                os.path.isfile(shipped):
            return shipped
        return name_or_path
    path = os.path.join(d, f"{name_or_path}.yaml")
    if not os.path.isfile(path):
        have = sorted(os.path.splitext(f)[0] for f in os.listdir(d)
                      if f.endswith(".yaml")) if os.path.isdir(d) else []
        raise ConfigError(f"unknown {kind} file '{name_or_path}' (available in "
                          f"msg_configs/{kind}/: {', '.join(have) or 'none'})")
    return path


#: The 11 configurations of the paper's Table 1, in its order: the presets in msg_configs/
#: (C compliant, H hard; m/E/M minimal, extended, maximal coordinates; J/S JOR or SOR prox;
#: D/P bilateral constraints direct or by prox).
PRESETS = ("Cm", "HmJ", "HmS", "HEJD", "HEJP", "HESD", "HESP", "HMJD", "HMJP", "HMSD", "HMSP")


def available_presets() -> list[str]:
    """The names of the preset files in msg_configs/ (PRESETS, and any a user added)."""
    d = config_dir()
    return sorted(os.path.splitext(f)[0] for f in os.listdir(d)
                  if f.endswith(".yaml") and not f.startswith("sim_node")
                  and _is_physics_file(os.path.join(d, f)))


def _is_physics_file(path):
    try:
        data = load_yaml_file(path)
    except ConfigError:
        return False
    return isinstance(data, dict) and "contact_model" in data


def load_preset(name_or_path: str) -> PhysicsConfig:
    """A preset name from msg_configs/ (e.g. 'HmJ') or the path of a YAML file; a relative
    path that is not a file here is looked for in msg_configs/ (the shipped terrains:
    'terrain/stairs.yaml')."""
    if os.path.sep in name_or_path or name_or_path.endswith((".yaml", ".yml")):
        shipped = os.path.join(config_dir(), name_or_path)
        if not os.path.isabs(name_or_path) and not os.path.exists(name_or_path) and \
                os.path.isfile(shipped):
            return PhysicsConfig.from_yaml(shipped)
        return PhysicsConfig.from_yaml(name_or_path)
    path = os.path.join(config_dir(), f"{name_or_path}.yaml")
    if not os.path.exists(path):
        raise ConfigError(f"unknown physics preset '{name_or_path}' (available: "
                          f"{', '.join(available_presets())})")
    return PhysicsConfig.from_yaml(path)
