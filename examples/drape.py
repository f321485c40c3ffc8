"""A 1 m sheet falls onto a sphere (r = 0.3 m) and drapes over it.

    python examples/drape.py --out drape.usd [--frames 120 --solver explicit --friction 0.4]

Shows the contact API: obstacles from `warp_cloth.collision`, given once, to a `CollisionStage`
that the solver uses inside its solve; the scene draws the stage's obstacles.
"""

import argparse

import warp_cloth as wc
from warp_cloth.collision import CollisionStage, Plane, Sphere
from warp_cloth.util import quiet_warp


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="drape.usd")
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--res", type=int, default=32)
    p.add_argument("--solver", default="explicit")
    p.add_argument("--friction", type=float, default=0.4, help="Coulomb mu_T")
    p.add_argument("--device", default=None)
    args = p.parse_args()
    quiet_warp()

    mesh = wc.TriMesh.grid(args.res, args.res, size=1.0, plane="xz", origin=(-0.5, 0.9, -0.5),
                           name="cloth")
    model = wc.ClothModel(mesh, density=0.15, stretch_stiffness=1000.0, damping=0.1,
                          device=args.device)
    obstacles = [Sphere(0.3, center=(0.0, 0.5, 0.0)), Plane(point=(0.0, 0.0, 0.0))]
    stage = CollisionStage(model, obstacles, thickness=0.005, friction=args.friction,
                           restitution=0.0)
    solver = wc.make_solver(args.solver, model, collision=stage)
    scene = wc.Scene(model, solver, fps=60, frames=args.frames, name="drape")
    print(scene.run(args.out).summary())


if __name__ == "__main__":
    main()
