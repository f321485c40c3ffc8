"""Inner linear solvers (Jacobi, Chebyshev-Jacobi, CG) against a dense NumPy solve."""

import numpy as np
import pytest
import warp as wp

from warp_cloth.scenes import hanging_model
from warp_cloth.solvers.linear import (
    SpringSystemOperator, dense_matrix, estimate_spectral_radius, make_linear_solver)


@pytest.fixture(scope="module")
def system():
    m = hanging_model(res=6, device="cpu")
    A = SpringSystemOperator(m, mass_scale=3600.0)
    A.fill_laplacian()
    A.update()
    free = m.inverse_masses > 0
    rng = np.random.default_rng(0)
    b = rng.standard_normal((m.num_vertices, 3))
    b[~free] = 0.0
    D = dense_matrix(A)
    f3 = np.repeat(free, 3)
    xs = np.zeros(3 * m.num_vertices)
    xs[f3] = np.linalg.solve(D[np.ix_(f3, f3)], b.reshape(-1)[f3])
    return m, A, b, xs.reshape(-1, 3), D


def test_operator_is_symmetric_and_matches_laplacian(system):
    m, A, b, xs, D = system
    assert np.allclose(D, D.T, atol=1e-3)
    # row sums of the Laplacian part vanish: A 1 = M/dt^2 1
    ones = np.ones(3 * m.num_vertices)
    assert np.allclose(D @ ones, 3600.0 * np.repeat(m.masses, 3), rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("name", ["jacobi", "chebyshev", "cg"])
def test_solvers_match_dense_solve(system, name):
    m, A, b, xs, _ = system
    opts = {"rho": estimate_spectral_radius(A)} if name == "chebyshev" else {}
    s = make_linear_solver(name, iterations=3000, tolerance=1e-5, **opts)
    x = wp.zeros(m.num_vertices, dtype=wp.vec3)
    info = s.solve(A, wp.array(b, dtype=wp.vec3), x)
    assert info["converged"]
    err = np.abs(x.numpy() - xs).max() / np.abs(xs).max()
    assert err < 1e-3
    # pinned vertices are eliminated: their entries never change
    assert np.all(x.numpy()[m.pins] == 0.0)


def test_chebyshev_needs_fewer_iterations_than_jacobi(system):
    m, A, b, _, _ = system
    rho = estimate_spectral_radius(A)
    assert 0.5 < rho < 1.0
    its = {}
    for name, opts in (("jacobi", {}), ("chebyshev", {"rho": rho})):
        x = wp.zeros(m.num_vertices, dtype=wp.vec3)
        its[name] = make_linear_solver(name, iterations=3000, tolerance=1e-4, **opts).solve(
            A, wp.array(b, dtype=wp.vec3), x)["iterations"]
    assert its["chebyshev"] * 5 <= its["jacobi"]


def test_chebyshev_overestimated_rho_falls_back(system):
    m, A, b, xs, _ = system
    # alpha = 1.9 makes the Jacobi iteration diverge-prone; rho = 0.9999 overshoots badly
    s = make_linear_solver("chebyshev", iterations=400, tolerance=1e-4, rho=0.9999, delay=0,
                           check_every=5)
    x = wp.zeros(m.num_vertices, dtype=wp.vec3)
    info = s.solve(A, wp.array(b, dtype=wp.vec3), x)
    assert np.all(np.isfinite(x.numpy()))
    assert info["residual"] < 1.0  # never worse than the start


def test_fixed_iterations_read_nothing_back(system):
    m, A, b, _, _ = system
    s = make_linear_solver("cg", iterations=10, tolerance=None)
    assert s.capturable
    x = wp.zeros(m.num_vertices, dtype=wp.vec3)
    bb = wp.array(b, dtype=wp.vec3)
    with wp.ScopedCapture(device="cpu") as cap:
        s.solve(A, bb, x)
    wp.capture_launch(cap.graph)
    x2 = wp.zeros(m.num_vertices, dtype=wp.vec3)
    s.solve(A, bb, x2)
    assert np.allclose(x.numpy(), x2.numpy())


def test_bad_options():
    with pytest.raises(ValueError, match="rho"):
        make_linear_solver("chebyshev", rho=1.2)
    with pytest.raises(ValueError, match="unknown linear solver"):
        make_linear_solver("gmres")
    with pytest.raises(ValueError, match="iterations"):
        make_linear_solver("cg", iterations=0)


def test_compact_operator_equals_dense_blocks():
    """Compact blocks (g g^T + beta I, gathered per vertex) equal the dense assembly of the
    3x3 spring blocks, with rank-one parts (random g) as the implicit solver writes them."""
    m = hanging_model(res=5, device="cpu")
    A = SpringSystemOperator(m, mass_scale=900.0)
    rng = np.random.default_rng(1)
    coef = rng.standard_normal((2 * A.num_springs, 4)).astype(np.float32)
    slots = A.slots.numpy()
    coef[slots[:, 1]] = coef[slots[:, 0]]  # both ends hold the same block
    coef[:, 3] = np.abs(coef[:, 3])
    A.coef.assign(coef)
    A.update()
    H = A.spring_blocks().astype(np.float64)
    g, beta = coef[slots[:, 0], :3].astype(np.float64), coef[slots[:, 0], 3].astype(np.float64)
    assert np.allclose(H, g[:, :, None] * g[:, None, :] + beta[:, None, None] * np.eye(3), atol=1e-5)
    n = m.num_vertices
    ref = np.zeros((3 * n, 3 * n))
    for i in range(n):
        ref[3 * i:3 * i + 3, 3 * i:3 * i + 3] = 900.0 * m.masses[i] * np.eye(3)
    for (i, j), h in zip(m.spring_pairs, H):
        for a, b_, s in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
            ref[3 * a:3 * a + 3, 3 * b_:3 * b_ + 3] += s * h
    D = dense_matrix(A)
    assert np.allclose(D, ref, rtol=1e-5, atol=1e-4 * np.abs(ref).max())
    # diagonal blocks and their inverses (zero for pins)
    free = m.inverse_masses > 0
    for i in range(n):
        blk = ref[3 * i:3 * i + 3, 3 * i:3 * i + 3]
        assert np.allclose(A.diag.numpy()[i], blk, rtol=1e-5, atol=1e-4)
        want = np.linalg.inv(blk) if free[i] else np.zeros((3, 3))
        assert np.allclose(A.diag_inv.numpy()[i], want, rtol=1e-3, atol=1e-6 * np.abs(want).max())


def test_cg_fused_and_generic_paths_agree(system):
    """CG's fused direction+matvec launch gives the same iterates as the generic path
    (operator matvec, then the direction kernel) used when extra terms are present."""
    m, A, b, xs, _ = system

    class Generic:  # same operator, no cg_direction: forces the generic path
        n, device, free, diag_inv = A.n, A.device, A.free, A.diag_inv

        def matvec(self, x, out):
            A.matvec(x, out)

    bb = wp.array(b, dtype=wp.vec3)
    out = []
    for op in (A, Generic()):
        x = wp.zeros(m.num_vertices, dtype=wp.vec3)
        info = make_linear_solver("cg", iterations=400, tolerance=1e-5).solve(op, bb, x)
        out.append((info["iterations"], x.numpy()))
    assert out[0][0] == out[1][0]
    assert np.allclose(out[0][1], out[1][1], atol=1e-6 * np.abs(xs).max())
    assert np.abs(out[0][1] - xs).max() < 1e-3 * np.abs(xs).max()


@pytest.mark.parametrize("name", ["jacobi", "cg"])
def test_strided_sums_do_not_depend_on_the_thread_count(system, monkeypatch, name):
    """The solvers' per-vertex kernels stride over the vertices and add each thread's float64
    sums once (`util.stride_threads`: one thread on the CPU, one per vertex elsewhere). Run
    with one thread per vertex, as on a GPU, they give the same iterates and residuals: every
    vertex is visited once, whatever the thread count (a thread that skipped or repeated one
    would change the solution or its residual)."""
    import warp_cloth.solvers.linear as lin

    m, A, b, xs, _ = system
    bb = wp.array(b, dtype=wp.vec3)
    out = []
    for per_vertex in (False, True):
        if per_vertex:
            monkeypatch.setattr(lin, "stride_threads", lambda n, device: int(n))
        op = SpringSystemOperator(m, mass_scale=3600.0)
        op.fill_laplacian()
        op.update()
        assert op.threads == (m.num_vertices if per_vertex else 1)
        x = wp.zeros(m.num_vertices, dtype=wp.vec3)
        info = make_linear_solver(name, iterations=60, tolerance=1e-12, check_every=10).solve(
            op, bb, x)
        out.append((info["residual"], x.numpy()))
    assert out[0][0] == pytest.approx(out[1][0], rel=1e-5)
    assert np.allclose(out[0][1], out[1][1], atol=1e-6 * np.abs(xs).max())
    assert out[0][0] < 0.5  # the iterations did reduce the residual


def test_folded_constant_term_equals_its_own_product():
    """A constant-Hessian term (quadratic bending) is folded into the operator's scalar rows:
    the operator equals springs + mass + ``dense_q (x) I_3``, its diagonal holds the term's
    diagonal, and CG runs the fused two-launch path (no extra term left) to the dense solution."""
    from warp_cloth.forces.bending import QuadraticBending

    m = hanging_model(res=5, bending="quadratic", bend_stiffness=0.05, device="cpu")
    term = next(t for t in m.force_terms if isinstance(t, QuadraticBending))
    A = SpringSystemOperator(m, mass_scale=900.0, extra=[term])
    assert A.folded == [term] and A.extra == []
    A.fill_laplacian()
    A.update()
    n = m.num_vertices
    ref = np.kron(np.diag(900.0 * m.masses) + term.dense_q(), np.eye(3))
    for (i, j), k in zip(m.spring_pairs, m.spring_stiffness):
        for a, b_, s in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
            ref[3 * a:3 * a + 3, 3 * b_:3 * b_ + 3] += s * k * np.eye(3)
    D = dense_matrix(A)
    assert np.abs(term.dense_q()).max() > 1e-2 * np.abs(ref).max()  # the term matters here
    assert np.allclose(D, ref, rtol=1e-5, atol=1e-5 * np.abs(ref).max())
    for i in range(n):
        assert np.allclose(A.diag.numpy()[i], ref[3 * i:3 * i + 3, 3 * i:3 * i + 3], rtol=1e-5)
    free = m.inverse_masses > 0
    f3 = np.repeat(free, 3)
    b = np.random.default_rng(2).standard_normal((n, 3)) * free[:, None]
    xs = np.zeros(3 * n)
    xs[f3] = np.linalg.solve(ref[np.ix_(f3, f3)], b.reshape(-1)[f3])
    x = wp.zeros(n, dtype=wp.vec3)
    info = make_linear_solver("cg", iterations=500, tolerance=1e-6).solve(
        A, wp.array(b, dtype=wp.vec3), x)
    assert info["converged"]
    assert np.abs(x.numpy().reshape(-1) - xs).max() < 1e-3 * np.abs(xs).max()


def test_cg_translation_correction_leaves_no_net_residual_force(system):
    """CG stopped after 2 iterations, then the translation correction (the operator's
    ``translation_gate`` non-zero): the residual ``b - A x`` sums to zero over the free vertices
    (no net force left), and the error in the energy norm is no larger than CG's alone (a
    Galerkin correction). With the gate at zero the solve is CG's alone, bit for bit."""
    m, A, b, xs, D = system
    free = m.inverse_masses > 0
    f3 = np.repeat(free, 3)
    bw = wp.array(b, dtype=wp.vec3)

    def solve(gate):
        if gate is not None:
            A.translation_gate = wp.array([gate], dtype=int)
        try:
            x = wp.zeros(m.num_vertices, dtype=wp.vec3)
            make_linear_solver("cg", iterations=2, tolerance=None).solve(A, bw, x)
        finally:
            A.__dict__.pop("translation_gate", None)
        return x.numpy().astype(float)

    def energy_error(x):
        e = (x - xs).reshape(-1)[f3]
        return float(e @ D[np.ix_(f3, f3)] @ e)

    plain, off, on = solve(None), solve(0), solve(1)
    np.testing.assert_array_equal(off, plain)
    r = (b.reshape(-1) - D @ plain.reshape(-1)).reshape(-1, 3)
    rc = (b.reshape(-1) - D @ on.reshape(-1)).reshape(-1, 3)
    net, net_c = np.abs(r[free].sum(0)).max(), np.abs(rc[free].sum(0)).max()
    assert net > 1e-2 * np.abs(b).sum()  # CG alone leaves a net force
    assert net_c < 1e-5 * np.abs(b).sum()
    assert energy_error(on) <= energy_error(plain)
    assert np.all(on[m.pins] == 0.0)
