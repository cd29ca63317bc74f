"""One emulated CiA 406 linear position sensor per cylinder: a canopen ``LocalNode`` from the
EDS shipped in the package.

- TPDO1 (0x180 + node): position 0x6020 sub 1 (INT32, measuring step 0x6005 sub 1, from
  ``can.position_step_mm``), speed 0x6030 sub 1 (INT16, 0.1 mm/s), status 0x2000; sent every
  event timer (0x1800 sub 5, from ``can.event_timer_ms``).
- TPDO2 (0x280 + node): diagnostics 0x2001..0x2004 (uncertainty, flags, input frames,
  rejected frames) every 0x1801 sub 5 (EDS default 100 ms), in the same tick as a TPDO1.
- Heartbeat producer 0x1017 (EDS default 1000 ms), boot-up message, NMT slave. The node
  starts itself (boot-up, then OPERATIONAL, as sensors with "auto start" do); PDOs go out only
  while OPERATIONAL; a reset command reboots the node (the estimate is kept).
- SDO server: reads return the live values; writing the preset 0x6010 sub 1 (in measuring
  steps) sets the estimate, refused with abort 0609 0030 outside the stroke; event timers and
  the heartbeat time may be written too.

canopen's own timers (``PdoMap.start``, the NMT heartbeat task) run in threads on the bus and
would keep a hung service looking alive; here the service's tick sends everything, so a
heartbeat on the bus means the service loop is running. ``LocalNode`` TPDOs ignore SYNC, and
so does this node (transmission type 254: event timer only).
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import can
import canopen
from canopen.sdo import SdoAbortedError

from ..config import Config

log = logging.getLogger(__name__)

EDS_PATH = Path(__file__).resolve().parent.parent / "data" / "cia406_position_sensor.eds"

ABORT_VALUE_RANGE = 0x06090030      # value range of parameter exceeded
ABORT_VALUE_TOO_HIGH = 0x06090031
ABORT_VALUE_TOO_LOW = 0x06090032
SPEED_STEP_MM_S = 0.1               # 0x6030 counts (EDS comment, DBC scale)
UNCERTAINTY_STEP_MM = 0.01          # 0x2001 counts
INT32 = (-(2 ** 31), 2 ** 31 - 1)
INT16 = (-(2 ** 15), 2 ** 15 - 1)


def _clamp(value: int, bounds: tuple[int, int]) -> int:
    return min(max(value, bounds[0]), bounds[1])


@dataclass(frozen=True)
class Published:
    """What one sensor node reports: the service's view of one cylinder at one instant."""

    position_mm: float
    speed_mm_s: float
    uncertainty_mm: float
    flags: int
    input_frames: int
    rejected_frames: int


class ServiceNetwork(canopen.Network):
    """A canopen Network that is never ``connect()``-ed: the service feeds it frames
    (``notify``) from its own reader and it sends through the service's bus link."""

    def __init__(self, send: Callable[[can.Message], bool]) -> None:
        super().__init__(bus=None)
        self._send = send

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self._send(can.Message(arbitration_id=can_id, data=bytes(data),
                               is_extended_id=can_id > 0x7FF, is_remote_frame=remote))

    def send_periodic(self, *args: object, **kwargs: object):  # type: ignore[override]
        raise RuntimeError("periodic frames are sent by the service's tick, not by threads")


class SensorNode:
    """The emulated sensor of one cylinder."""

    event_timer_bounds_ms: tuple[float, float] = (1.0, 1000.0)   # the service sets its config
    _tick: int | None = None                                      # last tick index published

    def __init__(self, network: ServiceNetwork, cfg: Config, actuator: str,
                 live: Callable[[], Published],
                 on_preset: Callable[[float], None],
                 eds: str | Path = EDS_PATH) -> None:
        self.actuator = actuator
        self.node_id = cfg.can.units[actuator].sensor_node_id  # type: ignore[index]
        self.step_mm = cfg.can.position_step_mm
        self.stroke_mm = cfg.unit(actuator).stroke_mm
        self.live, self.on_preset = live, on_preset
        self.network = network
        node = network.create_node(self.node_id, str(eds))
        assert isinstance(node, canopen.LocalNode)
        self.node = node
        node.tpdo.read(from_od=True)
        for pdo in (node.tpdo[1], node.tpdo[2]):
            if pdo.cob_id in network.subscribers:       # we send these; never receive them
                network.unsubscribe(pdo.cob_id, pdo.on_message)
        self.tpdo1, self.tpdo2 = node.tpdo[1], node.tpdo[2]
        self._pos, self._speed, self._status = (self.tpdo1[0x6020], self.tpdo1[0x6030],
                                                self.tpdo1[0x2000])
        self._diag = [self.tpdo2[i] for i in (0x2001, 0x2002, 0x2003, 0x2004)]
        self.cob_ids = {"position": self.tpdo1.cob_id, "diag": self.tpdo2.cob_id,
                        "heartbeat": 0x700 + self.node_id, "sdo_tx": 0x580 + self.node_id,
                        "sdo_rx": 0x600 + self.node_id}
        # Settings from the config, stored as if written by a configuration tool.
        node.set_data(0x6005, 1, struct.pack("<I", round(self.step_mm * 1e6)))
        self.event_timer_ms = float(cfg.can.event_timer_ms)
        node.set_data(0x1800, 5, struct.pack("<H", max(1, round(self.event_timer_ms))))
        self.diag_timer_ms = float(node.sdo[0x1801][5].raw)
        self._every = (1, 10)               # ticks per TPDO1, per TPDO2 (set_tick)
        self._next = (0, 0)                 # tick index at which each is due next
        self.heartbeat_period_s = 0.0
        self._next_heartbeat_s: float | None = None
        self.on_timer_change: Callable[[], None] | None = None
        # The NMT slave's heartbeat goes through our tick, not a thread.
        node.nmt.start_heartbeat = self._start_heartbeat          # type: ignore[method-assign]
        node.nmt.stop_heartbeat = self._stop_heartbeat            # type: ignore[method-assign]
        node.nmt.update_heartbeat = lambda: None                  # type: ignore[method-assign]
        node.add_read_callback(self._on_read)
        node.add_write_callback(self._on_write)
        self.presets = 0

    # --- NMT and heartbeat ---------------------------------------------------------------

    def _start_heartbeat(self, heartbeat_time_ms: int) -> None:
        self.heartbeat_period_s = heartbeat_time_ms / 1000.0
        self._next_heartbeat_s = None          # send at the next tick, then every period

    def _stop_heartbeat(self) -> None:
        self.heartbeat_period_s = 0.0

    def boot(self) -> None:
        """Boot-up message, PRE-OPERATIONAL (heartbeat starts), then OPERATIONAL."""
        nmt = self.node.nmt
        nmt._state = 0                                         # noqa: SLF001 - re-boot
        nmt.send_command(0x81)          # reset node: boot-up message (state 0)
        nmt.send_command(0x80)          # -> PRE-OPERATIONAL: heartbeat from 0x1017
        nmt.send_command(0x01)          # auto start -> OPERATIONAL
        log.info("%s sensor node %d booted, OPERATIONAL", self.actuator, self.node_id)

    def after_nmt_command(self) -> None:
        """An NMT command was received: a reset reboots the node (boot-up again)."""
        if self.node.nmt._state == 0:                          # noqa: SLF001
            self.boot()

    @property
    def operational(self) -> bool:
        return self.node.nmt.state == "OPERATIONAL"

    def heartbeat_due(self, now_s: float) -> None:
        if self.heartbeat_period_s <= 0.0:
            return
        if self._next_heartbeat_s is None or now_s >= self._next_heartbeat_s:
            base = now_s if self._next_heartbeat_s is None else self._next_heartbeat_s
            self._next_heartbeat_s = base + self.heartbeat_period_s
            if self._next_heartbeat_s <= now_s:            # far behind: do not burst
                self._next_heartbeat_s = now_s + self.heartbeat_period_s
            self.network.send_message(0x700 + self.node_id, bytes([self.node.nmt._state]))  # noqa: SLF001

    # --- publishing ------------------------------------------------------------------------

    def encode(self, p: Published) -> None:
        self._pos.raw = _clamp(round(p.position_mm / self.step_mm), INT32)
        self._speed.raw = _clamp(round(p.speed_mm_s / SPEED_STEP_MM_S), INT16)
        self._status.raw = p.flags & 0xFF

    def encode_diag(self, p: Published) -> None:
        u, flags, inputs, rejected = self._diag
        u.raw = _clamp(round(p.uncertainty_mm / UNCERTAINTY_STEP_MM), (0, 0xFFFF))
        flags.raw = p.flags & 0xFF
        inputs.raw = p.input_frames & 0xFFFF
        rejected.raw = p.rejected_frames & 0xFFFF

    def set_tick(self, tick_ms: float) -> None:
        """The service ticks every ``tick_ms``: TPDO1 every round(event timer / tick)
        ticks, TPDO2 every round(its timer / tick) ticks, in a tick that also sends TPDO1.
        A shorter timer takes effect at once: nothing already scheduled waits longer than
        the new interval from the last tick."""
        pos = max(1, round(self.event_timer_ms / tick_ms))
        diag = max(pos, round(self.diag_timer_ms / tick_ms / pos) * pos)
        self._every = (pos, diag)
        if self._tick is not None:
            self._next = (min(self._next[0], self._tick + pos),
                          min(self._next[1], self._tick + diag))

    def publish(self, p: Published, tick_index: int) -> int:
        """TPDO1 (and TPDO2) if due at this tick; frames sent (none unless OPERATIONAL)."""
        self._tick = tick_index
        if not self.operational:
            return 0
        next_pos, next_diag = self._next
        if tick_index < next_pos:
            return 0
        every_pos, every_diag = self._every
        self.encode(p)
        self.tpdo1.transmit()
        sent = 1
        if tick_index >= next_diag:
            self.encode_diag(p)
            self.tpdo2.transmit()
            sent = 2
            next_diag = tick_index + every_diag
        self._next = (tick_index + every_pos, next_diag)
        return sent

    # --- SDO -------------------------------------------------------------------------------

    def _on_read(self, index: int, subindex: int, od: object) -> int | None:
        if index not in (0x6020, 0x6030, 0x2000, 0x2001, 0x2002, 0x2003, 0x2004):
            return None
        if index in (0x6020, 0x6030) and subindex != 1:
            return None
        p = self.live()
        if index == 0x6020:
            return _clamp(round(p.position_mm / self.step_mm), INT32)
        if index == 0x6030:
            return _clamp(round(p.speed_mm_s / SPEED_STEP_MM_S), INT16)
        if index == 0x2001:
            return _clamp(round(p.uncertainty_mm / UNCERTAINTY_STEP_MM), (0, 0xFFFF))
        if index in (0x2000, 0x2002):
            return p.flags & 0xFF
        return (p.input_frames if index == 0x2003 else p.rejected_frames) & 0xFFFF

    def _on_write(self, index: int, subindex: int, od: object, data: bytes) -> None:
        if index == 0x6010 and subindex == 1:
            counts = struct.unpack("<i", bytes(data))[0]
            position_mm = counts * self.step_mm
            half_step = 0.5 * self.step_mm          # the stroke ends, to the step's precision
            if not -half_step <= position_mm <= self.stroke_mm + half_step:
                log.warning("%s: preset %.3f mm refused: outside the stroke 0..%g mm",
                            self.actuator, position_mm, self.stroke_mm)
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            position_mm = min(max(position_mm, 0.0), self.stroke_mm)
            self.on_preset(position_mm)
            self.presets += 1
            log.info("%s: position preset to %.3f mm over SDO", self.actuator, position_mm)
        elif index in (0x1800, 0x1801) and subindex == 5:
            ms = struct.unpack("<H", bytes(data))[0]
            lo, hi = self.event_timer_bounds_ms
            if ms < lo or ms > hi:           # 0: this node only sends on a timer
                log.warning("%s: TPDO%d event timer %d ms refused: outside %g..%g ms",
                            self.actuator, 1 if index == 0x1800 else 2, ms, lo, hi)
                raise SdoAbortedError(ABORT_VALUE_TOO_LOW if ms < lo else ABORT_VALUE_TOO_HIGH)
            if index == 0x1800:
                self.event_timer_ms = float(ms)
            else:
                self.diag_timer_ms = float(ms)
            log.info("%s: TPDO%d event timer set to %d ms over SDO", self.actuator,
                     1 if index == 0x1800 else 2, ms)
            if self.on_timer_change is not None:
                self.on_timer_change()


def sdo_preset(network: canopen.Network, node_id: int, position_mm: float,
               step_mm: float, eds: str | Path = EDS_PATH) -> None:
    """Client side: write the preset of a sensor node (raises SdoAbortedError if refused)."""
    node = network.nodes.get(node_id) or network.add_node(node_id, str(eds))
    node.sdo[0x6010][1].raw = round(position_mm / step_mm)
