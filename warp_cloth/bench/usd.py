"""``warp-cloth bench usd``: what saving the USD output costs, and whether a kill can corrupt it.

Two measurements of `warp_cloth.usd.UsdWriter` (no simulation: synthetic frames of a grid):

- ``--cost`` (default): a grid of about ``--vertices`` vertices (default 65,536), ``--frames``
  frames (default 2,000) with a save after every frame (the worst case; the default CLI saves
  every 2 s). Prints the median milliseconds per frame (authoring + save) over frames 100-199
  and over the last 100 frames, their ratio (flat cost: about 1), the same for the save alone
  and for the root's rewrite within it (its clip list grows by one entry, about 46 bytes, a
  save), and the bytes on disk::

      cost: vertices=N frames=F early_ms=A late_ms=B ratio=B/A save_early_ms=.. save_late_ms=..
            root_early_ms=.. root_late_ms=.. root_bytes=R total_mb=M

  On a shared machine other processes' load moves these medians by tens of percent between the
  start and the end of a run; the save's parts show what, if anything, grows.

- ``--kill N``: N times, starts a writer process (a child of this command) saving every frame,
  waits until the output folder changes on disk (a save is writing) plus a random delay of up to
  ``--max-delay`` seconds, sends ``--signal`` (KILL or TERM, alternating with ``both``), and
  opens the result with ``Usd.Stage.Open``: it must compose, its points' time samples must be
  ``0 .. last`` and its end time code ``last``. Prints one line per try and::

      kill: tries=N ok=K

  (ok: readable, samples 0..last, end time code = last). Exit status 1 if any try was not ok.
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

__all__ = ["main", "check_output", "kill_once", "measure_cost"]


def _grid(n_vertices: int):
    side = max(2, int(round(np.sqrt(n_vertices))))
    i, j = np.meshgrid(np.arange(side), np.arange(side))
    pts = np.stack([i.reshape(-1) / side, np.zeros(side * side), j.reshape(-1) / side], 1)
    v = (np.arange(side - 1)[None, :] + side * np.arange(side - 1)[:, None]).reshape(-1)
    tris = np.concatenate([np.stack([v, v + 1, v + side + 1], 1), np.stack([v, v + side + 1, v + side], 1)])
    return pts.astype(np.float32), tris.astype(np.int32)


def check_output(path) -> tuple[bool, int, str]:
    """Open a written stage; returns ``(ok, frames, why)``: ok when it composes, its first
    time-sampled mesh has samples ``0 .. last`` and the end time code is ``last`` (an empty stage
    with end time code 0 is ok with 0 frames)."""
    from pxr import Usd, UsdGeom

    try:
        stage = Usd.Stage.Open(os.fspath(path))
    except Exception as e:  # noqa: BLE001 - any failure to open is the finding
        return False, 0, f"cannot open: {str(e).strip().splitlines()[-1] if str(e).strip() else e}"
    if stage is None:
        return False, 0, "cannot open"
    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    times = []
    if meshes:
        attr = UsdGeom.Mesh(meshes[0]).GetPointsAttr()
        times = attr.GetTimeSamples()
        for t in times[-1:]:
            if attr.Get(t) is None:
                return False, len(times), f"no points at time {t}"
    if times != [float(k) for k in range(len(times))]:
        return False, len(times), f"time samples are not 0..N-1: {times[:5]}..."
    end = stage.GetEndTimeCode()
    if end != (times[-1] if times else 0):
        return False, len(times), f"end time code {end} but last frame {times[-1] if times else None}"
    return True, len(times), ""


def _child(out: str, vertices: int) -> None:
    """The writer process the kill loop kills: saves after every frame, forever."""
    from ..usd import UsdWriter

    pts, tris = _grid(vertices)
    w = UsdWriter(out, fps=60, save_interval=0.0)
    mesh = w.add_mesh("cloth", tris)
    print("ready", flush=True)
    f = 0
    while True:
        w.write_frame(f, {mesh: pts + np.float32(0.001 * f)})
        f += 1


def _folder_state(folder: str):
    try:
        return tuple(sorted((e.name, e.stat().st_mtime_ns, e.stat().st_size)
                            for e in os.scandir(folder)))
    except OSError:
        return None


def kill_once(out: str, sig: int, *, vertices: int = 400, max_delay: float = 0.3,
              cli: bool = False, rng: random.Random | None = None) -> tuple[bool, int, str, int]:
    """Start a writer (or, with ``cli``, ``warp-cloth run hanging`` saving every frame), kill it
    with ``sig`` while it saves, and check the file. Returns ``(ok, frames, why, exit status)``."""
    rng = rng or random.Random()
    env = dict(os.environ)
    if cli:
        cmd = [sys.executable, "-m", "warp_cloth.cli", "run", "hanging", "--res", "6",
               "--frames", "1000000", "--save-interval", "0", "--quiet", "--out", out]
    else:
        cmd = [sys.executable, "-m", "warp_cloth.bench.usd", "--child", out,
               "--vertices", str(vertices)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True)
    try:
        folder = out + ".frames"
        deadline = time.monotonic() + 120
        # wait for the first frame files, then for a change on disk (a save writing), then a
        # random moment later
        while not os.path.exists(os.path.join(folder, "000000.usdc")):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"writer did not start: {proc.communicate()[1][-2000:]}")
            time.sleep(0.005)
        before = _folder_state(folder)
        while _folder_state(folder) == before and time.monotonic() < deadline:
            time.sleep(0.0005)
        time.sleep(rng.uniform(0.0, max_delay))
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    ok, frames, why = check_output(out)
    return ok, frames, why, proc.returncode


def measure_cost(out: str, vertices: int = 65536, frames: int = 2000, echo=print) -> dict:
    """Write ``frames`` frames of a ``vertices`` grid, saving after each; medians of the
    per-frame times (frames 100-199 and the last 100) of the frame's authoring, its save, and
    the root's rewrite within the save."""
    from ..usd import UsdWriter

    pts, tris = _grid(vertices)
    w = UsdWriter(out, fps=60, save_interval=float("inf"))
    mesh = w.add_mesh("cloth", tris)
    write_ms, save_ms, root_ms = [], [], []
    write_root = w._write_root

    def timed_root(*a, **k):  # the only part of a save that grows with the run
        t = time.perf_counter()
        write_root(*a, **k)
        root_ms.append(1e3 * (time.perf_counter() - t))

    w._write_root = timed_root
    for f in range(frames):
        t0 = time.perf_counter()
        w.write_frame(f, {mesh: pts + np.float32(0.001 * f)})
        t1 = time.perf_counter()
        w.save()
        t2 = time.perf_counter()
        write_ms.append(1e3 * (t1 - t0))
        save_ms.append(1e3 * (t2 - t1))
        if echo and (f + 1) % 500 == 0:
            echo(f"  frame {f + 1}: write+save {statistics.median(write_ms[-100:]):.1f} + "
                 f"{statistics.median(save_ms[-100:]):.1f} ms (medians of the last 100)")
    w.close()
    early, late = slice(100, 200) if frames >= 200 else slice(0, frames), slice(-100, None)
    med = statistics.median
    total = [a + b for a, b in zip(write_ms, save_ms)]
    folder = out + ".frames"
    size = os.path.getsize(out) + sum(e.stat().st_size for e in os.scandir(folder))
    return {"vertices": len(pts), "frames": frames,
            "early_ms": med(total[early]), "late_ms": med(total[late]),
            "ratio": med(total[late]) / med(total[early]),
            "save_early_ms": med(save_ms[early]), "save_late_ms": med(save_ms[late]),
            "root_early_ms": med(root_ms[early]), "root_late_ms": med(root_ms[late]),
            "root_bytes": os.path.getsize(out), "total_mb": size / 1e6}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="warp-cloth bench usd", description=__doc__.split("\n\n")[0])
    ap.add_argument("--cost", action="store_true", help="measure the save cost (default)")
    ap.add_argument("--kill", type=int, default=0, metavar="N", help="kill loop of N tries")
    ap.add_argument("--signal", choices=["KILL", "TERM", "both"], default="both")
    ap.add_argument("--cli", action="store_true",
                    help="kill loop on `warp-cloth run hanging` instead of a bare writer")
    ap.add_argument("--vertices", type=int, default=None)
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--max-delay", type=float, default=0.3)
    ap.add_argument("--dir", default=None, help="folder for the files (default: a temporary one)")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        _child(a.child, a.vertices or 400)
        return 0
    with tempfile.TemporaryDirectory(dir=a.dir) as tmp:
        if a.kill:
            rng = random.Random(1)
            good = 0
            for k in range(a.kill):
                name = a.signal if a.signal != "both" else ("KILL", "TERM")[k % 2]
                sig = getattr(signal, f"SIG{name}")
                out = os.path.join(tmp, f"kill{k}.usd")
                ok, frames, why, rc = kill_once(out, sig, vertices=a.vertices or 400,
                                                max_delay=a.max_delay, cli=a.cli, rng=rng)
                good += ok
                print(f"try {k}: SIG{name} exit {rc}: {'readable' if ok else 'BAD'} "
                      f"{frames} frames {why}", flush=True)
            print(f"kill: tries={a.kill} ok={good}")
            return 0 if good == a.kill else 1
        r = measure_cost(os.path.join(tmp, "cost.usd"), a.vertices or 65536, a.frames)
        print("cost: " + " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                  for k, v in r.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
