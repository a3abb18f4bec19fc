"""``starleth-view``: a recorded run replayed in 3D, as one self-contained HTML file.

    starleth-view runs/demo.mcap                    # writes runs/demo.html
    starleth-view run.mcap -o replay.html --fps 30
    starleth-view rosbag2_dir/ --namespace /robot1

The page needs no server and no network: meshcat's three.js viewer
(``meshcat/viewer/dist/main.min.js`` of the ``meshcat`` package, MIT licence) and the replay
data are inlined. Open it in a browser; play / pause (space), step (arrow keys), scrub with
the slider, pick a speed; the camera follows the trunk (drag to orbit, scroll to zoom).
``?t=1.5&paused=1`` in the URL shows t = 1.5 s paused (also ``speed=0.5``, ``follow=0``).

What is drawn, from the bag (an MCAP file written by ``sim_node``, or a rosbag2 directory of
.mcap files; topics are matched by suffix, so ``/joint_states`` and ``/robot1/joint_states``
both work):

* the robot's URDF visuals (boxes, spheres, cylinders), from the bag's ``robot_description``
  topic, else its ``starleth.urdf`` attachment (``sim_node``'s recorder), else the package's
  ``urdf/starleth.urdf``;
* link poses from Pinocchio forward kinematics of a free-flyer model of that URDF, at the
  recorded ``joint_states`` (sensor_msgs/JointState, positions by joint name) and
  ``starleth/base_state`` (nav_msgs/Odometry: pose of the base in the world);
* the ground plane, a 0.5 m checkerboard (height and normal from the recording's physics
  configuration, if any);
* contact forces as arrows from the foot contact points (sphere centre minus radius along
  the ground normal), ``starleth/{LF,RF,LH,RH}_foot/wrench`` (geometry_msgs/WrenchStamped,
  force in the world frame), scaled by ``--force-scale`` [m/N].

Frames: one every 1/fps s of sim time (header stamps) from the first joint state, each the
latest recorded sample at or before that time (sample and hold, no interpolation), plus the
last sample; the base pose and foot forces are the latest at or before the frame's joint
state. Frames are worked out per sample, so that memory goes with the samples in the bag,
whatever the span of their stamps (two samples 2e9 s apart: 2 frames). A recorded value
that is NaN, infinite or beyond 1e9 is garbage: the previous value is drawn instead (a
force: no arrow), with a warning counting the messages. Numbers are rounded: positions and
arrows to 0.1 mm, quaternions to 1e-4, times to 0.1 ms. A 20 s run at 400 Hz gives a 1.7 MB
page at the default 50 fps (0.85 MB of it the viewer), 7.3 MB with every sample.

A bag that cannot be read (not MCAP, truncated, corrupt; ``--salvage`` reads a truncated one
up to the damage), one without (readable) joint states or base state, or a shown message
that cannot be decoded, ends the program with a one-line message on stderr and exit
status 1.

This module is the command line and :func:`write_html`; the run is read by
:mod:`.view_recording`, its frames worked out by :mod:`.view_frames`, drawn by
:mod:`.view_scene` and written into the page by :mod:`.view_page`.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time

from .bag import BagError
from .console import run_console_script
from .view_frames import load_description
from .view_page import ROUNDING_TEXT, render_html, replay_data
from .view_recording import PROG, ViewError, read_recording

DEFAULT_FPS = 50.0
#: arrow length per newton of contact force [m/N]: 1 m = 500 N
DEFAULT_FORCE_SCALE = 0.002


def default_output(bag_path: str) -> str:
    """run.mcap -> run.html beside it; a bag directory d/ -> d.html beside it."""
    p = os.path.abspath(bag_path).rstrip(os.sep)
    stem = os.path.splitext(p)[0] if os.path.isfile(p) else p
    return stem + ".html"


def write_html(bag_path: str, out_path: str | None = None, fps: float = DEFAULT_FPS,
               force_scale: float = DEFAULT_FORCE_SCALE, namespace: str | None = None,
               salvage: bool = False) -> dict:
    """Write the replay page of a bag. Returns {'path', 'frames', 'bytes', 'duration',
    'fps', 'samples', 'namespace', 'urdf_source', 'seconds'}. Raises BagError (a bag
    that cannot be read) or ViewError (nothing to replay, bad options, unusable URDF)."""
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise ViewError(f"fps must be a positive number, got {fps!r}")
    if not (isinstance(force_scale, (int, float)) and math.isfinite(force_scale)
            and force_scale > 0):
        raise ViewError(f"force scale must be a positive number [m/N], got {force_scale!r}")
    t_start = time.perf_counter()
    rec = read_recording(bag_path, namespace=namespace, salvage=salvage)
    desc = load_description(rec.urdf, rec.urdf_source)
    data, scene = replay_data(rec, desc, float(fps), float(force_scale))
    page = render_html(data, scene)
    out = out_path or default_output(bag_path)
    d = os.path.dirname(os.path.abspath(out))
    os.makedirs(d, exist_ok=True)
    tmp = out + ".part"
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(page)
    os.replace(tmp, out)
    return {"path": out, "frames": data["frames"], "bytes": os.path.getsize(out),
            "duration": data["duration"], "fps": float(fps), "samples": data["samples"],
            "namespace": rec.namespace, "urdf_source": rec.urdf_source,
            "seconds": round(time.perf_counter() - t_start, 3)}


def build_parser():
    ap = argparse.ArgumentParser(
        prog=PROG,
        description="Replay a recorded StarlETH run (MCAP bag) in 3D in the browser: writes "
        "one self-contained HTML file (meshcat's three.js viewer and the data inlined; no "
        "server, no network). The robot from the bag's URDF, poses from Pinocchio forward "
        "kinematics of the recorded joint_states and starleth/base_state, the ground, and "
        "the foot contact forces as arrows; play/pause, scrub, speed, camera following the "
        "trunk.",
        epilog=f"Subsampling: one frame every 1/FPS s of sim time, each the latest recorded "
        f"sample at or before it (no interpolation), plus the last sample. Rounding: "
        f"{ROUNDING_TEXT}. In the page, ?t=1.5&paused=1 shows t = 1.5 s paused (also "
        f"speed=X, follow=0). Exit status: 0 ok, 1 a bag that cannot be read or holds no "
        f"joint states / base state, 2 bad arguments.")
    ap.add_argument("bag", metavar="RUN.mcap",
                    help="MCAP bag file, or a rosbag2 directory holding .mcap files")
    ap.add_argument("-o", "--output", metavar="RUN.html",
                    help="the HTML file to write (default: the bag's name with .html, "
                         "beside it)")
    ap.add_argument("--fps", type=float, default=DEFAULT_FPS,
                    help=f"frames per second of sim time kept in the page (default "
                         f"{DEFAULT_FPS:g}; at or above the recording's rate: every sample)")
    ap.add_argument("--force-scale", type=float, default=DEFAULT_FORCE_SCALE, metavar="M_PER_N",
                    help=f"arrow length per newton of contact force [m/N] (default "
                         f"{DEFAULT_FORCE_SCALE:g}: 1 m = {1 / DEFAULT_FORCE_SCALE:g} N)")
    ap.add_argument("--namespace", metavar="NS",
                    help="the robot's namespace in a bag with several (e.g. /robot1; default: "
                         "the only one, or the first)")
    ap.add_argument("--salvage", action="store_true",
                    help="read a truncated/damaged bag up to the damage instead of failing")
    return ap


def run(argv=None) -> int:
    ap = build_parser()
    a = ap.parse_args(argv)
    if not (math.isfinite(a.fps) and a.fps > 0):
        ap.error("--fps must be a positive number")
    if not (math.isfinite(a.force_scale) and a.force_scale > 0):
        ap.error("--force-scale must be a positive number [m/N]")
    info = write_html(a.bag, a.output, fps=a.fps, force_scale=a.force_scale,
                      namespace=a.namespace, salvage=a.salvage)
    print(f"wrote {info['path']}: {info['frames']} frames at {info['fps']:g} fps of "
          f"{info['samples']} samples, {info['duration']:.2f} s, "
          f"{info['bytes'] / 1e6:.2f} MB ({info['seconds']:.1f} s)")
    return 0


def main(argv=None) -> int:
    """Console script: exit status 0, or 1 with a one-line message (no traceback) for a bag
    that cannot be replayed, 2 for bad arguments."""
    return run_console_script(PROG, run, argv, (BagError, ViewError))


if __name__ == "__main__":
    sys.exit(main())
