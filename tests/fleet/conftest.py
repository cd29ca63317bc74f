"""A small simulated fleet, ingested and reported on a local Dask cluster (session-wide:
the fleet tests share it)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from ddh_vsensor.cli.main import main

MACHINES, DAYS, LOG_S, SEED = 3, 3, 30, 11


@pytest.fixture(scope="session")
def fleet_logs(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fleet") / "logs"
    assert main(["simulate", "fleet", "--machines", str(MACHINES), "--days", str(DAYS),
                 "--log-s", str(LOG_S), "--seed", str(SEED), "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="session")
def local_store(fleet_logs, tmp_path_factory) -> tuple[Path, dict]:
    """The fleet ingested and reported on the default LocalCluster."""
    root = tmp_path_factory.mktemp("local")
    store = root / "store"
    assert main(["fleet", "ingest", str(fleet_logs), "--store", str(store)]) == 0
    out = root / "report.html"
    assert main(["fleet", "report", "--store", str(store), "--out", str(out)]) == 0
    return store, json.loads(out.with_suffix(".json").read_text())
