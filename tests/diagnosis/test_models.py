"""The pieces: the chamber model, the fit and cross-validation, the breakdown, run checks."""

from __future__ import annotations

import numpy as np
import pytest

from ddh_vsensor.physics.air import compliance, log_density, secant_compliance
from ddh_vsensor.diagnosis.breakdown import breakdown, classify
from ddh_vsensor.diagnosis.causes import Cause
from ddh_vsensor.estimator.chambers import ChamberRow, track_chambers
from ddh_vsensor.diagnosis.fit import fit_cause
from ddh_vsensor.diagnosis.runs import AnalysisRun, prepare_run
from ddh_vsensor.measured import MeasuredDataError, Run
from ddh_vsensor.io.csv import read_csv
from ddh_vsensor.physics.steady import steady_state, steady_state_at_torque


def test_air_law_collapses_the_bulk_modulus_at_low_pressure(cfg):
    beta = cfg.oil.bulk_modulus_pa
    assert compliance(0.0, 0.0, beta) == pytest.approx(1.0 / beta, rel=1e-3)
    assert compliance(0.0, 0.01, beta) > 50.0 / beta        # 1 % air: >50x softer at 1 atm
    assert compliance(250e5, 0.01, beta) < 1.2 / beta       # compressed away at 250 bar
    p0, p1 = 1e5, 40e5
    exact = (log_density(p1, 0.02, beta) - log_density(p0, 0.02, beta)) / (p1 - p0)
    assert secant_compliance(p0, p1, 0.02, beta) == pytest.approx(exact)


def test_chamber_model_settles_to_the_tables_steady_state(boom):
    """Constant speed and torque: the compressible model ends where the tables are."""
    force = boom.load_force_n(500.0)
    st = steady_state(boom, 2500.0, force, 35.0)
    t = np.arange(0.0, 20.0, 0.01)
    row = ChamberRow(t, np.full_like(t, 2500.0), np.full_like(t, float(st.torque_nm)),
                     np.full_like(t, 35.0), 50.0, 0.0)
    track = track_chambers(boom, [row])[0]
    v = np.gradient(track.position_mm, t)[-100:]
    ss = steady_state_at_torque(boom, 2500.0, float(st.torque_nm), 35.0)
    assert np.allclose(v, float(ss.velocity_m_s) * 1e3, rtol=1e-6, atol=1e-6)
    assert track.p_a_pa[-1] == pytest.approx(float(ss.p_a_pa) - boom.reservoir_pa, rel=1e-6)


def test_chamber_model_follows_a_simulated_run_closely(cfg, boom, campaigns):
    """Nominal oil, measured speed and torque: within 0.4 mm of the draw wire (the tables,
    which hold steady states, err by about 1 mm on the same run)."""
    _, paths = campaigns.get("sensor")           # the boom has no effect
    run = read_csv(paths["boom"][-1])
    track = track_chambers(boom, [ChamberRow(run.time_s, run.speed_rpm, run.torque_nm,
                                             run.oil_temp_c, float(run.position_mm[0]))])[0]
    assert np.nanmax(np.abs(track.position_mm - run.position_mm)) < 0.4
    gap_bar = np.abs(track.p_a_pa / 1e5 - run.p_a_bar)
    assert np.median(gap_bar) < 0.5 and np.max(gap_bar) < 15.0


class _Linear(Cause):
    """A synthetic cause: the estimate changes by theta x a known signature."""

    def deltas(self, bench, base, values):
        return [[v * s for s in bench.signatures] for v in values]


class _Bench:
    def __init__(self, signatures, masks):
        self.signatures, self.masks = signatures, masks
        self.base = [np.zeros_like(s) for s in signatures]


def test_fit_recovers_a_parameter_and_scores_held_out_runs():
    rng = np.random.default_rng(3)
    sig = [np.cumsum(rng.normal(size=400)) for _ in range(5)]
    masks = [np.ones(400, dtype=bool) for _ in sig]
    truth = 0.37
    noise = [rng.normal(scale=0.05, size=400) for _ in sig]
    target = [-truth * s + n for s, n in zip(sig, noise)]         # residual the cause removes
    cause = _Linear("linear", "theta", "", 0.0, (-2.0, 2.0),
                    (-2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0), False, "", "")
    fit = fit_cause(cause, _Bench(sig, masks), target, [1.0] * 5)
    assert fit.value == pytest.approx(truth, abs=0.01)
    assert all(v == pytest.approx(truth, abs=0.02) for v in fit.fold_values)
    assert 0.95 < fit.explained < 1.0
    assert fit.score == pytest.approx(fit.explained - 0.02)
    for h, n in zip(fit.heldout, noise):
        assert np.std(h) == pytest.approx(np.std(n), rel=0.2)


def test_breakdown_charges_the_error_to_the_phase_that_adds_it():
    t = np.arange(0.0, 20.0, 0.01)
    v = np.where((t > 5) & (t < 15), 50.0 * np.sin(np.pi * (t - 5) / 10) ** 2, 0.0)
    x = 100.0 + np.cumsum(v) * 0.01
    creep = np.where(v == 0.0, 0.2 * 0.01, 0.0).cumsum()            # 0.2 mm/s while held
    run = AnalysisRun("synthetic", t, v * 30.0, np.full_like(t, 20.0), np.full_like(t, 40.0),
                      x)
    labels = classify(run, x + creep)
    assert set(labels["phase"][t < 4]) == {"holding"}
    assert set(labels["phase"][(t > 6) & (t < 8)]) == {"accelerating"}
    assert set(labels["phase"][(t > 12) & (t < 14)]) == {"decelerating"}
    stats = {s.name: s for s in breakdown([run], [x + creep])["phase"]}
    assert stats["holding"].error_rate_mm_s == pytest.approx(0.2, rel=0.1)
    assert abs(stats["accelerating"].error_added_mm) < 1e-9


def test_prepare_run_starts_at_the_first_reference_position():
    t = np.arange(0.0, 5.0, 0.01)
    pos = np.where(t >= 1.0, 50.0 + 3.0 * t, np.nan)
    run = Run(t, np.full_like(t, 100.0), np.full_like(t, 10.0), np.full_like(t, 30.0), pos,
              source="x.csv")
    ar = prepare_run(run)
    assert ar.time_s[0] == pytest.approx(1.0) and ar.initial_position_mm == pytest.approx(53.0)
    short = Run(t[:150], np.full(150, 100.0), np.full(150, 10.0), np.full(150, 30.0),
                pos[:150], source="y.csv")
    with pytest.raises(MeasuredDataError, match="y.csv: too short"):
        prepare_run(short)
