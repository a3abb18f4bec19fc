"""The ``starleth-view`` page: its data (frame times, body poses and force arrows, rounded)
and the self-contained HTML around it (meshcat's inlined viewer, the data, the player of
``view_page.html``)."""
from __future__ import annotations

import html
import json
import os
import re
from importlib.metadata import version

import numpy as np

from ..physics.description import RobotDescription
from .view_frames import body_poses, configurations, contact_arrows, select_frames
from .view_recording import FEET, PROG, Recording, ViewError
from .view_scene import ARROW_HEAD, CAMERA_OFFSET, robot_visuals, scene_commands

FORMAT = "starleth-view/1"
#: decimals of the numbers in the page: positions/arrows [m], quaternions, times [s]
POSITION_DECIMALS = 4
QUATERNION_DECIMALS = 4
TIME_DECIMALS = 4
ROUNDING_TEXT = "positions and arrows to 0.1 mm, quaternions to 1e-4, times to 0.1 ms"
#: the camera target's height follows the trunk height averaged over +-this [s]
CAMERA_HEIGHT_WINDOW = 0.5
#: the page template (HTML + the player's JavaScript), beside this module; __NAME__ markers
#: are filled by render_html
PAGE_TEMPLATE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "view_page.html")


def _rounded(a, decimals) -> list:
    """A flat list of numbers rounded to `decimals` (no negative zeros)."""
    return (np.round(np.asarray(a, dtype=float).reshape(-1), decimals) + 0.0).tolist()


def _script_json(obj) -> str:
    """JSON that is safe inside a <script> element."""
    text = json.dumps(obj, separators=(",", ":"), allow_nan=False)
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


def meshcat_bundle() -> tuple:
    """(main.min.js text, its licence notices) of the installed meshcat package."""
    try:
        import meshcat
    except ImportError:
        raise ViewError("the Python package 'meshcat' is not installed (pip install meshcat): "
                        "its bundled three.js viewer is inlined into the page") from None
    base = os.path.join(os.path.dirname(meshcat.__file__), "viewer")
    js_path = os.path.join(base, "dist", "main.min.js")
    try:
        with open(js_path, encoding="utf-8") as f:
            js = f.read()
    except OSError as e:
        raise ViewError(f"cannot read meshcat's viewer {js_path}: {e.strerror or e}") from None
    notices = []
    for name in ("LICENSE", os.path.join("dist", "main.min.js.LICENSE.txt")):
        try:
            with open(os.path.join(base, name), encoding="utf-8") as f:
                notices.append(f.read().strip())
        except OSError:
            pass
    try:
        with open(os.path.join(base, "dist", "main.min.js.THIRD_PARTY_LICENSES.json")) as f:
            third = json.load(f)
        notices.append("Bundled packages: " + ", ".join(
            f"{p.get('name')} {p.get('version', '')} ({p.get('license', '?')})" for p in third))
    except (OSError, ValueError, AttributeError):
        pass
    if "</script" in js.lower():
        raise ViewError(f"{js_path} contains '</script' and cannot be inlined")
    return js, "\n\n".join(notices).replace("*/", "* /")


def replay_data(rec: Recording, desc: RobotDescription, fps: float, force_scale: float):
    """The page's data: frame times, body poses, force arrows and what they mean; and the
    scene commands."""
    frames = select_frames(rec.joints.t_ns, fps)
    q = configurations(rec, desc, frames)
    visuals = robot_visuals(desc)
    joint_ids = sorted({j for j, _, _ in visuals} | {1})   # 1: the free-flyer (trunk)
    poses, placements = body_poses(desc, q, joint_ids)
    arrows = contact_arrows(rec, desc, frames, placements, force_scale)
    if not np.isfinite(np.round(arrows, POSITION_DECIMALS)).all():
        raise ViewError(f"force scale {force_scale:g} m/N: the force arrows are too long to "
                        "write down")
    t0 = min(rec.joints.t_ns[0], rec.base.t_ns[0])
    t = (rec.joints.t_ns[frames] - t0) * 1e-9
    n = rec.joints.t_ns.size
    span = float(rec.joints.t_ns[-1] - rec.joints.t_ns[0]) * 1e-9
    rate = (n - 1) / span if n > 1 and span > 0 else 0.0     # all at one stamp: no rate
    step = int(np.median(np.diff(frames))) if frames.size > 1 else 1
    data = {
        "format": FORMAT, "source": os.path.basename(os.path.abspath(rec.path).rstrip(os.sep)),
        "namespace": rec.namespace, "frames": int(frames.size), "fps": fps,
        "samples": n, "sample_rate": round(rate, 3), "duration": round(float(t[-1]), 4),
        "t0_ns": int(t0), "t": _rounded(t, TIME_DECIMALS),     # t: seconds after t0_ns
        "bodies": [desc.model.names[j] for j in joint_ids], "trunk": joint_ids.index(1),
        "poses": [], "feet": list(FEET),
        "has_force": [foot in rec.wrenches for foot in FEET],
        "arrows": _rounded(arrows, POSITION_DECIMALS), "force_scale": force_scale,
        "arrow_head": ARROW_HEAD,
        "rounding": {"position": 10.0 ** -POSITION_DECIMALS,
                     "quaternion": 10.0 ** -QUATERNION_DECIMALS,
                     "time": 10.0 ** -TIME_DECIMALS},
        "camera": {"offset": list(CAMERA_OFFSET), "height_window": CAMERA_HEIGHT_WINDOW},
        "urdf_source": rec.urdf_source,
        "ground": {"height": rec.ground_height, "normal": list(rec.ground_normal)},
        "subsampling": f"1 in {step} samples" if step > 1 else "every sample",
    }
    poses[:, :, :3] = np.round(poses[:, :, :3], POSITION_DECIMALS)
    poses[:, :, 3:] = np.round(poses[:, :, 3:], QUATERNION_DECIMALS)
    data["poses"] = (poses.reshape(-1) + 0.0).tolist()
    scene = scene_commands(desc, visuals, rec, poses[:, data["trunk"], :2])
    return data, scene


def _info_lines(data: dict) -> tuple:
    """The page's explanation: (always shown: frames and subsampling, the force scale;
    under 'more': rounding, URDF, controls)."""
    ns = f" · namespace {data['namespace']}" if data["namespace"] else ""
    rate = f" at {data['sample_rate']:g} Hz" if data["sample_rate"] else ""
    scale = data["force_scale"]
    shown = [
        f"{data['duration']:.2f} s{ns} · {data['frames']} frames at {data['fps']:g} fps: "
        f"{data['subsampling']} of the {data['samples']} joint states{rate}",
        f"green arrows: foot contact forces, {scale:g} m/N (1 m = {1 / scale:g} N)",
    ]
    more = [
        "Each frame shows the latest recorded sample at or before its time (sample and "
        "hold, no interpolation); the last sample is always a frame.",
        f"Link poses: Pinocchio forward kinematics of the recorded joint_states and "
        f"starleth/base_state; rounded: {ROUNDING_TEXT}.",
        "Arrows start at the foot contact points (sphere centre minus radius along the "
        "ground normal); forces in the world frame.",
        f"URDF: {data['urdf_source']}.",
        "Mouse: drag to orbit, scroll to zoom, right-drag to pan. Keys: space play/pause, "
        "←/→ step.",
        "URL options: ?t=1.5&paused=1&speed=0.5&follow=0.",
    ]
    return shown, more


def _info_html(shown, more) -> str:
    return ("<br>".join(html.escape(line, quote=False) for line in shown)
            + "<details><summary>more</summary>"
            + "<br>".join(html.escape(line, quote=False) for line in more) + "</details>")


def render_html(data: dict, scene: list) -> str:
    """The self-contained page: meshcat's viewer, the data, the player."""
    js, notices = meshcat_bundle()
    fills = {
        "TITLE": html.escape(f"StarlETH replay: {data['source']}"),
        "INFO": _info_html(*_info_lines(data)),
        "LAST": str(data["frames"] - 1),
        "MESHCAT": (f"/*! meshcat's viewer (meshcat {_meshcat_version()}, "
                    f"meshcat/viewer/dist/main.min.js), inlined by {PROG}.\n\n{notices}\n*/\n"
                    + js),
        "DATA": _script_json(data),
        "SCENE": _script_json(scene),
    }
    # one pass over the template, so that nothing inside the fills is taken for a marker
    with open(PAGE_TEMPLATE, encoding="utf-8") as f:
        page = f.read()
    pieces = re.split(r"__(TITLE|INFO|LAST|MESHCAT|DATA|SCENE)__", page)
    return "".join(p if i % 2 == 0 else fills[p] for i, p in enumerate(pieces))


def _meshcat_version() -> str:
    try:
        return version("meshcat")
    except Exception:
        return "?"
