"""Quiet by default: no Warp start-up or module-load lines and no CUDA-driver warning unless
asked for; a progress bar with the time remaining; set-up time that includes every compile."""

import subprocess
import sys
import time

import pytest

from warp_cloth import scene as scene_mod
from warp_cloth.scenes import hanging

RUN = ["run", "hanging", "--res", "3", "--frames", "3"]


def cli(args, tmp_path):
    return subprocess.run([sys.executable, "-m", "warp_cloth.cli", *args, "--out",
                           str(tmp_path / "q.usd")], capture_output=True, text=True, timeout=300)


def test_cli_is_quiet_by_default_and_verbose_on_request(tmp_path):
    r = cli(RUN, tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stderr == "", r.stderr  # no CUDA warning
    # Warp prints its banner and module loads to stdout (on a terminal: into the bar's line)
    assert r.stdout.startswith("explicit: 3 frames") and r.stdout.count("\n") == 1, r.stdout
    v = cli(RUN + ["--verbose"], tmp_path)
    assert v.returncode == 0
    assert "Module warp_cloth" in v.stdout and "initialized" in v.stdout  # Warp's own messages
    import warp as wp

    if not wp.is_cuda_available():
        assert "CUDA driver" in v.stderr
        # asking for a CUDA device shows why there is none
        c = cli(RUN + ["--device", "cuda:0"], tmp_path)
        assert c.returncode == 2 and "CUDA driver" in c.stderr


def test_progress_bar_has_no_warp_lines_and_shows_time_left(tmp_path):
    code = ("from warp_cloth.util import init_warp; init_warp(); "
            "from warp_cloth.scenes import hanging; "
            "hanging(res=3, frames=40, device='cpu').run(None, progress=True)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=300)
    err, out = r.stderr.decode(), r.stdout.decode()
    assert r.returncode == 0, err
    assert out == ""  # nothing from Warp between the bar's redraws
    assert "frames/s" in err and "Module" not in err and "CUDA" not in err
    assert err.endswith("\n") and err.count("\n") == 1, err  # one line, redrawn with \r


def test_eta_from_the_steady_rate(monkeypatch, capsys):
    clock = iter([0.0, 1.0, 2.0, 3.0, 5.0, 10.0, 10.5, 11.0])
    monkeypatch.setattr(scene_mod._time, "perf_counter", lambda: next(clock))
    bar = scene_mod._Progress(100, True, "t")  # t0 = 0
    bar.update(1)  # 1 s: compile frame
    bar.update(2)  # 2 s
    bar.update(3)  # 3 s: steady from here
    bar.update(13)  # 5 s: 10 frames in 2 s -> 87 left at 5 frames/s = 17.4 s
    out = capsys.readouterr().err
    assert "13/100 frames" in out and "0:17 left" in out
    assert bar.eta(53, 13.0) == pytest.approx(47 / 5.0)
    assert scene_mod._clock(3725) == "1:02:05"


def test_setup_time_includes_the_first_measurement_and_frames(monkeypatch):
    """The set-up time reported covers the first measurement (the diagnostics compile on a
    cold cache) and the first frame, not only the first frame."""
    real = scene_mod.Meter.__call__
    calls = []

    def slow_first(self, *a, **k):
        calls.append(1)
        if len(calls) == 1:
            time.sleep(0.3)
        return real(self, *a, **k)

    monkeypatch.setattr(scene_mod.Meter, "__call__", slow_first)
    stats = hanging(res=3, frames=4, device="cpu").run(None)
    assert stats.setup_s >= 0.3 + stats.first_frame_s
    assert stats.setup_s + stats.wall_s <= stats.total_s
    assert f"set-up incl. compile {stats.setup_s:.2f} s" in stats.summary()
