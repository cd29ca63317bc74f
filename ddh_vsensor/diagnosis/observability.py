"""Which catalogued causes the evidence of an analysis could show at all.

``none`` must mean that every catalogued cause was observable and none is there. A cause is
*observable* from a set of runs when, at its catalogue's :attr:`.Cause.reference_size` (a
deviation that matters in service), the decision would name it: its exact change of what the
decision scores (the position error at the logged samples, or the edge-to-edge increments and
the holds' creep) is computed with the same extended model the fit uses, and the held-out
share of the squared error it would explain is compared with :data:`.selection.MIN_SCORE`.

That share is taken in expectation, for the runs' own error as white noise of the RMS the
decision left (``noise``): a cause changing the evidence by ``Delta_j`` on run ``j`` (weighted
energy ``E_j``) is fitted without run ``j`` and predicts it with the variance of that fit, so

    share = (sum E_j - sum_j E_j * sum_{i != j} nu_i E_i / (sum_{i != j} E_i)^2)
            / (sum E_j + SSE_noise),          nu_i = w_i noise^2,

less the parameter penalty. It falls with the noise and with evidence a single run carries
(the others cannot fit it). The causes checked are those the analysis fits, as applicable in
its mode (from references, not the draw-wire's scale: there is no draw-wire to err).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ddh_vsensor.config import Config
from ddh_vsensor.estimator.references import switches_from_config
from ddh_vsensor.diagnosis.causes import Cause
from ddh_vsensor.diagnosis.fit import PENALTY_PER_PARAMETER
from ddh_vsensor.diagnosis.references import ReferenceRun
from ddh_vsensor.diagnosis.selection import MIN_SCORE, Decision, rms
from ddh_vsensor.diagnosis.workbench import Workbench


@dataclass(frozen=True)
class Observability:
    """One cause against one analysis's evidence."""

    cause: str
    value: float | None          # the parameter value checked (None: the cause has none)
    effect_rms_mm: float         # RMS change of the scored evidence at that value
    noise_rms_mm: float          # RMS the runs err by without the cause (what the decision left)
    expected_share: float        # held-out share of the squared error it would explain
    observable: bool
    why: str                     # why not: the fact of the runs that hides it, else the
                                 # numbers ("" when observable)
    shown_by: str                # runs that would show it

    def as_dict(self) -> dict[str, Any]:
        return {"cause": self.cause, "value": self.value,
                "effect_rms_mm": round(self.effect_rms_mm, 4),
                "noise_rms_mm": round(self.noise_rms_mm, 4),
                "expected_share": round(self.expected_share, 4),
                "observable": self.observable, "why": self.why, "shown_by": self.shown_by}


@dataclass(frozen=True)
class Evidence:
    """What the runs hold that a cause can show in: the facts the explanations quote."""

    positions: bool                      # a position sensor was logged (else references)
    switches: tuple[str, ...]            # switches with a used edge
    both_ways: bool                      # each of them met moving up and moving down
    switch_strokes: int                  # increments from one switch to another
    max_step_mm: float                   # largest net travel from one edge to the next
    holds: int
    hold_torque_nm: tuple[float, float]  # |mean motor torque| over the holds, least and most
    travel_mm: float                     # largest range of the logged position in a run


def expected_share(delta: Sequence[np.ndarray], weights: Sequence[float],
                   noise_rms_mm: float) -> float:
    """The held-out share of the squared error a fit of ``delta`` (the cause's change of the
    scored evidence, per run) would explain over white noise of ``noise_rms_mm``."""
    e = np.array([w * float(np.dot(d, d)) for d, w in zip(delta, weights)])
    n = np.array([len(d) for d in delta], dtype=float)
    nu = np.asarray(weights, dtype=float) * noise_rms_mm ** 2
    total, sse_noise = float(e.sum()), float(np.dot(nu, n))
    if total <= 0.0:
        return 0.0
    loss = 0.0
    for j in range(len(e)):
        rest = total - e[j]
        seen = rest > 1e-12 * total
        var = (float(np.dot(nu, e)) - nu[j] * e[j]) / rest ** 2 if seen else np.inf
        loss += min(e[j] * var, e[j])        # a run the others cannot fit keeps its error
    return (total - loss) / (total + sse_noise)


def _at_value(cause: Cause, value: float | None) -> str:
    """"at x1.03 ", "at 5 N*m " (the unit without its explanation); "" without a value."""
    if value is None:
        return ""
    return f"at x{value:g} " if cause.log else f"at {value:g} {cause.unit.split(' (')[0]} "


def _clause(cause: Cause, ev: Evidence, against: str) -> str:
    """The fact of the evidence that hides the cause, where one does; ``against`` compares
    its effect with the runs' own error."""
    if cause.grows_with == "travel" and not ev.positions and ev.switch_strokes == 0:
        where = (f"only the {ev.switches[0]} switch" if len(ev.switches) == 1
                 else f"the {', '.join(ev.switches)} switches, never one after another")
        ways = ", both ways" if ev.both_ways else ""
        return (f"the rod crossed {where}{ways}, at most {ev.max_step_mm:.1f} mm net from one "
                "edge to the next: its error, which follows the travel, cancels")
    if cause.grows_with == "travel" and ev.positions:
        return f"the rod travels at most {ev.travel_mm:.0f} mm in a run: {against}"
    if cause.grows_with == "holds" and not ev.positions and ev.holds == 0:
        return "no hold away from the stroke ends: its error is the creep of a held load"
    if cause.grows_with == "holds" and not ev.positions:
        lo, hi = ev.hold_torque_nm
        return f"the {ev.holds} hold(s) took {lo:.0f}-{hi:.0f} N*m: {against}"
    return ""


def check(cause: Cause, value: float | None, delta: Sequence[np.ndarray],
          weights: Sequence[float], noise_rms_mm: float, ev: Evidence) -> Observability:
    """Whether ``cause`` at ``value``, changing the scored evidence by ``delta``, would be
    named over the runs' own error."""
    share = expected_share(delta, weights, noise_rms_mm)
    effect = rms(delta, weights)
    ok = bool(share - PENALTY_PER_PARAMETER * cause.parameters >= MIN_SCORE)
    why = ""
    if not ok:
        what = "the positions" if ev.positions else "the references"
        against = (f"{_at_value(cause, value)}it would move {what} {effect:.2f} mm RMS "
                   f"against their own {noise_rms_mm:.2f} mm, {100 * max(share, 0.0):.0f} % of "
                   f"the held-out error where naming needs {100 * MIN_SCORE:.0f} %")
        why = _clause(cause, ev, against) or against
    return Observability(cause.name, value, float(effect), float(noise_rms_mm), float(share),
                         ok, why, cause.shown_by)


def _at_reference_size(bench: Workbench, cause: Cause) -> list[np.ndarray]:
    """The cause's exact change of the estimate at its reference size, per run (full length),
    with the bench's default torque."""
    inertia = bench.inertia
    bench.use(bench.default_inertia)
    values = [cause.reference_size] if cause.reference_size is not None else [0.0]
    try:
        return cause.deltas(bench, bench.base, values)[0]
    finally:
        bench.use(inertia)


def _checked(causes: Iterable[Cause], mode: str) -> list[Cause]:
    return [c for c in causes if c.name != "none" and c.applicable(mode)
            and (c.parameter is None or c.reference_size is not None)]


def reference_evidence(rruns: Sequence[ReferenceRun], switch_mm: dict[str, float]
                       ) -> Evidence:
    """The facts of references and holds. ``switch_mm``: each switch's position (an edge below
    it rising, or above it falling, was met moving up)."""
    names = sorted({s for rr in rruns for s in rr.switch})
    ways: dict[str, set[bool]] = {s: set() for s in names}
    strokes, step = 0, 0.0
    for rr in rruns:
        for s, rising, x in zip(rr.switch, rr.rising, rr.edge_mm):
            ways[s].add(bool((x < switch_mm[s]) == bool(rising)))
        strokes += sum(a != b for a, b in zip(rr.switch[:-1], rr.switch[1:]))
        if len(rr.edge_mm) > 1:
            step = max(step, float(np.max(np.abs(np.diff(rr.edge_mm)))))
    torques = [abs(h.torque_nm) for rr in rruns for h in rr.holds]
    return Evidence(False, tuple(names), all(len(w) == 2 for w in ways.values()), strokes,
                    step, len(torques),
                    (min(torques), max(torques)) if torques else (0.0, 0.0), 0.0)


def observe_references(cfg: Config, bench: Workbench, rruns: Sequence[ReferenceRun],
                       causes: Iterable[Cause], noise_rms_mm: float) -> list[Observability]:
    """Each cause against the edge-to-edge increments and the holds' creep."""
    switch_mm = {s.name: s.position_mm for s in switches_from_config(cfg.unit(bench.actuator))}
    ev = reference_evidence(rruns, switch_mm)
    weights = [1.0] * len(rruns)
    out = []
    for c in _checked(causes, bench.mode):
        delta = [rr.observe_delta(d) for rr, d in zip(rruns, _at_reference_size(bench, c))]
        out.append(check(c, c.reference_size, delta, weights, noise_rms_mm, ev))
    return out


def observe_positions(bench: Workbench, causes: Iterable[Cause], weights: Sequence[float],
                      noise_rms_mm: float) -> list[Observability]:
    """Each cause against the position error at the logged samples."""
    travel = max(float(np.ptp(r.position_mm[r.mask])) for r in bench.runs)
    ev = Evidence(True, (), False, 0, 0.0, 0, (0.0, 0.0), travel)
    out = []
    for c in _checked(causes, bench.mode):
        delta = [d[m] for d, m in zip(_at_reference_size(bench, c), bench.masks)]
        out.append(check(c, c.reference_size, delta, weights, noise_rms_mm, ev))
    return out


def answer(not_seen: Sequence[tuple[str, str, str]]) -> str:
    """The words of a ``none`` that could not see every cause."""
    items = "; ".join(f"{c} ({why}; {shown} would show it)" for c, why, shown in not_seen)
    return f"no observable cause; not observable from these runs: {items}"


def with_observability(decision: Decision, checks: Sequence[Observability]) -> Decision:
    """The decision with the causes its evidence could not show; a ``none`` says so first
    (it stays ``none`` for the programs reading it: no cause is named, nothing to apply)."""
    hidden = [(o.cause, o.why, o.shown_by) for o in checks if not o.observable]
    reason = decision.reason
    if decision.cause == "none" and hidden:
        reason = f"{answer(hidden)}. {reason[:1].upper()}{reason[1:]}"
    return dataclasses.replace(decision, reason=reason, not_observable=hidden)
