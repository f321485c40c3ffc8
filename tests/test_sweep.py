"""`warp-cloth sweep`: spec expansion, a tiny sweep on the process pool (every row present, a
diverging cell and a failing cell recorded as such, a re-run skips what finished), and the same
on Ray when it is installed."""

import csv
import json
import os

import pytest

from warp_cloth.sweep import SweepError, check_spec, expand, load_spec, run_sweep

SPEC = {
    "scene": "hanging",
    "solvers": ["explicit"],
    "frames": 4,
    "usd": True,
    "params": {"shape": [[4, 4]], "substeps": 2,
               # 1e5 N/m at 2 substeps a frame is far past explicit Euler's stable step: it
               # diverges (without self-collision, whose rigid impact zones hold such a cloth
               # frozen); a negative stiffness is refused by ClothModel (an error row)
               "self_collision": False,
               "stiffness": [30.0, 100.0, 1.0e5, -1.0]},
}


def write_spec(tmp_path, spec, name="s.json"):
    p = tmp_path / name
    p.write_text(json.dumps(spec))
    return str(p)


def read_rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_expand_is_the_product_with_stable_ids(tmp_path):
    spec = check_spec({"scene": "hanging", "solvers": ["explicit", "pd"], "frames": 3,
                       "params": {"stiffness": [1.0, 2.0, 3.0], "shape": [[4, 4], [2, 3]]},
                       "solver_options": {"pd": {"iterations": [5, 10]}}})
    spec["out"] = str(tmp_path)
    runs = expand(spec)
    # explicit: 3 x 2; pd: 3 x 2 x 2 (its options multiply only its own runs)
    assert len(runs) == 6 + 12
    assert len({r["run_id"] for r in runs}) == 18
    assert [r["params"]["shape"] for r in runs[:2]] == [[4, 4], [4, 4]]
    assert {r["options"].get("iterations") for r in runs if r["solver"] == "pd"} == {5, 10}
    assert [r["run_id"] for r in expand(spec)] == [r["run_id"] for r in runs]  # deterministic
    other = dict(spec, frames=4)
    assert not {r["run_id"] for r in expand(other)} & {r["run_id"] for r in runs}


@pytest.mark.parametrize("bad,match", [
    ({"scene": "hanging", "bogus": 1}, "unknown key"),
    ({"scene": "hanging", "solvers": ["nope"]}, "unknown solver"),
    ({"scene": "hanging", "solvers": ["pd"], "solver_options": {"pbd": {"iterations": 2}}},
     "not in 'solvers'"),
    ({"scene": "hanging", "params": {"stiffness": []}}, "empty list"),
    ({"scene": "hanging", "frames": 0}, "'frames'"),
    ({"solvers": ["pd"]}, "'scene'"),
])
def test_bad_specs_are_named(bad, match):
    with pytest.raises(SweepError, match=match):
        check_spec(bad)


def test_load_spec_toml_and_errors(tmp_path):
    p = tmp_path / "a.toml"
    p.write_text('scene = "hanging"\nsolvers = ["pbd"]\n[params]\nstiffness = [1.0, 2.0]\n')
    spec = load_spec(p)
    assert spec["out"] == str(tmp_path / "a-sweep") and len(expand(spec)) == 2
    p.write_text("scene = [")
    with pytest.raises(SweepError, match="not a valid spec"):
        load_spec(p)
    with pytest.raises(SweepError, match="cannot read"):
        load_spec(tmp_path / "missing.json")


def check_first_sweep(res, spec):
    assert res["runs"] == 4 and res["ran"] == 4 and res["skipped"] == 0
    assert res["counts"] == {"ok": 2, "diverged": 1, "error": 1}
    rows = {float(r["param.stiffness"]): r for r in read_rows(res["csv"])}
    assert sorted(rows) == [-1.0, 30.0, 100.0, 1.0e5]
    assert {r["run_id"] for r in rows.values()} == {r["run_id"] for r in expand(spec)}
    for k in (30.0, 100.0):
        assert rows[k]["status"] == "ok" and rows[k]["error"] == ""
        assert int(rows[k]["frames"]) == 4 and float(rows[k]["max_strain"]) < 0.5
        assert rows[k]["method"] == "explicit"
    d = rows[1.0e5]
    assert d["status"] == "diverged" and "diverged at frame" in d["error"]
    assert 1 <= int(d["diverged_frame"]) <= 3
    e = rows[-1.0]
    assert e["status"] == "error" and "ValueError" in e["error"] and "stiffness" in e["error"]
    return rows


@pytest.fixture(scope="module")
def pool_sweep(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("sweep")
    spec = load_spec(write_spec(tmp, SPEC))
    first = run_sweep(spec, executor="pool", workers=2, progress=False)
    return spec, first


def test_pool_sweep_records_every_run(pool_sweep):
    spec, first = pool_sweep
    assert first["executor"] == "pool"
    check_first_sweep(first, spec)


def test_pool_sweep_writes_one_usd_per_run(pool_sweep):
    from pxr import Usd

    spec, first = pool_sweep
    rows = read_rows(first["csv"])
    for r in rows:
        assert r["usd"] == os.path.join(spec["out"], "usd", r["run_id"] + ".usd")
        if r["status"] == "ok":
            stage = Usd.Stage.Open(r["usd"])
            assert stage.GetEndTimeCode() == 3  # frames 0..3
        elif r["status"] == "error":  # the model was refused: nothing to write
            assert not os.path.exists(r["usd"])
        else:  # diverged: the frames before the divergence
            assert Usd.Stage.Open(r["usd"]).GetEndTimeCode() < int(r["diverged_frame"])


def test_rerun_skips_finished_runs(pool_sweep):
    spec, first = pool_sweep
    before = {r["run_id"]: r for r in read_rows(first["csv"])}
    again = run_sweep(spec, executor="pool", workers=1, progress=False)
    # ok and diverged runs are finished; the error row is tried again (and fails again)
    assert again["skipped"] == 3 and again["ran"] == 1
    after = {r["run_id"]: r for r in read_rows(again["csv"])}
    assert after.keys() == before.keys()
    for rid, r in before.items():
        if r["status"] != "error":
            assert after[rid] == r  # untouched, same worker pid and timings
    assert again["counts"] == first["counts"]


def test_cli_dry_run_lists_runs_with_their_state(pool_sweep, capsys):
    from warp_cloth.cli import main

    spec, _ = pool_sweep
    path = os.path.join(os.path.dirname(spec["out"]), "s.json")
    assert main(["sweep", path, "--dry-run"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 4
    assert sum("[ok]" in line for line in out) == 2 and sum("[diverged]" in line for line in out) == 1


def test_ray_sweep(tmp_path):
    import ray  # in the test extra: the Ray executor must run here

    spec = load_spec(write_spec(tmp_path, SPEC))
    try:
        res = run_sweep(spec, executor="ray", workers=2, progress=False)
        assert res["executor"] == "ray"
        check_first_sweep(res, spec)
        again = run_sweep(spec, executor="ray", workers=2, progress=False)
        assert again["skipped"] == 3 and again["ran"] == 1
    finally:  # its workers (about 0.4 GB each) would idle through the rest of the suite
        ray.shutdown()


def test_stability_bench_cells_on_the_pool_match_the_sequential_run(tmp_path):
    from warp_cloth.bench import stability

    common = ["--methods", "explicit", "--res", "3", "--duration", "0.05", "--quick"]
    assert stability.main(common + ["--out-dir", str(tmp_path / "seq")]) == 0
    assert stability.main(common + ["--out-dir", str(tmp_path / "par"), "--workers", "2"]) == 0
    seq = read_rows(tmp_path / "seq" / "stability.csv")
    par = read_rows(tmp_path / "par" / "stability.csv")
    key = ("method", "stiffness", "dt", "mass_ratio", "status", "frame")
    assert [tuple(r[k] for k in key) for r in par] == [tuple(r[k] for k in key) for r in seq]
    assert {r["status"] for r in seq} >= {"S", "D"}  # the quick grid has both


def crashy(i):
    """Module-level (pickled by reference into the spawned workers): cell 1 kills its process
    while cell 2 is still running in the other worker (and cell 3 waits)."""
    import time

    if i == 1:
        time.sleep(0.3)
        os._exit(3)
    time.sleep(1.0 if i >= 2 else 0.0)
    return 10 * i


def test_a_crashed_worker_is_a_result_and_the_rest_finish():
    """The pool breaks when a worker dies, failing every run in flight; those are run again one
    at a time, so only the crashing cell gets the crash result."""
    from warp_cloth.sweep import map_cells

    out = map_cells(crashy, [(0,), (1,), (2,), (3,)], workers=2, executor="pool",
                    on_crash=lambda args, msg: ("crashed", args, "died" in msg))
    assert out == [0, ("crashed", (1,), True), 20, 30]


def test_warm_runs_once_per_process_and_solver(monkeypatch):
    import warp_cloth.scenes as scenes
    from warp_cloth import sweep

    calls = []

    class Fake:
        def run(self, out, quiet):
            pass

    monkeypatch.setattr(scenes, "build_scene", lambda name, **kw: calls.append((name, kw)) or Fake())
    monkeypatch.setattr(sweep, "_WARMED", set())
    sweep.warm("hanging", ["pbd", "pd"])
    sweep.warm("hanging", ["pd", "pbd"])
    sweep.warm("flag", ["pd"])
    assert [(n, kw["solver"]) for n, kw in calls] == [("hanging", "pbd"), ("hanging", "pd"),
                                                       ("flag", "pd")]
    assert all(kw["shape"] == (2, 2) and kw["frames"] == 2 for _, kw in calls)


def test_cli_bad_spec_is_a_one_line_usage_error(tmp_path, capsys):
    from warp_cloth.cli import main

    assert main(["sweep", str(tmp_path / "missing.json")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and "cannot read" in err and len(err.splitlines()) == 1
    bad = write_spec(tmp_path, {"scene": "hanging", "solvers": ["warp-drive"]})
    assert main(["sweep", bad, "--dry-run"]) == 2
    assert "unknown solver" in capsys.readouterr().err


def test_the_sweep_driver_does_not_load_warp(tmp_path):
    """``import warp_cloth`` and a sweep's driver (spec checks, expansion, the results table)
    do not import Warp (0.5 s at start-up, every CLI call); its workers load it."""
    import subprocess
    import sys

    spec = tmp_path / "s.json"
    spec.write_text(json.dumps({"scene": "hanging", "solvers": ["explicit", "pd"], "frames": 3,
                                "out": str(tmp_path / "out"), "params": {"stiffness": [1, 2]}}))
    probe = ("import sys; import warp_cloth; from warp_cloth.cli import main; "
             f"rc = main(['sweep', {str(spec)!r}, '--dry-run']); "
             "print('WARP' if 'warp' in sys.modules else 'NOWARP', rc)")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         check=True).stdout.split()
    assert out[-2:] == ["NOWARP", "0"] and len(out) > 2  # the 4 runs listed, then the probe


def test_example_specs_expand_to_the_48_measured_runs():
    """The README's sweep measurements use these two specs: 48 runs each, the same runs but for
    the frames (30 and 240), 12 of them explicit Euler."""
    import os

    root = os.path.join(os.path.dirname(__file__), "..", "examples")
    short = expand(load_spec(os.path.join(root, "sweep_hanging.toml")))
    long = expand(load_spec(os.path.join(root, "sweep_hanging_long.toml")))
    assert len(short) == len(long) == 48
    assert sum(r["solver"] == "explicit" for r in short) == 12
    strip = [{k: v for k, v in r.items() if k not in ("frames", "run_id", "out")} for r in short]
    assert strip == [{k: v for k, v in r.items() if k not in ("frames", "run_id", "out")}
                     for r in long]
    assert {r["frames"] for r in short} == {30} and {r["frames"] for r in long} == {240}
