"""The commissioned configuration: the datasheet file with the calibrated switch keys set and
commented with their evidence, checked by loading it; and the edges behind them as JSON."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jinja2

from ddh_vsensor.atomic import atomic_path, atomic_write
from ddh_vsensor.commission.switches import KIND_KEYS, UnitCalibration
from ddh_vsensor.commission.yaml_text import Setting, set_values
from ddh_vsensor.config import Config, load_config
from ddh_vsensor.errors import UserError


def _mm(value: float) -> str:
    return f"{value:.2f}"


def settings(cal: UnitCalibration, spread_factor: float) -> list[Setting]:
    """The keys of one unit to set, each with its evidence; a switch not calibrated keeps
    its value and gets the reason instead."""
    base = ("units", cal.unit)
    out = []
    good = [s for s in cal.switches.values() if s.calibrated]
    edges = sum(len(s.edges) for s in good)
    for s in cal.switches.values():
        path = (*base, "references_mm", s.name)
        if not s.calibrated:
            out.append(Setting(path, None, f"not commissioned: {s.problem}"))
            continue
        spread = max((k.spread_mm for k in s.kinds.values() if k.count > 1), default=0.0)
        out.append(Setting(path, _mm(s.position_mm),
                           f"commissioned: {_mm(s.position_mm)} +-{s.tolerance_mm:.2f} mm, "
                           f"{len(s.edges)} edges, spread {spread:.2f} mm "
                           f"(datasheet {s.configured_mm:g})"))
    if not good:
        return out
    shared = f"{len(good)} switches' {edges} edges"
    for key, value, old, name in (
            ("reference_window_mm", cal.window_mm, cal.configured_window_mm, "window"),
            ("reference_hysteresis_mm", cal.hysteresis_mm, cal.configured_hysteresis_mm,
             "hysteresis")):
        how = "commissioned" if name in cal.fitted else "kept"
        out.append(Setting((*base, key), _mm(value),
                           f"{how}: {_mm(value)} mm from {shared} (datasheet {old:g})"))
    if cal.notes:
        out.append(Setting((*base, "reference_tolerance_mm"), _mm(cal.tolerance_mm),
                           f"kept: {'; '.join(cal.notes)}", after="reference_hysteresis_mm"))
    else:
        out.append(Setting((*base, "reference_tolerance_mm"), _mm(cal.tolerance_mm),
                           f"commissioned: largest residual {cal.max_residual_mm:.2f} mm + "
                           f"{spread_factor:g} x spread up to {cal.max_spread_mm:.2f} mm over "
                           f"{shared} (datasheet {cal.configured_tolerance_mm:g})",
                           after="reference_hysteresis_mm"))
    return out


def write_config(datasheet: Path, out: Path, cals: Mapping[str, UnitCalibration],
                 spread_factor: float) -> Config:
    """Write the commissioned file atomically, only once it loads as a configuration."""
    try:
        text = datasheet.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{datasheet}: cannot read: {exc}") from None
    items = [s for cal in cals.values() for s in settings(cal, spread_factor)]
    new = set_values(text, str(datasheet), items)
    with atomic_path(out) as tmp:
        tmp.write_text(new, encoding="utf-8")
        try:
            cfg = load_config(tmp)
        except UserError as exc:
            raise UserError(f"{out}: the commissioned configuration does not load: "
                            f"{str(exc).replace(str(tmp), str(out))}") from None
    return cfg


def _number(x: float) -> float | None:
    return None if math.isnan(x) else round(x, 4)


def report_data(cals: Mapping[str, UnitCalibration]) -> dict[str, Any]:
    """Per unit and switch: the calibrated values, each kind's statistics, every edge."""
    units: dict[str, Any] = {}
    for unit, cal in cals.items():
        units[unit] = {
            "window_mm": cal.window_mm, "hysteresis_mm": cal.hysteresis_mm,
            "tolerance_mm": cal.tolerance_mm, "fitted": list(cal.fitted),
            "configured": {"window_mm": cal.configured_window_mm,
                           "hysteresis_mm": cal.configured_hysteresis_mm,
                           "tolerance_mm": cal.configured_tolerance_mm},
            "max_residual_mm": _number(cal.max_residual_mm),
            "max_spread_mm": _number(cal.max_spread_mm),
            "max_interpolation_bound_mm": _number(cal.max_bound_mm),
            "standstill_edges": cal.standstill_edges, "notes": cal.notes,
            "switches": {s.name: {
                "configured_mm": s.configured_mm, "position_mm": _number(s.position_mm),
                "tolerance_mm": _number(s.tolerance_mm), "problem": s.problem,
                "required": [KIND_KEYS[k] for k in s.required],
                "kinds": {st.key: {"count": st.count, "mean_mm": _number(st.mean_mm),
                                   "spread_mm": _number(st.spread_mm),
                                   "configured_mm": st.configured_mm,
                                   "fitted_mm": _number(st.fitted_mm)}
                          for st in s.kinds.values()},
                "edges": [{"source": e.source, "time_s": round(e.time_s, 6),
                           "position_mm": round(e.position_mm, 4), "kind": KIND_KEYS[
                               (e.rising, e.moving_up)],
                           "velocity_mm_s": round(e.velocity_mm_s, 2),
                           "bound_mm": round(e.bound_mm, 4), "timed": e.timed}
                          for e in s.edges]}
                for s in cal.switches.values()}}
    return {"units": units}


_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Commissioned Hall switches</title>
<style>body{font-family:sans-serif;max-width:60em;margin:2em auto}
table{border-collapse:collapse;margin:0.5em 0 1.5em}td,th{border:1px solid #bbb;padding:2px 8px}
td{text-align:right}.bad{color:#a00}</style></head><body>
<h1>Commissioned Hall switches</h1>
<p>Switching positions (mm) measured at the rod's draw-wire position; the model is one position
per switch and the unit's common window and hysteresis. Every edge is in commission.json.</p>
{% for unit, u in units.items() %}
<h2>{{ unit }}</h2>
<p>window {{ "%.2f"|format(u.window_mm) }} mm (datasheet {{ u.configured.window_mm }}),
hysteresis {{ "%.2f"|format(u.hysteresis_mm) }} mm ({{ u.configured.hysteresis_mm }}),
tolerance {{ "%.2f"|format(u.tolerance_mm) }} mm ({{ u.configured.tolerance_mm }});
fitted: {{ u.fitted|join(", ") or "positions only" }}.
{% for note in u.notes %}<br>{{ note }}{% endfor %}</p>
<table><tr><th>switch</th><th>p</th><th>kind</th><th>edges</th><th>mean</th><th>spread</th>
<th>model</th><th>datasheet</th></tr>
{% for name, s in u.switches.items() %}
{% if s.problem %}<tr><th>{{ name }}</th><td colspan="7" class="bad">{{ s.problem }}</td></tr>
{% else %}{% for key, k in s.kinds.items() if k.count %}
<tr><th>{{ name }}</th><td>{{ s.position_mm }}</td><td>{{ key }}</td><td>{{ k.count }}</td>
<td>{{ "%.3f"|format(k.mean_mm) }}</td>
<td>{{ "%.3f"|format(k.spread_mm) if k.spread_mm is not none else "" }}</td>
<td>{{ "%.2f"|format(k.fitted_mm) }}</td><td>{{ k.configured_mm }}</td></tr>
{% endfor %}{% endif %}{% endfor %}</table>
{% endfor %}</body></html>
"""


def write_report(directory: Path, cals: Mapping[str, UnitCalibration]) -> Path:
    """commission.json (every edge) and commission.html (the table per switch); returns
    the JSON's path."""
    data = report_data(cals)
    path = directory / "commission.json"
    with atomic_write(path) as fh:
        json.dump(data, fh, indent=1)
        fh.write("\n")
    page = jinja2.Environment(autoescape=True, trim_blocks=True,
                              undefined=jinja2.StrictUndefined).from_string(_PAGE)
    with atomic_write(directory / "commission.html") as fh:
        fh.write(page.render(units=data["units"]))
    return path
