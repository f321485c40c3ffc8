"""Mass-spring forces per edge (``reference/physics.md`` section 2.1), one thread per spring.

    E_e = 1/2 k (|x_ij| - L)^2,   f_i = -k (|x_ij| - L) x_ij / |x_ij|,   f_j = -f_i

with an optional dashpot along the spring, ``-c ((v_i - v_j) . d) d`` (explicit solver only).
The Hessian block ``H_e`` (used by the implicit solver) is in `spring_hessian_block`.
"""

from __future__ import annotations

import warp as wp

from ..util import launch

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile


@wp.func
def spring_force(xi: wp.vec3, xj: wp.vec3, k: float, rest: float):
    """Force on vertex i of the spring (i, j); the force on j is its negative."""
    d = xi - xj
    l = wp.length(d)
    if l < 1.0e-12:
        return wp.vec3(0.0)
    return -k * (l - rest) / l * d


@wp.func
def spring_hessian_block(xi: wp.vec3, xj: wp.vec3, k: float, rest: float, definite: int):
    """The notes' ``H_e = k d d^T/|d|^2 + k (1 - L/|d|)(I - d d^T/|d|^2)`` with ``d = x_i - x_j``.

    With ``definite != 0`` the second term is dropped when the spring is compressed
    (``|d| < L``), which makes ``H_e`` positive semi-definite (physics.md 2.1, L990-994).
    """
    d = xi - xj
    l = wp.length(d)
    if l < 1.0e-12:
        return k * wp.identity(n=3, dtype=float)
    P = wp.outer(d, d) / (l * l)
    c = 1.0 - rest / l
    if definite != 0 and c < 0.0:
        c = 0.0
    return k * P + k * c * (wp.identity(n=3, dtype=float) - P)


@wp.kernel
def spring_forces_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    springs: wp.array2d(dtype=wp.int32),
    rest: wp.array(dtype=float),
    stiffness: wp.array(dtype=float),
    damping: float,
    f: wp.array(dtype=wp.vec3),
):
    e = wp.tid()
    i = springs[e, 0]
    j = springs[e, 1]
    fi = spring_force(x[i], x[j], stiffness[e], rest[e])
    if damping > 0.0:
        d = x[i] - x[j]
        l = wp.length(d)
        if l > 1.0e-12:
            n = d / l
            fi = fi - damping * wp.dot(v[i] - v[j], n) * n
    wp.atomic_add(f, i, fi)
    wp.atomic_sub(f, j, fi)


@wp.kernel
def spring_energy_kernel(
    x: wp.array(dtype=wp.vec3),
    springs: wp.array2d(dtype=wp.int32),
    rest: wp.array(dtype=float),
    stiffness: wp.array(dtype=float),
    out: wp.array(dtype=float),
):
    e = wp.tid()
    s = wp.length(x[springs[e, 0]] - x[springs[e, 1]]) - rest[e]
    wp.atomic_add(out, 0, 0.5 * stiffness[e] * s * s)


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



class SpringForce:
    """All springs of a model (stretch, shear, bending springs share one kernel)."""

    name = "springs"

    def __init__(self, model):
        self.model = model

    def eval(self, x, v, f, time=None, damping: float | None = None):
        m = self.model
        c = m.spring_damping if damping is None else damping
        launch(
            spring_forces_kernel,
            m.num_springs,
            [x, v, m.spring_indices, m.spring_rest_length, m.spring_k, float(c), f],
            device=m.device,
        )

    def energy64(self, x, out):
        """The springs' energy added to ``out[0]`` (a float64 array) in float64, from the
        float32 positions as stored (`spring_stretch64`): `diagnostics.Meter` measures with it.
        In float32 the length rounds by about 1e-7 L: a 32 x 32 sheet at k = 1e9 N/m measured
        1.7e-5 J off (of 1.5e-4 J), more than a frame's energy change there."""
        m = self.model
        launch(spring_energy64_kernel, m.num_springs,
               [x, m.spring_indices, m.spring_rest_length, m.spring_k, out], device=m.device)

    def energy(self, x, out):
        m = self.model
        launch(
            spring_energy_kernel,
            m.num_springs,
            [x, m.spring_indices, m.spring_rest_length, m.spring_k, out],
            device=m.device,
        )
