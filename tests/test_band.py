"""The banded Cholesky preconditioners (`solvers/band.py`, ``linear="cholesky"``): of implicit
Euler's Newton solve, and of projective dynamics' constant matrix."""

import numpy as np
import pytest
import warp as wp

from warp_cloth.scenes import hanging_model
from warp_cloth.solvers.band import BandFactor, CholeskyCGSolver, band_width, rcm_order
from warp_cloth.solvers.implicit import ImplicitEuler
from warp_cloth.solvers.linear import dense_matrix


def _grid_edges(nx, ny):
    idx = np.arange(nx * ny).reshape(ny, nx)
    e = [np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], 1),
         np.stack([idx[:-1, :].ravel(), idx[1:, :].ravel()], 1),
         np.stack([idx[:-1, :-1].ravel(), idx[1:, 1:].ravel()], 1)]
    return np.concatenate(e)


def test_rcm_finds_a_narrow_band_in_a_shuffled_grid(rng):
    """A 12 x 30 grid graph numbered at random has a bandwidth of about the vertex count; RCM's
    order is a permutation with a band of about one short row (a grid's levels)."""
    nx, ny = 12, 30
    e = _grid_edges(nx, ny)
    shuffle = rng.permutation(nx * ny)
    e = shuffle[e]
    perm = rcm_order(nx * ny, e[:, 0], e[:, 1])
    assert sorted(perm.tolist()) == list(range(nx * ny))
    assert band_width(np.arange(nx * ny), e[:, 0], e[:, 1]) > 100
    assert band_width(perm, e[:, 0], e[:, 1]) <= 2 * (nx + 1)


def test_rcm_orders_every_component():
    """Two disjoint paths: every vertex placed once, each path contiguous (width 1)."""
    e = np.array([[0, 2], [2, 4], [1, 3], [3, 5]])
    perm = rcm_order(6, e[:, 0], e[:, 1])
    assert sorted(perm.tolist()) == list(range(6))
    assert band_width(perm, e[:, 0], e[:, 1]) == 1


def _system(bending="quadratic"):
    model = hanging_model(res=6, stiffness=1e6, bending=bending, bend_stiffness=1e-3)
    state = model.state()
    solver = ImplicitEuler(model, linear="cholesky")
    A, b = solver.newton_system(state, 1 / 30)
    return model, A, b


@pytest.mark.parametrize("bending", ["quadratic", "none"])
def test_one_preconditioned_iteration_solves_the_newton_system(bending):
    """Springs and quadratic bending (folded scalar entries) all lie in the band, so the factor
    is the matrix's: one CG iteration solves the stiff (k dt^2/m ~ 1e8) Newton system to float32
    accuracy, where block-Jacobi CG is still far off after 20."""
    model, A, b = _system(bending)
    D = dense_matrix(A)
    free = np.repeat(model.inverse_masses > 0, 3)
    bn = b.numpy().astype(np.float64).ravel()
    exact = np.zeros_like(bn)
    exact[free] = np.linalg.solve(D[np.ix_(free, free)], bn[free])
    x = wp.zeros_like(b)
    solver = CholeskyCGSolver(iterations=1, tolerance=None)
    solver.solve(A, b, x)
    err = np.abs(x.numpy().ravel() - exact).max() / np.abs(exact).max()
    assert err < 1e-4, err
    assert solver.fallbacks == 0
    from warp_cloth.solvers.linear import CGSolver

    y = wp.zeros_like(b)
    CGSolver(iterations=20, tolerance=None).solve(A, b, y)
    assert np.abs(y.numpy().ravel() - exact).max() / np.abs(exact).max() > 100 * err


def test_an_indefinite_matrix_falls_back_to_block_jacobi_and_is_counted():
    """A non-positive pivot (here one diagonal block made negative) sets the device flag: the
    applications use ``D^-1`` instead (finite result), and each is counted."""
    model, A, b = _system()
    i = int(np.flatnonzero(model.inverse_masses > 0)[0])
    d = A.diag.numpy()
    d[i] = -np.eye(3, dtype=np.float32)
    A.diag.assign(d)
    x = wp.zeros_like(b)
    solver = CholeskyCGSolver(iterations=3, tolerance=None)
    solver.solve(A, b, x)
    assert solver.fallbacks == 3  # the start and two iterations (the last z is never used)
    assert np.all(np.isfinite(x.numpy()))


def test_a_band_too_large_is_refused_with_the_way_out():
    """A mesh whose band would not fit gets a clear error naming linear='cg'."""
    import warp_cloth.solvers.band as band

    model, A, b = _system()
    old = band.MAX_BAND_ENTRIES
    band.MAX_BAND_ENTRIES = 100
    try:
        with pytest.raises(ValueError, match="linear='cg'"):
            BandFactor(A)
    finally:
        band.MAX_BAND_ENTRIES = old


def test_newton_with_the_factor_converges_in_few_inner_iterations():
    """A hanging 6 x 6 sheet at k = 1e3 N/m, one step of 1/30 s: with exact directions Newton
    meets its tolerance, each solve in one or two CG iterations."""
    model = hanging_model(res=6, stiffness=1e3)
    state = model.state()
    solver = ImplicitEuler(model, linear="cholesky", newton_iterations=20)
    for _ in range(3):
        solver.step(state, 1 / 30)
        st = solver.stats
        assert st["residual"] < solver.tolerance, st
        assert st["inner_iterations"] <= 2 * st["newton_iterations"], st


def test_the_stability_map_names_it_and_pd_refuses_an_unknown_inner_solver():
    """``implicit-cholesky`` is a stability-map method (implicit Euler with this inner solve);
    projective dynamics takes ``"cholesky"`` (its own scalar factor) and refuses a name it does
    not know, listing the ones it does."""
    from warp_cloth.bench.stability import split_method
    from warp_cloth.solvers.projective import ProjectiveDynamics

    assert split_method("implicit-cholesky") == ("implicit", {"linear": "cholesky"})
    assert ProjectiveDynamics(hanging_model(res=4), linear="cholesky").linear_name == "cholesky"
    with pytest.raises(ValueError, match="linear must be one of.*cholesky"):
        ProjectiveDynamics(hanging_model(res=4), linear="lu")


# ------------------------------------------------- projective dynamics' constant matrix
def _pd_system(res=6, **kw):
    """The PD operator of a pinned hanging sheet with quadratic bending (folded into the rows)
    at one step of 1/30 s, a random right-hand side on the free vertices, and the exact
    solution from the dense scalar matrix (float64)."""
    from warp_cloth.solvers.projective import ProjectiveDynamics

    model = hanging_model(res=res, stiffness=1e5, bending="quadratic", bend_stiffness=1e-2, **kw)
    pd = ProjectiveDynamics(model).prepare(1 / 30)
    A = pd.operator
    free = model.inverse_masses > 0
    rng = np.random.default_rng(3)
    bh = (rng.standard_normal((model.num_vertices, 3)) * free[:, None]).astype(np.float32)
    S = A.dense_scalar()
    exact = np.zeros((model.num_vertices, 3))
    exact[free] = np.linalg.solve(S[np.ix_(free, free)], bh[free].astype(np.float64))
    return model, pd, A, wp.array(bh, dtype=wp.vec3), exact


def test_pd_scalar_factor_solves_the_constant_matrix_in_one_iteration():
    """Springs, masses and quadratic bending all lie in the scalar band: one preconditioned CG
    iteration solves the global step to float32 accuracy (the three components share the
    factor), where block-Jacobi CG is still far off after 20."""
    from warp_cloth.solvers.linear import CGSolver

    model, pd, A, b, exact = _pd_system()
    x = wp.zeros_like(b)
    solver = CholeskyCGSolver(iterations=1, tolerance=None)
    solver.solve(A, b, x)
    err = np.abs(x.numpy() - exact).max() / np.abs(exact).max()
    assert err < 1e-5, err
    assert solver.fallbacks == 0
    assert solver.factor.width <= 2 * 7  # a 7 x 7 grid in its own order: two rows
    y = wp.zeros_like(b)
    CGSolver(iterations=20, tolerance=None).solve(A, b, y)
    assert np.abs(y.numpy() - exact).max() / np.abs(exact).max() > 100 * err


def test_pd_scalar_factor_keeps_a_shuffled_mesh_narrow():
    """The same sheet with its vertices numbered at random: the factor takes reverse
    Cuthill-McKee's order (band about two rows, not the vertex count) and still solves it."""
    from warp_cloth.model import ClothModel
    from warp_cloth.solvers.projective import ProjectiveDynamics

    base = hanging_model(res=8)
    rng = np.random.default_rng(0)
    perm = rng.permutation(base.num_vertices)  # new vertex k is old vertex perm[k]
    inv = np.argsort(perm)
    mesh = base.mesh.__class__(base.mesh.vertices[perm], inv[base.mesh.triangles])
    model = ClothModel(mesh, density=0.15, stretch_stiffness=1e3, pins=inv[base.pins])
    pd = ProjectiveDynamics(model).prepare(1 / 60)
    A = pd.operator
    free = model.inverse_masses > 0
    bh = (rng.standard_normal((model.num_vertices, 3)) * free[:, None]).astype(np.float32)
    S = A.dense_scalar()
    exact = np.zeros((model.num_vertices, 3))
    exact[free] = np.linalg.solve(S[np.ix_(free, free)], bh[free].astype(np.float64))
    x = wp.zeros(model.num_vertices, dtype=wp.vec3)
    solver = CholeskyCGSolver(iterations=1, tolerance=None)
    solver.solve(A, wp.array(bh, dtype=wp.vec3), x)
    assert solver.factor.width <= 3 * 9, solver.factor.width
    assert np.abs(x.numpy() - exact).max() / np.abs(exact).max() < 1e-5
    assert pd.linear_name == "cholesky" and pd._band_width == solver.factor.width
    # above `RCM_MAX_VERTICES` the default choice takes the mesh's own order (wide here)
    import warp_cloth.solvers.projective as pdm

    old = pdm.RCM_MAX_VERTICES
    pdm.RCM_MAX_VERTICES = 10
    try:
        big = ProjectiveDynamics(model)
        assert big.linear_name == "cholesky" and big._band_width > 2 * solver.factor.width
    finally:
        pdm.RCM_MAX_VERTICES = old


def test_pd_defaults_to_the_factor_without_contact_and_its_step_is_the_direct_one():
    """Without a collision stage PD's default inner solve on the CPU is the factor, one
    iteration: its step is the host dense solve's (``direct=True``) to float32 rounding; with
    a collision stage the default stays CG x 20; a band wider than `CHOLESKY_MAX_WIDTH` gets
    Chebyshev."""
    import warp_cloth.solvers.projective as pdm
    from warp_cloth.collision.stage import CollisionStage

    model = hanging_model(res=6, stiffness=1e4, bending="quadratic", bend_stiffness=1e-2)
    pd = pdm.ProjectiveDynamics(model)
    assert (pd.linear_name, pd.linear_iterations) == ("cholesky", 1)
    ref = pdm.ProjectiveDynamics(model, direct=True)
    a, b = model.state(), model.state()
    for _ in range(5):
        pd.step(a, 1 / 60)
        ref.step(b, 1 / 60)
    moved = np.abs(b.positions() - model.mesh.vertices).max()
    assert moved > 1e-3
    assert np.abs(a.positions() - b.positions()).max() < 1e-5 * max(moved, 1.0)
    assert pd.stats["linear"] == "cholesky" and pd.capturable
    assert pd.linear.factor.width == pd._band_width  # the order the choice found
    staged = pdm.ProjectiveDynamics(model, collision=CollisionStage(model, [],
                                                                    self_collision=True))
    assert (staged.linear_name, staged.linear_iterations) == ("cg", 20)
    old = pdm.CHOLESKY_MAX_WIDTH
    pdm.CHOLESKY_MAX_WIDTH = 3
    try:
        wide = pdm.ProjectiveDynamics(model)
        assert (wide.linear_name, wide.linear_iterations) == ("chebyshev", 20)
    finally:
        pdm.CHOLESKY_MAX_WIDTH = old
    old = pdm.CHOLESKY_MAX_ENTRIES
    pdm.CHOLESKY_MAX_ENTRIES = model.num_vertices * 4  # a band of 3: too many entries
    try:
        assert pdm.ProjectiveDynamics(model).linear_name == "chebyshev"
    finally:
        pdm.CHOLESKY_MAX_ENTRIES = old
    assert pdm.ProjectiveDynamics(model, linear="cholesky", linear_iterations=3
                                  ).linear_iterations == 3


def test_pd_factor_without_a_pivot_falls_back_and_says_so():
    """A constant matrix with a non-positive pivot (one vertex's diagonal made negative before
    the factorisation): the applications fall back to block Jacobi (finite steps), counted in
    the solver's stats and reported by its frame report; nothing silent."""
    from warp_cloth.solvers.projective import ProjectiveDynamics

    model = hanging_model(res=4)
    pd = ProjectiveDynamics(model).prepare(1 / 60)
    i = int(np.flatnonzero(model.inverse_masses > 0)[0])
    pd.operator.laplacian_diag[i] = -1e9  # read by the factor at its first solve
    s = model.state()
    pd.step(s, 1 / 60)
    assert pd.stats["factor_fallbacks"] == 10  # one application a global step
    msgs = pd.frame_end()
    assert any("fell back to block Jacobi" in m for m in msgs), msgs
    assert not any("fell back" in m for m in pd.frame_end())  # said once
    assert np.all(np.isfinite(s.positions()))
    good = ProjectiveDynamics(model)
    good.step(model.state(), 1 / 60)
    assert good.stats["factor_fallbacks"] == 0 and good.frame_end() == []


def test_pd_band_too_large_is_refused_with_the_way_out():
    """``linear="cholesky"`` on a matrix whose band would not fit: a clear error naming
    linear='cg', at the first step, before anything moves."""
    import warp_cloth.solvers.band as band
    from warp_cloth.solvers.projective import ProjectiveDynamics

    model = hanging_model(res=6)
    pd = ProjectiveDynamics(model, linear="cholesky")
    old = band.MAX_BAND_ENTRIES
    band.MAX_BAND_ENTRIES = 10
    try:
        s = model.state()
        with pytest.raises(ValueError, match="linear='cg'"):
            pd.step(s, 1 / 60)
    finally:
        band.MAX_BAND_ENTRIES = old


def test_an_indefinite_newton_matrix_is_reported_by_the_solver():
    """``exact_hessian=True`` on a sheet squeezed to half its size: stiff compressed springs make
    the Newton matrix indefinite, the factorisation fails, and the fall-back to block Jacobi is
    in the solver's stats and its frame report (nothing silent); the step stays finite."""
    model = hanging_model(res=4, stiffness=1e6)
    state = model.state()
    x = model.mesh.vertices.copy()
    free = model.inverse_masses > 0
    x[free] = x[0] + 0.5 * (x[free] - x[0])
    state.x.assign(x.astype(np.float32))
    solver = ImplicitEuler(model, linear="cholesky", exact_hessian=True, newton_iterations=2)
    solver.step(state, 1 / 30)
    assert solver.stats["factor_fallbacks"] > 0
    assert any("fell back to block Jacobi" in m for m in solver.frame_end())
    assert not any("fell back" in m for m in solver.frame_end())  # reported once
    assert np.all(np.isfinite(state.x.numpy()))
    ok = ImplicitEuler(model, linear="cholesky")
    ok.step(model.state(), 1 / 30)
    assert ok.stats["factor_fallbacks"] == 0
    assert not any("fell back" in m for m in ok.frame_end())
