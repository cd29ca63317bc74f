"""Trends and alarms: per machine and unit, each cause's parameter log by log with its
interval, the cause that explains the references across days, the expected position error
now and where the parameter's trend takes it.

Per log and cause (rows of the fleet analysis, or of a day's summary): the parameter
minimising the loss of the observations (squared error, linear beyond
:data:`diagnosis.evidence.ROBUST_MM`; a parabola through the best grid point and its
neighbours, on a log scale for factors) and a 90 % profile interval (loss within
F(1, n-1)/(n-1) of the best).
Across the last :data:`WINDOW` logs the cause is judged held out, day by day: each log's
parameter is predicted by the linear trend fitted to the *other* logs, and the score is the
share of the references' loss that prediction removes (minus a penalty per trend
parameter). The loss at a predicted parameter is read between the log's grid nodes along a
parabola: an error linear in the parameter has a squared loss that is one, and a straight
line between two nodes overstates it there (on the coarse grid near neutral, enough to hold
a young wear's score below zero for days). The best cause is named when it scores
:data:`MIN_SCORE` or more (the position-truth analysis's threshold).

The expected position error of a parameter value is the largest change it makes to an
edge-to-edge increment on the unit's recent work (median over the last three logs; linear
beyond the grid). The cause judged for an alarm is, of those scoring at least
:data:`TREND_SCORE` whose trend is significant (slope at :data:`SLOPE_T`; the line weighs
each log by its interval and the day-to-day scatter, see :func:`_line`), the one whose slope
adds most to its score over a constant (what wears is what changes: a cause that explains
the machine's constant deviation may also follow a wear it stands in for, but its slope adds
little); where none trends, the best-scoring. An alarm is raised when that cause's trend
takes that error past the tolerance within the horizon (beyond the days the trend was fitted
on at the slope's conservative bound, :data:`EXTRAPOLATION_SE` standard errors nearer zero:
a week of logs says how fast a parameter moves over that week, no more), or when a named
cause has it there already. An alarm, once raised, holds for :data:`HOLD_DAYS` (with the
figures of the day it was last raised) unless the evidence raises it again: a trend near the
tolerance's horizon is judged over and over on noisy days, and a warning that comes and goes
with them reads as noise to whoever acts on it (alarm management's off-delay). A trend is
caught while the error is still small against the nominal model's own ~1 mm at the
references, so its cause cannot yet explain the :data:`MIN_SCORE` share that naming a cause
asks for; the significant slope, the positive held-out score and the projected error
together do.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy.stats import f as f_dist

from ddh_vsensor.diagnosis.causes import ALL_CAUSES
from ddh_vsensor.diagnosis.selection import MIN_SCORE

WINDOW = 10                     # logs the naming and the trend look back over
MIN_LOGS = 7                    # a week of daily logs before anything is named
SLOPE_T = 4.0                   # |slope| / its standard error for a trend to count
EXTRAPOLATION_SE = 2.0          # beyond its days, a trend goes on at |slope| - this x its se
TREND_SCORE = 0.05              # held-out score a trending cause needs for an alarm
HOLD_DAYS = 3                   # an alarm holds this many days after the evidence raised it
PENALTY_PER_PARAMETER = 0.02
LEVEL = 0.90
DAY_S = 86400.0


@dataclass
class LogFit:
    time_s: float
    log_id: str
    u: float                    # best parameter (log scale for factors)
    lo_u: float
    hi_u: float
    grid_u: np.ndarray
    loss: np.ndarray
    emax_mm: np.ndarray
    loss_nominal: float
    max_increment_mm: float
    censored: bool = False      # best at a grid end: the parameter is there or beyond


@dataclass
class Alarm:
    time_s: float
    cause: str
    value: float
    error_now_mm: float
    error_projected_mm: float
    crossing_time_s: float | None


@dataclass
class UnitTrend:
    machine: str
    actuator: str
    times_s: list[float] = field(default_factory=list)
    series: dict[str, list[LogFit]] = field(default_factory=dict)
    named: list[str] = field(default_factory=list)            # per log: cause or none
    scores: list[dict[str, float]] = field(default_factory=list)
    error_now_mm: list[float] = field(default_factory=list)
    error_projected_mm: list[float] = field(default_factory=list)
    reference_error_mm: list[float] = field(default_factory=list)   # nominal, per log
    alarms: list[Alarm | None] = field(default_factory=list)

    @property
    def first_alarm(self) -> Alarm | None:
        return next((a for a in self.alarms if a is not None), None)

    def value(self, cause: str, fit: LogFit) -> float:
        return from_u(cause, fit.u)


def to_u(cause: str, v):
    return np.log(v) if ALL_CAUSES[cause].log else np.asarray(v, float)


def from_u(cause: str, u):
    return float(np.exp(u)) if ALL_CAUSES[cause].log else float(u)


def _interp(x: float, xs: np.ndarray, ys: np.ndarray) -> float:
    """Piecewise linear, extended linearly beyond the ends."""
    if x <= xs[0]:
        k = 0
    elif x >= xs[-1]:
        k = len(xs) - 2
    else:
        return float(np.interp(x, xs, ys))
    return float(ys[k] + (ys[k + 1] - ys[k]) * (x - xs[k]) / (xs[k + 1] - xs[k]))


def _interp_loss(x: float, xs: np.ndarray, ys: np.ndarray) -> float:
    """A loss between its grid nodes: the parabola through the node pair around ``x`` and
    the next node on the nearer side (an error linear in the parameter makes its squared
    loss a parabola, which a straight line between nodes overstates between them by up to
    a quarter of the nodes' spacing squared times its curvature); beyond the grid, linear."""
    n = len(xs)
    if n < 3 or x <= xs[0] or x >= xs[-1]:
        return _interp(x, xs, ys)
    k = int(np.searchsorted(xs, x)) - 1                 # xs[k] < x <= xs[k + 1]
    near_left = x - xs[k] < xs[k + 1] - x
    j = k - 1 if (near_left and k > 0) or k + 2 >= n else k
    x0, x1, x2 = xs[j], xs[j + 1], xs[j + 2]
    y0, y1, y2 = ys[j], ys[j + 1], ys[j + 2]
    return float(y0 * (x - x1) * (x - x2) / ((x0 - x1) * (x0 - x2))
                 + y1 * (x - x0) * (x - x2) / ((x1 - x0) * (x1 - x2))
                 + y2 * (x - x0) * (x - x1) / ((x2 - x0) * (x2 - x1)))


def log_fit(cause: str, row: dict) -> LogFit:
    g = to_u(cause, np.asarray(row["grid"], float))
    loss = np.asarray(row["loss"], float)
    k = int(np.argmin(loss))
    u = float(g[k])
    if 0 < k < len(g) - 1:
        x, y = g[k - 1:k + 2], loss[k - 1:k + 2]
        a, b, _ = np.polyfit(x, y, 2)
        if a > 0:
            u = float(np.clip(-b / (2 * a), x[0], x[-1]))
    n = max(int(row["n_obs"]), 2)
    smin = float(np.min(loss))
    limit = smin * (1.0 + f_dist.ppf(LEVEL, 1, n - 1) / (n - 1))
    inside = np.flatnonzero(loss <= limit)
    lo_k, hi_k = int(inside.min()), int(inside.max())
    lo = g[lo_k] if lo_k == 0 else _cross(g, loss, lo_k - 1, lo_k, limit)
    hi = g[hi_k] if hi_k == len(g) - 1 else _cross(g, loss, hi_k, hi_k + 1, limit)
    # best at a grid end that is no bound of the parameter: it lies there or beyond
    neutral = ALL_CAUSES[cause].neutral
    censored = k in (0, len(g) - 1) and (
        neutral is None or not np.isclose(g[k], float(to_u(cause, neutral))))
    return LogFit(float(row["time_s"]), row["log_id"], u, float(min(lo, u)), float(max(hi, u)),
                  g, loss, np.asarray(row["emax_mm"], float), float(row["loss_nominal"]),
                  float(row["max_increment_mm"]), censored)


def _cross(g, s, i, j, level) -> float:
    return float(g[i] + (g[j] - g[i]) * (level - s[i]) / (s[j] - s[i]))


def _line(t: np.ndarray, u: np.ndarray, var: np.ndarray) -> tuple[float, float, float]:
    """Weighted least-squares line u = a + b t: (a, b, standard error of b).

    Each log weighs 1 / (its own variance + the day-to-day variance): a log's interval says
    how well its own references fix the parameter, not how far one day's work takes the fit
    from the next (the day's moves, payload, oil); that scatter is estimated from the logs
    themselves (DerSimonian-Laird, for a line), so no single tight log carries the trend.
    The slope's error is then scaled by the weighted residuals (Knapp-Hartung)."""
    v = np.asarray(var, float)
    known = np.isfinite(v)                  # a censored log has no place on the line
    if not known.any():
        return float(np.median(u)), 0.0, float("inf")
    t, u, v = t[known], u[known], v[known]
    n = len(t)
    if n < 2 or np.ptp(t) == 0:
        return float(np.average(u, weights=1.0 / v)), 0.0, float("inf")
    x = np.column_stack([np.ones(n), t])
    if n > 2:
        w = 1.0 / v
        xtwx_inv = np.linalg.inv(x.T @ (w[:, None] * x))
        res = u - x @ (xtwx_inv @ (x.T @ (w * u)))
        q = float(np.sum(w * res ** 2))
        trace = float(np.sum(w) - np.trace(xtwx_inv @ (x.T @ ((w ** 2)[:, None] * x))))
        v = v + max(0.0, (q - (n - 2)) / trace)
    w = 1.0 / v
    tm = float(np.average(t, weights=w))
    um = float(np.average(u, weights=w))
    sxx = float(np.sum(w * (t - tm) ** 2))
    b = float(np.sum(w * (t - tm) * (u - um))) / sxx
    a = um - b * tm
    if n < 3:
        return a, b, float("inf")
    res = u - (a + b * t)
    s2 = float(np.sum(w * res ** 2)) / (n - 2)
    return a, b, float(np.sqrt(s2 / sxx))


def _variances(fits: Sequence[LogFit]) -> np.ndarray:
    """Each log's own variance of the parameter, from its 90 % interval (infinite where
    the fit is censored by the grid)."""
    z = 2.0 * 1.6449
    width = np.array([np.inf if f.censored else max(f.hi_u - f.lo_u, 1e-6) for f in fits])
    return (width / z) ** 2


def heldout_score(fits: Sequence[LogFit], slope: bool = True) -> float:
    """Share of the references' loss removed when each log's parameter is
    predicted by the trend of the other logs (``slope`` False: by their weighted mean, a
    constant deviation), less the prediction's penalty per parameter."""
    t = np.array([f.time_s for f in fits]) / DAY_S
    u = np.array([f.u for f in fits])
    var = _variances(fits)
    held = total = 0.0
    for j, f in enumerate(fits):
        others = np.arange(len(fits)) != j
        if slope:
            a, b, _ = _line(t[others], u[others], var[others])
            predicted = a + b * t[j]
        else:
            predicted = _level(u[others], var[others])
        held += max(_interp_loss(predicted, f.grid_u, f.loss), 0.0)
        total += f.loss_nominal
    parameters = 2 if slope else 1
    return 1.0 - held / total - parameters * PENALTY_PER_PARAMETER if total > 0 else 0.0


def _level(u: np.ndarray, var: np.ndarray) -> float:
    """The logs' common value: weighted by their own variances (a censored log left out)."""
    known = np.isfinite(var)
    if not known.any():
        return float(np.median(u))
    return float(np.average(u[known], weights=1.0 / var[known]))


class Trend(NamedTuple):
    """A window's line: days, parameters, intercept, slope, the slope's standard error, and
    whether the slope counts."""

    t: np.ndarray
    u: np.ndarray
    a: float
    b: float
    se: float
    trending: bool


def _trend(window: Sequence[LogFit]) -> Trend:
    t = np.array([f.time_s for f in window]) / DAY_S
    u = np.array([f.u for f in window])
    a, b, se = _line(t, u, _variances(window))
    return Trend(t, u, a, b, se, bool(abs(b) > SLOPE_T * se))


def expected_error_mm(fits: Sequence[LogFit], u: float) -> float:
    """Largest change of an edge-to-edge increment at parameter ``u`` on recent work."""
    return float(np.median([max(_interp(u, f.grid_u, f.emax_mm), 0.0) for f in fits[-3:]]))


def unit_trend(machine: str, actuator: str, rows: Sequence[dict], tolerance_mm: float,
               horizon_days: float) -> UnitTrend:
    """The trend of one machine's unit from its analysis rows (any order)."""
    out = UnitTrend(machine, actuator)
    by_cause: dict[str, list[LogFit]] = {}
    for r in rows:
        if r["cause"] in ALL_CAUSES and r["n_obs"] >= 2 and len(r["grid"]):
            by_cause.setdefault(r["cause"], []).append(log_fit(r["cause"], r))
    for fits in by_cause.values():
        fits.sort(key=lambda f: f.time_s)
    out.series = by_cause
    if not by_cause:
        return out
    first = next(iter(by_cause.values()))
    out.times_s = [f.time_s for f in first]
    for i, t_now in enumerate(out.times_s):
        out.reference_error_mm.append(first[i].max_increment_mm)
        scores = {}
        if i + 1 >= MIN_LOGS:
            for cause, fits in by_cause.items():
                scores[cause] = heldout_score(fits[max(0, i + 1 - WINDOW):i + 1])
        out.scores.append(scores)
        candidates = {c: _trend(by_cause[c][max(0, i + 1 - WINDOW):i + 1])
                      for c, score in scores.items() if score >= TREND_SCORE}
        if not candidates:
            out.named.append("none")
            out.error_now_mm.append(float("nan"))
            out.error_projected_mm.append(float("nan"))
            out.alarms.append(None)
            continue
        # what wears is what changes: of the causes that trend, the one whose slope adds most
        # over a constant deviation (the machine's tolerances), else the best-scoring
        trend_causes = [c for c, tr in candidates.items() if tr.trending]

        def slope_gain(c: str) -> float:
            return scores[c] - heldout_score(by_cause[c][max(0, i + 1 - WINDOW):i + 1],
                                             slope=False)
        best = (max(trend_causes, key=slope_gain) if trend_causes
                else max(candidates, key=scores.get))
        window = by_cause[best][max(0, i + 1 - WINDOW):i + 1]
        t, u, a, b, se, trending = candidates[best]
        u_now = a + b * t[-1] if trending else float(np.median(u[-3:]))
        named = scores[best] >= MIN_SCORE and ALL_CAUSES[best].resolved(from_u(best, u_now))
        out.named.append(best if named or trending else "none")
        now = expected_error_mm(window, u_now)
        # within the days it was fitted on the trend goes on at its slope, beyond them at
        # the slope's conservative bound (the same sign, or flat)
        fitted_days = float(t[-1] - t[0])
        slope_beyond = np.sign(b) * max(abs(b) - EXTRAPOLATION_SE * se, 0.0)
        days = np.arange(0.0, horizon_days + 0.5, 0.5)
        path = [expected_error_mm(window, u_now + b * min(d, fitted_days)
                                  + slope_beyond * max(d - fitted_days, 0.0))
                if trending else now for d in days]
        out.error_now_mm.append(now)
        out.error_projected_mm.append(path[-1])
        over = [d for d, e in zip(days, path) if e > tolerance_mm]
        if over and (trending or named):
            out.alarms.append(Alarm(t_now, best, from_u(best, u_now), now, path[-1],
                                    t_now + over[0] * DAY_S))
        else:
            out.alarms.append(None)
    return _held(out)


def _held(out: UnitTrend) -> UnitTrend:
    """Each day without an alarm of its own keeps the last one raised fewer than
    :data:`HOLD_DAYS` calendar days before it."""
    raised: Alarm | None = None
    for i, (t, alarm) in enumerate(zip(out.times_s, out.alarms)):
        if alarm is not None:
            raised = alarm
        elif raised is not None and t // DAY_S - raised.time_s // DAY_S < HOLD_DAYS:
            out.alarms[i] = raised
    return out
