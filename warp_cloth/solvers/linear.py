"""Inner linear solvers for ``A x = b`` with one ``vec3`` unknown per vertex (``physics.md`` 2.4).

All three solvers are matrix-free and share one interface::

    solver = make_linear_solver("cg" | "jacobi" | "chebyshev", **options)
    info = solver.solve(A, b, x)        # x: initial guess in, solution out (warm start)

``A`` is any operator with

- ``n``, ``device``;
- ``matvec(x, out)``: ``out = A x`` (the operator clears ``out`` itself);
- ``diag_inv``: ``wp.array(dtype=wp.mat33)``, the inverse 3x3 diagonal blocks of ``A``, and
  *zero blocks for eliminated (pinned) vertices*;
- ``free``: ``wp.array(dtype=float)``, 1 for free vertices, 0 for eliminated ones.

Pinned vertices are eliminated (reduced coordinates, ``physics.md`` 2.15): the solvers never
change their entries of ``x`` (which the caller keeps at 0 for an increment), and residual norms
are taken over free vertices only. That is the notes' ``K A K^T x_f = K b`` without building K.

- **Jacobi** (block-diagonal, relaxed by ``alpha``): ``x <- x + alpha D^-1 (b - A x)``.
  Converges for any s.p.d. A when ``alpha`` is small enough (L1000-1001).
- **Chebyshev-Jacobi** (Wang 2015, the notes' L1023-1041): the Jacobi iterate is blended with the
  one before it, ``x <- omega (x + alpha D^-1 r) + (1 - omega) x_prev`` with the omega recurrence
  from the estimated spectral radius ``rho`` of the Jacobi iteration, after ``delay`` plain
  iterations. `estimate_spectral_radius` measures rho for an operator. An overestimated rho
  diverges: when residual checks are on (``tolerance`` or ``check_every``) a growing residual
  restores the iterate of the last check and finishes with plain Jacobi (``info["fallback"]``).
- **CG** with the block-Jacobi preconditioner. Scalars (``r.z``, ``p.Ap``) stay on the device, so
  with a fixed iteration count a solve makes no host read and can be captured in a Warp graph.

``tolerance`` is on the relative residual ``||b - A x|| / ||b||`` (free vertices). With
``tolerance=None`` a solver runs exactly ``iterations`` iterations and reads nothing back
(capturable); otherwise it checks every ``check_every`` iterations (one small host read each).
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..util import launch, stride_threads

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile

__all__ = [
    "JacobiSolver", "ChebyshevSolver", "CGSolver", "make_linear_solver", "SpringSystemOperator",
    "estimate_spectral_radius", "dense_matrix", "LINEAR_SOLVERS",
]


# ----------------------------------------------------------------------------------- kernels
@wp.func
def _cg_beta(rz: wp.array(dtype=wp.float64), k: int):
    beta = float(0.0)
    if k > 0:
        if rz[k - 1] > wp.float64(0.0):
            beta = float(rz[k] / rz[k - 1])
    return beta


@wp.func
def _cg_direction_row(i: int, k: int, beta: float, zi: wp.vec3, azi: wp.vec3,
                      free: wp.array(dtype=float), p: wp.array(dtype=wp.vec3),
                      ap: wp.array(dtype=wp.vec3)):
    """Row ``i`` of CG's direction: ``p = z + beta p``, ``Ap = A z + beta Ap`` (``zi``,
    ``azi``: row ``i`` of ``z`` and ``A z``; ``beta`` unused at ``k = 0``); returns its share
    of ``p . Ap`` (free vertices)."""
    pi = zi
    api = azi
    if k > 0:
        pi = pi + beta * p[i]
        api = api + beta * ap[i]
    p[i] = pi
    ap[i] = api
    return wp.float64(wp.dot(pi, api) * free[i])


@wp.kernel
def _residual_kernel(b: wp.array(dtype=wp.vec3), ax: wp.array(dtype=wp.vec3),
                     free: wp.array(dtype=float), r: wp.array(dtype=wp.vec3),
                     sums: wp.array(dtype=wp.float64), slot: int, num_threads: int):
    """r = b - Ax (free vertices); sums[slot] += r.r. Each thread strides over the vertices
    and adds its total once (`util.stride_threads`), as do the kernels below."""
    t = wp.tid()
    acc = wp.float64(0.0)
    for i in range(t, b.shape[0], num_threads):
        ri = (b[i] - ax[i]) * free[i]
        r[i] = ri
        acc += wp.float64(wp.dot(ri, ri))
    wp.atomic_add(sums, slot, acc)


@wp.kernel
def _norm2_kernel(b: wp.array(dtype=wp.vec3), free: wp.array(dtype=float),
                  sums: wp.array(dtype=wp.float64), slot: int, num_threads: int):
    t = wp.tid()
    acc = wp.float64(0.0)
    for i in range(t, b.shape[0], num_threads):
        bi = b[i] * free[i]
        acc += wp.float64(wp.dot(bi, bi))
    wp.atomic_add(sums, slot, acc)


@wp.kernel
def _jacobi_update_kernel(x: wp.array(dtype=wp.vec3), last: wp.array(dtype=wp.vec3),
                          b: wp.array(dtype=wp.vec3), ax: wp.array(dtype=wp.vec3),
                          dinv: wp.array(dtype=wp.mat33), free: wp.array(dtype=float),
                          alpha: float, omega: float, sums: wp.array(dtype=wp.float64), slot: int,
                          num_threads: int):
    """r = b - Ax; x_new = omega (x + alpha D^-1 r) + (1 - omega) last; last = x."""
    t = wp.tid()
    acc = wp.float64(0.0)
    for i in range(t, x.shape[0], num_threads):
        r = (b[i] - ax[i]) * free[i]
        acc += wp.float64(wp.dot(r, r))
        xi = x[i]
        xn = xi + alpha * (dinv[i] * r)
        if omega != 1.0:
            xn = omega * xn + (1.0 - omega) * last[i]
        last[i] = xi
        x[i] = xn
    wp.atomic_add(sums, slot, acc)


@wp.kernel
def _cg_start_kernel(b: wp.array(dtype=wp.vec3), ax: wp.array(dtype=wp.vec3),
                     free: wp.array(dtype=float), dinv: wp.array(dtype=wp.mat33),
                     r: wp.array(dtype=wp.vec3), z: wp.array(dtype=wp.vec3),
                     rz: wp.array(dtype=wp.float64), bnorm: wp.array(dtype=wp.float64),
                     num_threads: int):
    """r = b - A x (free vertices), z = D^-1 r, rz_0 = r.z, bnorm = |b|^2 (free vertices)."""
    t = wp.tid()
    s_rz = wp.float64(0.0)
    s_bb = wp.float64(0.0)
    for i in range(t, b.shape[0], num_threads):
        fi = free[i]
        bi = b[i] * fi
        ri = (b[i] - ax[i]) * fi
        zi = dinv[i] * ri
        r[i] = ri
        z[i] = zi
        s_rz += wp.float64(wp.dot(ri, zi))
        s_bb += wp.float64(wp.dot(bi, bi))
    wp.atomic_add(rz, 0, s_rz)
    wp.atomic_add(bnorm, 0, s_bb)


@wp.kernel
def _cg_update_kernel(x: wp.array(dtype=wp.vec3), r: wp.array(dtype=wp.vec3),
                      z: wp.array(dtype=wp.vec3), p: wp.array(dtype=wp.vec3),
                      ap: wp.array(dtype=wp.vec3), dinv: wp.array(dtype=wp.mat33),
                      free: wp.array(dtype=float), rz: wp.array(dtype=wp.float64),
                      pap: wp.array(dtype=wp.float64), rr: wp.array(dtype=wp.float64), k: int,
                      num_threads: int):
    """alpha = rz_k / pAp_k; x += alpha p; r -= alpha Ap; z = D^-1 r; rz_{k+1} = r.z; rr_k = r.r."""
    t = wp.tid()
    alpha = wp.float64(0.0)
    if pap[k] > wp.float64(0.0):
        alpha = rz[k] / pap[k]
    a = float(alpha)
    s_rz = wp.float64(0.0)
    s_rr = wp.float64(0.0)
    for i in range(t, x.shape[0], num_threads):
        x[i] = x[i] + a * p[i]
        ri = (r[i] - a * ap[i]) * free[i]
        r[i] = ri
        zi = dinv[i] * ri
        z[i] = zi
        s_rz += wp.float64(wp.dot(ri, zi))
        s_rr += wp.float64(wp.dot(ri, ri))
    wp.atomic_add(rz, k + 1, s_rz)
    wp.atomic_add(rr, k, s_rr)


@wp.kernel
def _cg_direction_kernel(z: wp.array(dtype=wp.vec3), az: wp.array(dtype=wp.vec3),
                         free: wp.array(dtype=float), p: wp.array(dtype=wp.vec3),
                         ap: wp.array(dtype=wp.vec3), rz: wp.array(dtype=wp.float64),
                         pap: wp.array(dtype=wp.float64), k: int, num_threads: int):
    """beta = rz_k / rz_{k-1} (0 at k = 0); p = z + beta p; Ap = A z + beta Ap; pAp_k = p . Ap."""
    t = wp.tid()
    beta = _cg_beta(rz, k)
    acc = wp.float64(0.0)
    for i in range(t, z.shape[0], num_threads):
        acc += _cg_direction_row(i, k, beta, z[i], az[i], free, p, ap)
    wp.atomic_add(pap, k, acc)


@wp.kernel
def _unit_fill_kernel(free: wp.array(dtype=float), k: int, out: wp.array(dtype=wp.vec3)):
    """``out_i = free_i e_k``: the translation of the free vertices along axis ``k``."""
    i = wp.tid()
    e = wp.vec3(0.0)
    e[k] = free[i]
    out[i] = e


@wp.kernel
def _sum_rows_kernel(v: wp.array(dtype=wp.vec3), free: wp.array(dtype=float),
                     out: wp.array(dtype=wp.float64), first: int, num_threads: int):
    """``out[first:first + 3] += sum_i free_i v_i`` (float64)."""
    t = wp.tid()
    acc = wp.vec3d()
    for i in range(t, v.shape[0], num_threads):
        f = free[i]
        if f != 0.0:
            vi = v[i]
            acc = acc + wp.vec3d(wp.float64(f * vi[0]), wp.float64(f * vi[1]),
                                 wp.float64(f * vi[2]))
    for j in range(3):
        wp.atomic_add(out, first + j, acc[j])


@wp.kernel
def _translate_kernel(x: wp.array(dtype=wp.vec3), free: wp.array(dtype=float),
                      sums: wp.array(dtype=wp.float64)):
    """``x_i += free_i delta`` with ``C delta = s``: ``C = P^T A P`` (columns in ``sums[0:9]``)
    and ``s = P^T r`` (``sums[9:12]``), P the free vertices' translations."""
    i = wp.tid()
    C = wp.mat33d(sums[0], sums[3], sums[6], sums[1], sums[4], sums[7], sums[2], sums[5],
                  sums[8])
    s = wp.vec3d(sums[9], sums[10], sums[11])
    det = wp.determinant(C)
    if det == wp.float64(0.0):
        return
    d = wp.inverse(C) * s
    x[i] = x[i] + free[i] * wp.vec3(float(d[0]), float(d[1]), float(d[2]))


# ----------------------------------------------------------------------------------- solvers
class _Base:
    name = "base"

    def __init__(self, iterations: int = 100, tolerance: float | None = 1e-4,
                 check_every: int | None = None):
        if int(iterations) != iterations or iterations < 1:
            raise ValueError(f"{self.name}: iterations must be a positive integer, got {iterations}")
        if tolerance is not None and not (tolerance > 0 and math.isfinite(tolerance)):
            raise ValueError(f"{self.name}: tolerance must be > 0 or None, got {tolerance}")
        if check_every is not None and (int(check_every) != check_every or check_every < 1):
            raise ValueError(f"{self.name}: check_every must be a positive integer")
        self.iterations = int(iterations)
        self.tolerance = tolerance
        self.check_every = check_every if check_every is not None else (
            None if tolerance is None else 1)
        self._n = None

    @property
    def capturable(self) -> bool:
        """True when a solve makes no host read (fixed iterations, no checks)."""
        return self.tolerance is None and self.check_every is None

    def _alloc(self, A):
        if self._n == A.n and self._device == A.device:
            return
        n, d = A.n, A.device
        self._n, self._device = n, d
        self.threads = stride_threads(n, d)  # the per-vertex kernels' (`util.stride_threads`)
        self.ax = wp.zeros(n, dtype=wp.vec3, device=d)
        self.r = wp.zeros(n, dtype=wp.vec3, device=d)
        self.z = wp.zeros(n, dtype=wp.vec3, device=d)
        self.p = wp.zeros(n, dtype=wp.vec3, device=d)
        self.last = wp.zeros(n, dtype=wp.vec3, device=d)
        self.ap = wp.zeros(n, dtype=wp.vec3, device=d)
        self.saved = wp.zeros(n, dtype=wp.vec3, device=d)
        m = self.iterations + 2
        self.s1 = wp.zeros(m, dtype=wp.float64, device=d)
        self.s2 = wp.zeros(m, dtype=wp.float64, device=d)
        self.s3 = wp.zeros(m, dtype=wp.float64, device=d)
        self.bnorm = wp.zeros(1, dtype=wp.float64, device=d)
        self.tsums = wp.zeros(12, dtype=wp.float64, device=d)  # `_translation_correction`

    def _translation_correction(self, A, x, r) -> None:
        """The residual's net force taken out by a translation of every free vertex: ``x +=
        P (P^T A P)^-1 P^T r`` with ``P`` the free vertices' rigid translations (a Galerkin
        correction on that three-dimensional space; three products with ``A``, no host read).
        An inner solve stopped early leaves a residual whose sum over the vertices is a force
        that no spring or contact exerts: internal forces sum to zero and so do the rows of
        their Hessians. Newton with CG stopped at a relative residual of 0.1 made the folded
        sheet on the floor slide off sideways, faster every frame (implicit Euler, 20 x 20
        fold: 0.95 m/s after 45 frames and 0.07 J gained; `CGSolver` ``translation``). After
        it the step changes the cloth's momentum only as its linearised forces do."""
        # after the iterations ``z`` and ``ax`` are free to hold the translations and their
        # products (allocated with the solver's arrays: nothing allocated inside a step)
        d, n, th = A.device, A.n, self.threads
        self.tsums.zero_()
        for k in range(3):
            launch(_unit_fill_kernel, n, [A.free, k, self.z], device=d)
            A.matvec(self.z, self.ax)
            launch(_sum_rows_kernel, th, [self.ax, A.free, self.tsums, 3 * k, th], device=d)
        launch(_sum_rows_kernel, th, [r, A.free, self.tsums, 9, th], device=d)
        launch(_translate_kernel, n, [x, A.free, self.tsums], device=d)

    def _bnorm2(self, A, b):
        self.bnorm.zero_()
        th = self.threads
        launch(_norm2_kernel, th, [b, A.free, self.bnorm, 0, th], device=A.device)

    def solve(self, A, b, x, iterations: int | None = None, tolerance=..., ) -> dict:
        """Solve ``A x = b`` starting from ``x`` (updated in place). Returns
        ``{"iterations", "residual" (relative, nan when not measured), "converged", ...}``."""
        raise NotImplementedError


class JacobiSolver(_Base):
    """Block-Jacobi with relaxation ``alpha`` (and, in the subclass, Chebyshev acceleration)."""

    name = "jacobi"

    def __init__(self, iterations: int = 100, tolerance: float | None = 1e-4, alpha: float = 0.66,
                 check_every: int | None = None):
        super().__init__(iterations, tolerance, check_every)
        if not (0 < alpha <= 2):
            raise ValueError(f"{self.name}: alpha must be in (0, 2], got {alpha}")
        self.alpha = float(alpha)

    def _omegas(self, iters):
        return [1.0] * iters

    def solve(self, A, b, x, iterations=None, tolerance=...):
        self._alloc(A)
        iters = self.iterations if iterations is None else int(iterations)
        tol = self.tolerance if tolerance is ... else tolerance
        check = self.check_every if (tolerance is ... or tol is None) else (self.check_every or 1)
        if iters + 2 > self.s1.shape[0]:
            self.s1 = wp.zeros(iters + 2, dtype=wp.float64, device=A.device)
        d, th = A.device, self.threads
        sums = self.s1
        sums.zero_()
        wp.copy(self.last, x)
        omegas = self._omegas(iters)
        bn = None
        if check is not None:
            self._bnorm2(A, b)
            bn = math.sqrt(float(self.bnorm.numpy()[0])) or 1.0
            wp.copy(self.saved, x)
        best = math.inf
        fallback = converged = False
        done = iters
        res = float("nan")
        k = 0
        while k < iters:
            A.matvec(x, self.ax)
            om = 1.0 if fallback else omegas[k]
            launch(_jacobi_update_kernel, th,
                   [x, self.last, b, self.ax, A.diag_inv, A.free, self.alpha, om, sums, k, th],
                   device=d)
            k += 1
            if check is not None and (k % check == 0 or k == iters):
                # sums[k-1] holds ||r||^2 of the iterate BEFORE update k
                rel = math.sqrt(float(sums.numpy()[k - 1])) / bn
                if not math.isfinite(rel) or rel > 4.0 * best:
                    if not fallback and om != 1.0 or not math.isfinite(rel):
                        wp.copy(x, self.saved)  # back to the last good iterate
                        wp.copy(self.last, x)
                        fallback = True
                        continue
                if rel < best:
                    best = rel
                    wp.copy(self.saved, self.last)  # the iterate whose residual is rel
                res = rel
                if tol is not None and rel < tol:
                    done, converged = k, True
                    break
        if check is not None:
            # residual of the final iterate
            A.matvec(x, self.ax)
            tmp = self.s2
            tmp.zero_()
            launch(_residual_kernel, th, [b, self.ax, A.free, self.r, tmp, 0, th], device=d)
            res = math.sqrt(float(tmp.numpy()[0])) / bn
        return {"iterations": done, "residual": res,
                "converged": converged or (tol is not None and res < tol), "fallback": fallback}


class ChebyshevSolver(JacobiSolver):
    """Chebyshev-accelerated block Jacobi (Wang 2015; notes L1023-1041).

    Args:
        rho: estimated spectral radius of the Jacobi iteration matrix ``I - alpha D^-1 A``
            (< 1). Too large diverges (caught when checks are on), too small accelerates less;
            `estimate_spectral_radius` measures it.
        delay: plain Jacobi iterations before the acceleration starts (Wang uses about 10).
        alpha: Jacobi relaxation.
    """

    name = "chebyshev"

    def __init__(self, iterations: int = 100, tolerance: float | None = 1e-4, alpha: float = 0.66,
                 rho: float = 0.99, delay: int = 5, check_every: int | None = None):
        super().__init__(iterations, tolerance, alpha, check_every)
        if not (0 <= rho < 1):
            raise ValueError(f"chebyshev: rho must be in [0, 1), got {rho}")
        if int(delay) != delay or delay < 0:
            raise ValueError(f"chebyshev: delay must be an integer >= 0, got {delay}")
        self.rho, self.delay = float(rho), int(delay)

    def _omegas(self, iters):
        out, om = [], 1.0
        for k in range(iters):
            j = k - self.delay
            if j < 0 or j == 0:
                om = 1.0
            elif j == 1:
                om = 2.0 / (2.0 - self.rho ** 2)
            else:
                om = 4.0 / (4.0 - self.rho ** 2 * om)
            out.append(om)
        return out


class CGSolver(_Base):
    """Conjugate gradient with the block-Jacobi preconditioner. Needs an s.p.d. A (use the
    definiteness fix for springs).

    Two launches per iteration when the operator offers ``cg_direction`` (`SpringSystemOperator`
    without extra terms): (1) ``p = z + beta p``, ``Ap = A z + beta Ap`` and ``p.Ap`` in one
    gather kernel (``A p`` by linearity from ``A z``, so the direction needs no launch of its
    own), (2) ``x += alpha p``, ``r -= alpha Ap``, ``z = D^-1 r``, ``r.z``, ``r.r``. Otherwise
    the operator's ``matvec`` of ``z`` replaces the fused matvec (its launches + 2)."""

    name = "cg"
    #: end a solve with `_translation_correction` (the residual's net force removed) when the
    #: operator has a ``translation_gate`` (a device int array) that is non-zero: implicit
    #: Euler's Newton operator in iterations with active self-contacts
    translation = True

    def _prepare(self, A) -> None:
        """Before a solve (a preconditioner's set-up: `band.CholeskyCGSolver`); none here."""

    def _precondition(self, A, rz, slot: int) -> None:
        """``z`` from ``r`` and ``rz[slot] = r . z`` when the preconditioner is not the block
        Jacobi that the start and update kernels apply (`band.CholeskyCGSolver`); none here."""

    def setup(self, A) -> None:
        """The work arrays and the preconditioner for ``A`` (host work and allocations): done
        by the first `solve`, or beforehand, outside a recorded graph."""
        self._alloc(A)
        self._prepare(A)

    def solve(self, A, b, x, iterations=None, tolerance=...):
        self.setup(A)
        iters = self.iterations if iterations is None else int(iterations)
        tol = self.tolerance if tolerance is ... else tolerance
        check = self.check_every if (tolerance is ... or tol is None) else (self.check_every or 1)
        if iters + 2 > self.s1.shape[0]:
            for name in ("s1", "s2", "s3"):
                setattr(self, name, wp.zeros(iters + 2, dtype=wp.float64, device=A.device))
        d, n = A.device, A.n
        rz, pap, rr = self.s1, self.s2, self.s3
        rz.zero_(), pap.zero_(), rr.zero_(), self.bnorm.zero_()
        A.matvec(x, self.ax)
        th = self.threads
        launch(_cg_start_kernel, th,
               [b, self.ax, A.free, A.diag_inv, self.r, self.z, rz, self.bnorm, th], device=d)
        self._precondition(A, rz, 0)
        fused = getattr(A, "cg_direction", None)
        bn = None
        if check is not None:
            bn = math.sqrt(float(self.bnorm.numpy()[0])) or 1.0
        done, res = iters, float("nan")
        for k in range(iters):
            if fused is None or not fused(self.z, self.p, self.ap, rz, pap, k):
                A.matvec(self.z, self.ax)
                launch(_cg_direction_kernel, th,
                       [self.z, self.ax, A.free, self.p, self.ap, rz, pap, k, th], device=d)
            launch(_cg_update_kernel, th,
                   [x, self.r, self.z, self.p, self.ap, A.diag_inv, A.free, rz, pap, rr, k, th],
                   device=d)
            if k + 1 < iters or check is not None:  # (the last z is never used)
                self._precondition(A, rz, k + 1)
            if check is not None and ((k + 1) % check == 0 or k + 1 == iters):
                res = math.sqrt(float(rr.numpy()[k])) / bn
                if tol is not None and res < tol:
                    done = k + 1
                    break
        # the operator's device count that asks for the translation correction (non-zero:
        # run it; a conditional node when recorded, no host read); none: never
        gate = getattr(A, "translation_gate", None)
        if self.translation and gate is not None:
            wp.capture_if(gate, self._translation_correction, A=A, x=x, r=self.r)
        return {"iterations": done, "residual": res,
                "converged": tol is not None and res < tol, "fallback": False}


LINEAR_SOLVERS = {"jacobi": JacobiSolver, "chebyshev": ChebyshevSolver, "cg": CGSolver}


def make_linear_solver(name: str, **options):
    """Build ``"jacobi"``, ``"chebyshev"`` or ``"cg"`` with its keyword options (and
    ``"cholesky"``, `band.CholeskyCGSolver`, for implicit Euler's operator)."""
    if name == "cholesky":
        from .band import CholeskyCGSolver

        return CholeskyCGSolver(**options)
    if name not in LINEAR_SOLVERS:
        raise ValueError(f"unknown linear solver {name!r}; choose one of {sorted(LINEAR_SOLVERS)}")
    return LINEAR_SOLVERS[name](**options)


# ----------------------------------------------------------------------------------- operator
@wp.func
def spring_block_apply(c: wp.vec4, u: wp.vec3):
    """``H_e u`` for the compact block ``c = (g, beta)``: ``H_e = g g^T + beta I``."""
    g = wp.vec3(c[0], c[1], c[2])
    return wp.dot(g, u) * g + c[3] * u


@wp.func
def spring_block_matrix(c: wp.vec4):
    g = wp.vec3(c[0], c[1], c[2])
    return wp.outer(g, g) + c[3] * wp.identity(n=3, dtype=float)


@wp.func
def spring_row_apply(x: wp.array(dtype=wp.vec3), i: int, scale: float, mass: wp.array(dtype=float),
                     offsets: wp.array(dtype=wp.int32), other: wp.array(dtype=wp.int32),
                     coef: wp.array(dtype=wp.vec4), s_offsets: wp.array(dtype=wp.int32),
                     s_cols: wp.array(dtype=wp.int32), s_vals: wp.array(dtype=float)):
    """Row i of ``A x``: mass and springs, ``s m_i x_i + sum_{e=(i,j)} H_e (x_i - x_j)``, plus
    the folded constant scalar rows ``sum_j S_ij x_j`` (`SpringSystemOperator`; none: empty
    rows)."""
    xi = x[i]
    acc = (scale * mass[i]) * xi
    for q in range(offsets[i], offsets[i + 1]):
        acc = acc + spring_block_apply(coef[q], xi - x[other[q]])
    for q in range(s_offsets[i], s_offsets[i + 1]):
        acc = acc + s_vals[q] * x[s_cols[q]]
    return acc


@wp.kernel
def _spring_matvec_kernel(x: wp.array(dtype=wp.vec3), mass: wp.array(dtype=float), scale: float,
                          offsets: wp.array(dtype=wp.int32), other: wp.array(dtype=wp.int32),
                          coef: wp.array(dtype=wp.vec4), s_offsets: wp.array(dtype=wp.int32),
                          s_cols: wp.array(dtype=wp.int32), s_vals: wp.array(dtype=float),
                          out: wp.array(dtype=wp.vec3)):
    """out = A x (mass + springs + folded rows), one thread per vertex gathering its CSR rows
    (no atomics)."""
    i = wp.tid()
    out[i] = spring_row_apply(x, i, scale, mass, offsets, other, coef, s_offsets, s_cols, s_vals)


@wp.kernel
def _spring_cg_direction_kernel(z: wp.array(dtype=wp.vec3), mass: wp.array(dtype=float),
                                scale: float, offsets: wp.array(dtype=wp.int32),
                                other: wp.array(dtype=wp.int32), coef: wp.array(dtype=wp.vec4),
                                s_offsets: wp.array(dtype=wp.int32),
                                s_cols: wp.array(dtype=wp.int32), s_vals: wp.array(dtype=float),
                                free: wp.array(dtype=float), p: wp.array(dtype=wp.vec3),
                                ap: wp.array(dtype=wp.vec3), rz: wp.array(dtype=wp.float64),
                                pap: wp.array(dtype=wp.float64), k: int, num_threads: int):
    """CG direction with its matvec fused: beta = rz_k / rz_{k-1} (0 at k = 0);
    p = z + beta p; Ap = A z + beta Ap (A p by linearity, so p need not be complete before the
    matvec); pAp_k = p . Ap (free vertices)."""
    t = wp.tid()
    beta = _cg_beta(rz, k)
    acc = wp.float64(0.0)
    for i in range(t, z.shape[0], num_threads):
        azi = spring_row_apply(z, i, scale, mass, offsets, other, coef, s_offsets, s_cols,
                               s_vals)
        acc += _cg_direction_row(i, k, beta, z[i], azi, free, p, ap)
    wp.atomic_add(pap, k, acc)


@wp.kernel
def _spring_matvec_vb_kernel(x: wp.array(dtype=wp.vec3), mass: wp.array(dtype=float),
                             scale: float, offsets: wp.array(dtype=wp.int32),
                             other: wp.array(dtype=wp.int32), coef: wp.array(dtype=wp.vec4),
                             s_offsets: wp.array(dtype=wp.int32), s_cols: wp.array(dtype=wp.int32),
                             s_vals: wp.array(dtype=float), vblock: wp.array(dtype=wp.mat33),
                             out: wp.array(dtype=wp.vec3)):
    """`_spring_matvec_kernel` plus a per-vertex block (the contact term's Hessian)."""
    i = wp.tid()
    out[i] = (spring_row_apply(x, i, scale, mass, offsets, other, coef, s_offsets, s_cols, s_vals)
              + vblock[i] * x[i])


@wp.kernel
def _spring_cg_direction_vb_kernel(z: wp.array(dtype=wp.vec3), mass: wp.array(dtype=float),
                                   scale: float, offsets: wp.array(dtype=wp.int32),
                                   other: wp.array(dtype=wp.int32),
                                   coef: wp.array(dtype=wp.vec4),
                                   s_offsets: wp.array(dtype=wp.int32),
                                   s_cols: wp.array(dtype=wp.int32), s_vals: wp.array(dtype=float),
                                   vblock: wp.array(dtype=wp.mat33),
                                   free: wp.array(dtype=float), p: wp.array(dtype=wp.vec3),
                                   ap: wp.array(dtype=wp.vec3), rz: wp.array(dtype=wp.float64),
                                   pap: wp.array(dtype=wp.float64), k: int, num_threads: int):
    """`_spring_cg_direction_kernel` plus a per-vertex block (the contact term's Hessian)."""
    t = wp.tid()
    beta = _cg_beta(rz, k)
    acc = wp.float64(0.0)
    for i in range(t, z.shape[0], num_threads):
        zi = z[i]
        azi = (spring_row_apply(z, i, scale, mass, offsets, other, coef, s_offsets, s_cols,
                                s_vals) + vblock[i] * zi)
        acc += _cg_direction_row(i, k, beta, zi, azi, free, p, ap)
    wp.atomic_add(pap, k, acc)


@wp.kernel
def _diag_init_kernel(mass: wp.array(dtype=float), scale: float, diag: wp.array(dtype=wp.mat33)):
    i = wp.tid()
    diag[i] = (scale * mass[i]) * wp.identity(n=3, dtype=float)


@wp.kernel
def _diag_finish_kernel(offsets: wp.array(dtype=wp.int32), coef: wp.array(dtype=wp.vec4),
                        free: wp.array(dtype=float), diag: wp.array(dtype=wp.mat33),
                        dinv: wp.array(dtype=wp.mat33)):
    """diag_i += sum of the blocks of the springs at i (gathered); dinv = diag^-1 (0 for pins)."""
    i = wp.tid()
    D = diag[i]
    for q in range(offsets[i], offsets[i + 1]):
        D = D + spring_block_matrix(coef[q])
    diag[i] = D
    if free[i] > 0.0:
        dinv[i] = wp.inverse(D)
    else:
        dinv[i] = wp.mat33(0.0)


@wp.kernel
def _fill_laplacian_kernel(k: wp.array(dtype=float), slots: wp.array2d(dtype=wp.int32),
                           coef: wp.array(dtype=wp.vec4)):
    e = wp.tid()
    c = wp.vec4(0.0, 0.0, 0.0, k[e])
    coef[slots[e, 0]] = c
    coef[slots[e, 1]] = c


@wp.kernel
def _blocks_kernel(slots: wp.array2d(dtype=wp.int32), coef: wp.array(dtype=wp.vec4),
                   blocks: wp.array(dtype=wp.mat33)):
    e = wp.tid()
    blocks[e] = spring_block_matrix(coef[slots[e, 0]])


def spring_adjacency(model):
    """CSR adjacency of the springs, per vertex: ``(offsets (n+1), other (2S), slots (S, 2))``.

    Row ``i`` lists, at ``offsets[i]:offsets[i+1]``, the other end of every spring at ``i``;
    spring ``e = (i, j)`` owns entry ``slots[e, 0]`` in row i and ``slots[e, 1]`` in row j."""
    n = model.num_vertices
    pairs = np.asarray(model.spring_pairs, dtype=np.int64).reshape(-1, 2)
    S = len(pairs)
    rows = np.concatenate([pairs[:, 0], pairs[:, 1]])
    cols = np.concatenate([pairs[:, 1], pairs[:, 0]])
    order = np.argsort(rows, kind="stable")
    counts = np.bincount(rows, minlength=n) if S else np.zeros(n, dtype=np.int64)
    offsets = np.zeros(n + 1, dtype=np.int32)
    offsets[1:] = np.cumsum(counts)
    other = cols[order].astype(np.int32)
    pos = np.empty(2 * S, dtype=np.int32)
    pos[order] = np.arange(2 * S, dtype=np.int32)
    slots = np.stack([pos[:S], pos[S:]], 1).astype(np.int32)
    return offsets, other, slots


class SpringSystemOperator:
    """``A = mass_scale * M + sum_e [[H_e, -H_e], [-H_e, H_e]] (+ extra terms)``, matrix-free.

    Every spring block is rank one plus a multiple of the identity (a spring's Hessian
    ``k P + k c (I - P)`` with ``P = d d^T``, ``physics.md`` 2.1, and the projective-dynamics
    ``k I``), so it is stored compactly as ``coef = (g, beta)`` (``wp.vec4``) with
    ``H_e = g g^T + beta I`` (``g = sqrt(k L/|d|) d/|d|``, ``beta = k c``), once in each end's
    CSR row (`spring_adjacency`: ``offsets``, ``other``, and ``slots[e] = (row-i entry, row-j
    entry)``). The matvec is a gather, one thread per vertex, no atomics, and CG fuses it with
    its direction update (`cg_direction`). Whoever writes the blocks writes both slots: the
    implicit solver every Newton iteration, `fill_laplacian` once (``H_e = k_e I``, the
    projective-dynamics matrix ``A = M/dt^2 + L (x) I_3``). `spring_blocks` returns the 3x3
    blocks (host, for tests and comparisons); this replaces the former per-spring ``blocks``
    array (``mat33``, written with atomics).

    ``extra`` terms (e.g. bending) provide ``matvec_add(x, out)`` and ``add_diagonal(diag)``.
    Those with a constant scalar Hessian ``S (x) I_3`` (quadratic bending: ``scalar_entries``)
    are *folded*: their entries become a scalar CSR (``s_offsets``, ``s_cols``, ``s_vals``,
    duplicates summed) gathered in the same launch as the springs, so CG keeps its fused
    two-launch iteration (on the 2,500-vertex twist the per-quad product with atomics and the
    unfused direction cost more than the spring rows); they still add their own diagonal.
    ``vertex_blocks`` (None, or a ``mat33`` array per vertex) adds a block-diagonal term inside
    the same gather (the contact term of `warp_cloth.solvers.contact_coupling`; its owner also
    adds it to ``diag``). Call `update` after changing the blocks, the extra terms or
    ``mass_scale``.
    Pinned vertices (``model.inv_mass == 0``) are eliminated.
    """

    def __init__(self, model, mass_scale: float, extra=()):
        self.model = model
        self.n = model.num_vertices
        self.device = model.device
        self.threads = stride_threads(self.n, self.device)  # `cg_direction`
        self.mass_scale = float(mass_scale)
        self.extra = list(extra)
        d = self.device
        offsets, other, slots = spring_adjacency(model)
        self.num_springs = len(slots)
        self.offsets = wp.array(offsets, dtype=wp.int32, device=d)
        self.other = wp.array(other if len(other) else np.zeros(1, np.int32), dtype=wp.int32,
                              device=d)
        self.slots = wp.array(slots if len(slots) else np.zeros((1, 2), np.int32), dtype=wp.int32,
                              ndim=2, device=d)
        self.coef = wp.zeros(max(2 * self.num_springs, 1), dtype=wp.vec4, device=d)
        self.diag = wp.zeros(self.n, dtype=wp.mat33, device=d)
        self.diag_inv = wp.zeros(self.n, dtype=wp.mat33, device=d)
        free = (model.inverse_masses > 0).astype(np.float32)
        self.free = wp.array(free, dtype=wp.float32, device=d)
        self.vertex_blocks = None
        self.folded = [t for t in self.extra if hasattr(t, "scalar_entries")]
        self.extra = [t for t in self.extra if not hasattr(t, "scalar_entries")]
        self._fold(self.folded)

    def _fold(self, terms):
        """The scalar CSR of the folded terms' entries (`scalar_csr`)."""
        ent = [t.scalar_entries() for t in terms]
        offsets, cols, vals = scalar_csr(self.n, [e[0] for e in ent], [e[1] for e in ent],
                                         [e[2] for e in ent])
        self.s_offsets, self.s_cols, self.s_vals = csr_arrays(offsets, cols, vals, self.device)

    def _rows(self):
        """The launch arguments of the row gathers after ``scale``."""
        return [self.offsets, self.other, self.coef, self.s_offsets, self.s_cols, self.s_vals]

    def fill_laplacian(self):
        """``H_e = k_e I`` for every spring (the projective-dynamics / Liu 2013 matrix)."""
        m = self.model
        if self.num_springs:
            launch(_fill_laplacian_kernel, self.num_springs, [m.spring_k, self.slots, self.coef],
                   device=self.device)

    def spring_blocks(self) -> np.ndarray:
        """The spring blocks ``H_e`` as a ``(S, 3, 3)`` NumPy array (host; tests, benchmarks)."""
        out = wp.zeros(max(self.num_springs, 1), dtype=wp.mat33, device=self.device)
        if self.num_springs:
            launch(_blocks_kernel, self.num_springs, [self.slots, self.coef, out],
                   device=self.device)
        return out.numpy()[: self.num_springs]

    def update(self, mass_scale: float | None = None):
        if mass_scale is not None:
            self.mass_scale = float(mass_scale)
        m, d = self.model, self.device
        launch(_diag_init_kernel, self.n, [m.mass, self.mass_scale, self.diag], device=d)
        for t in self.folded + self.extra:
            t.add_diagonal(self.diag)
        launch(_diag_finish_kernel, self.n,
               [self.offsets, self.coef, self.free, self.diag, self.diag_inv], device=d)

    def matvec(self, x, out):
        m, d = self.model, self.device
        if self.vertex_blocks is not None:
            launch(_spring_matvec_vb_kernel, self.n,
                   [x, m.mass, self.mass_scale, *self._rows(), self.vertex_blocks, out],
                   device=d)
        else:
            launch(_spring_matvec_kernel, self.n,
                   [x, m.mass, self.mass_scale, *self._rows(), out], device=d)
        for t in self.extra:
            t.matvec_add(x, out)

    def cg_direction(self, z, p, ap, rz, pap, k) -> bool:
        """CG's fused step ``p = z + beta p; Ap = A z + beta Ap; pAp_k = p . Ap`` in one launch.
        Returns False (nothing done) when extra terms make the fused form unavailable."""
        if self.extra:
            return False
        if self.vertex_blocks is not None:
            launch(_spring_cg_direction_vb_kernel, self.threads,
                   [z, self.model.mass, self.mass_scale, *self._rows(), self.vertex_blocks,
                    self.free, p, ap, rz, pap, k, self.threads], device=self.device)
            return True
        launch(_spring_cg_direction_kernel, self.threads,
               [z, self.model.mass, self.mass_scale, *self._rows(), self.free, p, ap, rz,
                pap, k, self.threads], device=self.device)
        return True


# ----------------------------------------------------------------------------------- helpers
def scalar_csr(n: int, rows, cols, vals):
    """Coordinate lists (sequences of arrays) -> CSR of an ``n x n`` scalar matrix, rows and
    columns sorted, duplicates summed: ``(offsets (n+1) int32, cols int32, vals float64)``
    (host). Shared by the implicit operator's folded terms and projective dynamics' matrix."""
    rows = np.concatenate([np.asarray(r, np.int64) for r in rows] + [np.zeros(0, np.int64)])
    cols = np.concatenate([np.asarray(c, np.int64) for c in cols] + [np.zeros(0, np.int64)])
    vals = np.concatenate([np.asarray(v, np.float64) for v in vals] + [np.zeros(0)])
    key, inv = np.unique(rows * n + cols, return_inverse=True)  # by row, then column
    vals = np.bincount(inv.ravel(), weights=vals, minlength=len(key)) if len(key) else vals
    rows, cols = key // max(n, 1), key % max(n, 1)
    offsets = np.zeros(n + 1, dtype=np.int32)
    if len(rows):
        offsets[1:] = np.cumsum(np.bincount(rows, minlength=n))
    return offsets, cols.astype(np.int32), vals


def csr_arrays(offsets, cols, vals, device):
    """`scalar_csr`'s arrays on ``device`` (``vals`` as float32; empty lists get one dummy
    entry, never read)."""
    return (wp.array(offsets, dtype=wp.int32, device=device),
            wp.array(cols if len(cols) else np.zeros(1, np.int32), dtype=wp.int32,
                     device=device),
            wp.array(vals.astype(np.float32) if len(vals) else np.zeros(1, np.float32),
                     dtype=wp.float32, device=device))


def dense_matrix(A) -> np.ndarray:
    """Assemble ``A`` as a dense (3n x 3n) NumPy matrix by matvecs with unit vectors (tests only)."""
    n = A.n
    out = np.zeros((3 * n, 3 * n))
    e = wp.zeros(n, dtype=wp.vec3, device=A.device)
    y = wp.zeros(n, dtype=wp.vec3, device=A.device)
    for c in range(3 * n):
        h = np.zeros((n, 3), dtype=np.float32)
        h.reshape(-1)[c] = 1.0
        e.assign(h)
        A.matvec(e, y)
        out[:, c] = y.numpy().reshape(-1)
    return out


def estimate_spectral_radius(A, alpha: float = 0.66, iterations: int = 60, seed: int = 0) -> float:
    """Spectral radius of the Jacobi iteration matrix ``I - alpha D^-1 A`` (free vertices),
    measured by running the iteration on ``A e = 0`` from a random start: the geometric mean of
    the last residual ratios. Use it to set `ChebyshevSolver` ``rho`` (slightly above is unsafe)."""
    n, d = A.n, A.device
    th = stride_threads(n, d)
    rng = np.random.default_rng(seed)
    x = wp.array(rng.standard_normal((n, 3)).astype(np.float32) * A.free.numpy()[:, None],
                 dtype=wp.vec3, device=d)
    b = wp.zeros(n, dtype=wp.vec3, device=d)
    last = wp.clone(x)
    ax = wp.zeros(n, dtype=wp.vec3, device=d)
    sums = wp.zeros(iterations, dtype=wp.float64, device=d)
    tail = max(2, iterations // 3)
    # the estimate reads two residuals: the first and the last of the tail
    needed = {iterations - tail, iterations - 1}
    sweep = getattr(A, "jacobi_sweep", None)
    if sweep is not None and sweep(x, ax, b, alpha, sums, 0 if 0 in needed else -1):
        # the fused sweep (projective dynamics): the same iterates, ping-ponged between x and ax,
        # the residual norm summed only where it is read
        for k in range(1, iterations):
            x, ax = ax, x
            sweep(x, ax, b, alpha, sums, k if k in needed else -1)
        iterations = 0
    for k in range(iterations):
        A.matvec(x, ax)
        launch(_jacobi_update_kernel, th, [x, last, b, ax, A.diag_inv, A.free, float(alpha),
                                           1.0, sums, k, th], device=d)
    r = np.sqrt(sums.numpy())
    r = r[-tail:]
    if r[0] <= 0:
        return 0.0
    return float((r[-1] / r[0]) ** (1.0 / (len(r) - 1)))
