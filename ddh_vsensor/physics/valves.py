"""The circuit's valves, each a piecewise-linear pressure-flow characteristic.

Pressures here are over the reservoir (Pa). Linear pieces let the steady state be solved
exactly by enumerating valve states instead of iterating.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from ddh_vsensor.config import HydraulicsConfig
from ddh_vsensor.physics.conversions import BAR_PA, LPM_M3S


@dataclass(frozen=True)
class ReliefValve:
    """Opens at its setting; pressure rises by a fraction of the setting over a given flow."""

    setting_pa: float
    gradient_m3_s_pa: float

    @classmethod
    def from_config(cls, setting_bar: float, hyd: HydraulicsConfig) -> "ReliefValve":
        setting = setting_bar * BAR_PA
        rise = hyd.relief_rise_fraction * setting
        return cls(setting, hyd.relief_rise_flow_lpm * LPM_M3S / rise)

    def flow_m3_s(self, dp_pa: ArrayLike) -> np.ndarray:
        """Flow out of the chamber to the reservoir."""
        return self.gradient_m3_s_pa * np.maximum(np.asarray(dp_pa) - self.setting_pa, 0.0)


@dataclass(frozen=True)
class AntiCavitationValve:
    """Check valve from the reservoir; cracks slightly below reservoir pressure."""

    cracking_pa: float          # negative: below reservoir pressure
    gradient_m3_s_pa: float

    @classmethod
    def from_config(cls, hyd: HydraulicsConfig) -> "AntiCavitationValve":
        return cls(-hyd.anticavitation_cracking_bar * BAR_PA,
                   hyd.anticavitation_gradient_lpm_per_bar * LPM_M3S / BAR_PA)

    def flow_m3_s(self, dp_pa: ArrayLike) -> np.ndarray:
        """Flow from the reservoir into the chamber."""
        return self.gradient_m3_s_pa * np.maximum(self.cracking_pa - np.asarray(dp_pa), 0.0)
