"""Scripted rigid motion of obstacles, evaluated on the device from the simulated time.

An obstacle has a rest pose ``B`` (centre ``c_B``, rotation ``R_B``) and a `Motion`. Its pose at
time ``t`` maps a point ``p`` of the obstacle's own (local) frame to the world as

    y(t) = c(t) + R(t) p,      c(t) = c_B + d(t) + u tau(t),      R(t) = exp(w tau(t)) Q(t) R_B

where ``u`` (m/s) and ``w`` (rad/s, world axes, about the obstacle's centre) are a constant linear
and angular velocity, ``d(t), Q(t)`` an optional `KeyframePath` (offset of the centre, rotation about
the centre; linear / slerp between keys, clamped at both ends), and ``tau(t)`` the elapsed time since
``start`` with an optional linear ``ramp`` of the speed:

    s = max(t - start, 0);   tau = s^2 / (2 ramp)  if s < ramp,   else  s - ramp / 2

so the velocity grows linearly from 0 to ``u`` (and the spin to ``w``) over ``ramp`` seconds.

The same formula exists twice: `Motion.pose` (NumPy, float64; for USD output and tests) and
`obstacle_pose` (a Warp function used by the contact kernels, reading the time from the device
so a step stays capturable as a graph). The surface velocity of the obstacle at a world point is
taken as the displacement of the material point over the step, ``(y - T(t0) T(t1)^-1 y) / dt``,
which is consistent with the contact kernels' test of each vertex's path in the obstacle frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

#: largest finite float32 (the device arrays' type; as `warp_cloth.mesh.FLOAT32_MAX`)
FLOAT32_MAX = float(np.finfo(np.float32).max)

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile

__all__ = [
    "KeyframePath", "Motion", "ObstacleData", "ObstacleReach", "obstacle_pose", "step_reach", "quat_from_axis_angle",
    "quat_between", "quat_multiply", "quat_rotate", "KIND_PLANE", "KIND_SPHERE", "KIND_BOX",
    "KIND_MESH", "FAST_NONE", "FAST_SPHERE", "FAST_PLANE",
]

KIND_PLANE = 0
KIND_SPHERE = 1
KIND_BOX = 2
KIND_MESH = 3

#: `ObstacleReach.fast` values
FAST_NONE = 0
FAST_SPHERE = 1
FAST_PLANE = 2

TWO_PI = 2.0 * math.pi


# ---------------------------------------------------------------- host quaternions (x, y, z, w)
def quat_from_axis_angle(axis, angle: float) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` for a rotation of ``angle`` radians about ``axis``."""
    a = np.asarray(axis, dtype=np.float64).reshape(3)
    n = np.linalg.norm(a)
    if n == 0.0 or angle == 0.0:
        return np.array([0.0, 0.0, 0.0, 1.0])
    s = math.sin(0.5 * angle) / n
    return np.array([a[0] * s, a[1] * s, a[2] * s, math.cos(0.5 * angle)])


def quat_multiply(a, b) -> np.ndarray:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ])


def quat_rotate(q, p) -> np.ndarray:
    """Rotate points ``p`` (..., 3) by the unit quaternion ``q``."""
    q = np.asarray(q, dtype=np.float64)
    u, w = q[:3], q[3]
    p = np.asarray(p, dtype=np.float64)
    t = 2.0 * np.cross(u, p)
    return p + w * t + np.cross(u, t)


def quat_between(a, b) -> np.ndarray:
    """The shortest rotation taking direction ``a`` to direction ``b``."""
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    c = float(np.dot(a, b))
    if c < -1.0 + 1e-12:  # opposite: any perpendicular axis
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 0.0, 1.0])
        return quat_from_axis_angle(axis, math.pi)
    q = np.array([*np.cross(a, b), 1.0 + c])
    return q / np.linalg.norm(q)


def _slerp(a, b, s):
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    d = float(np.dot(a, b))
    if d < 0.0:
        b, d = -b, -d
    if d > 0.9995:
        q = a + s * (b - a)
        return q / np.linalg.norm(q)
    th = math.acos(min(d, 1.0))
    return (math.sin((1 - s) * th) * a + math.sin(s * th) * b) / math.sin(th)


def check_vec3(name, value) -> np.ndarray:
    """``value`` as 3 finite float64 numbers within float32's range, else a `ValueError`
    naming ``name`` (strings, bools and other non-numbers included)."""
    raw = np.asarray(value, dtype=object).reshape(-1)
    if any(isinstance(c, (str, bytes, bool, np.bool_)) for c in raw):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    try:
        a = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}") from None
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    if np.abs(a).max() > FLOAT32_MAX:  # (the device's float32 would make it inf)
        raise ValueError(f"{name} {tuple(float(c) for c in a)} is beyond the float32 range the "
                         f"simulation "
                         f"computes in (+-{FLOAT32_MAX:.3g})")
    return a


def check_quat(name, value) -> np.ndarray:
    q = np.asarray(value, dtype=np.float64).reshape(-1)
    if q.shape != (4,) or not np.all(np.isfinite(q)):
        raise ValueError(f"{name} must be a quaternion of 4 finite numbers (x, y, z, w), got {value!r}")
    n = np.linalg.norm(q)
    if n < 1e-9:
        raise ValueError(f"{name} must be a non-zero quaternion, got {value!r}")
    return q / n


# ---------------------------------------------------------------- host motion description
@dataclass
class KeyframePath:
    """A keyframed rigid path: offsets of the obstacle's centre and rotations about it.

    Args:
        times: (K,) strictly increasing key times in seconds. Before the first key the obstacle
            holds the first key's pose, after the last the last one's.
        offsets: (K, 3) displacement of the centre from its rest position, metres.
        rotations: optional (K, 4) unit quaternions ``(x, y, z, w)`` applied about the centre
            (slerp between keys, so keep successive keys less than 180 degrees apart).
    """

    times: np.ndarray
    offsets: np.ndarray
    rotations: np.ndarray | None = None

    def __post_init__(self):
        self.times = np.asarray(self.times, dtype=np.float64).reshape(-1)
        k = len(self.times)
        if k < 1:
            raise ValueError("KeyframePath: needs at least one key")
        if not np.all(np.isfinite(self.times)):
            raise ValueError("KeyframePath: times must be finite")
        if k > 1 and np.any(np.diff(self.times) <= 0):
            i = int(np.argmax(np.diff(self.times) <= 0))
            raise ValueError(f"KeyframePath: times must increase strictly (key {i + 1})")
        self.offsets = np.asarray(self.offsets, dtype=np.float64)
        if self.offsets.shape != (k, 3) or not np.all(np.isfinite(self.offsets)):
            raise ValueError(f"KeyframePath: offsets must be finite with shape ({k}, 3), "
                             f"got {self.offsets.shape}")
        if self.rotations is None:
            self.rotations = np.tile([0.0, 0.0, 0.0, 1.0], (k, 1))
        else:
            r = np.asarray(self.rotations, dtype=np.float64)
            if r.shape != (k, 4) or not np.all(np.isfinite(r)):
                raise ValueError(f"KeyframePath: rotations must be finite with shape ({k}, 4)")
            n = np.linalg.norm(r, axis=1)
            if np.any(n < 1e-9):
                raise ValueError(f"KeyframePath: rotation {int(np.argmin(n))} is a zero quaternion")
            self.rotations = r / n[:, None]

    def at(self, t: float):
        """(offset, rotation) at time ``t``."""
        ts = self.times
        if t <= ts[0]:
            return self.offsets[0].copy(), self.rotations[0].copy()
        if t >= ts[-1]:
            return self.offsets[-1].copy(), self.rotations[-1].copy()
        k = int(np.searchsorted(ts, t, side="right") - 1)
        s = (t - ts[k]) / (ts[k + 1] - ts[k])
        off = self.offsets[k] * (1 - s) + self.offsets[k + 1] * s
        return off, _slerp(self.rotations[k], self.rotations[k + 1], s)


@dataclass
class Motion:
    """Scripted rigid motion of an obstacle (see the module docstring for the formula).

    Args:
        linear_velocity: m/s, world axes.
        angular_velocity: rad/s, world axes, about the obstacle's centre (``(0, 3, 0)``: spin
            about the vertical at 3 rad/s).
        start: s; the velocities act from this time on.
        ramp: s; the velocities grow linearly from 0 over this time after ``start`` (0: at once).
        path: optional `KeyframePath` composed with the velocities.
    """

    linear_velocity: tuple = (0.0, 0.0, 0.0)
    angular_velocity: tuple = (0.0, 0.0, 0.0)
    start: float = 0.0
    ramp: float = 0.0
    path: KeyframePath | None = None

    def __post_init__(self):
        self.linear_velocity = check_vec3("linear_velocity", self.linear_velocity)
        self.angular_velocity = check_vec3("angular_velocity", self.angular_velocity)
        self.start = float(self.start)
        self.ramp = float(self.ramp)
        if not math.isfinite(self.start):
            raise ValueError(f"start must be finite, got {self.start}")
        if not (math.isfinite(self.ramp) and self.ramp >= 0):
            raise ValueError(f"ramp must be finite and >= 0 seconds, got {self.ramp}")
        if self.path is not None and not isinstance(self.path, KeyframePath):
            raise TypeError("path must be a KeyframePath")

    @property
    def is_static(self) -> bool:
        return (self.path is None and not np.any(self.linear_velocity)
                and not np.any(self.angular_velocity))

    def tau(self, t: float) -> float:
        s = max(t - self.start, 0.0)
        if self.ramp > 0.0 and s < self.ramp:
            return s * s / (2.0 * self.ramp)
        return s - 0.5 * self.ramp

    def pose(self, t: float, position, rotation):
        """World centre and rotation ``(x, y, z, w)`` at time ``t`` of a body at rest pose
        (``position``, ``rotation``)."""
        tau = self.tau(t)
        c = np.asarray(position, dtype=np.float64) + self.linear_velocity * tau
        q = np.asarray(rotation, dtype=np.float64)
        if self.path is not None:
            off, qp = self.path.at(t)
            c = c + off
            q = quat_multiply(qp, q)
        rate = float(np.linalg.norm(self.angular_velocity))
        if rate > 0.0:
            ang = math.fmod(rate * tau, TWO_PI)
            q = quat_multiply(quat_from_axis_angle(self.angular_velocity, ang), q)
        return c, q / np.linalg.norm(q)


def steady_frame(obstacles, gravity):
    """The rigid frame in which every moving obstacle of ``obstacles`` stands still once its
    ramp is over: ``(velocity, angular_velocity, centre)`` (float64 arrays), or None.

    It exists when the moving obstacles share one steady motion without a keyframe path: a
    translation at one velocity, or a turn at one angular velocity parallel to gravity about one
    axis (their centres on it). In that frame the obstacles do no work: their normal forces
    are workless and friction only takes relative motion out, so the cloth's energy seen from
    it (`warp_cloth.diagnostics.frame_energy`: the relative kinetic energy, gravity, elastic,
    and the centrifugal potential) must not rise. A turn about another axis (gravity would turn
    in the frame and do work there), a translation and a turn together (an axis that moves),
    or obstacles moving differently have no such frame: None."""
    movers = [ob for ob in obstacles if ob.moving]
    if not movers:
        return None
    g = np.asarray(gravity, dtype=np.float64).reshape(3)
    first = movers[0].motion
    u = np.asarray(first.linear_velocity, dtype=np.float64)
    w = np.asarray(first.angular_velocity, dtype=np.float64)
    c = np.asarray(movers[0].pose(0.0)[0], dtype=np.float64)
    if np.any(u) and np.any(w):
        return None
    if np.any(w) and np.linalg.norm(np.cross(w, g)) > 1e-9 * np.linalg.norm(w) * max(
            np.linalg.norm(g), 1e-30):
        return None
    axis = w / np.linalg.norm(w) if np.any(w) else None
    for ob in movers:
        m = ob.motion
        if m.path is not None:
            return None
        if not (np.array_equal(np.asarray(m.linear_velocity, dtype=np.float64), u)
                and np.array_equal(np.asarray(m.angular_velocity, dtype=np.float64), w)):
            return None
        if axis is not None:  # turning about one axis: the centres on it
            off = np.asarray(ob.pose(0.0)[0], dtype=np.float64) - c
            if np.linalg.norm(np.cross(off, axis)) > 1e-9 * max(1.0, np.linalg.norm(off)):
                return None
    return u, w, c


# ---------------------------------------------------------------- device data and pose
@wp.struct
class ObstacleData:
    """One obstacle as the contact kernels see it (see `warp_cloth.collision.obstacles`)."""

    kind: int  # KIND_PLANE, KIND_SPHERE, KIND_BOX, KIND_MESH
    size: wp.vec3  # sphere: (r, 0, 0); box: half extents; mesh: local AABB half extents
    center: wp.vec3  # mesh: local AABB centre (else 0)
    closed: int  # mesh: 1 when watertight and outward oriented
    moving: int  # 0: the pose never changes
    bound: float  # radius of a ball about the local origin holding the shape (0 for a plane)
    position: wp.vec3  # rest pose centre, m
    rotation: wp.quat  # rest pose rotation
    velocity: wp.vec3  # m/s
    spin_axis: wp.vec3  # unit
    spin_rate: wp.float64  # rad/s
    start: wp.float64  # s
    ramp: wp.float64  # s
    key_start: int  # first key in the shared key arrays
    key_count: int  # 0: no path
    friction: float  # mu_T
    restitution: float  # mu_N


@wp.func
def motion_tau(ob: ObstacleData, t: wp.float64):
    s = wp.max(t - ob.start, wp.float64(0.0))
    if ob.ramp > wp.float64(0.0) and s < ob.ramp:
        return s * s / (wp.float64(2.0) * ob.ramp)
    return s - wp.float64(0.5) * ob.ramp


@wp.func
def obstacle_pose(ob: ObstacleData, key_times: wp.array(dtype=wp.float64),
                  key_offsets: wp.array(dtype=wp.vec3), key_rotations: wp.array(dtype=wp.quat),
                  t: wp.float64):
    """World transform (local -> world) of obstacle ``ob`` at time ``t`` (same as `Motion.pose`)."""
    tau = motion_tau(ob, t)
    c = ob.position + ob.velocity * float(tau)
    q = ob.rotation
    n = ob.key_count
    if n > 0:
        k0 = ob.key_start
        off = key_offsets[k0]
        qp = key_rotations[k0]
        if t >= key_times[k0 + n - 1]:
            off = key_offsets[k0 + n - 1]
            qp = key_rotations[k0 + n - 1]
        elif t > key_times[k0]:
            k = k0
            while k < k0 + n - 2 and t >= key_times[k + 1]:
                k += 1
            s = float((t - key_times[k]) / (key_times[k + 1] - key_times[k]))
            off = key_offsets[k] * (1.0 - s) + key_offsets[k + 1] * s
            qa = key_rotations[k]
            qb = key_rotations[k + 1]
            if wp.dot(qa, qb) < 0.0:
                qb = -qb
            qp = wp.quat_slerp(qa, qb, s)
        c = c + off
        q = wp.mul(qp, q)
    if ob.spin_rate > wp.float64(0.0):
        ang = wp.mod(ob.spin_rate * tau, wp.float64(6.283185307179586))
        q = wp.mul(wp.quat_from_axis_angle(ob.spin_axis, float(ang)), q)
    return wp.transform(c, wp.normalize(q))


@wp.struct
class ObstacleReach:
    """What the contact kernels' far test needs of one obstacle in one step, in the world frame
    (a few floats, so that a vertex far from every obstacle loads little and transforms nothing).

    A vertex at ``x0 -> x1`` with ``lb = |x1 - origin| - bound`` (plane: ``(x1 - origin) . normal``)
    is at least ``lb`` from the obstacle at ``t1``, and its path in the obstacle's frame is at
    most ``|x1 - x0| + sweep + turn (|x1 - origin| + |x1 - x0| + sweep)`` long (the translation
    and rotation of the obstacle over the step act on the vertex's local position)."""

    origin: wp.vec3  # world position of the local origin at t1
    normal: wp.vec3  # world direction of the local +y axis at t1 (a plane's normal)
    bound: float  # radius of a ball about the origin holding the shape (a plane: 0, unused)
    plane: int  # 1: half-space test along ``normal``
    sweep: float  # |c(t1) - c(t0)|, m (0 for a static obstacle)
    turn: float  # 2 sin(theta / 2), theta the rotation over the step (0 for a static obstacle)
    shrink: float  # 1 / (1 - turn) when turn < 1/2 (the far test's squared shortcut), else 0
    fresh: int  # 0: this step does not start where the last apply ended (moving-mesh cache)
    fast: int  # FAST_SPHERE / FAST_PLANE: a static sphere (origin, bound = radius) or plane
    #            (origin, normal) handled in the world frame; 0: the general local-frame path
    friction: float  # mu_T (copied here so the world-frame paths need nothing else)
    restitution: float  # mu_N


@wp.func
def step_reach(T0: wp.transform, T1: wp.transform, bound: float, kind: int, moving: int,
               fresh: int, friction: float, restitution: float):
    """The `ObstacleReach` of an obstacle moving from pose ``T0`` to ``T1`` over a step. The
    bounds are rounded up (relative 1e-5 plus 1e-7 m / rad) to cover float32 rounding; a static
    obstacle (``moving == 0``) gets exact zeros, which the far test treats as the cheap case."""
    r = ObstacleReach()
    r.origin = wp.transform_get_translation(T1)
    r.normal = wp.transform_vector(T1, wp.vec3(0.0, 1.0, 0.0))
    r.bound = bound
    r.plane = int(0)
    if kind == KIND_PLANE:
        r.plane = 1
    r.friction = friction
    r.restitution = restitution
    r.sweep = 0.0
    r.turn = 0.0
    r.shrink = 1.0
    r.fresh = fresh
    r.fast = FAST_NONE
    if moving != 0:
        r.sweep = wp.length(r.origin - wp.transform_get_translation(T0)) * 1.00001 + 1.0e-7
        qr = wp.mul(wp.transform_get_rotation(T1), wp.quat_inverse(wp.transform_get_rotation(T0)))
        r.turn = 2.0 * wp.length(wp.vec3(qr[0], qr[1], qr[2])) * 1.00001 + 1.0e-7
        r.shrink = 0.0
        if r.turn < 0.5:
            r.shrink = 1.0 / (1.0 - r.turn) * 1.00001
    else:
        r.fresh = 1  # a static obstacle's cache never goes stale
        if kind == KIND_SPHERE:
            r.fast = FAST_SPHERE
        elif kind == KIND_PLANE:
            r.fast = FAST_PLANE
    return r


@wp.kernel
def obstacle_poses_kernel(
    obstacles: wp.array(dtype=ObstacleData),
    key_times: wp.array(dtype=wp.float64),
    key_offsets: wp.array(dtype=wp.vec3),
    key_rotations: wp.array(dtype=wp.quat),
    time: wp.array(dtype=wp.float64),
    clock: wp.array(dtype=wp.float64),
    dt: float,
    advance_clock: int,
    poses: wp.array(dtype=wp.transform),
    reach: wp.array(dtype=ObstacleReach),
    last_t1: wp.array(dtype=wp.float64),
    still: wp.array(dtype=int),
    steady: wp.array(dtype=int),
):
    """Poses of every obstacle at the start and end of the step, once per step (one thread per
    obstacle): ``poses[5k + 0..4] = T(t0), T(t1), T(t0)^-1, T(t1)^-1`` and the world direction
    of the local +y axis at t1 (a plane's normal) as the translation of the fifth; ``reach[k]``
    for the far test. ``advance_clock`` (``apply``) also records the step's end time, so the next
    ``apply`` knows whether it starts where this one ended (``reach[k].fresh``). ``still[0]``
    (set to 1 before the launch) is cleared when some obstacle's pose differs between the
    step's start and end: an obstacle that stands still this step does no work on the cloth.
    ``steady[0]`` (set to 1 before the launch when the obstacles have a `steady_frame`) is
    cleared when some moving obstacle is not yet past its ramp at the step's start: then the
    step does not run in that frame's steady motion."""
    k = wp.tid()
    ob = obstacles[k]
    t0 = time[0]
    t1 = t0 + wp.float64(dt)
    if advance_clock != 0 and k == 0:
        clock[0] = t1  # the next step's start time, for project_positions without a time
    T0 = obstacle_pose(ob, key_times, key_offsets, key_rotations, t0)
    T1 = obstacle_pose(ob, key_times, key_offsets, key_rotations, t1)
    poses[5 * k + 0] = T0
    poses[5 * k + 1] = T1
    p0 = wp.transform_get_translation(T0)
    p1 = wp.transform_get_translation(T1)
    q0 = wp.transform_get_rotation(T0)
    q1 = wp.transform_get_rotation(T1)
    dq = wp.vec4(q1[0] - q0[0], q1[1] - q0[1], q1[2] - q0[2], q1[3] - q0[3])
    if wp.length_sq(p1 - p0) + wp.length_sq(dq) > 0.0:
        still[0] = 0
    if ob.moving != 0 and (ob.key_count > 0 or t0 < ob.start + ob.ramp):
        steady[0] = 0
    poses[5 * k + 2] = wp.transform_inverse(T0)
    poses[5 * k + 3] = wp.transform_inverse(T1)
    poses[5 * k + 4] = wp.transform(wp.transform_vector(T1, wp.vec3(0.0, 1.0, 0.0)), wp.quat_identity())
    fresh = int(0)
    if last_t1[k] == t0:
        fresh = 1
    reach[k] = step_reach(T0, T1, ob.bound, ob.kind, ob.moving, fresh, ob.friction,
                          ob.restitution)
    if advance_clock != 0:
        last_t1[k] = t1
