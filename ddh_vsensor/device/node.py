"""One emulated CiA 406 linear position sensor per cylinder: a canopen ``LocalNode`` from the
EDS shipped in the package, behaving as CiA 301 / CiA 406 describe for a generic master.

- TPDO1 (0x180 + node): position 0x6020 sub 1 (INT32, measuring step 0x6005 sub 1, from
  ``can.position_step_mm``), speed 0x6030 sub 1 (INT16, 0.1 mm/s), status 0x2000; sent every
  event timer (0x1800 sub 5, from ``can.event_timer_ms``).
- TPDO2 (0x280 + node): diagnostics 0x2001..0x2004 (uncertainty, flags, input frames,
  rejected frames) every 0x1801 sub 5 (EDS default 100 ms), in the same tick as a TPDO1.
- PDO configuration by a master: :mod:`.pdo`; EMCY, error register 0x1001 and error field
  0x1003: :mod:`.emcy`; what the SDO server accepts (not in STOPPED, bounded segmented
  downloads): :mod:`.sdo_gate`.
- NMT slave: boot-up, then PRE-OPERATIONAL, then OPERATIONAL if ``can.nmt_auto_start``.
  Reset communication restores the communication area (0x1000..0x1FFF) to its defaults,
  reset node everything; the estimate itself is the process value and is kept. PDOs go out
  only while OPERATIONAL.
- Heartbeat producer 0x1017 (EDS default 1000 ms); node guarding answered, life guarding
  with 0x100C x 0x100D: :mod:`.guarding`.
- CiA 406 cyclic timer 0x6200: TPDO1's event timer (0x1800 sub 5) by the profile's name,
  which masters written for encoders set; reading and writing either is the same.
- SDO server: reads return the live values; writing the preset 0x6010 sub 1 (in measuring
  steps) sets the estimate, refused with abort 0609 0030 outside the stroke; event timers and
  the heartbeat time may be written too.

canopen's own timers (``PdoMap.start``, the NMT heartbeat task) run in threads on the bus and
would keep a hung service looking alive; here the service's tick sends everything, so a
heartbeat on the bus means the service loop is running. ``LocalNode`` TPDOs ignore SYNC: a
TPDO a master made synchronous goes out from :meth:`SensorNode.on_sync`, which the service
calls for every SYNC (COB-ID 0x1005, the pre-defined 0x80) on the node's bus.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable

import canopen
from canopen.sdo import SdoAbortedError

from ddh_vsensor.canbus.eds import unit_object_dictionary
from ddh_vsensor.config import Config
from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.device.emcy import EmcyProducer
from ddh_vsensor.device.guarding import Guarding
from ddh_vsensor.device.network import ServiceNetwork
from ddh_vsensor.device.objects import (ABORT_MAX_BELOW_MIN, ABORT_VALUE_RANGE, ABORT_VALUE_TOO_HIGH,
                      ABORT_VALUE_TOO_LOW, ALARM_POSITION_ERROR, CHANNEL_ARRAYS, COMM_AREA,
                      INT16, INT32, LIVE_OBJECTS, PDO_INVALID, SPEED_STEP_MM_S, UINT24_MAX,
                      UNCERTAINTY_STEP_MM, WARNING_CLAMPED, WARNING_NO_REFERENCE,
                      WARNING_SOFT_LIMIT, Published, clamp, value_of)
from ddh_vsensor.device.pdo import SYNC_TYPE_MAX, Getter, Packer, PdoConfig
from ddh_vsensor.device.sdo_gate import SdoGate

log = logging.getLogger(__name__)

SYNC_COB_ID = 0x80              # the pre-defined SYNC COB-ID the service routes to on_sync
CYCLIC_TIMER = 0x6200           # CiA 406 cyclic timer (ms): TPDO1's event timer by another name


class SensorNode:
    """The emulated sensor of one cylinder."""

    event_timer_bounds_ms: tuple[float, float] = (1.0, 1000.0)   # the service sets its config
    _tick: int | None = None                                      # last tick index published

    def __init__(self, network: ServiceNetwork, cfg: Config, actuator: str,
                 live: Callable[[], Published],
                 on_preset: Callable[[float], None]) -> None:
        self.actuator = actuator
        self.node_id = cfg.can.units[actuator].sensor_node_id  # type: ignore[index]
        self.step_mm = cfg.can.position_step_mm
        self.stroke_mm = cfg.unit(actuator).stroke_mm
        self.live, self.on_preset = live, on_preset
        self.network = network
        node = network.create_node(self.node_id, unit_object_dictionary(cfg, actuator))
        assert isinstance(node, canopen.LocalNode)
        self.node = node
        node.tpdo.read(from_od=True)
        for pdo in (node.tpdo[1], node.tpdo[2]):
            if pdo.cob_id in network.subscribers:       # we send these; never receive them
                network.unsubscribe(pdo.cob_id, pdo.on_message)
        self.pdos = PdoConfig(node, actuator)
        self.tpdo1, self.tpdo2 = self.pdos.tpdo1, self.pdos.tpdo2
        for pdo in (self.tpdo1, self.tpdo2):
            pdo.transmit = lambda pdo=pdo: self._transmit(pdo)   # type: ignore[method-assign]
        self.cob_ids = {"position": self.tpdo1.cob_id, "diag": self.tpdo2.cob_id,
                        "heartbeat": 0x700 + self.node_id, "sdo_tx": 0x580 + self.node_id,
                        "sdo_rx": 0x600 + self.node_id, "emcy": 0x80 + self.node_id}
        self.auto_start = cfg.can.nmt_auto_start
        self.stroke_steps = round(self.stroke_mm / self.step_mm)
        # Settings from the config, stored as if written by a configuration tool: the
        # defaults that NMT resets return to.
        self._configured: dict[tuple[int, int], bytes] = {}
        self._configure(0x6005, 1, struct.pack("<I", round(self.step_mm * 1e6)))
        emcy_cob_id = self.cob_ids["emcy"] | (0 if cfg.can.emcy_enabled else PDO_INVALID)
        self._configure(0x1014, 0, struct.pack("<I", emcy_cob_id))
        self.event_timer_ms = float(cfg.can.event_timer_ms)
        self._configure(0x1800, 5, struct.pack("<H", max(1, round(self.event_timer_ms))))
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
        self.emcy = EmcyProducer(node, network, actuator, self.cob_ids["emcy"])
        self.guarding = Guarding(node, network.send_message, actuator)
        node.add_read_callback(self._on_read)
        node.add_read_callback(self.emcy.on_read)
        node.add_write_callback(self._on_write)
        node.add_write_callback(self.pdos.on_write)
        node.add_write_callback(self.emcy.on_write)
        node.add_write_callback(self._on_write_profile)
        # NMT commands are seen here too (which reset?), SDO requests pass a gate first.
        self._nmt_command: int | None = None
        network.subscribe(0, self._on_nmt_command)
        self.sdo_gate = SdoGate(node, network, self.cob_ids["sdo_tx"])
        self.presets = 0

    # --- NMT and heartbeat ---------------------------------------------------------------

    def _start_heartbeat(self, heartbeat_time_ms: int) -> None:
        self.heartbeat_period_s = heartbeat_time_ms / 1000.0
        self._next_heartbeat_s = None          # send at the next tick, then every period

    def _stop_heartbeat(self) -> None:
        self.heartbeat_period_s = 0.0

    def boot(self) -> None:
        """Boot-up message, PRE-OPERATIONAL (heartbeat starts), then OPERATIONAL if the
        config says auto start. Active faults are reported again after every boot."""
        nmt = self.node.nmt
        nmt._state = 0                                         # noqa: SLF001 - re-boot
        nmt.send_command(0x81)          # reset node: boot-up message (state 0)
        nmt.send_command(0x80)          # -> PRE-OPERATIONAL: heartbeat from 0x1017
        if self.auto_start:
            nmt.send_command(0x01)      # -> OPERATIONAL
        self.emcy.booted()
        self.guarding.reset()
        log.info("%s sensor node %d booted, %s", self.actuator, self.node_id, nmt.state)

    def _on_nmt_command(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) >= 2 and data[1] in (0, self.node_id):
            self._nmt_command = data[0]

    def after_nmt_command(self) -> None:
        """An NMT command was received: reset communication restores the communication
        area's defaults, reset node all defaults; either reboots the node (boot-up again)."""
        command, self._nmt_command = self._nmt_command, None
        if command in (0x81, 0x82):
            self.restore_defaults(communication_only=command == 0x82)
            self.boot()

    def restore_defaults(self, communication_only: bool) -> None:
        """Objects back to their power-on values (EDS defaults plus the config's settings):
        the communication area only, or everything; PDOs rebuilt, timers re-applied."""
        store = self.node.data_store
        timers = {index: self.node.get_data(index, 5) for index in (0x1800, 0x1801)}
        for index in list(store):
            if not communication_only or index in COMM_AREA:
                del store[index]
        for (index, subindex), data in self._configured.items():
            if not communication_only or index in COMM_AREA:
                store.setdefault(index, {})[subindex] = data
        self.pdos.restore()                    # rebuilt only if a master changed it
        self.emcy.reset()
        for index, before in timers.items():  # a changed timer: the path of an SDO write
            data = self.node.get_data(index, 5)
            if data != before:
                od = self.node.object_dictionary[index][5]
                self._on_write(index=index, subindex=5, od=od, data=data)
        self.sdo_gate.download_limit = None

    @property
    def operational(self) -> bool:
        return self.node.nmt.state == "OPERATIONAL"

    def error_control_due(self, now_s: float) -> None:
        """Every housekeeping tick: the heartbeat when due, the life guarding's verdict (its
        EMCY goes out with the next fault report)."""
        self.emcy.life_guarding(self.guarding.check(now_s))
        if self.heartbeat_period_s <= 0.0:
            return
        if self._next_heartbeat_s is None or now_s >= self._next_heartbeat_s:
            base = now_s if self._next_heartbeat_s is None else self._next_heartbeat_s
            self._next_heartbeat_s = base + self.heartbeat_period_s
            if self._next_heartbeat_s <= now_s:            # far behind: do not burst
                self._next_heartbeat_s = now_s + self.heartbeat_period_s
            state = self.node.nmt._state                              # noqa: SLF001
            self.network.send_message(0x700 + self.node_id, bytes([state]))

    # --- publishing ------------------------------------------------------------------------

    def encode(self, p: Published) -> None:
        """TPDO1's data from ``p``, whatever a master mapped into it."""
        self._encode(self.tpdo1, p)

    def encode_diag(self, p: Published) -> None:
        """TPDO2's data from ``p``, whatever a master mapped into it."""
        self._encode(self.tpdo2, p)

    def _encode(self, pdo: canopen.pdo.PdoMap, p: Published) -> None:
        packers = self.pdos.packers
        packer = packers[pdo] if pdo in packers else \
            packers.setdefault(pdo, Packer.compile(pdo, self._getter))
        data = packer.pack(p) if packer is not None else None
        if data is not None:
            pdo.data[:] = data
            return
        for var in pdo.map:
            value = self._value(var.index, var.subindex, p)
            if value is not None:
                var.raw = value
            elif var.index >= 0x20:                     # a stored object (dummies stay 0)
                var.set_data(self.node.get_data(var.index, var.subindex))

    def _getter(self, index: int, subindex: int, length_bytes: int) -> Getter:
        """A mapped object's value from a published record, as :meth:`_value` gives it
        (the estimate's objects directly), else its stored data (None: not that long)."""
        step_mm = self.step_mm
        live: dict[int, Getter] = {
            0x6020: lambda p: min(max(round(p.position_mm / step_mm), INT32[0]), INT32[1]),
            0x6030: lambda p: min(max(round(p.speed_mm_s / SPEED_STEP_MM_S), INT16[0]),
                                  INT16[1]),
            0x2001: lambda p: min(max(round(p.uncertainty_mm / UNCERTAINTY_STEP_MM), 0),
                                  UINT24_MAX),
            0x2000: lambda p: p.flags & 0xFF, 0x2002: lambda p: p.flags & 0xFF,
            0x2003: lambda p: p.input_frames & 0xFFFF,
            0x2004: lambda p: p.rejected_frames & 0xFFFF}
        if index in live:
            return live[index]
        get_data, value = self.node.get_data, self._value

        def other(p: Published) -> int | None:
            v = value(index, subindex, p)
            if v is not None:
                return v
            data = get_data(index, subindex)
            return int.from_bytes(data, "little") if len(data) == length_bytes else None
        return other

    def _transmit(self, pdo: canopen.pdo.PdoMap) -> None:
        """A TPDO goes out only while valid (COB-ID bit 31 clear)."""
        if pdo.enabled:
            self.network.send_message(pdo.cob_id, pdo.data)

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

    def due(self, tick_index: int) -> bool:
        """Whether :meth:`publish` at this tick sends the position (TPDO1 on its timer)."""
        return self.operational and tick_index >= self._next[0] and \
            self.tpdo1.trans_type > SYNC_TYPE_MAX

    def publish(self, p: Published, tick_index: int) -> int:
        """TPDO1 (and TPDO2) if due at this tick and not synchronous; frames sent (none
        unless OPERATIONAL)."""
        self._tick = tick_index
        if not self.operational:
            return 0
        next_pos, next_diag = self._next
        if tick_index < next_pos:
            return 0
        every_pos, every_diag = self._every
        sent = 0
        if self.tpdo1.trans_type > SYNC_TYPE_MAX:
            self.encode(p)
            self.tpdo1.transmit()
            sent += 1
        if tick_index >= next_diag:
            if self.tpdo2.trans_type > SYNC_TYPE_MAX:
                self.encode_diag(p)
                self.tpdo2.transmit()
                sent += 1
            next_diag = tick_index + every_diag
        self._next = (tick_index + every_pos, next_diag)
        return sent

    @property
    def synchronous(self) -> bool:
        """Whether a valid TPDO goes out on SYNC."""
        tpdo1, tpdo2 = self.tpdo1, self.tpdo2
        return (tpdo1.enabled and tpdo1.trans_type <= SYNC_TYPE_MAX) or \
            (tpdo2.enabled and tpdo2.trans_type <= SYNC_TYPE_MAX)

    def on_sync(self) -> int:
        """A SYNC: the synchronous TPDOs that are due go out now with the estimate as it
        stands (every frame received before the SYNC integrated): type n at every n-th
        SYNC, type 0 when its data changed since it last went out. Frames sent (none unless
        OPERATIONAL)."""
        if not self.operational:
            return 0
        sent = 0
        p: Published | None = None
        pdos = self.pdos
        for pdo in (self.tpdo1, self.tpdo2):
            every = pdo.trans_type
            if every > SYNC_TYPE_MAX or not pdo.enabled:
                continue
            if every:
                counted = pdos.syncs_counted.get(pdo, 0) + 1
                pdos.syncs_counted[pdo] = counted if counted < every else 0
                if counted < every:
                    continue
            p = p or self.live()
            self._encode(pdo, p)
            if every == 0:
                if pdos.sync_sent.get(pdo) == pdo.data:
                    continue
                pdos.sync_sent[pdo] = bytes(pdo.data)
            pdo.transmit()
            sent += 1
        return sent

    # --- SDO -------------------------------------------------------------------------------

    def _on_read(self, index: int, subindex: int, od: object) -> int | None:
        if index in (0x6501, 0x650A):
            return self._value(index, subindex, None)
        if index == CYCLIC_TIMER:
            return struct.unpack("<H", self.node.get_data(0x1800, 5))[0]
        if index not in LIVE_OBJECTS or subindex != (1 if index in CHANNEL_ARRAYS else 0):
            return None
        return self._value(index, subindex, self.live())

    def _value(self, index: int, subindex: int, p: Published | None) -> int | None:
        """The value of an object that follows the estimate (None: a stored object)."""
        if index == 0x6501:                     # measuring step, as 0x6005 sub 1
            return struct.unpack("<I", self.node.get_data(0x6005, 1))[0]
        if index == 0x650A:                     # module identification: offset, min, max
            return {1: 0, 2: 0, 3: self.stroke_steps}.get(subindex)
        if p is None or index not in LIVE_OBJECTS:
            return None
        if index == 0x6020:
            return clamp(round(p.position_mm / self.step_mm), INT32)
        if index == 0x6030:
            return clamp(round(p.speed_mm_s / SPEED_STEP_MM_S), INT16)
        if index == 0x2001:
            return clamp(round(p.uncertainty_mm / UNCERTAINTY_STEP_MM), (0, UINT24_MAX))
        if index in (0x2000, 0x2002):
            return p.flags & 0xFF
        if index in (0x2003, 0x2004):
            return (p.input_frames if index == 0x2003 else p.rejected_frames) & 0xFFFF
        if index == 0x1001:
            return self.emcy.register(p.flags)
        if index == 0x6400:
            return self._area_state(p.position_mm)
        if index == 0x6503:
            alarm = Flags.STALE_INPUT | Flags.CONTROLLER_NOT_OPERATIONAL
            return ALARM_POSITION_ERROR if p.flags & alarm else 0
        no_reference = Flags.NOT_REFERENCED | Flags.PRESET_UNCONFIRMED
        return ((WARNING_NO_REFERENCE if p.flags & no_reference else 0)
                | (WARNING_CLAMPED if p.flags & Flags.TABLE_CLAMPED else 0)
                | (WARNING_SOFT_LIMIT if p.flags & Flags.AT_SOFT_LIMIT else 0))      # 0x6505

    def _area_state(self, position_mm: float) -> int:
        """CiA 406 0x6400: bit 0 outside the measuring range (0x650A), bit 1 above the work
        area's high limit (0x6402), bit 2 below its low limit (0x6401)."""
        steps = round(position_mm / self.step_mm)
        low = struct.unpack("<i", self.node.get_data(0x6401, 1))[0]
        high = struct.unpack("<i", self.node.get_data(0x6402, 1))[0]
        return ((0x01 if not 0 <= steps <= self.stroke_steps else 0)
                | (0x02 if steps > high else 0) | (0x04 if steps < low else 0))

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
        elif index == 0x1005:
            # consumed only: the pre-defined 11-bit ID, no SYNC produced (bit 30), bit 31
            # is don't care (CiA 301)
            if value_of(data) & ~PDO_INVALID != SYNC_COB_ID:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
        elif index in (0x1800, 0x1801) and subindex == 5 or index == CYCLIC_TIMER:
            ms = struct.unpack("<H", bytes(data))[0]
            lo, hi = self.event_timer_bounds_ms
            if ms < lo or ms > hi:           # 0: this node only sends on a timer
                log.warning("%s: TPDO%d event timer %d ms refused: outside %g..%g ms",
                            self.actuator, 2 if index == 0x1801 else 1, ms, lo, hi)
                raise SdoAbortedError(ABORT_VALUE_TOO_LOW if ms < lo else ABORT_VALUE_TOO_HIGH)
            if index == CYCLIC_TIMER:       # CiA 406's name for TPDO1's event timer
                index = 0x1800
                self.node.data_store.setdefault(index, {})[5] = bytes(data)
            if index == 0x1800:
                self.event_timer_ms = float(ms)
            else:
                self.diag_timer_ms = float(ms)
            log.info("%s: TPDO%d event timer set to %d ms over SDO", self.actuator,
                     1 if index == 0x1800 else 2, ms)
            if self.on_timer_change is not None:
                self.on_timer_change()

    # --- configuration defaults and PDO configuration ---------------------------------------

    def _configure(self, index: int, subindex: int, data: bytes) -> None:
        """A setting from the config: stored now, and restored by NMT resets."""
        self._configured[(index, subindex)] = data
        self.node.data_store.setdefault(index, {})[subindex] = data

    def _on_write_profile(self, index: int, subindex: int, od: object, data: bytes) -> None:
        """CiA 406 settings: operating parameters 0x6000 (only 0: the code sequence and the
        scaling are fixed), work area limits 0x6401/0x6402 (low <= high)."""
        if index == 0x6000 and value_of(data) != 0:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        if index in (0x6401, 0x6402) and subindex == 1:
            limit = struct.unpack("<i", bytes(data))[0]
            other_index = 0x6402 if index == 0x6401 else 0x6401
            other = struct.unpack("<i", self.node.get_data(other_index, 1))[0]
            low, high = (limit, other) if index == 0x6401 else (other, limit)
            if low > high:
                raise SdoAbortedError(ABORT_MAX_BELOW_MIN)

    # --- EMCY --------------------------------------------------------------------------------

    def report_faults(self, p: Published, now_s: float | None = None) -> int:
        """Every tick: EMCY for the fault flags that changed (see :meth:`EmcyProducer.report`);
        returns the number of EMCY frames sent."""
        return self.emcy.report(p, now_s)
