"""``warp-cloth bench stability``: where each method stays stable.

A grid over spring stiffness k (1e1 to 1e7 N/m), time step dt (1/2000 to 1/10 s) and vertex
mass ratio (uniform, and a checkerboard of heavy and light vertices with ``--ratio`` = 1000) for
every available method, on the hanging cloth. Each cell runs ``--duration`` simulated seconds
with that dt per solver step and is classified by the solvers' own divergence guard (the scene
runner's `SimulationDiverged`, never a crash):

- ``S``: stable (finite, every edge strain under ``--strain-bound``);
- ``Ofr``: stable but over-stretched (strain above ``--strain-bound``, 10 % by default) from frame fr on;
- ``Dfr``: diverged (non-finite, or strain above 1000 %) at frame fr.

Outputs (``--out-dir``): ``stability.csv``, ``stability.md`` (one table per method and mass
ratio), and with matplotlib ``stability.png`` (heat maps). ``--quick`` is a small grid that
finishes in under two minutes.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np

from ..util import quiet_warp
from .harness import have_matplotlib, write_csv

FULL_K = [1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7]
FULL_DT = [1 / 2000, 1 / 500, 1 / 120, 1 / 30, 1 / 10]
QUICK_K = [1e1, 1e3, 1e5, 1e7]
QUICK_DT = [1 / 2000, 1 / 120, 1 / 10]


def checker_masses(res: int, density: float, ratio: float, size: float = 1.0):
    """Lumped masses times a checkerboard pattern: heavy = ratio x light, same total mass."""
    from ..mesh import TriMesh

    mesh = TriMesh.grid(res, res, size=size)
    m = mesh.vertex_areas() * density
    i, j = np.meshgrid(np.arange(res + 1), np.arange(res + 1))
    heavy = ((i + j) % 2 == 0).reshape(-1)
    w = np.where(heavy, ratio, 1.0)
    return m * w * (m.sum() / (m * w).sum())


def run_cell(method, k, dt, ratio, res, duration, bound, density=0.15):
    from ..errors import SimulationDiverged
    from ..scenes import build_scene

    substeps = max(1, int(round((1 / 60) / dt)))
    fps = 1.0 / (dt * substeps)
    frames = max(3, int(round(duration * fps)) + 1)
    masses = None if ratio == 1 else checker_masses(res, density, ratio)
    scene = build_scene("hanging", solver=method, res=res, stiffness=k, density=density,
                        masses=masses, fps=fps, frames=frames, substeps=substeps, strain_bound=10.0)
    over = [None]

    def on_frame(f, state):
        if over[0] is None and f > 0:
            x = state.x.numpy()
            e = scene.model.mesh.edges
            s = np.abs(np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1) / scene.model.spring_rest[: len(e)] - 1)
            if s.max() > bound:
                over[0] = f

    t0 = time.perf_counter()
    try:
        st = scene.run(None, quiet=True, on_frame=on_frame)
    except SimulationDiverged as e:
        return {"status": "D", "frame": e.frame, "max_strain": e.max_strain, "seconds": time.perf_counter() - t0}
    status = "S" if over[0] is None else "O"
    return {"status": status, "frame": over[0], "max_strain": st.max_strain,
            "seconds": time.perf_counter() - t0}


def _crashed_cell(args, msg):
    """A cell whose worker process died: diverged at no known frame (the message on stderr)."""
    print(f"warning: cell {args[:4]}: {msg}", file=sys.stderr)
    return {"status": "D", "frame": None, "max_strain": math.nan, "seconds": math.nan}


def parallel_cells(methods, ratios, ks, dts, res, duration, bound, workers, address) -> dict:
    """The cells on `warp_cloth.sweep.map_cells` (Ray when installed, else a process pool)."""
    from ..sweep import map_cells

    grid = [(m, k, dt, r) for m in methods for r in ratios for k in ks for dt in dts]
    out = map_cells(run_cell, [(m, k, dt, r, res, duration, bound) for m, k, dt, r in grid],
                    workers=workers, address=address, warm_with=("hanging", methods),
                    on_crash=_crashed_cell)
    return dict(zip(grid, out))


def fmt_dt(dt):
    return f"1/{round(1 / dt)}"


def plot(path, cells, methods, ks, dts, ratios):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    cmap = ListedColormap(["#2ca02c", "#ffbf00", "#d62728"])  # S, O, D
    code = {"S": 0, "O": 1, "D": 2}
    fig, axes = plt.subplots(len(ratios), len(methods), figsize=(3.0 * len(methods) + 1, 2.6 * len(ratios) + 0.6),
                             squeeze=False)
    for a, ratio in enumerate(ratios):
        for b, m in enumerate(methods):
            ax = axes[a][b]
            grid = np.array([[code[cells[(m, k, dt, ratio)]["status"]] for dt in dts] for k in ks])
            ax.imshow(grid, cmap=cmap, vmin=0, vmax=2, origin="lower", aspect="auto")
            ax.set_xticks(range(len(dts)), [fmt_dt(d) for d in dts], fontsize=7)
            ax.set_yticks(range(len(ks)), [f"{k:.0e}" for k in ks], fontsize=7)
            ax.set_title(f"{m}, mass ratio {ratio:g}", fontsize=9)
            if b == 0:
                ax.set_ylabel("k [N/m]")
            if a == len(ratios) - 1:
                ax.set_xlabel("dt [s]")
    fig.suptitle("green: stable, amber: over-stretched, red: diverged", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="warp-cloth bench stability", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--methods", default=None, help="comma list (default: all available)")
    p.add_argument("--res", type=int, default=None, help="cells per side (default 8, quick 6)")
    p.add_argument("--duration", type=float, default=None, help="simulated seconds (default 1, quick 0.25)")
    p.add_argument("--ratio", type=float, default=1000.0, help="heavy/light vertex mass ratio")
    p.add_argument("--strain-bound", type=float, default=0.1, help="over-stretch threshold (0.1 = 10 %%)")
    p.add_argument("--out-dir", default="bench_out")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--workers", type=int, default=None,
                   help="run the cells in N worker processes (Ray when installed, else a local "
                        "process pool; default: one after another in this process)")
    p.add_argument("--address", default=None, help="run the cells on this Ray cluster")
    args = p.parse_args(argv)
    quiet_warp()
    from ..solvers import available

    avail = available()
    methods = avail if args.methods is None else [m.strip() for m in args.methods.split(",")]
    bad = [m for m in methods if m not in avail]
    if bad:
        p.error(f"methods {bad} not available; available: {avail}")
    if not (args.ratio >= 1):
        p.error("--ratio must be >= 1")
    res = args.res or (6 if args.quick else 8)
    duration = args.duration or (0.25 if args.quick else 1.0)
    ks, dts = (QUICK_K, QUICK_DT) if args.quick else (FULL_K, FULL_DT)
    ratios = [1.0, args.ratio]
    os.makedirs(args.out_dir, exist_ok=True)
    t0 = time.perf_counter()
    cells = {}
    if args.workers is not None or args.address is not None:
        if args.workers is not None and args.workers < 1:
            p.error("--workers must be positive")
        cells = parallel_cells(methods, ratios, ks, dts, res, duration, args.strain_bound,
                               args.workers, args.address)
    total = len(methods) * len(ks) * len(dts) * len(ratios)
    n = 0
    for m in (methods if not cells else ()):
        for ratio in ratios:
            for k in ks:
                for dt in dts:
                    n += 1
                    if sys.stderr.isatty():
                        sys.stderr.write(f"\r[{n}/{total}] {m} k={k:.0e} dt={fmt_dt(dt)} ratio={ratio:g}     ")
                        sys.stderr.flush()
                    cells[(m, k, dt, ratio)] = run_cell(m, k, dt, ratio, res, duration, args.strain_bound)
    if sys.stderr.isatty():
        sys.stderr.write("\n")
    rows = [{"method": m, "stiffness": k, "dt": dt, "mass_ratio": r, **c} for (m, k, dt, r), c in cells.items()]
    write_csv(os.path.join(args.out_dir, "stability.csv"), rows)
    md = [f"# Stability map: hanging cloth, {res}x{res} cells, {duration:g} s per cell\n",
          f"Command: `warp-cloth bench stability --res {res} --duration {duration:g} --ratio {args.ratio:g} "
          f"--strain-bound {args.strain_bound:g}{' --quick' if args.quick else ''}`\n",
          f"S = stable; O<f> = stable but strain above {100 * args.strain_bound:g} % from frame f; "
          f"D<f> = diverged (non-finite or strain above 1000 %) at frame f. Rows: stiffness k [N/m]; "
          f"columns: dt [s] per solver step; mass ratio = heavy/light checkerboard.\n"]
    for m in methods:
        for ratio in ratios:
            md.append(f"\n**{m}**, mass ratio {ratio:g}\n")
            md.append("| k \\ dt | " + " | ".join(fmt_dt(d) for d in dts) + " |")
            md.append("|---|" + "---|" * len(dts))
            for k in ks:
                cs = [cells[(m, k, dt, ratio)] for dt in dts]
                md.append(f"| {k:.0e} | " + " | ".join(
                    c["status"] + ("" if c["frame"] is None else str(c["frame"])) for c in cs) + " |")
    text = "\n".join(md) + "\n"
    with open(os.path.join(args.out_dir, "stability.md"), "w") as fh:
        fh.write(text)
    print(text)
    if have_matplotlib():
        plot(os.path.join(args.out_dir, "stability.png"), cells, methods, ks, dts, ratios)
    print(f"wrote {args.out_dir}/stability.csv, stability.md"
          + (", stability.png" if have_matplotlib() else "") + f" in {time.perf_counter() - t0:.1f} s",
          file=sys.stderr)
    return 0
