"""``warp-cloth bench render``: what seeing a run costs: render time per frame and page size.

The ``mesh`` scene (a sheet dropped on a torus that rests, slides and tilts, then comes back, over
a floor) at ``--res`` cells a side (default 49: 2,500 vertices), with the torus remade at
``--torus U,V`` segments (default 96,64: 12,288 triangles), is simulated for ``--frames`` frames
(explicit Euler, the scene's defaults) into a USD file in a temporary folder. Then:

- render: `warp_cloth.viewer.render.Renderer` at ``--size`` (default 640x480), one ray a pixel,
  with and without shadow rays, timed over ``--rounds`` frames spread over the run after a
  warm-up render (kernel compile excluded), median; the time per primary ray beside it. The
  frame update (the cloth's points copied, its BVH refitted, normals gathered) is inside the
  timing;
- page: `warp_cloth.viewer.page.write_page` size, split into the fixed part (three.js, the player,
  triangles, obstacles) and the bytes per frame of the packed cloth points, with the page size
  that gives for a 600-frame run.

Timings on this shared 2-core machine are noisy; the ratio shadows / no shadows is measured in
the same run.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import tempfile
import time

import numpy as np

from ..util import quiet_warp


def torus_obj(path, nu: int, nv: int, major: float = 0.25, minor: float = 0.08) -> int:
    """Write a closed, outward-oriented torus (the shape of ``assets/torus.obj``) with ``nu``
    x ``nv`` segments; returns its triangle count."""
    u = 2 * np.pi * np.arange(nu) / nu
    w = 2 * np.pi * np.arange(nv) / nv
    r = major + minor * np.cos(w)[None, :]
    v = np.stack([r * np.cos(u)[:, None], np.broadcast_to(minor * np.sin(w), (nu, nv)),
                  r * np.sin(u)[:, None]], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a = i * nv + j
    b = ((i + 1) % nu) * nv + j
    c = ((i + 1) % nu) * nv + (j + 1) % nv
    d = i * nv + (j + 1) % nv
    t = np.concatenate([np.stack([a, d, c], -1).reshape(-1, 3), np.stack([a, c, b], -1).reshape(-1, 3)])
    vol = np.einsum("ij,ij->i", v[t[:, 0]], np.cross(v[t[:, 1]], v[t[:, 2]])).sum() / 6
    if vol < 0:
        t = t[:, [0, 2, 1]]
    with open(path, "w") as fh:
        fh.write("".join(f"v {x:.7g} {y:.7g} {z:.7g}\n" for x, y, z in v))
        fh.write("".join(f"f {p + 1} {q + 1} {s + 1}\n" for p, q, s in t))
    return len(t)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="warp-cloth bench render", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--res", type=int, default=49, help="cells a side (49: 2,500 vertices)")
    p.add_argument("--torus", default="96,64", help="torus segments U,V (96,64: 12,288 triangles)")
    p.add_argument("--frames", type=int, default=180, help="frames simulated (60 fps)")
    p.add_argument("--size", default="640x480")
    p.add_argument("--rounds", type=int, default=5, help="frames timed")
    p.add_argument("--device", default=None)
    p.add_argument("--keep", default=None, help="also keep the USD file here")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    from ..viewer.render import parse_size

    try:
        w, h = parse_size(args.size)
        nu, nv = (int(s) for s in args.torus.split(","))
    except ValueError as e:
        p.error(str(e))
    if args.res < 2 or args.frames < 3 or args.rounds < 1 or nu < 3 or nv < 3:
        p.error("--res >= 2, --frames >= 3, --rounds >= 1, --torus U,V >= 3,3")
    quiet_warp()
    import warp as wp

    from ..contact_scenes import mesh as mesh_scene
    from ..viewer.page import pack_playback, write_page
    from ..viewer.playback import read_playback
    from ..viewer.render import Renderer

    t_all = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        obj = os.path.join(tmp, "torus.obj")
        n_tris = torus_obj(obj, nu, nv)
        usd = args.keep or os.path.join(tmp, "render_bench.usd")
        scene = mesh_scene(res=args.res, frames=args.frames, mesh_file=obj, device=args.device,
                           self_collision=False)
        t0 = time.perf_counter()
        scene.run(usd, quiet=True)
        t_sim = time.perf_counter() - t0
        t0 = time.perf_counter()
        pb = read_playback(usd)
        t_read = time.perf_counter() - t0
        cloth = next(q for q in pb.parts if q.deforming)
        obstacle_tris = sum(len(q.triangles) for q in pb.parts if not q.deforming)
        frames = sorted({int(round(x)) for x in np.linspace(0, pb.num_frames - 1, args.rounds)})
        res = {}
        for shadows in (False, True):
            r = Renderer(pb, w, h, shadows=shadows, device=args.device)
            r.render(0)                                   # compile, first BVH builds
            times = []
            for f in frames:
                wp.synchronize_device(r.device)
                t0 = time.perf_counter()
                r.render(f)
                times.append(time.perf_counter() - t0)
            res[shadows] = statistics.median(times)
        page = os.path.join(tmp, "page.html")
        size = write_page(pb, page)
        packed = pack_playback(pb)
        cloth_blob = next(d for d in packed["parts"] if d["deforming"])["points"]
        per_frame = len(cloth_blob) / pb.num_frames     # base64 bytes in the page
        fixed = size - len(cloth_blob)
    row = dict(vertices=cloth.num_vertices, cloth_triangles=len(cloth.triangles),
               obstacle_triangles=obstacle_tris, torus_triangles=n_tris, frames=pb.num_frames,
               width=w, height=h, device=str(wp.get_device(args.device)),
               s_per_frame_no_shadows=res[False], s_per_frame_shadows=res[True],
               shadow_ratio=res[True] / res[False],
               us_per_primary_ray=1e6 * res[False] / (w * h),
               page_bytes=size, page_fixed_bytes=fixed, page_bytes_per_frame=per_frame,
               raw_float32_bytes_per_frame=cloth.num_vertices * 12,
               page_mb_600_frames=(fixed + 600 * per_frame) / 1e6,
               sim_s=t_sim, read_s=t_read)
    if args.json:
        print(json.dumps(row, indent=1))
        return 0
    print(f"# render and page cost: mesh scene, {row['vertices']} cloth vertices, "
          f"{obstacle_tris} obstacle triangles ({n_tris} in the torus), {pb.num_frames} frames, "
          f"{w}x{h}, device {row['device']}\n")
    print("| quantity | value |")
    print("|---|---|")
    print(f"| render, s/frame (1 ray/pixel, no shadows) | {res[False]:.3f} |")
    print(f"| render, s/frame (with shadow rays, the default) | {res[True]:.3f} |")
    print(f"| shadows / no shadows | {row['shadow_ratio']:.2f} |")
    print(f"| per primary ray (no shadows) | {row['us_per_primary_ray']:.2f} us |")
    print(f"| page, total ({pb.num_frames} frames) | {size / 1e6:.2f} MB |")
    print(f"| page, fixed part (three.js, player, triangles, obstacles) | {fixed / 1e6:.2f} MB |")
    print(f"| page, per frame (packed cloth points, base64) | {per_frame:.0f} B "
          f"(raw float32: {row['raw_float32_bytes_per_frame']} B) |")
    print(f"| page for a 600-frame run at that rate | {row['page_mb_600_frames']:.1f} MB |")
    print(f"\n(simulation {t_sim:.0f} s, reading the USD {t_read:.1f} s, "
          f"total {time.perf_counter() - t_all:.0f} s)")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
