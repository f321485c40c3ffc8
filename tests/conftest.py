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
