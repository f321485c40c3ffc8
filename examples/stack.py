"""Three sheets, one above the other, dropped onto a sphere on the ground: they drape over it
and over each other without passing through.

    python examples/stack.py --out stack.usd [--frames 150 --solver pd]

Self-collision (a broad phase over the cloth, continuous vertex-triangle and edge-edge tests,
projection rounds and impact zones, and with implicit Euler or projective dynamics the
self-contacts inside the solve) is on. Every frame is checked for crossing (edge, triangle) pairs
(`check_intersections`); the script exits 1 if any frame has one. Same scene as
``warp-cloth run stack``.
"""

import argparse

from warp_cloth.contact_scenes import stack
from warp_cloth.util import quiet_warp


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="stack.usd")
    p.add_argument("--frames", type=int, default=150)
    p.add_argument("--solver", default="pd", choices=["explicit", "implicit", "pbd", "pd"])
    p.add_argument("--device", default=None)
    args = p.parse_args()
    quiet_warp()
    scene = stack(frames=args.frames, solver=args.solver, device=args.device)
    stats = scene.run(args.out, check_intersections=True)
    print(stats.summary())
    print(f"frames with crossing (edge, triangle) pairs: {stats.crossing_frames} "
          f"(at most {stats.max_crossings} pairs in a frame)")
    return 1 if stats.crossing_frames else 0


if __name__ == "__main__":
    raise SystemExit(main())
