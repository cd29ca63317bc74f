"""Table lookups for the estimator: a scalar call for the 1 kHz loop, a vectorised one for logs.

Both clamp inputs to the grid and report that they did, so a caller can flag it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .grid import Axis, lerp


@dataclass(frozen=True)
class FullTable:
    """Cylinder velocity (mm/s) over motor speed x motor torque x oil temperature.

    Speed-continuous: at the leakage-balance speed the table gives zero motion, which is what
    keeps a held load from creeping in the estimate.
    """

    speed: Axis
    torque: Axis
    temp: Axis
    velocity_mm_s: np.ndarray            # [temp, speed, torque]
    _item: Any = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Bound ``item`` of the flat table: the scalar path reads 8 Python floats per call.
        object.__setattr__(self, "_item", np.ascontiguousarray(self.velocity_mm_s).ravel().item)

    def velocity(self, speed_rpm: float, torque_nm: float,
                 oil_temp_c: float) -> tuple[float, bool]:
        """Velocity in mm/s at one operating point, and whether any input was clamped."""
        it, wt, ct = self.temp.locate(oil_temp_c)
        i, ws, cs = self.speed.locate(speed_rpm)
        j, wq, cq = self.torque.locate(torque_nm)
        nq = self.torque.count
        plane = self.speed.count * nq
        k0 = it * plane + i * nq + j
        k1 = k0 + plane
        f = self._item
        lo = lerp(lerp(f(k0), f(k0 + 1), wq), lerp(f(k0 + nq), f(k0 + nq + 1), wq), ws)
        hi = lerp(lerp(f(k1), f(k1 + 1), wq), lerp(f(k1 + nq), f(k1 + nq + 1), wq), ws)
        return lerp(lo, hi, wt), ct or cs or cq

    def velocity_many(self, speed_rpm: ArrayLike, torque_nm: ArrayLike,
                      oil_temp_c: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Vectorised :meth:`velocity`: arrays of velocity (mm/s) and of clamped flags."""
        it, wt, ct = self.temp.locate_many(oil_temp_c)
        i, ws, cs = self.speed.locate_many(speed_rpm)
        j, wq, cq = self.torque.locate_many(torque_nm)
        t = self.velocity_mm_s
        lo = lerp(lerp(t[it, i, j], t[it, i, j + 1], wq),
                  lerp(t[it, i + 1, j], t[it, i + 1, j + 1], wq), ws)
        hi = lerp(lerp(t[it + 1, i, j], t[it + 1, i, j + 1], wq),
                  lerp(t[it + 1, i + 1, j], t[it + 1, i + 1, j + 1], wq), ws)
        return lerp(lo, hi, wt), ct | cs | cq


@dataclass(frozen=True)
class PaperTable:
    """The paper's tables: mm per motor revolution over torque, per temperature, per speed range.

    Each of the three motor speed ranges (per direction) is represented by one steady state
    at the range's middle speed: exactly what cannot follow leakage at low speed.
    """

    torque: Axis
    temp: Axis
    range_edges_rpm: np.ndarray          # four edges of three |speed| ranges
    mm_per_rev: np.ndarray               # [direction (0: speed > 0, 1: < 0), range, temp, torque]

    @property
    def representative_rpm(self) -> np.ndarray:
        e = self.range_edges_rpm
        return 0.5 * (e[:-1] + e[1:])

    def _range(self, abs_speed: float) -> tuple[int, bool]:
        e = self.range_edges_rpm
        for r in range(3):
            if abs_speed < e[r + 1]:
                return r, False
        return 2, abs_speed > e[3]

    def movement_mm_per_rev(self, speed_rpm: float, torque_nm: float,
                            oil_temp_c: float) -> tuple[float, bool]:
        r, cr = self._range(abs(speed_rpm))
        d = 0 if speed_rpm >= 0.0 else 1
        it, wt, ct = self.temp.locate(oil_temp_c)
        j, wq, cq = self.torque.locate(torque_nm)
        t = self.mm_per_rev
        lo = lerp(float(t[d, r, it, j]), float(t[d, r, it, j + 1]), wq)
        hi = lerp(float(t[d, r, it + 1, j]), float(t[d, r, it + 1, j + 1]), wq)
        return lerp(lo, hi, wt), cr or ct or cq

    def movement_mm_per_rev_many(self, speed_rpm: ArrayLike, torque_nm: ArrayLike,
                                 oil_temp_c: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        n = np.asarray(speed_rpm, dtype=float)
        e = self.range_edges_rpm
        r = np.minimum(np.searchsorted(e[1:], np.abs(n), side="right"), 2)
        cr = np.abs(n) > e[3]
        d = (n < 0.0).astype(np.intp)
        it, wt, ct = self.temp.locate_many(oil_temp_c)
        j, wq, cq = self.torque.locate_many(torque_nm)
        t = self.mm_per_rev
        lo = lerp(t[d, r, it, j], t[d, r, it, j + 1], wq)
        hi = lerp(t[d, r, it + 1, j], t[d, r, it + 1, j + 1], wq)
        return lerp(lo, hi, wt), cr | ct | cq


@dataclass(frozen=True)
class UnitTables:
    """Both table kinds of one actuator, with the metadata they were built under."""

    actuator: str
    full: FullTable
    paper: PaperTable
    meta: dict[str, Any]
