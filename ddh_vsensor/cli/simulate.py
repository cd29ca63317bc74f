"""``ddh-vsensor simulate``: a simulated measured run of every unit (CSV per unit + BLF)."""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

from ddh_vsensor.config import Config
from ddh_vsensor.errors import UserError
from ddh_vsensor.sim.control import PIDSettings
from ddh_vsensor.commission.programme import CALIBRATION, calibration_cycle
from ddh_vsensor.sim.cycles import RANDOM, WORK, Profile, cycle_names, random_cycle, require_cycle
from ddh_vsensor.sim.effects import EFFECTS, build_effects, describe
from ddh_vsensor.sim.run import DEFAULT_STEP_S, RunSpec, simulate, write_run_dir
from ddh_vsensor.sim.sensors import SensorSettings
from ddh_vsensor.atomic import output_dir
from ddh_vsensor.cli.common import add_config_arg, config_from
from ddh_vsensor.cli.progress import ProgressBar


def register(sub: argparse._SubParsersAction) -> None:
    # argparse %-formats help strings: the effects' own text may contain '%'
    effects = "; ".join(f"{e.name} ({e.parameter}, {e.allowed})"
                        for e in EFFECTS.values()).replace("%", "%%")
    p = sub.add_parser(
        "simulate", help="simulate a work cycle of every unit: UNIT.csv per unit, run.blf",
        description="Time-domain simulation of the machine's DDH units under PID position "
                    "control. Writes DIR/UNIT.csv per unit (measured-data format) and "
                    "DIR/run.blf.")
    add_config_arg(p)
    p.add_argument("--cycle", required=True, metavar="NAME|random|calibration|FILE.csv",
                   help="'work' (the machine's typical cycle: the first of its configuration's "
                        "work_cycle.cycles), a cycle's name (reference loader: paper, "
                        "dig-dump), 'random' (random work, --duration-s long, seeded by "
                        "--seed), 'calibration' (one run of the commissioning programme: the "
                        "typical cycle at every speed, each unit swept and held; about 7 "
                        "minutes) or a CSV setpoint profile with columns time_s and UNIT_mm per "
                        "unit")
    p.add_argument("--speed", type=int, default=4, help="speed level 1..4 of a named cycle: "
                   "N/4 of the units' travel speeds (4 = fastest; reference loader's paper "
                   "cycle about 25 s; default 4)")
    p.add_argument("--duration-s", type=float, default=60.0,
                   help="length of a random cycle (default 60)")
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


def _cycle(cfg: Config, args: argparse.Namespace) -> str | Path | Profile:
    """``--cycle`` as a RunSpec's cycle: a configured name, random work or a profile file."""
    if args.cycle == CALIBRATION:
        return calibration_cycle(cfg)
    if args.cycle == RANDOM:
        if not 5.0 <= args.duration_s <= 86400.0:
            raise UserError(f"--duration-s {args.duration_s:g}: a random cycle lasts 5..86400 s")
        return random_cycle(cfg, args.seed, args.duration_s)
    if args.cycle == WORK or args.cycle in cycle_names(cfg):
        return require_cycle(cfg, args.cycle)
    if Path(args.cycle).is_file():
        try:
            Path(args.cycle).read_text(encoding="utf-8")
        except UnicodeDecodeError as exc:
            raise UserError(f"--cycle {args.cycle}: not UTF-8 text ({exc.reason} at byte "
                            f"{exc.start}), not a profile CSV") from None
        return Path(args.cycle)
    names = ", ".join((WORK,) + cycle_names(cfg) + (RANDOM, CALIBRATION))
    raise UserError(f"--cycle {args.cycle}: neither a cycle of this machine ({names}) nor a "
                    "readable profile file")


def _run(args: argparse.Namespace) -> int:
    cfg = config_from(args)
    cycle = _cycle(cfg, args)
    if not -1.0 <= args.oil_temp_drift <= 1.0:
        raise UserError(f"--oil-temp-drift {args.oil_temp_drift}: outside -1..1 degC/s")
    effects = build_effects(args.effect, cfg.unit_names)
    spec = RunSpec(cycle=cycle,
                   speed=args.speed, payload_kg=args.payload_kg, oil_temp_c=args.oil_temp_c,
                   cycles=args.cycles, effects=effects, seed=args.seed, step_s=args.step_s,
                   sensors=replace(SensorSettings(), rate_hz=args.rate_hz,
                                   oil_temp_drift_c_per_s=args.oil_temp_drift),
                   controller=PIDSettings())
    output_dir(args.out, create=False)       # made when written, the other inputs checked
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
