"""Kernels every solver shares: scripted pin targets and the device clock."""

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
