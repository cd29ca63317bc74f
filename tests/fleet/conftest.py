"""A small simulated fleet (its logs only), ingested and reported on a local Dask cluster
(session-wide: the fleet tests share it), and day summaries of its logs."""

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
                 "--log-s", str(LOG_S), "--seed", str(SEED), "--out", str(out),
                 "--work-s", "0"]) == 0
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


@pytest.fixture(scope="session")
def fleet_summaries(fleet_logs, cfg, tmp_path_factory) -> Path:
    """What the daemons of machines M00 and M01 would have written for the logs' days, had
    the logged minutes been all their work (each log through the daemon's summary code)."""
    from ddh_vsensor.diagnosis.day_summary import summarise_runs
    from ddh_vsensor.fleet.ingest import read_log
    out = tmp_path_factory.mktemp("summaries")
    for log in sorted(fleet_logs.glob("M0[01]_*.blf")):
        runs, _, _ = read_log(str(log), cfg)
        summarise_runs(cfg, log.name.split("_")[0], [runs], out)
    return out
