"""The speed/accuracy and stability harness: tiny end-to-end runs and the Pareto logic."""

import csv
import json
import math
import os

import numpy as np
import pytest

from warp_cloth.bench import stability, tradeoff
from warp_cloth.bench.harness import Config, Result, pareto


def _r(t, e, div=False):
    return Result(Config("explicit"), div, 1 if div else None, t, e, e, 0.0, 0.0)


def test_pareto_frontier_is_exactly_the_non_dominated_points():
    res = [_r(1.0, 0.5), _r(2.0, 0.1), _r(3.0, 0.2), _r(0.5, 0.9), _r(0.1, 0.01, div=True), _r(2.0, 0.3)]
    front = pareto(res)
    assert front == [3, 0, 1]  # sorted by time; 2 and 5 are dominated by 1; 4 diverged
    for i in front:
        assert not any(r.wall_per_sim_s <= res[i].wall_per_sim_s and r.rms_error < res[i].rms_error
                       for j, r in enumerate(res) if j != i and not r.diverged)


def test_tradeoff_end_to_end(tmp_path, monkeypatch):
    monkeypatch.setenv("WARP_CLOTH_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "bo"
    argv = ["--res", "3", "--duration", "0.1", "--ref-substeps", "2", "--repeats", "1",
            "--methods", "explicit,pbd", "--out-dir", str(out), "--quick", "--no-progress"]
    assert tradeoff.main(argv) == 0
    rows = list(csv.DictReader(open(out / "tradeoff_hanging.csv")))
    assert {r["method"] for r in rows} == {"explicit", "pbd"}
    stable = [r for r in rows if r["diverged"] == "False"]
    assert stable and all(math.isfinite(float(r["rms_error"])) for r in stable)
    front = [r for r in rows if r["pareto"] == "True"]
    assert front
    for a in front:  # frontier points are not dominated
        assert not any(float(b["wall_per_sim_s"]) <= float(a["wall_per_sim_s"])
                       and float(b["rms_error"]) < float(a["rms_error"]) for b in stable if b is not a)
    md = (out / "tradeoff_hanging.md").read_text()
    assert "warp-cloth bench tradeoff" in md and "Richardson" in md
    assert (out / "tradeoff_hanging.png").stat().st_size > 1000
    # the reference is cached: a second run does not recompute it
    cached = os.listdir(tmp_path / "cache")
    assert len(cached) == 1 and cached[0].startswith("ref_hanging_")


#: the columns of tradeoff's CSV that do not depend on timing (wall time and the frontier do)
ACCURACY = ("rms_error", "max_error", "max_strain", "energy_drift")
IDENTITY = ("method", "label", "substeps", "options", "strain_limit", "diverged", "diverged_frame")


def test_tradeoff_cells_on_the_pool_match_the_sequential_run(tmp_path, monkeypatch, capsys):
    """``--workers 2`` (a process pool: Ray is not in the test environment) runs the same
    configurations against the same reference: same rows in the same order, same errors; only
    the timings (and so the frontier) may differ, and the output says they were concurrent."""
    monkeypatch.setenv("WARP_CLOTH_CACHE", str(tmp_path / "cache"))
    common = ["--res", "3", "--duration", "0.1", "--ref-substeps", "2", "--repeats", "1",
              "--methods", "explicit,pbd", "--quick", "--no-progress"]
    assert tradeoff.main(common + ["--out-dir", str(tmp_path / "seq")]) == 0
    seq_out = capsys.readouterr().out
    assert tradeoff.main(common + ["--out-dir", str(tmp_path / "par"), "--workers", "2"]) == 0
    par_out = capsys.readouterr().out
    seq = list(csv.DictReader(open(tmp_path / "seq" / "tradeoff_hanging.csv")))
    par = list(csv.DictReader(open(tmp_path / "par" / "tradeoff_hanging.csv")))
    assert len(seq) == 5 and list(par[0]) == list(seq[0])  # same columns
    assert [tuple(r[k] for k in IDENTITY) for r in par] == [tuple(r[k] for k in IDENTITY) for r in seq]
    for a, b in zip(seq, par):
        for k in ACCURACY:
            assert math.isclose(float(a[k]), float(b[k]), rel_tol=1e-6, abs_tol=1e-12), (a["label"], k)
    assert all(math.isfinite(float(r["wall_per_sim_s"])) for r in par)
    assert "2 concurrent workers" in par_out and "concurrent" not in seq_out
    assert "--workers 2" in (tmp_path / "par" / "tradeoff_hanging.md").read_text()
    assert len(os.listdir(tmp_path / "cache")) == 1  # one reference, computed once, shared


def test_tradeoff_rejects_a_non_positive_worker_count(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("WARP_CLOTH_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "bo"
    with pytest.raises(SystemExit) as e:  # (a tiny run, should the check ever let it through)
        tradeoff.main(["--workers", "0", "--res", "3", "--duration", "0.1", "--ref-substeps", "2",
                       "--methods", "explicit", "--quick", "--no-progress", "--out-dir", str(out)])
    assert e.value.code == 2
    assert "--workers must be a positive integer, got 0" in capsys.readouterr().err
    assert not os.path.exists(out) and not os.path.exists(tmp_path / "cache")  # before any work


def test_stability_classifier_on_synthetic_trajectories():
    """Each class from a made-up trajectory: a cell is stable only when finite, without energy
    gain and within the stretch factor of the reference; the first failing test wins."""
    c = stability.classify
    e_ok = [1.0, 0.9, 0.7, 0.65]  # dissipating
    s_ok = [0.0, 0.01, 0.02, 0.015]
    assert c(e_ok, s_ok, 0.012, 1.0) == ("S", None)  # 0.02 <= 2 x 0.012 + 0.001
    # over-stretched: beyond twice the reference, from the first such frame
    assert c(e_ok, [0.0, 0.01, 0.03, 0.02], 0.012, 1.0) == ("O", 2)
    # a plausible-looking stretch with an energy rise is not stable: gains energy, frame 2
    assert c([1.0, 0.9, 1.05, 0.8], s_ok, 0.012, 1.0) == ("E", 2)
    assert c([1.0, 0.9, 1.009, 0.8], s_ok, 0.012, 1.0) == ("S", None)  # within 1 % of scale
    assert c([1.0, 0.9, 1.05, 0.8], s_ok, 0.012, 10.0) == ("S", None)  # tolerance scales
    # gains energy beats over-stretched; diverged beats both
    assert c([1.0, 3.0, 9.0], [0.0, 0.5, 2.0], 0.01, 1.0) == ("E", 1)
    assert c([1.0, 3.0, np.nan], [0.0, 0.5, np.nan], 0.01, 1.0) == ("D", 2)
    assert c([1.0, 0.9], [0.0, 0.01], 0.01, 1.0, diverged_frame=7) == ("D", 7)
    assert c([1.0, np.inf, 0.5], s_ok[:3], 0.01, 1.0) == ("D", 1)
    # the floor keeps strains below what shows (0.1 %) from counting as over-stretched
    assert c(e_ok, [0.0, 5e-4, 8e-4, 1e-4], 1e-6, 1.0) == ("S", None)
    with pytest.raises(ValueError):
        c(e_ok, s_ok, 0.01, 0.0)


def test_strict_stability_classes():
    """``--strict`` (the extremes issue's check): no stretch floor, and a one-frame energy rise
    beyond float32 rounding is a gain even while the energy stays below its start."""
    c = stability.classify
    strict = dict(stretch_floor=0.0, rise_tol=stability.STRICT_RISE)
    e_ok = [1.0, 0.9, 0.7, 0.65]
    # the floor's noise allowance is gone: 8e-4 against a 1e-6 reference is over-stretched
    assert c(e_ok, [0.0, 5e-4, 8e-4, 1e-4], 1e-6, 1.0, **strict) == ("O", 1)
    assert c(e_ok, [0.0, 1e-6, 2e-6, 1e-6], 1e-6, 1.0, **strict) == ("S", None)
    # a rise from 0.7 back to 0.8 stays below the start (not a gain by default) but is one here
    e_up = [1.0, 0.9, 0.7, 0.8, 0.6]
    assert c(e_up, [0.0] * 5, 0.01, 1.0) == ("S", None)
    assert c(e_up, [0.0] * 5, 0.01, 1.0, **strict) == ("E", 3)
    # rounding-sized wobbles (below STRICT_RISE of the scale) are not gains
    e_flat = [1.0, 1.0 - 1e-7, 1.0 - 5e-8, 1.0 - 2e-7]
    assert c(e_flat, [0.0] * 4, 0.01, 1.0, **strict) == ("S", None)


def test_stability_cells_follow_the_theory():
    ref = stability.reference_strain(1e3, 1.0, 4, 0.1, ref_dt=1 / 500)
    assert 0 < ref < 0.05
    # explicit: stable far below the bound, diverges at large k dt^2 / m
    assert stability.run_cell("explicit", 1e3, 1 / 2000, 1.0, 4, 0.1, ref)["status"] == "S"
    d = stability.run_cell("explicit", 1e7, 1 / 120, 1.0, 4, 0.1, ref)
    assert d["status"] == "D" and d["frame"] >= 1
    # implicit Euler with its line search neither diverges nor gains energy at k = 1e9, dt = 1/30
    ref9 = stability.reference_strain(1e9, 1.0, 4, 0.1, ref_dt=1 / 500)
    cell = stability.run_cell("implicit", 1e9, 1 / 30, 1.0, 4, 0.1, ref9)
    assert cell["status"] in ("S", "O") and cell["energy_gain"] <= 0.01


def test_checker_masses_keep_total_and_ratio():
    from warp_cloth.mesh import TriMesh

    m = stability.checker_masses(4, 0.15, 1000.0)
    assert np.isclose(m.sum(), 0.15)  # the 1 m^2 sheet keeps its mass
    per_area = m / TriMesh.grid(4, 4).vertex_areas()
    levels = np.unique(np.round(per_area / per_area.min(), 6))
    assert np.allclose(levels, [1.0, 1000.0])


def test_stability_end_to_end(tmp_path):
    assert stability.main(["--methods", "explicit", "--res", "3", "--duration", "0.05", "--quick",
                           "--ks", "1e3,1e7", "--ref-dt", "0.002", "--ratios", "1,10000",
                           "--out-dir", str(tmp_path)]) == 0
    rows = list(csv.DictReader(open(tmp_path / "stability.csv")))
    assert len(rows) == 2 * 3 * 2
    assert {r["status"] for r in rows} <= {"S", "O", "E", "D"}
    assert "D" in {r["status"] for r in rows} and "S" in {r["status"] for r in rows}
    assert (tmp_path / "stability.png").stat().st_size > 1000


def test_tradeoff_without_matplotlib_still_writes_table_and_csv(tmp_path, monkeypatch):
    monkeypatch.setenv("WARP_CLOTH_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(tradeoff, "have_matplotlib", lambda: False)
    monkeypatch.setattr(stability, "have_matplotlib", lambda: False)
    out = tmp_path / "bo"
    assert tradeoff.main(["--res", "3", "--duration", "0.1", "--ref-substeps", "2", "--methods",
                          "explicit", "--out-dir", str(out), "--quick", "--no-progress"]) == 0
    assert stability.main(["--methods", "explicit", "--res", "3", "--duration", "0.05", "--quick",
                           "--out-dir", str(out)]) == 0
    names = set(os.listdir(out))
    assert {"tradeoff_hanging.csv", "tradeoff_hanging.md", "stability.csv", "stability.md"} <= names
    assert not any(n.endswith(".png") for n in names)


def test_contact_bench_equal_work_rows(capsys):
    from warp_cloth.bench import contact

    # 30 frames: the sheet (dropped 0.1 m above the sphere, lands after ~9) lies on it; 12
    # cells follow the 0.3 m sphere's curvature (6 are curved for it: its vertices then rest
    # off the sphere, above the triangles its feature entries hold, `FeatureContact`)
    argv = ["--res", "12", "--warmup", "30", "--frames", "1", "--rounds", "1",
            "--solver", "explicit", "pbd", "--only", "sphere", "--json"]
    assert contact.main(argv) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [(r["solver"], r["config"]) for r in rows] == [
        ("explicit", "sphere"), ("explicit", contact.FLOOR), ("pbd", "sphere")]
    for r in rows:
        for k in ("ms_per_frame_without", "ms_per_frame_with"):
            assert math.isfinite(r[k]) and r[k] > 0
        assert math.isclose(r["overhead"], r["ms_per_frame_with"] / r["ms_per_frame_without"] - 1)
        assert r["vertices"] == 169 and r["substeps"] >= 1 and r["captured"]
        assert 0 < r["vertices_in_contact"] <= r["vertices"]
    by = {r["config"]: r for r in rows if r["solver"] == "explicit"}
    # the floor shares the baseline of the sphere row, has no target, and does the same contact
    assert by[contact.FLOOR]["ms_per_frame_without"] == by["sphere"]["ms_per_frame_without"]
    assert by[contact.FLOOR]["target"] is None and by["sphere"]["target"] == 0.20
    assert by[contact.FLOOR]["floor_max_deviation"] < 1e-4


def test_selfcollision_bench_reports_both_variants(capsys):
    import json

    from warp_cloth.bench import selfcollision

    assert selfcollision.main(["--solver", "explicit", "--res", "6", "--warmup", "60",
                               "--rounds", "1", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [(r["solver"], r["broadphase"], r["self_motion"]) for r in rows] == [
        ("explicit", "grid", 0.0), ("explicit", "grid", 0.25), ("explicit", "bvh", 0.0),
        ("explicit", "bvh", 0.25)]
    for r in rows:
        assert r["ms_step_with"] > 0 and r["ms_step_without"] > 0
        assert r["contacts"] > 0  # it timed the folded, touching state
        # explicit Euler's frames are replayed as recorded graphs, as a scene run does; the
        # counts below come from the device counters the replayed graphs advance
        assert r["captured"] is True
    assert len({r["ms_step_without"] for r in rows}) == 1  # one baseline per solver
    every, spans = rows[2], rows[3]
    assert every["responses"] == every["substeps"]  # self_motion 0: after every step
    assert 1 <= spans["responses"] < every["responses"]  # spans: the frame's end at least
    assert selfcollision.main(["--scenes", "twist", "--solver", "pd", "--res", "4", "--warmup",
                               "30", "--rounds", "1", "--broadphase", "bvh", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [(r["scene"], r["res"], r["solver"], r["self_motion"]) for r in rows] == [
        ("twist", 4, "pd", 0.0), ("twist", 4, "pd", 0.25)]
    assert all(r["ms_step_with"] > 0 and r["ms_step_without"] > 0 for r in rows)
    assert selfcollision.main(["--solver", "explicit", "--res", "6", "--warmup", "60",
                               "--rounds", "1", "--broadphase", "bvh", "--self-motion", "0",
                               "--no-capture", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["captured"] for r in rows] == [False]
    assert rows[0]["responses"] == rows[0]["substeps"]
    # implicit Euler's guesses, each a row of its own (the guess reaches the solver)
    assert selfcollision.main(["--solver", "implicit", "--res", "6", "--warmup", "40",
                               "--rounds", "1", "--broadphase", "bvh", "--self-motion", "0.25",
                               "--initial-guess", "inertial", "auto", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["solver"] for r in rows] == ["implicit (inertial)", "implicit"]
    with pytest.raises(SystemExit):
        selfcollision.main(["--self-motion", "-1"])


def test_ccd_bench_totals_line(capsys):
    from warp_cloth.bench import ccd

    here = __import__("os").path.dirname(__file__)
    assert ccd.main(["--queries", here + "/data/ccd-queries", "--repeats", "1"]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith("total: queries=179 ") and "false_negatives=0" in last


def test_ccd_bench_constructed_queries(capsys):
    """``--constructed N``: N built positives of each kind, reported with their misses; bad
    counts and angles are refused before any work."""
    from warp_cloth.bench import ccd

    here = __import__("os").path.dirname(__file__)
    assert ccd.main(["--queries", here + "/data/ccd-queries", "--repeats", "1",
                     "--constructed", "60", "--angle", "1e-4"]) == 0
    out = capsys.readouterr().out
    assert "constructed edge-edge (angle 0.0001): queries=60 missed=0" in out
    assert "constructed vertex-face (angle 0.0001): queries=60 missed=0" in out
    for bad in (["--constructed", "-1"], ["--angle", "nan"], ["--angle", "-1e-7"]):
        with pytest.raises(SystemExit):
            ccd.main(["--queries", here + "/data/ccd-queries", *bad])
    with pytest.raises(ValueError, match="angle"):
        ccd.constructed_queries(4, True, angle=float("inf"))


def test_render_bench_reports_time_and_page_size(capsys):
    import json

    from warp_cloth.bench import render

    assert render.main(["--res", "6", "--frames", "6", "--torus", "12,8", "--size", "64x48",
                        "--rounds", "2", "--json"]) == 0
    row = json.loads(capsys.readouterr().out)
    assert row["vertices"] == 49 and row["torus_triangles"] == 192 and row["frames"] == 6
    assert row["obstacle_triangles"] == 192 + 2            # the torus and the floor
    assert row["s_per_frame_no_shadows"] > 0 and row["s_per_frame_shadows"] > 0
    assert 0 < row["page_bytes_per_frame"] and row["page_fixed_bytes"] < row["page_bytes"]


def test_limits_bench_on_built_in_scenes(capsys):
    """`bench limits --scenes`: a row per solver, each within the 1 % limit plus its tolerance
    (the frames where the default hanging scene under PD needs the most sweeps are 7-8: 9 frames
    reach them)."""
    from warp_cloth.bench import limits

    assert limits.main(["--scenes", "hanging", "--frames", "9"]) == 0
    rows = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("| hanging |")]
    assert [r.split("|")[2].strip() for r in rows] == ["explicit", "implicit", "pbd", "pd"]
    for r in rows:
        cells = [c.strip() for c in r.split("|")[1:-1]]
        assert float(cells[2]) <= 1.1 + 1e-6 and cells[3] == "0", r
    with pytest.raises(SystemExit):
        limits.main(["--scenes", "nope"])


def test_scenes_bench_measures_the_collision_checks(capsys):
    """`bench scenes`: a row per scene and solver with the issue's columns. The energy rise is
    taken only over frames where no obstacle moved: the mesh scene's torus rests for 0.8 s, so
    at 60 fps exactly frames 1-48 count; the spin scene's sphere turns steadily from 1.5 s, so
    its turning-frame rise exists once frames pass 90, and a still table has none. Every free
    vertex keeps the thickness less 0.1 mm from the obstacles, and the strain rule compares
    with explicit Euler's row of the same scene."""
    import json

    from warp_cloth.bench import scenes

    assert scenes.main(["--scenes", "mesh,spin,table", "--solver", "explicit", "pd", "--res",
                        "4", "--frames", "95", "--json"]) == 0
    rows = {(r["scene"], r["solver"]): r for r in json.loads(capsys.readouterr().out)}
    assert set(rows) == {(s, m) for s in ("mesh", "spin", "table") for m in ("explicit", "pd")}
    assert rows["mesh", "explicit"]["still_frames"] == 48
    assert rows["table", "pd"]["still_frames"] == 94
    assert rows["spin", "pd"]["still_frames"] == 60  # the spin starts at 1 s
    assert rows["spin", "pd"]["rise_turning"] is not None
    assert rows["table", "pd"]["rise_turning"] is None
    for r in rows.values():
        assert r["clearance_mm"] >= r["thickness_mm"] - 0.1 - 1e-6, r
        assert r["crossing_frames"] == 0
        ex = rows[r["scene"], "explicit"]["max_strain"]
        assert r["ratio_to_explicit"] == pytest.approx(r["max_strain"] / ex)
        assert r["strain_ok"] == (r["max_strain"] <= 0.05 or r["max_strain"] <= 1.5 * ex)
    with pytest.raises(SystemExit):
        scenes.main(["--scenes", "hanging"])  # no obstacles


def test_meshes_bench_checks_are_exact_and_find_what_self_collision_prevents(capsys):
    """`bench meshes`: its own crossing test (float64 numpy, no simulator code) counts the
    exact crossings of two triangles through each other; the irregular fold under PD is clean
    with self-collision (exit 0) and crosses without it (exit 1), its count of crossing frames
    equal to the run's own Warp checker's."""
    from warp_cloth.bench import meshes

    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0],
                  [0.2, 0.2, -1], [0.2, 0.2, 1], [3, 3, 0.0]])
    tris = np.array([[0, 1, 2], [3, 4, 5]])
    assert meshes.segment_triangle_hits(x, meshes.edges_of(tris), x, tris, True) == 2
    x[3:5, 0] += 2.0
    assert meshes.segment_triangle_hits(x, meshes.edges_of(tris), x, tris, True) == 0
    on = meshes.run_case("jitterfold", "pd", 40)
    assert not meshes.failed(on) and on["crossing_frames"] == 0 and on["nan_frames"] == 0
    assert abs(on["clearance"] - meshes.THICKNESS) < meshes.CLEARANCE_SLACK
    off = meshes.run_case("jitterfold", "pd", 40, self_collision=False)
    assert meshes.failed(off) and off["crossing_frames"] == off["run_crossing_frames"] > 0
    rc = meshes.main(["--cases", "jitterfold", "--solver", "pd", "--frames", "40",
                      "--self-collision", "off"])
    assert rc == 1 and "| jitterfold | pd |" in capsys.readouterr().out


def test_meshes_bench_lumpy_obstacle_is_written_as_exporters_do_and_read_back_closed():
    """`bench meshes`' ``lumpy`` case: the obstacle's source has one vertex per face corner and
    a tenth of its faces wound the other way; the obstacle is closed, welded and wound
    outward (the case itself, four solvers: docs/bench/meshes.md)."""
    from warp_cloth.bench import meshes

    ob = meshes.lumpy_obstacle()
    src = ob.source
    assert len(src.vertices) == 3 * len(src.triangles) and len(src.boundary_edges) > 0
    assert ob.closed and len(ob.vertices) == 642 and len(ob.triangles) == 1280
    d = np.concatenate([ob.triangles[:, [0, 1]], ob.triangles[:, [1, 2]], ob.triangles[:, [2, 0]]])
    assert len({tuple(e) for e in d.tolist()}) == len(d)
    assert abs(float(ob.vertices[:, 1].min())) < 1e-12
