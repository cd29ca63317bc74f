import math

import numpy as np

from ddh_vsensor.physics.oil import Oil


def _walther_by_hand(t_c: float) -> float:
    """ASTM D341 through 32 cSt @ 40 °C and 6.1 cSt @ 100 °C, written out independently."""
    y1 = math.log10(math.log10(32.0 + 0.7))
    y2 = math.log10(math.log10(6.1 + 0.7))
    x1, x2 = math.log10(313.15), math.log10(373.15)
    y = y1 + (y2 - y1) * (math.log10(t_c + 273.15) - x1) / (x2 - x1)
    return 10 ** (10 ** y) - 0.7


def test_viscosity_passes_through_the_datasheet_points(cfg):
    oil = Oil(cfg.oil)
    assert oil.kinematic_viscosity_cst(40.0) == np.float64(32.0) or \
        abs(oil.kinematic_viscosity_cst(40.0) - 32.0) < 1e-9
    assert abs(oil.kinematic_viscosity_cst(100.0) - 6.1) < 1e-9


def test_viscosity_matches_hand_computed_walther(cfg):
    oil = Oil(cfg.oil)
    for t in (-5.0, 0.0, 27.0, 60.0, 90.0):
        assert abs(oil.kinematic_viscosity_cst(t) / _walther_by_hand(t) - 1) < 1e-12
    # -5 °C is far thicker than 40 °C: HV oil still ~ 300-400 cSt there.
    assert 250.0 < oil.kinematic_viscosity_cst(-5.0) < 500.0


def test_density_and_dynamic_viscosity(cfg):
    oil = Oil(cfg.oil)
    assert abs(oil.density_kg_m3(15.0) - 872.0) < 1e-9
    assert abs(oil.density_kg_m3(40.0) - 872.0 / (1 + 7e-4 * 25)) < 1e-9
    mu = oil.dynamic_viscosity_pa_s(40.0)
    assert abs(mu - 32e-6 * 872.0 / (1 + 7e-4 * 25)) < 1e-12
    assert abs(oil.temperature_at_viscosity_c(32.0) - 40.0) < 1e-9
