"""The state estimate's error against ground truth, for ``starleth-analyze``: a bag with
``estimator/odometry`` (controller_node ``state_source:=estimator``) and
``starleth/base_state`` (the simulator's ground truth) gives, over the stamps both carry,

* velocity RMS [m/s]: √mean |v̂ − v|² of the base velocity (world frame; both Odometry
  twists are in the base frame, turned by their own orientations);
* position drift per metre walked [%]: the horizontal position error's change from the
  first stamp to the last, |e_xy(end) − e_xy(start)|, over the horizontal distance the
  base walked (the truth's path length); the start's offset (the estimator starts above
  the origin) does not count;
* yaw drift [deg]: the heading error's change from the first stamp to the last;

and a plot of the errors over time (``estimator_error.png``). A bag without
``estimator/odometry`` gives nothing (no line, no plot).
"""
from __future__ import annotations

import math
import os

import numpy as np

from starleth_interface.topics import TOPIC_BASE_STATE, TOPIC_ESTIMATOR_ODOMETRY, namespace_of

from ..common.bag import read_messages

ODOMETRY = "nav_msgs/msg/Odometry"


def _rotations(q):
    """R (n, 3, 3), base → world, of quaternions (n, 4) x, y, z, w."""
    x, y, z, w = q.T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w),
                               2 * (x * z + y * w)], -1),
                     np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z),
                               2 * (y * z - x * w)], -1),
                     np.stack([2 * (x * z - y * w), 2 * (y * z + x * w),
                               1 - 2 * (x * x + y * y)], -1)], -2)


def odometry_arrays(msgs) -> dict:
    """{stamp ns: (position, orientation xyzw, linear velocity in the world)} of Odometry
    messages (twist in the child frame, as both topics carry it)."""
    rows = {}
    for m in msgs:
        s = m.header.stamp
        p, q = m.pose.pose.position, m.pose.pose.orientation
        v = m.twist.twist.linear
        rows[s.sec * 1_000_000_000 + s.nanosec] = (p.x, p.y, p.z, q.x, q.y, q.z, q.w,
                                                   v.x, v.y, v.z)
    return rows


def error_series(truth: dict, estimate: dict) -> dict | None:
    """The errors over the stamps of both (odometry_arrays' dicts): t [s from the first],
    v_err (n, 3) [m/s], r_err (n, 3) [m], yaw_err (n,) [rad], and the figures
    velocity_rms, distance, drift (a share of the distance), yaw_drift_deg; None without
    at least two common stamps."""
    stamps = sorted(set(truth) & set(estimate))
    if len(stamps) < 2:
        return None
    a = np.array([truth[s] for s in stamps])
    b = np.array([estimate[s] for s in stamps])
    Ra, Rb = _rotations(a[:, 3:7]), _rotations(b[:, 3:7])
    v_err = np.einsum("nij,nj->ni", Rb, b[:, 7:10]) - np.einsum("nij,nj->ni", Ra, a[:, 7:10])
    r_err = b[:, 0:3] - a[:, 0:3]
    yaw_err = np.unwrap(np.arctan2(Rb[:, 1, 0], Rb[:, 0, 0]) -
                        np.arctan2(Ra[:, 1, 0], Ra[:, 0, 0]))
    distance = float(np.sum(np.linalg.norm(np.diff(a[:, 0:2], axis=0), axis=1)))
    drift_m = float(np.linalg.norm(r_err[-1, :2] - r_err[0, :2]))
    return {"t": (np.array(stamps) - stamps[0]) * 1e-9, "v_err": v_err, "r_err": r_err,
            "yaw_err": yaw_err,
            "velocity_rms": float(np.sqrt(np.mean(np.sum(v_err * v_err, axis=1)))),
            "distance": distance, "drift_m": drift_m,
            "drift": drift_m / distance if distance > 0 else math.nan,
            "yaw_drift_deg": math.degrees(float(yaw_err[-1] - yaw_err[0])),
            "stamps": len(stamps)}


def read_errors(path: str, salvage: bool = False) -> dict | None:
    """error_series of a bag's estimator/odometry against its starleth/base_state (in one
    namespace); None when the bag has no estimate."""
    def select(topic, type_name):
        return type_name == ODOMETRY and any(
            namespace_of(topic, rel) is not None
            for rel in (TOPIC_BASE_STATE, TOPIC_ESTIMATOR_ODOMETRY))

    bag = read_messages(path, select, salvage, on_warning=lambda _: None)
    by_ns = {}
    for topic, rows in bag.messages.items():
        for rel in (TOPIC_BASE_STATE, TOPIC_ESTIMATOR_ODOMETRY):
            ns = namespace_of(topic, rel)
            if ns is not None:
                by_ns.setdefault(ns, {})[rel] = odometry_arrays(m for _, m in rows)
    for topics in by_ns.values():
        if len(topics) == 2:
            return error_series(topics[TOPIC_BASE_STATE], topics[TOPIC_ESTIMATOR_ODOMETRY])
    return None


def format_errors(label: str, e: dict) -> str:
    drift = "n/a (no distance walked)" if math.isnan(e["drift"]) else \
        f"{100 * e['drift']:.2f} % ({e['drift_m']:.3f} m over {e['distance']:.2f} m)"
    return (f"{label}: state estimate vs ground truth ({e['stamps']} stamps): velocity RMS "
            f"{e['velocity_rms']:.4f} m/s, position drift {drift}, yaw drift "
            f"{e['yaw_drift_deg']:+.2f} deg")


def plot_errors(plt, errors: dict):
    """The figure of the errors over time of {label: error_series}."""
    fig, ax = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for label, e in errors.items():
        t = e["t"]
        ax[0].plot(t, np.linalg.norm(e["v_err"], axis=1), label=label)
        ax[1].plot(t, np.linalg.norm(e["r_err"][:, :2] - e["r_err"][0, :2], axis=1),
                   label=label)
        ax[2].plot(t, np.degrees(e["yaw_err"] - e["yaw_err"][0]), label=label)
    ax[0].set_ylabel("|v̂ − v| [m/s]")
    ax[1].set_ylabel("horizontal drift [m]")
    ax[2].set_ylabel("yaw drift [deg]")
    ax[2].set_xlabel("t [s] (from the first estimate)")
    ax[0].set_title("state estimate (estimator/odometry) vs ground truth (starleth/base_state)")
    for a in ax:
        a.grid(True, alpha=0.3)
    ax[0].legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    return fig


def report(runs, out_dir, dpi, load_pyplot, salvage=False) -> tuple[dict, dict]:
    """starleth-analyze's part: prints one line per run (run.Run) whose bag has an estimate
    (read again for its two topics; the others are not), plots them into `out_dir` (None:
    no plot); ({label: figures}, {plot name: path})."""
    errors = {}
    for r in runs:
        if any(namespace_of(t, TOPIC_ESTIMATOR_ODOMETRY) is not None for t in r.counts):
            e = read_errors(r.path, salvage)
            if e is not None:
                errors[r.label] = e
    for label, e in errors.items():
        print(format_errors(label, e))
    if not errors or out_dir is None:
        return _figures(errors), {}
    plt = load_pyplot()
    fig = plot_errors(plt, errors)
    os.makedirs(out_dir, exist_ok=True)
    path = os.path.join(out_dir, "estimator_error.png")
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return _figures(errors), {"estimator_error": path}


def _figures(errors):
    keys = ("velocity_rms", "distance", "drift_m", "drift", "yaw_drift_deg", "stamps")
    return {label: {k: e[k] for k in keys} for label, e in errors.items()}
