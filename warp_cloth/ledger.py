"""Where a step's energy goes: a diagnostic that splits each step's energy change by stage.

A step (`Solver.step`) runs its method's update (the solve), then the corrections (strain and
area limits), then the collision stage's response (`CollisionStage.resolve`): vertex contact with
the obstacles, the cloth's edges and triangles against the meshes' sharp features (friction, then
the response), vertex contact again, and self-collision. Each of these can add or remove energy;
the scene's frame-to-frame energy shows only their sum. `EnergyLedger` measures the cloth's energy
(kinetic + gravity + springs + bending: `diagnostics.Meter`) before and after each stage of every
step of the frames asked for, so a rise is traced to the stage that made it:

    from warp_cloth.scenes import build_scene
    from warp_cloth.ledger import EnergyLedger

    scene = build_scene("table", solver="implicit")
    ledger = EnergyLedger(scene, frames=(42, 44))
    scene.run()                      # eager while attached (no graphs: each stage is measured)
    print(ledger.report())

or ``warp-cloth run table --solver implicit --ledger 42:44``. Rows: ``solve`` (the method's
update), ``limit NAME`` (each correction), ``obstacle contact`` (each call: the second is the
pass after the features), ``feature friction``, ``feature response``, ``self-collision`` (the
hold of the last response's contacts between responses) and ``self-collision response``, and
``other`` (what the step did outside them: scripted pins).
A stage run inside another is its own row and the outer row keeps the rest (explicit Euler runs the
features inside its step; its obstacle contact, fused into its vertex update, is in ``solve``).
A frame run again (`Scene.retries`) has the steps of every attempt (the return to the frame's
start between attempts is no step, in no row). Each measurement is a few
launches and a host read: a diagnostic, not for timing (the scene records no graphs while a
ledger is attached).

Measured with it (2026-11-25, before the scenes had bending: ``bending="none"`` now): on the
``table`` under implicit Euler the largest one-frame rise
(frame 43, 1.4e-3 J) came from self-collision's response (+4.2e-3 and +3.5e-3 J of spring energy
in the frame's two steps: it pushes out of the thickness the layers the solve's penalty left
sagging) and from the vertex contact after the features (+1.6e-3 J: feature friction had slowed a
vertex sliding along the table's edge, and the contact's friction then moved it back by a share
of its whole step, 1.4 mm), while the solve itself lost 3.4e-3 and 4.5e-3 J.
"""

from __future__ import annotations

from collections import OrderedDict

from .diagnostics import Meter

__all__ = ["EnergyLedger"]


class EnergyLedger:
    """Per-stage energy changes of every step of ``scene`` in frames ``frames = (first, last)``
    (inclusive; frame ``f`` is the steps that lead from written frame ``f - 1`` to ``f``).

    Attaching wraps the stages' methods on the scene's own objects (nothing else is touched) and
    turns the scene's graph recording off; `detach` restores both. ``rows``: one
    ``(frame, step, parts, total)`` per step, ``parts`` an ordered ``{stage: dE}`` (J).
    """

    def __init__(self, scene, frames=(1, 1)):
        if getattr(scene, "_ledger", None) is not None:
            raise ValueError("EnergyLedger: this scene already has a ledger attached; detach it "
                             "first")
        try:
            first, last = frames
            ok = all(int(f) == f and not isinstance(f, bool) for f in (first, last))
        except (TypeError, ValueError):
            ok = False
        if not ok or first < 1 or last < first:
            raise ValueError(f"EnergyLedger: frames must be (first, last) with 1 <= first <= last, "
                             f"got {frames!r}")
        self.scene = scene
        self.frames = (int(first), int(last))
        self.meter = Meter(scene.model)
        self.rows = []
        self._frame = 1  # the frame whose steps run now
        self._parts = None
        self._nested = []
        self._wrapped = []
        self._capture = scene.capture
        self.attach()

    # ------------------------------------------------------------------ wrapping
    def _energy(self, state) -> float:
        return self.meter(state, energy=True).energy

    def _wrap(self, obj, name: str, label: str) -> None:
        inner = getattr(obj, name)
        ledger = self

        def measured(state, *args, **kwargs):
            if ledger._parts is None:
                return inner(state, *args, **kwargs)
            e0 = ledger._energy(state)
            ledger._nested.append(0.0)  # what the stages inside this one change
            try:
                out = inner(state, *args, **kwargs)
            finally:
                inside = ledger._nested.pop()
            change = ledger._energy(state) - e0
            parts = ledger._parts
            # a stage run inside another (explicit Euler's step runs the features' response) is
            # its own row, and the outer one's row is what is left
            parts[label] = parts.get(label, 0.0) + change - inside
            if ledger._nested:
                ledger._nested[-1] += change
            return out

        had = name in vars(obj)
        self._wrapped.append((obj, name, inner if had else None))
        setattr(obj, name, measured)

    def attach(self) -> None:
        solver = self.scene.solver
        self._wrap(solver, "_advance", "solve")
        for c in solver.corrections:
            self._wrap(c, "apply", f"limit {type(c).__name__}")
        stage = getattr(solver, "collision", None)
        if stage is not None:
            if getattr(stage, "contact", None) is not None:
                self._wrap(stage.contact, "apply", "obstacle contact")
            features = getattr(stage, "features", None)
            if features is not None:
                self._wrap(features, "friction", "feature friction")
                self._wrap(features, "respond", "feature response")
            if getattr(stage, "self_collision", None) is not None:
                # the response (detection rounds, impact zones) apart from what runs between
                # responses (`hold`, the spans' bookkeeping), which stays "self-collision"
                self._wrap(stage.self_collision, "step", "self-collision")
                self._wrap(stage.self_collision, "resolve", "self-collision response")
        inner_step = solver.step
        ledger = self

        def step(state, dt):
            first, last = ledger.frames
            if not first <= ledger._frame <= last:
                return inner_step(state, dt)
            ledger._parts = OrderedDict()
            e0 = ledger._energy(state)
            try:
                inner_step(state, dt)
            finally:
                parts, ledger._parts = ledger._parts, None
            total = ledger._energy(state) - e0
            parts["other"] = total - sum(parts.values())
            n = sum(1 for r in ledger.rows if r[0] == ledger._frame)
            ledger.rows.append((ledger._frame, n, parts, total))

        self._wrapped.append((solver, "step", inner_step if "step" in vars(solver) else None))
        solver.step = step
        self.scene.capture = False  # every step through Python, so that each stage is measured
        # the runner's per-frame callback tells which frame the next steps belong to
        self.scene._ledger = self

    def frame_done(self, frame: int) -> None:
        """Called by `Scene.run` after frame ``frame`` is written: the next steps are frame + 1."""
        self._frame = frame + 1

    def detach(self) -> None:
        """Restore the wrapped methods and the scene's graph recording."""
        for obj, name, inner in reversed(self._wrapped):
            if inner is None:
                delattr(obj, name)
            else:
                setattr(obj, name, inner)
        self._wrapped = []
        self.scene.capture = self._capture
        if getattr(self.scene, "_ledger", None) is self:
            self.scene._ledger = None

    # ------------------------------------------------------------------ report
    def per_frame(self) -> "OrderedDict[int, tuple[OrderedDict, float, int]]":
        """``{frame: (parts summed over its steps, total, steps)}``."""
        out = OrderedDict()
        for frame, _, parts, total in self.rows:
            acc, tot, n = out.get(frame, (OrderedDict(), 0.0, 0))
            for k, v in parts.items():
                acc[k] = acc.get(k, 0.0) + v
            out[frame] = (acc, tot + total, n + 1)
        return out

    def as_list(self) -> list:
        """The rows as JSON-ready dicts: ``{"frame", "step", "parts": {stage: J}, "total"}``."""
        return [{"frame": f, "step": k, "parts": dict(parts), "total": total}
                for f, k, parts, total in self.rows]

    def report(self) -> str:
        """A text table: per frame, each stage's energy change summed over its steps (J), the
        step with the largest rise, and the frame's total."""
        frames = self.per_frame()
        if not frames:
            return "energy ledger: no step measured (frames outside the run?)"
        labels = []
        for parts, _, _ in frames.values():
            labels += [k for k in parts if k not in labels]
        head = ["frame", "steps"] + labels + ["total", "largest step rise"]
        lines = ["# energy ledger (J; kinetic + gravity + springs + bending, per stage of each "
                 "step)", "", "| " + " | ".join(head) + " |",
                 "|" + "---|" * len(head)]
        for frame, (parts, total, n) in frames.items():
            steps = [r for r in self.rows if r[0] == frame]
            worst = max(steps, key=lambda r: r[3])
            cells = [str(frame), str(n)] + [f"{parts.get(k, 0.0):+.3e}" for k in labels]
            cells += [f"{total:+.3e}", f"{worst[3]:+.3e} (step {worst[1]})"]
            lines.append("| " + " | ".join(cells) + " |")
        return "\n".join(lines)
