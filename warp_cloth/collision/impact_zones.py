"""Rigid impact zones (``physics.md`` 2.20; Provot 1997, Bridson et al. 2002, Harmon et al. 2008).

The last resort of the self-collision response, for the contacts that the rounds of projection
(`warp_cloth.collision.self_collision`) could not separate. The vertices of the remaining
contacts are merged into **zones**: two contacts sharing a vertex are in the same zone (union by
label propagation: each entry lowers the labels of its vertices to their minimum, then pointer
jumping, repeated until a round changes no label: a device-side loop, no host read in a graph). Each zone then moves **rigidly** over the step:
its centre of mass moves as the zone's vertices did on average (linear momentum kept), and it
turns by the rotation that keeps the zone's angular momentum about that centre
(``theta = I^-1 sum m_i r_i x u_i``, with ``r_i`` the vertex's offset from the centre at the start
and ``u_i`` its displacement relative to the centre: the rotation vector of the step), so the
distances inside a zone stay what they were at the start of the step, when the cloth was free of
crossings. A zone that holds pinned (or kinematically driven) vertices follows them instead: its rigid
motion is the one fitted to the pinned vertices' prescribed motion (centroid and rotation vector
of their displacements, weight 1 each), which is exact when they move rigidly (an edge held and
turned) and otherwise their best rigid approximation; the pinned vertices themselves keep their
prescribed positions.

A zone whose rigid end would put a member inside an obstacle's thickness (the collision stage's
vertex contact would move it) goes back to the path's start with zero velocity instead
(`ImpactZones.hold_grounded`), while every obstacle stands still: held by the obstacle as a
pinned zone is by its pins. Vertex contact does not run after the zones (it could push a layer
through another), so without this a zone turning about its centre left a vertex up to 0.5 mm
inside the floor's thickness (PBD's fold at one step a frame).

Zones are **grown**: after each rigid pass the paths are detected again, and the new contacts
merge into the existing zones (labels persist through the step), up to ``passes`` times. If a
path still comes too close after that, the caller returns the whole cloth to its start.

All counts go to the caller's counters: the zones formed and the vertices moved rigidly.
"""

from __future__ import annotations

import warp as wp

from ..util import launch
from .record import ContactRecord

wp.set_module_options({"enable_backward": False})

__all__ = ["ImpactZones"]

#: Before 2026-12-07 a union ran a fixed 4 propagation sweeps and 6 jumps. On the CPU, whose
#: threads run one after another, a sweep sees its own writes and that always sufficed; on a
#: GPU a sweep's threads may all read the labels from before it, and a chain of contacts then
#: merges only a few links a sweep (a model of that order: a chain of 256 entries ended as 87
#: zones), which moved one contact-connected group as several rigid bodies. Now the rounds go
#: on until one changes no label (`zone_union_kernel` and `zone_jump_kernel` flag every change;
#: labels only decrease, so the loop ends), usually two rounds on the CPU.


@wp.kernel
def zone_mark_kernel(rec: ContactRecord, label: wp.array(dtype=int),
                     member: wp.array(dtype=int), num_threads: int):
    """The vertices of the record's entries become zone members (labels persist)."""
    t = wp.tid()
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    for e in range(t, count, num_threads):
        vid = rec.vertex[e]
        for j in range(4):
            v = vid[j]
            if v >= 0:
                member[v] = 1


@wp.kernel
def zone_union_kernel(rec: ContactRecord, label: wp.array(dtype=int), num_threads: int,
                      changed: wp.array(dtype=int)):
    """One propagation sweep: every entry's vertices (and their current roots) take the
    smallest label among them; ``changed[0] = 1`` if a label fell."""
    t = wp.tid()
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    for e in range(t, count, num_threads):
        vid = rec.vertex[e]
        lo = int(2147483647)
        for j in range(4):
            v = vid[j]
            if v >= 0:
                lo = wp.min(lo, label[label[v]])
        for j in range(4):
            v = vid[j]
            if v >= 0:
                if wp.atomic_min(label, label[v], lo) > lo:
                    changed[0] = 1
                if wp.atomic_min(label, v, lo) > lo:
                    changed[0] = 1


@wp.kernel
def zone_jump_kernel(label: wp.array(dtype=int), changed: wp.array(dtype=int)):
    """Pointer jumping: ``label[i] = label[label[i]]`` (never larger: ``label[j] <= j`` for
    every ``j``); ``changed[0] = 1`` where a label was not yet a root."""
    i = wp.tid()
    r = label[label[i]]
    if r != label[i]:
        label[i] = r
        changed[0] = 1


@wp.kernel
def zone_flag_kernel(changed: wp.array(dtype=int), value: int):
    changed[0] = value


@wp.kernel
def zone_clear_kernel(rec: ContactRecord, zmass: wp.array(dtype=float),
                      zc0: wp.array(dtype=wp.vec3), zc1: wp.array(dtype=wp.vec3),
                      zang: wp.array(dtype=wp.vec3), zinert: wp.array(dtype=wp.mat33),
                      zpinned: wp.array(dtype=int), zsize: wp.array(dtype=int),
                      counters: wp.array(dtype=int), slot: int):
    """The per-zone sums cleared (one launch instead of seven; nothing if no new entry), and
    the zones' counts of this step (``counters[slot]``, ``counters[slot + 1]``): the zones
    persist through a step's passes and each pass that moves them counts them all again
    (`zone_move_kernel`), so the step's counts are its last moving pass's."""
    i = wp.tid()
    if rec.count[0] == 0:
        return
    if i == 0:
        counters[slot] = 0
        counters[slot + 1] = 0
    zmass[i] = 0.0
    zc0[i] = wp.vec3(0.0)
    zc1[i] = wp.vec3(0.0)
    zang[i] = wp.vec3(0.0)
    zinert[i] = wp.mat33(0.0)
    zpinned[i] = 0
    zsize[i] = 0


@wp.kernel
def zone_pinned_kernel(rec: ContactRecord, member: wp.array(dtype=int),
                       label: wp.array(dtype=int), inv_mass: wp.array(dtype=float),
                       zpinned: wp.array(dtype=int), zsize: wp.array(dtype=int)):
    """Zones holding a pinned vertex flagged; zone sizes."""
    i = wp.tid()
    if member[i] == 0 or rec.count[0] == 0:
        return
    wp.atomic_add(zsize, label[i], 1)
    if inv_mass[i] <= 0.0:
        zpinned[label[i]] = 1


@wp.func
def zone_weight(i: int, r: int, inv_mass: wp.array(dtype=float), zpinned: wp.array(dtype=int)):
    """A vertex's weight in its zone's rigid motion: its mass, or in a pinned zone 1 for the
    pinned vertices (whose prescribed motion the zone follows) and 0 for the free ones."""
    if zpinned[r] != 0:
        if inv_mass[i] <= 0.0:
            return 1.0
        return 0.0
    return 1.0 / inv_mass[i]


@wp.kernel
def zone_sums_kernel(member: wp.array(dtype=int), label: wp.array(dtype=int),
                     x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
                     inv_mass: wp.array(dtype=float), zpinned: wp.array(dtype=int),
                     zmass: wp.array(dtype=float), zc0: wp.array(dtype=wp.vec3),
                     zc1: wp.array(dtype=wp.vec3)):
    """Weight and weighted start and end positions per zone (at its root's index)."""
    i = wp.tid()
    if member[i] == 0:
        return
    r = label[i]
    m = zone_weight(i, r, inv_mass, zpinned)
    if m > 0.0:
        wp.atomic_add(zmass, r, m)
        wp.atomic_add(zc0, r, m * x0[i])
        wp.atomic_add(zc1, r, m * x1[i])


@wp.kernel
def zone_moments_kernel(member: wp.array(dtype=int), label: wp.array(dtype=int),
                        x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
                        inv_mass: wp.array(dtype=float), zpinned: wp.array(dtype=int),
                        zmass: wp.array(dtype=float),
                        zc0: wp.array(dtype=wp.vec3), zc1: wp.array(dtype=wp.vec3),
                        zang: wp.array(dtype=wp.vec3), zinert: wp.array(dtype=wp.mat33)):
    """Angular momentum (times dt) and inertia tensor about the zone's start centre."""
    i = wp.tid()
    if member[i] == 0:
        return
    r = label[i]
    m = zone_weight(i, r, inv_mass, zpinned)
    if m <= 0.0:
        return
    M = zmass[r]
    c0 = zc0[r] / M
    c1 = zc1[r] / M
    q = x0[i] - c0
    u = (x1[i] - x0[i]) - (c1 - c0)
    wp.atomic_add(zang, r, m * wp.cross(q, u))
    wp.atomic_add(zinert, r, m * (wp.dot(q, q) * wp.identity(3, dtype=float) - wp.outer(q, q)))


@wp.kernel
def zone_move_kernel(rec: ContactRecord, member: wp.array(dtype=int), label: wp.array(dtype=int),
                     x0: wp.array(dtype=wp.vec3), x: wp.array(dtype=wp.vec3),
                     v: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float),
                     zmass: wp.array(dtype=float), zc0: wp.array(dtype=wp.vec3),
                     zc1: wp.array(dtype=wp.vec3), zang: wp.array(dtype=wp.vec3),
                     zinert: wp.array(dtype=wp.mat33), zpinned: wp.array(dtype=int),
                     inv_dt: float, steps: wp.array(dtype=int), counters: wp.array(dtype=int),
                     slot: int):
    """Each free zone member to its zone's rigid end position, ``v = (x - x0) / (steps[0] dt)``
    (the path's mean velocity); the zones (roots) and moved vertices counted. Nothing when the
    record is empty (the zones are already rigid: no new contact merged into them)."""
    i = wp.tid()
    if member[i] == 0 or rec.count[0] == 0:
        return
    r = label[i]
    if r == i:
        wp.atomic_add(counters, slot, 1)
    if inv_mass[i] <= 0.0:
        return
    wp.atomic_add(counters, slot + 1, 1)
    M = zmass[r]
    c0 = zc0[r] / M
    c1 = zc1[r] / M
    I = zinert[r]
    # regularised: a zone on a line (or a point) has no inertia about some axis
    eps = 1.0e-6 * (I[0, 0] + I[1, 1] + I[2, 2]) + 1.0e-30
    theta = wp.inverse(I + eps * wp.identity(3, dtype=float)) * zang[r]
    ang = wp.length(theta)
    q = x0[i] - c0
    rq = q
    if ang > 1.0e-12:
        rq = wp.quat_rotate(wp.quat_from_axis_angle(theta / ang, ang), q)
    xn = c1 + rq
    x[i] = xn
    v[i] = (xn - x0[i]) * (inv_dt / float(steps[0]))


@wp.kernel
def zone_grounded_kernel(member: wp.array(dtype=int), label: wp.array(dtype=int),
                         x: wp.array(dtype=wp.vec3), probe: wp.array(dtype=wp.vec3),
                         grounded: wp.array(dtype=int)):
    """A zone whose rigid end puts a member where obstacle contact moves it (``probe``: the
    end positions after the obstacles' projection) is grounded."""
    i = wp.tid()
    if member[i] == 0:
        return
    if wp.length_sq(probe[i] - x[i]) > 0.0:
        grounded[label[i]] = 1


@wp.kernel
def zone_hold_kernel(member: wp.array(dtype=int), label: wp.array(dtype=int),
                     x0: wp.array(dtype=wp.vec3), x: wp.array(dtype=wp.vec3),
                     v: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float),
                     grounded: wp.array(dtype=int), still: wp.array(dtype=int),
                     counters: wp.array(dtype=int), slot: int):
    """The free members of a grounded zone back at the path's start with zero velocity (held
    by the obstacle like a pinned zone by its pins), while every obstacle stands still; the
    grounded zones (roots) counted in ``counters[slot]``."""
    i = wp.tid()
    if member[i] == 0 or still[0] == 0:
        return
    r = label[i]
    if grounded[r] != 0:
        if inv_mass[i] > 0.0:
            x[i] = x0[i]
            v[i] = wp.vec3(0.0)
        if r == i:
            wp.atomic_add(counters, slot, 1)


@wp.kernel
def zone_ground_clear_kernel(grounded: wp.array(dtype=int)):
    grounded[wp.tid()] = 0


class ImpactZones:
    """Zone labels and per-zone sums for a model's vertices (module docstring)."""

    def __init__(self, model):
        n = model.num_vertices
        d = self.device = model.device
        self.model = model
        self.label = wp.zeros(n, dtype=int, device=d)
        self.member = wp.zeros(n, dtype=int, device=d)
        self.zmass = wp.zeros(n, dtype=float, device=d)
        self.zc0 = wp.zeros(n, dtype=wp.vec3, device=d)
        self.zc1 = wp.zeros(n, dtype=wp.vec3, device=d)
        self.zang = wp.zeros(n, dtype=wp.vec3, device=d)
        self.zinert = wp.zeros(n, dtype=wp.mat33, device=d)
        self.zpinned = wp.zeros(n, dtype=int, device=d)
        self.zsize = wp.zeros(n, dtype=int, device=d)
        import numpy as np

        self._iota = wp.array(np.arange(n, dtype=np.int32), dtype=int, device=d)
        self._one = wp.ones(1, dtype=int, device=d)
        self._changed = wp.zeros(1, dtype=int, device=d)  # a union round changed a label
        #: union rounds run by the last eager `merge` (not counted inside a recorded graph)
        self.union_rounds = 0
        self.grounded = wp.zeros(n, dtype=int, device=d)
        # `hold_grounded`'s end positions after the obstacles' projection
        self._probe = wp.zeros(n, dtype=wp.vec3, device=d)

    def reset(self) -> None:
        """No zones (start of a step)."""
        wp.copy(self.label, self._iota)
        self.member.zero_()

    def merge(self, rec: ContactRecord, threads: int) -> None:
        """The record's entries merged into the zones."""
        d = self.device
        launch(zone_mark_kernel, threads, [rec, self.label, self.member, threads], device=d)
        # rounds of one sweep and one jump until a round changes nothing: every entry's
        # vertices then share one label, and every label is a root
        self.union_rounds = 0
        launch(zone_flag_kernel, 1, [self._changed, 1], device=d)
        wp.capture_while(self._changed, self._union_round, rec=rec, threads=threads)

    def _union_round(self, rec, threads) -> None:
        d = self.device
        self.union_rounds += 1
        launch(zone_flag_kernel, 1, [self._changed, 0], device=d)
        launch(zone_union_kernel, threads, [rec, self.label, threads, self._changed], device=d)
        launch(zone_jump_kernel, len(self.label), [self.label, self._changed], device=d)

    def move(self, rec: ContactRecord, x0, state, dt: float, counters, slot: int,
             steps=None) -> None:
        """Every zone moved rigidly (or held at its start if pinned), unless ``rec`` (the
        entries just merged) is empty; the path ``x0 -> state.x`` lasts ``steps[0]`` steps of
        ``dt`` (a device array); ``counters[slot]`` = zones, ``counters[slot + 1]`` = free
        vertices moved (the step's zones so far: they persist through its passes)."""
        m, d, n = self.model, self.device, len(self.label)
        if steps is None:
            steps = self._one
        launch(zone_clear_kernel, n, [rec, self.zmass, self.zc0, self.zc1, self.zang,
                                      self.zinert, self.zpinned, self.zsize, counters, slot],
               device=d)
        launch(zone_pinned_kernel, n, [rec, self.member, self.label, m.inv_mass, self.zpinned,
                                       self.zsize], device=d)
        launch(zone_sums_kernel, n, [self.member, self.label, x0, state.x, m.inv_mass,
                                     self.zpinned, self.zmass, self.zc0, self.zc1], device=d)
        launch(zone_moments_kernel, n, [self.member, self.label, x0, state.x, m.inv_mass,
                                        self.zpinned, self.zmass, self.zc0, self.zc1,
                                        self.zang, self.zinert], device=d)
        launch(zone_move_kernel, n, [rec, self.member, self.label, x0, state.x, state.v,
                                     m.inv_mass, self.zmass, self.zc0, self.zc1, self.zang,
                                     self.zinert, self.zpinned, 1.0 / dt, steps, counters,
                                     slot],
               device=d)

    def hold_grounded(self, x0, state, project, still, counters, slot: int) -> None:
        """After `move`: the zones whose rigid end would put a member inside an obstacle's
        thickness (``project(positions)`` moves such positions out: the collision stage's vertex
        contact) go back to the path's start ``x0`` with zero velocity, where the cloth was
        clear of the obstacles and of itself, while every obstacle stands still (``still[0]``,
        a device flag that ``project`` sets: a moving obstacle could meet the held zone there).
        The rigid motion keeps the zone's own distances but not its distance to an obstacle,
        and vertex contact after it could push a layer through another: the next zone pass's
        detection sees the held zones. ``counters[slot]`` += zones held."""
        m, d, n = self.model, self.device, len(self.label)
        wp.copy(self._probe, state.x)
        project(self._probe)
        launch(zone_grounded_kernel, n, [self.member, self.label, state.x, self._probe,
                                         self.grounded], device=d)
        launch(zone_hold_kernel, n, [self.member, self.label, x0, state.x, state.v, m.inv_mass,
                                     self.grounded, still, counters, slot], device=d)
        launch(zone_ground_clear_kernel, n, [self.grounded], device=d)
