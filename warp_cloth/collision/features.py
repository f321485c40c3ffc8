"""Cloth edges and triangles against the sharp features of mesh obstacles.

Vertex contact (`ObstacleContact`) keeps every cloth *vertex* outside the obstacles, but a cloth
edge between two such vertices can still cut through a thin part of a mesh (a blade, a thin tube,
a sharp rim) and a cloth triangle can still be pierced by a spike. Only where the surface turns
sharply over a cloth edge's length ``L`` can that happen: a cloth edge whose ends are the thickness
``h`` outside dips under a crease whose normals differ by ``theta`` by at most about
``(L/2) sin(theta/2) - h``, and under a curved part of radius ``R`` by ``L^2 / (8R) - h``.
`sharp_features` keeps, once on the host, the convex edges where either exceeds ``h/2`` (``L``:
the longest cloth edge stretched by 20 %), boundary and non-manifold edges, and their vertices;
and, since those estimates take one crease or one radius at a time, a probe (`dip_probe`) keeps
every other convex vertex and convex edge that a straight cloth edge of the longest rest length,
its ends the thickness out on either side, passes below (a ridge of several moderate creases).
Elsewhere a rest-length cloth edge stays outside the surface between its vertices (sampled, not
bounded: a stretched edge may cut into the thickness).
The 960-triangle torus of the ``mesh`` scene (tube radius 8 cm) has no such feature for the
default 32 x 32 sheet, and pays nothing; a blade or a thin tube does. Boxes are meshes of their
12 triangles here (edges and corners). A `Sphere` whose curvature a rest-length cloth triangle
(`obstacles.cloth_chord`) cuts into by more than half the thickness gets its centre as a sharp
vertex with its radius added to the separation (`_sphere_pair`); one it cuts into by less has
the vertex contact's radius padded (`obstacles.sphere_contact_pad`); the others pay nothing.

Each step, on the paths from ``x_start`` to ``x`` (cloth) and from the pose at ``t`` to the pose
at ``t + dt`` (obstacle):

- **broad phase** (`warp_cloth.collision.broadphase`): swept boxes of the cloth's triangles and
  edges (inflated by the thickness and a margin) in two refitted `wp.Bvh`; each sharp vertex
  queries the triangle BVH and each sharp edge the edge BVH with its own swept box;
- **narrow phase**: the continuous vertex-triangle and edge-edge tests of
  `warp_cloth.collision.geometry` (float64, minimum separation = the thickness), which also
  report pairs that end within the thickness;
- **record**: each hit becomes a record entry (`warp_cloth.collision.record`): the cloth
  vertices with their barycentric weights, the normal from the obstacle feature to the cloth at
  the time of impact (the side the cloth came from) and the offset that keeps the cloth feature
  the thickness away from the obstacle feature's end position;
- **response** (`respond`): Jacobi rounds over the entries, each moving the cloth feature's
  vertices along its normal by their share ``w_j / m_j / sum_k w_k^2 / m_k`` of the violation
  (Bridson et al. 2002), averaged per vertex, with ``v += dx / dt``; at least `rounds`, then
  on while a round finds an entry violated by more than `RESOLVE_TOL` of the thickness, up to
  `MAX_ROUNDS` (a device-side loop: no host read). Before the rounds, Coulomb friction
  (`friction`) for the entries in contact: the tangential velocity of the entry's point
  relative to the obstacle's surface there loses up to ``mu`` times the normal impulse.
  A step that ends its rounds with an entry
  still violated is counted (``stats``) and reported once a frame (`frame_end`). A fixed four
  rounds left a cloth edge on a spike's tip, where two dozen edge-edge entries of nearly
  opposite normals meet, pushed by the average only part of the way: it slid through the spike
  (a 32 x 32 sheet under PBD, dropped from 1.5 m onto a 5 cm cone; 16 rounds hold it).

Implicit Euler and projective dynamics get the entries of the predicted path in their solve
(`CollisionStage.detect`), like vertex contacts.

No host decision (the broad phase's refits are captured). Entries past the record's capacity
are counted (``stats``), not silent.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..util import launch
from .broadphase import ClothBroadPhase, cloth_bounds_kernel
from .geometry import (CCD_MISS, ccd_edge_edge, ccd_vertex_triangle, d3, ee_impact, f3,
                       point_triangle_closest, segment_segment_closest, vt_impact)
from .motion import KIND_BOX, KIND_SPHERE
from .obstacles import sphere_needs_features
from .record import (KIND_EDGE_EDGE, KIND_VERTEX_TRIANGLE, ContactRecord, entry_gap,
                     record_append, record_threads)

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile

__all__ = ["sharp_features", "box_mesh", "FeatureContact"]

#: advances of the continuous tests before a conservative hit
CCD_ITERATIONS = 64
#: cloth edges are taken this much longer than at rest when deciding which ridges are sharp
STRETCH_MARGIN = 1.2
#: the cloth's boxes in the feature pass's BVHs are its vertices' paths widened by this many
#: thicknesses, refitted only when a path leaves its box (explicit Euler's 182 steps a frame on
#: the table moved a vertex about 0.1 mm a step: a refit every twenty-odd steps, not every step)
FAT_SLACK = 0.5
#: `FeatureContact.respond` goes on while an entry is violated by more than this fraction of
#: the thickness ...
RESOLVE_TOL = 1.0e-3
#: ... up to this many rounds in a step (then the step is counted as unresolved)
MAX_ROUNDS = 64


#: a convex mesh vertex whose cone a cloth triangle over it could come within this share of the
#: thickness of piercing (``(L/2) cos alpha > SOFT_TIP_SHARE h``, `sharp_features`; ``L`` the
#: cloth triangles' stretched chord) is kept as a sharp vertex, its edges not: the cloth's
#: triangles then keep the thickness from it. Before (only tips past ``1.5 h``), a 32 x 32 sheet
#: dropped on a lumpy 1,280-triangle mesh (`docs/bench/probes/robust.py blob`, through
#: ``warp-cloth run mesh --obstacle``) had a mesh vertex of 77.3 degrees' half-angle
#: (``(L/2) cos alpha`` 5.8 mm, h 5 mm) 0.24 mm through a cloth triangle, and another 0.07 mm,
#: every cloth vertex 5 mm out. 0.9: the torus of the ``mesh`` scene gains none (0.8: 90)
SOFT_TIP_SHARE = 0.9
#: the dip probe (`dip_probe`, `sharp_features`' ``probe``): a convex vertex, or a convex edge's
#: midpoint, that a straight cloth edge of the cloth's longest rest edge with both ends the
#: thickness out passes within this share of the thickness of is sharp. The crease and arc
#: estimates take one crease or one radius at a time: a ridge bent by several creases in a row
#: (15, 21 and 18 degrees within 2 cm on a lumpy 1,280-triangle mesh, none sharp alone) let a
#: 43 mm cloth diagonal pass 0.2 mm under a mesh vertex with both its vertices 5 mm out (PD and
#: implicit Euler, 1 of 12 lumpy meshes, 2026-12-07). 0 (an edge through the surface) and the
#: rest length: the `mesh` scene's torus (tube creases of 22.5 degrees: a 44 mm edge comes
#: within 0.7 mm) gains none; 0.1 with the probe's finest sampling kept 150 of its vertices
PROBE_SHARE = 0.0
#: an edge is a probe candidate only where its own crease dips a probe edge by this share of the
#: thickness (``(L/2) sin(theta/2)``): a flatter edge pokes out only with the surface around it,
#: whose vertices the probe keeps (the thin ring of `contact_scenes.thin_parts_mesh`: its 2,304
#: edges of 1.9 degrees around the tube were kept by a 44 mm probe, 35 % more time a frame
#: for PBD, while its creases along the tube and every vertex of it were sharp already)
PROBE_MIN_CREASE = 0.1
#: the probe runs where the mesh is coarse (edges at least this share of the probe's length):
#: the failure it finds is a few moderate creases under one cloth edge. Where the mesh is finer
#: its edges' arc estimate (``L^2 theta / (8 l)``, the curvature) is kept with the probe's
#: length where it comes within `PROBE_SHARE` of a crossing. 82k triangles: 19.5 s of probing
#: the whole mesh, 1.6 s now
PROBE_FINE = 0.25
#: `dip_probe`'s directions about a candidate (pairs of opposite ones) and distances along each
PROBE_DIRECTIONS = 16
PROBE_RADII = tuple(0.25 + 0.5 * k / (11 - 1) for k in range(11))  # 0.25 .. 0.75


@wp.kernel
def probe_ends_kernel(mid: wp.uint64, two_sided: int, cpts: wp.array(dtype=wp.vec3),
                      cnrm: wp.array(dtype=wp.vec3), length: float, gap: float,
                      radii: wp.array(dtype=float), ends: wp.array3d(dtype=wp.vec3),
                      ok: wp.array3d(dtype=int)):
    """`dip_probe`'s cloth-vertex places about candidate ``i``: along direction ``k`` of its
    tangent plane, at ``radii[r] * length``, the surface below (a ray down the candidate's
    normal from ``length`` above) and ``gap`` out along that face's normal; valid where the ray
    meets a front face (either face of an open mesh: ``two_sided``) and nothing of the mesh is
    nearer than the gap."""
    i, k, r = wp.tid()
    c = cpts[i]
    n = cnrm[i]
    a = wp.vec3(1.0, 0.0, 0.0)
    if wp.abs(n[0]) > 0.9:
        a = wp.vec3(0.0, 1.0, 0.0)
    t1 = wp.normalize(wp.cross(n, a))
    t2 = wp.cross(n, t1)
    phi = 2.0 * wp.pi * float(k) / float(ends.shape[1])
    start = c + radii[r] * length * (wp.cos(phi) * t1 + wp.sin(phi) * t2) + length * n
    ok[i, k, r] = 0
    ray = wp.mesh_query_ray(mid, start, -n, 2.0 * length)
    if not ray.result:
        return
    fn = wp.mesh_eval_face_normal(mid, ray.face)
    if two_sided != 0 and wp.dot(fn, n) < 0.0:
        fn = -fn  # an open mesh: either side is outside
    if wp.dot(fn, n) <= 0.0:
        return  # a back face: the ray started inside another part
    e = start - ray.t * n + gap * fn
    q = wp.mesh_query_point_no_sign(mid, e, 0.99 * gap)
    if q.result:
        return  # nearer the mesh than a cloth vertex may be
    ends[i, k, r] = e
    ok[i, k, r] = 1


@wp.kernel
def probe_dip_kernel(cpts: wp.array(dtype=wp.vec3), cnrm: wp.array(dtype=wp.vec3),
                     length: float, ends: wp.array3d(dtype=wp.vec3),
                     ok: wp.array3d(dtype=int), low: wp.array(dtype=float)):
    """The lowest height above candidate ``i`` (along its normal) of a segment of at most
    ``length`` between a place on one side and one on the opposite side (`dip_probe`)."""
    i = wp.tid()
    c = cpts[i]
    n = cnrm[i]
    nk = ends.shape[1]
    nr = ends.shape[2]
    best = float(1.0e30)
    for k in range(nk // 2):
        for r1 in range(nr):
            if ok[i, k, r1] == 0:
                continue
            e1 = ends[i, k, r1]
            for r2 in range(nr):
                if ok[i, k + nk // 2, r2] == 0:
                    continue
                d = ends[i, k + nk // 2, r2] - e1
                ll = wp.length_sq(d)
                if ll > length * length or ll <= 0.0:
                    continue
                t = wp.dot(c - e1, d) / ll
                if t <= 0.0 or t >= 1.0:
                    continue
                best = wp.min(best, wp.dot(e1 + t * d - c, n))
    low[i] = best


def dip_probe(vertices, triangles, points, normals, length: float, gap: float,
              device="cpu", two_sided: bool = False) -> np.ndarray:
    """Per candidate point on the mesh (``points``, unit ``normals``): the lowest height above it
    of a straight cloth edge of at most ``length`` whose ends lie ``gap`` out from the surface
    on opposite sides of it, sampled: `PROBE_DIRECTIONS` directions in its tangent plane, the
    ends at `PROBE_RADII` times ``length`` along them, on the surface a ray down the normal
    meets (once; Warp kernels on ``device``, about 0.4 ms a candidate on this project's CPU:
    5.7 s for a lumpy 82k-triangle mesh, 1.6 s of it the estimates). Below zero, such an edge
    passes through the mesh there with both ends outside. The crease and arc estimates of
    `sharp_features` take one crease or one radius at a time; this measures a ridge bent by
    several creases in a row. Samples, not a bound. ``two_sided``: an open mesh, whose faces
    are met from either side (each candidate's normal gives the side probed)."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not len(pts) or not len(t):
        return np.full(len(pts), np.inf)
    d = device
    mesh = wp.Mesh(points=wp.array(v.astype(np.float32), dtype=wp.vec3, device=d),
                   indices=wp.array(t.astype(np.int32).ravel(), dtype=int, device=d))
    cp = wp.array(pts.astype(np.float32), dtype=wp.vec3, device=d)
    cn = wp.array(np.asarray(normals, dtype=np.float32).reshape(-1, 3), dtype=wp.vec3, device=d)
    shape = (len(pts), PROBE_DIRECTIONS, len(PROBE_RADII))
    ends = wp.zeros(shape, dtype=wp.vec3, device=d)
    ok = wp.zeros(shape, dtype=int, device=d)
    launch(probe_ends_kernel, shape,
           [mesh.id, int(two_sided), cp, cn, float(length), float(gap),
            wp.array(PROBE_RADII, dtype=float, device=d), ends, ok], device=d)
    low = wp.zeros(len(pts), dtype=float, device=d)
    launch(probe_dip_kernel, len(pts), [cp, cn, float(length), ends, ok, low], device=d)
    return low.numpy().astype(np.float64)


def sharp_features(vertices, triangles, length: float, thickness: float,
                   chord: float | None = None, probe: float | None = None, device="cpu"):
    """``(edges (E, 2), vertices (V,))`` of a triangle mesh that a cloth edge of ``length`` whose
    ends are ``thickness`` outside can cut into by more than half the thickness: convex edges
    where either estimate of the dip exceeds ``1.5 thickness``, a single crease
    ``(L/2) sin(theta/2)`` (``theta``: the angle between the face normals) or an arc
    ``L^2 / (8 R)`` with the local radius ``R = l / theta`` (``l``: the distance between the two
    faces' centroids; a thin tube has no sharp crease but a small radius), plus boundary and
    non-manifold edges, and every vertex of those edges (host, once).

    And the tips: a convex vertex whose faces close around it like a cone of half-angle
    ``alpha`` (``sin alpha = 1 - delta / (2 pi)``, ``delta`` the angle defect, ``2 pi`` less
    the sum of its faces' angles) lets a straight edge through it dip ``(L/2) cos alpha``
    (its ends on the cone, its middle through the axis); where that exceeds ``1.5 thickness``
    the vertex and every convex edge at it are kept. The centroid estimate above misses a
    spike's tip: its faces are slivers from the tip to a wide base, whose centroids lie where
    the spike is wide (a 5 cm cone 40 cm tall dropped on by a 32 x 32 sheet: a cloth edge slid
    onto the spike between its vertices, through it, with every vertex outside).

    And the soft tips (the vertex only, not its edges): a cloth triangle whose corners are the
    thickness out of a cone of half-angle ``alpha`` has the apex ``(C/2) cos alpha - h``
    through it at worst (``C``: ``chord``, the triangle's enclosing diameter, default
    ``length``), so a convex vertex where ``(C/2) cos alpha > SOFT_TIP_SHARE h`` is returned
    among the vertices (`SOFT_TIP_SHARE`).

    And what the dip probe finds (``probe``: the cloth edge's length, `dip_probe`; None: no
    probe): the convex vertices and the convex edges (by their midpoints, with their vertices)
    that an edge of that length, its ends the thickness out, passes within `PROBE_SHARE` of the
    thickness of."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    cen = v[t].mean(axis=1)
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    opp = np.concatenate([t[:, 2], t[:, 0], t[:, 1]])
    face = np.tile(np.arange(len(t)), 3)
    key = np.sort(e, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, opp, face = key[order], opp[order], face[order]
    start = np.flatnonzero(np.r_[True, (key[1:] != key[:-1]).any(axis=1)])
    count = np.diff(np.r_[start, len(key)])
    L, h = float(length), float(thickness)
    open_v = np.zeros(len(v), dtype=bool)  # on a boundary or non-manifold edge
    open_v[key[start[count != 2]].ravel()] = True
    # an open mesh is met from either side: a crease or tip convex from its back counts too
    # (a tent's ridge whose normals pointed down was no feature: a cloth edge through it)
    two = bool((count != 2).any())
    tips = _sharp_tips(v, t, L, h, open_v, two_sided=two)
    soft = _sharp_tips(v, t, float(chord) if chord is not None else L, h, open_v,
                       share=SOFT_TIP_SHARE, two_sided=two)
    sharp, rest = [], []  # rest: convex manifold edges not sharp by the estimates
    for s, c in zip(start, count):
        a, b = key[s]
        if c != 2:  # boundary (an open mesh's rim) or non-manifold
            sharp.append((a, b))
            continue
        f1, f2 = face[s], face[s + 1]
        side = float((v[opp[s + 1]] - v[a]) @ n[f1])
        if side >= 0.0 and not (two and side > 0.0):
            continue  # concave or flat: a straight edge outside it stays outside
        theta = math.acos(min(1.0, max(-1.0, float(n[f1] @ n[f2]))))
        ell = max(float(np.linalg.norm(cen[f1] - cen[f2])), 1e-12)
        dip = max(0.5 * L * math.sin(0.5 * theta), min(L * L * theta / (8.0 * ell), 0.5 * L))
        if dip > 1.5 * h or tips[a] or tips[b]:
            sharp.append((a, b))
        elif probe is None:
            continue
        elif float(np.linalg.norm(v[a] - v[b])) < PROBE_FINE * probe:
            # a fine part: the arc estimate is the curvature there; with the probe's
            # length, kept where an edge would pass within PROBE_SHARE of crossing
            if min(probe * probe * theta / (8.0 * ell), 0.5 * probe) > (1.0 - PROBE_SHARE) * h:
                sharp.append((a, b))
        elif 0.5 * probe * math.sin(0.5 * theta) >= PROBE_MIN_CREASE * h:
            rest.append((a, b, f1, f2))
    probe_v = np.zeros(0, dtype=np.int64)
    if probe is not None:
        # the probe for what the estimates left: convex vertices not yet kept, and the
        # midpoints of the convex edges not yet sharp
        kept = np.zeros(len(v), dtype=bool)
        kept[np.asarray(sharp, dtype=np.int64).ravel()] = True
        kept |= soft
        # the vertices of a coarse part (their edges PROBE_FINE of the probe or longer, on
        # average; a fine part's curvature is its edges' arc estimate)
        ue = key[start]
        elen = np.linalg.norm(v[ue[:, 0]] - v[ue[:, 1]], axis=1)
        deg = np.bincount(ue.ravel(), minlength=len(v))
        mean = np.bincount(ue.ravel(), weights=np.repeat(elen, 2), minlength=len(v)) / \
            np.maximum(deg, 1)
        coarse = mean >= PROBE_FINE * float(probe)
        cand_v = np.flatnonzero(_convex_vertices(v, t, two) & ~open_v & ~kept & coarse)
        ce = np.asarray([r[:2] for r in rest], dtype=np.int64).reshape(-1, 2)
        fs = np.asarray([r[2:] for r in rest], dtype=np.int64).reshape(-1, 2)
        cn = n[fs[:, 0]] + n[fs[:, 1]]
        cn /= np.maximum(np.linalg.norm(cn, axis=1, keepdims=True), 1e-300)
        pts = np.concatenate([v[cand_v], 0.5 * (v[ce[:, 0]] + v[ce[:, 1]])])
        nrm = np.concatenate([vertex_normals(v, t)[cand_v], cn])
        nc = len(pts)
        if two:  # an open mesh: probed from both sides
            pts, nrm = np.concatenate([pts, pts]), np.concatenate([nrm, -nrm])
        low = dip_probe(v, t, pts, nrm, float(probe), h, device, two_sided=two)
        hit = low < PROBE_SHARE * h
        if two:
            hit = hit[:nc] | hit[nc:]
        probe_v = cand_v[hit[:len(cand_v)]]
        sharp += [tuple(e) for e in ce[hit[len(cand_v):]].tolist()]
    edges = np.asarray(sharp, dtype=np.int64).reshape(-1, 2)
    return edges, np.unique(np.concatenate([edges.ravel(), np.flatnonzero(soft), probe_v]))


def edge_face_normals(vertices, triangles, edges) -> np.ndarray:
    """(E, 2, 3): the unit normals of the two triangles at each of ``edges`` (zeros for an
    edge with another number of triangles: a rim or a non-manifold edge)."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    faces = {}
    for f, tri in enumerate(t):
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            faces.setdefault((min(a, b), max(a, b)), []).append(f)
    out = np.zeros((len(edges), 2, 3))
    for k, (a, b) in enumerate(np.asarray(edges, dtype=np.int64).reshape(-1, 2)):
        fs = faces.get((min(a, b), max(a, b)), [])
        if len(fs) == 2:
            out[k] = n[fs]
    return out


def vertex_normals(vertices, triangles) -> np.ndarray:
    """(V, 3): each vertex's unit outward normal, its faces' normals weighted by their angle
    at it (zero for a vertex of no face)."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    out = np.zeros_like(v)
    fn = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    for k in range(3):
        p, q, r = v[t[:, k]], v[t[:, (k + 1) % 3]], v[t[:, (k + 2) % 3]]
        a, b = q - p, r - p
        c = np.einsum("ij,ij->i", a, b) / np.maximum(
            np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-300)
        np.add.at(out, t[:, k], fn * np.arccos(np.clip(c, -1.0, 1.0))[:, None])
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)


def box_mesh(half_extents):
    """``(vertices (8, 3), triangles (12, 3))`` of a box with these half extents about the
    origin, outward winding: a `Box` obstacle's surface in its own frame."""
    h = np.asarray(half_extents, dtype=np.float64)
    v = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)],
                 dtype=np.float64) * h
    tris = []
    for axis in range(3):
        for side in (0, 1):
            quad = [i for i in range(8) if (i >> (2 - axis)) & 1 == side]  # 4 corners of a face
            a, b, c, d = sorted(quad)  # a square's corners in binary order: a-b-d-c around it
            for t in ((a, b, d), (a, d, c)):
                n = np.cross(v[t[1]] - v[t[0]], v[t[2]] - v[t[0]])
                tris.append(t if n[axis] * (1 if side else -1) > 0 else (t[0], t[2], t[1]))
    return v, np.asarray(tris, dtype=np.int64)


def _convex_vertices(v, t, two_sided: bool = False) -> np.ndarray:
    """Per vertex: True when it lies outside the plane through its faces' centroids along its
    (area-weighted) normal; ``two_sided`` (an open mesh, met from either side): off that plane
    on either side."""
    nv = len(v)
    area_n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    vn = np.zeros_like(v)
    cen_sum = np.zeros_like(v)
    deg = np.zeros(nv)
    cen = v[t].mean(axis=1)
    for k in range(3):
        np.add.at(vn, t[:, k], area_n)
        np.add.at(cen_sum, t[:, k], cen)
        np.add.at(deg, t[:, k], 1.0)
    used = deg > 0
    convex = np.zeros(nv, dtype=bool)
    off = np.einsum("ij,ij->i", v[used] - cen_sum[used] / deg[used, None], vn[used])
    convex[used] = (np.abs(off) > 0.0) if two_sided else (off > 0.0)
    return convex


def _sharp_tips(v, t, L: float, h: float, open_v, share: float = 1.5,
                two_sided: bool = False) -> np.ndarray:
    """Per vertex: a convex tip that a cloth edge of length ``L`` dips into by more than
    ``share`` times ``h`` (`sharp_features`); not the vertices of ``open_v`` (on a boundary or
    non-manifold edge, whose angle defect means nothing)."""
    nv = len(v)
    if not len(t):
        return np.zeros(nv, dtype=bool)
    angle = np.zeros(nv)
    for k in range(3):
        p, q, r = v[t[:, k]], v[t[:, (k + 1) % 3]], v[t[:, (k + 2) % 3]]
        u, w = q - p, r - p
        c = np.einsum("ij,ij->i", u, w) / np.maximum(
            np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1), 1e-300)
        np.add.at(angle, t[:, k], np.arccos(np.clip(c, -1.0, 1.0)))
    convex = _convex_vertices(v, t, two_sided)
    used = np.zeros(nv, dtype=bool)
    used[t.ravel()] = True
    sin_a = np.clip(1.0 - (2.0 * math.pi - angle) / (2.0 * math.pi), 0.0, 1.0)
    dip = 0.5 * L * np.sqrt(np.maximum(0.0, 1.0 - sin_a * sin_a))
    return used & ~open_v & convex & (angle < 2.0 * math.pi) & (dip > share * h)


@wp.kernel
def feature_world_kernel(local: wp.array(dtype=wp.vec3), pose_of: wp.array(dtype=int),
                         poses: wp.array(dtype=wp.transform), p0: wp.array(dtype=wp.vec3),
                         p1: wp.array(dtype=wp.vec3)):
    """Sharp vertices in the world at the start and the end of the step."""
    i = wp.tid()
    k = pose_of[i]
    p0[i] = wp.transform_point(poses[5 * k + 0], local[i])
    p1[i] = wp.transform_point(poses[5 * k + 1], local[i])


@wp.func
def box_start_normal(n: wp.vec3, r: wp.vec3, inv0: wp.transform, pose1: wp.transform,
                     half: wp.vec3, u: wp.vec3, along: int, sep: float):
    """The normal of a box feature's entry whose cloth point ``r`` (at the step's start) lies in
    the box or on its surface, where the side the cloth came from means nothing (a sheet placed
    on the box's face: its edges cross the rims, its triangles touch the corners, at distance
    0, and the closest points' direction or the cross product of two edges can point into the
    box, along a side face or down). The box's own answer: the outward normal of the face
    nearest to ``r`` (the signed distance's gradient inside the box, at the end pose); where
    several faces are equally near (``r`` on a rim or a corner), the one the cloth element lies
    along best: largest ``sqrt(1 - (u . a_k)^2)`` for a cloth edge of direction ``u``
    (``along`` = 1), largest ``|u . a_k|`` for a cloth triangle of normal ``u`` (``along`` = 0),
    and on a tie the local y face, then x, then z, as vertex contact's `shape_sdf` chooses (a
    grid sheet laid on a box with its lines on the rims: each feature entry and each vertex
    contact then lift it the same way). Measured with the faces' bisector instead: a cloth edge
    lying on the top face across the rim was moved sideways with the vertex contacts lifting
    its ends straight up, and the sheet left at 1-2 m/s in its first frame (against 0.16 m/s
    of free fall); with a blend weighted as above, 8-13 m/s at the corner of a 16 x 16 grid
    whose lines lie on the rims. ``n`` is returned unchanged when ``r`` is outside the box."""
    pl = wp.transform_point(inv0, r)
    tie = 1.0e-3 * sep
    if (wp.abs(pl[0]) > half[0] + tie or wp.abs(pl[1]) > half[1] + tie
            or wp.abs(pl[2]) > half[2] + tie):
        return n
    depth = wp.vec3(half[0] - wp.abs(pl[0]), half[1] - wp.abs(pl[1]), half[2] - wp.abs(pl[2]))
    lo = wp.min(depth[0], wp.min(depth[1], depth[2]))
    lu = wp.length(u)
    best = wp.vec3(0.0)
    score = float(-1.0)
    order = wp.vec3i(1, 0, 2)  # y, x, z: the first of near-equal scores stays
    for j in range(3):
        k = order[j]
        if depth[k] <= lo + tie:
            axis = wp.vec3(0.0)
            axis[k] = 1.0
            if pl[k] < 0.0:
                axis[k] = -1.0
            a = wp.transform_vector(pose1, axis)
            c = float(1.0)
            if lu > 0.0:
                c = wp.abs(wp.dot(u, a)) / lu
                if along != 0:
                    c = wp.sqrt(wp.max(1.0 - c * c, 0.0))
            if c > score + 1.0e-3:  # the first of near-equal ones stays
                score = c
                best = a
    return best


#: a sharp mesh feature and a cloth element closer than this many thicknesses at the start
#: of the step touch: the side the cloth came from means nothing there (`_vt_pair`, `_ee_pair`)
TOUCH = wp.constant(1.0e-3)


@wp.func
def touching_edge_normal(w1: wp.vec3, w2: wp.vec3, u: wp.vec3):
    """The normal for a cloth edge of direction ``u`` that starts touching a mesh edge whose
    faces have the normals ``w1``, ``w2``: the face the cloth edge lies along best (larger
    ``sqrt(1 - (u . w)^2)``; a cloth edge lying on the top face across the rim is lifted
    straight up), on a tie the one facing up the more (+y), as `box_start_normal` chooses for a
    box. Measured with the cross product of the two edges instead (its sign arbitrary at
    distance 0): a sheet lying on a closed box-shaped mesh across its rims reached 8-22 m/s
    under explicit Euler."""
    lu = wp.length(u)
    c1 = float(1.0)
    c2 = float(1.0)
    if lu > 0.0:
        d1 = wp.dot(u, w1) / lu
        d2 = wp.dot(u, w2) / lu
        c1 = wp.sqrt(wp.max(1.0 - d1 * d1, 0.0))
        c2 = wp.sqrt(wp.max(1.0 - d2 * d2, 0.0))
    if c1 > c2 + 1.0e-3:
        return w1
    if c2 > c1 + 1.0e-3:
        return w2
    if w2[1] > w1[1]:
        return w2
    return w1


@wp.func
def _vt_pair(a0: wp.vec3, a1: wp.vec3, src: int, ia: int, ib: int, ic: int,
             x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3), gap: float, sep: float,
             mu: float, rec: ContactRecord, half: wp.vec3, inv0: wp.transform,
             pose1: wp.transform, vnormal: wp.vec3):
    """The narrow phase of a sharp vertex's path ``a0 -> a1`` against cloth triangle
    ``(ia, ib, ic)``: an entry keeping the triangle ``sep`` (the thickness) away from the
    vertex's end position, on the side the triangle was at the time of impact. ``half``: a
    box's half extents (zero for a mesh), ``inv0`` / ``pose1`` its inverse pose at the step's
    start and its pose at the end: while the triangle's point nearest the corner starts in the
    box or on it, the normal is the box's own (`box_start_normal`). A mesh's vertex whose path
    starts touching the triangle (closer than `TOUCH` thicknesses) has no side it came from
    either: the triangle's normal, turned to the side of the vertex's outward normal
    ``vnormal`` (world, the end pose)."""
    s, toi = ccd_vertex_triangle(d3(a0), d3(x0[ia]), d3(x0[ib]), d3(x0[ic]), d3(a1),
                                 d3(x1[ia]), d3(x1[ib]), d3(x1[ic]), wp.float64(gap),
                                 CCD_ITERATIONS)
    if s != CCD_MISS:
        # at the time of impact; the triangle moves away from the vertex (-n)
        n, bw, ok = vt_impact(a0, a1, x0[ia], x1[ia], x0[ib], x1[ib], x0[ic], x1[ic], toi)
        if ok:
            n = -n
            if half[0] > 0.0:
                q0, bw0 = point_triangle_closest(d3(a0), d3(x0[ia]), d3(x0[ib]), d3(x0[ic]))
                tn = wp.cross(x0[ib] - x0[ia], x0[ic] - x0[ia])
                n = box_start_normal(n, f3(q0), inv0, pose1, half, tn, 0, sep)
            elif wp.length(vnormal) > 0.0:
                q0, bw0 = point_triangle_closest(d3(a0), d3(x0[ia]), d3(x0[ib]), d3(x0[ic]))
                tn = wp.cross(x0[ib] - x0[ia], x0[ic] - x0[ia])
                if wp.length(f3(q0) - a0) < TOUCH * sep and wp.length(tn) > 0.0:
                    n = wp.normalize(tn)
                    if wp.dot(n, vnormal) < 0.0:
                        n = -n
            w = wp.vec4(bw[0], bw[1], bw[2], 0.0)
            # ref: the plane's point at the step's start (offset - n . ref: how far the
            # obstacle moved it along n in the step; `respond` takes the cloth's approach
            # relative to it)
            record_append(rec, KIND_VERTEX_TRIANGLE, wp.vec4i(ia, ib, ic, -1), w, n,
                          wp.dot(n, a1) + sep, a0 + sep * n, mu, 0.0, src)


@wp.func
def _sphere_pair(a0: wp.vec3, a1: wp.vec3, src: int, ia: int, ib: int, ic: int,
                 x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3), gap: float,
                 sep: float, mu: float, rec: ContactRecord):
    """A sphere's centre (path ``a0 -> a1``) against cloth triangle ``(ia, ib, ic)``; ``gap``
    and ``sep`` include the radius. On a hit the entry holds the triangle's point nearest the
    centre at the step's end (weights and normal from there, not from the time of impact): a
    triangle that slid over the sphere during the step reaches it first near one corner and
    ends deepest in its middle, and an entry with the corner's weights, already satisfied,
    left it 1.2 mm inside the sphere (a 16 x 16 sheet at a 0.5 mm thickness, implicit
    Euler)."""
    s, toi = ccd_vertex_triangle(d3(a0), d3(x0[ia]), d3(x0[ib]), d3(x0[ic]), d3(a1),
                                 d3(x1[ia]), d3(x1[ib]), d3(x1[ic]), wp.float64(gap),
                                 CCD_ITERATIONS)
    if s != CCD_MISS:
        q, bw = point_triangle_closest(d3(a1), d3(x1[ia]), d3(x1[ib]), d3(x1[ic]))
        dv = f3(q) - a1
        n = wp.vec3(0.0)
        ok = True
        if wp.length(dv) > 1.0e-6 * sep:
            n = wp.normalize(dv)
        else:  # the centre on the triangle: the side it met it from
            nt, bwt, ok = vt_impact(a0, a1, x0[ia], x1[ia], x0[ib], x1[ib], x0[ic], x1[ic], toi)
            n = -nt
        if ok:
            w = wp.vec4(float(bw[0]), float(bw[1]), float(bw[2]), 0.0)
            record_append(rec, KIND_VERTEX_TRIANGLE, wp.vec4i(ia, ib, ic, -1), w, n,
                          wp.dot(n, a1) + sep, a0 + sep * n, mu, 0.0, src)


@wp.func
def _ee_pair(a0: wp.vec3, b0: wp.vec3, a1: wp.vec3, b1: wp.vec3, src: int, ic: int, id: int,
             x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3), gap: float, sep: float,
             mu: float, rec: ContactRecord, w1: wp.vec3, w2: wp.vec3, half: wp.vec3,
             inv0: wp.transform, pose1: wp.transform):
    """The narrow phase of a sharp edge's path against cloth edge ``(ic, id)``: an entry keeping
    the cloth edge ``sep`` (the thickness) away from the obstacle edge's end position. ``w1``,
    ``w2``: the normals of the obstacle edge's two faces (zero for a rim). ``half``: a box's half
    extents (zero for a mesh), ``inv0`` / ``pose1`` its inverse pose at the step's start and
    its pose at the end: a cloth edge whose closest point lies in the box (or on it) at the
    start has no side it came from (it touched or straddled the edge: a sheet starting on the
    box's face), and its normal is the box's own (`box_start_normal`). Measured before: a
    normal into the solid behind both faces held such edges inside; one along a side face
    pointing down (the cross product of a cloth edge lying
    exactly across the rim and the rim) pulled a 10 x 10 sheet's overhanging vertex 4.5 cm down
    in one step (11 m/s); the faces' bisector moved the sheet sideways (1-2 m/s at the first
    frame, against 0.16 m/s of free fall); and a vertical edge's side normal (in its normal
    cone: the cross product of the two edges) pushed a cloth edge lying on the top face out
    sideways. A mesh has no such inside test here (behind both faces of a thin part's edge is
    also its far side, where cloth may lie), but a cloth edge that starts touching a mesh edge
    (closer than `TOUCH` thicknesses: no side it came from) takes the normal of the face it
    lies along (`touching_edge_normal`)."""
    s, toi = ccd_edge_edge(d3(a0), d3(b0), d3(x0[ic]), d3(x0[id]), d3(a1), d3(b1),
                           d3(x1[ic]), d3(x1[id]), wp.float64(gap), CCD_ITERATIONS)
    if s != CCD_MISS:
        # at the time of impact; the cloth edge moves away from the obstacle edge (-n)
        n, fs, ft2, ok = ee_impact(a0, a1, b0, b1, x0[ic], x1[ic], x0[id], x1[id], toi)
        n = -n
        if ok and half[0] > 0.0:
            s0, t0, q0, r0 = segment_segment_closest(d3(a0), d3(b0), d3(x0[ic]), d3(x0[id]))
            n = box_start_normal(n, f3(r0), inv0, pose1, half, x0[id] - x0[ic], 1, sep)
        elif ok and wp.length(w1) > 0.0 and wp.length(w2) > 0.0:
            s0, t0, q0, r0 = segment_segment_closest(d3(a0), d3(b0), d3(x0[ic]), d3(x0[id]))
            if wp.length(f3(q0) - f3(r0)) < TOUCH * sep:
                fs0 = float(s0)
                if fs0 < 1.0e-4 or fs0 > 1.0 - 1.0e-4:
                    # touching at the obstacle edge's end, a vertex of the mesh: its entries
                    # with the cloth triangles at the cloth edge hold it (`_vt_pair`); this
                    # edge's faces need not face the cloth there (a vertical edge's sides
                    # for a cloth lying on the top face across the corner pushed it sideways)
                    ok = False
                else:
                    n = touching_edge_normal(w1, w2, x0[id] - x0[ic])
        if ok:
            o1 = a1 + fs * (b1 - a1)
            o0 = a0 + fs * (b0 - a0)
            w = wp.vec4(1.0 - ft2, ft2, 0.0, 0.0)
            record_append(rec, KIND_EDGE_EDGE, wp.vec4i(ic, id, -1, -1), w, n,
                          wp.dot(n, o1) + sep, o0 + sep * n, mu, 0.0, src)


@wp.kernel
def vertex_triangle_kernel(
    bvh: wp.uint64,
    p0: wp.array(dtype=wp.vec3),
    p1: wp.array(dtype=wp.vec3),
    source: wp.array(dtype=int),
    x0: wp.array(dtype=wp.vec3),
    x1: wp.array(dtype=wp.vec3),
    tris: wp.array2d(dtype=wp.int32),
    gap: float,
    sep: float,
    mu_t: wp.array(dtype=float),
    rec: ContactRecord,
    vbox_half: wp.array(dtype=wp.vec3),
    pose_of: wp.array(dtype=int),
    poses: wp.array(dtype=wp.transform),
    vnormals: wp.array(dtype=wp.vec3),
    vradius: wp.array(dtype=float),
):
    """A sharp obstacle vertex against the cloth triangles its path comes within ``gap`` of
    (`_vt_pair`); a sphere's centre (radius ``vradius[i] > 0``) with the radius added to the
    gap and the separation."""
    i = wp.tid()
    a0 = p0[i]
    a1 = p1[i]
    r = vradius[i]
    lo = wp.min(a0, a1) - wp.vec3(gap + r)
    hi = wp.max(a0, a1) + wp.vec3(gap + r)
    q = wp.bvh_query_aabb(bvh, lo, hi)
    t = int(0)
    src = source[i]
    pose1 = poses[5 * pose_of[i] + 1]  # the end of the step
    inv0 = poses[5 * pose_of[i] + 2]  # the inverse at the start
    half = vbox_half[i]
    vn = wp.transform_vector(pose1, vnormals[i])
    while wp.bvh_query_next(q, t):
        if r > 0.0:
            _sphere_pair(a0, a1, src, tris[t, 0], tris[t, 1], tris[t, 2], x0, x1, gap + r,
                         sep + r, mu_t[src], rec)
        else:
            _vt_pair(a0, a1, src, tris[t, 0], tris[t, 1], tris[t, 2], x0, x1, gap, sep,
                     mu_t[src], rec, half, inv0, pose1, vn)


@wp.kernel
def edge_edge_kernel(
    bvh: wp.uint64,
    p0: wp.array(dtype=wp.vec3),
    p1: wp.array(dtype=wp.vec3),
    fedges: wp.array2d(dtype=wp.int32),
    source: wp.array(dtype=int),
    x0: wp.array(dtype=wp.vec3),
    x1: wp.array(dtype=wp.vec3),
    edges: wp.array2d(dtype=wp.int32),
    gap: float,
    sep: float,
    mu_t: wp.array(dtype=float),
    rec: ContactRecord,
    face_normals: wp.array2d(dtype=wp.vec3),
    box_half: wp.array(dtype=wp.vec3),
    pose_of: wp.array(dtype=int),
    poses: wp.array(dtype=wp.transform),
):
    """A sharp obstacle edge against the cloth edges its path comes within ``gap`` of
    (`_ee_pair`)."""
    k = wp.tid()
    ja = fedges[k, 0]
    jb = fedges[k, 1]
    a0 = p0[ja]
    b0 = p0[jb]
    a1 = p1[ja]
    b1 = p1[jb]
    lo = wp.min(wp.min(a0, a1), wp.min(b0, b1)) - wp.vec3(gap)
    hi = wp.max(wp.max(a0, a1), wp.max(b0, b1)) + wp.vec3(gap)
    q = wp.bvh_query_aabb(bvh, lo, hi)
    e = int(0)
    src = source[ja]
    pose = poses[5 * pose_of[ja] + 1]  # the end of the step
    w1 = wp.transform_vector(pose, face_normals[k, 0])
    w2 = wp.transform_vector(pose, face_normals[k, 1])
    inv0 = poses[5 * pose_of[ja] + 2]  # the inverse at the start
    while wp.bvh_query_next(q, e):
        _ee_pair(a0, b0, a1, b1, src, edges[e, 0], edges[e, 1], x0, x1, gap, sep, mu_t[src],
                 rec, w1, w2, box_half[k], inv0, pose)


#: an entry whose free vertices carry less than this share of its squared weights is held by
#: its pinned vertices (`pin_held`)
PIN_SHARE = wp.constant(1.0e-2)


@wp.func
def pin_held(vid: wp.vec4i, w: wp.vec4, inv_mass: wp.array(dtype=float)):
    """Whether an entry's point is (nearly) a pinned vertex's: its free vertices carry less than
    `PIN_SHARE` of ``sum w_j^2`` (a cloth edge touched within a few percent of its length from
    its pinned end, an edge pair whose free end weighs 0.006). Moving the free vertices cannot
    move such a point: the projection's share ``w_j / m_j / sum w_k^2 / m_k`` would throw the
    free vertex by the violation over its weight (measured: a thin rod driven through a
    curtain's pinned row moved a vertex 4 cm in one step, then 1e6 strain under every solver),
    and a penalty of stiffness ``kappa / (sum w_k^2 / m_k)`` throws it the same way. Contact
    against pinned (prescribed) cloth is a conflict of the scene: such an entry is left alone
    and reported (the response's stats), not forced."""
    free = float(0.0)
    total = float(0.0)
    for j in range(4):
        v = vid[j]
        if v >= 0:
            w2 = w[j] * w[j]
            total = total + w2
            if inv_mass[v] > 0.0:
                free = free + w2
    return free < PIN_SHARE * total


@wp.func
def side_normal_velocities(vid: wp.vec4i, w: wp.vec4, n: wp.vec3, vel: wp.array(dtype=wp.vec3)):
    """An entry's two sides' normal velocities: the mean of ``v . n`` over its vertices of
    positive weight and over those of negative weight, weighted ``|w_k|`` (a vertex and the
    point of the triangle under it, the points of two edges); 0 for a side with none."""
    sp = float(0.0)
    ap = float(0.0)
    sm = float(0.0)
    am = float(0.0)
    for k in range(4):
        i = vid[k]
        if i >= 0:
            if w[k] > 0.0:
                sp += w[k] * wp.dot(vel[i], n)
                ap += w[k]
            elif w[k] < 0.0:
                sm -= w[k] * wp.dot(vel[i], n)
                am -= w[k]
    if ap > 0.0:
        sp = sp / ap
    if am > 0.0:
        sm = sm / am
    return sp, sm


@wp.kernel
def jacobi_project_kernel(rec: ContactRecord, first: int, x: wp.array(dtype=wp.vec3),
                          inv_mass: wp.array(dtype=float), acc: wp.array(dtype=wp.vec3),
                          cnt: wp.array(dtype=int), violated: wp.array(dtype=int),
                          tol: float, num_threads: int, moved: wp.array(dtype=wp.vec3),
                          x_start: wp.array(dtype=wp.vec3), vel: wp.array(dtype=wp.vec3),
                          frame: wp.array(dtype=float)):
    """One Jacobi round: each violated entry's correction, shared by mass and weight (the
    number of entries violated by more than ``tol`` is added to ``violated[0]``; an entry
    `pin_held` is left alone and, if ``violated`` has a second slot, sets ``violated[1]``). With a
    ``moved`` array (obstacle features), also how far the entry's plane moved along its normal
    in the step, ``(offset - n . ref) n``, summed per vertex like the correction. With an
    ``x_start`` array (inside a position-based solver's iterations), an entry that started
    inside (``g(x_start) < 0``) is held where it started, not pushed out: the solver's velocity
    update would make that push a separation speed (a sheet starting on a box's face left at
    5.6 m/s); the response after the step, whose velocity rule is inelastic, takes it out.
    With velocities ``vel`` (self-contacts: the cloth's own layers), ``frame`` keeps for each
    corrected vertex the largest velocity of its entries' other sides (`side_normal_velocities`)
    along its correction from that entry, the frame of `self_collision.layer_apply`'s
    velocity rule."""
    t = wp.tid()
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    for e in range(first + t, count, num_threads):
        vid = rec.vertex[e]
        w = rec.weight[e]
        n = rec.normal[e]
        g, den = entry_gap(rec, e, x, inv_mass)
        if x_start.shape[0] > 0:
            g0, den0 = entry_gap(rec, e, x_start, inv_mass)
            g = g - wp.min(g0, 0.0)
        if g < 0.0 and den > 0.0 and pin_held(vid, w, inv_mass):
            # the entry's point is (nearly) a pinned vertex's: not projected (see `pin_held`),
            # flagged in ``violated[1]``
            if g < -tol and violated.shape[0] > 1:
                violated[1] = 1
        elif g < 0.0 and den > 0.0:
            if g < -tol:
                wp.atomic_add(violated, 0, 1)
            lam = -g / den
            shift = wp.vec3(0.0)
            if moved.shape[0] > 0:
                shift = (rec.offset[e] - wp.dot(n, rec.ref[e])) * n
            layers = vel.shape[0] > 0
            vp = float(0.0)
            vm = float(0.0)
            if layers:
                vp, vm = side_normal_velocities(vid, w, n, vel)
            for j in range(4):
                v = vid[j]
                if v >= 0 and inv_mass[v] > 0.0:
                    wp.atomic_add(acc, v, (lam * w[j] * inv_mass[v]) * n)
                    wp.atomic_add(cnt, v, 1)
                    if moved.shape[0] > 0:
                        wp.atomic_add(moved, v, shift)
                    # the other side's velocity along this entry's push on the vertex
                    # (``lam > 0``: along ``n`` for a positive weight, against it else)
                    if layers and w[j] > 0.0:
                        wp.atomic_max(frame, v, vm)
                    elif layers and w[j] < 0.0:
                        wp.atomic_max(frame, v, -vp)


@wp.func
def inelastic_velocity(v: wp.vec3, d: wp.vec3, ws: wp.vec3):
    """The velocity of a vertex corrected by ``d``: it loses the part that approached along
    ``d`` (relative to a surface moving at ``ws``) and gains nothing (`inelastic_apply_kernel`;
    the area limit's blend too, `limits.limit_apply_kernel`)."""
    l = wp.length(d)
    if l > 0.0:
        u = d / l
        a = wp.dot(v - ws, u)
        if a < 0.0:
            return v - a * u
    return v


@wp.func
def inelastic_apply_rel(i: int, x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
                        acc: wp.array(dtype=wp.vec3), cnt: wp.array(dtype=int), ws: wp.vec3):
    """`inelastic_apply_kernel` for vertex ``i``, the approach taken relative to a surface
    moving at ``ws``."""
    c = cnt[i]
    if c > 0:
        d = acc[i] / float(c)
        x[i] = x[i] + d
        v[i] = inelastic_velocity(v[i], d, ws)
        acc[i] = wp.vec3(0.0)
        cnt[i] = 0


@wp.kernel
def inelastic_apply_kernel(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
                           acc: wp.array(dtype=wp.vec3), cnt: wp.array(dtype=int),
                           moved: wp.array(dtype=wp.vec3), inv_dt: float):
    """``x += d`` (``d = acc / cnt``, the Jacobi average) and the velocity loses the component
    that approached along ``d``: ``v += max(-v . d^, 0) d^`` (inelastic); clears the
    accumulators. For a resting contact over one step this is ``v += d / dt`` (the step's fall
    is both the approach and the correction). Where the correction is larger than the
    approach (a pair already closer than the thickness, or a path that entered the thickness
    and was leaving again at the end of a span of steps, `SelfCollision.plan`), ``v += d /
    dt`` made a separation speed out of the overlap: measured, a 1 mm correction over one
    step kicked the folded sheet to 5 m/s; and cloth edges resting on a mesh's sharp features
    (`FeatureContact.respond`) gained energy from a static obstacle (the ``mesh`` scene at
    16 x 16 cells: up to 5.4e-4 J in a frame under explicit Euler, 3e-2 J under projective
    dynamics; none with this rule). With ``moved`` (a moving obstacle's features: how far the
    entries' planes moved, summed like ``acc``), the approach is measured relative to the
    surface's velocity ``moved / (cnt dt)``: against the absolute velocity, a torus sliding
    under a coarse sheet pushed its edges out every step without taking the approach out, and
    the sheet gained up to 5e-4 J a frame in the torus's frame (implicit Euler, 16 x 16)."""
    i = wp.tid()
    ws = wp.vec3(0.0)
    if moved.shape[0] > 0:
        c = cnt[i]
        if c > 0:
            ws = moved[i] * (inv_dt / float(c))
        moved[i] = wp.vec3(0.0)
    inelastic_apply_rel(i, x, v, acc, cnt, ws)


@wp.kernel
def friction_kernel(rec: ContactRecord, x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
                    inv_mass: wp.array(dtype=float), poses: wp.array(dtype=wp.transform),
                    dt: float, slack: float, pressed: wp.array(dtype=wp.vec3),
                    acc: wp.array(dtype=wp.vec3), cnt: wp.array(dtype=int), num_threads: int):
    """Coulomb friction of the entries in contact (gap at most ``slack``, friction ``mu > 0``,
    not `pin_held`), before the response's rounds (Bridson et al. 2002, as the vertex
    contacts' `response.impulse`): the entry's point's velocity relative to the obstacle's
    surface there, ``v_r = sum_j w_j v_j - W v_s`` (``W = sum_j w_j``; ``v_s`` the velocity the
    obstacle's motion over the step gives that point, from its poses: a spinning sphere's
    surface), loses its tangential part ``v_T`` up to ``mu dv_N`` (all of it: static). The
    normal impulse ``dv_N`` (a velocity of the point) is the larger of the approach the
    response's rounds take out (``-v_r . n``: explicit Euler, whose step lets the point fall
    into the feature) and what contact pushed the point by in the step, ``sum_j w_j n .
    pressed_j`` (PBD's projections inside its iterations, `project_positions`; implicit
    Euler's and projective dynamics' penalties at the end of their solve, bounded by the load,
    `contact_coupling.feature_press_kernel`): a point resting there, held by the solve,
    approaches no more, though the cloth's weight and tension press it on. The change
    ``delta`` of the point is shared like the response's correction (``w_j / m_j / sum_k w_k^2
    / m_k``, so ``sum_j w_j dv_j = delta``), Jacobi-averaged per vertex by
    `friction_apply_kernel`, which with ``position`` (`FeatureContact.friction`) also moves the
    vertex by ``dv dt`` (what that velocity moved it in the step: a sticking point does not
    creep)."""
    t = wp.tid()
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    for e in range(t, count, num_threads):
        mu = rec.friction[e]
        if mu <= 0.0:
            continue
        vid = rec.vertex[e]
        w = rec.weight[e]
        g, den = entry_gap(rec, e, x, inv_mass)
        if g > slack or den <= 0.0:
            continue
        if pin_held(vid, w, inv_mass):
            continue
        n = rec.normal[e]
        total = float(0.0)
        c = wp.vec3(0.0)
        vc = wp.vec3(0.0)
        press = float(0.0)
        for j in range(4):
            k = vid[j]
            if k >= 0:
                total = total + w[j]
                c = c + w[j] * x[k]
                vc = vc + w[j] * v[k]
                press = press + w[j] * wp.dot(n, pressed[k])
        vs = wp.vec3(0.0)
        src = rec.source[e]
        if src >= 0 and wp.abs(total) > 1.0e-6:
            pc = c / total  # the cloth point, carried back through the obstacle's motion
            local = wp.transform_point(poses[5 * src + 3], pc)
            p0 = wp.transform_point(poses[5 * src + 0], local)
            vs = (pc - p0) / dt
        vr = vc - total * vs
        vn = wp.dot(vr, n)
        vt = vr - vn * n
        lt = wp.length(vt)
        if lt <= 0.0:
            continue
        dvn = wp.max(-vn, press)
        scale = wp.min(1.0, mu * dvn / lt)
        delta = -scale * vt
        for j in range(4):
            k = vid[j]
            if k >= 0 and inv_mass[k] > 0.0:
                wp.atomic_add(acc, k, (w[j] * inv_mass[k] / den) * delta)
                wp.atomic_add(cnt, k, 1)


@wp.kernel
def friction_apply_kernel(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
                          acc: wp.array(dtype=wp.vec3), cnt: wp.array(dtype=int), dt: float,
                          shift: float, pressed: wp.array(dtype=wp.vec3)):
    """``v += dv``, ``x += dv dt`` (``dv = acc / cnt``, the Jacobi average of `friction_kernel`'s
    changes); clears the accumulators and ``pressed``."""
    i = wp.tid()
    pressed[i] = wp.vec3(0.0)
    c = cnt[i]
    if c > 0:
        d = acc[i] / float(c)
        v[i] = v[i] + d
        x[i] = x[i] + d * (dt * shift)
        acc[i] = wp.vec3(0.0)
        cnt[i] = 0


@wp.kernel
def path_left_box_kernel(x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
                         lo: wp.array(dtype=wp.vec3), hi: wp.array(dtype=wp.vec3),
                         stale: wp.array(dtype=int)):
    """``stale[0] = 1`` if vertex ``i``'s path ``x0 -> x1`` leaves its box (a box holds a
    straight path when it holds both ends)."""
    i = wp.tid()
    a = x0[i]
    b = x1[i]
    l = lo[i]
    h = hi[i]
    for c in range(3):
        if wp.min(a[c], b[c]) < l[c] or wp.max(a[c], b[c]) > h[c]:
            stale[0] = 1


@wp.kernel
def vertex_box_kernel(x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3), slack: float,
                      lo: wp.array(dtype=wp.vec3), hi: wp.array(dtype=wp.vec3),
                      stale: wp.array(dtype=int)):
    """Vertex ``i``'s box: its path's, widened by ``slack``; clears ``stale``."""
    i = wp.tid()
    lo[i] = wp.min(x0[i], x1[i]) - wp.vec3(slack)
    hi[i] = wp.max(x0[i], x1[i]) + wp.vec3(slack)
    if i == 0:
        stale[0] = 0


@wp.kernel
def position_apply_kernel(x: wp.array(dtype=wp.vec3), acc: wp.array(dtype=wp.vec3),
                          cnt: wp.array(dtype=int), pressed: wp.array(dtype=wp.vec3),
                          inv_dt: float):
    """``x += acc / cnt`` (the Jacobi average) and the accumulators cleared; no velocity. With a
    ``pressed`` array, the move over ``dt`` is added to it (the velocity the projections gave
    the vertex in the step: friction's normal impulse, `FeatureContact.friction`)."""
    i = wp.tid()
    c = cnt[i]
    if c > 0:
        d = acc[i] / float(c)
        x[i] = x[i] + d
        if pressed.shape[0] > 0:
            pressed[i] = pressed[i] + d * inv_dt
        acc[i] = wp.vec3(0.0)
        cnt[i] = 0


@wp.kernel
def rounds_begin_kernel(flags: wp.array(dtype=int), rec: ContactRecord, first: int,
                        counters: wp.array(dtype=int)):
    """A response starts: run (``flags[0]``) if the record has an entry from ``first`` on, no
    round taken (``flags[1]``); with none, no round (``counters[0]``, the last response's
    rounds, 0)."""
    flags[1] = 0
    if wp.min(rec.count[0], rec.vertex.shape[0]) > first:
        flags[0] = 1
    else:
        flags[0] = 0
        counters[0] = 0


@wp.kernel
def round_done_kernel(violated: wp.array(dtype=int), flags: wp.array(dtype=int),
                      min_rounds: int, max_rounds: int, counters: wp.array(dtype=int)):
    """After a round: another while it found a violated entry (or fewer than ``min_rounds``
    ran) and fewer than ``max_rounds`` ran; ``violated`` cleared. ``counters``: [0] rounds of
    the last response, [1] += rounds, [2] += 1 for a response that stopped at ``max_rounds``
    still violated, [3] += 1 for a response that left a `pin_held` entry violated."""
    k = flags[1] + 1
    flags[1] = k
    more = violated[0] > 0 or k < min_rounds
    if more and k >= max_rounds:
        more = False
        if violated[0] > 0:
            counters[2] = counters[2] + 1
    if more:
        flags[0] = 1
    else:
        flags[0] = 0
        counters[0] = k
        counters[1] = counters[1] + k
        if violated[1] > 0:
            counters[3] = counters[3] + 1
        violated[1] = 0
    violated[0] = 0


class FeatureContact:
    """The sharp features of a stage's mesh obstacles against the cloth's edges and triangles
    (module docstring). ``active`` is False (and nothing is allocated) when no mesh has one.

    Args:
        model: the `ClothModel`.
        contact: the stage's `ObstacleContact` (its meshes, poses and thickness), or None
            (inactive).
        rounds: Jacobi rounds `respond` runs at least (then on while violated, up to
            `MAX_ROUNDS`).
    """

    def __init__(self, model, contact, rounds: int = 4, stretch: float = 1.0):
        self.model = model
        self.device = d = model.device
        self.contact = contact
        self.rounds = int(rounds)
        #: the cloth's edges are taken this many times their rest length (and `STRETCH_MARGIN`
        #: more) in choosing the sharp features (`CollisionStage.cloth_stretched` raises it)
        self.stretch = float(stretch)
        #: the longest rest edge of the cloth (0: no feature to choose again)
        self.rest_max = 0.0
        self.active = False
        self.num_vertices = self.num_edges = 0
        if contact is None:
            return
        # meshes and boxes (a box's edges and corners are as sharp as a mesh's)
        shapes = [(a, box_mesh(ob.half_extents), np.asarray(ob.half_extents, dtype=np.float64))
                  for a, ob in enumerate(contact.analytic) if ob.kind == KIND_BOX]
        n_analytic = len(contact.analytic)
        shapes += [(n_analytic + m, (ob.vertices, ob.triangles), np.zeros(3))
                   for m, ob in enumerate(contact.meshes)]
        spheres = [(a, ob.radius) for a, ob in enumerate(contact.analytic)
                   if ob.kind == KIND_SPHERE]
        if not shapes and not spheres:
            return
        self.thickness = h = contact.thickness
        rest = _edge_lengths(model)
        # the longest cloth edge, stretched by STRETCH_MARGIN: ridges it cannot cut into by
        # more than half the thickness are skipped
        self.rest_max = float(rest.max()) if len(rest) else 0.0
        self.length = STRETCH_MARGIN * self.stretch * self.rest_max
        local, pose_of, src, fedges, fnormals, halves, vhalves, vnormals = ([] for _ in range(8))
        radii = []
        #: record room for the sphere centres' entries (`capacity`)
        self._sphere_room = 0
        # a sphere that a cloth triangle (its rest chord ``L0``, `cloth_chord`: for a grid the
        # diagonal) can cut into by more than half the thickness (``L0^2 / (8 R) - h``, as for a
        # mesh's curved part, but without the stretch margin; `sphere_needs_features`): its
        # centre is a sharp vertex with the radius added to the separation
        # (`vertex_triangle_kernel`), so the cloth triangles keep the thickness from its
        # surface, not only the vertices (a sphere it dips into by less has the vertex
        # contact's radius padded instead: `obstacles.sphere_contact_pad`). Measured: an 8 x 8
        # sheet (1 m) dropped on a 0.1 m sphere, its triangles 17 / 16 / 43 / 38 mm inside the
        # sphere (explicit / implicit / PBD / PD) with vertex contact only; none closer than
        # 4.95 mm with these entries. The entries lift the triangle's vertices off their own
        # contacts: their friction (`friction`) carries the sheet then. Before it had any, with
        # the stretch margin, the 10 x 10 sheet (0.8 m) on a 0.3 m sphere that spins (a rest
        # diagonal cuts 0.3 mm into it) was no longer carried round under PBD and PD
        L0 = contact.chord * self.stretch
        areas = model.mesh.triangle_areas()
        #: the sphere centres kept as sharp vertices: the first ones (`respond_spheres_again`)
        self.num_spheres = 0
        for a, radius in spheres:
            if not sphere_needs_features(contact.analytic[a], L0, h):
                continue
            local.append(np.zeros((1, 3)))
            pose_of.append(np.full(1, a))
            src.append(np.full(1, a))
            vhalves.append(np.zeros((1, 3)))
            vnormals.append(np.zeros((1, 3)))
            radii.append(np.full(1, radius))
            # the cloth triangles that fit around it (twice over: layers), at least 64
            smallest = float(areas.min()) if len(areas) else 1.0
            cover = 4.0 * math.pi * (radius + 2.0 * h) ** 2 / max(smallest, 1e-12)
            self._sphere_room += int(min(len(areas), max(64, 2.0 * cover)))
            self.num_spheres += 1
        base = len(local)
        for k, (verts, tris), half in shapes:
            e, vs = sharp_features(verts, tris, self.length, self.thickness,
                                   chord=max(self.length, STRETCH_MARGIN * L0),
                                   probe=self.length / STRETCH_MARGIN, device=d)
            if len(vs) == 0:
                continue
            remap = -np.ones(len(verts), dtype=np.int64)
            remap[vs] = np.arange(len(vs)) + base
            local.append(np.asarray(verts, dtype=np.float64)[vs])
            pose_of.append(np.full(len(vs), k))
            src.append(np.full(len(vs), k))
            fedges.append(remap[e])
            fnormals.append(edge_face_normals(verts, tris, e))
            halves.append(np.tile(half, (len(e), 1)))
            vhalves.append(np.tile(half, (len(vs), 1)))
            vnormals.append(vertex_normals(verts, tris)[vs])
            radii.append(np.zeros(len(vs)))
            base += len(vs)
        self.active = base > 0
        self.num_vertices = base
        self.num_edges = int(sum(len(e) for e in fedges))
        if not self.active:
            return
        self.broad = b = ClothBroadPhase(model)
        # fat boxes: each vertex's box is its path's, widened by FAT_SLACK thicknesses, and the
        # BVHs are refitted only once a path leaves its box (`detect`)
        n = model.num_vertices
        x = wp.array(np.asarray(model.mesh.vertices, dtype=np.float32), dtype=wp.vec3, device=d)
        self._vlo, self._vhi = wp.clone(x), wp.clone(x)
        self._stale = wp.ones(1, dtype=int, device=d)
        self._pad = 0.0  # the gap the boxes were widened by (the largest asked for)
        b.update(x, x, 0.0)  # builds the BVHs (allocations: not in a recorded step)
        self.local = wp.array(_stack(local, (-1, 3), np.float64), dtype=wp.vec3, device=d)
        self.pose_of = wp.array(_stack(pose_of, (-1,), np.int32), dtype=int, device=d)
        self.source = wp.array(_stack(src, (-1,), np.int32), dtype=int, device=d)
        self.fedges = wp.array(_stack(fedges, (-1, 2), np.int32), dtype=wp.int32, ndim=2,
                               device=d)
        #: a box's half extents for each of its sharp edges (zeros for a mesh's)
        self.box_half = wp.array(_stack(halves, (-1, 3), np.float32), dtype=wp.vec3, device=d)
        #: each sharp vertex's radius: a sphere's for its centre, 0 for the others
        self.vradius = wp.array(_stack(radii, (-1,), np.float32), dtype=float, device=d)
        #: ... and for each of its sharp vertices (its corners)
        self.vbox_half = wp.array(_stack(vhalves, (-1, 3), np.float32), dtype=wp.vec3, device=d)
        #: each sharp vertex's outward normal in its obstacle's frame (`vertex_normals`)
        self.vnormals = wp.array(_stack(vnormals, (-1, 3), np.float32), dtype=wp.vec3, device=d)
        #: each sharp edge's two face normals in its obstacle's frame (zeros for a rim)
        self.face_normals = wp.array(_stack(fnormals, (-1, 2, 3), np.float32), dtype=wp.vec3,
                                     ndim=2, device=d)
        self.p0 = wp.zeros(base, dtype=wp.vec3, device=d)
        self.p1 = wp.zeros(base, dtype=wp.vec3, device=d)
        ordered = contact.analytic + contact.meshes
        fr = np.array([(ob.friction if ob.friction is not None else contact.friction)
                       for ob in ordered], dtype=np.float64)
        # float32 on the device: a coefficient past its range (friction 1e300 is accepted, and
        # sticks like any large one) is its largest value, not inf with a cast warning
        self.mu_t = wp.array(np.minimum(fr, 3.0e38).astype(np.float32), dtype=float, device=d)
        #: whether any obstacle with features has friction (`friction` costs nothing if not)
        self.has_friction = bool((fr[_stack(src, (-1,), np.int64)] > 0.0).any())
        n = model.num_vertices
        self.acc = wp.zeros(n, dtype=wp.vec3, device=d)
        self.cnt = wp.zeros(n, dtype=int, device=d)
        #: the velocity the solve's contact terms (`contact_coupling.feature_press_kernel`) or
        #: the in-iteration projections (`project_positions`) gave each vertex along the
        #: features' normals in this step: `friction`'s normal impulse (cleared there)
        self.pressed = wp.zeros(n if self.has_friction else 0, dtype=wp.vec3, device=d)
        # how far the entries' planes moved, per vertex (`inelastic_apply_kernel`): only when an
        # obstacle moves
        self.moved = wp.zeros(n if getattr(contact, "moving", False) else 0, dtype=wp.vec3,
                              device=d)
        self._no_moved = wp.zeros(0, dtype=wp.vec3, device=d)  # also: no x_start
        self._no_float = wp.zeros(0, dtype=float, device=d)
        # the in-iteration projection's count of violated entries (one slot: pinned entries
        # are not flagged there), not read
        self._scratch = wp.zeros(1, dtype=int, device=d)
        self.violated = wp.zeros(2, dtype=int, device=d)  # [violated entries, a pin_held one]
        self.threads = record_threads(n, d)
        self._flags = wp.zeros(2, dtype=int, device=d)
        #: [rounds of the last response, rounds in all, responses left violated, responses
        #: that left a `pin_held` entry]
        self.counters = wp.zeros(4, dtype=int, device=d)
        self._reported = 0
        self._reported_pinned = 0

    @property
    def capacity(self) -> int:
        """Record entries this source may need: 8 per sharp vertex and edge (at least 256),
        and for each sphere centre the cloth triangles that fit twice round it."""
        if not self.active:
            return 0
        return max(256, 8 * (self.num_vertices + self.num_edges)) + self._sphere_room

    def detect(self, x0, x1, margin: float, record) -> None:
        """Entries of the sharp features against the cloth on the paths ``x0 -> x1`` appended
        to ``record`` (the obstacle poses must be those of the step: `ObstacleContact._poses`)."""
        if not self.active:
            return
        d = self.device
        gap = self.thickness + margin
        launch(feature_world_kernel, self.num_vertices,
               [self.local, self.pose_of, self.contact.poses, self.p0, self.p1], device=d)
        b = self.broad
        self._boxes(x0, x1, gap)
        launch(vertex_triangle_kernel, self.num_vertices,
               [b.tri_bvh.id, self.p0, self.p1, self.source, x0, x1, b.tris, gap,
                self.thickness, self.mu_t, record, self.vbox_half, self.pose_of,
                self.contact.poses, self.vnormals, self.vradius], device=d)
        if self.num_edges:
            launch(edge_edge_kernel, self.num_edges,
                   [b.edge_bvh.id, self.p0, self.p1, self.fedges, self.source, x0, x1,
                    b.edges, gap, self.thickness, self.mu_t, record, self.face_normals,
                    self.box_half, self.pose_of, self.contact.poses], device=d)

    def _boxes(self, x0, x1, gap: float) -> None:
        """The BVHs' boxes hold every path ``x0 -> x1`` widened by ``gap`` (refitted on the
        device when one left its box)."""
        if gap > self._pad:  # a wider gap than the boxes have (host floats: the same each step)
            self._pad = gap
            self._stale.fill_(1)
        launch(path_left_box_kernel, len(x0), [x0, x1, self._vlo, self._vhi, self._stale],
               device=self.device)
        wp.capture_if(self._stale, self._refit, x0=x0, x1=x1)

    def respond_spheres_again(self, state, x_start, dt: float, record) -> None:
        """The spheres' entries found again on the corrected paths ``x_start -> state.x`` and
        responded to (`respond`; ``record`` is cleared first), after a first `detect` and
        `respond`. A sphere's entry holds its triangle's point nearest the centre at
        detection; the response's corrections, averaged per vertex, turn the triangle, and its
        nearest point moves off the one held: measured, a 16 x 16 sheet (1 m) with quadratic
        bending landing under implicit Euler on a 0.3 m sphere at a 0.5 mm thickness ended a
        step with a triangle's interior 0.36 mm from the sphere, its entry's point at the
        thickness. A sphere centre is one query (the first `num_spheres` sharp vertices),
        so this costs little; a mesh's or a box's sharp vertices keep their one pass (a second
        full detection took the thin-parts scene under explicit Euler from 676 to 1,217 ms a
        frame)."""
        if not self.num_spheres:
            return
        record.count.zero_()
        b = self.broad
        self._boxes(x_start, state.x, self.thickness)  # the response moved the paths' ends
        launch(vertex_triangle_kernel, self.num_spheres,
               [b.tri_bvh.id, self.p0, self.p1, self.source, x_start, state.x, b.tris,
                self.thickness, self.thickness, self.mu_t, record, self.vbox_half,
                self.pose_of, self.contact.poses, self.vnormals, self.vradius],
               device=self.device)
        self.respond(state, dt, record)

    def _refit(self, x0, x1):
        """New vertex boxes around the paths ``x0 -> x1`` (widened by `FAT_SLACK` thicknesses),
        the elements' boxes from them (widened by the gap) and the BVHs refitted."""
        b, d = self.broad, self.device
        launch(vertex_box_kernel, len(x0),
               [x0, x1, FAT_SLACK * self.thickness, self._vlo, self._vhi, self._stale], device=d)
        # an element's box holds its vertices' boxes (the swept boxes of "paths" from each
        # vertex box's low corner to its high one), widened by the gap
        launch(cloth_bounds_kernel, b.num_tris + b.num_edges,
               [self._vlo, self._vhi, b.tris, b.edges, b.num_tris, self._pad, b.lowers, b.uppers,
                b.elowers, b.euppers], device=d)
        b.tri_bvh.refit()
        b.edge_bvh.refit()

    def project_positions(self, x, x_start, record, first: int = 0, dt: float = 0.0) -> None:
        """One Jacobi round of the record's entries from ``first`` on, positions only (inside a
        position-based solver's iterations, whose velocity update follows the positions); an
        entry that started inside is held where it started (`jacobi_project_kernel` with
        ``x_start``)."""
        if not self.active:
            return
        d, m = self.device, self.model
        launch(jacobi_project_kernel, self.threads,
               [record, first, x, m.inv_mass, self.acc, self.cnt, self._scratch,
                RESOLVE_TOL * self.thickness, self.threads, self._no_moved, x_start,
                self._no_moved, self._no_float], device=d)
        press = self.pressed if self.has_friction and dt > 0.0 else self._no_moved
        launch(position_apply_kernel, m.num_vertices,
               [x, self.acc, self.cnt, press, 1.0 / dt if dt > 0.0 else 0.0], device=d)

    def respond(self, state, dt: float, record, first: int = 0) -> None:
        """Jacobi rounds over the record's entries from ``first`` on: at least `rounds`, then
        on while one is violated by more than `RESOLVE_TOL` thicknesses, up to `MAX_ROUNDS`
        (`wp.capture_while` on a device flag: a conditional node in a recorded graph)."""
        if not self.active:
            return
        self.violated.zero_()
        launch(rounds_begin_kernel, 1, [self._flags, record, first, self.counters],
               device=self.device)
        wp.capture_while(self._flags[0:1], self._round, state=state, dt=dt, record=record,
                         first=first)

    def friction(self, state, dt: float, record, slack: float, position: bool = False) -> None:
        """Coulomb friction of the record's entries within ``slack`` of their planes
        (`friction_kernel`, then `friction_apply_kernel`), before `respond`. ``position``: also
        move the vertices back by the velocity taken out times dt, so a sticking point does not
        creep (the solver's choice, `Solver.friction_by_position`: explicit Euler)."""
        if not self.active or not self.has_friction:
            return
        d, m = self.device, self.model
        launch(friction_kernel, self.threads,
               [record, state.x, state.v, m.inv_mass, self.contact.poses,
                dt, slack, self.pressed, self.acc, self.cnt, self.threads],
               device=d)
        launch(friction_apply_kernel, m.num_vertices,
               [state.x, state.v, self.acc, self.cnt, dt, 1.0 if position else 0.0,
                self.pressed], device=d)

    def _round(self, state, dt, record, first):
        d, m = self.device, self.model
        launch(jacobi_project_kernel, self.threads,
               [record, first, state.x, m.inv_mass, self.acc, self.cnt, self.violated,
                RESOLVE_TOL * self.thickness, self.threads, self.moved, self._no_moved,
                self._no_moved, self._no_float], device=d)
        launch(inelastic_apply_kernel, m.num_vertices,
               [state.x, state.v, self.acc, self.cnt, self.moved, 1.0 / dt], device=d)
        launch(round_done_kernel, 1,
               [self.violated, self._flags, self.rounds, MAX_ROUNDS, self.counters],
               device=d)

    @property
    def stats(self) -> dict:
        """``feature_rounds`` (the last response), ``feature_rounds_total``,
        ``feature_unresolved_total`` (responses that stopped at `MAX_ROUNDS` with an entry
        still violated), ``feature_pinned_total`` (responses that left an entry `pin_held`:
        a sharp feature pressed on the cloth at a pinned vertex): host reads."""
        if not self.active:
            return {}
        c = self.counters.numpy()
        return {"feature_rounds": int(c[0]), "feature_rounds_total": int(c[1]),
                "feature_unresolved_total": int(c[2]), "feature_pinned_total": int(c[3])}

    def frame_end(self) -> list:
        """Responses left violated, and responses that left a `pin_held` entry, since the last
        call, as ``(message, False)`` (host read)."""
        if not self.active:
            return []
        c = self.counters.numpy()
        n, p = int(c[2]), int(c[3])
        new, self._reported = n - self._reported, n
        pinned, self._reported_pinned = p - self._reported_pinned, p
        out = []
        if new > 0:
            out.append((f"mesh features: {new} step(s) ended {MAX_ROUNDS} response rounds with a "
                        f"cloth edge or triangle still inside a sharp feature's thickness", False))
        if pinned > 0:
            out.append((f"mesh features: {pinned} step(s) pressed a sharp feature on the cloth "
                        "at a pinned vertex, which contact cannot move (left inside the "
                        "thickness: the obstacle's path crosses the pins)", False))
        return out


def _stack(parts, shape, dtype) -> np.ndarray:
    """The arrays ``parts`` stacked and reshaped to ``shape`` (-1 first), empty if none."""
    if not parts:
        return np.zeros((0,) + tuple(shape[1:]), dtype=dtype)
    return np.concatenate(parts).astype(dtype).reshape(shape)


def _edge_lengths(model):
    v = np.asarray(model.mesh.vertices, dtype=np.float64)
    e = np.asarray(model.mesh.edges)
    return np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)
