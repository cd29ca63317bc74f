"""The drive's torque reading against the shaft's, measured on runs with chamber pressures.

The drive's torque is its estimate from the motor's currents. Where the chamber pressures are
logged, the shaft's torque is known from them: the pumps' torque at those pressures (the unit
model's gains, efficiency by direction) plus the rotor's inertia torque J dω/dt. The reading
is then, to first order,

    τ_read(t) = τ_shaft(t − T_f) + o + s n / n_limit

with T_f the drive's estimate filter (a first-order lag delays a ramp by its time constant),
o its offset and s its speed-proportional part at the speed limit (``motor.torque_filter_s``,
``torque_offset_nm``, ``torque_speed_offset_nm``). For each T_f on a grid the reading,
carried that far along its change (and by the configured reporting lag ``torque_lag_s``),
less the shaft's torque is regressed on [1, n / n_limit]; the T_f of the smallest residual
wins. Samples count only where the motor turns (|n| above :data:`MIN_SPEED_RPM`: standing,
its torque is anywhere in the pumps' friction band). The sigmas are the
regression's, over blocks of :data:`BLOCK_S` (a torque error persists over a move: samples
within one are not independent). Without logged pressures a pressure read from the torque
would carry the very offset sought, so nothing is measured and the answer says what run
would.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ddh_vsensor.commission.flow import gauge_pressures
from ddh_vsensor.config import Config
from ddh_vsensor.estimator.timing import torque_at_speed_instants
from ddh_vsensor.measured import Run
from ddh_vsensor.physics.conversions import RPM_RAD_S
from ddh_vsensor.physics.unit import DDHUnit

MIN_SPEED_RPM = 100.0
BLOCK_S = 1.0
FILTER_GRID_S = tuple(np.round(np.arange(0.0, 0.0105, 0.0005), 4))
MIN_BLOCKS = 20
NOT_MEASURED = ("no run logs the chamber pressures: the drive's offset, speed offset and "
                "filter are not measured (log p_a_bar and p_b_bar on the calibration day; a "
                "torque read from pressures it gave itself cannot tell its own offset)")


@dataclass(frozen=True)
class DriveFit:
    """One unit's drive: the configured keys' values with their sigmas, or why none."""

    offset_nm: float = 0.0
    offset_sigma_nm: float = float("inf")
    speed_offset_nm: float = 0.0
    speed_offset_sigma_nm: float = float("inf")
    filter_s: float = 0.0
    residual_rms_nm: float = float("nan")
    blocks: int = 0
    why_not: str | None = None

    @property
    def measured(self) -> bool:
        return self.why_not is None


def shaft_torque_from_pressures(unit: DDHUnit, run: Run, dp_a_pa: np.ndarray,
                                dp_b_pa: np.ndarray) -> np.ndarray:
    """The shaft's torque (N*m) the logged pressures and the speed's change imply."""
    n = np.asarray(run.speed_rpm, dtype=float)
    t = np.asarray(run.time_s, dtype=float)
    inertia = unit.motor.inertia_kg_m2 * RPM_RAD_S * np.gradient(n, t)
    return unit.motor_torque_nm(dp_a_pa, dp_b_pa, n) + inertia


def fit_drive(cfg: Config, actuator: str, runs: Sequence[Run]) -> DriveFit:
    """The drive's filter, offset and speed offset from the runs with logged pressures."""
    unit = DDHUnit.from_config(cfg, actuator)
    motor = cfg.unit(actuator).motor
    rows = []
    for run in runs:
        pressures = gauge_pressures(unit, run)
        if pressures is None or len(run.time_s) < 3:
            continue
        dp_a, dp_b = pressures
        n = np.asarray(run.speed_rpm, dtype=float)
        keep = np.abs(n) > MIN_SPEED_RPM
        keep[:1] = False
        block = np.floor((run.time_s - run.time_s[0]) / BLOCK_S).astype(int)
        rows.append((run, shaft_torque_from_pressures(unit, run, dp_a, dp_b), n, keep, block))
    if not rows:
        return DriveFit(why_not=NOT_MEASURED)
    best: DriveFit | None = None
    gap = cfg.estimator.max_gap_s
    for filter_s in FILTER_GRID_S:
        y, x, blocks = [], [], []
        for i, (run, shaft, n, keep, block) in enumerate(rows):
            read = torque_at_speed_instants(run.time_s, run.torque_nm,
                                            motor.torque_lag_s + filter_s, gap)
            y.append((read - shaft)[keep])
            x.append(n[keep] / motor.speed_limit_rpm)
            blocks.append(block[keep] + 100000 * i)
        yv, xv, bv = np.concatenate(y), np.concatenate(x), np.concatenate(blocks)
        ids = np.unique(bv)
        if len(ids) < MIN_BLOCKS:
            return DriveFit(why_not=f"{len(ids)} s of turning with logged pressures, "
                                    f"{MIN_BLOCKS} needed: run the calibration programme "
                                    "with the pressures logged")
        design = np.column_stack([np.ones_like(xv), xv])
        coef, *_ = np.linalg.lstsq(design, yv, rcond=None)
        resid = yv - design @ coef
        rms = float(np.sqrt(np.mean(resid ** 2)))
        if best is not None and rms >= best.residual_rms_nm:
            continue
        # the blocks' means as the independent observations: the sigma of a block-level fit
        inv = np.searchsorted(ids, bv)
        counts = np.bincount(inv)
        block_x = np.bincount(inv, xv) / counts
        block_r = np.bincount(inv, resid) / counts
        bdesign = np.column_stack([np.ones_like(block_x), block_x])
        cov = np.linalg.pinv(bdesign.T @ bdesign) * float(np.var(block_r, ddof=2))
        best = DriveFit(float(coef[0]), float(np.sqrt(cov[0, 0])), float(coef[1]),
                        float(np.sqrt(cov[1, 1])), float(filter_s), rms, len(ids))
    assert best is not None
    return best
