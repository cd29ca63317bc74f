"""The estimator over a set of runs, as the diagnosis varies its model.

Every candidate cause is judged by the estimate it produces, so this runs the project's own
``Estimator`` (offline face, no references, no adaptation, from each run's first reference
position) with modified tables or inputs. Tables are built only over the oil temperatures the
runs reach (the same grid nodes, so the lookups are those of the full tables), which makes a
table set of a modified unit cost about 10 ms.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from ..config import Config
from ..estimator.estimator import Estimator
from ..physics.unit import DDHUnit
from ..tables.build import build_unit_tables
from ..tables.lookup import UnitTables
from ..estimator.chambers import ChamberRow, track_chambers
from .inertia import with_inertia_compensation
from .runs import AnalysisRun


def _table_config(cfg: Config, runs: Sequence[AnalysisRun]) -> Config:
    """The config with its table temperatures cut to the runs' range (same grid nodes)."""
    t0, t1, dt = cfg.tables.temperatures_c
    last = round((t1 - t0) / dt)
    lo = min(float(np.min(r.oil_temp_c)) for r in runs)
    hi = max(float(np.max(r.oil_temp_c)) for r in runs)
    k0 = min(max(0, math.floor((lo - t0) / dt)), last - 1)
    k1 = min(max(k0 + 1, math.ceil((hi - t0) / dt)), last)
    temps = (t0 + k0 * dt, t0 + k1 * dt, dt)
    return dataclasses.replace(cfg, tables=dataclasses.replace(cfg.tables, temperatures_c=temps))


class Workbench:
    """Runs of one actuator and the estimator to replay them with."""

    def __init__(self, cfg: Config, actuator: str, runs: Sequence[AnalysisRun],
                 mode: str, inertia: bool | None = None) -> None:
        """``inertia``: feed the estimator the pump torque (motor torque less the motor's
        inertia torque, :mod:`.inertia`); None decides from the runs (below)."""
        self.cfg, self.actuator, self.runs, self.mode = cfg, actuator, list(runs), mode
        self._cfg_inertia = {flag: with_inertia_compensation(cfg, flag) for flag in (False, True)}
        self.unit = DDHUnit.from_config(cfg, actuator)
        self.table_cfg = _table_config(cfg, self.runs)
        self.nominal_tables = self.tables(self.unit)
        self.reference = [r.position_mm for r in self.runs]
        self.masks = [r.mask for r in self.runs]
        self.inertia = False
        self.as_is = self.estimate()                          # the estimator as it stands
        self.full_as_is = self.as_is if mode == "full" else self.estimate(mode="full")
        self.inertia = True
        self.with_inertia = self.estimate()
        self.full_with_inertia = (self.with_inertia if mode == "full"
                                  else self.estimate(mode="full"))
        if inertia is None:
            # Parameter-free, so judged on all runs: kept if it lowers the error of the
            # speed-continuous tables (in paper mode their low-speed error would dominate).
            inertia = self.sse(self.full_with_inertia) < self.sse(self.full_as_is)
        self.default_inertia = bool(inertia)
        self.use(self.default_inertia)
        self._chamber_cache: dict[float, list[np.ndarray]] = {}

    def use(self, inertia: bool) -> None:
        """Evaluate with (or without) the motor's inertia taken off the motor torque."""
        self.inertia = bool(inertia)
        self.base = self.with_inertia if self.inertia else self.as_is     # the model
        self.full_estimate = self.full_with_inertia if self.inertia else self.full_as_is

    def sse(self, estimates: Sequence[np.ndarray]) -> float:
        """Squared error against the references, each run weighted by its duration."""
        total = 0.0
        for x, r, m in zip(estimates, self.runs, self.masks):
            e = (x - r.position_mm)[m]
            total += r.duration_s * float(np.dot(e, e)) / max(len(e), 1)
        return total

    @property
    def nominal_chambers(self) -> list[np.ndarray]:
        """The compressible-chamber model with nominal oil (no air), per run."""
        return self.chambers([0.0])[0]

    def tables(self, unit: DDHUnit) -> UnitTables:
        return build_unit_tables(self.table_cfg, self.actuator, unit)

    def estimate(self, tables: UnitTables | None = None, mode: str | None = None,
                 speed_rpm: Sequence[np.ndarray] | None = None,
                 time_shift_s: float = 0.0) -> list[np.ndarray]:
        """Position estimate (mm) of every run with the given tables, mode and inputs.

        ``time_shift_s`` feeds the estimator the motor signals that many seconds later
        (logged speed and torque lagging the position by that much, undone).
        """
        tables = tables or self.nominal_tables
        out = []
        for i, r in enumerate(self.runs):
            n = r.speed_rpm if speed_rpm is None else speed_rpm[i]
            motor, tau = r.speed_rpm, r.torque_nm
            if time_shift_s:
                n, motor, tau = (shift_signal(r.time_s, s, time_shift_s)
                                 for s in (n, motor, tau))
            est = Estimator(self._cfg_inertia[self.inertia], self.actuator, tables,
                            mode=mode or self.mode,
                            references=False, adaptation=False,
                            initial_position_mm=r.initial_position_mm)
            out.append(est.run(r.time_s, n, tau, r.oil_temp_c).position_mm)
        return out

    def chambers(self, air_fractions: Sequence[float]) -> list[list[np.ndarray]]:
        """Compressible-chamber positions (mm): [air fraction][run] (cached)."""
        todo = sorted({float(x) for x in air_fractions} - set(self._chamber_cache))
        if todo:
            rows = [ChamberRow(r.time_s, r.speed_rpm, r.torque_nm, r.oil_temp_c,
                               r.initial_position_mm, x) for x in todo for r in self.runs]
            tracks = track_chambers(self.unit, rows, max_gap_s=self.cfg.estimator.max_gap_s)
            k = len(self.runs)
            for j, x in enumerate(todo):
                self._chamber_cache[x] = [tr.position_mm for tr in tracks[j * k:(j + 1) * k]]
        return [self._chamber_cache[float(x)] for x in air_fractions]


def shift_signal(time_s: np.ndarray, signal: np.ndarray, shift_s: float) -> np.ndarray:
    """The signal ``shift_s`` seconds later, by linear interpolation (held at the ends)."""
    return np.interp(time_s + shift_s, time_s, signal)
