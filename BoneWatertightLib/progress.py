"""Progress reporting with cancel, shared by every stage."""

from __future__ import annotations

from typing import Callable, Optional

from .errors import CancelledError

ProgressCallback = Callable[[float, str], Optional[bool]]
"""callback(fraction_done_0_to_1, message). Returning False cancels the run."""


class Progress:
    """Maps each stage's local progress onto the overall [0, 1] range."""

    def __init__(self, callback: Optional[ProgressCallback] = None):
        self._callback = callback
        self._start = 0.0
        self._width = 1.0

    def stage(self, start: float, end: float) -> "Progress":
        child = Progress(self._callback)
        child._start = self._start + start * self._width
        child._width = (end - start) * self._width
        return child

    def __call__(self, fraction: float, message: str = "") -> None:
        if self._callback is None:
            return
        overall = self._start + min(max(fraction, 0.0), 1.0) * self._width
        if self._callback(overall, message) is False:
            raise CancelledError("Cancelled by the user; nothing was changed.")
