"""Intersection checks between the cloth and mesh obstacles (host entry points, device kernels).

`mesh_edge_crossings` counts the cloth edges that cross a mesh obstacle's surface: a ray from
one end of the edge to the other (Warp's BVH ray query, exact up to float32 rounding) hits a
triangle of the obstacle. With both ends outside (which vertex contact guarantees) such an edge
passes through the obstacle. Used by the tests and by anyone checking a run's output.
"""

from __future__ import annotations

import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile

__all__ = ["mesh_edge_crossings"]


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
    wp.launch(edge_ray_kernel, len(edges), [obstacle.wp_mesh(device).id, x, e, hit], device=device)
    return hit.numpy().astype(bool)
