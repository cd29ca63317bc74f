"""The fleet report: per machine and unit what was found, in words (:mod:`.finding`: the
cause and its figure, the expected position error now and projected, the days and date until
it passes the tolerance, the action and the extension file to load; or nothing found; or too
few days for a trend yet), the fitted parameters over time with their intervals where they
say something (a unit with a named cause or an alarm), and what each parameter means; HTML
(figures embedded, readable from disk) plus a JSON summary."""

from __future__ import annotations

import datetime as dt
import io
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ddh_vsensor.config import Config
from ddh_vsensor.diagnosis.causes import ALL_CAUSES
from ddh_vsensor.diagnosis.finding import (Finding, label, parameter_meanings,
                                            unit_finding)
from ddh_vsensor.diagnosis.report import render_page
from ddh_vsensor.estimator.extension import Extension
from ddh_vsensor.diagnosis.trend import DAY_S, MIN_LOGS, UnitTrend, from_u


STATE_WORDS = {"alarm": "ALARM", "cause": "named, within tolerance", "none": "nothing found",
               "too_few_days": "too few days for a trend", "no_evidence": "no evidence"}


def _date(t: float) -> str:
    return dt.datetime.fromtimestamp(t, dt.timezone.utc).date().isoformat()


def _figure(tr: UnitTrend, tolerance_mm: float) -> bytes:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    days = (np.array(tr.times_s) - tr.times_s[0]) / DAY_S
    shown = [c for c in dict.fromkeys(n for n in tr.named if n != "none")] or \
        [max(tr.series, key=lambda c: tr.scores[-1].get(c, -9) if tr.scores else 0)]
    fig, axes = plt.subplots(len(shown) + 1, 1, figsize=(7.5, 2.2 * (len(shown) + 1)),
                             sharex=True)
    for ax, cause in zip(axes, shown):
        fits = tr.series[cause]
        x = (np.array([f.time_s for f in fits]) - tr.times_s[0]) / DAY_S
        v = [from_u(cause, f.u) for f in fits]
        lo = [from_u(cause, f.lo_u) for f in fits]
        hi = [from_u(cause, f.hi_u) for f in fits]
        ax.fill_between(x, lo, hi, alpha=0.3, label="90 % interval")
        ax.plot(x, v, "o-", ms=3, label="fitted per log")
        ax.axhline(ALL_CAUSES[cause].neutral, color="k", lw=0.7)
        ax.set_ylabel(f"{cause}\n{ALL_CAUSES[cause].parameter}", fontsize=8)
        ax.legend(fontsize=7, loc="upper left")
    ax = axes[-1]
    ax.plot(days, tr.reference_error_mm, ".", color="0.5", label="nominal model, max at refs")
    ax.plot(days, tr.error_now_mm, "o-", ms=3, label="expected error of the cause")
    ax.plot(days, tr.error_projected_mm, "--", label="projected at the horizon")
    ax.axhline(tolerance_mm, color="r", lw=1, label="tolerance")
    for a in tr.alarms:
        if a is not None:
            ax.axvline((a.time_s - tr.times_s[0]) / DAY_S, color="r", alpha=0.15)
    ax.set_ylabel("mm", fontsize=8)
    ax.set_xlabel(f"days since {_date(tr.times_s[0])}")
    ax.legend(fontsize=7, loc="upper left")
    fig.suptitle(f"{tr.machine} {tr.actuator}")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80)
    plt.close(fig)
    return buf.getvalue()


def plotted(tr: UnitTrend) -> bool:
    """Whether a unit's trend figure says something: a cause was named or an alarm raised
    on some day (otherwise its sentence says all there is)."""
    return any(n != "none" for n in tr.named) or tr.first_alarm is not None


def _entries(trends: list[UnitTrend], tolerance_mm: float, horizon_days: float,
             ext_dir: Path, cfg: Config,
             sources: Mapping[str, str] | None) -> list[tuple[UnitTrend, dict, Finding]]:
    """(trend, JSON entry, finding) of each unit with evidence; writes the alarms'
    extensions first, so that the finding names the file to load. The entry's ``logs``
    counts the days' logs and summaries the trend took (as before), ``days_of_evidence``
    the days they cover."""
    out = []
    for tr in trends:
        if not tr.times_s:
            continue
        cause = tr.named[-1]
        alarm = tr.alarms[-1]
        entry: dict[str, Any] = {
            "machine": tr.machine, "actuator": tr.actuator, "logs": len(tr.times_s),
            "days_of_evidence": len({_date(t) for t in tr.times_s}),
            "last_log": _date(tr.times_s[-1]), "cause": cause,
            "reference_error_mm": round(tr.reference_error_mm[-1], 3),
            "expected_error_mm": None if cause == "none" else round(tr.error_now_mm[-1], 3),
            "projected_error_mm": None if cause == "none" else round(
                tr.error_projected_mm[-1], 3),
            "alarm": alarm is not None, "first_alarm": None, "extension_file": None}
        if sources is not None:
            kinds = [sources.get(f.log_id, "") for f in next(iter(tr.series.values()))]
            entry["evidence"] = {"summaries": kinds.count("summary"), "logs": kinds.count("log")}
        if cause != "none":
            f = tr.series[cause][-1]
            entry["parameter"] = {ALL_CAUSES[cause].parameter: round(from_u(cause, f.u), 5)}
            entry["interval"] = [round(from_u(cause, f.lo_u), 5), round(from_u(cause, f.hi_u), 5)]
        first = tr.first_alarm
        if first is not None:
            entry["first_alarm"] = {"date": _date(first.time_s), "cause": first.cause}
        if alarm is not None:
            entry["crossing"] = _date(alarm.crossing_time_s) if alarm.crossing_time_s else None
            ext = Extension(cause=alarm.cause,
                            parameters={ALL_CAUSES[alarm.cause].parameter: alarm.value},
                            actuator=tr.actuator, config_hash=cfg.physics_hash(),
                            mode=cfg.estimator.mode,
                            motor_inertia=cfg.estimator.inertia_compensation,
                            fitted_on=tuple(f.log_id for f in tr.series[alarm.cause][-7:]),
                            notes={"machine": tr.machine, "truth": "references and holds",
                                   "alarm": f"expected error {alarm.error_now_mm:.2f} mm, "
                                            f"{alarm.error_projected_mm:.2f} mm in "
                                            f"{horizon_days:g} days"})
            path = ext.save(ext_dir / f"{tr.machine}_{tr.actuator}.json")
            entry["extension_file"] = str(path.resolve())
        finding = unit_finding(tr, tolerance_mm, horizon_days, entry["extension_file"],
                               sources)
        entry.update(state=finding.state, finding=finding.text, figure=plotted(tr),
                     days_left=None if finding.days_left is None else round(
                         finding.days_left, 1),
                     action=finding.action or None)
        out.append((tr, entry, finding))
    return out


def summary(trends: list[UnitTrend], tolerance_mm: float, horizon_days: float,
            ext_dir: Path, cfg: Config,
            sources: Mapping[str, str] | None = None) -> list[dict[str, Any]]:
    """One entry per machine and unit (the JSON summary) with its finding in words; writes
    the alarms' extensions. ``sources``: log id -> "summary" or "log" (the analysis' rows),
    to say what the days of evidence are."""
    return [e for _, e, _ in _entries(trends, tolerance_mm, horizon_days, ext_dir, cfg,
                                      sources)]


def _parameter(entry: dict[str, Any]) -> str:
    return ", ".join(f"{k}={v:.4g}" for k, v in entry.get("parameter", {}).items())


def write_report(trends: list[UnitTrend], out: Path, tolerance_mm: float,
                 horizon_days: float, cfg: Config, store_summary: dict[str, Any],
                 sources: Mapping[str, str] | None = None) -> dict:
    """report.html, report.json and the alarms' extension files (``<stem>_extensions/``).
    ``sources`` (log id -> "summary" or "log") words each unit's evidence as day summaries
    and logs; without it, as days."""
    ext_dir = out.parent / f"{out.stem}_extensions"
    done = _entries(trends, tolerance_mm, horizon_days, ext_dir, cfg, sources)
    entries = [e for _, e, _ in done]
    alarms = [(e, f) for _, e, f in done if e["alarm"]]
    out.write_text(render_page(
        "fleet.html.j2", title="ddh-vsensor fleet report", store=store_summary,
        summaries=store_summary.get("summaries", 0),
        tolerance_mm=tolerance_mm, horizon_days=horizon_days, min_days=MIN_LOGS,
        alarms=[[e["machine"], e["actuator"], f"{label(e['cause'])} ({e['cause']})", f.what,
                 e["expected_error_mm"], e["projected_error_mm"], f.time_left,
                 (e["first_alarm"] or {}).get("date"), f.action, e["extension_file"]]
                for e, f in alarms],
        machines=[[e["machine"], e["actuator"], e["days_of_evidence"], e["last_log"],
                   e["cause"], _parameter(e),
                   " .. ".join(f"{v:.4g}" for v in e.get("interval", [])),
                   e["reference_error_mm"], e["expected_error_mm"], e["projected_error_mm"],
                   STATE_WORDS[e["state"]]]
                  for e in entries],
        too_few=[f"{f.machine} {f.actuator}" for _, _, f in done
                 if f.state == "too_few_days"],
        units=[{"machine": tr.machine, "actuator": tr.actuator, "state": f.state,
                "text": f.text, "png": _figure(tr, tolerance_mm) if e["figure"] else None}
               for tr, e, f in done],
        parameters=[[c + (" (pressure scale)" if label(c) == "pressure scale" else ""),
                     p, u, m, a] for c, p, u, m, a in parameter_meanings()]),
        encoding="utf-8")
    data = {"tolerance_mm": tolerance_mm, "horizon_days": horizon_days, **store_summary,
            "units": entries}
    out.with_suffix(".json").write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    return data
