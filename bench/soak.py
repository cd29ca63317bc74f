"""Benchmark: the service for hours at the reference load, a clean phase then hostile traffic.

The service reads the production path (the event loop's fd reader on a kernel datagram socket,
as bench/daemon.py's ``socket`` mode); the machine's frames carry their due wall time, as a
hub passes a sender's stamps, the flood's are stamped by the kernel on arrival. Two other processes write to that socket: the machine (the simulated paper
cycle at speed 4, looped, each lap's frames at their log times from absolute deadlines) and,
after the clean phase, the flood (``--flood-hz`` hostile frames: random 29-bit IDs, error
frames, unknown 11-bit IDs, Sevcon frames of the wrong length, junk on the controllers'
heartbeat IDs). Every published value is judged as it goes out against the lap's truth over
the interval it may stand for (its newest integrated frame to the output less LATENCY_S): an
unflagged value further from the truth than its uncertainty is a violation. Outputs within
SETTLE_S of a lap's start and before each unit's first reference switch of the lap are not
judged (the lap's first frame follows its last: the machine "jumps" by the cycle's small
closing error, which a reference corrects).

Figures: RSS growth fitted after ``--warmup-s`` (MB/h), the largest gap between the watchdog
pings (``WATCHDOG_USEC`` 2 s: a ping every second while the service integrates), the share
of outputs flagged in each phase and their difference, violations per phase, flagged outputs
by flag. A partial record is written every ``--partial-s`` (10 min), the final one at the end.

``python bench/soak.py --duration-s 7200 [--clean-s 600] [--flood-hz 2000] [--out PATH]``;
writes bench/results/soak.json (or ``--out``). Exit status 1 when a violation was seen.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import math
import multiprocessing
import random
import resource
import select
import socket
import struct
import sys
import tempfile
import threading
import time
import tracemalloc
from pathlib import Path

import can
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _results
from _results import publish
from daemon import SocketPairBus, kernel_stamp

from ddh_vsensor.canbus.dbc import FrameCodec, message_name
from ddh_vsensor.config import Config, load_config
from ddh_vsensor.estimator.flags import EXPLAINING, Flags
from ddh_vsensor.master.replay import machine_frames
from ddh_vsensor.service import Service, ServiceOptions
from ddh_vsensor.service.sdnotify import SystemdNotifier
from ddh_vsensor.sim import RunSpec, simulate_with_truth
from ddh_vsensor.tables.build import build_unit_tables

LATENCY_S = 0.1            # as tests/faults/harness.py: an output may stand for frames this old
TOLERANCE_MM = 0.05        # the diagnostic frame's quantisation, both values
SETTLE_S = 1.0             # after a lap's start (or its first reference): not judged
WATCHDOG_USEC = 2_000_000
LAP_GAP_S = 0.01           # between a lap's last frame and the next lap's first
SOCKET_BUFFER = 212992     # SocketCAN's default receive buffer (net.core.rmem_default)
ROOT = Path(__file__).resolve().parents[1]
JUNK_STATES = [b for b in range(256) if b & 0x7F not in (0, 4, 5, 127)]


def _rss_kb() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


class Lap:
    """The paper cycle: its frames (times from 0) and truth, and when each unit's truth first
    meets one of its reference switches (judging starts SETTLE_S after that)."""

    def __init__(self, cfg: Config) -> None:
        result = simulate_with_truth(cfg, [RunSpec(speed=4)])[0]
        runs = {a: run for a, (run, _) in result.items()}
        frames = list(machine_frames(cfg, runs, heartbeat_period_s=0.1))
        t0 = frames[0].timestamp
        self.frames = [(m.timestamp - t0, m.arbitration_id, bytes(m.data)) for m in frames]
        self.span_s = self.frames[-1][0] + LAP_GAP_S
        self.truth = {a: (truth.time_s - t0, truth.x_m * 1e3) for a, (_, truth) in result.items()}
        self.judge_from_s = {}
        for a, (t, x) in self.truth.items():
            crossings = [t[np.argmax(np.sign(x - ref) != np.sign(x[0] - ref))]
                         for ref in cfg.unit(a).references_mm.values()
                         if np.any(np.sign(x - ref) != np.sign(x[0] - ref))]
            self.judge_from_s[a] = (min(crossings) if crossings else self.span_s) + SETTLE_S
        self.closing_error_mm = {a: float(x[-1] - x[0]) for a, (_, x) in self.truth.items()}


class StampedPairBus(SocketPairBus):
    """SocketPairBus with SocketCAN's ID flags (extended IDs and error frames arrive as such)
    and the sender's own stamp when it gives one (the machine's frames carry their due time,
    as a hub passes a sender's stamps: a machine process that fell behind on a loaded host
    does not shift what its frames stand for); else the kernel's, on arrival."""

    RECORD = struct.Struct("=IB3xd8s")
    EFF, ERR = 0x80000000, 0x20000000

    def _recv_internal(self, timeout):
        if timeout != 0.0 and not select.select([self.sock], [], [], timeout)[0]:
            return None, False
        try:
            data, ancillary, _, _ = self.sock.recvmsg(self.RECORD.size, 64)
        except BlockingIOError:
            return None, False
        raw, dlc, stamp, payload = self.RECORD.unpack(data)
        return can.Message(timestamp=stamp or kernel_stamp(ancillary, time.time()),
                           arbitration_id=raw & 0x1FFFFFFF, data=payload[:dlc],
                           is_extended_id=bool(raw & self.EFF),
                           is_error_frame=bool(raw & self.ERR)), True

    def send(self, msg, timeout=None):
        raw = msg.arbitration_id | (self.EFF if msg.is_extended_id else 0) \
            | (self.ERR if msg.is_error_frame else 0)
        try:
            self.sock.send(self.RECORD.pack(raw, msg.dlc, msg.timestamp,
                                            bytes(msg.data).ljust(8, b"\0")))
        except BlockingIOError:
            self.send_errors += 1
            raise can.CanOperationError("receive queue full") from None


def _machine(sock: socket.socket, lap_frames: list, span_s: float, start_wall, stop) -> None:
    """Child process: the machine's frames, lap after lap, from absolute deadlines; late
    slots are sent late (their kernel stamp is their time); the outputs read and dropped."""
    bus = StampedPairBus(sock)

    def drop_outputs() -> None:
        while not stop.is_set():
            try:
                sock.recv(StampedPairBus.RECORD.size)
            except BlockingIOError:
                time.sleep(0.005)

    threading.Thread(target=drop_outputs, daemon=True).start()
    start = time.time() + 0.05
    start_wall.value = start
    lap = 0
    while not stop.is_set():
        for t, can_id, data in lap_frames:
            due = start + lap * span_s + t
            delay = due - time.time()
            if delay > 0 and stop.wait(delay):
                return
            try:
                bus.send(can.Message(timestamp=due, arbitration_id=can_id, data=data,
                                     is_extended_id=False))
            except can.CanError:
                pass
        lap += 1


def _flood(sock: socket.socket, cfg: Config, rate_hz: float, stop) -> None:
    """Child process: hostile frames at ``rate_hz`` (paced every 5 ms)."""
    bus = StampedPairBus(sock)
    codec = FrameCodec(cfg)
    rng = random.Random(7)
    sevcon = [codec.ids[message_name("sevcon", a)] for a in cfg.can.units]
    heartbeat = [0x700 + n for n in cfg.faults.heartbeat_node_ids.values()]
    known = set(codec.ids.values()) | set(heartbeat) | {0}
    unknown = [i for i in range(0x100, 0x7FF) if i not in known and not 0x580 <= i < 0x680
               and not 0x700 <= i < 0x780 and not 0x80 <= i < 0x100]
    makers = [
        lambda: can.Message(arbitration_id=rng.getrandbits(29), is_extended_id=True,
                            data=b"x"),
        lambda: can.Message(arbitration_id=0x40, is_error_frame=True,
                            is_extended_id=False),
        lambda: can.Message(arbitration_id=rng.choice(unknown), data=b"1",
                            is_extended_id=False),
        lambda: can.Message(arbitration_id=rng.choice(sevcon), data=b"\x01",
                            is_extended_id=False),
        # no heartbeat (two to eight bytes, or a state NMT does not have): a spoofed state
        # is another fault, reported as it should be
        lambda: can.Message(arbitration_id=rng.choice(heartbeat),
                            data=bytes(rng.getrandbits(8) for _ in range(rng.randint(2, 8)))
                            if rng.random() < 0.75 else bytes([rng.choice(JUNK_STATES)]),
                            is_extended_id=False),
    ]
    sent, start = 0, time.monotonic()
    while not stop.is_set():
        due = int((time.monotonic() - start) * rate_hz)
        while sent < due:
            try:
                bus.send(rng.choice(makers)())
            except can.CanError:
                pass
            sent += 1
        time.sleep(0.005)


class Judge:
    """Each published value against the lap's truth, counted per phase (constant memory)."""

    def __init__(self, cfg: Config, lap: Lap) -> None:
        self.lap = lap
        self.start_wall = math.nan
        self.phase = "clean"
        self.counts = {p: {"outputs": 0, "flagged": 0, "judged": 0, "violations": 0,
                           "by_flag": {f.name: 0 for f in Flags if int(f) & EXPLAINING}}
                       for p in ("clean", "hostile")}
        self.examples: list[dict] = []
        self.max_error_mm = 0.0

    def __call__(self, actuator: str, p, last_frame_t: float | None) -> None:
        now = time.time()
        if not now - self.start_wall >= max(self.lap.judge_from_s.values()):
            return                   # commissioning: flagged until the first references
        c = self.counts[self.phase]
        c["outputs"] += 1
        flags = int(p.flags)
        if flags & EXPLAINING:
            c["flagged"] += 1
            for f in Flags:
                if int(f) & EXPLAINING & flags:
                    c["by_flag"][f.name] += 1
            return
        if last_frame_t is None or math.isnan(self.start_wall):
            return
        lap = self.lap
        lo = last_frame_t - self.start_wall
        hi = max(lo, now - self.start_wall - LATENCY_S)
        k = math.floor(lo / lap.span_s)
        lo, hi = lo - k * lap.span_s, hi - k * lap.span_s
        if lo < lap.judge_from_s[actuator] or hi >= lap.span_s - LAP_GAP_S:
            return
        c["judged"] += 1
        t, x = lap.truth[actuator]
        ts = np.linspace(lo, hi, max(2, int((hi - lo) / 0.01) + 2))
        err = float(np.max(np.abs(np.interp(ts, t, x) - p.position_mm)))
        self.max_error_mm = max(self.max_error_mm, err)
        if err > p.uncertainty_mm + TOLERANCE_MM:
            c["violations"] += 1
            if len(self.examples) < 10:
                self.examples.append({"phase": self.phase, "actuator": actuator,
                                      "lap_s": round(lo, 3), "error_mm": round(err, 2),
                                      "uncertainty_mm": round(float(p.uncertainty_mm), 2)})


class Notifier(SystemdNotifier):
    """The watchdog as systemd would see it: the time of every ping."""

    def __init__(self) -> None:
        super().__init__({"WATCHDOG_USEC": str(WATCHDOG_USEC)})
        self.pings: list[float] = []
        self.largest_gap_s = 0.0

    def notify(self, **fields: object) -> bool:
        if "WATCHDOG" in fields:
            now = time.monotonic()
            if self.pings:
                self.largest_gap_s = max(self.largest_gap_s, now - self.pings[-1])
            self.pings[:] = [now]
        return True


def _slope_mb_h(samples: list[tuple[float, int]], after_s: float) -> float | None:
    pts = [(t, r) for t, r in samples if t >= after_s]
    if len(pts) < 3:
        return None
    return round(float(np.polyfit([t for t, _ in pts], [r for _, r in pts], 1)[0])
                 * 3600 / 1024, 3)


def figures(args, lap: Lap, judge: Judge, notifier: Notifier, rss: list[tuple[float, int]],
            elapsed_s: float, service: Service) -> dict[str, object]:
    share = {p: c["flagged"] / c["outputs"] if c["outputs"] else None
             for p, c in judge.counts.items()}
    diff = (round(100 * (share["hostile"] - share["clean"]), 2)
            if share["hostile"] is not None and share["clean"] is not None else None)
    return {
        "duration_s": args.duration_s, "elapsed_s": round(elapsed_s, 1),
        "clean_s": args.clean_s, "warmup_s": args.warmup_s, "flood_hz": args.flood_hz,
        "config": str(args.config),
        "rss_start_mb": round(rss[0][1] / 1024, 1) if rss else None,
        "rss_now_mb": round(rss[-1][1] / 1024, 1) if rss else None,
        "rss_max_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "rss_growth_mb_per_h_after_warmup": _slope_mb_h(rss, args.warmup_s),
        "watchdog_pings": service.watchdog_pings,
        "watchdog_largest_gap_s": round(notifier.largest_gap_s, 3),
        "flagged_share_clean_pct": None if share["clean"] is None
        else round(100 * share["clean"], 2),
        "flagged_share_hostile_pct": None if share["hostile"] is None
        else round(100 * share["hostile"], 2),
        "flagged_share_difference_points": diff,
        "violations": sum(c["violations"] for c in judge.counts.values()),
        "phases": judge.counts,
        "violation_examples": judge.examples,
        "max_error_unflagged_mm": round(judge.max_error_mm, 2),
        "lap_s": round(lap.span_s, 3),
        "lap_closing_error_mm": {a: round(v, 2) for a, v in lap.closing_error_mm.items()},
        "backlog_dropped_frames": service.ingest.dropped_frames,
        "canopen_dropped_frames": service.ingest.canopen_dropped,
        "rejected_frames": service.inputs.rejected_total,
        "unknown_frames": service.inputs.counts["unknown"],
        "state_saves": service.saves,
    }


def _write(args, record: dict[str, object], final: bool) -> None:
    """The final record through ``publish`` (bench/results/soak.json, or ``--out``); a
    partial one printed and written to the same file, marked partial."""
    out = Path(args.out) if args.out is not None else _results.RESULTS / "soak.json"
    if final:
        _results.RESULTS = out.parent
        publish(out.stem, record)
        return
    print(json.dumps({k: v for k, v in record.items() if k != "phases"}), flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps({"benchmark": out.stem, "partial": True,
                               "when": time.strftime("%Y-%m-%dT%H:%M:%S"),
                               "command": " ".join(["python", "bench/soak.py", *sys.argv[1:]]),
                               "figures": record}, indent=2) + "\n")
    tmp.replace(out)


async def soak(args, cfg: Config, lap: Lap) -> dict[str, object]:
    ctx = multiprocessing.get_context("fork")      # before the service starts any thread
    mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    for s in (mine, theirs):
        s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SOCKET_BUFFER)
    stop = ctx.Event()
    start_wall = ctx.Value("d", math.nan)
    machine = ctx.Process(target=_machine, args=(theirs, lap.frames, lap.span_s, start_wall,
                                                 stop), daemon=True)
    flood = ctx.Process(target=_flood, args=(theirs, cfg, args.flood_hz, stop), daemon=True)
    tables = {a: build_unit_tables(cfg, a) for a in cfg.can.units}
    bus = StampedPairBus(mine)
    notifier = Notifier()
    state_dir = tempfile.TemporaryDirectory(prefix="ddh-soak-")
    service = Service(cfg, tables, {"interface": "socketpair", "channel": "default"},
                      ServiceOptions(state_dir=Path(state_dir.name), fd_reader=True),
                      notifier=notifier, opener=lambda settings, filters: bus)
    judge = Judge(cfg, lap)
    service.observers.append(judge)
    await service.start()
    for unit in service.units.values():         # commissioned: preset to the lap's start
        x = lap.truth[unit.actuator][1]
        unit.preset(float(x[0]), service.published(unit))
    machine.start()
    while math.isnan(start_wall.value):
        await asyncio.sleep(0.01)
    judge.start_wall = start_wall.value
    rss: list[tuple[float, int]] = []
    t0 = time.monotonic()
    traced = None
    next_partial = t0 + args.partial_s
    sample_s = min(10.0, max(args.duration_s / 100, 0.5))
    try:
        while (elapsed := time.monotonic() - t0) < args.duration_s:
            if judge.phase == "clean" and elapsed >= args.clean_s and args.flood_hz > 0:
                judge.phase = "hostile"
                flood.start()
            await asyncio.sleep(sample_s)
            rss.append((time.monotonic() - t0, _rss_kb()))
            if args.tracemalloc and traced is None and rss[-1][0] >= args.warmup_s:
                traced = tracemalloc.take_snapshot()
            if time.monotonic() >= next_partial:
                next_partial += args.partial_s
                _write(args, figures(args, lap, judge, notifier, rss, time.monotonic() - t0,
                                     service), final=False)
    finally:
        stop.set()
        for proc in (machine, flood):
            if proc.pid is not None:
                proc.join(5)
                if proc.is_alive():
                    proc.kill()
        await service.shutdown()
        state_dir.cleanup()
    record = figures(args, lap, judge, notifier, rss, time.monotonic() - t0, service)
    if traced is not None:
        growth = tracemalloc.take_snapshot().compare_to(traced, "traceback")
        record["tracemalloc_growth_after_warmup"] = [
            {"kb": round(d.size_diff / 1024, 1), "blocks": d.count_diff,
             "where": [f"{f.filename}:{f.lineno}" for f in d.traceback[-4:]]}
            for d in growth[:8]]
    return record


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration-s", type=float, default=7200.0,
                    help="the whole run, clean phase included (default %(default)s)")
    ap.add_argument("--clean-s", type=float, default=None,
                    help="the clean phase (default: 600 s, a third of shorter runs)")
    ap.add_argument("--warmup-s", type=float, default=None,
                    help="RSS growth is fitted after this (default: as --clean-s)")
    ap.add_argument("--flood-hz", type=float, default=2000.0)
    ap.add_argument("--partial-s", type=float, default=600.0,
                    help="a partial record this often (default %(default)s)")
    ap.add_argument("--config", type=Path, default=ROOT / "config" / "loader.yaml")
    ap.add_argument("--tracemalloc", action="store_true",
                    help="trace allocations (slower): the largest growth after the warm-up")
    ap.add_argument("--out", type=Path, default=None,
                    help="the record's file instead of bench/results/soak.json (partial "
                         "ones too)")
    args = ap.parse_args(argv)
    if args.clean_s is None:
        args.clean_s = min(600.0, args.duration_s / 3)
    if args.warmup_s is None:
        args.warmup_s = args.clean_s
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s")
    cfg = load_config(args.config)
    if args.tracemalloc:
        tracemalloc.start(8)
    print("simulating the paper cycle ...", flush=True)
    lap = Lap(cfg)
    record = asyncio.run(soak(args, cfg, lap))
    _write(args, record, final=True)
    ok = record["violations"] == 0
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
