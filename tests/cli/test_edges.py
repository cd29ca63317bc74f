"""The edges a user meets, each one line on stderr and exit 2 (or a run that goes through
where the data allow it): a run of the other actuator, a log without the position column,
an output path that cannot be written, a cut-off BLF, the fleet without its extra or its
workers, the demo's start and end, the simulated logs' heartbeats."""

from __future__ import annotations

import logging
import re
import shutil
import sys
from pathlib import Path

import can
import numpy as np
import pytest

from ddh_vsensor.cli.main import main
from ddh_vsensor.config import load_config
from ddh_vsensor.io.csv import read_csv

UNWRITABLE = Path("/sys")          # refuses new files even to root
needs_unwritable = pytest.mark.skipif(not UNWRITABLE.is_dir(), reason="no /sys")


def _one_line(err: str) -> str:
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """``ddh-vsensor simulate`` of the work cycle: boom.csv, bucket.csv, run.blf."""
    out = tmp_path_factory.mktemp("sim") / "runs"
    assert main(["-q", "simulate", "--cycle", "work", "--payload-kg", "0", "--oil-temp-c", "40",
                 "--out", str(out)]) == 0
    return out


# --- 1: a file's '# actuator:' line against --actuator; runs titled by their path ---------

def test_a_run_of_the_other_actuator_is_refused(runs: Path, capsys) -> None:
    assert main(["estimate", str(runs / "bucket.csv"), "--actuator", "boom"]) == 2
    err = _one_line(capsys.readouterr().err)
    assert "bucket.csv: a run of the bucket (its '# actuator: bucket' line), not of the boom " \
           "(--actuator boom)" in err
    assert main(["analyze", str(runs / "boom.csv"), str(runs / "bucket.csv"), "--actuator",
                 "boom", "--report", str(runs.parent / "rep")]) == 2
    assert "bucket.csv: a run of the bucket" in _one_line(capsys.readouterr().err)


def test_the_report_titles_runs_by_their_paths(runs: Path, tmp_path: Path, capsys) -> None:
    other = tmp_path / "other"
    other.mkdir()
    shutil.copy(runs / "boom.csv", other / "boom.csv")
    report = tmp_path / "rep"
    paths = [str(runs / "boom.csv"), str(other / "boom.csv")]
    assert main(["-q", "analyze", *paths, "--actuator", "boom", "--report", str(report)]) == 0
    html = (report / "report.html").read_text()
    for path in paths:
        assert f"<td>{path}</td>" in html, path


# --- 2: no position_mm column ------------------------------------------------------------

@pytest.fixture(scope="module")
def no_position(runs: Path) -> Path:
    """The boom run as a machine in service logs it: no position column at all."""
    lines = (runs / "boom.csv").read_text().splitlines()
    k = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    column = lines[k].split(",").index("position_mm")
    path = runs.parent / "in_service.csv"
    path.write_text("\n".join(lines[:k] + [",".join(c for i, c in enumerate(line.split(","))
                                                    if i != column)
                                           for line in lines[k:]]) + "\n")
    return path


def test_a_log_without_the_position_column_reads_as_never_sampled(no_position: Path) -> None:
    run = read_csv(no_position)
    assert len(run.time_s) > 1000 and np.isnan(run.position_mm).all()


def test_the_tools_that_need_the_position_say_so(no_position: Path, tmp_path: Path,
                                                 capsys) -> None:
    assert main(["estimate", str(no_position), "--actuator", "boom"]) == 2
    assert "no reference position (position_mm) to score" in _one_line(capsys.readouterr().err)
    assert main(["analyze", str(no_position), str(no_position), "--actuator", "boom",
                 "--truth", "position", "--report", str(tmp_path / "r")]) == 2
    assert "position_mm is never given" in _one_line(capsys.readouterr().err)
    out = tmp_path / "est.csv"
    assert main(["estimate", str(no_position), "--actuator", "boom", "--out", str(out)]) == 0
    assert "no reference position to score against" in capsys.readouterr().out
    assert np.isfinite(read_csv(out).position_mm).all()


# --- 3: every output path checked before the work -----------------------------------------

@needs_unwritable
@pytest.mark.parametrize("argv, problem", [
    (["estimate", "RUN", "--actuator", "boom", "--plot", "/sys/x.png"],
     r"/sys/x\.png: cannot write the plot in /sys: \w"),
    (["estimate", "RUN", "--actuator", "boom", "--plot", "OUT/x.figure"],
     r"x\.figure: cannot write the plot: its extension must be one of .*\.png.*\(not \.figure\)"),
    (["estimate", "RUN", "--actuator", "boom", "--out", "OUT/missing/e.csv"],
     r"e\.csv: cannot write the estimate: no directory .*missing"),
    (["tables", "build", "--out", "/sys/tables"], r"/sys/tables: cannot create the tables "
                                                   r"directory: \w"),
    (["tables", "plot", "--out", "OUT"], r"cannot write the figure: its extension"),
    (["simulate", "--cycle", "work", "--payload-kg", "0", "--oil-temp-c", "40", "--out",
      "/sys/runs"], r"/sys/runs: cannot (create|write) the output directory"),
    (["simulate", "fleet", "--machines", "1", "--days", "1", "--out", "/sys/fleet"],
     r"/sys/fleet: cannot (create|write) the output directory"),
    (["analyze", "RUN", "RUN", "--actuator", "boom", "--report", "/sys/rep"],
     r"/sys/rep: cannot create the report directory"),
    (["dbc", "--out", "OUT"], r"cannot write the DBC: a directory of that name exists"),
])
def test_an_output_that_cannot_be_written_stops_before_the_work(
        argv: list[str], problem: str, runs: Path, tmp_path: Path, monkeypatch,
        capsys) -> None:
    def no_work(*_a, **_k):
        raise AssertionError("the work started")
    for target in ("ddh_vsensor.cli.simulate.simulate", "ddh_vsensor.io.reader.read_csv",
                   "ddh_vsensor.cli.tables.build_unit_tables", "ddh_vsensor.sim.fleet.plan_fleet"):
        monkeypatch.setattr(target, no_work)
    argv = [str(runs / "boom.csv") if a == "RUN" else a.replace("OUT", str(tmp_path))
            for a in argv]
    assert main(argv) == 2
    err = _one_line(capsys.readouterr().err)
    assert re.search(problem, err), err


# --- 4: a cut-off BLF: read what is whole, say what was cut -------------------------------

@pytest.fixture(scope="module")
def cut_blf(runs: Path) -> Path:
    raw = (runs / "run.blf").read_bytes()
    path = runs.parent / "cut.blf"
    path.write_bytes(raw[:len(raw) // 2])
    return path


WARNING = re.compile(r"WARNING ddh_vsensor\.io\.blf: (\S+): truncated BLF: object at byte \d+ "
                     r"cut off; read the whole objects before it, \d+ of \d+ bytes \(\d+ %\)")


@pytest.mark.parametrize("argv", [
    ["estimate", "LOG", "--actuator", "boom"],
    ["monitor", "--log", "LOG", "--every", "5"],
    ["replay", "LOG", "--interface", "virtual", "--channel", "edges-cut", "--rate", "0"],
])
def test_a_cut_blf_is_read_in_part_with_one_warning(argv: list[str], cut_blf: Path,
                                                    capsys) -> None:
    assert main([a.replace("LOG", str(cut_blf)) for a in argv]) == 0
    err = capsys.readouterr().err
    warnings = [line for line in err.splitlines() if "WARNING" in line]
    assert len(warnings) == 1 and "Traceback" not in err, err
    match = WARNING.search(warnings[0])
    assert match and match.group(1) == str(cut_blf), warnings


@pytest.mark.parametrize("argv", [
    ["estimate", "LOG", "--actuator", "boom"],
    ["monitor", "--log", "LOG"],
    ["replay", "LOG", "--interface", "virtual", "--channel", "edges-empty", "--rate", "0"],
])
def test_an_empty_blf_is_one_line(argv: list[str], tmp_path: Path, capsys) -> None:
    empty = tmp_path / "empty.blf"
    empty.write_bytes(b"")
    assert main([a.replace("LOG", str(empty)) for a in argv]) == 2
    assert f"{empty}: cannot read CAN log: the file is empty" in _one_line(
        capsys.readouterr().err)


# --- 5: the fleet: its extra, nothing ingested, a scheduler without workers ----------------

def test_fleet_without_its_extra_names_the_install(monkeypatch, tmp_path: Path,
                                                   capsys) -> None:
    monkeypatch.setitem(sys.modules, "pyarrow", None)
    for argv in (["fleet", "ingest", str(tmp_path), "--store", str(tmp_path / "s")],
                 ["fleet", "report", "--store", str(tmp_path), "--out", "r.html"]):
        assert main(argv) == 2
        err = _one_line(capsys.readouterr().err)
        assert 'needs pyarrow, part of the fleet extra: pip install "ddh-vsensor[fleet]"' in err


def test_fleet_ingest_of_a_mistyped_directory_is_one_line(tmp_path: Path, capsys) -> None:
    pytest.importorskip("pyarrow")
    assert main(["fleet", "ingest", str(tmp_path / "lgos"), "--store", str(tmp_path / "s")]) == 2
    assert f"{tmp_path / 'lgos'}: no such file or directory" in _one_line(
        capsys.readouterr().err)
    assert main(["fleet", "ingest", str(tmp_path), "--store", str(tmp_path / "s")]) == 2
    assert "no logs in" in _one_line(capsys.readouterr().err)


@pytest.fixture(scope="module")
def threads_cluster():
    """Schedulers on 127.0.0.1: one with a worker (threads of this process), one without."""
    distributed = pytest.importorskip("dask.distributed")
    kwargs = dict(processes=False, protocol="tcp://", host="127.0.0.1", dashboard_address=None,
                  scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                  silence_logs=logging.ERROR)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, **kwargs) as one, \
            distributed.LocalCluster(n_workers=0, **kwargs) as none:
        yield one.scheduler_address, none.scheduler_address


def test_fleet_ingest_with_every_log_rejected_exits_2(threads_cluster, tmp_path: Path,
                                                      capsys) -> None:
    empty = tmp_path / "m1_2026-01-01_10h.blf"
    empty.write_bytes(b"")
    assert main(["fleet", "ingest", str(empty), "--store", str(tmp_path / "s"),
                 "--scheduler", threads_cluster[0]]) == 2
    captured = capsys.readouterr()
    assert "rejected: " in captured.out and "the file is empty" in captured.out
    error = [line for line in captured.err.splitlines() if "error:" in line]
    assert error == ["ddh-vsensor fleet: error: nothing ingested: 1 file(s) given, every one "
                     "rejected"], captured.err


def test_a_scheduler_without_workers_times_out_in_one_line(threads_cluster, tmp_path: Path,
                                                           capsys) -> None:
    log = tmp_path / "m1_2026-01-01_10h.blf"
    log.write_bytes(b"")
    assert main(["fleet", "ingest", str(log), "--store", str(tmp_path / "s"), "--scheduler",
                 threads_cluster[1], "--worker-timeout-s", "1"]) == 2
    err = capsys.readouterr().err
    assert f"--scheduler {threads_cluster[1]}: no worker joined within 1 s" in err
    assert "Traceback" not in err


# --- 6: the simulated logs carry the controllers' heartbeats; the demo ends cleanly --------

def _heartbeats(path: Path) -> dict[int, np.ndarray]:
    out: dict[int, list[float]] = {}
    with can.BLFReader(path) as reader:
        for msg in reader:
            if 0x701 <= msg.arbitration_id <= 0x77F:
                assert bytes(msg.data) == b"\x05", msg           # OPERATIONAL
                out.setdefault(msg.arbitration_id, []).append(msg.timestamp)
    return {k: np.array(v) for k, v in out.items()}


def _assert_heartbeats(path: Path) -> None:
    cfg = load_config()
    beats = _heartbeats(path)
    assert set(beats) == {0x700 + n for n in cfg.faults.heartbeat_node_ids.values()}, beats
    for t in beats.values():
        np.testing.assert_allclose(np.diff(t), 0.1, atol=1e-6)
        assert np.diff(t).max() < cfg.faults.heartbeat_timeout_s


def test_simulated_logs_carry_the_controllers_heartbeats(runs: Path, tmp_path: Path) -> None:
    _assert_heartbeats(runs / "run.blf")
    # the logs alone: --work-s 0 leaves out the day summaries, not a frame of the logs
    assert main(["-q", "simulate", "fleet", "--machines", "1", "--days", "2", "--log-s", "20",
                 "--work-s", "0", "--out", str(tmp_path)]) == 0
    logs = sorted(tmp_path.glob("*.blf"))
    assert len(logs) == 2
    for log in logs:
        _assert_heartbeats(log)


def test_the_demo_starts_and_ends_without_warnings(capsys) -> None:
    assert main(["demo", "--rate", "10", "--no-figure"]) == 0
    captured = capsys.readouterr()
    for word in ("no heartbeat yet", "no oil temperature yet", "input stale",
                 "controller_not_operational"):
        assert word not in captured.err, captured.err
    blocks = captured.out.split("  t = ")
    last = blocks[-1].split("\n\nsummary:")[0]
    rows = [line for line in last.splitlines() if " true " in line]
    assert len(rows) == 2 and all(line.endswith("[ok]") for line in rows), last


def test_the_demo_figure_is_scaled_to_the_error() -> None:
    from ddh_vsensor.cli.demo import _Pairing, figure

    class Truth:
        time_s = np.linspace(0.0, 10.0, 101)
        x_m = np.linspace(0.1, 0.3, 101)

    t = Truth.time_s
    p = _Pairing(t, t, Truth.x_m * 1e3)
    u = np.full(len(t), 3.7)
    u[-1] = 24.0                                     # an end-of-run spike
    p.samples = [(ti, xi + 0.05, xi, ui) for ti, xi, ui in zip(t, Truth.x_m * 1e3, u)]
    fig = figure({"boom": p}, {"boom": Truth})
    low, high = fig.axes[1].get_ylim()
    assert high == pytest.approx(0.075) and low == pytest.approx(-0.075)


def test_a_simulated_log_replayed_into_the_service_finds_its_controllers_operational(
        runs: Path) -> None:
    """The service consumes the controllers' heartbeats (faults.heartbeat_node_ids): a log
    without them is flagged controller_not_operational throughout, with EMCYs."""
    import asyncio
    import os

    from ddh_vsensor.canbus.dbc import FrameCodec, message_name
    from ddh_vsensor.master.replay import bus_sender, read_log, replay
    from ddh_vsensor.service import Service, ServiceOptions
    from ddh_vsensor.tables.build import build_unit_tables

    cfg = load_config()
    codec = FrameCodec(cfg)
    positions = {codec.ids[message_name("position", a)] for a in cfg.unit_names}
    frames = [m for m in read_log(runs / "run.blf")
              if m.timestamp <= 3.0 and m.arbitration_id not in positions]
    channel = f"edges-heartbeat-{os.getpid()}"

    async def serve() -> tuple[str, list[can.Message]]:
        service = Service(cfg, {a: build_unit_tables(cfg, a) for a in cfg.unit_names},
                          {"interface": "virtual", "channel": channel},
                          ServiceOptions(state_dir=None))
        machine = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        listener = can.Bus(interface="virtual", channel=channel)
        try:
            await service.start()
            await replay(frames, bus_sender(machine), rate=1.0, stamp="log")
            status = service.status_line()
        finally:
            await service.shutdown()
        heard = []
        while (msg := listener.recv(0.0)) is not None:
            heard.append(msg)
        for bus in (machine, listener):
            bus.shutdown()
        return status, heard

    status, heard = asyncio.run(serve())
    assert "controller_not_operational" not in status, status
    emcy_ids = {0x80 + cfg.can.units[a].sensor_node_id for a in cfg.unit_names}
    codes = {int.from_bytes(bytes(m.data[:2]), "little") for m in heard
             if m.arbitration_id in emcy_ids}
    assert not codes & {0x8130, 0xFF11}, sorted(hex(c) for c in codes)
