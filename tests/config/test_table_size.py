"""The movement tables bounded as a whole: grid keys each within its own bounds can together
ask for terabytes; validation says so in one line (exit 2), it never reaches numpy."""

from __future__ import annotations

import copy
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml

from ddh_vsensor.config import ConfigError, parse_config
from ddh_vsensor.config.schema import TABLE_BYTES_MAX, table_cells
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.tables.build import _axes

from ..conftest import REPO

RAW = yaml.safe_load((REPO / "config" / "loader.yaml").read_text())


def _with_tables(**tables: object) -> dict:
    data = copy.deepcopy(RAW)
    data["tables"].update(tables)
    return data


GRIDS = {
    "fine temperatures": {"temperatures_c": [-15.0, 100.0, 0.01]},
    "huge temperature range": {"temperatures_c": [-1e9, 1e9, 5.0]},
    "speed and torque at their bounds": {"speed_step_rpm": 1.0, "torque_step_nm": 0.01},
}


@pytest.mark.parametrize("grid", GRIDS.values(), ids=GRIDS)
def test_grids_too_large_together_exit_2_with_one_line(tmp_path, grid) -> None:
    path = tmp_path / "machine.yaml"
    path.write_text(yaml.safe_dump(_with_tables(**grid)))
    started = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "ddh_vsensor", "config", "--validate",
                           str(path)], capture_output=True, text=True, timeout=60, check=False)
    elapsed_s = time.monotonic() - started
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "temperatures_c" in lines[0] and "torque_step_nm" in lines[0] and "iB" in lines[0]
    print(f"refused in {elapsed_s:.2f} s: {lines[0]}")


def test_grid_keys_drawn_within_their_bounds_never_raise_anything_else() -> None:
    """Seeded draws of the grid keys, each within its own bounds (log-uniform): a config is
    refused with a ConfigError or accepted, and an accepted one's tables (as the table
    builder lays out its axes) fit the bound."""
    rng = np.random.default_rng(406)
    accepted = refused = 0
    for _ in range(300):
        start = float(rng.uniform(-1e6, 1e6)) * float(10.0 ** rng.uniform(-6, 3))
        span = float(10.0 ** rng.uniform(-2, 9))
        step = float(10.0 ** rng.uniform(-3, 3))
        data = _with_tables(temperatures_c=[start, start + span, step],
                            speed_step_rpm=float(10.0 ** rng.uniform(0, 4)),
                            torque_step_nm=float(10.0 ** rng.uniform(-2, 3)))
        try:
            cfg = parse_config(data)
        except ConfigError as exc:
            assert "\n" not in str(exc)
            refused += 1
            continue
        accepted += 1
        assert 8 * table_cells(cfg) <= TABLE_BYTES_MAX
        real = 0
        for actuator in cfg.units:
            speed, torque, temp = _axes(cfg, DDHUnit.from_config(cfg, actuator))
            real += temp.count * torque.count * (speed.count + 6)
        assert 8 * real <= TABLE_BYTES_MAX
    assert accepted > 20 and refused > 20, (accepted, refused)
