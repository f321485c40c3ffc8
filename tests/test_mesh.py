"""TriMesh topology (the notes' edge sort), generators, loaders and validation."""

import numpy as np
import pytest

from warp_cloth.mesh import TriMesh, edge_triples

FIVE_V = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
FIVE_T = np.array([[1, 2, 3], [0, 1, 3], [0, 3, 4]])


def five_vertex_mesh():
    # positions chosen so that no triangle is degenerate; only connectivity matters
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 1, 0], [1, 1.5, 0], [-0.5, 1, 0]], dtype=float)
    return TriMesh(v, FIVE_T)


def test_five_vertex_golden_case():
    """physics.md 4.A item 1: triples, sorted triples, edges, interior edges, bending pairs."""
    trip = edge_triples(FIVE_T)
    assert trip.tolist() == [[0, 1, 1], [0, 3, 1], [0, 3, 2], [0, 4, 2], [1, 2, 0],
                             [1, 3, 0], [1, 3, 1], [2, 3, 0], [3, 4, 2]]
    m = five_vertex_mesh()
    assert m.edges.tolist() == [[0, 1], [0, 3], [0, 4], [1, 2], [1, 3], [2, 3], [3, 4]]
    interior = {tuple(e): tuple(t) for e, t in zip(m.edges.tolist(), m.edge_tris.tolist()) if t[1] >= 0}
    assert interior == {(0, 3): (1, 2), (1, 3): (0, 1)}
    pairs = {tuple(sorted(p)) for p in m.bending_pairs.tolist()}
    assert pairs == {(1, 4), (0, 2)}
    assert sorted(map(tuple, m.boundary_edges.tolist())) == [(0, 1), (0, 4), (1, 2), (2, 3), (3, 4)]
    assert len(m.edges) == 3 * 5 - 3 - 5  # Euler relation (T22)


def test_bend_quads_orientation():
    m = five_vertex_mesh()
    for a, b, c, d in m.bend_quads:
        # (a, b, c) is a triangle of the mesh in its own winding; (b, a, d) is the other one
        tris = {tuple(np.roll(t, k)) for t in m.triangles.tolist() for k in range(3)}
        assert (a, b, c) in tris and (b, a, d) in tris


@pytest.mark.parametrize("nx,ny,diag", [(1, 1, "fixed"), (4, 3, "alternating"), (7, 5, "fixed"), (6, 6, "alternating")])
def test_grid_euler_relation(nx, ny, diag):
    m = TriMesh.grid(nx, ny, size=(2.0, 1.0), diagonals=diag)
    V, E, B = m.num_vertices, len(m.edges), len(m.boundary_edges)
    assert V == (nx + 1) * (ny + 1) and m.num_triangles == 2 * nx * ny
    assert E == 3 * V - 3 - B
    assert B == 2 * (nx + ny)
    assert np.isclose(m.triangle_areas().sum(), 2.0)
    assert len(m.bend_quads) == E - B


def test_grid_planes_and_orientation():
    for plane, normal in (("xy", [0, 0, 1]), ("xz", [0, -1, 0]), ("yz", [1, 0, 0])):
        m = TriMesh.grid(2, 2, plane=plane)
        x, t = m.vertices, m.triangles
        n = np.cross(x[t[:, 1]] - x[t[:, 0]], x[t[:, 2]] - x[t[:, 0]])
        assert np.allclose(n / np.linalg.norm(n, axis=1, keepdims=True), normal)


def test_alternating_diagonals_differ():
    a = TriMesh.grid(2, 1, diagonals="fixed")
    b = TriMesh.grid(2, 1, diagonals="alternating")
    assert {tuple(e) for e in a.edges.tolist()} != {tuple(e) for e in b.edges.tolist()}


@pytest.mark.parametrize("verts,tris,match", [
    (FIVE_V, [[0, 1, 5]], r"triangle 0 has vertex index 5 out of range"),
    (FIVE_V, [[0, 1, 3], [0, -1, 3]], r"triangle 1 has vertex index -1"),
    (FIVE_V, [[0, 1, 3], [2, 2, 3]], r"triangle 1 repeats a vertex"),
    (FIVE_V, [[0, 1, 2]], r"triangle 0 \[0, 1, 2\] has zero area"),
    (FIVE_V, [[0, 1, 3], [1, 3, 0]], r"triangles \[0, 1\] are duplicates"),
    (np.array([[0, 0, 0], [1, 0, np.nan], [0, 1, 0]]), [[0, 1, 2]], r"vertex 1 has a non-finite"),
    (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]]),
     [[0, 1, 2], [1, 0, 3], [0, 1, 4]], r"non-manifold edge \(0, 1\) is shared by 3 triangles \[0, 1, 2\]"),
    (FIVE_V, [[0, 1]], r"triangles must have shape"),
    (FIVE_V[:, :2], [[0, 1, 3]], r"vertices must have shape"),
])
def test_validation_errors(verts, tris, match):
    with pytest.raises(ValueError, match=match):
        TriMesh(np.asarray(verts, dtype=float), np.asarray(tris))


def test_grid_bad_arguments():
    with pytest.raises(ValueError, match="positive integers"):
        TriMesh.grid(0, 3)
    with pytest.raises(ValueError, match="plane"):
        TriMesh.grid(2, 2, plane="xw")
    with pytest.raises(ValueError, match="size"):
        TriMesh.grid(2, 2, size=-1.0)


def test_obj_round_trip(tmp_path):
    m = TriMesh.grid(3, 2, size=(1.5, 1.0), plane="xy")
    p = tmp_path / "m.obj"
    m.to_obj(p)
    r = TriMesh.from_obj(p)
    assert np.allclose(r.vertices, m.vertices) and np.array_equal(r.triangles, m.triangles)


def test_obj_forms_quads_polygons_and_negative_indices(tmp_path):
    p = tmp_path / "q.obj"
    p.write_text(
        "# a quad, a pentagon and a triangle with relative indices\n"
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\n"
        "f 1/1/1 2/1/1 3/1/1 4/1/1\n"
        "v 2 0 0\nv 3 0 0\nv 3 1 0\nv 2.5 1.5 0\nv 2 1 0\n"
        "f 5//1 6//1 7//1 8//1 9//1\n"
        "v 0 2 0\nf -1 4/1 3\n"
    )
    m = TriMesh.from_obj(p)
    assert m.num_vertices == 10
    assert m.triangles.tolist() == [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7], [4, 7, 8], [9, 3, 2]]


def test_obj_errors(tmp_path):
    p = tmp_path / "bad.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    with pytest.raises(ValueError, match="out of range"):
        TriMesh.from_obj(p)
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 x 3\n")
    with pytest.raises(ValueError, match=r"bad.obj:4: bad face index 'x'"):
        TriMesh.from_obj(p)


def test_usd_round_trip(tmp_path):
    from pxr import Usd, UsdGeom, Gf

    from warp_cloth.usd import UsdWriter

    m = TriMesh.grid(3, 3, size=1.0, plane="xz", origin=(-0.5, 1.0, -0.5))
    path = tmp_path / "mesh.usda"
    with UsdWriter(path, fps=24) as w:
        w.add_mesh("sheet", m.triangles, points=m.vertices)
    r = TriMesh.from_usd(path)
    assert np.allclose(r.vertices, m.vertices, atol=1e-6)
    assert np.array_equal(r.triangles, m.triangles)
    # a quad mesh with a transform: fan-triangulated, points in world space
    stage = Usd.Stage.CreateNew(str(tmp_path / "quad.usda"))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)  # unauthored, USD's fallback is 0.01 (cm)
    xf = UsdGeom.Xform.Define(stage, "/X")
    xf.AddTranslateOp().Set(Gf.Vec3d(0, 2, 0))
    q = UsdGeom.Mesh.Define(stage, "/X/Q")
    q.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
    q.CreateFaceVertexCountsAttr([4])
    q.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    stage.Save()
    r = TriMesh.from_usd(tmp_path / "quad.usda")
    assert r.triangles.tolist() == [[0, 1, 2], [0, 2, 3]]
    assert np.allclose(r.vertices[:, 1], [2, 2, 3, 3])


def test_usd_obstacle_takes_every_mesh_of_the_stage(tmp_path):
    """An obstacle stage of several meshes (a seat and a leg under their own transforms): the
    obstacle has every part, in world space and metres; a cloth read from the same stage is its
    first mesh, as before. Only the first was taken for the obstacle too: the other parts were
    dropped without a word."""
    from pxr import Gf, Usd, UsdGeom

    from warp_cloth.collision import MeshObstacle
    from warp_cloth.contact_scenes import load_obstacle_mesh

    part = TriMesh.icosphere(1, 0.1)  # a closed part
    stage = Usd.Stage.CreateNew(str(tmp_path / "chair.usda"))
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)  # centimetres
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    for k, (name, y) in enumerate((("seat", 50.0), ("leg", 20.0))):
        xf = UsdGeom.Xform.Define(stage, f"/Chair/{name}")
        xf.AddTranslateOp().Set(Gf.Vec3d(10.0 * k, y, 0.0))
        m = UsdGeom.Mesh.Define(stage, f"/Chair/{name}/mesh")
        m.CreatePointsAttr([tuple(p) for p in (part.vertices * 100.0).tolist()])
        m.CreateFaceVertexCountsAttr([3] * len(part.triangles))
        m.CreateFaceVertexIndicesAttr(np.asarray(part.triangles).ravel().tolist())
    stage.Save()
    path = tmp_path / "chair.usda"
    ob = MeshObstacle(str(path))
    assert len(ob.vertices) == 2 * len(part.vertices) and ob.closed
    assert np.isclose(ob.vertices[:, 1].max(), 0.6) and np.isclose(ob.vertices[:, 1].min(), 0.1)
    tm, position, height = load_obstacle_mesh(path)
    assert len(tm.vertices) == 2 * len(part.vertices) and np.isclose(position[1], -0.1)
    assert len(TriMesh.from_usd(path).vertices) == len(part.vertices)


def _two_patches(gap=0.0, jitter=0.0):
    a = TriMesh.grid(2, 2, size=1.0, plane="xz")
    b = TriMesh.grid(2, 2, size=1.0, plane="xz", origin=(1.0 + gap, 0.0, 0.0))
    v = np.concatenate([a.vertices, b.vertices])
    v[9] += jitter  # b's first vertex, on the shared border with a's vertex 2
    return TriMesh(v, np.concatenate([a.triangles, b.triangles + 9]))


def test_coincident_vertices_and_weld():
    """Two 2x2 patches whose shared border is written twice (vertices 2, 5, 8 of the first at
    the positions of 9, 12, 15 of the second): found exactly or within a tolerance, merged by
    `weld` into one sheet whose triangles now share the border (its edges are no longer two)."""
    m = _two_patches()
    assert m.coincident_vertices().tolist() == [[2, 9], [5, 12], [8, 15]]
    w, index = m.weld()
    assert w.num_vertices == 15 and len(w.edges) == len(m.edges) - 2
    assert index[9] == index[2] and index[12] == index[5] and index[15] == index[8]
    assert np.allclose(w.vertices[index], m.vertices)  # every old vertex maps to its position
    # one 4 x 2-cell sheet: no seam left in its interior (each patch had 8 boundary edges)
    assert len(m.boundary_edges) == 16 and len(w.boundary_edges) == 12
    near = _two_patches(jitter=3e-7)
    assert near.coincident_vertices().tolist() == [[5, 12], [8, 15]]
    assert near.coincident_vertices(1e-6).tolist() == [[2, 9], [5, 12], [8, 15]]
    assert near.coincident_vertices(1e-7).tolist() == [[5, 12], [8, 15]]
    assert len(_two_patches(gap=5e-4).coincident_vertices(1e-4)) == 0
    assert len(TriMesh.grid(8, 8).coincident_vertices(1e-3)) == 0
    with pytest.raises(ValueError, match="tolerance"):
        m.coincident_vertices(-1.0)


def test_weld_refuses_what_it_would_collapse(tmp_path):
    # a triangle whose two vertices coincide cannot be welded (validation names it) ...
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1e-9, 0], [2, 0, 0]], dtype=float)
    m = TriMesh(v, np.array([[0, 1, 2], [1, 4, 3]]))
    with pytest.raises(ValueError, match="triangle"):
        m.weld(1e-6)
    # ... and an OBJ with the seam written twice loads welded on request
    p = tmp_path / "seam.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 0 1\nv 1 0 0\nv 1 0 1\nv 0 0 1\nf 1 2 3\nf 4 5 6\n")
    assert TriMesh.from_obj(p).num_vertices == 6
    w = TriMesh.from_obj(p, weld=True)
    assert w.num_vertices == 4 and len(w.edges) == 5
    assert TriMesh.from_obj(p, weld=1e-3).num_vertices == 4
    for bad in (-1.0, "close", float("nan")):
        with pytest.raises(ValueError, match=r"seam\.obj: weld must be"):
            TriMesh.from_obj(p, weld=bad)


def test_icosphere_is_a_closed_sphere_and_checks_its_arguments():
    m = TriMesh.icosphere(2, 0.5)
    assert len(m.triangles) == 20 * 4 ** 2 and len(m.boundary_edges) == 0
    assert np.allclose(np.linalg.norm(m.vertices, axis=1), 0.5)
    v = m.vertices
    t = m.triangles
    n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    assert (np.einsum("ij,ij->i", n, v[t].mean(axis=1)) > 0).all()  # outward
    for bad in ({"subdivisions": -1}, {"subdivisions": 9}, {"radius": 0.0},
                {"radius": float("nan")}):
        with pytest.raises(ValueError, match="icosphere"):
            TriMesh.icosphere(**bad)
