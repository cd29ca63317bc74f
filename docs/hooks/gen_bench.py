"""Accuracy and performance figures from the benches' committed JSON (bench/results)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from gen_code import table

MODES = ("dynamic", "full", "paper")


def fmt(value: Any) -> str:
    """A figure as the JSON holds it (the benches round; nothing is re-rounded here)."""
    if isinstance(value, bool) or value is None:
        return str(value).lower()
    if isinstance(value, (int, float)):
        return str(value)
    if isinstance(value, list):
        return ", ".join(fmt(v) for v in value)
    return str(value)


def load(root: Path, name: str) -> dict[str, Any]:
    path = root / "bench" / "results" / f"{name}.json"
    if not path.is_file():
        raise ValueError(f"{path.relative_to(root)} is not there: run the bench and commit "
                         "its JSON")
    return json.loads(path.read_text(encoding="utf-8"))


def provenance(record: dict[str, Any]) -> str:
    command = record.get("command")
    how = f"`{command}`" if command else "a command line the file does not record"
    load_avg = record.get("load_average_1min")
    host = (f"{record.get('cpus', '?')} CPUs, {record.get('machine', '?')}, "
            f"Python {record.get('python', '?')}")
    if load_avg is not None:
        host += f", 1-minute load average {load_avg} when it ended"
    return (f"Measured by {how} ({host}; {record.get('when', 'time not recorded')}; "
            f"`bench/results/{record['benchmark']}.json`).\n")


def _flatten(figures: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    rows = []
    for key, value in figures.items():
        if isinstance(value, dict):
            rows += _flatten(value, f"{prefix}{key}.")
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            for i, item in enumerate(value):
                rows += _flatten(item, f"{prefix}{key}[{i}].")
        else:
            rows.append((f"{prefix}{key}", value))
    return rows


def _units(figures: dict[str, Any], pattern: str) -> list[str]:
    seen: list[str] = []
    for key in figures:
        m = re.match(pattern, key)
        if m and m.group("unit") not in seen:
            seen.append(m.group("unit"))
    return seen


# --- accuracy.json -----------------------------------------------------------------------

_WORST = r"^(?P<mode>dynamic|full|paper)_(?P<unit>[a-z0-9_]+?)_worst_max_abs_error_mm$"
_NOMINAL = (r"^(?P<mode>dynamic|full|paper)_(?P<unit>[a-z0-9_]+?)_speed(?P<speed>\d+)_"
            r"(?P<kg>[\d.]+)kg$")
_CYCLES = (r"^(?P<mode>dynamic|full|paper)_(?P<unit>[a-z0-9_]+?)_(?P<n>\d+)cycles_"
           r"(?P<kind>norefs|refs_rows|refs)_(?P<what>max_abs_error_mm|first10_max_mm|"
           r"last10_max_mm)$")
_DRIFT = r"^(?P<mode>dynamic|full|paper)_(?P<unit>[a-z0-9_]+?)_drift_per_cycle_norefs_mm$"
_KIND = {"norefs": "no references", "refs": "references timed by the I/O module",
         "refs_rows": "references at the samples"}


def _worst_table(figures: dict[str, Any], consumed: set[str]) -> str:
    units = _units(figures, _WORST)
    rows = []
    for mode in MODES:
        keys = [f"{mode}_{u}_worst_max_abs_error_mm" for u in units]
        if all(k in figures for k in keys):
            rows.append([f"`{mode}`", *(fmt(figures[k]) for k in keys)])
            consumed.update(keys)
    return table(["mode", *(f"{u}: worst \\|error\\| (mm)" for u in units)], rows)


def accuracy_headline(root: Path) -> str:
    """One sentence with the figure that matters: the default mode's worst error."""
    figures = load(root, "accuracy")["figures"]
    units = _units(figures, _WORST)
    parts = [f"{u} {fmt(figures[f'dynamic_{u}_worst_max_abs_error_mm'])} mm" for u in units]
    paper = [f"{fmt(figures[f'paper_{u}_worst_max_abs_error_mm'])}" for u in units
             if f"paper_{u}_worst_max_abs_error_mm" in figures]
    text = (f"Worst position error of the default `dynamic` mode over the paper's work cycle "
            f"(simulated, oil at 27 °C, speeds 1–4, empty and 1040 kg, no references): "
            f"**{', '.join(parts)}**")
    if len(paper) == len(units):
        text += f"; the paper's own method on the same runs: {' / '.join(paper)} mm"
    return text + ".\n"


def _accuracy(figures: dict[str, Any], consumed: set[str]) -> str:
    out = ["### Worst error per mode\n", ("Over the nominal runs (the paper's cycle at "
           "speeds 1–4, empty and 1040 kg, oil at 27 °C), no references.\n"),
           _worst_table(figures, consumed)]
    cells: dict[tuple[str, str], dict[str, str]] = {}
    columns: list[str] = []
    for key, value in figures.items():
        m = re.match(_NOMINAL, key)
        if not m or not isinstance(value, dict):
            continue
        column = f"speed {m['speed']}, {m['kg']} kg"
        if column not in columns:
            columns.append(column)
        cells.setdefault((m["mode"], m["unit"]), {})[column] = (
            f"{fmt(value.get('max_abs_error_mm'))} / {fmt(value.get('rms_error_mm'))}")
        consumed.add(key)
    if cells:
        out += ["### Per run\n", "Maximum / RMS error (mm) per run, no references.\n",
                table(["mode", "unit", *columns],
                      [[f"`{mode}`", unit, *(row.get(c, "") for c in columns)]
                       for (mode, unit), row in cells.items()])]
    runs: dict[tuple[str, str, str, str], dict[str, Any]] = {}
    for key, value in figures.items():
        m = re.match(_CYCLES, key)
        if m:
            runs.setdefault((m["n"], m["mode"], m["unit"], m["kind"]), {})[m["what"]] = value
            consumed.add(key)
    if runs:
        n = next(iter(runs))[0]
        rows = []
        for (_, mode, unit, kind), row in runs.items():
            drift_key = f"{mode}_{unit}_drift_per_cycle_norefs_mm"
            drift = fmt(figures[drift_key]) if kind == "norefs" and drift_key in figures else ""
            consumed.add(drift_key)
            rows.append([f"`{mode}`", unit, _KIND[kind], fmt(row.get("max_abs_error_mm")),
                         fmt(row.get("first10_max_mm")), fmt(row.get("last10_max_mm")), drift])
        out += [f"### {n} cycles in a row\n", (f"The paper's cycle {n} times at speed 4, "
                "empty, the oil warming from 27 °C: worst error overall, over the first and "
                "the last ten cycles, and the drift per cycle without references.\n"),
                table(["mode", "unit", "references", "max (mm)", "first 10 (mm)",
                       "last 10 (mm)", "drift per cycle (mm)"], rows)]
    return "\n".join(out)


_SWEEP = (r"^(?P<set>[a-z0-9.]+(?:_[a-z0-9.]+)*?)_(?P<mode>dynamic|full|paper)_"
          r"(?P<unit>[a-z0-9]+)_(?P<temp>-?[\d.]+)C_(?P<what>max_abs_error_mm|rms_error_mm|"
          r"worst_run)$")


def _sweep(figures: dict[str, Any], consumed: set[str]) -> str:
    """The temperature sweep: per oil temperature, mode and unit, max / RMS error."""
    cells: dict[str, dict[str, dict[str, Any]]] = {}
    columns: list[str] = []
    sets: list[str] = []
    for key, value in figures.items():
        m = re.match(_SWEEP, key)
        if not m:
            continue
        column = f"`{m['mode']}` {m['unit']}"
        if column not in columns:
            columns.append(column)
        if m["set"] not in sets:
            sets.append(m["set"])
        cells.setdefault(m["temp"], {}).setdefault(column, {})[m["what"]] = value
        consumed.add(key)
    if not cells:
        return ""
    rows = [[f"{temp} °C", *(f"{fmt(c.get(col, {}).get('max_abs_error_mm'))} / "
                               f"{fmt(c.get(col, {}).get('rms_error_mm'))}" for col in columns)]
            for temp, c in cells.items()]
    worst = [[f"{temp} °C", *(fmt(c.get(col, {}).get("worst_run", "")) for col in columns)]
             for temp, c in cells.items()]
    return "\n".join([
        f"### Temperature sweep (`{', '.join(sets)}`)\n",
        ("Per oil temperature, over the set's runs (the paper's cycle at several speeds and "
        "payloads, the dig-dump cycle and random work cycles with end-stop contact), no "
        "references: maximum / RMS error (mm).\n"),
        table(["oil", *columns], rows),
        "The run each maximum came from:\n",
        table(["oil", *columns], worst)])


def _accuracy_all(figures: dict[str, Any], consumed: set[str]) -> str:
    return "\n".join(p for p in (_accuracy(figures, consumed), _sweep(figures, consumed)) if p)


_DAEMON_COLUMNS = (("latency_p50_ms", "latency p50 (ms)"), ("latency_p99_ms", "latency p99 (ms)"),
                   ("jitter_p99_ms", "jitter p99 (ms)"), ("cpu_share_pct", "CPU share (%)"),
                   ("sevcon_frames_lost", "Sevcon frames lost"))
_DAEMON_GOALS = {"latency_p99_ms": "goal_latency_p99_ms", "jitter_p99_ms": "goal_jitter_p99_ms",
                 "cpu_share_pct": "goal_cpu_share_pct"}


def _daemon(figures: dict[str, Any], consumed: set[str]) -> str:
    """Headline per mode and load: latency, jitter, CPU share, frames lost, and the goals."""
    runs = []
    for key in figures:
        m = re.match(r"^(?P<run>[a-z]+_(?:nominal|saturated))_latency_p50_ms$", key)
        if m:
            runs.append(m["run"])
    if not runs:
        return ""
    rows = []
    for run in runs:
        mode, load = run.split("_", 1)
        row: list[object] = [f"`{mode}`", load]
        for suffix, _ in _DAEMON_COLUMNS:
            key = f"{run}_{suffix}"
            row.append(fmt(figures[key]) if key in figures else "")
            consumed.add(key)
        rows.append(row)
    goals: list[object] = ["goal", ""]
    for suffix, _ in _DAEMON_COLUMNS:
        key = _DAEMON_GOALS.get(suffix)
        goals.append(f"≤ {fmt(figures[key])}" if key in figures else "")
        consumed.add(key or "")
    if "goal_lost_at_8000_fps" in figures:
        goals[-1] = f"{fmt(figures['goal_lost_at_8000_fps'])} (saturated)"
        consumed.add("goal_lost_at_8000_fps")
    return "\n".join(["### Headline\n",
                      table(["mode", "load", *(label for _, label in _DAEMON_COLUMNS)],
                            [*rows, goals])])


_DIAGNOSIS_COLUMNS = (("named_exactly", "named exactly"),
                      ("false_unexplained", "false `unexplained`"),
                      ("ambiguous", "ambiguous"), ("halved", "max error halved"),
                      ("median_max_error_mm", "median max error (mm)"),
                      ("interval_coverage", "90 % intervals cover"))


def _diagnosis(figures: dict[str, Any], consumed: set[str]) -> str:
    """Per hidden-effect class: how often the diagnosis answered right, and what it gained."""
    suffixes = "|".join(suffix for suffix, _ in _DIAGNOSIS_COLUMNS)
    classes: list[str] = []
    for key in figures:
        m = re.match(rf"^(?P<cls>[a-z_]+?)_(?:{suffixes})$", key)
        if m and m["cls"] not in classes and not m["cls"].startswith(("goal", "single")):
            classes.append(m["cls"])
    rows = []
    for cls in classes:
        row: list[object] = [f"`{cls}`"]
        for suffix, _ in _DIAGNOSIS_COLUMNS:
            key = f"{cls}_{suffix}"
            row.append(fmt(figures[key]) if key in figures else "")
            consumed.add(key)
        rows.append(row)
    if not rows:
        return ""
    return "\n".join(["### Per class\n", ("A class is a hidden catalogue cause, a pair of "
                      "them, or a deviation outside the catalogue (`outside`: named exactly "
                      "means answered `unexplained`).\n"),
                      table(["class", *(label for _, label in _DIAGNOSIS_COLUMNS)], rows)])


# --- kalman.json --------------------------------------------------------------------------
_KALMAN_COLUMNS = (("max_abs_error_mm", "worst mm"), ("median_uncertainty_mm", "median u mm"),
                   ("unflagged_beyond_uncertainty_share", "unflagged beyond u"))
_LEVELS = {"none": "nominal", "typical": "structure typical", "double": "structure x2"}


def _kalman(figures: dict[str, Any], consumed: set[str]) -> str:
    """Per set, plant, references and unit: the filter against `dynamic` (the per-run lists
    are the bench's detail, left to its JSON)."""
    consumed.update(k for k in figures if k.endswith("_runs"))
    rows = []
    for key in figures:
        parts = key.split("_")
        if len(parts) != 5 or parts[3] != "kalman" or not isinstance(figures[key], dict):
            continue
        which, level, refs, _, unit = parts
        other = "_".join([which, level, refs, "dynamic", unit])
        cells = [which.replace("heldout", "held out"), _LEVELS.get(level, level),
                 "yes" if refs == "refs" else "no", unit]
        for name in (key, other):
            consumed.add(name)
            record = figures.get(name, {})
            for field, _ in _KALMAN_COLUMNS:
                value = record.get(field)
                cells.append(f"{100 * value:.2f} %" if field.endswith("share") and value
                             is not None else fmt(value))
        rows.append(cells)
    heads = ["set", "plant", "refs", "unit",
             *(f"kalman {label}" for _, label in _KALMAN_COLUMNS),
             *(f"dynamic {label}" for _, label in _KALMAN_COLUMNS)]
    return table(heads, rows)


# --- commission.json ----------------------------------------------------------------------
_COMMISSION_CASES = (("before", "datasheet"), ("after_estimated", "commissioned, pressures "
                     "read from the torque"), ("after_logged", "commissioned, pressures logged"))


def _commission(figures: dict[str, Any], consumed: set[str]) -> str:
    """Per configuration, references and unit: the worst validation run from 27 degC up and
    below, how many machines are within the issue's bands, the median uncertainty and how
    many machines published a value beyond its uncertainty with no flag (per machine: the
    JSON's ``per_machine``, with each drawn machine's truth)."""
    consumed.add("per_machine")
    n = figures["machines"]
    rows = []
    for case, label in _COMMISSION_CASES:
        for refs in ("norefs", "refs"):
            units = sorted({k.split("_")[-4] for k in figures
                            if k.startswith(f"{case}_{refs}_") and k.endswith("_warm_max_mm")})
            for unit in units:
                base = f"{case}_{refs}_{unit}_"
                keys = [base + k for k in ("warm_max_mm", "cold_max_mm", "warm_within_0_5mm",
                                           "cold_within_1_0mm", "median_uncertainty_mm",
                                           "machines_with_unflagged_beyond")]
                consumed.update(keys)
                w, c, wn, cn, u, bad = (figures[k] for k in keys)
                rows.append([label, "yes" if refs == "refs" else "no", unit, fmt(w), fmt(c),
                             f"{wn}/{n}", f"{cn}/{n}", fmt(u), f"{bad}/{n}"])
    return table(["configuration", "refs", "unit", "worst mm from 27 degC",
                  "worst mm below", "machines within 0.5 mm (27 degC up)",
                  "machines within 1.0 mm (below)", "median u mm",
                  "machines with an unflagged value beyond u"], rows)


def _fleet_acceptance(figures: dict[str, Any], consumed: set[str]) -> str:
    """Per fleet: seen while designing or drawn after, the wears due a warning and those
    warned in time with the right cause, the misses, false alarms, and the cluster check."""
    consumed.add("fleets")
    rows = []
    for seed, f in figures["fleets"].items():
        due = next(v for k, v in f.items() if k.startswith("crossing on day"))
        ok = next(v for k, v in f.items() if k.startswith("of those alarmed"))
        remote = f.get("scheduler + 2 workers: identical alarms")
        rows.append([seed, f["set"], f"{ok}/{due}", "; ".join(f["missed"]) or "none",
                     fmt(f["false alarms"]), fmt(f["false alarms per 20 machine-months"]),
                     "" if remote is None else fmt(remote), "yes" if f["passes"] else "no"])
    return table(["seed", "set", "warned in time / due", "missed", "false alarms",
                  "per 20 machine-months", "scheduler + 2 workers identical", "passes"], rows)


def _switches(figures: dict[str, Any], consumed: set[str]) -> str:
    """Per configuration (the datasheet's switch positions, or the commissioned ones),
    estimator and unit, with references: the worst run, the runs within 0.5 mm, the median
    uncertainty and what was published beyond it with no flag (per machine and run: the
    JSON's ``per_machine`` and ``failures``, not rendered)."""
    consumed.update({"per_machine", "failures", "sources", "sources_at_end"})
    rows = []
    for key, v in figures.items():
        m = re.fullmatch(r"(uncommissioned|commissioned)_([a-z]+)_([a-z0-9_]+)", key)
        if not (m and isinstance(v, dict) and "max_abs_error_mm" in v):
            continue
        consumed.add(key)
        config, estimator, unit = m.groups()
        rows.append([config, estimator, unit, fmt(v["max_abs_error_mm"]),
                     f"{v['runs_within_0_5mm']}/{v['runs']}", fmt(v["median_uncertainty_mm"]),
                     fmt(v["unflagged_beyond_share"]), fmt(v["max_unflagged_excess_mm"])])
    return table(["switch positions", "estimator", "unit", "worst mm", "runs within 0.5 mm",
                  "median u mm", "share unflagged beyond u", "largest unflagged excess mm"],
                 rows)


_ORACLE_RUNS = (("commission", "as commissioned"),
                ("commission_ideal_drive", "the drive's torque reading exact"),
                ("commission_oracle_pumps", "+ the pumps' true parameters"),
                ("commission_oracle_friction", "+ the true friction"),
                ("commission_oracle_air", "+ the true entrained air"),
                ("commission_oracle_air_friction_pumps", "+ all three"),
                ("commission_oracle_air_friction_pumps_ideal_drive",
                 "+ all three, the reading exact"))


def commission_oracles(root: Path) -> str:
    """The commission bench's machines again, each time knowing one more thing the
    calibration day did not measure (``--oracle``, ``--ideal-drive``): per unit, no
    references, the median and the worst machine's worst run from 27 degC up, with the
    pressures logged and read from the torque."""
    rows = []
    for name, label in _ORACLE_RUNS:
        figures = load(root, name)["figures"]
        units = [k.removeprefix("after_logged_norefs_").removesuffix("_warm_median_mm")
                 for k in figures
                 if k.startswith("after_logged_norefs_") and k.endswith("_warm_median_mm")]
        for unit in units:
            cells = []
            for how in ("logged", "estimated"):
                base = f"after_{how}_norefs_{unit}_"
                cells += [fmt(figures[base + "warm_median_mm"]),
                          fmt(figures[base + "warm_max_mm"])]
            rows.append([label, unit, *cells])
    return table(["what is known", "unit", "logged: median mm", "logged: worst mm",
                  "read from the torque: median mm", "read from the torque: worst mm"], rows)


CURATED = {"accuracy": _accuracy_all, "daemon": _daemon, "diagnosis": _diagnosis,
           "kalman": _kalman, "commission": _commission, "fleet_acceptance": _fleet_acceptance,
           "switches": _switches, "switches_calibration_runs2": _switches}


def bench_section(root: Path, name: str) -> str:
    """Where a bench's figures come from, its curated tables, then every other figure."""
    if not re.fullmatch(r"[a-z0-9_]+", name):
        raise ValueError(f"bench name {name!r}")
    record = load(root, name)
    figures = record["figures"]
    consumed: set[str] = set()
    out = [provenance(record)]
    if name in CURATED:
        out.append(CURATED[name](figures, consumed))
    rest = [(k, v) for k, v in _flatten({k: v for k, v in figures.items()
                                         if k not in consumed})]
    if rest:
        title = "All other figures" if name in CURATED else "Figures"
        out += [f"### {title}\n" if name in CURATED else "",
                table(["figure", "value"], [[f"`{k}`", fmt(v)] for k, v in rest])]
    return "\n".join(o for o in out if o)
