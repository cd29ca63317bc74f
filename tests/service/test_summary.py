"""The daemon's day summary: the frames it integrates, summarised by its worker process, give
the day the simulator's summary of the same work gives; a dead worker is started again and
goes on from the day's file; a bad machine name is one line."""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import signal
import time
from pathlib import Path

import pytest

from ddh_vsensor.cli.main import main
from ddh_vsensor.diagnosis.day_summary import read_summary, summarise_runs
from ddh_vsensor.master.replay import machine_frames
from ddh_vsensor.service import Service, ServiceOptions
from ddh_vsensor.sim.fleet import day_spec, plan_fleet
from ddh_vsensor.sim.run import simulate_campaign

# a bound, not a timing: the worker runs at nice 10, and a machine whose cores are busy
# (CI beside another load) gives it a small share
WORKER_WAIT_S = 300.0

DAY = dt.datetime(2026, 3, 2, 7, tzinfo=dt.timezone.utc).timestamp()


@pytest.fixture(scope="module")
def sessions(cfg) -> list[dict]:
    """Two minutes of a fleet machine's work, an hour apart (times on the wall clock)."""
    plan = plan_fleet(cfg, 1, 3, seed=8, log_s=60.0)
    runs = simulate_campaign(cfg, [day_spec(cfg, plan, plan.machines[0], d) for d in (0, 1)])
    for k, per_unit in enumerate(runs):
        for run in per_unit.values():
            run.shift_time(DAY + 3600.0 * k)
    return runs


@pytest.fixture(scope="module")
def session_frames(cfg, sessions) -> list[list]:
    """Each session's frames as the machine puts them on the bus (made once: the service
    only reads them)."""
    return [list(machine_frames(cfg, runs, heartbeat_period_s=None)) for runs in sessions]


def daemon(cfg, unit_tables, state: Path) -> Service:
    return Service(cfg, unit_tables, {"interface": "virtual", "channel": "unused"},
                   ServiceOptions(state_dir=state, machine="M7"))


def integrate(service: Service, frames: list) -> None:
    """A session's frames through the service's own receive path, stamped as received."""
    for msg in frames:
        service.ingest.handle([msg], msg.timestamp)


def handed_over(recorder):
    """The worker, once it has taken every block shipped now (bounded wait)."""
    recorder.ship(force=True)
    worker = recorder._worker
    deadline = time.monotonic() + WORKER_WAIT_S
    while worker.queued and time.monotonic() < deadline:
        time.sleep(0.05)
        worker.collect()
    return worker


def written(state: Path) -> dict:
    path, = (state / "summaries").glob("M7_*.summary.json")
    return json.loads(path.read_text())


def test_the_daemons_day_is_the_simulators_day_of_the_same_work(cfg, unit_tables, sessions,
                                                                session_frames, tmp_path):
    service = daemon(cfg, unit_tables, tmp_path / "state")
    assert all(u.summary_feed is not None for u in service.units.values())
    for frames in session_frames:
        integrate(service, frames)
        service.summaries.ship(force=True)
    assert service.summaries.close(WORKER_WAIT_S)
    got = written(tmp_path / "state")
    assert got["day"] == dt.datetime.now(dt.timezone.utc).date().isoformat()   # its clock's
    want = json.loads(summarise_runs(cfg, "M7", sessions, tmp_path / "sim")[0].read_text())
    for actuator, u in want["units"].items():
        g = got["units"][actuator]
        assert u["stretches"] >= 2
        for k in ("stretches", "increments", "holds", "n_obs"):
            assert g[k] == u[k], (actuator, k)
        assert g["loss_nominal"] == pytest.approx(u["loss_nominal"], rel=1e-12)
        for cause, arrays in u["causes"].items():
            for k, values in arrays.items():
                assert g["causes"][cause][k] == pytest.approx(values, rel=1e-12, abs=1e-15)
    read_summary(json.dumps(got).encode(), "daemon", cfg)


def test_a_dead_worker_is_started_again_and_goes_on_from_the_days_file(
        cfg, unit_tables, session_frames, tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="ddh_vsensor.service.summary")
    service = daemon(cfg, unit_tables, tmp_path / "state")
    recorder = service.summaries
    recorder.save_interval_s = 0.0              # the worker writes after every block
    integrate(service, session_frames[0])
    worker = handed_over(recorder)
    before = written(tmp_path / "state")
    os.kill(worker.process.pid, signal.SIGKILL)
    worker.process.wait()
    integrate(service, session_frames[1])
    assert recorder.close(WORKER_WAIT_S)
    assert recorder.restarts == 1 and recorder._worker is not worker
    after = written(tmp_path / "state")
    assert after["first_s"] == before["first_s"]
    for actuator in cfg.can.units:
        assert after["units"][actuator]["stretches"] > before["units"][actuator]["stretches"]
    assert "goes on from it" in caplog.text and "started again" in caplog.text


def test_no_machine_no_summaries_and_a_bad_name_is_one_line(cfg, unit_tables, tmp_path,
                                                            capsys):
    service = Service(cfg, unit_tables, {"interface": "virtual", "channel": "unused"},
                      ServiceOptions(state_dir=tmp_path))
    assert service.summaries is None
    assert all(u.summary_feed is None for u in service.units.values())
    capsys.readouterr()     # the service's own start lines (logging set up by earlier tests)
    assert main(["run", "--machine", "no/name", "--state-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--machine: machine name 'no/name'" in err[0]


def test_a_worker_left_by_a_killed_daemon_writes_the_day_on_sigterm(cfg, unit_tables,
                                                                   session_frames, tmp_path):
    """What systemd does to a killed daemon's worker: SIGTERM; the worker ends its stretches
    and writes the day before it exits."""
    service = daemon(cfg, unit_tables, tmp_path / "state")
    recorder = service.summaries
    integrate(service, session_frames[0])
    worker = handed_over(recorder)
    assert not (tmp_path / "state" / "summaries").exists()      # nothing written yet
    worker.process.send_signal(signal.SIGTERM)
    assert worker.process.wait(WORKER_WAIT_S) == 0
    day = written(tmp_path / "state")
    assert all(u["stretches"] >= 1 for u in day["units"].values())
