"""Position-based dynamics (``physics.md`` section 2.9): Jacobi with atomics, coloured Gauss-Seidel,
and compliance (XPBD).

Müller et al. 2007, *Position Based Dynamics*; Macklin, Müller and Chentanez 2016, *XPBD:
Position-Based Simulation of Compliant Constrained Dynamics*; the GAMES103 notes L1257-1368.
One step (the notes' PBD simulator, L1321-1348):

    v  <- (v + dt (f_ext / m + g)) exp(-damping dt)      external forces except the springs
    x* <- x + dt v                                        prediction
    [each contact correction's begin_iterations(x*, x_start, dt), if any: contact planes]
    repeat `iterations` times: project every constraint   (Jacobi or coloured Gauss-Seidel)
        [then each contact correction's project_positions(x, x_start, dt), if any]
    v  <- v + (x - x*) / dt                               (L1344; = (x - x_old)/dt)

The velocity update is written in the notes' incremental form rather than ``(x - x_old)/dt``:
the two are equal in exact arithmetic, but with float32 positions the latter loses the
gravity increment ``g dt^2`` once it falls below half an ulp of the coordinates (about 6e-8 m at
1 m: ``dt < 8e-5 s``), which freezes the cloth; the incremental form keeps it in the velocity.

**Constraints.** A distance constraint ``C = |x_i - x_j| - L`` on every spring of the model
(mesh edges, and the shear and bending springs when the model has them) and, with
``bending_compliance`` set, an *across-edge distance* bending constraint between the two vertices
opposite each interior edge (``mesh.bend_quads[:, 2:4]``, the notes' bending pairs, L1171). A
dihedral bending constraint is not implemented; the model's ``"dihedral"``/``"quadratic"`` bending
and wind act as explicit forces in the prediction.

**Stiff force terms.** Those explicit forces are stable only for steps below their own bound,
which PBD's substep count does not follow: bending stiffens as ``1/h^2`` with the cell size ``h``,
and on 2 mm cells (bend stiffness 1e-4 N m, 64 substeps at 60 fps) a sheet reached 5,000 m/s
(dihedral: 5e5 m/s, then the strain bound). So the prediction divides each vertex's force by
``m_i + dt^2 K_i`` instead of ``m_i``, ``K_i`` the Gershgorin row sum of the force terms'
stiffness (`SymplecticEuler.stiffness_row_sums` without the springs: exact for quadratic bending,
dihedral bending's at the rest shape). Then ``dt^2 lambda_max((M + dt^2 K)^-1 H) <= 1 < 4`` for
the bending Hessian ``H``, the symplectic bound, at any ``dt``: one diagonal (Jacobi) step of an
implicit solve. Where ``dt^2 K_i / m_i`` is small this is the plain force (the scale
``1 + dt^2 K_i / m_i`` on the built-in scenes with bending: at most 1.11 on the twist's 2 cm
cells, 1.02 on the fold, 1.003 on the stack); where it is large the bending is stable but slower
than the real one (its modes get the extra inertia). ``stats["force_mass_scale"]`` (the largest
scale) and ``stats["force_scaled_vertices"]`` (those above 2) say how much, and the first frame
with any vertex above 2 says so once (`frame_end`); more substeps make it exact.

**Jacobi with atomics** (default; the notes' L1310-1318, the GPU way; as written here with
``blend="vertex"``, the default sharing each constraint's correction instead, *Momentum*): one
thread per constraint
computes its mass-weighted correction (the single-spring projection, L1275-1295, shared with
`warp_cloth.limits.StrainLimit`) and ``atomic_add``s it into a per-vertex accumulator; one thread
per vertex blends ``x <- (x_acc + alpha x) / (n + alpha)``, written with deltas as
``x <- x + sum(dx) / (n + alpha)``. Every constraint is an equality, so ``n_i`` (constraints at
vertex i) is the same every iteration: it is counted once at set-up instead of with a second atomic.
``alpha`` is the ``relaxation`` option (default 0: plain averaging, a convex combination of the
per-constraint projections, so it cannot overshoot); the GAMES103 lab's 0.2 (physics.md 4.B)
under-relaxes: measured on the default hanging scene (64 substeps, 10 iterations) it lets the
first fall stretch 5.7 % instead of 3.7 %. Two launches per iteration; the last blend also updates the velocity.
Jacobi is order-independent (T26) up to float summation order.

**Over-relaxation** (``over_relaxation``, default 1.7 for plain Jacobi PBD; with the default
``blend="constraint"`` (*Momentum* below) ``omega`` scales each constraint's share instead,
``min(omega, m)/(m + alpha)``; the description and the figures of this paragraph are the
per-vertex blend's, ``blend="vertex"``): the blend moves a
vertex by ``omega`` times its averaged correction,
``x <- x + min(omega, n) sum(dx) / (n + alpha)``, as Macklin et al. (2014, "Unified particle
physics for real-time applications") do with their constraint-averaged Jacobi (successive
over-relaxation, ``omega`` in [1, 2]); capped at the plain sum of the corrections
(``omega <= n``), which is exact for a vertex of one constraint (T23) and for independent
corrections, where averaging is exact only for identical ones. Averaging divides every
correction by the vertex's constraint count (6 to 8 on a grid with shear springs), so plain
Jacobi propagates a load one small fraction of an edge per iteration; a cloth held only by
contact has no tethers to carry it. Measured at defaults (64 substeps x 10 iterations, max
edge strain, ms a frame;
``omega`` 1 / 1.5 / 1.7 / 1.85, before the cap, which changed none of the 1.7 figures): the
table's sheet, hanging over the box's edge, 8.1 % (at the stretch guard, 1,004 ms) / 6.8 % (625)
/ 5.0 % (369) / 6.6 % (381), ending at 7.9 / 6.8 / 2.6 / 2.8 %; fold 4.3 / 1.9 / 1.3 / 1.6 %
(largest one-frame energy rise 2.7e-2 J at 1, 1.2e-2 at 1.7); stack 1.6 / 1.3 / 1.2 / 1.9 %;
drape 2.0 / 1.5 / 2.6 / 1.9 %; mesh 2.5 / 1.9 / 2.0 / 2.0 %; spin 3.7 / 2.8 / 2.1 / 2.0 %; the
hanging cloth's first fall 2.7 / 1.9 / 2.8 / 2.8 % (its tethers carry the load there); finer
cloth, 1 / 1.5: table at 40 x 40 cells 8.1 / 7.9 %, drape 40 x 40 3.1 / 2.2 %, hanging 48 x 48
7.9 / 4.3 %. ``omega = 1`` is the notes'
blend (T26 compares that with Gauss-Seidel). Not with Gauss-Seidel or multipliers (XPBD keeps
``x - x* = M^-1 grad C^T lambda`` with its own shares).

**Momentum** (``blend``): averaged per vertex (the notes' blend, ``blend="vertex"``), a
constraint between vertices of different counts ``n_i != n_j`` moves its ends by different
fractions of its projection: it no longer keeps the pair's momentum, and the cloth gains energy.
Measured on the fold (64 substeps x 10 iterations, no self-collision): while the lifted half fell,
kinetic + gravitational energy rose 0.053 J above its start (on 0.19 J) by frame 11, more
iterations did not help and 256 substeps left 0.018 J; Gauss-Seidel, explicit and implicit
Euler lost energy there. So by default (``blend="constraint"``) each constraint moves both its
ends by one share, ``min(omega, m)/(m + alpha)`` with ``m = max(n_i, n_j)`` (the larger count:
at every vertex the shares of plain averaging or less), as XPBD's Jacobi below: the fold then
loses energy like the other solvers. Measured at defaults (`python /tmp/s9/contact_table.py
SCENES pbd`, vertex -> constraint blend; max strain, largest one-frame energy rise, ms a frame):
fold 1.31 -> 0.23 %, 1.2e-2 -> 2.6e-7 J, 101 -> 59 ms; table 4.97 -> 3.64 %, 7.1e-3 -> 1.2e-4 J,
369 -> 150 ms; drape 2.6 -> 2.15 %; stack 1.22 -> 1.73 %, 2.0e-4 -> 3.9e-3 J; the hanging
sheet 2.76 -> 1.71 % (final 0.83 -> 0.42 %; its energy after 2 s 0.74 -> 1.24 J of 1.47: less
numerical damping), at 1 / 2 / 4 substeps without the stretch guard 50 -> 52 %, 20 -> 23 %,
10.5 -> 11.4 % (a vertex with fewer constraints than its neighbour takes a smaller share).

**Gauss-Seidel** (``gauss_seidel=True``, L1297-1308): the constraints are greedily coloured once at
set-up so that no two constraints of a colour share a vertex; each colour is then one parallel
launch that updates positions in place. The result equals sequential Gauss-Seidel in colour
order. One launch per colour per iteration (about 7 colours on a triangle grid).

**Compliance (XPBD)**: ``compliance=a`` (m/N, the inverse of a spring stiffness) gives every
distance constraint the XPBD update ``dlambda = (-C - a~ lambda)/(w_i + w_j + a~)`` with
``a~ = a/dt^2`` and ``lambda`` reset each step, so the converged stiffness is ``1/a`` whatever the
iteration count and time step. ``compliance="springs"`` uses ``1/k`` of each spring of the model
(the mass-spring physics). ``compliance=0`` is plain PBD; ``None`` (default) is plain PBD without
the multiplier bookkeeping. In Jacobi mode with multipliers each constraint takes its own share
``s_e = 1/(max(n_i, n_j) + alpha)`` of its update ``dlambda`` (both positions and ``lambda`` move by
``s_e dlambda``) and the blend adds the shares unscaled: at every vertex the shares sum to at most
1, so the blend stays a sub-convex combination, and ``x - x* = M^-1 grad C^T lambda`` holds exactly,
so the converged state is XPBD's (the exact spring equilibrium at rest). Averaging per vertex
instead, as plain PBD does, moves the two ends of a constraint by different fractions ``1/n_i``,
``1/n_j``; no single ``lambda`` then matches both, and the strip settled 5 % too soft at
boundaries whatever the iteration count (tests/test_pbd.py checks the exact equilibrium).

**Pins** have zero inverse mass: prediction and projection never move them; scripted pins are put
at their targets by the base class before the step and keep the velocity it gives them.

**Long-range attachments (tethers)**, Kim, Chentanez and Müller 2012, *Long Range Attachments: A
Method to Simulate Inextensible Clothing in Computer Games*: every free vertex is tied to its
``tether_pins`` (default 2) nearest pins, with rest length the geodesic distance on the rest mesh
(`tether_anchors`: a multi-source Dijkstra with the fast-marching triangle update, exact on a
planar rest mesh) times ``1 + tether_slack``. A tether is unilateral: when the vertex is farther
from the pin's *current* position (scripted pins included) than its rest length, it is put back on
that sphere; nearer, it is free. One thread per vertex projects its own tethers once per iteration,
after the distance constraints (in place, no atomics). Without them the weight of a hanging cloth
must travel up the whole chain of springs to the pins, one edge per Jacobi iteration, so at large
steps the stretch grows every frame until the divergence guard stops the run (946 % at frame 40 of
the default hanging scene at 1 substep x 10 iterations); with them the cloth can never be farther
from its pins than its rest shape allows. They are on by default for plain PBD on a model with
pins (``tethers=None``); not with ``compliance``, since an XPBD material is meant to stretch by
its compliance (pass ``tethers=True`` to cap it at the rest length anyway). What remains is local
stretch between neighbours, which depends on the iterations and substeps: measured on the default
hanging scene (32 x 32, 60 fps, 2 s, 10 iterations) it is bounded at every step but above 10 % at 1
and 2 substeps (README, *Methods*: the table).

**Contact inside the iterations.** A correction in ``corrections`` that has a method
``project_positions(x, x_start, dt)`` is called inside every iteration, after the constraint
projection (positions only), so constraints and contact are satisfied together; one that also
has ``begin_iterations`` is given the predicted positions first, once per step
(`ObstacleContact` makes its contact planes there, so the iterations only project onto planes).
The base class still calls every correction's ``apply(state, x_start, dt)`` after the step
(exact contact of every vertex, velocity impulse, friction, limits).

**Self-contacts inside the iterations** (``self_contacts``, with a `CollisionStage` that has
self-collision): in a step of at least `SELF_CONTACT_DT` (by default; always with
``self_contacts=True``) the stage lists the vertex-triangle and edge-edge pairs whose
predicted paths come within two thicknesses (`CollisionStage.begin_iterations`), and every
iteration projects them after the springs (one Jacobi round, positions only; a pair that
started closer than the thickness is held where it started), as do the stretch guard's sweeps
after the response. The self-collision response after the step stays the guarantee. In long
steps it otherwise had to undo whole steps of sinking layers, and its projections and impact
zones stretched the edges beside them: three sheets on the stack's sphere at one step a
frame, 30 fps, ended at 31 % strain with 274 impact zones and a vertex 2.6 mm inside the
ground's thickness; with them 10.7 %, 3 zones, none inside. Short steps (the default 64 a
frame) do not need them and would pay a detection each.

Stability and limitations (honest): positions of a pinned cloth stay bounded with the tethers
(without pins or tethers PBD's stretch can grow without bound at large steps), but it is not
physically accurate: without compliance the stiffness depends on the iteration
count, the time step and the mesh resolution (T27), and Jacobi converges slowly on long chains
(a sheet hanging from two corners stretches more with fewer substeps or iterations). Use
substeps rather than iterations for stiffness (``default_substeps`` below), or compliance plus
enough iterations for a resolution-independent material. Self-collision is the collision
stage's (the response after the step, and the self-contacts above).
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..forces.springs import SpringForce
from ..limits import color_constraints, edge_projection
from ..tethers import PinStretch, model_tether_anchors, tether_anchors, tether_kernel  # noqa: F401 (tether_anchors re-exported)
from ..util import launch
from .base import Solver
from .explicit import SymplecticEuler

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile

__all__ = ["PositionBased", "color_constraints"]


#: the stretch guard's bound (`PositionBased` ``max_stretch``): 8 % over the rest length
DEFAULT_MAX_STRETCH = 0.08

#: plain PBD's Jacobi blend over-relaxation (`PositionBased` ``over_relaxation``, module doc)
DEFAULT_OVER_RELAXATION = 1.7

#: s; steps at least this long project the self-contacts of their predicted paths in every
#: iteration (`PositionBased` ``self_contacts="auto"``). Measured (three 10 x 10 sheets dropped
#: on the stack's sphere, 60 fps, 90 frames): one step a frame 15.1 -> 9.4 % max strain, 28
#: impact zones -> none, least clearance to the ground 3.9 -> 5.0 mm (the thickness); two
#: steps 10.8 -> 9.2 %; at four (4.2 ms) and more no gain, and at PBD's default 64 steps the
#: detection every step would cost several times the step (16 x 16 fold: 52 -> 196 ms a frame)
SELF_CONTACT_DT = 0.006


# ---------------------------------------------------------------------------- kernels
@wp.kernel
def predict_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    xp: wp.array(dtype=wp.vec3),
    f: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    stiff: wp.array(dtype=float),
    gravity: wp.vec3,
    decay: float,
    dt: float,
):
    """v <- (v + dt (f w_f + g)) decay; x <- x + dt v (free vertices); xp <- x (the prediction
    x*); clear f. ``w_f = w / (1 + dt^2 K w)``, ``K`` the vertex's Gershgorin row sum of the force
    terms' stiffness (``stiff``; 0 without bending: ``w_f = w`` exactly)."""
    i = wp.tid()
    xi = x[i]
    w = inv_mass[i]
    if w > 0.0:
        wf = w / (1.0 + dt * dt * stiff[i] * w)
        vi = (v[i] + dt * (f[i] * wf + gravity)) * decay
        v[i] = vi
        xi = xi + dt * vi
        x[i] = xi
    xp[i] = xi
    f[i] = wp.vec3(0.0)


@wp.kernel
def jacobi_distance_kernel(
    x: wp.array(dtype=wp.vec3),
    cons: wp.array2d(dtype=wp.int32),
    rest: wp.array(dtype=float),
    compliance: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    escale: wp.array(dtype=float),
    inv_dt2: float,
    use_lambda: int,
    vertex_blend: int,
    delta: wp.array(dtype=wp.vec3),
):
    """One thread per distance constraint: scatter its correction into ``delta`` (atomics).

    The correction is scaled by the constraint's own share ``escale[e]`` (plain PBD:
    ``min(omega, m)/(m + alpha)``, XPBD: ``1/(m + alpha)``, ``m = max(n_i, n_j)``), and with
    multipliers the multiplier advances by exactly what both ends realise; the blend then adds
    ``delta`` unscaled. With ``vertex_blend`` (plain PBD, ``blend="vertex"``: the notes' blend)
    the projection is scattered whole and the blend averages per vertex. See the module
    docstring."""
    e = wp.tid()
    i = cons[e, 0]
    j = cons[e, 1]
    wi = inv_mass[i]
    wj = inv_mass[j]
    g = wp.vec3(0.0)
    if use_lambda == 0:
        g = edge_projection(x[i], x[j], wi, wj, rest[e])
        if vertex_blend == 0:
            g = g * escale[e]
    else:
        wsum = wi + wj
        d = x[i] - x[j]
        l = wp.length(d)
        if l < 1.0e-12 or wsum <= 0.0:
            return
        at = compliance[e] * inv_dt2
        dl = escale[e] * (rest[e] - l - at * lam[e]) / (wsum + at)
        lam[e] = lam[e] + dl  # both ends move by w dl grad C: positions and lambda agree
        g = dl / l * d
    wp.atomic_add(delta, i, wi * g)
    wp.atomic_sub(delta, j, wj * g)


@wp.kernel
def jacobi_blend_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    xp: wp.array(dtype=wp.vec3),
    delta: wp.array(dtype=wp.vec3),
    count: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    alpha: float,
    omega: float,
    inv_dt: float,
    finish: int,
):
    """x <- x + min(omega, n) sum(dx)/(n + alpha) (never more than the sum: a vertex of one
    constraint is projected exactly); clear delta; last iteration: v <- v + (x - x*)/dt."""
    i = wp.tid()
    c = count[i]
    xi = x[i]
    if c > 0.0:
        xi = xi + delta[i] * wp.min(omega, c) / (c + alpha)  # exact when omega = 1
        x[i] = xi
    delta[i] = wp.vec3(0.0)
    if finish != 0 and inv_mass[i] > 0.0:
        v[i] = v[i] + (xi - xp[i]) * inv_dt


@wp.kernel
def gs_distance_kernel(
    x: wp.array(dtype=wp.vec3),
    cons: wp.array2d(dtype=wp.int32),
    rest: wp.array(dtype=float),
    compliance: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    inv_dt2: float,
    use_lambda: int,
    offset: int,
):
    """One colour of Gauss-Seidel: constraints ``offset + tid`` share no vertex; update in place."""
    e = wp.tid() + offset
    i = cons[e, 0]
    j = cons[e, 1]
    wi = inv_mass[i]
    wj = inv_mass[j]
    xi = x[i]
    xj = x[j]
    g = wp.vec3(0.0)
    if use_lambda == 0:
        g = edge_projection(xi, xj, wi, wj, rest[e])
    else:
        wsum = wi + wj
        d = xi - xj
        l = wp.length(d)
        if l < 1.0e-12 or wsum <= 0.0:
            return
        at = compliance[e] * inv_dt2
        dl = (rest[e] - l - at * lam[e]) / (wsum + at)
        lam[e] = lam[e] + dl
        g = dl / l * d
    x[i] = xi + wi * g
    x[j] = xj - wj * g


@wp.kernel
def velocity_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    xp: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    inv_dt: float,
):
    """The notes' velocity update v <- v + (x_new - x*)/dt (L1344) for free vertices."""
    i = wp.tid()
    if inv_mass[i] > 0.0:
        v[i] = v[i] + (x[i] - xp[i]) * inv_dt


# ---------------------------------------------------------------------------- set-up helpers
def _check_compliance(name, value, allow_springs: bool):
    if value is None:
        return None
    if allow_springs and isinstance(value, str):
        if value != "springs":
            raise ValueError(f"{name} must be a number >= 0 (m/N), None or 'springs', got {value!r}")
        return value
    try:
        a = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number >= 0 (m/N) or None, got {value!r}") from None
    if not (math.isfinite(a) and a >= 0.0):
        raise ValueError(f"{name} must be a finite number >= 0 (m/N), got {value!r}")
    return a


class PositionBased(Solver):
    """Position-based dynamics, optionally compliant (XPBD). ``solver.step(state, dt)``.

    Args:
        model: the `ClothModel`.
        iterations: constraint-projection iterations per step (default 10).
        gauss_seidel: project colour by colour in place (coloured Gauss-Seidel) instead of the
            Jacobi blend (default False).
        compliance: ``None`` (default: plain PBD), a number ``>= 0`` in m/N (XPBD, the same for
            every distance constraint; 0 is the notes' plain PBD, without over-relaxation), or
            ``"springs"`` (XPBD with ``1/k`` of each of the model's springs).
        relaxation: the Jacobi blend's ``alpha >= 0`` in ``x <- (x_acc + alpha x)/(n + alpha)``
            (default 0: plain averaging; the GAMES103 lab uses 0.2). Unused by Gauss-Seidel.
        over_relaxation: ``omega`` in ``(0, 2)``: plain PBD's Jacobi blend moves each vertex by
            ``omega`` times its averaged correction (successive over-relaxation, module doc).
            ``None`` (default): `DEFAULT_OVER_RELAXATION` (1.7) for plain Jacobi PBD, 1 (the
            notes' plain blend) with Gauss-Seidel or compliance, where another value is refused.
        blend: how plain Jacobi PBD combines the constraints' corrections: ``"constraint"``
            (default) moves both ends of each constraint by the same share ``min(omega, m)/(m +
            alpha)`` of its projection, ``m = max(n_i, n_j)``, so every constraint keeps the
            momentum; ``"vertex"`` is the notes' blend (L1310-1318), each vertex's corrections
            averaged over its own count ``n_i`` (``x <- x + min(omega, n_i) sum(dx)/(n_i +
            alpha)``), which moves a constraint's two ends by different fractions and gains
            energy (module docstring, *Momentum*). Unused by Gauss-Seidel and XPBD (whose
            shares are the constraint's own).
        bending_compliance: ``None`` (default: no bending constraint) or a number ``>= 0`` in m/N:
            adds an across-edge distance constraint between the two vertices opposite every
            interior edge, with this XPBD compliance (0 = rigid).
        tethers: long-range attachments to the pins (see the module docstring): ``None``
            (default: on when the model has pins and ``compliance`` is None), True or False.
        tether_pins: how many of the nearest pins each vertex is tied to (default 2).
        tether_slack: tethers act beyond ``(1 + tether_slack)`` times the geodesic rest distance
            (default 0: the cloth may not be farther from a pin than in its rest shape).
        max_stretch: the stretch guard, a `warp_cloth.limits.StrainLimit` to ``1 + max_stretch``
            run after the iterations (its sweeps repeat on the device until every mesh edge is
            within it; none when none is over). ``"auto"`` (default): 0.08 (8 %) for plain PBD,
            none with ``compliance`` (an XPBD material is meant to stretch) or with pins that
            follow a `PinPath` (they may impose any stretch); ``None``: none. Never over edges
            without a stretch spring (or of stiffness 0). ``stretch_guard``: the limit or None.
            PBD's stiffness comes from substeps: at 1, 2 and 4 substeps of 10 Jacobi iterations
            the default hanging cloth stretched 66 %, 29 % and 13 % even with tethers (Gauss-Seidel
            23 %, 11 %, 3.9 %); with the guard 8.1 % at 3.1 ms/frame against 1.4 ms unguarded
            at 1 substep. At the default substeps it never acts (1.3 % there).
        self_contacts: ``"auto"`` (default), True or False: whether the iterations project the
            self-contacts of the step's predicted paths (module docstring): ``"auto"`` in steps
            of at least `SELF_CONTACT_DT` (6 ms: one or two steps a frame at 60 fps), True in
            every step, False never. Needs a collision stage with self-collision and
            ``self_in_solve`` (otherwise nothing). The stage's ``stats`` give the last step's
            count (``self_iteration_contacts``) and the pairs dropped for want of room
            (``self_iteration_dropped``, reported and the record doubled at frame ends).
        corrections: limits / contact passes (see the module docstring for contact inside the
            iterations).

    Attributes:
        default_substeps: substeps per frame the scene runner uses when none is given: 64 for
            Jacobi, 32 for Gauss-Seidel. Measured on the default hanging scene (1 m, 32 x 32 cells,
            0.15 kg/m^2, 60 fps, 10 iterations), these keep the maximum edge strain of the first
            fall at about 1.3 % (Jacobi) and 2.2 % (Gauss-Seidel) with the default tethers (3.7 %
            and 2.9 % without), settling under 1 %; 16 substeps let Jacobi stretch 6.1 % (36 %
            without tethers). PBD stiffness comes from substeps more than iterations:
            1 iteration x 320 substeps gives 1.9 % at about 60 % of the cost (small steps).
            The count is not resolution-aware: on the finer 64 x 32-cell cloth of
            ``warp-cloth bench pbd`` the same settings ended 0.5 s at 10.9 % strain without
            tethers (explicit: 3.6 %); with them 0.9 % (2.3 % at most, Gauss-Seidel 0.28 %).
        constraint_pairs: (C, 2) host copy of the constraints in the order they are stored (sorted
            by colour for Gauss-Seidel); ``color_offsets`` gives each colour's range.
        tethers: whether tethers are on; ``num_tethers`` how many; ``tether_anchor_indices``
            and ``tether_rest``: (N, k) host arrays of each vertex's pins (-1: none) and rest
            lengths in metres.
    """

    name = "pbd"
    uniform_method = True
    default_substeps = 64

    def __init__(self, model, *, iterations: int = 10, gauss_seidel: bool = False,
                 compliance=None, relaxation: float = 0.0, bending_compliance=None,
                 tethers=None, tether_pins: int = 2, tether_slack: float = 0.0,
                 max_stretch="auto", over_relaxation=None, blend: str = "constraint",
                 self_contacts="auto", corrections=(), collision=None):
        if not (self_contacts == "auto" or isinstance(self_contacts, (bool, np.bool_))):
            raise ValueError(f"self_contacts must be 'auto', True or False, got "
                             f"{self_contacts!r}")
        self.self_contacts = self_contacts if self_contacts == "auto" else bool(self_contacts)
        self._self_iter = False  # the collision stage is ready for them (`set_collision`)
        super().__init__(model, corrections=corrections, collision=collision)
        if blend not in ("constraint", "vertex"):
            raise ValueError(f"blend must be 'constraint' or 'vertex', got {blend!r}")
        self.blend = blend
        if isinstance(iterations, bool) or int(iterations) != iterations or iterations < 1:
            raise ValueError(f"iterations must be a positive integer, got {iterations!r}")
        self.iterations = int(iterations)
        self.gauss_seidel = bool(gauss_seidel)
        self.default_substeps = 32 if self.gauss_seidel else 64
        self.compliance = _check_compliance("compliance", compliance, True)
        self.bending_compliance = _check_compliance("bending_compliance", bending_compliance, False)
        a = float(relaxation)
        if not (math.isfinite(a) and a >= 0.0):
            raise ValueError(f"relaxation must be a finite number >= 0, got {relaxation!r}")
        self.relaxation = a
        plain_jacobi = not self.gauss_seidel and self.compliance is None \
            and self.bending_compliance is None
        if over_relaxation is None:
            w = DEFAULT_OVER_RELAXATION if plain_jacobi else 1.0
        else:
            w = over_relaxation
            if isinstance(w, bool) or not isinstance(w, (int, float, np.floating, np.integer)) \
                    or not (math.isfinite(w) and 0.0 < w < 2.0):
                raise ValueError(f"over_relaxation must be a number in (0, 2), got "
                                 f"{over_relaxation!r}")
            if not plain_jacobi and w != 1.0:
                raise ValueError(
                    "over_relaxation applies to plain PBD's Jacobi blend only (not with "
                    "gauss_seidel, compliance or bending_compliance, whose updates keep their "
                    f"own weights); got {over_relaxation!r}")
        self.over_relaxation = float(w)

        # ---- constraints on the host, once
        # a spring of stiffness 0 exerts nothing: it is no constraint (not a rigid link)
        live = np.asarray(model.spring_stiffness) > 0
        pairs = [model.spring_pairs.reshape(-1, 2)[live]]
        rest = [np.asarray(model.spring_rest)[live]]
        if self.compliance is None:
            comp = [np.zeros(int(live.sum()))]
        elif self.compliance == "springs":
            k = np.asarray(model.spring_stiffness)[live]
            comp = [1.0 / k]
        else:
            comp = [np.full(int(live.sum()), self.compliance)]
        if self.bending_compliance is not None and len(model.mesh.bend_quads):
            bp = model.mesh.bend_quads[:, 2:4]
            x0 = model.mesh.vertices
            pairs.append(bp)
            rest.append(np.linalg.norm(x0[bp[:, 0]] - x0[bp[:, 1]], axis=1))
            comp.append(np.full(len(bp), self.bending_compliance))
        pairs = np.concatenate(pairs).astype(np.int64)
        rest = np.concatenate(rest)
        comp = np.concatenate(comp)
        self.use_lambda = int(self.compliance is not None or self.bending_compliance is not None)

        if self.gauss_seidel:
            colors = color_constraints(pairs, model.num_vertices)
            order = np.argsort(colors, kind="stable")
            pairs, rest, comp, colors = pairs[order], rest[order], comp[order], colors[order]
            nc = int(colors.max()) + 1 if len(colors) else 0
            self.color_offsets = np.searchsorted(colors, np.arange(nc + 1)).astype(np.int64)
        else:
            self.color_offsets = np.array([0, len(pairs)], dtype=np.int64)
        self.constraint_pairs = pairs
        self.num_constraints = len(pairs)

        n = model.num_vertices
        count = np.zeros(n)
        np.add.at(count, pairs.reshape(-1), 1.0)
        d = self.device
        self._cons = wp.array(pairs.astype(np.int32).reshape(-1, 2), dtype=wp.int32, ndim=2, device=d)
        self._rest = wp.array(rest.astype(np.float32), dtype=float, device=d)
        self._compliance = wp.array(comp.astype(np.float32), dtype=float, device=d)
        self._lambda = wp.zeros(max(len(pairs), 1), dtype=float, device=d)
        self._count = wp.array(count.astype(np.float32), dtype=float, device=d)
        # XPBD Jacobi: each constraint scaled by its own share 1/(max(n_i, n_j) + alpha), so the
        # blend adds the corrections unscaled (a sub-convex combination at every vertex) and the
        # multiplier stays consistent with the positions; plain PBD averages per vertex instead
        # (plain PBD with ``blend="constraint"``, the default, likewise: its share
        # min(omega, m)/(m + alpha), m = max(n_i, n_j), moves both ends by the same fraction of
        # the projection, so each constraint keeps the momentum, module docstring)
        self._vertex_blend = not self.use_lambda and self.blend == "vertex"
        if len(pairs):
            mx = np.maximum(count[pairs[:, 0]], count[pairs[:, 1]])
            escale = (np.minimum(self.over_relaxation, mx) if not self.use_lambda else 1.0) \
                / (mx + a)
        else:
            escale = np.zeros(0)
        self._escale = wp.array(escale.astype(np.float32), dtype=float, device=d)
        if not self._vertex_blend:
            self._blend_count = wp.array((count > 0).astype(np.float32), dtype=float, device=d)
            self._blend_alpha = 0.0
            self._blend_omega = 1.0
        else:
            self._blend_count = self._count
            self._blend_alpha = a
            self._blend_omega = self.over_relaxation
        self._delta = wp.zeros(n, dtype=wp.vec3, device=d)
        self._xp = wp.zeros(n, dtype=wp.vec3, device=d)
        self._f = wp.zeros(n, dtype=wp.vec3, device=d)
        # external forces: everything but the springs (they are constraints here)
        self._forces = [t for t in model.force_terms if not isinstance(t, SpringForce)]
        # their stiffness per vertex (bending; Gershgorin row sums), for the prediction's scaled
        # mass (module docstring: *Stiff force terms*)
        stiff = SymplecticEuler.stiffness_row_sums(model, springs=False)[0]
        stiff[model.inverse_masses <= 0] = 0.0
        self._stiff_np = stiff
        self._stiff = wp.array(stiff.astype(np.float32), dtype=float, device=d)
        self._scale_dt = None  # the dt whose largest scale `_force_scale` holds
        self._force_scale = (1.0, 0)  # (largest 1 + dt^2 K w, vertices above 2) at that dt
        self._scale_told = False

        # ---- long-range attachments (tethers) to the pins
        if tethers is None:  # plain PBD with pins: its stretch is an artefact, the rest length is meant
            tethers = len(model.pins) > 0 and self.compliance is None
        if not isinstance(tethers, (bool, np.bool_)):
            raise ValueError(f"tethers must be True, False or None, got {tethers!r}")
        if isinstance(tether_pins, bool) or int(tether_pins) != tether_pins or tether_pins < 1:
            raise ValueError(f"tether_pins must be a positive integer, got {tether_pins!r}")
        sl = float(tether_slack)
        if not (math.isfinite(sl) and sl >= 0.0):
            raise ValueError(f"tether_slack must be a finite number >= 0, got {tether_slack!r}")
        self.tether_pins = int(tether_pins)
        self.tether_slack = sl
        self.num_tethers = 0
        self.tethers = bool(tethers) and len(model.pins) > 0
        if self.tethers:
            k = min(self.tether_pins, len(model.pins))
            anchors, dist = model_tether_anchors(model, k)
            ok = anchors >= 0
            self.num_tethers = int(ok.sum())
            self.tethers = self.num_tethers > 0
            rest_t = np.where(ok, dist * (1.0 + sl), 0.0)
            self.tether_anchor_indices = anchors
            self.tether_rest = rest_t
            self._tether_anchor = wp.array(anchors.astype(np.int32), dtype=wp.int32, ndim=2, device=d)
            self._tether_rest = wp.array(rest_t.astype(np.float32), dtype=float, ndim=2, device=d)
            self._pin_stretch = PinStretch(model)

        # ---- the stretch guard: a strain limit that acts only where the iterations left more
        if isinstance(max_stretch, str) and max_stretch == "auto":
            # not with pins that follow a path: they may impose any stretch (the twist scene's
            # counter-turning edges need about 30 %), and a guard below it never ends
            max_stretch = (DEFAULT_MAX_STRETCH if self.compliance is None and model.pin_path is None
                           else None)
        self.max_stretch = None
        self.stretch_guard = None
        if max_stretch is not None:
            try:
                ms = float(max_stretch)
            except (TypeError, ValueError):
                ms = math.nan
            if not (math.isfinite(ms) and ms > 0.0):
                raise ValueError(f"max_stretch must be a finite number > 0 or None, got "
                                 f"{max_stretch!r}")
            from ..limits import StrainLimit

            self.max_stretch = ms
            ne = len(model.mesh.edges)
            k = np.asarray(model.spring_stiffness)
            # only over a material that resists stretching: its mesh edges are its first springs
            if ne and len(k) >= ne and bool((k[:ne] > 0).all()):
                self.stretch_guard = StrainLimit(model, 0.0, 1.0 + ms)
                self.corrections.insert(0, self.stretch_guard)
                self._need_start()
                if getattr(self.collision, "self_collision", None) is not None:
                    self._self_again_alloc()

    # ------------------------------------------------------------------ pieces
    @property
    def _projectors(self):
        return [self.collision] if self.collision is not None else []

    def set_collision(self, collision) -> None:
        super().set_collision(collision)
        # the self-contacts of the iterations: their record allocated now, not in a step
        self._self_iter = (self.self_contacts is not False
                           and hasattr(self.collision, "use_self_iterations")
                           and self.collision.use_self_iterations())

    def self_contacts_on(self, dt: float) -> bool:
        """Whether a step of ``dt`` seconds projects the self-contacts of its predicted paths in
        its iterations: with a collision stage that has self-collision (and ``self_in_solve``),
        always with ``self_contacts=True``, and by default (``"auto"``) in steps of at least
        `SELF_CONTACT_DT`."""
        if not self._self_iter:
            return False
        return self.self_contacts is True or dt >= SELF_CONTACT_DT

    def _iterate(self, x, v, dt, iterations, finish_velocity):
        """``iterations`` projection iterations on ``x``; returns True if it set ``v`` too."""
        m = self.model
        d = self.device
        inv_dt2 = 1.0 / (dt * dt)
        projectors = self._projectors
        if self.use_lambda:
            self._lambda.zero_()
        fused = False
        if self.tethers:  # how far the pins themselves stretch the cloth (moving pins)
            self._pin_stretch.update(x)
        selfc = self.self_contacts_on(dt)
        kw = {"self_contacts": True} if selfc else {}
        for c in projectors:  # contact: the vertices near obstacles, listed once per step
            if hasattr(c, "begin_iterations"):
                c.begin_iterations(x, self._x_start, dt, **kw)
        for it in range(iterations):
            if self.gauss_seidel:
                offs = self.color_offsets
                for c in range(len(offs) - 1):
                    launch(gs_distance_kernel, int(offs[c + 1] - offs[c]),
                           [x, self._cons, self._rest, self._compliance, self._lambda,
                            m.inv_mass, inv_dt2, self.use_lambda, int(offs[c])], device=d)
            else:
                last = (finish_velocity and not projectors and not self.tethers
                        and it == iterations - 1)
                launch(jacobi_distance_kernel, self.num_constraints,
                       [x, self._cons, self._rest, self._compliance, self._lambda, m.inv_mass,
                        self._escale, inv_dt2, self.use_lambda, int(self._vertex_blend),
                        self._delta], device=d)
                launch(jacobi_blend_kernel, m.num_vertices,
                       [x, v, self._xp, self._delta, self._blend_count, m.inv_mass,
                        self._blend_alpha, self._blend_omega, 1.0 / dt, int(last)],
                       device=d)
                fused = fused or last
            if self.tethers:
                launch(tether_kernel, m.num_vertices,
                       [x, self._tether_anchor, self._tether_rest, self._pin_stretch.scale],
                       device=d)
            for c in projectors:
                c.project_positions(x, self._x_start, dt, **kw)
        return fused

    def project(self, x, dt: float = 1.0, iterations: int | None = None):
        """Run only the constraint projection on positions ``x`` (a ``wp.array`` of vec3), in place.

        ``dt`` matters only with compliance (``a~ = a/dt^2``). For tests and for use as a building
        block; ``step`` does prediction + projection + velocity update.
        """
        its = self.iterations if iterations is None else int(iterations)
        if self.num_constraints or self.tethers:
            self._iterate(x, x, dt, its, False)
        return x

    def _advance(self, state, dt):
        m = self.model
        d = self.device
        for term in self._forces:
            term.eval(state.x, state.v, self._f, state.time)
        if dt != self._scale_dt:  # host arithmetic on set-up data, once per step size
            s = 1.0 + dt * dt * self._stiff_np * m.inverse_masses
            self._scale_dt = dt
            self._force_scale = (float(s.max()) if len(s) else 1.0, int((s > 2.0).sum()))
            self.stats["force_mass_scale"], self.stats["force_scaled_vertices"] = \
                self._force_scale
        launch(predict_kernel, m.num_vertices,
               [state.x, state.v, self._xp, self._f, m.inv_mass, self._stiff,
                wp.vec3(*m.gravity), math.exp(-m.damping * dt), dt], device=d)
        fused = False
        if self.num_constraints or self.tethers:
            fused = self._iterate(state.x, state.v, dt, self.iterations, True)
        if not fused:
            launch(velocity_kernel, m.num_vertices,
                   [state.x, state.v, self._xp, m.inv_mass, 1.0 / dt], device=d)

    def _frame_messages(self) -> list:
        """Once a run: the bending that this step size does not resolve (its scaled mass)."""
        s, n = self._force_scale
        if n and not self._scale_told:
            self._scale_told = True
            return [f"pbd: the bending of {n} vertices is stiffer than a step of "
                    f"{self._scale_dt:.3g} s resolves; their bending acceleration is divided by "
                    f"up to {s:.3g} (stable, but slower to bend; more substeps make it exact)"]
        return []

    def describe(self) -> str:
        kind = "gauss-seidel" if self.gauss_seidel else "jacobi"
        if self.over_relaxation != 1.0:
            kind += f" x{self.over_relaxation:g}"
        if self._vertex_blend:
            kind += ", vertex blend"
        s = f"pbd ({kind}, {self.iterations} it"
        if self.compliance is not None:
            s += f", compliance {self.compliance}" if isinstance(self.compliance, str) else \
                f", compliance {self.compliance:g} m/N"
        if self.tethers:
            s += f", {self.num_tethers} tethers"
        if self.stretch_guard is not None:
            s += f", stretch <= {100 * self.max_stretch:g} %"
        return s + ")"
