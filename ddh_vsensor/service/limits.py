"""Rates held down on the bus path: a token bucket for frames, and log lines at most one per
key and interval (ours, and the libraries' on the bus path: canopen, the emulated nodes), the
ones held back counted into the next."""

from __future__ import annotations

import logging
import math
import time
from collections import Counter


class LogLimiter(logging.Filter):
    """A logging filter: one record per logger, message template and interval; the records
    held back are counted into the next one let through. Attached to the loggers of the bus
    path (canopen's and the nodes'), so that no frame, however often it comes, writes a line
    each time."""

    def __init__(self, interval_s: float = 5.0, max_keys: int = 1024) -> None:
        super().__init__()
        self.interval_s, self.max_keys = interval_s, max_keys
        self._last: dict[tuple[str, str], float] = {}
        self._held: Counter[tuple[str, str]] = Counter()
        self.suppressed = 0
        self._loggers: list[logging.Logger] = []

    def filter(self, record: logging.LogRecord) -> bool:
        key = (record.name, str(record.msg)[:200])
        now = time.monotonic()
        if now - self._last.get(key, -math.inf) < self.interval_s:
            self._held[key] += 1
            self.suppressed += 1
            return False
        if len(self._last) >= self.max_keys and key not in self._last:
            self._last.clear()                    # bounded: forget, then start counting again
            self._held.clear()
        self._last[key] = now
        held = self._held.pop(key, 0)
        if held:
            record.msg = f"{record.msg} (+{held} more since the last report)"
        return True

    def attach(self, prefixes: tuple[str, ...]) -> None:
        """Add to every existing logger whose name starts with one of ``prefixes``."""
        names = [n for n in list(logging.Logger.manager.loggerDict)
                 if n.startswith(prefixes)]
        for name in {*names, *prefixes}:
            logger = logging.getLogger(name)
            if self not in logger.filters:
                logger.addFilter(self)
                self._loggers.append(logger)

    def detach(self) -> None:
        for logger in self._loggers:
            logger.removeFilter(self)
        self._loggers.clear()


class RateLimitedLog:
    """One log line per key and interval; the lines held back are counted into the next."""

    def __init__(self, logger: logging.Logger, interval_s: float = 5.0) -> None:
        self.logger, self.interval_s = logger, interval_s
        self._last: dict[str, float] = {}
        self._held: Counter[str] = Counter()

    def warning(self, key: str, message: str, *args: object) -> None:
        self.log(logging.WARNING, key, message, *args)

    def info(self, key: str, message: str, *args: object) -> None:
        self.log(logging.INFO, key, message, *args)

    def log(self, level: int, key: str, message: str, *args: object) -> None:
        now = time.monotonic()
        if now - self._last.get(key, -math.inf) < self.interval_s:
            self._held[key] += 1
            return
        self._last[key] = now
        held = self._held.pop(key, 0)
        suffix = f" (+{held} more since the last report)" if held else ""
        self.logger.log(level, message + suffix, *args, stacklevel=3)


class RateLimiter:
    """Tokens refilled at ``rate_hz`` up to ``burst``; each frame let through takes one."""

    __slots__ = ("rate_hz", "burst", "tokens", "last_s")

    def __init__(self, rate_hz: float, burst: float) -> None:
        self.rate_hz, self.burst = rate_hz, burst
        self.tokens = 0.0
        self.last_s: float | None = None

    def take(self, now_s: float) -> bool:
        last = self.last_s
        if last is None:
            self.tokens, self.last_s = self.burst, now_s
        elif now_s > last:
            self.tokens = min(self.burst, self.tokens + (now_s - last) * self.rate_hz)
            self.last_s = now_s
        elif now_s < last:              # the clock went back: refill from here, not from
            self.last_s = now_s         # when it catches up with the old reading
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False
