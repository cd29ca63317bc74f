"""Bad input: a clear message naming the file (and the row where one is at fault), exit 2."""

from __future__ import annotations

import numpy as np
import pytest

from ddh_vsensor.cli.main import main

HEADER = "time_s,speed_rpm,torque_nm,oil_temp_c,position_mm\n"


def write(path, rows: list[str], header: str = HEADER, comments: str = "") -> str:
    path.write_text(comments + header + "".join(r + "\n" for r in rows))
    return str(path)


def good_rows(seconds: float = 6.0) -> list[str]:
    t = np.arange(0.0, seconds, 0.01)
    x = 100.0 + 20.0 * np.sin(t)
    return [f"{a:.2f},{1000 * np.cos(b):.1f},20.0,30.0,{c:.3f}" for a, b, c in zip(t, t, x)]


def run_cli(*args: str) -> int:
    return main(["analyze", *args, "--actuator", "boom", "--report", "/nonexistent/never"])


@pytest.mark.parametrize("case, expect", [
    ("missing_column", ":2: missing column(s) torque_nm"),
    ("time_backwards", ":103: time_s goes backwards"),
    ("nan_speed", ":53: column 'speed_rpm': missing value"),
    ("empty_torque", ":21: column 'torque_nm': empty cell"),
    ("too_short", ":31: too short to diagnose"),
    ("no_position", "position_mm is never given"),
    ("no_motion", "too short to diagnose: the rod moves"),
])
def test_bad_runs_are_named_with_file_and_row(case, expect, tmp_path, capsys):
    rows = good_rows()
    good = write(tmp_path / "good.csv", rows)
    bad = tmp_path / f"{case}.csv"
    if case == "missing_column":
        write(bad, [",".join(r.split(",")[:2] + r.split(",")[3:]) for r in rows],
              header="time_s,speed_rpm,oil_temp_c,position_mm\n", comments="# a comment\n")
    elif case == "time_backwards":
        rows[101] = "0.5" + rows[101][rows[101].index(","):]
        write(bad, rows)
    elif case == "nan_speed":
        parts = rows[51].split(",")
        rows[51] = ",".join([parts[0], "nan", *parts[2:]])
        write(bad, rows)
    elif case == "empty_torque":
        parts = rows[19].split(",")
        rows[19] = ",".join([parts[0], parts[1], "", *parts[3:]])
        write(bad, rows)
    elif case == "too_short":
        write(bad, rows[:30])
    elif case == "no_position":
        write(bad, [r[:r.rindex(",") + 1] for r in rows])
    elif case == "no_motion":
        write(bad, [r[:r.rindex(",") + 1] + "100.0" for r in rows[:500]])
    assert run_cli(good, str(bad)) == 2
    err = capsys.readouterr().err
    assert f"{bad}{expect}" in err or (str(bad) in err and expect in err), err
    assert "Traceback" not in err


def test_one_run_is_not_enough(tmp_path, capsys):
    good = write(tmp_path / "good.csv", good_rows())
    assert run_cli(good) == 2
    assert "at least two runs" in capsys.readouterr().err


def test_unreadable_file(tmp_path, capsys):
    good = write(tmp_path / "good.csv", good_rows())
    assert run_cli(good, str(tmp_path / "missing.csv")) == 2
    assert f"{tmp_path / 'missing.csv'}: cannot read" in capsys.readouterr().err


def test_report_dir_that_cannot_be_made(tmp_path, capsys):
    a = write(tmp_path / "a.csv", good_rows())
    b = write(tmp_path / "b.csv", good_rows(8.0))
    blocker = tmp_path / "file"
    blocker.write_text("")
    code = main(["analyze", a, b, "--actuator", "boom", "--report", str(blocker / "sub")])
    assert code == 2
    assert "cannot create the report directory" in capsys.readouterr().err
