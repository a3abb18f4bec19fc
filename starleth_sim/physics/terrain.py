"""The terrain on the ground plane: boxes and a heightfield (the `terrain:` section of a
physics configuration), its generators (stairs, slope, rough) and its packing for the C
contact query (``csrc/terrain.c``).

The plane is the `ground` section (height, normal, μ), as before; `terrain` adds to it:

- ``boxes``: a list of boxes ``{centre: [x, y, z], size: [sx, sy, sz], yaw: ψ, mu: μ}``
  (yaw in radians about z, default 0; μ default ground.mu). Steps and stairs are boxes.
- ``heightfield``: one grid ``{origin: [x0, y0], cell: c, heights: ..., mu: μ}``: the
  heights h[ix][iy] at (x0 + ix·c, y0 + iy·c), given inline (a list of nx rows of ny
  numbers, nx, ny >= 2), as the path of a ``.npy`` file (nx x ny), of a grey PNG
  (``scale``: the height of white, black is 0; rows of the image are x, columns y) or as
  ``{shape: [nx, ny], float64: <base64 of the little-endian doubles>}`` (how `to_dict`, hence
  a recording, writes it). The
  surface is bilinear in each cell; outside the grid there is no heightfield.
- generators: ``stairs: {rise, run, count, start, width, landing, mu}`` (boxes: step k of
  height k·rise from x = start + (k−1)·run, the last one `landing` long),
  ``slope: {angle, length, start, width, top, mu}`` (a heightfield: a ramp up at `angle`
  degrees over `length` metres from x = start, a flat top `top` long, the same ramp down)
  and ``rough: {amplitude, wavelength, seed, size, centre, mu}`` (a heightfield of
  size x size metres: the mean of 8 plane waves of the wavelength in directions and phases
  drawn from `seed`, scaled to the amplitude, faded to 0 within one wavelength of its
  border so it meets the plane without a step). slope and rough are heightfields: a
  terrain has one heightfield at most. Heights are above ground.height.

The surface rule (csrc/terrain.c): each contact sphere (centre c, radius r) takes the surface
with the smallest gap g_N; a tie goes to the first of plane, boxes (in their order),
heightfield. A box's gap is the exact distance of c to the box minus r (negative inside:
the nearest face), its normal points from the closest point of the box to c, so it turns
continuously round an edge or a corner: a foot resting on a step edge has one gap and one
normal, and nothing switches. The heightfield's gap is (c_z − h(x, y)) n_z − r with the
normal n of the cell's bilinear surface at (c_x, c_y) (the distance to the tangent plane
there). Where two surfaces meet in a concave corner (a foot against a riser, on the
floor) the sphere has a second contact, on the other surface (SECOND_SURFACE_*; the
coordinates give each sphere two contact slots on a terrain: doc/physics.md, "Terrain").
"""
from __future__ import annotations

import base64
import binascii
import math
import os
from dataclasses import dataclass, field

import numpy as np

from starleth_interface.config_checks import ConfigError, check_int, check_number, short_repr
from starleth_interface.robot.contact_points import BOX_REACH

#: the floats of the packed terrain's header (csrc/terrain.c TERRAIN_HEADER), and the index
#: of its flag: the contacts have a second surface each (every terrain that is not flat)
TERRAIN_HEADER = 16
SECOND_SURFACES = 14
#: the index of the terrain's top: the highest z of its boxes and heightfield; a contact
#: sphere whose lowest point is more than BOX_REACH above it meets the plane alone (its gap
#: to the terrain is more than BOX_REACH: beyond where gaps are exact, see BOX_REACH)
TOP = 15
#: a contact sphere's second surface (csrc/terrain.c): the nearest other surface whose
#: normal is more than SECOND_SURFACE_ANGLE from the first's, when both gaps are within
#: SECOND_SURFACE_REACH [m]; with none, its slot's gap is SECOND_SURFACE_NONE [m]
SECOND_SURFACE_ANGLE = 20.0         # degrees
SECOND_SURFACE_REACH = 0.1
SECOND_SURFACE_NONE = 1000.0
#: BOX_REACH (starleth_interface.robot.contact_points, with the bound it puts on a contact
#: sphere's radius): a box is tested for the contacts whose centre lies within it of its
#: bounds in x and y [m]: the gap to a box farther away is > BOX_REACH − r, and such a gap
#: is the plane's or another surface's (a contact only needs exact gaps near its surfaces)
#: the side of the bins of the boxes [m], and their most per side
BIN_SIZE = 0.25
MAX_BINS = 512
#: the most (bin, box) memberships packed (8 MiB of floats): where boxes that span many bins
#: would make more, the bins are made larger (10 000 boxes of 1000 m were 2.6e9 entries)
MAX_BIN_ITEMS = 1 << 20
#: the floats per packed box (csrc/terrain.c BOX_STRIDE)
BOX_STRIDE = 11
MAX_BOXES = 10_000
#: points per side of a heightfield: 1024² doubles are 8 MiB, 11 MiB of base64 in a
#: recorded configuration (the configuration loader reads at most 16 MiB)
MAX_GRID = 1024
MAX_EXTENT = 1000.0                 # m: positions and sizes
MAX_MU = 10.0
ROUGH_WAVES = 8
#: the rough generator's grid points per wavelength (fewer where MAX_GRID a side does not
#: hold them), and the fewest it accepts (2: the sampling limit; below, the waves alias)
ROUGH_POINTS_PER_WAVE = 8
ROUGH_MIN_POINTS_PER_WAVE = 2
SLOPE_CELL = 0.05                   # m: the slope generator's target cell size


def _vector(path, v, n, lo=-MAX_EXTENT, hi=MAX_EXTENT, lo_open=False):
    if not isinstance(v, (list, tuple)) or len(v) != n:
        raise ConfigError(f"{path}: expected a list of {n} numbers, got {short_repr(v)}")
    return [check_number(f"{path}[{i}]", x, lo, hi, lo_open=lo_open) for i, x in enumerate(v)]


def _mapping(path, v, known, required=()):
    if not isinstance(v, dict):
        raise ConfigError(f"{path}: expected a mapping, got {short_repr(v)}")
    for k in v:
        if k not in known:
            raise ConfigError(f"{path}: unknown field '{k}' (known: {', '.join(known)})")
    for k in required:
        if k not in v:
            raise ConfigError(f"{path}.{k}: missing")
    return v


def _mu(path, v):
    return None if v is None else check_number(path, v, 0.0, MAX_MU)


def _box(path, b):
    _mapping(path, b, ("centre", "size", "yaw", "mu"), ("centre", "size"))
    return {"centre": _vector(f"{path}.centre", b["centre"], 3),
            "size": _vector(f"{path}.size", b["size"], 3, 0.0, MAX_EXTENT, lo_open=True),
            "yaw": check_number(f"{path}.yaw", b.get("yaw", 0.0), -2 * math.pi, 2 * math.pi),
            "mu": _mu(f"{path}.mu", b.get("mu"))}


def _grid_heights(path, v, scale):
    """The heights (nx x ny float array) of an inline list, a .npy file or a grey PNG."""
    if isinstance(v, np.ndarray):           # validated before (a copy with overrides)
        a = v
    elif isinstance(v, dict):               # to_dict's form: {shape, float64 (base64)}
        a = _packed_heights(path, v)
    elif isinstance(v, str):
        if not os.path.isfile(v):
            raise ConfigError(f"{path}: no such file: {short_repr(v)}")
        if v.endswith(".npy"):
            try:
                a = np.load(v, allow_pickle=False)
            except (OSError, ValueError) as e:
                raise ConfigError(f"{path}: not a .npy array: {e}") from None
        elif v.endswith(".png"):
            if scale is None:
                raise ConfigError(f"{path}: a PNG needs heightfield.scale (the height of "
                                  "white) [m]")
            a = _png_heights(path, v) * scale
        else:
            raise ConfigError(f"{path}: expected a list of rows, a .npy or a .png file, got "
                              f"{short_repr(v)}")
    else:
        if not isinstance(v, (list, tuple)) or not v or \
                not all(isinstance(r, (list, tuple)) for r in v):
            raise ConfigError(f"{path}: expected a list of rows of numbers")
        if len({len(r) for r in v}) != 1:
            raise ConfigError(f"{path}: the rows must have one length")
        if len(v) > MAX_GRID or len(v[0]) > MAX_GRID:    # (before walking it: YAML aliases
            raise ConfigError(f"{path}: the grid must have 2 to {MAX_GRID} points a side, "
                              f"got {len(v)} x {len(v[0])}")    # make big lists of few bytes)
        try:
            if any(isinstance(x, bool) for r in v for x in r):
                raise TypeError
            a = np.array(v, dtype=float)
        except (TypeError, ValueError, OverflowError):
            for i, r in enumerate(v):                   # the first bad entry, named
                for j, x in enumerate(r):
                    check_number(f"{path}[{i}][{j}]", x)
            raise ConfigError(f"{path}: expected rows of numbers") from None
    if a.ndim != 2 or a.dtype.kind not in "fiu":
        raise ConfigError(f"{path}: expected a 2-d array of numbers, got shape {a.shape}")
    a = np.ascontiguousarray(a, dtype=float)
    if not (2 <= a.shape[0] <= MAX_GRID and 2 <= a.shape[1] <= MAX_GRID):
        raise ConfigError(f"{path}: the grid must have 2 to {MAX_GRID} points a side, got "
                          f"{a.shape[0]} x {a.shape[1]}")
    if not np.all(np.isfinite(a)) or np.abs(a).max() > MAX_EXTENT:
        raise ConfigError(f"{path}: heights must be finite and within +-{MAX_EXTENT:g} m")
    return a


def _packed_heights(path, v):
    """The heights of {shape: [nx, ny], float64: base64 of the little-endian doubles}."""
    _mapping(path, v, ("shape", "float64"), ("shape", "float64"))
    shape = v["shape"]
    if not isinstance(shape, (list, tuple)) or len(shape) != 2:
        raise ConfigError(f"{path}.shape: expected [nx, ny], got {short_repr(shape)}")
    nx, ny = (check_int(f"{path}.shape[{k}]", n, 2, MAX_GRID) for k, n in enumerate(shape))
    if not isinstance(v["float64"], str) or len(v["float64"]) > 4 * nx * ny * 8 // 3 + 8:
        raise ConfigError(f"{path}.float64: expected the base64 of {nx} x {ny} doubles")
    try:
        raw = base64.b64decode(v["float64"], validate=True)
    except (binascii.Error, ValueError):
        raise ConfigError(f"{path}.float64: not base64") from None
    if len(raw) != 8 * nx * ny:
        raise ConfigError(f"{path}.float64: {len(raw)} bytes, {nx} x {ny} doubles are "
                          f"{8 * nx * ny}")
    return np.frombuffer(raw, dtype="<f8").reshape(nx, ny).astype(float)


def _png_heights(path, file):
    """A grey PNG's values in [0, 1] (8 or 16 bits)."""
    try:
        from PIL import Image  # deferred: Pillow is optional (with matplotlib), for PNGs only
    except ImportError:
        raise ConfigError(f"{path}: reading a PNG needs Pillow (pip install pillow)") from None
    try:
        with Image.open(file) as im:
            if im.mode not in ("L", "I;16", "I"):
                raise ConfigError(f"{path}: expected a grey PNG, got mode {im.mode}")
            bits = 8 if im.mode == "L" else 16
            return np.asarray(im, dtype=float) / (2 ** bits - 1)
    except OSError as e:
        raise ConfigError(f"{path}: not a PNG image: {e}") from None


def _heightfield(path, h):
    _mapping(path, h, ("origin", "cell", "heights", "scale", "mu"),
             ("origin", "cell", "heights"))
    scale = None if h.get("scale") is None else \
        check_number(f"{path}.scale", h["scale"], 0.0, MAX_EXTENT, lo_open=True)
    return {"origin": _vector(f"{path}.origin", h["origin"], 2),
            "cell": check_number(f"{path}.cell", h["cell"], 0.0, 100.0, lo_open=True),
            "heights": _grid_heights(f"{path}.heights", h["heights"], scale),
            "mu": _mu(f"{path}.mu", h.get("mu"))}


_GENERATORS = {
    "stairs": (("rise", 0.0, 1.0, None), ("run", 0.0, 10.0, None),
               ("count", 1, 100, None), ("start", -MAX_EXTENT, MAX_EXTENT, 0.5),
               ("width", 0.0, 100.0, 2.0), ("landing", 0.0, 100.0, 1.0)),
    "slope": (("angle", 0.0, 45.0, None), ("length", 0.0, 100.0, None),
              ("start", -MAX_EXTENT, MAX_EXTENT, 0.5), ("width", 0.0, 100.0, 2.0),
              ("top", 0.0, 100.0, 1.0)),
    "rough": (("amplitude", 0.0, 0.5, None), ("wavelength", 0.0, 100.0, None),
              ("seed", 0, 2 ** 32 - 1, 0), ("size", 0.0, 100.0, 4.0)),
}


def _generator(name, g):
    spec = _GENERATORS[name]
    extra = ("centre", "mu") if name == "rough" else ("mu",)
    _mapping(name, g, tuple(s[0] for s in spec) + extra,
             tuple(s[0] for s in spec if s[3] is None))
    out = {}
    for key, lo, hi, default in spec:
        v = g.get(key, default)
        if isinstance(lo, int) and key in ("count", "seed"):
            out[key] = check_int(f"{name}.{key}", v, lo, hi)
        else:
            out[key] = check_number(f"{name}.{key}", v, lo, hi,
                                    lo_open=lo == 0.0 and key not in ("top", "landing"))
    if name == "rough":
        out["centre"] = _vector("rough.centre", g.get("centre", [0.0, 0.0]), 2)
    out["mu"] = _mu(f"{name}.mu", g.get("mu"))
    _GRID_CHECKS.get(name, lambda _section: None)(out)
    return out


def _check_slope_grid(s):
    """The slope's grid fits MAX_GRID points a side (checked before it is made)."""
    n, cell, n_top, ny = slope_shape(s)
    nx = 2 * n + n_top + 1
    if nx > MAX_GRID or ny > MAX_GRID:
        most = (MAX_GRID - 1) * cell
        raise ConfigError(f"slope: its heightfield would be {nx} x {ny} points (cell "
                          f"{cell:.4g} m = length / {n}); at most {MAX_GRID} a side: "
                          f"2 x length + top and width must be <= {most:.4g} m at this cell")


def _check_rough_grid(s):
    """The rough ground's grid holds its waves (at most MAX_GRID points a side)."""
    most = (MAX_GRID - 1) / ROUGH_MIN_POINTS_PER_WAVE
    if s["size"] / s["wavelength"] > most:
        raise ConfigError(f"rough: size / wavelength must be <= {most:g} (at least "
                          f"{ROUGH_MIN_POINTS_PER_WAVE} of its {MAX_GRID} grid points a side "
                          f"per wavelength), got {s['size']:g} / {s['wavelength']:g}")


_GRID_CHECKS = {"slope": _check_slope_grid, "rough": _check_rough_grid}


@dataclass
class TerrainConfig:
    """The `terrain:` section (see the module docstring); empty: the plane alone."""

    boxes: list = field(default_factory=list)
    heightfield: dict | None = None
    stairs: dict | None = None
    slope: dict | None = None
    rough: dict | None = None

    def validate(self, p):
        if not isinstance(self.boxes, (list, tuple)):
            raise ConfigError(f"{p}.boxes: expected a list of boxes, got "
                              f"{short_repr(self.boxes)}")
        if len(self.boxes) > MAX_BOXES:
            raise ConfigError(f"{p}.boxes: at most {MAX_BOXES} boxes, got {len(self.boxes)}")
        self.boxes = [_box(f"{p}.boxes[{i}]", b) for i, b in enumerate(self.boxes)]
        if self.heightfield is not None:
            self.heightfield = _heightfield(f"{p}.heightfield", self.heightfield)
        for name in _GENERATORS:
            if getattr(self, name) is not None:
                setattr(self, name, _prefixed(p, name, getattr(self, name)))
        grids = [n for n in ("heightfield", "slope", "rough") if getattr(self, n) is not None]
        if len(grids) > 1:
            raise ConfigError(f"{p}: {' and '.join(grids)} are each a heightfield; a terrain "
                              "has one at most")

    @property
    def is_flat(self) -> bool:
        return not self.boxes and self.stairs is None and self.grid() is None

    def all_boxes(self, ground_height=0.0):
        """The boxes, the stairs' included (dicts of centre, size, yaw, mu)."""
        out = [dict(b) for b in self.boxes]
        s = self.stairs
        if s is not None:
            for k in range(1, s["count"] + 1):
                length = s["run"] + (s["landing"] if k == s["count"] else 0.0)
                out.append({"centre": [s["start"] + (k - 1) * s["run"] + 0.5 * length, 0.0,
                                       ground_height + 0.5 * k * s["rise"]],
                            "size": [length, s["width"], k * s["rise"]], "yaw": 0.0,
                            "mu": s["mu"]})
        return out

    def grid(self, ground_height=0.0):
        """The heightfield, given or generated: (origin, cell, heights, mu) or None."""
        if self.heightfield is not None:
            h = self.heightfield
            return h["origin"], h["cell"], h["heights"] + ground_height, h["mu"]
        if self.slope is not None:
            return slope_grid(self.slope, ground_height)
        if self.rough is not None:
            return rough_grid(self.rough, ground_height)
        return None

    def to_dict(self) -> dict:
        """Plain data (YAML): a heightfield's heights inline, so the dict alone re-creates
        the terrain (a recording's physics YAML needs no other file), as {shape, float64: the
        base64 of the little-endian doubles}: exact, and read fast (a 256 x 256 grid as a
        YAML list of numbers takes PyYAML seconds)."""
        h = self.heightfield
        return {"boxes": [dict(b) for b in self.boxes],
                "heightfield": None if h is None else
                {"origin": list(h["origin"]), "cell": h["cell"],
                 "heights": {"shape": list(h["heights"].shape), "float64": base64.b64encode(
                     h["heights"].astype("<f8").tobytes()).decode("ascii")},
                 "mu": h["mu"]},
                "stairs": _plain(self.stairs), "slope": _plain(self.slope),
                "rough": _plain(self.rough)}


def _prefixed(p, name, g):
    try:
        return _generator(name, g)
    except ConfigError as e:
        raise ConfigError(f"{p}.{e}") from None


def _plain(d):
    return None if d is None else {k: (list(v) if isinstance(v, (list, tuple)) else v)
                                   for k, v in d.items()}


def slope_shape(s):
    """(cells of a ramp n, cell [m], cells of the top, points across) of a slope: the ramp
    in cells of about SLOPE_CELL, its grid 2 n + top cells + 1 points long."""
    n = max(1, round(s["length"] / SLOPE_CELL))
    cell = s["length"] / n
    return n, cell, math.ceil(s["top"] / cell), max(2, math.ceil(s["width"] / cell) + 1)


def slope_grid(s, ground_height=0.0):
    """The slope generator's heightfield: (origin, cell, heights, mu)."""
    n, cell, n_top, ny = slope_shape(s)
    rise = math.tan(math.radians(s["angle"]))
    up = np.arange(n + 1) * cell * rise
    profile = np.concatenate([up, np.full(n_top, up[-1]), up[::-1][1:]])
    heights = np.repeat(profile[:, None], ny, axis=1) + ground_height
    return [s["start"], -0.5 * (ny - 1) * cell], cell, heights, s["mu"]


def rough_grid(s, ground_height=0.0):
    """The rough generator's heightfield: (origin, cell, heights, mu)."""
    lam, size = s["wavelength"], s["size"]
    n = max(2, min(MAX_GRID, math.ceil(ROUGH_POINTS_PER_WAVE * size / lam) + 1))
    cell = size / (n - 1)
    rng = np.random.default_rng(s["seed"])
    direction = rng.uniform(0.0, 2 * math.pi, ROUGH_WAVES)
    phase = rng.uniform(0.0, 2 * math.pi, ROUGH_WAVES)
    x = np.arange(n) * cell - 0.5 * size
    X, Y = np.meshgrid(x, x, indexing="ij")
    h = np.zeros((n, n))
    for d, ph in zip(direction, phase, strict=True):
        h += np.sin(2 * math.pi * (X * math.cos(d) + Y * math.sin(d)) / lam + ph)
    h *= s["amplitude"] / np.abs(h).max()
    edge = np.minimum(np.minimum(X, Y) + 0.5 * size, 0.5 * size - np.maximum(X, Y))
    h *= np.clip(edge / lam, 0.0, 1.0)
    cx, cy = s["centre"]
    return [cx - 0.5 * size, cy - 0.5 * size], cell, h + ground_height, s["mu"]


def pack_terrain(terrain: TerrainConfig | None, ground_height=0.0, ground_mu=0.8):
    """The packed terrain (float64) for csrc/terrain.c: its header, the boxes and the
    heightfield's heights; a surface without μ gets the ground's."""
    boxes = [] if terrain is None else terrain.all_boxes(ground_height)
    grid = None if terrain is None else terrain.grid(ground_height)
    header = np.zeros(TERRAIN_HEADER)
    header[0] = len(boxes)
    header[7] = ground_mu
    packed_boxes = np.zeros((len(boxes), BOX_STRIDE))
    for k, b in enumerate(boxes):
        c, s, yaw = b["centre"], b["size"], b["yaw"]
        cs, sn = math.cos(yaw), math.sin(yaw)
        hx, hy = 0.5 * s[0], 0.5 * s[1]
        packed_boxes[k] = [c[0], c[1], c[2], hx, hy, 0.5 * s[2], cs, sn,
                           ground_mu if b["mu"] is None else b["mu"],
                           abs(cs) * hx + abs(sn) * hy, abs(sn) * hx + abs(cs) * hy]
    bins = _bins(packed_boxes, header)
    heights = np.zeros(0)
    if grid is not None:
        origin, cell, heights, mu = grid
        header[1], header[2] = heights.shape
        header[3], header[4], header[5] = origin[0], origin[1], cell
        header[6] = ground_mu if mu is None else mu
    header[SECOND_SURFACES] = float(bool(len(boxes)) or grid is not None)
    tops = [b[2] + b[5] for b in packed_boxes] + ([float(np.max(heights))] if len(heights)
                                                    else [])
    header[TOP] = max(tops) if tops else ground_height
    return np.concatenate([header, packed_boxes.ravel(), *bins, np.ravel(heights)])


def _bins(boxes, header):
    """The xy bins of the boxes (their bounds grown by BOX_REACH): (starts, items), and
    the bins' origin, size and counts into the header."""
    if not len(boxes):
        return ()
    lo = np.stack([boxes[:, 0] - boxes[:, 9], boxes[:, 1] - boxes[:, 10]], 1) - BOX_REACH
    hi = np.stack([boxes[:, 0] + boxes[:, 9], boxes[:, 1] + boxes[:, 10]], 1) + BOX_REACH
    x0, y0 = lo.min(axis=0)
    extent = max(hi[:, 0].max() - x0, hi[:, 1].max() - y0)
    size = max(BIN_SIZE, extent / MAX_BINS)
    while True:     # (larger bins where the boxes would make more than MAX_BIN_ITEMS)
        nbx = max(1, math.ceil((hi[:, 0].max() - x0) / size))
        nby = max(1, math.ceil((hi[:, 1].max() - y0) / size))
        first = np.floor((lo - (x0, y0)) / size).astype(int)
        last = np.floor((hi - (x0, y0)) / size).astype(int)
        first, last = np.maximum(first, 0), np.minimum(last, (nbx - 1, nby - 1))
        if np.prod(last - first + 1, axis=1).sum() <= MAX_BIN_ITEMS:
            break
        size *= 2.0
    members = [[] for _ in range(nbx * nby)]
    for k, ((i0, j0), (i1, j1)) in enumerate(zip(first.tolist(), last.tolist(), strict=True)):
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                members[i * nby + j].append(k)
    starts = np.cumsum([0] + [len(m) for m in members])
    header[8:14] = [x0, y0, size, nbx, nby, starts[-1]]
    return starts.astype(float), np.array([k for m in members for k in m], dtype=float)


def terrain_height(packed, x, y):
    """The highest surface of a packed terrain above (x, y) from the plane z = 0 up: the
    boxes' tops and the heightfield (for tests and tools; the plane's own height is not
    included)."""
    nbox, nbx, nby, n_items = int(packed[0]), int(packed[11]), int(packed[12]), \
        int(packed[13])
    best = -math.inf
    for k in range(nbox):
        b = packed[TERRAIN_HEADER + BOX_STRIDE * k:][:BOX_STRIDE]
        dx, dy = x - b[0], y - b[1]
        px, py = b[6] * dx + b[7] * dy, -b[7] * dx + b[6] * dy
        if abs(px) <= b[3] and abs(py) <= b[4]:
            best = max(best, b[2] + b[5])
    nx, ny = int(packed[1]), int(packed[2])
    if nx:
        x0, y0, cell = packed[3:6]
        o = TERRAIN_HEADER + BOX_STRIDE * nbox + (nbx * nby + 1 if nbox else 0) + n_items
        hs = packed[o:].reshape(nx, ny)
        u, v = (x - x0) / cell, (y - y0) / cell
        if 0 <= u <= nx - 1 and 0 <= v <= ny - 1:
            i, j = min(int(u), nx - 2), min(int(v), ny - 2)
            fx, fy = u - i, v - j
            a = hs[i, j] + fy * (hs[i, j + 1] - hs[i, j])
            b = hs[i + 1, j] + fy * (hs[i + 1, j + 1] - hs[i + 1, j])
            best = max(best, a + fx * (b - a))
    return best
