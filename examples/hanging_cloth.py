"""A 1 m sheet of light cotton (0.15 kg/m^2) pinned at two corners, falling and swinging.

    python examples/hanging_cloth.py --out hanging.usd [--solver explicit --res 32 --frames 120
                                                        --no-self-collision]

Builds the scene by hand to show the API; `warp_cloth.scenes.hanging` is the packaged version.
Self-collision (a `CollisionStage` with no obstacles) keeps the swinging sheet from passing
through itself, as in the packaged scene.
"""

import argparse

import warp_cloth as wc
from warp_cloth.util import quiet_warp


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="hanging.usd")
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--res", type=int, default=32)
    p.add_argument("--solver", default="explicit")
    p.add_argument("--device", default=None)
    p.add_argument("--no-self-collision", action="store_true",
                   help="let the sheet pass through itself (faster)")
    args = p.parse_args()
    quiet_warp()

    n = args.res
    mesh = wc.TriMesh.grid(n, n, size=1.0, plane="xz", origin=(-0.5, 1.0, -0.5))
    model = wc.ClothModel(mesh, density=0.15, stretch_stiffness=1000.0, pins=[0, n], damping=0.1,
                          device=args.device)
    collision = None
    if not args.no_self_collision:
        from warp_cloth.collision import CollisionStage

        collision = CollisionStage(model, [], self_collision=True)
    solver = wc.make_solver(args.solver, model, collision=collision)
    scene = wc.Scene(model, solver, fps=60, frames=args.frames, name="hanging")
    stats = scene.run(args.out)
    print(stats.summary())


if __name__ == "__main__":
    main()
