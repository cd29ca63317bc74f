"""The report of a diagnosis: ``report.json`` (the figures of merit), ``breakdown.json`` (the
error by class), ``extension.json`` (the extended model) and ``report.html`` (all of it with
embedded figures, readable without a server)."""

from __future__ import annotations

import base64
import html
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ddh_vsensor.atomic import output_dir
from ddh_vsensor.diagnosis.analyze import Diagnosis
from ddh_vsensor.diagnosis.breakdown import breakdown
from ddh_vsensor.diagnosis.causes import ALL_CAUSES
from ddh_vsensor.estimator.extension import Extension
from ddh_vsensor.diagnosis.figures import breakdown_figure, errors_per_run, ranking_figure, signature_figure
from ddh_vsensor.diagnosis.selection import MIN_SCORE, separation
from ddh_vsensor.diagnosis.fit import PENALTY_PER_PARAMETER
from ddh_vsensor.diagnosis.signatures import signature, signature_errors


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


def report_data(diag: Diagnosis, extension_file: Path) -> dict[str, Any]:
    """The content of report.json: the issue's nine keys, ``causes`` and ``ambiguous``."""
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

_STYLE = """
body { font-family: sans-serif; max-width: 1200px; margin: 1em auto; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1em; font-size: 0.85em; }
th, td { border: 1px solid #ccc; padding: 2px 8px; text-align: right; }
th:first-child, td:first-child { text-align: left; }
.named { font-size: 1.3em; font-weight: bold; }
img { max-width: 100%; }
.note { color: #555; font-size: 0.85em; }
"""


def _img(png: bytes, alt: str) -> str:
    return (f'<img alt="{html.escape(alt)}" '
            f'src="data:image/png;base64,{base64.b64encode(png).decode()}">')


def _table(head: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    def cell(v: Any) -> str:
        if isinstance(v, float):
            return "" if not np.isfinite(v) else f"{v:.3g}" if abs(v) < 1e-2 else f"{v:.3f}"
        return html.escape(str(v))
    return ("<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"
            + "".join("<tr>" + "".join(f"<td>{cell(v)}</td>" for v in r) + "</tr>"
                      for r in rows) + "</table>")


def _html(diag: Diagnosis, data: dict[str, Any], stats) -> str:
    bench = diag.bench
    shown = diag.chosen.cause.name
    masks = bench.masks
    before = diag.baseline
    after = [_full(m, h) for m, h in zip(masks, diag.heldout)]
    names = [r.name for r in diag.runs]
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>ddh-vsensor diagnosis:"
             f" {diag.actuator}</title><style>{_STYLE}</style></head><body>",
             f"<h1>Model diagnosis: {diag.actuator}, {diag.mode} mode</h1>",
             f"<p class='named'>Cause: {html.escape(diag.cause)}</p>",
             f"<p>{html.escape(diag.decision.reason)}.</p>"]
    if data["causes"]:
        parts.append("<h2>Causes (fitted jointly)</h2>" + _table(
            ["cause", "what it is", "parameter", "fitted", "90 % interval",
             "share of held-out error removed"],
            [[c["cause"], ALL_CAUSES[c["cause"]].summary if c["cause"] in ALL_CAUSES
              else "not in the catalogue: a residual model of physical features",
              next(iter(c["parameters"]), ""), next(iter(c["parameters"].values()),
                                                    float("nan")),
              " .. ".join(f"{v:.4g}" for v in next(iter(c["interval"].values()), [])),
              c["share"]] for c in data["causes"]]))
        parts.append(f"<p>Extension: <code>{html.escape(data['extension_file'])}</code> "
                     f"(<code>ddh-vsensor estimate RUN --actuator {diag.actuator} --extension "
                     f"FILE</code>).</p>")
    if diag.ambiguous:
        parts.append("<h2>What the runs cannot tell apart</h2><ul>" + "".join(
            f"<li><b>{html.escape(a)}</b> and <b>{html.escape(b)}</b> explain the runs about "
            f"equally well; to separate them: {html.escape(separation(a, b))}.</li>"
            for a, b in diag.ambiguous) + "</ul>")
    if diag.evidence is not None:
        parts.append(f"<p class='note'>{html.escape(diag.evidence.describe())}: candidate "
                     "sets whose torque gain x displacement or torque offset disagree were "
                     "not considered.</p>")
    else:
        parts.append("<p class='note'>No chamber pressures in the runs: torque gain, "
                     "displacement and leakage are told apart by their signatures only; the "
                     "columns p_a_bar and p_b_bar would separate them directly.</p>")
    if diag.cause == "unexplained" and diag.residual is not None:
        follows = ", ".join(f"{k} ({100 * v:.0f} %)" for k, v in diag.residual.follows()[:4])
        parts.append("<h2>The unexplained error: what it follows, where it lives</h2>"
                     f"<p>The residual model's correction is carried by: "
                     f"{html.escape(follows)} (standardised weights). Where the error the "
                     "catalogue leaves lives, by class:</p>")
        left = []
        for i, (x, r, m) in enumerate(zip(bench.base, diag.runs, masks)):
            est = np.array(x, dtype=float)
            est[m] = r.position_mm[m] + _nearest(diag, i)
            left.append(est)
        for dim, st in breakdown(diag.runs, left).items():
            parts.append(f"<h3>{dim}</h3>" + _table(
                ["class", "time (s)", "error added (mm)", "per second (mm/s)", "RMS (mm)",
                 "max |error| (mm)"],
                [[x.name, x.time_s, x.error_added_mm, x.error_rate_mm_s, x.rms_error_mm,
                  x.max_abs_error_mm] for x in st]))
    b, e = data["baseline"], data["extended"]
    rows = [["model as it is", b["max_abs_error_mm"], b["rms_error_mm"]]]
    if bench.default_inertia:
        m = _errors([x[k] for x, k in zip(diag.model, masks)])
        rows.append(["with the motor's inertia torque taken off the motor torque",
                     m["max_abs_error_mm"], m["rms_error_mm"]])
    rows.append([f"extended ({', '.join(diag.named) or diag.cause}), each run fitted "
                 "without it", e["max_abs_error_mm"],
                 e["rms_error_mm"]])
    parts.append("<h2>Gain on held-out runs</h2>" + _table(
        ["", "max |error| (mm)", "RMS error (mm)"], rows))
    if bench.default_inertia:
        parts.append("<p class='note'>The motor torque also accelerates the rotor and pumps; "
                     "the tables hold pump torque. Taking J d(omega)/dt off lowered the error "
                     "on these runs, so none is judged on that basis; each cause is fitted "
                     "both ways and keeps the better (extension flag motor_inertia).</p>")
    parts.append("<h2>Why: the candidate causes</h2>" + _table(
        ["cause", "score", "parameter", "fitted", "per held-out run (range)", "resolution",
         "signature"],
        [[f.cause.name, f.score, f.cause.parameter or "", next(iter(f.parameters.values()),
                                                              float("nan")),
          _range(f.fold_values), _resolution(f.cause), f.cause.signature]
         for f in diag.fits]))
    parts.append(_img(ranking_figure([f.cause.name for f in diag.fits],
                                     [f.score for f in diag.fits], MIN_SCORE, diag.cause),
                      "ranking"))
    parts.append(
        f"<p class='note'>Score: share of the squared error on held-out runs (each run "
        f"predicted by the cause fitted on the other runs) that the extension removes, minus "
        f"{PENALTY_PER_PARAMETER:g} per fitted parameter. A cause is named when its score "
        f"reaches {MIN_SCORE:g} and its parameter is further from neutral than the model's "
        "own error can mimic (the resolution column); otherwise the answer is none.</p>")
    sig = signature(shown, bench)
    parts.append(f"<h2>The feature that gives {html.escape(shown)} away</h2>")
    parts.append(_img(signature_figure(sig, signature_errors(sig, bench, before),
                                       signature_errors(sig, bench, after), shown),
                      "residual against feature"))
    parts.append("<h2>Error before and after, per run</h2>")
    parts.append(_img(errors_per_run(names, [r.time_s for r in diag.runs], before, after,
                                     f"extended ({', '.join(diag.named) or diag.cause}), "
                                     "held out",
                                     diag.model if bench.default_inertia else None),
                      "errors per run"))
    parts.append("<h2>Runs</h2>" + _table(
        ["run", "duration (s)", "oil (degC)", "max |torque| (N*m)", "max |error| before",
         "RMS before", "max |error| after", "RMS after"],
        [[Path(r.name).name, r.duration_s,
          f"{np.min(r.oil_temp_c):.1f}-{np.max(r.oil_temp_c):.1f}",
          float(np.max(np.abs(r.torque_nm))), float(np.nanmax(np.abs(eb))),
          float(np.sqrt(np.nanmean(eb ** 2))), float(np.max(np.abs(h))),
          float(np.sqrt(np.mean(h ** 2)))]
         for r, eb, h in zip(diag.runs, before, diag.heldout)]))
    parts.append("<h2>What is wrong: the error of the model as it is, by class</h2>")
    parts.append(_img(breakdown_figure(stats), "breakdown"))
    for dim, st in stats.items():
        parts.append(f"<h3>{dim}</h3>" + _table(
            ["class", "time (s)", "travel (mm)", "error added (mm)", "per second (mm/s)",
             "per metre (mm/m)", "RMS error (mm)", "max |error| (mm)"],
            [[s.name, s.time_s, s.travel_mm, s.error_added_mm, s.error_rate_mm_s,
              s.error_per_m_mm, s.rms_error_mm, s.max_abs_error_mm] for s in st]))
    parts.append("</body></html>")
    return "\n".join(parts)


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
