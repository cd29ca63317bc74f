"""Regular grid axes and the interpolation arithmetic shared by every table lookup.

The scalar and vectorised paths use the same formulas so that the online estimator and the
offline one agree to rounding.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Axis:
    """``count`` evenly spaced points from ``start`` in steps of ``step``."""

    name: str
    unit: str
    start: float
    step: float
    count: int

    @classmethod
    def spanning(cls, name: str, unit: str, start: float, stop: float, step: float) -> "Axis":
        count = int(round((stop - start) / step)) + 1
        return cls(name, unit, float(start), float(step), count)

    @property
    def stop(self) -> float:
        return self.start + self.step * (self.count - 1)

    def values(self) -> np.ndarray:
        return self.start + self.step * np.arange(self.count)

    def locate(self, x: float) -> tuple[int, float, bool]:
        """Cell index, fraction within the cell, and whether ``x`` was clamped to the axis."""
        f = (x - self.start) / self.step
        clamped = False
        if f < 0.0 or f != f:
            f, clamped = 0.0, True
        elif f > self.count - 1:
            f, clamped = float(self.count - 1), True
        i = min(int(f), self.count - 2)
        return i, f - i, clamped

    def locate_many(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        f = (np.asarray(x, dtype=float) - self.start) / self.step
        clamped = ~((f >= 0.0) & (f <= self.count - 1))
        f = np.clip(np.nan_to_num(f, nan=0.0), 0.0, self.count - 1)
        i = np.minimum(np.floor(f).astype(np.intp), self.count - 2)
        return i, f - i, clamped

    def as_dict(self) -> dict[str, object]:
        return {"name": self.name, "unit": self.unit, "start": self.start, "step": self.step,
                "count": self.count}


def lerp(a: float, b: float, w: float) -> float:
    return a + (b - a) * w
