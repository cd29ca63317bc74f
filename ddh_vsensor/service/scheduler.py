"""Fixed-rate ticks from absolute deadlines: the period never drifts, a late tick is not
followed by a short one, and missed ticks are counted instead of sent in a burst.

``await ticker.wait()`` per tick, or ``ticker.call_every(callback)``: the callback runs
straight from the loop's wake, without a task switch per tick (measured: that switch cost as
much CPU as the wake itself, ~1 % of a core per 100 Hz ticker on a loaded machine).

On Linux the deadlines are a kernel ``timerfd`` (CLOCK_MONOTONIC, absolute start, periodic)
watched by the event loop: the loop wakes when the fd becomes readable, with the kernel's
timer precision. asyncio's own timers round every wait up to a whole millisecond, which alone
would make the output period jitter by up to 1 ms; they are the fallback where timerfd is not
available (``ctypes`` call fails, other OS).
"""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import logging
import os
import struct
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

log = logging.getLogger(__name__)

_TFD_TIMER_ABSTIME = 1


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [("it_interval", _Timespec), ("it_value", _Timespec)]


def _timespec(seconds: float) -> _Timespec:
    whole = int(seconds // 1)
    return _Timespec(whole, min(int(round((seconds - whole) * 1e9)), 999_999_999))


def _libc() -> ctypes.CDLL | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        libc.timerfd_create.argtypes = [ctypes.c_int, ctypes.c_int]
        libc.timerfd_settime.argtypes = [ctypes.c_int, ctypes.c_int,
                                         ctypes.POINTER(_Itimerspec), ctypes.c_void_p]
        return libc
    except (OSError, AttributeError):
        return None


@dataclass(frozen=True)
class Tick:
    deadline: float      # time.monotonic() at which this tick was due
    missed: int          # ticks skipped just before this one (the loop was late)


class _TimerFdUser:
    """Owns a timerfd registered with the event loop (or none, on asyncio timers)."""

    _fd: int | None = None
    _loop: asyncio.AbstractEventLoop | None = None

    def close(self) -> None:
        if self._fd is not None:
            if self._loop is not None and not self._loop.is_closed():
                self._loop.remove_reader(self._fd)
            os.close(self._fd)
            self._fd = None


class Ticker(_TimerFdUser):
    """``await ticker.wait()`` returns at each deadline start + k * period."""

    def __init__(self, period_s: float, *, use_timerfd: bool | None = None) -> None:
        if period_s <= 0:
            raise ValueError("period must be positive")
        self.period_s = period_s
        self._libc = _libc() if use_timerfd is not False else None
        if use_timerfd and self._libc is None:
            raise OSError("timerfd is not available here")
        self._fd: int | None = None
        self._event: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._anchor = 0.0     # deadline of tick number 0 of the current period setting
        self._count = 0        # ticks (including missed ones) since the anchor
        self._wake: asyncio.Future | None = None   # the asyncio wait in progress
        self._callback: Callable[[Tick], None] | None = None     # call_every
        self._timer: asyncio.TimerHandle | None = None           # call_every on asyncio timers
        self.missed_total = 0

    @property
    def kind(self) -> str:
        return "timerfd" if self._libc is not None else "asyncio"

    def close(self) -> None:
        self._callback = None
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        super().close()

    @property
    def anchor_s(self) -> float:
        """A deadline of the current period setting (time.monotonic()): every deadline is
        this plus a whole number of periods."""
        return self._anchor

    def start(self, first_deadline: float | None = None) -> None:
        self._loop = asyncio.get_running_loop()
        self._anchor = time.monotonic() + self.period_s if first_deadline is None \
            else first_deadline
        self._count = 0
        if self._libc is not None:
            try:
                self._open_timerfd()
            except OSError as exc:
                log.warning("timerfd unavailable (%s); using asyncio timers", exc)
                self._libc = None

    def _open_timerfd(self) -> None:
        assert self._libc is not None and self._loop is not None
        fd = self._libc.timerfd_create(time.CLOCK_MONOTONIC, os.O_NONBLOCK | os.O_CLOEXEC)
        if fd < 0:
            raise OSError(ctypes.get_errno(), os.strerror(ctypes.get_errno()))
        self._fd = fd
        self._arm()
        self._event = asyncio.Event()
        self._loop.add_reader(fd, self._event.set)

    def _arm(self) -> None:
        assert self._libc is not None and self._fd is not None
        spec = _Itimerspec(_timespec(self.period_s), _timespec(self._anchor))
        if self._libc.timerfd_settime(self._fd, _TFD_TIMER_ABSTIME, ctypes.byref(spec), None):
            err = ctypes.get_errno()
            raise OSError(err, os.strerror(err))

    def set_period(self, period_s: float) -> None:
        """New period at once: the next deadline is the last one plus the new period, or now
        if that has passed (e.g. an event timer written over SDO); a wait in progress for
        the old deadline is woken to follow the new one."""
        if period_s <= 0 or period_s == self.period_s:
            return
        last = self._anchor + (self._count - 1) * self.period_s if self._count else \
            self._anchor - self.period_s
        self.period_s = period_s
        self._anchor, self._count = max(last + period_s, time.monotonic()), 0
        if self._fd is not None:
            self._arm()
        elif self._wake is not None and not self._wake.done():
            self._wake.set_result(None)
        elif self._timer is not None:
            self._timer.cancel()
            self._schedule()

    def call_every(self, callback: Callable[[Tick], None]) -> None:
        """``callback(tick)`` at every deadline, called from the loop's wake itself (the
        timerfd's reader, or an asyncio timer) instead of :meth:`wait`; after :meth:`start`.
        """
        assert self._loop is not None, "start() first"
        self._callback = callback
        if self._fd is not None:
            self._loop.remove_reader(self._fd)
            self._loop.add_reader(self._fd, self._on_timerfd)
        else:
            self._schedule()

    def _on_timerfd(self) -> None:
        assert self._fd is not None and self._callback is not None
        try:
            expirations = struct.unpack("=Q", os.read(self._fd, 8))[0]
        except BlockingIOError:
            return
        self._callback(self._advance(expirations))

    def _schedule(self) -> None:
        assert self._loop is not None
        deadline = self._anchor + self._count * self.period_s
        self._timer = self._loop.call_at(self._loop.time() + (deadline - time.monotonic()),
                                         self._on_timer)

    def _on_timer(self) -> None:
        assert self._callback is not None
        self._timer = None
        if self._anchor + self._count * self.period_s > time.monotonic():
            self._schedule()                    # woken early (the loop's clock resolution)
            return
        try:
            self._callback(self._advance(self._expired()))
        finally:
            if self._callback is not None and self._timer is None:
                self._schedule()

    def _expired(self) -> int:
        """Deadlines passed since the last tick (asyncio timers: every one already passed
        counts as expired; late ones are skipped)."""
        expirations = int((time.monotonic() - self._anchor) / self.period_s) + 1 - self._count
        return max(expirations, 1)

    def _advance(self, expirations: int) -> Tick:
        self._count += expirations
        missed = expirations - 1
        self.missed_total += missed
        return Tick(self._anchor + (self._count - 1) * self.period_s, missed)

    async def wait(self) -> Tick:
        if self._loop is None:
            self.start()
        if self._fd is not None:
            assert self._event is not None
            while True:
                await self._event.wait()
                self._event.clear()
                try:
                    expirations = struct.unpack("=Q", os.read(self._fd, 8))[0]
                except BlockingIOError:
                    continue
                break
        else:
            assert self._loop is not None
            while True:
                deadline = self._anchor + self._count * self.period_s
                now = time.monotonic()
                if deadline <= now:
                    break
                future = self._wake = self._loop.create_future()
                handle = self._loop.call_at(self._loop.time() + (deadline - now),
                                            _resolve, future)
                try:
                    await future
                finally:
                    handle.cancel()
                    self._wake = None
            expirations = self._expired()
        return self._advance(expirations)


def _resolve(future: asyncio.Future) -> None:
    if not future.done():
        future.set_result(None)


class Sleeper(_TimerFdUser):
    """``await sleeper.until(deadline)`` (time.monotonic()): a one-shot timerfd where
    available, so consecutive waits do not each lose up to a millisecond to asyncio's
    rounding; asyncio timers otherwise."""

    def __init__(self, use_timerfd: bool | None = None) -> None:
        self._libc = _libc() if use_timerfd is not False else None
        self._fd: int | None = None
        self._event: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    def _open(self) -> None:
        assert self._libc is not None
        self._loop = asyncio.get_running_loop()
        fd = self._libc.timerfd_create(time.CLOCK_MONOTONIC, os.O_NONBLOCK | os.O_CLOEXEC)
        if fd < 0:
            self._libc = None
            return
        self._fd, self._event = fd, asyncio.Event()
        self._loop.add_reader(fd, self._event.set)

    async def until(self, deadline: float) -> None:
        if deadline <= time.monotonic():
            return
        if self._fd is None and self._libc is not None:
            self._open()
        if self._fd is None or self._libc is None:
            await asyncio.sleep(deadline - time.monotonic())
            return
        assert self._event is not None
        spec = _Itimerspec(_timespec(0.0), _timespec(deadline))
        if self._libc.timerfd_settime(self._fd, _TFD_TIMER_ABSTIME, ctypes.byref(spec), None):
            await asyncio.sleep(deadline - time.monotonic())
            return
        while time.monotonic() < deadline:
            self._event.clear()
            try:
                os.read(self._fd, 8)
                break
            except BlockingIOError:
                pass
            await self._event.wait()

