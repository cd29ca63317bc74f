"""The diagnosis of one actuator over a set of runs: what is wrong, why, and the gain of the
extended model on runs it was not fitted to."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ..config import Config
from ..errors import UserError
from .causes import ALL_CAUSES, Cause
from .fit import CauseFit, fit_cause, rescore
from .runs import AnalysisRun
from .selection import Decision, decide
from .workbench import Workbench

Progress = Callable[[str, float], None]


@dataclass
class Diagnosis:
    actuator: str
    mode: str
    runs: list[AnalysisRun]
    bench: Workbench
    baseline: list[np.ndarray]          # the estimator as it is: estimate minus reference
    model: list[np.ndarray]             # the same with the motor inertia (if it helps)
    fits: list[CauseFit]                # best first; scored against ``model``'s error
    decision: Decision

    @property
    def cause(self) -> str:
        return self.decision.cause

    @property
    def chosen(self) -> CauseFit:
        return next(f for f in self.fits if f.cause.name == self.cause)


def _fit_either_torque(cause: Cause, bench: Workbench, target: list[np.ndarray],
                       weights: list[float]) -> CauseFit:
    """Fit ``cause`` on the tables fed the motor torque and fed the pump torque (the motor's
    inertia taken off); keep the one that explains more of ``target`` on held-out runs.

    In a transient the tables' velocity can hinge on a few N*m (a valve regime), so which
    torque reads right depends on the runs and on the cause; the chamber model of
    ``compressibility`` takes the inertia into account itself.
    """
    if cause.name == "none":
        bench.use(bench.default_inertia)
        fit = fit_cause(cause, bench, target, weights)
        fit.motor_inertia = bench.default_inertia
        return fit
    best = None
    for inertia in ((bench.default_inertia,) if cause.name == "compressibility"
                    else (False, True)):
        bench.use(inertia)
        own = [(x - r.position_mm)[m] for x, r, m in zip(bench.base, bench.runs, bench.masks)]
        fit = rescore(fit_cause(cause, bench, own, weights), target, weights)
        fit.motor_inertia = inertia
        if best is None or fit.score > best.score:
            best = fit
    return best


def diagnose(cfg: Config, actuator: str, runs: Sequence[AnalysisRun], mode: str = "full",
             progress: Progress | None = None) -> Diagnosis:
    """Fit every cause of the catalogue, cross-validated one run out at a time, and decide."""
    if len(runs) < 2:
        raise UserError(f"{len(runs)} run given: the diagnosis needs at least two runs (the "
                        "fit is judged on runs it did not see)")
    if mode not in ("full", "paper"):
        raise UserError(f"unknown mode {mode!r} (full or paper)")
    report = progress or (lambda stage, fraction: None)
    report("baseline", 0.0)
    bench = Workbench(cfg, actuator, runs, mode)
    baseline = [x - r.position_mm for x, r in zip(bench.as_is, runs)]
    model = [x - r.position_mm for x, r in zip(bench.base, runs)]
    target = [e[m] for e, m in zip(model, bench.masks)]
    weights = [r.duration_s / max(int(m.sum()), 1) for r, m in zip(runs, bench.masks)]
    causes: list[Cause] = list(ALL_CAUSES.values())
    fits = []
    for i, cause in enumerate(causes):
        report(cause.name, i / len(causes))
        fits.append(_fit_either_torque(cause, bench, target, weights))
    bench.use(bench.default_inertia)
    report("decision", 1.0)
    fits.sort(key=lambda f: (-f.score, f.cause.name != "none"))
    return Diagnosis(actuator, mode, list(runs), bench, baseline, model, fits,
                     decide(fits, target, weights))
