"""The CAN bus as the service sees it: opened from the config's ``bus:`` mapping, read
without blocking the event loop, written without ever raising, reopened with back-off.

Reading: on ``socketcan`` the socket is watched by the event loop (``add_reader``) and every
readable wake drains it. With ``coalesce_s`` the watch pauses after each wake (the frames wait
in the kernel's socket buffer): while frames keep coming a timer reads them every
``coalesce_s`` instead (one wake per period, on the grid ``grid_anchor_s``: the service puts
it on its ticks), and once a period passes without frames (the tick's drains count) the fd is
watched again. The service calls
:meth:`BusLink.drain` right before it publishes: the published values still include
every frame received before the tick, at a fraction of the wake-ups. Other interfaces
(``virtual``, ``remote``, vendor drivers) get one reader thread that hands frames to the loop
in batches (one ``call_soon_threadsafe`` per batch, not per frame). No ``can.Notifier``: its
listener chain stops at the first listener that raises, and its error path leaves a dead
reader behind; here a receive error closes the bus and a new one is opened after a back-off
(0.1 s doubling to 5 s), the service's state untouched. Every log line here is rate-limited
(``log_interval_s``): error frames at thousands per second are counted, not each written.

Kernel filters (``can_filters``) are set on socketcan, the interface that applies them in
the kernel; elsewhere python-can would filter in Python anyway, so all frames are delivered
and the service counts the ones it does not know.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

import can

from ddh_vsensor.errors import UserError
from ddh_vsensor.service.limits import RateLimitedLog

log = logging.getLogger(__name__)

KERNEL_FILTER_INTERFACES = frozenset({"socketcan"})
BATCH_MAX = 512            # frames handed over per wake, at most
# the reader thread's receive timeout: how long a stop waits for it (an idle bus wakes it as
# often; a frame ends a receive at once)
READ_TIMEOUT_S = 0.05
BACKOFF_START_S = 0.1
BACKOFF_MAX_S = 5.0
CAN_ERR_BUSOFF = 0x40      # error class bit of a SocketCAN error frame's ID

FramesCallback = Callable[[list[can.Message]], None]


def exact_filters(ids: Iterable[int]) -> list[dict[str, Any]]:
    """One exact 11-bit filter per frame ID."""
    return [{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in sorted(set(ids))]


def bus_settings(bus_cfg: dict[str, Any], interface: str | None = None,
                 channel: str | None = None) -> dict[str, Any]:
    """The config's ``bus:`` mapping with command-line overrides (``--interface/--channel``)."""
    settings = dict(bus_cfg)
    if interface:
        settings["interface"] = interface
    if channel is not None:
        settings["channel"] = channel
    if "bustype" in settings and "interface" not in settings:
        settings["interface"] = settings.pop("bustype")
    if not settings.get("interface"):
        raise UserError("no CAN interface: set bus.interface in the config or give --interface")
    return settings


def open_bus(settings: dict[str, Any], filters: list[dict[str, Any]] | None = None) -> can.BusABC:
    """``can.Bus(**settings)``; a wrong interface name or setting is a UserError, a bus that
    is not there (yet) raises ``can.CanError``/``OSError`` for the caller to retry."""
    kwargs = dict(settings)
    if filters is not None and kwargs.get("interface") in KERNEL_FILTER_INTERFACES:
        kwargs["can_filters"] = filters
    try:
        return can.Bus(**kwargs)
    except can.CanInterfaceNotImplementedError as exc:
        raise UserError(f"CAN interface {settings.get('interface')!r}: {exc}") from None
    except (ValueError, TypeError) as exc:
        raise UserError(f"CAN bus settings {settings}: {exc}") from None


def nonblocking_receiver(bus: can.BusABC) -> Callable[[], can.Message | None]:
    """``bus.recv(0.0)``, without python-can's per-call wrapper where the interface keeps
    python-can's own ``recv``: the interface's ``_recv_internal(0.0)`` (the call every
    python-can interface implements) and python-can's filter check for frames the kernel
    did not filter. The wrapper's clock reads and debug log call were a fifth of the read
    cost per frame (1.7 of 7.8 us here); a frame the filters drop no longer ends the drain."""
    if type(bus).recv is not can.BusABC.recv:
        return lambda: bus.recv(0.0)
    internal, matches = bus._recv_internal, bus._matches_filters   # noqa: SLF001

    def receive() -> can.Message | None:
        while True:
            msg, filtered = internal(timeout=0.0)
            if msg is None:
                return None
            if filtered or matches(msg):
                return msg
    return receive


class BusLink:
    """The service's bus: ``await start()``, ``send(msg)``, ``await close()``.

    ``on_frames(batch)`` runs in the event loop for every batch received. ``state`` is
    ``"open"``, ``"reconnecting"`` or ``"closed"``; ``on_state(state, reason)`` is told of
    changes. Counters: ``rx_frames``, ``tx_frames``, ``tx_errors``, ``bus_errors``,
    ``error_frames``, ``bus_off``, ``reconnects``.
    """

    def __init__(self, settings: dict[str, Any], filters: list[dict[str, Any]] | None,
                 on_frames: FramesCallback, *,
                 on_state: Callable[[str, str], None] | None = None,
                 opener: Callable[[dict[str, Any], list[dict[str, Any]] | None],
                                  can.BusABC] = open_bus,
                 backoff_start_s: float = BACKOFF_START_S,
                 backoff_max_s: float = BACKOFF_MAX_S,
                 watch_fd: bool | None = None, coalesce_s: float = 0.0,
                 log_interval_s: float = 5.0) -> None:
        self.settings, self.filters = settings, filters
        self._log = RateLimitedLog(log, log_interval_s)
        # None: watch the bus's file descriptor on socketcan (a kernel socket, every readable
        # wake drained); True: on any bus with a fileno() whose recv(0) drains it; False: thread
        self.watch_fd = watch_fd
        self.coalesce_s = coalesce_s
        # reads on the grid grid_anchor_s + k * coalesce_s (monotonic; None: coalesce_s
        # after each wake): the service puts it on its ticks, so that reads and ticks share
        # the loop's wakes
        self.grid_anchor_s: float | None = None
        self.wakes = 0
        self.prompt = False         # read_promptly()
        self._watching = False
        self._rearm: asyncio.TimerHandle | None = None
        self._rx_at_poll = 0       # rx_frames when the pending timer read was scheduled
        self.on_frames, self.on_state = on_frames, on_state
        self.opener = opener
        self.backoff_start_s, self.backoff_max_s = backoff_start_s, backoff_max_s
        self.bus: can.BusABC | None = None
        self.state = "closed"
        self.reason = ""
        self.rx_frames = self.tx_frames = self.tx_errors = 0
        # The batch being handed over: when it was read (monotonic; by the reader thread, so
        # that a loop busy elsewhere delays its handling, not what the arrival clock says),
        # and the last time the bus was looked at before it and found with nothing newer
        # (fd reading: the previous read; a reader thread: when the recv that returned its
        # first frame began). A frame's predecessors that were read before ``watched_s`` arrived at
        # least that long before it, whatever the frames' own stamps say.
        self.received_s = self.watched_s = 0.0
        self._last_read_s = 0.0
        self.bus_errors = self.error_frames = self.bus_off = self.reconnects = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._generation = 0
        self._thread: threading.Thread | None = None
        self._fd: int | None = None
        self._receive: Callable[[], can.Message | None] = lambda: None
        self._stopping = False
        self._reopen_task: asyncio.Task | None = None
        self._last_tx_error_log = -1e9

    @property
    def channel_info(self) -> str:
        return getattr(self.bus, "channel_info", "") or str(self.settings.get("channel", ""))

    # --- lifecycle ---------------------------------------------------------------------

    async def start(self, wait: bool = False) -> None:
        """Open the bus. A configuration mistake raises UserError at once; a bus that is
        not there yet is retried in the background (``wait=True``: until it opens)."""
        self._loop = asyncio.get_running_loop()
        self._stopping = False
        try:
            self._attach(self.opener(self.settings, self.filters))
        except UserError:
            raise
        except Exception as exc:   # noqa: BLE001 - any driver failure means "not there yet"
            self._lost(self._generation, exc)
            if wait and self._reopen_task is not None:
                await self._reopen_task

    def _attach(self, bus: can.BusABC) -> None:
        assert self._loop is not None
        self.bus = bus
        self._generation += 1
        generation = self._generation
        fd = -1
        if self.watch_fd or (self.watch_fd is None
                             and self.settings.get("interface") in KERNEL_FILTER_INTERFACES):
            try:
                fd = bus.fileno()
            except (NotImplementedError, AttributeError, OSError):
                fd = -1
        if fd >= 0:
            self._fd = fd
            self._receive = nonblocking_receiver(bus)
            self._watch(bus, generation)
        else:
            self._thread = threading.Thread(target=self._reader, args=(bus, generation),
                                            name=f"can-reader {self.channel_info}", daemon=True)
            self._thread.start()
        self._set_state("open", self.channel_info)

    def _set_state(self, state: str, reason: str) -> None:
        changed = state != self.state
        self.state, self.reason = state, reason
        if changed and self.on_state is not None:
            try:
                self.on_state(state, reason)
            except Exception:   # noqa: BLE001 - a status callback must not stop the bus
                log.exception("bus state callback failed")

    async def close(self) -> None:
        self._stopping = True
        if self._reopen_task is not None:
            self._reopen_task.cancel()
            try:
                await self._reopen_task
            except (asyncio.CancelledError, Exception):  # noqa: BLE001
                pass
            self._reopen_task = None
        await self._detach()
        self._set_state("closed", "stopped")

    async def _detach(self) -> None:
        bus, self.bus = self.bus, None
        self._generation += 1
        if self._rearm is not None:
            self._rearm.cancel()
            self._rearm = None
        if self._fd is not None and self._loop is not None:
            if self._watching:
                self._loop.remove_reader(self._fd)
                self._watching = False
            self._fd = None
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            await asyncio.get_running_loop().run_in_executor(None, thread.join, 2.0)
        if bus is not None:
            try:
                bus.shutdown()
            except Exception as exc:   # noqa: BLE001 - closing a broken bus may fail too
                log.debug("bus shutdown: %s", exc)
                # marked shut down as python-can does it: else its __del__ tries the dead
                # connection again and prints a traceback (python-can-remote on a lost hub)
                can.BusABC.shutdown(bus)

    # --- receiving -----------------------------------------------------------------------

    def _reader(self, bus: can.BusABC, generation: int) -> None:
        """Reader thread: blocks in recv, hands batches to the loop."""
        loop = self._loop
        assert loop is not None
        while generation == self._generation and not self._stopping:
            try:
                # the bus is watched from here: a frame this recv returns arrived after it
                # (however long a busy host keeps this thread from running meanwhile)
                watched_s = time.monotonic()
                msg = bus.recv(READ_TIMEOUT_S)
                if msg is None:
                    continue
                batch = [msg]
                while len(batch) < BATCH_MAX:
                    msg = bus.recv(0.0)
                    if msg is None:
                        break
                    batch.append(msg)
            except Exception as exc:   # noqa: BLE001 - any receive failure: reopen
                if generation == self._generation and not self._stopping:
                    try:
                        loop.call_soon_threadsafe(self._lost, generation, exc)
                    except RuntimeError:   # loop closed
                        pass
                return
            try:
                loop.call_soon_threadsafe(self._deliver, generation, batch, time.monotonic(),
                                          watched_s)
            except RuntimeError:           # loop closed under us: the service is gone
                return

    def _watch(self, bus: can.BusABC, generation: int) -> None:
        self._rearm = None
        if generation == self._generation and self._fd is not None and not self._watching:
            assert self._loop is not None
            self._loop.add_reader(self._fd, self._on_readable, bus, generation)
            self._watching = True

    def read_promptly(self, on: bool) -> None:
        """While on, every frame is read as it comes (no coalescing): a unit waits for its
        next frame to publish. Off: coalescing resumes at the next wake."""
        self.prompt = on
        if on and self._rearm is not None and self.bus is not None:
            self._rearm.cancel()
            self._rearm = None
            self._watch(self.bus, self._generation)

    def _on_readable(self, bus: can.BusABC, generation: int) -> None:
        self.wakes += 1
        if self.coalesce_s > 0.0 and not self.prompt and self._loop is not None \
                and self._fd is not None:
            self._loop.remove_reader(self._fd)
            self._watching = False
            self._schedule_poll(bus, generation)
        self._drain(bus, generation)

    def _schedule_poll(self, bus: can.BusABC, generation: int) -> None:
        assert self._loop is not None
        now = self._loop.time()                   # time.monotonic()
        anchor = self.grid_anchor_s
        if anchor is None:
            when = now + self.coalesce_s
        else:
            when = anchor + (math.floor((now - anchor) / self.coalesce_s) + 1) * self.coalesce_s
        self._rx_at_poll = self.rx_frames
        self._rearm = self._loop.call_at(when, self._poll, bus, generation)

    def _poll(self, bus: can.BusABC, generation: int) -> None:
        """Coalescing: while frames keep coming they are read every ``coalesce_s`` by this
        timer alone (one wake per period, the fd not watched); a poll that finds none
        watches the fd again."""
        self._rearm = None
        if generation != self._generation or self._loop is None:
            return
        self.wakes += 1
        frames = self._drain(bus, generation)
        if frames < 0:
            return                                 # the reopen takes over
        if self.rx_frames > self._rx_at_poll:      # frames came, read here or by drain()
            self._schedule_poll(bus, generation)
        else:
            self._watch(bus, generation)

    def drain(self, rounds: int = 1) -> int:
        """Hand over every frame waiting in the socket now (fd reading only; a reader
        thread hands frames over as they come anyway); frames handed over. ``rounds`` > 1:
        read again while a read found frames, at most that often: the frames that came while
        the previous ones were handled are in too."""
        total = 0
        for _ in range(rounds):
            if self._fd is None or self.bus is None:
                break
            n = self._drain(self.bus, self._generation)
            if n <= 0:
                break
            total += n
        return total

    def _drain(self, bus: can.BusABC, generation: int) -> int:
        """Frames handed over (-1: the bus failed)."""
        batch: list[can.Message] = []
        receive = self._receive
        watched_s, self._last_read_s = self._last_read_s, time.monotonic()
        try:
            while len(batch) < BATCH_MAX:
                msg = receive()
                if msg is None:
                    break
                batch.append(msg)
        except Exception as exc:   # noqa: BLE001
            if batch:
                self._deliver(generation, batch, self._last_read_s, watched_s)
            self._lost(generation, exc)
            return -1
        if batch:
            self._deliver(generation, batch, self._last_read_s, watched_s)
        return len(batch)

    def _deliver(self, generation: int, batch: list[can.Message],
                 received_s: float | None = None, watched_s: float | None = None) -> None:
        if generation != self._generation:
            return
        self.received_s = time.monotonic() if received_s is None else received_s
        self.watched_s = self.received_s if watched_s is None else watched_s
        self.rx_frames += len(batch)
        for msg in batch:
            if msg.is_error_frame:
                self.error_frames += 1
                if msg.arbitration_id & CAN_ERR_BUSOFF:
                    self.bus_off += 1
                    self._log.warning("bus-off", "%s: bus-off reported by the controller "
                                      "(%d so far)", self.channel_info, self.bus_off)
        try:
            self.on_frames(batch)
        except Exception:   # noqa: BLE001 - the consumer guards itself; belt and braces
            log.exception("frame consumer failed")

    # --- failures and reconnecting ---------------------------------------------------------

    def _lost(self, generation: int, exc: BaseException) -> None:
        if generation != self._generation or self._stopping:
            return
        self.bus_errors += 1
        self._log.warning("lost", "%s: bus error: %.200s; reopening",
                          self.channel_info or "CAN bus", exc)
        self._set_state("reconnecting", str(exc))
        if self._reopen_task is None or self._reopen_task.done():
            assert self._loop is not None
            self._reopen_task = self._loop.create_task(self._reopen())

    async def _reopen(self) -> None:
        await self._detach()
        delay = self.backoff_start_s
        while not self._stopping:
            await asyncio.sleep(delay)
            try:
                bus = self.opener(self.settings, self.filters)
            except Exception as exc:   # noqa: BLE001
                self._log.info("unavailable", "bus still unavailable (%.200s); next try in "
                               "%.1f s", exc, min(delay * 2, self.backoff_max_s))
                self._set_state("reconnecting", str(exc))
                delay = min(delay * 2, self.backoff_max_s)
                continue
            self.reconnects += 1
            self._attach(bus)
            self._log.info("open", "%s: bus open again", self.channel_info)
            return

    # --- sending -------------------------------------------------------------------------

    def send(self, msg: can.Message) -> bool:
        """Send without blocking and without raising; False (counted) when it failed."""
        bus = self.bus
        if bus is None:
            self.tx_errors += 1
            return False
        try:
            bus.send(msg, timeout=0.0)
        except Exception as exc:   # noqa: BLE001 - full tx queue, bus-off, closed socket
            self.tx_errors += 1
            now = time.monotonic()
            if now - self._last_tx_error_log >= 5.0:
                self._last_tx_error_log = now
                log.warning("%s: send failed (%d so far): %s", self.channel_info,
                            self.tx_errors, exc)
            return False
        self.tx_frames += 1
        return True
