"""The paper's Figure 5: cylinder movement per motor revolution against motor torque."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ddh_vsensor.config import Config  # noqa: E402
from ddh_vsensor.tables.lookup import UnitTables  # noqa: E402

FIGURE5_TEMPERATURES_C = (-5.0, 25.0, 60.0, 100.0)


def plot_figure5(tables: dict[str, UnitTables], cfg: Config, out: str | Path,
                 speed_rpm: float = 5000.0) -> None:
    fig, axes = plt.subplots(1, len(tables), figsize=(6.2 * len(tables), 4.6))
    for ax, (actuator, t) in zip(np.atleast_1d(axes), tables.items()):
        # Working direction of the load: a load pushing the rod in is held by the A side
        # (positive torque), a pulling one by the B side (negative torque).
        sign = 1.0 if cfg.unit(actuator).load.holding_force_n >= 0.0 else -1.0
        q_max = t.full.torque.stop
        torque = np.linspace(0.0, sign * q_max, 600)
        colors = plt.cm.coolwarm(np.linspace(0.0, 1.0, len(FIGURE5_TEMPERATURES_C)))
        for temp_c, color in zip(FIGURE5_TEMPERATURES_C, colors):
            for direction, style, label in ((1.0, "-", "lifting"), (-1.0, "--", "lowering")):
                # Lifting against a pulling load is a retraction: the motor turns negative.
                n = direction * sign * speed_rpm
                v, _ = t.full.velocity_many(np.full_like(torque, n), torque,
                                            np.full_like(torque, temp_c))
                mm_rev = v / (n / 60.0)
                ax.plot(torque, mm_rev, style, color=color,
                        label=f"{temp_c:g} °C, {label}")
        ax.set_title(f"{actuator}: movement per motor revolution at {speed_rpm:g} rpm")
        ax.set_xlabel("motor torque (N·m)")
        ax.set_ylabel("cylinder movement (mm/rev)")
        ax.grid(True, alpha=0.3)
        ax.set_ylim(*_robust_limits(ax))
        ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


def _robust_limits(ax: plt.Axes) -> tuple[float, float]:
    """Y range of the working region: the relief drop shows, overrunning extremes do not."""
    y = np.concatenate([line.get_ydata() for line in ax.get_lines()])
    y = y[np.isfinite(y)]
    lo, hi = np.percentile(y, [2, 99])
    pad = 0.1 * (hi - lo)
    return max(lo - pad, 0.0), hi + pad
