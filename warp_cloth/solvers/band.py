"""Conjugate gradient preconditioned by a banded Cholesky factor of the Newton matrix
(``linear="cholesky"`` of `ImplicitEuler`), or of projective dynamics' constant matrix
(``linear="cholesky"`` of `ProjectiveDynamics`, its default on the CPU without contact:
`ScalarBandFactor`, one scalar band for the three components, factored once per ``dt``).

Why: block-Jacobi CG needs about ``sqrt(cond)`` iterations, and stiff, light cloth makes the
Newton matrix ``M/dt^2 + K`` very ill-conditioned (``k dt^2 / m`` ~ 5e6 on the default 32 x 32
sheet at k = 1e6 N/m and one step a frame at 30 fps): 200 CG iterations per Newton iteration
leave every step far from converged, the strain several times the converged step's and the sheet
falling too slowly. A direct factor of the same matrix makes CG converge in one or two
iterations, so Newton converges as Newton does.

How: the vertices are renumbered once by reverse Cuthill-McKee (`rcm_order`, host, over the
springs' and folded terms' graph: a grid keeps its row-by-row order, bandwidth about one row),
so every spring and folded block lies within ``b`` vertices of the diagonal. Each factorisation
gathers the matrix's lower band (scalar, ``B = 3 b + 2`` wide, float64) from the operator
(`band_assemble_kernel`: the diagonal blocks ``diag`` as the operator keeps them, the springs'
blocks ``-H_e`` and the folded scalar entries), then factors it in place
(`band_factor_kernel`, float64: float32 loses everything at these condition numbers). Terms the
band does not hold (the off-diagonal blocks of contact pairs and self-contacts, dihedral
bending's) are left to CG, which still sees the whole operator; their diagonal blocks are in
``diag``, so the preconditioner stays symmetric positive definite.

Cost (one thread, float64): factorising ~ ``3 n B^2 / 2`` multiply-adds, each application
``4 * 3 n B``; ``n = 1,089`` vertices, ``B = 107``: 1.9e7 and 1.4e6. The factor kernel is
serial (one thread, on "cuda" too, where it runs unchanged but slowly: a GPU user wants ``cg``).
A factorisation that meets a non-positive pivot (an indefinite matrix: ``exact_hessian=True``)
sets a flag on the device and the applications fall back to block Jacobi (counted,
``factor_failures``); nothing is read back during a solve, so a step stays capturable.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..util import launch
from .linear import CGSolver, spring_block_matrix

wp.set_module_options({"enable_backward": False})

__all__ = ["rcm_order", "band_width", "narrowest_order", "CholeskyCGSolver", "ScalarBandFactor", "MAX_BAND_ENTRIES"]

#: the largest band (rows x width, float64 entries) a factor may take: 64 M entries = 512 MB
MAX_BAND_ENTRIES = 1 << 26


def _sym_csr(n: int, rows: np.ndarray, cols: np.ndarray):
    """Symmetric adjacency (no self loops, duplicates kept) as ``(indptr, indices)``."""
    keep = rows != cols
    r = np.concatenate([rows[keep], cols[keep]]).astype(np.int64)
    c = np.concatenate([cols[keep], rows[keep]]).astype(np.int64)
    order = np.lexsort((c, r))
    r, c = r[order], c[order]
    indptr = np.zeros(n + 1, dtype=np.int64)
    np.add.at(indptr, r + 1, 1)
    return np.cumsum(indptr), c


def _bfs_levels(start: int, indptr, indices, degree, seen):
    """Breadth-first order from ``start`` (neighbours by increasing degree) over unseen
    vertices, and the last level."""
    order, level = [start], [start]
    seen[start] = True
    while True:
        nxt = []
        for v in level:
            nb = indices[indptr[v]:indptr[v + 1]]
            nb = np.unique(nb[~seen[nb]])
            if len(nb):
                nb = nb[np.argsort(degree[nb], kind="stable")]
                seen[nb] = True
                nxt.extend(int(u) for u in nb)
        if not nxt:
            return order, level
        order.extend(nxt)
        level = nxt


def rcm_order(n: int, rows, cols) -> np.ndarray:
    """Reverse Cuthill-McKee order of the graph with edges ``(rows[k], cols[k])``: ``perm`` with
    ``perm[p]`` the vertex placed ``p``-th. Each component starts from a pseudo-peripheral
    vertex (two breadth-first sweeps from its least-connected vertex)."""
    rows = np.asarray(rows, dtype=np.int64).ravel()
    cols = np.asarray(cols, dtype=np.int64).ravel()
    indptr, indices = _sym_csr(n, rows, cols)
    degree = np.diff(indptr)
    placed = np.zeros(n, dtype=bool)
    out = []
    for s in np.argsort(degree, kind="stable"):
        if placed[s]:
            continue
        start = int(s)
        for _ in range(2):  # a far vertex of low degree: a narrower band
            seen = placed.copy()
            _, last = _bfs_levels(start, indptr, indices, degree, seen)
            start = int(min(last, key=lambda v: (degree[v], v)))
        order, _ = _bfs_levels(start, indptr, indices, degree, placed)
        out.extend(order)
    return np.asarray(out[::-1], dtype=np.int32)


def band_width(perm: np.ndarray, rows, cols) -> int:
    """Largest ``|position(i) - position(j)|`` over the edges in the order ``perm``."""
    rows = np.asarray(rows, dtype=np.int64).ravel()
    cols = np.asarray(cols, dtype=np.int64).ravel()
    if len(rows) == 0:
        return 0
    iperm = np.empty(len(perm), dtype=np.int64)
    iperm[perm] = np.arange(len(perm))
    return int(np.abs(iperm[rows] - iperm[cols]).max())


def narrowest_order(n: int, rows, cols, rcm: bool = True):
    """``(perm, width)``: the narrower band of the mesh's own numbering and, with ``rcm``,
    reverse Cuthill-McKee's order (a grid with diagonal springs: its rows, one row wide;
    RCM's levels there are two rows wide), over the edges ``(rows[k], cols[k])``."""
    orders = [np.arange(n, dtype=np.int32)]
    if rcm:
        orders.append(rcm_order(n, rows, cols))
    return min(((p, band_width(p, rows, cols)) for p in orders), key=lambda pw: pw[1])


@wp.kernel
def band_assemble_kernel(perm: wp.array(dtype=wp.int32), iperm: wp.array(dtype=wp.int32),
                         diag: wp.array(dtype=wp.mat33), free: wp.array(dtype=float),
                         offsets: wp.array(dtype=wp.int32), other: wp.array(dtype=wp.int32),
                         coef: wp.array(dtype=wp.vec4), s_offsets: wp.array(dtype=wp.int32),
                         s_cols: wp.array(dtype=wp.int32), s_vals: wp.array(dtype=float),
                         width: int, band: wp.array2d(dtype=wp.float64)):
    """The three scalar rows of the vertex placed ``p``-th, lower band only
    (``band[r, r - c] = A[r, c]``): its diagonal block, ``-H_e`` for each spring to an earlier
    free vertex, the folded scalar entries ``S_ij I``; a pinned vertex's rows are the identity."""
    p = wp.tid()
    i = perm[p]
    for a in range(3):
        for j in range(width + 1):
            band[3 * p + a, j] = wp.float64(0.0)
    if free[i] == 0.0:
        for a in range(3):
            band[3 * p + a, 0] = wp.float64(1.0)
        return
    D = diag[i]
    for a in range(3):
        for c in range(a + 1):
            band[3 * p + a, a - c] = wp.float64(D[a, c])
    for q in range(offsets[i], offsets[i + 1]):
        j = other[q]
        pj = iperm[j]
        if pj < p and free[j] != 0.0:
            H = spring_block_matrix(coef[q])
            for a in range(3):
                for c in range(3):
                    d = 3 * (p - pj) + a - c
                    band[3 * p + a, d] = band[3 * p + a, d] - wp.float64(H[a, c])
    for q in range(s_offsets[i], s_offsets[i + 1]):
        j = s_cols[q]
        pj = iperm[j]
        if pj < p and free[j] != 0.0:
            for a in range(3):
                d = 3 * (p - pj)
                band[3 * p + a, d] = band[3 * p + a, d] + wp.float64(s_vals[q])


@wp.kernel
def band_factor_kernel(band: wp.array2d(dtype=wp.float64), rows: int, width: int,
                       failed: wp.array(dtype=int)):
    """In place, row by row: ``A = L L^T`` with ``L`` in the same lower band
    (``band[r, r - c] = L[r, c]``). A pivot that is not positive sets ``failed[0]``."""
    failed[0] = 0
    for r in range(rows):
        j0 = wp.max(0, r - width)
        for c in range(j0, r + 1):
            # the dot product of rows r and c over their common band, in four partial sums
            # (independent multiply-adds: about twice as fast as one running sum on a CPU)
            k0 = wp.max(j0, c - width)
            s0 = band[r, r - c]
            s1 = wp.float64(0.0)
            s2 = wp.float64(0.0)
            s3 = wp.float64(0.0)
            k = k0
            while k + 3 < c:
                s0 = s0 - band[r, r - k] * band[c, c - k]
                s1 = s1 - band[r, r - k - 1] * band[c, c - k - 1]
                s2 = s2 - band[r, r - k - 2] * band[c, c - k - 2]
                s3 = s3 - band[r, r - k - 3] * band[c, c - k - 3]
                k += 4
            while k < c:
                s0 = s0 - band[r, r - k] * band[c, c - k]
                k += 1
            s = (s0 + s1) + (s2 + s3)
            if c < r:
                band[r, r - c] = s / band[c, 0]
            else:
                if s > wp.float64(0.0):
                    band[r, 0] = wp.sqrt(s)
                else:
                    failed[0] = 1
                    band[r, 0] = wp.float64(1.0)


@wp.func
def jacobi_fallback(n: int, dinv: wp.array(dtype=wp.mat33), r: wp.array(dtype=wp.vec3),
                    z: wp.array(dtype=wp.vec3), fallbacks: wp.array(dtype=int)):
    """Block Jacobi ``z = D^-1 r`` where a factorisation failed, counted; returns ``r . z``."""
    fallbacks[0] = fallbacks[0] + 1
    acc = wp.float64(0.0)
    for i in range(n):
        zi = dinv[i] * r[i]
        z[i] = zi
        acc = acc + wp.float64(wp.dot(r[i], zi))
    return acc


@wp.kernel
def band_solve_kernel(band: wp.array2d(dtype=wp.float64), rows: int, width: int,
                      perm: wp.array(dtype=wp.int32), free: wp.array(dtype=float),
                      dinv: wp.array(dtype=wp.mat33), failed: wp.array(dtype=int),
                      r: wp.array(dtype=wp.vec3), y: wp.array(dtype=wp.float64),
                      z: wp.array(dtype=wp.vec3), rz: wp.array(dtype=wp.float64), slot: int,
                      fallbacks: wp.array(dtype=int)):
    """``z = (L L^T)^-1 r`` (forward and back substitution in float64, in the band's order),
    ``rz[slot] = r . z``; block Jacobi ``z = D^-1 r`` when the factorisation failed."""
    n = rows // 3
    acc = wp.float64(0.0)
    if failed[0] != 0:
        rz[slot] = jacobi_fallback(n, dinv, r, z, fallbacks)
        return
    for row in range(rows):
        p = row // 3
        i = perm[p]
        s = wp.float64(r[i][row - 3 * p] * free[i])
        for k in range(wp.max(0, row - width), row):
            s = s - band[row, row - k] * y[k]
        y[row] = s / band[row, 0]
    for t in range(rows):  # L^T: by columns of L^T (rows of L), reading the band in order
        row = rows - 1 - t
        xr = y[row] / band[row, 0]
        y[row] = xr
        for k in range(wp.max(0, row - width), row):
            y[k] = y[k] - band[row, row - k] * xr
    for p in range(n):
        i = perm[p]
        zi = wp.vec3(float(y[3 * p]), float(y[3 * p + 1]), float(y[3 * p + 2])) * free[i]
        z[i] = zi
        acc = acc + wp.float64(wp.dot(r[i], zi))
    rz[slot] = acc


class BandFactor:
    """The banded Cholesky factor of a `SpringSystemOperator`'s in-band part (module
    docstring): ``perm`` / ``width`` fixed from the operator's graph at construction,
    `factor` every time the matrix changed, `apply` per preconditioning."""

    def __init__(self, A):
        for attr in ("offsets", "other", "coef", "s_offsets", "s_cols", "s_vals", "diag"):
            if not hasattr(A, attr):
                raise ValueError(f"linear='cholesky' needs implicit Euler's spring operator "
                                 f"(its {attr!r}); {type(A).__name__} has none")
        n, d = A.n, A.device
        off = A.offsets.numpy().astype(np.int64)
        rows = np.repeat(np.arange(n), np.diff(off))
        cols = A.other.numpy()[: len(rows)]
        soff = A.s_offsets.numpy().astype(np.int64)
        srows = np.repeat(np.arange(n), np.diff(soff))
        scols = A.s_cols.numpy()[: len(srows)]
        allr, allc = np.concatenate([rows, srows]), np.concatenate([cols, scols])
        self.perm, self.vertex_width = narrowest_order(n, allr, allc)
        self.width = 3 * self.vertex_width + 2
        self.rows = 3 * n
        if self.rows * (self.width + 1) > MAX_BAND_ENTRIES:
            raise ValueError(f"linear='cholesky': the band is {self.rows} x {self.width + 1} "
                             f"float64 entries (more than {MAX_BAND_ENTRIES}); this mesh's "
                             f"ordering is too wide for a banded factor: use linear='cg'")
        iperm = np.empty(n, dtype=np.int32)
        iperm[self.perm] = np.arange(n, dtype=np.int32)
        self.perm_d = wp.array(self.perm, dtype=wp.int32, device=d)
        self.iperm_d = wp.array(iperm, dtype=wp.int32, device=d)
        self.band = wp.zeros((self.rows, self.width + 1), dtype=wp.float64, device=d)
        self.y = wp.zeros(self.rows, dtype=wp.float64, device=d)
        self.failed = wp.zeros(1, dtype=int, device=d)
        self.fallbacks = wp.zeros(1, dtype=int, device=d)  # applications that fell back
        self.factorisations = 0
        self.operator = A

    def factor(self) -> None:
        A = self.operator
        launch(band_assemble_kernel, A.n,
               [self.perm_d, self.iperm_d, A.diag, A.free, A.offsets, A.other, A.coef,
                A.s_offsets, A.s_cols, A.s_vals, self.width, self.band], device=A.device)
        launch(band_factor_kernel, 1, [self.band, self.rows, self.width, self.failed],
               device=A.device)
        self.factorisations += 1

    def apply(self, r, z, rz, slot: int) -> None:
        A = self.operator
        launch(band_solve_kernel, 1,
               [self.band, self.rows, self.width, self.perm_d, A.free, A.diag_inv, self.failed,
                r, self.y, z, rz, int(slot), self.fallbacks], device=A.device)


@wp.kernel
def band_transpose_kernel(band: wp.array2d(dtype=wp.float64), n: int, width: int,
                          upper: wp.array2d(dtype=wp.float64)):
    """``upper[p, j] = L[p + j, p]`` (0 past the last row): the factor's columns as rows, so the
    back substitution reads memory in order as the forward one does."""
    p = wp.tid()
    for j in range(width + 1):
        v = wp.float64(0.0)
        if p + j < n:
            v = band[p + j, j]
        upper[p, j] = v


@wp.kernel
def band3_solve_kernel(band: wp.array2d(dtype=wp.float64), upper: wp.array2d(dtype=wp.float64),
                       n: int, width: int, perm: wp.array(dtype=wp.int32),
                       free: wp.array(dtype=float), dinv: wp.array(dtype=wp.mat33),
                       failed: wp.array(dtype=int), r: wp.array(dtype=wp.vec3),
                       y: wp.array(dtype=wp.vec3d), z: wp.array(dtype=wp.vec3),
                       rz: wp.array(dtype=wp.float64), slot: int, fallbacks: wp.array(dtype=int)):
    """``z = (S^-1 (x) I_3) r`` for a scalar banded factor ``S = L L^T`` (the three components
    at once, float64, in the band's order), ``rz[slot] = r . z``; block Jacobi ``z = D^-1 r``
    when the factorisation failed. Both substitutions are row dot products over the band in
    two partial sums (``upper``: the factor's columns as rows)."""
    acc = wp.float64(0.0)
    if failed[0] != 0:
        rz[slot] = jacobi_fallback(n, dinv, r, z, fallbacks)
        return
    zero = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    for p in range(n):  # L y = P r
        i = perm[p]
        ri = r[i] * free[i]
        s0 = wp.vec3d(wp.float64(ri[0]), wp.float64(ri[1]), wp.float64(ri[2]))
        s1 = zero
        k = wp.max(0, p - width)
        while k + 1 < p:
            s0 = s0 - band[p, p - k] * y[k]
            s1 = s1 - band[p, p - k - 1] * y[k + 1]
            k += 2
        if k < p:
            s0 = s0 - band[p, p - k] * y[k]
        y[p] = (s0 + s1) / band[p, 0]
    for t in range(n):  # L^T x = y, rows of L^T from ``upper``
        p = n - 1 - t
        s0 = y[p]
        s1 = zero
        j = int(1)
        m = wp.min(width, n - 1 - p)
        while j + 1 <= m:
            s0 = s0 - upper[p, j] * y[p + j]
            s1 = s1 - upper[p, j + 1] * y[p + j + 1]
            j += 2
        if j <= m:
            s0 = s0 - upper[p, j] * y[p + j]
        y[p] = (s0 + s1) / upper[p, 0]
    for p in range(n):
        i = perm[p]
        yp = y[p]
        zi = wp.vec3(float(yp[0]), float(yp[1]), float(yp[2])) * free[i]
        z[i] = zi
        acc = acc + wp.float64(wp.dot(r[i], zi))
    rz[slot] = acc


class ScalarBandFactor:
    """The banded Cholesky factor of projective dynamics' constant matrix ``S (x) I_3``
    (`projective.PDSystemOperator`: masses over ``dt^2``, the springs' weighted Laplacian and the
    folded constant terms, quadratic bending): one scalar band (``n`` rows, ``b`` wide, float64)
    shared by the three components, so 27 times less factorisation work and 3 times less per
    application than the vector band of implicit Euler's matrix. Assembled on the host (the
    matrix is constant for a ``dt``), factored once on the device. The operator's other terms
    (contact blocks, self-contacts' pairs) are left to CG, which sees the whole operator."""

    def __init__(self, A):
        n, d = A.n, A.device
        offsets, cols, w = A.csr_host
        rows = np.repeat(np.arange(n), np.diff(offsets.astype(np.int64)))
        given = getattr(A, "band_order", None)  # (order, width) its solver found
        if given is not None:
            self.perm, self.width = np.asarray(given[0], dtype=np.int32), int(given[1])
        else:
            self.perm, self.width = narrowest_order(n, rows, cols)
        self.vertex_width = self.width
        self.rows = n
        if n * (self.width + 1) > MAX_BAND_ENTRIES:
            raise ValueError(f"linear='cholesky': the band is {n} x {self.width + 1} float64 "
                             f"entries (more than {MAX_BAND_ENTRIES}); this mesh's ordering is "
                             f"too wide for a banded factor: use linear='cg'")
        iperm = np.empty(n, dtype=np.int64)
        iperm[self.perm] = np.arange(n)
        free = A.free.numpy() > 0
        band = np.zeros((n, self.width + 1))
        diag = A.mass_scale * np.asarray(A.model.masses, np.float64) + A.laplacian_diag
        band[:, 0] = np.where(free[self.perm], diag[self.perm], 1.0)
        pr, pc = iperm[rows], iperm[cols]
        keep = (pc < pr) & free[rows] & free[cols]
        # the operator's row i is diag_i x_i - sum_j w_ij x_j: the entry is -w_ij
        np.add.at(band, (pr[keep], pr[keep] - pc[keep]), -np.asarray(w, np.float64)[keep])
        self.perm_d = wp.array(self.perm, dtype=wp.int32, device=d)
        self.band = wp.array(band, dtype=wp.float64, device=d)
        self.upper = wp.zeros_like(self.band)
        self.y = wp.zeros(n, dtype=wp.vec3d, device=d)
        self.failed = wp.zeros(1, dtype=int, device=d)
        self.fallbacks = wp.zeros(1, dtype=int, device=d)
        self.factorisations = 0
        self.operator = A
        self._host_band = band

    def factor(self) -> None:
        A = self.operator
        self.band.assign(self._host_band)
        launch(band_factor_kernel, 1, [self.band, self.rows, self.width, self.failed],
               device=A.device)
        launch(band_transpose_kernel, self.rows, [self.band, self.rows, self.width, self.upper],
               device=A.device)
        self.factorisations += 1

    def apply(self, r, z, rz, slot: int) -> None:
        A = self.operator
        launch(band3_solve_kernel, 1,
               [self.band, self.upper, self.rows, self.width, self.perm_d, A.free, A.diag_inv,
                self.failed, r, self.y, z, rz, int(slot), self.fallbacks], device=A.device)


class CholeskyCGSolver(CGSolver):
    """CG preconditioned by `BandFactor` (module docstring): the same iteration as `CGSolver`
    with ``z = (L L^T)^-1 r`` in place of ``D^-1 r``. The factor is refreshed on the next
    `solve` after `invalidate` (`ImplicitEuler` calls it at every Newton assembly, so each
    Newton matrix is factored once).

    Args:
        iterations: most CG iterations per solve (default 20: one or two suffice when every
            term is in the band).
        tolerance: relative residual ending a solve (None: run ``iterations``, capturable).
        check_every: residual check period (host reads) with a tolerance.
    """

    name = "cholesky"

    def __init__(self, iterations: int = 20, tolerance: float | None = 1e-3,
                 check_every: int | None = None):
        super().__init__(iterations, tolerance, check_every)
        self.factor = None
        self._stale = True

    def invalidate(self) -> None:
        """The operator's blocks changed: factor again before the next solve."""
        self._stale = True

    @property
    def fallbacks(self) -> int:
        """Applications that fell back to block Jacobi (a failed factorisation; host read)."""
        return 0 if self.factor is None else int(self.factor.fallbacks.numpy()[0])

    def _prepare(self, A) -> None:
        if self.factor is None or self.factor.operator is not A:
            # projective dynamics' constant scalar matrix (its host CSR), or implicit Euler's
            self.factor = (ScalarBandFactor(A) if hasattr(A, "csr_host") else BandFactor(A))
            self._stale = True
        if self._stale:
            self.factor.factor()
            self._stale = False

    def _precondition(self, A, rz, slot: int) -> None:
        self.factor.apply(self.r, self.z, rz, slot)
