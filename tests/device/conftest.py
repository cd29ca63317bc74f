"""A CANopen master on the service's bus: the in-process service runs its own event loop in a
thread, the test drives a canopen ``RemoteNode`` per sensor from the shipped EDS, over
python-can's ``virtual`` bus, the way a PLC or a configuration tool would.

Waits are bounded (``wait_for``) and every "nothing came" is counted against frames that did
come (TPDO1s, heartbeats), never against the wall clock."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import can
import canopen
import pytest

from ddh_vsensor.config import Config
from ddh_vsensor.service import Service, ServiceOptions
from ddh_vsensor.master.client import clients
from ddh_vsensor.device.objects import Published

WAIT_S = 10.0          # bound of every wait: generous, a loaded machine only makes it slower
# receive timeout of the test's bus readers: only how long stopping one may wait for it (a
# frame ends a receive at once)
NOTIFIER_CYCLE_S = 0.05


def wait_for(predicate: Callable[[], Any], what: str, timeout_s: float = WAIT_S) -> Any:
    """Poll until ``predicate()`` is truthy; its value, or a failure naming ``what``."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.005)


class Frames(can.Listener):
    """Every frame the master sees, in order."""

    def __init__(self) -> None:
        self.frames: list[can.Message] = []
        self._lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        with self._lock:
            self.frames.append(msg)

    def mark(self) -> int:
        with self._lock:
            return len(self.frames)

    def since(self, mark: int, can_id: int | None = None) -> list[can.Message]:
        with self._lock:
            frames = self.frames[mark:]
        return [m for m in frames if can_id is None or m.arbitration_id == can_id]

    def wait_count(self, mark: int, can_id: int, count: int, what: str) -> list[can.Message]:
        return wait_for(lambda: len(got := self.since(mark, can_id)) >= count and got,
                        f"{count} x {what}")


@dataclasses.dataclass
class Master:
    network: canopen.Network
    frames: Frames
    nodes: dict[str, canopen.RemoteNode]


class FlaggedService(Service):
    """The real service with fault flags added at its boundary (``extra_flags``), for the
    faults a test cannot provoke through inputs, and flags hidden there (``masked_flags``)
    where a test needs a clean start the inputs cannot give (a preset stays unconfirmed
    until a Hall reference)."""

    extra_flags: dict[str, int]
    masked_flags: int = 0

    def published(self, unit, now=None) -> Published:  # type: ignore[override]
        p = super().published(unit, now)
        extra = getattr(self, "extra_flags", {}).get(unit.actuator, 0)
        flags = (p.flags & ~self.masked_flags) | extra
        return dataclasses.replace(p, flags=flags) if flags != p.flags else p


@contextlib.contextmanager
def service_thread(cfg: Config, tables: dict, channel: str,
                   options: ServiceOptions | None = None,
                   service_cls: type[Service] = Service) -> Iterator[Service]:
    """The service on ``channel`` with its own event loop in a thread, until the block ends."""
    started = threading.Event()
    holder: dict[str, Any] = {}

    async def main() -> None:
        service = service_cls(cfg, tables, {"interface": "virtual", "channel": channel},
                              options or ServiceOptions())
        holder["service"], holder["loop"] = service, asyncio.get_running_loop()
        await service.start()
        started.set()
        try:
            await service._stop_event.wait()                   # noqa: SLF001
        finally:
            await service.shutdown()

    def run() -> None:
        try:
            asyncio.run(main())
        except BaseException as exc:   # noqa: BLE001 - reported to the test
            holder["error"] = exc
            started.set()

    thread = threading.Thread(target=run, name="ddh-vsensor service", daemon=True)
    thread.start()
    started.wait(WAIT_S)
    if "error" in holder or "service" not in holder:
        raise RuntimeError(f"service did not start: {holder.get('error')!r}")
    service = holder["service"]
    try:
        yield service
    finally:
        holder["loop"].call_soon_threadsafe(service.request_stop)
        thread.join(WAIT_S)
        assert not thread.is_alive(), "service thread did not stop"
        assert "error" not in holder, holder.get("error")


@contextlib.contextmanager
def master_on(cfg: Config, channel: str) -> Iterator[Master]:
    """A canopen master network with one RemoteNode per sensor (the shipped EDS)."""
    network = canopen.Network()
    network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S      # canopen's 1 s: a second per disconnect
    frames = Frames()
    network.listeners.append(frames)
    network.connect(interface="virtual", channel=channel)
    nodes = {unit: client.node for unit, client in clients(network, cfg).items()}
    try:
        yield Master(network, frames, nodes)
    finally:
        network.disconnect()


@pytest.fixture
def channel() -> str:
    return f"ddh-canopen-{uuid.uuid4().hex[:12]}"


@pytest.fixture
def bus(cfg: Config, unit_tables: dict, channel: str) -> Iterator[tuple[Service, Master]]:
    """Master first (it sees the boot-up), then the service, auto start as configured."""
    with master_on(cfg, channel) as master, service_thread(cfg, unit_tables, channel) as service:
        yield service, master


class Feeder:
    """The machine's inputs: oil temperature and standstill Sevcon frames every 10 ms, and the
    controllers' OPERATIONAL heartbeats every 100 ms, from a thread, with increasing
    timestamps, until stopped."""

    def __init__(self, cfg: Config, channel: str) -> None:
        from ddh_vsensor.canbus.dbc import FrameCodec
        self.codec = FrameCodec(cfg)
        self.cfg = cfg
        self.bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="feeder", daemon=True)

    def _run(self) -> None:
        t, k = 1000.0, 0
        heartbeats = [0x700 + n for n in self.cfg.faults.heartbeat_node_ids.values()]
        while not self._stop.is_set():
            self.bus.send(self.codec.encode_oil_temp(30.0, t))
            for actuator in self.cfg.can.units:
                self.bus.send(self.codec.encode_sevcon(actuator, 0.0, 0.0, t))
            if k % 10 == 0:
                for can_id in heartbeats:
                    self.bus.send(can.Message(arbitration_id=can_id, data=[0x05],
                                              is_extended_id=False, timestamp=t))
            t, k = t + 0.01, k + 1
            self._stop.wait(0.01)

    def __enter__(self) -> Feeder:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(WAIT_S)
        self.bus.shutdown()
