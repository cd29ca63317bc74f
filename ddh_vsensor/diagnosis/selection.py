"""Naming a cause: the best-scoring one, only if it explains significantly more than none.

Two tests, set from what the model's own error looks like on simulated runs without any
effect (paper cycle and random point-to-point cycles, payloads 0 and 1040 kg, oil 22..60 degC;
numbers in diagnosis/README.md):

1. The score (held-out share of squared error explained, minus the parameter penalty) must
   reach :data:`MIN_SCORE` (0.6). With an effect of the trial ranges the true cause scored
   0.84 or more (median 0.98, 100 analyses).
2. The fitted parameter must be *resolved*: further from neutral than the model's own error
   can mimic. Without any effect the model still errs by 0.5-1.5 mm (the tables hold steady
   states: no compression, no settling of the chamber pressures), and small fits explain
   much of that, systematically: the compressible-chamber model at 0-0.014 % air (it holds
   the nominal oil's compression: scores up to 0.97), a time offset of 3-4.5 ms (up to 0.55),
   a leakage factor of 0.95-0.98 (up to 0.68 on hard point-to-point cycles). Each cause's
   ``resolution`` sits at several times those: air 0.5 %, time offset 10 ms, leakage and
   displacement factors x/ 1.10 and 1.005, belt slip 1 % per 100 N*m. Below it the answer is
   none: the effect, if any, is within the model's own error.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .fit import CauseFit

MIN_SCORE = 0.6


@dataclass(frozen=True)
class Decision:
    cause: str
    reason: str
    rms_before_mm: float
    rms_after_mm: float


def _rms(residuals: Sequence[np.ndarray], weights: Sequence[float]) -> float:
    num = sum(w * float(np.dot(r, r)) for r, w in zip(residuals, weights))
    den = sum(w * len(r) for r, w in zip(residuals, weights))
    return float(np.sqrt(num / den)) if den else 0.0


def decide(fits: Sequence[CauseFit], target: Sequence[np.ndarray],
           weights: Sequence[float]) -> Decision:
    """The decision on ``fits`` (best first) for the baseline residual ``target``."""
    best = fits[0]
    before = _rms(target, weights)
    after = _rms(best.heldout, weights)
    share = f"{100 * best.score:.0f} %"
    if best.cause.name == "none":
        return Decision("none", "no cause explains any of the held-out error", before, before)
    if best.score < MIN_SCORE:
        return Decision("none", f"the best candidate, {best.cause.name}, explains {share} of "
                        "the held-out squared error (after its parameter penalty); naming a "
                        f"cause needs {100 * MIN_SCORE:.0f} %", before, before)
    if not best.cause.resolved(best.value):
        return Decision("none", f"the best candidate, {best.cause.name}, fits "
                        f"{best.cause.parameter} = {best.value:.4g}, within what the model's "
                        f"own error can mimic (named from {_bound(best.cause)})", before, before)
    return Decision(best.cause.name, f"{best.cause.name} explains {share} of the held-out "
                    f"squared error (RMS {before:.2f} -> {after:.2f} mm)", before, after)


def _bound(cause) -> str:
    if cause.log:
        return (f"x{1 + cause.resolution:g} or x{1 / (1 + cause.resolution):.3g} "
                f"{cause.unit}")
    return f"{cause.resolution:g} {cause.unit} from {cause.neutral:g}"
