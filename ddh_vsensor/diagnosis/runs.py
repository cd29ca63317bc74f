"""Measured runs as the diagnosis needs them: validated, named, starting at a known position.

Reading is the project's own (``io.csv.read_csv``, ``io.log.read_can_log``); this adds
what a diagnosis needs on top: a reference position to compare with, and enough of it to say
anything. Every problem names the file and, where one row is at fault, its line.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ddh_vsensor.config import Config
from ddh_vsensor.measured import MeasuredDataError, Run
from ddh_vsensor.io.csv import read_csv

MIN_DURATION_S = 2.0            # shorter runs cannot separate creep from noise
MIN_POSITION_SAMPLES = 20       # reference positions needed to score an estimate
MIN_TRAVEL_MM = 5.0             # or the rod must move at least this far (else: holding only)
MIN_HOLD_S = 10.0               # a run without travel must at least hold this long


@dataclass(frozen=True, eq=False)
class AnalysisRun:
    """One run cut to start at its first reference position (the estimate starts there)."""

    name: str
    time_s: np.ndarray
    speed_rpm: np.ndarray
    torque_nm: np.ndarray
    oil_temp_c: np.ndarray
    position_mm: np.ndarray          # reference (draw-wire), NaN where not sampled
    p_a_bar: np.ndarray | None = None
    p_b_bar: np.ndarray | None = None

    @property
    def mask(self) -> np.ndarray:
        """Samples with a reference position."""
        return np.isfinite(self.position_mm)

    @property
    def initial_position_mm(self) -> float:
        return float(self.position_mm[0])

    @property
    def duration_s(self) -> float:
        return float(self.time_s[-1] - self.time_s[0])

    def __len__(self) -> int:
        return len(self.time_s)


def _data_lines(path: str) -> list[int] | None:
    """File line number of each data row of a CSV (for messages), None if unreadable."""
    try:
        with open(path, encoding="utf-8-sig", newline="") as f:
            lines = f.read().splitlines()
    except (OSError, UnicodeDecodeError):
        return None
    i = 0
    while i < len(lines) and (not lines[i].strip() or lines[i].startswith("#")):
        i += 1
    return [k + 1 for k in range(i + 1, len(lines)) if lines[k].strip()]


def prepare_run(run: Run, lines: list[int] | None = None) -> AnalysisRun:
    """Check a run is usable for diagnosis; ``lines`` maps rows to file lines for messages."""
    source = run.source

    def line(row: int) -> int | None:
        return lines[row] if lines is not None and 0 <= row < len(lines) else None

    known = np.flatnonzero(np.isfinite(run.position_mm))
    if known.size == 0:
        raise MeasuredDataError(source, "position_mm is never given (the diagnosis compares "
                                "the estimate with the reference position)")
    for name in ("speed_rpm", "torque_nm", "oil_temp_c", "time_s"):
        column = getattr(run, name)
        bad = ~np.isfinite(column)
        if bad.any():
            row = int(np.argmax(bad))
            raise MeasuredDataError(source, f"column {name!r}: missing value", line(row))
    step = np.diff(run.time_s)
    if (step <= 0.0).any():
        row = int(np.argmax(step <= 0.0)) + 1
        raise MeasuredDataError(source, f"time_s does not increase ({run.time_s[row - 1]!r} "
                                f"then {run.time_s[row]!r})", line(row))
    first = int(known[0])
    t = run.time_s[first:]
    x = run.position_mm[first:]
    duration = float(t[-1] - t[0]) if len(t) else 0.0
    sampled = int(np.isfinite(x).sum())
    travel = float(np.nanmax(x) - np.nanmin(x))
    last = len(run.time_s) - 1
    if duration < MIN_DURATION_S or sampled < MIN_POSITION_SAMPLES:
        raise MeasuredDataError(source, f"too short to diagnose: {duration:.2f} s and "
                                f"{sampled} reference position(s) from the first one (row "
                                f"{first + 1}) to the end; at least {MIN_DURATION_S:g} s and "
                                f"{MIN_POSITION_SAMPLES} positions are needed", line(last))
    if travel < MIN_TRAVEL_MM and duration < MIN_HOLD_S:
        raise MeasuredDataError(source, f"too short to diagnose: the rod moves {travel:.2f} mm "
                                f"in {duration:.2f} s; a run must travel at least "
                                f"{MIN_TRAVEL_MM:g} mm or hold for {MIN_HOLD_S:g} s",
                                line(last))

    def cut(a: np.ndarray | None) -> np.ndarray | None:
        return None if a is None else np.asarray(a[first:], dtype=float)

    return AnalysisRun(name=source, time_s=cut(run.time_s), speed_rpm=cut(run.speed_rpm),
                       torque_nm=cut(run.torque_nm), oil_temp_c=cut(run.oil_temp_c),
                       position_mm=cut(run.position_mm), p_a_bar=cut(run.p_a_bar),
                       p_b_bar=cut(run.p_b_bar))


def load_analysis_run(path: str | Path, actuator: str, cfg: Config) -> AnalysisRun:
    """A CSV of the measured-data format or a CAN log, checked for diagnosis; a CSV whose
    ``# actuator:`` line names another unit is refused. ``name`` is the path as given: the
    report titles the run by it."""
    path = str(path)
    if path.lower().endswith(".csv"):
        run = read_csv(path, require_position=True, actuator=actuator)
        return prepare_run(run, _data_lines(path))
    from ddh_vsensor.io.log import read_can_log
    return prepare_run(read_can_log(path, actuator, cfg))
