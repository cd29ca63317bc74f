"""What the chamber pressures say, where the runs carry them (``p_a_bar``, ``p_b_bar``).

The pumps' torque at the motor follows from the two chamber pressures through the physics'
torque gains and efficiencies (``DDHUnit.motor_torque_nm``). Against the drive's torque less
the rotor's inertia torque, in quasi-steady samples with the motor turning, a straight line
tau = g tau_p + o gives the drive's torque gain times the pumps' displacement factor (g) and
the torque offset (o) directly, whatever the leakage, the temperature sensor or the position
sensor do. That is what separates a torque or displacement error from leakage: a candidate
set whose g and o disagree with the pressures is not an answer.

The drive's signals may lag the pressures (a logging offset: the drive's frames stamped
late, the pressures logged with the position). Compared sample by sample, a lag reads as a
wrong gain and offset and would rule out the time offset that explains the runs; so a
candidate set with a time offset is checked against the line fitted with the drive's
signals taken that much later (:meth:`TorqueEvidence.at`). A lag searched for in the
pressures alone was tried: on the boom's slow torque changes the residual hardly depends on
it (per run 0.80-0.98 of the unlagged one with a true 0.27 s offset, 0.91-0.99 without), so
it scattered the runs' gains instead.

On a machine the drive's torque estimate is not the pressures' torque even without any
effect (its own lag, offsets, the pumps' real efficiencies): its baseline (``commission``)
holds that line and its spread from run to run, and the evidence is then read relative to it
(:meth:`TorqueEvidence.against`).
"""

from __future__ import annotations

import dataclasses
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
class OwnLine:
    """The machine's own line without any effect (its baseline) and the tolerances it sets:
    the measured line is read relative to it."""

    gain: float
    offset_nm: float
    gain_tolerance: float           # relative (log), at least GAIN_TOLERANCE
    offset_tolerance_nm: float      # at least OFFSET_TOLERANCE_NM


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
    own: OwnLine | None = None  # the machine's line without any effect (None: g 1, o 0)

    def against(self, own: OwnLine | None) -> TorqueEvidence:
        """The evidence read relative to the machine's own line (``None``: the physics')."""
        return dataclasses.replace(self, own=own)

    @property
    def relative_gain(self) -> float:
        """The drive's gain over the pressures' torque beyond the machine's own."""
        return self.gain / (self.own.gain if self.own else 1.0)

    @property
    def relative_offset_nm(self) -> float:
        return self.offset_nm - (self.own.offset_nm if self.own else 0.0)

    @property
    def tolerances(self) -> tuple[float, float]:
        """(gain, relative; offset, N*m) within which a set agrees, before the line's own
        standard errors and the set's intervals."""
        if self.own is None:
            return GAIN_TOLERANCE, OFFSET_TOLERANCE_NM
        return self.own.gain_tolerance, self.own.offset_tolerance_nm

    def at(self, params: Mapping[str, float]) -> TorqueEvidence:
        """The evidence under ``params``' own time offset (the drive's signals lagging the
        pressures by it); this one without a time offset, or where none can be fitted."""
        lag = round(float(params.get("time_offset_s", 0.0)), 3)
        if lag == self.lag_s or self.lagged is None:
            return self
        other = self.lagged(lag)
        return self if other is None else other.against(self.own)

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

        gain_tol, offset_tol = self.tolerances
        tol_g = max(2.5 * self.gain_se, gain_tol) + half("torque_gain", True) \
            + half("displacement_factor", True)
        tol_o = max(2.5 * self.offset_se_nm, offset_tol) + half("torque_offset_nm", False)
        return abs(np.log(g / self.relative_gain)) <= tol_g \
            and abs(o - self.relative_offset_nm) <= tol_o

    def _value(self, parameter: str, params: Mapping[str, float]
               ) -> tuple[float, tuple[float, float]] | None:
        gain_tol, offset_tol = self.tolerances
        if parameter == "torque_offset_nm":
            half = max(1.645 * self.offset_se_nm, offset_tol / 2.0)
            o = self.relative_offset_nm
            return o, (o - half, o + half)
        other = {"torque_gain": "displacement_factor",
                 "displacement_factor": "torque_gain"}.get(parameter)
        if other is None:
            return None
        v = self.relative_gain / params.get(other, 1.0)
        half = max(1.645 * self.gain_se, gain_tol / 2.0)
        return v, (float(v * np.exp(-half)), float(v * np.exp(half)))

    def describe(self) -> str:
        said = (f"chamber pressures: drive torque = {self.gain:.3f} x pressure torque "
                f"{self.offset_nm:+.2f} N*m ({self.runs} runs)")
        if self.own is None:
            return said
        own = self.own
        return (f"{said}; the machine's own line {own.gain:.3f} x {own.offset_nm:+.2f} N*m "
                f"(its baseline), within {100 * own.gain_tolerance:.1f} % and "
                f"{own.offset_tolerance_nm:.2f} N*m")


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


def run_lines(bench: Workbench, lag_s: float = 0.0) -> list[tuple[str, float, float]]:
    """(run, gain, offset N*m) of each run with pressures enough for a line."""
    unit = bench.unit
    j = unit.motor.inertia_kg_m2
    out = []
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
            out.append((r.name, float(got[0]), float(got[1])))
    return out


def torque_evidence(bench: Workbench, lag_s: float = 0.0) -> TorqueEvidence | None:
    """The line through the runs' quasi-steady samples, the drive's signals taken ``lag_s``
    later than the pressures (None without pressure columns)."""
    fits = [(g, o) for _, g, o in run_lines(bench, lag_s)]
    if len(fits) < 2:
        return None
    c = np.array(fits)
    k = len(c)
    se = c.std(axis=0, ddof=1) / np.sqrt(k)
    return TorqueEvidence(float(np.median(c[:, 0])), float(np.median(c[:, 1])),
                          float(se[0] / abs(np.median(c[:, 0]))), float(se[1]), k, lag_s,
                          None if lag_s else functools.lru_cache(maxsize=32)(
                              functools.partial(torque_evidence, bench)))
