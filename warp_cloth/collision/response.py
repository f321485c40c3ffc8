"""The contact response shared by every obstacle kind (Warp functions; no kernels here).

The impulse method of the notes (``physics.md`` section 2.17, L2670-2691), applied to the velocity
relative to the obstacle's own surface velocity ``v_s``, with outward unit normal ``N``:

    v_r = v - v_s;   if v_r . N < 0:
        v_N = (v_r . N) N,   v_T = v_r - v_N
        a   = max(1 - mu_T (1 + mu_N) |v_N| / |v_T|, 0)         (a = 0 when |v_T| ~ 0)
        v  <- v_s - mu_N v_N + a v_T

``a = 0`` is static friction (the tangential relative velocity vanishes: stick); ``0 < a < 1`` is
sliding friction, whose tangential change ``(1 - a)|v_T|`` equals ``mu_T`` times the normal change
``(1 + mu_N)|v_N|`` (Coulomb). The same factor ``a`` scales the vertex's tangential displacement
relative to the obstacle over the step, so that positions agree with velocities: a sticking vertex
does not creep, and one on a moving obstacle is carried along with it.
"""

from __future__ import annotations

import warp as wp


@wp.func
def impulse(v: wp.vec3, vs: wp.vec3, n: wp.vec3, mu_n: float, mu_t: float):
    """(new velocity, tangential factor a). ``a = 1`` means no impulse (separating)."""
    vr = v - vs
    vn = wp.dot(vr, n)
    if vn >= 0.0:
        return v, 1.0
    v_n = vn * n
    v_t = vr - v_n
    lt = wp.length(v_t)
    a = float(1.0)
    if mu_t > 0.0:
        a = 0.0
        if lt > 1.0e-12:
            a = wp.max(1.0 - mu_t * (1.0 + mu_n) * (-vn) / lt, 0.0)
    return vs - mu_n * v_n + a * v_t, a


@wp.func
def position_friction(p0: wp.vec3, p_in: wp.vec3, p_out: wp.vec3, n: wp.vec3, mu_t: float):
    """Coulomb friction at the position level (for `project_positions`, inside position-based
    iterations, where velocities are not available; Macklin et al. 2014, *Unified Particle
    Physics*, eq. 24): the projection moved the vertex by ``delta = |p_out - p_in|`` along the
    normal; its tangential displacement relative to the obstacle since the start of the step,
    ``d_T``, is removed if ``|d_T| <= mu_T delta`` (static) and shortened by ``mu_T delta``
    otherwise (sliding). All in the obstacle's frame."""
    d = p_out - p0
    d_t = d - wp.dot(d, n) * n
    lt = wp.length(d_t)
    cap = mu_t * wp.length(p_out - p_in)
    if lt <= cap:
        return p_out - d_t
    return p_out - (cap / lt) * d_t


@wp.func
def contact_share(p0: wp.vec3, p_in: wp.vec3, p1: wp.vec3, n: wp.vec3, level: float):
    """The share of the step's path ``p0 -> p_in`` spent in contact, along the normal ``n`` of
    the end ``p1`` (``p_in`` projected): with ``h0`` and ``h_in`` the start's and the
    unprojected end's heights above the end along ``n``, the path comes within ``level`` (the
    thickness) of the end's level at ``tau = (h0 - level) / (h0 - h_in)``, and the share is
    ``1 - tau``; 1 for a path that starts within ``level`` of it (resting, sliding, or lifted by
    another response: self-collision's projection moves a layer by up to the thickness between
    steps, which is no approach; with the slack (a tenth of it) as the level, explicit Euler's
    stack of sheets gained 2.4e-2 J in a frame, 6e-5 before)."""
    h0 = wp.dot(p0 - p1, n)
    h_in = wp.dot(p_in - p1, n)
    if h0 <= level or h0 <= h_in:
        return 1.0
    return wp.clamp((level - h_in) / (h0 - h_in), 0.0, 1.0)


@wp.func
def outcome_in_frame(p0: wp.vec3, p_in: wp.vec3, p1: wp.vec3, n: wp.vec3, v: wp.vec3,
                     vs: wp.vec3, nv: wp.vec3, mu_n: float, mu_t: float, respond_velocity: int,
                     level: float):
    """The end of one vertex-obstacle contact in the obstacle's frame: (end position ``q`` in that
    frame, new velocity). ``v``, ``vs`` and ``nv`` (the normal ``n`` in the velocities' frame) are
    only used with ``respond_velocity``.

    With ``respond_velocity`` (``apply``): the notes' impulse (`impulse`) and the matching
    tangential position change (the same factor ``a`` scales the tangential displacement of the
    part of the step spent in contact, `contact_share`: a sticking vertex does not creep, and a
    vertex arriving from afar keeps the slide it made before it touched: one arriving from 2 cm
    above the thickness at 2.4 m/s, with as much sideways speed, was put back 8 mm, now 2.3).
    With ``respond_velocity == 2`` (the pass
    after the features' response, `CollisionStage._pairs`): the impulse only. The features'
    friction may have slowed the vertex since the first pass without moving it back (velocity
    only, all solvers but explicit Euler), so its velocity no longer tells how it moved in the
    step, and the factor of that small velocity undid the whole step's slide: measured, a vertex
    sliding at 0.42 m/s onto the table's edge under projective dynamics (20 iterations) was put
    back 2.35 mm, stretching its edges 7 % and adding 2.2e-2 J in a step. The slide happened
    before the stop; what this pass's impulse changes moves it at most ``|v_T| dt``. Without
    (``project_positions``, inside position-based iterations): the projected position with
    position-level Coulomb friction."""
    if respond_velocity != 0:
        vnew, a = impulse(v, vs, nv, mu_n, mu_t)
        if respond_velocity == 2:
            return p1, vnew
        d = p1 - p0
        d_t = d - wp.dot(d, n) * n
        return p1 - (1.0 - a) * contact_share(p0, p_in, p1, n, level) * d_t, vnew
    q = p1
    if mu_t > 0.0:
        q = position_friction(p0, p_in, p1, n, mu_t)
    return q, v


@wp.func
def pose_velocity(T0: wp.transform, T1: wp.transform, p: wp.vec3, dt: float):
    """World velocity at the end of a step of the material point ``p`` (obstacle frame) of a
    body posed ``T0`` / ``T1`` at the step's start / end: the centre's mean velocity plus the
    step's mean turn about the centre where the point is at the end, ``(c1 - c0) / dt + W x
    (T1 p - c1)`` (``W``: the rotation ``q1 q0^-1`` as axis times angle, over ``dt``), as the
    obstacles move (`motion.obstacle_pose`: a centre that moves, a turn about it). The chord
    ``(T1 p - T0 p) / dt`` is not a surface velocity: it points off the surface by half the
    step's turn, so a sphere spinning about its centre (3 rad/s, 1/180 s steps) seemed to move
    its surface outward at ``r w^2 dt / 2`` = 7.5 mm/s, and each inelastic impulse pushed the
    cloth out at that speed (projective dynamics gained up to 6e-5 J a frame from a
    frictionless spinning sphere, which can do no work)."""
    c0 = wp.transform_get_translation(T0)
    c1 = wp.transform_get_translation(T1)
    dq = wp.mul(wp.transform_get_rotation(T1), wp.quat_inverse(wp.transform_get_rotation(T0)))
    if dq[3] < 0.0:
        dq = -dq
    axis = wp.vec3(dq[0], dq[1], dq[2])
    s = wp.length(axis)
    w = wp.vec3(0.0)
    if s > 1.0e-12:
        w = axis * (2.0 * wp.atan2(s, dq[3]) / (s * dt))
    return (c1 - c0) / dt + wp.cross(w, wp.transform_point(T1, p) - c1)


@wp.func
def contact_outcome(p0: wp.vec3, p_in: wp.vec3, p1: wp.vec3, n: wp.vec3, T0: wp.transform,
                    T1: wp.transform, v: wp.vec3, dt: float, mu_n: float, mu_t: float,
                    respond_velocity: int, level: float):
    """`outcome_in_frame` for an obstacle with poses ``T0`` / ``T1`` at the start / end of the
    step (positions in its frame, velocities in the world's); the surface velocity is that of
    the material point at the end position (`pose_velocity`). Returns (world end position,
    world velocity; ``v`` unchanged without a velocity response)."""
    vs = wp.vec3(0.0)
    nw = n
    if respond_velocity != 0:
        nw = wp.transform_vector(T1, n)
        vs = pose_velocity(T0, T1, p1, dt)
    q, vnew = outcome_in_frame(p0, p_in, p1, n, v, vs, nw, mu_n, mu_t, respond_velocity,
                               level)
    return wp.transform_point(T1, q), vnew
