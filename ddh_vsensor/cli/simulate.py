"""``ddh-vsensor simulate``: a simulated measured run of both units (CSV per unit + BLF)."""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

from ..errors import UserError
from ..sim.control import PIDSettings
from ..sim.effects import EFFECTS, build_effects, describe
from ..sim.run import DEFAULT_STEP_S, RunSpec, simulate, write_run_dir
from ..sim.sensors import SensorSettings
from .common import add_config_arg, config_from
from .progress import ProgressBar


def register(sub: argparse._SubParsersAction) -> None:
    # argparse %-formats help strings: the effects' own text may contain '%'
    effects = "; ".join(f"{e.name} ({e.parameter}, {e.allowed})"
                        for e in EFFECTS.values()).replace("%", "%%")
    p = sub.add_parser(
        "simulate", help="simulate a work cycle of both units: boom.csv, bucket.csv, run.blf",
        description="Time-domain simulation of both DDH units under PID position control. "
                    "Writes DIR/boom.csv, DIR/bucket.csv (measured-data format) and DIR/run.blf.")
    add_config_arg(p)
    p.add_argument("--cycle", required=True, metavar="paper|FILE.csv",
                   help="'paper' (the paper's work cycle) or a CSV setpoint profile with "
                        "columns time_s, boom_mm, bucket_mm")
    p.add_argument("--speed", type=int, default=4, help="paper cycle speed level 1..4 "
                   "(4 = fastest, about 25 s; default 4)")
    p.add_argument("--payload-kg", type=float, required=True)
    p.add_argument("--oil-temp-c", type=float, required=True, help="oil temperature at start")
    p.add_argument("--cycles", type=int, default=1, help="repeat the cycle N times (default 1)")
    p.add_argument("--effect", action="append", default=[], metavar="[UNIT.]NAME=VALUE",
                   help=f"plant effect, repeatable; applies to every unit unless prefixed "
                        f"with a unit's name and a dot. Effects: {effects}")
    p.add_argument("--seed", type=int, default=0, help="seed of the sensor noise (default 0)")
    p.add_argument("--rate-hz", type=float, default=100.0, help="sample rate (default 100)")
    p.add_argument("--step-s", type=float, default=DEFAULT_STEP_S,
                   help=f"simulation step (default {DEFAULT_STEP_S:g})")
    p.add_argument("--oil-temp-drift", type=float, default=SensorSettings().oil_temp_drift_c_per_s,
                   metavar="DEGC_PER_S", help="oil warm-up rate (default %(default)s degC/s)")
    p.add_argument("--no-blf", action="store_true", help="write the CSV files only")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    cfg = config_from(args)
    if args.cycle != "paper" and not Path(args.cycle).is_file():
        raise UserError(f"--cycle {args.cycle}: neither 'paper' nor a readable profile file")
    if not -1.0 <= args.oil_temp_drift <= 1.0:
        raise UserError(f"--oil-temp-drift {args.oil_temp_drift}: outside -1..1 degC/s")
    effects = build_effects(args.effect, cfg.unit_names)
    spec = RunSpec(cycle="paper" if args.cycle == "paper" else Path(args.cycle),
                   speed=args.speed, payload_kg=args.payload_kg, oil_temp_c=args.oil_temp_c,
                   cycles=args.cycles, effects=effects, seed=args.seed, step_s=args.step_s,
                   sensors=replace(SensorSettings(), rate_hz=args.rate_hz,
                                   oil_temp_drift_c_per_s=args.oil_temp_drift),
                   controller=PIDSettings())
    bar = ProgressBar("simulate")
    started = time.monotonic()
    runs = simulate(cfg, spec, progress=bar.update)
    wall = time.monotonic() - started
    duration = float(next(iter(runs.values())).time_s[-1])
    bar.close(f"{duration:.1f} s simulated, {duration / max(wall, 1e-9):.0f}x real time")
    written = write_run_dir(cfg, runs, args.out, blf=not args.no_blf)
    for path in written:
        print(path)
    print(f"effects: {describe(effects)}", file=sys.stderr)
    return 0
