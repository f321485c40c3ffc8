"""Kernels every solver shares: scripted pin targets, the device clock, the energy seen from a
moving obstacles' steady frame."""

from __future__ import annotations

import warp as wp

from ..forces.springs import spring_energy64_kernel, spring_stretch64  # noqa: F401 (shared here)

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile


@wp.func
def pin_target(times: wp.array(dtype=wp.float64), keys: wp.array(dtype=wp.vec3), num_pins: int,
               p: int, t: wp.float64):
    """Position of pin ``p`` at time ``t``, linear between keyframes, clamped at both ends."""
    nk = times.shape[0]
    if t <= times[0]:
        return keys[p]
    if t >= times[nk - 1]:
        return keys[(nk - 1) * num_pins + p]
    k = int(0)
    while k < nk - 2 and t >= times[k + 1]:
        k += 1
    s = float((t - times[k]) / (times[k + 1] - times[k]))
    return keys[k * num_pins + p] * (1.0 - s) + keys[(k + 1) * num_pins + p] * s


@wp.kernel
def move_pins_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    pins: wp.array(dtype=wp.int32),
    times: wp.array(dtype=wp.float64),
    keys: wp.array(dtype=wp.vec3),
    time: wp.array(dtype=wp.float64),
    dt: float,
):
    """Put every pin at its target at the END of the step and give it the matching velocity."""
    p = wp.tid()
    n = pins.shape[0]
    t0 = time[0]
    t1 = t0 + wp.float64(dt)
    a = pin_target(times, keys, n, p, t0)
    b = pin_target(times, keys, n, p, t1)
    i = pins[p]
    x[i] = b
    v[i] = (b - a) / dt


@wp.kernel
def advance_time_kernel(time: wp.array(dtype=wp.float64), dt: float):
    time[0] = time[0] + wp.float64(dt)


@wp.kernel
def to_float64_kernel(src: wp.array(dtype=float), dst: wp.array(dtype=wp.float64)):
    """``dst[0] += src[0]`` (a float32 energy into a float64 sum)."""
    dst[0] = dst[0] + wp.float64(src[0])


@wp.func
def frame_kinetic(half_mass: float, v: wp.vec3, x: wp.vec3, frame_u: wp.vec3, frame_w: wp.vec3,
                  frame_c: wp.vec3):
    """A vertex's kinetic energy seen from a frame moving at ``frame_u`` and turning at
    ``frame_w`` about ``frame_c``, less the centrifugal potential: ``1/2 m |v - u - w x r|^2 -
    1/2 m |w x r|^2`` (``r = x - c``; `motion.steady_frame`, where steadily moving obstacles do
    no work), and the size of its terms, ``1/2 m (|v - u - w x r|^2 + |w x r|^2)`` (their
    float32 rounding scale)."""
    rot = wp.cross(frame_w, x - frame_c)
    rel = v - frame_u - rot
    return (half_mass * (wp.dot(rel, rel) - wp.dot(rot, rot)),
            half_mass * (wp.dot(rel, rel) + wp.dot(rot, rot)))


def steady_frame_args(contact, empty):
    """``(flag, u, w, c)`` for the kernels measuring in the moving obstacles' steady frame
    (`frame_kinetic`): the device flag 'this step runs in it' (`ObstacleContact.steady`) and
    the frame (`motion.steady_frame`); a flag that stays 0 (and zeros) when the moving obstacles
    have no such frame, ``empty`` (an empty int array: the world frame) when none moves."""
    zero = wp.vec3(0.0, 0.0, 0.0)
    if contact is not None and contact.moving:
        if contact.frame is None:
            return contact.steady, zero, zero, zero
        u, w, c = contact.frame
        return contact.steady, wp.vec3(*u), wp.vec3(*w), wp.vec3(*c)
    return empty, zero, zero, zero


@wp.kernel
def after_begin_kernel(after: wp.array(dtype=wp.int32)):
    """`Solver._after_round`'s loop starts: one round, none run."""
    after[0] = 1
    after[1] = 0


@wp.kernel
def after_round_kernel(moved: wp.array(dtype=wp.int32), stalled: wp.array(dtype=wp.int32),
                       after: wp.array(dtype=wp.int32), rounds: int):
    """After a round: another while the limits' pass moved anything, did not stall (the limit
    counts and reports that step itself) and ``rounds`` allow; a step whose last allowed round
    still moved something is counted in ``after[2]`` (over all steps: the response came last,
    but the limits may be left broken)."""
    after[1] = after[1] + 1
    after[0] = wp.where(moved[0] != 0 and stalled[0] == 0 and after[1] < rounds, 1, 0)
    if moved[0] != 0 and stalled[0] == 0 and after[1] >= rounds:
        after[2] = after[2] + 1
