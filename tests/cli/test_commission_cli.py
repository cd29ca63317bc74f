"""``ddh-vsensor commission``: calibration runs (CAN logs or CSV) in, the datasheet file with
the switch keys set out, loading as a configuration with the calibrated values; bad inputs
one line and exit 2, before any work."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest

from ddh_vsensor.cli.main import main
from ddh_vsensor.cli.config import datasheet_text
from ddh_vsensor.commission.machine import FLOORS, TRANSDUCER_BAR
from ddh_vsensor.commission.programme import calibration_profile
from ddh_vsensor.config import Config, load_config
from ddh_vsensor.sim.run import RunSpec, simulate_campaign, write_run_dir

REPO = Path(__file__).resolve().parents[2]
DATASHEET = REPO / "config" / "loader.yaml"
TRUE_SWITCHES_MM = {"bottom": 1.0, "mid": 157.4, "top": 309.65}
TRUE_WINDOW_MM, TRUE_HYSTERESIS_MM = 2.0, 0.8
KEYS = ("references_mm", "reference_window_mm", "reference_hysteresis_mm",
        "reference_tolerance_mm")


@pytest.fixture(scope="module")
def run_dirs(cfg: Config, tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Two calibration runs of the boom (its switches off the datasheet's) as each a
    directory of boom.csv, bucket.csv (the bucket held still) and run.blf."""
    boom = dataclasses.replace(cfg.unit("boom"), references_mm=dict(TRUE_SWITCHES_MM),
                               reference_window_mm=TRUE_WINDOW_MM,
                               reference_hysteresis_mm=TRUE_HYSTERESIS_MM)
    true_cfg = dataclasses.replace(cfg, units={**cfg.units, "boom": boom})
    runs = simulate_campaign(true_cfg, [
        RunSpec(cycle=calibration_profile(cfg, "boom", s), seed=i)
        for i, s in enumerate((4.0, 9.0))])
    out = tmp_path_factory.mktemp("calibration")
    dirs = []
    for i, r in enumerate(runs):
        write_run_dir(true_cfg, r, out / f"run{i}")
        dirs.append(out / f"run{i}")
    return dirs


def test_can_logs_give_a_configuration_with_the_measured_switches(
        run_dirs: list[Path], tmp_path: Path, capsys) -> None:
    out, report = tmp_path / "machine.yaml", tmp_path / "report"
    assert main(["commission", *(str(d / "run.blf") for d in run_dirs), "--config",
                 str(DATASHEET), "--out", str(out), "--report", str(report),
                 "--switches-only"]) == 0
    printed = capsys.readouterr().out
    assert "boom: 2 runs, 3 of 3 switches calibrated" in printed
    assert "bucket: 2 runs, 0 of 3 switches calibrated" in printed
    data = json.loads((report / "commission.json").read_text())["units"]
    assert "never switched" in (report / "commission.html").read_text()
    boom, datasheet = load_config(out).unit("boom"), load_config(DATASHEET)
    # the written file reproduces the calibrated values, and they are the switches' own
    for name, sw in data["boom"]["switches"].items():
        assert boom.references_mm[name] == sw["position_mm"]
        assert sw["position_mm"] == pytest.approx(TRUE_SWITCHES_MM[name], abs=0.05)
        assert sum(k["count"] for k in sw["kinds"].values()) == len(sw["edges"]) >= 6
    assert (boom.reference_window_mm, boom.reference_hysteresis_mm,
            boom.reference_tolerance_mm) == (data["boom"]["window_mm"],
                                             data["boom"]["hysteresis_mm"],
                                             data["boom"]["tolerance_mm"])
    assert boom.reference_window_mm == pytest.approx(TRUE_WINDOW_MM, abs=0.05)
    assert boom.reference_hysteresis_mm == pytest.approx(TRUE_HYSTERESIS_MM, abs=0.05)
    assert boom.reference_tolerance_mm <= 0.2
    # the bucket never moved: its values stay, with the run that would calibrate them
    assert load_config(out).unit("bucket") == datasheet.unit("bucket")
    assert "run the bucket through 425 mm up and down" in data["bucket"]["switches"]["mid"][
        "problem"]
    # the user's file otherwise intact: only the switch keys' lines differ
    before, after = DATASHEET.read_text().splitlines(), out.read_text().splitlines()
    assert len(before) == len(after)
    changed = [(a, b) for a, b in zip(before, after) if a != b]
    assert len(changed) == 6 + 3              # the boom's keys; the bucket's switches' notes
    for a, b in changed:
        key = a.split(":")[0].strip()
        assert key in (*KEYS, *TRUE_SWITCHES_MM) and b.split(":")[0] == a.split(":")[0]
        assert "# commissioned: " in b or "# not commissioned: " in b


def test_csv_runs_of_one_unit(run_dirs: list[Path], tmp_path: Path) -> None:
    out = tmp_path / "machine.yml"
    assert main(["commission", *(str(d / "boom.csv") for d in run_dirs), "--config",
                 str(DATASHEET), "--out", str(out), "--actuator", "boom"]) == 0
    boom = load_config(out).unit("boom")
    for name, position in TRUE_SWITCHES_MM.items():    # rows only: within their tolerance
        assert boom.references_mm[name] == pytest.approx(position,
                                                         abs=boom.reference_tolerance_mm)
    assert 0.05 < boom.reference_tolerance_mm < 1.0


def _no_position(path: Path, tmp_path: Path) -> Path:
    """The CSV without its position column."""
    lines = path.read_text().splitlines()
    head = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    col = lines[head].split(",").index("position_mm")
    out = tmp_path / "no_position.csv"
    out.write_text("\n".join(lines[:head] + [",".join(c for j, c in enumerate(line.split(","))
                                                      if j != col)
                                             for line in lines[head:]]) + "\n")
    return out


@pytest.mark.parametrize("case, problem", [
    ("out is the datasheet", "the datasheet configuration itself"),
    ("out not yaml", "its extension must be one of .yaml, .yml"),
    ("unknown unit", "bulldozer"),
    ("no position", "position"),
    ("nothing calibrated", "no switch calibrated and no flow value measured"),
    ("report over a file", "cannot create the report directory"),
    ("bad spread factor", "--spread-factor"),
])
def test_a_bad_input_is_one_line_and_exit_2(case: str, problem: str, run_dirs: list[Path],
                                             tmp_path: Path, capsys) -> None:
    datasheet = tmp_path / "datasheet.yaml"
    datasheet.write_text(DATASHEET.read_text())
    out = tmp_path / "machine.yaml"
    runs = [str(d / "boom.csv") for d in run_dirs]
    extra: list[str] = []
    if case == "out is the datasheet":
        out = datasheet
    elif case == "out not yaml":
        out = tmp_path / "machine.txt"
    elif case == "unknown unit":
        extra = ["--actuator", "bulldozer"]
    elif case == "no position":
        runs = [str(_no_position(run_dirs[0] / "boom.csv", tmp_path))]
    elif case == "nothing calibrated":
        runs = [str(d / "bucket.csv") for d in run_dirs]
    elif case == "report over a file":
        (tmp_path / "taken").write_text("")
        extra = ["--report", str(tmp_path / "taken")]
    elif case == "bad spread factor":
        extra = ["--spread-factor", "nan"]
    original = datasheet.read_text()
    assert main(["commission", *runs, "--config", str(datasheet), "--out", str(out),
                 *extra]) == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if "error:" in line]
    assert len(errors) == 1 and problem in errors[0] and "Traceback" not in err, err
    # before any work, nothing but the error; after reading the runs, the progress's line
    assert len(err.splitlines()) == 1 + (case == "nothing calibrated"), err
    assert datasheet.read_text() == original
    assert out == datasheet or not out.exists()


@pytest.fixture(scope="module")
def leaky_csvs(cfg: Config, tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """The boom's CSV runs (logged pressures) of a machine whose pumps leak 1.3x the
    datasheet's, 30 % through orifices: loaded paper cycles at 20 and 60 degC."""
    from ddh_vsensor.sim.effects import UnitEffects
    plant = {a: UnitEffects(pump_leakage=1.3, leak_orifice=30.0) for a in cfg.unit_names}
    runs = simulate_campaign(cfg, [RunSpec(speed=s, payload_kg=1040.0, oil_temp_c=t,
                                           effects=plant, seed=s)
                                   for t in (20.0, 60.0) for s in (2, 4)])
    out = tmp_path_factory.mktemp("leaky")
    for i, r in enumerate(runs):
        write_run_dir(cfg, r, out / f"run{i}")
    return [out / f"run{i}" / "boom.csv" for i in range(len(runs))]


def test_the_measured_flow_model_is_written_with_its_evidence(
        leaky_csvs: list[Path], tmp_path: Path, capsys) -> None:
    out, report = tmp_path / "machine.yaml", tmp_path / "report"
    sheet = tmp_path / "datasheet.yaml"             # a datasheet's bands: wider than measured
    sheet.write_text(datasheet_text())
    assert main(["commission", *map(str, leaky_csvs), "--config", str(sheet), "--out",
                 str(out), "--actuator", "boom", "--report", str(report)]) == 0
    printed = capsys.readouterr().out
    assert "pump A leakage factor: 1.3" in printed and "pressures logged" in printed
    datasheet_cfg = load_config(sheet)
    datasheet, machine = datasheet_cfg.unit("boom"), load_config(out).unit("boom")
    leak = (1.0 - machine.pump_a.volumetric_efficiency) / (
        1.0 - datasheet.pump_a.volumetric_efficiency)
    assert leak == pytest.approx(1.3, rel=0.02)
    assert machine.pump_a.leakage_orifice_share == pytest.approx(0.3, abs=0.02)
    # its chamber never loaded: its leakage kept; the structure is the unit's pumps'
    assert machine.pump_b.volumetric_efficiency == datasheet.pump_b.volumetric_efficiency
    assert machine.pump_b.leakage_orifice_share == machine.pump_a.leakage_orifice_share
    text = out.read_text()
    assert text.count("# commissioned: ") >= 4 and "hold it loaded" in text
    flow = json.loads((report / "commission.json").read_text())["units"]["boom"]["flow"]
    assert flow["leakage_factor"]["a"]["identified"] and not flow["leakage_factor"]["b"][
        "identified"]
    assert "Flow model" in (report / "commission.html").read_text()
    # the measured pump's leakage band narrows to what was measured (the floor for logged
    # pressures); the pump not measured keeps the machine's band; both sides' displacement
    # measured (logged pressures): the unit's band narrows
    assert machine.pump_a.leakage_tolerance == pytest.approx(FLOORS["logged"]["leakage"])
    assert machine.pump_b.leakage_tolerance is None
    assert load_config(out).tolerances == datasheet_cfg.tolerances
    assert machine.displacement_tolerance == pytest.approx(FLOORS["logged"]["displacement"])
    # the drive reads the shaft's torque (no drive effect): measured as such, known to what a
    # transducer's bar puts through the pumps
    assert "drive's torque reading: gain" in printed
    # the pressures' torque is the model's, 0.03-0.06 % off the simulated plant's (measured)
    assert abs(machine.motor.torque_gain - 1.0) < 0.002
    assert abs(machine.motor.torque_offset_nm) < 0.05
    assert abs(machine.motor.torque_speed_offset_nm) < 0.05
    assert machine.motor.torque_offset_tolerance_nm == pytest.approx(max(
        p.displacement_cm3_rev * 1e-6 * p.speed_ratio / (2.0 * math.pi) * TRANSDUCER_BAR * 1e5
        for p in (datasheet.pump_a, datasheet.pump_b)), abs=1e-3)


def test_a_fit_never_widens_a_band(leaky_csvs: list[Path], tmp_path: Path) -> None:
    """The reference loader's leakage is known to +-10 % (its pumps measured): a calibration
    day whose pressures allow +-16 % leaves that band as it is."""
    out = tmp_path / "machine.yaml"
    assert main(["commission", *map(str, leaky_csvs), "--config", str(DATASHEET), "--out",
                 str(out), "--actuator", "boom"]) == 0
    machine = load_config(out).unit("boom")
    assert FLOORS["logged"]["leakage"] > load_config(DATASHEET).tolerances.pump_leakage
    assert machine.pump_a.leakage_tolerance is None
    assert machine.pump_a.volumetric_efficiency != load_config(DATASHEET).unit(
        "boom").pump_a.volumetric_efficiency          # the value is still measured
