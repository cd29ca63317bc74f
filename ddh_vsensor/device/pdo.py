"""The emulated sensor's TPDO configuration as a master may write it (CiA 301): disable and
enable a TPDO (COB-ID bit 31), remap it (disable, sub 0 = 0, entries, sub 0 = n, enable) with
any mappable object, set the transmission type: 254/255 on the event timer, 1..240 every n-th
SYNC, 0 at a SYNC after its data changed (:meth:`.SensorNode.on_sync`). Everything else is
refused with its abort code: the COB-IDs stay the pre-defined ones the service routes and
the DBC describes (no RTR, bit 30 set), no RTR-only or reserved types (241..253), inhibit
time 0. The event timers (sub 5) are the node's. All three TPDOs (position, diagnostics,
health: :data:`TPDO_COMS`) are configured alike.

A TPDO's data is packed every tick: canopen encodes each mapped variable through its object
dictionary (tens of microseconds per frame), so each mapping is compiled once into
:class:`Packer` (one integer per frame, one shift per entry) and compiled again whenever a
master changes it; a mapping it cannot pack the same way (bit fields, non-integer objects)
stays with canopen's encoding."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import canopen
from canopen.sdo import SdoAbortedError

from ddh_vsensor.device.objects import (ABORT_MAP_LENGTH, ABORT_NOT_MAPPABLE,
                                        ABORT_UNSUPPORTED_ACCESS, ABORT_VALUE_RANGE,
                                        PDO_INVALID, PDO_NO_RTR, raw, value_of)

log = logging.getLogger(__name__)

PDO_MAX_BITS = 64
TPDO_COMS = (0x1800, 0x1801, 0x1802)            # TPDO1..3 communication parameters
TPDO_MAPS = tuple(com + 0x200 for com in TPDO_COMS)     # ... and mapping parameters
SYNC_TYPE_MAX = 240             # transmission types 0..240 are synchronous (CiA 301)
DUMMY_INDEX_END = 0x20          # indices below are the data type dummies: mapped, never written

# A mapped object's value for what a node publishes (None: not known here, canopen's way).
Getter = Callable[[Any], "int | None"]


class Packer:
    """The data of one TPDO mapping from a published record, equal to canopen's encoding of
    every mapped variable: entries whole bytes at their offsets, integer objects, dummies
    left 0. ``pack(p)`` returns None when a getter does (the caller then encodes the
    canopen way)."""

    def __init__(self, fields: list[tuple[Getter, int, int]], length_bytes: int) -> None:
        self.fields, self.length_bytes = fields, length_bytes

    @classmethod
    def compile(cls, pdo: canopen.pdo.PdoMap,
                getter: Callable[[int, int, int], Getter]) -> Packer | None:
        """``getter(index, subindex, bytes)`` gives each mapped object's value getter; None
        when an entry is a bit field or not an integer object."""
        fields = []
        for var in pdo.map:
            bits = var.length
            if var.offset % 8 or bits % 8 or bits != len(var.od) or \
                    var.od.data_type not in canopen.objectdictionary.INTEGER_TYPES:
                return None
            if var.index >= DUMMY_INDEX_END:
                fields.append((getter(var.index, var.subindex, bits // 8), var.offset,
                               (1 << bits) - 1))
        return cls(fields, len(pdo.data))

    def pack(self, p: object) -> bytes | None:
        value = 0
        for get, shift, mask in self.fields:
            v = get(p)
            if v is None:
                return None
            value |= (v & mask) << shift
        return value.to_bytes(self.length_bytes, "little")


class PdoConfig:
    """The TPDOs of one node (``tpdos``: TPDO1..3) and the writes to their communication
    (0x1800.. sub 1..3) and mapping (0x1A00..) parameters; ``on_write`` is an object
    dictionary write callback."""

    def __init__(self, node: canopen.LocalNode, name: str) -> None:
        self.node, self.name = node, name
        self.tpdos: tuple[canopen.pdo.PdoMap, ...] = tuple(
            node.tpdo[n] for n in range(1, len(TPDO_COMS) + 1))
        self.tpdo1, self.tpdo2, self.tpdo3 = self.tpdos
        # communication or mapping parameter index -> its TPDO
        self.by_index = {index: pdo for pdo, com, mapping in zip(self.tpdos, TPDO_COMS, TPDO_MAPS)
                         for index in (com, mapping)}
        self.predefined_cob_ids = {pdo: pdo.cob_id for pdo in self.tpdos}
        self.written: set[canopen.pdo.PdoMap] = set()   # configured over SDO since boot
        # compiled mappings (None: canopen encodes it); dropped whenever a mapping changes
        self.packers: dict[canopen.pdo.PdoMap, Packer | None] = {}
        # synchronous TPDOs: SYNCs counted since the last sent (types 1..240), the data
        # last sent at a SYNC (type 0)
        self.syncs_counted: dict[canopen.pdo.PdoMap, int] = {}
        self.sync_sent: dict[canopen.pdo.PdoMap, bytes] = {}

    def restore(self) -> None:
        """After the object dictionary's defaults came back: every TPDO a master changed
        rebuilt from them."""
        for pdo in self.written:
            self.load(pdo)
        self.written.clear()

    def load(self, pdo: canopen.pdo.PdoMap) -> None:
        """Validity and mapping of a TPDO from the object dictionary's current values."""
        com, mapping = pdo.com_record.od.index, pdo.map_array.od.index
        pdo.enabled = not raw(self.node, com, 1) & PDO_INVALID
        pdo.trans_type = raw(self.node, com, 2)
        self.packers.pop(pdo, None)
        self.syncs_counted.pop(pdo, None)
        self.sync_sent.pop(pdo, None)
        pdo.clear()
        for sub in range(1, raw(self.node, mapping, 0) + 1):
            entry = raw(self.node, mapping, sub)
            if entry & 0xFF:
                pdo.add_variable(entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF)

    def mapped_bits(self, entry: int) -> int:
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

    def on_write(self, index: int, subindex: int, od: object, data: bytes) -> None:
        pdo = self.by_index.get(index)
        if pdo is None:
            return
        self.written.add(pdo)
        if index in TPDO_COMS:
            value = value_of(data)
            if subindex == 1:
                self.write_cob_id(pdo, value)
            elif subindex == 2:
                if not (value <= SYNC_TYPE_MAX or value in (254, 255)):
                    raise SdoAbortedError(ABORT_VALUE_RANGE)    # RTR-only or reserved
                pdo.trans_type = value
                self.syncs_counted.pop(pdo, None)
            elif subindex == 3 and value != 0:  # no inhibit time: the event timer paces
                raise SdoAbortedError(ABORT_VALUE_RANGE)
        else:
            value = value_of(data)
            if pdo.enabled or (subindex > 0 and raw(self.node, index, 0) != 0):
                raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)   # CiA 301 procedure
            if subindex > 0:
                self.mapped_bits(value)
                return
            entries = len(self.node.object_dictionary[index]) - 1
            if value > entries:
                raise SdoAbortedError(ABORT_MAP_LENGTH)
            bits = sum(self.mapped_bits(raw(self.node, index, sub))
                       for sub in range(1, value + 1))
            if bits > PDO_MAX_BITS:
                raise SdoAbortedError(ABORT_MAP_LENGTH)

    def write_cob_id(self, pdo: canopen.pdo.PdoMap, value: int) -> None:
        """Bit 31 makes the PDO invalid/valid; the 11-bit ID stays the pre-defined one, no
        29-bit ID, no RTR (bit 30 set)."""
        if value & ~PDO_INVALID != self.predefined_cob_ids[pdo] | PDO_NO_RTR:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        valid = not value & PDO_INVALID
        mapping = pdo.map_array.od.index
        if valid and raw(self.node, mapping, 0) == 0:
            raise SdoAbortedError(ABORT_VALUE_RANGE)              # nothing mapped
        if valid and not pdo.enabled:
            com = pdo.com_record.od.index
            self.node.data_store.setdefault(com, {})[1] = value.to_bytes(4, "little")
            self.load(pdo)
            log.info("%s: TPDO%d %s over SDO: %s", self.name, com - 0x1800 + 1,
                     "enabled", ", ".join(f"0x{v.index:04X}:{v.subindex}" for v in pdo.map))
        elif not valid and pdo.enabled:
            pdo.enabled = False
            log.info("%s: TPDO%d disabled over SDO", self.name,
                     pdo.com_record.od.index - 0x1800 + 1)
