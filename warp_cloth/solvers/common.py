"""Kernels every solver shares: scripted pin targets and the device clock."""

from __future__ import annotations

import warp as wp

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


@wp.func
def spring_stretch64(xi: wp.vec3, xj: wp.vec3, rest: float):
    """``|x_i - x_j| - L`` in float64 from the float32 positions (exact for the positions as
    stored). In float32 the length alone rounds by about 1e-7 L: at k = 1e6 N/m and L = 3 cm
    that is a spurious force of 2e-3 N, a 32 x 32 sheet vertex's weight, and at 1e9 N/m a
    thousand times it, so Newton's gradient and the line search's energies were noise."""
    return wp.length(wp.vec3d(xi) - wp.vec3d(xj)) - wp.float64(rest)


@wp.kernel
def spring_energy64_kernel(x: wp.array(dtype=wp.vec3), springs: wp.array2d(dtype=wp.int32),
                           rest: wp.array(dtype=float), stiffness: wp.array(dtype=float),
                           out: wp.array(dtype=wp.float64)):
    """``sum_e k_e / 2 (|x_i - x_j| - L_e)^2`` added to ``out[0]`` in float64 (the energy checks
    of implicit Euler and projective dynamics: float32 sums round at their tolerance)."""
    e = wp.tid()
    s = spring_stretch64(x[springs[e, 0]], x[springs[e, 1]], rest[e])
    wp.atomic_add(out, 0, wp.float64(0.5) * wp.float64(stiffness[e]) * s * s)


@wp.kernel
def to_float64_kernel(src: wp.array(dtype=float), dst: wp.array(dtype=wp.float64)):
    """``dst[0] += src[0]`` (a float32 energy into a float64 sum)."""
    dst[0] = dst[0] + wp.float64(src[0])
