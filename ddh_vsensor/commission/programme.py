"""The calibration programme as simulator profiles.

:func:`calibration_profile`: one unit from its bottom end to its top end and back, a few
times, so that every switch is crossed each way the stroke allows (the ends' switches entered
and left); the other units hold. Run it at two speeds.

:func:`calibration_cycle`: one run of a commissioning day (``simulate --cycle calibration``),
about six minutes: the machine's typical cycle at each speed level (pressures and speeds as
work has them), then each unit in turn swept end to end slowly and fast (every switch, both
ways) and held still at a quarter, half and most of its stroke for
:data:`HOLD_S` (the leakage alone moves the oil at a hold). Run it empty and with the full
payload at two oil temperatures 30 K or more apart: the viscosity's change separates the
orifice share of the leakage from the laminar, the speeds its gain with speed.
"""

from __future__ import annotations

import numpy as np

from ddh_vsensor.config import Config
from ddh_vsensor.sim.cycles import (SPEED_LEVELS, WORK, Profile, Trajectory, move_time,
                                    sequence, work_cycle, work_unit)

SETTLE_S = 0.7          # rest at each end: the end switch is seen on, the move is over
HOLD_S = 20.0           # a hold: long against the position's resolution at a hold's creep
HOLD_SHARES = (0.25, 0.5, 0.85)     # where a unit holds, in shares of its stroke
SWEEP_SPEED_SHARES = (0.3, 1.0)     # of the unit's travel speed
CALIBRATION = "calibration"


def calibration_profile(cfg: Config, unit: str, move_s: float, repeats: int = 2) -> Profile:
    """End to end and back ``repeats`` times, each move ``move_s`` long; the ends half the
    configured window inside the stroke (within an end switch's window, clear of the stop)."""
    u = cfg.unit(cfg.require_unit(unit))
    lo, hi = 0.5 * u.reference_window_mm, u.stroke_mm - 0.5 * u.reference_window_mm
    t, x = [0.0, 0.5], [lo, lo]
    for _ in range(repeats):
        t0 = t[-1]
        t += [t0 + move_s, t0 + move_s + SETTLE_S, t0 + 2 * move_s + SETTLE_S,
              t0 + 2 * (move_s + SETTLE_S)]
        x += [hi, hi, lo, lo]
    moves = {a: Trajectory(np.array([0.0, t[-1]]), np.full(2, 0.4 * cfg.unit(a).stroke_mm))
             for a in cfg.unit_names}
    moves[unit] = Trajectory(np.array(t), np.array(x))
    return Profile(f"calibration of the {unit}", moves, t[-1])


def _start_mm(cfg: Config) -> dict[str, float]:
    """Where the typical cycle starts (mid-stroke where none is configured)."""
    if cfg.work_cycle is not None:
        return {a: float(tr.position_mm[0])
                for a, tr in work_cycle(cfg, WORK, 4).trajectories.items()}
    return {a: 0.5 * cfg.unit(a).stroke_mm for a in cfg.unit_names}


def _unit_moves(cfg: Config, unit: str, start_mm: float) -> tuple[list[float], list[float]]:
    """One unit's sweeps and holds from and back to ``start_mm``: knot times and positions."""
    u = cfg.unit(unit)
    lo, hi = 0.5 * u.reference_window_mm, u.stroke_mm - 0.5 * u.reference_window_mm
    top = work_unit(cfg, unit).travel_speed_mm_s
    t, x = [0.0], [start_mm]

    def move(to_mm: float, speed_mm_s: float, rest_s: float) -> None:
        t.append(t[-1] + move_time(to_mm - x[-1], speed_mm_s))
        x.append(to_mm)
        t.append(t[-1] + rest_s)
        x.append(to_mm)

    for share in SWEEP_SPEED_SHARES:
        move(lo, share * top, SETTLE_S)
        move(hi, share * top, SETTLE_S)
    for share in HOLD_SHARES:
        move(share * u.stroke_mm, 0.5 * top, HOLD_S)
    move(start_mm, 0.5 * top, SETTLE_S)
    return t, x


def calibration_cycle(cfg: Config) -> Profile:
    """One run of the calibration programme (see the module's docstring)."""
    start = _start_mm(cfg)
    parts = [work_cycle(cfg, WORK, s) for s in SPEED_LEVELS] if cfg.work_cycle else []
    for unit in cfg.unit_names:
        t, x = _unit_moves(cfg, unit, start[unit])
        moves = {a: Trajectory(np.array([0.0, t[-1]]), np.full(2, start[a]))
                 for a in cfg.unit_names}
        moves[unit] = Trajectory(np.array(t), np.array(x))
        parts.append(Profile(f"sweeps and holds of the {unit}", moves, t[-1]))
    return sequence(CALIBRATION, parts)
