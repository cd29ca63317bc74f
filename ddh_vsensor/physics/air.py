"""Entrained air in the oil: the standard oil-air mixture law.

A unit volume of mixture at atmospheric pressure holds a volume fraction X of free air. At an
absolute pressure p the oil compresses with its own bulk modulus and the air polytropically:

    V(p) = (1 - X) exp(-(p - p0) / beta_oil) + X (p0 / p)^(1/kappa)

so the effective bulk modulus -V dp/dV collapses at low pressure, where the air is not yet
compressed, and tends to the oil's own at high pressure. ``log_density`` (= -ln V) is what a
chamber balance needs: the oil a chamber of fixed size takes in between two pressures is its
volume times the change of -ln V. X = 0 is the nominal oil of the configuration.

Below an absolute pressure of 1 kPa the oil cavitates: the gas fills a cavity while the
pressure stays put. The law holds the floor's compliance there, so -ln V goes on falling
with it and the pressure a chamber shows below the floor is its cavity's volume over that
compliance (a hundred pascals per percent of the chamber with 0.5 % of air).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

ATMOSPHERE_PA = 101325.0        # absolute pressure at which the air fraction is stated
POLYTROPIC_EXPONENT = 1.4       # fast compression: adiabatic air
MIN_ABSOLUTE_PA = 1000.0        # below it the gas fills a cavity (deep cavitation)


def _parts(p_gauge_pa: ArrayLike, air_fraction: ArrayLike, beta_oil_pa: float,
           reservoir_pa: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    p = np.maximum(np.asarray(p_gauge_pa, dtype=float) + reservoir_pa + ATMOSPHERE_PA,
                   MIN_ABSOLUTE_PA)
    x = np.asarray(air_fraction, dtype=float)
    oil = (1.0 - x) * np.exp(-(p - ATMOSPHERE_PA) / beta_oil_pa)
    air = x * (ATMOSPHERE_PA / p) ** (1.0 / POLYTROPIC_EXPONENT)
    return p, oil, air


def _cavity(p_gauge_pa: ArrayLike, reservoir_pa: float) -> np.ndarray:
    """How far below the floor a gauge pressure is (Pa, <= 0): there the gas fills a cavity
    that grows at the floor's compliance, so log_density's slope stays the compliance."""
    return np.minimum(np.asarray(p_gauge_pa, dtype=float) + reservoir_pa + ATMOSPHERE_PA
                      - MIN_ABSOLUTE_PA, 0.0)


def log_density(p_gauge_pa: ArrayLike, air_fraction: ArrayLike, beta_oil_pa: float,
                reservoir_pa: float = 0.0) -> np.ndarray:
    """-ln of the mixture's specific volume relative to atmospheric pressure."""
    return log_density_and_compliance(p_gauge_pa, air_fraction, beta_oil_pa, reservoir_pa)[0]


def compliance(p_gauge_pa: ArrayLike, air_fraction: ArrayLike, beta_oil_pa: float,
               reservoir_pa: float = 0.0) -> np.ndarray:
    """1 / effective bulk modulus (1/Pa) at a gauge pressure: d(log_density)/dp."""
    p, oil, air = _parts(p_gauge_pa, air_fraction, beta_oil_pa, reservoir_pa)
    return (oil / beta_oil_pa + air / (POLYTROPIC_EXPONENT * p)) / (oil + air)


def log_density_and_compliance(p_gauge_pa: ArrayLike, air_fraction: ArrayLike,
                               beta_oil_pa: float, reservoir_pa: float = 0.0
                               ) -> tuple[np.ndarray, np.ndarray]:
    """Both of the above from one evaluation of the law (the chamber model's inner loop)."""
    p, oil, air = _parts(p_gauge_pa, air_fraction, beta_oil_pa, reservoir_pa)
    mix = oil + air
    comp = (oil / beta_oil_pa + air / (POLYTROPIC_EXPONENT * p)) / mix
    return -np.log(mix) + comp * _cavity(p_gauge_pa, reservoir_pa), comp


def secant_compliance(p0_pa: ArrayLike, p1_pa: ArrayLike, air_fraction: ArrayLike,
                      beta_oil_pa: float, reservoir_pa: float = 0.0) -> np.ndarray:
    """Mean compliance over [p0, p1]: the exact compression between the two pressures."""
    p0, p1 = np.asarray(p0_pa, dtype=float), np.asarray(p1_pa, dtype=float)
    dp = p1 - p0
    small = np.abs(dp) < 100.0
    phi = (log_density(p1, air_fraction, beta_oil_pa, reservoir_pa)
           - log_density(p0, air_fraction, beta_oil_pa, reservoir_pa))
    tangent = compliance(0.5 * (p0 + p1), air_fraction, beta_oil_pa, reservoir_pa)
    return np.where(small, tangent, phi / np.where(small, 1.0, dp))
