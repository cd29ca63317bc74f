"""The paper's Figures 6/8: measured and calculated position, and their difference."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def plot_estimate(time_s: np.ndarray, reference_mm: np.ndarray, estimate_mm: np.ndarray,
                  uncertainty_mm: np.ndarray, title: str, out: str | Path) -> None:
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.2))
    left.plot(time_s, reference_mm, label="measured (draw-wire)", color="k", lw=1.2)
    left.plot(time_s, estimate_mm, label="calculated", color="tab:red", lw=1.0, ls="--")
    left.set_xlabel("time (s)")
    left.set_ylabel("cylinder position (mm)")
    left.legend()
    left.grid(True, alpha=0.3)
    err = estimate_mm - reference_mm
    right.plot(time_s, err, color="tab:blue", lw=1.0, label="calculated − measured")
    right.fill_between(time_s, -uncertainty_mm, uncertainty_mm, color="tab:blue", alpha=0.12,
                       label="± published uncertainty")
    right.set_xlabel("time (s)")
    right.set_ylabel("difference (mm)")
    right.legend()
    right.grid(True, alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
