"""A machine's health from its own day summaries: a wearing unit's cause, interval and the days
until its error passes the tolerance; a steady one none; too few days said so; the file
written atomically and read back, unreadable summaries left out with a note."""

from __future__ import annotations

import datetime as dt
import json

import numpy as np
import pytest

from ddh_vsensor.diagnosis.day_summary import summary_name
from ddh_vsensor.diagnosis.health import (FILE, machine_health, read_health, refresh,
                                          summary_files)
from ddh_vsensor.diagnosis.trend import DAY_S, MIN_LOGS

from ..conftest import MACHINE, T0, day_docs, steady, wearing

def test_a_wearing_unit_is_alarmed_with_its_cause_and_days_left_a_steady_one_not(cfg):
    boom, bucket = cfg.unit_names[:2]
    docs = day_docs(cfg, {boom: wearing(16), bucket: steady(16)})
    health = machine_health(cfg, MACHINE, docs)
    h = health[boom]
    assert h.cause == "pump_leakage" and h.parameter == "leakage_factor" and h.alarm
    assert h.days == 16 and h.days_needed == 0
    true_factor = 1.0 + 0.03 * 12
    assert h.interval[0] < h.value < h.interval[1]
    assert abs(np.log(h.value / true_factor)) < 3 * 0.02      # the day's noise: 0.02 in log
    # 8 mm per unit of log(factor): 3 mm at factor exp(3/8) = 1.45, i.e. day 18; today 15
    assert h.days_to_tolerance is not None and 1.0 <= h.days_to_tolerance <= 5.0
    assert h.error_now_mm == pytest.approx(8.0 * np.log(true_factor), abs=0.4)
    quiet = health[bucket]
    assert not quiet.alarm and quiet.days_to_tolerance is None and quiet.days == 16


def test_too_few_days_say_how_many_more(cfg):
    boom = cfg.unit_names[0]
    h = machine_health(cfg, MACHINE, day_docs(cfg, {boom: wearing(MIN_LOGS - 2)}))[boom]
    assert h.cause == "none" and not h.alarm and h.days == MIN_LOGS - 2
    assert h.days_needed == 2
    other = machine_health(cfg, MACHINE, [])[cfg.unit_names[1]]
    assert other.days == 0 and other.days_needed == MIN_LOGS


def test_the_file_is_written_read_back_and_bad_summaries_are_left_out(cfg, tmp_path):
    boom = cfg.unit_names[0]
    summaries = tmp_path / "summaries"
    summaries.mkdir()
    for doc in day_docs(cfg, {boom: wearing(14)}):
        (summaries / summary_name(MACHINE, doc["day"])).write_text(json.dumps(doc))
    (summaries / summary_name(MACHINE, "2030-01-01")).write_text("{not json")
    (summaries / summary_name("M08", "2026-01-05")).write_text("{}")   # another machine's
    assert len(summary_files(summaries, MACHINE)) == 15
    doc, notes = refresh(cfg, MACHINE, summaries, tmp_path / FILE)
    assert len(notes) == 1 and "2030-01-01" in notes[0] and "not JSON" in notes[0]
    assert doc["units"][boom]["cause_code"] > 0 and doc["units"][boom]["alarm"]
    back = read_health(tmp_path / FILE)
    assert back[boom] == machine_health(cfg, MACHINE, [
        json.loads(p.read_text()) for p in summary_files(summaries, MACHINE)
        if "2030" not in p.name])[boom]
    assert not list(tmp_path.glob("*.tmp"))


def test_a_file_that_is_not_a_health_is_refused(tmp_path):
    path = tmp_path / FILE
    path.write_text(json.dumps({"format": "something else", "version": 1, "units": {}}))
    with pytest.raises(ValueError, match="not a ddh-vsensor health"):
        read_health(path)
    path.write_text(json.dumps({"format": "ddh-vsensor health", "version": 1,
                                "units": {"boom": {"actuator": "boom", "days": 3,
                                                   "cause": "gremlins"}}}))
    with pytest.raises(ValueError, match="gremlins"):
        read_health(path)


def test_only_the_newest_days_are_read(cfg, tmp_path):
    boom = cfg.unit_names[0]
    for doc in day_docs(cfg, {boom: steady(30)}):
        (tmp_path / summary_name(MACHINE, doc["day"])).write_text(json.dumps(doc))
    files = summary_files(tmp_path, MACHINE, days=10)
    newest = dt.datetime.fromtimestamp(T0 + 29 * DAY_S, dt.timezone.utc).date().isoformat()
    assert len(files) == 10 and files[-1].name == summary_name(MACHINE, newest)
