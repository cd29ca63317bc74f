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
