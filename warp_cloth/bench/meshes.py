"""``warp-cloth bench meshes``: cloth of the kinds users bring, built through the public API,
run under every solver with self-collision on, and checked on the written USD by tests that
share no code with the simulator.

The cases (``--cases``, default all) are not the built-in scenes: an irregular sheet (interior
vertices jittered by up to 0.3 of a cell, each cell split along a random diagonal) folded onto
itself, a sheet standing on its edge that falls and buckles, a sheet with a hole dropped onto a
sphere, a long strip over a box bar, two sheets of different resolution onto a sphere, an
irregular sheet onto the 9,704-triangle thin-parts mesh, a hanging sheet hit by a ball at 8 m/s,
an irregular sheet crumpled onto a small sphere, a 64 x 64 fold (``--big-res``), and an
irregular sheet onto a lumpy closed mesh as exporters write them (`lumpy_obstacle`: 1,280
triangles, ridges of several moderate creases, a tenth of its faces wound the other way, one
vertex per face corner). Each runs
``--frames`` frames at 60 fps (default 150) with each solver (``--solver``, default all four)
at its defaults, writes its USD to a temporary folder, and every written frame is read back and
checked on the host, in float64 numpy:

- **crossings**: frames with an edge of the cloth crossing one of its triangles (the pairs not
  sharing a vertex among those whose boxes overlap; segment-triangle by Moller-Trumbore), the
  run's own count (`--check-intersections`, Warp kernels) beside it;
- **NaN**: frames with a position not finite;
- **clearance**: the least distance of a vertex to the analytic obstacles (planes, spheres,
  boxes at rest) over all frames, in mm (the promise: the thickness, 5 mm, less 0.1 mm);
- **inside**: the deepest of 9 points along each cloth edge inside an analytic obstacle, mm;
- **through mesh**: frames with a cloth edge crossing the mesh obstacle's triangles or an
  obstacle edge crossing the cloth's triangles;
- max strain over all frames (the landing's peaks, not the rest state) and ms a frame.

A run that ends early (`SimulationDiverged`) is listed with its reason. ``--self-collision off``
runs the same cases without it, to see the checks find what they look for. Exit status 1 when
any row has a crossing, a NaN, a clearance short of the promise, an edge inside an obstacle or
an edge through the mesh obstacle. Measured: docs/bench/meshes.md.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time

import numpy as np

from ..collision.check import edges_of  # noqa: F401 - also the probes' (docs/bench/probes)
from ..util import quiet_warp

SOLVERS = ("explicit", "implicit", "pbd", "pd")
CASES = ("jitterfold", "vertical", "holesphere", "stripbar", "twosheets", "thinjit",
         "fastball", "crumple", "bigfold", "lumpy")
THICKNESS = 0.005
#: the obstacles' promise: no free vertex closer than the thickness less this (m)
CLEARANCE_SLACK = 1e-4


def jittered_grid(n: int, size: float, seed: int, height: float, keep_column=None):
    """An ``n`` x ``n``-cell sheet of ``size`` m at ``height``: interior vertices moved by up to
    0.3 of a cell, each cell split along a random diagonal (``seed``). ``keep_column``: an x
    at which the vertices keep their x (a fold line no edge spans)."""
    from .. import TriMesh

    rng = np.random.default_rng(seed)
    g = TriMesh.grid(n, n, size=size, plane="xz", origin=(-size / 2, height, -size / 2))
    v = g.vertices.copy()
    h = size / n
    inner = (np.abs(v[:, 0]) < size / 2 - 1e-9) & (np.abs(v[:, 2]) < size / 2 - 1e-9)
    move_x = inner.copy()
    if keep_column is not None:
        move_x &= np.abs(v[:, 0] - keep_column) > 1e-9
    v[move_x, 0] += rng.uniform(-0.3, 0.3, move_x.sum()) * h
    v[inner, 2] += rng.uniform(-0.3, 0.3, inner.sum()) * h
    tris = []
    for i in range(n):
        for j in range(n):
            a, b = i * (n + 1) + j, i * (n + 1) + j + 1
            c, d = b + n + 1, a + n + 1
            tris += [(a, b, c), (a, c, d)] if rng.random() < 0.5 else [(a, b, d), (b, c, d)]
    return TriMesh(v, np.array(tris), name="cloth")


def _fold(x, hinge: float, degrees: float, height: float):
    """Positions with the part beyond ``x = hinge`` turned ``degrees`` up about that line."""
    x = x.copy()
    up = x[:, 0] > hinge + 1e-9
    r, a = x[up, 0] - hinge, math.radians(degrees)
    x[up, 0], x[up, 1] = hinge + r * math.cos(a), height + r * math.sin(a)
    return x


def lumpy_mesh(seed: int, amp: float, waves: float, subdivisions: int = 3):
    """A lumpy closed mesh: `TriMesh.icosphere` (``subdivisions``) of radius 0.2 m times
    ``1 + amp tanh(sum_k sin(waves c_k . p + k) / 2)``, six random directions ``c_k`` (``seed``,
    scaled by ``1 + seed % 2``). ``docs/bench/probes/lumpy_meshes.py`` writes the family
    (``lumpy3``: seed 3, 0.45, 3; ``m10``: seed 10, 0.5, 4), the tests and `lumpy_obstacle` use it."""
    from .. import TriMesh

    ico = TriMesh.icosphere(subdivisions, 1.0)
    v = np.asarray(ico.vertices)
    c = np.random.default_rng(seed).normal(size=(6, 3)) * (1 + seed % 2)
    r = 0.2 * (1 + amp * np.tanh(sum(np.sin(waves * v @ ck + k) for k, ck in enumerate(c)) / 2))
    return TriMesh(v * r[:, None], np.asarray(ico.triangles), name=f"lumpy{seed}")


def lumpy_obstacle():
    """The ``lumpy`` case's obstacle: `lumpy_mesh` (``docs/bench/probes/lumpy_meshes.py``'s
    ``lumpy1``), standing on y = 0, written as exporters do: a tenth of its faces wound the
    other way and one vertex per face corner (`obstacles.orient_closed` and `weld_seams` undo
    both; with the faces as given, a sheet dropped on it ended 42 mm inside, 24.5 % strain)."""
    from .. import TriMesh
    from ..collision import MeshObstacle

    lumpy = lumpy_mesh(1, 0.35, 3)
    v, t = np.asarray(lumpy.vertices), np.asarray(lumpy.triangles).copy()
    flip = np.random.default_rng(0).random(len(t)) < 0.1
    t[flip] = t[flip][:, ::-1]
    v = v - [0.5 * (v[:, 0].min() + v[:, 0].max()), v[:, 1].min(),
             0.5 * (v[:, 2].min() + v[:, 2].max())]
    split = TriMesh(v[t.ravel()], np.arange(3 * len(t)).reshape(-1, 3), name="lumpy")
    return MeshObstacle(split, name="lumpy")


def build_case(name: str, big_res: int = 64):
    """``(mesh, initial positions or None, pins or None, obstacles)`` of a case."""
    from .. import TriMesh
    from ..collision import Box, KeyframePath, MeshObstacle, Motion, Plane, Sphere
    from ..contact_scenes import thin_parts_mesh

    th = THICKNESS
    if name == "jitterfold":
        mesh = jittered_grid(20, 1.0, 1, th, keep_column=0.0)
        return mesh, _fold(mesh.vertices, 0.0, 110.0, th), None, [Plane()]
    if name == "vertical":  # standing on its edge, leaning and waved: falls and buckles
        mesh = TriMesh.grid(18, 18, size=0.6, plane="xy", origin=(-0.3, th + 0.002, 0.0),
                            name="cloth")
        return mesh, _vertical_start(mesh), None, [Plane()]
    if name == "holesphere":
        g = TriMesh.grid(24, 24, size=1.0, plane="xz", origin=(-0.5, 0.75, -0.5))
        v, t = g.vertices, g.triangles
        c = v[t].mean(axis=1)
        t = t[~((np.abs(c[:, 0]) < 0.18) & (np.abs(c[:, 2]) < 0.18))]
        used = np.unique(t)
        remap = -np.ones(len(v), dtype=np.int64)
        remap[used] = np.arange(len(used))
        return (TriMesh(v[used], remap[t], name="cloth"), None, None,
                [Sphere(0.25, (0.0, 0.25, 0.0)), Plane()])
    if name == "stripbar":
        mesh = TriMesh.grid(48, 3, size=1.2, plane="xz", origin=(-0.6, 0.6, -0.0375),
                            name="cloth")
        return mesh, None, None, [Box((0.02, 0.02, 0.4), (0.15, 0.4, 0.0)), Plane()]
    if name == "twosheets":
        m1 = TriMesh.grid(14, 14, size=0.7, plane="xz", origin=(-0.35, 0.6, -0.35))
        m2 = TriMesh.grid(10, 10, size=0.5, plane="xz", origin=(-0.25, 0.7, -0.25))
        v2 = m2.vertices.copy()
        a = 0.6
        v2[:, 0] = math.cos(a) * m2.vertices[:, 0] - math.sin(a) * m2.vertices[:, 2]
        v2[:, 2] = math.sin(a) * m2.vertices[:, 0] + math.cos(a) * m2.vertices[:, 2]
        v2[:, 1] += 0.02 * v2[:, 0]
        mesh = TriMesh(np.concatenate([m1.vertices, v2]),
                       np.concatenate([m1.triangles, m2.triangles + len(m1.vertices)]),
                       name="cloth")
        return mesh, None, None, [Sphere(0.15, (0.05, 0.15, 0.0)), Plane()]
    if name == "thinjit":
        g = jittered_grid(24, 0.9, 3, 0.45)
        v = g.vertices.copy()
        a = 0.5
        v[:, 0] = math.cos(a) * g.vertices[:, 0] - math.sin(a) * g.vertices[:, 2]
        v[:, 2] = math.sin(a) * g.vertices[:, 0] + math.cos(a) * g.vertices[:, 2]
        return (TriMesh(v, g.triangles, name="cloth"), None, None,
                [MeshObstacle(thin_parts_mesh(), name="thin_parts"), Plane()])
    if name == "fastball":  # a hanging sheet; a ball at 8 m/s goes 0.7 m into it and stops
        mesh = TriMesh.grid(24, 24, size=1.0, plane="xy", origin=(-0.5, 0.3, 0.0),
                            name="cloth")
        top = np.flatnonzero(np.isclose(mesh.vertices[:, 1], mesh.vertices[:, 1].max()))
        path = KeyframePath([0.1, 0.175, 0.2, 1.0],
                            [[0, 0, 0], [0, 0, 0.6], [0, 0, 0.7], [0, 0, 0.7]])
        return (mesh, None, top[::4],
                [Sphere(0.12, (0.05, 0.75, -0.6), motion=Motion(path=path)), Plane()])
    if name == "crumple":
        return (jittered_grid(28, 1.0, 7, 0.9), None, None,
                [Sphere(0.08, (0.03, 0.08, -0.02)), Plane()])
    if name == "lumpy":
        ob = lumpy_obstacle()
        top = float(ob.vertices[:, 1].max())
        mesh = TriMesh.grid(32, 32, size=1.0, plane="xz", origin=(-0.5, top + 0.1, -0.5),
                            name="cloth")
        return mesh, None, None, [ob, Plane()]
    if name == "bigfold":
        mesh = TriMesh.grid(big_res, big_res, size=1.0, plane="xz", origin=(-0.5, th, -0.5),
                            name="cloth")
        return mesh, _fold(mesh.vertices, 0.0, 100.0, th), None, [Plane()]
    raise ValueError(f"unknown case {name!r} (one of {', '.join(CASES)})")


def _vertical_start(mesh):
    """The standing sheet bent round a vertical cylinder of 0.4 m (its edges keep their
    lengths to 2e-4) and leaning 5 degrees: it falls and buckles onto itself."""
    x = mesh.vertices.copy()
    R, a = 0.4, math.radians(5.0)
    s = x[:, 0]
    x[:, 0], x[:, 2] = R * np.sin(s / R), R * (1.0 - np.cos(s / R))
    y = x[:, 1] - THICKNESS
    x[:, 1], x[:, 2] = THICKNESS + y * math.cos(a), x[:, 2] + y * math.sin(a)
    return x


def segment_triangle_hits(P, edges, Q, tris, skip_shared: bool) -> int:
    """Pairs (edge of ``P``, triangle of ``Q``) whose segment crosses the triangle (float64,
    Moller-Trumbore, over the pairs whose boxes overlap); ``skip_shared``: one mesh, pairs
    sharing a vertex left out."""
    P = np.asarray(P, dtype=np.float64)
    Q = np.asarray(Q, dtype=np.float64)
    A, B, C = Q[tris[:, 0]], Q[tris[:, 1]], Q[tris[:, 2]]
    tlo = np.minimum(np.minimum(A, B), C)
    thi = np.maximum(np.maximum(A, B), C)
    order = np.argsort(np.minimum(P[edges[:, 0], 0], P[edges[:, 1], 0]), kind="stable")
    edges = edges[order]  # sorted along x: each chunk meets a slab of the triangles
    E0, E1 = P[edges[:, 0]], P[edges[:, 1]]
    elo, ehi = np.minimum(E0, E1), np.maximum(E0, E1)
    hits = 0
    for i0 in range(0, len(edges), 128):
        sl = slice(i0, i0 + 128)
        slab = np.flatnonzero((tlo[:, 0] <= ehi[sl, 0].max()) & (thi[:, 0] >= elo[sl, 0].min()))
        over = np.all((elo[sl, None, :] <= thi[slab][None]) & (ehi[sl, None, :] >= tlo[slab][None]),
                      axis=2)
        ei, ti = np.nonzero(over)
        ei, ti = ei + i0, slab[ti]
        if skip_shared and len(ei):
            e, t = edges[ei], tris[ti]
            shared = (e[:, :1] == t).any(axis=1) | (e[:, 1:] == t).any(axis=1)
            ei, ti = ei[~shared], ti[~shared]
        if len(ei) == 0:
            continue
        o, d = E0[ei], E1[ei] - E0[ei]
        a = A[ti]
        e1, e2 = B[ti] - a, C[ti] - a
        pv = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, pv)
        ok = np.abs(det) > 1e-18
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tv = o - a
        u = np.einsum("ij,ij->i", tv, pv) * inv
        qv = np.cross(tv, e1)
        v = np.einsum("ij,ij->i", d, qv) * inv
        s = np.einsum("ij,ij->i", e2, qv) * inv
        hits += int((ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (s >= 0) & (s <= 1)).sum())
    return hits


def _signed_distance(points, ob):
    """Distance of ``points`` to an analytic obstacle at rest (negative inside), or None."""
    from ..collision import Box, Plane, Sphere

    if ob.moving:
        return None
    if isinstance(ob, Plane):
        return points[:, 1] - float(ob.position[1])
    if isinstance(ob, Sphere):
        return np.linalg.norm(points - np.asarray(ob.position), axis=1) - ob.radius
    if isinstance(ob, Box) and np.allclose(ob.rotation, (0.0, 0.0, 0.0, 1.0)):
        q = np.abs(points - np.asarray(ob.position)) - ob.half_extents
        return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)
    return None


def check_frames(frames, tris, obstacles) -> dict:
    """The module docstring's checks over ``frames`` (F, N, 3)."""
    from ..collision import MeshObstacle

    edges = edges_of(tris)
    meshes = [(np.asarray(o.vertices, np.float64), np.asarray(o.triangles, np.int64),
               edges_of(np.asarray(o.triangles, np.int64)))
              for o in obstacles if isinstance(o, MeshObstacle) and not o.moving]
    crossing = nan = through = 0
    clearance, inside = math.inf, 0.0
    ts = np.linspace(0.0, 1.0, 9)[:, None, None]
    for P in frames:
        if not np.all(np.isfinite(P)):
            nan += 1
            continue
        P = P.astype(np.float64)
        crossing += segment_triangle_hits(P, edges, P, tris, True) > 0
        samples = (P[edges[:, 0]][None] * (1 - ts) + P[edges[:, 1]][None] * ts).reshape(-1, 3)
        for ob in obstacles:
            d = _signed_distance(P, ob)
            if d is not None:
                clearance = min(clearance, float(d.min()))
                inside = max(inside, float(-_signed_distance(samples, ob).min()))
        hit = 0
        for OV, OT, OE in meshes:
            hit += segment_triangle_hits(P, edges, OV, OT, False)
            hit += segment_triangle_hits(OV, OE, P, tris, False)
        through += hit > 0
    return {"crossing_frames": crossing, "nan_frames": nan, "clearance": clearance,
            "inside": inside, "through_frames": through}


def run_case(name: str, solver: str, frames: int, self_collision: bool = True,
             big_res: int = 64, folder: str | None = None) -> dict:
    """One case with one solver: the checks of `check_frames` with the run's own figures."""
    from .. import ClothModel, Scene, SimulationDiverged, make_solver
    from ..collision import CollisionStage
    from ..usd import read_points

    mesh, x0, pins, obstacles = build_case(name, big_res)
    model = ClothModel(mesh, density=0.15, stretch_stiffness=1000.0, damping=0.1, pins=pins)
    if x0 is not None:
        model.initial_positions = x0
    stage = CollisionStage(model, obstacles, thickness=THICKNESS, friction=0.4,
                           self_collision=self_collision)
    scene = Scene(model, make_solver(solver, model, collision=stage), fps=60.0, frames=frames,
                  name=name)
    own = tempfile.mkdtemp(prefix="meshes-") if folder is None else folder
    out = os.path.join(own, f"{name}-{solver}.usd")
    t0 = time.perf_counter()
    error, stats = None, None
    try:
        stats = scene.run(out, quiet=True, check_intersections=True)
    except SimulationDiverged as e:
        error = str(e)
    wall = time.perf_counter() - t0
    _, pts, _ = read_points(out)
    row = {"case": name, "solver": solver, "vertices": model.num_vertices,
           "frames": len(pts), "error": error,
           "run_crossing_frames": None if stats is None else stats.crossing_frames,
           "max_strain": None if stats is None else stats.max_strain,
           "ms_per_frame": None if stats is None else float(stats.ms_per_frame),
           "wall_s": wall}
    row.update(check_frames(pts, np.asarray(mesh.triangles, np.int64), obstacles))
    return row


def failed(row) -> bool:
    return bool(row["crossing_frames"] or row["nan_frames"] or row["through_frames"]
                or row["inside"] > 0.0
                or row["clearance"] < THICKNESS - CLEARANCE_SLACK)


def table(rows) -> list:
    lines = ["| case | solver | vertices | frames | crossing frames (run) | NaN | clearance mm "
             "| inside mm | through mesh | max strain % | ms/frame | ok |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        strain = "-" if r["max_strain"] is None else f"{100 * r['max_strain']:.2f}"
        ms = "-" if r["ms_per_frame"] is None else f"{r['ms_per_frame']:.1f}"
        clear = "-" if math.isinf(r["clearance"]) else f"{1e3 * r['clearance']:.3f}"
        run = "-" if r["run_crossing_frames"] is None else r["run_crossing_frames"]
        ok = "no" if failed(r) else "yes"
        if r["error"]:
            ok += " (diverged)"
        lines.append(f"| {r['case']} | {r['solver']} | {r['vertices']} | {r['frames']} | "
                     f"{r['crossing_frames']} ({run}) | {r['nan_frames']} | {clear} | "
                     f"{1e3 * r['inside']:.3f} | {r['through_frames']} | {strain} | {ms} | "
                     f"{ok} |")
    return lines


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="warp-cloth bench meshes",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", default=",".join(CASES),
                   help=f"comma list (default all: {','.join(CASES)})")
    p.add_argument("--solver", nargs="+", default=list(SOLVERS), choices=SOLVERS)
    p.add_argument("--frames", type=int, default=150, help="frames per run (default 150)")
    p.add_argument("--big-res", type=int, default=64, help="cells a side of bigfold")
    p.add_argument("--self-collision", choices=("on", "off"), default="on",
                   help="off: the same runs without it (the checks then find crossings)")
    p.add_argument("--out-dir", default=None,
                   help="keep the USD files here (default: a temporary folder)")
    p.add_argument("--json", action="store_true", help="print the rows as JSON too")
    p.add_argument("--device", default=None)
    a = p.parse_args(argv)
    cases = [c.strip() for c in a.cases.split(",") if c.strip()]
    bad = [c for c in cases if c not in CASES]
    if bad:
        p.error(f"unknown case(s) {', '.join(bad)}; choose from {', '.join(CASES)}")
    if a.frames < 2:
        p.error("--frames must be at least 2")
    if a.big_res < 2:
        p.error("--big-res must be at least 2")
    if a.out_dir is not None:
        os.makedirs(a.out_dir, exist_ok=True)
    quiet_warp()
    if a.device:
        import warp as wp

        wp.set_device(a.device)
    rows = []
    for case in cases:
        for solver in a.solver:
            rows.append(run_case(case, solver, a.frames, a.self_collision == "on",
                                 a.big_res, a.out_dir))
            print(f"# {case} {solver}: {rows[-1]['wall_s']:.1f} s", file=sys.stderr)
    print(f"# users' meshes, self-collision {a.self_collision}, {a.frames} frames at 60 fps "
          "(checks: module docstring)\n")
    print("\n".join(table(rows)))
    if a.json:
        import json

        print(json.dumps(rows, default=float))
    return 1 if any(failed(r) for r in rows) else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
