"""Benchmark: the daemon's health warning on a wearing machine's month, replayed.

One wearing machine of the simulated fleet (``plan_fleet``: one machine, every machine
wearing) and one that does not, each over ``--days`` days of ``--work-s`` seconds of work a
day, replayed day by day through the real service (:class:`.Service`, running in its own
event loop thread on a python-can ``virtual`` bus, its day-summary worker a process as in
production) with the time compressed: each session's frames go through the service's own
receive path (``ingest.handle``) as fast as it takes them, and the daemon's wall clock
follows the frames (``unit_state.read_wall_offset`` and the service's ``wall_clock`` give the
current frame's time), so that each simulated day's samples land in that day's summary.

After each day the harness hands the worker the last samples, waits until it has taken
every block, written the day and judged the health, and until the service has ticked twice
(its tick sends the EMCY); then it records each node's health (``node.health``: what 0x2010
serves), the EMCY frames a second virtual bus on the same channel received (FF30: maintenance
due), and ``health.json``.

Figures: per day the wearing unit's health (cause, error now, days to the tolerance, alarm);
the first day an EMCY FF30 came from the wearing unit's node; the crossing day from the
plan's truth (the first day ``sim.fleet.expected_error_mm`` passes the tolerance, 3 mm); the
lead in days; the no-wear machine's FF30s (false alarms); wall time; summary bytes per
machine-day. Seeds are tried from ``--seed`` on until a wear crosses on day 10 or later and
within the days (every seed tried is reported, with why it was skipped).

    python bench/health.py [--days 30] [--work-s 600] [--seed 2026]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import shutil
import sys
import tempfile
import threading
import time
import uuid
from collections import Counter
from pathlib import Path
from typing import Any

import can

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import publish  # noqa: E402

import ddh_vsensor.service.unit_state as unit_state  # noqa: E402
from ddh_vsensor.cli.progress import ProgressBar  # noqa: E402
from ddh_vsensor.config import load_config  # noqa: E402
from ddh_vsensor.device.emcy import MAINTENANCE_CODE  # noqa: E402
from ddh_vsensor.diagnosis.causes import CAUSE_NAMES  # noqa: E402
from ddh_vsensor.master.replay import machine_frames  # noqa: E402
from ddh_vsensor.service import Service, ServiceOptions  # noqa: E402
from ddh_vsensor.service.summary import HEALTH_FILE, SUBDIR  # noqa: E402
from ddh_vsensor.sim.fleet import (START_DATE, FleetPlan, MachinePlan,  # noqa: E402
                                   expected_error_mm, plan_fleet, simulate_fleet)
from ddh_vsensor.tables.build import build_unit_tables  # noqa: E402

MIN_CROSSING_DAY = 10          # a crossing earlier leaves no room for a week's warning
WAIT_S = 300.0                 # bound of every wait on the service or its worker
CHUNK = 2000                   # frames per call into the service's loop
SLICE = 200                    # ... between which the loop runs its ticks


class ReplayClock:
    """The daemon's wall clock in a replay: the time of the frame being handled."""

    def __init__(self, start_s: float) -> None:
        self.now_s = start_s

    def __call__(self) -> float:
        return self.now_s

    def wall_offset(self) -> tuple[float, float, float]:
        """As :func:`.unit_state.read_wall_offset`: the wall clock, the wall less the
        monotonic clock (held constant: no step of the wall clock against it) and the
        reading's error."""
        return self.now_s, 0.0, 0.0


def day_frames(cfg, sessions: list[dict]) -> list[can.Message]:
    """A day's sessions as the machine puts them on the bus: its inputs
    (:func:`.master.replay.machine_frames`). Not the controllers' heartbeats: compressed in
    time they would pass the service's flood limit for CANopen frames (50/s per COB-ID) and
    be dropped; without them the controllers are flagged not operational, which changes
    nothing of what is integrated or summarised."""
    return [m for runs in sessions
            for m in machine_frames(cfg, runs, heartbeat_period_s=None)]


class DaemonReplay:
    """The service in its own event loop thread on a virtual bus, its wall clock the
    replay's, fed frames through its own receive path; a second bus on the channel keeps
    the EMCY and TPDO3 frames the nodes send."""

    def __init__(self, cfg, tables, state_dir: Path, machine: str) -> None:
        self.cfg, self.state_dir = cfg, Path(state_dir)
        self.state_dir.mkdir(parents=True, exist_ok=True)     # as `run` makes it
        self.clock = ReplayClock(START_DATE.timestamp())
        self._saved_wall_offset = unit_state.read_wall_offset
        unit_state.read_wall_offset = self.clock.wall_offset
        self.channel = f"ddh-health-{uuid.uuid4().hex[:12]}"
        self.day = 0                   # the day being replayed
        self.frames: list[tuple[int, can.Message]] = []       # (that day, EMCY or TPDO3)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None
        options = ServiceOptions(state_dir=self.state_dir, machine=machine)
        self._thread = threading.Thread(target=self._run, args=(tables, options),
                                         name="ddh-vsensor service", daemon=True)
        self._thread.start()
        if not self._started.wait(WAIT_S) or self._error is not None:
            self.close()
            raise RuntimeError(f"the service did not start: {self._error!r}")
        self.service: Service = self._service
        recorder = self.service.summaries
        assert recorder is not None
        recorder.save_interval_s = 0.0     # the worker writes the day (and judges) per block
        nodes = {a: u.node for a, u in self.service.units.items()}
        self.emcy_ids = {n.emcy.cob_id: a for a, n in nodes.items()}
        self.tpdo3_ids = {n.tpdo3.cob_id: a for a, n in nodes.items()}
        self.bus = can.Bus(interface="virtual", channel=self.channel, can_filters=[
            {"can_id": i, "can_mask": 0x7FF} for i in (*self.emcy_ids, *self.tpdo3_ids)])
        self._notifier = can.Notifier(self.bus, [self._keep], 0.1)

    def _keep(self, msg: can.Message) -> None:
        self.frames.append((self.day, msg))

    def _run(self, tables, options) -> None:
        async def main() -> None:
            self._service = Service(self.cfg, tables,
                                    {"interface": "virtual", "channel": self.channel},
                                    options, wall_clock=self.clock)
            self._loop = asyncio.get_running_loop()
            await self._service.start()
            self._started.set()
            try:
                await self._service._stop_event.wait()               # noqa: SLF001
            finally:
                await self._service.shutdown()
        try:
            asyncio.run(main())
        except BaseException as exc:   # noqa: BLE001 - reported to the caller
            self._error = exc
            self._started.set()

    def call(self, fn, *args) -> Any:
        """``fn(*args)`` in the service's loop; its result."""
        async def run() -> Any:
            return fn(*args)
        assert self._loop is not None
        return asyncio.run_coroutine_threadsafe(run(), self._loop).result(WAIT_S)

    def feed(self, frames: list[can.Message]) -> None:
        """The frames through the service's receive path, stamped as received now (the
        monotonic clock), the wall clock at each frame's time; the ticks run between
        slices."""
        ingest, clock = self.service.ingest, self.clock

        async def handle(chunk: list[can.Message]) -> None:
            for k in range(0, len(chunk), SLICE):
                for msg in chunk[k:k + SLICE]:
                    clock.now_s = msg.timestamp
                    ingest.handle([msg], time.monotonic())
                await asyncio.sleep(0)
        assert self._loop is not None
        for i in range(0, len(frames), CHUNK):
            asyncio.run_coroutine_threadsafe(handle(frames[i:i + CHUNK]),
                                             self._loop).result(WAIT_S)

    def settle(self) -> None:
        """The kept samples to the worker now; wait until it has taken every block (the day
        written, the health judged and on the nodes) and the service has ticked twice since
        (its tick sends the EMCY)."""
        recorder = self.service.summaries
        assert recorder is not None
        self.call(recorder.ship, True)
        deadline = time.monotonic() + WAIT_S
        while True:
            worker = recorder._worker                                   # noqa: SLF001
            if worker is None or self.call(lambda w=worker: w.queued) == 0:
                break
            if time.monotonic() > deadline or recorder.disabled:
                raise RuntimeError("the summary worker did not finish its blocks")
            time.sleep(0.05)
        ticks = self.service.ticks
        while self.service.ticks < ticks + 2:
            if time.monotonic() > deadline:
                raise RuntimeError("the service's tick did not run")
            time.sleep(0.01)
        time.sleep(0.05)                       # the EMCY's way to the other bus

    def health(self) -> dict[str, Any]:
        return self.call(lambda: {a: u.node.health for a, u in self.service.units.items()})

    def health_file(self) -> dict | None:
        path = self.state_dir / HEALTH_FILE
        return json.loads(path.read_text()) if path.is_file() else None

    def close(self) -> None:
        if self._loop is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self.service.request_stop)
        self._thread.join(WAIT_S)
        if hasattr(self, "_notifier"):
            self._notifier.stop(1.0)
            self.bus.shutdown()
        unit_state.read_wall_offset = self._saved_wall_offset


def ff30_days(replay: DaemonReplay) -> dict[str, list[int]]:
    """Per unit the days (index) an EMCY FF30 came from its node."""
    out: dict[str, list[int]] = {a: [] for a in replay.emcy_ids.values()}
    for day, msg in replay.frames:
        unit = replay.emcy_ids.get(msg.arbitration_id)
        if unit is not None and int.from_bytes(msg.data[:2], "little") == MAINTENANCE_CODE:
            out[unit].append(day)
    return out


def crossing_day(cfg, plan: FleetPlan, machine: MachinePlan, tolerance_mm: float) -> int | None:
    """The truth: the first day the wear's expected error passes the tolerance."""
    return next((d for d in range(plan.days)
                 if expected_error_mm(cfg, plan, machine, d) > tolerance_mm), None)


def pick_wear(cfg, days: int, first_seed: int, work_s: float, tolerance_mm: float,
              tries: int = 20) -> tuple[FleetPlan, int, list[dict]]:
    """The first seed from ``first_seed`` whose wearing machine crosses the tolerance on
    day :data:`MIN_CROSSING_DAY` or later and within the days; every seed tried, and why
    it was skipped."""
    tried = []
    for seed in range(first_seed, first_seed + tries):
        plan = plan_fleet(cfg, 1, days, seed, wear_share=1.0, work_s=work_s)
        m = plan.machines[0]
        cross = crossing_day(cfg, plan, m, tolerance_mm)
        w = m.wear
        entry = {"seed": seed, "wear": f"{w.actuator} {w.effect} from day {w.start_day}, "
                 f"{w.rate_per_day:.4g}/day", "crossing_day": cross}
        if cross is None:
            entry["skipped"] = f"no crossing within {days} days"
        elif cross < MIN_CROSSING_DAY:
            entry["skipped"] = f"crosses on day {cross} (< {MIN_CROSSING_DAY})"
        tried.append(entry)
        if "skipped" not in entry:
            return plan, cross, tried
    raise SystemExit(f"no seed of {first_seed}..{first_seed + tries - 1} gave a wear crossing "
                     f"on day {MIN_CROSSING_DAY}..{days - 1}: {tried}")


def replay_machine(cfg, tables, plan: FleetPlan, work: Path, bar: ProgressBar, part: tuple,
                   label: str, wearing: str | None) -> dict[str, Any]:
    """The plan's machine replayed day by day through the daemon; per day what the nodes
    and health.json say and the EMCY FF30s seen. A day is recorded once the worker has
    taken all of it, before the next day's frames go in; the next day is simulated (and
    its frames made) meanwhile."""
    machine = plan.machines[0]
    state = work / f"state_{label}"
    replay = DaemonReplay(cfg, tables, state, machine.name)
    per_day: list[dict[str, Any]] = []
    started = time.perf_counter()

    def record(day: int) -> None:
        replay.settle()
        health = replay.health()
        doc = replay.health_file()
        row: dict[str, Any] = {"day": day}
        for a, h in health.items():
            row[a] = None if h is None else {
                "cause": CAUSE_NAMES[h.cause_code], "days": h.days,
                "error_now_mm": None if h.error_now_mm is None else round(h.error_now_mm, 2),
                "days_to_tolerance": None if h.days_to_tolerance is None
                else round(h.days_to_tolerance, 1), "alarm": h.alarm}
        row["health.json units alarmed"] = sorted(
            a for a, u in (doc or {}).get("units", {}).items() if u["alarm"])
        per_day.append(row)
        u = row.get(wearing or cfg.unit_names[0])
        note = f"{label} day {day}: " + (
            "no health" if u is None else
            f"{wearing or cfg.unit_names[0]} {u['cause']}, error now {u['error_now_mm']} mm, "
            f"{u['days_to_tolerance']} days to the tolerance, alarm {u['alarm']}; FF30 so far "
            f"{ {a: len(d) for a, d in ff30_days(replay).items()} }")
        print(note, flush=True)
        bar.update((part[0] + (day + 1) / plan.days) / part[1], note)

    try:
        def summarise(name: str, day: int, sessions: list) -> None:
            frames = day_frames(cfg, sessions)
            if day:
                record(day - 1)
            replay.day = day
            replay.feed(frames)
            replay.call(replay.service.summaries.ship, True)     # the worker starts on it

        simulate_fleet(cfg, plan, work / f"logs_{label}", summarise=summarise,
                       days_per_batch=plan.sessions)
        record(plan.days - 1)
        wall_s = time.perf_counter() - started
        final = replay.health_file()
    finally:
        replay.close()
    sizes = sorted(p.stat().st_size for p in (state / SUBDIR).glob("*.summary.json"))
    return {"per_day": per_day, "ff30_days": ff30_days(replay), "health.json": final,
            "wall_s": wall_s, "summary_bytes": sizes,
            "emcy_codes": dict(sorted(Counter(
                f"{int.from_bytes(m.data[:2], 'little'):04X}" for _, m in replay.frames
                if m.arbitration_id in replay.emcy_ids).items()))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=int, default=30)
    ap.add_argument("--work-s", type=float, default=600.0, help="a day's work (s)")
    ap.add_argument("--seed", type=int, default=2026, help="the first seed tried")
    ap.add_argument("--work", default=None, help="working directory (default: a temporary "
                                                 "one, removed at the end)")
    args = ap.parse_args()
    cfg = load_config(None)
    tolerance_mm = cfg.health.tolerance_mm
    started = time.perf_counter()
    plan, cross, tried = pick_wear(cfg, args.days, args.seed, args.work_s, tolerance_mm)
    wear = plan.machines[0].wear
    assert wear is not None
    for t in tried:
        print(f"seed {t['seed']}: {t['wear']}, crossing day {t['crossing_day']}"
              + (f": skipped, {t['skipped']}" if "skipped" in t else ": taken"))
    steady = plan_fleet(cfg, 1, args.days, plan.seed, wear_share=0.0, work_s=args.work_s)
    tables = {a: build_unit_tables(cfg, a) for a in cfg.unit_names}
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="ddh_health_"))
    work.mkdir(parents=True, exist_ok=True)
    bar = ProgressBar("health replay")
    try:
        worn = replay_machine(cfg, tables, plan, work, bar, (0, 2), "wear", wear.actuator)
        calm = replay_machine(cfg, tables, steady, work, bar, (1, 2), "steady", None)
    finally:
        bar.close()
        if not args.work:
            shutil.rmtree(work, ignore_errors=True)
    first = min(worn["ff30_days"][wear.actuator], default=None)
    named = [r[wear.actuator]["cause"] for r in worn["per_day"]
             if r[wear.actuator] and r[wear.actuator]["alarm"]]
    sizes = worn["summary_bytes"] + calm["summary_bytes"]
    figures: dict[str, object] = {
        "seeds tried": tried,
        "machine": f"{plan.machines[0].name}, {args.days} days of {args.work_s:g} s of work "
                   f"({plan.sessions} sessions of {plan.log_s:g} s), replayed through the "
                   "service (virtual bus, its summary worker a process)",
        "wear (truth)": f"{wear.actuator} {wear.effect} from day {wear.start_day}, "
                        f"{wear.rate_per_day:.4g}/day",
        "tolerance / horizon": f"{tolerance_mm} mm / {cfg.health.horizon_days} days",
        "expected error per day (truth, mm)": [
            round(expected_error_mm(cfg, plan, plan.machines[0], d), 2)
            for d in range(args.days)],
        "crossing day (truth)": cross,
        "first EMCY FF30 day (wearing unit)": first,
        "EMCY FF30 days (wearing unit; one per alarm episode)": worn["ff30_days"][wear.actuator],
        "lead days (crossing - first FF30)": None if first is None else cross - first,
        "cause named at the alarms": sorted(set(named)),
        "right cause": bool(named) and set(named) <= {wear.effect},
        "FF30 from the other units (wearing machine)": {
            a: d for a, d in worn["ff30_days"].items() if a != wear.actuator},
        "per day, wearing unit (cause, error now mm, days to tolerance, alarm)": [
            None if r[wear.actuator] is None else
            [r["day"], r[wear.actuator]["cause"], r[wear.actuator]["error_now_mm"],
             r[wear.actuator]["days_to_tolerance"], r[wear.actuator]["alarm"]]
            for r in worn["per_day"]],
        "no-wear machine: FF30 days (false alarms)": calm["ff30_days"],
        "no-wear machine: false alarms": sum(len(d) for d in calm["ff30_days"].values()),
        "no-wear machine: causes named": sorted({r[a]["cause"] for r in calm["per_day"]
                                                 for a in cfg.unit_names if r[a]}),
        "health.json at the end (wearing machine)": {
            a: {k: u[k] for k in ("cause", "cause_code", "days", "error_now_mm",
                                  "days_to_tolerance", "alarm")}
            for a, u in (worn["health.json"] or {}).get("units", {}).items()},
        "EMCY frames seen by code (wearing, no-wear)": [worn["emcy_codes"], calm["emcy_codes"]],
        "summary bytes per machine-day (median, max)": [sizes[len(sizes) // 2], max(sizes)],
        "replay wall time (s): wearing, no-wear, total": [
            round(worn["wall_s"]), round(calm["wall_s"]), round(time.perf_counter() - started)],
    }
    publish("health", figures)


if __name__ == "__main__":
    main()
