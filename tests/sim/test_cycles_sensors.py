"""Setpoint profiles and sensor models."""

from __future__ import annotations

import numpy as np
import pytest

from ddh_vsensor.errors import UserError
from ddh_vsensor.sim.cycles import dig_dump_cycle, load_profile_csv, random_cycle, work_cycle
from ddh_vsensor.sim.sensors import hall_switch, lagged, quantise


@pytest.mark.parametrize("speed", [1, 2, 3, 4])
def test_paper_cycle_positions_cross_the_references(cfg, speed):
    p = work_cycle(cfg, "paper", speed)
    t = np.arange(0.0, p.duration_s, 0.01)
    boom, _ = p.evaluate("boom", t)
    bucket, _ = p.evaluate("bucket", t)
    b = cfg.unit("boom")
    assert boom[0] == boom[-1] and bucket[0] == bucket[-1]              # repeatable
    assert abs(boom[0] - b.references_mm["bottom"]) < b.reference_window_mm
    assert boom.max() < b.references_mm["top"] - b.reference_window_mm - b.reference_hysteresis_mm
    assert boom.min() < b.references_mm["mid"] < boom.max()
    assert bucket.min() < cfg.unit("bucket").references_mm["mid"] < bucket.max()
    # lift the bucket (retract) first, then the boom
    first_bucket = t[np.argmax(np.abs(bucket - bucket[0]) > 1.0)]
    first_boom = t[np.argmax(np.abs(boom - boom[0]) > 1.0)]
    assert bucket[np.searchsorted(t, first_bucket) + 5] < bucket[0] and first_bucket < first_boom


def test_speed_levels_and_repetition(cfg):
    durations = [work_cycle(cfg, "paper", s).duration_s for s in (1, 2, 3, 4)]
    assert durations == sorted(durations, reverse=True)
    assert 20.0 <= durations[-1] <= 32.0
    three = work_cycle(cfg, "paper", 4, cycles=3)
    assert three.duration_s == pytest.approx(3 * durations[-1])
    t = np.array([1.0, 9.0, 15.0])
    for a in ("boom", "bucket"):
        np.testing.assert_allclose(three.evaluate(a, t + 2 * durations[-1])[0],
                                   three.evaluate(a, t)[0])
    with pytest.raises(UserError, match="speed"):
        work_cycle(cfg, "paper", 5)


def test_smooth_moves_have_consistent_rates(cfg):
    p = work_cycle(cfg, "paper", 4)
    t = np.arange(0.0, p.duration_s, 1e-4)
    x, v, a = p.trajectories["bucket"].evaluate_all(t)
    np.testing.assert_allclose(np.gradient(x, t), v, atol=1e-3)
    np.testing.assert_allclose(np.gradient(v, t)[2:-2], a[2:-2], atol=0.1)
    assert np.max(np.abs(v)) == pytest.approx(195.0)


def test_profile_csv(cfg, tmp_path):
    good = tmp_path / "p.csv"
    good.write_text("# my profile\ntime_s,boom_mm,bucket_mm\n0,2,600\n5,150,400\n10,2,600\n")
    p = load_profile_csv(good, cfg, cycles=2)
    assert p.duration_s == 20.0
    x, v = p.evaluate("boom", np.array([2.5, 12.5]))
    np.testing.assert_allclose(x, [76.0, 76.0])
    np.testing.assert_allclose(v, [29.6, 29.6])
    bad = {"time_s,boom_mm\n0,1\n1,2\n": "missing bucket_mm",
           "time_s,boom_mm,bucket_mm\n0,1,600\n0,2,600\n": "increase",
           "time_s,boom_mm,bucket_mm\n0,1,600\n1,400,600\n": "stroke",
           "time_s,boom_mm,bucket_mm\n0,1,600\n1,x,600\n": "not a number",
           "time_s,boom_mm,bucket_mm\n0,1,600\n": "two rows"}
    for i, (text, words) in enumerate(bad.items()):
        path = tmp_path / f"bad{i}.csv"
        path.write_text(text)
        with pytest.raises(UserError, match=words):
            load_profile_csv(path, cfg)
    one_way = tmp_path / "oneway.csv"
    one_way.write_text("time_s,boom_mm,bucket_mm\n0,2,600\n5,150,400\n")
    with pytest.raises(UserError, match="does not end where it starts"):
        load_profile_csv(one_way, cfg, cycles=2)
    with pytest.raises(UserError, match="cannot read"):
        load_profile_csv(tmp_path / "missing.csv", cfg)


def test_hall_switch_hysteresis():
    x = np.array([10.0, 3.5, 2.9, 1.0, 3.2, 3.49, 3.51, 2.0, 10.0])
    np.testing.assert_array_equal(hall_switch(x, 0.0, 3.0, 0.5), [0, 0, 1, 1, 1, 1, 0, 1, 0])


def test_quantise_and_lag():
    np.testing.assert_array_equal(quantise(np.array([1.234, -0.004, 0.3]), 0.01),
                                  [1.23, 0.0, 0.3])
    q = quantise(np.array([22.1, -1.03]), 1 / 16)
    np.testing.assert_array_equal(q * 16, np.round(q * 16))
    t = np.arange(5) * 0.1
    np.testing.assert_allclose(lagged(t, t * 10, 0.2), [0, 0, 0, 1, 2])


def test_dig_dump_cycle_presses_the_bucket_into_both_end_stops(cfg):
    p = dig_dump_cycle(cfg, 4, cycles=3)
    stroke = cfg.unit("bucket").stroke_mm
    t = np.arange(0.0, p.duration_s, 0.01)
    x, _ = p.evaluate("bucket", t)
    boom, _ = p.evaluate("boom", t)
    beyond_top, beyond_bottom = x > stroke, x < 0.0
    assert beyond_top.any() and beyond_bottom.any() and (boom < 0.0).any()
    # several contacts per cycle, each held a while: the rod is pressed, not just touched
    assert np.count_nonzero(np.diff(beyond_top.astype(int)) == 1) == 2 * 3
    assert np.count_nonzero(beyond_top) * 0.01 > 3 * 1.0
    assert p.duration_s == pytest.approx(3 * p.cycle_s)
    with pytest.raises(UserError):
        dig_dump_cycle(cfg, 5)


def test_random_cycles_are_seeded_and_reach_the_end_stops(cfg):
    a, b = random_cycle(cfg, 7), random_cycle(cfg, 7)
    for name in ("boom", "bucket"):
        assert np.array_equal(a.trajectories[name].position_mm,
                              b.trajectories[name].position_mm)
    contacts = 0
    for seed in range(5):
        p = random_cycle(cfg, seed, duration_s=60.0)
        for name in ("boom", "bucket"):
            xk = p.trajectories[name].position_mm
            stroke = cfg.unit(name).stroke_mm
            contacts += np.count_nonzero((xk < 0.0) | (xk > stroke))
            assert 0.0 <= xk[-1] <= stroke                 # ends off the stops
        assert p.duration_s == pytest.approx(60.0, abs=2.0)
    assert contacts >= 5


def test_hall_edge_times_are_where_the_rod_crossed(cfg):
    """The changes' times at 100 Hz samples equal those a 1 kHz sampling of the same plant
    finds, within 0.2 ms (the rod linear between two 10 ms samples)."""
    from ddh_vsensor.sim import RunSpec, simulate
    from ddh_vsensor.sim.sensors import SensorSettings
    spec = RunSpec(speed=4, payload_kg=0.0, oil_temp_c=30.0, seed=3)
    coarse = simulate(cfg, spec)
    fine = simulate(cfg, RunSpec(speed=4, payload_kg=0.0, oil_temp_c=30.0, seed=3,
                                 sensors=SensorSettings(rate_hz=1000.0)))
    late = []                   # each change's sample time minus its own time
    for unit, run in coarse.items():
        for name, edge in run.ref_edge_s.items():
            k = np.flatnonzero(run.refs[name][1:] != run.refs[name][:-1]) + 1
            np.testing.assert_array_equal(np.flatnonzero(np.isfinite(edge)), k)
            finer = fine[unit].ref_edge_s[name]
            finer = finer[np.isfinite(finer)]
            assert len(finer) == len(k)
            np.testing.assert_allclose(edge[k], finer, rtol=0, atol=2e-4)
            late.extend(run.time_s[k] - edge[k])
    assert len(late) >= 10
    assert max(late) > 5e-3 > min(late)         # anywhere in the sample's period
