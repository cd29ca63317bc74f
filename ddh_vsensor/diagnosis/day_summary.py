"""A machine's day of evidence in a few kilobytes: what the fleet's analysis computes per CAN
log (:mod:`.evidence`), summed over every stretch of work the daemon saw that day.

The analysis of a log is a sum over its observations (edge-to-edge increments of the
estimate's error and the holds' creep): per cause and grid value the robust loss and the
counts, which add up over a day as over one long log of the whole day, cut into stretches.
They are sufficient for that analysis (a fixed grid per cause, one cause at a time), not for
another one: the single observations are not kept (a day has thousands). The largest change
a cause makes to an increment (the expected position error) is a maximum over a log's work,
not a sum: over a whole day it grows with the day's work (on the simulated fleet a wear's
day maximum crossed the tolerance 3-15 days before its maximum over a log's minute), while
the tolerance and the alarms are about the error a stretch of work carries between
references. So the day keeps each stretch's (a log's worth of work) in a sum, and the
analysis takes their mean, as it takes a log's, with the day's maximum beside it.

The samples (:class:`.day_samples.SampleFeed`, per Sevcon frame in the daemon's loop) are
kept at the loggers' period plus the two around every Hall change, and passed on in blocks.
:class:`DaySummaries` (the daemon's worker process, or the simulator) cuts each unit's
stream into stretches, the same code as a log's analysis on each
(:func:`.references.reference_run`, :func:`.evidence.fit_log`):

- a stretch is :data:`STRETCH_S` of samples (longer, up to :data:`MAX_STRETCH_S`, until it
  has the three edges a reference run needs; beyond that its samples before the last Hall
  change are dropped: an increment that long is no evidence the analysis would trust);
- its observations up to its last used edge count; the next stretch starts at that edge
  (:data:`EDGE_MARGIN_S` before it, after any other Hall change), so every increment and
  every hold counts once, and the estimator restarts at an edge as it does on a log;
- a gap in the samples (longer than ``estimator.max_gap_s``, or the clock going back), a new
  day (UTC, by the wall clock) or a stop ends the stretch with all its observations.

The partial day is written (atomically) every :data:`SAVE_INTERVAL_S` and whenever a day or
the process ends; a restart reads today's file back and goes on from it: a crash loses the
evidence since the last write and the stretch in progress. One file per machine and day,
``<machine>_<YYYY-MM-DD>.summary.json`` (JSON, :data:`VERSION`), every unit in it: the units
share the day, its oil and the one file a modem sends.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ddh_vsensor.atomic import atomic_write, remove_temp_files
from ddh_vsensor.config import Config
from ddh_vsensor.diagnosis.evidence import FLEET_MODE, GRIDS, ROBUST_MM, fit_log
from ddh_vsensor.diagnosis.references import ReferenceRun, reference_run
from ddh_vsensor.estimator.day_samples import (  # noqa: F401 - the summary's names
    MACHINE_RE, SAMPLE_S, SAVE_INTERVAL_S, SUFFIX, Block, SampleFeed, SummaryError, day_of,
    feed_run, machine_name, summary_name)
from ddh_vsensor.measured import MeasuredDataError, Run
from ddh_vsensor.version import __version__

FORMAT = "ddh-vsensor day summary"
VERSION = 1
STRETCH_S = 60.0             # a stretch: the length of a day's CAN log
MAX_STRETCH_S = 600.0
EDGE_MARGIN_S = 1.0          # samples kept before a stretch's first edge
KEEP_DAYS = 400              # summaries older than this are deleted (~7 kB each)
MAX_BYTES = 1 << 20          # a summary file larger than this is no summary


# --- a unit's day --------------------------------------------------------------------------


def _stats() -> list[float]:
    return [math.inf, 0.0, -math.inf, 0.0]            # min, sum, max, count


def _add_stats(s: list[float], values: np.ndarray) -> None:
    if len(values):
        s[0] = min(s[0], float(np.min(values)))
        s[1] += float(np.sum(values))
        s[2] = max(s[2], float(np.max(values)))
        s[3] += len(values)


def _stats_json(s: list[float]) -> dict[str, float] | None:
    return None if not s[3] else {"min": s[0], "mean": s[1] / s[3], "max": s[2], "n": int(s[3])}


def _stats_from(d: dict[str, float] | None) -> list[float]:
    return _stats() if d is None else [float(d["min"]), float(d["mean"]) * int(d["n"]),
                                       float(d["max"]), int(d["n"])]


@dataclass
class UnitDay:
    """One unit's evidence of one day: per cause and grid value the summed loss and the
    largest increment change, and the day's counts and context."""

    loss: dict[str, np.ndarray] = field(default_factory=lambda: {
        c: np.zeros(len(g)) for c, g in GRIDS.items()})
    emax_sum_mm: dict[str, np.ndarray] = field(default_factory=lambda: {
        c: np.zeros(len(g)) for c, g in GRIDS.items()})     # over the stretches
    emax_day_mm: dict[str, np.ndarray] = field(default_factory=lambda: {
        c: np.zeros(len(g)) for c, g in GRIDS.items()})
    n_obs: int = 0
    n_increments: int = 0
    holds: int = 0
    loss_nominal: float = 0.0
    max_increment_sum_mm: float = 0.0    # the nominal model's largest, over the stretches
    max_increment_day_mm: float = 0.0
    stretches: int = 0               # analysed
    unused_stretches: int = 0        # too few edges: no observation
    work_s: float = 0.0              # time with samples (intervals up to max_gap_s)
    analysed_s: float = 0.0          # from each stretch's first to its last edge
    oil_c: list[float] = field(default_factory=_stats)
    hold_torque_nm: list[float] = field(default_factory=_stats)

    def add(self, rows: Sequence[dict], rr: ReferenceRun) -> None:
        """A stretch's rows (:func:`.evidence.fit_log`) and its reference run."""
        for row in rows:
            self.loss[row["cause"]] += np.asarray(row["loss"])
            self.emax_sum_mm[row["cause"]] += np.asarray(row["emax_mm"])
            self.emax_day_mm[row["cause"]] = np.maximum(self.emax_day_mm[row["cause"]],
                                                        np.asarray(row["emax_mm"]))
        first = rows[0]
        self.n_obs += first["n_obs"]
        self.n_increments += first["n_increments"]
        self.loss_nominal += first["loss_nominal"]
        self.max_increment_sum_mm += first["max_increment_mm"]
        self.max_increment_day_mm = max(self.max_increment_day_mm, first["max_increment_mm"])
        self.holds += len(rr.holds)
        self.stretches += 1
        t = rr.run.time_s
        self.analysed_s += float(t[rr.edges[-1]] - t[rr.edges[0]])
        _add_stats(self.hold_torque_nm, np.array([h.torque_nm for h in rr.holds]))

    def to_json(self) -> dict[str, Any]:
        return {"stretches": self.stretches, "unused_stretches": self.unused_stretches,
                "work_s": self.work_s, "analysed_s": self.analysed_s,
                "increments": self.n_increments, "holds": self.holds, "n_obs": self.n_obs,
                "loss_nominal": self.loss_nominal,
                "max_increment_sum_mm": self.max_increment_sum_mm,
                "max_increment_day_mm": self.max_increment_day_mm,
                "oil_c": _stats_json(self.oil_c),
                "hold_torque_nm": _stats_json(self.hold_torque_nm),
                "causes": {c: {"loss": self.loss[c].tolist(),
                               "emax_sum_mm": self.emax_sum_mm[c].tolist(),
                               "emax_day_mm": self.emax_day_mm[c].tolist()} for c in GRIDS}}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> UnitDay:
        u = cls()
        u.stretches, u.unused_stretches = int(d["stretches"]), int(d["unused_stretches"])
        u.work_s, u.analysed_s = float(d["work_s"]), float(d["analysed_s"])
        u.n_increments = int(d["increments"])
        u.holds, u.n_obs = int(d["holds"]), int(d["n_obs"])
        u.loss_nominal = float(d["loss_nominal"])
        u.max_increment_sum_mm = float(d["max_increment_sum_mm"])
        u.max_increment_day_mm = float(d["max_increment_day_mm"])
        u.oil_c, u.hold_torque_nm = _stats_from(d["oil_c"]), _stats_from(d["hold_torque_nm"])
        for c in GRIDS:
            u.loss[c] = np.asarray(d["causes"][c]["loss"], float)
            u.emax_sum_mm[c] = np.asarray(d["causes"][c]["emax_sum_mm"], float)
            u.emax_day_mm[c] = np.asarray(d["causes"][c]["emax_day_mm"], float)
        return u


@dataclass
class Day:
    """A machine's day: every unit's evidence, and when it was seen (wall clock)."""

    day: str
    units: dict[str, UnitDay] = field(default_factory=dict)
    first_s: float = math.inf
    last_s: float = -math.inf
    complete: bool = False
    dirty: bool = False

    def unit(self, actuator: str) -> UnitDay:
        if actuator not in self.units:
            self.units[actuator] = UnitDay()
        return self.units[actuator]


# --- the stream of one unit -----------------------------------------------------------------


_COLUMNS = ("t_s", "speed_rpm", "torque_nm", "oil_temp_c", "hall", "change_s")


class _Stream:
    """One unit's samples not yet in the day's evidence: from the start of the stretch
    whose evidence waits (``pending``) on, the next stretch from ``cursor``."""

    def __init__(self, actuator: str, switches: Sequence[str]) -> None:
        self.actuator, self.switches = actuator, tuple(switches)
        self.cols = {k: np.zeros(0, np.uint8 if k == "hall" else float) for k in _COLUMNS}
        self.day: str | None = None
        self.due_s = STRETCH_S
        self.wall_offset_s = 0.0
        self.cursor = 0
        # the last stretch's rows and reference run: counted once the next stretch is, or
        # taken again to the end at a last stretch too short for a reference run of its own
        self.pending: tuple[list[dict], ReferenceRun] | None = None

    def __len__(self) -> int:
        return len(self.cols["t_s"])

    def append(self, block: Block, lo: int, hi: int) -> None:
        for k in _COLUMNS:
            self.cols[k] = np.concatenate([self.cols[k], getattr(block, k)[lo:hi]])

    def drop(self, upto: int) -> None:
        """Forget the samples before ``upto``; the next stretch starts there."""
        for k in _COLUMNS:
            self.cols[k] = self.cols[k][upto:]
        self.cursor = max(self.cursor - upto, 0)
        self.due_s = STRETCH_S

    def run(self, lo: int, hi: int, source: str) -> Run:
        """Samples ``lo`` to ``hi`` as a run, its times from its first (as a log's in the
        fleet store: a wall-clock time's rounding, 0.24 us, would move a time offset's
        shifted signals by 1e-5 of their step)."""
        c = {k: v[lo:hi] for k, v in self.cols.items()}
        t0 = c["t_s"][0]
        t, hall, change = c["t_s"] - t0, c["hall"], c["change_s"] - t0
        changed = np.zeros(len(t), bool)
        refs, edges = {}, {}
        ok = np.zeros(len(t), bool)          # a change's time within its sample's period
        ok[1:] = (change[1:] > t[:-1]) & (change[1:] <= t[1:])
        for i, name in enumerate(self.switches):
            state = (hall >> i) & 1
            refs[name] = state.astype(np.uint8)
            changed[:] = False
            changed[1:] = state[1:] != state[:-1]
            edges[name] = np.where(changed & ok, change, np.nan)
        return Run(time_s=t, speed_rpm=c["speed_rpm"], torque_nm=c["torque_nm"],
                   oil_temp_c=c["oil_temp_c"], position_mm=np.full(len(t), np.nan),
                   refs=refs, source=source, ref_edge_s=edges)

    def carry_from(self, edge: int) -> int:
        """Where the next stretch starts, for one whose first edge is sample ``edge``:
        :data:`EDGE_MARGIN_S` before it, after any other Hall change (the new stretch sees
        that edge first), at least one sample before it."""
        t, hall = self.cols["t_s"], self.cols["hall"]
        start = int(np.searchsorted(t, t[edge] - EDGE_MARGIN_S))
        changes = np.flatnonzero(hall[1:edge + 1] != hall[:edge]) + 1
        changes = changes[changes < edge]
        if len(changes):
            start = max(start, int(changes[-1]))
        return min(start, edge - 1)


# --- a machine's days -----------------------------------------------------------------------


class DaySummaries:
    """Every unit's stream of a machine, cut into stretches, summed into days, written to
    ``directory`` (None: kept in memory). ``lean``: tables over each stretch's oil only
    (the daemon's memory; the simulator keeps the full range's); ``resume``: a day's file
    found at start is gone on from (the daemon), else replaced (the simulator writes its
    days afresh); ``clock``: monotonic seconds, for the periodic writes."""

    def __init__(self, cfg: Config, machine: str, directory: Path | None, *, lean: bool = True,
                 resume: bool = True, save_interval_s: float = SAVE_INTERVAL_S,
                 keep_days: int = KEEP_DAYS, clock: Callable[[], float] = time.monotonic
                 ) -> None:
        self.cfg, self.machine = cfg, machine_name(machine)
        self.directory = None if directory is None else Path(directory)
        self.lean, self.resume = lean, resume
        self.save_interval_s, self.keep_days, self.clock = save_interval_s, keep_days, clock
        self.max_gap_s = cfg.estimator.max_gap_s
        self.physics_hash = cfg.physics_hash()
        self.streams = {a: _Stream(a, list(cfg.unit(a).references_mm)) for a in cfg.can.units}
        self.days: dict[str, Day] = {}
        self.notes: list[str] = []                # for the caller's log
        self.written: list[Path] = []
        self.writes = 0                           # files written (the health follows them)
        self._saved_s = clock()

    # samples in

    def feed(self, actuator: str, block: Block | None) -> None:
        """A unit's next samples: stretches analysed as they fill, the day written when due."""
        if block is not None and len(block):
            stream = self.streams[actuator]
            stream.wall_offset_s = block.wall_offset_s
            wall = block.t_s + block.wall_offset_s
            days = [day_of(float(wall[0]))]
            cuts = [0]
            if day_of(float(wall[-1])) != days[0]:            # over midnight (UTC)
                keys = np.array([day_of(float(w)) for w in wall])
                cuts = [0, *(np.flatnonzero(keys[1:] != keys[:-1]) + 1).tolist()]
                days = [str(keys[i]) for i in cuts]
            for day, lo, hi in zip(days, cuts, [*cuts[1:], len(block)]):
                self._feed_day(stream, day, block, lo, hi)
        if self.clock() - self._saved_s >= self.save_interval_s:
            self.save()

    def _feed_day(self, stream: _Stream, day: str, block: Block, lo: int, hi: int) -> None:
        if stream.day != day:
            if stream.day is not None:
                self._final(stream)
            stream.day = day
            self._retire_days()
        record = self._day(day)
        t = block.t_s[lo:hi]
        wall = t + block.wall_offset_s
        record.first_s = min(record.first_s, float(wall[0]))
        record.last_s = max(record.last_s, float(wall[-1]))
        record.dirty = True
        unit = record.unit(stream.actuator)
        _add_stats(unit.oil_c, block.oil_temp_c[lo:hi])
        # gaps (or the clock going back) end the stretch before them
        steps = np.diff(t, prepend=stream.cols["t_s"][-1] if len(stream) else t[0])
        unit.work_s += float(np.sum(steps[(steps > 0) & (steps <= self.max_gap_s)]))
        breaks = np.flatnonzero((steps > self.max_gap_s) | (steps <= 0))
        if not len(stream):                  # the first sample follows nothing
            breaks = breaks[breaks > 0]
        start = lo
        for b in [*(lo + breaks).tolist(), hi]:
            stream.append(block, start, b)
            self._stretches(stream)
            if b < hi:
                self._final(stream)
            start = b

    # stretches

    def _stretches(self, stream: _Stream) -> None:
        t = stream.cols["t_s"]
        while len(t) > stream.cursor and t[-1] - t[stream.cursor] >= stream.due_s:
            lo = stream.cursor
            end = int(np.searchsorted(t, t[lo] + stream.due_s))
            rr = self._reference_run(stream, lo, end)
            if rr is None:
                if stream.due_s < MAX_STRETCH_S:
                    stream.due_s += STRETCH_S            # wait for more edges
                else:
                    self._drop_without_references(stream, end)
                t = stream.cols["t_s"]
                continue
            first = end - len(rr.run.time_s)        # the run is cut at its first edge
            last = int(rr.edges[-1])
            holds = tuple(h for h in rr.holds if h.stop <= last)   # after it: the next's
            rr = ReferenceRun(rr.run, rr.edges, rr.edge_mm, rr.switch, rr.rising, holds,
                              rr.edge_var_mm2)
            self._commit(stream)
            stream.pending = (self._rows(stream, rr), rr)
            stream.cursor = stream.carry_from(first + last)
            stream.drop(lo)                     # kept from the pending stretch's start
            t = stream.cols["t_s"]

    def _drop_without_references(self, stream: _Stream, end: int) -> None:
        """:data:`MAX_STRETCH_S` without a reference run: the window is dropped, but for an
        increment the last Hall change of its last :data:`STRETCH_S` may have started."""
        self._commit(stream)
        self._unit(stream).unused_stretches += 1
        lo = stream.cursor
        t, hall = stream.cols["t_s"], stream.cols["hall"][:end]
        changes = np.flatnonzero(hall[lo + 1:] != hall[lo:-1]) + lo + 1
        recent = changes[t[changes] >= t[end - 1] - STRETCH_S]
        stream.cursor = stream.carry_from(int(recent[-1])) if len(recent) else end
        stream.drop(stream.cursor)

    def _final(self, stream: _Stream) -> None:
        """The stream's samples as a last stretch (a gap, a new day, a stop). Too few edges
        after the pending stretch's last: that stretch again, to the end."""
        n = len(stream)
        if n > stream.cursor:
            rr = self._reference_run(stream, stream.cursor, n)
            if rr is not None:
                self._commit(stream)
                self._unit(stream).add(self._rows(stream, rr), rr)
            elif stream.pending is not None:
                rr = self._reference_run(stream, 0, n)
                if rr is not None:
                    stream.pending = (self._rows(stream, rr), rr)
            else:
                t = stream.cols["t_s"]
                if t[-1] - t[stream.cursor] >= STRETCH_S:
                    self._unit(stream).unused_stretches += 1
        self._commit(stream)
        stream.drop(n)
        stream.cursor = 0

    def _commit(self, stream: _Stream) -> None:
        if stream.pending is not None:
            self._unit(stream).add(*stream.pending)
            stream.pending = None

    def _reference_run(self, stream: _Stream, lo: int, hi: int) -> ReferenceRun | None:
        if hi - lo < 2:
            return None
        source = f"{self.machine} {stream.actuator} {stream.day}"
        try:
            return reference_run(self.cfg, stream.actuator, stream.run(lo, hi, source),
                                 model_speeds=False)
        except MeasuredDataError:
            return None

    def _rows(self, stream: _Stream, rr: ReferenceRun) -> list[dict]:
        return fit_log(self.cfg, rr, stream.actuator, lean=self.lean)

    def _unit(self, stream: _Stream) -> UnitDay:
        """The stream's unit in its day, about to change (the day to be written)."""
        assert stream.day is not None
        record = self._day(stream.day)
        record.dirty = True
        return record.unit(stream.actuator)

    # days

    def _day(self, day: str) -> Day:
        if day not in self.days:
            self.days[day] = self._load(day) if self.resume else Day(day)
        return self.days[day]

    def path(self, day: str) -> Path | None:
        return None if self.directory is None else \
            self.directory / summary_name(self.machine, day)

    def _load(self, day: str) -> Day:
        path = self.path(day)
        if path is None or not path.is_file():
            return Day(day)
        try:
            doc = read_summary(path.read_bytes(), path.name, self.cfg)
        except (OSError, SummaryError) as exc:
            self.notes.append(f"{path}: not gone on from ({exc}); the day starts afresh")
            return Day(day)
        if doc["machine"] != self.machine or doc["day"] != day or \
                doc["grids"] != {c: list(g) for c, g in GRIDS.items()}:
            self.notes.append(f"{path}: another machine's, day's or grid's; the day starts "
                              "afresh")
            return Day(day)
        record = Day(day, {a: UnitDay.from_json(u) for a, u in doc["units"].items()
                           if a in self.streams},
                     float(doc["first_s"]), float(doc["last_s"]))
        self.notes.append(f"{path}: the day goes on from it")
        return record

    def _retire_days(self) -> None:
        """A day every unit that had samples in it has left is complete: written, dropped."""
        for day in sorted(self.days):
            record = self.days[day]
            left = all(s.day is not None and s.day > day for a, s in self.streams.items()
                       if a in record.units)
            later = any(s.day is not None and s.day > _next_day(day)
                        for s in self.streams.values())
            if left or later:
                for stream in self.streams.values():
                    if stream.day == day:               # gone quiet in it: its last stretch
                        self._final(stream)
                record.complete, record.dirty = left, True
                self._write(record)
                del self.days[day]
                self._expire(day)

    def save(self) -> None:
        """Write every day that changed since it was last written."""
        self._saved_s = self.clock()
        for record in list(self.days.values()):
            if record.dirty:
                self._write(record)

    def close(self) -> None:
        """Every stream's samples as a last stretch, every day written (a stop)."""
        for stream in self.streams.values():
            self._final(stream)
        self.save()

    def document(self, record: Day) -> dict[str, Any]:
        return {"format": FORMAT, "version": VERSION, "machine": self.machine,
                "day": record.day, "physics_hash": self.physics_hash,
                "software": __version__, "complete": record.complete,
                "first_s": record.first_s, "last_s": record.last_s,
                "sample_s": SAMPLE_S, "stretch_s": STRETCH_S,
                "robust_mm": ROBUST_MM, "mode": FLEET_MODE,
                "grids": {c: list(g) for c, g in GRIDS.items()},
                "units": {a: u.to_json() for a, u in sorted(record.units.items())}}

    def _write(self, record: Day) -> None:
        record.dirty = False
        path = self.path(record.day)
        if path is None:
            return
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            remove_temp_files(path)
            with atomic_write(path) as fh:
                fh.write(json.dumps(self.document(record), separators=(",", ":")) + "\n")
        except OSError as exc:
            record.dirty = True
            self.notes.append(f"cannot write the day summary {path}: {exc}")
            return
        self.writes += 1
        if path not in self.written:
            self.written.append(path)

    def _expire(self, today: str) -> None:
        """Delete this machine's summaries more than ``keep_days`` before ``today``."""
        if self.directory is None or not self.directory.is_dir():
            return
        oldest = (dt.date.fromisoformat(today) - dt.timedelta(days=self.keep_days)).isoformat()
        for p in self.directory.glob(f"{self.machine}_*{SUFFIX}"):
            day = p.name[len(self.machine) + 1:-len(SUFFIX)]
            if len(day) == 10 and day < oldest:
                p.unlink(missing_ok=True)


def _next_day(day: str) -> str:
    return (dt.date.fromisoformat(day) + dt.timedelta(days=1)).isoformat()


def summarise_runs(cfg: Config, machine: str, runs: Iterable[Mapping[str, Run]],
                   directory: Path, lean: bool = False) -> list[Path]:
    """A machine's runs (every unit's, in time order, times on the wall clock) through the
    daemon's feed and day summaries; returns the files written (replacing any there)."""
    days = DaySummaries(cfg, machine, directory, lean=lean, resume=False,
                        save_interval_s=math.inf)
    feeds = {a: SampleFeed(list(cfg.unit(a).references_mm)) for a in cfg.can.units}
    for per_unit in runs:
        for actuator, run in per_unit.items():
            feed_run(feeds[actuator], run)
            days.feed(actuator, feeds[actuator].take())
    days.close()
    return days.written


# --- the file ---------------------------------------------------------------------------------


def _number(where: str, value: Any, lo: float = 0.0) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or \
            not math.isfinite(value) or value < lo:
        raise SummaryError(f"{where}: {value!r} is not a finite number >= {lo:g}")
    return float(value)


def _stats_ok(where: str, d: Any) -> None:
    if d is None:
        return
    if not isinstance(d, dict) or set(d) != {"min", "mean", "max", "n"}:
        raise SummaryError(f"{where}: expected min, mean, max, n")
    for k in ("min", "mean", "max"):
        _number(f"{where}.{k}", d[k], -math.inf)
    _number(f"{where}.n", d["n"], 1)


def read_summary(data: bytes, source: str, cfg: Config | None = None) -> dict[str, Any]:
    """A summary file's document, checked (SummaryError: one line); with ``cfg``, it must
    have been computed under that configuration's physics and units."""
    if len(data) > MAX_BYTES:
        raise SummaryError(f"{source}: {len(data)} bytes, more than a summary's "
                           f"{MAX_BYTES}")
    try:
        doc = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise SummaryError(f"{source}: not JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise SummaryError(f"{source}: not a {FORMAT}")
    if doc.get("version") != VERSION:
        raise SummaryError(f"{source}: {FORMAT} version {doc.get('version')!r}; this "
                           f"software reads version {VERSION}")
    try:
        _check(doc, source, cfg)
    except (KeyError, TypeError, AttributeError) as exc:
        raise SummaryError(f"{source}: incomplete ({type(exc).__name__}: {exc})") from None
    return doc


def _check(doc: dict[str, Any], source: str, cfg: Config | None) -> None:
    if not isinstance(doc["machine"], str) or not MACHINE_RE.fullmatch(doc["machine"]):
        raise SummaryError(f"{source}: machine {doc['machine']!r} is no machine name")
    try:
        dt.date.fromisoformat(doc["day"])
    except (TypeError, ValueError):
        raise SummaryError(f"{source}: day {doc['day']!r} is no date (YYYY-MM-DD)") from None
    for k in ("first_s", "last_s"):
        _number(f"{source}: {k}", doc[k])
    if cfg is not None and doc["physics_hash"] != cfg.physics_hash():
        raise SummaryError(f"{source}: computed under another configuration (physics hash "
                           f"{str(doc['physics_hash'])[:12]}, this one's "
                           f"{cfg.physics_hash()[:12]})")
    grids = doc["grids"]
    if not isinstance(grids, dict) or not grids:
        raise SummaryError(f"{source}: no grids")
    for cause, grid in grids.items():
        if cause not in GRIDS:
            raise SummaryError(f"{source}: unknown cause {cause!r}")
        values = [_number(f"{source}: grid of {cause}", v, -math.inf) for v in grid]
        if len(values) < 3 or any(b <= a for a, b in zip(values, values[1:])):
            raise SummaryError(f"{source}: the grid of {cause} is not increasing (3 values "
                               "at least)")
    units = doc["units"]
    if not isinstance(units, dict) or not units:
        raise SummaryError(f"{source}: no units")
    for actuator, u in units.items():
        where = f"{source}: unit {actuator}"
        if cfg is not None and actuator not in cfg.can.units:
            raise SummaryError(f"{where}: not a unit of this configuration "
                               f"({', '.join(cfg.can.units)})")
        for k in ("stretches", "unused_stretches", "increments", "holds", "n_obs"):
            if not isinstance(u[k], int) or isinstance(u[k], bool) or u[k] < 0:
                raise SummaryError(f"{where}: {k} {u[k]!r} is no count")
        if u["n_obs"] < u["increments"]:
            raise SummaryError(f"{where}: fewer observations than increments")
        for k in ("work_s", "analysed_s", "loss_nominal", "max_increment_sum_mm",
                  "max_increment_day_mm"):
            _number(f"{where}: {k}", u[k])
        _stats_ok(f"{where}: oil_c", u["oil_c"])
        _stats_ok(f"{where}: hold_torque_nm", u["hold_torque_nm"])
        if set(u["causes"]) != set(grids):
            raise SummaryError(f"{where}: causes {sorted(u['causes'])} differ from the grids'")
        for cause, arrays in u["causes"].items():
            for k in ("loss", "emax_sum_mm", "emax_day_mm"):
                values = arrays[k]
                if not isinstance(values, list) or len(values) != len(grids[cause]):
                    raise SummaryError(f"{where}: {cause} {k}: {len(grids[cause])} values "
                                       "expected, one per grid value")
                for v in values:
                    _number(f"{where}: {cause} {k}", v)


def summary_rows(doc: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The analysis' rows of a summary: per unit and cause, as :func:`.evidence.fit_log`
    gives them for a log, the largest changes a stretch's (their mean: see the module's
    docstring); units without an observation give none."""
    out = []
    for actuator, u in doc["units"].items():
        if not u["n_obs"] or not u["stretches"]:
            continue
        n = u["stretches"]
        for cause, arrays in u["causes"].items():
            out.append({"actuator": actuator, "cause": cause,
                        "grid": [float(v) for v in doc["grids"][cause]],
                        "loss": [float(v) for v in arrays["loss"]],
                        "emax_mm": [float(v) / n for v in arrays["emax_sum_mm"]],
                        "n_obs": u["n_obs"], "n_increments": u["increments"],
                        "loss_nominal": float(u["loss_nominal"]),
                        "max_increment_mm": float(u["max_increment_sum_mm"]) / n})
    return out
