"""Hall switches' switching points, measured on runs with the draw-wire position still fitted.

Each accepted edge (:func:`~ddh_vsensor.estimator.references.accepted_edges`, the configured
debounce) is placed at the rod's true position at the edge's time: the I/O module's timing
(:attr:`.Run.ref_edge_s`) where the log has it, else the middle of the edge sample's period.
The position is the draw-wire's, linear between its samples; that interpolation errs by at most
``|a| dt^2 / 8`` (``a`` the acceleration, ``dt`` the position's sample period), taken per edge as
the largest second difference of the samples around it over 8 (noise included, so an upper
bound). An edge without its own time adds half the travel over its sample's period.

Edges are classified by kind (rising: the switch came on; falling: it went off) and by the
direction of travel, giving up to four switching positions per switch. The configuration's
model has one position ``p`` per switch and ONE window ``w`` and hysteresis ``h`` per unit
(what :func:`~ddh_vsensor.estimator.references.switches_from_config` gives the estimator):
``p`` per switch and the common ``w``, ``h`` are fitted by least squares to the measured means
(weighted by their counts); whichever of ``w``, ``h`` the measured kinds cannot tell apart from
the positions keeps its configured value. The per-switch scatter of the real ``w``, ``h`` about
the common ones is what the fitted model misses: the calibrated tolerance is the largest
residual of the model at a measured mean plus ``k`` times that kind's spread (default k = 3).
A switch is calibrated only when every kind its place on the stroke lets the rod make was
seen at least :data:`MIN_EDGES` times; otherwise its position stays as configured, and so do
the window, hysteresis and tolerance it shares with the unit's other switches (those get their
positions fitted with them), and the reason says which run would calibrate it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ddh_vsensor.config import UnitConfig
from ddh_vsensor.estimator.references import (DIRECTION_SPEED_MM_S, Switch, accepted_edges,
                                              switches_from_config)
from ddh_vsensor.measured import Run

MIN_EDGES = 3               # per kind: a spread needs a few, the programme crosses a few times
SPREAD_FACTOR = 3.0         # k: the tolerance covers the residual plus k standard deviations
DIRECTION_SPAN_S = 0.1      # the direction of travel from the position change over this span
DECIMALS = 2                # written to 0.01 mm; the residuals are those of the rounded values

# (rising, moving_up): how the switch changed, in words
KINDS: tuple[tuple[bool, bool], ...] = ((True, True), (True, False), (False, True),
                                        (False, False))
KIND_WORDS = {(True, True): "entered from below", (True, False): "entered from above",
              (False, True): "left upwards", (False, False): "left downwards"}
KIND_KEYS = {(True, True): "rising_up", (True, False): "rising_down",
             (False, True): "falling_up", (False, False): "falling_down"}


@dataclass(frozen=True)
class Edge:
    """One accepted edge at the rod's true position."""

    source: str
    time_s: float
    position_mm: float
    rising: bool
    moving_up: bool
    velocity_mm_s: float
    bound_mm: float         # interpolation (and, untimed, sample-period) error bound
    timed: bool             # the I/O module's own time of the change


@dataclass(frozen=True)
class KindStats:
    rising: bool
    moving_up: bool
    count: int
    mean_mm: float
    spread_mm: float        # standard deviation of the edges (ddof 1; NaN below two edges)
    configured_mm: float    # the datasheet's switching position of this kind
    fitted_mm: float = math.nan     # the calibrated model's, where the switch is calibrated

    @property
    def key(self) -> str:
        return KIND_KEYS[(self.rising, self.moving_up)]


@dataclass
class SwitchCalibration:
    name: str
    configured_mm: float
    edges: list[Edge]
    kinds: dict[tuple[bool, bool], KindStats]
    required: tuple[tuple[bool, bool], ...]     # the kinds the stroke lets the rod make
    problem: str | None = None                  # why it is not calibrated
    position_mm: float = math.nan               # the calibrated p
    tolerance_mm: float = math.nan              # its kinds' largest residual + k spread

    @property
    def calibrated(self) -> bool:
        return self.problem is None


@dataclass
class UnitCalibration:
    unit: str
    switches: dict[str, SwitchCalibration]
    configured_window_mm: float
    configured_hysteresis_mm: float
    configured_tolerance_mm: float
    window_mm: float
    hysteresis_mm: float
    tolerance_mm: float
    fitted: tuple[str, ...]                     # of "window", "hysteresis": fitted, not kept
    max_residual_mm: float = math.nan
    max_spread_mm: float = math.nan
    max_bound_mm: float = math.nan
    standstill_edges: int = 0                   # too slow for a direction: not used
    notes: list[str] = field(default_factory=list)

    @property
    def calibrated(self) -> list[str]:
        return [s.name for s in self.switches.values() if s.calibrated]

    @property
    def problems(self) -> list[str]:
        return [s.problem for s in self.switches.values() if s.problem]


def _interp_bound(tp: np.ndarray, xp: np.ndarray, j: int) -> float:
    """Linear interpolation's error bound on the position sample interval [j-1, j]: the
    largest neighbouring second difference over 8 (|a| dt^2 / 8)."""
    d2 = [abs(xp[i + 1] - 2.0 * xp[i] + xp[i - 1]) for i in (j - 1, j)
          if 1 <= i < len(xp) - 1]
    return max(d2, default=0.0) / 8.0


def run_edges(run: Run, name: str, debounce_s: float) -> tuple[list[Edge], int]:
    """The edges of one switch in one run at the true position, and how many were too slow
    to tell their direction of travel (not used)."""
    have = np.isfinite(run.position_mm)
    tp, xp = run.time_s[have], run.position_mm[have]
    if name not in run.refs or len(tp) < 2:
        return [], 0
    t = run.time_s
    timed_s = run.ref_edge_s.get(name)
    edges, slow = [], 0
    for _, k, rising in accepted_edges(t, run.refs[name], debounce_s):
        timed = timed_s is not None and bool(np.isfinite(timed_s[k]))
        te = float(timed_s[k]) if timed else 0.5 * (t[k - 1] + t[k])
        if not tp[0] <= te <= tp[-1]:
            continue
        x = float(np.interp(te, tp, xp))
        lo, hi = max(te - DIRECTION_SPAN_S / 2, tp[0]), min(te + DIRECTION_SPAN_S / 2, tp[-1])
        v = float((np.interp(hi, tp, xp) - np.interp(lo, tp, xp)) / (hi - lo)) if hi > lo else 0.0
        if abs(v) < DIRECTION_SPEED_MM_S:
            slow += 1
            continue
        j = int(np.clip(np.searchsorted(tp, te), 1, len(tp) - 1))
        bound = _interp_bound(tp, xp, j)
        if not timed:
            bound += 0.5 * abs(float(np.interp(t[k], tp, xp) - np.interp(t[k - 1], tp, xp)))
        edges.append(Edge(run.source, te, x, bool(rising), v > 0, v, bound, timed))
    return edges, slow


def required_kinds(sw: Switch, stroke_mm: float) -> tuple[tuple[bool, bool], ...]:
    """The kinds the rod can make at this switch: coming on from below and going off
    downwards need room below its off-zone (within the stroke, with the mounting tolerance
    to spare), from above and upwards room above it."""
    reach = sw.window_mm + sw.hysteresis_mm + sw.tolerance_mm
    below, above = sw.position_mm - reach > 0.0, sw.position_mm + reach < stroke_mm
    return tuple(k for k in KINDS if (below if k[0] == k[1] else above))


def _stats(edges: list[Edge], kind: tuple[bool, bool], sw: Switch) -> KindStats:
    x = np.array([e.position_mm for e in edges if (e.rising, e.moving_up) == kind])
    spread = float(np.std(x, ddof=1)) if len(x) > 1 else math.nan
    return KindStats(kind[0], kind[1], len(x), float(np.mean(x)) if len(x) else math.nan,
                     spread, sw.switching_position_mm(*kind))


def _advice(unit: str, sw: Switch, required: tuple[tuple[bool, bool], ...]) -> str:
    if len(required) == 4:
        return f"run the {unit} through {sw.position_mm:g} mm up and down"
    if required and required[0][0] == required[0][1]:      # room only below: the top end
        return f"run the {unit} to its top end and back"
    return f"run the {unit} to its bottom end and back"


def _coefficients(kind: tuple[bool, bool]) -> tuple[float, float]:
    """A kind's switching position as p + a w + b h: (a, b)."""
    return {(True, True): (-1.0, 0.0), (True, False): (1.0, 0.0),
            (False, True): (1.0, 1.0), (False, False): (-1.0, -1.0)}[kind]


def _fit(unit_cfg: UnitConfig, switches: list[SwitchCalibration], shared: bool
         ) -> tuple[dict[str, float], float, float, tuple[str, ...]]:
    """Weighted least squares of p per switch and, where ``shared`` (every switch of the
    unit is measured), the common w, h on the measured means; w and/or h stay configured
    where the measured kinds cannot separate them from the positions."""
    rows = [(i, s.kinds[k]) for i, s in enumerate(switches) for k in KINDS
            if s.kinds[k].count]
    n = len(switches)
    a = np.zeros((len(rows), n + 2))
    y = np.array([st.mean_mm for _, st in rows])
    wt = np.sqrt([float(st.count) for _, st in rows])
    for r, (i, st) in enumerate(rows):
        a[r, i] = 1.0
        a[r, n:] = _coefficients((st.rising, st.moving_up))
    fixed = np.array([unit_cfg.reference_window_mm, unit_cfg.reference_hysteresis_mm])
    for free in ((0, 1), (1,), (0,), ()) if shared else ((),):
        cols = [*range(n), *(n + f for f in free)]
        m = a[:, cols] * wt[:, None]
        if np.linalg.matrix_rank(m) < len(cols):
            continue
        kept = [f for f in (0, 1) if f not in free]
        rhs = (y - a[:, [n + f for f in kept]] @ fixed[kept]) * wt
        sol = np.linalg.lstsq(m, rhs, rcond=None)[0]
        wh = fixed.copy()
        for f, value in zip(free, sol[n:]):
            wh[f] = value
        names = tuple(("window", "hysteresis")[f] for f in free)
        return {s.name: float(sol[i]) for i, s in enumerate(switches)}, float(wh[0]), \
            float(wh[1]), names
    raise AssertionError("the positions alone are always determined")   # pragma: no cover


def calibrate_unit(unit: str, unit_cfg: UnitConfig, runs: Sequence[Run], debounce_s: float,
                   spread_factor: float = SPREAD_FACTOR) -> UnitCalibration:
    """Every switch of one unit from its runs (each with its position)."""
    configured = {s.name: s for s in switches_from_config(unit_cfg)}
    result = UnitCalibration(unit, {}, unit_cfg.reference_window_mm,
                             unit_cfg.reference_hysteresis_mm, unit_cfg.reference_tolerance_mm,
                             unit_cfg.reference_window_mm, unit_cfg.reference_hysteresis_mm,
                             unit_cfg.reference_tolerance_mm, ())
    for name, sw in configured.items():
        edges: list[Edge] = []
        for run in runs:
            found, slow = run_edges(run, name, debounce_s)
            edges += found
            result.standstill_edges += slow
        kinds = {k: _stats(edges, k, sw) for k in KINDS}
        required = required_kinds(sw, unit_cfg.stroke_mm)
        cal = SwitchCalibration(name, sw.position_mm, edges, kinds, required)
        missing = [k for k in required if kinds[k].count < MIN_EDGES]
        if not edges:
            cal.problem = (f"the {name} switch never switched: "
                           f"{_advice(unit, sw, required)}, a few times")
        elif missing:
            seen = ", ".join(f"{KIND_WORDS[k]} only {kinds[k].count} times" if kinds[k].count
                             else f"never {KIND_WORDS[k]}" for k in missing)
            cal.problem = (f"the {name} switch was {seen} (at least {MIN_EDGES} times each "
                           f"needed): "
                           f"{_advice(unit, sw, required)}, a few times")
        result.switches[name] = cal
    good = [s for s in result.switches.values() if s.calibrated]
    if not good:
        return result
    everyone = len(good) == len(result.switches)
    positions, w, h, result.fitted = _fit(unit_cfg, good, everyone)
    # within the schema's bounds (a window, a hysteresis not below nothing): the residual
    # shows what that costs
    w, h = max(round(w, DECIMALS), 10.0 ** -DECIMALS), max(round(h, DECIMALS), 0.0)
    result.window_mm, result.hysteresis_mm = w, h
    residual, spread, bound = 0.0, 0.0, 0.0
    for s in good:
        # the schema keeps a switch within the stroke; what that costs shows as residual
        s.position_mm = round(float(np.clip(positions[s.name], 0.0, unit_cfg.stroke_mm)),
                              DECIMALS)
        s.tolerance_mm = 0.0
        model = Switch(s.name, s.position_mm, w, h)
        for k, st in s.kinds.items():
            if not st.count:
                continue
            fitted = model.switching_position_mm(*k)
            s.kinds[k] = KindStats(st.rising, st.moving_up, st.count, st.mean_mm, st.spread_mm,
                                   st.configured_mm, fitted)
            sd = 0.0 if math.isnan(st.spread_mm) else st.spread_mm
            residual, spread = max(residual, abs(fitted - st.mean_mm)), max(spread, sd)
            s.tolerance_mm = max(s.tolerance_mm, abs(fitted - st.mean_mm) + spread_factor * sd)
        bound = max(bound, max(e.bound_mm for e in s.edges))
    tolerance = math.ceil(max(s.tolerance_mm for s in good) * 10 ** DECIMALS) / 10 ** DECIMALS
    result.max_residual_mm, result.max_spread_mm, result.max_bound_mm = residual, spread, bound
    if everyone:
        result.tolerance_mm = tolerance
    else:
        result.notes.append(f"window, hysteresis and tolerance kept as configured: they are "
                            f"shared with a switch not calibrated (the others' residuals "
                            f"with them: {tolerance:.2f} mm)")
    return result
