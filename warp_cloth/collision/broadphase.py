"""Broad phase over the cloth's own triangles and edges: swept boxes in two `wp.Bvh`, or their
centres in two `wp.HashGrid`.

Every step the box of each cloth triangle and edge over its path from ``x0`` to ``x1`` (start and
end positions: a linear path stays inside the box of its ends), inflated by a pad, is written by
one kernel and the two BVHs are refitted. A query with the swept box of another primitive (an
obstacle feature, or a cloth vertex or edge for self-collision) inflated the same way returns
every primitive whose box overlaps it: no pair whose swept boxes overlap is missed (Warp's BVH
query is exact on boxes). Two elements that come within a distance ``g`` of each other at some
time of their paths have, at that time, points less than ``g`` apart along every axis, each
inside its element's swept box; so their boxes inflated by ``g / 2`` each overlap, and a pad of
half the contact gap on both sides finds every pair that can come within the gap (`padded` adds
a few float32 ulps of the coordinates, so rounding cannot shrink a box below that). The BVHs
are built on the first call (outside any capture: the scene runner captures from its second
frame) and then refitted; Warp records a CPU refit in a captured graph and re-runs it on
replay, and on CUDA the refit is a kernel, so steps stay capturable.

**Hash grid** (``method="grid"``): the centres of the same swept boxes are bucketed in a
`wp.HashGrid` (one for triangles, one for edges), rebuilt every step (Warp records a CPU build in a
captured graph and re-runs it on replay; on CUDA the build is kernels), and the largest half
diagonal of any stored box is kept on the device (``rmax``). A query element with swept box of
centre ``c`` and half diagonal ``r`` asks the grid for every point within ``R = rmax + r`` of ``c``
and keeps those whose box overlaps its own. Nothing is missed: two boxes overlap only if along
each axis their centres are at most the sum of their half extents apart, so the centres are at
most ``|h_a + h_b| <= |h_a| + |h_b| <= rmax + r = R`` apart, and the grid visits every cell that
meets the cube of half side ``R`` around ``c`` (its range is clamped to the grid's dimensions, so
no cell is visited twice and no pair is reported twice; far from the origin and at negative
coordinates the cells wrap around the hash, which only adds candidates). ``R`` is padded by a few
float32 ulps of the coordinates so rounding in the cell computation cannot drop a point on a cell
boundary. One long element (a fast or over-stretched triangle) raises ``rmax`` and so the query
range of every element for that step: the grid is then slower, never wrong.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..util import launch

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile

__all__ = ["ClothBroadPhase", "BROADPHASE_METHODS", "grid_radius", "padded"]

BROADPHASE_METHODS = ("grid", "bvh")


@wp.func
def grid_radius(c: wp.vec3, r: float, rmax: float):
    """Query radius around centre ``c`` covering every stored box that can overlap a box of
    half diagonal ``r`` (module docstring), padded for float32 rounding of the cell index."""
    big = wp.max(wp.max(wp.abs(c[0]), wp.abs(c[1])), wp.abs(c[2])) + r + rmax
    return (r + rmax) * 1.0001 + 4.0e-7 * big


@wp.func
def boxes_overlap(alo: wp.vec3, ahi: wp.vec3, blo: wp.vec3, bhi: wp.vec3):
    return (alo[0] <= bhi[0] and blo[0] <= ahi[0] and alo[1] <= bhi[1] and blo[1] <= ahi[1]
            and alo[2] <= bhi[2] and blo[2] <= ahi[2])


@wp.kernel
def box_centres_kernel(lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3),
                       centres: wp.array(dtype=wp.vec3), rmax: wp.array(dtype=float), slot: int):
    """Centres of the boxes and the largest half diagonal into ``rmax[slot]``."""
    k = wp.tid()
    lo = lowers[k]
    hi = uppers[k]
    centres[k] = 0.5 * (lo + hi)
    wp.atomic_max(rmax, slot, 0.5 * wp.length(hi - lo))


#: relative float32 rounding allowance of a padded box's corner (`padded`)
BOX_ROUNDING = wp.constant(2.5e-7)


@wp.func
def padded(lo: wp.vec3, hi: wp.vec3, pad: float):
    """The box ``lo, hi`` inflated by ``pad``, and by four float32 ulps of its corners more:
    the rounding of ``lo - pad`` (at most one ulp of the result) cannot shrink it below the
    exact inflation, so two boxes inflated by ``g / 2`` each overlap whenever their contents
    come within ``g`` (module docstring), at any distance from the origin."""
    return (lo - wp.vec3(pad) - BOX_ROUNDING * wp.abs(lo),
            hi + wp.vec3(pad) + BOX_ROUNDING * wp.abs(hi))


@wp.func
def vertex_box(x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3), v: int, pad: float):
    """Vertex ``v``'s swept box, inflated by ``pad`` (`padded`)."""
    return padded(wp.min(x0[v], x1[v]), wp.max(x0[v], x1[v]), pad)


@wp.kernel
def vertex_bounds_kernel(x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3), pad: float,
                         lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
    """Swept boxes of the vertices, inflated by ``pad``."""
    i = wp.tid()
    lo, hi = vertex_box(x0, x1, i, pad)
    lowers[i] = lo
    uppers[i] = hi


@wp.kernel
def cloth_bounds_kernel(x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
                        tris: wp.array2d(dtype=wp.int32), edges: wp.array2d(dtype=wp.int32),
                        num_tris: int, pad: float, lowers: wp.array(dtype=wp.vec3),
                        uppers: wp.array(dtype=wp.vec3), elowers: wp.array(dtype=wp.vec3),
                        euppers: wp.array(dtype=wp.vec3)):
    """Swept boxes (start and end positions, inflated by ``pad``): threads below ``num_tris``
    for triangles, the rest for edges."""
    k = wp.tid()
    lo = wp.vec3(1.0e30)
    hi = wp.vec3(-1.0e30)
    if k < num_tris:
        for c in range(3):
            i = tris[k, c]
            lo = wp.min(lo, wp.min(x0[i], x1[i]))
            hi = wp.max(hi, wp.max(x0[i], x1[i]))
        lo, hi = padded(lo, hi, pad)
        lowers[k] = lo
        uppers[k] = hi
    else:
        e = k - num_tris
        for c in range(2):
            i = edges[e, c]
            lo = wp.min(lo, wp.min(x0[i], x1[i]))
            hi = wp.max(hi, wp.max(x0[i], x1[i]))
        lo, hi = padded(lo, hi, pad)
        elowers[e] = lo
        euppers[e] = hi


class ClothBroadPhase:
    """Swept boxes of a model's triangles and edges, in BVHs (``tri_bvh``, ``edge_bvh``) or hash
    grids of their centres (``tri_grid``, ``edge_grid``, with ``rmax``: module docstring).

    Args:
        model: the `ClothModel`.
        method: ``"bvh"`` (default; refitted each step) or ``"grid"`` (rebuilt each step).
    """

    def __init__(self, model, method: str = "bvh"):
        if method not in BROADPHASE_METHODS:
            raise ValueError(f"broad phase method {method!r}: expected one of {BROADPHASE_METHODS}")
        self.method = method
        d = self.device = model.device
        tris = np.asarray(model.mesh.triangles, dtype=np.int32)
        edges = np.asarray(model.mesh.edges, dtype=np.int32)
        self.num_tris, self.num_edges = len(tris), len(edges)
        self.tris = wp.array(tris, dtype=wp.int32, ndim=2, device=d)
        self.edges = wp.array(edges, dtype=wp.int32, ndim=2, device=d)
        self.lowers = wp.zeros(len(tris), dtype=wp.vec3, device=d)
        self.uppers = wp.zeros(len(tris), dtype=wp.vec3, device=d)
        self.elowers = wp.zeros(len(edges), dtype=wp.vec3, device=d)
        self.euppers = wp.zeros(len(edges), dtype=wp.vec3, device=d)
        self.tri_bvh = self.edge_bvh = self.vertex_bvh = None
        self.tri_grid = self.edge_grid = None
        if method == "grid":
            x = np.asarray(model.mesh.vertices, dtype=np.float64)
            span = [np.linalg.norm(x[tris[:, a]] - x[tris[:, b]], axis=1).max(initial=0.0)
                    for a, b in ((0, 1), (1, 2), (0, 2))]
            #: the longest rest edge: the grid's cells are about a rest triangle wide
            self.rest_span = max(max(span), 1e-6)
            self.centres = wp.zeros(len(tris), dtype=wp.vec3, device=d)
            self.ecentres = wp.zeros(len(edges), dtype=wp.vec3, device=d)
            self.rmax = wp.zeros(2, dtype=float, device=d)  # [triangles, edges]
            # a table of about 8 cells per element (a build clears the whole table: no larger)
            dim = int(min(128, max(8, np.ceil(np.cbrt(8 * max(len(tris), len(edges)))))))
            self.tri_grid = wp.HashGrid(dim, dim, dim, device=d)
            self.edge_grid = wp.HashGrid(dim, dim, dim, device=d)
            self.tri_grid.reserve(len(tris))
            self.edge_grid.reserve(len(edges))

    def build_vertex_bvh(self, x, pad: float) -> None:
        """The vertices' BVH (``vertex_bvh``) built now from positions ``x`` (boxes inflated by
        ``pad``), if it is not yet: an allocation, so not inside a recorded graph; `update`
        refits it. The triangles' and edges' BVHs are left to `update`'s first call."""
        if self.method != "bvh" or self.vertex_bvh is not None:
            return
        n = len(x)
        self.vlowers = wp.zeros(n, dtype=wp.vec3, device=self.device)
        self.vuppers = wp.zeros(n, dtype=wp.vec3, device=self.device)
        launch(vertex_bounds_kernel, n, [x, x, float(pad), self.vlowers, self.vuppers],
               device=self.device)
        self.vertex_bvh = wp.Bvh(self.vlowers, self.vuppers)

    def update(self, x0, x1, pad: float, vertices: bool = False) -> None:
        """Boxes of the paths ``x0 -> x1`` inflated by ``pad``, and the BVHs refitted;
        ``vertices``: also the vertices' boxes and their BVH ``vertex_bvh`` (BVH method only)."""
        launch(cloth_bounds_kernel, self.num_tris + self.num_edges,
               [x0, x1, self.tris, self.edges, self.num_tris, float(pad), self.lowers,
                self.uppers, self.elowers, self.euppers], device=self.device)
        if vertices and self.method == "bvh":
            if self.vertex_bvh is None:
                n = len(x0)
                self.vlowers = wp.zeros(n, dtype=wp.vec3, device=self.device)
                self.vuppers = wp.zeros(n, dtype=wp.vec3, device=self.device)
            launch(vertex_bounds_kernel, len(x0), [x0, x1, float(pad), self.vlowers,
                                                   self.vuppers], device=self.device)
            if self.vertex_bvh is None:
                self.vertex_bvh = wp.Bvh(self.vlowers, self.vuppers)
            else:
                self.vertex_bvh.refit()
        if self.method == "grid":
            self.rmax.zero_()
            if self.num_tris:
                launch(box_centres_kernel, self.num_tris,
                       [self.lowers, self.uppers, self.centres, self.rmax, 0], device=self.device)
            if self.num_edges:
                launch(box_centres_kernel, self.num_edges,
                       [self.elowers, self.euppers, self.ecentres, self.rmax, 1],
                       device=self.device)
            cell = self.rest_span + 2.0 * float(pad)
            self.tri_grid.build(self.centres, cell)
            self.edge_grid.build(self.ecentres, cell)
        elif self.tri_bvh is None:
            self.tri_bvh = wp.Bvh(self.lowers, self.uppers)
            self.edge_bvh = wp.Bvh(self.elowers, self.euppers)
        else:
            self.tri_bvh.refit()
            self.edge_bvh.refit()
