"""Benchmark: the daemon at nominal load and on a saturated bus.

Nominal: two Sevcon controllers at 1 kHz, oil 10 Hz, I/O module 100 Hz, heartbeats 10 Hz;
the service publishes at 100 Hz (event timer 10 ms; the diagnostic frame's timer is set to
10 ms over SDO so every published position can be paired with its input counter).
Saturated: the same plus other nodes' traffic, >= 8000 frames/s in all.

Figures (all from bus timestamps, as a listener on the bus sees them):
- latency: publish time of a position frame minus the bus time of the newest Sevcon frame
  the published value includes (its diag frame's input counter names it). With 1 kHz input
  this is at most ~1 ms plus the pipeline's own delay. Socket mode: a Sevcon frame's bus
  time is taken when its send returned, a position frame's by the kernel as it arrives at
  the recorder (SO_TIMESTAMPNS); ``latency_beyond_input_age`` is the part the service adds
  to the newest input's own age (0 when it included every frame sent before the publish);
- processing: a Sevcon frame's bus time to the end of its estimator step (inside the service);
- jitter: |period - 10 ms| between consecutive position frames of a cylinder;
- CPU share: the service's threads' CPU time over wall time (in-process: the event loop thread
  and the bus reader thread, per-thread clocks; separate process: /proc/PID/stat);
- lost: Sevcon frames sent minus Sevcon frames the service counted.

Modes (this machine has no SocketCAN):
- ``socket`` (the headline): the production read path. The service reads a kernel datagram
  socket carrying SocketCAN's 16-byte frames with the event loop's fd reader, exactly as it
  reads a SocketCAN socket (no reader thread); the machine's traffic comes from a separate
  process that stamps each frame when it sends it and each output frame when it receives it:
  the figures are end to end, two kernel hops included. CPU: the service process's own time.
- ``inproc``: python-can ``virtual``; the feeder a thread of the same process (sharing its
  GIL), the service's bus reader a thread;
- ``remote``: the daemon as its own process (``ddh-vsensor run``) behind python-can-remote on
  127.0.0.1: websocket decoding in the daemon and a server process in between.

``--units N`` (socket mode): a larger machine, N copies of the reference loader's first unit
(``u1``..``uN``, Sevcon node i, sensor node 48 + i, three Hall bits each), inputs at
``--input-hz`` (500 Hz for N > 2), split over ``--buses`` (2 by default for N > 2: the upper
half of the units on a second bus, ``can.units.*.bus``) where the service reads several buses;
results in ``daemon_units<N>.json``.

``--profile MS``: where the time goes, independent of the machine's load: MS milliseconds of
the machine's traffic pushed through the service's own receive, routing, estimator and publish
path synchronously (no event loop, frame times from a virtual clock), once to count CPU time
per frame and once under cProfile for each stage's share; results in ``daemon_profile.json``.
The event loop's own cost is what the socket mode's CPU share adds to this.

``--summaries``: the socket mode's nominal load without and with the day summary (the
service process's CPU share: the per-frame sample feed and the blocks handed over), then
the summary worker's own cost (:func:`summary_worker_cost`); results in
``daemon_summaries.json``.

``--estimator-mode MODE``: the service on that estimator mode instead of the configuration's
(``kalman``: the Kalman filter, stepping at ``can.sevcon_period_ms``, set here to the bench's
Sevcon period, 1 ms at 1 kHz); results in ``daemon_<MODE>.json`` (and ``_<MODE>`` appended
to the other modes' names), the committed ``daemon.json`` untouched.
``--saturated-seconds 0``: the nominal load only.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import collections
import cProfile
import dataclasses
import pstats
import resource
import multiprocessing
import os
import select
import signal
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

import can
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import publish  # noqa: E402

from ddh_vsensor.canbus.dbc import FrameCodec, message_name  # noqa: E402
from ddh_vsensor.config import DEFAULT_BUS, load_config  # noqa: E402
from ddh_vsensor.service import Service, ServiceOptions  # noqa: E402
from ddh_vsensor.master.client import clients, sdo_network  # noqa: E402
from ddh_vsensor.tables.build import build_unit_tables  # noqa: E402

INPUT_HZ = 1000.0
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)    # Linux; not exported by Python
TIMESPEC = struct.Struct("@qq")
OTHER_IDS = [0x200 + i for i in range(1, 40)] + [0x300 + i for i in range(1, 40)]


def kernel_stamp(ancillary: list, default: float) -> float:
    """The kernel's arrival time of a datagram read with recvmsg (SO_TIMESTAMPNS on)."""
    for level, kind, value in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
            sec, nsec = TIMESPEC.unpack(value)
            return sec + nsec * 1e-9
    return default


class Feeder(threading.Thread):
    """Sends the machine's traffic (and ``other_hz`` frames/s of other nodes) in slots of
    1 / ``input_hz`` from absolute deadlines; counts what it sent. ``buses``: bus name ->
    bus; each unit's frames go to its unit's bus, the oil, I/O and other frames to the
    default bus (one bus for all: every name maps to it)."""

    def __init__(self, buses: dict[str, can.BusABC], cfg, other_hz: float,
                 input_hz: float = INPUT_HZ) -> None:
        super().__init__(daemon=True)
        self.codec, self.other_hz, self.input_hz = FrameCodec(cfg), other_hz, input_hz
        self.units = list(cfg.can.units)
        self.default = buses[DEFAULT_BUS]
        self.bus_of = {a: buses.get(cfg.can.units[a].bus, self.default) for a in self.units}
        self.bus = self.default
        self.stop_event = threading.Event()
        self.sent = {a: 0 for a in self.units}
        self.sevcon_times: dict[str, list[float]] = {a: [] for a in self.units}
        self.send_s: list[float] = []      # each Sevcon frame's send call (its stamp's spread)
        self.total = 0
        self.errors = 0
        self.skipped_slots = 0          # slots the feeder was too late for (not sent)
        self.started_s = self.ended_s = 0.0
        self.start_at_s: float | None = None   # first slot (monotonic); None: 10 ms from now

    def _send(self, msg: can.Message, bus: can.BusABC | None = None) -> None:
        try:
            (bus or self.default).send(msg)
            self.total += 1
        except can.CanError:
            self.errors += 1

    def run(self) -> None:
        c = self.codec
        self._send(c.encode_oil_temp(30.0))
        self._send(c.encode_inputs({a: {} for a in self.units}))
        slot, k = 1.0 / self.input_hz, 0
        per_10ms = max(1, round(0.01 * self.input_hz))
        other_acc, other_i = 0.0, 0
        start = self.start_at_s or time.monotonic() + 0.01
        self.started_s = start
        while not self.stop_event.is_set():
            due = start + k * slot
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -2 * slot:     # late: skip, as a controller's timer would (no burst)
                behind = int(-delay / slot)
                self.skipped_slots += behind
                k += behind
                continue
            t = k * slot
            for i, a in enumerate(self.units):
                speed = 3000.0 * np.sin(2 * np.pi * t / (6.0 + i))
                msg = c.encode_sevcon(a, 10.0 + 5 * np.sin(t), round(speed))
                before = time.time()
                self._send(msg, self.bus_of[a])
                # the frame is on the bus once its send returned (a stamp taken before the
                # encoding would count a frame as sent before it was)
                self.sevcon_times[a].append(time.time())
                self.send_s.append(self.sevcon_times[a][-1] - before)
                self.sent[a] += 1
            if k % per_10ms == 0:
                refs = {a: {"mid": int(np.sin(2 * np.pi * t / (6.0 + i)) > 0.9)}
                        for i, a in enumerate(self.units)}
                self._send(c.encode_inputs(refs))
            if k % (10 * per_10ms) == 0:
                self._send(c.encode_oil_temp(30.0 + t * 0.01))
                for a in self.units:
                    self._send(c.encode(message_name("heartbeat", a), {"NmtState": 5}),
                               self.bus_of[a])
            other_acc += self.other_hz * slot
            while other_acc >= 1.0:
                other_acc -= 1.0
                other_i += 1
                self._send(can.Message(arbitration_id=OTHER_IDS[other_i % len(OTHER_IDS)],
                                       data=other_i.to_bytes(8, "little"),
                                       is_extended_id=False))
            k += 1
        self.ended_s = time.monotonic()


def machine_config(units: int | None, buses: int):
    """The reference loader, or ``units`` copies of its first unit named u1..uN (Sevcon node
    i, sensor node 48 + i, consecutive Hall bits), the upper half on a second bus when
    ``buses`` is 2. Tables are built once and shared: the copies have the same physics."""
    cfg = load_config(None)
    if units is None and buses == 1:
        return cfg
    count = units or len(cfg.unit_names)
    first = cfg.unit_names[0]
    unit, can_unit = cfg.units[first], cfg.can.units[first]
    names = [f"u{i}" for i in range(1, count + 1)]
    refs = list(unit.references_mm)
    split = count - count // 2 if buses > 1 else count
    can_units = {name: dataclasses.replace(
        can_unit, sevcon_node_id=i + 1, sensor_node_id=48 + i + 1,
        hall_bits={r: len(refs) * i + b for b, r in enumerate(refs)},
        bus=DEFAULT_BUS if i < split else "second") for i, name in enumerate(names)}
    bus_kwargs = {"interface": "socketpair", "channel": DEFAULT_BUS}
    return dataclasses.replace(
        cfg, units={name: unit for name in names}, bus=bus_kwargs,
        buses={"second": {"interface": "socketpair", "channel": "second"}} if buses > 1
        else {},
        can=dataclasses.replace(cfg.can, units=can_units),
        faults=dataclasses.replace(cfg.faults, heartbeat_node_ids={
            name: i + 1 for i, name in enumerate(names)}))


def machine_tables(cfg) -> dict:
    """Tables per unit; units with the same physics share one build."""
    built: dict[str, object] = {}
    tables = {}
    for name in cfg.unit_names:
        key = repr(cfg.units[name])
        if key not in built:
            built[key] = build_unit_tables(cfg, name)
        tables[name] = dataclasses.replace(built[key], actuator=name)
    return tables


def _commission(bus: can.BusABC, cfg) -> None:
    """Diagnostic frame every position frame (SDO), so that each output pairs with inputs."""
    with sdo_network(bus) as network:
        for client in clients(network, cfg, timeout_s=3.0).values():
            client.node.sdo[0x1801][5].raw = client.node.sdo[0x1800][5].raw


def analyse(cfg, frames: list[can.Message], period_s: float, since: float,
            until: float, pool: dict[str, list[float]] | None = None) -> dict[str, float]:
    """Latency (publish - newest included input) and jitter from the recorded bus: every
    frame from the service's start, figures from frames sent between ``since`` and
    ``until`` (wall time: the measurement window, inputs flowing).

    The latency holds the age of the newest input at the moment of publishing, which is up
    to one input period whatever the service does (the controllers are not synchronised to
    the sensor's tick); so two more figures: ``input_age_at_publish`` (publish - the newest
    Sevcon frame *sent* before it: the part no service can remove) and ``inputs_behind``
    (Sevcon frames sent before the publish but not in the published value: 0 when the
    service included everything it could), and ``latency_beyond_input_age`` (latency -
    input age, per position: how much older the published value's newest input is than the
    newest input on the bus; what the service adds to the input's own age)."""
    codec = FrameCodec(cfg)
    out: dict[str, list[float]] = {"latency": [], "jitter": [], "age": [], "behind": []}
    for a in cfg.can.units:
        sev_id = codec.ids[message_name("sevcon", a)]
        pos_id = codec.ids[message_name("position", a)]
        diag_id = codec.ids[message_name("diag", a)]
        sevcon_t: list[float] = []
        pos_t: list[float] = []
        pairs: list[tuple[float, int]] = []          # (publish time, inputs included)
        pending = None
        received, last_raw = 0, 0
        for m in frames:
            if m.arbitration_id == sev_id:
                sevcon_t.append(m.timestamp)
            elif m.arbitration_id == pos_id:
                if since <= m.timestamp <= until:
                    pos_t.append(m.timestamp)
                pending = m.timestamp
            elif m.arbitration_id == diag_id and pending is not None:
                raw = codec.decode(m)[1]["InputFrames"]
                received += (int(raw) - last_raw) % 0x10000
                last_raw = int(raw)
                if 0 < received <= len(sevcon_t) and since <= pending <= until:
                    out["latency"].append(pending - sevcon_t[received - 1])
                    pairs.append((pending, received))
                pending = None
        periods = np.diff(pos_t)
        out["jitter"] += list(np.abs(periods - period_s))
        sent = np.sort(np.array(sevcon_t))
        for publish_t, included in pairs:
            before = int(np.searchsorted(sent, publish_t, side="right"))
            out["age"].append(publish_t - sent[before - 1])
            out["behind"].append(max(before - included, 0))
    lat, jit = np.array(out["latency"]), np.array(out["jitter"])
    age, behind = np.array(out["age"]), np.array(out["behind"])
    if pool is not None:                 # pooled over several runs by the caller
        for key in ("latency", "age", "behind"):
            pool.setdefault(key, []).extend(out[key])
    return {"latency_p50_ms": round(float(np.percentile(lat, 50)) * 1e3, 3),
            "latency_p99_ms": round(float(np.percentile(lat, 99)) * 1e3, 3),
            "latency_max_ms": round(float(lat.max()) * 1e3, 3),
            "input_age_at_publish_p50_ms": round(float(np.percentile(age, 50)) * 1e3, 3),
            "input_age_at_publish_p99_ms": round(float(np.percentile(age, 99)) * 1e3, 3),
            "latency_beyond_input_age_p99_ms": round(
                float(np.percentile(lat - age, 99)) * 1e3, 3),
            "inputs_behind_p50": float(np.percentile(behind, 50)),
            "inputs_behind_p99": float(np.percentile(behind, 99)),
            "inputs_behind_share_pct": round(100 * float(np.mean(behind > 0)), 1),
            "jitter_p99_ms": round(float(np.percentile(jit, 99)) * 1e3, 3),
            "jitter_max_ms": round(float(jit.max()) * 1e3, 3),
            "published_positions": int(len(jit) + len(cfg.can.units))}


def phase_sweep(cfg, tables, seconds: float, input_hz: float, phases: int) -> dict[str, object]:
    """The socket mode's nominal run once per phase of the controllers' slots after the
    service's tick (0, 1/N, ... of an input period): the newest input's age at publish is
    set by that phase, constant through a run (both sides keep absolute deadlines on one
    clock), so one run measures one phase; the pooled figures are over all of them."""
    global PHASE_S
    raw: dict[str, list[float]] = {}
    rows, cpu = [], []
    lost = 0
    for k in range(phases):
        PHASE_S = k / phases / input_hz
        r = asyncio.run(run_socket(cfg, tables, seconds, 0.0, input_hz, raw))
        rows.append({"phase_ms": round(PHASE_S * 1e3, 3), "latency_p99_ms": r["latency_p99_ms"],
                     "input_age_at_publish_p99_ms": r["input_age_at_publish_p99_ms"],
                     "inputs_behind_share_pct": r["inputs_behind_share_pct"],
                     "jitter_p99_ms": r["jitter_p99_ms"],
                     "cpu_share_pct": r["cpu_share_pct"], "load_avg_1min": round(
                         os.getloadavg()[0], 2)})
        print(" ".join(f"{k_}={v}" for k_, v in rows[-1].items()), flush=True)
        cpu.append(r["cpu_share_pct"])
        lost += r["sevcon_frames_lost"]
    PHASE_S = None
    lat, age = np.array(raw["latency"]), np.array(raw["age"])
    behind = np.array(raw["behind"])
    return {"phases": rows,
            "pooled_latency_p50_ms": round(float(np.percentile(lat, 50)) * 1e3, 3),
            "pooled_latency_p99_ms": round(float(np.percentile(lat, 99)) * 1e3, 3),
            "pooled_latency_max_ms": round(float(lat.max()) * 1e3, 3),
            "pooled_input_age_at_publish_p99_ms": round(float(np.percentile(age, 99)) * 1e3,
                                                        3),
            "pooled_latency_beyond_input_age_p99_ms": round(
                float(np.percentile(lat - age, 99)) * 1e3, 3),
            "pooled_inputs_behind_share_pct": round(100 * float(np.mean(behind > 0)), 1),
            "phases_meeting_p99_2ms": sum(r["latency_p99_ms"] <= 2.0 for r in rows),
            "jitter_p99_ms_worst_phase": max(r["jitter_p99_ms"] for r in rows),
            "cpu_share_pct_mean": round(float(np.mean(cpu)), 1),
            "sevcon_frames_lost": int(lost)}


def _realtime(pid: int = 0) -> None:
    """SCHED_FIFO 50 for the service (what CPUSchedulingPolicy=fifo would give it)."""
    os.sched_setscheduler(pid, os.SCHED_FIFO, os.sched_param(50))


REALTIME = False
PHASE_S: float | None = None             # socket mode: the feeder's slots this long after a tick
COALESCE_S: float | None = None          # socket mode's fd reader pause (None: the service's)
# TPDO2 (diagnostics: the input counter that pairs an output with its inputs) event timer in
# socket and profile modes; None: with every TPDO1, so that every position is paired
DIAG_MS: int | None = None


def _thread_cpu_s(thread: threading.Thread | None) -> float:
    if thread is None or thread.ident is None or not thread.is_alive():
        return 0.0
    return time.clock_gettime(time.pthread_getcpuclockid(thread.ident))


async def run_inproc(cfg, tables, seconds: float, other_hz: float) -> dict[str, float]:
    channel = f"bench-{uuid.uuid4().hex[:8]}"
    service = Service(cfg, tables, {"interface": "virtual", "channel": channel},
                      ServiceOptions(record_latency=True))
    recorder = can.Bus(interface="virtual", channel=channel)
    feeder_bus = can.Bus(interface="virtual", channel=channel)
    sdo_bus = can.Bus(interface="virtual", channel=channel)
    await service.start()
    await asyncio.get_running_loop().run_in_executor(None, _commission, sdo_bus, cfg)
    sdo_bus.shutdown()
    feeder = Feeder({DEFAULT_BUS: feeder_bus}, cfg, other_hz)
    feeder.start()
    await asyncio.sleep(1.0)                       # warm up
    since = time.time()
    service.latency_s.clear()
    received0 = {a: service.inputs.units[a].received for a in cfg.can.units}
    sent0 = dict(feeder.sent)
    reader = service.link._thread
    wall0, loop_cpu0, reader_cpu0 = time.monotonic(), time.thread_time(), _thread_cpu_s(reader)
    missed0 = service.ticker.missed_total
    await asyncio.sleep(seconds)
    wall1, loop_cpu1, reader_cpu1 = time.monotonic(), time.thread_time(), _thread_cpu_s(reader)
    until = time.time()
    feeder.stop_event.set()
    feeder.join(5)
    await asyncio.sleep(0.2)
    received = {a: service.inputs.units[a].received - received0[a] for a in cfg.can.units}
    sent = {a: feeder.sent[a] - sent0[a] for a in cfg.can.units}
    processing = np.array(service.latency_s)
    missed = service.ticker.missed_total - missed0
    kind = service.ticker.kind
    await service.shutdown()
    frames = []
    while (m := recorder.recv(0.0)) is not None:
        frames.append(m)
    recorder.shutdown()
    feeder_bus.shutdown()
    span = feeder.ended_s - feeder.started_s
    figures = analyse(cfg, frames, service.ticker.period_s, since, until)
    figures.update({
        "bus_frames_per_s": round(feeder.total / span),
        "cpu_share_pct": round(100 * ((loop_cpu1 - loop_cpu0) + (reader_cpu1 - reader_cpu0))
                               / (wall1 - wall0), 1),
        "processing_p50_ms": round(float(np.percentile(processing, 50)) * 1e3, 3),
        "processing_p99_ms": round(float(np.percentile(processing, 99)) * 1e3, 3),
        "processing_max_ms": round(float(processing.max()) * 1e3, 3),
        "sevcon_frames_lost": int(sum(sent.values()) - sum(received.values())),
        "sevcon_frames_rejected": int(sum(service.inputs.units[a].rejected
                                          for a in cfg.can.units)),
        "feeder_skipped_slots": feeder.skipped_slots,
        "missed_ticks": int(missed),
        "ticks": kind,
    })
    return figures


# --- the daemon as a separate process behind python-can-remote -----------------------------

def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _proc_cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class _RemoteRecorder(threading.Thread):
    def __init__(self, url: str) -> None:
        super().__init__(daemon=True)
        self.bus = can.Bus(interface="remote", channel=url)
        self.frames: list[can.Message] = []
        self.stop_event = threading.Event()

    def run(self) -> None:
        while not self.stop_event.is_set():
            m = self.bus.recv(0.1)
            if m is not None:
                self.frames.append(m)


def run_remote(cfg, seconds: float, other_hz: float) -> dict[str, float]:
    port = _free_port()
    url = f"ws://127.0.0.1:{port}/"
    server = subprocess.Popen([sys.executable, "-m", "can_remote", "-i", "virtual", "-c",
                               f"bench-{uuid.uuid4().hex[:8]}", "-H", "127.0.0.1", "-p",
                               str(port)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    daemon = None
    try:
        end = time.monotonic() + 15
        while time.monotonic() < end:
            try:
                socket.create_connection(("127.0.0.1", port), 0.2).close()
                break
            except OSError:
                time.sleep(0.05)
        daemon = subprocess.Popen([sys.executable, "-m", "ddh_vsensor.cli.main", "run",
                                   "--interface", "remote", "--channel", url, "--no-state",
                                   "--log-level", "error"])
        time.sleep(4.0)                          # start-up (imports, tables)
        if REALTIME:
            _realtime(daemon.pid)
        sdo_bus = can.Bus(interface="remote", channel=url)
        _commission(sdo_bus, cfg)
        sdo_bus.shutdown()
        recorder = _RemoteRecorder(url)
        recorder.start()
        feeder = Feeder({DEFAULT_BUS: can.Bus(interface="remote", channel=url)}, cfg, other_hz)
        feeder.start()
        time.sleep(1.0)
        since = time.time()
        wall0, cpu0 = time.monotonic(), _proc_cpu_s(daemon.pid)
        time.sleep(seconds)
        wall1, cpu1 = time.monotonic(), _proc_cpu_s(daemon.pid)
        until = time.time()
        feeder.stop_event.set()
        feeder.join(5)
        time.sleep(0.5)
        recorder.stop_event.set()
        recorder.join(5)
        frames = recorder.frames
        feeder.bus.shutdown()
        recorder.bus.shutdown()
        figures = analyse(cfg, frames, cfg.can.event_timer_ms / 1000.0, since, until)
        codec = FrameCodec(cfg)
        sev_ids = {codec.ids[message_name("sevcon", a)] for a in cfg.can.units}
        figures["bus_frames_per_s"] = round(feeder.total / (feeder.ended_s - feeder.started_s))
        figures["cpu_share_pct"] = round(100 * (cpu1 - cpu0) / (wall1 - wall0), 1)
        figures["sevcon_frames_recorded"] = sum(1 for m in frames if m.arbitration_id in sev_ids)
        figures["sevcon_frames_sent"] = sum(feeder.sent.values())
        figures["feeder_skipped_slots"] = feeder.skipped_slots
        return figures
    finally:
        if daemon is not None and daemon.poll() is None:
            daemon.send_signal(signal.SIGTERM)
            try:
                daemon.wait(10)
            except subprocess.TimeoutExpired:
                daemon.kill()
        server.terminate()
        try:
            server.wait(5)
        except subprocess.TimeoutExpired:
            server.kill()


# --- the production read path on a kernel socket, the machine in another process -----------

class SocketPairBus(can.BusABC):
    """SocketCAN's frame layout (can_id, dlc, pad, 8 data bytes) over an AF_UNIX seqpacket
    socket (one record per frame, queued up to the socket buffer like a SocketCAN socket's
    receive queue): recv(0) never blocks, fileno() is the socket, each frame is stamped by the
    kernel on arrival (SO_TIMESTAMPNS, as python-can's socketcan reads them)."""

    FRAME = struct.Struct("=IB3x8s")

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.sock.setblocking(False)
        self.sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        self.channel_info = "socketpair"
        self.send_errors = 0
        super().__init__(channel="socketpair")

    def _recv_internal(self, timeout):
        if timeout != 0.0:
            ready = select.select([self.sock], [], [], timeout)[0]
            if not ready:
                return None, False
        try:
            data, ancillary, _, _ = self.sock.recvmsg(16, 64)
        except BlockingIOError:
            return None, False
        stamp = kernel_stamp(ancillary, time.time())
        can_id, dlc, payload = self.FRAME.unpack(data)
        return can.Message(timestamp=stamp, arbitration_id=can_id, data=payload[:dlc],
                           is_extended_id=False), True

    def send(self, msg, timeout=None):
        try:
            self.sock.send(self.FRAME.pack(msg.arbitration_id, msg.dlc,
                                           bytes(msg.data).ljust(8, b"\0")))
        except BlockingIOError:          # the receiver's queue is full: the frame is lost
            self.send_errors += 1
            raise can.CanOperationError("receive queue full") from None

    def fileno(self):
        return self.sock.fileno()


def _machine_process(cfg, socks: dict[str, socket.socket], other_hz: float, input_hz: float,
                     go, stop, conn, realtime: bool, start_at) -> None:
    """Child process (forked: the parent's config): the machine's traffic out on each bus,
    the sensors' frames in, all time-stamped (SCHED_FIFO 40 with --rt, so that its stamps are
    the service's timing, not this process's waiting for a CPU)."""
    if realtime:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(40))
    buses = {name: SocketPairBus(sock) for name, sock in socks.items()}
    received: list[tuple[float, int, bytes]] = []
    done = threading.Event()

    # publish times: the kernel's stamp of each output frame's arrival (SO_TIMESTAMPNS), not
    # this thread's clock after its wake, which waits for the feeder thread's GIL and CPU
    stamp_delays: list[float] = []
    for sock in socks.values():
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)

    def receive() -> None:
        while not done.is_set():
            for sock in select.select(list(socks.values()), [], [], 0.1)[0]:
                try:
                    data, ancillary, _, _ = sock.recvmsg(16, 64)
                except BlockingIOError:
                    continue
                woke = time.time()
                stamp = kernel_stamp(ancillary, woke)
                stamp_delays.append(woke - stamp)
                can_id, dlc, payload = SocketPairBus.FRAME.unpack(data)
                received.append((stamp, can_id, payload[:dlc]))

    receiver = threading.Thread(target=receive, daemon=True)
    receiver.start()
    go.wait()
    feeder = Feeder(buses, cfg, other_hz, input_hz)
    feeder.start_at_s = start_at.value or None
    feeder.start()
    stop.wait()
    feeder.stop_event.set()
    feeder.join(5)
    time.sleep(0.2)
    done.set()
    receiver.join(5)
    conn.send({"sevcon_times": feeder.sevcon_times, "received": received,
               "sent": feeder.sent, "total": feeder.total, "errors": feeder.errors,
               "span": feeder.ended_s - feeder.started_s, "skipped": feeder.skipped_slots,
               "stamp_delays": stamp_delays, "send_s": feeder.send_s})
    conn.close()


async def run_socket(cfg, tables, seconds: float, other_hz: float,
                     input_hz: float = INPUT_HZ,
                     raw: dict[str, list[float]] | None = None,
                     summaries: bool = False) -> dict[str, float]:
    ctx = multiprocessing.get_context("fork")      # before the service starts any thread
    bus_names = [DEFAULT_BUS, *(b for b in cfg.buses if cfg.units_on_bus(b))]
    pairs = {name: socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
             for name in bus_names}
    for pair in pairs.values():     # SocketCAN's default receive buffer (net.core.rmem_default)
        for s_ in pair:
            s_.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 212992)
    go, stop = ctx.Event(), ctx.Event()
    start_at = ctx.Value("d", 0.0)
    parent_conn, child_conn = ctx.Pipe()
    child = ctx.Process(target=_machine_process,
                        args=(cfg, {n: p[1] for n, p in pairs.items()}, other_hz, input_hz,
                              go, stop, child_conn, REALTIME, start_at))
    child.start()
    for _, theirs in pairs.values():
        theirs.close()
    if REALTIME:
        _realtime()
    buses = {name: SocketPairBus(mine) for name, (mine, _) in pairs.items()}
    extra = {"buses": {name: {"interface": "socketpair", "channel": name}
                       for name in bus_names[1:]}} if len(bus_names) > 1 else {}
    state = tempfile.mkdtemp(prefix="ddh-bench-state-") if summaries else None
    service = Service(cfg, tables, {"interface": "socketpair", "channel": DEFAULT_BUS},
                      ServiceOptions(record_latency=True, fd_reader=True,
                                     coalesce_s=COALESCE_S,
                                     state_dir=None if state is None else Path(state),
                                     machine="bench" if summaries else None),
                      opener=lambda settings, filters: buses[settings["channel"]], **extra)
    sends: list[float] = []
    first = next(iter(cfg.can.units))
    service.observers.append(lambda a, p, t: sends.append(time.monotonic()) if a == first
                             else None)
    await service.start()
    for unit in service.units.values():           # diag timer (SDO, in process)
        unit.node.node.sdo[0x1801][5].raw = DIAG_MS or unit.node.node.sdo[0x1800][5].raw
    links = list(getattr(service, "links", {DEFAULT_BUS: service.link}).values())
    if PHASE_S is not None:      # the controllers' slots at a set phase after the service's ticks
        period = service.ticker.period_s
        anchor = service.ticker.anchor_s
        start_at.value = anchor + (math.floor((time.monotonic() - anchor) / period) + 3) \
            * period + PHASE_S
    go.set()
    await asyncio.sleep(1.0)
    since = time.time()
    service.latency_s.clear()
    received0 = {a: service.inputs.units[a].received for a in cfg.can.units}
    t0, times0 = time.monotonic(), os.times()
    wakes0 = sum(link.wakes for link in links)
    n_sends0 = len(sends)
    missed0 = service.ticker.missed_total
    await asyncio.sleep(seconds)
    t1, times1 = time.monotonic(), os.times()
    wakes = sum(link.wakes for link in links) - wakes0
    until = time.time()
    send_jitter = np.abs(np.diff(sends[n_sends0:]) - service.ticker.period_s)
    received1 = {a: service.inputs.units[a].received for a in cfg.can.units}
    processing = np.array(service.latency_s)
    missed = service.ticker.missed_total - missed0
    stop.set()
    if not await asyncio.get_running_loop().run_in_executor(None, parent_conn.poll, 30.0):
        child.kill()
        raise RuntimeError("the machine process did not report (see its traceback above)")
    result = parent_conn.recv()
    child.join(10)
    await service.shutdown()
    if state is not None:
        shutil.rmtree(state, ignore_errors=True)
    codec = FrameCodec(cfg)
    frames = [can.Message(timestamp=t, arbitration_id=codec.ids[message_name("sevcon", a)],
                          data=b"", is_extended_id=False)
              for a, times in result["sevcon_times"].items() for t in times]
    frames += [can.Message(timestamp=t, arbitration_id=i, data=d, is_extended_id=False)
               for t, i, d in result["received"]]
    figures = analyse(cfg, frames, service.ticker.period_s, since, until, raw)
    in_window = int(sum(received1[a] - received0[a] for a in cfg.can.units))
    wall = t1 - t0
    figures.update({
        "bus_frames_per_s": round(result["total"] / result["span"]),
        "cpu_share_pct": round(100 * (sum(times1[:2]) - sum(times0[:2])) / wall, 1),
        "cpu_user_pct": round(100 * (times1[0] - times0[0]) / wall, 1),
        "cpu_system_pct": round(100 * (times1[1] - times0[1]) / wall, 1),
        "cpu_us_per_sevcon_frame": round(1e6 * (sum(times1[:2]) - sum(times0[:2]))
                                         / max(in_window, 1), 1),
        "reader_wakes_per_s": round(wakes / wall),
        "service_side_jitter_p99_ms": round(float(np.percentile(send_jitter, 99)) * 1e3, 3),
        "service_side_jitter_max_ms": round(float(send_jitter.max()) * 1e3, 3),
        "processing_p50_ms": round(float(np.percentile(processing, 50)) * 1e3, 3),
        "processing_p99_ms": round(float(np.percentile(processing, 99)) * 1e3, 3),
        "processing_max_ms": round(float(processing.max()) * 1e3, 3),
        "sevcon_frames_lost": int(sum(result["sent"].values())
                                  - sum(service.inputs.units[a].received for a in cfg.can.units)),
        "send_errors_queue_full": result["errors"],
        "sevcon_frames_in_window": in_window,
        "missed_ticks": int(missed),
        "feeder_skipped_slots": result["skipped"],
        # how late a user-space clock read after the receiver's wake would have stamped the
        # outputs, and how long a Sevcon frame's send took (the feeder's stamp is after it)
        "publish_stamp_wake_delay_p50_ms": round(
            float(np.percentile(result["stamp_delays"], 50)) * 1e3, 3),
        "publish_stamp_wake_delay_p99_ms": round(
            float(np.percentile(result["stamp_delays"], 99)) * 1e3, 3),
        "sevcon_send_call_p99_ms": round(float(np.percentile(result["send_s"], 99)) * 1e3, 3),
        "ticks": service.ticker.kind,
    })
    return figures


# --- where the time goes: the service's path without the event loop -------------------------

class _ClockBus(SocketPairBus):
    """A SocketPairBus whose frames carry the profile's virtual time of their sending (kept
    in ``stamps`` in sending order, as a SocketCAN socket stamps frames on arrival)."""

    def __init__(self, sock: socket.socket, stamps: collections.deque) -> None:
        super().__init__(sock)
        self.stamps = stamps

    def _recv_internal(self, timeout):
        try:
            data = self.sock.recv(16)
        except BlockingIOError:
            return None, False
        can_id, dlc, payload = self.FRAME.unpack(data)
        return can.Message(timestamp=self.stamps.popleft(), arbitration_id=can_id,
                           data=payload[:dlc], is_extended_id=False), True


# (label, file the function is in, function): cumulative time of each, in the profile
STAGES = (
    ("receive_and_handle", "service/bus.py", "_drain"),
    ("python_can_recv", "service/bus.py", "receive"),      # the interface's _recv_internal
    ("route", "", "_route"),
    ("sevcon_frame", "", "_on_sevcon"),
    ("input_checks_and_decode", "service/inputs.py", "sevcon"),
    ("cantools_decode", "canbus/dbc.py", "decode"),
    ("estimator_step", "estimator/estimator.py", "step"),
    ("table_lookup", "tables/lookup.py", "velocity"),
    ("publish_tick", "", "_on_tick"),
    ("published_values", "", "published"),
    ("pdo_encode_and_transmit", "", "publish"),
    ("pdo_encode_canopen", "", "_encode"),
    ("emcy_check", "", "report_faults"),
    ("bus_send", "service/bus.py", "send"),
    ("housekeeping", "", "_on_housekeeping"),
    ("logging", "logging/__init__.py", "log"),
)


def profile(cfg, tables, ms: int, input_hz: float) -> dict[str, object]:
    """``ms`` milliseconds of the machine's traffic (as the socket mode's feeder sends it)
    through the service's receive, routing, estimator and publish path, driven here: a
    reader wake every reading period (the fd reader's coalescing), a tick every event timer,
    the housekeeping tick every 10 ms. CPU time per Sevcon frame without the profiler, then each
    stage's share under cProfile (its cumulative time; stages nest)."""
    bus_names = [DEFAULT_BUS, *(b for b in cfg.buses if cfg.units_on_bus(b))]
    pairs = {name: socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
             for name in bus_names}
    for _, theirs in pairs.values():
        theirs.setblocking(False)
    stamps = {name: collections.deque() for name in bus_names}
    buses = {name: _ClockBus(mine, stamps[name]) for name, (mine, _) in pairs.items()}
    extra = {"buses": {name: {"interface": "socketpair", "channel": name}
                       for name in bus_names[1:]}} if len(bus_names) > 1 else {}
    service = Service(cfg, tables, {"interface": "socketpair", "channel": DEFAULT_BUS},
                      ServiceOptions(fd_reader=True, coalesce_s=COALESCE_S),
                      opener=lambda settings, filters: buses[settings["channel"]], **extra)
    loop = asyncio.new_event_loop()
    loop.run_until_complete(service.start())      # opens the links; the loop never runs again
    for unit in service.units.values():           # diag timer, as in the socket mode
        unit.node.node.sdo[0x1801][5].raw = DIAG_MS or unit.node.node.sdo[0x1800][5].raw
    links = list(getattr(service, "links", {DEFAULT_BUS: service.link}).values())

    class Recorder(can.BusABC):
        """Collects the feeder's frames as SocketCAN records per bus."""

        def __init__(self, name: str) -> None:
            self.name, self.records = name, []
            super().__init__(channel=name)

        def send(self, msg, timeout=None):
            self.records.append((self.name, SocketPairBus.FRAME.pack(
                msg.arbitration_id, msg.dlc, bytes(msg.data).ljust(8, b"\0"))))

        def _recv_internal(self, timeout):
            return None, False

    slots = round(ms * input_hz / 1000.0)
    recorders = {name: Recorder(name) for name in bus_names}
    feeder = Feeder(recorders, cfg, 0.0, input_hz)
    traffic: list[list[tuple[str, bytes]]] = []
    feeder.stop_event.set()                       # encode slot by slot, no sending thread
    for k in range(slots):
        for r in recorders.values():
            r.records.clear()
        _feed_slot(feeder, k)
        traffic.append([rec for r in recorders.values() for rec in r.records])
    slot_s = 1.0 / input_hz
    wake_every = max(1, round(links[0].coalesce_s / slot_s))
    tick_every = max(1, round(service.ticker.period_s / slot_s))
    house_every = max(1, round(cfg.faults.housekeeping_tick_ms / 1000.0 / slot_s))
    socks = {name: theirs for name, (_, theirs) in pairs.items()}

    def run(first: int, paced: bool = False) -> None:
        # frame times ahead of the wall clock: a slow run is never mistaken for late frames
        t0 = time.time() + 10.0 * slots * slot_s + 1.0
        start_s = time.monotonic()
        for k, records in enumerate(traffic):
            now = t0 + (first + k) * slot_s
            for name, rec in records:
                stamps[name].append(now)
                socks[name].send(rec)
            if k % wake_every == wake_every - 1:
                if paced:        # asleep until the wake is due, as the daemon is between wakes
                    time.sleep(max(start_s + (k + 1) * slot_s - time.monotonic(), 0.0))
                for link in links:
                    link.drain()
            if k % tick_every == tick_every - 1:
                service._on_tick(time.monotonic(), 0)               # noqa: SLF001
                for sock in socks.values():                          # the sensors' frames
                    while True:
                        try:
                            sock.recv(16)
                        except BlockingIOError:
                            break
            if k % house_every == house_every - 1:
                service._on_housekeeping()                           # noqa: SLF001

    units = cfg.unit_names
    run(0)                                        # warm up: first frames, oil, references
    n0 = sum(service.inputs.units[a].received for a in units)
    cpu0 = time.thread_time()
    run(slots)
    cpu = time.thread_time() - cpu0
    frames = sum(service.inputs.units[a].received for a in units) - n0
    # the same work at the daemon's pace: asleep between the wakes (caches go cold)
    n0 = sum(service.inputs.units[a].received for a in units)
    cpu0, ru0 = time.thread_time(), resource.getrusage(resource.RUSAGE_THREAD)
    run(2 * slots, paced=True)
    cpu_paced = time.thread_time() - cpu0
    ru1 = resource.getrusage(resource.RUSAGE_THREAD)
    paced_system = (ru1.ru_stime - ru0.ru_stime) / max(
        ru1.ru_stime - ru0.ru_stime + ru1.ru_utime - ru0.ru_utime, 1e-9)
    frames_paced = sum(service.inputs.units[a].received for a in units) - n0
    prof = cProfile.Profile()
    prof.enable()
    run(3 * slots)
    prof.disable()
    loop.run_until_complete(service.shutdown())
    loop.close()
    stats = pstats.Stats(prof).stats              # type: ignore[attr-defined]
    everything = sum(tt for _, _, tt, _, _ in stats.values())
    # The machine's side (this loop, its sends and reads) is not the service's time.
    run_key = next(k for k in stats if k[2] == "run" and k[0] == __file__)
    harness = stats[run_key][2] + sum(
        v[4][run_key][3] for k, v in stats.items()
        if run_key in v[4] and k[0] == "~" and ("send" in k[2] or "recv" in k[2]
                                                or "append" in k[2]))
    total = everything - harness
    cpu *= total / everything
    cpu_paced *= total / everything
    us_frame = 1e6 * cpu / max(frames, 1)
    out: dict[str, object] = {
        "profile_units": len(units), "profile_input_hz_per_unit": input_hz,
        "profile_sevcon_frames": frames,
        "profile_cpu_us_per_sevcon_frame": round(us_frame, 2),
        "profile_paced_cpu_us_per_sevcon_frame": round(1e6 * cpu_paced / max(frames_paced, 1),
                                                       2),
        "profile_paced_system_share_pct": round(100 * paced_system, 1),
        "profile_cpu_share_at_this_load_pct": round(
            100 * cpu / (slots * slot_s), 1),
        "profile_published_frames": service.frames_published,
        "profile_harness_share_removed_pct": round(100 * harness / everything, 1),
    }
    for label, path, func in STAGES:
        ct = sum(v[3] for (file, _, name), v in stats.items()
                 if name == func and file.replace("\\", "/").endswith(".py")
                 and (not path or file.replace("\\", "/").endswith(path))
                 and ("ddh_vsensor" in file or path.startswith(("can/", "logging/"))))
        out[f"stage_{label}_pct"] = round(100 * ct / total, 1)
        out[f"stage_{label}_us_per_sevcon_frame"] = round(us_frame * ct / total, 2)
    top = sorted(stats.items(), key=lambda kv: -kv[1][2])[:15]
    out["top_self_time"] = [f"{Path(f).name}:{n} {100 * v[2] / total:.1f}% ({v[1]} calls)"
                            for (f, _, n), v in top]
    return out


def _feed_slot(feeder: Feeder, k: int) -> None:
    """One slot of the feeder's traffic, sent to its buses now."""
    c, units = feeder.codec, feeder.units
    per_10ms = max(1, round(0.01 * feeder.input_hz))
    t = k / feeder.input_hz
    if k == 0:
        feeder._send(c.encode_oil_temp(30.0))                      # noqa: SLF001
        feeder._send(c.encode_inputs({a: {} for a in units}))       # noqa: SLF001
    for i, a in enumerate(units):
        speed = 3000.0 * np.sin(2 * np.pi * t / (6.0 + i))
        feeder._send(c.encode_sevcon(a, 10.0 + 5 * np.sin(t), round(speed)),  # noqa: SLF001
                     feeder.bus_of[a])
    if k % per_10ms == 0:
        refs = {a: {"mid": int(np.sin(2 * np.pi * t / (6.0 + i)) > 0.9)}
                for i, a in enumerate(units)}
        feeder._send(c.encode_inputs(refs))                        # noqa: SLF001
    if k % (10 * per_10ms) == 0:
        feeder._send(c.encode_oil_temp(30.0 + t * 0.01))           # noqa: SLF001
        for a in units:
            feeder._send(c.encode(message_name("heartbeat", a), {"NmtState": 5}),  # noqa: SLF001
                         feeder.bus_of[a])


def summary_worker_cost(cfg, minutes: int = 10) -> dict[str, object]:
    """The day summary's worker, measured as it runs: ``minutes`` of a fleet machine's work
    (1-minute sessions of the simulated fleet, 100 Hz as the daemon keeps them) through
    the worker's own code in 10 s blocks, CPU time per minute of a unit's work (lean
    tables); the worker process's start-up (imports) to its first answer, and its peak
    memory after the work; the day file's size."""
    import resource

    from ddh_vsensor.diagnosis.day_summary import DaySummaries
    from ddh_vsensor.estimator.day_samples import SampleFeed, run_samples
    from ddh_vsensor.service.summary import Worker
    from ddh_vsensor.sim.fleet import plan_fleet, session_spec, session_start_s
    from ddh_vsensor.sim.run import simulate_campaign
    plan = plan_fleet(cfg, 1, 2, seed=31, log_s=60.0, work_s=60.0 * minutes)
    m = plan.machines[0]
    sessions = simulate_campaign(cfg, [session_spec(cfg, plan, m, 0, k) for k in range(minutes)])
    blocks = []
    feeds = {a: SampleFeed(list(cfg.unit(a).references_mm)) for a in cfg.can.units}
    for k, per_unit in enumerate(sessions):
        for a, run in per_unit.items():
            run.shift_time(session_start_s(plan, 0, k))
            for t, n, q, c, h, e in run_samples(feeds[a].switches, run):
                feeds[a].add_bits(t, n, q, c, h, e, t)
                if feeds[a].pending_s() >= 10.0:
                    blocks.append((a, feeds[a].take()))
            blocks.append((a, feeds[a].take()))
    work_s = sum(float(r.time_s[-1] - r.time_s[0]) for s in sessions for r in s.values())
    # the loop's part, per integrated Sevcon frame at 1 kHz (one kept in ten)
    feed, refs, n = SampleFeed(["bottom", "mid", "top"]), {"mid": True}, 200_000
    cpu0 = time.process_time()
    for i in range(n):
        feed.add(i * 1e-3, 100.0, 5.0, 30.0, refs, math.nan, 1e9 + i * 1e-3)
    feed_us = 1e6 * (time.process_time() - cpu0) / n
    out = Path(tempfile.mkdtemp(prefix="ddh-bench-summary-"))
    days = DaySummaries(cfg, "bench", out, lean=True, resume=False)
    cpu0 = time.process_time()
    for a, block in blocks:
        days.feed(a, block)
    days.close()
    cpu = time.process_time() - cpu0
    size = days.written[0].stat().st_size
    started = time.perf_counter()
    worker = Worker(("start", cfg, "bench", str(out / "w"), 300.0, str(out / "health.json")))
    worker.send(("feed", blocks[0][0], blocks[0][1]))
    while worker.queued:
        worker.collect()
        time.sleep(0.01)
    start_s = time.perf_counter() - started
    for a, block in blocks[1:]:
        worker.send(("feed", a, block))
    worker.close(300.0)
    rss_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    shutil.rmtree(out, ignore_errors=True)
    stretches = sum(u.stretches for d in days.days.values() for u in d.units.values())
    return {"summary_feed_us_per_sevcon_frame": round(feed_us, 2),
            "summary_work_minutes_per_unit": round(work_s / 60.0 / len(cfg.can.units), 1),
            "summary_stretches": stretches,
            "summary_worker_cpu_s_per_unit_minute": round(cpu / (work_s / 60.0), 3),
            "summary_worker_cpu_pct_of_a_core_per_unit": round(100 * cpu / work_s, 2),
            "summary_worker_start_s": round(start_s, 2),
            "summary_worker_peak_rss_mb": round(rss_mb),
            "summary_bytes_per_machine_day": size}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="nominal measurement")
    parser.add_argument("--saturated-seconds", type=float, default=10.0,
                        help="saturated measurement (0: nominal load only)")
    parser.add_argument("--bus-rate", type=float, default=8200.0,
                        help="total frames/s on the saturated bus (default 8200)")
    parser.add_argument("--modes", default="socket,inproc,remote")
    parser.add_argument("--rt", action="store_true",
                        help="run the service SCHED_FIFO 50 (as CPUSchedulingPolicy=fifo "
                             "would): results go to daemon_rt.json")
    parser.add_argument("--units", type=int, default=None,
                        help="a machine of this many copies of the loader's first unit, "
                             "socket mode, nominal load only: results in daemon_units<N>.json")
    parser.add_argument("--input-hz", type=float, default=None,
                        help="Sevcon frames per second per unit (default 1000; 500 for "
                             "--units above 2)")
    parser.add_argument("--buses", type=int, choices=(1, 2), default=None,
                        help="buses the units are split over (default 2 for --units above 2, "
                             "where the service reads several buses)")
    parser.add_argument("--coalesce-ms", type=float, default=None,
                        help="socket mode: the fd reader's reading period while frames come "
                             "(default: the service's, 5 ms); the tick drains the socket "
                             "before publishing whatever this is")
    parser.add_argument("--housekeeping-ms", type=float, default=None,
                        help="the service's housekeeping tick (faults.housekeeping_tick_ms; "
                             "default: the configuration's, 10 ms): each tick is a wake")
    parser.add_argument("--diag-ms", type=int, default=None,
                        help="socket and profile modes: TPDO2 event timer (default: with every "
                             "TPDO1, every position paired with its inputs; 100 is the EDS "
                             "default, what a machine runs: latency from every tenth position)")
    parser.add_argument("--phases", type=int, default=None, metavar="N",
                        help="with --units: N runs, the controllers' slots at N phases spread "
                             "over one input period after the service's tick (unsynchronised "
                             "controllers take any phase): latency per phase and pooled")
    parser.add_argument("--summaries", action="store_true",
                        help="socket mode, nominal load, without and with the day summary "
                             "(the service process's CPU), and the summary worker's own cost: "
                             "results in daemon_summaries.json")
    parser.add_argument("--profile", type=int, metavar="MS", default=None,
                        help="only profile MS milliseconds of traffic through the service's "
                             "path (no event loop): results in daemon_profile.json")
    parser.add_argument("--estimator-mode", choices=("full", "paper", "dynamic", "kalman"),
                        default=None,
                        help="the service's estimator mode (default: the configuration's); "
                             "kalman steps at the Sevcon period (can.sevcon_period_ms set to "
                             "1000 / input Hz): results in daemon_<mode>.json")
    args = parser.parse_args()
    global REALTIME, COALESCE_S, DIAG_MS
    REALTIME = args.rt
    DIAG_MS = args.diag_ms
    if DIAG_MS is not None and not 1 <= DIAG_MS <= 1000:
        parser.error("--diag-ms: 1 to 1000")
    COALESCE_S = None if args.coalesce_ms is None else args.coalesce_ms / 1000.0
    if args.phases is not None and (args.units is None or not 1 <= args.phases <= 50):
        parser.error("--phases: 1 to 50, with --units")
    if (args.estimator_mode is not None and "remote" in args.modes.split(",")
            and args.units is None and not args.summaries and args.profile is None):
        parser.error("--estimator-mode: not with --modes remote (its daemon process runs "
                     "the default configuration)")
    if args.units is not None and not 1 <= args.units <= 16:
        parser.error("--units: a machine has 1 to 16 units")
    large = args.units is not None and args.units > 2
    input_hz = args.input_hz if args.input_hz is not None else (500.0 if large else INPUT_HZ)
    if not 1.0 <= input_hz <= 2000.0:
        parser.error("--input-hz: 1 to 2000")
    buses = args.buses or (2 if large else 1)
    cfg = machine_config(args.units, buses)
    if args.housekeeping_ms is not None:
        cfg = dataclasses.replace(cfg, faults=dataclasses.replace(
            cfg.faults, housekeeping_tick_ms=args.housekeeping_ms))
    mode = "" if args.estimator_mode is None else f"_{args.estimator_mode}"   # results' names
    if args.estimator_mode is not None:
        cfg = dataclasses.replace(cfg, estimator=dataclasses.replace(
            cfg.estimator, mode=args.estimator_mode))
    if cfg.estimator.mode == "kalman":      # the filter steps at the frames' period
        cfg = dataclasses.replace(cfg, can=dataclasses.replace(
            cfg.can, sevcon_period_ms=1000.0 / input_hz))
    tables = machine_tables(cfg)
    figures: dict[str, object] = {
        "cpus": os.cpu_count(), "load_avg_1min_at_start": round(os.getloadavg()[0], 2),
        "estimator_mode": cfg.estimator.mode,
    }
    if cfg.estimator.mode == "kalman":
        figures["kalman_step_ms"] = cfg.can.sevcon_period_ms
    if args.profile is not None:
        figures.update(profile(cfg, tables, args.profile, input_hz))
        figures["load_avg_1min_at_end"] = round(os.getloadavg()[0], 2)
        figures["diag_timer_ms"] = args.diag_ms or cfg.can.event_timer_ms
        publish("daemon_profile" + ("" if args.diag_ms is None else f"_diag{args.diag_ms}ms")
                + mode, figures)
        return
    if args.summaries:
        for label, on in (("off", False), ("on", True)):
            result = asyncio.run(run_socket(cfg, tables, args.seconds, 0.0, input_hz,
                                            summaries=on))
            figures.update({f"socket_nominal_summaries_{label}_{k}": result[k] for k in (
                "cpu_share_pct", "cpu_us_per_sevcon_frame", "latency_p99_ms",
                "jitter_p99_ms", "sevcon_frames_lost")})
        figures["service_cpu_added_by_summaries_pct"] = round(
            figures["socket_nominal_summaries_on_cpu_share_pct"]
            - figures["socket_nominal_summaries_off_cpu_share_pct"], 1)
        figures.update(summary_worker_cost(cfg))
        figures["load_avg_1min_at_end"] = round(os.getloadavg()[0], 2)
        publish("daemon_summaries" + mode, figures)
        return
    if args.units is not None:
        figures.update({"units": len(cfg.unit_names), "input_hz_per_unit": input_hz,
                        "buses": buses,
                        "goal_latency_p99_ms": 2.0, "goal_lost": 0})
        if args.phases:
            figures.update(phase_sweep(cfg, tables, args.seconds, input_hz, args.phases))
        else:
            result = asyncio.run(run_socket(cfg, tables, args.seconds, 0.0, input_hz))
            figures.update({f"socket_nominal_{k}": v for k, v in result.items()})
        figures["load_avg_1min_at_end"] = round(os.getloadavg()[0], 2)
        figures["scheduling"] = "SCHED_FIFO 50" if args.rt else "SCHED_OTHER (default)"
        if args.coalesce_ms is not None:
            figures["socket_coalesce_ms"] = args.coalesce_ms
        suffix = "" if args.coalesce_ms is None else f"_coalesce{args.coalesce_ms:g}ms"
        if args.diag_ms is not None:
            figures["diag_timer_ms"] = args.diag_ms
            suffix += f"_diag{args.diag_ms}ms"
        if args.phases:
            suffix += f"_phases{args.phases}"
        suffix += mode
        publish(f"daemon_units{len(cfg.unit_names)}" + ("_rt" if args.rt else "") + suffix,
                figures)
        return
    machine = len(cfg.unit_names) * (input_hz + 10) + 100 + 10   # Sevcon+heartbeat, I/O, oil
    other_hz = max(args.bus_rate - machine, 0.0)
    figures.update({"goal_latency_p99_ms": 2.0, "goal_jitter_p99_ms": 1.0,
                    "goal_cpu_share_pct": 10.0, "goal_lost_at_8000_fps": 0})
    modes = args.modes.split(",")
    loads = [("nominal", args.seconds, 0.0)] + (
        [("saturated", args.saturated_seconds, other_hz)] if args.saturated_seconds > 0 else [])
    if "socket" in modes:
        for name, seconds, other in loads:
            result = asyncio.run(run_socket(cfg, tables, seconds, other, input_hz))
            figures.update({f"socket_{name}_{k}": v for k, v in result.items()})
    if "inproc" in modes and not args.rt:       # the feeder shares the process: no RT here
        for name, seconds, other in loads:
            result = asyncio.run(run_inproc(cfg, tables, seconds, other))
            figures.update({f"inproc_{name}_{k}": v for k, v in result.items()})
    if "remote" in modes:
        for name, seconds, other in loads:
            result = run_remote(cfg, seconds, other)
            figures.update({f"remote_{name}_{k}": v for k, v in result.items()})
    figures["load_avg_1min_at_end"] = round(os.getloadavg()[0], 2)
    figures["scheduling"] = "SCHED_FIFO 50" if args.rt else "SCHED_OTHER (default)"
    if args.coalesce_ms is not None:
        figures["socket_coalesce_ms"] = args.coalesce_ms
    suffix = "" if args.coalesce_ms is None else f"_coalesce{args.coalesce_ms:g}ms"
    if args.housekeeping_ms is not None:
        figures["housekeeping_tick_ms"] = args.housekeeping_ms
        suffix += f"_housekeeping{args.housekeeping_ms:g}ms"
    if args.diag_ms is not None:
        figures["diag_timer_ms"] = args.diag_ms
        suffix += f"_diag{args.diag_ms}ms"
    publish(("daemon_rt" if args.rt else "daemon") + suffix + mode, figures)


if __name__ == "__main__":
    main()
