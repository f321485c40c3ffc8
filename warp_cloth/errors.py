"""Exceptions raised by warp_cloth."""

from __future__ import annotations


class SimulationDiverged(RuntimeError):
    """A step produced non-finite positions or exceeded the configured strain bound.

    Attributes:
        frame: the frame (0 = initial state) whose positions failed the check.
        method: the solver's name.
        max_strain: the largest edge strain ``|x_i - x_j| / L - 1`` seen at that frame
            (``nan`` if the positions were not finite).
        reason: ``"non-finite positions"`` or ``"strain bound exceeded"``.
    """

    def __init__(self, frame: int, method: str, max_strain: float, reason: str):
        self.frame, self.method, self.max_strain, self.reason = frame, method, max_strain, reason
        super().__init__(
            f"simulation diverged at frame {frame} with method '{method}': {reason} "
            f"(largest edge strain seen {max_strain:.4g})"
        )


class OutputError(OSError):
    """An output file cannot be written (permissions, a directory, a read-only or full file
    system). The message is one line naming the path and the reason; files already written
    stay readable."""
