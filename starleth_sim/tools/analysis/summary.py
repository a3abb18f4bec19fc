"""The summary of a recorded run for ``starleth-analyze``, apart from the plots: the figures
(contact forces and stance phases, base path and speeds, joint torques against the effort
limits, solver iterations, real-time factors, sim_node's parameters and counters), their
text and their JSON form."""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np

from ...physics.description import urdf_path
from .run import Run, float_or_nan

G = 9.81


def quat_rotate(q, v):
    """Rotate vectors v (n, 3) by unit quaternions q (n, 4: x y z w)."""
    u, w = q[:, :3], q[:, 3:4]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def horizontal_velocity(run: Run, twist_frame: str = "auto"):
    """(t, world-frame v_x, v_y) of the base from the Odometry twist."""
    s = run.series("base")
    d = s["data"]
    q, v = d[:, 3:7], d[:, 7:10]
    frame = twist_frame
    if frame == "auto":
        parent, child = run.base_frames
        frame = "parent" if (not child or child == parent) else "child"
    if frame == "child":
        n = np.linalg.norm(q, axis=1, keepdims=True)
        n[n == 0] = 1.0
        v = quat_rotate(q / n, v)
    return s["t"], v[:, 0], v[:, 1], frame


def stance_intervals(t, fz, threshold=5.0, min_phase=0.02):
    """Stance intervals [(t_start, t_end)] where fz > threshold; swing gaps and stance blips
    shorter than min_phase [s] are removed (gaps merged first, also at the ends). Returns
    (intervals, touchdowns) where a touchdown is a stance interval that does not begin at
    the first sample."""
    t = np.asarray(t, dtype=float)
    if t.size == 0:
        return [], 0
    dt = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    s = np.asarray(fz) > threshold
    d = np.diff(np.concatenate(([0], s.astype(np.int8), [0])))
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1
    iv = [[t[a], t[b] + dt, a] for a, b in zip(starts, ends, strict=True)]
    merged = []
    for x in iv:
        if merged and x[0] - merged[-1][1] < min_phase - 1e-12:
            merged[-1][1] = x[1]
        else:
            merged.append(x)
    # a swing shorter than min_phase at either end (e.g. the first sample of a recording,
    # before any contact force was computed) is no phase of its own either
    if merged and 0 < merged[0][0] - t[0] < min_phase - 1e-12:
        merged[0][0], merged[0][2] = t[0], 0
    if merged and 0 < t[-1] + dt - merged[-1][1] < min_phase - 1e-12:
        merged[-1][1] = t[-1] + dt
    kept = [x for x in merged if x[1] - x[0] >= min_phase - 1e-12 or x[2] == 0
            or x[1] >= t[-1] + dt - 1e-12]
    touchdowns = sum(1 for x in kept if x[2] > 0)
    return [(a, b) for a, b, _ in kept], touchdowns


def urdf_info(urdf: str | None):
    """(total mass [kg], {joint: effort limit [N m]}) from URDF text, or (None, {})."""
    if not urdf:
        return None, {}
    try:
        root = ET.fromstring(urdf)
    except ET.ParseError:
        return None, {}
    mass = 0.0
    for link in root.iter("link"):
        m = link.find("inertial/mass")
        if m is not None:
            mass += float_or_nan(m.get("value"))
    limits = {}
    for j in root.iter("joint"):
        lim = j.find("limit")
        if lim is not None and lim.get("effort") is not None:
            limits[j.get("name")] = float_or_nan(lim.get("effort"))
    return (mass if math.isfinite(mass) and mass > 0 else None), limits


def package_urdf():
    """The package's URDF text, or None where it cannot be read."""
    try:
        with open(urdf_path()) as f:
            return f.read()
    except Exception:
        return None


def real_time_factor(run: Run) -> dict:
    """What the bag says about sim time vs wall time (see the module docstring)."""
    out = {"source": None, "value": None}
    ref = None
    for key in run.timed_series():
        s = run.series_by_key[key]
        if s["t"].size > 1:
            ref = s
            break
    if ref is not None:
        stamp = ref["stamp"]
        for name, label in (("pub", "publish_time"), ("log", "log_time")):
            wall = ref[name]
            if wall.any() and not np.array_equal(wall, stamp):
                d_wall = (wall[-1] - wall[0]) * 1e-9
                d_sim = (stamp[-1] - stamp[0]) * 1e-9
                if d_wall > 0 and d_sim > 0:
                    out.update(source=label, value=d_sim / d_wall,
                               sim=(stamp - stamp[0]) * 1e-9, wall=(wall - wall[0]) * 1e-9,
                               t=ref["t"])
                    break
    s = run.series("solver")
    st = s["data"][:, 3] if s["t"].size else np.zeros(0)
    ok = np.isfinite(st)
    cp = run.control_period
    if ok.sum() > 0 and st[ok].sum() > 0 and math.isfinite(cp):
        out["compute"] = {"value": cp * ok.sum() / st[ok].sum(),
                          "mean_step_time": float(st[ok].mean()),
                          "max_step_time": float(st[ok].max()),
                          "t": s["t"][ok], "wall": np.cumsum(st[ok]),
                          "sim": np.arange(1, ok.sum() + 1) * cp}
    summ = run.sim_node_summary()
    pm = float_or_nan(summ.get("period_mean_ms"))
    if math.isfinite(pm) and pm > 0 and math.isfinite(cp):
        out["loop"] = {"value": cp * 1e3 / pm, "period_mean_ms": pm}
    return out



def summarise(run: Run, threshold=5.0, min_phase=0.02, twist_frame="auto") -> dict:
    """The numbers of the text summary (also written by --json)."""
    S = {"label": run.label, "path": run.path, "file_size": run.file_size,
         "messages": run.messages, "read_seconds": round(run.read_seconds, 3),
         "robot": run.robot, "feet_order": list(run.feet),
         "truncated": run.truncated, "missing_topics": list(run.missing),
         "topics": {n: run.counts.get(n, 0) for n in run.topic_names.values()},
         "window": list(run.window)}
    ts = [run.series_by_key[k]["t"] for k in run.series_by_key if run.series_by_key[k]["t"].size]
    if ts:
        t_start, t_end = min(float(t[0]) for t in ts), max(float(t[-1]) for t in ts)
        S["sim_time"] = {"start": t_start, "end": t_end, "duration": t_end - t_start,
                         "t0_stamp": run.t0_ns * 1e-9, "control_period": run.control_period}
    S["control_steps"] = int(run.series("joints")["t"].size)
    desc = run.description
    if desc is not None:      # the recorded robot: its spec's limits over the URDF's
        mass, mass_source = desc.total_mass, f"the bag's robot ({desc.name})"
        limits = dict(zip(desc.joint_names, np.ravel(desc.effort_limit).tolist(), strict=True))
    else:
        urdf, mass_source = run.urdf, "the bag's URDF"
        if urdf is None:
            urdf, mass_source = package_urdf(), "the package URDF (none in the bag)"
        mass, limits = urdf_info(urdf)
    S.update(_contact_summary(run, threshold, min_phase))
    if mass:
        S["mass"], S["weight"], S["mass_source"] = mass, mass * G, mass_source
    if run.has("base"):
        S["base"] = _base_summary(run, twist_frame)
    if run.series("joints")["t"].size:
        S["joints"] = _joint_summary(run, limits)
    if run.has("solver"):
        S["solver"] = _solver_summary(run)
    S["real_time_factor"] = _rtf_summary(run)
    S.update(_sim_node_summary(run))
    return S


def _contact_summary(run: Run, threshold, min_phase) -> dict:
    """Per foot: normal force, stance fraction, touchdowns; the total mean normal force."""
    feet, total = {}, 0.0
    for foot in run.feet:
        if not run.has("wrench", foot):
            continue
        t, fz = run.normal_force(foot)
        iv, td = stance_intervals(t, fz, threshold, min_phase)
        dur = (t[-1] - t[0] + run.control_period) if t.size > 1 else 0.0
        stance = sum(b - a for a, b in iv)
        feet[foot] = {"mean_normal_force": float(fz.mean()), "max_normal_force": float(fz.max()),
                      "stance_fraction": float(stance / dur) if dur > 0 else math.nan,
                      "touchdowns": int(td), "stance_phases": len(iv)}
        total += float(fz.mean())
    if not feet:
        return {}
    return {"feet": feet, "contact_threshold": threshold,
            "total_mean_normal_force": total if len(feet) == 4 else None}


def _base_summary(run: Run, twist_frame) -> dict:
    """Base path: distance, path length, speeds, heights, frames."""
    p = run.series("base")["data"][:, 0:3]
    t, vx, vy, frame = horizontal_velocity(run, twist_frame)
    sp = np.hypot(vx, vy)
    seg = np.hypot(np.diff(p[:, 0]), np.diff(p[:, 1]))
    dur = float(t[-1] - t[0]) if t.size > 1 else 0.0
    net = float(np.hypot(*(p[-1, :2] - p[0, :2])))
    return {"start": p[0].tolist(), "end": p[-1].tolist(), "distance": net,
            "path_length": float(seg.sum()),
            "mean_speed_displacement": net / dur if dur > 0 else math.nan,
            "mean_speed": float(sp.mean()), "max_speed": float(sp.max()),
            "height_min": float(p[:, 2].min()), "height_max": float(p[:, 2].max()),
            "height_mean": float(p[:, 2].mean()), "twist_frame": frame,
            "frames": list(run.base_frames)}


def _joint_summary(run: Run, limits) -> dict:
    """Joint torques: max |τ| and RMS per joint and overall, time at the effort limit."""
    e = run.series("joints")["data"]
    JOINTS = run.joint_names
    with np.errstate(invalid="ignore"):
        absmax = np.nanmax(np.abs(e), axis=0) if np.isfinite(e).any() else \
            np.full(len(JOINTS), np.nan)
        rms = np.sqrt(np.nanmean(e * e, axis=0)) if np.isfinite(e).any() else absmax
    J = {"max_abs": {n: float(x) for n, x in zip(JOINTS, absmax, strict=True)},
         "rms": {n: float(x) for n, x in zip(JOINTS, rms, strict=True)}}
    if np.isfinite(absmax).any():
        i = int(np.nanargmax(absmax))
        J["max_abs_overall"], J["max_abs_joint"] = float(absmax[i]), JOINTS[i]
        J["rms_overall"] = float(np.sqrt(np.nanmean(e * e)))
    if limits and all(n in limits for n in JOINTS):
        lim = np.array([limits[n] for n in JOINTS])
        fin = np.isfinite(e)
        with np.errstate(invalid="ignore"):
            sat = (np.abs(e) >= lim * (1 - 1e-6)) & fin
        J["at_effort_limit_fraction"] = float(sat.sum() / max(fin.sum(), 1))
        J["effort_limit"] = float(lim.max())
    if run.ignored_joints:
        J["ignored_joints"] = list(run.ignored_joints)
    return J


def _solver_summary(run: Run) -> dict:
    """Prox iterations per step (mean, median, p95, max), non-converged steps, residual."""
    d = run.series("solver")["data"]
    it = d[:, 0]
    fin = it[np.isfinite(it)]
    conv = d[:, 1]
    return {"steps": int(it.size), "iterations_mean": float(fin.mean()) if fin.size else None,
            "iterations_median": float(np.median(fin)) if fin.size else None,
            "iterations_p95": float(np.percentile(fin, 95)) if fin.size else None,
            "iterations_max": float(fin.max()) if fin.size else None,
            "nonconverged": int(np.sum(conv[np.isfinite(conv)] == 0)),
            "residual_max": float(np.nanmax(d[:, 2])) if np.isfinite(d[:, 2]).any() else None}


def _rtf_summary(run: Run) -> dict:
    rtf = real_time_factor(run)
    R = {"source": rtf["source"], "value": rtf["value"]}
    if "compute" in rtf:
        c = rtf["compute"]
        R["compute"] = c["value"]
        R["mean_step_time"] = c["mean_step_time"]
        R["max_step_time"] = c["max_step_time"]
    if "loop" in rtf:
        R["loop"] = rtf["loop"]["value"]
        R["loop_period_mean_ms"] = rtf["loop"]["period_mean_ms"]
    return R


def _sim_node_summary(run: Run) -> dict:
    """sim_node's parameters and final counters as recorded in the bag's metadata."""
    out = {}
    params = run.sim_node_parameters()
    if params:
        out["sim_node"] = {k: params.get(k) for k in ("physics", "mode", "real_time_factor")
                           if k in params}
    summ = run.sim_node_summary()
    if summ:
        out.setdefault("sim_node", {}).update(
            {k: summ[k] for k in ("steps", "lockstep_timeouts", "commands_rejected",
                                  "simulation_errors", "overruns") if k in summ})
    return out

def _f(x, fmt=".2f", none="n/a"):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return none
    return format(x, fmt)


def format_summary(S: dict) -> str:
    """The summary `S` (summarise's) as the text starleth-analyze prints."""
    L = []
    mb = S["file_size"] / 1e6
    L.append(f"== {S['label']}: {S['path']} ({mb:.1f} MB, {S['messages']} messages"
             f"{', TRUNCATED' if S['truncated'] else ''}; read in {S['read_seconds']:.2f} s) ==")
    if "sim_node" in S:
        L.append("  sim_node          " + ", ".join(f"{k} {v}" for k, v in S["sim_node"].items()))
    st = S.get("sim_time")
    if st:
        cp = st["control_period"]
        rate = f" at {1 / cp:.0f} Hz" if cp and math.isfinite(cp) and cp > 0 else ""
        L.append(f"  sim time          {st['start']:.3f} .. {st['end']:.3f} s "
                 f"({st['duration']:.3f} s; {S['control_steps']} joint states{rate})")
    if S["missing_topics"]:
        L.append(f"  missing topics    {', '.join(S['missing_topics'])}")
    L += _contact_lines(S) + _base_lines(S.get("base")) + _joint_lines(S.get("joints"))
    s = S.get("solver")
    if s:
        L.append(f"  solver            iterations per control step mean "
                 f"{_f(s['iterations_mean'], '.1f')}, median {_f(s['iterations_median'], '.0f')},"
                 f" p95 {_f(s['iterations_p95'], '.0f')}, max {_f(s['iterations_max'], '.0f')};"
                 f" not converged {s['nonconverged']} of {s['steps']}; max residual "
                 f"{_f(s['residual_max'], '.2e')}")
    L.append(_real_time_line(S["real_time_factor"]))
    return "\n".join(L)


def _contact_lines(S):
    if "feet" not in S:
        return []
    L = [f"  contact           normal force F_z [N], stance = F_z > "
         f"{S['contact_threshold']:g} N"]
    for foot, d in S["feet"].items():
        L.append(f"    {foot}   mean {d['mean_normal_force']:7.1f}   max "
                 f"{d['max_normal_force']:7.1f}   stance {100 * d['stance_fraction']:5.1f} %"
                 f"   touchdowns {d['touchdowns']}")
    tot = S.get("total_mean_normal_force")
    if tot is not None:
        line = f"    sum of means {tot:.1f} N"
        if S.get("weight"):
            line += (f" = {100 * tot / S['weight']:.1f} % of the weight "
                     f"({S['mass']:.2f} kg x {G} m/s^2 = {S['weight']:.1f} N, "
                     f"{S['mass_source']})")
        L.append(line)
    return L


def _base_lines(b):
    if not b:
        return []
    return [f"  base              start ({b['start'][0]:.2f}, {b['start'][1]:.2f}, "
            f"{b['start'][2]:.3f}) m, end ({b['end'][0]:.2f}, {b['end'][1]:.2f}, "
            f"{b['end'][2]:.3f}) m",
            f"                    distance {b['distance']:.2f} m (path {b['path_length']:.2f}"
            f" m), mean speed {b['mean_speed_displacement']:.3f} m/s by displacement, "
            f"{b['mean_speed']:.3f} m/s by twist (max {b['max_speed']:.3f})",
            f"                    height {b['height_min']:.3f} .. {b['height_max']:.3f} m"
            f" (mean {b['height_mean']:.3f}); twist frame: {b['twist_frame']}"]


def _joint_lines(j):
    if not j or "max_abs_overall" not in j:
        return []
    line = (f"  joint torques     max |tau| {j['max_abs_overall']:.2f} N m "
            f"({j['max_abs_joint']}), RMS {j['rms_overall']:.2f} N m")
    if "at_effort_limit_fraction" in j:
        line += (f"; at the effort limit ({j['effort_limit']:g} N m) "
                 f"{100 * j['at_effort_limit_fraction']:.2f} % of samples")
    return [line]


def _real_time_line(r):
    if r["source"]:
        parts = [f"{r['value']:.2f} (sim time / wall time, wall = message {r['source']})"]
    else:
        parts = ["no wall clock in the bag (message times = sim stamps)"]
    if "compute" in r:
        parts.append(f"physics compute only {r['compute']:.1f} (solver step_time mean "
                     f"{r['mean_step_time'] * 1e3:.3f} ms, max {r['max_step_time'] * 1e3:.2f} ms)")
    if "loop" in r:
        parts.append(f"realtime loop {r['loop']:.3f} (mean period "
                     f"{r['loop_period_mean_ms']:.3f} ms)")
    return "  real-time factor  " + "; ".join(parts)


def jsonable(x):
    """x for json.dump: numpy scalars as Python numbers, NaN and infinities as None."""
    if isinstance(x, dict):
        return {k: jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, np.generic):
        return jsonable(x.item())
    return x

