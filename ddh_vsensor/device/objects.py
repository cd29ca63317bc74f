"""The emulated sensor's object dictionary: CiA 301 abort codes, the objects whose value is
the estimate, their encodings, the record a node publishes from, and the unit's health as its
node publishes it (record 0x2010, TPDO3, EMCY FF30)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import canopen

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
ABORT_NOT_STORED = 0x08000020       # data cannot be transferred or stored (0x1010/0x1011)
ABORT_DEVICE_STATE = 0x08000022     # not in the right state (NMT, or the rod is moving)
COMM_AREA = range(0x1000, 0x2000)   # what NMT reset communication restores
PDO_INVALID, PDO_NO_RTR = 1 << 31, 1 << 30     # COB-ID bits (PDO, EMCY): not valid, no RTR
# CiA 406 0x6503 alarms bit 0 "position error"; 0x6505 warnings bit 5 "reference point not
# reached", manufacturer bits 12 (table clamped) and 13 (at a soft limit).
ALARM_POSITION_ERROR = 0x0001
WARNING_NO_REFERENCE, WARNING_CLAMPED, WARNING_SOFT_LIMIT = 0x0020, 0x1000, 0x2000
SPEED_STEP_MM_S = 0.1               # 0x6030 counts (EDS comment, DBC scale)
UNCERTAINTY_STEP_MM = 0.01          # 0x2001 counts (UNSIGNED32: any stroke)
UNCERTAINTY_MAX_COUNTS = 2 ** 32 - 1
# Objects whose value is the estimate's (read callback, PDO encoding).
LIVE_OBJECTS = frozenset({0x1001, 0x2000, 0x2001, 0x2002, 0x2003, 0x2004, 0x6020, 0x6030,
                          0x6400, 0x6503, 0x6505})
CHANNEL_ARRAYS = frozenset({0x6020, 0x6030, 0x6400})     # CiA 406 per-channel: sub 1
INT32 = (-(2 ** 31), 2 ** 31 - 1)
INT16 = (-(2 ** 15), 2 ** 15 - 1)
# The unit's health, manufacturer record 0x2010 (read only, served from the node's Health):
# sub 1 cause code (UNSIGNED8), 2 status bits, 3 and 4 the expected error at the references
# now and at the horizon (UNSIGNED16, 0.01 mm), 5 the days until the tolerance (UNSIGNED16,
# 0.1 day), 6 days of evidence (UNSIGNED16), 7 the cause's parameter, 8 and 9 its interval
# (REAL32). Sub 1..5 are TPDO3's default mapping (8 bytes).
HEALTH = 0x2010
HEALTH_SUBS = 9
HEALTH_ALARM = 0x01                 # sub 2: the tolerance is passed within the horizon
HEALTH_FEW_DAYS = 0x02              # sub 2: too few days of evidence for a trend
HEALTH_NONE = 0x04                  # sub 2: no health computed yet
HEALTH_ERROR_STEP_MM = 0.01         # sub 3, 4
HEALTH_DAY_STEP = 0.1               # sub 5
HEALTH_UNKNOWN = 0xFFFF             # sub 3, 4 unknown; sub 5 not within the horizon
REAL32_MAX = 3.4028234663852886e38


@dataclass(frozen=True)
class Published:
    """What one sensor node reports: the service's view of one cylinder at one instant."""

    position_mm: float
    speed_mm_s: float
    uncertainty_mm: float
    flags: int
    input_frames: int
    rejected_frames: int


@dataclass(frozen=True)
class Health:
    """One unit's health as its node publishes it (0x2010, TPDO3, EMCY FF30)."""

    # 0 none, else the cause's index in diagnosis.causes.CAUSE_NAMES (the service converts:
    # the device does not import diagnosis)
    cause_code: int
    alarm: bool                     # the expected error passes the tolerance within the horizon
    days_needed: int                # days of evidence still missing to name a cause (0: enough)
    days: int                       # days of evidence looked at
    error_now_mm: float | None      # expected position error at the references now
    error_projected_mm: float | None    # ... at the horizon
    days_to_tolerance: float | None     # None: not within the horizon
    value: float | None             # the cause's parameter
    interval: tuple[float, float] | None


def _steps(value: float | None, step: float) -> int:
    """A non-negative UNSIGNED16 in ``step`` units; 0xFFFF for None (or not finite), values
    beyond saturating at 0xFFFE so they never read as unknown."""
    if value is None or not math.isfinite(value):
        return HEALTH_UNKNOWN
    return clamp(round(value / step), (0, HEALTH_UNKNOWN - 1))


def _real32(value: float | None) -> float:
    """A REAL32's value: NaN for None; beyond the type's range, its infinity."""
    if value is None:
        return math.nan
    value = float(value)
    return math.copysign(math.inf, value) if math.isfinite(value) and \
        abs(value) > REAL32_MAX else value


def health_values(h: Health | None) -> tuple[int | float | None, ...]:
    """0x2010 sub 0..9 as the node serves them (sub 0, the EDS's constant, is None). No
    health yet (None): status bit 2 only, the errors unknown, no days, NaN parameters."""
    if h is None:
        return (None, 0, HEALTH_NONE, HEALTH_UNKNOWN, HEALTH_UNKNOWN, HEALTH_UNKNOWN, 0,
                math.nan, math.nan, math.nan)
    status = (HEALTH_ALARM if h.alarm else 0) | (HEALTH_FEW_DAYS if h.days_needed > 0 else 0)
    low, high = h.interval if h.interval is not None else (None, None)
    return (None, clamp(h.cause_code, (0, 0xFF)), status,
            _steps(h.error_now_mm, HEALTH_ERROR_STEP_MM),
            _steps(h.error_projected_mm, HEALTH_ERROR_STEP_MM),
            _steps(h.days_to_tolerance, HEALTH_DAY_STEP), clamp(h.days, (0, 0xFFFF)),
            _real32(h.value), _real32(low), _real32(high))


def clamp(value: int, bounds: tuple[int, int]) -> int:
    return min(max(value, bounds[0]), bounds[1])


def value_of(data: bytes) -> int:
    """An unsigned little-endian object value."""
    return int.from_bytes(bytes(data), "little")


def raw(node: canopen.LocalNode, index: int, subindex: int) -> int:
    """An object's current value, decoded by its type in the object dictionary."""
    od = node.object_dictionary[index]
    od = od[subindex] if not isinstance(od, canopen.objectdictionary.ODVariable) else od
    return od.decode_raw(node.get_data(index, subindex))
