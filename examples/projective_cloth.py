"""Projective dynamics (Liu et al. 2013) on the hanging cloth, written to a USD file.

    python examples/projective_cloth.py --out pd_cloth.usd --frames 120

A 1 m sheet of 0.15 kg/m^2 with 1000 N/m springs, pinned at two corners, one projective-dynamics
step per frame at 60 fps (10 local/global iterations, Chebyshev-accelerated Jacobi global steps).
The run statistics and the last step's objective per iteration are printed.
"""

import argparse

import warp as wp

from warp_cloth.scenes import hanging


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="pd_cloth.usd")
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--res", type=int, default=32, help="cells per side")
    p.add_argument("--iterations", type=int, default=10, help="local/global iterations per step")
    p.add_argument("--linear", choices=["jacobi", "chebyshev", "cg"], default="chebyshev")
    args = p.parse_args(argv)
    wp.config.quiet = True
    scene = hanging(solver="pd", res=args.res, frames=args.frames,
                    solver_options=dict(iterations=args.iterations, linear=args.linear))
    stats = scene.run(args.out, quiet=True)
    print(stats.summary())
    obj = stats.extra.get("objective", [])
    if obj:
        print("objective of the last step per iteration (J): "
              + ", ".join(f"{v:.5g}" for v in obj))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
