"""A sheet falls onto a moving triangle-mesh obstacle (warp_cloth/assets/torus.obj, 960 triangles).

    python examples/mesh_obstacle.py --out mesh.usd [--frames 180 --mesh warp_cloth/assets/torus.obj]

The torus is a closed `MeshObstacle` queried through Warp's BVH; it rests, then slides 0.3 m and
tilts 25 degrees along a `KeyframePath`, then comes back level. Any closed or open OBJ works
with --mesh (closed meshes push vertices out, open ones are two-sided).
"""

import argparse

from warp_cloth.contact_scenes import mesh
from warp_cloth.util import quiet_warp


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="mesh.usd")
    p.add_argument("--frames", type=int, default=180)
    p.add_argument("--res", type=int, default=32)
    p.add_argument("--mesh", default=None, help="an .obj file (default: warp_cloth/assets/torus.obj)")
    p.add_argument("--solver", default="explicit")
    p.add_argument("--device", default=None)
    args = p.parse_args()
    quiet_warp()
    scene = mesh(frames=args.frames, res=args.res, mesh_file=args.mesh, solver=args.solver,
                 device=args.device)
    print(scene.run(args.out).summary())


if __name__ == "__main__":
    main()
