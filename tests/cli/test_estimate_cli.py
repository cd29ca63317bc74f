"""``ddh-vsensor estimate`` on a CAN log without position frames: the rod's start is not
known, so the estimate is a cold start until its first Hall switch, never a made-up
position it would learn from or meet an end stop at."""

from __future__ import annotations

import csv

import numpy as np

from ddh_vsensor.io.blf import write_blf_inputs
from ddh_vsensor.cli.main import main
from ddh_vsensor.diagnosis.trials import draw_trial, simulate_trial
from ddh_vsensor.estimator.flags import Flags


def test_a_log_without_positions_starts_cold(tmp_path, cfg):
    runs = simulate_trial(cfg, draw_trial(6103, "none"))
    run = runs[0]["bucket"]
    assert run.position_mm[0] > 300.0                   # far from where a made-up start is
    log = tmp_path / "run.blf"
    write_blf_inputs(log, runs[0], cfg)                 # Sevcon, oil, Hall: no position
    out = tmp_path / "est.csv"
    assert main(["estimate", str(log), "--actuator", "bucket", "--out", str(out)]) == 0
    with open(out, newline="") as f:
        rows = [r for r in csv.reader(f) if r and not r[0].startswith("#")]
    head = rows[0]
    body = np.array([[float(c) if c else np.nan for c in r] for r in rows[1:]])
    x, flags = body[:, head.index("position_mm")], body[:, head.index("flags")].astype(int)
    cold = (flags & Flags.NOT_REFERENCED) != 0
    assert cold[0] and not cold[-1]
    after = ~cold
    after[:np.argmax(after)] = False
    # the log's frames are the run's samples: compare sample by sample after the first edge
    assert len(x) == len(run.position_mm)
    worst = float(np.max(np.abs(x[after] - run.position_mm[after])))
    assert worst <= 0.5, f"{worst:.2f} mm after the first reference"


def _csv_columns(path) -> dict[str, np.ndarray]:
    with open(path, newline="") as f:
        rows = [r for r in csv.reader(f) if r and not r[0].startswith("#")]
    body = np.array([[float(c) if c else np.nan for c in r] for r in rows[1:]])
    return {name: body[:, i] for i, name in enumerate(rows[0])}


def test_kalman_mode_offline_covers_its_error(tmp_path, cfg, capsys):
    """`--mode kalman` on a simulated paper cycle (nominal plant, the loader's measured
    tolerances): every unflagged value within its published uncertainty, and the worst error
    within 0.5 mm (measured 0.29 mm; the filter's nominal training worst on the boom, with
    references, is 0.42 mm)."""
    from ddh_vsensor.io.csv import write_csv
    from ddh_vsensor.sim import RunSpec, simulate
    run = simulate(cfg, RunSpec(speed=4, payload_kg=0.0, oil_temp_c=27.0))["boom"]
    path, out = tmp_path / "boom.csv", tmp_path / "est.csv"
    write_csv(path, run)
    assert main(["estimate", str(path), "--actuator", "boom", "--mode", "kalman",
                 "--out", str(out)]) == 0
    assert "boom (kalman): max |error|" in capsys.readouterr().out
    col = _csv_columns(out)
    error = np.abs(col["position_mm"] - col["reference_mm"])
    trusted = col["flags"].astype(int) == 0
    assert trusted.mean() > 0.9
    assert np.all(error[trusted] <= col["uncertainty_mm"][trusted] + 0.05)
    assert float(np.nanmax(error)) <= 0.5


def test_kalman_mode_takes_no_tables_or_extension(tmp_path, capsys):
    assert main(["estimate", "missing.csv", "--actuator", "boom", "--mode", "kalman",
                 "--tables", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--tables: not for the kalman mode" in err
