"""Per-frame measurements: finiteness, edge strain, energies. One small host read per call.

Used by the scene runner's divergence guard and run summary, and by tests and benchmarks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile


@wp.kernel
def vertex_measure_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    gravity: wp.vec3,
    out: wp.array(dtype=float),
    sums: wp.array(dtype=wp.float64),
):
    # out: [non-finite count, unused, unused, max strain, elastic]; sums: [kinetic, gravitational
    # potential], each vertex's term and the sum in float64: in float32 a sheet's potential
    # rounds by up to ~1e-5 J per 1,000 vertices and J (a false "energy rise" of that size)
    i = wp.tid()
    xi = x[i]
    vi = v[i]
    ok = wp.isfinite(xi[0]) and wp.isfinite(xi[1]) and wp.isfinite(xi[2])
    ok = ok and wp.isfinite(vi[0]) and wp.isfinite(vi[1]) and wp.isfinite(vi[2])
    if not ok:
        wp.atomic_add(out, 0, 1.0)
        return
    m = wp.float64(mass[i])
    vd = wp.vec3d(wp.float64(vi[0]), wp.float64(vi[1]), wp.float64(vi[2]))
    xd = wp.vec3d(wp.float64(xi[0]), wp.float64(xi[1]), wp.float64(xi[2]))
    gd = wp.vec3d(wp.float64(gravity[0]), wp.float64(gravity[1]), wp.float64(gravity[2]))
    wp.atomic_add(sums, 0, wp.float64(0.5) * m * wp.dot(vd, vd))
    wp.atomic_add(sums, 1, -m * wp.dot(gd, xd))


@wp.kernel
def strain_measure_kernel(
    x: wp.array(dtype=wp.vec3),
    springs: wp.array2d(dtype=wp.int32),
    rest: wp.array(dtype=float),
    out: wp.array(dtype=float),
):
    e = wp.tid()
    s = wp.length(x[springs[e, 0]] - x[springs[e, 1]]) / rest[e] - 1.0
    if wp.isfinite(s):
        wp.atomic_max(out, 3, s)


@dataclass
class Measure:
    finite: bool
    kinetic: float
    gravity_potential: float
    elastic: float
    max_strain: float  # largest stretch over mesh edges, max(l/L - 1), >= 0

    @property
    def energy(self) -> float:
        return self.kinetic + self.gravity_potential + self.elastic


class Meter:
    """Preallocated measuring of a model's state (no allocation per call)."""

    def __init__(self, model):
        self.model = model
        self.out = wp.zeros(5, dtype=wp.float32, device=model.device)
        self.sums = wp.zeros(2, dtype=wp.float64, device=model.device)
        self._elastic = self.out[4:5]

    def __call__(self, state, energy: bool = True) -> Measure:
        m, out = self.model, self.out
        out.zero_()
        self.sums.zero_()
        wp.launch(vertex_measure_kernel, m.num_vertices,
                  [state.x, state.v, m.mass, wp.vec3(*m.gravity), out, self.sums],
                  device=m.device)
        if m.num_stretch_springs:
            wp.launch(strain_measure_kernel, m.num_stretch_springs,
                      [state.x, m.spring_indices, m.spring_rest_length, out], device=m.device)
        h = out.numpy()
        finite = h[0] == 0
        if energy and finite:
            for term in m.force_terms:
                term.energy(state.x, self._elastic)
            h = out.numpy()
        k, g = (float(v) for v in self.sums.numpy())
        return Measure(bool(finite), k, g, float(h[4]) if energy else float("nan"),
                       float(h[3]) if finite else float("nan"))


def edge_strains(model, positions) -> np.ndarray:
    """Host-side ``|x_i - x_j| / L - 1`` for every mesh edge (for tests and reports)."""
    x = np.asarray(positions, dtype=np.float64)
    e = model.mesh.edges
    rest = model.spring_rest[: len(e)]
    return np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1) / rest - 1.0
