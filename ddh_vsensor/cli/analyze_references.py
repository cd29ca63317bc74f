"""``analyze --truth references``: the diagnosis from Hall edges and holds (no position)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ddh_vsensor.config import Config
from ddh_vsensor.diagnosis.selection import OwnError
from ddh_vsensor.errors import UserError
from ddh_vsensor.measured import Run
from ddh_vsensor.io.csv import read_csv
from ddh_vsensor.cli.progress import ProgressBar


def read_any(path: str, actuator: str, cfg: Config) -> Run:
    """A CSV of the measured-data format or a CAN log, position optional."""
    if path.lower().endswith(".csv"):
        return read_csv(path, actuator=actuator)
    from ddh_vsensor.io.log import read_can_log
    return read_can_log(path, actuator, cfg)


def lacks_position(runs: list[Run]) -> bool:
    """No run has a reference position (a mix is an error of the runs without one)."""
    return all(not (r.position_mm == r.position_mm).any() for r in runs)


def run_references(args: argparse.Namespace, cfg: Config, mode: str,
                   runs: list[Run], own: OwnError | None = None) -> int:
    from ddh_vsensor.diagnosis.reference_fit import diagnose_references
    from ddh_vsensor.diagnosis.reference_report import write_reference_report
    from ddh_vsensor.diagnosis.references import reference_run

    if own is not None and own.references_rms_mm is None and own.holds_rms_mm is None:
        raise UserError(f"{args.baseline}: no reference or hold residuals of the "
                        f"{args.actuator} in the baseline: commission it with runs that pass "
                        "its Hall switches")
    rruns = [reference_run(cfg, args.actuator, r) for r in runs]
    bar = ProgressBar("analyze")
    diag = diagnose_references(cfg, args.actuator, rruns, mode,
                               progress=lambda stage, f: bar.update(f, stage), own=own)
    data = write_reference_report(diag, args.report, cfg.physics_hash())
    # a none with causes the runs could not show is not "the machine is fine"
    said = ("none observable" if diag.cause == "none" and diag.not_observable
            else diag.cause)
    bar.close(f"cause: {said}")
    if args.json:
        print(json.dumps(data, indent=2))
        return 0
    b, e = data["baseline"], data["extended"]
    print(f"{args.actuator} ({mode} mode), {len(runs)} runs, {data['references']} reference "
          f"increments, {data['holds']} holds: cause {said}")
    print(f"  {diag.decision.reason}")
    print(f"  {diag.thresholds.describe()}")
    for item in data["causes"]:
        params = ", ".join(f"{k}={v:.4g}" for k, v in item["parameters"].items())
        ivs = ", ".join(f"[{lo:.4g}, {hi:.4g}]" for lo, hi in item["interval"].values())
        print(f"  {item['cause']:<18} score {item['score']:+.3f}  {params} {ivs}")
    print(f"  held-out max |error| at the references {b['max_abs_error_mm']:.2f} -> "
          f"{e['max_abs_error_mm']:.2f} mm")
    print(f"  report: {Path(args.report) / 'report.html'}; extension: {data['extension_file']}")
    return 0
