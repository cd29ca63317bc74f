"""Several causes at once: a joint fit of up to three, each run predicted by the set fitted on
the other runs, and the set grown one cause at a time while each adds a resolved gain.

The joint fit is Gauss-Newton on exact evaluations of the extended model (every parameter of
the set applied together, :meth:`Workbench.evaluate`): per iteration one evaluation per
parameter for the sensitivities (a step of half its resolution) and one to accept the step.
Cross-validation refits the set without each run in the last linearisation and then
evaluates each run *exactly* at its own fold's parameters, so the held-out error is the
extended model's, not the linearisation's.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ddh_vsensor.diagnosis.causes import Cause
from ddh_vsensor.diagnosis.fit import PENALTY_PER_PARAMETER, Z90, CauseFit
from ddh_vsensor.diagnosis.workbench import Params, Workbench

ITERATIONS = 4
RIDGE = 1e-9


@dataclass
class SetFit:
    """A set of causes fitted jointly and cross-validated."""

    causes: tuple[Cause, ...]
    params: dict[str, float]                # fitted on all runs
    fold_params: list[dict[str, float]]     # fitted without run j
    heldout: list[np.ndarray]               # residual (mm) of held-out run j
    explained: float                        # share of the baseline's held-out SSE removed
    own_sse: float                          # each run's own linearised best fit
    weights: tuple[float, ...]
    motor_inertia: bool
    intervals: dict[str, tuple[float, float]]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.causes)

    @property
    def sse(self) -> float:
        return float(sum(w * np.dot(h, h) for h, w in zip(self.heldout, self.weights)))

    @property
    def score(self) -> float:
        return self.explained - PENALTY_PER_PARAMETER * sum(c.parameters for c in self.causes)

    @property
    def heterogeneity(self) -> float:
        return self.sse / self.own_sse if self.own_sse > 0 else 1.0

    def resolved(self) -> bool:
        return all(c.resolved(self.params.get(c.parameter)) for c in self.causes)

    @classmethod
    def single(cls, fit: CauseFit) -> "SetFit":
        c = fit.cause
        params = fit.parameters
        folds = [{} if v is None else {c.parameter: float(v)} for v in fit.fold_values]
        intervals = {} if fit.interval is None else {c.parameter: fit.interval}
        return cls((c,), params, folds, fit.heldout, fit.explained, fit.own_sse,
                   fit.weights, fit.motor_inertia, intervals)


def _u(c: Cause, v: float) -> float:
    return float(np.log(v)) if c.log else float(v)


def _v(c: Cause, u: float) -> float:
    return c.clip(float(np.exp(u)) if c.log else float(u))


def _step_u(c: Cause) -> float:
    return (np.log1p(c.resolution) if c.log else c.resolution) / 2.0


def _residuals(bench: Workbench, sets: Sequence[Params | Sequence[Params]]
               ) -> list[list[np.ndarray]]:
    return [[(x - r.position_mm)[m] for x, r, m in zip(xs, bench.runs, bench.masks)]
            for xs in bench.evaluate_many(sets)]


def _sse(res: Sequence[np.ndarray], weights: Sequence[float]) -> float:
    return float(sum(w * np.dot(r, r) for r, w in zip(res, weights)))


def screen(bench: Workbench, base: SetFit, candidates: Sequence[Cause],
           weights: Sequence[float]) -> list[tuple[float, Cause]]:
    """Candidates to add to ``base`` by the SSE the linearised joint fit would leave
    (smallest first): one exact evaluation per candidate and per member for sensitivities."""
    causes = list(base.causes)
    p0 = dict(base.params)
    r0 = _residuals(bench, [p0])[0]
    probes, steps = [], []
    for c in causes + list(candidates):
        u0 = _u(c, p0.get(c.parameter, c.neutral))
        u1 = u0 + _step_u(c)
        if _v(c, u1) == _v(c, u0):
            u1 = u0 - _step_u(c)
        probes.append({**p0, c.parameter: _v(c, u1)})
        steps.append(u1 - u0)
    res = _residuals(bench, probes)
    cols = [[(res[i][j] - r0[j]) / steps[i] for j in range(len(r0))]
            for i in range(len(probes))]
    m = len(causes)
    out = []
    for i, c in enumerate(candidates):
        use = list(range(m)) + [m + i]
        jac = [np.stack([cols[q][j] for q in use], axis=1) for j in range(len(r0))]
        a = sum(w * jj.T @ jj for jj, w in zip(jac, weights))
        b = -sum(w * jj.T @ rr for jj, rr, w in zip(jac, r0, weights))
        du = np.linalg.solve(a + RIDGE * np.trace(a) * np.eye(len(use)) + 1e-300, b)
        out.append((_sse([rr + jj @ du for rr, jj in zip(r0, jac)], weights), c))
    out.sort(key=lambda x: x[0])
    return out


def fit_set(bench: Workbench, causes: Sequence[Cause], start: Mapping[str, float],
            weights: Sequence[float], total: float,
            fixed: Mapping[Cause, tuple[float, tuple[float, float]]] | None = None) -> SetFit:
    """Fit ``causes`` jointly from ``start`` (parameter -> value; absent: neutral) and
    cross-validate; ``total`` is the baseline's held-out SSE the share is taken of.
    ``fixed``: further causes held at a measured value (with its 90 % interval)."""
    causes = tuple(causes)
    fixed = dict(fixed or {})
    held_at = {c.parameter: v for c, (v, _) in fixed.items()}
    names = [c.parameter for c in causes]
    u = np.array([_u(c, start.get(c.parameter, c.neutral)) for c in causes])
    h = np.array([_step_u(c) for c in causes])

    def params(uu: np.ndarray) -> dict[str, float]:
        return {**held_at, **{p: _v(c, x) for p, c, x in zip(names, causes, uu)}}

    r0 = _residuals(bench, [params(u)])[0]
    s0 = _sse(r0, weights)
    jac: list[np.ndarray] = []
    for _ in range(ITERATIONS):
        probes = []
        for i, c in enumerate(causes):
            uu = u.copy()
            uu[i] += h[i]
            if _v(c, uu[i]) == _v(c, u[i]):      # at the upper bound: step down
                uu[i] = u[i] - h[i]
            probes.append(uu)
        res = _residuals(bench, [params(p) for p in probes])
        jac = [np.stack([(res[i][j] - r0[j]) / (probes[i][i] - u[i])
                         for i in range(len(causes))], axis=1) for j in range(len(r0))]
        a = sum(w * jj.T @ jj for jj, w in zip(jac, weights))
        b = -sum(w * jj.T @ rr for jj, rr, w in zip(jac, r0, weights))
        du = np.linalg.solve(a + RIDGE * np.trace(a) * np.eye(len(u)) + 1e-300, b)
        improved = False
        for _half in range(3):
            cand = np.array([_u(c, _v(c, x)) for c, x in zip(causes, u + du)])
            rc = _residuals(bench, [params(cand)])[0]
            sc = _sse(rc, weights)
            if sc < s0:
                u, r0, s0, improved = cand, rc, sc, True
                break
            du = du / 2.0
        if not improved or np.all(np.abs(du) < 0.05 * h):
            break

    # leave one run out in the last linearisation, then each run exactly at its fold's values
    k = len(r0)
    a_j = [w * jj.T @ jj for jj, w in zip(jac, weights)]
    b_j = [-w * jj.T @ rr for jj, rr, w in zip(jac, r0, weights)]
    a_all, b_all = sum(a_j), sum(b_j)
    eye = np.eye(len(u))
    fold_u, own = [], 0.0
    for j in range(k):
        a = a_all - a_j[j]
        fold_u.append(np.array([_u(c, _v(c, x)) for c, x in zip(
            causes, u + np.linalg.solve(a + RIDGE * np.trace(a) * eye + 1e-300,
                                        b_all - b_j[j]))]))
        d_own = np.linalg.solve(a_j[j] + RIDGE * np.trace(a_all) * eye + 1e-300, b_j[j])
        rr = r0[j] + jac[j] @ d_own
        own += weights[j] * float(np.dot(rr, rr))
    folds = [params(x) for x in fold_u]
    held = _residuals(bench, [folds])[0]
    fu = np.array(fold_u)
    se = np.sqrt((k - 1) / k * np.sum((fu - fu.mean(axis=0)) ** 2, axis=0))
    half = np.hypot(Z90 * se, h)
    intervals = {p: (_v(c, x - d), _v(c, x + d)) for p, c, x, d in zip(names, causes, u, half)}
    intervals.update({c.parameter: iv for c, (_, iv) in fixed.items()})
    explained = 1.0 - _sse(held, weights) / total if total > 0 else 0.0
    return SetFit(causes + tuple(fixed), params(u), folds, held, explained, min(own, _sse(held, weights)),
                  tuple(weights), bench.inertia, intervals)
