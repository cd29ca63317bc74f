"""How far an estimate is from the reference position, where the reference was sampled."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class Accuracy:
    max_abs_error_mm: float
    rms_error_mm: float
    final_error_mm: float
    samples: int

    def as_dict(self) -> dict[str, float]:
        d = asdict(self)
        d.pop("samples")
        return d


def accuracy(estimate_mm: np.ndarray, reference_mm: np.ndarray) -> Accuracy | None:
    """Errors (estimate minus reference) over the samples with a reference; None if none."""
    err = np.asarray(estimate_mm, dtype=float) - np.asarray(reference_mm, dtype=float)
    err = err[np.isfinite(err)]
    if err.size == 0:
        return None
    return Accuracy(float(np.max(np.abs(err))), float(np.sqrt(np.mean(err ** 2))),
                    float(err[-1]), int(err.size))
