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

from .util import launch

wp.set_module_options({"enable_backward": False})

__all__ = ["tether_anchors", "model_tether_anchors", "tether_kernel", "PinStretch"]


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
            launch(pin_stretch_kernel, 1, [x, self._pins, self._rest, self.scale],
                   device=self.device)


@wp.func
def _unfold64(xa: wp.vec3d, xb: wp.vec3d, xc: wp.vec3d, da: wp.float64, db: wp.float64):
    """`_unfold` in float64 for the kernel: the distance, or -1 where the line misses."""
    zero = wp.float64(0.0)
    e = xb - xa
    L = wp.length(e)
    if L <= zero:
        return wp.float64(-1.0)
    ex = e / L
    ac = xc - xa
    cx = wp.dot(ac, ex)
    cy2 = wp.dot(ac, ac) - cx * cx
    sx = (da * da - db * db + L * L) / (wp.float64(2.0) * L)
    sy2 = da * da - sx * sx
    if cy2 <= zero or sy2 < zero:
        return wp.float64(-1.0)
    cy = wp.sqrt(cy2)
    sy = -wp.sqrt(sy2)
    t = -sy / (cy - sy)
    cross = sx + (cx - sx) * t
    if cross < zero or cross > L:
        return wp.float64(-1.0)
    return wp.sqrt((cx - sx) * (cx - sx) + (cy - sy) * (cy - sy))


@wp.func
def _heap_less(hd: wp.array(dtype=wp.float64), hv: wp.array(dtype=wp.int32),
               hs: wp.array(dtype=wp.int32), i: int, j: int):
    """Entry ``i`` before entry ``j``: by distance, then vertex, then source (Python's tuple
    order, so that ties come out as in the reference implementation)."""
    if hd[i] != hd[j]:
        return hd[i] < hd[j]
    if hv[i] != hv[j]:
        return hv[i] < hv[j]
    return hs[i] < hs[j]


@wp.func
def _heap_swap(hd: wp.array(dtype=wp.float64), hv: wp.array(dtype=wp.int32),
               hs: wp.array(dtype=wp.int32), i: int, j: int):
    td = hd[i]
    tv = hv[i]
    ts = hs[i]
    hd[i] = hd[j]
    hv[i] = hv[j]
    hs[i] = hs[j]
    hd[j] = td
    hv[j] = tv
    hs[j] = ts


@wp.func
def _heap_push(hd: wp.array(dtype=wp.float64), hv: wp.array(dtype=wp.int32),
               hs: wp.array(dtype=wp.int32), size: int, d: wp.float64, v: int, s: int):
    """Push onto the heap of ``size`` entries; returns the new size (-1: full)."""
    if size >= hd.shape[0]:
        return -1
    i = size
    hd[i] = d
    hv[i] = v
    hs[i] = s
    while i > 0:
        p = (i - 1) // 2
        if _heap_less(hd, hv, hs, i, p):
            _heap_swap(hd, hv, hs, i, p)
            i = p
        else:
            break
    return size + 1


@wp.func
def _has_label(label_s: wp.array2d(dtype=wp.int32), count: int, v: int, s: int):
    """Whether vertex ``v``'s first ``count`` labels include source ``s``."""
    for j in range(count):
        if label_s[v, j] == s:
            return True
    return False


@wp.kernel
def geodesic_labels_kernel(x: wp.array(dtype=wp.vec3d), tris: wp.array2d(dtype=wp.int32),
                           vt_start: wp.array(dtype=wp.int32), vt: wp.array(dtype=wp.int32),
                           is_src: wp.array(dtype=wp.int32), srcs: wp.array(dtype=wp.int32),
                           k: int, label_s: wp.array2d(dtype=wp.int32),
                           label_d: wp.array2d(dtype=wp.float64),
                           nlab: wp.array(dtype=wp.int32), hd: wp.array(dtype=wp.float64),
                           hv: wp.array(dtype=wp.int32), hs: wp.array(dtype=wp.int32),
                           full: wp.array(dtype=wp.int32)):
    """`_tether_anchors_py` in one thread (run on the CPU: a set-up step): the same multi-source
    Dijkstra with the fast-marching triangle update, the labels in finalisation order."""
    size = int(0)
    for j in range(srcs.shape[0]):
        size = _heap_push(hd, hv, hs, size, wp.float64(0.0), srcs[j], srcs[j])
    while size > 0:
        if size < 0:
            full[0] = 1
            return
        d = hd[0]
        v = hv[0]
        s = hs[0]
        size = size - 1
        if size > 0:  # the last entry to the root, sifted down
            hd[0] = hd[size]
            hv[0] = hv[size]
            hs[0] = hs[size]
            i = int(0)
            while True:
                c = 2 * i + 1
                if c >= size:
                    break
                if c + 1 < size and _heap_less(hd, hv, hs, c + 1, c):
                    c = c + 1
                if _heap_less(hd, hv, hs, c, i):
                    _heap_swap(hd, hv, hs, c, i)
                    i = c
                else:
                    break
        nv = nlab[v]
        if nv >= k or (is_src[v] != 0 and v != s) or _has_label(label_s, nv, v, s):
            continue
        label_s[v, nv] = s
        label_d[v, nv] = d
        nlab[v] = nv + 1
        for a in range(vt_start[v], vt_start[v + 1]):
            t = vt[a]
            # the triangle's other two vertices, each in turn as u (with w the third)
            o0 = tris[t, 0]
            o1 = tris[t, 1]
            if o0 == v:
                o0 = tris[t, 2]
            elif o1 == v:
                o1 = tris[t, 2]
            for r in range(2):
                u = o0
                w = o1
                if r == 1:
                    u = o1
                    w = o0
                nu = nlab[u]
                if is_src[u] != 0 or nu >= k or _has_label(label_s, nu, u, s):
                    continue
                size = _heap_push(hd, hv, hs, size, d + wp.length(x[v] - x[u]), u, s)
                if size < 0:
                    full[0] = 1
                    return
                dw = wp.float64(-1.0)
                for j in range(nlab[w]):
                    if label_s[w, j] == s:
                        dw = label_d[w, j]
                if dw >= wp.float64(0.0):
                    du = _unfold64(x[v], x[w], x[u], d, dw)
                    if du >= wp.float64(0.0):
                        size = _heap_push(hd, hv, hs, size, du, u, s)
                        if size < 0:
                            full[0] = 1
                            return


def tether_anchors(vertices, triangles, sources, k: int = 2, *, heap: int | None = None):
    """The ``k`` nearest sources of every vertex by geodesic distance on the mesh, and the
    distances (the long-range attachments of Kim, Chentanez and Müller 2012).

    A multi-source Dijkstra over the mesh in which a vertex accepts one label per distinct
    source, up to ``k``; a label reaches a vertex along an edge or across a triangle whose other
    two vertices carry the same source, with the source unfolded into the triangle's plane
    (`_unfold`), so distances are exact on a planar (or developable, unrolled) rest mesh, not the
    up-to-8 % longer edge paths of a grid; elsewhere the first-order fast-marching approximation.
    Paths do not pass through another source. Cost ``O(k T log(k T))`` for ``T`` triangles,
    whatever the number of sources: one Warp thread on the CPU (`geodesic_labels_kernel`; a
    set-up step, serial by nature), about 1 s at 262k vertices where the same loop in Python
    (`_tether_anchors_py`) took 41 s; its heap doubles and the search runs again if it fills.

    Returns ``(anchors, dist)``, (N, k) arrays: source vertex indices (-1 where fewer than ``k``
    sources reach the vertex, e.g. in another connected component) and distances (inf there).
    Sources themselves get no label. ``heap``: the heap's first capacity (entries; default
    ``8 N k``).
    """
    x = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    tris = np.asarray(triangles, dtype=np.int32).reshape(-1, 3)
    n, k = len(x), int(k)
    src = np.unique(np.asarray(sources, dtype=np.int64).reshape(-1)).astype(np.int32)
    anchors = np.full((n, k), -1, dtype=np.int64)
    dist = np.full((n, k), np.inf)
    if n == 0 or k < 1 or len(src) == 0:
        return anchors, dist
    flat = tris.reshape(-1)
    order = np.argsort(flat, kind="stable")
    vt_start = np.searchsorted(flat[order], np.arange(n + 1)).astype(np.int32)
    vt = (order // 3).astype(np.int32)
    is_src = np.zeros(n, dtype=np.int32)
    is_src[src] = 1
    cpu = "cpu"
    args = [wp.array(x, dtype=wp.vec3d, device=cpu), wp.array(tris, dtype=wp.int32, device=cpu),
            wp.array(vt_start, dtype=wp.int32, device=cpu),
            wp.array(vt, dtype=wp.int32, device=cpu),
            wp.array(is_src, dtype=wp.int32, device=cpu),
            wp.array(src, dtype=wp.int32, device=cpu), k]
    cap = int(heap) if heap is not None else 8 * n * k + len(src) + 1024
    cap = max(cap, len(src) + 1)
    while True:
        label_s = wp.full((n, k), -1, dtype=wp.int32, device=cpu)
        label_d = wp.zeros((n, k), dtype=wp.float64, device=cpu)
        nlab = wp.zeros(n, dtype=wp.int32, device=cpu)
        full = wp.zeros(1, dtype=wp.int32, device=cpu)
        heap = (wp.empty(cap, dtype=wp.float64, device=cpu),
                wp.empty(cap, dtype=wp.int32, device=cpu),
                wp.empty(cap, dtype=wp.int32, device=cpu))
        launch(geodesic_labels_kernel, 1, [*args, label_s, label_d, nlab, *heap, full],
               device=cpu)
        if not full.numpy()[0]:
            break
        cap *= 2
    ls, ld = label_s.numpy(), label_d.numpy()
    own = is_src.astype(bool)
    got = ls >= 0
    got[own] = False  # a source's own label (distance 0) is no anchor
    anchors[got] = ls[got]
    dist[got] = ld[got]
    return anchors, dist


def model_tether_anchors(model, k: int):
    """`tether_anchors` of ``model``'s rest mesh and pins, computed once per model and ``k``
    (PBD's tethers and the stretch guard's `StrainLimit` ask for the same ones); the cache is
    keyed by the rest positions, triangles and pins, so a changed mesh is searched again."""
    import hashlib

    mesh = model.mesh
    key = hashlib.blake2b(digest_size=16)
    for a in (mesh.vertices, mesh.triangles, model.pins):
        arr = np.ascontiguousarray(a)
        key.update(str((arr.dtype, arr.shape)).encode())
        key.update(arr.tobytes())
    key = (int(k), key.hexdigest())
    cache = model.__dict__.setdefault("_tether_anchor_cache", {})
    if key not in cache:
        cache.clear()  # one mesh at a time
        cache[key] = tether_anchors(mesh.vertices, mesh.triangles, model.pins, k)
    anchors, dist = cache[key]
    return anchors.copy(), dist.copy()


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


def _tether_anchors_py(vertices, triangles, sources, k: int = 2):
    """`tether_anchors` in plain Python, the same search step for step: the reference the tests
    compare the kernel with (about 160 us a vertex: 41 s at 262k vertices)."""
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
