"""Position-based dynamics (physics.md 2.9, T23-T27, T31): exact small cases and properties."""

import math

import numpy as np
import pytest
import warp as wp

from warp_cloth import ClothModel, PinPath, Scene, TriMesh
from warp_cloth.diagnostics import edge_strains
from warp_cloth.scenes import hanging_model
from warp_cloth.solvers import make_solver
from warp_cloth.solvers.pbd import PositionBased, color_constraints


def one_triangle_model(pins=(), masses=(1.0, 3.0, 0.5), **kw):
    mesh = TriMesh(np.array([[0.0, 0, 0], [1.0, 0, 0], [0.0, 0, 1.0]]), np.array([[0, 1, 2]]))
    return ClothModel(mesh, masses=list(masses), pins=list(pins), **kw)


def keep_springs(model, idx):
    """Restrict the model's springs (host arrays the solver reads) to ``idx`` (test hack)."""
    idx = np.asarray(idx, dtype=np.int64)
    model.spring_pairs = model.spring_pairs[idx]
    model.spring_rest = model.spring_rest[idx]
    model.spring_stiffness = model.spring_stiffness[idx]
    model.num_springs = len(idx)
    return model


def arr(x):
    return wp.array(np.asarray(x, dtype=np.float32), dtype=wp.vec3, device="cpu")


def corners_model(n=10, damping=4.0):
    mesh = TriMesh.grid(n, n, size=1.0, plane="xz", origin=(-0.5, 1.0, -0.5))
    return ClothModel(mesh, pins=[0, n, n * (n + 1), (n + 1) ** 2 - 1], damping=damping)


def perturbed(model, seed=0, drop=0.01, noise=0.01):
    """Rest positions with the free vertices dropped and jittered (a PBD prediction)."""
    rng = np.random.default_rng(seed)
    x = model.mesh.vertices.copy()
    free = model.inverse_masses > 0
    x[free, 1] -= drop * rng.random(free.sum())
    x[free] += noise * rng.standard_normal((free.sum(), 3))
    return x


# ---------------------------------------------------------------------- T23: single edge
@pytest.mark.parametrize("gs", [False, True])
def test_single_edge_projection_exact_and_keeps_mass_centre(gs):
    model = keep_springs(one_triangle_model(), [0])  # edge (0, 1), masses 1 and 3
    solver = PositionBased(model, iterations=1, gauss_seidel=gs, relaxation=0.0)
    x0 = np.array([[-0.3, 0.2, 0.1], [1.4, -0.5, 0.3], [0.0, 0.0, 1.0]])
    x = arr(x0)
    solver.project(x)
    xn = x.numpy().astype(np.float64)
    assert np.linalg.norm(xn[0] - xn[1]) == pytest.approx(1.0, abs=1e-6)
    c0 = (1.0 * x0[0] + 3.0 * x0[1]) / 4.0
    c1 = (1.0 * xn[0] + 3.0 * xn[1]) / 4.0
    np.testing.assert_allclose(c1, c0, atol=1e-6)
    # moves along the edge, the light vertex 3x as far as the heavy one
    d0 = x0[0] - x0[1]
    for k in (0, 1):
        mv = xn[k] - x0[k]
        assert np.linalg.norm(np.cross(mv, d0)) < 1e-5
    assert np.linalg.norm(xn[0] - x0[0]) == pytest.approx(3 * np.linalg.norm(xn[1] - x0[1]), rel=1e-4)
    np.testing.assert_array_equal(xn[2], x0[2])  # not in any constraint


def test_single_edge_with_pinned_end_moves_only_the_other():
    model = keep_springs(one_triangle_model(pins=[0]), [0])
    solver = PositionBased(model, iterations=1, relaxation=0.0)
    x0 = np.array([[0.0, 0.0, 0.0], [0.0, -2.5, 0.0], [0.0, 0.0, 1.0]])
    x = arr(x0)
    solver.project(x)
    xn = x.numpy()
    np.testing.assert_array_equal(xn[0], x0[0])
    np.testing.assert_allclose(xn[1], [0.0, -1.0, 0.0], atol=1e-6)


def test_pins_never_move_in_a_step_and_scripted_pins_follow():
    model = hanging_model(res=6, damping=0.0)
    solver = PositionBased(model, iterations=5)
    state = model.state()
    x_pins = state.positions()[model.pins]
    for _ in range(20):
        solver.step(state, 1.0 / 240)
    np.testing.assert_array_equal(state.positions()[model.pins], x_pins)
    assert np.all(state.velocities()[model.pins] == 0.0)

    mesh = model.mesh
    p0 = mesh.vertices[[0, 6]]
    path = PinPath([0.0, 1.0], np.stack([p0, p0 + [0.0, 0.5, 0.0]]))
    model2 = ClothModel(mesh, pins=[0, 6], pin_path=path)
    s2 = PositionBased(model2, iterations=5)
    st = model2.state()
    for _ in range(10):
        s2.step(st, 0.01)
    np.testing.assert_allclose(st.positions()[[0, 6]], p0 + [0.0, 0.05, 0.0], atol=1e-5)
    np.testing.assert_allclose(st.velocities()[[0, 6]], [[0.0, 0.5, 0.0]] * 2, atol=1e-3)


# ---------------------------------------------------------------------- T24: more iterations
@pytest.mark.parametrize("gs", [False, True])
def test_more_iterations_monotonically_smaller_violation(gs):
    model = hanging_model(res=12)
    x_start = perturbed(model, drop=0.05)
    solver = PositionBased(model, gauss_seidel=gs)
    viol = []
    for its in (1, 2, 4, 8, 16, 32, 64):
        x = arr(x_start)
        solver.project(x, iterations=its)
        viol.append(np.abs(edge_strains(model, x.numpy())).max())
    assert all(b < a for a, b in zip(viol, viol[1:])), viol
    assert viol[-1] < 0.2 * viol[0]


def test_gauss_seidel_converges_faster_than_jacobi():
    """T26, for the notes' Jacobi blend (no over-relaxation) and the default over-relaxed one."""
    model = hanging_model(res=12)
    x_start = perturbed(model, drop=0.05)
    out = {}
    for key, kw in (("gs", dict(gauss_seidel=True)), ("plain", dict(over_relaxation=1.0)),
                    ("default", {})):
        x = arr(x_start)
        PositionBased(model, **kw).project(x, iterations=16)
        out[key] = np.abs(edge_strains(model, x.numpy())).max()
    assert out["gs"] < out["default"] < out["plain"]


@pytest.mark.parametrize("its", [4, 16, 64])
def test_over_relaxed_jacobi_blend_converges_faster(its):
    """The default blend moves each vertex by 1.7 times its averaged correction: after the same
    iterations from the same perturbed cloth the largest constraint violation is about a third
    lower than the notes' blend (measured 0.119 / 0.046 / 0.015 against 0.166 / 0.064 /
    0.024), and an explicit ``over_relaxation`` is what the blend uses."""
    model = hanging_model(res=12)
    x_start = perturbed(model, drop=0.05)
    viol = {}
    for w in (1.0, None, 1.7):
        x = arr(x_start)
        PositionBased(model, over_relaxation=w).project(x, iterations=its)
        viol[w] = np.abs(edge_strains(model, x.numpy())).max()
    assert viol[None] < 0.8 * viol[1.0]
    assert viol[1.7] == viol[None]


def test_over_relaxation_options():
    model = hanging_model(res=4)
    assert PositionBased(model).over_relaxation == 1.7
    assert "jacobi x1.7" in PositionBased(model).describe()
    assert PositionBased(model, over_relaxation=1.0).describe().startswith("pbd (jacobi, ")
    for kw in (dict(gauss_seidel=True), dict(compliance=1e-3), dict(bending_compliance=0.0)):
        assert PositionBased(model, **kw).over_relaxation == 1.0  # their own weights
        assert PositionBased(model, over_relaxation=1.0, **kw).over_relaxation == 1.0
        with pytest.raises(ValueError, match="over_relaxation applies to plain PBD"):
            PositionBased(model, over_relaxation=1.5, **kw)
    for bad in (0.0, 2.0, -1.0, float("nan"), float("inf"), True, "1.5"):
        with pytest.raises(ValueError, match=r"over_relaxation must be a number in \(0, 2\)"):
            PositionBased(model, over_relaxation=bad)


# ---------------------------------------------------------------------- T26: order independence
def test_jacobi_does_not_depend_on_edge_order():
    model = hanging_model(res=8)
    x_start = perturbed(model)
    ref = arr(x_start)
    PositionBased(model, iterations=7).project(ref)

    model2 = hanging_model(res=8)
    rng = np.random.default_rng(5)
    perm = rng.permutation(model2.num_springs)
    keep_springs(model2, perm)
    flip = rng.random(model2.num_springs) < 0.5
    model2.spring_pairs[flip] = model2.spring_pairs[flip][:, ::-1]
    x = arr(x_start)
    PositionBased(model2, iterations=7).project(x)
    np.testing.assert_allclose(x.numpy(), ref.numpy(), atol=2e-6)
    # ... whereas Gauss-Seidel order matters (T25)
    a, b = arr(x_start), arr(x_start)
    PositionBased(model, iterations=1, gauss_seidel=True).project(a)
    PositionBased(model2, iterations=1, gauss_seidel=True).project(b)
    assert np.abs(a.numpy() - b.numpy()).max() > 1e-4


# ---------------------------------------------------------------------- coloured Gauss-Seidel
def test_coloring_is_valid_and_small():
    model = hanging_model(res=8)
    pairs = model.spring_pairs
    colors = color_constraints(pairs, model.num_vertices)
    for c in range(colors.max() + 1):
        v = pairs[colors == c].reshape(-1)
        assert len(np.unique(v)) == len(v), f"colour {c} shares a vertex"
    assert colors.max() + 1 <= 8


def test_colored_gauss_seidel_equals_sequential_in_color_order():
    model = hanging_model(res=8)
    x_start = perturbed(model, drop=0.05)
    solver = PositionBased(model, iterations=3, gauss_seidel=True, tethers=False)  # springs only
    x = arr(x_start)
    solver.project(x)

    # sequential Gauss-Seidel in the solver's (colour) order, on the host in float64
    pairs = solver.constraint_pairs
    rest = np.linalg.norm(model.mesh.vertices[pairs[:, 0]] - model.mesh.vertices[pairs[:, 1]], axis=1)
    w = model.inverse_masses
    xr = x_start.astype(np.float32).astype(np.float64)
    for _ in range(3):
        for (i, j), L in zip(pairs, rest):
            d = xr[i] - xr[j]
            l = np.linalg.norm(d)
            g = (L - l) / ((w[i] + w[j]) * l) * d
            xr[i] += w[i] * g
            xr[j] -= w[j] * g
    np.testing.assert_allclose(x.numpy(), xr, atol=2e-5)


# ---------------------------------------------------------------------- compliance (XPBD)
def _corner_sag(iterations, compliance, gauss_seidel):
    model = corners_model()
    solver = PositionBased(model, iterations=iterations, compliance=compliance,
                           gauss_seidel=gauss_seidel)
    scene = Scene(model, solver, substeps=4, frames=90)
    scene.run(None, quiet=True, energy=False)
    return 1.0 - scene.state.positions()[:, 1].min()  # centre drop of a sheet held at 4 corners


@pytest.mark.parametrize("gs,its", [(True, 10), (False, 40)])
def test_compliance_makes_sag_independent_of_iterations(gs, its):
    a, b = _corner_sag(its, 0.03, gs), _corner_sag(2 * its, 0.03, gs)
    assert abs(b - a) / a < 0.05, (a, b)
    p, q = _corner_sag(its, None, gs), _corner_sag(2 * its, None, gs)
    assert abs(q - p) / p > 0.05, (p, q)  # plain PBD: stiffer with more iterations (T27)
    assert q < p


def test_xpbd_single_spring_equilibrium_is_the_spring_law():
    # vertex 1 (mass 3 kg) hangs straight below pinned vertex 0 on one constraint of
    # compliance a: at rest the stretch is m g a, whatever dt (the point of XPBD). The damping
    # factor exp(-c dt) multiplies the gravity increment of the prediction, hence in the law.
    a, m, g, c = 0.002, 3.0, 9.81, 5.0
    mesh = TriMesh(np.array([[0.0, 0, 0], [0.0, -1.0, 0], [0.0, 0, 1.0]]), np.array([[0, 1, 2]]))
    for dt in (1.0 / 60, 1.0 / 600):
        model = keep_springs(ClothModel(mesh, masses=[1.0, m, 1.0], pins=[0, 2], damping=c), [0])
        solver = PositionBased(model, iterations=2, compliance=a)
        state = model.state()
        for _ in range(int(round(4.0 / dt))):
            solver.step(state, dt)
        x = state.positions()
        assert abs(x[1, 0]) < 1e-6 and abs(x[1, 2]) < 1e-6
        assert -x[1, 1] - 1.0 == pytest.approx(m * g * a * math.exp(-c * dt), rel=1e-3)
    # compliance 0 is the notes' plain PBD (not over-relaxed): the same projection
    m0 = one_triangle_model()
    x_start = np.array([[0.1, 0.3, -0.2], [1.3, 0.0, 0.1], [0.0, -0.2, 1.4]])
    p, q = arr(x_start), arr(x_start)
    PositionBased(m0, iterations=3, over_relaxation=1.0).project(p)
    PositionBased(m0, iterations=3, compliance=0.0).project(q)
    np.testing.assert_allclose(p.numpy(), q.numpy(), atol=1e-6)


def test_bending_constraints_across_edges():
    model = hanging_model(res=6)
    n_bend = len(model.mesh.bend_quads)
    s = PositionBased(model, bending_compliance=0.0, gauss_seidel=True, iterations=60)
    assert s.num_constraints == model.num_springs + n_bend
    x_start = perturbed(model, drop=0.0, noise=0.02)
    x = arr(x_start)
    s.project(x)
    xn = x.numpy().astype(np.float64)
    bp = model.mesh.bend_quads[:, 2:4]
    x0 = model.mesh.vertices
    L = np.linalg.norm(x0[bp[:, 0]] - x0[bp[:, 1]], axis=1)
    before = np.abs(np.linalg.norm(x_start[bp[:, 0]] - x_start[bp[:, 1]], axis=1) / L - 1).max()
    after = np.abs(np.linalg.norm(xn[bp[:, 0]] - xn[bp[:, 1]], axis=1) / L - 1).max()
    assert after < 0.1 * before


# ---------------------------------------------------------------------- step, velocities, contact
def test_step_velocity_matches_position_change_and_falls_under_gravity():
    model = hanging_model(res=6, damping=0.0)
    solver = PositionBased(model, iterations=4)
    state = model.state()
    dt = 1.0 / 240
    solver.step(state, dt)
    x1 = state.positions()
    solver.step(state, dt)
    x2, v2 = state.positions(), state.velocities()
    free = model.inverse_masses > 0
    np.testing.assert_allclose(v2[free], (x2[free] - x1[free]) / dt, atol=2e-3)
    assert x2[free, 1].mean() < x1[free, 1].mean() < 1.0  # falling
    # without constraints it is exact free fall: y = y0 - g t^2 (1+...)/2 in symplectic form
    free_model = keep_springs(one_triangle_model(damping=0.0), [])
    st = free_model.state()
    s = PositionBased(free_model)
    for _ in range(10):
        s.step(st, 0.01)
    np.testing.assert_allclose(st.velocities()[:, 1], -9.81 * 0.1, rtol=1e-5)
    np.testing.assert_allclose(st.positions()[:, 1], -9.81 * 0.01 * 0.01 * 55, rtol=1e-4)


@pytest.mark.parametrize("gs", [False, True])
def test_contact_hook_runs_inside_every_iteration(gs):
    """The collision stage projects inside each of PBD's iterations and resolves once a step."""
    from warp_cloth.collision import CollisionStage, Plane

    model = hanging_model(res=6)
    stage = CollisionStage(model, [Plane(point=(0.0, 0.8, 0.0))])
    calls = {"project": 0, "resolve": 0}
    project, resolve = stage.project_positions, stage.resolve

    def counted_project(*a, **k):
        calls["project"] += 1
        return project(*a, **k)

    def counted_resolve(*a, **k):
        calls["resolve"] += 1
        return resolve(*a, **k)

    stage.project_positions, stage.resolve = counted_project, counted_resolve
    solver = PositionBased(model, iterations=3, gauss_seidel=gs, collision=stage)
    state = model.state()
    for _ in range(30):
        solver.step(state, 1.0 / 120)
    assert calls == {"project": 90, "resolve": 30}
    free = model.inverse_masses > 0
    x, v = state.positions(), state.velocities()
    floor = 0.8 + stage.thickness
    assert x[free, 1].min() >= floor - 1e-4
    assert x[free, 1].min() < floor + 1e-3  # it did reach the floor
    # resting on the floor: velocities follow the projected positions (no downward speed left)
    on_floor = free & (x[:, 1] < floor + 1e-6)
    assert on_floor.any() and np.all(v[on_floor, 1] > -0.05)


def test_scene_runs_captured_and_stays_plausible():
    model = hanging_model(res=8)
    solver = make_solver("pbd", model)
    assert solver.capturable and solver.default_substeps == 64
    stats = Scene(model, solver, frames=5).run(None, quiet=True)
    assert stats.captured and stats.substeps == 64
    assert stats.max_strain < 0.05


def test_bad_options_raise():
    model = hanging_model(res=4)
    for kw in (dict(iterations=0), dict(iterations=2.5), dict(compliance=-1.0),
               dict(compliance="soft"), dict(relaxation=-0.1), dict(relaxation=math.nan),
               dict(bending_compliance=math.inf)):
        with pytest.raises(ValueError):
            PositionBased(model, **kw)
    with pytest.raises(ValueError):
        make_solver("pbd", model, iteration=3)
    with pytest.raises(ValueError):
        PositionBased(model).step(model.state(), 0.0)


def test_cli_runs_pbd(tmp_usd):
    from warp_cloth.cli import main

    assert main(["run", "hanging", "--solver", "pbd", "--iterations", "4", "--gauss-seidel",
                 "--compliance", "0.001", "--res", "6", "--frames", "3", "--substeps", "8",
                 "--quiet", "--out", tmp_usd]) == 0
    import os

    assert os.path.getsize(tmp_usd) > 0
    assert main(["run", "hanging", "--solver", "pbd", "--no-tethers", "--res", "4", "--frames",
                 "2", "--substeps", "2", "--quiet", "--out", tmp_usd]) == 0
    with pytest.raises(SystemExit) as e:
        main(["run", "hanging", "--no-tethers", "--res", "4", "--frames", "2", "--quiet"])
    assert e.value.code == 2


def test_cli_compliance_takes_springs_and_none(tmp_usd, capsys):
    """``--compliance springs`` (each spring's 1/k) and ``none`` (plain PBD, also where the
    twist would give PBD the springs' compliance); anything else is a usage error."""
    import json

    from warp_cloth.cli import main

    for val, method in (("springs", "compliance springs"), ("0.002", "compliance 0.002 m/N")):
        assert main(["run", "hanging", "--solver", "pbd", "--compliance", val, "--res", "4",
                     "--frames", "2", "--substeps", "2", "--quiet", "--json", "--out",
                     tmp_usd]) == 0
        assert method in json.loads(capsys.readouterr().out)["method"]
    assert main(["run", "twist", "--solver", "pbd", "--compliance", "none", "--res", "4",
                 "--frames", "2", "--substeps", "2", "--quiet", "--json", "--out", tmp_usd]) == 0
    assert "compliance" not in json.loads(capsys.readouterr().out)["method"]
    with pytest.raises(SystemExit) as e:
        main(["run", "hanging", "--solver", "pbd", "--compliance", "stiff", "--res", "4",
              "--frames", "2", "--quiet", "--out", tmp_usd])
    assert e.value.code == 2
    assert "'springs' or 'none'" in capsys.readouterr().err


def test_cli_over_relaxation(tmp_usd, capsys):
    import json

    from warp_cloth.cli import main

    assert main(["run", "hanging", "--solver", "pbd", "--over-relaxation", "1.2", "--res", "4",
                 "--frames", "2", "--substeps", "2", "--quiet", "--json", "--out",
                 tmp_usd]) == 0
    assert json.loads(capsys.readouterr().out)["method"].startswith("pbd (jacobi x1.2, ")
    for bad in (["--over-relaxation", "2.5"], ["--over-relaxation", "1.2", "--gauss-seidel"]):
        with pytest.raises(SystemExit) as e:
            main(["run", "hanging", "--solver", "pbd", *bad, "--res", "4", "--frames", "2",
                  "--quiet", "--out", tmp_usd + ".bad.usd"])
        assert e.value.code == 2
        assert "over_relaxation" in capsys.readouterr().err


def test_spring_of_zero_stiffness_is_no_constraint():
    """A spring of stiffness 0 exerts nothing: PBD must not turn it into a rigid link (issue 14)."""
    from warp_cloth import ClothModel, TriMesh

    mesh = TriMesh.grid(1, 1, size=0.1, plane="xz")
    model = ClothModel(mesh, stretch_stiffness=0.0, gravity=(0.0, 0.0, 0.0),
                       velocity=[[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 0], [0, 0, 0]])
    solver = PositionBased(model)
    assert solver.num_constraints == 0
    st = model.state()
    for _ in range(10):
        solver.step(st, 0.01)
    x = st.positions()
    np.testing.assert_allclose(x[0] - mesh.vertices[0], [0.1, 0, 0], atol=1e-5)
    np.testing.assert_allclose(x[1] - mesh.vertices[1], [-0.1, 0, 0], atol=1e-5)


def _static_equilibrium(model, gravity):
    """Exact static equilibrium of the model's springs under ``gravity`` (Newton on the host,
    in the plane z = 0, which holds by symmetry for a planar xy mesh)."""
    x = model.mesh.vertices.astype(np.float64).copy()
    n = len(x)
    mass = model.mass.numpy().astype(np.float64)
    dof = np.repeat(model.inverse_masses > 0, 3) & np.tile([True, True, False], n)
    for _ in range(50):
        f = mass[:, None] * np.asarray(gravity, dtype=np.float64)[None, :]
        H = np.zeros((3 * n, 3 * n))
        for (i, j), k, L in zip(model.spring_pairs, model.spring_stiffness, model.spring_rest):
            d = x[i] - x[j]
            l = np.linalg.norm(d)
            u = d / l
            f[i] -= k * (l - L) * u
            f[j] += k * (l - L) * u
            P = np.outer(u, u)
            B = k * P + k * (1 - L / l) * (np.eye(3) - P)
            for a, b, s in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
                H[3 * a:3 * a + 3, 3 * b:3 * b + 3] += s * B
        dx = np.linalg.solve(H[np.ix_(dof, dof)], f.reshape(-1)[dof])
        flat = x.reshape(-1)
        flat[dof] += dx
        x = flat.reshape(-1, 3)
        if np.abs(dx).max() < 1e-13:
            break
    return x


@pytest.mark.parametrize("gs,its", [(False, 40), (True, 10)])
def test_xpbd_springs_settle_at_the_exact_equilibrium_jacobi_and_gauss_seidel(gs, its):
    """Issue 14: XPBD with compliance 1/k on a one-cell strip hanging from its top edge settles
    at the exact static equilibrium of the springs, with Jacobi as with Gauss-Seidel (Jacobi's
    per-vertex averaging used to scale the multipliers and settled 5 % too soft: 1.4 mm off
    here). The damping factor exp(-c dt) multiplies the gravity increment, hence g_eff."""
    mesh = TriMesh.grid(1, 1, size=0.1, plane="xy", origin=(0.0, -0.1, 0.0))
    c, dt = 5.0, 1.0 / 120
    model = ClothModel(mesh, density=15.0, stretch_stiffness=10.0, pins=[2, 3], damping=c)
    assert np.allclose(mesh.vertices[[2, 3], 1], 0.0)  # the top edge is pinned
    exact = _static_equilibrium(model, (0.0, -9.81 * math.exp(-c * dt), 0.0))
    assert -exact[:, 1].min() - 0.1 > 0.03  # a 30 % stretch: the bias would show
    solver = PositionBased(model, iterations=its, compliance="springs", gauss_seidel=gs)
    state = model.state()
    for _ in range(int(4.0 / dt)):
        solver.step(state, dt)
    assert np.abs(state.positions() - exact).max() < 2e-4


# ---------------------------------------------------------------------- long-range attachments
def test_tether_distances_are_geodesic_and_k_nearest():
    """On a flat sheet the geodesic distance is the straight one: the tethers' rest lengths equal
    it (within 0.2 %, never shorter); every free vertex gets its k nearest pins, nearest first;
    a vertex no pin reaches (another component) gets none."""
    from warp_cloth.solvers.pbd import tether_anchors

    mesh = TriMesh.grid(8, 8, size=1.0, plane="xz")
    x = mesh.vertices
    pins = np.array([0, 8, 80])
    a, d = tether_anchors(x, mesh.triangles, pins, 2)
    free = np.setdiff1d(np.arange(len(x)), pins)
    assert np.all(a[pins] == -1) and np.all(a[free] >= 0)
    eu = np.linalg.norm(x[free, None] - x[a[free]], axis=2)
    assert np.all(d[free] >= eu * (1 - 1e-12)) and np.all(d[free] <= eu * 1.002)
    assert np.all(d[free, 0] <= d[free, 1])
    allp = np.linalg.norm(x[free, None] - x[pins][None], axis=2)
    np.testing.assert_allclose(d[free], np.sort(allp, axis=1)[:, :2], rtol=2e-3)
    # two disjoint triangles, a pin in the first: the second is unreachable
    xs = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 0, 0], [6, 0, 0], [5, 1, 0.0]])
    a2, d2 = tether_anchors(xs, np.array([[0, 1, 2], [3, 4, 5]]), [0], 1)
    assert a2[:, 0].tolist() == [-1, 0, 0, -1, -1, -1] and np.isinf(d2[3:]).all()


def test_tether_search_kernel_matches_the_python_reference():
    """The one-thread Warp Dijkstra (`tether_anchors`) against the plain Python one it replaced
    (`_tether_anchors_py`), on a curved, irregular mesh with many pins, for k = 1, 2, 3: the
    same anchors in the same order and the same distances (to float64 rounding), also when its
    heap starts too small and has to grow; and a model's tethers are searched once for PBD and
    its stretch guard together."""
    from warp_cloth import tethers

    rng = np.random.default_rng(5)
    mesh = TriMesh.grid(11, 9, size=1.0, plane="xz")
    x = mesh.vertices.copy()
    x[:, 1] = 0.2 * np.sin(3 * x[:, 0]) * np.cos(2 * x[:, 2])  # curved: fast-marching paths
    x[:, [0, 2]] += rng.uniform(-0.02, 0.02, (len(x), 2))     # irregular triangles
    pins = np.array([0, 5, 11, 40, 107, 119])
    for k in (1, 2, 3):
        a, d = tethers.tether_anchors(x, mesh.triangles, pins, k)
        a2, d2 = tethers._tether_anchors_py(x, mesh.triangles, pins, k)
        np.testing.assert_array_equal(a, a2)
        np.testing.assert_allclose(d, d2, rtol=1e-12)
    a3, d3 = tethers.tether_anchors(x, mesh.triangles, pins, 3, heap=8)
    np.testing.assert_array_equal(a3, a)
    np.testing.assert_allclose(d3, d, rtol=1e-12)

    calls = []
    orig = tethers.tether_anchors

    def counting(*args, **kw):
        calls.append(1)
        return orig(*args, **kw)

    model = ClothModel(TriMesh.grid(6, 6, size=1.0, plane="xz"), pins=[0, 6])
    try:
        tethers.tether_anchors = counting
        solver = make_solver("pbd", model)
    finally:
        tethers.tether_anchors = orig
    assert len(calls) == 1 and solver.num_tethers > 0


def test_tethers_are_unilateral_and_anchor_at_the_pins_current_position():
    """Tethers alone (no springs): a vertex nearer its pin than the rest length does not move; one
    farther is put on the sphere about the pin, along the line to it; pins that move carry it."""
    mesh = TriMesh.grid(2, 2, size=1.0, plane="xz")
    model = ClothModel(mesh, stretch_stiffness=0.0, pins=[0, 2])
    s = PositionBased(model)
    assert s.num_constraints == 0 and s.tethers and s.num_tethers == 2 * 7
    x0 = mesh.vertices.astype(np.float64)
    near = x0.copy()
    mid = 0.5 * (x0[0] + x0[2])
    near[3:] = mid + 0.7 * (x0[3:] - mid)  # pulled towards the pins' midpoint: nearer both
    x = arr(near)
    s.project(x)
    np.testing.assert_allclose(x.numpy(), near, atol=1e-6)
    far = x0.copy()
    far[8] = x0[8] + [0.0, -3.0, 0.0]  # the far corner, 3 m below
    x = arr(far)
    s.project(x)
    got = x.numpy().astype(np.float64)
    ratio = [np.linalg.norm(got[8] - got[s.tether_anchor_indices[8, t]]) / s.tether_rest[8, t]
             for t in range(2)]
    assert max(ratio) == pytest.approx(1.0, rel=1e-5)  # held by its tethers, no farther
    np.testing.assert_allclose(got[:8], far[:8], atol=1e-6)  # the others were within theirs
    # moving pins: both lifted by 2 m; a free-falling cloth stays within its tethers of them
    path = PinPath([0.0, 0.5], np.stack([x0[[0, 2]], x0[[0, 2]] + [0.0, 2.0, 0.0]]))
    model = ClothModel(mesh, stretch_stiffness=0.0, pins=[0, 2], pin_path=path)
    s = PositionBased(model)
    st = model.state()
    for _ in range(60):
        s.step(st, 1.0 / 60)
    xf = st.positions()
    np.testing.assert_allclose(xf[[0, 2], 1], 2.0, atol=1e-5)
    for v in range(9):
        for t in range(2):
            p = s.tether_anchor_indices[v, t]
            if p >= 0:
                # 1 %: the vertex between the two pins sits where its two spheres just touch,
                # which alternating projections approach slowly
                assert np.linalg.norm(xf[v] - xf[p]) <= s.tether_rest[v, t] * 1.01
    assert xf[:, 1].min() > 2.0 - 1.01 * np.sqrt(2.0)  # carried up (free fall: -4.9 m)


@pytest.mark.parametrize("gs,bound", [(False, 0.25), (True, 0.08)])
def test_pbd_one_substep_hanging_cloth_stays_bounded_with_tethers(gs, bound):
    """Issue 14: plain PBD at one substep per 60 fps frame and 10 iterations (12x12 hanging
    cloth, 1 s): with the default tethers the stretch stays bounded (Jacobi 16 %, Gauss-Seidel
    4.6 % measured) and nothing falls below the length of cloth that holds it; without them
    Jacobi stretches 198 % and Gauss-Seidel 58 %."""
    from warp_cloth.scenes import hanging

    out = {}
    for tethers in (None, False):
        scene = hanging(res=12, solver="pbd", substeps=1, frames=60, strain_bound=1e9,
                        solver_options=dict(iterations=10, gauss_seidel=gs, tethers=tethers,
                                            max_stretch=None),  # tethers alone
                        device="cpu")
        assert scene.solver.tethers == (tethers is None)
        out[tethers] = scene.run(None, quiet=True, energy=False)
    on, off = out[None], out[False]
    assert on.max_strain < bound and on.min_height > -2e-3
    assert off.max_strain > 2 * bound


def test_tethers_follow_pins_that_move_apart():
    """Pins that stretch the cloth (a 10-cell strip, its right end pulled 0.1 m to the right
    over 0.1 s): the tethers of the vertices tied to opposite ends scale with the pins' own
    stretch (`PinStretch`), so the strip stretches evenly (10 % every edge along it) instead of
    the tethers putting the whole 0.1 m into the middle cell (100 % there)."""
    from warp_cloth.tethers import PinStretch

    mesh = TriMesh.grid(10, 1, size=(1.0, 0.1), plane="xz")
    x0 = mesh.vertices.astype(np.float64)
    left = np.flatnonzero(np.isclose(x0[:, 0], x0[:, 0].min()))
    right = np.flatnonzero(np.isclose(x0[:, 0], x0[:, 0].max()))
    pins = np.concatenate([left, right])
    p0 = x0[pins]
    p1 = p0 + np.where(np.isin(pins, right)[:, None], [0.1, 0.0, 0.0], 0.0)
    model = ClothModel(mesh, pins=pins, pin_path=PinPath([0.0, 0.1], np.stack([p0, p1])),
                       gravity=(0.0, 0.0, 0.0), damping=2.0)
    assert PinStretch(model).moving
    s = PositionBased(model, iterations=10)
    assert s.tethers
    st = model.state()
    for _ in range(60):
        s.step(st, 1.0 / 60)
    assert s._pin_stretch.scale.numpy()[0] == pytest.approx(1.1, rel=1e-4)
    strain = edge_strains(model, st.positions())
    assert strain.max() < 0.15, strain.max()
    # static pins: the ratio from the initial positions, 1 at rest
    assert PinStretch(ClothModel(mesh, pins=pins)).scale.numpy()[0] == pytest.approx(1.0)


@pytest.mark.parametrize("gs", [False, True])
@pytest.mark.parametrize("substeps", [1, 2, 4])
def test_pbd_stretch_guard_bounds_the_default_hanging_cloth_at_any_substeps(gs, substeps):
    """Issue 14: PBD at 1, 2 and 4 substeps of 10 iterations on the default hanging scene
    (32 x 32, 2 s): at most 10 % stretch, no divergence. The tethers alone leave 66 / 29 / 13 %
    (Jacobi) and 23 / 11 / 3.9 % (Gauss-Seidel): the default stretch guard (a strain limit to
    8 %, run only where the iterations left more) holds it, and reports no short step."""
    from warp_cloth.scenes import hanging

    scene = hanging(solver="pbd", substeps=substeps,
                    solver_options=dict(iterations=10, gauss_seidel=gs), device="cpu")
    assert scene.solver.stretch_guard is not None
    st = scene.run(None, quiet=True, energy=False)
    assert st.max_strain <= 0.08 + 1.5e-3 and not st.short_frames
    if substeps == 1 and not gs:  # the same run without the guard goes far past it
        scene = hanging(solver="pbd", substeps=1, frames=60,
                        solver_options=dict(iterations=10, max_stretch=None), device="cpu")
        assert scene.solver.stretch_guard is None
        assert scene.run(None, quiet=True, energy=False).max_strain > 0.2


def test_pbd_stretch_guard_options():
    from warp_cloth.collision import CollisionStage  # noqa: F401

    model = hanging_model(res=4)
    assert PositionBased(model).max_stretch == pytest.approx(0.08)
    assert PositionBased(model, compliance=1e-6).stretch_guard is None  # XPBD stretches
    assert PositionBased(model, max_stretch=None).stretch_guard is None
    assert "stretch <= 5 %" in PositionBased(model, max_stretch=0.05).describe()
    for bad in (0.0, -1.0, float("nan"), "much"):
        with pytest.raises(ValueError, match="max_stretch"):
            PositionBased(model, max_stretch=bad)


@pytest.mark.parametrize("bending", ["quadratic", "dihedral"])
def test_stiff_bending_on_small_cells_stays_bounded(bending):
    """Bending is an explicit force in PBD's prediction; on 2 mm cells (bend stiffness 1e-4 N m)
    it is far stiffer than a 1/3840 s step resolves (without the scaled mass a sheet on a sphere
    reached 5,000 m/s, dihedral 5e5 m/s and 1,100 % strain within 10 frames). With
    ``w / (1 + dt^2 K w)`` a weightless, damped sheet started with a 0.2 mm ripple on its flat
    rest shape rings (its bending energy, about 4e-4 J on 6e-5 kg, gives explicit Euler speeds of
    several m/s) but never grows."""
    mesh = TriMesh.grid(10, 10, size=0.02, plane="xz")
    model = ClothModel(mesh, density=0.15, stretch_stiffness=1000.0, bending=bending,
                       bend_stiffness=1e-4, gravity=(0.0, 0.0, 0.0), damping=5.0)
    solver = make_solver("pbd", model)
    state = model.state()
    x = state.x.numpy()
    x[:, 1] += np.random.default_rng(3).uniform(-2e-4, 2e-4, len(x))
    state.x.assign(x)
    dt = 1.0 / (60 * 64)
    speeds = []
    for _ in range(30):
        for _ in range(64):
            solver.step(state, dt)
        speeds.append(float(np.abs(state.v.numpy()).max()))
    assert solver.stats["force_mass_scale"] > 100.0  # the regime the scaling is for
    assert solver.stats["force_scaled_vertices"] == model.num_vertices
    assert np.all(np.isfinite(speeds)) and max(speeds) < 1.0, speeds
    assert max(speeds[20:]) < 2.0 * max(speeds[:10]), speeds  # no growth


def test_stiff_bending_scale_is_reported_once_and_absent_without_bending():
    mesh = TriMesh.grid(6, 6, size=0.012, plane="xz")
    model = ClothModel(mesh, density=0.15, bending="quadratic", bend_stiffness=1e-4)
    solver = make_solver("pbd", model)
    state = model.state()
    solver.step(state, 1.0 / 960.0)
    first = solver.frame_end()
    assert len(first) == 1 and "bending" in first[0] and "divided by" in first[0]
    solver.step(state, 1.0 / 960.0)
    assert solver.frame_end() == []
    plain = make_solver("pbd", ClothModel(mesh, density=0.15))
    plain.step(plain.model.state(), 1.0 / 960.0)
    assert plain.stats["force_mass_scale"] == 1.0 and plain.stats["force_scaled_vertices"] == 0
    assert plain.frame_end() == []


# ---------------------------------------------------------------------- momentum of the blend
@pytest.mark.parametrize("omega", [None, 1.0])
def test_jacobi_constraint_blend_keeps_momentum_and_the_vertex_blend_does_not(omega):
    """A free 6 x 6 sheet (uneven masses, vertices of 3 to 8 constraints), jittered: the default
    Jacobi blend moves both ends of each constraint by one share of its mass-weighted
    projection, so the projection keeps the linear momentum sum m_i dx_i (to float32 round-off)
    whatever the over-relaxation; the notes' per-vertex average moves them by different
    fractions and does not."""
    mesh = TriMesh.grid(6, 6, size=1.0, plane="xz")
    rng = np.random.default_rng(3)
    masses = rng.uniform(0.5, 2.0, mesh.num_vertices)
    model = ClothModel(mesh, masses=list(masses))
    x0 = perturbed(model, noise=0.03)
    m = np.asarray(masses)[:, None]
    moved = {}
    for blend in ("constraint", "vertex"):
        x = arr(x0)
        PositionBased(model, iterations=3, blend=blend, over_relaxation=omega,
                      tethers=False, max_stretch=None).project(x)
        dx = x.numpy().astype(np.float64) - x0
        moved[blend] = (np.abs(dx).max(), np.linalg.norm((m * dx).sum(0)))
    scale = np.abs(moved["constraint"][0]) * masses.sum()
    assert moved["constraint"][0] > 1e-3  # it did project
    assert moved["constraint"][1] < 1e-5 * scale, moved
    assert moved["vertex"][1] > 1e-2 * scale, moved


def test_the_fold_under_jacobi_pbd_gains_no_energy():
    """The fold's lifted half falling about its hinge (64 substeps x 10 iterations, no
    self-collision): kinetic + gravity + elastic energy never above its start with the default
    blend (the other solvers lose energy there too); the notes' per-vertex blend gained 0.05 J
    on 0.2 J by frame 11."""
    from warp_cloth.diagnostics import Meter
    from warp_cloth.scenes import build_scene

    out = {}
    for blend in ("constraint", "vertex"):
        sc = build_scene("fold", solver="pbd", solver_options={"blend": blend}, frames=12,
                         self_collision=False)
        meter = Meter(sc.model)
        energy = []
        sc.run(None, quiet=True, on_frame=lambda f, st: energy.append(meter(st).energy))
        out[blend] = max(energy[1:]) - energy[0]
    assert out["constraint"] < 1e-4, out
    assert out["vertex"] > 1e-2, out


def test_a_bad_blend_is_refused():
    model = corners_model(n=3)
    with pytest.raises(ValueError, match="blend must be 'constraint' or 'vertex'"):
        PositionBased(model, blend="edge")
