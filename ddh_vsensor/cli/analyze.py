"""``ddh-vsensor analyze``: where the model fails on measured runs, why, and the extended model.

Runs are CSVs of the measured-data format or CAN logs of one actuator. The report directory
gets report.json, report.html (figures embedded), breakdown.json and extension.json (the
extended model, for ``estimate --extension``).
"""

from __future__ import annotations

import argparse
import json

from ddh_vsensor.atomic import output_dir
from ddh_vsensor.cli.common import add_actuator_arg, add_config_arg, config_from
from ddh_vsensor.cli.progress import ProgressBar
from ddh_vsensor.errors import UserError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "analyze", help="diagnose the model on measured runs: what is wrong, why, the fix",
        description="Compares the estimate with the reference position of each run, breaks "
                    "the error down by motion phase, direction, load, speed and temperature, "
                    "fits each candidate cause (a physical extension of the model, the "
                    "sensors included) and sets of up to three jointly, judges them on runs "
                    "left out of the fit, names a set only if each cause adds a resolved "
                    "gain, says which causes the runs cannot tell apart, answers "
                    "'unexplained' (with a residual model) when nothing in the catalogue "
                    "fits, and saves the extended model.")
    p.add_argument("runs", nargs="+", metavar="RUN",
                   help="measured runs of one actuator: CSV (measured-data format) or CAN log; "
                        "at least two")
    add_config_arg(p)
    add_actuator_arg(p)
    p.add_argument("--mode", choices=("dynamic", "full", "paper"), default=None,
                   help="estimator mode to diagnose (default: the config's)")
    p.add_argument("--report", required=True, metavar="DIR", help="report directory")
    p.add_argument("--json", action="store_true", help="print report.json to stdout")
    p.add_argument("--truth", choices=("auto", "position", "references"), default="auto",
                   help="what the estimate is compared with: the reference position, or the "
                        "Hall edges and holds (auto: references when no run has a position)")
    p.add_argument("--baseline", metavar="FILE", default=None,
                   help="the machine's baseline written by 'ddh-vsensor commission' "
                        "(MACHINE.baseline.json): the model's own error is judged against it "
                        "for this unit (default: the simulator's thresholds)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from ddh_vsensor.diagnosis.analyze import diagnose
    from ddh_vsensor.diagnosis.report import prepare_report_dir, write_report
    from ddh_vsensor.diagnosis.runs import load_analysis_run
    from ddh_vsensor.diagnosis.selection import separation
    from ddh_vsensor.diagnosis.workbench import resolve_mode

    cfg = config_from(args)
    mode = resolve_mode(cfg, args.mode)
    own = None
    if args.baseline is not None:
        from ddh_vsensor.commission.baseline import for_analysis
        own = for_analysis(args.baseline, cfg, args.actuator, mode)
    if args.truth != "position":
        from ddh_vsensor.cli.analyze_references import lacks_position, read_any, run_references
        raw = [read_any(path, args.actuator, cfg) for path in args.runs]
        if args.truth == "references" or lacks_position(raw):
            output_dir(args.report, "report directory")
            return run_references(args, cfg, mode, raw, own)
    runs = [load_analysis_run(path, args.actuator, cfg) for path in args.runs]
    if own is not None and own.position_rms_mm is None:
        raise UserError(f"{args.baseline}: no position residuals of the {args.actuator} in "
                        "the baseline: commission it with the draw-wire logged")
    prepare_report_dir(args.report)
    bar = ProgressBar("analyze")
    diag = diagnose(cfg, args.actuator, runs, mode,
                    progress=lambda stage, f: bar.update(f, stage), own=own)
    data = write_report(diag, args.report, cfg.physics_hash())
    # a none with causes the runs could not show is not "the machine is fine"
    said = ("none observable" if diag.cause == "none" and diag.not_observable
            else diag.cause)
    bar.close(f"cause: {said}")
    if args.json:
        print(json.dumps(data, indent=2))
        return 0
    b, e = data["baseline"], data["extended"]
    print(f"{args.actuator} ({mode} mode), {len(runs)} runs: cause {said}")
    print(f"  {diag.decision.reason}")
    print(f"  {diag.thresholds.describe()}")
    for c in data["causes"]:
        params = ", ".join(f"{k}={v:.4g} (90 %: {lo:.4g}..{hi:.4g})"
                           for (k, v), (lo, hi) in zip(c["parameters"].items(),
                                                       c["interval"].values()))
        print(f"  + {c['cause']:<17} share {c['share']:.3f}  {params}")
    for a, b in data["ambiguous"]:
        print(f"  ? {a} or {b}: to tell them apart, {separation(a, b)}")
    for item in data["ranking"]:
        params = ", ".join(f"{k}={v:.4g}" for k, v in item["parameters"].items())
        print(f"  {item['cause']:<18} score {item['score']:+.3f}  {params}")
    print(f"  held-out max |error| {b['max_abs_error_mm']:.2f} -> {e['max_abs_error_mm']:.2f} mm,"
          f" RMS {b['rms_error_mm']:.2f} -> {e['rms_error_mm']:.2f} mm")
    print(f"  report: {args.report}/report.html; extension: {data['extension_file']}")
    return 0
