"""Measured runs as CSV: the interchange format (docs: measured-data).

Reading is strict (every problem names file and line) and column-wise through numpy, so a
million-row log loads in about a second.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ddh_vsensor.atomic import atomic_path
from ddh_vsensor.measured import (MAY_BE_EMPTY, PRESSURES, REF_PREFIX, REQUIRED, MeasuredDataError,
                                  Run)


# A log from a machine in service has no position sensor: the whole column may be missing
# (docs: measured-data), and reads as never sampled.
POSITION = "position_mm"
NEEDED = tuple(name for name in REQUIRED if name != POSITION)


def _empty_is_nan(cell: str) -> float:
    return float(cell) if cell.strip() else float("nan")


def _find_cell_problem(source: str, body: list[str], first_line: int, columns: dict[str, int],
                       header_fields: int) -> MeasuredDataError | None:
    """Slow scan for the first bad cell, run only after the fast parser has failed."""
    needed = max(columns.values()) + 1
    for offset, row in enumerate(csv.reader(body)):
        line = first_line + offset
        if not body[offset]:
            continue
        if len(row) < needed:
            return MeasuredDataError(source, f"row has {len(row)} field(s), the header "
                                     f"{header_fields}", line)
        for name, index in columns.items():
            cell = row[index].strip()
            if not cell:
                if name in MAY_BE_EMPTY:
                    continue
                return MeasuredDataError(source, f"column {name!r}: empty cell", line)
            try:
                float(cell)
            except ValueError:
                return MeasuredDataError(source, f"column {name!r}: {cell!r} is not a number",
                                         line)
    return None


def _line_numbers(body: list[str], first_line: int) -> np.ndarray:
    """File line of each data row (numpy's reader skips empty lines)."""
    return first_line + np.flatnonzero(np.fromiter((bool(s) for s in body), bool, len(body)))


def header_actuator(comments: list[str]) -> str | None:
    """The unit an ``# actuator: NAME`` comment line names (the simulator writes one)."""
    for text in comments:
        key, colon, value = text.partition(":")
        if colon and key.strip().lower() == "actuator" and value.strip():
            return value.strip()
    return None


def read_csv(path: str | Path, *, require_position: bool = False,
             actuator: str | None = None) -> Run:
    """Read one run; any problem raises MeasuredDataError naming file, line and column.
    Without a ``position_mm`` column the position is NaN throughout, unless
    ``require_position`` (a tool that compares with it) makes that an error. ``actuator``
    (the unit the caller takes the run for) must match the file's ``# actuator:`` line,
    where it has one."""
    source = str(path)
    try:
        with open(path, encoding="utf-8-sig", newline="") as f:
            text = f.read()
    except OSError as exc:
        raise MeasuredDataError(source, f"cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise MeasuredDataError(source, f"not UTF-8 text: {exc.reason}") from None
    lines = text.splitlines()
    if text and not text.endswith("\n"):
        # every line a writer finishes ends with its line end: without one the file was cut,
        # and a number cut short in the last cell would still read as a number
        raise MeasuredDataError(source, "cut off: the last line has no line end (the file "
                                "is truncated)", len(lines))

    comments: list[str] = []
    header_index = 0
    while header_index < len(lines) and (not lines[header_index].strip()
                                         or lines[header_index].startswith("#")):
        text = lines[header_index]
        if text.startswith("#"):
            text = text[1:]
            comments.append(text[1:] if text.startswith(" ") else text)
        header_index += 1
    if header_index == len(lines):
        raise MeasuredDataError(source, "no header row (expected columns "
                                f"{', '.join(REQUIRED)})")
    named = header_actuator(comments)
    if actuator is not None and named is not None and named != actuator:
        raise MeasuredDataError(source, f"a run of the {named} (its '# actuator: {named}' "
                                f"line), not of the {actuator} (--actuator {actuator})")
    header_line = header_index + 1
    header = [name.strip() for name in next(csv.reader([lines[header_index]]))]
    missing = [name for name in NEEDED if name not in header]
    if missing:
        raise MeasuredDataError(source, f"missing column(s) {', '.join(missing)} (header: "
                                f"{', '.join(header)})", header_line)
    wanted = [name for name in header
              if name in REQUIRED or name in PRESSURES or name.startswith(REF_PREFIX)]
    duplicated = sorted({name for name in wanted if wanted.count(name) > 1})
    if duplicated:
        raise MeasuredDataError(source, f"column(s) {', '.join(duplicated)} appear twice",
                                header_line)
    columns = {name: header.index(name) for name in wanted}
    body = lines[header_index + 1:]
    while body and not body[-1].strip():
        body.pop()
    first_line = header_line + 1
    rows = sum(map(bool, body))
    if rows < 2:
        raise MeasuredDataError(source, f"{rows} data row(s); a run needs at least 2")
    try:
        data = np.loadtxt(body, delimiter=",", comments=None, ndmin=2, dtype=np.float64,
                          usecols=list(columns.values()),
                          converters={columns[n]: _empty_is_nan
                                      for n in MAY_BE_EMPTY if n in columns})
    except ValueError as exc:
        problem = _find_cell_problem(source, body, first_line, columns, len(header))
        raise problem or MeasuredDataError(source, f"cannot parse: {exc}") from None

    def line_of(row: int) -> int:
        if len(data) == len(body):
            return first_line + row
        return int(_line_numbers(body, first_line)[row])

    values = {name: data[:, i] for i, name in enumerate(columns)}
    for name, column in values.items():
        bad = np.isinf(column) if name in MAY_BE_EMPTY else ~np.isfinite(column)
        if bad.any():
            row = int(np.argmax(bad))
            word = "missing value" if np.isnan(column[row]) else "not a finite number"
            raise MeasuredDataError(source, f"column {name!r}: {word}", line_of(row))
        if name.startswith(REF_PREFIX):
            bad = (column != 0.0) & (column != 1.0)
            if bad.any():
                row = int(np.argmax(bad))
                raise MeasuredDataError(source, f"column {name!r}: {column[row]:g} is not "
                                        "0 or 1", line_of(row))
    step_s = np.diff(values["time_s"])
    if (step_s <= 0.0).any():
        row = int(np.argmax(step_s <= 0.0)) + 1
        word = "repeats" if step_s[row - 1] == 0.0 else "goes backwards"
        raise MeasuredDataError(source, f"time_s {word} ({values['time_s'][row - 1]!r} then "
                                f"{values['time_s'][row]!r})", line_of(row))
    if POSITION not in values:
        values[POSITION] = np.full(len(values["time_s"]), np.nan)
    if require_position and np.isnan(values[POSITION]).all():
        raise MeasuredDataError(source, "position_mm is never given (this tool needs the "
                                "reference position)")

    return Run(time_s=values["time_s"], speed_rpm=values["speed_rpm"],
               torque_nm=values["torque_nm"], oil_temp_c=values["oil_temp_c"],
               position_mm=values["position_mm"], p_a_bar=values.get("p_a_bar"),
               p_b_bar=values.get("p_b_bar"),
               refs={name[len(REF_PREFIX):]: column for name, column in values.items()
                     if name.startswith(REF_PREFIX)},
               comments=comments, source=source)


# --- writing --------------------------------------------------------------------------------

def _cells(column: np.ndarray) -> list[str]:
    """Shortest round-trip text of each value; NaN (not sampled) becomes an empty cell."""
    return ["" if v != v else repr(v) for v in column.tolist()]


def write_csv(path: str | Path, run: Run, extra: dict[str, np.ndarray] | None = None) -> None:
    """Write one run: comments as '# ' lines, then header and rows; atomic. ``extra`` adds
    columns (readers of the format ignore unknown ones)."""
    columns = {name: _cells(getattr(run, name)) for name in REQUIRED}
    for name in PRESSURES:
        if getattr(run, name) is not None:
            columns[name] = _cells(getattr(run, name))
    for name, state in run.refs.items():
        columns[REF_PREFIX + name] = [str(v) for v in state.tolist()]
    for name, values in (extra or {}).items():
        columns[name] = _cells(np.asarray(values, dtype=float))
    comment_lines = [f"# {line}" for text in run.comments
                     for line in (text.splitlines() or [""])]
    try:
        with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8", newline="\n") as f:
            f.writelines(line + "\n" for line in comment_lines)
            f.write(",".join(columns) + "\n")
            f.writelines(row + "\n" for row in map(",".join, zip(*columns.values())))
    except OSError as exc:
        raise MeasuredDataError(str(path), f"cannot write: {exc.strerror or exc}") from None
