"""Benchmark: the daemon at nominal load and on a saturated bus.

Nominal: two Sevcon controllers at 1 kHz, oil 10 Hz, I/O module 100 Hz, heartbeats 10 Hz;
the service publishes at 100 Hz (event timer 10 ms; the diagnostic frame's timer is set to
10 ms over SDO so every published position can be paired with its input counter).
Saturated: the same plus other nodes' traffic, >= 8000 frames/s in all.

Figures (all from bus timestamps, as a listener on the bus sees them):
- latency: publish time of a position frame minus the bus time of the newest Sevcon frame
  the published value includes (its diag frame's input counter names it). With 1 kHz input
  this is at most ~1 ms plus the pipeline's own delay;
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
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing
import os
import select
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import can
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import publish  # noqa: E402

from ddh_vsensor.canbus.dbc import FrameCodec, message_name  # noqa: E402
from ddh_vsensor.config import load_config  # noqa: E402
from ddh_vsensor.service import Service, ServiceOptions  # noqa: E402
from ddh_vsensor.service.node import EDS_PATH  # noqa: E402
from ddh_vsensor.tables.build import build_unit_tables  # noqa: E402

INPUT_HZ = 1000.0
OTHER_IDS = [0x200 + i for i in range(1, 40)] + [0x300 + i for i in range(1, 40)]


class Feeder(threading.Thread):
    """Sends the machine's traffic (and ``other_hz`` frames/s of other nodes) in 1 ms slots
    from absolute deadlines; counts what it sent."""

    def __init__(self, bus: can.BusABC, cfg, other_hz: float) -> None:
        super().__init__(daemon=True)
        self.bus, self.codec, self.other_hz = bus, FrameCodec(cfg), other_hz
        self.units = list(cfg.can.units)
        self.stop_event = threading.Event()
        self.sent = {a: 0 for a in self.units}
        self.sevcon_times: dict[str, list[float]] = {a: [] for a in self.units}
        self.total = 0
        self.errors = 0
        self.skipped_slots = 0          # slots the feeder was too late for (not sent)
        self.started_s = self.ended_s = 0.0

    def _send(self, msg: can.Message) -> None:
        try:
            self.bus.send(msg)
            self.total += 1
        except can.CanError:
            self.errors += 1

    def run(self) -> None:
        c = self.codec
        self._send(c.encode_oil_temp(30.0))
        self._send(c.encode_inputs({a: {} for a in self.units}))
        slot, k = 1.0 / INPUT_HZ, 0
        other_acc, other_i = 0.0, 0
        start = time.monotonic() + 0.01
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
                self.sevcon_times[a].append(time.time())
                self._send(c.encode_sevcon(a, 10.0 + 5 * np.sin(t), round(speed)))
                self.sent[a] += 1
            if k % 10 == 0:
                refs = {a: {"mid": int(np.sin(2 * np.pi * t / (6.0 + i)) > 0.9)}
                        for i, a in enumerate(self.units)}
                self._send(c.encode_inputs(refs))
            if k % 100 == 0:
                self._send(c.encode_oil_temp(30.0 + t * 0.01))
                for a in self.units:
                    self._send(c.encode(message_name("heartbeat", a), {"NmtState": 5}))
            other_acc += self.other_hz * slot
            while other_acc >= 1.0:
                other_acc -= 1.0
                other_i += 1
                self._send(can.Message(arbitration_id=OTHER_IDS[other_i % len(OTHER_IDS)],
                                       data=other_i.to_bytes(8, "little"),
                                       is_extended_id=False))
            k += 1
        self.ended_s = time.monotonic()


def _commission(bus: can.BusABC, cfg) -> None:
    """Diagnostic frame every position frame (SDO), so that each output pairs with inputs."""
    import canopen
    network = canopen.Network(bus)
    notifier = can.Notifier(bus, network.listeners, 0.1)
    try:
        for unit in cfg.can.units.values():
            node = network.add_node(unit.sensor_node_id, str(EDS_PATH))
            node.sdo.RESPONSE_TIMEOUT = 3.0
            node.sdo[0x1801][5].raw = node.sdo[0x1800][5].raw
    finally:
        notifier.stop(1.0)


def analyse(cfg, frames: list[can.Message], period_s: float, since: float,
            until: float) -> dict[str, float]:
    """Latency (publish - newest included input) and jitter from the recorded bus: every
    frame from the service's start, figures from frames sent between ``since`` and
    ``until`` (wall time: the measurement window, inputs flowing)."""
    codec = FrameCodec(cfg)
    out: dict[str, list[float]] = {"latency": [], "jitter": []}
    for a in cfg.can.units:
        sev_id = codec.ids[message_name("sevcon", a)]
        pos_id = codec.ids[message_name("position", a)]
        diag_id = codec.ids[message_name("diag", a)]
        sevcon_t: list[float] = []
        pos_t: list[float] = []
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
                pending = None
        periods = np.diff(pos_t)
        out["jitter"] += list(np.abs(periods - period_s))
    lat, jit = np.array(out["latency"]), np.array(out["jitter"])
    return {"latency_p50_ms": round(float(np.percentile(lat, 50)) * 1e3, 3),
            "latency_p99_ms": round(float(np.percentile(lat, 99)) * 1e3, 3),
            "latency_max_ms": round(float(lat.max()) * 1e3, 3),
            "jitter_p99_ms": round(float(np.percentile(jit, 99)) * 1e3, 3),
            "jitter_max_ms": round(float(jit.max()) * 1e3, 3),
            "published_positions": int(len(jit) + len(cfg.can.units))}


def _realtime(pid: int = 0) -> None:
    """SCHED_FIFO 50 for the service (what CPUSchedulingPolicy=fifo would give it)."""
    os.sched_setscheduler(pid, os.SCHED_FIFO, os.sched_param(50))


REALTIME = False


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
    feeder = Feeder(feeder_bus, cfg, other_hz)
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
        feeder = Feeder(can.Bus(interface="remote", channel=url), cfg, other_hz)
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
    receive queue): recv(0) never blocks, fileno() is the socket, as on SocketCAN."""

    FRAME = struct.Struct("=IB3x8s")

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.sock.setblocking(False)
        self.channel_info = "socketpair"
        self.send_errors = 0
        super().__init__(channel="socketpair")

    def _recv_internal(self, timeout):
        if timeout != 0.0:
            ready = select.select([self.sock], [], [], timeout)[0]
            if not ready:
                return None, False
        try:
            data = self.sock.recv(16)
        except BlockingIOError:
            return None, False
        can_id, dlc, payload = self.FRAME.unpack(data)
        return can.Message(timestamp=time.time(), arbitration_id=can_id, data=payload[:dlc],
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


def _machine_process(cfg, sock: socket.socket, other_hz: float, go, stop, conn,
                     realtime: bool) -> None:
    """Child process (forked: the parent's config): the machine's traffic out, the sensors'
    frames in, all time-stamped (SCHED_FIFO 40 with --rt, so that its stamps are the
    service's timing, not this process's waiting for a CPU)."""
    if realtime:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(40))
    bus = SocketPairBus(sock)
    received: list[tuple[float, int, bytes]] = []
    done = threading.Event()

    def receive() -> None:
        while not done.is_set():
            if select.select([sock], [], [], 0.1)[0]:
                try:
                    data = sock.recv(16)
                except BlockingIOError:
                    continue
                can_id, dlc, payload = SocketPairBus.FRAME.unpack(data)
                received.append((time.time(), can_id, payload[:dlc]))

    receiver = threading.Thread(target=receive, daemon=True)
    receiver.start()
    go.wait()
    feeder = Feeder(bus, cfg, other_hz)
    feeder.start()
    stop.wait()
    feeder.stop_event.set()
    feeder.join(5)
    time.sleep(0.2)
    done.set()
    receiver.join(5)
    conn.send({"sevcon_times": feeder.sevcon_times, "received": received,
               "sent": feeder.sent, "total": feeder.total, "errors": feeder.errors,
               "span": feeder.ended_s - feeder.started_s, "skipped": feeder.skipped_slots})
    conn.close()


async def run_socket(cfg, tables, seconds: float, other_hz: float) -> dict[str, float]:
    ctx = multiprocessing.get_context("fork")      # before the service starts any thread
    mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    for s_ in (mine, theirs):       # SocketCAN's default receive buffer (net.core.rmem_default)
        s_.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 212992)
    go, stop = ctx.Event(), ctx.Event()
    parent_conn, child_conn = ctx.Pipe()
    child = ctx.Process(target=_machine_process,
                        args=(cfg, theirs, other_hz, go, stop, child_conn, REALTIME))
    child.start()
    theirs.close()
    if REALTIME:
        _realtime()
    bus = SocketPairBus(mine)
    service = Service(cfg, tables, {"interface": "socketpair"},
                      ServiceOptions(record_latency=True, fd_reader=True),
                      opener=lambda settings, filters: bus)
    sends: list[float] = []
    first = next(iter(cfg.can.units))
    service.observers.append(lambda a, p, t: sends.append(time.monotonic()) if a == first
                             else None)
    await service.start()
    for unit in service.units.values():           # diag every tick (SDO, in process)
        unit.node.node.sdo[0x1801][5].raw = unit.node.node.sdo[0x1800][5].raw
    go.set()
    await asyncio.sleep(1.0)
    since = time.time()
    service.latency_s.clear()
    received0 = {a: service.inputs.units[a].received for a in cfg.can.units}
    t0, cpu0 = time.monotonic(), sum(os.times()[:2])
    n_sends0 = len(sends)
    missed0 = service.ticker.missed_total
    await asyncio.sleep(seconds)
    t1, cpu1 = time.monotonic(), sum(os.times()[:2])
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
    codec = FrameCodec(cfg)
    frames = [can.Message(timestamp=t, arbitration_id=codec.ids[message_name("sevcon", a)],
                          data=b"", is_extended_id=False)
              for a, times in result["sevcon_times"].items() for t in times]
    frames += [can.Message(timestamp=t, arbitration_id=i, data=d, is_extended_id=False)
               for t, i, d in result["received"]]
    figures = analyse(cfg, frames, service.ticker.period_s, since, until)
    figures.update({
        "bus_frames_per_s": round(result["total"] / result["span"]),
        "cpu_share_pct": round(100 * (cpu1 - cpu0) / (t1 - t0), 1),
        "service_side_jitter_p99_ms": round(float(np.percentile(send_jitter, 99)) * 1e3, 3),
        "service_side_jitter_max_ms": round(float(send_jitter.max()) * 1e3, 3),
        "processing_p50_ms": round(float(np.percentile(processing, 50)) * 1e3, 3),
        "processing_p99_ms": round(float(np.percentile(processing, 99)) * 1e3, 3),
        "processing_max_ms": round(float(processing.max()) * 1e3, 3),
        "sevcon_frames_lost": int(sum(result["sent"].values())
                                  - sum(service.inputs.units[a].received for a in cfg.can.units)),
        "send_errors_queue_full": result["errors"],
        "sevcon_frames_in_window": int(sum(received1[a] - received0[a] for a in cfg.can.units)),
        "missed_ticks": int(missed),
        "feeder_skipped_slots": result["skipped"],
        "ticks": service.ticker.kind,
    })
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="nominal measurement")
    parser.add_argument("--saturated-seconds", type=float, default=10.0)
    parser.add_argument("--bus-rate", type=float, default=8200.0,
                        help="total frames/s on the saturated bus (default 8200)")
    parser.add_argument("--modes", default="socket,inproc,remote")
    parser.add_argument("--rt", action="store_true",
                        help="run the service SCHED_FIFO 50 (as CPUSchedulingPolicy=fifo "
                             "would): results go to daemon_rt.json")
    args = parser.parse_args()
    global REALTIME
    REALTIME = args.rt
    cfg = load_config(None)
    tables = {a: build_unit_tables(cfg, a) for a in cfg.can.units}
    machine = 2 * INPUT_HZ + 100 + 10 + 2 * 10        # Sevcon, I/O, oil, heartbeats
    other_hz = max(args.bus_rate - machine, 0.0)
    figures: dict[str, object] = {
        "goal_latency_p99_ms": 2.0, "goal_jitter_p99_ms": 1.0, "goal_cpu_share_pct": 15.0,
        "goal_lost_at_8000_fps": 0,
        "cpus": os.cpu_count(), "load_avg_1min_at_start": round(os.getloadavg()[0], 2),
    }
    modes = args.modes.split(",")
    if "socket" in modes:
        for name, seconds, other in (("nominal", args.seconds, 0.0),
                                     ("saturated", args.saturated_seconds, other_hz)):
            result = asyncio.run(run_socket(cfg, tables, seconds, other))
            figures.update({f"socket_{name}_{k}": v for k, v in result.items()})
    if "inproc" in modes and not args.rt:       # the feeder shares the process: no RT here
        for name, seconds, other in (("nominal", args.seconds, 0.0),
                                     ("saturated", args.saturated_seconds, other_hz)):
            result = asyncio.run(run_inproc(cfg, tables, seconds, other))
            figures.update({f"inproc_{name}_{k}": v for k, v in result.items()})
    if "remote" in modes:
        for name, seconds, other in (("nominal", args.seconds, 0.0),
                                     ("saturated", args.saturated_seconds, other_hz)):
            result = run_remote(cfg, seconds, other)
            figures.update({f"remote_{name}_{k}": v for k, v in result.items()})
    figures["load_avg_1min_at_end"] = round(os.getloadavg()[0], 2)
    figures["scheduling"] = "SCHED_FIFO 50" if args.rt else "SCHED_OTHER (default)"
    publish("daemon_rt" if args.rt else "daemon", figures)


if __name__ == "__main__":
    main()
