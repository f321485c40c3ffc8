"""`RunStats`: the summary of a `Scene.run` (a plain dataclass: importing it loads no Warp, so a
sweep's driver can name its columns without loading the simulator)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

__all__ = ["Note", "RunStats"]


class Note(str):
    """A solver's frame message that reports no shortfall (`Solver.frame_end`): the runner
    prints it as a note and does not count its frame in ``RunStats.short_frames``."""


@dataclass
class RunStats:
    """Summary of a run. Times in seconds; lengths in metres; energies in joules."""

    method: str
    frames: int
    fps: float
    substeps: int
    dt: float
    wall_s: float  # stepping + checks of the timed frames: excludes compile, graph recording, USD I/O
    first_frame_s: float  # first stepped frame, includes compiling the kernels it uses
    total_s: float
    ms_per_frame: float
    ms_per_substep: float
    max_strain: float  # largest mesh-edge stretch l/L - 1 over all frames (compression not counted)
    final_max_strain: float
    min_height: float  # along the model's up axis (mesh.up_axis: y or z), over all frames
    max_height: float
    energy_initial: float
    energy_final: float
    captured: bool
    timed_frames: int = 0  # frames in wall_s (not the first, nor the one that recorded the graph)
    #: set-up inside the run, compiles included: the first measurement (which compiles the
    #: diagnostics), the first frame and the frame that recorded the graph (not USD output)
    setup_s: float = 0.0
    out: str | None = None
    # with ``check_intersections``: frames whose cloth passes through itself, and the most
    # crossing (edge, triangle) pairs in one frame (None: not checked)
    crossing_frames: int | None = None
    max_crossings: int | None = None
    # ... and against the obstacles (`collision.check.ObstacleChecker`; None: not checked or no
    # obstacle): frames with a cloth edge point inside an analytic obstacle or a cloth edge
    # through a mesh obstacle, the deepest such point (m), and the least distance of a free
    # vertex to any obstacle over the frames (m; the promise: the thickness less 1e-4 m)
    obstacle_frames: int | None = None
    obstacle_depth: float | None = None
    min_clearance: float | None = None
    #: frames in which a step stopped short of a tolerance (an unconverged solve, a limit out of
    #: sweeps: `Solver.frame_end`), each reported on stderr with the frame unless quiet
    short_frames: int = 0
    #: frames run again from their start with more steps because a step of theirs failed (its
    #: self-collision returned the whole cloth to its start, or contacts were dropped for want
    #: of room: `Scene`'s ``retries``), each reported on stderr unless quiet
    retried_frames: int = 0
    #: frames whose collision stage reported a failure that its last attempt kept (contacts
    #: dropped for want of room, the whole cloth returned to its start, impact zones holding
    #: most of it, feature contacts left violated, a contact at a pinned vertex: each reported
    #: on stderr unless quiet; `CollisionStage.frame_end`), so that a quiet run (a sweep's, a
    #: benchmark's) still says so
    collision_frames: int = 0
    #: frames that ended with a pinned vertex inside an obstacle (deeper than 0.1 mm), and the
    #: deepest (m): a pin follows its target, contact does not move it (`scene._PinnedInside`;
    #: reported on stderr at the first frame of each stretch unless quiet)
    pinned_inside_frames: int = 0
    pinned_depth: float = 0.0
    extra: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return asdict(self)

    def summary(self) -> str:
        return (
            f"{self.method}: {self.frames} frames x {self.substeps} substeps (dt {self.dt:.3g} s), "
            f"{self.ms_per_frame:.3f} ms/frame, {self.ms_per_substep:.4f} ms/substep "
            f"(set-up incl. compile {self.setup_s:.2f} s, of which first frame "
            f"{self.first_frame_s:.2f} s); max strain "
            f"{100 * self.max_strain:.3f} %, final {100 * self.final_max_strain:.3f} %; height "
            f"[{self.min_height:.3f}, {self.max_height:.3f}] m; energy {self.energy_initial:.4g} -> "
            f"{self.energy_final:.4g} J"
            + ("" if self.crossing_frames is None else
               f"; self-intersection: {self.crossing_frames} of {self.frames} frames "
               f"(at most {self.max_crossings} crossing pairs)")
            + ("" if self.obstacle_frames is None else
               f"; obstacles: cloth inside in {self.obstacle_frames} frames"
               + (f" (deepest {1e3 * self.obstacle_depth:.3f} mm)" if self.obstacle_frames else "")
               + f", least vertex clearance {1e3 * self.min_clearance:.3f} mm")
            + (f"; {self.short_frames} frames with a step short of its tolerance"
               if self.short_frames else "")
            + (f"; {self.retried_frames} frames run again with more steps"
               if self.retried_frames else "")
            + (f"; {self.collision_frames} frames with a collision-stage warning"
               if self.collision_frames else "")
            + (f"; pinned vertices inside an obstacle in {self.pinned_inside_frames} frames "
               f"(deepest {1e3 * self.pinned_depth:.3g} mm)" if self.pinned_inside_frames else "")
            + (f"; wrote {self.out}" if self.out else "")
        )
