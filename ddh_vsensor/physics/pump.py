"""Fixed-displacement pump set of one side, driven from the motor through a belt.

Leakage is laminar (Hagen-Poiseuille): q = k * dp / mu, independent of speed, with k fixed by
the nominal volumetric efficiency at the rating point. Torque is the ideal D*dp/2pi, divided by
the hydromechanical efficiency when the pump puts power into the fluid and multiplied by it
when the fluid drives the pump (motoring).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from ddh_vsensor.config import HydraulicsConfig, PumpConfig
from ddh_vsensor.physics.oil import Oil
from ddh_vsensor.physics.conversions import BAR_PA, CM3_M3, CST_M2S, RPM_REV_S


def rating_viscosity_pa_s(oil: Oil, hyd: HydraulicsConfig) -> float:
    """The dynamic viscosity of the pumps' rating point (its kinematic one, at the density of
    the temperature where the oil has it): where the nominal efficiencies were measured."""
    t_ref = oil.temperature_at_viscosity_c(hyd.nominal_viscosity_cst)
    return hyd.nominal_viscosity_cst * CST_M2S * float(oil.density_kg_m3(t_ref))


@dataclass(frozen=True)
class Pump:
    """``sign`` is +1 when positive motor speed pushes oil into the chamber, -1 when it draws."""

    sign: int
    displacement_m3_rev: float
    speed_ratio: float
    leak_coeff_m3: float
    eta_hm: float
    max_speed_rpm: float

    @classmethod
    def from_config(cls, cfg: PumpConfig, hyd: HydraulicsConfig, oil: Oil, sign: int) -> "Pump":
        disp = cfg.displacement_cm3_rev * CM3_M3
        mu_ref = rating_viscosity_pa_s(oil, hyd)
        q_nominal = disp * hyd.nominal_pump_speed_rpm * RPM_REV_S
        leak_nominal = (1.0 - cfg.volumetric_efficiency) * q_nominal
        k = leak_nominal * mu_ref / (hyd.nominal_pressure_bar * BAR_PA)
        return cls(sign=sign, displacement_m3_rev=disp, speed_ratio=cfg.speed_ratio,
                   leak_coeff_m3=k, eta_hm=cfg.hydromechanical_efficiency,
                   max_speed_rpm=cfg.max_speed_rpm)

    def scaled(self, leakage: float = 1.0, displacement: float = 1.0) -> "Pump":
        """The same pump with its leakage coefficient and displacement scaled (wear, effects).

        Leakage must stay positive: it is what sets the pressure of a chamber whose valves are
        closed, so a leak-free pump has no steady state unless flows match exactly.
        """
        if leakage <= 0.0 or displacement <= 0.0:
            raise ValueError(f"leakage ({leakage}) and displacement ({displacement}) factors "
                             "must be positive")
        return replace(self, leak_coeff_m3=self.leak_coeff_m3 * leakage,
                       displacement_m3_rev=self.displacement_m3_rev * displacement)

    def geometric_flow_m3_s(self, motor_speed_rpm: ArrayLike) -> np.ndarray:
        """Displacement flow into the chamber (negative: drawn from it)."""
        n_pump = self.speed_ratio * np.asarray(motor_speed_rpm, dtype=float)
        return self.sign * self.displacement_m3_rev * n_pump * RPM_REV_S

    def leak_conductance_m3_s_pa(self, mu_pa_s: ArrayLike) -> np.ndarray:
        """Leakage flow out of the chamber per pascal of chamber pressure over the reservoir."""
        return self.leak_coeff_m3 / np.asarray(mu_pa_s, dtype=float)

    def torque_gain_nm_per_pa(self, dp_sign: ArrayLike, motor_speed_rpm: ArrayLike) -> np.ndarray:
        """Motor torque per pascal, for a pressure of sign ``dp_sign`` (efficiency included).

        Standstill counts as pumping: the motor must hold the pressure through the pump's
        own friction.
        """
        ideal = self.sign * self.speed_ratio * self.displacement_m3_rev / (2.0 * math.pi)
        pumping = self.sign * np.asarray(dp_sign) * np.asarray(motor_speed_rpm) >= 0.0
        return np.where(pumping, ideal / self.eta_hm, ideal * self.eta_hm)

    def motor_torque_nm(self, dp_pa: ArrayLike, motor_speed_rpm: ArrayLike) -> np.ndarray:
        dp = np.asarray(dp_pa, dtype=float)
        return self.torque_gain_nm_per_pa(np.sign(dp), motor_speed_rpm) * dp
