"""The energy ledger (`warp_cloth.ledger`): each stage's energy change, measured, not guessed."""

import numpy as np
import pytest
import warp as wp

from warp_cloth import cli
from warp_cloth.contact_scenes import drape, sheet_model
from warp_cloth.ledger import EnergyLedger
from warp_cloth.scene import Scene
from warp_cloth.solvers import make_solver


class _Lift:
    """A correction that lifts every vertex by ``dy`` metres (a rigid move: only the gravity
    potential changes, by ``M g dy``)."""

    capturable = False

    def __init__(self, dy):
        self.dy = dy

    def apply(self, state, x_start, dt):
        x = state.x.numpy()
        x[:, 1] += self.dy
        state.x.assign(x)


def _free_sheet_scene(correction, frames=4):
    model = sheet_model(res=4, damping=0.0, device="cpu")
    solver = make_solver("explicit", model, corrections=[correction])
    return model, Scene(model, solver, fps=60.0, frames=frames, substeps=3)


def test_a_correction_that_lifts_the_sheet_is_charged_exactly_its_work():
    dy = 1.0e-3
    model, scene = _free_sheet_scene(_Lift(dy))
    ledger = EnergyLedger(scene, frames=(2, 3))
    scene.run(quiet=True)
    mass = float(np.sum(model.masses))
    g = float(np.linalg.norm(model.gravity))
    rows = [r for r in ledger.rows if r[0] in (2, 3)]
    assert len(rows) == 6  # 3 steps in each of the 2 frames
    for _, _, parts, total in rows:
        assert parts["limit _Lift"] == pytest.approx(mass * g * dy, rel=1e-3)
        # a free fall's symplectic Euler step (v += g dt, x += v dt) changes the energy by
        # exactly -M g^2 dt^2 / 2, whatever the velocity
        assert parts["solve"] == pytest.approx(-0.5 * mass * (g * scene.dt) ** 2, rel=1e-3)
        assert abs(parts["other"]) < 1e-9
        assert total == pytest.approx(sum(v for k, v in parts.items()), abs=1e-12)
    per_frame = ledger.per_frame()
    assert list(per_frame) == [2, 3]
    assert per_frame[2][2] == 3
    assert "limit _Lift" in ledger.report()


def test_stages_inside_the_step_are_not_counted_twice():
    # explicit Euler runs the features' friction and response inside its step: each is its own
    # row and the solve's row is what is left, so nothing is left for "other"
    scene = drape(res=6, frames=30, solver="explicit")
    ledger = EnergyLedger(scene, frames=(20, 29))
    scene.run(quiet=True)
    assert ledger.rows
    labels = set().union(*(r[2] for r in ledger.rows))
    assert {"solve", "feature friction", "feature response", "self-collision",
            "self-collision response"} <= labels
    moved = sum(abs(r[2].get("feature response", 0.0)) for r in ledger.rows)
    assert moved > 0.0  # the sheet rests on the ball: the features act
    for _, _, parts, total in ledger.rows:
        assert abs(parts["other"]) < 1e-6 * max(1.0, abs(total))


def test_detach_restores_the_scene_and_its_graphs():
    model, scene = _free_sheet_scene(_Lift(0.0), frames=3)
    solver = scene.solver
    ledger = EnergyLedger(scene, frames=(1, 2))
    assert scene.capture is False and "step" in vars(solver)
    with pytest.raises(ValueError, match="already has a ledger"):
        EnergyLedger(scene, frames=(1, 2))
    ledger.detach()
    assert scene.capture is True
    assert "step" not in vars(solver) and "_advance" not in vars(solver)
    assert "apply" not in vars(solver.corrections[0])
    scene.run(quiet=True)
    assert ledger.rows == []  # detached: nothing measured


def test_ledger_frames_are_checked():
    _, scene = _free_sheet_scene(_Lift(0.0), frames=3)
    for bad in ((0, 2), (3, 2), ("a", 2), (1.5, 2), 3, (1, 2, 3)):
        with pytest.raises(ValueError, match="frames"):
            EnergyLedger(scene, frames=bad)


def test_cli_ledger_prints_the_frames_asked_for(tmp_path, capsys):
    out = str(tmp_path / "h.usd")
    rc = cli.main(["run", "hanging", "--res", "4", "--frames", "5", "--quiet", "--out", out,
                   "--ledger", "2:3"])
    assert rc == 0
    text = capsys.readouterr().out
    table = [ln for ln in text.splitlines() if ln.startswith("| ") and ln[2].isdigit()]
    assert [ln.split("|")[1].strip() for ln in table] == ["2", "3"]
    # with --json, one JSON document holding the ledger's steps
    assert cli.main(["run", "hanging", "--res", "4", "--frames", "5", "--quiet", "--out", out,
                     "--ledger", "3", "--json"]) == 0
    import json

    doc = json.loads(capsys.readouterr().out)
    steps = doc["ledger"]
    assert steps and {r["frame"] for r in steps} == {3}
    for r in steps:
        assert sum(r["parts"].values()) == pytest.approx(r["total"], abs=1e-12)
    with pytest.raises(SystemExit) as e:
        cli.main(["run", "hanging", "--res", "4", "--frames", "5", "--quiet", "--out", out,
                  "--ledger", "2:9"])
    assert e.value.code == 2
    assert "past the run's last frame" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["run", "hanging", "--frames", "5", "--ledger", "x"])
    assert "FIRST:LAST" in capsys.readouterr().err
