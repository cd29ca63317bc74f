"""The catalogue of candidate causes: each a physical extension of the model, with its
parameter, its physical range, and how it changes the estimate.

A cause's ``deltas`` are the changes of the position estimate it makes at given parameter
values, run by run, relative to the baseline estimate (the estimator as it stands, in the
analysed mode). They are computed with the extended model itself, not a linearisation:

``pump_leakage`` (factor on every pump's laminar leakage coefficient)
    tables of ``unit.with_pumps(leakage=f)``; leakage flow ~ pressure / viscosity, so the
    error grows with load and temperature and shows as creep while a load is held.
``displacement`` (factor on every pump's displacement)
    tables of ``unit.with_pumps(displacement=d)``; the error grows with travel.
``belt_slip`` (% speed-ratio drop per 100 N*m of |motor torque|)
    the pumps turn at n (1 - s/100 |tau|/100): the lookup takes that speed (the torque ratio,
    hence the pressures at a torque, is unchanged). Error ~ speed x |torque|: lifting loaded.
``time_offset`` (s the logged motor signals lag the position)
    speed and torque are taken that much later; error ~ -velocity x offset, gone at rest.
``compressibility`` (air volume fraction at atmospheric pressure)
    the compressible-chamber model of :mod:`.chambers` with the oil-air law instead of the
    tables: the oil a chamber takes to change its pressure does not move the rod, and at low
    pressure air makes that volume large. The model also holds the nominal oil's
    compression, which the tables leave out, so without any air it already fits better than
    the tables: an air fraction is named only beyond its resolution (see ``selection``).
``oil_temp_offset`` (degC the tank sensor reads above the oil the pumps see)
    the estimator takes logged temperature minus the offset: viscosity, hence leakage.
``torque_gain``, ``torque_offset`` (the drive's torque reads g x true + o)
    the estimator takes (logged - o) / g: the pressures it infers, hence leakage and valves.
``position_scale`` (the reference sensor reads s x true position)
    the comparison takes s x the estimate (started from the first reading / s). A constant
    offset of that sensor cannot be seen: the estimate starts at its first reading, so the
    offset cancels from every comparison (the Hall switches would show it).
``low_speed_leakage`` (no parameter; ``paper`` mode only)
    the speed-continuous tables instead of the paper's three speed ranges: the ranges' mm
    per revolution is wrong where leakage dominates, i.e. at low speed, and a held load
    creeps in the estimate.
``none``
    the model as it is.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ddh_vsensor.diagnosis.workbench import Workbench

Deltas = list[list[np.ndarray]]          # [parameter value][run] -> mm per sample


@dataclass(frozen=True)
class Cause:
    name: str
    parameter: str | None               # key of its parameter in reports and extensions
    unit: str
    neutral: float | None
    bounds: tuple[float, float] | None
    grid: tuple[float, ...]             # coarse search grid (within bounds, with neutral)
    log: bool                           # search on a log scale (factors)
    summary: str                        # what it is, physically
    signature: str                      # how it shows in the error
    resolution: float = 0.0             # smallest deviation from neutral it is named for
                                        # (relative for factors; see ``selection``)
    # The parameter value of a deviation that matters in service (well beyond ``resolution``,
    # about the low end of what the trials hide): a diagnosis that cannot see a cause this
    # large says so instead of answering none (:mod:`.observability`).
    reference_size: float | None = None
    # What the cause's error grows with, in the evidence: "travel" (distance moved between
    # references), "holds" (creep of a held load), or "motion" (speed and its changes).
    grows_with: str = "motion"
    shown_by: str = ""                  # runs that would show it, where these did not

    @property
    def parameters(self) -> int:
        return 0 if self.parameter is None else 1

    def applicable(self, mode: str) -> bool:
        return True

    def deltas(self, bench: Workbench, base: Sequence[np.ndarray],
               values: Sequence[float]) -> Deltas:
        raise NotImplementedError

    def resolved(self, value: float | None) -> bool:
        """Whether a fitted value is beyond what the model's own error can mimic."""
        if value is None or self.neutral is None:
            return True
        if self.log:
            return abs(np.log(value / self.neutral)) >= np.log1p(self.resolution)
        return abs(value - self.neutral) >= self.resolution

    def clip(self, value: float) -> float:
        lo, hi = self.bounds  # type: ignore[misc]
        return float(min(max(value, lo), hi))


def _minus(runs: Sequence[np.ndarray], base: Sequence[np.ndarray]) -> list[np.ndarray]:
    return [x - b for x, b in zip(runs, base)]


class _None(Cause):
    def deltas(self, bench, base, values):
        return [[np.zeros_like(b) for b in base]]


class _LowSpeedLeakage(Cause):
    def applicable(self, mode: str) -> bool:
        return mode == "paper"

    def deltas(self, bench, base, values):
        if bench.mode != "paper":
            return [[np.zeros_like(b) for b in base]]
        return [_minus(bench.full_estimate, base)]


class _Parametric(Cause):
    """A cause evaluated by the workbench's extended model with its one parameter set."""

    def deltas(self, bench, base, values):
        sets = [{self.parameter: float(v)} for v in values]
        return [_minus(x, base) for x in bench.evaluate_many(sets)]


NONE = _None("none", None, "", None, None, (), False,
             "nothing beyond the model is significant", "no structure the causes explain")
CAUSES: dict[str, Cause] = {c.name: c for c in (
    _LowSpeedLeakage(
        "low_speed_leakage", None, "", None, None, (), False,
        "three speed ranges cannot represent the leakage at low speed",
        "creep while a load is held (motor turning at the leakage speed)",
        grows_with="holds", shown_by="a hold of the load away from the stroke ends"),
    _Parametric(
        "pump_leakage", "leakage_factor", "x nominal", 1.0, (0.05, 50.0),
        (0.05, 0.1, 0.2, 0.35, 0.5, 0.7, 0.85, 1.0, 1.2, 1.5, 2.0, 3.0, 5.0, 10.0, 20.0, 50.0),
        True, "pump leakage differs from the nominal efficiencies (wear, oil)",
        "error rate ~ pressure / viscosity; creep while holding; larger when warm",
        resolution=0.10, reference_size=1.5, grows_with="holds",
        shown_by="a hold of the load for a few seconds away from the stroke ends"),
    _Parametric(
        "compressibility", "air_fraction", "volume fraction at 1 atm", 0.0, (0.0, 0.19),
        (0.0, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.19), False,
        "entrained air: the oil compresses more than modelled at low pressure",
        "offsets at pressure changes from low pressure; does not grow with travel",
        resolution=0.005, reference_size=0.02,
        shown_by="starts from rest at low pressure between two references"),
    _Parametric(
        "belt_slip", "slip_percent_per_100nm", "% per 100 N*m", 0.0, (0.0, 30.0),
        (0.0, 0.5, 1.0, 2.0, 3.5, 5.0, 7.5, 10.0, 15.0, 20.0, 30.0), False,
        "the belt's speed ratio drops with transmitted torque",
        "error rate ~ speed x |torque|: lifting loaded, not lowering", resolution=1.0,
        reference_size=5.0, grows_with="travel",
        shown_by="a loaded lift from one switch to another"),
    _Parametric(
        "displacement", "displacement_factor", "x nominal", 1.0, (0.7, 1.4),
        (0.7, 0.8, 0.9, 0.95, 0.98, 0.99, 1.0, 1.01, 1.02, 1.05, 1.1, 1.2, 1.4), True,
        "the pumps' effective displacement differs from nominal",
        "error ~ travel, both directions, any load or temperature", resolution=0.005,
        reference_size=1.03, grows_with="travel",
        shown_by="a run crossing two switches in one stroke"),
    _Parametric(
        "time_offset", "time_offset_s", "s (motor signals lag the position)", 0.0, (-1.0, 1.0),
        (-1.0, -0.5, -0.25, -0.12, -0.06, -0.03, -0.01, 0.0, 0.01, 0.03, 0.06, 0.12, 0.25, 0.5,
         1.0), False,
        "the motor signals and the position are not aligned in time",
        "error ~ -velocity x offset; vanishes at rest, does not accumulate",
        resolution=0.010, reference_size=0.05,
        shown_by="switches passed at different speeds (fast one way, slow the other)"),
    _Parametric(
        "oil_temp_offset", "oil_temp_offset_c", "degC (the tank sensor reads true + offset)",
        0.0, (-30.0, 30.0), (-30.0, -20.0, -12.0, -6.0, -3.0, 0.0, 3.0, 6.0, 12.0, 20.0, 30.0),
        False, "the oil temperature sensor reads off (or the pumps run warmer than the tank)",
        "as a leakage factor that changes with temperature (viscosity ~ exp(-b T))",
        resolution=3.0, reference_size=10.0, grows_with="holds",
        shown_by="holds of the load at two oil temperatures"),
    _Parametric(
        "torque_gain", "torque_gain", "x true (the drive's torque estimate)", 1.0, (0.5, 2.0),
        (0.5, 0.7, 0.8, 0.9, 0.95, 1.0, 1.05, 1.1, 1.25, 1.4, 2.0), True,
        "the drive's torque (an estimate from current) is off by a factor",
        "as leakage (pressure inferred wrong); chamber pressures give it away at once",
        resolution=0.03, reference_size=1.1, grows_with="holds",
        shown_by="holds at two loads, or the chamber pressure columns p_a_bar, p_b_bar"),
    _Parametric(
        "torque_offset", "torque_offset_nm", "N*m (added to the true torque)", 0.0,
        (-20.0, 20.0), (-20.0, -10.0, -5.0, -2.0, -1.0, 0.0, 1.0, 2.0, 5.0, 10.0, 20.0), False,
        "the drive's torque reads an offset",
        "creep while holding unloaded, in the offset's direction; no change with load",
        resolution=1.0, reference_size=5.0, grows_with="holds",
        shown_by="a hold unloaded away from the stroke ends"),
    _Parametric(
        "position_scale", "position_scale", "x true (the reference sensor)", 1.0, (0.8, 1.25),
        (0.8, 0.9, 0.95, 0.98, 0.99, 1.0, 1.01, 1.02, 1.05, 1.1, 1.25), True,
        "the reference position sensor's scale is off (the estimate may be right)",
        "error ~ distance from the sensor's zero; as displacement without pressure data",
        resolution=0.005, reference_size=1.03, grows_with="travel",
        shown_by="the draw-wire position logged over a long stroke"),
)}
ALL_CAUSES: dict[str, Cause] = {NONE.name: NONE, **CAUSES}
CAUSE_NAMES = tuple(ALL_CAUSES)
