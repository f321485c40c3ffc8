"""`Scene`: a model, a solver, obstacles and a frame schedule, run to a USD file.

`Scene.run` steps ``frames - 1`` frames of ``substeps`` solver steps each (frame 0 is the initial
state), checks every frame with the divergence guard, writes it to the USD stage, and returns a
`RunStats` summary. When the solver is capturable (no host decision inside a step) the substeps
of a frame are recorded once as a Warp graph and replayed, which removes most of the per-launch
cost on the CPU.
"""

from __future__ import annotations

import math
import os
import sys
import time as _time

import numpy as np
import warp as wp

from .diagnostics import Meter
from .errors import SimulationDiverged
from .runstats import Note, RunStats
from .util import check_number

__all__ = ["Scene", "RunStats"]

#: a frame needing more automatic substeps than this is refused (a user may still ask for more)
MAX_SUBSTEPS = 100_000
#: automatic substeps past this get a note at the start of a run naming what sets the stable
#: step (`SymplecticEuler.stiffest`): measured, a 14 x 14 sheet with one sliver triangle (a
#: vertex 0.1 % of an edge off it, as some exporters leave) under quadratic bending took 12,975
#: explicit steps a frame, 15 s a frame, without a word of why
MANY_SUBSTEPS = 1000
#: s: the shortest and longest solver step a scene takes (float32 holds dt^2 and 1 / dt^2)
MIN_DT, MAX_DT = 1.0e-9, 1.0e3

#: `Scene`'s ``retries``: a frame in which a self-collision step failed runs again with 2, then 4
#: times the steps
DEFAULT_RETRIES = 2

#: frames in a row whose self-collision held most of the cloth in rigid impact zones, or returned
#: the whole cloth to its start in most of its steps (after their retries; `frame_frozen`), end
#: a run as diverged: an unstable step frozen into rigid bodies, or standing still, is not cloth
#: (measured: explicit Euler at k = 1e9 N/m and 2 steps a frame on a 4 x 4 hanging sheet, far
#: past its stable step, ran on "ok" with the cloth rigid; PBD's twist stood still from frame
#: 109 with a warning a frame)
FROZEN_FRAMES = 3

#: a frame (of a scene with a collision stage, whose frames can run again) in which a solver
#: that solves to a tolerance (implicit Euler) left a step short of it runs again with more
#: steps too (`retries`) when its largest edge strain ends above this and
#: more than `RETRY_STRAIN_RISE` above the frame's start: a landing the solve did not converge
#: through (measured: light, stiff curtains, 0.1 kg/m^2 and 1e5 N/m, dropped 1.5 m onto the
#: floor at 2 steps a frame and 30 fps, Newton at its 40-iteration cap with its inner solves at
#: theirs: eight irregular curtains ended at 4.3-19.7 % max strain, 11.3 % on average, without
#: this rule, 2.1-11.8 %, 5.2 %, with it; `tests/test_retry.py`). Frames that keep a strain, or
#: stretch slowly, do not rise so fast and do not pay for it
RETRY_STRAIN = 0.05
#: see `RETRY_STRAIN` (a strain difference: 0.03 is 3 %)
RETRY_STRAIN_RISE = 0.03

#: after a frame that ran again, the next frames run without a recorded graph until this many
#: in a row needed no retry (each retry drops the graph; recording one costs several frames)
RETRY_EAGER_FRAMES = 8


def _clock(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


class _Progress:
    """A one-line progress bar on stderr: frames done, rate and time remaining.

    The rate (and so the time remaining) counts from the third frame on, after the first
    frame's compile and the graph recording."""

    def __init__(self, total: int, enabled: bool, label: str):
        self.total, self.enabled, self.label = total, enabled, label
        self.t0 = _time.perf_counter()
        self._last = 0.0
        self._steady = None  # (time, frames done) when the steady rate starts

    def eta(self, done: int, now: float) -> float | None:
        """Seconds remaining at the steady rate; ``None`` until it is known."""
        if self._steady is None or done <= self._steady[1] or now <= self._steady[0]:
            return None
        rate = (done - self._steady[1]) / (now - self._steady[0])
        return (self.total - done) / rate

    def note(self, msg: str):
        """A line on stderr above the bar (the bar is drawn again on its next update)."""
        if self.enabled:
            sys.stderr.write("\r\033[K")
        sys.stderr.write(msg + "\n")
        sys.stderr.flush()
        self._last = 0.0

    def update(self, done: int):
        if not self.enabled:
            return
        now = _time.perf_counter()
        if self._steady is None and done >= min(3, self.total):
            self._steady = (now, done)
        if done < self.total and now - self._last < 0.1:
            return
        self._last = now
        w = 30
        fill = int(w * done / max(self.total, 1))
        rate = done / max(now - self.t0, 1e-9)
        eta = self.eta(done, now)
        left = f", {_clock(eta)} left" if eta is not None and done < self.total else ""
        sys.stderr.write(
            f"\r{self.label} [{'#' * fill}{'.' * (w - fill)}] {done}/{self.total} frames "
            f"{rate:.1f} frames/s{left}   "
        )
        if done >= self.total:
            sys.stderr.write("\n")
        sys.stderr.flush()


def _check_start(model, state) -> None:
    """`ValueError` if the cloth at ``state`` passes through itself (`Scene.run`): an edge
    crosses a triangle, or two triangles on an edge lie folded flat onto each other
    (`folded_flat_edges`; measured: a jittered 16 x 16 sheet with one inverted triangle froze
    in every response, whole cloth returned to its start, and ended as diverged at frame 3
    under every solver, with no word of the cause)."""
    from .collision.check import SelfIntersectionChecker, folded_flat_edges

    mesh = model.mesh
    flat = folded_flat_edges(state.x.numpy(), mesh.edges, mesh.edge_tris, mesh.triangles)
    if len(flat):
        e = int(flat[0])
        a, b = (int(c) for c in mesh.edges[e])
        t0, t1 = (int(t) for t in mesh.edge_tris[e])
        raise ValueError(
            f"{mesh.name}: the cloth lies folded flat onto itself at the start ({len(flat)} "
            f"edge(s); the first: triangles {t0} and {t1} on edge {a}-{b} overlap in one plane, "
            "an inverted triangle), and self-collision keeps a cloth that starts free of itself "
            "so: fix the mesh or its start positions, or turn self-collision off")

    checker = SelfIntersectionChecker(model.mesh.triangles, model.mesh.edges, model.num_vertices,
                                      device=model.device)
    k = checker(state.x)
    if k:
        e = int(np.flatnonzero(checker.per_edge.numpy())[0])
        a, b = (int(c) for c in model.mesh.edges[e])
        raise ValueError(
            f"{model.mesh.name}: the cloth passes through itself at the start ({k} crossing "
            f"(edge, triangle) pairs; the first edge: vertices {a}-{b}), and self-collision "
            "keeps a cloth that starts free of itself so: start it apart, or turn "
            "self-collision off")


def _check_obstacle_start(model, state, stage) -> None:
    """`ValueError` if a free vertex starts inside an obstacle (deeper than
    `PENETRATION_TOLERANCE`, float rounding of a cloth laid exactly on a surface) (`Scene.run`):
    vertex contact moves a vertex that starts inside out at once, along the nearest face, which
    need not be the way out (measured: a box standing on the floor through a sheet lying 2 mm
    above the floor, its vertices 2 mm inside the box's bottom face, pushed down into the floor
    and back: 60 m/s and 102 % strain under explicit Euler, 259 % under projective dynamics). A
    vertex may start on a surface or within the contact thickness of it (a sheet lying on the
    floor at height 0): that start is pushed out to the thickness as a position change only."""
    contact = getattr(stage, "contact", None)
    if contact is None:
        return
    free = np.flatnonzero(np.asarray(model.inverse_masses) > 0)
    if not len(free):
        return
    sd = np.asarray(contact.signed_distances(state.positions()[free], state.t))
    if not sd.size:
        return
    from .collision.contact import PENETRATION_TOLERANCE

    k, j = np.unravel_index(int(np.argmin(sd)), sd.shape)
    depth = -float(sd[k, j])
    if depth > PENETRATION_TOLERANCE:
        what = _obstacle_words(contact, k)
        inside = int((sd.min(axis=0) < -PENETRATION_TOLERANCE).sum())
        raise ValueError(
            f"{model.mesh.name}: vertex {int(free[j])} starts {1e3 * depth:.2f} mm inside "
            f"obstacle {k} ({what}; {inside} vertices start inside an obstacle); contact would "
            "throw such a cloth out of it: start the cloth outside the obstacles (on a surface "
            "or within the contact thickness of it is fine)")


def _obstacle_words(contact, k: int) -> str:
    """Obstacle ``k`` of an `ObstacleContact` by kind and name, for messages."""
    ob = contact.obstacles[k]
    return f"{type(ob).__name__} {getattr(ob, 'name', None) or k}"


class _PinnedInside:
    """The pinned vertices inside an obstacle (deeper than `PENETRATION_TOLERANCE`), measured
    on the host once a frame (`Scene.run`): a pin follows its target and contact does not move
    it, so a path that drives one into an obstacle (or an obstacle that passes one) pulls the
    cloth beside it in, and running the frame again with more steps changes nothing (measured:
    a sheet whose pinned corner a rising floor passed ran each frame three times, 16-19 s a
    frame, with no word of the pins). Call with the frame's positions (simulation frame) and
    time: ``None`` or ``(count, depth m, obstacle index, vertex)``."""

    def __init__(self, model, contact):
        from .collision.contact import PENETRATION_TOLERANCE

        self.tolerance = PENETRATION_TOLERANCE
        self.contact = contact
        used = np.zeros(model.num_vertices, dtype=bool)
        used[np.asarray(model.mesh.triangles).reshape(-1)] = True
        self.pins = np.flatnonzero((np.asarray(model.inverse_masses) == 0) & used)

    def __call__(self, x, t: float):
        sd = np.asarray(self.contact.signed_distances(np.asarray(x)[self.pins], t))
        if not sd.size or sd.min() >= -self.tolerance:
            return None
        k, j = np.unravel_index(int(np.argmin(sd)), sd.shape)
        return (int((sd.min(axis=0) < -self.tolerance).sum()), -float(sd[k, j]), int(k),
                int(self.pins[j]))

    def describe(self, found) -> str:
        n, depth, k, v = found
        return (f"{n} pinned vertex(es) inside an obstacle, the deepest {1e3 * depth:.3g} mm "
                f"(vertex {v}, obstacle {k}: {_obstacle_words(self.contact, k)}): a pin follows its target and contact does "
                "not move it, so the cloth beside it is pulled in (its frames are not run again "
                "for that); keep the pins' targets outside the obstacles")


class Scene:
    """A runnable scene.

    Args:
        model: the `ClothModel`.
        solver: a solver built on ``model`` (any of `warp_cloth.solvers`).
        fps: output frames per second.
        frames: number of frames written, including frame 0 (the initial state).
        substeps: solver steps per frame; ``None`` asks the solver (`suggest_substeps`), which for
            the explicit solver derives it from its stability bound, and, with moving obstacles,
            takes at least enough that none travels more than a quarter of the cloth's shortest
            edge in a step (`CollisionStage.contact_substeps`).
        obstacles: obstacles for a solver without a collision stage: the runner gives the
            solver a `CollisionStage` with them (default contact options), so they are
            simulated and drawn. A solver with a stage is drawn with the stage's obstacles;
            giving others here then raises `ValueError` (obstacles are given in one place).
        strain_bound: the divergence guard stops the run when a mesh edge's stretch
            ``l/L - 1`` exceeds this (default 10, i.e. 1000 %); ``inf`` disables it.
        capture: replay each frame's substeps as a recorded Warp graph when the solver allows.
        name: a label for progress output.
        retries: with a collision stage, a frame in which a step failed (self-collision
            returned the whole cloth to its start or held most of it in rigid impact zones, the
            collision response over-stretched an edge, `collision.stage.STRETCH_AFTER`, or
            contacts were
            dropped for want of room, `CollisionStage.frame_end`) runs again from
            its start with twice the steps, then four times, up to ``retries`` times (default
            2; 0: off), self-collision responding after every step; the failed attempts are
            reported as notes, a last attempt that fails too as a warning, and the frames run
            again are counted (``RunStats.retried_frames``; their time is in ``wall_s``). Costs
            a copy of the state a frame. Measured: the twist at one step a frame (PD) froze from
            frame 179 (every step returned to its start while the pins turned on) and diverged
            at frame 211; with retries 102 of 300 frames ran again with 2 steps, all resolved.
    """

    #: an attached `warp_cloth.ledger.EnergyLedger` (told each frame written), or None
    _ledger = None

    def __init__(self, model, solver, *, fps: float = 60.0, frames: int = 120, substeps=None,
                 obstacles=(), strain_bound: float = 10.0, capture: bool = True,
                 name: str = "scene", retries: int = DEFAULT_RETRIES):
        if not hasattr(solver, "model") or not hasattr(solver, "step"):
            raise ValueError(f"Scene(model, solver): solver must be a warp_cloth solver "
                            f"(make_solver), got {type(solver).__name__}")
        if solver.model is not model:
            raise ValueError("the solver was built for a different model")

        fps = float(check_number(fps, "fps"))
        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"fps must be positive, got {fps}")
        if check_number(frames, "frames", True) < 1:
            raise ValueError(f"frames must be a positive integer, got {frames}")
        if substeps is not None and check_number(substeps, "substeps", True) < 1:
            raise ValueError(f"substeps must be a positive integer, got {substeps}")
        if substeps is not None and substeps > MAX_SUBSTEPS:
            # (10**9 substeps ran on for minutes: a hang, not a run)
            raise ValueError(f"substeps must be at most {MAX_SUBSTEPS}, got {substeps}")
        if not (check_number(strain_bound, "strain_bound") > 0):
            raise ValueError(f"strain_bound must be > 0, got {strain_bound}")
        # the obstacles first: a stage made here from them sets the substeps like any other
        drawn = _scene_obstacles(model, solver, obstacles)
        given = substeps
        if substeps is None:
            substeps = suggest_substeps(solver, 1.0 / fps)
            if substeps > MAX_SUBSTEPS:
                raise ValueError(
                    f"the {solver.name} solver needs {substeps} substeps per frame at {fps:g} fps "
                    f"to stay stable (more than {MAX_SUBSTEPS}); raise fps or give substeps")
            stage = getattr(solver, "collision", None)
            if stage is not None and hasattr(stage, "contact_substeps"):
                # moving obstacles: no more than a quarter of a cloth edge of travel in a step
                need = stage.contact_substeps(fps, int(frames))
                if need > MAX_SUBSTEPS:
                    raise ValueError(
                        f"an obstacle moves so fast that contact needs {need} substeps per frame "
                        f"at {fps:g} fps (more than {MAX_SUBSTEPS}: it travels more than "
                        f"{MAX_SUBSTEPS // 4} of the cloth's shortest edges in a frame); raise "
                        "fps or give substeps")
                substeps = max(substeps, need)
        stage = getattr(solver, "collision", None)
        if stage is not None and hasattr(stage, "plan"):
            stage.plan(int(substeps))  # self-collision spans end with the frames
        self.model, self.solver = model, solver
        self.fps, self.frames, self.substeps = fps, int(frames), int(substeps)
        self.dt = 1.0 / (fps * self.substeps)
        if not (MIN_DT <= self.dt <= MAX_DT):
            # float32 cannot hold dt^2 or 1 / dt^2 beyond these (fps = 1e200: a division by
            # zero in the implicit, PBD and PD steps; fps = 1e-40: non-finite positions)
            raise ValueError(f"fps {fps:g} with {self.substeps} substeps gives a step of "
                             f"{self.dt:.3g} s, outside [{MIN_DT:g}, {MAX_DT:g}] s")
        self.obstacles = drawn
        self.strain_bound = float(strain_bound)
        self.capture = capture
        self.name = name
        self.retries = retries
        self._auto_substeps = given is None
        self.state = model.state()

    def reset(self):
        self.state = self.model.state()

    @property
    def retries(self) -> int:
        """How many times a failed frame runs again with more steps (`_stage_frame_end`)."""
        return self._retries

    @retries.setter
    def retries(self, value) -> None:
        if (isinstance(value, bool) or not isinstance(value, (int, np.integer))
                or not 0 <= value <= 8):
            raise ValueError(f"retries must be an integer in [0, 8], got {value!r}")
        self._retries = int(value)

    def _solve_stretched(self, state, snap, meter, short0):
        """``(start, end)`` strains when the solver left a step of this attempt short of its
        tolerance (its ``short_steps_total`` past ``short0``) and the frame's largest edge strain
        ended above `RETRY_STRAIN` and more than `RETRY_STRAIN_RISE` above its start's; else
        None (no host read when no step was short)."""
        short = getattr(self.solver, "short_steps_total", None)
        if meter is None or snap is None or short is None or short <= short0:
            return None
        s1 = meter(state, energy=False).max_strain
        if not s1 > RETRY_STRAIN:
            return None
        s0 = meter(snap, energy=False).max_strain
        return (s0, s1) if s1 - s0 > RETRY_STRAIN_RISE else None

    def _stage_frame_end(self, stage, state, snap, meter=None, short0: int = 0,
                         pinned: bool = False):
        """The collision stage's report on the frame just run (`CollisionStage.frame_end`), and
        the frame run again from ``snap`` (its start) with twice the steps, up to ``retries``
        times, while a step of it returned the whole cloth to its start or dropped contacts, or
        its impact zones held most of the cloth (``stage.frame_failed``), or the solver left a
        step short of its tolerance with the cloth stretched past `RETRY_STRAIN` in the frame
        (``meter`` measures it; ``short0``: the solver's short steps before the frame), unless
        ``pinned``: a pinned vertex is inside an obstacle (`_PinnedInside`: more steps do not
        move it);
        self-collision then responds after every step (no spans). Returns the times it ran again
        and ``(kind, message, regrown)`` triples to report (the attempts that failed as
        notes)."""
        out = [("warning", msg, regrown) for msg, regrown in stage.frame_end()]
        k, n = 0, self.substeps
        stretched = self._solve_stretched(state, snap, meter, short0)
        while snap is not None and k < self.retries and not pinned and (
                getattr(stage, "frame_failed", 0) or stretched is not None):
            k += 1
            n = self.substeps << k
            out = [("note", msg, regrown) for _, msg, regrown in out]
            if stretched is not None:
                out.append(("note", f"{self.solver.name}: a step ended short of its tolerance "
                            f"with the cloth stretched to {100 * stretched[1]:.3g} % "
                            f"({100 * stretched[0]:.3g} % at the frame's start)", False))
            out.append(("note", f"run again from its start with {n} steps", False))
            short0 = getattr(self.solver, "short_steps_total", 0)
            state.assign(snap)
            stage.restart_span()  # no span, hold or carried sag from the failed attempt
            motion, stage.self_motion = stage.self_motion, 0.0
            try:
                stage.plan(n)
            finally:
                stage.self_motion = motion
            for _ in range(n):
                self.solver.step(state, self.dt * self.substeps / n)
            out += [("warning", msg, regrown) for msg, regrown in stage.frame_end()]
            stretched = self._solve_stretched(state, snap, meter, short0)
        if stretched is not None and k:
            out.append(("warning", f"{self.solver.name}: with {n} steps too, a step ended short "
                        f"of its tolerance with the cloth stretched to {100 * stretched[1]:.3g} % "
                        f"({100 * stretched[0]:.3g} % at the frame's start)", False))
        if k:
            stage.plan(self.substeps)
        return k, out

    def run(self, out: str | os.PathLike | None = None, *, quiet: bool = False,
            progress: bool | None = None, energy: bool = True, on_frame=None,
            save_interval: float = 2.0, check_intersections: bool = False) -> RunStats:
        """Run from the initial state; write ``out`` (a ``.usd``) if given.

        The file is saved every ``save_interval`` seconds of wall time (0: after every frame) and
        when the run ends for any reason; it is readable at every moment (`warp_cloth.usd`).
        An unwritable ``out`` raises `warp_cloth.usd.OutputError`.

        ``check_intersections``: count every frame's crossing (edge, triangle) pairs of the cloth
        (`warp_cloth.collision.check.SelfIntersectionChecker`) into ``RunStats.crossing_frames``
        and ``max_crossings``, and the cloth against the obstacles
        (`warp_cloth.collision.check.ObstacleChecker`: edge points inside an analytic obstacle,
        edges through a mesh obstacle, the least clearance of a free vertex) into
        ``obstacle_frames``, ``obstacle_depth`` and ``min_clearance``, with a warning on stderr
        for each frame that has any crossing or point inside (unless ``quiet``). Whatever the
        option, a frame in which self-collision had to return the
        whole cloth to its start, or dropped contacts for want of room, is reported on stderr
        (unless ``quiet``); room then grows, the frame graph is recorded again, and the frame
        runs again with more steps (``retries``).

        Raises `SimulationDiverged` when a frame has a non-finite position or an edge strain above
        ``strain_bound``, or after `FROZEN_FRAMES` frames in a row whose self-collision held
        most of the cloth in rigid impact zones or returned the whole cloth to its start in
        most of its steps; the USD file then holds the frames before it.
        ``on_frame(frame, state)`` is called after each frame is checked (for custom
        recording; ``state.x`` is in the model's simulation frame, `State.world_positions` in
        the world's: they differ for a cloth far from the origin, `ClothModel.origin`). With self-collision, a cloth that passes through itself at the start raises
        `ValueError` (naming an edge and a triangle) before anything is written:
        self-collision keeps an intersection-free cloth so, and cannot make one (such a start
        held every step at its start: a frozen cloth).
        Likewise a free vertex that starts inside an obstacle (more than 0.1 mm; on a surface or
        within the contact thickness of it is fine: `_check_obstacle_start`).
        """
        from .usd import UsdWriter

        t_start = _time.perf_counter()
        self.reset()
        state, solver, model = self.state, self.solver, self.model
        stage = getattr(solver, "collision", None)
        if getattr(stage, "self_collision", None) is not None:
            _check_start(model, state)
        if stage is not None:
            _check_obstacle_start(model, state, stage)
        meter = Meter(model)
        if progress is None:
            progress = (not quiet) and sys.stderr.isatty()
        bar = _Progress(self.frames, progress, self.name)
        stable = getattr(solver, "stable_dt", None)
        if stable is not None and not quiet:
            # explicit Euler given more than its stable step (`--substeps`): say so before it
            # diverges (a step past the bound grows every mode above it each step)
            sdt = float(stable(model))
            if math.isfinite(sdt) and self.dt > sdt:
                need = suggest_substeps(solver, 1.0 / self.fps)
                bar.note(f"warning: {solver.name}: its step {self.dt:.3g} s is "
                         f"{self.dt / sdt:.3g} times its stability bound {sdt:.3g} s: it will "
                         f"diverge; {need} steps a frame keep it stable (leave the substeps "
                         "to the solver)")
            why = getattr(solver, "stiffest", None)
            if self._auto_substeps and self.substeps > MANY_SUBSTEPS and why is not None:
                bar.note(f"note: {solver.name}: {self.substeps} steps a frame: "
                         f"{_stiffest_words(why(model), 1.0 / self.fps)}")
        writer = None
        mesh_path = None
        if out is not None:
            writer = UsdWriter(out, fps=self.fps, up_axis=model.up_axis,
                               save_interval=save_interval)
            mesh_path = writer.add_mesh(model.mesh.name, model.mesh.triangles)
            for ob in self.obstacles:
                writer.add_obstacle(ob)
        up = model.up_index  # heights along the mesh's up axis
        checker = None
        crossing_frames, max_crossings = 0, 0
        short_frames = 0
        if check_intersections:
            from .collision.check import SelfIntersectionChecker

            checker = SelfIntersectionChecker(model.mesh.triangles, model.mesh.edges,
                                              model.num_vertices, device=model.device)
        ob_checker = None
        ob_frames, ob_depth, clearance = 0, 0.0, float("inf")
        if check_intersections and self.obstacles:
            from .collision.check import ObstacleChecker

            # in the simulation frame, as the state (`ClothModel.origin`)
            sim = getattr(stage, "sim_obstacles", self.obstacles)
            ob_checker = ObstacleChecker(sim, model.mesh.edges,
                                         model.inverse_masses > 0, device=model.device)
        stage = getattr(solver, "collision", None)
        if stage is not None and hasattr(stage, "restart_span"):
            stage.restart_span()
        pinned_probe = None
        if getattr(stage, "contact", None) is not None and len(model.pins):
            pinned_probe = _PinnedInside(model, stage.contact)
        pinned_frames, pinned_depth, pinned_before = 0, 0.0, False
        graph = None
        no_graph = False
        # the frame's start, kept while self-collision (or contact) can fail a step (`retries`)
        snap = state.clone() if (self.retries and hasattr(stage, "plan")) else None
        retried_frames = 0
        collision_frames = 0
        frozen = 0  # frames in a row whose impact zones held most of the cloth
        locked = 0  # of them, frames that froze run again with the most steps too
        eager_until = 0  # no graph recorded before this frame (after a retry)
        recorded = False  # a graph was recorded (the next recordings are run time)
        wall = 0.0
        first = 0.0
        timed = 0
        max_strain = 0.0
        lo, hi = math.inf, -math.inf
        try:
            t_setup = _time.perf_counter()
            m0 = meter(state, energy=energy)  # compiles the diagnostics on a cold cache
            setup = _time.perf_counter() - t_setup
            e0 = m0.energy
            mfin = m0
            for msg, _ in (stage.cloth_stretched(m0.max_strain)  # a cloth that starts stretched
                           if hasattr(stage, "cloth_stretched") else ()):
                if not quiet:
                    bar.note(f"note: frame 0: {msg}")
            for frame in range(self.frames):
                if frame > 0:
                    t0 = _time.perf_counter()
                    if snap is not None:
                        snap.assign(state)  # the frame's start, should it run again
                    short0 = getattr(solver, "short_steps_total", 0)
                    recording = False
                    if graph is not None:
                        _replay(graph)
                    elif (frame >= 2 and self.capture and solver.capturable and not no_graph
                          and frame >= eager_until):
                        recording = True
                        try:
                            graph = _record_frame(solver, state, self.dt, self.substeps,
                                                  model.device)
                        except Exception as e:  # noqa: BLE001 - any capture failure: run eagerly
                            # e.g. a device whose driver cannot record conditional graph nodes
                            # (wp.capture_while needs CUDA 12.4+): recorded launches did not run
                            no_graph = True
                            if not quiet:
                                bar.note(f"warning: frame {frame}: recording the frame as a Warp "
                                         f"graph failed ({type(e).__name__}: {e}); running "
                                         "without a graph")
                            for _ in range(self.substeps):
                                solver.step(state, self.dt)
                        else:
                            _replay(graph)
                    else:
                        for _ in range(self.substeps):
                            solver.step(state, self.dt)
                    pinned = None
                    if pinned_probe is not None:  # pins inside an obstacle (a host read)
                        pinned = pinned_probe(state.x.numpy(), frame / self.fps)
                        if pinned is not None:
                            pinned_frames += 1
                            pinned_depth = max(pinned_depth, pinned[1])
                            if not quiet and not pinned_before:  # once a stretch of frames
                                bar.note(f"warning: frame {frame}: "
                                         f"{pinned_probe.describe(pinned)}")
                        pinned_before = pinned is not None
                    if stage is not None:
                        # what the stage reports (host reads), and the frame run again with more
                        # steps where a step of it failed (`_stage_frame_end`)
                        retried, msgs = self._stage_frame_end(stage, state, snap, meter, short0,
                                                              pinned is not None)
                        retried_frames += retried > 0
                        collision_frames += any(kind == "warning" and msg is not None
                                                for kind, msg, _ in msgs)
                        for kind, msg, regrown in msgs:
                            if not quiet and msg is not None:
                                bar.note(f"{kind}: frame {frame}: {msg}")
                            if regrown:
                                graph = None  # arrays were reallocated: record the graph again
                        if retried:
                            # steps of another dt ran (set-up the graph holds may have been
                            # redone): the graph is recorded again, after `RETRY_EAGER_FRAMES`
                            # frames without a retry (a stretch of retries records no graphs)
                            graph = None
                            eager_until = frame + 1 + RETRY_EAGER_FRAMES
                    mfin = meter(state, energy=energy)
                    # a cloth stretched past what the obstacles' sharp features were chosen for
                    # gets them chosen again (`CollisionStage.cloth_stretched`)
                    for msg, regrown in (stage.cloth_stretched(mfin.max_strain)
                                         if hasattr(stage, "cloth_stretched") else ()):
                        if not quiet:
                            bar.note(f"note: frame {frame}: {msg}")
                        if regrown:
                            graph = None
                    dtw = _time.perf_counter() - t0
                    if frame == 1:
                        first = dtw
                        setup += dtw
                    elif recording and not recorded:  # the first recording is set-up
                        setup += dtw
                        recorded = True
                    else:
                        wall += dtw
                        timed += 1
                    if math.isfinite(mfin.max_strain):
                        max_strain = max(max_strain, mfin.max_strain)
                    if not mfin.finite:
                        raise SimulationDiverged(frame, solver.name, max_strain, "non-finite positions")
                    if mfin.max_strain > self.strain_bound:
                        raise SimulationDiverged(frame, solver.name, max_strain,
                                                 f"strain bound {self.strain_bound:g} exceeded")
                    frozen_now = getattr(stage, "frame_frozen", False)
                    frozen = frozen + 1 if frozen_now else 0
                    # frozen frames that still froze run again with the most steps
                    locked = locked + 1 if frozen_now and self.retries > 0 and stage is not None \
                        and retried == self.retries else 0
                    if frozen >= FROZEN_FRAMES:
                        why = ("its steps tangle the cloth everywhere: an unstable step; more "
                               "substeps, or a smaller step, hold it")
                        if getattr(stage, "frame_diverged", False):
                            # (`self_collision.DIVERGED_STRAIN`: measured, explicit Euler at
                            # one step a frame at 24 fps on the hanging sheet, 231 times its
                            # stable step: 40-100 s a frame before, 6 s to this message)
                            why = (f"the solver's steps diverged: they stretched a mesh edge "
                                   f"past 1,000 % or left a position not finite before the "
                                   f"collision response, with up to "
                                   f"{self.substeps << self.retries} steps a frame too; explicit "
                                   "Euler: let it choose its substeps, or a smaller step")
                        elif locked >= FROZEN_FRAMES:
                            # (the 16 x 16 twist from frame 287 under implicit Euler, with 8
                            # times the steps too; the default 49 x 49 runs through)
                            why = (f"run again with up to {self.substeps << self.retries} "
                                   "steps, each froze too: a step still far past the solver's "
                                   "stable one (explicit Euler: let it choose its substeps), or "
                                   "a cloth locked by its own layers, which cannot stay a "
                                   "thickness apart as it is driven on (a twist wound tight on a "
                                   "coarse mesh: a finer mesh goes further)")
                        raise SimulationDiverged(
                            frame, solver.name, max_strain,
                            f"self-collision froze the cloth (most of it in rigid impact zones, "
                            f"or the whole cloth returned to its start in most steps) for "
                            f"{frozen} frames in a row ({why})")
                if frame > 0 and hasattr(solver, "frame_end"):
                    msgs = solver.frame_end()
                    short_frames += any(not isinstance(msg, Note) for msg in msgs)
                    for msg in msgs if not quiet else ():
                        kind = "note" if isinstance(msg, Note) else "warning"
                        bar.note(f"{kind}: frame {frame}: {msg}")
                if checker is not None:
                    k = checker(state.x)
                    if k:
                        crossing_frames += 1
                        max_crossings = max(max_crossings, k)
                        if not quiet:
                            bar.note(f"warning: frame {frame}: the cloth passes through itself "
                                     f"({k} crossing edge-triangle pairs)")
                x = state.x.numpy()
                if ob_checker is not None:
                    k, deep, clear = ob_checker(x, frame / self.fps)
                    clearance = min(clearance, clear)
                    if k:
                        ob_frames += 1
                        ob_depth = max(ob_depth, deep)
                        if not quiet:
                            bar.note(f"warning: frame {frame}: the cloth is inside an obstacle "
                                     f"({k} edge points or edges; deepest point "
                                     f"{1e3 * deep:.3f} mm)")
                lo = min(lo, float(x[:, up].min()) + float(model.origin[up]))
                hi = max(hi, float(x[:, up].max()) + float(model.origin[up]))
                if writer is not None:  # in the world frame
                    writer.write_frame(frame, {mesh_path: model.to_world(x)},
                                       sim_time=frame / self.fps)
                if on_frame is not None:
                    on_frame(frame, state)
                if self._ledger is not None:  # `warp_cloth.ledger.EnergyLedger`: the next steps
                    self._ledger.frame_done(frame)
                bar.update(frame + 1)
        finally:
            if writer is not None:
                writer.close()
        ms_frame = 1e3 * wall / timed if timed else 1e3 * first
        return RunStats(
            method=solver.describe(), frames=self.frames, fps=self.fps, substeps=self.substeps,
            dt=self.dt, wall_s=wall, first_frame_s=first, total_s=_time.perf_counter() - t_start,
            ms_per_frame=ms_frame, ms_per_substep=ms_frame / self.substeps, max_strain=max_strain,
            final_max_strain=mfin.max_strain, min_height=lo, max_height=hi, energy_initial=e0,
            energy_final=mfin.energy, captured=graph is not None, timed_frames=timed,
            setup_s=setup,
            out=os.fspath(out) if out is not None else None, extra=dict(solver.stats),
            crossing_frames=crossing_frames if checker is not None else None,
            max_crossings=max_crossings if checker is not None else None,
            obstacle_frames=ob_frames if ob_checker is not None else None,
            obstacle_depth=ob_depth if ob_checker is not None else None,
            min_clearance=clearance if ob_checker is not None else None,
            short_frames=short_frames, retried_frames=retried_frames,
            collision_frames=collision_frames, pinned_inside_frames=pinned_frames,
            pinned_depth=pinned_depth,
        )


#: a solver whose steps all record the same launches (``uniform_steps``) has a frame recorded
#: as a graph of this many steps (and one of the frame's remaining steps), replayed through the
#: frame: recording costs a few steps instead of the frame's (measured, the explicit hanging
#: scene with self-collision, 185 steps a frame: 1.6 s to record the whole frame), replaying
#: costs a call per graph
GRAPH_BLOCK = 16


def _record_frame(solver, state, dt: float, substeps: int, device) -> list:
    """A frame's ``substeps`` steps recorded as Warp graphs: ``[(graph, times), ...]`` to replay
    in order (`_replay`). Nothing runs while recording."""
    block = substeps
    if getattr(solver, "uniform_steps", False):
        block = min(substeps, GRAPH_BLOCK)
    parts = []
    for steps, times in ((block, substeps // block), (substeps % block, 1)):
        if steps == 0:
            continue
        with wp.ScopedCapture(device=device, force_module_load=False) as cap:
            for _ in range(steps):
                solver.step(state, dt)
        parts.append((cap.graph, times))
    return parts


def _replay(parts) -> None:
    """One frame: the graphs of `_record_frame`, each as many times as it says."""
    for graph, times in parts:
        for _ in range(times):
            wp.capture_launch(graph)


def _scene_obstacles(model, solver, obstacles) -> list:
    """The obstacles to draw: the solver's collision stage's (made here from ``obstacles`` when
    the solver has none)."""
    from .util import obstacle_list

    obstacles = obstacle_list(obstacles if obstacles is not None else (), "Scene")
    stage = getattr(solver, "collision", None)
    if stage is None:
        if obstacles:
            from .collision import CollisionStage

            solver.set_collision(CollisionStage(model, obstacles))
            stage = solver.collision
        else:
            return []
    elif obstacles:
        known = {id(ob) for ob in stage.obstacles}
        extra = [k for k, ob in enumerate(obstacles) if id(ob) not in known]
        if extra:
            raise ValueError(f"obstacles{extra} given to the Scene are not in the solver's "
                             "collision stage: give every obstacle to the CollisionStage only "
                             "(the scene draws the stage's obstacles)")
    return stage.obstacles


def _stiffest_words(found, frame_dt: float) -> str:
    """`Scene.run`'s note on what sets explicit Euler's many steps (`SymplecticEuler.stiffest`)."""
    if found is None:
        return "its stable step is small"
    out = f"vertex {found['vertex']}'s {found['term']} sets the stable step"
    if found["min_angle"] < 5.0:
        out += (f" (a triangle there has a {found['min_angle']:.2g}-degree angle: a sliver, "
                "whose bending stiffness grows as one over its angle)")
    sdt = found["springs_dt"]
    if found["term"] != "springs":
        spring_steps = 1 if not math.isfinite(sdt) else max(1, math.ceil(frame_dt / (0.5 * sdt)))
        out += (f"; the springs alone would take {spring_steps}. Mend the mesh, or a softer or "
                "other bending, or implicit Euler or projective dynamics (large steps)")
    else:
        out += "; implicit Euler or projective dynamics take large steps"
    return out


def suggest_substeps(solver, frame_dt: float) -> int:
    """Substeps per frame: the solver's own suggestion, else 1.

    The explicit solver asks for ``ceil(frame_dt / (0.5 * stable_dt))`` (half its Gershgorin
    stability bound); the implicit methods are unconditionally stable and default to their
    ``default_substeps`` attribute.
    """
    fn = getattr(solver, "suggest_substeps", None)
    if fn is not None:
        return max(1, int(fn(frame_dt)))
    return max(1, int(getattr(solver, "default_substeps", 1)))
