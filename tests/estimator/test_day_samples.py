"""The day summary's samples as the daemon's loop keeps them: the loggers' period, and the
two samples around every Hall change with the change's own time."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ddh_vsensor.estimator.day_samples import SampleFeed, SummaryError, day_of, machine_name


def test_one_sample_per_period_and_both_around_a_hall_change() -> None:
    feed = SampleFeed(["bottom", "mid", "top"], sample_s=0.01)
    on, off = {"mid": True}, {"mid": False}
    t = np.round(np.arange(0.0, 0.1, 0.001), 6)
    for ti in t:
        refs = on if 0.0433 <= ti < 0.0777 else off
        change = 0.0432 if refs is on else 0.0776
        feed.add(float(ti), 100.0 * ti, 1.0, 30.0, refs, change, wall_s=1e9 + ti)
    block = feed.take()
    assert block is not None and feed.take() is None
    kept = block.t_s.tolist()
    # every 10 ms, and 43 and 44 ms (the sample before the change and the change's own)
    assert kept == pytest.approx([0.0, 0.01, 0.02, 0.03, 0.04, 0.043, 0.044, 0.054, 0.064,
                                  0.074, 0.077, 0.078, 0.088, 0.098])
    assert block.hall.tolist() == [0] * 6 + [2] * 5 + [0] * 3
    changes = {k: v for k, v in zip(kept, block.change_s.tolist()) if not math.isnan(v)}
    assert changes == {0.044: 0.0432, 0.078: 0.0776}
    assert block.wall_offset_s == pytest.approx(1e9)


def test_the_first_state_is_no_change_and_nothing_without_samples() -> None:
    feed = SampleFeed(["mid"])
    assert feed.take() is None
    feed.add_bits(5.0, 0.0, 0.0, 30.0, 1, 4.99)
    block = feed.take()
    assert block is not None and math.isnan(block.change_s[0]) and block.hall[0] == 1


def test_days_and_machine_names() -> None:
    assert day_of(1767571200.0 - 1.0) == "2026-01-04"       # 2026-01-05 00:00 UTC, less 1 s
    assert day_of(1767571200.0) == "2026-01-05"
    assert machine_name("loader-07.a_b") == "loader-07.a_b"
    for bad in ("", "-x", "a/b", "a b", "x" * 65):
        with pytest.raises(SummaryError):
            machine_name(bad)
