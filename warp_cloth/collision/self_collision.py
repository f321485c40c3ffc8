"""Self-collision: the cloth's vertices against its triangles and its edges against its edges.

Per step, on the cloth's path from ``x_start`` to ``x`` (``physics.md`` 2.18-2.21):

1. **Broad phase** (`warp_cloth.collision.broadphase`): swept boxes of every triangle and edge,
   inflated by half the detection gap (the thickness, or more), in two refitted `wp.Bvh`; each
   vertex queries the triangle BVH and each edge the edge BVH with its own swept box inflated
   the same way, so no pair whose paths come within the gap is missed (their half-inflated
   boxes overlap). Topological neighbours are skipped (a vertex and its own triangles, edges that
   share a vertex), and each edge pair is tested once (the lower edge index queries).
   **Candidate lists** (BVH broad phase, ``candidate_reach``): the traversal lists its pairs
   with every box grown by a reach (the thickness by default) and the detections that
   follow test the listed pairs with their own boxes, until a vertex's path start or end
   lies farther than the reach outside the box of its build path: the element boxes of such a
   detection lie inside the build's grown boxes, so every pair whose boxes overlap was listed
   and the contacts are those of a traversal (tested). A step's solve detection, its
   response's rounds and its impact-zone passes (and PBD's detections in its iterations) then
   share one traversal, and so do steps in which the cloth moves little.
2. **Narrow phase**: the continuous vertex-triangle and edge-edge tests of
   `warp_cloth.collision.geometry` (conservative advancement in float64) with the thickness as
   minimum separation: a pair that comes within the thickness at any time of the step, or ends
   there, is a contact. Each becomes a record entry (`warp_cloth.collision.record`): the four
   vertices with weights ``(1, -b0, -b1, -b2)`` (vertex-triangle) or ``(1 - s, s, -(1 - t), -t)``
   (edge-edge), the normal from the second element to the first at the time of impact (the side
   they were on before meeting) and the thickness as offset: ``n . sum w_j x_j >= h``. A pair of
   one connected piece whose primitives lie closer than twice the thickness in the rest shape
   (a mesh with edges shorter than the thickness) keeps half its rest distance instead of the
   thickness (`rest_scale`): held to the thickness, the response stretched such short edges to
   it (823 % strain on a Delaunay sheet with 0.65 mm edges at 5 mm).
3. **Response** (Bridson et al. 2002, combined Jacobi-style with atomics): rounds of projection
   of the violated entries, each moving its vertices along ``n`` by their share
   ``w_j / m_j / sum w_k^2 / m_k`` of the violation, averaged per vertex, ``v += dx / dt``;
   then fresh detection on the corrected path, up to ``rounds`` times. Where the solver
   detected its own self-contacts with a larger gap (implicit Euler, projective dynamics:
   `SelfCollision.note_solve`), the response's detections start from those: the entries of
   vertices whose paths stay within half the gaps' difference of the solve's are tested again,
   only the pairs of the others are detected anew (`SelfCollision._reuse_or`; the same
   contacts, counted in ``self_reused``).
4. **Rigid impact zones** (`warp_cloth.collision.impact_zones`): if a path still comes within
   5 % of the thickness after the last round (all but touching: a crossing passes through zero
   distance), or a round's projection finds nothing to move while a pair's path comes that
   close (`deep_path_kernel`: its end keeps the constraint taken at the time of impact, yet
   the pair passed through; measured on the 3-sheet stack at 5 fps, a sheet that turned in
   the step ended with two edges through it and every constraint kept), the vertices of
   those contacts are merged into zones (contacts sharing a vertex),
   each zone moves rigidly over the step with its linear and angular momentum (distances inside
   it as at the start of the step, which was free of crossings; a zone that a still obstacle
   would push stays at its start, ``self_zones_held``), the paths are detected again and
   new contacts grow the zones, ``zone_passes`` times. If one still comes that close, the whole
   cloth returns to its start with zero velocity. All counted in ``stats`` (``self_zones``,
   ``self_zone_vertices``, ``self_fallback_all``, per step and summed over the run), never
   silent. An entry whose point is (nearly) a pinned vertex's (`features.pin_held`: the free
   vertices carry under 1 % of its squared weights) is not projected, since moving them cannot
   move it (the projection would throw them by the violation over their weight); a step that
   leaves one violated is counted (``self_pinned``) and reported.

No host decision: the rounds are a device-side loop and the impact zones a device-side
conditional (`SelfCollision.resolve`).

5. **Spans** (`SelfCollision.plan`, under the scene runner): the response runs once per span of
   solver steps, on the straight paths from the span's start, when some vertex has moved past
   its allowance, and at every frame's end. After each response `SelfCollision.clear` gives
   every vertex an allowance: half the least distance beyond the thickness of the non-adjacent
   pairs it belongs to (vertex-triangle and edge-edge, found within ``clearance`` thicknesses),
   at least the ``self_motion`` reach (a fraction of the thickness: of a vertex's least pair
   share of it, `rest_and_pieces`, where its pairs keep less) and at most
   ``(clearance - 1.01) / 2`` thicknesses (a
   partial pass, over the pairs of the vertices that moved, when few did). A pair
   whose vertices all stay within their allowances cannot come within the thickness, so a
   cloth clear of itself runs long spans, and the span's detection skips such pairs: only the
   vertices past their allowance query the BVHs (`active_kernel`; the BVH broad phase). A
   span's response records the pairs within the thickness plus twice the reach (projecting
   only those closer than the thickness), and until the next response `hold` projects them
   once a step: a layer approaching another is held from the step it reaches the thickness,
   not pushed back out by the next response.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..util import launch
from .broadphase import (BOX_ROUNDING, ClothBroadPhase, boxes_overlap, cloth_bounds_kernel,
                         grid_radius, padded, vertex_bounds_kernel, vertex_box)
from .features import jacobi_project_kernel, pin_held
from .impact_zones import ImpactZones
from .geometry import (CCD_MISS, ccd_edge_edge, ccd_vertex_triangle, d3, ee_distance, ee_impact,
                       vt_distance, vt_impact)
from .record import (KIND_EDGE_EDGE, KIND_VERTEX_TRIANGLE, ContactRecord, make_record,
                     record_append, record_threads)

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile

__all__ = ["SelfCollision"]

CCD_ITERATIONS = 64
#: the counters of `SelfCollision.stats`, per step (and ``*_total``: summed over all steps)
STAT_KEYS = ("self_contacts", "self_overflow", "self_zones", "self_zone_vertices",
             "self_fallback_all", "self_responses", "self_pinned", "self_zones_held",
             "self_reused", "self_diverged")
# the counters the kernels write, by name (the order of STAT_KEYS is free)
I_CONTACTS = wp.constant(STAT_KEYS.index("self_contacts"))
I_OVERFLOW = wp.constant(STAT_KEYS.index("self_overflow"))
I_RESPONSES = wp.constant(STAT_KEYS.index("self_responses"))
I_PINNED = wp.constant(STAT_KEYS.index("self_pinned"))
I_ZONES = STAT_KEYS.index("self_zones")  # the impact zones write this slot and the next
I_FALLBACK = STAT_KEYS.index("self_fallback_all")
I_FALLBACK_C = wp.constant(I_FALLBACK)
I_HELD = STAT_KEYS.index("self_zones_held")
I_REUSED = wp.constant(STAT_KEYS.index("self_reused"))
I_DIVERGED = wp.constant(STAT_KEYS.index("self_diverged"))
if STAT_KEYS[I_ZONES + 1] != "self_zone_vertices":  # pragma: no cover - a layout invariant
    raise RuntimeError("STAT_KEYS: self_zone_vertices must follow self_zones")
#: `SelfCollision.frame_end` warns (``frame_frozen``) when the rigid impact zones held this share
#: of the free vertices per response, averaged over a frame, or when this share of the frame's
#: responses returned the whole cloth to its start
FROZEN_SHARE = 0.5
#: allowances keep pairs this many thicknesses apart (1 % to spare)
CLEAR_SPARE = wp.constant(1.01)
#: spans of frames with fewer steps than this keep the reach (`SelfCollision.plan`)
ALLOWANCE_STEPS = 8
#: `SelfCollision.clear` looks at every pair again once this fraction of the vertices moved
CLEAR_FULL_FRACTION = 0.25
#: the fail-safe acts on paths that come this close (a fraction of the thickness)
FAILSAFE_GAP = 0.05
#: a response whose solve left a mesh edge stretched past this (1,000 %, the runner's default
#: strain bound) or a position not finite meets a diverged step: it returns the whole cloth to
#: its start without detecting anything (`SelfCollision.resolve`; counted as ``self_diverged``
#: and ``self_fallback_all``). Detection on such paths, metres long, lists nearly every pair of
#: the cloth: explicit Euler forced to one step a frame at 24 fps on the hanging sheet (231
#: times its stable step) took 40-100 s a frame in the rounds' and zones' detections, whose
#: rigid zones then held the exploding cloth below the strain bound, so the runner's guard
#: never saw the divergence it stops within a second without self-collision
DIVERGED_STRAIN = 10.0

#: detections that grow the rigid impact zones before the whole cloth returns to its start
#: (`SelfCollision`'s ``zone_passes``). Each pass runs only in a step whose rounds failed, and
#: the loop stops at the first detection that finds no path (a device-side loop: one
#: detection in a recorded graph). At 3, a step whose zones met new pairs on their third
#: growth sent the whole cloth back, while the pinned edges turned on: the 24 x 24 twist under
#: implicit Euler froze from frame 341 and the 16 x 16 under PD from 438, retries with 8 steps
#: a frame failing the same way; at 10 both run through all 600 frames, no crossing (122 %
#: and 135 % max strain, the twist's own)
ZONE_PASSES = 10
_DEEP = wp.constant(FAILSAFE_GAP)
#: vertices of the rest mesh closer than this share of the thickness (and not the same vertex)
#: are refused: a seam written twice (`SelfCollision`); they would start inside every gap
COINCIDENT = 1.0e-3
#: `SelfCollision._reuse_or`: the share of the allowance ``(g_s - g) / 2`` left for
#: rounding (positions are float32, the tests' distances float64)
SOLVE_ALLOW_MARGIN = 1.0e-3
#: ... and the share of the vertices that may be far from the solve's paths (their pairs
#: detected by the BVHs) for the solve's detection to be reused
SOLVE_MOST_FAR = 0.1
#: a pair closer than twice the thickness in the rest shape keeps this share of its rest
#: distance instead of the thickness (`rest_scale`)
REST_SHARE = wp.constant(0.5)


@wp.func
def vt_ids(v: int, t: int, tris: wp.array2d(dtype=wp.int32), inv_mass: wp.array(dtype=float)):
    """Triangle ``t``'s corners, and whether ``(v, t)`` is a pair at all: not when ``v`` is a
    corner (adjacent) or all four vertices are pinned."""
    ia = tris[t, 0]
    ib = tris[t, 1]
    ic = tris[t, 2]
    ok = not (ia == v or ib == v or ic == v)
    if inv_mass[v] + inv_mass[ia] + inv_mass[ib] + inv_mass[ic] == 0.0:
        ok = False
    return ia, ib, ic, ok


@wp.func
def ee_ids(e: int, f: int, edges: wp.array2d(dtype=wp.int32), inv_mass: wp.array(dtype=float)):
    """The two edges' vertices, and whether ``(e, f)`` is a pair at all: not when they share a
    vertex or all four are pinned."""
    ia = edges[e, 0]
    ib = edges[e, 1]
    ic = edges[f, 0]
    id = edges[f, 1]
    ok = not (ic == ia or ic == ib or id == ia or id == ib)
    if inv_mass[ia] + inv_mass[ib] + inv_mass[ic] + inv_mass[id] == 0.0:
        ok = False
    return ia, ib, ic, id, ok


@wp.func
def rest_scale(d_rest: wp.float64, h: float):
    """The share of the thickness ``h`` kept by a pair of one connected piece of cloth whose
    primitives lie ``d_rest`` apart in the rest shape: ``min(1, REST_SHARE d_rest / h)``. A mesh
    whose edges are shorter than the thickness has such pairs closer than it at rest without
    touching (a vertex and a triangle a ring or two away on a flat sheet); held to the full
    thickness, the response stretched the short edges to it (a Delaunay sheet with 0.65 mm
    edges: 823 % strain in 10 frames at 5 mm). Such a pair keeps half its rest distance
    instead; a pair at least twice the thickness apart at rest (every pair of the built-in
    scenes' grids) keeps the thickness, and so does every pair of two separate pieces (their
    rest placement is not a shape: `SelfCollision.rest`)."""
    share = float(1.0)
    if h > 0.0:
        share = wp.min(share, REST_SHARE * float(d_rest) / h)
    return share


@wp.func
def shared_gap(gap: float, sep: float, share: float):
    """A detection distance ``gap`` for a pair that keeps ``share`` of the thickness ``sep``:
    the part of ``gap`` up to the thickness scales with it (the fail-safe's 5 % of the thickness
    stays 5 % of the pair's), a margin beyond it does not (the spans' reach, whose pairs `hold`
    keeps apart, and the solve's margin are distances the vertices move, whatever the pair)."""
    return share * wp.min(gap, sep) + wp.max(gap - sep, 0.0)


@wp.func
def rest_point(rest: wp.array(dtype=wp.vec4), i: int):
    r = rest[i]
    return wp.vec3d(wp.float64(r[0]), wp.float64(r[1]), wp.float64(r[2]))


@wp.func
def vt_rest_scale(v: int, ia: int, ib: int, ic: int, rest: wp.array(dtype=wp.vec4), h: float):
    """`rest_scale` of a vertex-triangle pair (1 across separate pieces, and when ``v`` has no
    pair close at rest: `rest_and_pieces`)."""
    if rest[v][3] < 0.0 or rest[v][3] != rest[ia][3]:
        return float(1.0)
    return rest_scale(vt_distance(rest_point(rest, v), rest_point(rest, ia),
                                  rest_point(rest, ib), rest_point(rest, ic)), h)


@wp.func
def ee_rest_scale(ia: int, ib: int, ic: int, id: int, rest: wp.array(dtype=wp.vec4), h: float):
    """`rest_scale` of an edge-edge pair (1 across separate pieces, and when ``ia`` has no pair
    close at rest)."""
    if rest[ia][3] < 0.0 or rest[ia][3] != rest[ic][3]:
        return float(1.0)
    return rest_scale(ee_distance(rest_point(rest, ia), rest_point(rest, ib),
                                  rest_point(rest, ic), rest_point(rest, id)), h)


@wp.func
def vt_pair(v: int, t: int, x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
            tris: wp.array2d(dtype=wp.int32), gap: float, sep: float,
            inv_mass: wp.array(dtype=float), rest: wp.array(dtype=wp.vec4), rec: ContactRecord,
            pairs: wp.array(dtype=wp.vec2i), npairs: wp.array(dtype=int)):
    """Vertex ``v`` against triangle ``t`` (a broad-phase candidate): skipped when ``v`` is one
    of its corners or all four are pinned; with a ``pairs`` buffer the pair is only listed
    (broad-phase tests), else the continuous test appends a contact."""
    ia, ib, ic, ok = vt_ids(v, t, tris, inv_mass)
    if not ok:
        return
    if pairs.shape[0] > 0:
        k = wp.atomic_add(npairs, 0, 1)
        if k < pairs.shape[0]:
            pairs[k] = wp.vec2i(v, t)
        return
    vt_test(v, ia, ib, ic, x0, x1, gap, sep, rest, rec)


@wp.func
def vt_test(v: int, ia: int, ib: int, ic: int, x0: wp.array(dtype=wp.vec3),
            x1: wp.array(dtype=wp.vec3), gap: float, sep: float, rest: wp.array(dtype=wp.vec4),
            rec: ContactRecord):
    """`vt_pair`'s continuous test of vertex ``v`` against the triangle ``ia ib ic``."""
    a0 = x0[v]
    a1 = x1[v]
    s, toi = ccd_vertex_triangle(d3(a0), d3(x0[ia]), d3(x0[ib]), d3(x0[ic]), d3(a1),
                                 d3(x1[ia]), d3(x1[ib]), d3(x1[ic]), wp.float64(gap),
                                 CCD_ITERATIONS)
    if s == CCD_MISS:
        return
    # a pair close in the rest shape keeps less (`rest_scale`): tested again with its share
    # (a miss at the full gap is a miss at any smaller one, so only hits pay for this)
    share = vt_rest_scale(v, ia, ib, ic, rest, sep)
    if share < 1.0:
        s, toi = ccd_vertex_triangle(d3(a0), d3(x0[ia]), d3(x0[ib]), d3(x0[ic]), d3(a1),
                                     d3(x1[ia]), d3(x1[ib]), d3(x1[ic]),
                                     wp.float64(shared_gap(gap, sep, share)), CCD_ITERATIONS)
        if s == CCD_MISS:
            return
        # the margin is many times such a pair's own thickness: it enters the gap long before
        # it could touch, and the closest points there are not where it meets. When it comes
        # within its own thickness on the path, the entry is taken at that time instead
        s2, t2 = ccd_vertex_triangle(d3(a0), d3(x0[ia]), d3(x0[ib]), d3(x0[ic]), d3(a1),
                                     d3(x1[ia]), d3(x1[ib]), d3(x1[ic]),
                                     wp.float64(share * sep), CCD_ITERATIONS)
        if s2 != CCD_MISS:
            toi = t2
    n, bw, ok = vt_impact(a0, a1, x0[ia], x1[ia], x0[ib], x1[ib], x0[ic], x1[ic], toi)
    if not ok:
        return
    w = wp.vec4(1.0, -bw[0], -bw[1], -bw[2])
    record_append(rec, KIND_VERTEX_TRIANGLE, wp.vec4i(v, ia, ib, ic), w, n, share * sep,
                  wp.vec3(0.0), 0.0, 0.0, -1)


@wp.func
def ee_pair(e: int, f: int, x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
            edges: wp.array2d(dtype=wp.int32), gap: float, sep: float,
            inv_mass: wp.array(dtype=float), rest: wp.array(dtype=wp.vec4), rec: ContactRecord,
            pairs: wp.array(dtype=wp.vec2i), npairs: wp.array(dtype=int)):
    """Edge ``e`` against edge ``f > e`` (a candidate): skipped when they share a vertex or all
    four are pinned; listed or tested as `vt_pair`."""
    if f <= e:
        return
    ia, ib, ic, id, ok = ee_ids(e, f, edges, inv_mass)
    if not ok:
        return
    if pairs.shape[0] > 0:
        k = wp.atomic_add(npairs, 0, 1)
        if k < pairs.shape[0]:
            pairs[k] = wp.vec2i(e, f)
        return
    ee_test(ia, ib, ic, id, x0, x1, gap, sep, rest, rec)


@wp.func
def ee_test(ia: int, ib: int, ic: int, id: int, x0: wp.array(dtype=wp.vec3),
            x1: wp.array(dtype=wp.vec3), gap: float, sep: float, rest: wp.array(dtype=wp.vec4),
            rec: ContactRecord):
    """`ee_pair`'s continuous test of the edges ``ia ib`` and ``ic id``."""
    s, toi = ccd_edge_edge(d3(x0[ia]), d3(x0[ib]), d3(x0[ic]), d3(x0[id]), d3(x1[ia]),
                           d3(x1[ib]), d3(x1[ic]), d3(x1[id]), wp.float64(gap), CCD_ITERATIONS)
    if s == CCD_MISS:
        return
    share = ee_rest_scale(ia, ib, ic, id, rest, sep)  # as in `vt_pair`
    if share < 1.0:
        s, toi = ccd_edge_edge(d3(x0[ia]), d3(x0[ib]), d3(x0[ic]), d3(x0[id]), d3(x1[ia]),
                               d3(x1[ib]), d3(x1[ic]), d3(x1[id]),
                               wp.float64(shared_gap(gap, sep, share)), CCD_ITERATIONS)
        if s == CCD_MISS:
            return
        s2, t2 = ccd_edge_edge(d3(x0[ia]), d3(x0[ib]), d3(x0[ic]), d3(x0[id]), d3(x1[ia]),
                               d3(x1[ib]), d3(x1[ic]), d3(x1[id]), wp.float64(share * sep),
                               CCD_ITERATIONS)
        if s2 != CCD_MISS:  # at the time it comes within its own thickness (`vt_pair`)
            toi = t2
    n, s1, t1, ok = ee_impact(x0[ia], x1[ia], x0[ib], x1[ib], x0[ic], x1[ic], x0[id], x1[id], toi)
    if not ok:
        return
    w = wp.vec4(1.0 - s1, s1, -(1.0 - t1), -t1)
    record_append(rec, KIND_EDGE_EDGE, wp.vec4i(ia, ib, ic, id), w, n, share * sep, wp.vec3(0.0),
                  0.0, 0.0, -1)


@wp.func
def edge_box(x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
             edges: wp.array2d(dtype=wp.int32), e: int, pad: float):
    """Edge ``e``'s swept box, inflated by ``pad`` (`padded`)."""
    ia = edges[e, 0]
    ib = edges[e, 1]
    return padded(wp.min(wp.min(x0[ia], x1[ia]), wp.min(x0[ib], x1[ib])),
                  wp.max(wp.max(x0[ia], x1[ia]), wp.max(x0[ib], x1[ib])), pad)


@wp.kernel
def self_vt_bvh_kernel(bvh: wp.uint64, x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
                       tris: wp.array2d(dtype=wp.int32), gap: float, sep: float,
                       inv_mass: wp.array(dtype=float),
                       rest: wp.array(dtype=wp.vec4), done: wp.array(dtype=int),
                       active: wp.array(dtype=int), rec: ContactRecord,
                       pairs: wp.array(dtype=wp.vec2i), npairs: wp.array(dtype=int)):
    """Vertex ``v`` against the triangles whose swept box meets its own (BVH); nothing once
    ``done[0]``. With an ``active`` set (`active_kernel`), only an active vertex queries (the
    pairs of an inactive vertex with a triangle that has an active corner: `self_tv_bvh_kernel`)."""
    v = wp.tid()
    if done[0] != 0:
        return
    if active.shape[0] > 0:
        if active[v] == 0:
            return
    lo, hi = vertex_box(x0, x1, v, 0.5 * gap)  # `_query`
    q = wp.bvh_query_aabb(bvh, lo, hi)
    t = int(0)
    while wp.bvh_query_next(q, t):
        vt_pair(v, t, x0, x1, tris, gap, sep, inv_mass, rest, rec, pairs, npairs)


#: candidate lists (`SelfCollision`'s ``candidate_reach``): a list built from the BVHs serves
#: every later detection whose path ends (start and end) stay within this many thicknesses of
#: the build's, per axis
CANDIDATE_REACH = 1.0
#: ... with room for this many pairs per vertex (vertex-triangle) and per edge (edge-edge); a
#: build that needs more grows the lists at the frame's end and detects by the BVHs meanwhile
CANDIDATE_ROOM = 24


@wp.func
def any_active(active: wp.array(dtype=int), a: int, b: int, c: int, d: int):
    """No ``active`` set (empty), or one of the four vertices in it."""
    if active.shape[0] == 0:
        return True
    return active[a] + active[b] + active[c] + active[d] != 0


@wp.kernel
def cand_begin_kernel(gap: float, built_gap: wp.array(dtype=float),
                      flags: wp.array(dtype=int)):
    """A detection with candidate lists starts: rebuild (``flags[0]``) unless they were built
    (``built_gap[0] >= 0``) for at least this ``gap``."""
    flags[0] = wp.where(built_gap[0] < 0.0 or gap > built_gap[0], 1, 0)


@wp.kernel
def cand_check_kernel(x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
                      b0: wp.array(dtype=wp.vec3), b1: wp.array(dtype=wp.vec3), reach: float,
                      flags: wp.array(dtype=int)):
    """``flags[0] = 1`` (rebuild) when vertex ``i``'s start or end lies outside the box of its
    build path (start and end) grown by ``reach``, less a float32 rounding allowance: inside
    it, every swept box of this detection lies inside the build's boxes grown by ``reach``
    (a span's path from its start and the steps' paths inside it share one build)."""
    i = wp.tid()
    p = x0[i]
    r = x1[i]
    lo = wp.min(b0[i], b1[i])
    hi = wp.max(b0[i], b1[i])
    far = False
    for k in range(3):
        slack = 4.0 * BOX_ROUNDING * (wp.abs(p[k]) + wp.abs(r[k]) + wp.abs(lo[k]) + wp.abs(hi[k]))
        if (p[k] < lo[k] - reach + slack or p[k] > hi[k] + reach - slack
                or r[k] < lo[k] - reach + slack or r[k] > hi[k] + reach - slack):
            far = True
    if far:
        flags[0] = 1


@wp.kernel
def cand_built_kernel(n: wp.array(dtype=int), cap_vt: int, cap_ee: int, gap: float,
                      built_gap: wp.array(dtype=float), flags: wp.array(dtype=int),
                      stats: wp.array(dtype=int)):
    """After a build: the lists hold every pair (``flags[1]``: use them, ``built_gap[0]``:
    the gap they serve) or one overflowed (``flags[2]``: detect by the BVHs; ``built_gap[0]``
    -1 so the next detection builds again; ``stats[1]`` counts it, ``stats[2]`` keeps the
    most pairs asked for, ``stats[3]`` the most edge pairs). ``stats[0]`` counts builds."""
    stats[0] = stats[0] + 1
    if n[0] > cap_vt or n[1] > cap_ee:
        flags[1] = 0
        flags[2] = 1
        built_gap[0] = -1.0
        stats[1] = stats[1] + 1
    else:
        flags[1] = 1
        flags[2] = 0
        built_gap[0] = gap
    stats[2] = wp.max(stats[2], n[0])
    stats[3] = wp.max(stats[3], n[1])


@wp.kernel
def cand_use_kernel(flags: wp.array(dtype=int)):
    """No rebuild needed: use the lists."""
    if flags[0] == 0:
        flags[1] = 1
        flags[2] = 0


@wp.kernel
def vt_list_kernel(pairs: wp.array(dtype=wp.vec2i), n: wp.array(dtype=int),
                   lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3),
                   x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
                   tris: wp.array2d(dtype=wp.int32), gap: float, sep: float,
                   inv_mass: wp.array(dtype=float), rest: wp.array(dtype=wp.vec4),
                   done: wp.array(dtype=int), active: wp.array(dtype=int), rec: ContactRecord,
                   no_pairs: wp.array(dtype=wp.vec2i), npairs: wp.array(dtype=int),
                   num_threads: int):
    """The listed vertex-triangle pairs whose swept boxes, inflated by ``gap / 2``, overlap
    (the BVH query's own test: the same candidates), with an active vertex when an ``active``
    set is given, tested as `self_vt_bvh_kernel` does."""
    t0 = wp.tid()
    if done[0] != 0:
        return
    count = wp.min(n[0], pairs.shape[0])
    for q in range(t0, count, num_threads):
        p = pairs[q]
        v = p[0]
        t = p[1]
        if any_active(active, v, tris[t, 0], tris[t, 1], tris[t, 2]):
            lo, hi = vertex_box(x0, x1, v, 0.5 * gap)
            if boxes_overlap(lo, hi, lowers[t], uppers[t]):
                vt_pair(v, t, x0, x1, tris, gap, sep, inv_mass, rest, rec, no_pairs, npairs)


@wp.kernel
def ee_list_kernel(pairs: wp.array(dtype=wp.vec2i), n: wp.array(dtype=int),
                   lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3),
                   x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
                   edges: wp.array2d(dtype=wp.int32), gap: float, sep: float,
                   inv_mass: wp.array(dtype=float), rest: wp.array(dtype=wp.vec4),
                   done: wp.array(dtype=int), active: wp.array(dtype=int), rec: ContactRecord,
                   no_pairs: wp.array(dtype=wp.vec2i), npairs: wp.array(dtype=int),
                   num_threads: int):
    """The listed edge-edge pairs as `vt_list_kernel` (`self_ee_bvh_kernel`'s test)."""
    t0 = wp.tid()
    if done[0] != 0:
        return
    count = wp.min(n[1], pairs.shape[0])
    for q in range(t0, count, num_threads):
        p = pairs[q]
        e = p[0]
        f = p[1]
        if boxes_overlap(lowers[e], uppers[e], lowers[f], uppers[f]):
            if any_active(active, edges[e, 0], edges[e, 1], edges[f, 0], edges[f, 1]):
                ee_pair(e, f, x0, x1, edges, gap, sep, inv_mass, rest, rec, no_pairs, npairs)


@wp.kernel
def self_tv_bvh_kernel(vbvh: wp.uint64, lowers: wp.array(dtype=wp.vec3),
                       uppers: wp.array(dtype=wp.vec3), x0: wp.array(dtype=wp.vec3),
                       x1: wp.array(dtype=wp.vec3), tris: wp.array2d(dtype=wp.int32),
                       gap: float, sep: float, inv_mass: wp.array(dtype=float),
                       rest: wp.array(dtype=wp.vec4),
                       done: wp.array(dtype=int), active: wp.array(dtype=int),
                       rec: ContactRecord, pairs: wp.array(dtype=wp.vec2i),
                       npairs: wp.array(dtype=int)):
    """Triangle ``t`` with an active corner against the inactive vertices whose swept box meets
    its own (the broad phase's, ``lowers`` / ``uppers``; the vertices' BVH): the
    vertex-triangle pairs `self_vt_bvh_kernel` leaves out."""
    t = wp.tid()
    if done[0] != 0:
        return
    if active[tris[t, 0]] + active[tris[t, 1]] + active[tris[t, 2]] == 0:
        return
    q = wp.bvh_query_aabb(vbvh, lowers[t], uppers[t])
    v = int(0)
    while wp.bvh_query_next(q, v):
        if active[v] == 0:
            vt_pair(v, t, x0, x1, tris, gap, sep, inv_mass, rest, rec, pairs, npairs)


@wp.kernel
def active_kernel(x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
                  allow: wp.array(dtype=float), slack: float, active: wp.array(dtype=int)):
    """A vertex is active once it is farther from its start than its allowance
    (`SelfCollision.clear`) less ``slack``: a pair none of whose vertices is active cannot come
    within the thickness plus ``2 slack`` on the straight paths, so detection with that gap
    skips it."""
    i = wp.tid()
    d = x1[i] - x0[i]
    a = allow[i] - slack
    active[i] = 0
    if a < 0.0 or wp.dot(d, d) > a * a:
        active[i] = 1


@wp.kernel
def self_vt_grid_kernel(grid: wp.uint64, lowers: wp.array(dtype=wp.vec3),
                        uppers: wp.array(dtype=wp.vec3), rmax: wp.array(dtype=float),
                        x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
                        tris: wp.array2d(dtype=wp.int32), gap: float, sep: float,
                        inv_mass: wp.array(dtype=float),
                        rest: wp.array(dtype=wp.vec4), done: wp.array(dtype=int),
                        rec: ContactRecord, pairs: wp.array(dtype=wp.vec2i),
                        npairs: wp.array(dtype=int)):
    """Vertex ``v`` against the triangles whose swept box meets its own (hash grid of box
    centres, `warp_cloth.collision.broadphase`); nothing once ``done[0]``."""
    v = wp.tid()
    if done[0] != 0:
        return
    lo, hi = vertex_box(x0, x1, v, 0.5 * gap)  # `_query`
    c = 0.5 * (lo + hi)
    q = wp.hash_grid_query(grid, c, grid_radius(c, 0.5 * wp.length(hi - lo), rmax[0]))
    t = int(0)
    while wp.hash_grid_query_next(q, t):
        if boxes_overlap(lo, hi, lowers[t], uppers[t]):
            vt_pair(v, t, x0, x1, tris, gap, sep, inv_mass, rest, rec, pairs, npairs)


@wp.kernel
def self_ee_bvh_kernel(bvh: wp.uint64, x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
                       edges: wp.array2d(dtype=wp.int32), gap: float, sep: float,
                       inv_mass: wp.array(dtype=float),
                       rest: wp.array(dtype=wp.vec4), done: wp.array(dtype=int),
                       active: wp.array(dtype=int), rec: ContactRecord,
                       pairs: wp.array(dtype=wp.vec2i), npairs: wp.array(dtype=int)):
    """Edge ``e`` against the edges of higher index whose swept box meets its own (BVH);
    nothing once ``done[0]``. With an ``active`` set, only an edge with an active vertex
    queries, and it also takes the lower edges that have none."""
    e = wp.tid()
    if done[0] != 0:
        return
    some = active.shape[0] > 0
    if some:
        if active[edges[e, 0]] + active[edges[e, 1]] == 0:
            return
    lo, hi = edge_box(x0, x1, edges, e, 0.5 * gap)  # `_query`
    q = wp.bvh_query_aabb(bvh, lo, hi)
    f = int(0)
    while wp.bvh_query_next(q, f):
        if f > e:
            ee_pair(e, f, x0, x1, edges, gap, sep, inv_mass, rest, rec, pairs, npairs)
        elif some:  # a lower edge with no active vertex does not query: this pair is ours
            if active[edges[f, 0]] + active[edges[f, 1]] == 0:
                ee_pair(f, e, x0, x1, edges, gap, sep, inv_mass, rest, rec, pairs, npairs)


@wp.kernel
def self_ee_grid_kernel(grid: wp.uint64, lowers: wp.array(dtype=wp.vec3),
                        uppers: wp.array(dtype=wp.vec3), rmax: wp.array(dtype=float),
                        x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
                        edges: wp.array2d(dtype=wp.int32), gap: float, sep: float,
                        inv_mass: wp.array(dtype=float),
                        rest: wp.array(dtype=wp.vec4), done: wp.array(dtype=int),
                        rec: ContactRecord, pairs: wp.array(dtype=wp.vec2i),
                        npairs: wp.array(dtype=int)):
    """Edge ``e`` against the edges of higher index whose swept box meets its own (hash grid);
    nothing once ``done[0]``."""
    e = wp.tid()
    if done[0] != 0:
        return
    lo, hi = edge_box(x0, x1, edges, e, 0.5 * gap)  # `_query`
    c = 0.5 * (lo + hi)
    q = wp.hash_grid_query(grid, c, grid_radius(c, 0.5 * wp.length(hi - lo), rmax[1]))
    f = int(0)
    while wp.hash_grid_query_next(q, f):
        if f > e and boxes_overlap(lo, hi, lowers[f], uppers[f]):
            ee_pair(e, f, x0, x1, edges, gap, sep, inv_mass, rest, rec, pairs, npairs)


@wp.kernel
def revert_kernel(rec: ContactRecord, x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
                  x_start: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float),
                  stats: wp.array(dtype=int), slot: int, num_threads: int):
    """Last resort, once any entry remains: every free vertex back at its start position with
    zero velocity (``stats[slot]`` += 1)."""
    t = wp.tid()
    if rec.count[0] == 0:
        return
    for i in range(t, x.shape[0], num_threads):
        if inv_mass[i] > 0.0:
            x[i] = x_start[i]
            v[i] = wp.vec3(0.0)
    if t == 0:
        stats[slot] = stats[slot] + 1


@wp.kernel
def diverged_kernel(x: wp.array(dtype=wp.vec3), edges: wp.array(dtype=wp.int32, ndim=2),
                    rest: wp.array(dtype=wp.vec4), bound: float, flag: wp.array(dtype=int)):
    """``flag[0] = 1`` where a mesh edge is longer than ``1 + bound`` times its rest length or
    not finite (`DIVERGED_STRAIN`)."""
    e = wp.tid()
    a = edges[e, 0]
    b = edges[e, 1]
    ra = rest[a]
    rb = rest[b]
    r = wp.length(wp.vec3(ra[0] - rb[0], ra[1] - rb[1], ra[2] - rb[2]))
    d = wp.length(x[a] - x[b])
    if not (d <= (1.0 + bound) * r):  # (a NaN fails every comparison)
        flag[0] = 1


@wp.kernel
def revert_all_kernel(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
                      x_start: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float),
                      stats: wp.array(dtype=int)):
    """A diverged step (`diverged_kernel`): every free vertex back at its start with zero
    velocity, counted as a whole-cloth fall-back and as diverged."""
    i = wp.tid()
    if inv_mass[i] > 0.0:
        x[i] = x_start[i]
        v[i] = wp.vec3(0.0)
    if i == 0:
        stats[I_FALLBACK_C] = stats[I_FALLBACK_C] + 1
        stats[I_DIVERGED] = stats[I_DIVERGED] + 1


#: the self-contacts' velocity rule's frame before any entry is projected (`layer_apply`)
_NO_FRAME = -1.0e30
NO_FRAME = wp.constant(_NO_FRAME)


@wp.func
def layer_apply(i: int, x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
                acc: wp.array(dtype=wp.vec3), cnt: wp.array(dtype=int),
                frame: wp.array(dtype=float)):
    """``x += d`` (``d = acc / cnt``, the Jacobi average) and the self-contacts' velocity rule:
    along ``u = d / |d|`` the vertex's velocity ``a = v . u`` becomes ``max(a, min(b, 0))``,
    ``b`` (``frame``) the largest velocity of its entries' other sides along their pushes on
    it (`features.side_normal_velocities`). It loses its approach to the layers it met, measured
    in their motion, and never more than its approach to a world at rest (``b > 0``, the
    other side pushing it, adds nothing); a vertex moving along ``u`` keeps its velocity.
    ``|a|`` never grows: the rule adds no kinetic energy. Clears the accumulators.

    Two sheets meeting while both fall: the upper one takes the lower one's fall (the rule
    before took the approach against a world at rest, ``max(a, 0)``, and stopped the upper
    sheet's fall in mid-air: a folded sheet dropped from 4 m slowed from 4.8 to 1.35 m/s); a
    layer resting on one the floor holds (``b`` about 0) stops as before; two layers meeting
    head on both stop (each one's ``b`` points away from it). The largest ``b``, not a mean:
    with the mean of the other sides' velocities taken along the averaged push, the folded
    sheet's stacked hinge layers (PBD, 16 x 16) passed a downward velocity round and pressed
    into each other at 0.024 m/s for good (the mean of each entry's ``b``: 0.006 m/s; the
    largest: 0.001-0.003). ``frame`` at `NO_FRAME` (no velocities given: `layer_frames`
    False) measures the approach against a world at rest, the rule before."""
    c = cnt[i]
    if c > 0:
        d = acc[i] / float(c)
        x[i] = x[i] + d
        l = wp.length(d)
        if l > 0.0:
            u = d / l
            a = wp.dot(v[i], u)
            b = float(0.0)  # no frame (`NO_FRAME`): a world at rest
            if frame[i] > NO_FRAME:
                b = wp.min(frame[i], 0.0)
            if a < b:
                v[i] = v[i] + (b - a) * u
        acc[i] = wp.vec3(0.0)
        cnt[i] = 0
    frame[i] = NO_FRAME


@wp.kernel
def layer_apply_kernel(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
                       acc: wp.array(dtype=wp.vec3), cnt: wp.array(dtype=int),
                       frame: wp.array(dtype=float)):
    layer_apply(wp.tid(), x, v, acc, cnt, frame)


@wp.kernel
def span_begin_kernel(x: wp.array(dtype=wp.vec3), start: wp.array(dtype=wp.vec3),
                      steps: wp.array(dtype=int), flag: wp.array(dtype=int),
                      frame_k: wp.array(dtype=int)):
    """A self-collision span (`SelfCollision.plan`) starts at ``x``: no step taken, no response
    due; only at a frame's first step if ``frame_k`` (the frame's steps taken) is given."""
    i = wp.tid()
    if frame_k.shape[0] > 0:
        if frame_k[0] != 0:
            return
    start[i] = x[i]
    if i == 0:
        steps[0] = 0
        flag[0] = 0


@wp.kernel
def span_step_kernel(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
                     acc: wp.array(dtype=wp.vec3), cnt: wp.array(dtype=int),
                     frame: wp.array(dtype=float), start: wp.array(dtype=wp.vec3), reach: float,
                     reach_share: wp.array(dtype=float), allow: wp.array(dtype=float),
                     frame_k: wp.array(dtype=int), frame_steps: int,
                     steps: wp.array(dtype=int), flag: wp.array(dtype=int)):
    """One more step in the span: the held contacts' correction applied (`SelfCollision.hold`),
    then the response is due (``flag``) on the frame's last step (``frame_k``: the frame's
    steps taken, counted here on the device, back to 0 after ``frame_steps``) or once a vertex
    is farther from its start of the span than its allowance (``allow``, at least ``reach``:
    one launch for both)."""
    i = wp.tid()
    layer_apply(i, x, v, acc, cnt, frame)
    if i == 0:
        steps[0] = steps[0] + 1
        k = frame_k[0] + 1
        if k >= frame_steps:
            flag[0] = 1
            k = 0
        frame_k[0] = k
    d = x[i] - start[i]
    a = wp.max(reach * reach_share[i], allow[i])
    if wp.dot(d, d) > a * a:
        flag[0] = 1


@wp.kernel
def fill_kernel(a: wp.array(dtype=float), value: float):
    a[wp.tid()] = value


@wp.func
def clearance_share(d: float, h: float, i0: int, i1: int, i2: int, i3: int,
                    allow: wp.array(dtype=float)):
    # a pair at distance d: each of its vertices may move (d - h) / 2 and the pair stays h apart
    a = 0.5 * (d - CLEAR_SPARE * h)
    wp.atomic_min(allow, i0, a)
    wp.atomic_min(allow, i1, a)
    wp.atomic_min(allow, i2, a)
    wp.atomic_min(allow, i3, a)


@wp.func
def clearance_vt_pair(v: int, t: int, x: wp.array(dtype=wp.vec3),
                      tris: wp.array2d(dtype=wp.int32), inv_mass: wp.array(dtype=float),
                      rest: wp.array(dtype=wp.vec4),
                      h: float, allow: wp.array(dtype=float)):
    ia, ib, ic, ok = vt_ids(v, t, tris, inv_mass)
    if not ok:
        return
    d = float(vt_distance(d3(x[v]), d3(x[ia]), d3(x[ib]), d3(x[ic])))
    clearance_share(d, vt_rest_scale(v, ia, ib, ic, rest, h) * h, v, ia, ib, ic, allow)


@wp.kernel
def clearance_vt_kernel(bvh: wp.uint64, x: wp.array(dtype=wp.vec3),
                        tris: wp.array2d(dtype=wp.int32), inv_mass: wp.array(dtype=float),
                        rest: wp.array(dtype=wp.vec4),
                        half: float, h: float, moved: wp.array(dtype=int),
                        allow: wp.array(dtype=float)):
    """Vertex ``v`` against the triangles within ``2 half`` (boxes inflated by ``half`` each):
    the allowance of the four vertices of each such pair lowered to half its distance beyond
    ``h`` (`SelfCollision.clear`). With a ``moved`` set, only the moved vertices."""
    v = wp.tid()
    if moved.shape[0] > 0:
        if moved[v] == 0:
            return
    p = x[v]
    q = wp.bvh_query_aabb(bvh, p - wp.vec3(half), p + wp.vec3(half))
    t = int(0)
    while wp.bvh_query_next(q, t):
        clearance_vt_pair(v, t, x, tris, inv_mass, rest, h, allow)


@wp.kernel
def clearance_tv_kernel(vbvh: wp.uint64, lowers: wp.array(dtype=wp.vec3),
                        uppers: wp.array(dtype=wp.vec3), x: wp.array(dtype=wp.vec3),
                        tris: wp.array2d(dtype=wp.int32), inv_mass: wp.array(dtype=float),
                        rest: wp.array(dtype=wp.vec4),
                        h: float, moved: wp.array(dtype=int), allow: wp.array(dtype=float)):
    """Triangle ``t`` with a moved corner (its box inflated by half the clearance, ``lowers`` /
    ``uppers``) against the vertices that did not move within the clearance (the vertices'
    BVH): the pairs `clearance_vt_kernel` leaves out."""
    t = wp.tid()
    if moved[tris[t, 0]] + moved[tris[t, 1]] + moved[tris[t, 2]] == 0:
        return
    q = wp.bvh_query_aabb(vbvh, lowers[t], uppers[t])
    v = int(0)
    while wp.bvh_query_next(q, v):
        if moved[v] == 0:
            clearance_vt_pair(v, t, x, tris, inv_mass, rest, h, allow)


@wp.func
def clearance_ee_pair(e: int, f: int, x: wp.array(dtype=wp.vec3),
                      edges: wp.array2d(dtype=wp.int32), inv_mass: wp.array(dtype=float),
                      rest: wp.array(dtype=wp.vec4),
                      h: float, allow: wp.array(dtype=float)):
    ia, ib, ic, id, ok = ee_ids(e, f, edges, inv_mass)
    if not ok:
        return
    d = float(ee_distance(d3(x[ia]), d3(x[ib]), d3(x[ic]), d3(x[id])))
    clearance_share(d, ee_rest_scale(ia, ib, ic, id, rest, h) * h, ia, ib, ic, id, allow)


@wp.kernel
def clearance_ee_kernel(bvh: wp.uint64, x: wp.array(dtype=wp.vec3),
                        edges: wp.array2d(dtype=wp.int32), inv_mass: wp.array(dtype=float),
                        rest: wp.array(dtype=wp.vec4),
                        lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3),
                        h: float, moved: wp.array(dtype=int), allow: wp.array(dtype=float)):
    """Edge ``e`` against the edges of higher index within reach (`clearance_vt_kernel`); with
    a ``moved`` set, only an edge with a moved vertex, which also takes the lower edges that
    have none."""
    e = wp.tid()
    some = moved.shape[0] > 0
    if some:
        if moved[edges[e, 0]] + moved[edges[e, 1]] == 0:
            return
    q = wp.bvh_query_aabb(bvh, lowers[e], uppers[e])
    f = int(0)
    while wp.bvh_query_next(q, f):
        if f > e:
            clearance_ee_pair(e, f, x, edges, inv_mass, rest, h, allow)
        elif some:
            if moved[edges[f, 0]] + moved[edges[f, 1]] == 0:
                clearance_ee_pair(f, e, x, edges, inv_mass, rest, h, allow)


@wp.kernel
def clearance_moved_kernel(x: wp.array(dtype=wp.vec3), ref: wp.array(dtype=wp.vec3),
                           tau: float, fraction: float, moved: wp.array(dtype=int),
                           still: wp.array(dtype=float), count: wp.array(dtype=int),
                           full: wp.array(dtype=int)):
    """Against the last full pass (positions ``ref``): a vertex moved once farther than
    ``tau``; ``still[0]``: the farthest any other vertex went; a full pass is due (``full``)
    once more than ``fraction`` of the vertices moved, or when ``full`` was already set."""
    i = wp.tid()
    d = x[i] - ref[i]
    moved[i] = 0
    l2 = wp.dot(d, d)
    if l2 > tau * tau:
        moved[i] = 1
        c = wp.atomic_add(count, 0, 1)
        if float(c + 1) > fraction * float(x.shape[0]):
            full[0] = 1
    else:
        wp.atomic_max(still, 0, wp.sqrt(l2))


@wp.kernel
def clearance_start_kernel(allow_ref: wp.array(dtype=float), still: wp.array(dtype=float),
                           allow: wp.array(dtype=float)):
    """A pair none of whose vertices moved is at most ``2 still`` closer than at the last full
    pass: its vertices keep that pass's allowance less ``still``."""
    i = wp.tid()
    allow[i] = allow_ref[i] - still[0]


@wp.kernel
def clearance_keep_kernel(x: wp.array(dtype=wp.vec3), allow: wp.array(dtype=float),
                          ref: wp.array(dtype=wp.vec3), allow_ref: wp.array(dtype=float),
                          full: wp.array(dtype=int)):
    """After a full pass: its positions and allowances are the reference of the next ones (and
    no full pass is forced any more)."""
    i = wp.tid()
    ref[i] = x[i]
    allow_ref[i] = allow[i]
    if i == 0:
        full[0] = 0


@wp.kernel
def accumulate_kernel(counters: wp.array(dtype=int), totals: wp.array(dtype=int)):
    i = wp.tid()
    totals[i] = totals[i] + counters[i]


@wp.kernel
def deep_path_kernel(rec: ContactRecord, x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
                     inv_mass: wp.array(dtype=float), violated: wp.array(dtype=int),
                     done: wp.array(dtype=int), num_threads: int):
    """After a round whose projection found nothing violated (``violated[0] == 0``): the
    entries whose path ``x0 -> x1`` (as the round left it) still comes within the fail-safe gap
    (`FAILSAFE_GAP` of the pair's own thickness, the entry's offset) are counted in
    ``violated[2]``. Such a pair passed through, or all but, although its end keeps the linear
    constraint of its time of impact (a primitive that turned in the step: that normal and
    those weights no longer describe it), so the round must not count the step resolved. A
    `pin_held` entry is left out (the response cannot move it; counted apart)."""
    t = wp.tid()
    if done[0] != 0 or violated[0] != 0:
        return
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    for e in range(t, count, num_threads):
        vid = rec.vertex[e]
        if pin_held(vid, rec.weight[e], inv_mass):
            continue
        deep = wp.float64(_DEEP * rec.offset[e])
        a = vid[0]
        b = vid[1]
        c = vid[2]
        dd = vid[3]
        s = CCD_MISS
        if rec.kind[e] == KIND_VERTEX_TRIANGLE:
            s, toi = ccd_vertex_triangle(d3(x0[a]), d3(x0[b]), d3(x0[c]), d3(x0[dd]), d3(x1[a]),
                                         d3(x1[b]), d3(x1[c]), d3(x1[dd]), deep, CCD_ITERATIONS)
        elif rec.kind[e] == KIND_EDGE_EDGE:
            s, toi = ccd_edge_edge(d3(x0[a]), d3(x0[b]), d3(x0[c]), d3(x0[dd]), d3(x1[a]),
                                   d3(x1[b]), d3(x1[c]), d3(x1[dd]), deep, CCD_ITERATIONS)
        if s != CCD_MISS:
            wp.atomic_add(violated, 2, 1)


@wp.kernel
def round_end_kernel(rec: ContactRecord, violated: wp.array(dtype=int), done: wp.array(dtype=int),
                     stats: wp.array(dtype=int), flags: wp.array(dtype=int), rounds: int):
    """After a round: its contacts and overflow into the step's counters; ``done`` once a round's
    projection found no entry violated by more than 1 % of the thickness (the next detections
    would find the same pairs, already apart). ``flags``: [rounds run, another round (the
    `wp.capture_while` condition), the impact-zone passes needed (`wp.capture_if`)]."""
    more = violated[0] > 0  # the projection moved something: another detection
    if done[0] == 0:
        stats[I_CONTACTS] = stats[I_CONTACTS] + wp.min(rec.count[0], rec.vertex.shape[0])
        stats[I_OVERFLOW] = stats[I_OVERFLOW] + rec.overflow[0]
        if violated[0] == 0 and violated[2] == 0:
            done[0] = 1
    if violated[1] > 0:  # a `pin_held` entry left alone: this step counts once
        stats[I_PINNED] = 1
    violated[0] = 0
    violated[1] = 0
    violated[2] = 0
    flags[0] = flags[0] + 1
    flags[1] = 0
    # a round that projected nothing but left paths through (`deep_path_kernel`) goes straight
    # to the impact zones: the next detection would find the same
    if done[0] == 0 and flags[0] < rounds and more:
        flags[1] = 1
    flags[2] = 1 - done[0]


@wp.kernel
def zone_begin_kernel(flags: wp.array(dtype=int), passes: int):
    """The impact zones' loop starts (`zone_pass_kernel`): ``passes`` passes, then a last
    detection that only looks."""
    flags[0] = 0
    flags[1] = 1
    flags[2] = wp.where(passes > 0, 1, 0)


@wp.kernel
def zone_pass_kernel(rec: ContactRecord, flags: wp.array(dtype=int), passes: int,
                     stats: wp.array(dtype=int)):
    """The impact zones' loop (`SelfCollision._fallback`, a `wp.capture_while` on ``flags[1]``;
    ``flags``: [zone passes run, another detection, this detection grows and moves the zones
    (a `wp.capture_if`)]). After a detection the loop goes on unless it found no path (a pass
    that moved nothing leaves the next detection the same paths) or it was the last. The
    detection's dropped entries go to the step's overflow count (as a round's do,
    `round_end_kernel`): the frame's report grows the record and the runner may run the frame
    again; uncounted, an overflowing pass merged only the entries that fit."""
    stats[I_OVERFLOW] = stats[I_OVERFLOW] + rec.overflow[0]
    rec.overflow[0] = 0
    if flags[2] == 0 or rec.count[0] == 0:
        flags[1] = 0
        return
    flags[0] = flags[0] + 1
    if flags[0] >= passes:
        flags[2] = 0


@wp.func
def record_copy(src: ContactRecord, i: int, dst: ContactRecord, j: int):
    """Entry ``i`` of ``src`` written as entry ``j`` of ``dst``."""
    dst.vertex[j] = src.vertex[i]
    dst.weight[j] = src.weight[i]
    dst.normal[j] = src.normal[i]
    dst.offset[j] = src.offset[i]
    dst.ref[j] = src.ref[i]
    dst.friction[j] = src.friction[i]
    dst.restitution[j] = src.restitution[i]
    dst.source[j] = src.source[i]
    dst.kind[j] = src.kind[i]


@wp.kernel
def round_begin_kernel(x: wp.array(dtype=wp.vec3), x_round: wp.array(dtype=wp.vec3),
                       rec: ContactRecord, flags: wp.array(dtype=int),
                       moved: wp.array(dtype=int), incremental: wp.array(dtype=int)):
    """Before a round: ``moved[i]`` = 1 where the last round's projection (or the obstacles'
    push after it) changed vertex ``i`` (``x_round``: the positions it started from), and
    ``incremental[0]`` = 1 when this is not the step's first round and the last detection
    dropped nothing (`SelfCollision._round`)."""
    i = wp.tid()
    a = x[i]
    b = x_round[i]
    moved[i] = 0
    if a[0] != b[0] or a[1] != b[1] or a[2] != b[2]:
        moved[i] = 1
    if i == 0:
        incremental[0] = 0
        if flags[0] >= 1 and rec.overflow[0] == 0:
            incremental[0] = 1


@wp.kernel
def record_stash_kernel(rec: ContactRecord, stash: ContactRecord, num_threads: int):
    """The record's entries copied into ``stash`` (with their count)."""
    t = wp.tid()
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    if t == 0:
        stash.count[0] = count
    for e in range(t, count, num_threads):
        record_copy(rec, e, stash, e)


@wp.func
def none_moved(vid: wp.vec4i, moved: wp.array(dtype=int)):
    """No vertex of an entry (``vid``, -1 unused) is marked in ``moved``."""
    keep = True
    for j in range(4):
        if vid[j] >= 0:
            if moved[vid[j]] != 0:
                keep = False
    return keep


@wp.kernel
def record_keep_kernel(stash: ContactRecord, moved: wp.array(dtype=int), rec: ContactRecord,
                       num_threads: int):
    """The stashed entries none of whose vertices moved, appended to ``rec`` (emptied before):
    their paths are the ones they were detected on, so detection would find them again."""
    t = wp.tid()
    for e in range(t, stash.count[0], num_threads):
        vid = stash.vertex[e]
        keep = none_moved(vid, moved)
        if keep:
            k = wp.atomic_add(rec.count, 0, 1)
            if k < rec.vertex.shape[0]:  # (the stash holds at most the record's capacity)
                record_copy(stash, e, rec, k)


@wp.func
def pair_boxes_meet(kind: int, vid: wp.vec4i, x0: wp.array(dtype=wp.vec3),
                    x1: wp.array(dtype=wp.vec3), pad: float):
    """Whether the swept boxes of a pair's two elements (the vertex and the triangle, or the
    two edges), each inflated by ``pad`` (`padded`), overlap: a detection's broad-phase test
    of the pair, with the same boxes."""
    n = 1
    if kind == KIND_EDGE_EDGE:
        n = 2
    lo = wp.min(x0[vid[0]], x1[vid[0]])
    hi = wp.max(x0[vid[0]], x1[vid[0]])
    if n == 2:
        lo = wp.min(lo, wp.min(x0[vid[1]], x1[vid[1]]))
        hi = wp.max(hi, wp.max(x0[vid[1]], x1[vid[1]]))
    lo2 = wp.min(x0[vid[3]], x1[vid[3]])
    hi2 = wp.max(x0[vid[3]], x1[vid[3]])
    for j in range(n, 3):
        lo2 = wp.min(lo2, wp.min(x0[vid[j]], x1[vid[j]]))
        hi2 = wp.max(hi2, wp.max(x0[vid[j]], x1[vid[j]]))
    a, b = padded(lo, hi, pad)
    c, d = padded(lo2, hi2, pad)
    return boxes_overlap(a, b, c, d)


@wp.kernel
def record_retest_kernel(stash: ContactRecord, moved: wp.array(dtype=int),
                         x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
                         gap: float, sep: float, rest: wp.array(dtype=wp.vec4),
                         rec: ContactRecord, num_threads: int):
    """The stashed entries none of whose vertices moved, tested again on the paths
    ``x0 -> x1`` with the detection gap ``gap`` (`vt_test` / `ee_test`, as a detection would
    test their pairs, after the same box test: `pair_boxes_meet`) and appended to ``rec``
    where they hit."""
    t = wp.tid()
    for e in range(t, stash.count[0], num_threads):
        vid = stash.vertex[e]
        keep = none_moved(vid, moved)
        if not keep:
            continue
        if not pair_boxes_meet(stash.kind[e], vid, x0, x1, 0.5 * gap):
            continue
        if stash.kind[e] == KIND_VERTEX_TRIANGLE:
            vt_test(vid[0], vid[1], vid[2], vid[3], x0, x1, gap, sep, rest, rec)
        elif stash.kind[e] == KIND_EDGE_EDGE:
            ee_test(vid[0], vid[1], vid[2], vid[3], x0, x1, gap, sep, rest, rec)


@wp.kernel
def solve_far_kernel(x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
                     s0: wp.array(dtype=wp.vec3), s1: wp.array(dtype=wp.vec3), allow: float,
                     moved: wp.array(dtype=int), far: wp.array(dtype=int),
                     either: wp.array(dtype=int),
                     flags: wp.array(dtype=int)):
    """``far[i]`` = 1 where vertex ``i``'s path ``x0 -> x1`` leaves the solve detection's
    ``s0 -> s1`` by more than ``allow`` at either end (so at any time of the step), and
    ``either[i]`` = 1 where it is far or marked in ``moved``; ``flags[1]`` = 1 if some vertex
    is far, ``flags[2]`` counts them (both cleared by the caller)."""
    i = wp.tid()
    d = wp.max(wp.length(x0[i] - s0[i]), wp.length(x1[i] - s1[i]))
    far[i] = 0
    either[i] = moved[i]
    if not (d <= allow):
        far[i] = 1
        either[i] = 1
        flags[1] = 1
        wp.atomic_add(flags, 2, 1)


@wp.kernel
def solve_use_kernel(ok: wp.array(dtype=int), most_far: int, flags: wp.array(dtype=int),
                     counters: wp.array(dtype=int)):
    """``flags[0]`` = 1: the solve's record serves (``ok[0]``, `SelfCollision.note_solve`)
    and at most ``most_far`` vertices are far (`solve_far_kernel`); counted in
    ``self_reused``."""
    flags[0] = wp.where(ok[0] != 0 and flags[2] <= most_far, 1, 0)
    counters[I_REUSED] = counters[I_REUSED] + flags[0]


@wp.kernel
def solve_retest_kernel(rec: ContactRecord, far: wp.array(dtype=int),
                        moved: wp.array(dtype=int), x0: wp.array(dtype=wp.vec3),
                        x1: wp.array(dtype=wp.vec3), gap: float, sep: float,
                        rest: wp.array(dtype=wp.vec4), out: ContactRecord, num_threads: int):
    """The solve's entries (`SelfCollision.note_solve`) with no vertex in ``far`` and, given a
    ``moved`` set, at least one in it, tested again on the paths ``x0 -> x1`` with ``gap``
    after a detection's box test (`pair_boxes_meet`), appended to ``out`` where they hit."""
    t = wp.tid()
    for e in range(t, rec.count[0], num_threads):
        vid = rec.vertex[e]
        if moved.shape[0] > 0:
            if none_moved(vid, moved):
                continue
        if not none_moved(vid, far):
            continue
        kind = rec.kind[e]
        if not pair_boxes_meet(kind, vid, x0, x1, 0.5 * gap):
            continue
        if kind == KIND_VERTEX_TRIANGLE:
            vt_test(vid[0], vid[1], vid[2], vid[3], x0, x1, gap, sep, rest, out)
        elif kind == KIND_EDGE_EDGE:
            ee_test(vid[0], vid[1], vid[2], vid[3], x0, x1, gap, sep, rest, out)


@wp.kernel
def solve_noted_kernel(rec: ContactRecord, ok: wp.array(dtype=int)):
    """The solve's record serves the response (`SelfCollision.note_solve`) unless its
    detection dropped entries."""
    ok[0] = wp.where(rec.overflow[0] == 0, 1, 0)


@wp.kernel
def step_begin_kernel(done: wp.array(dtype=int), violated: wp.array(dtype=int),
                      flags: wp.array(dtype=int), counters: wp.array(dtype=int)):
    """The step's flags and counters reset in one launch: not done, a first round to run."""
    i = wp.tid()
    if i < counters.shape[0]:
        counters[i] = 0
        if i == I_RESPONSES:  # this step is one response
            counters[i] = 1
    if i == 0:
        done[0] = 0
        violated[0] = 0
        violated[1] = 0
        violated[2] = 0
        flags[0] = 0
        flags[1] = 1
        flags[2] = 0


@wp.func
def rest_close_mark(i0: int, i1: int, i2: int, i3: int, d: wp.float64, reach: float,
                    share: wp.array(dtype=float)):
    # a pair ``d`` apart at rest, closer than ``reach`` (twice the thickness): its vertices'
    # least `rest_scale`
    if d < wp.float64(reach):
        f = rest_scale(d, 0.5 * reach)
        wp.atomic_min(share, i0, f)
        wp.atomic_min(share, i1, f)
        wp.atomic_min(share, i2, f)
        wp.atomic_min(share, i3, f)


@wp.kernel
def rest_close_vt_kernel(bvh: wp.uint64, rest: wp.array(dtype=wp.vec4),
                         tris: wp.array2d(dtype=wp.int32), reach: float,
                         share: wp.array(dtype=float)):
    """Vertex ``v`` against the triangles of its piece within ``reach`` (twice the thickness)
    of it in the rest shape (not its own): the least `rest_scale` of each such pair's four
    vertices."""
    v = wp.tid()
    p = rest_point(rest, v)
    c = wp.vec3(float(p[0]), float(p[1]), float(p[2]))
    q = wp.bvh_query_aabb(bvh, c - wp.vec3(reach), c + wp.vec3(reach))
    t = int(0)
    while wp.bvh_query_next(q, t):
        ia = tris[t, 0]
        ib = tris[t, 1]
        ic = tris[t, 2]
        if ia != v and ib != v and ic != v and rest[v][3] == rest[ia][3]:
            d = vt_distance(p, rest_point(rest, ia), rest_point(rest, ib), rest_point(rest, ic))
            rest_close_mark(v, ia, ib, ic, d, reach, share)


@wp.kernel
def rest_close_ee_kernel(bvh: wp.uint64, rest: wp.array(dtype=wp.vec4),
                         edges: wp.array2d(dtype=wp.int32), lowers: wp.array(dtype=wp.vec3),
                         uppers: wp.array(dtype=wp.vec3), reach: float,
                         share: wp.array(dtype=float)):
    """Edge ``e`` against the edges of its piece within ``reach`` in the rest shape sharing no
    vertex with it: as `rest_close_vt_kernel`."""
    e = wp.tid()
    ia = edges[e, 0]
    ib = edges[e, 1]
    q = wp.bvh_query_aabb(bvh, lowers[e] - wp.vec3(reach), uppers[e] + wp.vec3(reach))
    f = int(0)
    while wp.bvh_query_next(q, f):
        ic = edges[f, 0]
        id = edges[f, 1]
        if f > e and ic != ia and ic != ib and id != ia and id != ib:
            if rest[ia][3] == rest[ic][3]:
                d = ee_distance(rest_point(rest, ia), rest_point(rest, ib), rest_point(rest, ic),
                                rest_point(rest, id))
                rest_close_mark(ia, ib, ic, id, d, reach, share)


@wp.kernel
def rest_touch_kernel(rest: wp.array(dtype=wp.vec4), tris: wp.array2d(dtype=wp.int32),
                      edges: wp.array2d(dtype=wp.int32), v: int, at_v: wp.array(dtype=int),
                      d_tri: wp.array(dtype=wp.float64), d_edge: wp.array(dtype=wp.float64),
                      e_at: wp.array(dtype=int)):
    """Rest distances, to name the pair `check_rest_apart` found: vertex ``v`` against each
    triangle of its piece (``d_tri``; -1: one of its own, or another piece's), and each edge
    against the nearest of ``v``'s edges ``at_v`` that shares no vertex with it (``d_edge``,
    that edge in ``e_at``; -1: none)."""
    i = wp.tid()
    if i < tris.shape[0]:
        ia = tris[i, 0]
        ib = tris[i, 1]
        ic = tris[i, 2]
        d_tri[i] = wp.float64(-1.0)
        if ia != v and ib != v and ic != v and rest[v][3] == rest[ia][3]:
            d_tri[i] = vt_distance(rest_point(rest, v), rest_point(rest, ia),
                                   rest_point(rest, ib), rest_point(rest, ic))
    if i < edges.shape[0]:
        d_edge[i] = wp.float64(-1.0)
        e_at[i] = -1
        ic = edges[i, 0]
        id = edges[i, 1]
        for k in range(at_v.shape[0]):
            e = at_v[k]
            ia = edges[e, 0]
            ib = edges[e, 1]
            if ic != ia and ic != ib and id != ia and id != ib and rest[ia][3] == rest[ic][3]:
                d = ee_distance(rest_point(rest, ia), rest_point(rest, ib),
                                rest_point(rest, ic), rest_point(rest, id))
                if e_at[i] < 0 or d < d_edge[i]:
                    d_edge[i] = d
                    e_at[i] = e


def check_rest_apart(mesh, rest, share, thickness: float, device=None) -> None:
    """`ValueError` naming the pair if two primitives of one piece of the cloth that share no
    vertex (a vertex and a triangle, two edges) lie closer than `COINCIDENT` thicknesses in the
    rest shape (``share``, `rest_and_pieces`: below `REST_SHARE` times that): the mesh
    overlaps itself (an inverted triangle folded onto its neighbours, a T-junction: a vertex on
    another triangle's edge). Such a pair keeps nothing of the thickness (`rest_scale`), and a
    path through zero distance meets the fail-safe: measured, a jittered sheet with one
    inverted triangle (a vertex inside a triangle it is not a corner of) returned the whole
    cloth to its start, velocities zeroed, in 301 of its first frame's 302 steps, and froze as
    diverged at frame 5 under explicit Euler."""
    bad = np.flatnonzero(np.asarray(share) < float(REST_SHARE) * COINCIDENT)
    if not len(bad):
        return
    tris = np.asarray(mesh.triangles, dtype=np.int32)
    edges = np.asarray(mesh.edges, dtype=np.int32).reshape(-1, 2)
    d_tri = wp.zeros(max(len(tris), 1), dtype=wp.float64, device=device)
    d_edge = wp.zeros(max(len(edges), 1), dtype=wp.float64, device=device)
    e_at = wp.zeros(max(len(edges), 1), dtype=int, device=device)
    args = [wp.array(rest, dtype=wp.vec4, device=device),
            wp.array(tris, dtype=wp.int32, device=device),
            wp.array(edges, dtype=wp.int32, device=device)]
    found = []  # (distance as printed, 0 for a vertex and a triangle / 1 for edges, words)
    # each vertex of a pair found is marked: the closest pair of a few names one (at equal
    # distance a vertex and its triangle, the plainer)
    for v in (int(v) for v in bad[:8]):
        at_v = np.flatnonzero((edges == v).any(axis=1)).astype(np.int32)
        wp.launch(rest_touch_kernel, max(len(tris), len(edges)),
                  [*args, v, wp.array(at_v, dtype=int, device=device), d_tri, d_edge, e_at],
                  device=device)
        dt, de = d_tri.numpy()[:len(tris)], d_edge.numpy()[:len(edges)]
        at = e_at.numpy()[:len(edges)]
        dt, de = np.where(dt < 0.0, np.inf, dt), np.where(at < 0, np.inf, de)
        if len(dt) and np.isfinite(dt.min()):
            t = int(np.argmin(dt))
            found.append((float(f"{dt[t]:.3g}"), 0,
                          f"vertex {v} lies {dt[t]:.3g} m from triangle {t} (vertices "
                          f"{', '.join(str(int(c)) for c in tris[t])}), which it is not a "
                          "corner of,"))
        if len(de) and np.isfinite(de.min()):
            f = int(np.argmin(de))
            (a, b), (c, d) = edges[at[f]], edges[f]
            found.append((float(f"{de[f]:.3g}"), 1,
                          f"edges {a}-{b} and {c}-{d}, which share no vertex, lie {de[f]:.3g} "
                          "m apart"))
    what = min(found)[2] if found else "two parts touch"
    raise ValueError(
        f"{mesh.name}: {what} in the rest shape ({len(bad)} vertices of such pairs, closer "
        f"than {COINCIDENT:g} of the self-collision thickness {float(thickness):g} m): the mesh "
        "overlaps itself (an inverted triangle, a vertex on another triangle's edge). "
        "Self-collision keeps parts of the cloth apart and cannot hold ones that touch at rest: "
        "fix the mesh (triangulate it again), or turn self-collision off")


def mesh_pieces(mesh) -> np.ndarray:
    """(N,) each vertex's connected piece (the components of the mesh's edge graph, numbered
    from 0 in the order of their lowest vertex)."""
    n = len(mesh.vertices)
    parent = np.arange(n)

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in np.asarray(mesh.edges):
        ra, rb = root(int(a)), root(int(b))
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    roots = np.array([root(i) for i in range(n)], dtype=np.int64)
    return np.unique(roots, return_inverse=True)[1].reshape(-1)


def check_start_apart(mesh, thickness: float) -> None:
    """`ValueError` naming them if the rest mesh has vertices closer than `COINCIDENT`
    thicknesses (a seam written twice: weld it), or vertices of separate pieces closer than
    the thickness (`SelfCollision`)."""
    h = float(thickness)
    x = np.asarray(mesh.vertices, dtype=np.float64)
    same = mesh.coincident_vertices(COINCIDENT * h)
    if len(same):
        i, j = (int(c) for c in same[0])
        gap = float(np.linalg.norm(x[i] - x[j]))
        raise ValueError(
            f"{mesh.name}: vertices {i} and {j} are {gap:.3g} m apart but not joined "
            f"({len(same)} such vertices; a seam written twice?): self-collision keeps separate "
            f"parts of the cloth {h:g} m apart and cannot hold ones that start at one point. "
            f"Weld them: mesh, index = mesh.weld({max(2.0 * gap, 1e-9):.2g}) (or "
            f"TriMesh.from_obj(path, weld={max(2.0 * gap, 1e-9):.2g})), or move them apart")
    from .check import close_vertex_pairs

    piece = mesh_pieces(mesh)
    if piece.max(initial=0) == 0:
        return
    pairs = close_vertex_pairs(x, h)
    cross = pairs[piece[pairs[:, 0]] != piece[pairs[:, 1]]] if len(pairs) else pairs
    if len(cross):
        d = np.linalg.norm(x[cross[:, 0]] - x[cross[:, 1]], axis=1)
        k = int(np.argmin(d))
        i, j = (int(c) for c in cross[k])
        raise ValueError(
            f"{mesh.name}: vertices {i} and {j} of separate pieces of the cloth start "
            f"{d[k]:.3g} m apart ({len(cross)} such pairs), closer than the self-collision "
            f"thickness {h:g} m, which would throw them apart in the first step: start them at "
            f"least the thickness apart (or a smaller thickness), or, if they are one seam, weld "
            f"them: mesh, index = mesh.weld({1.5 * float(d.max()):.3g})")


def rest_and_pieces(mesh, thickness: float = 0.0, device=None):
    """``(rest, share)``: ``rest`` (N, 4) float32, each vertex's rest position and, as the
    fourth coordinate, the index of
    its connected piece (the components of the mesh's edge graph, numbered from 0; float32
    holds them exactly up to 2^24), or -1 for a vertex of no pair of its piece closer than
    ``2 thickness`` in the rest shape (`rest_scale` is 1 for every pair of such a vertex, and
    is not computed: the built-in scenes' grids have no such pair). With ``thickness`` 0 every
    vertex keeps its piece. The pairs are found once, with two BVHs over the rest shape.
    ``share`` (N,) float32: each vertex's least `rest_scale` over those pairs (1 if none): the
    spans' reach, a fraction of the thickness, is that fraction of the vertex's pairs' own
    (`span_step_kernel`)."""
    n = len(mesh.vertices)
    piece = mesh_pieces(mesh)
    out = np.zeros((n, 4), dtype=np.float32)
    out[:, :3] = mesh.vertices
    out[:, 3] = piece
    reach = 2.0 * float(thickness)
    tris = np.asarray(mesh.triangles, dtype=np.int32)
    edges = np.asarray(mesh.edges, dtype=np.int32)
    ones = np.ones(n, dtype=np.float32)
    if reach <= 0.0 or n == 0 or not len(tris):
        return out, ones
    x = np.asarray(mesh.vertices, dtype=np.float32)
    rest = wp.array(out, dtype=wp.vec4, device=device)
    share = wp.array(ones, dtype=float, device=device)
    t_lo, t_hi = x[tris].min(axis=1), x[tris].max(axis=1)
    tri_bvh = wp.Bvh(wp.array(t_lo, dtype=wp.vec3, device=device),
                     wp.array(t_hi, dtype=wp.vec3, device=device))
    wp.launch(rest_close_vt_kernel, n, [tri_bvh.id, rest, wp.array(tris, dtype=wp.int32,
                                                                     device=device),
                                        reach, share], device=device)
    if len(edges):
        e_lo = wp.array(x[edges].min(axis=1), dtype=wp.vec3, device=device)
        e_hi = wp.array(x[edges].max(axis=1), dtype=wp.vec3, device=device)
        edge_bvh = wp.Bvh(e_lo, e_hi)
        wp.launch(rest_close_ee_kernel, len(edges),
                  [edge_bvh.id, rest, wp.array(edges, dtype=wp.int32, device=device), e_lo,
                   e_hi, reach, share], device=device)
    least = share.numpy()
    out[least >= 1.0, 3] = -1.0  # no pair closer than twice the thickness
    return out, least


class SelfCollision:
    """Self-collision of the cloth (module docstring).

    Args:
        model: the `ClothModel`.
        thickness: m, > 0: the minimum distance kept between non-adjacent parts of the cloth.
        rounds: detection + response rounds per step (default 4).
        iterations: Jacobi projection rounds per detection (default 4).
        capacity: record entries per detection (default ``16 * (vertices + edges)``); more are
            counted in ``stats["self_overflow"]``.
        zone_passes: detections that grow the rigid impact zones (default `ZONE_PASSES`; 0:
            the whole cloth returns to its start whenever the rounds leave a path too close).
        broadphase: ``"bvh"`` (swept-box BVHs refitted each step) or ``"grid"`` (hash grids of
            the box centres rebuilt each step); both find every pair whose swept boxes overlap
            (`warp_cloth.collision.broadphase`).
        clearance: in thicknesses (default 4): under spans (`plan`), how far around each vertex
            `clear` looks for the pairs that set its allowance; a vertex clear of the rest of
            the cloth may move ``(clearance - 1.01) / 2`` thicknesses in a span (1.5 at the
            default) instead of the ``self_motion`` reach. <= 1.01: no allowances (the reach
            everywhere, every vertex queries).
        incremental: after a step's first round, detect again only the pairs with a vertex
            the last round's projection moved, and keep the other entries (their paths did not
            change, so a detection would find them again; BVH broad phase). Default True;
            False detects every pair in every round (the same contacts, for comparison).
        candidate_reach: in thicknesses (default `CANDIDATE_REACH`; BVH broad phase): the
            detections test pairs from candidate lists built by the BVHs with boxes grown by
            this reach, built again only once a vertex's path start or end has moved farther
            than it from the box of the build's path (or a larger gap is asked for): a step's
            solve, response
            rounds and impact-zone passes, and the next steps while the cloth moves little,
            share one traversal. The same contacts as without (every pair whose boxes overlap
            at the detection is listed: its boxes lie inside the build's grown ones). 0: no
            lists, every detection traverses the BVHs.

    Attributes:
        layer_frames: the response's velocity rule measures a vertex's approach in the motion
            of the layer it met (`layer_apply`; default True). False: against a world at rest
            (the rule before; explicit Euler sets it, `ExplicitEuler`).
    """

    #: `layer_apply`'s frames: the other layers' velocities (True) or a world at rest
    layer_frames = True

    def __init__(self, model, thickness: float, rounds: int = 4, iterations: int = 4,
                 capacity: int | None = None, broadphase: str = "bvh",
                 zone_passes: int | None = None,
                 clearance: float = 4.0, incremental: bool = True,
                 candidate_reach: float | None = None):
        self.model = model
        self.device = d = model.device
        self.thickness = float(thickness)
        self.rounds, self.iterations = int(rounds), int(iterations)
        if self.rounds < 1 or self.iterations < 1:
            raise ValueError("self-collision rounds and iterations must be >= 1")
        check_start_apart(model.mesh, self.thickness)
        self._free = int((np.asarray(model.inverse_masses) > 0).sum())
        self.broad = ClothBroadPhase(model, broadphase)
        n = model.num_vertices
        #: the rest shape and, as the fourth coordinate, each vertex's connected piece: pairs of
        #: one piece that lie close in it keep less than the thickness (`rest_scale`)
        rest, share = rest_and_pieces(model.mesh, self.thickness, d)
        check_rest_apart(model.mesh, rest, share, self.thickness, d)
        self.rest = wp.array(rest, dtype=wp.vec4, device=d)
        #: each vertex's least pair share of the thickness: the spans' reach scales with it
        self._reach_share = wp.array(share, dtype=float, device=d)
        self.capacity = int(capacity or 16 * (n + self.broad.num_edges))
        self.record = make_record(self.capacity, d)
        self.acc = wp.zeros(n, dtype=wp.vec3, device=d)
        self._no_moved = wp.zeros(0, dtype=wp.vec3, device=d)  # its layers do not move apart
        self.cnt = wp.zeros(n, dtype=int, device=d)
        # per vertex, the largest velocity of its projected entries' other sides (`layer_apply`)
        self._frame = wp.full(n, _NO_FRAME, dtype=float, device=d)
        self.threads = record_threads(self.capacity, self.device)
        # per step: STAT_KEYS
        self.counters = wp.zeros(len(STAT_KEYS), dtype=int, device=d)
        self.totals = wp.zeros(len(STAT_KEYS), dtype=int, device=d)  # summed over all steps
        self.zones = ImpactZones(model)
        self.zone_passes = ZONE_PASSES if zone_passes is None else int(zone_passes)
        if self.zone_passes < 0:
            raise ValueError("self-collision zone_passes must be >= 0")
        self.done = wp.zeros(1, dtype=int, device=d)
        # [violated entries, a pin_held one, paths through kept at their end: `deep_path_kernel`]
        self.violated = wp.zeros(3, dtype=int, device=d)
        self._never = wp.zeros(1, dtype=int, device=d)
        self._flags = wp.zeros(3, dtype=int, device=d)  # round_end_kernel
        self._diverged = wp.zeros(1, dtype=int, device=d)  # diverged_kernel
        self._zone_flags = wp.zeros(3, dtype=int, device=d)  # zone_pass_kernel
        self._no_pairs = wp.zeros(0, dtype=wp.vec2i, device=d)
        self._npairs = wp.zeros(1, dtype=int, device=d)
        self._one = wp.ones(1, dtype=int, device=d)
        self._held = wp.zeros(2, dtype=int, device=d)  # `hold`'s violation counts (unused)
        # spans (`plan`): steps per frame (None: a response after every step), and on the
        # device the frame's steps taken, the span's start positions, steps and "respond" flag
        self.frame_steps = None
        self._frame_k = wp.zeros(1, dtype=int, device=d)  # the frame's steps taken
        self._span = None
        self._reach = 0.0
        self._in_span = False
        self._gap = self.thickness  # a round's detection gap (`_span_resolve`)
        self._no_int = wp.zeros(0, dtype=int, device=d)
        try:
            c = float(clearance)
        except (TypeError, ValueError):
            c = float("nan")
        if not (c >= 0.0 and c < float("inf")):
            raise ValueError(f"self-collision clearance must be a number of thicknesses >= 0, "
                             f"got {clearance!r}")
        self.clearance = c * self.thickness
        self._allowances = c > 1.01
        self.allowances = False  # in use (`plan`)
        # candidate lists (`_query_listed`; BVH broad phase)
        self._cand = None
        reach = CANDIDATE_REACH if candidate_reach is None else candidate_reach
        try:
            reach = float(reach)
        except (TypeError, ValueError):
            reach = float("nan")
        if not (reach >= 0.0 and reach < float("inf")):
            raise ValueError(f"self-collision candidate_reach must be a number of thicknesses "
                             f">= 0, got {candidate_reach!r}")
        if reach > 0.0 and self.broad.method == "bvh":
            self._cand = True
            self._cand_reach = reach * self.thickness
            self._cand_gap_max = self.thickness
            self._cand_gap = wp.zeros(1, dtype=float, device=d)
            self._cand_alloc(CANDIDATE_ROOM * n, CANDIDATE_ROOM * self.broad.num_edges)
            self._cand_x0 = wp.zeros(n, dtype=wp.vec3, device=d)
            self._cand_x1 = wp.zeros(n, dtype=wp.vec3, device=d)
            self._cand_flags = wp.zeros(3, dtype=int, device=d)
            self._cand_n = wp.zeros(2, dtype=int, device=d)
            # [builds, overflowed builds, most vertex-triangle pairs, most edge-edge pairs]
            self._cand_stats = wp.zeros(4, dtype=int, device=d)
            self._cand_grown = 0
        # incremental rounds (`_round`): the positions a round's projection started from, the
        # vertices it moved, the device flag and a second record for the kept entries
        self._incremental = None
        if incremental and self.broad.method == "bvh":
            self._x_round = wp.zeros(n, dtype=wp.vec3, device=d)
            self._moved_round = wp.zeros(n, dtype=int, device=d)
            self._incremental = wp.zeros(1, dtype=int, device=d)
            self._zone_incremental = wp.zeros(1, dtype=int, device=d)
            self._stash = make_record(self.capacity, d)
            # the vertices' BVH built now, not inside a recorded graph (`_round_incremental`
            # refits it; the others are built by the first step's detection, as before)
            x = wp.array(model.mesh.vertices, dtype=wp.vec3, device=d)
            self.broad.build_vertex_bvh(x, 0.5 * self.thickness)
            # the solve's detection (`note_solve`), which a response's first round may reuse
            self._sol_x0 = wp.zeros(n, dtype=wp.vec3, device=d)
            self._sol_x1 = wp.zeros(n, dtype=wp.vec3, device=d)
            self._sol_ok = wp.zeros(1, dtype=int, device=d)
            self._sol_far = wp.zeros(n, dtype=int, device=d)
            self._sol_either = wp.zeros(n, dtype=int, device=d)
            self._sol_flags = wp.zeros(3, dtype=int, device=d)

    def note_solve(self, x0, x1, gap: float, record) -> None:
        """``record`` now holds the contacts of the solve's detection (`detect` on the paths
        ``x0 -> x1`` with ``gap``: `ContactCoupling.detect_self`); kept (the paths copied) so
        that the response's detections can test those entries again instead of scanning
        every candidate (`_reuse_or`). Call `forget_solve` when ``record`` is cleared or
        refilled otherwise. Without incremental rounds (the grid broad phase): nothing.

        Raises ValueError for a gap that is not a finite number above the thickness (the
        response's detections could not start from it) or paths of another vertex count."""
        try:
            g = float(gap)
        except (TypeError, ValueError):
            g = float("nan")
        if not (g > self.thickness and g < float("inf")):
            raise ValueError(f"SelfCollision.note_solve: gap must be a finite number of metres "
                             f"above the thickness {self.thickness}, got {gap!r}")
        n = self.model.num_vertices
        for name, a in (("x0", x0), ("x1", x1)):
            if len(a) != n:
                raise ValueError(f"SelfCollision.note_solve: {name} has {len(a)} positions, the "
                                 f"cloth {n} vertices")
        if self._incremental is None:
            return
        self._sol = (record, g, record_threads(record.vertex.shape[0], self.device))
        wp.copy(self._sol_x0, x0)
        wp.copy(self._sol_x1, x1)
        launch(solve_noted_kernel, 1, [record, self._sol_ok], device=self.device)

    def forget_solve(self) -> None:
        """The record given to `note_solve` no longer holds that detection's contacts."""
        if self._incremental is not None:
            self._sol_ok.zero_()

    def detect(self, x0, x1, gap: float, record, done=None) -> None:
        """Self-contacts on the paths ``x0 -> x1`` that come within ``gap`` appended to
        ``record`` as constraints keeping the thickness (none while ``done[0]``)."""
        self._query(x0, x1, gap, record, self._never if done is None else done,
                    self._no_pairs, self._no_pairs, self._npairs)

    def candidates(self, x0, x1, gap: float, capacity: int = 1 << 20):
        """The broad phase's candidate pairs for the paths ``x0 -> x1`` and detection gap
        ``gap`` (boxes inflated by ``gap / 2`` each: every pair that can come within ``gap``),
        after the topological and pinned filters: ``(vt, ee)`` as sets of ``(vertex, triangle)`` and
        ``(edge, edge)`` index pairs. Host reads: for tests and benchmarks, not for steps."""
        out = []
        for kind in (0, 1):
            pairs = wp.zeros(capacity, dtype=wp.vec2i, device=self.device)
            npairs = wp.zeros(1, dtype=int, device=self.device)
            self._query(x0, x1, gap, self.record, self._never, pairs if kind == 0 else
                        self._no_pairs, pairs if kind == 1 else self._no_pairs, npairs,
                        vt=kind == 0, ee=kind == 1)
            k = int(npairs.numpy()[0])
            if k > capacity:
                raise RuntimeError(f"{k} candidate pairs: more than capacity={capacity}")
            out.append({tuple(int(i) for i in p) for p in pairs.numpy()[:k]})
        return tuple(out)

    def _query(self, x0, x1, gap, record, done, vt_pairs, ee_pairs, npairs, vt=True, ee=True,
               moved=None):
        # every box, the stored ones and the queries', is inflated by half the gap: two
        # elements that come within ``gap`` of each other on their paths have points in their
        # swept boxes less than ``gap`` apart along every axis, so the half-inflated boxes
        # overlap (`broadphase.padded` covers float32 rounding). Each inflated by the whole
        # gap, as before, listed the pairs within twice it: on the twist at frame 150, 95k
        # edge-edge candidates for 278 contacts, 45k with half (`bench selfcollision`)
        b, m, d = self.broad, self.model, self.device
        if b.method == "grid":
            b.update(x0, x1, 0.5 * float(gap))
            common = [x0, x1]
            if vt:
                launch(self_vt_grid_kernel, m.num_vertices,
                       [b.tri_grid.id, b.lowers, b.uppers, b.rmax, *common, b.tris, gap,
                        self.thickness, m.inv_mass, self.rest, done, record, vt_pairs, npairs],
                       device=d)
            if ee:
                launch(self_ee_grid_kernel, b.num_edges,
                       [b.edge_grid.id, b.elowers, b.euppers, b.rmax, *common, b.edges, gap,
                        self.thickness, m.inv_mass, self.rest, done, record, ee_pairs, npairs],
                       device=d)
            return
        # ``moved`` (BVH): only the pairs with a marked vertex (`_detect_moved`)
        active = self._no_int if moved is None else moved
        if self._in_span and moved is None:  # allowances from the span's start: only the
            # active part queries
            active = self._active
            slack = max(0.0, 0.5 * (float(gap) - self.thickness))
            launch(active_kernel, m.num_vertices, [x0, x1, self._allow, slack, active],
                   device=d)
        if (self._cand is not None and vt and ee and vt_pairs.shape[0] == 0
                and ee_pairs.shape[0] == 0):
            # contacts (not a listing of candidates): by the candidate lists
            self._query_listed(x0, x1, gap, record, done, active)
        else:
            self._query_bvh(x0, x1, gap, record, done, active, vt_pairs, ee_pairs, npairs,
                            vt, ee)

    def _query_listed(self, x0, x1, gap, record, done, active):
        """`_query` by the candidate lists: built from the BVHs (boxes grown by the reach
        ``_cand_reach`` and for the largest gap asked so far) when a vertex's start or end left
        the reach of the last build's or the gap is larger, then the listed pairs whose boxes
        for this detection overlap are tested. A build that overflowed detects by the BVHs
        (`_query_bvh`). Device-side choices (`wp.capture_if`): capturable."""
        d, n = self.device, self.model.num_vertices
        g = float(gap)
        self._cand_gap_max = max(self._cand_gap_max, g)
        launch(cand_begin_kernel, 1, [g, self._cand_gap, self._cand_flags], device=d)
        launch(cand_check_kernel, n, [x0, x1, self._cand_x0, self._cand_x1,
                                      0.999 * self._cand_reach, self._cand_flags], device=d)
        launch(cand_use_kernel, 1, [self._cand_flags], device=d)
        wp.capture_if(self._cand_flags[0:1], self._cand_build, x0=x0, x1=x1)
        wp.capture_if(self._cand_flags[1:2], self._cand_test, x0=x0, x1=x1, gap=g,
                      record=record, done=done, active=active)
        wp.capture_if(self._cand_flags[2:3], self._query_bvh, x0=x0, x1=x1, gap=g,
                      record=record, done=done, active=active)

    def _cand_build(self, x0, x1):
        b, m, d = self.broad, self.model, self.device
        g = self._cand_gap_max + 2.0 * self._cand_reach  # its half: the boxes' pad
        b.update(x0, x1, 0.5 * g)
        self._cand_n.zero_()
        launch(self_vt_bvh_kernel, m.num_vertices,
               [b.tri_bvh.id, x0, x1, b.tris, g, self.thickness, m.inv_mass, self.rest,
                self._never, self._no_int, self.record, self._cand_vt, self._cand_n[0:1]],
               device=d)
        launch(self_ee_bvh_kernel, b.num_edges,
               [b.edge_bvh.id, x0, x1, b.edges, g, self.thickness, m.inv_mass, self.rest,
                self._never, self._no_int, self.record, self._cand_ee, self._cand_n[1:2]],
               device=d)
        wp.copy(self._cand_x0, x0)
        wp.copy(self._cand_x1, x1)
        launch(cand_built_kernel, 1, [self._cand_n, self._cand_vt.shape[0],
                                      self._cand_ee.shape[0], self._cand_gap_max,
                                      self._cand_gap, self._cand_flags, self._cand_stats],
               device=d)

    def _cand_test(self, x0, x1, gap, record, done, active):
        b, m, d = self.broad, self.model, self.device
        # this detection's boxes (the BVHs' arrays; the next traversal writes its own)
        launch(cloth_bounds_kernel, b.num_tris + b.num_edges,
               [x0, x1, b.tris, b.edges, b.num_tris, 0.5 * float(gap), b.lowers, b.uppers,
                b.elowers, b.euppers], device=d)
        rest = [gap, self.thickness, m.inv_mass, self.rest, done, active, record,
                self._no_pairs, self._npairs, self._cand_threads]
        launch(vt_list_kernel, self._cand_threads,
               [self._cand_vt, self._cand_n, b.lowers, b.uppers, x0, x1, b.tris, *rest],
               device=d)
        launch(ee_list_kernel, self._cand_threads,
               [self._cand_ee, self._cand_n, b.elowers, b.euppers, x0, x1, b.edges, *rest],
               device=d)

    def _query_bvh(self, x0, x1, gap, record, done, active, vt_pairs=None, ee_pairs=None,
                   npairs=None, vt=True, ee=True):
        """`_query`'s BVH traversal: the vertices against the triangles and the edges against
        the edges, contacts appended to ``record`` (or, with ``vt_pairs`` / ``ee_pairs``, the
        candidates listed); with an ``active`` set only the pairs with an active vertex (the
        vertices' BVH finds the inactive vertices of triangles with an active corner)."""
        b, m, d = self.broad, self.model, self.device
        vt_pairs = self._no_pairs if vt_pairs is None else vt_pairs
        ee_pairs = self._no_pairs if ee_pairs is None else ee_pairs
        npairs = self._npairs if npairs is None else npairs
        partial = active.shape[0] > 0
        b.update(x0, x1, 0.5 * float(gap), vertices=partial)
        if vt:
            launch(self_vt_bvh_kernel, m.num_vertices,
                   [b.tri_bvh.id, x0, x1, b.tris, gap, self.thickness, m.inv_mass, self.rest,
                    done, active, record, vt_pairs, npairs], device=d)
            if partial:
                launch(self_tv_bvh_kernel, b.num_tris,
                       [b.vertex_bvh.id, b.lowers, b.uppers, x0, x1, b.tris, gap,
                        self.thickness, m.inv_mass, self.rest, done, active, record, vt_pairs,
                        npairs], device=d)
        if ee:
            launch(self_ee_bvh_kernel, b.num_edges,
                   [b.edge_bvh.id, x0, x1, b.edges, gap, self.thickness, m.inv_mass, self.rest,
                    done, active, record, ee_pairs, npairs], device=d)

    def _cand_alloc(self, vt: int, ee: int) -> None:
        """Candidate lists of ``vt`` vertex-triangle and ``ee`` edge-edge pairs (allocation:
        outside any captured step); the next detection builds them."""
        d = self.device
        self._cand_vt = wp.zeros(max(int(vt), 1), dtype=wp.vec2i, device=d)
        self._cand_ee = wp.zeros(max(int(ee), 1), dtype=wp.vec2i, device=d)
        self._cand_threads = record_threads(max(int(vt), int(ee), 1), d)
        self._cand_gap.fill_(-1.0)

    def candidate_stats(self) -> dict:
        """The candidate lists' counts so far (host read): ``builds``, ``overflows`` (builds
        that did not fit: those detections ran by the BVHs), the most pairs a build listed
        (``most_vt``, ``most_ee``) and the lists' room (``room_vt``, ``room_ee``); empty
        without lists."""
        if self._cand is None:
            return {}
        c = self._cand_stats.numpy()
        return {"builds": int(c[0]), "overflows": int(c[1]), "most_vt": int(c[2]),
                "most_ee": int(c[3]), "room_vt": int(self._cand_vt.shape[0]),
                "room_ee": int(self._cand_ee.shape[0])}

    # ------------------------------------------------------------------ spans
    def plan(self, substeps: int, motion: float) -> None:
        """Frames of ``substeps`` solver steps: the response runs once a span of steps has
        moved some vertex more than ``motion`` thicknesses since the last response, and always
        on a frame's last step (`CollisionStage`'s ``self_motion``); ``motion`` 0 or one step a
        frame: after every step. The decision is on the device (`wp.capture_if` on a flag that
        `span_step_kernel` sets), so a recorded frame graph stays valid; the frame's steps are
        counted on the device too (every step records the same launches), from this call or
        `restart_span` on, which is why the runner must step whole frames (it does)."""
        self._frame_k.zero_()
        if motion <= 0 or substeps <= 1:
            self.frame_steps = None
            return
        self.frame_steps = int(substeps)
        if self._held_record is None:  # `_fallback_held` (allocated here, outside a capture)
            self._held_record = make_record(self.capacity, self.device)
        self._reach = float(motion) * self.thickness
        self.reach_max = max(self._reach, 0.5 * (self.clearance - CLEAR_SPARE * self.thickness))
        # allowances pay (a pass like one detection a response) only where spans can save
        # responses: frames of many steps. Measured on the 32x32 fold, ms/frame with / without
        # them: projective dynamics (3 steps a frame) 188 / 125, implicit Euler (2) 351 / 266;
        # explicit Euler (185) 136, PBD (64) 159 against 257 before
        self.allowances = self._allowances and self.frame_steps >= ALLOWANCE_STEPS
        if self._span is None:
            d, n = self.device, self.model.num_vertices
            self._span = (wp.zeros(n, dtype=wp.vec3, device=d),  # start positions
                          wp.zeros(1, dtype=int, device=d),  # steps in the span
                          wp.zeros(1, dtype=int, device=d))  # respond now
            self._allow = wp.zeros(n, dtype=float, device=d)  # per vertex, `clear`
            self._active = wp.zeros(n, dtype=int, device=d)  # per vertex, `active_kernel`
            self._clear_boxes = [wp.zeros(k, dtype=wp.vec3, device=d) for k in
                                 (self.broad.num_tris, self.broad.num_tris,
                                  self.broad.num_edges, self.broad.num_edges, n, n)]
            self._clear_bvh = None
            # the last full pass's positions and allowances; moved flags and their count; a
            # full pass due (`clear`)
            self._ref = wp.zeros(n, dtype=wp.vec3, device=d)
            self._allow_ref = wp.zeros(n, dtype=float, device=d)
            self._moved = wp.zeros(n, dtype=int, device=d)
            self._nmoved = wp.zeros(1, dtype=int, device=d)
            self._still = wp.zeros(1, dtype=float, device=d)
            self._full = wp.ones(1, dtype=int, device=d)
        if self.allowances and self._clear_bvh is None:  # BVHs built now, not in a capture
            x = wp.array(self.model.mesh.vertices, dtype=wp.vec3, device=self.device)
            self._clear_bounds(x, True)
            if self.broad.method == "bvh":
                self.broad.update(x, x, self.thickness, vertices=True)
        self._allow.fill_(-1.0)  # until the first response: none (``reach`` everywhere)
        self._full.fill_(1)  # and its pass is a full one

    def restart_span(self) -> None:
        """The next step starts a frame (of a run from a new state: allowances back to
        ``reach``, and no contacts from the last response for `hold` to project: the last
        run's, projected onto the new start, moved the fold under PBD 10 cm off its first
        run)."""
        self._frame_k.zero_()
        self.record.count.zero_()
        if self._span is not None:
            self._allow.fill_(-1.0)
            self._full.fill_(1)

    def clear(self, x) -> None:
        """Each vertex's allowance for the next span: how far it may move before a pair it
        belongs to could come within the thickness ``h``. A pair at distance ``d`` (vertex-
        triangle or edge-edge, not adjacent) changes its distance by at most the largest
        displacement on one side plus the largest on the other, so if each of its vertices moves
        at most ``(d - h) / 2`` it stays ``h`` apart; a vertex's allowance is the least over its
        pairs, and at most ``(clearance - h) / 2``, which covers every pair farther than
        ``clearance`` (the query boxes, inflated by half of it each, find every nearer pair). The
        span then waits for a vertex to pass ``max(reach, allowance)``: near other layers as
        before (``reach``), much longer where the cloth is clear of itself.

        A full pass looks at every pair; while fewer than a quarter of the vertices moved more
        than the reach since the last full pass, a partial one looks only at the pairs of those
        (from the moved vertex, from a triangle with a moved corner, from an edge with a moved
        vertex), and every other vertex keeps the full pass's allowance less the farthest a
        still vertex went (a pair of still vertices is at most twice that closer): a lower
        bound, never above the exact allowance. The choice is a device-side flag
        (`wp.capture_if`): capturable."""
        d = self.device
        self._nmoved.zero_()
        self._still.zero_()
        launch(clearance_moved_kernel, self.model.num_vertices,
               [x, self._ref, self._reach, CLEAR_FULL_FRACTION, self._moved, self._still,
                self._nmoved, self._full], device=d)
        wp.capture_if(self._full, on_true=self._clear_full, on_false=self._clear_part, x=x)

    def _clear_bounds(self, x, vertices: bool):
        d, b = self.device, self.broad
        half = 0.5 * self.clearance
        tl, tu, el, eu, vl, vu = self._clear_boxes
        launch(cloth_bounds_kernel, b.num_tris + b.num_edges,
               [x, x, b.tris, b.edges, b.num_tris, half, tl, tu, el, eu], device=d)
        if vertices:
            launch(vertex_bounds_kernel, len(x), [x, x, half, vl, vu], device=d)
        if self._clear_bvh is None:
            self._clear_bvh = (wp.Bvh(tl, tu), wp.Bvh(el, eu), wp.Bvh(vl, vu))
        else:
            for bvh in self._clear_bvh[:3 if vertices else 2]:
                bvh.refit()
        return half

    def _clear_full(self, x):
        # every pair within the clearance; the result is the next passes' reference
        d, b, m = self.device, self.broad, self.model
        launch(fill_kernel, len(self._allow), [self._allow, self.reach_max], device=d)
        half = self._clear_bounds(x, self._clear_bvh is None)
        tb, eb = self._clear_bvh[:2]
        el, eu = self._clear_boxes[2:4]
        if b.num_tris:
            launch(clearance_vt_kernel, m.num_vertices,
                   [tb.id, x, b.tris, m.inv_mass, self.rest, half, self.thickness, self._no_int,
                    self._allow], device=d)
        if b.num_edges:
            launch(clearance_ee_kernel, b.num_edges,
                   [eb.id, x, b.edges, m.inv_mass, self.rest, el, eu, self.thickness,
                    self._no_int,
                    self._allow], device=d)
        launch(clearance_keep_kernel, m.num_vertices,
               [x, self._allow, self._ref, self._allow_ref, self._full],
               device=d)

    def _clear_part(self, x):
        # the pairs with a vertex that moved since the last full pass; the others keep that
        # pass's allowance less the farthest a still vertex went
        d, b, m = self.device, self.broad, self.model
        launch(clearance_start_kernel, m.num_vertices, [self._allow_ref, self._still,
                                                       self._allow], device=d)
        half = self._clear_bounds(x, True)
        tb, eb, vb = self._clear_bvh
        el, eu = self._clear_boxes[2:4]
        if b.num_tris:
            launch(clearance_vt_kernel, m.num_vertices,
                   [tb.id, x, b.tris, m.inv_mass, self.rest, half, self.thickness, self._moved,
                    self._allow], device=d)
            tl, tu = self._clear_boxes[:2]
            launch(clearance_tv_kernel, b.num_tris,
                   [vb.id, tl, tu, x, b.tris, m.inv_mass, self.rest, self.thickness,
                    self._moved,
                    self._allow], device=d)
        if b.num_edges:
            launch(clearance_ee_kernel, b.num_edges,
                   [eb.id, x, b.edges, m.inv_mass, self.rest, el, eu, self.thickness,
                    self._moved,
                    self._allow], device=d)

    def step(self, state, x_start, dt: float, obstacles=None) -> None:
        """Self-collision after one solver step: `resolve` every step, or once per span
        (`plan`), with the last response's contacts held in between (`hold`). ``obstacles``:
        a callable that keeps the vertices out of the obstacles (the collision stage's vertex
        contact on this step's path), run inside every round after its projection, so that the
        next round's detection sees what it moved (`_round`); called with an array it projects
        that array instead, and its ``still`` attribute (a device flag: every obstacle stands
        still this step) lets the impact zones hold a zone it would push (`ImpactZones.
        hold_grounded`)."""
        self._obstacles = obstacles
        if self.frame_steps is None:
            self.resolve(state, x_start, dt)
            return
        start, steps, flag = self._span
        d = self.device
        # a frame starts a span (the previous frame ended with a response); the frame's steps
        # are counted on the device, so every step records the same launches (the runner may
        # record a few steps as a graph and replay it through the frame: `uniform_steps`)
        launch(span_begin_kernel, len(start), [x_start, start, steps, flag, self._frame_k],
               device=d)
        self.hold(state)
        launch(span_step_kernel, len(start), [state.x, state.v, self.acc, self.cnt, self._frame,
                                              start,
                                              self._reach, self._reach_share, self._allow,
                                              self._frame_k, self.frame_steps, steps, flag],
               device=d)
        wp.capture_if(flag, self._span_resolve, state=state, dt=dt)

    def _span_resolve(self, state, dt):
        start, steps, flag = self._span
        # the detections may use the allowances (the BVH broad phase has the vertices' BVH)
        self._in_span = self.allowances and self.broad.method == "bvh"
        # the span's detections also record the pairs within twice the reach beyond the
        # thickness (projected only once closer than it): `hold` keeps those from sinking into
        # each other in the next span, and every other pair's vertices have an allowance of
        # at least the reach. Measured (drape, explicit, 120 frames): the largest one-frame
        # energy rise 6.5e-4 J with the thickness as gap (each response undid a span's
        # sinking at once), none with this gap
        if self.allowances:
            self._gap = self.thickness + 2.0 * self._reach
        try:
            self.resolve(state, start, dt, steps)
        finally:
            self._in_span = False
            self._gap = self.thickness
        if self.allowances:
            self.clear(state.x)
        launch(span_begin_kernel, len(start), [state.x, start, steps, flag, self._no_int],
               device=self.device)

    def hold(self, state) -> None:
        """One Jacobi projection of the contacts the last `resolve` found (no detection), into
        ``acc`` / ``cnt``: keeps a layer resting on another from sinking into it between the
        responses of a span (`CollisionStage.plan`, whose `span_step_kernel` applies it)."""
        launch(jacobi_project_kernel, self.threads,
               [self.record, 0, state.x, self.model.inv_mass, self.acc, self.cnt, self._held,
                0.01 * self.thickness, self.threads, self._no_moved, self._no_moved,
                state.v if self.layer_frames else self._no_moved, self._frame],
               device=self.device)

    def _project(self, state, dt):
        m, d = self.model, self.device
        for _ in range(self.iterations):
            launch(jacobi_project_kernel, self.threads,
                   [self.record, 0, state.x, m.inv_mass, self.acc, self.cnt, self.violated,
                    0.01 * self.thickness, self.threads, self._no_moved, self._no_moved,
                    state.v if self.layer_frames else self._no_moved, self._frame], device=d)
            launch(layer_apply_kernel, m.num_vertices,
                   [state.x, state.v, self.acc, self.cnt, self._frame], device=d)

    def resolve(self, state, x_start, dt: float, steps=None) -> None:
        """Rounds of detection and response on ``x_start -> state.x``, then the impact zones.
        ``steps``: a device array whose first entry is the number of solver steps of ``dt``
        the path spans (`CollisionStage` spans; default one step): velocity changes are the
        path's mean velocity changes.
        The rounds run in a device-side loop (`wp.capture_while`) that stops once a round's
        projection finds every contact satisfied (``done``) or after ``rounds``; the impact
        zones and the last resort run only if it stopped short (`wp.capture_if`). In a recorded
        graph both are conditional nodes: no host read, and a step without contacts pays one
        round. Run eagerly, Warp reads the flags on the host."""
        m, d = self.model, self.device
        launch(step_begin_kernel, max(len(STAT_KEYS), 1),
               [self.done, self.violated, self._flags, self.counters], device=d)
        steps = self._one if steps is None else steps
        # a diverged solve (`DIVERGED_STRAIN`): the whole cloth back, nothing detected
        self._diverged.zero_()
        launch(diverged_kernel, self.broad.num_edges,
               [state.x, self.broad.edges, self.rest, DIVERGED_STRAIN, self._diverged], device=d)
        wp.capture_if(self._diverged, on_true=self._revert_all, on_false=self._respond,
                      state=state, x_start=x_start, dt=dt, steps=steps)
        launch(accumulate_kernel, len(STAT_KEYS), [self.counters, self.totals], device=d)

    def _respond(self, state, x_start, dt, steps):
        wp.capture_while(self._flags[1:2], self._round, state=state, x_start=x_start, dt=dt)
        wp.capture_if(self._flags[2:3], self._fallback_held, state=state, x_start=x_start,
                      dt=dt, steps=steps)

    def _fallback_held(self, state, x_start, dt, steps):
        """`_fallback`, with the rounds' contacts kept for `hold` when the response runs in
        spans: the fall-back's detections (at 5 % of the thickness) leave the record with
        none of them, and the next span's steps would let the layers sink into each other
        unheld until its response pushed them back out. Measured (three sheets stacked on a
        sphere, explicit Euler, 116 steps a frame): rounds that ended short every response
        from frame 75 on, each response then pushing the same vertices of the middle sheet
        1.1-1.3 mm back out against their springs (2-4.7 mJ of elastic energy a response),
        and the cloth's energy rose 0.806 -> 0.852 J over frames 70-80 (PBD: 0.046 J over
        frames 40-120)."""
        if self._held_record is None:
            self._fallback(state, x_start, dt, steps)
            return
        d = self.device
        launch(record_stash_kernel, self.threads, [self.record, self._held_record,
                                                   self.threads], device=d)
        self._fallback(state, x_start, dt, steps)
        launch(record_stash_kernel, self.threads, [self._held_record, self.record,
                                                   self.threads], device=d)

    def _revert_all(self, state, x_start, dt, steps):
        m = self.model
        launch(revert_all_kernel, m.num_vertices,
               [state.x, state.v, x_start, m.inv_mass, self.counters], device=self.device)

    #: `step`'s ``obstacles`` callable (None: no obstacles)
    _obstacles = None
    #: the rounds' contacts across a fall-back, for `hold` (`_fallback_held`; made by `plan`)
    _held_record = None
    #: the solve's detection (`note_solve`): (record, gap, threads), or None
    _sol = None

    #: steps of the last frame (`frame_end`) that returned the whole cloth to its start or
    #: dropped contacts, plus one if its impact zones held most of the cloth (``frame_frozen``)
    frame_failed = 0
    #: the last frame's responses held on average `FROZEN_SHARE` of the free vertices in rigid
    #: impact zones, or at least that share of them returned the whole cloth to its start (its
    #: steps tangle the cloth everywhere)
    frame_frozen = False
    #: at least `FROZEN_SHARE` of the last frame's responses met a diverged solve
    #: (`DIVERGED_STRAIN`)
    frame_diverged = False

    def _round(self, state, x_start, dt):
        if self._incremental is None:
            self.record.count.zero_()
            self.record.overflow.zero_()
            self.detect(x_start, state.x, self._gap, self.record, self.done)
        else:
            # after the first round only the vertices the last projection moved have new
            # paths: the entries of the others are kept and only pairs with a moved vertex are
            # detected again (`_round_incremental`); a full detection after one that dropped
            # entries. A device-side choice (`wp.capture_if`): capturable
            launch(round_begin_kernel, self.model.num_vertices,
                   [state.x, self._x_round, self.record, self._flags, self._moved_round,
                    self._incremental], device=self.device)
            self.record.overflow.zero_()
            self._reuse_or(x_start, state.x, self._gap, self._round_detect, self._reuse_round)
            wp.copy(self._x_round, state.x)
        self._project(state, dt)
        if self._obstacles is not None:
            # the projection splits a pair's correction between its layers and can push a
            # layer lying on an obstacle into it; pushed back out here, the next round's
            # detection checks the layers again. A round whose projection moved nothing
            # (the last) leaves nothing for this to move: the rounds end clear of both
            self._obstacles()
        launch(deep_path_kernel, self.threads, [self.record, x_start, state.x,
                                                self.model.inv_mass, self.violated, self.done,
                                                self.threads], device=self.device)
        launch(round_end_kernel, 1, [self.record, self.violated, self.done, self.counters,
                                     self._flags, self.rounds], device=self.device)

    def _detect_full(self, x_start, x, gap):
        self.record.count.zero_()
        self.detect(x_start, x, gap, self.record, self.done)

    def _round_detect(self, x_start, x, gap):
        """A round's detection without the solve's: incremental after the first round."""
        wp.capture_if(self._incremental, on_true=self._round_incremental,
                      on_false=self._detect_full, x_start=x_start, x=x, gap=gap)

    def _zone_detect(self, x_start, x, gap):
        """A zone pass's detection without the solve's: incremental in the first pass."""
        wp.capture_if(self._zone_incremental, on_true=self._zone_detect_incremental,
                      on_false=self._detect_full, x_start=x_start, x=x, gap=gap)

    def _reuse_or(self, x_start, x, gap, otherwise, reuse):
        """A response's detection (its rounds' and zone passes') from the solve's where that
        holds every contact, else ``otherwise``. The solve detected its pairs on the paths
        ``s0 -> s1`` with a gap ``g_s`` larger than this one's ``g`` (`note_solve`); a vertex
        whose path ends here are both within ``(g_s - g) / 2`` of those is *near*. Two elements
        of near vertices are never more than ``g_s - g`` closer on these paths than on the
        solve's at the same time, so a pair of four near vertices that comes within ``g``
        here came within ``g_s`` there and is an entry of the solve's record: those entries
        are tested again (`solve_retest_kernel`, skipping pairs with a far vertex) and the
        pairs with a far vertex are detected by the BVHs (``active`` = the far vertices).
        After a response's first round only the solve's entries with a vertex the last
        projection moved are tested again (``reuse``: `_reuse_round` keeps the last round's
        entries of unmoved near vertices, `_reuse_zone` tests them again at the zone passes'
        smaller gap).
        Exactly a full detection's contacts; a device-side choice (`wp.capture_if`), the
        ``otherwise`` detection when the solve's record dropped entries or more than
        `SOLVE_MOST_FAR` of the vertices are far (a span's response, whose path starts steps
        before the solve's: the BVHs' traversal for most of the cloth costs more than the
        candidate lists' scan). Measured on the 16 x
        16 fold (PD, frames 30-50): no far vertex in 59 of 60 responses; on the twist at
        frame 150: 18 of 2,500 far, the rest within 2.3 mm of 2.5; there the rounds had
        scanned the whole candidate lists (225k edge-edge pairs) four times a step for the
        few hundred vertices each projection moved, and the first round built new lists
        every other step."""
        sol = self._sol
        if sol is None or float(gap) >= sol[1]:  # host: fixed for a recorded graph
            otherwise(x_start, x, gap)
            return
        d = self.device
        allow = 0.5 * (sol[1] - float(gap)) * (1.0 - SOLVE_ALLOW_MARGIN)
        self._sol_flags.zero_()
        n = self.model.num_vertices
        launch(solve_far_kernel, n,
               [x_start, x, self._sol_x0, self._sol_x1, allow, self._moved_round,
                self._sol_far, self._sol_either, self._sol_flags], device=d)
        launch(solve_use_kernel, 1,
               [self._sol_ok, int(SOLVE_MOST_FAR * n), self._sol_flags, self.counters],
               device=d)
        wp.capture_if(self._sol_flags[0:1], on_true=reuse, on_false=otherwise,
                      x_start=x_start, x=x, gap=gap)

    def _reuse_round(self, x_start, x, gap):
        wp.capture_if(self._incremental, on_true=self._reuse_kept, on_false=self._reuse_all,
                      x_start=x_start, x=x, gap=gap)

    def _reuse_zone(self, x_start, x, gap):
        wp.capture_if(self._zone_incremental, on_true=self._reuse_retested,
                      on_false=self._reuse_all, x_start=x_start, x=x, gap=gap)

    def _reuse_all(self, x_start, x, gap):
        """Every solve entry of near vertices tested again, the far vertices' pairs by BVH."""
        self.record.count.zero_()
        self._reuse_rest(x_start, x, gap, self._no_int)

    def _reuse_kept(self, x_start, x, gap):
        """A later round: the last round's entries of unmoved near vertices kept, the solve's
        entries with a moved near vertex tested again, the far vertices' pairs by BVH."""
        self._keep_unmarked(self._sol_either)
        self._reuse_rest(x_start, x, gap, self._moved_round)

    def _reuse_retested(self, x_start, x, gap):
        """A zone pass's first detection: as `_reuse_kept`, the kept entries tested again at
        its gap."""
        self._retest_unmarked(self._sol_either, x_start, x, gap)
        self._reuse_rest(x_start, x, gap, self._moved_round)

    def _keep_unmarked(self, marked):
        """The record's entries with no vertex in ``marked`` kept, the others dropped."""
        d = self.device
        launch(record_stash_kernel, self.threads, [self.record, self._stash, self.threads],
               device=d)
        self.record.count.zero_()
        launch(record_keep_kernel, self.threads, [self._stash, marked, self.record,
                                                  self.threads], device=d)

    def _retest_unmarked(self, marked, x_start, x, gap):
        """The record's entries with no vertex in ``marked`` tested again on the paths
        ``x_start -> x`` with ``gap`` (kept where they hit), the others dropped."""
        d = self.device
        launch(record_stash_kernel, self.threads, [self.record, self._stash, self.threads],
               device=d)
        self.record.count.zero_()
        launch(record_retest_kernel, self.threads,
               [self._stash, marked, x_start, x, gap, self.thickness, self.rest, self.record,
                self.threads], device=d)

    def _reuse_rest(self, x_start, x, gap, moved):
        rec, _, threads = self._sol
        d = self.device
        launch(solve_retest_kernel, threads,
               [rec, self._sol_far, moved, x_start, x, gap, self.thickness, self.rest,
                self.record, threads], device=d)
        wp.capture_if(self._sol_flags[1:2], self._query_bvh, x0=x_start, x1=x,
                      gap=float(gap), record=self.record, done=self.done,
                      active=self._sol_far)

    def _round_incremental(self, x_start, x, gap):
        self._keep_unmarked(self._moved_round)
        self._detect_moved(x_start, x, gap)

    def _detect_moved(self, x_start, x, gap):
        """The pairs with a vertex marked in ``_moved_round`` that come within ``gap`` on the
        paths ``x_start -> x``, appended to the record."""
        self._query(x_start, x, gap, self.record, self.done, self._no_pairs, self._no_pairs,
                    self._npairs, moved=self._moved_round)

    def _fallback(self, state, x_start, dt, steps):
        # what is left after the last round: paths that still come within 5 % of the thickness
        # (all but touching: a crossing would pass through zero), fresh detection. Pairs merely
        # closer than the thickness (a fold tighter than it, a contact the rounds did not
        # separate fully) are not a failure and keep their motion. Rigid impact zones, grown
        # over `zone_passes` detections, then the whole cloth back to its start
        m, d = self.model, self.device
        gap = FAILSAFE_GAP * self.thickness
        self.zones.reset()
        # the passes and the last detection as a device-side loop: a recorded graph holds one
        # detection, not ``zone_passes + 1`` (recording the explicit hanging scene's frame
        # graph, 185 steps each with its fall-back: 7.1 s with the passes unrolled, 4.2 s)
        launch(zone_begin_kernel, 1, [self._zone_flags, self.zone_passes], device=d)
        if self._incremental is not None:
            # the first pass's detection as the rounds': only the pairs with a vertex the last
            # projection moved are detected, the last round's other entries tested again at
            # the fail-safe gap (a pair not among them was farther than the rounds' gap on
            # this same path). Later passes follow rigid zone moves: full detections
            launch(round_begin_kernel, m.num_vertices,
                   [state.x, self._x_round, self.record, self._flags, self._moved_round,
                    self._zone_incremental], device=d)
        # the last round's overflow is counted (`round_end_kernel`); the passes count theirs
        self.record.overflow.zero_()
        wp.capture_while(self._zone_flags[1:2], self._zone_pass, state=state, x_start=x_start,
                         dt=dt, steps=steps, gap=gap)
        launch(revert_kernel, self.threads,
               [self.record, state.x, state.v, x_start, m.inv_mass, self.counters, I_FALLBACK,
                self.threads], device=d)

    def _zone_pass(self, state, x_start, dt, steps, gap):
        if self._incremental is None:
            self._detect_full(x_start, state.x, gap)
        else:
            self._reuse_or(x_start, state.x, gap, self._zone_detect, self._reuse_zone)
            self._zone_incremental.zero_()
        wp.capture_if(self._zone_flags[2:3], self._zone_move, state=state, x_start=x_start,
                      dt=dt, steps=steps)
        launch(zone_pass_kernel, 1, [self.record, self._zone_flags, self.zone_passes,
                                     self.counters], device=self.device)

    def _zone_detect_incremental(self, x_start, x, gap):
        self._retest_unmarked(self._moved_round, x_start, x, gap)
        self._detect_moved(x_start, x, gap)

    def _zone_move(self, state, x_start, dt, steps):
        self.zones.merge(self.record, self.threads)
        self.zones.move(self.record, x_start, state, dt, self.counters, I_ZONES, steps)
        still = getattr(self._obstacles, "still", None)
        if still is not None:
            self.zones.hold_grounded(x_start, state, self._obstacles, still, self.counters,
                                     I_HELD)

    def frame_end(self) -> list:
        """Since the last call: steps that returned the whole cloth to its start, frames whose
        rigid impact zones held on average at least `FROZEN_SHARE` of the free vertices per
        response (measured: explicit Euler at k = 1e6 N/m and two steps a frame, far past its
        stable step, froze the whole cloth in every response and ran on without a word: without
        self-collision the divergence guard stops it) or in which at least that share of the
        responses returned the whole cloth to its start (both ``frame_frozen``), and dropped
        contacts (the record's room then grows). ``(message, regrown)`` pairs (message None:
        the candidate lists grew, nothing to report); host reads, once a frame
        (`CollisionStage.frame_end`)."""
        t = self.totals.numpy()
        seen = getattr(self, "_seen", None)
        self._seen = t.copy()
        if seen is None:
            seen = 0 * t
        out = []
        i_all, i_over = STAT_KEYS.index("self_fallback_all"), STAT_KEYS.index("self_overflow")
        i_pin = STAT_KEYS.index("self_pinned")
        if t[i_pin] > seen[i_pin]:
            out.append((f"self-collision: {t[i_pin] - seen[i_pin]} step(s) left a contact at a "
                        "pinned vertex, which the response cannot move (the pins press the "
                        "cloth into itself)", False))
        i_zv, i_resp = STAT_KEYS.index("self_zone_vertices"), STAT_KEYS.index("self_responses")
        zv, resp = t[i_zv] - seen[i_zv], t[i_resp] - seen[i_resp]
        zoned = bool(resp > 0 and zv >= FROZEN_SHARE * self._free * resp)
        # a frame most of whose responses returned the whole cloth to its start did not move
        # either (measured: PBD's twist from frame 109, 246 of 256 steps, at 128 and 256 steps
        # a frame too, ran on with the cloth standing still)
        returned = int(t[i_all] - seen[i_all])
        standing = not zoned and bool(resp > 0 and returned >= FROZEN_SHARE * resp)
        self.frame_frozen = zoned or standing
        i_div = STAT_KEYS.index("self_diverged")
        diverged = int(t[i_div] - seen[i_div])
        #: most of the frame's responses met a diverged solve (`DIVERGED_STRAIN`)
        self.frame_diverged = bool(resp > 0 and diverged >= FROZEN_SHARE * resp)
        if diverged:
            out.append((f"self-collision: {diverged} of the frame's {resp} response(s) met a "
                        f"solve that stretched a mesh edge past {100 * DIVERGED_STRAIN:,.0f} % "
                        "or left a position not finite (a diverged step: an unstable solver "
                        "step; explicit Euler: let it choose its substeps) and returned the "
                        "whole cloth to its start without detecting", False))
        if zoned:
            out.append((f"self-collision moved on average {zv / resp:.0f} of the cloth's "
                        f"{self._free} free vertices as rigid impact zones in the frame's {resp} "
                        "response(s): most of the cloth was frozen into rigid bodies (its steps "
                        "tangle it everywhere: an unstable solver step, or cloth crushed into "
                        "itself)", False))
        elif standing and returned > diverged:  # (a diverged frame's message says it)
            out.append((f"self-collision returned the whole cloth to its start in {returned} of "
                        f"the frame's {resp} response(s): the cloth was frozen (its steps "
                        "tangle it everywhere: an unstable solver step, or cloth crushed into "
                        "itself)", False))
        # steps of the frame that returned the whole cloth to its start or dropped contacts:
        # the runner may run the frame again with more steps (`Scene`'s ``retries``)
        self.frame_failed = returned + int(t[i_over] - seen[i_over]) + int(self.frame_frozen)
        if returned > diverged and not standing:  # (the messages above say the others)
            out.append((f"self-collision returned the whole cloth to its start in "
                        f"{returned - diverged} step(s): contacts the projection and the "
                        "impact zones could not resolve", False))
        if t[i_over] > seen[i_over]:
            # at least doubled; by what was dropped (summed over the frame's detections: an
            # upper bound) when more, so that a frame run again (`Scene`'s ``retries``) fits
            dropped = int(t[i_over] - seen[i_over])
            self.grow(max(2 * self.capacity, self.capacity + dropped))
            out.append((f"{dropped} self-contacts did not fit the record; its room grows to "
                        f"{self.capacity} entries", True))
        if self._cand is not None:
            c = self._cand_stats.numpy()
            if c[1] > self._cand_grown:  # a build did not fit: those detections used the BVHs
                self._cand_grown = int(c[1])
                self._cand_alloc(max(self._cand_vt.shape[0], int(1.5 * c[2])),
                                 max(self._cand_ee.shape[0], int(1.5 * c[3])))
                out.append((None, True))  # nothing to report; a recorded graph is recorded again
        return out

    def grow(self, capacity: int) -> None:
        """A record of ``capacity`` entries (allocation: outside any captured step)."""
        self.capacity = int(capacity)
        self.record = make_record(self.capacity, self.device)
        self.threads = record_threads(self.capacity, self.device)
        if self._held_record is not None:
            self._held_record = make_record(self.capacity, self.device)
        if self._incremental is not None:
            self._stash = make_record(self.capacity, self.device)

    @property
    def stats(self) -> dict:
        """The last step's counts, and (``*_total``) their sums over every step so far; with
        candidate lists, their counts so far (`candidate_stats`) as ``self_list_*``."""
        c, t = self.counters.numpy(), self.totals.numpy()
        out = {k: int(v) for k, v in zip(STAT_KEYS, c)}
        out.update({k + "_total": int(v) for k, v in zip(STAT_KEYS, t)})
        out.update({"self_list_" + k: v for k, v in self.candidate_stats().items()})
        return out
