"""Per-frame measurements: finiteness, edge strain, energies. One small host read per call.

Used by the scene runner's divergence guard and run summary, and by tests and benchmarks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from .util import launch

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
        # [kinetic, gravity's potential, the springs' energy] in float64
        self.sums = wp.zeros(3, dtype=wp.float64, device=model.device)
        self._springs64 = self.sums[2:3]
        self._elastic = self.out[4:5]
        # gravity's potential of the simulation frame's offset (`ClothModel.origin`): energies
        # are the world frame's
        # (with the float32 masses and gravity the kernel sums, in float64)
        o = getattr(model, "origin", None)
        g32 = np.asarray(model.gravity, dtype=np.float32).astype(np.float64)
        m32 = np.asarray(model.masses, dtype=np.float32).astype(np.float64)
        self._g_offset = 0.0 if o is None else -float(np.dot(g32, o)) * float(m32.sum())

    def __call__(self, state, energy: bool = True) -> Measure:
        m, out = self.model, self.out
        out.zero_()
        self.sums.zero_()
        launch(vertex_measure_kernel, m.num_vertices,
               [state.x, state.v, m.mass, wp.vec3(*m.gravity), out, self.sums],
               device=m.device)
        if m.num_stretch_springs:
            launch(strain_measure_kernel, m.num_stretch_springs,
                   [state.x, m.spring_indices, m.spring_rest_length, out], device=m.device)
        h = out.numpy()
        finite = h[0] == 0
        if energy and finite:
            for term in m.force_terms:
                if hasattr(term, "energy64"):  # the springs: float64 (stiff ones round in float32)
                    term.energy64(state.x, self._springs64)
                else:
                    term.energy(state.x, self._elastic)
            h = out.numpy()
        k, g, springs = (float(v) for v in self.sums.numpy())
        g += self._g_offset
        return Measure(bool(finite), k, g, float(h[4]) + springs if energy else float("nan"),
                       float(h[3]) if finite else float("nan"))


def edge_strains(model, positions) -> np.ndarray:
    """Host-side ``|x_i - x_j| / L - 1`` for every mesh edge (for tests and reports)."""
    x = np.asarray(positions, dtype=np.float64)
    e = model.mesh.edges
    rest = model.spring_rest[: len(e)]
    return np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1) / rest - 1.0


def frame_energy(model, state, *, velocity=(0.0, 0.0, 0.0), angular_velocity=(0.0, 0.0, 0.0),
                 center=(0.0, 0.0, 0.0), meter: Meter | None = None) -> float:
    """The cloth's energy seen from a frame that moves rigidly with an obstacle (J, host read).

    A moving obstacle does work on the cloth, so the cloth's energy (`Measure.energy`) may rise
    while the obstacle moves. Seen from a frame that moves with the obstacle, the obstacle is
    at rest and its contact forces (normal and friction) can only take energy out; what must
    then never rise is::

        J = sum_i 1/2 m_i |v_i - u_i|^2 + gravity potential + elastic - sum_i 1/2 m_i |w x r_i|^2

    with ``u_i = velocity + w x r_i``, ``r_i = x_i - center``, ``w = angular_velocity``: for a
    translating frame (``w = 0``) the kinetic energy relative to ``velocity``; for a frame
    turning about a vertical axis through ``center`` the Jacobi integral (the last sum is the
    centrifugal potential; the Coriolis force does no work). This is how "no energy gained
    except the work of a moving obstacle" is checked (`tests/test_frame_energy.py` on the
    spinning sphere, the README's figures also on a sliding torus): over steps in which the
    obstacle's motion is steady, ``J`` must not rise.

    Args:
        model: the `ClothModel`.
        state: its state (``x``, ``v``).
        velocity: m/s, the frame's translation.
        angular_velocity: rad/s; must be parallel to gravity (else gravity, turning in that
            frame, does work there and ``J`` is not conserved): ValueError otherwise.
        center: m, a point on the rotation axis.
        meter: a `Meter` of the model to reuse (made when None).
    """
    U = np.asarray(velocity, dtype=np.float64).reshape(3)
    w = np.asarray(angular_velocity, dtype=np.float64).reshape(3)
    c = np.asarray(center, dtype=np.float64).reshape(3)
    for name, a in (("velocity", U), ("angular_velocity", w), ("center", c)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"frame_energy: {name} must be finite, got {a.tolist()}")
    g = np.asarray(model.gravity, dtype=np.float64)
    if np.linalg.norm(np.cross(w, g)) > 1e-9 * max(np.linalg.norm(w) * np.linalg.norm(g), 1e-30):
        raise ValueError(f"frame_energy: angular_velocity {w.tolist()} must be parallel to gravity "
                         f"{g.tolist()} (gravity would do work in a frame turning about another "
                         f"axis)")
    meter = meter if meter is not None else Meter(model)
    m = meter(state)
    mass = model.mass.numpy().astype(np.float64)
    x = state.x.numpy().astype(np.float64)
    v = state.v.numpy().astype(np.float64)
    rot = np.cross(w, x - c)
    u = U + rot
    rel = 0.5 * float(np.sum(mass * np.sum((v - u) ** 2, axis=1)))
    centrifugal = 0.5 * float(np.sum(mass * np.sum(rot * rot, axis=1)))
    return rel + m.gravity_potential + m.elastic - centrifugal
