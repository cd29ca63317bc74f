"""``ddh-vsensor estimate``: run the estimator over a measured run and score it."""

from __future__ import annotations

import argparse
import json

import numpy as np

from ddh_vsensor.config import Config
from ddh_vsensor.errors import UserError
from ddh_vsensor.estimator.accuracy import accuracy
from ddh_vsensor.estimator.estimator import Estimator, RunEstimate
from ddh_vsensor.measured import Run
from ddh_vsensor.io.csv import write_csv
from ddh_vsensor.io.reader import read_run
from ddh_vsensor.atomic import output_file
from ddh_vsensor.cli.common import (add_actuator_arg, add_config_arg, config_from, figure_path,
                                    load_tables_for)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("estimate", help="estimate positions over a measured run (CSV or CAN log)")
    p.add_argument("run", metavar="RUN", help="CSV of the measured-data format, or a CAN log")
    add_config_arg(p)
    add_actuator_arg(p)
    p.add_argument("--mode", choices=("full", "paper", "dynamic", "kalman"), default=None,
                   help="estimator mode (default: the config's); kalman: the Kalman filter on "
                        "the unit's own model, offline only, its uncertainty from the "
                        "configuration's tolerances")
    p.add_argument("--tables", metavar="DIR", help="table set (default: built from --config)")
    p.add_argument("--no-references", action="store_true", help="ignore the Hall switches")
    p.add_argument("--no-adaptation", action="store_true", help="do not learn at references")
    p.add_argument("--initial-position-mm", type=float, default=None,
                   help="start here (default: the run's first measured position; without "
                        "one the estimate is not referenced until its first Hall switch)")
    p.add_argument("--extension", metavar="FILE",
                   help="extended model saved by 'ddh-vsensor analyze' (its extension.json)")
    p.add_argument("--out", metavar="EST.csv", help="write the estimate")
    p.add_argument("--plot", metavar="FILE.png", help="the paper's Figures 6/8")
    p.add_argument("--json", action="store_true", help="print the errors as JSON")
    p.set_defaults(func=_run)


def initial_position(run: Run, given: float | None) -> float | None:
    """Where the rod starts: as given, else the run's first measured position, else not
    known (a log without position frames)."""
    if given is not None:
        return given
    known = run.position_mm[np.isfinite(run.position_mm)]
    return float(known[0]) if known.size else None


def estimate_run(args: argparse.Namespace, cfg: Config, run: Run,
                 actuator: str) -> tuple[str, RunEstimate]:
    """The mode and the result for one run, as the CLI options say."""
    if (args.mode or cfg.estimator.mode) == "kalman":
        return "kalman", _kalman(args, cfg, run, actuator)
    extension = None
    if getattr(args, "extension", None):
        from ddh_vsensor.estimator.extension import Extension
        extension = Extension.load(args.extension, cfg, actuator)
    tables = (load_tables_for(args, cfg, actuator)
              if extension is None or not extension.changes_tables() else None)
    options = dict(mode=args.mode, references=not args.no_references,
                   adaptation=False if args.no_adaptation else None,
                   initial_position_mm=initial_position(run, args.initial_position_mm))
    est = (Estimator(cfg, actuator, tables, **options) if extension is None
           else extension.estimator(cfg, tables, **options))
    refs = None if args.no_references else run.refs
    return est.model.mode, est.run(run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c,
                                   refs, None if args.no_references else run.ref_edge_s)


def _kalman(args: argparse.Namespace, cfg: Config, run: Run, actuator: str) -> RunEstimate:
    """The Kalman filter over the run: it predicts with the unit's own model, so it takes no
    table set, extension or learnt gains."""
    from ddh_vsensor.estimator import kalman
    return kalman.run(cfg, actuator, run, references=not args.no_references,
                      initial_position_mm=initial_position(run, args.initial_position_mm),
                      settings=kalman.settings_from_config(cfg))


def _run(args: argparse.Namespace) -> int:
    given = [name for name, value in (("--tables", args.tables), ("--extension", args.extension),
                                      ("--no-adaptation", args.no_adaptation)) if value]
    cfg = config_from(args)
    if (args.mode or cfg.estimator.mode) == "kalman" and given:
        raise UserError(f"{', '.join(given)}: not for the kalman mode (it predicts with the "
                        "unit's own model and learns nothing between runs)")
    if args.out:
        output_file(args.out, "estimate")
    if args.plot:
        figure_path(args.plot, "plot")
    run = read_run(args.run, cfg, args.actuator)
    if not (args.out or args.plot) and not np.isfinite(run.position_mm).any():
        raise UserError(f"{args.run}: no reference position (position_mm) to score the "
                        "estimate against; --out writes the estimate without a score")
    mode, res = estimate_run(args, cfg, run, args.actuator)
    score = accuracy(res.position_mm, run.position_mm)
    if args.out:
        write_csv(args.out, Run(
            time_s=run.time_s, speed_rpm=run.speed_rpm, torque_nm=run.torque_nm,
            oil_temp_c=run.oil_temp_c, position_mm=res.position_mm,
            comments=[f"ddh-vsensor estimate of {args.run} ({args.actuator}, mode "
                      f"{mode}); position_mm is the estimate",
                      "extra columns: uncertainty_mm, flags, reference_mm (the run's own)"],
            source=args.out), extra={"uncertainty_mm": res.uncertainty_mm,
                                     "flags": res.flags.astype(float),
                                     "reference_mm": run.position_mm})
    if args.plot:
        from ddh_vsensor.estimator.plot import plot_estimate
        plot_estimate(run.time_s, run.position_mm, res.position_mm, res.uncertainty_mm,
                      f"{args.actuator}, {mode} mode: {args.run}", args.plot)
    if score is None:
        if args.json:
            print(json.dumps({"max_abs_error_mm": None, "rms_error_mm": None,
                              "final_error_mm": None}))
        else:
            print(f"final position {res.position_mm[-1]:.2f} mm (the run has no reference "
                  "position to score against)")
        return 0
    if args.json:
        print(json.dumps(score.as_dict()))
    else:
        print(f"{args.actuator} ({mode}): max |error| {score.max_abs_error_mm:.2f} mm,"
              f" RMS {score.rms_error_mm:.2f} mm, final {score.final_error_mm:+.2f} mm over "
              f"{score.samples} samples; {len(res.events)} reference events")
    return 0
