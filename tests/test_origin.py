"""A cloth far from the world origin is simulated in a frame centred on it (`ClothModel.origin`).

float32 positions 1,000 m out resolve 6e-5 m, and a step's small moves round away: before the
frame a 16 x 16 fold there froze under projective dynamics, gained 94 % of its energy under PBD
and did not fold under explicit Euler. The simulation frame makes a far scene the same
computation as a near one: every number the solvers see is the same, and only the output (USD,
heights, energies, `State.world_positions`) is moved back to the world.
"""

import numpy as np
import pytest

import warp_cloth as wc
from warp_cloth.collision import Box, CollisionStage, Motion, Plane, Sphere
from warp_cloth.collision.motion import KeyframePath
from warp_cloth.usd import read_points

#: a world offset whose coordinates, and every sum below, are exact in float64 and float32
FAR = np.array([1024.0, 512.0, -2048.0])
FRAMES = 12


def _scene(solver, shift, origin=None, out=None, self_collision=True):
    """An 8 x 8 sheet (dyadic coordinates, so a shift is exact) pinned at two corners that a
    `PinPath` carries sideways, over a sphere and a box that slides by keyframes, on a floor;
    everything moved by ``shift``."""
    s = np.asarray(shift, dtype=np.float64)
    mesh = wc.TriMesh.grid(8, 8, size=0.5, plane="xz", origin=tuple(s + (-0.125, 0.625, -0.25)))
    pins = [0, 8]
    x0 = mesh.vertices[pins]
    path = wc.PinPath(np.array([0.0, 1.0]), np.stack([x0, x0 + (0.25, 0.0, 0.0)]))
    model = wc.ClothModel(mesh, density=0.15, stretch_stiffness=1000.0, pins=pins,
                          pin_path=path, damping=0.1, origin=origin)
    box_path = KeyframePath(np.array([0.0, 1.0]), np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.25]]))
    obstacles = [Plane(point=tuple(s)),
                 Sphere(0.125, center=tuple(s + (0.0, 0.25, 0.0))),
                 Box((0.0625, 0.0625, 0.125), center=tuple(s + (0.25, 0.125, -0.125)),
                     motion=Motion(path=box_path))]
    stage = CollisionStage(model, obstacles, self_collision=self_collision)
    solver_obj = wc.make_solver(solver, model, collision=stage)
    return wc.Scene(model, solver_obj, fps=60, frames=FRAMES), out


def test_the_frame_is_chosen_only_far_from_the_origin():
    near = wc.ClothModel(wc.TriMesh.grid(4, 4, size=1.0, plane="xz", origin=(2.5, 1.0, -3.5)))
    assert not np.any(near.origin)
    assert near.mesh is near.world_mesh
    far = wc.ClothModel(wc.TriMesh.grid(4, 4, size=1.0, plane="xz", origin=(999.6, 1.0, 3.0)))
    np.testing.assert_array_equal(far.origin, [1000.0, 1.0, 4.0])  # the box's centre, rounded
    np.testing.assert_allclose(far.initial_positions + far.origin, far.world_mesh.vertices)
    st = far.state()
    np.testing.assert_allclose(st.world_positions(), far.world_mesh.vertices, atol=1e-12)
    # the rest shape is the same in either frame
    np.testing.assert_allclose(far.spring_rest, near.spring_rest, rtol=1e-12)
    forced = wc.ClothModel(far.world_mesh, origin=(0, 0, 0))
    assert not np.any(forced.origin)


@pytest.mark.parametrize("bad", [(1.0, 2.0), (0.0, np.nan, 0.0), "origin", (1e39, 0.0, 0.0)])
def test_a_bad_origin_is_refused_by_name(bad):
    with pytest.raises(ValueError, match="origin"):
        wc.ClothModel(wc.TriMesh.grid(2, 2), origin=bad)


@pytest.mark.parametrize("solver", ["explicit", "implicit", "pbd", "pd"])
def test_a_far_scene_computes_exactly_as_the_same_scene_near_the_origin(solver, tmp_path):
    # the near scene is given the same simulation frame by hand (its sheet's centre rounds to
    # (0, 1, 0)); the far one finds its own: the solvers then see the same numbers bit for bit
    near, _ = _scene(solver, (0.0, 0.0, 0.0), origin=(0.0, 1.0, 0.0))
    far, _ = _scene(solver, FAR)
    np.testing.assert_array_equal(far.model.origin, FAR + (0.0, 1.0, 0.0))
    out_near, out_far = tmp_path / "near.usd", tmp_path / "far.usd"
    a = near.run(str(out_near), quiet=True, check_intersections=True)
    b = far.run(str(out_far), quiet=True, check_intersections=True)
    np.testing.assert_array_equal(far.state.x.numpy(), near.state.x.numpy())
    np.testing.assert_allclose(far.state.world_positions() - near.state.world_positions(),
                               np.broadcast_to(FAR, (near.model.num_vertices, 3)), rtol=0, atol=1e-9)
    # the cloth moved (pins carried sideways, falling onto the sphere and the sliding box)
    assert np.abs(near.state.x.numpy() - near.model.initial_positions).max() > 0.01
    assert b.max_strain == a.max_strain
    assert b.crossing_frames == a.crossing_frames == 0
    assert b.obstacle_frames == a.obstacle_frames == 0
    assert b.min_clearance == a.min_clearance
    assert b.min_height == pytest.approx(a.min_height + FAR[1], abs=1e-9)
    assert b.max_height == pytest.approx(a.max_height + FAR[1], abs=1e-9)
    # energies are the world frame's: gravity's potential of the offset added
    lift = far.model.total_mass * 9.81 * FAR[1]
    assert b.energy_initial - a.energy_initial == pytest.approx(lift, rel=1e-6)
    assert b.energy_final - b.energy_initial == pytest.approx(a.energy_final - a.energy_initial,
                                                              abs=1e-6)
    # the output is in the world frame: the cloth and the obstacles
    _, pn, _ = read_points(str(out_near))
    _, pf, _ = read_points(str(out_far))
    np.testing.assert_allclose(pf - pn, np.broadcast_to(FAR, pn.shape), atol=2e-4)


def test_far_obstacles_are_drawn_where_they_were_given(tmp_path):
    scene, _ = _scene("pbd", FAR)
    stage = scene.solver.collision
    assert [type(ob).__name__ for ob in stage.obstacles] == ["Plane", "Sphere", "Box"]
    assert stage.obstacles[1].position[0] == FAR[0]  # the world objects, as given
    assert stage.sim_obstacles[1].position[0] == FAR[0] - scene.model.origin[0]
    assert scene.obstacles == stage.obstacles
    # a sphere given to the scene is the stage's own (no "not in the stage" refusal)
    assert wc.Scene(scene.model, scene.solver, obstacles=stage.obstacles[1:2], frames=2)


def test_a_far_fold_folds_under_every_solver():
    """The measured failure: a 16 x 16 fold 1,000 m out froze under PD (0.194 J kept), rose to
    0.376 J under PBD and did not fold under explicit Euler; folded at the origin, all end
    near 0.02-0.04 J."""
    from warp_cloth import contact_scenes as cs

    for solver in ("pd", "pbd", "explicit"):
        near = cs.fold(solver=solver, res=16, frames=40).run(None, quiet=True)
        far = cs.fold(solver=solver, res=16, frames=40, center=(1000.0, 0.0)).run(None,
                                                                                 quiet=True)
        assert far.energy_final < 0.5 * far.energy_initial, solver
        assert far.energy_final == pytest.approx(near.energy_final, rel=0.05), solver


def test_a_tilted_plane_far_away_is_anchored_near_the_cloth():
    p = Plane(normal=(0.0, 1.0, 1.0), point=(0.0, 0.0, 0.0))
    o = np.array([1000.0, 3.0, -500.0])
    q = p.shifted(-o)
    assert np.linalg.norm(q.position) < 1000.0  # its point nearest the frame's origin
    pts = np.array([[0.5, 0.25, -0.75], [-1.0, 2.0, 0.5]])
    np.testing.assert_allclose(q.signed_distance(pts), p.signed_distance(pts + o), atol=1e-9)
    spinning = Plane(normal=(0.0, 1.0, 1.0), motion=Motion(angular_velocity=(0.0, 1.0, 0.0)))
    np.testing.assert_allclose(spinning.shifted(-o).position, -o)  # turns about its own point


def _uv_sphere(radius=0.3, nu=24, nv=12):
    th = np.linspace(0.0, np.pi, nv + 1)
    ph = np.linspace(0.0, 2.0 * np.pi, nu, endpoint=False)
    v = [(0.0, radius, 0.0)]
    for i in range(1, nv):
        for j in range(nu):
            v.append((radius * np.sin(th[i]) * np.cos(ph[j]), radius * np.cos(th[i]),
                      radius * np.sin(th[i]) * np.sin(ph[j])))
    v.append((0.0, -radius, 0.0))
    f = [(0, 1 + (j + 1) % nu, 1 + j) for j in range(nu)]
    for i in range(nv - 2):
        for j in range(nu):
            a, b = 1 + i * nu + j, 1 + i * nu + (j + 1) % nu
            f += [(a, b, b + nu), (a, b + nu, a + nu)]
    last = len(v) - 1
    f += [(last, 1 + (nv - 2) * nu + j, 1 + (nv - 2) * nu + (j + 1) % nu) for j in range(nu)]
    return np.array(v), np.array(f)


def test_a_mesh_obstacle_baked_far_out_keeps_its_clearance():
    """A mesh exported in world coordinates (vertices 1,000 m out, no pose) under a far sheet:
    its simulation copy is re-centred on its vertices, so the BVH queries run near the origin
    (left 1,000 m out, a PBD drape kept 4.93 mm of the 5 mm clearance)."""
    from warp_cloth.collision import MeshObstacle

    v, f = _uv_sphere()
    off = np.array([1000.0, 0.3, 0.0])
    baked = MeshObstacle((v + off, f))
    mesh = wc.TriMesh.grid(16, 16, size=1.0, plane="xz", origin=(999.5, 0.75, -0.5))
    model = wc.ClothModel(mesh, density=0.15, stretch_stiffness=1000.0, damping=0.1)
    stage = CollisionStage(model, [Plane(), baked], self_collision=True)
    sim = stage.sim_obstacles[1]
    assert np.abs(sim.vertices).max() < 1.0  # re-centred; the given object untouched
    assert np.abs(baked.vertices).max() > 999.0 and stage.obstacles[1] is baked
    # the same surface: as the sphere given by its pose (whose queries are near its origin;
    # the baked one's own, in float32 1,000 m out, are 2e-5 m off)
    posed = MeshObstacle((v, f), position=tuple(off))
    pts = np.array([[1000.1, 0.7, 0.05], [999.8, 0.1, 0.2]])
    np.testing.assert_allclose(sim.signed_distance(pts - model.origin),
                               posed.signed_distance(pts), atol=1e-6)
    scene = wc.Scene(model, wc.make_solver("pbd", model, collision=stage), fps=60, frames=60)
    st = scene.run(None, quiet=True, check_intersections=True)
    assert st.min_clearance >= 0.005 - 1e-5
    assert st.crossing_frames == 0 and st.obstacle_frames == 0
    # a turning mesh turns about its own origin: not re-centred
    spun = MeshObstacle((v + off, f), motion=Motion(angular_velocity=(0.0, 1.0, 0.0)))
    s2 = CollisionStage(model, [spun])
    np.testing.assert_array_equal(s2.sim_obstacles[0].vertices, spun.vertices)
