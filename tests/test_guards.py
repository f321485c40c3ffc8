"""Tests that catch the bugs they are named for (issue 14, item 7).

Each test here was checked by breaking the line it guards on purpose:
the dashpot's sign (`forces/springs.py`), the runner's non-finite check (`scene.py`), strain
measured with ``abs()`` (`diagnostics.py`) and the extent written without a time code (`usd.py`).
"""

import math

import numpy as np
import pytest
import warp as wp
from pxr import Usd, UsdGeom

from warp_cloth import ClothModel, SimulationDiverged, TriMesh
from warp_cloth.diagnostics import Meter, edge_strains
from warp_cloth.forces.springs import SpringForce
from warp_cloth.scenes import hanging
from warp_cloth.solvers.explicit import SymplecticEuler

TRI = TriMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2]]))


# ------------------------------------------------------------------ (a) spring dashpot
def test_spring_dashpot_force_is_minus_c_relative_velocity_along_the_spring():
    """f_i = -c ((v_i - v_j) . n) n on every spring (n = unit vector j -> i), at rest length so
    the spring force is 0; the dashpot's power sum(f . v) is negative (it dissipates)."""
    c = 0.7
    model = ClothModel(TRI, stretch_stiffness=50.0, spring_damping=c, gravity=(0, 0, 0))
    x = TRI.vertices.astype(np.float64)
    v = np.array([[0.3, 0.2, -0.1], [-0.5, 0.1, 0.4], [0.2, -0.6, 0.3]])
    f = wp.zeros(3, dtype=wp.vec3)
    SpringForce(model).eval(wp.array(x, dtype=wp.vec3), wp.array(v, dtype=wp.vec3), f)
    want = np.zeros((3, 3))
    for (i, j) in model.spring_pairs:
        n = (x[i] - x[j]) / np.linalg.norm(x[i] - x[j])
        fi = -c * np.dot(v[i] - v[j], n) * n
        want[i] += fi
        want[j] -= fi
    got = f.numpy().astype(np.float64)
    np.testing.assert_allclose(got, want, atol=1e-6)
    assert np.sum(got * v) < -0.1  # dissipates


def test_spring_dashpot_damps_an_oscillating_spring():
    """Explicit Euler, one spring with a dashpot, no velocity damping: the oscillation's energy
    falls (with the dashpot's sign flipped it grows)."""
    k, m, c = 40.0, 0.1, 0.2
    model = ClothModel(TRI, masses=[m, m, m], stretch_stiffness=[k, 0.0, 0.0], spring_damping=c,
                       gravity=(0, 0, 0), pins=[0, 2])
    solver = SymplecticEuler(model)
    state = model.state()
    x = state.positions()
    x[1, 0] = 1.1
    state.x.assign(x.astype(np.float32))
    dt = 0.25 * SymplecticEuler.stable_dt(model)
    for _ in range(int(1.0 / dt)):  # 1 s, 2 periods; decay time 2 m / c = 1 s
        solver.step(state, dt)
    ext = state.positions()[1, 0] - 1.0
    vel = state.velocities()[1, 0]
    energy = 0.5 * k * ext ** 2 + 0.5 * m * vel ** 2
    assert energy < 0.5 * (0.5 * k * 0.1 ** 2)


# ------------------------------------------------------------------ (b) non-finite guard
def test_guard_catches_nan_that_the_strain_bound_cannot_see(tmp_usd):
    """A NaN injected into the state (the strain measure skips non-finite edges, so the strain
    bound never trips): the run stops with SimulationDiverged naming non-finite positions at the
    next frame, and the USD file holds only the finite frames before it."""
    from warp_cloth.usd import read_points

    scene = hanging(res=4, frames=8, fps=30, strain_bound=1e30, device="cpu")

    def poison(frame, state):
        if frame == 2:
            x = state.positions().astype(np.float32)
            x[7] = np.nan
            state.x.assign(x)

    with pytest.raises(SimulationDiverged, match="non-finite") as info:
        scene.run(tmp_usd, on_frame=poison, save_interval=0.0)
    assert info.value.frame == 3 and info.value.reason == "non-finite positions"
    times, pts, _ = read_points(tmp_usd)
    assert len(times) == 3 and np.all(np.isfinite(pts))


# ------------------------------------------------------------------ (c) compression is not strain
def test_compressed_sheet_reports_zero_strain():
    mesh = TriMesh.grid(3, 3, size=1.0, plane="xz")
    model = ClothModel(mesh, device="cpu")
    state = model.state()
    meter = Meter(model)
    state.x.assign((0.9 * mesh.vertices).astype(np.float32))  # every edge at -10 %
    assert meter(state, energy=False).max_strain == 0.0
    x = 0.9 * mesh.vertices
    x[0] = mesh.vertices[0] - np.array([0.05, 0, 0])  # stretch the edges at vertex 0
    state.x.assign(x.astype(np.float32))
    want = edge_strains(model, x).max()
    assert want > 0.0 and edge_strains(model, x).min() < -0.09  # signed: compression negative
    assert meter(state, energy=False).max_strain == pytest.approx(want, rel=1e-5)


# ------------------------------------------------------------------ (d) extent per frame
def test_extent_is_written_every_frame(tmp_usd):
    scene = hanging(res=4, frames=8, fps=30, device="cpu")
    scene.run(tmp_usd, save_interval=0.0)
    stage = Usd.Stage.Open(tmp_usd)
    mesh = next(UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    exts = []
    for t in (0, 1, 7):
        pts = np.asarray(mesh.GetPointsAttr().Get(t))
        ext = mesh.GetExtentAttr().Get(t)
        assert ext is not None, f"no extent at frame {t}"
        ext = np.asarray(ext)
        np.testing.assert_allclose(ext, [pts.min(0), pts.max(0)], atol=1e-7)
        exts.append(ext)
    assert exts[0][0, 1] - exts[2][0, 1] > 0.05  # the cloth fell: the extents differ


def test_meter_sums_kinetic_and_potential_energy_in_float64():
    """The Meter's kinetic and gravitational energies against a float64 host sum: a 48x48 sheet
    1 km up with random velocities, where a float32 sum of its 2,401 vertices' potentials
    (about 1,500 J), or of float32 terms, is off by 3.6e-5 J; the Meter's is below 1e-6 J."""
    mesh = TriMesh.grid(48, 48, size=1.0, plane="xz", origin=(0.0, 1000.0, 0.0))
    model = ClothModel(mesh, device="cpu")
    state = model.state()
    rng = np.random.default_rng(1)
    v = rng.normal(0.0, 3.0, (model.num_vertices, 3)).astype(np.float32)
    state.v.assign(v)
    # the world's potential (the sheet is simulated in a frame 1,000 m up: `test_origin.py`)
    assert model.origin[1] == 1000.0
    x = state.world_positions()
    m = model.mass.numpy().astype(np.float64)
    g = np.asarray(model.gravity, np.float32).astype(np.float64)  # as the kernels get it
    meas = Meter(model)(state, energy=False)
    assert abs(meas.gravity_potential - float(-(m * (x @ g)).sum())) < 1e-6
    assert abs(meas.kinetic - float(0.5 * (m * (v.astype(np.float64) ** 2).sum(1)).sum())) < 1e-6
