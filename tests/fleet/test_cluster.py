"""A real Dask scheduler and two workers on 127.0.0.1: ingestion and analysis give exactly
what the local cluster gives."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time

import pytest

from ddh_vsensor.cli.main import main
from ddh_vsensor.fleet.store import Store


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def scheduler():
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = dict(os.environ)
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler",
                               "--host", "127.0.0.1", "--port", str(port), "--no-dashboard",
                               "--idle-timeout", "600"], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                time.sleep(0.3)
        else:
            pytest.fail("the dask scheduler did not start within 60 s")
        for _ in range(2):
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads",
                 "1", "--nworkers", "1", "--host", "127.0.0.1", "--no-dashboard",
                 "--death-timeout", "30", "--lifetime", "900"], env=env,
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        from dask.distributed import Client
        with Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=120)
        yield address
    finally:
        # one at a time, the workers before their scheduler: stopped together with it, the
        # workers at times took 8 s to exit after a run (one after the other, under 1 s)
        for p in reversed(procs):
            p.terminate()
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def _tables(store) -> dict:
    s = Store(store)
    return {t: s.query(f"SELECT * EXCLUDE (path) FROM {t} ORDER BY ALL" if t == "meta" else
                       f"SELECT * FROM {t} ORDER BY ALL").to_pylist()
            for t in ("meta", "events", "holds")} | {
        "fits": s.query("SELECT machine, log_id, actuator, cause, loss, emax_mm FROM fits "
                        "ORDER BY machine, log_id, actuator, cause").to_pylist()}


def test_scheduler_and_two_workers_equal_the_local_run(scheduler, local_store, fleet_logs,
                                                       tmp_path):
    store, local_report = local_store
    remote = tmp_path / "store"
    assert main(["fleet", "ingest", str(fleet_logs), "--store", str(remote), "--scheduler",
                 scheduler]) == 0
    out = tmp_path / "report.html"
    assert main(["fleet", "report", "--store", str(remote), "--out", str(out), "--scheduler",
                 scheduler]) == 0
    assert _tables(remote) == _tables(store)
    report = json.loads(out.with_suffix(".json").read_text())
    strip = [{k: v for k, v in u.items() if k != "extension_file"} for u in report["units"]]
    assert strip == [{k: v for k, v in u.items() if k != "extension_file"}
                     for u in local_report["units"]]


def test_two_local_clusters_at_once_serve_on_their_own_ports_of_127_0_0_1():
    """Every port the embedded cluster listens on is 127.0.0.1's, the scheduler's HTTP
    server's included (8787 by default, which a second cluster would find taken)."""
    from ddh_vsensor.fleet.cluster import dask_client
    with dask_client(None, 1) as one, dask_client(None, 1) as two:
        infos = [c.scheduler_info() for c in (one, two)]
    ports = [info["services"]["dashboard"] for info in infos]
    assert 8787 not in ports and ports[0] != ports[1]
    for info in infos:
        assert info["address"].startswith("tcp://127.0.0.1:")
        assert all(w.startswith("tcp://127.0.0.1:") for w in info["workers"])
