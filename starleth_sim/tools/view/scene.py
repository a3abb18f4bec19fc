"""The 3D scene of a ``starleth-view`` page as meshcat commands: the robot's URDF visuals as
three.js objects (its meshes within the page's triangle budget), the checkerboard ground, the
force arrows, the background and the camera."""
from __future__ import annotations

import base64
import math
import struct
import xml.etree.ElementTree as ET
import zlib

import numpy as np
import pinocchio as pin

from starleth_interface.robot.scaling import RobotScale, robot_scale
from starleth_interface.robot.urdf import urdf_origin

from ...physics.description import RobotDescription
from ...robots.meshes import MeshError, read_mesh, resolve_mesh, simplified
from .recording import Recording, warn

#: colours (0xRRGGBB): a distinctive orange robot, green arrows, grey ground, blue-grey sky
ROBOT_COLOR = 0xF07818      # boxes (the trunk)
LEG_COLOR = 0xD2600C        # cylinders (hips, thighs, shanks)
FOOT_COLOR = 0x303030       # spheres (feet)
ARROW_COLOR = 0x18B43C
GROUND_COLORS = ((0xD6, 0xD6, 0xCC), (0xBC, 0xBC, 0xB2))   # unlit 0.5 m checkerboard
GROUND_SQUARE = 0.5         # [m]
TERRAIN_COLOR = 0x9A9A8E    # boxes and heightfield (lit, a little darker than the ground)
#: a heightfield is drawn with at most this many points a side (every k-th point)
TERRAIN_DRAWN_POINTS = 128
SKY_TOP, SKY_BOTTOM = (0.84, 0.89, 0.95), (0.62, 0.69, 0.78)
#: camera position relative to the followed trunk point, world axes [m], for StarlETH (times
#: λ, page_scale, for a page of other robots)
CAMERA_OFFSET = (0.9, -1.35, 0.42)
ARROW_HEAD = 0.05           # length of an arrow's cone [m] (times λ as the camera offset)
ARROW_RADIUS = 0.011        # of its shaft [m] (the cone: 2.5 times that)
#: the mesh triangles a page holds, all robots together (20-30 bytes each in the page):
#: the meshes of a robot with more are simplified, each to its share
PAGE_TRIANGLES = 60_000
#: a mesh keeps at least this many triangles
MIN_MESH_TRIANGLES = 12


def page_scale(descs) -> RobotScale:
    """The scale of a page's camera distance and arrows: the RobotScale (λ, μ vs StarlETH)
    of its largest robot (the longest legs)."""
    return max((robot_scale(d.legs, d.total_mass) for d in descs), key=lambda s: s.length)


def _matrix(M4) -> list:
    """A 4x4 homogeneous matrix as meshcat/three.js want it: 16 numbers, column-major."""
    return [float(round(x, 6)) + 0.0 for x in np.asarray(M4, dtype=float).T.reshape(16)]


def _mesh(uid: str, name: str, geometry: dict, color: int, matrix, **material) -> dict:
    """A three.js JSON object (format 4.5, what meshcat's set_object takes): one Mesh."""
    mat = {"uuid": f"{uid}/material", "type": "MeshLambertMaterial", "color": color,
           "side": 2, **material}
    return {"metadata": {"version": 4.5, "type": "Object"},
            "geometries": [dict(geometry, uuid=f"{uid}/geometry")],
            "materials": [mat],
            "object": {"uuid": uid, "type": "Mesh", "name": name,
                       "geometry": f"{uid}/geometry", "material": f"{uid}/material",
                       "matrix": _matrix(matrix)}}


_ROT_Y_TO_Z = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])


def _visual_geometry(geom):
    """(three.js geometry dict, extra 4x4 intrinsic transform, colour) of a URDF <geometry>
    element, or None for a mesh or an unknown shape."""
    box, sphere, cyl = geom.find("box"), geom.find("sphere"), geom.find("cylinder")
    if box is not None:
        x, y, z = (float(v) for v in box.get("size").split())
        return {"type": "BoxGeometry", "width": x, "height": y, "depth": z}, np.eye(4), \
            ROBOT_COLOR
    if sphere is not None:
        return {"type": "SphereGeometry", "radius": float(sphere.get("radius")),
                "widthSegments": 20, "heightSegments": 14}, np.eye(4), FOOT_COLOR
    if cyl is not None:   # three.js cylinders lie along y, URDF ones along z
        r = float(cyl.get("radius"))
        return {"type": "CylinderGeometry", "radiusTop": r, "radiusBottom": r,
                "height": float(cyl.get("length")), "radialSegments": 20}, _ROT_Y_TO_Z, \
            LEG_COLOR
    return None


def _color(vis, materials: dict, default: int) -> int:
    """The colour of a <visual>: its <material>'s rgba, or that of the URDF's material of
    that name, else `default`."""
    mat = vis.find("material")
    color = mat.find("color") if mat is not None else None
    rgba = color.get("rgba") if color is not None else materials.get(
        mat.get("name") if mat is not None else None)
    try:
        r, g, b = (min(255, max(0, round(float(x) * 255))) for x in rgba.split()[:3])
    except (AttributeError, ValueError, TypeError):
        return default
    return (r << 16) | (g << 8) | b


def _inertia_box(link):
    """(three.js box, its 4x4 pose in the link frame) of the box with the link's mass and
    inertia (its principal axes at its <inertial> origin), or None."""
    inertial = link.find("inertial")
    try:
        m = float(inertial.find("mass").get("value"))
        i = inertial.find("inertia")
        inertia = np.array([[float(i.get(a, 0)) for a in row] for row in
                            (("ixx", "ixy", "ixz"), ("ixy", "iyy", "iyz"),
                             ("ixz", "iyz", "izz"))])
        moments, axes = np.linalg.eigh(inertia)
    except (AttributeError, TypeError, ValueError, np.linalg.LinAlgError):
        return None
    if not (m > 0 and np.all(np.isfinite(moments))):
        return None
    total = moments.sum()
    size = [math.sqrt(max(6.0 * (total - 2 * mk) / m, 1e-6)) for mk in moments]
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1
    M = urdf_origin(inertial).homogeneous @ np.block([[axes, np.zeros((3, 1))],
                                                       [np.zeros((1, 3)), np.ones((1, 1))]])
    return {"type": "BoxGeometry", "width": size[0], "height": size[1], "depth": size[2]}, M


def _fallback_shapes(link) -> list:
    """[(geometry, 4x4 pose in the link frame, colour)] drawn for a link whose mesh cannot
    be read: its collision primitives, else its inertia box."""
    out = []
    for coll in link.findall("collision"):
        try:
            shape = _visual_geometry(coll.find("geometry"))
        except (TypeError, ValueError, AttributeError):
            shape = None
        if shape is not None:
            geometry, intrinsic, color = shape
            out.append((geometry, urdf_origin(coll).homogeneous @ intrinsic, color))
    box = None if out else _inertia_box(link)
    return out or ([(box[0], box[1], ROBOT_COLOR)] if box else [])


def _mesh_file(geom, meshes):
    """(path, scale) of a <mesh> geometry's file; MeshError naming it where it is not there."""
    mesh = geom.find("mesh")
    scale = tuple(float(x) for x in (mesh.get("scale") or "1 1 1").split())
    if len(scale) != 3:
        raise MeshError(f"mesh {mesh.get('filename')}: scale must be three numbers")
    return resolve_mesh(mesh.get("filename") or "", *meshes), scale


def _link_shapes(link, meshes, materials, failed) -> list:
    """[(k, geometry or ('mesh', path, scale), 4x4 pose in the link frame, colour)] of a
    link's visuals; a mesh that cannot be read: its fallback shapes, noted in `failed`
    ({message: [links]})."""
    out = []
    for k, vis in enumerate(link.findall("visual")):
        geom = vis.find("geometry")
        origin = urdf_origin(vis).homogeneous
        if geom is not None and geom.find("mesh") is not None:
            try:
                if meshes is None:
                    raise MeshError(f"mesh {geom.find('mesh').get('filename')}: not drawn")
                path, scale = _mesh_file(geom, meshes)
                read_mesh(path, scale)
            except (MeshError, ValueError) as e:
                failed.setdefault(str(e), []).append(link.get("name"))
                out += [(k, g, M, c) for g, M, c in _fallback_shapes(link)]
                continue
            out.append((k, ("mesh", path, scale), origin, _color(vis, materials, ROBOT_COLOR)))
            continue
        try:
            shape = _visual_geometry(geom) if geom is not None else None
        except (TypeError, ValueError, AttributeError):   # missing/odd attributes
            shape = None
        if shape is None:
            warn(f"link {link.get('name')}: visual {k} is not a box, sphere, cylinder or "
                 "mesh; not drawn")
            continue
        geometry, intrinsic, color = shape
        out.append((k, geometry, origin @ intrinsic, _color(vis, materials, color)))
    return out


def _mesh_geometry(path, scale, max_triangles) -> dict:
    """A three.js BufferGeometry of a mesh file, simplified to max_triangles."""
    v, t = simplified(*read_mesh(path, scale), max_triangles)
    return {"type": "BufferGeometry", "data": {
        "attributes": {"position": {"itemSize": 3, "type": "Float32Array",
                                    "array": (np.round(v.ravel(), 5) + 0.0).tolist(),
                                    "normalized": False}},
        "index": {"type": "Uint32Array", "array": t.ravel().tolist()}}}


def robot_visuals(desc: RobotDescription, robot: str = "", meshes=None,
                  triangles: int = PAGE_TRIANGLES):
    """[(pin joint id, visual name, three.js object)] of the URDF's <visual> elements, each
    placed in the frame of the joint that moves it (fixed joints merged by pin); `robot`
    (the robot's frame prefix) keeps the objects' ids apart from another robot's. Meshes
    (meshes: (package roots, directory of relative paths), None: not drawn) within
    `triangles` in all: each simplified to its share (its triangles' fraction of the
    whole); one that cannot be read: one warning naming it, the link's collision
    primitives (else its inertia box) drawn instead."""
    model = desc.model
    root = ET.fromstring(desc.urdf_xml)
    materials = {m.get("name"): m.find("color").get("rgba") for m in root.findall("material")
                 if m.find("color") is not None}
    failed, items = {}, []
    for link in root.findall("link"):
        lname = link.get("name")
        shapes = _link_shapes(link, meshes, materials, failed)
        if not model.existFrame(lname, pin.FrameType.BODY):
            continue
        frame = model.frames[model.getFrameId(lname, pin.FrameType.BODY)]
        several = len(shapes) > 1
        for n, (_k, geometry, M, color) in enumerate(shapes):
            name = f"{lname}_{n}" if several else lname
            items.append((int(frame.parentJoint), name, geometry,
                          pin.SE3(frame.placement).homogeneous @ M, color))
    for message, links in failed.items():
        warn(f"{message}; drawn as primitives (link {', '.join(dict.fromkeys(links))})")
    sizes = [len(read_mesh(*g[1:])[1]) for _, _, g, _, _ in items if isinstance(g, tuple)]
    share = min(1.0, triangles / sum(sizes)) if sizes else 1.0
    out = []
    for joint, name, geometry, M, color in items:
        extra = {}
        if isinstance(geometry, tuple):
            n = len(read_mesh(*geometry[1:])[1])
            geometry = _mesh_geometry(*geometry[1:], max(MIN_MESH_TRIANGLES, int(share * n)))
            extra = {"flatShading": True}
        out.append((joint, name, _mesh(f"robots/{robot}{name}", name, geometry, color, M,
                                       **extra)))
    return out


def _ground_pose(height, normal, centre_xy):
    """4x4 pose of the ground plane: z axis along the normal, origin on the plane below
    centre_xy."""
    n = np.asarray(normal, dtype=float)
    z = np.array([0.0, 0.0, 1.0])
    axis, c = np.cross(z, n), float(np.dot(z, n))
    R = np.eye(3)
    if np.linalg.norm(axis) > 1e-9:
        K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        R = np.eye(3) + K + K @ K / (1.0 + c)
    x, y = centre_xy
    pz = (height - n[0] * x - n[1] * y) / n[2] if abs(n[2]) > 0.1 else 0.0
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, ((x, y, pz) if abs(n[2]) > 0.1 else height * n)
    return M


def _png_rgb(pixels) -> bytes:
    """A PNG file of an (h, w, 3) uint8 RGB image."""
    pixels = np.asarray(pixels, dtype=np.uint8)
    h, w, _ = pixels.shape
    raw = b"".join(b"\x00" + pixels[r].tobytes() for r in range(h))

    def chunk(tag, data):
        return (struct.pack(">I", len(data)) + tag + data
                + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def _ground_object(size: float, tile: float) -> dict:
    """The ground: a size x size plane (in its xy plane), unlit, with a checkerboard
    texture (a 2x2 PNG repeated every `tile` m)."""
    a, b = GROUND_COLORS
    png = base64.b64encode(_png_rgb([[a, b], [b, a]])).decode("ascii")
    obj = _mesh("ground", "ground", {"type": "PlaneGeometry", "width": size, "height": size},
                0xFFFFFF, np.eye(4), type="MeshBasicMaterial", map="ground/texture")
    obj["images"] = [{"uuid": "ground/image", "url": "data:image/png;base64," + png}]
    obj["textures"] = [{"uuid": "ground/texture", "image": "ground/image",
                        "wrap": [1000, 1000],                 # RepeatWrapping
                        "repeat": [size / tile, size / tile],
                        "magFilter": 1003}]                   # NearestFilter
    return obj


def terrain_objects(terrain, ground_height=0.0) -> list:
    """[(name, three.js object)] of a terrain (physics.terrain.TerrainConfig): each box
    (stairs included) and the heightfield as a triangle mesh (every k-th point of its grid,
    at most TERRAIN_DRAWN_POINTS a side)."""
    out = []
    for k, b in enumerate(terrain.all_boxes(ground_height)):
        M = np.eye(4)
        c, s = math.cos(b["yaw"]), math.sin(b["yaw"])
        M[:2, :2] = [[c, -s], [s, c]]
        M[:3, 3] = b["centre"]
        sx, sy, sz = b["size"]
        out.append((f"box{k}", _mesh(f"terrain/box{k}", f"terrain box {k}", {
            "type": "BoxGeometry", "width": sx, "height": sy, "depth": sz}, TERRAIN_COLOR, M)))
    grid = terrain.grid(ground_height)
    if grid is not None:
        (x0, y0), cell, heights, _ = grid
        step = max(1, math.ceil(max(heights.shape) / TERRAIN_DRAWN_POINTS))
        ix = np.unique(np.r_[np.arange(0, heights.shape[0], step), heights.shape[0] - 1])
        iy = np.unique(np.r_[np.arange(0, heights.shape[1], step), heights.shape[1] - 1])
        X, Y = np.meshgrid(x0 + ix * cell, y0 + iy * cell, indexing="ij")
        pts = np.stack([X, Y, heights[np.ix_(ix, iy)]], axis=-1).reshape(-1, 3)
        nx, ny = len(ix), len(iy)
        a = (np.arange(nx - 1)[:, None] * ny + np.arange(ny - 1)[None, :]).ravel()
        tri = np.stack([a, a + ny, a + 1, a + 1, a + ny, a + ny + 1], axis=1).ravel()
        geometry = {"type": "BufferGeometry", "data": {
            "attributes": {"position": {"itemSize": 3, "type": "Float32Array",
                                        "array": np.round(pts.ravel(), 5).tolist(),
                                        "normalized": False}},
            "index": {"type": "Uint32Array", "array": tri.tolist()}}}
        out.append(("heightfield", _mesh("terrain/heightfield", "terrain heightfield",
                                         geometry, TERRAIN_COLOR, np.eye(4),
                                         flatShading=True)))
    return out


def body_frames(desc: RobotDescription, joint_ids, prefix: str) -> list:
    """The frame names (as on /tf: prefix + link) of the bodies the pin joints joint_ids
    move: each joint's child link (the first body frame on it; fixed links are merged
    into it)."""
    model = desc.model
    out = []
    for j in joint_ids:
        link = next(f.name for f in model.frames
                    if f.parentJoint == j and f.type == pin.FrameType.BODY)
        out.append(prefix + link)
    return out


def scene_commands(ground: Recording, robots, trunk_xy, scale: float = 1.0) -> list:
    """meshcat commands that build the scene: background, a checkerboard ground plane (in
    place of meshcat's grid) and the terrain of `ground` (a Recording), for each robot
    (robots: [(Recording, visuals, {pin joint id: frame name}, name)]) its visuals under
    /world/robots/<frame> (its bodies' frames as on /tf: robot1/base, ...) and its force
    arrows under /world/forces/<name><foot>, the camera; `scale` (λ of page_scale) scales
    the camera's distance and the arrows' thickness. The page follows the trunks (their
    mean point) by moving /world so that it stays at the origin, which meshcat's orbit
    controls turn the camera around."""
    lo, hi = trunk_xy.min(axis=0), trunk_xy.max(axis=0)
    tile = 2 * GROUND_SQUARE
    centre = np.round((lo + hi) / 2 / tile) * tile         # squares on multiples of 0.5 m
    size = tile * 2 * math.ceil((float(np.max(hi - lo)) + 40.0) / (2 * tile))
    cmds = [
        {"type": "set_property", "path": "/Background", "property": "top_color",
         "value": list(SKY_TOP)},
        {"type": "set_property", "path": "/Background", "property": "bottom_color",
         "value": list(SKY_BOTTOM)},
        {"type": "set_property", "path": "/Axes", "property": "visible", "value": False},
        {"type": "set_property", "path": "/Grid", "property": "visible", "value": False},
        {"type": "set_object", "path": "/world/ground", "object": _ground_object(size, tile)},
        {"type": "set_transform", "path": "/world/ground", "matrix": _matrix(
            _ground_pose(ground.ground_height, ground.ground_normal, centre))},
    ]
    if ground.terrain is not None:
        for name, obj in terrain_objects(ground.terrain, ground.ground_height):
            cmds.append({"type": "set_object", "path": f"/world/terrain/{name}", "object": obj})
    for rec, visuals, frames, robot in robots:
        for joint, name, obj in visuals:
            cmds.append({"type": "set_object", "path": f"/world/robots/{frames[joint]}/{name}",
                         "object": obj})
        cmds += _arrow_objects(rec, robot, scale)
    # the camera's position relative to the point it orbits (the origin), given in the
    # Y-up frame of /Cameras/default/rotated: (x, z, -y) of the world
    ox, oy, oz = (scale * c for c in CAMERA_OFFSET)
    cmds.append({"type": "set_property", "path": "/Cameras/default/rotated/<object>",
                 "property": "position", "value": [ox, oz, -oy]})
    return cmds


def _arrow_objects(rec: Recording, robot: str, size: float) -> list:
    """The force arrows of a robot (`robot`: its frame prefix), a shaft and a head per foot
    with force messages (its foot contact name), under /world/forces/<robot><foot>; their
    head and radius times `size`."""
    cmds = []
    shaft = np.eye(4)
    shaft[1, 3] = 0.5                                      # unit cylinder from y=0 to y=1
    head = np.eye(4)
    head[1, 3] = size * ARROW_HEAD / 2                     # cone from y=0 to the tip
    radius = size * ARROW_RADIUS
    for foot in rec.wrenches:
        path = f"forces/{robot}{foot}"
        cmds.append({"type": "set_object", "path": f"/world/{path}/shaft",
                     "object": _mesh(f"{path}/shaft", f"{robot}{foot} force", {
                         "type": "CylinderGeometry", "radiusTop": radius,
                         "radiusBottom": radius, "height": 1.0, "radialSegments": 12},
                         ARROW_COLOR, shaft)})
        cmds.append({"type": "set_object", "path": f"/world/{path}/head",
                     "object": _mesh(f"{path}/head", f"{robot}{foot} force head", {
                         "type": "ConeGeometry", "radius": 2.5 * radius,
                         "height": size * ARROW_HEAD,
                         "radialSegments": 12}, ARROW_COLOR, head)})
    return cmds

