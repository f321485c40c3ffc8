"""What every solver shares: argument checks, scripted pins, corrections, the clock.

A step is composed, in this order, of only the parts the scene uses (GUIDE.md):

    pins to their end-of-step targets -> method (external forces + integrator/solver)
    -> corrections (strain/area limits, obstacle contact, self-collision) -> time += dt

Each correction changes positions and adds the same change divided by dt to the velocities
(``v += (x_new - x_old) / dt``, the position-based velocity update of the notes, L1344), so
velocities stay consistent with the positions. A correction is any object with
``apply(state, x_start, dt)``, where ``x_start`` holds the positions at the start of the step
(for continuous collision tests).
"""

from __future__ import annotations

import math

import warp as wp

from . import common


def check_dt(dt) -> float:
    try:
        dt = float(dt)
    except (TypeError, ValueError):
        raise ValueError(f"dt must be a number of seconds, got {dt!r}") from None
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive finite number of seconds, got {dt}")
    return dt


class Solver:
    """Base class. Subclasses implement ``_advance(state, dt)``.

    Args:
        model: the `ClothModel`.
        corrections: objects with ``apply(state, x_start, dt)`` run after the method in the
            given order (limits, contact, self-collision).

    Attributes:
        capturable: True when a step makes no host decision, so a sequence of steps can be
            recorded as a Warp graph and replayed (the scene runner does this).
        stats: per-step statistics of the last step (method-specific keys).
    """

    name = "solver"

    def __init__(self, model, *, corrections=()):
        self.model = model
        self.device = model.device
        self.corrections = [c for c in corrections if c is not None]
        self.capturable = all(getattr(c, "capturable", True) for c in self.corrections)
        self.stats: dict = {}
        self._x_start = (
            wp.zeros(model.num_vertices, dtype=wp.vec3, device=self.device)
            if self.corrections
            else None
        )

    def add_correction(self, c) -> None:
        self.corrections.append(c)
        self.capturable = self.capturable and getattr(c, "capturable", True)
        if self._x_start is None:
            self._x_start = wp.zeros(self.model.num_vertices, dtype=wp.vec3, device=self.device)

    #: True for a solver whose ``_advance`` can run a first correction that is ``fusable``
    #: (obstacle contact) as part of its own vertex update (see `fused`)
    fuses_contact = False

    @property
    def fused(self):
        """The correction this step runs inside the method's vertex update, or None: the first
        correction when the solver `fuses_contact` and the correction is ``fusable`` (it would
        have run first anyway, so the order of corrections is kept)."""
        if self.fuses_contact and self.corrections and getattr(self.corrections[0], "fusable",
                                                                 False):
            return self.corrections[0]
        return None

    def step(self, state, dt: float):
        """Advance ``state`` in place by ``dt`` seconds and return it."""
        dt = check_dt(dt)
        m = self.model
        rest = self.corrections[1:] if self.fused is not None else self.corrections
        if rest:  # a fused contact writes the start positions it needs itself
            wp.copy(self._x_start, state.x)
        if m.pin_path is not None and len(m.pins):
            wp.launch(
                common.move_pins_kernel,
                len(m.pins),
                [state.x, state.v, m.pin_indices, m.pin_times, m.pin_keys, state.time, dt],
                device=self.device,
            )
        self._advance(state, dt)
        for c in rest:
            c.apply(state, self._x_start, dt)
        wp.launch(common.advance_time_kernel, 1, [state.time, dt], device=self.device)
        return state

    def _advance(self, state, dt: float):  # pragma: no cover - abstract
        raise NotImplementedError

    def describe(self) -> str:
        return self.name
