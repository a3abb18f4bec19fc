"""Triangles of a COLLADA (.dae) file, read with the standard library's XML parser: every
<triangles>, <polylist> and <polygons> element of the geometries the visual scene's nodes
instance, each node's transforms applied (<matrix>, <translate>, <rotate>, <scale>), scaled
to metres by <unit meter=...>; the up axis ignored as ROS (RViz, Gazebo) does. Not coal's
loader: it indexes the triangles of a geometry's second and later primitive elements (a
mesh of several materials) into the first one's vertices."""
from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np


class ColladaError(ValueError):
    """A .dae file whose geometry cannot be read (the message says what)."""


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _strip_namespaces(root):
    for e in root.iter():
        e.tag = _local(e.tag)
    return root


def _floats(text) -> np.ndarray:
    return np.array((text or "").split(), dtype=float)


def _positions(mesh) -> dict:
    """{id of a <vertices> or <source>: (n, 3) positions} of a <mesh>."""
    out = {}
    for src in mesh.findall("source"):
        arr, acc = src.find("float_array"), src.find("technique_common/accessor")
        stride = int(acc.get("stride", 3)) if acc is not None else 3
        a = _floats(arr.text if arr is not None else "")
        if stride >= 3 and a.size >= stride:
            out[src.get("id")] = a[:a.size // stride * stride].reshape(-1, stride)[:, :3]
    for v in mesh.findall("vertices"):
        for inp in v.findall("input"):
            if inp.get("semantic") == "POSITION" and inp.get("source", "")[1:] in out:
                out[v.get("id")] = out[inp.get("source")[1:]]
    return out


def _primitive_triangles(prim, positions: dict):
    """(vertices, triangles) of one <triangles>/<polylist>/<polygons> element (polygons
    split into fans), or None where it has no positions."""
    inputs = prim.findall("input")
    vert = next((i for i in inputs if i.get("semantic") in ("VERTEX", "POSITION")), None)
    if vert is None or vert.get("source", "")[1:] not in positions:
        return None
    pts = positions[vert.get("source")[1:]]
    width = 1 + max(int(i.get("offset", 0)) for i in inputs)
    offset = int(vert.get("offset", 0))
    polys = []
    for p in prim.findall("p"):
        idx = _floats(p.text).astype(np.int64)
        polys.append(idx[:idx.size // width * width].reshape(-1, width)[:, offset])
    if prim.tag == "triangles":
        corners = np.concatenate(polys) if polys else np.zeros(0, np.int64)
        tris = corners[:corners.size // 3 * 3].reshape(-1, 3)
    else:
        if prim.tag == "polylist":
            counts = _floats(getattr(prim.find("vcount"), "text", "")).astype(np.int64)
            polys = np.split(polys[0], np.cumsum(counts)[:-1]) if polys else []
        tris = np.array([(poly[0], poly[k], poly[k + 1]) for poly in polys
                         for k in range(1, len(poly) - 1)], dtype=np.int64).reshape(-1, 3)
    if tris.size and (tris.min() < 0 or tris.max() >= len(pts)):
        raise ColladaError(f"<{prim.tag}> indexes a vertex it does not have")
    return pts, tris


def _geometry(geom) -> list:
    """[(vertices, triangles)] of a <geometry>'s primitive elements."""
    mesh = geom.find("mesh")
    if mesh is None:
        return []
    positions = _positions(mesh)
    out = [_primitive_triangles(p, positions) for p in mesh
           if p.tag in ("triangles", "polylist", "polygons")]
    return [x for x in out if x is not None]


def _node_matrix(node) -> np.ndarray:
    """A <node>'s transform: its transform elements multiplied in document order."""
    M = np.eye(4)
    for t in node:
        v, T = _floats(t.text), np.eye(4)
        if t.tag == "matrix" and v.size == 16:
            T = v.reshape(4, 4)
        elif t.tag == "translate" and v.size == 3:
            T[:3, 3] = v
        elif t.tag == "scale" and v.size == 3:
            T[:3, :3] = np.diag(v)
        elif t.tag == "rotate" and v.size == 4:
            axis, a = v[:3] / (np.linalg.norm(v[:3]) or 1.0), np.radians(v[3])
            K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]],
                          [-axis[1], axis[0], 0]])
            T[:3, :3] = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
        M = M @ T
    return M


def read_collada(path: str):
    """(vertices (n, 3) in metres, those the triangles use; triangles (m, 3)) of a .dae
    file; ColladaError (or ET.ParseError, OSError) where it cannot be read."""
    root = _strip_namespaces(ET.parse(path).getroot())
    unit = root.find("asset/unit")
    meter = float(unit.get("meter", 1.0)) if unit is not None else 1.0
    geoms = {g.get("id"): g for g in root.iter("geometry")}
    library_nodes = {n.get("id"): n for n in root.findall("library_nodes/node")}
    scene_ref = root.find("scene/instance_visual_scene")
    scenes = {s.get("id"): s for s in root.iter("visual_scene")}
    scene = scenes.get(scene_ref.get("url", "")[1:]) if scene_ref is not None else None
    parts = []

    def visit(node, M, depth=0):
        if depth > 64:
            raise ColladaError("nodes nested deeper than 64")
        M = M @ _node_matrix(node)
        for inst in node.findall("instance_geometry"):
            g = geoms.get(inst.get("url", "")[1:])
            parts.extend((v @ M[:3, :3].T + M[:3, 3], t) for v, t in
                         (_geometry(g) if g is not None else []))
        for child in node.findall("node"):
            visit(child, M, depth + 1)
        for inst in node.findall("instance_node"):
            if inst.get("url", "")[1:] in library_nodes:
                visit(library_nodes[inst.get("url")[1:]], M, depth + 1)

    if scene is not None:
        for node in scene.findall("node"):
            visit(node, np.eye(4))
    else:   # no scene: every geometry where it is
        for g in geoms.values():
            parts.extend(_geometry(g))
    parts = [(v, t) for v, t in parts if t.size]
    if not parts:
        raise ColladaError("no triangles")
    starts = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    vertices = np.concatenate([v for v, _ in parts]) * meter
    triangles = np.concatenate([t + s for (_, t), s in zip(parts, starts, strict=True)])
    used, triangles = np.unique(triangles, return_inverse=True)   # the vertices drawn
    return vertices[used], triangles.reshape(-1, 3)
