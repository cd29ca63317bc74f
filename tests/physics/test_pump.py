import math

import numpy as np
import pytest

from ddh_vsensor.physics.conversions import BAR_PA


def test_leak_coefficient_from_nominal_efficiency_by_hand(boom):
    # Boom A: 31.6 cm3/rev, eta_v 0.93 at 250 bar, 1450 pump rpm, 32 cSt at rho(40 °C).
    mu_ref = 32e-6 * 872.0 / (1 + 7e-4 * 25)
    k = 0.07 * 31.6e-6 * 1450 / 60 * mu_ref / 250e5
    assert boom.a.pump.leak_coeff_m3 == pytest.approx(k, rel=1e-12)
    # At the rating point the pump delivers exactly its nominal volumetric efficiency.
    n_motor = 1450 / boom.a.pump.speed_ratio
    q = boom.a.pump.geometric_flow_m3_s(n_motor)
    leak = boom.a.pump.leak_conductance_m3_s_pa(mu_ref) * 250 * BAR_PA
    assert (q - leak) / q == pytest.approx(0.93, rel=1e-12)


def test_leakage_is_inverse_to_viscosity(boom):
    oil = boom.oil
    g_cold = boom.a.pump.leak_conductance_m3_s_pa(oil.dynamic_viscosity_pa_s(10.0))
    g_hot = boom.a.pump.leak_conductance_m3_s_pa(oil.dynamic_viscosity_pa_s(80.0))
    ratio_mu = oil.dynamic_viscosity_pa_s(10.0) / oil.dynamic_viscosity_pa_s(80.0)
    assert g_hot / g_cold == pytest.approx(ratio_mu, rel=1e-12)


def test_torque_pumping_divides_and_motoring_multiplies_by_efficiency(boom):
    pump = boom.a.pump
    dp = 100 * BAR_PA
    ideal = pump.speed_ratio * pump.displacement_m3_rev * dp / (2 * math.pi)
    assert pump.motor_torque_nm(dp, 1000.0) == pytest.approx(ideal / 0.91)     # pumping
    assert pump.motor_torque_nm(dp, -1000.0) == pytest.approx(ideal * 0.91)    # motoring
    # B side draws from its chamber at positive speed: its pressure drives the motor.
    b = boom.b.pump
    ideal_b = b.speed_ratio * b.displacement_m3_rev * dp / (2 * math.pi)
    assert b.motor_torque_nm(dp, 1000.0) == pytest.approx(-ideal_b * 0.91)
    assert b.motor_torque_nm(dp, -1000.0) == pytest.approx(-ideal_b / 0.91)


def test_shaft_power_at_least_hydraulic_power_when_pumping(boom, bucket):
    for unit in (boom, bucket):
        for side in unit.sides:
            n = np.linspace(-6000, 6000, 41)
            dp = np.linspace(-0.3, 300, 37)[:, None] * BAR_PA
            shaft = side.pump.motor_torque_nm(dp, n) * n * 2 * math.pi / 60
            hydraulic = dp * side.pump.geometric_flow_m3_s(n)      # into the fluid
            pumping = hydraulic > 0
            assert np.all(shaft[pumping] >= hydraulic[pumping])
            assert np.all(shaft[~pumping] >= hydraulic[~pumping] - 1e-9)  # motoring: less back


def test_scaling_rejects_non_physical_factors(boom):
    with pytest.raises(ValueError):
        boom.a.pump.scaled(leakage=0.0)
    assert boom.a.pump.scaled(leakage=2.0).leak_coeff_m3 == 2 * boom.a.pump.leak_coeff_m3
