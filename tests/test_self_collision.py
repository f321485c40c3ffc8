"""Self-collision (issue 13, first steps): the intersection checker, the fold scene with every
solver, the fail-safe counters and the ``warp-cloth check`` command."""

import json

import numpy as np
import pytest
import warp as wp

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


def _fold(solver_name, on=True, res=10, frames=50, capture=True, out=None, motion=None):
    from warp_cloth.collision.check import SelfIntersectionChecker

    scene = fold(solver=solver_name, res=res, frames=frames, size=0.6, self_collision=on,
                 angle=150.0)
    scene.capture = capture
    if motion is not None:  # the stage's self_motion, re-planned for the scene's frames
        scene.collision.self_motion = motion
        scene.collision.plan(scene.substeps)
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
    assert st["self_zones_total"] == 0  # the rounds of projection resolved every contact
    assert st["self_contacts_total"] > 0
    # the solvers that detect their own self-contacts hand them to the response, which
    # starts from them (`SelfCollision.note_solve`), in the recorded frames too
    reused = st["self_reused_total"]
    assert reused > 0 if solver_name in ("implicit", "pd") else reused == 0
    # it did fold: the lifted half came down onto the other (within a few thicknesses)
    x = scene.state.positions()
    assert x[:, 1].max() < 0.1


def test_fold_without_self_collision_passes_through():
    crossings, _ = _fold("implicit", on=False)
    assert max(crossings) > 0  # the check above can fail


@pytest.mark.parametrize("solver_name", ["pd", "explicit"])
def test_fold_replays_exactly_when_captured(solver_name):
    """A recorded frame replays the steps run one by one, bit for bit: PD's frame as one graph;
    explicit Euler's 97 steps as a graph of `GRAPH_BLOCK` steps replayed 6 times and one of
    the last step (its steps are uniform: self-collision counts the frame's steps on the
    device, so its response still comes on every frame's last step)."""
    from warp_cloth.scene import GRAPH_BLOCK

    _, a = _fold(solver_name, frames=12, capture=True)
    _, b = _fold(solver_name, frames=12, capture=False)
    assert a.solver.uniform_steps == (solver_name == "explicit")
    if solver_name == "explicit":
        assert a.substeps > GRAPH_BLOCK and a.substeps % GRAPH_BLOCK
    st = a.collision.stats
    assert st["self_responses_total"] == b.collision.stats["self_responses_total"] > 0
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


def _stage(path, meshes, times=None):
    """A USD stage with one Mesh per ``(name, faces, points, translate)``; ``points`` and
    ``translate`` are lists over ``times`` when given (time-sampled), else single values."""
    from pxr import Gf, Usd, UsdGeom

    st = Usd.Stage.CreateNew(str(path))
    for name, faces, points, translate in meshes:
        xf = UsdGeom.Xform.Define(st, f"/World/{name}")
        m = UsdGeom.Mesh.Define(st, f"/World/{name}/geom")
        m.CreateFaceVertexCountsAttr([len(f) for f in faces])
        m.CreateFaceVertexIndicesAttr([int(i) for f in faces for i in f])
        op = xf.AddTranslateOp()
        if times is None:
            m.CreatePointsAttr([Gf.Vec3f(*map(float, p)) for p in points])
            op.Set(Gf.Vec3d(*translate))
        else:
            for k, t in enumerate(times):
                pk = points[k] if isinstance(points, list) else points
                m.GetPointsAttr().Set([Gf.Vec3f(*map(float, p)) for p in pk], Usd.TimeCode(t))
                tk = translate[k] if isinstance(translate, list) else translate
                op.Set(Gf.Vec3d(*tk), Usd.TimeCode(t))
    st.GetRootLayer().Save()


def _check_json(args, capsys):
    capsys.readouterr()
    rc = cli.main(["check", *args, "--json"])
    return rc, json.loads(capsys.readouterr().out.strip().splitlines()[-1])


_TRI = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]])
_PIERCE = np.array([[0.2, 0.2, -1], [0.2, 0.2, 1], [3, 3, 0.0]])  # its edge (0, 1) through _TRI


def test_cli_check_tests_every_mesh_in_world_space(tmp_path, capsys):
    """Two meshes, each clean: their crossing is found between them, in world space (the
    second's transform is animated: in its local frame it pierces the first at time 0, in
    the world only at time 1; the pair of `test_checker_counts_exact_crossings`: 2 crossings)."""
    f = tmp_path / "two.usda"
    _stage(f, [("a", [[0, 1, 2]], _TRI, (0, 0, 0)),
               ("b", [[0, 1, 2]], _PIERCE, [(5.0, 0, 0), (0, 0, 0), (0, 0, 3.0)])],
           times=[0, 1, 2])
    rc, rep = _check_json([str(f)], capsys)
    assert rc == 1
    assert rep["meshes"] == ["/World/a/geom", "/World/b/geom"]
    assert rep["times"] == [0, 1, 2]
    assert rep["between"] == [0, 2, 0] and rep["crossings"] == [0, 2, 0]  # as the pair below
    assert rep["per_mesh"] == {"/World/a/geom": [0, 0, 0], "/World/b/geom": [0, 0, 0]}
    # one mesh alone has none
    rc, rep = _check_json([str(f), "--prim", "/World/b/geom"], capsys)
    assert rc == 0 and rep["crossings"] == [0, 0, 0]
    # far from the origin: the same counts
    g = tmp_path / "far.usda"
    far = (1.0e4, -2.0e4, 3.0e4)
    _stage(g, [("a", [[0, 1, 2]], _TRI, far),
               ("b", [[0, 1, 2]], _PIERCE, [tuple(c + d for c, d in zip(far, (5.0, 0, 0))), far])],
           times=[0, 1])
    rc, rep = _check_json([str(g)], capsys)
    assert rc == 1 and rep["crossings"] == [0, 2]
    # two rigid meshes (points not animated) laid into each other: reported, not failed
    h = tmp_path / "rigid.usda"
    _stage(h, [("a", [[0, 1, 2]], _TRI, (0, 0, 0)), ("b", [[0, 1, 2]], _PIERCE, (0, 0, 0))])
    rc, rep = _check_json([str(h)], capsys)
    assert rc == 0 and rep["between_rigid"] == [2] and rep["crossings"] == [0]


def test_cli_check_measures_cloth_edges_inside_spheres_and_cubes(tmp_path, capsys):
    """`warp-cloth check` also samples the animated meshes' edges against the stage's spheres
    and cubes, in each solid's frame: a sphere of radius 0.5 scaled 2 about (1, 2, 3), an edge
    passing 0.9 from its centre: one sample (the middle) inside, 0.1 m deep; a cube (size 2,
    scaled to half extents 0.5 / 0.2 / 0.3, turned 90 degrees about y) at (-3, 0, 0), an edge
    along x at y = 0.15: 3 samples inside, 0.05 m deep (along its y, and its z, which the turn
    lays along x). Nothing inside at time 0; exit status 1."""
    from pxr import Gf, Usd, UsdGeom

    far = [[0, 10, 0], [1, 10, 0], [0, 11, 0]]
    ball = [[-1, 2.9, 3], [3, 2.9, 3], [1, 10, 3]]
    box = [[-4, 0.15, 0], [-2, 0.15, 0], [-3, 10, 0]]
    f = tmp_path / "solids.usda"
    _stage(f, [("cloth", [[0, 1, 2]], [far, ball, box], (0, 0, 0))], times=[0, 1, 2])
    st = Usd.Stage.Open(str(f))
    xf = UsdGeom.Xform.Define(st, "/World/ball")
    xf.AddTranslateOp().Set(Gf.Vec3d(1, 2, 3))
    xf.AddScaleOp().Set(Gf.Vec3f(2, 2, 2))
    UsdGeom.Sphere.Define(st, "/World/ball/geom").CreateRadiusAttr(0.5)
    xf = UsdGeom.Xform.Define(st, "/World/box")
    xf.AddTranslateOp().Set(Gf.Vec3d(-3, 0, 0))
    xf.AddRotateYOp().Set(90.0)
    xf.AddScaleOp().Set(Gf.Vec3f(0.5, 0.2, 0.3))
    UsdGeom.Cube.Define(st, "/World/box/geom")
    st.GetRootLayer().Save()
    rc, rep = _check_json([str(f)], capsys)
    assert rc == 1 and rep["crossings"] == [0, 0, 0]
    assert rep["solids"] == ["/World/ball/geom (sphere)", "/World/box/geom (cube)"]
    assert rep["inside_solids"] == [0, 1, 3] and rep["frames_inside_solids"] == 2
    assert rep["inside_depth"] == pytest.approx([0.0, 0.1, 0.05], abs=1e-6)
    # a stage whose spheres and cubes are not obstacles: --no-solids
    rc, rep = _check_json([str(f), "--no-solids"], capsys)
    assert rc == 0 and rep["solids"] == [] and rep["inside_solids"] == [0, 0, 0]
    # a sphere of negative radius: a usage error naming the prim (exit 2)
    st = Usd.Stage.Open(str(f))
    UsdGeom.Sphere(st.GetPrimAtPath("/World/ball/geom")).GetRadiusAttr().Set(-1.0)
    st.GetRootLayer().Save()
    capsys.readouterr()
    assert cli.main(["check", str(f)]) == 2
    err = capsys.readouterr().err
    assert "/World/ball/geom" in err and "not a positive number" in err
    # the same cloth without the solids: clean
    g = tmp_path / "none.usda"
    _stage(g, [("cloth", [[0, 1, 2]], [far, ball, box], (0, 0, 0))], times=[0, 1, 2])
    rc, rep = _check_json([str(g)], capsys)
    assert rc == 0 and rep["solids"] == [] and rep["inside_solids"] == [0, 0, 0]


def test_cli_check_takes_any_mesh_static_polygons_degenerate_and_non_manifold(tmp_path, capsys):
    """A mesh that is no valid cloth (a quad, a zero-area triangle, an edge with three
    triangles) and has no time samples: read once, tested as it is, and its one crossing
    found; a non-finite point is reported, not tested."""
    pts = np.vstack([_TRI, _PIERCE,
                     [[10, 0, 0], [11, 0, 0], [11, 1, 0], [10, 1, 0],  # a quad
                      [20, 0, 0], [21, 0, 0], [22, 0, 0],  # collinear
                      [30, 0, 0], [31, 0, 0], [30, 1, 0], [30, -1, 0], [30, 0, 1]]])
    faces = [[0, 1, 2], [3, 4, 5], [6, 7, 8, 9], [10, 11, 12],
             [13, 14, 15], [13, 14, 16], [13, 14, 17]]  # three triangles on edge (13, 14)
    f = tmp_path / "soup.usda"
    _stage(f, [("soup", faces, pts, (0, 0, 0))])
    rc, rep = _check_json([str(f)], capsys)
    assert rc == 1 and rep["frames"] == 1 and rep["times"] == [None]
    assert rep["crossings"] == [2]  # as `test_checker_counts_exact_crossings`
    g = tmp_path / "nan.usda"
    bad = pts.copy()
    bad[12] = np.nan
    moved = pts.copy()
    moved[3:6, 0] += 2.0  # the piercing triangle beside the first: none
    _stage(g, [("soup", faces, [moved, bad, moved], (0, 0, 0))], times=[0, 1, 2])
    rc, rep = _check_json([str(g)], capsys)
    assert rc == 1 and rep["nonfinite"] == [0, 1, 0] and rep["frames_with_crossings"] == 0


def test_cli_check_refuses_unreadable_meshes(tmp_path, capsys):
    from pxr import Usd, UsdGeom

    empty = tmp_path / "empty.usda"
    st = Usd.Stage.CreateNew(str(empty))
    UsdGeom.Xform.Define(st, "/World")
    st.GetRootLayer().Save()
    capsys.readouterr()
    assert cli.main(["check", str(empty)]) == 2
    assert "has no Mesh prim" in capsys.readouterr().err
    f = tmp_path / "outside.usda"
    _stage(f, [("m", [[0, 1, 7]], _TRI, (0, 0, 0))])
    assert cli.main(["check", str(f)]) == 2
    err = capsys.readouterr().err
    assert "/World/m/geom" in err and "= 7 is outside its 3 points" in err
    assert cli.main(["check", str(f), "--prim", "/World/m"]) == 2
    assert "not a Mesh" in capsys.readouterr().err


def test_self_collision_alone_and_its_arguments():
    model = sheet_model(res=4)
    stage = CollisionStage(model, self_collision=True, self_thickness=0.004)
    assert stage.obstacles == [] and stage.thickness == 0.004
    with pytest.raises(ValueError, match="obstacles or self_collision"):
        CollisionStage(model)
    with pytest.raises(ValueError, match="self_thickness"):
        CollisionStage(model, self_collision=True, self_thickness=-1.0)
    from warp_cloth.collision.self_collision import SelfCollision

    for bad in (-1.0, float("nan"), float("inf"), "wide", None):
        with pytest.raises(ValueError, match="clearance"):
            SelfCollision(model, 0.004, clearance=bad)
    sc = SelfCollision(model, 0.004, clearance=1.0)  # no allowances: the reach everywhere
    sc.plan(10, 0.25)
    assert not sc.allowances
    for bad in (-0.5, float("nan"), float("inf"), "far"):
        with pytest.raises(ValueError, match="candidate_reach"):
            SelfCollision(model, 0.004, candidate_reach=bad)
    assert SelfCollision(model, 0.004, candidate_reach=0).candidate_stats() == {}
    assert SelfCollision(model, 0.004, broadphase="grid").candidate_stats() == {}  # BVH only


def test_default_fold_on_the_floor_stays_above_it():
    """The README's figures: the default fold (lifted 100 degrees) never passes through itself,
    and the layer under the other stays the thickness above the floor (less 1e-4 m, the
    stage's promise): self-collision's response, which splits its corrections between the
    layers, pushed it down to 4.6 mm of the 5 here before vertex contact ran again after it."""
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
    assert min(low) >= th - 1e-4, f"a vertex {min(low) * 1e3:.2f} mm above the floor"
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


def test_twist_pd_runs_no_contact_iterations_unless_asked():
    """The twist's pins do work, so PD's energy criterion for contact iterations is off there
    and only the penalty residual ran them (23 % of the time, for no measured change:
    `SCENE_TWIST_PD_CONTACT_ITERATIONS`); a user's value wins, and other scenes keep PD's."""
    from warp_cloth.contact_scenes import SCENE_TWIST_PD_CONTACT_ITERATIONS, twist

    assert SCENE_TWIST_PD_CONTACT_ITERATIONS == 0
    assert twist(solver="pd", res=4, frames=1).solver.contact_iterations == 0
    assert twist(solver="pd", res=4, frames=1,
                 solver_options={"contact_iterations": 5}).solver.contact_iterations == 5
    assert fold(solver="pd", res=4, frames=1).solver.contact_iterations > 0


def test_pbd_winds_the_twist_with_its_springs_compliance():
    """Pins that wind the cloth up impose stretch, which plain PBD's constraints (and tethers)
    refuse: on a 10 x 10 twist turned at 2 rad/s (30 fps) its substeps pulled vertices into the
    rope's layers and the response pushed them back until the impact zones froze the cloth
    (diverged at frame 33). The scene gives PBD XPBD with the springs' compliance
    (`SCENE_PBD_MOVING_PINS_COMPLIANCE`), which winds the rope on: all 45 frames, none through
    itself, no step returned to its start; a user's compliance wins, plain PBD included."""
    from warp_cloth.contact_scenes import SCENE_PBD_MOVING_PINS_COMPLIANCE, twist

    assert SCENE_PBD_MOVING_PINS_COMPLIANCE == "springs"
    scene = twist(solver="pbd", res=10, rate=2.0, fps=30, frames=45)
    assert scene.solver.compliance == "springs"
    st = scene.run(None, quiet=True, energy=False, check_intersections=True)
    assert st.crossing_frames == 0 and st.retried_frames == 0
    assert scene.collision.stats["self_fallback_all_total"] == 0
    assert st.max_strain < 1.5  # the twist's own stretch (75 %), not a blow-up
    assert twist(solver="pbd", res=4, frames=1,
                 solver_options={"compliance": None}).solver.compliance is None
    assert twist(solver="pbd", res=4, frames=1,
                 solver_options={"compliance": 1e-3}).solver.compliance == 1e-3
    assert fold(solver="pbd", res=4, frames=1).solver.compliance is None  # pins that stay


def test_pbd_long_steps_keep_the_stack_apart_with_contacts_in_their_iterations():
    """PBD at one step a frame (30 fps): three 6 x 6 sheets dropped on the stack's sphere. The
    self-contacts of each step's predicted paths are projected in its iterations and in the
    stretch guard's sweeps after the response (``self_contacts="auto"``, on in steps of at
    least `SELF_CONTACT_DT`): no impact zone, every vertex at the thickness from the ground
    and the sphere, the stretch guard's bound nearly kept. Without them the response after
    the step pulled the sheets to 18 % strain and its impact zones left a vertex 1.3 mm inside
    the thickness."""
    from warp_cloth.contact_scenes import stack
    from warp_cloth.solvers.pbd import SELF_CONTACT_DT

    scene = stack(solver="pbd", res=6, sheets=3, frames=45, fps=30, substeps=1)
    assert scene.solver.self_contacts_on(1.0 / 30) and not scene.solver.self_contacts_on(
        0.5 * SELF_CONTACT_DT)
    th = scene.collision.thickness
    obs = scene.collision.contact
    least, listed = [np.inf], [0]

    def on_frame(f, st):
        d = obs.signed_distances(st.x.numpy(), f / scene.fps)
        least[0] = min(least[0], float(d.min()))
        listed[0] = max(listed[0], scene.collision.stats["self_iteration_contacts"])

    st = scene.run(None, quiet=True, energy=False, on_frame=on_frame, check_intersections=True)
    s = scene.collision.stats
    assert st.crossing_frames == 0 and s["self_zones_total"] == 0
    assert s["self_fallback_all_total"] == 0 and s["self_iteration_dropped"] == 0
    assert listed[0] > 0
    assert least[0] >= th - 1e-4
    # the guard's 8 % and what the self-collision response after it left (README, *Methods*:
    # 9.9-11.7 % at one step a frame); 8.9 % before friction moved back only the share of a
    # slide made in contact, 10.1 % since (the sheets slide further on the sphere); 18 %
    # without the self-contacts in the iterations
    assert st.max_strain < 0.11


def test_pbd_self_contacts_option_is_checked_and_its_overflow_reported(capsys):
    """``self_contacts`` takes "auto", True or False (False: no record); with room for 2
    entries the iterations' record drops pairs, which is reported on stderr and doubles it."""
    from warp_cloth.contact_scenes import stack

    with pytest.raises(ValueError, match="self_contacts"):
        stack(solver="pbd", res=2, frames=1, solver_options={"self_contacts": "yes"})
    off = stack(solver="pbd", res=2, frames=1, substeps=1, solver_options={"self_contacts": False})
    assert not off.solver.self_contacts_on(1.0) and off.collision.iter_record is None
    on = stack(solver="pbd", res=2, frames=1, solver_options={"self_contacts": True})
    assert on.solver.self_contacts_on(1e-5)
    scene = stack(solver="pbd", res=6, sheets=2, frames=20, fps=30, substeps=1, gap=0.01)
    st = scene.collision
    from warp_cloth.collision.record import make_record

    st.iter_record = make_record(2, st.device)
    scene.run(None, energy=False, progress=False)
    assert "did not fit the iterations' record" in capsys.readouterr().err
    assert st.iter_record.vertex.shape[0] >= 4 and st.stats["self_iteration_dropped"] > 0


def test_checker_ignores_segments_in_a_triangles_plane():
    """The fold's start: the hinge edges lie in the lifted half's plane, outside its triangles
    (a coplanar segment touches at most; float rounding once made that a crossing)."""
    scene = fold(res=12, frames=1)
    m = scene.model
    assert self_crossings(m.initial_positions, m.mesh.triangles, m.mesh.edges) == 0


def _brute_candidates(mesh, x0, x1, gap, inv_mass):
    """Every non-adjacent (vertex, triangle) and (edge, edge) pair whose swept boxes, each
    inflated by ``gap / 2``, overlap: the set a conservative broad phase must find (float32
    boxes, computed the kernels' way: `broadphase.padded`)."""
    x0 = np.asarray(x0, np.float32)
    x1 = np.asarray(x1, np.float32)
    g = np.float32(0.5 * gap)
    r = np.float32(2.5e-7)
    lo_v, hi_v = np.minimum(x0, x1), np.maximum(x0, x1)
    tris, edges = mesh.triangles, mesh.edges

    def pad(lo, hi):
        return lo - g - r * np.abs(lo), hi + g + r * np.abs(hi)

    lo_t, hi_t = pad(lo_v[tris].min(axis=1), hi_v[tris].max(axis=1))
    lo_e, hi_e = pad(lo_v[edges].min(axis=1), hi_v[edges].max(axis=1))
    lo_v, hi_v = pad(lo_v, hi_v)
    free = inv_mass > 0

    def overlap(alo, ahi, blo, bhi):
        return np.all((alo[:, None] <= bhi[None]) & (blo[None] <= ahi[:, None]), axis=2)

    vt = overlap(lo_v, hi_v, lo_t, hi_t)
    vt &= ~np.any(tris[None, :, :] == np.arange(len(x0))[:, None, None], axis=2)
    vt &= free[:, None] | free[tris].any(axis=1)[None]
    ee = overlap(lo_e, hi_e, lo_e, hi_e)
    ee &= np.triu(np.ones_like(ee), 1).astype(bool)
    share = (edges[:, None, :, None] == edges[None, :, None, :]).any(axis=(2, 3))
    ee &= ~share & (free[edges].any(axis=1)[:, None] | free[edges].any(axis=1)[None])
    return ({(int(a), int(b)) for a, b in zip(*np.nonzero(vt))},
            {(int(a), int(b)) for a, b in zip(*np.nonzero(ee))})


@pytest.mark.parametrize("method", ["grid", "bvh"])
@pytest.mark.parametrize("where", ["random", "crumpled", "far", "negative"])
def test_broad_phase_finds_every_overlapping_pair(method, where):
    """Both broad phases against brute force: the same candidate set, exactly (conservative and
    nothing extra after the box test), on a random triangle soup and a crumpled sheet with
    large motions, near the origin, far from it and at negative coordinates."""
    import warp as wp

    from warp_cloth.collision.self_collision import SelfCollision
    from warp_cloth.mesh import TriMesh
    from warp_cloth.model import ClothModel

    rng = np.random.default_rng(7)
    if where == "random":
        n = 60
        tris = np.array([rng.choice(n, 3, replace=False) for _ in range(40)])
        x0 = rng.uniform(-0.3, 0.3, (n, 3))
        used = np.unique(tris)
        remap = -np.ones(n, int)
        remap[used] = np.arange(len(used))
        tris, x0 = remap[tris], x0[used]
        mesh = TriMesh(x0, tris)
    else:
        mesh = sheet_model(res=7).mesh
        x0 = mesh.vertices + rng.normal(0, 0.05, mesh.vertices.shape)
        mesh = TriMesh(x0, mesh.triangles)
    model = ClothModel(mesh, device="cpu")
    shift = {"random": 0.0, "crumpled": 0.0, "far": 1.0e3, "negative": -7.3}[where]
    x0 = mesh.vertices + shift
    x1 = x0 + rng.normal(0, 0.08, x0.shape)
    x1[3] += 0.5  # one fast vertex: a long swept box
    inv_mass = model.inv_mass.numpy()
    sc = SelfCollision(model, 0.01, broadphase=method)
    a0 = wp.array(x0, dtype=wp.vec3, device="cpu")
    a1 = wp.array(x1, dtype=wp.vec3, device="cpu")
    vt, ee = sc.candidates(a0, a1, 0.01)
    bvt, bee = _brute_candidates(mesh, a0.numpy(), a1.numpy(), 0.01, inv_mass)
    assert len(bvt) > 20 and len(bee) > 20
    assert bvt <= vt and bee <= ee  # nothing missed
    if method == "grid":  # the grid keeps only boxes that overlap: exactly the brute-force set
        assert vt == bvt and ee == bee


@pytest.mark.parametrize("method", ["grid", "bvh"])
@pytest.mark.parametrize("shift", [0.0, -523.7])
def test_broad_phase_lists_every_pair_that_comes_within_the_gap(method, shift):
    """The boxes are inflated by half the gap each: every non-adjacent pair whose elements come
    within the gap at some time of their straight paths is a candidate (distances in float64 at
    five times of the paths, brute force over every pair of a crumpled sheet, near the origin
    and far from it). Many pairs lie between half the gap and the gap, so boxes inflated by a
    quarter of it each would miss some."""
    import warp as wp

    from warp_cloth.collision.self_collision import SelfCollision

    model, rng = _crumpled()
    x0 = model.mesh.vertices + shift
    x1 = x0 + rng.normal(0, 0.01, x0.shape)
    x0 = x0.astype(np.float32).astype(np.float64)  # the kernels' positions, exactly
    x1 = x1.astype(np.float32).astype(np.float64)
    gap = 0.1
    sc = SelfCollision(model, 0.01, broadphase=method)
    a0 = wp.array(x0, dtype=wp.vec3, device="cpu")
    a1 = wp.array(x1, dtype=wp.vec3, device="cpu")
    vt, ee = sc.candidates(a0, a1, gap)
    tris, edges = model.mesh.triangles, model.mesh.edges
    keys = [(v, t) for v in range(len(x0)) for t in range(len(tris)) if v not in tris[t]]
    nvt = len(keys)
    keys += [(e, f) for e in range(len(edges)) for f in range(e + 1, len(edges))
             if not set(edges[e]) & set(edges[f])]
    least = np.full(len(keys), np.inf)
    for t in (0.0, 0.25, 0.5, 0.75, 1.0):
        _, d = _pair_distances(model.mesh, x0 + t * (x1 - x0))
        least = np.minimum(least, d)
    within = [k for k, d in zip(keys[:nvt], least[:nvt]) if d < gap]
    within_ee = [k for k, d in zip(keys[nvt:], least[nvt:]) if d < gap]
    band = np.count_nonzero((least > 0.5 * gap) & (least < gap))
    assert band > 100 and len(within) > 50 and len(within_ee) > 50
    assert set(within) <= vt
    assert set(within_ee) <= ee


def test_broad_phase_method_is_checked():
    from warp_cloth.collision.self_collision import SelfCollision

    with pytest.raises(ValueError, match="broad phase method 'octree'"):
        SelfCollision(sheet_model(res=2), 0.01, broadphase="octree")


def _zones_setup(n, entries, x0, x1, inv_mass):
    import warp as wp

    from warp_cloth.collision.impact_zones import ImpactZones
    from warp_cloth.collision.record import make_record

    class _M:  # the two fields ImpactZones reads
        num_vertices = n
        device = "cpu"

    _M.inv_mass = wp.array(np.asarray(inv_mass, np.float32), dtype=float, device="cpu")
    rec = make_record(16, "cpu")
    vid = -np.ones((16, 4), np.int32)
    for k, e in enumerate(entries):
        vid[k, :len(e)] = e
    rec.vertex.assign(vid)
    rec.count.assign(np.array([len(entries)], np.int32))
    z = ImpactZones(_M)
    z.reset()
    z.merge(rec, 4)

    class _S:
        x = wp.array(np.asarray(x1, np.float32), dtype=wp.vec3, device="cpu")
        v = wp.zeros(n, dtype=wp.vec3, device="cpu")

    counters = wp.zeros(2, dtype=int, device="cpu")
    xs = wp.array(np.asarray(x0, np.float32), dtype=wp.vec3, device="cpu")
    return z, rec, xs, _S, counters


def test_impact_zones_merge_contacts_sharing_vertices_and_move_rigidly():
    """Entries (0,1), (1,2), (2,3) chain into one zone, (5,6) is another, 4 and 7 are in none.
    Each zone moves rigidly: its inner distances stay those of the start, its centre of mass
    moves as its vertices did on average, its angular momentum is kept; other vertices keep
    their end positions."""
    rng = np.random.default_rng(3)
    n = 8
    x0 = rng.uniform(-1, 1, (n, 3))
    x1 = x0 + rng.normal(0, 0.05, (n, 3))
    mass = rng.uniform(0.5, 2.0, n)
    z, rec, xs, st, counters = _zones_setup(n, [(0, 1), (1, 2), (2, 3), (5, 6)], x0, x1, 1 / mass)
    label = z.label.numpy()
    assert len(set(label[[0, 1, 2, 3]])) == 1 and label[5] == label[6] != label[0]
    assert set(np.flatnonzero(z.member.numpy())) == {0, 1, 2, 3, 5, 6}
    z.move(rec, xs, st, 0.01, counters, 0)
    x = st.x.numpy().astype(float)
    assert list(counters.numpy()) == [2, 6]  # two zones, six vertices moved
    np.testing.assert_allclose(x[[4, 7]], x1[[4, 7]], atol=1e-6)  # not in a zone: untouched
    for zone in ([0, 1, 2, 3], [5, 6]):
        m = mass[zone]
        d0 = np.linalg.norm(x0[zone][:, None] - x0[zone][None], axis=2)
        d1 = np.linalg.norm(x[zone][:, None] - x[zone][None], axis=2)
        np.testing.assert_allclose(d1, d0, atol=2e-6)  # rigid
        c1 = (m[:, None] * x1[zone]).sum(0) / m.sum()
        np.testing.assert_allclose((m[:, None] * x[zone]).sum(0) / m.sum(), c1, atol=2e-6)
        c0 = (m[:, None] * x0[zone]).sum(0) / m.sum()
        q = x0[zone] - c0
        L_before = (m[:, None] * np.cross(q, (x1[zone] - x0[zone]) - (c1 - c0))).sum(0)
        L_after = (m[:, None] * np.cross(q, (x[zone] - x0[zone]) - (c1 - c0))).sum(0)
        # the rotation is finite: its momentum matches to second order in the small angle
        np.testing.assert_allclose(L_after, L_before, atol=3e-2 * np.abs(L_before).max())
    v = st.v.numpy()
    np.testing.assert_allclose(v[[0, 1, 2, 3, 5, 6]], (x - x0)[[0, 1, 2, 3, 5, 6]] / 0.01,
                               rtol=1e-4, atol=1e-3)


def test_impact_zone_with_pins_follows_their_rigid_motion():
    """A zone holding pinned vertices turned by a prescribed rotation: its free vertex ends where
    that rotation takes it (the zone follows the pins), the pins keep their positions."""
    x0 = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.3, 0.3, 0.5]])
    a = 0.02
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    x1 = x0.copy()
    x1[:3] = x0[:3] @ R.T + [0.01, 0, 0]  # the pins: turned and shifted
    x1[3] = [0.2, 0.2, -0.4]  # the free vertex: elsewhere
    z, rec, xs, st, counters = _zones_setup(4, [(3, 0, 1, 2)], x0, x1, [0, 0, 0, 1.0])
    z.move(rec, xs, st, 0.01, counters, 0)
    x = st.x.numpy()
    np.testing.assert_allclose(x[:3], x1[:3], atol=1e-6)
    np.testing.assert_allclose(x[3], x0[3] @ R.T + [0.01, 0, 0], atol=5e-4)


@wp.kernel
def _floor_kernel(x: wp.array(dtype=wp.vec3)):
    """A floor at y = 0 for `hold_grounded`: every point below it lifted onto it."""
    i = wp.tid()
    if x[i][1] < 0.0:
        x[i] = wp.vec3(x[i][0], 0.0, x[i][2])


@pytest.mark.parametrize("still", [1, 0])
def test_impact_zone_that_a_still_obstacle_would_push_goes_back_to_its_start(still):
    """Two zones, (0, 1, 2) and (4, 5); the obstacles' projection (here: a floor at y = 0 that
    lifts every point below it) would move vertex 1 after the rigid move, so its whole zone
    returns to the path's start with zero velocity and is counted; the other zone and vertex 3
    (in none) keep their ends. With an obstacle moving this step (``still`` 0) nothing is held."""
    x0 = np.array([[0.0, 0.1, 0], [0.1, 0.02, 0], [0.2, 0.1, 0], [0.3, 0.2, 0], [0.5, 0.3, 0],
                   [0.6, 0.3, 0]])
    x1 = x0 + [0.0, -0.05, 0.01]  # vertex 1 ends below the floor
    z, rec, xs, st, counters = _zones_setup(6, [(0, 1), (1, 2), (4, 5)], x0, x1, np.ones(6))
    z.move(rec, xs, st, 0.01, counters, 0)
    moved = st.x.numpy().copy()

    held = wp.zeros(1, dtype=int, device="cpu")
    z.hold_grounded(xs, st, lambda x: wp.launch(_floor_kernel, len(x), [x], device="cpu"),
                    wp.array([still], dtype=int, device="cpu"), held, 0)
    x, v = st.x.numpy(), st.v.numpy()
    if still:
        np.testing.assert_allclose(x[:3], x0[:3], atol=1e-7)
        assert np.all(v[:3] == 0.0) and held.numpy()[0] == 1
    else:
        np.testing.assert_allclose(x[:3], moved[:3])
        assert held.numpy()[0] == 0
    np.testing.assert_allclose(x[3:], moved[3:])  # the other zone, and no zone, untouched
    assert not z.grounded.numpy().any()  # the flags are clear for the next pass


def test_pbd_fold_in_long_steps_keeps_its_zones_off_the_floor():
    """PBD's 12 x 12 fold at one step a frame, 20 fps: the response falls back on impact zones
    (about a hundred), whose rigid motion had left a vertex 0.5 mm inside the floor's thickness;
    a zone that the floor would push now goes back to its start (counted), so every vertex
    stays at the thickness, and nothing crosses."""
    scene = fold(solver="pbd", res=12, frames=40, fps=20, substeps=1)
    th = scene.collision.thickness
    least = [np.inf]
    st = scene.run(None, quiet=True, energy=False, check_intersections=True,
                   on_frame=lambda f, s: least.__setitem__(
                       0, min(least[0], float(s.x.numpy()[:, 1].min()))))
    s = scene.collision.stats
    assert st.crossing_frames == 0 and s["self_zones_held_total"] > 0
    assert least[0] >= th - 1e-4


def _weak_stack(**stack_args):
    """``stack`` under PD with a deliberately weak self-collision projection (one round of one
    Jacobi iteration) and the self-contacts after the solve only (inside it, PD alone keeps the
    layers apart and the fall-backs are never reached): (scene, crossings per frame)."""
    from warp_cloth.collision.check import SelfIntersectionChecker
    from warp_cloth.collision.self_collision import SelfCollision
    from warp_cloth.contact_scenes import stack

    scene = stack(solver="pd", res=8, frames=60, **stack_args)
    m = scene.model
    sc = scene.collision.self_collision
    scene.collision.self_collision = SelfCollision(m, sc.thickness, rounds=1, iterations=1)
    scene.collision.self_in_solve = False
    chk = SelfIntersectionChecker(m.mesh.triangles, m.mesh.edges, m.num_vertices)
    crossings = []
    scene.run(None, quiet=True, energy=False, on_frame=lambda f, st: crossings.append(chk(st.x)))
    return scene, crossings


def test_impact_zone_union_runs_until_a_round_changes_nothing():
    """Zones are merged by rounds of label propagation that go on until one changes no label
    (a fixed number of rounds sufficed on the CPU, where a sweep sees its own writes, but not on
    a GPU, whose threads may all read the labels from before the sweep). Chains of 2,000 entries
    whose vertex ids are shuffled and whose entries come in shuffled or reversed order: every
    chain ends as one zone, every label a root, the loop stopped after a round that changed
    nothing (a further round with the same entries changes nothing), and a shuffled chain
    needs more than one changing round (the loop is what merged it)."""
    import warp as wp

    from warp_cloth.collision.impact_zones import ImpactZones, zone_jump_kernel, zone_union_kernel
    from warp_cloth.collision.record import make_record

    n, N = 2001, 2000

    class _M:
        num_vertices = n
        device = "cpu"

    rec = make_record(N, "cpu")
    z = ImpactZones(_M)
    rng = np.random.default_rng(11)
    most = 0
    for trial in range(4):
        ids = rng.permutation(n) if trial % 2 else np.arange(n)
        order = rng.permutation(N) if trial < 2 else np.arange(N)[::-1]
        vid = -np.ones((N, 4), np.int32)
        vid[:, 0], vid[:, 1] = ids[:-1][order], ids[1:][order]
        rec.vertex.assign(vid)
        rec.count.assign(np.array([N], np.int32))
        z.reset()
        z.merge(rec, 1)
        label = z.label.numpy()
        assert len(np.unique(label)) == 1 and np.all(label[label] == label)
        most = max(most, z.union_rounds)
        changed = wp.zeros(1, dtype=int, device="cpu")
        wp.launch(zone_union_kernel, 1, [rec, z.label, 1, changed], device="cpu")
        wp.launch(zone_jump_kernel, n, [z.label, changed], device="cpu")
        assert changed.numpy()[0] == 0
    assert most >= 3


def test_contacts_dropped_by_the_impact_zone_passes_are_counted():
    """A record with room for 2 entries, two patches driven 20 cm through each other in one
    step: the impact zones' detections drop entries too, and they go to the step's overflow
    count (the frame's report then grows the record, and the runner may run the frame again).
    Before, only the rounds' drops were counted: the passes merged the entries that fit, without
    a word. The zones' counts are the step's distinct zones and vertices (at most the cloth's)."""
    import warp as wp

    from warp_cloth import ClothModel, TriMesh
    from warp_cloth.collision.self_collision import STAT_KEYS, SelfCollision

    a = TriMesh.grid(2, 2, size=1.0, plane="xz", origin=(0, 0.0, 0))
    b = TriMesh.grid(2, 2, size=1.0, plane="xz", origin=(0.13, 0.1, 0.17))
    v = np.vstack([a.vertices, b.vertices])
    t = np.vstack([a.triangles, b.triangles + len(a.vertices)])
    model = ClothModel(TriMesh(v, t), density=0.1, stretch_stiffness=100.0)
    sc = SelfCollision(model, 0.005, capacity=2)
    i_over = STAT_KEYS.index("self_overflow")
    seen = {"before": None, "passes": 0}
    fallback, zone_move = sc._fallback, sc._zone_move

    def logged_fallback(*args, **kw):
        seen["before"] = int(sc.counters.numpy()[i_over])
        fallback(*args, **kw)

    def logged_zone_move(*args, **kw):  # after a zone pass's detection
        seen["passes"] += int(sc.record.overflow.numpy()[0])
        zone_move(*args, **kw)

    sc._fallback, sc._zone_move = logged_fallback, logged_zone_move
    state = model.state()
    x0 = wp.clone(state.x)
    x1 = v.copy()
    x1[len(a.vertices):, 1] -= 0.2
    state.x.assign(x1.astype(np.float32))
    sc.resolve(state, x0, 1 / 60)
    c = dict(zip(STAT_KEYS, sc.counters.numpy().tolist()))
    assert seen["before"] is not None and seen["passes"] > 0
    assert c["self_overflow"] >= seen["before"] + seen["passes"]
    assert 0 < c["self_zone_vertices"] <= len(v) and c["self_zones"] >= 1


def test_weak_projection_falls_back_on_impact_zones_not_crossings():
    """With one round of one Jacobi iteration the projection leaves contacts unresolved: the
    rigid impact zones take them (counted, without the whole-cloth return), and no frame has a
    crossing. Two sheets dropped onto a sphere, one PD step a frame (a fold no longer reaches
    the zones: since vertex contact runs inside the rounds, its floor no longer pushes the
    lower layer back into the upper one)."""
    scene, crossings = _weak_stack(sheets=2, substeps=1)
    st = scene.collision.stats
    assert st["self_zones_total"] > 0 and st["self_zone_vertices_total"] >= 2
    assert st["self_fallback_all_total"] == 0
    assert max(crossings) == 0


def test_obstacle_contact_inside_the_rounds_pushes_no_layer_through_another():
    """Vertex contact runs inside the self-collision rounds (the projection may push a layer
    lying on an obstacle into it), each followed by a fresh detection. Run once after the
    response instead, it pushed sheets lying on each other through each other: three sheets on
    a sphere under the weak projection had crossings in 12 frames (and 94 whole-cloth
    returns). Here: none."""
    scene, crossings = _weak_stack()
    assert max(crossings) == 0, f"crossings in {sum(c > 0 for c in crossings)} frames"
    assert scene.collision.stats["self_zones_total"] > 0  # the layers did press together


def test_run_counts_crossings_and_cli_exit_status(tmp_path, capsys):
    """``check_intersections``: RunStats counts the frames with crossings (none with
    self-collision, some without), the CLI warns per frame and exits 5."""
    scene = fold(solver="implicit", res=10, frames=40, size=0.6, angle=150.0,
                 self_collision=False)
    st = scene.run(None, quiet=True, energy=False, check_intersections=True)
    assert st.crossing_frames > 0 and st.max_crossings > 0
    assert "self-intersection: " in st.summary()
    scene = fold(solver="implicit", res=10, frames=40, size=0.6, angle=150.0)
    st = scene.run(None, quiet=True, energy=False, check_intersections=True)
    assert st.crossing_frames == 0 and st.max_crossings == 0
    assert scene.run(None, quiet=True, energy=False).crossing_frames is None  # not checked
    out = tmp_path / "f.usd"
    rc = cli.main(["run", "fold", "--res", "6", "--frames", "40", "--self-collision", "off",
                   "--check-intersections", "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 5 and "passes through itself" in err and "crossing edge-triangle pairs" in err


def test_record_overflow_is_reported_and_the_record_regrows(capsys):
    """A self-collision record with room for 4 entries: the dropped contacts are reported on
    stderr, the room doubles at each frame end until nothing is dropped (the captured graph
    recorded again with the new arrays). Without retries (`test_retry` has them), so that the
    frames that dropped contacts are written."""
    from warp_cloth.collision.self_collision import SelfCollision

    scene = fold(solver="implicit", res=8, frames=30, size=0.6, angle=150.0)
    scene.retries = 0
    m = scene.model
    th = scene.collision.self_collision.thickness
    sc = SelfCollision(m, th, capacity=4)
    scene.collision.self_collision = sc
    over = []
    scene.run(None, energy=False, progress=False,
              on_frame=lambda f, st: over.append(sc.stats["self_overflow"]))
    err = capsys.readouterr().err
    assert "did not fit the record; its room grows to" in err
    assert sc.capacity >= 64  # grew several times
    assert over[-1] == 0 and max(over) > 0  # dropped early, nothing at the end


def test_solve_self_contacts_overflow_is_reported_and_regrows(capsys):
    """The solve's own self-contact record with room for 4 entries: the dropped pairs are
    counted in the solver's stats, reported on stderr, and the room doubles at frame ends."""
    scene = fold(solver="implicit", res=8, frames=30, size=0.6, angle=150.0)
    cc = scene.solver._contact()
    cc._grow_self(4)
    scene.run(None, energy=False, progress=False)
    err = capsys.readouterr().err
    assert "did not fit the solve's record" in err
    assert cc.self_record.vertex.shape[0] >= 16
    assert scene.solver.stats["self_solve_dropped"] > 0


@pytest.mark.parametrize("solver_name", ["pd", "implicit"])
def test_self_contacts_inside_the_solve_keep_a_fold_calm(solver_name):
    """Self-contacts as penalty terms of the implicit and projective solves (the stage's
    default ``self_in_solve``): the fold (16 x 16, 90 frames) gains at most 2 mJ in any frame
    and stretches under 2 %, without crossings; with the self-contacts only after the solve,
    the solve pushes the layers into each other every step and the response pushes them apart
    (measured with the inelastic response: +23 mJ in a frame and 2.6 % with pd, +0.40 J and
    2.8 % with implicit; in solve 0.19 / 0.23 mJ, 0.33 / 0.31 %; since the floor holds the
    lower layer inside the response's rounds, the upper one takes the whole correction where
    the half lands: implicit 1.53 % in that frame, against 0.53 % when the lower layer could be
    pushed into the floor). (On a 12 x 12 fold of 0.6 m the response alone is as calm since its
    velocity rule became inelastic.)"""
    from warp_cloth.diagnostics import Meter

    out = {}
    for ins in (True, False):
        scene = fold(solver=solver_name, res=16, frames=90)
        scene.collision.self_in_solve = ins
        meter, E = Meter(scene.model), []
        r = scene.run(None, quiet=True, check_intersections=True,
                      on_frame=lambda f, st: E.append(meter(st).energy))
        out[ins] = (float(np.diff(E).max()), r.max_strain, r.crossing_frames)
    rise, strain, crossings = out[True]
    assert rise < 2e-3 and strain < 0.02 and crossings == 0, out
    assert out[False][0] > 5 * rise, out  # the same fold, self-contacts after the solve only


def test_implicit_newton_converges_through_a_fold_landing_on_itself(short_steps):
    """The 12 x 12 fold under implicit Euler, 60 frames (the sheet lands on the floor and on
    itself): most steps converge. Two things had stalled them. A resting self-contact's
    equilibrium lay about 1e-6 m inside its constraint, where float32 roundings of its gap
    switch the plain penalty's stiffness on and off (thousands of a folded sheet's entries
    flipped between iterations): the self-contacts' penalty now starts with a cubic onset
    (`normal_penalty`, `SELF_ONSET`). And an entry just above its constraint had no stiffness,
    so Newton's direction drove its vertex deep in and the line search cut the step to 1/64
    (the contact energies rose by 4.8e-3 J at the full step): an entry moving toward its
    constraint, or inside it at the last assembly, now keeps the penalty's block there
    (`HOLD_FLIPS`, self-contacts). Short steps: 89 of 120 with neither, 73 without the hold,
    51 without the onset, 17 with both."""
    scene = fold(solver="implicit", res=12)
    short, steps, state = short_steps(scene, 60)
    assert short <= 0.3 * steps, (short, steps)
    assert np.isfinite(state.positions()).all()


def test_implicit_fold_lying_on_the_floor_does_not_slide_away():
    """A 12 x 12 sheet folded almost flat (170 degrees) under implicit Euler: once it lies on
    the floor it stays there. CG stopped at a relative residual of 0.1 left a residual whose
    sum over the vertices, a force no spring or contact exerts, pushed the folded sheet
    sideways every step: it slid off at 0.55 m/s after 45 frames, its energy up from 0.022 to
    0.041 J. The inner solve now ends, in Newton iterations with active self-contacts, with
    the Galerkin correction along the free vertices' translations (`CGSolver.translation`)."""
    from warp_cloth.diagnostics import Meter

    scene = fold(solver="implicit", res=12, frames=45, angle=170.0)
    meter, E, speed = Meter(scene.model), [], []

    def on_frame(f, st):
        E.append(meter(st).energy)
        speed.append(float(np.linalg.norm(st.v.numpy(), axis=1).mean()))

    r = scene.run(None, quiet=True, check_intersections=True, on_frame=on_frame)
    assert r.crossing_frames == 0
    assert max(speed[20:]) < 0.02  # at rest on the floor (it slid at 0.1-0.55 m/s)
    assert E[-1] <= E[10] + 1e-4


@pytest.mark.parametrize("guess", ["start", "auto"])
def test_guesses_without_the_gravity_step_fold_and_rest_converged(guess):
    """Implicit Euler from ``x0`` or (``"auto"``, in steps with contact) ``x0 + dt v0``: the
    10 x 10 fold at 150 degrees falls over and then rests with Newton converging in a step or
    two. The inertial guess presses every supported vertex ``dt^2 g`` into its support and
    runs 3-5 iterations a step there, stopping at residuals of 2e-3 to 8e-3 m. Without the
    resting-contact rule (`newton_contact_kernel`) both guesses froze the sheet in its start
    pose (every step stalled: Newton's direction ignored the floor under the resting
    vertices and the line search refused it). Frames 30-59 (at rest after frame ~25), auto:
    1.53 Newton iterations a step on average with the self-contacts' velocity rule against a
    world at rest, 1.8 with the rule in the layers' frame (`layer_apply`: a layer resting on
    one takes its small motion; over frames 30-44 alone 1.93 and 2.13)."""
    from warp_cloth.collision.check import SelfIntersectionChecker

    scene = fold(solver="implicit", res=10, frames=60, size=0.6, angle=150.0,
                 solver_options={"initial_guess": guess})
    m, s = scene.model, scene.solver
    chk = SelfIntersectionChecker(m.mesh.triangles, m.mesh.edges, m.num_vertices)
    crossings, its, res = [], [], []

    def on_frame(f, st):
        crossings.append(chk(st.x))
        if f >= 30:
            its.append(s.stats["newton_iterations"])
            res.append(s.stats["residual"])

    scene.run(None, quiet=True, energy=False, on_frame=on_frame)
    assert max(crossings) == 0
    assert scene.state.positions()[:, 1].max() < 0.1  # folded
    assert np.mean(its) <= 2.0, its
    assert max(res) < 1.5e-3, res


def test_implicit_curtain_landing_at_speed_keeps_its_stretch():
    """A vertical 8 x 8 curtain (0.5 m, 2 mm thickness) dropped from 1.5 m lands on the floor
    at 5.6 m/s and piles onto itself, at 30 fps (two implicit steps a frame). Its bottom row
    stops at the floor while the rows above fall on through where the prediction put them:
    the self-contacts the solve took from the predicted path (all rows falling side by side)
    have none of those pairs, and at Newton's cap a bottom vertex stood 3 cm above its start
    with the row above gone through it. The response after the solve then pulled single
    vertices centimetres apart: 14.8 % max strain (16 x 16: 41 %; explicit Euler 6.8 % on a
    10 x 10). Now such a step, still moving vertices more than the thickness at its cap, goes
    on with the self-contacts detected again on the path to its iterate (`IMPACT_ROUNDS`):
    2.3 %. Without the new detection, the extra iterations alone: 13.6 %."""
    import warp_cloth as wc
    from warp_cloth.collision.obstacles import Plane

    n, size = 8, 0.5
    mesh = wc.TriMesh.grid(n, n, size=size, plane="xy", origin=(-size / 2, 1.52, 0.0))
    x = mesh.vertices.copy()
    x[:, 2] = 0.03 * np.sin(7 * x[:, 0]) * ((x[:, 1] - x[:, 1].min()) / size)  # a little wavy
    model = wc.ClothModel(wc.TriMesh(x, mesh.triangles), density=0.15,
                          stretch_stiffness=1000.0, bending="quadratic", bend_stiffness=1e-4,
                          damping=0.1)
    stage = CollisionStage(model, [Plane()], thickness=0.002, friction=0.4, self_collision=True)
    solver = wc.make_solver("implicit", model, newton_iterations=10)
    solver.set_collision(stage)
    scene = wc.Scene(model, solver, fps=30, frames=30, strain_bound=10.0, name="curtain")
    stats = scene.run(None, quiet=True, energy=False, check_intersections=True)
    assert stats.crossing_frames == 0
    assert solver.stats["impact_steps"] > 0  # the landing's steps went on
    assert stats.max_strain < 0.05, stats.max_strain
    # landed and piled up: its top (2.02 m at the start) fell more than 1.65 m. (How the pile
    # stands at frame 30 is chaotic: its top edge leaned at 0.12-0.32 m from run to run of
    # slightly different code, toppling by frame 80 where it leaned; `/tmp/s27/curt.py`)
    assert scene.state.positions()[:, 1].max() < 0.35


def test_implicit_folded_sheet_at_rest_does_not_pop():
    """A 12 x 12 fold (120 degrees) under implicit Euler, lying folded on the floor from frame
    60: no vertex moves more than half a millimetre between frames. With CG stopped at its 0.1
    in the Newton iterations with active self-contacts, vertices of the upper layer popped up to
    4.8 mm (median 0.74 mm a frame); the inner solve there now ends at `SELF_LINEAR_TOLERANCE`
    (0.13 mm at most). A bad value is refused."""
    from warp_cloth.solvers.implicit import SELF_LINEAR_TOLERANCE

    scene = fold(solver="implicit", res=12, frames=90, angle=120.0)
    assert scene.solver.self_linear_tolerance == SELF_LINEAR_TOLERANCE < 0.01
    prev, moves = [None], []

    def on_frame(f, st):
        x = st.x.numpy().copy()
        if f > 60:
            moves.append(float(np.linalg.norm(x - prev[0], axis=1).max()))
        prev[0] = x

    r = scene.run(None, quiet=True, check_intersections=True, on_frame=on_frame)
    assert r.crossing_frames == 0 and max(moves) < 5e-4, max(moves)
    for bad in (0.0, 1.0, -1e-3, float("nan"), "tight"):
        with pytest.raises(ValueError, match="self_linear_tolerance"):
            fold(solver="implicit", res=2, frames=1,
                 solver_options={"self_linear_tolerance": bad})


def test_inelastic_response_velocity_exact():
    """The response's velocity rule on exact cases: an approaching vertex loses its approach
    along the correction (a resting contact over one step: exactly ``v += d / dt``), one
    already leaving along it keeps its velocity (``v += d / dt`` kicked it), a tangential
    velocity is kept, and a vertex without correction is untouched."""
    import warp as wp

    from warp_cloth.collision.features import inelastic_apply_kernel

    dt, g = 0.01, 9.81
    x = wp.array(np.zeros((4, 3)), dtype=wp.vec3)
    v0 = np.array([[0.0, -g * dt, 0.0],     # resting: fell g dt^2 in the step
                   [0.0, 0.5, 0.0],          # already leaving upwards
                   [0.3, -2.0, 0.0],         # fast impact with a tangential part
                   [1.0, 2.0, 3.0]])         # no correction
    v = wp.array(v0, dtype=wp.vec3)
    d = np.array([[0.0, g * dt * dt, 0.0], [0.0, 1e-3, 0.0], [0.0, 1e-3, 0.0], [0.0, 0.0, 0.0]])
    acc = wp.array(2.0 * d, dtype=wp.vec3)
    cnt = wp.array(np.array([2, 2, 2, 0], dtype=np.int32), dtype=int)
    wp.launch(inelastic_apply_kernel, 4, [x, v, acc, cnt, wp.zeros(0, dtype=wp.vec3), 0.0])
    out = v.numpy()
    np.testing.assert_allclose(out[0], v0[0] + d[0] / dt, atol=1e-7)  # = 0
    np.testing.assert_allclose(out[1], v0[1])
    np.testing.assert_allclose(out[2], [0.3, 0.0, 0.0], atol=1e-7)
    np.testing.assert_allclose(out[3], v0[3])
    np.testing.assert_allclose(x.numpy(), d, atol=1e-9)
    assert not acc.numpy().any() and not cnt.numpy().any()

    # a moving obstacle's feature (``moved``: how far the entries' planes moved, summed like
    # ``acc``): the approach is taken relative to the surface, which here rises at 0.5 m/s
    up = np.array([0.0, 0.5 * dt, 0.0])
    x = wp.array(np.zeros((3, 3)), dtype=wp.vec3)
    v0 = np.array([[0.0, 0.0, 0.0],      # at rest: the surface runs into it, it leaves with it
                   [0.2, 0.8, 0.0],      # already leaving faster than the surface
                   [0.0, -1.0, 0.0]])    # falling onto it
    v = wp.array(v0, dtype=wp.vec3)
    acc = wp.array(np.tile([0.0, 2e-3, 0.0], (3, 1)), dtype=wp.vec3)
    cnt = wp.array(np.array([2, 2, 2], dtype=np.int32), dtype=int)
    moved = wp.array(np.tile(2.0 * up, (3, 1)), dtype=wp.vec3)
    wp.launch(inelastic_apply_kernel, 3, [x, v, acc, cnt, moved, 1.0 / dt])
    np.testing.assert_allclose(v.numpy(), [[0.0, 0.5, 0.0], [0.2, 0.8, 0.0], [0.0, 0.5, 0.0]],
                               atol=1e-6)
    assert not moved.numpy().any()


def _layer_case(v0, masses, b):
    """One vertex-triangle entry (vertex 0 over the point ``b`` of triangle 1 2 3, 4 mm above,
    thickness 5 mm): the response's Jacobi projection and its velocity rule once (`_project`'s
    kernels): (x, v)."""
    from warp_cloth.collision.features import jacobi_project_kernel
    from warp_cloth.collision.record import KIND_VERTEX_TRIANGLE, make_record
    from warp_cloth.collision.self_collision import layer_apply_kernel

    x0 = np.array([[0.0, 0.004, 0.0], [0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.0, 0.5]])
    x0[0, [0, 2]] = b @ x0[1:, [0, 2]]
    rec = make_record(4, "cpu")
    rec.count.fill_(1)
    rec.vertex.assign([wp.vec4i(0, 1, 2, 3)])
    rec.weight.assign([wp.vec4(1.0, *(-b))])
    rec.normal.assign([wp.vec3(0.0, 1.0, 0.0)])
    rec.offset.assign([0.005])
    rec.kind.assign([KIND_VERTEX_TRIANGLE])
    im = wp.array(1.0 / masses, dtype=float)
    x, v = wp.array(x0, dtype=wp.vec3), wp.array(v0, dtype=wp.vec3)
    acc, cnt = wp.zeros(4, dtype=wp.vec3), wp.zeros(4, dtype=int)
    frame = wp.full(4, -1.0e30, dtype=float)
    none = wp.zeros(0, dtype=wp.vec3)
    wp.launch(jacobi_project_kernel, 1, [rec, 0, x, im, acc, cnt, wp.zeros(2, dtype=int), 0.0,
                                         1, none, none, v, frame])
    wp.launch(layer_apply_kernel, 4, [x, v, acc, cnt, frame])
    assert not acc.numpy().any() and not cnt.numpy().any()
    assert (frame.numpy() == -1.0e30).all()
    return x.numpy(), v.numpy().astype(np.float64)


@pytest.mark.parametrize("common", [(0.0, 0.0, 0.0), (0.7, -5.0, 0.3)])
def test_self_contact_velocity_rule_is_the_same_in_a_falling_frame(common):
    """The self-contacts' velocity rule on one vertex-triangle entry (barycentric 0.5 0.3 0.2,
    unequal masses, the vertex 1 mm inside the 5 mm thickness), all four carried by a common
    velocity (none, or a fall of 5 m/s with a drift). The vertex approaching at 2 m/s takes
    the triangle's normal velocity (its approach, measured in the layer it met, taken out;
    its tangential motion kept); the triangle, pushed away from it, keeps its velocity; the
    kinetic energy falls; the outcome relative to the common motion is the same in both
    frames. The rule before measured the approach against a world at rest: falling at 5 m/s,
    the vertex lost its fall. Moving apart, nothing changes. Head on (the triangle rising at
    1 m/s, the vertex falling at 1 m/s, no common motion): both stop. Nothing is given speed
    along a push: a triangle rising into a vertex at rest stops, the vertex stays at rest."""
    b = np.array([0.5, 0.3, 0.2])
    m = np.array([0.02, 0.01, 0.03, 0.015])
    w = np.array([1.0, *(-b)])
    c = np.array(common)
    rel = np.array([[0.3, -2.0, 0.0], [0.0, 0, 0.1], [-0.2, 0, 0], [0, 0, 0]])
    ke = lambda u: 0.5 * m @ (u * u).sum(axis=1)
    x, v = _layer_case(c + rel, m, b)
    assert abs(w @ x[:, 1] - 0.005) < 1e-7  # positions: the gap closed
    expect = rel.copy()
    expect[0, 1] = 0.0
    np.testing.assert_allclose(v - c, expect, atol=1e-5)
    assert ke(v) < ke(c + rel)
    apart = rel.copy()
    apart[0, 1] = 1.5
    x, v = _layer_case(c + apart, m, b)
    np.testing.assert_allclose(v, c + apart, atol=1e-6)
    if not c.any():
        head = np.array([[0, -1.0, 0], [0, 1.0, 0], [0, 1.0, 0], [0, 1.0, 0]])
        x, v = _layer_case(head, m, b)
        np.testing.assert_allclose(v, 0.0, atol=1e-6)
        rise = np.array([[0, 0.0, 0], [0, 1.0, 0], [0, 1.0, 0], [0, 1.0, 0]])
        x, v = _layer_case(rise, m, b)
        np.testing.assert_allclose(v, 0.0, atol=1e-6)


def test_each_solver_sets_the_self_contacts_velocity_frames():
    """The layers' frames under implicit Euler, PBD and PD; the rule at rest under explicit
    Euler (`SymplecticEuler.self_contact_layer_frames`)."""
    from warp_cloth import make_solver

    for name, frames in (("explicit", False), ("implicit", True), ("pbd", True), ("pd", True)):
        model = sheet_model(res=4)
        stage = CollisionStage(model, self_collision=True)
        make_solver(name, model, collision=stage)
        assert stage.self_collision.layer_frames is frames, name


@pytest.mark.parametrize("solver_name", ["implicit", "pbd", "pd"])
def test_sheets_meeting_in_free_fall_keep_falling_freely(solver_name):
    """Two 6 x 6 sheets 2 cm apart fall freely, the upper one 1 m/s faster: after 20 frames
    they move together, no crossing, and neither is slower than free fall (their contact
    takes out their approach, not the fall that gravity gave both). The rule before took each
    vertex's approach against a world at rest: the upper sheet ended 0.15 m/s slower than
    free fall, the pair with less momentum than gravity alone gives it. Explicit Euler keeps
    that rule (`SymplecticEuler.self_contact_layer_frames`; README, *Self-collision*)."""
    from warp_cloth import ClothModel, TriMesh, make_solver
    from warp_cloth.collision.check import SelfIntersectionChecker
    from warp_cloth.scene import Scene

    g = TriMesh.grid(6, 6, size=0.5, plane="xz", origin=(-0.25, 3.0, -0.25))
    k = len(g.vertices)
    mesh = TriMesh(np.concatenate([g.vertices, g.vertices + [0.01, 0.02, 0.013]]),
                   np.concatenate([g.triangles, g.triangles + k]))
    v0 = np.zeros((2 * k, 3))
    v0[k:, 1] = -1.0
    model = ClothModel(mesh, density=0.15, stretch_stiffness=1000.0, damping=0.0, velocity=v0)
    stage = CollisionStage(model, self_collision=True)
    scene = Scene(model, make_solver(solver_name, model, collision=stage), fps=60.0, frames=20)
    chk = SelfIntersectionChecker(mesh.triangles, mesh.edges, model.num_vertices)
    crossings = []
    scene.run(None, quiet=True, energy=False, on_frame=lambda f, st: crossings.append(chk(st.x)))
    m = model.masses
    v = scene.state.velocities().astype(np.float64)
    t = scene.state.t
    assert t > 0.3
    fall = -9.81 * t
    assert max(crossings) == 0
    assert stage.self_collision.stats["self_contacts_total"] > 0
    lower, upper = v[:k, 1].mean() - fall, v[k:, 1].mean() - fall
    assert lower < 0.02 and upper < 0.02, (lower, upper)  # no slower than free fall
    assert abs(upper - lower) < 0.05, (lower, upper)  # together
    assert m @ v[:, 1] < m.sum() * fall * (1.0 - 1e-3)


def _two_sheets(gap, res=6, **model_args):
    """Two flat ``res`` x ``res`` sheets (1 m), the second ``gap`` m above the first (its
    vertices, edges and triangles numbered after the first's)."""
    from warp_cloth.mesh import TriMesh
    from warp_cloth.model import ClothModel

    m = sheet_model(res=res).mesh
    n = len(m.vertices)
    mesh = TriMesh(np.concatenate([m.vertices, m.vertices + [0.0, gap, 0.0]]),
                   np.concatenate([m.triangles, m.triangles + n]))
    return ClothModel(mesh, device="cpu", **model_args)


def _span_stage(motion=0.25, gravity=(0.0, 0.0, 0.0), layers=None):
    """A flat 6x6 sheet (two, ``layers`` m apart, when given) with self-collision only, no
    gravity: nothing moves unless told."""
    from warp_cloth import make_solver

    model = sheet_model(res=6, gravity=gravity) if layers is None else \
        _two_sheets(layers, gravity=gravity)
    stage = CollisionStage(model, self_collision=True, self_motion=motion)
    solver = make_solver("explicit", model, collision=stage)
    return model, stage, solver, _count_responses(stage)


def _count_responses(stage):
    """The steps each self-collision response of ``stage`` spans, appended as they run."""
    calls = []
    orig = stage.self_collision.resolve

    def counting(state, x_start, dt, steps=None):
        calls.append(1 if steps is None else int(steps.numpy()[0]))
        orig(state, x_start, dt, steps)

    stage.self_collision.resolve = counting
    return calls


def test_self_collision_spans_end_on_frames_and_follow_the_motion():
    """Under `CollisionStage.plan` the response runs once a span of steps has moved a vertex
    past its allowance (frames of 8 steps or more) or ``self_motion`` thicknesses, and always
    on a frame's last step; each response is told how many steps its path spans. Without
    `plan`, or with ``self_motion=0``, every step."""
    model, stage, solver, calls = _span_stage()
    dt = 0.25 * solver.stable_dt(model)
    state = model.state()
    stage.plan(10)
    for _ in range(20):
        solver.step(state, dt)
    assert calls == [10, 10]  # nothing moves: only the frames' ends
    # the whole sheet moving 1 mm a step: clear of itself (cells of 17 cm), each vertex may
    # move its allowance, (4 - 1.01) / 2 x 5 mm = 7.5 mm, before a response -> the 8th step
    sc = stage.self_collision
    assert sc.allowances
    assert sc.reach_max == pytest.approx(0.5 * (sc.clearance - 1.01 * sc.thickness))
    assert np.allclose(sc._allow.numpy(), 0.5 * (sc.clearance - 1.01 * sc.thickness))
    calls.clear()
    stage.plan(10)
    state.v.assign(np.tile([0.0, 1e-3 / dt, 0.0], (model.num_vertices, 1)))
    for _ in range(20):
        solver.step(state, dt)
    # a new plan forgets the allowances: its first span ends at the reach (1.25 mm), then 8 steps
    assert calls == [2, 8, 8, 2], calls
    # frames of fewer than 8 steps keep the reach everywhere: every 2nd step
    calls.clear()
    stage.plan(5)
    assert not sc.allowances
    for _ in range(5):
        solver.step(state, dt)
    assert calls == [2, 2, 1], calls
    # two sheets 7 mm apart (allowance (7 - 5.05) / 2 mm, below the reach of 0.25 x 5 mm),
    # the upper one sliding 1 mm a step: every 2nd step
    model, stage, solver, calls = _span_stage(layers=0.007)
    state = model.state()
    stage.plan(10)
    for _ in range(10):
        solver.step(state, dt)
    v = np.zeros((model.num_vertices, 3))
    v[model.num_vertices // 2:, 0] = 1e-3 / dt
    state.v.assign(v)
    calls.clear()
    for _ in range(10):
        solver.step(state, dt)
    assert calls == [2, 2, 2, 2, 2], calls
    # by hand (no plan) and self_motion=0: every step
    for stage_args in ({"plan": False}, {"motion": 0.0}):
        model, stage, solver, calls = _span_stage(stage_args.get("motion", 0.25))
        if stage_args.get("plan", True):
            stage.plan(5)
        state = model.state()
        for _ in range(5):
            solver.step(state, dt)
        assert calls == [1] * 5, (stage_args, calls)
    with pytest.raises(ValueError, match="self_motion"):
        CollisionStage(model, self_collision=True, self_motion=-0.1)
    with pytest.raises(ValueError, match="self_motion"):
        CollisionStage(model, self_collision=True, self_motion="fast")


@pytest.mark.parametrize("motion", [0.25, 0.0])
def test_explicit_fold_with_spans_stays_apart_and_comes_to_rest(motion):
    """Explicit Euler's many small substeps with self-collision once per span (the default)
    and after every step: no crossing in any frame, and the folded sheet comes to rest (the
    response's velocity rule; with ``v += d / dt`` the spans kicked the resting layers to
    1-13 m/s), in far fewer responses than steps."""
    crossings, scene = _fold("explicit", res=8, frames=75, motion=motion)
    st = scene.collision.self_collision.stats
    assert max(crossings) == 0 and st["self_fallback_all_total"] == 0
    steps = 74 * scene.substeps
    if motion:
        assert st["self_responses_total"] < steps / 4, (st["self_responses_total"], steps)
    v = scene.state.v.numpy()
    assert np.abs(v).max() < 0.1, np.abs(v).max()
    assert scene.state.positions()[:, 1].max() < 0.1  # folded


def test_line_search_energies_in_one_pass_equal_each_configuration_alone():
    """Implicit Euler's line search evaluates the contact term (obstacle and self-contact
    records: `ContactCoupling.energy_line`, gaps affine along the line) and quadratic bending
    (`energy_configs`) at ``x`` and its four candidates in one launch each; each slot must
    equal that configuration's energy evaluated alone (fails with ``gd`` off by 0.1 % or the
    friction term left out: checked)."""
    import warp as wp

    from warp_cloth.solvers import implicit as imp

    scene = fold(solver="implicit", res=8, frames=1, size=0.6, angle=150.0)
    solver, m = scene.solver, scene.model
    st = m.state()
    dt = 1.0 / 120.0
    for _ in range(50):  # until the layers touch: self-contacts in the solve
        solver.step(st, dt)
    c = solver._coupling
    assert int(c.self_record.count.numpy()[0]) > 0 and int(c.record.count.numpy()[0]) > 0
    rng = np.random.default_rng(3)
    solver.dx.assign(rng.normal(scale=2e-3, size=(m.num_vertices, 3)).astype(np.float32))
    steps = wp.vec4(*imp.LS_STEPS)
    solver._ls_energies(st.x, steps)
    fused = solver._ls_energy.numpy()[:len(imp.LS_STEPS) + 1].copy()
    configs = [st.x] + [solver._ls_try[j] for j in range(len(imp.LS_STEPS))]
    alone = []
    for j, xc in enumerate(configs):  # the contact term and the bending term, one at a time
        e64 = wp.zeros(1, dtype=wp.float64)
        c.energy(xc, e64, solver._dt, 0)
        e32 = wp.zeros(1, dtype=float)
        for t in solver.implicit_terms:
            t.energy(xc, e32)
        alone.append(float(e64.numpy()[0]) + float(e32.numpy()[0]))
    # the rest of F (inertia, springs, gravity) is evaluated the same way in both
    solver.implicit_terms, terms = [], solver.implicit_terms
    coupling, solver._coupling = solver._coupling, None
    try:
        solver._ls_energies(st.x, steps)
        rest = solver._ls_energy.numpy()[:len(imp.LS_STEPS) + 1].copy()
    finally:
        solver.implicit_terms, solver._coupling = terms, coupling
    contact_and_bending = fused - rest
    assert len(set(np.round(alone, 12))) == len(alone)  # the candidates differ
    # the difference of two sums that hold the whole F: float rounding of F's own size (the
    # bending term is float32), far below the 0.1 % a wrong gap derivative makes
    floor = 1e-7 * np.abs(fused).max()
    assert np.allclose(contact_and_bending, alone, rtol=1e-6, atol=floor), (fused, rest, alone)


def _crumpled(res=7, seed=11, spread=0.05):
    """A ``res`` x ``res`` sheet (1 m) crumpled by random offsets: many non-adjacent pairs
    within a few thicknesses of each other."""
    from warp_cloth.mesh import TriMesh
    from warp_cloth.model import ClothModel

    rng = np.random.default_rng(seed)
    m = sheet_model(res=res).mesh
    x = m.vertices + rng.normal(0, spread, m.vertices.shape)
    return ClothModel(TriMesh(x, m.triangles), device="cpu"), rng


def _pair_distances(mesh, x):
    """Every non-adjacent vertex-triangle and edge-edge pair of ``mesh`` at ``x``: (the four
    vertices of each pair, its distance), from the geometry module's float64 functions."""
    import warp as wp

    from warp_cloth.collision import geometry

    @wp.kernel
    def dist_kernel(p: wp.array2d(dtype=wp.vec3d), ee: wp.array(dtype=int),
                    out: wp.array(dtype=wp.float64)):
        i = wp.tid()
        if ee[i] == 0:
            out[i] = geometry.vt_distance(p[i, 0], p[i, 1], p[i, 2], p[i, 3])
        else:
            out[i] = geometry.ee_distance(p[i, 0], p[i, 1], p[i, 2], p[i, 3])

    tris, edges = mesh.triangles, mesh.edges
    quads = [(v, *t) for v in range(len(x)) for t in tris if v not in t]
    nvt = len(quads)
    quads += [(*e, *f) for i, e in enumerate(edges) for f in edges[i + 1:]
              if not set(e) & set(f)]
    quads = np.array(quads)
    p = wp.array(np.asarray(x, np.float64)[quads], dtype=wp.vec3d, device="cpu")
    kind = wp.array((np.arange(len(quads)) >= nvt).astype(np.int32), dtype=int, device="cpu")
    out = wp.zeros(len(quads), dtype=wp.float64, device="cpu")
    wp.launch(dist_kernel, len(quads), [p, kind, out], device="cpu")
    return quads, out.numpy()


def test_span_allowance_is_the_least_half_clearance_of_each_vertex_pairs():
    """`SelfCollision.clear`: each vertex's allowance is exactly min(cap, min over the non-
    adjacent pairs it belongs to of (d - 1.01 h_p) / 2), brute force over every pair of a
    crumpled sheet (so moving each vertex at most its allowance keeps every such pair h_p
    apart); the cap covers the pairs farther than the clearance. ``h_p`` is the pair's
    thickness, ``h min(1, d_rest / (2 h))`` (`rest_scale`): this sheet's rest shape is the
    crumpled one, so ``d_rest = d``."""
    import warp as wp

    from warp_cloth.collision.self_collision import SelfCollision

    model, _ = _crumpled()
    h = 0.04
    sc = SelfCollision(model, h)
    sc.plan(10, 0.25)
    x = model.mesh.vertices
    sc.clear(wp.array(x, dtype=wp.vec3, device="cpu"))
    allow = sc._allow.numpy()
    quads, d = _pair_distances(model.mesh, x)
    hp = h * np.minimum(1.0, 0.5 * d / h)
    expect = np.full(len(x), sc.reach_max)
    np.minimum.at(expect, quads.ravel(), np.repeat(0.5 * (d - 1.01 * hp), 4))
    assert (d < sc.clearance).sum() > 50 and (d < 2 * h).sum() > 10  # near pairs, some scaled
    assert (expect < sc.reach_max).sum() > 10
    np.testing.assert_allclose(allow, expect, rtol=0, atol=2e-7)


def test_span_detection_of_the_active_part_finds_every_contact():
    """In a span's response only the vertices past their allowance query the broad phase
    (`active_kernel`); the pairs of a still vertex with a moving triangle and of a still lower
    edge with a moving higher one are taken from the moving side. Two sheets 10 cm apart, one
    triangle of the upper sheet (higher indices) pushed down through the lower: exactly the
    contacts of a full detection, among them such pairs."""
    import warp as wp

    from warp_cloth.collision.self_collision import SelfCollision

    model = _two_sheets(0.1)
    h = 0.02
    sc = SelfCollision(model, h)
    sc.plan(10, 0.25)
    x0 = model.mesh.vertices
    a0 = wp.array(x0, dtype=wp.vec3, device="cpu")
    sc.clear(a0)
    assert np.allclose(sc._allow.numpy(), sc.reach_max)  # 3 cm: clear of each other
    n = len(x0) // 2
    tri = model.mesh.triangles[len(model.mesh.triangles) // 2 + 20]
    x1 = x0.copy()
    x1[tri, 1] -= 0.11  # 1 cm below the lower sheet
    x1[tri] += [0.013, 0.0, 0.021]  # off the lower sheet's vertices and edges
    a1 = wp.array(x1, dtype=wp.vec3, device="cpu")

    def entries(in_span):
        sc._in_span = in_span
        sc.record.count.zero_()
        sc.detect(a0, a1, h, sc.record)
        sc._in_span = False
        k = int(sc.record.count.numpy()[0])
        return {(int(kd), *map(int, v)) for kd, v in
                zip(sc.record.kind.numpy()[:k], sc.record.vertex.numpy()[:k])}

    full, part = entries(False), entries(True)
    active = sc._active.numpy()
    assert sorted(np.flatnonzero(active)) == sorted(tri)
    assert any(e[0] == 1 and e[1] < n for e in full)  # a still vertex, the moving triangle
    assert any(e[0] == 2 and max(e[1:3]) < n for e in full)  # a still lower edge
    assert part == full
    for f, expect in ((0.9, []), (1.1, [3])):  # active: past the allowance, not before
        x1 = x0.copy()
        x1[3, 0] += f * sc.reach_max
        sc._in_span = True
        sc.detect(a0, wp.array(x1, dtype=wp.vec3, device="cpu"), h, sc.record)
        sc._in_span = False
        assert list(np.flatnonzero(sc._active.numpy())) == expect


def test_span_response_records_near_pairs_and_hold_keeps_them_apart():
    """A span's response also records the pairs within twice the reach beyond the thickness
    (5 + 2 x 1.25 mm), without moving them; `hold` then projects them every step of the next
    span: an upper sheet 6 mm above a lower one, pushed down 0.4 mm a step, stops at the
    thickness (within 3 %) instead of sinking into it until the next response."""
    model, stage, solver, calls = _span_stage(layers=0.006)
    sc = stage.self_collision
    h = sc.thickness
    dt = 0.25 * solver.stable_dt(model)
    state = model.state()
    x0 = state.x.numpy().copy()
    stage.plan(8)
    for _ in range(8):
        solver.step(state, dt)
    assert calls == [8] and int(sc.record.count.numpy()[0]) > 50
    np.testing.assert_array_equal(state.x.numpy(), x0)  # recorded, not moved
    n = model.num_vertices // 2
    v = np.zeros((2 * n, 3))
    v[n:, 1] = -4e-4 / dt
    state.v.assign(v)
    calls.clear()
    gaps = []
    for _ in range(8):
        solver.step(state, dt)
        x = state.x.numpy()
        gaps.append(float((x[n:, 1] - x[:n, 1]).min()))
    assert min(gaps) > 0.95 * h, gaps  # one Jacobi projection a step: 0.974 h


def test_hold_keeps_the_rounds_contacts_after_a_fall_back():
    """A span's response whose rounds end short runs the fall-back, whose detections (at 5 %
    of the thickness) find nothing where the rounds left the layers at about the thickness;
    `hold` must still project the rounds' contacts through the next span. An upper sheet
    pushed down 0.4 mm every step, one round a response: one projection a step keeps it
    within 15 % of the thickness (4.43 mm at least) through two more spans. With the
    fall-back's empty record the spans after it let it sink to 3.56 mm (three sheets stacked
    on a sphere under explicit Euler then gained 0.046 J in ten frames: every response pushed
    the sunk layers back out against their springs)."""
    model, stage, solver, calls = _span_stage(layers=0.006)
    sc = stage.self_collision
    sc.rounds = 1
    fell = []
    fallback = sc._fallback
    sc._fallback = lambda *a, **k: (fell.append(1), fallback(*a, **k))
    h = sc.thickness
    dt = 0.25 * solver.stable_dt(model)
    state = model.state()
    stage.plan(8)
    for _ in range(8):
        solver.step(state, dt)
    n = model.num_vertices // 2
    v = np.zeros((2 * n, 3))
    v[n:, 1] = -4e-4 / dt
    gaps, held = [], []
    for _ in range(16):
        state.v.assign(v)
        solver.step(state, dt)
        x = state.x.numpy()
        gaps.append(float((x[n:, 1] - x[:n, 1]).min()))
        held.append(int(sc.record.count.numpy()[0]))
    assert len(fell) >= 2  # the responses of this span and the next ran the fall-back
    assert min(held) > 50, held
    assert min(gaps) > 0.85 * h, gaps  # 0.887 h; with the fall-back's record 0.71 h


def test_explicit_stack_of_three_sheets_gains_no_energy():
    """The `stack` scene (three 16 x 16 sheets on a sphere) under explicit Euler, 90 frames:
    no frame's energy above the one before's by more than 1e-4 J. Its responses end short
    (four rounds cannot settle a sheet pressed between two) from frame ~75 on; with `hold`
    projecting nothing after the fall-back, every response pushed the middle sheet's sunk
    vertices 1.1-1.3 mm back out against their springs: 1.6e-2 J in one frame, 0.060 J over
    frames 30-90 (now none)."""
    from warp_cloth.contact_scenes import stack
    from warp_cloth.diagnostics import Meter

    scene = stack(solver="explicit", frames=90)
    meter = Meter(scene.model)
    energies = []
    scene.run(quiet=True, on_frame=lambda f, st: energies.append(meter(st).energy))
    rises = np.diff(energies)
    assert len(rises) == 89 and rises.max() < 1e-4, (rises.max(), int(rises.argmax()) + 1)


def test_explicit_drape_self_collision_response_adds_no_energy():
    """Explicit Euler's drape (16x16, self-collision on, spans with allowances), 120 frames run
    step by step: no response of a span raises the energy by more than 3e-4 J, and no frame
    crosses itself. With the thickness as the span's detection gap (no near pairs held), the
    responses push layers that sank during the span back out at once, stretching springs and
    bending. Measured with the scenes' bending (`SCENE_BENDING`), largest response rise: 1.2e-4
    J (the landing, frames 19-20; the run's ~800 responses take 3.6e-3 J out in all), 6.8e-4 J
    with that gap. (Without bending: 1.7e-5 J, and 8.2e-5 J with that gap, which the old bound
    of 1e-4 J no longer told apart.)"""
    from warp_cloth.diagnostics import Meter
    from warp_cloth.scenes import build_scene

    scene = build_scene("drape", res=16, frames=120, self_collision=True)
    scene.capture = False
    sc = scene.collision.self_collision
    assert sc.allowances
    meter = Meter(scene.model)
    gains = []
    resolve = sc._span_resolve

    def measured(state, dt):
        e0 = meter(state).energy
        resolve(state, dt)
        gains.append(meter(state).energy - e0)

    sc._span_resolve = measured
    stats = scene.run(quiet=True, check_intersections=True)
    assert stats.crossing_frames == 0
    assert len(gains) > 120 and max(gains) < 3e-4, max(gains)


def test_span_allowance_after_a_partial_pass_is_a_lower_bound():
    """`SelfCollision.clear` after a full pass: with few vertices moved past the reach it looks
    again only at the pairs of those, and every other vertex keeps the full pass's allowance
    less the farthest a still vertex went. The result is never above the exact allowance at the
    new positions (brute force), and never below the least of that and the old one less that
    motion (equal to it at the moved vertices); with most vertices moved it is a full pass
    again (exact)."""
    import warp as wp

    from warp_cloth.collision.self_collision import SelfCollision

    model, rng = _crumpled(seed=3)
    h = 0.04
    sc = SelfCollision(model, h)
    sc.plan(10, 0.25)
    x0 = model.mesh.vertices
    _, d_rest = _pair_distances(model.mesh, x0)  # the rest shape is the crumpled one
    hp = h * np.minimum(1.0, 0.5 * d_rest / h)  # each pair's thickness (`rest_scale`)

    def exact(x):
        quads, d = _pair_distances(model.mesh, x)
        out = np.full(len(x), sc.reach_max)
        np.minimum.at(out, quads.ravel(), np.repeat(0.5 * (d - 1.01 * hp), 4))
        return out

    sc.clear(wp.array(x0, dtype=wp.vec3, device="cpu"))  # the first pass is a full one
    a0 = exact(x0)
    np.testing.assert_allclose(sc._allow.numpy(), a0, atol=2e-7)
    moved = rng.random(len(x0)) < 0.15
    u = rng.normal(size=x0.shape)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = np.where(moved, rng.uniform(0.02, 0.06, len(x0)), rng.uniform(0, 0.009, len(x0)))
    x1 = x0 + u * r[:, None]
    sc.clear(wp.array(x1, dtype=wp.vec3, device="cpu"))
    assert int(sc._full.numpy()[0]) == 0  # partial: 15 % moved
    assert list(np.flatnonzero(sc._moved.numpy())) == list(np.flatnonzero(moved))
    allow, a1 = sc._allow.numpy(), exact(x1)
    still = r[~moved].max()
    assert (allow <= a1 + 2e-7).all(), (allow - a1).max()
    assert (allow >= np.minimum(a1, a0 - still) - 2e-7).all()
    # a moved vertex's pairs are all looked at again: exactly the least of the two
    np.testing.assert_allclose(allow[moved], np.minimum(a1, a0 - still)[moved], atol=2e-7)
    x2 = x0 + u * rng.uniform(0.02, 0.06, len(x0))[:, None]  # everything moved: full again
    sc.clear(wp.array(x2, dtype=wp.vec3, device="cpu"))
    np.testing.assert_allclose(sc._allow.numpy(), exact(x2), atol=2e-7)
    # two sheets 10 cm apart, one lower vertex raised 2 cm; a triangle of the upper sheet
    # (higher indices) moved down to 3 cm, its centre over that vertex: the still vertex
    # nearest its face is found from the moved side, exact as nothing else moved
    model = _two_sheets(0.1)
    sc = SelfCollision(model, 0.005)
    sc.plan(10, 0.25)
    x0 = model.mesh.vertices.copy()
    n = len(x0) // 2
    tri = model.mesh.triangles[len(model.mesh.triangles) // 2 + 20]
    c = x0[tri].mean(axis=0)
    v = int(np.argmin(np.linalg.norm(x0[:n] - c, axis=1)))
    x0[v, 1] += 0.02
    sc.clear(wp.array(x0, dtype=wp.vec3, device="cpu"))
    x1 = x0.copy()
    x1[tri] += [x0[v, 0] - c[0], -0.07, x0[v, 2] - c[2]]
    sc.clear(wp.array(x1, dtype=wp.vec3, device="cpu"))
    assert int(sc._full.numpy()[0]) == 0
    quads, d = _pair_distances(model.mesh, x1)
    a1 = np.full(len(x1), sc.reach_max)
    np.minimum.at(a1, quads.ravel(), np.repeat(0.5 * (d - 1.01 * 0.005), 4))
    assert a1[v] < 0.003  # the face 1 cm above it
    np.testing.assert_allclose(sc._allow.numpy(), a1, atol=2e-7)


def test_a_self_contact_at_a_pinned_vertex_is_reported_not_forced():
    """Two triangles, one free corner between them: a pinned edge 2 mm above a cloth edge, 0.5 mm
    from that edge's pinned end (weight 0.0125 on its free end). Moving the free vertex cannot
    clear it: the projection's share would throw it by the violation over its weight (about
    24 cm). The entry is left alone; the step is counted (``self_pinned``) and reported."""
    import warp as wp

    from warp_cloth import ClothModel, TriMesh
    from warp_cloth.collision.self_collision import SelfCollision

    v = np.array([[0.0, 0.0, 0.0], [0.04, 0.0, 0.0], [0.0, 0.0, 0.04],
                  [0.0005, 0.002, -0.02], [0.0005, 0.002, 0.02], [0.0005, 0.03, 0.0]])
    mesh = TriMesh(v, np.array([[0, 1, 2], [3, 4, 5]]))
    model = ClothModel(mesh, pins=[0, 2, 3, 4, 5], device="cpu")
    sc = SelfCollision(model, 0.005)
    st = model.state()
    x0 = st.positions()
    sc.resolve(st, wp.array(x0, dtype=wp.vec3, device="cpu"), 1.0 / 600.0)
    assert np.linalg.norm(st.positions() - x0, axis=1).max() < 1e-3
    assert sc.stats["self_pinned"] == 1 and sc.stats["self_fallback_all"] == 0
    assert any("pinned vertex" in m for m, _ in sc.frame_end())


def _thin_column_sheet(height=0.0):
    """A 0.3 m sheet whose cells are 5 cm wide but for one column 1 mm wide: non-adjacent
    vertex-triangle and edge-edge pairs across that column lie 1 mm apart at rest."""
    from warp_cloth import TriMesh

    xs = np.array([0.0, 0.05, 0.1, 0.15, 0.151, 0.2, 0.25, 0.3])
    zs = np.linspace(0.0, 0.3, 7)
    X, Z = np.meshgrid(xs, zs, indexing="ij")
    v = np.stack([X.ravel(), np.full(X.size, height), Z.ravel()], axis=1)
    idx = np.arange(X.size).reshape(X.shape)
    tris = []
    for i in range(len(xs) - 1):
        for j in range(len(zs) - 1):
            a, b, c, d = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
            tris += [(a, b, c), (a, c, d)]
    return TriMesh(v, np.array(tris))


def test_pairs_close_in_the_rest_shape_keep_half_their_rest_distance():
    """A sheet with a 1 mm column under a 5 mm thickness: its pairs across the column are 1 mm
    apart at rest. They keep half that (`rest_scale`), so the sheet at rest is left as it is;
    held to the full thickness, the response pushed them 5 mm apart (the 1 mm edges stretched
    by hundreds of percent). Two separate pieces as close keep the full thickness (the
    pinned-vertex test above: its triangles are 2 mm apart)."""
    import warp as wp

    from warp_cloth import ClothModel, diagnostics
    from warp_cloth.collision.self_collision import SelfCollision, rest_and_pieces

    mesh = _thin_column_sheet()
    model = ClothModel(mesh, device="cpu")
    sc = SelfCollision(model, 0.005)
    st = model.state()
    x0 = st.positions()
    sc.resolve(st, wp.array(x0, dtype=wp.vec3, device="cpu"), 1.0 / 600.0)
    assert diagnostics.edge_strains(model, st.positions()).max() < 1e-6
    assert sc.stats["self_fallback_all"] == 0 and sc.stats["self_zones"] == 0
    pieces = rest_and_pieces(mesh)[0][:, 3]
    assert set(pieces) == {0.0}
    two, _ = rest_and_pieces(type(mesh)(np.concatenate([mesh.vertices, mesh.vertices + 0.002]),
                                        np.concatenate([mesh.triangles,
                                                        mesh.triangles + len(mesh.vertices)])))
    assert (two[:len(mesh.vertices), 3] == 0).all() and (two[len(mesh.vertices):, 3] == 1).all()
    # with the thickness: only the vertices of pairs closer than 2 h at rest keep their piece
    # (the others skip the rest distance): here the columns at x = 0.15 and 0.151 and their
    # neighbours' triangles' corners; none on the built-in grids
    rest, share = rest_and_pieces(mesh, 0.005)
    flagged = rest[:, 3] >= 0
    xs = np.round(mesh.vertices[flagged, 0], 4)
    assert set(xs) <= {0.1, 0.15, 0.151, 0.2} and {0.15, 0.151} <= set(xs)
    assert (sc.rest.numpy()[:, 3] >= 0).sum() == flagged.sum()
    # each vertex's least share (the spans' reach scales with it): 0.5 * 1 mm / 5 mm on the
    # column's edges, 1 where no pair is close
    on_column = np.isin(np.round(mesh.vertices[:, 0], 4), [0.15, 0.151])
    np.testing.assert_allclose(share[on_column], 0.1, rtol=1e-3)
    assert (share[~flagged] == 1.0).all()
    grid_rest, grid_share = rest_and_pieces(sheet_model(res=16).mesh, 0.005)
    assert (grid_rest[:, 3] == -1).all() and (grid_share == 1.0).all()


@pytest.mark.parametrize("solver_name", ["explicit", "implicit"])
def test_sheet_with_short_edges_falls_without_stretching(solver_name):
    """The same sheet dropped 2 cm onto the floor with self-collision on: the short edges keep
    their length (without `rest_scale`: several hundred percent of strain) and nothing crosses."""
    from warp_cloth import ClothModel
    from warp_cloth.collision import Plane
    from warp_cloth.scenes import _finish

    model = ClothModel(_thin_column_sheet(0.02), density=0.15, stretch_stiffness=1000.0,
                       damping=0.1, device="cpu")
    stage = CollisionStage(model, [Plane()], thickness=0.005, self_collision=True)
    scene = _finish(model, solver_name, None, (), 60.0, 20, None, (), 10.0, "thin-column",
                    collision=stage)
    stats = scene.run(None, quiet=True, energy=False, check_intersections=True)
    assert stats.max_strain < 0.05, stats.max_strain
    assert stats.crossing_frames == 0


class _PushThrough:
    """A limit-like correction whose pass after contact moves one vertex 6 mm straight down
    (through the layer below) and says it moved something: what a strain limit's sweeps can do,
    since they see obstacles but not the cloth's other layers."""

    capturable = True

    def __init__(self, vertex, device="cpu"):
        self.vertex = vertex

    def apply(self, state, x_start, dt):
        pass

    def after_contact(self, state, x_start, dt, stage):
        x = state.x.numpy()
        x[self.vertex, 1] -= 0.006
        state.x.assign(x)
        return True

    def moved_into(self, flag):
        flag.fill_(1)


@pytest.mark.parametrize("solver_name", ["explicit", "pbd"])
def test_a_limit_pass_after_contact_cannot_push_the_cloth_through_itself(solver_name):
    """Two triangles of separate pieces, a free corner of the upper one 3 mm above the lower
    one: a correction's pass after contact drops it 6 mm, through the lower triangle. The step
    then runs the self-collision response again on that pass's path (`Solver._self_again`), so
    the step ends with no crossing and the corner above the lower triangle (without it
    crossing pairs, the corner 3 mm below)."""
    from warp_cloth import ClothModel, TriMesh
    from warp_cloth.collision.check import self_crossings
    from warp_cloth.solvers import make_solver

    v = np.array([[-0.1, 0.0, -0.1], [0.1, 0.0, -0.1], [0.0, 0.0, 0.1],
                  [0.0, 0.003, 0.0], [0.3, 0.003, 0.05], [0.3, 0.003, -0.05]])
    mesh = TriMesh(v, np.array([[0, 1, 2], [3, 4, 5]]))
    model = ClothModel(mesh, pins=[0, 1, 2, 4, 5], gravity=(0.0, 0.0, 0.0), device="cpu")
    stage = CollisionStage(model, [], thickness=0.001, self_collision=True)
    solver = make_solver(solver_name, model, collision=stage, corrections=[_PushThrough(3)])
    st = model.state()
    solver.step(st, 1.0 / 600.0)
    x = st.positions()
    assert self_crossings(x, mesh.triangles, mesh.edges) == 0
    assert x[3, 1] > 0.0


def test_span_reach_scales_with_the_pairs_share_of_the_thickness():
    """The spans' reach is a fraction of the thickness (``self_motion``); for a vertex whose
    pairs keep only a share of it (`rest_scale`: 0.1 across the thin column) the reach is that
    share of it, 0.125 mm instead of 1.25 mm: a column moving 0.2 mm a step needs a response
    every step (with the plain reach, only at the frame's end), since its pairs' gap is that
    share."""
    from warp_cloth import ClothModel, make_solver

    model = ClothModel(_thin_column_sheet(), gravity=(0.0, 0.0, 0.0), device="cpu")
    stage = CollisionStage(model, self_collision=True, self_motion=0.25)
    solver = make_solver("explicit", model, collision=stage)
    calls = _count_responses(stage)
    dt = 0.25 * solver.stable_dt(model)
    state = model.state()
    column = np.isin(np.round(model.mesh.vertices[:, 0], 4), [0.15, 0.151])
    v = np.zeros((model.num_vertices, 3))
    v[column, 1] = 2e-4 / dt
    state.v.assign(v)
    stage.plan(5)
    for _ in range(5):
        solver.step(state, dt)
    assert calls == [1, 1, 1, 1, 1], calls


def test_a_rest_close_pair_is_recorded_where_it_comes_within_its_own_thickness():
    """A vertex beside the 1 mm column (its pairs across it keep 0.5 mm) sliding 2 cm along it
    while closing 0.8 mm: detected with the spans' margin it is within the gap from the start,
    but the entry's closest point is taken where it comes within its own 0.5 mm (z about
    0.1625), not at the start (z = 0.15), where the pair does not meet."""
    import warp as wp

    from warp_cloth import ClothModel
    from warp_cloth.collision.self_collision import SelfCollision

    mesh = _thin_column_sheet()
    model = ClothModel(mesh, gravity=(0.0, 0.0, 0.0), device="cpu")
    sc = SelfCollision(model, 0.005)
    x0 = mesh.vertices.astype(np.float64)
    v = int(np.flatnonzero(np.isclose(x0[:, 0], 0.15) & np.isclose(x0[:, 2], 0.15))[0])
    x1 = x0.copy()
    x1[v] += [0.0008, 0.0, 0.02]
    sc.record.count.zero_()
    sc.detect(wp.array(x0, dtype=wp.vec3, device="cpu"), wp.array(x1, dtype=wp.vec3, device="cpu"),
              0.005 + 2 * 0.00125, sc.record)
    n = int(sc.record.count.numpy()[0])
    from warp_cloth.collision.self_collision import KIND_VERTEX_TRIANGLE

    ids, w = sc.record.vertex.numpy()[:n], sc.record.weight.numpy()[:n]
    kind = sc.record.kind.numpy()[:n]
    # the vertex against the triangle of the next cell whose edge it slides along (two corners
    # on x = 0.151, z from 0.15 to 0.2)
    mine = [k for k in range(n) if kind[k] == KIND_VERTEX_TRIANGLE and ids[k][0] == v
            and np.isclose(x0[ids[k][1:], 0], 0.151).sum() == 2
            and x0[ids[k][1:], 2].min() > 0.149]
    assert mine
    for k in mine:  # the triangle's point of the entry, at rest
        z = -(w[k][1:] @ x0[ids[k][1:], 2])
        assert abs(z - 0.1625) < 2e-3, z


def test_a_seam_written_twice_is_refused_and_welded_falls():
    """A sheet of two patches whose shared border is written twice: the coincident vertices
    are separate parts of the cloth that start at one point, inside every gap, and every step
    ended in the whole-cloth return (the sheet hung frozen at its start, every solver). Refused,
    naming the vertices; welded, the sheet falls as one."""
    from warp_cloth import ClothModel, Scene, TriMesh, make_solver

    a = TriMesh.grid(4, 8, size=(0.5, 1.0), plane="xz", origin=(-0.5, 0.9, -0.5))
    b = TriMesh.grid(4, 8, size=(0.5, 1.0), plane="xz", origin=(0.0, 0.9, -0.5))
    seam = TriMesh(np.vstack([a.vertices, b.vertices]),
                   np.vstack([a.triangles, b.triangles + len(a.vertices)]))
    with pytest.raises(ValueError, match=r"vertices 4 and 45 are 0 m apart .* weld"):
        CollisionStage(ClothModel(seam), [], thickness=0.005, self_collision=True)
    from warp_cloth.collision import Plane

    CollisionStage(ClothModel(seam), [Plane()], thickness=0.005)  # no self-collision: 2 pieces
    model = ClothModel(seam.weld()[0], density=0.15)
    stage = CollisionStage(model, [], thickness=0.005, self_collision=True)
    scene = Scene(model, make_solver("explicit", model, collision=stage), fps=60, frames=20)
    stats = scene.run(None, quiet=True, energy=False)
    assert stats.min_height < 0.45  # free fall over 19 frames: 0.9 - 0.49 m
    assert stage.self_collision.stats["self_fallback_all_total"] == 0


def test_a_start_that_passes_through_itself_is_refused_before_writing(tmp_path):
    """Two sheets crossing at the start: self-collision keeps a cloth free of itself, it cannot
    make one (each step returned the cloth to its start: frozen, crossed, in every frame).
    `Scene.run` refuses it, naming a crossing edge, before the output exists."""
    from warp_cloth import ClothModel, Scene, TriMesh, make_solver

    a = TriMesh.grid(4, 4, size=0.4, plane="xz", origin=(-0.2, 0.5, -0.2))
    b = TriMesh.grid(4, 4, size=0.4, plane="xy", origin=(-0.2, 0.3, 0.02))
    mesh = TriMesh(np.vstack([a.vertices, b.vertices]),
                   np.vstack([a.triangles, b.triangles + len(a.vertices)]))
    model = ClothModel(mesh, density=0.15)
    assert self_crossings(mesh.vertices, mesh.triangles, mesh.edges) > 0
    stage = CollisionStage(model, [], thickness=0.005, self_collision=True)
    scene = Scene(model, make_solver("explicit", model, collision=stage), fps=60, frames=3)
    out = tmp_path / "crossed.usd"
    with pytest.raises(ValueError, match=r"passes through itself at the start .* vertices \d+-\d+"):
        scene.run(out, quiet=True)
    assert not out.exists()
    plain = Scene(model, make_solver("explicit", model), fps=60, frames=3)  # no self-collision
    assert plain.run(None, quiet=True, energy=False).frames == 3


def test_a_start_folded_flat_onto_itself_is_refused_before_writing(tmp_path):
    """A flat sheet with an inverted triangle (a vertex moved past its neighbours) overlaps
    itself in one plane, which no edge-triangle crossing test sees (an edge in a triangle's
    plane does not cross it); a jittered sheet with one such triangle froze in every response
    and ended as diverged under every solver. `Scene.run` refuses it, naming the triangles and
    their edge, before the output exists. A sheet in a tilted plane far from the origin, in
    float32, is not folded anywhere (no false alarm from rounding)."""
    from warp_cloth import ClothModel, Scene, TriMesh, make_solver
    from warp_cloth.collision.check import folded_flat_edges

    grid = TriMesh.grid(4, 4, size=0.4, plane="xz", origin=(-0.2, 0.5, -0.2))
    x = grid.vertices.copy()
    x[6, 0] += 0.12  # the interior vertex (1, 1) past the column of vertices at x = 0
    flat = folded_flat_edges(x, grid.edges, grid.edge_tris, grid.triangles)
    assert len(flat) > 0
    model = ClothModel(grid, density=0.15)
    model.initial_positions = x
    stage = CollisionStage(model, [], thickness=0.005, self_collision=True)
    scene = Scene(model, make_solver("explicit", model, collision=stage), fps=60, frames=3)
    out = tmp_path / "folded.usd"
    with pytest.raises(ValueError, match=r"folded flat onto itself at the start .* triangles "
                                         r"\d+ and \d+ on edge \d+-\d+"):
        scene.run(out, quiet=True)
    assert not out.exists()
    plain = Scene(model, make_solver("explicit", model), fps=60, frames=3)  # no self-collision
    assert plain.run(None, quiet=True, energy=False).frames == 3

    rot = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))[0]
    tilted = (grid.vertices @ rot.T + 1000.0).astype(np.float32)
    assert len(folded_flat_edges(tilted, grid.edges, grid.edge_tris, grid.triangles)) == 0
    folded = grid.vertices.copy()  # a real fold of the sheet, 1 degree short of flat: not flat
    right = folded[:, 0] > 0.0
    a = np.radians(179.0)
    folded[right, 0] = folded[right, 0] * np.cos(a)
    folded[right, 1] = 0.5 + grid.vertices[right, 0] * np.sin(a)
    assert len(folded_flat_edges(folded, grid.edges, grid.edge_tris, grid.triangles)) == 0


def test_an_inverted_sliver_in_a_tilted_float32_sheet_is_folded_flat():
    """An inverted triangle whose far vertex lies 1.7 mm past its edge, in a sheet turned out
    of every axis and stored in float32 (a fuzzed scene: it froze every response and diverged),
    is off flat by the rounding only (~2e-5 rad, past the angle tolerance alone): found."""
    from warp_cloth import TriMesh
    from warp_cloth.collision.check import folded_flat_edges

    grid = TriMesh.grid(4, 4, size=0.4, plane="xz", origin=(-0.2, 0.0, -0.2))
    x = grid.vertices.copy()
    x[6, 0] += 0.1017  # the interior vertex (1, 1) 1.7 mm past the column at x = 0
    assert len(folded_flat_edges(x, grid.edges, grid.edge_tris, grid.triangles)) > 0
    found = 0
    for seed in range(8):
        rot = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))[0]
        tilted = (x @ rot.T + 0.3).astype(np.float32)
        found += len(folded_flat_edges(tilted, grid.edges, grid.edge_tris, grid.triangles)) > 0
    assert found == 8


def _t_junction(lift=0.0):
    """A triangle over a pair of triangles whose shared vertex ``m`` lies on the big one's base
    edge (a T-junction; ``lift`` moves it off the edge, away from the big triangle)."""
    from warp_cloth import TriMesh

    v = np.array([[0.0, 1.0, 0.0], [0.2, 1.0, 0.0], [0.1, 1.0, 0.2], [0.1, 1.0, -lift],
                  [0.1, 1.0, -0.2]])
    return TriMesh(v, np.array([[0, 1, 2], [0, 3, 4], [3, 1, 4]]), name="tee")


@pytest.mark.parametrize("case", ["t-junction", "inverted"])
def test_a_rest_mesh_that_touches_itself_is_refused_naming_the_pair(case):
    """Two primitives of one piece sharing no vertex that touch in the rest shape (a vertex on
    another triangle's edge; an inverted triangle folded onto its neighbours) keep nothing of the
    thickness and every path through them meets the fail-safe: a fuzzed sheet with one inverted
    triangle had the whole cloth returned to its start, velocities zeroed, in 301 of its first
    302 steps and froze as diverged. Refused when self-collision is made, naming the pair; the
    same mesh with the vertex 0.2 thickness off the edge is accepted (it keeps half of that)."""
    from warp_cloth import ClothModel, TriMesh

    h = 0.005
    if case == "t-junction":
        mesh, ok = _t_junction(), _t_junction(lift=0.2 * h)
        name = r"vertex 3 lies 0 m from triangle 0 \(vertices 0, 1, 2\), which it is not a corner"
    else:
        grid = TriMesh.grid(4, 4, size=0.4, plane="xz", origin=(-0.2, 1.0, -0.2))
        x = grid.vertices.copy()
        x[6, 0] += 0.12
        mesh, ok = TriMesh(x, grid.triangles, name="tee"), grid
        name = r"(vertex \d+ lies|edges \d+-\d+ and \d+-\d+, which share no vertex, lie)"
    with pytest.raises(ValueError, match=rf"tee: {name}.* in the rest shape .*overlaps itself"):
        CollisionStage(ClothModel(mesh, density=0.15), [], thickness=h, self_collision=True)
    from warp_cloth import Plane, make_solver

    model = ClothModel(mesh, density=0.15)  # without self-collision: fine
    make_solver("explicit", model, collision=CollisionStage(model, [Plane()], thickness=h))
    CollisionStage(ClothModel(ok, density=0.15), [], thickness=h, self_collision=True)


def test_separate_pieces_starting_within_the_thickness_are_refused():
    """Separate pieces whose vertices start closer than the thickness (a seam written twice
    0.1 mm apart; sheets stacked 1 mm apart) were pushed to the thickness in the first step and
    thrown apart (the seam's halves at 0.23-0.49 m/s, +6e-2 J in a frame): refused, naming the
    closest pair, with the weld that joins a seam; the suggested weld does."""
    import re

    from warp_cloth import ClothModel, TriMesh

    a = TriMesh.grid(4, 4, size=0.5, plane="xz", origin=(-0.5, 0.5, -0.25))
    b = TriMesh.grid(4, 4, size=0.5, plane="xz", origin=(1e-4, 0.5, -0.25))
    seam = TriMesh(np.vstack([a.vertices, b.vertices]),
                   np.vstack([a.triangles, b.triangles + len(a.vertices)]))
    with pytest.raises(ValueError, match=r"separate pieces .* 0\.0001 m apart .* weld") as e:
        CollisionStage(ClothModel(seam), [], thickness=0.005, self_collision=True)
    tol = float(re.search(r"weld\(([0-9.e-]+)\)", str(e.value)).group(1))
    welded = seam.weld(tol)[0]
    assert welded.num_vertices == seam.num_vertices - 5
    CollisionStage(ClothModel(welded), [], thickness=0.005, self_collision=True)
    c = TriMesh.grid(4, 4, size=0.5, plane="xz", origin=(-0.25, 0.501, -0.25))
    stacked = TriMesh(np.vstack([a.vertices + [0.25, 0, 0], c.vertices]),
                      np.vstack([a.triangles, c.triangles + len(a.vertices)]))
    with pytest.raises(ValueError, match=r"separate pieces .* 0\.001 m apart"):
        CollisionStage(ClothModel(stacked), [], thickness=0.005, self_collision=True)
    CollisionStage(ClothModel(stacked), [], thickness=5e-4, self_collision=True)  # thinner: ok


@pytest.mark.parametrize("margin, entries", [(0.005, False), (None, True)])
def test_a_self_margin_of_the_thickness_takes_no_in_plane_neighbours(margin, entries):
    """A flat sheet of 2 cm cells, 5 mm thickness: a vertex and the triangle across its cell's
    diagonal lie 1.4 cm apart. With the solve's self margin at the thickness (the twist scene's)
    they are no entries of the solve; with the default (the obstacles' 1 cm `solve_margin`)
    every step carries them through every iteration."""
    from warp_cloth.solvers.projective import ProjectiveDynamics

    model = sheet_model(res=10, size=0.2, height=0.5)
    stage = CollisionStage(model, [], self_collision=True, self_solve_margin=margin)
    assert stage.self_solve_margin == pytest.approx(stage.solve_margin if margin is None
                                                    else margin)
    solver = ProjectiveDynamics(model, collision=stage)
    state = model.state()
    solver.step(state, 1 / 180)
    n = solver.stats["self_solve_contacts"]
    assert (n > 100) if entries else (n == 0), n


@pytest.mark.parametrize("bad", [-1.0, float("nan"), "wide"])
def test_a_bad_self_solve_margin_is_refused(bad):
    model = sheet_model(res=4)
    with pytest.raises(ValueError, match="self_solve_margin"):
        CollisionStage(model, [], self_collision=True, self_solve_margin=bad)


def test_the_twist_takes_the_thickness_as_its_solve_self_margin():
    """The twist's 2 cm cells put in-plane pairs within the default margin (above)."""
    from warp_cloth.contact_scenes import twist

    scene = twist(res=6, frames=2, thickness=0.004)
    assert scene.collision.self_solve_margin == pytest.approx(0.004)


def _loaded_layer(g, res=4, h=0.005):
    """A ``res`` x ``res`` sheet (1 m) with every vertex pinned, and above it, 1.2 ``h`` up, a
    free sheet of half its size shifted off its grid (a separate piece), under gravity ``g``
    m/s^2: the free sheet comes to rest on the pinned one, pressed on it by its weight."""
    from warp_cloth.mesh import TriMesh
    from warp_cloth.model import ClothModel

    m = sheet_model(res=res).mesh
    n, cell = len(m.vertices), 1.0 / res
    c = m.vertices.mean(axis=0)
    up = c + 0.5 * (m.vertices - c) + [0.3 * cell, 1.2 * h, 0.4 * cell]
    mesh = TriMesh(np.concatenate([m.vertices, up]), np.concatenate([m.triangles, m.triangles + n]))
    return ClothModel(mesh, device="cpu", gravity=(0.0, -g, 0.0), pins=list(range(n))), n


def test_a_loaded_self_contact_ends_its_solve_at_the_thickness():
    """A penalty gives under load: a self-contact pressed by a force ``f`` ends projective
    dynamics' solve ``f dt^2 / (kappa m)`` inside its target, and the response after the solve
    pushed it out against the load at every step (energy put in each step: the table's pile of
    folds gained up to 7e-4 J in a frame under PD, a stack of sheets 1.8e-3 J under implicit
    Euler). The next step's target is raised by the last step's sag (`ContactCoupling`'s
    ``self_sag``), so the solve ends at the thickness and the response has nothing left to do:
    a sheet resting on a pinned one under 400 m/s^2 (a 57 um sag at dt = 1/60 s) is moved by
    the response less than 5 um a step, against the full sag without the raise."""
    from warp_cloth import make_solver

    h, dt = 0.005, 1.0 / 60.0
    moved = {}
    for raised in (True, False):
        model, n = _loaded_layer(400.0, h=h)
        stage = CollisionStage(model, self_collision=True, thickness=h)
        solver = make_solver("pd", model, collision=stage)
        state = model.state()
        steps = []
        orig = stage.self_collision.step

        def measured(st, *args, **kwargs):
            x0 = st.x.numpy().copy()
            orig(st, *args, **kwargs)
            steps.append(float(np.abs(st.x.numpy() - x0).max()))

        stage.self_collision.step = measured
        for k in range(40):
            solver.step(state, dt)
            if k == 0 and not raised:
                solver._contact().self_sag_cap = 0.0
        x = state.x.numpy()
        assert x[n:, 1].min() - x[:n, 1].max() > h - 1e-6  # at rest on it, the thickness apart
        moved[raised] = max(steps[-10:])
    assert moved[True] < 5e-6, moved
    assert moved[False] > 3e-5, moved  # the same layer without the raise


def test_a_path_through_the_cloth_is_not_resolved_by_its_end_constraints():
    """A step of the 3-sheet stack at 5 fps (4 steps a frame; PD): the sheet's end positions
    ``x1`` keep every detected pair's constraint (normal and weights at the time of impact),
    yet two of its edges pass through triangles of the same sheet (it turned in the step). The
    response on ``x0 -> x1`` must not call that resolved: the pairs whose path comes within the
    fail-safe gap go to the impact zones, which end it clear of itself."""
    from pathlib import Path

    from warp_cloth.contact_scenes import stack

    data = np.load(Path(__file__).parent / "data" / "stack_deep_path_step.npz")
    scene = stack(solver="pd", res=8, fps=5, frames=2, substeps=1)
    m, sc = scene.model, scene.collision.self_collision
    tris, edges = m.mesh.triangles, m.mesh.edges
    assert self_crossings(data["x0"], tris, edges) == 0
    assert self_crossings(data["x1"], tris, edges) == 3
    state = m.state()
    state.x.assign(data["x1"])
    import warp as wp

    sc.resolve(state, wp.array(data["x0"], dtype=wp.vec3, device=m.device), float(data["dt"]))
    assert self_crossings(state.x.numpy(), tris, edges) == 0
    assert sc.stats["self_zones"] > 0 and sc.stats["self_fallback_all"] == 0


def _entries(sc):
    k = int(sc.record.count.numpy()[0])
    return sorted((int(kd), *map(int, v)) for kd, v in
                  zip(sc.record.kind.numpy()[:k], sc.record.vertex.numpy()[:k]))


@pytest.mark.parametrize("rounds", [6, 1])
def test_incremental_rounds_detect_what_full_rounds_detect(rounds):
    """After a step's first round only the pairs with a vertex the last projection moved are
    detected again and the other entries are kept (`SelfCollision._round_incremental`); the
    impact zones' first detection likewise, the kept entries tested again at the fail-safe gap
    (`_zone_detect_incremental`): every round's and every zone pass's entries are exactly
    those of a full detection, on a crumpled sheet whose random path needs several rounds (one
    round: the zones), and the response ends in the same positions."""
    import warp as wp

    from warp_cloth.collision.self_collision import SelfCollision

    model, rng = _crumpled(res=8, spread=0.04)
    h = 0.03
    x0 = model.mesh.vertices
    x1 = x0 + rng.normal(0, 0.03 if rounds > 1 else 0.08, x0.shape)
    runs = {}
    for incremental in (True, False):
        sc = SelfCollision(model, h, rounds=rounds, iterations=2, incremental=incremental)
        rounds_seen, zones_seen, moved = [], [], []
        project, zone_pass = sc._project, sc._zone_pass

        def spy(state, dt, sc=sc, project=project, seen=rounds_seen, moved=moved):
            seen.append(_entries(sc))
            if incremental:
                moved.append(int(sc._incremental.numpy()[0]) * int(sc._moved_round.numpy().sum()))
            project(state, dt)

        def zspy(*a, sc=sc, zone_pass=zone_pass, seen=zones_seen, **k):
            zone_pass(*a, **k)
            seen.append(_entries(sc))

        calls = []
        zinc_detect = sc._zone_detect_incremental

        def zinc_spy(*a, zinc_detect=zinc_detect, calls=calls, **k):
            calls.append(1)
            zinc_detect(*a, **k)

        sc._project, sc._zone_pass, sc._zone_detect_incremental = spy, zspy, zinc_spy
        state = model.state()
        state.x.assign(x1)
        sc.resolve(state, wp.array(x0, dtype=wp.vec3, device="cpu"), 1.0 / 60.0)
        runs[incremental] = (rounds_seen, zones_seen, state.x.numpy(), moved, sc.stats)
        # the zones' first detection alone is incremental
        assert len(calls) == (1 if incremental and zones_seen else 0)
    (inc, zinc, x_inc, moved, st_inc), (full, zfull, x_full, _, st_full) = runs[True], runs[False]
    assert len(inc) == len(full) and len(zinc) == len(zfull)
    if rounds > 1:
        assert len(inc) >= 4
        assert 0 < min(moved[1:]) and max(moved[1:]) < len(x0)  # partial re-detections ran
        assert min(len(r) for r in full) >= 3  # contacts left in every round
    else:
        assert len(zfull) >= 2 and len(zfull[0]) > 0 and st_full["self_zones"] > 0
    for a, b in zip(inc + zinc, full + zfull):
        assert a == b
    for key in ("self_contacts", "self_zones", "self_zone_vertices", "self_fallback_all"):
        assert st_inc[key] == st_full[key], key
    np.testing.assert_allclose(x_inc, x_full, atol=1e-6)


@pytest.mark.parametrize("marked", [0.0, 0.3])
def test_zone_detection_from_the_last_round_entries_equals_a_full_one(marked):
    """`_zone_detect_incremental`: the last round's entries whose vertices did not move, tested
    again at the fail-safe gap, plus the pairs of the marked vertices, are exactly a full
    detection at that gap on the same paths (kinds, vertices, normals, weights): a pair not
    among the entries was farther than the round's gap. With no vertex marked, only the
    retest; with 30 % marked, both halves."""
    import warp as wp

    from warp_cloth.collision.self_collision import FAILSAFE_GAP, SelfCollision

    model, rng = _crumpled(res=8, spread=0.04)
    h = 0.03
    x0 = model.mesh.vertices
    a0 = wp.array(x0, dtype=wp.vec3, device="cpu")
    a1 = wp.array(x0 + rng.normal(0, 0.03, x0.shape), dtype=wp.vec3, device="cpu")
    sc = SelfCollision(model, h)

    def entries():
        k = int(sc.record.count.numpy()[0])
        r = sc.record
        rows = sorted(zip(map(int, r.kind.numpy()[:k]), map(tuple, r.vertex.numpy()[:k].tolist()),
                          map(tuple, r.normal.numpy()[:k].tolist()),
                          map(tuple, r.weight.numpy()[:k].tolist()), r.offset.numpy()[:k]))
        return rows

    gap = FAILSAFE_GAP * h
    sc.record.count.zero_()
    sc.detect(a0, a1, h, sc.record)
    at_h = entries()
    sc._moved_round.assign((rng.random(len(x0)) < marked).astype(np.int32))
    sc._zone_detect_incremental(a0, a1, gap)
    inc = entries()
    sc.record.count.zero_()
    sc.detect(a0, a1, gap, sc.record)
    full = entries()
    assert 0 < len(full) < len(at_h)
    assert [(k, v) for k, v, *_ in inc] == [(k, v) for k, v, *_ in full]
    for a, b in zip(inc, full):
        np.testing.assert_allclose(np.r_[a[2], a[3], a[4]], np.r_[b[2], b[3], b[4]], atol=1e-6)


def test_impact_zones_grow_along_a_chain_before_the_cloth_returns_to_its_start():
    """Eight separate vertical plates (two triangles each) side by side along x, the gaps
    narrowing (6, 4.5, 3, 2.2, 1.8, 1.5, 1.3 mm; 1 mm thickness); the first plate moves 10 mm
    toward them in the step, through the second only. With one round of one projection the
    response goes to the impact zones: the first zone (plates 1-2) moves rigidly with their
    momentum, 5 mm, into plate 3; that zone moves 3.3 mm into plate 4, and so on: each pass
    grows the zone by one plate, seven passes in all. With the former 3 passes the whole cloth
    went back to its start (the twist's coarse sheets froze so: `ZONE_PASSES`); now every plate
    ends moved by the same distance, 1.34 mm (10 mm over eight plates is 1.25: the round's
    Jacobi projection, which averages each vertex's corrections, added 0.7 mm before the
    zones took the plates' momentum)."""
    import warp as wp

    import warp_cloth as wc
    from warp_cloth.collision.self_collision import ZONE_PASSES, SelfCollision

    gaps = np.cumsum([0.0, 0.006, 0.0045, 0.003, 0.0022, 0.0018, 0.0015, 0.0013])
    verts, tris = [], []
    for x in gaps:
        b = len(verts)
        verts += [[x, 0, 0], [x, 0.02, 0], [x, 0.02, 0.02], [x, 0, 0.02]]
        tris += [[b, b + 1, b + 2], [b, b + 2, b + 3]]
    model = wc.ClothModel(wc.TriMesh(np.array(verts, float), np.array(tris)), density=0.15,
                          stretch_stiffness=1000.0)
    x0 = model.mesh.vertices.copy()
    x1 = x0.copy()
    x1[:4, 0] += 0.01
    dt = 1.0 / 60.0

    def resolve(**kw):
        sc = SelfCollision(model, 0.001, rounds=1, iterations=1, **kw)
        state = model.state()
        state.x.assign(wp.array(x1, dtype=wp.vec3))
        state.v.assign(wp.array((x1 - x0) / dt, dtype=wp.vec3))
        sc.resolve(state, wp.array(x0, dtype=wp.vec3), dt)
        st = dict(sc.stats, passes=int(sc._zone_flags.numpy()[0]))
        return st, state.x.numpy()[::4, 0] - x0[::4, 0]

    assert ZONE_PASSES >= 7
    st, moved = resolve()
    # seven passes, each growing the zone by one plate; the step's zones are counted once (its
    # last pass's: one zone of all 32 vertices; the passes each counted theirs again before)
    assert st["passes"] == 7, st
    assert st["self_fallback_all"] == 0 and st["self_zones"] == 1, st
    assert st["self_zone_vertices"] == 32, st
    np.testing.assert_allclose(moved, moved.mean(), atol=1e-6)  # one rigid zone
    assert 0.00125 <= moved.mean() < 0.0014  # one plate's 10 mm over eight, and the round's
    st, moved = resolve(zone_passes=3)
    assert st["self_fallback_all"] == 1 and np.allclose(moved, 0.0)  # back to the start


def _full_entries(sc):
    """`_entries` with each entry's normal and weights (rounded: float32 from float64)."""
    k = int(sc.record.count.numpy()[0])
    r = sc.record
    return sorted((int(kd), *map(int, v), *np.round(n, 5), *np.round(w, 5)) for kd, v, n, w in
                  zip(r.kind.numpy()[:k], r.vertex.numpy()[:k], r.normal.numpy()[:k],
                      r.weight.numpy()[:k]))


def test_candidate_lists_detect_what_the_bvhs_detect():
    """Detections by the candidate lists (`SelfCollision._query_listed`: pairs listed by one
    BVH traversal with boxes grown by the reach, tested again with each detection's own
    boxes) find exactly the contacts of a BVH traversal per detection (``candidate_reach=0``),
    normals and weights included, on a crumpled sheet: at the build, after every vertex moved
    by less than the reach (no new build), past it (a new build), with a larger gap (a new
    build), with only some vertices marked (`_detect_moved`), and when a build does not fit
    its room (the BVHs detect; the lists grow at the frame's end, a recorded graph is
    recorded again)."""
    import warp as wp

    from warp_cloth.collision.self_collision import CANDIDATE_REACH, SelfCollision

    assert CANDIDATE_REACH > 0
    model, rng = _crumpled(res=8, spread=0.04)
    h = 0.03
    x0 = model.mesh.vertices
    x1 = x0 + rng.normal(0, 0.02, x0.shape)
    lists, plain = SelfCollision(model, h), SelfCollision(model, h, candidate_reach=0)
    assert plain.candidate_stats() == {}
    reach = lists._cand_reach
    assert reach == pytest.approx(CANDIDATE_REACH * h)

    def both(a, b, gap, moved=None):
        out = []
        for sc in (lists, plain):
            sc.record.count.zero_()
            a_ = wp.array(a, dtype=wp.vec3, device="cpu")
            b_ = wp.array(b, dtype=wp.vec3, device="cpu")
            if moved is None:
                sc.detect(a_, b_, gap, sc.record)
            else:
                sc._moved_round.assign(moved)
                sc._detect_moved(a_, b_, gap)
            out.append(_full_entries(sc))
        assert out[0] == out[1]
        assert len(out[0]) > 20
        return lists.candidate_stats()["builds"]

    assert both(x0, x1, h) == 1
    step = rng.uniform(-0.9, 0.9, x0.shape) * reach  # every vertex, within the reach
    assert both(x0 + step, x1 - step, h) == 1
    moved = (rng.uniform(size=len(x0)) < 0.3).astype(np.int32)
    assert both(x0, x1 + step, h, moved) == 1
    far = x1.copy()
    far[5, 2] = max(x0[5, 2], x1[5, 2]) + 1.5 * reach  # one vertex past its path's box
    assert both(x0, far, h) == 2
    assert both(x0, far, 1.5 * h) == 3  # a larger gap than built for
    assert both(x0, far, h) == 3  # the lists serve the smaller gap too
    st = lists.candidate_stats()
    assert st["overflows"] == 0 and st["most_ee"] > st["most_vt"] > 0
    lists._cand_alloc(10, 10)  # too little room: the build overflows, the BVHs detect
    assert both(x0, x1, h) == 4
    st = lists.candidate_stats()
    assert st["overflows"] == 1 and lists.stats["self_list_overflows"] == 1
    assert [m for m in lists.frame_end() if m[1]] == [(None, True)]  # grown; graphs again
    st = lists.candidate_stats()
    assert st["room_vt"] >= st["most_vt"] and st["room_ee"] >= st["most_ee"]
    assert both(x0, x1, h) == 5 and lists.candidate_stats()["overflows"] == 1
    assert [m for m in lists.frame_end() if m[1]] == []


def test_candidate_lists_cover_pairs_that_come_close_within_the_reach():
    """Two sheets farther apart than the gap at the lists' build (no pair close, no box
    overlap at the gap alone), then each moved 0.9 reach toward the other, a detection
    without a build: they now come within the gap, and the lists (built with boxes grown by
    the reach) hold those pairs: the BVH traversal's contacts exactly."""
    import warp as wp

    from warp_cloth.collision.self_collision import SelfCollision

    h = 0.01
    reach = 0.5 * h
    model = _two_sheets(h + 1.7 * reach)
    lists = SelfCollision(model, h, candidate_reach=0.5)
    plain = SelfCollision(model, h, candidate_reach=0)
    x = model.mesh.vertices
    n = len(x) // 2
    closer = x.copy()
    closer[:n, 1] += 0.9 * reach
    closer[n:, 1] -= 0.9 * reach
    out = []
    for sc in (lists, plain):
        for a, b in ((x, x), (closer, closer)):
            sc.record.count.zero_()
            sc.detect(wp.array(a, dtype=wp.vec3, device="cpu"),
                      wp.array(b, dtype=wp.vec3, device="cpu"), h, sc.record)
            out.append(_full_entries(sc))
    assert out[0] == out[2] == []
    assert len(out[3]) > 50 and out[1] == out[3]
    assert lists.candidate_stats()["builds"] == 1


def test_response_detections_reuse_the_solve_detection():
    """A response's detections take the solve's (`SelfCollision._reuse_or`): the solve's
    record entries tested again on the response's paths, plus the pairs with a vertex whose
    path ends left the solve's by more than half the gaps' difference (detected by the BVHs):
    exactly a full detection's contacts. Two sheets 1.5 thicknesses apart, then pressed
    together by 0.3 each (every vertex near: the contacts come from the solve's entries);
    one vertex pushed far through the other sheet (a far vertex too); sheets 3.6 thicknesses
    apart (no solve entry), four vertices of each pressed by 1.4 toward the other (far: fails
    with the allowance doubled, those vertices would count as near and their contacts be
    missed); the whole sheets pressed (most vertices far), a solve record that dropped
    entries, a forgotten one, and a gap not below the solve's: a full detection."""
    import warp as wp

    from warp_cloth.collision.record import make_record
    from warp_cloth.collision.self_collision import SelfCollision

    h = 0.01
    model = _two_sheets(1.5 * h)
    sc = SelfCollision(model, h)
    plain = SelfCollision(model, h, candidate_reach=0)
    x = model.mesh.vertices
    n = len(x) // 2

    def arr(a):
        return wp.array(a, dtype=wp.vec3, device="cpu")

    def note(a, b, gs, rec):
        rec.count.zero_()
        rec.overflow.zero_()
        sc.detect(arr(a), arr(b), gs, rec)
        sc.note_solve(arr(a), arr(b), gs, rec)

    def respond(a, b, g):
        sc.record.count.zero_()
        sc.counters.zero_()
        sc._reuse_or(arr(a), arr(b), g, sc._detect_full, sc._reuse_all)
        plain.record.count.zero_()
        plain.detect(arr(a), arr(b), g, plain.record)
        got = _full_entries(sc)
        assert got == _full_entries(plain)
        return len(got), sc.stats["self_reused"], int(sc._sol_flags.numpy()[1])

    def pressed(a, by):
        b = a.copy()
        b[:n, 1] += by
        b[n:, 1] -= by
        return b

    solve = make_record(1 << 14, "cpu")
    note(x, x, 3 * h, solve)
    assert int(solve.count.numpy()[0]) > 50
    k, reused, far = respond(x, pressed(x, 0.3 * h), h)
    assert k > 50 and reused == 1 and far == 0
    through = pressed(x, 0.3 * h)
    through[n + 3] += [0.3, -2.0 * h, 0.0]
    k2, reused, far = respond(x, through, h)
    assert k2 != k and reused == 1 and far == 1
    apart = x.copy()
    apart[n:, 1] += 2.1 * h
    note(apart, apart, 3 * h, solve)
    assert int(solve.count.numpy()[0]) == 0
    patch = apart.copy()
    for i in (16, 17, 23, 24):  # four vertices of each sheet, facing each other
        patch[i, 1] += 1.4 * h
        patch[n + i, 1] -= 1.4 * h
    k, reused, far = respond(apart, patch, h)
    assert k > 4 and reused == 1 and far == 1
    k, reused, far = respond(apart, pressed(apart, 1.3 * h), h)  # most vertices far
    assert k > 50 and reused == 0 and far == 1
    small = make_record(4, "cpu")  # the solve's detection drops entries: not reused
    note(x, x, 3 * h, small)
    k, reused, _ = respond(x, pressed(x, 0.3 * h), h)
    assert k > 50 and reused == 0
    note(x, x, 3 * h, solve)
    sc.forget_solve()
    assert respond(x, pressed(x, 0.3 * h), h)[1] == 0
    note(x, x, 3 * h, solve)
    assert respond(x, pressed(x, 0.3 * h), 3 * h)[1] == 0
    for bad in (h, 0.5 * h, float("nan"), float("inf"), "wide"):  # not above the thickness
        with pytest.raises(ValueError, match="note_solve: gap"):
            sc.note_solve(arr(x), arr(x), bad, solve)
    with pytest.raises(ValueError, match="note_solve: x1 has 3 positions"):
        sc.note_solve(arr(x), arr(x[:3]), 3 * h, solve)


@pytest.mark.parametrize("rounds", [6, 1])
def test_responses_from_the_solve_detection_detect_what_full_rounds_detect(rounds):
    """A response whose detections start from the solve's (`SelfCollision._reuse_or`): its
    first round's solve entries tested again, later rounds' only those with a vertex the last
    projection moved beside the kept entries (`_reuse_kept`), the zones' first pass's kept
    entries tested again at the fail-safe gap (`_reuse_retested`), far vertices' pairs by
    the BVHs: every round's and zone pass's entries exactly those of full detections, on the
    crumpled sheet of `test_incremental_rounds_detect_what_full_rounds_detect` with a solve
    path near the response's but for a few vertices, and the same end positions. (Once the
    zones' rigid moves take most vertices far from the solve's paths, full detections.)"""
    import warp as wp

    from warp_cloth.collision.record import make_record
    from warp_cloth.collision.self_collision import SelfCollision

    model, rng = _crumpled(res=8, spread=0.04)
    h = 0.03
    x0 = model.mesh.vertices
    x1 = x0 + rng.normal(0, 0.03 if rounds > 1 else 0.08, x0.shape)
    pred = x1 + rng.normal(0, 0.05 * h, x0.shape)
    pred[::17] += 1.5 * h  # far from the response's paths

    def arr(a):
        return wp.array(a, dtype=wp.vec3, device="cpu")

    runs = {}
    for reuse in (True, False):
        sc = SelfCollision(model, h, rounds=rounds, iterations=2, incremental=reuse)
        rounds_seen, zones_seen = [], []
        project, zone_pass = sc._project, sc._zone_pass

        def spy(state, dt, sc=sc, project=project, seen=rounds_seen):
            seen.append(_entries(sc))
            project(state, dt)

        def zspy(*a, sc=sc, zone_pass=zone_pass, seen=zones_seen, **k):
            zone_pass(*a, **k)
            seen.append(_entries(sc))

        sc._project, sc._zone_pass = spy, zspy
        if reuse:
            solve = make_record(1 << 15, "cpu")
            sc.detect(arr(x0), arr(pred), 3.0 * h, solve)
            sc.note_solve(arr(x0), arr(pred), 3.0 * h, solve)
        state = model.state()
        state.x.assign(x1)
        sc.resolve(state, arr(x0), 1.0 / 60.0)
        runs[reuse] = (rounds_seen, zones_seen, state.x.numpy(), sc.stats)
    (r, z, x_r, st_r), (f, zf, x_f, st_f) = runs[True], runs[False]
    assert len(r) == len(f) and len(z) == len(zf)
    assert st_f["self_reused"] == 0 and st_r["self_reused"] >= 1
    if rounds > 1:  # every detection reused (with one round the zones' moves leave the
        assert st_r["self_reused"] == len(r) + len(z)  # solve's paths: full detections)
    if rounds > 1:
        assert len(r) >= 4 and min(len(e) for e in f) >= 3
    else:
        assert len(zf) >= 2 and len(zf[0]) > 0
    for a, b in zip(r + z, f + zf):
        assert a == b
    assert np.allclose(x_r, x_f, atol=1e-6)


def test_later_reused_detections_keep_or_test_again_the_unmoved_entries():
    """The later detections of a response that starts from the solve's: a round keeps the last
    record's entries whose vertices neither moved nor are far and tests again only the solve's
    entries with a moved vertex (`SelfCollision._reuse_kept`: with every solve entry tested
    again the kept pairs come twice; with the moved vertices' entries kept they are stale);
    a zone pass's first detection tests the kept entries again at its smaller gap
    (`_reuse_retested`: kept as they were, pairs beyond that gap stay). Each exactly a full
    detection's contacts; two sheets 1.2 thicknesses apart, rounds detecting at 2, a third of
    the vertices moved, a zone pass at 1.1."""
    import warp as wp

    from warp_cloth.collision.record import make_record
    from warp_cloth.collision.self_collision import SelfCollision

    h = 0.01
    model = _two_sheets(1.2 * h)
    sc = SelfCollision(model, h)
    plain = SelfCollision(model, h, candidate_reach=0)
    x = model.mesh.vertices
    rng = np.random.default_rng(5)
    moved = (rng.uniform(size=len(x)) < 0.3).astype(np.int32)
    x2 = x + moved[:, None] * rng.uniform(-0.1, 0.1, x.shape) * h

    def arr(a):
        return wp.array(a, dtype=wp.vec3, device="cpu")

    def full(b, g):
        plain.record.count.zero_()
        plain.detect(arr(x), arr(b), g, plain.record)
        return _full_entries(plain)

    solve = make_record(1 << 14, "cpu")
    sc.detect(arr(x), arr(x), 5 * h, solve)
    sc.note_solve(arr(x), arr(x), 5 * h, solve)
    sc.counters.zero_()
    sc._moved_round.zero_()
    sc._incremental.zero_()
    sc._reuse_or(arr(x), arr(x), 2 * h, sc._round_detect, sc._reuse_round)  # a first round
    first = _full_entries(sc)
    assert first == full(x, 2 * h) and len(first) > 100
    sc._moved_round.assign(moved)
    sc._incremental.fill_(1)
    sc._reuse_or(arr(x), arr(x2), 2 * h, sc._round_detect, sc._reuse_round)  # a later round
    assert _full_entries(sc) == full(x2, 2 * h)
    sc._zone_incremental.fill_(1)
    sc._moved_round.zero_()
    sc._reuse_or(arr(x), arr(x2), 1.1 * h, sc._zone_detect, sc._reuse_zone)  # a zone pass
    zone = _full_entries(sc)
    assert zone == full(x2, 1.1 * h) and 0 < len(zone) < len(first)
    assert sc.stats["self_reused"] == 3


def _irregular_fold(solver_name, self_collision=True, res=10, frames=60, seed=1):
    """A sheet of irregular triangles (interior vertices moved up to 0.3 of a cell, each cell
    split along a random diagonal), 0.6 m, lying on the floor with its half beyond the middle
    column (x = 0, moved along z only, so that no edge spans it and the fold keeps every
    length) lifted 150 degrees about it: it falls over onto the other half. Built through the
    public API, as a user's own mesh would be."""
    from warp_cloth import ClothModel, Scene, make_solver
    from warp_cloth.bench.meshes import _fold, jittered_grid
    from warp_cloth.collision import Plane

    thickness, size = 0.005, 0.6
    mesh = jittered_grid(res, size, seed, thickness, keep_column=0.0)
    x = _fold(mesh.vertices, 0.0, 150.0, thickness)
    model = ClothModel(mesh, density=0.15, stretch_stiffness=1000.0, damping=0.1, device="cpu")
    model.initial_positions = x
    stage = CollisionStage(model, [Plane()], thickness=thickness, friction=0.4,
                           self_collision=self_collision)
    scene = Scene(model, make_solver(solver_name, model, collision=stage), fps=60.0,
                  frames=frames)
    stats = scene.run(None, quiet=True, energy=False, check_intersections=True)
    return stats, scene


@pytest.mark.parametrize("solver_name", ["explicit", "implicit", "pd", "pbd"])
def test_irregular_sheet_folds_onto_itself_without_crossing(solver_name):
    """Not a grid: a user's mesh of irregular triangles folds onto itself under every solver
    with no crossing edge-triangle pair in any frame (`RunStats.crossing_frames`; the checker
    fails the same fold without self-collision, below), and it did fold: the lifted half lies
    on the other, within a few thicknesses of the floor."""
    stats, scene = _irregular_fold(solver_name)
    assert stats.crossing_frames == 0, stats.max_crossings
    x = scene.state.positions()
    assert np.all(np.isfinite(x))
    assert x[:, 1].max() < 0.03, x[:, 1].max()
    assert stats.max_strain < 0.05, stats.max_strain


def test_irregular_sheet_passes_through_itself_without_self_collision():
    stats, _ = _irregular_fold("pd", self_collision=False)
    assert stats.crossing_frames > 0


@pytest.mark.parametrize("stretch, diverged", [(10.5, True), (9.5, False), (np.nan, True)])
def test_a_response_to_a_diverged_solve_returns_the_cloth_without_detecting(stretch, diverged):
    """A 4 x 4 sheet whose solve moved one corner so far that its edge is ``1 + stretch`` times
    its rest length (`DIVERGED_STRAIN` = 10), or to NaN: the response returns every free vertex
    to its start with zero velocity and detects nothing (``self_diverged``, also a whole-cloth
    fall-back); just under the bound it responds as usual, and the paths (no other layer) need
    nothing."""
    from warp_cloth.collision.self_collision import DIVERGED_STRAIN, SelfCollision

    assert DIVERGED_STRAIN == 10.0
    model = sheet_model(res=4)
    sc = SelfCollision(model, 0.005)
    st = model.state()
    x0 = st.positions()
    x = x0.copy()
    h = 1.0 / 4  # the cell: corner 0's edge along x runs to vertex 1
    x[0] = x[1] - np.array([h * (1.0 + stretch), 0.0, 0.0]) if np.isfinite(stretch) \
        else np.array([np.nan, 0.0, 0.0])
    st.x.assign(wp.array(x, dtype=wp.vec3, device="cpu"))
    st.v.assign(wp.array(np.ones_like(x), dtype=wp.vec3, device="cpu"))
    sc.resolve(st, wp.array(x0, dtype=wp.vec3, device="cpu"), 1.0 / 60.0)
    s = sc.stats
    if diverged:
        np.testing.assert_array_equal(st.positions(), x0)
        assert np.all(st.v.numpy() == 0.0)
        assert s["self_diverged"] == 1 and s["self_fallback_all"] == 1
        assert s["self_contacts"] == 0
        msgs = [m for m, _ in sc.frame_end()]
        assert sc.frame_diverged and sc.frame_frozen
        assert any("past 1,000 %" in m for m in msgs), msgs
    else:
        np.testing.assert_allclose(st.positions(), x, atol=1e-6)
        assert s["self_diverged"] == 0 and s["self_fallback_all"] == 0
        sc.frame_end()
        assert not sc.frame_diverged


def test_explicit_euler_far_past_its_stable_step_with_self_collision_stops_as_diverged():
    """Explicit Euler forced to one step a frame at 24 fps (far past its stable step) on a
    hanging sheet with self-collision: the run ends as diverged, naming the solver's steps,
    within the frames the frozen-frame guard allows, instead of detecting over the exploded
    paths (40-100 s a frame on the 32 x 32 sheet before `DIVERGED_STRAIN`)."""
    from warp_cloth import SimulationDiverged
    from warp_cloth.scenes import hanging

    scene = hanging(solver="explicit", res=8, fps=24.0, frames=12, substeps=1,
                    self_collision=True)
    with pytest.raises(SimulationDiverged, match="the solver's steps diverged") as info:
        scene.run(None, quiet=True, energy=False)
    assert info.value.frame <= 6
    assert scene.solver.collision.stats["self_diverged_total"] > 0
