"""Plant structure the estimator's model does not share: neutral to the bit, typical values
doing what the physics says, all of them together at twice typical without a NaN."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from ddh_vsensor.physics.air import log_density
from ddh_vsensor.physics.conversions import BAR_PA, CST_M2S
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.sim import RunSpec, simulate_with_truth
from ddh_vsensor.sim.cycles import Profile, Trajectory
from ddh_vsensor.sim.effects import (
    NOMINAL,
    STRUCTURE_TYPICAL,
    UnitEffects,
    structure_effects,
)
from ddh_vsensor.model.plant import Plant
from ddh_vsensor.model.unit import seal_rings_m2
from ddh_vsensor.sim.sensors import SensorSettings, first_order_lag

T = 27.0
PLANT = ("leak_orifice", "leak_speed", "seal_friction", "hose_expansion")
CHAIN = ("torque_lag", "torque_ripple", "torque_speed_offset", "oil_temp_lag")
TRUTH_FIELDS = ("x_m", "v_m_s", "dp_a_pa", "dp_b_pa", "speed_rpm", "torque_nm")
LOG_FIELDS = ("speed_rpm", "torque_nm", "oil_temp_c", "position_mm", "p_a_bar", "p_b_bar")


@pytest.fixture(scope="module")
def runs(cfg, short_profile):
    """The short profile: nominal alone, then one batch with the nominal plant, each effect
    given explicitly at its neutral value, and each at its typical value."""
    solo = simulate_with_truth(cfg, [RunSpec(cycle=short_profile, seed=3)])[0]
    names = PLANT + CHAIN
    specs = [RunSpec(cycle=short_profile, seed=3)]
    specs += [RunSpec(cycle=short_profile, seed=3, effects=[f"{n}=0"]) for n in names]
    specs += [RunSpec(cycle=short_profile, seed=3, effects=[f"{n}={STRUCTURE_TYPICAL[n]}"])
              for n in names]
    batch = simulate_with_truth(cfg, specs)
    out = {"solo": solo, "nominal": batch[0]}
    out.update({f"{n}=0": r for n, r in zip(names, batch[1:1 + len(names)])})
    out.update({n: r for n, r in zip(names, batch[1 + len(names):])})
    return out


def _same(a, b, fields) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in fields)


# --- neutral: today's plant to the bit ----------------------------------------------------

@pytest.mark.parametrize("name", PLANT + CHAIN)
def test_neutral_value_is_the_nominal_plant_to_the_bit(runs, name):
    """Each effect at its neutral value, simulated in a batch whose other rows have the
    effects on (their code paths run for every row), equals the nominal run simulated alone,
    in every true and every logged signal."""
    for case in ("nominal", f"{name}=0"):
        for a in ("boom", "bucket"):
            run, truth = runs[case][a]
            ref_run, ref_truth = runs["solo"][a]
            assert _same(truth, ref_truth, TRUTH_FIELDS), (case, a)
            assert _same(run, ref_run, LOG_FIELDS), (case, a)


@pytest.mark.parametrize("name", PLANT)
def test_plant_effects_change_the_plant(runs, name):
    truth, ref = runs[name]["boom"][1], runs["nominal"]["boom"][1]
    assert not _same(truth, ref, TRUTH_FIELDS)
    # the position loop still follows its setpoint
    np.testing.assert_allclose(truth.x_m, ref.x_m, atol=3e-3)


@pytest.mark.parametrize("name", CHAIN)
def test_chain_effects_change_the_log_not_the_plant(runs, name):
    (run, truth), (ref_run, ref) = runs[name]["boom"], runs["nominal"]["boom"]
    assert _same(truth, ref, TRUTH_FIELDS)
    assert np.array_equal(run.position_mm, ref_run.position_mm)
    assert not _same(run, ref_run, ("torque_nm", "oil_temp_c"))


# --- leakage ------------------------------------------------------------------------------

def _rating(cfg, unit):
    hyd = cfg.hydraulics
    t_r = unit.oil.temperature_at_viscosity_c(hyd.nominal_viscosity_cst)
    mu_r = hyd.nominal_viscosity_cst * CST_M2S * float(unit.oil.density_kg_m3(t_r))
    return hyd.nominal_pressure_bar * BAR_PA, mu_r


def test_orifice_share_keeps_the_rating_point_and_leaks_more_below_it(cfg, boom):
    dp_r, mu_r = _rating(cfg, boom)
    row = UnitEffects(leak_orifice=30.0).row(boom, 0.0, cfg.hydraulics)
    for side, k_orf in (("a", row.orifice_leak_a_m3_s_sqrt_pa),
                        ("b", row.orifice_leak_b_m3_s_sqrt_pa)):
        k_lam = getattr(boom, side).pump.leak_coeff_m3
        k_lam_row = getattr(row.unit, side).pump.leak_coeff_m3
        dp = np.array([10e5, 60e5, 150e5, dp_r, 350e5])
        total = k_lam_row * dp / mu_r + k_orf * np.sqrt(dp)
        laminar = k_lam * dp / mu_r
        assert total[3] == pytest.approx(laminar[3], rel=1e-12)
        assert k_orf * math.sqrt(dp_r) == pytest.approx(0.3 * laminar[3], rel=1e-12)
        assert np.all(total[:3] > laminar[:3])     # below the rating pressure: more
        assert total[4] < laminar[4]


@pytest.fixture(scope="module")
def holds(cfg):
    """3 s of holding both units still: nominal, and each leakage effect at its typical
    value (the runs start at the nominal plant's holding state and settle within 1 s)."""
    still = Profile("hold", {"boom": Trajectory(np.array([0.0, 3.0]), np.full(2, 1.5)),
                             "bucket": Trajectory(np.array([0.0, 3.0]), np.full(2, 600.0))},
                    3.0)
    cases = {"nominal": None, "leak_orifice": [f"leak_orifice={STRUCTURE_TYPICAL['leak_orifice']}"],
             "leak_speed": [f"leak_speed={STRUCTURE_TYPICAL['leak_speed']}"]}
    runs = simulate_with_truth(cfg, [RunSpec(cycle=still, effects=e) for e in cases.values()])
    return dict(zip(cases, runs))


def _hold(truth):
    sel = truth.time_s > 1.5
    return float(np.mean(truth.speed_rpm[sel])), float(np.mean(truth.dp_a_pa[sel]))


def test_orifice_share_raises_the_holding_creep_by_its_law(cfg, boom, holds):
    """Holding the boom (A at ~58 bar, its valves closed) the A pumps deliver exactly A's
    leakage: with the orifice share that leakage is the law's, more than the laminar one
    (at 27 degC, 58 bar: some 80 % more)."""
    dp_r, mu_r = _rating(cfg, boom)
    n_nom, dp_nom = _hold(holds["nominal"]["boom"][1])
    n, dp = _hold(holds["leak_orifice"]["boom"][1])
    assert dp == pytest.approx(dp_nom, rel=0.01)
    mu = float(boom.oil.dynamic_viscosity_pa_s(T))
    k = boom.a.pump.leak_coeff_m3
    q_per_rpm = float(boom.a.pump.geometric_flow_m3_s(1.0))
    s = STRUCTURE_TYPICAL["leak_orifice"] / 100.0
    expected = ((1 - s) * k * dp / mu + s * k * math.sqrt(dp_r) / mu_r * math.sqrt(dp)) \
        / q_per_rpm
    assert n == pytest.approx(expected, rel=0.01)
    assert n_nom == pytest.approx(k * dp_nom / mu / q_per_rpm, rel=0.01)
    assert n > 1.2 * n_nom


def test_speed_leakage_keeps_the_rating_speed_and_leaks_less_at_standstill(cfg, boom, holds):
    c = STRUCTURE_TYPICAL["leak_speed"]
    plant = Plant([UnitEffects(leak_speed=c).row(boom, 0.0, cfg.hydraulics)], 1e-3)
    rated_motor = cfg.hydraulics.nominal_pump_speed_rpm / boom.a.pump.speed_ratio
    assert plant.leak_base[0] + plant.leak_slope_a[0] * rated_motor == pytest.approx(1.0)
    assert plant.leak_base[0] == pytest.approx(1.0 / (1.0 + c))
    # holding, n q = g dp (b + s n): the creep speed solves that
    n_nom, dp_nom = _hold(holds["nominal"]["boom"][1])
    n, dp = _hold(holds["leak_speed"]["boom"][1])
    g_dp = n_nom * float(boom.a.pump.geometric_flow_m3_s(1.0)) * dp / dp_nom
    q = float(boom.a.pump.geometric_flow_m3_s(1.0))
    expected = g_dp * plant.leak_base[0] / (q - g_dp * plant.leak_slope_a[0])
    assert n == pytest.approx(expected, rel=0.01)
    assert n < 0.85 * n_nom


# --- seal friction ------------------------------------------------------------------------

def test_seal_friction_is_the_pressure_share_on_the_rings(cfg, boom, runs):
    """Lifting the boom at constant speed, the force the pressures spend beyond load,
    Coulomb and viscous friction and the mass's acceleration is the seals' pressure friction:
    mu_p (p_a A_a,ring + p_b A_b,ring), within 3 %; without the effect it is nothing (within
    30 N)."""
    mu_p = STRUCTURE_TYPICAL["seal_friction"] / 100.0
    ring_a, ring_b = seal_rings_m2(boom)
    cyl = boom.cylinder
    # 2 x 114 mm bores, 4 mm seals: the A ring is 2 pi 0.1143 m x 4 mm
    assert ring_a == pytest.approx(2 * math.pi * 0.1143 * 4e-3, rel=1e-3)

    def residual(truth):
        sel = (truth.time_s > 1.3) & (truth.time_s < 2.2)      # mid-lift, constant speed
        v = truth.v_m_s[sel]
        assert np.all(v > 0.03) and np.ptp(v) < 0.05 * np.mean(v)
        accel = np.gradient(truth.v_m_s, truth.time_s)[sel]
        force = (cyl.area_a_m2 * truth.dp_a_pa[sel] - cyl.area_b_m2 * truth.dp_b_pa[sel]
                 - boom.load_force_n(0.0) - cyl.coulomb_friction_n
                 - cyl.viscous_friction_n_s_m * v - boom.moving_mass_kg(0.0) * accel)
        seal = mu_p * (ring_a * np.maximum(truth.dp_a_pa[sel], 0.0)
                       + ring_b * np.maximum(truth.dp_b_pa[sel], 0.0))
        return float(np.mean(force)), float(np.mean(seal))

    f_nom, _ = residual(runs["nominal"]["boom"][1])
    f, seal = residual(runs["seal_friction"]["boom"][1])
    assert abs(f_nom) < 30.0
    assert seal > 400.0
    assert f == pytest.approx(seal, rel=0.03)


# --- hose expansion -----------------------------------------------------------------------

def test_hose_expansion_slows_the_pressure_rise_by_its_capacitance(cfg, boom):
    """The rod on its bottom stop, the A pumps turning slowly: A's pressure rises at the
    pump's flow over the chamber's capacitance, V/beta nominal, V/beta + V_dead e with the
    hoses' walls."""
    e = STRUCTURE_TYPICAL["hose_expansion"] / 100.0 / (100.0 * BAR_PA)
    rows = [NOMINAL.row(boom, 0.0, cfg.hydraulics),
            UnitEffects(hose_expansion=STRUCTURE_TYPICAL["hose_expansion"]).row(
                boom, 0.0, cfg.hydraulics)]
    h, p0, n = 1e-3, 5e5, 100.0
    plant = Plant(rows, h)
    plant.set_speed_control(np.ones(2, bool), n)
    plant.set_state(np.zeros(2), np.full(2, n), np.full(2, p0), np.zeros(2))
    mu = boom.oil.dynamic_viscosity_pa_s(np.full(2, T))
    plant.step(np.zeros(2), mu)
    assert np.all(plant.x == 0.0) and np.all(plant.regime_a == 2)      # A's valves closed
    c_nom = boom.dead_volume_m3 / boom.bulk_modulus_pa
    c = np.array([c_nom, c_nom + boom.dead_volume_m3 * e])
    # backward Euler on C dp/dt = q n - g p
    g = boom.a.pump.leak_conductance_m3_s_pa(mu)
    q = float(boom.a.pump.geometric_flow_m3_s(n))
    np.testing.assert_allclose(plant.dp_a, (c * p0 + h * q) / (c + h * g), rtol=1e-12)
    rise = plant.dp_a - p0
    assert rise[1] / rise[0] == pytest.approx(c[0] / c[1], rel=0.01)
    assert c[0] / c[1] < 0.5


def test_oil_is_conserved_with_the_structure(cfg, short_profile):
    """Per step, the pumps' flow less the structure's leakage law (conductance at the step's
    start) equals the chambers' growth plus the oil's and air's compression plus the hoses'
    expansion."""
    eff = structure_effects(1.0)
    spec = RunSpec(cycle=short_profile, effects={"boom": eff, "bucket": eff},
                   sensors=SensorSettings(rate_hz=1000.0, oil_temp_drift_c_per_s=0.0))
    runs = simulate_with_truth(cfg, [spec])[0]
    for a in ("boom", "bucket"):
        tr = runs[a][1]
        unit = DDHUnit.from_config(cfg, a)
        row = eff.row(unit, 0.0, cfg.hydraulics)
        plant = Plant([row], 1e-3)
        mu = unit.oil.dynamic_viscosity_pa_s(tr.oil_temp_c[1:])
        h = tr.time_s[1] - tr.time_s[0]
        cyl = unit.cylinder
        for side, dp in (("a", tr.dp_a_pa), ("b", tr.dp_b_pa)):
            s = getattr(row.unit, side)
            k_orf = getattr(plant, f"orifice_{side}")[0]
            slope = getattr(plant, f"leak_slope_{side}")[0]
            g = (s.pump.leak_coeff_m3 / mu + k_orf / np.sqrt(np.maximum(np.abs(dp[:-1]), 1e5))) \
                * (plant.leak_base[0] + slope * np.abs(tr.speed_rpm[:-1]))
            inflow = (s.pump.geometric_flow_m3_s(tr.speed_rpm[1:]) - g * dp[1:]
                      + s.anticav.flow_m3_s(dp[1:]) - s.relief.flow_m3_s(dp[1:])) * h
            growth = s.sign * s.area_m2 * np.diff(tr.x_m)
            vol = unit.dead_volume_m3 + (s.area_m2 * tr.x_m[:-1] if side == "a"
                                         else s.area_m2 * (cyl.stroke_m - tr.x_m[:-1]))
            air = np.full_like(dp, row.air_fraction)
            compression = vol * np.diff(log_density(dp, air, unit.bulk_modulus_pa))
            hoses = unit.dead_volume_m3 * row.hose_compliance_per_pa * np.diff(dp)
            residual = inflow - growth - compression - hoses
            moved = np.sum(np.abs(inflow))
            assert moved > 1e-4
            assert np.max(np.abs(residual)) < 1e-5 * moved, (a, side)


# --- the drive's torque and the tank sensor -----------------------------------------------

def test_lag_trails_a_step_by_its_time_constant():
    """A step sampled at 10 kHz: the lag reaches 1 - 1/e of it one time constant after the
    step (within 0.1 ms), and on a ramp it runs tau x slope behind, exactly."""
    t = np.arange(2000) * 1e-4
    tau = STRUCTURE_TYPICAL["torque_lag"] * 1e-3
    step = np.where(t >= 0.05, 10.0, 0.0)
    y = first_order_lag(t, step, tau)
    t63 = t[np.argmax(y >= 10.0 * (1.0 - math.exp(-1.0)))]
    assert t63 - 0.05 == pytest.approx(tau, abs=1e-4)
    assert y[0] == 0.0 and y[-1] == pytest.approx(10.0, abs=1e-9)
    ramp = 3.0 + 2.0 * t
    np.testing.assert_allclose(first_order_lag(t, ramp, tau, 2.0), ramp - 2.0 * tau,
                               rtol=0, atol=1e-12)


def test_drive_torque_ripple_and_speed_offset(cfg, runs):
    """The logged torque less the (lagless) shaft torque: ripple of the stated amplitude,
    and the losses' offset proportional to speed, in the direction of turning."""
    motor = cfg.unit("boom").motor
    run, truth = runs["torque_ripple"]["boom"]
    diff = run.torque_nm - truth.torque_nm
    amp = STRUCTURE_TYPICAL["torque_ripple"] / 100.0 * motor.torque_limit_nm
    moving = np.abs(truth.speed_rpm) > 500.0
    assert np.max(np.abs(diff)) <= amp + 1 / 32 + 1e-9
    assert np.sqrt(np.mean(diff[moving] ** 2)) == pytest.approx(amp / math.sqrt(2), rel=0.2)
    run, truth = runs["torque_speed_offset"]["boom"]
    expected = STRUCTURE_TYPICAL["torque_speed_offset"] * truth.speed_rpm / motor.speed_limit_rpm
    np.testing.assert_allclose(run.torque_nm - truth.torque_nm, expected, atol=1 / 32 + 1e-9)
    assert np.max(expected) > 0.5 and np.min(expected) < -0.5


def test_logged_torque_lags_the_shaft_in_the_run(runs):
    """At the logger's 100 Hz the lagged torque is nearer the shaft torque of 3 ms before
    than of the sample's own instant."""
    run, truth = runs["torque_lag"]["boom"]
    tau = STRUCTURE_TYPICAL["torque_lag"] * 1e-3
    earlier = np.interp(truth.time_s - tau, truth.time_s, truth.torque_nm)
    busy = np.abs(np.gradient(truth.torque_nm, truth.time_s)) > 50.0    # N*m/s
    assert busy.sum() > 20
    err_now = np.abs(run.torque_nm - truth.torque_nm)[busy]
    err_before = np.abs(run.torque_nm - earlier)[busy]
    assert np.mean(err_before) < 0.5 * np.mean(err_now)


def test_tank_sensor_reads_below_the_pumps_oil_in_warm_up(runs):
    """Warming at the simulator's 0.01 degC/s, the tank sensor with a 3 min lag reads
    0.01 x 180 = 1.8 degC below the pumps' oil, throughout the run (to 0.1 degC steps)."""
    run, truth = runs["oil_temp_lag"]["boom"]
    drift = SensorSettings().oil_temp_drift_c_per_s
    behind = truth.oil_temp_c - run.oil_temp_c
    np.testing.assert_allclose(behind, drift * STRUCTURE_TYPICAL["oil_temp_lag"], atol=0.051)


def test_tank_sensor_catches_up_after_a_warm_up():
    """Pumps' oil rising 20 degC in 10 min then steady: the sensor reads below throughout,
    and within 1/e^3 of the gap three time constants after the warm-up stops."""
    t = np.arange(0.0, 1800.0, 1.0)
    oil = 20.0 + np.minimum(t, 600.0) * (20.0 / 600.0)
    tau = STRUCTURE_TYPICAL["oil_temp_lag"]
    tank = first_order_lag(t, oil, tau, 20.0 / 600.0)
    assert np.all(tank[1:] < oil[1:])
    gap_at_stop = oil[600] - tank[600]
    assert gap_at_stop == pytest.approx(20.0 / 600.0 * tau, rel=0.01)
    k = 600 + int(3 * tau)
    assert oil[k] - tank[k] < gap_at_stop * math.exp(-3.0) * 1.5


# --- all of them ----------------------------------------------------------------------------

@pytest.mark.parametrize("temp_c, payload_kg", [(-10.0, 1040.0), (80.0, 0.0)])
def test_everything_at_twice_typical_runs_clean(cfg, short_profile, temp_c, payload_kg):
    eff = structure_effects(2.0)
    assert set(eff.non_neutral()) == set(STRUCTURE_TYPICAL)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)       # unsettled steps, NaN arithmetic
        runs = simulate_with_truth(cfg, [RunSpec(cycle=short_profile, oil_temp_c=temp_c,
                                                 payload_kg=payload_kg,
                                                 effects={"boom": eff, "bucket": eff})])[0]
    for a, (run, truth) in runs.items():
        for f in TRUTH_FIELDS:
            assert np.all(np.isfinite(getattr(truth, f))), (a, f)
        for f in LOG_FIELDS:
            assert np.all(np.isfinite(getattr(run, f))), (a, f)
        assert np.max(np.abs(truth.x_m[-100:] - truth.x_m[-1])) < 2e-3
