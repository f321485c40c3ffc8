"""Two parallel sheets meeting head on, no gravity: the lower rises at 1 m/s into the upper,
2 cm above, falling at 0.5 m/s; the upper ``RATIO`` times as heavy (env; RES cells a side,
default 8). Internal contact only, so a response that keeps momentum ends with the pair's
momentum ``p0``. ``python docs/bench/probes/head_on.py SOLVER [FRAMES]`` prints, every 3
frames, the momentum over ``p0`` and each sheet's mean vertical velocity (their common one,
``p0 / M``, on the first line). Env ``SKW``: solver options (a Python dict). Measured
2026-12-08: docs/bench/selfcollision.md."""
import os
import sys

import numpy as np

from warp_cloth.util import quiet_warp
quiet_warp()
from warp_cloth import ClothModel, Scene, TriMesh, make_solver
from warp_cloth.collision import CollisionStage

solver = sys.argv[1]
frames = int(sys.argv[2]) if len(sys.argv) > 2 else 30
res = int(os.environ.get("RES", "8"))
ratio = float(os.environ.get("RATIO", "1"))
g1 = TriMesh.grid(res, res, size=0.5, plane="xz", origin=(-0.25, 0.0, -0.25))
g2 = TriMesh.grid(res, res, size=0.5, plane="xz", origin=(-0.23, 0.02, -0.27))
k = g1.num_vertices
mesh = TriMesh(np.concatenate([g1.vertices, g2.vertices]),
               np.concatenate([g1.triangles, g2.triangles + k]), name="cloth")
v0 = np.zeros((2 * k, 3))
v0[:k, 1], v0[k:, 1] = 1.0, -0.5
m = np.concatenate([np.full(k, 0.0375 / k), np.full(k, ratio * 0.0375 / k)])
model = ClothModel(mesh, masses=m, stretch_stiffness=1000.0, gravity=(0, 0, 0), velocity=v0)
stage = CollisionStage(model, [], thickness=0.004, self_collision=True)
sol = make_solver(solver, model, collision=stage, **eval(os.environ.get("SKW", "{}")))
scene = Scene(model, sol, fps=60, frames=frames)
p0 = float(m @ v0[:, 1])
print(f"{solver}: p0 {p0:.5f} kg m/s, common velocity {p0 / m.sum():+.4f} m/s")


def on_frame(f, st):
    if f % 3 == 0 or f == frames - 1:
        v = st.v.numpy()
        print(f"frame {f:3d}: momentum / p0 {float(m @ v[:, 1]) / p0:.4f}, lower "
              f"{v[:k, 1].mean():+.4f} m/s, upper {v[k:, 1].mean():+.4f} m/s")


scene.run(None, quiet=True, energy=False, on_frame=on_frame)
