"""Shared collision geometry (`warp_cloth.collision.geometry`): closest points against brute force,
continuous tests on the exact-rational CCD queries (no false negative) and on degenerate cases."""

import os

import numpy as np
import pytest
import warp as wp

from warp_cloth.bench.ccd import (constructed_queries, default_queries_dir, read_queries,
                                  run_queries)
from warp_cloth.collision import geometry

HERE = os.path.dirname(os.path.abspath(__file__))
VENDORED = os.path.join(HERE, "data", "ccd-queries")  # the shared set's unit-tests scene


@wp.kernel
def _closest_kernel(p: wp.array2d(dtype=wp.vec3d), bary: wp.array(dtype=wp.vec3d),
                    seg: wp.array(dtype=wp.vec2d), dist: wp.array(dtype=wp.float64)):
    i = wp.tid()
    q, w = geometry.point_triangle_closest(p[i, 0], p[i, 1], p[i, 2], p[i, 3])
    bary[i] = w
    s, t, cp, cq = geometry.segment_segment_closest(p[i, 0], p[i, 1], p[i, 2], p[i, 3])
    seg[i] = wp.vec2d(s, t)
    dist[i] = wp.length(cp - cq)


def _closest(points):
    n = len(points)
    p = wp.array(points, dtype=wp.vec3d, device="cpu")
    bary = wp.zeros(n, dtype=wp.vec3d, device="cpu")
    seg = wp.zeros(n, dtype=wp.vec2d, device="cpu")
    dist = wp.zeros(n, dtype=wp.float64, device="cpu")
    wp.launch(_closest_kernel, n, [p, bary, seg, dist], device="cpu")
    return bary.numpy(), seg.numpy(), dist.numpy()


def test_closest_points_match_brute_force():
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(300, 4, 3))
    pts[:40, 3] = pts[:40, 1] + 0.5 * (pts[:40, 2] - pts[:40, 1])  # degenerate triangles
    pts[40:80, 3] = pts[40:80, 2] + (pts[40:80, 1] - pts[40:80, 0])  # parallel segments
    bary, seg, dist = _closest(pts)
    u = np.linspace(0, 1, 201)
    for k in range(len(pts)):
        p, a, b, c = pts[k]
        # triangle: sample barycentrics densely
        uu, vv = np.meshgrid(u, u)
        m = uu + vv <= 1
        tri = a + uu[m, None] * (b - a) + vv[m, None] * (c - a)
        best = np.linalg.norm(tri - p, axis=1).min()
        w = bary[k]
        assert w.min() >= -1e-12 and abs(w.sum() - 1) < 1e-9
        q = w[0] * a + w[1] * b + w[2] * c
        assert np.linalg.norm(q - p) <= best + 1e-9
        # segments p0 = p, p1 = a; q0 = b, q1 = c
        s_, t_ = np.meshgrid(u, u)
        d = np.linalg.norm((p + s_[..., None] * (a - p)) - (b + t_[..., None] * (c - b)), axis=-1)
        assert dist[k] <= d.min() + 1e-9
        s, t = seg[k]
        assert 0 <= s <= 1 and 0 <= t <= 1
        assert abs(np.linalg.norm(p + s * (a - p) - (b + t * (c - b))) - dist[k]) < 1e-9


def _query_files():
    roots = [VENDORED]
    shared = default_queries_dir()
    if shared is not None and os.path.isdir(shared):
        roots = [shared]  # the whole shared set (it contains the vendored scene)
    out = []
    for root in roots:
        for dirpath, _, files in os.walk(root):
            out += [os.path.join(dirpath, f) for f in files if f.endswith(".csv")]
    return sorted(out)


def test_query_files_found():
    files = _query_files()
    assert any("edge-edge" in f for f in files) and any("vertex-face" in f for f in files)


@pytest.mark.parametrize("path", _query_files(), ids=lambda p: "/".join(p.split(os.sep)[-3:-1]))
def test_ccd_has_no_false_negative_on_exact_queries(path):
    pts, truth = read_queries(path)
    status, toi, _ = run_queries(pts, "edge-edge" in path, delta=1e-10)
    hit = status != geometry.CCD_MISS
    assert not (truth & ~hit).any(), f"missed {int((truth & ~hit).sum())} of {int(truth.sum())}"
    assert (toi >= 0).all() and (toi <= 1).all()
    # a miss is honest: a query the test calls separate at every time it stepped through
    # cannot be a positive (checked above); hits on negatives are counted by bench ccd


#: the same query with its primitives in another order (rows 0-3 at t = 0, 4-7 at t = 1)
EE_ORDERS = ([2, 3, 0, 1], [1, 0, 2, 3], [0, 1, 3, 2], [3, 2, 1, 0])  # edges swapped, reversed
VF_ORDERS = ([0, 2, 3, 1], [0, 3, 1, 2], [0, 1, 3, 2])  # the triangle's corners turned, flipped


@pytest.mark.parametrize("path", _query_files(), ids=lambda p: "/".join(p.split(os.sep)[-3:-1]))
def test_ccd_misses_nothing_in_another_order_or_scale(path):
    """The exact queries with their primitives reordered (edges swapped or reversed, a
    triangle's corners turned or flipped) and scaled by 2^20 and 2^-20 (exact in float64): the
    answer is the same, and the test must not miss one either way (an asymmetric bound or a
    tolerance in absolute units would)."""
    pts, truth = read_queries(path)
    ee = "edge-edge" in path
    for order in EE_ORDERS if ee else VF_ORDERS:
        idx = order + [i + 4 for i in order]
        for scale in (1.0, 2.0 ** 20, 2.0 ** -20):
            status, _, _ = run_queries(pts[:, idx, :] * scale, ee, delta=1e-10)
            hit = status != geometry.CCD_MISS
            assert not (truth & ~hit).any(), (order, scale, int((truth & ~hit).sum()))


@pytest.mark.parametrize("ee", [False, True], ids=["vertex-face", "edge-edge"])
def test_ccd_misses_no_constructed_contact_in_another_order_or_scale(ee):
    """`constructed_queries` (every one touches; half nearly degenerate; at the origin and far
    from it) reordered and scaled as above."""
    pts, _, _ = constructed_queries(400, ee, seed=3)
    for order in EE_ORDERS if ee else VF_ORDERS:
        idx = order + [i + 4 for i in order]
        for scale in (1.0, 2.0 ** 20, 2.0 ** -20):
            status, _, _ = run_queries(pts[:, idx, :] * scale, ee, delta=1e-10)
            missed = int((status == geometry.CCD_MISS).sum())
            assert missed == 0, (order, scale, missed)


def _vt(v0, tri0, v1, tri1, delta=1e-9):
    pts = np.array([[v0, *tri0, v1, *tri1]], dtype=np.float64)
    s, t, _ = run_queries(pts, False, delta=delta)
    return int(s[0]), float(t[0])


def _ee(a0, b0, a1, b1, delta=1e-9):
    pts = np.array([[*a0, *b0, *a1, *b1]], dtype=np.float64)
    s, t, _ = run_queries(pts, True, delta=delta)
    return int(s[0]), float(t[0])


TRI = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]


def test_ccd_degenerate_cases():
    # a vertex falling through the face: hit near t = 0.5
    s, t = _vt((0.2, 0.2, 1), TRI, (0.2, 0.2, -1), TRI)
    assert s == 1 and abs(t - 0.5) < 1e-6
    # passing beside the triangle: miss
    assert _vt((2, 2, 1), TRI, (2, 2, -1), TRI)[0] == 0
    # motion starting coplanar (in the plane, outside the face) and sliding over an edge
    s, t = _vt((2, 0.5, 0), TRI, (0.2, 0.5, 0), TRI)
    assert s == 1 and abs(t - 1.5 / 1.8) < 1e-6
    # coplanar and staying outside: miss
    assert _vt((2, 0.5, 0), TRI, (3, 0.5, 0), TRI)[0] == 0
    # no motion at all: hit only if touching
    assert _vt((0.2, 0.2, 0), TRI, (0.2, 0.2, 0), TRI)[0] == 1
    assert _vt((0.2, 0.2, 0.1), TRI, (0.2, 0.2, 0.1), TRI)[0] == 0
    # a vertex ending exactly on an edge (touching at t = 1), and starting on one (t = 0)
    s, t = _vt((0.5, -1, 0), TRI, (0.5, 0, 0), TRI)
    assert s == 1 and t > 0.99
    s, t = _vt((0.5, 0, 0), TRI, (0.5, -1, 0), TRI)
    assert s == 1 and t == 0.0
    # crossing edges (the classic EE case), and parallel edges sliding past each other
    s, t = _ee([(0, 0, 1), (1, 0, 1)], [(0.5, -1, 0), (0.5, 1, 0)],
               [(0, 0, -1), (1, 0, -1)], [(0.5, -1, 0), (0.5, 1, 0)])
    assert s == 1 and abs(t - 0.5) < 1e-6
    assert _ee([(0, 0, 0), (1, 0, 0)], [(0, 1, 0), (1, 1, 0)],
               [(0, 0, 0), (1, 0, 0)], [(2, 1, 0), (3, 1, 0)])[0] == 0
    # parallel edges meeting head-on (collinear) and parallel ones closing in
    s, t = _ee([(0, 0, 0), (1, 0, 0)], [(2, 0, 0), (3, 0, 0)],
               [(0, 0, 0), (1, 0, 0)], [(0.5, 0, 0), (1.5, 0, 0)])
    assert s == 1 and 0.25 < t < 0.75
    s, t = _ee([(0, 0, 0), (1, 0, 0)], [(0, 1, 0), (1, 1, 0)],
               [(0, 0, 0), (1, 0, 0)], [(0, -1, 0), (1, -1, 0)])
    assert s == 1 and abs(t - 0.5) < 1e-6
    # a fast vertex through a tiny triangle far from the origin (the time step tunnels)
    off = np.array([1e3, -2e3, 5e2])
    small = [tuple(off + 1e-3 * np.array(p)) for p in TRI]
    s, t = _vt(tuple(off + [2e-4, 2e-4, 50]), small, tuple(off + [2e-4, 2e-4, -50]), small,
               delta=1e-7)
    assert s == 1 and abs(t - 0.5) < 1e-3


@pytest.mark.parametrize("end", [0.9e-3, 1.1e-3])
def test_ccd_reaching_delta_at_the_end_of_the_step(end):
    """Paths whose distance falls to ``end`` exactly at t = 1, ``delta`` 1e-3 (coordinates
    within 1: `run_queries` scales it with larger ones): a hit just
    below it, a miss just above (the early miss once the distance less the most the rest of
    the path can close exceeds ``delta``: with ``lp`` halved or the remaining time ignored,
    the hits here are missed). Head-on, after an advance along a slanted path (the remaining
    time enters the bound), with both primitives moving, and edge against edge."""
    hit = end < 1e-3
    s, t = _vt((0.2, 0.2, 1), TRI, (0.2, 0.2, end), TRI, delta=1e-3)
    assert s == int(hit) and (not hit or t > 0.99)
    s, t = _vt((1, 0.2, 1), TRI, (0.2, 0.2, end), TRI, delta=1e-3)
    assert s == int(hit) and (not hit or t > 0.99)
    up = [(x, y, z + 0.25) for x, y, z in TRI]
    s, t = _vt((0.2, 0.2, 1), TRI, (0.2, 0.2, 0.25 + end), up, delta=1e-3)
    assert s == int(hit) and (not hit or t > 0.99)
    b = [(0.5, -1, 0), (0.5, 1, 0)]
    s, t = _ee([(0, 0, 1), (1, 0, 1)], b, [(0, 0, end), (1, 0, end)], b, delta=1e-3)
    assert s == int(hit) and (not hit or t > 0.99)


def test_ccd_time_is_conservative():
    """At the reported time the primitives are still apart (the advancement never steps past
    the contact), and the distance there is at most delta."""
    rng = np.random.default_rng(7)
    n = 400
    pts = rng.normal(size=(n, 8, 3))
    pts[:, 4:] = pts[:, :4] + 2.0 * rng.normal(size=(n, 4, 3))
    for ee in (False, True):
        status, toi, _ = run_queries(pts, ee, delta=1e-3)
        for k in np.flatnonzero(status == 1):
            delta = 1e-3 * max(1.0, np.abs(pts[k]).max())  # delta is relative to the coordinates
            x = pts[k, :4] + toi[k] * (pts[k, 4:] - pts[k, :4])
            if ee:
                _, _, d = _closest(x[None])
            else:
                w, _, _ = _closest(x[None])
                q = w[0] @ x[1:]
                d = [np.linalg.norm(q - x[0])]
            assert d[0] <= delta + 1e-9


@pytest.mark.parametrize("angle", [1e-5, 1e-7, 1e-9])
def test_ccd_edges_crossing_at_a_small_angle(angle):
    """Two edges a small angle apart that cross: the closest points of their lines must not
    come from the Gram form (b f - c e) / (a e - b^2), which cancels at small angles (below
    1e-7 rad the old code treated them as parallel and took an endpoint, 1e-8 apart, so the
    crossing below passed as a miss at delta 1e-10)."""
    c = np.array([0.3, 0.0, 0.0])
    u = np.array([np.cos(angle), np.sin(angle), 0.0])
    p = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0)]
    q = np.stack([c - 0.4 * u, c + 0.6 * u])
    _, _, d = _closest(np.array([[p[0], p[1], q[0], q[1]]]))
    assert d[0] < 1e-15
    up, down = q + [0.0, 0.0, 1e-3], q - [0.0, 0.0, 1e-3]
    s, t = _ee(p, [tuple(v) for v in up], p, [tuple(v) for v in down], delta=1e-10)
    assert s == 1 and abs(t - 0.5) < 1e-6


def test_ccd_no_false_negative_on_constructed_crossings():
    """Edge pairs built to cross at a known time (`constructed_queries`: half of them 1e-7 rad
    apart, a tenth touching at t = 0 and a tenth at t = 1, some far from the origin, some moving
    together): every one is a hit. With the Gram form of the closest points 136 of 10,800 such
    queries (all nearly parallel) were missed; 26 of these 400."""
    pts, _, _ = constructed_queries(400, True, seed=11, angle=1e-7)
    status, _, _ = run_queries(pts, True, delta=1e-10)
    assert (status != geometry.CCD_MISS).all(), np.flatnonzero(status == geometry.CCD_MISS)
    # the vertex-triangle queries of the same kind, the 1e-7 thin slivers among them: every
    # one a hit as well (without the round-off bound of the distance to a thin triangle's
    # plane, `vt_round_off`, 8 slivers of these 400 were missed)
    pts, _, degenerate = constructed_queries(400, False, seed=11, angle=1e-7)
    assert degenerate.sum() > 100
    status, _, _ = run_queries(pts, False, delta=1e-10)
    assert (status != geometry.CCD_MISS).all(), np.flatnonzero(status == geometry.CCD_MISS)


@pytest.mark.parametrize("thin", [1e-6, 1e-8, 1e-10])
def test_ccd_vertex_through_a_sliver(thin):
    """A vertex crossing a triangle ``thin`` times as wide as long, turned at random and 130 m
    from the origin: a hit no later than the crossing. In float64 the plane of such a triangle
    is off by up to about ``1e-15 * 130 / thin`` (the cross product of two nearly parallel edges
    cancels); without that bound (`vt_round_off`) 34 of 40 such crossings at 1e-10 were missed.
    Where the bound is below 1e-4, the same vertex passing 1e-4 beside the plane is a miss: the
    test is widened only as far as the round-off."""
    rng = np.random.default_rng(5)
    off = np.array([123.0, -45.0, 6.0])
    for _ in range(10):
        Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))

        def at(v):
            return tuple(off + Q @ np.asarray(v, dtype=np.float64))

        tri = [at([0.0, 0.0, 0.0]), at([1.0, 0.0, 0.0]), at([0.5, thin, 0.0])]
        q = np.array([0.5, 0.4 * thin, 0.0])  # inside the sliver
        s, t = _vt(at(q + [0.0, 0.0, 1e-3]), tri, at(q - [0.0, 0.0, 3e-3]), tri, delta=1e-10)
        assert s == geometry.CCD_HIT and t <= 0.25 + 1e-9  # it crosses at t = 0.25
        if thin >= 1e-8:  # bound about 3e-5 at 1e-8: the hit within 1e-2 of the crossing
            assert t > 0.24
            s, _ = _vt(at(q + [0.0, 0.0, 1e-4]), tri, at(q + [0.0, 0.3, 1e-4]), tri,
                       delta=1e-10)
            assert s == geometry.CCD_MISS
