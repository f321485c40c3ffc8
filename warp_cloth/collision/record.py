"""The contact record: what the collision stage detected in a step, in one shape for every source.

Each entry is one linear non-penetration constraint on the cloth's positions,

    g(x) = n . (sum_j w_j x_{v_j}) - offset >= 0,

with up to four cloth vertices ``v_j`` (``-1``: unused) and weights ``w_j``:

- a cloth vertex against an obstacle (``KIND_VERTEX_OBSTACLE``): ``v = (i, -1, -1, -1)``,
  ``w = (1, 0, 0, 0)``, ``n`` the obstacle's outward normal at the closest point and ``offset =
  n . p`` with ``p`` the point at the contact thickness above the surface (after the continuous
  test: a path that entered the shape is stopped at its entry point first);
- vertex-triangle and edge-edge pairs (self-collision, cloth edges against obstacle edges) use
  the same form with barycentric weights (``w = (1, -b0, -b1, -b2)`` for a vertex above a
  triangle, ``(1 - a, a, -(1 - b), -b)`` for two edges), so a solver that consumes the record
  needs nothing new for them.

Beside the constraint each entry carries what a response needs: ``ref`` (vertex-obstacle
entries: the start position carried by the obstacle's motion over the step, for friction; mesh
feature entries: the constraint plane's point at the step's start, so ``offset - n . ref`` is
how far the obstacle moved the plane, `features.inelastic_apply_kernel`), ``friction`` (mu_T),
``restitution`` (mu_N), ``source`` (the obstacle index, or -1) and ``kind``. The record has a
fixed ``capacity`` (allocated once); ``count[0]`` is the number of entries written, and an entry
past the capacity is not written but counted in ``overflow[0]`` (read by `CollisionStage.stats`:
nothing is dropped silently).
"""

from __future__ import annotations

import warp as wp

from ..util import stride_threads

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile

__all__ = ["ContactRecord", "make_record", "entry_gap", "KIND_VERTEX_OBSTACLE",
           "KIND_VERTEX_TRIANGLE", "KIND_EDGE_EDGE", "record_append", "planes_to_record_kernel",
           "record_threads"]

KIND_VERTEX_OBSTACLE = 0
KIND_VERTEX_TRIANGLE = 1
KIND_EDGE_EDGE = 2


@wp.struct
class ContactRecord:
    """Device arrays of one contact record (see the module docstring)."""

    count: wp.array(dtype=int)  # [1] entries written
    overflow: wp.array(dtype=int)  # [1] entries that did not fit
    vertex: wp.array(dtype=wp.vec4i)  # cloth vertex ids, -1 unused
    weight: wp.array(dtype=wp.vec4)  # w_j
    normal: wp.array(dtype=wp.vec3)  # unit normal n (world frame, end of step)
    offset: wp.array(dtype=float)  # g = n . sum w_j x_j - offset
    ref: wp.array(dtype=wp.vec3)  # friction's reference point / a feature plane's start
    friction: wp.array(dtype=float)  # mu_T
    restitution: wp.array(dtype=float)  # mu_N
    source: wp.array(dtype=int)  # obstacle index, or -1
    kind: wp.array(dtype=int)  # KIND_*


def record_threads(entries: int, device, batch: int = 16) -> int:
    """Threads for a kernel that strides over up to ``entries`` record entries: one per
    ``batch`` on a GPU; one on the CPU (`util.stride_threads`)."""
    return stride_threads(entries, device, batch)


def make_record(capacity: int, device) -> ContactRecord:
    """A record of ``capacity`` entries on ``device`` (all arrays allocated here, once)."""
    cap = max(int(capacity), 1)
    r = ContactRecord()
    r.count = wp.zeros(1, dtype=int, device=device)
    r.overflow = wp.zeros(1, dtype=int, device=device)
    r.vertex = wp.full(cap, wp.vec4i(-1, -1, -1, -1), dtype=wp.vec4i, device=device)
    r.weight = wp.zeros(cap, dtype=wp.vec4, device=device)
    r.normal = wp.zeros(cap, dtype=wp.vec3, device=device)
    r.offset = wp.zeros(cap, dtype=float, device=device)
    r.ref = wp.zeros(cap, dtype=wp.vec3, device=device)
    r.friction = wp.zeros(cap, dtype=float, device=device)
    r.restitution = wp.zeros(cap, dtype=float, device=device)
    r.source = wp.zeros(cap, dtype=int, device=device)
    r.kind = wp.zeros(cap, dtype=int, device=device)
    return r


@wp.kernel
def add_overflow_kernel(rec: ContactRecord, total: wp.array(dtype=int)):
    """``total[0] +=`` the entries the record's last detection dropped (a running count over
    the detections that reset the record's own)."""
    total[0] = total[0] + rec.overflow[0]


@wp.func
def record_append(rec: ContactRecord, kind: int, vertex: wp.vec4i, weight: wp.vec4, n: wp.vec3,
                  offset: float, ref: wp.vec3, mu_t: float, mu_n: float, source: int):
    """Append one entry (atomically); past the capacity only ``overflow`` is incremented."""
    slot = wp.atomic_add(rec.count, 0, 1)
    if slot >= rec.vertex.shape[0]:
        wp.atomic_add(rec.overflow, 0, 1)
        return -1
    rec.vertex[slot] = vertex
    rec.weight[slot] = weight
    rec.normal[slot] = n
    rec.offset[slot] = offset
    rec.ref[slot] = ref
    rec.friction[slot] = mu_t
    rec.restitution[slot] = mu_n
    rec.source[slot] = source
    rec.kind[slot] = kind
    return slot


@wp.func
def entry_gap(rec: ContactRecord, e: int, x: wp.array(dtype=wp.vec3),
              inv_mass: wp.array(dtype=float)):
    """``(g, im)`` of entry ``e`` at positions ``x``: its gap ``n . sum w_j x_j - offset``
    (negative: violated) and ``sum w_j^2 / m_j`` (its inverse effective mass; 0 when every
    vertex of it is pinned)."""
    vid = rec.vertex[e]
    w = rec.weight[e]
    n = rec.normal[e]
    g = -rec.offset[e]
    im = float(0.0)
    for j in range(4):
        v = vid[j]
        if v >= 0:
            g = g + w[j] * wp.dot(n, x[v])
            im = im + w[j] * w[j] * inv_mass[v]
    return g, im


@wp.kernel
def planes_to_record_kernel(
    x: wp.array(dtype=wp.vec3),
    point: wp.array(dtype=wp.vec3),
    normal: wp.array(dtype=wp.vec3),
    ref: wp.array(dtype=wp.vec3),
    friction: wp.array(dtype=float),
    restitution: float,
    num: int,
    first_source: int,
    near_count: wp.array(dtype=int),
    near_list: wp.array(dtype=int),
    margin: float,
    num_threads: int,
    rec: ContactRecord,
):
    """Contact planes of listed vertices (``warp_cloth.collision.planes``, entry ``e * num + k``
    for obstacle ``k``) into the record: those whose vertex at ``x`` lies less than ``margin``
    above its plane (a plane farther away constrains nothing a solve can reach)."""
    t = wp.tid()
    n_list = near_count[0]
    for e in range(t, n_list, num_threads):
        i = near_list[e]
        xi = x[i]
        for k in range(num):
            c = e * num + k
            n = normal[c]
            if wp.length_sq(n) == 0.0:
                continue
            off = wp.dot(n, point[c])
            if wp.dot(n, xi) - off < margin:
                record_append(rec, KIND_VERTEX_OBSTACLE, wp.vec4i(i, -1, -1, -1),
                              wp.vec4(1.0, 0.0, 0.0, 0.0), n, off, ref[c], friction[c],
                              restitution, first_source + k)
