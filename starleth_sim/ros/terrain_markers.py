"""The terrain as sim_node publishes it: one latched (transient local)
visualization_msgs/MarkerArray on ``terrain`` in `world_frame`, sent once at start (sim time
0), recorded and served by the live view as every other topic of the node (through
:class:`~.topic_output.TopicOutput`). Only a run with a terrain (a non-empty ``terrain:``
section of the physics configuration, :mod:`..physics.terrain`) has the topic.

- namespace ``ground``: the ground plane (height, normal) as a thin CUBE whose top face lies
  GROUND_DROP below the plane (not fighting with a viewer's grid drawn on it), large enough
  to hold the terrain;
- namespace ``boxes``: every box, the stairs' included, as a CUBE (centre, size, yaw);
- namespace ``heightfield``: the heightfield (given or generated) as one TRIANGLE_LIST of two
  triangles per cell, coloured by height, every k-th point of its grid (at most
  MAX_DRAWN_POINTS a side: a 1024 x 1024 field would be a 150 MB message; the physics
  uses every point).
"""
from __future__ import annotations

import math

import numpy as np

from starleth_interface.topics import TOPIC_TERRAIN

from .qos import LATCHED_QOS

#: points per side of the heightfield drawn, at most (100: 58 806 vertices, 2.4 MB)
MAX_DRAWN_POINTS = 100
GROUND_SIZE = 10.0            # m: the drawn plane's side at least
GROUND_THICKNESS = 0.01       # m
GROUND_DROP = 0.001           # m: its top face below the plane
GROUND_COLOUR = (0.62, 0.62, 0.6, 1.0)
BOX_COLOUR = (0.55, 0.45, 0.35, 1.0)
#: the heightfield's colours at its lowest and highest point (linear between)
LOW_COLOUR, HIGH_COLOUR = (0.3, 0.4, 0.3, 1.0), (0.8, 0.75, 0.55, 1.0)


def _yaw_quaternion(yaw):
    return 0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw)


def _normal_quaternion(normal):
    """(x, y, z, w) of the rotation taking the z axis onto `normal` (unit)."""
    n = np.asarray(normal, dtype=float)
    n = n / np.linalg.norm(n)
    c = float(n[2])
    if c < -1.0 + 1e-12:                       # upside down: half a turn about x
        return 1.0, 0.0, 0.0, 0.0
    axis = np.cross([0.0, 0.0, 1.0], n)        # |axis| = sin(angle)
    w = math.sqrt(0.5 * (1.0 + c))
    s = 0.5 / w                                # sin(angle/2) / sin(angle)
    return float(axis[0] * s), float(axis[1] * s), float(axis[2] * s), w


def grid_triangles(grid, max_points=MAX_DRAWN_POINTS):
    """(vertices (3m x 3), heights fraction in [0, 1] per vertex) of a heightfield `grid`
    ((origin, cell, heights, mu): TerrainConfig.grid) as triangles, two per drawn cell, every
    k-th point of the grid and its last row and column (at most `max_points` a side)."""
    (x0, y0), cell, heights, _ = grid
    nx, ny = heights.shape
    step = max(1, math.ceil(max(nx, ny) / max_points))
    ix = np.unique(np.r_[np.arange(0, nx, step), nx - 1])
    iy = np.unique(np.r_[np.arange(0, ny, step), ny - 1])
    X, Y = np.meshgrid(x0 + ix * cell, y0 + iy * cell, indexing="ij")
    pts = np.stack([X, Y, heights[np.ix_(ix, iy)]], axis=-1).reshape(-1, 3)
    m = len(iy)
    a = (np.arange(len(ix) - 1)[:, None] * m + np.arange(m - 1)[None, :]).ravel()
    tri = np.stack([a, a + m, a + 1, a + 1, a + m, a + m + 1], axis=1).ravel()
    v = pts[tri]
    lo, hi = float(heights.min()), float(heights.max())
    frac = (v[:, 2] - lo) / (hi - lo) if hi > lo else np.zeros(len(v))
    return v, frac


class TerrainMessage:
    """Builds the terrain's MarkerArray; the message classes are passed in
    (visualization_msgs is optional: the caller imports it)."""

    def __init__(self, Marker, MarkerArray, Point, ColorRGBA):
        self.Marker, self.MarkerArray = Marker, MarkerArray
        self.Point, self.ColorRGBA = Point, ColorRGBA

    def _marker(self, frame, ns, i, typ, colour):
        m = self.Marker()
        m.header.frame_id = frame
        m.ns, m.id, m.type, m.action = ns, i, typ, self.Marker.ADD
        m.pose.orientation.w = 1.0
        m.color.r, m.color.g, m.color.b, m.color.a = colour
        m.frame_locked = True
        return m

    def build(self, config, frame):
        """The MarkerArray of `config`'s (a PhysicsConfig) ground plane and terrain."""
        Marker = self.Marker
        ground = config.ground
        boxes = config.terrain.all_boxes(ground.height)
        grid = config.terrain.grid(ground.height)
        msg = self.MarkerArray()
        # the plane: under the terrain's extent (and the origin), GROUND_SIZE at least
        xs, ys = [0.0], [0.0]
        for b in boxes:
            r = 0.5 * math.hypot(b["size"][0], b["size"][1])
            xs += [b["centre"][0] - r, b["centre"][0] + r]
            ys += [b["centre"][1] - r, b["centre"][1] + r]
        if grid is not None:
            (x0, y0), cell, heights, _ = grid
            xs += [x0, x0 + cell * (heights.shape[0] - 1)]
            ys += [y0, y0 + cell * (heights.shape[1] - 1)]
        cx, cy = 0.5 * (min(xs) + max(xs)), 0.5 * (min(ys) + max(ys))
        size = max(GROUND_SIZE, 2.0 + max(max(xs) - min(xs), max(ys) - min(ys)))
        n = np.asarray(ground.normal, dtype=float)
        n = n / np.linalg.norm(n)
        # the point of the plane n . x = height above (cx, cy) (along n where n is level)
        p = np.array([cx, cy, (ground.height - n[0] * cx - n[1] * cy) / n[2]]) \
            if abs(n[2]) > 0.1 else ground.height * n
        p = p - n * (GROUND_DROP + 0.5 * GROUND_THICKNESS)
        m = self._marker(frame, "ground", 0, Marker.CUBE, GROUND_COLOUR)
        m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(v) for v in p)
        o = m.pose.orientation
        o.x, o.y, o.z, o.w = _normal_quaternion(n)
        m.scale.x, m.scale.y, m.scale.z = size, size, GROUND_THICKNESS
        msg.markers.append(m)
        for i, b in enumerate(boxes):
            m = self._marker(frame, "boxes", i, Marker.CUBE, BOX_COLOUR)
            m.pose.position.x, m.pose.position.y, m.pose.position.z = \
                (float(v) for v in b["centre"])
            o = m.pose.orientation
            o.x, o.y, o.z, o.w = _yaw_quaternion(b["yaw"])
            m.scale.x, m.scale.y, m.scale.z = (float(v) for v in b["size"])
            msg.markers.append(m)
        if grid is not None:
            m = self._marker(frame, "heightfield", 0, Marker.TRIANGLE_LIST, HIGH_COLOUR)
            m.scale.x = m.scale.y = m.scale.z = 1.0
            vertices, frac = grid_triangles(grid)
            Point, Colour = self.Point, self.ColorRGBA
            m.points = [Point(x=x, y=y, z=z) for x, y, z in vertices.tolist()]
            lo, hi = np.array(LOW_COLOUR), np.array(HIGH_COLOUR)
            m.colors = [Colour(r=r, g=g, b=b, a=a) for r, g, b, a in
                        (lo + frac[:, None] * (hi - lo)).tolist()]
            msg.markers.append(m)
        return msg


class TerrainTopic:
    """sim_node's ``terrain`` topic: made by :meth:`create` (None without a terrain), sent
    once by :meth:`publish`."""

    def __init__(self, output, msg):
        self.output, self.msg = output, msg

    @classmethod
    def create(cls, output, config, frame, log):
        """The topic of `config`'s terrain in `frame`, its publisher added to `output` (a
        TopicOutput: before the recording and the live view start, which take its topics);
        None if the terrain is flat, or visualization_msgs is missing (a warning)."""
        if config.terrain.is_flat:
            return None
        try:
            from geometry_msgs.msg import Point
            from std_msgs.msg import ColorRGBA
            from visualization_msgs.msg import Marker, MarkerArray
        except ImportError:
            log.warning("visualization_msgs is not installed: the terrain is simulated but "
                        "not published (no 'terrain' topic)")
            return None
        msg = TerrainMessage(Marker, MarkerArray, Point, ColorRGBA).build(config, frame)
        output.add("terrain", MarkerArray, TOPIC_TERRAIN, LATCHED_QOS)
        return cls(output, msg)

    def publish(self):
        """Publish, record and serve the markers (latched: at the stamp of the start)."""
        self.output.emit("terrain", self.msg, True)
