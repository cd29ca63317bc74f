"""A stretch's rows per cause: the daemon's lean tables (over the stretch's own oil, dropped
after each grid value) give the rows of the fleet workers' cached full-range tables."""

from __future__ import annotations

import numpy as np

from ddh_vsensor.diagnosis.evidence import GRIDS, LeanBench, fit_log, lean_range
from ddh_vsensor.diagnosis.references import reference_run


def test_lean_tables_give_the_rows_of_the_full_range(cfg, fleet_sessions):
    for actuator, run in fleet_sessions[0].items():
        rr = reference_run(cfg, actuator, run, model_speeds=False)
        full, lean = fit_log(cfg, rr, actuator), fit_log(cfg, rr, actuator, lean=True)
        assert [r["cause"] for r in lean] == list(GRIDS)
        for f, g in zip(full, lean):
            assert f["n_obs"] == g["n_obs"] and f["grid"] == g["grid"]
            np.testing.assert_allclose(g["loss"], f["loss"], rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(g["emax_mm"], f["emax_mm"], rtol=1e-9, atol=1e-12)


def test_lean_tables_span_the_nodes_around_the_oil_only(cfg, fleet_sessions):
    run = fleet_sessions[0]["boom"]
    t0, t1, _ = lean_range(cfg, [run.oil_temp_c]).tables.temperatures_c
    assert t0 <= run.oil_temp_c.min() and run.oil_temp_c.max() <= t1 and t1 - t0 <= 15.0
    rr = reference_run(cfg, "boom", run, model_speeds=False)
    bench = LeanBench(cfg, "boom", [rr.run], "full")
    assert bench.nominal_tables.full.velocity_mm_s.shape[0] == round((t1 - t0) / 5.0) + 1
    assert lean_range(cfg, [np.array([-5.0, 95.0])]).tables.temperatures_c[:2] == (10.0, 80.0)
