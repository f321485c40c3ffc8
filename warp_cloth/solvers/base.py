"""What every solver shares: argument checks, scripted pins, corrections, collision, the clock.

A step is composed, in this order, of only the parts the scene uses (GUIDE.md):

    pins to their end-of-step targets -> method (external forces + integrator/solver, which
    respects the current contact set) -> corrections (strain/area limits)
    -> collision stage (`warp_cloth.collision.CollisionStage.resolve`: continuous test,
       projection, impulse) -> limits again with the contact projection inside their sweeps
       (``after_contact``: only where the response left an element outside its bound; the last
       self-collision response's contacts projected too)
       -> if those sweeps moved anything and the stage has self-collision: its response again,
          on the path from before them (`Solver._self_again`, after the sharp obstacle features
          again on the step's path: `CollisionStage.pairs_again`), and the two again while the
          sweeps move anything (`AFTER_CONTACT_ROUNDS`) -> time += dt

Each correction changes positions and adds the same change divided by dt to the velocities
(``v += (x_new - x_old) / dt``, the position-based velocity update of the notes, L1344), so
velocities stay consistent with the positions. A correction is any object with
``apply(state, x_start, dt)``, where ``x_start`` holds the positions at the start of the step.

Contact is not a correction: a solver holds at most one `CollisionStage` (``collision``), which
owns every obstacle of the scene; the method uses it inside its solve (implicit Euler and
projective dynamics through its contact record, position-based dynamics as constraints in its
iterations, explicit Euler by running its far tests in the vertex update) and the stage's
``resolve`` ends the step, after the limits, as the final guarantee.
"""

from __future__ import annotations

import math

import warp as wp

from . import common
from ..util import launch, positive_finite


def check_dt(dt) -> float:
    return positive_finite(dt, "dt", "seconds")


def _as_stage(model, collision):
    """A `CollisionStage` from a stage, an `ObstacleContact` or obstacles (collision layer)."""
    from ..collision import CollisionStage, Obstacle, ObstacleContact

    if isinstance(collision, CollisionStage):
        if collision.model is not model:
            raise ValueError("the collision stage was built for a different model")
        return collision
    if isinstance(collision, ObstacleContact):
        return CollisionStage(model, collision)
    if isinstance(collision, Obstacle) or (
            isinstance(collision, (list, tuple)) and collision
            and all(isinstance(o, Obstacle) for o in collision)):
        return CollisionStage(model, collision)
    raise ValueError(f"collision must be a CollisionStage, an ObstacleContact or a list of "
                     f"obstacles, got {collision!r}")


#: with self-collision and limits, the most rounds of the limits' pass after the collision
#: response and the self-collision response again on its path (`Solver._after_round`, a
#: device-side loop that stops after a pass that moved nothing): the response can stretch an
#: edge past its limit where it meets contacts the sweeps did not project. On the default
#: `stack` under ``StrainLimit(model, 0, 1.01)``, PD's max strain: one round 1.235 %, three
#: 1.169 %, eight 1.100 %
AFTER_CONTACT_ROUNDS = 8


class Solver:
    """Base class. Subclasses implement ``_advance(state, dt)``.

    Args:
        model: the `ClothModel`.
        corrections: objects with ``apply(state, x_start, dt)`` run after the method in the
            given order (strain and area limits). An `ObstacleContact` given here becomes the
            solver's collision stage instead (as if given as ``collision``).
        collision: a `warp_cloth.collision.CollisionStage` (or an `ObstacleContact`, or a list
            of obstacles with default contact options): every contact of the scene.

    Attributes:
        capturable: True when a step makes no host decision, so a sequence of steps can be
            recorded as a Warp graph and replayed (the scene runner does this).
        uniform_steps: True when, besides, every step records the same launches (no host
            state that changes from one step to the next), so the runner records a few steps
            and replays them through a frame (`warp_cloth.scene.GRAPH_BLOCK`).
        collision: the `CollisionStage`, or None.
        stats: per-step statistics of the last step (method-specific keys).
    """

    name = "solver"

    def __init__(self, model, *, corrections=(), collision=None):
        self.model = model
        self.device = model.device
        self.corrections = []
        self.collision = None
        self.capturable = True
        self.stats: dict = {}
        self._x_start = None
        for c in corrections:
            if c is not None:
                self.add_correction(c)
        if collision is not None:
            self.set_collision(collision)

    def _need_start(self):
        if self._x_start is None:
            self._x_start = wp.zeros(self.model.num_vertices, dtype=wp.vec3, device=self.device)

    def _self_again_alloc(self) -> None:
        """The arrays of `_self_again` (when the stage has self-collision or sharp obstacle
        features and there are corrections: allocated with them, never inside a captured
        step)."""
        if getattr(self, "_x_mid", None) is None:
            self._x_mid = wp.zeros(self.model.num_vertices, dtype=wp.vec3, device=self.device)
            self._limit_moved = wp.zeros(1, dtype=wp.int32, device=self.device)
            self._limit_stalled = wp.zeros(1, dtype=wp.int32, device=self.device)
            # [another round, rounds run, steps that ran out of rounds] (`_after_round`)
            self._after = wp.zeros(3, dtype=wp.int32, device=self.device)
            self._after_short_seen = 0

    def _self_again_prepare(self, state) -> None:
        """Before the limits' pass after contact: the positions it starts from, and its flag."""
        self._self_again_alloc()
        wp.copy(self._x_mid, state.x)
        self._limit_moved.zero_()
        self._limit_stalled.zero_()

    def _after_round(self, state, dt, stage, afters, sc) -> None:
        """One round after the collision response: the limits' pass (sweeps only where a bound
        is broken, with the obstacles' and the last self-collision response's contacts
        projected in them), then, if it moved anything, the self-collision response on its
        path: the sweeps do not see new self-contacts and could push the cloth through itself
        (an irregular sheet with 0.65 mm edges under PBD's stretch guard: 2-5 crossing pairs
        from its first frames), so the response comes last. Another round while the pass moved
        anything and no pass stalled (`limits.STALL_SWEEPS`: a bound that the pins or the
        contacts keep out of reach, which more rounds do not reach either: a 10 x 10 sheet
        whose pinned corner a rising floor passed ran eight rounds of stalled passes in every
        step), up to `AFTER_CONTACT_ROUNDS`."""
        self._self_again_prepare(state)
        self._limits_after(state, dt, stage, afters)
        wp.capture_if(self._limit_moved, self._self_again, state=state, dt=dt, stage=stage,
                      sc=sc)
        launch(common.after_round_kernel, 1, [self._limit_moved, self._limit_stalled,
                                              self._after, int(AFTER_CONTACT_ROUNDS)],
               device=self.device)

    def _limits_after(self, state, dt, stage, afters) -> None:
        """The limits' pass after contact, each limit raising ``_limit_moved`` if it moved the
        cloth and ``_limit_stalled`` if it stalled."""
        for c in afters:
            ran = c.after_contact(state, self._x_start, dt, stage)
            if ran and hasattr(c, "moved_into"):
                c.moved_into(self._limit_moved)
            if ran and hasattr(c, "stalled_into"):
                c.stalled_into(self._limit_stalled)

    def _self_again(self, state, dt, stage, sc) -> None:
        """After the limits' pass after contact moved the cloth: the sharp obstacle features
        on the step's path (`CollisionStage.pairs_again`; none without them), then the
        self-collision response on the path the pass moved the cloth along (from positions free
        of crossings, so its fall-backs end free of them)."""
        stage.pairs_again(state, self._x_start, dt)
        sc.resolve(state, self._x_mid, dt)

    def add_correction(self, c) -> None:
        """Append a correction (a limit); an `ObstacleContact` or `CollisionStage` becomes the
        collision stage (`set_collision`), which always runs after the corrections."""
        from ..collision import CollisionStage, ObstacleContact

        if isinstance(c, (ObstacleContact, CollisionStage)):
            self.set_collision(c)
            return
        if not hasattr(c, "apply"):
            raise ValueError(f"a correction needs an apply(state, x_start, dt) method, got {c!r}")
        owner = getattr(c, "model", None)
        if owner is not None and owner is not self.model:
            # its arrays are sized and indexed for its own model's vertices and edges: on
            # another model it read and wrote out of bounds (a limit of an 8 x 8 sheet on a
            # 2 x 2 one's solver ended the process in a heap corruption)
            raise ValueError(f"{type(c).__name__} was built for another model (its "
                             f"{owner.num_vertices} vertices) than this solver's "
                             f"({self.model.num_vertices} vertices): build it with the "
                             "solver's model")
        self.corrections.append(c)
        self.capturable = self.capturable and getattr(c, "capturable", True)
        self._need_start()
        if (getattr(self.collision, "self_collision", None) is not None
                or getattr(self.collision, "contact", None) is not None):
            self._self_again_alloc()  # (obstacles: their sharp features may come later)

    def set_collision(self, collision) -> None:
        """Give the solver its collision stage (one per solver: it owns every obstacle)."""
        if self.collision is not None:
            raise ValueError("this solver already has a collision stage; give all obstacles to "
                             "one CollisionStage (or one ObstacleContact)")
        self.collision = _as_stage(self.model, collision)
        self.capturable = self.capturable and self.collision.capturable
        self._need_start()
        sc = getattr(self.collision, "self_collision", None)
        if sc is not None:
            sc.layer_frames = self.self_contact_layer_frames
        if self.corrections and (sc is not None
                                 or getattr(self.collision, "contact", None) is not None):
            self._self_again_alloc()

    #: the self-contacts' velocity rule in the frames of the layers that meet
    #: (`SelfCollision.layer_frames`), else against a world at rest
    self_contact_layer_frames = True

    #: True for a method whose steps record the same launches from one step to the next
    #: (`uniform_steps`)
    uniform_method = False

    @property
    def uniform_steps(self) -> bool:
        """Every step records the same launches: the method's (``uniform_method``), its
        corrections' and its collision stage's (an ``uniform_steps`` attribute, True if absent,
        as for ``capturable``)."""
        parts = [*self.corrections, self.collision]
        return bool(self.uniform_method and self.capturable and
                    all(getattr(c, "uniform_steps", True) for c in parts if c is not None))

    #: True for a solver whose vertex update is a per-vertex Warp function that the collision
    #: stage can run in its far pass (`fused`); such a solver defines ``vertex_update``
    fuses_contact = False

    #: whether the collision stage's friction on obstacle features (after the step) also moves
    #: the vertices back by the velocity it takes out times dt, so a sticking point does not
    #: creep (`FeatureContact.friction`): explicit Euler. Not after implicit Euler and
    #: projective dynamics: it fought their solve, which has no friction on these entries and
    #: had relaxed the cloth around the sliding points (a strip held over a small sphere: 13.5 %
    #: strain under implicit Euler, 9.3 % under projective dynamics, against 1.3 % under
    #: explicit); nor after PBD: it stretched springs that the next projections turned into
    #: speed (an 8 x 8 sheet sliding off a 0.1 m sphere gained 7.6e-3 J in a frame, 2.2e-3 J
    #: without; friction held as well at PBD's small steps). Before, a flag on the stage that
    #: the other solvers cleared: a stage used by PBD and then by explicit Euler kept it off.
    friction_by_position = False

    @property
    def fused(self):
        """The collision stage this step runs inside the method's vertex update, or None: when
        the solver `fuses_contact`, the stage is ``fusable`` and no correction must run between
        the method and the stage (the order of the step is kept)."""
        c = self.collision
        if self.fuses_contact and c is not None and not self.corrections and c.fusable:
            return c
        return None

    def _outside_work(self) -> bool:
        """Whether something outside the cloth does work on it over a step: scripted pins or a
        moving obstacle (an energy check comparing a step's end with its start then means
        nothing)."""
        if getattr(self.model, "pin_path", None) is not None:
            return True
        obstacles = getattr(self.collision, "obstacles", None) or ()
        return any(getattr(o, "moving", False) for o in obstacles)

    def step(self, state, dt: float):
        """Advance ``state`` in place by ``dt`` seconds and return it."""
        dt = check_dt(dt)
        m = self.model
        stage = self.collision if self.fused is None else None
        if self.corrections or stage is not None:  # a fused stage writes the start itself
            wp.copy(self._x_start, state.x)
        if m.pin_path is not None and len(m.pins):
            launch(
                common.move_pins_kernel,
                len(m.pins),
                [state.x, state.v, m.pin_indices, m.pin_times, m.pin_keys, state.time, dt],
                device=self.device,
            )
        self._advance(state, dt)
        for c in self.corrections:
            c.apply(state, self._x_start, dt)
        if stage is not None:
            stage.resolve(state, self._x_start, dt, position_friction=self.friction_by_position)
            afters = [c for c in self.corrections if getattr(c, "after_contact", None)]
            sc = getattr(stage, "self_collision", None) if afters else None
            if sc is None and not (afters and getattr(stage, "has_pairs", False)):
                for c in afters:  # what friction's response stretched, within contact
                    c.after_contact(state, self._x_start, dt, stage)
            elif sc is None:
                # the same, then the sharp features again if the pass moved anything: its
                # sweeps meet no new cloth edge against an obstacle edge (`pairs_again`)
                self._self_again_prepare(state)
                self._limits_after(state, dt, stage, afters)
                wp.capture_if(self._limit_moved, stage.pairs_again, state=state,
                              x_start=self._x_start, dt=dt)
            else:
                # rounds of the limits' pass and the self-collision response on its path, while
                # a pass moved anything (a device-side loop: capturable)
                launch(common.after_begin_kernel, 1, [self._after], device=self.device)
                wp.capture_while(self._after[0:1], self._after_round, state=state, dt=dt,
                                 stage=stage, afters=afters, sc=sc)
        launch(common.advance_time_kernel, 1, [state.time, dt], device=self.device)
        return state

    def frame_end(self) -> list:
        """Messages (strings) about the steps since the last call that stopped short of a
        tolerance: the method's own (`_frame_messages`: an unconverged Newton or inner solve)
        and each correction's (a limit that ran out of sweeps). Host reads, once a frame: the
        scene runner calls it after every frame and prints each message as a warning."""
        out = list(self._frame_messages())
        after = getattr(self, "_after", None)
        if after is not None:  # `_after_round`'s loop ran out in some step
            short = int(after.numpy()[2])
            new, self._after_short_seen = short - self._after_short_seen, short
            self.after_contact_short_steps = short
            if new > 0:
                out.append(f"the limits' pass after contact still moved the cloth after "
                           f"{AFTER_CONTACT_ROUNDS} rounds with the self-collision response in "
                           f"{new} step(s): the limits may be left broken there (the response "
                           f"came last: no crossing); use more substeps")
        for c in self.corrections:
            fe = getattr(c, "frame_end", None)
            if fe is not None:
                out.extend(fe())
        return out

    #: steps (over the run, as of the last `frame_end`) whose rounds of the limits' pass and
    #: the self-collision response after contact ran out (`AFTER_CONTACT_ROUNDS`) while the
    #: pass still moved the cloth: each frame with new ones gets a message
    after_contact_short_steps = 0

    def _frame_messages(self) -> list:
        return []

    def _advance(self, state, dt: float):  # pragma: no cover - abstract
        raise NotImplementedError

    def describe(self) -> str:
        return self.name
