"""Deciding what the runs say: a set of causes, an ambiguity, none, or unexplained.

The rules, each set from what the model's own error looks like without any effect and with
single catalogued effects (numbers in diagnosis/README.md), never from the open-set trials:

1. A cause is a candidate only if its fitted parameter is *resolved* (further from neutral
   than the model's own error can mimic: each cause's ``resolution``) and, where the runs
   carry chamber pressures, agrees with what they measure (:mod:`.pressures`).
2. The set grows from the best single candidate, one cause at a time, up to three; a cause
   joins only if the joint fit, cross-validated, removes at least :data:`MIN_ADDED` of the
   held-out error left without it and every parameter stays resolved, and none joins a set
   that leaves no more than the chamber model's own error (:data:`GROWTH_FLOOR_RMS_MM`: a
   torque gain of 1.03 took half of the 0.04 mm RMS a leakage of x 0.57 left; at the tables'
   0.5 mm, air or an oil offset next to a leakage that left 0.45 mm were kept out). Every
   cause is fitted
   exactly as the second (a linearised screen ranked air last where it made a torque offset
   exact); the third from the two the screen ranks best. A set the pressures disagree with
   is no answer: the cause they point at joins at its measured value (to the grown set or to
   its first cause alone), a member it leaves unresolved goes (it stood in for it), and the
   set counts if it leaves at most 1 / (1 - :data:`MIN_ADDED`) times the error the
   disagreeing set left. Where no single cause agrees with the pressures, sets are grown from
   the two best (a torque error hides leakage and an oil temperature offset alike), and
   where none is resolved but the pressures see a torque-chain error, from the two best fits
   as they are (the set must end resolved).
3. The set is named when it explains :data:`MIN_SCORE` of the held-out squared error, one
   parameter value describes every run (not: held-out error over each run's own best fit
   above :data:`MAX_HETEROGENEITY` *and* the difference :data:`RESIDUAL_SHARE` of the
   original error) and the residual model finds no structured error left (it must not
   remove :data:`MIN_ADDED` of what is left *and* :data:`RESIDUAL_SHARE` of the original,
   *and* what is left must be more than the model's own error: :data:`OWN_ERROR_RMS_MM`.
   The residual model removes ~75 % of the own error itself, so a small effect, named
   right, left only that and was called unexplained).
4. Two candidates are *ambiguous* when the second leaves at most :data:`AMBIGUITY_RATIO`
   times the held-out error of the first (counted at no less than the machine's own error,
   where a baseline gives it: :class:`Thresholds`); if the largest contributor is ambiguous
   the answer is ``ambiguous``, never one of the two.
5. Otherwise ``unexplained`` if the model's held-out error is more than its own
   (:data:`OWN_ERROR_RMS_MM`: a flexible model finds structure in any own error; without an
   effect, the boom on random cycles, 0.38 mm at most, was answered ``unexplained``), the
   residual model explains :data:`MIN_SCORE` of the
   held-out error and leaves at most :data:`MIN_ADDED` of what the best *unresolved* fit
   leaves (that fit is the model's own error, mimicked: without any effect the chamber
   model at nominal oil explains ~90 % of it; the residual model, being flexible, ~75 %);
   the extension is then that model. Else ``none``.
6. A ``none`` holds only for the causes the runs could show: each cause at its catalogue's
   reference size is checked against the evidence (:mod:`.observability`), and those it
   could not show are listed with the answer (``Decision.not_observable``).

The own-error constants are our simulator's, where the nominal model is nearly exact; with a
machine's baseline (``commission``, ``analyze --baseline``) each is judged against that
machine's own error instead (:class:`Thresholds`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ddh_vsensor.diagnosis.pressures import OwnLine

MIN_SCORE = 0.6
MIN_ADDED = 0.5
MAX_HETEROGENEITY = 3.0
RESIDUAL_SHARE = 0.03
AMBIGUITY_RATIO = 1.25
# The nominal model's own held-out error (RMS) on runs without an effect, 90th percentile of
# 32 analyses (paper cycles 0.16-0.33 mm, random cycles 0.10-0.79 mm; diagnosis/README.md)
OWN_ERROR_RMS_MM = 0.5
MAX_CAUSES = 3
# The chamber model's own held-out error (RMS) without any effect: 0.03-0.10 mm on 100
# analyses (seeds 29000 and 33000, paper and random cycles). A set that leaves no more has
# nothing left for a further cause to explain (what fits half of it is noise).
GROWTH_FLOOR_RMS_MM = 0.1
# With a machine's baseline (``commission``), its own error replaces these: an analysis of
# the machine's effect-free runs errs by up to OWN_SPREAD x the baseline's RMS (run-to-run
# spread: other cycles, loads and temperatures than the baseline's runs; docs/diagnosis.md).
OWN_SPREAD = 2.0
SIMULATOR = "the simulator's"

# What would tell two look-alikes apart (order-free pairs); the default names the signatures.
SEPARATE: dict[frozenset[str], str] = {
    frozenset({"pump_leakage", "oil_temp_offset"}):
        "a run at another oil temperature (a leakage factor stays the same, a sensor offset "
        "changes it), or the tank sensor against a reference thermometer",
    frozenset({"pump_leakage", "torque_gain"}):
        "the chamber pressure columns p_a_bar, p_b_bar (a torque gain error shows as drive "
        "torque / pressure torque != 1, leakage does not)",
    frozenset({"pump_leakage", "torque_offset"}):
        "a hold at two loads (an offset creeps the same, leakage with the pressure), or the "
        "pressure columns",
    frozenset({"displacement", "position_scale"}):
        "the pressure columns (a displacement error changes torque per bar, a sensor scale "
        "does not), or a move between the two Hall switches",
    frozenset({"displacement", "torque_gain"}):
        "a hold at two loads (displacement errs with travel, a torque gain with load)",
    frozenset({"belt_slip", "displacement"}):
        "the same move loaded and unloaded (slip grows with torque, displacement does not)",
    frozenset({"time_offset", "compressibility"}):
        "a step in speed from rest at low pressure (air delays the start, a logging offset "
        "shifts start and stop alike)",
}


def separation(a: str, b: str) -> str:
    from ddh_vsensor.diagnosis.causes import ALL_CAUSES
    hint = SEPARATE.get(frozenset({a, b}))
    if hint:
        return hint
    sig = {c: ALL_CAUSES[c].signature for c in (a, b) if c in ALL_CAUSES}
    return ("runs that excite one signature but not the other: " +
            "; ".join(f"{c}: {s}" for c, s in sig.items()))


@dataclass(frozen=True)
class Decision:
    cause: str                              # largest contributor, ambiguous, none, unexplained
    reason: str
    rms_before_mm: float
    rms_after_mm: float
    ambiguous: list[tuple[str, str]] = field(default_factory=list)
    # (cause, why, what would show it) of each cause the runs could not show at its
    # catalogue's reference size (:mod:`.observability`); a ``none`` is only as good as it
    not_observable: list[tuple[str, str, str]] = field(default_factory=list)


@dataclass(frozen=True)
class OwnError:
    """A machine's own error per kind of evidence (RMS, mm; None: its baseline has none),
    measured by ``commission`` on runs its model was not fitted to."""

    position_rms_mm: float | None
    references_rms_mm: float | None
    holds_rms_mm: float | None
    source: str                     # the baseline file and its date, for the answer
    pressure_line: OwnLine | None = None    # the drive's torque against the pressures'


@dataclass(frozen=True)
class Thresholds:
    """What the decision takes for the model's own error: the simulator's constants, or
    each raised to the machine's (:data:`OWN_SPREAD` x its baseline's RMS, never below the
    simulator's: there the model is its own plant, so no machine errs less).

    With a baseline two further rules use the machine's own error: a best candidate's
    held-out error counts at no less than it when a rival is judged ambiguous (rule 4), and
    a set leaving no more than OWN_SPREAD x it cannot show that it only mimics (rule 3's
    heterogeneity)."""

    evidence: str                   # "positions" or "references"
    source: str                     # SIMULATOR, or the baseline file
    # the machine's own error, its baseline's RMS for this evidence (0 for the simulator's:
    # its model is nearly exact)
    machine_rms_mm: float = 0.0
    own_error_rms_mm: float = OWN_ERROR_RMS_MM          # positions: OWN_ERROR_RMS_MM
    growth_floor_rms_mm: float = GROWTH_FLOOR_RMS_MM    # positions: GROWTH_FLOOR_RMS_MM
    left_rms_mm: float = 0.0                            # references: LEFT_RMS_MM
    unexplained_rms_mm: float = 0.0                     # references: UNEXPLAINED_RMS_MM
    # positions with pressures: the machine's line (None: the physics', within the
    # pressures' GAIN_TOLERANCE and OFFSET_TOLERANCE_NM)
    pressure_line: OwnLine | None = None

    @property
    def simulator(self) -> bool:
        return self.source == SIMULATOR

    @classmethod
    def positions(cls, own: OwnError | None) -> Thresholds:
        """The position analysis's: own error and growth floor, each the larger of the
        simulator's constant and the machine's position RMS x :data:`OWN_SPREAD`."""
        if own is None:
            return cls("positions", SIMULATOR)
        if own.position_rms_mm is None:
            raise ValueError("the baseline has no position residuals")
        machine = own.position_rms_mm
        return cls("positions", own.source, machine, max(OWN_ERROR_RMS_MM, OWN_SPREAD * machine),
                   max(GROWTH_FLOOR_RMS_MM, OWN_SPREAD * machine),
                   pressure_line=own.pressure_line)

    @property
    def mixed_floor_rms_mm(self) -> float:
        """What a set may leave and still be judged by its runs' heterogeneity."""
        return OWN_SPREAD * self.machine_rms_mm

    def as_dict(self) -> dict[str, object]:
        values = {"own_error_rms_mm": self.own_error_rms_mm,
                  "growth_floor_rms_mm": self.growth_floor_rms_mm} \
            if self.evidence == "positions" else \
            {"left_rms_mm": self.left_rms_mm, "unexplained_rms_mm": self.unexplained_rms_mm}
        line = self.pressure_line
        return {"source": "simulator" if self.simulator else "baseline",
                "baseline": None if self.simulator else self.source,
                "machine_rms_mm": round(self.machine_rms_mm, 4),
                **{k: round(v, 4) for k, v in values.items()},
                "pressure_line": None if line is None else {
                    "gain": round(line.gain, 4), "offset_nm": round(line.offset_nm, 3),
                    "gain_tolerance": round(line.gain_tolerance, 4),
                    "offset_tolerance_nm": round(line.offset_tolerance_nm, 3)}}

    def describe(self) -> str:
        """One line for the answer: whose thresholds, and what they are."""
        values = (f"own error {self.own_error_rms_mm:.2f} mm RMS, growth floor "
                  f"{self.growth_floor_rms_mm:.2f} mm" if self.evidence == "positions" else
                  f"a named cause may leave {self.left_rms_mm:.2f} mm RMS, unexplained beyond "
                  f"{self.unexplained_rms_mm:.2f} mm")
        if self.simulator:
            return (f"thresholds: the simulator's, where the nominal model is nearly exact "
                    f"({values}); --baseline FILE (from commission) judges them against "
                    "this machine's own error")
        line = self.pressure_line
        if line is not None:
            values += (f"; the pressures against its own line {line.gain:.3f} x "
                       f"{line.offset_nm:+.2f} N*m within {100 * line.gain_tolerance:.1f} % "
                       f"and {line.offset_tolerance_nm:.2f} N*m")
        return (f"thresholds: the machine's baseline {self.source}, its own error "
                f"{self.machine_rms_mm:.2f} mm RMS (thresholds {OWN_SPREAD:g} x it, at least "
                f"the simulator's: {values})")


def rms(residuals: Sequence[np.ndarray], weights: Sequence[float]) -> float:
    num = sum(w * float(np.dot(r, r)) for r, w in zip(residuals, weights))
    den = sum(w * len(r) for r, w in zip(residuals, weights))
    return float(np.sqrt(num / den)) if den else 0.0


def bound(cause) -> str:
    if cause.log:
        return (f"x{1 + cause.resolution:g} or x{1 / (1 + cause.resolution):.3g} "
                f"{cause.unit}")
    return f"{cause.resolution:g} {cause.unit} from {cause.neutral:g}"


def alike(rival_sse: float, best_sse: float, floor_sse: float = 0.0) -> bool:
    """Rule 4: a rival leaves at most :data:`AMBIGUITY_RATIO` times what the best leaves,
    counted at no less than the machine's own error (``floor_sse``: its squared own error
    over the samples; 0 for the simulator's, where the model is nearly exact)."""
    return rival_sse <= AMBIGUITY_RATIO * max(best_sse, floor_sse)


def decide_single(fits: Sequence, target: Sequence[np.ndarray],
                  weights: Sequence[float], machine_rms_mm: float = 0.0) -> Decision:
    """The one-cause decision on ``fits`` (best first) for the baseline residual ``target``:
    the best cause is named only beyond MIN_SCORE and beyond what the model's own error can
    mimic. Used where the data cannot carry joint fits (references and holds only).
    ``machine_rms_mm``: the machine's own error (its baseline), below which two candidates'
    held-out errors do not tell them apart."""
    best = fits[0]
    before, after = rms(target, weights), rms(best.heldout, weights)
    share = f"{100 * best.score:.0f} %"
    if best.cause.name == "none":
        return Decision("none", "no cause explains any of the held-out error", before, before)
    if best.score < MIN_SCORE:
        return Decision("none", f"the best candidate, {best.cause.name}, explains {share} of "
                        "the held-out squared error (after its parameter penalty); naming a "
                        f"cause needs {100 * MIN_SCORE:.0f} %", before, before)
    if not best.cause.resolved(best.value):
        return Decision("none", f"the best candidate, {best.cause.name}, fits "
                        f"{best.cause.parameter} = {best.value:.4g}, within what the model's "
                        f"own error can mimic (named from {bound(best.cause)})", before, before)
    # rule 4, as the position analysis has it: a rival that leaves nearly as little
    rivals = [f for f in fits[1:] if f.cause.name != "none" and f.score >= MIN_SCORE
              and f.cause.resolved(f.value)
              and alike(rms(f.heldout, weights) ** 2, after ** 2, machine_rms_mm ** 2)]
    if rivals:
        first, second = best.cause.name, rivals[0].cause.name
        return Decision("ambiguous", f"{first} and {second} explain the held-out error alike "
                        f"(RMS {before:.2f} -> {after:.2f} / "
                        f"{rms(rivals[0].heldout, weights):.2f} mm); what would separate "
                        f"them: {separation(first, second)}", before, before,
                        [(first, f.cause.name) for f in rivals])
    return Decision(best.cause.name, f"{best.cause.name} explains {share} of the held-out "
                    f"squared error (RMS {before:.2f} -> {after:.2f} mm)", before, after)
