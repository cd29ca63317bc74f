"""The emulated sensor's EMCY producer (0x1014, 0x80 + node), error register 0x1001 and
pre-defined error field 0x1003.

Each fault flag of ``Published.flags`` sends its emergency when it appears and an error reset
(code 0000, remaining error register) when it clears, one per inhibit time 0x1015 at most; a
fault that appears enters the error field (newest first). An EMCY's manufacturer bytes: the
flag set or cleared (0: none), then the fault flags active after it. A fault that came and went
while the inhibit time held its EMCY back is not announced, but the register the master was
last told may have counted it: an error reset with no flag then brings it up to date.

The node's own life guarding event (:mod:`.guarding`) is no flag of the estimate: it sends
EMCY 8130 with no flag concerned and sets register bits 0 and 4, and its end an error reset.
So is the unit's health alarm (:meth:`.SensorNode.set_health`: the expected position error
passes the tolerance within the horizon): a warning "maintenance due", EMCY FF30 with no flag
concerned, register bits 0 (generic) and 7 (manufacturer) while it lasts, an error reset when
it ends. Both enter the error field as they begin; the alarm, which outlives NMT resets and
boots, enters it again after a reset clears the field and is announced again after a boot.
"""

from __future__ import annotations

import logging
import struct
import time

import canopen
from canopen.sdo import SdoAbortedError

from ddh_vsensor.canbus.layout import EMCY_CODES, MAINTENANCE_EMCY
from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.device.objects import (ABORT_NO_DATA, ABORT_VALUE_RANGE, PDO_INVALID,
                                        Published, value_of)

log = logging.getLogger(__name__)

ERROR_FIELD_SIZE = 8                # sub-indices of the pre-defined error field 0x1003
# Fault flag -> error register 0x1001 bits. Register bit 0 (generic) is set with any fault;
# bit 4 communication (inputs), bit 7 manufacturer-specific.
_REGISTER_BITS = {
    Flags.STALE_INPUT: 0x11,                    # communication: input frames missing
    Flags.NOT_REFERENCED: 0x81,                 # device specific: not referenced
    Flags.TABLE_CLAMPED: 0x81,                  # device specific: off the tables
    Flags.PRESET_UNCONFIRMED: 0x81,             # device specific: preset unconfirmed
    Flags.CONTROLLER_NOT_OPERATIONAL: 0x11,     # the motor controller's heartbeat
}
# Fault flag -> (EMCY error code, register bits); the codes are the frame layout's. Plain int
# keys: this is checked every tick.
EMCY_FAULTS: dict[int, tuple[int, int]] = {
    int(flag): (EMCY_CODES[flag][0], bits) for flag, bits in _REGISTER_BITS.items()}
FAULT_FLAGS = sum(EMCY_FAULTS)
LIFE_GUARD_CODE = 0x8130            # CiA 301: life guard error or heartbeat error
LIFE_GUARD_REGISTER = 0x11          # generic and communication
MAINTENANCE_CODE = MAINTENANCE_EMCY[0]     # the health alarm: maintenance due (FF30)
MAINTENANCE_REGISTER = 0x81         # generic and manufacturer specific


def error_register(flags: int) -> int:
    """CiA 301 error register 0x1001 for these fault flags."""
    register = 0
    for bit, (_, bits) in EMCY_FAULTS.items():
        if flags & bit:
            register |= bits
    return register


class EmcyProducer:
    """The EMCY objects of one node: ``report`` every tick, ``on_read``/``on_write`` as its
    object dictionary callbacks."""

    def __init__(self, node: canopen.LocalNode, network: canopen.Network, name: str,
                 cob_id: int) -> None:
        self.node, self.network, self.name, self.cob_id = node, network, name, cob_id
        self.reported = 0                   # fault flags the master has been told of
        self.told_register = 0              # the error register of the last EMCY sent
        self.active = 0                     # fault flags in the error field already
        self.next_emcy_s = 0.0              # monotonic time the inhibit time ends
        self.errors: list[int] = []         # 0x1003: newest first
        self.life_guard = False             # a life guarding event is on
        self.told_life_guard = False        # ... as the master was last told
        self.maintenance_due = False        # the health alarm is on
        self.told_maintenance = False       # ... as the master was last told

    def booted(self) -> None:
        """Active faults and a maintenance due are reported again after every boot."""
        self.reported = self.told_register = 0
        self.life_guard = self.told_life_guard = False
        self.told_maintenance = False

    def reset(self) -> None:
        """Error field cleared; active faults enter it again (a maintenance due at once)."""
        self.errors.clear()
        self.active = 0
        if self.maintenance_due:
            self._enter(MAINTENANCE_CODE)

    def _enter(self, code: int) -> None:
        """A new entry of the error field 0x1003 (newest first)."""
        self.errors.insert(0, code)
        del self.errors[ERROR_FIELD_SIZE:]

    def life_guarding(self, on: bool) -> None:
        """The node's life guarding event is on (or not): it enters the error field as it
        begins; its EMCY (or error reset) goes out with the next report."""
        if on and not self.life_guard:
            self._enter(LIFE_GUARD_CODE)
        self.life_guard = on

    def maintenance(self, due: bool) -> None:
        """The unit's health alarm is on (or not): "maintenance due" enters the error field
        as it begins; its EMCY FF30 (or error reset) goes out with the next report."""
        if due and not self.maintenance_due:
            self._enter(MAINTENANCE_CODE)
        self.maintenance_due = due

    def register(self, flags: int) -> int:
        """The error register 0x1001: the fault flags' bits, the life guarding event's and
        the maintenance due's."""
        return error_register(flags) | (LIFE_GUARD_REGISTER if self.life_guard else 0) | \
            (MAINTENANCE_REGISTER if self.maintenance_due else 0)

    def on_read(self, index: int, subindex: int, od: object) -> int | None:
        if index != 0x1003:
            return None
        if subindex == 0:
            return len(self.errors)
        if subindex > len(self.errors):
            raise SdoAbortedError(ABORT_NO_DATA)
        return self.errors[subindex - 1]

    def on_write(self, index: int, subindex: int, od: object, data: bytes) -> None:
        """The inhibit time 0x1015 (takes effect at once), the EMCY COB-ID 0x1014 (only
        the pre-defined one, valid or not), clearing the error field 0x1003 (only 0)."""
        if index == 0x1015:
            self.next_emcy_s = 0.0
        elif index == 0x1014:
            if value_of(data) & ~PDO_INVALID != self.cob_id:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
        elif index == 0x1003 and value_of(data) != 0:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        elif index == 0x1003:
            self.errors.clear()

    def report(self, p: Published, now_s: float | None = None) -> int:
        """Called every tick: a fault flag that appeared enters the error field 0x1003; the
        master gets an EMCY for each fault, life guarding event or maintenance due that began
        and an error reset for each that ended since it was last told (not while STOPPED or
        with the EMCY COB-ID invalid: then when that ends), at most one EMCY per inhibit time
        0x1015 (a flapping flag cannot flood the bus). Returns the number of EMCY frames
        sent."""
        faults = p.flags & FAULT_FLAGS
        if faults != self.active:
            for bit, (code, _) in EMCY_FAULTS.items():
                if faults & bit and not self.active & bit:
                    self._enter(code | bit << 16)
            self.active = faults
        guard_changed = self.life_guard != self.told_life_guard
        maintenance_changed = self.maintenance_due != self.told_maintenance
        register = self.register(faults)
        told = faults == self.reported and register == self.told_register and \
            not guard_changed and not maintenance_changed
        if told or self.node.nmt.state in ("STOPPED", "INITIALISING"):
            return 0
        cob_id = value_of(self.node.get_data(0x1014, 0))
        now_s = time.monotonic() if now_s is None else now_s
        if cob_id & PDO_INVALID or now_s < self.next_emcy_s:
            return 0
        inhibit_s = value_of(self.node.get_data(0x1015, 0)) * 1e-4     # 100 us units
        # (flag concerned, code, event told: "guard", "maintenance" or "" for a flag)
        changes = [(bit, code if faults & bit else 0x0000, "")
                   for bit, (code, _) in EMCY_FAULTS.items() if (faults ^ self.reported) & bit]
        if maintenance_changed:
            changes.insert(0, (0, MAINTENANCE_CODE if self.maintenance_due else 0x0000,
                               "maintenance"))
        if guard_changed:
            changes.insert(0, (0, LIFE_GUARD_CODE if self.life_guard else 0x0000, "guard"))
        sent = 0
        for bit, code, event in changes or [(0, 0x0000, "register")]:     # register only
            self.network.send_message(cob_id & 0x7FF, struct.pack(
                "<HBBB3x", code, register, bit, faults))
            log.info("%s: EMCY %04X (%s)", self.name, code,
                     f"flag 0x{bit:02X} {'set' if faults & bit else 'cleared'}" if bit else
                     {"guard": "life guarding", "maintenance": "maintenance due" if code
                      else "maintenance due ended"}.get(event, "error register"))
            if bit:
                self.reported ^= bit
            elif event == "guard":
                self.told_life_guard = self.life_guard
            elif event == "maintenance":
                self.told_maintenance = self.maintenance_due
            self.told_register = register
            sent += 1
            if inhibit_s > 0.0:
                self.next_emcy_s = now_s + inhibit_s
                break
        return sent
