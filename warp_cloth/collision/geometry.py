"""Geometry shared by every contact source: closest points, distances and continuous tests.

Obstacle contact (a cloth vertex against an obstacle's faces, an obstacle's vertices against cloth
triangles, an obstacle's edges against cloth edges) and self-collision (the cloth's vertices
against its triangles, its edges against its edges) use these functions and no others.

- `closest_point_triangle` (float32): the point of a triangle closest to a point (Ericson,
  *Real-Time Collision Detection*, 5.1.5), the hot path of mesh-obstacle contact.
- `point_triangle_closest` / `segment_segment_closest` (float64): closest points with their
  barycentric / segment parameters, for vertex-triangle and edge-edge pairs (Ericson 5.1.5,
  5.1.9; robust for degenerate triangles and parallel or degenerate segments).
- `ccd_vertex_triangle` / `ccd_edge_edge` (float64): continuous tests of linear motion over the
  step, by **conservative advancement** (Mitchell et al.; the additive form of Li et al. 2021,
  "Codimensional Incremental Potential Contact", ACCD), not by the roots of the coplanarity
  cubic: the time is advanced by ``0.9 d / l`` where ``d`` is the current distance and ``l`` an
  upper bound of how fast the distance can shrink (the largest displacement of each primitive's
  vertices after removing their common mean, added), so the distance stays above ``0.1 d > 0``
  over each advance: a contact cannot be stepped over, whatever the geometry (coplanar starts,
  parallel edges, a vertex on an edge, touching at t = 0 or 1). Once the distance less the most
  the rest of the path can close (``(1 - t) l``) exceeds ``delta``, the query ends as a miss
  without further advances (most of a resting fold's candidates: their list scans 13-16 %
  faster). A query reports a hit when the
  distance falls to ``delta`` (the minimum separation: the contact thickness in the simulator,
  a round-off bound for exact-contact queries); the returned time is the first such advance, so
  the primitives are at least ``0.1 d`` apart before it. Distances are computed in float64, so
  round-off cannot hide a contact of coordinates of order one by more than about 1e-15, except
  to the plane of a thin triangle, where it grows as 1 / thinness: the vertex-triangle test
  advances on the distance less its round-off bound (`vt_round_off`), a lower bound, so a sliver
  reports its contact early (at most by that bound) rather than never.
  Queries that need more than ``max_iter`` advances (grazing motion at a distance just above
  ``delta``) report a conservative hit with status `CCD_CAPPED` (counted, never dropped).

Why not the cubic: its roots need tolerances in floating point and miss contacts in exactly the
degenerate cases above (the shared sample queries' README: a production cubic CCD misses 25 of
435 positive queries); the advancement has no such case (`warp-cloth bench ccd`: zero false
negatives on the shared queries, false positives counted).
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile

__all__ = ["closest_point_triangle", "point_triangle_closest", "segment_segment_closest",
           "ccd_vertex_triangle", "ccd_edge_edge", "vt_round_off", "vt_impact", "ee_impact",
           "CCD_MISS", "CCD_HIT", "CCD_CAPPED"]

CCD_MISS = wp.constant(0)
CCD_HIT = wp.constant(1)
CCD_CAPPED = wp.constant(2)  # conservative hit: the advancement ran out of iterations
# ``lp`` rounded up past float64's round-off in the early miss (`ccd_vertex_triangle`)
ONE_UP = wp.constant(wp.float64(1.0 + 1e-9))


@wp.func
def closest_point_triangle(a: wp.vec3, b: wp.vec3, c: wp.vec3, p: wp.vec3):
    """The point of triangle ``abc`` closest to ``p`` (Ericson, *Real-Time Collision Detection*,
    5.1.5: Voronoi regions of the vertices, edges and face)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        return a
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        return b
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        return a + (d1 / (d1 - d3)) * ab
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= 0.0 and d5 <= d6:
        return c
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        return a + (d2 / (d2 - d6)) * ac
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        return b + ((d4 - d3) / ((d4 - d3) + (d5 - d6))) * (c - b)
    denom = 1.0 / (va + vb + vc)
    return a + (vb * denom) * ab + (vc * denom) * ac


@wp.func
def point_segment_closest(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d):
    """(parameter s in [0, 1], closest point a + s (b - a)) of segment ``ab`` to ``p``."""
    ab = b - a
    l2 = wp.dot(ab, ab)
    s = wp.float64(0.0)
    if l2 > wp.float64(0.0):
        s = wp.clamp(wp.dot(p - a, ab) / l2, wp.float64(0.0), wp.float64(1.0))
    return s, a + s * ab


@wp.func
def point_triangle_closest(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d):
    """(closest point q, barycentric weights (wa, wb, wc) of q) of triangle ``abc`` to ``p``.

    The face region by Ericson's Voronoi test when the triangle is not degenerate; otherwise
    (and for the edge regions) the best of the three edges, so a zero-area triangle is treated
    as the segments it is made of."""
    ab = b - a
    ac = c - a
    n = wp.cross(ab, ac)
    n2 = wp.dot(n, n)
    scale = wp.max(wp.dot(ab, ab), wp.dot(ac, ac))
    if n2 > wp.float64(1.0e-24) * scale * scale:
        ap = p - a
        # barycentrics of the projection onto the plane
        v = wp.dot(wp.cross(ap, ac), n) / n2
        w = wp.dot(wp.cross(ab, ap), n) / n2
        u = wp.float64(1.0) - v - w
        if u >= wp.float64(0.0) and v >= wp.float64(0.0) and w >= wp.float64(0.0):
            return u * a + v * b + w * c, wp.vec3d(u, v, w)
    # edges: ab, bc, ca
    s0, q0 = point_segment_closest(p, a, b)
    s1, q1 = point_segment_closest(p, b, c)
    s2, q2 = point_segment_closest(p, c, a)
    d0 = wp.length_sq(p - q0)
    d1 = wp.length_sq(p - q1)
    d2 = wp.length_sq(p - q2)
    one = wp.float64(1.0)
    zero = wp.float64(0.0)
    if d0 <= d1 and d0 <= d2:
        return q0, wp.vec3d(one - s0, s0, zero)
    if d1 <= d2:
        return q1, wp.vec3d(zero, one - s1, s1)
    return q2, wp.vec3d(s2, zero, one - s2)


@wp.func
def segment_segment_closest(p0: wp.vec3d, p1: wp.vec3d, q0: wp.vec3d, q1: wp.vec3d):
    """(s, t, closest point on p, closest point on q) of segments ``p0 p1`` and ``q0 q1``
    (Ericson 5.1.9; parallel and degenerate segments handled)."""
    d1 = p1 - p0
    d2 = q1 - q0
    r = p0 - q0
    a = wp.dot(d1, d1)
    e = wp.dot(d2, d2)
    f = wp.dot(d2, r)
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    eps = wp.float64(1.0e-30)
    s = zero
    t = zero
    if a <= eps and e <= eps:
        return zero, zero, p0, q0
    if a <= eps:
        t = wp.clamp(f / e, zero, one)
    else:
        c = wp.dot(d1, r)
        if e <= eps:
            s = wp.clamp(-c / a, zero, one)
        else:
            b = wp.dot(d1, d2)
            # the lines' closest point by cross products, not by the Gram form
            # (b f - c e) / (a e - b^2): for edges a small angle apart that form cancels (at
            # 1e-7 rad it keeps two digits, and a crossing was reported 1e-8 apart), while
            # |d1 x d2|^2 and its numerator keep their relative precision at any angle (the
            # distance's error stays about 1e-16 |r|)
            n = wp.cross(d1, d2)
            denom = wp.dot(n, n)
            if denom > wp.float64(1.0e-30) * a * e:
                s = wp.clamp(wp.dot(wp.cross(q0 - p0, d2), n) / denom, zero, one)
            t = (b * s + f) / e
            if t < zero:
                t = zero
                s = wp.clamp(-c / a, zero, one)
            elif t > one:
                t = one
                s = wp.clamp((b - c) / a, zero, one)
    return s, t, p0 + s * d1, q0 + t * d2


@wp.func
def vt_distance(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d):
    q, w = point_triangle_closest(p, a, b, c)
    return wp.length(p - q)


@wp.func
def vt_round_off(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d):
    """A bound on the float64 round-off of `vt_distance` at these points, the rounding of the
    points themselves (interpolated along their paths) included.

    Measured to the plane of a thin triangle, the distance is ill-conditioned: the plane's
    normal is the cross product of two nearly parallel edges, and a perturbation ``delta`` of a
    corner tilts the plane by ``delta / h`` (``h`` the triangle's least height), moving it by
    ``R delta / h`` at the point (``R`` the point's distance from the triangle). With
    ``delta`` the rounding of a coordinate of magnitude ``M`` (about ``eps M``) and the cross
    product's own cancellation, the error is at most about ``8 eps (M + (R / h) (M + L))``
    (``L`` the longest edge): about ``1e-15`` for a triangle of ordinary shape at coordinates of
    order one, ``1e-9`` for one 1e-7 thin. A triangle too thin for its plane
    (`point_triangle_closest`'s degenerate branch) is measured to its edges, which are not
    ill-conditioned."""
    ab = b - a
    ac = c - a
    bc = c - b
    l2 = wp.max(wp.dot(ab, ab), wp.max(wp.dot(ac, ac), wp.dot(bc, bc)))
    scale = wp.max(wp.dot(ab, ab), wp.dot(ac, ac))
    n = wp.cross(ab, ac)
    n2 = wp.dot(n, n)
    m = wp.float64(0.0)
    for k in range(3):
        m = wp.max(m, wp.max(wp.max(wp.abs(p[k]), wp.abs(a[k])),
                             wp.max(wp.abs(b[k]), wp.abs(c[k]))))
    big = wp.sqrt(l2)
    eps = wp.float64(8.0 * 2.220446049250313e-16)
    if n2 > wp.float64(1.0e-24) * scale * scale:
        r = wp.length(p - a) + big
        h = wp.sqrt(n2) / big  # the least height: twice the area over the longest edge
        return eps * (m + (r / h) * (m + big))
    return eps * (m + big)


@wp.func
def ee_distance(p0: wp.vec3d, p1: wp.vec3d, q0: wp.vec3d, q1: wp.vec3d):
    s, t, cp, cq = segment_segment_closest(p0, p1, q0, q1)
    return wp.length(cp - cq)


@wp.func
def ccd_vertex_triangle(p0: wp.vec3d, a0: wp.vec3d, b0: wp.vec3d, c0: wp.vec3d,
                        p1: wp.vec3d, a1: wp.vec3d, b1: wp.vec3d, c1: wp.vec3d,
                        delta: wp.float64, max_iter: int):
    """Continuous vertex-triangle test of the linear motion ``*0 -> *1`` over t in [0, 1]:
    (status `CCD_MISS` / `CCD_HIT` / `CCD_CAPPED`, time of the hit). A hit is the distance
    falling to ``delta`` (module docstring: conservative advancement, no false negatives)."""
    dp = p1 - p0
    da = a1 - a0
    db = b1 - b0
    dc = c1 - c0
    mean = wp.float64(0.25) * (dp + da + db + dc)
    lp = wp.length(dp - mean) + wp.max(wp.length(da - mean),
                                       wp.max(wp.length(db - mean), wp.length(dc - mean)))
    t = wp.float64(0.0)
    one = wp.float64(1.0)
    for it in range(max_iter):
        pt = p0 + t * dp
        at = a0 + t * da
        bt = b0 + t * db
        ct = c0 + t * dc
        # the distance less its round-off bound (`vt_round_off`): a lower bound of the distance
        d = vt_distance(pt, at, bt, ct) - vt_round_off(pt, at, bt, ct)
        if d <= delta:
            return CCD_HIT, t
        if d - (one - t) * lp * ONE_UP > delta:  # cannot close the gap before t = 1
            return CCD_MISS, one
        step = wp.float64(0.9) * d / lp
        if t + step >= one:
            d1 = vt_distance(p1, a1, b1, c1) - vt_round_off(p1, a1, b1, c1)
            if d1 <= delta:
                return CCD_HIT, one
            return CCD_MISS, one
        t = t + step
    return CCD_CAPPED, t


@wp.func
def ccd_edge_edge(p0: wp.vec3d, p1: wp.vec3d, q0: wp.vec3d, q1: wp.vec3d,
                  p0e: wp.vec3d, p1e: wp.vec3d, q0e: wp.vec3d, q1e: wp.vec3d,
                  delta: wp.float64, max_iter: int):
    """Continuous edge-edge test of edges ``p0 p1`` and ``q0 q1`` moving linearly to
    ``p0e p1e`` and ``q0e q1e``: (status, time), as `ccd_vertex_triangle`."""
    dp0 = p0e - p0
    dp1 = p1e - p1
    dq0 = q0e - q0
    dq1 = q1e - q1
    mean = wp.float64(0.25) * (dp0 + dp1 + dq0 + dq1)
    lp = wp.max(wp.length(dp0 - mean), wp.length(dp1 - mean)) + wp.max(
        wp.length(dq0 - mean), wp.length(dq1 - mean))
    t = wp.float64(0.0)
    one = wp.float64(1.0)
    for it in range(max_iter):
        d = ee_distance(p0 + t * dp0, p1 + t * dp1, q0 + t * dq0, q1 + t * dq1)
        if d <= delta:
            return CCD_HIT, t
        if d - (one - t) * lp * ONE_UP > delta:  # as `ccd_vertex_triangle`
            return CCD_MISS, one
        step = wp.float64(0.9) * d / lp
        if t + step >= one:
            d1 = ee_distance(p0e, p1e, q0e, q1e)
            if d1 <= delta:
                return CCD_HIT, one
            return CCD_MISS, one
        t = t + step
    return CCD_CAPPED, t


@wp.func
def d3(v: wp.vec3):
    return wp.vec3d(wp.float64(v[0]), wp.float64(v[1]), wp.float64(v[2]))


@wp.func
def f3(v: wp.vec3d):
    return wp.vec3(float(v[0]), float(v[1]), float(v[2]))


@wp.func
def vt_impact(p0: wp.vec3, p1: wp.vec3, a0: wp.vec3, a1: wp.vec3, b0: wp.vec3, b1: wp.vec3,
              c0: wp.vec3, c1: wp.vec3, toi: wp.float64):
    """A vertex-triangle contact at the time of impact ``toi`` of the linear paths ``*0 -> *1``:
    (unit normal from the triangle's closest point to the vertex, barycentric weights of that
    point, valid). When they touch there, the face normal, turned to the side the vertex was
    on at the start; not valid for a degenerate triangle then."""
    ft = float(toi)
    pa = a0 + ft * (a1 - a0)
    pb = b0 + ft * (b1 - b0)
    pc = c0 + ft * (c1 - c0)
    pv = p0 + ft * (p1 - p0)
    cq, bw = point_triangle_closest(d3(pv), d3(pa), d3(pb), d3(pc))
    w = wp.vec3(float(bw[0]), float(bw[1]), float(bw[2]))
    d = pv - f3(cq)
    if wp.length(d) > 1.0e-9:
        return wp.normalize(d), w, True
    n = wp.cross(pb - pa, pc - pa)
    if wp.length(n) < 1.0e-12:
        return wp.vec3(0.0), w, False
    n = wp.normalize(n)
    if wp.dot(p0 - (w[0] * a0 + w[1] * b0 + w[2] * c0), n) < 0.0:
        n = -n
    return n, w, True


@wp.func
def ee_impact(a0: wp.vec3, a1: wp.vec3, b0: wp.vec3, b1: wp.vec3, c0: wp.vec3, c1: wp.vec3,
              d0: wp.vec3, d1: wp.vec3, toi: wp.float64):
    """An edge-edge contact of edges ``ab`` and ``cd`` at the time of impact ``toi``: (unit
    normal from ``cd``'s closest point to ``ab``'s, parameter on ``ab``, parameter on ``cd``,
    valid). When they touch there, the normal of both edges, turned to the side ``ab`` was on
    at the start; not valid for parallel edges then."""
    ft = float(toi)
    pa = a0 + ft * (a1 - a0)
    pb = b0 + ft * (b1 - b0)
    pc = c0 + ft * (c1 - c0)
    pd = d0 + ft * (d1 - d0)
    s, t, c1p, c2p = segment_segment_closest(d3(pa), d3(pb), d3(pc), d3(pd))
    fs = float(s)
    fu = float(t)
    d = f3(c1p) - f3(c2p)
    if wp.length(d) > 1.0e-9:
        return wp.normalize(d), fs, fu, True
    n = wp.cross(pb - pa, pd - pc)
    if wp.length(n) < 1.0e-12:
        return wp.vec3(0.0), fs, fu, False
    n = wp.normalize(n)
    if wp.dot((a0 + fs * (b0 - a0)) - (c0 + fu * (d0 - c0)), n) < 0.0:
        n = -n
    return n, fs, fu, True


@wp.kernel
def ccd_queries_kernel(points: wp.array2d(dtype=wp.vec3d), edge_edge: int, delta: wp.float64,
                       max_iter: int, status: wp.array(dtype=int), toi: wp.array(dtype=wp.float64)):
    """One query per thread: ``points[q]`` holds the 8 positions of the shared query format
    (vertex-face: v, f0, f1, f2 at t0 then at t1; edge-edge: ea0, ea1, eb0, eb1 at t0 then t1).
    ``delta`` is scaled by ``max(1, max |coordinate|)`` of the query (float64 round-off of the
    inputs grows with their magnitude)."""
    q = wp.tid()
    s = int(0)
    t = wp.float64(0.0)
    scale = wp.float64(1.0)  # delta is relative to the coordinates' magnitude (round-off)
    for k in range(8):
        p = points[q, k]
        scale = wp.max(scale, wp.max(wp.abs(p[0]), wp.max(wp.abs(p[1]), wp.abs(p[2]))))
    delta = delta * scale
    if edge_edge != 0:
        s, t = ccd_edge_edge(points[q, 0], points[q, 1], points[q, 2], points[q, 3],
                             points[q, 4], points[q, 5], points[q, 6], points[q, 7], delta, max_iter)
    else:
        s, t = ccd_vertex_triangle(points[q, 0], points[q, 1], points[q, 2], points[q, 3],
                                   points[q, 4], points[q, 5], points[q, 6], points[q, 7], delta,
                                   max_iter)
    status[q] = s
    toi[q] = t
