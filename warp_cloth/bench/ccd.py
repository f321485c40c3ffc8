"""``warp-cloth bench ccd [--queries DIR]``: the project's continuous collision tests on CCD queries
with exact ground truth (default: the shared sample queries of Wang et al. 2021,
``../shared/data/ccd-sample-queries``, or ``$WARP_CLOTH_CCD_QUERIES``).

Reads every ``*.csv`` under DIR in the sample-queries format (8 rows a query; 7 integer columns
``x_num, x_den, y_num, y_den, z_num, z_den, truth``; a file under a folder named ``edge-edge`` holds
edge-edge queries, any other vertex-face queries), converts the exact rationals to float64 once
(`fractions.Fraction`), runs `warp_cloth.collision.geometry.ccd_vertex_triangle` /
`ccd_edge_edge` on each query (one thread per query) and prints per file and in total: queries,
positives (ground truth), false negatives, false positives, capped queries (conservative hits
after ``--max-iter`` advances) and microseconds per query (kernel time over the file, median of
``--repeats``). The last line is the totals::

    total: queries=N positives=P false_negatives=FN false_positives=FP us_per_query=T

``--delta`` is the minimum separation reported as contact, relative to the query's largest
coordinate (at least 1): default 1e-10 (the queries' ground truth is exact contact, and float64
coordinates carry round-off near 1e-16 of their magnitude). Measured here: 0 false negatives
and 277 false positives of 4,884 queries at 1e-10; 158 at 1e-12; with 0, 87 false negatives.
Exit status 1 when any false negative is found.

``--constructed N`` adds N queries of each kind built to touch at a known time
(`constructed_queries`: random primitives meeting at a point, half of them nearly degenerate,
``--angle`` apart: edges at that angle, triangles that thin; a tenth touching at t = 0 and a tenth
at t = 1; at the origin, far from it and at mixed offsets; some moving together), every one a
positive, and prints their misses. Measured here (10,800 of each kind, seed 0): no edge-edge
miss at ``--angle`` 1e-4 to 1e-7 (136 of a similar set at 1e-7 before the closest points of
nearly parallel edges were taken from cross products, 2026-11-24); no vertex-triangle miss at
1e-4 to 1e-11. Before the distance to a triangle carried its round-off bound
(`geometry.vt_round_off`, 2026-11-24) 17 slivers were missed at 1e-6 and 266 at 1e-7: the
plane of a triangle that thin is evaluated in float64 with a relative error of about
1e-16 / thinness (the cross product of two nearly parallel edges cancels), so a point lying in
it was measured up to about ``1e-16 |ap| / thinness`` away (exact arithmetic on the same
rounded inputs: 1e-17 to 3e-15) and the advancement stepped past it. The shared queries'
counts did not change with the bound (277 false positives).
"""

from __future__ import annotations

import argparse
import glob
import json
import math
import os
import sys
import time
from fractions import Fraction

import numpy as np
import warp as wp

from ..util import quiet_warp

__all__ = ["main", "read_queries", "run_queries", "default_queries_dir", "constructed_queries"]


def default_queries_dir() -> str | None:
    env = os.environ.get("WARP_CLOTH_CCD_QUERIES")
    if env:
        return env
    here = os.path.dirname(os.path.abspath(__file__))
    for up in (3, 4):
        root = here
        for _ in range(up):
            root = os.path.dirname(root)
        p = os.path.join(root, "shared", "data", "ccd-sample-queries")
        if os.path.isdir(p):
            return p
    for p in (os.path.join(os.getcwd(), "..", "shared", "data", "ccd-sample-queries"),):
        if os.path.isdir(p):
            return os.path.abspath(p)
    return None


def read_queries(path: str):
    """``(points (Q, 8, 3) float64, truth (Q,) bool)`` from one CSV of the sample-queries format.
    Raises `ValueError` naming the file and line on a malformed row."""
    rows, truth = [], []
    with open(path, encoding="ascii") as fh:
        for ln, line in enumerate(fh, 1):
            line = line.strip()
            if not line:
                continue
            parts = line.split(",")
            if len(parts) != 7:
                raise ValueError(f"{path}:{ln}: expected 7 integer columns, got {len(parts)}")
            try:
                ints = [int(p) for p in parts]
                xyz = [float(Fraction(ints[2 * k], ints[2 * k + 1])) for k in range(3)]
            except (ValueError, ZeroDivisionError) as e:
                raise ValueError(f"{path}:{ln}: {e}") from None
            rows.append(xyz)
            truth.append(ints[6])
    if len(rows) % 8:
        raise ValueError(f"{path}: {len(rows)} rows is not a multiple of 8")
    pts = np.asarray(rows, dtype=np.float64).reshape(-1, 8, 3)
    tr = np.asarray(truth, dtype=np.int64).reshape(-1, 8)
    if (tr != tr[:, :1]).any():
        bad = int(np.flatnonzero((tr != tr[:, :1]).any(axis=1))[0])
        raise ValueError(f"{path}: query {bad} has differing ground-truth flags")
    return pts, tr[:, 0].astype(bool)


def run_queries(points: np.ndarray, edge_edge: bool, delta: float = 1e-10, max_iter: int = 4096,
                device="cpu", repeats: int = 1):
    """Run the project's CCD on ``points`` (Q, 8, 3): ``(status (Q,), toi (Q,), seconds)``."""
    from ..collision.geometry import ccd_queries_kernel

    q = len(points)
    if q == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0), 0.0
    pts = wp.array(points, dtype=wp.vec3d, device=device)
    status = wp.zeros(q, dtype=int, device=device)
    toi = wp.zeros(q, dtype=wp.float64, device=device)
    args = [pts, int(edge_edge), wp.float64(delta), int(max_iter), status, toi]
    wp.launch(ccd_queries_kernel, q, args, device=device)  # compile and warm up
    wp.synchronize_device(device)
    times = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        wp.launch(ccd_queries_kernel, q, args, device=device)
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
    return status.numpy(), toi.numpy(), float(np.median(times))


def constructed_queries(n: int, edge_edge: bool, seed: int = 0, angle: float = 1e-7):
    """``(points (n, 8, 3), times (n,), degenerate (n,) bool)``: queries whose primitives touch
    at ``times`` (exactly, before the positions are rounded to float64): two edges crossing at
    a point, or a point of a triangle, at the touching time, with random velocities. Every
    second query is nearly degenerate: edges ``angle`` rad apart, or a triangle whose third
    corner lies ``angle`` (times its size) off the line of the other two. A tenth touch at
    t = 0 and a tenth at t = 1; offsets cycle through the origin, (1e3, -2e3, 5e2) and
    (-7.5, 3.1, 100); velocity scales through 1e-4, 1 and 100; every fifth query moves rigidly
    (no relative motion). The slivers test the round-off bound of the distance to a thin
    triangle's plane (`geometry.vt_round_off`)."""
    if int(n) != n or n < 0:
        raise ValueError(f"constructed_queries: n must be a whole number >= 0, got {n!r}")
    if not (math.isfinite(angle) and angle >= 0.0):
        raise ValueError(f"constructed_queries: angle must be a finite number >= 0, got {angle!r}")
    n = int(n)
    rng = np.random.default_rng(seed)
    pts = np.zeros((n, 8, 3))
    times = rng.uniform(0.0, 1.0, n)
    times[: n // 10], times[n // 10: n // 5] = 0.0, 1.0
    degenerate = np.arange(n) % 2 == 1
    offsets = np.array([(0.0, 0.0, 0.0), (1e3, -2e3, 5e2), (-7.5, 3.1, 100.0)])
    for k in range(n):
        scale = [1e-3, 1.0, 10.0][(k // 3) % 3]
        if edge_edge:
            c = scale * rng.normal(size=3)
            d1 = rng.normal(size=3)
            d1 /= np.linalg.norm(d1)
            d2 = d1 + angle * rng.normal(size=3) if degenerate[k] else rng.normal(size=3)
            d2 /= np.linalg.norm(d2)
            s, t = rng.uniform(0.0, 1.0, 2)
            l1, l2 = scale * rng.uniform(0.01, 1.0, 2)
            x = np.array([c - s * l1 * d1, c + (1 - s) * l1 * d1, c - t * l2 * d2,
                          c + (1 - t) * l2 * d2])
        else:
            tri = scale * rng.normal(size=(3, 3))
            if degenerate[k]:
                u = rng.uniform()
                tri[2] = tri[0] + u * (tri[1] - tri[0]) + angle * scale * rng.normal(size=3)
            w = rng.dirichlet([1.0, 1.0, 1.0])
            x = np.vstack([w @ tri, tri])
        x = x + offsets[k % 3]
        v = rng.normal(size=(4, 3)) * [1e-4, 1.0, 100.0][(k // 9) % 3]
        if k % 5 == 0:
            v[:] = v[0]
        pts[k, :4], pts[k, 4:] = x - times[k] * v, x + (1 - times[k]) * v
    return pts, times, degenerate


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="warp-cloth bench ccd", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--queries", default=None, help="folder searched for *.csv (recursively)")
    p.add_argument("--delta", type=float, default=1e-10, help="minimum separation (m)")
    p.add_argument("--max-iter", type=int, default=4096, help="advances before a capped hit")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--device", default=None)
    p.add_argument("--json", action="store_true")
    p.add_argument("--constructed", type=int, default=0, metavar="N",
                   help="also N constructed positives of each kind (see above)")
    p.add_argument("--angle", type=float, default=1e-7,
                   help="the constructed degenerate queries' angle / thinness (default 1e-7)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.constructed < 0:
        p.error("--constructed must be >= 0")
    if not (math.isfinite(args.angle) and args.angle >= 0.0):
        p.error(f"--angle must be a finite number >= 0 (radians, or a triangle's thinness), "
                f"got {args.angle}")
    quiet_warp()
    root = args.queries or default_queries_dir()
    if root is None or not os.path.isdir(root):
        p.error(f"no query folder: {root!r} (give --queries DIR)")
    if not (args.delta >= 0) or args.max_iter < 1:
        p.error("--delta must be >= 0 and --max-iter >= 1")
    files = sorted(glob.glob(os.path.join(root, "**", "*.csv"), recursive=True))
    if not files:
        p.error(f"no *.csv under {root}")
    device = args.device or "cpu"
    tot = dict(queries=0, positives=0, false_negatives=0, false_positives=0, capped=0, seconds=0.0)
    rows = []
    for f in files:
        ee = "edge-edge" in os.path.relpath(f, root).split(os.sep)
        try:
            pts, truth = read_queries(f)
        except (OSError, ValueError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        status, toi, sec = run_queries(pts, ee, args.delta, args.max_iter, device, args.repeats)
        hit = status != 0
        r = dict(file=os.path.relpath(f, root), kind="edge-edge" if ee else "vertex-face",
                 queries=len(truth), positives=int(truth.sum()),
                 false_negatives=int((truth & ~hit).sum()),
                 false_positives=int((~truth & hit).sum()), capped=int((status == 2).sum()),
                 us_per_query=1e6 * sec / max(len(truth), 1))
        rows.append(r)
        for k in ("queries", "positives", "false_negatives", "false_positives", "capped"):
            tot[k] += r[k]
        tot["seconds"] += sec
        if not args.json:
            print(f"{r['file']}: queries={r['queries']} positives={r['positives']} "
                  f"false_negatives={r['false_negatives']} false_positives={r['false_positives']} "
                  f"capped={r['capped']} us_per_query={r['us_per_query']:.2f}")
    us = 1e6 * tot["seconds"] / max(tot["queries"], 1)
    built = {}
    for ee in (False, True) if args.constructed else ():
        pts, _, degen = constructed_queries(args.constructed, ee, args.seed, args.angle)
        status, _, _ = run_queries(pts, ee, args.delta, args.max_iter, device, 1)
        miss = status == 0
        kind = "edge-edge" if ee else "vertex-face"
        built[kind] = dict(queries=len(pts), missed=int(miss.sum()),
                           missed_degenerate=int((miss & degen).sum()))
        if not args.json:
            print(f"constructed {kind} (angle {args.angle:g}): queries={len(pts)} "
                  f"missed={int(miss.sum())} (nearly degenerate: {int((miss & degen).sum())})")
    if args.json:
        print(json.dumps({"files": rows, "total": {**tot, "us_per_query": us},
                          "constructed": built}, indent=1))
    print(f"total: queries={tot['queries']} positives={tot['positives']} "
          f"false_negatives={tot['false_negatives']} false_positives={tot['false_positives']} "
          f"us_per_query={us:.2f}")
    return 1 if tot["false_negatives"] else 0


if __name__ == "__main__":
    sys.exit(main())
