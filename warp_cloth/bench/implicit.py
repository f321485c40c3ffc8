"""``warp-cloth bench implicit``: inner linear solvers on one Newton system of the hanging cloth.

The 64 x 32-cell hanging cloth (`warp_cloth.scenes.hanging_model(shape=(64, 32))`, 2,145
vertices, 1 m wide, 0.15 kg/m^2, 1000 N/m, damping 0.1/s) is simulated for ``--warmup`` steps of
``dt = 1/(60 * ImplicitEuler.default_substeps)`` s with the implicit solver (so it falls and
swings), then the first Newton system ``(M/dt^2 + H) dx = -grad F`` of the next step is built.
From ``dx = 0`` each inner solver runs to a relative residual ``||b - A dx|| / ||b||`` of
``--tolerance`` (1e-4), and the table reports

- ``iters``: iterations needed (checked every iteration);
- ``ms checked``: wall time of that solve with a host residual check each iteration;
- ``ms graph``: wall time of the same number of iterations with no checks, replayed as a
  captured Warp graph (what a capturable step costs); ``us/iter`` from it;
- ``x iters`` / ``x time``: Jacobi's iterations / time divided by this solver's.

Then the cost of one Newton iteration with CG is reported twice, both as a captured graph (and
as a multiple of a trivial kernel over the same vertex array timed in the same run) and with
host checks: with CG run to ``--tolerance``, and with the solver's default settings (its CG
forcing term; the CG count per Newton iteration is the mean of a default step on the same
state, and the checked figure is that default step's time divided by its Newton iterations).

Chebyshev uses ``rho`` measured by Lanczos (`jacobi_spectral_radius`); Jacobi and Chebyshev
use ``alpha`` = ``--alpha`` (0.66). Then one full Newton iteration with CG (assembly of gradient
and Hessian, the CG solve to the tolerance, the update) is timed, captured as a graph and
uncaptured, and, unless ``--no-sparse``, the same CG solve with Warp's own BSR matrices
(`warp.sparse`) and `warp.optim.linear.cg` with its diagonal preconditioner, to decide whether
the matrix-free operator is the faster choice. All timings are medians of ``--repeats`` runs on
the current device; on a shared CPU compare the ratios, not the absolute numbers.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile


def _median_ms(fn, repeats):
    out = []
    for _ in range(repeats):
        wp.synchronize()
        t0 = time.perf_counter()
        fn()
        wp.synchronize()
        out.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(out)


def _graph(fn, device):
    with wp.ScopedCapture(device=device, force_module_load=False) as cap:
        fn()
    return cap.graph


@wp.kernel
def _bsr_values_kernel(springs: wp.array2d(dtype=wp.int32), blocks: wp.array(dtype=wp.mat33),
                       diag: wp.array(dtype=wp.mat33), free: wp.array(dtype=float),
                       values: wp.array(dtype=wp.mat33)):
    """Triplet values in the order [diag (n), then per spring (i,j), (j,i)]; pins eliminated."""
    e = wp.tid()
    n = diag.shape[0]
    if e < n:
        if free[e] > 0.0:
            values[e] = diag[e]
        else:
            values[e] = wp.identity(n=3, dtype=float)
        return
    s = e - n
    i = springs[s, 0]
    j = springs[s, 1]
    h = -blocks[s] * (free[i] * free[j])
    values[n + 2 * s] = h
    values[n + 2 * s + 1] = h


@wp.kernel
def _mask_kernel(b: wp.array(dtype=wp.vec3), free: wp.array(dtype=float), out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    out[i] = b[i] * free[i]


def _sparse_cg(model, A, b, tol, repeats, max_iters):
    """Warp BSR + warp.optim.linear.cg on the same system; returns a result dict."""
    import warp.optim.linear as wl
    import warp.sparse as ws

    n, d = A.n, A.device
    pairs = model.spring_pairs
    rows = np.concatenate([np.arange(n), pairs[:, 0], pairs[:, 1]]).astype(np.int32)
    cols = np.concatenate([np.arange(n), pairs[:, 1], pairs[:, 0]]).astype(np.int32)
    # interleave (i, j), (j, i) per spring to match _bsr_values_kernel
    rows[n:] = np.stack([pairs[:, 0], pairs[:, 1]], 1).reshape(-1)
    cols[n:] = np.stack([pairs[:, 1], pairs[:, 0]], 1).reshape(-1)
    rows_w = wp.array(rows, dtype=wp.int32, device=d)
    cols_w = wp.array(cols, dtype=wp.int32, device=d)
    vals = wp.zeros(len(rows), dtype=wp.mat33, device=d)
    blocks = wp.array(A.spring_blocks(), dtype=wp.mat33, device=d)  # 3x3 blocks for the BSR
    fill = lambda: wp.launch(_bsr_values_kernel, n + model.num_springs,  # noqa: E731
                             [model.spring_indices, blocks, A.diag, A.free, vals], device=d)
    fill()
    M = ws.bsr_zeros(n, n, wp.mat33, device=d)
    mapping = ws.bsr_set_from_triplets(M, rows_w, cols_w, vals, prune_numerical_zeros=False,
                                       build_mapping=True)
    t_triplets = _median_ms(lambda: ws.bsr_set_from_triplets(M, rows_w, cols_w, vals,
                                                             prune_numerical_zeros=False), repeats)
    if mapping is not None:
        t_refill = _median_ms(lambda: (fill(), ws.bsr_set_from_mapped_values(M, mapping, vals)),
                              repeats)
    else:
        t_refill = float("nan")
    bm = wp.zeros(n, dtype=wp.vec3, device=d)
    wp.launch(_mask_kernel, n, [b, A.free, bm], device=d)
    P = wl.preconditioner(M, ptype="diag")
    x = wp.zeros(n, dtype=wp.vec3, device=d)
    its = None

    def solve():
        nonlocal its
        x.zero_()
        its, _, _ = wl.cg(M, bm, x, tol=tol, maxiter=max_iters, M=P, check_every=1,
                          use_cuda_graph=False)

    solve()
    t_solve = _median_ms(solve, repeats)
    # matvec cost for comparison
    y = wp.zeros(n, dtype=wp.vec3, device=d)
    t_mv = _median_ms(lambda: [ws.bsr_mv(M, x, y) for _ in range(100)], repeats) / 100
    return {"iterations": int(its), "ms_solve": t_solve, "ms_triplets": t_triplets,
            "ms_refill": t_refill, "us_matvec": 1e3 * t_mv}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="warp-cloth bench implicit", description=__doc__.split("\n\n")[0])
    p.add_argument("--shape", type=int, nargs=2, default=(64, 32), metavar=("NX", "NY"))
    p.add_argument("--warmup", type=int, default=30, help="implicit steps before the measured system")
    p.add_argument("--tolerance", type=float, default=1e-4, help="relative residual to reach")
    p.add_argument("--alpha", type=float, default=0.66, help="Jacobi / Chebyshev relaxation")
    p.add_argument("--max-iterations", type=int, default=40000)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--no-sparse", action="store_true", help="skip the warp.sparse comparison")
    p.add_argument("--device", default=None)
    p.add_argument("--json", action="store_true", help="print the results as JSON too")
    args = p.parse_args(argv)
    if args.warmup < 0 or args.repeats < 1 or not (0 < args.tolerance < 1):
        p.error("--warmup >= 0, --repeats >= 1 and 0 < --tolerance < 1")

    wp.config.quiet = True
    wp.init()
    from ..scenes import hanging_model
    from ..solvers.implicit import ImplicitEuler, jacobi_spectral_radius
    from ..solvers.linear import make_linear_solver

    model = hanging_model(shape=tuple(args.shape), device=args.device)
    dev = model.device
    dt = 1.0 / (60.0 * ImplicitEuler.default_substeps)
    sim = ImplicitEuler(model)
    state = model.state()
    for _ in range(args.warmup):
        sim.step(state, dt)
    base = state.clone()
    work = base.clone()
    A, b = sim.newton_system(work, dt)
    rho, lam_lo, lam_hi = jacobi_spectral_radius(A, args.alpha)
    n = model.num_vertices
    print(f"hanging cloth {args.shape[0]} x {args.shape[1]} cells, {n} vertices, "
          f"{model.num_springs} springs, dt = {dt:.5g} s after {args.warmup} steps; device {dev}")
    print(f"Jacobi iteration matrix: eig(D^-1 A) in [{lam_lo:.4g}, {lam_hi:.4g}], "
          f"rho(I - {args.alpha} D^-1 A) = {rho:.6f} (Lanczos)")

    results = {}
    dx = wp.zeros(n, dtype=wp.vec3, device=dev)
    for name in ("jacobi", "chebyshev", "cg"):
        opts = {"alpha": args.alpha} if name != "cg" else {}
        if name == "chebyshev":
            opts["rho"] = rho
        checked = make_linear_solver(name, iterations=args.max_iterations,
                                     tolerance=args.tolerance, **opts)

        def run_checked():
            dx.zero_()
            return checked.solve(A, b, dx)

        info = run_checked()
        its = int(info["iterations"])
        t_checked = _median_ms(run_checked, args.repeats)
        fixed = make_linear_solver(name, iterations=max(its, 1), tolerance=None, **opts)
        dx.zero_()
        fixed.solve(A, b, dx)  # allocate scratch, load modules
        graph = _graph(lambda: (dx.zero_(), fixed.solve(A, b, dx)), dev)
        t_graph = _median_ms(lambda: wp.capture_launch(graph), args.repeats)
        results[name] = {"iterations": its, "converged": bool(info["converged"]),
                         "fallback": bool(info.get("fallback", False)),
                         "ms_checked": t_checked, "ms_graph": t_graph,
                         "us_per_iteration": 1e3 * t_graph / max(its, 1)}

    jac = results["jacobi"]
    print()
    print(f"Inner solves to relative residual {args.tolerance:g} (one Newton system, from dx = 0)")
    print()
    print("| solver | iters | ms checked | ms graph | us/iter | x iters vs Jacobi | x time vs Jacobi (graph) |")
    print("|---|---|---|---|---|---|---|")
    for name, r in results.items():
        conv = "" if r["converged"] else " (not converged)"
        print(f"| {name} | {r['iterations']}{conv} | {r['ms_checked']:.2f} | {r['ms_graph']:.2f} | "
              f"{r['us_per_iteration']:.1f} | {jac['iterations'] / max(r['iterations'], 1):.1f} | "
              f"{jac['ms_graph'] / max(r['ms_graph'], 1e-9):.1f} |")

    # one full Newton iteration with CG: assembly + solve to the tolerance + update
    cg_its = results["cg"]["iterations"]
    newton_graph = ImplicitEuler(model, newton_iterations=1, tolerance=None, linear="cg",
                                 linear_iterations=max(cg_its, 1), linear_tolerance=None)
    newton_checked = ImplicitEuler(model, newton_iterations=1, tolerance=None, linear="cg",
                                   linear_iterations=args.max_iterations,
                                   linear_tolerance=args.tolerance)
    s = base.clone()
    newton_graph.step(s, dt)
    s.assign(base)
    g = _graph(lambda: newton_graph.step(s, dt), dev)
    t_newton_graph = _median_ms(lambda: (s.assign(base), wp.capture_launch(g)), args.repeats)
    t_newton_checked = _median_ms(lambda: (s.assign(base), newton_checked.step(s, dt)), args.repeats)
    t_assign = _median_ms(lambda: s.assign(base), args.repeats)
    # the realistic figure: the solver's default settings (tolerances, host checks) on the same
    # state, per Newton iteration; and the same CG count per Newton iteration as a graph
    dflt = ImplicitEuler(model)
    s.assign(base)
    dflt.step(s, dt)  # load modules
    s.assign(base)
    dflt.step(s, dt)
    d_newton = max(int(dflt.stats["newton_iterations"]), 1)
    d_cg = max(int(round(dflt.stats["inner_iterations"] / d_newton)), 1)
    t_dflt = _median_ms(lambda: (s.assign(base), dflt.step(s, dt)), args.repeats) - t_assign
    dflt_graph = ImplicitEuler(model, newton_iterations=1, tolerance=None, linear="cg",
                               linear_iterations=d_cg, linear_tolerance=None)
    s.assign(base)
    dflt_graph.step(s, dt)
    s.assign(base)
    g2 = _graph(lambda: dflt_graph.step(s, dt), dev)
    t_dflt_graph = _median_ms(lambda: (s.assign(base), wp.capture_launch(g2)), args.repeats) - t_assign
    # a trivial kernel over the same vertex array, in the same run (one launch, graph-replayed)
    from .common import trivial_kernel
    vtmp = wp.zeros(n, dtype=wp.vec3, device=dev)
    reps = 100
    wp.launch(trivial_kernel, n, [vtmp, vtmp, 0.0], device=dev)
    g3 = _graph(lambda: [wp.launch(trivial_kernel, n, [vtmp, vtmp, 0.0], device=dev)
                         for _ in range(reps)], dev)
    t_triv = _median_ms(lambda: wp.capture_launch(g3), args.repeats) / reps
    t_ng = t_newton_graph - t_assign
    t_nc = t_newton_checked - t_assign
    lin_tol = dflt.linear.tolerance
    print()
    print(f"One Newton iteration with CG, whole step incl. assembly and velocity update "
          f"(trivial {n}-vertex kernel in this run: {1e3 * t_triv:.1f} us as a graph launch; "
          f"target < 5 ms at 2,145 vertices):")
    print()
    print("| setting | CG iters / Newton iter | ms graph | x trivial | ms with host checks |")
    print("|---|---|---|---|---|")
    print(f"| relative residual {args.tolerance:g} | {cg_its} | {t_ng:.2f} | {t_ng / t_triv:.0f} | "
          f"{t_nc:.2f} |")
    print(f"| defaults (CG forcing {lin_tol:g}; {d_newton} Newton iters, {d_cg} CG each) | {d_cg} | "
          f"{t_dflt_graph:.2f} | {t_dflt_graph / t_triv:.0f} | {t_dflt / d_newton:.2f} |")

    out = {"vertices": n, "dt": dt, "rho": rho, "lambda_min": lam_lo, "lambda_max": lam_hi,
           "solvers": results, "newton_cg_ms_graph": t_ng, "newton_cg_ms_checked": t_nc,
           "trivial_us": 1e3 * t_triv, "default_newton_iterations": d_newton,
           "default_cg_per_newton": d_cg, "default_ms_per_newton_graph": t_dflt_graph,
           "default_ms_per_newton_checked": t_dflt / d_newton}
    if not args.no_sparse:
        sp = _sparse_cg(model, A, b, args.tolerance, args.repeats, args.max_iterations)
        mf = results["cg"]
        print()
        print("CG: matrix-free operator vs warp.sparse BSR + warp.optim.linear.cg (diag precond.)")
        print()
        print("| variant | iters | ms solve (checked) | per-Newton assembly ms |")
        print("|---|---|---|---|")
        print(f"| matrix-free (linear.CGSolver) | {mf['iterations']} | {mf['ms_checked']:.2f} | "
              "0 (blocks written by the gradient kernel) |")
        print(f"| warp.sparse BSR | {sp['iterations']} | {sp['ms_solve']:.2f} | "
              f"{sp['ms_refill']:.2f} (mapped refill; {sp['ms_triplets']:.2f} from triplets) |")
        out["sparse"] = sp
    if args.json:
        print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":  # pragma: no cover
    import sys

    sys.exit(main(sys.argv[1:]))
