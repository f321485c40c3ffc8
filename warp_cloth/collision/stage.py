"""`CollisionStage`: every contact source of a scene in one object, below the solvers.

    from warp_cloth.collision import CollisionStage, Sphere, Plane

    stage = CollisionStage(model, [Sphere(0.3, (0, 0.5, 0)), Plane()], friction=0.5)
    solver = make_solver("implicit", model, collision=stage)
    Scene(model, solver).run("out.usd")        # the obstacles are simulated and drawn

The stage owns the obstacles (given once: the scene runner draws ``solver.collision.obstacles``)
and the `ContactRecord` (`warp_cloth.collision.record`), and offers each kind of solver what it
needs, through one interface:

- ``detect(x_start, x_pred, dt, time)``: before a solve, the contacts of the step's predicted
  path into ``record`` (one linear constraint ``n . sum w_j x_j >= offset`` per entry). Implicit
  Euler and projective dynamics read the record inside their solve (`warp_cloth.solvers.
  contact_coupling`), so their iterations converge to a state that satisfies contact and springs
  together.
- ``begin_iterations`` / ``project_positions``: contact planes projected inside position-based
  iterations (`ObstacleContact`).
- ``resolve(state, x_start, dt)``: after the solve and the limits, the final guarantee: the
  continuous test of every vertex's whole path, projection to the thickness, and the impulse
  with restitution and Coulomb friction. After it every free vertex is at least ``thickness -
  PENETRATION_TOLERANCE`` from every obstacle.
- ``fusable`` / ``integrate_and_apply(..., update)``: a solver whose vertex update is a
  per-vertex function (symplectic Euler) may pass that function to be run in the same pass as
  the far tests (the collision layer knows nothing of the solver; the solver hands it its
  update, `warp_cloth.solvers.explicit`).

Mesh obstacles' sharp features (thin parts, rims, spikes), boxes' edges and corners and spheres
too curved for the cloth's cells against the cloth's edges and triangles
(`warp_cloth.collision.features`) are a second source: vertex-triangle and edge-edge
pairs in the same record with barycentric weights, responded to in ``resolve``. Self-collision
plugs in the same way.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from .contact import DEFAULT_THICKNESS, ObstacleContact
from .features import RESOLVE_TOL, jacobi_project_kernel, position_apply_kernel
from .obstacles import Obstacle
from .record import add_overflow_kernel, make_record, record_threads
from ..util import count_since, launch, nonnegative_finite, positive_finite

#: `CollisionStage.contact_substeps`: a moving obstacle travels at most this many of the cloth's
#: shortest edge lengths in one step
SUBSTEP_TRAVEL = 0.25

__all__ = ["CollisionStage", "DEFAULT_SOLVE_MARGIN", "DEFAULT_SELF_MOTION"]


#: `CollisionStage.cloth_stretched`: the sharp features are chosen again once the cloth's
#: largest edge stretch passes this share of the stretch they were chosen for (within their
#: `features.STRETCH_MARGIN`), ...
FEATURE_RECHOOSE = 1.1
#: ... for this much more than the stretch seen, ...
FEATURE_HEADROOM = 1.2
#: ... and for at most this stretch (the runner's divergence guard stops at 1,000 % strain)
FEATURE_MAX_STRETCH = 11.0


def _positive(name, value) -> float:
    return positive_finite(value, name, "metres")


def _margin(name, value) -> float:
    return nonnegative_finite(value, name, "metres")

#: m; a vertex whose predicted path comes this far beyond the contact thickness of an obstacle
#: gets a constraint in the record (the solve may move it that much off its prediction)
DEFAULT_SOLVE_MARGIN = 0.01
#: under the scene runner, self-collision's response waits until some vertex has moved this
#: fraction of the self-collision thickness since the last response (`CollisionStage.plan`)
DEFAULT_SELF_MOTION = 0.25

#: a response (`CollisionStage.resolve`: obstacles, mesh features, self-collision) that leaves
#: a mesh edge the solve ended within this (a fraction of its rest length) stretched past it,
#: and by more than `STRETCH_RISE`, is counted (``response_stretched``) and fails
#: its frame, which the runner runs again with more steps (`Scene`'s ``retries``): the
#: responses project each contact along a normal taken where it met, and at large steps that
#: can pull a vertex far from its neighbours. Measured: real cloth (0.1 kg/m^2, 1e5 N/m) on an
#: irregular mesh held vertically and dropped 1.5 m onto the floor at 30 fps, implicit Euler at
#: its 2 steps a frame: the landing solves ended within 1.5 %, the self-collision response
#: left edges at 58-84 % (11 % at 10 Newton iterations, 84 % at 40); the same sheet dropped
#: across a 2 cm bar: the obstacle response took an edge from 13.5 to 23 %. The largest rise
#: by a response in the built-in scenes: 13 % (PD's twist, 240 frames, an edge the twist holds
#: at 60 %), 6.3 % (PBD's fast twist), 2.9 % (implicit's stack); edges the solve left past the
#: bound do not count (the twist's own stretch: counted too, 25 of the default twist's 600
#: frames ran again, late in the rope, for nothing it could change)
STRETCH_AFTER = wp.constant(0.10)
STRETCH_RISE = wp.constant(0.20)


@wp.kernel
def response_stretch_kernel(edges: wp.array2d(dtype=wp.int32), rest_len: wp.array(dtype=float),
                            x_pre: wp.array(dtype=wp.vec3), x: wp.array(dtype=wp.vec3),
                            count: wp.array(dtype=int)):
    """``count[0]`` += 1 when the response left edge ``e``, within `STRETCH_AFTER` before it
    (``x_pre``), stretched past it and by more than `STRETCH_RISE`."""
    e = wp.tid()
    a = edges[e, 0]
    b = edges[e, 1]
    inv = 1.0 / rest_len[e]
    after = wp.length(x[a] - x[b]) * inv
    before = wp.length(x_pre[a] - x_pre[b]) * inv
    if before <= 1.0 + STRETCH_AFTER and after > before + STRETCH_RISE:
        wp.atomic_add(count, 0, 1)
#: self-contacts inside a position-based solver's iterations (`begin_iterations`): the paths
#: that come within this many self-collision thicknesses. Measured (PBD, one step a frame:
#: 3 sheets of 10 x 10 cells dropped on the stack's sphere at 30 fps; the fold at 16 x 16): 1
#: thickness 16.7 % max strain on the stack, 2 thicknesses 9.4 % (9.8 % on the fold), 3 on the
#: fold 10.7 % and twice its impact zones
ITER_SELF_GAP = 2.0


class CollisionStage:
    """All contact of a scene: the obstacles, the contact record, detection and response.

    Args:
        model: the `ClothModel`.
        obstacles: `Plane`, `Sphere`, `Box`, `MeshObstacle` instances (at least one), or an
            `ObstacleContact` already built on ``model``.
        solve_margin: m, >= 0; how far beyond the thickness a predicted path may pass an
            obstacle and still get a constraint for the solve (default 0.01 m).
        edges: also keep the cloth's edges and triangles out of the meshes' and boxes' sharp
            features and of spheres too curved for its cells (`warp_cloth.collision.features`;
            default True). False tests vertices only (for a model whose mesh edges are not a
            surface, e.g. free particles).
        self_collision: True (or a `SelfCollision`) to keep the cloth from passing through
            itself (`warp_cloth.collision.self_collision`; default False). Obstacles may then be
            empty.
        self_thickness: m, > 0: the distance kept between non-adjacent parts of the cloth
            (default: the obstacle contact thickness).
        self_broadphase: ``"bvh"`` or ``"grid"`` (`warp_cloth.collision.broadphase`): how
            self-collision finds its candidate pairs (default ``"bvh"``, the faster here:
            ``warp-cloth bench selfcollision``).
        self_motion: >= 0, a fraction of the self-collision thickness. Under the scene runner
            (`plan`), self-collision's response (detection, projection, impact zones) runs
            once a span of solver steps has moved some vertex more than its allowance, and at
            the end of every frame, on the straight paths from the span's start to its end,
            instead of after every step (default 0.25; 0: after every step). The allowance is
            this fraction of the thickness near other parts of the cloth and up to 1.5
            thicknesses where the cloth is clear of itself (`SelfCollision.clear`). Every
            written frame has been resolved, and no pair can come a half thickness closer
            within a span before it is looked at (nor within the thickness, if it was clear). Solvers with many small
            substeps (explicit Euler, PBD) then pay for self-collision a few times a frame
            instead of every substep: ``warp-cloth bench selfcollision``. Without `plan` (a
            solver stepped by hand) every step is resolved.
        self_in_solve: with self-collision, the solvers that take contact into their solve
            (implicit Euler, projective dynamics) take the self-contacts too (default True):
            the vertex-triangle and edge-edge pairs whose predicted paths come within the
            thickness plus ``self_solve_margin`` become penalty terms of the solve with their full
            Hessian (`warp_cloth.solvers.contact_coupling`), so the solve keeps the layers
            apart and the response after it has little left to do. Measured on the fold scene
            (largest one-frame energy gain, max strain; time per frame with / without, both
            timed beside another run): implicit 0.57 J, 8.6 % without, 0.006 J, 3.8 % with
            (1.27x the time); projective dynamics 2.6 J, 38 % and 173 steps that returned the
            whole cloth to its start without, 0.0015 J, 0.9 % and none with (0.5x the time).
            Position-based dynamics projects them in its iterations in long steps
            (`PositionBased` ``self_contacts``; `begin_iterations`).
            False: self-contacts only after the solve.
        self_solve_margin: m, >= 0, or None (default: ``solve_margin``): the margin of the
            self-contacts taken into the solve. On a grid of 2 cm cells a vertex and the
            triangle across its cell's diagonal lie 1.4 cm apart: within the thickness (5 mm)
            plus 1 cm, so such pairs of the flat sheet are entries of every step, inactive but
            detected and carried through every iteration. The `twist` scene (2 cm cells) takes
            the thickness: PD, 150 frames, 932 -> 809 ms a frame, the same strain, energy and
            crossings (none). Not the default: on the default `table` the 5 mm margin moved
            implicit Euler's landing spike from 4.5 to 5.6 % strain (2.5 mm: 4.1 %, 7.5 mm:
            4.5 %: that spike depends on the margin chaotically), and fold and stack changed
            within the timing noise.
        **contact_options: `ObstacleContact` options (``thickness``, ``friction``,
            ``restitution``, ``ccd``, ``slack``, ...), when ``obstacles`` are shapes.

    Attributes:
        obstacles: the obstacles (the scene writes them to the USD stage).
        contact: the `ObstacleContact` (obstacle source).
        record: the `ContactRecord` that `detect` fills.
        capturable: True (no host decision in any call).
    """

    capturable = True

    def __init__(self, model, obstacles=(), *, solve_margin: float = DEFAULT_SOLVE_MARGIN,
                 edges: bool = True, self_collision=False, self_thickness: float | None = None,
                 self_broadphase: str = "bvh", self_in_solve: bool = True,
                 self_solve_margin: float | None = None,
                 self_motion: float = DEFAULT_SELF_MOTION, **contact_options):
        from ..util import check_model

        check_model(model, "CollisionStage")
        contact = None
        if isinstance(obstacles, ObstacleContact):
            if contact_options:
                raise ValueError("CollisionStage: give contact options to the ObstacleContact, "
                                 f"not to the stage ({sorted(contact_options)})")
            if obstacles.model is not model:
                raise ValueError("CollisionStage: the ObstacleContact was built for a different "
                                 "model")
            contact = obstacles
        else:
            from ..util import obstacle_list

            obstacles = obstacle_list(obstacles if obstacles is not None else (),
                                      "CollisionStage")
            if obstacles:
                contact = ObstacleContact(model, obstacles, **contact_options)
            elif not self_collision:
                raise ValueError("CollisionStage needs obstacles or self_collision=True")
            elif set(contact_options) - {"thickness"}:
                raise ValueError(f"CollisionStage: obstacle contact options "
                                 f"{sorted(set(contact_options) - {'thickness'})} without "
                                 "obstacles")
        solve_margin = _margin("solve_margin", solve_margin)
        self_motion = nonnegative_finite(self_motion, "self_motion", "thicknesses")
        self.model = model
        self.device = model.device
        self.contact = contact
        self.solve_margin = solve_margin
        self.self_solve_margin = (solve_margin if self_solve_margin is None
                                  else _margin("self_solve_margin", self_solve_margin))
        self.self_motion = self_motion
        self.self_in_solve = bool(self_in_solve)
        # cloth edges and triangles against the meshes' sharp features (none: no cost)
        from .features import FeatureContact

        self.features = FeatureContact(model, contact if edges else None)
        # self-collision (off unless asked for: it costs a broad phase over the cloth every step;
        # the built-in scenes ask for it)
        self.self_collision = None
        if self_collision:
            from .self_collision import SelfCollision

            if isinstance(self_collision, SelfCollision):
                self.self_collision = self_collision
            else:
                th = (self_thickness if self_thickness is not None else
                      contact.thickness if contact is not None else
                      contact_options.get("thickness", DEFAULT_THICKNESS))
                self.self_collision = SelfCollision(model, _positive("self_thickness", th),
                                                    broadphase=self_broadphase)
        if contact is not None or self.self_collision is not None:
            v = np.asarray(model.mesh.vertices, dtype=np.float64)
            size = float(np.ptp(v, axis=0).max()) if len(v) else 0.0
            if size > 0.0 and self.thickness > 0.5 * size:
                # (a 1 m sheet at a 1 m thickness over a sphere went from 1.3 to 191 J in two
                # frames; at 10 m it was returned to its start in every step)
                raise ValueError(f"CollisionStage: the contact thickness {self.thickness:g} m is "
                                 f"more than half the cloth's size ({size:g} m): the thickness "
                                 "is the gap contact keeps, a few millimetres for real cloth")
        n_obs = len(contact.obstacles) if contact is not None else 0
        # one vertex-obstacle entry per (vertex, obstacle) at most, and the pairs' shares
        self.capacity = model.num_vertices * n_obs + self.features.capacity
        self.record = make_record(self.capacity, self.device)
        self.pair_record = (make_record(self.features.capacity, self.device)
                            if self.features.active else None)
        # entries that did not fit, as last reported (`frame_end`), and what a regrown `record`
        # must tell (a solve's coupling sizes its own arrays by it: `on_record_regrown`)
        # `_project_self`'s violation counts (not read) and empty "moved" array, made here:
        # the projections run inside steps
        self._self_scratch = wp.zeros(2, dtype=int, device=self.device)
        # `resolve`'s stretch check: the positions after the solve, the mesh edges and their
        # rest lengths, and the count of edges over-stretched by a response (over all steps)
        self._edges = None
        er = np.asarray(model.mesh.edges, dtype=np.int32).reshape(-1, 2)
        if len(er):
            xr = np.asarray(model.mesh.vertices, dtype=np.float64)
            rest = np.linalg.norm(xr[er[:, 0]] - xr[er[:, 1]], axis=1)
            self._edges = wp.array(er, dtype=wp.int32, ndim=2, device=self.device)
            self._rest_len = wp.array(np.maximum(rest, 1e-12).astype(np.float32), dtype=float,
                                      device=self.device)
            self._x_solved = wp.zeros(model.num_vertices, dtype=wp.vec3, device=self.device)
        self._stretched = wp.zeros(1, dtype=int, device=self.device)
        self._stretched_seen = 0
        self._no_vec = wp.zeros(0, dtype=wp.vec3, device=self.device)
        self._no_float = wp.zeros(0, dtype=float, device=self.device)
        self._dropped_seen = [0, 0]
        self._regrow_listeners = []
        self._restart_listeners = []

    # ------------------------------------------------------------------ what it holds
    @property
    def obstacles(self) -> list:
        """The obstacles as given, in the world frame (the scene draws these)."""
        return list(self.contact.world_obstacles) if self.contact is not None else []

    @property
    def sim_obstacles(self) -> list:
        """The obstacles in the model's simulation frame (`ClothModel.origin`), as the contact
        computes with them; the given ones when that is the world frame."""
        return list(self.contact.obstacles) if self.contact is not None else []

    @property
    def thickness(self) -> float:
        if self.contact is not None:
            return self.contact.thickness
        return self.self_collision.thickness

    # ------------------------------------------------------------------ steps
    def contact_substeps(self, fps: float, frames: int) -> int:
        """Solver steps per frame such that no point of a moving obstacle travels farther than
        `SUBSTEP_TRAVEL` times the cloth's shortest edge in one step, over the ``frames`` frames
        at ``fps`` (1 when nothing moves; host work, once). A step's contacts are planes taken
        from the predicted path; a sharp feature that sweeps past whole cloth edges within one
        step leaves them to a single linearisation. Measured: a 6 mm rod through a curtain of
        4.2 cm edges at 5 m/s (8 cm a frame), implicit Euler at its 2 steps a frame: an edge
        hooked on the rod's end stretched to 280 % (explicit Euler, 185 steps: 11 %); at 4 steps
        (half an edge) 16 %, at 8 (a quarter) 14 %. A 60 cm blade spinning at 8 rad/s (4 cm a
        frame at its tips) into the curtain: 36 % at 2 steps (half an edge), 3.5 % at 4."""
        fps = float(fps)
        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"contact_substeps: fps must be a positive number, got {fps}")
        if int(frames) != frames or frames < 0:
            raise ValueError(f"contact_substeps: frames must be a whole number >= 0, got "
                             f"{frames!r}")
        moving = [ob for ob in self.sim_obstacles if ob.moving]
        if not moving or frames < 1:
            return 1
        m = self.model
        ne = len(m.mesh.edges)
        rest = np.asarray(m.spring_rest)[:ne] if ne else np.zeros(0)
        rest = rest[rest > 0]
        if len(rest) == 0:
            return 1
        edge = float(rest.min())
        t = np.arange(int(frames) + 1) / float(fps)
        travel = max(ob.travel(t[k], t[k + 1]) for ob in moving for k in range(int(frames)))
        return max(1, int(math.ceil(travel / (SUBSTEP_TRAVEL * edge) - 1e-9)))

    # ------------------------------------------------------------------ spans
    def plan(self, substeps: int) -> None:
        """Frames of ``substeps`` solver steps (the scene runner calls this): self-collision's
        response then runs once per span of steps (``self_motion``; `SelfCollision.plan`)."""
        substeps = int(substeps)
        if substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        if self.self_collision is not None:
            self.self_collision.plan(substeps, self.self_motion)

    def restart_span(self) -> None:
        """The next step starts a frame (the runner calls this at the start of a run): also
        what a solver's coupling carried from the last step (`on_restart`) is forgotten, so a
        second run of a scene repeats the first."""
        if self.self_collision is not None:
            self.self_collision.restart_span()
        if self.contact is not None:
            self.contact.restart()
        for callback in self._restart_listeners:
            callback()

    def on_restart(self, callback) -> None:
        """``callback()`` at `restart_span` (the start of a run)."""
        self._restart_listeners.append(callback)

    # ------------------------------------------------------------------ detection
    def detect(self, x_start, x_pred, dt: float, time) -> None:
        """Fill `record` with the constraints of the predicted paths ``x_start -> x_pred``
        (``time``: the device clock at the step's start). Capturable: counts stay on the device."""
        self.record.count.zero_()
        if self.contact is not None:
            self.contact.detect(x_pred, x_start, dt, time, self.solve_margin, self.record)
            self.features.detect(x_start, x_pred, self.solve_margin, self.record)
        # self-contacts (`self_in_solve`) go into the coupling's own record
        # (`ContactCoupling.detect`): with their diagonal blocks only, Newton did not converge
        # and the folded sheet gained energy; with the full Hessian it does

    # ------------------------------------------------------------------ response
    def resolve(self, state, x_start, dt: float, position_friction: bool = False) -> None:
        """The final guarantee after the solve and the limits: `ObstacleContact.apply` (every
        vertex), then the sharp mesh features against the cloth's edges and triangles on the
        actual paths (`FeatureContact`). ``position_friction``: the features' friction also
        moves the vertices back by what it takes out (`Solver.friction_by_position`)."""
        if self._edges is not None:
            wp.copy(self._x_solved, state.x)
        if self.contact is not None:
            self.contact.apply(state, x_start, dt)
        self._pairs(state, x_start, dt, position_friction)
        if self._edges is not None:  # did the response over-stretch an edge? (`STRETCH_AFTER`)
            launch(response_stretch_kernel, len(self._edges),
                   [self._edges, self._rest_len, self._x_solved, state.x, self._stretched],
                   device=self.device)

    def _pairs(self, state, x_start, dt, position_friction: bool = False):
        """The sharp features against the cloth's edges and triangles, then self-collision, on
        the actual paths; then vertex contact again for the vertices those responses moved
        (one may push a vertex into another surface; the others are not approaching and are
        left as they are)."""
        self._feature_pass(state, x_start, dt, friction=True,
                           position_friction=position_friction)
        if self.self_collision is not None:
            # after obstacle contact, whose projection can push one layer of a fold through
            # another (measured: 88 crossing pairs on the fold); every step, or once per span
            # (`plan`). Its own projection splits corrections between the layers, so it pushed
            # a layer lying on an obstacle into it (measured: 4.6 mm of a 5 mm thickness left
            # on a fold, 0.31 mm of 2 mm under implicit Euler): vertex contact's position
            # projection (on this step's path; it moves only the vertices it finds inside the
            # thickness) runs inside each of its rounds, whose next detection sees what it
            # moved. Run once after the response instead (`apply`), it pushed layers through
            # each other (a stack of sheets under a deliberately weak projection: 12 frames
            # with crossings), and `apply` inside the rounds applied friction once a round (a
            # fold's landing stretched 2.2 %, 1.5 % with positions only). Between a span's
            # responses `hold` pushes by one step's sinking at most; the impact zones and the
            # whole-cloth return (the fall-backs) come after the rounds and are not followed
            # by it
            obstacles = None
            if self.contact is not None:
                def obstacles(x=None):  # positions only: friction and restitution acted already
                    self.contact.project_positions(state.x if x is None else x, x_start, dt,
                                                   state.time)
                # every obstacle stands still this step (the projection sets it): the impact
                # zones may hold a zone that touches one where it started
                obstacles.still = self.contact.still
            self.self_collision.step(state, x_start, dt, obstacles=obstacles)

    @property
    def has_pairs(self) -> bool:
        """Whether the stage tests cloth edges and triangles against sharp obstacle features
        (`pairs_again` does something)."""
        return self.pair_record is not None

    def pairs_again(self, state, x_start, dt: float) -> None:
        """The sharp features detected again on the step's path ``x_start -> state.x`` and
        responded to, then vertex contact again: after the limits' pass that follows the
        response (`Solver.step`), whose sweeps project the entries of the response's detection
        but meet no new pair. Measured (a randomized scene, implicit Euler, a sheet thrown at
        a moving rotated box under ``StrainLimit(model, 0, 1.068)``): the sweeps pulled a cloth
        edge across a box edge the response had held it clear of, from 1.2 mm to 0.27 mm of
        it with 2.26 mm kept, then through it; the next step's detection took the far side for
        the cloth's own, and the edge cut 3.4-8 mm into the box for four frames, with every
        vertex outside and no step counted as unresolved. Positions and velocities, like
        `resolve`; no friction (the response's acted)."""
        self._feature_pass(state, x_start, dt)

    def _feature_pass(self, state, x_start, dt: float, friction: bool = False,
                      position_friction: bool = False) -> None:
        """The sharp features on the paths ``x_start -> state.x``: detect, (``friction``:
        Coulomb friction first), respond, the spheres again, then vertex contact again for the
        vertices they moved (`_pairs`, `pairs_again`). Nothing without features."""
        if self.pair_record is None:
            return
        self.pair_record.count.zero_()
        # with friction, within the vertex contacts' slack: a point the solve (or PBD's
        # iterations) left resting on a feature, at the thickness, is in contact for it
        margin = self.contact.slack if friction and self.features.has_friction else 0.0
        self.features.detect(x_start, state.x, margin, self.pair_record)
        if friction:
            self.features.friction(state, dt, self.pair_record, self.contact.slack,
                                   position_friction)
        self.features.respond(state, dt, self.pair_record)
        self.features.respond_spheres_again(state, x_start, dt, self.pair_record)
        if self.contact is not None:
            self.contact.apply(state, x_start, dt, again=True)

    # position-based iterations
    def begin_iterations(self, x, x_start, dt: float, time=None,
                         self_contacts: bool = False) -> None:
        """Before a position-based solver's iterations (``x``: its prediction): the vertex
        contacts' planes, and the sharp features' entries of the predicted paths (within the
        thickness), which `project_positions` then projects in every iteration: kept out of the
        iterations, the features' response after the step and the iterations' pull undid each
        other and PBD's velocity update gained energy from it (a 14 x 14 sheet sliding off a
        table's edge: 2.7e-2 J in a frame; 4.6e-4 J now). With the solve's 1 cm margin instead,
        2.8e-3 J there, and the thin-parts mesh under PBD cost 644 instead of 291 ms a frame
        (more entries, and the feature pass's boxes widened for every query).
        ``self_contacts`` (with self-collision; `use_self_iterations` first): also the
        self-contacts of the predicted paths, within twice the self-collision thickness, into
        `iter_record` (`SelfCollision.detect`; entries that do not fit are counted and reported
        by `frame_end`, and the record doubles)."""
        if self.contact is not None:
            self.contact.begin_iterations(x, x_start, dt, time)
            if self.pair_record is not None:
                self.pair_record.count.zero_()
                self.features.detect(x_start, x, 0.0, self.pair_record)
        self.iter_live = bool(self_contacts)
        if self_contacts:
            sc = self.self_collision
            rec = self.iter_record
            rec.count.zero_()
            rec.overflow.zero_()
            sc.detect(x_start, x, ITER_SELF_GAP * sc.thickness, rec)
            launch(add_overflow_kernel, 1, [rec, self._iter_dropped], device=self.device)

    def project_positions(self, x, x_start, dt: float, time=None,
                          self_contacts: bool = False) -> None:
        """One projection of the contacts `begin_iterations` listed, positions only; with
        ``self_contacts``, the self-contacts of `iter_record` too (one Jacobi round; an entry
        whose pair started closer than the thickness is held where it started, not pushed out:
        PBD's velocity update would make that push a separation speed)."""
        if self.contact is not None:
            self.contact.project_positions(x, x_start, dt, time)
            if self.pair_record is not None:
                self.features.project_positions(x, x_start, self.pair_record, dt=dt)
        if self_contacts:
            self._project_self(self.iter_record, self._iter_threads, self._iter_acc,
                               self._iter_cnt, x, x_start)

    def _project_self(self, rec, threads, acc, cnt, x, x_start) -> None:
        """One Jacobi round of the self-contact record ``rec``, positions only (an entry that
        started closer than its constraint held where it started, `jacobi_project_kernel`)."""
        m, d = self.model, self.device
        launch(jacobi_project_kernel, threads,
               [rec, 0, x, m.inv_mass, acc, cnt, self._self_scratch,
                RESOLVE_TOL * self.self_collision.thickness, threads, self._no_vec, x_start,
                self._no_vec, self._no_float],
               device=d)
        launch(position_apply_kernel, m.num_vertices, [x, acc, cnt, self._no_vec, 0.0], device=d)

    def project_self_response(self, x, x_start) -> None:
        """One Jacobi projection, positions only, of the contacts the last self-collision
        response found (its record; no detection): the limits' sweeps after the response
        (`StrainLimit.after_contact`) run it after each sweep when no position-based solver's
        iterations listed the step's self-contacts, so a sweep does not pull one layer back
        into another and the response after the sweeps (`Solver._self_again`) has nothing to
        move: on the default `stack` under ``StrainLimit(model, 0, 1.01)`` that response left
        edges at 1.24 % (PD) and 1.23 % (explicit Euler). An entry that started closer than its
        constraint is held where it started (``x_start``), as in `project_positions`."""
        sc = self.self_collision
        if sc is not None:
            self._project_self(sc.record, sc.threads, sc.acc, sc.cnt, x, x_start)

    def use_self_iterations(self) -> bool:
        """Get ready for ``self_contacts`` in `begin_iterations` / `project_positions` (a
        position-based solver calls this once, at set-up: it allocates). False, and nothing
        allocated, without self-collision or with ``self_in_solve`` off."""
        sc = self.self_collision
        if sc is None or not self.self_in_solve:
            return False
        if self.iter_record is None:
            n, d = self.model.num_vertices, self.device
            self.iter_record = make_record(sc.capacity, d)
            self._iter_threads = record_threads(sc.capacity, d)
            self._iter_acc = wp.zeros(n, dtype=wp.vec3, device=d)
            self._iter_cnt = wp.zeros(n, dtype=int, device=d)
            self._iter_dropped = wp.zeros(1, dtype=int, device=d)  # over all steps
        return True

    #: the self-contacts of a position-based solver's iterations (`use_self_iterations`)
    iter_record = None
    #: whether the last `begin_iterations` listed them (host flag, the same every step of a
    #: size): the limits' sweeps after the response project them too (`StrainLimit.
    #: after_contact`), so PBD's stretch guard does not pull one layer into another
    iter_live = False
    _iter_dropped_seen = 0

    # a solver's vertex update fused with the far tests
    @property
    def fusable(self) -> bool:
        return self.contact is not None and self.contact.fusable

    def integrate_and_apply(self, state, x_start, f, gravity, decay, dt, update,
                            position_friction: bool = False) -> None:
        """The solver's vertex update with `resolve` in the same pass (`ObstacleContact.
        integrate_and_apply`), then the sharp features (which need every start position);
        ``position_friction`` as in `resolve`."""
        if self.pair_record is not None or self.self_collision is not None:
            wp.copy(x_start, state.x)
        self.contact.integrate_and_apply(state, x_start, f, gravity, decay, dt, update)
        self._pairs(state, x_start, dt, position_friction)

    # ------------------------------------------------------------------ reports
    #: steps of the last frame (`frame_end`) that failed: the whole cloth returned to its start
    #: by self-collision, or contacts dropped for want of room (obstacle or self); one more if
    #: self-collision's impact zones held most of the cloth (``frame_frozen``)
    frame_failed = 0
    #: self-collision's rigid impact zones held most of the cloth in the last frame
    #: (`SelfCollision.frame_frozen`)
    frame_frozen = False
    #: most of the last frame's self-collision responses met a solve that had diverged
    #: (`SelfCollision.frame_diverged`)
    frame_diverged = False

    def frame_end(self) -> list:
        """Called by the runner after each frame (host reads): ``(message, regrown)`` for each
        thing to report: responses to mesh features that ended still violated or pressed on
        pinned vertices, self-collision steps that returned the whole cloth to its start, and
        contacts dropped for want of room, obstacle or self (the record then doubles: ``regrown``
        True, so a recorded graph must be recorded again). ``frame_failed`` is then the number
        of the frame's steps that returned the whole cloth to its start or dropped contacts
        (the scene runner runs such a frame again with more steps: `Scene`'s ``retries``)."""
        out = self.features.frame_end()
        out += self._overflow_report()
        self.frame_failed = sum(regrown for _, regrown in out)
        new, self._stretched_seen = count_since(self._stretched, self._stretched_seen)
        if new > 0:
            self.frame_failed += 1
            out.append((f"the collision response stretched {new} mesh edge(s) past "
                        f"{100 * float(STRETCH_AFTER):g} % (and by more than "
                        f"{100 * float(STRETCH_RISE):g} % over the solve's) in the frame's "
                        "steps: the cloth moves too far in a step for its contacts (a landing or "
                        "an impact at speed); more steps a frame keep it", False))
        if self.self_collision is not None:
            out += self.self_collision.frame_end()
            self.frame_failed += self.self_collision.frame_failed
            self.frame_frozen = self.self_collision.frame_frozen
            self.frame_diverged = self.self_collision.frame_diverged
        coupling = getattr(self, "solve_coupling", None)  # self-contacts inside a solve
        if coupling is not None:
            out += coupling.self_frame_end()
        out += self._iter_frame_end()
        return out

    def _iter_frame_end(self) -> list:
        """Self-contacts of a position-based solver's iterations dropped for want of room
        since the last call (host read): the record doubles (``regrown``: a recorded graph
        must be recorded again). The dropped pairs were still resolved after the step."""
        if self.iter_record is None:
            return []
        new, self._iter_dropped_seen = count_since(self._iter_dropped, self._iter_dropped_seen)
        if new <= 0:
            return []
        cap = 2 * int(self.iter_record.vertex.shape[0])
        self.iter_record = make_record(cap, self.device)
        self._iter_threads = record_threads(cap, self.device)
        return [(f"{new} self-contacts did not fit the iterations' record (they were resolved "
                 f"after the step); its room is doubled to {cap} entries", True)]

    def cloth_stretched(self, strain: float) -> list:
        """The runner's frame-end call with the cloth's largest edge strain: once it passes
        `FEATURE_RECHOOSE` of the stretch the sharp features were chosen for (its rest length
        at first), they are chosen again for `FEATURE_HEADROOM` times the stretch (at most
        `FEATURE_MAX_STRETCH`), and the records grow to their room. ``(message, regrown)``
        pairs (regrown: a recorded graph must be recorded again). The features are the ridges a
        straight cloth edge of the longest length can dip under (module docstring of
        `warp_cloth.collision.features`): a cloth dragged by a moving lumpy mesh against its
        pinned edge, stretched to 245 %, had the mesh's ridges (not sharp for its rest edges)
        through its triangles in 13-14 of 40 frames under every solver."""
        f = self.features
        if f.rest_max <= 0.0 or not math.isfinite(strain):  # (0: no features, or turned off)
            return []
        s = 1.0 + max(float(strain), 0.0)
        if s <= FEATURE_RECHOOSE * f.stretch:
            return []
        new_s = min(FEATURE_HEADROOM * s, FEATURE_MAX_STRETCH)
        if new_s <= f.stretch:
            return []
        from .features import FeatureContact

        before = (f.num_vertices, f.num_edges)
        self.features = f = FeatureContact(self.model, self.contact, f.rounds, stretch=new_s)
        if f.active:
            cap = f.capacity
            if self.pair_record is None or self.pair_record.vertex.shape[0] < cap:
                self.pair_record = make_record(cap, self.device)
                self._dropped_seen[1] = 0
            need = self.model.num_vertices * len(self.contact.obstacles) + cap
            if need > self.capacity:
                self.capacity = need
                self.record = make_record(need, self.device)
                self._dropped_seen[0] = 0
                for callback in self._regrow_listeners:
                    callback(self.record)
        return [(f"the cloth is stretched to {100.0 * (s - 1.0):.3g} %: the obstacles' sharp "
                 f"features are chosen again for cloth edges {new_s:.3g} times their rest "
                 f"length ({f.num_vertices} vertices and {f.num_edges} edges; {before[0]} and "
                 f"{before[1]} before)", True)]

    def on_record_regrown(self, callback) -> None:
        """``callback(record)`` after `frame_end` replaces `record` with a larger one."""
        self._regrow_listeners.append(callback)

    def _overflow_report(self) -> list:
        """Obstacle and mesh-feature entries dropped for want of room since the last call (host
        reads, once a frame): the record that overflowed doubles (a recorded graph must then
        be recorded again). The vertex-obstacle entries always fit (one per vertex and
        obstacle); the sharp features' (8 per feature vertex and edge) may not, where a cloth
        wraps around a feature: a thin rod through a curtain dropped 4,624 in one step."""
        out = []
        for k, name in ((0, "record"), (1, "pair_record")):
            rec = getattr(self, name)
            if rec is None:
                continue
            n = int(rec.overflow.numpy()[0])
            new = n - self._dropped_seen[k]
            if new <= 0:
                continue
            cap = 2 * int(rec.vertex.shape[0])
            setattr(self, name, make_record(cap, self.device))
            self._dropped_seen[k] = 0
            if k == 0:
                self.capacity = cap
                for callback in self._regrow_listeners:
                    callback(self.record)
            what = ("the solve's obstacle contacts (they were still resolved after the solve)"
                    if k == 0 else "the response's mesh-feature contacts")
            out.append((f"{new} entries of {what} did not fit their record; its room is doubled "
                        f"to {cap} entries", True))
        return out

    @property
    def stats(self) -> dict:
        """Entries of the last `detect` and entries dropped for capacity (host reads)."""
        count = int(self.record.count.numpy()[0])
        out = {"contacts": min(count, self.capacity),
               "contact_overflow": int(self.record.overflow.numpy()[0])}
        if self.pair_record is not None:
            pc = int(self.pair_record.count.numpy()[0])
            out["feature_contacts"] = min(pc, self.pair_record.vertex.shape[0])
            out["contact_overflow"] += int(self.pair_record.overflow.numpy()[0])
            out.update(self.features.stats)
        if self.self_collision is not None:
            out.update(self.self_collision.stats)
        out["response_stretched"] = int(self._stretched.numpy()[0])
        if self.iter_record is not None:
            out["self_iteration_contacts"] = min(int(self.iter_record.count.numpy()[0]),
                                                 self.iter_record.vertex.shape[0])
            out["self_iteration_dropped"] = int(self._iter_dropped.numpy()[0])
        return out

    def max_penetration(self, state) -> float:
        return self.contact.max_penetration(state) if self.contact is not None else 0.0

    def signed_distances(self, positions, t: float):
        import numpy as np

        if self.contact is None:
            return np.full((0, len(positions)), np.inf)
        return self.contact.signed_distances(positions, t)

    def __repr__(self):
        return f"CollisionStage({self.contact!r}, solve_margin={self.solve_margin:g} m)"
