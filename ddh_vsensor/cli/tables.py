"""``ddh-vsensor tables build|plot``: make the movement tables and draw the paper's Figure 5."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ddh_vsensor.tables.build import build_unit_tables
from ddh_vsensor.tables.store import load_tables, save_unit_tables
from ddh_vsensor.atomic import output_dir
from ddh_vsensor.cli.common import add_config_arg, config_from, figure_path
from ddh_vsensor.cli.progress import ProgressBar


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("tables", help="build or plot the movement tables")
    tsub = p.add_subparsers(dest="tables_command", required=True, metavar="ACTION")
    b = tsub.add_parser("build", help="build every unit's tables from the steady state")
    add_config_arg(b)
    b.add_argument("--out", metavar="DIR", default="tables", help="output directory")
    b.set_defaults(func=_build)
    pl = tsub.add_parser("plot", help="movement per motor revolution vs torque (Figure 5)")
    add_config_arg(pl)
    pl.add_argument("--tables", metavar="DIR", default="tables")
    pl.add_argument("--out", metavar="FILE.png", required=True)
    pl.add_argument("--speed-rpm", type=float, default=5000.0,
                    help="motor speed of the curves (default 5000, the paper's maximum)")
    pl.set_defaults(func=_plot)


def _build(args: argparse.Namespace) -> int:
    cfg = config_from(args)
    output_dir(args.out, "tables directory")
    bar = ProgressBar("tables")
    started = time.perf_counter()
    units = cfg.unit_names
    for k, actuator in enumerate(units):
        tables = build_unit_tables(
            cfg, actuator,
            progress=lambda a, f, k=k: bar.update((k + f) / len(units), a))
        path = save_unit_tables(args.out, tables)
        bar.update((k + 1) / len(units), f"{path}")
    bar.close(f"built {', '.join(units)} in {time.perf_counter() - started:.2f} s "
              f"-> {Path(args.out)}")
    return 0


def _plot(args: argparse.Namespace) -> int:
    from ddh_vsensor.tables.plot import plot_figure5     # matplotlib only when plotting
    cfg = config_from(args)
    figure_path(args.out)
    plot_figure5(load_tables(args.tables, cfg), cfg, args.out, speed_rpm=args.speed_rpm)
    print(f"wrote {args.out}")
    return 0
