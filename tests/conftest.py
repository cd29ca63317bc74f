"""Fixtures shared across the test tree: the reference config, its units and built tables."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ddh_vsensor.config import Config, load_config
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.sim.cycles import Profile, Trajectory
from ddh_vsensor.tables.build import build_unit_tables
from ddh_vsensor.tables.lookup import UnitTables
from ddh_vsensor.tables.store import save_unit_tables

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def cfg() -> Config:
    return load_config(REPO / "config" / "loader.yaml")


@pytest.fixture(scope="session")
def boom(cfg: Config) -> DDHUnit:
    return DDHUnit.from_config(cfg, "boom")


@pytest.fixture(scope="session")
def bucket(cfg: Config) -> DDHUnit:
    return DDHUnit.from_config(cfg, "bucket")


@pytest.fixture(scope="session")
def unit_tables(cfg: Config) -> dict[str, UnitTables]:
    return {a: build_unit_tables(cfg, a) for a in ("boom", "bucket")}


@pytest.fixture(scope="session")
def tables_dir(tmp_path_factory: pytest.TempPathFactory,
               unit_tables: dict[str, UnitTables]) -> Path:
    out = tmp_path_factory.mktemp("tables")
    for t in unit_tables.values():
        save_unit_tables(out, t)
    return out


@pytest.fixture(scope="session")
def short_profile() -> Profile:
    """7 s: the boom lifts through its middle switch and back down, the bucket retracts and
    extends through its middle switch (smooth moves at about speed 4), then both hold."""
    boom = Trajectory(np.array([0.0, 0.5, 3.0, 3.5, 6.0, 7.0]),
                      np.array([1.5, 1.5, 170.0, 170.0, 1.5, 1.5]))
    bucket = Trajectory(np.array([0.0, 0.3, 2.4, 2.8, 4.9, 7.0]),
                        np.array([600.0, 600.0, 300.0, 300.0, 600.0, 600.0]))
    return Profile("test short", {"boom": boom, "bucket": bucket}, 7.0)
