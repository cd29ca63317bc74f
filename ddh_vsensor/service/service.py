"""The daemon: Sevcon frames in, one emulated CiA 406 sensor per cylinder out.

One asyncio loop, three activities:

- the bus link hands received frames over in batches; a dispatcher task routes each one
  (Sevcon TPDO -> that unit's estimator step with the frame's own timestamp, oil and I/O
  frames -> latest values, NMT / SDO / heartbeats -> canopen, anything else counted). It
  works through a backlog in slices so that a flood never holds up the publishing tick;
- the tick, from absolute deadlines at the TPDO1 event timer, publishes every OPERATIONAL
  node's TPDO1 (and TPDO2 on its own, slower timer), sends heartbeats, pings the systemd
  watchdog while the integration keeps up, updates the systemd status, and persists the
  estimates every ``state_save_interval_s`` (written in a worker thread, atomically);
- stop (SIGTERM/SIGINT via :meth:`Service.request_stop`): STOPPING=1, state saved, bus
  closed, exit code 0.

A unit is stale when no Sevcon frame was integrated for 3 periods (the slower of the event
timer and the measured Sevcon period), when its controller's heartbeat is lost or not
OPERATIONAL, or while no oil temperature has been received. Stale: the position is held,
published speed 0, the uncertainty grows at the last measured speed plus the creep
allowance, and the stale flag is set; with the next integrated frame the flag clears, and a
gap the estimator could not integrate (longer than ``estimator.max_gap_s``) leaves its share of
uncertainty behind until the next reference.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from ..canbus.dbc import FrameCodec
from ..config import Config
from ..estimator.extension import Extension
from ..estimator.estimator import FLAG_CLAMPED, FLAG_NAMES, FLAG_STALE, Estimator, Step
from ..estimator.state import EstimatorState, load_state, save_state
from ..tables.lookup import UnitTables
from .bus import BusLink, exact_filters
from .heartbeat import DEFAULT_CONSUMER_TIME_S, HeartbeatConsumer
from .inputs import Inputs, RateLimitedLog
from .node import Published, SensorNode, ServiceNetwork
from .scheduler import Ticker
from .sdnotify import SystemdNotifier

log = logging.getLogger(__name__)

STALE_PERIODS = 3.0
DISPATCH_SLICE_FRAMES = 1000     # frames per dispatcher slice before yielding to the tick
DISPATCH_SLICE_S = 0.002
BACKLOG_UNHEALTHY_S = 1.0        # a frame waiting this long: integration is not keeping up
STATUS_INTERVAL_S = 2.0


@dataclass
class ServiceOptions:
    state_dir: Path | None = None            # None: nothing persisted
    heartbeat_timeout_s: float = DEFAULT_CONSUMER_TIME_S
    stale_periods: float = STALE_PERIODS
    use_timerfd: bool | None = None          # None: timerfd where available
    status_interval_s: float = STATUS_INTERVAL_S
    record_latency: bool = False             # keep frame-to-estimate delays (benchmark)
    fd_reader: bool | None = None            # None: event-loop fd reader on socketcan only
    coalesce_s: float | None = None          # fd reader pause after a wake (None: see below)
    extensions: dict[str, Extension] = field(default_factory=dict)   # actuator -> from analyze


@dataclass
class Unit:
    """One cylinder: its estimator, its emulated node and its input bookkeeping."""

    actuator: str
    estimator: Estimator
    heartbeat: HeartbeatConsumer
    node: SensorNode | None = None
    last_step: Step | None = None
    last_frame_t: float | None = None        # timestamp of the last integrated Sevcon frame
    last_rx_s: float | None = None           # monotonic time it was integrated
    input_period_s: float | None = None      # measured Sevcon period (smoothed)
    integrated: int = 0
    held: int = 0                            # frames not integrated: unit stale (heartbeat/oil)
    stale_since_s: float | None = None
    stale_reason: str = ""
    references: int = 0
    restored: bool = False

    @property
    def velocity_mm_s(self) -> float:
        return self.last_step.velocity_mm_s if self.last_step is not None else 0.0


def estimator_flags(est: Estimator, clamped: bool = False) -> int:
    """The estimator's flags for its current state (as its step() would report them)."""
    return est.state_flags() | (FLAG_CLAMPED if clamped else 0)


def flag_names(flags: int) -> str:
    return ",".join(name for bit, name in FLAG_NAMES.items() if flags & bit) or "ok"


class Service:
    """``await Service(...).run()`` until :meth:`request_stop`; returns the exit code."""

    def __init__(self, cfg: Config, tables: dict[str, UnitTables], bus: dict[str, Any],
                 options: ServiceOptions | None = None,
                 notifier: SystemdNotifier | None = None,
                 opener: Callable[..., can.BusABC] | None = None) -> None:
        self.cfg, self.options = cfg, options or ServiceOptions()
        self.notifier = notifier or SystemdNotifier()
        self.codec = FrameCodec(cfg)
        self.inputs = Inputs(cfg, self.codec)
        self.network = ServiceNetwork(self._send)
        self.units: dict[str, Unit] = {}
        for actuator in cfg.can.units:
            ext = self.options.extensions.get(actuator)
            est = (Estimator(cfg, actuator, tables[actuator]) if ext is None
                   else ext.estimator(cfg, tables[actuator]))
            hb = HeartbeatConsumer(self.network, cfg.can.units[actuator].sevcon_node_id,
                                   actuator, self.options.heartbeat_timeout_s)
            unit = Unit(actuator, est, hb)
            unit.node = SensorNode(self.network, cfg, actuator,
                                   live=lambda u=unit: self.published(u),
                                   on_preset=lambda mm, u=unit: self._preset(u, mm))
            unit.node.on_timer_change = self._timers_changed
            self.units[actuator] = unit
        self._restore_states()
        self._routes = self._build_routes()
        link_kwargs = {"opener": opener} if opener is not None else {}
        self.link = BusLink(bus, exact_filters(self._routes), self._on_frames,
                            on_state=self._bus_state, watch_fd=self.options.fd_reader,
                            coalesce_s=self._coalesce_s(), **link_kwargs)
        self.ticker = Ticker(self._period_s(), use_timerfd=self.options.use_timerfd)
        self._inbox: deque[tuple[float, list[can.Message]]] = deque()
        self._inbox_event = asyncio.Event()
        self._stop_event = asyncio.Event()
        self._exit_code = 0
        self._tasks: list[asyncio.Task] = []
        self._save_task: asyncio.Future | None = None
        self._next_save_s = math.inf
        self._next_watchdog_s = 0.0
        self._next_status_s = 0.0
        self._tick_index = 0          # ticks since start, missed ones included
        self._log = RateLimitedLog(log)
        self.started = False
        self.ticks = 0
        self.frames_published = 0
        self.canopen_errors = 0
        self.latency_s: deque[float] = deque(maxlen=1_000_000)
        self.observers: list[Callable[[str, Published, float | None], None]] = []
        self._timers_changed()

    # --- set-up ------------------------------------------------------------------------------

    def _state_path(self, actuator: str) -> Path | None:
        d = self.options.state_dir
        return None if d is None else Path(d) / f"{actuator}.json"

    def _restore_states(self) -> None:
        for actuator, unit in self.units.items():
            path = self._state_path(actuator)
            state = load_state(path, actuator, self.cfg.physics_hash()) if path else None
            est = unit.estimator
            if state is not None:
                est.restore(state)
                unit.restored = True
                log.info("%s: estimate restored from %s: %.2f mm +-%.2f mm (not referenced "
                         "until the next reference switch)", actuator, path, est.position_mm,
                         est.uncertainty_mm)
            else:
                stroke = self.cfg.unit(actuator).stroke_mm
                est.restore(EstimatorState(actuator, self.cfg.physics_hash(), 0.0, stroke))
                log.info("%s: no saved estimate; starting at 0 mm, uncertainty the whole stroke "
                         "(%g mm), until a reference switch or an SDO preset", actuator, stroke)

    def _build_routes(self) -> dict[int, tuple[str, Any]]:
        routes: dict[int, tuple[str, Any]] = {}
        for frame_id, actuator in self.inputs.sevcon_ids.items():
            routes[frame_id] = ("sevcon", self.units[actuator])
        routes[self.inputs.oil_id] = ("oil", None)
        routes[self.inputs.io_id] = ("io", None)
        for can_id in self.network.subscribers:          # NMT, SDO requests, heartbeats
            routes.setdefault(can_id, ("canopen", None))
        for unit in self.units.values():
            assert unit.node is not None
            for kind, can_id in unit.node.cob_ids.items():
                if kind != "sdo_rx":
                    routes[can_id] = ("clash", None)
        routes.pop(0x7E5, None)                          # LSS: not served
        return routes

    def _period_s(self) -> float:
        nodes = [u.node for u in self.units.values() if u.node is not None]
        return min(n.event_timer_ms for n in nodes) / 1000.0

    def _coalesce_s(self) -> float:
        """Fd reader wake-ups at most every 2 ms (a quarter period at short event timers):
        the tick drains the socket before publishing, so outputs are as fresh regardless."""
        if self.options.coalesce_s is not None:
            return self.options.coalesce_s
        return min(0.002, self._period_s() / 4)

    def _timers_changed(self) -> None:
        """One tick for all nodes at the fastest TPDO1 event timer; each node sends its TPDO1
        and TPDO2 every whole number of ticks nearest its own timers."""
        nodes = [u.node for u in self.units.values() if u.node is not None]
        period_ms = min(n.event_timer_ms for n in nodes)
        for n in nodes:
            n.set_tick(period_ms)
        if hasattr(self, "ticker"):
            self.ticker.set_period(period_ms / 1000.0)
            self.link.coalesce_s = self._coalesce_s()

    # --- run / stop ----------------------------------------------------------------------------

    def request_stop(self, exit_code: int = 0) -> None:
        self._exit_code = max(self._exit_code, exit_code)
        self._stop_event.set()

    async def run(self) -> int:
        await self.start()
        try:
            await self._stop_event.wait()
        finally:
            await self.shutdown()
        return self._exit_code

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        self._inbox_event = asyncio.Event()
        self._stop_event = asyncio.Event()
        await self.link.start()
        for unit in self.units.values():
            assert unit.node is not None
            unit.node.boot()
        # Everything alive now (modules, tables, DBC, object dictionaries: ~70 000 objects)
        # lives as long as the service: out of the cyclic GC's sight, a full collection
        # costs microseconds instead of a ~30 ms pause in the middle of the output period.
        gc.collect()
        gc.freeze()
        self.ticker.start()
        now = time.monotonic()
        self._next_save_s = now + self.cfg.estimator.state_save_interval_s
        for coro, name in ((self._dispatcher(), "dispatcher"), (self._ticks(), "tick")):
            task = loop.create_task(coro, name=f"ddh-vsensor {name}")
            task.add_done_callback(self._task_ended)
            self._tasks.append(task)
        self.started = True
        self.notifier.notify(READY=1, STATUS=self.status_line())
        log.info("running: %s, TPDO1 every %g ms (%s ticks), state %s", self.link.channel_info
                 or self.link.settings, self.ticker.period_s * 1000, self.ticker.kind,
                 self.options.state_dir or "not persisted")

    def _task_ended(self, task: asyncio.Task) -> None:
        if task.cancelled() or self._stop_event.is_set():
            return
        exc = task.exception()
        log.error("%s ended unexpectedly: %r; stopping (exit 1)", task.get_name(), exc,
                  exc_info=exc)
        self.request_stop(1)

    async def shutdown(self) -> None:
        if not self.started:
            return
        self.started = False
        self.notifier.notify(STOPPING=1, STATUS="stopping: saving the estimates")
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks.clear()
        if self._save_task is not None:
            await asyncio.gather(self._save_task, return_exceptions=True)
        self.save_states()
        self.ticker.close()
        await self.link.close()
        log.info("stopped; %s", self.status_line())
        self.notifier.close()

    # --- persistence -------------------------------------------------------------------------

    def _snapshots(self) -> list[tuple[Path, EstimatorState]]:
        out = []
        for actuator, unit in self.units.items():
            path = self._state_path(actuator)
            if path is not None:
                state = unit.estimator.snapshot()
                state.uncertainty_mm = self.published(unit).uncertainty_mm
                out.append((path, state))
        return out

    def save_states(self) -> None:
        """Write every unit's estimate now (blocking; used at stop)."""
        _write_states(self._snapshots())

    def _save_in_background(self) -> None:
        if self._save_task is not None and not self._save_task.done():
            return
        snapshots = self._snapshots()
        if snapshots:
            self._save_task = asyncio.get_running_loop().run_in_executor(
                None, _write_states, snapshots)

    # --- receiving ---------------------------------------------------------------------------

    def _send(self, msg: can.Message) -> bool:
        return self.link.send(msg)

    def _on_frames(self, batch: list[can.Message]) -> None:
        """A batch from the bus link. Handled right here when nothing is waiting (one loop
        iteration per batch: the common case, a few frames per wake); appended to the
        dispatcher's backlog otherwise, so that order is kept and a flood is worked through
        in slices between ticks."""
        now = time.monotonic()
        if self._inbox or len(batch) > DISPATCH_SLICE_FRAMES:
            self._inbox.append((now, batch))
            self._inbox_event.set()
            return
        self._handle(batch, now)

    def _handle(self, batch: list[can.Message], now: float) -> None:
        for msg in batch:
            try:
                self._route(msg, now)
            except Exception:   # noqa: BLE001 - one bad frame must not stop the rest
                self.canopen_errors += 1
                self._log.warning("route", "frame 0x%03X could not be handled",
                                  msg.arbitration_id)
                log.debug("frame handling failed", exc_info=True)

    async def _dispatcher(self) -> None:
        """Works through the backlog, yielding to the tick every slice."""
        while True:
            await self._inbox_event.wait()
            self._inbox_event.clear()
            slice_start = time.perf_counter()
            done = 0
            while self._inbox:
                _, batch = self._inbox[0]
                if len(batch) > DISPATCH_SLICE_FRAMES:      # split a huge batch
                    head, rest = batch[:DISPATCH_SLICE_FRAMES], batch[DISPATCH_SLICE_FRAMES:]
                    self._inbox[0] = (self._inbox[0][0], rest)
                    batch = head
                else:
                    self._inbox.popleft()
                self._handle(batch, time.monotonic())
                done += len(batch)
                if done >= DISPATCH_SLICE_FRAMES or \
                        time.perf_counter() - slice_start >= DISPATCH_SLICE_S:
                    await asyncio.sleep(0)     # let the tick run
                    slice_start, done = time.perf_counter(), 0

    def _route(self, msg: can.Message, now: float) -> None:
        if msg.is_error_frame:
            return
        if msg.timestamp <= 0.0:          # an interface without timestamps: arrival time
            msg.timestamp = time.time()
        route = self._routes.get(msg.arbitration_id) if not msg.is_extended_id else None
        if route is None:
            self.inputs.unknown(msg)
            return
        kind, unit = route
        if kind == "sevcon":
            self._on_sevcon(unit, msg, now)
        elif kind == "oil":
            self.inputs.oil(msg, now)
        elif kind == "io":
            self.inputs.io(msg, now)
        elif kind == "canopen":
            if msg.is_remote_frame:
                return
            self.network.notify(msg.arbitration_id, msg.data, msg.timestamp)
            if msg.arbitration_id == 0:
                for u in self.units.values():
                    assert u.node is not None
                    u.node.after_nmt_command()
        else:
            self.inputs.clash(msg)

    def _on_sevcon(self, unit: Unit, msg: can.Message, now: float) -> None:
        sample = self.inputs.sevcon(unit.actuator, msg, now)
        if sample is None:
            return
        oil = self.inputs.oil_temp_c
        hb_ok, hb_why = unit.heartbeat.status(now)
        if oil is None or not hb_ok:
            unit.held += 1
            self.inputs.units[unit.actuator].reasons["held"] += 1
            return
        est = unit.estimator
        if unit.last_frame_t is not None:
            dt = sample.t_s - unit.last_frame_t
            if 0.0 < dt <= est.max_gap_s:
                unit.input_period_s = dt if unit.input_period_s is None else \
                    0.9 * unit.input_period_s + 0.1 * dt
            elif dt > est.max_gap_s:
                # not integrated by the estimator: the travel in the gap is unknown
                est.add_uncertainty(unit.velocity_mm_s * dt)
        u_before = est.uncertainty_mm
        step = est.step(sample.t_s, sample.speed_rpm, sample.torque_nm, oil,
                        self.inputs.refs(unit.actuator))
        unit.last_step = step
        unit.last_frame_t, unit.last_rx_s = sample.t_s, now
        unit.integrated += 1
        if step.uncertainty_mm < u_before - 1e-9 and est.travel_mm == 0.0:
            unit.references += 1
            log.info("%s: reference switch: position %.2f mm, uncertainty %.2f mm",
                     unit.actuator, step.position_mm, step.uncertainty_mm)
        if self.options.record_latency:
            self.latency_s.append(time.time() - msg.timestamp)

    def _preset(self, unit: Unit, position_mm: float) -> None:
        unit.estimator.preset(position_mm,
                         self.cfg.estimator.uncertainty_reference_mm)
        if unit.last_step is not None:
            unit.last_step = Step(unit.estimator.position_mm, unit.last_step.velocity_mm_s,
                                  unit.estimator.uncertainty_mm,
                                  estimator_flags(unit.estimator))

    # --- what is published -------------------------------------------------------------------

    def stale(self, unit: Unit, now: float | None = None) -> tuple[bool, str]:
        now = time.monotonic() if now is None else now
        if self.inputs.oil_temp_c is None:
            return True, "no oil temperature yet"
        hb_ok, hb_why = unit.heartbeat.status(now)
        if not hb_ok:
            return True, f"controller {hb_why}"
        period = max(self.ticker.period_s, unit.input_period_s or 0.0)
        if unit.last_rx_s is None:
            return True, "no Sevcon frame yet"
        if now - unit.last_rx_s > self.options.stale_periods * period:
            return True, f"no Sevcon frame for {now - unit.last_rx_s:.2f} s"
        return False, ""

    def published(self, unit: Unit, now: float | None = None) -> Published:
        now = time.monotonic() if now is None else now
        est = unit.estimator
        stale, why = self.stale(unit, now)
        clamped = bool(unit.last_step and unit.last_step.flags & FLAG_CLAMPED)
        flags = estimator_flags(est, clamped)
        u = est.uncertainty_mm
        speed = unit.velocity_mm_s
        if stale:
            if unit.stale_since_s is None:
                unit.stale_since_s = unit.last_rx_s if unit.last_rx_s is not None else now
                unit.stale_reason = why
                self._log.warning(f"stale-{unit.actuator}", "%s: input stale (%s): position "
                                  "held at %.2f mm", unit.actuator, why, est.position_mm)
            held_s = max(now - unit.stale_since_s, 0.0)
            u += (abs(speed) + self.cfg.estimator.uncertainty_hold_mm_per_s) * held_s
            flags |= FLAG_STALE
            speed = 0.0
        elif unit.stale_since_s is not None:
            self._log.info(f"back-{unit.actuator}", "%s: input back after %.2f s (%s)",
                           unit.actuator, now - unit.stale_since_s, unit.stale_reason)
            unit.stale_since_s = None
        counters = self.inputs.units[unit.actuator]
        return Published(est.position_mm, speed, u, flags, counters.received, counters.rejected)

    # --- the tick ----------------------------------------------------------------------------

    async def _ticks(self) -> None:
        while True:
            tick = await self.ticker.wait()
            try:
                self._on_tick(tick.deadline, tick.missed)
            except Exception:   # noqa: BLE001 - a failed tick must not end publishing
                self._log.warning("tick", "tick failed")
                log.debug("tick failed", exc_info=True)

    def _on_tick(self, deadline: float, missed: int) -> None:
        self.link.drain()            # every frame received so far is in what goes out now
        now = time.monotonic()
        self.ticks += 1
        self._tick_index += 1 + missed
        for unit in self.units.values():
            assert unit.node is not None
            p = self.published(unit, now)
            self.frames_published += unit.node.publish(p, self._tick_index)
            unit.node.heartbeat_due(now)
            for observer in self.observers:
                observer(unit.actuator, p, unit.last_frame_t)
        if self.notifier.watchdog_interval_s and now >= self._next_watchdog_s \
                and self.integrating(now):
            self.notifier.notify(WATCHDOG=1)
            self._next_watchdog_s = now + self.notifier.watchdog_interval_s
        if now >= self._next_status_s:
            self._next_status_s = now + self.options.status_interval_s
            self.notifier.notify(STATUS=self.status_line(now))
        if now >= self._next_save_s:
            self._next_save_s = now + self.cfg.estimator.state_save_interval_s
            self._save_in_background()

    def integrating(self, now: float | None = None) -> bool:
        """The integrator is advancing: the dispatcher runs and no received frame has waited
        longer than BACKLOG_UNHEALTHY_S for it (the tick that asks is itself running)."""
        now = time.monotonic() if now is None else now
        if not self._tasks or self._tasks[0].done():
            return False
        return not self._inbox or now - self._inbox[0][0] < BACKLOG_UNHEALTHY_S

    def status_line(self, now: float | None = None) -> str:
        parts = []
        for actuator, unit in self.units.items():
            p = self.published(unit, now)
            parts.append(f"{actuator} {p.position_mm:.2f} mm +-{p.uncertainty_mm:.2f} "
                         f"[{flag_names(p.flags)}]")
        link = self.link
        parts.append(f"bus {link.state}" + (f" ({link.reason})" if link.state != "open" else ""))
        parts.append(f"in {sum(u.received for u in self.inputs.units.values())} "
                     f"rejected {self.inputs.rejected_total} unknown {self.inputs.counts['unknown']}")
        return "; ".join(parts)

    def _bus_state(self, state: str, reason: str) -> None:
        if self.started:
            self.notifier.notify(STATUS=f"bus {state}: {reason}")


def _write_states(snapshots: list[tuple[Path, EstimatorState]]) -> None:
    for path, state in snapshots:
        try:
            save_state(path, state)
        except OSError as exc:
            log.error("cannot save the estimate to %s: %s", path, exc)
