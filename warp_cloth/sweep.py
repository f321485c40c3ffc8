"""Parameter sweeps: many runs of a scene, on Ray or a local process pool (``warp-cloth sweep``).

A spec file (TOML or JSON) names the scene, the solvers, the parameters and the outputs::

    scene = "hanging"                 # any built-in scene (warp-cloth run --help)
    solvers = ["explicit", "pd"]      # one run per solver per parameter combination
    frames = 30                       # frames per run (frame 0 included), default 30
    fps = 60                          # default 60
    usd = false                       # true: one USD file per run in OUT/usd/<run_id>.usd
    out = "results"                   # output folder, relative to the spec (default SPEC-sweep)

    [params]                          # scene / model arguments; a list is swept
    stiffness = [300.0, 1000.0, 3000.0]
    shape = [[8, 8]]                  # a list-valued argument is written as a list of lists
    substeps = 4

    [solver_options.pd]               # per-solver options, lists swept the same way
    iterations = [5, 10]

The runs are the Cartesian product of the solvers and every list (a solver's options only
multiply its own runs). Each run has an id: a hash of its scene, solver, parameters and frames.
Results go to ``OUT/results.csv``, one row per run: the id, status (``ok``, ``diverged``:
`SimulationDiverged`, ``error``: any other exception or a crashed worker), the error message, the
parameters (``param.NAME``, ``option.NAME``) and the `RunStats` fields (``extra`` as JSON). The file
is rewritten atomically after every run, so an interrupted sweep keeps what finished; a second
invocation skips the runs whose rows say ``ok`` or ``diverged`` and runs the others again.

Executors: Ray tasks when Ray is installed (``pip install "warp-cloth[cluster]"``):
``ray.init()`` starts an embedded local Ray by default, ``--address`` or ``RAY_ADDRESS`` joins a
cluster. Without Ray (or with ``--executor pool``) a local `ProcessPoolExecutor` of ``--workers``
processes (spawned: no forked Warp state). Every worker process loads (and, on a cold cache,
compiles) the sweep's kernels once, by a 2-frame run of a 2 x 2 cloth per solver, before its first
run. A worker that dies (a crash in native code) fails its pool; the runs that were in flight are
then run again one at a time in fresh single-worker pools, so the row of the one that crashes
says so and the sweep goes on.
"""

from __future__ import annotations

import csv
import hashlib
import itertools
import json
import os
import sys
import time
from dataclasses import fields

__all__ = ["load_spec", "expand", "execute_run", "run_sweep", "map_cells", "SweepError"]

SPEC_KEYS = {"scene", "solvers", "solver", "frames", "fps", "usd", "out", "params",
             "solver_options", "strain_bound", "name"}
#: the status values of a row; "ok" and "diverged" rows are finished (skipped on a re-run)
FINISHED = ("ok", "diverged")


class SweepError(ValueError):
    """A bad sweep spec (the message names the key)."""


# --------------------------------------------------------------------------------- the spec
def load_spec(path) -> dict:
    """Read a TOML (``.toml``) or JSON spec file and check it (`SweepError` on a bad one)."""
    path = os.fspath(path)
    try:
        if path.endswith(".toml"):
            try:
                import tomllib
            except ImportError:  # Python 3.10
                raise SweepError(f"{path}: TOML specs need Python 3.11 (tomllib); use JSON") from None
            with open(path, "rb") as fh:
                spec = tomllib.load(fh)
        else:
            with open(path, encoding="utf-8") as fh:
                spec = json.load(fh)
    except OSError as e:
        raise SweepError(f"{path}: cannot read the spec ({e.strerror})") from None
    except ValueError as e:  # JSONDecodeError, TOMLDecodeError
        if isinstance(e, SweepError):
            raise
        raise SweepError(f"{path}: not a valid spec file: {e}") from None
    spec = check_spec(spec, path)
    if spec.get("out") is None:
        spec["out"] = os.path.splitext(path)[0] + "-sweep"
    elif not os.path.isabs(spec["out"]):
        spec["out"] = os.path.join(os.path.dirname(os.path.abspath(path)), spec["out"])
    return spec


def check_spec(spec, where: str = "spec") -> dict:
    if not isinstance(spec, dict):
        raise SweepError(f"{where}: a spec is a table of keys, got {type(spec).__name__}")
    unknown = sorted(set(spec) - SPEC_KEYS)
    if unknown:
        raise SweepError(f"{where}: unknown key(s) {unknown}; known: {sorted(SPEC_KEYS)}")
    spec = dict(spec)
    if not isinstance(spec.get("scene"), str):
        raise SweepError(f"{where}: 'scene' must name a scene, got {spec.get('scene')!r}")
    solvers = spec.pop("solver", None) if "solvers" not in spec else spec["solvers"]
    if isinstance(solvers, str):
        solvers = [solvers]
    if solvers is None:
        solvers = ["explicit"]
    if not (isinstance(solvers, list) and solvers and all(isinstance(s, str) for s in solvers)):
        raise SweepError(f"{where}: 'solvers' must be a list of solver names, got {solvers!r}")
    from .registry import SOLVERS  # names only: the driver does not load Warp

    bad = [s for s in solvers if s not in SOLVERS]
    if bad:
        raise SweepError(f"{where}: unknown solver(s) {bad}; available: {list(SOLVERS)}")
    spec["solvers"] = solvers
    for key, default in (("frames", 30), ("fps", 60.0)):
        v = spec.get(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0 or (
                key == "frames" and int(v) != v):
            raise SweepError(f"{where}: '{key}' must be a positive number, got {v!r}")
        spec[key] = int(v) if key == "frames" else float(v)
    if not isinstance(spec.get("usd", False), bool):
        raise SweepError(f"{where}: 'usd' must be true or false, got {spec['usd']!r}")
    spec["usd"] = spec.get("usd", False)
    params = spec.get("params", {})
    if not isinstance(params, dict):
        raise SweepError(f"{where}: 'params' must be a table, got {params!r}")
    for k, v in params.items():
        if isinstance(v, list) and not v:
            raise SweepError(f"{where}: params.{k} is an empty list (nothing to sweep)")
    spec["params"] = params
    opts = spec.get("solver_options", {})
    if not isinstance(opts, dict) or not all(isinstance(v, dict) for v in opts.values()):
        raise SweepError(f"{where}: 'solver_options' must be a table of tables, one per solver")
    stray = sorted(set(opts) - set(solvers))
    if stray:
        raise SweepError(f"{where}: solver_options for {stray}, which are not in 'solvers'")
    spec["solver_options"] = opts
    return spec


def _axes(table: dict):
    keys = sorted(table)
    values = [table[k] if isinstance(table[k], list) else [table[k]] for k in keys]
    return [dict(zip(keys, combo)) for combo in itertools.product(*values)]


def run_id(run: dict) -> str:
    key = {k: run[k] for k in ("scene", "solver", "params", "options", "frames", "fps",
                               "strain_bound")}
    blob = json.dumps(key, sort_keys=True, separators=(",", ":"))
    return hashlib.sha1(blob.encode()).hexdigest()[:12]


def expand(spec: dict) -> list[dict]:
    """The runs of a checked spec, in a fixed order (solver, then parameters, then options)."""
    runs = []
    for solver in spec["solvers"]:
        for params in _axes(spec["params"]):
            for options in _axes(spec["solver_options"].get(solver, {})):
                run = {"scene": spec["scene"], "solver": solver, "params": params,
                       "options": options, "frames": spec["frames"], "fps": spec["fps"],
                       "strain_bound": spec.get("strain_bound")}
                run["run_id"] = run_id(run)
                run["usd"] = (os.path.join(spec["out"], "usd", run["run_id"] + ".usd")
                              if spec["usd"] else None)
                runs.append(run)
    ids = [r["run_id"] for r in runs]
    if len(set(ids)) != len(ids):
        raise SweepError("the spec lists the same run twice (repeated values in a list)")
    return runs


# --------------------------------------------------------------------------------- workers
_WARMED: set = set()


def warm(scene: str, solvers) -> None:
    """Load (and on a cold cache compile) the kernels of ``scene`` with each solver, once per
    process: a 2-frame run of a 2 x 2 cloth. Failures are ignored (the real run reports them)."""
    from .util import init_warp

    init_warp()
    from .scenes import build_scene

    for s in solvers:
        if (scene, s) in _WARMED:
            continue
        _WARMED.add((scene, s))
        try:
            build_scene(scene, solver=s, frames=2, shape=(2, 2)).run(None, quiet=True)
        except Exception:  # noqa: BLE001 - a scene without ``shape`` etc.: warm on the real run
            pass


def _stat_fields() -> list[str]:
    from .runstats import RunStats

    return [f.name for f in fields(RunStats)]


def execute_run(run: dict) -> dict:
    """Run one cell; never raises: returns its row (status ``ok``, ``diverged`` or ``error``)."""
    warm(run["scene"], [run["solver"]])
    from .errors import SimulationDiverged
    from .scenes import build_scene

    row = {"run_id": run["run_id"], "status": "error", "error": "", "scene": run["scene"],
           "solver": run["solver"]}
    t0 = time.perf_counter()
    try:
        kw = dict(run["params"])
        kw.update(solver=run["solver"], solver_options=dict(run["options"]) or None,
                  frames=run["frames"], fps=run["fps"])
        if run.get("strain_bound") is not None:
            kw["strain_bound"] = run["strain_bound"]
        for k, v in list(kw.items()):
            if k == "shape" and isinstance(v, list):
                kw[k] = tuple(v)
        scene = build_scene(run["scene"], **kw)
        if run.get("usd"):
            os.makedirs(os.path.dirname(run["usd"]), exist_ok=True)
        stats = scene.run(run.get("usd"), quiet=True, progress=False)
        d = stats.as_dict()
        d["extra"] = json.dumps(d["extra"], sort_keys=True, default=str)
        row.update(d)
        row["status"] = "ok"
    except SimulationDiverged as e:
        row.update(status="diverged", error=str(e), frames=run["frames"],
                   diverged_frame=e.frame, diverged_strain=e.max_strain)
    except Exception as e:  # noqa: BLE001 - a row with its error, never the end of the sweep
        msg = " ".join(str(e).split())
        row.update(status="error", error=f"{type(e).__name__}: {msg}"[:2000])
    row["run_s"] = time.perf_counter() - t0
    row["pid"] = os.getpid()
    return row


# --------------------------------------------------------------------------------- table
def _row_for_csv(run: dict, result: dict) -> dict:
    row = dict(result)
    for k, v in run["params"].items():
        row[f"param.{k}"] = json.dumps(v) if isinstance(v, (list, dict)) else v
    for k, v in run["options"].items():
        row[f"option.{k}"] = json.dumps(v) if isinstance(v, (list, dict)) else v
    row["usd"] = run.get("usd") or ""
    return row


def read_results(path) -> dict:
    """``run_id -> row`` of an existing results CSV (empty if there is none)."""
    if not os.path.exists(path):
        return {}
    with open(path, newline="", encoding="utf-8") as fh:
        return {r["run_id"]: r for r in csv.DictReader(fh)}


def write_results(path, rows: list[dict]) -> None:
    """Write the rows atomically (temporary file, then rename)."""
    head = ["run_id", "status", "error", "scene", "solver"]
    cols = list(head)
    for r in rows:
        for k in r:
            if k not in cols:
                cols.append(k)
    order = head + sorted(c for c in cols if c.startswith(("param.", "option."))) + [
        c for c in cols if c not in head and not c.startswith(("param.", "option."))]
    tmp = path + ".tmp"
    with open(tmp, "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=order, restval="")
        w.writeheader()
        w.writerows(rows)
    os.replace(tmp, path)


class _Bar:
    """Progress over runs on stderr: a redrawn bar on a terminal, else a line per run."""

    def __init__(self, total: int, enabled: bool):
        self.total, self.enabled = total, enabled
        self.tty = enabled and sys.stderr.isatty()
        self.t0 = time.perf_counter()
        self.done = 0
        self.counts = {"ok": 0, "diverged": 0, "error": 0}

    def update(self, row: dict) -> None:
        self.done += 1
        self.counts[row["status"]] = self.counts.get(row["status"], 0) + 1
        if not self.enabled:
            return
        el = time.perf_counter() - self.t0
        left = el / self.done * (self.total - self.done)
        c = self.counts
        tail = (f"{self.done}/{self.total} runs, {c['diverged']} diverged, {c['error']} errors, "
                f"{el:.0f} s, about {left:.0f} s left")
        if self.tty:
            w = 30
            fill = int(w * self.done / max(self.total, 1))
            sys.stderr.write(f"\rsweep [{'#' * fill}{'.' * (w - fill)}] {tail}   ")
            if self.done == self.total:
                sys.stderr.write("\n")
        else:
            sys.stderr.write(f"sweep: {row['run_id']} {row['solver']} {row['status']}; {tail}\n")
        sys.stderr.flush()


# --------------------------------------------------------------------------------- executors
def _ray_available() -> bool:
    try:
        import ray  # noqa: F401

        return True
    except ImportError:
        return False


CRASH = ("the worker process died during this run (a crash in native code or killed for "
         "memory)")


def _crash_row(run: dict, error: str) -> dict:
    return {"run_id": run["run_id"], "status": "error", "scene": run["scene"],
            "solver": run["solver"], "error": error}


def _run_pool(runs, workers: int, on_done, fn=execute_run, on_crash=_crash_row):
    """``fn(run)`` for every run in a spawned process pool, ``on_done(run, result)`` as each ends.
    A crashed worker's in-flight runs are run again one at a time, each in a fresh pool, so a
    crash names its own run: ``on_crash(run, message)`` gives that run's result."""
    import concurrent.futures as cf
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    retry = []
    with cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
        futs = {pool.submit(fn, r): r for r in runs}
        for f in cf.as_completed(futs):
            try:
                res = f.result()
            except cf.process.BrokenProcessPool:
                retry.append(futs[f])
                continue
            on_done(futs[f], res)
    for r in retry:
        with cf.ProcessPoolExecutor(max_workers=1, mp_context=ctx) as pool:
            try:
                res = pool.submit(fn, r).result()
            except cf.process.BrokenProcessPool:
                res = on_crash(r, CRASH)
        on_done(r, res)


def _ray_init(workers, address):
    import ray

    if not ray.is_initialized():
        kw = {"address": address} if address else {}
        if not address and workers:
            kw["num_cpus"] = int(workers)
        ray.init(include_dashboard=False, log_to_driver=False, **kw)
    return ray


def _run_ray(runs, workers, address, on_done, fn=execute_run, on_crash=_crash_row):
    """``fn(run)`` for every run as Ray tasks (no retries); a task that fails (its worker died)
    gives ``on_crash(run, message)``."""
    ray = _ray_init(workers, address)
    remote = ray.remote(max_retries=0)(fn)
    refs = {remote.remote(r): r for r in runs}
    pending = list(refs)
    while pending:
        ready, pending = ray.wait(pending, num_returns=1)
        for ref in ready:
            r = refs[ref]
            try:
                res = ray.get(ref)
            except Exception as e:  # noqa: BLE001 - a crashed worker: a row with its error
                res = on_crash(r, f"{type(e).__name__}: {' '.join(str(e).split())[:500]}")
            on_done(r, res)


def resolve_executor(executor: str = "auto", address: str | None = None) -> tuple[str, str | None]:
    """``(executor, address)``: ``"auto"`` is Ray when it is installed or an address is given
    (``address`` or ``$RAY_ADDRESS``), else the process pool."""
    address = address or os.environ.get("RAY_ADDRESS") or None
    if executor == "auto":
        executor = "ray" if (address or _ray_available()) else "pool"
    if executor not in ("ray", "pool"):
        raise SweepError(f"executor must be 'auto', 'ray' or 'pool', got {executor!r}")
    if executor == "ray" and not _ray_available():
        raise SweepError('Ray is not installed (pip install "warp-cloth[cluster]")')
    return executor, address


def _call_cell(job):
    """Worker side of `map_cells`: warm once per process, then ``fn(*args)``."""
    fn, args, warm_with = job["fn"], job["args"], job["warm"]
    if warm_with is not None:
        warm(*warm_with)
    return fn(*args)


def map_cells(fn, cells, *, workers: int | None = None, address: str | None = None,
              executor: str = "auto", warm_with=None, on_crash=None, on_done=None) -> list:
    """``[fn(*args) for args in cells]`` on the sweep's executors (for the benchmarks' grids).

    ``fn`` must be a module-level function (it is pickled). ``warm_with = (scene, solvers)``
    warms each worker once (`warm`). A cell whose worker crashes gets ``on_crash(args,
    message)`` (default: raise `RuntimeError`). ``on_done(i, result)`` is called as cells end
    (in any order). Results come back in the order of ``cells``."""
    executor, address = resolve_executor(executor, address)
    jobs = [{"run_id": i, "fn": fn, "args": tuple(a), "warm": warm_with} for i, a in enumerate(cells)]
    out = [None] * len(jobs)

    def crash(job, msg):
        if on_crash is None:
            raise RuntimeError(f"cell {job['args']}: {msg}")
        return on_crash(job["args"], msg)

    def done(job, res):
        out[job["run_id"]] = res
        if on_done is not None:
            on_done(job["run_id"], res)

    if workers is None:
        workers = max(1, os.cpu_count() or 1)
    if executor == "ray":
        _run_ray(jobs, workers, address, done, fn=_call_cell, on_crash=crash)
    else:
        _run_pool(jobs, int(workers), done, fn=_call_cell, on_crash=crash)
    return out


def run_sweep(spec: dict, *, executor: str = "auto", workers: int | None = None,
              address: str | None = None, progress: bool = True) -> dict:
    """Run the spec's unfinished runs; return ``{"runs", "skipped", "ran", "counts", "csv",
    "executor", "wall_s"}``. ``executor``: ``"auto"`` (Ray when installed or ``address`` /
    ``RAY_ADDRESS`` is given, else the pool), ``"ray"`` or ``"pool"``."""
    runs = expand(spec)
    out = spec["out"]
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, "results.csv")
    old = read_results(path)
    todo = [r for r in runs if old.get(r["run_id"], {}).get("status") not in FINISHED]
    rows = {rid: row for rid, row in old.items()}
    executor, address = resolve_executor(executor, address)
    if workers is None:
        workers = max(1, os.cpu_count() or 1)
    if int(workers) != workers or workers < 1:
        raise SweepError(f"workers must be a positive integer, got {workers!r}")
    bar = _Bar(len(todo), progress)
    t0 = time.perf_counter()

    def on_done(run, res):
        rows[run["run_id"]] = _row_for_csv(run, res)
        order = [r["run_id"] for r in runs]
        known = [rows[i] for i in order if i in rows] + [
            v for k, v in rows.items() if k not in set(order)]
        write_results(path, known)
        bar.update(res)

    if todo:
        if executor == "ray":
            _run_ray(todo, workers, address, on_done)
        else:
            _run_pool(todo, int(workers), on_done)
    counts = {}
    for r in runs:
        s = rows[r["run_id"]]["status"]
        counts[s] = counts.get(s, 0) + 1
    return {"runs": len(runs), "skipped": len(runs) - len(todo), "ran": len(todo),
            "counts": counts, "csv": path, "executor": executor,
            "wall_s": time.perf_counter() - t0}


def main(argv=None) -> int:
    """``warp-cloth sweep SPEC`` (see the module docstring)."""
    import argparse

    p = argparse.ArgumentParser(prog="warp-cloth sweep", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(p)
    return cmd_sweep(p.parse_args(argv))


def add_arguments(p) -> None:
    p.add_argument("spec", help="a .toml or .json sweep spec")
    p.add_argument("--out", default=None, help="output folder (default: the spec's 'out', else "
                   "SPEC-sweep beside the spec)")
    p.add_argument("--workers", type=int, default=None,
                   help="worker processes (default: the CPU count); with Ray, its local CPUs")
    p.add_argument("--address", default=None,
                   help="a Ray cluster to join (default: $RAY_ADDRESS, else a local Ray)")
    p.add_argument("--executor", choices=("auto", "ray", "pool"), default="auto",
                   help="auto: Ray when installed, else a local process pool")
    p.add_argument("--dry-run", action="store_true", help="list the runs and exit")
    p.add_argument("--quiet", action="store_true", help="no progress output")


def cmd_sweep(args) -> int:
    try:
        spec = load_spec(args.spec)
        if args.out is not None:
            spec["out"] = args.out
        if args.dry_run:
            done = read_results(os.path.join(spec["out"], "results.csv"))
            for r in expand(spec):
                st = done.get(r["run_id"], {}).get("status", "todo")
                print(f"{r['run_id']} {r['solver']:9s} {json.dumps(r['params'], sort_keys=True)} "
                      f"{json.dumps(r['options'], sort_keys=True)} [{st}]")
            return 0
        res = run_sweep(spec, executor=args.executor, workers=args.workers,
                        address=args.address, progress=not args.quiet)
    except SweepError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    c = res["counts"]
    print(f"sweep: {res['runs']} runs ({res['skipped']} finished before, {res['ran']} run now on "
          f"{res['executor']}, {res['wall_s']:.1f} s): {c.get('ok', 0)} ok, "
          f"{c.get('diverged', 0)} diverged, {c.get('error', 0)} errors; {res['csv']}")
    return 0 if not c.get("error") else 1
