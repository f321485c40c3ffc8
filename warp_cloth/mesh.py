"""Triangle meshes and their topology.

`TriMesh` holds vertices (N x 3, metres) and triangles (M x 3 vertex indices) on the host and
derives, once, everything the solvers need from the connectivity:

- ``edges`` (E x 2, ``i < j``), ``edge_tris`` (E x 2, the one or two triangles on each edge, -1
  where there is none) and ``boundary_edges``;
- ``bend_quads`` (B x 4): for every interior edge ``(a, b)`` shared by triangles ``(a, b, c)`` and
  ``(b, a, d)`` the four vertices ``(a, b, c, d)``; ``(c, d)`` is the notes' *bending pair*.

The edges are built exactly as in the course notes (``reference/physics.md`` section 2.1): every
triangle emits the triples ``(min(i, j), max(i, j), tri)``, the triples are sorted, and equal
neighbours are interior edges.

Generators (`TriMesh.grid`) and loaders (`TriMesh.from_obj`, `TriMesh.from_usd`) build meshes;
`TriMesh.validate` (run by the constructor) rejects bad input with a `ValueError` that names the
offending vertex, triangle or edge.
"""

from __future__ import annotations

import math
import numbers
import os
from dataclasses import dataclass, field

import numpy as np

from .util import positive_finite

__all__ = ["TriMesh", "edge_triples", "check_up_axis"]

UP_AXES = ("Y", "Z")


def _positive_finite(x, what: str) -> float:
    return positive_finite(x, what)


#: the file extensions of USD stages (`TriMesh.from_file`)
USD_EXTENSIONS = (".usd", ".usda", ".usdc", ".usdz")
#: largest finite float32: the device arrays' type
FLOAT32_MAX = float(np.finfo(np.float32).max)


def _describe(x) -> str:
    r = repr(x)
    return f"{type(x).__name__} {r[:40] + '...' if len(r) > 40 else r}"


def _number_array(x, what: str, expect: str) -> np.ndarray:
    """``x`` as a float64 array, or `ValueError` saying ``what`` must be ``expect``."""
    if x is None or isinstance(x, (str, bytes)):
        raise ValueError(f"{what} must be {expect}, got {_describe(x)}")
    try:
        with np.errstate(all="ignore"):
            a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"{what} must be {expect}, got {_describe(x)}") from None
    return a


def index_array(x, what: str, kind: str = "vertex") -> np.ndarray:
    """``x`` as an int64 array of indices: integers, or floats with integral values. Booleans,
    strings, fractions, non-finite or huge values raise `ValueError` naming ``what``."""
    if x is None or isinstance(x, (str, bytes)):
        raise ValueError(f"{what} must be {kind} indices (integers), got {_describe(x)}")
    try:
        a = np.asarray(x)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"{what} must be {kind} indices (integers), got {_describe(x)}") from None
    if a.dtype.kind == "O":
        try:
            a = np.asarray(a.tolist(), dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            raise ValueError(f"{what} must be {kind} indices (integers), got "
                             f"{_describe(x)}") from None
    if a.dtype.kind == "b" or a.dtype.kind not in "iuf":
        raise ValueError(f"{what} must be {kind} indices (integers), got an array of "
                         f"{'booleans' if a.dtype.kind == 'b' else a.dtype}")
    if a.dtype.kind == "f":
        with np.errstate(all="ignore"):
            bad = ~np.isfinite(a) | (a != np.round(a))
        if bad.any():
            k = np.unravel_index(int(np.argmax(bad)), a.shape)
            raise ValueError(f"{what}: entry {list(map(int, k))} is {float(a[k])!r}, not an integer "
                             f"{kind} index")
    big = np.abs(a.astype(np.float64)) > 2.0**62
    if big.any():
        k = np.unravel_index(int(np.argmax(big)), a.shape)
        raise ValueError(f"{what}: {kind} index {a[k]:.4g} at {list(map(int, k))} is out of range")
    return a.astype(np.int64)


def cross3(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (..., 3) float arrays: the same arithmetic as `np.cross`
    (bit-identical results) at a fraction of its cost on large arrays."""
    out = np.empty(np.broadcast_shapes(u.shape, v.shape), dtype=np.result_type(u, v))
    out[..., 0] = u[..., 1] * v[..., 2] - u[..., 2] * v[..., 1]
    out[..., 1] = u[..., 2] * v[..., 0] - u[..., 0] * v[..., 2]
    out[..., 2] = u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]
    return out


def check_up_axis(up_axis, where: str = "up_axis") -> str:
    """``"Y"`` or ``"Z"`` (either case accepted); anything else raises `ValueError`."""
    a = up_axis.upper() if isinstance(up_axis, str) else None
    if a not in UP_AXES:
        raise ValueError(f"{where}: up_axis must be 'Y' or 'Z', got {up_axis!r}")
    return a


def _sorted_sides(triangles: np.ndarray):
    """The triangle sides as three 1-D arrays ``(lo, hi, tri)`` sorted by ``(lo, hi, tri)``.

    One stable sort of the single key ``lo * n + hi`` (sides are generated triangle by triangle,
    so equal keys keep increasing ``tri``): the same order as a lexicographic sort of the triples
    at a fraction of the cost."""
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    m = len(tris)
    a = tris.reshape(-1)
    b = tris[:, [1, 2, 0]].reshape(-1)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    n = int(hi.max()) + 1 if len(hi) else 1
    if n < 3_000_000_000:
        order = np.argsort(lo * n + hi, kind="stable")
    else:  # keys would overflow int64
        order = np.lexsort((hi, lo))
    return lo[order], hi[order], order // 3 if m else order


def edge_triples(triangles: np.ndarray) -> np.ndarray:
    """The notes' sorted edge triples ``(min(i, j), max(i, j), tri)``, one per triangle side.

    Returned sorted lexicographically (by first vertex, then second, then triangle), which puts the
    two triples of an interior edge next to each other.
    """
    return np.stack(_sorted_sides(triangles), axis=1).reshape(-1, 3)


@dataclass
class TriMesh:
    """A triangle mesh with validated connectivity and derived topology.

    Args:
        vertices: (N, 3) positions in metres.
        triangles: (M, 3) vertex indices, counter-clockwise seen from the front side.
        grid_shape: ``(nx, ny)`` when the mesh is a structured grid made by `TriMesh.grid`
            (vertex ``j * (nx + 1) + i``); enables the structured shear/bending springs.
        name: a label used in error messages and as the USD prim name.
        up_axis: ``"Y"`` or ``"Z"``: the axis that points up in the frame of ``vertices``.
            `ClothModel`'s default gravity points down along it, `RunStats` heights are measured
            along it and the output stage records it. Loaders set it from the file
            (`from_usd`: the stage's ``upAxis``; `from_obj`: the ``up_axis`` argument).

    Raises:
        ValueError: on non-finite coordinates, out-of-range or negative indices, a repeated vertex
            in a triangle, a zero-area or duplicate triangle, or a non-manifold edge (more than two
            triangles); the message names the index.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    grid_shape: tuple[int, int] | None = None
    name: str = "cloth"
    up_axis: str = "Y"
    edges: np.ndarray = field(init=False, repr=False)
    edge_tris: np.ndarray = field(init=False, repr=False)
    bend_quads: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        if not isinstance(self.name, str):
            raise ValueError(f"name must be a string, got {type(self.name).__name__}")
        self.up_axis = check_up_axis(self.up_axis, self.name)
        v = _number_array(self.vertices, f"{self.name}: vertices", "an (N, 3) array of numbers")
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"{self.name}: vertices must have shape (N, 3), got {v.shape}")
        t = index_array(self.triangles, f"{self.name}: triangles", "vertex")
        if t.ndim != 2 or t.shape[1] != 3:
            raise ValueError(f"{self.name}: triangles must have shape (M, 3), got {t.shape}")
        if len(t) == 0:
            raise ValueError(f"{self.name}: mesh has no triangles")
        if self.grid_shape is not None:
            try:
                nx, ny = (int(c) for c in self.grid_shape)
            except (TypeError, ValueError):
                raise ValueError(f"{self.name}: grid_shape must be (nx, ny), got "
                                 f"{self.grid_shape!r}") from None
            if nx < 1 or ny < 1 or (nx + 1) * (ny + 1) != len(v):
                raise ValueError(f"{self.name}: grid_shape {self.grid_shape} does not match "
                                 f"{len(v)} vertices")
            self.grid_shape = (nx, ny)
        self.vertices = v
        self.triangles = t
        self.validate()
        self._build_topology()

    # ------------------------------------------------------------------ validation
    def validate(self) -> None:
        """Check the mesh; raise `ValueError` naming the first offending vertex/triangle/edge."""
        v, t, n = self.vertices, self.triangles, len(self.vertices)
        bad = np.argwhere(~np.isfinite(v))
        if len(bad):
            i = int(bad[0, 0])
            raise ValueError(f"{self.name}: vertex {i} has a non-finite coordinate {v[i].tolist()}")
        bad = np.argwhere(np.abs(v) > FLOAT32_MAX)
        if len(bad):
            i = int(bad[0, 0])
            raise ValueError(f"{self.name}: vertex {i} has a coordinate beyond the float32 range "
                             f"(+-{FLOAT32_MAX:.3g} m) of the simulation: {v[i].tolist()}")
        bad = np.argwhere((t < 0) | (t >= n))
        if len(bad):
            k, c = (int(x) for x in bad[0])
            raise ValueError(
                f"{self.name}: triangle {k} has vertex index {int(t[k, c])} out of range "
                f"[0, {n - 1}] (triangle {t[k].tolist()})"
            )
        rep = (t[:, 0] == t[:, 1]) | (t[:, 1] == t[:, 2]) | (t[:, 0] == t[:, 2])
        if rep.any():
            k = int(np.argmax(rep))
            raise ValueError(f"{self.name}: triangle {k} repeats a vertex {t[k].tolist()}")
        # relative to each triangle's own size: a 1e30 m triangle is not "zero area", nor is a
        # small one in a large mesh
        # the sides once, for the areas (as `triangle_areas`) and the longest side
        # ((x0 - x2)^2 == (x2 - x0)^2 exactly)
        x0, x1, x2 = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
        e1, e2 = x1 - x0, x2 - x0
        area = 0.5 * np.linalg.norm(cross3(e1, e2), axis=1)
        longest2 = np.maximum.reduce([(e1 ** 2).sum(1), ((x2 - x1) ** 2).sum(1), (e2 ** 2).sum(1)])
        tiny = area <= 1e-12 * longest2
        if tiny.any():
            k = int(np.argmax(tiny))
            raise ValueError(
                f"{self.name}: triangle {k} {t[k].tolist()} has zero area ({area[k]:.3g} m^2 for "
                f"a longest side of {np.sqrt(longest2[k]):.3g} m: its vertices are collinear)"
            )
        key = np.sort(t, axis=1)
        if n < 2**21:  # one int64 per sorted triple: a 1-D unique, much faster than axis=0
            _, first, counts = np.unique((key[:, 0] * n + key[:, 1]) * n + key[:, 2],
                                         return_index=True, return_counts=True)
        else:
            _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
        if (counts > 1).any():
            dup_key = key[first[np.argmax(counts > 1)]]
            same = np.flatnonzero((key == dup_key).all(axis=1))
            raise ValueError(
                f"{self.name}: triangles {same.tolist()} are duplicates (vertices {dup_key.tolist()})"
            )

    # ------------------------------------------------------------------ topology
    def _build_topology(self) -> None:
        lo, hi, tri_of = _sorted_sides(self.triangles)
        same_as_prev = np.zeros(len(lo), dtype=bool)
        same_as_prev[1:] = (lo[1:] == lo[:-1]) & (hi[1:] == hi[:-1])
        starts = np.flatnonzero(~same_as_prev)
        counts = np.diff(np.append(starts, len(lo)))
        if (counts > 2).any():
            e = int(np.argmax(counts > 2))
            s = starts[e]
            tris = tri_of[s : s + counts[e]].tolist()
            raise ValueError(
                f"{self.name}: non-manifold edge ({lo[s]}, {hi[s]}) is shared by "
                f"{counts[e]} triangles {tris}; a cloth edge may have at most two"
            )
        self.edges = np.stack([lo[starts], hi[starts]], axis=1).reshape(-1, 2)
        self.edge_tris = np.full((len(starts), 2), -1, dtype=np.int64)
        self.edge_tris[:, 0] = tri_of[starts]
        interior = counts == 2
        self.edge_tris[interior, 1] = tri_of[starts[interior] + 1]

        # bending quads (a, b, c, d): shared edge (a, b) in the winding of the first triangle,
        # c opposite it in that triangle, d in the other (vectorised over the interior edges)
        ie = np.flatnonzero(interior)
        tri = self.triangles
        i, j = self.edges[ie, 0], self.edges[ie, 1]
        t0, t1 = tri[self.edge_tris[ie, 0]], tri[self.edge_tris[ie, 1]]
        # the position k of i in t0; (i, j) keeps its order iff t0[k + 1] == j
        k = np.argmax(t0 == i[:, None], axis=1)
        rows = np.arange(len(ie))
        forward = t0[rows, (k + 1) % 3] == j
        a = np.where(forward, i, j)
        b = np.where(forward, j, i)
        # the vertex of a triangle that is neither i nor j: the sum of its three minus i and j
        c = t0.sum(axis=1) - i - j
        d = t1.sum(axis=1) - i - j
        quads = np.stack([a, b, c, d], axis=1).astype(np.int64).reshape(-1, 4)
        self.bend_quads = quads

    @property
    def num_vertices(self) -> int:
        return len(self.vertices)

    @property
    def num_triangles(self) -> int:
        return len(self.triangles)

    @property
    def boundary_edges(self) -> np.ndarray:
        """(B, 2) edges that belong to a single triangle."""
        return self.edges[self.edge_tris[:, 1] < 0]

    @property
    def interior_edges(self) -> np.ndarray:
        return self.edges[self.edge_tris[:, 1] >= 0]

    @property
    def bending_pairs(self) -> np.ndarray:
        """(B, 2) the two vertices opposite each interior edge (the notes' bending springs)."""
        return self.bend_quads[:, 2:4].copy()

    def triangle_areas(self, positions: np.ndarray | None = None) -> np.ndarray:
        x = self.vertices if positions is None else np.asarray(positions, dtype=np.float64)
        t = self.triangles
        return 0.5 * np.linalg.norm(
            cross3(x[t[:, 1]] - x[t[:, 0]], x[t[:, 2]] - x[t[:, 0]]), axis=1
        )

    def vertex_areas(self) -> np.ndarray:
        """Lumped area per vertex: a third of each adjacent triangle's area."""
        a = np.zeros(self.num_vertices)
        np.add.at(a, self.triangles.reshape(-1), np.repeat(self.triangle_areas() / 3.0, 3))
        return a

    def extent(self) -> float:
        """Largest side of the axis-aligned bounding box (m); the 'cloth size' of error metrics."""
        return float(np.ptp(self.vertices, axis=0).max())

    def coincident_vertices(self, tolerance: float = 0.0) -> np.ndarray:
        """(K, 2) pairs ``i < j`` of distinct vertices at most ``tolerance`` metres apart
        (``0``: at the same position), each vertex paired with the lowest index of its group:
        a seam written twice, as some exporters split vertices by normal or texture
        coordinate. Such vertices are separate pieces of cloth that touch."""
        tol = float(tolerance)
        if not (math.isfinite(tol) and tol >= 0.0):
            raise ValueError(f"{self.name}: tolerance must be >= 0 metres, got {tolerance!r}")
        v = self.vertices
        if tol == 0.0:
            _, first, inverse = np.unique(v, axis=0, return_index=True, return_inverse=True)
            rep = first[inverse.reshape(-1)]
        else:  # the pairs within tol (a hash grid), then their groups (union-find on the host)
            from .collision.check import close_vertex_pairs

            parent = np.arange(len(v))

            def root(i):
                while parent[i] != i:
                    parent[i] = parent[parent[i]]
                    i = parent[i]
                return i

            for i, j in close_vertex_pairs(v, tol):
                ri, rj = root(int(i)), root(int(j))
                if ri != rj:
                    parent[max(ri, rj)] = min(ri, rj)
            rep = np.array([root(i) for i in range(len(v))])
        j = np.flatnonzero(rep != np.arange(len(v)))
        return np.stack([rep[j], j], axis=1).astype(np.int64).reshape(-1, 2)

    def weld(self, tolerance: float = 0.0):
        """``(mesh, index)``: this mesh with every group of `coincident_vertices` (within
        ``tolerance`` m) merged into its lowest-indexed vertex, and ``index`` (N,) the new
        index of each old vertex (per-vertex data map through it; pins on both copies of a
        seam become one: ``np.unique(index[pins])``). Raises `ValueError`
        (naming them) if merging collapses a triangle or makes two triangles the same, as
        validation does for any mesh."""
        pairs = self.coincident_vertices(tolerance)
        rep = np.arange(self.num_vertices)
        rep[pairs[:, 1]] = pairs[:, 0]
        keep = rep == np.arange(self.num_vertices)
        new = np.cumsum(keep) - 1
        index = new[rep]
        mesh = TriMesh(self.vertices[keep], index[self.triangles], name=self.name,
                       up_axis=self.up_axis)
        return mesh, index

    # ------------------------------------------------------------------ generators
    @classmethod
    def grid(
        cls,
        nx: int,
        ny: int,
        size: tuple[float, float] | float = 1.0,
        plane: str = "xz",
        origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
        diagonals: str = "alternating",
        name: str = "cloth",
        up_axis: str = "Y",
    ) -> "TriMesh":
        """A rectangular sheet of ``nx`` x ``ny`` cells, two triangles per cell.

        Vertex ``(i, j)`` (``0 <= i <= nx``, ``0 <= j <= ny``) has index ``j * (nx + 1) + i`` and
        position ``origin + i * dx * u + j * dy * w``, where ``(u, w)`` are the unit axes of
        ``plane`` (``"xy"``, ``"xz"`` or ``"yz"``) and ``(dx, dy) = size / (nx, ny)``.

        ``diagonals="alternating"`` flips the diagonal cell by cell (no directional bias);
        ``"fixed"`` uses the same diagonal everywhere. Triangles are counter-clockwise about
        ``u x w``. ``up_axis`` is the mesh's up axis (``"Y"``: a ``plane="xz"`` sheet is
        horizontal; ``"Z"``: a ``plane="xy"`` sheet is).
        """
        for v in (nx, ny):
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real) or \
                    not math.isfinite(float(v)):
                raise ValueError(f"grid: nx and ny must be positive integers, got ({nx!r}, "
                                 f"{ny!r})")
        if int(nx) != nx or int(ny) != ny or nx < 1 or ny < 1:
            raise ValueError(f"grid: nx and ny must be positive integers, got ({nx}, {ny})")
        nx, ny = int(nx), int(ny)
        try:
            sz = np.asarray(size, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            sz = np.zeros(0)
        if sz.size == 1:
            sz = np.repeat(sz, 2)
        if sz.shape != (2,) or not (np.all(sz > 0) and np.all(np.isfinite(sz))):
            raise ValueError(f"grid: size must be a positive number or two, got {size!r}")
        sx, sy = float(sz[0]), float(sz[1])
        try:
            org = np.asarray(origin, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            org = np.zeros(0)
        if org.shape != (3,) or not np.all(np.isfinite(org)):
            raise ValueError(f"grid: origin must be 3 finite numbers, got {origin!r}")
        axes = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}
        if not isinstance(plane, str) or plane not in axes:
            raise ValueError(f"grid: plane must be one of {sorted(axes)}, got {plane!r}")
        if diagonals not in ("alternating", "fixed"):
            raise ValueError(f"grid: diagonals must be 'alternating' or 'fixed', got {diagonals!r}")
        au, aw = axes[plane]
        i, j = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1))
        verts = np.zeros(((nx + 1) * (ny + 1), 3))
        verts[:, au] = i.reshape(-1) * (sx / nx)
        verts[:, aw] = j.reshape(-1) * (sy / ny)
        verts += org
        # counter-clockwise about u x w (for plane "xz" that is -y); cells in row-major order
        cj, ci = np.meshgrid(np.arange(ny, dtype=np.int64), np.arange(nx, dtype=np.int64),
                             indexing="ij")
        cj, ci = cj.reshape(-1), ci.reshape(-1)
        v00 = cj * (nx + 1) + ci
        v10, v01, v11 = v00 + 1, v00 + nx + 1, v00 + nx + 2
        fixed = np.ones(len(v00), dtype=bool) if diagonals == "fixed" else (ci + cj) % 2 == 0
        first = np.where(fixed[:, None], np.stack([v00, v10, v11], 1), np.stack([v00, v10, v01], 1))
        second = np.where(fixed[:, None], np.stack([v00, v11, v01], 1),
                          np.stack([v10, v11, v01], 1))
        tris = np.stack([first, second], axis=1).reshape(-1, 3)
        return cls(verts, tris, grid_shape=(nx, ny), name=name,
                   up_axis=up_axis)

    @classmethod
    def icosphere(cls, subdivisions: int = 3, radius: float = 1.0,
                  name: str = "icosphere") -> "TriMesh":
        """A closed sphere of ``radius`` m: an icosahedron whose triangles are split in four
        ``subdivisions`` times (20 * 4^s triangles), the new vertices pushed onto the sphere;
        outward windings. A test and probe mesh (the lumpy meshes of
        ``docs/bench/probes/lumpy_meshes.py`` are these with a radial relief)."""
        s = int(subdivisions)
        if not 0 <= s <= 8:
            raise ValueError(f"icosphere: subdivisions must be an integer in [0, 8], got "
                             f"{subdivisions!r}")
        r = float(radius)
        if not (math.isfinite(r) and r > 0):
            raise ValueError(f"icosphere: radius must be a positive finite number, got {radius!r}")
        t = (1 + 5 ** 0.5) / 2
        V = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
             [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]
        F = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
             [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
             [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
        V = [np.array(p, float) / np.linalg.norm(p) for p in V]
        for _ in range(s):
            mid, F2 = {}, []

            def m(a, b):
                k = (min(a, b), max(a, b))
                if k not in mid:
                    p = V[a] + V[b]
                    V.append(p / np.linalg.norm(p))
                    mid[k] = len(V) - 1
                return mid[k]
            for a, b, c in F:
                ab, bc, ca = m(a, b), m(b, c), m(c, a)
                F2 += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
            F = F2
        return cls(np.array(V) * r, np.array(F), name=name)

    # ------------------------------------------------------------------ loaders
    @classmethod
    def from_file(cls, path: str | os.PathLike, all_meshes: bool = False) -> "TriMesh":
        """A mesh file by its extension: a USD stage's first mesh (`USD_EXTENSIONS`,
        `from_usd`; ``all_meshes``: all of them as one), else an OBJ (`from_obj`: every face
        of the file)."""
        if os.path.splitext(os.fspath(path))[1].lower() in USD_EXTENSIONS:
            return cls.from_usd(path, all_meshes=all_meshes)
        return cls.from_obj(path)

    @classmethod
    def from_obj(cls, path: str | os.PathLike, name: str | None = None, *, scale: float = 1.0,
                 up_axis: str = "Y", weld=False) -> "TriMesh":
        """Load a Wavefront OBJ file: ``v`` lines and ``f`` lines (``i``, ``i/t``, ``i//n``,
        ``i/t/n``, negative = relative indices). Quads and polygons are fan-triangulated; other
        statements are ignored.

        OBJ files carry no unit or up axis: ``scale`` (metres per file unit, e.g. 0.01 for a file
        in centimetres) multiplies every coordinate, and ``up_axis`` (``"Y"``, the OBJ
        convention, or ``"Z"``) says which axis is up in the file; it becomes the mesh's
        `up_axis` (coordinates are not rotated). ``weld=True`` merges vertices written twice
        at one position (`weld`; some exporters split a seam so), which self-collision needs; a
        number merges those within that many metres (after ``scale``).

        Raises:
            ValueError: naming the file and line of a malformed or undecodable line, an index out
                of range, or a bad ``scale``/``up_axis``.
        """
        if not isinstance(path, (str, os.PathLike)):
            # (an int is a file descriptor to open(): 0 read standard input, and closed it)
            raise ValueError(f"from_obj: path must be a str or os.PathLike, got "
                            f"{type(path).__name__}")
        up_axis = check_up_axis(up_axis, f"{path}")
        scale = _positive_finite(scale, f"{path}: scale")
        verts, tris, tri_lines = [], [], []
        name = name or os.path.splitext(os.path.basename(str(path)))[0]
        with open(path, "rb") as fh:
            for lineno, raw in enumerate(fh, 1):
                try:
                    line = raw.decode("utf-8")
                except UnicodeDecodeError as e:
                    # comments and names may be in any encoding; statements we read are ASCII
                    line = raw.decode("latin-1")
                    hash_at = raw.find(b"#")
                    in_comment = 0 <= hash_at < e.start
                    words = line.split()  # (a line of only U+0085, a space, has no word)
                    if not in_comment and words and words[0] in ("v", "f"):
                        raise ValueError(f"{path}:{lineno}: bytes that are not UTF-8 "
                                         f"({e.reason} at column {e.start + 1})") from None
                parts = line.split("#", 1)[0].split()
                if not parts:
                    continue
                if parts[0] == "v":
                    try:
                        verts.append([float(c) for c in parts[1:4]])
                    except ValueError:
                        raise ValueError(f"{path}:{lineno}: bad vertex line {line.strip()!r}") from None
                    if len(verts[-1]) != 3:
                        raise ValueError(f"{path}:{lineno}: vertex needs 3 coordinates")
                elif parts[0] == "f":
                    idx = []
                    for tok in parts[1:]:
                        try:
                            k = int(tok.split("/")[0])
                        except ValueError:
                            raise ValueError(f"{path}:{lineno}: bad face index {tok!r}") from None
                        if k == 0:
                            raise ValueError(f"{path}:{lineno}: OBJ indices start at 1, got 0")
                        j = k - 1 if k > 0 else len(verts) + k
                        if j < 0 or abs(k) > 2**62:  # (a relative index before the first)
                            raise ValueError(f"{path}:{lineno}: face index {k} is out of range "
                                             f"(the file has {len(verts)} vertices so far)")
                        idx.append(j)
                    if len(idx) < 3:
                        raise ValueError(f"{path}:{lineno}: face needs at least 3 vertices")
                    for q in range(1, len(idx) - 1):
                        tris.append((idx[0], idx[q], idx[q + 1]))
                        tri_lines.append(lineno)
        if not verts:
            raise ValueError(f"{path}: no vertices found")
        for (a, b, c), lineno in zip(tris, tri_lines):  # forward references allowed till here
            if max(a, b, c) >= len(verts):
                raise ValueError(f"{path}:{lineno}: face index {max(a, b, c) + 1} is out of "
                                 f"range (the file has {len(verts)} vertices)")
        v = np.asarray(verts, dtype=np.float64) * scale
        mesh = cls(v, np.asarray(tris, dtype=np.int64).reshape(-1, 3), name=name, up_axis=up_axis)
        if weld is False or weld is None:
            return mesh
        if weld is True:
            return mesh.weld(0.0)[0]
        try:
            tol = float(weld)
        except (TypeError, ValueError):
            tol = math.nan
        if isinstance(weld, (bool, np.bool_)) or not (math.isfinite(tol) and tol >= 0.0):
            raise ValueError(f"{path}: weld must be True, False or a distance >= 0 in metres, "
                             f"got {weld!r}")
        return mesh.weld(tol)[0]

    def to_obj(self, path: str | os.PathLike) -> None:
        """Write the mesh as a Wavefront OBJ file."""
        with open(path, "w", encoding="utf-8") as fh:
            for p in self.vertices:
                fh.write(f"v {float(p[0])!r} {float(p[1])!r} {float(p[2])!r}\n")
            for t in self.triangles:
                fh.write(f"f {t[0] + 1} {t[1] + 1} {t[2] + 1}\n")

    @classmethod
    def from_usd(cls, path: str | os.PathLike, prim_path: str | None = None, time=None,
                 all_meshes: bool = False) -> "TriMesh":
        """Load a `UsdGeom.Mesh` (the first one found, or the one at ``prim_path``; with
        ``all_meshes``, every mesh of the stage as one, its parts apart: an obstacle made of
        several, such as a chair's seat and legs, `MeshObstacle`).

        Points are taken at ``time`` (default: the default value, else the earliest time sample)
        and transformed to world space; polygons are fan-triangulated. The mesh keeps the stage's
        frame: its coordinates are scaled by the stage's ``metersPerUnit`` to metres (the
        simulator's unit), and its `up_axis` is the stage's ``upAxis``, so a Z-up file falls
        along -z (`ClothModel`'s default gravity) and is written back Z-up.
        """
        from pxr import Sdf, Tf, Usd, UsdGeom

        try:
            stage = Usd.Stage.Open(str(path))
        except Tf.ErrorException as e:
            first = str(e).strip().splitlines()[-1].strip() if str(e).strip() else "unreadable"
            raise ValueError(f"{path}: cannot open USD stage ({first})") from None
        if stage is None:
            raise ValueError(f"{path}: cannot open USD stage")
        if prim_path is not None:
            if not Sdf.Path.IsValidPathString(str(prim_path)):
                raise ValueError(f"{path}: {prim_path!r} is not a prim path")
            prim = stage.GetPrimAtPath(prim_path)
            if not prim or not prim.IsA(UsdGeom.Mesh):
                raise ValueError(f"{path}: no UsdGeom.Mesh at {prim_path}")
        else:
            prims = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
            if not prims:
                raise ValueError(f"{path}: no UsdGeom.Mesh in the stage")
            prim = prims[0]
            if all_meshes and len(prims) > 1:
                parts = [cls.from_usd(path, str(p.GetPath()), time) for p in prims]
                verts, tris, base = [], [], 0
                for m in parts:
                    verts.append(m.vertices)
                    tris.append(np.asarray(m.triangles) + base)
                    base += len(m.vertices)
                return cls(np.concatenate(verts), np.concatenate(tris),
                           name=os.path.splitext(os.path.basename(os.fspath(path)))[0],
                           up_axis=parts[0].up_axis)
        up_axis = str(UsdGeom.GetStageUpAxis(stage))
        if up_axis not in ("Y", "Z"):
            raise ValueError(f"{path}: unsupported upAxis {up_axis!r}")
        mpu = float(UsdGeom.GetStageMetersPerUnit(stage))
        if not (math.isfinite(mpu) and mpu > 0):
            raise ValueError(f"{path}: metersPerUnit must be positive, got {mpu}")
        mesh = UsdGeom.Mesh(prim)
        if time is not None:
            t = Usd.TimeCode(time)
        elif mesh.GetPointsAttr().Get(Usd.TimeCode.Default()) is not None:
            t = Usd.TimeCode.Default()
        else:
            t = Usd.TimeCode.EarliestTime()
        raw_pts = mesh.GetPointsAttr().Get(t)
        if raw_pts is None or mesh.GetFaceVertexCountsAttr().Get(t) is None:
            raise ValueError(f"{path}: {prim.GetPath()} has no points or faces")
        pts = np.asarray(raw_pts, dtype=np.float64).reshape(-1, 3)
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(t), dtype=np.int64)
        idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(t), dtype=np.int64)
        if counts.sum() != len(idx):
            raise ValueError(f"{path}: {prim.GetPath()} has {len(idx)} face vertex indices, its "
                             f"face counts add up to {int(counts.sum())}")
        xf = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t), dtype=np.float64)
        pts = pts @ xf[:3, :3] + xf[3, :3]  # USD matrices act on row vectors
        pts *= mpu
        tris, o = [], 0
        for c in counts:
            if c < 3:
                raise ValueError(f"{path}: face with {c} vertices in {prim.GetPath()}")
            for q in range(1, c - 1):
                tris.append((idx[o], idx[o + q], idx[o + q + 1]))
            o += c
        return cls(pts, np.asarray(tris, dtype=np.int64).reshape(-1, 3), name=prim.GetName(),
                   up_axis=up_axis)
