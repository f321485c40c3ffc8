"""Symplectic Euler: exact small cases, pins, stability bound, divergence guard (T1, T53)."""

import math

import numpy as np
import pytest
import warp as wp

from warp_cloth import ClothModel, PinPath, Scene, SimulationDiverged, TriMesh, make_solver
from warp_cloth.scenes import hanging
from warp_cloth.solvers.explicit import SymplecticEuler
from warp_cloth.usd import read_points

TRI = TriMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2]]))


def run_steps(solver, state, dt, n, record=None):
    out = []
    for _ in range(n):
        solver.step(state, dt)
        if record is not None:
            out.append(record(state))
    return out


def test_free_fall_is_exact_symplectic_euler():
    model = ClothModel(TRI, stretch_stiffness=0.0, gravity=(0, -9.81, 0))
    solver = SymplecticEuler(model)
    state = model.state()
    dt, n = 0.01, 50
    run_steps(solver, state, dt, n)
    y = state.positions()[:, 1]
    # symplectic Euler: y_n = y_0 - g dt^2 n (n + 1) / 2, i.e. g t^2/2 + g t dt/2
    expect = TRI.vertices[:, 1] - 9.81 * dt * dt * n * (n + 1) / 2
    assert np.allclose(y, expect, atol=1e-5)
    t = n * dt
    assert abs((TRI.vertices[0, 1] - y[0]) - 9.81 * t * t / 2) <= 9.81 * t * dt / 2 + 1e-5
    assert np.isclose(state.t, t)


@pytest.mark.parametrize("pinned", [True, False])
def test_two_vertex_spring_period(pinned):
    k, m = 40.0, 0.1
    # only edge (0, 1) has stiffness; no gravity
    model = ClothModel(TRI, masses=[m, m, m], stretch_stiffness=[k, 0.0, 0.0], gravity=(0, 0, 0),
                       pins=[0] if pinned else [])
    mu = m if pinned else m / 2
    omega = math.sqrt(k / mu)
    period = 2 * math.pi / omega
    solver = SymplecticEuler(model)
    state = model.state()
    x = state.positions()
    x[1, 0] = 1.1  # stretched by 0.1
    state.x.assign(x.astype(np.float32))
    dt = period / 2000
    ext = np.array(run_steps(solver, state, dt, 5000, lambda s: s.positions()[1, 0] - s.positions()[0, 0] - 1.0))
    crossings = np.flatnonzero((ext[:-1] > 0) & (ext[1:] <= 0))
    measured = (crossings[-1] - crossings[0]) * dt / (len(crossings) - 1)
    assert abs(measured - period) / period < 5e-3
    assert np.abs(ext).max() < 0.1 * 1.01  # no energy gain


def test_stability_bound_separates_stable_and_divergent():
    """T1: below the Gershgorin bound the spring oscillates boundedly; far above it explodes."""
    k, m = 40.0, 0.1
    model = ClothModel(TRI, masses=[m, m, m], stretch_stiffness=[k, 0.0, 0.0], gravity=(0, 0, 0), pins=[0])
    sdt = SymplecticEuler.stable_dt(model)
    assert sdt <= 2.0 / math.sqrt(k / m) + 1e-12  # conservative: never above the exact 2/omega
    for factor, bounded in ((0.9, True), (3.0, False)):
        solver = SymplecticEuler(model)
        state = model.state()
        x = state.positions()
        x[1, 0] = 1.1
        state.x.assign(x.astype(np.float32))
        run_steps(solver, state, factor * sdt, 200)
        amp = np.abs(state.positions()[1, 0] - 1.0)
        assert (amp < 0.2) == bounded


def test_velocity_damping_is_geometric():
    model = ClothModel(TRI, stretch_stiffness=0.0, gravity=(0, 0, 0), damping=2.0, velocity=(1.0, 0, 0))
    solver = SymplecticEuler(model)
    state = model.state()
    run_steps(solver, state, 0.01, 100)
    assert np.allclose(state.velocities()[:, 0], math.exp(-2.0), rtol=1e-4)


def test_pins_stay_put_and_scripted_pins_follow_path():
    scene = hanging(res=6, frames=5, device="cpu")
    x0 = scene.model.mesh.vertices[[0, 6]]
    scene.run()
    assert np.array_equal(scene.state.positions()[[0, 6]], x0.astype(np.float32).astype(np.float64))
    # scripted: the two pins move up by 0.3 m over 0.5 s
    mesh = TriMesh.grid(4, 4, size=1.0, plane="xz")
    path = PinPath([0.0, 0.5], np.stack([mesh.vertices[[0, 4]], mesh.vertices[[0, 4]] + [0, 0.3, 0]]))
    model = ClothModel(mesh, pins=[0, 4], pin_path=path)
    solver = SymplecticEuler(model)
    state = model.state()
    dt = 1e-3
    run_steps(solver, state, dt, 250)
    assert np.allclose(state.positions()[[0, 4], 1], 0.15, atol=1e-5)
    assert np.allclose(state.velocities()[[0, 4], 1], 0.6, atol=1e-3)
    run_steps(solver, state, dt, 400)
    assert np.allclose(state.positions()[[0, 4], 1], 0.3, atol=1e-5)
    assert np.allclose(state.velocities()[[0, 4]], 0.0, atol=1e-6)


def test_divergence_guard_stops_and_file_is_finite(tmp_usd):
    scene = hanging(res=8, stiffness=1e6, substeps=2, frames=30, device="cpu", self_collision=False)
    with pytest.raises(SimulationDiverged) as info:
        scene.run(tmp_usd)
    err = info.value
    assert err.method == "explicit" and 1 <= err.frame < 30
    assert f"frame {err.frame}" in str(err) and "explicit" in str(err)
    times, pts, stage = read_points(tmp_usd)
    assert len(times) == err.frame and np.all(np.isfinite(pts))
    assert stage.GetEndTimeCode() == err.frame - 1


def test_strain_bound_is_configurable():
    scene = hanging(res=6, stiffness=20.0, frames=20, strain_bound=0.01, device="cpu")
    with pytest.raises(SimulationDiverged, match="strain bound"):
        scene.run()


def test_captured_replay_equals_plain_steps():
    a = hanging(res=6, frames=6, device="cpu")
    b = hanging(res=6, frames=6, device="cpu")
    b.capture = False
    sa, sb = a.run(), b.run()
    assert sa.captured and not sb.captured
    assert np.allclose(a.state.positions(), b.state.positions(), atol=1e-6)


def test_bad_dt_and_solver_options():
    model = ClothModel(TRI)
    solver = make_solver("explicit", model)
    state = model.state()
    for dt in (0.0, -1e-3, float("nan"), "x"):
        with pytest.raises(ValueError, match="dt"):
            solver.step(state, dt)
    with pytest.raises(ValueError, match="unknown solver 'rk4'"):
        make_solver("rk4", model)
    with pytest.raises(ValueError, match=r"no option\(s\) \['iterations'\]"):
        make_solver("explicit", model, iterations=3)
    with pytest.raises(ValueError, match="different model"):
        Scene(ClothModel(TRI), solver)


@pytest.mark.parametrize("bending", ["quadratic", "dihedral"])
def test_stable_dt_counts_bending_and_dashpots(bending):
    """Issue 14: the automatic substeps count bending and spring dashpots. The bound falls as the
    bending stiffness rises and as the dashpot grows; a run at the suggested substeps stays finite
    and bounded, one at a quarter of them (twice the bound) blows up."""
    from warp_cloth.scenes import hanging_model

    sdt = [SymplecticEuler.stable_dt(hanging_model(res=8, bending=bending, bend_stiffness=kb))
           for kb in (0.0, 0.1, 1.0, 10.0)]
    assert all(a > b for a, b in zip(sdt, sdt[1:])), sdt
    damped = [SymplecticEuler.stable_dt(hanging_model(res=8, spring_damping=c)) for c in (0, 0.01, 0.1)]
    assert damped[0] == pytest.approx(sdt[0]) and damped[0] > damped[1] > damped[2]
    scene = hanging(res=8, bending=bending, bend_stiffness=1.0, frames=10, device="cpu",
                    self_collision=False)
    assert scene.substeps >= 40
    stats = scene.run(None, quiet=True)
    assert stats.max_strain < 0.02
    fewer = hanging(res=8, bending=bending, bend_stiffness=1.0, frames=10, device="cpu",
                    self_collision=False,
                    substeps=scene.substeps // 4)
    with pytest.raises(SimulationDiverged):
        fewer.run(None, quiet=True)


def test_stable_dt_of_the_dashpot_is_the_exact_two_mode_bound():
    """One spring (k, c) to a pinned vertex: symplectic Euler is stable iff
    dt^2 w^2 + 2 dt g < 4 with w^2 = k/m, g = c/m; the Gershgorin bound uses 2k and 2c."""
    k, m, c = 40.0, 0.1, 0.3
    model = ClothModel(TRI, masses=[m, m, m], stretch_stiffness=[k, 0.0, 0.0], gravity=(0, 0, 0),
                       pins=[0, 2], spring_damping=c)
    # vertex 1 is in two springs, (0, 1) of stiffness k and (1, 2) of stiffness 0; both have the dashpot
    K, C = SymplecticEuler.stiffness_row_sums(model)
    assert K[1] == pytest.approx(2 * k) and C[1] == pytest.approx(2 * 2 * c)
    w2, g = K[1] / m, C[1] / m
    dt = SymplecticEuler.stable_dt(model)
    assert dt * dt * w2 + 2 * dt * g == pytest.approx(4.0)


def test_a_step_past_the_stability_bound_is_warned_before_the_run(capsys):
    """Substeps given by hand that put explicit Euler's step past its stability bound are a
    warning at the start, naming the factor and the steps a frame that hold it; the solver's
    own substeps are not."""
    scene = hanging(solver="explicit", res=4, fps=24.0, frames=2, substeps=1,
                    self_collision=False)
    sdt = SymplecticEuler.stable_dt(scene.model)
    try:
        scene.run(None, energy=False)
    except SimulationDiverged:
        pass
    err = capsys.readouterr().err
    assert f"{scene.dt / sdt:.3g} times its stability bound" in err, err
    need = scene.solver.suggest_substeps(1.0 / 24.0)
    assert f"{need} steps a frame keep it stable" in err
    ok = hanging(solver="explicit", res=4, fps=24.0, frames=2, self_collision=False)
    ok.run(None, energy=False)
    assert "stability bound" not in capsys.readouterr().err


def _sliver_sheet(bending, lift=1e-3):
    """A 6 x 6 sheet with one sliver triangle on its boundary edge 0-1: its apex ``lift`` of
    the edge's length outside the edge (as some exporters leave)."""
    g = TriMesh.grid(6, 6, size=0.6, plane="xz", origin=(-0.3, 1.0, -0.3))
    v, t = np.asarray(g.vertices, float), np.asarray(g.triangles)
    apex = (v[0] + v[1]) / 2 + np.array([0.0, 0.0, -lift * np.linalg.norm(v[1] - v[0])])
    mesh = TriMesh(np.vstack([v, apex]), np.vstack([t, [1, 0, len(v)]]), name="sliver")
    return ClothModel(mesh, density=0.2, stretch_stiffness=165.0, bending=bending,
                      bend_stiffness=1e-3)


@pytest.mark.parametrize("bending", ["quadratic", "dihedral"])
def test_many_automatic_steps_are_explained_naming_the_sliver(bending, capsys):
    """A sliver triangle stiffens bending as one over its angle: explicit Euler's automatic
    step count grows a thousandfold (a fuzzed 14 x 14 sheet: 12,975 steps, 15 s a frame, without
    a word). The run's start names the vertex, the term and the angle, and what the springs
    alone would take; the same sheet without the sliver gets no note."""
    from warp_cloth import scene as scene_mod

    model = _sliver_sheet(bending)
    found = SymplecticEuler.stiffest(model)
    assert found["vertex"] == model.num_vertices - 1  # the apex
    assert found["term"] == f"{bending} bending"
    assert found["min_angle"] == pytest.approx(np.degrees(np.arctan(2e-3)), rel=1e-3)
    sc = Scene(model, make_solver("explicit", model), fps=40, frames=1)
    assert sc.substeps > scene_mod.MANY_SUBSTEPS
    sc.run(None, quiet=False, progress=False, energy=False)
    err = capsys.readouterr().err
    assert f"{sc.substeps} steps a frame: vertex {model.num_vertices - 1}'s {bending} bending" \
        in err, err
    assert "a sliver" in err and "the springs alone would take" in err, err
    plain = ClothModel(TriMesh.grid(6, 6, size=0.6, plane="xz", origin=(-0.3, 1.0, -0.3)),
                       density=0.2, stretch_stiffness=165.0, bending=bending,
                       bend_stiffness=1e-3)
    Scene(plain, make_solver("explicit", plain), fps=40, frames=1).run(None, quiet=False,
                                                                        progress=False)
    assert "steps a frame:" not in capsys.readouterr().err
