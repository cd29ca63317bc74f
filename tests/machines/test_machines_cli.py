"""Every command of the issue's offline chain on every shipped machine, as a user runs it:
``python -m ddh_vsensor`` in a subprocess, exit 0."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

from ddh_vsensor.config import DEFAULT_BUS, Config
from ddh_vsensor.io.csv import read_csv

TIMEOUT_S = 600


def cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "ddh_vsensor", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=TIMEOUT_S,
                          env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert proc.returncode == 0, (args, proc.stdout[-2000:], proc.stderr[-2000:])
    assert "Traceback" not in proc.stderr
    return proc


@pytest.fixture(scope="module")
def workdir(machine: Config, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp(Path(machine.source).stem)


@pytest.fixture(scope="module")
def simulated(machine: Config, workdir: Path) -> dict[str, Path]:
    """``simulate`` of the machine's work cycle (CSV + BLF) and of a random cycle (CSV)."""
    cfg = machine.source
    work, rand = workdir / "work", workdir / "random"
    cli("simulate", "--config", cfg, "--cycle", "work", "--payload-kg", "0", "--oil-temp-c",
        "27", "--step-s", "0.002", "--out", work, cwd=workdir)
    cli("simulate", "--config", cfg, "--cycle", "random", "--duration-s", "20", "--seed", "5",
        "--payload-kg", "0", "--oil-temp-c", "35", "--step-s", "0.002", "--no-blf",
        "--out", rand, cwd=workdir)
    return {"work": work, "random": rand}


def test_config_validate_and_tables_build(machine: Config, workdir: Path):
    out = cli("config", "--validate", machine.source, cwd=workdir).stdout
    assert "valid" in out
    cli("tables", "build", "--config", machine.source, "--out", workdir / "tables", cwd=workdir)
    for a in machine.unit_names:
        assert any(p.name.startswith(a) for p in (workdir / "tables").iterdir()), a


def test_simulate_writes_one_csv_per_unit(machine: Config, simulated: dict[str, Path]):
    for a in machine.unit_names:
        assert (simulated["work"] / f"{a}.csv").is_file()
        assert (simulated["random"] / f"{a}.csv").is_file()
    assert (simulated["work"] / "run.blf").is_file()
    assert not (simulated["random"] / "run.blf").exists()


def test_estimate_every_unit(machine: Config, simulated: dict[str, Path], workdir: Path):
    for a in machine.unit_names:
        out = cli("estimate", simulated["work"] / f"{a}.csv", "--config", machine.source,
                  "--actuator", a, "--mode", "full", "--json", cwd=workdir).stdout
        score = json.loads(out)
        assert score["max_abs_error_mm"] < 10.0, (a, score)


def test_analyze_a_unit(machine: Config, simulated: dict[str, Path], workdir: Path):
    a = machine.unit_names[-1]
    cli("analyze", simulated["work"] / f"{a}.csv", simulated["random"] / f"{a}.csv",
        "--config", machine.source, "--actuator", a, "--report", workdir / "report",
        cwd=workdir)
    assert (workdir / "report" / "report.json").is_file()


def test_demo(machine: Config, workdir: Path):
    out = cli("demo", "--config", machine.source, "--rate", "20", "--no-figure",
              cwd=workdir).stdout
    assert "summary" in out
    for a in machine.unit_names:
        assert f"  {a}" in out, a


# --- the daemon and its bench tools ---------------------------------------------------------

# Worst full-mode error of each machine on its work cycle and random strokes, measured in
# test_machines.py (the loader's figure; the others' shortfalls). From a preset the daemon
# takes its first reference whole (a preset is provisional: docs, operations, Presets), even
# in motion, where an edge is known to one sample's travel: the bound adds the run's largest
# travel between two samples (about 2 mm at this 100 Hz log's top speeds; 0.2 mm at 1 kHz).
MAX_ERROR_MM = {"loader": 0.75, "bench": 1.25, "excavator": 1.95}
READY_TIMEOUT_S = 60.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def remote_buses(names: tuple[str, ...]) -> Iterator[dict[str, str]]:
    """A python-can-remote server (virtual bus) on 127.0.0.1 per bus name: name -> URL."""
    procs, urls = [], {}
    try:
        for name in names:
            port = _free_port()
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "can_remote", "-i", "virtual", "-c",
                 f"ddh-{uuid.uuid4().hex[:8]}", "-H", "127.0.0.1", "-p", str(port)],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            end = time.monotonic() + 30.0
            while True:
                try:
                    socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
                    break
                except OSError:
                    assert time.monotonic() < end, f"can_remote for {name} did not start"
                    time.sleep(0.05)
            urls[name] = f"ws://127.0.0.1:{port}/"
        yield urls
    finally:
        for proc in procs:
            proc.terminate()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)


def _on_remote_buses(machine: Config, urls: dict[str, str], path: Path) -> Path:
    data = yaml.safe_load(Path(machine.source).read_text())
    data["bus"] = {"interface": "remote", "channel": urls[DEFAULT_BUS]}
    data["buses"] = {name: {"interface": "remote", "channel": urls[name]}
                     for name in machine.buses}
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_run_status_replay_monitor(machine: Config, simulated: dict[str, Path], workdir: Path):
    """``run`` on the machine's buses (one python-can-remote server per configured bus),
    ``status --preset`` of every unit to its start, ``replay --inputs-only`` of the simulated
    log onto each unit's bus, ``status --json`` (each unit within the machine's figure of
    the truth), ``monitor --log``, SIGTERM: exit 0 throughout."""
    pytest.importorskip("can_remote", reason="python-can-remote is not installed")
    truth = {a: read_csv(simulated["work"] / f"{a}.csv").position_mm
             for a in machine.unit_names}
    with remote_buses(machine.bus_names) as urls:
        cfg = _on_remote_buses(machine, urls, workdir / "remote.yaml")
        notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        notify.bind(str(workdir / "notify"))
        notify.settimeout(0.5)
        log = open(workdir / "run.log", "wb")
        daemon = subprocess.Popen(
            [sys.executable, "-m", "ddh_vsensor", "run", "--config", str(cfg), "--state-dir",
             str(workdir / "state")], stdout=log, stderr=subprocess.STDOUT,
            env={**os.environ, "NOTIFY_SOCKET": str(workdir / "notify")})
        try:
            end, said = time.monotonic() + READY_TIMEOUT_S, ""
            while "READY=1" not in said:
                assert daemon.poll() is None and time.monotonic() < end, \
                    (workdir / "run.log").read_text()[-3000:]
                with contextlib.suppress(socket.timeout):
                    said += notify.recv(4096).decode()
            presets = [f"{a}={float(x[0]):.2f}" for a, x in truth.items()]
            cli("status", "--config", cfg, *[arg for p in presets for arg in ("--preset", p)],
                cwd=workdir)
            cli("replay", simulated["work"] / "run.blf", "--config", cfg, "--inputs-only",
                "--rate", "4", "--stamp", "log", cwd=workdir)
            time.sleep(0.5)
            status = json.loads(cli("status", "--config", cfg, "--json", cwd=workdir).stdout)
            out = cli("monitor", "--config", cfg, "--log", simulated["work"] / "run.blf",
                      cwd=workdir).stdout
        finally:
            daemon.send_signal(signal.SIGTERM)
            code = daemon.wait(30)
            log.close()
            notify.close()
    assert code == 0, (workdir / "run.log").read_text()[-3000:]
    for a in machine.unit_names:
        bound = MAX_ERROR_MM[Path(machine.source).stem] + machine.can.position_step_mm \
            + float(np.max(np.abs(np.diff(truth[a]))))
        assert status[a]["input_frames"] > 0, a
        assert status[a]["position_mm"] == pytest.approx(float(truth[a][-1]), abs=bound), a
        assert a in out, a
