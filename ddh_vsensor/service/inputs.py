"""The frames the service reads: routed by ID, decoded with the project's DBC, checked, counted.

Nothing here raises on bad input. A frame with the wrong length, an implausible value (an
I/O state no rod position gives included) or arriving faster than any controller sends is
*rejected*: counted (per unit for the Sevcon
frames, they go out in the diagnostic frame) and logged at a limited rate. Frames on IDs the
service does not read are counted as unknown (the first ``unknown_ids_max`` distinct IDs one
by one, the rest together: a flood of random IDs costs no memory); frames on the service's own
output IDs mean another node uses the emulated sensors' node IDs and are counted as ID
clashes. Logging and frame rates are held by :mod:`.limits`.
"""

from __future__ import annotations

import bisect
import logging
from collections import Counter
import struct
from dataclasses import dataclass, field
from typing import NamedTuple

import can
import cantools

from ddh_vsensor.canbus.dbc import IO_MODULE, OIL_TEMP, FrameCodec, message_name
from ddh_vsensor.config import Config
from ddh_vsensor.service.limits import RateLimitedLog, RateLimiter

log = logging.getLogger(__name__)

# A Sevcon value beyond this multiple of the motor's limit is a broken frame, not motion.
PLAUSIBLE_LIMIT_FACTOR = 2.0
OIL_TEMP_RANGE_C = (-40.0, 150.0)
# Flood guard per input ID: a rate limiter whose tokens refill at this rate (frames/s), up
# to this many.
# The fastest legitimate input is a 1 ms TPDO (1000 frames/s).
FLOOD_RATE_HZ = 2500.0
FLOOD_BURST = 50
# Hall states by time: the I/O module's last state changes kept, and how far apart the I/O
# and Sevcon frame clocks may be for a lookup by time to mean anything.
IO_CHANGES_KEPT = 32
IO_MODE_MIN_SAMPLES = 100     # Sevcon frames per unit before the I/O module's mode is judged
SAMPLE_STAMP_S = 1e-4         # an I/O change this close before a drive sample: stamped with it
IO_CLOCK_MATCH_S = 1.0


@dataclass
class UnitCounters:
    received: int = 0            # Sevcon frames on the unit's ID (diag InputFrames)
    rejected: int = 0            # of which rejected (diag RejectedFrames)
    reasons: Counter[str] = field(default_factory=Counter)


class SevconSample(NamedTuple):
    t_s: float
    speed_rpm: float
    torque_nm: float


class Inputs:
    """Per-frame checks and the latest oil temperature and Hall input byte."""

    def __init__(self, cfg: Config, codec: FrameCodec, *, log_interval_s: float | None = None,
                 flood_rate_hz: float = FLOOD_RATE_HZ, flood_burst: int = FLOOD_BURST) -> None:
        self.cfg, self.codec = cfg, codec
        self.log = RateLimitedLog(log, cfg.faults.log_interval_s if log_interval_s is None
                                  else log_interval_s)
        self.unknown_ids_max = cfg.faults.unknown_ids_max
        ids = codec.ids
        self.sevcon_ids = {ids[message_name("sevcon", a)]: a for a in cfg.can.units}
        self.oil_id, self.io_id = ids[OIL_TEMP], ids[IO_MODULE]
        self._lengths = {frame_id: codec.messages[name].length for name, frame_id in ids.items()}
        self._limits = {a: (PLAUSIBLE_LIMIT_FACTOR * cfg.unit(a).motor.speed_limit_rpm,
                            PLAUSIBLE_LIMIT_FACTOR * cfg.unit(a).motor.torque_limit_nm)
                        for a in cfg.can.units}
        self._limiters = {i: RateLimiter(flood_rate_hz, flood_burst)
                         for i in (*self.sevcon_ids, self.oil_id, self.io_id)}
        self._last_t: dict[int, float] = {}
        self.clock_steps_back = 0                 # frames (any input ID) older than the last
        # per unit: what its Sevcon frames are checked against and decoded with
        self._sevcon = {a: (ids[message_name("sevcon", a)], self._lengths[ids[message_name(
            "sevcon", a)]], self._limiters[ids[message_name("sevcon", a)]],
            codec.sevcon_decoder(a), *self._limits[a]) for a in cfg.can.units}
        self.units = {a: UnitCounters() for a in cfg.can.units}
        self.counts: Counter[str] = Counter()     # everything else, by kind
        self.unknown_ids: Counter[int] = Counter()
        self.oil_temp_c: float | None = None
        self.oil_rx_s: float | None = None        # monotonic receipt time of the last oil frame
        self.io_t_s: float | None = None          # timestamp of the latest I/O frame
        # the I/O module's state changes (frame time, data), oldest first; the last is now
        self._io_changes_t: list[float] = []
        self._io_changes: list[bytes] = []
        self._io_changes_total = 0                # changes appended ever: a change's number
        self._io_served: dict[str, int] = {}      # per unit, the newest change number given
        self.refs_since_s: float | None = None    # see refs()
        # whether a change of the I/O module's inputs came between two drive samples, not
        # stamped with a sample's own time (see io_sends_on_change)
        self._io_change_between_samples = False
        self._io_change_unjudged_t: float | None = None   # the newest change, until a sample
        self._refs_cache: dict[str, tuple[bytes, dict[str, bool]]] = {}
        # per unit, the bit masks of switch pairs too far apart for one rod's magnet to reach
        # both (more than twice the reference window): such a state is no rod position
        self._apart_masks: list[tuple[str, int]] = []
        for a, unit_can in cfg.can.units.items():
            unit = cfg.unit(a)
            names = [n for n in unit.references_mm if n in unit_can.hall_bits]
            for i, one in enumerate(names):
                for other in names[i + 1:]:
                    if abs(unit.references_mm[one] - unit.references_mm[other]) \
                            > 2.0 * unit.reference_window_mm:
                        self._apart_masks.append((a, (1 << unit_can.hall_bits[one])
                                                  | (1 << unit_can.hall_bits[other])))

    # --- checks shared by all inputs ---------------------------------------------------

    def _shape_ok(self, msg: can.Message, what: str) -> bool:
        if msg.is_remote_frame or msg.is_extended_id or msg.is_fd:
            self.log.warning(f"shape-{msg.arbitration_id}", "%s frame 0x%03X: remote, extended "
                             "or FD frame on an input ID ignored", what, msg.arbitration_id)
            return False
        expected = self._lengths[msg.arbitration_id]
        if msg.dlc != expected or len(msg.data) != expected:
            self.log.warning(f"dlc-{msg.arbitration_id}", "%s frame 0x%03X with %d data bytes "
                             "rejected (the DBC says %d)", what, msg.arbitration_id,
                             len(msg.data), expected)
            return False
        return True

    def _not_flooded(self, msg: can.Message, what: str) -> bool:
        # Frame timestamps, not arrival times: a backlog of frames received in time but
        # handled late is no flood.
        if self._limiters[msg.arbitration_id].take(msg.timestamp):
            return True
        self._flooded(msg, what)
        return False

    def _flooded(self, msg: can.Message, what: str) -> None:
        self.log.warning(f"flood-{msg.arbitration_id}", "%s frames on 0x%03X arrive faster "
                         "than %.0f/s: the excess is rejected", what, msg.arbitration_id,
                         self._limiters[msg.arbitration_id].rate_hz)

    def _check_time(self, msg: can.Message, what: str) -> None:
        last = self._last_t.get(msg.arbitration_id)
        if last is not None and msg.timestamp < last:
            self.clock_steps_back += 1
            self.log.warning(f"time-{msg.arbitration_id}", "%s frame time went back by %.6f s "
                             "(clock step?)", what, last - msg.timestamp)
        self._last_t[msg.arbitration_id] = msg.timestamp

    # --- per input -------------------------------------------------------------------------

    def sevcon(self, actuator: str, msg: can.Message, now_s: float) -> SevconSample | None:
        """The sample of a Sevcon TPDO, or None when rejected (counted). The checks of
        ``_shape_ok``, ``_not_flooded`` and ``_check_time`` inline: this runs for every
        frame, the log text is built only for a rejected one."""
        counters = self.units[actuator]
        counters.received += 1
        frame_id, length, limiter, decode, speed_max, torque_max = self._sevcon[actuator]
        data, t = msg.data, msg.timestamp
        reason = None
        if msg.is_remote_frame or msg.is_extended_id or msg.is_fd or msg.dlc != length \
                or len(data) != length:
            self._shape_ok(msg, f"{actuator} Sevcon")
            reason = "length"
        elif not limiter.take(t):
            self._flooded(msg, f"{actuator} Sevcon")
            reason = "flood"
        else:
            try:
                torque, speed = decode(data)
            except (cantools.database.DecodeError, ValueError, struct.error) as exc:
                self.log.warning(f"decode-{frame_id}", "%s Sevcon frame undecodable: %s",
                                 actuator, exc)
                reason = "decode"
            else:
                if -speed_max <= speed <= speed_max and -torque_max <= torque <= torque_max:
                    last = self._last_t.get(frame_id)
                    if last is not None and t < last:
                        self._check_time(msg, f"{actuator} Sevcon")
                    self._last_t[frame_id] = t
                    change_t = self._io_change_unjudged_t
                    if change_t is not None and t >= change_t - SAMPLE_STAMP_S:
                        self._io_change_unjudged_t = None
                        if t - change_t > SAMPLE_STAMP_S:
                            self._io_change_between_samples = True
                    return SevconSample(t, float(speed), float(torque))
                self.log.warning(f"range-{frame_id}", "%s Sevcon frame out of range "
                                 "rejected: %.0f rpm, %.2f N*m (plausible: |speed| <= "
                                 "%.0f, |torque| <= %.0f)", actuator, speed, torque, speed_max,
                                 torque_max)
                reason = "range"
        counters.rejected += 1
        counters.reasons[reason] += 1
        return None

    def oil(self, msg: can.Message, now_s: float) -> bool:
        if not (self._shape_ok(msg, "oil temperature")
                and self._not_flooded(msg, "oil temperature")):
            self.counts["oil_rejected"] += 1
            return False
        value = float(self.codec.decode(msg)[1]["OilTemp"])  # type: ignore[index]
        lo, hi = OIL_TEMP_RANGE_C
        if not lo <= value <= hi:
            self.log.warning("oil-range", "oil temperature %.1f degC outside %g..%g rejected",
                             value, lo, hi)
            self.counts["oil_rejected"] += 1
            return False
        self._check_time(msg, "oil temperature")
        self.oil_temp_c, self.oil_rx_s = value, now_s
        self.counts["oil"] += 1
        return True

    def io(self, msg: can.Message, now_s: float) -> bool:
        if not (self._shape_ok(msg, "I/O module") and self._not_flooded(msg, "I/O module")
                and self._one_position_each(msg)):
            self.counts["io_rejected"] += 1
            return False
        self._check_time(msg, "I/O module")
        data, t_s = bytes(msg.data), msg.timestamp
        if self.io_t_s is not None and t_s < self.io_t_s:
            self._io_changes_t.clear()            # its clock went back: earlier times are void
            self._io_changes.clear()
        if not self._io_changes or data != self._io_changes[-1]:
            if self._io_changes and not self._io_change_between_samples:
                self._io_change_unjudged_t = t_s
            self._io_changes_t.append(t_s)
            self._io_changes.append(data)
            self._io_changes_total += 1
            if len(self._io_changes) > IO_CHANGES_KEPT:
                del self._io_changes_t[0], self._io_changes[0]
        self.io_t_s = t_s
        self.counts["io"] += 1
        return True

    def _one_position_each(self, msg: can.Message) -> bool:
        """The I/O module's inputs name at most one rod position per unit: two of a unit's
        switches active that are further apart than its magnet reaches is no state of the
        machine (a foreign frame on the module's ID), and its edges would be references."""
        inputs = int.from_bytes(bytes(msg.data), "little")
        for actuator, mask in self._apart_masks:
            if inputs & mask == mask:
                self.log.warning("io-implausible", "I/O module frame 0x%02X... rejected: %s's "
                                 "switches active together that no rod position reaches "
                                 "at once", inputs & 0xFF, actuator)
                return False
        return True

    @property
    def io_sends_on_change(self) -> bool:
        """Whether the I/O module's frames time the switches' changes finer than the samples
        (:func:`.canbus.log.io_sends_on_change`): it has sent fewer than half as many frames
        as each unit's drive, over at least :data:`IO_MODE_MIN_SAMPLES` of theirs, and a
        change of its inputs has come between two samples (changes stamped with the samples'
        own times, as a replayed log may have them, say nothing finer)."""
        if not self._io_change_between_samples:        # per Sevcon frame: the cheap test first
            return False
        received = min((u.received for u in self.units.values()), default=0)
        return received >= IO_MODE_MIN_SAMPLES and 2 * self.counts["io"] < received

    def refs(self, actuator: str, t_s: float | None = None) -> dict[str, bool] | None:
        """Hall switch states of a unit (None before the first I/O frame): at frame time
        ``t_s`` when given, else the latest. The I/O module may sit on another bus than the
        unit's controller, and two buses are read one after the other: an I/O frame can be
        handled before Sevcon frames older than it, and a Hall edge applied to them would be
        taken early by that much travel. So a Sevcon sample gets the state of the last I/O
        frame not younger than itself (frame clocks alike, within ``IO_CLOCK_MATCH_S``), but
        never a change older than one the unit was given at a frame time: its samples come in
        time order, so an older sample is a frame clock that stepped back, which the I/O
        module's frames, sent on change of state, may not show for up to their event timer;
        the changes before the step, looked up at the new clock's times, would be edges that
        never happened. :attr:`refs_since_s` is then the frame time since which the returned
        states hold."""
        if not self._io_changes:
            return None
        kept = len(self._io_changes)
        k = kept - 1
        if t_s is not None:
            if t_s < self.io_t_s and self.io_t_s - t_s < IO_CLOCK_MATCH_S:
                k = max(bisect.bisect_right(self._io_changes_t, t_s) - 1, 0)
            first = self._io_changes_total - kept           # the number of change 0
            k = max(k, self._io_served.get(actuator, first) - first)
            self._io_served[actuator] = first + k
        data, self.refs_since_s = self._io_changes[k], self._io_changes_t[k]
        cached = self._refs_cache.get(actuator)
        if cached is None or cached[0] != data:
            cached = data, {name: bool(state)
                            for name, state in self.codec.hall_states(actuator, data).items()}
            self._refs_cache[actuator] = cached
        return cached[1]

    def unknown(self, msg: can.Message) -> None:
        self.counts["unknown"] += 1
        if msg.arbitration_id in self.unknown_ids or \
                len(self.unknown_ids) < self.unknown_ids_max:
            self.unknown_ids[msg.arbitration_id] += 1
        else:
            self.counts["unknown_other_ids"] += 1
        self.log.warning("unknown", "frames on IDs the service does not read are ignored "
                         "(%d so far, latest 0x%03X)", self.counts["unknown"], msg.arbitration_id)

    def clash(self, msg: can.Message) -> None:
        if msg.is_remote_frame:             # a request for our frame, not another sender
            self.counts["remote_requests"] += 1
            self.log.warning(f"rtr-{msg.arbitration_id}", "remote request on 0x%03X not "
                             "served: the emulated sensors' TPDOs go out on their timer or "
                             "on SYNC, never on request (node guarding on 0x700 + node is "
                             "answered)",
                             msg.arbitration_id)
            return
        self.counts["id_clash"] += 1
        self.log.warning(f"clash-{msg.arbitration_id}", "another node transmits on 0x%03X, an "
                         "ID of an emulated sensor: is the old sensor still connected, or a "
                         "second ddh-vsensor running?", msg.arbitration_id)

    @property
    def rejected_total(self) -> int:
        return sum(u.rejected for u in self.units.values()) + self.counts["oil_rejected"] \
            + self.counts["io_rejected"]
