"""Hall switches' geometry checked in service: the travel between two edges of one switch.

A switch at ``p`` is on within ``w`` of it and goes off only beyond ``w + h``
(:mod:`.references`), so the rod's travel between two consecutive edges of one switch is fixed
by ``w`` and ``h`` alone, whatever ``p`` and whatever error the estimate carries:

- passing through (on, then off on the other side; or off, then on from that side): ``2w + h``
  (:data:`THROUGH`);
- turning back (on, then off on the side it came from; or off, then on again from the side it
  left to): ``h`` (:data:`HYSTERESIS`).

The estimator's own travel between the two crossings measures the span. With ``e`` an edge's
error (estimate minus the configured switching position, :attr:`.ReferenceEvent.error_mm`) and
``k1`` the share of the first error the first edge corrected, the measured span departs from
the configured one by ``d = e2 - (1 - k1) e1``: ``p`` cancels, and so does the error the
estimate brought into the pair. A changed ``w`` or ``h`` (a switch knocked or its air gap
changed, a magnet that slipped on its carrier or weakened) moves the mean of ``d`` away from
0; a switch moved along the stroke as a whole keeps its spans (the estimator flags that one:
its references disagree with the estimate, :attr:`.Estimator.suspect_switch`).

Noise of one pair's ``d``: the estimator's travel error over a few millimetres (its relative
error, 1 % of 6.5 mm is 0.07 mm, plus the pressure transients at the edges and, turning back,
the leakage's creep while the rod stands), where within its sample each crossing lies (the
I/O module's time of the change where it sends one, else up to half a sample's travel: 0.5 mm
at 100 mm/s and 10 ms) and the switch's own pass-to-pass repeatability. Measured on simulated
machines working around their switches (six 4-minute runs per case, about 2,700 pairs): a
pair's spread 0.01-0.09 mm on the nominal plant, 0.08-0.24 mm with the drives' typical
structure the model lacks, up to 0.56 mm where the model is far off (that structure, the
pumps' leakage doubled, the torque read 5 % off, 60 degC oil, 1 t payload); there the spans
turning back read long by up to 0.67 mm on average (creep under load), the largest mean of
any span on a switch as configured.

Per switch and span, an exponentially weighted mean of ``d`` (weight :data:`WEIGHT` per pair,
about the last 20 pairs) and of its spread. The mean starts at 0 (the configuration is taken as
right until the pairs say otherwise); a pair counts at most :data:`CLIP_SPREADS` spreads or
one tolerance beyond the mean, so that an edge misread (the rod turned at it: the span then
off by twice the window) moves the mean by a tenth of the tolerance at most. With a per-pair
spread ``s`` the mean's is ``s sqrt(WEIGHT / (2 - WEIGHT))``, 0.23 s. The tolerance
(``estimator.reference_drift_mm``, default 1 mm) is thus 18 of the mean's spreads with the
typical structure, and where the model is far off still 2.6 of them beyond its worst mean
(0.67 mm): no verdict changed on any of those runs (10,600 pairs, four cases). A span
off by twice the tolerance is reported after 8-9 pairs of it (7 unclipped: ``log(1 - 1/2) /
log(1 - WEIGHT)``), by 1.5 tolerances after 10-13; one off by the tolerance itself after 25-50
pairs, or not. A switch drifts when either span's mean departs by more than the tolerance
after at least :data:`MIN_PAIRS` pairs; it is back once both are within :data:`CLEAR_SHARE`
of it, so that a mean near the tolerance does not toggle the verdict. What is reported is the
mean divided by the weight its pairs have in it (:attr:`SpanStats.measured_mm`): the departure
itself, not its start at 0.

Pairs not taken, and why:

- across a gap, a preset, a restart or another switch's reference (:meth:`SwitchDrift.
  interrupt`): the estimate between the edges was not the estimator's own travel;
- across a soft limit: the estimate was clipped there and its travel lost (a rod pressed into
  the end stop between an end switch's edges);
- where either edge's direction of travel was not told by the motion (:data:`MIN_CROSSING_MM_S`):
  the switching position, hence the span, is then the estimator's guess;
- edges of one kind twice, or off-then-on from the far side: an edge was missed;
- where the estimator's own uncertainty grew by more than a quarter of the tolerance between
  the edges (``uncertainty_per_travel`` x travel + ``uncertainty_hold_mm_per_s`` x time
  standing: 25 mm of travel or 25 s standing at the defaults), or more than
  :data:`MAX_PAIR_S` apart: there the model's own error, not the switch, is what a pair
  would measure.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ddh_vsensor.config import Config
from ddh_vsensor.estimator.estimator import ReferenceEvent, RunEstimate
from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.estimator.references import Switch, switches_from_config

THROUGH, HYSTERESIS = "through", "hysteresis"
SPANS = (THROUGH, HYSTERESIS)
SPAN_WORDS = {THROUGH: "passing through (2 window + hysteresis)",
              HYSTERESIS: "turning back (hysteresis)"}
WEIGHT = 0.1                # per pair: the mean remembers about the last 20 pairs
MIN_PAIRS = 5               # before a span's mean can raise a drift
CLEAR_SHARE = 0.5           # back to ok once every mean is within this share of the tolerance
# One pair moves the mean by at most WEIGHT times this many spreads, or the tolerance: an
# edge misread at a reversal (the span then off by twice the window) is one such pair
CLIP_SPREADS = 3.0
GROWTH_SHARE = 0.25         # the estimator's own uncertainty growth a pair may span
MAX_PAIR_S = 60.0           # edges further apart are not one pass (temperature, load change)
# An edge is a crossing in a known direction where the velocity at its sample and over the
# debounce time after it agree and both exceed this; else the rod may have turned at the
# switching point, and the estimator guessed the side (its mean over 15 ms reaches 10 mm/s
# from a reversal at 1.3 m/s^2)
MIN_CROSSING_MM_S = 10.0
RECORD_FORMAT = "ddh-vsensor switch spans 1"


def configured_span_mm(switch: Switch, span: str) -> float:
    """The span the configuration gives ``switch``: ``2w + h`` through it, ``h`` turning."""
    h = switch.hysteresis_mm
    return 2.0 * switch.window_mm + h if span == THROUGH else h


@dataclass
class SpanStats:
    """One span of one switch: how many pairs measured it, and the weighted mean and spread
    of their departures from the configured span."""

    pairs: int = 0
    departure_mm: float = 0.0
    spread_mm: float = 0.0
    last_mm: float = math.nan           # the latest pair's departure (not persisted)

    def add(self, departure_mm: float, tolerance_mm: float) -> None:
        """One pair's departure, clipped to :data:`CLIP_SPREADS` spreads or the tolerance,
        whichever is more, about the mean."""
        clip_mm = max(CLIP_SPREADS * self.spread_mm, tolerance_mm)
        delta = min(max(departure_mm - self.departure_mm, -clip_mm), clip_mm)
        self.departure_mm += WEIGHT * delta
        # West's exponentially weighted variance: about the mean before and after this pair
        self.spread_mm = math.sqrt((1.0 - WEIGHT) * (self.spread_mm ** 2 + WEIGHT * delta ** 2))
        self.pairs += 1
        self.last_mm = departure_mm

    @property
    def measured_mm(self) -> float:
        """The departure the pairs say: the mean without its start at 0 (the mean divided
        by the weight its pairs have in it)."""
        weight = 1.0 - (1.0 - WEIGHT) ** self.pairs
        return self.departure_mm / weight if weight > 0.0 else 0.0


@dataclass
class SwitchSpans:
    """One switch: its two spans, and whether it is reported drifted."""

    switch: Switch
    spans: dict[str, SpanStats] = field(default_factory=lambda: {s: SpanStats() for s in SPANS})
    drifted: bool = False

    def judge(self, tolerance_mm: float) -> bool:
        """Update the verdict; True when it changed."""
        stats = self.spans.values()
        if self.drifted:
            now = any(abs(st.departure_mm) > CLEAR_SHARE * tolerance_mm for st in stats)
        else:
            now = any(abs(st.departure_mm) > tolerance_mm and st.pairs >= MIN_PAIRS
                      for st in stats)
        changed, self.drifted = now != self.drifted, now
        return changed

    def summary(self) -> dict[str, Any]:
        """The verdict and each measured span, configured and as measured (mm)."""
        return {"drifted": self.drifted,
                "spans": {span: {"pairs": st.pairs,
                                 "configured_mm": configured_span_mm(self.switch, span),
                                 "measured_mm": (configured_span_mm(self.switch, span)
                                                 + st.measured_mm),
                                 "spread_mm": st.spread_mm}
                          for span, st in self.spans.items() if st.pairs}}

    def describe(self) -> str:
        """What the switch's spans measure against the configuration, in one line."""
        parts = []
        for span, st in self.spans.items():
            if not st.pairs:
                continue
            nominal = configured_span_mm(self.switch, span)
            measured = st.measured_mm
            parts.append(f"{SPAN_WORDS[span]} {nominal + measured:.2f} mm, configured "
                         f"{nominal:.2f} ({measured:+.2f}, spread {st.spread_mm:.2f}, "
                         f"{st.pairs} pairs)")
        return "; ".join(parts) if parts else "no pair measured yet"


@dataclass(frozen=True)
class Change:
    """A switch whose verdict changed with the latest edge."""

    switch: str
    drifted: bool
    text: str           # what its spans measure


@dataclass
class _Edge:
    event: ReferenceEvent
    t_s: float


class SwitchDrift:
    """One unit's switches' spans from its estimator's accepted edges (:meth:`edges`)."""

    def __init__(self, switches: Sequence[Switch], tolerance_mm: float,
                 per_travel: float, hold_mm_per_s: float) -> None:
        self.tolerance_mm = tolerance_mm
        self.per_travel, self.hold_mm_per_s = per_travel, hold_mm_per_s
        self.switches = {sw.name: SwitchSpans(sw) for sw in switches}
        self._last: _Edge | None = None
        self.ignored: dict[str, int] = {}       # pairs not taken, by reason
        self.version = 0                        # counts the changes to what is recorded

    @classmethod
    def from_config(cls, cfg: Config, actuator: str) -> "SwitchDrift":
        ecfg = cfg.estimator
        return cls(switches_from_config(cfg.unit(actuator)), ecfg.reference_drift_mm,
                   ecfg.uncertainty_per_travel, ecfg.uncertainty_hold_mm_per_s)

    @property
    def drifted(self) -> list[str]:
        return [name for name, s in self.switches.items() if s.drifted]

    def interrupt(self) -> None:
        """The estimate stopped being the estimator's own travel (a gap, a preset, a soft
        limit): no pair across this point."""
        self._last = None

    def edges(self, events: Iterable[ReferenceEvent], t_s: float) -> list[Change]:
        """Edges the estimator took at time ``t_s`` (one step's), in order; returns the
        switches whose verdict they changed."""
        changes = []
        for event in events:
            change = self._edge(event, t_s)
            if change is not None:
                changes.append(change)
        return changes

    def feed(self, estimate: RunEstimate, time_s: np.ndarray) -> list[Change]:
        """The offline face: a whole run's edges (:meth:`.Estimator.run`), interrupted
        where its samples were not integrated or the estimate sat at a soft limit, as the
        service interrupts them online."""
        broken = (estimate.flags & (Flags.AT_SOFT_LIMIT | Flags.STALE_INPUT)) != 0
        changes, since = [], 0
        for event in estimate.events:
            if broken[since:event.index].any():
                self.interrupt()
            changes += self.edges([event], float(time_s[event.index]))
            since = event.index
        return changes

    def _edge(self, event: ReferenceEvent, t_s: float) -> Change | None:
        last, self._last = self._last, _Edge(event, t_s)
        spans = self.switches.get(event.switch)
        if last is None or spans is None:
            return None
        why = self._skip(last, event, t_s)
        if why is not None:
            self.ignored[why] = self.ignored.get(why, 0) + 1
            return None
        span = self._span(spans.switch, last.event, event)
        if span is None:
            self.ignored["an edge missed"] = self.ignored.get("an edge missed", 0) + 1
            return None
        first = last.event
        # the span is travelled in the second edge's direction: up, it adds to the errors
        sign = 1.0 if event.crossing_mm_s > 0.0 else -1.0
        departure = sign * (event.error_mm - (1.0 - first.gain) * first.error_mm)
        spans.spans[span].add(departure, self.tolerance_mm)
        self.version += 1
        if spans.judge(self.tolerance_mm):
            return Change(event.switch, spans.drifted, spans.describe())
        return None

    def _skip(self, last: _Edge, event: ReferenceEvent, t_s: float) -> str | None:
        """Why the pair (last, event) says nothing of the switch; None when it does."""
        first = last.event
        if first.switch != event.switch:
            return "another switch between"
        if not (_crossed(first) and _crossed(event)):
            return "direction not told"
        if not (math.isfinite(event.path_mm) and math.isfinite(event.held_s)):
            return "travel not known"
        growth = self.per_travel * event.path_mm + self.hold_mm_per_s * event.held_s
        if growth > GROWTH_SHARE * self.tolerance_mm or not 0.0 <= t_s - last.t_s <= MAX_PAIR_S:
            return "too long"
        return None

    @staticmethod
    def _span(sw: Switch, first: ReferenceEvent, second: ReferenceEvent) -> str | None:
        """Which span the two edges bound (None: not one span: an edge was missed)."""
        up1, up2 = first.crossing_mm_s > 0.0, second.crossing_mm_s > 0.0
        if first.rising == second.rising:
            return None
        if first.rising:                        # on, then off
            return THROUGH if up1 == up2 else HYSTERESIS
        return HYSTERESIS if up1 != up2 else None   # off, then on: only from the side it left

    # --- persistence ---------------------------------------------------------------------

    def record(self) -> dict[str, Any]:
        """What a restart keeps: per switch the geometry it was judged against, the verdict
        and each span's pairs, mean and spread."""
        return {"format": RECORD_FORMAT, "tolerance_mm": self.tolerance_mm,
                "switches": {name: {"window_mm": s.switch.window_mm,
                                    "hysteresis_mm": s.switch.hysteresis_mm,
                                    "drifted": s.drifted,
                                    "spans": {span: {"pairs": st.pairs,
                                                     "departure_mm": st.departure_mm,
                                                     "spread_mm": st.spread_mm}
                                              for span, st in s.spans.items()}}
                             for name, s in self.switches.items()}}

    def restore(self, record: Mapping[str, Any]) -> list[str]:
        """Carry on from :meth:`record`'s output; returns the switches restored. A switch
        whose configured window or hysteresis changed since (commissioned again) starts
        afresh; ValueError when the record does not parse."""
        if not isinstance(record, Mapping) or record.get("format") != RECORD_FORMAT:
            raise ValueError(f"not a {RECORD_FORMAT!r} record")
        switches = record.get("switches")
        if not isinstance(switches, Mapping):
            raise ValueError("switches must be a mapping")
        parsed = {}
        for name, data in switches.items():
            if name not in self.switches:
                continue
            sw = self.switches[name].switch
            if not isinstance(data, Mapping):
                raise ValueError(f"{name}: not a mapping")
            if (_number(data, "window_mm"), _number(data, "hysteresis_mm")) != (
                    sw.window_mm, sw.hysteresis_mm):
                continue
            drifted = data.get("drifted")
            spans = data.get("spans")
            if not isinstance(drifted, bool) or not isinstance(spans, Mapping):
                raise ValueError(f"{name}: drifted must be true or false, spans a mapping")
            stats = {}
            for span in SPANS:
                s = spans.get(span)
                if not isinstance(s, Mapping):
                    raise ValueError(f"{name}.{span}: missing")
                pairs = s.get("pairs")
                if type(pairs) is not int or pairs < 0:
                    raise ValueError(f"{name}.{span}.pairs: a whole number >= 0")
                spread = _number(s, "spread_mm")
                if spread < 0.0:
                    raise ValueError(f"{name}.{span}.spread_mm: negative")
                stats[span] = SpanStats(pairs, _number(s, "departure_mm"), spread)
            parsed[name] = (drifted, stats)
        for name, (drifted, stats) in parsed.items():
            self.switches[name].drifted, self.switches[name].spans = drifted, stats
            self.switches[name].judge(self.tolerance_mm)    # under today's tolerance
        self.version += 1
        return list(parsed)


def _crossed(event: ReferenceEvent) -> bool:
    """Whether the edge was crossed in the direction the estimator took (see
    :data:`MIN_CROSSING_MM_S`)."""
    v, v_cross = event.velocity_mm_s, event.crossing_mm_s
    return (v > 0.0) == (v_cross > 0.0) and min(abs(v), abs(v_cross)) >= MIN_CROSSING_MM_S


def _number(data: Mapping[str, Any], key: str) -> float:
    value = data.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value):
        raise ValueError(f"{key}: not a finite number")
    return float(value)
