"""Accuracy against analytic answers (issue 6): free fall, a hanging chain's static sag, and
first-order convergence in the time step. Each would fail for a broken solver (wrong sign of
gravity, wrong spring force, a lost dt factor)."""

import math

import numpy as np
import pytest

from warp_cloth import ClothModel, TriMesh, make_solver
from warp_cloth.solvers import available

# options that make each method converge tightly in these small problems
TIGHT = {
    "explicit": {},
    "implicit": {"newton_iterations": 20, "tolerance": 1e-7, "linear": "cg", "linear_iterations": 200,
                 "linear_tolerance": 1e-7},
    "pd": {"iterations": 100, "direct": True},  # host direct global step: exact, fast on tiny meshes
    "pbd": {"iterations": 10},
}
PHYSICAL = [m for m in ("explicit", "implicit", "pd") if m in available()]
TRI = TriMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2]]))


def solver_for(method, model):
    return make_solver(method, model, **TIGHT[method])


@pytest.mark.parametrize("method", available())
def test_free_fall(method):
    """Every method integrates a free particle as y_n = y_0 - g dt^2 n (n + 1) / 2 exactly."""
    model = ClothModel(TRI, stretch_stiffness=0.0)
    solver = solver_for(method, model)
    state = model.state()
    dt, n = 1 / 60, 30
    for _ in range(n):
        solver.step(state, dt)
    y = state.positions()[:, 1]
    assert np.allclose(y, TRI.vertices[:, 1] - 9.81 * dt * dt * n * (n + 1) / 2, atol=2e-5)
    assert np.allclose(state.velocities()[:, 1], -9.81 * n * dt, atol=1e-4)


def chain_model(n=6, h=0.1, k=100.0, m=0.01, damping=5.0):
    """A vertical chain of n springs: column i = 0 of a 1 x n strip, top vertex pinned, every other
    edge with zero stiffness and the whole other column pinned (so it exerts no force)."""
    mesh = TriMesh.grid(1, n, size=(h, n * h), plane="xy")
    col0 = np.arange(0, 2 * (n + 1), 2)
    chain = {(int(a), int(a) + 2) for a in col0[:-1]}
    ks = np.array([k if tuple(e) in chain else 0.0 for e in mesh.edges.tolist()])
    pins = [int(col0[-1])] + list(range(1, 2 * (n + 1), 2))
    masses = np.full(mesh.num_vertices, m)
    model = ClothModel(mesh, masses=masses, stretch_stiffness=ks, pins=pins, damping=damping)
    top = mesh.vertices[col0[-1], 1]
    # spring between rows s and s + 1 carries the weight of rows 0..s
    ext = [(s + 1) * m * 9.81 / k for s in range(n)]
    y_eq = np.array([top - sum(h + ext[s] for s in range(j, n)) for j in range(n + 1)])
    return model, col0, y_eq


@pytest.mark.parametrize("method", PHYSICAL)
def test_hanging_chain_static_sag(method):
    model, col0, y_eq = chain_model()
    solver = solver_for(method, model)
    state = model.state()
    dt, t_end = {"explicit": (1e-3, 4.0), "implicit": (1 / 60, 6.0), "pd": (0.05, 6.0)}[method]
    for _ in range(int(round(t_end / dt))):
        solver.step(state, dt)
    y = state.positions()[col0, 1]
    sag = y_eq[-1] - y_eq[0]  # total length under load
    assert np.abs(y - y_eq).max() < 2e-3 * sag
    # the stretch itself (not just the rest length) is right to 2 %
    ext = np.diff(y) - 0.1
    assert np.allclose(ext, np.diff(y_eq) - 0.1, rtol=0.02)


def oscillator_error(method, dt, t_end):
    k, m = 40.0, 0.1
    model = ClothModel(TRI, masses=[m] * 3, stretch_stiffness=[k, 0.0, 0.0], gravity=(0, 0, 0), pins=[0])
    solver = solver_for(method, model)
    state = model.state()
    x = state.positions()
    x[1, 0] = 1.1
    state.x.assign(x.astype(np.float32))
    n = int(round(t_end / dt))
    for _ in range(n):
        solver.step(state, dt)
    omega = math.sqrt(k / m)
    exact = 0.1 * math.cos(omega * n * dt)
    return abs(state.positions()[1, 0] - 1.0 - exact)


@pytest.mark.parametrize("method", [m for m in ("explicit", "implicit") if m in available()])
def test_first_order_convergence_in_dt(method):
    """Error at t = 0.3 s halves when dt halves (both Euler methods are first order)."""
    errs = [oscillator_error(method, dt, 0.3) for dt in (2e-3, 1e-3, 5e-4)]
    r1, r2 = errs[0] / errs[1], errs[1] / errs[2]
    assert 1.6 < r1 < 2.5 and 1.6 < r2 < 2.5, errs
