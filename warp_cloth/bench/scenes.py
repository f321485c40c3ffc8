"""``warp-cloth bench scenes``: the contact scenes at their defaults, every solver, against the
collision issue's checks.

Each built-in scene (``--scenes``, default ``drape,table,spin,mesh``: the issue's contact scenes)
runs with each solver (``--solver``, default all four) at the scene's defaults (``--res`` and
``--frames`` shrink it for a quick look). Every written frame is measured on the host:

- **max strain**: the largest edge strain over all frames, beside its ratio to explicit Euler's
  on the same scene (the check: at most 1.5 times explicit's, or at most 5 %: ``ok``);
- **rise, still**: the largest one-frame rise of the cloth's energy (kinetic + gravity + springs
  + bending, `diagnostics.Meter`) over the frames in which no obstacle moved: nothing then does
  work on the cloth, so a rise is the method's own;
- **rise, turning**: for an obstacle turning steadily about a vertical axis (the ``spin``
  scene's sphere, once its ramp is over), the largest one-frame rise of the cloth's energy seen
  from the turning frame (`diagnostics.frame_energy`, the Jacobi integral): the obstacle's work
  taken out, contact can only lower it;
- **clearance**: the least signed distance of a free vertex to any obstacle over all frames, in
  mm (the promise: at least ``thickness - 0.1 mm``);
- **crossings**: frames in which the cloth passes through itself (`--check-intersections`);
- ms a frame (the run's own timing, graphs replayed where the step allows).

Frames in which an obstacle moves otherwise (the ``mesh`` scene's torus once it slides) are left
out of both energy columns: the obstacle does work there. Times depend on the machine and its
load: compare the rows of one run.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from ..util import quiet_warp

SOLVERS = ("explicit", "implicit", "pbd", "pd")
DEFAULT_SCENES = ("drape", "table", "spin", "mesh")
#: the collision issue's rule on strain: at most this times explicit Euler's, or at most ``CAP``
RATIO, CAP = 1.5, 0.05


def _turning(ob):
    """``(angular_velocity, centre, steady_from)`` of an obstacle that turns steadily about a
    vertical axis through its centre, else None."""
    m = getattr(ob, "motion", None)
    if m is None or m.path is not None or np.any(m.linear_velocity):
        return None
    w = np.asarray(m.angular_velocity, dtype=np.float64)
    if not np.any(w) or np.any(w[[0, 2]]):
        return None
    return w, np.asarray(ob.pose(0.0)[0], dtype=np.float64), m.start + m.ramp


def run_scene(name: str, solver: str, res=None, frames=None) -> dict:
    """One scene with one solver at its defaults (``res``, ``frames``: override); the columns of
    the module docstring as a dict."""
    from ..diagnostics import Meter, frame_energy
    from ..scenes import build_scene

    kw = {}
    if res is not None:
        kw["res"] = int(res)
    if frames is not None:
        kw["frames"] = int(frames)
    scene = build_scene(name, solver=solver, **kw)
    stage = scene.collision
    obstacles = stage.obstacles
    free = np.flatnonzero(np.asarray(scene.model.inverse_masses) > 0)
    meter = Meter(scene.model)
    turning = [_turning(ob) for ob in obstacles if ob.moving]
    turning = turning[0] if len(turning) == 1 and turning[0] is not None else None
    rec = {"strain": [], "energy": [], "jacobi": [], "clear": [], "t": []}

    def on_frame(f, st):
        m = meter(st, energy=True)
        rec["strain"].append(m.max_strain)
        rec["energy"].append(m.energy)
        rec["t"].append(f / scene.fps)  # the frame's time (the state's clock is float32)
        if turning is not None:
            w, c, _ = turning
            rec["jacobi"].append(frame_energy(scene.model, st, meter=meter, angular_velocity=w,
                                              center=c))
        if obstacles and len(free):
            sd = stage.contact.signed_distances(st.positions()[free], f / scene.fps)
            rec["clear"].append(float(np.min(sd)))

    stats = scene.run(None, quiet=True, check_intersections=True, on_frame=on_frame)
    t = np.asarray(rec["t"])
    e = np.asarray(rec["energy"])

    def still(k):  # no obstacle moved between frames k - 1 and k
        for ob in obstacles:
            if not ob.moving:
                continue
            a, b = ob.pose(t[k - 1]), ob.pose(t[k])
            if not (np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])):
                return False
        return True

    rises = [e[k] - e[k - 1] for k in range(1, len(e)) if still(k)]
    out = {"scene": name, "solver": solver, "frames": len(e),
           "max_strain": float(max(rec["strain"])),
           "rise_still": float(max(rises)) if rises else None,
           "still_frames": len(rises),
           "rise_turning": None,
           "clearance_mm": 1e3 * min(rec["clear"]) if rec["clear"] else None,
           "thickness_mm": 1e3 * float(stage.thickness),
           "crossing_frames": int(stats.crossing_frames or 0),
           "ms_per_frame": float(stats.ms_per_frame)}
    if turning is not None:
        j = np.asarray(rec["jacobi"])
        steady = [k for k in range(1, len(j)) if t[k - 1] >= turning[2] - 1e-9]
        if steady:
            out["rise_turning"] = float(max(j[k] - j[k - 1] for k in steady))
    return out


def _fmt(x, spec):
    return "-" if x is None else format(x, spec)


def table(rows) -> list:
    explicit = {r["scene"]: r["max_strain"] for r in rows if r["solver"] == "explicit"}
    lines = ["| scene | solver | max strain % | / explicit's | <= 5 % or 1.5 x explicit | "
             "largest rise, obstacles still (J) | largest rise, turning frame (J) | "
             "least clearance (mm) | frames crossing | ms/frame |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ex = explicit.get(r["scene"])
        ratio = r["max_strain"] / ex if ex else None
        r["ratio_to_explicit"] = ratio
        r["strain_ok"] = bool(r["max_strain"] <= CAP or (ratio is not None and ratio <= RATIO))
        lines.append(
            f"| {r['scene']} | {r['solver']} | {100 * r['max_strain']:.2f} | "
            f"{_fmt(ratio, '.2f')} | {'ok' if r['strain_ok'] else 'NO'} | "
            f"{_fmt(r['rise_still'], '.1e')} | {_fmt(r['rise_turning'], '.1e')} | "
            f"{_fmt(r['clearance_mm'], '.3f')} | {r['crossing_frames']} | "
            f"{r['ms_per_frame']:.0f} |")
    return lines


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="warp-cloth bench scenes", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", default=",".join(DEFAULT_SCENES),
                   help="comma list of built-in scenes with obstacles (default: %(default)s)")
    p.add_argument("--solver", nargs="+", default=list(SOLVERS), choices=SOLVERS)
    p.add_argument("--res", type=int, default=None, help="cells a side (default: the scene's)")
    p.add_argument("--frames", type=int, default=None,
                   help="frames written, frame 0 included (default: the scene's)")
    p.add_argument("--json", action="store_true", help="the rows as JSON")
    args = p.parse_args(argv)
    from ..cli import CONTACT_SCENES

    names = [n.strip() for n in args.scenes.split(",") if n.strip()]
    bad = [n for n in names if n not in CONTACT_SCENES]
    if bad or not names:
        p.error(f"--scenes: {bad or 'none'}; choose from {CONTACT_SCENES}")
    if args.res is not None and args.res < 2:
        p.error("--res must be >= 2")
    if args.frames is not None and args.frames < 3:
        p.error("--frames must be >= 3")
    quiet_warp()
    solvers = [s for s in SOLVERS if s in args.solver]
    if "explicit" not in solvers:
        print("note: without explicit there is no ratio to explicit Euler's strain",
              file=sys.stderr)
    rows = []
    for name in names:
        for solver in solvers:
            rows.append(run_scene(name, solver, args.res, args.frames))
            print(f"{name} {solver}: {100 * rows[-1]['max_strain']:.2f} % "
                  f"({rows[-1]['ms_per_frame']:.0f} ms/frame)", file=sys.stderr)
    lines = table(rows)
    if args.json:
        print(json.dumps(rows, indent=1))
    else:
        print(f"# contact scenes at their defaults (res {args.res or 'default'}, frames "
              f"{args.frames or 'default'})\n")
        print("\n".join(lines))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
