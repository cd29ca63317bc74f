"""The oil temperature sensor in the tank trails the oil the pumps work.

The sensor and the tank's oil around it warm as a first-order lag of the oil returning from
the pumps: tau dT_tank/dt = T_pump - T_tank, so the pumps' oil is the reading plus tau times
its rate. The rate is taken as the least-squares slope of the reading over a window centred
on each sample (a reading quantised to 0.1 K over a minute gives a rate to ~0.003 K/s); with
tau = 0 the reading is returned as it is.
"""

from __future__ import annotations

from collections import deque

import numpy as np

SLOPE_WINDOW_S = 60.0       # the reading's rate from this much of it around each sample


def reading_rate_c_per_s(time_s: np.ndarray, temp_c: np.ndarray,
                         window_s: float = SLOPE_WINDOW_S) -> np.ndarray:
    """Least-squares slope of ``temp_c`` over ``window_s`` centred on each sample (shorter at
    the run's ends; 0 where the window holds one sample)."""
    t = np.asarray(time_s, dtype=float)
    y = np.asarray(temp_c, dtype=float)
    c = np.concatenate(([0.0], np.cumsum(np.ones_like(t))))
    st = np.concatenate(([0.0], np.cumsum(t)))
    sy = np.concatenate(([0.0], np.cumsum(y)))
    stt = np.concatenate(([0.0], np.cumsum(t * t)))
    sty = np.concatenate(([0.0], np.cumsum(t * y)))
    lo = np.searchsorted(t, t - 0.5 * window_s, side="left")
    hi = np.searchsorted(t, t + 0.5 * window_s, side="right")
    n = c[hi] - c[lo]
    s_t, s_y = st[hi] - st[lo], sy[hi] - sy[lo]
    s_tt, s_ty = stt[hi] - stt[lo], sty[hi] - sty[lo]
    den = n * s_tt - s_t * s_t
    with np.errstate(invalid="ignore", divide="ignore"):
        slope = (n * s_ty - s_t * s_y) / den
    return np.where((n > 1) & (den > 0.0), slope, 0.0)


def pump_oil_temperature_c(time_s: np.ndarray, tank_c: np.ndarray, lag_s: float) -> np.ndarray:
    """The pumps' oil from the tank sensor's reading and the sensor's thermal lag (s)."""
    tank = np.asarray(tank_c, dtype=float)
    if lag_s == 0.0 or len(tank) < 2:
        return tank
    return tank + lag_s * reading_rate_c_per_s(time_s, tank)


class TrailingRate:
    """Online: the least-squares slope of the reading over the last ``window_s`` (the offline
    slope is centred on its sample, which a stream cannot be: this one is half a window late,
    seconds on a warm-up whose rate changes over minutes). The sums are over times relative to
    an origin moved to the window's start every two windows (recomputed then), so that they
    keep their precision over days."""

    def __init__(self, window_s: float = SLOPE_WINDOW_S) -> None:
        self.window_s = window_s
        self._origin_s: float | None = None
        self._samples: deque[tuple[float, float]] = deque()
        self._sums = [0.0, 0.0, 0.0, 0.0, 0.0]          # n, t, y, t^2, t y

    def update(self, time_s: float, temp_c: float) -> float:
        """Take one reading; the slope (K/s) over the window now (0 with one sample)."""
        self._samples.append((time_s, temp_c))
        while self._samples[0][0] < time_s - self.window_s:
            self._add(*self._samples.popleft(), -1.0)
        if self._origin_s is None or time_s - self._origin_s > 2.0 * self.window_s:
            self._origin_s = self._samples[0][0]
            self._sums = [0.0, 0.0, 0.0, 0.0, 0.0]
            for t, y in self._samples:
                self._add(t, y, 1.0)
        else:
            self._add(time_s, temp_c, 1.0)
        n, st, sy, stt, sty = self._sums
        den = n * stt - st * st
        return (n * sty - st * sy) / den if n > 1 and den > 0.0 else 0.0

    def _add(self, time_s: float, y: float, sign: float) -> None:
        t = time_s - self._origin_s if self._origin_s is not None else 0.0
        for i, v in enumerate((1.0, t, y, t * t, t * y)):
            self._sums[i] += sign * v
