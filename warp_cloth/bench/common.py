"""Timing helpers shared by the benchmarks."""

from __future__ import annotations

import statistics
import time

import warp as wp

wp.set_module_options({"enable_backward": False})  # no gradients here: less to compile


@wp.kernel
def trivial_kernel(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), dt: float):
    """The baseline: one read-modify-write per vertex, the least a step can do."""
    i = wp.tid()
    x[i] = x[i] + dt * v[i]


def time_callable(fn, repeats: int = 5, sync_device=None) -> float:
    """Median wall time of ``fn()`` over ``repeats`` runs (seconds)."""
    out = []
    for _ in range(repeats):
        wp.synchronize_device(sync_device)
        t0 = time.perf_counter()
        fn()
        wp.synchronize_device(sync_device)
        out.append(time.perf_counter() - t0)
    return statistics.median(out)


def capture(fn, device):
    """Record ``fn()`` as a Warp graph (all its modules must be loaded already)."""
    with wp.ScopedCapture(device=device, force_module_load=False) as cap:
        fn()
    return cap.graph


def markdown_table(headers, rows) -> str:
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(fmt(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)
