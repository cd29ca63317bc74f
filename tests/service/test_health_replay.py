"""The daemon warns of a wear before it matters (the issue's done-when, small): a machine whose
boom's pumps wear fast, replayed day by day through the real service (its own event loop
thread on a virtual bus, its day-summary worker a process), time compressed; a canopen master
on the bus reads the health object 0x2010 over SDO every day and collects the EMCY; the
"maintenance due" warning (FF30) comes at least a week before the expected error passes the
tolerance, with the right cause, and never from the steady unit. Then the daemon as a process
(``ddh-vsensor run`` on a python-can-remote bus on 127.0.0.1) given the replay's state
directory publishes that health at once, and again at once after a kill -9.

The replay: each day's work is one minute of the fleet simulator's work (``simulate_fleet``,
times already the day's wall clock), fed through the service's own receive path
(``ingest.handle``) with the daemon's wall clock at each frame's time
(``unit_state.read_wall_offset`` and the service's ``wall_clock``), so that each day's samples
land in that day's summary. After each day the worker is handed the last samples and awaited
(every block taken: the day written, the health judged and on the nodes). The truth of the
crossing is the simulator's (:func:`.sim.fleet.expected_error_mm`). Every wait is bounded;
nothing is timed.

The 30-day version (the fleet's own wear rates, a no-wear machine beside it) is
``bench/health.py``."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import canopen
import pytest

from ddh_vsensor.device.emcy import MAINTENANCE_CODE
from ddh_vsensor.device.objects import HEALTH_ALARM, health_values
from ddh_vsensor.diagnosis.causes import CAUSE_NAMES
from ddh_vsensor.diagnosis.health import FILE
from ddh_vsensor.master.client import clients
from ddh_vsensor.master.replay import machine_frames
from ddh_vsensor.service import Service, ServiceOptions, unit_state
from ddh_vsensor.service.health import node_health
from ddh_vsensor.sim.fleet import (START_DATE, FleetPlan, MachinePlan, Wear, expected_error_mm,
                                   simulate_fleet)

MACHINE = "M09"
DAYS = 15
WORN, STEADY = "boom", "bucket"
# The boom's pump leakage from nominal, 3.6 % more a day from day 0: on this machine's days
# (machine seed 3, fleet seed 5: a minute of work a day) the expected error at the references
# passes 3 mm on day 14 (the simulator's truth). The health can name it from seven days of
# evidence; the daemon has day 6 whole once day 7's work comes (a day's last stretch is
# summed into its day when the next samples come).
WEAR = Wear(WORN, "pump_leakage", 0, 0.036)
PLAN = FleetPlan([MachinePlan(MACHINE, {a: {"pump_leakage": 1.0, "displacement": 1.0}
                                        for a in (WORN, STEADY)}, WEAR, seed=3)],
                 DAYS, seed=5, log_s=60.0, work_s=60.0)
CROSSING_DAY = 14
LEAD_DAYS = 7
WAIT_S = 120.0          # bound of every wait on the service, its worker or a process
# the master's bus reader's receive timeout, which its disconnect waits out (canopen: 1 s)
NOTIFIER_CYCLE_S = 0.05


class ReplayClock:
    """The daemon's wall clock in the replay: the time of the frame being handled."""

    def __init__(self) -> None:
        self.now_s = START_DATE.timestamp()

    def __call__(self) -> float:
        return self.now_s

    def wall_offset(self) -> tuple[float, float, float]:
        """As :func:`.unit_state.read_wall_offset`: the wall clock, a constant offset to the
        monotonic clock (no clock step), no reading error."""
        return self.now_s, 0.0, 0.0


class ServiceInThread:
    """The real service on a virtual channel, its own loop in a thread; frames into its
    receive path from the test's thread."""

    def __init__(self, cfg, tables, channel: str, options: ServiceOptions,
                 clock: ReplayClock) -> None:
        self.clock = clock
        self._ready = threading.Event()
        self._holder: dict[str, Any] = {}
        self._thread = threading.Thread(target=self._run,
                                        args=(cfg, tables, channel, options), daemon=True)
        self._thread.start()
        assert self._ready.wait(WAIT_S) and "error" not in self._holder, self._holder
        self.service: Service = self._holder["service"]
        self.loop: asyncio.AbstractEventLoop = self._holder["loop"]

    def _run(self, cfg, tables, channel, options) -> None:
        async def main() -> None:
            service = Service(cfg, tables, {"interface": "virtual", "channel": channel},
                              options, wall_clock=self.clock)
            self._holder.update(service=service, loop=asyncio.get_running_loop())
            await service.start()
            self._ready.set()
            try:
                await service._stop_event.wait()                     # noqa: SLF001
            finally:
                await service.shutdown()
        try:
            asyncio.run(main())
        except BaseException as exc:   # noqa: BLE001 - reported to the test
            self._holder["error"] = exc
            self._ready.set()

    def call(self, fn, *args) -> Any:
        async def run() -> Any:
            return fn(*args)
        return asyncio.run_coroutine_threadsafe(run(), self.loop).result(WAIT_S)

    def feed(self, frames: list[can.Message]) -> None:
        """Through ``ingest.handle`` as the bus link hands frames over, received now
        (monotonic), the wall clock at the frame's time; the ticks run between slices."""
        ingest, clock = self.service.ingest, self.clock

        async def handle(chunk: list[can.Message]) -> None:
            for k in range(0, len(chunk), 200):
                for msg in chunk[k:k + 200]:
                    clock.now_s = msg.timestamp
                    ingest.handle([msg], time.monotonic())
                await asyncio.sleep(0)
        for i in range(0, len(frames), 2000):
            asyncio.run_coroutine_threadsafe(handle(frames[i:i + 2000]),
                                             self.loop).result(WAIT_S)

    def settle(self) -> None:
        """The kept samples to the worker; every block taken (the day written, the health
        judged and handed to the nodes: it comes before the block's "done"), then two
        ticks (the EMCY goes out on a tick)."""
        recorder = self.service.summaries
        assert recorder is not None
        self.call(recorder.ship, True)
        deadline = time.monotonic() + WAIT_S
        while (w := recorder._worker) is not None and \
                self.call(lambda w=w: w.queued):
            assert time.monotonic() < deadline and not recorder.disabled, \
                "the summary worker did not take its blocks"
            time.sleep(0.05)
        ticks = self.service.ticks
        while self.service.ticks < ticks + 2:
            assert time.monotonic() < deadline, "the service did not tick"
            time.sleep(0.01)

    def stop(self) -> None:
        self.loop.call_soon_threadsafe(self.service.request_stop)
        self._thread.join(WAIT_S)
        assert not self._thread.is_alive() and "error" not in self._holder, self._holder


@dataclass
class Day:
    day: int
    health: dict[str, Any]                  # the nodes' Health
    sdo: dict[str, list[int]]               # 0x2010 sub 1..6 as the master read them
    ff30: dict[str, int]                    # FF30s the master got from each node so far


@dataclass
class Replayed:
    crossing_day: int
    days: list[Day] = field(default_factory=list)
    emcy: dict[str, list[tuple[int, int, int]]] = field(default_factory=dict)  # day, code, reg
    state: Path | None = None
    doc: dict | None = None                 # health.json at the end
    final: dict[str, Any] | None = None     # the nodes' health after the stop


def _emcy_seen(node: canopen.RemoteNode, code: int) -> int:
    return sum(1 for e in node.emcy.log if e.code == code)


@pytest.fixture(scope="module")
def replayed(cfg, unit_tables, tmp_path_factory) -> Replayed:
    machine = PLAN.machines[0]
    crossing = next(d for d in range(DAYS) if expected_error_mm(cfg, PLAN, machine, d)
                    > cfg.health.tolerance_mm)
    out = Replayed(crossing)
    work = tmp_path_factory.mktemp("health_replay")
    state = work / "state"
    state.mkdir()                                       # as `run` makes it
    channel = f"ddh-health-{uuid.uuid4().hex[:12]}"
    clock = ReplayClock()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(unit_state, "read_wall_offset", clock.wall_offset)
        network = canopen.Network()
        network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
        network.connect(interface="virtual", channel=channel)
        try:
            nodes = {u: c.node for u, c in clients(network, cfg).items()}
            daemon = ServiceInThread(cfg, unit_tables, channel,
                                     ServiceOptions(state_dir=state, machine=MACHINE), clock)
            recorder = daemon.service.summaries
            assert recorder is not None
            # the samples go to the worker once a day, at its end (the test's settle); the
            # worker writes the day and judges the health after each block: once a day, as
            # its 5-minute writes would for a minute of work in a real day
            recorder.clock = lambda: 0.0
            recorder.save_interval_s = 0.0
            taken = {u: 0 for u in nodes}
            try:
                def summarise(_name: str, day: int, sessions: list) -> None:
                    daemon.feed([m for runs in sessions
                                 for m in machine_frames(cfg, runs, heartbeat_period_s=None)])
                    daemon.settle()
                    health = daemon.call(lambda: {a: u.node.health
                                                  for a, u in daemon.service.units.items()})
                    for unit, node in nodes.items():
                        if health[unit] is not None and health[unit].alarm:
                            _wait_for(lambda n=node: _emcy_seen(n, MAINTENANCE_CODE),
                                      f"the {unit}'s FF30")
                    for unit, node in nodes.items():
                        new = node.emcy.log[taken[unit]:]
                        taken[unit] += len(new)
                        out.emcy.setdefault(unit, []).extend(
                            (day, e.code, e.register) for e in new)
                    out.days.append(Day(
                        day, health,
                        {u: [n.sdo[0x2010][s].raw for s in range(1, 7)]
                         for u, n in nodes.items()},
                        {u: _emcy_seen(n, MAINTENANCE_CODE) for u, n in nodes.items()}))

                simulate_fleet(cfg, PLAN, work / "logs", summarise=summarise,
                               days_per_batch=DAYS)     # one campaign: the days at once
            finally:
                daemon.stop()               # the last day whole, judged, on the nodes
            out.final = {a: u.node.health for a, u in daemon.service.units.items()}
        finally:
            network.disconnect()
    out.state = state
    out.doc = json.loads((state / FILE).read_text())
    return out


def _wait_for(predicate, what: str, timeout_s: float = 10.0) -> Any:
    deadline = time.monotonic() + timeout_s
    while not (value := predicate()):
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)
    return value


def test_the_warning_comes_a_week_before_the_crossing_with_the_right_cause(cfg, replayed):
    days = replayed.days
    assert [d.day for d in days] == list(range(DAYS))
    assert replayed.crossing_day == CROSSING_DAY        # the simulator's truth
    assert all(d.health[u] is not None for d in days for u in cfg.unit_names)
    first = next(d for d in days if d.ff30[WORN])
    assert first.day <= replayed.crossing_day - LEAD_DAYS, [
        (d.day, d.health[WORN]) for d in days]
    # the master read it as the node served it: cause, maintenance due, the same as judged
    code = CAUSE_NAMES.index(WEAR.effect)
    h = first.health[WORN]
    assert h.alarm and h.cause_code == code and h.days >= 7
    assert first.sdo[WORN][0] == code and first.sdo[WORN][1] & HEALTH_ALARM
    assert first.sdo[WORN] == list(health_values(h)[1:7])
    assert h.days_to_tolerance is not None and h.days_to_tolerance <= cfg.health.horizon_days
    # EMCY FF30 with the error register's generic and manufacturer bits
    (day, _, register), = [e for e in replayed.emcy[WORN] if e[1] == MAINTENANCE_CODE]
    assert day == first.day and register & 0x81 == 0x81
    # nothing before it; the wear only grows: it stays due, told once
    assert all(not d.health[WORN].alarm and not d.sdo[WORN][1] & HEALTH_ALARM
               for d in days[:first.day])
    assert all(d.health[WORN].alarm and d.sdo[WORN][1] & HEALTH_ALARM
               for d in days[first.day:])
    # the steady unit: never a warning
    assert all(not d.health[STEADY].alarm for d in days)
    assert not any(c == MAINTENANCE_CODE for _, c, _ in replayed.emcy[STEADY])
    # what the worker wrote is what the nodes serve
    doc = replayed.doc
    assert doc["units"][WORN]["cause"] == WEAR.effect and doc["units"][WORN]["alarm"]
    assert node_health(doc) == replayed.final


# --- the daemon as a process: the health at once after a start and after a kill -9 ---------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Process:
    """``ddh-vsensor run`` in its own process; READY=1 awaited on a fake notify socket."""

    def __init__(self, url: str, state: Path, workdir: Path, name: str) -> None:
        self.notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.notify.bind(str(workdir / f"{name}.notify"))
        self.log_path = workdir / f"{name}.log"
        env = {**os.environ, "NOTIFY_SOCKET": str(workdir / f"{name}.notify"),
               "PYTHONUNBUFFERED": "1"}
        env.pop("WATCHDOG_USEC", None)
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "ddh_vsensor.cli.main", "run", "--interface", "remote",
                 "--channel", url, "--state-dir", str(state), "--machine", MACHINE],
                stdout=log, stderr=subprocess.STDOUT, env=env)

    def wait_ready(self) -> None:
        deadline = time.monotonic() + WAIT_S
        self.notify.settimeout(0.2)
        while time.monotonic() < deadline:
            assert self.proc.poll() is None, self.log_path.read_text(errors="replace")
            try:
                if "READY=1" in self.notify.recv(4096).decode():
                    return
            except TimeoutError:
                pass
        raise AssertionError(f"no READY=1: {self.log_path.read_text(errors='replace')}")

    def end(self, sig: int) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(WAIT_S)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self.notify.close()


@pytest.fixture
def hub():
    """A python-can-remote hub on 127.0.0.1 for one test."""
    pytest.importorskip("can_remote", reason="python-can-remote is not installed")
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "can_remote", "-i", "virtual", "-c",
                             f"ddh-{uuid.uuid4().hex[:8]}", "-H", "127.0.0.1", "-p", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + WAIT_S
        while True:
            assert proc.poll() is None, "can_remote ended"
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                    break
            except OSError:
                assert time.monotonic() < deadline, "can_remote did not listen"
                time.sleep(0.05)
        yield f"ws://127.0.0.1:{port}/"
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


@pytest.mark.slow
def test_a_killed_daemon_publishes_the_health_at_once_after_its_restart(cfg, replayed, hub,
                                                                        tmp_path):
    state = tmp_path / "state"
    shutil.copytree(replayed.state, state)
    want = {u: list(health_values(h)[1:6]) for u, h in node_health(replayed.doc).items()}
    assert want[WORN][1] & HEALTH_ALARM and want[WORN][0] == CAUSE_NAMES.index(WEAR.effect)
    network = canopen.Network()
    network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
    network.connect(interface="remote", channel=hub)
    try:
        nodes = {u: c.node for u, c in clients(network, cfg).items()}

        def read() -> dict[str, list[int]]:
            return {u: [n.sdo[0x2010][s].raw for s in range(1, 6)] for u, n in nodes.items()}

        first = Process(hub, state, tmp_path, "first")
        try:
            first.wait_ready()
            assert read() == want
        finally:
            first.end(signal.SIGKILL)
        assert first.proc.returncode == -signal.SIGKILL
        assert json.loads((state / FILE).read_text()) == replayed.doc     # as it was
        second = Process(hub, state, tmp_path, "second")
        try:
            second.wait_ready()
            assert read() == want                       # at once: no day fed since
        finally:
            second.end(signal.SIGTERM)
        assert second.proc.returncode == 0, second.log_path.read_text(errors="replace")
    finally:
        network.disconnect()
