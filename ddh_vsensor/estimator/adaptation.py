"""Learning at references: a travel gain per direction, by normalised LMS.

Between two references the estimate's error is e = (g_up - g*_up) S_up + (g_down - g*_down)
S_down, with S the model's raw travel up and down. Each reference gives one such equation; a
normalised LMS step moves the gains along that equation's regressor only. Between two
crossings of one switch S_up ~ -S_down, so only the difference of the gains is observable; an
RLS update let the unobservable common mode wander (measured: both gains drifted 0.7 % over
50 cycles and the bucket's error grew); NLMS leaves it alone. The gains stay within 1 +- bound
so a bad reference cannot wreck the model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class DirectionalGain:
    bound: float
    step: float                 # NLMS step size in (0, 1]: share of the error removed
    min_travel_mm: float
    enabled: bool = True

    def __post_init__(self) -> None:
        self.gain = np.ones(2)

    @property
    def gain(self) -> np.ndarray:
        """[up, down]; kept as two Python floats, which the per-sample path reads."""
        return np.array([self._up, self._down])

    @gain.setter
    def gain(self, value: np.ndarray) -> None:
        self._up, self._down = float(value[0]), float(value[1])

    @property
    def active(self) -> bool:
        """Learning is on and has moved the gains off 1."""
        return self.enabled and (self._up != 1.0 or self._down != 1.0)

    def scale(self, dx_raw: float) -> float:
        return dx_raw * (self._up if dx_raw > 0.0 else self._down)

    def scale_many(self, dx_raw: np.ndarray) -> np.ndarray:
        return dx_raw * np.where(dx_raw > 0.0, self._up, self._down)

    def update(self, error_mm: float, travel_up_mm: float, travel_down_mm: float) -> bool:
        """One reference's equation; returns whether the gains were updated."""
        phi = np.array([travel_up_mm, travel_down_mm])
        if not self.enabled or abs(phi[0]) + abs(phi[1]) < self.min_travel_mm:
            return False
        self.gain = np.clip(self.gain - self.step * error_mm * phi / (phi @ phi),
                            1.0 - self.bound, 1.0 + self.bound)
        return True
