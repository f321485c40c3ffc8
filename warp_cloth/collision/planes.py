"""Contact planes for position-based iterations (Müller et al. 2007, *Position Based Dynamics*,
section 3.5: collision constraints are generated once per time step and projected in every
iteration).

`ObstacleContact.begin_iterations` lists the vertices whose path comes near an obstacle and
gives each (vertex, obstacle) pair a plane from the exact geometry at the predicted position: the
point ``p`` at the contact thickness above the closest surface point (after the continuous test:
a path that entered the shape is stopped at its entry point first) and the outward normal ``n``,
in the world frame at the end of the step, plus the start position carried along by the
obstacle's motion over the step (``ref``, for friction). Each iteration then only projects:

    phi = (x - p) . n;   if phi < 0:  x <- x - phi n,  then position-level Coulomb friction:
    d_T = tangential part of (x - ref);  |d_T| <= mu_T |phi|: x <- x - d_T (static),
                                          else x <- x - mu_T |phi| d_T / |d_T| (sliding)

A few operations per pair instead of the exact distance, continuous test and transforms in every
iteration. The planes linearise curved surfaces over the iterations' small displacements (a
sphere of radius R: an error of about ``s^2 / 2R`` for a displacement ``s``); the `apply` that
ends every step tests the exact geometry of every vertex, so the non-penetration guarantee after
a step is unchanged.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile


@wp.struct
class ContactPlanes:
    """Planes of the listed vertices: entry ``slot * num + k`` for obstacle ``k`` of a family."""

    point: wp.array(dtype=wp.vec3)  # world point at the contact thickness above the surface
    normal: wp.array(dtype=wp.vec3)  # outward unit normal (world); zero: no plane
    ref: wp.array(dtype=wp.vec3)  # start position carried by the obstacle (friction)
    friction: wp.array(dtype=float)  # mu_T


def make_planes(n_entries: int, device) -> ContactPlanes:
    pl = ContactPlanes()
    pl.point = wp.zeros(n_entries, dtype=wp.vec3, device=device)
    pl.normal = wp.zeros(n_entries, dtype=wp.vec3, device=device)
    pl.ref = wp.zeros(n_entries, dtype=wp.vec3, device=device)
    pl.friction = wp.zeros(n_entries, dtype=float, device=device)
    return pl


@wp.kernel
def project_planes_kernel(
    x: wp.array(dtype=wp.vec3),
    planes: ContactPlanes,
    num: int,
    near_count: wp.array(dtype=int),
    near_list: wp.array(dtype=int),
    num_threads: int,
):
    """One iteration's contact: every plane of every listed vertex, strided over the threads."""
    t = wp.tid()
    n_list = near_count[0]
    for e in range(t, n_list, num_threads):
        i = near_list[e]
        xi = x[i]
        moved = bool(False)
        for k in range(num):
            c = e * num + k
            n = planes.normal[c]
            phi = wp.dot(xi - planes.point[c], n)
            if phi < 0.0:
                xi = xi - phi * n
                moved = True
                mu = planes.friction[c]
                if mu > 0.0:
                    d = xi - planes.ref[c]
                    d_t = d - wp.dot(d, n) * n
                    lt = wp.length(d_t)
                    cap = -mu * phi
                    if lt <= cap:
                        xi = xi - d_t
                    else:
                        xi = xi - (cap / lt) * d_t
        if moved:
            x[i] = xi
