"""Every example runs as a user would run it and writes a readable, finite USD file."""

import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from warp_cloth.usd import read_points

EXAMPLES = sorted((pathlib.Path(__file__).parent.parent / "examples").glob("*.py"))


@pytest.mark.parametrize("script", EXAMPLES, ids=lambda p: p.stem)
def test_example_runs(script, tmp_path):
    out = tmp_path / f"{script.stem}.usd"
    env = dict(os.environ, PYTHONPATH=str(script.parent.parent))
    proc = subprocess.run([sys.executable, str(script), "--out", str(out), "--frames", "6"],
                          capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    times, pts, _ = read_points(out)
    assert len(times) == 6 and np.all(np.isfinite(pts))
