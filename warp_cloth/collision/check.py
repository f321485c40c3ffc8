"""Intersection checks between the cloth and mesh obstacles (host entry points, device kernels).

`mesh_edge_crossings` counts the cloth edges that cross a mesh obstacle's surface: a ray from
one end of the edge to the other (Warp's BVH ray query, exact up to float32 rounding) hits a
triangle of the obstacle. With both ends outside (which vertex contact guarantees) such an edge
passes through the obstacle. Used by the tests and by anyone checking a run's output.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..util import launch

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile

__all__ = ["mesh_edge_crossings", "self_crossings", "SelfIntersectionChecker", "folded_flat_edges",
           "check_meshes", "edges_of", "solid_depths", "ObstacleChecker"]


#: two triangles on an edge lie folded flat onto each other when the far vertex of one is within
#: this share of the shared edge's length of the other's plane (float32 rounding of a sheet in a
#: tilted plane is ~1e-7 of it) and on the same side of the edge
FOLDED_FLAT_TOLERANCE = 1e-6
#: ... or off flat by at most this many float32 units in the last place of the positions
FOLDED_FLAT_ULPS = 8.0


def folded_flat_edges(positions, edges, edge_tris, triangles) -> np.ndarray:
    """Indices of the interior edges whose two triangles lie folded flat onto each other at
    ``positions``: coplanar (`FOLDED_FLAT_TOLERANCE`, or `FOLDED_FLAT_ULPS`) with their far vertices on the same side of
    the shared edge, so that they overlap over an area (an inverted triangle in a flat sheet, a
    vertex moved past the opposite edge of its triangle). The edge-triangle crossing test
    (`self_crossings`) cannot see such an overlap: an edge lying in a triangle's plane does not
    cross it. By geometry only, so a mesh's winding does not matter. Host (numpy, float64)."""
    x = np.asarray(positions, dtype=np.float64)
    edges = np.asarray(edges).reshape(-1, 2)
    et = np.asarray(edge_tris).reshape(-1, 2)
    tris = np.asarray(triangles).reshape(-1, 3)
    inner = np.flatnonzero(et[:, 1] >= 0)
    if len(inner) == 0:
        return inner
    a, b = edges[inner, 0], edges[inner, 1]

    def far(t):  # the vertex of triangle t that is not on the edge
        tv = tris[t]
        return np.where((tv[:, 0] != a) & (tv[:, 0] != b), tv[:, 0],
                        np.where((tv[:, 1] != a) & (tv[:, 1] != b), tv[:, 1], tv[:, 2]))

    c, d = far(et[inner, 0]), far(et[inner, 1])
    xa = x[a]
    u = x[b] - xa
    length = np.linalg.norm(u, axis=1)
    u = u / np.maximum(length, 1e-300)[:, None]
    pc, pd = x[c] - xa, x[d] - xa
    pc = pc - (pc * u).sum(1)[:, None] * u  # perpendicular to the edge
    pd = pd - (pd * u).sum(1)[:, None] * u
    nc = np.linalg.norm(pc, axis=1)
    nd = np.linalg.norm(pd, axis=1)
    # the far vertices' directions from the edge agree: the dihedral angle is (nearly) zero
    dot = (pc * pd).sum(1)
    cross = np.linalg.norm(np.cross(pc, pd), axis=1)
    # or within float32 rounding of flat: the nearer far vertex lies within a few units in the
    # last place of the largest coordinate of the other triangle's plane (measured: a tilted
    # jittered sheet's inverted sliver triangle, its far vertex 1.7 mm from the edge, lay
    # 2e-5 rad off flat in float32, past the angle alone, and froze every response)
    off = FOLDED_FLAT_ULPS * np.finfo(np.float32).eps * float(np.abs(x).max(initial=0.0))
    flat = (dot > 0) & ((cross <= FOLDED_FLAT_TOLERANCE * length * np.minimum(nc, nd))
                        | (cross <= off * np.maximum(nc, nd)))
    return inner[flat]


@wp.kernel
def edge_ray_kernel(mesh: wp.uint64, x: wp.array(dtype=wp.vec3), edges: wp.array2d(dtype=wp.int32),
                    hit: wp.array(dtype=int)):
    e = wp.tid()
    a = x[edges[e, 0]]
    b = x[edges[e, 1]]
    d = b - a
    length = wp.length(d)
    hit[e] = 0
    if length > 0.0:
        q = wp.mesh_query_ray(mesh, a, d / length, length)
        if q.result:
            hit[e] = 1


def mesh_edge_crossings(obstacle, positions, edges, t: float = 0.0, device="cpu") -> np.ndarray:
    """Boolean mask (E,) of the edges ``edges`` (E, 2) of the cloth at ``positions`` (N, 3, world)
    that cross the surface of the `MeshObstacle` ``obstacle`` in its pose at time ``t``."""
    edges = np.asarray(edges, dtype=np.int32).reshape(-1, 2)
    if len(edges) == 0:
        return np.zeros(0, dtype=bool)
    local = obstacle.to_local(np.asarray(positions, dtype=np.float64), t)
    x = wp.array(local.astype(np.float32), dtype=wp.vec3, device=device)
    e = wp.array(edges, dtype=wp.int32, ndim=2, device=device)
    hit = wp.zeros(len(edges), dtype=int, device=device)
    launch(edge_ray_kernel, len(edges), [obstacle.wp_mesh(device).id, x, e, hit], device=device)
    return hit.numpy().astype(bool)


@wp.kernel
def tri_box_kernel(x: wp.array(dtype=wp.vec3), tris: wp.array2d(dtype=wp.int32),
                   lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
    t = wp.tid()
    a = x[tris[t, 0]]
    b = x[tris[t, 1]]
    c = x[tris[t, 2]]
    lowers[t] = wp.min(a, wp.min(b, c))
    uppers[t] = wp.max(a, wp.max(b, c))


@wp.func
def segment_crosses_triangle(p: wp.vec3d, q: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d):
    """True when the segment ``pq`` meets the triangle ``abc`` (Moller-Trumbore, float64; a
    segment lying in the triangle's plane is not a crossing)."""
    d = q - p
    e1 = b - a
    e2 = c - a
    h = wp.cross(d, e2)
    det = wp.dot(e1, h)
    # a segment (nearly) in the triangle's plane touches it at most: not a crossing. Relative
    # threshold: det is a triple product, rounded to about 1e-16 of |d| |e1| |e2|
    if wp.abs(det) <= wp.float64(1.0e-9) * wp.length(d) * wp.length(e1) * wp.length(e2):
        return False
    f = wp.float64(1.0) / det
    s = p - a
    u = f * wp.dot(s, h)
    if u < wp.float64(0.0) or u > wp.float64(1.0):
        return False
    qv = wp.cross(s, e1)
    v = f * wp.dot(d, qv)
    if v < wp.float64(0.0) or u + v > wp.float64(1.0):
        return False
    t = f * wp.dot(e2, qv)
    return t >= wp.float64(0.0) and t <= wp.float64(1.0)


@wp.kernel
def self_crossing_kernel(bvh: wp.uint64, x: wp.array(dtype=wp.vec3),
                         tris: wp.array2d(dtype=wp.int32), edges: wp.array2d(dtype=wp.int32),
                         count: wp.array(dtype=int), per_edge: wp.array(dtype=int),
                         part: wp.array(dtype=int), rigid: wp.array(dtype=int),
                         other: wp.array(dtype=int), rigid_other: wp.array(dtype=int)):
    """For edge ``e``: the triangles it passes through, none of which it shares a vertex with.
    With a ``part`` per vertex (several meshes in one soup, `check_meshes`), ``other[e]`` counts
    those of them in another part than the edge's where one of the two parts deforms, and
    ``rigid_other[e]`` those where both are ``rigid`` (``per_edge[e]`` counts all)."""
    e = wp.tid()
    i = edges[e, 0]
    j = edges[e, 1]
    p = x[i]
    q = x[j]
    query = wp.bvh_query_aabb(bvh, wp.min(p, q), wp.max(p, q))
    t = int(0)
    n = int(0)
    n_other = int(0)
    n_rigid = int(0)
    while wp.bvh_query_next(query, t):
        a = tris[t, 0]
        b = tris[t, 1]
        c = tris[t, 2]
        if a == i or a == j or b == i or b == j or c == i or c == j:
            continue
        pd = wp.vec3d(wp.float64(p[0]), wp.float64(p[1]), wp.float64(p[2]))
        qd = wp.vec3d(wp.float64(q[0]), wp.float64(q[1]), wp.float64(q[2]))
        xa = x[a]
        xb = x[b]
        xc = x[c]
        if segment_crosses_triangle(pd, qd, wp.vec3d(wp.float64(xa[0]), wp.float64(xa[1]), wp.float64(xa[2])),
                                    wp.vec3d(wp.float64(xb[0]), wp.float64(xb[1]), wp.float64(xb[2])),
                                    wp.vec3d(wp.float64(xc[0]), wp.float64(xc[1]), wp.float64(xc[2]))):
            n += 1
            if part.shape[0] > 0:
                if part[a] != part[i]:
                    if rigid[a] != 0 and rigid[i] != 0:
                        n_rigid += 1
                    else:
                        n_other += 1
    per_edge[e] = n
    if other.shape[0] > 0:
        other[e] = n_other
        rigid_other[e] = n_rigid
    if n > 0:
        wp.atomic_add(count, 0, n)


@wp.kernel
def close_pairs_kernel(grid: wp.uint64, x: wp.array(dtype=wp.vec3d), xf: wp.array(dtype=wp.vec3),
                       tol: wp.float64, radius: float, count: wp.array(dtype=int),
                       pairs: wp.array2d(dtype=int)):
    """Vertex ``i`` with every lower-indexed vertex within ``tol`` (float64 distance; the
    float32 grid is queried with a padded ``radius``)."""
    i = wp.tid()
    q = wp.hash_grid_query(grid, xf[i], radius)
    j = int(0)
    while wp.hash_grid_query_next(q, j):
        if j < i and wp.length(x[i] - x[j]) <= tol:
            k = wp.atomic_add(count, 0, 1)
            if k < pairs.shape[0]:
                pairs[k, 0] = j
                pairs[k, 1] = i


def close_vertex_pairs(vertices, tolerance: float, device="cpu") -> np.ndarray:
    """(K, 2) pairs ``j < i`` of points at most ``tolerance`` apart (a `wp.HashGrid` of cells
    the size of the query radius; distances in float64)."""
    v = np.asarray(vertices, dtype=np.float64)
    if len(v) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    tol = float(tolerance)
    # float32 rounding of the grid's points: pad the radius by it
    radius = tol + 4e-7 * max(1.0, float(np.abs(v).max()))
    lo = v.min(axis=0)
    xf = wp.array((v - lo).astype(np.float32), dtype=wp.vec3, device=device)
    xd = wp.array(v, dtype=wp.vec3d, device=device)
    dims = np.clip(np.ceil(np.ptp(v, axis=0) / radius), 1, 128).astype(int)
    grid = wp.HashGrid(int(dims[0]), int(dims[1]), int(dims[2]), device=device)
    grid.build(xf, radius)
    cap = max(16, len(v))
    while True:
        count = wp.zeros(1, dtype=int, device=device)
        pairs = wp.zeros((cap, 2), dtype=int, device=device)
        launch(close_pairs_kernel, len(v), [grid.id, xd, xf, tol, radius, count, pairs],
               device=device)
        n = int(count.numpy()[0])
        if n <= cap:
            return pairs.numpy()[:n].astype(np.int64)
        cap = n


class SelfIntersectionChecker:
    """Counts the (edge, triangle) pairs of a cloth mesh whose edge passes through the triangle,
    for pairs that share no vertex (a surface that passes through itself has such pairs; one
    that does not has none). A BVH over the triangles' boxes finds the candidates, an exact
    float64 segment-triangle test decides. For tests, `RunStats` (``check_intersections``) and
    ``warp-cloth check``."""

    def __init__(self, triangles, edges, num_vertices: int, device="cpu", parts=None,
                 rigid=None):
        """``parts`` (optional, an int per vertex: several meshes in one soup) also counts per
        edge the crossings through another part's triangles (``other``), apart where both
        parts are ``rigid`` (an int per vertex, 1: rigid; ``rigid_other``)."""
        self.device = device
        self.tris = wp.array(np.asarray(triangles, dtype=np.int32), dtype=wp.int32, ndim=2,
                             device=device)
        self.edges = wp.array(np.asarray(edges, dtype=np.int32).reshape(-1, 2), dtype=wp.int32,
                              ndim=2, device=device)
        self.x = wp.zeros(num_vertices, dtype=wp.vec3, device=device)
        nt = self.tris.shape[0]
        self.lowers = wp.zeros(nt, dtype=wp.vec3, device=device)
        self.uppers = wp.zeros(nt, dtype=wp.vec3, device=device)
        self.count = wp.zeros(1, dtype=int, device=device)
        self.per_edge = wp.zeros(self.edges.shape[0], dtype=int, device=device)
        ne = self.edges.shape[0] if parts is not None else 0
        self.part = wp.array(np.zeros(0, np.int32) if parts is None else
                             np.asarray(parts, np.int32), dtype=int, device=device)
        self.rigid = wp.array(np.zeros(len(self.part), np.int32) if rigid is None else
                              np.asarray(rigid, np.int32), dtype=int, device=device)
        self.other = wp.zeros(ne, dtype=int, device=device)
        self.rigid_other = wp.zeros(ne, dtype=int, device=device)
        self.bvh = None

    def __call__(self, positions) -> int:
        """Crossing (edge, triangle) pairs of the cloth at ``positions`` (N, 3) (host array or
        a device ``wp.array`` of vec3)."""
        if isinstance(positions, wp.array):
            wp.copy(self.x, positions)
        else:
            self.x.assign(np.asarray(positions, dtype=np.float32))
        launch(tri_box_kernel, self.tris.shape[0], [self.x, self.tris, self.lowers, self.uppers],
               device=self.device)
        if self.bvh is None:
            self.bvh = wp.Bvh(self.lowers, self.uppers)
        else:
            self.bvh.refit()
        self.count.zero_()
        launch(self_crossing_kernel, self.edges.shape[0],
               [self.bvh.id, self.x, self.tris, self.edges, self.count, self.per_edge,
                self.part, self.rigid, self.other, self.rigid_other], device=self.device)
        return int(self.count.numpy()[0])


def self_crossings(positions, triangles, edges, device="cpu") -> int:
    """(edge, triangle) pairs sharing no vertex whose edge passes through the triangle."""
    positions = np.asarray(positions)
    return SelfIntersectionChecker(triangles, edges, len(positions), device)(positions)


def edges_of(triangles) -> np.ndarray:
    """The unique edges (E, 2; sorted pairs) of triangles (T, 3), host numpy: any triangles,
    no topology checks (`TriMesh` builds a valid cloth's own)."""
    t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def check_meshes(tracks, device="cpu") -> dict:
    """Crossings of the meshes ``tracks`` (`warp_cloth.usd.MeshTrack`: triangles, world points
    per time and whether the points are animated), per time: (edge, triangle) pairs that share
    no vertex and whose edge passes through the triangle, within each mesh and between meshes
    (one soup: no vertex is shared across meshes, so every pair across two meshes is tested).

    Needs no valid cloth topology: any triangles (non-manifold, degenerate, duplicated) are
    tested as they are (a degenerate triangle is crossed by nothing). A time at which some
    point is not finite is not tested and is reported in ``nonfinite`` (its count of such
    points). Returns ``{"crossings": [...], "per_mesh": {path: [...]}, "between": [...],
    "between_rigid": [...], "nonfinite": [...]}`` (lists over the times): a mesh's count holds
    its edges through its own triangles; ``between`` the crossings of two meshes of which one
    deforms (its points animated: a cloth against anything), ``between_rigid`` those of two
    rigid meshes (points fixed, moved by transforms only: obstacles laid into each other or
    into the ground, a scene's layout rather than a simulation's output). ``crossings`` is the
    sum of all but ``between_rigid``."""
    tracks = list(tracks)
    offs = np.cumsum([0] + [t.points.shape[1] for t in tracks])
    tris = np.concatenate([t.triangles + o for t, o in zip(tracks, offs[:-1])]) \
        if tracks else np.zeros((0, 3), np.int64)
    frames = tracks[0].points.shape[0] if tracks else 0
    names = [t.path for t in tracks]
    keys = ("crossings", "between", "between_rigid", "nonfinite")
    out = {k: [] for k in keys}
    out["per_mesh"] = {n: [] for n in names}

    def none_tested(bad):
        for k in keys[:3]:
            out[k].append(0)
        out["nonfinite"].append(bad)
        for n in names:
            out["per_mesh"][n].append(0)

    if len(tris) == 0:
        for _ in range(frames):
            none_tested(0)
        return out
    edges = edges_of(tris)
    part_v = np.repeat(np.arange(len(tracks)), np.diff(offs))
    rigid_v = np.repeat([0 if t.deforming else 1 for t in tracks], np.diff(offs))
    chk = SelfIntersectionChecker(tris, edges, int(offs[-1]), device, parts=part_v,
                                  rigid=rigid_v)
    edge_part = part_v[edges[:, 0]]
    # the test is translation-invariant: float32 coordinates about the meshes' centre keep a
    # stage far from the origin as precise as one at it
    first = np.concatenate([t.points[0] for t in tracks]) if frames else np.zeros((0, 3))
    ok = first[np.isfinite(first).all(axis=1)]
    centre = 0.5 * (ok.min(axis=0) + ok.max(axis=0)) if len(ok) else np.zeros(3)
    for f in range(frames):
        x = np.concatenate([t.points[f] for t in tracks]) - centre
        bad = int((~np.isfinite(x).all(axis=1)).sum())
        if bad:
            none_tested(bad)
            continue
        total = chk(x)
        per_edge = chk.per_edge.numpy()
        other = chk.other.numpy()
        rigid = chk.rigid_other.numpy()
        same = np.bincount(edge_part, weights=per_edge - other - rigid, minlength=len(tracks))
        out["crossings"].append(total - int(rigid.sum()))
        out["between"].append(int(other.sum()))
        out["between_rigid"].append(int(rigid.sum()))
        out["nonfinite"].append(0)
        for k, n in enumerate(names):
            out["per_mesh"][n].append(int(same[k]))
    return out


#: points sampled along each edge (ends included) by `solid_depths` and `ObstacleChecker`
SOLID_SAMPLES = 9


def edge_samples(x, edges) -> np.ndarray:
    """`SOLID_SAMPLES` evenly spaced points along each of ``edges`` (E, 2) of the points ``x``
    (ends included), as one (SOLID_SAMPLES * E, 3) array: a cloth edge between two vertices
    held outside can still cut into a curved solid."""
    s = np.linspace(0.0, 1.0, SOLID_SAMPLES)[:, None, None]
    return (x[edges[:, 0]][None] * (1.0 - s) + x[edges[:, 1]][None] * s).reshape(-1, 3)


def solid_depths(tracks, solids, tolerance: float = 1e-6) -> dict:
    """How deep the deforming meshes of ``tracks`` (`warp_cloth.usd.MeshTrack`, points
    time-sampled: cloth) go into the implicit solids ``solids`` (`warp_cloth.usd.SolidTrack`:
    spheres and cubes), per time: `SOLID_SAMPLES` points along every edge (a cloth edge between
    two vertices held outside can still cut into a curved solid) tested in each solid's own
    frame. A sphere's depth is ``(r - |p|)`` times the transform's smallest scale (exact for a
    rotation and a uniform scale, a lower bound for an ellipsoid); a cube's the least of
    ``(half - |p_i|)`` times the scale of axis ``i`` (exact without shear). Returns ``{"inside":
    [...], "depth": [...]}``: per time, the sampled points deeper than ``tolerance`` (m) and
    the deepest depth (m, 0 when none is inside); a time with a non-finite point counts 0."""
    out = {"inside": [], "depth": []}
    cloth = [t for t in tracks if t.deforming and len(t.triangles)]
    frames = tracks[0].points.shape[0] if tracks else 0
    edges = [edges_of(t.triangles) for t in cloth]
    for f in range(frames):
        inside, deepest = 0, 0.0
        for t, e in zip(cloth, edges):
            x = t.points[f]
            if not np.isfinite(x).all():
                continue
            pts = edge_samples(x, e)
            for sol in solids:
                m = sol.matrices[f]
                a, b = m[:3, :3], m[3, :3]
                try:
                    local = np.linalg.solve(a.T, (pts - b).T).T  # world = local a + b
                except np.linalg.LinAlgError:
                    continue  # a degenerate transform: no volume
                r = sol.size[f]
                if sol.kind == "sphere":
                    scale = float(np.linalg.svd(a, compute_uv=False).min())
                    d = (r - np.linalg.norm(local, axis=1)) * scale
                else:
                    axis = np.linalg.norm(a, axis=1)  # row i: local axis i in world
                    d = ((r - np.abs(local)) * axis).min(axis=1)
                deep = d > tolerance
                inside += int(deep.sum())
                if deep.any():
                    deepest = max(deepest, float(d.max()))
        out["inside"].append(inside)
        out["depth"].append(deepest)
    return out


class ObstacleChecker:
    """The cloth against its obstacles after a frame, on the host in float64 (`Scene.run`'s
    ``check_intersections``): `SOLID_SAMPLES` points along every cloth edge against each
    analytic obstacle (plane, sphere, box: a cloth edge between two vertices held outside can
    still cut into a curved one) and every cloth edge against each mesh obstacle's surface
    (`mesh_edge_crossings`: an edge through a thin part), and the least distance of a free
    vertex to any obstacle. ``edges`` (E, 2); ``free``: a boolean mask of the vertices that
    are not pinned (pins may be placed anywhere: an edge between two pins is not tested)."""

    def __init__(self, obstacles, edges, free, tolerance: float = 1e-6, device="cpu"):
        from .motion import KIND_MESH

        self.analytic = [ob for ob in obstacles if ob.kind != KIND_MESH]
        self.meshes = [ob for ob in obstacles if ob.kind == KIND_MESH]
        self.free = np.asarray(free, dtype=bool)
        e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        self.edges = e[self.free[e[:, 0]] | self.free[e[:, 1]]]
        self.tolerance = float(tolerance)
        self.device = device

    def __call__(self, positions, t: float):
        """``(inside, depth, clearance)`` at world ``positions`` and time ``t``: edge points more
        than the tolerance inside an analytic obstacle plus cloth edges through a mesh
        obstacle's surface; the deepest of those points (m, 0 when none); the least signed
        distance of a free vertex to any obstacle (m, inf without obstacles)."""
        x = np.asarray(positions, dtype=np.float64)
        e = self.edges
        inside, depth, clear = 0, 0.0, float("inf")
        if len(e) and self.analytic:
            pts = edge_samples(x, e)
            for ob in self.analytic:
                d = ob.signed_distance(pts, t)
                deep = d < -self.tolerance
                inside += int(deep.sum())
                if deep.any():
                    depth = max(depth, float(-d.min()))
        for ob in self.meshes:
            inside += int(mesh_edge_crossings(ob, x, e, t, self.device).sum())
        free = x[self.free]
        if len(free):
            for ob in self.analytic + self.meshes:
                clear = min(clear, float(ob.signed_distance(free, t).min()))
        return inside, depth, clear
