"""``warp-cloth bench stability``: where each method stays stable, by a test that cannot be fooled.

A grid over spring stiffness k (1e1 to 1e9 N/m), time step dt (1/2000 to 1/10 s per solver step)
and vertex mass ratio (uniform, and checkerboards of heavy and light vertices with the same total
mass: 100:1 and 10,000:1 by default) for every available method, on the hanging cloth (pinned at
two corners, released at rest: nothing outside does work on it, since the pins do not move and
gravity is part of the potential energy). Each cell runs ``--duration`` simulated seconds and
records every frame's total energy (kinetic + gravity + springs) and largest edge strain. It is
then classified by `classify`, first match wins:

- ``D``: diverged - non-finite positions, or strain above 1000 % (the runner's guard);
- ``E``: gains energy - the total energy rose above its start by more than ``--energy-tol``
  (default 1 %) of ``M g size`` (the energy a drop of its own size releases). The scene has no
  external work, and every method here is meant to be dissipative or conservative, so a rise is a
  numerical defect, however plausible the motion looks;
- ``O``: over-stretched - the largest strain exceeded ``--stretch-factor`` (default 2) times the
  *converged reference's* plus 0.1 % (absolute: an allowance below what shows; at k >= 1e6 N/m
  and large steps Newton's unconverged steps leave 2-9 times the reference's 0.0003-0.03 %,
  which ``--strict`` counts). The reference
  for (k, mass ratio) is implicit Euler with its line search at dt = ``--ref-dt`` (default 1/2000 s)
  and a Newton tolerance of 1e-6 m, over the same duration;
- ``S``: stable - finite, no energy gained, stretch within the factor of the reference.

``--strict`` is the extremes issue's own check, without the two allowances above: a cell gains
energy when any frame's energy exceeds the frame before's by more than `STRICT_RISE` of ``M g
size`` (float32 rounding of the state: about 1e-7 of it), and is over-stretched above the factor
times the reference's strain with no absolute floor.

The letter is followed by the first frame where its test failed (``D12``, ``E3``, ``O5``).
Outputs (``--out-dir``): ``stability.csv`` (with every cell's max strain, energy gain and the
reference strain), ``stability.md`` (one table per method and mass ratio), and with matplotlib
``stability.png``. ``--quick`` is a reduced grid (k 1e1, 1e3, 1e5, 1e7, 1e9; dt 1/2000, 1/120,
1/30; mass ratios 1 and 1e4; 6 x 6 cells; 0.25 s per cell).
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

FULL_K = [1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9]
FULL_DT = [1 / 2000, 1 / 500, 1 / 120, 1 / 30, 1 / 10]
QUICK_K = [1e1, 1e3, 1e5, 1e7, 1e9]
QUICK_DT = [1 / 2000, 1 / 120, 1 / 30]
#: the classes, in the order `classify` tests them
CLASSES = {"D": "diverged", "E": "gains energy", "O": "over-stretched", "S": "stable"}
#: absolute strain added to the reference's times the factor: an allowance below what shows (at
#: very stiff k the excess over twice the reference is Newton's convergence, not float32 noise:
#: `docs/bench/stability_strict.md`; ``--strict`` drops it)
STRETCH_FLOOR = 1e-3
#: ``--strict``: a one-frame energy rise above this share of ``M g size`` counts as a gain
STRICT_RISE = 1e-6
GRAVITY = 9.81


def classify(energies, strains, ref_strain: float, energy_scale: float, *,
             diverged_frame: int | None = None, energy_tol: float = 0.01,
             stretch_factor: float = 2.0, stretch_floor: float = STRETCH_FLOOR,
             rise_tol: float | None = None):
    """Classify one cell from its per-frame records. Returns ``(status, frame)``.

    ``energies[f]`` and ``strains[f]``: total energy (J) and largest edge strain of frame ``f``
    (frame 0 the start) for the frames that ran; ``diverged_frame``: the frame the divergence
    guard stopped the run at, or None. ``energy_scale``: J; a rise of ``energy_tol`` times it
    over the start counts as a gain; with ``rise_tol``, so does any frame's rise over the frame
    before by more than ``rise_tol`` times it (``--strict``: energy never grows). A non-finite
    record counts as divergence at that frame.
    """
    e = np.asarray(energies, dtype=np.float64)
    s = np.asarray(strains, dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(e) | ~np.isfinite(s))
    if diverged_frame is not None or len(bad):
        f = diverged_frame if diverged_frame is not None else int(bad[0])
        if len(bad):
            f = min(f, int(bad[0]))
        return "D", f
    if not (math.isfinite(energy_scale) and energy_scale > 0):
        raise ValueError(f"energy_scale must be > 0 J, got {energy_scale!r}")
    gain = np.flatnonzero(e - e[0] > energy_tol * energy_scale)
    if rise_tol is not None:
        rises = np.flatnonzero(np.diff(e) > rise_tol * energy_scale) + 1
        gain = np.union1d(gain, rises)
    if len(gain):
        return "E", int(gain[0])
    over = np.flatnonzero(s > stretch_factor * ref_strain + stretch_floor)
    if len(over):
        return "O", int(over[0])
    return "S", None


def checker_masses(res: int, density: float, ratio: float, size: float = 1.0):
    """Lumped masses times a checkerboard pattern: heavy = ratio x light, same total mass."""
    from ..mesh import TriMesh

    mesh = TriMesh.grid(res, res, size=size)
    m = mesh.vertex_areas() * density
    i, j = np.meshgrid(np.arange(res + 1), np.arange(res + 1))
    heavy = ((i + j) % 2 == 0).reshape(-1)
    w = np.where(heavy, ratio, 1.0)
    return m * w * (m.sum() / (m * w).sum())


#: implicit Euler with another inner solver, as a method of its own (``--methods``)
IMPLICIT_VARIANTS = {"implicit-jacobi": "jacobi", "implicit-chebyshev": "chebyshev",
                     "implicit-cholesky": "cholesky"}


def split_method(method, solver_options=None):
    """``(solver, options)`` of a map method: ``implicit-jacobi`` is implicit Euler with the
    Jacobi inner solve (``implicit-chebyshev``, ``implicit-cholesky`` with those); others are
    solver names."""
    if method in IMPLICIT_VARIANTS:
        return "implicit", {**(solver_options or {}), "linear": IMPLICIT_VARIANTS[method]}
    return method, solver_options


def simulate(method, k, dt, ratio, res, duration, density=0.15, solver_options=None):
    """Run one cell; per-frame energies and strains, the divergence frame (or None), seconds."""
    method, solver_options = split_method(method, solver_options)
    from ..diagnostics import Meter
    from ..errors import SimulationDiverged
    from ..scenes import build_scene

    substeps = max(1, int(round((1 / 60) / dt)))
    fps = 1.0 / (dt * substeps)
    frames = max(3, int(round(duration * fps)) + 1)
    masses = None if ratio == 1 else checker_masses(res, density, ratio)
    scene = build_scene("hanging", solver=method, res=res, stiffness=k, density=density,
                        masses=masses, fps=fps, frames=frames, substeps=substeps,
                        strain_bound=10.0, solver_options=solver_options, self_collision=False)
    meter = Meter(scene.model)
    energies, strains = [], []

    def on_frame(f, state):
        m = meter(state, energy=True)
        energies.append(m.energy if m.finite else math.nan)
        strains.append(m.max_strain if m.finite else math.nan)

    t0 = time.perf_counter()
    div = None
    try:
        scene.run(None, quiet=True, energy=False, on_frame=on_frame)
    except SimulationDiverged as e:
        div = e.frame
    mass = float(scene.model.masses.sum())
    return energies, strains, div, time.perf_counter() - t0, mass * GRAVITY * 1.0


def reference_strain(k, ratio, res, duration, ref_dt=1 / 2000, density=0.15) -> float:
    """Largest strain of the converged reference: implicit Euler (line search) at ``ref_dt``,
    Newton to 1e-6 m."""
    _, strains, div, _, _ = simulate("implicit", k, ref_dt, ratio, res, duration, density,
                                     solver_options={"tolerance": 1e-6, "newton_iterations": 30})
    if div is not None or not np.all(np.isfinite(strains)):
        raise RuntimeError(f"the stability reference diverged at k={k:g}, ratio={ratio:g}")
    return float(np.max(strains))


def run_cell(method, k, dt, ratio, res, duration, ref_strain, density=0.15, energy_tol=0.01,
             stretch_factor=2.0, strict=False):
    """One cell, classified (`classify`; ``strict``: no stretch floor, no one-frame rise)."""
    energies, strains, div, secs, scale = simulate(method, k, dt, ratio, res, duration, density)
    status, frame = classify(energies, strains, ref_strain, scale, diverged_frame=div,
                             energy_tol=energy_tol, stretch_factor=stretch_factor,
                             stretch_floor=0.0 if strict else STRETCH_FLOOR,
                             rise_tol=STRICT_RISE if strict else None)
    fin = [s for s in strains if math.isfinite(s)]
    efin = [e for e in energies if math.isfinite(e)]
    return {"status": status, "frame": frame, "max_strain": max(fin) if fin else math.nan,
            "energy_gain": (max(efin) - efin[0]) / scale if efin else math.nan,
            "ref_strain": ref_strain, "seconds": secs}


def _crashed_cell(args, msg):
    """A cell whose worker process died: diverged at no known frame (the message on stderr)."""
    print(f"warning: cell {args[:4]}: {msg}", file=sys.stderr)
    return {"status": "D", "frame": None, "max_strain": math.nan, "energy_gain": math.nan,
            "ref_strain": args[6], "seconds": math.nan}


def parallel_cells(methods, ratios, ks, dts, res, duration, refs, energy_tol, stretch_factor,
                   workers, address, strict=False) -> dict:
    """The cells on `warp_cloth.sweep.map_cells` (Ray when installed, else a process pool);
    ``refs[(k, ratio)]``: the converged reference strains (computed first, in this process)."""
    from ..sweep import map_cells

    grid = [(m, k, dt, r) for m in methods for r in ratios for k in ks for dt in dts]
    out = map_cells(run_cell, [(m, k, dt, r, res, duration, refs[(k, r)], 0.15, energy_tol,
                                stretch_factor, strict) for m, k, dt, r in grid],
                    workers=workers, address=address,
                    warm_with=("hanging", sorted({split_method(m)[0] for m in methods})),
                    on_crash=_crashed_cell)
    return dict(zip(grid, out))


def fmt_dt(dt):
    return f"1/{round(1 / dt)}"


def plot(path, cells, methods, ks, dts, ratios):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    cmap = ListedColormap(["#2ca02c", "#ffbf00", "#9467bd", "#d62728"])  # S, O, E, D
    code = {"S": 0, "O": 1, "E": 2, "D": 3}
    fig, axes = plt.subplots(len(ratios), len(methods),
                             figsize=(3.0 * len(methods) + 1, 2.6 * len(ratios) + 0.6), squeeze=False)
    for a, ratio in enumerate(ratios):
        for b, m in enumerate(methods):
            ax = axes[a][b]
            grid = np.array([[code[cells[(m, k, dt, ratio)]["status"]] for dt in dts] for k in ks])
            ax.imshow(grid, cmap=cmap, vmin=0, vmax=3, origin="lower", aspect="auto")
            ax.set_xticks(range(len(dts)), [fmt_dt(d) for d in dts], fontsize=7)
            ax.set_yticks(range(len(ks)), [f"{k:.0e}" for k in ks], fontsize=7)
            ax.set_title(f"{m}, mass ratio {ratio:g}", fontsize=9)
            if b == 0:
                ax.set_ylabel("k [N/m]")
            if a == len(ratios) - 1:
                ax.set_xlabel("dt [s]")
    fig.suptitle("green: stable, amber: over-stretched (vs converged reference), "
                 "purple: gains energy, red: diverged", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="warp-cloth bench stability", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--methods", default=None,
                   help="comma list (default: all available); implicit-jacobi, "
                        "implicit-chebyshev and implicit-cholesky: implicit Euler with that "
                        "inner solve")
    p.add_argument("--res", type=int, default=None, help="cells per side (default 8, quick 6)")
    p.add_argument("--duration", type=float, default=None,
                   help="simulated seconds (default 1, quick 0.25)")
    p.add_argument("--ratios", default=None,
                   help="comma list of heavy/light vertex mass ratios (default 1,100,10000; "
                        "quick 1,10000)")
    p.add_argument("--ks", default=None, help="comma list of stiffnesses in N/m (overrides)")
    p.add_argument("--dts", default=None, help="comma list of steps in s, e.g. 1/2000,1/30")
    p.add_argument("--energy-tol", type=float, default=0.01,
                   help="energy gain allowed, as a fraction of M g size (default 0.01)")
    p.add_argument("--stretch-factor", type=float, default=2.0,
                   help="over-stretched above this times the reference's strain (+0.1 %%)")
    p.add_argument("--ref-dt", type=float, default=1 / 2000, help="reference step (s)")
    p.add_argument("--strict", action="store_true",
                   help="no stretch floor, and any one-frame energy rise (beyond float32 "
                        "rounding) is a gain")
    p.add_argument("--out-dir", default="bench_out")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--device", default=None)
    p.add_argument("--workers", type=int, default=None,
                   help="run the cells in N worker processes (Ray when installed, else a local "
                        "process pool; default: one after another in this process)")
    p.add_argument("--address", default=None, help="run the cells on this Ray cluster")
    args = p.parse_args(argv)
    quiet_warp()
    from ..solvers import available

    avail = available()
    methods = avail if args.methods is None else [m.strip() for m in args.methods.split(",")]
    if "implicit" in avail:
        avail = avail + list(IMPLICIT_VARIANTS)
    bad = [m for m in methods if m not in avail]
    if bad:
        p.error(f"methods {bad} not available; available: {avail}")

    def floats(text, what):
        try:
            out = [float(t.split("/")[0]) / float(t.split("/")[1]) if "/" in t else float(t)
                   for t in text.split(",")]
        except Exception:
            p.error(f"--{what}: a comma list of numbers, got {text!r}")
        if not out or not all(math.isfinite(v) and v > 0 for v in out):
            p.error(f"--{what}: positive numbers, got {text!r}")
        return out

    ratios = floats(args.ratios or ("1,10000" if args.quick else "1,100,10000"), "ratios")
    if not all(r >= 1 for r in ratios):
        p.error("--ratios must be >= 1")
    ks = floats(args.ks, "ks") if args.ks else (QUICK_K if args.quick else FULL_K)
    dts = floats(args.dts, "dts") if args.dts else (QUICK_DT if args.quick else FULL_DT)
    if not (args.energy_tol > 0 and args.stretch_factor >= 1 and args.ref_dt > 0):
        p.error("--energy-tol and --ref-dt must be > 0, --stretch-factor >= 1")
    res = args.res or (6 if args.quick else 8)
    duration = args.duration or (0.25 if args.quick else 1.0)
    os.makedirs(args.out_dir, exist_ok=True)
    tty = sys.stderr.isatty()
    t0 = time.perf_counter()
    refs = {}
    for ratio in ratios:
        for k in ks:
            if tty:
                sys.stderr.write(f"\rreference k={k:.0e} ratio={ratio:g}      ")
                sys.stderr.flush()
            refs[(k, ratio)] = reference_strain(k, ratio, res, duration, args.ref_dt)
    cells = {}
    if args.workers is not None or args.address is not None:
        if args.workers is not None and args.workers < 1:
            p.error("--workers must be positive")
        cells = parallel_cells(methods, ratios, ks, dts, res, duration, refs, args.energy_tol,
                               args.stretch_factor, args.workers, args.address, args.strict)
    total = len(methods) * len(ks) * len(dts) * len(ratios)
    n = 0
    for m in (methods if not cells else ()):
        for ratio in ratios:
            for k in ks:
                for dt in dts:
                    n += 1
                    if tty:
                        sys.stderr.write(f"\r[{n}/{total}] {m} k={k:.0e} dt={fmt_dt(dt)} "
                                         f"ratio={ratio:g}     ")
                        sys.stderr.flush()
                    cells[(m, k, dt, ratio)] = run_cell(m, k, dt, ratio, res, duration,
                                                        refs[(k, ratio)], energy_tol=args.energy_tol,
                                                        stretch_factor=args.stretch_factor,
                                                        strict=args.strict)
    if tty:
        sys.stderr.write("\n")
    rows = [{"method": m, "stiffness": k, "dt": dt, "mass_ratio": r, **c}
            for (m, k, dt, r), c in cells.items()]
    write_csv(os.path.join(args.out_dir, "stability.csv"), rows)
    cmd = (f"warp-cloth bench stability --res {res} --duration {duration:g} --ratios "
           f"{','.join(f'{r:g}' for r in ratios)} --ks {','.join(f'{k:g}' for k in ks)} --dts "
           f"{','.join(fmt_dt(d) for d in dts)}" + (" --quick" if args.quick else "")
           + ("" if args.methods is None else f" --methods {','.join(methods)}")
           + (" --strict" if args.strict else ""))
    floor = 0.0 if args.strict else STRETCH_FLOOR
    gains = (f"any frame's energy above the frame before's by more than {STRICT_RISE:g} of M g "
             f"(1 m), or " if args.strict else "")
    md = [f"# Stability map: hanging cloth, {res}x{res} cells, {duration:g} s per cell\n",
          f"Command: `{cmd}` ({time.perf_counter() - t0:.0f} s on this machine)\n",
          f"S = stable; O<f> = over-stretched: strain above {args.stretch_factor:g} x the "
          f"converged reference's + {100 * floor:g} % from frame f; E<f> = gains energy: {gains}"
          f"total energy above its start by more than {100 * args.energy_tol:g} % of M g (1 m) "
          f"from frame f; D<f> = diverged (non-finite or strain above 1000 %) at frame f. Rows: "
          f"stiffness k [N/m]; columns: dt [s] per solver step; mass ratio = heavy/light "
          f"checkerboard. Reference: implicit Euler at dt = {fmt_dt(args.ref_dt)} s, Newton to "
          f"1e-6 m.\n",
          "\n**Cells per class** (stable / over-stretched / gains energy / diverged)\n",
          "| method | " + " | ".join(f"mass ratio {r:g}" for r in ratios) + " |",
          "|---|" + "---|" * len(ratios)]
    for m in methods:
        counts = []
        for ratio in ratios:
            st = [cells[(m, k, dt, ratio)]["status"] for k in ks for dt in dts]
            counts.append(" / ".join(str(st.count(c)) for c in "SOED"))
        md.append(f"| {m} | " + " | ".join(counts) + " |")
    for ratio in ratios:
        md.append(f"\nReference max strain, mass ratio {ratio:g}: " + ", ".join(
            f"k={k:.0e}: {100 * refs[(k, ratio)]:.3g} %" for k in ks))
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
