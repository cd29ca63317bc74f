"""The daemon: Sevcon frames in, one emulated CiA 406 sensor per cylinder out.

One asyncio loop, four activities:

- the bus link hands received frames over in batches; every batch is queued and a dispatcher
  task routes the frames in bounded slices (Sevcon TPDO -> that unit's estimator step with the
  frame's own timestamp, oil and I/O frames -> latest values, NMT / SDO / heartbeats ->
  canopen, each canopen COB-ID through its own token bucket, anything else counted), yielding
  between slices so that a flood never holds up the ticks. The backlog is capped
  (``faults.backlog_max_frames``, and no frame older than BACKLOG_DROP_S): the oldest batches
  are dropped and counted, and the Sevcon frames lost with them are an unintegrated gap;
- the publishing tick, from absolute deadlines at the fastest TPDO1 event timer (bounded to
  ``faults.event_timer_min_ms..event_timer_max_ms``; a new timer takes effect at once),
  sends every OPERATIONAL node's TPDO1 (and TPDO2 on its own, slower timer);
- the housekeeping tick, fixed at ``faults.housekeeping_tick_ms`` whatever the event timers:
  heartbeats, the systemd watchdog (while the integration keeps up), READY once the bus is
  open, the systemd status, and the estimates saved every ``state_save_interval_s`` (in a
  worker thread, atomically);
- stop (SIGTERM/SIGINT via :meth:`Service.request_stop`): STOPPING=1, state saved as a clean
  stop, bus closed, exit code 0.

Motion is never dropped silently. Sevcon frames are integrated whatever the controller's
heartbeat says (a consumed controller that is not OPERATIONAL sets Flags.CONTROLLER_NOT_OPERATIONAL). Any
interval the estimator did not integrate (frames missing, held before the first oil
temperature, dropped from the backlog; longer than ``estimator.max_gap_s``) widens the
uncertainty by the worst travel possible in it, ``Config.max_speed_mm_s`` x its length; when
that reaches the stroke the unit is "not referenced" until the next Hall reference. A unit is
stale while no Sevcon frame was integrated for 3 periods (the slower of the event timer and
the measured Sevcon period), while the newest integrated frame is older than that by its own
timestamp (when frame timestamps are this host's wall clock: frames delivered late), or no
oil temperature was ever received: position held,
published speed 0, published uncertainty growing at the worst-case speed (capped at the
stroke), Flags.STALE_INPUT set. The stale flag clears with the first integrated frame after the gap,
because that frame brings the gap's worst-case travel into the uncertainty: from then on the
bound holds again.

A restored estimate is trusted at its saved uncertainty only when it was written at a clean
stop; a periodic save (what a kill leaves) is widened by the worst travel possible since it
was written (wall clock), a save from the future or of unknown age by the whole stroke.
The time between the start and the first Sevcon frame is not counted as a gap: a controller
that has sent nothing since the start is taken as not yet powered.
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
from canopen.sdo import SdoAbortedError

from ..atomic import remove_temp_files
from ..canbus.dbc import FrameCodec
from ..config import DEFAULT_BUS, Config
from ..estimator.estimator import Estimator, Step
from ..estimator.flags import Flags, flag_text
from ..estimator.extension import Extension
from ..estimator.state import EstimatorState, load_state, save_state
from ..tables.lookup import UnitTables
from .bus import BusLink, exact_filters, machine_buses
from .heartbeat import HeartbeatConsumer
from .inputs import Inputs, LogLimiter, RateLimitedLog, TokenBucket
from .network import ServiceNetwork
from .node import SensorNode
from .objects import UINT24_MAX, UNCERTAINTY_STEP_MM, Published
from .scheduler import Ticker
from .sdnotify import SystemdNotifier

log = logging.getLogger(__name__)

STALE_PERIODS = 3.0
DISPATCH_SLICE_FRAMES = 200      # frames per dispatcher slice before yielding to the ticks
DISPATCH_SLICE_S = 0.002
BACKLOG_UNHEALTHY_S = 1.0        # a frame waiting this long: integration is not keeping up
# Batches waiting longer are dropped (counted): sooner than BACKLOG_UNHEALTHY_S would withhold
# the watchdog.
BACKLOG_DROP_S = 0.9
STATUS_INTERVAL_S = 2.0
# Frame timestamps within this of the wall clock are this host's clock (socketcan stamps on
# reception; a remote hub passes the sender's time on): then the newest integrated frame's
# own age says how old the published position is, delivery delays included.
WALL_CLOCK_MATCH_S = 5.0
# The largest uncertainty the diagnostic frame can carry (UNSIGNED24 counts): a bound beyond
# it is published as "not referenced".
UNCERTAINTY_MAX_MM = UINT24_MAX * UNCERTAINTY_STEP_MM
# canopen traffic per COB-ID (NMT, SDO requests, consumed heartbeats): rate and burst. An NMT
# master sends a handful of commands, an SDO client one request per response, a controller
# one heartbeat per 100 ms or slower; beyond that a frame is dropped and counted.
CANOPEN_RATE_HZ = {"nmt": 20.0, "sdo": 500.0, "heartbeat": 50.0}
CANOPEN_BURST = {"nmt": 10, "sdo": 100, "heartbeat": 10}
BUS_PATH_LOGGERS = ("canopen", "ddh_vsensor.service.node", "can")
# CiA 301 SDO abort codes for a refused preset
ABORT_READ_ONLY = 0x06010002            # presets disabled: the object is not writable
ABORT_DEVICE_STATE = 0x08000022         # not in PRE-OPERATIONAL, or the rod is moving
ABORT_VALUE_RANGE = 0x06090030          # the jump is beyond the bound


@dataclass
class ServiceOptions:
    state_dir: Path | None = None            # None: nothing persisted
    heartbeat_timeout_s: float | None = None  # None: faults.heartbeat_timeout_s
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
    heartbeat: HeartbeatConsumer | None      # None: the controller's heartbeat is not consumed
    node: SensorNode | None = None
    last_step: Step | None = None
    last_frame_t: float | None = None        # timestamp of the last integrated Sevcon frame
    last_rx_s: float | None = None           # monotonic time it was integrated
    input_period_s: float | None = None      # measured Sevcon period (smoothed)
    integrated: int = 0
    held: int = 0                            # frames not integrated: no oil temperature yet
    first_held_t: float | None = None        # timestamp of the first of them
    stale_since_s: float | None = None
    stale_reason: str = ""
    references: int = 0
    restored: bool = False
    gaps: int = 0                            # unintegrated intervals that widened the bound
    gap_widening_mm: float = 0.0             # their worst-case travel, in total
    preset_pending: bool = False             # Flags.PRESET_UNCONFIRMED: until a reference confirms it
    # After a preset or a widened gap the estimate is provisional: the estimator is kept
    # unreferenced inside (its next reference corrects in full and teaches the gains
    # nothing), while the flags published say what the service knows (PRESET, or nothing
    # beyond the widened bound).
    provisional: bool = False
    presets_accepted: int = 0
    presets_refused: int = 0

    @property
    def velocity_mm_s(self) -> float:
        return self.last_step.velocity_mm_s if self.last_step is not None else 0.0


def estimator_flags(est: Estimator, clamped: bool = False) -> int:
    """The estimator's flags for its current state (as its step() would report them)."""
    return est.state_flags() | (Flags.TABLE_CLAMPED if clamped else 0)


class Service:
    """``await Service(...).run()`` until :meth:`request_stop`; returns the exit code."""

    def __init__(self, cfg: Config, tables: dict[str, UnitTables], bus: dict[str, Any],
                 options: ServiceOptions | None = None,
                 notifier: SystemdNotifier | None = None,
                 opener: Callable[..., can.BusABC] | None = None,
                 buses: dict[str, dict[str, Any]] | None = None) -> None:
        """``bus``: the settings of the default bus (the config's ``bus:`` with command-line
        overrides); ``buses``: settings of the other buses by name (default: the config's)."""
        self.cfg, self.options = cfg, options or ServiceOptions()
        self.faults = cfg.faults
        self.notifier = notifier or SystemdNotifier()
        self.codec = FrameCodec(cfg)
        self.inputs = Inputs(cfg, self.codec)
        # The default bus carries the oil temperature and the I/O module; the others are
        # opened when a unit is on them. One canopen network per bus: a broadcast NMT command
        # reaches the nodes of the bus it came on.
        settings = machine_buses(cfg, bus)
        settings.update({name: kwargs for name, kwargs in (buses or {}).items()
                         if name in settings})
        self.bus_names = tuple(settings)
        self.networks = {name: ServiceNetwork(lambda msg, name=name: self._send(name, msg))
                         for name in self.bus_names}
        self._log = RateLimitedLog(log, self.faults.log_interval_s)
        self.log_limiter = LogLimiter(self.faults.log_interval_s)
        hb_timeout_s = self.options.heartbeat_timeout_s or self.faults.heartbeat_timeout_s
        self.units: dict[str, Unit] = {}
        for actuator in cfg.can.units:
            ext = self.options.extensions.get(actuator)
            est = (Estimator(cfg, actuator, tables[actuator]) if ext is None
                   else ext.estimator(cfg, tables[actuator]))
            hb_node = self.faults.heartbeat_node_ids.get(actuator)  # type: ignore[call-overload]
            network = self.networks[cfg.can.units[actuator].bus]
            hb = None if hb_node is None else HeartbeatConsumer(
                network, hb_node, actuator, hb_timeout_s,
                log_interval_s=self.faults.log_interval_s)
            unit = Unit(actuator, est, hb)
            unit.node = SensorNode(network, cfg, actuator,
                                   live=lambda u=unit: self.published(u),
                                   on_preset=lambda mm, u=unit: self._preset(u, mm))
            unit.node.event_timer_bounds_ms = (self.faults.event_timer_min_ms,
                                               self.faults.event_timer_max_ms)
            unit.node.on_timer_change = self._timers_changed
            self.units[actuator] = unit
        self.max_speed_mm_s = {a: cfg.max_speed_mm_s(a) for a in self.units}
        self._restore_states()
        self._routes = self._build_routes()
        self._canopen_buckets: dict[tuple[str, int], TokenBucket] = {}
        link_kwargs = {"opener": opener} if opener is not None else {}
        filters = exact_filters(self._routes)
        self.links: dict[str, BusLink] = {}
        for name in self.bus_names:
            self.links[name] = BusLink(
                settings[name], filters, lambda batch, name=name: self._on_frames(batch, name),
                on_state=lambda state, reason, name=name: self._bus_state(name, state, reason),
                watch_fd=self.options.fd_reader, coalesce_s=self._coalesce_s(),
                log_interval_s=self.faults.log_interval_s, **link_kwargs)
        self.link = self.links[DEFAULT_BUS]
        self.ticker = Ticker(self._period_s(), use_timerfd=self.options.use_timerfd)
        self.housekeeper = Ticker(self.faults.housekeeping_tick_ms / 1000.0,
                                  use_timerfd=self.options.use_timerfd)
        self._inbox: deque[tuple[float, str, list[can.Message]]] = deque()
        self._inbox_frames = 0
        self.dropped_frames = 0
        self.canopen_dropped = 0
        self.ready = False
        self._inbox_event = asyncio.Event()
        self._stop_event = asyncio.Event()
        self._exit_code = 0
        self._tasks: list[asyncio.Task] = []
        self._save_task: asyncio.Future | None = None
        self._next_save_s = math.inf
        self._next_watchdog_s = 0.0
        self._next_status_s = 0.0
        self._last_publish_s = math.inf
        self._tick_index = 0          # ticks since start, missed ones included
        self.started = False
        self.ticks = 0
        self.housekeeping_ticks = 0
        self.watchdog_pings = 0
        self.saves = 0
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
            state = None
            if path is not None:
                for tmp in remove_temp_files(path):
                    log.info("%s: removed %s, left by an interrupted save", actuator, tmp.name)
                state = load_state(path, actuator, self.cfg.physics_hash(),
                                   max_bytes=self.faults.state_file_max_bytes)
            est = unit.estimator
            if state is not None:
                est.restore(state)
                unit.restored = True
                if not state.clean:
                    age_s = time.time() - state.saved_at
                    if not math.isfinite(age_s) or age_s < 0.0:
                        self._widen(unit, math.inf, "a saved state from the future")
                    else:
                        self._widen(unit, self.max_speed_mm_s[actuator] * age_s,
                                    f"{age_s:.1f} s since the last periodic save (no clean "
                                    "stop)")
                log.info("%s: estimate restored from %s (%s): %.2f mm +-%.2f mm (not "
                         "referenced until the next reference switch)", actuator, path,
                         "clean stop" if state.clean else "periodic save", est.position_mm,
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
        for network in self.networks.values():           # SDO requests, heartbeats
            for can_id in network.subscribers:
                routes.setdefault(can_id, ("canopen", network))
        routes[0] = ("nmt", None)                        # to the network of its bus
        for unit in self.units.values():
            assert unit.node is not None
            for kind, can_id in unit.node.cob_ids.items():
                if kind != "sdo_rx":
                    routes[can_id] = ("clash", None)
        routes.pop(0x7E5, None)                          # LSS: not served
        return routes

    def _widen(self, unit: Unit, travel_mm: float, why: str) -> None:
        """Motion that was not integrated: widen the uncertainty by its worst-case travel;
        when the bound reaches the stroke the unit is not referenced (until a reference)."""
        est = unit.estimator
        stroke = self.cfg.unit(unit.actuator).stroke_mm
        add = min(abs(travel_mm), stroke)
        unit.gaps += 1
        unit.gap_widening_mm += add
        est.forget_switch_states()          # a switch that changed in the gap is no edge
        if add >= stroke or est.uncertainty_mm + add >= stroke:
            est.add_uncertainty(max(stroke - est.uncertainty_mm, 0.0))
            est.referenced = False
            unit.preset_pending = unit.provisional = False
            self._log.warning(f"gap-{unit.actuator}", "%s: %s: up to %.1f mm of travel not "
                              "integrated: not referenced until the next reference switch",
                              unit.actuator, why, add)
        else:
            est.add_uncertainty(add)
            if est.referenced:
                est.referenced, unit.provisional = False, True
            self._log.warning(f"gap-{unit.actuator}", "%s: %s: uncertainty widened by %.1f "
                              "mm (worst-case travel)", unit.actuator, why, add)

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
            for link in self.links.values():
                link.coalesce_s = self._coalesce_s()

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
        self.log_limiter.attach(BUS_PATH_LOGGERS)
        for link in self.links.values():
            await link.start()
        for unit in self.units.values():
            assert unit.node is not None
            unit.node.boot()
        # Everything alive now (modules, tables, DBC, object dictionaries: ~70 000 objects)
        # lives as long as the service: out of the cyclic GC's sight, a full collection
        # costs microseconds instead of a ~30 ms pause in the middle of the output period.
        gc.collect()
        gc.freeze()
        self.ticker.start()
        self.housekeeper.start()
        now = time.monotonic()
        self._last_publish_s = now
        self._next_save_s = now + self.cfg.estimator.state_save_interval_s
        for coro, name in ((self._dispatcher(), "dispatcher"), (self._ticks(), "tick"),
                           (self._housekeeping(), "housekeeping")):
            task = loop.create_task(coro, name=f"ddh-vsensor {name}")
            task.add_done_callback(self._task_ended)
            self._tasks.append(task)
        self.started = True
        self._ready_when_open()
        log.info("running: %s, TPDO1 every %g ms (%s ticks), state %s",
                 ", ".join(f"{name} {link.channel_info or link.settings}"
                           for name, link in self.links.items()),
                 self.ticker.period_s * 1000, self.ticker.kind,
                 self.options.state_dir or "not persisted")

    def _ready_when_open(self) -> None:
        """READY=1 once every bus is open. Inputs are not awaited (a parked machine sends
        none, and systemd would kill a service that never gets ready): until they come the
        outputs are flagged stale, and the STATUS line says so."""
        if self.ready or any(link.state != "open" for link in self.links.values()):
            return
        self.ready = True
        waiting = [a for a, u in self.units.items() if u.last_rx_s is None]
        note = (f"; ready without inputs from {', '.join(waiting)} (not awaited: published "
                "as stale until they come)") if waiting else ""
        self.notifier.notify(READY=1, STATUS=self.status_line() + note)

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
        self.save_states(clean=True)
        self.ticker.close()
        self.housekeeper.close()
        for link in self.links.values():
            await link.close()
        log.info("stopped; %s", self.status_line())
        self.log_limiter.detach()
        self.notifier.close()

    # --- persistence -------------------------------------------------------------------------

    def _snapshots(self, clean: bool = False) -> list[tuple[Path, EstimatorState]]:
        out = []
        for actuator, unit in self.units.items():
            path = self._state_path(actuator)
            if path is not None:
                state = unit.estimator.snapshot()
                state.uncertainty_mm = self.published(unit).uncertainty_mm
                state.clean = clean
                out.append((path, state))
        return out

    def save_states(self, clean: bool = False) -> None:
        """Write every unit's estimate now (blocking). ``clean`` only at a clean stop: the
        one state a restart trusts at its saved uncertainty."""
        self.saves += 1
        _write_states(self._snapshots(clean))

    def on_signal(self, name: str) -> None:
        """A signal that does not stop the service (SIGHUP, SIGUSR1, SIGUSR2): the
        configuration is not reloaded (a restart applies a new one); the estimates are saved
        now, so that no signal goes unnoticed or loses state."""
        log.warning("%s received: configuration not reloaded (restart the service to apply "
                    "a new one); estimates saved", name)
        if self.started:
            self._save_in_background()
        else:
            self.save_states()

    def _save_in_background(self) -> None:
        if self._save_task is not None and not self._save_task.done():
            return
        snapshots = self._snapshots()
        self.saves += 1
        if snapshots:
            self._save_task = asyncio.get_running_loop().run_in_executor(
                None, _write_states, snapshots)

    # --- receiving ---------------------------------------------------------------------------

    def _send(self, bus: str, msg: can.Message) -> bool:
        return self.links[bus].send(msg)

    def _on_frames(self, batch: list[can.Message], bus: str = DEFAULT_BUS) -> None:
        """A batch from the bus link. Handled right here when nothing is waiting and it is
        small (the common case, a few frames per wake); queued for the dispatcher otherwise,
        so that order is kept and a flood is worked through in bounded slices between
        ticks. The queue is capped: the oldest batches go first (counted)."""
        now = time.monotonic()
        if not self._inbox and len(batch) <= DISPATCH_SLICE_FRAMES:
            self._handle(batch, now, bus)
            return
        self._inbox.append((now, bus, batch))
        self._inbox_frames += len(batch)
        while self._inbox_frames > self.faults.backlog_max_frames or \
                now - self._inbox[0][0] > BACKLOG_DROP_S:
            _, _, dropped = self._inbox.popleft()
            self._inbox_frames -= len(dropped)
            self.dropped_frames += len(dropped)
            self._log.warning("backlog", "received frames not handled in time: %d dropped so "
                              "far (Sevcon frames among them count as an unintegrated gap)",
                              self.dropped_frames)
            if not self._inbox:
                break
        self._inbox_event.set()

    def _handle(self, batch: list[can.Message], now: float, bus: str = DEFAULT_BUS) -> None:
        for msg in batch:
            try:
                self._route(msg, now, bus)
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
                received_s, bus, batch = self._inbox[0]
                if len(batch) > DISPATCH_SLICE_FRAMES:      # split a huge batch
                    head, rest = batch[:DISPATCH_SLICE_FRAMES], batch[DISPATCH_SLICE_FRAMES:]
                    self._inbox[0] = (received_s, bus, rest)
                    batch = head
                else:
                    self._inbox.popleft()
                self._inbox_frames -= len(batch)
                self._handle(batch, received_s, bus)
                done += len(batch)
                if done >= DISPATCH_SLICE_FRAMES or \
                        time.perf_counter() - slice_start >= DISPATCH_SLICE_S:
                    await asyncio.sleep(0)     # let the tick run
                    slice_start, done = time.perf_counter(), 0

    def _route(self, msg: can.Message, now: float, bus: str = DEFAULT_BUS) -> None:
        if msg.is_error_frame:
            return
        if msg.timestamp <= 0.0:          # an interface without timestamps: arrival time
            msg.timestamp = time.time()
        route = self._routes.get(msg.arbitration_id) if not msg.is_extended_id else None
        if route is None:
            self.inputs.unknown(msg)
            return
        kind, target = route
        if kind == "sevcon":
            self._on_sevcon(target, msg, now)
        elif kind == "oil":
            self.inputs.oil(msg, now)
        elif kind == "io":
            self.inputs.io(msg, now)
        elif kind == "canopen":
            if msg.is_remote_frame or not self._canopen_allowed(msg, bus):
                return
            target.notify(msg.arbitration_id, msg.data, msg.timestamp)
        elif kind == "nmt":
            if msg.is_remote_frame or not self._canopen_allowed(msg, bus):
                return
            self.networks[bus].notify(0, msg.data, msg.timestamp)
            for u in self.units.values():
                assert u.node is not None
                if u.node.network is self.networks[bus]:
                    u.node.after_nmt_command()
        else:
            self.inputs.clash(msg)

    def _canopen_allowed(self, msg: can.Message, bus: str = DEFAULT_BUS) -> bool:
        """Token bucket per bus and canopen COB-ID: the excess of a flood is dropped,
        counted."""
        can_id = msg.arbitration_id
        bucket = self._canopen_buckets.get((bus, can_id))
        if bucket is None:
            kind = "nmt" if can_id == 0 else "sdo" if 0x600 <= can_id < 0x680 else "heartbeat"
            bucket = TokenBucket(CANOPEN_RATE_HZ[kind], CANOPEN_BURST[kind])
            self._canopen_buckets[(bus, can_id)] = bucket
        if bucket.take(time.monotonic()):
            return True
        self.canopen_dropped += 1
        self._log.warning(f"canopen-{msg.arbitration_id}", "canopen frames on 0x%03X arrive "
                          "faster than %.0f/s: the excess is dropped (%d so far)",
                          msg.arbitration_id, bucket.rate_hz, self.canopen_dropped)
        return False

    def _on_sevcon(self, unit: Unit, msg: can.Message, now: float) -> None:
        sample = self.inputs.sevcon(unit.actuator, msg, now)
        if sample is None:
            return
        oil = self.inputs.oil_temp_c
        if oil is None:
            unit.held += 1
            self.inputs.units[unit.actuator].reasons["held"] += 1
            if unit.first_held_t is None:
                unit.first_held_t = sample.t_s
            return
        est = unit.estimator
        since = unit.last_frame_t if unit.last_frame_t is not None else unit.first_held_t
        if since is not None:
            dt = sample.t_s - since
            if 0.0 < dt <= est.max_gap_s and unit.last_frame_t is not None:
                unit.input_period_s = dt if unit.input_period_s is None else \
                    0.9 * unit.input_period_s + 0.1 * dt
            elif dt > est.max_gap_s or unit.last_frame_t is None:
                # not integrated by the estimator: only the worst case is known
                self._widen(unit, self.max_speed_mm_s[unit.actuator] * max(dt, 0.0),
                            f"{dt:.3f} s without integrated Sevcon frames")
            elif dt <= 0.0 and unit.last_rx_s is not None:
                # the frame's clock went back: the estimator skips this interval; its length
                # is the arrival gap, at least one input period
                gap_s = max(now - unit.last_rx_s, unit.input_period_s or est.max_gap_s)
                self._widen(unit, self.max_speed_mm_s[unit.actuator] * gap_s,
                            "Sevcon frame time went back")
        unit.first_held_t = None
        was_referenced = est.referenced
        step = est.step(sample.t_s, sample.speed_rpm, sample.torque_nm, oil,
                        self.inputs.refs(unit.actuator))
        unit.last_step = step
        unit.last_frame_t, unit.last_rx_s = sample.t_s, now
        unit.integrated += 1
        if step.reference is not None and not was_referenced:
            # Taken in full from an unreferenced estimate: the edge lies somewhere within its
            # sample, whose travel an estimate clipped at a stroke end did not record, and the
            # travel from the edge to its acceptance (debounce) is the model's: widen by both.
            period_s = unit.input_period_s or est.max_gap_s
            est.add_uncertainty(abs(step.velocity_mm_s)
                                * (self.cfg.estimator.debounce_s + 2.0 * period_s))
        confirmed = unit.provisional and step.reference is not None
        if confirmed:
            unit.provisional = False
            if unit.preset_pending:
                unit.preset_pending = False
                log.info("%s: preset confirmed by a reference switch", unit.actuator)
        if step.reference is not None:
            unit.references += 1
            self._log.info(f"ref-{unit.actuator}", "%s: reference switch %s (%s): position "
                           "%.2f mm, uncertainty %.2f mm", unit.actuator, step.reference,
                           "taken whole" if step.reference_gain >= 1.0 else
                           f"{step.reference_gain:.0%} taken", step.position_mm,
                           step.uncertainty_mm)
        if self.options.record_latency:
            self.latency_s.append(time.time() - msg.timestamp)

    def _preset(self, unit: Unit, position_mm: float) -> None:
        """An SDO write of the preset (0x6010): accepted only as configured
        (``faults.preset``), near standstill and within the jump bound; otherwise refused
        with a CiA 301 abort code. Either way logged with the old and new value, counted."""
        est, node = unit.estimator, unit.node
        assert node is not None
        old_mm = est.position_mm
        p = self.published(unit)
        mode = self.faults.preset
        refusal: tuple[int, str] | None = None
        if mode == "disabled":
            refusal = (ABORT_READ_ONLY, "presets are disabled (faults.preset)")
        elif mode == "pre-operational only" and node.node.nmt.state != "PRE-OPERATIONAL":
            refusal = (ABORT_DEVICE_STATE, f"the node is {node.node.nmt.state}, presets only "
                       "in PRE-OPERATIONAL")
        elif abs(unit.velocity_mm_s) > self.faults.preset_standstill_mm_s:
            refusal = (ABORT_DEVICE_STATE, f"the rod moves at {unit.velocity_mm_s:.1f} mm/s "
                       f"(standstill: below {self.faults.preset_standstill_mm_s:g} mm/s)")
        elif abs(position_mm - old_mm) > p.uncertainty_mm + self.faults.preset_max_jump_mm:
            refusal = (ABORT_VALUE_RANGE, f"a jump of {position_mm - old_mm:+.2f} mm, beyond "
                       f"the uncertainty {p.uncertainty_mm:.2f} mm + "
                       f"{self.faults.preset_max_jump_mm:g} mm")
        if refusal is not None:
            unit.presets_refused += 1
            self._log.warning(f"preset-refused-{unit.actuator}", "%s: preset %.3f mm refused "
                              "(%s): position stays %.3f mm (%d refused so far)", unit.actuator,
                              position_mm, refusal[1], old_mm, unit.presets_refused)
            raise SdoAbortedError(refusal[0])
        est.preset(position_mm, self.cfg.estimator.uncertainty_reference_mm)
        est.referenced = False                       # provisional: see Unit.provisional
        if unit.stale_since_s is not None:
            unit.stale_since_s = time.monotonic()    # worst-case travel counts from here
        unit.preset_pending = unit.provisional = True
        unit.presets_accepted += 1
        self._log.info(f"preset-{unit.actuator}", "%s: preset accepted: %.3f mm -> %.3f mm "
                       "(flagged until a reference switch confirms it; %d accepted so far)",
                       unit.actuator, old_mm, est.position_mm, unit.presets_accepted)
        if unit.last_step is not None:
            unit.last_step = Step(est.position_mm, unit.last_step.velocity_mm_s,
                                  est.uncertainty_mm,
                                  estimator_flags(est) & ~Flags.NOT_REFERENCED)

    # --- what is published -------------------------------------------------------------------

    def stale(self, unit: Unit, now: float | None = None) -> tuple[bool, str]:
        now = time.monotonic() if now is None else now
        if self.inputs.oil_temp_c is None:
            return True, "no oil temperature yet"
        period = max(self.ticker.period_s, unit.input_period_s or 0.0)
        if unit.last_rx_s is None:
            return True, "no Sevcon frame yet"
        limit_s = self.options.stale_periods * period
        if now - unit.last_rx_s > limit_s:
            return True, f"no Sevcon frame for {now - unit.last_rx_s:.2f} s"
        if unit.last_frame_t is not None:
            age_s = time.time() - unit.last_frame_t
            if limit_s < age_s < WALL_CLOCK_MATCH_S:
                return True, f"the newest Sevcon frame is {age_s:.2f} s old (delivered late)"
        return False, ""

    def published(self, unit: Unit, now: float | None = None) -> Published:
        now = time.monotonic() if now is None else now
        est = unit.estimator
        stale, why = self.stale(unit, now)
        clamped = bool(unit.last_step and unit.last_step.flags & Flags.TABLE_CLAMPED)
        flags = estimator_flags(est, clamped)
        if unit.provisional:
            flags &= ~Flags.NOT_REFERENCED
        if unit.preset_pending:
            flags |= Flags.PRESET_UNCONFIRMED
        if unit.heartbeat is not None and not unit.heartbeat.status(now)[0]:
            flags |= Flags.CONTROLLER_NOT_OPERATIONAL
        u = est.uncertainty_mm
        speed = unit.velocity_mm_s
        if stale:
            if unit.stale_since_s is None:
                unit.stale_since_s = unit.last_rx_s if unit.last_rx_s is not None else now
                unit.stale_reason = why
                self._log.warning(f"stale-{unit.actuator}", "%s: input stale (%s): position "
                                  "held at %.2f mm", unit.actuator, why, est.position_mm)
            held_s = max(now - unit.stale_since_s, 0.0)
            stroke = self.cfg.unit(unit.actuator).stroke_mm
            u = max(u, min(u + self.max_speed_mm_s[unit.actuator] * held_s, stroke))
            flags |= Flags.STALE_INPUT
            speed = 0.0
        elif unit.stale_since_s is not None:
            self._log.info(f"back-{unit.actuator}", "%s: input back after %.2f s (%s)",
                           unit.actuator, now - unit.stale_since_s, unit.stale_reason)
            unit.stale_since_s = None
        if u >= UNCERTAINTY_MAX_MM:
            flags |= Flags.NOT_REFERENCED
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
        """The publishing tick: TPDOs of the OPERATIONAL nodes."""
        for link in self.links.values():
            link.drain()             # every frame received so far is in what goes out now
        now = time.monotonic()
        self.ticks += 1
        self._tick_index += 1 + missed
        self._last_publish_s = now
        for unit in self.units.values():
            assert unit.node is not None
            p = self.published(unit, now)
            self.frames_published += unit.node.publish(p, self._tick_index)
            unit.node.report_faults(p)
            for observer in self.observers:
                observer(unit.actuator, p, unit.last_frame_t)

    async def _housekeeping(self) -> None:
        while True:
            await self.housekeeper.wait()
            try:
                self._on_housekeeping()
            except Exception:   # noqa: BLE001 - a failed tick must not end the housekeeping
                self._log.warning("housekeeping", "housekeeping tick failed")
                log.debug("housekeeping tick failed", exc_info=True)

    def _on_housekeeping(self) -> None:
        """The service's own fixed tick, whatever the event timers: heartbeats, READY,
        watchdog, status, saves."""
        now = time.monotonic()
        self.housekeeping_ticks += 1
        for unit in self.units.values():
            assert unit.node is not None
            unit.node.heartbeat_due(now)
        self._ready_when_open()
        if self.notifier.watchdog_interval_s and now >= self._next_watchdog_s \
                and self.integrating(now):
            self.notifier.notify(WATCHDOG=1)
            self.watchdog_pings += 1
            self._next_watchdog_s = now + self.notifier.watchdog_interval_s
        if now >= self._next_status_s:
            self._next_status_s = now + self.options.status_interval_s
            self.notifier.notify(STATUS=self.status_line(now))
        if now >= self._next_save_s:
            self._next_save_s = now + self.cfg.estimator.state_save_interval_s
            self._save_in_background()

    def integrating(self, now: float | None = None) -> bool:
        """The service is healthy: the dispatcher and the publishing tick run, no received
        frame has waited longer than BACKLOG_UNHEALTHY_S, and the publishing tick ran within
        its period plus BACKLOG_UNHEALTHY_S."""
        now = time.monotonic() if now is None else now
        if len(self._tasks) < 2 or any(t.done() for t in self._tasks[:2]):
            return False
        if now - self._last_publish_s > self.ticker.period_s + BACKLOG_UNHEALTHY_S:
            return False
        return not self._inbox or now - self._inbox[0][0] < BACKLOG_UNHEALTHY_S

    def status_line(self, now: float | None = None) -> str:
        parts = []
        for actuator, unit in self.units.items():
            p = self.published(unit, now)
            parts.append(f"{actuator} {p.position_mm:.2f} mm +-{p.uncertainty_mm:.2f} "
                         f"[{flag_text(p.flags)}]")
        for name, link in self.links.items():
            label = "bus" if len(self.links) == 1 else f"bus {name}"
            parts.append(f"{label} {link.state}"
                         + (f" ({link.reason})" if link.state != "open" else ""))
        parts.append(f"in {sum(u.received for u in self.inputs.units.values())} "
                     f"rejected {self.inputs.rejected_total} unknown {self.inputs.counts['unknown']}")
        presets = [f"{a} {u.presets_accepted}/{u.presets_refused}"
                   for a, u in self.units.items() if u.presets_accepted or u.presets_refused]
        if presets:
            parts.append("presets accepted/refused " + ", ".join(presets))
        if self.dropped_frames or self.canopen_dropped:
            parts.append(f"dropped {self.dropped_frames} backlog, {self.canopen_dropped} "
                         "canopen")
        return "; ".join(parts)

    def _bus_state(self, bus: str, state: str, reason: str) -> None:
        if self.started:
            label = "bus" if len(self.links) == 1 else f"bus {bus}"
            self.notifier.notify(STATUS=f"{label} {state}: {reason}")


def _write_states(snapshots: list[tuple[Path, EstimatorState]]) -> None:
    for path, state in snapshots:
        try:
            save_state(path, state)
        except OSError as exc:
            log.error("cannot save the estimate to %s: %s", path, exc)
