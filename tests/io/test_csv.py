"""The measured-data CSV: round trip, and every bad input named by file, line and column."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ddh_vsensor.errors import UserError
from ddh_vsensor.measured import MeasuredDataError, Run
from ddh_vsensor.io.csv import read_csv, write_csv

HEADER = "time_s,speed_rpm,torque_nm,oil_temp_c,position_mm"


def sample_run() -> Run:
    n = 50
    time_s = np.linspace(0.0, 0.49, n)
    position_mm = 100.0 + 10.0 * time_s
    position_mm[::3] = np.nan
    return Run(time_s=time_s, speed_rpm=np.linspace(-3000, 3000, n), torque_nm=np.full(n, 12.3),
               oil_temp_c=np.full(n, 41.7), position_mm=position_mm,
               p_a_bar=np.linspace(0, 250, n), p_b_bar=np.full(n, np.nan),
               refs={"top": np.arange(n) % 2, "bottom": np.zeros(n)},
               comments=["simulator 0.1", "", "seed: 3"])


def test_round_trip(tmp_path: Path) -> None:
    run = sample_run()
    path = tmp_path / "run.csv"
    write_csv(path, run)
    text = path.read_text()
    assert text.startswith("# simulator 0.1\n# \n# seed: 3\n" + HEADER + ",p_a_bar,p_b_bar,"
                           "ref_top,ref_bottom\n0.0,-3000.0,12.3,41.7,,0.0,,0,0\n")
    read = read_csv(path, require_position=True)
    for name in ("time_s", "speed_rpm", "torque_nm", "oil_temp_c", "position_mm", "p_a_bar",
                 "p_b_bar"):
        np.testing.assert_array_equal(getattr(read, name), getattr(run, name), err_msg=name)
    assert read.refs.keys() == run.refs.keys()
    for name, state in run.refs.items():
        np.testing.assert_array_equal(read.refs[name], state)
    assert read.comments == run.comments and read.source == str(path)
    assert [p.name for p in tmp_path.iterdir()] == ["run.csv"]        # no temp file left


def test_any_column_order_extra_columns_and_blank_lines(tmp_path: Path) -> None:
    path = tmp_path / "other.csv"
    path.write_text("\ufeff# from the machine\n\nposition_mm,oil_temp_c,note,time_s,note,"
                    "torque_nm,speed_rpm\r\n5.5,40,a,0.1,a,1,100\r\n,40,b,0.2,b,2,200\r\n\r\n"
                    "6.5,40,c,0.3,c,3,300\r\n\r\n")
    run = read_csv(path)
    np.testing.assert_array_equal(run.time_s, [0.1, 0.2, 0.3])
    np.testing.assert_array_equal(run.speed_rpm, [100, 200, 300])
    np.testing.assert_array_equal(run.position_mm, [5.5, np.nan, 6.5])
    assert run.p_a_bar is None and run.refs == {} and run.comments == ["from the machine"]


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "bad.csv"
    path.write_text(text)
    return path


OK_ROWS = "0.0,1,2,40,\n0.1,1,2,40,5\n"


@pytest.mark.parametrize("text, where, problem", [
    ("time_s,speed_rpm,oil_temp_c\n0,1,2\n", ":1", "missing column\\(s\\) torque_nm \\("),
    ("# c\n" + HEADER + "\n" + OK_ROWS + "0.2,x1,2,40,\n", ":5", "'speed_rpm': 'x1' is not a"),
    (HEADER + "\n" + OK_ROWS + "0.2,1,,40,\n", ":4", "'torque_nm': empty cell"),
    (HEADER + ",p_a_bar\n0,1,2,40,,1\n0.1,1,2,40,?,1\n", ":3", "'position_mm': '\\?' is not"),
    (HEADER + "\n" + OK_ROWS + "0.2,1,2,nan,\n", ":4", "'oil_temp_c': missing value"),
    (HEADER + "\n" + OK_ROWS + "0.2,1,2,inf,\n", ":4", "'oil_temp_c': not a finite number"),
    (HEADER + "\n" + OK_ROWS + "0.2,1,2\n", ":4", "row has 3 field.*header 5"),
    (HEADER + "\n" + OK_ROWS + "0.05,1,2,40,\n", ":4", "time_s goes backwards"),
    (HEADER + "\n" + OK_ROWS + "\n0.1,1,2,40,\n", ":5", "time_s repeats"),
    (HEADER + ",ref_top\n0.0,1,2,40,,0\n0.1,1,2,40,,2\n", ":3", "'ref_top': 2 is not 0 or 1"),
    (HEADER + ",time_s\n" + OK_ROWS, ":1", "time_s appear twice"),
    (HEADER + "\n0.0,1,2,40,\n", "", "1 data row.*at least 2"),
    ("# only a comment\n", "", "no header row"),
])
def test_bad_input_is_named(tmp_path: Path, text: str, where: str, problem: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(MeasuredDataError, match=f"^{path}{where}: .*{problem}") as info:
        read_csv(path)
    assert isinstance(info.value, UserError)


def test_missing_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(MeasuredDataError, match=r"nowhere\.csv: cannot read"):
        read_csv(tmp_path / "nowhere.csv")


def test_position_required_but_never_given(tmp_path: Path) -> None:
    path = write(tmp_path, HEADER + "\n0.0,1,2,40,\n0.1,1,2,40,\n")
    assert np.isnan(read_csv(path).position_mm).all()
    with pytest.raises(MeasuredDataError, match=r"bad\.csv: position_mm is never given"):
        read_csv(path, require_position=True)


def test_write_error_is_named(tmp_path: Path) -> None:
    with pytest.raises(MeasuredDataError, match=r"no_dir.*cannot write"):
        write_csv(tmp_path / "no_dir" / "run.csv", sample_run())


def test_run_columns_must_agree_in_length() -> None:
    with pytest.raises(ValueError, match="differ in length"):
        Run(time_s=[0.0, 1.0], speed_rpm=[0.0], torque_nm=[0.0, 0.0], oil_temp_c=[1.0, 1.0],
            position_mm=[np.nan, np.nan])


def test_switch_edge_times_move_with_the_run_and_stay_in_their_samples() -> None:
    """A change timed a nanosecond after the sample before it stays after it on the wall
    clock, where a float resolves only ~0.2 us; a time outside its sample is refused."""
    import dataclasses
    t = np.arange(5) * 0.01
    edge = np.full(5, np.nan)
    edge[2] = t[1] + 1e-9
    run = Run(time_s=t, speed_rpm=np.zeros(5), torque_nm=np.zeros(5),
              oil_temp_c=np.zeros(5), position_mm=np.full(5, np.nan),
              refs={"mid": np.array([0, 0, 1, 1, 1])}, ref_edge_s={"mid": edge})
    run.shift_time(1.7e9)
    assert run.time_s[1] < run.ref_edge_s["mid"][2] <= run.time_s[2]
    dataclasses.replace(run)                             # still a valid run
    bad = edge.copy()
    bad[2] = t[2] + 0.001
    with pytest.raises(ValueError, match="not within its sample's period"):
        dataclasses.replace(run, time_s=t, ref_edge_s={"mid": bad})
