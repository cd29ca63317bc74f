"""Every command of the issue's offline chain on every shipped machine, as a user runs it:
``python -m ddh_vsensor`` in a subprocess, exit 0."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ddh_vsensor.config import Config
from ddh_vsensor.errors import UserError

TIMEOUT_S = 600


def frames_for(cfg: Config) -> bool:
    """Whether the frame codec knows this machine's frames (BLF logs, the demo's bus): the
    DBC generated from the configuration; until that is in, only the reference loader's."""
    from ddh_vsensor.canbus.dbc import FrameCodec
    try:
        FrameCodec(cfg)
    except UserError:
        return False
    return True


def cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "ddh_vsensor", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=TIMEOUT_S,
                          env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert proc.returncode == 0, (args, proc.stdout[-2000:], proc.stderr[-2000:])
    assert "Traceback" not in proc.stderr
    return proc


@pytest.fixture(scope="module")
def workdir(machine: Config, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp(Path(machine.source).stem)


@pytest.fixture(scope="module")
def simulated(machine: Config, workdir: Path) -> dict[str, Path]:
    """``simulate`` of the machine's work cycle (CSV + BLF) and of a random cycle (CSV)."""
    cfg = machine.source
    work, rand = workdir / "work", workdir / "random"
    blf = [] if frames_for(machine) else ["--no-blf"]
    cli("simulate", "--config", cfg, "--cycle", "work", "--payload-kg", "0", "--oil-temp-c",
        "27", "--step-s", "0.002", *blf, "--out", work, cwd=workdir)
    cli("simulate", "--config", cfg, "--cycle", "random", "--duration-s", "20", "--seed", "5",
        "--payload-kg", "0", "--oil-temp-c", "35", "--step-s", "0.002", "--no-blf",
        "--out", rand, cwd=workdir)
    return {"work": work, "random": rand}


def test_config_validate_and_tables_build(machine: Config, workdir: Path):
    out = cli("config", "--validate", machine.source, cwd=workdir).stdout
    assert "valid" in out
    cli("tables", "build", "--config", machine.source, "--out", workdir / "tables", cwd=workdir)
    for a in machine.unit_names:
        assert any(p.name.startswith(a) for p in (workdir / "tables").iterdir()), a


def test_simulate_writes_one_csv_per_unit(machine: Config, simulated: dict[str, Path]):
    for a in machine.unit_names:
        assert (simulated["work"] / f"{a}.csv").is_file()
        assert (simulated["random"] / f"{a}.csv").is_file()
    assert (simulated["work"] / "run.blf").is_file() == frames_for(machine)
    assert not (simulated["random"] / "run.blf").exists()


def test_estimate_every_unit(machine: Config, simulated: dict[str, Path], workdir: Path):
    for a in machine.unit_names:
        out = cli("estimate", simulated["work"] / f"{a}.csv", "--config", machine.source,
                  "--actuator", a, "--mode", "full", "--json", cwd=workdir).stdout
        score = json.loads(out)
        assert score["max_abs_error_mm"] < 10.0, (a, score)


def test_analyze_a_unit(machine: Config, simulated: dict[str, Path], workdir: Path):
    a = machine.unit_names[-1]
    cli("analyze", simulated["work"] / f"{a}.csv", simulated["random"] / f"{a}.csv",
        "--config", machine.source, "--actuator", a, "--report", workdir / "report",
        cwd=workdir)
    assert (workdir / "report" / "report.json").is_file()


def test_demo(machine: Config, workdir: Path):
    if not frames_for(machine):
        pytest.skip("the frames of this machine need the DBC generated from its configuration")
    out = cli("demo", "--config", machine.source, "--rate", "20", "--no-figure",
              cwd=workdir).stdout
    assert "summary" in out
    for a in machine.unit_names:
        assert f"  {a}" in out, a
