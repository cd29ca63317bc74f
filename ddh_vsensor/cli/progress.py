"""A one-line progress bar on stderr for long commands (quiet when stderr is not a terminal
except for the final line, so logs stay readable)."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class ProgressBar:
    """``update(fraction)`` redraws at most ten times a second; ``close()`` ends the line."""

    def __init__(self, label: str, stream: TextIO | None = None, width: int = 30) -> None:
        self.label, self.width = label, width
        self.stream = stream or sys.stderr
        self.started = time.monotonic()
        self._last_draw = -1.0
        self._tty = self.stream.isatty()

    def update(self, fraction: float, note: str = "") -> None:
        now = time.monotonic()
        if self._tty and (now - self._last_draw >= 0.1 or fraction >= 1.0):
            self._last_draw = now
            self._draw(fraction, note, end="\r")

    def close(self, note: str = "") -> None:
        self._draw(1.0, note, end="\n")

    def _draw(self, fraction: float, note: str, end: str) -> None:
        fraction = min(max(fraction, 0.0), 1.0)
        filled = int(round(fraction * self.width))
        elapsed = time.monotonic() - self.started
        bar = "#" * filled + "-" * (self.width - filled)
        self.stream.write(f"{self.label} [{bar}] {fraction * 100:5.1f}% {elapsed:6.1f}s {note}"
                          f"{end}")
        self.stream.flush()
