"""The per-machine analysis: every log's references and holds against each catalogued cause
on a fixed grid of its parameter, one row per log, actuator and cause
(:mod:`ddh_vsensor.diagnosis.evidence`), and the rows of the machine's day summaries (the
daemon summed the same rows over the whole day's work: taken as they are).

A machine's logs are days apart and its parameters drift, so each log is fitted on its own
(the trend is :mod:`.trend`'s business, with the held-out discipline across days there).
The grid is fixed so that the tables of a modified unit are built once per worker process
and reused for every log: per log only the estimator runs (a few ms each).
"""

from __future__ import annotations

import json
import os

import pyarrow as pa
import pyarrow.parquet as pq

from ddh_vsensor.diagnosis.evidence import (  # noqa: F401 - the analysis' names
    FLEET_MODE, GRIDS, ROBUST_MM, TABLE_RANGE_C, FleetBench, fit_log, robust_loss)
from ddh_vsensor.diagnosis.references import reference_run
from ddh_vsensor.measured import MeasuredDataError
from ddh_vsensor.estimator.day_samples import day_of
from ddh_vsensor.fleet.ingest import config_of, run_of
from ddh_vsensor.fleet.store import Store

_INPUTS = b"ddh_vsensor_inputs"     # the fits' metadata: the ids they were fitted from


def _newest_summaries(meta: dict[str, dict]) -> dict[str, str]:
    """day -> the id of the machine's summary of that day that saw the most of it (a daemon
    writes its day over and over: each export is another file, the last the whole day)."""
    best: dict[str, tuple] = {}
    for log_id, m in meta.items():
        if m.get("kind") == "summary":
            rank = (m["last_s"], bool(m["complete"]), log_id)
            if m["day"] not in best or rank > best[m["day"]]:
                best[m["day"]] = rank
    return {day: rank[2] for day, rank in best.items()}


def analyse_machine(args: tuple[str, str, str | None]) -> dict:
    """Fit every log of a machine and take its day summaries' rows (a Dask task); writes
    DIR/fits/<machine>.parquet. A unit's day with observations in a summary is that
    summary's (the daemon saw the whole day's work); the day's logs, minutes of the same
    work, are left out for that unit. Fitted again only when the machine's files change."""
    store_dir, machine, config = args
    store = Store(store_dir)
    cfg = config_of(config)
    ids = store.machine_logs().get(machine, [])
    meta = {r["log_id"]: r for r in store.query(
        f"SELECT * FROM meta WHERE machine = '{machine}'").to_pylist()}
    inputs = json.dumps(sorted(ids)).encode()
    path = store.fits_path(machine)
    if path.is_file():
        done = pq.read_schema(path).metadata or {}
        if done.get(_INPUTS) == inputs:
            return {"machine": machine, "logs": len(ids), "cached": True}
    chosen = set(_newest_summaries(meta).values())
    evidence = {sid: store.read(sid, "evidence").to_pylist() for sid in chosen}
    covered = {(meta[sid]["day"], r["actuator"]) for sid, rows in evidence.items()
               for r in rows if r["n_obs"] > 0}
    rows = []
    for log_id in ids:
        m = meta[log_id]
        where = {"machine": machine, "log_id": log_id, "time_s": m["start_time_s"],
                 "operating_hours": m["operating_hours"]}
        if m.get("kind") == "summary":
            for r in evidence.get(log_id, []):
                rows.append({**where, **{k: v for k, v in r.items()
                                         if k not in ("machine", "log_id")},
                             "source": "summary"})
            continue
        day = m.get("day") or day_of(m["start_time_s"])
        for actuator in cfg.can.units:
            if (day, actuator) in covered:
                continue
            try:
                rr = reference_run(cfg, actuator, run_of(store, log_id, actuator, cfg),
                                   model_speeds=False)
            except MeasuredDataError:
                continue
            for row in fit_log(cfg, rr, actuator, table_dir=store.root / "tables"):
                rows.append({**where, "actuator": actuator, **row, "source": "log"})
    if not rows:                                    # keep the ids: nothing to fit
        rows = [{"machine": machine, "log_id": log_id, "actuator": "", "cause": "",
                 "time_s": meta[log_id]["start_time_s"], "operating_hours": float("nan"),
                 "grid": [], "loss": [], "emax_mm": [], "n_obs": 0, "n_increments": 0,
                 "loss_nominal": 0.0, "max_increment_mm": 0.0, "source": ""}
                for log_id in ids]
    table = pa.Table.from_pylist(rows)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    pq.write_table(table.replace_schema_metadata({_INPUTS: inputs}), tmp)
    tmp.replace(path)
    return {"machine": machine, "logs": len(ids), "cached": False}
