"""The drive's torque reading against the shaft's, measured on runs with chamber pressures.

The drive's torque is its estimate from the motor's currents. Where the chamber pressures are
logged, the shaft's torque is known from them: the pumps' torque at those pressures (the unit
model's gains, efficiency by direction) plus the rotor's inertia torque J dω/dt. The reading
is then, to first order,

    τ_read(t) = g τ_shaft(t − T_f) + o + s n / n_limit

with T_f the drive's estimate filter (a first-order lag delays a ramp by its time constant),
g its gain (current sensing a few percent off reads every torque that much off), o its offset
and s its speed-proportional part at the speed limit (``motor.torque_filter_s``,
``torque_gain``, ``torque_offset_nm``, ``torque_speed_offset_nm``). For each T_f on a grid the
reading, carried that far along its change (and by the configured reporting lag
``torque_lag_s``), less the shaft's torque is regressed on [1, n / n_limit, τ_shaft] (the
speed term carried alike, as the estimators carry the reading less it; the third coefficient
is g − 1); the T_f of the smallest residual wins. The gain is a slope: it is fitted only where
the blocks' shaft torques span :data:`GAIN_MIN_SPAN` of the motor's torque limit, and
otherwise kept at 1 with the reason (:attr:`DriveFit.gain_why_not`). Samples count only where
the motor turns (|n| above :data:`MIN_SPEED_RPM`: standing, its torque is anywhere in the
pumps' friction band). The sigmas are the regression's, over blocks of :data:`BLOCK_S` (a
torque error persists over a move: samples within one are not independent). Without logged
pressures a pressure read from the torque would carry the very offset sought, so nothing is
measured and the answer says what run would.
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
# The gain is told from the offset only by torques well apart: over less than a fifth of the
# torque limit (18 N*m on the reference loader) a gain 5 % off moves the reading by under
# 0.9 N*m across the span, a few bar through the pumps, which the transducers' own
# calibration errors reach, so the slope would measure them rather than the drive.
GAIN_MIN_SPAN = 0.2
NOT_MEASURED = ("no run logs the chamber pressures: the drive's offset, speed offset and "
                "filter are not measured (log p_a_bar and p_b_bar on the calibration day; a "
                "torque read from pressures it gave itself cannot tell its own offset)")


@dataclass(frozen=True)
class DriveFit:
    """One unit's drive: the configured keys' values with their sigmas, or why none (the
    gain alone: ``gain_why_not``, the gain then 1 and the rest fitted with it)."""

    offset_nm: float = 0.0
    offset_sigma_nm: float = float("inf")
    speed_offset_nm: float = 0.0
    speed_offset_sigma_nm: float = float("inf")
    filter_s: float = 0.0
    residual_rms_nm: float = float("nan")
    blocks: int = 0
    why_not: str | None = None
    gain: float = 1.0
    gain_sigma: float = float("inf")
    gain_why_not: str | None = None
    torque_span_nm: float = 0.0         # of the blocks' mean shaft torques

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
    """The drive's filter, gain, offset and speed offset from the runs with logged
    pressures."""
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
    # what does not depend on the filter: the samples kept, their blocks and shaft torques
    tau = np.concatenate([shaft[keep] for _, shaft, _, keep, _ in rows])
    ids, inv = np.unique(np.concatenate([block[keep] + 100000 * i for i, (*_, keep, block)
                                         in enumerate(rows)]), return_inverse=True)
    if len(ids) < MIN_BLOCKS:
        return DriveFit(why_not=f"{len(ids)} s of turning with logged pressures, "
                                f"{MIN_BLOCKS} needed: run the calibration programme "
                                "with the pressures logged")
    counts = np.bincount(inv)
    block_tau = np.bincount(inv, tau) / counts
    span = float(np.ptp(block_tau))
    gain_why_not = None
    if span < GAIN_MIN_SPAN * motor.torque_limit_nm:
        gain_why_not = (f"the shaft's torque spans {span:.1f} N*m over the blocks, "
                        f"{GAIN_MIN_SPAN * motor.torque_limit_nm:.1f} needed to tell a gain "
                        "from the offset: move loaded and unloaded with the pressures logged")
    best: DriveFit | None = None
    gap = cfg.estimator.max_gap_s
    for filter_s in FILTER_GRID_S:
        lag_s = motor.torque_lag_s + filter_s
        # the reading and its speed term carried alike: the estimators carry the reading less
        # its speed offset (:mod:`ddh_vsensor.estimator.timing`)
        read = np.concatenate([torque_at_speed_instants(run.time_s, run.torque_nm, lag_s,
                                                        gap)[keep]
                               for run, _, _, keep, _ in rows])
        x = np.concatenate([torque_at_speed_instants(run.time_s, n, lag_s, gap)[keep]
                            for run, _, n, keep, _ in rows]) / motor.speed_limit_rpm
        columns = [np.ones_like(x), x] + ([] if gain_why_not else [tau])
        design = np.column_stack(columns)
        yv = read - tau
        coef, *_ = np.linalg.lstsq(design, yv, rcond=None)
        resid = yv - design @ coef
        rms = float(np.sqrt(np.mean(resid ** 2)))
        if best is not None and rms >= best.residual_rms_nm:
            continue
        # the blocks' means as the independent observations: the sigma of a block-level fit
        bdesign = np.column_stack([np.bincount(inv, c) / counts for c in columns])
        block_r = np.bincount(inv, resid) / counts
        sigma = np.sqrt(np.diag(np.linalg.pinv(bdesign.T @ bdesign))
                        * float(np.var(block_r, ddof=design.shape[1])))
        gain = ({} if gain_why_not else
                {"gain": 1.0 + float(coef[2]), "gain_sigma": float(sigma[2])})
        best = DriveFit(float(coef[0]), float(sigma[0]), float(coef[1]), float(sigma[1]),
                        float(filter_s), rms, len(ids), gain_why_not=gain_why_not,
                        torque_span_nm=span, **gain)
    assert best is not None
    return best
