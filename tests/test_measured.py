"""The measured run: its first samples taken as a run of their own."""

from __future__ import annotations

import numpy as np

from ddh_vsensor.measured import Run


def test_the_head_keeps_every_column_switch_and_edge_time_to_its_length() -> None:
    n = 10
    t = np.arange(n) * 0.01
    edge = np.full(n, np.nan)
    edge[6] = t[6] - 0.004
    run = Run(t, np.arange(n) * 10.0, np.ones(n), np.full(n, 30.0), np.linspace(0, 9, n),
              p_a_bar=np.full(n, 5.0), refs={"mid": (t > 0.05).astype(np.uint8)},
              ref_edge_s={"mid": edge}, source="test.csv")
    head = run.head(7)
    assert len(head.time_s) == 7 and head.source == "test.csv" and head.p_b_bar is None
    assert np.array_equal(head.p_a_bar, run.p_a_bar[:7])
    assert np.array_equal(head.refs["mid"], run.refs["mid"][:7])
    assert head.ref_edge_s["mid"][6] == edge[6]
    assert run.head(n).time_s.tolist() == run.time_s.tolist()
