"""``ddh-vsensor eds``: one unit's emulated CiA 406 sensor as an EDS, from the configuration."""

from __future__ import annotations

import argparse
from pathlib import Path

from ddh_vsensor.atomic import atomic_write, output_file
from ddh_vsensor.errors import UserError
from ddh_vsensor.cli.common import add_config_arg, config_from


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eds", help="write the EDS of one unit's emulated position sensor",
                       description="The packaged CiA 406 template with the unit's measuring "
                       "step, stroke, TPDO1 event timer, EMCY setting, identity and consumer "
                       "heartbeat time from the configuration; loadable by canopen and any "
                       "CANopen master. An --out ending in .dcf writes the unit's DCF: the "
                       "same with its node ID (DeviceComissioning).")
    add_config_arg(p)
    p.add_argument("--unit", metavar="UNIT", required=True,
                   help="which unit of the configured machine")
    p.add_argument("--out", metavar="FILE.eds", required=True,
                   help="where to write the EDS (replaced whole, never half-written)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from ddh_vsensor.canbus.eds import write_unit_eds
    cfg = config_from(args)
    unit = cfg.require_unit(args.unit)
    output_file(args.out, "EDS")
    try:
        with atomic_write(args.out) as fh:
            write_unit_eds(cfg, unit, fh, Path(args.out).name)
    except OSError as exc:
        raise UserError(f"{args.out}: cannot write: {exc.strerror or exc}") from None
    print(f"{args.out}: sensor of the {unit}, node {cfg.can.units[unit].sensor_node_id}")
    return 0
