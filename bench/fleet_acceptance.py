"""Benchmark: the fleet's alarms on several simulated fleets, judged by the acceptance rule.

Each seed's fleet (20 machines x 30 days, ``--work-s`` of work a day summarised by the
daemon's code, the logs as ``simulate fleet`` writes them) is simulated once into
``ROOT/<seed>/logs`` (kept: a second call only analyses), ingested with its summaries into a
store on a local cluster of 2 workers, analysed and scored against its truth file:

- every wearing unit whose error crosses the tolerance on day ``--from-day`` or later is
  alarmed at least 7 days before the crossing with the right cause (the pressure scale's two
  readings, pump leakage and torque gain, count as one);
- at most one false alarm per 20 machine-months.

The first seed (or those given by ``--remote``) is analysed again on a Dask scheduler and two
workers on 127.0.0.1 (separate processes): its alarms must equal the local cluster's.

    python bench/fleet_acceptance.py --seeds 99 2026 7 --fresh 11 12 --root DIR

``--seeds`` were seen while the fleet analysis was designed, ``--fresh`` drawn after it was
frozen; both are reported apart. Results in ``bench/results/fleet_acceptance.json``.
"""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import publish  # noqa: E402
from fleet import HORIZON_DAYS, TOLERANCE_MM, score  # noqa: E402

from ddh_vsensor.config import load_config  # noqa: E402
from ddh_vsensor.diagnosis.day_summary import summarise_runs  # noqa: E402
from ddh_vsensor.diagnosis.trend import unit_trend  # noqa: E402
from ddh_vsensor.fleet.analysis import analyse_machine  # noqa: E402
from ddh_vsensor.fleet.cluster import dask_client, run_batched, run_tasks  # noqa: E402
from ddh_vsensor.fleet.ingest import DEFAULT_NAME_PATTERN, IngestJob, ingest_batch  # noqa: E402
from ddh_vsensor.fleet.store import Store  # noqa: E402
from ddh_vsensor.sim.fleet import (day_summary_name, log_name, plan_fleet,  # noqa: E402
                                   simulate_fleet)

WARNING_DAYS = 7


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def scheduler_and_two_workers() -> Iterator[str]:
    """A Dask scheduler and two single-threaded workers, each its own process on 127.0.0.1;
    all stop with the block (and by themselves after an hour)."""
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler",
                               "--host", "127.0.0.1", "--port", str(port), "--no-dashboard",
                               "--idle-timeout", "3600"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise RuntimeError("the dask scheduler did not start within 120 s")
                time.sleep(0.3)
        procs += [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker",
                                    address, "--nthreads", "1", "--nworkers", "1", "--host",
                                    "127.0.0.1", "--no-dashboard", "--lifetime", "3600"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                  for _ in range(2)]
        from dask.distributed import Client
        with Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=300)
        yield address
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()


def simulate(cfg, seed: int, logs: Path, work_s: float) -> float:
    """The fleet's days not yet in ``logs``; wall seconds spent."""
    plan = plan_fleet(cfg, 20, 30, seed, 30.0, work_s=work_s)
    done = {p.name for p in logs.glob("*")} if logs.is_dir() else set()

    def day_done(d: int) -> bool:
        return all(log_name(m.name, d) in done and day_summary_name(m.name, d) in done
                   for m in plan.machines)
    missing = [d for d in range(30) if not day_done(d)]
    if not missing and "truth.json" in done:
        return 0.0
    started = time.perf_counter()

    def summarise(machine: str, _day: int, sessions: list) -> None:
        summarise_runs(cfg, machine, sessions, logs)
    simulate_fleet(cfg, plan, logs, days=missing, days_per_batch=5, summarise=summarise,
                   progress=lambda f: print(f"  seed {seed}: simulated {100 * f:.0f} %",
                                            flush=True))
    return time.perf_counter() - started


def analyse(cfg, logs: Path, store_dir: Path, scheduler: str | None) -> list:
    """Ingest the logs and summaries, analyse every machine, and the units' trends."""
    files = sorted(logs.glob("*.blf")) + sorted(logs.glob("*.summary.json"))
    if not (store_dir / "analysed").is_file():
        import shutil
        shutil.rmtree(store_dir, ignore_errors=True)
        Store(store_dir, create=True)
        jobs = [IngestJob(str(p), str(store_dir), None, DEFAULT_NAME_PATTERN) for p in files]
        with dask_client(scheduler, 2) as client:
            run_batched(client, ingest_batch, jobs)
            store = Store(store_dir)
            run_tasks(client, analyse_machine,
                      [(str(store.root), m, None) for m in sorted(store.machine_logs())])
        (store_dir / "analysed").write_text("")
    store = Store(store_dir)
    rows = store.query("SELECT * FROM fits").to_pylist()
    return [unit_trend(m, a, [r for r in rows if r["machine"] == m and r["actuator"] == a],
                       TOLERANCE_MM, HORIZON_DAYS)
            for m in sorted(store.machine_logs()) for a in cfg.can.units]


def alarm_days(trends) -> list:
    return [(t.machine, t.actuator, [None if a is None else (a.cause, round(a.time_s))
                                     for a in t.alarms]) for t in trends]


def judge(trends, truth: dict, from_day: int) -> dict:
    s = score(trends, truth, 30)
    due = [w for w in s["wearing"] if w["crossing_day"] is not None
           and w["crossing_day"] >= from_day]
    ok = [w for w in due if w["warning_days"] is not None
          and w["warning_days"] >= WARNING_DAYS]
    months = 20 * 30 / 30.0
    fa_rate = round(20 * s["false_alarms"] / months, 2)
    return {"wearing units": s["wearing"],
            f"crossing on day {from_day} or later": len(due),
            f"of those alarmed >= {WARNING_DAYS} days ahead with the right cause": len(ok),
            "missed": [f"{w['machine']} {w['actuator']} {w['cause']}: crossing day "
                       f"{w['crossing_day']}, warned {w['warning_days']}" for w in due
                       if w not in ok],
            "false alarms": s["false_alarms"],
            "false alarms per 20 machine-months": fa_rate,
            "passes": len(ok) == len(due) and fa_rate <= 1.0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="*", default=[99, 2026, 7, 31, 123, 4242, 808])
    ap.add_argument("--fresh", type=int, nargs="*", default=[],
                    help="seeds drawn after the design was frozen")
    ap.add_argument("--work-s", type=float, default=300.0,
                    help="a day's work the daemon's summaries see (s)")
    ap.add_argument("--from-day", type=int, default=10,
                    help="wears crossing the tolerance on this day or later must be warned")
    ap.add_argument("--root", default="/tmp/ddh_fleet_acceptance")
    ap.add_argument("--remote", type=int, nargs="*", default=None, metavar="SEED",
                    help="fleets also analysed on a scheduler + 2 workers (default: the first; "
                         "none with no seed)")
    args = ap.parse_args()
    cfg = load_config(None)
    root = Path(args.root)
    remote = (args.seeds + args.fresh)[:1] if args.remote is None else args.remote
    fleets: dict[str, dict] = {}
    for seed in args.seeds + args.fresh:
        logs = root / str(seed) / "logs"
        sim_s = simulate(cfg, seed, logs, args.work_s)
        truth = json.loads((logs / "truth.json").read_text())
        started = time.perf_counter()
        trends = analyse(cfg, logs, root / str(seed) / "store", None)
        figures = {"set": "fresh" if seed in args.fresh else "seen",
                   "simulate (s)": round(sim_s), "ingest and analyse (s)":
                   round(time.perf_counter() - started)}
        figures.update(judge(trends, truth, args.from_day))
        if seed in remote:
            with scheduler_and_two_workers() as address:
                on_cluster = analyse(cfg, logs, root / str(seed) / "store_remote", address)
            figures["scheduler + 2 workers: identical alarms"] = \
                alarm_days(on_cluster) == alarm_days(trends)
        fleets[str(seed)] = figures
        print(f"seed {seed}: " + json.dumps({k: v for k, v in figures.items()
                                             if k != "wearing units"}), flush=True)
        summary(fleets, args)


def summary(fleets: dict, args: argparse.Namespace) -> None:
    """Written after every fleet: a stopped run keeps what it measured."""
    due = sum(f[f"crossing on day {args.from_day} or later"] for f in fleets.values())
    ok = sum(f[f"of those alarmed >= {WARNING_DAYS} days ahead with the right cause"]
             for f in fleets.values())
    publish("fleet_acceptance", {
        "fleets": fleets,
        "rule": f"wears crossing {TOLERANCE_MM} mm on day {args.from_day} or later alarmed "
                f">= {WARNING_DAYS} days ahead with the right cause; <= 1 false alarm per 20 "
                f"machine-months; horizon {HORIZON_DAYS} days",
        "work per machine-day (s)": args.work_s,
        "wears due, warned in time": [due, ok],
        "worst false alarms per 20 machine-months":
            max(f["false alarms per 20 machine-months"] for f in fleets.values()),
        "every fleet passes": all(f["passes"] for f in fleets.values()),
        "fleets judged": f"{len(fleets)} of {len(args.seeds) + len(args.fresh)}"})


if __name__ == "__main__":
    main()
