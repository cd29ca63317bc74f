"""The steady state: exact balances, the circuit's consequences, hand-computed points."""

import numpy as np
import pytest

from ddh_vsensor.physics.steady import (holding_speed, steady_state, steady_state_at_torque,
                                        velocity_torque_curve)
from ddh_vsensor.physics.conversions import BAR_PA


def _random_points(unit, rng, count=20000):
    n = rng.uniform(-6000, 6000, count)
    f0 = unit.load_force_n(0.0)
    f = rng.uniform(-1.5, 3.0, count) * f0
    t = rng.uniform(-5, 100, count)
    return n, f, t


@pytest.mark.parametrize("name", ["boom", "bucket"])
def test_every_balance_holds_over_the_whole_range(name, request):
    unit = request.getfixturevalue(name)
    rng = np.random.default_rng(7)
    n, f, t = _random_points(unit, rng)
    s = steady_state(unit, n, f, t)
    cyl = unit.cylinder
    # Volume balance of each chamber, from the reported flows.
    res_a = (s.pump_a_m3_s - s.leak_a_m3_s + s.anticav_a_m3_s - s.relief_a_m3_s
             - cyl.area_a_m2 * s.velocity_m_s)
    res_b = (s.pump_b_m3_s - s.leak_b_m3_s + s.anticav_b_m3_s - s.relief_b_m3_s
             + cyl.area_b_m2 * s.velocity_m_s)
    scale = np.abs(s.pump_a_m3_s) + 1e-6
    assert np.max(np.abs(res_a) / scale) < 1e-9
    assert np.max(np.abs(res_b) / scale) < 1e-9
    # Force balance: moving points against Coulomb + viscous, stuck points within static.
    net = cyl.hydraulic_force_n(s.p_a_pa, s.p_b_pa) - f
    moving = s.velocity_m_s != 0
    fr = cyl.moving_friction_n(s.velocity_m_s)
    assert np.max(np.abs(net[moving] - fr[moving]) / np.abs(f0 := unit.load_force_n(0))) < 1e-9
    assert np.all(np.abs(net[~moving]) <= cyl.static_friction_n + 1e-6)
    # Valve states agree with the pressures they produced (no clamping after the fact).
    for p, relief, anticav, side in ((s.p_a_pa, s.relief_a_m3_s, s.anticav_a_m3_s, unit.a),
                                     (s.p_b_pa, s.relief_b_m3_s, s.anticav_b_m3_s, unit.b)):
        assert np.all((relief > 0) == (p > side.relief.setting_pa))
        assert np.all((anticav > 0) == (p < side.anticav.cracking_pa))


@pytest.mark.parametrize("name", ["boom", "bucket"])
def test_torque_parametrisation_is_the_same_family(name, request):
    unit = request.getfixturevalue(name)
    n, f, t = _random_points(unit, np.random.default_rng(3), 5000)
    s = steady_state(unit, n, f, t)
    s2 = steady_state_at_torque(unit, n, s.torque_nm, t)
    assert np.max(np.abs(s2.velocity_m_s - s.velocity_m_s)) < 1e-9
    assert np.max(np.abs(s2.p_a_pa - s.p_a_pa)) < 1.0


def test_curve_breakpoints_reproduce_the_torque_solution(boom):
    n = np.array([-4000.0, -50.0, 0.0, 20.0, 3000.0])
    tau, v = velocity_torque_curve(boom, n, 27.0)
    q = np.linspace(-80, 80, 321)
    for i in range(len(n)):
        exact = steady_state_at_torque(boom, n[i], q, 27.0).velocity_m_s
        assert np.max(np.abs(np.interp(q, tau[i], v[i]) - exact)) < 1e-12


def test_geometric_motion_when_leakage_is_switched_off(boom, bucket):
    for unit in (boom, bucket):
        tight = unit.with_pumps(leakage=1e-9)
        for n in (3000.0, -3000.0):
            s = steady_state(tight, n, tight.load_force_n(0), 27.0)
            q_a = tight.a.pump.geometric_flow_m3_s(n) / tight.cylinder.area_a_m2
            q_b = -tight.b.pump.geometric_flow_m3_s(n) / tight.cylinder.area_b_m2
            # The side that falls short sets the speed; the other side's valve takes the rest.
            expected = min(q_a, q_b, key=abs)
            assert float(s.velocity_m_s) == pytest.approx(expected, rel=1e-6)


def test_circuit_consequences_of_the_flow_ratios(boom, bucket):
    """Spec: boom flow ratio 1.416 < area ratio 1.446, bucket 1.542 > 1.524."""
    up = steady_state(boom, 4000.0, boom.load_force_n(0), 27.0)
    down = steady_state(boom, -4000.0, boom.load_force_n(0), 27.0)
    assert up.anticav_b_m3_s > 0 and up.relief_a_m3_s == 0      # extending: B runs short
    assert down.relief_b_m3_s > 0                               # retracting: B has surplus
    assert down.p_b_pa == pytest.approx(70 * BAR_PA, rel=0.01)   # ... held at its relief
    ext = steady_state(bucket, 4000.0, bucket.load_force_n(0), 27.0)
    ret = steady_state(bucket, -4000.0, bucket.load_force_n(0), 27.0)
    # Extending: A has surplus. The load pulls, yet A pressurises until its leakage takes the
    # surplus, and at high speed the relief valve does.
    assert ext.p_a_pa > 30 * BAR_PA
    assert steady_state(bucket, 5500.0, bucket.load_force_n(0), 27.0).relief_a_m3_s > 0
    assert ret.anticav_a_m3_s > 0 and ret.relief_b_m3_s == 0     # retracting: A runs short


def test_relief_opening_drops_the_movement(boom):
    n = 3000.0
    torque = np.linspace(20, 130, 221)
    s = steady_state_at_torque(boom, n, torque, 27.0)
    mm_rev = s.velocity_m_s * 1e3 / (n / 60)
    opening = s.relief_a_m3_s > 0
    assert opening.any() and (~opening).any()
    slope_closed = np.diff(mm_rev)[~opening[1:]].mean()
    slope_relief = np.diff(mm_rev)[opening[1:]].mean()
    assert slope_relief < 20 * slope_closed < 0        # a much steeper drop past the setting


def test_standstill_at_the_leakage_balance_speed(boom, bucket):
    for unit in (boom, bucket):
        f = unit.load_force_n(0)
        h = holding_speed(unit, f, 27.0)
        assert h.band_low_rpm < h.speed_rpm < h.band_high_rpm
        s = steady_state(unit, h.speed_rpm, f, 27.0)
        assert float(s.velocity_m_s) == 0.0
        assert steady_state(unit, h.band_high_rpm + 5, f, 27.0).velocity_m_s > 0
        assert steady_state(unit, h.band_low_rpm - 5, f, 27.0).velocity_m_s < 0


def test_boom_holding_speed_by_hand(boom):
    """Tens of rpm, as the paper saw during holds: motor speed = leakage / displacement."""
    f = boom.load_force_n(0)
    mu = boom.oil.dynamic_viscosity_pa_s(27.0)
    # The B pump draws its side down to the anti-cavitation cracking pressure (~ -0.3 bar).
    dp_b = -0.3 * BAR_PA
    dp_a = (f + boom.cylinder.area_b_m2 * dp_b) / boom.cylinder.area_a_m2
    leak = boom.a.pump.leak_coeff_m3 * dp_a / mu
    n_hand = leak / (boom.a.pump.displacement_m3_rev * boom.a.pump.speed_ratio) * 60
    h = holding_speed(boom, f, 27.0)
    assert h.speed_rpm == pytest.approx(n_hand, rel=0.01)
    assert 10.0 <= h.speed_rpm < 100.0
