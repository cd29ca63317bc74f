"""The per-log analysis: its expected error (the largest change a cause makes to an
edge-to-edge increment, replayed through the estimator) against the simulator's own
sensitivity, from which the simulated fleet's wear rates are drawn."""

from __future__ import annotations

import dataclasses

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


def test_one_observation_no_cause_makes_does_not_carry_a_logs_fit(local_store, cfg,
                                                                   monkeypatch):
    """A 'hold' in which the estimate moves (flow over a valve, a slow move) is an
    observation no catalogued cause explains: with it, a squared-error fit of leakage goes
    where that one observation wants; the log's robust loss keeps the fit of the others."""
    from ddh_vsensor.diagnosis.holds import Hold
    from ddh_vsensor.diagnosis.references import reference_run
    from ddh_vsensor.diagnosis import evidence as analysis
    from ddh_vsensor.fleet.ingest import run_of
    from ddh_vsensor.diagnosis.trend import from_u, log_fit

    store = Store(local_store[0])
    machine, logs = sorted(store.machine_logs().items())[0]
    rr = reference_run(cfg, "boom", run_of(store, logs[0], "boom", cfg), model_speeds=False)
    fastest = int(np.argmax(np.abs(rr.run.speed_rpm)))
    start, stop = max(fastest - 25, 0), min(fastest + 25, len(rr.run.time_s) - 1)
    fake = Hold(start, stop, float(rr.run.time_s[stop] - rr.run.time_s[start]), 0.0, 0.0,
                float(rr.run.oil_temp_c[start]), float("nan"))
    odd = dataclasses.replace(rr, holds=rr.holds + (fake,))

    def leakage(run, robust_mm):
        monkeypatch.setattr(analysis, "ROBUST_MM", robust_mm)
        row, = [r for r in analysis.fit_log(cfg, run, "boom", causes=("pump_leakage",))]
        return from_u("pump_leakage", log_fit("pump_leakage", {**row, "time_s": 0.0,
                                                               "log_id": "x"}).u)

    clean = leakage(rr, analysis.ROBUST_MM)
    assert abs(np.log(leakage(odd, analysis.ROBUST_MM) / clean)) < np.log(1.25)
    assert abs(np.log(leakage(odd, 1e9) / clean)) > np.log(1.25)    # squared error: carried
