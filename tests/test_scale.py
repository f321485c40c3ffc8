"""Large meshes in linear time: the vectorised topology, grid and spring builders equal the
former per-element loops (kept here verbatim as the reference) on grids and an irregular mesh."""

import numpy as np
import pytest

from warp_cloth.limits import color_constraints
from warp_cloth.mesh import TriMesh
from warp_cloth.model import ClothModel


# ----------------------------------------------------------------- the former loop versions
def loop_grid_triangles(nx, ny, diagonals):
    tris = []
    for cj in range(ny):
        for ci in range(nx):
            v00 = cj * (nx + 1) + ci
            v10, v01, v11 = v00 + 1, v00 + nx + 1, v00 + nx + 2
            if diagonals == "fixed" or (ci + cj) % 2 == 0:
                tris += [(v00, v10, v11), (v00, v11, v01)]
            else:
                tris += [(v00, v10, v01), (v10, v11, v01)]
    return np.asarray(tris, dtype=np.int64)


def loop_bend_quads(mesh):
    """Brute force from the definition: for every interior edge (i, j) (i < j, in edge order)
    shared by t0 = edge_tris[e, 0] and t1: (a, b) as the edge appears in t0's winding, c the third
    vertex of t0, d the third vertex of t1."""
    tri = mesh.triangles
    quads = []
    for e in np.flatnonzero(mesh.edge_tris[:, 1] >= 0):
        i, j = mesh.edges[e]
        t0, t1 = tri[mesh.edge_tris[e, 0]], tri[mesh.edge_tris[e, 1]]
        k = int(np.flatnonzero(t0 == i)[0])
        a, b = (i, j) if t0[(k + 1) % 3] == j else (j, i)
        c = int(t0[(t0 != i) & (t0 != j)][0])
        d = int(t1[(t1 != i) & (t1 != j)][0])
        quads.append((a, b, c, d))
    return np.asarray(quads, dtype=np.int64).reshape(-1, 4)


def loop_edges(triangles):
    """Edges by a dictionary: (min, max) -> the triangles on it, in triangle order."""
    on = {}
    for t, tri in enumerate(np.asarray(triangles).tolist()):
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            on.setdefault((min(a, b), max(a, b)), []).append(t)
    keys = sorted(on)
    edge_tris = np.asarray([on[k] + [-1] * (2 - len(on[k])) for k in keys], dtype=np.int64)
    return np.asarray(keys, dtype=np.int64), edge_tris


def loop_shear_pairs(mesh):
    nx, ny = mesh.grid_shape
    have = {tuple(e) for e in mesh.edges.tolist()}
    out = []
    for j in range(ny):
        for i in range(nx):
            v00 = j * (nx + 1) + i
            for a, b in ((v00, v00 + nx + 2), (v00 + 1, v00 + nx + 1)):
                if (min(a, b), max(a, b)) not in have:
                    out.append((min(a, b), max(a, b)))
    return np.asarray(out, dtype=np.int64).reshape(-1, 2)


def loop_bend_springs(mesh):
    nx, ny = mesh.grid_shape
    out = []
    for j in range(ny + 1):
        for i in range(nx + 1):
            v = j * (nx + 1) + i
            if i + 2 <= nx:
                out.append((v, v + 2))
            if j + 2 <= ny:
                out.append((v, v + 2 * (nx + 1)))
    return np.asarray(out, dtype=np.int64).reshape(-1, 2)


def irregular_mesh(seed=3):
    """A grid with shuffled vertex numbering, shuffled triangles and rotated windings, plus a
    fan around an extra vertex: nothing lines up with the generator's order."""
    g = TriMesh.grid(5, 4, diagonals="alternating")
    rng = np.random.default_rng(seed)
    perm = rng.permutation(g.num_vertices)
    inv = np.empty_like(perm)
    inv[perm] = np.arange(len(perm))
    verts = g.vertices[perm]
    tris = inv[g.triangles]
    tris = tris[rng.permutation(len(tris))]
    roll = rng.integers(0, 3, len(tris))
    tris = np.stack([np.roll(t, r) for t, r in zip(tris, roll)])
    # a flap hinged on a boundary edge of the sheet
    b = TriMesh(verts, tris).boundary_edges[0]
    verts = np.vstack([verts, verts[b[0]] + [0.0, 0.3, 0.1]])
    tris = np.vstack([tris, [b[1], b[0], len(verts) - 1]])
    return TriMesh(verts, tris)


MESHES = [
    lambda: TriMesh.grid(1, 1),
    lambda: TriMesh.grid(3, 2, diagonals="fixed"),
    lambda: TriMesh.grid(6, 5, diagonals="alternating"),
    lambda: TriMesh.grid(7, 3, plane="xy", diagonals="alternating"),
    irregular_mesh,
]


@pytest.mark.parametrize("make", MESHES)
def test_topology_equals_the_loop_definitions(make):
    mesh = make()
    edges, edge_tris = loop_edges(mesh.triangles)
    assert np.array_equal(mesh.edges, edges)
    assert np.array_equal(mesh.edge_tris, edge_tris)
    quads = loop_bend_quads(mesh)
    assert quads.shape[0] == int((edge_tris[:, 1] >= 0).sum())
    assert np.array_equal(mesh.bend_quads, quads)
    assert mesh.bend_quads.dtype == np.int64


@pytest.mark.parametrize("nx,ny", [(1, 1), (2, 3), (5, 4), (8, 1)])
@pytest.mark.parametrize("diagonals", ["alternating", "fixed"])
def test_grid_and_grid_springs_equal_the_loops(nx, ny, diagonals):
    mesh = TriMesh.grid(nx, ny, diagonals=diagonals)
    assert np.array_equal(mesh.triangles, loop_grid_triangles(nx, ny, diagonals))
    model = ClothModel(mesh, shear_stiffness=10.0, bending="springs", bend_stiffness=1.0,
                       device="cpu")
    assert np.array_equal(model._shear_pairs(), loop_shear_pairs(mesh))
    assert np.array_equal(model._bend_spring_pairs(), loop_bend_springs(mesh))
    # fixed diagonals: every cell has exactly one missing diagonal
    if diagonals == "fixed":
        assert len(model._shear_pairs()) == nx * ny


def loop_greedy_colors(pairs, n):
    used = [set() for _ in range(n)]
    out = []
    for i, j in np.asarray(pairs).tolist():
        k = 0
        while k in used[i] or k in used[j]:
            k += 1
        out.append(k)
        used[i].add(k)
        used[j].add(k)
    return np.asarray(out, dtype=np.int64)


@pytest.mark.parametrize("make", MESHES)
def test_colouring_equals_greedy_definition(make):
    mesh = make()
    pairs = np.concatenate([mesh.edges, mesh.bending_pairs])
    colors = color_constraints(pairs, mesh.num_vertices)
    assert np.array_equal(colors, loop_greedy_colors(pairs, mesh.num_vertices))
    for c in np.unique(colors):  # a colour touches every vertex at most once
        v = pairs[colors == c].reshape(-1)
        assert len(np.unique(v)) == len(v)


@pytest.mark.parametrize("make", MESHES)
def test_edge_triples_equal_the_lexicographic_sort(make):
    from warp_cloth.mesh import edge_triples

    tris = make().triangles
    a, b = tris.reshape(-1), tris[:, [1, 2, 0]].reshape(-1)
    trip = np.stack([np.minimum(a, b), np.maximum(a, b), np.repeat(np.arange(len(tris)), 3)], 1)
    ref = trip[np.lexsort((trip[:, 2], trip[:, 1], trip[:, 0]))]
    assert np.array_equal(edge_triples(tris), ref)


def test_pd_fused_jacobi_sweep_gives_the_same_rho():
    """PD's set-up measures Chebyshev's rho by 200 Jacobi sweeps; the fused sweep (one launch
    instead of matvec + update) must give the very same estimate."""
    from warp_cloth.scenes import hanging_model
    from warp_cloth.solvers import make_solver
    from warp_cloth.solvers.linear import estimate_spectral_radius

    model = hanging_model(shape=(6, 5), device="cpu")
    solver = make_solver("pd", model)
    solver.prepare(1.0 / 240.0)
    A = solver.operator
    fused = estimate_spectral_radius(A, 1.0, iterations=60)
    A.jacobi_sweep = lambda *args: False  # the separate matvec + update path
    separate = estimate_spectral_radius(A, 1.0, iterations=60)
    assert 0.5 < fused < 1.0
    assert fused == separate


def test_scale_helpers_exact():
    import warp as wp

    from warp_cloth.bench.scale import device_bytes, loglog_slope

    x = np.array([1e3, 4e3, 1.6e4])
    assert loglog_slope(x, 3.0 * x**1.5) == pytest.approx(1.5, abs=1e-12)
    a = wp.zeros(10, dtype=wp.vec3, device="cpu")
    b = wp.zeros(7, dtype=wp.float32, device="cpu")
    # the same array reached twice, through a dict, or as another object on the same memory
    # (a view) counts once
    assert device_bytes([a, b, a], {"k": a}, a.view(wp.vec3)) == 10 * 12 + 7 * 4


def test_scale_bench_end_to_end(tmp_path, monkeypatch, capsys):
    import csv

    from warp_cloth.bench import scale

    monkeypatch.setattr(scale, "have_matplotlib", lambda: False)
    assert scale.main(["--sides", "3", "7", "--solvers", "explicit", "pd", "--substeps", "1",
                       "--repeats", "1", "--out-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "log-log slopes" in out and "matplotlib is not installed" in out
    rows = list(csv.DictReader(open(tmp_path / "scale.csv")))
    assert [(r["solver"], int(r["vertices"])) for r in rows] == [
        ("explicit", 16), ("explicit", 64), ("pd", 16), ("pd", 64)]
    for r in rows:
        assert r["finite"] == "True" and float(r["substep_ms"]) > 0
        # at least positions, velocities, rest shape, masses, inverse masses: 44 bytes a vertex
        assert float(r["bytes_per_vertex"]) >= 44
    assert (tmp_path / "scale.md").exists() and not (tmp_path / "scale.png").exists()


def test_compiled_colouring_equals_the_python_loop_and_falls_back():
    from warp_cloth.limits import _color_constraints_python

    rng = np.random.default_rng(0)
    pairs = rng.integers(0, 40, (400, 2))
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    assert np.array_equal(color_constraints(pairs, 40), _color_constraints_python(pairs, 40))
    assert np.array_equal(color_constraints(pairs, 40), loop_greedy_colors(pairs, 40))
    # a star of 70 constraints at one vertex needs 70 colours: past the 63-bit mask, the Python
    # loop answers, the same greedy colours
    star = np.stack([np.zeros(70, dtype=np.int64), np.arange(1, 71)], axis=1)
    assert np.array_equal(color_constraints(star, 71), np.arange(70))
    assert len(color_constraints(np.zeros((0, 2), dtype=np.int64), 3)) == 0
