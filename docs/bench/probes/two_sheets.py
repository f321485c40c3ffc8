"""Two parallel 8 x 8 sheets in free fall, the upper one 2 cm above moving down 1 m/s faster
(env RES, REL): internal contact only, so the momentum would be p0 + M g t if the contact kept
it. ``python docs/bench/probes/two_sheets.py SOLVER [FRAMES]`` prints the momentum over that,
the share of the relative momentum lost, each sheet's mean vertical velocity less free fall's,
the largest one-frame energy rise. Measured 2026-12-07: docs/bench/selfcollision.md."""
import sys, os, numpy as np
from warp_cloth.util import quiet_warp
quiet_warp()
from warp_cloth import ClothModel, make_solver, TriMesh
from warp_cloth.collision import CollisionStage
from warp_cloth.scene import suggest_substeps
from warp_cloth.diagnostics import Meter
solver = sys.argv[1]; NF = int(sys.argv[2]) if len(sys.argv) > 2 else 30
res = int(os.environ.get("RES", "8")); rel = float(os.environ.get("REL", "1.0"))
g = TriMesh.grid(res, res, size=0.5, plane="xz", origin=(-0.25, 3.0, -0.25))
nv = len(g.vertices)
V = np.concatenate([g.vertices, g.vertices + [0.01, 0.02, 0.013]])
mesh = TriMesh(V, np.concatenate([g.triangles, g.triangles + nv]), name="cloth")
model = ClothModel(mesh, density=0.15, stretch_stiffness=1000.0, damping=0.0)
v0 = np.zeros_like(V); v0[nv:, 1] = -rel
model.initial_velocity = v0
stage = CollisionStage(model, [], thickness=0.005, self_collision=True)
s = make_solver(solver, model, collision=stage)
st = model.state(); n = suggest_substeps(s, 1/60); dt = 1/60/n; stage.plan(n)
m = model.masses; M = m.sum(); p0 = (m[:, None] * v0).sum(0)
meter = Meter(model); E = [meter(st).energy]
for f in range(NF):
    for _ in range(n): s.step(st, dt)
    stage.frame_end(); E.append(meter(st).energy)
v = st.v.numpy(); p = (m[:, None] * v).sum(0)
expect = p0[1] - 9.81 * M * NF / 60
vl = v[:nv, 1].mean() + 9.81 * NF / 60; vu = v[nv:, 1].mean() + 9.81 * NF / 60
d = np.diff(E)
print(solver, "p_y/expected %.4f" % (p[1] / expect), "lost %.3f of the relative momentum" % ((p[1] - expect) / p0[1]),
      "lower/upper v - g t: %.3f %.3f" % (vl, vu), "max rise %.1e" % d.max(),
      {k: v for k, v in stage.self_collision.stats.items() if k.endswith("_total") and v and k in ("self_contacts_total", "self_zones_total", "self_fallback_all_total")})
