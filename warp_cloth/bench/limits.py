"""``warp-cloth bench limits``: does ``StrainLimit(model, 0, 1.01)`` hold, and at what cost?

The scene is Newton's ``cloth_hanging`` example built with our public API
(`newton_cloth_hanging`): a 64 x 32-cell sheet of 0.1 m cells (6.4 x 3.2 m), 0.1 kg a vertex,
horizontal 4 m above a ground plane (friction 0.4), the 33 vertices of one short edge pinned,
1000 N/m springs on the mesh edges, 60 frames per second. It falls, swings down and lands on
the ground. Each configuration (a solver, its substeps and options) runs ``--frames`` frames
with the limit, and, with ``--unlimited``, once without. The table gives, per configuration:
the largest edge strain over all frames (the limit's promise: at most 1 % + its tolerance,
0.1 %), the frame rate (ms a frame over the timed frames, replayed as a graph when the step is
capturable), the limit's sweeps a step (mean and most) and its steps that stopped short.

Newton's own fastest CPU path there (XPBD, 10 substeps of 10 iterations) was measured at
146 ms a frame with 47 % max strain; the issue's target is a limited method at 60 frames per
second (16.7 ms a frame) on this CPU. Times depend on the machine and its load: compare the
rows of one run.

``--scenes hanging,drape,...`` runs the limit on built-in scenes instead (`build_scene`, every
solver at its defaults): max strain over all frames, the limit's sweeps and short steps, per
scene and solver.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from ..util import quiet_warp

#: (label, solver, substeps or None for the solver's default, solver options)
CONFIGS = [
    ("explicit", "explicit", None, {}),
    ("implicit", "implicit", None, {}),
    ("implicit 1 step, 2 Newton, captured", "implicit", 1,
     {"newton_iterations": 2, "tolerance": None, "linear_tolerance": None}),
    ("pbd", "pbd", None, {}),
    ("pbd 4 substeps", "pbd", 4, {}),
    ("pbd 1 substep", "pbd", 1, {}),
    ("pbd 1 substep, 3 iterations", "pbd", 1, {"iterations": 3}),
    ("pd", "pd", None, {}),
    ("pd 1 step", "pd", 1, {}),
]


def newton_cloth_hanging(*, solver: str = "explicit", solver_options: dict | None = None,
                         corrections=(), frames: int = 120, substeps=None, friction: float = 0.4,
                         device=None):
    """Newton's ``cloth_hanging`` scene (see the module docstring) as a `Scene`.

    ``corrections``: factories ``model -> correction`` (or corrections) added to the solver."""
    from ..collision import Plane
    from ..mesh import TriMesh
    from ..model import ClothModel
    from ..scene import Scene
    from ..solvers import make_solver

    nx, ny = 64, 32
    mesh = TriMesh.grid(nx, ny, size=(0.1 * nx, 0.1 * ny), plane="xz",
                        origin=(0.0, 4.0, -0.05 * ny), name="cloth")
    pins = [j * (nx + 1) for j in range(ny + 1)]  # the short edge x = 0
    model = ClothModel(mesh, masses=np.full(len(mesh.vertices), 0.1), stretch_stiffness=1e3,
                       pins=pins, device=device)
    s = make_solver(solver, model, **(solver_options or {}))
    for c in corrections:
        s.add_correction(c if hasattr(c, "apply") else c(model))
    return Scene(model, s, fps=60.0, frames=frames, substeps=substeps,
                 obstacles=[Plane(point=(0.0, 0.0, 0.0), friction=friction)],
                 strain_bound=100.0, name="cloth_hanging")


def run_one(solver, substeps, options, frames, limit: bool):
    from ..limits import StrainLimit

    lim = []

    def make(model):
        lim.append(StrainLimit(model, 0.0, 1.01))
        return lim[-1]

    scene = newton_cloth_hanging(solver=solver, solver_options=options, substeps=substeps,
                                 frames=frames, corrections=[make] if limit else [])
    t0 = time.perf_counter()
    st = scene.run(None, quiet=True, energy=False)
    row = {"max_strain": st.max_strain, "ms_per_frame": st.ms_per_frame,
           "substeps": scene.substeps, "captured": st.captured, "wall_s": time.perf_counter() - t0,
           "short_frames": st.short_frames}
    if lim:
        ls = lim[0].stats
        row.update(sweeps_mean=ls["sweeps_total"] / max(ls["steps"], 1),
                   sweeps_max=ls["sweeps_max"], short_steps=ls["short_steps"])
    return row


def run_scene(scene, solver, frames):
    """The built-in ``scene`` with ``solver`` at its defaults under ``StrainLimit(0, 1.01)``."""
    from ..limits import StrainLimit
    from ..scenes import build_scene

    lim = []

    def make(model):
        lim.append(StrainLimit(model, 0.0, 1.01))
        return lim[-1]

    st = build_scene(scene, solver=solver, frames=frames, corrections=[make],
                     self_collision=False).run(
        None, quiet=True, energy=False)
    ls = lim[0].stats
    return {"max_strain": st.max_strain, "ms_per_frame": st.ms_per_frame,
            "sweeps_mean": ls["sweeps_total"] / max(ls["steps"], 1),
            "sweeps_max": ls["sweeps_max"], "short_steps": ls["short_steps"]}


def scenes_table(scenes, frames) -> list:
    lines = [f"# StrainLimit(0, 1.01) on built-in scenes, every solver at its defaults, "
             f"{frames} frames\n",
             "| scene | solver | max strain % | short steps | sweeps/step (mean, max) | ms/frame |",
             "|---|---|---|---|---|---|"]
    for scene in scenes:
        for solver in ("explicit", "implicit", "pbd", "pd"):
            r = run_scene(scene, solver, frames)
            lines.append(f"| {scene} | {solver} | {100 * r['max_strain']:.3f} | "
                         f"{r['short_steps']} | {r['sweeps_mean']:.1f}, {r['sweeps_max']} | "
                         f"{r['ms_per_frame']:.1f} |")
            print(lines[-1], file=sys.stderr)
    return lines


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="warp-cloth bench limits", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=120, help="frames per run (default 120: 2 s)")
    p.add_argument("--configs", default=None,
                   help="comma list of row numbers (0-based) of the configurations to run")
    p.add_argument("--unlimited", action="store_true",
                   help="also run each configuration without the limit")
    p.add_argument("--scenes", default=None,
                   help="comma list of built-in scenes (hanging, drape, table, spin, mesh, ...) "
                        "to run with every solver instead of the cloth_hanging configurations")
    p.add_argument("--device", default=None)
    args = p.parse_args(argv)
    quiet_warp()
    if args.scenes:
        from ..scenes import LAZY_SCENES, SCENES

        known = sorted(set(SCENES) | set(LAZY_SCENES))
        names = [n.strip() for n in args.scenes.split(",") if n.strip()]
        bad = [n for n in names if n not in known]
        if bad or not names:
            p.error(f"--scenes: unknown {bad}; choose from {known}")
        print("\n".join(scenes_table(names, args.frames)))
        return 0
    if args.frames < 3:
        p.error("--frames must be >= 3")
    configs = CONFIGS
    if args.configs:
        try:
            configs = [CONFIGS[int(k)] for k in args.configs.split(",")]
        except (ValueError, IndexError):
            p.error(f"--configs: row numbers 0..{len(CONFIGS) - 1}")
    lines = [f"# StrainLimit(0, 1.01) on Newton's cloth_hanging scene, {args.frames} frames at 60 fps\n",
             "| configuration | substeps | max strain % | ms/frame | frames/s | captured | "
             "sweeps/step (mean, max) | short steps |" + (" unlimited max strain % |"
                                                           if args.unlimited else ""),
             "|---|---|---|---|---|---|---|---|" + ("---|" if args.unlimited else "")]
    best = None
    for label, solver, sub, opts in configs:
        r = run_one(solver, sub, opts, args.frames, True)
        extra = ""
        if args.unlimited:
            u = run_one(solver, sub, opts, args.frames, False)
            extra = f" {100 * u['max_strain']:.2f} |"
        lines.append(f"| {label} | {r['substeps']} | {100 * r['max_strain']:.3f} | "
                     f"{r['ms_per_frame']:.1f} | {1e3 / r['ms_per_frame']:.1f} | "
                     f"{'yes' if r['captured'] else 'no'} | {r['sweeps_mean']:.1f}, "
                     f"{r['sweeps_max']} | {r['short_steps']} |" + extra)
        print(lines[-1], file=sys.stderr)
        if r["max_strain"] <= 0.011 and (best is None or r["ms_per_frame"] < best[1]):
            best = (label, r["ms_per_frame"])
    lines.append("")
    lines.append("fastest configuration within 1.1 %: " + (
        f"{best[0]} at {best[1]:.1f} ms a frame ({1e3 / best[1]:.1f} frames/s; target 60)"
        if best else "none"))
    print("\n".join(lines))
    return 0
