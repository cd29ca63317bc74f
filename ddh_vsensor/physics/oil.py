"""Hydraulic oil: viscosity by ASTM D341 (Walther) and density with temperature.

Pump leakage is laminar, so it scales with 1/dynamic viscosity; the viscosity law therefore
sets how the tables move with temperature.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from ddh_vsensor.config import OilConfig
from ddh_vsensor.physics.conversions import CST_M2S, KELVIN_OFFSET

_WALTHER_SHIFT_CST = 0.7


def _loglog(nu_cst: float) -> float:
    return math.log10(math.log10(nu_cst + _WALTHER_SHIFT_CST))


class Oil:
    """ASTM D341 line through two viscosity points; density with linear thermal expansion."""

    def __init__(self, cfg: OilConfig) -> None:
        self.cfg = cfg
        t40, t100 = math.log10(40.0 + KELVIN_OFFSET), math.log10(100.0 + KELVIN_OFFSET)
        y40, y100 = _loglog(cfg.viscosity_cst_at_40c), _loglog(cfg.viscosity_cst_at_100c)
        self._slope = (y100 - y40) / (t100 - t40)   # -B of log log(nu+0.7) = A - B log T
        self._intercept = y40 - self._slope * t40

    def __eq__(self, other: object) -> bool:
        """An oil is its configuration (units built from equal configurations are equal)."""
        return isinstance(other, Oil) and other.cfg == self.cfg

    def __hash__(self) -> int:
        return hash(self.cfg)

    @property
    def walther_coefficients(self) -> tuple[float, float]:
        """(a, b) of the D341 line log10 log10(nu_cSt + 0.7) = a + b log10(T / K)."""
        return self._intercept, self._slope

    def kinematic_viscosity_cst(self, temp_c: ArrayLike) -> np.ndarray:
        t = np.log10(np.asarray(temp_c, dtype=float) + KELVIN_OFFSET)
        return 10.0 ** (10.0 ** (self._intercept + self._slope * t)) - _WALTHER_SHIFT_CST

    def density_kg_m3(self, temp_c: ArrayLike) -> np.ndarray:
        dt = np.asarray(temp_c, dtype=float) - 15.0
        return self.cfg.density_kg_m3_at_15c / (1.0 + self.cfg.thermal_expansion_per_k * dt)

    def dynamic_viscosity_pa_s(self, temp_c: ArrayLike) -> np.ndarray:
        return self.kinematic_viscosity_cst(temp_c) * CST_M2S * self.density_kg_m3(temp_c)

    def temperature_at_viscosity_c(self, nu_cst: float) -> float:
        """Inverse of the D341 line: the temperature where the oil has ``nu_cst``."""
        return 10.0 ** ((_loglog(nu_cst) - self._intercept) / self._slope) - KELVIN_OFFSET
