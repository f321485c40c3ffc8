"""A sheet drapes over a sphere that starts spinning; friction carries the cloth round.

    python examples/spin.py --out spin.usd [--frames 180 --spin 3 --friction 0.6]

The sphere's `Motion` has an angular velocity about +y that starts at 1 s and ramps up over
0.5 s; the motion is evaluated on the device from the simulated time, so the step stays a
replayable graph. Prints the cloth's angular momentum about the axis (zero with --friction 0).
"""

import argparse

import numpy as np

from warp_cloth.contact_scenes import spin
from warp_cloth.util import quiet_warp


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="spin.usd")
    p.add_argument("--frames", type=int, default=180)
    p.add_argument("--res", type=int, default=32)
    p.add_argument("--spin", type=float, default=3.0, help="rad/s about +y")
    p.add_argument("--solver", default="explicit")
    p.add_argument("--friction", type=float, default=0.6, help="Coulomb mu_T")
    p.add_argument("--device", default=None)
    args = p.parse_args()
    quiet_warp()
    scene = spin(frames=args.frames, res=args.res, spin_rate=args.spin, solver=args.solver,
                 friction=args.friction, device=args.device)
    print(scene.run(args.out).summary())
    st, model = scene.state, scene.model
    r = st.positions() - scene.contact.obstacles[0].position
    ly = float((model.masses[:, None] * np.cross(r, st.velocities()))[:, 1].sum())
    print(f"cloth angular momentum about the spin axis: {ly:.4g} kg m^2/s")


if __name__ == "__main__":
    main()
