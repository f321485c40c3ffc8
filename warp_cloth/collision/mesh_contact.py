"""Contact kernel for triangle-mesh obstacles (`wp.Mesh` BVH queries): one thread per vertex, all
mesh obstacles of a contact fused into one launch. Kept apart from the analytic kernels so that a
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

Distance cache (``apply`` only): each vertex keeps a lower bound of its distance to each mesh
(``gap``, from the last query, searched ``margin`` beyond the reach) and the position it ended the
last step at (``last``). While the step starts exactly there (and, for a moving mesh, at the time
the last ``apply`` ended: ``ObstacleReach.fresh``) and ``gap`` minus the length of the path in the
mesh's frame stays above the reach, the vertex skips the BVH queries: the distance cannot have
dropped by more than that. For a moving mesh the path length is bounded by the vertex's own motion
plus the mesh's translation and rotation over the step (`warp_cloth.collision.motion.ObstacleReach`).
Anything else that moved the vertex in between (a state reset, a later correction, another mesh
of this kernel) fails the ``last == x_start`` check and the vertex is queried again. A vertex that
touched a mesh last step queries without the margin (a tighter query; it would not skip anyway).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .motion import ObstacleData, ObstacleReach
from .response import contact_outcome


@wp.func
def closest(mid: wp.uint64, closed: int, p: wp.vec3, p_from: wp.vec3, center: wp.vec3,
            half: wp.vec3, max_dist: float):
    """(found, closest point c, signed distance phi, unit normal n pointing from c to the side
    the point belongs on). Closed mesh: outside; when ``p`` is in the mesh's bounding box the
    whole mesh is searched, so a point deep inside is found too. Open mesh: the side of ``p``,
    or of ``p_from`` when ``p`` lies on the surface."""
    c = p
    phi = float(0.0)
    n = wp.vec3(0.0, 1.0, 0.0)
    if closed != 0:
        q = wp.mesh_query_point_sign_normal(mid, p, max_dist)
        if not q.result:
            rel = p - center
            if wp.abs(rel[0]) <= half[0] and wp.abs(rel[1]) <= half[1] and wp.abs(rel[2]) <= half[2]:
                # in the bounding box: might be deep inside, search the whole mesh
                q = wp.mesh_query_point_sign_normal(mid, p, 2.0 * wp.length(half) + max_dist)
            if not q.result:
                return False, c, phi, n
        c = wp.mesh_eval_position(mid, q.face, q.u, q.v)
        diff = p - c
        dist = wp.length(diff)
        n = wp.mesh_eval_face_normal(mid, q.face)
        phi = dist
        if q.sign < 0.0:
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


@wp.func
def mesh_vertex(
    obstacles: wp.array(dtype=ObstacleData),
    mesh_ids: wp.array(dtype=wp.uint64),
    reaches: wp.array(dtype=ObstacleReach),
    poses: wp.array(dtype=wp.transform),
    pose_offset: int,
    i: int,
    x0: wp.vec3,
    x1: wp.vec3,
    v: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    dt: float,
    thickness: float,
    slack: float,
    respond_velocity: int,
    ccd: int,
    gap: wp.array(dtype=float),
    last: wp.array(dtype=wp.vec3),
    margin: float,
):
    """Contact of vertex ``i`` (path ``x0 -> x1``) with every mesh obstacle; maintains the
    distance cache. Returns (end position, velocity, touched) like `analytic_vertex`."""
    vi = wp.vec3(0.0)
    if inv_mass[i] == 0.0:
        return x1, vi, False
    touched = bool(False)  # read v and write back only for vertices near an obstacle
    reach = thickness + slack
    num = obstacles.shape[0]
    # distance cache (apply only): valid when this step starts where the last one ended
    caching = respond_velocity != 0
    valid = caching and last[i] == x0
    s = wp.length(x1 - x0)
    for k in range(num):
        rb = reaches[k]
        # the length of the vertex's path in the mesh's frame is at most `path`
        # (ObstacleReach; just |x1 - x0| for a static mesh, no distance to the origin needed)
        path = s
        if rb.sweep != 0.0 or rb.turn != 0.0:
            path = s + rb.sweep + rb.turn * (wp.length(x1 - rb.origin) + s + rb.sweep)
        if valid and rb.fresh != 0:
            g = gap[i * num + k] - path  # a lower bound of the distance along the path
            if g > reach:
                gap[i * num + k] = g
                continue
        # far test in the world frame (no transform): outside the bounding ball by more than
        # the reach and than the path length
        lb = wp.length(x1 - rb.origin) - rb.bound - reach
        if lb > 0.0 and (ccd == 0 or lb >= path):
            if caching:
                gap[i * num + k] = lb + reach
            continue
        ob = obstacles[k]
        mid = mesh_ids[k]
        j = 5 * (pose_offset + k)
        p0 = wp.transform_point(poses[j + 2], x0)
        p1 = wp.transform_point(poses[j + 3], x1)
        d = p1 - p0
        len_d = wp.length(d)
        if ccd == 0:
            len_d = 0.0
        # cheap rejection: the path's box against the mesh's box grown by the reach
        lo = wp.min(p0, p1) - ob.center
        hi = wp.max(p0, p1) - ob.center
        ext = ob.size + wp.vec3(reach)
        if (lo[0] > ext[0] or lo[1] > ext[1] or lo[2] > ext[2]
                or hi[0] < -ext[0] or hi[1] < -ext[1] or hi[2] < -ext[2]):
            if caching:
                gap[i * num + k] = reach
            continue
        # closest point to the end position, as far as the path could reach (plus the cache
        # margin, so that a miss keeps the vertex out of the queries for a while)
        radius = reach + len_d
        if caching and gap[i * num + k] > reach:
            # not touching last step: look beyond the reach so that a miss
            # keeps the vertex out of the next steps' queries; a touching vertex will most
            # likely touch again, and a tighter query visits fewer BVH nodes
            radius = radius + margin
        found, c, phi, n = closest(mid, ob.closed, p1, p0, ob.center, ob.size, radius)
        if not found:
            if caching:
                gap[i * num + k] = radius
            continue  # no surface within reach of the end, so the path cannot cross one
        moved = False
        p_in = p1
        if ccd != 0 and (phi < 0.0 or phi < len_d):
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
            gap[i * num + k] = phi
            if moved:
                gap[i * num + k] = 0.0
        if moved or (respond_velocity != 0 and phi < reach):
            if respond_velocity != 0 and not touched:
                vi = v[i]
            touched = True
            x1, vi = contact_outcome(p0, p_in, p1, n, poses[j], poses[j + 1], vi, dt,
                                     ob.restitution, ob.friction, respond_velocity)
    if caching:
        # a vertex this kernel moved may have moved towards another mesh by more than its path
        # length: no cache for it next step (NaN never compares equal)
        last[i] = x1
        if touched:
            last[i] = wp.vec3(wp.nan)
    return x1, vi, touched

@wp.kernel
def mesh_contact_kernel(
    obstacles: wp.array(dtype=ObstacleData),
    mesh_ids: wp.array(dtype=wp.uint64),
    reaches: wp.array(dtype=ObstacleReach),
    poses: wp.array(dtype=wp.transform),
    pose_offset: int,
    x: wp.array(dtype=wp.vec3),
    x_start: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    dt: float,
    thickness: float,
    slack: float,
    respond_velocity: int,
    ccd: int,
    gap: wp.array(dtype=float),
    last: wp.array(dtype=wp.vec3),
    margin: float,
):
    i = wp.tid()
    x1, vi, touched = mesh_vertex(obstacles, mesh_ids, reaches, poses, pose_offset, i, x_start[i],
                                  x[i], v, inv_mass, dt, thickness, slack, respond_velocity, ccd,
                                  gap, last, margin)
    if touched:
        x[i] = x1
        if respond_velocity != 0:
            v[i] = vi


@wp.kernel
def mesh_distance_kernel(mesh: wp.uint64, closed: int, points: wp.array(dtype=wp.vec3),
                         max_dist: float, out: wp.array(dtype=float)):
    i = wp.tid()
    p = points[i]
    if closed != 0:
        q = wp.mesh_query_point_sign_winding_number(mesh, p, max_dist)
        if q.result:
            c = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
            out[i] = q.sign * wp.length(p - c)
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
    wp.launch(mesh_distance_kernel, len(pts),
              [mesh.id, int(obstacle.closed), wp.array(pts, dtype=wp.vec3, device=device), big, out],
              device=device)
    return out.numpy().astype(np.float64)
