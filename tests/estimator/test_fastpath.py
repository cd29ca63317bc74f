"""The per-frame fast paths compute what the general code computes, to the bit.

The scalar table lookup writes out :meth:`.Axis.locate` and :func:`.lerp`; the online step
writes out the clip, the gain, the flags and the uncertainty. These tests feed random inputs
(off the grid, NaN, gaps, repeated times, chattering switches) and compare exactly."""

from __future__ import annotations

import copy
import pickle

import numpy as np
import pytest

from ddh_vsensor.estimator.estimator import Estimator
from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.estimator.state import EstimatorState


@pytest.mark.parametrize("unit", ["boom", "bucket"])
def test_scalar_lookup_equals_the_vectorised_one_to_the_bit(unit, unit_tables):
    full = unit_tables[unit].full
    rng = np.random.default_rng(17)
    count = 20000
    n = rng.uniform(full.speed.start - 500, full.speed.stop + 500, count)
    q = rng.uniform(full.torque.start - 5, full.torque.stop + 5, count)
    t = rng.uniform(full.temp.start - 10, full.temp.stop + 10, count)
    n[:50], q[50:100], t[100:150] = np.nan, np.nan, np.nan
    n[150:160] = full.speed.values()[rng.integers(0, full.speed.count, 10)]   # on nodes
    t[160:170] = full.temp.stop                                                # last node
    v, clamped = full.velocity_many(n, q, t)
    scalar = [full.velocity(a, b, c) for a, b, c in zip(n.tolist(), q.tolist(), t.tolist())]
    assert [s[0] for s in scalar] == v.tolist()
    assert [s[1] for s in scalar] == clamped.tolist()
    assert clamped.any() and (~clamped).any()


def test_tables_still_pickle_and_copy(unit_tables):
    """Worker processes receive tables pickled: the fast path's view is rebuilt, not sent."""
    tables = unit_tables["boom"]
    for back in (pickle.loads(pickle.dumps(tables)), copy.deepcopy(tables)):
        assert np.array_equal(back.full.velocity_mm_s, tables.full.velocity_mm_s)
        assert back.full.velocity(1234.5, 12.3, 31.0) == tables.full.velocity(1234.5, 12.3, 31.0)


def _inputs(seed: int, count: int) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.0005, 0.0015, count))
    t[count // 2:] += 0.3                                  # a gap: stale, not integrated
    t[count // 3] = t[count // 3 - 1]                      # a repeated time
    speed = 4000 * np.sin(2 * np.pi * t / 5) + rng.normal(0, 30, count)
    speed[100:150] = rng.uniform(-9000, 9000, 50)          # off the table
    torque = 20 + 15 * np.sin(2 * np.pi * t / 3) + rng.normal(0, 2, count)
    temp = 27 + 10 * np.sin(t)
    phase = np.sin(2 * np.pi * t / 5)
    mid = (phase > 0.3) ^ (rng.random(count) < 0.01)       # chattering near the edges
    bottom = phase < -0.95
    return t, speed, torque, temp, mid, bottom


@pytest.mark.parametrize("mode", ["full", "paper", "dynamic"])
@pytest.mark.parametrize("cold", [False, True])
def test_online_step_equals_the_estimators_own_methods(cfg, unit_tables, mode, cold):
    """After every step, the written-out flags and uncertainty equal ``state_flags()`` and
    ``uncertainty_mm``; references are accepted, gains adapt, limits and clamps are hit."""
    est = Estimator(cfg, "bucket", unit_tables["bucket"], mode=mode, initial_position_mm=300.0)
    if cold:
        est.restore(EstimatorState("bucket", cfg.physics_hash(), 0.0, 500.0))
    t, speed, torque, temp, mid, bottom = _inputs(5, 12000)
    seen = 0
    for k in range(len(t)):
        refs = {"mid": bool(mid[k]), "bottom": int(bottom[k])} if k % 3 else None
        s = est.step(float(t[k]), float(speed[k]), float(torque[k]), float(temp[k]), refs)
        assert s.position_mm == est.position_mm
        assert s.uncertainty_mm == est.uncertainty_mm
        clamped = s.flags & Flags.TABLE_CLAMPED
        stale = s.flags & Flags.STALE_INPUT
        assert s.flags & ~(Flags.TABLE_CLAMPED | Flags.STALE_INPUT) == est.state_flags()
        seen |= s.flags
        if stale:
            assert k == len(t) // 2
        if clamped:
            assert mode != "dynamic"
    assert est.travel_mm >= 0.0
    assert seen & Flags.AT_SOFT_LIMIT and seen & Flags.STALE_INPUT
    assert mode == "dynamic" or seen & Flags.TABLE_CLAMPED
    assert est.gain.active or cold
