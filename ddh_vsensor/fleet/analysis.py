"""The per-machine analysis: every log's references and holds against each catalogued cause
on a fixed grid of its parameter, one row per log, actuator and cause. ``compressibility``
is left out: its chamber model costs ~1 s per value and log, and entrained air does not
creep up over weeks (``analyze --truth references`` fits it on a machine's runs).

A machine's logs are days apart and its parameters drift, so each log is fitted on its own
(the trend is :mod:`.trend`'s business, with the held-out discipline across days there).
The grid is fixed so that the tables of a modified unit are built once per worker process
and reused for every log: per log only the estimator runs (a few ms each). Each row holds,
per grid value, the loss of the observations (:class:`diagnosis.references.ReferenceRun`;
:func:`robust_loss`) and the largest change the cause makes to an edge-to-edge increment
(the error it puts into the estimate between references: the expected position error).
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from scipy.special import huber

from ddh_vsensor.config import Config
from ddh_vsensor.diagnosis.causes import ALL_CAUSES
from ddh_vsensor.diagnosis.references import ReferenceRun, reference_run
from ddh_vsensor.diagnosis.workbench import Workbench
from ddh_vsensor.measured import MeasuredDataError
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.tables.build import build_unit_tables
from ddh_vsensor.tables.lookup import UnitTables
from ddh_vsensor.tables.store import TableError, load_unit_tables, save_unit_tables
from ddh_vsensor.fleet.ingest import config_of, run_of
from ddh_vsensor.fleet.store import Store

# Fixed grids (include neutral); wide enough to extrapolate the trends they feed.
GRIDS: dict[str, tuple[float, ...]] = {
    "pump_leakage": (0.4, 0.55, 0.7, 0.8, 0.9, 1.0, 1.1, 1.25, 1.5, 1.75, 2.0, 2.5, 3.0, 4.0,
                     6.0),
    "displacement": (0.94, 0.96, 0.98, 0.99, 0.995, 1.0, 1.005, 1.01, 1.02, 1.04, 1.06),
    "belt_slip": (0.0, 1.0, 2.0, 3.0, 5.0, 7.5, 10.0, 15.0, 20.0, 30.0),
    "time_offset": (-0.3, -0.2, -0.12, -0.08, -0.05, -0.03, -0.015, 0.0, 0.015, 0.03, 0.05,
                    0.08, 0.12, 0.2, 0.3),
}
# Tables over the oil a fleet's logs see (same grid nodes as the config's).
TABLE_RANGE_C = (10.0, 80.0)
# A log's fit is the squared error up to ROBUST_MM and linear beyond (Huber): 30 s of work
# give 3-10 observations, and one that no cause makes (a "hold" that was the slow end of a
# move: 23 mm of creep against increments below 0.7 mm) had carried the log's fit to a grid
# end and raised alarms.
ROBUST_MM = 1.0
# Every log replayed on the tables: the chamber model (which `analyze` uses) gave no better
# warnings or fewer false alarms on two fleets, at the same cost.
FLEET_MODE = "full"
_TABLE_CACHE: dict[tuple, UnitTables] = {}


def _fixed_range(cfg: Config) -> Config:
    t0, t1, step = cfg.tables.temperatures_c
    lo = t0 + step * np.floor((max(TABLE_RANGE_C[0], t0) - t0) / step)
    hi = t0 + step * np.ceil((min(TABLE_RANGE_C[1], t1) - t0) / step)
    return dataclasses.replace(cfg, tables=dataclasses.replace(
        cfg.tables, temperatures_c=(float(lo), float(hi), step)))


class FleetBench(Workbench):
    """A workbench whose modified tables are cached across logs (the full temperature
    range, so every log's lookups are those of the same tables), keyed by the pumps: the
    only part of the unit the catalogue's causes change."""

    def __init__(self, cfg: Config, actuator: str, runs, mode: str,
                 table_dir: Path | None = None) -> None:
        self._key = cfg.physics_hash()
        self._table_dir = table_dir
        self._fixed = _fixed_range(cfg)
        super().__init__(cfg, actuator, runs, mode, inertia=cfg.estimator.inertia_compensation)

    def tables(self, unit: DDHUnit) -> UnitTables:
        key = (self._key, self.actuator, repr(unit.a.pump), repr(unit.b.pump))
        if key not in _TABLE_CACHE:
            _TABLE_CACHE[key] = self._load_or_build(key, unit)
        return _TABLE_CACHE[key]

    def _load_or_build(self, key: tuple, unit: DDHUnit) -> UnitTables:
        """Tables are shared between worker processes through the store (DIR/tables/)."""
        if self._table_dir is None:
            return build_unit_tables(self._fixed, self.actuator, unit)
        where = self._table_dir / hashlib.sha1(repr(key).encode()).hexdigest()[:16]
        try:
            return load_unit_tables(where, self.actuator)
        except (OSError, TableError, ValueError, KeyError):
            tables = build_unit_tables(self._fixed, self.actuator, unit)
            save_unit_tables(where, tables)
            return tables


def fit_log(cfg: Config, rr: ReferenceRun, actuator: str,
            causes: Sequence[str] = tuple(GRIDS), table_dir: Path | None = None) -> list[dict]:
    """One log's rows: per cause its grid, loss and largest increment change."""
    bench = FleetBench(cfg, actuator, [rr.run], FLEET_MODE, table_dir)
    nominal = rr.observe(bench.base[0])
    n_inc = rr.n_increments
    rows = []
    for name in causes:
        cause = ALL_CAUSES[name]
        grid = GRIDS[name]
        deltas = cause.deltas(bench, bench.base, grid)
        loss, emax = [], []
        for per_run in deltas:
            d = rr.observe_delta(per_run[0])
            loss.append(robust_loss(nominal + d))
            emax.append(float(np.max(np.abs(d[:n_inc]))) if n_inc else 0.0)
        rows.append({"cause": name, "grid": list(grid), "loss": loss, "emax_mm": emax,
                     "n_obs": int(len(nominal)), "n_increments": int(n_inc),
                     "loss_nominal": robust_loss(nominal),
                     "max_increment_mm": float(np.max(np.abs(nominal[:n_inc])))})
    return rows


def robust_loss(residual_mm: np.ndarray) -> float:
    """Squared error within ROBUST_MM of zero, linear beyond (mm²: twice scipy's Huber)."""
    return 2.0 * float(np.sum(huber(ROBUST_MM, residual_mm)))


def analyse_machine(args: tuple[str, str, str | None]) -> dict:
    """Fit every log of a machine (a Dask task); writes DIR/fits/<machine>.parquet."""
    store_dir, machine, config = args
    store = Store(store_dir)
    cfg = config_of(config)
    logs = store.machine_logs().get(machine, [])
    meta = {r["log_id"]: r for r in store.query(
        f"SELECT log_id, start_time_s, operating_hours FROM meta WHERE machine = '{machine}'"
    ).to_pylist()}
    path = store.fits_path(machine)
    if path.is_file():
        done = pq.read_table(path)
        current = "loss" in done.column_names            # else fitted before the robust loss
        if current and sorted(set(done["log_id"].to_pylist())) == sorted(logs):
            return {"machine": machine, "logs": len(logs), "cached": True}
    rows = []
    for log_id in logs:
        for actuator in cfg.can.units:
            try:
                rr = reference_run(cfg, actuator, run_of(store, log_id, actuator, cfg),
                                   model_speeds=False)
            except MeasuredDataError:
                continue
            for row in fit_log(cfg, rr, actuator, table_dir=store.root / "tables"):
                rows.append({"machine": machine, "log_id": log_id, "actuator": actuator,
                             "time_s": meta[log_id]["start_time_s"],
                             "operating_hours": meta[log_id]["operating_hours"], **row})
    if not rows:                                    # keep the log ids: nothing to fit
        rows = [{"machine": machine, "log_id": log_id, "actuator": "", "cause": "",
                 "time_s": meta[log_id]["start_time_s"], "operating_hours": float("nan"),
                 "grid": [], "loss": [], "emax_mm": [], "n_obs": 0, "n_increments": 0,
                 "loss_nominal": 0.0, "max_increment_mm": 0.0} for log_id in logs]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    pq.write_table(pa.Table.from_pylist(rows), tmp)
    tmp.replace(path)
    return {"machine": machine, "logs": len(logs), "cached": False}


