"""Contact kernels for the analytic obstacles (plane, sphere, box): all analytic obstacles of a
contact in one far pass (a thread per vertex) and one near pass (the listed vertices), made per
tuple of obstacle kinds (`far_kinds`: static sphere, plane or box, or moving), so each
obstacle's tests are compiled in without branches on its kind; for explicit Euler the far pass
runs inside the vertex update (`integrate_far_kernel`), and with static spheres and planes only
the whole contact does (`integrate_contact_kernel`).

Per vertex and obstacle (``th`` = contact thickness), in the obstacle's frame, where the obstacle
is at rest: ``p0`` = start of step position at the pose of t0, ``p1`` = end position at the pose
of t1 (so the obstacle's motion during the step is part of the relative path).

0. Far test: ``phi(p1) >= th + slack`` and ``phi(p1) - th >= |p1 - p0|`` (phi is 1-Lipschitz, so
   no point of the path is within ``th``): nothing to do. Most vertices stop here. It runs in the
   world frame on bounds (`far_from`); for a path no longer than the slack the second condition
   follows from the first, so a sphere's test is one squared comparison.
1. Continuous test (sphere, box): if ``p0`` is outside the shape inflated by ``th`` and the segment
   ``p0 -> p1`` enters it (sphere: the notes' quadratic, ``physics.md`` 2.16 / T40; box: slab test),
   ``p1`` is projected onto the tangent plane at the entry point. This catches a vertex that passes
   through the shape within one step. (A path no longer than the slack is not swept against a
   sphere: it cannot cross one, and its end's projection is what it needs.) (A plane is a half-space: a crossing always ends inside it,
   so the discrete test below already catches it.)
2. Discrete test: if ``phi(p1) < th``, ``p1 <- p1 + (th - phi) grad phi``.
3. If in contact (``phi < th + slack``), the impulse of `warp_cloth.collision.response`.
"""

from __future__ import annotations

import warp as wp

from .motion import (FAST_NONE, FAST_SPHERE, KIND_BOX, KIND_PLANE, KIND_SPHERE, ObstacleData,
                     ObstacleReach)
from .planes import ContactPlanes
from .response import contact_outcome, outcome_in_frame

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile


#: m: a box's signed distance treats a point within this of a face's plane as on it (float32
#: rounding of a coordinate near 1 m is about 6e-8 m)
BOX_TIE = wp.constant(1.0e-6)


@wp.func
def shape_sdf(kind: int, size: wp.vec3, p: wp.vec3):
    """(phi, outward unit normal) of an analytic shape in its local frame."""
    if kind == KIND_PLANE:
        return p[1], wp.vec3(0.0, 1.0, 0.0)
    if kind == KIND_SPHERE:
        l = wp.length(p)
        n = wp.vec3(0.0, 1.0, 0.0)
        if l > 1.0e-9:
            n = p / l
        return l - size[0], n
    # box
    q = wp.vec3(wp.abs(p[0]) - size[0], wp.abs(p[1]) - size[1], wp.abs(p[2]) - size[2])
    qmax = wp.max(q[0], wp.max(q[1], q[2]))
    # beyond a face by more than BOX_TIE somewhere: the closest point's direction (a face, a
    # rim or a corner region); a component within BOX_TIE of its face counts as on it
    if qmax > BOX_TIE:
        qo = wp.vec3(0.0)
        for k in range(3):
            if q[k] > BOX_TIE:
                qo[k] = q[k]
        l = wp.length(qo)
        n = wp.vec3(wp.sign(p[0]) * qo[0], wp.sign(p[1]) * qo[1], wp.sign(p[2]) * qo[2]) / l
        return wp.length(wp.vec3(wp.max(q[0], 0.0), wp.max(q[1], 0.0), wp.max(q[2], 0.0))), n
    # inside, or on the surface within BOX_TIE: the nearest face; on a tie within BOX_TIE (a
    # point on a rim or a corner: a grid sheet laid on the box with its lines on the rims) the
    # local y face first, a box's top under gravity. With x first, or the rim's bisector for
    # a point a float's rounding outside it, a sheet lying on a table had its rim vertices
    # pushed out sideways by the thickness, against their neighbours lifted straight up by it
    # (a 16 x 16 sheet on a box: 8-13 m/s in its first frames)
    n = wp.vec3(0.0)
    if q[1] >= q[0] - BOX_TIE and q[1] >= q[2] - BOX_TIE:
        n = wp.vec3(0.0, wp.sign(p[1]), 0.0)
    elif q[0] >= q[2] - BOX_TIE:
        n = wp.vec3(wp.sign(p[0]), 0.0, 0.0)
    else:
        n = wp.vec3(0.0, 0.0, wp.sign(p[2]))
    return qmax, n


@wp.func
def slab_entry(p0: wp.vec3, d: wp.vec3, ext: wp.vec3):
    """Slab test of the segment ``p0 -> p0 + d`` against the box ``|p_k| <= ext_k``: (enters,
    entry parameter in [0, 1], entry axis). A segment starting inside does not enter."""
    tmin = float(0.0)
    tmax = float(1.0)
    axis = int(-1)
    miss = bool(False)
    for k in range(3):
        if wp.abs(d[k]) < 1.0e-12:
            if wp.abs(p0[k]) > ext[k]:
                miss = True
        else:
            ta = (-ext[k] - p0[k]) / d[k]
            tb = (ext[k] - p0[k]) / d[k]
            tn = wp.min(ta, tb)
            tf = wp.max(ta, tb)
            if tn > tmin:
                tmin = tn
                axis = k
            tmax = wp.min(tmax, tf)
    return (not miss) and axis >= 0 and tmin <= tmax, tmin, axis


@wp.func
def shape_ccd(kind: int, size: wp.vec3, th: float, p0: wp.vec3, p1: wp.vec3, short2: float):
    """First entry of the segment p0 -> p1 into the shape inflated by ``th``.

    Returns (hit, entry point, outward normal there). Only when p0 starts outside. A sphere is
    not swept by a path no longer than ``sqrt(short2)`` (the contact passes the slack: a vertex
    resting on it moves that little, and its end's radial projection is all it needs; such a
    path cannot cross the sphere, and cuts at most ``short2 / (8 R)`` into it between its ends).
    """
    d = p1 - p0
    if kind == KIND_SPHERE:
        r = size[0] + th
        a = wp.dot(d, d)
        b = wp.dot(p0, d)
        c = wp.dot(p0, p0) - r * r
        if c > 0.0 and a > short2:
            disc = b * b - a * c
            if disc >= 0.0:
                t = (-b - wp.sqrt(disc)) / a
                if t >= 0.0 and t <= 1.0:
                    h = p0 + t * d
                    return True, h, wp.normalize(h)
        return False, p1, wp.vec3(0.0, 1.0, 0.0)
    if kind == KIND_BOX:
        # a path that enters the box itself is stopped where it enters the box inflated by th;
        # one that only cuts the inflated box's edge or corner region (outside the rounded
        # thickness layer, or barely in it) is not: its end's projection is all it needs, and
        # stopping it would hold a vertex sliding over an edge up in the air
        hit0, t0, axis0 = slab_entry(p0, d, size)
        if hit0:
            hit, t, axis = slab_entry(p0, d, size + wp.vec3(th))
            if hit:
                n = wp.vec3(0.0)
                n[axis] = -wp.sign(d[axis])
                return True, p0 + t * d, n
    return False, p1, wp.vec3(0.0, 1.0, 0.0)


@wp.func
def static_ball_far(reaches: wp.array(dtype=ObstacleReach), k: int, x0: wp.vec3, x1: wp.vec3,
                    reach: float, thickness: float, ccd: int):
    """`far_from` for a static obstacle other than a plane: its bounding ball (a sphere's is
    itself). A path no longer than the slack (``reach - thickness``) is far exactly when its end
    is (``lb >= reach`` implies ``lb - thickness >= slack >=`` the path), so squared lengths
    decide it without a square root: most vertices, most steps."""
    p = x1 - reaches[k].origin
    s2 = wp.length_sq(x1 - x0)
    sl = reach - thickness
    if ccd == 0 or s2 <= sl * sl:
        rr = reaches[k].bound + reach
        return wp.length_sq(p) >= rr * rr
    lb = wp.length(p) - reaches[k].bound
    gap = lb - thickness
    return lb >= reach and gap * gap >= s2


@wp.func
def static_plane_far(reaches: wp.array(dtype=ObstacleReach), k: int, x0: wp.vec3, x1: wp.vec3,
                     reach: float, thickness: float, ccd: int):
    """`far_from` for a static plane (exact)."""
    lb = wp.dot(x1 - reaches[k].origin, reaches[k].normal)
    if lb < reach:
        return False
    if ccd == 0:
        return True
    gap = lb - thickness
    return gap * gap >= wp.length_sq(x1 - x0)


@wp.func
def far_from(reaches: wp.array(dtype=ObstacleReach), k: int, x0: wp.vec3, x1: wp.vec3,
             reach: float, thickness: float, ccd: int):
    """True when the vertex's path ``x0 -> x1`` provably stays out of obstacle ``k``'s reach
    this step (then the vertex needs nothing from it). World frame, no transform: ``lb`` is a
    lower bound of phi at the end (exact for a plane and a sphere), phi is 1-Lipschitz, and the
    path in the obstacle's frame is no longer than ``|x1 - x0|`` plus what the obstacle's
    translation and rotation move the vertex's local position by (`ObstacleReach`). The fields
    are read in place: a struct passed by value is copied at every call (measured: a third of
    the far pass)."""
    sweep = reaches[k].sweep
    turn = reaches[k].turn
    if sweep == 0.0 and turn == 0.0:
        if reaches[k].plane != 0:
            return static_plane_far(reaches, k, x0, x1, reach, thickness, ccd)
        return static_ball_far(reaches, k, x0, x1, reach, thickness, ccd)
    r = x1 - reaches[k].origin
    shrink = reaches[k].shrink
    if reaches[k].plane == 0 and ccd != 0 and shrink > 0.0:
        # moving ball, short path (s <= slack): the test below holds when |r| (1 - turn) >=
        # bound + thickness + (slack + sweep) (1 + turn) (which also gives |r| - bound >=
        # reach); squared lengths (shrink = 1 / (1 - turn), from the pose launch) instead of two
        # square roots
        sl = reach - thickness
        if wp.length_sq(x1 - x0) <= sl * sl:
            rr = (reaches[k].bound + thickness + (sl + sweep) * (1.0 + turn)) * shrink
            if wp.length_sq(r) >= rr * rr:
                return True
    lb = float(0.0)
    if reaches[k].plane != 0:
        lb = wp.dot(r, reaches[k].normal)
    else:
        lb = wp.length(r) - reaches[k].bound
    if lb < reach:
        return False
    if ccd == 0:
        return True
    s = wp.length(x1 - x0)
    return lb - thickness >= s + sweep + turn * (wp.length(r) + s + sweep)


@wp.func
def analytic_near(
    ob: ObstacleData,
    poses: wp.array(dtype=wp.transform),
    j: int,
    i: int,
    x0: wp.vec3,
    x1: wp.vec3,
    v: wp.array(dtype=wp.vec3),
    vi: wp.vec3,
    touched: bool,
    dt: float,
    thickness: float,
    slack: float,
    respond_velocity: int,
    ccd: int,
):
    """Steps 1-3 in the obstacle's frame (any analytic kind, moving or not; ``j``: its first
    pose) for a vertex the far test did not reject. Returns (x1, vi, touched) updated."""
    reach = thickness + slack
    p1 = wp.transform_point(poses[j + 3], x1)
    p0 = wp.transform_point(poses[j + 2], x0)
    phi, n = shape_sdf(ob.kind, ob.size, p1)
    if phi >= reach:
        # the exact local test (the world bound is loose for boxes and moving shapes)
        if ccd == 0:
            return x1, vi, touched
        if (phi - thickness) * (phi - thickness) >= wp.length_sq(p1 - p0):
            return x1, vi, touched
    moved = False
    p_in = p1
    if ccd != 0 and ob.kind != KIND_PLANE:
        hit, h, nh = shape_ccd(ob.kind, ob.size, thickness, p0, p1, slack * slack)
        if hit:
            p1 = p1 + wp.max(-wp.dot(p1 - h, nh), 0.0) * nh
            phi, n = shape_sdf(ob.kind, ob.size, p1)
            moved = True
    if phi < thickness:
        p1 = p1 + (thickness - phi) * n
        moved = True
    if moved or (respond_velocity != 0 and phi < reach):
        vr = vi
        if respond_velocity != 0 and not touched:
            vr = v[i]
        xo, vo = contact_outcome(p0, p_in, p1, n, poses[j], poses[j + 1], vr, dt,
                                 ob.restitution, ob.friction, respond_velocity, thickness)
        return xo, vo, True
    return x1, vi, touched


@wp.func
def static_near(
    reaches: wp.array(dtype=ObstacleReach),
    k: int,
    i: int,
    x0: wp.vec3,
    x1: wp.vec3,
    v: wp.array(dtype=wp.vec3),
    vi: wp.vec3,
    touched: bool,
    thickness: float,
    slack: float,
    respond_velocity: int,
    ccd: int,
):
    """`analytic_near` for a static sphere or plane (``reaches[k].fast``), in the world frame: the same
    tests and outcome with the transforms and the (zero) surface velocity left out. Sphere:
    centre ``origin``, radius ``bound``; plane: point ``origin``, normal ``normal`` (fields read
    in place: a struct passed by value is copied at every call).
    Such a vertex arrives here only when within reach (`far_from` is exact for both)."""
    reach = thickness + slack
    p1 = x1 - reaches[k].origin
    p0 = x0 - reaches[k].origin
    phi = float(0.0)
    n = reaches[k].normal
    size = wp.vec3(reaches[k].bound, 0.0, 0.0)
    if reaches[k].fast == FAST_SPHERE:
        phi, n = shape_sdf(KIND_SPHERE, size, p1)
    else:
        phi = wp.dot(p1, n)
    moved = False
    p_in = p1
    if ccd != 0 and reaches[k].fast == FAST_SPHERE:
        hit, h, nh = shape_ccd(KIND_SPHERE, size, thickness, p0, p1, slack * slack)
        if hit:
            p1 = p1 + wp.max(-wp.dot(p1 - h, nh), 0.0) * nh
            phi, n = shape_sdf(KIND_SPHERE, size, p1)
            moved = True
    if phi < thickness:
        p1 = p1 + (thickness - phi) * n
        moved = True
    if moved or (respond_velocity != 0 and phi < reach):
        vr = vi
        if respond_velocity != 0 and not touched:
            vr = v[i]
        q, vo = outcome_in_frame(p0, p_in, p1, n, vr, wp.vec3(0.0), n, reaches[k].restitution,
                                 reaches[k].friction, respond_velocity, thickness)
        return q + reaches[k].origin, vo, True
    return x1, vi, touched


_KERNELS = {}


def analytic_far_kernel(kinds, update=None):
    """The far pass for analytic obstacles with the given `far_kinds` (a kernel per tuple, made
    on first use: a loop of known length is unrolled, which measured 30 % cheaper than a loop
    over ``reaches.shape[0]`` on the CPU, and each obstacle keeps only its own test)."""
    return _kernels(kinds, update)[0]


def integrate_far_kernel(kinds, update):
    """A solver's vertex update with the far pass of `analytic_far_kernel` in the same thread
    (`ObstacleContact.integrate_and_apply`). ``update`` is the solver's Warp function
    ``(v, f, inv_mass, gravity, decay, dt) -> new v`` (the collision layer knows no solver)."""
    return _kernels(kinds, update)[1]


def integrate_contact_kernel(kinds, update):
    """A solver's vertex update with the whole contact in the same thread, for static
    spheres and planes only (`FAR_SPHERE`, `FAR_PLANE`)."""
    if any(k not in (FAR_SPHERE, FAR_PLANE) for k in kinds):
        raise ValueError("integrate_contact_kernel is for static spheres and planes only")
    return _kernels(kinds, update)[3]


def analytic_near_kernel(kinds, update=None):
    """The near pass (the listed vertices) for analytic obstacles with the given `far_kinds`
    (``update``: the module the solver's fused kernels share, so one compile serves both)."""
    return _kernels(kinds, update)[2]


#: `far_kinds` codes: what each obstacle's kernels compile in. GENERAL: moving (general far test,
#: local-frame near path); BALL: static box (bounding-ball far test, local-frame near path);
#: SPHERE / PLANE: static sphere / plane (exact squared far test, world-frame near path)
FAR_GENERAL, FAR_BALL, FAR_SPHERE, FAR_PLANE = 0, 1, 2, 3


def far_kinds(obstacles) -> tuple:
    """Per analytic obstacle, its `far_kinds` code (which tests its kernels compile in)."""
    from .motion import KIND_PLANE, KIND_SPHERE

    return tuple(FAR_GENERAL if ob.moving else FAR_PLANE if ob.kind == KIND_PLANE
                 else FAR_SPHERE if ob.kind == KIND_SPHERE else FAR_BALL for ob in obstacles)


def _kernels(kinds, update=None):
    kinds = tuple(int(k) for k in kinds)
    key = (kinds, update)
    kernels = _KERNELS.get(key)
    if kernels is None:
        kernels = _KERNELS[key] = _make_far_kernels(kinds, update)
    return kernels


def _make_far_kernels(kinds, update):
    num = len(kinds)
    # the four kernels of one tuple in one module (one compile), without the backward pass
    module = "warp_cloth.collision.analytic_kinds_" + "_".join(str(k) for k in kinds)
    if update is not None:
        module += "_" + update.key
    wp.set_module_options({"enable_backward": False}, module=module)
    # which test each obstacle needs, as constants of the generated code (the unrolled loop
    # keeps one test per obstacle, without the branches on its kind and motion)
    BALLS = wp.constant(sum(1 << k for k, c in enumerate(kinds) if c in (FAR_BALL, FAR_SPHERE)))
    PLANES = wp.constant(sum(1 << k for k, c in enumerate(kinds) if c == FAR_PLANE))
    FAST = wp.constant(sum(1 << k for k, c in enumerate(kinds) if c in (FAR_SPHERE, FAR_PLANE)))

    @wp.func
    def far_k(reaches: wp.array(dtype=ObstacleReach), k: int, x0: wp.vec3, x1: wp.vec3,
              reach: float, thickness: float, ccd: int):
        """`far_from` for obstacle ``k`` (a loop constant), with only the test its kind needs."""
        if ((BALLS >> k) & 1) != 0:
            return static_ball_far(reaches, k, x0, x1, reach, thickness, ccd)
        if ((PLANES >> k) & 1) != 0:
            return static_plane_far(reaches, k, x0, x1, reach, thickness, ccd)
        return far_from(reaches, k, x0, x1, reach, thickness, ccd)

    @wp.func
    def first_near(reaches: wp.array(dtype=ObstacleReach), first: int, x0: wp.vec3,
                   x1: wp.vec3, reach: float, thickness: float, ccd: int):
        """The first obstacle from ``first`` on whose far test the path fails, or -1."""
        for k in range(num):
            if k >= first and not far_k(reaches, k, x0, x1, reach, thickness, ccd):
                return k
        return -1

    @wp.kernel(module=module)
    def near_kernel(
        obstacles: wp.array(dtype=ObstacleData),
        reaches: wp.array(dtype=ObstacleReach),
        poses: wp.array(dtype=wp.transform),
        pose_offset: int,
        x: wp.array(dtype=wp.vec3),
        x_start: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        dt: float,
        thickness: float,
        slack: float,
        respond_velocity: int,
        ccd: int,
        near_count: wp.array(dtype=int),
        near_list: wp.array(dtype=int),
        num_threads: int,
    ):
        """Pass 2, the listed vertices (strided over the threads): each obstacle the vertex is
        within reach of (the far test again from the second obstacle on: an earlier one may
        have moved the vertex; a single obstacle's was the test that listed it), static spheres
        and planes in the world frame (`static_near`), the rest in their frames
        (`analytic_near`). ``v[i]`` is read only when touched."""
        t = wp.tid()
        n = near_count[0]
        reach = thickness + slack
        for e in range(t, n, num_threads):
            i = near_list[e]
            x0 = x_start[i]
            x1 = x[i]
            vi = wp.vec3(0.0)
            touched = bool(False)
            for k in range(num):
                if num == 1 or not far_k(reaches, k, x0, x1, reach, thickness, ccd):
                    if ((FAST >> k) & 1) != 0:
                        x1, vi, touched = static_near(reaches, k, i, x0, x1, v, vi, touched,
                                                      thickness, slack, respond_velocity, ccd)
                    else:
                        x1, vi, touched = analytic_near(obstacles[k], poses,
                                                        5 * (pose_offset + k), i, x0, x1, v, vi,
                                                        touched, dt, thickness, slack,
                                                        respond_velocity, ccd)
            if touched:
                x[i] = x1
                if respond_velocity != 0:
                    v[i] = vi

    @wp.kernel(module=module)
    def far_kernel(
        reaches: wp.array(dtype=ObstacleReach),
        x: wp.array(dtype=wp.vec3),
        x_start: wp.array(dtype=wp.vec3),
        inv_mass: wp.array(dtype=float),
        thickness: float,
        slack: float,
        ccd: int,
        near_count: wp.array(dtype=int),
        near_list: wp.array(dtype=int),
        margin: float,
        iter_count: wp.array(dtype=int),
        iter_list: wp.array(dtype=int),
    ):
        """Pass 1, every vertex: the far tests; a vertex that passes none is appended to
        ``near_list`` (two passes: see `warp_cloth.collision.mesh_contact`). With
        ``margin > 0`` a vertex within the reach plus ``margin`` is also appended to
        ``iter_list``: the vertices the next step's position-based iterations will test
        (`ObstacleContact.begin_iterations`)."""
        i = wp.tid()
        if inv_mass[i] == 0.0:
            return  # pinned vertices are never moved by contact
        x0 = x_start[i]
        x1 = x[i]
        reach = thickness + slack
        first = int(0)
        if margin > 0.0:
            first = first_near(reaches, 0, x0, x1, reach + margin, thickness + margin, ccd)
            if first < 0:
                return
            iter_list[wp.atomic_add(iter_count, 0, 1)] = i
        if first_near(reaches, first, x0, x1, reach, thickness, ccd) >= 0:
            near_list[wp.atomic_add(near_count, 0, 1)] = i

    if update is None:
        return far_kernel, None, near_kernel, None

    @wp.kernel(module=module)
    def integrate_far(
        x: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        f: wp.array(dtype=wp.vec3),
        inv_mass: wp.array(dtype=float),
        gravity: wp.vec3,
        decay: float,
        dt: float,
        x_start: wp.array(dtype=wp.vec3),
        reaches: wp.array(dtype=ObstacleReach),
        thickness: float,
        slack: float,
        ccd: int,
        near_count: wp.array(dtype=int),
        near_list: wp.array(dtype=int),
    ):
        """The solver's vertex update (``update``), then the far tests of the new path; a vertex that
        passes none is listed for the near pass, and only its start position is written to
        ``x_start`` (the near pass reads no other)."""
        i = wp.tid()
        w = inv_mass[i]
        fi = f[i]
        f[i] = wp.vec3(0.0)  # cleared for the next step's forces
        if w == 0.0:
            return
        x0 = x[i]
        vi = update(v[i], fi, w, gravity, decay, dt)
        x1 = x0 + dt * vi
        v[i] = vi
        x[i] = x1
        if first_near(reaches, 0, x0, x1, thickness + slack, thickness, ccd) >= 0:
            x_start[i] = x0
            near_list[wp.atomic_add(near_count, 0, 1)] = i

    @wp.kernel(module=module)
    def integrate_contact(
        x: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        f: wp.array(dtype=wp.vec3),
        inv_mass: wp.array(dtype=float),
        gravity: wp.vec3,
        decay: float,
        dt: float,
        reaches: wp.array(dtype=ObstacleReach),
        thickness: float,
        slack: float,
        ccd: int,
    ):
        """For static spheres and planes only: the solver's vertex update and the whole
        contact (far tests, then `static_near` from the first obstacle within reach) in one
        thread: no list, no second pass. The same result as `integrate_far` and `near_kernel`
        (their world-frame path has few variables, so far vertices do not pay for it)."""
        i = wp.tid()
        w = inv_mass[i]
        fi = f[i]
        f[i] = wp.vec3(0.0)  # cleared for the next step's forces
        if w == 0.0:
            return
        x0 = x[i]
        vi = update(v[i], fi, w, gravity, decay, dt)
        x1 = x0 + dt * vi
        v[i] = vi
        reach = thickness + slack
        first = first_near(reaches, 0, x0, x1, reach, thickness, ccd)
        if first >= 0:
            touched = bool(True)  # v[i] holds vi: static_near reads it from vi
            for k in range(num):
                if k == first or (k > first and not far_k(reaches, k, x0, x1, reach, thickness,
                                                          ccd)):
                    x1, vi, touched = static_near(reaches, k, i, x0, x1, v, vi, touched,
                                                  thickness, slack, 1, ccd)
            v[i] = vi
        x[i] = x1

    return far_kernel, integrate_far, near_kernel, integrate_contact


@wp.kernel
def analytic_planes_kernel(
    obstacles: wp.array(dtype=ObstacleData),
    reaches: wp.array(dtype=ObstacleReach),
    poses: wp.array(dtype=wp.transform),
    x: wp.array(dtype=wp.vec3),
    x_start: wp.array(dtype=wp.vec3),
    thickness: float,
    ccd: int,
    near_count: wp.array(dtype=int),
    near_list: wp.array(dtype=int),
    num_threads: int,
    planes: ContactPlanes,
):
    """The contact plane of each listed vertex and analytic obstacle (`warp_cloth.collision.
    planes`): the continuous test, then the point at the thickness above the closest surface
    point of the (possibly stopped) end position, in the world frame at ``t1``."""
    t = wp.tid()
    n_list = near_count[0]
    num = obstacles.shape[0]
    for e in range(t, n_list, num_threads):
        i = near_list[e]
        x0 = x_start[i]
        x1 = x[i]
        for k in range(num):
            c = e * num + k
            rb = reaches[k]
            if rb.fast != FAST_NONE:  # static sphere or plane: in the world frame
                p1 = x1 - rb.origin
                n = rb.normal
                phi = wp.dot(p1, n)
                if rb.fast == FAST_SPHERE:
                    size = wp.vec3(rb.bound, 0.0, 0.0)
                    if ccd != 0:
                        hit, h, nh = shape_ccd(KIND_SPHERE, size, thickness, x0 - rb.origin, p1, 0.0)
                        if hit:
                            p1 = p1 + wp.max(-wp.dot(p1 - h, nh), 0.0) * nh
                    phi, n = shape_sdf(KIND_SPHERE, size, p1)
                planes.point[c] = rb.origin + p1 + (thickness - phi) * n
                planes.normal[c] = n
                planes.ref[c] = x0
                planes.friction[c] = rb.friction
                continue
            ob = obstacles[k]
            j = 5 * k
            p1 = wp.transform_point(poses[j + 3], x1)
            p0 = wp.transform_point(poses[j + 2], x0)
            if ccd != 0 and ob.kind != KIND_PLANE:
                hit, h, nh = shape_ccd(ob.kind, ob.size, thickness, p0, p1, 0.0)
                if hit:
                    p1 = p1 + wp.max(-wp.dot(p1 - h, nh), 0.0) * nh
            phi, n = shape_sdf(ob.kind, ob.size, p1)
            T1 = poses[j + 1]
            planes.point[c] = wp.transform_point(T1, p1 + (thickness - phi) * n)
            planes.normal[c] = wp.transform_vector(T1, n)
            planes.ref[c] = wp.transform_point(T1, p0)
            planes.friction[c] = ob.friction
