"""``warp-cloth bench explicit``: time per substep of symplectic Euler on the hanging cloth.

Reports, on the 64 x 32-cell hanging cloth (2,145 vertices, 6,240 springs) by default:

- ms per substep, plain launches and replayed as a captured Warp graph;
- the same for a trivial one-line kernel over the same vertex array (the floor any step pays),
  and the ratio of the two, measured in the same run;
- optionally (``--cold``) the cold start: a fresh Python process with an empty kernel cache, from
  interpreter start to the first frame written (imports + compile + first frame).

Target (issue 2): under 0.3 ms per substep; cold start under 30 s.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
import warp as wp

from ..util import quiet_warp
from .common import capture, markdown_table, time_callable, trivial_kernel

COLD_SNIPPET = """
import time; t0 = time.perf_counter()
from warp_cloth.util import quiet_warp; quiet_warp()
from warp_cloth.scenes import hanging
s = hanging(shape=({nx}, {ny}), frames=2, device={device!r}, self_collision=False)
s.run(None, quiet=True)
print(time.perf_counter() - t0)
"""


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="warp-cloth bench explicit", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--shape", type=int, nargs=2, default=(64, 32), metavar=("NX", "NY"))
    p.add_argument("--steps", type=int, default=500, help="substeps per timing")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--device", default=None)
    p.add_argument("--cold", action="store_true", help="also measure a cold start (empty cache)")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    if args.steps < 1 or args.repeats < 1:
        p.error("--steps and --repeats must be positive")

    quiet_warp()
    from ..scenes import hanging_model
    from ..solvers.explicit import SymplecticEuler

    model = hanging_model(shape=tuple(args.shape), device=args.device)
    dev = model.device
    solver = SymplecticEuler(model)
    state = model.state()
    dt = 0.5 * SymplecticEuler.stable_dt(model)
    n = args.steps

    def steps():
        for _ in range(n):
            solver.step(state, dt)

    def trivial():
        for _ in range(n):
            wp.launch(trivial_kernel, model.num_vertices, [state.x, state.v, 0.0], device=dev)

    steps(), trivial()  # compile and warm up
    g_step, g_triv = capture(steps, dev), capture(trivial, dev)
    res = {
        "vertices": model.num_vertices, "springs": model.num_springs, "dt": dt,
        "step_ms": 1e3 * time_callable(steps, args.repeats, dev) / n,
        "trivial_ms": 1e3 * time_callable(trivial, args.repeats, dev) / n,
        "step_graph_ms": 1e3 * time_callable(lambda: wp.capture_launch(g_step), args.repeats, dev) / n,
        "trivial_graph_ms": 1e3 * time_callable(lambda: wp.capture_launch(g_triv), args.repeats, dev) / n,
    }
    res["ratio"] = res["step_ms"] / res["trivial_ms"]
    res["ratio_graph"] = res["step_graph_ms"] / res["trivial_graph_ms"]
    res["finite"] = bool(np.all(np.isfinite(state.x.numpy())))
    if args.cold:
        with tempfile.TemporaryDirectory() as cache:
            env = dict(os.environ, WARP_CACHE_PATH=cache)
            code = COLD_SNIPPET.format(nx=args.shape[0], ny=args.shape[1], device=args.device)
            t0 = time.perf_counter()
            out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                                 text=True, check=True)
            res["cold_start_s"] = float(out.stdout.strip().splitlines()[-1])
            res["cold_process_s"] = time.perf_counter() - t0
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    print(f"explicit solver, hanging cloth {args.shape[0]} x {args.shape[1]} cells: "
          f"{res['vertices']} vertices, {res['springs']} springs, dt {dt:.3g} s, device {dev}")
    rows = [
        ["symplectic Euler step", res["step_ms"], res["step_graph_ms"]],
        ["trivial kernel (baseline)", res["trivial_ms"], res["trivial_graph_ms"]],
        ["ratio step / baseline", res["ratio"], res["ratio_graph"]],
    ]
    print(markdown_table(["ms per substep", "plain launches", "captured graph"], rows))
    if args.cold:
        print(f"cold start (empty kernel cache) to first frame: {res['cold_start_s']:.2f} s "
              f"(whole process {res['cold_process_s']:.2f} s)")
    return 0
