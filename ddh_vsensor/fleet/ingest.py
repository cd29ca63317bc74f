"""Ingesting CAN logs and daemons' day summaries into the store: per log the machine, time,
operating hours, the samples, the reference events and the holds with their features; per
summary (:mod:`ddh_vsensor.diagnosis.day_summary`, ``*.summary.json``) its machine, day,
the analysis' rows it holds (``evidence``: the daemon computed them) and the day's context.

Runs as one task per batch of logs (on Dask workers, :mod:`.cluster`): a log's features are
its own, only the holds' modelled speeds are computed for the batch at once (vectorised,
row by row: the same numbers) and the batch's files reach the disk with one sync. A log
that cannot be read, or whose name says no machine, is recorded as rejected with the reason
and never stops the others; so is a summary that is corrupt or was computed under another
configuration (physics hash) or for other units. A log's machine and operating hours come
from the file name through a regular expression with the groups ``machine`` (required) and
``hours`` (optional); its time from the log's own timestamps (the BLF header), else a
``date`` group. A summary says its machine and day itself (the name pattern is not used).
"""

from __future__ import annotations

import datetime as dt
import re
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import pyarrow as pa

from ddh_vsensor.config import Config, load_config
from ddh_vsensor.diagnosis.day_summary import SummaryError, read_summary, summary_rows
from ddh_vsensor.diagnosis.holds import model_holding_speeds_rpm
from ddh_vsensor.estimator.day_samples import SUFFIX as SUMMARY_SUFFIX, day_of
from ddh_vsensor.estimator.estimator import Estimator
from ddh_vsensor.measured import MeasuredDataError, Run
from ddh_vsensor.fleet.store import Store, log_id_of

DEFAULT_NAME_PATTERN = (r"^(?P<machine>[A-Za-z0-9-]+)_(?P<date>\d{4}-\d{2}-\d{2})"
                        r"_(?P<hours>[0-9.]+)h")
_EPOCH_1990_S = 631152000.0


@dataclass(frozen=True)
class IngestJob:
    path: str
    store: str
    config: str | None = None
    name_pattern: str = DEFAULT_NAME_PATTERN


@lru_cache(maxsize=4)
def config_of(path: str | None) -> Config:
    return load_config(path)


def compile_pattern(pattern: str) -> re.Pattern:
    from ddh_vsensor.errors import UserError
    try:
        rx = re.compile(pattern)
    except re.error as exc:
        raise UserError(f"--name-pattern {pattern!r}: {exc}") from None
    if "machine" not in rx.groupindex:
        raise UserError(f"--name-pattern {pattern!r}: needs a group (?P<machine>...)")
    return rx


def read_log(path: str, cfg: Config, raw: bytes | None = None
             ) -> tuple[dict[str, Run], int, float | None]:
    """Runs per actuator, the number of frames and the log's wall-clock start (if any). A
    cut-off BLF is refused: a day's log in part would pass for a shorter day."""
    if path.lower().endswith(".blf"):
        from ddh_vsensor.io.blf import frames_to_runs, read_frames
        frames = read_frames(path, raw, need_whole=True)
        runs = frames_to_runs(frames, cfg, path)
        t0 = float(frames.timestamp_s.min()) if len(frames) else None
        return runs, len(frames), t0
    from ddh_vsensor.io.log import _frames, read_can_log
    runs = {a: read_can_log(path, a, cfg) for a in cfg.can.units}
    n = sum(1 for _ in _frames(path))
    return runs, n, float(min(r.time_s[0] for r in runs.values()))


_EVENT_SCHEMA = pa.schema([("machine", pa.string()), ("log_id", pa.string()),
                           ("actuator", pa.string()), ("time_s", pa.float64()),
                           ("switch", pa.string()), ("rising", pa.bool_()),
                           ("position_mm", pa.float64()),
                           ("nominal_increment_mm", pa.float64())])
_HOLD_SCHEMA = pa.schema([("machine", pa.string()), ("log_id", pa.string()),
                          ("actuator", pa.string()), ("time_s", pa.float64()),
                          ("duration_s", pa.float64()), ("speed_rpm", pa.float64()),
                          ("model_speed_rpm", pa.float64()), ("torque_nm", pa.float64()),
                          ("oil_temp_c", pa.float64()), ("nominal_creep_mm", pa.float64())])


def _column_table(columns: dict[str, object], n: int, schema: pa.Schema) -> pa.Table:
    """A table from columns (arrays, or one value repeated ``n`` times)."""
    return pa.table({f.name: pa.array(np.broadcast_to(np.asarray(columns[f.name]), (n,))
                                      if f.type != pa.string() else
                                      ([columns[f.name]] * n if isinstance(columns[f.name], str)
                                       else list(columns[f.name])), f.type)
                     for f in schema}, schema=schema)


def _features(cfg: Config, machine: str, log_id: str, actuator: str, run: Run,
              t0: float) -> tuple[pa.Table, dict[str, np.ndarray]]:
    """Reference events of one actuator, with the nominal model's errors there, and its
    holds' columns (the modelled holding speed NaN: :func:`ingest_batch` computes every
    log's of a batch at once)."""
    from ddh_vsensor.diagnosis.references import _nominal_tables, reference_run
    try:
        rr = reference_run(cfg, actuator, run, model_speeds=False)
    except MeasuredDataError:                 # too few edges today: nothing to observe
        return _EVENT_SCHEMA.empty_table(), {f.name: np.zeros(0) for f in _HOLD_SCHEMA
                                             if f.type == pa.float64()}
    est = Estimator(cfg, actuator, _nominal_tables(cfg, actuator), references=False,
                    adaptation=False, initial_position_mm=rr.run.initial_position_mm)
    x = est.run(rr.run.time_s, rr.run.speed_rpm, rr.run.torque_nm,
                rr.run.oil_temp_c).position_mm
    obs = rr.observe(x)
    n_edges = len(rr.edges)
    events = _column_table({
        "machine": machine, "log_id": log_id, "actuator": actuator,
        "time_s": rr.run.time_s[rr.edges] - t0, "switch": rr.switch,
        "rising": np.asarray(rr.rising, bool), "position_mm": rr.edge_mm,
        "nominal_increment_mm": np.concatenate([[np.nan], obs[:rr.n_increments]])},
        n_edges, _EVENT_SCHEMA)
    # the first edge starts the estimate: it has no increment (null, not NaN)
    events = events.set_column(7, "nominal_increment_mm", pa.array(
        events["nominal_increment_mm"].to_numpy(), mask=np.arange(n_edges) == 0))
    h = rr.holds
    holds = {"time_s": np.array([rr.run.time_s[x.start] - t0 for x in h], float),
             "duration_s": np.array([x.duration_s for x in h], float),
             "speed_rpm": np.array([x.speed_rpm for x in h], float),
             "model_speed_rpm": np.full(len(h), np.nan),
             "torque_nm": np.array([x.torque_nm for x in h], float),
             "oil_temp_c": np.array([x.oil_temp_c for x in h], float),
             "nominal_creep_mm": np.asarray(obs[rr.n_increments:], float)}
    return events, holds


@dataclass
class _Extracted:
    """One log read and its features, before the batch's holding speeds and the store (or
    a summary's tables)."""
    result: dict
    log_id: str
    tables: dict[str, pa.Table]
    holds: dict[str, dict[str, np.ndarray]] | None   # actuator -> columns; None: a summary
    machine: str


def is_summary(path: str) -> bool:
    return path.lower().endswith(SUMMARY_SUFFIX)


_CONTEXT = ("work_s", "analysed_s", "stretches", "unused_stretches", "increments", "holds",
            "n_obs", "max_increment_day_mm")


def _summary_tables(doc: dict, log_id: str, name: str, path: str) -> dict[str, pa.Table]:
    """A summary's meta (its day's first time, the longest unit's work), the analysis rows
    it holds (``evidence``) and each unit's day (``context``)."""
    machine, units = doc["machine"], doc["units"]
    rows = summary_rows(doc)
    evidence = pa.Table.from_pylist(
        [{"machine": machine, "log_id": log_id, **r} for r in rows], schema=_EVIDENCE_SCHEMA)
    context = pa.Table.from_pylist([{
        "machine": machine, "log_id": log_id, "actuator": a, "day": doc["day"],
        **{k: u[k] for k in _CONTEXT},
        **{f"{what}_{k}": (u[what] or {}).get(k, float("nan"))
           for what in ("oil_c", "hold_torque_nm") for k in ("min", "mean", "max")}}
        for a, u in units.items()])
    meta = pa.table({"log_id": [log_id], "machine": [machine], "file": [name],
                     "path": [str(Path(path).resolve())],
                     "start_time_s": [float(doc["first_s"])],
                     "duration_s": [max((float(u["work_s"]) for u in units.values()),
                                        default=0.0)],
                     "operating_hours": [float("nan")], "frames": [0],
                     "events": [sum(int(u["increments"]) for u in units.values())],
                     "holds": [sum(int(u["holds"]) for u in units.values())],
                     "kind": ["summary"], "day": [doc["day"]],
                     "last_s": [float(doc["last_s"])], "complete": [bool(doc["complete"])]})
    return {"meta": meta, "evidence": evidence, "context": context}


_EVIDENCE_SCHEMA = pa.schema([("machine", pa.string()), ("log_id", pa.string()),
                              ("actuator", pa.string()), ("cause", pa.string()),
                              ("grid", pa.list_(pa.float64())),
                              ("loss", pa.list_(pa.float64())),
                              ("emax_mm", pa.list_(pa.float64())), ("n_obs", pa.int64()),
                              ("n_increments", pa.int64()), ("loss_nominal", pa.float64()),
                              ("max_increment_mm", pa.float64())])


def _extract_summary(job: IngestJob, data: bytes, log_id: str, base: dict,
                     started: float) -> dict | _Extracted:
    """A day summary's tables, or its rejection."""
    name = Path(job.path).name
    try:
        doc = read_summary(data, name, config_of(job.config))
    except SummaryError as exc:
        Store(job.store).reject(log_id, job.path, str(exc))
        return {**base, "status": "rejected", "problem": str(exc), "kind": "summary",
                "seconds": time.perf_counter() - started}
    tables = _summary_tables(doc, log_id, name, job.path)
    return _Extracted({**base, "status": "ingested", "machine": doc["machine"],
                       "kind": "summary", "duration_s": tables["meta"]["duration_s"][0].as_py(),
                       "seconds": time.perf_counter() - started},
                      log_id, tables, None, doc["machine"])


def _extract(job: IngestJob) -> dict | _Extracted:
    """One log's tables, or what happened to it (present, rejected) as a result."""
    started = time.perf_counter()
    store = Store(job.store)
    name = Path(job.path).name
    try:
        data = Path(job.path).read_bytes()
    except OSError as exc:
        return {"path": job.path, "status": "rejected", "problem": f"cannot read: {exc}",
                "frames": 0, "duration_s": 0.0, "seconds": time.perf_counter() - started}
    log_id = log_id_of(data)
    kind = "summary" if is_summary(job.path) else "log"
    base = {"path": job.path, "log_id": log_id, "frames": 0, "duration_s": 0.0, "kind": kind}
    if store.has(log_id):
        return {**base, "status": "present", "seconds": time.perf_counter() - started}
    if kind == "summary":
        return _extract_summary(job, data, log_id, base, started)
    try:
        m = re.search(job.name_pattern, name)
        if m is None:
            raise MeasuredDataError(job.path, "the file name does not match the name "
                                    f"pattern {job.name_pattern!r} (no machine)")
        machine = m.group("machine")
        hours = float(m.group("hours")) if "hours" in m.re.groupindex and m.group("hours") \
            else float("nan")
        cfg = config_of(job.config)
        runs, n_frames, t0 = read_log(job.path, cfg, data)
        if t0 is None or t0 < _EPOCH_1990_S:
            if "date" not in m.re.groupindex or not m.group("date"):
                raise MeasuredDataError(job.path, "no wall-clock time in the log and no "
                                        "date in its name")
            date = dt.datetime.fromisoformat(m.group("date")).replace(tzinfo=dt.timezone.utc)
            start_time_s = date.timestamp() + (t0 or 0.0)
        else:
            start_time_s = t0
        t_ref = min(float(r.time_s[0]) for r in runs.values())
        events, holds, samples = [], {}, []
        for actuator, run in runs.items():
            e, holds[actuator] = _features(cfg, machine, log_id, actuator, run, t_ref)
            events.append(e)
            switches = list(cfg.unit(actuator).references_mm)
            hall = np.zeros(len(run.time_s), np.uint8)
            edge_s = np.full(len(run.time_s), np.nan)       # a switch's change, timed
            for i, sw in enumerate(switches):
                if sw in run.refs:
                    hall |= run.refs[sw].astype(np.uint8) << i
                if sw in run.ref_edge_s:
                    timed = np.isfinite(run.ref_edge_s[sw])
                    edge_s[timed] = run.ref_edge_s[sw][timed] - t_ref
            samples.append(pa.table({
                "actuator": pa.DictionaryArray.from_arrays(
                    np.zeros(len(run.time_s), np.int32), [actuator]).cast(pa.string()),
                "time_s": run.time_s - t_ref, "speed_rpm": run.speed_rpm,
                "torque_nm": run.torque_nm, "oil_temp_c": run.oil_temp_c, "hall": hall,
                "hall_edge_s": edge_s}))
        duration = max(float(r.time_s[-1] - r.time_s[0]) for r in runs.values())
        n_events = sum(len(e) for e in events)
        n_holds = sum(len(h["time_s"]) for h in holds.values())
        meta = pa.table({"log_id": [log_id], "machine": [machine], "file": [name],
                         "path": [str(Path(job.path).resolve())],
                         "start_time_s": [start_time_s], "duration_s": [duration],
                         "operating_hours": [hours], "frames": [n_frames],
                         "events": [n_events], "holds": [n_holds], "kind": ["log"],
                         "day": [day_of(start_time_s)]})
        return _Extracted({**base, "status": "ingested", "machine": machine,
                           "frames": n_frames, "duration_s": duration,
                           "seconds": time.perf_counter() - started}, log_id,
                          {"samples": pa.concat_tables(samples),
                           "events": pa.concat_tables(events), "meta": meta},
                          holds, machine)
    except Exception as exc:           # any problem with one log: reported, never fatal
        problem = str(exc) if isinstance(exc, MeasuredDataError) else \
            f"{Path(job.path).name}: {type(exc).__name__}: {exc}"
        store.reject(log_id, job.path, problem)
        return {**base, "status": "rejected", "problem": problem,
                "seconds": time.perf_counter() - started}


def _fill_model_speeds(cfg_of_job: list[Config], logs: list[_Extracted]) -> None:
    """Every hold's modelled holding speed, one vectorised call per config and unit for
    the whole batch (row by row: the numbers one log at a time would give)."""
    from ddh_vsensor.physics.unit import DDHUnit
    groups: dict[tuple[int, str], list[dict[str, np.ndarray]]] = {}
    cfgs: dict[int, Config] = {}
    for cfg, log in zip(cfg_of_job, logs):
        cfgs[id(cfg)] = cfg
        for actuator, cols in log.holds.items():
            groups.setdefault((id(cfg), actuator), []).append(cols)
    for (key, actuator), parts in groups.items():
        torque = np.concatenate([p["torque_nm"] for p in parts])
        if not len(torque):
            continue
        speed = model_holding_speeds_rpm(DDHUnit.from_config(cfgs[key], actuator), torque,
                                         np.concatenate([p["oil_temp_c"] for p in parts]))
        for p, s in zip(parts, np.split(speed, np.cumsum([len(p["torque_nm"])
                                                            for p in parts])[:-1])):
            p["model_speed_rpm"] = s


def ingest_batch(jobs: list[IngestJob]) -> list[dict]:
    """Ingest several logs (one Dask task); returns what happened to each, in order (never
    raises for a bad log). The logs' hold speeds are modelled in one call and their files
    synced to disk at once, before each log's directory is renamed into the store."""
    out: list[dict | _Extracted] = [_extract(job) for job in jobs]
    done = [(job, x) for job, x in zip(jobs, out) if isinstance(x, _Extracted)]
    logs = [(job, x) for job, x in done if x.holds is not None]
    _fill_model_speeds([config_of(job.config) for job, _ in logs], [x for _, x in logs])
    by_store: dict[str, list[tuple[str, dict[str, pa.Table]]]] = {}
    for job, x in done:
        if x.holds is None:                       # a summary: its tables as they are
            by_store.setdefault(job.store, []).append((x.log_id, x.tables))
            continue
        holds = pa.concat_tables([_column_table(
            {"machine": x.machine, "log_id": x.log_id, "actuator": a, **cols},
            len(cols["time_s"]), _HOLD_SCHEMA) for a, cols in x.holds.items()]) \
            if x.holds else _HOLD_SCHEMA.empty_table()
        by_store.setdefault(job.store, []).append((x.log_id, {
            "samples": x.tables["samples"], "events": x.tables["events"], "holds": holds,
            "meta": x.tables["meta"]}))
    for store, logs in by_store.items():
        Store(store).put_logs(logs)
    return [x.result if isinstance(x, _Extracted) else x for x in out]


def ingest_one(job: IngestJob) -> dict:
    """Ingest one log; returns what happened (never raises for a bad log)."""
    return ingest_batch([job])[0]


def run_of(store: Store, log_id: str, actuator: str, cfg: Config) -> Run:
    """An actuator's run back from the store's samples (times relative to the log)."""
    import pyarrow.compute as pc
    t = store.read(log_id, "samples")
    t = t.filter(pc.equal(t["actuator"], actuator))
    col = {k: t[k].to_numpy() for k in ("time_s", "speed_rpm", "torque_nm", "oil_temp_c",
                                        "hall")}
    switches = list(cfg.unit(actuator).references_mm)
    refs = {sw: ((col["hall"] >> i) & 1).astype(np.uint8) for i, sw in enumerate(switches)}
    edges = {}
    if "hall_edge_s" in t.column_names:             # (stores from before it have none)
        edge_s = t["hall_edge_s"].to_numpy()
        for sw, state in refs.items():
            changed = np.concatenate([[False], state[1:] != state[:-1]])
            edges[sw] = np.where(changed, edge_s, np.nan)
    return Run(time_s=col["time_s"], speed_rpm=col["speed_rpm"], torque_nm=col["torque_nm"],
               oil_temp_c=col["oil_temp_c"], position_mm=np.full(len(col["time_s"]), np.nan),
               refs=refs, source=f"{log_id}:{actuator}", ref_edge_s=edges)
