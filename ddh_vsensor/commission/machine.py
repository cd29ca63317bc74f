"""The commissioned configuration: the datasheet file with the calibrated switch keys and the
measured flow model set and commented with their evidence, checked by loading it; and the
evidence behind them as JSON and HTML."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jinja2
import yaml

from ddh_vsensor.atomic import atomic_path, atomic_write
from ddh_vsensor.commission.flow import (MACHINE_WIDE, Estimate, FlowFit, applied,
                                         machine_wide)
from ddh_vsensor.commission.drive import DriveFit
from ddh_vsensor.commission.switches import KIND_KEYS, UnitCalibration
from ddh_vsensor.commission.yaml_text import Setting, set_values
from ddh_vsensor.config import Config, load_config, parse_config, parse_yaml
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


# A band written from a fit is 3 sigma, never narrower than what the pressures allow: read
# from the torque, the chambers' split of it and the pumps' torque efficiencies scale the
# pressures and so the leakage (and, less, the displacement) fitted to them; logged, the
# transducers' calibration. Measured on bench/commission.py's drawn machines (the floors
# cover their worst): see docs/commission.md
COVERAGE = 3.0
FLOORS = {"estimated": {"leakage": 0.35, "displacement": 0.01, "orifice_share": 0.4},
          "logged": {"leakage": 0.16, "displacement": 0.0025, "orifice_share": 0.12}}


def _evidence(e: Estimate, fit: FlowFit) -> str:
    return (f"+-{e.sd:.4g} (1 sigma), {sum(fit.loaded_windows.values())} loaded windows, "
            f"pressures {fit.pressures}")


def _band(fit: FlowFit, name: str, sd: float) -> float:
    floors = FLOORS["estimated" if "estimated" in fit.pressures else "logged"]
    return max(COVERAGE * sd, floors[name])


def _configured(cfg: Config, own: float | None, key: str) -> float:
    """The band the configuration has now: the pump's or unit's own, else the machine's (a
    fit never widens it)."""
    return getattr(cfg.tolerances, key) if own is None else own


def flow_settings(cfg: Config, fits: Mapping[str, FlowFit], last_hydraulics_key: str,
                  tolerances: bool) -> list[Setting]:
    """The keys of the measured flow model, each with its evidence, and the bands of what is
    now known: each measured pump's leakage band, a unit's displacement band where both its
    sides were measured; a value the runs did not identify keeps the datasheet's (and its
    band) with what would measure it. ``tolerances``: the file has a ``tolerances`` section
    (the orifice share's band is the machine's: narrowed where every unit measured it)."""
    out = []
    measured = applied(cfg, dict(fits))     # the values, converted once
    for unit, fit in fits.items():
        bands: list[float] = []
        for side in ("a", "b"):
            base = ("units", unit, f"pump_{side}")
            pump = getattr(cfg.unit(unit), f"pump_{side}")
            new = getattr(measured.unit(unit), f"pump_{side}")
            d = fit.displacement[side]
            if d.identified:
                out.append(Setting((*base, "displacement_cm3_rev"),
                                   f"{new.displacement_cm3_rev:.4g}",
                                   f"commissioned: x{d.value:.4f} the datasheet's "
                                   f"({pump.displacement_cm3_rev:g}) per the cylinder's area "
                                   f"{_evidence(d, fit)}"))
                bands.append(_band(fit, "displacement", d.sd))
            else:
                out.append(Setting((*base, "displacement_cm3_rev"), None,
                                   f"not commissioned: {d.problem}"))
            e = fit.leakage[side]
            if e.identified:
                out.append(Setting((*base, "volumetric_efficiency"),
                                   f"{new.volumetric_efficiency:.4f}",
                                   f"commissioned: leakage x{e.value:.3f} the datasheet's "
                                   f"({pump.volumetric_efficiency:g}) {_evidence(e, fit)}"))
                band = _band(fit, "leakage", e.sd / e.value)
                if band < _configured(cfg, pump.leakage_tolerance, "pump_leakage"):
                    out.append(Setting((*base, "leakage_tolerance"), f"{band:.3f}",
                                       f"commissioned: {COVERAGE:g} sigma, at least the floor "
                                       f"of pressures {fit.pressures}",
                                       after="volumetric_efficiency"))
            else:
                out.append(Setting((*base, "volumetric_efficiency"), None,
                                   f"not commissioned: {e.problem}"))
            for key, est in (("leakage_orifice_share", fit.orifice_share),
                             ("leakage_speed_gain", fit.speed_gain)):
                if est.identified:
                    out.append(Setting((*base, key), f"{est.value:.3f}",
                                       f"commissioned: {_evidence(est, fit)}",
                                       after="volumetric_efficiency"))
        if len(bands) == 2 and max(bands) < _configured(
                cfg, cfg.unit(unit).displacement_tolerance, "pump_displacement"):
            out.append(Setting(("units", unit, "displacement_tolerance"), f"{max(bands):.4f}",
                               f"commissioned: both sides' displacement, {COVERAGE:g} sigma, "
                               f"at least the floor of pressures {fit.pressures}",
                               after="dead_volume_l"))
    for key in MACHINE_WIDE:
        e = machine_wide(fits, key)
        if e is not None:
            pressures = ", ".join(sorted({f.pressures for f in fits.values()}))
            out.append(Setting(("hydraulics", key), f"{getattr(measured.hydraulics, key):.4f}",
                               f"commissioned: +-{e.sd:.4f} (1 sigma) from the units' windows, "
                               f"pressures {pressures}", after=last_hydraulics_key))
    shares = [f for f in fits.values() if f.orifice_share.identified]
    band = max((_band(f, "orifice_share", f.orifice_share.sd) for f in shares), default=1.0)
    if (tolerances and len(shares) == len(cfg.unit_names)
            and band < cfg.tolerances.leakage_orifice_share):
        out.append(Setting(("tolerances", "leakage_orifice_share"), f"{band:.3f}",
                           f"commissioned: {COVERAGE:g} sigma of every unit's fitted share, "
                           "at least the floor of its pressures"))
    return out


# a pressure transducer's accuracy (bar): what a drive offset measured through it is known to
TRANSDUCER_BAR = 1.0


def drive_settings(cfg: Config, drives: Mapping[str, DriveFit]) -> list[Setting]:
    """The drive's reading of the shaft's torque where the runs measured it: its gain (1,
    and why, where the runs' torques were too close together to tell it), offset (and the
    band now known of it: 3 sigma, at least what a transducer's accuracy puts through the
    larger pump's gain), speed offset and filter. Where they did not, the keys stay as they
    are (the command says why)."""
    out = []
    for unit, fit in drives.items():
        if not fit.measured:
            continue
        base = ("units", unit, "motor")
        evidence = (f"{fit.blocks} s of turning with logged pressures, residual "
                    f"{fit.residual_rms_nm:.3f} N*m RMS")
        u = cfg.unit(unit)
        gain = max(p.displacement_cm3_rev * 1e-6 * p.speed_ratio / (2.0 * math.pi)
                   for p in (u.pump_a, u.pump_b))
        band = max(COVERAGE * fit.offset_sigma_nm, gain * TRANSDUCER_BAR * 1e5)
        # each missing key goes after the motor's last required one, so listed last first
        out += [Setting((*base, "torque_offset_tolerance_nm"), f"{band:.3f}",
                        f"commissioned: {COVERAGE:g} sigma, at least a transducer's "
                        f"{TRANSDUCER_BAR:g} bar through the pumps", after="speed_limit_rpm"),
                Setting((*base, "torque_filter_s"), f"{fit.filter_s:.4f}",
                        "commissioned: the filter time that left the least residual",
                        after="speed_limit_rpm"),
                Setting((*base, "torque_speed_offset_nm"), f"{fit.speed_offset_nm:.3f}",
                        f"commissioned: +-{fit.speed_offset_sigma_nm:.3f} (1 sigma) at the "
                        "speed limit", after="speed_limit_rpm"),
                Setting((*base, "torque_offset_nm"), f"{fit.offset_nm:.3f}",
                        f"commissioned: +-{fit.offset_sigma_nm:.3f} (1 sigma), {evidence}",
                        after="speed_limit_rpm"),
                Setting((*base, "torque_gain"), f"{fit.gain:.4f}",
                        f"not commissioned: {fit.gain_why_not} (the offsets are fitted at 1)"
                        if fit.gain_why_not else
                        f"commissioned: +-{fit.gain_sigma:.4f} (1 sigma), shaft torques "
                        f"spanning {fit.torque_span_nm:.1f} N*m", after="speed_limit_rpm")]
    return out


def read_datasheet(datasheet: Path) -> str:
    try:
        return datasheet.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{datasheet}: cannot read: {exc}") from None


def commissioned_text(text: str, source: str, cals: Mapping[str, UnitCalibration],
                      spread_factor: float, flows: Mapping[str, FlowFit] | None = None,
                      cfg: Config | None = None,
                      drives: Mapping[str, DriveFit] | None = None) -> str:
    """The datasheet file's ``text`` with the measured keys set (``cfg``: the datasheet's
    configuration, needed with ``flows`` or ``drives``)."""
    items = [s for cal in cals.values() for s in settings(cal, spread_factor)]
    if drives:
        if cfg is None:
            raise ValueError("the drive settings need the datasheet's configuration")
        items += drive_settings(cfg, drives)
    if flows:
        if cfg is None:
            raise ValueError("the flow settings need the datasheet's configuration")
        data = yaml.safe_load(text) or {}
        hydraulics = list((data.get("hydraulics") or {}).keys())
        items += flow_settings(cfg, flows, hydraulics[-1] if hydraulics else "",
                               isinstance(data.get("tolerances"), dict))
    return set_values(text, source, items)


def commissioned_config(text: str, source: str, cals: Mapping[str, UnitCalibration],
                        spread_factor: float, flows: Mapping[str, FlowFit] | None = None,
                        cfg: Config | None = None,
                        drives: Mapping[str, DriveFit] | None = None) -> Config:
    """The configuration :func:`write_config` would write, in memory (rounded as written):
    what a baseline's fold is estimated with."""
    new = commissioned_text(text, source, cals, spread_factor, flows, cfg, drives)
    return parse_config(parse_yaml(new, source), source)


def write_config(datasheet: Path, out: Path, cals: Mapping[str, UnitCalibration],
                 spread_factor: float, flows: Mapping[str, FlowFit] | None = None,
                 cfg: Config | None = None,
                 drives: Mapping[str, DriveFit] | None = None) -> Config:
    """Write the commissioned file atomically, only once it loads as a configuration
    (``cfg``: the datasheet file's, loaded; needed with ``flows`` or ``drives``)."""
    new = commissioned_text(read_datasheet(datasheet), str(datasheet), cals, spread_factor,
                            flows, cfg, drives)
    with atomic_path(out) as tmp:
        tmp.write_text(new, encoding="utf-8")
        try:
            cfg = load_config(tmp)
        except UserError as exc:
            raise UserError(f"{out}: the commissioned configuration does not load: "
                            f"{str(exc).replace(str(tmp), str(out))}") from None
    return cfg


def _number(x: float) -> float | None:
    return None if not math.isfinite(x) else round(x, 4)


def _estimate_data(e: Estimate) -> dict[str, Any]:
    return {"value": round(e.value, 5), "sd": _number(e.sd), "identified": e.identified,
            "datasheet": e.datasheet, "problem": e.problem}


def flow_data(fit: FlowFit) -> dict[str, Any]:
    """One unit's fitted flow model as the report's JSON has it."""
    return {"pressures": fit.pressures, "windows": fit.windows,
            "loaded_windows": fit.loaded_windows,
            "leakage_factor": {s: _estimate_data(e) for s, e in fit.leakage.items()},
            "displacement_factor": {s: _estimate_data(e) for s, e in fit.displacement.items()},
            "orifice_share": _estimate_data(fit.orifice_share),
            "speed_gain": _estimate_data(fit.speed_gain),
            "hose_expansion_per_100bar": _estimate_data(fit.hose_expansion_per_100bar),
            "air_fraction": _estimate_data(fit.air_fraction),
            "residual_rms_ml": fit.residual_rms_ml, "datasheet_rms_ml": fit.datasheet_rms_ml,
            "rows": [{"name": name, **_estimate_data(e)} for name, e in fit.named()]}


def report_data(cals: Mapping[str, UnitCalibration],
                flows: Mapping[str, FlowFit] | None = None) -> dict[str, Any]:
    """Per unit and switch: the calibrated values, each kind's statistics, every edge; per
    unit the fitted flow model."""
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
    for unit, fit in (flows or {}).items():
        units.setdefault(unit, {})["flow"] = flow_data(fit)
    return {"units": units}


_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Commissioned machine</title>
<style>body{font-family:sans-serif;max-width:60em;margin:2em auto}
table{border-collapse:collapse;margin:0.5em 0 1.5em}td,th{border:1px solid #bbb;padding:2px 8px}
td{text-align:right}.bad{color:#a00}</style></head><body>
<h1>Commissioned machine</h1>
<p>Switching positions (mm) measured at the rod's draw-wire position; the model is one position
per switch and the unit's common window and hysteresis. Every edge is in commission.json.</p>
{% for unit, u in units.items() %}
<h2>{{ unit }}</h2>
{% if "flow" in u %}
<h3>Flow model</h3>
<p>Chamber pressures {{ u.flow.pressures }}; balance windows A {{ u.flow.windows.a }},
B {{ u.flow.windows.b }} (loaded A {{ u.flow.loaded_windows.a }}, B {{ u.flow.loaded_windows.b }}).
{% for side, rms in u.flow.residual_rms_ml.items() %}<br>side {{ side|upper }}: residual
{{ "%.2f"|format(rms) }} ml per window, datasheet model
{{ "%.2f"|format(u.flow.datasheet_rms_ml[side]) }}{% endfor %}</p>
<table><tr><th>parameter</th><th>value</th><th>sigma</th><th>datasheet</th><th>measured</th></tr>
{% for e in u.flow.rows %}
<tr><th>{{ e.name }}</th><td>{{ e.value }}</td><td>{{ e.sd if e.sd is not none else "" }}</td>
<td>{{ e.datasheet }}</td><td{% if not e.identified %} class="bad"{% endif %}>
{{ "yes" if e.identified else e.problem }}</td></tr>
{% endfor %}</table>
{% endif %}
{% if "switches" in u %}
<h3>Hall switches</h3>
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
{% endif %}
{% endfor %}</body></html>
"""


def write_report(directory: Path, cals: Mapping[str, UnitCalibration],
                 flows: Mapping[str, FlowFit] | None = None) -> Path:
    """commission.json (every edge, the flow fits) and commission.html (the tables per
    unit); returns the JSON's path."""
    data = report_data(cals, flows)
    path = directory / "commission.json"
    with atomic_write(path) as fh:
        json.dump(data, fh, indent=1)
        fh.write("\n")
    page = jinja2.Environment(autoescape=True, trim_blocks=True,
                              undefined=jinja2.StrictUndefined).from_string(_PAGE)
    with atomic_write(directory / "commission.html") as fh:
        fh.write(page.render(units=data["units"]))
    return path
