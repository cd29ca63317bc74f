"""Each unit's health on its node: the worker judges it from the day summaries whenever it
writes a day and the daemon puts it on the node; the file it writes is read at the next start
(after a kill too); a file that is not a health is logged and none published."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import pytest

from ddh_vsensor.diagnosis.day_summary import summary_name
from ddh_vsensor.diagnosis.health import FILE, document, machine_health
from ddh_vsensor.service import Service, ServiceOptions
from ddh_vsensor.service.health import load_health, node_health

# a bound, not a timing: the worker runs at nice 10, and a machine whose cores are busy
# (CI beside another load) gives it a small share
WORKER_WAIT_S = 300.0

MACHINE = "M07"                      # the synthetic days' (tests/conftest.py)


def summaries(wear_days, state: Path, days: int = 16) -> list[dict]:
    """A wearing boom and a steady bucket, ``days`` day summaries in the state directory."""
    docs = wear_days(days)
    (state / "summaries").mkdir(parents=True)
    for doc in docs:
        (state / "summaries" / summary_name(MACHINE, doc["day"])).write_text(json.dumps(doc))
    return docs


def daemon(cfg, unit_tables, state: Path) -> Service:
    return Service(cfg, unit_tables, {"interface": "virtual", "channel": "unused"},
                   ServiceOptions(state_dir=state, machine=MACHINE))


def test_the_health_document_becomes_the_nodes_objects(cfg, wear_days):
    boom, bucket = cfg.unit_names[:2]
    docs = wear_days(16)
    doc = json.loads(json.dumps(document(cfg, MACHINE, machine_health(cfg, MACHINE, docs))))
    health = node_health(doc)
    h = health[boom]
    judged = machine_health(cfg, MACHINE, docs)[boom]
    assert h.alarm and h.cause_code == judged.cause_code > 0 and h.days == 16
    assert h.days_to_tolerance == judged.days_to_tolerance and h.value == judged.value
    assert h.interval == judged.interval and h.days_needed == 0
    assert not health[bucket].alarm and health[bucket].days_to_tolerance is None
    for bad in ({"format": "x", "units": {}}, {**doc, "units": {boom: {"alarm": True}}},
                {**doc, "units": {boom: {**doc["units"][boom], "value": float("nan")}}}):
        with pytest.raises(ValueError):
            node_health(bad)


def test_the_worker_judges_the_health_and_the_nodes_get_it(cfg, unit_tables, wear_days,
                                                           tmp_path):
    state = tmp_path / "state"
    summaries(wear_days, state)
    service = daemon(cfg, unit_tables, state)
    boom = cfg.unit_names[0]
    assert service.units[boom].node.health is None            # no file yet
    recorder = service.summaries
    assert recorder._alive()                   # the worker judges the days it finds at start
    deadline = time.monotonic() + WORKER_WAIT_S
    while not (state / FILE).is_file() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert recorder.close(WORKER_WAIT_S)
    h = service.units[boom].node.health
    assert h is not None and h.alarm and h.cause_code > 0
    assert service._health_alarms == {boom}
    assert json.loads((state / FILE).read_text())["units"][boom]["alarm"]


def test_a_restart_publishes_the_last_health_at_once(cfg, unit_tables, wear_days, tmp_path,
                                                     caplog):
    state = tmp_path / "state"
    docs = summaries(wear_days, state)
    (state / FILE).write_text(json.dumps(document(cfg, MACHINE,
                                                  machine_health(cfg, MACHINE, docs))))
    service = daemon(cfg, unit_tables, state)          # no worker started: the file's
    boom, bucket = cfg.unit_names[:2]
    assert service.units[boom].node.health.alarm
    assert not service.units[bucket].node.health.alarm
    (state / FILE).write_text("{half a file")
    caplog.set_level(logging.WARNING, logger="ddh_vsensor.service.health")
    assert load_health(state / FILE) == {}
    assert "not read" in caplog.text and "none published" in caplog.text
    service = daemon(cfg, unit_tables, state)
    assert service.units[boom].node.health is None


def test_status_health_prints_the_finding_in_words_and_bad_input_is_one_line(
        cfg, wear_days, tmp_path, capsys):
    from ddh_vsensor.cli.main import main
    boom, bucket = cfg.unit_names[:2]
    docs = wear_days(16)
    (tmp_path / FILE).write_text(json.dumps(document(cfg, MACHINE,
                                                     machine_health(cfg, MACHINE, docs))))
    assert main(["status", "--health", "--state-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out.splitlines()
    line = next(x for x in out if x.startswith(f"{boom}: "))
    left = machine_health(cfg, MACHINE, docs)[boom].days_to_tolerance
    assert "ALARM" in line and "pressure scale" in line, line
    assert f"in {int(left)} days" in line and "From 16 days of evidence (16 day summaries)" \
        in line, line
    assert any(x.startswith(f"{bucket}: ") and "ALARM" not in x for x in out)
    assert main(["status", "--health", "--state-dir", str(tmp_path), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data[boom]["alarm"] and data[boom]["cause"] == "pump_leakage"
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["status", "--health", "--state-dir", str(empty)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no health in" in err[0]
