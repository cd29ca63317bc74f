"""What a unit's trend found, in the words a maintenance engineer acts on: the cause with its
figure, the position error it makes now and where its trend takes it, the days (and date)
until that passes the tolerance, and what to do; or that nothing was found, or that there
are too few days for a trend yet.

The fleet report prints these sentences and the daemon will say the same of its own
summaries, so they live here, beside :mod:`.trend`, with nothing of HTML or plotting.

A pump-leakage factor and a torque gain are one quantity to references and holds: the
estimator infers the pressures from the drive's torque, and the leakage it models grows with
those pressures, so pumps leaking L x nominal and a drive reading its torque 1/L x true
shift the estimate alike (docs/diagnosis.md: a torque reading 12 % high fits as a leakage of
x0.89). A finding of either is worded as the *pressure scale*, naming both readings; the
chamber pressure columns tell them apart.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from ddh_vsensor.diagnosis.causes import CAUSES
from ddh_vsensor.diagnosis.trend import DAY_S, MIN_LOGS, LogFit, UnitTrend, from_u

PRESSURE_SCALE = ("pump_leakage", "torque_gain")
PRESSURE_SCALE_HINT = ("References and holds cannot tell these two apart; the chamber pressure "
                       "columns p_a_bar, p_b_bar can.")


@dataclass(frozen=True)
class Words:
    """A cause in maintenance terms: what its parameter means, what to do about it, a value
    with its unit (``shown``, also for the interval) and the finding's phrase for a unit and
    a value (``what``)."""

    meaning: str
    action: str
    shown: Callable[[float], str]
    what: Callable[[str, float | None], str]


def _times(digits: int) -> Callable[[float], str]:
    return lambda v: f"{v:.{digits}f}\u00d7"


def _pressure_scale(unit: str, leakage: float) -> str:
    return (f"the {unit}'s pressure scale: its pumps leak {leakage:.2f}\u00d7 their nominal, "
            f"or its drive's torque reads {1.0 / leakage:.2f}\u00d7 true")


WORDS: dict[str, Words] = {
    "low_speed_leakage": Words(
        "no parameter: the paper mode's three speed ranges cannot represent the pumps' "
        "leakage at low speed, so a held load creeps in the estimate",
        "load the extension (the speed-continuous tables)", lambda v: "",
        lambda u, v: f"the {u}'s estimate misjudges the leakage at low speed (the paper "
                     "mode's three speed ranges)"),
    "pump_leakage": Words(
        "factor on the pumps' internal leakage; 1 = as new; worn pumps leak more (the error "
        "grows with load and warm oil, and shows as creep while a load is held)",
        "check the chamber pressures to tell which: service the pumps if they leak, "
        "recalibrate the drive's torque reading if it reads off", _times(2),
        _pressure_scale),
    "compressibility": Words(
        "share of air in the oil, by volume at atmospheric pressure; 0 = none; a suction-side "
        "leak, low oil or foaming adds air (the rod lags at starts from low pressure)",
        "bleed the air from the circuit (check the oil level and the suction side)",
        lambda v: f"{100 * v:.1f} %",
        lambda u, v: f"the {u}'s oil carries {100 * v:.1f} % air (by volume at atmospheric "
                     "pressure)"),
    "belt_slip": Words(
        "how much the belt slips under load: % of speed lost per 100 N\u00b7m of motor "
        "torque; 0 = no slip; a slack or worn belt slips more (lifting loaded)",
        "tension or replace the belt", lambda v: f"{v:.1f} %",
        lambda u, v: f"the {u}'s belt slips {v:.1f} % per 100 N\u00b7m of motor torque"),
    "displacement": Words(
        "factor on the oil the pumps deliver per revolution; 1 = the datasheet's; wear or a "
        "pump other than configured changes it (the error grows with travel)",
        "service or replace the pumps, or correct the configured pump", _times(3),
        lambda u, v: f"the {u}'s pumps deliver {v:.3f}\u00d7 their nominal oil per "
                     "revolution"),
    "time_offset": Words(
        "seconds the logged motor signals lag the position; 0 = in step; a logger or bus "
        "delay (the error follows speed and does not accumulate)",
        "fix the logging's timing (motor signals and position out of step)",
        lambda v: f"{1000 * v:+.0f} ms",
        lambda u, v: f"the {u}'s logged motor signals {'lag' if v >= 0 else 'lead'} the "
                     f"position by {1000 * abs(v):.0f} ms"),
    "oil_temp_offset": Words(
        "\u00b0C the tank temperature sensor reads above the oil the pumps see; 0 = true; "
        "a sensor off, or pumps running warmer than the tank",
        "check the tank temperature sensor against a thermometer",
        lambda v: f"{v:+.1f} \u00b0C",
        lambda u, v: f"the {u}'s tank temperature sensor reads {abs(v):.1f} \u00b0C "
                     f"{'above' if v >= 0 else 'below'} the pumps' oil"),
    "torque_gain": Words(
        "factor on the drive's torque reading; 1 = reads true; the model infers the pressures "
        "from it, so it acts as the pumps' leakage does (the pressure scale)",
        "check the chamber pressures to tell which: recalibrate the drive's torque reading if "
        "it reads off, service the pumps if they leak", _times(2),
        lambda u, v: _pressure_scale(u, 1.0 / v)),
    "torque_offset": Words(
        "N\u00b7m the drive's torque reading is off at zero torque; 0 = true (a held load "
        "creeps the same whatever it weighs)",
        "re-zero the drive's torque reading (commission the drive)",
        lambda v: f"{v:+.1f} N\u00b7m",
        lambda u, v: f"the {u}'s drive reads its torque {abs(v):.1f} N\u00b7m "
                     f"{'high' if v >= 0 else 'low'}"),
    "position_scale": Words(
        "factor the reference position sensor reads of the true position; 1 = true; the "
        "sensor's calibration, not the estimate's",
        "recalibrate the reference position sensor (the estimate may be right)", _times(3),
        lambda u, v: f"the {u}'s reference position sensor reads {v:.3f}\u00d7 the true "
                     "position"),
}


def _date(t_s: float) -> str:
    return dt.datetime.fromtimestamp(t_s, dt.timezone.utc).date().isoformat()


def label(cause: str) -> str:
    """A cause's name in the report: the two readings of the pressure scale share one."""
    return "pressure scale" if cause in PRESSURE_SCALE else cause.replace("_", " ")


def parameter_meanings() -> list[tuple[str, str, str, str, str]]:
    """(cause, parameter, unit, meaning, action) of every catalogued cause."""
    return [(c.name, c.parameter or "", c.unit, WORDS[c.name].meaning, WORDS[c.name].action)
            for c in CAUSES.values()]


def what_found(cause: str, actuator: str, value: float | None) -> str:
    """The cause with its figure: "the boom's belt slips 4.2 % per 100 N*m of motor torque"."""
    return WORDS[cause].what(actuator, value)


def action_text(cause: str, extension_file: str | None) -> str:
    """What to do: the cause's own service, or the extension that corrects the estimate
    meanwhile (a position sensor's scale needs none: the estimate is of the true position)."""
    ext = f"the extension {extension_file}" if extension_file else \
        "an extension fitted to it (ddh-vsensor analyze)"
    if cause == "position_scale":
        return f"{WORDS[cause].action}; {ext} only records the scale"
    return f"{WORDS[cause].action}; or, until then, load {ext}"


def evidence_text(days: int, summaries: int | None = None, logs: int | None = None) -> str:
    """"12 days of evidence (10 day summaries, 2 logs)": a day summary is the daemon's whole
    day, a log only the minutes logged, so the count says which."""
    text = f"{days} day{'s' if days != 1 else ''} of evidence"
    parts = [f"{n} {one if n == 1 else many}" for n, one, many in
             ((summaries, "day summary", "day summaries"), (logs, "log", "logs")) if n]
    return f"{text} ({', '.join(parts)})" if parts else text


def too_few_days_text(actuator: str, evidence: str, have: int, reference_error_mm: float,
                      last_time_s: float) -> str:
    """The notice for a unit with fewer than :data:`MIN_LOGS` days: nothing is named before
    a week of days, so say how many more are needed and when that is (one a day)."""
    need = MIN_LOGS - have
    ready = _date(last_time_s + need * DAY_S)
    return (f"Too few days for a trend on the {actuator}: {evidence}, a trend needs "
            f"{MIN_LOGS}. {need} more day{'s' if need != 1 else ''} of evidence needed "
            f"(about {ready} at one a day); nothing is named before then. The nominal model's "
            f"largest error at the references so far: {reference_error_mm:.1f} mm.")


def none_text(actuator: str, evidence: str, reference_error_mm: float,
              tolerance_mm: float) -> str:
    """Nothing found: no catalogued cause explains the references and holds or trends."""
    text = (f"Nothing found on the {actuator} with {evidence}: no catalogued cause explains "
            "the references and holds, and none trends towards the tolerance. The nominal "
            f"model's largest error at the references is {reference_error_mm:.1f} mm "
            f"(tolerance {tolerance_mm:g} mm).")
    if reference_error_mm > tolerance_mm:
        return text + (" That is beyond the tolerance with no catalogued cause: check the "
                       "machine's configuration, or commission it anew.")
    return text + " No action."


@dataclass(frozen=True)
class Finding:
    """One unit's finding: ``state`` is alarm, cause (named, within tolerance), none,
    too_few_days or no_evidence; ``text`` the paragraph, the rest its parts."""

    machine: str
    actuator: str
    state: str
    cause: str
    evidence: str
    text: str
    what: str = ""                      # the cause with its figure
    interval: str = ""                  # the last day's 90 % interval, in words
    error_now_mm: float | None = None
    error_projected_mm: float | None = None
    days_left: float | None = None      # until the expected error passes the tolerance
    crossing_date: str | None = None
    time_left: str = ""                 # "in 11 days (2026-01-12)", "already (...)"
    action: str = ""


def _interval_words(cause: str, fit: LogFit) -> str:
    """The last day's 90 % interval in the figure's own unit (a torque gain as the leakage
    it equals, as the figure is)."""
    lo, hi = from_u(cause, fit.lo_u), from_u(cause, fit.hi_u)
    shown, of = WORDS[cause].shown, ""
    if cause in PRESSURE_SCALE:
        lo, hi = (1.0 / hi, 1.0 / lo) if cause == "torque_gain" else (lo, hi)
        shown, of = WORDS["pump_leakage"].shown, " of the leakage"
    text = f"90 % interval{of} {shown(lo)} to {shown(hi)} on the last day"
    return text + (", at the end of the searched range: or beyond" if fit.censored else "")


def _first_up(text: str) -> str:
    return text[:1].upper() + text[1:]


def _plural_days(d: float) -> str:
    n = math.floor(d)
    return "within a day" if n < 1 else f"in {n} day{'s' if n != 1 else ''}"


def unit_finding(tr: UnitTrend, tolerance_mm: float, horizon_days: float,
                 extension_file: str | None = None,
                 sources: Mapping[str, str] | None = None) -> Finding:
    """The finding of one machine's unit from its trend: the last day's cause, value and
    interval, expected error now (mm), projected error at ``horizon_days`` and the days and
    date until it passes ``tolerance_mm``, and the action with ``extension_file``.
    ``sources`` (log id -> "summary" or "log", as the fleet analysis' rows say) words the
    evidence as day summaries and logs; without it, as days."""
    unit = tr.actuator
    if not tr.times_s:
        return Finding(tr.machine, unit, "no_evidence", "none", evidence_text(0),
                       f"No evidence on the {unit}: no references or holds were fitted.")
    fits = next(iter(tr.series.values()))
    days = len({_date(t) for t in tr.times_s})
    kinds = [sources.get(f.log_id, "") for f in fits] if sources is not None else None
    evidence = evidence_text(days, kinds.count("summary") if kinds else None,
                             kinds.count("log") if kinds else None)
    ref_mm = tr.reference_error_mm[-1]
    if len(tr.times_s) < MIN_LOGS:
        return Finding(tr.machine, unit, "too_few_days", "none", evidence,
                       too_few_days_text(unit, evidence, len(tr.times_s), ref_mm,
                                         tr.times_s[-1]))
    cause = tr.named[-1]
    if cause == "none" or cause not in WORDS:
        return Finding(tr.machine, unit, "none", "none", evidence,
                       none_text(unit, evidence, ref_mm, tolerance_mm))
    alarm = tr.alarms[-1]
    fit = tr.series[cause][-1] if cause in tr.series else None
    value = alarm.value if alarm is not None else (
        from_u(cause, fit.u) if fit is not None else None)
    what = what_found(cause, unit, value)
    interval = _interval_words(cause, fit) if fit is not None else ""
    now_mm, proj_mm = tr.error_now_mm[-1], tr.error_projected_mm[-1]
    found = f"{_first_up(what)}" + (f" ({interval})" if interval else "") + "."
    if cause in PRESSURE_SCALE:
        found += f" {PRESSURE_SCALE_HINT}"
    errors = (f"The position error this makes at the references is {now_mm:.1f} mm now, "
              f"{proj_mm:.1f} mm in {horizon_days:g} days at this rate")
    if alarm is None:
        action = f"no action yet: watch it; if it grows, {WORDS[cause].action}"
        text = (f"{found} {errors}, within the {tolerance_mm:g} mm tolerance. "
                f"{_first_up(action)}. From {evidence}.")
        return Finding(tr.machine, unit, "cause", cause, evidence, text, what, interval,
                       now_mm, proj_mm, None, None, "", action)
    action = action_text(cause, extension_file)
    crossing = alarm.crossing_time_s
    days_left = None if crossing is None else max((crossing - tr.times_s[-1]) / DAY_S, 0.0)
    date = None if crossing is None else _date(max(crossing, tr.times_s[-1]))
    if days_left is None:
        time_left = f"past the horizon of {horizon_days:g} days"
        when = f"{errors}."
    elif days_left <= 0:
        time_left = f"already ({date})"
        when = (f"The position is already {now_mm:.1f} mm off at the references, past the "
                f"{tolerance_mm:g} mm tolerance ({proj_mm:.1f} mm in {horizon_days:g} days "
                "at this rate).")
    else:
        time_left = f"{_plural_days(days_left)} ({date})"
        when = (f"The position error this makes at the references is {now_mm:.1f} mm now; at "
                f"this rate the position will be {tolerance_mm:g} mm off at the references "
                f"{_plural_days(days_left)}, by {date} ({proj_mm:.1f} mm in "
                f"{horizon_days:g} days).")
    text = f"ALARM: {found} {when} {_first_up(action)}. From {evidence}."
    return Finding(tr.machine, unit, "alarm", cause, evidence, text, what, interval, now_mm,
                   proj_mm, days_left, date, time_left, action)
