"""Long-range attachments (tethers; Kim, Chentanez and Müller 2012): each free vertex tied to its
nearest pins by a unilateral constraint of the geodesic rest distance (times a factor).

Shared by position-based dynamics (`warp_cloth.solvers.pbd`: tethers at the rest length keep a
pinned cloth bounded at any step) and `warp_cloth.limits.StrainLimit` (tethers at ``sigma_max``
times the rest geodesic: a bound the edge limits already imply, which the edge sweeps alone
reach only slowly). `tether_anchors` runs once on the host; `tether_kernel` once per iteration.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["tether_anchors", "tether_kernel", "PinStretch"]


@wp.kernel
def tether_kernel(
    x: wp.array(dtype=wp.vec3),
    anchors: wp.array2d(dtype=wp.int32),
    rest: wp.array2d(dtype=float),
    scale: wp.array(dtype=float),
):
    """One thread per vertex: each of its tethers (anchor pin, rest length times ``scale[0]``,
    `PinStretch`) pulls it back onto the sphere of that radius about the pin's current position
    when it is farther (unilateral; the pin has zero inverse mass, so only the vertex moves).
    Only this thread writes ``x[i]``."""
    i = wp.tid()
    xi = x[i]
    s = scale[0]
    moved = int(0)
    for t in range(anchors.shape[1]):
        p = anchors[i, t]
        if p >= 0:
            d = xi - x[p]
            l = wp.length(d)
            r = rest[i, t] * s
            if l > r:
                xi = x[p] + d * (r / l)
                moved = 1
    if moved != 0:
        x[i] = xi


@wp.kernel
def pin_stretch_kernel(x: wp.array(dtype=wp.vec3), pins: wp.array(dtype=wp.int32),
                       rest: wp.array(dtype=wp.vec3), scale: wp.array(dtype=float)):
    """One thread: ``scale[0]`` = the largest ratio of current to rest distance over every pair
    of pins, at least 1."""
    s = float(1.0)
    n = pins.shape[0]
    for a in range(n):
        xa = x[pins[a]]
        for b in range(a + 1, n):
            l0 = wp.length(rest[a] - rest[b])
            if l0 > 0.0:
                s = wp.max(s, wp.length(xa - x[pins[b]]) / l0)
    scale[0] = s


class PinStretch:
    """How far the pins themselves stretch the cloth: the largest ratio of current to rest
    distance over every pair of pins (at least 1), by which every tether's rest length is scaled.

    Tethers assume the pins keep their rest distances. Prescribed pins need not: two edges
    turned in opposite directions (the twist scene) move corner pins apart, and the tethers of
    two neighbouring vertices tied to opposite edges then put the whole difference into the one
    edge between them (measured: 108 % strain on that edge by frame 12 of the twist, the energy
    1.5 -> 5.5 J, with PBD). Scaled by the pins' own stretch, the tethers never ask for less
    than the pins impose. With pins that follow a `PinPath` the ratio is computed on the device
    at every `update` (one thread, O(pins^2)); otherwise once, from the initial positions."""

    def __init__(self, model):
        d = model.device
        pins = np.asarray(model.pins, dtype=np.int64)
        rest = np.asarray(model.mesh.vertices, dtype=np.float64)[pins]
        self.moving = model.pin_path is not None and len(pins) > 1
        if self.moving:
            self._pins = wp.array(pins.astype(np.int32), dtype=wp.int32, device=d)
            self._rest = wp.array(rest.astype(np.float32), dtype=wp.vec3, device=d)
            s = 1.0
        else:
            x = np.asarray(model.initial_positions, dtype=np.float64)[pins]
            s = 1.0
            for a in range(0, len(pins), 256):  # chunks: O(pins) memory
                l0 = np.linalg.norm(rest[a:a + 256, None] - rest[None], axis=-1)
                l1 = np.linalg.norm(x[a:a + 256, None] - x[None], axis=-1)
                ok = l0 > 0
                if ok.any():
                    s = max(s, float((l1[ok] / l0[ok]).max()))
        self.scale = wp.array([s], dtype=float, device=d)
        self.device = d

    def update(self, x) -> None:
        """The ratio for the pins' positions in ``x`` (nothing if the pins do not move)."""
        if self.moving:
            wp.launch(pin_stretch_kernel, 1, [x, self._pins, self._rest, self.scale],
                      device=self.device)


def _unfold(xa, xb, xc, da, db):
    """Distance at ``c`` from a source seen at distances ``da``, ``db`` from ``a``, ``b``: the
    source is placed in the plane of the triangle (a, b, c), unfolded across the edge ``ab``, and
    the straight line from it to ``c`` must cross that edge (else None). Exact on a planar mesh
    (the fast-marching update of Kimmel and Sethian 1998, with the source point kept)."""
    ex = [xb[0] - xa[0], xb[1] - xa[1], xb[2] - xa[2]]
    L = math.sqrt(ex[0] * ex[0] + ex[1] * ex[1] + ex[2] * ex[2])
    if L <= 0.0:
        return None
    ex = [t / L for t in ex]
    ac = [xc[0] - xa[0], xc[1] - xa[1], xc[2] - xa[2]]
    cx = ac[0] * ex[0] + ac[1] * ex[1] + ac[2] * ex[2]
    cy2 = ac[0] * ac[0] + ac[1] * ac[1] + ac[2] * ac[2] - cx * cx
    sx = (da * da - db * db + L * L) / (2.0 * L)
    sy2 = da * da - sx * sx
    if cy2 <= 0.0 or sy2 < 0.0:
        return None
    cy, sy = math.sqrt(cy2), -math.sqrt(sy2)
    t = -sy / (cy - sy)
    cross = sx + (cx - sx) * t
    if cross < 0.0 or cross > L:
        return None
    return math.sqrt((cx - sx) ** 2 + (cy - sy) ** 2)


def tether_anchors(vertices, triangles, sources, k: int = 2):
    """The ``k`` nearest sources of every vertex by geodesic distance on the mesh, and the
    distances (the long-range attachments of Kim, Chentanez and Müller 2012).

    A multi-source Dijkstra over the mesh in which a vertex accepts one label per distinct
    source, up to ``k``; a label reaches a vertex along an edge or across a triangle whose other
    two vertices carry the same source, with the source unfolded into the triangle's plane
    (`_unfold`), so distances are exact on a planar (or developable, unrolled) rest mesh, not the
    up-to-8 % longer edge paths of a grid; elsewhere the first-order fast-marching approximation.
    Paths do not pass through another source. Cost ``O(k T log(k T))`` for ``T`` triangles,
    whatever the number of sources.

    Returns ``(anchors, dist)``, (N, k) arrays: source vertex indices (-1 where fewer than ``k``
    sources reach the vertex, e.g. in another connected component) and distances (inf there).
    Sources themselves get no label.
    """
    import heapq

    x = [tuple(map(float, p)) for p in np.asarray(vertices, dtype=np.float64)]
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    n = len(x)
    # vertex -> incident triangles (CSR)
    flat = tris.reshape(-1)
    order = np.argsort(flat, kind="stable")
    vt_start = np.searchsorted(flat[order], np.arange(n + 1)).tolist()
    vt = (order // 3).tolist()
    tl = tris.tolist()
    anchors = np.full((n, k), -1, dtype=np.int64)
    dist = np.full((n, k), np.inf)
    label = [dict() for _ in range(n)]  # final labels: source -> distance
    src = set(int(s) for s in np.asarray(sources).reshape(-1))
    heap = [(0.0, s, s) for s in sorted(src)]
    heapq.heapify(heap)

    def length(i, j):
        a, b = x[i], x[j]
        return math.sqrt((a[0] - b[0]) ** 2 + (a[1] - b[1]) ** 2 + (a[2] - b[2]) ** 2)

    while heap:
        d, v, s = heapq.heappop(heap)
        lv = label[v]
        if s in lv or len(lv) >= k or (v in src and v != s):
            continue
        lv[s] = d
        if v != s:
            anchors[v, len(lv) - 1] = s
            dist[v, len(lv) - 1] = d
        for a in range(vt_start[v], vt_start[v + 1]):
            t = tl[vt[a]]
            others = [u for u in t if u != v]
            for u, w in (others, others[::-1]):
                lu = label[u]
                if u in src or s in lu or len(lu) >= k:
                    continue
                heapq.heappush(heap, (d + length(v, u), u, s))  # along the edge
                dw = label[w].get(s)
                if dw is not None:  # across the triangle (v, w, u)
                    du = _unfold(x[v], x[w], x[u], d, dw)
                    if du is not None:
                        heapq.heappush(heap, (du, u, s))
    return anchors, dist
