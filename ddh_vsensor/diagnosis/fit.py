"""Fitting one cause to the runs, and scoring it on runs it was not fitted to.

The parameter is found on all runs first: a coarse grid over its physical range, a round of
refinement inside the best bracket, then a five-point stencil around the optimum, every
point an exact evaluation of the extended model (batched where the model allows). Across the stencil each sample's change of
the estimate is a quadratic in the parameter, so cross-validation needs no further model
runs: for each held-out run, the parameter is refitted on the others (least squares over the
stencil's range) and the held-out residual is the model's at that parameter.

Residuals are weighted per run by its sample period, so a run counts by its duration, not
its sample rate. The score of a cause is the share of the held-out squared error it
explains, minus a penalty per parameter (:data:`PENALTY_PER_PARAMETER`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ddh_vsensor.diagnosis.causes import Cause
from ddh_vsensor.diagnosis.workbench import Workbench

PENALTY_PER_PARAMETER = 0.02
REFINE_ROUNDS = 1
REFINE_POINTS = 4
MIN_STEP = {True: 0.01, False: 1e-4}     # smallest stencil step: 1 % for factors, else units
DENSE = 401


@dataclass
class CauseFit:
    """One cause fitted and cross-validated."""

    cause: Cause
    value: float | None                     # fitted on all runs
    fold_values: list[float | None]         # fitted without run j, for held-out run j
    heldout: list[np.ndarray]               # residual (mm) of held-out run j, extended model
    explained: float                        # share of held-out squared error explained
    score: float
    evaluations: int = 0
    motor_inertia: bool = True              # fitted with the estimator's inertia compensation
    own_sse: float = 0.0                    # sum over runs of each run's own best fit's SSE
    interval: tuple[float, float] | None = None     # 90 %, see :func:`interval_90`

    @property
    def heterogeneity(self) -> float:
        """Held-out SSE over the SSE of each run fitted on its own: near 1 when one value
        describes every run, large when each run wants its own (the cause only mimics)."""
        held = sum(float(np.dot(h, h)) * w for h, w in zip(self.heldout, self.weights))
        return held / self.own_sse if self.own_sse > 0 else 1.0

    weights: tuple[float, ...] = ()

    @property
    def parameters(self) -> dict[str, float]:
        if self.cause.parameter is None or self.value is None:
            return {}
        return {self.cause.parameter: float(self.value)}


Z90 = 1.645


def interval_90(cause: Cause, value: float, fold_values: Sequence[float]) -> tuple[float, float]:
    """90 % interval of a fitted parameter: the jackknife spread of the leave-one-run-out fits
    combined with half the cause's resolution (what the model's own error can mimic), in the
    search's scale (log for factors), clipped to the physical range."""
    to_u = np.log if cause.log else (lambda x: np.asarray(x, dtype=float))
    u = to_u(np.asarray([value if v is None else v for v in fold_values], dtype=float))
    k = len(u)
    se = float(np.sqrt((k - 1) / k * np.sum((u - u.mean()) ** 2))) if k > 1 else 0.0
    floor = (np.log1p(cause.resolution) if cause.log else cause.resolution) / 2.0
    half = float(np.hypot(Z90 * se, floor))
    u0 = float(to_u(value))
    lo, hi = (np.exp([u0 - half, u0 + half]) if cause.log else (u0 - half, u0 + half))
    return cause.clip(float(lo)), cause.clip(float(hi))


def _weighted_sse(residuals: Sequence[np.ndarray], weights: Sequence[float]) -> float:
    return float(sum(w * np.dot(r, r) for r, w in zip(residuals, weights)))


class _Search:
    """Exact evaluations of one cause, cached by parameter value (masked samples)."""

    def __init__(self, cause: Cause, bench: Workbench, target: Sequence[np.ndarray],
                 weights: Sequence[float]) -> None:
        self.cause, self.bench, self.target, self.weights = cause, bench, target, weights
        self.deltas: dict[float, list[np.ndarray]] = {}
        self.sse: dict[float, float] = {}

    def to_u(self, v: float) -> float:
        return float(np.log(v)) if self.cause.log else float(v)

    def from_u(self, u: float) -> float:
        return float(np.exp(u)) if self.cause.log else float(u)

    def evaluate(self, values: Sequence[float]) -> None:
        new = sorted({self.cause.clip(v) for v in values} - set(self.deltas))
        if not new:
            return
        for v, d in zip(new, self.cause.deltas(self.bench, self.bench.base, new)):
            masked = [x[m] for x, m in zip(d, self.bench.masks)]
            self.deltas[v] = masked
            self.sse[v] = _weighted_sse([t + x for t, x in zip(self.target, masked)],
                                        self.weights)

    def best(self) -> float:
        return min(self.sse, key=self.sse.get)

    def bracket(self, v: float) -> tuple[float, float]:
        values = sorted(self.sse)
        i = values.index(v)
        return values[max(i - 1, 0)], values[min(i + 1, len(values) - 1)]


def fit_cause(cause: Cause, bench: Workbench, target: Sequence[np.ndarray],
              weights: Sequence[float]) -> CauseFit:
    """Fit ``cause`` to explain ``target``, the baseline residual (estimate minus reference,
    masked samples, per run), and cross-validate it leaving one run out at a time."""
    k = len(target)
    total = _weighted_sse(target, weights)
    if cause.parameters == 0:
        delta = [x[m] for x, m in zip(cause.deltas(bench, bench.base, [0.0])[0], bench.masks)]
        held = [t + d for t, d in zip(target, delta)]
        explained = 1.0 - _weighted_sse(held, weights) / total if total > 0 else 0.0
        return CauseFit(cause, None, [None] * k, held, explained, explained, 1,
                        own_sse=_weighted_sse(held, weights), weights=tuple(weights))

    s = _Search(cause, bench, target, weights)
    s.evaluate(cause.grid)
    for _ in range(REFINE_ROUNDS):
        lo, hi = s.bracket(s.best())
        u = np.linspace(s.to_u(lo), s.to_u(hi), REFINE_POINTS + 2)[1:-1]
        s.evaluate([s.from_u(x) for x in u])
    best = s.best()
    lo, hi = s.bracket(best)
    u0 = s.to_u(best)
    step = max(s.to_u(hi) - u0, u0 - s.to_u(lo), MIN_STEP[cause.log]) / 2.0
    stencil = sorted({cause.clip(s.from_u(u0 + j * step)) for j in (-2, -1, 0, 1, 2)})
    s.evaluate(stencil)

    # each sample's change of the estimate, as a quadratic in u across the stencil
    us = np.array([s.to_u(v) for v in stencil])
    deg = min(2, len(us) - 1)
    pinv = np.linalg.pinv(np.vander(us - u0, deg + 1, increasing=True))
    coef = [np.tensordot(pinv, np.stack([s.deltas[v][i] for v in stencil]), axes=1)
            for i in range(k)]                                      # [run] -> [deg+1, samples]
    grid = np.linspace(us.min(), us.max(), DENSE) - u0 if len(us) > 1 else np.zeros(1)
    powers = np.vander(grid, deg + 1, increasing=True)              # [dense, deg+1]
    sse_runs = np.empty((k, len(grid)))
    for i in range(k):
        pred = target[i][None, :] + powers @ coef[i]                # [dense, samples]
        sse_runs[i] = weights[i] * np.einsum("ij,ij->i", pred, pred)
    all_runs = sse_runs.sum(axis=0)
    u_all = grid[int(np.argmin(all_runs))]
    fold_u = [grid[int(np.argmin(all_runs - sse_runs[j]))] if k > 1 else u_all
              for j in range(k)]
    held = [target[j] + np.vander([u], deg + 1, increasing=True)[0] @ coef[j]
            for j, u in enumerate(fold_u)]
    explained = 1.0 - _weighted_sse(held, weights) / total if total > 0 else 0.0
    value = cause.clip(s.from_u(u0 + u_all))
    folds = [cause.clip(s.from_u(u0 + u)) for u in fold_u]
    return CauseFit(cause, value, folds, held, explained,
                    explained - PENALTY_PER_PARAMETER * cause.parameters, len(s.deltas),
                    own_sse=float(sse_runs.min(axis=1).sum()), weights=tuple(weights),
                    interval=interval_90(cause, value, folds))


def rescore(fit: CauseFit, target: Sequence[np.ndarray], weights: Sequence[float]) -> CauseFit:
    """The fit's score against another reference residual (the common baseline of the
    comparison); its held-out residuals are absolute, so only the denominator changes."""
    total = _weighted_sse(target, weights)
    fit.explained = 1.0 - _weighted_sse(fit.heldout, weights) / total if total > 0 else 0.0
    fit.score = fit.explained - PENALTY_PER_PARAMETER * fit.cause.parameters
    return fit
