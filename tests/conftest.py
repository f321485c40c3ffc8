"""Shared test set-up: everything runs on Warp's CPU device; kernels compile once per session."""

import os

import numpy as np
import pytest
import warp as wp

from warp_cloth.util import quiet_warp

quiet_warp()
wp.init()
wp.set_device("cpu")


@pytest.fixture(scope="session")
def device():
    return "cpu"


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def tmp_usd(tmp_path):
    return os.fspath(tmp_path / "out.usd")


def _run_metered(scene, **run_kw):
    """Run ``scene`` and return the per-frame total energy and max edge strain (numpy arrays,
    `warp_cloth.diagnostics.Meter`)."""
    from warp_cloth.diagnostics import Meter

    meter = Meter(scene.model)
    energy, strain = [], []

    def on_frame(f, st):
        m = meter(st, energy=True)
        energy.append(m.energy)
        strain.append(m.max_strain)

    scene.run(None, quiet=True, on_frame=on_frame, **run_kw)
    return np.asarray(energy), np.asarray(strain)


@pytest.fixture
def run_metered():
    """`_run_metered`: a scene's per-frame energy and max strain."""
    return _run_metered


def _short_steps(scene, frames: int):
    """Step ``scene`` (its solver and collision stage, from the model's start) for ``frames``
    frames of ``scene.substeps`` steps and return ``(short, steps, state)``: how many steps
    ended short of the solver's tolerance (``stats["converged"]`` false), of how many."""
    solver, stage = scene.solver, scene.collision
    state = scene.model.state()
    stage.plan(scene.substeps)
    short = steps = 0
    for _ in range(frames):
        for _ in range(scene.substeps):
            solver.step(state, scene.dt)
            steps += 1
            short += not solver.stats["converged"]
        stage.frame_end()
    return short, steps, state


@pytest.fixture
def short_steps():
    """`_short_steps`: a scene's steps that ended short of the solver's tolerance."""
    return _short_steps
