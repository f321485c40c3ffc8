"""Write lumpy closed meshes (icospheres with a smooth random radial relief, 0.2 m mean radius)
for ``warp-cloth run mesh --obstacle``:
``python docs/bench/probes/lumpy_meshes.py DIR`` writes DIR/lumpy1.obj .. lumpy4.obj (1,280
triangles) and DIR/m5.obj .. m16.obj (1,280 or 5,120 triangles, relief 40-75 %, 3-5 waves:
the sweep of 2026-12-07, twenty-first session), then e.g.
``warp-cloth run mesh --obstacle DIR/lumpy3.obj --solver explicit --frames 90
--check-intersections`` and ``warp-cloth check OUT.usd``. Measured 2026-12-07:
docs/bench/selfcollision.md (lumpy3 defeated explicit Euler until the sign of Warp's closest-point
query was confirmed; m10 had a cloth edge through a ridge of several creases until the dip
probe)."""
import os
import sys

import numpy as np

from warp_cloth.bench.meshes import lumpy_mesh

sys.argv += [] if len(sys.argv) > 1 else ["."]
out = sys.argv[1]
os.makedirs(out, exist_ok=True)


def lumpy(sub, seed, amp, waves):
    m = lumpy_mesh(seed, amp, waves, sub)
    return np.asarray(m.vertices), np.asarray(m.triangles)


def write(name, V, F):
    path = os.path.join(out, name + ".obj")
    with open(path, "w") as f:
        for v in V:
            f.write("v %.6f %.6f %.6f\n" % tuple(v))
        for t in F:
            f.write("f %d %d %d\n" % tuple(t + 1))
    print(path)


for seed in (1, 2, 3, 4):
    write(f"lumpy{seed}", *lumpy(3, seed, [0.35, 0.5, 0.45, 0.6][seed - 1], 3))
for seed in range(5, 17):
    write(f"m{seed}", *lumpy(3 if seed % 3 else 4, seed, 0.4 + 0.05 * (seed % 8), 3 + seed % 3))
