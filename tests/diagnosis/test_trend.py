"""Trends and alarms on synthetic per-log fits: a parameter drifting away is named and
alarmed before the expected error crosses the tolerance; a constant one is not."""

from __future__ import annotations

import numpy as np
import pytest

from ddh_vsensor.diagnosis.trend import DAY_S, _interp_loss, unit_trend

from ..conftest import T0, mixed_rows, rows

def test_a_rising_leakage_is_named_and_alarmed_before_it_crosses():
    days = np.arange(30)
    u = np.log(1.0 + 0.03 * np.maximum(days - 3, 0))    # leakage factor +3 % a day from day 3
    tr = unit_trend("M1", "boom", rows(u), tolerance_mm=3.0, horizon_days=14.0)
    crossing = int(np.argmax(8.0 * u > 3.0))             # expected error = 8 mm per unit of u
    first = tr.first_alarm
    assert first is not None and first.cause == "pump_leakage"
    warned = crossing - (first.time_s - T0) / DAY_S
    assert warned >= 7, f"alarm {warned:.1f} days before crossing on day {crossing}"
    assert tr.named[-1] == "pump_leakage"
    lo, hi = tr.series["pump_leakage"][-1].lo_u, tr.series["pump_leakage"][-1].hi_u
    assert lo <= u[-1] + 0.1 and hi >= u[-1] - 0.1


def test_a_constant_deviation_raises_no_alarm():
    u = np.full(30, np.log(1.12))
    tr = unit_trend("M2", "boom", rows(u, seed=3), tolerance_mm=3.0, horizon_days=14.0)
    assert tr.first_alarm is None


def test_an_error_already_beyond_tolerance_alarms_without_a_trend():
    u = np.full(12, np.log(1.6))                         # 8 * 0.47 = 3.8 mm, flat
    tr = unit_trend("M3", "boom", rows(u, seed=4), tolerance_mm=3.0, horizon_days=14.0)
    assert tr.alarms[-1] is not None and tr.alarms[-1].cause == "pump_leakage"


def test_beyond_its_days_a_trend_goes_on_at_its_slopes_conservative_bound():
    """A week of logs says how fast a parameter moves over that week: within those days the
    trend goes on at its slope, beyond them at the slope less EXTRAPOLATION_SE standard
    errors. A steady drift crossing 3 mm (8 mm per u) on day 18.75 is alarmed as soon as a
    week of logs allows, and the projection to the horizon is the damped one."""
    from ddh_vsensor.diagnosis.trend import EXTRAPOLATION_SE, _trend
    u = 0.02 * np.arange(30.0)
    tr = unit_trend("M4", "boom", rows(u, cause="time_offset",
                                       others=("pump_leakage", "displacement"), noise=0.02),
                    tolerance_mm=3.0, horizon_days=14.0)
    first = tr.first_alarm
    assert first is not None and first.cause == "time_offset"
    day = (first.time_s - T0) / DAY_S
    assert day == 6.0 and 18.75 - day >= 7.0
    t, fitted, a, b, se, trending = _trend(tr.series["time_offset"][:7])
    assert trending and 0.0 < EXTRAPOLATION_SE * se < b
    u_now, span = a + b * t[-1], t[-1] - t[0]
    damped = u_now + b * span + (b - EXTRAPOLATION_SE * se) * (14.0 - span)
    assert first.error_projected_mm == pytest.approx(8.0 * damped, rel=1e-6)
    assert first.error_projected_mm < 8.0 * (u_now + 14.0 * b)
    assert abs((first.crossing_time_s - T0) / DAY_S - 18.75) <= 1.5


def test_no_cause_is_named_from_less_than_a_week_of_logs():
    """A young window's trend is the scatter of a few days' work (a fleet's false alarms
    came on days 3-6): nothing is named or alarmed before a week of daily logs."""
    u = np.log(1.0 + 0.15 * np.arange(12.0))            # steep: 3 mm by day 3
    tr = unit_trend("M5", "boom", rows(u, seed=5), tolerance_mm=3.0, horizon_days=14.0)
    week = 7
    assert all(a is None for a in tr.alarms[:week - 1])
    assert set(tr.named[:week - 1]) == {"none"}
    assert tr.alarms[week - 1] is not None


def test_one_tight_log_off_the_trend_does_not_carry_it():
    """A log's interval says how well its own references fix the parameter, not how far one
    day's work takes the fit from the next: a confident log far off (a fleet's leakage fit
    x4 for x1.1) must not pull the line through itself."""
    from ddh_vsensor.diagnosis.trend import _line
    t = np.arange(10.0)
    u = 0.01 * t + np.random.default_rng(5).normal(0.0, 0.005, 10)
    var = np.full(10, 0.005 ** 2)
    u[5], var[5] = 1.0, 1e-8
    _, b, se = _line(t, u, var)
    assert abs(b - 0.01) < 0.02, b          # 0.017; weighted by the intervals alone 0.067
    assert abs(b) < 4 * se                  # and no trend to speak of


def test_a_wear_is_alarmed_beside_a_constant_deviation_that_explains_more():
    """What wears is what changes: a machine's constant displacement deviation explains more
    of its references than a young time offset, yet the alarm is the offset's."""
    days = np.arange(30.0)
    u_wear = 0.025 * np.maximum(days - 3, 0)             # 8 mm per u: 3 mm on day 19
    u_const = np.full(30, np.log(1.5))                   # 6 mm per u: 2.4 mm, constant
    shown = {"time_offset": (8.0, u_wear), "displacement": (6.0, u_const)}
    tr = unit_trend("M5", "bucket", mixed_rows(shown, ("belt_slip",), 0.002, 0),
                    tolerance_mm=3.0, horizon_days=14.0)
    crossing = float(np.argmax(8.0 * u_wear > 3.0))
    first = tr.first_alarm
    assert first is not None and first.cause == "time_offset"
    day = int(round((first.time_s - T0) / DAY_S))
    assert crossing - day >= 7                  # 5 when the best-scoring cause was judged
    scores = tr.scores[day]
    assert scores["displacement"] > scores["time_offset"] >= 0.05     # the case in point


def test_a_constant_deviation_that_follows_the_wear_does_not_take_its_alarm():
    """Two causes trend: the pumps' leakage that wears, and the displacement that explains
    the machine's constant deviation (1.5 mm) and follows a little of the wear it stands in
    for (its own error stays under 2.9 mm over the 30 days). The displacement scores more;
    the alarm is judged on the cause whose slope adds most over a constant, the leakage (the
    best-scoring trending cause was judged before: the displacement, on day 20)."""
    days = np.arange(30.0)
    u_wear = 0.02 * np.maximum(days - 2, 0)              # 8 mm per u: 3 mm on day 21
    u_disp = np.log(1.03) + 0.05 * u_wear                # 50 mm per u
    shown = {"pump_leakage": (8.0, u_wear), "displacement": (50.0, u_disp)}
    tr = unit_trend("M5", "bucket", mixed_rows(shown, ("belt_slip",), 0.002, 0),
                    tolerance_mm=3.0, horizon_days=14.0)
    first = tr.first_alarm
    assert first is not None and first.cause == "pump_leakage"
    day = int(round((first.time_s - T0) / DAY_S))
    assert float(np.argmax(8.0 * u_wear > 3.0)) - day >= 7
    scores = tr.scores[day]
    assert scores["displacement"] > scores["pump_leakage"]                # the case in point


def test_between_grid_nodes_a_squared_loss_is_read_as_the_parabola_it_is():
    """The held-out loss of a parameter between two nodes: on a coarse grid a straight line
    would put a loss 0.5 where the parabola has 0.25, enough to keep a young wear's
    held-out score below zero."""
    nodes = np.array([-0.03, -0.01, 0.0, 0.01, 0.03, 0.06])
    loss = (100.0 * nodes) ** 2
    assert _interp_loss(0.005, nodes, loss) == pytest.approx(0.25)
    assert _interp_loss(0.02, nodes, loss) == pytest.approx(4.0)
    assert _interp_loss(0.01, nodes, loss) == pytest.approx(1.0)      # a node is itself


def test_a_fit_at_a_grid_end_has_no_place_on_the_line():
    """A log whose best is the grid's end says the parameter is there or beyond, not where:
    it is left off the trend (a leakage read x0.40 on a wearing bucket held its alarm
    back ten days); the end of a parameter's range (no slip) is a value like any other."""
    from ddh_vsensor.diagnosis.trend import _line, _variances, log_fit
    r = rows(np.log(np.full(3, 0.3)))               # below the leakage grid's x0.4
    leak = log_fit("pump_leakage", next(x for x in r if x["cause"] == "pump_leakage"))
    assert leak.censored and np.isinf(_variances([leak])[0])
    slip = rows(np.zeros(3), cause="belt_slip", others=())[0]
    assert not log_fit("belt_slip", slip).censored
    t, u = np.arange(6.0), 0.1 * np.arange(6.0)
    var = np.full(6, 1e-4)
    u[2], var[2] = -5.0, np.inf
    _, b, _ = _line(t, u, var)
    assert abs(b - 0.1) < 1e-9


def test_an_alarm_holds_for_hold_days_unless_raised_again():
    """A trend near the horizon judged on noisy days raises and drops its alarm from day to
    day; each day without one keeps the last raised fewer than HOLD_DAYS days before."""
    from ddh_vsensor.diagnosis.trend import HOLD_DAYS, Alarm, UnitTrend, _held
    days = 10
    out = UnitTrend("M", "boom", times_s=[T0 + d * DAY_S + 3600.0 * (d % 3)
                                          for d in range(days)])
    raised = {2, 3, 7}
    out.alarms = [Alarm(out.times_s[d], "pump_leakage", 1.3, 2.0, 3.5,
                        out.times_s[d] + 5 * DAY_S) if d in raised else None
                  for d in range(days)]
    held = _held(out).alarms
    on = [d for d, a in enumerate(held) if a is not None]
    assert HOLD_DAYS == 3
    assert on == [2, 3, 4, 5, 7, 8, 9]
    assert held[5] is held[3] and held[9] is held[7]
