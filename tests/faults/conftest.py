"""Shared by the fault-injection suite: the simulated paper cycle (once per session), a hub
per test, and ``run_row``: daemon up, commissioned, fed in real time with a fault injected,
stopped, its outputs recorded."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import can
import numpy as np
import pytest
import yaml

from ddh_vsensor.config import Config
from ddh_vsensor.master.client import commission
from ddh_vsensor.master.replay import machine_frames
from ddh_vsensor.sim import RunSpec, simulate_with_truth

from .harness import Daemon, Hub, Recorder, feed, write_config

REPO = Path(__file__).resolve().parents[2]

pytest.importorskip("can_remote", reason="python-can-remote is not installed")


@dataclass
class Paper:
    """The paper's work cycle at speed 4: the machine's frames and the true positions."""

    frames: list[can.Message]              # with the controllers' heartbeats (every 0.1 s)
    frames_no_heartbeat: list[can.Message]
    truth_t: dict[str, np.ndarray]
    truth_mm: dict[str, np.ndarray]

    def segment(self, t0: float, t1: float, heartbeats: bool = True) -> list[can.Message]:
        src = self.frames if heartbeats else self.frames_no_heartbeat
        return [m for m in src if t0 <= m.timestamp < t1]

    def at(self, actuator: str, t: float) -> float:
        return float(np.interp(t, self.truth_t[actuator], self.truth_mm[actuator]))


@pytest.fixture(scope="session")
def paper(cfg: Config) -> Paper:
    result = simulate_with_truth(cfg, [RunSpec(speed=4)])[0]
    runs = {a: run for a, (run, _) in result.items()}
    return Paper(list(machine_frames(cfg, runs, heartbeat_period_s=0.1)),
                 list(machine_frames(cfg, runs, heartbeat_period_s=None)),
                 {a: truth.time_s for a, (_, truth) in result.items()},
                 {a: truth.x_m * 1e3 for a, (_, truth) in result.items()})


@pytest.fixture(scope="session")
def cfg_raw() -> dict:
    return yaml.safe_load((REPO / "config" / "loader.yaml").read_text())


@pytest.fixture
def hub():
    h = Hub()
    try:
        yield h
    finally:
        h.close()


class Flood:
    """A flooding participant in its own process (``flood.py``): started, then joined."""

    def __init__(self, hub: Hub, kind: str, rate_hz: float, duration_s: float) -> None:
        self.args = [sys.executable, str(Path(__file__).with_name("flood.py")), hub.url, kind,
                     str(rate_hz), str(duration_s)]
        self.proc: subprocess.Popen | None = None
        self.sent = 0
        self.started_wall = self.ended_wall = 0.0

    def start(self) -> None:
        self.proc = subprocess.Popen(self.args, stdout=subprocess.PIPE, text=True)

    def join(self, timeout_s: float = 30.0) -> None:
        assert self.proc is not None
        out, _ = self.proc.communicate(timeout=timeout_s)
        sent, start, end = out.split()
        self.sent, self.started_wall, self.ended_wall = int(sent), float(start), float(end)


@dataclass
class Row:
    daemon: Daemon
    frames: list[can.Message]
    base_wall: float
    exit_code: int | None
    extra: dict = field(default_factory=dict)


CURRENT: list[Daemon] = []       # the daemon of the row running now (RSS samples)


def start_daemon(hub: Hub, tmp_path: Path, cfg_raw: dict, name: str = "daemon", *,
                 overrides: dict | None = None, state_dir: Path | None = None,
                 watchdog_usec: int | None = None) -> Daemon:
    config = write_config(cfg_raw, tmp_path / f"{name}.yaml", **(overrides or {}))
    daemon = Daemon(hub.url, tmp_path, name, config=config, state_dir=state_dir,
                    watchdog_usec=watchdog_usec)
    CURRENT[:] = [daemon]
    try:
        daemon.wait_for("READY=1")
    except BaseException:
        daemon.stop(signal.SIGKILL)          # never leave a daemon behind
        raise
    return daemon


def run_row(hub: Hub, tmp_path: Path, cfg: Config, cfg_raw: dict, paper: Paper,
            t0: float, t1: float, *, heartbeats: bool = True,
            drop: Callable[[can.Message], bool] | None = None,
            hook: Callable[[float, can.BusABC], None] | None = None,
            stamp: Callable[[float, float], float] | None = None,
            overrides: dict | None = None, watchdog_usec: int | None = None,
            preset: bool = True, settle_s: float = 0.3) -> Row:
    """Daemon up; diagnostic frames every 10 ms and (``preset``) both units preset to the
    truth at ``t0`` over SDO; the paper cycle from ``t0`` to ``t1`` fed in real time (less
    the frames ``drop`` says, plus whatever ``hook`` injects; stamped as ``stamp`` says);
    SIGTERM."""
    recorder = Recorder(hub)
    try:
        daemon = start_daemon(hub, tmp_path, cfg_raw, overrides=overrides,
                              watchdog_usec=watchdog_usec)
    except BaseException:
        recorder.close()
        raise
    try:
        commission({"interface": "remote", "channel": hub.url}, cfg,
                   {a: paper.at(a, t0) for a in cfg.can.units} if preset else None,
                   diag_ms=int(cfg.can.event_timer_ms), timeout_s=3.0)
        frames = [m for m in paper.segment(t0, t1, heartbeats) if drop is None or not drop(m)]
        base_wall = feed(hub, frames, hook=hook, stamp=stamp)
        time.sleep(settle_s)
    finally:
        code = daemon.stop(signal.SIGTERM)
        recorder.close()
    return Row(daemon, recorder.frames, base_wall, code)
