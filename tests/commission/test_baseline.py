"""The machine's baseline: written by ``commission`` beside the configuration, each run file's
residuals those of the model commissioned on the other files; read back by ``analyze
--baseline``, where every bad input is one line."""

from __future__ import annotations

import dataclasses
import json
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest

from ddh_vsensor.cli.main import main
from ddh_vsensor.commission.baseline import (FORMAT, FORMAT_VERSION, LEAVE_ONE_OUT,
                                             POSITION_SEGMENT_S, measure_fixed, read, segments)
from ddh_vsensor.config import Config, load_config
from ddh_vsensor.diagnosis.runs import AnalysisRun
from ddh_vsensor.io.csv import read_csv, write_csv
from ddh_vsensor.measured import Run

REPO = Path(__file__).resolve().parents[2]
LOADER = str(REPO / "config" / "loader.yaml")


@pytest.fixture(scope="module")
def calibration_csvs(configured_runs: list[dict[str, Run]],
                     tmp_path_factory: pytest.TempPathFactory) -> list[str]:
    """The reference loader's two calibration runs of the boom as CSV files."""
    out = tmp_path_factory.mktemp("calibration")
    paths = []
    for i, runs in enumerate(configured_runs):
        paths.append(str(out / f"cal{i}.csv"))
        write_csv(paths[-1], runs["boom"])
    return paths


@pytest.fixture(scope="module")
def commissioned(calibration_csvs: list[str], tmp_path_factory: pytest.TempPathFactory
                 ) -> tuple[Path, dict]:
    """(the commissioned configuration, its baseline's JSON), the baseline at its default
    path."""
    out = tmp_path_factory.mktemp("machine") / "machine.yaml"
    assert main(["commission", *calibration_csvs, "--config", LOADER, "--actuator", "boom",
                 "--out", str(out)]) == 0
    path = out.with_name("machine.baseline.json")
    return out, json.loads(path.read_text())


def test_commission_writes_the_baseline_beside_the_configuration(commissioned,
                                                                  calibration_csvs) -> None:
    out, data = commissioned
    assert data["format"] == FORMAT and data["format_version"] == FORMAT_VERSION
    assert data["config_hash"] == load_config(out).estimate_hash()
    assert data["mode"] == load_config(out).estimator.mode
    assert data["held_out"] == LEAVE_ONE_OUT
    assert data["runs"] == calibration_csvs
    created = datetime.fromisoformat(data["created"])
    assert timedelta(0) <= datetime.now(timezone.utc) - created < timedelta(hours=1)
    assert set(data["units"]) == {"boom"}
    boom = data["units"]["boom"]
    # the sweeps rest 0.7 s at the ends, held too close to the stops: no hold is scored
    assert boom["holds"] is None
    for kind in ("position", "references"):
        k = boom[kind]
        assert set(k["run_rms_mm"]) == set(calibration_csvs)
        assert 0.0 < k["rms_mm"] <= k["p95_mm"] < 5.0 and k["count"] > 0
    assert boom["pressures"]["count"] == 2 and boom["pressures"]["gain"] > 0.0


def test_each_run_is_scored_by_the_model_commissioned_without_it(commissioned,
                                                                  calibration_csvs,
                                                                  tmp_path) -> None:
    """The first run's residuals are those of the configuration commissioned on the second
    alone, not of the one fitted on both: the references tell the two apart (measured: 0.31
    against 0.20 mm RMS); on the position they coincide within 0.0001 mm (0.022)."""
    out, data = commissioned
    first, second = calibration_csvs
    alone = tmp_path / "second.yaml"
    assert main(["commission", second, "--config", LOADER, "--actuator", "boom", "--out",
                 str(alone), "--no-baseline"]) == 0
    assert not alone.with_name("second.baseline.json").exists()
    run = read_csv(first, require_position=True, actuator="boom")
    held = measure_fixed(load_config(alone), {"boom": [run]}).units["boom"].kinds
    fitted = measure_fixed(load_config(out), {"boom": [run]}).units["boom"].kinds
    for kind in ("references", "position"):
        written = data["units"]["boom"][kind]["run_rms_mm"][first]
        assert written == pytest.approx(held[kind].rms_mm, abs=1e-4)
    written = data["units"]["boom"]["references"]["run_rms_mm"][first]
    assert abs(written - fitted["references"].rms_mm) > 0.01


def test_one_run_file_is_not_enough(calibration_csvs, tmp_path, capsys) -> None:
    out = tmp_path / "machine.yaml"
    assert main(["commission", calibration_csvs[0], "--config", LOADER, "--actuator", "boom",
                 "--out", str(out)]) == 0
    assert "baseline not written: one run file" in capsys.readouterr().out
    assert not (tmp_path / "machine.baseline.json").exists()
    asked = tmp_path / "asked.json"
    assert main(["commission", calibration_csvs[0], "--config", LOADER, "--actuator", "boom",
                 "--out", str(out), "--baseline", str(asked)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "needs at least two run files" in err
    assert not asked.exists()


def test_the_file_reads_back(commissioned, tmp_path) -> None:
    out, data = commissioned
    base = read(out.with_name("machine.baseline.json"))
    assert base.as_dict() == data
    copy = base.save(tmp_path / "copy.json")
    assert json.loads(copy.read_text()) == data


def _bad(data: dict, tmp_path: Path, name: str, edit) -> Path:
    changed = json.loads(json.dumps(data))
    edit(changed)
    path = tmp_path / name
    path.write_text(json.dumps(changed))
    return path


@pytest.mark.parametrize("case,expected", [
    ("missing", "no such baseline file"),
    ("not json", "not a baseline file (not JSON"),
    ("format", "not a baseline file"),
    ("version", "baseline format version 2; this ddh-vsensor reads version 1"),
    ("hash", "the baseline of another configuration"),
    ("switch moved", "switches, drive reading or estimator settings differ"),
    ("unit", "no baseline for the bucket (units in it: boom)"),
    ("mode", "measured in dynamic mode, the analysis is in full: analyze with --mode dynamic"),
    ("malformed", "units.boom.position.rms_mm must be a number >= 0"),
])
def test_a_bad_baseline_is_one_line(commissioned, calibration_csvs, tmp_path, capsys,
                                    case: str, expected: str) -> None:
    out, data = commissioned
    unit, extra = "boom", []
    if case == "missing":
        path = tmp_path / "nowhere.json"
    elif case == "not json":
        path = tmp_path / "text.json"
        path.write_text("format: yaml\n")
    elif case == "format":
        path = _bad(data, tmp_path, "f.json", lambda d: d.update(format="something else"))
    elif case == "version":
        path = _bad(data, tmp_path, "v.json", lambda d: d.update(format_version=2))
    elif case == "hash":
        path = _bad(data, tmp_path, "h.json", lambda d: d.update(config_hash="0" * 16))
    elif case == "switch moved":          # same physics, a reference switch 2 mm further
        path = out.with_name("machine.baseline.json")
        text = out.read_text()
        moved = tmp_path / "moved.yaml"
        cfg = load_config(out)
        ref, mm = next(iter(cfg.unit("boom").references_mm.items()))
        moved.write_text(text.replace(f"{ref}: {mm:g}", f"{ref}: {mm + 2.0:g}", 1))
        changed = load_config(moved)
        assert changed.unit("boom").references_mm[ref] == mm + 2.0
        assert changed.physics_hash() == cfg.physics_hash()
        out = moved
    elif case == "unit":
        path, unit = out.with_name("machine.baseline.json"), "bucket"
    elif case == "mode":
        path, extra = out.with_name("machine.baseline.json"), ["--mode", "full"]
    else:
        path = _bad(data, tmp_path, "m.json",
                    lambda d: d["units"]["boom"]["position"].update(rms_mm="a lot"))
    code = main(["analyze", *calibration_csvs, "--config", str(out), "--actuator", unit,
                 "--report", str(tmp_path / "report"), "--baseline", str(path), *extra])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.count("\n") == 0 and "Traceback" not in err
    assert err.startswith(f"ddh-vsensor analyze: error: {path}: ") and expected in err, err
    assert not (tmp_path / "report").exists()


def _analysis_run(duration_s: float, dt_s: float = 0.01, every: int = 1) -> AnalysisRun:
    t = np.arange(0.0, duration_s + dt_s / 2, dt_s)
    x = np.where(np.arange(len(t)) % every == 0, 100.0 + t, np.nan)
    zeros = np.zeros(len(t))
    return AnalysisRun("r", t, zeros, zeros, zeros + 40.0, x)


@pytest.mark.parametrize("duration_s,parts", [(20.0, 1), (400.0, 7), (89.0, 1), (91.0, 2)])
def test_segments_are_about_an_analysed_run_long(duration_s: float, parts: int) -> None:
    """Equal parts of about POSITION_SEGMENT_S, each starting at a draw-wire sample (here
    one sample in three has it), covering the run without overlap."""
    run = _analysis_run(duration_s, every=3)
    got = segments(run)
    assert len(got) == parts
    assert sum(len(s) for s in got) == len(run)
    assert np.array_equal(np.concatenate([s.time_s for s in got]), run.time_s)
    for s in got:
        assert np.isfinite(s.position_mm[0])
        assert s.duration_s <= 1.5 * POSITION_SEGMENT_S
        if parts > 1:
            assert s.duration_s >= 0.7 * POSITION_SEGMENT_S


def test_a_unit_without_references_has_none_in_its_baseline(cfg: Config,
                                                            configured_runs) -> None:
    """Runs whose switches the log lacks: position only (the analysis from references then
    refuses the baseline)."""
    run = dataclasses.replace(configured_runs[0]["boom"], refs={}, ref_edge_s={},
                              source="no-switches")
    unit = measure_fixed(cfg, {"boom": [run]}).units["boom"]
    assert set(unit.kinds) == {"position"}
    own = unit.own_error("x")
    assert own.references_rms_mm is None and own.holds_rms_mm is None
