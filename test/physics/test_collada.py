"""starleth_sim.robots.collada: a .dae file's triangles, each primitive element (a
material) indexing its own vertices, node transforms and units applied; the library's
multi-material meshes (Go2) drawn whole, their triangles spanning the link's collision mesh."""
from __future__ import annotations

import numpy as np
import pytest

from starleth_sim.robots.collada import read_collada
from starleth_sim.robots.meshes import read_mesh, resolve_mesh

# two materials: a unit right triangle in z=0 (<triangles>) and a unit square in x=2
# (<polylist>, one quad), the node moving everything by (0, 0, 10) and rotating it 90 deg
# about z, in centimetres
DAE = """<?xml version="1.0"?>
<COLLADA xmlns="http://www.collada.org/2005/11/COLLADASchema" version="1.4.1">
 <asset><unit name="centimeter" meter="0.01"/><up_axis>Y_UP</up_axis></asset>
 <library_geometries><geometry id="g"><mesh>
  <source id="a"><float_array id="aa" count="9">0 0 0 1 0 0 0 1 0</float_array>
   <technique_common><accessor source="#aa" count="3" stride="3"/></technique_common></source>
  <source id="b"><float_array id="ba" count="12">2 0 0 2 1 0 2 1 1 2 0 1</float_array>
   <technique_common><accessor source="#ba" count="4" stride="3"/></technique_common></source>
  <source id="n"><float_array id="na" count="3">0 0 1</float_array>
   <technique_common><accessor source="#na" count="1" stride="3"/></technique_common></source>
  <vertices id="va"><input semantic="POSITION" source="#a"/></vertices>
  <vertices id="vb"><input semantic="POSITION" source="#b"/></vertices>
  <triangles material="m1" count="1"><input semantic="VERTEX" source="#va" offset="0"/>
   <input semantic="NORMAL" source="#n" offset="1"/><p>0 0 1 0 2 0</p></triangles>
  <polylist material="m2" count="1"><input semantic="VERTEX" source="#vb" offset="0"/>
   <vcount>4</vcount><p>0 1 2 3</p></polylist>
 </mesh></geometry></library_geometries>
 <library_visual_scenes><visual_scene id="s"><node id="n1">
  <translate>0 0 10</translate><rotate>0 0 1 90</rotate>
  <instance_geometry url="#g"/></node></visual_scene></library_visual_scenes>
 <scene><instance_visual_scene url="#s"/></scene>
</COLLADA>
"""


def area(v, t):
    a = v[t]
    return 0.5 * np.linalg.norm(np.cross(a[:, 1] - a[:, 0], a[:, 2] - a[:, 0]), axis=1)


def test_each_material_indexes_its_own_vertices_transformed_and_in_metres(tmp_path):
    path = tmp_path / "two.dae"
    path.write_text(DAE)
    v, t = read_collada(str(path))
    assert t.shape == (3, 3) and len(v) == 7
    # areas: the triangle 0.5 cm^2, the square 1 cm^2 in two triangles, in m^2
    assert np.allclose(np.sort(area(v, t)), [0.5e-4, 0.5e-4, 0.5e-4])
    # rotated 90 deg about z (x -> y), then 10 cm up
    square = v[np.unique(t[1:])]
    assert np.allclose(square[:, 1], 0.02) and np.allclose(np.sort(square[:, 2])[[0, -1]],
                                                          [0.10, 0.11])
    assert np.allclose(v[np.unique(t[0])][:, 2], 0.10)


@pytest.mark.parametrize("link", ["FL_thigh", "RR_calf"])
def test_go2_multi_material_meshes_span_their_collision_mesh(link):
    """Go2's visuals have several materials each: their triangles (not only their
    vertices) reach the ends of the link's collision mesh, and no triangle is longer than
    the mesh."""
    import xml.etree.ElementTree as ET

    from starleth_sim.robots import load_robot, package_dirs, robot_description
    try:
        desc = robot_description("go2")
    except Exception as e:   # example-robot-data not installed: make robots
        pytest.skip(f"go2: {e}")
    roots = package_dirs(load_robot("go2"))
    el = ET.fromstring(desc.urdf_xml).find(f"link[@name='{link}']")
    vis = read_mesh(resolve_mesh(el.find("visual/geometry/mesh").get("filename"), roots))
    coll = [read_mesh(resolve_mesh(m.get("filename"), roots))[0]
            for m in el.findall("collision/geometry/mesh")]
    lo, hi = np.min([c.min(0) for c in coll], 0), np.max([c.max(0) for c in coll], 0)
    v, t = vis
    centres = v[t].mean(axis=1)
    assert np.all(centres.min(0) < lo + 0.3 * (hi - lo))
    assert np.all(centres.max(0) > hi - 0.3 * (hi - lo))
    edges = np.linalg.norm(v[t] - v[np.roll(t, 1, axis=1)], axis=2)
    assert edges.max() < 0.5 * np.linalg.norm(hi - lo)


@pytest.mark.parametrize("text", ["<COLLADA><library_geometries>", DAE.replace("0 1 2", "0 1 7"),
                                  DAE.replace("<p>0 1 2 3</p>", "").replace("0 0 1 0 2 0", "")])
def test_a_dae_that_cannot_be_drawn_is_a_mesh_error_naming_it(tmp_path, text):
    """Not XML, an index past its vertices, no triangles: MeshError naming the file."""
    from starleth_sim.robots.meshes import MeshError
    path = tmp_path / "bad.dae"
    path.write_text(text)
    with pytest.raises(MeshError, match=r"mesh .*bad\.dae: cannot be read"):
        read_mesh(str(path))
