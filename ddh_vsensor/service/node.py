"""One emulated CiA 406 linear position sensor per cylinder: a canopen ``LocalNode`` from the
EDS shipped in the package, behaving as CiA 301 / CiA 406 describe for a generic master.

- TPDO1 (0x180 + node): position 0x6020 sub 1 (INT32, measuring step 0x6005 sub 1, from
  ``can.position_step_mm``), speed 0x6030 sub 1 (INT16, 0.1 mm/s), status 0x2000; sent every
  event timer (0x1800 sub 5, from ``can.event_timer_ms``).
- TPDO2 (0x280 + node): diagnostics 0x2001..0x2004 (uncertainty, flags, input frames,
  rejected frames) every 0x1801 sub 5 (EDS default 100 ms), in the same tick as a TPDO1.
- PDO configuration: a master may disable/enable a TPDO (COB-ID bit 31), remap it (CiA 301
  procedure: disable, sub 0 = 0, entries, sub 0 = n, enable) with any mappable object, and
  set the transmission type 254/255; everything else is refused with its abort code (the
  COB-IDs stay the pre-defined ones the service routes and the DBC describes; no RTR, bit 30
  set; no SYNC; inhibit time 0).
- NMT slave: boot-up, then PRE-OPERATIONAL, then OPERATIONAL if ``can.nmt_auto_start``.
  Reset communication restores the communication area (0x1000..0x1FFF) to its defaults,
  reset node everything; the estimate itself is the process value and is kept. PDOs go out
  only while OPERATIONAL; in STOPPED the SDO server does not answer (CiA 301).
- Heartbeat producer 0x1017 (EDS default 1000 ms).
- EMCY producer (0x1014, 0x80 + node): each fault flag of ``Published.flags`` sends its
  emergency when it appears and an error reset (code 0000, remaining error register) when it
  clears, one per inhibit time 0x1015 at most; error register 0x1001 and the pre-defined
  error field 0x1003 follow.
- SDO server: reads return the live values; writing the preset 0x6010 sub 1 (in measuring
  steps) sets the estimate, refused with abort 0609 0030 outside the stroke; event timers and
  the heartbeat time may be written too. A segmented download is bounded by the size of its
  target object (aborted with 0607 0012, never buffered beyond it).

canopen's own timers (``PdoMap.start``, the NMT heartbeat task) run in threads on the bus and
would keep a hung service looking alive; here the service's tick sends everything, so a
heartbeat on the bus means the service loop is running. ``LocalNode`` TPDOs ignore SYNC, and
so does this node (transmission type 254: event timer only).
"""

from __future__ import annotations

import logging
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import can
import canopen
from canopen.sdo import SdoAbortedError

from ..config import Config
from ..estimator.flags import Flags

log = logging.getLogger(__name__)

EDS_PATH = Path(__file__).resolve().parent.parent / "data" / "cia406_position_sensor.eds"

ABORT_VALUE_RANGE = 0x06090030      # value range of parameter exceeded
ABORT_VALUE_TOO_HIGH = 0x06090031
ABORT_VALUE_TOO_LOW = 0x06090032
ABORT_MAX_BELOW_MIN = 0x06090036
ABORT_UNSUPPORTED_ACCESS = 0x06010000
ABORT_READ_ONLY = 0x06010002
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_MAP_LENGTH = 0x06040042
ABORT_LENGTH_TOO_HIGH = 0x06070012
ABORT_COMMAND = 0x05040001          # command specifier not valid or unknown
ABORT_NO_DATA = 0x08000024
TEXT_OBJECT_MAX_BYTES = 256         # download bound of an object without a fixed size
PDO_INVALID, PDO_NO_RTR = 1 << 31, 1 << 30     # COB-ID bits: not valid, no RTR
PDO_MAX_BITS = 64
ERROR_FIELD_SIZE = 8                # sub-indices of the pre-defined error field 0x1003
COMM_AREA = range(0x1000, 0x2000)   # what NMT reset communication restores

# Fault flag -> (EMCY error code, error register 0x1001 bits). Register bit 0 (generic) is
# set with any fault; bit 4 communication (inputs), bit 7 manufacturer-specific. An EMCY's
# manufacturer bytes: the flag set or cleared, then the fault flags active after it.
EMCY_FAULTS: dict[int, tuple[int, int]] = {
    Flags.STALE_INPUT: (0x8100, 0x11),             # communication: input frames missing
    Flags.NOT_REFERENCED: (0xFF02, 0x81),    # device specific: position not referenced
    Flags.TABLE_CLAMPED: (0xFF10, 0x81),           # device specific: operating point off the tables
    Flags.PRESET_UNCONFIRMED: (0xFF20, 0x81),            # device specific: preset not confirmed by a switch
    Flags.CONTROLLER_NOT_OPERATIONAL: (0x8130, 0x11),        # heartbeat error (the motor controller's)
}
FAULT_FLAGS = sum(EMCY_FAULTS)
# CiA 406 0x6503 alarms bit 0 "position error"; 0x6505 warnings bit 5 "reference point not
# reached", manufacturer bits 12 (table clamped) and 13 (at a soft limit).
ALARM_POSITION_ERROR = 0x0001
WARNING_NO_REFERENCE, WARNING_CLAMPED, WARNING_SOFT_LIMIT = 0x0020, 0x1000, 0x2000
SPEED_STEP_MM_S = 0.1               # 0x6030 counts (EDS comment, DBC scale)
UNCERTAINTY_STEP_MM = 0.01          # 0x2001 counts (UNSIGNED24: up to 167 m, any stroke)
UINT24_MAX = 2 ** 24 - 1
# Objects whose value is the estimate's (read callback, PDO encoding).
LIVE_OBJECTS = frozenset({0x1001, 0x2000, 0x2001, 0x2002, 0x2003, 0x2004, 0x6020, 0x6030,
                          0x6400, 0x6503, 0x6505})
CHANNEL_ARRAYS = frozenset({0x6020, 0x6030, 0x6400})     # CiA 406 per-channel: sub 1
INT32 = (-(2 ** 31), 2 ** 31 - 1)
INT16 = (-(2 ** 15), 2 ** 15 - 1)


def _clamp(value: int, bounds: tuple[int, int]) -> int:
    return min(max(value, bounds[0]), bounds[1])


def value_of(data: bytes) -> int:
    """An unsigned little-endian object value."""
    return int.from_bytes(bytes(data), "little")


def error_register(flags: int) -> int:
    """CiA 301 error register 0x1001 for these fault flags."""
    register = 0
    for bit, (_, bits) in EMCY_FAULTS.items():
        if flags & bit:
            register |= bits
    return register


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
        self.predefined_cob_ids = {pdo: pdo.cob_id for pdo in (self.tpdo1, self.tpdo2)}
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
        node.add_read_callback(self._on_read)
        node.add_write_callback(self._on_write)
        node.add_write_callback(self._on_write_comm)
        node.add_write_callback(self._on_write_profile)
        # NMT commands are seen here too (which reset?), SDO requests pass a gate first.
        self._nmt_command: int | None = None
        network.subscribe(0, self._on_nmt_command)
        network.unsubscribe(node.sdo.rx_cobid, node.sdo.on_request)
        network.subscribe(node.sdo.rx_cobid, self._on_sdo_request)
        self._download_limit: int | None = None    # bytes, while a segmented download runs
        self._pdo_written: set[canopen.pdo.PdoMap] = set()   # configured over SDO since boot
        self._reported_faults = 0                  # fault flags the master has been told of
        self._active_faults = 0                    # fault flags in the error field already
        self._next_emcy_s = 0.0                    # monotonic time the inhibit time ends
        self._errors: list[int] = []               # 0x1003: newest first
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
        self._reported_faults = 0
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
        for pdo in self._pdo_written:          # rebuilt only if a master changed it
            self._load_pdo(pdo)
        self._pdo_written.clear()
        self._errors.clear()
        self._active_faults = 0                    # active faults enter the field again
        for index, before in timers.items():  # a changed timer: the path of an SDO write
            data = self.node.get_data(index, 5)
            if data != before:
                od = self.node.object_dictionary[index][5]
                self._on_write(index=index, subindex=5, od=od, data=data)
        self._download_limit = None

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
        """TPDO1's data from ``p``, whatever a master mapped into it."""
        self._encode(self.tpdo1, p)

    def encode_diag(self, p: Published) -> None:
        """TPDO2's data from ``p``, whatever a master mapped into it."""
        self._encode(self.tpdo2, p)

    def _encode(self, pdo: canopen.pdo.PdoMap, p: Published) -> None:
        for var in pdo.map:
            value = self._value(var.index, var.subindex, p)
            if value is not None:
                var.raw = value
            elif var.index >= 0x20:                     # a stored object (dummies stay 0)
                var.set_data(self.node.get_data(var.index, var.subindex))

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
        if index == 0x1003:
            if subindex == 0:
                return len(self._errors)
            if subindex > len(self._errors):
                raise SdoAbortedError(ABORT_NO_DATA)
            return self._errors[subindex - 1]
        if index in (0x6501, 0x650A):
            return self._value(index, subindex, None)
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
            return _clamp(round(p.position_mm / self.step_mm), INT32)
        if index == 0x6030:
            return _clamp(round(p.speed_mm_s / SPEED_STEP_MM_S), INT16)
        if index == 0x2001:
            return _clamp(round(p.uncertainty_mm / UNCERTAINTY_STEP_MM), (0, UINT24_MAX))
        if index in (0x2000, 0x2002):
            return p.flags & 0xFF
        if index in (0x2003, 0x2004):
            return (p.input_frames if index == 0x2003 else p.rejected_frames) & 0xFFFF
        if index == 0x1001:
            return error_register(p.flags)
        if index == 0x6400:
            return self._area_state(p.position_mm)
        if index == 0x6503:
            return ALARM_POSITION_ERROR if p.flags & (Flags.STALE_INPUT | Flags.CONTROLLER_NOT_OPERATIONAL) else 0
        return ((WARNING_NO_REFERENCE if p.flags & (Flags.NOT_REFERENCED | Flags.PRESET_UNCONFIRMED) else 0)
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

    # --- configuration defaults and PDO configuration ---------------------------------------

    def _configure(self, index: int, subindex: int, data: bytes) -> None:
        """A setting from the config: stored now, and restored by NMT resets."""
        self._configured[(index, subindex)] = data
        self.node.data_store.setdefault(index, {})[subindex] = data

    def _raw(self, index: int, subindex: int) -> int:
        od = self.node.object_dictionary[index]
        od = od[subindex] if not isinstance(od, canopen.objectdictionary.ODVariable) else od
        return od.decode_raw(self.node.get_data(index, subindex))

    def _load_pdo(self, pdo: canopen.pdo.PdoMap) -> None:
        """Validity and mapping of a TPDO from the object dictionary's current values."""
        com, mapping = pdo.com_record.od.index, pdo.map_array.od.index
        pdo.enabled = not self._raw(com, 1) & PDO_INVALID
        pdo.trans_type = self._raw(com, 2)
        pdo.clear()
        for sub in range(1, self._raw(mapping, 0) + 1):
            entry = self._raw(mapping, sub)
            if entry & 0xFF:
                pdo.add_variable(entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF)

    def _mapped_object(self, entry: int) -> int:
        """Bit length of a valid mapping entry (0 for an empty one); abort 0604 0041 if the
        object does not exist, cannot be mapped or has another length."""
        index, subindex, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
        if entry == 0:
            return 0
        od = self.node.object_dictionary
        try:
            obj = od[index]
            if not isinstance(obj, canopen.objectdictionary.ODVariable):
                obj = obj[subindex]
            elif subindex != 0:
                raise KeyError(subindex)
        except KeyError:
            raise SdoAbortedError(ABORT_NOT_MAPPABLE) from None
        dummy = index < 0x20
        if not (obj.pdo_mappable or dummy) or bits != len(obj):
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)
        return bits

    def _on_write_comm(self, index: int, subindex: int, od: object, data: bytes) -> None:
        """Communication-area writes: TPDO communication (0x1800/0x1801 sub 1..3; the event
        timer, sub 5, is :meth:`_on_write`'s) and mapping (0x1A00/0x1A01), the EMCY COB-ID
        0x1014, clearing the error field 0x1003."""
        if index in (0x1800, 0x1801, 0x1A00, 0x1A01):
            self._pdo_written.add(self.tpdo1 if index in (0x1800, 0x1A00) else self.tpdo2)
        if index in (0x1800, 0x1801):
            pdo = self.tpdo1 if index == 0x1800 else self.tpdo2
            value = value_of(data)
            if subindex == 1:
                self._write_pdo_cob_id(pdo, value)
            elif subindex == 2:
                if value not in (254, 255):     # no SYNC: event timer only
                    raise SdoAbortedError(ABORT_VALUE_RANGE)
                pdo.trans_type = value
            elif subindex == 3 and value != 0:  # no inhibit time: the event timer paces
                raise SdoAbortedError(ABORT_VALUE_RANGE)
        elif index in (0x1A00, 0x1A01):
            pdo = self.tpdo1 if index == 0x1A00 else self.tpdo2
            value = value_of(data)
            if pdo.enabled or (subindex > 0 and self._raw(index, 0) != 0):
                raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)   # CiA 301 procedure
            if subindex > 0:
                self._mapped_object(value)
                return
            entries = len(self.node.object_dictionary[index]) - 1
            if value > entries:
                raise SdoAbortedError(ABORT_MAP_LENGTH)
            bits = sum(self._mapped_object(self._raw(index, sub)) for sub in range(1, value + 1))
            if bits > PDO_MAX_BITS:
                raise SdoAbortedError(ABORT_MAP_LENGTH)
        elif index == 0x1015:
            self._next_emcy_s = 0.0                               # takes effect at once
        elif index == 0x1014:
            if value_of(data) & ~PDO_INVALID != self.cob_ids["emcy"]:
                raise SdoAbortedError(ABORT_VALUE_RANGE)          # the pre-defined COB-ID
        elif index == 0x1003 and value_of(data) != 0:
            raise SdoAbortedError(ABORT_VALUE_RANGE)              # only 0: clear the field
        elif index == 0x1003:
            self._errors.clear()

    def _write_pdo_cob_id(self, pdo: canopen.pdo.PdoMap, value: int) -> None:
        """Bit 31 makes the PDO invalid/valid; the 11-bit ID stays the pre-defined one, no
        29-bit ID, no RTR (bit 30 set)."""
        if value & ~PDO_INVALID != self.predefined_cob_ids[pdo] | PDO_NO_RTR:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        valid = not value & PDO_INVALID
        mapping = pdo.map_array.od.index
        if valid and self._raw(mapping, 0) == 0:
            raise SdoAbortedError(ABORT_VALUE_RANGE)              # nothing mapped
        if valid and not pdo.enabled:
            com = pdo.com_record.od.index
            self.node.data_store.setdefault(com, {})[1] = value.to_bytes(4, "little")
            self._load_pdo(pdo)
            log.info("%s: TPDO%d %s over SDO: %s", self.actuator, com - 0x1800 + 1,
                     "enabled", ", ".join(f"0x{v.index:04X}:{v.subindex}" for v in pdo.map))
        elif not valid and pdo.enabled:
            pdo.enabled = False
            log.info("%s: TPDO%d disabled over SDO", self.actuator,
                     pdo.com_record.od.index - 0x1800 + 1)

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

    # --- SDO gate ----------------------------------------------------------------------------

    def _on_sdo_request(self, can_id: int, data: bytes, timestamp: float) -> None:
        """CiA 301: no SDO in STOPPED. A segmented download is bounded by its object's size."""
        if self.node.nmt.state in ("STOPPED", "INITIALISING") or len(data) != 8:
            return
        ccs = data[0] & 0xE0
        if ccs == 0x20 and not data[0] & 0x02:         # initiate segmented download
            self._download_limit = None
            index, subindex = struct.unpack_from("<HB", data, 1)
            try:
                obj = self.node._find_object(index, subindex)   # noqa: SLF001
            except SdoAbortedError as exc:
                self._abort(index, subindex, exc.code)
                return
            if not obj.writable:
                self._abort(index, subindex, ABORT_READ_ONLY)
                return
            limit = len(obj) // 8 if obj.data_type in canopen.objectdictionary.NUMBER_TYPES \
                else TEXT_OBJECT_MAX_BYTES
            if data[0] & 0x01 and struct.unpack_from("<I", data, 4)[0] > limit:
                self._abort(index, subindex, ABORT_LENGTH_TOO_HIGH)
                return
            self._download_limit = limit
        elif ccs == 0x00:                               # download segment
            sdo = self.node.sdo
            if self._download_limit is None:
                self._abort(sdo._index or 0, sdo._subindex or 0, ABORT_COMMAND)  # noqa: SLF001
                return
            size = 7 - ((data[0] >> 1) & 0x07)
            if len(sdo._buffer) + size > self._download_limit:               # noqa: SLF001
                self._download_limit, sdo._buffer = None, None                 # noqa: SLF001
                self._abort(sdo._index, sdo._subindex, ABORT_LENGTH_TOO_HIGH)  # noqa: SLF001
                return
            if data[0] & 0x01:                          # last segment
                self._download_limit = None
        else:
            self._download_limit = None
        self.node.sdo.on_request(can_id, data, timestamp)

    def _abort(self, index: int, subindex: int, code: int) -> None:
        self.network.send_message(self.cob_ids["sdo_tx"],
                                  struct.pack("<BHBL", 0x80, index, subindex, code))

    # --- EMCY --------------------------------------------------------------------------------

    def report_faults(self, p: Published, now_s: float | None = None) -> int:
        """Called every tick: a fault flag that appeared enters the error field 0x1003; the
        master gets an EMCY for each fault that appeared and an error reset for each that
        cleared since it was last told (not while STOPPED or with the EMCY COB-ID invalid:
        then when that ends), at most one EMCY per inhibit time 0x1015 (a flapping flag
        cannot flood the bus). Returns the number of EMCY frames sent."""
        faults = p.flags & FAULT_FLAGS
        for bit, (code, _) in EMCY_FAULTS.items():
            if faults & bit and not self._active_faults & bit:
                self._errors.insert(0, code | bit << 16)
                del self._errors[ERROR_FIELD_SIZE:]
        self._active_faults = faults
        if faults == self._reported_faults or self.node.nmt.state in ("STOPPED",
                                                                      "INITIALISING"):
            return 0
        cob_id = value_of(self.node.get_data(0x1014, 0))
        now_s = time.monotonic() if now_s is None else now_s
        if cob_id & PDO_INVALID or now_s < self._next_emcy_s:
            return 0
        inhibit_s = value_of(self.node.get_data(0x1015, 0)) * 1e-4     # 100 us units
        sent = 0
        for bit, (code, _) in EMCY_FAULTS.items():
            if (faults ^ self._reported_faults) & bit:
                appeared = bool(faults & bit)
                self.network.send_message(cob_id & 0x7FF, struct.pack(
                    "<HBBB3x", code if appeared else 0x0000, error_register(faults), bit, faults))
                log.info("%s: EMCY %04X (flag 0x%02X %s)", self.actuator,
                         code if appeared else 0, bit, "set" if appeared else "cleared")
                self._reported_faults ^= bit
                sent += 1
                if inhibit_s > 0.0:
                    self._next_emcy_s = now_s + inhibit_s
                    break
        return sent
