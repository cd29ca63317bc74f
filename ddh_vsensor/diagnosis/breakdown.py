"""What is wrong: the estimate's error broken down by motion phase, direction, load, speed and
oil temperature.

The error e = estimate - reference accumulates, so a class of samples is charged with the
error it *adds* (the change of e over its samples), as a total, per second spent in it and
per metre travelled in it; the RMS and maximum of e over its samples say where the error is
large. Classes come from the estimate's velocity and acceleration (motion phase, direction),
the motor torque (load: pumping into the load or driven by it, and |torque|), the motor
speed (the paper's three ranges, plus the leakage speeds) and the oil temperature.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from ddh_vsensor.diagnosis.runs import AnalysisRun

HOLD_FRACTION = 0.02          # |v| below this share of the run's peak (and 0.5 mm/s): holding
HOLD_MIN_MM_S = 0.5
ACCEL_FRACTION = 0.1          # |a| above this share of the run's 98th-percentile |a|: (de)acc.
SMOOTH_S = 0.1                # velocity and acceleration smoothed over this window

PHASES = ("accelerating", "moving", "decelerating", "holding")
DIRECTIONS = ("extending", "retracting", "standing")
SPEED_BINS_RPM = (0.0, 100.0, 2000.0, 4000.0, np.inf)
SPEED_NAMES = ("< 100 rpm (leakage speeds)", "100-2000 rpm", "2000-4000 rpm", ">= 4000 rpm")
TORQUE_BINS_NM = (0.0, 10.0, 25.0, 45.0, np.inf)
TEMP_STEP_C = 10.0


@dataclass(frozen=True)
class ClassStats:
    dimension: str
    name: str
    time_s: float
    travel_mm: float
    error_added_mm: float           # sum of the error's changes over the class's samples
    error_rate_mm_s: float
    error_per_m_mm: float           # per metre of travel (NaN without travel)
    rms_error_mm: float
    max_abs_error_mm: float

    def as_dict(self) -> dict[str, float | str]:
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                for k, v in asdict(self).items()}


def _smooth(x: np.ndarray, t: np.ndarray, window_s: float) -> np.ndarray:
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    k = max(1, int(round(window_s / max(dt, 1e-9))))
    if k <= 1 or len(x) < k:
        return x
    return np.convolve(x, np.ones(k) / k, mode="same")


def motion(time_s: np.ndarray, estimate_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed velocity (mm/s) and acceleration (mm/s^2) of an estimate."""
    v = _smooth(np.gradient(estimate_mm, time_s), time_s, SMOOTH_S)
    a = _smooth(np.gradient(v, time_s), time_s, SMOOTH_S)
    return v, a


def classify(run: AnalysisRun, estimate_mm: np.ndarray) -> dict[str, np.ndarray]:
    """Class labels (strings) of every sample, per dimension."""
    v, a = motion(run.time_s, estimate_mm)
    peak = float(np.max(np.abs(v))) if len(v) else 0.0
    hold = np.abs(v) < max(HOLD_MIN_MM_S, HOLD_FRACTION * peak)
    a_ref = float(np.percentile(np.abs(a), 98)) if len(a) else 0.0
    along = a * np.sign(v)
    phase = np.where(hold, "holding", np.where(along > ACCEL_FRACTION * a_ref, "accelerating",
                     np.where(along < -ACCEL_FRACTION * a_ref, "decelerating", "moving")))
    direction = np.where(hold, "standing", np.where(v > 0, "extending", "retracting"))
    n, tau = run.speed_rpm, run.torque_nm
    k = np.clip(np.searchsorted(SPEED_BINS_RPM, np.abs(n), side="right") - 1, 0, 3)
    speed = np.array(SPEED_NAMES)[k]
    flow = np.where(n * tau >= 0.0, "pumping", "motoring (load drives)")
    kt = np.clip(np.searchsorted(TORQUE_BINS_NM, np.abs(tau), side="right") - 1, 0, 3)
    edges = TORQUE_BINS_NM
    tnames = [f"|torque| {edges[i]:g}-{edges[i + 1]:g} N*m" if np.isfinite(edges[i + 1])
              else f"|torque| >= {edges[i]:g} N*m" for i in range(4)]
    load = np.char.add(np.char.add(flow.astype(str), ", "), np.array(tnames)[kt])
    lo = np.floor(run.oil_temp_c / TEMP_STEP_C) * TEMP_STEP_C
    temp = np.array([f"{x:g}-{x + TEMP_STEP_C:g} degC" for x in lo])
    return {"phase": phase, "direction": direction, "load": load, "speed": speed,
            "temperature": temp}


def breakdown(runs: Sequence[AnalysisRun], estimates: Sequence[np.ndarray]
              ) -> dict[str, list[ClassStats]]:
    """Per dimension, the statistics of every class present (pooled over the runs)."""
    pooled: dict[str, list[np.ndarray]] = {}
    cols: dict[str, list[np.ndarray]] = {"dt": [], "travel": [], "de": [], "e": [],
                                         "has_e": []}
    for run, est in zip(runs, estimates):
        labels = classify(run, est)
        for dim, lab in labels.items():
            pooled.setdefault(dim, []).append(lab)
        t = run.time_s
        err = est - run.position_mm
        dt = np.diff(t, prepend=t[0])
        # the error's change between consecutive samples that both have a reference; the
        # travel is the estimate's (the reference's noise would add up while holding)
        known = np.flatnonzero(np.isfinite(run.position_mm))
        de = np.zeros(len(t))
        if len(known) > 1:
            de[known[1:]] = np.diff(err[known])
        travel = np.abs(np.diff(est, prepend=est[0]))
        cols["dt"].append(dt)
        cols["travel"].append(travel)
        cols["de"].append(de)
        cols["e"].append(np.where(np.isfinite(err), err, 0.0))
        cols["has_e"].append(np.isfinite(err))
    flat = {k: np.concatenate(v) for k, v in cols.items()}
    out: dict[str, list[ClassStats]] = {}
    for dim, labs in pooled.items():
        lab = np.concatenate(labs)
        order = list(PHASES) if dim == "phase" else list(DIRECTIONS) if dim == "direction" \
            else sorted(set(lab.tolist()))
        stats = []
        for name in order:
            m = lab == name
            if not m.any():
                continue
            time_s = float(flat["dt"][m].sum())
            travel = float(flat["travel"][m].sum())
            added = float(flat["de"][m].sum())
            e = flat["e"][m & flat["has_e"]]
            stats.append(ClassStats(
                dim, name, time_s, travel, added,
                added / time_s if time_s > 0 else float("nan"),
                added / travel * 1000.0 if travel > 1.0 else float("nan"),
                float(np.sqrt(np.mean(e ** 2))) if e.size else float("nan"),
                float(np.max(np.abs(e))) if e.size else float("nan")))
        out[dim] = stats
    return out
