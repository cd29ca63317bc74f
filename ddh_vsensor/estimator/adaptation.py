"""Learning at references: a travel gain per direction, by bounded recursive least squares.

Between two references the estimate's error is e = (g_up - g*_up) S_up + (g_down - g*_down)
S_down, with S the model's raw travel up and down. Each reference gives one such equation;
RLS with forgetting tracks g* (wear, oil, anything that scales travel per direction), and the
gains stay within 1 +- bound so a bad reference cannot wreck the model.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

_P0 = 1.0e-5          # initial covariance, 1/mm^2: a first 300 mm travel takes ~half its error


@dataclass
class DirectionalGain:
    bound: float
    forgetting: float
    min_travel_mm: float
    enabled: bool = True
    gain: np.ndarray = field(default_factory=lambda: np.ones(2))        # [up, down]
    cov: np.ndarray = field(default_factory=lambda: np.eye(2) * _P0)

    def scale(self, dx_raw: float) -> float:
        return dx_raw * (self.gain[0] if dx_raw > 0.0 else self.gain[1])

    def scale_many(self, dx_raw: np.ndarray) -> np.ndarray:
        return dx_raw * np.where(dx_raw > 0.0, self.gain[0], self.gain[1])

    def update(self, error_mm: float, travel_up_mm: float, travel_down_mm: float) -> bool:
        """One reference's equation; returns whether the gains were updated."""
        phi = np.array([travel_up_mm, travel_down_mm])
        if not self.enabled or abs(phi[0]) + abs(phi[1]) < self.min_travel_mm:
            return False
        p_phi = self.cov @ phi
        k = p_phi / (self.forgetting + phi @ p_phi)
        self.gain = np.clip(self.gain - k * error_mm, 1.0 - self.bound, 1.0 + self.bound)
        cov = (self.cov - np.outer(k, p_phi)) / self.forgetting
        cov = 0.5 * (cov + cov.T)
        trace = np.trace(cov)
        # Forgetting inflates the covariance along unexcited directions: cap it (no windup).
        self.cov = cov * (2 * _P0 / trace) if trace > 2 * _P0 else cov
        return True
