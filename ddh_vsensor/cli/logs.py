"""Logging for every subcommand: one stderr handler, the level from ``--log-level`` (where a
subcommand has it) moved by the global ``-v``/``-q``, and canopen's per-request INFO lines
(every SDO upload/download, every NMT state change: most of a service's log at INFO) folded
into one summary line per interval unless the level is DEBUG."""

from __future__ import annotations

import atexit
import logging
import os
import sys
import threading
from collections import Counter

LEVELS = ("debug", "info", "warning", "error", "critical")
SUMMARY_INTERVAL_S = 60.0
SUMMARY_TOP = 4                  # distinct requests named in a summary line
FOLDED_LOGGERS = ("canopen",)    # libraries whose INFO lines are folded into the summary

log = logging.getLogger("ddh_vsensor.cli.logs")


def effective_level(base: str | None, verbosity: int) -> int:
    """``base`` (a name of LEVELS; None: warning) moved ``verbosity`` steps (-v: +1 more
    detail, -q: -1), clamped to DEBUG..CRITICAL."""
    start = LEVELS.index(base) if base is not None else LEVELS.index("warning")
    index = min(max(start - verbosity, 0), len(LEVELS) - 1)
    return getattr(logging, LEVELS[index].upper())


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time (tests swap it)."""

    @property  # type: ignore[override]
    def stream(self):  # noqa: ANN201 - logging's own attribute
        return sys.stderr

    @stream.setter
    def stream(self, _value) -> None:  # noqa: ANN001
        pass


class ActivitySummary(logging.Filter):
    """Drops the folded libraries' records below WARNING, counting them; the first one of a
    quiet spell starts a timer that logs one line with the counts ``interval_s`` later."""

    def __init__(self, interval_s: float = SUMMARY_INTERVAL_S) -> None:
        super().__init__()
        self.interval_s = interval_s
        self.counts: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._timer: threading.Timer | None = None

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.WARNING or not record.name.startswith(FOLDED_LOGGERS):
            return True
        with self._lock:
            self.counts[f"{record.name.split('.')[-1]}: {record.getMessage()}"] += 1
            if self._timer is None:
                self._timer = threading.Timer(self.interval_s, self.flush)
                self._timer.daemon = True
                self._timer.start()
        return False

    def flush(self) -> None:
        """Log the counts gathered so far (nothing when there are none)."""
        with self._lock:
            counts, self.counts = self.counts, Counter()
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None
        if counts:
            log.info(summary_line(counts, self.interval_s))


def summary_line(counts: Counter[str], interval_s: float) -> str:
    top = ", ".join(f"{n} x {what}" for what, n in counts.most_common(SUMMARY_TOP))
    rest = len(counts) - SUMMARY_TOP
    more = f", {rest} other kinds" if rest > 0 else ""
    return (f"canopen activity (up to {interval_s:g} s; -v shows each line): "
            f"{sum(counts.values())} events: {top}{more}")


_installed: tuple[logging.Handler, ActivitySummary | None] | None = None


def configure_logging(base: str | None, verbosity: int,
                      interval_s: float = SUMMARY_INTERVAL_S) -> int:
    """Set up logging for this process (again: replaces the previous setup); returns the
    level."""
    global _installed
    level = effective_level(base, verbosity)
    root = logging.getLogger()
    if _installed is not None:
        handler, old = _installed
        root.removeHandler(handler)
        if old is not None:
            old.flush()
    # Under systemd the journal stamps each line; elsewhere the time is useful.
    fmt = "%(levelname)s %(name)s: %(message)s" if os.environ.get("JOURNAL_STREAM") \
        else "%(asctime)s %(levelname)s %(name)s: %(message)s"
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter(fmt))
    summary = None
    if level == logging.INFO:
        summary = ActivitySummary(interval_s)
        handler.addFilter(summary)
    root.addHandler(handler)
    root.setLevel(level)
    _installed = (handler, summary)
    return level


def _flush_at_exit() -> None:
    if _installed is not None and _installed[1] is not None:
        _installed[1].flush()


atexit.register(_flush_at_exit)
