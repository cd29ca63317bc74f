"""Benchmark: a randomised fault campaign and a hostile-traffic soak against the service.

Campaign (in-process, virtual time, for speed): the simulated paper cycle fed frame by frame
into a ``Service`` (never started: its frame routing, estimators, nodes and published values,
with the clock passed in), each episode preset to the truth, with randomly drawn faults:
Sevcon frames missing (0.02..4 s), a spoofed controller heartbeat (any NMT state), heartbeats
lost, an SDO preset from anywhere in the stroke, malformed and out-of-range Sevcon frames, an
NMT reset, a step of the frame clock (back or forward), a junk burst (unknown, extended and
error frames), a kill and restart from the last periodic save after 0.2..5 s. Every 10 ms
of machine time each unit's published value is checked: unless a flag says why (stale, not
referenced, unconfirmed preset, controller, table clamped), the truth must lie within the
published uncertainty over the interval the output may stand for (from its newest integrated
frame to now less 3 periods, the service's stale threshold).

Soak (real time, in-process on python-can ``virtual``): the service started, the paper cycle
looping at 100 Hz, hostile frames at ``--flood-hz`` (random 29-bit IDs, error frames, NMT
resets, unknown 11-bit IDs, short Sevcon frames); RSS sampled every second, the growth rate
fitted over the second half; the housekeeping tick's largest gap and the share of its ticks
at which the watchdog would be pinged (``Service.integrating``).

``python bench/faults.py [--faults 1000] [--seed 9] [--soak-s 60] [--mode dynamic]``; writes
bench/results/faults.json (``--mode kalman``, the service on the Kalman filter:
bench/results/faults_kalman.json; the simulated frames are 100 Hz, ``can.sevcon_period_ms``
10 ms, the filter's sample period).
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import logging
import random
import struct
import sys
import tempfile
import threading
import time
from pathlib import Path

import can
import numpy as np
from canopen.sdo import SdoAbortedError

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import publish  # noqa: E402

from ddh_vsensor.canbus.dbc import FrameCodec, message_name  # noqa: E402
from ddh_vsensor.config import Config, load_config  # noqa: E402
from ddh_vsensor.estimator.flags import EXPLAINING  # noqa: E402
from ddh_vsensor.service import Service, ServiceOptions  # noqa: E402
from ddh_vsensor.master.replay import machine_frames  # noqa: E402
from ddh_vsensor.sim import RunSpec, simulate_with_truth  # noqa: E402
from ddh_vsensor.tables.build import build_unit_tables  # noqa: E402

CHECK_S = 0.01
# Frame stamps: the frames' clock starts here, never at or below 0 (an interface without
# timestamps, to the service: it stamps such a frame with the wall clock).
FRAME_EPOCH_S = 1000.0
TOLERANCE_MM = 0.01
KINDS = ("gap", "heartbeat_spoof", "heartbeat_loss", "preset", "malformed", "nmt_reset",
         "clock_step", "junk_burst", "kill")


class Clock:
    """The campaign's monotonic time: machine time plus an offset."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def _truth(paper: dict, actuator: str, t: np.ndarray | float) -> np.ndarray:
    tt, xx = paper["truth"][actuator]
    return np.interp(t, tt, xx)


def _new_service(cfg: Config, tables: dict, clock: Clock, state_dir: Path) -> Service:
    return Service(cfg, tables, {"interface": "virtual", "channel": "unused"},
                   ServiceOptions(state_dir=state_dir), clock=clock)


class Episode:
    """One paper cycle with faults drawn at random times."""

    def __init__(self, cfg: Config, tables: dict, paper: dict, rng: random.Random,
                 n_faults: int, state_dir: Path) -> None:
        self.cfg, self.tables, self.paper, self.rng = cfg, tables, paper, rng
        self.codec = FrameCodec(cfg)
        self.sevcon_ids = {self.codec.ids[message_name("sevcon", a)]: a for a in cfg.can.units}
        self.clock = Clock()
        self.state_dir = state_dir
        self.service = _new_service(cfg, tables, self.clock, state_dir)
        end = paper["frames"][-1].timestamp
        self.faults = sorted((rng.uniform(0.5, end - 0.5), rng.choice(KINDS))
                             for _ in range(n_faults))
        self.counts = {k: 0 for k in KINDS}
        self.checks = self.unflagged = 0
        self.violations: list[dict] = []
        self.skip_until = {a: -1.0 for a in cfg.can.units}
        self.clock_offset = 0.0
        self.last_integrated = {a: None for a in cfg.can.units}
        self.preset_refused = self.preset_accepted = 0
        self.clipped_t = {a: -1e9 for a in cfg.can.units}

    def _now(self, t: float) -> float:
        return 1000.0 + t

    def _stamp(self, t: float) -> float:
        """A frame's timestamp at machine time ``t``: the frame clock, stepped as drawn."""
        return FRAME_EPOCH_S + t + self.clock_offset

    def _route(self, msg: can.Message, t: float) -> None:
        self.clock.now = self._now(t)
        self.service.ingest.handle([msg], self.clock.now)

    def _inject(self, t: float, kind: str) -> None:
        rng, cfg = self.rng, self.cfg
        actuator = rng.choice(list(cfg.can.units))
        self.counts[kind] += 1
        hb_ids = cfg.faults.heartbeat_node_ids
        if kind == "gap":
            self.skip_until[actuator] = t + rng.uniform(0.02, 4.0)
        elif kind == "heartbeat_spoof":
            node = hb_ids.get(actuator, 1)
            self._route(can.Message(timestamp=self._stamp(t), arbitration_id=0x700 + node,
                                    data=[rng.choice([0, 4, 5, 127])], is_extended_id=False), t)
        elif kind == "heartbeat_loss":
            self.hb_quiet_until = t + rng.uniform(0.5, 3.0)
        elif kind == "preset":
            unit = self.service.units[actuator]
            counts = round(rng.uniform(0.0, cfg.unit(actuator).stroke_mm)
                           / cfg.can.position_step_mm)
            try:
                unit.node._on_write(0x6010, 1, None, struct.pack("<i", counts))  # noqa: SLF001
                self.preset_accepted += 1
            except SdoAbortedError:
                self.preset_refused += 1
        elif kind == "malformed":
            sid = self.codec.ids[message_name("sevcon", actuator)]
            for msg in (can.Message(timestamp=self._stamp(t), arbitration_id=sid, data=b"\x01\x02",
                                    is_extended_id=False),
                        self.codec.encode_sevcon(actuator, 5.0, 50000.0, self._stamp(t)),
                        self.codec.encode_sevcon(actuator, 2000.0, 100.0, self._stamp(t))):
                self._route(msg, t)
        elif kind == "nmt_reset":
            self._route(can.Message(timestamp=self._stamp(t), arbitration_id=0, data=[0x81, 0],
                                    is_extended_id=False), t)
        elif kind == "clock_step":
            self.clock_offset += rng.choice([-1.0, 1.0]) * rng.uniform(0.05, 2.0)
        elif kind == "junk_burst":
            stamp = self._stamp(t)
            for k in range(500):
                self._route(can.Message(timestamp=stamp, arbitration_id=rng.getrandbits(29),
                                        is_extended_id=True, data=b"x"), t)
                self._route(can.Message(timestamp=stamp, arbitration_id=0x40, is_error_frame=True,
                                        is_extended_id=False), t)
                self._route(can.Message(timestamp=stamp, arbitration_id=0x555, data=b"1",
                                        is_extended_id=False), t)
        elif kind == "kill":
            down_s = rng.uniform(0.2, 5.0)
            from ddh_vsensor.estimator.state import save_state
            for a, unit in self.service.units.items():            # the last periodic save
                state = unit.estimator.snapshot()
                state.uncertainty_mm = self.service.published(unit, self.clock.now).uncertainty_mm
                path = self.state_dir / f"{a}.json"
                save_state(path, state)
                data = json.loads(path.read_text())
                data["saved_at"] -= down_s                         # it was written down_s ago
                path.write_text(json.dumps(data))
            self.service = _new_service(self.cfg, self.tables, self.clock, self.state_dir)
            for a in self.skip_until:                              # the machine went on
                self.skip_until[a] = max(self.skip_until[a], t + down_s)
            self.last_integrated = {a: None for a in self.cfg.can.units}

    def _check(self, t: float) -> None:
        now = self._now(t)
        stale_s = 3 * self.cfg.can.event_timer_ms / 1000.0
        for actuator, unit in self.service.units.items():
            est = unit.estimator
            if not est.referenced and not est.lower_mm < est.position_mm < est.upper_mm:
                self.clipped_t[actuator] = t
            p = self.service.published(unit, now)
            self.checks += 1
            if p.flags & EXPLAINING:
                continue
            self.unflagged += 1
            t_n = self.last_integrated[actuator]
            if t_n is None:
                t_n = t
            window = np.linspace(t_n, max(t_n, t - stale_s), 8)
            err = float(np.max(np.abs(_truth(self.paper, actuator, window) - p.position_mm)))
            if err > p.uncertainty_mm + TOLERANCE_MM:
                cause = ("reference after an unreferenced estimate clipped at a stroke end"
                         if t - self.clipped_t[actuator] < 3.0 else "other")
                self.violations.append({"t": round(t, 3), "actuator": actuator, "cause": cause,
                                        "error_mm": round(err, 3),
                                        "uncertainty_mm": round(p.uncertainty_mm, 3),
                                        "flags": p.flags,
                                        "recent_faults": [(round(ft, 2), k) for ft, k in
                                                          self.faults if t - 5 < ft <= t]})

    def run(self) -> None:
        cfg = self.cfg
        frames = self.paper["frames"]
        for a, unit in self.service.units.items():        # commissioned at the truth
            unit.estimator.preset(float(_truth(self.paper, a, frames[0].timestamp)),
                                  cfg.estimator.uncertainty_reference_mm)
            if hasattr(unit.estimator, "gain"):           # the Kalman filter has none
                unit.estimator.gain.gain[:] = 1.0
        self.hb_quiet_until = -1.0
        fault_i = 0
        next_check = frames[0].timestamp
        hb_ids = {0x700 + n for n in cfg.faults.heartbeat_node_ids.values()}
        for msg in frames:
            t = msg.timestamp
            while next_check <= t:
                self._check(next_check)
                next_check += CHECK_S
            while fault_i < len(self.faults) and self.faults[fault_i][0] <= t:
                self._inject(t, self.faults[fault_i][1])
                fault_i += 1
            actuator = self.sevcon_ids.get(msg.arbitration_id)
            if actuator is not None and t < self.skip_until[actuator]:
                continue
            if msg.arbitration_id in hb_ids and t < self.hb_quiet_until:
                continue
            out = can.Message(timestamp=self._stamp(t), arbitration_id=msg.arbitration_id,
                              data=msg.data, is_extended_id=False)
            self._route(out, t)
            if actuator is not None:
                unit = self.service.units[actuator]
                if unit.last_frame_t is not None and unit.last_frame_t == out.timestamp:
                    self.last_integrated[actuator] = t


def campaign(cfg: Config, tables: dict, paper: dict, n_faults: int, seed: int) -> dict:
    rng = random.Random(seed)
    per_episode = 25
    episodes = max(1, -(-n_faults // per_episode))
    totals = {k: 0 for k in KINDS}
    checks = unflagged = 0
    violations: list[dict] = []
    refused = accepted = 0
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="ddh-faults-") as tmp:
        for e in range(episodes):
            state_dir = Path(tmp) / f"e{e}"
            ep = Episode(cfg, tables, paper, rng, per_episode, state_dir)
            ep.run()
            for k, v in ep.counts.items():
                totals[k] += v
            checks += ep.checks
            unflagged += ep.unflagged
            violations += ep.violations
            refused += ep.preset_refused
            accepted += ep.preset_accepted
            print(f"\repisode {e + 1}/{episodes}: {sum(totals.values())} faults, "
                  f"{len(violations)} violations", end="", flush=True)
    print()
    causes: dict[str, int] = {}
    for v in violations:
        causes[v["cause"]] = causes.get(v["cause"], 0) + 1
    others = [v for v in violations if v["cause"] == "other"]
    return {"faults_injected": sum(totals.values()), "faults_by_kind": totals,
            "episodes": episodes, "checks": checks, "checks_unflagged": unflagged,
            "violations": len(violations), "violations_by_cause": causes,
            "violation_examples": (others or violations)[:5],
            "presets_refused": refused, "presets_accepted": accepted,
            "campaign_wall_s": round(time.perf_counter() - started, 1)}


def _drain(bus: can.BusABC) -> None:
    while bus.recv(0.0) is not None:
        pass


def _rss_kb() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def soak(cfg: Config, tables: dict, paper: dict, seconds: float, flood_hz: float) -> dict:
    channel = f"ddh-faults-soak-{time.time_ns()}"
    codec = FrameCodec(cfg)
    stop = threading.Event()
    sent = {"flood": 0, "machine": 0}

    def flood() -> None:
        rng = random.Random(7)
        bus = can.Bus(interface="virtual", channel=channel)
        sid = codec.ids[message_name("sevcon", "boom")]
        makers = [lambda: can.Message(arbitration_id=rng.getrandbits(29), is_extended_id=True,
                                      data=b"x"),
                  lambda: can.Message(arbitration_id=0x40, is_error_frame=True,
                                      is_extended_id=False),
                  lambda: can.Message(arbitration_id=0, data=[0x81, 0], is_extended_id=False),
                  lambda: can.Message(arbitration_id=rng.randrange(0x100, 0x7FF), data=b"1",
                                      is_extended_id=False),
                  lambda: can.Message(arbitration_id=sid, data=b"\x01", is_extended_id=False)]
        start = time.time()
        try:
            while not stop.is_set():
                due = int((time.time() - start) * flood_hz)
                while sent["flood"] < due:
                    bus.send(rng.choice(makers)())
                    sent["flood"] += 1
                _drain(bus)           # a virtual bus queues every frame of the channel
                time.sleep(0.005)
        finally:
            bus.shutdown()

    def machine() -> None:
        bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        frames = paper["frames"]
        span = frames[-1].timestamp - frames[0].timestamp + 0.01
        start = time.time()
        lap = 0
        try:
            while not stop.is_set():
                for msg in frames:
                    due = start + lap * span + msg.timestamp - frames[0].timestamp
                    delay = due - time.time()
                    if delay > 0:
                        if stop.wait(delay):
                            return
                    bus.send(can.Message(timestamp=due, arbitration_id=msg.arbitration_id,
                                         data=msg.data, is_extended_id=False))
                    sent["machine"] += 1
                    _drain(bus)
                lap += 1
        finally:
            bus.shutdown()

    async def run() -> dict:
        service = Service(cfg, tables, {"interface": "virtual", "channel": channel},
                          ServiceOptions())
        ticks: list[float] = []
        healthy = [0, 0]
        original = service._on_housekeeping                       # noqa: SLF001

        def housekeeping() -> None:
            now = time.monotonic()
            ticks.append(now)
            healthy[0] += service.integrating(now)
            healthy[1] += 1
            original()

        service._on_housekeeping = housekeeping                   # noqa: SLF001
        await service.start()
        threads = [threading.Thread(target=f, daemon=True) for f in (flood, machine)]
        for th in threads:
            th.start()
        rss: list[tuple[float, int]] = []
        t0 = time.monotonic()
        try:
            while time.monotonic() - t0 < seconds:
                await asyncio.sleep(1.0)
                rss.append((time.monotonic() - t0, _rss_kb()))
        finally:
            stop.set()
            for th in threads:
                th.join(5)
            await service.shutdown()
        half = [(t, r) for t, r in rss if t >= seconds / 2]
        slope_kb_s = float(np.polyfit([t for t, _ in half], [r for _, r in half], 1)[0]) \
            if len(half) >= 3 else float("nan")
        gaps = np.diff(ticks) if len(ticks) > 1 else np.array([np.inf])
        return {"soak_s": seconds, "flood_frames_per_s": round(sent["flood"] / seconds),
                "machine_frames_per_s": round(sent["machine"] / seconds),
                "rss_start_mb": round(rss[0][1] / 1024, 1) if rss else None,
                "rss_end_mb": round(rss[-1][1] / 1024, 1) if rss else None,
                "rss_growth_mb_per_h_fit": round(slope_kb_s * 3600 / 1024, 2),
                "housekeeping_ticks": len(ticks),
                "housekeeping_max_gap_ms": round(float(gaps.max()) * 1000, 1),
                "watchdog_eligible_share": round(healthy[0] / max(healthy[1], 1), 4),
                "backlog_dropped_frames": service.ingest.dropped_frames,
                "canopen_dropped_frames": service.ingest.canopen_dropped,
                "integrated_boom": service.units["boom"].integrated}

    return asyncio.run(run())


def main() -> int:
    logging.disable(logging.WARNING)        # the faults are meant: their log lines are noise here
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--faults", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=9)
    ap.add_argument("--soak-s", type=float, default=60.0)
    ap.add_argument("--flood-hz", type=float, default=8000.0)
    ap.add_argument("--mode", choices=("full", "paper", "dynamic", "kalman"),
                    help="the estimator mode (default: the configuration's); kalman writes "
                    "bench/results/faults_kalman.json")
    args = ap.parse_args()
    cfg = load_config()
    if args.mode is not None:
        cfg = dataclasses.replace(cfg, estimator=dataclasses.replace(cfg.estimator,
                                                                     mode=args.mode))
    print("simulating the paper cycle ...", flush=True)
    result = simulate_with_truth(cfg, [RunSpec(speed=4)])[0]
    runs = {a: run for a, (run, _) in result.items()}
    period_s = float(np.median(np.diff(next(iter(runs.values())).time_s)))
    if cfg.estimator.mode == "kalman" and abs(period_s * 1e3 - cfg.can.sevcon_period_ms) > 1e-6:
        cfg = dataclasses.replace(cfg, can=dataclasses.replace(
            cfg.can, sevcon_period_ms=round(period_s * 1e3, 6)))   # the filter's sample period
        print(f"can.sevcon_period_ms set to the frames' {period_s * 1e3:g} ms", flush=True)
    paper = {"frames": list(machine_frames(cfg, runs, heartbeat_period_s=0.1)),
             "truth": {a: (truth.time_s, truth.x_m * 1e3) for a, (_, truth) in result.items()}}
    tables = {a: build_unit_tables(cfg, a) for a in cfg.can.units}
    figures = {"mode": cfg.estimator.mode}
    figures.update(campaign(cfg, tables, paper, args.faults, args.seed))
    if args.soak_s > 0:
        print(f"soak: {args.soak_s:g} s at {args.flood_hz:g} hostile frames/s ...", flush=True)
        figures.update(soak(cfg, tables, paper, args.soak_s, args.flood_hz))
    publish("faults_kalman" if cfg.estimator.mode == "kalman" else "faults", figures)
    return 0 if figures["violations"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
