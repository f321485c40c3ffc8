"""A 50 x 50-vertex sheet held by two opposite edges that turn in opposite directions at
pi/3 rad/s (as Newton's cloth_twist): the middle winds up into a rope that must not pass through
itself. As the rope tightens the response falls back, now and then, to returning the whole cloth
to its start, and such a frame runs again with more steps (reported on stderr). Projective
dynamics (the default) and implicit Euler run all 600 frames of the scene without a crossing
(README, *Self-collision*); PBD, which this scene gives the springs' compliance (XPBD: plain
PBD's inextensible constraints froze at frame ~111), stops frozen at frame 257. 300 frames (5 s)
is this script's default.

    python examples/twist.py --out twist.usd [--frames 300 --solver pd]

Self-collision (a broad phase over the cloth, continuous vertex-triangle and edge-edge tests,
projection rounds and impact zones, and with implicit Euler or projective dynamics the
self-contacts inside the solve) is on. Every frame is checked for crossing (edge, triangle) pairs
(`check_intersections`); the script exits 1 if any frame has one. Same scene as
``warp-cloth run twist``.
"""

import argparse

from warp_cloth.contact_scenes import twist
from warp_cloth.util import quiet_warp


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="twist.usd")
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--solver", default="pd", choices=["explicit", "implicit", "pbd", "pd"])
    p.add_argument("--device", default=None)
    args = p.parse_args()
    quiet_warp()
    scene = twist(frames=args.frames, solver=args.solver, device=args.device)
    stats = scene.run(args.out, check_intersections=True)
    print(stats.summary())
    print(f"frames with crossing (edge, triangle) pairs: {stats.crossing_frames} "
          f"(at most {stats.max_crossings} pairs in a frame)")
    return 1 if stats.crossing_frames else 0


if __name__ == "__main__":
    raise SystemExit(main())
