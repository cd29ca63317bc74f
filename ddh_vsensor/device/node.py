"""One emulated CiA 406 linear position sensor per cylinder: a canopen ``LocalNode`` from the
EDS shipped in the package, behaving as CiA 301 / CiA 406 describe for a generic master.

- TPDO1 (0x180 + node): position 0x6020 sub 1 (INT32, measuring step 0x6005 sub 1, from
  ``can.position_step_mm``), speed 0x6030 sub 1 (INT16, 0.1 mm/s), status 0x2000; sent every
  event timer (0x1800 sub 5, from ``can.event_timer_ms``).
- TPDO2 (0x280 + node): diagnostics every 0x1801 sub 5 (EDS default 100 ms), in the same
  tick as a TPDO1: uncertainty 0x2001 (UNSIGNED32, 0.01 mm: any stroke), flags 0x2002
  (UNSIGNED8), rejected frames 0x2004 (UNSIGNED8, wraps) and input frames 0x2003
  (UNSIGNED16, wraps), 64 bits, every entry a type IEC 61131-3 tools map (USINT, UINT,
  UDINT; no 24-bit object) and the 16-bit one on an even byte. The rejected-frames counter
  is the one narrowed to fit 64 bits: a master differencing it stays right up to 255
  rejections per TPDO2 period, where a controller sends 10 frames in the default 100 ms.
- TPDO3 (0x380 + node): the unit's health every 0x1802 sub 5 (EDS default 10000 ms; a master
  may write 1..65535 ms, the lower bound TPDO1's), in the same tick as a TPDO1: 0x2010 sub 1
  cause code (UNSIGNED8), sub 2 status (UNSIGNED8), sub 3 and 4 the expected error at the
  references now and at the horizon (UNSIGNED16, 0.01 mm), sub 5 the days until the
  tolerance (UNSIGNED16, 0.1 day), 64 bits.
- Unit health 0x2010 (read only): :meth:`SensorNode.set_health` gives it (the service, from
  the daemon's day summaries; None until one is computed), the node serves it live (SDO reads
  and every TPDO it is mapped into), so NMT resets and boots keep it. Status bit 0 alarm (the
  expected error passes the tolerance within the horizon), bit 1 too few days of evidence for
  a trend, bit 2 no health yet; 0xFFFF: an error unknown, or the tolerance not passed within
  the horizon; sub 6 days of evidence (UNSIGNED16), sub 7 the cause's parameter and sub 8/9
  its interval (REAL32, NaN unknown: SDO only). The alarm is also an EMCY warning FF30
  "maintenance due" (:mod:`.emcy`).
- Identity 0x1018 and device name 0x1008: configuration (``can.vendor_id``,
  ``can.serial_number_base``, ...; :func:`ddh_vsensor.canbus.eds.unit_object_dictionary`).
- PDO configuration by a master: :mod:`.pdo`; EMCY, error register 0x1001 and error field
  0x1003: :mod:`.emcy`; what the SDO server accepts (not in STOPPED, bounded segmented
  downloads): :mod:`.sdo_gate`.
- NMT slave: boot-up, then PRE-OPERATIONAL, then OPERATIONAL if ``can.nmt_auto_start``.
  Reset communication restores the communication area (0x1000..0x1FFF) to its defaults,
  reset node everything; the estimate itself is the process value and is kept. PDOs go out
  only while OPERATIONAL: every TPDO at the first tick there (after a boot or a start), then
  each on its timer.
- Heartbeat producer 0x1017 (EDS default 1000 ms); node guarding answered, life guarding
  with 0x100C x 0x100D: :mod:`.guarding`.
- Consumer heartbeat time 0x1016 sub 1: the unit's motor controller, whose heartbeat the
  service consumes (``faults.heartbeat_node_ids``), and its consumer time (default
  ``faults.heartbeat_timeout_s``). A master's write changes the consumer's time at once; only
  the configured controller's node ID and a time of 1..65535 ms are accepted (0609 0030
  otherwise: which controller is consumed is the configuration's, and a unit's controller is
  always consumed when configured). Without a consumed controller it reads 0, and only 0 is
  accepted.
- Store 0x1010 / restore 0x1011 parameters: :mod:`.storage` (sub 1 all, sub 2
  communication; "save"/"load" signatures, else abort 0800 0020). Stored values are replayed
  through the object dictionary's write path at start (a stored set the node refuses is
  ignored whole, with a warning) and are the values NMT resets return to; a restore makes the
  defaults those values again from the next start or reset. Without a state directory the
  node cannot store: 0x1010/0x1011 read 0 and writes abort 0800 0020.
- CiA 406 cyclic timer 0x6200: TPDO1's event timer (0x1800 sub 5) by the profile's name,
  which masters written for encoders set; reading and writing either is the same.
- SDO server: reads return the live values; writing the preset 0x6010 sub 1 (in measuring
  steps) sets the estimate, refused with abort 0609 0030 outside the stroke; event timers and
  the heartbeat time may be written too.

canopen's own timers (``PdoMap.start``, the NMT heartbeat task) run in threads on the bus and
would keep a hung service looking alive; here the service's tick sends everything, so a
heartbeat on the bus means the service loop is running. Every TPDO (:data:`.pdo.TPDO_COMS`) is
scheduled, configured, stored and restored the same way; TPDO2 and TPDO3 go out in ticks that
send a TPDO1 (on its timer), every whole number of TPDO1 periods nearest their own timers.
``LocalNode`` TPDOs ignore SYNC: a TPDO a master made synchronous goes out from
:meth:`SensorNode.on_sync`, which the service calls for every SYNC (COB-ID 0x1005, the
pre-defined 0x80) on the node's bus.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable
from typing import Protocol

import canopen
from canopen.sdo import SdoAbortedError

from ddh_vsensor.canbus.eds import unit_object_dictionary
from ddh_vsensor.config import Config
from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.device.emcy import EmcyProducer
from ddh_vsensor.device.guarding import Guarding
from ddh_vsensor.device.network import ServiceNetwork
from ddh_vsensor.device.objects import (ABORT_MAX_BELOW_MIN, ABORT_NOT_STORED, ABORT_VALUE_RANGE,
                      ABORT_VALUE_TOO_HIGH, ABORT_VALUE_TOO_LOW, ALARM_POSITION_ERROR,
                      CHANNEL_ARRAYS, COMM_AREA, HEALTH, HEALTH_SUBS, INT16, INT32,
                      LIVE_OBJECTS, PDO_INVALID, SPEED_STEP_MM_S, UNCERTAINTY_MAX_COUNTS,
                      UNCERTAINTY_STEP_MM, WARNING_CLAMPED, WARNING_NO_REFERENCE,
                      WARNING_SOFT_LIMIT, Health, Published, clamp, health_values, raw,
                      value_of)
from ddh_vsensor.device.pdo import (SYNC_TYPE_MAX, TPDO_COMS, TPDO_MAPS, Getter, Packer,
                                    PdoConfig)
from ddh_vsensor.device.pdo import log as pdo_log    # quiet while stored values replay
from ddh_vsensor.device.sdo_gate import SdoGate
from ddh_vsensor.device.storage import (ALL, COMMUNICATION, LOAD, SAVE, Key, ParameterStore,
                                        in_scope, parameters)

log = logging.getLogger(__name__)

SYNC_COB_ID = 0x80              # the pre-defined SYNC COB-ID the service routes to on_sync
CYCLIC_TIMER = 0x6200           # CiA 406 cyclic timer (ms): TPDO1's event timer by another name
STORE, RESTORE, CONSUMER_HEARTBEAT = 0x1010, 0x1011, 0x1016
HEALTH_TPDO = 2                 # TPDO3's place in the node's TPDOs (0-based)
HEALTH_TIMER_MAX_MS = 0xFFFF    # TPDO3's event timer: any UNSIGNED16 but 0 (a slow TPDO)


class _Warnings(logging.Filter):
    """Warnings and errors only: a replay of stored values is logged once, as a whole."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno > logging.INFO


class ConsumedHeartbeat(Protocol):
    """The service's consumer of the unit's controller heartbeat, as 0x1016 sees it."""

    node_id: int
    consumer_time_s: float


class SensorNode:
    """The emulated sensor of one cylinder."""

    event_timer_bounds_ms: tuple[float, float] = (1.0, 1000.0)   # the service sets its config
    _tick: int | None = None                                      # last tick index published

    def __init__(self, network: ServiceNetwork, cfg: Config, actuator: str,
                 live: Callable[[], Published],
                 on_preset: Callable[[float], None],
                 heartbeat: ConsumedHeartbeat | None = None) -> None:
        """``heartbeat``: the consumer whose time 0x1016 sets (None: the object is kept,
        nothing consumes it)."""
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
        self.pdos = PdoConfig(node, actuator)
        self.tpdos = self.pdos.tpdos                    # TPDO1..3
        self.tpdo1, self.tpdo2, self.tpdo3 = self.tpdos
        for pdo in self.tpdos:
            if pdo.cob_id in network.subscribers:       # we send these; never receive them
                network.unsubscribe(pdo.cob_id, pdo.on_message)
            pdo.transmit = lambda pdo=pdo: self._transmit(pdo)   # type: ignore[method-assign]
        self.cob_ids = {"position": self.tpdo1.cob_id, "diag": self.tpdo2.cob_id,
                        "health": self.tpdo3.cob_id,
                        "heartbeat": 0x700 + self.node_id, "sdo_tx": 0x580 + self.node_id,
                        "sdo_rx": 0x600 + self.node_id, "emcy": 0x80 + self.node_id}
        self._health: Health | None = None
        self._health_values = health_values(None)      # 0x2010 sub 0..9 as served
        self.auto_start = cfg.can.nmt_auto_start
        self.stroke_steps = round(self.stroke_mm / self.step_mm)
        # Settings from the config, stored as if written by a configuration tool: the
        # defaults that NMT resets return to.
        self._configured: dict[tuple[int, int], bytes] = {}
        self._configure(0x6005, 1, struct.pack("<I", round(self.step_mm * 1e6)))
        emcy_cob_id = self.cob_ids["emcy"] | (0 if cfg.can.emcy_enabled else PDO_INVALID)
        self._configure(0x1014, 0, struct.pack("<I", emcy_cob_id))
        # each TPDO's event timer (ms): TPDO1's from the config, the others the EDS's
        self.timers_ms = [float(cfg.can.event_timer_ms)] + [
            float(raw(node, com, 5)) for com in TPDO_COMS[1:]]
        self._configure(0x1800, 5, struct.pack("<H", max(1, round(self.event_timer_ms))))
        self.heartbeat = heartbeat
        # the controller 0x1016 names: the configuration's (the consumer's, if one is given)
        self.controller_node_id = heartbeat.node_id if heartbeat is not None else \
            cfg.faults.heartbeat_node_ids.get(actuator)
        if heartbeat is not None:       # the consumer's actual time (options may override)
            self._configure(CONSUMER_HEARTBEAT, 1, struct.pack(
                "<I", heartbeat.node_id << 16 | clamp(round(heartbeat.consumer_time_s * 1000),
                                                      (1, 0xFFFF))))
        self.storage: ParameterStore | None = None
        self._stored: dict[Key, bytes] = {}     # stored by 0x1010: power-on values
        self._every: tuple[int, ...] = ()   # ticks per TPDO (set_tick)
        self._restart = (0,) * len(self.tpdos)      # every TPDO due at once
        self._next = self._restart          # tick index at which each is due next
        self.set_tick(self.event_timer_ms)  # until the service sets its tick
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
        node.add_write_callback(self._on_write_storage)
        node.add_write_callback(self.pdos.on_write)
        node.add_write_callback(self.emcy.on_write)
        node.add_write_callback(self._on_write_profile)
        # NMT commands are seen here too (which reset?), SDO requests pass a gate first.
        self._nmt_command: int | None = None
        network.subscribe(0, self._on_nmt_command)
        self.sdo_gate = SdoGate(node, network, self.cob_ids["sdo_tx"])
        self.presets = 0

    # --- event timers (ms) of TPDO1, TPDO2 and TPDO3 ------------------------------------------

    @property
    def event_timer_ms(self) -> float:
        return self.timers_ms[0]

    @event_timer_ms.setter
    def event_timer_ms(self, ms: float) -> None:
        self.timers_ms[0] = ms

    @property
    def diag_timer_ms(self) -> float:
        return self.timers_ms[1]

    @diag_timer_ms.setter
    def diag_timer_ms(self, ms: float) -> None:
        self.timers_ms[1] = ms

    @property
    def health_timer_ms(self) -> float:
        return self.timers_ms[HEALTH_TPDO]

    @health_timer_ms.setter
    def health_timer_ms(self, ms: float) -> None:
        self.timers_ms[HEALTH_TPDO] = ms

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
        self._next = self._restart      # every TPDO at the first tick
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
        timers = {index: self.node.get_data(index, 5) for index in TPDO_COMS}
        for index in list(store):
            if not communication_only or index in COMM_AREA:
                del store[index]
        for (index, subindex), data in [*self._configured.items(), *self._stored.items()]:
            if not communication_only or index in COMM_AREA:
                store.setdefault(index, {})[subindex] = data
        if self._stored:
            self.pdos.written.update(self.tpdos)
        self.pdos.restore()                    # rebuilt only if a master or a store changed it
        self.emcy.reset()
        for index, before in timers.items():  # a changed timer: the path of an SDO write
            data = self.node.get_data(index, 5)
            if data != before:
                od = self.node.object_dictionary[index][5]
                self._on_write(index=index, subindex=5, od=od, data=data)
        self._consume(value_of(self.node.get_data(CONSUMER_HEARTBEAT, 1)))
        self.sdo_gate.reset()

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
                                  UNCERTAINTY_MAX_COUNTS),
            0x2000: lambda p: p.flags & 0xFF, 0x2002: lambda p: p.flags & 0xFF,
            0x2003: lambda p: p.input_frames & 0xFFFF,
            0x2004: lambda p: p.rejected_frames & 0xFF}
        if index in live:
            return live[index]
        if index == HEALTH and 0 < subindex <= HEALTH_SUBS:     # the health as it is now
            return lambda p: self._health_values[subindex]      # type: ignore[return-value]
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
        """The service ticks every ``tick_ms``: TPDO1 every round(event timer / tick) ticks,
        TPDO2 and TPDO3 each every whole number of TPDO1 periods nearest its own timer, in a
        tick that also sends TPDO1. A shorter timer takes effect at once: nothing already
        scheduled waits longer than the new interval from the last tick."""
        pos = max(1, round(self.event_timer_ms / tick_ms))
        self._every = (pos, *(max(pos, round(ms / tick_ms / pos) * pos)
                              for ms in self.timers_ms[1:]))
        if self._tick is not None:
            self._next = tuple(min(due, self._tick + every)
                               for due, every in zip(self._next, self._every))

    def due(self, tick_index: int) -> bool:
        """Whether :meth:`publish` at this tick sends the position (TPDO1 on its timer)."""
        return self.operational and tick_index >= self._next[0] and \
            self.tpdo1.trans_type > SYNC_TYPE_MAX

    def publish(self, p: Published, tick_index: int) -> int:
        """TPDO1 (and TPDO2, TPDO3) if due at this tick and not synchronous; frames sent
        (none unless OPERATIONAL). The first tick in OPERATIONAL (after a boot, or a start
        from PRE-OPERATIONAL or STOPPED) sends every TPDO, then each goes out on its timer:
        a master starting the node sees the slow TPDO3 at once."""
        self._tick = tick_index
        if not self.operational:
            self._next = self._restart
            return 0
        if tick_index < self._next[0]:
            return 0
        sent = 0
        due = list(self._next)      # all 0 after a boot or a stop: every TPDO goes out now
        for k, (pdo, every) in enumerate(zip(self.tpdos, self._every)):
            if tick_index < due[k]:             # TPDO2, TPDO3: not in this TPDO1's tick
                continue
            if pdo.trans_type > SYNC_TYPE_MAX:
                self._encode(pdo, p)
                pdo.transmit()
                sent += 1
            due[k] = tick_index + every
        self._next = tuple(due)
        return sent

    @property
    def synchronous(self) -> bool:
        """Whether a valid TPDO goes out on SYNC."""
        return any(pdo.enabled and pdo.trans_type <= SYNC_TYPE_MAX for pdo in self.tpdos)

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
        for pdo in self.tpdos:
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

    # --- health (0x2010, TPDO3, EMCY FF30) -----------------------------------------------------

    def set_health(self, h: Health | None) -> None:
        """The unit's health as of now (None: none computed yet): 0x2010 serves it from now
        on, every TPDO it is mapped into carries it, and its alarm is the EMCY warning
        "maintenance due" (FF30 as it begins, an error reset as it ends, with the next fault
        report)."""
        if h != self._health:
            self._health = h
            self._health_values = health_values(h)
        self.emcy.maintenance(h is not None and h.alarm)

    @property
    def health(self) -> Health | None:
        return self._health

    # --- SDO -------------------------------------------------------------------------------

    def _on_read(self, index: int, subindex: int, od: object) -> int | None:
        if index in (STORE, RESTORE) and subindex in (ALL, COMMUNICATION):
            return 1 if self.storage is not None else 0     # 1: on command (CiA 301)
        if index in (0x6501, 0x650A):
            return self._value(index, subindex, None)
        if index == CYCLIC_TIMER:
            return struct.unpack("<H", self.node.get_data(0x1800, 5))[0]
        if index == HEALTH:
            return self._value(index, subindex, None)
        if index not in LIVE_OBJECTS or subindex != (1 if index in CHANNEL_ARRAYS else 0):
            return None
        return self._value(index, subindex, self.live())

    def _value(self, index: int, subindex: int, p: Published | None) -> int | float | None:
        """The value of an object that follows the estimate or the health (None: a stored
        object)."""
        if index == 0x6501:                     # measuring step, as 0x6005 sub 1
            return struct.unpack("<I", self.node.get_data(0x6005, 1))[0]
        if index == 0x650A:                     # module identification: offset, min, max
            return {1: 0, 2: 0, 3: self.stroke_steps}.get(subindex)
        if index == HEALTH:                     # the unit's health (sub 0: the EDS's)
            return self._health_values[subindex] if 0 < subindex <= HEALTH_SUBS else None
        if p is None or index not in LIVE_OBJECTS:
            return None
        if index == 0x6020:
            return clamp(round(p.position_mm / self.step_mm), INT32)
        if index == 0x6030:
            return clamp(round(p.speed_mm_s / SPEED_STEP_MM_S), INT16)
        if index == 0x2001:
            return clamp(round(p.uncertainty_mm / UNCERTAINTY_STEP_MM),
                         (0, UNCERTAINTY_MAX_COUNTS))
        if index in (0x2000, 0x2002):
            return p.flags & 0xFF
        if index == 0x2003:
            return p.input_frames & 0xFFFF
        if index == 0x2004:
            return p.rejected_frames & 0xFF
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
        elif index == CONSUMER_HEARTBEAT and subindex == 1:
            value = value_of(data)
            node_id, ms = value >> 16, value & 0xFFFF
            expected = self.controller_node_id
            if (value != 0) if expected is None else (node_id != expected or ms == 0):
                log.warning("%s: consumer heartbeat 0x%08X refused: %s", self.actuator, value,
                            "no controller heartbeat is consumed" if expected is None else
                            f"node {expected}, 1..65535 ms only")
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            self._consume(value)
            log.info("%s: controller heartbeat consumer time set to %d ms over SDO",
                     self.actuator, ms)
        elif index == 0x1005:
            # consumed only: the pre-defined 11-bit ID, no SYNC produced (bit 30), bit 31
            # is don't care (CiA 301)
            if value_of(data) & ~PDO_INVALID != SYNC_COB_ID:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
        elif index in TPDO_COMS and subindex == 5 or index == CYCLIC_TIMER:
            ms = struct.unpack("<H", bytes(data))[0]
            k = 0 if index == CYCLIC_TIMER else TPDO_COMS.index(index)
            lo, hi = self.event_timer_bounds_ms
            if k == HEALTH_TPDO:            # a slow TPDO: any timer the object holds
                hi = HEALTH_TIMER_MAX_MS
            if ms < lo or ms > hi:           # 0: this node only sends on a timer
                log.warning("%s: TPDO%d event timer %d ms refused: outside %g..%g ms",
                            self.actuator, k + 1, ms, lo, hi)
                raise SdoAbortedError(ABORT_VALUE_TOO_LOW if ms < lo else ABORT_VALUE_TOO_HIGH)
            if index == CYCLIC_TIMER:       # CiA 406's name for TPDO1's event timer
                self.node.data_store.setdefault(0x1800, {})[5] = bytes(data)
            self.timers_ms[k] = float(ms)
            log.info("%s: TPDO%d event timer set to %d ms over SDO", self.actuator, k + 1, ms)
            if self.on_timer_change is not None:
                self.on_timer_change()

    def _consume(self, value: int) -> None:
        """0x1016 sub 1 in effect: the consumer's time from its low 16 bits (ms)."""
        if self.heartbeat is not None and value & 0xFFFF:
            self.heartbeat.consumer_time_s = (value & 0xFFFF) / 1000.0

    # --- store and restore parameters (0x1010, 0x1011) ---------------------------------------

    def attach_storage(self, storage: ParameterStore) -> None:
        """Before boot: the parameters stored in ``storage`` replayed through the write path
        (validated as a master's writes are), then kept as the values NMT resets return to.
        A stored set the node refuses is ignored whole: the defaults apply."""
        self.storage = storage
        stored = storage.load()
        if not stored:
            return
        quiet = _Warnings()
        for logger in (log, pdo_log):
            logger.addFilter(quiet)
        try:
            self._replay(stored)
        except (SdoAbortedError, KeyError, struct.error, ValueError) as exc:
            self._stored = {}
            self.restore_defaults(communication_only=False)
            log.warning("%s: stored parameters in %s ignored (%s); defaults apply",
                        self.actuator, storage.path,
                        f"abort 0x{exc.code:08X}" if isinstance(exc, SdoAbortedError) else exc)
            return
        finally:
            for logger in (log, pdo_log):
                logger.removeFilter(quiet)
        log.info("%s: %d stored parameters applied from %s", self.actuator, len(stored),
                 storage.path)

    def _replay(self, stored: dict[Key, int]) -> None:
        """Stored values written in the order CiA 301 asks of a master: each TPDO disabled,
        its mapping cleared, entries, count, then everything else, the COB-IDs last."""
        od, set_data = self.node.object_dictionary, self.node.set_data
        encoded = {}
        for (index, sub), value in stored.items():
            obj = od[index]
            var = obj if isinstance(obj, canopen.objectdictionary.ODVariable) else obj[sub]
            if not var.writable or not in_scope(index, ALL):
                raise ValueError(f"0x{index:04X} sub {sub} is not a stored parameter")
            encoded[(index, sub)] = var.encode_raw(value)
        for com, mapping in zip(TPDO_COMS, TPDO_MAPS):
            cob_id = stored.get((com, 1), raw(self.node, com, 1))
            set_data(com, 1, struct.pack("<I", cob_id | PDO_INVALID), check_writable=True)
            entries = [k for k in encoded if k[0] == mapping and k[1] > 0]
            if (mapping, 0) in encoded or entries:
                set_data(mapping, 0, b"\x00", check_writable=True)
                for key in sorted(entries):
                    set_data(*key, encoded[key], check_writable=True)
                count = encoded.get((mapping, 0), struct.pack("<B", raw(self.node, mapping, 0)))
                set_data(mapping, 0, count, check_writable=True)
        last = [(com, 1) for com in TPDO_COMS]
        for key in sorted(encoded):
            if key[0] not in TPDO_MAPS and key not in last:
                set_data(*key, encoded[key], check_writable=True)
        for key in last:
            if key in encoded:
                set_data(*key, encoded[key], check_writable=True)
        self._stored = encoded

    def _on_write_storage(self, index: int, subindex: int, od: object, data: bytes) -> None:
        """0x1010 "save" stores the parameters of sub 1 (all) or 2 (communication) now;
        0x1011 "load" removes them from the store: the defaults apply from the next start or
        NMT reset. A wrong signature, another sub-index or no store: abort 0800 0020."""
        if index not in (STORE, RESTORE):
            return
        signature = SAVE if index == STORE else LOAD
        if self.storage is None or subindex not in (ALL, COMMUNICATION) or \
                value_of(data) != signature:
            raise SdoAbortedError(ABORT_NOT_STORED)
        kept = {key: data for key, data in self._stored.items()
                if not in_scope(key[0], subindex)}
        if index == STORE:
            kept.update({(var.index, var.subindex): bytes(self.node.get_data(
                var.index, var.subindex)) for var in parameters(self.node.object_dictionary,
                                                                subindex)})
        values = {key: self._decode(key, data) for key, data in kept.items()}
        try:
            self.storage.save(values)
        except OSError as exc:
            log.error("%s: cannot store parameters in %s: %s", self.actuator,
                      self.storage.path, exc.strerror or exc)
            raise SdoAbortedError(ABORT_NOT_STORED) from None
        self._stored = kept
        if index == RESTORE:                # the next reset rebuilds the TPDOs from defaults
            self.pdos.written.update(self.tpdos)
        log.info("%s: %s parameters %s (0x%04X over SDO; %s)", self.actuator,
                 "all" if subindex == ALL else "communication",
                 "stored" if index == STORE else "back to their defaults from the next reset "
                 "or start", index, self.storage.path)

    def _decode(self, key: Key, data: bytes) -> int:
        obj = self.node.object_dictionary[key[0]]
        var = obj if isinstance(obj, canopen.objectdictionary.ODVariable) else obj[key[1]]
        return int(var.decode_raw(data))

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
