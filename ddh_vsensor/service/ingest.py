"""Every received frame, from every bus, through one path: routed by its ID (IDs are unique
across the machine's buses), in arrival order, in bounded slices.

Sevcon TPDO -> that unit's estimator step with the frame's own timestamp; oil and I/O frames
-> latest values; NMT -> the canopen network of the bus it came on (a broadcast reaches that
bus's nodes only); SYNC -> that bus's nodes' synchronous TPDOs; SDO requests and consumed
heartbeats -> the network that serves them; a remote frame on a node's error-control ID (node
guarding) -> that node; each canopen COB-ID through its own rate limiter (a controller's
heartbeat ID one per reported state, frames that are no heartbeat dropped before it);
other frames on the emulated nodes' own IDs -> counted as ID clashes; anything else counted as
unknown. A batch is handled at once when nothing is waiting and it is small (the common
case, a few frames per wake), else queued for the dispatcher task, which works through the
queue yielding between slices so that a flood never holds up the ticks. The backlog is capped
(``faults.backlog_max_frames``, and no batch older than BACKLOG_DROP_S): the oldest batches
are dropped and counted, and the Sevcon frames lost with them are an unintegrated gap.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

import can

from ddh_vsensor.config import DEFAULT_BUS, FaultsConfig
from ddh_vsensor.service.inputs import Inputs
from ddh_vsensor.service.limits import RateLimitedLog, RateLimiter
from ddh_vsensor.device.network import ServiceNetwork
from ddh_vsensor.device.node import SYNC_COB_ID
from ddh_vsensor.service.unit_state import Unit

log = logging.getLogger(__name__)

DISPATCH_SLICE_FRAMES = 200      # frames per dispatcher slice before yielding to the ticks
DISPATCH_SLICE_S = 0.002
# Batches waiting longer are dropped (counted): sooner than the service's unhealthy backlog
# age would withhold the watchdog.
BACKLOG_DROP_S = 0.9
# canopen traffic per COB-ID (NMT, SDO requests, consumed heartbeats): rate and burst. An NMT
# master sends a handful of commands, an SDO client one request per response, a controller
# one heartbeat per 100 ms or slower; beyond that a frame is dropped and counted.
# A SYNC producer sends one per communication cycle, 1 ms at the fastest; a guarding master
# one request per guard time, 10 ms at the fastest masters allow.
CANOPEN_RATE_HZ = {"nmt": 20.0, "sdo": 500.0, "heartbeat": 50.0, "sync": 2000.0,
                   "guard": 200.0}
CANOPEN_BURST = {"nmt": 10, "sdo": 100, "heartbeat": 10, "sync": 10, "guard": 10}
LSS_ID = 0x7E5                   # not served
NMT_HEARTBEAT_STATES = frozenset({0, 4, 5, 127})   # boot-up, stopped, operational, pre-op


class Ingest:
    """``on_frames(batch, bus)`` from each bus link; ``run()`` is the dispatcher task."""

    def __init__(self, inputs: Inputs, units: Mapping[str, Unit],
                 networks: Mapping[str, ServiceNetwork],
                 on_sevcon: Callable[[Unit, can.Message, float, float | None], None],
                 on_sync: Callable[[str], None], faults: FaultsConfig) -> None:
        self.inputs, self.units, self.networks = inputs, units, networks
        self.on_sevcon, self.on_sync = on_sevcon, on_sync
        self.backlog_max_frames = faults.backlog_max_frames
        self._log = RateLimitedLog(log, faults.log_interval_s)
        self.routes = self._build_routes()
        self._canopen_limiters: dict[tuple[str, int, int], RateLimiter] = {}
        self.inbox: deque[tuple[float, str, list[can.Message], float | None]] = deque()
        self._inbox_frames = 0
        self._event = asyncio.Event()
        self.dropped_frames = 0
        self.canopen_dropped = 0
        self.canopen_errors = 0

    def _build_routes(self) -> dict[int, tuple[str, Any]]:
        routes: dict[int, tuple[str, Any]] = {}
        for frame_id, actuator in self.inputs.sevcon_ids.items():
            routes[frame_id] = ("sevcon", self.units[actuator])
        routes[self.inputs.oil_id] = ("oil", None)
        routes[self.inputs.io_id] = ("io", None)
        for network in self.networks.values():           # SDO requests, heartbeats
            for can_id in network.subscribers:
                kind = "sdo" if 0x600 <= can_id < 0x680 else "heartbeat"
                routes.setdefault(can_id, (kind, network))
        routes[0] = ("nmt", None)                        # to the network of its bus
        routes[SYNC_COB_ID] = ("sync", None)
        for unit in self.units.values():
            assert unit.node is not None
            for kind, can_id in unit.node.cob_ids.items():
                if kind == "heartbeat":
                    routes[can_id] = ("guard", unit.node.guarding)
                elif kind != "sdo_rx":
                    routes[can_id] = ("clash", None)
        routes.pop(LSS_ID, None)
        return routes

    def oldest_s(self) -> float | None:
        """When the oldest batch waiting was received (monotonic); None: nothing waits."""
        return self.inbox[0][0] if self.inbox else None

    def on_frames(self, batch: list[can.Message], bus: str = DEFAULT_BUS,
                  received_s: float | None = None, watched_s: float | None = None) -> None:
        """A batch from a bus link, read at ``received_s`` (monotonic; default: now), the
        bus last found without it at ``watched_s`` (default: when read; see
        :class:`.bus.BusLink`): handled now, or queued (see the module's docstring)."""
        now = time.monotonic() if received_s is None else received_s
        if not self.inbox and len(batch) <= DISPATCH_SLICE_FRAMES:
            self.handle(batch, now, bus, watched_s)
            return
        self.inbox.append((now, bus, batch, watched_s))
        self._inbox_frames += len(batch)
        while self._inbox_frames > self.backlog_max_frames or \
                now - self.inbox[0][0] > BACKLOG_DROP_S:
            _, _, dropped, _ = self.inbox.popleft()
            self._inbox_frames -= len(dropped)
            self.dropped_frames += len(dropped)
            self._log.warning("backlog", "received frames not handled in time: %d dropped so "
                              "far (Sevcon frames among them count as an unintegrated gap)",
                              self.dropped_frames)
            if not self.inbox:
                break
        self._event.set()

    def handle(self, batch: list[can.Message], now: float, bus: str = DEFAULT_BUS,
               watched_s: float | None = None) -> None:
        for msg in batch:
            try:
                self.route(msg, now, bus, watched_s)
            except Exception:   # noqa: BLE001 - one bad frame must not stop the rest
                self.canopen_errors += 1
                self._log.warning("route", "frame 0x%03X could not be handled",
                                  msg.arbitration_id)
                log.debug("frame handling failed", exc_info=True)

    async def run(self) -> None:
        """The dispatcher: works through the backlog, yielding to the ticks every slice."""
        self._event = asyncio.Event()
        if self.inbox:
            self._event.set()
        while True:
            await self._event.wait()
            self._event.clear()
            slice_start = time.perf_counter()
            done = 0
            while self.inbox:
                received_s, bus, batch, watched_s = self.inbox[0]
                if len(batch) > DISPATCH_SLICE_FRAMES:      # split a huge batch
                    head, rest = batch[:DISPATCH_SLICE_FRAMES], batch[DISPATCH_SLICE_FRAMES:]
                    self.inbox[0] = (received_s, bus, rest, watched_s)
                    batch = head
                else:
                    self.inbox.popleft()
                self._inbox_frames -= len(batch)
                self.handle(batch, received_s, bus, watched_s)
                done += len(batch)
                if done >= DISPATCH_SLICE_FRAMES or \
                        time.perf_counter() - slice_start >= DISPATCH_SLICE_S:
                    await asyncio.sleep(0)     # let the tick run
                    slice_start, done = time.perf_counter(), 0

    def route(self, msg: can.Message, now: float, bus: str = DEFAULT_BUS,
              watched_s: float | None = None) -> None:
        if msg.is_error_frame:
            return
        if msg.timestamp <= 0.0:          # an interface without timestamps: arrival time
            msg.timestamp = time.time()
        route = self.routes.get(msg.arbitration_id) if not msg.is_extended_id else None
        if route is None:
            self.inputs.unknown(msg)
            return
        kind, target = route
        if kind == "sevcon":
            self.on_sevcon(target, msg, now, watched_s)
        elif kind == "oil":
            self.inputs.oil(msg, now)
        elif kind == "io":
            self.inputs.io(msg, now)
        elif kind in ("sdo", "heartbeat"):
            if msg.is_remote_frame or (kind == "heartbeat" and not self._heartbeat_ok(msg)) \
                    or not self._canopen_allowed(msg, now, bus, kind):
                return
            target.notify(msg.arbitration_id, msg.data, msg.timestamp)
        elif kind == "guard":
            if not msg.is_remote_frame:
                self.inputs.clash(msg)
            elif self._canopen_allowed(msg, now, bus, kind):
                target.on_request(now)
        elif kind == "sync":
            if not msg.is_remote_frame and self._canopen_allowed(msg, now, bus, kind):
                self.on_sync(bus)
        elif kind == "nmt":
            if msg.is_remote_frame or not self._canopen_allowed(msg, now, bus, kind):
                return
            network = self.networks[bus]
            network.notify(0, msg.data, msg.timestamp)
            for unit in self.units.values():
                assert unit.node is not None
                if unit.node.network is network:
                    unit.node.after_nmt_command()
        else:
            self.inputs.clash(msg)

    def _heartbeat_ok(self, msg: can.Message) -> bool:
        """A heartbeat is one byte naming an NMT state; anything else on a controller's
        heartbeat ID is junk, dropped (counted) before it can take a real heartbeat's
        place in the rate limit."""
        if not 0x700 < msg.arbitration_id < 0x780 or (
                len(msg.data) == 1 and msg.data[0] & 0x7F in NMT_HEARTBEAT_STATES):
            return True
        self.canopen_dropped += 1
        self._log.warning(f"heartbeat-junk-{msg.arbitration_id}", "frames on 0x%03X that are "
                          "no heartbeat (%d bytes) dropped (%d canopen frames so far)",
                          msg.arbitration_id, len(msg.data), self.canopen_dropped)
        return False

    def _canopen_allowed(self, msg: can.Message, now: float, bus: str, kind: str) -> bool:
        """A rate limiter per bus and canopen COB-ID (its route's kind sets rate and burst),
        for heartbeats per COB-ID and state: a flood repeating one state cannot drown the
        controller's own heartbeats reporting another. On arrival time: the excess of a flood
        is dropped, counted."""
        can_id = msg.arbitration_id
        key = (bus, can_id, msg.data[0] & 0x7F) if kind == "heartbeat" and msg.data \
            else (bus, can_id, -1)
        limiter = self._canopen_limiters.get(key)
        if limiter is None:
            limiter = RateLimiter(CANOPEN_RATE_HZ[kind], CANOPEN_BURST[kind])
            self._canopen_limiters[key] = limiter
        if limiter.take(now):
            return True
        self.canopen_dropped += 1
        self._log.warning(f"canopen-{msg.arbitration_id}", "canopen frames on 0x%03X arrive "
                          "faster than %.0f/s: the excess is dropped (%d so far)",
                          msg.arbitration_id, limiter.rate_hz, self.canopen_dropped)
        return False
