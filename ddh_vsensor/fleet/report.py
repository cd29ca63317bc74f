"""The fleet report: per machine and unit the fitted parameters over time with their
intervals, the expected position error now and projected, alarms naming the cause, and the
extension file to load; HTML (figures embedded, readable from disk) plus a JSON summary."""

from __future__ import annotations

import datetime as dt
import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from ddh_vsensor.config import Config
from ddh_vsensor.diagnosis.causes import ALL_CAUSES
from ddh_vsensor.diagnosis.report import render_page
from ddh_vsensor.estimator.extension import Extension
from ddh_vsensor.diagnosis.trend import DAY_S, UnitTrend, from_u


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


def summary(trends: list[UnitTrend], tolerance_mm: float, horizon_days: float,
            ext_dir: Path, cfg: Config) -> list[dict[str, Any]]:
    """One entry per machine and unit (the JSON summary); writes the alarms' extensions."""
    out = []
    for tr in trends:
        if not tr.times_s:
            continue
        cause = tr.named[-1]
        alarm = tr.alarms[-1]
        entry: dict[str, Any] = {
            "machine": tr.machine, "actuator": tr.actuator, "logs": len(tr.times_s),
            "last_log": _date(tr.times_s[-1]), "cause": cause,
            "reference_error_mm": round(tr.reference_error_mm[-1], 3),
            "expected_error_mm": None if cause == "none" else round(tr.error_now_mm[-1], 3),
            "projected_error_mm": None if cause == "none" else round(
                tr.error_projected_mm[-1], 3),
            "alarm": alarm is not None, "first_alarm": None, "extension_file": None}
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
        out.append(entry)
    return out


def _parameter(entry: dict[str, Any]) -> str:
    return ", ".join(f"{k}={v:.4g}" for k, v in entry.get("parameter", {}).items())


def write_report(trends: list[UnitTrend], out: Path, tolerance_mm: float,
                 horizon_days: float, cfg: Config, store_summary: dict[str, Any]) -> dict:
    """report.html, report.json and the alarms' extension files (``<stem>_extensions/``)."""
    ext_dir = out.parent / f"{out.stem}_extensions"
    entries = summary(trends, tolerance_mm, horizon_days, ext_dir, cfg)
    alarms = [e for e in entries if e["alarm"]]
    out.write_text(render_page(
        "fleet.html.j2", title="ddh-vsensor fleet report", store=store_summary,
        tolerance_mm=tolerance_mm, horizon_days=horizon_days,
        alarms=[[e["machine"], e["actuator"], e["cause"], _parameter(e),
                 e["expected_error_mm"], e["projected_error_mm"], e.get("crossing"),
                 (e["first_alarm"] or {}).get("date"), e["extension_file"]]
                for e in alarms],
        machines=[[e["machine"], e["actuator"], e["logs"], e["last_log"], e["cause"],
                   _parameter(e), " .. ".join(f"{v:.4g}" for v in e.get("interval", [])),
                   e["reference_error_mm"], e["expected_error_mm"], e["projected_error_mm"],
                   "ALARM" if e["alarm"] else ""]
                  for e in entries],
        trends=[{"machine": tr.machine, "actuator": tr.actuator,
                 "png": _figure(tr, tolerance_mm)} for tr in trends if tr.times_s]),
        encoding="utf-8")
    data = {"tolerance_mm": tolerance_mm, "horizon_days": horizon_days, **store_summary,
            "units": entries}
    out.with_suffix(".json").write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    return data
