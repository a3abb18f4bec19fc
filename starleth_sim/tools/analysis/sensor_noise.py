"""Measured against true for ``starleth-analyze``: where a bag has the ground_truth/ topics
(sim_node with noisy sensors), the error of every measured signal (joint_states, the IMU,
the foot contacts) against the exact one, its standard deviation and mean (bias) beside
what the recorded sensors configuration gives (physics/sensors.py; doc/sensors.md).

The measured value of control step k is compared with the exact one of the sample it
holds: step k − delay, and at the IMU's sample steps (a multiple of its every-th step) when
it is slower than the control rate. The standard deviation is taken per channel (an axis,
a joint, a foot) about the channel's mean and pooled (the root of the mean variance), so a
constant bias shows in the mean and not in σ. Expected σ: the white noise's (IMU: density
√rate; a bias random walk adds to it over long runs); encoders √(σ² + Δ²/12) with the
quantum Δ = 2π/counts (exact when σ is well above Δ/4 or zero); the filtered velocity has no
σ of its own (its error, the filter's lag and the noise, is given as RMS).

The IMU's bias random walk (density q) is measured from the error's means over windows of
WALK_WINDOW seconds: two adjacent windows' means differ by Var = q² 2W/3 (a Wiener process
averaged over each) plus the white noise's 2σ²/n (n samples a window, σ from the
sample-to-sample differences); disjoint pairs of windows give independent differences, so
q̂² = (mean d² − 2σ²/n) 3/(2W) over 3 axes x the pairs is a chi-square estimate
(``bias_walk``; the test's band: doc/sensors.md).
"""
from __future__ import annotations

import json
import math

import numpy as np

from starleth_interface.yaml_files import load_yaml_text

from ...physics.config import ConfigError, PhysicsConfig
from ..common.bag import BagError, read_messages

#: the signals compared; the metadata keys of the measured and exact topics; units
SIGNALS = ("gyro", "accel", "orientation", "joint_position", "joint_velocity",
           "joint_effort", "contact_force", "contact_flag")
_TOPIC_KEYS = {"joints": ("joint_states_topic", "ground_truth_joint_states_topic"),
               "imu": ("imu_topic", "ground_truth_imu_topic"),
               "contacts": ("foot_contacts_topic", "ground_truth_foot_contacts_topic")}
UNITS = {"gyro": "rad/s", "accel": "m/s^2", "orientation": "rad", "joint_position": "rad",
         "joint_velocity": "rad/s", "joint_effort": "N m", "contact_force": "N",
         "contact_flag": ""}


def expected_sigma(c, control_rate: float) -> dict:
    """The configured σ of each signal's error (None: none configured as a σ)."""
    rate = c.imu_rate or control_rate
    quantum = 2 * math.pi / c.encoder_counts if c.encoder_counts else 0.0
    return {"gyro": c.imu_gyro_noise_density * math.sqrt(rate),
            "accel": c.imu_accel_noise_density * math.sqrt(rate),
            "orientation": c.imu_orientation_noise,
            "joint_position": math.sqrt(c.encoder_noise ** 2 + quantum ** 2 / 12),
            "joint_velocity": 0.0 if c.encoder_velocity == "exact" else None,
            "joint_effort": c.torque_noise, "contact_force": c.contact_force_noise,
            "contact_flag": None}


#: the windows of the bias walk's estimate [s]
WALK_WINDOW = 0.125


def bias_walk(e, rate: float, window: float = WALK_WINDOW) -> dict | None:
    """The bias random walk's density q̂ [unit/s/√Hz] of an error series `e` (samples x
    axes at `rate` Hz, one row per distinct sample) and the number of independent window
    differences it rests on (module docstring); None when the run is shorter than two
    windows."""
    n = max(1, int(round(window * rate)))
    pairs = len(e) // (2 * n)
    if pairs < 1:
        return None
    means = e[:2 * n * pairs].reshape(2 * pairs, n, -1).mean(axis=1)
    d = means[1::2] - means[0::2]
    white = np.diff(e, axis=0).var(axis=0).mean() / 2 if len(e) > 2 else 0.0
    scale = 3 / (2 * n / rate)
    q2 = (float((d * d).mean()) - 2 * white / n) * scale
    # the white noise's share alone scatters q̂² by this much (chi-square, d.size terms): a
    # walk below 3 of it is not resolved by the run
    floor = 3 * 2 * white / n * math.sqrt(2 / d.size) * scale
    return {"density": math.sqrt(max(q2, 0.0)), "differences": int(d.size),
            "resolved": q2 > floor, "floor": math.sqrt(floor)}


def sample_index(n: int, delay: int, every: int = 1) -> np.ndarray:
    """For each measured step k < n, the step whose exact value it holds: k − delay rounded
    down to a multiple of `every` (the first step until then)."""
    k = np.arange(n) - delay
    return np.maximum(k - k % every, 0)


def rotation_error(q_true, q_meas) -> np.ndarray:
    """The rotation vectors of q_true⁻¹ ⊗ q_meas (n x 4, x y z w) [rad], base frame."""
    x1, y1, z1, w1 = -q_true[:, 0], -q_true[:, 1], -q_true[:, 2], q_true[:, 3]
    x2, y2, z2, w2 = (q_meas[:, i] for i in range(4))
    v = np.stack([w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2, w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                  w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=1)
    w = w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2
    v *= np.sign(w + (w == 0))[:, None]
    s = np.linalg.norm(v, axis=1)
    angle = 2 * np.arctan2(s, np.abs(w))
    return v * np.where(s > 0, angle / np.where(s > 0, s, 1), 2.0)[:, None]


def noise_statistics(measured: dict, truth: dict, c, control_rate: float) -> dict:
    """{signal: {sigma, expected_sigma, mean (per channel), rms, n}} of measured − true
    (`measured`, `truth`: {signal: (steps, channels)} over the same steps k = 0, 1, ...;
    `c`: the SensorConfig the run had)."""
    n = min(len(measured["gyro"]), len(truth["gyro"]))
    imu_every = max(1, round(control_rate / (c.imu_rate or control_rate)))
    imu_at = sample_index(n, round(c.imu_delay * control_rate), imu_every)
    contact_at = sample_index(n, c.contact_delay)
    same = np.arange(n)
    expected = expected_sigma(c, control_rate)
    out = {}
    for s in SIGNALS:
        at = imu_at if s in ("gyro", "accel", "orientation") else \
            contact_at if s.startswith("contact") else same
        m, t = np.asarray(measured[s][:n], float), np.asarray(truth[s], float)[at]
        e = rotation_error(t, m) if s == "orientation" else m - t
        if s == "contact_flag":
            e = np.abs(e)
        mean = e.mean(axis=0)
        out[s] = {"sigma": float(np.sqrt(e.var(axis=0).mean())),
                  "expected_sigma": expected[s], "mean": mean.tolist(),
                  "rms": float(np.sqrt((e ** 2).mean())), "n": int(e.size)}
        if s in WALKS:
            _, first = np.unique(at, return_index=True)     # each distinct sample once
            walk = bias_walk(e[first], c.imu_rate or control_rate)
            if walk is not None:
                walk["expected_density"] = getattr(c, WALKS[s])
                out[s]["walk"] = walk
    return out


#: the signals with a bias random walk, and its field of the sensors section
WALKS = {"gyro": "imu_gyro_bias_random_walk", "accel": "imu_accel_bias_random_walk"}


def _rows(messages, period_ns, values) -> np.ndarray:
    """The messages' values by step (stamp / period), the first of a stamp."""
    by_step = {}
    for _, m in messages:
        s = m.header.stamp
        by_step.setdefault((s.sec * 1_000_000_000 + s.nanosec) // period_ns, values(m))
    n = 0
    while n in by_step:
        n += 1
    return np.array([by_step[k] for k in range(n)], dtype=float)


def _signals(bag, joints, imu, contacts, period_ns) -> dict:
    """{signal: (steps, channels)} of the joint states, IMU and foot contact topics."""
    msgs = bag.messages
    j = _rows(msgs.get(joints, ()), period_ns,
              lambda m: (*m.position, *m.velocity, *m.effort))
    i = _rows(msgs.get(imu, ()), period_ns, lambda m: (
        m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z,
        m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z,
        m.orientation.x, m.orientation.y, m.orientation.z, m.orientation.w))
    c = _rows(msgs.get(contacts, ()), period_ns, lambda m: (*m.position, *m.effort))
    nj, nf = j.shape[1] // 3, c.shape[1] // 2
    return {"joint_position": j[:, :nj], "joint_velocity": j[:, nj:2 * nj],
            "joint_effort": j[:, 2 * nj:], "gyro": i[:, :3], "accel": i[:, 3:6],
            "orientation": i[:, 6:], "contact_flag": c[:, :nf], "contact_force": c[:, nf:]}


def bag_noise(path: str, salvage: bool = False) -> dict | None:
    """The noise statistics of a bag recorded by sim_node with noisy sensors (None: the
    bag has no ground_truth/ topics); BagError on a bag whose records do not fit."""
    probe = read_messages(path, lambda _t, _y: False, salvage=salvage, on_warning=_quiet)
    md = probe.metadata.get("starleth_sim", {})
    topics = {k: (md.get(a), md.get(b)) for k, (a, b) in _TOPIC_KEYS.items()}
    if not all(t for pair in topics.values() for t in pair):
        return None
    wanted = {t for pair in topics.values() for t in pair}
    bag = read_messages(path, lambda t, _y: t in wanted, salvage=salvage, on_warning=_quiet)
    try:
        cfg = PhysicsConfig.from_dict(load_yaml_text(md["physics_config"], path), path)
        period_ns = int(md["stamp_period_ns"])
        measured, truth = (_signals(bag, *(topics[k][i] for k in _TOPIC_KEYS), period_ns)
                           for i in (0, 1))
        stats = noise_statistics(measured, truth, cfg.sensors, cfg.control_rate)
    except (ConfigError, KeyError, ValueError, IndexError, json.JSONDecodeError) as e:
        raise BagError(f"{path}: the sensor topics cannot be compared: "
                       f"{type(e).__name__}: {e}") from None
    return {"seed": cfg.sensors.seed, "signals": stats}


def _quiet(_message):
    """(the run's own reading has warned of the bag's problems already)"""


def format_noise(doc: dict) -> str:
    """The text of bag_noise's figures: one line per signal."""
    lines = [f"  sensors (measured - true, seed {doc['seed']}): sigma [expected], mean "
             "(largest |channel mean|)"]
    for s, f in doc["signals"].items():
        if s == "contact_flag":
            wrong = float(np.mean(f["mean"])) if f["mean"] else 0.0
            lines.append(f"    {s:15s} {100 * wrong:.1f} % of the flags differ from the "
                         "exact ones (normal force > 0)")
            continue
        exp = f["expected_sigma"]
        exp_text = f"[{exp:.3g}]" if exp is not None else f"(rms {f['rms']:.3g})"
        big = max((abs(x) for x in f["mean"]), default=0.0)
        walk = f.get("walk")
        walk_text = "" if walk is None else (
            f", bias walk {walk['density']:.3g} [{walk['expected_density']:.3g}] "
            f"{UNITS[s]}/s/sqrt(Hz) ({walk['differences']} window differences)"
            if walk["resolved"] else f", bias walk below {walk['floor']:.2g} (not resolved "
            f"by the run) [{walk['expected_density']:.3g}] {UNITS[s]}/s/sqrt(Hz)")
        lines.append(f"    {s:15s} {f['sigma']:.3g} {exp_text} {UNITS[s]}, mean {big:.3g}"
                     + walk_text)
    return "\n".join(lines)
