"""The daemon: Sevcon frames in, one emulated CiA 406 sensor per cylinder out.

One asyncio loop:

- the bus links (one per bus the machine's frames are on: :mod:`.buses`) hand received frames
  over in batches to one ingestion path (:mod:`.ingest`) that routes them by ID, with a
  dispatcher task working through any backlog in bounded slices;
- the publishing tick, from absolute deadlines at the fastest TPDO1 event timer (bounded to
  ``faults.event_timer_min_ms..event_timer_max_ms``; a new timer takes effect at once),
  sends every OPERATIONAL node's TPDO1 (and TPDO2 on its own, slower timer), each on its
  unit's bus; a unit whose newest Sevcon frame is older than ``can.fresh_input_ms`` then
  (slow input: 500 Hz) sends right after its next frame instead, at most a period later;
- the housekeeping tick, fixed at ``faults.housekeeping_tick_ms`` whatever the event timers:
  heartbeats, the systemd watchdog (while the integration keeps up), READY once every bus is
  open, the systemd status, the estimates saved every ``state_save_interval_s`` (in a
  worker thread, atomically: :mod:`.persistence`), and with ``options.machine`` the day
  summary's samples handed to its worker process (:mod:`.summary`), and the health it
  judges from the summaries on the nodes (:mod:`.health`; the last one at start);
- both ticks run straight from the loop's wake on the same deadlines (one wake where their
  periods meet), and the bus links read on the publishing tick's grid (:mod:`.bus`): the
  loop's wake-ups, not the per-frame work, were most of the service's CPU;
- stop (SIGTERM/SIGINT via :meth:`Service.request_stop`): STOPPING=1, state saved as a clean
  stop, the day summary's last samples summarised, buses closed, exit code 0.

What each unit publishes, and why (gaps, staleness, presets): :mod:`.units`. The time between
the start and the first Sevcon frame is not counted as a gap: a controller that has sent
nothing since the start is taken as not yet powered.
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
from typing import TYPE_CHECKING, Any

import can

from ddh_vsensor.canbus.dbc import FrameCodec
from ddh_vsensor.config import DEFAULT_BUS, Config
from ddh_vsensor.estimator.estimator import Estimator
from ddh_vsensor.estimator.extension import Extension
from ddh_vsensor.estimator.flags import flag_text
from ddh_vsensor.tables.lookup import UnitTables
from ddh_vsensor.service.bus import BusLink, exact_filters
from ddh_vsensor.service.buses import machine_buses
from ddh_vsensor.service.heartbeat import HeartbeatConsumer
from ddh_vsensor.service.ingest import Ingest
from ddh_vsensor.service.inputs import Inputs
from ddh_vsensor.service.limits import LogLimiter, RateLimitedLog
from ddh_vsensor.device.network import ServiceNetwork
from ddh_vsensor.device.node import SensorNode
from ddh_vsensor.device.objects import Health, Published
from ddh_vsensor.service.persistence import StateStore, write_states, write_switch_records
from ddh_vsensor.service.scheduler import Tick, Ticker
from ddh_vsensor.service.sdnotify import SystemdNotifier
from ddh_vsensor.service.health import load_health, node_health
from ddh_vsensor.service.summary import HEALTH_FILE, SummaryRecorder
from ddh_vsensor.service.unit_state import STALE_PERIODS, Unit

if TYPE_CHECKING:
    from ddh_vsensor.estimator.kalman_online import KalmanEstimator

log = logging.getLogger(__name__)

BACKLOG_UNHEALTHY_S = 1.0        # a frame waiting this long: integration is not keeping up
STATUS_INTERVAL_S = 2.0
# reads before publishing, at most: a read that found frames is followed by another, since
# handling the first batch takes long enough (0.2-0.5 ms) for a controller's next frame to come
DRAIN_ROUNDS = 3
# a held unit (can.fresh_input_ms) is published by the next tick's half period at the latest
HOLD_MAX_TICKS = 0.5
BUS_PATH_LOGGERS = ("canopen", "ddh_vsensor.device.node", "ddh_vsensor.device.pdo",
                    "ddh_vsensor.device.emcy", "can")


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
    machine: str | None = None               # day summaries under state_dir (None: none)


class Service:
    """``await Service(...).run()`` until :meth:`request_stop`; returns the exit code."""

    def __init__(self, cfg: Config, tables: dict[str, UnitTables], bus: dict[str, Any],
                 options: ServiceOptions | None = None,
                 notifier: SystemdNotifier | None = None,
                 opener: Callable[..., can.BusABC] | None = None,
                 buses: dict[str, dict[str, Any]] | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 wall_clock: Callable[[], float] = time.time) -> None:
        """``bus``: the settings of the default bus (the config's ``bus:`` with command-line
        overrides); ``buses``: settings of the other buses by name (default: the config's);
        ``clock``: monotonic time for what is not passed a time (presets, SDO reads, the
        heartbeat consumers): a campaign driving a service never started passes its own;
        ``wall_clock``: what SocketCAN stamps frames with, for their age at a tick."""
        self.cfg, self.options = cfg, options or ServiceOptions()
        self.clock, self.wall_clock = clock, wall_clock
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
        self.units: dict[str, Unit] = {}
        for actuator in cfg.can.units:
            self.units[actuator] = self._unit(actuator, tables[actuator])
        self._bus_nodes: dict[str, list[SensorNode]] = {name: [] for name in self.bus_names}
        for actuator, unit in self.units.items():
            assert unit.node is not None
            self._bus_nodes[cfg.can.units[actuator].bus].append(unit.node)
        self.states = StateStore(cfg, self.options.state_dir)
        self.summaries: SummaryRecorder | None = None
        if self.options.machine is not None and self.options.state_dir is not None:
            self.summaries = SummaryRecorder(cfg, self.options.machine, self.options.state_dir,
                                             on_health=self._on_health)
            for actuator, feed in self.summaries.feeds.items():
                self.units[actuator].summary_feed = feed
        if self.options.state_dir is not None:
            self._set_health(load_health(Path(self.options.state_dir) / HEALTH_FILE))
        self.states.restore(self.units)
        for unit in self.units.values():
            unit.cap_uncertainty_at_stroke()
        self.ingest = Ingest(self.inputs, self.units, self.networks, self._on_sevcon,
                             self._on_sync, self.faults)
        link_kwargs = {"opener": opener} if opener is not None else {}
        filters = exact_filters(self.ingest.routes)
        self.links: dict[str, BusLink] = {}
        for name in self.bus_names:
            self.links[name] = BusLink(
                settings[name], filters,
                lambda batch, name=name: self.ingest.on_frames(
                    batch, name, self.links[name].received_s, self.links[name].watched_s),
                on_state=lambda state, reason, name=name: self._bus_state(name, state, reason),
                watch_fd=self.options.fd_reader, coalesce_s=self._coalesce_s(),
                log_interval_s=self.faults.log_interval_s, **link_kwargs)
        self.link = self.links[DEFAULT_BUS]
        self.ticker = Ticker(self._period_s(), use_timerfd=self.options.use_timerfd)
        self.housekeeper = Ticker(self.faults.housekeeping_tick_ms / 1000.0,
                                  use_timerfd=self.options.use_timerfd)
        self.ready = False
        self._stop_event = asyncio.Event()
        self._exit_code = 0
        self._tasks: list[asyncio.Task] = []
        self._save_task: asyncio.Future | None = None
        self._save_again = False
        self._next_save_s = math.inf
        self._next_watchdog_s = 0.0
        self._next_status_s = 0.0
        self._last_publish_s = math.inf
        self._tick_index = 0          # ticks since start, missed ones included
        # units whose due TPDO1 waits for their next Sevcon frame (can.fresh_input_ms) ->
        # the tick it belongs to; released by that frame or by the timer at the latest
        self._held: dict[str, int] = {}
        self._release: asyncio.TimerHandle | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.started = False
        self.ticks = 0
        self.housekeeping_ticks = 0
        self.watchdog_pings = 0
        self.saves = 0
        self.frames_published = 0
        self.latency_s: deque[float] = deque(maxlen=1_000_000)
        self.observers: list[Callable[[str, Published, float | None], None]] = []
        self._timers_changed()

    # --- set-up ------------------------------------------------------------------------------

    def _unit(self, actuator: str, tables: UnitTables) -> Unit:
        """A unit with its estimator (extended if ``options.extensions`` says so), its
        controller's heartbeat consumer and its sensor node, on its bus's network."""
        cfg, faults = self.cfg, self.faults
        ext = self.options.extensions.get(actuator)
        est: Estimator | KalmanEstimator
        if ext is not None:
            est = ext.estimator(cfg, tables)
        elif cfg.estimator.mode == "kalman":
            from ddh_vsensor.estimator.kalman_online import KalmanEstimator
            est = KalmanEstimator(cfg, actuator)
        else:
            est = Estimator(cfg, actuator, tables)
        network = self.networks[cfg.can.units[actuator].bus]
        hb_node = faults.heartbeat_node_ids.get(actuator)  # type: ignore[call-overload]
        hb = None if hb_node is None else HeartbeatConsumer(
            network, hb_node, actuator,
            self.options.heartbeat_timeout_s or faults.heartbeat_timeout_s,
            log_interval_s=faults.log_interval_s, clock=self.clock)
        unit = Unit(actuator, est, hb, cfg, self.inputs, self._log,
                    lambda: self.ticker.period_s, self.options.stale_periods, clock=self.clock)
        unit.node = SensorNode(network, cfg, actuator,
                               live=lambda: self.published(unit),
                               on_preset=lambda mm: unit.preset(mm, self.published(unit)),
                               heartbeat=hb)
        unit.node.event_timer_bounds_ms = (faults.event_timer_min_ms, faults.event_timer_max_ms)
        unit.node.on_timer_change = self._timers_changed
        return unit

    def _period_s(self) -> float:
        nodes = [u.node for u in self.units.values() if u.node is not None]
        return min(n.event_timer_ms for n in nodes) / 1000.0

    def _coalesce_s(self) -> float:
        """Fd reader wake-ups at most every 5 ms (half a period at short event timers): the
        tick drains the socket before publishing, so outputs are as fresh regardless."""
        if self.options.coalesce_s is not None:
            return self.options.coalesce_s
        return min(0.005, self._period_s() / 2)

    def _poll_grid(self) -> None:
        """The fd readers read on the tick's deadlines (and between them): a read due with
        a tick shares its wake of the loop (a read just before each tick was measured: more
        jitter, no less CPU)."""
        for link in self.links.values():
            link.grid_anchor_s = self.ticker.anchor_s

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
            if self.started:
                self._poll_grid()

    # --- per unit ----------------------------------------------------------------------------

    def _on_sevcon(self, unit: Unit, msg: can.Message, now: float,
                   watched_s: float | None = None) -> None:
        if unit.integrate(msg, now, watched_s):
            if self.options.record_latency:
                self.latency_s.append(time.time() - msg.timestamp)
            if self._held and unit.actuator in self._held:
                self._publish_held(unit)

    def _on_sync(self, bus: str) -> None:
        """A SYNC on ``bus``: its nodes send the TPDOs a master made synchronous. While one
        does, the bus is read as frames come (no coalescing: a SYNC is answered at once, not
        up to a reading period later)."""
        prompt = bool(self._held)
        for node in self._bus_nodes[bus]:
            self.frames_published += node.on_sync()
            prompt = prompt or node.synchronous
        link = self.links[bus]
        if link.prompt != prompt:
            link.read_promptly(prompt)

    def _synchronous_on(self, bus: str) -> bool:
        return any(node.synchronous for node in self._bus_nodes[bus])

    def stale(self, unit: Unit, now: float | None = None) -> tuple[bool, str]:
        return unit.stale(self.clock() if now is None else now)

    def published(self, unit: Unit, now: float | None = None) -> Published:
        """What ``unit``'s node publishes at ``now`` (monotonic; default: now)."""
        return unit.published(self.clock() if now is None else now)

    # --- run / stop ----------------------------------------------------------------------------

    def _on_health(self, doc: dict) -> None:
        try:
            health = node_health(doc)
        except ValueError as exc:
            log.warning("health: the worker's document not taken (%s)", exc)
            return
        self._set_health(health)

    def _set_health(self, health: dict[str, Health]) -> None:
        for actuator, unit in self.units.items():
            assert unit.node is not None
            h = health.get(actuator)
            if h is not None and h.alarm and actuator not in self._health_alarms:
                log.warning("%s: maintenance due: the expected position error at the references "
                            "passes %g mm within %g days (ddh-vsensor status --health)",
                            actuator, self.cfg.health.tolerance_mm,
                            self.cfg.health.horizon_days)
            unit.node.set_health(h)

    @property
    def _health_alarms(self) -> set[str]:
        """The units whose node publishes a maintenance due."""
        return {a for a, u in self.units.items()
                if u.node is not None and u.node.health is not None and u.node.health.alarm}

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
        loop = self._loop = asyncio.get_running_loop()
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
        # on the tick's deadlines: both fall in one wake of the loop where their periods meet
        self.housekeeper.start(self.ticker.anchor_s)
        self.ticker.call_every(self._tick)
        self.housekeeper.call_every(self._housekeeping)
        self._poll_grid()
        now = time.monotonic()
        self._last_publish_s = now
        self._next_save_s = now + self.cfg.estimator.state_save_interval_s
        task = loop.create_task(self.ingest.run(), name="ddh-vsensor dispatcher")
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
        if self.summaries is not None:
            await asyncio.get_running_loop().run_in_executor(None, self.summaries.close)
        self._end_hold()
        self.ticker.close()
        self.housekeeper.close()
        for link in self.links.values():
            await link.close()
        log.info("stopped; %s", self.status_line())
        self.log_limiter.detach()
        self.notifier.close()

    # --- persistence -------------------------------------------------------------------------

    def save_states(self, clean: bool = False) -> None:
        """Write every unit's estimate now (blocking), and the switch records that changed.
        ``clean`` only at a clean stop: the one state a restart trusts at its saved
        uncertainty."""
        self.saves += 1
        _write(self.states.snapshots(self.units, self.published, clean),
               self.states.switch_records(self.units))

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
        """Save now, off the loop; asked while a save is still writing (a slow disk), save
        again when it is done, with the estimates of then: no request is dropped."""
        if self._save_task is not None and not self._save_task.done():
            self._save_again = True
            return
        self._save_again = False
        snapshots = self.states.snapshots(self.units, self.published)
        records = self.states.switch_records(self.units)
        self.saves += 1
        if snapshots:
            self._save_task = asyncio.get_running_loop().run_in_executor(
                None, _write, snapshots, records)
            self._save_task.add_done_callback(self._saved)

    def _saved(self, _: asyncio.Future) -> None:
        # a stop writes its own, clean, save after the last background one
        if self._save_again and self.started:
            self._save_in_background()

    # --- the buses ---------------------------------------------------------------------------

    def _send(self, bus: str, msg: can.Message) -> bool:
        return self.links[bus].send(msg)

    def _bus_state(self, bus: str, state: str, reason: str) -> None:
        if self.started:
            label = "bus" if len(self.links) == 1 else f"bus {bus}"
            self.notifier.notify(STATUS=f"{label} {state}: {reason}")

    # --- the ticks ---------------------------------------------------------------------------

    def _tick(self, tick: Tick) -> None:
        try:
            self._on_tick(tick.deadline, tick.missed)
        except Exception:   # noqa: BLE001 - a failed tick must not end publishing
            self._log.warning("tick", "tick failed")
            log.debug("tick failed", exc_info=True)

    def _on_tick(self, deadline: float, missed: int) -> None:
        """The publishing tick: TPDOs of the OPERATIONAL nodes."""
        for link in self.links.values():
            # every frame received so far is in what goes out now, also those that came
            # while the reads before were being handled
            link.drain(DRAIN_ROUNDS)
        now = self.clock()
        self.ticks += 1
        self._tick_index += 1 + missed
        self._last_publish_s = now
        if self._held:               # a hold outlived its bound (this tick came late)
            self._release_held()
        fresh_s = self.cfg.can.fresh_input_ms / 1000.0
        # Frame ages at the deadline decide the holds: what a unit does then depends on its
        # controller's phase alone, not on how late this wake came or on the unit's place in
        # the loop (either switched units between the tick and their next frame: measured,
        # 1.3-1.8 ms of jitter). A frame that came after the deadline is fresh.
        wall_s = self.wall_clock() - max(now - deadline, 0.0)
        release_s = 0.0
        for i, unit in enumerate(self.units.values()):
            assert unit.node is not None
            link = self.links[self.cfg.can.units[unit.actuator].bus]
            if i:                    # what arrived while the units before were published
                link.drain(DRAIN_ROUNDS)
            if unit.node.due(self._tick_index):
                wait_s = unit.hold_for_input_s(wall_s, fresh_s)
                if wait_s > 0.0:
                    self._held[unit.actuator] = self._tick_index
                    link.read_promptly(True)
                    release_s = max(release_s, deadline + wait_s)
                    continue
            self._publish(unit, now, self._tick_index)
        if self._held and self._loop is not None:
            if self._release is not None:
                self._release.cancel()
            self._release = self._loop.call_later(
                min(release_s, deadline + HOLD_MAX_TICKS * self.ticker.period_s)
                - self.clock(), self._release_held)

    def _publish(self, unit: Unit, now: float, tick_index: int) -> None:
        assert unit.node is not None
        p = self.published(unit, now)
        self.frames_published += unit.node.publish(p, tick_index)
        unit.node.report_faults(p)
        for observer in self.observers:
            observer(unit.actuator, p, unit.last_frame_t)

    def _publish_held(self, unit: Unit) -> None:
        """A held unit's next frame is in: its position goes out now."""
        self._publish(unit, self.clock(), self._held.pop(unit.actuator))
        if not self._held:
            self._end_hold()

    def _release_held(self) -> None:
        """The hold's bound passed without the held units' next frames: out as they are."""
        self._release = None
        now = self.clock()
        held, self._held = self._held, {}
        for actuator, tick_index in held.items():
            self._publish(self.units[actuator], now, tick_index)
        self._end_hold()

    def _end_hold(self) -> None:
        if self._release is not None:
            self._release.cancel()
            self._release = None
        for name, link in self.links.items():
            link.read_promptly(self._synchronous_on(name))

    def _housekeeping(self, tick: Tick) -> None:
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
            unit.node.error_control_due(now)
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
        if self.summaries is not None:
            self.summaries.ship()

    # --- health and status -------------------------------------------------------------------

    def integrating(self, now: float | None = None) -> bool:
        """The service is healthy: the dispatcher and the publishing tick run, no received
        frame has waited longer than BACKLOG_UNHEALTHY_S, and the publishing tick ran within
        its period plus BACKLOG_UNHEALTHY_S."""
        now = time.monotonic() if now is None else now
        if not self._tasks or self._tasks[0].done():
            return False
        if now - self._last_publish_s > self.ticker.period_s + BACKLOG_UNHEALTHY_S:
            return False
        oldest = self.ingest.oldest_s()
        return oldest is None or now - oldest < BACKLOG_UNHEALTHY_S

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
        inputs = self.inputs
        parts.append(f"in {sum(u.received for u in inputs.units.values())} "
                     f"rejected {inputs.rejected_total} unknown {inputs.counts['unknown']}")
        drifted = [f"{a} {name}" for a, u in self.units.items()
                   for name in u.switch_drift.drifted]
        if drifted:
            parts.append("reference switch drift: " + ", ".join(drifted))
        presets = [f"{a} {u.presets_accepted}/{u.presets_refused}"
                   for a, u in self.units.items() if u.presets_accepted or u.presets_refused]
        if presets:
            parts.append("presets accepted/refused " + ", ".join(presets))
        ingest = self.ingest
        if ingest.dropped_frames or ingest.canopen_dropped:
            parts.append(f"dropped {ingest.dropped_frames} backlog, {ingest.canopen_dropped} "
                         "canopen")
        return "; ".join(parts)


def _write(snapshots: list[tuple[Path, Any]], records: list[tuple[Path, Any]]) -> None:
    """One save (in a worker thread while running): the estimates, then the switch records
    that changed."""
    write_states(snapshots)
    write_switch_records(records)
