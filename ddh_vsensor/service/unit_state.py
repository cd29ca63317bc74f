"""One cylinder as the service keeps it: its estimator, its emulated node, the bookkeeping of
its inputs, and the rules that turn them into what is published.

Motion is never dropped silently. Sevcon frames are integrated whatever the controller's
heartbeat says (a consumed controller that is not OPERATIONAL sets
Flags.CONTROLLER_NOT_OPERATIONAL). Any interval the estimator did not integrate (frames
missing, held before the first oil temperature, dropped from the backlog; longer than
``estimator.max_gap_s`` by the frames' clock or by their arrivals on this host's monotonic
clock, whichever is longer) widens the uncertainty by the worst travel possible in it,
``Config.max_speed_mm_s`` x its length; when that reaches the stroke the unit is "not
referenced" until the next Hall reference. A unit is stale while no Sevcon frame was
integrated for 3 periods (the slower of the event timer, up to 10 ms, and the measured Sevcon
period), while the newest integrated frame is older than that by its own timestamp (when frame
timestamps are this host's wall clock: frames delivered late; a steady offset of the stamps
is learnt as their clock's, see LATE_LEARN_S), or no oil temperature was ever
received: position held, published speed 0, published uncertainty growing at the worst-case
speed (capped at the stroke), Flags.STALE_INPUT set. The stale flag clears with the first
integrated frame after the gap, because that frame brings the gap's worst-case travel into
the uncertainty: from then on the bound holds again.

A preset (SDO 0x6010) is accepted only as configured (``faults.preset``), near standstill
and within the jump bound, and stays flagged until a reference switch confirms it.

Each switch's travel between its edges is checked against its configured window and
hysteresis (:mod:`ddh_vsensor.estimator.switch_drift`): a change of verdict is logged once,
and nothing published changes with it. Gaps, presets and the estimate clipped at a soft limit
end the pair an edge would start.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import can
from canopen.sdo import SdoAbortedError

from ddh_vsensor.config import Config
from ddh_vsensor.estimator.day_samples import SampleFeed
from ddh_vsensor.estimator.estimator import Estimator, Step
from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.estimator.switch_drift import Change, SwitchDrift
from ddh_vsensor.service.heartbeat import HeartbeatConsumer
from ddh_vsensor.service.inputs import Inputs
from ddh_vsensor.service.limits import RateLimitedLog
from ddh_vsensor.device.node import SensorNode
from ddh_vsensor.device.objects import (ABORT_DEVICE_STATE, ABORT_READ_ONLY, ABORT_VALUE_RANGE,
                                        UNCERTAINTY_MAX_COUNTS, UNCERTAINTY_STEP_MM, Published)

log = logging.getLogger(__name__)

STALE_PERIODS = 3.0
# A slow event timer does not make old input fresh: inputs are read every few ms whatever
# the tick, so the tick's period counts towards staleness only up to the default timer's
STALE_TICK_CAP_S = 0.01
# Frame timestamps within this of the wall clock are this host's clock (socketcan stamps on
# reception; a remote hub passes the sender's time on): then the newest integrated frame's
# own age says how old the published position is, delivery delays included.
WALL_CLOCK_MATCH_S = 5.0
# Frames stamped behind this host's wall clock by a steady offset (a sender's clock passed on
# by a hub, not quite this host's): after LATE_LEARN_S of stamps that many seconds behind,
# within LATE_SPREAD_S of each other, the offset is the sender's clock, not a delivery delay,
# and is taken off their age (reported once); a stamp less behind lowers it at once.
LATE_LEARN_S = 10.0
LATE_SPREAD_S = 0.02
HOLD_SLACK_PERIODS = 0.25    # hold_for_input_s: the next frame's arrival, beyond one period
WALL_STEP_MIN_S = 0.005       # wall clock slews (NTP) below this: no step
WALL_READ_TRIES = 3
WALL_READ_GOOD_S = 1e-4       # a read of the two clocks this close together is not retried
# The largest uncertainty the diagnostic frame can carry (UNSIGNED32 counts): a bound beyond
# it is published as "not referenced".
UNCERTAINTY_MAX_MM = UNCERTAINTY_MAX_COUNTS * UNCERTAINTY_STEP_MM
# The flags as plain ints on the per-tick path: IntFlag arithmetic costs a Python call per
# operator.
_STALE_INPUT = int(Flags.STALE_INPUT)
_NOT_REFERENCED = int(Flags.NOT_REFERENCED)
_TABLE_CLAMPED = int(Flags.TABLE_CLAMPED)
_PRESET_UNCONFIRMED = int(Flags.PRESET_UNCONFIRMED)
_CONTROLLER_NOT_OPERATIONAL = int(Flags.CONTROLLER_NOT_OPERATIONAL)
# a step at a soft limit (the estimate clipped) or not integrated ends a switch's pair
_ENDS_PAIR = int(Flags.AT_SOFT_LIMIT | Flags.STALE_INPUT)


def read_wall_offset() -> tuple[float, float, float]:
    """The wall clock, the wall clock less the monotonic one, and how far that difference
    may be off: half the interval between two monotonic reads around the wall one. A process
    preempted between reading the two clocks (a loaded controller) would otherwise see a
    clock step of the preemption's length; the narrowest of a few reads is kept."""
    best = (0.0, 0.0, math.inf)
    for _ in range(WALL_READ_TRIES):
        before = time.monotonic()
        wall_s = time.time()
        half_s = 0.5 * (time.monotonic() - before)
        if half_s < best[2]:
            best = (wall_s, wall_s - before - half_s, half_s)
        if half_s <= WALL_READ_GOOD_S:
            break
    return best


def estimator_flags(est: Estimator, clamped: bool = False) -> int:
    """The estimator's flags for its current state (as its step() would report them)."""
    return int(est.state_flags()) | (_TABLE_CLAMPED if clamped else 0)


@dataclass(eq=False)
class Unit:
    """One cylinder: its estimator, its emulated node and its input bookkeeping."""

    actuator: str
    estimator: Estimator
    heartbeat: HeartbeatConsumer | None      # None: the controller's heartbeat is not consumed
    cfg: Config
    inputs: Inputs
    log: RateLimitedLog
    tick_period_s: Callable[[], float]       # the publishing tick's period, now
    stale_periods: float = STALE_PERIODS
    node: SensorNode | None = None
    last_step: Step | None = None
    last_frame_t: float | None = None        # timestamp of the last integrated Sevcon frame
    last_rx_s: float | None = None           # monotonic time it was integrated
    last_wall_offset_s: float = 0.0          # wall less monotonic clock then
    last_wall_offset_err_s: float = 0.0      # how far that reading may be off
    input_period_s: float | None = None      # measured Sevcon period (smoothed)
    integrated: int = 0
    held: int = 0                            # frames not integrated: no oil temperature yet
    first_held_t: float | None = None        # timestamp of the first of them
    stale_since_s: float | None = None
    stale_reason: str = ""
    references: int = 0
    restored: bool = False
    gaps: int = 0                            # unintegrated intervals that widened the bound
    gap_widening_mm: float = 0.0             # their worst-case travel, in total
    preset_pending: bool = False             # Flags.PRESET_UNCONFIRMED: until a reference
    # After a preset or a widened gap the estimate is provisional: the estimator is kept
    # unreferenced inside (its next reference corrects in full and teaches the gains
    # nothing), while the flags published say what the service knows (PRESET, or nothing
    # beyond the widened bound).
    provisional: bool = False
    presets_accepted: int = 0
    presets_refused: int = 0
    clock_disagreed: bool = False            # frame and arrival clocks disagreed (logged)
    stamp_offset_s: float = 0.0              # learnt: how far the stamps run behind the wall
    late_since_s: float | None = None        # monotonic start of the current steady window
    late_lo_s: float = 0.0                   # the window's least and largest lag
    late_hi_s: float = 0.0
    clock: Callable[[], float] = time.monotonic  # the service's monotonic time (a test's own)
    summary_feed: SampleFeed | None = None   # the day summary's samples (:mod:`.summary`)

    def __post_init__(self) -> None:
        self.max_speed_mm_s = self.cfg.max_speed_mm_s(self.actuator)
        self.stroke_mm = self.cfg.unit(self.actuator).stroke_mm
        self.switch_drift = SwitchDrift.from_config(self.cfg, self.actuator)

    @property
    def velocity_mm_s(self) -> float:
        return self.last_step.velocity_mm_s if self.last_step is not None else 0.0

    # --- motion in -----------------------------------------------------------------------

    def widen(self, travel_mm: float, why: str) -> None:
        """Motion that was not integrated: widen the uncertainty by its worst-case travel;
        when the bound reaches the stroke the unit is not referenced (until a reference)."""
        est = self.estimator
        stroke = self.stroke_mm
        add = min(abs(travel_mm), stroke)
        self.gaps += 1
        self.gap_widening_mm += add
        est.forget_switch_states()          # a switch that changed in the gap is no edge
        self.switch_drift.interrupt()
        if add >= stroke or est.uncertainty_mm + add >= stroke:
            est.add_uncertainty(max(stroke - est.uncertainty_mm, 0.0))
            est.referenced = False
            self.preset_pending = self.provisional = False
            self.log.warning(f"gap-{self.actuator}", "%s: %s: up to %.1f mm of travel not "
                             "integrated: not referenced until the next reference switch",
                             self.actuator, why, add)
        else:
            est.add_uncertainty(add)
            if est.referenced:
                est.referenced, self.provisional = False, True
            self.log.warning(f"gap-{self.actuator}", "%s: %s: uncertainty widened by %.1f "
                             "mm (worst-case travel)", self.actuator, why, add)

    def cap_uncertainty_at_stroke(self) -> None:
        """A bound beyond the stroke (a restored state's) says no more than the stroke."""
        est = self.estimator
        if est.uncertainty_mm > self.stroke_mm:
            est.restore(replace(est.snapshot(), uncertainty_mm=self.stroke_mm))

    def integrate(self, msg: can.Message, now: float, watched_s: float | None = None) -> bool:
        """A Sevcon frame read at ``now``, the bus last found without it at ``watched_s``
        (default: ``now``): checked, then one estimator step with the latest oil temperature
        and Hall states (held until the first oil temperature). True when integrated."""
        sample = self.inputs.sevcon(self.actuator, msg, now)
        if sample is None:
            return False
        oil = self.inputs.oil_temp_c
        if oil is None:
            self.held += 1
            self.inputs.units[self.actuator].reasons["held"] += 1
            if self.first_held_t is None:
                self.first_held_t = sample.t_s
            return False
        est = self.estimator
        since = self.last_frame_t if self.last_frame_t is not None else self.first_held_t
        wall_s, wall_offset_s, offset_err_s = read_wall_offset()
        if since is not None:
            dt = sample.t_s - since
            untracked_s = self.untracked_s(dt, now if watched_s is None else watched_s,
                                           sample.t_s, wall_s, wall_offset_s, offset_err_s)
            if 0.0 < dt <= est.max_gap_s and untracked_s <= est.max_gap_s \
                    and self.last_frame_t is not None:
                self.input_period_s = dt if self.input_period_s is None else \
                    0.9 * self.input_period_s + 0.1 * dt
            elif untracked_s > est.max_gap_s or self.last_frame_t is None:
                # not integrated by the estimator: only the worst case is known
                self.widen(self.max_speed_mm_s * max(untracked_s, 0.0),
                           f"{untracked_s:.3f} s without integrated Sevcon frames")
            elif dt <= 0.0 and self.last_rx_s is not None:
                # the frame's clock went back: the estimator skips this interval; its length
                # is the arrival gap, at least one input period
                gap_s = max(now - self.last_rx_s, self.input_period_s or est.max_gap_s)
                self.widen(self.max_speed_mm_s * gap_s, "Sevcon frame time went back")
        self.first_held_t = None
        was_referenced = est.referenced
        refs = self.inputs.refs(self.actuator, sample.t_s)
        step = est.step(sample.t_s, sample.speed_rpm, sample.torque_nm, oil, refs,
                        self.inputs.refs_since_s, self.inputs.io_sends_on_change)
        self.last_step = step
        feed = self.summary_feed
        if feed is not None:
            since = self.inputs.refs_since_s
            feed.add(sample.t_s, sample.speed_rpm, sample.torque_nm, oil, refs,
                     since if since is not None and self.inputs.io_sends_on_change
                     else math.nan, wall_s)
        if step.events:
            for change in self.switch_drift.edges(step.events, sample.t_s):
                self.report_drift(change)
        if step.flags & _ENDS_PAIR:
            self.switch_drift.interrupt()
        self.last_frame_t, self.last_rx_s = sample.t_s, now
        self.last_wall_offset_s, self.last_wall_offset_err_s = wall_offset_s, offset_err_s
        self._learn_stamp_offset(wall_s - sample.t_s, now)
        self.integrated += 1
        if step.reference is not None and not was_referenced:
            # Taken in full from an unreferenced estimate: the edge lies somewhere within its
            # sample, whose travel an estimate clipped at a stroke end did not record, and the
            # travel from the edge to its acceptance (debounce) is the model's: widen by both.
            period_s = self.input_period_s or est.max_gap_s
            est.add_uncertainty(abs(step.velocity_mm_s)
                                * (self.cfg.estimator.debounce_s + 2.0 * period_s))
        confirmed = self.provisional and step.reference is not None
        if confirmed:
            self.provisional = False
            if self.preset_pending:
                self.preset_pending = False
                log.info("%s: preset confirmed by a reference switch", self.actuator)
        if step.reference is not None:
            self.references += 1
            self.log.info(f"ref-{self.actuator}", "%s: reference switch %s (%s): position "
                          "%.2f mm, uncertainty %.2f mm", self.actuator, step.reference,
                          "taken whole" if step.reference_gain >= 1.0 else
                          f"{step.reference_gain:.0%} taken", step.position_mm,
                          step.uncertainty_mm)
        return True

    def _learn_stamp_offset(self, lag_s: float, now: float) -> None:
        """How far behind the wall clock the stamps run (see LATE_LEARN_S)."""
        if not 0.0 <= lag_s < WALL_CLOCK_MATCH_S:
            self.late_since_s = None
            return
        self.stamp_offset_s = min(self.stamp_offset_s, lag_s)
        excess_s = lag_s - self.stamp_offset_s
        if excess_s <= STALE_TICK_CAP_S:
            self.late_since_s = None
            return
        if self.late_since_s is None or not self.late_hi_s - LATE_SPREAD_S <= lag_s \
                <= self.late_lo_s + LATE_SPREAD_S:
            self.late_since_s, self.late_lo_s, self.late_hi_s = now, lag_s, lag_s
            return
        self.late_lo_s, self.late_hi_s = min(self.late_lo_s, lag_s), max(self.late_hi_s, lag_s)
        if now - self.late_since_s >= LATE_LEARN_S:
            self.stamp_offset_s, self.late_since_s = self.late_lo_s, None
            self.log.warning(f"offset-{self.actuator}", "%s: Sevcon frame stamps run %.3f s "
                             "behind this host's wall clock, steadily for %.0f s: taken as "
                             "their clock's offset, not as frames delivered late",
                             self.actuator, self.stamp_offset_s, LATE_LEARN_S)

    def untracked_s(self, dt: float, now: float, t_s: float, wall_s: float,
                    wall_offset_s: float, offset_err_s: float = 0.0) -> float:
        """How long the machine may have moved since the last integrated frame, by the
        clocks that can be trusted. Frames stamped by this host's wall clock: their interval,
        less any step of the wall clock against the monotonic one since (an NTP step during a
        gap hides travel; a step within the two readings' own error is not one). Frames
        stamped by another clock (an interface's own, a campaign's): their interval. Either
        way never less than the arrival interval on this host's monotonic clock, which no
        step of a frame clock shortens: a gap the host measured is a gap (a delivery delayed
        beyond ``max_gap_s`` counts as travel, the safe side)."""
        if self.last_rx_s is None or dt <= 0.0:
            return dt
        arrival_s = now - self.last_rx_s
        if abs(wall_s - t_s) < WALL_CLOCK_MATCH_S:
            stepped_s = wall_offset_s - self.last_wall_offset_s
            min_step_s = WALL_STEP_MIN_S + offset_err_s + self.last_wall_offset_err_s
            framed_s = dt - stepped_s if abs(stepped_s) > min_step_s else dt
        else:
            framed_s = dt
        if arrival_s - framed_s > self.estimator.max_gap_s and not self.clock_disagreed:
            # a frame clock that steps back while nothing arrives (an interface passing a
            # sender's stamps, an adapter whose own clock restarted) hides the gap's travel
            self.clock_disagreed = True
            self.log.warning(f"clock-{self.actuator}", "%s: Sevcon frame time says %.3f s "
                             "passed, this host measured %.3f s since the last integrated "
                             "frame: the host's interval counts (logged once)",
                             self.actuator, framed_s, arrival_s)
        return max(framed_s, arrival_s)

    def preset(self, position_mm: float, published: Published) -> None:
        """An SDO write of the preset (0x6010): accepted only as configured
        (``faults.preset``), near standstill and within the jump bound (beyond the
        ``published`` uncertainty); otherwise refused with a CiA 301 abort code. Either way
        logged with the old and new value, counted."""
        est, node, faults = self.estimator, self.node, self.cfg.faults
        assert node is not None
        old_mm = est.position_mm
        refusal: tuple[int, str] | None = None
        if faults.preset == "disabled":
            refusal = (ABORT_READ_ONLY, "presets are disabled (faults.preset)")
        elif faults.preset == "pre-operational only" and \
                node.node.nmt.state != "PRE-OPERATIONAL":
            refusal = (ABORT_DEVICE_STATE, f"the node is {node.node.nmt.state}, presets only "
                       "in PRE-OPERATIONAL")
        elif abs(self.velocity_mm_s) > faults.preset_standstill_mm_s:
            refusal = (ABORT_DEVICE_STATE, f"the rod moves at {self.velocity_mm_s:.1f} mm/s "
                       f"(standstill: below {faults.preset_standstill_mm_s:g} mm/s)")
        elif abs(position_mm - old_mm) > published.uncertainty_mm + faults.preset_max_jump_mm:
            refusal = (ABORT_VALUE_RANGE, f"a jump of {position_mm - old_mm:+.2f} mm, beyond "
                       f"the uncertainty {published.uncertainty_mm:.2f} mm + "
                       f"{faults.preset_max_jump_mm:g} mm")
        if refusal is not None:
            self.presets_refused += 1
            self.log.warning(f"preset-refused-{self.actuator}", "%s: preset %.3f mm refused "
                             "(%s): position stays %.3f mm (%d refused so far)", self.actuator,
                             position_mm, refusal[1], old_mm, self.presets_refused)
            raise SdoAbortedError(refusal[0])
        est.preset(position_mm, self.cfg.estimator.uncertainty_reference_mm)
        est.referenced = False                       # provisional: see Unit.provisional
        self.switch_drift.interrupt()
        if self.stale_since_s is not None:
            self.stale_since_s = self.clock()       # worst-case travel counts from here
        self.preset_pending = self.provisional = True
        self.presets_accepted += 1
        self.log.info(f"preset-{self.actuator}", "%s: preset accepted: %.3f mm -> %.3f mm "
                      "(flagged until a reference switch confirms it; %d accepted so far)",
                      self.actuator, old_mm, est.position_mm, self.presets_accepted)
        if self.last_step is not None:
            self.last_step = Step(est.position_mm, self.last_step.velocity_mm_s,
                                  est.uncertainty_mm,
                                  estimator_flags(est) & ~Flags.NOT_REFERENCED)

    def report_drift(self, change: Change, restored: bool = False) -> None:
        """A switch's verdict changed (``restored``: carried over from before the start):
        one line, at warning while drifted."""
        tol = self.switch_drift.tolerance_mm
        if change.drifted:
            log.warning("%s: reference switch %s drifted%s: its spans depart from the "
                        "configured window and hysteresis by more than %g mm "
                        "(estimator.reference_drift_mm): %s", self.actuator, change.switch,
                        " (carried over from before the start)" if restored else "", tol,
                        change.text)
        else:
            log.info("%s: reference switch %s back within %g mm of its configured window "
                     "and hysteresis: %s", self.actuator, change.switch, tol, change.text)

    # --- what is published -----------------------------------------------------------------

    def hold_for_input_s(self, wall_s: float, fresh_s: float) -> float:
        """How long after ``wall_s`` (the tick's deadline) to hold this unit's position
        for its next Sevcon frame (0: publish now). Held when the newest integrated
        frame is older than ``fresh_s`` and the next one is due within the measured input
        period (a quarter period of slack for its arrival): with slow input (500 Hz) a fixed
        tick would otherwise publish values up to a whole period old. Frames stamped by
        another clock than this host's, no measured period, or a frame overdue: not held.
        Frames arriving at the threshold's phase switch between the tick and the next frame:
        a jitter of the period less ``fresh_s``."""
        t, period = self.last_frame_t, self.input_period_s
        if t is None or period is None:
            return 0.0
        age_s = wall_s - t
        slack_s = HOLD_SLACK_PERIODS * period
        if not fresh_s < age_s < period + slack_s:
            return 0.0
        return period + slack_s - age_s

    def stale(self, now: float) -> tuple[bool, str]:
        if self.inputs.oil_temp_c is None:
            return True, "no oil temperature yet"
        period = max(min(self.tick_period_s(), STALE_TICK_CAP_S), self.input_period_s or 0.0)
        if self.last_rx_s is None:
            return True, "no Sevcon frame yet"
        limit_s = self.stale_periods * period
        if now - self.last_rx_s > limit_s:
            return True, f"no Sevcon frame for {now - self.last_rx_s:.2f} s"
        if self.last_frame_t is not None:
            age_s = time.time() - self.last_frame_t - self.stamp_offset_s
            if limit_s < age_s < WALL_CLOCK_MATCH_S:
                return True, f"the newest Sevcon frame is {age_s:.2f} s old (delivered late)"
        return False, ""

    def published(self, now: float) -> Published:
        est = self.estimator
        stale, why = self.stale(now)
        step = self.last_step
        flags = int(est.state_flags())
        if step is not None and int(step.flags) & _TABLE_CLAMPED:
            flags |= _TABLE_CLAMPED
        if self.provisional:
            flags &= ~_NOT_REFERENCED
        if self.preset_pending:
            flags |= _PRESET_UNCONFIRMED
        if self.heartbeat is not None and not self.heartbeat.status(now)[0]:
            flags |= _CONTROLLER_NOT_OPERATIONAL
        u = est.uncertainty_mm
        speed = self.velocity_mm_s
        if stale:
            if self.stale_since_s is None:
                self.stale_since_s = self.last_rx_s if self.last_rx_s is not None else now
                self.stale_reason = why
                self.log.warning(f"stale-{self.actuator}", "%s: input stale (%s): position "
                                 "held at %.2f mm", self.actuator, why, est.position_mm)
            held_s = max(now - self.stale_since_s, 0.0)
            u = max(u, min(u + self.max_speed_mm_s * held_s, self.stroke_mm))
            flags |= _STALE_INPUT
            speed = 0.0
        elif self.stale_since_s is not None:
            self.log.info(f"back-{self.actuator}", "%s: input back after %.2f s (%s)",
                          self.actuator, now - self.stale_since_s, self.stale_reason)
            self.stale_since_s = None
        if u >= UNCERTAINTY_MAX_MM:
            flags |= _NOT_REFERENCED
        counters = self.inputs.units[self.actuator]
        return Published(est.position_mm, speed, u, flags, counters.received, counters.rejected)
