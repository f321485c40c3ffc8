"""Bending across interior edges: the dihedral-angle model and the quadratic model.

Both act on the mesh's bending quads ``(a, b, c, d)`` (``TriMesh.bend_quads``): the interior edge
``(a, b)`` in the winding of the first triangle ``(a, b, c)``, ``c`` the vertex opposite the edge
in that triangle and ``d`` the one opposite it in the other triangle ``(b, a, d)``. One thread per
quad; forces are scattered to the four vertices with atomics. The kernels live in this module so
that a cloth without these models never compiles them. A scene picks one bending model
(``ClothModel(bending="springs" | "dihedral" | "quadratic")``); the three are alternatives.

**Dihedral angle** (Bridson, Marino and Fedkiw 2003, *Simulation of Clothing with Folds and
Wrinkles*; ``reference/physics.md`` section 2.7, notes L1123-1152 and 000:L200-204). With the
notes' names ``x1 = c``, ``x2 = d`` (wing vertices), ``x3 = a``, ``x4 = b`` (the shared edge)::

    N1 = (x1 - x3) x (x1 - x4),  N2 = (x2 - x4) x (x2 - x3),  E = x4 - x3
    u1 = |E| N1/|N1|^2,  u2 = |E| N2/|N2|^2
    u3 = (x1 - x4).E/|E| N1/|N1|^2 + (x2 - x4).E/|E| N2/|N2|^2
    u4 = -(x1 - x3).E/|E| N1/|N1|^2 - (x2 - x3).E/|E| N2/|N2|^2
    f_i = k |E|^2/(|N1| + |N2|) (sin(theta/2) - sin(theta0/2)) u_i

Here ``theta = atan2((n1 x n2).E/|E|, n1.n2)`` is the *signed* angle between the unit normals (0
when flat; the notes' dihedral angle is ``pi - theta``, so ``sin(theta/2) = sin((pi -
theta_dihedral)/2)``), and ``theta0`` is the same angle in the rest shape, so non-flat rest shapes
keep their folds. With this sign ``u_i = -d theta/d x_i`` exactly, so the force is restoring.
``k`` is in N m.

*Energy.* ``E_q = k c psi(theta)`` with ``c = |E|^2/(|N1| + |N2|)`` and
``psi = 2 (cos(theta0/2) - cos(theta/2)) - (theta - theta0) sin(theta0/2)`` (``psi(theta0) = 0``,
``psi' = sin(theta/2) - sin(theta0/2)``, ``psi'' = cos(theta/2)/2 > 0``, so ``psi >= 0``). The
Bridson force is exactly ``-grad E_q`` with ``c`` held fixed; the neglected term ``-k psi grad c``
is second order in ``theta - theta0`` (``psi = O((theta - theta0)^2)``), so energy and force agree
to first order about the rest angle. The energy is what the diagnostics and energy checks report.

*Hessian for the implicit solver* (Gauss-Newton, positive semi-definite): ``H ~= k c psi''(theta)
g g^T`` with ``g = [u1; u2; u3; u4] = -grad theta`` (12-vector), i.e. the derivatives of ``c``,
``u_i`` and the ``psi'`` terms are dropped. This is exact at the rest angle up to the (dropped)
curvature of ``theta`` itself, rank one per quad and PSD for ``|theta| < pi``. `eval_with_hessian`
refreshes it at the current iterate (one kernel: forces and ``g`` together).

**Quadratic** (Bergou, Wardetzky, Harmon, Zorin and Grinspun 2006, *A Quadratic Bending Model for
Inextensible Surfaces*; notes L1154-1184). With ``x0 = a``, ``x1 = b`` (the edge), ``x2 = c``,
``x3 = d``, and the rest-shape interior angles ``theta0, theta1`` at ``a, b`` in triangle
``(a, b, c)`` and ``theta2, theta3`` at ``a, b`` in triangle ``(a, b, d)``::

    K = [cot t1 + cot t3, cot t0 + cot t2, -cot t0 - cot t1, -cot t2 - cot t3]
    E = 1/2 x^T Q x,  Q = 3 k/(A0 + A1) K K^T (x) I_3,   f = -Q x,   H = Q (exact, constant)

``A0``, ``A1`` are the rest areas. ``K`` sums to zero (translation invariance) and ``K^T x = 0``
for a flat pair, so the energy is zero for any planar (rigidly moved) configuration.
Limitations (notes L1176-1181): valid only for small stretching and a planar rest shape; for a
non-planar rest shape the energy is not zero at rest and the model flattens the cloth (a
`UserWarning` says so).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import warp as wp

from ..mesh import cross3
from ..util import launch

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile

__all__ = ["DihedralBending", "QuadraticBending", "dihedral_angles"]


# ------------------------------------------------------------------------------ dihedral
@wp.func
def _dihedral_terms(x1: wp.vec3, x2: wp.vec3, x3: wp.vec3, x4: wp.vec3):
    """(theta, c, u1, u2, u3, u4); c < 0 flags a degenerate quad."""
    N1 = wp.cross(x1 - x3, x1 - x4)
    N2 = wp.cross(x2 - x4, x2 - x3)
    E = x4 - x3
    l1 = wp.length(N1)
    l2 = wp.length(N2)
    el = wp.length(E)
    z = wp.vec3(0.0)
    if l1 < 1.0e-20 or l2 < 1.0e-20 or el < 1.0e-12:
        return 0.0, -1.0, z, z, z, z
    a = N1 / (l1 * l1)
    b = N2 / (l2 * l2)
    u1 = el * a
    u2 = el * b
    u3 = wp.dot(x1 - x4, E) / el * a + wp.dot(x2 - x4, E) / el * b
    u4 = -wp.dot(x1 - x3, E) / el * a - wp.dot(x2 - x3, E) / el * b
    n1 = N1 / l1
    n2 = N2 / l2
    theta = wp.atan2(wp.dot(wp.cross(n1, n2), E) / el, wp.dot(n1, n2))
    c = el * el / (l1 + l2)
    return theta, c, u1, u2, u3, u4


@wp.kernel
def dihedral_forces_kernel(
    x: wp.array(dtype=wp.vec3),
    quads: wp.array2d(dtype=wp.int32),
    sin_half_rest: wp.array(dtype=float),
    k: float,
    f: wp.array(dtype=wp.vec3),
):
    q = wp.tid()
    a = quads[q, 0]
    b = quads[q, 1]
    c = quads[q, 2]
    d = quads[q, 3]
    theta, cc, u1, u2, u3, u4 = _dihedral_terms(x[c], x[d], x[a], x[b])
    if cc < 0.0:
        return
    s = k * cc * (wp.sin(0.5 * theta) - sin_half_rest[q])
    wp.atomic_add(f, c, s * u1)
    wp.atomic_add(f, d, s * u2)
    wp.atomic_add(f, a, s * u3)
    wp.atomic_add(f, b, s * u4)


@wp.kernel
def dihedral_forces_hessian_kernel(
    x: wp.array(dtype=wp.vec3),
    quads: wp.array2d(dtype=wp.int32),
    sin_half_rest: wp.array(dtype=float),
    k: float,
    f: wp.array(dtype=wp.vec3),
    g: wp.array2d(dtype=wp.vec3),
):
    """Forces, and ``g_i = sqrt(k c psi'') u_i`` so that the quad's Hessian is ``g g^T``."""
    q = wp.tid()
    a = quads[q, 0]
    b = quads[q, 1]
    c = quads[q, 2]
    d = quads[q, 3]
    theta, cc, u1, u2, u3, u4 = _dihedral_terms(x[c], x[d], x[a], x[b])
    if cc < 0.0:
        for i in range(4):
            g[q, i] = wp.vec3(0.0)
        return
    s = k * cc * (wp.sin(0.5 * theta) - sin_half_rest[q])
    wp.atomic_add(f, c, s * u1)
    wp.atomic_add(f, d, s * u2)
    wp.atomic_add(f, a, s * u3)
    wp.atomic_add(f, b, s * u4)
    w = wp.sqrt(wp.max(k * cc * 0.5 * wp.cos(0.5 * theta), 0.0))
    g[q, 0] = w * u1  # order of the quad's vertices in g: c, d, a, b
    g[q, 1] = w * u2
    g[q, 2] = w * u3
    g[q, 3] = w * u4


@wp.kernel
def dihedral_energy_kernel(
    x: wp.array(dtype=wp.vec3),
    quads: wp.array2d(dtype=wp.int32),
    rest_theta: wp.array(dtype=float),
    k: float,
    out: wp.array(dtype=float),
):
    q = wp.tid()
    a = quads[q, 0]
    b = quads[q, 1]
    c = quads[q, 2]
    d = quads[q, 3]
    theta, cc, u1, u2, u3, u4 = _dihedral_terms(x[c], x[d], x[a], x[b])
    if cc < 0.0:
        return
    t0 = rest_theta[q]
    psi = 2.0 * (wp.cos(0.5 * t0) - wp.cos(0.5 * theta)) - (theta - t0) * wp.sin(0.5 * t0)
    wp.atomic_add(out, 0, k * cc * psi)


@wp.kernel
def rank1_matvec_kernel(
    x: wp.array(dtype=wp.vec3),
    quads: wp.array2d(dtype=wp.int32),
    g: wp.array2d(dtype=wp.vec3),
    out: wp.array(dtype=wp.vec3),
):
    """``out += g (g^T x)`` per quad, ``g`` stored in the vertex order c, d, a, b."""
    q = wp.tid()
    a = quads[q, 0]
    b = quads[q, 1]
    c = quads[q, 2]
    d = quads[q, 3]
    s = wp.dot(g[q, 0], x[c]) + wp.dot(g[q, 1], x[d]) + wp.dot(g[q, 2], x[a]) + wp.dot(g[q, 3], x[b])
    wp.atomic_add(out, c, s * g[q, 0])
    wp.atomic_add(out, d, s * g[q, 1])
    wp.atomic_add(out, a, s * g[q, 2])
    wp.atomic_add(out, b, s * g[q, 3])


@wp.kernel
def rank1_diagonal_kernel(
    quads: wp.array2d(dtype=wp.int32),
    g: wp.array2d(dtype=wp.vec3),
    diag: wp.array(dtype=wp.mat33),
):
    q = wp.tid()
    wp.atomic_add(diag, quads[q, 2], wp.outer(g[q, 0], g[q, 0]))
    wp.atomic_add(diag, quads[q, 3], wp.outer(g[q, 1], g[q, 1]))
    wp.atomic_add(diag, quads[q, 0], wp.outer(g[q, 2], g[q, 2]))
    wp.atomic_add(diag, quads[q, 1], wp.outer(g[q, 3], g[q, 3]))


def dihedral_angles(positions: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Signed angle between the two normals of every quad (0 = flat), float64, on the host."""
    x = np.asarray(positions, dtype=np.float64)
    a, b, c, d = (x[quads[:, i]] for i in range(4))
    x1, x2, x3, x4 = c, d, a, b
    n1 = cross3(x1 - x3, x1 - x4)
    n2 = cross3(x2 - x4, x2 - x3)
    e = x4 - x3
    n1 /= np.maximum(np.linalg.norm(n1, axis=1, keepdims=True), 1e-300)
    n2 /= np.maximum(np.linalg.norm(n2, axis=1, keepdims=True), 1e-300)
    e /= np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-300)
    return np.arctan2(np.einsum("ij,ij->i", cross3(n1, n2), e), np.einsum("ij,ij->i", n1, n2))


def _check_k(k) -> float:
    k = float(k)
    if not (math.isfinite(k) and k >= 0):
        raise ValueError(f"bending stiffness must be finite and >= 0 (N m), got {k}")
    return k


class _QuadTerm:
    def __init__(self, model, k):
        self.model = model
        self.k = _check_k(k)
        self.device = model.device
        quads = np.asarray(model.mesh.bend_quads, dtype=np.int64).reshape(-1, 4)
        self.num_quads = len(quads)
        self.quads_np = quads
        self.quads = wp.array(quads.astype(np.int32).reshape(-1, 4), dtype=wp.int32, ndim=2,
                              device=self.device)


class DihedralBending(_QuadTerm):
    """Bridson et al. 2003 dihedral-angle bending, ``k`` in N m (see the module docstring).

    The rest angle of every quad comes from the rest shape (``model.mesh.vertices``), so a
    non-flat rest shape is kept. For the implicit solver it provides `eval_with_hessian` (forces
    plus the Gauss-Newton Hessian ``k c psi'' g g^T``, PSD), `matvec_add` and `add_diagonal`.
    """

    name = "dihedral"

    def __init__(self, model, k):
        super().__init__(model, k)
        theta0 = dihedral_angles(model.mesh.vertices, self.quads_np) if self.num_quads else np.zeros(0)
        self.rest_theta_np = theta0
        d = self.device
        self.rest_theta = wp.array(theta0, dtype=wp.float32, device=d)
        self.sin_half_rest = wp.array(np.sin(0.5 * theta0), dtype=wp.float32, device=d)
        self.g = wp.zeros((max(self.num_quads, 1), 4), dtype=wp.vec3, device=d)

    def eval(self, x, v=None, f=None, time=None, **_):
        if self.num_quads and self.k > 0:
            launch(dihedral_forces_kernel, self.num_quads,
                   [x, self.quads, self.sin_half_rest, self.k, f], device=self.device)

    def eval_with_hessian(self, x, f):
        """Add the forces at ``x`` to ``f`` and refresh the Hessian approximation at ``x``."""
        if self.num_quads:
            launch(dihedral_forces_hessian_kernel, self.num_quads,
                   [x, self.quads, self.sin_half_rest, self.k, f, self.g], device=self.device)

    def energy(self, x, out):
        if self.num_quads and self.k > 0:
            launch(dihedral_energy_kernel, self.num_quads,
                   [x, self.quads, self.rest_theta, self.k, out], device=self.device)

    def matvec_add(self, x, out):
        """``out += H x`` with the Hessian approximation of the last `eval_with_hessian`."""
        if self.num_quads:
            launch(rank1_matvec_kernel, self.num_quads, [x, self.quads, self.g, out],
                   device=self.device)

    def add_diagonal(self, diag):
        if self.num_quads:
            launch(rank1_diagonal_kernel, self.num_quads, [self.quads, self.g, diag],
                   device=self.device)


# ------------------------------------------------------------------------------ quadratic
@wp.kernel
def quadratic_apply_kernel(
    x: wp.array(dtype=wp.vec3),
    quads: wp.array2d(dtype=wp.int32),
    w: wp.array(dtype=wp.vec4),
    sign: float,
    out: wp.array(dtype=wp.vec3),
):
    """``out += sign Q x`` per quad with ``Q = w w^T (x) I`` (``w = sqrt(3k/(A0+A1)) K``):
    ``sign = -1`` gives the forces ``f = -Q x``, ``sign = +1`` the Hessian product."""
    q = wp.tid()
    wq = w[q]
    s = wq[0] * x[quads[q, 0]] + wq[1] * x[quads[q, 1]] + wq[2] * x[quads[q, 2]] + wq[3] * x[quads[q, 3]]
    for i in range(4):
        wp.atomic_add(out, quads[q, i], (sign * wq[i]) * s)


@wp.kernel
def quadratic_energy_kernel(
    x: wp.array(dtype=wp.vec3),
    x_try: wp.array2d(dtype=wp.vec3),
    quads: wp.array2d(dtype=wp.int32),
    w: wp.array(dtype=wp.vec4),
    out: wp.array(dtype=float),
):
    """The energy at ``x`` into ``out[0]`` and at each row ``j`` of ``x_try`` (none: an empty
    array) into ``out[j + 1]``, in one pass over the quads (a line search's candidates)."""
    q = wp.tid()
    wq = w[q]
    a = quads[q, 0]
    b = quads[q, 1]
    c = quads[q, 2]
    d = quads[q, 3]
    s = wq[0] * x[a] + wq[1] * x[b] + wq[2] * x[c] + wq[3] * x[d]
    wp.atomic_add(out, 0, 0.5 * wp.dot(s, s))
    for j in range(x_try.shape[0]):
        s = wq[0] * x_try[j, a] + wq[1] * x_try[j, b] + wq[2] * x_try[j, c] + wq[3] * x_try[j, d]
        wp.atomic_add(out, j + 1, 0.5 * wp.dot(s, s))


@wp.kernel
def quadratic_diagonal_kernel(
    quads: wp.array2d(dtype=wp.int32),
    w: wp.array(dtype=wp.vec4),
    diag: wp.array(dtype=wp.mat33),
):
    q = wp.tid()
    wq = w[q]
    for i in range(4):
        wp.atomic_add(diag, quads[q, i], (wq[i] * wq[i]) * wp.identity(n=3, dtype=float))


def _cot(p, q, r):
    """cot of the angle at p in the triangle (p, q, r), vectorised."""
    u, v = q - p, r - p
    return np.einsum("ij,ij->i", u, v) / np.linalg.norm(cross3(u, v), axis=1)


def quadratic_weights(positions: np.ndarray, quads: np.ndarray):
    """Bergou's ``K`` (B x 4, in the quad order a, b, c, d) and ``A0 + A1`` (B,), float64."""
    x = np.asarray(positions, dtype=np.float64)
    a, b, c, d = (x[quads[:, i]] for i in range(4))
    t0, t1 = _cot(a, b, c), _cot(b, a, c)  # angles at a, b in triangle (a, b, c)
    t2, t3 = _cot(a, b, d), _cot(b, a, d)  # angles at a, b in triangle (a, b, d)
    K = np.stack([t1 + t3, t0 + t2, -t0 - t1, -t2 - t3], axis=1)
    area = 0.5 * (np.linalg.norm(cross3(b - a, c - a), axis=1)
                  + np.linalg.norm(cross3(b - a, d - a), axis=1))
    return K, area


class QuadraticBending(_QuadTerm):
    """Bergou et al. 2006 quadratic bending, ``E = 1/2 x^T Q x``, ``k`` in N m.

    ``Q`` is built once from the cotangent weights of the rest shape (see the module docstring);
    its Hessian is exact and constant, so `eval_with_hessian` is just `eval`.
    """

    name = "quadratic"

    def __init__(self, model, k):
        super().__init__(model, k)
        self._no_configs = wp.zeros((0, 0), dtype=wp.vec3, device=self.device)
        if self.num_quads:
            K, area = quadratic_weights(model.mesh.vertices, self.quads_np)
            theta0 = dihedral_angles(model.mesh.vertices, self.quads_np)
            if np.abs(theta0).max() > 1e-3:
                warnings.warn(
                    "QuadraticBending assumes a planar rest shape (Bergou et al. 2006); this mesh's "
                    f"rest shape bends by up to {np.degrees(np.abs(theta0).max()):.1f} degrees, "
                    "which the model will flatten. Use bending='dihedral' to keep it.",
                    stacklevel=3)
        else:
            K, area = np.zeros((0, 4)), np.ones(0)
        self.K = K
        self.area = area
        self.weights_np = K * np.sqrt(3.0 * self.k / area)[:, None]
        self.w = wp.array(self.weights_np.astype(np.float32).reshape(-1, 4), dtype=wp.vec4,
                          device=self.device)

    def eval(self, x, v=None, f=None, time=None, **_):
        if self.num_quads and self.k > 0:
            launch(quadratic_apply_kernel, self.num_quads, [x, self.quads, self.w, -1.0, f],
                   device=self.device)

    def eval_with_hessian(self, x, f):
        self.eval(x, None, f)

    def energy(self, x, out):
        if self.num_quads and self.k > 0:
            launch(quadratic_energy_kernel, self.num_quads,
                   [x, self._no_configs, self.quads, self.w, out], device=self.device)

    def energy_configs(self, x, x_try, out):
        """`energy` at ``x`` into ``out[0]`` and at each row ``j`` of ``x_try`` (a 2d array of
        configurations) into ``out[j + 1]``: one launch (a line search's candidates)."""
        if self.num_quads and self.k > 0:
            launch(quadratic_energy_kernel, self.num_quads,
                   [x, x_try, self.quads, self.w, out], device=self.device)

    def matvec_add(self, x, out):
        """``out += Q x`` (exact)."""
        if self.num_quads and self.k > 0:
            launch(quadratic_apply_kernel, self.num_quads, [x, self.quads, self.w, 1.0, out],
                   device=self.device)

    def add_diagonal(self, diag):
        if self.num_quads and self.k > 0:
            launch(quadratic_diagonal_kernel, self.num_quads, [self.quads, self.w, diag],
                   device=self.device)

    def scalar_entries(self):
        """``Q``'s scalar factor (``Q = S (x) I_3``) as coordinates: ``(rows, cols, values)``,
        float64, duplicates not summed (one 4 x 4 block per quad; empty when ``k == 0``). A
        solver with a constant matrix folds them into its own (`projective.PDSystemOperator`)."""
        if not (self.num_quads and self.k > 0):
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
        q = self.quads_np.astype(np.int64)
        rows = np.repeat(q, 4, axis=1).ravel()
        cols = np.tile(q, (1, 4)).ravel()
        w = self.weights_np
        vals = (w[:, :, None] * w[:, None, :]).ravel()
        return rows, cols, vals

    def dense_q(self) -> np.ndarray:
        """The scalar (N x N) matrix with ``Q = dense_q (x) I_3`` (tests and small meshes)."""
        n = self.model.num_vertices
        out = np.zeros((n, n))
        for qd, w in zip(self.quads_np, self.weights_np):
            out[np.ix_(qd, qd)] += np.outer(w, w)
        return out
