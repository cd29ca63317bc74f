"""A unit's finding in words: each catalogued cause's alarm names the cause, its figure, the
time left (days and date) and the action with the extension to load; the pressure scale
names both readings; nothing found and too few days say so, with the days of evidence."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from ddh_vsensor.diagnosis.causes import ALL_CAUSES, CAUSES
from ddh_vsensor.diagnosis.evidence import GRIDS
from ddh_vsensor.diagnosis.finding import (WORDS, evidence_text, label, parameter_meanings,
                                           unit_finding)
from ddh_vsensor.diagnosis.trend import (DAY_S, MIN_LOGS, Alarm, LogFit, UnitTrend, to_u,
                                         unit_trend)

T0 = 1.767e9                        # 2025-12-29 UTC
EXT = "/srv/report_extensions/M1_boom.json"
# cause -> (fitted value, its figure in the sentence)
FIGURES = {
    "pump_leakage": (1.6, "pumps leak 1.60\u00d7 their nominal"),
    "torque_gain": (0.8, "drive's torque reads 0.80\u00d7 true"),
    "compressibility": (0.02, "2.0 % air"),
    "belt_slip": (5.0, "belt slips 5.0 % per 100 N\u00b7m"),
    "displacement": (1.03, "deliver 1.030\u00d7 their nominal oil"),
    "time_offset": (0.12, "lag the position by 120 ms"),
    "oil_temp_offset": (-8.0, "reads 8.0 \u00b0C below"),
    "torque_offset": (4.0, "torque 4.0 N\u00b7m high"),
    "position_scale": (1.03, "reads 1.030\u00d7 the true position"),
}


def made_trend(cause: str, value: float | None, days: int = 10, now_mm: float = 1.2,
               projected_mm: float = 4.0, crossing_days: float | None = 11.0,
               alarm: bool = True) -> UnitTrend:
    """A unit whose last day names ``cause`` at ``value`` (its interval +-0.02 in the
    search's scale), alarmed to cross the tolerance ``crossing_days`` after it."""
    t = [T0 + d * DAY_S for d in range(days)]
    named = cause if cause != "none" else "none"
    u = 0.0 if value is None else float(to_u(cause, value))
    fits = [LogFit(ts, f"d{i}", u, u - 0.02, u + 0.02, np.zeros(3), np.ones(3), np.zeros(3),
                   1.0, 0.8) for i, ts in enumerate(t)]
    last = None
    if alarm and named != "none":
        last = Alarm(t[-1], cause, value, now_mm, projected_mm,
                     None if crossing_days is None else t[-1] + crossing_days * DAY_S)
    return UnitTrend("M1", "boom", t, {cause if cause != "none" else "belt_slip": fits},
                     [named] * days, [{}] * days, [now_mm] * days, [projected_mm] * days,
                     [0.8] * days, [None] * (days - 1) + [last])


def test_every_catalogued_cause_has_a_meaning_and_an_action():
    assert set(WORDS) == set(CAUSES)
    rows = parameter_meanings()
    assert [r[0] for r in rows] == list(CAUSES)
    for cause, parameter, _, meaning, action in rows:
        assert meaning and action, cause
        if parameter:
            assert f"{ALL_CAUSES[cause].neutral:g} = " in meaning, cause
    assert "1 = as new" in WORDS["pump_leakage"].meaning
    assert "worn pumps leak more" in WORDS["pump_leakage"].meaning


@pytest.mark.parametrize("cause", list(FIGURES))
def test_each_causes_alarm_names_cause_figure_time_left_and_action(cause):
    value, figure = FIGURES[cause]
    f = unit_finding(made_trend(cause, value), 3.0, 14.0, EXT)
    assert f.state == "alarm" and f.cause == cause
    assert f.text.startswith("ALARM: ")
    assert figure in f.text and figure in f.what                    # cause and figure
    assert "in 11 days, by 2026-01-18" in f.text                    # time left, date
    assert f.days_left == pytest.approx(11.0) and f.crossing_date == "2026-01-18"
    assert f.time_left == "in 11 days (2026-01-18)"
    assert "1.2 mm now" in f.text and "4.0 mm in 14 days" in f.text
    assert "3 mm off at the references" in f.text
    assert f.action.startswith(WORDS[cause].action) and EXT in f.action  # action, extension
    assert f.action[:1].upper() + f.action[1:] in f.text
    assert "From 10 days of evidence." in f.text


def test_the_pressure_scale_names_both_readings_whichever_was_fitted():
    leak = unit_finding(made_trend("pump_leakage", 1.6), 3.0, 14.0, EXT)
    gain = unit_finding(made_trend("torque_gain", 1.0 / 1.6), 3.0, 14.0, EXT)
    for f in (leak, gain):
        assert "The boom's pressure scale: its pumps leak 1.60\u00d7 their nominal, or its " \
               "drive's torque reads 0.62\u00d7 true" in f.text
        assert "p_a_bar, p_b_bar" in f.text and "interval of the leakage" in f.text
    assert label("pump_leakage") == label("torque_gain") == "pressure scale"


def test_an_error_past_the_tolerance_already_says_so():
    f = unit_finding(made_trend("belt_slip", 9.0, now_mm=3.6, crossing_days=0.0), 3.0, 14.0,
                     EXT)
    assert f.state == "alarm" and f.days_left == 0.0
    assert "already 3.6 mm off at the references, past the 3 mm tolerance" in f.text
    assert f.time_left == "already (2026-01-07)"


def test_a_named_cause_within_the_tolerance_is_watched():
    f = unit_finding(made_trend("displacement", 1.02, projected_mm=1.5, alarm=False), 3.0,
                     14.0)
    assert f.state == "cause" and not f.text.startswith("ALARM")
    assert "1.020\u00d7" in f.text and "within the 3 mm tolerance" in f.text
    assert "No action yet" in f.text and f.action.endswith(WORDS["displacement"].action)


def test_nothing_found_says_with_how_many_days_of_evidence():
    f = unit_finding(made_trend("none", None, days=12), 3.0, 14.0)
    assert f.state == "none"
    assert f.text.startswith("Nothing found on the boom with 12 days of evidence:")
    assert "No action." in f.text


def test_too_few_days_says_how_many_more_are_needed():
    f = unit_finding(made_trend("belt_slip", 9.0, days=3), 3.0, 14.0, EXT)
    assert f.state == "too_few_days" and "ALARM" not in f.text
    more = MIN_LOGS - 3
    assert f.text.startswith("Too few days for a trend on the boom: 3 days of evidence")
    assert f"a trend needs {MIN_LOGS}. {more} more days of evidence needed" in f.text
    assert "(about 2026-01-04 at one a day)" in f.text


def test_the_evidence_is_worded_as_day_summaries_and_logs():
    assert evidence_text(1) == "1 day of evidence"
    assert evidence_text(9, 8, 1) == "9 days of evidence (8 day summaries, 1 log)"
    assert evidence_text(2, 0, 2) == "2 days of evidence (2 logs)"
    sources = {f"d{i}": "summary" if i < 7 else "log" for i in range(10)}
    f = unit_finding(made_trend("pump_leakage", 1.6), 3.0, 14.0, EXT, sources)
    assert "From 10 days of evidence (7 day summaries, 3 logs)." in f.text


def rising_rows(rate_per_day: float, days: int = 12) -> list[dict]:
    """Rows as the fleet analysis writes them: the leakage factor rising ``rate_per_day``
    (8 mm of increment change per unit of its log), the displacement explaining nothing."""
    rng = np.random.default_rng(0)
    out = []
    for day in range(days):
        v = np.log(1.0 + rate_per_day * day) + rng.normal(0.0, 0.02)
        nominal = 20.0 * (1.0 + (8.0 * v) ** 2)
        for cause in ("pump_leakage", "displacement"):
            grid = np.asarray(GRIDS[cause], float)
            gu = np.log(grid)
            loss = 20.0 * (1.0 + (8.0 * (gu - v)) ** 2) if cause == "pump_leakage" else \
                np.full(len(grid), nominal) + 5.0 * gu ** 2
            out.append({"cause": cause, "grid": list(grid), "loss": list(loss),
                        "emax_mm": list(8.0 * np.abs(gu)), "n_obs": 20,
                        "loss_nominal": nominal, "max_increment_mm": 1.0,
                        "time_s": T0 + day * DAY_S, "log_id": f"d{day}"})
    return out


def test_a_rising_leakages_trend_is_worded_as_an_alarm_days_ahead():
    tr = unit_trend("M1", "boom", rising_rows(0.02), tolerance_mm=3.0, horizon_days=14.0)
    f = unit_finding(tr, 3.0, 14.0, EXT)
    assert f.state == "alarm" and f.cause == "pump_leakage"
    assert f.days_left is not None and 3.0 < f.days_left <= 14.0
    assert f"in {int(f.days_left)} days, by {f.crossing_date}" in f.text


def test_the_wording_needs_no_html_or_plotting():
    """The daemon says the same words: the module brings in neither jinja2 nor matplotlib."""
    code = ("import sys, ddh_vsensor.diagnosis.finding; "
            "print(sorted(m for m in ('jinja2', 'matplotlib') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "[]"
