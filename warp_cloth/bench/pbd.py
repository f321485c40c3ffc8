"""``warp-cloth bench pbd``: time per substep of position-based dynamics on the hanging cloth.

Reports, on the 64 x 32-cell hanging cloth (2,145 vertices, 6,240 edges) by default:

- ms per substep of `PositionBased` with 10 Jacobi iterations (and, as extra rows, coloured
  Gauss-Seidel and XPBD with the springs' compliance), plain launches and replayed as a captured
  Warp graph;
- a *bare* two-kernel Jacobi iteration over the same edges (one thread per edge: projection +
  ``atomic_add``; one thread per vertex: average + clear), the least a Jacobi PBD iteration can
  cost, measured in the same run; the ratio ``step / (iterations x bare)`` is the solver's
  overhead over that floor (prediction, velocity update, multiplier bookkeeping, launches);
- the symplectic Euler step on the same cloth, for scale;
- the maximum edge strain ``|l/L - 1|`` at the end of ``--seconds`` of simulation with each
  method at its default substeps (the runner's choice), and the largest seen during the run.

Target (issue 7): under 2 ms per substep at 10 Jacobi iterations.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import warp as wp

from ..util import quiet_warp
from .common import capture, markdown_table, time_callable

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile


@wp.kernel
def bare_edge_kernel(
    x: wp.array(dtype=wp.vec3),
    edges: wp.array2d(dtype=wp.int32),
    rest: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    delta: wp.array(dtype=wp.vec3),
):
    e = wp.tid()
    i = edges[e, 0]
    j = edges[e, 1]
    wi = inv_mass[i]
    wj = inv_mass[j]
    d = x[i] - x[j]
    l = wp.length(d)
    g = (rest[e] - l) / ((wi + wj) * l + 1.0e-20) * d
    wp.atomic_add(delta, i, wi * g)
    wp.atomic_sub(delta, j, wj * g)


@wp.kernel
def bare_vertex_kernel(
    x: wp.array(dtype=wp.vec3),
    delta: wp.array(dtype=wp.vec3),
    count: wp.array(dtype=float),
):
    i = wp.tid()
    x[i] = x[i] + delta[i] / count[i]
    delta[i] = wp.vec3(0.0)


def _final_strain(scene_kwargs, seconds, fps=60.0):
    from ..scenes import hanging

    scene = hanging(frames=max(2, int(round(seconds * fps)) + 1), fps=fps,
                    **{"self_collision": False, **scene_kwargs})
    stats = scene.run(None, quiet=True, energy=False)
    return stats.final_max_strain, stats.max_strain, stats.substeps


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="warp-cloth bench pbd", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--shape", type=int, nargs=2, default=(64, 32), metavar=("NX", "NY"))
    p.add_argument("--iterations", type=int, default=10)
    p.add_argument("--steps", type=int, default=100, help="substeps per timing")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--seconds", type=float, default=0.5,
                   help="simulated time for the strain figures (0: skip them)")
    p.add_argument("--device", default=None)
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    if args.steps < 1 or args.repeats < 1 or args.iterations < 1 or args.seconds < 0:
        p.error("--steps, --repeats and --iterations must be positive, --seconds >= 0")

    quiet_warp()
    from ..scenes import hanging_model
    from ..solvers.explicit import SymplecticEuler
    from ..solvers.pbd import PositionBased

    shape = tuple(args.shape)
    model = hanging_model(shape=shape, device=args.device)
    dev = model.device
    n, its = args.steps, args.iterations
    solvers = {
        "pbd jacobi": PositionBased(model, iterations=its),
        "pbd gauss-seidel": PositionBased(model, iterations=its, gauss_seidel=True),
        "xpbd jacobi (1/k)": PositionBased(model, iterations=its, compliance="springs"),
    }
    dt = 1.0 / (60.0 * solvers["pbd jacobi"].default_substeps)
    explicit = SymplecticEuler(model)
    dt_explicit = 0.5 * SymplecticEuler.stable_dt(model)

    # the bare Jacobi iteration over the mesh edges
    ne = model.num_stretch_springs
    edges, rest = model.spring_indices[:ne], model.spring_rest_length[:ne]
    cnt = np.zeros(model.num_vertices)
    np.add.at(cnt, model.spring_pairs[:ne].reshape(-1), 1.0)
    count = wp.array(np.maximum(cnt, 1.0).astype(np.float32), dtype=float, device=dev)
    delta = wp.zeros(model.num_vertices, dtype=wp.vec3, device=dev)

    rows, res = [], {"vertices": model.num_vertices, "edges": ne, "iterations": its,
                     "dt_pbd": dt, "dt_explicit": dt_explicit, "device": str(dev)}

    def timed(name, fn):
        fn()  # compile and warm up
        g = capture(fn, dev)
        plain = 1e3 * time_callable(fn, args.repeats, dev) / n
        graph = 1e3 * time_callable(lambda: wp.capture_launch(g), args.repeats, dev) / n
        res[name] = {"plain_ms": plain, "graph_ms": graph}
        return plain, graph

    st = model.state()

    def bare():
        for _ in range(n):
            wp.launch(bare_edge_kernel, ne, [st.x, edges, rest, model.inv_mass, delta], device=dev)
            wp.launch(bare_vertex_kernel, model.num_vertices, [st.x, delta, count], device=dev)

    bare_plain, bare_graph = timed("bare jacobi iteration", bare)
    for name, s in solvers.items():
        state = model.state()
        plain, graph = timed(name, lambda s=s, state=state: [s.step(state, dt) for _ in range(n)])
        rows.append([f"{name}, {its} it", plain, graph, graph / (its * bare_graph)])
        res[name]["ratio_to_bare"] = graph / (its * bare_graph)
        res[name]["finite"] = bool(np.all(np.isfinite(state.x.numpy())))
    state = model.state()
    plain, graph = timed("explicit", lambda: [explicit.step(state, dt_explicit) for _ in range(n)])
    rows.append(["symplectic Euler", plain, graph, float("nan")])
    rows.append(["bare Jacobi iteration", bare_plain, bare_graph, 1.0])

    strain_rows = []
    if args.seconds > 0:
        for label, kw in (("pbd jacobi", dict(solver="pbd", solver_options={"iterations": its})),
                          ("pbd gauss-seidel", dict(solver="pbd", solver_options={
                              "iterations": its, "gauss_seidel": True})),
                          ("explicit", dict(solver="explicit"))):
            fin, mx, sub = _final_strain(dict(shape=shape, device=args.device, **kw), args.seconds)
            res.setdefault(label, {}).update(final_max_strain=fin, max_strain=mx, substeps=sub)
            strain_rows.append([label, sub, 100 * fin, 100 * mx])

    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    print(f"position-based dynamics, hanging cloth {shape[0]} x {shape[1]} cells: "
          f"{model.num_vertices} vertices, {ne} edges, device {dev}; PBD dt {dt:.3g} s, "
          f"explicit dt {dt_explicit:.3g} s; {n} substeps per timing, median of {args.repeats}")
    print(markdown_table(["ms per substep", "plain launches", "captured graph",
                          f"graph / ({its} x bare iteration)"], rows))
    if strain_rows:
        print()
        print(f"maximum edge strain, {args.seconds:g} s simulated at 60 fps (default substeps):")
        print(markdown_table(["method", "substeps/frame", "at the end (%)", "largest seen (%)"],
                             strain_rows))
    return 0
