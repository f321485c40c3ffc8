"""Small helpers shared across the package."""

from __future__ import annotations

import logging
import math

import warp as wp


def quiet_warp() -> None:
    """Silence Warp's start-up banner and per-module compile messages (warnings still show).

    Warp >= 1.13 uses ``wp.config.log_level``; older releases ``wp.config.quiet``.
    """
    if hasattr(wp.config, "log_level"):
        wp.config.log_level = logging.WARNING
    else:
        wp.config.quiet = True


#: Warp's native start-up warning on a machine without a CUDA driver
_NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"


def init_warp(*, verbose: bool = False, device=None) -> None:
    """Initialise Warp, quietly unless asked.

    Without ``verbose``: Warp's info messages (start-up banner, a line per module load, which
    would land inside a progress bar) are off (`quiet_warp`), and Warp's native "could not find
    the NVIDIA CUDA driver" warning, printed by its C library on a CPU-only machine, is held back
    unless ``device`` names a CUDA device. Anything else Warp prints while starting still shows.
    Calling it again is harmless (Warp initialises once).
    """
    import os
    import sys
    import tempfile

    if not verbose:
        quiet_warp()
    wants_cuda = device is not None and str(device).startswith("cuda")
    if verbose or wants_cuda:
        wp.init()
        return
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        wp.init()
        return
    with tempfile.TemporaryFile() as tmp:
        try:
            os.dup2(tmp.fileno(), 2)
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        tmp.seek(0)
        text = tmp.read().decode("utf-8", "replace")
    kept = [ln for ln in text.splitlines() if _NO_DRIVER not in ln]
    if kept:
        sys.stderr.write("\n".join(kept) + "\n")
        sys.stderr.flush()


def positive_finite(value, what: str, unit: str = "") -> float:
    """``float(value)`` if it is a positive finite number, else a `ValueError` naming ``what``
    (and its ``unit``, e.g. ``"metres"``)."""
    of = f" of {unit}" if unit else ""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a positive number{of}, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{what} must be positive and finite{f' ({unit})' if unit else ''}, "
                         f"got {value!r}")
    return v
