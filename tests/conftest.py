"""Fixtures shared across the test tree: the reference config, its units and built tables."""

from __future__ import annotations

from pathlib import Path

import pytest

from ddh_vsensor.config import Config, load_config
from ddh_vsensor.physics.unit import DDHUnit
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
