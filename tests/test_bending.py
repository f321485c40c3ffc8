"""Dihedral (Bridson 2003) and quadratic (Bergou 2006) bending: physics.md 2.7, T16-T19.

Float32 kernels are checked against float64 host references. Finite differences use float64
host functions where exactness matters (the dihedral angle); the quadratic energy is exactly
quadratic, so a central difference of the float32 kernel energy has no truncation error and only
rounding (relative tolerance 1e-3 for h = 1e-3 on energies of order 1e-2 J).
"""

import numpy as np
import pytest
import warp as wp

from warp_cloth.forces.bending import DihedralBending, QuadraticBending, dihedral_angles
from warp_cloth.mesh import TriMesh
from warp_cloth.model import ClothModel
from warp_cloth.solvers.linear import dense_matrix


def _model(bending, k=0.01, nx=4, ny=3, curved=False, gravity=(0.0, -9.81, 0.0)):
    mesh = TriMesh.grid(nx, ny, size=(0.4, 0.3), plane="xz")
    if curved:  # roll the sheet onto a cylinder of radius 0.3 m about the z axis
        v = mesh.vertices.copy()
        R = 0.3
        x = v[:, 0]
        v[:, 0], v[:, 1] = R * np.sin(x / R), R * (1 - np.cos(x / R))
        mesh = TriMesh(v, mesh.triangles)
    return ClothModel(mesh, bending=bending, bend_stiffness=k, gravity=gravity, device="cpu")


def _term(model):
    t = model.force_terms[-1]
    assert isinstance(t, (DihedralBending, QuadraticBending))
    return t


def _forces(term, x):
    f = wp.zeros(len(x), dtype=wp.vec3)
    term.eval(wp.array(x, dtype=wp.vec3), None, f)
    return f.numpy().astype(np.float64)


def _energy(term, x):
    out = wp.zeros(1, dtype=float)
    term.energy(wp.array(x, dtype=wp.vec3), out)
    return float(out.numpy()[0])


def _perturbed(model, rng, scale=0.02):
    return model.mesh.vertices + scale * rng.standard_normal(model.mesh.vertices.shape)


@pytest.mark.parametrize("bending", ["dihedral", "quadratic"])
def test_forces_sum_to_zero_and_vanish_at_rest(bending, rng):
    m = _model(bending)
    t = _term(m)
    f = _forces(t, _perturbed(m, rng))
    assert np.abs(f).max() > 1e-3  # a real force ...
    assert np.abs(f.sum(axis=0)).max() < 1e-5 * np.abs(f).max()  # ... that sums to zero (T17)
    assert np.abs(_forces(t, m.mesh.vertices)).max() < 1e-6
    assert abs(_energy(t, m.mesh.vertices)) < 1e-9


def test_dihedral_keeps_a_curved_rest_shape(rng):
    m = _model("dihedral", curved=True)
    t = _term(m)
    assert np.abs(t.rest_theta_np).max() > 0.1  # really curved
    assert np.abs(_forces(t, m.mesh.vertices)).max() < 1e-5  # zero force at the rest angle
    assert abs(_energy(t, m.mesh.vertices)) < 1e-9
    # flattening it costs energy and the force pushes back towards the curved shape
    flat = TriMesh.grid(4, 3, size=(0.4, 0.3), plane="xz").vertices
    assert _energy(t, flat) > 1e-4


def test_quadratic_warns_on_curved_rest_shape():
    with pytest.warns(UserWarning, match="planar rest shape"):
        _model("quadratic", curved=True)


def test_dihedral_u_vectors(rng):
    """T17 on random geometry: u1 || n1, u2 || n2, (u4 - u3) _|_ E, sum u = 0 (from the kernel)."""
    m = _model("dihedral")
    t = _term(m)
    x = _perturbed(m, rng, 0.05)
    f = wp.zeros(m.num_vertices, dtype=wp.vec3)
    t.eval_with_hessian(wp.array(x, dtype=wp.vec3), f)
    g = t.g.numpy().astype(np.float64)  # sqrt(w) * (u1, u2, u3, u4) per quad
    for q, (a, b, c, d) in enumerate(t.quads_np):
        u1, u2, u3, u4 = g[q]
        scale = np.abs(g[q]).max()
        assert scale > 0
        n1 = np.cross(x[c] - x[a], x[c] - x[b])
        n2 = np.cross(x[d] - x[b], x[d] - x[a])
        e = x[b] - x[a]
        assert np.linalg.norm(np.cross(u1, n1)) < 1e-4 * np.linalg.norm(u1) * np.linalg.norm(n1)
        assert np.linalg.norm(np.cross(u2, n2)) < 1e-4 * np.linalg.norm(u2) * np.linalg.norm(n2)
        assert abs(np.dot(u4 - u3, e)) < 1e-4 * scale * np.linalg.norm(e)
        assert np.abs(u1 + u2 + u3 + u4).max() < 1e-4 * scale


def test_dihedral_force_is_restoring_gradient_of_angle(rng):
    """f_i = -k c psi'(theta) d theta/d x_i, with d theta / dx by float64 central differences."""
    m = _model("dihedral", k=0.02)
    t = _term(m)
    x = _perturbed(m, rng, 0.03)
    f = _forces(t, x)
    quads = t.quads_np
    theta = dihedral_angles(x, quads)
    # expected forces from a float64 FD gradient of the host angle function (h = 1e-6, error ~1e-10)
    exp = np.zeros_like(x)
    h = 1e-6
    for q, quad in enumerate(quads):
        a, b, c, d = (x[i] for i in quad)
        n1 = np.linalg.norm(np.cross(c - a, c - b))
        n2 = np.linalg.norm(np.cross(d - b, d - a))
        coef = t.k * np.dot(b - a, b - a) / (n1 + n2)
        dpsi = np.sin(theta[q] / 2) - np.sin(t.rest_theta_np[q] / 2)
        for v in quad:
            for comp in range(3):
                xp, xm = x.copy(), x.copy()
                xp[v, comp] += h
                xm[v, comp] -= h
                dth = (dihedral_angles(xp, quads[q : q + 1])[0] - dihedral_angles(xm, quads[q : q + 1])[0]) / (2 * h)
                exp[v, comp] -= coef * dpsi * dth
    assert np.abs(f - exp).max() < 1e-4 * np.abs(exp).max()
    # and the energy decreases along the force (it is restoring)
    assert _energy(t, x + 1e-3 * f / np.abs(f).max()) < _energy(t, x)


def test_dihedral_hessian_psd_and_exact_at_rest(rng):
    """The Gauss-Newton Hessian is PSD, and at the rest angle (psi' = 0) it equals -df/dx."""
    m = _model("dihedral", k=0.05, nx=3, ny=2)
    t = _term(m)
    n = m.num_vertices

    class Op:  # the term's Hessian as an operator for dense_matrix
        def __init__(self):
            self.n, self.device = n, "cpu"

        def matvec(self, v, out):
            out.zero_()
            t.matvec_add(v, out)

    x = _perturbed(m, rng, 0.05)
    t.eval_with_hessian(wp.array(x, dtype=wp.vec3), wp.zeros(n, dtype=wp.vec3))
    H = dense_matrix(Op())
    assert np.allclose(H, H.T, atol=1e-6)
    assert np.linalg.eigvalsh(H).min() > -1e-6 * np.abs(H).max()
    # diagonal blocks match add_diagonal
    diag = wp.zeros(n, dtype=wp.mat33)
    t.add_diagonal(diag)
    blocks = np.stack([H[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] for i in range(n)])
    assert np.allclose(diag.numpy(), blocks, atol=1e-6)
    # at rest: Jacobian of the forces by central differences (float32, h = 1e-3 m on 0.1 m
    # cells: truncation ~1e-6 relative, rounding of forces ~1e-7 / 2e-3; tolerance 2 %)
    x0 = m.mesh.vertices
    t.eval_with_hessian(wp.array(x0, dtype=wp.vec3), wp.zeros(n, dtype=wp.vec3))
    H0 = dense_matrix(Op())
    v = rng.standard_normal(x0.shape)
    h = 1e-3
    fd = -(_forces(t, x0 + h * v) - _forces(t, x0 - h * v)) / (2 * h)
    hv = (H0 @ v.reshape(-1)).reshape(-1, 3)
    assert np.abs(hv).max() > 0
    assert np.abs(fd - hv).max() < 2e-2 * np.abs(hv).max()


def test_quadratic_energy_flat_zero_rigid_invariant_and_positive_when_folded(rng):
    m = _model("quadratic")
    t = _term(m)
    assert np.allclose(t.K.sum(axis=1), 0.0, atol=1e-12)  # translation invariance of q (T18)
    x0 = m.mesh.vertices
    # a random rotation and translation
    Q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    shift = rng.standard_normal(3)
    assert abs(_energy(t, x0 @ Q.T + shift)) < 1e-8  # flat pair, moved rigidly
    x = _perturbed(m, rng, 0.03)
    e = _energy(t, x)
    assert e > 1e-4  # folded: positive
    assert abs(_energy(t, x @ Q.T + shift) - e) < 1e-4 * e


def test_quadratic_gradient_matvec_and_diagonal(rng):
    m = _model("quadratic", k=0.03)
    t = _term(m)
    n = m.num_vertices
    x = _perturbed(m, rng, 0.03)
    Qs = t.dense_q()
    # host float64 reference: f = -Q x
    f_ref = -(Qs @ x)
    f = _forces(t, x)
    assert np.abs(f - f_ref).max() < 1e-4 * np.abs(f_ref).max()
    # central differences of the float32 kernel energy (exact for a quadratic up to rounding)
    h = 1e-3
    for v in (0, 5, n - 1):
        for c in range(3):
            xp, xm = x.copy(), x.copy()
            xp[v, c] += h
            xm[v, c] -= h
            g = (_energy(t, xp) - _energy(t, xm)) / (2 * h)
            assert abs(-g - f[v, c]) < 1e-3 * np.abs(f).max()
    # matvec and diagonal are the exact Q
    y = wp.zeros(n, dtype=wp.vec3)
    t.matvec_add(wp.array(x, dtype=wp.vec3), y)
    assert np.abs(y.numpy() - Qs @ x).max() < 1e-4 * np.abs(Qs @ x).max()
    diag = wp.zeros(n, dtype=wp.mat33)
    t.add_diagonal(diag)
    assert np.allclose(diag.numpy(), np.diag(Qs)[:, None, None] * np.eye(3), rtol=1e-5, atol=1e-8)


def test_dihedral_force_linear_in_angle_bending_spring_quadratic():
    """T16: near flat, the dihedral force grows ~theta, a bending spring's ~theta^2."""
    mesh = TriMesh(np.array([[0, 0, 0], [1, 0, 0], [0.5, 0, 1], [0.5, 0, -1.0]]),
                   np.array([[0, 1, 2], [1, 0, 3]]))
    mk = ClothModel(mesh, bending="dihedral", bend_stiffness=1.0, stretch_stiffness=0.0,
                    device="cpu")
    t = _term(mk)

    def fold(phi):  # rotate vertex 3 about the x axis (the shared edge) by phi
        v = mesh.vertices.copy()
        v[3] = [0.5, -np.sin(phi), -np.cos(phi)]
        return v

    fd = [np.linalg.norm(_forces(t, fold(p))[3]) for p in (0.02, 0.04)]
    # bending spring between 2 and 3: force k (|x2 - x3| - L)
    L = 2.0
    fs = [abs(np.linalg.norm(fold(p)[2] - fold(p)[3]) - L) for p in (0.02, 0.04)]
    assert fd[1] / fd[0] == pytest.approx(2.0, rel=0.02)
    assert fs[1] / fs[0] == pytest.approx(4.0, rel=0.02)


def test_bending_with_explicit_solver_relaxes_a_fold():
    from warp_cloth.solvers.explicit import SymplecticEuler

    for bending in ("dihedral", "quadratic"):
        m = _model(bending, k=1e-3, gravity=(0.0, 0.0, 0.0))
        st = m.state()
        x = m.mesh.vertices.copy()
        x[:, 1] += 0.05 * np.sin(np.pi * x[:, 0] / 0.4)  # a bump
        st.x.assign(x)
        s = SymplecticEuler(m)
        theta0 = np.abs(dihedral_angles(st.positions(), m.mesh.bend_quads)).max()
        for _ in range(200):
            s.step(st, 1e-4)
        assert np.all(np.isfinite(st.positions()))
        # bending alone (no springs pull the bump out): compare with a bending-free run
        m2 = _model("none", gravity=(0.0, 0.0, 0.0))
        st2 = m2.state()
        st2.x.assign(x)
        s2 = SymplecticEuler(m2)
        for _ in range(200):
            s2.step(st2, 1e-4)
        th = np.abs(dihedral_angles(st.positions(), m.mesh.bend_quads)).max()
        th2 = np.abs(dihedral_angles(st2.positions(), m.mesh.bend_quads)).max()
        assert th < th2 and th < theta0


def test_bad_stiffness():
    m = _model("none")
    with pytest.raises(ValueError, match="bending stiffness"):
        DihedralBending(m, -1.0)
    with pytest.raises(ValueError, match="bending stiffness"):
        QuadraticBending(m, float("nan"))
