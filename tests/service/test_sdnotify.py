"""sd_notify in the standard library, against a fake NOTIFY_SOCKET; the service's use of it."""

from __future__ import annotations

import asyncio
import os
import socket
import time
from pathlib import Path

import pytest

from ddh_vsensor.service import ServiceOptions
from ddh_vsensor.service.sdnotify import SystemdNotifier

from .conftest import channel_name, running_service, settle


class FakeSystemd:
    """An AF_UNIX datagram socket in a temp dir, as systemd's notify socket."""

    def __init__(self, directory: Path) -> None:
        self.path = str(directory / "notify.sock")
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(self.path)
        self.sock.setblocking(False)
        self.messages: list[dict[str, str]] = []

    def read(self) -> list[dict[str, str]]:
        while True:
            try:
                data = self.sock.recv(4096)
            except BlockingIOError:
                return self.messages
            self.messages.append(dict(line.split("=", 1) for line in data.decode().splitlines()))

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def systemd(tmp_path: Path):
    fake = FakeSystemd(tmp_path)
    yield fake
    fake.close()


def test_notify_sends_key_value_lines(systemd: FakeSystemd) -> None:
    n = SystemdNotifier({"NOTIFY_SOCKET": systemd.path})
    assert n.enabled and n.watchdog_interval_s is None
    assert n.notify(READY=1, STATUS="all good")
    assert systemd.read() == [{"READY": "1", "STATUS": "all good"}]


def test_abstract_socket_and_watchdog_interval() -> None:
    name = f"@ddh-vsensor-test-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name[1:])
    try:
        n = SystemdNotifier({"NOTIFY_SOCKET": name, "WATCHDOG_USEC": "2000000"})
        assert n.watchdog_interval_s == 1.0
        assert n.notify(WATCHDOG=1)
        assert sock.recv(100) == b"WATCHDOG=1"
    finally:
        sock.close()
    other = SystemdNotifier({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "1"})
    assert other.watchdog_interval_s is None          # meant for another process


def test_without_systemd_nothing_happens_and_errors_do_not_raise(tmp_path, caplog) -> None:
    assert not SystemdNotifier({}).notify(READY=1)
    gone = SystemdNotifier({"NOTIFY_SOCKET": str(tmp_path / "missing.sock")})
    assert not gone.notify(READY=1)
    assert not gone.notify(STATUS="x")
    assert caplog.text.count("sd_notify") == 1         # said once, not per call


def test_service_ready_status_watchdog_stopping(cfg, unit_tables, systemd) -> None:
    notifier = SystemdNotifier({"NOTIFY_SOCKET": systemd.path, "WATCHDOG_USEC": "40000"})
    channel = channel_name()

    async def scenario():
        options = ServiceOptions(status_interval_s=0.05)
        async with running_service(cfg, unit_tables, channel, options,
                                   notifier=notifier) as service:
            await settle(0.2)
            pings_healthy = sum("WATCHDOG" in m for m in systemd.read())
            # a received batch nobody integrates for > 1 s: the integrator is not advancing
            service.ingest.inbox.append((time.monotonic() - 5.0, "default", [], None))
            n = len(systemd.read())
            await settle(0.2)
            pings_stuck = sum("WATCHDOG" in m for m in systemd.read()[n:])
            service.ingest.inbox.clear()
        return pings_healthy, pings_stuck

    pings_healthy, pings_stuck = asyncio.run(scenario())
    messages = systemd.read()
    assert messages[0]["READY"] == "1" and "boom" in messages[0]["STATUS"]
    assert any("STATUS" in m and "bus open" in m["STATUS"] for m in messages)
    assert pings_healthy >= 2 and pings_stuck == 0
    assert "STOPPING" in messages[-1] or any("STOPPING" in m for m in messages[-2:])
