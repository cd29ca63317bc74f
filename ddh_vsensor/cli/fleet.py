"""``ddh-vsensor fleet ingest|report`` and ``ddh-vsensor simulate fleet``: CAN logs and the
daemons' day summaries of many machines into a Parquet store, analysed per machine on Dask,
trends and alarms in HTML.

Needs the ``fleet`` extra (dask[distributed], pyarrow, duckdb).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ddh_vsensor.atomic import output_dir, output_file
from ddh_vsensor.errors import UserError
from ddh_vsensor.cli.common import add_config_arg
from ddh_vsensor.cli.progress import ProgressBar

DEFAULT_WORKER_TIMEOUT_S = 30.0

LOG_SUFFIXES = (".blf", ".asc", ".log", ".trc", ".csv")
SUMMARY_SUFFIX = ".summary.json"          # a daemon's day (estimator.day_samples.SUFFIX)
FLEET_EXTRA = ("dask.distributed", "pyarrow", "duckdb")


def require_fleet_extra() -> None:
    """The fleet tools' libraries, or one line saying how to install them."""
    import importlib
    for name in FLEET_EXTRA:
        try:
            importlib.import_module(name)
        except ImportError:
            raise UserError(f"needs {name.split('.')[0]}, part of the fleet extra: "
                            'pip install "ddh-vsensor[fleet]"') from None


def _cluster_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="an existing Dask scheduler (tcp://host:port); default: a local "
                        "cluster on 127.0.0.1")
    p.add_argument("--workers", type=int, default=2,
                   help="worker processes of the local cluster (default 2)")
    p.add_argument("--worker-timeout-s", type=float, default=DEFAULT_WORKER_TIMEOUT_S,
                   metavar="S", help="with --scheduler: how long to wait for a first worker "
                                     "(default %(default)g s)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fleet", help="fleet diagnosis: ingest CAN logs, report trends/alarms",
                       description="CAN logs of many machines (no position sensor) into a "
                                   "columnar store; per-machine diagnosis from the Hall "
                                   "references and holds; trends and alarms.")
    fs = p.add_subparsers(dest="fleet_command", required=True, metavar="ACTION")
    i = fs.add_parser("ingest", help="extract machine, time, hours, references, holds of logs "
                                     "and the daemons' day summaries into the store "
                                     "(idempotent, resumable)")
    i.add_argument("logs", nargs="+", metavar="FILE",
                   help="CAN logs (BLF), day summaries (*.summary.json) or directories")
    i.add_argument("--store", required=True, metavar="DIR")
    i.add_argument("--name-pattern", default=None, metavar="REGEX",
                   help="regular expression on a log's file name with a group "
                        "(?P<machine>...) and optionally (?P<hours>...) and "
                        "(?P<date>YYYY-MM-DD); default: MACHINE_YYYY-MM-DD_HOURSh.blf (a "
                        "summary names its machine itself)")
    add_config_arg(i)
    _cluster_args(i)
    i.set_defaults(func=_ingest)
    r = fs.add_parser("report", help="per-machine analysis, trends, alarms: HTML report")
    r.add_argument("--store", required=True, metavar="DIR")
    r.add_argument("--out", required=True, metavar="FILE.html")
    r.add_argument("--tolerance-mm", type=float,
                   help="position error that must not be exceeded (default: the "
                   "configuration's health.tolerance_mm, 3 mm unless set)")
    r.add_argument("--horizon-days", type=float,
                   help="alarm when a trend crosses the tolerance within this (default: the "
                   "configuration's health.horizon_days, 14 unless set)")
    add_config_arg(r)
    _cluster_args(r)
    r.set_defaults(func=_report)

    s = sub.add_parser("simulate-fleet", help="simulated fleet of daily CAN logs and day "
                                              "summaries (also: 'simulate fleet')",
                       description="Per machine one BLF per day of varied work, without "
                                   "position frames, and the day summary its daemon would "
                                   "write over the day's whole work; some machines wear; "
                                   "truth.json holds the truth (the analysis never reads "
                                   "it).")
    s.add_argument("--machines", type=int, required=True)
    s.add_argument("--days", type=int, required=True)
    s.add_argument("--out", required=True, metavar="DIR")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--log-s", type=float, default=None, metavar="SECONDS",
                   help="work logged per day (default 60)")
    s.add_argument("--work-s", type=float, default=None, metavar="SECONDS",
                   help="a day's work the summaries see: sessions of --log-s spread over "
                        "the working day, the first the logged one (default 600; 0: no "
                        "summaries)")
    add_config_arg(s)
    s.set_defaults(func=_simulate)


def _expand(items: list[str]) -> list[str]:
    out = []
    for item in items:
        p = Path(item)
        if p.is_dir():
            out += sorted(str(f) for f in p.iterdir() if f.suffix.lower() in LOG_SUFFIXES
                          or f.name.lower().endswith(SUMMARY_SUFFIX))
        elif p.exists():
            out.append(item)
        else:
            raise UserError(f"{item}: no such file or directory")
    if not out:
        raise UserError(f"no logs in {', '.join(items)} (looked for "
                        f"{'/'.join(LOG_SUFFIXES)}/{SUMMARY_SUFFIX} files)")
    return out


def _ingest(args: argparse.Namespace) -> int:
    require_fleet_extra()
    from ddh_vsensor.config import load_config
    from ddh_vsensor.fleet.cluster import dask_client, run_batched
    from ddh_vsensor.fleet.ingest import (DEFAULT_NAME_PATTERN, IngestJob, compile_pattern,
                                          ingest_batch)
    from ddh_vsensor.fleet.store import Store
    pattern = args.name_pattern or DEFAULT_NAME_PATTERN
    compile_pattern(pattern)
    load_config(args.config)                      # a bad config fails here, once
    store = Store(args.store, create=True)
    if store.clean_partial():
        print("removed a crashed ingestion's partial files")
    logs = _expand(args.logs)
    jobs = [IngestJob(str(Path(p).resolve()) if Path(p).exists() else p,
                      str(store.root.resolve()), args.config, pattern) for p in logs]
    bar = ProgressBar("ingest")
    started = time.monotonic()
    with dask_client(args.scheduler, args.workers, args.worker_timeout_s) as client:
        results = run_batched(client, ingest_batch, jobs,
                            lambda d, n, r: bar.update(d / n, Path(r["path"]).name))
    wall = time.monotonic() - started
    counts = {s: sum(r["status"] == s for r in results)
              for s in ("ingested", "present", "rejected")}
    new = [r for r in results if r["status"] == "ingested"]
    frames = sum(r["frames"] for r in new)
    hours = sum(r["duration_s"] for r in new if r["kind"] == "log") / 3600.0
    days = sum(r["kind"] == "summary" for r in new)
    bar.close(f"{counts['ingested']} ingested, {counts['present']} already present, "
              f"{counts['rejected']} rejected")
    for r in results:
        if r["status"] == "rejected":
            print(f"rejected: {r['problem']}")
    rate = 1.0 / max(wall, 1e-9)
    print(f"{frames} frames, {hours:.3f} log-hours, {days} summaries (machine-days) in "
          f"{wall:.1f} s: {frames * rate:.0f} frames/s, {hours * 3600 * rate:.1f} "
          f"log-seconds/s, {days * rate:.1f} machine-days/s")
    if not counts["ingested"] and not counts["present"]:
        raise UserError(f"nothing ingested: {counts['rejected']} file(s) given, every one "
                        "rejected")
    return 0


def _report(args: argparse.Namespace) -> int:
    require_fleet_extra()
    from ddh_vsensor.config import load_config
    from ddh_vsensor.fleet.analysis import analyse_machine
    from ddh_vsensor.fleet.cluster import dask_client, run_tasks
    from ddh_vsensor.fleet.report import write_report
    from ddh_vsensor.fleet.store import Store
    from ddh_vsensor.diagnosis.trend import unit_trend
    for given in (args.tolerance_mm, args.horizon_days):
        if given is not None and not given > 0:
            raise UserError("--tolerance-mm and --horizon-days must be positive")
    out = output_file(args.out, "report")
    cfg = load_config(args.config)
    if args.tolerance_mm is None:
        args.tolerance_mm = cfg.health.tolerance_mm
    if args.horizon_days is None:
        args.horizon_days = cfg.health.horizon_days
    store = Store(args.store)
    machines = sorted(store.machine_logs())
    if not machines:
        raise UserError(f"--store {args.store}: no ingested logs")
    bar = ProgressBar("analyse")
    with dask_client(args.scheduler, args.workers, args.worker_timeout_s) as client:
        run_tasks(client, analyse_machine,
                  [(str(store.root.resolve()), m, args.config) for m in machines],
                  lambda d, n, r: bar.update(d / n, r["machine"]))
    bar.close(f"{len(machines)} machines")
    rows = store.query("SELECT * FROM fits").to_pylist()
    trends = []
    for m in machines:
        for a in cfg.can.units:
            mine = [r for r in rows if r["machine"] == m and r["actuator"] == a]
            if mine:
                trends.append(unit_trend(m, a, mine, args.tolerance_mm, args.horizon_days))
    meta = store.counts()
    meta["rejected"] = len(store.rejected())
    data = write_report(trends, out, args.tolerance_mm, args.horizon_days, cfg, meta,
                        sources={r["log_id"]: r.get("source", "") for r in rows})
    alarms = [u for u in data["units"] if u["alarm"]]
    for u in alarms:
        print(f"ALARM {u['machine']} {u['actuator']}: {u['cause']} {u.get('parameter')}, "
              f"expected error {u['expected_error_mm']} mm, {u['projected_error_mm']} mm in "
              f"{args.horizon_days:g} days; load {u['extension_file']}")
    print(f"{len(data['units'])} units, {len(alarms)} alarms: {out}")
    return 0


def _simulate(args: argparse.Namespace) -> int:
    from ddh_vsensor.config import load_config
    from ddh_vsensor.sim.fleet import LOG_S, WORK_S, plan_fleet, simulate_fleet
    cfg = load_config(args.config)
    output_dir(args.out, create=False)       # made when written, the other inputs checked
    plan = plan_fleet(cfg, args.machines, args.days, args.seed, args.log_s or LOG_S,
                      work_s=WORK_S if args.work_s is None else args.work_s)
    summaries: list[Path] = []
    summarise = None
    if plan.work_s:
        from ddh_vsensor.diagnosis.day_summary import summarise_runs

        def summarise(machine: str, _day: int, sessions: list) -> None:
            summaries.extend(summarise_runs(cfg, machine, sessions, Path(args.out)))

    bar = ProgressBar("simulate fleet")
    written = simulate_fleet(cfg, plan, args.out, progress=bar.update, summarise=summarise)
    bar.close(f"{len(written)} logs, {len(summaries)} summaries")
    what = f" and {len(summaries)} day summaries ({plan.sessions} x {plan.log_s:g} s of work " \
        "each)" if plan.work_s else ""
    print(f"{len(written)} logs{what} and truth.json in {args.out}")
    return 0
