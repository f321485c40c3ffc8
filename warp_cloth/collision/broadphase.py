"""Broad phase over the cloth's own triangles and edges: swept boxes in two `wp.Bvh`.

Every step the box of each cloth triangle and edge over its path from ``x0`` to ``x1`` (start and
end positions: a linear path stays inside the box of its ends), inflated by a pad (the contact
thickness plus any margin), is written by one kernel and the two BVHs are refitted. A query with
the swept box of another primitive (an obstacle feature, or a cloth vertex or edge for
self-collision) inflated the same way returns every primitive whose box overlaps it: no pair
whose swept boxes overlap is missed (Warp's BVH query is exact on boxes). The BVHs are built on
the first call (outside any capture: the scene runner captures from its second frame) and then
refitted; Warp records a CPU refit in a captured graph and re-runs it on replay, and on CUDA the
refit is a kernel, so steps stay capturable.
"""

from __future__ import annotations

import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile

__all__ = ["ClothBroadPhase"]


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
        lowers[k] = lo - wp.vec3(pad)
        uppers[k] = hi + wp.vec3(pad)
    else:
        e = k - num_tris
        for c in range(2):
            i = edges[e, c]
            lo = wp.min(lo, wp.min(x0[i], x1[i]))
            hi = wp.max(hi, wp.max(x0[i], x1[i]))
        elowers[e] = lo - wp.vec3(pad)
        euppers[e] = hi + wp.vec3(pad)


class ClothBroadPhase:
    """Swept-box BVHs of a model's triangles (``tri_bvh``) and edges (``edge_bvh``)."""

    def __init__(self, model):
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
        self.tri_bvh = self.edge_bvh = None

    def update(self, x0, x1, pad: float) -> None:
        """Boxes of the paths ``x0 -> x1`` inflated by ``pad``, and the BVHs refitted."""
        wp.launch(cloth_bounds_kernel, self.num_tris + self.num_edges,
                  [x0, x1, self.tris, self.edges, self.num_tris, float(pad), self.lowers,
                   self.uppers, self.elowers, self.euppers], device=self.device)
        if self.tri_bvh is None:
            self.tri_bvh = wp.Bvh(self.lowers, self.uppers)
            self.edge_bvh = wp.Bvh(self.elowers, self.euppers)
        else:
            self.tri_bvh.refit()
            self.edge_bvh.refit()
