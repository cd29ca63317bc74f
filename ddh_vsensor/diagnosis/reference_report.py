"""The report of a diagnosis from references and holds: ``report.json`` (the position-truth
report's nine keys, the errors taken at the references, plus ``truth``, ``causes``,
``unexplained``, ``not_observable``, ``observability`` and ``thresholds``),
``extension.json`` and a self-contained ``report.html``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ddh_vsensor.atomic import output_dir
from ddh_vsensor.diagnosis.causes import ALL_CAUSES
from ddh_vsensor.estimator.extension import Extension
from ddh_vsensor.diagnosis.figures import ranking_figure
from ddh_vsensor.diagnosis.reference_fit import ReferenceDiagnosis
from ddh_vsensor.diagnosis.report import not_observable_of, render_page
from ddh_vsensor.diagnosis.selection import MIN_SCORE


def _split(diag: ReferenceDiagnosis, obs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    inc = np.concatenate([o[:r.n_increments] for o, r in zip(obs, diag.rruns)])
    creep = np.concatenate([o[r.n_increments:] for o, r in zip(obs, diag.rruns)])
    return inc, creep


def _errors(inc: np.ndarray) -> dict[str, float]:
    return {"max_abs_error_mm": round(float(np.max(np.abs(inc))), 4),
            "rms_error_mm": round(float(np.sqrt(np.mean(inc ** 2))), 4)}


def extension_of(diag: ReferenceDiagnosis, cfg_hash: str) -> Extension:
    named = diag.cause not in ("none", "unexplained", "ambiguous")
    fit = diag.chosen if named else next(f for f in diag.fits if f.cause.name == "none")
    return Extension(cause=fit.cause.name, parameters=fit.parameters, actuator=diag.actuator,
                     config_hash=cfg_hash, mode=diag.mode, motor_inertia=fit.motor_inertia,
                     fitted_on=tuple(r.name for r in diag.rruns),
                     notes={"truth": "references and holds", "score": round(fit.score, 4),
                            "reason": diag.decision.reason})


def report_data(diag: ReferenceDiagnosis, extension_file: Path) -> dict[str, Any]:
    named = diag.cause not in ("none", "unexplained", "ambiguous")
    base_inc, _ = _split(diag, diag.baseline)
    ext_inc, _ = _split(diag, diag.chosen.heldout if named else diag.model)
    causes = []
    for f in diag.fits:
        iv = diag.intervals.get(f.cause.name)
        causes.append({"cause": f.cause.name, "score": round(float(f.score), 4),
                       "parameters": {k: round(v, 6) for k, v in f.parameters.items()},
                       "interval": ({f.cause.parameter: [round(iv[0], 6), round(iv[1], 6)]}
                                    if iv else {})})
    return {
        "actuator": diag.actuator,
        "mode": diag.mode,
        "runs": [r.name for r in diag.rruns],
        "cause": diag.cause,
        "ranking": [{"cause": c["cause"], "score": c["score"], "parameters": c["parameters"]}
                    for c in causes],
        "baseline": _errors(base_inc),
        "extended": _errors(ext_inc),
        "holdout_runs": [r.name for r in diag.rruns],
        "extension_file": str(extension_file),
        "truth": "references",
        "causes": causes,
        "unexplained": diag.cause == "unexplained",
        "references": sum(r.n_increments for r in diag.rruns),
        "holds": sum(len(r.holds) for r in diag.rruns),
        "not_observable": not_observable_of(diag.not_observable),
        "observability": [o.as_dict() for o in diag.observability],
        "thresholds": diag.thresholds.as_dict(),
    }


def write_reference_report(diag: ReferenceDiagnosis, out_dir: str | Path,
                           cfg_hash: str) -> dict[str, Any]:
    out = output_dir(out_dir, "report directory")
    ext = extension_of(diag, cfg_hash).save(out / "extension.json").resolve()
    data = report_data(diag, ext)
    (out / "report.json").write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    (out / "report.html").write_text(_html(diag, data), encoding="utf-8")
    return data


def _html(diag: ReferenceDiagnosis, data: dict[str, Any]) -> str:
    b, e = data["baseline"], data["extended"]
    named = diag.cause in ALL_CAUSES and diag.cause != "none"
    return render_page(
        "reference_diagnosis.html.j2",
        title=f"ddh-vsensor diagnosis from references: {diag.actuator}",
        actuator=diag.actuator, cause=diag.cause, reason=diag.decision.reason,
        thresholds=diag.thresholds.describe(),
        summary=ALL_CAUSES[diag.cause].summary if named else None,
        not_observable=diag.not_observable,
        extension_file=data["extension_file"],
        errors=[["model as it is", b["max_abs_error_mm"], b["rms_error_mm"]],
                [f"extended ({diag.cause})", e["max_abs_error_mm"], e["rms_error_mm"]]],
        candidates=[[c["cause"], c["score"],
                     ", ".join(f"{k}={v:.4g}" for k, v in c["parameters"].items()),
                     ", ".join(f"{v[0]:.4g}..{v[1]:.4g}" for v in c["interval"].values())]
                    for c in data["causes"]],
        ranking_png=ranking_figure([f.cause.name for f in diag.fits],
                                   [f.score for f in diag.fits], MIN_SCORE,
                                   diag.cause if diag.cause in ALL_CAUSES else "none"),
        runs=[[Path(r.name).name, r.run.duration_s, len(r.edges), len(r.holds),
               float(np.mean([h.speed_rpm for h in r.holds])) if r.holds else float("nan"),
               float(np.nanmean([h.model_speed_rpm for h in r.holds])) if r.holds
               else float("nan")]
              for r in diag.rruns])
