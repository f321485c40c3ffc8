"""`ObstacleContact`: the per-vertex obstacle contact correction (position projection, continuous
path test, impulse with restitution and Coulomb friction), usable by every solver.

    contact = ObstacleContact(model, [Sphere(0.3, (0, 0.5, 0)), Plane()],
                              thickness=0.005, restitution=0.0, friction=0.4)
    solver.add_correction(contact)

What one call does, per vertex (one thread each; pinned vertices are skipped), per obstacle, in
the obstacle's frame so that its scripted motion is part of the relative path:

1. **Continuous test** of the vertex's path from ``x_start`` (start of the step, obstacle pose at
   ``t``) to ``x`` (end, pose at ``t + dt``): sphere (the notes' quadratic) and box (slab test)
   against the shape inflated by the thickness, triangle meshes by a BVH ray query. A path that
   enters is stopped on the tangent plane at its entry point: no tunnelling through thin meshes
   or small shapes, at any speed. (A plane is a half-space: a crossing always ends inside it.)
2. **Projection**: an end position closer than ``thickness`` to the surface (or inside) is moved
   along the normal to distance ``thickness``.
3. **Impulse** (``apply`` only) relative to the obstacle's surface velocity, with restitution
   ``mu_N`` and Coulomb friction ``mu_T``, static and sliding (`warp_cloth.collision.response`);
   the same friction factor scales the tangential displacement, so positions agree with
   velocities. A vertex within ``thickness + slack`` of the surface that approaches it counts as
   touching.

Penetration tolerance: after ``apply`` every unpinned vertex is at signed distance
``>= thickness - PENETRATION_TOLERANCE`` from each obstacle it touches (float32 rounding; vertices
resting on a surface sit at ``thickness``). Only vertices are tested: a cloth edge or triangle
can still cut a sharp obstacle corner between vertices, and two overlapping obstacles can push a
vertex into each other (the last one wins).

**How contact enters each solver** (through the solver's `CollisionStage`, which owns this
object):

- every solver: `apply(state, x_start, dt)` ends the step (`CollisionStage.resolve`, after the
  limits): it projects positions and applies the impulse to the velocities, so the state leaves
  the step consistent (``v . N >= 0`` relative to the obstacle).
- implicit (Newton) and projective dynamics: before their solve, `detect` gives every vertex
  whose predicted path comes near an obstacle a contact plane in the stage's record, which they
  take into the solve (`warp_cloth.solvers.contact_coupling`).
- explicit (symplectic Euler): `integrate_and_apply` runs the solver's vertex update and `apply`
  with the far tests in one pass.
- position-based: before its iterations the solver calls `begin_iterations`, which gives each
  vertex the last `apply` found near an obstacle a contact plane per obstacle (exact geometry and
  continuous test at the predicted position; `warp_cloth.collision.planes`, as in Müller et al.
  2007, section 3.5), and `project_positions(x, x_start, dt)` inside each iteration projects
  onto those planes: non-penetration as a constraint among the others, plus position-level
  Coulomb friction (the tangential displacement relative to the obstacle is removed up to
  ``mu_T`` times the normal correction: static and sliding, the same threshold
  ``tan(angle) = mu_T`` on an incline). `apply` after its velocity update then tests the exact
  geometry of every vertex and adds restitution to vertices still approaching (and their
  friction impulse). Without `begin_iterations`, `project_positions` runs the exact test on
  every vertex. Pass ``time=state.time`` when possible; without it the contact uses its own
  clock, which `apply` advances (correct for steps run back to back from time 0).

No host decisions: ``capturable = True``. `apply` runs, per obstacle family (analytic, mesh), a
far pass over every vertex that appends the vertices within reach to a list, and a near pass
over the list (`NEAR_BATCH` list entries per thread); when any obstacle moves, one launch (a
thread per obstacle) first evaluates the poses at the start and end of the step from
``state.time``. The far tests use world-frame bounds per obstacle (`motion.ObstacleReach`):
squared lengths for static spheres, boxes and planes and for short paths near moving ones, and
for static meshes a per-vertex anchor ball that holds no surface. The kernels are made per
tuple of obstacle kinds (`analytic.far_kinds`, the meshes' motion flags), so each obstacle's
test is compiled in without branches on its kind. Static spheres and planes are handled in the
world frame; a mesh vertex in contact keeps its few nearby faces, or one plane
(`mesh_contact`, candidate cache), and such vertices are answered by a near pass of their own
before the general (BVH) one. Explicit Euler runs the far tests inside its own vertex update
(`integrate_and_apply`), and for static spheres and planes the whole contact. Nothing is
allocated per step.

**Cost** (``warp-cloth bench contact``: the 32x32 drape, each solver timed with and without the
contact from the same draped state; CPU, graph replay, medians; 2026-12-07). Implicit Euler and
projective dynamics, which take the contacts into their solve (`warp_cloth.solvers.
contact_coupling`): +11-14 % and +7-8 % (analytic), +16-17 % and +12 % (960-triangle mesh).
Position-based dynamics: +15-22 %, with the contact planes. Explicit Euler is the hard case: its
substep is ~37 us for 1,089 vertices (~34 ns a vertex, all forces included), so every per-vertex
test shows: one static sphere +18 % (the benchmark's floor row, a hand-written pass for that one
sphere with the same result, +17 %), mesh +44-50 %, spinning sphere +41-43 % (its near pass and
pose update every substep), sphere and plane +26 %: a second obstacle's far test alone costs
every vertex ~3 ns.
What Warp's CPU backend charges, measured: every variable of a kernel initialised for every
thread (hence separate far and near passes, and the mesh's general path in a kernel of its own:
its mere call site made the common case a fifth dearer), a struct passed by value copied at
every call (the far tests read the fields in place: a third of the far pass), each thread
starting from its own copy of the kernel's arguments (the mesh far pass takes three arrays, not
the cache struct), and ~50-100 ns per vertex in contact (dependent chains of square roots and
divisions).
Tried and not kept: the mesh's candidate path inside the integrator's kernel (no gain measured),
testing the mesh's bounding ball before the anchor ball (slower), out-of-line or forced-inline
near functions, batching vertices per thread in the far pass, a higher C++ optimisation level.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..util import launch, not_text_or_bool
from .motion import KIND_MESH, quat_rotate
from .obstacles import Obstacle, Sphere, cloth_chord, in_frame, sphere_contact_pad

__all__ = ["ObstacleContact", "PENETRATION_TOLERANCE", "DEFAULT_THICKNESS", "DEFAULT_FRICTION",
           "DEFAULT_RESTITUTION", "NEAR_BATCH"]

#: m; contact thickness: vertices rest this far from a surface
DEFAULT_THICKNESS = 0.005
#: Coulomb coefficient mu_T (cotton on wood or plastic: about 0.3-0.6)
DEFAULT_FRICTION = 0.4
#: normal restitution mu_N (cloth does not bounce)
DEFAULT_RESTITUTION = 0.0
#: m; after apply, signed distance >= thickness - PENETRATION_TOLERANCE
PENETRATION_TOLERANCE = 1.0e-4
#: vertices per thread of the near passes (their threads: ceil(N / NEAR_BATCH); on the CPU a
#: thread costs its set-up whether its list entries exist or not)
NEAR_BATCH = 32


def _num(name, value, lo=0.0, hi=math.inf, lo_open=False):
    not_text_or_bool(value, name)
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    ok = math.isfinite(value) and (value > lo if lo_open else value >= lo) and value <= hi
    if not ok:
        rng = f"({lo:g}, {hi:g}]" if lo_open else f"[{lo:g}, {hi:g}]"
        raise ValueError(f"{name} must be in {rng}, got {value}")
    return value


class ObstacleContact:
    """Contact of the cloth's vertices with rigid obstacles, as a solver correction.

    Args:
        model: the `ClothModel` (arrays live on ``model.device``).
        obstacles: `Plane`, `Sphere`, `Box`, `MeshObstacle` instances (at least one).
        thickness: m, > 0; vertices are kept this far from every surface (default 5 mm).
        restitution: mu_N in [0, 1]; 0 = no bounce, 1 = the normal relative speed is kept.
        friction: mu_T >= 0, Coulomb coefficient (static and sliding). Obstacles may override
            both with their own ``friction`` / ``restitution``.
        ccd: test each vertex's whole path in the step (default True). False tests end positions
            only (for comparison: fast vertices then tunnel through thin meshes).
        slack: m, >= 0; an approaching vertex this much beyond ``thickness`` still gets the
            impulse (default ``0.1 * thickness``), so a position-based solver that already
            projected it still gets restitution and friction.
        cache_margin: m, >= 0; mesh obstacles: how far beyond the reach a vertex's distance
            query looks, so that a vertex found farther away skips the queries of the next
            steps until it has moved that much (default 0.02; 0 disables the cache's benefit).
        candidate_radius: m, >= 0; mesh obstacles: a vertex in contact keeps the few faces
            near it and, while its path stays within this distance of where they were
            gathered, finds its closest point among them instead of querying the BVH (default
            ``0.5 * thickness``; 0 turns this cache off). Exact: see `mesh_contact`.
        fuse: let a solver that can (the explicit one) run the far tests inside its own vertex
            update (`integrate_and_apply`; obstacles of one family). Default True; the result
            is the same, False keeps contact a separate correction (for comparison).
    """

    capturable = True

    def __init__(self, model, obstacles, *, thickness: float = DEFAULT_THICKNESS,
                 restitution: float = DEFAULT_RESTITUTION, friction: float = DEFAULT_FRICTION,
                 ccd: bool = True, slack: float | None = None, cache_margin: float = 0.02,
                 candidate_radius: float | None = None, fuse: bool = True):
        from ..util import check_model, obstacle_list

        check_model(model, "ObstacleContact")
        obstacles = obstacle_list(obstacles, "ObstacleContact")
        if not obstacles:
            raise ValueError("ObstacleContact needs at least one obstacle")
        for k, ob in enumerate(obstacles):
            if not isinstance(ob, Obstacle):
                raise TypeError(f"obstacle {k} is a {type(ob).__name__}, not a Plane, Sphere, "
                                "Box or MeshObstacle")
        self.model = model
        self.device = model.device
        #: the obstacles as given, in the world frame (drawn in the USD output)
        self.world_obstacles = obstacles
        #: the same in the model's simulation frame (`ClothModel.origin`; the given objects
        #: themselves when that is the world frame): every computation uses these
        self.obstacles = in_frame(obstacles, getattr(model, "origin", None))
        obstacles = self.obstacles
        self.thickness = _num("thickness", thickness, 0.0, 1.0e6, lo_open=True)
        self.restitution = _num("restitution", restitution, 0.0, 1.0)
        self.friction = _num("friction", friction, 0.0)
        self.slack = 0.1 * self.thickness if slack is None else _num("slack", slack, 0.0)
        self.ccd = bool(ccd)
        self.cache_margin = _num("cache_margin", cache_margin, 0.0)
        self.fuse = bool(fuse)
        #: m; extra reach of the lists `begin_iterations` makes for position-based iterations
        self.iteration_margin = 0.5 * self.thickness
        self.candidate_radius = (0.5 * self.thickness if candidate_radius is None
                                 else _num("candidate_radius", candidate_radius, 0.0))
        d = self.device
        self.clock = wp.zeros(1, dtype=wp.float64, device=d)
        #: the vertex-update function of the solver whose step runs the far tests (see
        #: `integrate_and_apply`); the far and near kernels are made in the same module
        self._update = None

        # keyframes of all obstacles in shared arrays (a dummy key when none has a path)
        times, offs, rots, starts = [], [], [], []
        n = 0
        for ob in obstacles:
            starts.append(n)
            p = ob.motion.path
            if p is not None:
                times.append(p.times), offs.append(p.offsets), rots.append(p.rotations)
                n += len(p.times)
        if n == 0:
            times, offs, rots = [np.zeros(1)], [np.zeros((1, 3))], [np.array([[0, 0, 0, 1.0]])]
        self.key_times = wp.array(np.concatenate(times), dtype=wp.float64, device=d)
        self.key_offsets = wp.array(np.concatenate(offs), dtype=wp.vec3, device=d)
        self.key_rotations = wp.array(np.concatenate(rots), dtype=wp.quat, device=d)

        self.analytic = [ob for ob in obstacles if ob.kind != KIND_MESH]
        self.meshes = [ob for ob in obstacles if ob.kind == KIND_MESH]
        start_of = {id(ob): s for ob, s in zip(obstacles, starts)}
        from .motion import ObstacleData

        ordered = self.analytic + self.meshes  # pose k of `poses` belongs to ordered[k]
        # spheres whose curvature a cloth triangle between held vertices would cut into: their
        # radius padded for the vertex contact (`sphere_contact_pad`)
        #: m: the cloth's rest `cloth_chord` (also `FeatureContact`'s sphere criterion)
        self.chord = cloth_chord(model.mesh.vertices, model.mesh.triangles)
        #: m added to each obstacle's radius for the vertex contact (`ordered` order; spheres)
        self.pads = [sphere_contact_pad(ob, self.chord, self.thickness)
                     if isinstance(ob, Sphere) else 0.0 for ob in ordered]
        self._data = wp.array(
            [ob.device_data(start_of[id(ob)], self.friction, self.restitution, pad)
             for ob, pad in zip(ordered, self.pads)],
            dtype=ObstacleData, device=d)
        self.moving = any(ob.moving for ob in ordered)
        poses = []
        for ob in ordered:  # rest poses; moving obstacles get theirs every step
            c, q = ob.pose(0.0)
            tf = wp.transform(wp.vec3(*c), wp.quat(*q))
            ti = wp.transform_inverse(tf)
            up = wp.transform(wp.vec3(*quat_rotate(q, (0.0, 1.0, 0.0))), wp.quat_identity())
            poses += [tf, tf, ti, ti, up]
        self.poses = wp.array(poses, dtype=wp.transform, device=d)
        # far-test records (world frame, at the end of the step); the pose launch rewrites
        # those of moving obstacles every step, static ones keep these
        from .motion import FAST_NONE, FAST_PLANE, FAST_SPHERE, KIND_PLANE, KIND_SPHERE, ObstacleReach

        reaches = []
        for ob, data, pad in zip(ordered, self._data.numpy(), self.pads):
            c, q = ob.pose(0.0)
            r = ObstacleReach()
            r.origin = wp.vec3(*c)
            r.normal = wp.vec3(*quat_rotate(q, (0.0, 1.0, 0.0)))
            r.bound = float(ob._bound()) + pad
            r.plane = int(ob.kind == KIND_PLANE)
            r.sweep = 0.0
            r.turn = 0.0
            r.shrink = 1.0
            r.fresh = 1
            r.fast = FAST_NONE
            if not ob.moving:
                r.fast = {KIND_SPHERE: FAST_SPHERE, KIND_PLANE: FAST_PLANE}.get(ob.kind, FAST_NONE)
            r.friction = float(data["friction"])
            r.restitution = float(data["restitution"])
            reaches.append(r)
        self.reaches = wp.array(reaches, dtype=ObstacleReach, device=d)
        self._last_t1 = wp.array(np.full(len(ordered), np.nan), dtype=wp.float64, device=d)
        # 1 while no obstacle moved in the last posed step (`obstacle_poses_kernel`): a solver's
        # energy check may then compare the step's end with its start (device-side)
        self.still = wp.ones(1, dtype=int, device=d)
        # the frame in which the moving obstacles stand still once past their ramps
        # (`motion.steady_frame`, or None), and 1 while the last posed step ran in it
        from .motion import steady_frame

        self.frame = steady_frame(ordered, model.gravity)
        self.steady = wp.zeros(1, dtype=int, device=d)
        self._analytic_reach = self.reaches[: len(self.analytic)] if self.analytic else None
        self._mesh_reach = self.reaches[len(self.analytic):] if self.meshes else None
        self._analytic_data = self._data[: len(self.analytic)] if self.analytic else None
        n_v = model.num_vertices
        self._near_threads = max(1, -(-n_v // NEAR_BATCH))  # threads of the near passes
        self._lists = None  # (x, x_start, dt) of the lists `begin_iterations` made
        self._a_planes = self._m_planes = None  # made on the first begin_iterations
        if self.analytic:
            from .analytic import far_kinds

            self._far_kinds = far_kinds(self.analytic)
            self._a_count = wp.zeros(1, dtype=int, device=d)
            self._a_list = wp.zeros(n_v, dtype=int, device=d)
            self._ai_count = wp.zeros(1, dtype=int, device=d)  # for the iterations
            self._ai_list = wp.zeros(n_v, dtype=int, device=d)
        self._mesh_data = None
        if self.meshes:
            self._wp_meshes = [ob.wp_mesh(d) for ob in self.meshes]  # keep alive
            self._mesh_data = self._data[len(self.analytic):]
            self._mesh_ids = wp.array([m.id for m in self._wp_meshes], dtype=wp.uint64, device=d)
            self._mesh_moving = tuple(bool(ob.moving) for ob in self.meshes)
            n_v = model.num_vertices
            from .mesh_contact import MAX_CANDIDATES, MeshCache

            self._m_count = wp.zeros(1, dtype=int, device=d)
            self._m_list = wp.zeros(n_v, dtype=int, device=d)
            self._m_mask = wp.zeros(n_v, dtype=int, device=d)
            self._g_count = wp.zeros(1, dtype=int, device=d)  # what the near pass leaves
            self._g_list = wp.zeros(n_v, dtype=int, device=d)
            self._g_mask = wp.zeros(n_v, dtype=int, device=d)

            n_e = n_v * len(self.meshes)
            self._gap = wp.zeros(n_e, dtype=float, device=d)
            self._last = wp.array(np.full((n_v, 3), np.nan, dtype=np.float32), dtype=wp.vec3,
                                  device=d)
            c = MeshCache()
            c.gap = self._gap
            c.anchor = wp.zeros(n_e, dtype=wp.vec3, device=d)
            c.last = self._last
            c.margin = self.cache_margin
            c.cand_q = wp.zeros(n_e, dtype=wp.vec3, device=d)
            c.cand_phi = wp.zeros(n_e, dtype=float, device=d)
            c.cand_r2 = wp.zeros(n_e, dtype=float, device=d)
            c.cand_count = wp.zeros(n_e, dtype=int, device=d)
            c.cand_tris = wp.zeros(3 * n_e * MAX_CANDIDATES, dtype=wp.vec3, device=d)
            c.radius = self.candidate_radius
            self._cache = c

    # ------------------------------------------------------------------ the correction
    def restart(self) -> None:
        """A run starts (`CollisionStage.restart_span`): no list from the last `apply` for
        the first step's iterations (`begin_iterations`), as in a first run."""
        self._lists = None
        for name in ("_ai_count", "_m_count"):
            count = getattr(self, name, None)
            if count is not None:
                count.zero_()

    def apply(self, state, x_start, dt: float, again: bool = False) -> None:
        """Project, test paths and apply the impulse (positions and velocities of ``state``).
        ``state.time`` must hold the time at the start of the step (as in `Solver.step`).
        ``again``: a second pass in the step, after other responses changed velocities
        (`CollisionStage._pairs`): friction changes velocities only (`outcome_in_frame`)."""
        self._lists = None  # lists made for iterations are stale after the step
        dt = float(dt)
        self._poses(state.time, dt, 1)
        # the list for the next step's iterations only once a solver has asked for iterations
        self._far(state.x, x_start, 1, self.iteration_margin if self._a_planes is not None
                  else 0.0)
        self._near(state.x, x_start, state.v, dt, 2 if again else 1)

    @property
    def _all_fast(self) -> bool:
        """Only static spheres and planes (analytic): `integrate_and_apply` is one pass."""
        from .analytic import FAR_PLANE, FAR_SPHERE

        return bool(self.analytic) and all(k in (FAR_SPHERE, FAR_PLANE) for k in self._far_kinds)

    @property
    def fusable(self) -> bool:
        """True when `integrate_and_apply` can run this contact: ``fuse`` and obstacles of one
        family, analytic or mesh (a solver that `fuses_contact` then calls it instead of
        `apply`)."""
        return self.fuse and not (self.analytic and self.meshes)

    def integrate_and_apply(self, state, x_start, f, gravity, decay: float, dt: float,
                            update) -> None:
        """A solver's vertex update and `apply`, with the far tests in the same pass.

        ``update`` is the solver's Warp function ``(v, f, inv_mass, gravity, decay, dt) -> v``
        (symplectic Euler: ``(v + dt (f w + g)) decay``); ``v <- update(...); x <- x + dt v``
        for every free vertex (``f`` is cleared for the next step), then, in the same thread,
        the far tests of the path ``x -> x + dt v``; the near pass follows for the listed vertices, whose start positions this
        writes to ``x_start``. One pass over the vertices fewer, and no copy of the start
        positions: the same result as the update followed by `apply` (tests/test_contact.py).
        The explicit solver calls this when the contact is its first correction."""
        if not self.fusable:
            raise RuntimeError("integrate_and_apply needs fuse=True and obstacles of one family "
                               "(analytic or mesh)")
        m = self.model
        dt = float(dt)
        self._update = update
        self._lists = None
        self._poses(state.time, dt, 1)
        head = [state.x, state.v, f, m.inv_mass, gravity, float(decay), dt, x_start]
        if self.analytic and self._all_fast:
            from .analytic import integrate_contact_kernel

            # static spheres and planes: the whole contact inside the vertex update
            launch(integrate_contact_kernel(self._far_kinds, update), m.num_vertices,
                   [*head[:7], self._analytic_reach, self.thickness, self.slack,
                    int(self.ccd)], device=self.device)
            return
        if self.analytic:
            from .analytic import integrate_far_kernel

            self._a_count.zero_()
            launch(integrate_far_kernel(self._far_kinds, update), m.num_vertices,
                   [*head, self._analytic_reach, self.thickness, self.slack, int(self.ccd),
                    self._a_count, self._a_list], device=self.device)
        else:
            from .mesh_contact import integrate_mesh_far_kernel

            self._m_count.zero_()
            launch(integrate_mesh_far_kernel(self._mesh_moving, update), m.num_vertices,
                   [*head, self._mesh_reach, self.thickness, self.slack, int(self.ccd),
                    self._gap, self._cache.anchor, self._last, self._m_count, self._m_list,
                    self._m_mask],
                   device=self.device)
        self._near(state.x, x_start, state.v, dt, 1)

    def begin_iterations(self, x, x_start, dt: float, time=None) -> None:
        """Before position-based iterations: the obstacles' poses for the step and a contact
        plane (`warp_cloth.collision.planes`) for each vertex the last `apply` listed for
        iterations (analytic obstacles: path within the reach plus ``iteration_margin``;
        meshes: within the reach), from its path ``x_start -> x``; the `project_positions`
        calls that follow (until the next `apply`) project only those, onto their planes.

        The list comes from the last step's `apply`, which passes over every vertex anyway (it
        makes it once `begin_iterations` has been called), so the iterations add no pass of
        their own; it is a heuristic (a vertex that moves farther than the margin in one step is
        missed by the iterations of that step, as are all in the first step), not a guarantee: the `apply` that ends every step tests the exact geometry
        of every vertex. Allocates the planes on its first call."""
        dt = float(dt)
        if self._a_planes is None and self._m_planes is None:
            from .planes import make_planes

            n_v = self.model.num_vertices
            if self.analytic:
                self._a_planes = make_planes(n_v * len(self.analytic), self.device)
            if self.meshes:
                self._m_planes = make_planes(n_v * len(self.meshes), self.device)
        self._poses(self.clock if time is None else time, dt, 0)
        th, ccd, nt = self.thickness, int(self.ccd), self._near_threads
        if self._analytic_data is not None:
            from .analytic import analytic_planes_kernel

            launch(analytic_planes_kernel, nt,
                   [self._analytic_data, self._analytic_reach, self.poses, x, x_start, th, ccd,
                    self._ai_count, self._ai_list, nt, self._a_planes], device=self.device)
        if self._mesh_data is not None:
            from .mesh_contact import mesh_planes_kernel

            launch(mesh_planes_kernel, nt,
                   [self._mesh_data, self._mesh_ids, self.poses, len(self.analytic), x,
                    x_start, th, self.slack, ccd, self._cache, self._m_count, self._m_list,
                    self._m_mask, nt, self._m_planes], device=self.device)
        self._lists = (x.ptr, x_start.ptr, dt)

    def detect(self, x, x_start, dt: float, time, margin: float, record) -> None:
        """Contact planes of every vertex whose path ``x_start -> x`` comes within the reach plus
        ``margin`` of an obstacle, appended to ``record`` (`warp_cloth.collision.record`) as
        vertex-obstacle entries whose vertex at ``x`` lies less than ``margin`` above its plane.

        For solvers that take contact into their own solve (implicit Euler, projective
        dynamics): ``x`` is the step's predicted end (inertia and external forces). The same
        geometry as `begin_iterations` (exact closest point and continuous test at the predicted
        position), but from a far pass of its own with the margin, so the first step and fast
        vertices are covered too. Does not touch the distance caches of `apply` and leaves no
        list for `project_positions`. ``record.count`` must be zeroed by the caller."""
        dt = float(dt)
        self._lists = None
        if self._a_planes is None and self._m_planes is None:
            from .planes import make_planes

            n_v = self.model.num_vertices
            if self.analytic:
                self._a_planes = make_planes(n_v * len(self.analytic), self.device)
            if self.meshes:
                self._m_planes = make_planes(n_v * len(self.meshes), self.device)
        from .record import planes_to_record_kernel

        m = self.model
        self._poses(time, dt, 0)
        th, sl, ccd, nt = self.thickness, self.slack, int(self.ccd), self._near_threads
        if self._analytic_data is not None:
            from .analytic import analytic_far_kernel, analytic_planes_kernel

            self._a_count.zero_()
            self._ai_count.zero_()
            launch(analytic_far_kernel(self._far_kinds, self._update), m.num_vertices,
                   [self._analytic_reach, x, x_start, m.inv_mass, th, sl, ccd, self._a_count,
                    self._a_list, margin, self._ai_count, self._ai_list], device=self.device)
            launch(analytic_planes_kernel, nt,
                   [self._analytic_data, self._analytic_reach, self.poses, x, x_start, th, ccd,
                    self._ai_count, self._ai_list, nt, self._a_planes], device=self.device)
            pl = self._a_planes
            launch(planes_to_record_kernel, nt,
                   [x, pl.point, pl.normal, pl.ref, pl.friction, self.restitution,
                    len(self.analytic), 0, self._ai_count, self._ai_list, margin, nt, record],
                   device=self.device)
        if self._mesh_data is not None:
            from .mesh_contact import mesh_far_kernel, mesh_planes_kernel

            self._m_count.zero_()
            launch(mesh_far_kernel(self._mesh_moving, self._update), m.num_vertices,
                   [self._mesh_reach, x, x_start, m.inv_mass, th, sl, 0, ccd, margin,
                    self._gap, self._cache.anchor, self._last, self._m_count, self._m_list,
                    self._m_mask], device=self.device)
            launch(mesh_planes_kernel, nt,
                   [self._mesh_data, self._mesh_ids, self.poses, len(self.analytic), x,
                    x_start, th, sl + margin, ccd, self._cache, self._m_count, self._m_list,
                    self._m_mask, nt, self._m_planes], device=self.device)
            pl = self._m_planes
            launch(planes_to_record_kernel, nt,
                   [x, pl.point, pl.normal, pl.ref, pl.friction, self.restitution,
                    len(self.meshes), len(self.analytic), self._m_count, self._m_list, margin,
                    nt, record], device=self.device)

    def project_positions(self, x, x_start, dt: float, time=None) -> None:
        """Positions only: continuous test and projection (for position-based iterations).
        ``time``: the device time array of the step's start (default: the contact's clock).

        After `begin_iterations` for the same arrays and ``dt`` (until the next `apply`): only
        the listed vertices, against the contact planes made there (`warp_cloth.collision.
        planes`). Otherwise the exact test of every vertex."""
        dt = float(dt)
        if self._lists == (x.ptr, x_start.ptr, dt):
            from .planes import project_planes_kernel

            nt = self._near_threads
            if self._analytic_data is not None:
                launch(project_planes_kernel, nt,
                       [x, self._a_planes, len(self.analytic), self._ai_count, self._ai_list,
                        nt], device=self.device)
            if self._mesh_data is not None:
                launch(project_planes_kernel, nt,
                       [x, self._m_planes, len(self.meshes), self._m_count, self._m_list, nt],
                       device=self.device)
            return
        self._poses(self.clock if time is None else time, dt, 0)
        self._far(x, x_start, 0, 0.0)
        self._near(x, x_start, x, dt, 0)

    def _poses(self, time, dt, respond):
        if self.moving:
            from .motion import obstacle_poses_kernel

            self.still.fill_(1)
            self.steady.fill_(0 if self.frame is None else 1)
            launch(obstacle_poses_kernel, len(self.obstacles),
                   [self._data, self.key_times, self.key_offsets, self.key_rotations, time,
                    self.clock, dt, respond, self.poses, self.reaches, self._last_t1,
                    self.still, self.steady],
                   device=self.device)

    def _far(self, x, x_start, respond, margin):
        """Pass 1 (every vertex): the far tests; the rest go to the near lists."""
        m = self.model
        th, sl, ccd = self.thickness, self.slack, int(self.ccd)
        if self._analytic_data is not None:
            from .analytic import analytic_far_kernel

            self._a_count.zero_()
            if margin > 0.0:
                self._ai_count.zero_()
            launch(analytic_far_kernel(self._far_kinds, self._update), m.num_vertices,
                   [self._analytic_reach, x, x_start, m.inv_mass, th, sl, ccd, self._a_count,
                    self._a_list, margin, self._ai_count, self._ai_list], device=self.device)
        if self._mesh_data is not None:
            from .mesh_contact import mesh_far_kernel

            # no margin for meshes (the iterations reuse this list): a listed vertex that does
            # not touch would pay a BVH query for its plane (measured: PBD +320 % with one)
            self._m_count.zero_()
            launch(mesh_far_kernel(self._mesh_moving, self._update), m.num_vertices,
                   [self._mesh_reach, x, x_start, m.inv_mass, th, sl, respond, ccd, 0.0,
                    self._gap, self._cache.anchor, self._last, self._m_count, self._m_list,
                    self._m_mask],
                   device=self.device)

    def _near(self, x, x_start, v, dt, respond):
        """Pass 2 (listed vertices): projection, continuous test, outcome."""
        th, sl, ccd = self.thickness, self.slack, int(self.ccd)
        if self._analytic_data is not None:
            from .analytic import analytic_near_kernel

            launch(analytic_near_kernel(self._far_kinds, self._update), self._near_threads,
                   [self._analytic_data, self._analytic_reach, self.poses, 0, x, x_start, v,
                    dt, th, sl, respond, ccd, self._a_count, self._a_list,
                    self._near_threads], device=self.device)
        if self._mesh_data is not None:
            from .mesh_contact import mesh_general_kernel, mesh_near_kernel

            nt = self._near_threads
            self._g_count.zero_()
            launch(mesh_near_kernel, nt,
                   [self._mesh_data, x, x_start, v, th, sl, respond, self._cache,
                    self._m_count, self._m_list, self._m_mask, nt, self._g_count,
                    self._g_list, self._g_mask], device=self.device)
            launch(mesh_general_kernel, nt,
                   [self._mesh_data, self._mesh_ids, self.poses, len(self.analytic), x,
                    x_start, v, dt, th, sl, respond, ccd, self._cache, self._g_count,
                    self._g_list, self._g_mask, nt], device=self.device)

    # ------------------------------------------------------------------ reports (host side)
    def signed_distances(self, positions, t: float) -> np.ndarray:
        """(num_obstacles, N) signed distances of host positions at time ``t`` (tests, reports),
        in the model's simulation frame (`warp_cloth.model.ClothModel.origin`: ``state.x``, not
        `State.world_positions`)."""
        return np.stack([ob.signed_distance(positions, t) for ob in self.obstacles])

    def contact_distances(self, positions, t: float) -> np.ndarray:
        """`signed_distances` less each obstacle's pad (`pads`): the distances the contact holds
        at the thickness or more (a padded sphere's cloth rests the pad farther out)."""
        pad = {id(ob): p for ob, p in zip(self.analytic + self.meshes, self.pads)}
        return (self.signed_distances(positions, t)
                - np.array([pad[id(ob)] for ob in self.obstacles])[:, None])

    def max_penetration(self, state) -> float:
        """Deepest penetration (m, >= 0) of any unpinned vertex into any obstacle, now."""
        free = self.model.inverse_masses > 0
        phi = self.signed_distances(state.positions()[free], state.t)
        return float(max(0.0, -phi.min())) if phi.size else 0.0

    def __repr__(self):
        return (f"ObstacleContact({len(self.obstacles)} obstacles, thickness={self.thickness:g} m, "
                f"restitution={self.restitution:g}, friction={self.friction:g}, ccd={self.ccd})")

