"""A 1.5 m x 1 m flag pinned along its left edge, flapping in gusty 6 m/s wind.

    python examples/flag.py --out flag.usd [--wind 6 --frames 180 --solver explicit]

Wind acts per triangle (drag and lift against the relative air velocity, travelling gusts); see
`warp_cloth.forces.wind`.
"""

import argparse

import warp_cloth as wc
from warp_cloth.forces.wind import Wind
from warp_cloth.util import quiet_warp


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="flag.usd")
    p.add_argument("--frames", type=int, default=180)
    p.add_argument("--wind", type=float, default=6.0, help="mean wind speed, m/s")
    p.add_argument("--res", type=int, default=24)
    p.add_argument("--solver", default="explicit")
    p.add_argument("--device", default=None)
    args = p.parse_args()
    quiet_warp()

    nx, ny = args.res, max(1, round(args.res * 2 / 3))
    mesh = wc.TriMesh.grid(nx, ny, size=(1.5, 1.5 * ny / nx), plane="xy", origin=(0, 1, 0), name="flag")
    pins = [j * (nx + 1) for j in range(ny + 1)]  # the left edge, i = 0
    wind = Wind(velocity=(args.wind, 0.0, 0.15 * args.wind), gust_amplitude=0.3)
    model = wc.ClothModel(mesh, density=0.15, stretch_stiffness=1000.0, pins=pins, damping=0.1,
                          wind=wind, device=args.device)
    scene = wc.Scene(model, wc.make_solver(args.solver, model), fps=60, frames=args.frames, name="flag")
    print(scene.run(args.out).summary())


if __name__ == "__main__":
    main()
