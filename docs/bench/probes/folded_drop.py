"""A 20 x 20 irregular sheet, folded 60 degrees, dropped from 4 m onto the floor (5 mm
thickness, 90 frames at 60 fps): its lowest point and mean vertical velocity every 10 frames.
``python docs/bench/probes/folded_drop.py SOLVER [on|off]`` (self-collision, default on).
Measured 2026-12-07 (docs/bench/selfcollision.md): under PBD with self-collision the sheet
slows in mid-air (the response's velocity rule against a world at rest), without it it lands
at frame 60."""
import sys

from warp_cloth.util import quiet_warp

quiet_warp()
from warp_cloth import ClothModel, make_solver  # noqa: E402
from warp_cloth.bench.meshes import _fold, jittered_grid  # noqa: E402
from warp_cloth.collision import CollisionStage, Plane  # noqa: E402
from warp_cloth.scene import suggest_substeps  # noqa: E402

solver = sys.argv[1]
self_collision = (sys.argv[2] if len(sys.argv) > 2 else "on") == "on"
mesh = jittered_grid(20, 0.8, 11, 4.0)
model = ClothModel(mesh, density=0.15, stretch_stiffness=1000.0, damping=0.1)
model.initial_positions = _fold(mesh.vertices, 0.1, 60.0, 4.0)
stage = CollisionStage(model, [Plane()], thickness=0.005, friction=0.4,
                       self_collision=self_collision)
s = make_solver(solver, model, collision=stage)
st = model.state()
n = suggest_substeps(s, 1 / 60)
stage.plan(n)
for f in range(90):
    for _ in range(n):
        s.step(st, 1 / 60 / n)
    stage.frame_end()
    if f % 10 == 9:
        x, v = st.x.numpy(), st.v.numpy()
        print(f"frame {f + 1}: lowest {x[:, 1].min():.3f} m, mean vertical velocity "
              f"{v[:, 1].mean():.2f} m/s")
