"""The tasks of ``starleth-eval``: each one measurement run (or a few) in a worker process,
returning one result record ({"kind": ..., ...}) for the report: Table 1's speed, Fig. 5's
contact force, Fig. 6's iterations against α, Fig. 7's time by phase, the drifts, the
push-over test, and the hard-contact rule (the sagging posture, the ball drops and the
contact-law variants compared).
"""
from __future__ import annotations

import math

import numpy as np

from ...physics.config import load_preset
from ...physics.description import RobotDescription, sphere_urdf
from ...physics.simulator import Simulator
from ..common.falls import fall_height
from ..common.gait_run import GAIT_PERIOD, STAND_BEFORE_TROT, run_gait

#: iteration cap of the α sweep: a run "converges" if no step needs more (slow convergence at
#: small α is not divergence, so the cap is generous)
FIG6_MAX_ITERATIONS = 5000


def _steps_per_second(r, window):
    """Physics steps per second per gait cycle: mean and std over the cycles of the run."""
    wall = np.asarray(r["wall"])
    per = int(round(window / r["control_period"]))
    n = len(wall) // per
    if n == 0:
        return float("nan"), float("nan")
    rates = [per * r["steps_per_control"] / wall[i * per:(i + 1) * per].sum() for i in range(n)]
    return float(np.mean(rates)), float(np.std(rates))


# ----------------------------------------------------------------------------------------------
# tasks (each runs in a worker process)
# ----------------------------------------------------------------------------------------------
def task_table1(preset, seconds):
    r = run_gait(preset, "trot", seconds, record_lf=preset in ("Cm", "HmJ"))
    trot_wall = r["wall"][int(STAND_BEFORE_TROT / r["control_period"]):]
    sps, sps_std = _steps_per_second(dict(r, wall=trot_wall), GAIT_PERIOD)
    res = dict(kind="table1", preset=preset, steps_per_second=sps, steps_per_second_std=sps_std,
               rtf=sps / (r["steps_per_control"] / r["control_period"]),
               rtf_std=sps_std / (r["steps_per_control"] / r["control_period"]),
               mean_iterations=float(np.mean(r["iterations"])) / r["steps_per_control"],
               max_iterations=int(np.max(r["iterations"])) if r["iterations"] else 0,
               nonconverged=r["nonconverged"], min_height=r["min_height"],
               distance=r["distance"], error=r["error"])
    gaps = np.array([g for g in r["foot_gap"] if g[0] > STAND_BEFORE_TROT + 1.0])
    pen = np.asarray(r["foot_penetration"][int(round(STAND_BEFORE_TROT / r["control_period"])):])
    if r["preset"] != "Cm" and len(pen):
        res["foot_penetration_mean_mm"] = float(1e3 * pen.mean())
        res["foot_penetration_max_mm"] = float(1e3 * pen.max())
        res["loaded_contacts_opened"] = r["loaded_contacts_opened"]
        res["projections"] = r["projections"]
    if len(gaps):
        res["foot_sink_mean_mm"] = float(-1e3 * gaps[:, 1].mean())
        res["foot_sink_max_mm"] = float(-1e3 * gaps[:, 2].min())
    if r["drift_t"]:
        t, g = np.array(r["drift_t"]), np.array(r["drift_g"])
        sel = t > STAND_BEFORE_TROT + 1.0
        if sel.sum() > 2:
            res["bilateral_drift_um_per_min"] = float(np.polyfit(t[sel], g[sel], 1)[0] * 60e6)
            res["bilateral_violation_max_um"] = float(g[sel].max() * 1e6)
    if "lf_t" in r:
        res["lf_t"], res["lf_force"] = r["lf_t"], r["lf_force"]
    return res


def task_fig5_damped(seconds):
    """Cm with 10x normal damping; the step must shrink 4x (paper): 8 steps per control update
    (at 4 steps the run diverges). Only d_N is raised: with d_T = 500 N s/m as well, the
    explicit tangential damper chatters on the light feet even at Δt/4."""
    r = run_gait("Cm", "trot", seconds, record_lf=True, damping_normal=500.0,
                 steps_per_control=8)
    return dict(kind="fig5", preset="Cm_d10", lf_t=r["lf_t"], lf_force=r["lf_force"],
                error=r["error"])


def task_fig7(preset, seconds):
    r = run_gait(preset, "trot", seconds, profile=True)
    return dict(kind="fig7", preset=preset, phases_us=r["phases_us"], error=r["error"])


#: the trunk height [m] below which a Fig. 6 run has fallen (StarlETH's: falls.fall_height)
FIG6_FALL_HEIGHT = 0.3


def task_fig6(preset, gait, alpha, seconds):
    kept = {}

    def keep(sim):
        kept["sim"] = sim
    r = run_gait(preset, gait, seconds, alpha=alpha, fallback_alpha_factor=0.0,
                 max_iterations=FIG6_MAX_ITERATIONS, stand_time=0.2,
                 stop_on_nonconvergence=True, perturb=keep)
    it = np.asarray(r["iterations"], dtype=float)
    ok = r["error"] is None and r["nonconverged"] == 0 and \
        r["min_height"] > fall_height(kept["sim"].description, FIG6_FALL_HEIGHT)
    return dict(kind="fig6", preset=preset, gait=gait, alpha=alpha,
                mean_iterations=float(it.mean()) if len(it) else float("nan"),
                converged=ok, nonconverged=r["nonconverged"], error=r["error"])


def task_unilateral_drift(preset, seconds):
    """Vertical drift of the unilateral foot constraints while standing (µm/min)."""
    r = run_gait(preset, "stand", seconds)
    g = np.array(r["foot_gap"])
    sel = g[:, 0] > 2.0
    slope = float(np.polyfit(g[sel, 0], g[sel, 1], 1)[0] * 60e6) if sel.sum() > 2 else float("nan")
    return dict(kind="unilateral_drift", preset=preset, drift_um_per_min=slope,
                min_gap_um=float(1e6 * g[sel, 2].min()) if sel.any() else float("nan"))


def task_bilateral_drift(preset, seconds):
    """Growth of the bilateral constraint violation while trotting (µm/min)."""
    r = run_gait(preset, "trot", seconds)
    t, g = np.array(r["drift_t"]), np.array(r["drift_g"])
    sel = t > STAND_BEFORE_TROT + 1.0
    return dict(kind="bilateral_drift", preset=preset,
                drift_um_per_min=float(np.polyfit(t[sel], g[sel], 1)[0] * 60e6),
                violation_max_um=float(g[sel].max() * 1e6), seconds=seconds)


def task_pushover(preset, seconds):
    """The paper's stress test: a push on the standing robot's trunk throws it on its side."""
    r = run_gait(preset, "stand", seconds, push=(0.5, (0.0, 700.0, 0.0), 0.1))
    it = np.asarray(r["iterations"])
    return dict(kind="pushover", preset=preset, fell=r["max_tilt"] > 1.0,
                max_tilt_deg=math.degrees(r["max_tilt"]), nonfinite=r["nonfinite"],
                error=r["error"], max_iterations=int(it.max()) if len(it) else 0,
                all_converged=r["nonconverged"] == 0, nonconverged=r["nonconverged"],
                knee_trunk_contacts=r["knee_trunk_contacts"], completed=r["error"] is None)


# ----------------------------------------------------------------------------------------------
# hard-contact rule: the sagging-posture scenario and the comparison of the contact-law variants
# ----------------------------------------------------------------------------------------------
#: the soft joint PD hold under which StarlETH sags onto its feet: τ = K_p (φ₀ − φ) − K_d φ̇,
#: clipped at ±SAG_TORQUE_LIMIT
SAG_KP, SAG_KD, SAG_TORQUE_LIMIT = 80.0, 2.0, 20.0


def pd_sag(preset, seconds=2.0, **overrides):
    """StarlETH from `reset()` under the soft joint PD hold (it sags by ~15 mm onto its
    feet). Returns the simulator and per control step: the deepest foot penetration
    max(0, −min g_N) after the step [m], the largest gap of a foot that carried a normal
    impulse in the step (a "hovering" loaded foot) [m], prox iterations, loaded contacts
    opened, and the kinetic energy [J]."""
    sim = Simulator.from_preset(preset, **overrides)
    sim.reset()
    q0 = sim.joint_positions()
    feet = [sim.contact_names.index(f) for f in sim.description.foot_names]
    n = int(round(seconds / sim.control_period))
    out = np.zeros((n, 5))
    for k in range(n):
        tau = np.clip(SAG_KP * (q0 - sim.joint_positions()) - SAG_KD * sim.joint_velocities(),
                      -SAG_TORQUE_LIMIT, SAG_TORQUE_LIMIT)
        d = sim.step(tau)
        g = sim.gaps()[feet]
        cs = sim.contacts
        loaded = [g[j] for j, i in enumerate(feet) if cs[i].impulse @ sim.stepper.ground.n > 0]
        out[k] = (max(0.0, -g.min()), max(loaded) if loaded else np.nan, d.iterations,
                  d.loaded_contacts_opened, sim.coords.kinetic_energy(sim.q, sim.u))
    return sim, out


def ball_drop(restitution, height, overrides, seconds=1.0):
    """A 1 kg ball of radius 0.1 m dropped from `height` onto the ground at Δt = 1 ms with
    the HmJ contact law (and `overrides`). Returns (v⁻, v⁺ of the impact step, highest
    rebound above the rest height [m])."""
    cfg = load_preset("HmJ").with_overrides(control_rate=1000.0, restitution_normal=restitution,
                                            tol_rel=1e-10, tol_abs=1e-12, **overrides)
    sim = Simulator(cfg, description=RobotDescription.from_urdf_xml(sphere_urdf(0.1, 1.0)))
    z_rest = sim.q[2]
    q = sim.q
    q[2] += height
    sim.reset(q)
    vz, z = [], []
    for _ in range(int(round(seconds / sim.control_period))):
        sim.step()
        vz.append(sim.u[2])
        z.append(sim.q[2] - z_rest)
    vz, z = np.array(vz), np.array(z)
    k = int(np.argmax(np.diff(vz) > 0.5))
    return float(vz[k]), float(vz[k + 1]), float(z[k + 1:].max())


#: the rules compared in the report: (label, overrides of the HmJ preset)
CONTACT_VARIANTS = (
    ("paper: g_N ≤ 0, no correction", dict(activation="paper", activation_gap=0.0,
                                           penetration_stabilization=0.0)),
    ("paper's rule, g_act = 10 µm", dict(activation="paper", activation_gap=1e-5,
                                          penetration_stabilization=0.0)),
    ("hysteresis, no correction", dict(penetration_stabilization=0.0)),
    ("hysteresis + velocity β_N = 0.2", dict(penetration_correction="velocity",
                                             penetration_stabilization=0.2)),
    ("hysteresis + velocity β_N = 1", dict(penetration_correction="velocity",
                                           penetration_stabilization=1.0)),
    ("hysteresis + projection β_N = 1 (presets)", dict()),
)


def task_contact_variant(label, overrides, seconds):
    """One contact-law variant on HmJ: the sagging posture (2 s), trotting (stand 1 s, trot
    `seconds`), and the energy of impacts (plastic and ε_N = 0.5 ball drops)."""
    _, sag = pd_sag("HmJ", 2.0, **overrides)
    r = run_gait("HmJ", "trot", STAND_BEFORE_TROT + seconds, **overrides)
    k0 = int(round(STAND_BEFORE_TROT / r["control_period"]))
    pen = np.asarray(r["foot_penetration"][k0:])
    wall = np.asarray(r["wall"])
    _, v_plastic, h_plastic = ball_drop(0.0, 0.2, overrides)
    v_minus, v_plus, apex = ball_drop(0.5, 1.0, overrides)
    return dict(kind="contact_variant", label=label, overrides=overrides,
                sag_penetration_max_mm=float(1e3 * sag[:, 0].max()),
                sag_hover_max_um=float(1e6 * np.nanmax(sag[:, 1])),
                sag_opened=int(sag[:, 3].sum()), sag_iterations=float(sag[:, 2].mean()),
                sag_final_kinetic_energy=float(sag[-1, 4]),
                trot_penetration_mean_mm=float(1e3 * pen.mean()) if len(pen) else float("nan"),
                trot_penetration_max_mm=float(1e3 * pen.max()) if len(pen) else float("nan"),
                trot_iterations=float(np.mean(r["iterations"])),
                trot_opened=r["loaded_contacts_opened"], trot_projections=r["projections"],
                trot_steps_per_second=float(len(wall) / wall.sum()) if wall.sum() else 0.0,
                trot_distance=r["distance"], error=r["error"],
                plastic_rebound_velocity=v_plastic, plastic_rebound_height_mm=1e3 * h_plastic,
                restitution_ratio=-v_plus / v_minus, restitution_apex_ratio=apex / 1.0)
