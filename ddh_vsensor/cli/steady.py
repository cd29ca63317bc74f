"""``ddh-vsensor steady``: one steady operating point of a unit, or its holding speed."""

from __future__ import annotations

import argparse
import json

from ddh_vsensor.errors import UserError
from ddh_vsensor.physics.steady import holding_speed, steady_state
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.cli.common import add_actuator_arg, add_config_arg, config_from


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("steady", help="steady state at a motor speed and load")
    add_config_arg(p)
    add_actuator_arg(p)
    p.add_argument("--speed-rpm", type=float, help="motor speed (+ extends the cylinder)")
    p.add_argument("--load-n", type=float, default=None,
                   help="external load, + pushes the rod in (default: the unit's empty load)")
    p.add_argument("--oil-temp-c", type=float, required=True)
    p.add_argument("--holding-speed", action="store_true",
                   help="instead of a speed: the motor speed that holds the load still")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    cfg = config_from(args)
    unit = DDHUnit.from_config(cfg, args.actuator)
    load = unit.load_force_n(0.0) if args.load_n is None else args.load_n
    if not -40.0 <= args.oil_temp_c <= 150.0:
        raise UserError(f"--oil-temp-c {args.oil_temp_c}: outside -40..150 °C")
    if args.holding_speed:
        h = holding_speed(unit, load, args.oil_temp_c)
        out = {"holding_speed_rpm": h.speed_rpm, "band_low_rpm": h.band_low_rpm,
               "band_high_rpm": h.band_high_rpm}
    else:
        if args.speed_rpm is None:
            raise UserError("give --speed-rpm N (or --holding-speed)")
        limit = unit.motor.speed_limit_rpm
        if abs(args.speed_rpm) > limit:
            raise UserError(f"--speed-rpm {args.speed_rpm}: beyond the motor's ±{limit:g} rpm")
        out = steady_state(unit, args.speed_rpm, load, args.oil_temp_c).report()
    if args.json:
        print(json.dumps(out))
    else:
        width = max(map(len, out))
        for key, value in out.items():
            print(f"{key:<{width}}  {value:12.4f}")
    return 0
