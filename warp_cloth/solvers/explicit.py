"""Symplectic (semi-implicit) Euler for the mass-spring cloth (``physics.md`` section 2.2).

    f   <- sum of per-element forces (springs, bending, wind), scattered with atomics
    v_i <- (v_i + dt (f_i / m_i + g)) * exp(-damping dt)
    x_i <- x_i + dt v_i            (the NEW velocity: symplectic Euler)

Two launches per step without optional forces (springs, integrate; the integrate kernel clears
the force accumulator for the next step). Pinned vertices (inverse mass 0) are skipped.

Stability: conditional: ``dt < 2 / omega_max`` (less with spring dashpots), ``omega_max^2``
bounded by Gershgorin on ``M^-1 K`` with every stiff term in ``K``: springs, dihedral or quadratic
bending (``max_i sum_j ||H_ij|| / m_i``); `SymplecticEuler.stable_dt` returns that bound and the
scene runner uses half of it when no substep count is given. Past it the method
explodes (T1); the runner's divergence guard stops the run with `SimulationDiverged`.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..util import launch
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


def _dihedral_gradient_norms(positions, quads) -> np.ndarray:
    """``|u_1| .. |u_4|`` (B x 4, in the quad order a, b, c, d) of the dihedral-angle gradient
    (`warp_cloth.forces.bending`, notes' names ``x1 = c, x2 = d, x3 = a, x4 = b``) at ``positions``."""
    x = np.asarray(positions, dtype=np.float64)
    x3, x4, x1, x2 = (x[quads[:, i]] for i in range(4))
    N1 = np.cross(x1 - x3, x1 - x4)
    N2 = np.cross(x2 - x4, x2 - x3)
    E = x4 - x3
    el = np.maximum(np.linalg.norm(E, axis=1), 1e-300)[:, None]
    a = N1 / np.maximum(np.einsum("ij,ij->i", N1, N1), 1e-300)[:, None]
    b = N2 / np.maximum(np.einsum("ij,ij->i", N2, N2), 1e-300)[:, None]
    u1, u2 = el * a, el * b
    u3 = np.einsum("ij,ij->i", x1 - x4, E)[:, None] / el * a + \
        np.einsum("ij,ij->i", x2 - x4, E)[:, None] / el * b
    u4 = -np.einsum("ij,ij->i", x1 - x3, E)[:, None] / el * a - \
        np.einsum("ij,ij->i", x2 - x3, E)[:, None] / el * b
    return np.stack([np.linalg.norm(u, axis=1) for u in (u3, u4, u1, u2)], axis=1)


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
    # the self-contacts' velocity rule against a world at rest, not in the layers' frames
    # (`SelfCollision.layer_frames`): with those, three sheets stacked on a sphere (`stack`)
    # never settled under this solver (kinetic energy 0.02 -> 0.047 J from frame 50 to 150,
    # 0.0004 J with this rule; the other solvers settle). The layers' frames in the spans'
    # responses only, the rule at rest in `SelfCollision.hold`, settle it (0.0003 J) but
    # leave the free fall as it was: this solver's ~100 steps between responses are `hold`'s
    self_contact_layer_frames = False
    friction_by_position = True  # (`Solver.friction_by_position`)
    uniform_method = True

    def _advance(self, state, dt):
        m = self.model
        for term in m.force_terms:
            term.eval(state.x, state.v, self.f, state.time)
        fused = self.fused
        if fused is not None:  # obstacle contact's far tests inside the vertex update
            fused.integrate_and_apply(state, self._x_start, self.f, wp.vec3(*m.gravity),
                                      math.exp(-m.damping * dt), dt, symplectic_velocity,
                                      self.friction_by_position)
            return
        launch(
            integrate_symplectic_kernel,
            m.num_vertices,
            [state.x, state.v, self.f, m.inv_mass, wp.vec3(*m.gravity),
             math.exp(-m.damping * dt), dt],
            device=self.device,
        )

    @staticmethod
    def stiffness_row_sums(model, springs: bool = True, bending: bool = True, only=None):
        """Per-vertex Gershgorin row sums of the stiffness and damping matrices (N/m, N s/m).

        Returns ``(K, C)``, two (N,) arrays: ``K_i = sum_j ||H_ij||`` (3x3 block norms) over every
        stiff term of the model, ``C_i`` the same for the spring dashpots. ``springs=False``
        leaves the springs and their dashpots out (the force terms only: PBD, whose springs are
        constraints); ``bending=False`` leaves the bending terms out; ``only``: of the force
        terms, that one alone.

        - springs: ``||H_e|| <= k`` (equal at rest), so each spring adds ``2 k`` to both ends;
        - quadratic bending (exact, constant ``Q = w w^T (x) I``): ``|w_i| sum_j |w_j|`` per quad;
        - dihedral bending: its Hessian at the rest shape, ``k c cos(theta0/2)/2 g g^T``
          (`warp_cloth.forces.bending`; exact there, where the dropped terms vanish), adds
          ``k c cos(theta0/2)/2 |g_i| sum_j |g_j|`` per quad (``g`` from the rest geometry);
        - dashpots: ``c P`` per spring, ``2 c`` to both ends.

        Wind is ignored: a velocity-dependent drag far softer than these for cloth.
        """
        from ..forces.bending import DihedralBending, QuadraticBending

        n = model.num_vertices
        K = np.zeros(n)
        C = np.zeros(n)
        if springs and model.num_springs:
            pairs = np.asarray(model.spring_pairs).reshape(-1, 2)
            k = np.asarray(model.spring_stiffness, dtype=np.float64)
            for col in (0, 1):
                np.add.at(K, pairs[:, col], 2.0 * k)
                np.add.at(C, pairs[:, col], 2.0 * model.spring_damping)
        for term in model.force_terms if bending else ():
            if only is not None and term is not only:
                continue
            if isinstance(term, QuadraticBending) and term.num_quads and term.k > 0:
                g = np.abs(term.weights_np)  # (B, 4): ||w_i w_j I|| = |w_i| |w_j|
            elif isinstance(term, DihedralBending) and term.num_quads and term.k > 0:
                g = _dihedral_gradient_norms(model.mesh.vertices, term.quads_np)
                x = np.asarray(model.mesh.vertices, dtype=np.float64)
                q = term.quads_np
                e = np.linalg.norm(x[q[:, 1]] - x[q[:, 0]], axis=1)
                n1 = np.linalg.norm(np.cross(x[q[:, 2]] - x[q[:, 0]], x[q[:, 2]] - x[q[:, 1]]), axis=1)
                n2 = np.linalg.norm(np.cross(x[q[:, 3]] - x[q[:, 1]], x[q[:, 3]] - x[q[:, 0]]), axis=1)
                c = e * e / np.maximum(n1 + n2, 1e-300)
                g = g * np.sqrt(term.k * c * 0.5 * np.cos(0.5 * term.rest_theta_np))[:, None]
            else:
                continue
            row = g * g.sum(axis=1, keepdims=True)
            for col in range(4):
                np.add.at(K, term.quads_np[:, col], row[:, col])
        return K, C

    @staticmethod
    def stable_dt(model) -> float:
        """Stability bound of symplectic Euler for the model's stiff terms (seconds).

        For one mode ``x'' = -omega^2 x - gamma x'`` symplectic Euler with an explicit dashpot is
        stable for ``dt^2 omega^2 + 2 dt gamma < 4``, i.e. ``dt < 2/omega (sqrt(1 + zeta^2) -
        zeta)`` with ``zeta = gamma / (2 omega)`` (``2/omega`` without damping). ``omega^2`` and
        ``gamma`` are bounded by Gershgorin on ``M^-1 K`` and ``M^-1 C`` over the free vertices
        (`stiffness_row_sums`: springs, dihedral or quadratic bending, spring dashpots), and both
        maxima are used together (conservative when the stiffest and most damped modes differ).
        """
        free = model.inverse_masses > 0
        if not free.any():
            return math.inf
        K, C = SymplecticEuler.stiffness_row_sums(model)
        w = model.inverse_masses[free]
        lam = float((K[free] * w).max())
        gamma = float((C[free] * w).max())
        if lam <= 0:
            return math.inf if gamma <= 0 else 2.0 / gamma
        omega = math.sqrt(lam)
        zeta = gamma / (2.0 * omega)
        return 2.0 / omega * (math.sqrt(1.0 + zeta * zeta) - zeta)

    @staticmethod
    def stiffest(model) -> dict | None:
        """What sets the stable step (`stable_dt`): the free vertex of the largest ``K_i /
        m_i``, the stiff term with the largest share of its row (``"springs"``, ``"quadratic
        bending"``, ``"dihedral bending"``), the smallest angle (degrees) of the triangles at that vertex (a sliver
        makes bending stiff: its cotangent weights grow as one over its angle), and the stable
        step of the springs alone (inf without springs). None when nothing is stiff."""
        free = model.inverse_masses > 0
        if not free.any():
            return None
        K, _ = SymplecticEuler.stiffness_row_sums(model)
        w = np.where(free, model.inverse_masses, 0.0)
        if not (K * w).max() > 0:
            return None
        v = int(np.argmax(K * w))
        Ks, _ = SymplecticEuler.stiffness_row_sums(model, bending=False)
        share = {"springs": Ks[v]}
        for term in model.force_terms:
            one = SymplecticEuler.stiffness_row_sums(model, springs=False, only=term)[0]
            if one[v] > 0:
                share[f"{getattr(term, 'name', type(term).__name__)} bending"] = one[v]
        x = np.asarray(model.mesh.vertices, dtype=np.float64)
        angle = 180.0
        for tri in np.asarray(model.mesh.triangles)[(np.asarray(model.mesh.triangles) == v).any(1)]:
            for k in range(3):
                a, b, c = x[tri[k]], x[tri[(k + 1) % 3]], x[tri[(k + 2) % 3]]
                u, t = b - a, c - a
                nu, nt = np.linalg.norm(u), np.linalg.norm(t)
                if nu > 0 and nt > 0:
                    angle = min(angle, float(np.degrees(np.arccos(np.clip(u @ t / (nu * nt),
                                                                           -1.0, 1.0)))))
        lam = float((Ks * w).max())
        return {"vertex": v, "term": max(share, key=share.get), "min_angle": angle,
                "springs_dt": 2.0 / math.sqrt(lam) if lam > 0 else math.inf}

    def suggest_substeps(self, frame_dt: float) -> int:
        """``ceil(frame_dt / (0.5 stable_dt))``: half the stability bound, for margin."""
        sdt = self.stable_dt(self.model)
        return 1 if not math.isfinite(sdt) else max(1, math.ceil(frame_dt / (0.5 * sdt)))
