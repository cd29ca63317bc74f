"""A machine's baseline: the commissioned model's own error on runs it was not fitted to.

The diagnosis (``analyze --baseline``) judges every threshold that stands for "the model's own
error" against it, per unit and per kind of evidence, instead of the simulator's constants
(where the nominal model is nearly exact). The residuals are those the diagnosis itself scores:

- ``position``: the estimate without references from the draw-wire's first position, minus
  the draw-wire, in segments of :data:`POSITION_SEGMENT_S` (an open-loop error grows with the
  run's length, so the baseline's runs are cut to about an analysed run's);
- ``references``: the estimate's increment from one accepted Hall edge to the next minus the
  switches' distance (:meth:`ddh_vsensor.diagnosis.references.ReferenceRun.observe`);
- ``holds``: the estimate's creep over each hold away from the stroke ends, in mm per
  :data:`ddh_vsensor.diagnosis.references.HOLD_WEIGHT_S`;
- ``pressures`` (where the runs log the chamber pressures): the drive's torque against the
  pressures' torque, the line :mod:`ddh_vsensor.diagnosis.pressures` fits, per position
  segment: its median and spread (a drive's own torque estimate is not the physics').

Held out: every run's residuals come from the model fitted without it (``commission`` refits
the switches and the flow model leaving one run file out at a time), so the baseline states
what the model errs by on work it has not seen, a little more than the configuration fitted
on every run does.

The file is JSON (:data:`FORMAT`, :data:`FORMAT_VERSION`), written atomically; docs:
``docs/commission.md``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from ddh_vsensor.atomic import atomic_write
from ddh_vsensor.config import Config
from ddh_vsensor.diagnosis.pressures import (GAIN_TOLERANCE, OFFSET_TOLERANCE_NM, OwnLine,
                                             run_lines)
from ddh_vsensor.diagnosis.references import reference_run
from ddh_vsensor.diagnosis.runs import AnalysisRun, prepare_run
from ddh_vsensor.diagnosis.selection import OWN_SPREAD, OwnError, rms
from ddh_vsensor.diagnosis.workbench import Workbench, resolve_mode
from ddh_vsensor.errors import UserError
from ddh_vsensor.measured import MeasuredDataError, Run

FORMAT = "ddh-vsensor baseline"
FORMAT_VERSION = 1
KINDS = ("position", "references", "holds")
# An analysed run is typically a work cycle or a log of a minute or so; the position error
# without references grows with the time since the start, so the baseline's runs (a
# calibration run is several minutes) are scored in segments about that long.
POSITION_SEGMENT_S = 60.0
PERCENTILE = 95.0
LEAVE_ONE_OUT = ("leave-one-run-out: each run file's residuals are those of the model "
                 "commissioned on the other run files")
NOT_FITTED = "not fitted: the configuration was not fitted to these runs"


@dataclass(frozen=True)
class Residuals:
    """One kind of evidence of one unit: the residuals' RMS and high percentile (mm)."""

    rms_mm: float
    p95_mm: float
    count: int                      # samples, increments or holds
    run_rms_mm: dict[str, float] = field(default_factory=dict)   # per held-out run file

    def as_dict(self) -> dict[str, Any]:
        return {"rms_mm": round(self.rms_mm, 4), "p95_mm": round(self.p95_mm, 4),
                "count": self.count,
                "run_rms_mm": {k: round(v, 4) for k, v in self.run_rms_mm.items()}}


@dataclass(frozen=True)
class PressureLine:
    """The drive's torque against the pressures' torque without any effect: the median of
    the segments' lines and their spread (log of the gain; N*m)."""

    gain: float
    offset_nm: float
    gain_sd: float
    offset_sd_nm: float
    count: int                      # segments with a line

    def as_dict(self) -> dict[str, Any]:
        return {"gain": round(self.gain, 5), "offset_nm": round(self.offset_nm, 4),
                "gain_sd": round(self.gain_sd, 5), "offset_sd_nm": round(self.offset_sd_nm, 4),
                "count": self.count}

    def own_line(self) -> OwnLine:
        """The tolerances it sets: OWN_SPREAD x a segment's spread, never below the
        simulator's."""
        return OwnLine(self.gain, self.offset_nm, max(GAIN_TOLERANCE, OWN_SPREAD * self.gain_sd),
                       max(OFFSET_TOLERANCE_NM, OWN_SPREAD * self.offset_sd_nm))


@dataclass(frozen=True)
class UnitBaseline:
    unit: str
    kinds: dict[str, Residuals]     # of KINDS; a kind the runs did not have is absent
    pressures: PressureLine | None = None

    def own_error(self, source: str) -> OwnError:
        """What the diagnosis takes from it: each kind's RMS, the pressures' line."""
        def get(kind: str) -> float | None:
            r = self.kinds.get(kind)
            return None if r is None else r.rms_mm
        return OwnError(get("position"), get("references"), get("holds"), source,
                        None if self.pressures is None else self.pressures.own_line())


@dataclass(frozen=True)
class Baseline:
    config_hash: str                # the commissioned configuration's estimate hash
    mode: str                       # the estimator mode the residuals are of
    created: str                    # ISO 8601, UTC
    held_out: str                   # how the runs were held out
    runs: tuple[str, ...]
    units: dict[str, UnitBaseline]
    position_segment_s: float = POSITION_SEGMENT_S

    def as_dict(self) -> dict[str, Any]:
        return {"format": FORMAT, "format_version": FORMAT_VERSION,
                "config_hash": self.config_hash, "mode": self.mode, "created": self.created,
                "held_out": self.held_out, "runs": list(self.runs),
                "position_segment_s": self.position_segment_s, "percentile": PERCENTILE,
                "units": {u: {**{k: (b.kinds[k].as_dict() if k in b.kinds else None)
                                 for k in KINDS},
                              "pressures": None if b.pressures is None
                              else b.pressures.as_dict()}
                          for u, b in self.units.items()}}

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        with atomic_write(path) as fh:
            json.dump(self.as_dict(), fh, indent=1)
            fh.write("\n")
        return path


# --- residuals -------------------------------------------------------------------------------


@dataclass
class _Pooled:
    """One kind's residuals, gathered over held-out runs (weights as the diagnosis's)."""

    residuals: list[np.ndarray] = field(default_factory=list)
    weights: list[float] = field(default_factory=list)
    sources: list[str] = field(default_factory=list)

    def add(self, source: str, residuals: Sequence[np.ndarray],
            weights: Sequence[float]) -> None:
        for r, w in zip(residuals, weights):
            if len(r):
                self.residuals.append(np.asarray(r, dtype=float))
                self.weights.append(float(w))
                self.sources.append(source)

    def summary(self) -> Residuals | None:
        if not self.residuals:
            return None
        every = np.concatenate(self.residuals)
        per_run = {s: rms([r for r, t in zip(self.residuals, self.sources) if t == s],
                          [w for w, t in zip(self.weights, self.sources) if t == s])
                   for s in dict.fromkeys(self.sources)}
        return Residuals(rms(self.residuals, self.weights),
                         float(np.percentile(np.abs(every), PERCENTILE)), len(every), per_run)


def segments(run: AnalysisRun, segment_s: float = POSITION_SEGMENT_S) -> list[AnalysisRun]:
    """The run in about equal parts of about ``segment_s`` (at least one), each starting at a
    draw-wire sample: each is estimated afresh from there, as an analysed run is."""
    parts = max(1, round(run.duration_s / segment_s))
    known = np.flatnonzero(run.mask)
    bounds = run.time_s[0] + run.duration_s * np.arange(parts) / parts
    starts = sorted({int(known[min(np.searchsorted(run.time_s[known], b), len(known) - 1)])
                     for b in bounds})
    out = []
    for a, b in zip(starts, starts[1:] + [len(run.time_s)]):
        if b - a < 2:
            continue
        part = slice(a, b)
        out.append(AnalysisRun(
            f"{run.name}@{run.time_s[a] - run.time_s[0]:.0f}s",
            *(x[part] for x in (run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c,
                                run.position_mm)),
            *(None if x is None else x[part] for x in (run.p_a_bar, run.p_b_bar))))
    return out


def _position(cfg: Config, unit: str, runs: Sequence[Run], mode: str, pooled: _Pooled,
              lines: list[tuple[float, float]], segment_s: float) -> None:
    for run in runs:
        try:
            parts = segments(prepare_run(run), segment_s)
        except MeasuredDataError:
            continue                    # too short to score, as the diagnosis would refuse it
        bench = Workbench(cfg, unit, parts, mode)
        pooled.add(run.source, [(x - r.position_mm)[r.mask] for x, r in zip(bench.base, parts)],
                   [r.duration_s / max(int(r.mask.sum()), 1) for r in parts])
        lines += [(g, o) for _, g, o in run_lines(bench)]


def _line(lines: Sequence[tuple[float, float]]) -> PressureLine | None:
    """The segments' lines summed up (None below two: no spread)."""
    if len(lines) < 2:
        return None
    g, o = np.array(lines).T
    return PressureLine(float(np.median(g)), float(np.median(o)),
                        float(np.std(np.log(g), ddof=1)), float(np.std(o, ddof=1)), len(g))


def _references(cfg: Config, unit: str, runs: Sequence[Run], mode: str, refs: _Pooled,
                holds: _Pooled) -> None:
    for run in runs:
        try:
            rr = reference_run(cfg, unit, run)
        except MeasuredDataError:
            continue                    # too few edges: the run has no references to score
        bench = Workbench(cfg, unit, [rr.run], mode)
        obs = rr.observe(bench.base[0])
        refs.add(run.source, [obs[:rr.n_increments]], [1.0])
        holds.add(run.source, [obs[rr.n_increments:]], [1.0])


Fold = tuple[Config, Mapping[str, Sequence[Run]]]


def measure(folds: Iterable[Fold], config_hash: str, held_out: str, runs: Sequence[str],
            mode: str, segment_s: float = POSITION_SEGMENT_S,
            progress: Callable[[str], None] | None = None) -> Baseline:
    """The baseline from ``folds``: each a configuration and, per unit, the runs it was not
    fitted to (every run of a unit in exactly one fold)."""
    pooled: dict[str, dict[str, _Pooled]] = {}
    lines: dict[str, list[tuple[float, float]]] = {}
    for cfg, held in folds:
        if progress is not None:
            progress(", ".join(dict.fromkeys(Path(r.source).name for rs in held.values()
                                             for r in rs)))
        for unit, unit_runs in held.items():
            p = pooled.setdefault(unit, {k: _Pooled() for k in KINDS})
            _position(cfg, unit, unit_runs, mode, p["position"], lines.setdefault(unit, []),
                      segment_s)
            _references(cfg, unit, unit_runs, mode, p["references"], p["holds"])
    units = {u: UnitBaseline(u, {k: s for k, v in p.items() if (s := v.summary()) is not None},
                             _line(lines[u]))
             for u, p in pooled.items()}
    created = datetime.now(timezone.utc).isoformat(timespec="seconds")
    return Baseline(config_hash, mode, created, held_out, tuple(runs), units, segment_s)


def measure_fixed(cfg: Config, runs: Mapping[str, Sequence[Run]], mode: str | None = None,
                  segment_s: float = POSITION_SEGMENT_S) -> Baseline:
    """The baseline of a configuration not fitted to ``runs`` (every run is held out)."""
    names = list(dict.fromkeys(r.source for rs in runs.values() for r in rs))
    return measure([(cfg, runs)], cfg.estimate_hash(), NOT_FITTED, names,
                   resolve_mode(cfg, mode), segment_s)


def leave_one_out(runs: Mapping[str, Sequence[Run]],
                  fit: Callable[[dict[str, list[Run]]], Config]) -> Iterable[Fold]:
    """Folds leaving one run file (a CAN log holds every unit's run) out at a time: the
    configuration ``fit`` makes of the others, and the runs left out. A unit with no other
    run in a fold is left out of it (nothing to fit it on)."""
    sources = list(dict.fromkeys(r.source for rs in runs.values() for r in rs))
    for source in sources:
        rest = {u: [r for r in rs if r.source != source] for u, rs in runs.items()}
        held = {u: [r for r in rs if r.source == source] for u, rs in runs.items()}
        held = {u: rs for u, rs in held.items() if rs and rest[u]}
        if held:
            yield fit({u: rs for u, rs in rest.items() if rs}), held


# --- the file --------------------------------------------------------------------------------


def _number(data: Mapping[str, Any], key: str, where: str) -> float:
    value = data.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value) or value < 0:
        raise ValueError(f"{where}.{key} must be a number >= 0, not {value!r}")
    return float(value)


def _residuals(data: Any, where: str) -> Residuals | None:
    if data is None:
        return None
    if not isinstance(data, dict):
        raise ValueError(f"{where} must be an object or null")
    per_run = data.get("run_rms_mm", {})
    if not isinstance(per_run, dict):
        raise ValueError(f"{where}.run_rms_mm must be an object")
    return Residuals(_number(data, "rms_mm", where), _number(data, "p95_mm", where),
                     int(_number(data, "count", where)),
                     {str(k): _number(per_run, k, f"{where}.run_rms_mm") for k in per_run})


def _pressures(data: Any, where: str) -> PressureLine | None:
    if data is None:
        return None
    if not isinstance(data, dict):
        raise ValueError(f"{where} must be an object or null")
    gain = _number(data, "gain", where)
    if gain <= 0:
        raise ValueError(f"{where}.gain must be above 0")
    offset = data.get("offset_nm")
    if isinstance(offset, bool) or not isinstance(offset, (int, float)) \
            or not math.isfinite(offset):
        raise ValueError(f"{where}.offset_nm must be a number, not {offset!r}")
    return PressureLine(gain, float(offset), _number(data, "gain_sd", where),
                        _number(data, "offset_sd_nm", where), int(_number(data, "count", where)))


def parse(data: Any) -> Baseline:
    """A baseline from its JSON document; ValueError saying what is wrong."""
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ValueError(f"not a baseline file (no \"format\": \"{FORMAT}\")")
    version = data.get("format_version")
    if version != FORMAT_VERSION:
        raise ValueError(f"baseline format version {version!r}; this ddh-vsensor reads "
                         f"version {FORMAT_VERSION}: commission the machine again")
    for key in ("config_hash", "mode", "created", "held_out"):
        if not isinstance(data.get(key), str):
            raise ValueError(f"{key} must be a string")
    units = data.get("units")
    runs = data.get("runs")
    if not isinstance(units, dict) or not isinstance(runs, list):
        raise ValueError("units must be an object and runs a list")
    out = {}
    for unit, kinds in units.items():
        if not isinstance(kinds, dict):
            raise ValueError(f"units.{unit} must be an object")
        found = {k: r for k in KINDS
                 if (r := _residuals(kinds.get(k), f"units.{unit}.{k}")) is not None}
        line = _pressures(kinds.get("pressures"), f"units.{unit}.pressures")
        out[str(unit)] = UnitBaseline(str(unit), found, line)
    return Baseline(data["config_hash"], data["mode"], data["created"], data["held_out"],
                    tuple(map(str, runs)), out,
                    _number(data, "position_segment_s", "") if "position_segment_s" in data
                    else POSITION_SEGMENT_S)


def read(path: str | Path) -> Baseline:
    """The baseline file at ``path``; UserError (one line) when it cannot be read as one."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise UserError(f"{path}: no such baseline file (commission writes it: "
                        "MACHINE.baseline.json beside --out)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot read the baseline: "
                        f"{getattr(exc, 'strerror', None) or exc}") from None
    try:
        return parse(json.loads(text))
    except json.JSONDecodeError as exc:
        raise UserError(f"{path}: not a baseline file (not JSON: {exc.msg}, line "
                        f"{exc.lineno})") from None
    except (ValueError, TypeError, RecursionError) as exc:
        raise UserError(f"{path}: {exc}") from None


def for_analysis(path: str | Path, cfg: Config, unit: str, mode: str) -> OwnError:
    """The unit's own error from the baseline at ``path``, checked against the analysis: the
    same configuration (:meth:`Config.estimate_hash`: the physics, the switches, the drive's
    reading, the estimator), the unit present, the same estimator mode."""
    base = read(path)
    if base.config_hash != cfg.estimate_hash():
        raise UserError(f"{path}: the baseline of another configuration (its physics, "
                        "switches, drive reading or estimator settings differ; hash "
                        f"{base.config_hash[:12]}, this one's {cfg.estimate_hash()[:12]}): "
                        "give the baseline commission wrote with this configuration")
    if unit not in base.units or not base.units[unit].kinds:
        have = ", ".join(u for u, b in base.units.items() if b.kinds) or "none"
        raise UserError(f"{path}: no baseline for the {unit} (units in it: {have}): "
                        "commission it with runs of that unit")
    if base.mode != mode:
        raise UserError(f"{path}: measured in {base.mode} mode, the analysis is in {mode}: "
                        f"analyze with --mode {base.mode}")
    return base.units[unit].own_error(f"{path} ({base.created})")
