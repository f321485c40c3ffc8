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
