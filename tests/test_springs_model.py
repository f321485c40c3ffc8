"""ClothModel construction and the mass-spring force kernel (physics.md 2.1, T7, T8)."""

import numpy as np
import pytest
import warp as wp

from warp_cloth.forces.springs import SpringForce
from warp_cloth.mesh import TriMesh
from warp_cloth.model import ClothModel, PinPath


def eval_forces(model, x):
    f = wp.zeros(model.num_vertices, dtype=wp.vec3)
    xa = wp.array(x, dtype=wp.vec3)
    for t in model.force_terms:
        t.eval(xa, wp.zeros_like(xa), f, None)
    return f.numpy().astype(np.float64)


def energy(model, x):
    out = wp.zeros(1, dtype=float)
    for t in model.force_terms:
        t.energy(wp.array(x, dtype=wp.vec3), out)
    return float(out.numpy()[0])


def test_two_vertex_spring_exact():
    mesh = TriMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2]]))
    model = ClothModel(mesh, stretch_stiffness=50.0)
    x = mesh.vertices.copy()
    x[1] = [1.5, 0, 0]  # edge (0, 1): rest 1, length 1.5
    x[2] = [0, 1, 0]
    f = eval_forces(model, x)
    # edge (0,1) stretched by 0.5 along x: f0 = +25 x, f1 = -25 x; edge (1,2) rest sqrt2, now sqrt(3.25)
    d12 = x[1] - x[2]
    l12 = np.linalg.norm(d12)
    f1_12 = -50.0 * (l12 - np.sqrt(2)) * d12 / l12
    assert np.allclose(f[1], [-25.0, 0, 0] + f1_12, rtol=1e-5)
    assert np.isclose(energy(model, x), 0.5 * 50 * 0.25 + 0.5 * 50 * (l12 - np.sqrt(2)) ** 2, rtol=1e-5)


@pytest.fixture(scope="module")
def springy():
    mesh = TriMesh.grid(3, 3, size=1.0, plane="xy")
    model = ClothModel(mesh, stretch_stiffness=200.0, shear_stiffness=50.0, bending="springs",
                       bend_stiffness=10.0)
    rng = np.random.default_rng(3)
    x = mesh.vertices + 0.1 * rng.standard_normal(mesh.vertices.shape)
    return model, x


def test_forces_sum_to_zero_and_no_torque(springy):
    model, x = springy
    f = eval_forces(model, x)
    scale = np.abs(f).max()
    assert scale > 1.0
    assert np.abs(f.sum(axis=0)).max() < 1e-5 * scale * len(f)
    assert np.abs(np.cross(x, f).sum(axis=0)).max() < 1e-5 * scale * len(f)


def test_force_is_minus_energy_gradient(springy):
    model, x = springy
    f = eval_forces(model, x)
    h = 1e-3
    g = np.zeros_like(x)
    for i in range(len(x)):
        for c in range(3):
            xp, xm = x.copy(), x.copy()
            xp[i, c] += h
            xm[i, c] -= h
            g[i, c] = (energy(model, xp) - energy(model, xm)) / (2 * h)
    assert np.abs(f + g).max() < 2e-3 * np.abs(f).max()


def test_lumped_mass_and_pins():
    mesh = TriMesh.grid(4, 2, size=(2.0, 1.0))
    model = ClothModel(mesh, density=0.2, pins=[0, 4])
    assert np.isclose(model.total_mass, 0.2 * 2.0)
    assert np.allclose(model.masses, mesh.vertex_areas() * 0.2)
    assert model.inverse_masses[0] == 0 and model.inverse_masses[4] == 0
    assert np.all(model.inverse_masses[1:4] > 0)
    m2 = ClothModel(mesh, masses=np.full(mesh.num_vertices, 0.01))
    assert np.isclose(m2.total_mass, 0.01 * mesh.num_vertices)


def test_structured_spring_network_counts():
    nx, ny = 4, 3
    mesh = TriMesh.grid(nx, ny)
    model = ClothModel(mesh, shear_stiffness=1.0, bending="springs", bend_stiffness=1.0)
    n_edges = len(mesh.edges)
    n_shear = nx * ny  # the missing diagonal of every cell
    n_bend = (nx - 1) * (ny + 1) + (ny - 1) * (nx + 1)  # skip-one along rows and columns
    assert model.num_springs == n_edges + n_shear + n_bend
    rest = model.spring_rest
    # cells are 0.25 x 1/3: skip-one springs are 0.5 along rows and 2/3 along columns
    assert np.allclose(sorted(set(np.round(rest[n_edges + n_shear:], 9))), [0.5, 2 / 3])
    assert np.allclose(rest[n_edges:n_edges + n_shear], np.hypot(0.25, 1 / 3))


def test_unstructured_bending_springs_cross_interior_edges():
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 1, 0], [1, 1.5, 0], [-0.5, 1, 0]], float)
    m = TriMesh(v, np.array([[1, 2, 3], [0, 1, 3], [0, 3, 4]]))
    model = ClothModel(m, bending="springs", bend_stiffness=2.0)
    extra = {tuple(sorted(p)) for p in model.spring_pairs[len(m.edges):].tolist()}
    assert extra == {(1, 4), (0, 2)}


@pytest.mark.parametrize("kwargs,match", [
    (dict(density=0.0), "density"),
    (dict(masses=[1.0, 1.0]), "masses has 2 entries"),
    (dict(masses=[1.0, 1.0, -1.0, 1.0]), "vertex 2 has non-positive"),
    (dict(pins=[7]), "pin 7 is not a vertex index"),
    (dict(pins=[1, 1]), "vertex 1 is pinned twice"),
    (dict(stretch_stiffness=-5.0), "stretch_stiffness"),
    (dict(bending="cubic"), "bending must be one of"),
    (dict(gravity=(0, 1)), "gravity"),
    (dict(shear_stiffness=1.0), None),  # fine on a grid
])
def test_model_errors(kwargs, match):
    mesh = TriMesh.grid(1, 1)
    if match is None:
        ClothModel(mesh, **kwargs)
        return
    with pytest.raises(ValueError, match=match):
        ClothModel(mesh, **kwargs)


def test_shear_needs_grid():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    with pytest.raises(ValueError, match="structured grid"):
        ClothModel(TriMesh(v, np.array([[0, 1, 2]])), shear_stiffness=1.0)


def test_pin_path_validation():
    with pytest.raises(ValueError, match="increase strictly"):
        PinPath([0.0, 0.0], np.zeros((2, 1, 3)))
    with pytest.raises(ValueError, match=r"shape \(K=2, P, 3\)"):
        PinPath([0.0, 1.0], np.zeros((3, 1, 3)))
    with pytest.raises(ValueError, match="moves 1 vertices, pins has 2"):
        ClothModel(TriMesh.grid(1, 1), pins=[0, 1], pin_path=PinPath([0.0], np.zeros((1, 1, 3))))
