"""A machine's health from its own day summaries: per unit the catalogued cause its recent
days point to, the parameter with its interval, the expected position error at the
references now and at the horizon, and the days until that error passes the tolerance.

The daemon's summary worker computes it whenever it writes a day (and the service publishes
it on the bus); ``status --health`` reads it. It is the fleet's trend (:mod:`.trend`) on the
machine's own days, so a machine and the fleet report agree. Only day summaries feed it:
they hold reference increments and holds, never a preset or a stretch without references.

File: ``<state_dir>/health.json`` (:data:`FILE`), written atomically, read at start.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from ddh_vsensor.atomic import atomic_write
from ddh_vsensor.config import Config
from ddh_vsensor.diagnosis.causes import ALL_CAUSES, CAUSE_NAMES
from ddh_vsensor.diagnosis.day_summary import read_summary, summary_rows
from ddh_vsensor.diagnosis.finding import unit_finding
from ddh_vsensor.diagnosis.trend import DAY_S, MIN_LOGS, WINDOW, UnitTrend, from_u, unit_trend
from ddh_vsensor.estimator.day_samples import SUFFIX, SummaryError

FILE = "health.json"
FORMAT = "ddh-vsensor health"
VERSION = 1
# the days of summaries a health looks at: the trend's window and the days it needs first
DAYS_READ = WINDOW + MIN_LOGS


@dataclass(frozen=True)
class UnitHealth:
    """One unit's health as of its newest day of evidence."""

    actuator: str
    days: int                           # days with observations the trend looked at
    cause: str                          # a catalogued cause, or "none"
    parameter: str | None = None        # the cause's parameter key
    value: float | None = None
    interval: tuple[float, float] | None = None     # 90 % on the newest day
    error_now_mm: float | None = None   # expected change of an increment at the references
    error_projected_mm: float | None = None         # ... at the horizon
    days_to_tolerance: float | None = None          # None: not within the horizon
    alarm: bool = False                 # the tolerance is passed within the horizon
    last_day_s: float | None = None     # wall time of the newest day's first sample
    finding: str = ""                   # in words (:mod:`.finding`)

    @property
    def cause_code(self) -> int:
        """The cause's number on the bus (:data:`diagnosis.causes.CAUSE_NAMES`; 0 none)."""
        return CAUSE_NAMES.index(self.cause)

    @property
    def days_needed(self) -> int:
        """Days of evidence still missing before a cause can be named (0: enough)."""
        return max(MIN_LOGS - self.days, 0)


def unit_health(trend: UnitTrend, tolerance_mm: float, horizon_days: float,
                sources: Mapping[str, str] | None = None) -> UnitHealth:
    """The newest entry of a unit's trend (``sources``: as :func:`.finding.unit_finding`)."""
    days = len(trend.times_s)
    words = unit_finding(trend, tolerance_mm, horizon_days, sources=sources).text
    if not days:
        return UnitHealth(trend.actuator, 0, "none", finding=words)
    cause, alarm = trend.named[-1], trend.alarms[-1]
    last = trend.times_s[-1]
    if cause == "none":
        return UnitHealth(trend.actuator, days, "none", last_day_s=last, finding=words)
    fit = trend.series[cause][-1]
    crossing = None
    if alarm is not None and alarm.crossing_time_s is not None:
        crossing = max((alarm.crossing_time_s - last) / DAY_S, 0.0)
    return UnitHealth(
        trend.actuator, days, cause, ALL_CAUSES[cause].parameter,
        float(from_u(cause, fit.u)),
        (float(from_u(cause, fit.lo_u)), float(from_u(cause, fit.hi_u))),
        _finite(trend.error_now_mm[-1]), _finite(trend.error_projected_mm[-1]), crossing,
        alarm is not None, last, words)


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def summary_files(directory: Path, machine: str, days: int = DAYS_READ) -> list[Path]:
    """The machine's newest ``days`` day summaries in ``directory`` (by the day in the name)."""
    paths = sorted(p for p in Path(directory).glob(f"{machine}_*{SUFFIX}")
                   if len(p.name) == len(machine) + 1 + 10 + len(SUFFIX))
    return paths[-days:]


def machine_health(cfg: Config, machine: str, docs: Sequence[Mapping[str, Any]]
                   ) -> dict[str, UnitHealth]:
    """Every unit's health from a machine's day summaries (read, any order)."""
    rows: dict[str, list[dict]] = {a: [] for a in cfg.can.units}
    for doc in docs:
        for r in summary_rows(doc):
            if r["actuator"] in rows:
                rows[r["actuator"]].append({**r, "time_s": float(doc["first_s"]),
                                            "log_id": str(doc["day"])})
    tolerance_mm, horizon_days = cfg.health.tolerance_mm, cfg.health.horizon_days
    sources = {str(doc["day"]): "summary" for doc in docs}
    return {a: unit_health(unit_trend(machine, a, r, tolerance_mm, horizon_days), tolerance_mm,
                           horizon_days, sources)
            for a, r in rows.items()}


def read_days(cfg: Config, paths: Sequence[Path]) -> tuple[list[dict[str, Any]], list[str]]:
    """The summaries that can be read, and a note for each that cannot."""
    docs, notes = [], []
    for p in paths:
        try:
            docs.append(read_summary(p.read_bytes(), p.name, cfg))
        except (OSError, SummaryError) as exc:
            notes.append(f"{p}: left out of the health ({exc})")
    return docs, notes


def document(cfg: Config, machine: str, health: Mapping[str, UnitHealth]) -> dict[str, Any]:
    """The health file's content."""
    return {"format": FORMAT, "version": VERSION, "machine": machine,
            "tolerance_mm": cfg.health.tolerance_mm, "horizon_days": cfg.health.horizon_days,
            "units": {a: {**asdict(h), "cause_code": h.cause_code, "days_needed": h.days_needed}
                      for a, h in sorted(health.items())}}


def write_health(path: Path, doc: Mapping[str, Any]) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as fh:
        fh.write(json.dumps(doc, indent=1) + "\n")


def refresh(cfg: Config, machine: str, summaries: Path, path: Path
            ) -> tuple[dict[str, Any], list[str]]:
    """The machine's health from its newest summaries in ``summaries``, written to ``path``;
    the file's content and a note per summary left out."""
    docs, notes = read_days(cfg, summary_files(summaries, machine))
    doc = document(cfg, machine, machine_health(cfg, machine, docs))
    write_health(path, doc)
    return doc, notes


def read_health(path: Path) -> dict[str, UnitHealth]:
    """The units' health as last written; a file that is not one raises ValueError."""
    doc = json.loads(Path(path).read_text(encoding="utf-8"))
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or \
            doc.get("version") != VERSION or not isinstance(doc.get("units"), dict):
        raise ValueError(f"{path}: not a {FORMAT} file of version {VERSION}")
    out = {}
    for actuator, u in doc["units"].items():
        try:
            u = {k: v for k, v in u.items() if k not in ("cause_code", "days_needed")}
            if u.get("interval") is not None:
                u["interval"] = tuple(u["interval"])
            health = UnitHealth(**u)
            if health.cause not in CAUSE_NAMES:
                raise ValueError(f"unknown cause {health.cause!r}")
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: unit {actuator!r}: {exc}") from None
        out[actuator] = health
    return out
