"""The effects catalogue: each effect changes what it should, and nothing else."""

from __future__ import annotations

import numpy as np
import pytest

from ddh_vsensor.errors import UserError
from ddh_vsensor.physics.steady import holding_speed
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.sim import EFFECTS, RunSpec, build_effects, simulate_with_truth
from ddh_vsensor.sim.effects import parse_effect

CASES = {
    "nominal": [],
    "pump_leakage": ["boom.pump_leakage=2"],
    "displacement": ["boom.displacement=0.9"],
    "compressibility": ["boom.compressibility=0.02"],
    "belt_slip": ["boom.belt_slip=5"],
    "time_offset": ["time_offset=0.1"],
    "sensors": ["boom.torque_gain=0.9", "boom.torque_offset=2", "boom.oil_temp_offset=-10",
                "boom.position_scale=1.02", "boom.position_offset=3"],
    "valve_leak": ["boom.valve_leak=5"],
    "pump_fill": ["boom.pump_fill=5"],
    "bore_leak": ["bucket.bore_leak=5"],
}
TRUTH_FIELDS = ("x_m", "v_m_s", "dp_a_pa", "dp_b_pa", "speed_rpm", "torque_nm")


@pytest.fixture(scope="module")
def runs(cfg, short_profile):
    specs = [RunSpec(cycle=short_profile, effects=e, seed=7) for e in CASES.values()]
    return dict(zip(CASES, simulate_with_truth(cfg, specs)))


def _same_truth(a, b) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in TRUTH_FIELDS)


def _same_log(a, b) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True)
               for f in ("speed_rpm", "torque_nm", "position_mm", "p_a_bar", "p_b_bar"))


def _revs(truth, t0, t1) -> float:
    sel = (truth.time_s >= t0) & (truth.time_s <= t1)
    return float(np.sum(np.abs(truth.speed_rpm[sel])) / 60.0 * (truth.time_s[1] - truth.time_s[0]))


def _hold_speed(truth) -> float:            # motor speed while the boom waits at the start
    return float(np.mean(truth.speed_rpm[(truth.time_s > 0.1) & (truth.time_s < 0.45)]))


@pytest.mark.parametrize("name", ["pump_leakage", "displacement", "compressibility",
                                  "belt_slip"])
def test_boom_only_effect_leaves_the_bucket_alone(runs, name):
    nominal, changed = runs["nominal"], runs[name]
    assert _same_truth(changed["bucket"][1], nominal["bucket"][1])
    assert _same_log(changed["bucket"][0], nominal["bucket"][0])
    assert not _same_truth(changed["boom"][1], nominal["boom"][1])
    # the position loop still follows the setpoint: the cylinder does the same thing
    np.testing.assert_allclose(changed["boom"][1].x_m, nominal["boom"][1].x_m, atol=2e-3)
    assert f"effects: {CASES[name][0].split('.', 1)[1]}" in changed["boom"][0].comments


def test_pump_leakage_scales_the_holding_creep(cfg, runs):
    boom = DDHUnit.from_config(cfg, "boom")
    force = boom.load_force_n(0.0)
    expected = holding_speed(boom.with_pumps(leakage=2.0), force, 27.0).speed_rpm
    nominal = holding_speed(boom, force, 27.0).speed_rpm
    assert expected == pytest.approx(2.0 * nominal, rel=0.01)
    assert _hold_speed(runs["pump_leakage"]["boom"][1]) == pytest.approx(expected, rel=0.01)
    assert _hold_speed(runs["nominal"]["boom"][1]) == pytest.approx(nominal, rel=0.01)


def test_displacement_needs_more_revolutions(runs):
    ratio = _revs(runs["displacement"]["boom"][1], 0.5, 3.3) / _revs(
        runs["nominal"]["boom"][1], 0.5, 3.3)
    assert ratio == pytest.approx(1.0 / 0.9, rel=0.01)


def test_compressibility_changes_transients_not_steady_states(runs):
    nominal, airy = runs["nominal"]["boom"][1], runs["compressibility"]["boom"][1]
    assert _hold_speed(airy) == pytest.approx(_hold_speed(nominal), rel=1e-3)
    assert np.max(np.abs(airy.dp_b_pa - nominal.dp_b_pa)) > 2e5      # > 2 bar somewhere
    ratio = _revs(airy, 0.5, 3.3) / _revs(nominal, 0.5, 3.3)
    assert ratio == pytest.approx(1.0, abs=0.01)


def test_belt_slip_grows_with_torque(runs):
    nominal, slipping = runs["nominal"]["boom"][1], runs["belt_slip"]["boom"][1]
    hold_torque = float(np.mean(np.abs(nominal.torque_nm[:40])))
    assert _hold_speed(slipping) / _hold_speed(nominal) == pytest.approx(
        1.0 / (1.0 - 0.05 * hold_torque / 100.0), rel=2e-3)
    ratio = _revs(slipping, 0.5, 3.3) / _revs(nominal, 0.5, 3.3)
    assert 1.005 < ratio < 1.05


def test_time_offset_is_a_logging_lag(runs):
    nominal, lagged = runs["nominal"], runs["time_offset"]
    for a in ("boom", "bucket"):
        assert _same_truth(lagged[a][1], nominal[a][1])
        log, ref = lagged[a][0], nominal[a][0]
        assert np.array_equal(log.position_mm, ref.position_mm)
        assert np.array_equal(log.p_a_bar, ref.p_a_bar)
        assert np.array_equal(log.speed_rpm[10:], ref.speed_rpm[:-10])   # 0.1 s at 100 Hz
        assert np.array_equal(log.torque_nm[10:], ref.torque_nm[:-10])
        assert not np.array_equal(log.speed_rpm, ref.speed_rpm)


def test_effects_compose():
    eff = build_effects(["pump_leakage=1.5", "bucket.displacement=0.95", "boom.belt_slip=1"],
                        ("boom", "bucket"))
    assert eff["boom"].non_neutral() == {"pump_leakage": 1.5, "belt_slip": 1.0}
    assert eff["bucket"].non_neutral() == {"pump_leakage": 1.5, "displacement": 0.95}


@pytest.mark.parametrize("text, words", [
    ("pump_leakage=-1", "out of range"),
    ("displacement=0", "out of range"),
    ("compressibility=0.2", "out of range"),
    ("belt_slip=abc", "not a number"),
    ("time_offset=2", "out of range"),
    ("wear=2", "known: pump_leakage, compressibility, belt_slip, displacement, time_offset"),
    ("torque_gain=0.2", "out of range"),
    ("valve_leak=-1", "out of range"),
    ("stick.pump_leakage=2", "unknown unit"),
    ("pump_leakage", "NAME=VALUE"),
])
def test_bad_effects_are_user_errors(text, words):
    with pytest.raises(UserError, match=words):
        parse_effect(text, ("boom", "bucket"))


def test_same_effect_twice_is_an_error():
    with pytest.raises(UserError, match="twice"):
        build_effects(["pump_leakage=2", "boom.pump_leakage=3"], ("boom", "bucket"))
    assert set(EFFECTS) == {"pump_leakage", "compressibility", "belt_slip", "displacement",
                            "time_offset", "oil_temp_offset", "torque_gain", "torque_offset",
                            "position_scale", "position_offset", "valve_leak",
                            "pump_fill", "bore_leak", "leak_orifice", "leak_speed",
                            "seal_friction", "hose_expansion", "torque_lag", "torque_ripple",
                            "torque_speed_offset", "oil_temp_lag"}


def test_measurement_chain_effects_change_the_log_not_the_plant(runs):
    nominal, chain = runs["nominal"], runs["sensors"]
    assert _same_truth(chain["boom"][1], nominal["boom"][1])
    assert _same_log(chain["bucket"][0], nominal["bucket"][0])
    log, ref, truth = chain["boom"][0], nominal["boom"][0], nominal["boom"][1]
    np.testing.assert_allclose(log.torque_nm, 0.9 * truth.torque_nm + 2.0, atol=1 / 32 + 1e-9)
    np.testing.assert_allclose(log.oil_temp_c, ref.oil_temp_c - 10.0, atol=0.051)
    np.testing.assert_allclose(log.position_mm, 1.02 * ref.position_mm + 3.0, atol=0.03)
    assert np.array_equal(log.speed_rpm, ref.speed_rpm)
    assert np.array_equal(log.p_a_bar, ref.p_a_bar)
    for name, state in ref.refs.items():        # the Hall switches see the true position
        assert np.array_equal(log.refs[name], state)


def test_valve_leak_needs_pump_flow_only_above_its_opening(runs):
    nominal, leaky = runs["nominal"], runs["valve_leak"]
    assert _same_truth(leaky["bucket"][1], nominal["bucket"][1])
    t_nom, t_leak = nominal["boom"][1], leaky["boom"][1]
    np.testing.assert_allclose(t_leak.x_m, t_nom.x_m, atol=2e-3)
    # holding the boom (A at ~58 bar) the pumps make up for the seepage above 40 bar:
    # 5 L/min per 100 bar x 18 bar is ~0.9 L/min, some 40 rpm more
    hold = (t_nom.time_s > 0.1) & (t_nom.time_s < 0.45)
    assert 50e5 < np.mean(t_nom.dp_a_pa[hold]) < 70e5
    extra = np.mean(t_leak.speed_rpm[hold]) - np.mean(t_nom.speed_rpm[hold])
    assert 20.0 < extra < 80.0


def test_pump_fill_needs_more_speed_the_faster_the_motor_turns(runs, cfg):
    """Filling short, the pumps deliver 1 - 5 % x (n / limit)^2 of their flow: the position
    loop turns the motor faster for the same rod motion, by that share at each speed."""
    nominal, short = runs["nominal"], runs["pump_fill"]
    assert _same_truth(short["bucket"][1], nominal["bucket"][1])
    t_nom, t_short = nominal["boom"][1], short["boom"][1]
    np.testing.assert_allclose(t_short.x_m, t_nom.x_m, atol=2e-3)
    limit = cfg.unit("boom").motor.speed_limit_rpm
    fast = np.abs(t_nom.speed_rpm) > 0.3 * limit
    assert fast.sum() > 20
    ratio = np.median(t_short.speed_rpm[fast] / t_nom.speed_rpm[fast])
    expected = np.median(1.0 / (1.0 - 0.05 * (t_nom.speed_rpm[fast] / limit) ** 2))
    assert ratio == pytest.approx(expected, abs=0.2 * (expected - 1.0))


def test_bore_leak_is_fed_only_in_the_middle_of_the_stroke(runs):
    """The bucket (850 mm) holds at 300 mm, in the scored third (283-567 mm), against
    ~21 bar on B: 5 L/min per 100 bar there is ~1 L/min, some 40 rpm more; held at 600 mm,
    outside it, the motor turns as without the leak (within the pressures' own settling)."""
    nominal, scored = runs["nominal"], runs["bore_leak"]
    assert _same_truth(scored["boom"][1], nominal["boom"][1])
    t_nom, t_leak = nominal["bucket"][1], scored["bucket"][1]
    np.testing.assert_allclose(t_leak.x_m, t_nom.x_m, atol=2e-3)

    def extra(t0, t1):
        sel = (t_nom.time_s > t0) & (t_nom.time_s < t1)
        return abs(np.mean(t_leak.speed_rpm[sel])) - abs(np.mean(t_nom.speed_rpm[sel]))

    assert 25.0 < extra(2.5, 2.8) < 70.0
    assert abs(extra(6.0, 7.0)) < 5.0

