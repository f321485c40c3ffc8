"""Symplectic (semi-implicit) Euler for the mass-spring cloth (``physics.md`` section 2.2).

    f   <- sum of per-element forces (springs, bending, wind), scattered with atomics
    v_i <- (v_i + dt (f_i / m_i + g)) * exp(-damping dt)
    x_i <- x_i + dt v_i            (the NEW velocity: symplectic Euler)

Two launches per step without optional forces (springs, integrate; the integrate kernel clears
the force accumulator for the next step). Pinned vertices (inverse mass 0) are skipped.

Stability: conditional. For a spring network, ``dt < 2 / omega_max`` with ``omega_max^2`` bounded
by Gershgorin as ``max_i 2 sum_e k_e / m_i``; `SymplecticEuler.stable_dt` returns that bound and
the scene runner uses a fraction of it when no substep count is given. Past it the method
explodes (T1); the runner's divergence guard stops the run with `SimulationDiverged`.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from .base import Solver

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile


@wp.func
def symplectic_velocity(v: wp.vec3, f: wp.vec3, w: float, gravity: wp.vec3, decay: float, dt: float):
    """The new velocity of a free vertex (inverse mass ``w > 0``): ``(v + dt (f w + g)) decay``."""
    return (v + dt * (f * w + gravity)) * decay


@wp.kernel
def integrate_symplectic_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    f: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    gravity: wp.vec3,
    decay: float,
    dt: float,
):
    i = wp.tid()
    w = inv_mass[i]
    if w > 0.0:
        vi = symplectic_velocity(v[i], f[i], w, gravity, decay, dt)
        v[i] = vi
        x[i] = x[i] + dt * vi
    f[i] = wp.vec3(0.0)


class SymplecticEuler(Solver):
    """Explicit (symplectic) Euler. ``solver.step(state, dt)``.

    Args:
        model: the `ClothModel`.
        corrections: limits run after each step.
        collision: a `CollisionStage` (obstacles). Without limits, its far tests (and for
            static spheres and planes the whole contact) run inside the vertex update: the
            stage's kernels are made with this solver's `symplectic_velocity` (`Solver.fused`).
    """

    name = "explicit"

    def __init__(self, model, *, corrections=(), collision=None):
        super().__init__(model, corrections=corrections, collision=collision)
        self.f = wp.zeros(model.num_vertices, dtype=wp.vec3, device=self.device)

    fuses_contact = True

    def _advance(self, state, dt):
        m = self.model
        for term in m.force_terms:
            term.eval(state.x, state.v, self.f, state.time)
        fused = self.fused
        if fused is not None:  # obstacle contact's far tests inside the vertex update
            fused.integrate_and_apply(state, self._x_start, self.f, wp.vec3(*m.gravity),
                                      math.exp(-m.damping * dt), dt, symplectic_velocity)
            return
        wp.launch(
            integrate_symplectic_kernel,
            m.num_vertices,
            [state.x, state.v, self.f, m.inv_mass, wp.vec3(*m.gravity),
             math.exp(-m.damping * dt), dt],
            device=self.device,
        )

    @staticmethod
    def stable_dt(model) -> float:
        """Gershgorin bound ``2 / omega_max`` for the spring network (seconds).

        Conservative: ``omega_max^2 <= max_i 2 sum_{e at i} k_e / m_i``. Springs only; bending and
        wind are much softer for cloth and ignored. Spring dashpots lower it further: the bound
        is scaled by ``sqrt(1 + zeta^2) - zeta`` with ``zeta = c omega / (2 k)``.
        """
        if model.num_springs == 0:
            return math.inf
        ksum = np.zeros(model.num_vertices)
        np.add.at(ksum, model.spring_pairs[:, 0], model.spring_stiffness)
        np.add.at(ksum, model.spring_pairs[:, 1], model.spring_stiffness)
        free = model.inverse_masses > 0
        if not free.any():
            return math.inf
        lam = float((2.0 * ksum[free] * model.inverse_masses[free]).max())
        if lam <= 0:
            return math.inf
        omega = math.sqrt(lam)
        dt = 2.0 / omega
        if model.spring_damping > 0:
            kmax = float(model.spring_stiffness.max())
            zeta = model.spring_damping * omega / (2.0 * kmax) if kmax > 0 else 0.0
            dt *= math.sqrt(1.0 + zeta * zeta) - zeta
        return dt

    def suggest_substeps(self, frame_dt: float) -> int:
        """``ceil(frame_dt / (0.5 stable_dt))``: half the stability bound, for margin."""
        sdt = self.stable_dt(self.model)
        return 1 if not math.isfinite(sdt) else max(1, math.ceil(frame_dt / (0.5 * sdt)))
