"""The pumps' oil from the tank sensor's lagging reading: a warm-up the sensor trails by its
lag comes back, quantised as a real reading is, to a few tenths of a kelvin."""

from __future__ import annotations

import numpy as np
import pytest

from ddh_vsensor.physics.tank_sensor import (TrailingRate, pump_oil_temperature_c,
                                             reading_rate_c_per_s)
from ddh_vsensor.sim.sensors import quantise, tank_temperature

LAG_S = 180.0


def _warm_up() -> tuple[np.ndarray, np.ndarray]:
    """Oil warming at 0.6 K/min for 10 min, then at 0.2 K/min: 100 Hz."""
    t = np.arange(0.0, 1200.0, 0.01)
    oil = 30.0 + np.where(t < 600.0, 0.01 * t, 6.0 + 0.01 / 3.0 * (t - 600.0))
    return t, oil


def test_no_lag_is_the_reading() -> None:
    t, oil = _warm_up()
    assert np.array_equal(pump_oil_temperature_c(t, oil, 0.0), oil)


def test_a_lagging_reading_gives_the_pumps_oil_back() -> None:
    t, oil = _warm_up()
    reading = quantise(tank_temperature(t, oil, LAG_S), 0.1)
    assert np.max(np.abs(reading - oil)) > 1.7          # the sensor trails by lag x rate
    pumps = pump_oil_temperature_c(t, reading, LAG_S)
    settled = (t > 30.0) & (t < t[-1] - 30.0)            # a whole slope window each side
    # within the quantisation and the slope's noise, through the change of rate at 10 min
    # too (the inverse of a first-order lag is exact; measured 0.12 K, the reading 1.85 K off)
    assert np.max(np.abs(pumps[settled] - oil[settled])) < 0.25


def test_the_rate_of_a_line_is_its_slope() -> None:
    t = np.arange(0.0, 100.0, 0.1)
    assert reading_rate_c_per_s(t, 3.0 + 0.02 * t) == pytest.approx(np.full_like(t, 0.02))
    assert reading_rate_c_per_s(np.array([0.0]), np.array([1.0])).tolist() == [0.0]


def test_the_online_rate_is_the_last_minutes_slope_over_hours() -> None:
    """The stream's rate is the least-squares slope of the last minute (an hour of samples at
    epoch times: the sums keep their precision)."""
    t = 1.7e9 + np.arange(0.0, 3600.0, 0.01)
    y = quantise(20.0 + 0.01 * (t - t[0]) + 0.5 * np.sin((t - t[0]) / 50.0), 0.1)
    rate = TrailingRate()
    online = np.array([rate.update(a, b) for a, b in zip(t, y)])
    for i in (6000, 200000, len(t) - 1):
        last = (t >= t[i] - 60.0) & (t <= t[i])
        assert online[i] == pytest.approx(np.polyfit(t[last] - t[i], y[last], 1)[0],
                                          rel=1e-8, abs=1e-12)
