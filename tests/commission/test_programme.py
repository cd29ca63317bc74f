"""The calibration programme: one run sweeps every unit through every switch both ways at two
speeds and holds it still three times, after the typical cycle at every speed level; joined
profiles start where the one before ended."""

from __future__ import annotations

import numpy as np
import pytest

from ddh_vsensor.commission.programme import HOLD_S, HOLD_SHARES, calibration_cycle
from ddh_vsensor.config import Config
from ddh_vsensor.sim.cycles import Profile, Trajectory, sequence, work_cycle


def test_one_run_crosses_every_switch_both_ways_and_holds(cfg: Config) -> None:
    profile = calibration_cycle(cfg)
    t = np.arange(0.0, profile.duration_s, 0.05)
    typical = sum(work_cycle(cfg, "work", s).duration_s for s in (1, 2, 3, 4))
    assert 300.0 < profile.duration_s < 600.0 and profile.duration_s > typical + 2 * len(
        HOLD_SHARES) * HOLD_S
    for unit in cfg.unit_names:
        x, v = profile.evaluate(unit, t)
        u = cfg.unit(unit)
        for name, at in u.references_mm.items():
            above = x > at
            ups = np.sum(~above[:-1] & above[1:])
            downs = np.sum(above[:-1] & ~above[1:])
            if 0.0 < at < u.stroke_mm:
                assert ups >= 2 and downs >= 2, (unit, name)
        # held still at each hold position for the hold's time
        for share in HOLD_SHARES:
            still = np.isclose(x, share * u.stroke_mm) & (v == 0.0)
            assert still.sum() * 0.05 >= HOLD_S - 0.1, (unit, share)
        assert x.min() >= 0.0 and x.max() <= u.stroke_mm


def test_a_joined_profile_must_start_where_the_last_ended() -> None:
    a = Profile("a", {"u": Trajectory(np.array([0.0, 1.0]), np.array([0.0, 5.0]))}, 1.0)
    b = Profile("b", {"u": Trajectory(np.array([0.0, 2.0]), np.array([5.0, 0.0]))}, 2.0)
    joined = sequence("ab", [a, b])
    assert joined.duration_s == 3.0
    x, _ = joined.evaluate("u", np.array([0.0, 1.0, 3.0]))
    assert x.tolist() == [0.0, 5.0, 0.0]
    with pytest.raises(ValueError, match="starts the u at 5 mm, not at 0"):
        sequence("bb", [b, b])
