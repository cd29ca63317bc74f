"""The feature that gives each cause away, and the error seen against it.

For a cause whose error accumulates (leakage, displacement, belt slip, low-speed leakage) the
error *rate* over short windows is set against the feature's mean over the same windows: a
straight line through the origin is the cause's signature. For a cause whose error does not
accumulate (time offset, compressibility) the error itself is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ddh_vsensor.diagnosis.breakdown import motion
from ddh_vsensor.diagnosis.causes import ALL_CAUSES
from ddh_vsensor.diagnosis.workbench import Workbench

WINDOW_S = 0.5


@dataclass(frozen=True)
class Signature:
    label: str                  # x axis
    accumulates: bool           # y is an error rate (mm/s) if True, else an error (mm)
    x: list[np.ndarray]         # per run, per window (accumulating) or per sample


def _windows(t: np.ndarray) -> list[slice]:
    edges = np.searchsorted(t, np.arange(t[0], t[-1] + WINDOW_S, WINDOW_S))
    return [slice(a, b) for a, b in zip(edges[:-1], edges[1:]) if b - a >= 2]


def windowed_rate(t: np.ndarray, err: np.ndarray) -> np.ndarray:
    """Mean rate of change of ``err`` (mm/s) over each window (reference samples only)."""
    out = []
    for w in _windows(t):
        tt, ee = t[w], err[w]
        ok = np.isfinite(ee)
        out.append((ee[ok][-1] - ee[ok][0]) / (tt[ok][-1] - tt[ok][0])
                   if ok.sum() >= 2 and tt[ok][-1] > tt[ok][0] else np.nan)
    return np.array(out)


def windowed_mean(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    return np.array([float(np.mean(x[w])) for w in _windows(t)])


def signature(cause: str, bench: Workbench) -> Signature:
    """The feature of ``cause`` for every run of the bench."""
    runs, base = bench.runs, bench.base
    velocity = [motion(r.time_s, x)[0] for r, x in zip(runs, base)]
    if cause == "pump_leakage":
        # the velocity the nominal leakage takes (linear in the factor: f=1 minus f=2)
        doubled = ALL_CAUSES["pump_leakage"].deltas(bench, base, [2.0])[0]
        feats = [-windowed_rate(r.time_s, d) for r, d in zip(runs, doubled)]
        return Signature("velocity lost to the nominal pump leakage (mm/s)", True, feats)
    if cause == "belt_slip":
        return Signature("velocity x |torque| / 100 N*m (mm/s)", True,
                         [windowed_mean(r.time_s, v * np.abs(r.torque_nm) / 100.0)
                          for r, v in zip(runs, velocity)])
    if cause == "low_speed_leakage":
        return Signature("|motor speed| (rpm)", True,
                         [windowed_mean(r.time_s, np.abs(r.speed_rpm)) for r in runs])
    if cause == "time_offset":
        return Signature("estimated velocity (mm/s)", False, velocity)
    if cause == "compressibility":
        air = bench.chambers([0.05])[0]
        feats = [-(a - z) for a, z in zip(air, bench.nominal_chambers)]
        return Signature("error the chamber model predicts for 5 % air (mm)", False, feats)
    return Signature("estimated velocity (mm/s)", True,
                     [windowed_mean(r.time_s, v) for r, v in zip(runs, velocity)])


def signature_errors(sig: Signature, bench: Workbench, errors: list[np.ndarray]
                     ) -> list[np.ndarray]:
    """The errors (per sample, NaN without reference) to plot against the signature."""
    if not sig.accumulates:
        return errors
    return [windowed_rate(r.time_s, e) for r, e in zip(bench.runs, errors)]
