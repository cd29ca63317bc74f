"""The emulated sensor's object dictionary: CiA 301 abort codes, the objects whose value is
the estimate, their encodings, and the record a node publishes from."""

from __future__ import annotations

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


@dataclass(frozen=True)
class Published:
    """What one sensor node reports: the service's view of one cylinder at one instant."""

    position_mm: float
    speed_mm_s: float
    uncertainty_mm: float
    flags: int
    input_frames: int
    rejected_frames: int


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
