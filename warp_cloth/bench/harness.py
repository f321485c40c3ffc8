"""Shared machinery of the speed/accuracy and stability benchmarks.

A `Config` names a method, its solver options, substeps per frame and an optional strain limit.
`run_config` runs it on a built-in scene, records positions at fixed frames, and returns a
`Result` (wall time per simulated second with compile excluded, errors against a reference,
maximum strain, energy drift, divergence). `reference` computes and caches the reference
trajectory.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import statistics
from dataclasses import dataclass, field

import numpy as np

from ..errors import SimulationDiverged
from ..scenes import build_scene

METHOD_COLOURS = {"explicit": "tab:red", "implicit": "tab:blue", "pbd": "tab:green", "pd": "tab:purple"}


@dataclass
class Config:
    method: str
    solver_options: dict = field(default_factory=dict)
    substeps: int = 1
    strain_limit: tuple | None = None
    label: str = ""

    def __post_init__(self):
        if not self.label:
            opts = ",".join(f"{k}={v}" for k, v in sorted(self.solver_options.items()))
            self.label = f"{self.method}[{opts}]x{self.substeps}" + (
                f"+limit{self.strain_limit[1]:g}" if self.strain_limit else "")


@dataclass
class Result:
    config: Config
    diverged: bool
    diverged_frame: int | None
    wall_per_sim_s: float  # seconds of wall time per simulated second (compile excluded)
    rms_error: float  # relative to the cloth size, over all sample frames and vertices
    max_error: float
    max_strain: float
    energy_drift: float  # (E_end - E_0) / |E_0|
    positions: np.ndarray | None = None  # (S, N, 3) at the sample frames

    def row(self) -> dict:
        c = self.config
        return {
            "method": c.method, "label": c.label, "substeps": c.substeps,
            "options": json.dumps(c.solver_options, sort_keys=True),
            "strain_limit": "" if c.strain_limit is None else f"{c.strain_limit[0]:g},{c.strain_limit[1]:g}",
            "diverged": self.diverged, "diverged_frame": "" if self.diverged_frame is None else self.diverged_frame,
            "wall_per_sim_s": self.wall_per_sim_s, "rms_error": self.rms_error,
            "max_error": self.max_error, "max_strain": self.max_strain,
            "energy_drift": self.energy_drift,
        }


def _corrections(config: Config):
    if config.strain_limit is None:
        return ()
    from ..limits import StrainLimit

    lo, hi = config.strain_limit
    return (lambda model: StrainLimit(model, lo, hi),)


def simulate(scene_name: str, scene_params: dict, config: Config, frames: int, fps: float,
             sample_frames, repeats: int = 1):
    """Run ``config`` ``repeats`` times; return (positions at sample_frames, stats of the median
    run, diverged frame or None)."""
    walls, stats, pos, div = [], None, None, None
    sample = set(int(f) for f in sample_frames)
    for _ in range(max(1, repeats)):
        scene = build_scene(scene_name, solver=config.method, solver_options=dict(config.solver_options),
                            substeps=config.substeps, corrections=_corrections(config), frames=frames,
                            fps=fps, **{"self_collision": False, **scene_params})
        rec = {}

        def on_frame(f, state):
            if f in sample:
                rec[f] = state.x.numpy().astype(np.float64)

        try:
            st = scene.run(None, quiet=True, on_frame=on_frame)
        except SimulationDiverged as e:
            return None, None, e.frame
        walls.append(st.wall_s)
        stats = st
        pos = np.stack([rec[f] for f in sorted(sample)])
    stats.wall_s = statistics.median(walls)
    return pos, stats, div


def run_config(scene_name, scene_params, config, frames, fps, sample_frames, ref_positions,
               size, repeats=1) -> Result:
    pos, st, div = simulate(scene_name, scene_params, config, frames, fps, sample_frames, repeats)
    if pos is None:
        return Result(config, True, div, math.nan, math.nan, math.nan, math.nan, math.nan)
    steps_time = max(st.timed_frames, 1) / fps  # frames timed (compile and graph recording excluded)
    err = np.linalg.norm(pos - ref_positions, axis=2) / size
    return Result(
        config, False, None, st.wall_s / steps_time, float(np.sqrt((err ** 2).mean())),
        float(err.max()), st.max_strain,
        (st.energy_final - st.energy_initial) / max(abs(st.energy_initial), 1e-12), pos,
    )


# --------------------------------------------------------------------------- the reference
def reference_config(ref_substeps: int) -> Config:
    """Fixed Newton and CG counts, no tolerance: an absolute Newton tolerance would skip the
    solve entirely at small dt (the whole correction dt^2 f/m falls below it)."""
    return Config("implicit", {"newton_iterations": 4, "tolerance": None, "linear": "cg",
                               "linear_iterations": 150, "linear_tolerance": None},
                  substeps=ref_substeps, label=f"reference implicit x{ref_substeps}")


def cache_dir() -> str:
    d = os.environ.get("WARP_CLOTH_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "warp_cloth")
    os.makedirs(d, exist_ok=True)
    return d


def reference(scene_name, scene_params, frames, fps, sample_frames, ref_substeps, validate=True,
              log=print) -> dict:
    """Reference positions at ``sample_frames``, cached on disk, keyed by every parameter.

    Implicit Euler (Newton and CG run to their float32 floor) is only first-order accurate in dt,
    so a plain small-step run still carries an O(dt) damping error. The reference therefore uses
    Richardson extrapolation: with x(h) the positions at ``ref_substeps`` steps per frame,
    ``R1 = 2 x(h/2) - x(h)`` and ``R2 = 2 x(h/4) - x(h/2)`` are second-order estimates, and R2 is
    the reference. Validation: ``halving_rms`` / ``halving_max`` = |R2 - R1| (relative to the cloth
    size), the change when the step is halved; it must stay below the errors being measured.
    """
    from .. import __version__

    key = json.dumps({"scene": scene_name, "params": scene_params, "frames": frames, "fps": fps,
                      "sample": [int(f) for f in sample_frames], "substeps": ref_substeps,
                      "config": dataclasses.asdict(reference_config(ref_substeps)),
                      "method": "richardson-3", "version": __version__}, sort_keys=True, default=str)
    h = hashlib.sha256(key.encode()).hexdigest()[:16]
    path = os.path.join(cache_dir(), f"ref_{scene_name}_{h}.npz")
    if os.path.exists(path):
        data = np.load(path)
        out = {k: data[k] for k in data.files}
        out["cached"] = True
        out["path"] = path
        return out
    runs = []
    for s in (ref_substeps, 2 * ref_substeps, 4 * ref_substeps):
        log(f"computing reference: implicit Euler, {s} steps per frame")
        pos, st, div = simulate(scene_name, scene_params, reference_config(s), frames, fps, sample_frames)
        if pos is None:
            raise RuntimeError(f"the reference ({s} steps per frame) diverged at frame {div}")
        runs.append(pos)
    r1 = 2 * runs[1] - runs[0]
    r2 = 2 * runs[2] - runs[1]
    size = float(np.ptp(runs[0][0], axis=0).max()) or 1.0
    d = np.linalg.norm(r2 - r1, axis=2) / size
    plain = np.linalg.norm(runs[2] - r2, axis=2) / size
    out = {"positions": r2, "halving_rms": np.float64(np.sqrt((d ** 2).mean())),
           "halving_max": np.float64(d.max()),
           "plain_error_rms": np.float64(np.sqrt((plain ** 2).mean()))}
    np.savez(path, **out)
    out["cached"] = False
    out["path"] = path
    return out


# --------------------------------------------------------------------------- outputs
def pareto(results) -> list:
    """Indices of the non-dominated (faster and more accurate) stable results."""
    ok = [i for i, r in enumerate(results) if not r.diverged and math.isfinite(r.rms_error)]
    front = []
    for i in ok:
        a = results[i]
        dominated = any(
            (b.wall_per_sim_s <= a.wall_per_sim_s and b.rms_error <= a.rms_error)
            and (b.wall_per_sim_s < a.wall_per_sim_s or b.rms_error < a.rms_error)
            for j, b in ((j, results[j]) for j in ok) if j != i)
        if not dominated:
            front.append(i)
    return sorted(front, key=lambda i: results[i].wall_per_sim_s)


def write_csv(path, rows):
    import csv

    if not rows:
        return
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def have_matplotlib() -> bool:
    try:
        import matplotlib  # noqa: F401

        return True
    except ImportError:
        return False
