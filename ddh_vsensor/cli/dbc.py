"""``ddh-vsensor dbc``: the machine's frame layout as a DBC, generated from its configuration."""

from __future__ import annotations

import argparse

import cantools

from ddh_vsensor.atomic import atomic_path, output_file
from ddh_vsensor.errors import UserError
from ddh_vsensor.cli.common import add_config_arg, config_from


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("dbc", help="write the DBC of every frame the machine's daemon reads "
                                   "or writes",
                       description="Frame IDs, names, lengths and Hall bit signals follow the "
                       "configuration (can: section); the shipped dbc/ddh_vsensor.dbc is this "
                       "command's output for the reference loader.")
    add_config_arg(p)
    p.add_argument("--out", metavar="FILE.dbc", required=True,
                   help="where to write the DBC (replaced whole, never half-written)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from ddh_vsensor.canbus.layout import machine_database
    from ddh_vsensor.diagnosis.causes import CAUSE_NAMES
    cfg = config_from(args)
    output_file(args.out, "DBC")
    db = machine_database(cfg, CAUSE_NAMES)     # the health frame's cause value table
    try:
        with atomic_path(args.out) as tmp:
            cantools.database.dump_file(db, str(tmp), database_format="dbc")
    except OSError as exc:
        raise UserError(f"{args.out}: cannot write: {exc.strerror or exc}") from None
    print(f"{args.out}: {len(db.messages)} frames of {len(cfg.unit_names)} unit(s) "
          f"({', '.join(cfg.unit_names)})")
    return 0
