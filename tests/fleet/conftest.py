"""A small simulated fleet (its logs only), ingested and reported on a local Dask cluster
(session-wide: the fleet tests share it), and day summaries of its logs.

The fleet's logs and its store are made once per run of the suite: under pytest-xdist in a
directory every worker of the run shares (``build_once``, tests/conftest.py); each worker's
tests get their own copy of the store (hard links: the store writes each file anew and
renames it into place, so nothing a test does to its copy reaches another's).
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from ddh_vsensor.cli.main import main

MACHINES, DAYS, LOG_S, SEED = 3, 3, 30, 11


def linked_copy(source: Path, target: Path) -> Path:
    """``source`` copied to ``target`` as hard links (the store replaces files, never
    writes into them)."""
    shutil.copytree(source, target, copy_function=os.link)
    return target


@pytest.fixture(scope="session")
def fleet_logs(run_dir, build_once) -> Path:
    out = run_dir / "fleet" / "logs"
    with build_once(out) as build:
        if build:
            assert main(["simulate", "fleet", "--machines", str(MACHINES), "--days",
                         str(DAYS), "--log-s", str(LOG_S), "--seed", str(SEED), "--out",
                         str(out), "--work-s", "0"]) == 0
    return out


@pytest.fixture(scope="session")
def local_store(fleet_logs, build_once, tmp_path_factory) -> tuple[Path, dict]:
    """The fleet ingested and reported on the default LocalCluster (this worker's copy)."""
    shared = fleet_logs.parent / "local"
    with build_once(shared) as build:
        if build:
            assert main(["fleet", "ingest", str(fleet_logs), "--store",
                         str(shared / "store")]) == 0
            assert main(["fleet", "report", "--store", str(shared / "store"), "--out",
                         str(shared / "report.html")]) == 0
    root = tmp_path_factory.mktemp("local")
    for name in ("report.html", "report.json"):
        shutil.copy(shared / name, root / name)
    store = linked_copy(shared / "store", root / "store")
    return store, json.loads((root / "report.json").read_text())


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
