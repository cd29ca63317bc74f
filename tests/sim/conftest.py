"""Shared simulator fixtures: a short two-unit profile and the speed-4 paper run via the CLI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ddh_vsensor.cli.main import main
from ddh_vsensor.sim.cycles import Profile, Trajectory


@pytest.fixture(scope="session")
def short_profile() -> Profile:
    """7 s: the boom lifts through its middle switch and back down, the bucket retracts and
    extends through its middle switch (smooth moves at about speed 4), then both hold."""
    boom = Trajectory(np.array([0.0, 0.5, 3.0, 3.5, 6.0, 7.0]),
                      np.array([1.5, 1.5, 170.0, 170.0, 1.5, 1.5]))
    bucket = Trajectory(np.array([0.0, 0.3, 2.4, 2.8, 4.9, 7.0]),
                        np.array([600.0, 600.0, 300.0, 300.0, 600.0, 600.0]))
    return Profile("test short", {"boom": boom, "bucket": bucket}, 7.0)


@pytest.fixture(scope="session")
def paper_run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The issue's 'done when' command: speed 4, empty, 27 degC."""
    out = tmp_path_factory.mktemp("paper_run")
    assert main(["simulate", "--cycle", "paper", "--speed", "4", "--payload-kg", "0",
                 "--oil-temp-c", "27", "--out", str(out)]) == 0
    return out
