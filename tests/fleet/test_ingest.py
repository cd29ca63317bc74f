"""Ingestion into the store: what a log gives, idempotence, resuming after a crash, corrupt
logs reported and skipped."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from ddh_vsensor.io.blf import frames_to_runs, read_frames
from ddh_vsensor.io.log import read_can_log
from ddh_vsensor.cli.main import main
from ddh_vsensor.fleet.ingest import IngestJob, ingest_one
from ddh_vsensor.fleet.store import Store

from .conftest import DAYS, MACHINES


def files(store: Path) -> dict[str, bytes]:
    return {str(p.relative_to(store)): p.read_bytes()
            for p in sorted((store / "logs").rglob("*.parquet"))}


def test_a_log_gives_machine_time_hours_references_and_holds(local_store, fleet_logs):
    store, _ = local_store
    s = Store(store)
    meta = s.query("SELECT * FROM meta ORDER BY machine, start_time_s").to_pylist()
    assert len(meta) == MACHINES * DAYS
    assert {m["machine"] for m in meta} == {f"M{i:02d}" for i in range(MACHINES)}
    for m in meta:
        name = m["file"]
        assert name.startswith(m["machine"] + "_")
        assert m["operating_hours"] == pytest.approx(float(name.split("_")[2][:-5]))
        assert m["events"] > 0 and m["holds"] > 0 and m["frames"] > 0
    counted = s.query("SELECT count(*) AS n FROM events").to_pylist()[0]["n"]
    assert counted == sum(m["events"] for m in meta)
    holds = s.query("SELECT speed_rpm, model_speed_rpm FROM holds").to_pylist()
    assert all(np.isfinite(h["model_speed_rpm"]) for h in holds)


def test_twice_changes_nothing_and_a_crash_resumes(local_store, fleet_logs, tmp_path):
    store, _ = local_store
    before = files(store)
    assert main(["fleet", "ingest", str(fleet_logs), "--store", str(store), "--workers",
                 "1"]) == 0
    assert files(store) == before
    # a crash after half the logs, with one log half written: the rerun completes the store
    other = tmp_path / "store"
    logs = sorted(fleet_logs.glob("*.blf"))
    s = Store(other, create=True)
    for log in logs[: len(logs) // 2]:
        assert ingest_one(IngestJob(str(log), str(other)))["status"] == "ingested"
    partial = other / "tmp" / "deadbeef.123"
    partial.mkdir(parents=True)
    (partial / "samples.parquet").write_bytes(b"PAR1 half")
    assert main(["fleet", "ingest", str(fleet_logs), "--store", str(other), "--workers",
                 "1"]) == 0
    assert not any((other / "tmp").iterdir())
    assert files(other) == before
    assert s.rejected() == []


def test_corrupt_logs_are_reported_and_skipped(fleet_logs, tmp_path, capsys):
    logs = tmp_path / "logs"
    shutil.copytree(fleet_logs, logs)
    good = sorted(logs.glob("*.blf"))
    data = good[0].read_bytes()
    (logs / "M07_2026-02-01_0100.0h.blf").write_bytes(data[: len(data) // 3])   # cut off
    (logs / "M08_2026-02-01_0100.0h.blf").write_bytes(b"not a log at all" * 10)
    (logs / "nomachine.blf").write_bytes(data[:-1] + b"x")
    store = tmp_path / "store"
    assert main(["fleet", "ingest", str(logs), "--store", str(store), "--workers", "1"]) == 0
    out = capsys.readouterr().out
    assert out.count("rejected:") == 3
    s = Store(store)
    assert len(s.rejected()) == 3
    assert len(s.machine_logs()) == MACHINES


def test_fast_reader_equals_python_can(fleet_logs, cfg):
    import can
    path = sorted(fleet_logs.glob("*.blf"))[0]
    frames = read_frames(path)
    with can.BLFReader(path) as reader:
        msgs = list(reader)
    assert len(frames) == len(msgs)
    assert frames.timestamp_s.tolist() == [m.timestamp for m in msgs]
    assert frames.arbitration_id.tolist() == [m.arbitration_id for m in msgs]
    assert all(bytes(frames.data[i, :frames.dlc[i]]) == bytes(m.data)
               for i, m in enumerate(msgs))
    runs = frames_to_runs(frames, cfg, str(path))
    for actuator, run in runs.items():
        ref = read_can_log(path, actuator, cfg)
        for column in ("time_s", "speed_rpm", "torque_nm", "oil_temp_c"):
            assert np.array_equal(getattr(run, column), getattr(ref, column)), column
        assert np.all(np.isnan(run.position_mm)) and np.all(np.isnan(ref.position_mm))
        assert all(np.array_equal(run.refs[k], ref.refs[k]) for k in ref.refs)


def test_bad_arguments_are_one_line_and_exit_2(tmp_path, capsys):
    assert main(["fleet", "report", "--store", str(tmp_path / "none"), "--out",
                 str(tmp_path / "r.html")]) == 2
    assert main(["fleet", "ingest", str(tmp_path), "--store", str(tmp_path / "s"),
                 "--name-pattern", "(no group"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith("ddh-vsensor fleet: error:") for line in err)


def test_a_batch_gives_what_each_log_alone_and_the_per_log_analysis_give(fleet_logs, cfg,
                                                                           tmp_path):
    """Batched ingestion (holding speeds modelled for the whole batch, one sync) stores
    the same tables as one log per call, and each log's holds and reference increments
    are those of its own reference run (the per-log path of ``analyze --truth
    references``)."""
    from ddh_vsensor.diagnosis.references import _nominal_tables, reference_run
    from ddh_vsensor.estimator.estimator import Estimator
    from ddh_vsensor.fleet.ingest import ingest_batch, read_log
    from ddh_vsensor.measured import MeasuredDataError
    logs = sorted(fleet_logs.glob("*.blf"))
    one, batch = tmp_path / "one", tmp_path / "batch"
    Store(one, create=True), Store(batch, create=True)
    for log in logs:
        assert ingest_one(IngestJob(str(log), str(one)))["status"] == "ingested"
    assert [r["status"] for r in ingest_batch([IngestJob(str(p), str(batch))
                                               for p in logs])] == ["ingested"] * len(logs)
    assert files(batch) == files(one)
    s = Store(batch)
    checked = 0
    for log in logs:
        log_id = s.query(f"SELECT log_id FROM meta WHERE file = '{log.name}'")["log_id"][0]
        runs, _, _ = read_log(str(log), cfg)
        for actuator, run in runs.items():
            try:
                rr = reference_run(cfg, actuator, run)
            except MeasuredDataError:
                continue
            holds = s.query(f"SELECT * FROM holds WHERE log_id = '{log_id}' AND actuator = "
                            f"'{actuator}' ORDER BY time_s").to_pydict()
            assert holds["model_speed_rpm"] == [h.model_speed_rpm for h in rr.holds]
            assert holds["speed_rpm"] == [h.speed_rpm for h in rr.holds]
            est = Estimator(cfg, actuator, _nominal_tables(cfg, actuator), references=False,
                            adaptation=False, initial_position_mm=rr.run.initial_position_mm)
            obs = rr.observe(est.run(rr.run.time_s, rr.run.speed_rpm, rr.run.torque_nm,
                                     rr.run.oil_temp_c).position_mm)
            events = s.query(f"SELECT nominal_increment_mm FROM events WHERE log_id = "
                             f"'{log_id}' AND actuator = '{actuator}' ORDER BY time_s")
            assert events["nominal_increment_mm"].to_pylist() == [None] + list(
                obs[:rr.n_increments])
            assert holds["nominal_creep_mm"] == list(obs[rr.n_increments:])
            checked += len(rr.holds)
    assert checked > 0
