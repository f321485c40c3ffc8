"""Strain and area limiting: position corrections run after any solver (``physics.md`` 2.10).

Strain limiting (notes L1376-1439) uses projection only as a correction pass with loose bounds:
the method (explicit, implicit, position-based, projective) advances the cloth, then these
passes move only the elements that violate their bounds.

- `StrainLimit`: every mesh edge's stretch ratio ``sigma = |x_i - x_j| / L`` is clamped to
  ``[sigma_min, sigma_max]`` by the mass-weighted projection of the notes (L1386-1408, with the
  weight fix of physics.md 2.10):

      sigma0 = clamp(sigma, sigma_min, sigma_max)
      x_i <- x_i - w_i/(w_i + w_j) (|x_ij| - sigma0 L) x_ij/|x_ij|
      x_j <- x_j + w_j/(w_i + w_j) (|x_ij| - sigma0 L) x_ij/|x_ij|

  (``w = 1/m``, 0 for pinned vertices, so a pinned end never moves). PBD's stretch projection is
  the case ``sigma_min = sigma_max = 1``; ``sigma_min = 0, sigma_max = inf`` changes nothing
  (L1405-1407).
- `AreaLimit`: every triangle's area ``A`` is clamped to ``[a_min A0, a_max A0]`` (``A0`` its rest
  area) by scaling it about its mass-weighted centroid ``c`` by ``s = sqrt(clamp(A)/A)``
  (L1410-1429, with the sqrt fix of physics.md 2.10). A triangle with one pinned vertex scales
  about that vertex (its mass is infinite); one with two or three pinned vertices is skipped
  (it cannot scale without moving a pin).

Both can run Jacobi iterations in the GPU style: one thread per element computes its correction
and ``atomic_add``s it, with a count of 1, into per-vertex accumulators; one thread per vertex
then applies the average ``x_i <- x_i + sum(dx) / (n_i + alpha)`` over the ``n_i`` *active*
elements at the vertex (those on or outside a bound), which is the notes' Jacobi blend
``(x_acc + alpha x) / (n + alpha)`` written with deltas (L1310-1318). ``alpha`` (``relaxation``)
defaults to 0 here: a lone violated element is then corrected fully in one iteration.

`StrainLimit` defaults to *coloured Gauss-Seidel* instead (``gauss_seidel=True``; the edges are
greedily coloured once so that a colour shares no vertex, and each colour is one parallel launch
that corrects in place), as the notes' T29 suggests: measured on a soft (20 N/m) 24 x 24 sheet
hanging from two corners with 20 iterations per substep, the largest stretch over 2 s was 1.6 %
with Gauss-Seidel and 8.2 % with Jacobi, at 1.25x the cost. `AreaLimit` uses Jacobi.

**A bound that holds.** With a ``tolerance`` (default 1e-3, in ratio units: 0.1 % of the rest
length or area) a pass does not run a fixed count: a check kernel counts the elements outside
the bounds widened by the tolerance, and a device-side loop (`warp.capture_while`, a conditional
loop inside a recorded graph, so the step stays capturable) sweeps again while any is, up to
``iterations`` sweeps; the check runs after every ``check_every`` sweeps (3 for `StrainLimit`:
a check costs about a sweep, and a sweep past convergence moves almost nothing). A pass whose
elements are inside costs one check. A pass that reaches the
cap with elements still outside is counted on the device and reported once a frame by
`frame_end` (the scene runner prints a warning with the frame); nothing stops short silently.
Gauss-Seidel is accelerated by over-relaxation (``over_relaxation``, default 1.8: a violated
edge is moved 1.8 times its projection, into its allowed range) and, on pinned cloth, by
long-range tethers to the nearest pins (Kim, Chentanez and Müller 2012; implied by the edge
bounds in any direction, so they change no answer the limit should give). Measured on Newton's
cloth_hanging scene (64 x 32 cells falling from a pinned short edge, `warp-cloth bench
limits`), a taut 64-edge chain needs tens of sweeps a step; over-relaxation halved them,
tethers helped little there (the falling sheet is curved, so they are rarely active) and cut
them 3.2x on the default hanging scene under PD.

**Contact.** The collision stage runs after the limits (`warp_cloth.solvers.base`), and its
friction holds touching vertices where they are, which stretched edges past the limit (2.5 %
under a 1 % limit on that scene). So a limit with a tolerance runs again after the stage
(`after_contact`): one check, and only where something is outside, sweeps with the stage's
contact projection after each sweep, ending with both the bound and non-penetration.

Velocities are corrected consistently with the positions: every position change ``dx`` adds
``dx / dt`` to the velocity (the position-based velocity update of the notes, L1344), so the
pass removes exactly the velocity that produced the violation and the next step does not undo it;
it adds no energy (tested: a falling, limited sheet's total energy never rises).

Limitations: a taut sheet needs many sweeps (Gauss-Seidel converges slowly on long chains), so a
limited step costs more than the solver's step on stiff hanging scenes; ``tolerance=None``
restores the old fixed count. Outside a recorded graph the adaptive loop reads its condition on
the host after each check (an int on the CPU, a device sync on CUDA). On a GPU the float atomics
of the Jacobi mode sum in an arbitrary order, so results can differ in the last bits from run to
run (on the CPU they are deterministic).
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from .collision.features import inelastic_velocity
from .tethers import PinStretch, model_tether_anchors, tether_kernel
from .util import launch, not_text_or_bool, positive_finite

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile

__all__ = ["StrainLimit", "AreaLimit", "edge_projection", "color_constraints"]


@wp.func
def edge_projection(xi: wp.vec3, xj: wp.vec3, wi: float, wj: float, target: float):
    """The notes' single-edge projection to length ``target`` (L1275-1295), as a direction.

    Returns ``g`` such that ``x_i += w_i g`` and ``x_j -= w_j g`` give ``|x_i - x_j| = target``
    exactly (to rounding) and keep the mass-weighted centre. Zero for a degenerate edge or two
    pinned ends. Shared with the position-based solver, so that a ``[1, 1]`` strain limit is
    bit-for-bit a PBD pass.
    """
    d = xi - xj
    l = wp.length(d)
    wsum = wi + wj
    if l < 1.0e-12 or wsum <= 0.0:
        return wp.vec3(0.0)
    return (target - l) / (wsum * l) * d


@wp.kernel
def strain_limit_kernel(
    x: wp.array(dtype=wp.vec3),
    edges: wp.array2d(dtype=wp.int32),
    rest: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    sigma_min: float,
    sigma_max: float,
    delta: wp.array(dtype=wp.vec3),
    count: wp.array(dtype=float),
):
    e = wp.tid()
    i = edges[e, 0]
    j = edges[e, 1]
    wi = inv_mass[i]
    wj = inv_mass[j]
    if wi + wj <= 0.0:
        return
    L = rest[e]
    s = wp.length(x[i] - x[j]) / L
    if s > sigma_min and s < sigma_max:
        return  # inside the bounds: inactive, not counted
    s0 = wp.min(wp.max(s, sigma_min), sigma_max)
    g = edge_projection(x[i], x[j], wi, wj, s0 * L)
    wp.atomic_add(delta, i, wi * g)
    wp.atomic_sub(delta, j, wj * g)
    wp.atomic_add(count, i, 1.0)
    wp.atomic_add(count, j, 1.0)


@wp.kernel
def strain_limit_gs_kernel(
    x: wp.array(dtype=wp.vec3),
    edges: wp.array2d(dtype=wp.int32),
    rest: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    sigma_min: float,
    sigma_max: float,
    offset: int,
    lo_target: float,
    hi_target: float,
    omega: float,
):
    """One colour of Gauss-Seidel strain limiting: edges ``offset + tid`` share no vertex.

    An edge outside ``[sigma_min, sigma_max]`` is projected to ``hi_target`` (above) or
    ``lo_target`` (below), scaled by ``omega``."""
    e = wp.tid() + offset
    i = edges[e, 0]
    j = edges[e, 1]
    wi = inv_mass[i]
    wj = inv_mass[j]
    if wi + wj <= 0.0:
        return
    L = rest[e]
    xi = x[i]
    xj = x[j]
    s = wp.length(xi - xj) / L
    if s > sigma_min and s < sigma_max:
        return
    s0 = hi_target
    if s <= sigma_min:
        s0 = lo_target
    g = omega * edge_projection(xi, xj, wi, wj, s0 * L)
    x[i] = xi + wi * g
    x[j] = xj - wj * g


@wp.kernel
def strain_check_kernel(
    x: wp.array(dtype=wp.vec3),
    edges: wp.array2d(dtype=wp.int32),
    rest: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    lo: float,
    hi: float,
    bad: wp.array(dtype=wp.int32),
    excess: wp.array(dtype=float),
):
    """Count the edges whose stretch ratio is outside ``[lo, hi]`` (the bounds widened by the
    tolerance) into ``bad[0]``; the largest excess (ratio units) into ``excess[0]``."""
    e = wp.tid()
    i = edges[e, 0]
    j = edges[e, 1]
    if inv_mass[i] + inv_mass[j] <= 0.0:
        return
    s = wp.length(x[i] - x[j]) / rest[e]
    if s > hi or s < lo:
        wp.atomic_add(bad, 0, 1)
        wp.atomic_max(excess, 0, wp.max(s - hi, lo - s))


@wp.kernel
def area_check_kernel(
    x: wp.array(dtype=wp.vec3),
    tris: wp.array2d(dtype=wp.int32),
    rest_area: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    lo: float,
    hi: float,
    bad: wp.array(dtype=wp.int32),
    excess: wp.array(dtype=float),
):
    """Count the triangles whose area ratio ``A / A0`` is outside ``[lo, hi]`` and can be
    corrected (at most one pinned vertex, not degenerate) into ``bad[0]``."""
    t = wp.tid()
    i = tris[t, 0]
    j = tris[t, 1]
    k = tris[t, 2]
    npin = int(0)
    if inv_mass[i] <= 0.0:
        npin += 1
    if inv_mass[j] <= 0.0:
        npin += 1
    if inv_mass[k] <= 0.0:
        npin += 1
    if npin > 1:
        return
    xi = x[i]
    area = 0.5 * wp.length(wp.cross(x[j] - xi, x[k] - xi))
    if area < 1.0e-20:
        return
    r = area / rest_area[t]
    if r > hi or r < lo:
        wp.atomic_add(bad, 0, 1)
        wp.atomic_max(excess, 0, wp.max(r - hi, lo - r))


#: slots of a limit's int32 counters (device)
(C_SWEEPS, C_COND, C_SWEEPS_TOTAL, C_SHORT_TOTAL, C_STEPS_TOTAL, C_SWEEPS_MAX, C_BAD,
 C_WINDOW, C_STALLED_TOTAL, C_STALLED) = range(10)

#: a pass whose worst excess at the end of a window of ``STALL_SWEEPS`` sweeps is not below
#: ``1 - STALL_GAIN`` of its excess at the end of the window before stops there (a stalled
#: step: counted, reported); the first window is never a stall. Bounds that pins or contact
#: make unreachable keep the excess exactly where it is: a 10 x 10 sheet whose pinned corner
#: a rising floor passed, under PBD (whose default 1.08 limit is a StrainLimit), ran 2,000
#: sweeps in every step at 6.2e-2 and 7.2e-2 (95 s a frame, a run that looked hung); it now
#: stops after two windows.
#: Passes that converge can first raise the worst excess and then lower it slowly: PBD's
#: stretch guard on the stability map's 8 x 8 sheet at k = 10 N/m with 10,000:1 masses rose
#: from 0.029 to 0.035 in its first sweeps, then fell by 3-4 % every 45 sweeps (the rule before
#: compared each window's least excess with the least before it, the check before any sweep
#: included, 90 sweeps, 5 %: it stopped those passes at their first window, and the cells
#: gained energy, 44-122 % strain; the least of each window against the window before's still
#: stopped them, 0.035 against the first check's 0.029)
STALL_SWEEPS = 45
STALL_GAIN = 0.001
#: `limit_loop_kernel`: no window ended yet
_NO_EXCESS = wp.constant(1.0e30)


@wp.kernel
def limit_loop_kernel(counts: wp.array(dtype=wp.int32), excess: wp.array(dtype=float),
                      cap: int, begin: int, sweeps: int, window: int, gain: float):
    """Loop control of an adaptive limit, after each check: go on (``counts[C_COND] = 1``) while
    elements are outside the tolerance, fewer than ``cap`` sweeps ran and the pass has not
    stalled; at the end of a step that stops short, count it (``C_SHORT_TOTAL``, and
    ``C_STALLED_TOTAL`` when it stalled) and keep its excess (``excess[1]`` the largest over
    the run, ``excess[2]`` the last). ``begin``: the check before any sweep; ``sweeps``: the
    sweeps between two checks (the loop goes on only while another group of them stays within
    ``cap``). Stalled (`STALL_SWEEPS`): a window of ``window`` sweeps that ends with an excess
    not below ``1 - gain`` of the one the window before ended with (``excess[3]``; none for the
    first window)."""
    stalled = int(0)
    if begin != 0:
        counts[C_SWEEPS] = 0
        counts[C_WINDOW] = 0
        counts[C_STALLED] = 0
        counts[C_STEPS_TOTAL] = counts[C_STEPS_TOTAL] + 1
        excess[3] = _NO_EXCESS
    else:
        counts[C_SWEEPS] = counts[C_SWEEPS] + sweeps
        counts[C_SWEEPS_TOTAL] = counts[C_SWEEPS_TOTAL] + sweeps
        counts[C_WINDOW] = counts[C_WINDOW] + sweeps
        if counts[C_WINDOW] >= window:
            if excess[3] < _NO_EXCESS and excess[0] > (1.0 - gain) * excess[3]:
                stalled = 1
            excess[3] = excess[0]
            counts[C_WINDOW] = 0
    k = counts[C_SWEEPS]
    bad = counts[C_BAD]
    counts[C_BAD] = 0
    if bad > 0 and k + sweeps <= cap and stalled == 0:
        counts[C_COND] = 1
    else:
        counts[C_COND] = 0
        counts[C_SWEEPS_MAX] = wp.max(counts[C_SWEEPS_MAX], k)
        if bad > 0:
            counts[C_SHORT_TOTAL] = counts[C_SHORT_TOTAL] + 1
            counts[C_STALLED_TOTAL] = counts[C_STALLED_TOTAL] + stalled
            counts[C_STALLED] = stalled
            excess[1] = wp.max(excess[1], excess[0])
            excess[2] = excess[0]
    excess[0] = 0.0


@wp.kernel
def limit_moved_kernel(counts: wp.array(dtype=wp.int32), flag: wp.array(dtype=wp.int32)):
    """``flag[0] = 1`` when the last pass ran a sweep (`_JacobiLimit.moved_into`)."""
    if counts[C_SWEEPS] > 0:
        flag[0] = 1


@wp.kernel
def limit_stalled_kernel(counts: wp.array(dtype=wp.int32), flag: wp.array(dtype=wp.int32)):
    """``flag[0] = 1`` when the last pass stalled (`_JacobiLimit.stalled_into`)."""
    if counts[C_STALLED] != 0:
        flag[0] = 1


@wp.kernel
def limit_velocity_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    x_before: wp.array(dtype=wp.vec3),
    inv_dt: float,
):
    """``v += (x - x_before) / dt`` after in-place (Gauss-Seidel) corrections."""
    i = wp.tid()
    v[i] = v[i] + (x[i] - x_before[i]) * inv_dt


@wp.kernel
def area_limit_kernel(
    x: wp.array(dtype=wp.vec3),
    tris: wp.array2d(dtype=wp.int32),
    rest_area: wp.array(dtype=float),
    mass: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    a_min: float,
    a_max: float,
    delta: wp.array(dtype=wp.vec3),
    count: wp.array(dtype=float),
):
    t = wp.tid()
    i = tris[t, 0]
    j = tris[t, 1]
    k = tris[t, 2]
    xi = x[i]
    xj = x[j]
    xk = x[k]
    area = 0.5 * wp.length(wp.cross(xj - xi, xk - xi))
    A0 = rest_area[t]
    lo = a_min * A0
    hi = a_max * A0
    if area > lo and area < hi:
        return
    if area < 1.0e-20:
        return  # degenerate: no direction to scale along
    # mass-weighted centroid; a pinned vertex has infinite mass
    npin = int(0)
    c = wp.vec3(0.0)
    if inv_mass[i] <= 0.0:
        npin += 1
        c = xi
    if inv_mass[j] <= 0.0:
        npin += 1
        c = xj
    if inv_mass[k] <= 0.0:
        npin += 1
        c = xk
    if npin > 1:
        return
    if npin == 0:
        mi = mass[i]
        mj = mass[j]
        mk = mass[k]
        c = (mi * xi + mj * xj + mk * xk) / (mi + mj + mk)
    s = wp.sqrt(wp.min(wp.max(area, lo), hi) / area) - 1.0
    wp.atomic_add(delta, i, s * (xi - c))
    wp.atomic_add(delta, j, s * (xj - c))
    wp.atomic_add(delta, k, s * (xk - c))
    wp.atomic_add(count, i, 1.0)
    wp.atomic_add(count, j, 1.0)
    wp.atomic_add(count, k, 1.0)


@wp.kernel
def limit_apply_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    delta: wp.array(dtype=wp.vec3),
    count: wp.array(dtype=float),
    alpha: float,
    inv_dt: float,
    inelastic: int,
):
    """Jacobi blend of the active elements' corrections; ``v += dx / dt`` (``inelastic``: the
    vertex loses the part of its velocity that opposed ``dx`` and gains nothing, `AreaLimit`);
    clear accumulators."""
    i = wp.tid()
    c = count[i]
    if c > 0.0:
        dx = delta[i] / (c + alpha)
        x[i] = x[i] + dx
        if inelastic == 0:
            v[i] = v[i] + dx * inv_dt
        else:
            v[i] = inelastic_velocity(v[i], dx, wp.vec3(0.0))
    delta[i] = wp.vec3(0.0)
    count[i] = 0.0


@wp.kernel
def _greedy_color_kernel(pairs: wp.array2d(dtype=wp.int32), used: wp.array(dtype=wp.int64),
                         colors: wp.array(dtype=wp.int64), overflow: wp.array(dtype=wp.int32)):
    """`color_constraints`' loop, compiled: one thread walks the constraints in order."""
    for c in range(pairs.shape[0]):
        i = pairs[c, 0]
        j = pairs[c, 1]
        m = used[i] | used[j]
        k = int(0)
        while k < 63 and ((m >> wp.int64(k)) & wp.int64(1)) != wp.int64(0):
            k += 1
        if k >= 63:
            overflow[0] = 1
            return
        colors[c] = wp.int64(k)
        bit = wp.int64(1) << wp.int64(k)
        used[i] = used[i] | bit
        used[j] = used[j] | bit


def color_constraints(pairs: np.ndarray, num_vertices: int) -> np.ndarray:
    """Greedy colouring: ``colors[c]`` is the smallest colour used by neither vertex of ``c``.

    Within a colour no two constraints share a vertex, so a colour can be projected in parallel
    and gives the same result as projecting its constraints one after another (Gauss-Seidel).
    Runs once at set-up on the host: the constraints in order, as one compiled single-thread
    kernel on Warp's CPU device (linear time; 262k vertices' springs in milliseconds), or, when
    a vertex would need more than 63 colours (a 64-bit mask), the same loop in Python.
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if len(pairs) and num_vertices < 2**31:
        colors = wp.zeros(len(pairs), dtype=wp.int64, device="cpu")
        overflow = wp.zeros(1, dtype=wp.int32, device="cpu")
        launch(_greedy_color_kernel, 1,
               [wp.array(pairs.astype(np.int32), dtype=wp.int32, ndim=2, device="cpu"),
                wp.zeros(num_vertices, dtype=wp.int64, device="cpu"), colors, overflow],
               device="cpu")
        if not overflow.numpy()[0]:
            return colors.numpy().astype(np.int64)
    return _color_constraints_python(pairs, num_vertices)


def _color_constraints_python(pairs: np.ndarray, num_vertices: int) -> np.ndarray:
    """The reference loop of `color_constraints` (any number of colours)."""
    used = [0] * num_vertices  # bit mask of the colours at each vertex
    colors = np.empty(len(pairs), dtype=np.int64)
    for c, (i, j) in enumerate(np.asarray(pairs).tolist()):
        m = used[i] | used[j]
        k = (~m & (m + 1)).bit_length() - 1  # lowest zero bit
        colors[c] = k
        used[i] |= 1 << k
        used[j] |= 1 << k
    return colors


def _check_iterations(name, iterations) -> int:
    if isinstance(iterations, bool) or int(iterations) != iterations or iterations < 1:
        raise ValueError(f"{name}: iterations must be a positive integer, got {iterations!r}")
    return int(iterations)


def _check_relaxation(name, relaxation) -> float:
    a = float(relaxation)
    if not (math.isfinite(a) and a >= 0.0):
        raise ValueError(f"{name}: relaxation must be a finite number >= 0, got {relaxation!r}")
    return a


def _check_tolerance(name, tolerance):
    return None if tolerance is None else positive_finite(tolerance, f"{name}: tolerance")


def _check_bounds(name, lo, hi, lo_name, hi_name) -> tuple[float, float]:
    not_text_or_bool(lo, f"{name}: {lo_name}")
    not_text_or_bool(hi, f"{name}: {hi_name}")
    try:
        lo, hi = float(lo), float(hi)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: {lo_name} and {hi_name} must be numbers, got {lo!r}, {hi!r}") from None
    if not (math.isfinite(lo) and lo >= 0.0):
        raise ValueError(f"{name}: {lo_name} must be a finite number >= 0, got {lo}")
    if math.isnan(hi) or hi < lo:
        raise ValueError(f"{name}: need {lo_name} <= {hi_name}, got {lo_name}={lo}, {hi_name}={hi}")
    if hi <= 0.0:
        raise ValueError(f"{name}: {hi_name} must be > 0 (a zero-size element), got {hi}")
    if not (lo <= 1.0 <= hi):
        # the rest shape outside its own bounds: the limit then forces every element off its
        # rest size each step against its springs (StrainLimit(model, 0, 0.5) under explicit
        # Euler: 1.47 -> 1,133 J in two frames)
        raise ValueError(f"{name}: the rest size (1) must lie within [{lo_name}, {hi_name}], got "
                         f"[{lo}, {hi}]")
    return lo, hi


class _JacobiLimit:
    """Shared driver: accumulators and counters allocated once.

    With a ``tolerance`` a pass is adaptive: a check before the first sweep and after every
    ``check_every`` sweeps counts the elements still outside the bounds widened by the
    tolerance, and a device-side loop (`warp.capture_while`: a conditional loop in a recorded
    graph, no host read) sweeps again while any is and another ``check_every`` sweeps stay
    within ``iterations`` (so a pass runs a multiple of ``min(check_every, iterations)`` sweeps,
    at most ``iterations``; a sweep moves only elements outside their bounds, so the sweeps
    after convergence change little). A step that stops at the cap
    with elements still outside is counted (``stats["short_steps"]``) and reported by
    `frame_end` (the scene runner prints it as a warning with the frame). Outside a recorded
    graph the loop condition is read on the host after each sweep (one int on the CPU; a
    device sync on CUDA). ``tolerance=None`` runs exactly ``iterations`` sweeps and checks
    nothing."""

    capturable = True

    #: the blend's velocity rule (`limit_apply_kernel`): False, ``v += dx / dt``
    inelastic = False

    def __init__(self, model, iterations, relaxation, tolerance=None, check_every=1):
        from .util import check_model

        self.model = check_model(model, type(self).__name__)
        self.device = model.device
        name = type(self).__name__
        self.iterations = _check_iterations(name, iterations)
        self.relaxation = _check_relaxation(name, relaxation)
        self.tolerance = _check_tolerance(name, tolerance)
        if (isinstance(check_every, bool) or not isinstance(check_every, (int, np.integer))
                or check_every < 1):
            raise ValueError(f"{name}: check_every must be an integer >= 1, got {check_every!r}")
        self.check_every = int(check_every)
        self._group = min(self.check_every, self.iterations)  # sweeps between two checks
        n = model.num_vertices
        self._delta = wp.zeros(n, dtype=wp.vec3, device=self.device)
        self._count = wp.zeros(n, dtype=float, device=self.device)
        self._counts = wp.zeros(C_STALLED + 1, dtype=wp.int32, device=self.device)
        self._bad = self._counts[C_BAD:C_BAD + 1]
        self._cond = self._counts[C_COND:C_COND + 1]
        # [this check, largest short, last short, excess at the last window's end]
        self._excess = wp.zeros(4, dtype=float, device=self.device)
        self._short_seen = 0
        self._stalled_seen = 0
        self._contact = None

    @property
    def is_noop(self) -> bool:  # pragma: no cover - overridden
        return False

    def apply(self, state, x_start=None, dt: float = 1.0):
        """Correct ``state.x`` in place and add ``dx / dt`` to ``state.v``.

        ``x_start`` (the positions at the start of the step) is accepted for the correction
        interface and not used. A pass whose bounds cannot be violated launches nothing.
        """
        if self.is_noop or self._num_elements() == 0:
            return
        dt = float(dt)
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be a positive finite number of seconds, got {dt}")
        self._begin(state)
        if self.tolerance is None:
            for _ in range(self.iterations):
                self._sweep(state, dt)
        else:
            self._check(state.x)
            launch(limit_loop_kernel, 1, [self._counts, self._excess, self.iterations, 1,
                                          self._group, STALL_SWEEPS, STALL_GAIN],
                   device=self.device)
            wp.capture_while(self._cond, self._adaptive_sweep, state=state, dt=dt)
        self._finish(state, dt)

    def moved_into(self, flag) -> None:
        """``flag[0] = 1`` if the last pass (`apply`, `after_contact`) ran any sweep, i.e.
        moved vertices (device-side: capturable)."""
        launch(limit_moved_kernel, 1, [self._counts, flag], device=self.device)

    def stalled_into(self, flag) -> None:
        """``flag[0] = 1`` if the last pass stopped stalled (`STALL_SWEEPS`; device-side)."""
        launch(limit_stalled_kernel, 1, [self._counts, flag], device=self.device)

    def after_contact(self, state, x_start, dt: float, stage) -> bool:
        """Run after the collision stage's response (`Solver.step`): friction's tangential
        correction holds vertices where they touch and can stretch the edges beside them
        (measured 2.5 % under a 1 % limit on Newton's cloth_hanging scene). With a tolerance,
        this pass checks the bounds and, only where one is broken, sweeps again with the
        stage's contact projection (`CollisionStage.project_positions`: positions only, the
        exact test of every vertex) after each sweep, so the pass ends with both the bounds
        and non-penetration. Velocities get ``dx / dt`` as in `apply`. Returns whether the
        pass ran (`moved_into` then tells on the device whether it moved anything: the solver
        runs the self-collision response again after it, since the sweeps do not see the
        cloth's other layers)."""
        if self.tolerance is None or self.is_noop or self._num_elements() == 0:
            return False
        self._contact = (stage, x_start)
        try:
            self.apply(state, x_start, dt)
        finally:
            self._contact = None
        return True

    def _adaptive_sweep(self, state, dt):
        k = self._group
        self._group_begin(state)
        for _ in range(k):
            self._sweep(state, dt, True)
            if self._contact is not None:
                stage, x_start = self._contact
                # with the self-contacts a position-based solver's iterations projected this
                # step (`CollisionStage.iter_live`)
                live = getattr(stage, "iter_live", False)
                stage.project_positions(state.x, x_start, dt, state.time, self_contacts=live)
                if not live and hasattr(stage, "project_self_response"):
                    # the last self-collision response's contacts (none without it)
                    stage.project_self_response(state.x, x_start)
        self._check(state.x)
        launch(limit_loop_kernel, 1, [self._counts, self._excess, self.iterations, 0, k,
                                      STALL_SWEEPS, STALL_GAIN], device=self.device)

    def _begin(self, state):
        pass

    def _group_begin(self, state):
        pass

    def _finish(self, state, dt):
        pass

    def _sweep(self, state, dt, grouped=False):
        """One Jacobi iteration: every element's correction, then the blend (and ``v``)."""
        self._launch_elements(state.x)
        launch(limit_apply_kernel, self.model.num_vertices,
               [state.x, state.v, self._delta, self._count, self.relaxation, 1.0 / dt,
                int(self.inelastic)],
               device=self.device)

    # ---------------------------------------------------------------- reporting
    @property
    def stats(self) -> dict:
        """Totals since the limit was made (host reads): ``steps`` (adaptive passes),
        ``sweeps_total``, ``sweeps_max`` (most sweeps in one pass), ``short_steps`` (passes
        that stopped with elements still outside the tolerance: at ``iterations`` sweeps, or
        stalled), ``stalled_steps`` (those of them that stopped because `STALL_SWEEPS` sweeps
        had not lowered the worst excess by `STALL_GAIN`: bounds the pins or the contacts do
        not let it reach) and ``worst_excess`` (the largest remaining excess of such a pass,
        in ratio units)."""
        c, e = self._counts.numpy(), self._excess.numpy()
        return {"steps": int(c[C_STEPS_TOTAL]), "sweeps_total": int(c[C_SWEEPS_TOTAL]),
                "sweeps_max": int(c[C_SWEEPS_MAX]), "short_steps": int(c[C_SHORT_TOTAL]),
                "stalled_steps": int(c[C_STALLED_TOTAL]), "worst_excess": float(e[1])}

    def frame_end(self) -> list:
        """Messages for the steps that stopped short since the last call (one host read; the
        scene runner calls it after every frame and prints each as a warning)."""
        if self.tolerance is None:
            return []
        c = self._counts.numpy()
        short, stalled = int(c[C_SHORT_TOTAL]), int(c[C_STALLED_TOTAL])
        new, self._short_seen = short - self._short_seen, short
        new_stalled, self._stalled_seen = stalled - self._stalled_seen, stalled
        if new <= 0:
            return []
        last = float(self._excess.numpy()[2])
        out = []
        if new > new_stalled:
            ran = self.iterations - self.iterations % self._group
            out.append(f"{self!r} stopped short of its tolerance in {new - new_stalled} "
                       f"step(s): after {ran} sweeps elements were still up to {last:.3g} "
                       f"outside the bounds (ratio units); raise iterations or use more "
                       f"substeps")
        if new_stalled:
            out.append(f"{self!r} stalled in {new_stalled} step(s): {STALL_SWEEPS} sweeps did "
                       f"not lower its worst excess (last {last:.3g} outside the bounds, ratio "
                       f"units); the pins or the contacts keep elements out of the bounds "
                       f"(a pinned vertex an obstacle passed, a cloth pinched or pulled apart)")
        return out

class StrainLimit(_JacobiLimit):
    """Edge strain limiting to ``sigma_min <= |x_i - x_j| / L <= sigma_max`` (notes L1386-1408).

    Args:
        model: the `ClothModel`; the limit acts on its mesh edges (the stretch springs).
        sigma_min: smallest allowed stretch ratio, >= 0 (0: no compression limit).
        sigma_max: largest allowed stretch ratio, >= sigma_min; may be ``inf`` (no limit).
        tolerance: the guarantee, in stretch-ratio units (default 1e-3: 0.1 % of the rest
            length). Sweeps repeat, on the device, until every edge is inside
            ``[sigma_min - tolerance, sigma_max + tolerance]`` or ``iterations`` sweeps ran;
            a step that stops short is counted (``stats``) and reported (`frame_end`).
            ``None``: exactly ``iterations`` sweeps, no check (the old fixed-count pass).
        iterations: the most sweeps per application (default 2000; with a tolerance, a step
            whose edges are inside runs none, and most need a few: measured on the soft 12 x 12
            test sheet landing on a floor under implicit Euler, 21 sweeps a step on average and
            278 at the impact; the default hanging scene under PD needs up to about 1,150 in
            its seventh frame, when the former cap of 500 left it at 1.4 % under a 1 % limit).
        relaxation: the Jacobi blend's ``alpha`` >= 0 (default 0: plain averaging over the active
            edges at a vertex); unused by Gauss-Seidel.
        gauss_seidel: project the edges colour by colour in place (greedy colouring at set-up,
            one launch per colour; default True) instead of the Jacobi blend, which converges
            several times slower on long chains of violated edges (see the module docstring).
        tethers: with Gauss-Seidel and pins, each free vertex is also kept within
            ``sigma_max`` times its rest geodesic distance of its ``tethers`` nearest pins
            (long-range attachments, Kim, Chentanez and Müller 2012; one per-vertex launch before
            every ``check_every`` sweeps, and before every sweep without a tolerance; default 2,
            0 for none; once per pass instead took twice the sweeps under PD below, once per
            3 sweeps 9 % more than before every sweep, for a launch that costs about what the
            edge sweep costs). The geodesic is the straight rest distance when the
            rest mesh is flat and convex (every built-in scene), else the shortest path along
            edges (longer, so looser). Measured on the default hanging scene under PD (40
            frames): 5,742 sweeps and 4 short steps with tethers, 16,611 and 18 without.
        over_relaxation: ``omega`` in [1, 2) of Gauss-Seidel (successive over-relaxation): a
            violated edge is moved ``omega`` times its projection, past its bound into the
            allowed range (default 1.8: measured on Newton's cloth_hanging scene with the
            explicit solver, 9,252 sweeps in 60 frames against 19,560 with 1.0, the same
            energy; `warp-cloth bench limits`).
        check_every: sweeps between two checks of the tolerance (default 3). A check costs
            about what a sweep costs (one pass over the edges); on Newton's cloth_hanging scene
            with the explicit solver, 3 ran the same sweeps (about 150 a frame) with a third
            of the checks, and with the tethers once per 3 sweeps 35 -> 22 ms a frame
            (`warp-cloth bench limits`); under PD on the default hanging scene (40 frames),
            5,742 sweeps against 5,156 checking and tethering at every sweep, 4 short steps
            either way.

    ``sigma_min = sigma_max = 1`` with ``tolerance=None``, ``tethers=0`` and
    ``over_relaxation=1`` is exactly (bit for bit, on the CPU) a plain-PBD stretch pass with the
    same iterations, relaxation and mode (`PositionBased` with ``over_relaxation=1``, the notes'
    blend); ``[0, inf]`` launches
    nothing.
    """

    name = "strain-limit"

    def __init__(self, model, sigma_min: float = 0.0, sigma_max: float = math.inf, *,
                 tolerance: float | None = 1e-3, iterations: int = 2000, relaxation: float = 0.0,
                 gauss_seidel: bool = True, tethers: int = 2, over_relaxation: float = 1.8,
                 check_every: int = 3):
        self.sigma_min, self.sigma_max = _check_bounds("StrainLimit", sigma_min, sigma_max,
                                                       "sigma_min", "sigma_max")
        super().__init__(model, iterations, relaxation, tolerance, check_every)
        self.gauss_seidel = bool(gauss_seidel)
        if isinstance(tethers, bool) or int(tethers) != tethers or tethers < 0:
            raise ValueError(f"StrainLimit: tethers must be an integer >= 0, got {tethers!r}")
        self.tethers = int(tethers)
        w = float(over_relaxation)
        if not (1.0 <= w < 2.0):
            raise ValueError(f"StrainLimit: over_relaxation must be in [1, 2), got {over_relaxation!r}")
        self.over_relaxation = w
        # the mesh edges are the first num_stretch_springs springs of the model
        ne = model.num_stretch_springs
        self.num_edges = ne
        self._edges = model.spring_indices[:ne] if ne else None
        self._rest = model.spring_rest_length[:ne] if ne else None
        if self.gauss_seidel and ne:
            pairs = model.spring_pairs[:ne]
            colors = color_constraints(pairs, model.num_vertices)
            order = np.argsort(colors, kind="stable")
            self.color_offsets = np.searchsorted(colors[order], np.arange(colors.max() + 2)).tolist()
            d = self.device
            self._edges = wp.array(pairs[order].astype(np.int32), dtype=wp.int32, ndim=2, device=d)
            self._rest = wp.array(model.spring_rest[:ne][order].astype(np.float32), dtype=float,
                                  device=d)
            self._x_before = wp.zeros(model.num_vertices, dtype=wp.vec3, device=d)
        self._targets = (self.sigma_min, min(self.sigma_max, 3.0e38), self.over_relaxation)
        self._tether = None
        if (self.tethers and ne and len(model.pins)
                and math.isfinite(self.sigma_max) and self.gauss_seidel):
            anc, dist = model_tether_anchors(model, self.tethers)
            if (anc >= 0).any():
                # sigma_max times the rest geodesic (exact on a planar rest mesh, the
                # fast-marching estimate elsewhere): a tether the edge limits already imply
                d = self.device
                rest = np.where(anc >= 0, self.sigma_max * dist, 0.0)
                self._pin_stretch = PinStretch(model)
                self._tether = (wp.array(anc.astype(np.int32), dtype=wp.int32, ndim=2, device=d),
                                wp.array(rest.astype(np.float32), dtype=float, ndim=2, device=d),
                                self._pin_stretch.scale)

    @property
    def is_noop(self) -> bool:
        return self.sigma_min == 0.0 and self.sigma_max == math.inf

    def _num_elements(self):
        return self.num_edges

    def _begin(self, state):
        if self.gauss_seidel:
            wp.copy(self._x_before, state.x)
        if self._tether is not None:
            self._pin_stretch.update(state.x)

    def _finish(self, state, dt):
        if self.gauss_seidel:
            launch(limit_velocity_kernel, self.model.num_vertices,
                   [state.x, state.v, self._x_before, 1.0 / dt], device=self.device)

    def _group_begin(self, state):
        if self._tether is not None:
            launch(tether_kernel, self.model.num_vertices, [state.x, *self._tether],
                   device=self.device)

    def _sweep(self, state, dt, grouped=False):
        if not self.gauss_seidel:
            return super()._sweep(state, dt)
        m, offs = self.model, self.color_offsets
        if self._tether is not None and not grouped:
            launch(tether_kernel, m.num_vertices, [state.x, *self._tether], device=self.device)
        for c in range(len(offs) - 1):
            launch(strain_limit_gs_kernel, offs[c + 1] - offs[c],
                   [state.x, self._edges, self._rest, m.inv_mass, self.sigma_min,
                    min(self.sigma_max, 3.0e38), offs[c], *self._targets], device=self.device)

    def _check(self, x):
        t = self.tolerance
        launch(strain_check_kernel, self.num_edges,
               [x, self._edges, self._rest, self.model.inv_mass, self.sigma_min - t,
                min(self.sigma_max + t, 3.0e38), self._bad, self._excess], device=self.device)

    def _launch_elements(self, x):
        m = self.model
        launch(strain_limit_kernel, self.num_edges,
               [x, self._edges, self._rest, m.inv_mass, self.sigma_min,
                min(self.sigma_max, 3.0e38), self._delta, self._count],
               device=self.device)

    def __repr__(self):
        tol = "None" if self.tolerance is None else f"{self.tolerance:g}"
        return (f"StrainLimit([{self.sigma_min:g}, {self.sigma_max:g}], tolerance={tol}, "
                f"iterations={self.iterations}, relaxation={self.relaxation:g}, "
                f"gauss_seidel={self.gauss_seidel}, tethers={self.tethers}, "
                f"over_relaxation={self.over_relaxation:g}, check_every={self.check_every})")


class AreaLimit(_JacobiLimit):
    """Triangle area limiting to ``[a_min A0, a_max A0]`` (notes L1410-1429).

    Each violating triangle is scaled about its mass-weighted centroid by
    ``s = sqrt(clamp(A) / A)``, which is the least (mass-weighted) movement that reaches the
    clamped area and does not translate the triangle (L1425).

    Args:
        model: the `ClothModel`.
        a_min: smallest allowed area as a fraction of the rest area, >= 0.
        a_max: largest allowed fraction, >= a_min; may be ``inf``.
        tolerance: the guarantee in area-ratio units (default 1e-3): Jacobi iterations repeat
            on the device until every triangle that can be corrected (at most one pinned
            vertex) has ``A / A0`` inside ``[a_min - tolerance, a_max + tolerance]`` or
            ``iterations`` ran; short steps are counted and reported as for `StrainLimit`.
            ``None``: exactly ``iterations``, no check.
        iterations: the most Jacobi iterations per application (default 200).
        relaxation: the Jacobi blend's ``alpha`` >= 0 (default 0).
        check_every: Jacobi iterations between two checks of the tolerance (default 1).
    """

    name = "area-limit"
    #: a corrected vertex loses the part of its velocity that opposed the correction and gains
    #: nothing (`limit_apply_kernel`), instead of ``v += dx / dt``. Scaling a triangle about
    #: its centroid also moves the edges the springs did not stretch; with ``v += dx / dt``
    #: the next explicit step carried each vertex past its limit again, an undamped
    #: oscillation of the step's own period whose energy grows as ``1 / dt^2``: explicit Euler's
    #: hanging sheet under ``AreaLimit(model, 0, 1.01)`` went from 1.47 to 27.6 J in 120 frames
    #: (55 J at twice the substeps, 98 J at four times) and diverged on the drape; now 0.80 J,
    #: 1.46 % max strain. The edge limits keep ``v += dx / dt`` (no such oscillation measured)
    inelastic = True

    def __init__(self, model, a_min: float = 0.0, a_max: float = math.inf, *,
                 tolerance: float | None = 1e-3, iterations: int = 200, relaxation: float = 0.0,
                 check_every: int = 1):
        self.a_min, self.a_max = _check_bounds("AreaLimit", a_min, a_max, "a_min", "a_max")
        super().__init__(model, iterations, relaxation, tolerance, check_every)
        areas = model.mesh.triangle_areas()
        self._rest_area = wp.array(areas.astype(np.float32), dtype=float, device=self.device)

    @property
    def is_noop(self) -> bool:
        return self.a_min == 0.0 and self.a_max == math.inf

    def _num_elements(self):
        return self.model.num_triangles

    def _check(self, x):
        t = self.tolerance
        launch(area_check_kernel, self.model.num_triangles,
               [x, self.model.tri_indices, self._rest_area, self.model.inv_mass,
                self.a_min - t, min(self.a_max + t, 3.0e38), self._bad, self._excess],
               device=self.device)

    def _launch_elements(self, x):
        m = self.model
        launch(area_limit_kernel, m.num_triangles,
               [x, m.tri_indices, self._rest_area, m.mass, m.inv_mass, self.a_min,
                min(self.a_max, 3.0e38), self._delta, self._count],
               device=self.device)

    def __repr__(self):
        tol = "None" if self.tolerance is None else f"{self.tolerance:g}"
        return (f"AreaLimit([{self.a_min:g}, {self.a_max:g}], tolerance={tol}, "
                f"iterations={self.iterations}, relaxation={self.relaxation:g}, "
                f"check_every={self.check_every})")
