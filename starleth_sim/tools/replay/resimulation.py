"""Re-simulation of a recording for ``starleth-replay``: the recorded torques and wrenches run
through a configuration with sim_node's own calls (``SimService``), and the replayed run
compared with the recorded one, bit for bit or by where it diverges. The torques: those of
every physics step (starleth/applied_torque, ``Simulator.step_applied``: exact for impedance
commands, whose torque changes within a control period, their implicit dampers re-solved)
where the bag has them, else the
/joint_states effort (bags of before)."""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ...physics.config import ConfigError
from ...physics.simulator import Simulator
from ...ros.parameters import Settings
from ...ros.service import SimService
from ...ros.state_io import public_state, quat_to_matrix
from ..common.falls import fall_height
from .recording import (
    MEASURED_QUANTITIES,
    QUANTITIES,
    STATE_QUANTITIES,
    Recording,
    ReplayError,
    shortened,
    warn,
)

#: a replayed StarlETH has fallen with its base below this [m] (falls.fall_height)
FALL_HEIGHT = 0.3


@dataclass
class Replay:
    """A re-simulated run: the same quantities as Recording.states, for states 0..steps."""

    label: str
    config_name: str
    states: dict
    steps: int                       # steps taken (fewer than asked for if the physics failed)
    requested: int = 0               # steps asked for (all recorded ones, or --steps)
    error: str | None = None
    wall: float = 0.0
    iterations: np.ndarray = field(default_factory=lambda: np.zeros(0))


def _body_twist(quat, v_world):
    """The linear twist as sim_node publishes it: in the base frame, R^T v."""
    return quat_to_matrix(*quat).T @ v_world


def _measured(sensors) -> dict:
    """The sensor topics' values of the current state (MEASURED_QUANTITIES' layouts)."""
    m = sensors.measured
    return {"measured_joint_states": np.concatenate((m.joint_position, m.joint_velocity,
                                                     m.joint_effort)),
            "imu": np.concatenate((m.imu_orientation, m.imu_angular_velocity,
                                   m.imu_linear_acceleration)),
            "foot_contacts": np.concatenate((m.contact_flag, m.contact_force))}


def _snapshot(sim, feet, sensors=None):
    """The recorded quantities of the current state (the sensor topics' with `sensors`)."""
    pub = public_state(sim)
    quat = [float(x) for x in pub["base_orientation"]]
    cs = {c.name: c for c in sim.contacts}
    forces = np.concatenate([cs[f].force for f in feet]).astype(float)
    return {"joint_positions": pub["joint_positions"],
            "joint_velocities": pub["joint_velocities"],
            "base_position": pub["base_position"],
            "base_orientation": np.array(quat),
            "base_linear_velocity": _body_twist(quat, pub["base_linear_velocity"]),
            "base_angular_velocity": pub["base_angular_velocity"],
            "foot_forces": forces, **(_measured(sensors) if sensors is not None else {})}


def resimulate(rec: Recording, config=None, label=None, steps=None) -> Replay:
    """Run the recorded torques and wrenches through `config` (default: the recorded one)
    from the recorded initial state, with sim_node's own calls (SimService), on the recorded
    robot (rec.description: the bag's URDF and spec, whatever `config` names)."""
    own = config is None
    sim, cfg = _replay_simulator(rec, config)
    warnings = []
    svc = _replay_service(rec, sim, cfg, warnings)
    n = rec.steps if steps is None else min(steps, rec.steps)
    applied = _applied_torques(rec, sim, cfg)
    quantities = [q for q in QUANTITIES + MEASURED_QUANTITIES if q in rec.states]
    out = {q: np.full((n + 1,) + rec.states[q].shape[1:], np.nan) for q in quantities}
    first = _snapshot(sim, rec.feet, svc.sensors)
    for q in quantities:
        out[q][0] = first[q]
    its = np.zeros(n)
    error = None
    t0 = time.perf_counter()
    k = 0
    for k in range(n):
        for link, f, m, persistent in rec.wrenches.get(k, ()):
            svc.submit_wrench(link, f, m, persistent)
        svc.command = rec.effort[k + 1] if applied is None else applied[k + 1]
        d = svc.step()
        if d is None:
            error = warnings[-1] if warnings else f"the physics failed at step {k}"
            break
        its[k] = d.iterations
        snap = _snapshot(sim, rec.feet, svc.sensors)
        for q in quantities:
            out[q][k + 1] = snap[q]
    else:
        k = n
    done = k
    return Replay(label=label or (cfg.name + (" (replay)" if own else "")),
                  config_name=cfg.name, states={q: a[:done + 1] for q, a in out.items()},
                  steps=done, requested=n, error=error, wall=time.perf_counter() - t0,
                  iterations=its[:done])


def _replay_simulator(rec, config):
    """(Simulator, config) of the replay: `config` (None: the recorded one, its torques
    not derated again) on the recorded robot, at the recording's control period."""
    own = config is None
    cfg = rec.config() if own else config.with_overrides(robot=rec.description.name)
    if abs(cfg.control_period - rec.control_period) > 1e-12:
        raise ReplayError(f"{cfg.name}: control period {cfg.control_period * 1e3:g} ms, the "
                          f"recording's is {rec.control_period * 1e3:g} ms: the torque stream "
                          "does not fit (override control_rate)")
    if own:   # the recorded torques are the applied ones: derating them again would differ
        cfg = cfg.with_overrides(**{"actuator.velocity_limit": "ignore"})
    try:
        return Simulator(cfg, description=rec.description), cfg
    except ConfigError:
        raise
    except Exception as e:   # the robot's URDF (a path in the recorded configuration)
        raise ReplayError(f"{cfg.name}: no simulator of this configuration: "
                          f"{type(e).__name__}: {shortened(str(e))}") from None


def _replay_service(rec, sim, cfg, warnings):
    """sim_node's SimService over `sim` from the recorded initial state (through the
    minimal coordinates where the recording's set is another); its warnings to
    `warnings`, one per problem."""
    init = rec.initial
    try:
        if init.get("coordinates") == cfg.coordinates and "q" in init:
            q0, u0 = np.array(init["q"], dtype=float), np.array(init["u"], dtype=float)
        else:
            sim.reset(init["q_minimal"], init["u_minimal"], minimal=True)
            q0, u0 = sim.q, sim.u
        # the longest throttle period sim_node's parameter allows (and sim_node's frame
        # prefix: a wrench may name its link by its frame)
        settings = Settings(mode="lockstep", warn_throttle_period=3600.0,
                            tf_frame_prefix=rec.frame_prefix)
        return SimService(sim, settings, q0, u0, warn=warnings.append)
    except (ValueError, TypeError, KeyError, IndexError) as e:
        raise ReplayError(f"{rec.path}: the recorded initial_state does not fit "
                          f"{cfg.name}: {type(e).__name__}: {shortened(str(e))}") from None


def _applied_torques(rec, sim, cfg):
    """The applied torque of each physics step where the bag has it (an impedance run: the
    torque changes within a control period) and it fits this configuration, with the
    implicit dampers' replay rows where this simulator has implicit dampers; None: the
    torques of /joint_states (said where the bag's rows do not fit)."""
    applied = rec.applied if rec.applied is not None and \
        rec.applied.shape[1] == cfg.steps_per_control else None
    if applied is not None and rec.replay is not None and sim.stepper.implicit_dampers:
        applied = rec.replay
    if rec.applied is not None and applied is None:
        warn(f"{cfg.name}: {cfg.steps_per_control} physics steps per control "
             f"period, the recording's applied torques have {rec.applied.shape[1]}: "
             "replaying the torques of /joint_states")
    return applied


@dataclass
class Comparison:
    identical: bool
    steps: int                        # steps compared
    first_step: int | None = None     # first state k (1..steps) where a state quantity differs
    first_quantities: dict = field(default_factory=dict)   # quantity -> max |Δ| at that step
    max_abs: dict = field(default_factory=dict)            # quantity -> max |Δ| over the run
    forces_identical: bool = True


def compare_exact(rec: Recording, rep: Replay) -> Comparison:
    """Bit for bit, state by state (NaN equals NaN: a foot wrench missing in both); the
    sensor topics (MEASURED_QUANTITIES) where the bag has them, as the state."""
    n = rep.steps
    first, maxabs = None, {}
    compared = STATE_QUANTITIES + tuple(q for q in MEASURED_QUANTITIES if q in rep.states)
    for q in QUANTITIES + MEASURED_QUANTITIES:
        if q not in rep.states:
            continue
        a, b = rec.states[q][:n + 1], rep.states[q][:n + 1]
        same = (a.view(np.int64) == b.view(np.int64)) | (np.isnan(a) & np.isnan(b))
        bad = np.flatnonzero(~same.all(axis=1))
        diff = np.abs(a - b)
        maxabs[q] = float(np.nanmax(diff)) if diff.size and np.isfinite(diff).any() else 0.0
        if q in compared and bad.size and (first is None or bad[0] < first):
            first = int(bad[0])
    forces_same = np.array_equal(rec.states["foot_forces"][:n + 1],
                                 rep.states["foot_forces"][:n + 1], equal_nan=True)
    at = {}
    if first is not None:
        for q in compared:
            d = np.abs(rec.states[q][first] - rep.states[q][first])
            if np.any(d > 0) or np.any(np.isnan(d)):
                at[q] = float(np.nanmax(d))
    identical = first is None and rep.steps == rep.requested and rep.error is None
    return Comparison(identical=identical, steps=n, first_step=first, first_quantities=at,
                      max_abs=maxabs, forces_identical=forces_same)


def divergence(rec: Recording, rep: Replay, position=0.01, angle=0.05) -> dict:
    """Where an open-loop replay leaves the recorded run: the first time the base is more
    than `position` [m] from its recorded position or a joint more than `angle` [rad] from
    its recorded angle; with the largest differences, the final ones and whether the
    replayed robot fell (base below FALL_HEIGHT, scaled to the robot's standing height, or
    tilted more than 60°)."""
    n = rep.steps
    dp = np.linalg.norm(rec.states["base_position"][:n + 1] - rep.states["base_position"][:n + 1],
                        axis=1)
    dq = np.abs(rec.states["joint_positions"][:n + 1]
                - rep.states["joint_positions"][:n + 1]).max(axis=1)
    off = np.flatnonzero((dp > position) | (dq > angle))
    o = rep.states["base_orientation"][:n + 1]
    tilt = np.degrees(np.arccos(np.clip(1 - 2 * (o[:, 0] ** 2 + o[:, 1] ** 2), -1, 1)))
    z = rep.states["base_position"][:n + 1, 2]
    fallen = np.flatnonzero((z < fall_height(rec.description, FALL_HEIGHT)) | (tilt > 60.0))
    fz_rec = rec.states["foot_forces"][:n + 1, 2::3]
    fz_rep = rep.states["foot_forces"][:n + 1, 2::3]
    return {"steps": n, "diverges_at": float(off[0] * rec.control_period) if off.size else None,
            "fell_at": float(fallen[0] * rec.control_period) if fallen.size else None,
            "base_max_m": float(dp.max()), "base_final_m": float(dp[-1]),
            "joint_max_rad": float(dq.max()), "joint_rms_rad": float(np.sqrt(np.mean(
                (rec.states["joint_positions"][:n + 1]
                 - rep.states["joint_positions"][:n + 1]) ** 2))),
            "foot_force_rms_n": float(np.sqrt(np.nanmean((fz_rec - fz_rep) ** 2))),
            "iterations_mean": float(rep.iterations.mean()) if rep.iterations.size else 0.0,
            "error": rep.error}

