"""The report's figures, as PNG bytes (matplotlib, no display)."""

from __future__ import annotations

import io
from collections.abc import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ddh_vsensor.diagnosis.breakdown import ClassStats  # noqa: E402
from ddh_vsensor.diagnosis.signatures import Signature  # noqa: E402

BEFORE, AFTER = "tab:red", "tab:blue"


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return buf.getvalue()


def errors_per_run(names: Sequence[str], times: Sequence[np.ndarray],
                   before: Sequence[np.ndarray], after: Sequence[np.ndarray],
                   after_label: str, middle: Sequence[np.ndarray] | None = None) -> bytes:
    """Error against time, one panel per run: the model as it is and the extended one
    (fitted without that run); ``middle``: with the motor inertia only."""
    k = len(names)
    cols = 2 if k > 1 else 1
    rows = (k + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(6.2 * cols, 2.3 * rows), squeeze=False,
                             sharey=True)
    for i, ax in enumerate(axes.flat):
        if i >= k:
            ax.set_visible(False)
            continue
        ax.plot(times[i], before[i], color=BEFORE, lw=0.9, label="model as it is")
        if middle is not None:
            ax.plot(times[i], middle[i], color="tab:gray", lw=0.8,
                    label="with the motor inertia")
        ax.plot(times[i], after[i], color=AFTER, lw=0.9, label=after_label)
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_title(names[i], fontsize=8)
        ax.grid(True, alpha=0.3)
        ax.tick_params(labelsize=7)
        if i % cols == 0:
            ax.set_ylabel("estimate - reference (mm)", fontsize=7)
        if i >= k - cols:
            ax.set_xlabel("time (s)", fontsize=7)
    axes.flat[0].legend(fontsize=7, loc="best")
    fig.tight_layout()
    return _png(fig)


def breakdown_figure(stats: dict[str, list[ClassStats]]) -> bytes:
    """The error added per second in each class, per dimension."""
    dims = list(stats)
    cols = 3
    rows = (len(dims) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(13, 3.0 * rows), squeeze=False)
    for ax in axes.flat[len(dims):]:
        ax.set_visible(False)
    for ax, dim in zip(axes.flat, dims):
        st = stats[dim]
        names = [s.name for s in st]
        rate = [s.error_rate_mm_s for s in st]
        y = np.arange(len(st))
        ax.barh(y, rate, color=["tab:red" if r > 0 else "tab:blue" for r in rate])
        ax.set_yticks(y, [n.replace("motoring (load drives)", "motoring") for n in names],
                      fontsize=7)
        ax.axvline(0.0, color="k", lw=0.5)
        ax.set_title(dim, fontsize=9)
        ax.set_xlabel("error added (mm/s)", fontsize=7)
        ax.tick_params(axis="x", labelsize=7)
        ax.invert_yaxis()
    fig.tight_layout()
    return _png(fig)


def signature_figure(sig: Signature, before: Sequence[np.ndarray],
                     after: Sequence[np.ndarray], cause: str) -> bytes:
    """The error (rate) against the cause's feature, before and after extending."""
    x = np.concatenate(sig.x)
    yb, ya = np.concatenate(before), np.concatenate(after)
    ok = np.isfinite(x) & np.isfinite(yb) & np.isfinite(ya)
    x, yb, ya = x[ok], yb[ok], ya[ok]
    if x.size > 20000:                          # keep the PNG light
        pick = np.linspace(0, x.size - 1, 20000).astype(int)
        x, yb, ya = x[pick], yb[pick], ya[pick]
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    ax.scatter(x, yb, s=4, color=BEFORE, alpha=0.35, label="model as it is")
    ax.scatter(x, ya, s=4, color=AFTER, alpha=0.35, label=f"extended ({cause}), held out")
    ax.axhline(0.0, color="k", lw=0.5)
    ax.set_xlabel(sig.label, fontsize=8)
    ax.set_ylabel("error added per second (mm/s)" if sig.accumulates
                  else "estimate - reference (mm)", fontsize=8)
    ax.set_title(f"residual against the feature of {cause}", fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, markerscale=3)
    fig.tight_layout()
    return _png(fig)


def ranking_figure(causes: Sequence[str], scores: Sequence[float], threshold: float,
                   named: str) -> bytes:
    fig, ax = plt.subplots(figsize=(6.5, 0.35 * len(causes) + 1.2))
    y = np.arange(len(causes))
    ax.barh(y, scores, color=["tab:green" if c == named else "tab:gray" for c in causes])
    ax.axvline(threshold, color="k", ls="--", lw=0.8, label=f"naming threshold {threshold:g}")
    ax.set_yticks(y, causes, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("score: share of held-out squared error explained, minus penalty",
                  fontsize=8)
    ax.set_xlim(min(-0.1, min(scores) - 0.05), 1.0)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return _png(fig)
