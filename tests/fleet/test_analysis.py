"""The per-log analysis: its expected error (the largest change a cause makes to an
edge-to-edge increment, replayed through the estimator) against the simulator's own
sensitivity, from which the simulated fleet's wear rates are drawn."""

from __future__ import annotations

import numpy as np
import pyarrow.parquet as pq

from ddh_vsensor.fleet.store import Store
from ddh_vsensor.sim.fleet import START_DATE, _day_sensitivity_mm, plan_fleet

from .conftest import DAYS, LOG_S, MACHINES, SEED

# parameter value the expected errors are compared at, its neutral, and the band the median
# ratio (analysis / simulator) must fall in: the simulator's kinematic time offset is exact
# to first order; its leakage creep is a steady-state hold, the replay also sees the moves
# (seed 2026, 20 x 30 fleet: medians 1.00 and 0.85..0.93)
CHECKS = {"time_offset": (0.05, 0.0, (0.9, 1.1)), "pump_leakage": (2.0, 1.0, (0.7, 1.15))}


def test_the_analysis_sees_the_wear_the_simulator_plans_for(local_store, cfg):
    store, _ = local_store
    plan = plan_fleet(cfg, MACHINES, DAYS, SEED, LOG_S)
    ratios: dict[tuple[str, str], list[float]] = {}
    for m in plan.machines:
        for r in pq.read_table(Store(store).fits_path(m.name)).to_pylist():
            if r["cause"] not in CHECKS:
                continue
            value, neutral, _ = CHECKS[r["cause"]]
            day = int(round((r["time_s"] - START_DATE.timestamp()) / 86400.0))
            planned = abs(value - neutral) * _day_sensitivity_mm(
                cfg, r["actuator"], r["cause"], plan.seed, m.seed, day, LOG_S)
            grid, emax = np.asarray(r["grid"]), np.asarray(r["emax_mm"])
            if planned > 0:
                ratios.setdefault((r["cause"], r["actuator"]), []).append(
                    float(np.interp(value, grid, emax)) / planned)
    assert {cause for cause, _ in ratios} == set(CHECKS)
    for (cause, actuator), rs in ratios.items():
        lo, hi = CHECKS[cause][2]
        assert lo <= np.median(rs) <= hi, (cause, actuator, np.round(rs, 2))
