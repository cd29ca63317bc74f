"""Day summaries in the fleet store: ingested beside the logs with the same guarantees
(idempotent, corrupt or foreign ones reported and skipped, nothing but rejections exits
non-zero), and where a machine-day has one its rows stand for the unit's day."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pyarrow.parquet as pq

from ddh_vsensor.cli.main import main
from ddh_vsensor.fleet.store import Store

from .conftest import DAYS, MACHINES, linked_copy


def test_summaries_stand_for_their_days_logs(fleet_logs, fleet_summaries, local_store,
                                              tmp_path, capsys):
    store = tmp_path / "store"
    # the tables the logs' fits are made on, as the fleet's store has them (built there)
    linked_copy(local_store[0] / "tables", store / "tables")
    assert main(["fleet", "ingest", str(fleet_logs), str(fleet_summaries), "--store",
                 str(store), "--workers", "1"]) == 0
    out = capsys.readouterr().out
    assert f"{2 * DAYS} summaries (machine-days)" in out and "machine-days/s" in out
    s = Store(store)
    kinds = s.query("SELECT kind, count(*) AS n FROM meta GROUP BY kind").to_pydict()
    assert dict(zip(kinds["kind"], kinds["n"])) == {"log": MACHINES * DAYS,
                                                    "summary": 2 * DAYS}
    context = s.query("SELECT * FROM context").to_pylist()
    assert len(context) == 2 * DAYS * 2 and all(c["work_s"] > 20 for c in context)
    report = tmp_path / "report.html"
    assert main(["fleet", "report", "--store", str(store), "--out", str(report),
                 "--workers", "1"]) == 0
    logs_only = {(r["machine"], r["actuator"], r["cause"], round(r["time_s"])): r
                 for r in pq.read_table(local_store[0] / "fits").to_pylist() if r["cause"]}
    compared = 0
    for machine in ("M00", "M01", "M02"):
        rows = [r for r in pq.read_table(s.fits_path(machine)).to_pylist() if r["cause"]]
        assert {r["source"] for r in rows} == ({"summary"} if machine != "M02" else {"log"})
        for r in rows:
            # a log's whole minute is its summary's one stretch: the same rows
            twin = logs_only[(machine, r["actuator"], r["cause"], round(r["time_s"]))]
            assert r["n_obs"] == twin["n_obs"]
            np.testing.assert_allclose(r["loss"], twin["loss"], rtol=1e-6, atol=1e-9)
            np.testing.assert_allclose(r["emax_mm"], twin["emax_mm"], rtol=1e-6, atol=1e-9)
            compared += 1
    assert compared
    data = json.loads(report.with_suffix(".json").read_text())
    assert data["summaries"] == 2 * DAYS and data["logs"] == MACHINES * DAYS


def test_a_days_newest_summary_counts_and_twice_changes_nothing(fleet_summaries, cfg,
                                                                tmp_path):
    from ddh_vsensor.fleet.analysis import analyse_machine
    files = tmp_path / "in"
    files.mkdir()
    day = sorted(fleet_summaries.glob("M00_*.summary.json"))[0]
    doc = json.loads(day.read_text())
    partial = {**doc, "last_s": doc["last_s"] - 10.0, "units": {
        a: {**u, "n_obs": u["n_obs"] - u["holds"], "holds": 0} for a, u in doc["units"].items()}}
    (files / "M00_partial.summary.json").write_text(json.dumps(partial))
    shutil.copy(day, files / day.name)
    store = tmp_path / "store"
    for _ in range(2):
        assert main(["fleet", "ingest", str(files), "--store", str(store), "--workers",
                     "1"]) == 0
    s = Store(store)
    assert len(s.machine_logs()["M00"]) == 2 and not s.rejected()
    before = {p.name: p.read_bytes() for p in (store / "logs").rglob("*.parquet")}
    analyse_machine((str(store), "M00", None))
    rows = pq.read_table(s.fits_path("M00")).to_pylist()
    assert {r["n_obs"] for r in rows} == {u["n_obs"] for u in doc["units"].values()}
    assert analyse_machine((str(store), "M00", None))["cached"]
    assert main(["fleet", "ingest", str(files), "--store", str(store), "--workers", "1"]) == 0
    assert {p.name: p.read_bytes() for p in (store / "logs").rglob("*.parquet")} == before


def test_corrupt_and_foreign_summaries_are_reported_and_skipped(fleet_summaries, tmp_path,
                                                                 capsys):
    files = tmp_path / "in"
    shutil.copytree(fleet_summaries, files)
    good = sorted(files.glob("*.summary.json"))
    doc = json.loads(good[0].read_text())
    (files / "M05_2026-01-05.summary.json").write_text(good[0].read_text()[:200])
    (files / "M06_2026-01-05.summary.json").write_text(json.dumps(
        {**doc, "physics_hash": "f" * 16}))
    (files / "M07_2026-01-05.summary.json").write_text(json.dumps({**doc, "version": 7}))
    store = tmp_path / "store"
    assert main(["fleet", "ingest", str(files), "--store", str(store), "--workers", "1"]) == 0
    out = capsys.readouterr().out
    rejected = [line for line in out.splitlines() if line.startswith("rejected:")]
    assert len(rejected) == 3
    assert any("not JSON" in r for r in rejected)
    assert any("another configuration" in r for r in rejected)
    assert any("version 7" in r for r in rejected)
    assert len(Store(store).rejected()) == 3
    # only rejected inputs: nothing ingested, exit 2 with one line
    only = tmp_path / "bad"
    only.mkdir()
    shutil.copy(files / "M05_2026-01-05.summary.json", only)
    assert main(["fleet", "ingest", str(only), "--store", str(tmp_path / "s2"),
                 "--workers", "1"]) == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert errors == ["ddh-vsensor fleet: error: nothing ingested: 1 file(s) given, every "
                      "one rejected"]
