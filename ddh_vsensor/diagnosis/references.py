"""Runs without a position sensor: the Hall reference edges and the holds are the truth.

At each accepted edge of a switch the rod's position is known (the switching position for the
direction of travel, :class:`estimator.references.Switch`); in service the estimator resyncs
there, so the error it shows at an edge is the integral of every cause over the travel since
the previous edge. The diagnosis therefore observes, per run, the *increments* of the
estimate's error from edge to edge, and per hold the creep of the estimate (mm over
:data:`HOLD_WEIGHT_S`, truth 0 within what holding the rod lets it move: see :mod:`.holds`).
Both are linear in the estimate, so a cause's change of the estimate maps to a change of the
observations exactly.

A run is cut to start at its first usable edge (the estimate starts there, at the known
position); ``position_mm`` of the cut run holds the edge positions and NaN elsewhere.
"""

from __future__ import annotations

from dataclasses import dataclass
import numpy as np

from ddh_vsensor.config import Config
from ddh_vsensor.estimator.estimator import Estimator
from ddh_vsensor.estimator.references import (DIRECTION_SPEED_MM_S, accepted_edges,
                                    share_after_crossing, switches_from_config)
from ddh_vsensor.measured import MeasuredDataError, Run
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.tables.build import build_unit_tables
from ddh_vsensor.tables.lookup import UnitTables
from ddh_vsensor.diagnosis.holds import Hold, describe_holds, find_holds
from ddh_vsensor.diagnosis.runs import AnalysisRun

# A hold's creep rate counts as the mm it would creep in this long. A hold's truth is not
# exactly 0: the loop that holds the rod (the operator's, a controller's) lets it move while it
# settles, and the speed comes in whole rpm (1 rpm is 5-30 % of a holding speed). On trials
# without any effect the bucket's true rod moved 0.1-0.46 mm within 6-9 s holds; at 10 s a
# hold erred 0.14-0.85 mm RMS against 0.03-0.10 mm for the increments and carried the fits (a
# bucket displacement of 1.035 fitted 1.043). At 1 s the two err alike.
HOLD_WEIGHT_S = 1.0
MIN_EDGES = 3                # two increments at least: one edge starts, the others observe


@dataclass(frozen=True, eq=False)
class ReferenceRun:
    """A run seen through its references and holds (cut at its first usable edge)."""

    run: AnalysisRun
    edges: np.ndarray            # sample index of each used edge (the first is 0)
    edge_mm: np.ndarray          # the rod's position there
    switch: tuple[str, ...]
    rising: np.ndarray
    holds: tuple[Hold, ...]
    # each edge position's variance (mm²): 0 where the switch's change is timed, else the
    # rod's travel over the sample, uniform: (v dt)² / 12
    edge_var_mm2: np.ndarray

    @property
    def name(self) -> str:
        return self.run.name

    def observe(self, position_mm: np.ndarray) -> np.ndarray:
        """Error increments from edge to edge (mm), then each hold's creep (mm)."""
        err = position_mm[self.edges] - self.edge_mm
        inc = np.diff(err)
        creep = [(position_mm[h.stop] - position_mm[h.start]) / h.duration_s * HOLD_WEIGHT_S
                 for h in self.holds]
        return np.concatenate([inc, np.asarray(creep, dtype=float)])

    def observe_delta(self, delta_mm: np.ndarray) -> np.ndarray:
        """The observations' change for a change of the estimate (the map is linear)."""
        inc = np.diff(delta_mm[self.edges])
        creep = [(delta_mm[h.stop] - delta_mm[h.start]) / h.duration_s * HOLD_WEIGHT_S
                 for h in self.holds]
        return np.concatenate([inc, np.asarray(creep, dtype=float)])

    @property
    def n_increments(self) -> int:
        return len(self.edges) - 1

    def increment_var_mm2(self) -> np.ndarray:
        """Each increment's variance from its two edges' positions alone."""
        return self.edge_var_mm2[1:] + self.edge_var_mm2[:-1]


_TABLES: dict[tuple[int, str], tuple[Config, UnitTables]] = {}


def _nominal_tables(cfg: Config, actuator: str) -> UnitTables:
    """Per config object (held, so its id stays its own) and actuator, built once."""
    key = (id(cfg), actuator)
    if key not in _TABLES:
        _TABLES[key] = (cfg, build_unit_tables(cfg, actuator,
                                               DDHUnit.from_config(cfg, actuator)))
    return _TABLES[key][1]


# Holds this close to an end of the stroke (mm, beyond the estimator's soft limit) are left out.
END_HOLD_MARGIN_MM = 5.0


def nominal_velocity_mm_s(cfg: Config, actuator: str, run: Run) -> np.ndarray:
    """The nominal model's velocity at each sample (position-free: direction and holds; the
    chamber model of `dynamic` mode meets no end stop while its position is unknown)."""
    est = Estimator(cfg, actuator, _nominal_tables(cfg, actuator), references=False,
                    adaptation=False)
    return est.run(run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c).velocity_mm_s


def _check(run: Run) -> None:
    for name in ("time_s", "speed_rpm", "torque_nm", "oil_temp_c"):
        bad = ~np.isfinite(getattr(run, name))
        if bad.any():
            raise MeasuredDataError(run.source, f"column {name!r}: missing value at row "
                                    f"{int(np.argmax(bad)) + 1}")
    step = np.diff(run.time_s)
    if (step <= 0.0).any():
        row = int(np.argmax(step <= 0.0)) + 1
        raise MeasuredDataError(run.source, f"time_s does not increase at row {row + 1}")


def edge_events(cfg: Config, actuator: str, run: Run,
                velocity_mm_s: np.ndarray) -> list[tuple[int, str, bool, float, float]]:
    """(sample, switch, rising, rod position mm, its variance mm²) of every edge met in
    motion, in time order.

    The state changes at the first sample past the switching position, so the position there
    is the switching position plus the travel since the crossing: since the change's own
    time where the log has it (:attr:`Run.ref_edge_s`), else half a sample period, the
    crossing's mean time within it.
    """
    t = run.time_s
    out = []
    for sw in switches_from_config(cfg.unit(actuator)):
        if sw.name not in run.refs:
            continue
        timed = run.ref_edge_s.get(sw.name)
        for _, c, rising in accepted_edges(t, run.refs[sw.name], cfg.estimator.debounce_s):
            v = float(velocity_mm_s[c])
            if c == 0 or abs(v) < DIRECTION_SPEED_MM_S:
                continue                          # direction unknown: the edge says nothing
            dt = float(t[c] - t[c - 1])
            since_s = share_after_crossing(t, timed, c) * dt
            x = sw.switching_position_mm(rising, v > 0) + v * since_s
            at_its_time = timed is not None and t[c - 1] < timed[c] <= t[c]
            out.append((int(c), sw.name, bool(rising), x,
                        0.0 if at_its_time else (v * dt) ** 2 / 12.0))
    out.sort()
    return out


def _off_the_ends(cfg: Config, actuator: str, time_s: np.ndarray, velocity_mm_s: np.ndarray,
                  edges: np.ndarray, edge_mm: np.ndarray,
                  holds: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """The holds not at an end of the stroke. There the end stop may be what holds the rod,
    and the estimate, bounded at the stroke's ends, stops creeping into it whatever the
    leakage: a log's leakage fit then found its best where the replay ran into the stop
    (x4-6 for x1.1). Where a hold is, from the nominal travel since the edge before it."""
    ucfg = cfg.unit(actuator)
    margin = END_HOLD_MARGIN_MM + cfg.estimator.soft_limit_margin_mm
    travel = np.concatenate([[0.0], np.cumsum(0.5 * (velocity_mm_s[1:] + velocity_mm_s[:-1])
                                              * np.diff(time_s))])
    out = []
    for first, last in holds:
        j = int(np.searchsorted(edges, first, "right")) - 1
        x = edge_mm[j] + travel[first] - travel[edges[j]]
        if margin <= x <= ucfg.stroke_mm - margin:
            out.append((first, last))
    return out


def reference_run(cfg: Config, actuator: str, run: Run, *,
                  model_speeds: bool = True) -> ReferenceRun:
    """The run's usable edges and holds; MeasuredDataError when there are too few edges.
    ``model_speeds=False`` leaves the holds' modelled speeds NaN (the fit uses the creep)."""
    _check(run)
    velocity = nominal_velocity_mm_s(cfg, actuator, run)
    events = edge_events(cfg, actuator, run, velocity)
    if len(events) < MIN_EDGES:
        raise MeasuredDataError(run.source, f"{len(events)} reference edge(s) met in motion; "
                                f"the analysis from references needs at least {MIN_EDGES} "
                                "(the rod must pass the Hall switches)")
    first = events[0][0]
    idx = np.array([e[0] for e in events]) - first
    keep = np.concatenate([[True], np.diff(idx) > 0])          # one edge per sample
    idx = idx[keep]
    edge_mm = np.array([e[3] for e in events])[keep]
    cut = slice(first, None)
    position = np.full(len(run.time_s) - first, np.nan)
    position[idx] = edge_mm
    arun = AnalysisRun(name=run.source, time_s=run.time_s[cut].astype(float),
                       speed_rpm=run.speed_rpm[cut].astype(float),
                       torque_nm=run.torque_nm[cut].astype(float),
                       oil_temp_c=run.oil_temp_c[cut].astype(float), position_mm=position)
    ranges = _off_the_ends(cfg, actuator, arun.time_s, velocity[cut], idx, edge_mm,
                           find_holds(arun.time_s, arun.speed_rpm, velocity[cut], idx))
    unit = DDHUnit.from_config(cfg, actuator) if model_speeds else None
    holds = describe_holds(unit, arun.time_s, arun.speed_rpm,
                           arun.torque_nm, arun.oil_temp_c, ranges)
    return ReferenceRun(arun, idx, edge_mm, tuple(e[1] for e, k in zip(events, keep) if k),
                        np.array([e[2] for e, k in zip(events, keep) if k]), tuple(holds),
                        np.array([e[4] for e in events])[keep])
