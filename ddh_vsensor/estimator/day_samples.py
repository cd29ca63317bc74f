"""The lean half of the daemon's day summary (:mod:`ddh_vsensor.diagnosis.day_summary`): the
samples it is made of, as the daemon's loop takes them per Sevcon frame, and its files'
names. Here, below the diagnosis, so that the daemon's own process imports no more than
numpy for it (the analysis runs in a worker process).

The samples are kept at the loggers' period, :data:`SAMPLE_S` (the fleet's log analysis was
judged on such logs), plus the two around every Hall change: the edge's own sample, as the
full-rate input gives it, so that its position is as exact as the estimator's own.
"""

from __future__ import annotations

import datetime as dt
import math
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ddh_vsensor.measured import Run

SAMPLE_S = 0.01
SUFFIX = ".summary.json"
SAVE_INTERVAL_S = 300.0       # the partial day written this often (a kill loses less)
MACHINE_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")


class SummaryError(ValueError):
    """A summary file that cannot be taken: one line saying why."""


def day_of(wall_s: float) -> str:
    """The UTC date of a wall-clock time (s since 1970)."""
    return dt.datetime.fromtimestamp(wall_s, dt.timezone.utc).date().isoformat()


def summary_name(machine: str, day: str) -> str:
    return f"{machine}_{day}{SUFFIX}"


def machine_name(name: str) -> str:
    """A machine's name as a summary carries it (also its file name's first part)."""
    if not MACHINE_RE.fullmatch(name):
        raise SummaryError(f"machine name {name!r}: 1-64 of A-Z a-z 0-9 . _ -, starting with "
                           "a letter or digit")
    return name


@dataclass
class Block:
    """A unit's kept samples, in time order (frame clock), and how far the wall clock is
    ahead of that clock."""

    t_s: np.ndarray
    speed_rpm: np.ndarray
    torque_nm: np.ndarray
    oil_temp_c: np.ndarray
    hall: np.ndarray             # bit i: the unit's i-th reference switch (config order)
    change_s: np.ndarray         # where the Hall bits changed: the change's own time, or NaN
    wall_offset_s: float = 0.0

    def __len__(self) -> int:
        return len(self.t_s)


class SampleFeed:
    """One unit's samples as they come (the daemon: per Sevcon frame, a few hundred ns), kept
    one per :data:`SAMPLE_S` and around every Hall change, until :meth:`take`."""

    def __init__(self, switches: Sequence[str], sample_s: float = SAMPLE_S) -> None:
        self.switches = tuple(switches)
        # 5 % short: the inputs' own jitter, or the rounding of a wall-clock time (0.24 us
        # at 2026's), never drops a sample of a logger-rate input
        self._step_s = 0.95 * sample_s
        self._cols: tuple[list[float], ...] = ([], [], [], [], [], [])
        self._t_kept = -math.inf
        self._bits: int | None = None
        self._prev: tuple | None = None           # the last sample, when not kept
        self._refs: object = None
        self._refs_bits = 0
        self.wall_offset_s = 0.0
        self.samples = 0

    def add(self, t_s: float, speed_rpm: float, torque_nm: float, oil_temp_c: float,
            refs: Mapping[str, bool] | None, change_s: float = math.nan,
            wall_s: float | None = None) -> None:
        """A sample with the Hall states by name (the daemon's mapping: recomputed only when
        a new one comes) and, where it is known, the time since which they hold."""
        if refs is not self._refs:
            self._refs = refs
            bits = 0
            if refs:
                for i, name in enumerate(self.switches):
                    if refs.get(name):
                        bits |= 1 << i
            self._refs_bits = bits
        self.add_bits(t_s, speed_rpm, torque_nm, oil_temp_c, self._refs_bits, change_s, wall_s)

    def add_bits(self, t_s: float, speed_rpm: float, torque_nm: float, oil_temp_c: float,
                 bits: int, change_s: float = math.nan, wall_s: float | None = None) -> None:
        self.samples += 1
        if bits != self._bits:
            if self._bits is None:
                change_s = math.nan               # the first state is no change
            elif self._prev is not None:          # the edge's sample starts where this ends
                self._keep(*self._prev, math.nan)
            self._bits = bits
            self._keep(t_s, speed_rpm, torque_nm, oil_temp_c, bits, change_s)
            if wall_s is not None:
                self.wall_offset_s = wall_s - t_s
        elif t_s - self._t_kept >= self._step_s:
            self._keep(t_s, speed_rpm, torque_nm, oil_temp_c, bits, math.nan)
            if wall_s is not None:
                self.wall_offset_s = wall_s - t_s
        else:
            self._prev = (t_s, speed_rpm, torque_nm, oil_temp_c, bits)

    def _keep(self, t_s: float, speed_rpm: float, torque_nm: float, oil_temp_c: float,
              bits: int, change_s: float) -> None:
        t, n, q, c, h, e = self._cols
        t.append(t_s)
        n.append(speed_rpm)
        q.append(torque_nm)
        c.append(oil_temp_c)
        h.append(bits)
        e.append(change_s)
        self._t_kept = t_s
        self._prev = None

    @property
    def kept(self) -> int:
        return len(self._cols[0])

    def pending_s(self) -> float:
        t = self._cols[0]
        return t[-1] - t[0] if t else 0.0

    def take(self) -> Block | None:
        """The samples kept since the last take (None: none)."""
        if not self._cols[0]:
            return None
        t, n, q, c, h, e = self._cols
        block = Block(np.array(t), np.array(n), np.array(q), np.array(c),
                      np.array(h, dtype=np.uint8), np.array(e), self.wall_offset_s)
        self._cols = ([], [], [], [], [], [])
        return block


def run_samples(switches: Sequence[str], run: Run) -> Iterator[tuple]:
    """A run's samples as the daemon hands them to a feed (:meth:`SampleFeed.add_bits`)."""
    hall = np.zeros(len(run.time_s), np.int64)
    change = np.full(len(run.time_s), np.nan)
    for i, name in enumerate(switches):
        if name in run.refs:
            hall |= run.refs[name].astype(np.int64) << i
        if name in run.ref_edge_s:
            timed = np.isfinite(run.ref_edge_s[name])
            change[timed] = run.ref_edge_s[name][timed]
    return zip(run.time_s.tolist(), run.speed_rpm.tolist(), run.torque_nm.tolist(),
               run.oil_temp_c.tolist(), hall.tolist(), change.tolist())


def feed_run(feed: SampleFeed, run: Run) -> None:
    """A whole run through a feed, sample by sample (as the daemon gets them); its times are
    the wall clock's."""
    for t, n, q, c, h, e in run_samples(feed.switches, run):
        feed.add_bits(t, n, q, c, h, e, t)
