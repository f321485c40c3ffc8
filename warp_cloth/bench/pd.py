"""``warp-cloth bench pd``: projective dynamics against Newton on the same step.

The 64 x 32-cell hanging cloth (`warp_cloth.scenes.hanging_model`, 1 m wide, 0.15 kg/m^2,
1000 N/m, 60 fps, one step per frame). Two start states: the rest state (frame 0) and a moving
state after ``--warmup`` frames (simulated with projective dynamics, 20 x Chebyshev-40; any
plausible moving state will do). For each, the reference is the converged implicit-Euler state
of the step: `ImplicitEuler` with its line search, up to 60 Newton iterations, CG to
1e-7. Every configuration then takes that one step from the same state and reports

- ``err %``: max vertex distance to the reference, in % of the cloth size (1 m);
- ``F``: the objective at the start of its last iteration (J; PD) - lower is better;
- ``ms``: wall time of the step, replayed as a captured Warp graph when the solver is capturable
  (median of ``--repeats``), else run directly.

It prints Markdown tables and answers two questions with numbers: does a whole PD step cost less
than one Newton iteration (Liu et al. 2013's claim), and does Chebyshev PD reach the Newton state
within 1 % of the cloth size in under 8 ms per frame. Times are machine-dependent; ratios measured
in the same run are printed beside them.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import warp as wp


def _time_step(solver, base, repeats, dt):
    """(state after one step from ``base``, median ms of one step)."""
    s = base.clone()
    solver.step(s, dt)  # compile, build the matrix
    wp.synchronize()
    times = []
    if solver.capturable:
        with wp.ScopedCapture(device=solver.device, force_module_load=False) as cap:
            solver.step(s, dt)
        for _ in range(repeats):
            t0 = time.perf_counter()
            wp.capture_launch(cap.graph)
            wp.synchronize()
            times.append(time.perf_counter() - t0)
        s.assign(base)
        wp.capture_launch(cap.graph)
    else:
        for _ in range(repeats):
            s.assign(base)
            wp.synchronize()
            t0 = time.perf_counter()
            solver.step(s, dt)
            wp.synchronize()
            times.append(time.perf_counter() - t0)
        s.assign(base)
        solver.step(s, dt)
    return s, 1e3 * statistics.median(times)


def _table(headers, rows):
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    out = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    out += ["| " + " | ".join(fmt(v) for v in r) + " |" for r in rows]
    return "\n".join(out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="warp-cloth bench pd", description=__doc__.split("\n\n")[0])
    p.add_argument("--shape", default="64x32", help="cells NXxNY (default 64x32)")
    p.add_argument("--warmup", type=int, default=30, help="frames before the moving state")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--iterations", default="1,2,5,10,20,50", help="PD outer iterations to try")
    p.add_argument("--quick", action="store_true", help="fewer configurations")
    p.add_argument("--device", default=None)
    args = p.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    from ..scenes import hanging_model
    from ..solvers.implicit import ImplicitEuler
    from ..solvers.projective import ProjectiveDynamics

    nx, ny = (int(a) for a in args.shape.lower().split("x"))
    ks = [int(k) for k in args.iterations.split(",")]
    model = hanging_model(shape=(nx, ny), device=args.device)
    size = 1.0
    dt = 1.0 / 60.0
    print(f"# projective dynamics vs Newton: hanging cloth {nx}x{ny} cells, {model.num_vertices} "
          f"vertices, {model.num_springs} springs, dt = 1/60 s, device {model.device}\n")

    warm = ProjectiveDynamics(model, iterations=20, linear="chebyshev", linear_iterations=40)
    s = model.state()
    starts = {"rest (frame 0)": s.clone()}
    for _ in range(args.warmup):
        warm.step(s, dt)
    starts[f"moving (frame {args.warmup})"] = s.clone()

    pd_configs = [
        ("pd chebyshev x10", dict(linear="chebyshev", linear_iterations=10)),
        ("pd chebyshev x20", dict(linear="chebyshev", linear_iterations=20)),
        ("pd jacobi x20", dict(linear="jacobi", linear_iterations=20)),
        ("pd cg x20", dict(linear="cg", linear_iterations=20)),
        ("pd chebyshev x20 + outer Chebyshev 0.9", dict(linear="chebyshev", linear_iterations=20,
                                                        outer_rho=0.9)),
        ("pd direct (host dense inverse)", dict(direct=True)),
        ("pd cholesky x1 (banded factor)", dict(linear="cholesky", linear_iterations=1)),
    ]
    if args.quick:
        pd_configs = [pd_configs[1], pd_configs[3], pd_configs[5], pd_configs[6]]
    newton_ks = [1, 2, 5, 10, 20]

    summary = []
    for label, base in starts.items():
        ref = ImplicitEuler(model, newton_iterations=60, tolerance=1e-6, linear="cg",
                            linear_iterations=2000, linear_tolerance=1e-7, line_search=True)
        t0 = time.perf_counter()
        sref = base.clone()
        ref.step(sref, dt)
        t_ref = time.perf_counter() - t0
        xref = sref.positions()
        x_y = base.positions() + dt * base.velocities() + dt * dt * np.asarray(model.gravity)
        x_y[model.pins] = xref[model.pins]
        print(f"## start: {label}\n")
        print(f"reference: Newton + line search, {ref.stats.get('newton_iterations', '?')} iterations, "
              f"{t_ref:.2f} s; the inertial guess y is {100 * np.abs(x_y - xref).max() / size:.3f} % "
              f"of the size away from it.\n")
        rows = []
        for name, opts in pd_configs:
            for k in ks:
                if opts.get("direct") and k > 20:
                    continue
                sol = ProjectiveDynamics(model, iterations=k, **opts)
                st, ms = _time_step(sol, base, args.repeats, dt)
                err = 100 * np.abs(st.positions() - xref).max() / size
                rows.append((name, k, err, sol.stats["objective"][-1], ms))
        for k in newton_ks:
            sol = ImplicitEuler(model, newton_iterations=k, tolerance=None, linear="cg",
                                linear_iterations=200, linear_tolerance=None, line_search=False)
            st, ms = _time_step(sol, base, args.repeats, dt)
            err = 100 * np.abs(st.positions() - xref).max() / size
            rows.append(("newton cg x200 (no line search)", k, err, float("nan"), ms))
        print(_table(["method", "iterations", "err %", "F (PD, J)", "ms/step"], rows))
        print()
        summary.append((label, rows))

    # ---- the two questions
    print("## Liu et al. 2013: a whole PD step costs less than one Newton iteration?\n")
    for label, rows in summary:
        pd_def = next(r for r in rows if r[0].startswith("pd chebyshev x20") and r[1] == 10)
        n1 = next(r for r in rows if r[0].startswith("newton") and r[1] == 1)
        print(f"- {label}: PD step (10 x Chebyshev-20) {pd_def[4]:.2f} ms, err "
              f"{pd_def[2]:.3f} %; one Newton iteration (CG x200) {n1[4]:.2f} ms, err {n1[2]:.3f} %; "
              f"ratio PD/Newton-iteration = {pd_def[4] / n1[4]:.2f}")
    print("\n## Target: Chebyshev PD within 1 % of the size in under 8 ms per frame?\n")
    for label, rows in summary:
        ok = [r for r in rows if "chebyshev" in r[0] and r[2] < 1.0 and r[4] < 8.0]
        best = min((r for r in rows if "chebyshev" in r[0]), key=lambda r: r[2])
        if ok:
            r = min(ok, key=lambda r: r[4])
            print(f"- {label}: yes, {r[0]} with {r[1]} iterations: {r[2]:.3f} % in {r[4]:.2f} ms")
        else:
            print(f"- {label}: no; best Chebyshev PD reached {best[2]:.3f} % ({best[0]}, {best[1]} "
                  f"iterations, {best[4]:.2f} ms)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
