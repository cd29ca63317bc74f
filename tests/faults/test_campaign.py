"""The randomised fault campaign of ``bench/faults.py``, short and in process: the service's
invariant (a published position further from the truth than its uncertainty carries a flag
saying why) over the first seeded episodes of the paper cycle, in virtual time. The bench
runs 1000 faults per seed; these are the first 100 of two seeds where a rule once broke it."""

from __future__ import annotations

import importlib.util
import logging

import pytest

from .conftest import REPO


def _campaign():
    spec = importlib.util.spec_from_file_location("faults_bench", REPO / "bench" / "faults.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.campaign


@pytest.mark.parametrize("seed", [1, 2])
def test_no_unflagged_error_beyond_the_uncertainty_under_random_faults(cfg, unit_tables,
                                                                       paper, seed) -> None:
    """Seed 1's fourth episode has the frame clocks stepping back 0.8 s while the I/O module,
    sending on change of state, had not yet sent: a Hall state of before the step came back
    as an edge (the boom published 22.7 mm off under a 4.1 mm bound, unflagged)."""
    truth = {a: (paper.truth_t[a], paper.truth_mm[a]) for a in paper.truth_t}
    logging.disable(logging.WARNING)
    try:
        result = _campaign()(cfg, unit_tables, {"frames": paper.frames, "truth": truth},
                             n_faults=100, seed=seed)
    finally:
        logging.disable(logging.NOTSET)
    assert result["checks_unflagged"] > 0.3 * result["checks"]
    assert result["violations"] == 0, result["violation_examples"]
