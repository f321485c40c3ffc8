"""Contact inside an implicit solve: the collision stage's record as a stiff term of the objective.

Implicit Euler (Newton) and projective dynamics minimise the incremental potential
``F(x) = 1/(2 dt^2) ||x - y||_M^2 + E(x)`` (``physics.md`` 2.3). With contact, every entry of the
stage's `ContactRecord` (one linear constraint ``g(x) = n . sum_j w_j x_{v_j} - offset >= 0``,
`warp_cloth.collision.record`) adds a one-sided quadratic penalty

    E_c(x) = k_c / 2 * min(g(x), 0)^2,      k_c = kappa * m_eff / dt^2,  1/m_eff = sum_j w_j^2 / m_j

so that the minimiser satisfies springs and contact together: a constraint pushed against by a
force ``f`` is violated by ``|f| dt^2 / (kappa m_eff)``, i.e. by 1/kappa of how far that force would
move the vertex in one step (``kappa = 1e3``: 0.7 um for a vertex resting under gravity at
dt = 1/120 s). Scaling by the mass and ``1/dt^2`` keeps the term's share of the system matrix the
same at every mass and step (``kappa`` times the inertia block), which keeps the block-Jacobi
preconditioner and Chebyshev's ``rho`` valid: adding a positive semi-definite block-diagonal term
to the diagonal can only lower the spectral radius of the Jacobi iteration (Rayleigh quotients).

- **Newton** (`ImplicitEuler`): gradient ``-k_c g w_j n`` into the right-hand side and Hessian
  ``k_c w_j^2 n n^T`` into each vertex's diagonal block and into the operator's per-vertex blocks
  (`linear.SpringSystemOperator.vertex_blocks`), where ``g < 0`` (the active set is re-evaluated
  at every Newton iterate: ``E_c`` is C^1 and piecewise quadratic). Entries with several
  vertices (vertex-triangle, edge-edge: self-contacts, cloth edges on a mesh's sharp features)
  get their full Hessian: the diagonal blocks there and the off-diagonal coupling as an
  operator term (`pair_matvec_packed_kernel` for self-contacts, `pair_matvec_list_kernel`
  for the obstacle record's feature pairs, through `matvec_add`). With the diagonal blocks alone,
  Newton did not converge where cloth rests on such entries, and the response after the solve
  lifted the cloth out every step: a 16 x 16 sheet on the ``mesh`` scene's resting torus gained
  up to 1.9e-2 J in a frame (1.9e-4 J with the full Hessian).
- **Projective dynamics** (`ProjectiveDynamics`): the constraint's projection is the closest
  point of the half-space ``g >= 0``; its force ``-k_c min(g, 0) w_j n`` enters every local step
  and its matrix ``k_c w_j^2 n n^T`` (constant over a step's iterations, whether the entry is
  active or not) enters the global matrix as per-vertex blocks, so the global step sees contact.

**Friction** (vertex-obstacle entries, Coulomb coefficient ``mu_T``) is part of the same solve,
as in Incremental Potential Contact (Li et al. 2020): the smoothed Coulomb potential
``mu lam f0(|u|)`` of the tangential displacement ``u`` relative to the surface over the step
(``u`` = tangential part of ``x - ref``, ``ref`` the start position carried by the obstacle's
motion), with ``f0' = f1``, ``f1(y) = 2y/eps - y^2/eps^2`` below ``eps = friction_velocity * dt``
and 1 above it (a static branch that is a stiff spring, a sliding branch that is a constant
force), and the normal force ``lam`` fixed for the step: the larger of the last step's final
``k_c |g|`` (bounded by the load the other forces press the vertex on with:
`normal_force_kernel`) and ``m |g| / dt^2`` at the prediction (the force that stops the predicted
penetration within the step: a vertex's weight when it rests, the impact when it arrives). With
``lam`` fixed the potential is convex and Newton's line search applies. Its Hessian is exact in
both branches (none along ``u`` while sliding). Newton's model of static friction is very stiff,
so the initial guess places each vertex on the branch it will likely end on
(`friction_guess_kernel`); this matters for a solve stopped by a tolerance (a vertex left on
the sliding branch near sticking has a force imbalance below the tolerance and would creep) and
for projective dynamics, which converges slowly on whole-cloth motion.
With nothing along ``u`` while sliding, the Newton step of a vertex whose other forces are
inside the cone (or point back) takes the force ``mu lam`` as constant all the way and carries
the vertex back past its reference by up to that force over its inertia block, hundreds of
times the static branch (``eps`` = 0.8 um at 1e-4 m/s and dt = 1/120 s); at the next iterate
the force has turned round and throws it back, and the one line-search length of the whole
cloth shrinks for it. `limit_reversals` lands such a vertex on its reference instead (the
centre of the static branch: from there it sticks, or the static branch's stiffness starts it
sliding the other way). Measured with the implicit solver on the CLI contact scenes at
defaults (frames with a step short of the tolerance, before -> after): spin 172 -> 80, drape
106 -> 28, mesh 158 -> 88, table 134 -> 118, fold 119 -> 101, stack 55 -> 67
(docs/bench/selfcollision.md). Landing at ``eps/2`` on the far side, or where the step with the force
turned round would end, did worse on the first three.
Projective dynamics takes friction as a projective constraint instead (force ``-k_c u`` capped
at ``mu lam``, block ``k_c (I - n n^T)`` whatever the branch): its global step has no line
search, and the exact Hessian above made its iterations overshoot between the branches (the
drape at 30 iterations gained 22 J in a frame).

After the solve, a vertex within ``slack`` of one of its planes leaves the step with no normal
velocity towards it (restitution ``mu_N`` times it away), so the stage's impulse, which then sees
no approach, adds no second friction. The normal forces of the final iterate are kept for the
next step's friction.

The record is filled once per step by `CollisionStage.detect` from the predicted positions; the
stage's ``resolve`` after the solve stays as the final guarantee (continuous test, projection to
the thickness, and the impulse for vertices the solve did not hold).

Projective dynamics and sliding (measured, ``warp-cloth run table --solver pd``): the projective
friction spring ``k_c (I - n n^T)`` is 1000 times a vertex's inertia block, so the global step
pins a vertex near its current iterate, and at its default iterations PD did not let a sheet held
by static friction over a large area slide (the table's sheet, mu_T = 0.15, 55 % overhanging,
stayed on the table, also with the normal force bounded by the load). A spring of one inertia
block everywhere lets it slide, but then a vertex held below the friction angle creeps about
``f dt / m`` (measured on the incline test: 6.0 mm in 0.3 s, against 0.1 mm allowed); the secant
weight ``mu lam / |u|`` on the sliding branch alone left it on the table. So the step's friction
guess also classifies each entry (`friction_guess_kernel` with ``f_class``): a vertex that its
predicted motion and the other forces at the end of the last step (the cloth's tension, less
the weight the prediction already holds) drive past ``mu lam`` gets a friction spring of the
inertia block for the step (``slide``, `pd_local`); the others keep the stiff one. The default
32x32 table sheet then slides off as under explicit Euler (off the edge by frame ~60); coarser
sheets (8, 12, 16 cells) still stay: the tension reaches too few vertices past the cap. Not
solved there.

**Resting contact** (implicit Euler with a guess that leaves the external forces' step out,
``initial_guess`` ``"start"``, ``"velocity"`` or ``"auto"``). Such a guess starts a resting
vertex on its surface (``g >= 0``), where the penalty has no force and, active only for
``g < 0``, no Hessian: Newton's first direction then pushed every supported vertex down by
``dt^2 g`` as if free, the line search saw the penalty rise at every length (F 0.0281 ->
0.0284 J at the full step), and a folded sheet lying across the floor froze in its start pose
(a 10 x 10 fold at 150 degrees, every step stalled at a residual of 7.2e-3 m). In a step's
first Newton assembly an entry within `RESTING_BAND` above its constraint is therefore active
with the penalty's block and no force (`newton_contact_kernel`'s ``resting``): the direction
respects the support, the next iterate is just inside it (where the penalty acts by itself),
and a vertex that is being lifted is free again from the second iteration (a block kept
through the solve would hold it to the surface, about a thousandth of its free motion per
iteration). Its friction guess adds what the guess left out of the inertial prediction (the
external forces' step, and for ``x0`` the velocity's) to the predicted sliding and penetration
(`friction_guess_kernel`'s ``f_ext``), as at the inertial guess: without it a sheet at rest on
an incline above its friction angle started on friction's static branch and never slid, and
below it got no normal force in its first step and slid.

**Contacts that flip** (implicit Euler). An entry active only for ``g < 0`` has a stiffness
that jumps from nothing to ``kappa m/dt^2`` at its constraint. Newton met that jump two ways,
traced on the fold (`warp-cloth run fold --solver implicit`, 119 of its 120 frames had a step
short of its tolerance). A resting self-contact's equilibrium lies its load over that
stiffness inside, about 1e-6 m: a few float32 roundings of its gap, so thousands of the folded
sheet's entries switched on and off between iterations (at frame 100 of the table, 1,000-17,000
flips an iteration at gaps of 1e-7-1e-6 m). The self-contacts' penalty in Newton therefore
starts with a cubic over its first `SELF_ONSET` of the thickness (`normal_penalty`: C2, the
plain quadratic beyond, moved half the onset deeper), where a resting entry sits some 1e-5 m
deep with a stiffness that varies smoothly; the obstacles' entries keep the plain quadratic
(their sag and resting rules are tuned to it) and projective dynamics too (its matrix must be
constant). And an entry just above its constraint has no block: Newton's direction drove its
vertex in as if free, the contact energy rose at every line-search length (fold, frame 29:
+4.8e-3 J at the full step, +1.3e-5 J at 1/8) and the step stopped at 1/64 as stalled. So
from a step's second assembly on, an entry within `RESTING_BAND` above its constraint whose
gap shrank since the last assembly, or that was inside it then, keeps the penalty's block (no
force; `HOLD_FLIPS`, the gaps kept per entry); one being lifted is not held, so nothing slows
the cloth leaving a surface (holding every entry in the band at every assembly had cut the
drape's converged steps by half). The obstacles' entries are not held: with them held too the
friction scenes converged in more frames (spin 57 against 92 short), but the 16 x 16 sheet on
the turning sphere, inertial guess, gained 2.7e-5 J in a frame in the sphere's frame
(`test_implicit_energy_guard_works_in_the_spinning_frame`: at most 2e-5). Frames with a short
step at defaults, the landing alone -> with both: fold 101 -> 24, spin 80 -> 92, drape 28 ->
34, mesh 88 -> 89, table 118 -> 103, stack 67 -> 58 (docs/bench/selfcollision.md).

**Sag.** A penalty gives under load: a vertex pressed against a surface by the cloth's tension
(the table's sides, held by the draped part) ends its solve about ``load dt^2 / (kappa m)``
inside its target, 0.1-0.5 mm there, and the response after the solve (`CollisionStage.resolve`)
pushed it out against the springs every step: energy put in at every step (+1.8e-3 J in one on
the table under PD). `end_step` keeps each (vertex, obstacle) pair's sag below its target (at
most `SAG_CAP` of the thickness) and the next `detect` raises that pair's target by it, so a
steadily loaded contact ends its solve at the thickness (the augmented-Lagrangian idea with the
last step's multiplier); a pair without an entry has no sag.
Measured again after the normal force was bounded by the load and PD's sliding contacts got the
weak friction spring (PD, 16x16, 90 frames, largest one-frame rise): table 4.3e-5 J with the sag
and 2.7e-5 J without, drape 4.1e-5 / 7.0e-5 J, 32x32 table none either way: it no longer
decides these scenes' energy; kept, as it still lowers the drape's.

Self-contacts sag the same way, and far more: in a pile of tight folds (the table's cloth on
the floor) the springs pull the layers together with their whole tension, and the solve left
self-contacts up to 0.8 mm inside the 5 mm thickness, which the self-collision response after
the solve pushed out against the springs at every step (1.3e-2 to 2.0e-2 J of spring energy a
step under implicit Euler). Self-contact pairs are not kept from step to step, so the sag is
kept per vertex (``self_sag``: each vertex's deepest after the solve, at most `SAG_CAP` of the
thickness) and the next step raises each self-contact entry's target by the least sag of its
vertices (`self_sag_apply_kernel`): a pair that stayed loaded is raised by at least its own
sag, one beside a loaded pair by at most the cap. Only a sag of two steps in a row counts
(`self_sag_persist_kernel`): an impact's one deep step is the response's, and raising targets
after it pushed the table's landing folds apart (36 frames, implicit: 5.0 % strain against
explicit Euler's 3.2 %; 4.1 % with the persistence; 4.5 % without any raise). Measured on the
scenes at defaults (largest one-frame energy rise and max strain over the scene's frames,
without -> with): table implicit 3.2e-3 -> 1.4e-3 J, 5.2 -> 7.7 %, PD 7.1e-4 J -> no rise,
5.2 -> 5.1 %; stack implicit 1.8e-3 -> 9.2e-5 J, 6.1 -> 5.2 %, PD 7.3e-5 -> 7.0e-5 J; fold
implicit 1.2e-3 -> 2.5e-3 J, 2.5 -> 1.8 %, PD 1e-8 -> 7e-7 J. The default table is a lucky
case without it: the same table at 28, 30, 34 and 36 cells and at 50 and 72 fps, implicit, max
strain 4.3 / 23.5 / 9.0 / 10.6 / 12.3 / 8.4 % with rises of 4.7e-3 / 0.11 / 1.6e-2 / 1.9e-2 /
2.4e-2 / 1.4e-2 J; with it 8.0 / 7.7 / 6.2 / 6.8 / 7.1 / 5.7 % and 1.9e-4 / 3.1e-5 / 2.3e-3 /
6.8e-4 / 2.7e-3 / 4.4e-5 J.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..collision.features import pin_held
from ..collision.record import (KIND_VERTEX_OBSTACLE, ContactRecord, add_overflow_kernel,
                                entry_gap, record_threads)
from ..util import count_since, launch, positive_finite

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile

__all__ = ["ContactCoupling", "DEFAULT_CONTACT_STIFFNESS", "DEFAULT_FRICTION_VELOCITY", "BATCH"]

#: kappa: the contact term's stiffness over the inertia block ``m/dt^2``
DEFAULT_CONTACT_STIFFNESS = 1.0e3
#: m/s; friction's smoothing speed (IPC's eps_v): static friction holds a vertex to this creep
DEFAULT_FRICTION_VELOCITY = 1.0e-4
#: record entries per thread on a GPU (`record_threads`; the CPU runs one thread: there a thread
#: costs its call whether its entries exist, and one per 16 entries of a 17,424-entry
#: self-contact record made the products of a folded sheet's inner solves 20-40 % slower)
BATCH = 16
#: the largest sag (a fraction of the contact thickness) by which a loaded contact's next
#: target is raised (`ContactCoupling.end_step`); a deeper one, an impact the solve did not
#: stop, is left to the response after the solve rather than pushed out by the next solve
SAG_CAP = 0.2
#: the self-contacts' penalty in Newton (implicit Euler) starts with a cubic over this fraction
#: of their thickness (`normal_penalty`): the plain quadratic's stiffness jumps from 0 to
#: kappa m/dt^2 at the surface, where a resting entry's equilibrium lies about 1e-6 m deep
#: (its load over that stiffness), a few float32 roundings of its gap: thousands of a folded
#: sheet's entries switched on and off between Newton iterations, and the steps stalled
SELF_ONSET = 0.01
#: Newton: a self-contact entry within `RESTING_BAND` above its constraint that closed in on it
#: since the last assembly, or was inside it then, keeps the penalty's block (module doc,
#: *Contacts that flip*)
HOLD_FLIPS = True


@wp.func
def coulomb_energy(mu_lam: float, y: float, eps: float):
    """The smoothed Coulomb potential ``mu lam f0(y)`` of a tangential displacement ``y``
    (module doc: ``f0' = f1``, quadratic-cubic below ``eps``, linear above)."""
    if y < eps:
        return mu_lam * (y * y / eps - y * y * y / (3.0 * eps * eps) + eps / 3.0)
    return mu_lam * y


@wp.func
def normal_penalty(k: float, g: float, onset: float):
    """The normal penalty of stiffness ``k`` at gap ``g`` (< 0: violated): (force along the
    normal, stiffness, energy). ``onset == 0``: ``k g^2 / 2`` (its stiffness jumps from 0 to
    ``k`` at ``g = 0``). ``onset > 0``: a cubic onset over the first ``onset`` of depth
    (``s = -g``: ``k s^3 / (6 onset)``, stiffness ``k s / onset``), then the same quadratic
    moved ``onset / 2`` deeper, matched in value, slope and stiffness (C2 in ``g``;
    `SELF_ONSET`)."""
    if g >= 0.0:
        return 0.0, 0.0, 0.0
    s = -g
    if onset <= 0.0:
        return k * s, k, 0.5 * k * s * s
    if s < onset:
        return 0.5 * k * s * s / onset, k * s / onset, k * s * s * s / (6.0 * onset)
    d = s - 0.5 * onset
    return k * d, k, 0.5 * k * d * d + k * onset * onset / 24.0


@wp.func
def entry_response(rec: ContactRecord, e: int, x: wp.array(dtype=wp.vec3),
                   inv_mass: wp.array(dtype=float), kappa_dt2: float, eps: float,
                   lam: wp.array(dtype=float), num_sources: int, projective: float,
                   onset: float):
    """Entry ``e`` at ``x``: (active, force on the weighted point ``sum w_j x_j``, its 3x3
    Hessian block, the normal penalty's part of that block, energy). Normal: the penalty where
    ``g < 0``; tangential (vertex-obstacle
    entries with ``mu_T > 0`` whose vertex presses on the obstacle): smoothed Coulomb friction
    with the normal force ``lam`` fixed for the step (`friction_guess_kernel`; module doc).

    ``projective`` (projective dynamics): friction as a projective constraint of the same
    stiffness ``k`` as the normal penalty, its block ``k (I - n n^T)`` whatever the branch (the
    matrix PD's global step needs constant), force ``-k u`` up to ``mu lam`` (the Moreau envelope
    of ``mu lam |u|``, convex). The smoothed Coulomb model's exact Hessian instead (very stiff
    while sticking, none along ``u`` while sliding) made PD's undamped iterations overshoot
    between the branches: the drape gained 22 J at 30 iterations with CG."""
    on = bool(False)
    f = wp.vec3(0.0)
    H = wp.mat33(0.0)
    E = float(0.0)
    vid = rec.vertex[e]
    w = rec.weight[e]
    n = rec.normal[e]
    g = -rec.offset[e]  # `entry_gap`'s, in its order; the masses only for an active entry
    for j in range(4):
        if vid[j] >= 0:
            g = g + w[j] * wp.dot(n, x[vid[j]])
    mu = rec.friction[e]
    rubs = mu > 0.0 and rec.kind[e] == KIND_VERTEX_OBSTACLE
    if g >= 0.0 and not rubs:  # inactive whatever else (most entries of a solve's record)
        return on, f, H, H, E
    im = float(0.0)
    for j in range(4):
        if vid[j] >= 0:
            im = im + w[j] * w[j] * inv_mass[vid[j]]
    if im <= 0.0 or pin_held(vid, w, inv_mass):
        # a point (nearly) at a pinned vertex: its penalty, of stiffness kappa m_eff / dt^2
        # with m_eff the pin's, would throw the free vertex by the violation over its weight
        # (`pin_held`); left to the response, which reports it
        return on, f, H, H, E
    nn = wp.outer(n, n)
    if g < 0.0:
        fn, kn, En = normal_penalty(kappa_dt2 / im, g, onset)
        on = True
        f = fn * n
        H = kn * nn
        E = En
    Hn = H
    if rubs:
        i = rec.vertex[e][0]
        lam_i = lam[i * num_sources + rec.source[e]]
        if lam_i > 0.0 and projective > 0.0:
            on = True
            d = x[i] - rec.ref[e]
            u = d - wp.dot(d, n) * n
            y = wp.length(u)
            kt = projective * kappa_dt2 / im
            reach = mu * lam_i / kt
            c = kt
            if y <= reach:
                E = E + 0.5 * kt * y * y
            else:
                c = mu * lam_i / y
                E = E + mu * lam_i * (y - 0.5 * reach)
            H = H + kt * (wp.identity(n=3, dtype=float) - nn)
            f = f - c * u
        elif lam_i > 0.0:
            on = True
            d = x[i] - rec.ref[e]
            u = d - wp.dot(d, n) * n
            y = wp.length(u)
            T = wp.identity(n=3, dtype=float) - nn
            uu = wp.mat33(0.0)
            if y > 0.0:
                uu = wp.outer(u, u) / (y * y)
            c = float(0.0)
            if y < eps:
                # f1(y) = 2y/eps - y^2/eps^2: Hessian mu lam (f1'(y) uu^T + f1(y)/y (T - uu^T))
                c = mu * lam_i * (2.0 / eps - y / (eps * eps))
                H = H + (mu * lam_i * (2.0 / eps - 2.0 * y / (eps * eps))) * uu + c * (T - uu)
            else:
                # sliding: a constant force mu lam against u, no stiffness along u. Newton without
                # a line search overshoots between sliding and sticking with it (measured: the
                # drape diverged): the implicit solver's line search and friction's initial
                # guess (`friction_guess_kernel`) keep it from doing so
                c = mu * lam_i / y
                H = H + c * (T - uu)
            E = E + coulomb_energy(mu * lam_i, y, eps)
            f = f - c * u
    return on, f, H, Hn, E


@wp.kernel
def normal_force_kernel(
    rec: ContactRecord,
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    kappa_dt2: float,
    num_threads: int,
    num_sources: int,
    f_other: wp.array(dtype=wp.vec3),
    lam: wp.array(dtype=float),
):
    """The normal force of each active vertex-obstacle entry at ``x`` (the end of the solve)
    into ``lam[vertex * num_sources + obstacle]``: the next step's friction bound. The penalty's
    ``k_c |g|``, but at most the part of the other forces on the vertex (``f_other``: gravity,
    springs, bending, wind at ``x``) that presses it onto the surface, ``max(-n . f_other, 0)``:
    a solve short of convergence leaves the penalty deeper than the load needs (projective
    dynamics on the table scene: 3.2 times the weight of the cloth on the table top), and that
    overestimate held the sheet on the table (module doc). An impact's normal force (inertia)
    is left out: friction acts with the load while the vertex rests or slides."""
    t = wp.tid()
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    for e in range(t, count, num_threads):
        if rec.kind[e] != KIND_VERTEX_OBSTACLE:
            continue
        g, im = entry_gap(rec, e, x, inv_mass)
        if g < 0.0 and im > 0.0:
            i = rec.vertex[e][0]
            load = wp.max(-wp.dot(rec.normal[e], f_other[i]), 0.0)
            wp.atomic_add(lam, i * num_sources + rec.source[e], wp.min(-kappa_dt2 / im * g, load))


@wp.kernel
def feature_press_kernel(
    rec: ContactRecord,
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    kappa_dt2: float,
    dt: float,
    num_threads: int,
    f_other: wp.array(dtype=wp.vec3),
    pressed: wp.array(dtype=wp.vec3),
):
    """After the solve: the velocity each active obstacle-feature entry (several cloth
    vertices: a mesh's sharp feature, a box's rim, a sphere too curved for the cells) gave its
    vertices, added to ``pressed``: the penalty's ``k_c |g| dt`` shared like a correction
    (``w_j / m_j / sum_k w_k^2 / m_k``), at most the part of the other forces that presses the
    entry's point onto the feature (as `normal_force_kernel` bounds the vertex entries'). The
    features' friction after the solve takes it as its normal impulse
    (`FeatureContact.friction`)."""
    t = wp.tid()
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    for e in range(t, count, num_threads):
        if rec.kind[e] == KIND_VERTEX_OBSTACLE or rec.source[e] < 0:
            continue
        g, im = entry_gap(rec, e, x, inv_mass)
        if g < 0.0 and im > 0.0:
            vid = rec.vertex[e]
            w = rec.weight[e]
            n = rec.normal[e]
            a = wp.vec3(0.0)
            for j in range(4):
                k = vid[j]
                if k >= 0:
                    a = a + (w[j] * inv_mass[k]) * f_other[k]
            # the point's normal velocity change: the penalty's, at most the other forces'
            dvn = wp.min(-kappa_dt2 * g * dt, wp.max(-wp.dot(n, a), 0.0) * dt)
            for j in range(4):
                k = vid[j]
                if k >= 0 and inv_mass[k] > 0.0:
                    wp.atomic_add(pressed, k, (w[j] * inv_mass[k] / im * dvn) * n)


@wp.kernel
def weight_kernel(mass: wp.array(dtype=float), gravity: wp.vec3, f: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    f[i] = mass[i] * gravity


@wp.kernel
def sag_apply_kernel(rec: ContactRecord, sag: wp.array(dtype=float), num_sources: int,
                     num_threads: int):
    """Each vertex-obstacle entry's target raised by its pair's sag of the last step
    (`ContactCoupling.end_step`)."""
    t = wp.tid()
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    for e in range(t, count, num_threads):
        if rec.kind[e] == KIND_VERTEX_OBSTACLE and rec.source[e] >= 0:
            rec.offset[e] = rec.offset[e] + sag[rec.vertex[e][0] * num_sources + rec.source[e]]


@wp.kernel
def sag_update_kernel(rec: ContactRecord, x: wp.array(dtype=wp.vec3),
                      inv_mass: wp.array(dtype=float), cap: float, num_sources: int,
                      num_threads: int, sag: wp.array(dtype=float)):
    """After the solve: each vertex-obstacle pair's sag below its (raised) target, at most
    ``cap``, for the next step (``sag`` cleared before: pairs without an entry have none)."""
    t = wp.tid()
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    for e in range(t, count, num_threads):
        if rec.kind[e] != KIND_VERTEX_OBSTACLE or rec.source[e] < 0:
            continue
        g, im = entry_gap(rec, e, x, inv_mass)
        if g < 0.0 and im > 0.0:
            sag[rec.vertex[e][0] * num_sources + rec.source[e]] = wp.min(-g, cap)


@wp.kernel
def self_sag_apply_kernel(rec: ContactRecord, sag: wp.array(dtype=float), num_threads: int):
    """Each self-contact entry's target raised by the least sag of its vertices at the end of
    the last step (`ContactCoupling.end_step`, ``self_sag``): a pair that stayed loaded raises
    its target by at least its own sag of then, because each vertex keeps its deepest."""
    t = wp.tid()
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    for e in range(t, count, num_threads):
        vid = rec.vertex[e]
        s = float(1.0e30)
        for j in range(4):
            if vid[j] >= 0:
                s = wp.min(s, sag[vid[j]])
        if s > 0.0 and s < 1.0e30:
            rec.offset[e] = rec.offset[e] + s


@wp.kernel
def self_sag_update_kernel(rec: ContactRecord, x: wp.array(dtype=wp.vec3),
                           inv_mass: wp.array(dtype=float), cap: float, num_threads: int,
                           sag: wp.array(dtype=float)):
    """After the solve: each vertex's deepest sag below the (raised) target of a self-contact
    entry it belongs to, at most ``cap`` (``sag`` cleared before)."""
    t = wp.tid()
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    for e in range(t, count, num_threads):
        g, im = entry_gap(rec, e, x, inv_mass)
        if g < 0.0 and im > 0.0:
            s = wp.min(-g, cap)
            vid = rec.vertex[e]
            for j in range(4):
                if vid[j] >= 0:
                    wp.atomic_max(sag, vid[j], s)


@wp.kernel
def self_sag_persist_kernel(raw: wp.array(dtype=float), last: wp.array(dtype=float),
                            sag: wp.array(dtype=float)):
    """A vertex's sag raises its next targets only where it sagged in both of the last two
    steps (the lesser): a steady load, not an impact's one deep step (`ContactCoupling`)."""
    i = wp.tid()
    r = raw[i]
    sag[i] = wp.min(r, last[i])
    last[i] = r


#: metres: in the first Newton assembly of a step whose guess left the external forces' step
#: out, an entry whose gap is in [0, this) is active with its penalty block (module doc,
#: *Resting contact*); about the gravity step at dt = 1/120 s (6.8e-5 m)
RESTING_BAND = wp.constant(1.0e-4)


@wp.kernel
def newton_contact_kernel(
    rec: ContactRecord,
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    kappa_dt2: float,
    eps: float,
    lam: wp.array(dtype=float),
    num_sources: int,
    num_threads: int,
    b: wp.array(dtype=wp.vec3),
    diag: wp.array(dtype=wp.mat33),
    vblock: wp.array(dtype=wp.mat33),
    nblock: wp.array(dtype=wp.mat33),
    active: wp.array(dtype=int),
    on_out: wp.array(dtype=int),
    resting: int,
    pv: wp.array(dtype=wp.vec4i),
    pw: wp.array(dtype=wp.vec4),
    pn: wp.array(dtype=wp.vec4),
    packed: wp.array(dtype=int),
    onset: float,
    pen: wp.array(dtype=float),
    b_cloth: wp.array(dtype=wp.vec3),
):
    """Active entries: their force ``-grad E_c`` into ``b``; their blocks into ``diag`` and
    ``vblock`` (``w_j^2 H``), the normal penalty's alone into ``nblock`` (for the residual);
    the number of active entries into ``active[0]``; with an ``on_out`` array, each entry's
    activity (the off-diagonal part of the multi-vertex entries' Hessian, `pair_matvec_list_kernel`);
    with ``pv`` arrays, each active entry packed (`pack_entry`, counted in ``packed[0]``).

    With ``resting`` 1 (the step's first assembly, `ContactCoupling.resting`): an entry within
    `RESTING_BAND` above its constraint is active too, with the penalty's block and no force
    (module doc, *Resting contact*); with ``resting`` 2 (a later assembly), only such an entry
    whose gap shrank since the last assembly or that was inside its constraint then (``pen``:
    each entry's gap at the last assembly, written here for the next; module doc, *Contacts
    that flip*)."""
    t = wp.tid()
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    for e in range(t, count, num_threads):
        on, f, H, Hn, E = entry_response(rec, e, x, inv_mass, kappa_dt2, eps, lam, num_sources,
                                         0.0, onset)
        vid = rec.vertex[e]
        w = rec.weight[e]
        if resting != 0 or pen.shape[0] > 0:
            g, im = entry_gap(rec, e, x, inv_mass)
            hold = resting == 1
            if pen.shape[0] > 0:
                if resting == 2:
                    hold = g < pen[e] or pen[e] < 0.0
                pen[e] = g
            if (hold and g >= 0.0 and g < RESTING_BAND and im > 0.0
                    and not pin_held(vid, w, inv_mass)):
                n = rec.normal[e]
                on = True
                hn = (kappa_dt2 / im) * wp.outer(n, n)
                H = H + hn
                Hn = Hn + hn
        if on_out.shape[0] > 0:
            on_out[e] = int(on)
        if on and pv.shape[0] > 0:
            # the normal stiffness over kappa/dt^2 (an entry in its onset: below 1/im)
            pack_entry(rec, e, inv_mass, pv, pw, pn, packed,
                       (Hn[0, 0] + Hn[1, 1] + Hn[2, 2]) / kappa_dt2)
        # the residual's block (`implicit.vertex_residual`): the normal penalty's, and the
        # friction's too where the vertex sits on its static branch with the cloth's forces
        # (``b_cloth``: ``b`` before any contact entry's, a copy taken before this launch)
        # inside the cone: its answer sticks, and its imbalance is measured by the position
        # change its block allows. (It read ``b`` itself, which the other entries of the same
        # vertex add to in this launch: their order on the CPU, a race on a GPU)
        Hr = Hn
        if on and rec.kind[e] == KIND_VERTEX_OBSTACLE and rec.friction[e] > 0.0:
            i = vid[0]
            lam_i = lam[i * num_sources + rec.source[e]]
            if lam_i > 0.0:
                n = rec.normal[e]
                d = x[i] - rec.ref[e]
                u = d - wp.dot(d, n) * n
                bc = b_cloth[i]
                bt = bc - wp.dot(bc, n) * n
                if wp.length(u) < eps and wp.length(bt) <= rec.friction[e] * lam_i:
                    Hr = H
        if on:
            for j in range(4):
                v = vid[j]
                if v >= 0 and inv_mass[v] > 0.0:
                    wp.atomic_add(b, v, w[j] * f)
                    h = (w[j] * w[j]) * H
                    wp.atomic_add(diag, v, h)
                    wp.atomic_add(vblock, v, h)
                    wp.atomic_add(nblock, v, (w[j] * w[j]) * Hr)
            wp.atomic_add(active, 0, 1)


@wp.kernel
def friction_reversal_kernel(
    rec: ContactRecord,
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    eps: float,
    lam: wp.array(dtype=float),
    num_sources: int,
    num_threads: int,
    dx: wp.array(dtype=wp.vec3),
    count: wp.array(dtype=int),
    src: int,
):
    """A Newton direction ``dx`` that carries a sliding vertex (``|u| >= eps``) back past its
    friction reference (``u . (u + T dx) < 0``: its friction force would reverse) has that
    vertex's tangential part replaced by ``-u``: the vertex lands at the centre of friction's
    static branch. The sliding branch has no stiffness along ``u``, so the linearised step
    sees the constant force ``mu lam`` pull on past the reference, by as much as the force
    over the inertia block (module doc); counted in ``count[0]``. The entries of obstacle ``src``
    only (one launch per obstacle, in their order: a vertex with entries of two obstacles is
    judged by each in turn, the second on the direction the first left, on a GPU as on the
    CPU; one launch raced on ``dx[i]``): the direction only, which the line search then judges
    (and `ImplicitEuler` replaces by Newton's own where it raises F at every length)."""
    t = wp.tid()
    c = wp.min(rec.count[0], rec.vertex.shape[0])
    for e in range(t, c, num_threads):
        if (rec.friction[e] <= 0.0 or rec.kind[e] != KIND_VERTEX_OBSTACLE
                or rec.source[e] != src):
            continue
        i = rec.vertex[e][0]
        if inv_mass[i] <= 0.0 or lam[i * num_sources + rec.source[e]] <= 0.0:
            continue
        n = rec.normal[e]
        d = x[i] - rec.ref[e]
        u = d - wp.dot(d, n) * n
        if wp.length(u) < eps:
            continue
        di = dx[i]
        s = di - wp.dot(di, n) * n
        if wp.dot(u + s, u) < 0.0:
            dx[i] = di - s - u
            wp.atomic_add(count, 0, 1)


@wp.func
def pair_matvec_entry(rec: ContactRecord, e: int, inv_mass: wp.array(dtype=float),
                      kappa_dt2: float, x: wp.array(dtype=wp.vec3),
                      out: wp.array(dtype=wp.vec3)):
    """Entry ``e``'s off-diagonal Hessian blocks times ``x`` into ``out``
    (`pair_matvec_list_kernel`)."""
    vid = rec.vertex[e]
    w = rec.weight[e]
    n = rec.normal[e]
    im = float(0.0)
    s = float(0.0)
    for j in range(4):
        v = vid[j]
        if v >= 0:
            im = im + w[j] * w[j] * inv_mass[v]
            if inv_mass[v] > 0.0:
                s = s + w[j] * wp.dot(n, x[v])
    if im > 0.0:
        k = kappa_dt2 / im
        for j in range(4):
            v = vid[j]
            if v >= 0 and inv_mass[v] > 0.0:
                wp.atomic_add(out, v, (k * w[j] * (s - w[j] * wp.dot(n, x[v]))) * n)


@wp.kernel
def list_on_kernel(rec: ContactRecord, on: wp.array(dtype=int), min_vertices: int,
                   num_threads: int, out: wp.array(dtype=int), n: wp.array(dtype=int)):
    """The record's entries with ``on[e] != 0`` and at least ``min_vertices`` cloth vertices
    appended to ``out`` (``n[0]``, cleared by the caller, counts them; in record order on the
    CPU, whose launch runs one thread). The obstacle record lists its entries of two or more
    (a cloth edge or triangle on a mesh's sharp feature: the only ones with an off-diagonal
    Hessian block); the self-contact record all of them (0)."""
    t = wp.tid()
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    for e in range(t, count, num_threads):
        if on[e] != 0:
            c = int(0)
            if min_vertices > 0:
                vid = rec.vertex[e]
                for j in range(4):
                    if vid[j] >= 0:
                        c += 1
            if c >= min_vertices:
                out[wp.atomic_add(n, 0, 1)] = e


@wp.func
def pack_entry(rec: ContactRecord, e: int, inv_mass: wp.array(dtype=float),
               pv: wp.array(dtype=wp.vec4i), pw: wp.array(dtype=wp.vec4),
               pn: wp.array(dtype=wp.vec4), n: wp.array(dtype=int), stiffness: float):
    """An active self-contact entry packed for `pair_matvec_packed_kernel` (by the assembly
    that finds it active: `newton_contact_kernel`, `pd_contact_kernel`): its free vertices
    (``pv``, -1 for a pinned or unused one), their weights (``pw``, 0 there) and its normal
    with ``stiffness``, its normal penalty's stiffness over ``kappa / dt^2`` (negative: ``1 /
    sum_j w_j^2 m_j^-1``, the full penalty's) (``pn``; an entry with no free vertex is left out). The
    product that runs every inner iteration then reads one entry's data in three loads instead
    of walking the record and the inverse masses (`pair_matvec_entry`), and no pass over the
    record lists the active entries."""
    vid = rec.vertex[e]
    w = rec.weight[e]
    nrm = rec.normal[e]
    im = float(0.0)
    v = wp.vec4i(-1, -1, -1, -1)
    c = wp.vec4(0.0)
    for j in range(4):
        if vid[j] >= 0:
            im = im + w[j] * w[j] * inv_mass[vid[j]]
            if inv_mass[vid[j]] > 0.0:
                v[j] = vid[j]
                c[j] = w[j]
    if im > 0.0:
        k = wp.atomic_add(n, 0, 1)
        if k < pv.shape[0]:
            pv[k] = v
            pw[k] = c
            c_k = stiffness
            if c_k < 0.0:
                c_k = 1.0 / im
            pn[k] = wp.vec4(nrm[0], nrm[1], nrm[2], c_k)


@wp.kernel
def pair_matvec_packed_kernel(pv: wp.array(dtype=wp.vec4i), pw: wp.array(dtype=wp.vec4),
                              pn: wp.array(dtype=wp.vec4), n: wp.array(dtype=int),
                              kappa_dt2: float, num_threads: int, x: wp.array(dtype=wp.vec3),
                              out: wp.array(dtype=wp.vec3)):
    """`pair_matvec_list_kernel` over the entries `pack_entry` packed."""
    t = wp.tid()
    for q in range(t, n[0], num_threads):
        v = pv[q]
        c = pw[q]
        m = pn[q]
        nrm = wp.vec3(m[0], m[1], m[2])
        d = wp.vec4(0.0)
        for j in range(4):
            if v[j] >= 0:
                d[j] = wp.dot(nrm, x[v[j]])
        s = wp.dot(c, d)
        k = kappa_dt2 * m[3]
        for j in range(4):
            if v[j] >= 0:
                wp.atomic_add(out, v[j], (k * c[j] * (s - c[j] * d[j])) * nrm)


@wp.kernel
def pair_matvec_list_kernel(rec: ContactRecord, entries: wp.array(dtype=int),
                            n: wp.array(dtype=int), inv_mass: wp.array(dtype=float),
                            kappa_dt2: float, num_threads: int, x: wp.array(dtype=wp.vec3),
                            out: wp.array(dtype=wp.vec3)):
    """The off-diagonal part of the listed entries' Hessian ``k (w w^T) (x) n n^T`` times
    ``x`` into ``out`` (the diagonal blocks ``k w_j^2 n n^T`` are the operator's
    ``vertex_blocks``): ``out_j += k w_j n (n . sum_{l != j} w_l x_l)``, free vertices only
    (pins are eliminated). Only the active entries are listed (`list_on_kernel`, at each
    assembly): in a folded sheet's Newton and
    projective-dynamics solves 10-20 % of the self-contact record is active (16 x 16 fold:
    450-1,600 of 5,200-7,200 entries), and each inner iteration's product otherwise walked
    the whole record."""
    t = wp.tid()
    for q in range(t, n[0], num_threads):
        pair_matvec_entry(rec, entries[q], inv_mass, kappa_dt2, x, out)


@wp.kernel
def friction_guess_kernel(
    rec: ContactRecord,
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    num_sources: int,
    dt2: float,
    f_drive: wp.array(dtype=wp.vec3),
    num_threads: int,
    disp: wp.array(dtype=wp.vec3),
    f_class: wp.array(dtype=wp.vec3),
    gravity: wp.vec3,
    slide: wp.array(dtype=int),
    project: int,
    f_ext: wp.array(dtype=wp.vec3),
    src: int,
):
    """Friction's normal force for the step, and the initial guess of a vertex that friction
    can hold this step (the entries of obstacle ``src`` only: one launch per obstacle, in
    their order, so a vertex pressing on two obstacles takes the second's guess from where
    the first left it, on a GPU as on the CPU; in one launch a GPU's threads could both read
    the vertex's start and add their corrections: modelled on the CPU, a vertex slid 1 cm in
    a floor-wall crease ended 1 cm past its friction reference instead of on it). The force: the larger of the last step's and ``m |g| / dt^2`` at the
    prediction. With ``project``, a vertex arriving this step (no normal force from the last
    one) whose prediction lies inside its constraint starts on the constraint's plane: Newton
    then starts near the contact state instead of from a prediction up to ``|v| dt`` inside
    the surface, whose penalty energy (``kappa`` times the inertia's) its first iterations
    spent themselves undoing (the table's landing: 8.4 % one-frame strain at the box's corner
    after 8 iterations, 4.6 % with the projection). The guess: if static friction can hold the vertex where it started against the
    inertia of its predicted sliding ``u`` (tangential part of ``x - ref``) and the other forces
    ``f_drive`` at the prediction (``|u m / dt^2 + f_drive|_T <= mu lam``), it starts from
    ``ref`` tangentially (sticking); else from its prediction, shortened by what the full
    friction force cancels in a step (``mu lam dt^2 / m``). Newton's model of static friction
    is very stiff, so a vertex that sticks must start there; one that slides must not (the
    secant Hessian of the sliding branch would take many iterations to leave it). Newton and projective dynamics then correct only what the springs change:
    projective dynamics converges slowly on whole-cloth (low-frequency) motion, so a guess
    without friction left its sliding cloth almost frictionless."""
    t = wp.tid()
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    for e in range(t, count, num_threads):
        if slide.shape[0] > 0 and src == 0:
            slide[e] = 0
        mu = rec.friction[e]
        if rec.kind[e] != KIND_VERTEX_OBSTACLE or rec.source[e] != src:
            continue
        i = rec.vertex[e][0]
        w = inv_mass[i]
        if w <= 0.0:
            continue
        # the normal force that stops the predicted penetration within the step, m |g| / dt^2
        # (the impact on the step a vertex arrives, its weight when it rests), if larger than
        # the last step's
        slot = i * num_sources + rec.source[e]
        n = rec.normal[e]
        g = wp.dot(n, x[i]) - rec.offset[e]
        lam_i = lam[slot]
        gp = g
        pred = wp.vec3(0.0)  # what the guess left out of the inertial prediction
        if f_ext.shape[0] > 0:
            # a guess ``x0 + dt v0`` or ``x0`` left out the external forces' step (gravity)
            # and, for ``x0``, the velocity's (``-disp``, 0 for ``x0 + dt v0``): the predicted
            # penetration takes them in, so a resting vertex's normal force is its weight, as
            # at the inertial guess
            pred = (dt2 * w) * f_ext[i] - disp[i]
            gp = g + wp.dot(n, pred)
        arriving = lam_i <= 0.0  # no normal force from the last step
        if gp < 0.0:
            lam_i = wp.max(lam_i, -gp / (dt2 * w))
            lam[slot] = lam_i
        if g < 0.0:
            if project != 0 and arriving:
                # a vertex arriving at its surface this step starts on the constraint's plane,
                # not inside it (``project``: implicit Euler)
                wp.atomic_add(x, i, -g * n)
                wp.atomic_add(disp, i, -g * n)
        if lam_i <= 0.0 or mu <= 0.0:
            continue
        d = x[i] - rec.ref[e]
        u = d - wp.dot(d, n) * n  # predicted sliding (inertia, gravity)
        # the tangential force friction must supply to hold the vertex where it started,
        # the others at their predictions: inertia of the predicted sliding plus the rest
        F = u / (dt2 * w) + f_drive[i]
        F = F - wp.dot(F, n) * n
        if slide.shape[0] > 0:
            # with ``f_class`` (the other forces at the end of the last step: the cloth's
            # tension, which the prediction does not see) in place of ``f_drive``, less the
            # weight (``f_class`` holds it, and the prediction ``u`` already fell under it)
            Fc = u / (dt2 * w) + f_class[i] - gravity / w
            Fc = Fc - wp.dot(Fc, n) * n
            if wp.length(Fc) > mu * lam_i:
                slide[e] = 1
        target = wp.vec3(0.0)  # sticks
        if wp.length(F) > mu * lam_i:
            # slides: its prediction (with what the guess left out of it, ``pred``), slowed by
            # what the full friction force cancels in a step
            up = u + pred - wp.dot(pred, n) * n
            y = wp.length(up)
            cap = mu * lam_i * dt2 * w
            target = up
            if y > 0.0:
                target = (1.0 - wp.min(cap, y) / y) * up
        wp.atomic_add(x, i, target - u)
        wp.atomic_add(disp, i, target - u)


@wp.kernel
def contact_line_energy_kernel(
    rec: ContactRecord,
    x: wp.array(dtype=wp.vec3),
    dx: wp.array(dtype=wp.vec3),
    free: wp.array(dtype=float),
    steps: wp.vec4,
    inv_mass: wp.array(dtype=float),
    kappa_dt2: float,
    eps: float,
    lam: wp.array(dtype=float),
    num_sources: int,
    num_threads: int,
    out: wp.array(dtype=wp.float64),
    slot: int,
    onset: float,
):
    """``E_c`` (with the friction potential) at ``x`` into ``out[slot]`` (float64) and, with a
    direction ``dx`` (none: an empty array), at ``x + a_c d`` (``a_c = steps[c]``, ``d = free *
    dx``: a line search's candidates) into ``out[slot + c + 1]``: one pass over the record. An
    entry's gap is affine in the positions, ``g(x + a d) = g(x) + a g'(d)``, so the normal
    penalty at every candidate costs two dot products per vertex, not one per vertex and
    candidate (most of a self-contact record is inactive at all five: the fold's contact energy
    36.7 -> 24.6 ms a frame); an entry with friction (nonlinear in its vertex) is evaluated at
    each candidate. Pin-held entries (`pin_held`) have no energy here."""
    t = wp.tid()
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    line = dx.shape[0] > 0
    configs = int(1)
    if line:
        configs = 5
    for e in range(t, count, num_threads):
        vid = rec.vertex[e]
        w = rec.weight[e]
        n = rec.normal[e]
        im = float(0.0)
        g0 = -rec.offset[e]
        gd = float(0.0)
        for j in range(4):
            v = vid[j]
            if v >= 0:
                im = im + w[j] * w[j] * inv_mass[v]
                g0 = g0 + w[j] * wp.dot(n, x[v])
                if line:
                    gd = gd + w[j] * wp.dot(n, dx[v] * free[v])
        if im <= 0.0 or pin_held(vid, w, inv_mass):
            continue
        k = kappa_dt2 / im
        lam_i = float(0.0)
        if rec.friction[e] > 0.0 and rec.kind[e] == KIND_VERTEX_OBSTACLE:
            lam_i = lam[vid[0] * num_sources + rec.source[e]]
        for c in range(configs):
            a = float(0.0)
            if c > 0:
                a = steps[c - 1]
            g = g0 + a * gd
            fn, kn, E = normal_penalty(k, g, onset)
            if lam_i > 0.0:  # a vertex entry: its tangential displacement at the candidate
                i = vid[0]
                d = x[i] - rec.ref[e]
                if c > 0:  # (only along a line)
                    d = d + a * (dx[i] * free[i])
                u = d - wp.dot(d, n) * n
                E = E + coulomb_energy(rec.friction[e] * lam_i, wp.length(u), eps)
            if E != 0.0:
                wp.atomic_add(out, slot + c, wp.float64(E))


@wp.kernel
def pd_contact_kernel(
    rec: ContactRecord,
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    kappa_dt2: float,
    eps: float,
    lam: wp.array(dtype=float),
    num_sources: int,
    num_threads: int,
    f_out: wp.array(dtype=wp.vec3),
    vblock: wp.array(dtype=wp.mat33),
    objective: wp.array(dtype=wp.float64),
    slot: int,
    on_out: wp.array(dtype=int),
    slide: wp.array(dtype=int),
    slide_weight: float,
    pv: wp.array(dtype=wp.vec4i),
    pw: wp.array(dtype=wp.vec4),
    pn: wp.array(dtype=wp.vec4),
    packed: wp.array(dtype=int),
):
    """Local step of the contact constraints: the projection onto ``g >= 0`` gives the force
    ``-k_c min(g, 0) w_j n`` (and friction); the blocks ``w_j^2 H`` into ``vblock`` for this
    iteration's global matrix (lumped, ``|w_j| sum_l |w_l| H``, for an entry of several cloth
    vertices whose off-diagonal part the operator does not hold); ``E_c`` into the objective;
    with an ``on_out`` array, each entry's activity (`pair_matvec_list_kernel`), with ``pv``
    arrays each active entry packed (`pack_entry`). An entry marked in
    ``slide`` (the step's friction guess found its vertex driven past static friction) has a
    friction spring of ``slide_weight`` times ``k_c``: the inertia block, not 1000 times it
    (module doc)."""
    t = wp.tid()
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    for e in range(t, count, num_threads):
        weight = float(1.0)
        if slide.shape[0] > 0:
            if slide[e] != 0:
                weight = slide_weight
        on, f, H, Hn, E = entry_response(rec, e, x, inv_mass, kappa_dt2, eps, lam, num_sources,
                                         weight, 0.0)
        if on_out.shape[0] > 0:
            on_out[e] = int(on)
        if on and pv.shape[0] > 0:
            pack_entry(rec, e, inv_mass, pv, pw, pn, packed, -1.0)
        if on:
            vid = rec.vertex[e]
            w = rec.weight[e]
            # without the off-diagonal part in the operator (``on_out`` empty), an entry of
            # several cloth vertices (a cloth triangle or edge on a mesh feature) gets the
            # lumped block |w_j| (sum_l |w_l|) H: the diagonal blocks w_j^2 H alone moved each
            # vertex by the whole violation over w_j (a weighted point with weights 1/3 went
            # three times too far, and a vertex of small weight much farther: a coarse sheet
            # landing on the torus was thrown up at 6 m/s, +0.43 J in a step); the lumped
            # blocks move every vertex by the violation (the point exactly onto its target),
            # and they bound the entry's true Hessian (w w^T (x) H) from above
            lump = float(0.0)
            if on_out.shape[0] == 0:
                for j in range(4):
                    v = vid[j]
                    if v >= 0 and inv_mass[v] > 0.0:
                        lump = lump + wp.abs(w[j])
            for j in range(4):
                v = vid[j]
                if v >= 0 and inv_mass[v] > 0.0:
                    wp.atomic_add(f_out, v, w[j] * f)
                    c = w[j] * w[j]
                    if lump > 0.0:
                        c = wp.abs(w[j]) * lump
                    wp.atomic_add(vblock, v, c * H)
            wp.atomic_add(objective, slot, wp.float64(E))


@wp.kernel
def block_inverse_kernel(blocks: wp.array(dtype=wp.mat33), vblock: wp.array(dtype=wp.mat33),
                         free: wp.array(dtype=float), dinv: wp.array(dtype=wp.mat33)):
    """``dinv = (blocks + vblock)^-1`` for free vertices (0 for pins)."""
    i = wp.tid()
    if free[i] > 0.0:
        dinv[i] = wp.inverse(blocks[i] + vblock[i])
    else:
        dinv[i] = wp.mat33(0.0)


@wp.kernel
def contact_velocity_kernel(
    rec: ContactRecord,
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    inv_dt: float,
    slack: float,
    x_pred: wp.array(dtype=wp.vec3),
    num_threads: int,
    v: wp.array(dtype=wp.vec3),
):
    """After the solve: a vertex within ``slack`` of its plane that still approaches it
    (``n . (x - ref) / dt < 0``, relative to the surface) leaves the step with ``-mu_N`` times
    the normal speed it arrived with (from its predicted path ``x_pred``): the solve already
    stopped its position; its friction acted inside the solve, so the stage's impulse, which
    sees no approach, adds none."""
    t = wp.tid()
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    for e in range(t, count, num_threads):
        if rec.kind[e] != KIND_VERTEX_OBSTACLE:
            continue
        i = rec.vertex[e][0]
        if inv_mass[i] <= 0.0:
            continue
        n = rec.normal[e]
        xi = x[i]
        if wp.dot(n, xi) - rec.offset[e] < slack:  # touching, as the stage's impulse counts it
            vn = wp.dot(n, xi - rec.ref[e]) * inv_dt
            if vn < 0.0:
                # restitution of the normal speed it arrived with (the predicted path relative
                # to the surface), not of the step's average
                vin = wp.min(wp.dot(n, x_pred[i] - rec.ref[e]) * inv_dt, 0.0)
                wp.atomic_add(v, i, (-rec.restitution[e] * vin - vn) * n)


@wp.kernel
def start_overlap_kernel(
    rec: ContactRecord,
    x: wp.array(dtype=wp.vec3),
    x_start: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    inv_dt: float,
    num_threads: int,
    acc: wp.array(dtype=wp.vec3),
    cnt: wp.array(dtype=float),
):
    """The cap on a start overlap's push-out (`ContactCoupling.end_step`), one Jacobi pass.

    An entry that started inside its plane (start gap ``g0 < 0``: cloth placed within the
    thickness of a surface, or left there by the last step's response) was pushed out by the
    solve; that push is a position correction, not motion: the entry's point leaves with at
    most the normal speed (relative to the surface) of how far it ended beyond the plane,
    ``max(g1, 0) / dt``. Its excess over that, ``(min(g1, 0) - g0) / dt``, is taken from its
    vertices by their share ``w_j / m_j / sum w_k^2 / m_k``, as its projection moves them, and
    averaged per vertex weighted by ``|w_j|`` (`velocity_average_kernel`). ``g0``: a vertex entry's ``ref``
    is its start position carried by the obstacle (``g0 = n . ref - offset``), a feature
    entry's is its plane's point at the step's start (``g0 = n . (sum w_j x_start_j - ref)``);
    in both ``g1 - g0`` is the approach relative to the surface. (Four passes, each taking
    what the last left, gave the same first-frame speeds as one on the box scenes of
    ``test_cloth_starting_inside_the_thickness_is_not_launched``.)"""
    t = wp.tid()
    count = wp.min(rec.count[0], rec.vertex.shape[0])
    for e in range(t, count, num_threads):
        n = rec.normal[e]
        g1, den = entry_gap(rec, e, x, inv_mass)
        if den <= 0.0:
            continue
        vid = rec.vertex[e]
        w = rec.weight[e]
        # the start gap: against the plane's start position (offset - n . ref: how far it moved)
        g0, den0 = entry_gap(rec, e, x_start, inv_mass)
        g0 = g0 + rec.offset[e] - wp.dot(n, rec.ref[e])
        if rec.kind[e] == KIND_VERTEX_OBSTACLE:
            g0 = wp.dot(n, rec.ref[e]) - rec.offset[e]
        if g0 >= 0.0:
            continue
        excess = (wp.min(g1, 0.0) - g0) * inv_dt
        if excess > 0.0:
            for j in range(4):
                k = vid[j]
                if k >= 0 and inv_mass[k] > 0.0:
                    aw = wp.abs(w[j])
                    wp.atomic_add(acc, k, (-aw * excess * w[j] * inv_mass[k] / den) * n)
                    wp.atomic_add(cnt, k, aw)


@wp.kernel
def velocity_average_kernel(v: wp.array(dtype=wp.vec3), acc: wp.array(dtype=wp.vec3),
                            cnt: wp.array(dtype=float)):
    """``v += acc / cnt`` where ``cnt > 0`` (`start_overlap_kernel`'s caps, weighted), cleared."""
    i = wp.tid()
    c = cnt[i]
    if c > 0.0:
        v[i] = v[i] + acc[i] / c
        acc[i] = wp.vec3(0.0)
        cnt[i] = 0.0


class ContactCoupling:
    """A solver's view of its collision stage's record as the stiff term ``E_c`` (module doc).

    Args:
        model: the `ClothModel`.
        stage: the `CollisionStage`.
        stiffness: ``kappa`` (> 0), the term's stiffness over the inertia block ``m/dt^2``.
        friction_velocity: m/s, > 0: the relative sliding speed below which friction is a stiff
            spring rather than a constant force (the smoothing ``eps = friction_velocity * dt``
            of the Coulomb law; a vertex held by static friction creeps at most this fast).
    """

    @staticmethod
    def _check(stiffness, name="contact_stiffness") -> float:
        return positive_finite(stiffness, name)

    def __init__(self, model, stage, stiffness: float = DEFAULT_CONTACT_STIFFNESS,
                 friction_velocity: float = DEFAULT_FRICTION_VELOCITY):
        self.model = model
        self.stage = stage
        self.kappa = self._check(stiffness)
        self.friction_velocity = self._check(friction_velocity, "friction_velocity")
        self.device = model.device
        self.vblock = wp.zeros(model.num_vertices, dtype=wp.mat33, device=self.device)
        self.nblock = wp.zeros(model.num_vertices, dtype=wp.mat33, device=self.device)
        self.x_pred = wp.zeros(model.num_vertices, dtype=wp.vec3, device=self.device)
        self.x_start = wp.zeros(model.num_vertices, dtype=wp.vec3, device=self.device)
        self.v_acc = wp.zeros(model.num_vertices, dtype=wp.vec3, device=self.device)
        self.v_cnt = wp.zeros(model.num_vertices, dtype=float, device=self.device)
        self.f_other = wp.zeros(model.num_vertices, dtype=wp.vec3, device=self.device)
        self.active = wp.zeros(1, dtype=int, device=self.device)
        #: the self-contacts active at the last assembly (`add_newton`; ``active`` counts the
        #: record's): the inner solve's translation correction runs only then
        #: (`linear.CGSolver.translation`)
        self.self_active = wp.zeros(1, dtype=int, device=self.device)
        # with mesh features, the record holds entries of two cloth vertices (a cloth edge on an
        # obstacle's feature): their activity, for the off-diagonal part of their Hessian
        self._dt = 1.0  # the step's dt, set by `add_newton` (read by `matvec_add`)
        self._feature_pairs = getattr(getattr(stage, "features", None), "active", False)
        #: whether the features' friction takes its normal impulse from this solve
        #: (`feature_press_kernel`, `end_step`)
        self._feature_friction = bool(self._feature_pairs
                                      and getattr(stage.features, "has_friction", False))
        #: whether `matvec_add` applies the feature pairs' off-diagonal blocks (Newton: yes;
        #: projective dynamics sets False, its local step writes lumped diagonal blocks)
        self.pairs_in_operator = True
        self.sources = max(1, len(stage.obstacles))
        # `add_newton`'s copy of the cloth's forces before any contact entry's
        self._b_cloth = wp.zeros(model.num_vertices, dtype=wp.vec3, device=self.device)
        # normal force per (vertex, obstacle) at the end of the last step: friction's bound
        self.lam = wp.zeros(model.num_vertices * self.sources, dtype=float, device=self.device)
        # how far below its target the solve left each (vertex, obstacle) pair at the end of
        # the last step: the penalty's give under the load it carries. The next step's target
        # is raised by it, so a loaded contact ends at the thickness instead of inside it
        self.sag = wp.zeros(model.num_vertices * self.sources, dtype=float, device=self.device)
        has_obstacles = getattr(stage, "contact", None) is not None
        self.sag_cap = SAG_CAP * stage.thickness if has_obstacles else 0.0
        self._no_flags = wp.zeros(0, dtype=int, device=self.device)
        self._no_pack = (wp.zeros(0, dtype=wp.vec4i, device=self.device),
                         wp.zeros(0, dtype=wp.vec4, device=self.device),
                         wp.zeros(0, dtype=wp.vec4, device=self.device), self._no_flags)
        self._no_vec = wp.zeros(0, dtype=wp.vec3, device=self.device)
        self._no_gaps = wp.zeros(0, dtype=float, device=self.device)
        #: Newton's resting-contact rule (`newton_contact_kernel`'s ``resting``): set by implicit
        #: Euler when its guess leaves the external forces' step out (a resting vertex then
        #: starts on its surface, where its penalty is not yet active)
        self.resting = False
        self._no_free = wp.zeros(0, dtype=float, device=self.device)
        # sized by the obstacle record: `pairs_on`, `slide` (per entry: driven past static
        # friction this step, PD) and the threads (again whenever the stage regrows it)
        self._record_regrown(stage.record)
        if hasattr(stage, "on_record_regrown"):
            stage.on_record_regrown(self._record_regrown)
        if hasattr(stage, "on_restart"):
            stage.on_restart(self.restart)
        self._classified = False  # `friction_guess` wrote `slide` for this step
        # self-contacts inside the solve (stage.self_in_solve): their own record, each entry's
        # activity at the last assembly, and the off-diagonal Hessian as an operator term
        sc = getattr(stage, "self_collision", None)
        self.self_record = None
        #: m: the self-contacts' penalty onset in Newton (`normal_penalty`, `SELF_ONSET`)
        self.self_onset = 0.0
        if sc is not None and getattr(stage, "self_in_solve", False):
            self.self_onset = SELF_ONSET * float(getattr(sc, "thickness", 0.0))
            from ..collision.record import make_record

            self._dt = 1.0
            self._grow_self(sc.capacity)
            self.self_dropped = wp.zeros(1, dtype=int, device=self.device)  # over all steps
            # each vertex's deepest self-contact sag of the last two steps (``raw``: the
            # last's, ``last``: the one before): the next step's targets are raised by the
            # lesser (`self_sag_apply_kernel`, `self_sag_persist_kernel`), as the obstacles'
            self.self_sag = wp.zeros(model.num_vertices, dtype=float, device=self.device)
            self.self_sag_raw = wp.zeros(model.num_vertices, dtype=float, device=self.device)
            self.self_sag_last = wp.zeros(model.num_vertices, dtype=float, device=self.device)
            self.self_sag_cap = SAG_CAP * float(getattr(sc, "thickness", 0.0))
            self._dropped_seen = 0
            stage.solve_coupling = self  # its `frame_end` reports and regrows this record

    @property
    def record(self):
        return self.stage.record

    def _args(self, dt):
        return (self.kappa / (dt * dt), self.friction_velocity * dt, self.lam, self.sources,
                self.threads)

    def detect(self, x_start, x_pred, dt: float, time) -> None:
        """The record for this step (`CollisionStage.detect`), the active count cleared, the
        prediction kept (restitution reads the speed a vertex arrives with from it)."""
        self.stage.detect(x_start, x_pred, dt, time)
        if self.sag_cap > 0.0:
            launch(sag_apply_kernel, self.threads,
                   [self.record, self.sag, self.sources, self.threads], device=self.device)
        self.active.zero_()
        wp.copy(self.x_pred, x_pred)
        wp.copy(self.x_start, x_start)
        self.detect_self(x_start, x_pred)

    def detect_self(self, x_start, x_end) -> None:
        """The self-contacts of the solve (none without self-collision in the solve): the pairs
        whose paths ``x_start -> x_end`` come within the thickness plus the stage's
        ``self_solve_margin``, in place of the record's entries. `detect` takes them from the
        predicted path; implicit Euler takes them again from the path to its iterate where that
        left the prediction far behind (an impact: `implicit.IMPACT_ROUNDS`)."""
        if self.self_record is None:
            return
        sc = self.stage.self_collision  # (None, or in_solve off, when switched off since)
        self.self_record.count.zero_()
        self.self_record.overflow.zero_()
        self.self_pen.fill_(float("nan"))  # new entries: no last gap, none held (NaN compares false)
        if sc is not None and self.stage.self_in_solve:
            gap = sc.thickness + self.stage.self_solve_margin
            sc.detect(x_start, x_end, gap, self.self_record)
            # the response's first round may test these entries again (`note_solve`)
            sc.note_solve(x_start, x_end, gap, self.self_record)
            launch(add_overflow_kernel, 1, [self.self_record, self.self_dropped],
                   device=self.device)
            if self.self_sag_cap > 0.0:
                launch(self_sag_apply_kernel, self.self_threads,
                       [self.self_record, self.self_sag, self.self_threads],
                       device=self.device)
        elif sc is not None:
            sc.forget_solve()  # the record is empty now
        self.self_on.zero_()
        self.self_list_n.zero_()

    # ------------------------------------------------------------------ Newton
    def add_newton(self, x, b, diag, dt: float, resting: bool = False,
                   first: bool = True) -> None:
        """Active entries' force into ``b`` and Hessian blocks into ``diag`` and `vblock`
        (which this clears first: call once per Newton assembly, after ``diag`` is set);
        ``resting``: the entries resting on their constraints too (module doc, *Resting
        contact*; a step's first assembly). A later assembly (``first`` False) gives the
        penalty's block to a self-contact entry within `RESTING_BAND` above its constraint that
        closed in on it since the last assembly or was inside it then (module doc, *Contacts
        that flip*; `HOLD_FLIPS`)."""
        self.vblock.zero_()
        self.nblock.zero_()
        self.active.zero_()
        self.self_active.zero_()
        mode = 1 if resting and first else (0 if first or not HOLD_FLIPS else 2)
        wp.copy(self._b_cloth, b)  # the cloth's forces, before any contact entry's
        launch(newton_contact_kernel, self.threads,
               [self.record, x, self.model.inv_mass, *self._args(dt), b, diag, self.vblock,
                self.nblock, self.active,
                self.pairs_on if self.pairs_on is not None else self._no_flags,
                mode if mode < 2 else 0, *self._no_pack, 0.0, self._no_gaps, self._b_cloth],
               device=self.device)
        if self.pairs_on is not None:  # the active feature pairs, listed for `matvec_add`
            self.pairs_list_n.zero_()
            launch(list_on_kernel, self.threads,
                   [self.record, self.pairs_on, 2, self.threads, self.pairs_list,
                    self.pairs_list_n], device=self.device)
        self._dt = dt
        if self.self_record is not None:
            self.self_list_n.zero_()  # the active entries packed for `matvec_add`
            launch(newton_contact_kernel, self.self_threads,
                   [self.self_record, x, self.model.inv_mass, *self._args(dt)[:-1],
                    self.self_threads, b, diag, self.vblock, self.nblock, self.self_active,
                    self.self_on, mode, *self._self_pack, self.self_onset,
                    self.self_pen if HOLD_FLIPS else self._no_gaps, self._b_cloth],
                   device=self.device)

    def limit_reversals(self, x, dx, dt: float, count) -> None:
        """Newton's direction ``dx`` at ``x`` with every sliding vertex that it would carry
        back past its friction reference landed on that reference instead
        (`friction_reversal_kernel`); how many in ``count[0]``."""
        for src in range(self.sources):  # one obstacle at a time (the kernel's doc)
            launch(friction_reversal_kernel, self.threads,
                   [self.record, x, self.model.inv_mass, self.friction_velocity * dt, self.lam,
                    self.sources, self.threads, dx, count, src], device=self.device)

    def mark_free(self, free) -> None:
        """``free[0]`` = 1 when this step's records (obstacles, self-contacts) hold no entry,
        written or dropped, else 0 (`contact_free_kernel`; on the device, capturable)."""
        rec, srec = self.record, self.self_record
        no = self._no_flags  # an empty int array: no self record
        launch(contact_free_kernel, 1,
               [rec.count, rec.overflow, no if srec is None else srec.count,
                no if srec is None else srec.overflow, free], device=self.device)

    def restart(self) -> None:
        """A run starts (`CollisionStage.restart_span`): the last step's normal forces, the
        other forces and the sags (obstacles' and self-contacts') are forgotten; carried into
        a new run's first steps they made a second run of the fold differ from the first by
        0.9 mm."""
        for a in (self.lam, self.sag, self.f_other, getattr(self, "self_sag", None),
                  getattr(self, "self_sag_raw", None), getattr(self, "self_sag_last", None)):
            if a is not None:
                a.zero_()

    def _record_regrown(self, record) -> None:
        """The arrays sized by the stage's obstacle record: at construction, and when
        `CollisionStage.frame_end` replaces the record with a larger one (outside any captured
        step)."""
        cap = int(record.vertex.shape[0])
        self.threads = record_threads(cap, self.device, BATCH)
        self.slide = wp.zeros(max(cap, 1), dtype=int, device=self.device)
        self.pairs_on = (wp.zeros(max(cap, 1), dtype=int, device=self.device)
                         if self._feature_pairs else None)
        # the active entries of several cloth vertices, listed at each Newton assembly
        # (`add_newton`): each inner iteration's product walked the whole record (the table
        # under implicit Euler: 28 us a product, 1,900 products a frame)
        self.pairs_list = (wp.zeros(max(cap, 1), dtype=int, device=self.device)
                           if self._feature_pairs else None)
        self.pairs_list_n = wp.zeros(1, dtype=int, device=self.device)

    def _grow_self(self, capacity: int) -> None:
        """A self-contact record of ``capacity`` entries (allocation: outside a captured step)."""
        from ..collision.record import make_record

        self.self_record = make_record(int(capacity), self.device)
        self.self_on = wp.zeros(int(capacity), dtype=int, device=self.device)
        # per entry: its gap at the last Newton assembly (`newton_contact_kernel`, `HOLD_FLIPS`)
        self.self_pen = wp.zeros(int(capacity), dtype=float, device=self.device)
        # the active entries, packed by the assembly that finds them active (`pack_entry`)
        self.self_list_n = wp.zeros(1, dtype=int, device=self.device)
        self._self_pack = (wp.zeros(int(capacity), dtype=wp.vec4i, device=self.device),
                           wp.zeros(int(capacity), dtype=wp.vec4, device=self.device),
                           wp.zeros(int(capacity), dtype=wp.vec4, device=self.device),
                           self.self_list_n)
        self.self_threads = record_threads(int(capacity), self.device, BATCH)

    def self_frame_end(self) -> list:
        """Self-contacts of the solve dropped for want of room since the last call (host read,
        once a frame, `CollisionStage.frame_end`): the record then doubles. Dropped pairs are
        still resolved after the solve. ``(message, regrown)`` pairs."""
        if self.self_record is None:
            return []
        new, self._dropped_seen = count_since(self.self_dropped, self._dropped_seen)
        if new <= 0:
            return []
        cap = 2 * self.self_record.vertex.shape[0]
        self._grow_self(cap)
        return [(f"{new} self-contacts did not fit the solve's record (they were resolved after "
                 f"the solve); its room is doubled to {cap} entries", True)]

    @property
    def self_stats(self) -> dict:
        """The last step's self-contacts in the solve, and those dropped over all steps."""
        if self.self_record is None:
            return {}
        return {"self_solve_contacts": min(int(self.self_record.count.numpy()[0]),
                                           self.self_record.vertex.shape[0]),
                "self_solve_dropped": int(self.self_dropped.numpy()[0])}

    # the operator's extra term (`SpringSystemOperator.extra`)
    def matvec_add(self, x, out) -> None:
        """The off-diagonal blocks of this iteration's active multi-vertex entries times ``x``,
        added to ``out``: the feature pairs of the obstacle record when Newton writes their
        activity (`add_newton`; projective dynamics gives them lumped diagonal blocks instead,
        `pd_contact_kernel`, and skips them here), and the self-contacts."""
        if self.pairs_on is not None and self.pairs_in_operator:
            launch(pair_matvec_list_kernel, self.threads,
                   [self.record, self.pairs_list, self.pairs_list_n, self.model.inv_mass,
                    self.kappa / (self._dt * self._dt), self.threads, x, out],
                   device=self.device)
        if self.self_record is not None:
            launch(pair_matvec_packed_kernel, self.self_threads,
                   [*self._self_pack,
                    self.kappa / (self._dt * self._dt), self.self_threads, x, out],
                   device=self.device)

    def add_diagonal(self, diag) -> None:  # its diagonal blocks are added by `add_newton`
        pass

    def friction_guess(self, x, disp, dt: float, f_drive, classify: bool = False,
                       project: bool = False, f_ext=None) -> None:
        """Friction's normal force for the step and the initial guess of the vertices it acts
        on (`friction_guess_kernel`; ``f_drive``: the forces other than contact at ``x``, the
        prediction); ``disp`` (which tracks ``x - x_hat``) is updated the same. ``classify``
        (projective dynamics): also mark the entries whose vertex the other forces at the end
        of the last step drive past static friction (`slide`, read by `pd_local`). ``project``
        (Newton): a vertex arriving at its surface this step starts on its constraint's plane."""
        for src in range(self.sources):  # one obstacle at a time (the kernel's doc)
            launch(friction_guess_kernel, self.threads,
                   [self.record, x, self.model.inv_mass, self.lam, self.sources, dt * dt,
                    f_drive, self.threads, disp, self.f_other if classify else self._no_vec,
                    wp.vec3(*self.model.gravity), self.slide if classify else self._no_flags,
                    int(project), self._no_vec if f_ext is None else f_ext, src],
                   device=self.device)
        self._classified = bool(classify)

    def energy(self, x, out, dt: float, slot: int = 0) -> None:
        """``E_c(x)`` added to ``out[slot]`` (a float64 array)."""
        self.energy_line(x, self._no_vec, self._no_free, wp.vec4(0.0), out, dt, slot)

    def energy_line(self, x, dx, free, steps, out, dt: float, slot: int = 0) -> None:
        """`energy` at ``x`` added to ``out[slot]`` and at ``x + a_j free dx`` (``a_j`` the
        components of the vec4 ``steps``) to ``out[slot + j + 1]``: a line search's
        candidates, without their positions (`contact_line_energy_kernel`)."""
        launch(contact_line_energy_kernel, self.threads,
               [self.record, x, dx, free, steps, self.model.inv_mass, *self._args(dt), out,
                slot, 0.0], device=self.device)
        if self.self_record is not None:
            launch(contact_line_energy_kernel, self.self_threads,
                   [self.self_record, x, dx, free, steps, self.model.inv_mass,
                    *self._args(dt)[:-1], self.self_threads, out, slot, self.self_onset],
                   device=self.device)

    def end_step(self, x, v, dt: float, time=None) -> None:
        """After the solve: the normal forces for the next step's friction (bounded by the load
        of the other forces at ``x``: `normal_force_kernel`), and no vertex held by an active
        entry still approaching its surface. ``time``: the state's time array (wind reads it)."""
        m = self.model
        f = self.f_other
        launch(weight_kernel, m.num_vertices, [m.mass, wp.vec3(*m.gravity), f],
               device=self.device)
        for term in m.force_terms:
            term.eval(x, v, f, time)
        self.lam.zero_()
        launch(normal_force_kernel, self.threads,
               [self.record, x, m.inv_mass, self.kappa / (dt * dt), self.threads,
                self.sources, f, self.lam], device=self.device)
        if self._feature_friction:
            launch(feature_press_kernel, self.threads,
                   [self.record, x, m.inv_mass, self.kappa / (dt * dt), dt, self.threads, f,
                    self.stage.features.pressed], device=self.device)
        if self.sag_cap > 0.0:
            self.sag.zero_()
            launch(sag_update_kernel, self.threads,
                   [self.record, x, self.model.inv_mass, self.sag_cap, self.sources,
                    self.threads, self.sag], device=self.device)
        if self.self_record is not None and self.self_sag_cap > 0.0:
            self.self_sag_raw.zero_()
            launch(self_sag_update_kernel, self.self_threads,
                   [self.self_record, x, self.model.inv_mass, self.self_sag_cap,
                    self.self_threads, self.self_sag_raw], device=self.device)
            launch(self_sag_persist_kernel, self.model.num_vertices,
                   [self.self_sag_raw, self.self_sag_last, self.self_sag], device=self.device)
        launch(contact_velocity_kernel, self.threads,
               [self.record, x, self.model.inv_mass, 1.0 / dt,
                self.stage.contact.slack if self.stage.contact is not None else 0.0,
                self.x_pred, self.threads, v], device=self.device)
        # start overlaps: their push-out is not a separation speed (`start_overlap_kernel`).
        # Measured without: a sheet lying on the floor at height 0 (5 mm thickness) left at
        # 0.5 m/s (implicit Euler) and 0.8 m/s (projective dynamics) and rose 2-4 cm; a 10 x 10
        # sheet on a box's face, its overhang over the rims, 1.2 / 1.5 m/s at the first frame
        # (free fall: 0.16)
        launch(start_overlap_kernel, self.threads,
               [self.record, x, self.x_start, self.model.inv_mass, 1.0 / dt, self.threads,
                self.v_acc, self.v_cnt], device=self.device)
        launch(velocity_average_kernel, self.model.num_vertices, [v, self.v_acc, self.v_cnt],
               device=self.device)

    # ------------------------------------------------------------------ projective dynamics
    def pd_local(self, x, f, objective, slot: int, dt: float) -> None:
        """Forces into ``f``, this iteration's blocks into `vblock`, ``E_c`` into the objective."""
        self.vblock.zero_()
        launch(pd_contact_kernel, self.threads,
               [self.record, x, self.model.inv_mass, *self._args(dt), f, self.vblock,
                objective, slot, self._no_flags,
                self.slide if self._classified else self._no_flags,
                1.0 / self.kappa, *self._no_pack], device=self.device)
        if self.self_record is not None:
            self._dt = dt
            self.self_list_n.zero_()  # the active entries packed for `matvec_add`
            launch(pd_contact_kernel, self.self_threads,
                   [self.self_record, x, self.model.inv_mass, *self._args(dt)[:-1],
                    self.self_threads, f, self.vblock, objective, slot, self.self_on,
                    self._no_flags, 1.0, *self._self_pack], device=self.device)

    def invert_diagonal(self, blocks, free, dinv) -> None:
        """``dinv = (blocks + vblock)^-1`` (the global matrix's diagonal with contact)."""
        launch(block_inverse_kernel, self.model.num_vertices, [blocks, self.vblock, free, dinv],
               device=self.device)

    def host_factors(self, free_index):
        """`vblock` as low-rank factors for a direct solve (host): ``(rows, U)`` with ``rows``
        positions in ``free_index`` and ``U`` (r, 3) such that the blocks are ``sum u u^T``
        (eigen-decomposition of each non-zero block)."""
        vb = self.vblock.numpy().astype(np.float64)
        pos = -np.ones(self.model.num_vertices, dtype=np.int64)
        pos[free_index] = np.arange(len(free_index))
        rows, us = [], []
        for i in np.flatnonzero(np.abs(vb).reshape(len(vb), -1).max(axis=1) > 0):
            if pos[i] < 0:
                continue
            lam, V = np.linalg.eigh(0.5 * (vb[i] + vb[i].T))
            for a in range(3):
                if lam[a] > 1e-12 * max(lam.max(), 1e-30):
                    rows.append(pos[i])
                    us.append(math.sqrt(lam[a]) * V[:, a])
        return np.asarray(rows, dtype=np.int64), np.asarray(us, dtype=np.float64).reshape(-1, 3)


@wp.kernel
def contact_free_kernel(count: wp.array(dtype=int), overflow: wp.array(dtype=int),
                        self_count: wp.array(dtype=int), self_overflow: wp.array(dtype=int),
                        free: wp.array(dtype=int)):
    """``free[0]`` = 1 when the step's records (obstacles; self-contacts, when given) hold no
    entry, written or dropped: no contact term enters its Newton solve."""
    k = count[0] + overflow[0]
    if self_count.shape[0] > 0:
        k += self_count[0] + self_overflow[0]
    free[0] = 0
    if k == 0:
        free[0] = 1
