"""Projective dynamics for the mass-spring cloth: implicit Euler by local/global iterations.

One step minimises the implicit-Euler objective (``physics.md`` 2.3, L939-941)

    F(x) = 1/(2 dt^2) ||x - y||_M^2 + E(x),     y = x_n + dt v_n + dt^2 g

by alternating, ``iterations`` times (Liu et al. 2013, "Fast Simulation of Mass-Spring
Systems"; Bouaziz et al. 2014, "Projective Dynamics"; the notes' L1443-1500 and 001:L72-108):

- **local step**, one thread per spring: project the spring onto its rest length,
  ``d_e = L_e (x_i - x_j) / |x_i - x_j|``, and scatter the projective force
  ``f_i = -k_e ((x_i - x_j) - d_e)`` (= the mass-spring force, L1456; T32) with atomics; the same
  thread adds ``1/2 k_e (|x_ij| - L_e)^2`` to the objective;
- **global step**: solve the constant system

      (M/dt^2 + L + Q) dx = M/dt^2 (y - x) + f(x)                  (GAMES103 form, L1484-1500)

  for the increment ``dx`` with ``L = sum_e k_e A_e A_e^T (x) I_3`` the stiffness-weighted graph
  Laplacian (T33) and ``Q`` the constant Hessian of quadratic bending (Bergou et al. 2006), then
  ``x <- x + dx``. With ``dx`` started at 0 this is Liu's ``(M + h^2 L) x = M y + h^2 J d`` solved
  warm-started from the current iterate (the two forms agree exactly, T34; Liu's is ours times
  ``h^2``).

The global solve uses the shared inner solvers of `warp_cloth.solvers.linear` (block Jacobi,
Chebyshev-Jacobi after Wang 2015 with the spectral radius measured by
`linear.estimate_spectral_radius` and exposed as ``solver.rho``, preconditioned CG) on a
gather-form operator (`PDSystemOperator`, one thread per vertex, no atomics); CG preconditioned
by the banded float64 Cholesky factor of the constant scalar matrix (``linear="cholesky"``,
`band.ScalarBandFactor`: factored once per ``dt``, exact in one iteration while no contact term
is in the matrix, the default on the CPU without a collision stage); or, with ``direct=True``,
a dense inverse of the constant matrix precomputed on the host (small meshes).

Measured (`warp-cloth bench pd --quick`, the 64 x 32 sheet, 2,145 vertices, band 66 vertices,
2026-12-07): the factor's step is the dense inverse's to the printed digits (objective 0.03779
J after 10 iterations from the moving state, Chebyshev-20's 0.1023, CG-20's 0.06458) at 0.47 ms
an iteration against Chebyshev-20's 1.14 and CG-20's 1.32 (the dense host inverse: 4.0). With
a collision stage its contact terms (self-contacts' pairs above all) are not in the factor and
CG needs more iterations than the band saves: 4 iterations of it run the table, drape and fold
in the time of CG-20, with more contact-short steps on the fold (5 against 0 in 120 frames), so
CG-20 stays the default there, and the factor's one exact iteration runs in the iterations
whose local step put no contact block in the matrix (`_global_solve`, a device flag). Scene
runs at the defaults (120 frames, the code before and after run at the same time, ms a
frame): hanging (self-collision on, seldom in contact) 39.7 -> 26.2 (max strain 3.69 -> 3.53
%), twist 173.5 -> 159.0, drape, table, spin, mesh, fold, stack within the noise (they are in
contact from their first frames or soon after).

Pins, scripted ones included, are eliminated: their rows of ``dx`` stay 0 and they keep the
end-of-step targets `Solver.step` put them at (``physics.md`` 2.15, 001:L119-140). Velocities are
``v = (x_{n+1} - x_n)/dt * exp(-damping dt)``.

Other force terms of the model are explicit forces evaluated at the current iterate in every
outer iteration (so they are implicit at convergence): dihedral bending, and wind with the
start-of-step velocity. Their Hessians are not in the matrix, which is constant for the run.

Convergence (measured by ``warp-cloth bench pd``): PD is a descent method on F (T36: the
objective decreases monotonically when the global solve is exact), fast in the first iterations
and slow later (T35, L1515-1518), because its matrix ignores the Hessian of the projections. On a
small soft cloth (tests: 5 x 5 vertices, 20 N/m) exact-solve PD is 2e-3 m from the converged
Newton state after 10 iterations and 1e-6 m after 200. On the real-cloth hanging sheet (64 x 32
cells, 1000 N/m, 0.15 kg/m^2, dt = 1/60 s) PD hardly moves towards the Newton state: from a moving
state (frame 30) the inertial guess is 1.64 % of the cloth size away, 10 iterations of
Chebyshev-20 leave 1.64 %, 50 leave 1.51 %, 20 exact (direct) iterations 1.40 %, while Newton
needs about 20 iterations to get to 0.33 %. Stiff springs make ``L`` dominate ``M/dt^2`` by
about 1e4, and PD's matrix charges the slack transverse directions the full ``k``. On the default
32 x 32 hanging scene with one step per frame, 10 iterations per step give a max edge strain of
5.4 % (direct), 7.6 % (Chebyshev-100) and 25 % (Chebyshev-20): an under-converged PD step is
softer than the material. Smaller steps fix that more cheaply than more iterations (M/dt^2 grows
as 1/dt^2 and PD converges faster): 3 steps per frame of 10 x Chebyshev-20 gave 4.9 % at 19.8
ms/frame there, against 7.6 % at 30 ms for 1 step of 10 x Chebyshev-100 (same run, 2 s of the
default hanging scene). With the banded factor's exact global steps (the default without a
collision stage since 2026-12-07; the same scene without self-collision, 2 s, one run): 3 steps
3.53 % at 5.5 ms/frame (Chebyshev-20 4.89 % at 19.1, Chebyshev-100 3.57 % at 84.2), 1 step
5.36 % at 1.8 ms/frame (Chebyshev-100 7.62 % at 35.6).

Limitations: the matrix is built for one ``dt`` (rebuilt on the host when ``dt`` changes);
Chebyshev needs ``rho`` below the true spectral radius bound (an overestimate diverges; the
linear solver falls back to Jacobi only when residual checks are on); spring dashpots
(``model.spring_damping``) are not modelled (explicit solver only); the step is an approximation
of implicit Euler, as good as the number of iterations.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..util import count_since, launch, positive_finite
from .base import Solver
from .common import frame_kinetic, spring_energy64_kernel, steady_frame_args, to_float64_kernel
from .contact_coupling import DEFAULT_CONTACT_STIFFNESS, ContactCoupling
from .linear import (LINEAR_SOLVERS, SpringSystemOperator, csr_arrays, estimate_spectral_radius,
                     make_linear_solver, scalar_csr)
from .smoothing import VertexSmoother, check_sweeps, end_velocity_kernel, offset_kernel

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile

__all__ = ["ProjectiveDynamics", "PDSystemOperator"]

#: the global step's inner solvers: the shared ones and ``"cholesky"`` (CG preconditioned by the
#: banded factor of the constant matrix, `band.ScalarBandFactor`)
PD_LINEAR = (*LINEAR_SOLVERS, "cholesky")
#: the widest band (vertices) of the constant matrix for which the default inner solver without
#: a collision stage is ``"cholesky"`` on the CPU: a factor application costs about ``6 n b``
#: multiply-adds, a Chebyshev-20 solve about ``20 x`` a product over the rows; at b = 200
#: (a 100 x 100 grid with quadratic bending) the factorisation, ``n b^2 / 2``, is ~2e8
CHOLESKY_MAX_WIDTH = 200
#: ... and the most band entries it may take (float64; the factor keeps two copies: 64 MB
#: at this bound, e.g. 20,000 vertices 200 wide)
CHOLESKY_MAX_ENTRIES = 1 << 22
#: ... and the largest mesh on which that choice also tries reverse Cuthill-McKee's order (a
#: host breadth-first search: 0.5-0.8 s at 16,641 vertices, 3.7 s at 66,049, where a square
#: sheet's band is past the bound anyway); larger meshes are taken in their own order
RCM_MAX_VERTICES = 20000


# ----------------------------------------------------------------------------------- kernels
#: the energy rise (a fraction of ``M |g|`` times 1 m) above which PD's contact iterations go on
#: (`ProjectiveDynamics`, ``contact_iterations``). At 1e-5 (the implicit solver's guard) PD's
#: drape, table and mesh rose by up to 3.0e-5, 4.7e-5 and 3.3e-5 J in a frame, its iterations
#: stopping at the tolerance each step; at 1e-6 none of them rises, in the same time (`warp-cloth
#: bench scenes`, 2026-11-25; on the default hanging sheet 33 -> 36 contact iterations in 60
#: frames, and at k = 1e9 N/m, where PD gains energy anyway, no more than before)
ENERGY_EPS = 1.0e-6
#: ... and the rise (same unit) above which a step that used all its contact iterations counts
#: as gaining energy (``energy_gain_steps``, reported): the former ``ENERGY_EPS``. At 1e-6 a
#: 12 x 12 sheet landing on the torus counted 4 steps for rises under 1.5e-5 J
ENERGY_REPORT = 1.0e-5
#: ... and both at least this fraction of the step's starting kinetic energy: float32 velocities
#: round it by about 1e-7 of itself, which the 1e-9 J floor of a cloth without gravity did not
#: cover (a sheet translating at 1.1 m/s beside a plane without gravity: 378 contact
#: iterations in 60 steps and 16 steps reported as gaining energy, none with this floor)
ENERGY_KE_REL = wp.constant(1.0e-6)


@wp.kernel
def pd_predict_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    gravity: wp.vec3,
    dt: float,
    x0: wp.array(dtype=wp.vec3),
    y: wp.array(dtype=wp.vec3),
):
    """x0 = x; y = x + dt v + dt^2 g (free vertices); the first iterate is y."""
    i = wp.tid()
    xi = x[i]
    x0[i] = xi
    yi = xi
    if inv_mass[i] > 0.0:
        yi = xi + dt * v[i] + (dt * dt) * gravity
    y[i] = yi
    x[i] = yi


@wp.kernel
def pd_local_kernel(
    x: wp.array(dtype=wp.vec3),
    springs: wp.array2d(dtype=wp.int32),
    rest: wp.array(dtype=float),
    stiffness: wp.array(dtype=float),
    d: wp.array(dtype=wp.vec3),
    f: wp.array(dtype=wp.vec3),
    objective: wp.array(dtype=wp.float64),
    slot: int,
):
    """Local step: d_e = L_e x_ij/|x_ij|; f_i += -k (x_ij - d_e), f_j -= ...; F += k/2 |x_ij - d_e|^2."""
    e = wp.tid()
    i = springs[e, 0]
    j = springs[e, 1]
    xij = x[i] - x[j]
    l = wp.length(xij)
    de = xij  # degenerate spring: no direction to project on, no force
    if l > 1.0e-12:
        de = (rest[e] / l) * xij
    d[e] = de
    k = stiffness[e]
    s = xij - de
    fi = -k * s
    wp.atomic_add(f, i, fi)
    wp.atomic_sub(f, j, fi)
    wp.atomic_add(objective, slot, wp.float64(0.5 * k * wp.dot(s, s)))


@wp.kernel
def pd_rhs_kernel(
    x: wp.array(dtype=wp.vec3),
    y: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    free: wp.array(dtype=float),
    inv_dt2: float,
    f: wp.array(dtype=wp.vec3),
    b: wp.array(dtype=wp.vec3),
    dx: wp.array(dtype=wp.vec3),
    objective: wp.array(dtype=wp.float64),
    gradient: wp.array(dtype=wp.float64),
    slot: int,
):
    """b = -grad F = M/dt^2 (y - x) + f (free vertices, else 0); F += |x - y|_M^2/(2 dt^2);
    |grad F|^2 into ``gradient``; clears f and the increment dx for the next use."""
    i = wp.tid()
    bi = wp.vec3(0.0)
    if free[i] > 0.0:
        r = x[i] - y[i]
        mi = mass[i] * inv_dt2
        bi = f[i] - mi * r
        wp.atomic_add(objective, slot, wp.float64(0.5 * mi * wp.dot(r, r)))
        wp.atomic_add(gradient, slot, wp.float64(wp.dot(bi, bi)))
    b[i] = bi
    f[i] = wp.vec3(0.0)
    dx[i] = wp.vec3(0.0)


@wp.kernel
def pd_residual_kernel(b: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float), dt2: float,
                       res: wp.array(dtype=float)):
    """The implicit-Euler residual ``max_i dt^2 |b_i|_inf / m_i`` (metres) into ``res[0]``."""
    i = wp.tid()
    w = inv_mass[i]
    if w > 0.0:
        r = (dt2 * w) * b[i]
        wp.atomic_max(res, 0, wp.max(wp.abs(r[0]), wp.max(wp.abs(r[1]), wp.abs(r[2]))))


@wp.kernel
def pd_converged_kernel(res: wp.array(dtype=float), tolerance: float,
                        unconverged: wp.array(dtype=wp.int32)):
    """Count the step as unconverged (``unconverged[0]``) when ``res[0] > tolerance``; keep the last
    residual in ``res[1]`` and the last unconverged one in ``res[2]``; clear ``res[0]``."""
    r = res[0]
    res[1] = r
    if r > tolerance:
        unconverged[0] = unconverged[0] + 1
        res[2] = r
    res[0] = 0.0


@wp.kernel
def pd_more_kernel(res: wp.array(dtype=float), threshold: float, limit: int,
                   flag: wp.array(dtype=wp.int32), counters: wp.array(dtype=wp.int32),
                   energy: wp.array(dtype=wp.float64), eps: float, report: float, guard: int,
                   still: wp.array(dtype=int), steady: wp.array(dtype=int)):
    """After an evaluation of the contact iterations: another one runs (``flag[0] = 1``) while
    the residual ``res[0]`` is above ``threshold``, or (``guard``) the energy at the iterate
    ``energy[1]`` exceeds the step's start ``energy[0]`` by more than ``eps``, and fewer than
    ``limit`` ran this step (``counters[0]``: extra iterations this step, ``counters[1]``: over
    all steps, ``counters[2]``: steps that stopped at ``limit`` still above the residual,
    ``counters[3]``: steps that stopped there still gaining more than ``report``); clears
    ``res[0]``. With moving obstacles, the energy counts only in steps where none moved
    (``still[0]``) or where they move in their steady motion (``steady[0]``: the energies are
    then the frame's that moves with them, `pd_energy_kernel`)."""
    r = res[0]
    res[0] = 0.0
    # the tolerances, at least `ENERGY_KE_REL` of the start's kinetic terms (``energy[2]``)
    floor = wp.float64(ENERGY_KE_REL) * energy[2]
    eps_k = wp.max(wp.float64(eps), floor)
    report_k = wp.max(wp.float64(report), floor)
    gain = guard != 0 and energy[1] - energy[0] > eps_k
    if still.shape[0] > 0:
        if still[0] == 0 and steady[0] == 0:
            gain = False
    more = int(0)
    if r > threshold or gain:
        if counters[0] < limit:
            more = 1
            counters[0] = counters[0] + 1
            counters[1] = counters[1] + 1
        else:
            if r > threshold:
                counters[2] = counters[2] + 1
            if gain and energy[1] - energy[0] > report_k:
                counters[3] = counters[3] + 1
    flag[0] = more


@wp.kernel
def pd_energy_kernel(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
                     mass: wp.array(dtype=float), inv_mass: wp.array(dtype=float),
                     gravity: wp.vec3, out: wp.array(dtype=wp.float64),
                     frame_u: wp.vec3, frame_w: wp.vec3, frame_c: wp.vec3,
                     steady: wp.array(dtype=int), ke_out: wp.array(dtype=wp.float64)):
    """Kinetic energy and gravity's potential of the free vertices into ``out[0]`` (float64);
    while ``steady[0]`` (the moving obstacles in their steady motion, `motion.steady_frame`)
    seen from the frame that moves with them: ``1/2 m |v - u - w x r|^2 - 1/2 m |w x r|^2``
    (``r = x - c``; the relative kinetic energy and the centrifugal potential), in which
    they do no work. With a ``ke_out`` array, the size of the kinetic terms (their float32
    rounding scale) into ``ke_out[0]``."""
    i = wp.tid()
    if inv_mass[i] > 0.0:
        vi = v[i]
        ke = 0.5 * mass[i] * wp.dot(vi, vi)
        scale = ke
        if steady.shape[0] > 0:
            if steady[0] != 0:
                ke, scale = frame_kinetic(0.5 * mass[i], vi, x[i], frame_u, frame_w, frame_c)
        wp.atomic_add(out, 0, wp.float64(ke - mass[i] * wp.dot(gravity, x[i])))
        if ke_out.shape[0] > 0:
            wp.atomic_add(ke_out, 0, wp.float64(scale))


@wp.kernel
def pd_update_kernel(
    x: wp.array(dtype=wp.vec3),
    dx: wp.array(dtype=wp.vec3),
    x0: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    decay: float,
    inv_dt: float,
    final: int,
    omega: float,
    x_prev: wp.array(dtype=wp.vec3),
):
    """x += dx, blended with the previous iterate when omega != 1 (Wang 2015:
    x <- omega (x + dx) + (1 - omega) x_prev, x_prev <- x); on the last iteration also
    v = (x - x0)/dt * decay (free vertices)."""
    i = wp.tid()
    xo = x[i]
    xi = xo + dx[i]
    if omega != 1.0:
        xi = omega * xi + (1.0 - omega) * x_prev[i]
    x_prev[i] = xo
    x[i] = xi
    if final != 0 and inv_mass[i] > 0.0:
        v[i] = (xi - x0[i]) * (inv_dt * decay)


@wp.kernel
def pd_matvec_kernel(
    x: wp.array(dtype=wp.vec3),
    diag: wp.array(dtype=float),
    offsets: wp.array(dtype=wp.int32),
    neighbors: wp.array(dtype=wp.int32),
    weights: wp.array(dtype=float),
    out: wp.array(dtype=wp.vec3),
):
    """out_i = (m_i/dt^2 + sum_j k_ij) x_i - sum_j k_ij x_j: the Laplacian row gathered (no atomics)."""
    i = wp.tid()
    acc = diag[i] * x[i]
    for p in range(offsets[i], offsets[i + 1]):
        acc = acc - weights[p] * x[neighbors[p]]
    out[i] = acc


@wp.kernel
def pd_matvec_vb_kernel(
    x: wp.array(dtype=wp.vec3),
    diag: wp.array(dtype=float),
    offsets: wp.array(dtype=wp.int32),
    neighbors: wp.array(dtype=wp.int32),
    weights: wp.array(dtype=float),
    vblock: wp.array(dtype=wp.mat33),
    out: wp.array(dtype=wp.vec3),
):
    """`pd_matvec_kernel` plus a per-vertex block (the contact constraints' matrix)."""
    i = wp.tid()
    xi = x[i]
    acc = diag[i] * xi + vblock[i] * xi
    for p in range(offsets[i], offsets[i + 1]):
        acc = acc - weights[p] * x[neighbors[p]]
    out[i] = acc


@wp.kernel
def pd_jacobi_sweep_kernel(
    x: wp.array(dtype=wp.vec3),
    diag: wp.array(dtype=float),
    offsets: wp.array(dtype=wp.int32),
    neighbors: wp.array(dtype=wp.int32),
    weights: wp.array(dtype=float),
    b: wp.array(dtype=wp.vec3),
    dinv: wp.array(dtype=wp.mat33),
    free: wp.array(dtype=float),
    alpha: float,
    sums: wp.array(dtype=wp.float64),
    slot: int,
    x_out: wp.array(dtype=wp.vec3),
):
    """One relaxed Jacobi sweep ``x_out = x + alpha D^-1 (b - A x)`` with ``|r|^2`` summed into
    ``sums[slot]`` (not summed when ``slot < 0``): `pd_matvec_kernel` and `linear._jacobi_update_kernel` (omega = 1) fused, the
    same arithmetic in the same order, without the ``A x`` array between them."""
    i = wp.tid()
    xi = x[i]
    acc = diag[i] * xi
    for p in range(offsets[i], offsets[i + 1]):
        acc = acc - weights[p] * x[neighbors[p]]
    r = (b[i] - acc) * free[i]
    if slot >= 0:
        wp.atomic_add(sums, slot, wp.float64(wp.dot(r, r)))
    x_out[i] = xi + alpha * (dinv[i] * r)


@wp.kernel
def no_blocks_kernel(vblock: wp.array(dtype=wp.mat33), n: int, flag: wp.array(dtype=wp.int32)):
    """``flag[0]`` = 1 when every ``vblock`` is zero (one thread: a scan of ``n`` blocks costs
    about what a launch does on the CPU, where alone it is used), else 0."""
    f = int(1)
    i = int(0)
    while i < n and f == 1:
        if wp.ddot(vblock[i], vblock[i]) > 0.0:
            f = 0
        i += 1
    flag[0] = wp.int32(f)


@wp.kernel
def pd_diag_kernel(diag: wp.array(dtype=float), blocks: wp.array(dtype=wp.mat33)):
    i = wp.tid()
    blocks[i] = diag[i] * wp.identity(n=3, dtype=float)


@wp.kernel
def pd_diag_invert_kernel(blocks: wp.array(dtype=wp.mat33), free: wp.array(dtype=float),
                          dinv: wp.array(dtype=wp.mat33)):
    i = wp.tid()
    if free[i] > 0.0:
        dinv[i] = wp.inverse(blocks[i])
    else:
        dinv[i] = wp.mat33(0.0)


# ----------------------------------------------------------------------------------- operator
class PDSystemOperator:
    """The constant projective-dynamics matrix ``A = M/dt^2 + L (x) I_3 (+ extra terms)``.

    Same interface as `linear.SpringSystemOperator` (``n``, ``device``, ``matvec``, ``diag_inv``,
    ``free``), so the shared Jacobi / Chebyshev / CG solvers run on it, but the Laplacian is
    applied in gather form: one thread per vertex walks its CSR row of spring neighbours with
    scalar weights ``k_e`` (one launch, no atomics, no 3x3 blocks). ``extra`` terms (quadratic
    bending) add ``matvec_add(x, out)`` and ``add_diagonal(diag)``. Pinned vertices
    (``inv_mass == 0``) are eliminated through ``free`` and zero ``diag_inv`` blocks.

    Args:
        model: the `ClothModel`.
        mass_scale: ``1/dt^2`` in 1/s^2.
        extra: constant-Hessian force terms.
    """

    def __init__(self, model, mass_scale: float, extra=()):
        self.model = model
        self.n = n = model.num_vertices
        self.device = d = model.device
        # terms with a constant scalar Hessian (quadratic bending: ``scalar_entries``) are folded
        # into the CSR rows and the diagonal, so a matrix product is one gather launch (on the
        # 2,500-vertex twist the separate per-quad product cost more than the spring rows);
        # the rest (contact) stay ``extra`` terms with their own products
        self.folded = [t for t in extra if hasattr(t, "scalar_entries")]
        self.extra = [t for t in extra if not hasattr(t, "scalar_entries")]
        pairs = model.spring_pairs
        k = model.spring_stiffness
        rows = [pairs[:, 0], pairs[:, 1]]
        cols = [pairs[:, 1], pairs[:, 0]]
        w = [k, k]
        const_diag = np.zeros(n)
        if len(pairs):  # each spring adds k to both of its rows
            const_diag = (np.bincount(pairs[:, 0], weights=k, minlength=n)
                          + np.bincount(pairs[:, 1], weights=k, minlength=n))
        for t in self.folded:
            r, c, q = t.scalar_entries()
            off = r != c
            # out_i = diag_i x_i - sum_j w_ij x_j: an off-diagonal entry q_ij is a weight -q_ij
            rows.append(r[off])
            cols.append(c[off])
            w.append(-q[off])
            const_diag = const_diag + np.bincount(r[~off], weights=q[~off], minlength=n)
        #: the CSR rows on the host (float64): springs and folded constant terms
        self.csr_host = scalar_csr(n, rows, cols, w)
        self.offsets, self.neighbors, self.weights = csr_arrays(*self.csr_host, d)
        #: the constant part of the diagonal (springs' Laplacian, folded terms' diagonal)
        self.laplacian_diag = const_diag
        self.diag = wp.zeros(n, dtype=wp.float32, device=d)
        self.blocks = wp.zeros(n, dtype=wp.mat33, device=d)
        self.diag_inv = wp.zeros(n, dtype=wp.mat33, device=d)
        self.free = wp.array((model.inverse_masses > 0).astype(np.float32), dtype=wp.float32, device=d)
        #: None, or a mat33 per vertex added to A (contact; its owner updates ``diag_inv``)
        self.vertex_blocks = None
        self.mass_scale = None
        self.update(mass_scale)

    def update(self, mass_scale: float):
        """Rebuild the diagonal for a new ``1/dt^2`` (host work, once per ``dt``)."""
        self.mass_scale = float(mass_scale)
        self.diag.assign((self.mass_scale * self.model.masses + self.laplacian_diag).astype(np.float32))
        launch(pd_diag_kernel, self.n, [self.diag, self.blocks], device=self.device)
        for t in self.extra:
            t.add_diagonal(self.blocks)
        launch(pd_diag_invert_kernel, self.n, [self.blocks, self.free, self.diag_inv],
               device=self.device)

    def matvec(self, x, out):
        if self.vertex_blocks is not None:
            launch(pd_matvec_vb_kernel, self.n,
                   [x, self.diag, self.offsets, self.neighbors, self.weights,
                    self.vertex_blocks, out], device=self.device)
        else:
            launch(pd_matvec_kernel, self.n,
                   [x, self.diag, self.offsets, self.neighbors, self.weights, out],
                   device=self.device)
        for t in self.extra:
            t.matvec_add(x, out)

    def jacobi_sweep(self, x, x_out, b, alpha: float, sums, slot: int) -> bool:
        """``x_out = x + alpha D^-1 (b - A x)`` in one launch (`pd_jacobi_sweep_kernel`), the
        residual's squared norm added to ``sums[slot]`` (``slot < 0``: not computed). Returns False (nothing done) when extra
        terms or vertex blocks make the fused form unavailable."""
        if self.extra or self.vertex_blocks is not None:
            return False
        launch(pd_jacobi_sweep_kernel, self.n,
               [x, self.diag, self.offsets, self.neighbors, self.weights, b, self.diag_inv,
                self.free, float(alpha), sums, int(slot), x_out], device=self.device)
        return True

    def dense_scalar(self) -> np.ndarray:
        """The scalar (n x n) factor ``S`` of ``A = S (x) I_3`` in float64 (host; for ``direct``).

        Springs and masses are assembled on the host; each extra term is probed with unit
        vectors in the x component, and a `ValueError` is raised if it couples components
        (then ``A`` is not of the form ``S (x) I_3``)."""
        m = self.model
        n = self.n
        S = np.diag(self.mass_scale * m.masses + self.laplacian_diag)
        offsets, cols, wsum = self.csr_host
        rows = np.repeat(np.arange(n), np.diff(offsets))
        np.add.at(S, (rows, cols), -wsum)
        if self.extra:
            e = wp.zeros(n, dtype=wp.vec3, device=self.device)
            out = wp.zeros(n, dtype=wp.vec3, device=self.device)
            h = np.zeros((n, 3), dtype=np.float32)
            for c in range(n):
                h[:] = 0.0
                h[c, 0] = 1.0
                e.assign(h)
                out.zero_()
                for t in self.extra:
                    t.matvec_add(e, out)
                col = out.numpy().astype(np.float64)
                if np.abs(col[:, 1:]).max() > 1e-6 * max(np.abs(col[:, 0]).max(), 1e-30):
                    raise ValueError("direct=True needs extra terms whose Hessian is Q (x) I_3; "
                                     f"{type(self.extra[0]).__name__} couples x, y, z")
                S[:, c] += col[:, 0]
        return S


def _is_constant_hessian(term) -> bool:
    """Terms whose Hessian is constant enter the PD matrix (quadratic bending)."""
    if getattr(term, "constant_hessian", False):
        return True
    return type(term).__name__ == "QuadraticBending" and hasattr(term, "matvec_add")


# ----------------------------------------------------------------------------------- solver
class ProjectiveDynamics(Solver):
    """Projective dynamics (Liu et al. 2013; Bouaziz et al. 2014): ``solver.step(state, dt)``.

    Args:
        model: the `ClothModel`.
        iterations: outer local/global iterations per step (>= 1).
        linear: inner solver of the global step, ``"jacobi"``, ``"chebyshev"`` (Wang 2015),
            ``"cg"`` (block-Jacobi preconditioned) or ``"cholesky"`` (CG preconditioned by the
            banded float64 Cholesky factor of the constant matrix, `band.ScalarBandFactor`:
            exact in one iteration where no contact term is in the matrix), warm-started from
            the current iterate; ``None`` (default): ``"cg"`` when the solver has a collision
            stage, else ``"cholesky"`` on the CPU when the mesh's band is at most
            `CHOLESKY_MAX_WIDTH` vertices wide and holds at most `CHOLESKY_MAX_ENTRIES`
            entries, else ``"chebyshev"`` (`linear_name`).
        linear_iterations: inner iterations per global step (>= 1); ``None`` (default): 1 for
            ``"cholesky"`` without a collision stage (the exact solve), 4 with one (its contact
            terms are not in the factor), 20 for the others.
        linear_tolerance: relative residual at which the inner solve stops early; ``None`` (the
            default) runs exactly ``linear_iterations`` and reads nothing back (capturable).
        alpha: Jacobi relaxation of the ``jacobi`` and ``chebyshev`` inner solvers, in (0, 2].
        rho: Chebyshev's spectral radius of ``I - alpha D^-1 A`` in [0, 1); ``None`` measures it
            with `linear.estimate_spectral_radius` when the matrix is built (first step, host)
            and scales it by ``rho_safety``. Exposed as ``solver.rho`` after the first step.
        rho_safety: factor (0, 1] applied to the measured spectral radius (an overestimate
            diverges, an underestimate only accelerates less).
        delay: plain Jacobi iterations before Chebyshev acceleration starts.
        direct: solve the global step exactly with a dense inverse of the constant scalar matrix
            precomputed on the host in float64 (meshes up to ``direct_max_vertices``); one host
            round trip per iteration, so not capturable. ``linear`` is then unused.
        direct_max_vertices: refuse ``direct`` above this many vertices (memory ~ 8 n^2 bytes).
        contact_stiffness: ``kappa`` of the contact constraints, their weight over the inertia
            block ``m/dt^2`` (default 1e3; `warp_cloth.solvers.contact_coupling`).
        tolerance: metres, or None (default: PD runs a fixed count and claims no convergence).
            With a value, the implicit-Euler residual ``max_i dt^2 |grad F_i| / m_i`` at the
            start of the last outer iteration is measured on the device (``stats["residual"]``)
            and a step above it is counted (``stats["unconverged_steps"]``) and reported by
            `frame_end` (a warning with the frame from the scene runner). Capturable.
        contact_iterations: with a collision stage, up to this many more local/global
            iterations after ``iterations``, run while the implicit-Euler residual
            ``max_i dt^2 |grad F_i| / m_i`` is above ``contact_residual``, or while the step's
            energy (kinetic, gravity, springs, bending; float64 sums) is above its start by
            more than `ENERGY_EPS` ``M |g|`` x 1 m (not with scripted pins or wind, which do
            work, nor in a step where an obstacle moves other than in its steady motion:
            `ObstacleContact.still`, and `ObstacleContact.steady`, where the energy is the one
            seen from the obstacles' `motion.steady_frame`; a device-side loop,
            `wp.capture_while`: capturable). The
            energy criterion took the drape's largest one-frame rise from 8.8e-4 J to 3e-5 J
            (with the contact sag of `contact_coupling`; none since `ENERGY_EPS` is 1e-6);
            steps that end their iterations still gaining more than `ENERGY_REPORT` are
            counted (``energy_gain_steps``) and reported. By the residual alone
            (before): the largest one-frame energy gain fell from 2.3e-3 to 1.2e-3 J on the
            table scene and from 2.5e-3 to 0.9e-3 J on the drape; at rest or sliding they run
            rarely
            (`warp-cloth bench contact`: within noise). 0: none. Counted in ``stats``
            (``contact_iterations``: this step's, ``contact_iterations_total``,
            ``contact_short_steps``: steps that used them all still above the residual,
            reported by `frame_end`).
        contact_residual: metres (default 0.1). In contact the residual is dominated by the
            penalty, about ``kappa`` times its deepest violation (0.1 m: 0.1 mm at the default
            ``contact_stiffness``); 0.03 m ran them in most sliding steps (+88 % time on the
            spinning sphere) for little more.
        smoothing_sweeps: colour-ordered nonlinear Gauss-Seidel sweeps on the step's potential
            ``F = 1/(2 dt^2) |x - y|_M^2 + E(x)`` after the iterations
            (`warp_cloth.solvers.smoothing`, as implicit Euler's; default 0 = off): each free
            vertex takes a local Newton step with the springs' exact Hessian and a
            backtracking search, so F only falls; the end-of-step velocity is taken again.
            Under-converged PD leaves the springs stretched at short range, which the sweeps
            remove: on the tradeoff bench's 16 x 16 sheet (k = 1e3 N/m, 60 fps, no collision)
            4 sweeps took 10 iterations a frame from 0.184 to 0.122 m RMS error, 4 steps of 10
            from 0.074 to 0.039. Not in steps with contact entries (their penalty is not in
            the local potential), not with obstacles at all (the steps before and between
            contacts swept, those in contact not: on six variants of the table, 28-36 cells
            and 50 / 72 fps, PD's max strain averaged 5.65 % with them against 4.83 %
            without), nor with terms evaluated per iteration (wind, dihedral bending);
            ``stats["smoothing_sweeps"]``: the sweeps the last step ran. Off by default: on
            the default hanging scene (self-collision on, 120 frames) the swept swing folded
            the sheet onto itself more, and PD's steps in self-contact then reached 8.7 %
            strain (3.9 % without; the steps in contact are not swept).
        corrections: limits run after each step (`Solver.add_correction`).
        collision: a `CollisionStage`: its contacts are constraints of every local step (their
            projection onto the free half-space) and their blocks enter the global matrix, so
            the global step sees contact; the stage's ``resolve`` ends the step.

    Attributes:
        default_substeps: 3 per frame at 60 fps (one step per frame is stable too, but an
            under-converged step at dt = 1/60 s is visibly soft: 7.6 % peak strain vs 4.9 %).
        stats: after a step (read lazily from the device): ``iterations``,
            ``inner_iterations``, ``objective`` (F at the iterate where each outer iteration
            starts, J), ``gradient_norm`` (``|grad F|`` there, N), ``linear_residual`` (last
            inner solve, when measured), ``rho``, ``linear``, ``factor_fallbacks`` (banded-factor
            applications that fell back to block Jacobi over the run: a constant matrix with no
            Cholesky factor; reported by `frame_end` too).
    """

    name = "pd"
    default_substeps = 3

    def __init__(self, model, *, iterations: int = 10, linear: str | None = None,
                 linear_iterations: int | None = None, linear_tolerance: float | None = None,
                 alpha: float | None = None, rho: float | None = None, rho_safety: float = 0.99,
                 delay: int = 2, outer_rho: float | None = None, outer_delay: int = 2,
                 direct: bool = False, direct_max_vertices: int = 4000,
                 contact_stiffness: float = DEFAULT_CONTACT_STIFFNESS,
                 tolerance: float | None = None, contact_iterations: int = 20,
                 contact_residual: float = 0.1, smoothing_sweeps: int = 0,
                 corrections=(), collision=None):
        super().__init__(model, corrections=corrections, collision=collision)
        check_sweeps(smoothing_sweeps, "pd")
        self.smoothing_sweeps = int(smoothing_sweeps)
        if (isinstance(contact_iterations, bool) or int(contact_iterations) != contact_iterations
                or contact_iterations < 0):
            raise ValueError(f"pd: contact_iterations must be an integer >= 0, got "
                             f"{contact_iterations!r}")
        self.contact_iterations = int(contact_iterations)
        self.contact_residual = positive_finite(contact_residual, "pd: contact_residual", "metres")
        self._more_flag = wp.zeros(1, dtype=wp.int32, device=model.device)
        self._more = wp.zeros(4, dtype=wp.int32, device=model.device)
        self._no_int = wp.zeros(0, dtype=int, device=model.device)
        # the energy criterion of the contact iterations (`_energy_guard`): [start, iterate]
        self._e64 = wp.zeros(3, dtype=wp.float64, device=model.device)  # start, iterate, KE
        self._e32 = wp.zeros(1, dtype=float, device=model.device)
        self._e_views = (self._e64[0:1], self._e64[1:2])
        self._no_e64 = wp.zeros(0, dtype=wp.float64, device=model.device)
        self._ke_view = self._e64[2:3]
        mg = float(np.sum(model.masses)) * float(np.linalg.norm(model.gravity))
        self._energy_eps = max(ENERGY_EPS * mg, 1.0e-9)
        self._energy_report = max(ENERGY_REPORT * mg, self._energy_eps)
        self._more_step = self._more[0:1]  # this step's count (a view made once, not per step)
        self._more_res = wp.zeros(1, dtype=float, device=model.device)
        self._more_seen = 0
        self._gain_seen = 0
        self.tolerance = (None if tolerance is None
                          else positive_finite(tolerance, "pd: tolerance", "metres"))
        self._res = wp.zeros(3, dtype=float, device=model.device)
        self._short = wp.zeros(1, dtype=wp.int32, device=model.device)
        self._short_seen = 0
        if isinstance(iterations, bool) or int(iterations) != iterations or iterations < 1:
            raise ValueError(f"pd: iterations must be a positive integer, got {iterations!r}")
        if linear is not None and linear not in PD_LINEAR:
            raise ValueError(f"pd: linear must be one of {sorted(PD_LINEAR)} or None, "
                             f"got {linear!r}")
        if linear_iterations is not None and (
                isinstance(linear_iterations, bool) or int(linear_iterations) != linear_iterations
                or linear_iterations < 1):
            raise ValueError(f"pd: linear_iterations must be a positive integer or None, got "
                             f"{linear_iterations!r}")
        if linear_tolerance is not None and not (linear_tolerance > 0 and math.isfinite(linear_tolerance)):
            raise ValueError(f"pd: linear_tolerance must be > 0 or None, got {linear_tolerance!r}")
        if rho is not None and not (0.0 <= rho < 1.0):
            raise ValueError(f"pd: rho must be in [0, 1) or None, got {rho!r}")
        if not (0.0 < rho_safety <= 1.0):
            raise ValueError(f"pd: rho_safety must be in (0, 1], got {rho_safety!r}")
        if outer_rho is not None and not (0.0 <= outer_rho < 1.0):
            raise ValueError(f"pd: outer_rho must be in [0, 1) or None, got {outer_rho!r}")
        if isinstance(outer_delay, bool) or int(outer_delay) != outer_delay or outer_delay < 0:
            raise ValueError(f"pd: outer_delay must be an integer >= 0, got {outer_delay!r}")
        if isinstance(delay, bool) or int(delay) != delay or delay < 0:
            # (checked by the Chebyshev solver only at the first step, after the run had
            # opened its output: a bad value left a stage of one frame behind)
            raise ValueError(f"pd: delay must be an integer >= 0, got {delay!r}")
        if alpha is None:
            alpha = 1.0
        if not (0.0 < alpha <= 2.0):
            raise ValueError(f"pd: alpha must be in (0, 2], got {alpha!r}")
        if direct and model.num_vertices > direct_max_vertices:
            raise ValueError(f"pd: direct=True is for small meshes: {model.num_vertices} vertices > "
                             f"direct_max_vertices={direct_max_vertices}")
        if model.spring_damping > 0:
            import warnings

            warnings.warn("pd: spring_damping (dashpots) is ignored by projective dynamics",
                          stacklevel=2)
        self.iterations = int(iterations)
        self._linear_given = linear
        self._linear_iterations_given = (None if linear_iterations is None
                                         else int(linear_iterations))
        self._band_width = None  # the constant matrix's band, vertices (`linear_name`)
        self._band_order = None  # (order, width) found for it
        #: with a collision stage and the default inner solver: the factor's exact solve for
        #: the iterations with no contact block in the matrix (`_global_solve`), and their flag
        self._free_linear = None
        self._free_flag = wp.zeros(1, dtype=wp.int32, device=model.device)
        self._fallbacks_seen = 0  # (`_frame_messages`)
        self.linear_tolerance = linear_tolerance
        self.alpha = float(alpha)
        self.rho = rho
        self._rho_given = rho is not None
        self.rho_safety = float(rho_safety)
        self.delay = int(delay)
        self.direct = bool(direct)
        self.outer_rho = outer_rho
        self.outer_delay = int(outer_delay)
        self._omegas = self._outer_omegas()
        self.capturable = self.capturable and not self.direct and linear_tolerance is None

        m, d = model, self.device
        n = m.num_vertices
        self.matrix_terms = [t for t in m.force_terms if _is_constant_hessian(t)]
        self.explicit_terms = [t for t in m.force_terms
                               if t not in self.matrix_terms and type(t).__name__ != "SpringForce"]
        self.energy_terms = [t for t in m.force_terms if type(t).__name__ != "SpringForce"
                             and hasattr(t, "energy") and type(t).__name__ != "WindForce"]
        # the sweeps after the iterations (`smoothing`): springs, inertia, gravity and the
        # matrix terms; not with terms evaluated per iteration (wind, dihedral bending)
        self._smooth_on = bool(self.smoothing_sweeps) and not self.explicit_terms
        self._smoother = None  # made at the first step (its colouring is host work)
        self.x0 = wp.zeros(n, dtype=wp.vec3, device=d)
        self.x_prev = wp.zeros(n, dtype=wp.vec3, device=d)
        self.y = wp.zeros(n, dtype=wp.vec3, device=d)
        self.f = wp.zeros(n, dtype=wp.vec3, device=d)
        self.b = wp.zeros(n, dtype=wp.vec3, device=d)
        self.dx = wp.zeros(n, dtype=wp.vec3, device=d)
        self.d = wp.zeros(max(m.num_springs, 1), dtype=wp.vec3, device=d)
        K = self.iterations
        # slot K: the contact iterations' evaluations (scratch, not in `stats`)
        self._objective = wp.zeros(K + 1, dtype=wp.float64, device=d)
        self._gradient = wp.zeros(K + 1, dtype=wp.float64, device=d)
        self._energy32 = wp.zeros(K, dtype=wp.float32, device=d)
        self._energy_views = [self._energy32[k:k + 1] for k in range(K)]
        self.operator = None
        self.linear = None
        self._dt = None
        self._Sinv = None
        self._free_idx = np.flatnonzero(m.inverse_masses > 0)
        self._last_info = None
        self._stepped = False
        self.contact_stiffness = ContactCoupling._check(contact_stiffness)
        self._coupling = None

    def set_collision(self, collision) -> None:
        super().set_collision(collision)
        self._dt = None  # the default inner solver may change (`linear_name`): prepare again

    @property
    def linear_name(self) -> str:
        """The global step's inner solver: the one given, else ``"cg"`` with a collision stage
        (its contact blocks change the matrix after Chebyshev's spectral radius was measured
        on the contact-free one: with it, the under-converged steps gained up to 0.02 J a
        frame on impact in the drape scene, 0.09 J with ``rho_safety=0.9``; CG needs no
        estimate and lowers the energy norm of the error every iteration; its iterations with
        no contact block take the factor, `_hybrid`) and without one ``"cholesky"`` on the CPU
        where the band is narrow enough (`_narrow_band`: the exact solve, 2.4 times cheaper
        an iteration than Chebyshev-20 on the 64 x 32 sheet, ``docs/bench/pd.md``), else
        ``"chebyshev"`` (faster than CG to the same accuracy there)."""
        if self._linear_given is not None:
            return self._linear_given
        if self.collision is not None:
            return "cg"
        # without contact terms the banded factor is the whole matrix: one exact solve for less
        # than Chebyshev-20 costs (`warp-cloth bench pd`); not on a GPU, where its serial
        # substitutions run on one thread
        if self.device.is_cpu and self._narrow_band():
            return "cholesky"
        return "chebyshev"

    def _narrow_band(self) -> bool:
        """Whether the constant matrix's band (the mesh's own order, or reverse Cuthill-McKee
        on meshes up to `RCM_MAX_VERTICES` vertices, over springs and folded terms) is at most
        `CHOLESKY_MAX_WIDTH` vertices wide (host, once; the order found is the factor's,
        `band.ScalarBandFactor`)."""
        if self._band_width is None:
            from .band import narrowest_order

            m = self.model
            pairs = m.spring_pairs
            rows, cols = [pairs[:, 0]], [pairs[:, 1]]
            for t in self.matrix_terms:
                if hasattr(t, "scalar_entries"):
                    r, c, _ = t.scalar_entries()
                    rows.append(r)
                    cols.append(c)
            r = np.concatenate(rows).astype(np.int64)
            c = np.concatenate(cols).astype(np.int64)
            n = m.num_vertices
            self._band_order = narrowest_order(n, r, c, rcm=n <= RCM_MAX_VERTICES)
            self._band_width = self._band_order[1]
        return (self._band_width <= CHOLESKY_MAX_WIDTH
                and self.model.num_vertices * (self._band_width + 1) <= CHOLESKY_MAX_ENTRIES)

    @property
    def linear_iterations(self) -> int:
        """Inner iterations per global step: the given count, else the inner solver's default
        (constructor)."""
        if self._linear_iterations_given is not None:
            return self._linear_iterations_given
        if self.linear_name == "cholesky":
            return 1 if self.collision is None else 4
        return 20

    def _contact(self):
        """The contact coupling of the current collision stage (made on first use), or None."""
        if self.collision is None:
            return None
        if self._coupling is None or self._coupling.stage is not self.collision:
            if self.operator is not None and self._coupling in self.operator.extra:
                self.operator.extra.remove(self._coupling)
            self._coupling = ContactCoupling(self.model, self.collision, self.contact_stiffness)
            self._coupling.pairs_in_operator = False  # lumped in `pd_local` instead
        # self-contacts in the global matrix: their off-diagonal blocks as an operator term
        # (not with ``direct``, whose Woodbury update takes single-vertex blocks only)
        if (self._coupling.self_record is not None and not self.direct
                and self.operator is not None and self._coupling not in self.operator.extra):
            self.operator.extra.append(self._coupling)
        return self._coupling

    def _outer_omegas(self):
        """Wang 2015's Chebyshev weights over the outer iterations (1 when ``outer_rho`` is None)."""
        out, om = [], 1.0
        for k in range(self.iterations):
            j = k - self.outer_delay
            if self.outer_rho is None or j <= 0:
                om = 1.0
            elif j == 1:
                om = 2.0 / (2.0 - self.outer_rho ** 2)
            else:
                om = 4.0 / (4.0 - self.outer_rho ** 2 * om)
            out.append(om)
        return out

    # ------------------------------------------------------------------ set-up (host, per dt)
    def _prepare(self, dt: float):
        if self._dt == dt:
            return
        self._dt = dt
        if self.operator is None:
            self.operator = PDSystemOperator(self.model, 1.0 / (dt * dt), self.matrix_terms)
        else:
            self.operator.update(1.0 / (dt * dt))
        if self._linear_given is None and self.device.is_cpu and self._narrow_band():
            # the default factor (alone or in contact-free iterations) takes the order found
            self.operator.band_order = self._band_order
        if self.direct:
            S = self.operator.dense_scalar()
            f = self._free_idx
            self._Sinv = np.linalg.inv(S[np.ix_(f, f)])
            self._bhost = np.zeros((self.model.num_vertices, 3), dtype=np.float32)
            return
        opts = dict(iterations=self.linear_iterations, tolerance=self.linear_tolerance)
        if self.linear_name in ("jacobi", "chebyshev"):
            opts["alpha"] = self.alpha
        if self.linear_name == "chebyshev":
            if not self._rho_given:
                est = estimate_spectral_radius(self.operator, self.alpha, iterations=200)
                self.rho = min(self.rho_safety * est, 0.9999)
            opts["rho"] = self.rho
            opts["delay"] = self.delay
        self.linear = make_linear_solver(self.linear_name, **opts)
        self._free_linear = None
        if self._hybrid():
            # set up (allocations, the factor) now: the first contact-free step may be
            # recorded in a graph
            self._free_linear = make_linear_solver("cholesky", iterations=1, tolerance=None)
            self._free_linear.setup(self.operator)

    def _hybrid(self) -> bool:
        """Whether the default inner solver with a collision stage (CG) leaves the iterations
        with no contact block to the factor (`_global_solve`): on the CPU, with a narrow band,
        without a user's inner solver or inner tolerance."""
        return (self._linear_given is None and self.collision is not None
                and self.device.is_cpu and self.linear_tolerance is None
                and self._narrow_band())

    def _global_solve(self, cc=None) -> None:
        """``dx`` from the global system: the inner solver, or, in an iteration whose local
        step put no contact block in the matrix (a device flag, `_mark_free`: a conditional
        node when recorded), the exact banded solve (`_free_linear`): the matrix is then the
        constant one. Measured: module docstring."""
        if self._free_linear is None or cc is None:  # (no coupling: nothing sets the flag)
            self._last_info = self.linear.solve(self.operator, self.b, self.dx)
            return
        wp.capture_if(self._free_flag, on_true=self._solve_free, on_false=self._solve_contact)

    def _mark_free(self, cc) -> None:
        """``_free_flag`` = 1 when this iteration's local step put no contact block in the
        matrix (every vertex's ``vblock`` zero: no active obstacle or self-contact entry),
        else 0 (`no_blocks_kernel`)."""
        if self._free_linear is not None:
            launch(no_blocks_kernel, 1, [cc.vblock, self.model.num_vertices, self._free_flag],
                   device=self.device)

    def _solve_free(self) -> None:
        self._free_linear.solve(self.operator, self.b, self.dx)

    def _solve_contact(self) -> None:
        self._last_info = self.linear.solve(self.operator, self.b, self.dx)

    def prepare(self, dt: float):
        """Build the constant matrix (and Chebyshev's ``rho``, or the direct inverse) for ``dt``
        now, so the first `step` does no set-up work. `step` calls it itself when ``dt`` changes."""
        from .base import check_dt

        self._prepare(check_dt(dt))
        return self

    # ------------------------------------------------------------------ the step
    def _advance(self, state, dt):
        self._prepare(dt)
        m, d, A = self.model, self.device, self.operator
        n = m.num_vertices
        inv_dt2 = 1.0 / (dt * dt)
        launch(pd_predict_kernel, n,
               [state.x, state.v, m.inv_mass, wp.vec3(*m.gravity), dt, self.x0, self.y], device=d)
        cc = self._contact()
        A.vertex_blocks = cc.vblock if cc is not None else None
        if cc is not None:  # the step's contacts, from the predicted path
            cc.detect(self.x0, state.x, dt, state.time)
            # friction's guess from inertia alone (self.f is zero here; dx is scratch): with the
            # spring forces of an under-converged step in it, sliding cloth measured 20 % slow
            cc.friction_guess(state.x, self.dx, dt, self.f, classify=True)
        self._objective.zero_()
        self._gradient.zero_()
        if self.energy_terms:
            self._energy32.zero_()
        decay = math.exp(-m.damping * dt)
        guard = cc is not None and self.contact_iterations > 0 and self._energy_guard()
        if guard:  # the energy at the step's start (x0, the start velocity)
            self._energy(self.x0, state.v, 0, cc)
        K = self.iterations
        for k in range(K):
            if m.num_springs:
                launch(pd_local_kernel, m.num_springs,
                       [state.x, m.spring_indices, m.spring_rest_length, m.spring_k, self.d,
                        self.f, self._objective, k], device=d)
            for t in self.matrix_terms + self.explicit_terms:
                t.eval(state.x, state.v, self.f, state.time)
            if cc is not None:  # contact projections, and their blocks in this global matrix
                cc.pd_local(state.x, self.f, self._objective, k, dt)
                self._mark_free(cc)
                if not self.direct:
                    cc.invert_diagonal(A.blocks, A.free, A.diag_inv)
            for t in self.energy_terms:
                t.energy(state.x, self._energy_views[k])
            launch(pd_rhs_kernel, n,
                   [state.x, self.y, m.mass, A.free, inv_dt2, self.f, self.b, self.dx,
                    self._objective, self._gradient, k], device=d)
            if k == K - 1 and self.tolerance is not None:
                launch(pd_residual_kernel, n, [self.b, m.inv_mass, dt * dt, self._res],
                       device=d)
                launch(pd_converged_kernel, 1, [self._res, self.tolerance, self._short],
                       device=d)
            if self.direct:
                self._solve_direct(cc)
            else:
                self._global_solve(cc)
            launch(pd_update_kernel, n,
                   [state.x, self.dx, self.x0, state.v, m.inv_mass, decay, 1.0 / dt,
                    1 if k == K - 1 else 0, self._omegas[k], self.x_prev], device=d)
        if cc is not None and self.contact_iterations > 0 and not self.direct:
            self._more_step.zero_()
            self._evaluate(state, dt, cc, guard)
            wp.capture_while(self._more_flag, self._contact_iteration, state=state, dt=dt, cc=cc,
                             guard=guard)
        if self._smooth_on and (cc is None or cc.stage.contact is None):
            self._smooth(state, dt, cc, decay)
        if cc is not None:
            cc.end_step(state.x, state.v, dt, state.time)
        self._stepped = True

    def _smooth(self, state, dt, cc, decay) -> None:
        """`smoothing_sweeps` sweeps on F = 1/(2 dt^2) |x - y|_M^2 + E(x) (gravity is in y),
        then the end-of-step velocity again; nothing moves in a step with contact entries (the
        device flag of `contact_free_kernel`)."""
        m, d, n = self.model, self.device, self.model.num_vertices
        if self._smoother is None:
            adj = SpringSystemOperator(m, 1.0, extra=self.matrix_terms)
            self._smoother = VertexSmoother(m, adj)
            self._smooth_offset = wp.zeros(n, dtype=wp.vec3, device=d)
            self._smooth_force = wp.zeros(n, dtype=wp.vec3, device=d)  # none: gravity is in y
            self._smooth_free = wp.ones(1, dtype=int, device=d)
        free = self._smooth_free
        if cc is not None:
            cc.mark_free(free)
        launch(offset_kernel, n, [state.x, self.y, self._smooth_offset], device=d)
        self._smoother.sweep(state.x, self._smooth_offset, self._smooth_force, 1.0 / (dt * dt),
                             self.smoothing_sweeps, free)
        launch(end_velocity_kernel, n,
               [state.x, self.x0, m.inv_mass, 1.0 / dt, decay, free, state.v], device=d)

    def _energy_guard(self) -> bool:
        """Whether the contact iterations also run while the step gains energy: only when
        nothing outside the cloth does work on it (no scripted pins, no wind). Moving obstacles
        are decided per step on the device (`_still`): one standing still (the mesh scene's
        torus before it moves) does no work, and without the check PD's landing on it gained
        1.6e-2 J in a frame."""
        return not (getattr(self.model, "pin_path", None) is not None
                    or any(type(t).__name__ == "WindForce" for t in self.model.force_terms))

    def _still(self, cc):
        """The device flag 'no obstacle moved this step' (`ObstacleContact.still`), or an empty
        array when no obstacle ever moves."""
        contact = getattr(cc.stage, "contact", None)
        if contact is not None and contact.moving:
            return contact.still
        return self._no_int

    def _steady(self, cc):
        """``(flag, u, w, c)``: the device flag 'the moving obstacles run in their steady
        frame this step' (`ObstacleContact.steady`) and that frame (`motion.steady_frame`): a
        flag that stays 0 (and zeros) when they have no such frame, an empty one when no
        obstacle moves (as `_still`)."""
        contact = getattr(cc.stage, "contact", None) if cc is not None else None
        return steady_frame_args(contact, self._no_int)

    def _energy(self, x, v, slot: int, cc=None) -> None:
        """Kinetic, gravity and elastic energy at ``x``, ``v`` into ``_e64[slot]`` (float64
        sums; the other force terms' energy in float32)."""
        m, d = self.model, self.device
        out = self._e_views[slot]
        out.zero_()
        ke = self._ke_view if slot == 0 else self._no_e64  # the start's kinetic scale
        if slot == 0:
            ke.zero_()
        flag, u, w, c = self._steady(cc)
        launch(pd_energy_kernel, m.num_vertices,
               [x, v, m.mass, m.inv_mass, wp.vec3(*m.gravity), out, u, w, c, flag, ke],
               device=d)
        if m.num_springs:
            launch(spring_energy64_kernel, m.num_springs,
                   [x, m.spring_indices, m.spring_rest_length, m.spring_k, out], device=d)
        for t in self.energy_terms:  # bending (wind does work and has no energy)
            self._e32.zero_()
            t.energy(x, self._e32)
            launch(to_float64_kernel, 1, [self._e32, out], device=d)

    def _evaluate(self, state, dt, cc, guard=False):
        """Local step and right-hand side at the current iterate (scratch slot K), its residual,
        and whether another contact iteration runs (`pd_more_kernel`)."""
        m, d, A, K = self.model, self.device, self.operator, self.iterations
        if guard:  # the energy at the iterate (its velocity: the last update set it)
            self._energy(state.x, state.v, 1, cc)
        if m.num_springs:
            launch(pd_local_kernel, m.num_springs,
                   [state.x, m.spring_indices, m.spring_rest_length, m.spring_k, self.d,
                    self.f, self._objective, K], device=d)
        for t in self.matrix_terms + self.explicit_terms:
            t.eval(state.x, state.v, self.f, state.time)
        cc.pd_local(state.x, self.f, self._objective, K, dt)
        self._mark_free(cc)
        cc.invert_diagonal(A.blocks, A.free, A.diag_inv)
        launch(pd_rhs_kernel, m.num_vertices,
               [state.x, self.y, m.mass, A.free, 1.0 / (dt * dt), self.f, self.b, self.dx,
                self._objective, self._gradient, K], device=d)
        launch(pd_residual_kernel, m.num_vertices, [self.b, m.inv_mass, dt * dt,
                                                    self._more_res], device=d)
        launch(pd_more_kernel, 1, [self._more_res, self.contact_residual,
                                   self.contact_iterations, self._more_flag, self._more,
                                   self._e64, self._energy_eps, self._energy_report,
                                   int(guard),
                                   self._still(cc), self._steady(cc)[0]],
               device=d)

    def _contact_iteration(self, state, dt, cc, guard=False):
        """One more global step and update (velocity set), then `_evaluate`."""
        m = self.model
        self._global_solve(cc)
        launch(pd_update_kernel, m.num_vertices,
               [state.x, self.dx, self.x0, state.v, m.inv_mass, math.exp(-m.damping * dt),
                1.0 / dt, 1, 1.0, self.x_prev], device=self.device)
        self._evaluate(state, dt, cc, guard)

    def _solve_direct(self, cc=None):
        """Host decision by design: dx_f = S_ff^-1 b_f for the three components (float64).

        With contact blocks ``sum u u^T`` (rank one each, on one vertex), by the Woodbury
        identity: ``(S (x) I + U U^T)^-1 b = y - Z (I + U^T Z)^-1 U^T y``, ``y = S^-1 b``,
        ``Z = (S^-1 (x) I) U`` (one small dense solve per iteration)."""
        f = self._free_idx
        b = self.b.numpy()
        y = self._Sinv @ b[f].astype(np.float64)
        if cc is not None:
            rows, U = cc.host_factors(f)
            if len(rows):
                Si = self._Sinv[:, rows]  # (F, r)
                G = self._Sinv[np.ix_(rows, rows)] * (U @ U.T)  # U^T Z
                coef = np.linalg.solve(np.eye(len(rows)) + G, np.einsum("rc,rc->r", U, y[rows]))
                y = y - (Si * coef[None, :]) @ U
        self._bhost[f] = y.astype(np.float32)
        self.dx.assign(self._bhost)

    # ------------------------------------------------------------------ statistics
    @property
    def stats(self) -> dict:
        if not getattr(self, "_stepped", False):
            return {}
        obj = self._objective.numpy()[:self.iterations].copy()
        if self.energy_terms:
            obj += self._energy32.numpy()
        info = self._last_info or {}
        inner = self.linear_iterations if not self.direct else 0
        if info.get("iterations") is not None and self.linear_tolerance is not None:
            inner = info["iterations"]  # of the last solve; the others are not recorded
        return {
            "iterations": self.iterations,
            "inner_iterations": inner,
            "linear": "direct" if self.direct else self.linear_name,
            "factor_fallbacks": self._factor_fallbacks(),
            "objective": obj.tolist(),
            "gradient_norm": np.sqrt(self._gradient.numpy()[:self.iterations]).tolist(),
            "linear_residual": info.get("residual", float("nan")),
            "rho": self.rho,
            **({} if self._coupling is None else dict(zip(
                ("contact_iterations", "contact_iterations_total", "contact_short_steps",
                 "energy_gain_steps"),
                (int(c) for c in self._more.numpy())))),
            **({} if self.tolerance is None else {
                "residual": float(self._res.numpy()[1]),
                "unconverged_steps": int(self._short.numpy()[0])}),
            **(self.collision.stats if self._coupling is not None else {}),
            **(self._coupling.self_stats if self._coupling is not None else {}),
            "smoothing_sweeps": (self.smoothing_sweeps * int(self._smooth_free.numpy()[0])
                                 if self._smoother is not None else 0),
        }

    @stats.setter
    def stats(self, value):  # the base class initialises it; the property reads the device
        pass

    @property
    def short_steps_total(self) -> int:
        """Steps since the solver was made that used every contact iteration with the residual
        still above ``contact_residual`` (and, with a ``tolerance``, steps that ended above it):
        `Scene` compares it before and after a frame and runs a frame again with twice the
        steps when one was short and the cloth stretched past `scene.RETRY_STRAIN` in it (host
        read). Light, stiff cloth (0.1 kg/m^2, 1e5 N/m) landing on a lumpy mesh: 20 contact
        iterations left each of the landing's steps short and the feature response after the
        solve stretched it to 12.5 % and put 2.3 J into a 0.64 J sheet; with twice the steps
        1.6 %."""
        n = 0
        if self._coupling is not None and self.contact_iterations > 0:
            n += int(self._more.numpy()[2])
        if self.tolerance is not None:
            n += int(self._short.numpy()[0])
        return n

    def _factor_fallbacks(self) -> int:
        """Banded-factor applications that fell back to block Jacobi over the run (a matrix
        with a non-positive pivot: not positive definite; host read)."""
        return sum(getattr(lin, "fallbacks", 0) for lin in (self.linear, self._free_linear)
                   if lin is not None and getattr(lin, "name", "") == "cholesky")

    def _frame_messages(self) -> list:
        """Steps above ``tolerance`` since the last call, and steps that used every contact
        iteration still above ``contact_residual`` (`Solver.frame_end`; host reads)."""
        out = []
        n = self._factor_fallbacks()
        new, self._fallbacks_seen = n - self._fallbacks_seen, n
        if new > 0:
            out.append(f"pd: {new} banded-factor application(s) fell back to block Jacobi: its "
                       "constant matrix had no Cholesky factor (not positive definite: a "
                       "negative stiffness or mass?)")
        if self._coupling is not None and self.contact_iterations > 0:
            n = int(self._more.numpy()[2])
            new, self._more_seen = n - self._more_seen, n
            if new > 0:
                out.append(f"pd: {new} step(s) used all {self.contact_iterations} contact "
                           f"iterations with the residual still above {self.contact_residual:g} m")
            new, self._gain_seen = count_since(self._more, self._gain_seen, 3)
            if new > 0:
                out.append(f"pd: {new} step(s) used all {self.contact_iterations} contact "
                           f"iterations still gaining energy")
        return out + self._tolerance_messages()

    def _tolerance_messages(self) -> list:
        if self.tolerance is None:
            return []
        new, self._short_seen = count_since(self._short, self._short_seen)
        if new <= 0:
            return []
        r = float(self._res.numpy()[2])
        return [f"pd: {new} step(s) ended above the tolerance {self.tolerance:g} m after "
                f"{self.iterations} iterations (last: residual {r:.3g} m); raise iterations "
                f"or use more substeps"]

    def describe(self) -> str:
        lin = "direct" if self.direct else f"{self.linear_name} x{self.linear_iterations}"
        if not self.direct and (self._free_linear is not None or self._hybrid()):
            lin += "; cholesky x1 in contact-free iterations"
        sw = (f", {self.smoothing_sweeps} sweeps" if self._smooth_on and (
            self.collision is None or self.collision.contact is None) else "")
        return f"pd ({self.iterations} iterations, {lin}{sw})"
