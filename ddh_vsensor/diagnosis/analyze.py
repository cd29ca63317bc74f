"""The diagnosis of one actuator over a set of runs: what is wrong, why (one or several
causes, or none the catalogue has), how sure, and the gain of the extended model on runs it
was not fitted to. The rules are in :mod:`.selection`; which causes the runs could show at all,
in :mod:`.observability`."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ddh_vsensor.config import Config
from ddh_vsensor.errors import UserError
from ddh_vsensor.diagnosis.causes import ALL_CAUSES, Cause
from ddh_vsensor.diagnosis.fit import CauseFit, fit_cause, rescore
from ddh_vsensor.diagnosis.joint import SetFit, fit_set, screen
from ddh_vsensor.diagnosis.observability import (Observability, observe_positions,
                                                 with_observability)
from ddh_vsensor.diagnosis.pressures import TorqueEvidence, torque_evidence
from ddh_vsensor.diagnosis.residual import ResidualFit, fit_residual
from ddh_vsensor.diagnosis.runs import AnalysisRun
from ddh_vsensor.diagnosis.selection import (MAX_CAUSES, MAX_HETEROGENEITY, MIN_ADDED,
                                             MIN_SCORE, RESIDUAL_SHARE, Decision, OwnError,
                                             Thresholds, alike, bound, rms)
from ddh_vsensor.diagnosis.workbench import Workbench, resolve_mode

Progress = Callable[[str, float], None]
# exact fits tried: every other cause as the second, two as the third
CANDIDATES_PER_STEP = (8, 2)
# Causes fitted on both torques (a valve regime can hinge on a few N*m in a transient); the
# others on the torque that suits the model without any cause.
PRESSURE_CAUSES = ("torque_gain", "torque_offset", "displacement")   # what pressures measure
INCONSISTENT_STARTS = 2     # the best single causes a set is grown from when none agrees
BOTH_TORQUES = ("pump_leakage", "belt_slip", "displacement", "time_offset")


@dataclass
class Diagnosis:
    actuator: str
    mode: str
    runs: list[AnalysisRun]
    bench: Workbench
    baseline: list[np.ndarray]          # the estimator as it is: estimate minus reference
    model: list[np.ndarray]             # the same with the motor inertia (if it helps)
    fits: list[CauseFit]                # single causes, best first; against ``model``'s error
    decision: Decision
    chosen_set: SetFit | None = None    # the named set (or the nearest, if not named)
    shares: dict[str, float] = field(default_factory=dict)   # cause -> share of held-out SSE
    residual: ResidualFit | None = None  # the residual model (on top of the set, if named)
    residual_base: dict[str, float] = field(default_factory=dict)   # its base parameters
    evidence: TorqueEvidence | None = None
    heldout: list[np.ndarray] = field(default_factory=list)   # the extension's, per run
    extension_inertia: bool | None = None   # the extension's motor_inertia (None: the set's)
    observability: list[Observability] = field(default_factory=list)   # per checked cause
    thresholds: Thresholds = field(default_factory=lambda: Thresholds.positions(None))

    @property
    def cause(self) -> str:
        return self.decision.cause

    @property
    def not_observable(self) -> list[tuple[str, str, str]]:
        """(cause, why, what would show it) of each cause these runs could not show."""
        return self.decision.not_observable

    @property
    def ambiguous(self) -> list[tuple[str, str]]:
        return self.decision.ambiguous

    @property
    def named(self) -> tuple[str, ...]:
        """The causes the extension applies (empty for none and unexplained)."""
        if self.cause in ("none", "unexplained") or self.chosen_set is None:
            return ()
        return self.chosen_set.names

    @property
    def chosen(self) -> CauseFit:
        """The single fit shown in figures: the largest contributor, else the best."""
        name = max(self.shares, key=self.shares.get) if self.shares else self.fits[0].cause.name
        return next(f for f in self.fits if f.cause.name == name)


def _fit_either_torque(cause: Cause, bench: Workbench, target: list[np.ndarray],
                       weights: list[float]) -> CauseFit:
    """Fit ``cause`` on the tables fed the motor torque and fed the pump torque (the motor's
    inertia taken off); keep the one that explains more of ``target`` on held-out runs.

    In a transient the tables' velocity can hinge on a few N*m (a valve regime), so which
    torque reads right depends on the runs and on the cause; the chamber models (``dynamic``
    mode, and ``compressibility``'s) take the inertia into account themselves. The sensor
    causes are fitted on the model's own choice only (time).
    """
    if cause.name == "none":
        bench.use(bench.default_inertia)
        fit = fit_cause(cause, bench, target, weights)
        fit.motor_inertia = bench.default_inertia
        return fit
    best = None
    for inertia in (bench.inertia_choices if cause.name in BOTH_TORQUES
                    else (bench.default_inertia,)):
        bench.use(inertia)
        own = [(x - r.position_mm)[m] for x, r, m in zip(bench.base, bench.runs, bench.masks)]
        fit = rescore(fit_cause(cause, bench, own, weights), target, weights)
        fit.motor_inertia = inertia
        if best is None or fit.score > best.score:
            best = fit
    return best


def _sse(res: Sequence[np.ndarray], weights: Sequence[float]) -> float:
    return float(sum(w * np.dot(r, r) for r, w in zip(res, weights)))


def _floor_sse(diag: Diagnosis, weights: Sequence[float]) -> float:
    """The machine's own error as a held-out squared error over these runs' samples."""
    n = [int(m.sum()) for m in diag.bench.masks]
    return diag.thresholds.machine_rms_mm ** 2 * float(np.dot(weights, n))


def diagnose(cfg: Config, actuator: str, runs: Sequence[AnalysisRun], mode: str | None = None,
             progress: Progress | None = None, own: OwnError | None = None) -> Diagnosis:
    """Fit every cause of the catalogue, grow a set jointly, fit the residual model, and
    decide (cross-validated one run out at a time throughout); in the configured estimator
    mode unless ``mode`` says otherwise. ``own``: the machine's own error from its baseline
    (else the thresholds are the simulator's)."""
    mode = resolve_mode(cfg, mode)
    if len(runs) < 2:
        raise UserError(f"{len(runs)} run given: the diagnosis needs at least two runs (the "
                        "fit is judged on runs it did not see)")
    report = progress or (lambda stage, fraction: None)
    report("baseline", 0.0)
    bench = Workbench(cfg, actuator, runs, mode)
    baseline = [x - r.position_mm for x, r in zip(bench.as_is, runs)]
    model = [x - r.position_mm for x, r in zip(bench.base, runs)]
    target = [e[m] for e, m in zip(model, bench.masks)]
    weights = [r.duration_s / max(int(m.sum()), 1) for r, m in zip(runs, bench.masks)]
    total = _sse(target, weights)
    causes: list[Cause] = list(ALL_CAUSES.values())
    fits = []
    for i, cause in enumerate(causes):
        report(cause.name, 0.6 * i / len(causes))
        fits.append(_fit_either_torque(cause, bench, target, weights))
    fits.sort(key=lambda f: (-f.score, f.cause.name != "none"))
    evidence = torque_evidence(bench)
    thresholds = Thresholds.positions(own)
    if evidence is not None and thresholds.pressure_line is not None:
        evidence = evidence.against(thresholds.pressure_line)
    diag = Diagnosis(actuator, mode, list(runs), bench, baseline, model, fits,
                     Decision("none", "", 0.0, 0.0), evidence=evidence,
                     thresholds=thresholds)
    _decide(diag, target, weights, total, report)
    if diag.extension_inertia is None:
        diag.extension_inertia = (bench.default_inertia if diag.chosen_set is None
                                  or diag.cause == "none" else diag.chosen_set.motor_inertia)
    report("observability", 0.95)
    diag.observability = observe_positions(bench, causes, weights, diag.decision.rms_after_mm)
    diag.decision = with_observability(diag.decision, diag.observability)
    bench.use(diag.extension_inertia)
    report("decision", 1.0)
    return diag


def _grow(diag: Diagnosis, first: CauseFit, stepwise: bool, weights: list[float],
          total: float, report: Progress
          ) -> tuple[SetFit | None, dict[str, float], list[tuple[str, str]]]:
    """Grow a set from ``first`` (:mod:`.selection`, rule 2); ``stepwise``: every step must
    agree with the pressures, else only the final set (None if it does not)."""
    bench, ev = diag.bench, diag.evidence
    s = SetFit.single(first)
    shares = {first.cause.name: first.explained}
    ambiguous: list[tuple[str, str]] = []
    parametric = [f for f in diag.fits if f.cause.parameter is not None]
    for step, tries in enumerate(CANDIDATES_PER_STEP):
        if len(s.causes) >= MAX_CAUSES or \
                rms(s.heldout, weights) <= diag.thresholds.growth_floor_rms_mm:
            break       # (what is left is the model's own error: anything fits half of it)
        report(f"joint fits ({len(s.causes) + 1} causes)", 0.6 + 0.15 * step)
        bench.use(s.motor_inertia)
        others = [f.cause for f in parametric if f.cause.name not in s.names]
        trial = [c for _, c in screen(bench, s, others, weights)[:tries]]
        grown = []
        for c in trial:
            j = fit_set(bench, s.causes + (c,), s.params, weights, total)
            if j.resolved() and (not stepwise or _consistent(ev, j.params, j.intervals)) \
                    and j.sse <= (1.0 - MIN_ADDED) * s.sse:
                grown.append(j)
        if not grown:
            break
        grown.sort(key=lambda j: j.sse)
        for other in grown[1:]:
            if alike(other.sse, grown[0].sse, _floor_sse(diag, weights)):
                ambiguous.append((grown[0].names[-1], other.names[-1]))
        shares[grown[0].names[-1]] = (s.sse - grown[0].sse) / total if total else 0.0
        s = grown[0]
    s, shares = _prune(bench, s, shares, diag.fits, weights, total)
    if not _consistent(ev, s.params, s.intervals):
        # the pressures measure the torque chain: the cause they point at joins on their
        # evidence (it need not halve the error left: leakage can hide much of it), to the
        # grown set or to the first cause alone (a member grown without the pressures may
        # only have stood in for it)
        bases = [(s, shares)]
        if len(s.causes) > 1:
            bases.append((SetFit.single(first), {first.cause.name: first.explained}))
        best = None
        for base, base_shares in bases:
            got = None if len(base.causes) >= MAX_CAUSES else \
                _join_measured(bench, ev, base, base_shares, weights, total)
            if got is not None and (best is None or got[0].sse < best[0].sse):
                best = got
        if best is not None:
            s, shares = best
    if not _consistent(ev, s.params, s.intervals):
        return None, {}, []
    return s, shares, [p for p in ambiguous if any(n in p for n in s.names)]


def _join_measured(bench: Workbench, ev: TorqueEvidence, s: SetFit, shares: dict[str, float],
                   weights: list[float], total: float
                   ) -> tuple[SetFit, dict[str, float]] | None:
    """``s`` with the cause the pressures point at held at its measured value (a member
    that only stood in for it goes), if that agrees with the pressures and leaves at most
    1 / (1 - :data:`MIN_ADDED`) times the error ``s`` left; else None."""
    for name in PRESSURE_CAUSES:
        c = ALL_CAUSES[name]
        if name in s.names:
            continue
        bench.use(s.motor_inertia)
        value, interval = ev.measured(c.parameter, s.params)
        fixed = {c: (c.clip(value), interval)}
        j = fit_set(bench, s.causes, s.params, weights, total, fixed=fixed)
        kept = tuple(m for m in s.causes if m.resolved(j.params.get(m.parameter)))
        if not j.resolved() and kept and len(kept) < len(s.causes):
            j = fit_set(bench, kept, j.params, weights, total, fixed=fixed)
        if j.resolved() and _consistent(ev, j.params, j.intervals) \
                and j.sse * (1.0 - MIN_ADDED) <= s.sse:
            joined = {m.name: shares.get(m.name, 0.0) for m in j.causes if m.name != name}
            joined[name] = max(s.sse - j.sse, 0.0) / total if total else 0.0
            return j, joined
    return None


def _prune(bench: Workbench, s: SetFit, shares: dict[str, float], fits: list[CauseFit],
           weights: list[float], total: float) -> tuple[SetFit, dict[str, float]]:
    """Drop a member that adds no resolved gain over the others (the set grown in another
    order could have done without it): the set without it must leave at most 1/(1 -
    :data:`MIN_ADDED`) times the set's held-out error, or it goes."""
    while len(s.causes) > 1:
        worst, worst_sub = None, None
        for m in s.causes:
            rest = tuple(c for c in s.causes if c is not m)
            if len(rest) == 1:
                sub = SetFit.single(next(f for f in fits if f.cause is rest[0]))
            else:
                bench.use(s.motor_inertia)
                sub = fit_set(bench, rest, s.params, weights, total)
            if sub.sse * (1.0 - MIN_ADDED) < s.sse and (worst_sub is None
                                                        or sub.sse < worst_sub.sse):
                worst, worst_sub = m, sub
        if worst is None:
            break
        s = worst_sub
        shares = {c.name: shares.get(c.name, 0.0) for c in s.causes}
        if len(s.causes) == 1:
            shares = {s.names[0]: s.explained}
    return s, shares


def _consistent(ev: TorqueEvidence | None, params: dict[str, float],
                intervals: dict[str, tuple[float, float]] | None = None) -> bool:
    return ev is None or ev.consistent(params, intervals or {})


def _decide(diag: Diagnosis, target: list[np.ndarray], weights: list[float], total: float,
            report: Progress) -> None:
    bench, ev, limits = diag.bench, diag.evidence, diag.thresholds
    before = rms(target, weights)
    best = diag.fits[0]
    if best.cause.name == "low_speed_leakage" and best.score >= MIN_SCORE:
        s = SetFit.single(best)
        diag.chosen_set, diag.shares, diag.heldout = s, {best.cause.name: best.explained}, \
            best.heldout
        diag.decision = Decision("low_speed_leakage", f"low_speed_leakage explains "
                                 f"{100 * best.score:.0f} % of the held-out squared error",
                                 before, rms(best.heldout, weights))
        return
    resolved = [f for f in diag.fits if f.cause.parameter is not None
                and f.cause.resolved(f.value)]
    eligible = [f for f in resolved
                if _consistent(ev, f.parameters, {f.cause.parameter: f.interval})]
    # Start from the best pressure-consistent single cause; where the best of all is not
    # consistent on its own (a leakage next to a torque error), also from it and the next
    # best inconsistent ones (a torque error hides leakage and an oil temperature offset
    # alike): a set grown from there counts if it ends consistent.
    starts = eligible[:1]
    if resolved and resolved[0] not in eligible:
        starts += [f for f in resolved[:INCONSISTENT_STARTS] if f not in eligible]
    if not starts and not _consistent(ev, {}):
        # The pressures see a torque-chain error that no single cause resolves (another
        # effect hides it: a torque offset next to air): grow from the best fits as they
        # are; a set counts only if it ends resolved.
        starts = [f for f in diag.fits if f.cause.parameter is not None][:INCONSISTENT_STARTS]
    ambiguous: list[tuple[str, str]] = []
    s: SetFit | None = None
    shares: dict[str, float] = {}
    for first in starts:
        got, got_shares, got_amb = _grow(diag, first, first in eligible, weights, total,
                                         report)
        if got is None or not got.resolved() or (s is not None and got.sse >= s.sse):
            continue
        s, shares, ambiguous = got, got_shares, got_amb
        if first in eligible and len(got.causes) == 1:
            rivals = [f for f in eligible if f is not first and f.score >= MIN_SCORE
                      and alike((1.0 - f.explained) * total, (1.0 - first.explained) * total,
                                _floor_sse(diag, weights))]
            ambiguous = [(first.cause.name, f.cause.name) for f in rivals] \
                if got.names[0] == first.cause.name else got_amb
    # the residual model: on top of the set (its held-out error as the target), and alone
    report("residual model", 0.9)
    bench.use(bench.default_inertia)
    alone = fit_residual(bench, {}, target, weights, total)
    on_set = None
    if s is not None:
        bench.use(s.motor_inertia)
        on_set = fit_residual(bench, s.params, s.heldout, weights, total)
    diag.chosen_set, diag.shares = s, shares
    if s is not None:
        largest = max(shares, key=shares.get)
        structured = on_set is not None and on_set.explained > s.explained and \
            _sse(on_set.heldout, weights) <= (1.0 - MIN_ADDED) * s.sse and \
            s.sse - _sse(on_set.heldout, weights) >= RESIDUAL_SHARE * total and \
            rms(s.heldout, weights) > limits.own_error_rms_mm
        het = s.heterogeneity
        # runs wanting their own values shows a look-alike only beyond the machine's own
        # error (an orifice share of the leakage makes each temperature want its factor)
        mixed = het > MAX_HETEROGENEITY and s.sse - s.own_sse >= RESIDUAL_SHARE * total \
            and rms(s.heldout, weights) > limits.mixed_floor_rms_mm
        if s.score >= MIN_SCORE and not mixed and not structured:
            names = " + ".join(f"{c.name} ({c.parameter} = {s.params[c.parameter]:.4g})"
                               if c.parameter in s.params else f"{c.name} ()"
                               for c in s.causes)
            diag.heldout = s.heldout
            diag.extension_inertia = s.motor_inertia
            amb = [p for p in ambiguous if largest in p]
            cause = "ambiguous" if amb else largest
            verb = "explains" if len(s.causes) == 1 else "explain"
            why = (f"{names} {verb} {100 * s.explained:.0f} % of the held-out squared error "
                   f"(RMS {before:.2f} -> {rms(s.heldout, weights):.2f} mm)")
            if amb:
                why += "; " + "; ".join(f"{a} and {b} explain the runs about equally well"
                                         for a, b in amb)
            diag.decision = Decision(cause, why, before, rms(s.heldout, weights), ambiguous)
            return
        if s.score < MIN_SCORE:
            gap = (f"the best set, {' + '.join(s.names)}, explains {100 * s.explained:.0f} % "
                   f"of the held-out squared error (naming needs {100 * MIN_SCORE:.0f} %)")
        elif mixed:
            gap = (f"{' + '.join(s.names)} explains {100 * s.explained:.0f} % but no single "
                   f"value describes every run (held-out error {het:.1f} x each run's own "
                   "fit): it mimics something else")
        else:
            gap = (f"{' + '.join(s.names)} explains {100 * s.explained:.0f} %, but a residual "
                   f"model of the physical features removes {100 * on_set.explained:.0f} %: "
                   "a structured error the catalogue does not describe is left")
    else:
        unresolved = [f for f in diag.fits if f.cause.parameter is not None
                      and not f.cause.resolved(f.value)]
        gap = "no catalogued cause fits beyond what the model's own error can mimic"
        if diag.fits[0].cause.parameter is None:
            gap = "no cause explains any of the held-out error"
        if unresolved and unresolved[0] is diag.fits[0]:
            f = unresolved[0]
            gap = (f"the best candidate, {f.cause.name}, fits {f.cause.parameter} = "
                   f"{f.value:.4g}, within what the model's own error can mimic (named from "
                   f"{bound(f.cause)})")
    use = alone
    diag.extension_inertia = bench.default_inertia
    if on_set is not None and _sse(on_set.heldout, weights) < _sse(alone.heldout, weights):
        use = on_set
        diag.residual_base = dict(s.params)
        diag.extension_inertia = s.motor_inertia
    # what the model's own error can mimic: the best fit within its resolution
    mimic = max([f.explained for f in diag.fits if f.cause.parameter is not None
                 and not f.cause.resolved(f.value)] + [0.0])
    if before > limits.own_error_rms_mm and use.explained >= MIN_SCORE \
            and (1.0 - use.explained) <= MIN_ADDED * (1.0 - mimic):
        diag.residual, diag.heldout = use, use.heldout
        diag.decision = Decision("unexplained", f"{gap}; a residual model explains "
                                 f"{100 * use.explained:.0f} % of the held-out squared error "
                                 f"(RMS {before:.2f} -> {rms(use.heldout, weights):.2f} mm)",
                                 before, rms(use.heldout, weights))
        diag.shares = {}
        return
    diag.residual_base = {}
    diag.extension_inertia = bench.default_inertia
    diag.heldout = target
    diag.shares = {}
    if before <= limits.own_error_rms_mm:
        whose = "the simulator's" if limits.simulator else "this machine's baseline"
        gap += (f"; the model's held-out error, RMS {before:.2f} mm, is within its own "
                f"({limits.own_error_rms_mm:.2g} mm, {whose})")
    diag.decision = Decision("none", gap, before, before)
