"""What a stretch of work without a position sensor says about each catalogued cause: its
references and holds against the cause on a fixed grid of its parameter, one row per cause.

Shared by the fleet's analysis of a CAN log (:mod:`ddh_vsensor.fleet.analysis`) and the
daemon's day summary (:mod:`.day_summary`): both sum the same observations, so a day of
stretches adds up to what the analysis would find in one long log of the day.

Each row holds, per grid value, the loss of the observations (:class:`.references.ReferenceRun`:
edge-to-edge increments of the estimate's error and the holds' creep; :func:`robust_loss`)
and the largest change the cause makes to an increment (the error it puts into the estimate
between references: the expected position error). ``compressibility`` is left out: its
chamber model costs ~1 s per value and stretch, and entrained air does not creep up over
weeks (``analyze --truth references`` fits it on a machine's runs).

The grid is fixed so that the tables of a modified unit can be built once and reused for
every stretch (:class:`FleetBench`: per stretch only the estimator runs, a few ms each), or,
where memory is short (the daemon: a full table set is 16 MB, the grids need 25 per unit),
built per stretch over its own oil temperatures only (:class:`LeanBench`: ~0.2 s per unit
and minute-long stretch, a few MB at a time). Both take the same table nodes, so the
lookups, hence the rows, are the same to rounding.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.special import huber

from ddh_vsensor.config import Config
from ddh_vsensor.diagnosis.causes import ALL_CAUSES
from ddh_vsensor.diagnosis.references import ReferenceRun
from ddh_vsensor.diagnosis.workbench import Workbench
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.tables.build import build_unit_tables
from ddh_vsensor.tables.lookup import UnitTables
from ddh_vsensor.tables.store import TableError, load_unit_tables, save_unit_tables

# Fixed grids (include neutral); wide enough to extrapolate the trends they feed.
GRIDS: dict[str, tuple[float, ...]] = {
    "pump_leakage": (0.4, 0.55, 0.7, 0.8, 0.9, 1.0, 1.1, 1.25, 1.5, 1.75, 2.0, 2.5, 3.0, 4.0,
                     6.0),
    "displacement": (0.94, 0.96, 0.98, 0.99, 0.995, 1.0, 1.005, 1.01, 1.02, 1.04, 1.06),
    "belt_slip": (0.0, 1.0, 2.0, 3.0, 5.0, 7.5, 10.0, 15.0, 20.0, 30.0),
    "time_offset": (-0.3, -0.2, -0.12, -0.08, -0.05, -0.03, -0.015, 0.0, 0.015, 0.03, 0.05,
                    0.08, 0.12, 0.2, 0.3),
}
# Tables over the oil a fleet's work sees (same grid nodes as the config's).
TABLE_RANGE_C = (10.0, 80.0)
# A stretch's fit is the squared error up to ROBUST_MM and linear beyond (Huber): 30 s of
# work give 3-10 observations, and one that no cause makes (a "hold" that was the slow end
# of a move: 23 mm of creep against increments below 0.7 mm) had carried a log's fit to a
# grid end and raised alarms.
ROBUST_MM = 1.0
# Every stretch replayed on the tables: the chamber model (which `analyze` uses) gave no
# better warnings or fewer false alarms on two fleets, at the same cost.
FLEET_MODE = "full"
_TABLE_CACHE: dict[tuple, UnitTables] = {}


def _fixed_range(cfg: Config) -> Config:
    t0, t1, step = cfg.tables.temperatures_c
    lo = t0 + step * np.floor((max(TABLE_RANGE_C[0], t0) - t0) / step)
    hi = t0 + step * np.ceil((min(TABLE_RANGE_C[1], t1) - t0) / step)
    return dataclasses.replace(cfg, tables=dataclasses.replace(
        cfg.tables, temperatures_c=(float(lo), float(hi), step)))


class FleetBench(Workbench):
    """A workbench whose modified tables are cached across stretches (the full temperature
    range, so every stretch's lookups are those of the same tables), keyed by the pumps:
    the only part of the unit the catalogue's causes change."""

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


def lean_range(cfg: Config, oil_temp_c: Sequence[np.ndarray]) -> Config:
    """The config with its table temperatures cut to the nodes of :data:`TABLE_RANGE_C`
    that bracket the oil of the runs (at the range's ends the full tables clamp: so do
    these, at the same node)."""
    fixed = _fixed_range(cfg)
    t0, t1, step = fixed.tables.temperatures_c
    last = round((t1 - t0) / step)
    lo = min(float(np.min(t)) for t in oil_temp_c)
    hi = max(float(np.max(t)) for t in oil_temp_c)
    k0 = min(max(0, math.floor((lo - t0) / step)), last - 1)
    k1 = min(max(k0 + 1, math.ceil((hi - t0) / step)), last)
    return dataclasses.replace(fixed, tables=dataclasses.replace(
        fixed.tables, temperatures_c=(t0 + k0 * step, t0 + k1 * step, step)))


class LeanBench(Workbench):
    """A workbench whose tables span only the nodes around its runs' oil, a modified
    unit's dropped once its grid value is done: the memory of two table sets of a few
    nodes instead of the grids' 25 over the full range."""

    def __init__(self, cfg: Config, actuator: str, runs, mode: str) -> None:
        self._lean = lean_range(cfg, [r.oil_temp_c for r in runs])
        super().__init__(cfg, actuator, runs, mode, inertia=cfg.estimator.inertia_compensation)

    def tables(self, unit: DDHUnit) -> UnitTables:
        return build_unit_tables(self._lean, self.actuator, unit)

    def drop_modified(self) -> None:
        self._table_cache.clear()


def fit_log(cfg: Config, rr: ReferenceRun, actuator: str,
            causes: Sequence[str] = tuple(GRIDS), table_dir: Path | None = None,
            lean: bool = False) -> list[dict]:
    """One stretch's (a log's) rows: per cause its grid, loss and largest increment
    change. ``lean``: tables over the stretch's own oil (:class:`LeanBench`)."""
    bench: Workbench = LeanBench(cfg, actuator, [rr.run], FLEET_MODE) if lean else \
        FleetBench(cfg, actuator, [rr.run], FLEET_MODE, table_dir)
    nominal = rr.observe(bench.base[0])
    n_inc = rr.n_increments
    rows = []
    for name in causes:
        cause = ALL_CAUSES[name]
        grid = GRIDS[name]
        if isinstance(bench, LeanBench):
            deltas = []
            for value in grid:          # one value's tables at a time
                deltas += cause.deltas(bench, bench.base, [value])
                bench.drop_modified()
        else:
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
