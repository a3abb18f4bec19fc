"""A robot's mesh files: the ones its URDF names (``<mesh filename=...>``), where they are
(``package://`` URIs under the spec's package roots, else ROS's ament index; ``file://`` and
relative paths from the URDF's directory), read as triangles (STL, OBJ: coal's loader,
assimp; DAE: .collada) and simplified to a triangle budget (vertex clustering: vertices
snapped to a grid, the triangles that collapse dropped; the grid coarsened until the mesh
fits)."""
from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from functools import lru_cache

import coal  # pinocchio's collision library; its mesh loader is assimp
import numpy as np

from starleth_interface.config_checks import ConfigError
from starleth_interface.robot.library import package_dirs
from starleth_interface.robot.spec import spec_from_dict
from starleth_interface.yaml_files import load_yaml_text

from .collada import ColladaError, read_collada

#: the mesh formats drawn (STL, OBJ: coal's assimp loader; DAE: .collada)
MESH_SUFFIXES = (".stl", ".dae", ".obj")
#: the largest mesh file read or served [bytes]
MAX_MESH_BYTES = 64 * 1024 * 1024


class MeshError(Exception):
    """A mesh that cannot be found or read: the message names the file."""


def mesh_filenames(urdf_xml: str) -> list[str]:
    """The filenames of the URDF's <mesh> elements (visual and collision), each once, in
    document order."""
    root = ET.fromstring(urdf_xml)
    names = [m.get("filename") for m in root.iter("mesh") if m.get("filename")]
    return list(dict.fromkeys(names))


def _package_share(package: str) -> str | None:
    """A ROS package's share directory from the ament index, or None."""
    try:
        from ament_index_python.packages import get_package_share_directory
        return get_package_share_directory(package)
    except Exception:   # not ROS, or no such package
        return None


def resolve_mesh(uri: str, roots=(), base_dir: str | None = None) -> str:
    """The file of a URDF mesh filename: package://<pkg>/<path> under a root of `roots`
    (<root>/<pkg>/<path>), else under the package's ament share directory; file://<path>;
    a relative path from `base_dir`. MeshError naming the URI where there is none."""
    if uri.startswith("package://"):
        package, _, rel = uri[len("package://"):].partition("/")
        bases = [os.path.join(r, package) for r in roots]
        share = _package_share(package)
        bases += [share] if share else []
    elif uri.startswith("file://"):
        bases, rel = [""], uri[len("file://"):]
    elif "://" in uri:
        raise MeshError(f"mesh {uri}: only package://, file:// and plain paths are read")
    else:
        bases, rel = [base_dir or os.getcwd()], uri
    for base in bases:
        path = os.path.normpath(os.path.join(base, rel))
        inside = not base or os.path.commonpath([os.path.abspath(base),
                                                  os.path.abspath(path)]) == os.path.abspath(base)
        if inside and os.path.isfile(path):
            return path
    where = f" (package roots: {', '.join(roots)})" if uri.startswith("package://") and roots \
        else ""
    raise MeshError(f"mesh {uri}: no such file{where}")


def read_mesh(path: str, scale=(1.0, 1.0, 1.0)):
    """(vertices (n, 3) float, triangles (m, 3) int) of a mesh file, scaled (cached per file
    and scale). MeshError naming the file where it cannot be read."""
    return _read_mesh(os.path.abspath(path), tuple(float(s) for s in scale))


@lru_cache(maxsize=64)
def _read_mesh(path: str, scale: tuple):
    if not path.lower().endswith(MESH_SUFFIXES):
        raise MeshError(f"mesh {path}: not one of the formats read "
                        f"({', '.join(s[1:].upper() for s in MESH_SUFFIXES)})")
    try:
        size = os.path.getsize(path)
    except OSError as e:
        raise MeshError(f"mesh {path}: {e.strerror}") from None
    if size > MAX_MESH_BYTES:
        raise MeshError(f"mesh {path}: {size / 2**20:.0f} MiB, over the "
                        f"{MAX_MESH_BYTES / 2**20:.0f} MiB read")
    if path.lower().endswith(".dae"):
        try:
            vertices, triangles = read_collada(path)
        except (ColladaError, ET.ParseError, OSError, ValueError) as e:
            raise MeshError(f"mesh {path}: cannot be read ({str(e)[:200]})") from None
        vertices = vertices * np.asarray(scale)
    else:
        vertices, triangles = _read_with_coal(path, scale)
    if not triangles.size or not np.all(np.isfinite(vertices)):
        raise MeshError(f"mesh {path}: no triangles with finite vertices")
    return vertices, triangles


def _read_with_coal(path: str, scale: tuple):
    """(vertices, triangles) of an STL or OBJ file, scaled, read with coal's loader."""
    try:
        model = coal.MeshLoader().load(path, np.array(scale))
    except Exception as e:   # assimp's refusals come as RuntimeError with several lines
        lines = [x.strip() for x in str(e).splitlines() if x.strip()]
        reason = next((x for x in reversed(lines) if not x.startswith("Hint")), "unreadable")
        raise MeshError(f"mesh {path}: cannot be read ({reason[:200]})") from None
    vertices = np.asarray(model.vertices(), dtype=float).reshape(-1, 3)
    tris = [model.tri_indices(i) for i in range(model.num_tris)]
    return vertices, np.array([[t[0], t[1], t[2]] for t in tris], dtype=np.int64).reshape(-1, 3)


def simplified(vertices, triangles, max_triangles: int):
    """The mesh with at most max_triangles triangles (at least 1): unchanged where it fits,
    else by vertex clustering on a grid whose cell grows by 1.5 until it fits (each vertex
    moved to the mean of its cell's vertices)."""
    if len(triangles) <= max_triangles:
        return vertices, triangles
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    extent = float(np.max(hi - lo)) or 1.0
    cell = extent / max(2.0, math.sqrt(max_triangles / 2.0))
    while True:
        keys = np.floor((vertices - lo) / cell).astype(np.int64)
        _, cluster, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
        cluster = cluster.reshape(-1)
        t = cluster[triangles]
        t = t[(t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])]
        t = np.unique(t, axis=0) if len(t) else t
        if len(t) <= max_triangles or cell > 4 * extent:
            break
        cell *= 1.5
    v = np.zeros((counts.size, 3))
    np.add.at(v, cluster, vertices)
    v /= counts[:, None]
    return v, t[:max_triangles]


def spec_package_roots(spec_yaml: str | None, name: str) -> list[str]:
    """The package roots (package:// URIs) a robot spec's YAML text gives (a recording's
    copy): [] for none, a robot without a spec, or a distribution not installed here."""
    if spec_yaml is None:
        return []
    try:
        spec = spec_from_dict(load_yaml_text(spec_yaml, f"{name}.robot.yaml"),
                              f"{name}.robot.yaml")
        return package_dirs(spec)
    except (ConfigError, ImportError, OSError):   # PackageNotFoundError is an ImportError
        return []
