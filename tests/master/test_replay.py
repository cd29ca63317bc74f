"""A machine's frames from runs: the controllers' heartbeats span the runs' own times, also
when those are the wall clock's (a fleet day at 1.7e9 s), not from 0."""

from __future__ import annotations

import numpy as np

from ddh_vsensor.io.log import heartbeat_ids
from ddh_vsensor.master.replay import machine_frames
from ddh_vsensor.measured import Run

WALL_S = 1.767e9


def _run(t0_s: float, duration_s: float = 2.0) -> Run:
    t = t0_s + np.arange(0.0, duration_s + 1e-9, 0.01)
    zeros = np.zeros(len(t))
    return Run(t, zeros, zeros, zeros + 40.0, zeros + np.nan,
               refs={"bottom": zeros.astype(np.uint8)})


def test_heartbeats_span_the_runs_on_the_wall_clock(cfg):
    runs = {u: _run(WALL_S) for u in cfg.unit_names}
    ids = set(heartbeat_ids(cfg, list(runs)))
    beats = [m for m in machine_frames(cfg, runs, heartbeat_period_s=0.5)
             if m.arbitration_id in ids]
    times = sorted({m.timestamp for m in beats})
    assert times == [WALL_S + k * 0.5 for k in range(5)]
    assert len(beats) == 5 * len(ids)
