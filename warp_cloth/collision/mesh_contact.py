"""Contact kernels for triangle-mesh obstacles (`wp.Mesh` BVH queries): all mesh obstacles of a
contact in one far pass and one near pass (below). Kept apart from the analytic kernels so that a
scene without a mesh obstacle never compiles it.

Per vertex and mesh, in the mesh's frame (``p0`` at the pose of t0, ``p1`` at the pose of t1, so the
obstacle's motion during the step is part of the relative path), with contact thickness ``th``:

0. Closest point to ``p1`` within ``th + slack + |p1 - p0|`` (``wp.mesh_query_point_sign_normal``
   for closed meshes, searching the whole mesh when ``p1`` lies in its bounding box, so a vertex
   deep inside is found; ``mesh_query_point_no_sign`` for open meshes). None: the path cannot
   reach the surface, nothing to do (most vertices; a box test rejects the far ones first).
1. Continuous test, when the path is longer than the end's distance to the surface (or the end
   is inside): a ray query from ``p0`` along ``p1 - p0`` (``wp.mesh_query_ray``, ``max_t = 1``)
   finds the first triangle the path crosses. If it does (for a closed mesh: entering through the
   front side), ``p1`` is projected onto the plane ``th`` in front of the hit triangle on the side
   ``p0`` came from. No path can cross a triangle, however thin the mesh and however fast the vertex
   or the obstacle (T45).
2. Discrete test at ``p1``: if closer than ``th`` to the closest point ``c`` (or inside),
   ``p1 <- c + th n``, with ``n`` pointing from ``c`` to the outside (closed) or to the vertex's
   side (open).
3. In contact: the impulse of `warp_cloth.collision.response`.

Passes per step: ``mesh_far_kernel`` (every vertex) runs the far tests below and appends the
vertices that pass none to a list; ``mesh_near_kernel`` answers, strided over ``N / NEAR_BATCH``
threads, the listed vertices whose path lies in a static mesh's candidate ball (below) and
lists the rest for ``mesh_general_kernel``, which runs steps 0-3. (On Warp's CPU backend a kernel
initialises all its variables and by-value call arguments for every thread, so a single kernel
holding the near path cost every far vertex as much again; measured with ``warp-cloth bench
contact``.)

Distance cache (kept by ``apply``). Static mesh: each vertex keeps an anchor point ``a`` and
``gap``, a lower bound of the distance from ``a`` to the mesh (from the last query at ``a``,
searched ``margin`` beyond the reach, or from the mesh's bounding ball). While both ends of a
path lie within ``gap - reach`` of ``a`` the whole path does (a ball is convex), so no point of it
comes within the reach of the surface: the far test is two squared lengths, and nothing is
written (it is a fact about space, not about the vertex's history, so anything may move the
vertex in between). Moving mesh: ``gap`` bounds the distance of the vertex where it ended the
last step (``last``); while the step starts exactly there (and at the time the last ``apply``
ended: ``ObstacleReach.fresh``) and ``gap`` minus the length of the path in the mesh's frame
(the vertex's own motion plus the mesh's translation and rotation over the step,
`warp_cloth.collision.motion.ObstacleReach`) stays above the reach, the vertex skips the BVH
queries and keeps the lowered bound. Anything else that moved the vertex in between (a state
reset, a later correction, another mesh of this kernel) fails the ``last == x_start`` check and
the vertex is queried again. A vertex that touched a mesh last step queries without the margin
(a tighter query; it would not skip anyway).

Candidate cache (for vertices in contact, which the distance cache cannot skip): after a query
at a local point ``q`` with signed distance ``phi_q``, ``|phi_q| > r`` (``r`` =
``candidate_radius``, default half the thickness), the vertex keeps every face within
``|phi_q| + 2 r`` of ``q`` (at most `MAX_CANDIDATES`; an AABB query and exact point-triangle
distances). While both ends of a later path lie within ``r`` of ``q`` (in the mesh's frame, so
this holds for moving meshes too), (a) a face not kept is farther from the end than the face
closest to ``q`` (triangle inequality: ``> |phi_q| + 2r - r >= |phi_q| + r``), so the closest
point among the kept faces is the mesh's closest point, and (b) every point of the path is at
least ``|phi_q| - r > 0`` from the surface, so the path crosses none and keeps the sign of
``phi_q``: no ray or point query is needed. A draped vertex refreshes only when it has slid
``r``. Checked against the BVH queries step by step in ``tests/test_contact.py``. Where the
ball projects inside its closest face and every other candidate lies behind that face's plane,
the entry keeps only the plane (`PLANE`; `refresh_candidates` has the argument).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..util import launch
from .motion import ObstacleData, ObstacleReach
from .geometry import closest_point_triangle as closest_on_triangle
from .planes import ContactPlanes
from .response import contact_outcome, outcome_in_frame

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile


#: `wp.mesh_query_point_sign_normal`'s tie tolerance (relative to the mesh's average edge
#: length): faces whose closest points lie within it of the closest distance add their
#: normals to the sign's pseudo-normal. Warp's default (1e-3) also lumps faces of another part
#: of the surface whose distance is merely close, and their normals can turn the sign: on a
#: lumpy mesh (edges 5 cm), a point 60.5 mm outside, 35 um nearer one edge than another
#: region, was called inside, and the contact moved the vertex 65.5 mm through the mesh onto
#: its far side (2026-12-07). A tie at one edge or vertex differs by rounding only (about 1e-8 m
#: on meshes of metres)
SIGN_EPSILON = 1.0e-5


@wp.func(inline=False)
def inside_by_winding(mid: wp.uint64, p: wp.vec3, d: float, max_dist: float):
    """True when the point ``p`` (``d``: its distance to the surface) is inside the closed mesh
    by the generalized winding number, the majority at ``p`` and at two points ``1e-3 d``
    away: Warp's winding number gives the wrong sign at some points coplanar with a ring of
    the mesh's vertices (the bundled torus: 16 % of the points of its top plane y = 0.08, up to
    0.14 m from the surface), off any such plane the others do not. Out of line: its three
    query states are set up only when it runs (see `mesh_near`)."""
    q = wp.mesh_query_point_sign_winding_number(mid, p, max_dist)
    if not q.result:
        return False
    e = 1.0e-3 * d
    q1 = wp.mesh_query_point_sign_winding_number(mid, p + e * wp.vec3(0.5377, 0.8192, 0.1985),
                                                 max_dist)
    q2 = wp.mesh_query_point_sign_winding_number(mid, p + e * wp.vec3(-0.6843, 0.1234, 0.7187),
                                                 max_dist)
    votes = q.sign + wp.where(q1.result, q1.sign, q.sign) + wp.where(q2.result, q2.sign, q.sign)
    return votes < 0.0


@wp.func
def closest(mid: wp.uint64, closed: int, p: wp.vec3, p_from: wp.vec3, center: wp.vec3,
            half: wp.vec3, max_dist: float):
    """(found, closest point c, signed distance phi, unit normal n pointing from c to the side
    the point belongs on). Closed mesh: outside; when ``p`` is in the mesh's bounding box the
    whole mesh is searched, so a point deep inside is found too. The sign is the closest
    feature's angle-weighted normal (`SIGN_EPSILON`); an "inside" is confirmed by the winding
    number (`inside_by_winding`: rare, a cloth vertex is seldom inside) and dropped when it
    says outside, since a wrong "inside" moves the vertex through the mesh. Open mesh: the
    side of ``p``, or of ``p_from`` when ``p`` lies on the surface."""
    c = p
    phi = float(0.0)
    n = wp.vec3(0.0, 1.0, 0.0)
    if closed != 0:
        q = wp.mesh_query_point_sign_normal(mid, p, max_dist, SIGN_EPSILON)
        if not q.result:
            rel = p - center
            if wp.abs(rel[0]) <= half[0] and wp.abs(rel[1]) <= half[1] and wp.abs(rel[2]) <= half[2]:
                # in the bounding box: might be deep inside, search the whole mesh
                q = wp.mesh_query_point_sign_normal(mid, p, 2.0 * wp.length(half) + max_dist,
                                                    SIGN_EPSILON)
            if not q.result:
                return False, c, phi, n
        c = wp.mesh_eval_position(mid, q.face, q.u, q.v)
        diff = p - c
        dist = wp.length(diff)
        n = wp.mesh_eval_face_normal(mid, q.face)
        phi = dist
        inside = q.sign < 0.0
        if inside and dist > 1.0e-9:
            inside = inside_by_winding(mid, p, dist, 2.0 * wp.length(half) + dist + max_dist)
        if inside:
            phi = -dist
            if dist > 1.0e-9:
                n = -diff / dist
        elif dist > 1.0e-9:
            n = diff / dist
        return True, c, phi, n
    q = wp.mesh_query_point_no_sign(mid, p, max_dist)
    if not q.result:
        return False, c, phi, n
    c = wp.mesh_eval_position(mid, q.face, q.u, q.v)
    diff = p - c
    phi = wp.length(diff)
    if phi > 1.0e-9:
        n = diff / phi
    else:
        n = wp.mesh_eval_face_normal(mid, q.face)
        if wp.dot(p_from - c, n) < 0.0:
            n = -n
    return True, c, phi, n


#: most candidate faces a vertex keeps per mesh (more: no candidate cache for it; up to 10 faces
#: meet near a pole of the bundled sphere, and a vertex without a cache queries the BVH each step)
MAX_CANDIDATES = 16
#: `MeshCache.cand_count` of an entry whose closest point is, throughout its ball, the projection
#: onto one face's plane (stored as a point and the unit normal, in place of the corners)
PLANE = -1
#: m; a candidate face counts as behind the plane when no corner is more than this in front
#: (float32 rounding of corners transformed to the world frame)
PLANE_TOLERANCE = 1.0e-7


@wp.struct
class MeshCache:
    """Per-vertex, per-mesh caches of `mesh_vertex` (index ``i * num_meshes + k``)."""

    gap: wp.array(dtype=float)  # lower bound of a distance to the mesh: static mesh, of
    #                             `anchor`; moving mesh, of the vertex at the end of the last step
    anchor: wp.array(dtype=wp.vec3)  # static meshes: the world point `gap` bounds the distance of
    last: wp.array(dtype=wp.vec3)  # where the vertex ended the last step (NaN: moved since;
    #                                moving meshes only)
    margin: float  # how far beyond the reach a distance query looks (gap cache)
    cand_q: wp.array(dtype=wp.vec3)  # local centre q of the candidate ball
    cand_phi: wp.array(dtype=float)  # signed distance of q (|phi_q| > the ball's radius)
    cand_r2: wp.array(dtype=float)  # squared radius of the ball (`radius`, or a quarter of it
    #                                 where too many faces are near: see `refresh_candidates`)
    cand_count: wp.array(dtype=int)  # candidate faces (0: no cache; PLANE: one plane)
    cand_tris: wp.array(dtype=wp.vec3)  # 3 local corners of each candidate face, MAX_CANDIDATES
    #                                     per entry (no index lookups when they are used)
    radius: float  # m: the ball radius (0: candidate cache off)


@wp.func
def keep_gap(cache: MeshCache, ci: int, moving: int, x: wp.vec3, g: float):
    """Record ``g``, a lower bound of the distance of the world point ``x`` to the mesh (static
    mesh: with ``x`` as the anchor of the bound; moving mesh: as the vertex's bound for the next
    step, ``x`` being where it ends this one)."""
    cache.gap[ci] = g
    if moving == 0:
        cache.anchor[ci] = x


@wp.func
def face_closest(mid: wp.uint64, f: int, p: wp.vec3):
    return closest_on_triangle(wp.mesh_get_point(mid, 3 * f), wp.mesh_get_point(mid, 3 * f + 1),
                               wp.mesh_get_point(mid, 3 * f + 2), p)


@wp.func
def cached_closest(cache: MeshCache, ci: int, p: wp.vec3):
    """(closest point, signed distance, normal) of ``p`` from the candidate faces of entry ``ci``
    (valid only for ``p`` in the entry's ball: see `mesh_vertex`)."""
    cnt = cache.cand_count[ci]
    if cnt == PLANE:
        b0 = 3 * ci * MAX_CANDIDATES
        pn = cache.cand_tris[b0 + 1]
        h = wp.dot(p - cache.cand_tris[b0], pn)
        return p - h * pn, h, pn
    best = float(1.0e30)
    c = p
    for j in range(cnt):
        b = 3 * (ci * MAX_CANDIDATES + j)
        cj = closest_on_triangle(cache.cand_tris[b], cache.cand_tris[b + 1],
                                 cache.cand_tris[b + 2], p)
        d2 = wp.length_sq(p - cj)
        if d2 < best:
            best = d2
            c = cj
    dist = wp.sqrt(best)
    n = (p - c) / dist  # dist > 0: the ball holds no surface point
    if cache.cand_phi[ci] < 0.0:
        return c, -dist, -n
    return c, dist, n


@wp.func
def inside_by(u: wp.vec3, w: wp.vec3, z: wp.vec3, n: wp.vec3, q: wp.vec3, r: float):
    """True when ``q``'s projection onto the plane (normal ``n``) of triangle ``u w z`` lies at
    least ``r`` on the triangle's side of its edge ``u w``."""
    m = wp.normalize(wp.cross(n, w - u))
    if wp.dot(z - u, m) < 0.0:
        m = -m
    return wp.dot(q - u, m) >= r


@wp.func
def gather_candidates(mid: wp.uint64, ci: int, q: wp.vec3, keep: float, T: wp.transform,
                      cand_tris: wp.array(dtype=wp.vec3)):
    """Store (mapped by ``T``) the corners of every face within ``keep`` of ``q`` for entry
    ``ci``; returns (their number, or ``MAX_CANDIDATES + 1`` when there are more; the face
    closest to ``q``)."""
    lim = keep * (1.0 + 1.0e-5) + 1.0e-7  # float32 rounding of the distances below
    query = wp.mesh_query_aabb(mid, q - wp.vec3(lim), q + wp.vec3(lim))
    f = int(0)
    cnt = int(0)
    best = float(1.0e30)
    bf = int(-1)
    while wp.mesh_query_aabb_next(query, f):
        dq = wp.length(q - face_closest(mid, f, q))
        if dq <= lim:
            if cnt == MAX_CANDIDATES:
                return MAX_CANDIDATES + 1, bf
            b = 3 * (ci * MAX_CANDIDATES + cnt)
            cand_tris[b] = wp.transform_point(T, wp.mesh_get_point(mid, 3 * f))
            cand_tris[b + 1] = wp.transform_point(T, wp.mesh_get_point(mid, 3 * f + 1))
            cand_tris[b + 2] = wp.transform_point(T, wp.mesh_get_point(mid, 3 * f + 2))
            if dq < best:
                best = dq
                bf = f
            cnt += 1
    return cnt, bf


@wp.func(inline=False)
def refresh_candidates(mid: wp.uint64, closed: int, r: float, ci: int, q: wp.vec3,
                       center: wp.vec3, half: wp.vec3, max_dist: float, T: wp.transform,
                       cand_q: wp.array(dtype=wp.vec3), cand_phi: wp.array(dtype=float),
                       cand_count: wp.array(dtype=int), cand_tris: wp.array(dtype=wp.vec3),
                       cand_r2: wp.array(dtype=float)):
    """New candidate ball at ``q``: its exact signed distance by a BVH query, then every face
    within ``|phi_q| + 2 radius`` of ``q`` (an AABB query and exact triangle distances), stored
    mapped by the rigid ``T`` (a static mesh's pose: its cache lives in the world frame; identity
    for a moving mesh, whose cache stays in its own frame). No cache when ``|phi_q| <= radius``
    (the ball would reach the surface) or when there are more than `MAX_CANDIDATES` faces, even
    in a ball of a quarter of the radius (tried when the first has too many).

    One plane (`PLANE`) instead of the faces when, for every point ``p`` of the ball, the closest
    point is ``p``'s projection onto the plane of the face ``F`` closest to ``q``: ``q`` is
    outside (``phi_q > radius``, so the whole ball is in front of that plane), the ball projects
    inside ``F`` (each edge at least ``radius`` from ``q``'s projection: the closest point of
    ``F`` is the projection; failing that, the same with a quarter of the radius, and the ball
    shrinks to it: the faces kept for the radius cover the smaller ball too), and every other
    candidate lies behind the plane (then a segment
    from ``p`` to any of its points crosses the plane: it is no closer than the plane). Most
    vertices resting on a locally convex surface."""
    cand_count[ci] = 0
    found, c, phi, n = closest(mid, closed, q, q, center, half, max_dist)
    if not found or wp.abs(phi) <= r:
        return
    cnt, bf = gather_candidates(mid, ci, q, wp.abs(phi) + 2.0 * r, T, cand_tris)
    if cnt > MAX_CANDIDATES:  # many faces meet nearby (a pole, a fan): a smaller ball
        r = 0.25 * r
        cnt, bf = gather_candidates(mid, ci, q, wp.abs(phi) + 2.0 * r, T, cand_tris)
        if cnt > MAX_CANDIDATES:
            return  # still too many: no cache (count stays 0)
    cand_q[ci] = wp.transform_point(T, q)
    cand_phi[ci] = phi
    cand_r2[ci] = r * r
    if phi > r and bf >= 0:
        a = wp.mesh_get_point(mid, 3 * bf)
        b1 = wp.mesh_get_point(mid, 3 * bf + 1)
        c1 = wp.mesh_get_point(mid, 3 * bf + 2)
        nf = wp.normalize(wp.cross(b1 - a, c1 - a))
        if wp.dot(q - a, nf) < 0.0:
            nf = -nf
        # the ball's projection inside F: with the radius, or else with a quarter of it (a
        # smaller ball, refreshed sooner, but one plane instead of the faces: thin faces)
        rp = r
        plane = inside_by(a, b1, c1, nf, q, rp) and inside_by(b1, c1, a, nf, q, rp) and inside_by(
            c1, a, b1, nf, q, rp)
        if not plane:
            rp = 0.25 * r
            plane = inside_by(a, b1, c1, nf, q, rp) and inside_by(b1, c1, a, nf, q, rp) and (
                inside_by(c1, a, b1, nf, q, rp))
        if plane:
            aw = wp.transform_point(T, a)
            nw = wp.transform_vector(T, nf)
            for j in range(3 * cnt):
                if wp.dot(cand_tris[3 * ci * MAX_CANDIDATES + j] - aw, nw) > PLANE_TOLERANCE:
                    plane = False
            if plane:
                b0 = 3 * ci * MAX_CANDIDATES
                cand_tris[b0] = aw
                cand_tris[b0 + 1] = nw
                cand_r2[ci] = rp * rp
                cnt = PLANE
    cand_count[ci] = cnt


@wp.func(inline=True)
def static_cached_near(
    restitution: float,
    friction: float,
    ci: int,
    i: int,
    x0: wp.vec3,
    x1: wp.vec3,
    v: wp.array(dtype=wp.vec3),
    vi: wp.vec3,
    touched: bool,
    thickness: float,
    reach: float,
    respond_velocity: int,
    caching: bool,
    cache: MeshCache,
):
    """`mesh_near` for a static mesh whose candidate ball holds the vertex's whole path (most
    vertices resting on a static mesh, most steps): the candidates are kept in the world frame,
    so no transforms, and the surface does not move. Returns (x1, vi, touched) updated. The
    mesh's coefficients come as numbers: a struct passed by value is copied at every call."""
    c, phi, n = cached_closest(cache, ci, x1)
    moved = phi < thickness
    p = x1
    if moved:
        p = c + thickness * n
    if caching:
        keep_gap(cache, ci, 0, x1, wp.where(moved, 0.0, phi))
    if moved or (respond_velocity != 0 and phi < reach):
        vr = vi
        if respond_velocity != 0 and not touched:
            vr = v[i]
        xo, vo = outcome_in_frame(x0, x1, p, n, vr, wp.vec3(0.0), n, restitution, friction,
                                  respond_velocity, thickness)
        return xo, vo, True
    return x1, vi, touched


@wp.func(inline=False)
def mesh_near(
    obstacles: wp.array(dtype=ObstacleData),
    mesh_ids: wp.array(dtype=wp.uint64),
    poses: wp.array(dtype=wp.transform),
    k: int,
    j: int,
    ci: int,
    i: int,
    x0: wp.vec3,
    x1: wp.vec3,
    v: wp.array(dtype=wp.vec3),
    vi: wp.vec3,
    touched: bool,
    dt: float,
    thickness: float,
    slack: float,
    respond_velocity: int,
    ccd: int,
    caching: bool,
    cache: MeshCache,
):
    """Steps 0-3 for vertex ``i`` and mesh ``k`` (``j``: its first pose, ``ci``: its cache
    entry) once the far tests did not reject it and `static_cached_near` does not apply.
    Returns (x1, vi, touched) updated.

    Out of line: Warp declares every variable of a function at its top and initialises it on
    entry (BVH query states included), so the common static-candidate path must not carry this
    body's variables (measured: the near pass of a cloth draped on a static mesh twice as
    costly with it inline)."""
    reach = thickness + slack
    ob = obstacles[k]
    mid = mesh_ids[k]
    p0 = wp.transform_point(poses[j + 2], x0)
    p1 = wp.transform_point(poses[j + 3], x1)
    d = p1 - p0
    # candidate cache: the whole path inside the ball of the last refresh, so the closest
    # point is on one of its faces and no surface is crossed (no ray query)
    cached = False
    if ob.moving != 0 and cache.cand_count[ci] != 0:
        q = cache.cand_q[ci]
        r2 = cache.cand_r2[ci]
        cached = wp.length_sq(p1 - q) <= r2 and wp.length_sq(p0 - q) <= r2
    c = p1
    phi = float(0.0)
    n = wp.vec3(0.0, 1.0, 0.0)
    len_d = float(0.0)
    if cached:
        c, phi, n = cached_closest(cache, ci, p1)
    else:
        if ccd != 0:
            len_d = wp.length(d)
        # cheap rejection: the path's box against the mesh's box grown by the reach
        lo = wp.min(p0, p1) - ob.center
        hi = wp.max(p0, p1) - ob.center
        ext = ob.size + wp.vec3(reach)
        if (lo[0] > ext[0] or lo[1] > ext[1] or lo[2] > ext[2]
                or hi[0] < -ext[0] or hi[1] < -ext[1] or hi[2] < -ext[2]):
            if caching:
                keep_gap(cache, ci, ob.moving, x1, reach)
            return x1, vi, touched
        # closest point to the end position, as far as the path could reach (plus the
        # cache margin, so that a miss keeps the vertex out of the queries for a while)
        radius = reach + len_d
        if caching and cache.gap[ci] > reach:
            # not touching last step: look beyond the reach so that a miss
            # keeps the vertex out of the next steps' queries; a touching vertex will most
            # likely touch again, and a tighter query visits fewer BVH nodes
            radius = radius + cache.margin
        found, c, phi, n = closest(mid, ob.closed, p1, p0, ob.center, ob.size, radius)
        if not found:
            if caching:
                keep_gap(cache, ci, ob.moving, x1, radius)
            return x1, vi, touched  # no surface within reach of the end: no crossing
    moved = False
    p_in = p1
    if not cached and ccd != 0 and (phi < 0.0 or phi < len_d):
        ray = wp.mesh_query_ray(mid, p0, d, 1.0)
        if ray.result:
            dn = wp.dot(d, ray.normal)
            if ob.closed == 0 or dn < 0.0:
                ns = ray.normal  # the side the vertex came from
                if dn > 0.0:
                    ns = -ray.normal
                h = p0 + ray.t * d
                p1 = p1 + wp.max(thickness - wp.dot(p1 - h, ns), 0.0) * ns
                moved = True
                found, c, phi, n = closest(mid, ob.closed, p1, p0, ob.center, ob.size, reach)
                if not found:
                    n = ns
                    phi = thickness
    if phi < thickness:
        p1 = c + thickness * n
        moved = True
    if caching:
        keep_gap(cache, ci, ob.moving, x1, wp.where(moved, 0.0, phi))
        if not cached and cache.radius > 0.0 and phi < reach + cache.radius:
            frame = wp.transform_identity()
            if ob.moving == 0:
                frame = poses[j + 1]
            refresh_candidates(mid, ob.closed, cache.radius, ci, p1, ob.center, ob.size,
                               reach + 3.0 * cache.radius, frame, cache.cand_q,
                               cache.cand_phi, cache.cand_count, cache.cand_tris,
                               cache.cand_r2)
    if moved or (respond_velocity != 0 and phi < reach):
        if respond_velocity != 0 and not touched:
            vi = v[i]
        touched = True
        x1, vi = contact_outcome(p0, p_in, p1, n, poses[j], poses[j + 1], vi, dt,
                                 ob.restitution, ob.friction, respond_velocity, thickness)
    return x1, vi, touched


@wp.func(inline=True)
def mesh_vertex_near(
    obstacles: wp.array(dtype=ObstacleData),
    mesh_ids: wp.array(dtype=wp.uint64),
    poses: wp.array(dtype=wp.transform),
    pose_offset: int,
    mask: int,
    i: int,
    x0: wp.vec3,
    x1: wp.vec3,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    dt: float,
    thickness: float,
    slack: float,
    respond_velocity: int,
    ccd: int,
    caching: bool,
    cache: MeshCache,
):
    """`mesh_near` for each mesh in ``mask`` (bit k: mesh k passed no far test; meshes from
    the 31st on are always tried; `static_cached_near` where it applies), then the vertex's
    writes."""
    vi = wp.vec3(0.0)
    touched = bool(False)
    num = obstacles.shape[0]
    for k in range(num):
        if k < 31 and ((mask >> k) & 1) == 0:
            continue
        ci = i * num + k
        if cache.cand_count[ci] != 0 and obstacles[k].moving == 0:
            q = cache.cand_q[ci]
            r2 = cache.cand_r2[ci]
            if wp.length_sq(x1 - q) <= r2 and wp.length_sq(x0 - q) <= r2:
                x1, vi, touched = static_cached_near(obstacles[k].restitution,
                                                     obstacles[k].friction, ci, i, x0, x1, v, vi,
                                                     touched, thickness, thickness + slack,
                                                     respond_velocity, caching, cache)
                continue
        x1, vi, touched = mesh_near(obstacles, mesh_ids, poses, k, 5 * (pose_offset + k),
                                    i * obstacles.shape[0] + k, i, x0, x1, v, vi, touched, dt,
                                    thickness, slack, respond_velocity, ccd, caching, cache)
    if touched:
        x[i] = x1
        if respond_velocity != 0:
            v[i] = vi
    if caching and touched:
        # a vertex this kernel moved may have moved towards another mesh by more than its path
        # length: no cache for it next step (NaN never compares equal; `mesh_near_kernel`
        # recorded where it ended otherwise)
        cache.last[i] = wp.vec3(wp.nan)


_KERNELS = {}


def mesh_far_kernel(moving, update=None):
    """The far pass for meshes whose ``moving`` flags are given, one per mesh (a kernel per
    tuple of flags, made on first use, so that the loop over the meshes is unrolled and keeps
    only each mesh's own test; see `warp_cloth.collision.analytic.analytic_far_kernel`)."""
    return _kernels(moving, update)[0]


def integrate_mesh_far_kernel(moving, update):
    """A solver's vertex update (``update``, see `analytic.integrate_far_kernel`) with the far
    pass of `mesh_far_kernel` in the same thread (`ObstacleContact.integrate_and_apply`)."""
    return _kernels(moving, update)[1]


def _kernels(moving, update=None):
    key = (tuple(bool(m) for m in moving), update)
    kernels = _KERNELS.get(key)
    if kernels is None:
        kernels = _KERNELS[key] = _make_far_kernels(key[0], update)
    return kernels


def _make_far_kernels(moving, update):
    num = len(moving)
    # the kernels of one tuple in one module (one compile), without the backward pass
    module = "warp_cloth.collision.mesh_contact_moving_" + "".join(str(int(m)) for m in moving)
    if update is not None:
        module += "_" + update.key
    wp.set_module_options({"enable_backward": False}, module=module)
    # which meshes move, as constants of the generated code: the unrolled loop keeps only the
    # test each mesh needs (anchor balls for static meshes; the per-step budget for moving ones)
    MOVING = wp.constant(sum(1 << k for k, m in enumerate(moving) if m))
    ANY_MOVING = wp.constant(int(any(moving)))

    @wp.func
    def far_mask(reaches: wp.array(dtype=ObstacleReach), i: int, x0: wp.vec3, x1: wp.vec3,
                 reach: float, ccd: int, caching: bool, gap: wp.array(dtype=float),
                 anchor: wp.array(dtype=wp.vec3), last: wp.array(dtype=wp.vec3)):
        """The far tests of vertex ``i`` against the ``num`` meshes (distance cache, then
        bounding ball; the cache is kept with ``caching`` only). Returns the mask of the meshes
        it passed none of (bit k: mesh k; meshes from the 31st on always)."""
        valid = bool(False)
        if ANY_MOVING != 0:
            valid = caching and last[i] == x0
        mask = int(0)
        for k in range(num):
            ci = i * num + k
            origin = reaches[k].origin  # fields read in place (no struct copy)
            if ((MOVING >> k) & 1) == 0:
                # static mesh: no surface within gap of the anchor, so a path whose both ends
                # lie within gap - reach of it (a ball is convex: so does the whole path) stays
                # out of reach. Squared lengths only, nothing written: most vertices, most steps
                h = gap[ci] - reach
                if h > 0.0:
                    a = anchor[ci]
                    h2 = h * h
                    if wp.length_sq(x1 - a) < h2 and wp.length_sq(x0 - a) < h2:
                        continue
                # far test in the world frame: outside the bounding ball by more than the
                # reach and than the path length; the end becomes the vertex's new anchor
                lb = wp.length(x1 - origin) - reaches[k].bound - reach
                if lb > 0.0 and (ccd == 0 or lb * lb >= wp.length_sq(x1 - x0)):
                    if caching:
                        gap[ci] = lb + reach
                        anchor[ci] = x1
                    continue
            else:
                # moving mesh: the length of the vertex's path in the mesh's frame is at most
                # `path` (ObstacleReach)
                s = wp.length(x1 - x0)
                sweep = reaches[k].sweep
                path = s + sweep + reaches[k].turn * (wp.length(x1 - origin) + s + sweep)
                if valid and reaches[k].fresh != 0:
                    g = gap[ci] - path  # a lower bound of the distance along the path
                    if g > reach:
                        gap[ci] = g
                        continue
                lb = wp.length(x1 - origin) - reaches[k].bound - reach
                if lb > 0.0 and (ccd == 0 or lb >= path):
                    if caching:
                        gap[ci] = lb + reach
                    continue
            mask = mask | (1 << wp.min(k, 31))
        return mask

    @wp.kernel(module=module)
    def far_kernel(
        reaches: wp.array(dtype=ObstacleReach),
        x: wp.array(dtype=wp.vec3),
        x_start: wp.array(dtype=wp.vec3),
        inv_mass: wp.array(dtype=float),
        thickness: float,
        slack: float,
        respond_velocity: int,
        ccd: int,
        margin: float,
        gap: wp.array(dtype=float),
        anchor: wp.array(dtype=wp.vec3),
        last: wp.array(dtype=wp.vec3),
        near_count: wp.array(dtype=int),
        near_list: wp.array(dtype=int),
        near_mask: wp.array(dtype=int),
    ):
        """Pass 1, every vertex: the far tests (`far_mask`); a vertex that passes none is
        appended to ``near_list`` with the meshes it needs in ``near_mask``. ``margin``: extra
        reach, for a list that several position-based iterations reuse (the distance cache is
        used and kept only by ``apply``, whose margin is 0). Kept apart from the near work: Warp
        initialises a function's variables on entry and copies what a call takes by value, so a
        kernel that also holds the near path pays for it on every vertex (measured: twice this
        pass)."""
        i = wp.tid()
        if inv_mass[i] == 0.0:
            return
        x1 = x[i]
        caching = respond_velocity != 0
        mask = far_mask(reaches, i, x_start[i], x1, thickness + slack + margin, ccd, caching,
                        gap, anchor, last)
        if mask != 0:
            slot = wp.atomic_add(near_count, 0, 1)
            near_list[slot] = i
            near_mask[slot] = mask
        elif caching and ANY_MOVING != 0:
            last[i] = x1

    if update is None:
        return far_kernel, None

    @wp.kernel(module=module)
    def integrate_far(
        x: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        f: wp.array(dtype=wp.vec3),
        inv_mass: wp.array(dtype=float),
        gravity: wp.vec3,
        decay: float,
        dt: float,
        x_start: wp.array(dtype=wp.vec3),
        reaches: wp.array(dtype=ObstacleReach),
        thickness: float,
        slack: float,
        ccd: int,
        gap: wp.array(dtype=float),
        anchor: wp.array(dtype=wp.vec3),
        last: wp.array(dtype=wp.vec3),
        near_count: wp.array(dtype=int),
        near_list: wp.array(dtype=int),
        near_mask: wp.array(dtype=int),
    ):
        """The solver's vertex update (``update``), then `far_kernel`'s tests of the new path (``apply``:
        the cache is used and kept); only a listed vertex's start position is written to
        ``x_start`` (the near pass reads no other)."""
        i = wp.tid()
        w = inv_mass[i]
        fi = f[i]
        f[i] = wp.vec3(0.0)  # cleared for the next step's forces
        if w == 0.0:
            return
        x0 = x[i]
        vi = update(v[i], fi, w, gravity, decay, dt)
        x1 = x0 + dt * vi
        v[i] = vi
        x[i] = x1
        mask = far_mask(reaches, i, x0, x1, thickness + slack, ccd, True, gap, anchor, last)
        if mask != 0:
            x_start[i] = x0
            slot = wp.atomic_add(near_count, 0, 1)
            near_list[slot] = i
            near_mask[slot] = mask
        elif ANY_MOVING != 0:
            last[i] = x1

    return far_kernel, integrate_far


@wp.kernel
def mesh_near_kernel(
    obstacles: wp.array(dtype=ObstacleData),
    x: wp.array(dtype=wp.vec3),
    x_start: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    thickness: float,
    slack: float,
    respond_velocity: int,
    cache: MeshCache,
    near_count: wp.array(dtype=int),
    near_list: wp.array(dtype=int),
    near_mask: wp.array(dtype=int),
    num_threads: int,
    general_count: wp.array(dtype=int),
    general_list: wp.array(dtype=int),
    general_mask: wp.array(dtype=int),
):
    """Pass 2: the listed vertices, strided over ``ceil(N / NEAR_BATCH)`` threads (the list's
    length is known only on the device; a thread costs its set-up whether it has work or not,
    so fewer threads than vertices). Each of the vertex's meshes in order while its path lies in
    the mesh's static candidate ball (`static_cached_near`: most vertices resting on a static
    mesh); the first mesh that needs more, and the ones after it, go to a third list for
    `mesh_general_kernel` (kept apart: measured, the mere call of the general path in this loop
    cost the common case a fifth more)."""
    t = wp.tid()
    n = near_count[0]
    num = obstacles.shape[0]
    caching = respond_velocity != 0
    reach = thickness + slack
    for e in range(t, n, num_threads):
        i = near_list[e]
        left = near_mask[e]
        x0 = x_start[i]
        x1 = x[i]
        vi = wp.vec3(0.0)
        touched = bool(False)
        for k in range(wp.min(num, 31)):
            bit = 1 << k
            if (left & bit) != 0:
                ci = i * num + k
                if obstacles[k].moving != 0 or cache.cand_count[ci] == 0:
                    break
                q = cache.cand_q[ci]
                r2 = cache.cand_r2[ci]
                if wp.length_sq(x1 - q) > r2 or wp.length_sq(x0 - q) > r2:
                    break
                x1, vi, touched = static_cached_near(obstacles[k].restitution,
                                                     obstacles[k].friction, ci, i, x0, x1, v, vi,
                                                     touched, thickness, reach, respond_velocity,
                                                     caching, cache)
                left = left & ~bit
        if touched:
            x[i] = x1
            if respond_velocity != 0:
                v[i] = vi
        if caching:
            # a vertex this pass moved may have moved towards another mesh by more than its
            # path length: no distance cache for it next step (NaN never compares equal)
            cache.last[i] = wp.where(touched, wp.vec3(wp.nan), x1)
        if left != 0:
            slot = wp.atomic_add(general_count, 0, 1)
            general_list[slot] = i
            general_mask[slot] = left


@wp.kernel
def mesh_general_kernel(
    obstacles: wp.array(dtype=ObstacleData),
    mesh_ids: wp.array(dtype=wp.uint64),
    poses: wp.array(dtype=wp.transform),
    pose_offset: int,
    x: wp.array(dtype=wp.vec3),
    x_start: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    dt: float,
    thickness: float,
    slack: float,
    respond_velocity: int,
    ccd: int,
    cache: MeshCache,
    general_count: wp.array(dtype=int),
    general_list: wp.array(dtype=int),
    general_mask: wp.array(dtype=int),
    num_threads: int,
):
    """Pass 3: the vertices `mesh_near_kernel` left, with the meshes it left (`mesh_vertex_near`:
    BVH queries, moving meshes, candidate refreshes), in order."""
    t = wp.tid()
    n = general_count[0]
    for e in range(t, n, num_threads):
        i = general_list[e]
        mesh_vertex_near(obstacles, mesh_ids, poses, pose_offset, general_mask[e], i,
                         x_start[i], x[i], x, v, dt, thickness, slack, respond_velocity, ccd,
                         respond_velocity != 0, cache)


@wp.kernel
def mesh_planes_kernel(
    obstacles: wp.array(dtype=ObstacleData),
    mesh_ids: wp.array(dtype=wp.uint64),
    poses: wp.array(dtype=wp.transform),
    pose_offset: int,
    x: wp.array(dtype=wp.vec3),
    x_start: wp.array(dtype=wp.vec3),
    thickness: float,
    slack: float,
    ccd: int,
    cache: MeshCache,
    near_count: wp.array(dtype=int),
    near_list: wp.array(dtype=int),
    near_mask: wp.array(dtype=int),
    num_threads: int,
    planes: ContactPlanes,
):
    """The contact plane of each listed vertex and mesh in its mask (`warp_cloth.collision.
    planes`): closest point (candidate cache or BVH query), the ray test for a path that may
    cross the surface, and the point at the thickness above the closest point, in the world
    frame at ``t1``. No plane (zero normal) when no surface is within reach of the path."""
    t = wp.tid()
    n_list = near_count[0]
    num = obstacles.shape[0]
    reach = thickness + slack
    for e in range(t, n_list, num_threads):
        i = near_list[e]
        mask = near_mask[e]
        x0 = x_start[i]
        x1 = x[i]
        for k in range(num):
            c_e = e * num + k
            planes.normal[c_e] = wp.vec3(0.0)
            if k < 31 and ((mask >> k) & 1) == 0:
                continue
            ob = obstacles[k]
            mid = mesh_ids[k]
            j = 5 * (pose_offset + k)
            ci = i * num + k
            if ob.moving == 0 and cache.cand_count[ci] != 0:  # world-frame candidates
                q = cache.cand_q[ci]
                r2 = cache.cand_r2[ci]
                if wp.length_sq(x1 - q) <= r2 and wp.length_sq(x0 - q) <= r2:
                    cw, phiw, nw = cached_closest(cache, ci, x1)
                    planes.point[c_e] = cw + thickness * nw
                    planes.normal[c_e] = nw
                    planes.ref[c_e] = x0
                    planes.friction[c_e] = ob.friction
                    continue
            p0 = wp.transform_point(poses[j + 2], x0)
            p1 = wp.transform_point(poses[j + 3], x1)
            d = p1 - p0
            cached = False
            if ob.moving != 0 and cache.cand_count[ci] != 0:
                q = cache.cand_q[ci]
                r2 = cache.cand_r2[ci]
                cached = wp.length_sq(p1 - q) <= r2 and wp.length_sq(p0 - q) <= r2
            c = p1
            phi = float(0.0)
            n = wp.vec3(0.0, 1.0, 0.0)
            if cached:
                c, phi, n = cached_closest(cache, ci, p1)
            else:
                len_d = float(0.0)
                if ccd != 0:
                    len_d = wp.length(d)
                found = bool(False)
                found, c, phi, n = closest(mid, ob.closed, p1, p0, ob.center, ob.size,
                                           reach + len_d)
                if not found:
                    continue
                if ccd != 0 and (phi < 0.0 or phi < len_d):
                    ray = wp.mesh_query_ray(mid, p0, d, 1.0)
                    if ray.result:
                        dn = wp.dot(d, ray.normal)
                        if ob.closed == 0 or dn < 0.0:
                            ns = ray.normal  # the side the vertex came from
                            if dn > 0.0:
                                ns = -ray.normal
                            h = p0 + ray.t * d
                            c = h
                            n = ns
            T1 = poses[j + 1]
            planes.point[c_e] = wp.transform_point(T1, c + thickness * n)
            planes.normal[c_e] = wp.transform_vector(T1, n)
            planes.ref[c_e] = wp.transform_point(T1, p0)
            planes.friction[c_e] = ob.friction


@wp.kernel
def mesh_distance_kernel(mesh: wp.uint64, closed: int, points: wp.array(dtype=wp.vec3),
                         max_dist: float, out: wp.array(dtype=float)):
    i = wp.tid()
    p = points[i]
    if closed != 0:
        q = wp.mesh_query_point_no_sign(mesh, p, max_dist)
        if q.result:
            c = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
            d = wp.length(p - c)
            out[i] = wp.where(inside_by_winding(mesh, p, d, max_dist), -d, d)
    else:
        q = wp.mesh_query_point_no_sign(mesh, p, max_dist)
        if q.result:
            c = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
            out[i] = wp.length(p - c)


def mesh_signed_distance(obstacle, local_points, device="cpu") -> np.ndarray:
    """Signed (closed mesh; winding number) or unsigned (open) distance of local points, on the
    host. For tests and reports; not for use inside a step."""
    pts = np.asarray(local_points, dtype=np.float32).reshape(-1, 3)
    mesh = obstacle.wp_mesh(device)
    out = wp.zeros(len(pts), dtype=float, device=device)
    big = float(1e6)
    launch(mesh_distance_kernel, len(pts),
           [mesh.id, int(obstacle.closed), wp.array(pts, dtype=wp.vec3, device=device), big, out],
           device=device)
    return out.numpy().astype(np.float64)
