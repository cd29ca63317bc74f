"""Table lookups for the estimator: a scalar call for the 1 kHz loop, a vectorised one for logs.

Both clamp inputs to the grid and report that they did, so a caller can flag it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ddh_vsensor.tables.grid import Axis, lerp


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
    _fast: tuple = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # The scalar path runs per Sevcon frame: each axis as plain numbers and the table as a
        # flat memoryview (indexing it gives a Python float, no copy of the table, no numpy
        # call), so one lookup is arithmetic on locals.
        axes = tuple((a.start, a.step, float(a.count - 1), a.count - 2)
                     for a in (self.temp, self.speed, self.torque))
        flat = memoryview(np.ascontiguousarray(self.velocity_mm_s, dtype=float).ravel())
        nq = self.torque.count
        object.__setattr__(self, "_fast", (*axes, nq, self.speed.count * nq, flat))

    def __getstate__(self) -> dict[str, Any]:
        """Pickled (worker processes, deep copies) without the memoryview: rebuilt on load."""
        return {k: v for k, v in self.__dict__.items() if k != "_fast"}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self.__post_init__()

    def velocity(self, speed_rpm: float, torque_nm: float,
                 oil_temp_c: float) -> tuple[float, bool]:
        """Velocity in mm/s at one operating point, and whether any input was clamped.

        :meth:`.Axis.locate` and :func:`.lerp` written out (same operations in the same
        order, so equal to :meth:`velocity_many` to the bit)."""
        (t0, th, tn, tc), (s0, sh, sn, sc), (q0, qh, qn, qc), nq, plane, f = self._fast
        clamped = False
        x = (oil_temp_c - t0) / th
        if x < 0.0 or x != x:
            x, clamped = 0.0, True
        elif x > tn:
            x, clamped = tn, True
        it = int(x)
        if it > tc:
            it = tc
        wt = x - it
        x = (speed_rpm - s0) / sh
        if x < 0.0 or x != x:
            x, clamped = 0.0, True
        elif x > sn:
            x, clamped = sn, True
        i = int(x)
        if i > sc:
            i = sc
        ws = x - i
        x = (torque_nm - q0) / qh
        if x < 0.0 or x != x:
            x, clamped = 0.0, True
        elif x > qn:
            x, clamped = qn, True
        j = int(x)
        if j > qc:
            j = qc
        wq = x - j
        k = it * plane + i * nq + j
        a, b = f[k], f[k + 1]
        c = a + (b - a) * wq
        a, b = f[k + nq], f[k + nq + 1]
        d = a + (b - a) * wq
        lo = c + (d - c) * ws
        k += plane
        a, b = f[k], f[k + 1]
        c = a + (b - a) * wq
        a, b = f[k + nq], f[k + nq + 1]
        d = a + (b - a) * wq
        hi = c + (d - c) * ws
        return lo + (hi - lo) * wt, clamped

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
