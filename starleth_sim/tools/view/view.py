"""``starleth-view``: a recorded run replayed in 3D, as one self-contained HTML file.

    starleth-view runs/demo.mcap                    # writes runs/demo.html
    starleth-view run.mcap -o replay.html --fps 30
    starleth-view rosbag2_dir/ --namespace /robot1
    starleth-view robot1.mcap robot2.mcap -o both.html   # two robots in one scene

The page needs no server and no network: meshcat's three.js viewer
(``meshcat/viewer/dist/main.min.js`` of the ``meshcat`` package, MIT licence) and the replay
data are inlined. Open it in a browser; play / pause (space), step (arrow keys), scrub with
the slider, pick a speed; the camera follows the trunk (drag to orbit, scroll to zoom).
``?t=1.5&paused=1`` in the URL shows t = 1.5 s paused (also ``speed=0.5``, ``follow=0``).

What is drawn, from the bags (MCAP files written by ``sim_node``, or rosbag2 directories of
.mcap files; topics are matched by suffix, so ``/joint_states`` and ``/robot1/joint_states``
both work), for every robot of every bag (``--namespace``: those under the namespaces
named), all in one scene on one time line (their stamps), each robot's bodies named by their
frames on /tf (``robot1/base``: the prefix its base state's child frame has):

* the robot the bag recorded (``sim_node``'s 'starleth_sim' metadata: its URDF and spec
  attachments, robots.recorded_description), else the URDF of its ``robot_description``
  topic, of a .urdf attachment, or the package's ``urdf/starleth.urdf``: its URDF visuals
  (boxes, spheres, cylinders, and meshes: STL, DAE, OBJ, at most
  view_scene.PAGE_TRIANGLES triangles in a page, larger ones simplified; a mesh that cannot
  be read: one warning, the link's collision primitives); the page's title names it;
* link poses from Pinocchio forward kinematics of a free-flyer model of that URDF, at the
  recorded ``joint_states`` (sensor_msgs/JointState, positions by joint name) and
  ``starleth/base_state`` (nav_msgs/Odometry: pose of the base in the world);
* the ground plane, a 0.5 m checkerboard (height and normal from the recording's physics
  configuration, if any);
* contact forces as arrows from the foot contact points (sphere centre minus radius along
  the ground normal), ``starleth/<foot>/wrench`` for each of the robot's feet
  (geometry_msgs/WrenchStamped, force in the world frame), scaled by ``--force-scale``
  [m/N].

Frames: one every 1/fps s of sim time (header stamps) from the first joint state, each the
latest recorded sample at or before that time (sample and hold, no interpolation), plus the
last sample; the base pose and foot forces are the latest at or before the frame's joint
state. Frames are worked out per sample, so that memory goes with the samples in the bag,
whatever the span of their stamps (two samples 2e9 s apart: 2 frames). Several robots: the
frames of each, merged, each robot at its latest sample at or before a frame's time; the
camera follows their mean trunk position; the ground is the first bag's. A recorded value
that is NaN, infinite or beyond 1e9 is garbage: the previous value is drawn instead (a
force: no arrow), with a warning counting the messages. Numbers are rounded: positions and
arrows to 0.1 mm, quaternions to 1e-4, times to 0.1 ms. A 20 s run at 400 Hz gives a 1.7 MB
page at the default 50 fps (0.85 MB of it the viewer), 7.3 MB with every sample.

A bag that cannot be read (not MCAP, truncated, corrupt; ``--salvage`` reads a truncated one
up to the damage), one without (readable) joint states or base state, or a shown message
that cannot be decoded, ends the program with a one-line message on stderr and exit
status 1.

This module is the command line and :func:`write_html`; the run is read by
:mod:`.recording`, its frames worked out by :mod:`.frames`, drawn by
:mod:`.scene` and written into the page by :mod:`.page`.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time

from ..common.bag import BagError
from ..common.console import run_console_script
from .frames import load_description
from .page import ROUNDING_TEXT, render_html, replay_data
from .recording import (
    PROG,
    NamespaceNotFound,
    ViewError,
    normalised_namespace,
    read_recordings,
    warn,
)
from .scene import page_scale

DEFAULT_FPS = 50.0
#: arrow length per newton of contact force [m/N]: 1 m = 500 N, for StarlETH; a page of
#: other robots: times λ/μ of the largest (view_scene.page_scale), to 2 digits, so that
#: standing forces draw arrows of the same length relative to the legs
DEFAULT_FORCE_SCALE = 0.002


def default_force_scale(descs) -> float:
    """The default force scale of a page of these robots' descriptions [m/N]."""
    s = page_scale(descs)
    return float(f"{DEFAULT_FORCE_SCALE * s.length / s.mass:.2g}")


def default_output(bag_path: str) -> str:
    """run.mcap -> run.html beside it; a bag directory d/ -> d.html beside it."""
    p = os.path.abspath(bag_path).rstrip(os.sep)
    stem = os.path.splitext(p)[0] if os.path.isfile(p) else p
    return stem + ".html"


def read_robots(bag_paths, namespaces=None, salvage=False) -> list:
    """[(Recording, RobotDescription)] of the robots of the bags (or of those under
    `namespaces`: each must be in one of them)."""
    robots = []
    for path in bag_paths:
        try:
            recs = read_recordings(path, namespaces, salvage=salvage)
        except NamespaceNotFound as e:
            if len(bag_paths) == 1:
                raise
            warn(f"{e}; not drawn")
            continue
        robots += [(rec, load_description(rec)) for rec in recs]
    if namespaces is not None:
        found = {rec.namespace for rec, _ in robots}
        missing = [n or "/" for n in map(normalised_namespace, namespaces) if n not in found]
        if missing:
            raise ViewError(f"no robot under the namespace(s) {', '.join(missing)} in "
                            f"{', '.join(bag_paths)}")
    return robots


def robot_names(recs) -> list:
    """The robots' names in the page, before their frames: their frame prefixes (robot1/);
    where two robots share one (recorded without tf_frame_prefix), their namespaces, else
    robot1/, robot2/, ... (with a warning)."""
    names = [r.frame_prefix for r in recs]
    if len(set(names)) == len(names):
        return names
    by_ns = [r.namespace.strip("/") + "/" if r.namespace else "" for r in recs]
    chosen = by_ns if len(set(by_ns)) == len(by_ns) else \
        [f"robot{i + 1}/" for i in range(len(recs))]
    warn(f"the robots' frames have the same names (frame prefixes "
         f"{', '.join(repr(n) for n in names)}: recorded without tf_frame_prefix); drawn as "
         f"{', '.join(chosen)}")
    return chosen


def write_html(bag_path, out_path: str | None = None, fps: float = DEFAULT_FPS,
               force_scale: float | None = None, namespace=None,
               salvage: bool = False) -> dict:
    """Write the replay page of a bag, or of several in one scene (bag_path: a path or a
    list of them; namespace: a namespace or a list of them, None: every robot). Returns
    {'path', 'frames', 'bytes', 'duration', 'fps', 'samples', 'robots' (names),
    'namespaces', 'urdf_sources', 'seconds'}. Raises BagError (a bag that cannot be read)
    or ViewError (nothing to replay, bad options, unusable URDF)."""
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise ViewError(f"fps must be a positive number, got {fps!r}")
    if force_scale is not None and not (isinstance(force_scale, (int, float))
                                        and math.isfinite(force_scale) and force_scale > 0):
        raise ViewError(f"force scale must be a positive number [m/N], got {force_scale!r}")
    t_start = time.perf_counter()
    paths = [bag_path] if isinstance(bag_path, (str, os.PathLike)) else list(bag_path)
    paths = [os.fspath(p) for p in paths]
    namespaces = [namespace] if isinstance(namespace, str) else namespace
    robots = read_robots(paths, namespaces, salvage)
    names = robot_names([rec for rec, _ in robots])
    if force_scale is None:
        force_scale = default_force_scale([desc for _, desc in robots])
    data, scene = replay_data([(rec, desc, name)
                               for (rec, desc), name in zip(robots, names, strict=True)],
                              float(fps), float(force_scale))
    page = render_html(data, scene)
    out = out_path or default_output(paths[0])
    d = os.path.dirname(os.path.abspath(out))
    os.makedirs(d, exist_ok=True)
    tmp = out + ".part"
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(page)
    os.replace(tmp, out)
    return {"path": out, "frames": data["frames"], "bytes": os.path.getsize(out),
            "duration": data["duration"], "fps": float(fps), "samples": data["samples"],
            "robots": names, "namespaces": [rec.namespace for rec, _ in robots],
            "urdf_sources": [rec.urdf_source for rec, _ in robots],
            "seconds": round(time.perf_counter() - t_start, 3)}


def build_parser():
    ap = argparse.ArgumentParser(
        prog=PROG,
        description="Replay recorded runs (MCAP bags) in 3D in the browser: writes "
        "one self-contained HTML file (meshcat's three.js viewer and the data inlined; no "
        "server, no network). Every robot of the bags (several: side by side in one scene, "
        "on one time line) from its bag's robot (URDF, spec, meshes), poses from Pinocchio "
        "forward kinematics of the recorded joint_states and starleth/base_state, the "
        "ground, and the foot "
        "contact forces as arrows; play/pause, scrub, speed, camera following the trunk(s).",
        epilog=f"Subsampling: one frame every 1/FPS s of sim time, each the latest recorded "
        f"sample at or before it (no interpolation), plus the last sample. Rounding: "
        f"{ROUNDING_TEXT}. In the page, ?t=1.5&paused=1 shows t = 1.5 s paused (also "
        f"speed=X, follow=0). Exit status: 0 ok, 1 a bag that cannot be read or holds no "
        f"joint states / base state, 2 bad arguments.")
    ap.add_argument("bag", metavar="RUN.mcap", nargs="+",
                    help="MCAP bag file, or a rosbag2 directory holding .mcap files; several: "
                         "their robots in one scene, on one time line")
    ap.add_argument("-o", "--output", metavar="RUN.html",
                    help="the HTML file to write (default: the (first) bag's name with "
                         ".html, beside it)")
    ap.add_argument("--fps", type=float, default=DEFAULT_FPS,
                    help=f"frames per second of sim time kept in the page (default "
                         f"{DEFAULT_FPS:g}; at or above the recording's rate: every sample)")
    ap.add_argument("--force-scale", type=float, metavar="M_PER_N",
                    help=f"arrow length per newton of contact force [m/N] (default "
                         f"{DEFAULT_FORCE_SCALE:g} for StarlETH: 1 m = "
                         f"{1 / DEFAULT_FORCE_SCALE:g} N; another robot: times its leg "
                         "length over its mass, both relative to StarlETH's)")
    ap.add_argument("--namespace", metavar="NS", action="append",
                    help="draw the robot under this namespace (e.g. /robot1; repeat it for "
                         "several; default: every robot of the bags)")
    ap.add_argument("--salvage", action="store_true",
                    help="read a truncated/damaged bag up to the damage instead of failing")
    return ap


def run(argv=None) -> int:
    ap = build_parser()
    a = ap.parse_args(argv)
    if not (math.isfinite(a.fps) and a.fps > 0):
        ap.error("--fps must be a positive number")
    if a.force_scale is not None and not (math.isfinite(a.force_scale) and a.force_scale > 0):
        ap.error("--force-scale must be a positive number [m/N]")
    info = write_html(a.bag, a.output, fps=a.fps, force_scale=a.force_scale,
                      namespace=a.namespace, salvage=a.salvage)
    robots = info["robots"]
    several = f" of {len(robots)} robots ({', '.join(n or '/' for n in robots)})" \
        if len(robots) > 1 else ""
    print(f"wrote {info['path']}: {info['frames']} frames at {info['fps']:g} fps of "
          f"{info['samples']} samples{several}, {info['duration']:.2f} s, "
          f"{info['bytes'] / 1e6:.2f} MB ({info['seconds']:.1f} s)")
    return 0


def main(argv=None) -> int:
    """Console script: exit status 0, or 1 with a one-line message (no traceback) for a bag
    that cannot be replayed, 2 for bad arguments."""
    return run_console_script(PROG, run, argv, (BagError, ViewError))


if __name__ == "__main__":
    sys.exit(main())
