"""Holds: stretches where a cylinder is held under load, the second truth without a sensor.

While a load is held the rod stands still, yet the motor turns: it feeds what the pumps
leak. The model predicts that holding speed (``physics.steady.holding_speed``: pressure from
the measured torque, viscosity from the oil temperature); a pump leaking more than modelled
needs a faster one. In the estimate the same mismatch shows as creep: the model's velocity at
the measured speed and torque is not zero. The fit uses the creep (truth 0, weighted as the
rod is only held within what the loop holding it and the whole-rpm speed allow:
:data:`.references.HOLD_WEIGHT_S`); the store keeps both speeds for people to read.

A hold is found from the motor signals and the nominal estimate only: the estimated speed
below :data:`HOLD_MAX_MM_S` and the motor speed below :data:`HOLD_MAX_RPM`, for at least
:data:`MIN_HOLD_S` after :data:`SETTLE_S` of settling (the chamber pressures settle after a
move), with no reference edge inside.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ddh_vsensor.physics.steady import holding_speed, steady_state_at_torque
from ddh_vsensor.physics.unit import DDHUnit

HOLD_MAX_MM_S = 4.0          # |nominal estimated velocity| of a hold (creep of worn pumps fits)
HOLD_MAX_RPM = 800.0         # |motor speed| of a hold (leakage speeds are below ~300 rpm)
MIN_HOLD_S = 1.0
SETTLE_S = 0.5


@dataclass(frozen=True)
class Hold:
    start: int                   # first sample (after settling)
    stop: int                    # last sample (inclusive)
    duration_s: float
    speed_rpm: float             # mean measured motor speed
    torque_nm: float             # mean measured motor torque
    oil_temp_c: float
    model_speed_rpm: float       # the nominal model's holding speed for that torque


def find_holds(time_s: np.ndarray, speed_rpm: np.ndarray, velocity_mm_s: np.ndarray,
               edges: np.ndarray) -> list[tuple[int, int]]:
    """Sample ranges (first, last) of holds: slow estimate, slow motor, no edge inside."""
    still = (np.abs(velocity_mm_s) < HOLD_MAX_MM_S) & (np.abs(speed_rpm) < HOLD_MAX_RPM)
    still[np.asarray(edges, dtype=int)] = False
    padded = np.concatenate([[False], still, [False]])
    change = np.flatnonzero(padded[1:] != padded[:-1])
    out = []
    for a, b in zip(change[::2], change[1::2]):          # still over samples a .. b-1
        t0 = time_s[a] + SETTLE_S
        first = int(np.searchsorted(time_s, t0))
        if first < b and time_s[b - 1] - time_s[first] >= MIN_HOLD_S:
            out.append((first, int(b - 1)))
    return out


def model_holding_speed_rpm(unit: DDHUnit, speed_rpm: float, torque_nm: float,
                            oil_temp_c: float) -> float:
    """The model's holding speed for the load that the measured torque holds (exact)."""
    state = steady_state_at_torque(unit, speed_rpm, torque_nm, oil_temp_c)
    try:
        return float(holding_speed(unit, float(np.ravel(state.load_force_n)[0]),
                                   oil_temp_c).speed_rpm)
    except ValueError:                       # the load is beyond what the pumps can hold
        return float("nan")


def model_holding_speeds_rpm(unit: DDHUnit, torque_nm: np.ndarray,
                             oil_temp_c: np.ndarray) -> np.ndarray:
    """Many holds at once: the speed at which the model's steady state at the measured
    torque stands still (zero crossing nearest to 0 rpm on a 20 rpm grid, refined on a
    0.5 rpm grid inside its bracket). Agrees with :func:`model_holding_speed_rpm` to a
    fraction of an rpm (tests), ~100x cheaper."""
    torque_nm, oil_temp_c = np.atleast_1d(torque_nm), np.atleast_1d(oil_temp_c)
    out = np.full(len(torque_nm), np.nan)
    if not len(torque_nm):
        return out

    def velocity(n: np.ndarray) -> np.ndarray:
        return steady_state_at_torque(unit, n, torque_nm[:, None],
                                      oil_temp_c[:, None]).velocity_m_s

    coarse = np.arange(-HOLD_MAX_RPM, HOLD_MAX_RPM + 1.0, 20.0)
    v = velocity(np.broadcast_to(coarse, (len(torque_nm), len(coarse))))
    lo = np.full(len(torque_nm), np.nan)
    for i, row in enumerate(v):
        cross = np.flatnonzero(np.sign(row[:-1]) != np.sign(row[1:]))
        if len(cross):
            lo[i] = coarse[cross[np.argmin(np.abs(coarse[cross] + 10.0))]]
    ok = np.isfinite(lo)
    if not ok.any():
        return out
    fine = np.where(ok, lo, 0.0)[:, None] + np.arange(0.0, 20.5, 0.5)[None, :]
    v = velocity(fine)
    for i in np.flatnonzero(ok):
        row, n = v[i], fine[i]
        cross = np.flatnonzero(np.sign(row[:-1]) != np.sign(row[1:]))
        if len(cross):
            k = cross[0]
            out[i] = n[k] - row[k] * (n[k + 1] - n[k]) / (row[k + 1] - row[k])
    return out


def describe_holds(unit: DDHUnit | None, time_s: np.ndarray, speed_rpm: np.ndarray,
                   torque_nm: np.ndarray, oil_temp_c: np.ndarray,
                   ranges: list[tuple[int, int]]) -> list[Hold]:
    """Each hold's features: measured and modelled holding speed, torque, temperature.
    Without a ``unit`` the modelled speed is left NaN, for a caller that computes many
    runs' at once (:func:`model_holding_speeds_rpm` is row by row: the same numbers)."""
    means = np.array([[float(np.mean(x[a:b + 1])) for x in (speed_rpm, torque_nm, oil_temp_c)]
                      for a, b in ranges]).reshape(-1, 3)
    model = np.full(len(ranges), np.nan) if unit is None else \
        model_holding_speeds_rpm(unit, means[:, 1], means[:, 2])
    return [Hold(a, b, float(time_s[b] - time_s[a]), float(m[0]), float(m[1]), float(m[2]),
                 float(hs)) for (a, b), m, hs in zip(ranges, means, model)]
