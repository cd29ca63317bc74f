"""What the chamber pressures say, where the runs carry them (``p_a_bar``, ``p_b_bar``).

The pumps' torque at the motor follows from the two chamber pressures through the physics'
torque gains and efficiencies (``DDHUnit.motor_torque_nm``). Against the drive's torque less
the rotor's inertia torque, in quasi-steady samples with the motor turning, a straight line
tau = g tau_p + o gives the drive's torque gain times the pumps' displacement factor (g) and
the torque offset (o) directly, whatever the leakage, the temperature sensor or the position sensor do. That is
what separates a torque or displacement error from leakage: a candidate set whose g and o
disagree with the pressures is not an answer.

The drive's signals may lag the pressures (a logging offset: the drive's frames stamped
late, the pressures logged with the position). Compared sample by sample, a lag reads as a
wrong gain and offset and would rule out the time offset that explains the runs; so a
candidate set with a time offset is checked against the line fitted with the drive's
signals taken that much later (:meth:`TorqueEvidence.at`). A lag searched for in the
pressures alone was tried: on the boom's slow torque changes the residual hardly depends on
it (per run 0.80-0.98 of the unlagged one with a true 0.27 s offset, 0.91-0.99 without), so
it scattered the runs' gains instead.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from ddh_vsensor.diagnosis.workbench import Workbench
from ddh_vsensor.physics.conversions import RPM_RAD_S

MAX_ACCEL_RPM_S = 2000.0       # quasi-steady: the rotor's inertia torque is small
# A standing motor's pumps hold their pressures with any torque between the motoring and the
# pumping one (static friction): no line there. Without this the boom's loaded holds at 0 rpm
# pulled the line to 0.96-0.98 on random cycles with no effect at all (1.000 without them).
STANDSTILL_RPM = 0.5
MIN_SHARE_OF_MAX = 0.15        # samples with |pump torque| above this share of the maximum
MIN_SAMPLES = 200
# The pressures' line is the physics' own: its efficiencies and friction are not exactly
# the machine's; a set is refused only beyond these (gain relative, offset N*m).
GAIN_TOLERANCE = 0.02
OFFSET_TOLERANCE_NM = 1.5


@dataclass(frozen=True)
class TorqueEvidence:
    gain: float                 # drive torque per pressure torque (torque gain x displacement)
    offset_nm: float
    gain_se: float
    offset_se_nm: float
    runs: int
    lag_s: float = 0.0          # the drive's signals taken this much later than the pressures
    # the same line at another lag (None: not available)
    lagged: Callable[[float], TorqueEvidence | None] | None = field(
        default=None, compare=False, repr=False)

    def at(self, params: Mapping[str, float]) -> TorqueEvidence:
        """The evidence under ``params``' own time offset (the drive's signals lagging the
        pressures by it); this one without a time offset, or where none can be fitted."""
        lag = round(float(params.get("time_offset_s", 0.0)), 3)
        if lag == self.lag_s or self.lagged is None:
            return self
        return self.lagged(lag) or self

    def consistent(self, params: Mapping[str, float],
                   intervals: Mapping[str, tuple[float, float]] = {}) -> bool:
        """Whether a candidate set's torque gain x displacement and torque offset agree,
        within the pressures' tolerance plus the candidate's own 90 % intervals (against the
        line at the set's own time offset)."""
        return self.at(params)._agrees(params, intervals)

    def measured(self, parameter: str, params: Mapping[str, float]
                 ) -> tuple[float, tuple[float, float]] | None:
        """The value the pressures give ``parameter`` (torque_gain, displacement_factor,
        torque_offset_nm) next to the others of ``params``, with a 90 % interval (their
        spread and tolerance); None for another parameter. At ``params``' time offset."""
        return self.at(params)._value(parameter, params)

    def _agrees(self, params: Mapping[str, float],
                intervals: Mapping[str, tuple[float, float]]) -> bool:
        g = params.get("torque_gain", 1.0) * params.get("displacement_factor", 1.0)
        o = params.get("torque_offset_nm", 0.0)

        def half(key: str, log: bool) -> float:
            if key not in intervals:
                return 0.0
            lo, hi = intervals[key]
            return (np.log(hi / lo) if log else hi - lo) / 2.0

        tol_g = max(2.5 * self.gain_se, GAIN_TOLERANCE) + half("torque_gain", True) \
            + half("displacement_factor", True)
        tol_o = max(2.5 * self.offset_se_nm, OFFSET_TOLERANCE_NM) + half("torque_offset_nm",
                                                                         False)
        return abs(np.log(g / self.gain)) <= tol_g and abs(o - self.offset_nm) <= tol_o

    def _value(self, parameter: str, params: Mapping[str, float]
               ) -> tuple[float, tuple[float, float]] | None:
        if parameter == "torque_offset_nm":
            half = max(1.645 * self.offset_se_nm, OFFSET_TOLERANCE_NM / 2.0)
            return self.offset_nm, (self.offset_nm - half, self.offset_nm + half)
        other = {"torque_gain": "displacement_factor",
                 "displacement_factor": "torque_gain"}.get(parameter)
        if other is None:
            return None
        v = self.gain / params.get(other, 1.0)
        half = max(1.645 * self.gain_se, GAIN_TOLERANCE / 2.0)
        return v, (float(v * np.exp(-half)), float(v * np.exp(half)))

    def describe(self) -> str:
        return (f"chamber pressures: drive torque = {self.gain:.3f} x pressure torque "
                f"{self.offset_nm:+.2f} N*m ({self.runs} runs)")


def _run_line(unit, j: float, t: np.ndarray, speed: np.ndarray, torque: np.ndarray,
              dp_a: np.ndarray, dp_b: np.ndarray, ok: np.ndarray, lag_s: float
              ) -> np.ndarray | None:
    """The line drive torque = g x pressure torque + o with the drive's signals taken
    ``lag_s`` later than the pressures: (g, o)."""
    if lag_s:
        inside = ok & (t + lag_s >= t[0]) & (t + lag_s <= t[-1])
        n, tau_d = np.interp(t + lag_s, t, speed), np.interp(t + lag_s, t, torque)
    else:
        inside, n, tau_d = ok, speed, torque
    tau_p = np.asarray(unit.motor_torque_nm(dp_a, dp_b, n), dtype=float)
    accel = np.gradient(n, t)
    tau = tau_d - j * RPM_RAD_S * accel
    use = inside & (np.abs(accel) < MAX_ACCEL_RPM_S) & (np.abs(n) >= STANDSTILL_RPM)
    if not use.any():
        return None
    use &= np.abs(tau_p) > MIN_SHARE_OF_MAX * max(float(np.max(np.abs(tau_p[use]))), 1e-9)
    if use.sum() < MIN_SAMPLES:
        return None
    a = np.stack([tau_p[use], np.ones(int(use.sum()))], axis=1)
    coef, *_ = np.linalg.lstsq(a, tau[use], rcond=None)
    return coef


def torque_evidence(bench: Workbench, lag_s: float = 0.0) -> TorqueEvidence | None:
    """The line through the runs' quasi-steady samples, the drive's signals taken ``lag_s``
    later than the pressures (None without pressure columns)."""
    unit = bench.unit
    j = unit.motor.inertia_kg_m2
    fits = []
    for r in bench.runs:
        if r.p_a_bar is None or r.p_b_bar is None:
            continue
        ok = np.isfinite(r.p_a_bar) & np.isfinite(r.p_b_bar)
        if ok.sum() < MIN_SAMPLES:
            continue
        dp_a = np.where(ok, r.p_a_bar, 0.0) * 1e5 - unit.reservoir_pa
        dp_b = np.where(ok, r.p_b_bar, 0.0) * 1e5 - unit.reservoir_pa
        got = _run_line(unit, j, np.asarray(r.time_s, float), np.asarray(r.speed_rpm, float),
                        np.asarray(r.torque_nm, float), dp_a, dp_b, ok, lag_s)
        if got is not None:
            fits.append(got)
    if len(fits) < 2:
        return None
    c = np.array(fits)
    k = len(c)
    se = c.std(axis=0, ddof=1) / np.sqrt(k)
    return TorqueEvidence(float(np.median(c[:, 0])), float(np.median(c[:, 1])),
                          float(se[0] / abs(np.median(c[:, 0]))), float(se[1]), k, lag_s,
                          None if lag_s else functools.lru_cache(maxsize=32)(
                              functools.partial(torque_evidence, bench)))
