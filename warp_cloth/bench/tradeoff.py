"""``warp-cloth bench tradeoff``: what each method buys in accuracy for its cost.

For a scene (``hanging``, or ``drape`` when contact is installed) it runs a ladder of
configurations of every available method and measures, per configuration:

- wall time per simulated second (kernel compile excluded, median of ``--repeats`` runs);
- position error against a reference trajectory, RMS and max over the vertices at fixed sample
  times (every 0.25 s), relative to the cloth size;
- maximum edge strain, energy drift ``(E_end - E_0) / |E_0|``, and whether it diverged.

The scene has quadratic bending (1e-3 N m by default): without any bending stiffness the
falling sheet buckles chaotically after about 0.6 s (runs that differ only in rounding drift
apart by 2 % of the cloth size), and no reference can then be validated; 1e-3 N m keeps such
runs within 6e-4 over 1 s (measured with explicit runs at 186, 372 and 744 substeps per frame).

The reference is implicit Euler (Newton and CG to their float32 floor) at ``--ref-substeps``,
twice and four times as many steps per frame, Richardson-extrapolated to second order (implicit
Euler alone is first order), cached on disk (``$WARP_CLOTH_CACHE`` or ``~/.cache/warp_cloth``)
keyed by all scene parameters. It is validated by the change between the extrapolations from
(s, 2s) and (2s, 4s) steps per frame, i.e. when the step is halved: that change is printed and
must be smaller than the errors it measures.

Outputs (in ``--out-dir``): ``tradeoff_<scene>.csv``, ``tradeoff_<scene>.md`` (table, Pareto
frontier marked) and, with matplotlib installed, ``tradeoff_<scene>.png`` (error against time per
simulated second, log-log, one point per configuration coloured by method, frontier joined).
``--quick`` is a small smoke version that finishes in under two minutes.

``--workers N`` (or ``--address ADDR``, a Ray cluster) runs the configurations through the sweep
executor (`warp_cloth.sweep.map_cells`: Ray when installed or an address is given, else a local
pool of N spawned processes); the reference is computed first, once, in this process and handed
to every cell, and the rows come back in the sequential order. Cells that run at the same time
share the machine, so their wall times are noisier and each is slower than it would be alone:
the output says how many workers measured them. Ratios between rows of one such run stay roughly
comparable; absolute times, or times compared with a sequential run, less so. Without either
option the configurations run one after another in this process, each timed alone.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np

from ..util import quiet_warp
from .common import markdown_table
from .harness import (METHOD_COLOURS, Config, Result, have_matplotlib, pareto, reference,
                      run_config, write_csv)


def ladder(methods, base_substeps: int, stiffness: float, quick: bool):
    """The configurations per method (see module docstring)."""
    out = []
    s0 = max(1, base_substeps)
    lim = (0.0, 1.01)
    if "explicit" in methods:
        for f in ((1, 2) if quick else (0.5, 1, 2, 4)):
            out.append(Config("explicit", {}, substeps=max(1, int(round(s0 * f)))))
    if "implicit" in methods:
        grid = [(1, "cg", 20, 1), (3, "cg", 40, 1)] if quick else [
            (1, "cg", 20, 1), (1, "cg", 20, 4), (3, "cg", 40, 1), (3, "cg", 40, 4),
            (10, "cg", 100, 1), (1, "chebyshev", 40, 1), (3, "chebyshev", 80, 1),
            (1, "jacobi", 40, 1), (3, "jacobi", 160, 1)]
        for newton, lin, inner, sub in grid:
            out.append(Config("implicit", {"newton_iterations": newton, "linear": lin,
                                           "linear_iterations": inner, "tolerance": None,
                                           "linear_tolerance": None}, substeps=sub))
        out.append(Config("implicit", {"newton_iterations": 1, "linear": "cg", "linear_iterations": 20,
                                       "tolerance": None, "linear_tolerance": None},
                          substeps=1, strain_limit=lim))
        if not quick:  # Baraff-Witkin with the smoothing sweeps (off for it by default)
            out.append(Config("implicit", {"newton_iterations": 1, "linear": "cg",
                                           "linear_iterations": 20, "tolerance": None,
                                           "linear_tolerance": None, "smoothing_sweeps": 4},
                              substeps=1))
    if "pbd" in methods:
        grid = [(10, 1, None), (10, 4, None)] if quick else [
            (5, 1, None), (10, 1, None), (20, 1, None), (40, 1, None), (10, 4, None), (20, 4, None),
            (10, 1, 1.0 / stiffness), (20, 4, 1.0 / stiffness)]
        for it, sub, comp in grid:
            opts = {"iterations": it}
            if comp is not None:
                opts["compliance"] = comp
            out.append(Config("pbd", opts, substeps=sub))
        out.append(Config("pbd", {"iterations": 10}, substeps=1, strain_limit=lim))
    if "pd" in methods:
        grid = [(10, "chebyshev", 1), (10, "cg", 1), (10, "cholesky", 1)] if quick else [
            (5, "chebyshev", 1), (10, "chebyshev", 1), (20, "chebyshev", 1), (40, "chebyshev", 1),
            (10, "chebyshev", 4), (10, "cg", 1), (10, "jacobi", 1), (10, "cholesky", 1),
            (20, "cholesky", 1), (10, "cholesky", 4)]
        for it, lin, sub in grid:
            out.append(Config("pd", {"iterations": it, "linear": lin}, substeps=sub))
        out.append(Config("pd", {"iterations": 10, "linear": "chebyshev"}, substeps=1, strain_limit=lim))
        if not quick:  # with the smoothing sweeps (an option for PD)
            for sub in (1, 4):
                out.append(Config("pd", {"iterations": 10, "linear": "chebyshev",
                                         "smoothing_sweeps": 4}, substeps=sub))
    return out


def _crashed_cell(args, msg):
    """A configuration whose worker process died: a diverged row at no known frame (shown as
    ``crashed`` in the table), with the message on stderr."""
    cfg = args[2]
    print(f"warning: configuration {cfg.label}: {msg}; reported as crashed", file=sys.stderr)
    return Result(cfg, True, None, math.nan, math.nan, math.nan, math.nan, math.nan)


def parallel_cells(scene, params, configs, frames, fps, sample, ref_positions, size, repeats,
                   workers, address, on_done=None) -> list:
    """`run_config` for every configuration on `warp_cloth.sweep.map_cells` (Ray when installed,
    else a process pool), against ``ref_positions`` (computed once, by the caller). Results in
    the order of ``configs``."""
    from ..sweep import map_cells

    cells = [(scene, params, cfg, frames, fps, sample, ref_positions, size, repeats)
             for cfg in configs]
    methods = list(dict.fromkeys(cfg.method for cfg in configs))
    return map_cells(run_config, cells, workers=workers, address=address,
                     warm_with=(scene, methods), on_crash=_crashed_cell, on_done=on_done)


def concurrency_note(workers, address, cells: int) -> str:
    """The line that says the timings were measured with cells running concurrently."""
    from ..sweep import resolve_executor

    executor, address = resolve_executor("auto", address)
    if address:
        how = f"cells running concurrently on the Ray cluster {address}"
    else:
        n = min(int(workers or max(1, os.cpu_count() or 1)), cells)
        how = f"{n} concurrent workers ({'local Ray' if executor == 'ray' else 'process pool'})"
    return (f"Timings measured with {how}: concurrent cells share the machine, so ratios "
            f"between rows of this table are still roughly comparable, absolute times (and "
            f"comparisons with a sequential run) less so.")


def plot(path, results, front, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 5))
    seen = set()
    for r in results:
        if r.diverged:
            continue
        m = r.config.method
        ax.scatter(r.wall_per_sim_s, max(r.rms_error, 1e-7), c=METHOD_COLOURS.get(m, "k"),
                   marker="s" if r.config.strain_limit else "o", s=36, alpha=0.8,
                   label=m if m not in seen else None)
        seen.add(m)
    fx = [results[i].wall_per_sim_s for i in front]
    fy = [max(results[i].rms_error, 1e-7) for i in front]
    ax.plot(fx, fy, "k--", lw=1, label="Pareto frontier")
    ax.scatter(fx, fy, facecolors="none", edgecolors="k", s=110, lw=1.2)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time per simulated second [s] (compile excluded)")
    ax.set_ylabel("RMS position error / cloth size")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, title="square: with strain limit", title_fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="warp-cloth bench tradeoff", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", default="hanging", choices=["hanging", "drape"])
    p.add_argument("--res", type=int, default=None, help="cells per side (default 16, quick 8)")
    p.add_argument("--duration", type=float, default=None, help="simulated seconds (default 1, quick 0.5)")
    p.add_argument("--fps", type=float, default=60.0)
    p.add_argument("--stiffness", type=float, default=1000.0)
    p.add_argument("--bending", default="quadratic", choices=["none", "springs", "dihedral", "quadratic"])
    p.add_argument("--bend-stiffness", type=float, default=1e-3, help="N m (N/m for springs)")
    p.add_argument("--repeats", type=int, default=None, help="timing repeats (default 3, quick 1)")
    p.add_argument("--ref-substeps", type=int, default=None, help="reference steps per frame (default 32, quick 16)")
    p.add_argument("--methods", default=None, help="comma list (default: all available)")
    p.add_argument("--out-dir", default="bench_out")
    p.add_argument("--quick", action="store_true", help="small smoke run, under two minutes")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--workers", type=int, default=None,
                   help="run the configurations in N worker processes (Ray when installed, else a "
                        "local process pool; default: one after another in this process). "
                        "Concurrent cells share the machine: their timings are noisier and slower "
                        "than alone (ratios between rows stay roughly comparable, absolute times "
                        "less so); the output says how many workers measured them")
    p.add_argument("--address", default=None,
                   help="run the configurations on this Ray cluster (timings as with --workers)")
    args = p.parse_args(argv)
    if args.workers is not None and args.workers < 1:
        p.error(f"--workers must be a positive integer, got {args.workers}")
    quiet_warp()
    from ..solvers import available
    from ..solvers.explicit import SymplecticEuler
    from ..scenes import hanging_model

    res = args.res or (8 if args.quick else 16)
    duration = args.duration or (0.5 if args.quick else 1.0)
    repeats = args.repeats or (1 if args.quick else 3)
    ref_sub = args.ref_substeps or (16 if args.quick else 32)
    if res < 2 or duration <= 0 or repeats < 1 or ref_sub < 1 or not (args.fps > 0):
        p.error("--res >= 2, --duration > 0, --repeats >= 1, --ref-substeps >= 1, --fps > 0")
    avail = available()
    methods = avail if args.methods is None else [m.strip() for m in args.methods.split(",")]
    bad = [m for m in methods if m not in avail]
    if bad:
        p.error(f"methods {bad} not available; available: {avail}")
    if "implicit" not in avail:
        p.error("the reference needs the implicit solver, which is not available")
    os.makedirs(args.out_dir, exist_ok=True)

    frames = int(round(duration * args.fps)) + 1
    step = max(1, int(round(0.25 * args.fps)))
    sample = list(range(step, frames, step))
    if (frames - 1) not in sample:
        sample.append(frames - 1)
    params = {"res": res, "stiffness": args.stiffness, "bending": args.bending,
              "bend_stiffness": args.bend_stiffness}
    size = hanging_model(res=res).mesh.extent() if args.scene == "hanging" else 1.0
    base = max(1, math.ceil((1 / args.fps) / (0.5 * SymplecticEuler.stable_dt(hanging_model(res=res, stiffness=args.stiffness)))))

    log = (lambda *a: None) if args.no_progress else (lambda *a: print(*a, file=sys.stderr))
    t0 = time.perf_counter()
    ref = reference(args.scene, params, frames, args.fps, sample, ref_sub, validate=True, log=log)
    configs = ladder(methods, base, args.stiffness, args.quick)

    def progress(k, cfg):
        if not args.no_progress and sys.stderr.isatty():
            sys.stderr.write(f"\r[{k + 1}/{len(configs)}] {cfg.label:<70.70}")
            sys.stderr.flush()
        elif not args.no_progress:
            log(f"[{k + 1}/{len(configs)}] {cfg.label}")

    parallel = args.workers is not None or args.address is not None
    if parallel:
        finished = []

        def on_done(i, res):
            finished.append(i)
            progress(len(finished) - 1, configs[i])

        results = parallel_cells(args.scene, params, configs, frames, args.fps, sample,
                                 ref["positions"], size, repeats, args.workers, args.address,
                                 on_done=on_done)
    else:
        results = []
        for k, cfg in enumerate(configs):
            progress(k, cfg)
            results.append(run_config(args.scene, params, cfg, frames, args.fps, sample,
                                      ref["positions"], size, repeats))
    if not args.no_progress and sys.stderr.isatty():
        sys.stderr.write("\n")
    front = pareto(results)

    stem = os.path.join(args.out_dir, f"tradeoff_{args.scene}")
    rows = [dict(r.row(), pareto=(i in front)) for i, r in enumerate(results)]
    write_csv(stem + ".csv", rows)
    hdr = ["", "method", "configuration", "wall s / sim s", "RMS err", "max err", "max strain", "energy drift", "diverged"]
    table = []
    for i, r in enumerate(results):
        table.append(["*" if i in front else "", r.config.method, r.config.label, r.wall_per_sim_s,
                      r.rms_error, r.max_error, r.max_strain, r.energy_drift,
                      ("crashed" if r.diverged_frame is None else f"frame {r.diverged_frame}")
                      if r.diverged else "no"])
    min_err = min((r.rms_error for r in results if not r.diverged), default=math.nan)
    head = (
        f"# Speed/accuracy trade-off: {args.scene}\n\n"
        f"Command: `warp-cloth bench tradeoff --scene {args.scene} --res {res} --duration {duration:g} "
        f"--fps {args.fps:g} --stiffness {args.stiffness:g} --bending {args.bending} "
        f"--bend-stiffness {args.bend_stiffness:g} --repeats {repeats} --ref-substeps {ref_sub}"
        f"{' --quick' if args.quick else ''}"
        f"{f' --workers {args.workers}' if args.workers is not None else ''}"
        f"{f' --address {args.address}' if args.address is not None else ''}`\n\n"
        f"{(res + 1) ** 2 if args.scene == 'hanging' else ''} vertices, {duration:g} s simulated at "
        f"{args.fps:g} fps; errors at t = {', '.join(f'{f / args.fps:.2f}' for f in sample)} s, relative to "
        f"the cloth size {size:g} m. Reference: implicit Euler at {ref_sub}, {2 * ref_sub} and {4 * ref_sub} "
        f"steps per frame, Richardson-extrapolated; halving its step changes it by {float(ref['halving_rms']):.2e} RMS "
        f"({float(ref['halving_max']):.2e} max), "
        f"{'below' if float(ref['halving_rms']) < min_err else 'NOT below'} the smallest RMS error measured "
        f"({min_err:.2e}). `*` = Pareto frontier (nothing else is both faster and more accurate).\n\n")
    if parallel:
        head += concurrency_note(args.workers, args.address, len(configs)) + "\n\n"
    md = head + markdown_table(hdr, table) + "\n"
    with open(stem + ".md", "w") as fh:
        fh.write(md)
    print(md)
    if have_matplotlib():
        plot(stem + ".png", results, front,
             f"{args.scene}: {res}x{res} cells, {duration:g} s at {args.fps:g} fps, k={args.stiffness:g} N/m, "
             f"{args.bending} bending {args.bend_stiffness:g}")
        print(f"wrote {stem}.csv, {stem}.md, {stem}.png")
    else:
        print(f"wrote {stem}.csv, {stem}.md (install matplotlib for the plot)")
    print(f"total {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return 0
