"""Small helpers shared across the package."""

from __future__ import annotations

import logging

import warp as wp


def quiet_warp() -> None:
    """Silence Warp's start-up banner and per-module compile messages (warnings still show).

    Warp >= 1.13 uses ``wp.config.log_level``; older releases ``wp.config.quiet``.
    """
    if hasattr(wp.config, "log_level"):
        wp.config.log_level = logging.WARNING
    else:
        wp.config.quiet = True
