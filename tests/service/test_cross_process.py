"""The service as a separate process, on a python-can-remote bus served on 127.0.0.1: started
(READY over a fake NOTIFY_SOCKET), commissioned over SDO, fed a replay in real time, stopped
with SIGTERM (exit 0, estimates saved), restarted: its position carries on, and everything it
published equals the offline estimator on the frames it received."""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import can
import pytest

from ddh_vsensor.canbus.dbc import FrameCodec, message_name
from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.estimator.state import load_state
from ddh_vsensor.master.client import commission
from ddh_vsensor.master.replay import replay

from .conftest import START_MM, offline_estimate, paired_outputs

pytest.importorskip("can_remote", reason="python-can-remote is not installed")

STARTUP_TIMEOUT_S = 30.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_for_port(port: int, proc: subprocess.Popen, timeout_s: float) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise RuntimeError(f"can_remote exited with {proc.returncode}")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise TimeoutError(f"can_remote did not listen on {port}")


def _stop(proc: subprocess.Popen, timeout_s: float = 10.0) -> int | None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            return proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
            return None
    return proc.returncode


@pytest.fixture
def remote_url():
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "can_remote", "-i", "virtual", "-c",
                             f"ddh-{uuid.uuid4().hex[:8]}", "-H", "127.0.0.1", "-p", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        _wait_for_port(port, proc, 15.0)
        yield f"ws://127.0.0.1:{port}/"
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)


class Daemon:
    """``ddh-vsensor run`` in its own process, READY awaited on a fake notify socket."""

    def __init__(self, url: str, state_dir: Path, workdir: Path, name: str) -> None:
        self.notify_path = str(workdir / f"{name}.notify")
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(self.notify_path)
        self.log_path = workdir / f"{name}.log"
        env = {**os.environ, "NOTIFY_SOCKET": self.notify_path, "PYTHONUNBUFFERED": "1"}
        env.pop("WATCHDOG_USEC", None)
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ddh_vsensor.cli.main", "run", "--interface", "remote",
             "--channel", url, "--state-dir", str(state_dir)],
            stdout=self._log, stderr=subprocess.STDOUT, env=env)
        self.messages: list[str] = []

    def wait_for(self, key: str, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if any(m.startswith(key) for msg in self.messages for m in msg.splitlines()):
                return
            if self.proc.poll() is not None:
                raise AssertionError(f"daemon exited ({self.proc.returncode}):\n{self.log()}")
            self.sock.settimeout(0.2)
            try:
                self.messages.append(self.sock.recv(4096).decode())
            except socket.timeout:
                pass
        raise AssertionError(f"no {key} from the daemon within {timeout_s} s:\n{self.log()}")

    def log(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors="replace")

    def stop(self) -> int | None:
        code = _stop(self.proc)
        self.sock.settimeout(0.0)
        try:
            while True:
                self.messages.append(self.sock.recv(4096).decode())
        except (BlockingIOError, socket.timeout, OSError):
            pass
        self.sock.close()
        self._log.close()
        return code


class RemoteRecorder:
    """A remote client that keeps every frame it receives, in a thread."""

    def __init__(self, url: str) -> None:
        self.bus = can.Bus(interface="remote", channel=url)
        self.frames: list[can.Message] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.1)
            if msg is not None:
                self.frames.append(msg)

    def mark(self) -> int:
        return len(self.frames)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.bus.shutdown()


def _feed(url: str, frames: list[can.Message]) -> None:
    bus = can.Bus(interface="remote", channel=url)
    try:
        stats = asyncio.run(replay(frames, bus.send, rate=1.0))
    finally:
        bus.shutdown()
    assert stats.frames == len(frames)


def _check_against_offline(cfg, tables, frames, actuator, daemon: Daemon,
                           **offline_kwargs) -> list:
    offline = offline_estimate(cfg, tables, actuator, frames, **offline_kwargs)
    pairs = [p for p in paired_outputs(cfg, frames, actuator) if p.input_frames > offline.held]
    assert len(pairs) >= 10, actuator
    for p in pairs:
        expected = offline.position_mm[p.input_frames - 1 - offline.held]
        assert p.position_mm == pytest.approx(expected, abs=cfg.can.position_step_mm + 1e-9), \
            f"{actuator} at input frame {p.input_frames}; the daemon's log ends:\n" \
            f"{daemon.log()[-3000:]}"
    return pairs


def test_daemon_process_sigterm_and_restart(cfg, unit_tables, frames, remote_url,
                                            tmp_path: Path) -> None:
    state_dir = tmp_path / "state"
    # 2.5 s of the synthetic machine per segment keeps the test short
    segment = [m for m in frames if m.timestamp <= 2.5]
    codec = FrameCodec(cfg)
    recorder = RemoteRecorder(remote_url)
    first = Daemon(remote_url, state_dir, tmp_path, "first")
    try:
        first.wait_for("READY=1", STARTUP_TIMEOUT_S)
        commission({"interface": "remote", "channel": remote_url}, cfg, START_MM,
                   timeout_s=3.0)
        m0 = recorder.mark()
        _feed(remote_url, segment)
        time.sleep(0.3)
        seen1 = recorder.frames[m0:]
    finally:
        code = first.stop()
    assert code == 0, first.log()
    assert any("STOPPING=1" in m for m in first.messages)
    for actuator in cfg.can.units:
        _check_against_offline(cfg, unit_tables, seen1, actuator, first,
                               preset_mm=START_MM[actuator])
    saved = {a: load_state(state_dir / f"{a}.json", a, cfg.physics_hash())
             for a in cfg.can.units}
    assert all(s is not None for s in saved.values())
    last = {a: paired_outputs(cfg, seen1, a)[-1].position_mm for a in cfg.can.units}
    for a in cfg.can.units:
        assert saved[a].position_mm == pytest.approx(last[a], abs=0.02)

    second = Daemon(remote_url, state_dir, tmp_path, "second")
    try:
        second.wait_for("READY=1", STARTUP_TIMEOUT_S)
        m1 = recorder.mark()
        time.sleep(0.3)                          # nothing fed yet: the restored positions
        idle = recorder.frames[m1:]
        m2 = recorder.mark()
        _feed(remote_url, segment)
        time.sleep(0.3)
        seen2 = recorder.frames[m2:]
    finally:
        code = second.stop()
        recorder.close()
    assert code == 0, second.log()
    for actuator in cfg.can.units:
        pos_id = codec.ids[message_name("position", actuator)]
        restored = [codec.decode(m)[1] for m in idle if m.arbitration_id == pos_id]
        assert restored, second.log()
        assert restored[-1]["Position"] == pytest.approx(saved[actuator].position_mm, abs=0.01)
        assert restored[-1]["Status"] & Flags.NOT_REFERENCED      # until a reference switch
        _check_against_offline(cfg, unit_tables, seen2, actuator, second, state=saved[actuator])
