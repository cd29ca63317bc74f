"""The report of a diagnosis: ``report.json`` (the figures of merit), ``breakdown.json`` (the
error by class), ``extension.json`` (the extended model) and ``report.html`` (all of it with
embedded figures, readable without a server)."""

from __future__ import annotations

import base64
import functools
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jinja2
import numpy as np

from ddh_vsensor.atomic import output_dir
from ddh_vsensor.diagnosis.analyze import Diagnosis
from ddh_vsensor.diagnosis.breakdown import breakdown
from ddh_vsensor.diagnosis.causes import ALL_CAUSES
from ddh_vsensor.estimator.extension import Extension
from ddh_vsensor.diagnosis.figures import (breakdown_figure, errors_per_run, ranking_figure,
                                            signature_figure)
from ddh_vsensor.diagnosis.selection import MIN_SCORE, separation
from ddh_vsensor.diagnosis.fit import PENALTY_PER_PARAMETER
from ddh_vsensor.diagnosis.signatures import signature, signature_errors
from ddh_vsensor.version import __version__


def _full(mask: np.ndarray, masked: np.ndarray) -> np.ndarray:
    out = np.full(len(mask), np.nan)
    out[mask] = masked
    return out


def _errors(residuals: Sequence[np.ndarray]) -> dict[str, float]:
    e = np.concatenate([np.asarray(r)[np.isfinite(r)] for r in residuals])
    return {"max_abs_error_mm": round(float(np.max(np.abs(e))), 4),
            "rms_error_mm": round(float(np.sqrt(np.mean(e ** 2))), 4)}


def extension_of(diag: Diagnosis, cfg_hash: str) -> Extension:
    """The extended model of the decision: the named set jointly, the residual model (on
    top of the nearest set where that did better) for unexplained, nothing for none."""
    common = dict(actuator=diag.actuator, config_hash=cfg_hash,
                  motor_inertia=bool(diag.extension_inertia),
                  fitted_on=tuple(r.name for r in diag.runs))
    notes = {"reason": diag.decision.reason,
             "ambiguous": [list(p) for p in diag.ambiguous]}
    if diag.cause == "unexplained" and diag.residual is not None:
        notes["follows"] = {k: round(v, 3) for k, v in diag.residual.follows()}
        return Extension(cause="unexplained", parameters=dict(diag.residual_base),
                         mode=diag.mode, residual=diag.residual.model, notes=notes, **common)
    if not diag.named:
        return Extension(cause="none", parameters={}, mode=diag.mode, notes=notes, **common)
    s = diag.chosen_set
    notes["shares"] = {k: round(v, 4) for k, v in diag.shares.items()}
    return Extension(cause=diag.cause, parameters=dict(s.params), causes=s.names,
                     mode="full" if "low_speed_leakage" in s.names else diag.mode,
                     notes=notes, **common)


def causes_of(diag: Diagnosis) -> list[dict[str, Any]]:
    """``report.json``'s ``causes``: each applied cause, its parameters with their 90 %
    intervals, and the share of the held-out squared error it removes."""
    if diag.cause == "unexplained" and diag.residual is not None:
        return [{"cause": "unexplained", "parameters": {}, "interval": {},
                 "share": round(float(diag.residual.explained), 4)}]
    if not diag.named:
        return []
    s = diag.chosen_set
    out = []
    for c in s.causes:
        p = {} if c.parameter is None else {c.parameter: round(float(s.params[c.parameter]), 6)}
        iv = {k: [round(float(v[0]), 6), round(float(v[1]), 6)]
              for k, v in s.intervals.items() if k == c.parameter}
        out.append({"cause": c.name, "parameters": p, "interval": iv,
                    "share": round(float(diag.shares.get(c.name, 0.0)), 4)})
    return out


def not_observable_of(items: Sequence[tuple[str, str, str]]) -> list[dict[str, str]]:
    """``report.json``'s ``not_observable``: the causes these runs could not show, why, and
    what would (a ``none`` holds for the others only)."""
    return [{"cause": c, "why": why, "shown_by": shown} for c, why, shown in items]


def report_data(diag: Diagnosis, extension_file: Path) -> dict[str, Any]:
    """The content of report.json: the issue's nine keys, ``causes``, ``ambiguous``,
    ``not_observable``, ``observability`` (every checked cause's numbers) and ``thresholds``
    (the simulator's or the machine's baseline)."""
    return {
        "actuator": diag.actuator,
        "mode": diag.mode,
        "runs": [r.name for r in diag.runs],
        "cause": diag.cause,
        "ranking": [{"cause": f.cause.name, "score": round(float(f.score), 4),
                     "parameters": {k: round(v, 6) for k, v in f.parameters.items()}}
                    for f in diag.fits],
        "baseline": _errors([e[m] for e, m in zip(diag.baseline, diag.bench.masks)]),
        "extended": _errors(diag.heldout),
        "holdout_runs": [r.name for r in diag.runs],
        "extension_file": str(extension_file),
        "causes": causes_of(diag),
        "ambiguous": [list(p) for p in diag.ambiguous],
        "not_observable": not_observable_of(diag.not_observable),
        "observability": [o.as_dict() for o in diag.observability],
        "thresholds": diag.thresholds.as_dict(),
    }


def prepare_report_dir(out_dir: str | Path) -> Path:
    """Create the report directory (before a long analysis, so a bad path fails at once)."""
    return output_dir(out_dir, "report directory")


def write_report(diag: Diagnosis, out_dir: str | Path, cfg_hash: str) -> dict[str, Any]:
    """Write every file of the report into ``out_dir``; returns report.json's content."""
    out = prepare_report_dir(out_dir)
    ext_path = extension_of(diag, cfg_hash).save(out / "extension.json").resolve()
    data = report_data(diag, ext_path)
    stats = breakdown(diag.runs, diag.bench.as_is)
    (out / "report.json").write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    (out / "breakdown.json").write_text(json.dumps(
        {dim: [s.as_dict() for s in st] for dim, st in stats.items()}, indent=2) + "\n",
        encoding="utf-8")
    (out / "report.html").write_text(_html(diag, data, stats), encoding="utf-8")
    return data


# --- HTML ------------------------------------------------------------------------------------


def _cell(value: Any, small_g: bool = True) -> str:
    """A table cell's text: a number to three decimals (three significant digits below 0.01
    where ``small_g``), nothing for a non-finite number or None."""
    if value is None:
        return ""
    if isinstance(value, float):
        if not np.isfinite(value):
            return ""
        return f"{value:.3g}" if small_g and abs(value) < 1e-2 else f"{value:.3f}"
    return str(value)


def _base64(png: bytes) -> str:
    return base64.b64encode(png).decode("ascii")


@functools.cache
def _templates() -> jinja2.Environment:
    """The reports' templates (``data/templates``), every value HTML-escaped: a run name or
    a path may hold any character (``html.j2`` is named: the default list misses it)."""
    env = jinja2.Environment(loader=jinja2.PackageLoader("ddh_vsensor", "data/templates"),
                             autoescape=jinja2.select_autoescape(("html", "html.j2")),
                             undefined=jinja2.StrictUndefined, trim_blocks=True,
                             lstrip_blocks=True)
    env.filters.update(cell=_cell, b64=_base64)
    return env


def render_page(template: str, **context: Any) -> str:
    """A self-contained report page: ``template`` (which extends ``base.html.j2``) with
    ``context``; a missing value is an error, not an empty cell."""
    return _templates().get_template(template).render(version=__version__, **context)


def _html(diag: Diagnosis, data: dict[str, Any], stats) -> str:
    bench = diag.bench
    shown = diag.chosen.cause.name
    masks = bench.masks
    before = diag.baseline
    after = [_full(m, h) for m, h in zip(masks, diag.heldout)]
    extended = f"extended ({', '.join(diag.named) or diag.cause})"
    causes = [[c["cause"], ALL_CAUSES[c["cause"]].summary if c["cause"] in ALL_CAUSES
               else "not in the catalogue: a residual model of physical features",
               next(iter(c["parameters"]), ""),
               next(iter(c["parameters"].values()), float("nan")),
               " .. ".join(f"{v:.4g}" for v in next(iter(c["interval"].values()), [])),
               c["share"]] for c in data["causes"]]
    unexplained = None
    if diag.cause == "unexplained" and diag.residual is not None:
        left = []
        for i, (x, r, m) in enumerate(zip(bench.base, diag.runs, masks)):
            est = np.array(x, dtype=float)
            est[m] = r.position_mm[m] + _nearest(diag, i)
            left.append(est)
        unexplained = {
            "follows": ", ".join(f"{k} ({100 * v:.0f} %)"
                                 for k, v in diag.residual.follows()[:4]),
            "breakdown": [(dim, [[x.name, x.time_s, x.error_added_mm, x.error_rate_mm_s,
                                  x.rms_error_mm, x.max_abs_error_mm] for x in st])
                          for dim, st in breakdown(diag.runs, left).items()]}
    b, e = data["baseline"], data["extended"]
    gain = [["model as it is", b["max_abs_error_mm"], b["rms_error_mm"]]]
    if bench.default_inertia:
        m = _errors([x[k] for x, k in zip(diag.model, masks)])
        gain.append(["with the motor's inertia torque taken off the motor torque",
                     m["max_abs_error_mm"], m["rms_error_mm"]])
    gain.append([f"{extended}, each run fitted without it", e["max_abs_error_mm"],
                 e["rms_error_mm"]])
    sig = signature(shown, bench)
    return render_page(
        "diagnosis.html.j2",
        title=f"ddh-vsensor diagnosis: {diag.actuator}",
        actuator=diag.actuator, mode=diag.mode, cause=diag.cause,
        reason=diag.decision.reason, thresholds=diag.thresholds.describe(), causes=causes,
        extension_file=data["extension_file"],
        ambiguous=[(a, b, separation(a, b)) for a, b in diag.ambiguous],
        not_observable=diag.not_observable,
        evidence=None if diag.evidence is None else diag.evidence.describe(),
        unexplained=unexplained, gain=gain, default_inertia=bench.default_inertia,
        candidates=[[f.cause.name, f.score, f.cause.parameter or "",
                     next(iter(f.parameters.values()), float("nan")),
                     _range(f.fold_values), _resolution(f.cause), f.cause.signature]
                    for f in diag.fits],
        ranking_png=ranking_figure([f.cause.name for f in diag.fits],
                                   [f.score for f in diag.fits], MIN_SCORE, diag.cause),
        penalty_per_parameter=PENALTY_PER_PARAMETER, min_score=MIN_SCORE, shown=shown,
        signature_png=signature_figure(sig, signature_errors(sig, bench, before),
                                       signature_errors(sig, bench, after), shown),
        errors_png=errors_per_run([r.name for r in diag.runs], [r.time_s for r in diag.runs],
                                  before, after, f"{extended}, held out",
                                  diag.model if bench.default_inertia else None),
        runs=[[r.name, r.duration_s,
               f"{np.min(r.oil_temp_c):.1f}-{np.max(r.oil_temp_c):.1f}",
               float(np.max(np.abs(r.torque_nm))), float(np.nanmax(np.abs(eb))),
               float(np.sqrt(np.nanmean(eb ** 2))), float(np.max(np.abs(h))),
               float(np.sqrt(np.mean(h ** 2)))]
              for r, eb, h in zip(diag.runs, before, diag.heldout)],
        breakdown_png=breakdown_figure(stats),
        breakdown=[(dim, [[s.name, s.time_s, s.travel_mm, s.error_added_mm,
                           s.error_rate_mm_s, s.error_per_m_mm, s.rms_error_mm,
                           s.max_abs_error_mm] for s in st])
                   for dim, st in stats.items()])


def _nearest(diag: Diagnosis, i: int) -> np.ndarray:
    """The error the nearest catalogue set leaves on run ``i`` (the model's if none)."""
    s = diag.chosen_set
    return s.heldout[i] if s is not None else diag.model[i][diag.bench.masks[i]]


def _range(values: Sequence[float | None]) -> str:
    vals = [v for v in values if v is not None]
    if not vals:
        return ""
    return f"{min(vals):.4g} .. {max(vals):.4g}"


def _resolution(cause) -> str:
    if cause.neutral is None:
        return ""
    if cause.log:
        return f"x{1 + cause.resolution:g} / x{1 / (1 + cause.resolution):.3g}"
    return f"+-{cause.resolution:g}" if cause.name == "time_offset" else f">= {cause.resolution:g}"
