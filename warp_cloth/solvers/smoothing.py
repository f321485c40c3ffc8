"""Nonlinear block Gauss-Seidel sweeps on the incremental potential (after Newton).

Implicit Euler minimises ``F(x) = 1/(2 dt^2) ||x - x_hat||_M^2 - f_ext . x + E(x)``
(`warp_cloth.solvers.implicit`). Newton with the definiteness fix (the compressed springs'
transverse term dropped, physics.md 2.1) converges only linearly where springs are much stiffer
than the inertia block (``k dt^2 / m`` of 1e6 and more: stiff, light cloth at large steps), and
a step stopped at its Newton cap leaves single edges stretched far beyond the converged step:
on the 32 x 32 hanging sheet at k = 1e6 N/m, one step per frame at 30 fps, 8 Newton iterations
(CG) left 0.18 % strain where the step converged in time reaches 0.018 %.

A sweep visits the vertices colour by colour (no two vertices of a colour share a spring or a
folded bending entry, so a colour's vertices move in parallel without races) and moves each
free vertex ``i`` by one Newton step of ``F`` in ``x_i`` alone, the other vertices held:

    g_i = M_i/dt^2 (x_i - x_hat_i) - f_ext_i + sum_e k_e (l_e - L_e) d_e / l_e + (Q x)_i
    H_i = M_i/dt^2 I + sum_e k_e [(1 - c_e) n_e n_e^T + c_e I] + Q_ii I,   c_e = 1 - L_e / l_e

with the springs' exact Hessian (their compression term kept: a 3 x 3 block, projected onto
its eigenvalues ``>= M_i/dt^2``, which is cheap where Newton's global projection had to drop
it per spring), and a backtracking search on ``F`` restricted to ``x_i`` (float64; halvings
until it decreases, at most 8, else the vertex stays). So every accepted move lowers ``F``:
the sweeps keep the step's guarantee (no step adds energy that Newton's iterate did not have
in ``F``), and they remove what Newton leaves at short range (a single over-stretched edge)
in a few sweeps, while Newton carried the long range. (Gauss-Seidel on the vertex blocks is the
notes' Jacobi smoother made sequential by colour; with the local line search it is the vertex
block descent of Chen et al. 2024, used here as a finisher.)

Scope: the springs, inertia, the external forces and terms folded into the operator's
constant scalar matrix ``Q`` (quadratic bending); pins are held. A step with contact entries
(obstacle or self-contact: the solver's device flag ``free[0] == 0``) is not smoothed: the
contact penalty is not part of the local potential, and a vertex without an entry moved by
the sweeps toward a surface has nothing to stop it inside the solve (holding the entries'
vertices was not enough: on the 16 x 16 fold the strain went from 0.3 % to 2.1 %, and an
implicit sheet on a small sphere ended 0.35 mm from it at a 0.5 mm thickness). A model with
another implicit term (dihedral bending) is not smoothed. Launches: one per colour per sweep,
fixed (the contact test is read on the device): a captured step replays them.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..util import launch

wp.set_module_options({"enable_backward": False})

#: local backtracking halvings before a vertex is left where it is
LOCAL_HALVINGS = 8

#: sweeps after a solve (implicit Euler: after a Newton solve that stopped above its
#: tolerance; projective dynamics: after its iterations). Measured on the 32 x 32 hanging
#: sheet, k = 1e6 N/m, one implicit step a frame at 30 fps, 15 frames (CG): max strain 0.179 %
#: without, 0.040 % with 4, 0.042 % with 16 (what remains is long-range, Newton's part); the
#: converged reference (1/1980 s steps) 0.018 %.
DEFAULT_SMOOTHING_SWEEPS = 4


def check_sweeps(sweeps, solver: str) -> None:
    """A sweep count must be an integer >= 0 (``ValueError`` naming the solver otherwise)."""
    if (isinstance(sweeps, (bool, np.bool_, str)) or int(sweeps) != sweeps or sweeps < 0):
        raise ValueError(f"{solver}: smoothing_sweeps must be an integer >= 0, got {sweeps!r}")


def vertex_colors(num_vertices: int, offsets, others, seed: int = 0) -> np.ndarray:
    """A colouring of the vertices (host, vectorised): no two vertices joined by an entry of
    any of the CSR neighbour lists ``others[k]`` (rows ``offsets[k]``) share a colour.

    Jones-Plassmann rounds: each round, every uncoloured vertex whose random priority beats
    all its uncoloured neighbours' takes the smallest colour none of its neighbours has (a
    bitmask of the neighbours' colours; vertices of more than 62 neighbours fall back to a
    host loop). About as few colours as a sequential greedy pass, in a few dozen vectorised
    rounds (262,144 vertices: under a second)."""
    n = int(num_vertices)
    rows, cols = [], []
    for off, oth in zip(offsets, others):
        off = np.asarray(off, np.int64)
        cnt = np.diff(off[: n + 1])
        rows.append(np.repeat(np.arange(n, dtype=np.int64), cnt))
        cols.append(np.asarray(oth, np.int64)[: int(off[n])])
    r = np.concatenate(rows + [np.zeros(0, np.int64)])
    c = np.concatenate(cols + [np.zeros(0, np.int64)])
    keep = r != c
    r, c = r[keep], c[keep]
    color = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return color
    deg = np.bincount(r, minlength=n)
    if deg.max(initial=0) > 62:
        return _greedy_colors(n, r, c)
    order = np.argsort(r, kind="stable")
    r, c = r[order], c[order]
    start = np.searchsorted(r, np.arange(n))
    has = deg > 0
    prio = np.random.default_rng(seed).permutation(n)
    later = prio[c] > prio[r]  # the neighbour goes first if both are open
    while True:
        open_ = color < 0
        if not open_.any():
            return color
        # an uncoloured vertex with an uncoloured neighbour of higher priority waits
        waits = np.zeros(n, dtype=bool)
        waits[r[later & open_[c]]] = True
        pick = open_ & ~waits
        bits = np.where(color[c] >= 0, np.left_shift(np.int64(1), np.maximum(color[c], 0)), 0)
        used = np.zeros(n, dtype=np.int64)
        if len(bits):
            used[has] = np.bitwise_or.reduceat(bits, start[has])
        free = ~used & (used + 1)  # the lowest clear bit
        color[pick] = np.log2(free[pick].astype(np.float64)).round().astype(np.int64)


def _greedy_colors(n: int, r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Sequential greedy colouring (host loop), for vertices of very many neighbours."""
    order = np.argsort(r, kind="stable")
    r, c = r[order], c[order]
    start = np.searchsorted(r, np.arange(n + 1))
    color = np.full(n, -1, dtype=np.int64)
    for i in range(n):
        used = set(color[c[start[i]:start[i + 1]]].tolist())
        k = 0
        while k in used:
            k += 1
        color[i] = k
    return color


@wp.func
def _local_energy(x: wp.array(dtype=wp.vec3), i: int, xi: wp.vec3, u: wp.vec3, sm: float,
                  fe: wp.vec3, qc: wp.vec3, qii: float, offsets: wp.array(dtype=wp.int32),
                  other: wp.array(dtype=wp.int32), k: wp.array(dtype=float),
                  rest: wp.array(dtype=float)):
    """``F`` as a function of ``x_i`` alone (up to a constant), float64: inertia and external
    force through ``u = x_i - x_hat_i``, the springs at ``i``, the folded quadratic terms
    (``qc = sum_{j != i} Q_ij x_j``, ``qii = Q_ii``)."""
    e = wp.float64(0.5 * sm) * wp.float64(wp.dot(u, u)) - wp.float64(wp.dot(fe, u))
    e = e + wp.float64(wp.dot(qc, xi)) + wp.float64(0.5 * qii) * wp.float64(wp.dot(xi, xi))
    for q in range(offsets[i], offsets[i + 1]):
        d = wp.vec3d(xi) - wp.vec3d(x[other[q]])
        s = wp.length(d) - wp.float64(rest[q])
        e = e + wp.float64(0.5 * k[q]) * s * s
    return e


@wp.kernel
def smooth_color_kernel(x: wp.array(dtype=wp.vec3), disp: wp.array(dtype=wp.vec3),
                        mass: wp.array(dtype=float), movable: wp.array(dtype=float),
                        f_ext: wp.array(dtype=wp.vec3), scale: float,
                        offsets: wp.array(dtype=wp.int32), other: wp.array(dtype=wp.int32),
                        k: wp.array(dtype=float), rest: wp.array(dtype=float),
                        s_offsets: wp.array(dtype=wp.int32), s_cols: wp.array(dtype=wp.int32),
                        s_vals: wp.array(dtype=float), verts: wp.array(dtype=wp.int32),
                        start: int, free_step: wp.array(dtype=int), moved: wp.array(dtype=float)):
    """One colour of a sweep: each of its movable vertices takes a projected local Newton step
    on ``F`` with backtracking (module docstring); ``disp`` (x - x_hat, the solver's exact
    increment sum) moves with it; the largest move into ``moved[0]``. Nothing moves when
    ``free_step[0] == 0`` (the step has contact entries)."""
    i = verts[start + wp.tid()]
    if movable[i] == 0.0 or free_step[0] == 0:
        return
    sm = scale * mass[i]
    xi = x[i]
    u = disp[i]
    fe = f_ext[i]
    qc = wp.vec3(0.0)
    qii = float(0.0)
    for q in range(s_offsets[i], s_offsets[i + 1]):
        j = s_cols[q]
        if j == i:
            qii = qii + s_vals[q]
        else:
            qc = qc + s_vals[q] * x[j]
    g = sm * u - fe + qc + qii * xi
    H = (sm + qii) * wp.identity(n=3, dtype=float)
    for q in range(offsets[i], offsets[i + 1]):
        d64 = wp.vec3d(xi) - wp.vec3d(x[other[q]])
        l64 = wp.length(d64)
        if l64 > wp.float64(1.0e-12):
            kq = k[q]
            g = g + wp.vec3(d64 * (wp.float64(kq) * (l64 - wp.float64(rest[q])) / l64))
            l = float(l64)
            n = wp.vec3(d64) / l
            c = 1.0 - rest[q] / l
            H = H + (kq * (1.0 - c)) * wp.outer(n, n) + (kq * c) * wp.identity(n=3, dtype=float)
    Q = wp.mat33()
    ev = wp.vec3()
    wp.eig3(H, Q, ev)
    inv = wp.mat33(0.0)
    for a in range(3):
        lam = wp.max(ev[a], sm)
        qa = wp.vec3(Q[0, a], Q[1, a], Q[2, a])
        inv = inv + wp.outer(qa, qa) / lam
    dx = -(inv * g)
    e0 = _local_energy(x, i, xi, u, sm, fe, qc, qii, offsets, other, k, rest)
    step = float(1.0)
    for t in range(LOCAL_HALVINGS):
        e1 = _local_energy(x, i, xi + step * dx, u + step * dx, sm, fe, qc, qii, offsets, other,
                           k, rest)
        if e1 < e0:
            d = step * dx
            x[i] = xi + d
            disp[i] = u + d
            wp.atomic_max(moved, 0, wp.length(d))
            return
        step = 0.5 * step


@wp.kernel
def offset_kernel(x: wp.array(dtype=wp.vec3), x_hat: wp.array(dtype=wp.vec3),
                  out: wp.array(dtype=wp.vec3)):
    """``out = x - x_hat`` (a solver without an exact increment sum: projective dynamics)."""
    i = wp.tid()
    out[i] = x[i] - x_hat[i]


@wp.kernel
def end_velocity_kernel(x: wp.array(dtype=wp.vec3), x0: wp.array(dtype=wp.vec3),
                        inv_mass: wp.array(dtype=float), inv_dt: float, decay: float,
                        free_step: wp.array(dtype=int), v: wp.array(dtype=wp.vec3)):
    """``v = (x - x0)/dt * decay`` for free vertices again after the sweeps (projective
    dynamics' end-of-step velocity, the same expression); nothing when ``free_step[0] == 0``."""
    i = wp.tid()
    if inv_mass[i] > 0.0 and free_step[0] != 0:
        v[i] = (x[i] - x0[i]) * (inv_dt * decay)


class VertexSmoother:
    """Colour-ordered nonlinear Gauss-Seidel sweeps on ``F`` for the springs of ``operator``
    (a `linear.SpringSystemOperator`, whose CSR rows, folded scalar terms and ``free`` mask it
    reads). See the module docstring."""

    def __init__(self, model, operator):
        self.model = model
        self.A = operator
        d = self.device = model.device
        A = operator
        off = A.offsets.numpy()
        oth = A.other.numpy()[: 2 * A.num_springs]
        slots = A.slots.numpy()[: A.num_springs]
        k = np.zeros(max(len(oth), 1), np.float32)
        rest = np.zeros(max(len(oth), 1), np.float32)
        if A.num_springs:
            k[slots[:, 0]] = k[slots[:, 1]] = model.spring_k.numpy()
            rest[slots[:, 0]] = rest[slots[:, 1]] = model.spring_rest_length.numpy()
        self.k = wp.array(k, dtype=float, device=d)
        self.rest = wp.array(rest, dtype=float, device=d)
        color = vertex_colors(model.num_vertices, [off, A.s_offsets.numpy()],
                              [oth, A.s_cols.numpy()])
        order = np.argsort(color, kind="stable").astype(np.int32)
        counts = np.bincount(color, minlength=1) if len(color) else np.zeros(1, np.int64)
        self.num_colors = int(len(counts))
        self.starts = [0] + [int(c) for c in np.cumsum(counts)]
        self.verts = wp.array(order if len(order) else np.zeros(1, np.int32), dtype=wp.int32,
                              device=d)
        self.moved = wp.zeros(1, dtype=float, device=d)

    def sweep(self, x, disp, f_ext, scale: float, sweeps: int, free_step) -> None:
        """``sweeps`` colour-ordered sweeps (``x`` and ``disp`` move together) unless
        ``free_step[0] == 0`` (a device flag: the step has contact entries); the largest single
        move of the last call into ``moved``."""
        A, m, d = self.A, self.model, self.device
        self.moved.zero_()
        for _ in range(int(sweeps)):
            for c in range(self.num_colors):
                nv = self.starts[c + 1] - self.starts[c]
                if nv:
                    launch(smooth_color_kernel, nv,
                           [x, disp, m.mass, A.free, f_ext, scale, A.offsets, A.other,
                            self.k, self.rest, A.s_offsets, A.s_cols, A.s_vals, self.verts,
                            self.starts[c], free_step, self.moved], device=d)
