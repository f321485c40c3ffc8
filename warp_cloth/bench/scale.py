"""``warp-cloth bench scale``: how build, set-up, stepping and memory grow with the mesh.

For square hanging cloths of 1,024 to 262,144 vertices (grids of 31 x 31 to 511 x 511 cells,
the vertex count doubling twice per size) and every solver it measures:

- **build** (s): `TriMesh.grid` plus `ClothModel` (topology, springs, masses, device arrays);
- **set-up** (s): the solver's constructor plus ``prepare(dt)`` where it has one (PD's constant
  matrix and its Chebyshev ``rho``, measured by 200 Jacobi sweeps: the work of one PD substep);
- **substep** (ms): a captured Warp graph of ``--substeps`` substeps replayed (median of
  ``--repeats``) divided by the substeps; on a device without graph capture, plain launches;
- **memory** (bytes per vertex): the bytes of every device array the model and the solver hold
  (found by walking their attributes), divided by the vertices.

Every solver does a fixed amount of work per substep, so the time per substep shows the cost per
vertex and not the convergence of an iterative method (which slows with resolution at a fixed
tolerance): explicit (symplectic Euler at half its stable step), implicit with 1 Newton iteration of 20 CG iterations
(``tolerance=None``, the cheapest ``bench tradeoff`` configuration), PBD with 10 Jacobi iterations
(``pbd``) and 10 Gauss-Seidel iterations over the colours (``pbd-gs``), PD with 10 iterations of
20 Chebyshev iterations (the defaults).

Prints a table per solver and the log-log slope (least squares over all sizes) of each quantity
against the vertex count: 1 is linear. Targets (issue 16): build and set-up of the 256k-vertex
cloth under 2 s each, and a substep slope of at most 1.1 for every solver. Writes
``scale.csv``, ``scale.md`` and, when matplotlib is installed, ``scale.png`` (log-log) into
``--out-dir``; without matplotlib it says so and writes the table and CSV only.
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np
import warp as wp

from ..util import quiet_warp
from .common import capture, markdown_table, time_callable
from .harness import have_matplotlib, write_csv

#: solver label -> (registry name, options)
SOLVERS = {
    "explicit": ("explicit", {}),
    "implicit": ("implicit", {"newton_iterations": 1, "linear": "cg", "linear_iterations": 20,
                              "tolerance": None, "linear_tolerance": None}),
    "pbd": ("pbd", {"iterations": 10}),
    "pbd-gs": ("pbd", {"iterations": 10, "gauss_seidel": True}),
    "pd": ("pd", {"iterations": 10, "linear": "chebyshev", "linear_iterations": 20}),
}

#: cells per side: (n + 1)^2 vertices = 1k, 4k, 16k, 64k, 256k
SIDES = (31, 63, 127, 255, 511)


def device_bytes(*objects) -> int:
    """Bytes of the distinct Warp arrays reachable from ``objects`` through attributes, lists,
    tuples and dicts (a view counts as its own extent; arrays sharing a pointer count once)."""
    seen_obj, seen_ptr, total = set(), set(), 0
    stack = list(objects)
    while stack:
        o = stack.pop()
        if id(o) in seen_obj:
            continue
        seen_obj.add(id(o))
        if isinstance(o, wp.array):
            key = (o.ptr, o.device.alias)
            if o.ptr is not None and key not in seen_ptr:
                seen_ptr.add(key)
                total += int(o.capacity or 0)
            continue
        if isinstance(o, (list, tuple, set)):
            stack.extend(o)
        elif isinstance(o, dict):
            stack.extend(o.values())
        elif hasattr(o, "__dict__") and type(o).__module__.startswith("warp_cloth"):
            stack.extend(vars(o).values())
    return total


def loglog_slope(x, y) -> float:
    """Least-squares slope of log(y) against log(x) (nan with fewer than two positive points)."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    ok = (x > 0) & (y > 0) & np.isfinite(y)
    if ok.sum() < 2:
        return float("nan")
    return float(np.polyfit(np.log(x[ok]), np.log(y[ok]), 1)[0])


def measure(side: int, label: str, substeps: int, repeats: int, device=None) -> dict:
    """One size, one solver: build, set-up, substep and memory (see the module docstring)."""
    from ..scenes import hanging_model
    from ..solvers import make_solver

    name, opts = SOLVERS[label]
    t0 = time.perf_counter()
    model = hanging_model(shape=(side, side), device=device)
    build = time.perf_counter() - t0
    if name == "explicit":  # its stable step shrinks with the cell size
        from ..solvers.explicit import SymplecticEuler

        dt = 0.5 * SymplecticEuler.stable_dt(model)
    else:
        dt = 1.0 / 60.0 / (16 if name == "pbd" else 4)
    wp.synchronize_device(model.device)
    t0 = time.perf_counter()
    solver = make_solver(name, model, **opts)
    if hasattr(solver, "prepare"):
        solver.prepare(dt)
    wp.synchronize_device(model.device)
    setup = time.perf_counter() - t0
    state = model.state()

    def steps():
        for _ in range(substeps):
            solver.step(state, dt)

    steps()  # compile, warm up (and any first-step host work)
    dev = model.device
    if solver.capturable:
        graph = capture(steps, dev)
        run = lambda: wp.capture_launch(graph)  # noqa: E731
        how = "graph"
    else:
        run, how = steps, "launches"
    per = time_callable(run, repeats, dev) / substeps
    finite = bool(np.isfinite(state.x.numpy()).all())
    mem = device_bytes(model, solver, state)
    return {"solver": label, "cells": side, "vertices": model.num_vertices,
            "springs": model.num_springs, "build_s": build, "setup_s": setup,
            "substep_ms": 1e3 * per, "bytes_per_vertex": mem / model.num_vertices,
            "replay": how, "finite": finite}


def plot(rows, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2))
    keys = [("build_s", "build (s)"), ("setup_s", "set-up (s)"), ("substep_ms", "ms per substep")]
    labels = list(dict.fromkeys(r["solver"] for r in rows))
    for ax, (key, title) in zip(axes, keys):
        for lab in labels:
            rs = [r for r in rows if r["solver"] == lab]
            v = [r["vertices"] for r in rs]
            ax.loglog(v, [r[key] for r in rs], "o-", label=f"{lab} (slope "
                      f"{loglog_slope(v, [r[key] for r in rs]):.2f})")
        v = np.array(sorted({r["vertices"] for r in rows}), dtype=float)
        ref = np.median([r[key] for r in rows if r["vertices"] == v[0]])
        ax.loglog(v, ref * v / v[0], "k:", lw=1, label="linear")
        ax.set_xlabel("vertices")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="warp-cloth bench scale", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--solvers", nargs="+", default=list(SOLVERS), choices=list(SOLVERS))
    p.add_argument("--sides", type=int, nargs="+", default=list(SIDES), metavar="N",
                   help="grid cells per side ((N+1)^2 vertices); default: 1k to 256k vertices")
    p.add_argument("--max-vertices", type=int, default=None,
                   help="skip sizes above this many vertices (a quicker run)")
    p.add_argument("--substeps", type=int, default=4, help="substeps per captured graph")
    p.add_argument("--repeats", type=int, default=3, help="timed replays (median)")
    p.add_argument("--device", default=None)
    p.add_argument("--out-dir", default=".", help="where scale.csv / .md / .png go")
    args = p.parse_args(argv)
    if args.substeps < 1 or args.repeats < 1 or any(s < 1 for s in args.sides):
        p.error("--substeps, --repeats and --sides must be positive")
    sides = sorted(s for s in args.sides
                   if args.max_vertices is None or (s + 1) ** 2 <= args.max_vertices)
    if not sides:
        p.error("no size left under --max-vertices")
    quiet_warp()
    os.makedirs(args.out_dir, exist_ok=True)
    rows = []
    for label in args.solvers:
        measure(min(sides[0], 7), label, 1, 1, args.device)  # load the solver's modules (untimed)
        for side in sides:
            r = measure(side, label, args.substeps, args.repeats, args.device)
            rows.append(r)
            print(f"  {label:8s} {r['vertices']:7d} vertices: build {r['build_s']:.3f} s, set-up "
                  f"{r['setup_s']:.3f} s, {r['substep_ms']:.3f} ms/substep, "
                  f"{r['bytes_per_vertex']:.0f} B/vertex", flush=True)
    headers = ["solver", "vertices", "build s", "set-up s", "ms/substep", "us/vertex/substep",
               "bytes/vertex", "finite"]
    table = [[r["solver"], r["vertices"], r["build_s"], r["setup_s"], r["substep_ms"],
              1e3 * r["substep_ms"] / r["vertices"], r["bytes_per_vertex"], r["finite"]]
             for r in rows]
    slopes = []
    for label in args.solvers:
        rs = [r for r in rows if r["solver"] == label]
        v = [r["vertices"] for r in rs]
        slopes.append([label] + [loglog_slope(v, [r[k] for r in rs])
                                 for k in ("build_s", "setup_s", "substep_ms", "bytes_per_vertex")])
    big = max(r["vertices"] for r in rows)
    text = [f"device {wp.get_device(args.device)}; {args.substeps} substeps per graph, median of "
            f"{args.repeats} replays", "", markdown_table(headers, table), "",
            f"log-log slopes from {min(r['vertices'] for r in rows)} to {big} vertices "
            "(1 = linear):", "",
            markdown_table(["solver", "build", "set-up", "substep", "bytes/vertex"], slopes)]
    at_big = [r for r in rows if r["vertices"] == big]
    if at_big:
        b = sorted(r["build_s"] for r in at_big)
        text += ["", f"at {big} vertices: build {b[0]:.2f} s best, {b[len(b) // 2]:.2f} s median "
                 f"of the {len(b)} builds (one per solver; the spread is the machine's load); "
                 "set-up " + ", ".join(f"{r['solver']} {r['setup_s']:.2f} s" for r in at_big)]
    out = "\n".join(text)
    print(out)
    write_csv(os.path.join(args.out_dir, "scale.csv"), rows)
    with open(os.path.join(args.out_dir, "scale.md"), "w") as fh:
        fh.write(out + "\n")
    if have_matplotlib():
        plot(rows, os.path.join(args.out_dir, "scale.png"))
        print(f"wrote scale.csv, scale.md, scale.png in {args.out_dir}")
    else:
        print(f"wrote scale.csv, scale.md in {args.out_dir} (no plot: matplotlib is not installed)")
    bad = [r for r in rows if not r["finite"]]
    if bad:
        print(f"{len(bad)} run(s) ended with non-finite positions")
    return 0 if not bad and all(math.isfinite(s[3]) or len(sides) < 2 for s in slopes) else 1
