"""The progress of a long command on stderr, drawn by tqdm.

On a terminal the bar is live: redrawn in place (``\\r``) at most ten times a second, whatever
the fraction does (a stage may start its own share over), trimmed by tqdm to the terminal's
width so a long note never wraps; the final line is left whole. Anywhere else (a pipe, a log
file, journald, a test's captured stderr) nothing is drawn while the work runs, so logs carry
no carriage-return spam, and ``close()`` writes the final line once, in the same format.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

from tqdm import tqdm

REDRAW_S = 0.1
_ASCII = "-#"          # tqdm pads with the first character and fills with the last


class ProgressBar:
    """``update(fraction, note)`` with ``fraction`` in 0..1; ``close(note)`` ends the line.

    ``note`` says what is being done (a stage, a file); it follows the elapsed time."""

    def __init__(self, label: str, stream: TextIO | None = None, width: int = 30) -> None:
        self.label = label
        self.stream = stream or sys.stderr
        self._format = f"{{desc}} [{{bar:{width}}}] {{percentage:5.1f}}% {{elapsed}}{{postfix}}"
        self._started = time.monotonic()
        self._last_draw = self._started
        self._tty = self.stream.isatty()
        self._bar = tqdm(total=1.0, desc=label, file=self.stream, disable=not self._tty,
                         bar_format=self._format, ascii=_ASCII, dynamic_ncols=True,
                         leave=True)

    def update(self, fraction: float, note: str = "") -> None:
        if not self._tty:
            return
        self._bar.n = min(max(fraction, 0.0), 1.0)
        self._bar.set_postfix_str(note, refresh=False)
        now = time.monotonic()
        if now - self._last_draw >= REDRAW_S:
            self._last_draw = now
            self._bar.refresh()

    def close(self, note: str = "") -> None:
        """The final line at 100 %, on a terminal or not."""
        if self._tty:
            self._bar.n = 1.0
            self._bar.set_postfix_str(note, refresh=False)
            self._bar.dynamic_ncols, self._bar.ncols = None, None    # not redrawn: untrimmed
            self._bar.close()
        else:
            self.stream.write(tqdm.format_meter(
                1.0, 1.0, time.monotonic() - self._started, prefix=self.label,
                bar_format=self._format, ascii=_ASCII, postfix=note) + "\n")
            self.stream.flush()
