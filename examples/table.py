"""A sheet falls on a table (a box) with most of it over the edge and slides off onto the floor.

    python examples/table.py --out table.usd [--frames 180 --friction 0.15 --solver explicit]

The table is a `Box` (0.8 x 0.75 x 0.6 m), the floor a `Plane`; low friction lets the overhanging
weight pull the cloth off. Same as ``warp-cloth run table``.
"""

import argparse

from warp_cloth.contact_scenes import table
from warp_cloth.util import quiet_warp


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="table.usd")
    p.add_argument("--frames", type=int, default=180)
    p.add_argument("--res", type=int, default=32)
    p.add_argument("--solver", default="explicit")
    p.add_argument("--friction", type=float, default=0.15, help="Coulomb mu_T")
    p.add_argument("--device", default=None)
    args = p.parse_args()
    quiet_warp()
    scene = table(frames=args.frames, res=args.res, solver=args.solver, friction=args.friction,
                  device=args.device)
    print(scene.run(args.out).summary())


if __name__ == "__main__":
    main()
