"""The calibration programme's moves as a simulator profile: one unit from its bottom end to
its top end and back, a few times, so that every switch is crossed each way the stroke allows
(the ends' switches entered and left); the other units hold. Run it at two speeds."""

from __future__ import annotations

import numpy as np

from ddh_vsensor.config import Config
from ddh_vsensor.sim.cycles import Profile, Trajectory

SETTLE_S = 0.7          # rest at each end: the end switch is seen on, the move is over


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
