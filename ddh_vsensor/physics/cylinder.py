"""The cylinder(s) of a unit: areas, stroke and friction, totalled over parallel cylinders."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from ddh_vsensor.config import UnitConfig
from ddh_vsensor.physics.conversions import MM2_M2


@dataclass(frozen=True)
class Cylinder:
    """Totals over ``count`` identical cylinders working in parallel."""

    count: int
    stroke_m: float
    area_a_m2: float
    area_b_m2: float
    static_friction_n: float
    coulomb_friction_n: float
    viscous_friction_n_s_m: float

    @classmethod
    def from_config(cls, cfg: UnitConfig) -> "Cylinder":
        n = cfg.cylinders
        return cls(count=n, stroke_m=cfg.stroke_mm * 1e-3,
                   area_a_m2=n * cfg.area_a_mm2 * MM2_M2, area_b_m2=n * cfg.area_b_mm2 * MM2_M2,
                   static_friction_n=n * cfg.friction_static_n,
                   coulomb_friction_n=n * cfg.friction_coulomb_n,
                   viscous_friction_n_s_m=n * cfg.friction_viscous_n_s_per_m)

    def hydraulic_force_n(self, p_a_pa: ArrayLike, p_b_pa: ArrayLike) -> np.ndarray:
        """Force extending the rod(s) from gauge chamber pressures."""
        return self.area_a_m2 * np.asarray(p_a_pa) - self.area_b_m2 * np.asarray(p_b_pa)

    def moving_friction_n(self, velocity_m_s: ArrayLike) -> np.ndarray:
        """Friction opposing motion: Coulomb plus viscous; zero at exactly zero velocity."""
        v = np.asarray(velocity_m_s, dtype=float)
        return self.coulomb_friction_n * np.sign(v) + self.viscous_friction_n_s_m * v
