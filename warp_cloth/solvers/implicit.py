"""Implicit (backward) Euler solved by Newton's method (``reference/physics.md`` 2.3-2.6).

Backward Euler ``x1 = x0 + dt v0 + dt^2 M^-1 f(x1)``, ``v1 = (x1 - x0)/dt`` is the minimisation
(notes L939-941, L1050-1077)::

    x1 = argmin F(x),  F(x) = 1/(2 dt^2) ||x - x0 - dt v0||_M^2 + E(x) - x . f_ext

with ``E`` the springs' and bending models' energy and ``f_ext`` the external forces: gravity
``M g`` and every force term without a Hessian (wind), evaluated once at the start of the step
(``x0``, ``v0``, ``t0``) and treated as constant (zero derivative, note 001:L112-117). Newton
(L1776-1783): from ``x^(0)``, repeat

    (M/dt^2 + H(x^(k))) dx = -grad F(x^(k)) = f(x^(k)) + f_ext - M/dt^2 (x^(k) - x0 - dt v0)
    x^(k+1) = x^(k) + dx

Per Newton iteration: one per-vertex kernel (``-grad F`` inertia part, ``M/dt^2`` diagonal), one
per-spring kernel (spring forces, ``H_e`` blocks and their diagonal sums, fused), one per quad for
bending (forces + Hessian), one to finish the block diagonal, the inner solve, one update.

- **Spring Hessian**: the notes' ``H_e = k d d^T/|d|^2 + k (1 - L/|d|)(I - d d^T/|d|^2)``
  (physics.md 2.1). By default with the definiteness fix (L990-994): the second term is dropped
  for compressed springs, so ``A = M/dt^2 + H`` is s.p.d. and Newton is a descent method (L1813).
  ``exact_hessian=True`` keeps it (A may be indefinite; CG and Jacobi may then fail: for study).
- **Bending**: the terms of ``model.force_terms`` that provide ``eval_with_hessian``,
  ``matvec_add`` and ``add_diagonal`` (`warp_cloth.forces.bending`): quadratic bending with its
  exact constant Hessian, dihedral bending with a PSD Gauss-Newton approximation.
- **Inner solver** (`warp_cloth.solvers.linear`, matrix-free): ``"cg"`` (block-Jacobi
  preconditioned conjugate gradient), ``"jacobi"`` (relaxed block Jacobi, ``alpha``) or
  ``"chebyshev"`` (Chebyshev-accelerated Jacobi, Wang 2015; ``rho`` measured by Lanczos
  (`jacobi_spectral_radius`) on the first Newton system when not given, and again when ``dt``
  changes; overshooting is caught by the solver's divergence fall-back when residuals are checked).
  In a Newton iteration with active self-contacts, CG ends with the Galerkin correction along
  the free vertices' translations (`CGSolver.translation`, gated on the device by the
  coupling's count of active self-contacts): its residual then exerts no net force. Stopped at
  0.1 without it, the residual's net force pushed a sheet folded flat on the floor sideways,
  faster every step (12 x 12, folded at 170 degrees: 0.55 m/s after 45 frames; a 24 x 24 at
  150 degrees 0.45 m/s after 120, 4.5 mJ gained in a frame; now at rest, 0.12 mJ).
- **Pins** are eliminated (reduced coordinates, note 001:L119-140): the base class puts scripted
  pins at their end-of-step targets before the solve, their entries of ``dx`` stay 0, and the
  springs that touch them see the target positions.
- **Damping**: the model's velocity damping is applied after the solve,
  ``v1 = (x1 - x0)/dt * exp(-damping dt)``. Spring dashpots (``spring_damping``) are not used:
  backward Euler damps numerically (the notes' "implicit tends to vanish", L923-925).

**Stopping.** ``tolerance`` (metres) is on the residual of the implicit-Euler equation (T3),
``r = max_i |x1_i - x0_i - dt v0_i - dt^2 f_i(x1)/m_i|`` over free vertices, i.e. the
mass-scaled gradient ``dt^2 M^-1 grad F`` (checked before each linear solve, so a converged
iterate costs no extra solve; the final one is reported in ``stats["residual"]``). Since
``A >= M/dt^2``, the position error of the iterate is at most about ``r`` (mass norm). Newton
stops when ``r < tolerance`` (``stats["converged"]``), when an update moved no vertex by more
than ``step_tolerance`` (the notes' ``||dx||`` test, L1776-1783; it also catches the float32
floor of ``r``, about ``1e-7 max|x| k dt^2/m`` metres, which can exceed ``tolerance`` for stiff
springs or large steps), or after ``newton_iterations`` solves. ``newton_iterations=1`` is
Baraff and Witkin's (1998) one linear solve per step (notes L1043-1049); with
``initial_guess="start"`` (and no smoothing sweeps, its default) it is exactly their
linearised step about ``x0`` (L1913-1916, without their damping terms). It is fast but may not converge (T5): its
residual is reported.

**Smoothing.** A step whose Newton iteration stopped above its tolerance (or that runs without
one) ends with ``smoothing_sweeps`` colour-ordered nonlinear Gauss-Seidel sweeps on F
(`warp_cloth.solvers.smoothing`): each free vertex takes a local Newton step with the springs'
exact Hessian (projected per vertex) and a backtracking search, so F only decreases. With the
definiteness fix Newton converges only linearly where springs are far stiffer than the
inertia block; stopped at its cap it leaves single over-stretched edges, which the sweeps
remove (32 x 32 hanging sheet, k = 1e6 N/m, one step a frame at 30 fps: 0.18 % max strain
without them, 0.040 % with 4 sweeps, against 0.018 % for the converged reference; the
trajectory's error unchanged). Not in steps with contact entries, nor with dihedral bending,
nor by default after Baraff-Witkin's single solve (`warp-cloth bench tradeoff`, 16 x 16 sheet,
k = 1e3 N/m, one step a frame at 60 fps: 0.50 -> 0.34 m RMS for 2.3 times the step's time).

**Host reads.** With ``tolerance=None`` and ``linear_tolerance=None`` a step runs fixed iteration
counts and reads nothing back, so ``capturable`` is True and the scene runner replays steps as a
Warp graph. With tolerances a step reads one float per Newton iteration and per checked inner
iteration (documented host decisions). ``rho=None`` with Chebyshev measures rho on the first step
(host work, allocations); the runner captures only from its second frame, after that.

**Globalisation.** By default each Newton iteration ends with a line search on F done on the
device (`ls_select_kernel`: four step lengths evaluated in one pass, the largest meeting
Armijo's condition taken), so every iteration lowers the incremental potential (the notes'
2.6; T4) without a host read: the step stays capturable.

**Energy guard** (``energy_guard=True``, with a ``tolerance``: the mode that reads the host
anyway). Implicit Euler dissipates, so a step that ends with more energy than it started with
(kinetic, springs, bending, the external forces' potential; not counting contact) is a solver
defect. Measured on the stability map's 6 x 6 sheet at k = 1e9 N/m, dt = 1/30 s: Newton stops at
its cap at the float32 floor, and the line search, when all four steps raised F, took the least
bad one (F 1.4 -> 25 J in one iteration); with Jacobi and Chebyshev inner solves the sheet
gained 20 and 165 J. Now (1) a line search whose four steps all raise F tries steps 16 times
shorter and else moves nothing (``stats["ls_rejected"]``); (2) a step that reaches its Newton
cap, or stalls with a Jacobi-type inner solver, while its energy rose by more than `GUARD_EPS` (1e-6) of
``M |g|`` x 1 m goes on for up to ``2 newton_iterations`` more iterations until the rise is gone,
checked after every quarter of ``newton_iterations`` (whole rounds iterated up to 6 times more
than needed: 23 % fewer Newton iterations on the 32 x 32 fold with self-collision)
(``stats["energy_guard_steps"]``); with Jacobi or Chebyshev it starts again from its initial
guess with CG and ``3 newton_iterations`` (their iterate kept the energy: continuing it with CG
still gained); a step that still gains is
counted (``energy_gain_steps``) and shortened (below). Not with scripted pins, nor in a step
in which an obstacle moves (`_guard_applies`): those do work on the cloth. With CG that cell's
energy now never rises (and the drape's largest one-frame rise fell from 5e-4 to 3e-5 J, the
table's from 7e-4 J to none), and
with Jacobi and Chebyshev too (`warp-cloth bench stability --methods implicit-jacobi,...`:
every cell from k = 1e6 to 1e9 N/m at dt = 1/120 and 1/30 s stable).

**Precision and the start of Newton.** Spring forces, and every energy the line search and
the guard compare, take the stretch ``|x_i - x_j| - L`` in float64 from the float32 positions
(`common.spring_stretch64`): in float32 the length rounds by about 1e-7 L, a force error of
``k 1e-7 L`` (2 mN on a 2 cm spring at k = 1e6 N/m, a vertex's weight on a 32 x 32 sheet; 2 N at
1e9 N/m), and Newton's gradient was noise. Without contact, Newton starts from the lowest F of
the inertial guess and points on the straight way back to ``x0`` (where F is the start's total
energy; `_choose_guess`, device-side): on a swinging stiff sheet ``x0 + dt v0`` stretches the
springs (F 42-177 J against 1.5 J at ``x0``, 32 x 32, k = 1e6 N/m, dt = 1/30 s). When the inner
solve's direction raises F at every length, one block-Jacobi-preconditioned gradient step is
taken instead (``gradient_steps``). And the guard's last resort: a step that still ends with more
energy than its start is shortened toward its start until it gains none (`_clamp_energy`;
``energy_clamped_steps``, reported); not in contact, where the energy the guard measures leaves
the contact term out (on the self-folding sheet 37 resting steps "gained" 2e-5 to 1e-4 J and
were halved): there such a step is counted and reported, as before. "In contact" is a step
whose contact records hold an entry (`contact_free_kernel`), not a solver with a collision
stage: with self-collision on by default, the hanging sheet at k = 1e6 N/m, one step a frame at
30 fps, had lost the guess choice and the clamp (0.71 % strain, 1.47 -> 2.08 J in 30 frames;
0.18 % and 1.47 -> 1.07 J with them). Measured on the 32 x 32 sheet at one step per frame
(30 frames, 30 and 60 fps, k = 1e6 to 1e9 N/m, CG, Jacobi and Chebyshev: 24 runs): the energy
never rose above its start (before: up to 8.2 J from 1.47 J), max strain 0.18 % (before: up to
15.5 %). The price is honest but visible: at k >= 1e8 N/m these steps cannot be solved in
float32 (k dt^2/m ~ 1e8), the guard keeps them from gaining energy, and the sheet falls far too
slowly (centre of mass 1.000 -> 0.955 m in 0.5 s at k = 1e8, where PBD's falls to 0.50 m).

Limitations: Newton with the exact Hessian may diverge under compression;
float32 positions put a floor of roughly ``1e-7 max|x| k dt^2/m`` metres under the residual
(a cloth far from the origin has a higher floor).
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..runstats import Note
from ..util import launch
from .base import Solver
from .common import (frame_kinetic, spring_energy64_kernel, spring_stretch64,
                     steady_frame_args, to_float64_kernel)
from .contact_coupling import DEFAULT_CONTACT_STIFFNESS, ContactCoupling
from .linear import CGSolver, SpringSystemOperator, make_linear_solver, spring_block_matrix
from .smoothing import DEFAULT_SMOOTHING_SWEEPS, VertexSmoother, check_sweeps

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile

__all__ = ["ImplicitEuler"]

#: the initial guesses of a step and their flag in `begin_step_kernel` / `restart_kernel`
GUESSES = {"start": 0, "inertial": 1, "velocity": 2, "auto": 3}


# ----------------------------------------------------------------------------------- kernels
@wp.kernel
def begin_step_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    gravity: wp.vec3,
    dt: float,
    inertial: int,
    f_ext: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    x_hat: wp.array(dtype=wp.vec3),
    disp: wp.array(dtype=wp.vec3),
):
    """x_prev = x0; x_hat = x0 + dt v0; f_ext += m g; x^(0) = x_hat + dt^2 f_ext / m (inertial)
    or x0 (``inertial`` 0).

    ``disp`` accumulates x - x_hat exactly (as a sum of increments, not a difference of rounded
    positions), so the end-of-step velocity keeps full float32 precision at small dt."""
    i = wp.tid()
    xi = x[i]
    x_prev[i] = xi
    xh = xi + dt * v[i]
    x_hat[i] = xh
    disp[i] = wp.vec3(0.0)
    w = inv_mass[i]
    if w > 0.0:
        fe = f_ext[i] + mass[i] * gravity
        f_ext[i] = fe
        if inertial == 1 or inertial == 3:  # "auto": `contact_guess_kernel` may take d0 back
            d0 = (dt * dt * w) * fe
            x[i] = xh + d0
            disp[i] = d0
        elif inertial == 2:  # x0 + dt v0: x is x_hat
            x[i] = xh
        else:  # the guess is x0: x - x_hat = x0 - x_hat (it was left 0, as if x were x_hat)
            disp[i] = xi - xh


@wp.kernel
def restart_kernel(x: wp.array(dtype=wp.vec3), x_prev: wp.array(dtype=wp.vec3),
                   x_hat: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float),
                   f_ext: wp.array(dtype=wp.vec3), dt: float, inertial: int,
                   free: wp.array(dtype=int), disp: wp.array(dtype=wp.vec3)):
    """The free vertices back at the step's initial guess (as `begin_step_kernel` and, for
    ``"auto"``, `contact_guess_kernel` left them; ``f_ext`` already holds gravity), ``disp`` =
    x - x_hat exactly again."""
    i = wp.tid()
    w = inv_mass[i]
    if w > 0.0:
        mode = inertial
        if mode == 3:
            mode = 1
            if free[0] == 0:
                mode = 2
        if mode == 1:
            d0 = (dt * dt * w) * f_ext[i]
            x[i] = x_hat[i] + d0
            disp[i] = d0
        elif mode == 2:
            x[i] = x_hat[i]
            disp[i] = wp.vec3(0.0)
        else:
            x[i] = x_prev[i]
            disp[i] = x_prev[i] - x_hat[i]


@wp.kernel
def contact_guess_kernel(free: wp.array(dtype=int), inv_mass: wp.array(dtype=float),
                         x: wp.array(dtype=wp.vec3), disp: wp.array(dtype=wp.vec3)):
    """``initial_guess="auto"``, in a step with contact entries (``free[0] == 0``): the guess
    goes from the inertial ``x_hat + dt^2 f_ext / m`` back to ``x_hat = x0 + dt v0`` (``disp``,
    still ``dt^2 f_ext / m`` here, taken off): the external force's step is left to Newton's
    solve, which sees the contact terms that balance it."""
    i = wp.tid()
    if free[0] == 0 and inv_mass[i] > 0.0:
        x[i] = x[i] - disp[i]
        disp[i] = wp.vec3(0.0)


@wp.kernel
def newton_init_kernel(
    x: wp.array(dtype=wp.vec3),
    x_hat: wp.array(dtype=wp.vec3),
    disp: wp.array(dtype=wp.vec3),
    use_disp: int,
    mass: wp.array(dtype=float),
    f_ext: wp.array(dtype=wp.vec3),
    scale: float,
    b: wp.array(dtype=wp.vec3),
    diag: wp.array(dtype=wp.mat33),
    dx: wp.array(dtype=wp.vec3),
):
    """b = f_ext - M/dt^2 (x - x_hat) (the non-elastic part of -grad F); diag = M/dt^2; dx = 0.

    For the solver's own iterate (``use_disp``), ``x - x_hat`` is the exact increment sum ``disp``: at small dt the difference of the rounded
    positions loses all precision (dt^2 g is then below float32 resolution of x) and would act
    as a spurious force of order m * eps |x| / dt^2."""
    i = wp.tid()
    sm = scale * mass[i]
    u = x[i] - x_hat[i]
    if use_disp != 0:
        u = disp[i]
    b[i] = f_ext[i] - sm * u
    diag[i] = sm * wp.identity(n=3, dtype=float)
    dx[i] = wp.vec3(0.0)


@wp.kernel
def spring_newton_kernel(
    x: wp.array(dtype=wp.vec3),
    springs: wp.array2d(dtype=wp.int32),
    rest: wp.array(dtype=float),
    stiffness: wp.array(dtype=float),
    definite: int,
    b: wp.array(dtype=wp.vec3),
    slots: wp.array2d(dtype=wp.int32),
    coef: wp.array(dtype=wp.vec4),
):
    """Spring forces into b; the compact Hessian block ``H_e = g g^T + beta I`` into both of the
    spring's CSR entries (`linear.SpringSystemOperator`).

    ``H_e = k P + k c (I - P)`` with ``P = n n^T``, ``n = d/|d|``, ``c = 1 - L/|d|`` (physics.md
    2.1) is ``k (1 - c) n n^T + k c I``: ``g = sqrt(k L/|d|) n`` and ``beta = k c`` (with the
    definiteness fix ``c >= 0``, which makes ``H_e`` PSD)."""
    e = wp.tid()
    i = springs[e, 0]
    j = springs[e, 1]
    k = stiffness[e]
    # the force from the float64 stretch (`spring_stretch64`); the Hessian in float32
    d64 = wp.vec3d(x[i]) - wp.vec3d(x[j])
    l64 = wp.length(d64)
    d = wp.vec3(d64)
    l = float(l64)
    c = wp.vec4(0.0, 0.0, 0.0, k)
    fi = wp.vec3(0.0)
    if l >= 1.0e-12:
        fi = wp.vec3(d64 * (-wp.float64(k) * (l64 - wp.float64(rest[e])) / l64))
        cc = 1.0 - rest[e] / l
        if definite != 0 and cc < 0.0:
            cc = 0.0
        g = (wp.sqrt(k * (1.0 - cc)) / l) * d
        c = wp.vec4(g[0], g[1], g[2], k * cc)
    coef[slots[e, 0]] = c
    coef[slots[e, 1]] = c
    wp.atomic_add(b, i, fi)
    wp.atomic_sub(b, j, fi)


@wp.func
def vertex_residual(b: wp.vec3, w: float, dt2: float, vblock: wp.array(dtype=wp.mat33), i: int,
                    contact: int):
    """``dt^2 b_i / m_i``, the position change the residual force makes in a step; for a vertex
    with an active contact penalty ``(M/dt^2 + C_i)^-1 b_i`` (``C_i``: the penalty's normal
    block), so a contact's stiff force is measured by the position change it makes, not by
    1 + kappa times it (`contact_coupling`). Friction's tangential stiffness is left out (its
    static branch is so stiff that it would hide any tangential imbalance) except where the
    vertex sits on the static branch with the cloth's other forces inside the cone
    (`newton_contact_kernel`): there the answer sticks, and what is left of the imbalance is
    the position change that block allows (measured: short frames at defaults, spin 92 -> 81,
    mesh 89 -> 61, drape 34 -> 25, fold 24 -> 20, table 103, stack 58 -> 61)."""
    r = (dt2 * w) * b
    if contact != 0:
        C = vblock[i]
        if C[0, 0] + C[1, 1] + C[2, 2] > 0.0:
            r = wp.inverse(wp.identity(n=3, dtype=float) + (dt2 * w) * C) * r
    return r


@wp.kernel
def finish_system_kernel(
    diag: wp.array(dtype=wp.mat33),
    offsets: wp.array(dtype=wp.int32),
    coef: wp.array(dtype=wp.vec4),
    b: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    free: wp.array(dtype=float),
    dt2: float,
    dinv: wp.array(dtype=wp.mat33),
    residual: wp.array(dtype=float),
    slot: int,
    vblock: wp.array(dtype=wp.mat33),
    contact: int,
):
    """Add the spring blocks at i to the diagonal block (gathered over the CSR row), invert it
    (0 for pins) and measure the residual (free only, `vertex_residual`)."""
    i = wp.tid()
    D = diag[i]
    for q in range(offsets[i], offsets[i + 1]):
        D = D + spring_block_matrix(coef[q])
    diag[i] = D
    if free[i] > 0.0:
        dinv[i] = wp.inverse(D)
        r = vertex_residual(b[i], inv_mass[i], dt2, vblock, i, contact)
        wp.atomic_max(residual, slot, wp.max(wp.abs(r[0]), wp.max(wp.abs(r[1]), wp.abs(r[2]))))
    else:
        dinv[i] = wp.mat33(0.0)


@wp.kernel
def residual_only_kernel(
    b: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    dt2: float,
    residual: wp.array(dtype=float),
    slot: int,
    vblock: wp.array(dtype=wp.mat33),
    contact: int,
):
    i = wp.tid()
    w = inv_mass[i]
    if w > 0.0:
        r = vertex_residual(b[i], w, dt2, vblock, i, contact)
        wp.atomic_max(residual, slot, wp.max(wp.abs(r[0]), wp.max(wp.abs(r[1]), wp.abs(r[2]))))


@wp.kernel
def newton_update_kernel(
    x: wp.array(dtype=wp.vec3),
    dx: wp.array(dtype=wp.vec3),
    step: wp.array(dtype=float),
    free: wp.array(dtype=float),
    dx_max: wp.array(dtype=float),
    slot: int,
    disp: wp.array(dtype=wp.vec3),
):
    """x += a dx (a = step[0]: 1, or the device line search's choice); the largest move into
    ``dx_max[slot]`` (``slot < 0``: not recorded, the move to the initial guess)."""
    i = wp.tid()
    if free[i] > 0.0:
        d = step[0] * dx[i]
        x[i] = x[i] + d
        disp[i] = disp[i] + d
        if slot >= 0:
            wp.atomic_max(dx_max, slot, wp.length(d))


@wp.kernel
def end_step_kernel(
    x: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    inv_dt: float,
    decay: float,
    v: wp.array(dtype=wp.vec3),
    f_ext: wp.array(dtype=wp.vec3),
    disp: wp.array(dtype=wp.vec3),
):
    """v1 = (x1 - x0)/dt * decay = (v0 + (x1 - x_hat)/dt) * decay for free vertices, with
    x1 - x_hat taken from the exact increment sum ``disp`` (pins keep the base class's velocity).
    """
    i = wp.tid()
    if inv_mass[i] > 0.0:
        v[i] = (v[i] + disp[i] * inv_dt) * decay
    f_ext[i] = wp.vec3(0.0)


@wp.kernel
def objective_kernel(
    x: wp.array(dtype=wp.vec3),
    x_hat: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    f_ext: wp.array(dtype=wp.vec3),
    scale: float,
    out: wp.array(dtype=wp.float64),
):
    """Inertia and external-force part of F: sum_i m_i/(2 dt^2) |x_i - x_hat_i|^2 - f_ext_i . x_i."""
    i = wp.tid()
    if inv_mass[i] > 0.0:
        d = x[i] - x_hat[i]
        wp.atomic_add(out, 0, wp.float64(0.5 * scale * mass[i] * wp.dot(d, d) - wp.dot(f_ext[i], x[i])))


#: the energy rise (a fraction of ``M |g|`` times 1 m) the energy guard tolerates in a step. It
#: was 1e-5, for float32 rounding of a stiff spring's energy; but the guard sums in float64 (the
#: stretch from the stored positions, `spring_stretch64`), and what rounded at that level was the
#: meter's float32 sum: the 32 x 32 sheet at k = 1e9 N/m, one step at 60 fps, rose by 7.1e-6 J
#: (4.8e-6 M g) in a frame at 1e-5 and never at 1e-6, with the same fall and time
#: (`warp-cloth bench stability --strict`). Projective dynamics' `ENERGY_EPS` is the same.
GUARD_EPS = 1.0e-6
#: ... and at least this fraction of the step's starting kinetic energy: float32 velocities
#: round the kinetic energy by about 1e-7 of itself, which the 1e-9 J floor of a cloth without
#: gravity did not cover (a free sheet translating at 1.1 m/s "gained" 4.7e-9 J of 0.033 J in a
#: step, and the clamp halved its speed every step)
GUARD_KE_REL = 1.0e-6

#: the energy guard adds up to this many times ``newton_iterations`` to a step that reached its
#: cap above its tolerance while gaining energy (in rounds of a quarter of them, the gain
#: checked after each)
ENERGY_GUARD_ROUNDS = 2

#: a step with contact entries whose Newton reaches its cap while its last update still moved
#: some vertex more than the collision thickness goes on, in rounds of a quarter of ``newton_iterations``,
#: up to this many times ``newton_iterations`` more (``stats["impact_steps"]``). Such an iterate
#: is far from the step's solution (a landing at speed: penalty and springs still trading
#: centimetres), and the contacts the solve took from the predicted path no longer describe it;
#: what it leaves, the collision stage's response after the solve moves vertex by vertex: a
#: sheet falling 1.5 m and piling onto the floor at 30 fps (2 mm thickness) had a bottom vertex
#: 3.3 cm above its start at the cap and a falling one through it, and the response's projection
#: of that pair stretched an edge 35 % (explicit Euler 11 %; 20 iterations: 9 %)
IMPACT_ROUNDS = 2

#: a step at its Newton cap above its tolerance whose residual has been falling steadily goes
#: on, in rounds of a quarter of ``newton_iterations``, up to this many times them more, while
#: its rate (the residual's ratio per iteration over the last `CONVERGE_SPAN`) reaches the
#: tolerance within what is left (`_converging`); a step that stalls or wanders stops at the cap
#: as before. Counted in ``stats["converge_steps"]``
CONVERGE_ROUNDS = 1
CONVERGE_SPAN = 3
#: the largest ratio per iteration counted as converging
CONVERGE_RATE = 0.8

#: with the energy guard, a line search whose four steps all raise F tries these times shorter
LS_RETRY = 1.0 / 16.0

#: step lengths the device line search tries, largest first (one energy pass evaluates all)
LS_STEPS = (1.0, 0.5, 0.25, 0.125)
LS_N = wp.constant(len(LS_STEPS))
#: Armijo constant of the line search
LS_ARMIJO = 1.0e-4


@wp.kernel
def ls_vertex_kernel(
    x: wp.array(dtype=wp.vec3),
    dx: wp.array(dtype=wp.vec3),
    disp: wp.array(dtype=wp.vec3),
    b: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    free: wp.array(dtype=float),
    f_ext: wp.array(dtype=wp.vec3),
    scale: float,
    steps: wp.vec4,
    x_try: wp.array2d(dtype=wp.vec3),
    energy: wp.array(dtype=wp.float64),
):
    """Line-search candidates ``x + a_j dx`` (rows of ``x_try``) and the inertia and external
    force part of F at ``x`` (slot 0) and at each candidate (slot j + 1), from the exact
    increment ``disp = x - x_hat``; ``grad F . dx = -b . dx`` into slot ``LS_N + 1``."""
    i = wp.tid()
    xi = x[i]
    d = dx[i] * free[i]
    u = disp[i]
    sm = 0.5 * scale * mass[i]
    fe = f_ext[i]
    if free[i] > 0.0:
        wp.atomic_add(energy, 0, wp.float64(sm * wp.dot(u, u) - wp.dot(fe, xi)))
        wp.atomic_add(energy, LS_N + 1, wp.float64(-wp.dot(b[i], d)))
        # the size of the terms, for the float32 noise of F (slot LS_N + 2)
        wp.atomic_add(energy, LS_N + 2, wp.float64(sm * wp.dot(u, u) + wp.abs(wp.dot(fe, xi))))
    for j in range(LS_N):
        a = steps[j]
        xt = xi + a * d
        x_try[j, i] = xt
        if free[i] > 0.0:
            ut = u + a * d
            wp.atomic_add(energy, j + 1, wp.float64(sm * wp.dot(ut, ut) - wp.dot(fe, xt)))


@wp.kernel
def ls_spring_kernel(x: wp.array(dtype=wp.vec3), x_try: wp.array2d(dtype=wp.vec3),
                     springs: wp.array2d(dtype=wp.int32), rest: wp.array(dtype=float),
                     stiffness: wp.array(dtype=float), energy: wp.array(dtype=wp.float64)):
    """Spring energy at ``x`` (slot 0) and at each candidate (slot j + 1), float64."""
    e = wp.tid()
    i = springs[e, 0]
    j = springs[e, 1]
    k = wp.float64(0.5) * wp.float64(stiffness[e])
    L = wp.float64(rest[e])
    s = spring_stretch64(x[i], x[j], rest[e])
    wp.atomic_add(energy, 0, k * s * s)
    wp.atomic_add(energy, LS_N + 2, k * s * s + wp.float64(stiffness[e]) * L * wp.abs(s))
    for c in range(LS_N):
        st = spring_stretch64(x_try[c, i], x_try[c, j], rest[e])
        wp.atomic_add(energy, c + 1, k * st * st)


@wp.kernel
def ls_select_kernel(energy: wp.array(dtype=wp.float64), steps: wp.vec4, armijo: float,
                     chosen: wp.array(dtype=float), slot: int, record: wp.array(dtype=float),
                     reject: int):
    """The largest step whose F meets Armijo's condition ``F <= F0 + c a grad F . dx`` (up to
    the float32 noise of F); if none does, the step of the lowest F: with ``reject``, only if
    that one does not raise F beyond the noise, else 0 (no move: the step's caller, which reads
    it, tries shorter steps or another inner solver); without (the capturable fixed-iteration
    mode, which reads nothing), the smallest even when all rise. At k = 1e9 N/m, dt = 1/30 s
    such a step took F from 1.4 to 25 J. Written to ``chosen[0]`` (read by the update) and
    ``record[slot]``."""
    f0 = energy[0]
    slope = wp.min(energy[LS_N + 1], wp.float64(0.0))
    # F is summed in float64 from float32 terms: differences below ~1e-6 of the terms' size
    # are noise, and near convergence Armijo's decrease is smaller than that
    noise = wp.float64(1.0e-6) * energy[LS_N + 2]
    best = int(-1)
    for j in range(LS_N):
        if best < 0 and energy[j + 1] <= f0 + wp.float64(armijo * steps[j]) * slope + noise:
            best = j
    a = float(0.0)
    if best < 0:
        best = LS_N - 1
        for j in range(LS_N):
            if energy[j + 1] < energy[best + 1]:
                best = j
        if reject == 0 or energy[best + 1] <= f0 + noise:
            a = steps[best]
    else:
        a = steps[best]
    chosen[0] = a
    record[slot] = a


@wp.kernel
def step_energy_kernel(x: wp.array(dtype=wp.vec3), x_prev: wp.array(dtype=wp.vec3),
                       v: wp.array(dtype=wp.vec3), disp: wp.array(dtype=wp.vec3),
                       mass: wp.array(dtype=float), inv_mass: wp.array(dtype=float),
                       f_ext: wp.array(dtype=wp.vec3), inv_dt: float, decay: float,
                       out: wp.array(dtype=wp.float64), frame_u: wp.vec3, frame_w: wp.vec3,
                       frame_c: wp.vec3, steady: wp.array(dtype=int)):
    """Kinetic energy and the external forces' potential ``-f_ext . x`` of the free vertices,
    at the start of the step (``out[0]``: ``v``, ``x_prev``) and at the current iterate
    (``out[1]``: the velocity `end_step_kernel` would give, ``x``); the start's kinetic energy
    alone into ``out[2]`` when there is one."""
    i = wp.tid()
    if inv_mass[i] > 0.0:
        v0 = v[i]
        v1 = (v0 + disp[i] * inv_dt) * decay
        m = 0.5 * mass[i]
        f = f_ext[i]
        k0 = m * wp.dot(v0, v0)
        k1 = m * wp.dot(v1, v1)
        if steady.shape[0] > 0:
            if steady[0] != 0:  # seen from the moving obstacles' steady frame
                k0, s0 = frame_kinetic(m, v0, x_prev[i], frame_u, frame_w, frame_c)
                k1, s1 = frame_kinetic(m, v1, x[i], frame_u, frame_w, frame_c)
        wp.atomic_add(out, 0, wp.float64(k0 - wp.dot(f, x_prev[i])))
        wp.atomic_add(out, 1, wp.float64(k1 - wp.dot(f, x[i])))
        if out.shape[0] > 2:
            wp.atomic_add(out, 2, wp.float64(m * wp.dot(v0, v0)))


@wp.kernel
def guess_direction_kernel(v: wp.array(dtype=wp.vec3), disp: wp.array(dtype=wp.vec3),
                           free: wp.array(dtype=float), dt: float, dx: wp.array(dtype=wp.vec3)):
    """The direction from the initial guess back to the step's start ``x0``, in the exact
    increments: ``x0 - x = -(dt v0 + disp)`` (``disp = x - x_hat``, ``x_hat = x0 + dt v0``)."""
    i = wp.tid()
    dx[i] = -(dt * v[i] + disp[i]) * free[i]


@wp.kernel
def guess_select_kernel(energy: wp.array(dtype=wp.float64), steps: wp.vec4,
                        free: wp.array(dtype=int), chosen: wp.array(dtype=float)):
    """Of the initial guess (slot 0) and the candidates on the way back to ``x0`` (slots 1..),
    the one of lowest F: its step along `guess_direction_kernel`'s direction (0: the guess);
    always the guess when ``free[0]`` is 0 (the step has contacts: `contact_free_kernel`)."""
    best = int(-1)
    fb = energy[0]
    if free[0] != 0:
        for j in range(LS_N):
            if energy[j + 1] < fb:
                fb = energy[j + 1]
                best = j
    a = float(0.0)
    if best >= 0:
        a = steps[best]
    chosen[0] = a


@wp.kernel
def gradient_direction_kernel(b: wp.array(dtype=wp.vec3), diag_inv: wp.array(dtype=wp.mat33),
                              dx: wp.array(dtype=wp.vec3)):
    """``dx = D^-1 b``: the block-Jacobi-preconditioned steepest descent direction of F
    (``b = -grad F``; ``D^-1`` is zero on pinned vertices), a descent direction whatever the
    inner solve did."""
    i = wp.tid()
    dx[i] = diag_inv[i] * b[i]


@wp.kernel
def shorten_step_kernel(x: wp.array(dtype=wp.vec3), x_prev: wp.array(dtype=wp.vec3),
                        v: wp.array(dtype=wp.vec3), disp: wp.array(dtype=wp.vec3),
                        free: wp.array(dtype=float), dt: float, s: float):
    """The step's displacement ``x - x0 = dt v0 + disp`` scaled by ``s``: ``x = x0 + s (x - x0)``
    and ``disp`` to match (the energy clamp, `ImplicitEuler._clamp_energy`)."""
    i = wp.tid()
    if free[i] > 0.0:
        u = s * (dt * v[i] + disp[i])
        x[i] = x_prev[i] + u
        disp[i] = u - dt * v[i]


@wp.kernel
def add_float32_kernel(src: wp.array(dtype=float), dst: wp.array(dtype=wp.float64)):
    j = wp.tid()
    dst[j] = dst[j] + wp.float64(src[j])


# ----------------------------------------------------------------------------------- helpers
def jacobi_spectral_radius(A, alpha: float, iterations: int = 40, seed: int = 0):
    """Spectral radius of the Jacobi iteration matrix ``I - alpha D^-1 A`` by Lanczos.

    Runs ``iterations`` steps of block-Jacobi-preconditioned CG on ``A x = b`` (random ``b``)
    and takes the extreme eigenvalues ``lam_min``, ``lam_max`` of ``D^-1 A`` from the Lanczos
    tridiagonal matrix built from CG's coefficients (Saad, *Iterative Methods*, 6.7.3):
    ``rho = max(|1 - alpha lam_min|, |1 - alpha lam_max|)``. Extreme Ritz values converge much
    faster than power iteration on ``I - alpha D^-1 A`` (whose top eigenvalues are clustered
    near 1 for cloth): measured on a 16 x 16 hanging cloth, 40 steps give 0.99790 against the
    exact 0.99801, where `linear.estimate_spectral_radius` (60 power steps) gives 0.972.
    Host work and allocations: call it outside a captured step. Returns
    ``(rho, lam_min, lam_max)``.
    """
    cg = CGSolver(iterations=iterations, tolerance=None)
    free = A.free.numpy()
    rng = np.random.default_rng(seed)
    b = wp.array((rng.standard_normal((A.n, 3)) * free[:, None]).astype(np.float32),
                 dtype=wp.vec3, device=A.device)
    x = wp.zeros(A.n, dtype=wp.vec3, device=A.device)
    cg.solve(A, b, x)
    rz = cg.s1.numpy()[: iterations + 1].astype(np.float64)
    pap = cg.s2.numpy()[:iterations].astype(np.float64)
    k = 0
    while k < iterations and pap[k] > 0 and rz[k] > 0 and rz[k + 1] > 0:
        k += 1
    if k == 0:
        return 0.0, 1.0, 1.0
    a = rz[:k] / pap[:k]
    beta = rz[1 : k + 1] / rz[:k]
    T = np.zeros((k, k))
    for j in range(k):
        T[j, j] = 1.0 / a[j] + (beta[j - 1] / a[j - 1] if j else 0.0)
        if j + 1 < k:
            T[j, j + 1] = T[j + 1, j] = math.sqrt(beta[j]) / a[j]
    ev = np.linalg.eigvalsh(T)
    lo, hi = float(ev.min()), float(ev.max())
    return max(abs(1.0 - alpha * lo), abs(1.0 - alpha * hi)), lo, hi


# ----------------------------------------------------------------------------------- operator
class _NewtonOperator(SpringSystemOperator):
    """``M/dt^2 + H``: the spring blocks and the diagonal are written by the solver's fused
    kernels; `update` only adds the extra terms' diagonals and inverts (with the residual)."""

    def update(self, mass_scale=None):  # pragma: no cover - the solver calls _finish instead
        raise RuntimeError("the implicit solver assembles this operator itself")


#: the inner solves' relative residual in Newton iterations with active self-contacts
#: (`ImplicitEuler` ``self_linear_tolerance``; with a ``tolerance``, the mode that reads the
#: host). Stopped at CG's 0.1, the stiff self-contact terms coupling four vertices (which the
#: block-Jacobi preconditioner does not see) left errors that made a folded sheet at rest pop:
#: 20 x 20 fold at 120 degrees, frames 90-120, the largest move of a vertex between frames
#: 6.6 mm (median over frames 2.3 mm); at 1e-2 1.06 / 0.35 mm, 3e-3 0.29 / 0.09, 1e-3 0.19 /
#: 0.03. The cost, ms a frame at 0.1 / 1e-2 / 3e-3 / 1e-3 (one run after another): the table
#: 97 / 138 / 206 / 202, the twist's first 150 frames 250 / 367 / 456 / 530; the table's largest
#: one-frame energy rise 3.1e-5 / 1.4e-5 / 7.3e-6 / 3.1e-6 J. At 1e-2 a 16 x 16 fold at rest
#: still popped by 3.1 mm (0.5 mm at 3e-3, 0.28 at 1e-3; 3.1 at 0.1): 3e-3, about twice the time
#: Re-measured with the self-contacts' penalty onset and hold (2026-12-07; `/tmp/s27/pop.py`, the
#: 16 x 16 fold at 120 degrees, frames 90-120, largest / median move between frames, ms a
#: frame): 0.1: 0.60 / 0.20 mm, 31.4 ms; 1e-2: 0.10 / 0.01 mm, 16.5 ms; 3e-3: 0.11 / 0.02 mm,
#: 15.1 ms (a loose inner solve now costs Newton iterations instead): kept.
SELF_LINEAR_TOLERANCE = 3e-3

LINEAR_DEFAULTS = {
    # (iterations, relative tolerance)
    # CG: an inexact-Newton forcing term of 0.1 (Eisenstat & Walker 1996): Newton converges only
    # linearly here (the definiteness fix drops the compression terms), so tighter inner solves
    # are wasted. Measured on the 64 x 32 hanging cloth (8 Newton iterations per step): 391 CG
    # iterations per step and a final residual of 7.5e-3 m, against 1392 and 2.8e-2 at 1e-3.
    "cg": (200, 1e-1),
    "jacobi": (400, 1e-3),
    "chebyshev": (200, 1e-3),
    # CG preconditioned by the banded Cholesky factor of the Newton matrix (`band`): one or two
    # iterations when every term is in the band, so a tight tolerance costs little
    "cholesky": (20, 1e-3),
}


def _converging(history, tol: float, left: int) -> bool:
    """Whether the residuals ``history`` (one per Newton iterate, the last one's update already
    taken) fall steadily enough to reach ``tol`` within ``left`` more iterations: their ratio
    per iteration over the last `CONVERGE_SPAN` (the geometric mean: Newton's residual is not
    monotone) is below `CONVERGE_RATE`, and the last residual times it to the power ``left``
    is below ``tol`` (`CONVERGE_ROUNDS`)."""
    if left <= 0 or len(history) <= CONVERGE_SPAN:
        return False
    last, first = history[-1], history[-1 - CONVERGE_SPAN]
    if not (math.isfinite(last) and first > 0.0 and last > 0.0):
        return False
    rate = (last / first) ** (1.0 / CONVERGE_SPAN)
    return rate < CONVERGE_RATE and last * rate ** left < tol


class ImplicitEuler(Solver):
    """Backward Euler by Newton's method with a matrix-free inner solver. ``solver.step(state, dt)``.

    Args:
        model: the `ClothModel`.
        newton_iterations: maximum Newton iterations (linear solves) per step. 1 = Baraff-Witkin.
        tolerance: metres (default 1e-4); stop Newton when the implicit-Euler residual
            ``max_i |x_i - x0_i - dt v0_i - dt^2 f_i(x)/m_i|`` is below it, or below
            ``max(0.2 |g| dt^2, 1e-6 m)`` when that is smaller (small steps; `step_tolerances`).
            ``None``: always run ``newton_iterations`` (no host reads).
        step_tolerance: metres (default ``max(tolerance / 10, 1.2e-7 max|x_rest|)``); also stop
            when a Newton update moves no vertex farther than this (the remaining position error
            is then far smaller; float32 rounding alone moves vertices by about
            ``1e-7 max|x|``, so a cloth that travels far from its rest place may need more).
            ``stats["converged"]`` tells whether ``r < tolerance`` was reached; a step that
            ends above it is counted (``stats["unconverged_steps"]``) and reported by
            `frame_end` (the scene runner prints a warning with the frame), and so is an inner
            solve that stops at its cap above its tolerance (``stats["inner_short_total"]``).
            ``tolerance=None`` makes no convergence claim.
        linear: inner solver, ``"cg"``, ``"jacobi"``, ``"chebyshev"`` or ``"cholesky"`` (CG
            preconditioned by a banded Cholesky factor of each Newton matrix, float64:
            `warp_cloth.solvers.band`; for stiff, light cloth at large steps, where block-Jacobi
            CG leaves Newton's directions far off; a serial factorisation, slower per step).
        linear_iterations: maximum inner iterations per Newton iteration (default 200 for CG and
            Chebyshev, 400 for Jacobi, 20 for cholesky).
        linear_tolerance: relative residual ``||b - A dx||/||b||`` that ends an inner solve
            (the inexact-Newton forcing term; default 1e-1 for CG, 1e-3 for Jacobi and
            Chebyshev); ``None`` runs ``linear_iterations`` (no host reads).
        exact_hessian: keep the spring Hessian's compression term (indefinite; for study).
        rho: Chebyshev spectral-radius estimate in [0, 1); ``None`` measures it.
        alpha: Jacobi / Chebyshev relaxation (default 0.66, as in `linear.JacobiSolver`).
        delay: Chebyshev plain-Jacobi iterations before acceleration (default 5).
        check_every: inner residual check period when ``linear_tolerance`` is set (default 1;
            larger values mean fewer host reads).
        initial_guess: ``"auto"`` (the default since 2026-12-06: ``"inertial"`` in steps
            without contact entries, ``"velocity"`` in steps with them: see *Resting contact*
            in `contact_coupling`), ``"inertial"`` (``x0 + dt v0 + dt^2 f_ext/m``, note
            001:L26-44; the default before, with which the earlier figures were measured),
            ``"start"`` (``x0``; with one Newton iteration this is Baraff-Witkin's step) or
            ``"velocity"`` (``x0 + dt v0``: the external forces' step left to the solve). The
            inertial guess presses every supported vertex ``dt^2 g`` into its support, whose
            penalty (kappa times the inertia block) Newton then climbs out of: on a folded
            sheet at rest it ran 3-10 iterations a step at residuals of 2e-3 to 8e-3 m; with
            ``"auto"`` 0-2 iterations at about 1e-4 to 7e-4 m (10 x 10 fold, 150 degrees).
            A guess without the external forces' step takes one solve at least in a step
            with contact (below dt = 1/3100 s, ``dt^2 g`` is under the step tolerance's 1e-6 m
            floor: a cloth at rest would never start to fall).
        line_search: after each solve, take the largest of the steps 1, 1/2, 1/4, 1/8 along
            ``dx`` whose F meets Armijo's condition (all four evaluated in one pass on the
            device, chosen there: no host read, capturable), else the one of lowest F. Default
            True: each Newton iteration then lowers the incremental potential, which keeps
            Newton from overshooting with stiff springs, compression and friction.
        trace: record per-Newton-iteration ``F``, residual and ``max |dx|`` in
            ``stats["trace"]`` (host reads; for study and tests).
        measure_residual: in fixed-iteration mode, evaluate the residual after the last update
            (one extra gradient evaluation per step, read only when ``stats`` is read).
        contact_stiffness: ``kappa`` of the contact term inside the Newton solve, its
            stiffness over the inertia block ``m/dt^2`` (default 1e3;
            `warp_cloth.solvers.contact_coupling`).
        self_linear_tolerance: the inner solve's relative residual in Newton iterations with
            active self-contacts, when tighter than ``linear_tolerance`` (default 3e-3,
            `SELF_LINEAR_TOLERANCE`; with a ``tolerance``: it reads the active count on the
            host). CG's 0.1 left a folded sheet at rest popping by up to 6.6 mm between frames
            (0.3 mm at 3e-3, for about twice the time on the table and the twist: the
            constant's comment). ``None``: ``linear_tolerance`` throughout.
        energy_guard: with a ``tolerance``, steps that would gain energy iterate further and
            a line search never takes a step that raises F (default True; see *Energy guard*
            above). False restores the former behaviour.
        smoothing_sweeps: colour-ordered nonlinear Gauss-Seidel sweeps on F after a Newton
            solve that stopped above its tolerance (or runs without one): each free vertex
            takes a projected local Newton step with the springs' exact Hessian and a
            backtracking search, so F only decreases (`warp_cloth.solvers.smoothing`; 0 = off;
            default ``None``: 4, but 0 with ``newton_iterations=1``). They remove the single
            over-stretched edges that Newton stopped at its cap leaves on stiff, light cloth.
            After Baraff-Witkin's one solve they cost more than they buy: on the tradeoff
            bench's sheet they took its error from 0.50 to 0.34 m RMS for 2.3 times the step's
            time (substeps buy more there), so that step stays the notes' unless asked. Steps with contact entries and models with
            dihedral bending are not smoothed (``stats["smoothing_sweeps"]``: the sweeps a
            step ran).
        corrections: limits run after each step.
        collision: a `CollisionStage`: its contacts enter every Newton iteration (detected once
            per step from the predicted positions), and its ``resolve`` ends the step.

    Attributes:
        default_substeps: 2 solver steps per frame (used by the scene runner when no substep
            count is given). At 60 fps, dt = 1/120 s keeps the default hanging sheet's swing
            visibly alive while every step is unconditionally stable; one step per frame
            works too, with stronger numerical damping.
        stats: after each step ``newton_iterations`` (linear solves), ``inner_iterations``
            (summed over them), ``residual`` (m, of the final iterate; nan when not measured:
            fixed-iteration mode without ``measure_residual``), ``converged`` (``residual <
            tolerance``), ``linear_residual`` (relative, last inner solve; nan when unchecked),
            ``fallback`` (the last inner solve: Chebyshev fell back to Jacobi), ``rho``
            (Chebyshev), ``trace``; ``fallbacks_total`` (every such fall-back, over the run,
            reported by `frame_end`);
            run totals: ``unconverged_steps``, ``energy_guard_steps`` (extended),
            ``energy_gain_steps`` (extended and still gaining), ``energy_clamped_steps``
            (shortened toward their start), ``gradient_steps`` (a preconditioned gradient step
            where the inner solve's direction raised F), ``ls_rejected``,
            ``steady_stall_iterations`` (Newton iterations added where a short line-search step
            stalled a step in contact with steadily moving obstacles while the energy seen from
            their frame rose: a stall there raised the spinning sphere's frame energy by
            2.0e-4 J in a step under ``"auto"``).

    Cost (measured by ``warp-cloth bench implicit`` on the 2-core CPU of this project, 2,145
    vertices, dt = 1/120 s): a CG iteration costs about 90 us (2 launches; about 22x a trivial
    per-vertex launch); CG needs about 250 iterations to a relative residual of 1e-4, so such a
    Newton iteration costs about 23 ms as a captured graph. At the defaults (forcing 0.1) a
    Newton iteration takes about 43 CG iterations: about 4.3 ms as a captured graph, 8 ms with
    host checks (before launch replay, `util.launch`, which took about a third off eager steps).
    Chebyshev needs about 24x fewer iterations than plain Jacobi.
    """

    name = "implicit"
    default_substeps = 2

    def __init__(self, model, *, newton_iterations: int = 8, tolerance: float | None = 1e-4,
                 step_tolerance: float | None = None,
                 linear: str = "cg", linear_iterations: int | None = None,
                 linear_tolerance: float | None = ..., exact_hessian: bool = False,
                 rho: float | None = None, alpha: float = 0.66, delay: int = 5,
                 check_every: int | None = None, initial_guess: str = "auto",
                 line_search: bool = True, trace: bool = False, measure_residual: bool = False,
                 contact_stiffness: float = DEFAULT_CONTACT_STIFFNESS,
                 energy_guard: bool = True, smoothing_sweeps: int | None = None,
                 self_linear_tolerance: float | None = SELF_LINEAR_TOLERANCE,
                 corrections=(), collision=None):
        super().__init__(model, corrections=corrections, collision=collision)
        if int(newton_iterations) != newton_iterations or newton_iterations < 1:
            raise ValueError(f"implicit: newton_iterations must be a positive integer, got "
                             f"{newton_iterations!r}")
        if smoothing_sweeps is None:  # Baraff-Witkin's one solve stays the notes' step
            smoothing_sweeps = DEFAULT_SMOOTHING_SWEEPS if newton_iterations != 1 else 0
        check_sweeps(smoothing_sweeps, "implicit")
        if not isinstance(energy_guard, (bool, np.bool_)):
            raise ValueError(f"implicit: energy_guard must be True or False, got {energy_guard!r}")
        if tolerance is not None and not (math.isfinite(tolerance) and tolerance > 0):
            raise ValueError(f"implicit: tolerance must be > 0 metres or None, got {tolerance!r}")
        if linear not in LINEAR_DEFAULTS:
            raise ValueError(f"implicit: unknown linear solver {linear!r}; choose one of "
                             f"{sorted(LINEAR_DEFAULTS)}")
        if initial_guess not in GUESSES:
            raise ValueError(f"implicit: initial_guess must be one of {sorted(GUESSES)}, got "
                             f"{initial_guess!r}")
        if rho is not None and not (0.0 <= rho < 1.0):
            raise ValueError(f"implicit: rho must be in [0, 1) or None, got {rho!r}")
        its, tol = LINEAR_DEFAULTS[linear]
        if linear_iterations is None:
            linear_iterations = its
        if linear_tolerance is ...:
            linear_tolerance = tol
        opts = dict(iterations=linear_iterations, tolerance=linear_tolerance,
                    check_every=check_every)
        if linear in ("jacobi", "chebyshev"):
            opts["alpha"] = alpha
        if linear == "chebyshev":
            opts.update(rho=0.9 if rho is None else rho, delay=delay)
        self.linear_name = linear
        self.linear = make_linear_solver(linear, **opts)  # validates its options
        # the energy guard's inner solver (`step`): CG, whatever ``linear`` is (a Jacobi-type
        # solve makes almost no progress on very stiff springs: at k = 1e9 N/m, dt = 1/30 s
        # Jacobi and Chebyshev steps gained 20 and 165 J on a 0.15 kg sheet)
        cg_its, cg_tol = LINEAR_DEFAULTS["cg"]
        self._guard_linear = (make_linear_solver("cg", iterations=cg_its, tolerance=cg_tol)
                              if energy_guard and tolerance is not None
                              and linear not in ("cg", "cholesky") else None)
        self.newton_iterations = int(newton_iterations)
        self.tolerance = tolerance
        if self_linear_tolerance is not None and not (
                isinstance(self_linear_tolerance, (int, float)) and
                math.isfinite(self_linear_tolerance) and 0 < self_linear_tolerance < 1):
            raise ValueError(f"implicit: self_linear_tolerance must be in (0, 1) or None, got "
                             f"{self_linear_tolerance!r}")
        self.self_linear_tolerance = self_linear_tolerance
        if step_tolerance is None:
            # float32 rounding alone moves a vertex at |x| by about eps32 |x| per update
            reach = float(np.abs(model.mesh.vertices).max()) if model.num_vertices else 1.0
            step_tolerance = 0.0 if tolerance is None else max(0.1 * tolerance, 1.2e-7 * reach)
        reach = float(np.abs(model.mesh.vertices).max()) if model.num_vertices else 1.0
        self._float_floor = 1.2e-7 * reach  # float32 rounding of a vertex at |x|
        # the residual's float32 floor per dt^2 (`residual_floor`): rounding every position by
        # its float32 step, eps |x|, moves vertex i's residual by up to eps |x| dt^2 K_i / m_i
        # (K_i: the Gershgorin row sum of its stiffness)
        from .explicit import SymplecticEuler

        rows, _ = SymplecticEuler.stiffness_row_sums(model)
        w = np.asarray(model.inverse_masses, dtype=np.float64)
        self._floor_per_dt2 = self._float_floor * (float((rows * w).max()) if len(w) else 0.0)
        if not (math.isfinite(step_tolerance) and step_tolerance >= 0):
            raise ValueError(f"implicit: step_tolerance must be >= 0 metres, got {step_tolerance!r}")
        self.step_tolerance = float(step_tolerance)
        self.exact_hessian = bool(exact_hessian)
        self.rho = rho
        self.alpha = float(alpha)
        self.initial_guess = initial_guess
        self.line_search = bool(line_search)
        self.trace = bool(trace)
        self.measure_residual = bool(measure_residual)
        self._rho_dt = None  # dt at which rho was measured

        # force terms: bending (implicit, with a Hessian) and explicit ones (wind, ...)
        from ..forces.springs import SpringForce

        self.implicit_terms, self.explicit_terms = [], []
        for t in model.force_terms:
            if isinstance(t, SpringForce):
                continue
            if all(hasattr(t, a) for a in ("eval_with_hessian", "matvec_add", "add_diagonal")):
                self.implicit_terms.append(t)
            else:
                self.explicit_terms.append(t)

        n, d = model.num_vertices, self.device
        self.A = _NewtonOperator(model, 1.0, extra=self.implicit_terms)
        # the sweeps after Newton (`smoothing`): springs, inertia and folded terms only; a
        # model with another implicit term (dihedral bending) is not smoothed
        self.smoothing_sweeps = int(smoothing_sweeps)
        self._smooth_on = bool(self.smoothing_sweeps) and not self.A.extra
        self._smoother = None  # made at the first step that sweeps (its colouring is host work)
        self.b = wp.zeros(n, dtype=wp.vec3, device=d)
        self.dx = wp.zeros(n, dtype=wp.vec3, device=d)
        self.f_ext = wp.zeros(n, dtype=wp.vec3, device=d)
        self.x_prev = wp.zeros(n, dtype=wp.vec3, device=d)
        self.x_hat = wp.zeros(n, dtype=wp.vec3, device=d)
        self.disp = wp.zeros(n, dtype=wp.vec3, device=d)
        self._iterate = None  # the positions array whose x - x_hat is tracked exactly in disp
        self.energy_guard = bool(energy_guard) and tolerance is not None
        #: most Newton iterations of a step, the energy guard's extensions included
        # (a Jacobi-type inner solve that gains energy restarts the step with CG and its own
        # full budget: room for both)
        self._k_total = self.newton_iterations * (1 + ENERGY_GUARD_ROUNDS * self.energy_guard) * (
            2 if self._guard_linear is not None else 1)
        self._k_total = max(self._k_total, self.newton_iterations * (1 + IMPACT_ROUNDS))
        self._energy = wp.zeros(3, dtype=wp.float64, device=d)
        self._energy32 = wp.zeros(1, dtype=wp.float32, device=d)
        # 1 while this step's contact records are empty (`ContactCoupling.mark_free`): a collision
        # stage with nothing near (a hanging sheet with self-collision on) is no contact
        self._free = wp.ones(1, dtype=int, device=d)
        #: land a sliding vertex that Newton's direction would carry back past its friction
        #: reference on that reference (`ContactCoupling.limit_reversals`; measured in
        #: docs/bench/selfcollision.md); False: the plain Newton direction
        self.limit_reversals = True
        self._reversals = wp.zeros(1, dtype=int, device=d)
        self._dx_newton = wp.zeros(n, dtype=wp.vec3, device=d)  # dx before the landings
        self._no_int = wp.zeros(0, dtype=int, device=d)  # an empty flag: the world frame
        self._steady_now = False  # this step measures energy in the obstacles' steady frame
        self._fallbacks_seen = 0  # (`_frame_messages`, linear="cholesky")
        self._guard = {"extended": 0, "gained": 0, "new": 0, "last": 0.0, "rejected": 0,
                       "steady": 0, "impact": 0, "converge": 0,
                       "clamped": 0, "gradient": 0, "scale": 1.0, "unlanded": 0}
        self.residuals = wp.zeros(self._k_total + 1, dtype=wp.float32, device=d)
        self.dx_max = wp.zeros(self._k_total + 1, dtype=wp.float32, device=d)
        if self.trace:
            self._obj = wp.zeros(1, dtype=wp.float64, device=d)
            self._obj32 = wp.zeros(1, dtype=wp.float32, device=d)
        self._one = wp.ones(1, dtype=float, device=d)
        if self.line_search:
            self._ls_try = wp.zeros((len(LS_STEPS), n), dtype=wp.vec3, device=d)
            self._ls_energy = wp.zeros(len(LS_STEPS) + 3, dtype=wp.float64, device=d)
            self._ls_energy32 = wp.zeros(len(LS_STEPS) + 1, dtype=wp.float32, device=d)
            self._ls_views = [self._ls_energy32[j:j + 1] for j in range(len(LS_STEPS) + 1)]
            self._ls_step = wp.ones(1, dtype=float, device=d)
            self._ls_taken = wp.zeros(self._k_total, dtype=float, device=d)
        # Chebyshev with rho=None measures rho on the first step (host work): the scene runner
        # captures from its second frame on, after that.
        self.capturable = (self.capturable and tolerance is None and self.linear.capturable
                           and not self.trace)
        self._stats = {}
        # steps whose Newton iteration ended above ``tolerance``, inner solves that stopped at
        # their cap above theirs (host counts: both are known on the host in checked mode)
        self._short = {"steps": 0, "new": 0, "last": (0.0, 0, False), "inner": 0, "inner_new": 0,
                       "fallback": 0, "fallback_new": 0,
                       "floor": 0, "floor_told": False, "floor_last": (0.0, 0.0, 0.0)}
        self._lazy = None
        self.contact_stiffness = float(contact_stiffness)
        ContactCoupling._check(self.contact_stiffness)
        self._coupling = None

    def _self_tol_applies(self) -> bool:
        """Whether `self_linear_tolerance` can tighten this solver's inner solves: set, tighter
        than the inner solver's own tolerance, and a contact coupling with self-contacts."""
        t, own = self.self_linear_tolerance, self.linear.tolerance
        c = self._coupling
        return (t is not None and own is not None and t < own and c is not None
                and c.self_record is not None)

    def _contact(self):
        """The contact coupling of the current collision stage (made on first use), or None."""
        if self.collision is None:
            self.A.vertex_blocks = None
            return None
        if self._coupling is None or self._coupling.stage is not self.collision:
            if self._coupling is not None and self._coupling in self.A.extra:
                self.A.extra.remove(self._coupling)
            self._coupling = ContactCoupling(self.model, self.collision, self.contact_stiffness)
            if self._coupling.self_record is not None or self._coupling.pairs_on is not None:
                self.A.extra.append(self._coupling)
            # the inner solve takes out its residual's net force in Newton iterations with
            # self-contacts active (`linear.CGSolver.translation`)
            self.A.translation_gate = (self._coupling.self_active
                                       if self._coupling.self_record is not None else None)
        self.A.vertex_blocks = self._coupling.vblock
        # a guess without the external forces' step starts resting vertices on their surface
        self._coupling.resting = self.initial_guess != "inertial"
        return self._coupling

    # ------------------------------------------------------------------ statistics
    @property
    def stats(self) -> dict:
        if self._lazy is not None:  # fixed-iteration mode: read the residual only when asked
            slot = self._lazy
            self._lazy = None
            self._stats["residual"] = float(self.residuals.numpy()[slot])
        if self._coupling is not None and "contacts" not in self._stats:
            self._stats.update(self.collision.stats)
            self._stats["contacts_active"] = int(self._coupling.active.numpy()[0]
                                                 + self._coupling.self_active.numpy()[0])
            self._stats.update(self._coupling.self_stats)
            # Newton directions that carried a sliding vertex back past its friction
            # reference, landed on it instead (`ContactCoupling.limit_reversals`), over the run
            self._stats["friction_landings_total"] = int(self._reversals.numpy()[0])
        if self.linear_name == "cholesky":  # applications without a factor, over the run
            self._stats["factor_fallbacks"] = self.linear.fallbacks
        if self._stats.get("smoothing_sweeps") and self._coupling is not None:
            # the sweeps ran only if the step had no contact entries (a device flag)
            self._stats["smoothing_sweeps"] *= int(self._free_step())
        return self._stats

    @stats.setter
    def stats(self, value):
        self._stats = value

    @property
    def short_steps_total(self) -> int:
        """Steps that ended short of the tolerance (above the float32 floor) since the solver
        was made: `Scene` compares it before and after a frame (`scene.RETRY_STRAIN`)."""
        return int(self._short["steps"])

    # ------------------------------------------------------------------ assembly
    def _assemble(self, x, slot: int, hessian: bool = True, contact: bool = True):
        """b = -grad F(x), the Newton matrix at x (blocks, diagonal, inverse) and the residual."""
        m, d, A = self.model, self.device, self.A
        n = m.num_vertices
        launch(newton_init_kernel, n,
               [x, self.x_hat, self.disp, 1 if x is self._iterate else 0, m.mass, self.f_ext,
                self._scale, self.b, A.diag, self.dx],
               device=d)
        if m.num_springs:
            launch(spring_newton_kernel, m.num_springs,
                   [x, m.spring_indices, m.spring_rest_length, m.spring_k,
                    0 if self.exact_hessian else 1, self.b, A.slots, A.coef], device=d)
        for t in self.implicit_terms:
            t.eval_with_hessian(x, self.b)
        vb = (A.diag_inv, 0)  # (any mat33 array, flag): no contact term
        if contact and self._coupling is not None and self.collision is not None:
            self._coupling.add_newton(x, self.b, A.diag, self._dt,
                                      resting=self._coupling.resting, first=slot == 0)
            vb = (self._coupling.nblock, 1)
        if hessian:
            if self.linear_name == "cholesky":
                self.linear.invalidate()  # a new Newton matrix: factored before its solve
            for t in self.implicit_terms:
                t.add_diagonal(A.diag)
            launch(finish_system_kernel, n,
                   [A.diag, A.offsets, A.coef, self.b, m.inv_mass, A.free, self._dt2, A.diag_inv,
                    self.residuals, slot, *vb], device=d)
        else:
            launch(residual_only_kernel, n,
                   [self.b, m.inv_mass, self._dt2, self.residuals, slot, *vb], device=d)

    def objective(self, x) -> float:
        """F(x) for the current step (after `step` began it): host read, for tests and study."""
        m, d = self.model, self.device
        if not hasattr(self, "_obj"):
            self._obj = wp.zeros(1, dtype=wp.float64, device=d)
            self._obj32 = wp.zeros(1, dtype=wp.float32, device=d)
        self._obj.zero_()
        launch(objective_kernel, m.num_vertices,
               [x, self.x_hat, m.mass, m.inv_mass, self.f_ext, self._scale, self._obj], device=d)
        if m.num_springs:
            launch(spring_energy64_kernel, m.num_springs,
                   [x, m.spring_indices, m.spring_rest_length, m.spring_k, self._obj], device=d)
        for t in self.implicit_terms:
            self._obj32.zero_()
            t.energy(x, self._obj32)
            launch(to_float64_kernel, 1, [self._obj32, self._obj], device=d)
        if self._coupling is not None and self.collision is not None:
            self._coupling.energy(x, self._obj, self._dt)
        return float(self._obj.numpy()[0])

    def _measure_rho(self):
        """Measure the spectrum of ``D^-1 A`` (Lanczos) for the Jacobi-type inner solvers.

        Relaxed Jacobi converges only if ``alpha lam_max < 2``. Springs alone keep the block
        diagonal dominant enough for the default 0.66, but bending (a discrete bilaplacian) is
        not diagonally dominant (the notes' T13): on a 16 x 16 cloth with quadratic bending
        ``0.66 lam_max > 2`` and Jacobi / Chebyshev diverged at the first frame. So ``alpha`` is
        lowered to ``1.8 / lam_max`` when needed (reported as ``stats["alpha"]``), and Chebyshev's
        ``rho`` is then measured for that ``alpha``.
        """
        _, lo, hi = jacobi_spectral_radius(self.A, self.alpha)
        alpha = self.alpha if self.alpha * hi <= 1.8 else 1.8 / hi
        self.linear.alpha = alpha
        rho = max(abs(1.0 - alpha * lo), abs(1.0 - alpha * hi))
        if self.linear_name == "chebyshev" and self.rho is None:
            # Lanczos Ritz values lie inside the spectrum, so rho is (slightly) underestimated;
            # Chebyshev tolerates an overestimate better than an underestimate: nudge towards 1
            self.linear.rho = min(0.9999, 1.0 - 0.9 * (1.0 - rho))

    # ------------------------------------------------------------------ step
    def _advance(self, state, dt):
        m, d = self.model, self.device
        self._iterate = state.x
        n = m.num_vertices
        self._scale = 1.0 / (dt * dt)
        self._dt2 = dt * dt
        self._dt = dt
        self.A.mass_scale = self._scale
        for t in self.explicit_terms:
            t.eval(state.x, state.v, self.f_ext, state.time)
        launch(begin_step_kernel, n,
               [state.x, state.v, m.mass, m.inv_mass, wp.vec3(*m.gravity), dt,
                GUESSES[self.initial_guess], self.f_ext, self.x_prev,
                self.x_hat, self.disp], device=d)
        coupling = self._contact()
        if coupling is not None:  # the step's contacts, from the predicted path
            guess = self.initial_guess
            pred = state.x if guess in ("inertial", "auto") else self.x_hat
            coupling.detect(self.x_prev, pred, dt, state.time)
            coupling.mark_free(self._free)
            if guess == "auto":  # a step with contact entries starts from x0 + dt v0
                launch(contact_guess_kernel, n, [self._free, m.inv_mass, state.x, self.disp],
                       device=d)
            # the forces at the guess without contact (b = f(x) + f_ext - M/dt^2 (x - x_hat)):
            # friction's initial guess balances them; a vertex arriving at a surface starts on
            # its contact plane (`friction_guess_kernel`)
            self._assemble(state.x, 0, hessian=False, contact=False)
            coupling.friction_guess(state.x, self.disp, dt, self.b, project=True,
                                    f_ext=None if guess == "inertial" else self.f_ext)
        else:
            self._free.fill_(1)
        if self.line_search and self.initial_guess != "start":
            # (only in a step without contacts, `_free`: a contact's friction guess balances
            # the forces at the inertial guess, and going back toward x0 from there made a
            # sheet stick above its friction angle)
            self._choose_guess(state.x, state.v, dt)
        # a step in contact with steadily moving obstacles: a stall after a short line-search
        # step is checked against the energy seen from their frame
        steady_check = (self.energy_guard and self.line_search and self.tolerance is not None
                        and coupling is not None and self._steady_step())
        steady_more = 0
        self.residuals.zero_()
        self.dx_max.zero_()
        K = self.newton_iterations
        check = self.tolerance is not None
        # the tolerance of this step (`step_tolerances`): tighter at small steps
        tol, step_tol = self.step_tolerances(dt) if check else (None, self.step_tolerance)
        fixed = not check and self.linear.capturable
        inner = 0
        inner_short = 0  # inner solves that stopped at their cap above their tolerance
        fell_back = 0  # Chebyshev inner solves that diverged and finished as Jacobi
        stalled = False  # Newton stopped because an update moved less than step_tolerance
        done = 0
        info = {"residual": float("nan"), "fallback": False}
        trace = [] if self.trace else None
        x = state.x
        measured = False  # residual of the final iterate known?
        residual = float("nan")
        cap = K
        self._steady_now = steady_check  # the guard's energies in the obstacles' frame
        guard = check and self.energy_guard and self._guard_applies()
        guard_ls = check and self.energy_guard and self.line_search
        extended = use_cg = False
        # an impact (`IMPACT_ROUNDS`): the last update's largest move, and the move above which
        # a contact step at its cap goes on
        moved = 0.0
        impact = self._impact_move(coupling) if check else None
        impact_more = 0
        history = []  # the residual of each iterate (host reads of a step with a tolerance)
        converge_more = 0
        for k in range(self._k_total):
            if k >= cap:  # Newton reached its cap above its tolerance
                if (impact is not None and moved > impact and k < K * (1 + IMPACT_ROUNDS)
                        and not extended and (impact_more or not self._free_step())):
                    cap += max(1, K // 4)
                    if impact_more == 0:  # the solve's self-contacts from the path it took
                        coupling.detect_self(self.x_prev, x)
                    impact_more += 1
                elif (check and not extended and not impact_more
                      and _converging(history, tol, K * (1 + CONVERGE_ROUNDS) - k)):
                    cap += max(1, K // 4)
                    converge_more += 1
                elif not guard or self._energy_gain(x, state.v, dt) <= self._guard_eps:
                    break  # (the energy guard, below, goes on while the step gained energy)
                else:
                    cap += max(1, K // 4)
                    extended = True
                    if self._guard_linear is not None and not use_cg:
                        self._restart(x, dt)  # a Jacobi-type solve's iterate: start again, CG
                        use_cg = True
                        cap = k + K * (1 + ENERGY_GUARD_ROUNDS)
            if self.linear_name in ("jacobi", "chebyshev") and self._rho_dt != dt:
                # measured without the contact term: it can only lower the Jacobi iteration's
                # spectral radius (contact_coupling), so the bound holds with any contact set
                blocks, self.A.vertex_blocks = self.A.vertex_blocks, None
                self._assemble(x, k, contact=False)
                self._measure_rho()
                self._rho_dt = dt
                self.A.vertex_blocks = blocks
            self._assemble(x, k)
            if check or trace is not None:
                r = float(self.residuals.numpy()[k])
                history.append(r)
                if trace is not None:
                    trace.append({"F": self.objective(x), "residual": r})
                if check and r < tol and (k > 0 or not self._must_solve(coupling)):
                    residual, measured = r, True
                    break
            if (extended or use_cg) and self._guard_linear is not None:
                info = self._guard_linear.solve(self.A, self.b, self.dx)
                inner += int(info["iterations"])
            elif check and self._self_tol_applies() \
                    and int(self._coupling.self_active.numpy()[0]) > 0:
                # active self-contacts: the tighter relative residual (`self_linear_tolerance`)
                info = self.linear.solve(self.A, self.b, self.dx,
                                         tolerance=self.self_linear_tolerance)
                inner += int(info["iterations"])
            else:
                info = self.linear.solve(self.A, self.b, self.dx)
                inner += self.linear.iterations if fixed else int(info["iterations"])
            if not fixed and not info.get("converged", True):
                inner_short += 1
            if info.get("fallback", False):
                fell_back += 1
            landed = coupling is not None and self.limit_reversals
            if landed:
                if self.line_search and guard_ls:  # kept for the fallback below
                    wp.copy(self._dx_newton, self.dx)
                coupling.limit_reversals(x, self.dx, dt, self._reversals)
            step = self._one
            switched = False
            if self.line_search:
                strict = guard_ls
                self._line_search(x, k, 1.0, strict)
                taken = float(self._ls_taken.numpy()[k]) if strict else 1.0
                if landed and taken == 0.0:
                    # the landings' direction raised F at every length (a landed vertex that
                    # its other forces drive on past its reference, against the springs):
                    # Newton's own direction, which descends
                    wp.copy(self.dx, self._dx_newton)
                    self._line_search(x, k, 1.0, strict)
                    self._guard["unlanded"] += 1
                    taken = float(self._ls_taken.numpy()[k])
                if taken == 0.0:
                    # every step raised F: shorter ones, then (Jacobi / Chebyshev) CG
                    self._line_search(x, k, LS_RETRY, 1)
                    if float(self._ls_taken.numpy()[k]) == 0.0:
                        self._guard["rejected"] += 1
                        if self._guard_linear is not None and not use_cg:
                            use_cg = switched = True
                        elif self._descend(x, k):
                            # the inner solve's direction raised F at every length (far from
                            # the solution with stiff springs, or a CG direction that float32
                            # rounding left non-descending): one preconditioned gradient step
                            self._guard["gradient"] += 1
                            switched = True
                step = self._ls_step
            launch(newton_update_kernel, n,
                   [x, self.dx, step, self.A.free, self.dx_max, k, self.disp],
                   device=d)
            done = k + 1
            if check or trace is not None:
                moved = float(self.dx_max.numpy()[k])
                if trace is not None:
                    trace[-1]["dx"] = moved
                    trace[-1]["step"] = float(step.numpy()[0])
                if (check and moved < step_tol and not switched and steady_check
                        and float(step.numpy()[0]) < LS_STEPS[-1] and k + 1 < self._k_total
                        and self._energy_gain(x, state.v, dt) > self._guard_eps):
                    # the line search's short step, not a converged Newton, moved less than the
                    # step tolerance, while the energy seen from the moving obstacles' steady
                    # frame rose: iterate on (a stop there raised the spinning sphere's frame
                    # energy by 2.0e-4 J in a step, 4.6e-3 m above the tolerance)
                    steady_more += 1
                    cap = max(cap, k + 2)
                    continue
                if check and moved < step_tol and not switched:
                    if (guard and self._guard_linear is not None and not use_cg
                            and self._energy_gain(x, state.v, dt) > self._guard_eps):
                        # a Jacobi-type inner solve stalled while the step gains energy:
                        # start the step again with CG
                        self._restart(x, dt)
                        use_cg = extended = True
                        cap = k + 1 + K * (1 + ENERGY_GUARD_ROUNDS)
                        continue
                    stalled = True
                    break  # stagnated (float32 floor): more iterations cannot lower the residual
        smoothed = 0
        if self._smooth_on and not measured:
            if self._smoother is None:
                self._smoother = VertexSmoother(m, self.A)
            # Newton stopped short of its tolerance (or runs without one): the sweeps remove
            # what it left at short range (`smoothing`); each move lowers F. Not in a step with
            # contact entries (`_free`, read on the device)
            self._smoother.sweep(x, self.disp, self.f_ext, self._scale, self.smoothing_sweeps,
                                 self._free)
            smoothed = self.smoothing_sweeps
        if extended:
            self._guard["extended"] += 1
        # a step with a collision stage but no contact entries measures its whole energy
        free = guard and not measured and (coupling is None
                                           or self._free_step())
        pending = None  # a contact step's gain, counted below unless the step converged
        if guard and not measured and (extended or free):
            gain = self._energy_gain(x, state.v, dt)
            if gain > self._guard_eps:
                if free:
                    if extended:
                        self._guard["gained"] += 1
                    self._clamp_energy(x, state.v, dt, gain)
                else:
                    pending = gain
        lazy = None
        if not measured:
            if check or trace is not None:
                self._assemble(x, done, hessian=False)
                residual = float(self.residuals.numpy()[done])
                if trace is not None:
                    trace.append({"F": self.objective(x), "residual": residual})
            elif self.measure_residual:
                self._assemble(x, done, hessian=False)
                lazy = done
        if pending is not None and not (check and residual < tol):
            # the energy measured leaves contact out: counted, reported, kept. A step that
            # converged (its last update stopped Newton below the step tolerance, the residual
            # then below the tolerance) is implicit Euler's step: what its measure shows is the
            # contact energy it leaves out (the spin scene, frames 137-138: three such steps
            # reported 1.6-1.9e-6 J against the guard's 1.5e-6)
            if extended:
                self._guard["gained"] += 1
            self._guard["new"] += 1
            self._guard["last"] = pending
            self._guard["scale"] = 1.0
        launch(end_step_kernel, n,
               [x, self.x_prev, m.inv_mass, 1.0 / dt, math.exp(-m.damping * dt), state.v,
                self.f_ext, self.disp], device=d)
        if coupling is not None:
            coupling.end_step(x, state.v, dt, state.time)
        self._stats = {"newton_iterations": done, "inner_iterations": inner,
                       "smoothing_sweeps": smoothed,
                       "residual": residual,
                       "converged": bool(check and residual < tol), "linear_residual": info["residual"],
                       "fallback": bool(info.get("fallback", False))}
        self._stats["inner_short"] = inner_short
        self._guard["steady"] += steady_more
        self._guard["impact"] += 1 if impact_more else 0
        self._guard["converge"] += 1 if converge_more else 0
        self._stats["impact_steps"] = self._guard["impact"]
        self._stats["converge_steps"] = self._guard["converge"]
        self._stats["steady_stall_iterations"] = self._guard["steady"]
        if check and not self._stats["converged"]:
            floor = self.residual_floor(dt)
            if residual <= floor:  # as low as float32 positions can show: not short
                self._short["floor"] += 1
                self._short["floor_last"] = (residual, floor, tol)
            else:
                self._short["steps"] += 1
                self._short["new"] += 1
                self._short["last"] = (residual, done, stalled, tol, step_tol)
        if inner_short:
            self._short["inner"] += inner_short
            self._short["inner_new"] += inner_short
        if fell_back:
            self._short["fallback"] += fell_back
            self._short["fallback_new"] += fell_back
        self._stats["unconverged_steps"] = self._short["steps"]
        self._stats["floor_steps"] = self._short["floor"]
        self._stats["energy_guard_steps"] = self._guard["extended"]
        self._stats["energy_gain_steps"] = self._guard["gained"]
        self._stats["energy_clamped_steps"] = self._guard["clamped"]
        self._stats["gradient_steps"] = self._guard["gradient"]
        # iterations whose friction landings raised F at every length: Newton's own direction
        self._stats["unlanded_iterations"] = self._guard["unlanded"]
        self._stats["ls_rejected"] = self._guard["rejected"]
        self._stats["inner_short_total"] = self._short["inner"]
        self._stats["fallbacks_total"] = self._short["fallback"]
        if self.linear_name == "chebyshev":
            self._stats["rho"] = self.linear.rho
        if self.linear_name in ("jacobi", "chebyshev"):
            self._stats["alpha"] = self.linear.alpha
        if trace is not None:
            self._stats["trace"] = trace
        self._lazy = lazy

    def _choose_guess(self, x, v, dt: float) -> None:
        """Start Newton from the lowest F among the inertial guess and the points on the straight
        way back to the step's start ``x0`` (where F is the start's total energy): device-side,
        one line-search pass. When the cloth swings, ``x0 + dt v0`` stretches stiff springs (a
        32 x 32 sheet at k = 1e6 N/m, dt = 1/30 s: F 42-177 J at the inertial guess against
        1.5 J at ``x0``) and Newton spent its iterations coming down from there."""
        n, d = self.model.num_vertices, self.device
        launch(guess_direction_kernel, n, [v, self.disp, self.A.free, dt, self.dx], device=d)
        steps = wp.vec4(*LS_STEPS)
        self._ls_energies(x, steps)
        launch(guess_select_kernel, 1, [self._ls_energy, steps, self._free, self._ls_step],
               device=d)
        launch(newton_update_kernel, n,
               [x, self.dx, self._ls_step, self.A.free, self.dx_max, -1, self.disp], device=d)

    def _descend(self, x, k: int) -> bool:
        """After the inner solve's direction failed the line search: the preconditioned
        gradient direction ``D^-1 b`` into ``dx``, searched the same way (full lengths, then
        `LS_RETRY` times shorter). True if a step was found (``_ls_step`` holds it)."""
        launch(gradient_direction_kernel, self.model.num_vertices,
               [self.b, self.A.diag_inv, self.dx], device=self.device)
        for scale in (1.0, LS_RETRY):
            self._line_search(x, k, scale, 1)
            if float(self._ls_taken.numpy()[k]) > 0.0:
                return True
        return False

    def _clamp_energy(self, x, v, dt: float, gain: float) -> None:
        """The last resort of the energy guard: a step whose end still has more energy than its
        start is shortened toward its start, ``x = x0 + s (x - x0)`` for ``s`` = 1/2, 1/4, ...,
        1/64 and at last 0 (the start at rest: then the energy is the start's potential part,
        never more than the start's total), the first ``s`` that gains nothing is kept.
        Newton short of convergence is not implicit Euler's step and need not dissipate; this
        trades the unconverged step's motion for the guarantee, and is counted
        (``energy_clamped_steps``) and reported by `frame_end`."""
        n, d = self.model.num_vertices, self.device
        g = self._guard
        s = 1.0
        for target in (0.5, 0.25, 0.125, 0.0625, 0.03125, 0.015625, 0.0):
            launch(shorten_step_kernel, n,
                   [x, self.x_prev, v, self.disp, self.A.free, dt, target / s], device=d)
            s = target
            if s == 0.0 or self._energy_gain(x, v, dt) <= self._guard_eps:
                break
        g["clamped"] += 1
        g["new"] += 1
        g["last"] = gain
        g["scale"] = s

    def _restart(self, x, dt: float) -> None:
        m = self.model
        launch(restart_kernel, m.num_vertices,
               [x, self.x_prev, self.x_hat, m.inv_mass, self.f_ext, dt,
                GUESSES[self.initial_guess], self._free, self.disp], device=self.device)

    def _guard_applies(self) -> bool:
        """The energy guard compares the step's end with its start, which only means something
        when nothing outside the cloth does work on it over the step: no scripted pins, and no
        obstacle that moves in this step (`ObstacleContact.still`, set by the step's detection
        before the solve; one host read, in a step that reads its residuals anyway), or one
        whose moving obstacles run in their steady frame in a step with contact, where the
        guard's energies are the ones seen from that frame (`_energy_gain`; 16 x 16 sheet on
        a sphere turning at 3 rad/s, inertial guess: without it 6 frames rose by more than
        2e-5 J in that frame, up to 5.1e-5 J). Measured: with the guard off for a whole scene
        with a moving obstacle, the ``spin`` scene's sheet landing on its sphere, which starts
        turning only at 1 s, gained 5.0e-3 J in a frame."""
        contact = getattr(self.collision, "contact", None)
        if (contact is not None and contact.moving
                and getattr(self.model, "pin_path", None) is None):
            return bool(int(contact.still.numpy()[0])) or self._steady_now
        return not self._outside_work()

    @property
    def _guard_eps(self) -> float:
        """Energy rise the guard tolerates in a step: `GUARD_EPS` of ``M |g|`` times 1 m, at
        least 1e-9 J and `GUARD_KE_REL` of the step's starting kinetic energy (as measured by
        the last `_energy_gain`, which every comparison calls first)."""
        if not hasattr(self, "_eps_cache"):
            mg = float(np.sum(self.model.masses)) * float(np.linalg.norm(self.model.gravity))
            self._eps_cache = max(GUARD_EPS * mg, 1.0e-9)
        return max(self._eps_cache, GUARD_KE_REL * getattr(self, "_ke0", 0.0))

    def _free_step(self) -> bool:
        """This step has no contact entries (`ContactCoupling.mark_free`; a host read)."""
        return int(self._free.numpy()[0]) == 1

    def _impact_move(self, coupling):
        """The largest last Newton update (m) with which a contact step at its cap stops
        (`IMPACT_ROUNDS`): the collision thickness (the self-contacts' where that is smaller);
        None without a collision stage."""
        if coupling is None:
            return None
        stage = coupling.stage
        h = stage.thickness
        sc = getattr(stage, "self_collision", None)
        if sc is not None:
            h = min(h, sc.thickness)
        return float(h)

    def _must_solve(self, coupling) -> bool:
        """A step whose guess left the external forces' step out (`contact_guess_kernel`)
        takes one solve: their step, dt^2 g, can be below the step's tolerance (its 1e-6 m
        floor at small dt), and a cloth at rest would never start to fall. One host read
        (``"auto"``), only when the guess already meets the tolerance."""
        if self.initial_guess == "velocity":
            return True
        return (self.initial_guess == "auto" and coupling is not None
                and not self._free_step())

    def _steady_step(self) -> bool:
        """The step has moving obstacles, and they run in their steady frame (one host read)."""
        contact = getattr(self.collision, "contact", None)
        return bool(contact is not None and contact.moving and contact.frame is not None
                    and int(contact.steady.numpy()[0]))

    def _energy_gain(self, x, v, dt: float, steady: bool | None = None) -> float:
        """Total energy (kinetic, springs, implicit force terms, external forces' potential;
        contact penalties left out: they only rise where contact pushes) at the current
        iterate minus at the start of the step: one host read. ``steady`` (default: this
        step's ``_steady_now``): seen from the moving obstacles' steady frame
        (`common.steady_frame_args`)."""
        m, d, e = self.model, self.device, self._energy
        e.zero_()
        if steady is None:
            steady = self._steady_now
        contact = getattr(self.collision, "contact", None) if steady else None
        flag, u, w, c = steady_frame_args(contact, self._no_int)
        launch(step_energy_kernel, m.num_vertices,
               [x, self.x_prev, v, self.disp, m.mass, m.inv_mass, self.f_ext,
                1.0 / dt, math.exp(-m.damping * dt), e, u, w, c, flag], device=d)
        for j, xc in enumerate((self.x_prev, x)):
            if m.num_springs:
                launch(spring_energy64_kernel, m.num_springs,
                       [xc, m.spring_indices, m.spring_rest_length, m.spring_k, e[j:j + 1]],
                       device=d)
            for t in self.implicit_terms:
                self._energy32.zero_()
                t.energy(xc, self._energy32)
                launch(to_float64_kernel, 1, [self._energy32, e[j:j + 1]], device=d)
        e0, e1, self._ke0 = (float(v) for v in e.numpy())
        return e1 - e0

    def step_tolerances(self, dt: float) -> tuple:
        """``(tolerance, step_tolerance)`` of a step of ``dt`` seconds: ``tolerance`` capped at
        ``max(0.2 |g| dt^2, 1e-6 m)`` (a fifth of the step's gravity displacement), and the step
        tolerance at a tenth of that, never below the float32 floor. At the default 1e-4 m and
        dt = 1/2000 s the fixed tolerance was 40 times ``dt^2 g``: steps stopped almost unsolved
        and soft cloth gained energy (stability map, k = 10 and 1e3 N/m); from dt = 1/140 s up
        nothing changes."""
        g = float(np.linalg.norm(self.model.gravity))
        tol = min(self.tolerance, max(0.2 * g * dt * dt, 1.0e-6))
        return tol, min(self.step_tolerance, max(0.1 * tol, self._float_floor))

    def residual_floor(self, dt: float) -> float:
        """Metres: the largest change of the residual that rounding the positions to float32
        can make, ``1.2e-7 max|x_rest| dt^2 max_i K_i / m_i`` (``K_i``: vertex i's Gershgorin
        stiffness row sum, `SymplecticEuler.stiffness_row_sums`). A step whose residual ends
        between the tolerance and this floor has converged as far as float32 positions can
        show: counted in ``stats["floor_steps"]``, said once a run, not reported as short.
        Measured: the default hanging sheet (32 x 32, 1000 N/m, dt = 1/120 s) has a floor of
        1.0e-3 m against the 1e-4 m tolerance; 58 of its 118 steps ended at residuals of
        1.0e-4 to 2.8e-4 m, each warned about as unconverged before."""
        return self._floor_per_dt2 * float(dt) * float(dt)

    def _frame_messages(self) -> list:
        """Unconverged steps and inner solves since the last call (`Solver.frame_end`)."""
        out = []
        sh = self._short
        if sh["floor"] and not sh["floor_told"]:
            sh["floor_told"] = True
            r, floor, tol = sh["floor_last"]
            out.append(Note(f"implicit: the residual's float32 floor ({floor:.2g} m at this step) is "
                       f"above the tolerance {tol:.3g} m; steps that end between them (residual "
                       f"{r:.3g} m here) are as converged as float32 positions can show: "
                       "counted in stats['floor_steps'], not reported again"))
        if sh["new"]:
            r, k, stalled, tol, step_tol = sh["last"]
            why = (f"its updates fell below step_tolerance {step_tol:.2g} m" if stalled
                   else f"{k} iterations, the cap")
            out.append(f"implicit: Newton stopped above its tolerance {tol:.3g} m in "
                       f"{sh['new']} step(s) (last: residual {r:.3g} m; {why})")
        if sh["inner_new"]:
            out.append(f"implicit: {sh['inner_new']} {self.linear_name} inner solve(s) stopped at "
                       f"{self.linear.iterations} iterations above their tolerance")
        if sh["fallback_new"]:
            out.append(f"implicit: {sh['fallback_new']} chebyshev inner solve(s) diverged "
                       "(residual rising) and finished as plain Jacobi from their best iterate "
                       "(its rho does not fit the Newton matrix: set rho, or use cg)")
        sh["new"] = sh["inner_new"] = sh["fallback_new"] = 0
        if self.linear_name == "cholesky":
            n = self.linear.fallbacks
            new, self._fallbacks_seen = n - self._fallbacks_seen, n
            if new > 0:
                out.append(f"implicit: {new} cholesky preconditioner application(s) fell back to "
                           "block Jacobi: a Newton matrix had no Cholesky factor (not positive "
                           "definite: exact_hessian=True under compression)")
        g = self._guard
        if g["new"]:
            if g["scale"] < 1.0:
                out.append(f"implicit: {g['new']} step(s) would have gained energy after Newton "
                           f"stopped short (last: {g['last']:.3g} J); shortened toward the "
                           f"step's start to gain none (last kept {g['scale']:.3g} of the step)")
            else:
                out.append(f"implicit: {g['new']} step(s) still gained energy after "
                           f"{self._k_total} Newton iterations (the energy guard's cap; last "
                           f"{g['last']:.3g} J, contact energy not counted)")
            g["new"] = 0
        return out

    def newton_system(self, state, dt: float):
        """Begin a step on ``state`` and assemble its first Newton system (for benchmarks/tests).

        Mutates ``state`` like the start of `step` (free vertices move to the initial guess;
        the pins are not moved) and returns ``(A, b)``: the operator ``M/dt^2 + H(x^(0))`` and
        ``-grad F(x^(0))``. Solve with any `warp_cloth.solvers.linear` solver.
        """
        m = self.model
        self._iterate = state.x
        self._scale, self._dt2, self._dt = 1.0 / (dt * dt), dt * dt, dt
        self.A.mass_scale = self._scale
        self.f_ext.zero_()
        for t in self.explicit_terms:
            t.eval(state.x, state.v, self.f_ext, state.time)
        launch(begin_step_kernel, m.num_vertices,
               [state.x, state.v, m.mass, m.inv_mass, wp.vec3(*m.gravity), dt,
                GUESSES[self.initial_guess], self.f_ext, self.x_prev,
                self.x_hat, self.disp], device=self.device)
        self.residuals.zero_()
        self._assemble(state.x, 0)
        return self.A, self.b

    def _line_search(self, x, k: int, scale: float = 1.0, reject: int = 0) -> None:
        """Device line search along ``dx`` (`ls_vertex_kernel`, `ls_spring_kernel`, the force
        terms' and the contact term's energies at ``x`` and at the candidates,
        `ls_select_kernel`): the chosen step goes to ``_ls_step`` (and ``_ls_taken[k]``)."""
        steps = wp.vec4(*(scale * a for a in LS_STEPS))
        self._ls_energies(x, steps)
        launch(ls_select_kernel, 1, [self._ls_energy, steps, LS_ARMIJO, self._ls_step, k,
                                     self._ls_taken, int(reject)],
               device=self.device)

    def _ls_energies(self, x, steps) -> None:
        """F at ``x`` and at ``x + a_j dx`` (``a_j`` the components of ``steps``) into
        ``_ls_energy`` (slots 0 and j + 1), float64, on the device."""
        m, d, n = self.model, self.device, self.model.num_vertices
        E = self._ls_energy
        E.zero_()
        launch(ls_vertex_kernel, n,
               [x, self.dx, self.disp, self.b, m.mass, self.A.free, self.f_ext, self._scale,
                steps, self._ls_try, E], device=d)
        if m.num_springs:
            launch(ls_spring_kernel, m.num_springs,
                   [x, self._ls_try, m.spring_indices, m.spring_rest_length, m.spring_k, E],
                   device=d)
        configs = [x] + [self._ls_try[j] for j in range(len(LS_STEPS))]
        if self.implicit_terms:
            self._ls_energy32.zero_()
            for t in self.implicit_terms:
                if hasattr(t, "energy_configs"):  # every configuration in one launch
                    t.energy_configs(x, self._ls_try, self._ls_energy32)
                    continue
                for j, xc in enumerate(configs):
                    t.energy(xc, self._ls_views[j])
            launch(add_float32_kernel, len(configs), [self._ls_energy32, E], device=d)
        if self._coupling is not None and self.collision is not None:
            self._coupling.energy_line(x, self.dx, self.A.free, steps, E, self._dt)

    def describe(self) -> str:
        it = f"{self.newton_iterations} Newton"
        sw = f", {self.smoothing_sweeps} sweeps" if self._smooth_on else ""
        return f"implicit ({it}, {self.linear_name}{sw})"
