"""The ``starleth-view`` page: its data (frame times, body poses and force arrows, rounded)
and the self-contained HTML around it (meshcat's inlined viewer, the data, the player of
``page.html``)."""
from __future__ import annotations

import html
import json
import os
import re
from importlib.metadata import version

import numpy as np

from ...physics.description import RobotDescription
from ...robots.meshes import spec_package_roots
from .frames import body_poses, configurations, contact_arrows, select_frames
from .recording import PROG, Recording, ViewError
from .scene import (
    ARROW_HEAD,
    CAMERA_OFFSET,
    PAGE_TRIANGLES,
    body_frames,
    page_scale,
    robot_visuals,
    scene_commands,
)

FORMAT = "starleth-view/2"
#: decimals of the numbers in the page: positions/arrows [m], quaternions, times [s]
POSITION_DECIMALS = 4
QUATERNION_DECIMALS = 4
TIME_DECIMALS = 4
ROUNDING_TEXT = "positions and arrows to 0.1 mm, quaternions to 1e-4, times to 0.1 ms"
#: the camera target's height follows the trunk height averaged over +-this [s]
CAMERA_HEIGHT_WINDOW = 0.5
#: the page template (HTML + the player's JavaScript), beside this module; __NAME__ markers
#: are filled by render_html
PAGE_TEMPLATE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "page.html")


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


def page_times(recs, fps: float) -> np.ndarray:
    """The page's frame times [ns]: each robot's frames at fps (select_frames of its joint
    states), merged (one robot: its own)."""
    times = [r.joints.t_ns[select_frames(r.joints.t_ns, fps)] for r in recs]
    return np.unique(np.concatenate(times))


def _robot_data(rec: Recording, desc: RobotDescription, name: str, t_ns, force_scale,
                triangles: int):
    """One robot's part of the page at the frame times t_ns (its latest joint state at or
    before each, its first before it): its poses and arrows, what they come from; and its
    part of the scene: (rec, visuals, {pin joint: frame name}, name), its meshes within
    `triangles` (their package:// roots from its spec, relative paths from the bag's
    directory)."""
    samples = rec.joints.latest(t_ns)
    q = configurations(rec, desc, samples)
    meshes = (spec_package_roots(rec.spec, rec.robot),
              os.path.dirname(os.path.abspath(rec.path)))
    visuals = robot_visuals(desc, name, meshes, triangles)
    joint_ids = sorted({j for j, _, _ in visuals} | {1})   # 1: the free-flyer (trunk)
    poses, placements = body_poses(desc, q, joint_ids)
    arrows = contact_arrows(rec, desc, samples, placements, force_scale)
    if not np.isfinite(np.round(arrows, POSITION_DECIMALS)).all():
        raise ViewError(f"force scale {force_scale:g} m/N: the force arrows are too long to "
                        "write down")
    n = rec.joints.t_ns.size
    span = float(rec.joints.t_ns[-1] - rec.joints.t_ns[0]) * 1e-9
    rate = (n - 1) / span if n > 1 and span > 0 else 0.0     # all at one stamp: no rate
    shown = np.unique(samples)
    step = int(np.median(np.diff(shown))) if shown.size > 1 else 1
    poses[:, :, :3] = np.round(poses[:, :, :3], POSITION_DECIMALS)
    poses[:, :, 3:] = np.round(poses[:, :, 3:], QUATERNION_DECIMALS)
    frames = body_frames(desc, joint_ids, name)
    data = {
        "name": name, "namespace": rec.namespace, "frame_prefix": rec.frame_prefix,
        "source": os.path.basename(os.path.abspath(rec.path).rstrip(os.sep)),
        "samples": n, "sample_rate": round(rate, 3),
        "subsampling": f"1 in {step} samples" if step > 1 else "every sample",
        "bodies": [desc.model.names[j] for j in joint_ids], "tf_frames": frames,
        "trunk": joint_ids.index(1), "poses": (poses.reshape(-1) + 0.0).tolist(),
        "robot": desc.name, "feet": list(desc.foot_names),
        "has_force": [foot in rec.wrenches for foot in desc.foot_names],
        "arrows": _rounded(arrows, POSITION_DECIMALS), "urdf_source": rec.urdf_source,
    }
    scene = (rec, visuals, dict(zip(joint_ids, frames, strict=True)), name)
    return data, scene, poses[:, data["trunk"], :2]


def replay_data(robots, fps: float, force_scale: float):
    """The page's data for `robots` ([(Recording, RobotDescription, name)], name: the
    prefix of its frames in the page): the frame times, each robot's body poses and force
    arrows and what they mean; and the scene commands (the ground of the first robot's
    recording); the camera's distance and the arrows' size scaled to the largest robot
    (view_scene.page_scale)."""
    recs = [r for r, _, _ in robots]
    size = page_scale([desc for _, desc, _ in robots]).length
    t_ns = page_times(recs, fps)
    t0 = min(min(r.joints.t_ns[0], r.base.t_ns[0]) for r in recs)
    t = (t_ns - t0) * 1e-9
    triangles = PAGE_TRIANGLES // len(robots)
    parts = [_robot_data(rec, desc, name, t_ns, force_scale, triangles)
             for rec, desc, name in robots]
    sources = list(dict.fromkeys(p[0]["source"] for p in parts))
    data = {
        "format": FORMAT, "source": ", ".join(sources), "frames": int(t_ns.size), "fps": fps,
        "samples": sum(p[0]["samples"] for p in parts), "duration": round(float(t[-1]), 4),
        "t0_ns": int(t0), "t": _rounded(t, TIME_DECIMALS),     # t: seconds after t0_ns
        "robots": [p[0] for p in parts], "force_scale": force_scale,
        "arrow_head": size * ARROW_HEAD,
        "rounding": {"position": 10.0 ** -POSITION_DECIMALS,
                     "quaternion": 10.0 ** -QUATERNION_DECIMALS,
                     "time": 10.0 ** -TIME_DECIMALS},
        "camera": {"offset": [size * c for c in CAMERA_OFFSET],
                   "height_window": CAMERA_HEIGHT_WINDOW},
        "ground": {"height": recs[0].ground_height, "normal": list(recs[0].ground_normal)},
    }
    trunk_xy = np.concatenate([p[2] for p in parts])
    scene = scene_commands(recs[0], [p[1] for p in parts], trunk_xy, size)
    return data, scene


def _robot_line(robot: dict, several: bool) -> str:
    """What a robot's frames come from: its subsampling of its joint states (and, with
    several robots, its name, bag and namespace)."""
    rate = f" at {robot['sample_rate']:g} Hz" if robot["sample_rate"] else ""
    line = f"{robot['subsampling']} of the {robot['samples']} joint states{rate}"
    ns = f"namespace {robot['namespace']}" if robot["namespace"] else ""
    if several:
        where = ", ".join(x for x in (robot["source"], ns) if x)
        return f"{robot['name'] or 'robot'} ({where}): {line}"
    return (f"namespace {robot['namespace']}: " if ns else "") + line


def _info_lines(data: dict) -> tuple:
    """The page's explanation: (always shown: frames and subsampling, the force scale;
    under 'more': rounding, URDF, controls)."""
    robots = data["robots"]
    several = len(robots) > 1
    scale = data["force_scale"]
    shown = [f"{data['duration']:.2f} s · {data['frames']} frames at {data['fps']:g} fps"
             + (f", {len(robots)} robots" if several else "") + ":"]
    shown += [_robot_line(r, several) for r in robots]
    shown.append(f"green arrows: foot contact forces, {scale:g} m/N (1 m = {1 / scale:.4g} N)")
    urdfs = "; ".join(f"{r['name'] or 'robot'}: {r['urdf_source']}" if several else
                      r["urdf_source"] for r in robots)
    more = [
        "Each frame shows the latest recorded sample at or before its time (sample and "
        "hold, no interpolation); the last sample is always a frame.",
        f"Link poses: Pinocchio forward kinematics of the recorded joint_states and "
        f"starleth/base_state; rounded: {ROUNDING_TEXT}.",
        "Arrows start at the foot contact points (sphere centre minus radius along the "
        "ground normal); forces in the world frame.",
        f"URDF: {urdfs}.",
        "Mouse: drag to orbit, scroll to zoom, right-drag to pan. Keys: space play/pause, "
        "←/→ step.",
        "URL options: ?t=1.5&paused=1&speed=0.5&follow=0.",
    ]
    if several:
        more.insert(0, "Several robots: each frame shows every robot at its latest sample "
                       "at or before the frame's time (their stamps on one time line); the "
                       "camera follows their mean trunk position; the ground is the first "
                       "recording's.")
    return shown, more


def _info_html(shown, more) -> str:
    return ("<br>".join(html.escape(line, quote=False) for line in shown)
            + "<details><summary>more</summary>"
            + "<br>".join(html.escape(line, quote=False) for line in more) + "</details>")


def render_html(data: dict, scene: list) -> str:
    """The self-contained page: meshcat's viewer, the data, the player."""
    js, notices = meshcat_bundle()
    fills = {
        "TITLE": html.escape(f"{', '.join(dict.fromkeys(r['robot'] for r in data['robots']))} "
                             f"replay: {data['source']}"),
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
