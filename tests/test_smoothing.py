"""The smoothing sweeps after implicit Euler's Newton solve (`warp_cloth.solvers.smoothing`).

F is evaluated here on the host in float64 from the model's own (float32) data: inertia,
external force, springs and the quadratic bending matrix, so the kernel's local energy, gradient
and Hessian are checked against an independent F.
"""

import numpy as np
import pytest
import warp as wp

from warp_cloth.diagnostics import Meter
from warp_cloth.mesh import TriMesh
from warp_cloth.model import ClothModel
from warp_cloth.scenes import hanging
from warp_cloth.solvers.implicit import ImplicitEuler
from warp_cloth.solvers.linear import SpringSystemOperator
from warp_cloth.solvers.smoothing import VertexSmoother, vertex_colors


def _setup(model, x, x_hat, dt):
    """A smoother on ``model``'s springs (and folded quadratic bending), with device copies of
    ``x``, ``disp = x - x_hat`` and ``f_ext = M g``."""
    extra = [t for t in model.force_terms if t.name == "quadratic"]
    A = SpringSystemOperator(model, 1.0 / dt**2, extra=extra)
    sm = VertexSmoother(model, A)
    d = model.device
    xw = wp.array(x.astype(np.float32), dtype=wp.vec3, device=d)
    disp = wp.array((x - x_hat).astype(np.float32), dtype=wp.vec3, device=d)
    fe = (model.masses[:, None] * np.asarray(model.gravity)[None, :]).astype(np.float32)
    f_ext = wp.array(fe, dtype=wp.vec3, device=d)
    return sm, xw, disp, f_ext, wp.ones(1, dtype=int, device=d)


def _F(model, x, x_hat, dt, grad=False):
    """F(x) on the host, float64 (free vertices' inertia and external force; every spring;
    quadratic bending); with ``grad``, also its gradient."""
    x = np.asarray(x, np.float64)
    m = model.masses.astype(np.float32).astype(np.float64)
    free = model.inverse_masses > 0
    g = np.asarray(model.gravity, np.float64)
    u = x - x_hat
    F = np.sum((0.5 / dt**2 * m * np.einsum("ij,ij->i", u, u) - m * (x @ g))[free])
    G = (m / dt**2)[:, None] * u - m[:, None] * g
    p = model.spring_pairs
    k = model.spring_stiffness.astype(np.float32).astype(np.float64)
    rest = model.spring_rest.astype(np.float32).astype(np.float64)
    d = x[p[:, 0]] - x[p[:, 1]]
    ln = np.linalg.norm(d, axis=1)
    F += np.sum(0.5 * k * (ln - rest) ** 2)
    fs = (k * (ln - rest) / ln)[:, None] * d
    np.add.at(G, p[:, 0], fs)
    np.add.at(G, p[:, 1], -fs)
    for t in model.force_terms:
        if t.name == "quadratic":
            Q = t.dense_q()
            F += 0.5 * np.sum(x * (Q @ x))
            G += Q @ x
    G[~free] = 0.0
    return (F, G) if grad else F


def test_vertex_colors_never_join_two_vertices_of_a_colour():
    """Greedy colouring over the springs and the folded bending entries: no spring and no
    bending quad joins two vertices of one colour (so a colour's local steps do not race)."""
    mesh = TriMesh.grid(5, 4, size=(0.5, 0.4))
    model = ClothModel(mesh, bending="quadratic", bend_stiffness=1e-3, device="cpu")
    bend = [t for t in model.force_terms if t.name == "quadratic"]
    A = SpringSystemOperator(model, 1.0, extra=bend)
    col = vertex_colors(model.num_vertices, [A.offsets.numpy(), A.s_offsets.numpy()],
                        [A.other.numpy()[: 2 * A.num_springs], A.s_cols.numpy()])
    p = model.spring_pairs
    assert (col[p[:, 0]] != col[p[:, 1]]).all()
    quads = bend[0].quads_np
    for a in range(4):
        for b in range(a + 1, 4):
            assert (col[quads[:, a]] != col[quads[:, b]]).all()
    assert col.min() == 0 and len(np.unique(col)) == col.max() + 1


def test_vertex_colors_of_a_hub_with_many_neighbours():
    """A hub joined to 70 rim vertices (a fan: more neighbours than the vectorised bitmask
    holds) plus the rim's ring: the host fall-back colours it validly too."""
    n = 71
    pairs = [(0, i) for i in range(1, n)] + [(i, i % (n - 1) + 1) for i in range(1, n)]
    p = np.array(pairs + [(b, a) for a, b in pairs])
    p = p[np.lexsort((p[:, 1], p[:, 0]))]
    offsets = np.searchsorted(p[:, 0], np.arange(n + 1))
    col = vertex_colors(n, [offsets], [p[:, 1]])
    assert (col[p[:, 0]] != col[p[:, 1]]).all() and (col >= 0).all()
    assert len(np.unique(col)) <= 4


def test_one_free_vertex_reaches_the_minimiser_of_its_step():
    """One free vertex on three springs to pinned corners, its inertial target far enough to
    compress one spring (the local Hessian is indefinite there and gets projected): the sweeps
    (each a local Newton step with backtracking) reach the minimiser of F found by a float64
    Newton iteration on the host, and F never rises from one sweep to the next."""
    mesh = TriMesh.grid(1, 1, size=0.1)
    model = ClothModel(mesh, pins=[0, 1, 2], stretch_stiffness=500.0, shear_stiffness=300.0,
                       device="cpu")
    dt = 1.0 / 60.0
    x0 = mesh.vertices.astype(np.float64)
    x_hat = x0.copy()
    x_hat[3] += [-0.06, 0.02, -0.05]  # pulls toward the pinned corners: a spring compresses
    sm, xw, disp, f_ext, on = _setup(model, x_hat, x_hat, dt)
    Fs = [_F(model, x_hat, x_hat, dt)]
    for _ in range(12):
        sm.sweep(xw, disp, f_ext, 1.0 / dt**2, 1, on)
        Fs.append(_F(model, xw.numpy(), x_hat, dt))
    assert all(b <= a + 1e-12 for a, b in zip(Fs, Fs[1:])), Fs
    # the host's minimiser: damped Newton on the one free vertex with a finite-difference Hessian
    y = x_hat.copy()
    for _ in range(60):
        F0, G = _F(model, y, x_hat, dt, grad=True)
        H = np.zeros((3, 3))
        for c in range(3):
            e = np.zeros_like(y)
            e[3, c] = 1e-7
            H[:, c] = (_F(model, y + e, x_hat, dt, grad=True)[1][3]
                       - _F(model, y - e, x_hat, dt, grad=True)[1][3]) / 2e-7
        w, V = np.linalg.eigh(0.5 * (H + H.T))
        step = -(V / np.maximum(w, model.masses[3] / dt**2)) @ (V.T @ G[3])
        a = 1.0
        while _F(model, y + a * np.eye(4)[3][:, None] * step, x_hat, dt) > F0 and a > 1e-6:
            a *= 0.5
        y[3] += a * step
    np.testing.assert_allclose(xw.numpy()[3], y[3], atol=2e-6)
    assert np.linalg.norm(_F(model, y, x_hat, dt, grad=True)[1][3]) < 1e-6
    assert np.array_equal(xw.numpy()[:3], x0[:3].astype(np.float32))  # pins untouched
    np.testing.assert_allclose(disp.numpy(), xw.numpy() - x_hat, atol=1e-7)


def test_sweeps_lower_f_and_converge_to_its_stationary_point():
    """A perturbed 8 x 8 sheet with quadratic bending (folded into the operator): every sweep
    lowers the host's F, and many sweeps reach a point where F's gradient vanishes (up to
    float32 positions): the kernel's energy, gradient and Hessian are F's."""
    mesh = TriMesh.grid(7, 7, size=0.4)
    model = ClothModel(mesh, pins=[0, 7], stretch_stiffness=200.0, shear_stiffness=50.0,
                       bending="quadratic", bend_stiffness=2e-2, device="cpu")
    dt = 1.0 / 60.0
    rng = np.random.default_rng(3)
    x_hat = mesh.vertices.astype(np.float64) + 0.01 * rng.standard_normal((64, 3))
    x_hat[[0, 7]] = mesh.vertices[[0, 7]]
    sm, xw, disp, f_ext, on = _setup(model, x_hat, x_hat, dt)
    Fs = [_F(model, x_hat, x_hat, dt)]
    for _ in range(6):
        sm.sweep(xw, disp, f_ext, 1.0 / dt**2, 1, on)
        Fs.append(_F(model, xw.numpy(), x_hat, dt))
    assert all(b < a for a, b in zip(Fs, Fs[1:])), Fs
    g0 = np.abs(_F(model, x_hat, x_hat, dt, grad=True)[1]).max()
    sm.sweep(xw, disp, f_ext, 1.0 / dt**2, 400, on)
    g = np.abs(_F(model, xw.numpy(), x_hat, dt, grad=True)[1]).max()
    assert g < 2e-3 * g0, (g, g0)


def test_a_step_with_contacts_is_not_smoothed():
    """The device flag: with ``free[0] == 0`` (the step has contact entries) nothing moves."""
    mesh = TriMesh.grid(3, 3, size=0.3)
    model = ClothModel(mesh, pins=[0], device="cpu")
    dt = 1.0 / 60.0
    x_hat = mesh.vertices.astype(np.float64) + [0.0, 0.0, 0.02]
    sm, xw, disp, f_ext, on = _setup(model, x_hat, x_hat, dt)
    on.zero_()
    sm.sweep(xw, disp, f_ext, 1.0 / dt**2, 4, on)
    assert np.array_equal(xw.numpy(), x_hat.astype(np.float32)) and sm.moved.numpy()[0] == 0.0
    on.fill_(1)
    sm.sweep(xw, disp, f_ext, 1.0 / dt**2, 1, on)
    assert sm.moved.numpy()[0] > 0.0


def _max_strain(sweeps=None, substeps=1, newton=None, frames=10):
    opts = {} if sweeps is None else {"smoothing_sweeps": sweeps}
    if newton is not None:
        opts.update(newton)
    sc = hanging(solver="implicit", solver_options=opts, fps=30, frames=frames,
                 substeps=substeps, stiffness=1e6, res=16, self_collision=False)
    meter, st, worst = Meter(sc.model), sc.state, 0.0
    for _ in range(frames):
        for _ in range(substeps):
            sc.solver.step(st, 1.0 / 30 / substeps)
        worst = max(worst, meter(st).max_strain)
    return worst, sc.solver


def test_stiff_light_cloth_at_one_step_a_frame_stretches_like_the_converged_reference():
    """Issue 14's criterion on a 16 x 16 hanging sheet at k = 1e6 N/m, one implicit step a
    frame at 30 fps (8 Newton iterations, CG): max strain over 10 frames within twice the
    converged reference's (steps of 1/1980 s, Newton to 1e-6 m). Newton alone, stopped at its
    cap, leaves edges stretched to 2.5 times the reference (0.035 % against 0.014 %; with the
    sweeps 0.016 %)."""
    ref, _ = _max_strain(0, substeps=66, newton={"tolerance": 1e-6, "newton_iterations": 30})
    smoothed, solver = _max_strain()
    plain, _ = _max_strain(0)
    assert solver.stats["smoothing_sweeps"] == 4 and not solver.stats["converged"]
    assert smoothed <= 2.0 * ref, (smoothed, ref)
    assert plain > 2.0 * ref, (plain, ref)


def test_smoothing_sweeps_option_is_checked():
    from warp_cloth.solvers.projective import ProjectiveDynamics

    model = ClothModel(TriMesh.grid(2, 2), device="cpu")
    for bad in (-1, 1.5, True, "4"):
        with pytest.raises((ValueError, TypeError), match="implicit: smoothing_sweeps"):
            ImplicitEuler(model, smoothing_sweeps=bad)
        with pytest.raises((ValueError, TypeError), match="pd: smoothing_sweeps"):
            ProjectiveDynamics(model, smoothing_sweeps=bad)
    assert ProjectiveDynamics(model).smoothing_sweeps == 0
    assert not ImplicitEuler(model, smoothing_sweeps=0)._smooth_on
    assert ImplicitEuler(model).smoothing_sweeps == 4
    # Baraff-Witkin's single solve stays the notes' step unless sweeps are asked for
    assert not ImplicitEuler(model, newton_iterations=1)._smooth_on
    assert ImplicitEuler(model, newton_iterations=1, smoothing_sweeps=2)._smooth_on


def test_cli_smoothing_sweeps(tmp_usd, capsys):
    """``--smoothing-sweeps N`` reaches the implicit solver (its method string), 0 turns the
    sweeps off, a negative count or another solver is refused."""
    import json

    from warp_cloth.cli import main

    base = ["run", "hanging", "--res", "4", "--frames", "2", "--quiet", "--json"]
    assert main([*base, "--solver", "implicit", "--smoothing-sweeps", "2", "--out",
                 tmp_usd]) == 0
    assert json.loads(capsys.readouterr().out)["method"] == "implicit (8 Newton, cg, 2 sweeps)"
    assert main([*base, "--solver", "implicit", "--smoothing-sweeps", "0", "--out",
                 tmp_usd]) == 0
    assert json.loads(capsys.readouterr().out)["method"] == "implicit (8 Newton, cg)"
    for bad in (["--solver", "implicit", "--smoothing-sweeps", "-1"],
                ["--solver", "pbd", "--smoothing-sweeps", "2"]):
        with pytest.raises(SystemExit) as e:
            main([*base, *bad, "--out", tmp_usd + ".bad.usd"])
        assert e.value.code == 2
        assert "smoothing" in capsys.readouterr().err


def test_cli_linear_iterations(tmp_usd, capsys):
    """``--linear-iterations N`` reaches implicit Euler's and PD's inner solver (the method
    string), with ``--linear`` too; a count below 1 or a solver without an inner solve is
    refused (exit 2, named)."""
    import json

    from warp_cloth.cli import main

    base = ["run", "hanging", "--res", "4", "--frames", "2", "--quiet", "--json",
            "--self-collision", "off"]
    assert main([*base, "--solver", "pd", "--out", tmp_usd]) == 0
    assert json.loads(capsys.readouterr().out)["method"] == "pd (10 iterations, cholesky x1)"
    assert main([*base, "--solver", "pd", "--linear", "cg", "--linear-iterations", "7",
                 "--out", tmp_usd]) == 0
    assert json.loads(capsys.readouterr().out)["method"] == "pd (10 iterations, cg x7)"
    assert main([*base, "--solver", "implicit", "--linear-iterations", "3", "--out",
                 tmp_usd]) == 0
    capsys.readouterr()
    for bad in (["--solver", "pd", "--linear-iterations", "0"],
                ["--solver", "pbd", "--linear-iterations", "2"]):
        with pytest.raises(SystemExit) as e:
            main([*base, *bad, "--out", tmp_usd + ".bad.usd"])
        assert e.value.code == 2
        assert "linear-iterations" in capsys.readouterr().err


def test_projective_dynamics_sweeps_lower_f_and_keep_its_velocity_rule():
    """Projective dynamics ends its iterations with the sweeps too: from the same state, a step
    with them ends at a lower F (host, float64; gravity in PD's y is F's external force) than
    the same step without, and its velocity is again (x1 - x0)/dt times the damping decay."""
    from warp_cloth.scenes import hanging_model
    from warp_cloth.solvers.projective import ProjectiveDynamics

    model = hanging_model(res=10, stiffness=1e4, bending="quadratic", bend_stiffness=1e-3,
                          device="cpu")
    dt = 1.0 / 60.0
    start = model.state()
    warm = ProjectiveDynamics(model, smoothing_sweeps=0)
    for _ in range(6):  # falling and swinging, not at rest
        warm.step(start, dt)
    x0, v0 = start.positions().astype(np.float64), start.velocities().astype(np.float64)
    free = model.inverse_masses > 0
    x_hat = x0 + dt * v0 * free[:, None]
    out = {}
    for sweeps in (0, 4):
        st = model.state()
        st.x.assign(start.x), st.v.assign(start.v)
        pd = ProjectiveDynamics(model, smoothing_sweeps=sweeps)
        pd.step(st, dt)
        out[sweeps] = (st.positions().astype(np.float64), st.velocities(), pd)
    F0, F4 = (_F(model, out[s][0], x_hat, dt) for s in (0, 4))
    assert F4 < F0, (F4, F0)
    x1, v1, pd = out[4]
    decay = np.exp(-model.damping * dt)
    np.testing.assert_allclose(v1[free], ((x1 - x0) / dt * decay)[free], atol=2e-4)
    assert pd.stats["smoothing_sweeps"] == 4 and out[0][2].stats["smoothing_sweeps"] == 0
    assert pd.describe().endswith(", 4 sweeps)")


def test_projective_dynamics_sweeps_only_without_obstacles_and_contacts():
    """PD on the drape (a sphere: obstacles) never sweeps, not even in its first, contact-free
    steps above the sphere (bit for bit the run without sweeps); on a hanging sheet with
    self-collision on and nothing near, its steps sweep."""
    from warp_cloth.contact_scenes import drape

    runs = []
    for sweeps in (4, 0):
        sc = drape(solver="pd", res=8, frames=6, solver_options={"smoothing_sweeps": sweeps})
        sc.run(None, quiet=True, energy=False, progress=False)
        runs.append(sc.state.positions())
        assert sc.solver.stats["smoothing_sweeps"] == 0
    assert np.array_equal(runs[0], runs[1])
    sc = hanging(solver="pd", res=8, frames=3, self_collision=True,
                 solver_options={"smoothing_sweeps": 4})
    assert sc.solver.collision is not None
    sc.run(None, quiet=True, energy=False, progress=False)
    assert sc.solver.stats["smoothing_sweeps"] == 4
