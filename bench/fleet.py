"""Benchmark: fleet diagnosis on a simulated fleet (default 20 machines x 30 days).

Simulates the fleet (logs already in --logs are kept: the plan is seeded), ingests it on a
local Dask cluster of 1 and of 2 workers (throughput: frames and log-hours per wall second;
what limits it, from a per-stage timing of one process), analyses and reports on 2 workers,
and scores the alarms against truth.json: every wearing machine flagged with the right cause,
the days of warning before its error crosses the tolerance, false alarms per machine-month.

    python bench/fleet.py [--machines 20] [--days 30] [--seed 2026] [--logs DIR] [--work DIR]

``--work-s S``: each machine-day also simulated for S seconds of work and summarised by the
daemon's code (``simulate fleet``'s day summaries, beside the logs); the summaries' size and
ingestion throughput (machine-days per wall second, 1 and 2 workers) are measured too, and
the analysis takes the summaries where a machine-day has one: results in
``fleet_summaries.json``.
"""

from __future__ import annotations

import argparse
import gzip
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import publish  # noqa: E402

from ddh_vsensor.config import load_config  # noqa: E402
from ddh_vsensor.diagnosis.day_summary import summarise_runs  # noqa: E402
from ddh_vsensor.fleet.analysis import analyse_machine  # noqa: E402
from ddh_vsensor.fleet.cluster import dask_client, run_batched, run_tasks  # noqa: E402
from ddh_vsensor.fleet.ingest import DEFAULT_NAME_PATTERN, IngestJob, ingest_batch  # noqa: E402
from ddh_vsensor.fleet.report import write_report  # noqa: E402
from ddh_vsensor.fleet.store import Store  # noqa: E402
from ddh_vsensor.diagnosis.finding import PRESSURE_SCALE  # noqa: E402
from ddh_vsensor.diagnosis.trend import DAY_S, expected_error_mm, to_u, unit_trend  # noqa: E402
from ddh_vsensor.sim.fleet import (START_DATE, day_summary_name, log_name,  # noqa: E402
                                   plan_fleet, simulate_fleet)

TOLERANCE_MM, HORIZON_DAYS = 3.0, 14.0


def _worker_cpu_s() -> float:
    import resource
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def ingest(logs: list[Path], store: Path, workers: int) -> dict:
    """Wall-clock throughput, and the CPU the workers got meanwhile (on a shared machine
    the cores they are given, not their number, set the wall time)."""
    shutil.rmtree(store, ignore_errors=True)
    Store(store, create=True)
    jobs = [IngestJob(str(p), str(store), None, DEFAULT_NAME_PATTERN) for p in logs]
    with dask_client(None, workers) as client:
        client.run(lambda: __import__("ddh_vsensor.fleet.ingest"))       # imports, not work
        cpu0 = sum(client.run(_worker_cpu_s).values())
        load0 = os.getloadavg()[0]
        started = time.perf_counter()
        results = run_batched(client, ingest_batch, jobs)
        wall = time.perf_counter() - started
        cpu = sum(client.run(_worker_cpu_s).values()) - cpu0
    frames = sum(r["frames"] for r in results)
    hours = sum(r["duration_s"] for r in results if r.get("kind") != "summary") / 3600
    days = sum(r.get("kind") == "summary" for r in results)
    return {"workers": workers, "logs": len(logs), "wall_s": round(wall, 2),
            "frames": frames, "frames_per_s": round(frames / wall),
            "log_hours_per_s": round(hours / wall, 4),
            "summaries": days, "machine_days_per_s": round(days / wall, 1),
            "workers_cpu_s": round(cpu, 2), "cores_the_workers_got": round(cpu / wall, 2),
            "frames_per_worker_cpu_s": round(frames / cpu),
            "load_average_1min": [round(load0, 1), round(os.getloadavg()[0], 1)],
            "rejected": sum(r["status"] == "rejected" for r in results)}


def stages(logs: list[Path], cfg) -> dict:
    """Where one process spends an ingestion, in CPU seconds (the machine is shared: wall
    time would count the other processes' share): python-can's reader for comparison, the
    numpy reader, decoding, references and holds, and the whole batch ingestion (the
    holding speeds and the Parquet files included)."""
    import can

    from ddh_vsensor.io.blf import frames_to_runs, read_frames
    from ddh_vsensor.fleet.ingest import _features, ingest_batch
    t = {"python-can BLFReader": 0.0, "fast reader": 0.0, "decode": 0.0,
         "references and holds": 0.0, "whole ingestion (batch)": 0.0}
    frames = 0
    clock = time.process_time
    for p in logs:
        t0 = clock()
        with can.BLFReader(p) as r:
            n = sum(1 for _ in r)
        t1 = clock()
        fr = read_frames(p)
        t2 = clock()
        runs = frames_to_runs(fr, cfg, str(p))
        t3 = clock()
        for a, run in runs.items():
            _features(cfg, "M", "x", a, run, 0.0)
        t4 = clock()
        frames += n
        for k, d in zip(t, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
            t[k] += d
    store = Path(tempfile.mkdtemp(prefix="ddh_stages_"))
    try:
        Store(store, create=True)
        t0 = clock()
        ingest_batch([IngestJob(str(p), str(store)) for p in logs])
        t["whole ingestion (batch)"] = clock() - t0
    finally:
        shutil.rmtree(store, ignore_errors=True)
    return {"frames": frames, "logs": len(logs),
            **{f"{k} (frames per CPU second)": round(frames / v) for k, v in t.items()},
            "whole ingestion (CPU ms per log)": round(1e3 * t["whole ingestion (batch)"]
                                                      / len(logs), 1)}


def same_cause(named: str, true: str) -> bool:
    """The pressure scale's two readings (pump leakage, torque gain) name one cause."""
    return named == true or {named, true} <= set(PRESSURE_SCALE)


def score(trends, truth: dict, days: int) -> dict:
    start = START_DATE.timestamp()
    out = {"wearing": [], "false_alarms": 0}
    for tr in trends:
        m = truth["machines"][tr.machine]
        wear = m["wear"]
        is_worn = wear is not None and wear["actuator"] == tr.actuator
        episodes, prev = [], None
        for a in tr.alarms:
            if a is not None and prev is None:
                episodes.append(a)
            prev = a
        if not is_worn:
            out["false_alarms"] += len(episodes)
            continue
        cause = wear["effect"]
        right = [a for a in episodes if same_cause(a.cause, cause)]
        out["false_alarms"] += len(episodes) - len(right)
        # the true crossing: the expected error at the true parameter on that day's work
        fits = tr.series.get(cause, [])
        crossing = None
        for i, f in enumerate(fits):
            day = int(round((f.time_s - start) / DAY_S))
            true_value = m["effects_per_day"][day][tr.actuator].get(
                cause, 1.0 if cause == "pump_leakage" else 0.0)
            if expected_error_mm(fits[max(0, i - 2):i + 1], float(to_u(cause, true_value))) \
                    > TOLERANCE_MM:
                crossing = day
                break
        first = right[0] if right else None
        first_day = None if first is None else int(round((first.time_s - start) / DAY_S))
        out["wearing"].append({
            "machine": tr.machine, "actuator": tr.actuator, "cause": cause,
            "onset_day": wear["start_day"], "crossing_day": crossing, "first_alarm_day":
            first_day, "named_cause": first.cause if first else
            (episodes[0].cause if episodes else None),
            "warning_days": None if crossing is None or first_day is None
            else crossing - first_day})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machines", type=int, default=20)
    ap.add_argument("--days", type=int, default=30)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--log-s", type=float, default=30.0, help="work logged per day (s)")
    ap.add_argument("--work-s", type=float, default=0.0,
                    help="a day's work the daemon's summaries see (s; 0: logs only)")
    ap.add_argument("--part", type=int, nargs=2, default=None, metavar=("I", "N"),
                    help="only simulate every N-th missing day from the I-th, then stop")
    ap.add_argument("--logs", default="/tmp/ddh_fleet_bench/logs")
    ap.add_argument("--work", default="/tmp/ddh_fleet_bench")
    ap.add_argument("--no-simulate", action="store_true",
                    help="use the days already simulated in --logs")
    ap.add_argument("--ingest-only", type=int, default=0, metavar="ROUNDS",
                    help="only measure ingestion: ROUNDS alternations of 1 and 2 workers "
                         "(writes bench/results/fleet_ingest.json)")
    ap.add_argument("--rescore", action="store_true",
                    help="only recompute trends and alarms from the analysed store in --work "
                         "(keeps the other figures of bench/results/fleet.json)")
    args = ap.parse_args()
    cfg = load_config(None)
    plan = plan_fleet(cfg, args.machines, args.days, args.seed, args.log_s,
                      work_s=args.work_s)
    logs_dir, work = Path(args.logs), Path(args.work)
    present = {p.name for p in logs_dir.glob("*.blf")} if logs_dir.is_dir() else set()

    def done(m, d: int) -> bool:
        return log_name(m.name, d) in present and (
            not args.work_s or (logs_dir / day_summary_name(m.name, d)).is_file())

    missing = [d for d in range(args.days) if not all(done(m, d) for m in plan.machines)]
    if args.part:
        missing = missing[args.part[0]::args.part[1]]
    if missing and not args.no_simulate:
        started = time.perf_counter()
        summarise = None
        if args.work_s:
            def summarise(machine: str, _day: int, sessions: list) -> None:
                summarise_runs(cfg, machine, sessions, logs_dir)
        simulate_fleet(cfg, plan, logs_dir, days=missing, days_per_batch=5,
                       progress=lambda f: print(f"simulate {100 * f:.0f} %", flush=True),
                       summarise=summarise)
        print(f"simulated {len(missing)} days in {time.perf_counter() - started:.0f} s")
    if args.part:
        return
    truth = json.loads((logs_dir / "truth.json").read_text())
    logs = sorted(logs_dir.glob("*.blf"))
    days = len({p.name.split("_")[1] for p in logs})
    if args.ingest_only:
        runs = [ingest(logs, work / f"ingest{w}", w) for _ in range(args.ingest_only)
                for w in (1, 2)]
        publish("fleet_ingest", {"logs": f"{len(logs)} logs of {plan.log_s:g} s",
                                 "cores": os.cpu_count(), "runs": runs,
                                 "scaling 1 -> 2 workers (per round)": [
                                     round(a["wall_s"] / b["wall_s"], 2)
                                     for a, b in zip(runs[::2], runs[1::2])]})
        return
    if args.rescore:
        old = json.loads((Path(__file__).parent / "results" / "fleet.json").read_text())
        figures = old["figures"]
        figures.update(alarms(cfg, Store(work / "store2"), truth, args.machines, days, work))
        figures["seed"] = args.seed
        figures["alarms rescored with the current trend settings"] = True
        publish("fleet", figures)
        return
    load = os.getloadavg()
    figures: dict[str, object] = {
        "seed": args.seed,
        "fleet": f"{args.machines} machines x {days} days ({len(logs)} logs of "
                 f"{plan.log_s:g} s)", "load average at start (1/5/15 min)":
        [round(x, 1) for x in load], "cores": os.cpu_count()}
    figures["stages, one process, 16 logs (CPU time)"] = stages(logs[:16], cfg)
    runs = [ingest(logs, work / f"store{w}", w) for w in (1, 2)]
    figures["ingestion"] = runs
    figures["scaling 1 -> 2 workers"] = round(runs[0]["wall_s"] / runs[1]["wall_s"], 2)
    name = "fleet"
    if args.work_s:
        name = "fleet_summaries"
        summaries = sorted(logs_dir.glob("*.summary.json"))
        sizes = [p.stat().st_size for p in summaries]
        figures["summaries"] = f"{len(summaries)} machine-days of {plan.sessions} x " \
            f"{plan.log_s:g} s of work"
        figures["summary bytes per machine-day (median, max)"] = [
            int(sorted(sizes)[len(sizes) // 2]), max(sizes)]
        figures["summary bytes per machine-day gzipped (median)"] = sorted(
            len(gzip.compress(p.read_bytes())) for p in summaries)[len(summaries) // 2]
        figures["ingestion of summaries"] = [ingest(summaries, work / f"summaries{w}", w)
                                             for w in (1, 2)]
        ingest_into(summaries, work / "store2")   # the analysis': the logs and summaries
    store = Store(work / "store2")
    machines = sorted(store.machine_logs())
    with dask_client(None, 2) as client:
        started = time.perf_counter()
        run_tasks(client, analyse_machine, [(str(store.root), m, None) for m in machines])
        figures["analysis on 2 workers (s)"] = round(time.perf_counter() - started, 1)
    figures.update(alarms(cfg, store, truth, args.machines, days, work))
    publish(name, figures)


def ingest_into(files: list[Path], store: Path) -> None:
    """``files`` into an existing store (what is there already stays)."""
    jobs = [IngestJob(str(p), str(store), None, DEFAULT_NAME_PATTERN) for p in files]
    with dask_client(None, 2) as client:
        run_batched(client, ingest_batch, jobs)


def alarms(cfg, store: Store, truth: dict, n_machines: int, days: int, work: Path) -> dict:
    """Trends, the report and the alarm figures against the truth."""
    machines = sorted(store.machine_logs())
    figures: dict[str, object] = {}
    rows = store.query("SELECT * FROM fits").to_pylist()
    trends = [unit_trend(m, a, [r for r in rows if r["machine"] == m and r["actuator"] == a],
                         TOLERANCE_MM, HORIZON_DAYS) for m in machines for a in cfg.can.units]
    meta = store.counts()
    meta["rejected"] = len(store.rejected())
    write_report(trends, work / "report.html", TOLERANCE_MM, HORIZON_DAYS, cfg, meta)
    s = score(trends, truth, days)
    months = n_machines * days / 30.0
    figures["wearing units"] = s["wearing"]
    crossed = [w for w in s["wearing"] if w["crossing_day"] is not None]
    right = sum(same_cause(w["named_cause"] or "", w["cause"]) for w in s["wearing"])
    figures["wearing flagged with the right cause"] = f"{right}/{len(s['wearing'])}"
    figures["crossed tolerance within the days"] = f"{len(crossed)}/{len(s['wearing'])}"
    figures["flagged >= 7 days before crossing"] = \
        f"{sum((w['warning_days'] or -99) >= 7 for w in crossed)}/{len(crossed)}"
    figures["warning days (crossed)"] = [w["warning_days"] for w in crossed]
    figures["false alarms"] = s["false_alarms"]
    figures["false alarms per 20 machine-months"] = round(20 * s["false_alarms"] / months, 2)
    figures["tolerance / horizon"] = f"{TOLERANCE_MM} mm / {HORIZON_DAYS} days"
    figures["report"] = str(work / "report.html")
    return figures


if __name__ == "__main__":
    main()
