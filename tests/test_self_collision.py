"""Self-collision (issue 13, first steps): the intersection checker, the fold scene with every
solver, the fail-safe counters and the ``warp-cloth check`` command."""

import json

import numpy as np
import pytest

from warp_cloth import cli
from warp_cloth.collision import CollisionStage
from warp_cloth.collision.check import self_crossings
from warp_cloth.contact_scenes import fold, sheet_model


def test_checker_counts_exact_crossings():
    # two triangles through each other: the second's edge (3, 4) passes through the first, and
    # the first's edge (1, 2) through the second (their intersection segment ends on both)
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0],
                  [0.2, 0.2, -1], [0.2, 0.2, 1], [3, 3, 0.0]])
    tris = np.array([[0, 1, 2], [3, 4, 5]])
    edges = np.array([[0, 1], [1, 2], [0, 2], [3, 4], [4, 5], [3, 5]])
    assert self_crossings(x, tris, edges) == 2
    x2 = x.copy()
    x2[3:5, 0] += 2.0  # moved beside: none
    assert self_crossings(x2, tris, edges) == 0
    # a flat grid: adjacent triangles share vertices and never count
    mesh = sheet_model(res=4).mesh
    assert self_crossings(mesh.vertices, mesh.triangles, mesh.edges) == 0


def _fold(solver_name, on=True, res=10, frames=50, capture=True, out=None):
    from warp_cloth.collision.check import SelfIntersectionChecker

    scene = fold(solver=solver_name, res=res, frames=frames, size=0.6, self_collision=on,
                 angle=150.0)
    scene.capture = capture
    m = scene.model
    chk = SelfIntersectionChecker(m.mesh.triangles, m.mesh.edges, m.num_vertices)
    crossings = []
    scene.run(out, quiet=True, energy=False,
              on_frame=lambda f, st: crossings.append(chk(st.x)))
    return crossings, scene


@pytest.mark.parametrize("solver_name", ["implicit", "pd", "pbd"])
def test_fold_never_passes_through_itself(solver_name):
    crossings, scene = _fold(solver_name)
    assert max(crossings) == 0, f"{max(crossings)} crossing pairs in a frame"
    st = scene.collision.stats
    assert st["self_overflow_total"] == 0 and st["self_fallback_all_total"] == 0
    assert st["self_fallback_vertices_total"] == 0  # the response resolved every contact
    assert st["self_contacts_total"] > 0
    # it did fold: the lifted half came down onto the other (within a few thicknesses)
    x = scene.state.positions()
    assert x[:, 1].max() < 0.1


def test_fold_without_self_collision_passes_through():
    crossings, _ = _fold("implicit", on=False)
    assert max(crossings) > 0  # the check above can fail


def test_fold_replays_exactly_when_captured():
    _, a = _fold("pd", frames=12, capture=True)
    _, b = _fold("pd", frames=12, capture=False)
    np.testing.assert_array_equal(a.state.positions(), b.state.positions())


def test_cli_check_reports_crossings(tmp_path, capsys):
    bad = tmp_path / "through.usd"
    good = tmp_path / "folded.usd"
    _fold("implicit", on=False, res=8, frames=40, out=bad)
    _fold("implicit", on=True, res=8, frames=40, out=good)
    capsys.readouterr()
    assert cli.main(["check", str(bad), "--json"]) == 1
    rep = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert rep["frames"] == 40 and rep["frames_with_crossings"] > 0
    assert cli.main(["check", str(good)]) == 0
    with pytest.raises(SystemExit) as e:
        cli.main(["check", str(tmp_path / "missing.usd")])
    assert e.value.code == 2


def test_self_collision_alone_and_its_arguments():
    model = sheet_model(res=4)
    stage = CollisionStage(model, self_collision=True, self_thickness=0.004)
    assert stage.obstacles == [] and stage.thickness == 0.004
    with pytest.raises(ValueError, match="obstacles or self_collision"):
        CollisionStage(model)
    with pytest.raises(ValueError, match="self_thickness"):
        CollisionStage(model, self_collision=True, self_thickness=-1.0)


def test_default_fold_on_the_floor_stays_above_it():
    """The README's figures: the default fold (lifted 100 degrees) never passes through itself,
    and the layer under the other stays above the floor (within two thirds of the thickness
    of the thickness: self-collision's response runs after obstacle contact)."""
    from warp_cloth.collision.check import SelfIntersectionChecker

    scene = fold(solver="implicit", res=12, frames=75, size=0.6)
    m = scene.model
    chk = SelfIntersectionChecker(m.mesh.triangles, m.mesh.edges, m.num_vertices)
    crossings, low = [], []

    def on_frame(f, st):
        crossings.append(chk(st.x))
        low.append(float(st.positions()[:, 1].min()))

    scene.run(None, quiet=True, energy=False, on_frame=on_frame)
    th = scene.collision.thickness
    assert max(crossings) == 0
    assert min(low) > th / 3.0 - 1e-4
    assert scene.state.positions()[:, 1].max() < 0.1  # folded


def test_model_initial_positions_are_checked():
    from warp_cloth import ClothModel

    mesh = sheet_model(res=2).mesh
    x = mesh.vertices + [0.0, 0.1, 0.0]
    assert np.allclose(ClothModel(mesh, positions=x).state().positions(), x, atol=1e-6)
    with pytest.raises(ValueError, match="shape"):
        ClothModel(mesh, positions=x[:-1])
    x[4, 1] = np.nan
    with pytest.raises(ValueError, match="vertex 4"):
        ClothModel(mesh, positions=x)


def test_stack_of_sheets_stays_apart():
    from warp_cloth.collision.check import SelfIntersectionChecker
    from warp_cloth.contact_scenes import stack

    scene = stack(res=8, frames=45)
    m = scene.model
    chk = SelfIntersectionChecker(m.mesh.triangles, m.mesh.edges, m.num_vertices)
    crossings = []
    scene.run(None, quiet=True, energy=False, on_frame=lambda f, st: crossings.append(chk(st.x)))
    assert max(crossings) == 0
    assert scene.collision.stats["self_fallback_all_total"] == 0
    x = scene.state.positions()
    assert x[:, 1].max() < 2 * 0.2 + 0.1  # the three sheets came down onto the sphere


def test_twist_turns_its_edges_in_opposite_directions():
    from warp_cloth.contact_scenes import twist

    scene = twist(res=6, frames=31, self_collision=False, solver="pd")
    scene.run(None, quiet=True, energy=False)
    x, x0 = scene.state.positions(), scene.model.mesh.vertices
    left = np.isclose(x0[:, 0], x0[:, 0].min())
    right = np.isclose(x0[:, 0], x0[:, 0].max())
    t = scene.state.t
    ang = lambda p, q: np.arctan2(p[:, 2], p[:, 1] - 1.0) - np.arctan2(q[:, 2], q[:, 1] - 1.0)
    a_l = np.angle(np.exp(1j * ang(x[left], x0[left])))
    a_r = np.angle(np.exp(1j * ang(x[right], x0[right])))
    far = np.abs(x0[left, 2]) > 0.1  # points off the axis turn by the angle
    assert np.allclose(a_l[far], np.pi / 3 * t, atol=0.02)
    assert np.allclose(a_r[far[: right.sum()]], -np.pi / 3 * t, atol=0.02)


def test_checker_ignores_segments_in_a_triangles_plane():
    """The fold's start: the hinge edges lie in the lifted half's plane, outside its triangles
    (a coplanar segment touches at most; float rounding once made that a crossing)."""
    scene = fold(res=12, frames=1)
    m = scene.model
    assert self_crossings(m.initial_positions, m.mesh.triangles, m.mesh.edges) == 0
