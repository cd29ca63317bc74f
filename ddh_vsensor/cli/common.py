"""Arguments and helpers shared by several subcommands."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from ddh_vsensor.atomic import output_file
from ddh_vsensor.config import Config, load_config

if TYPE_CHECKING:
    from ddh_vsensor.estimator.extension import Extension
    from ddh_vsensor.tables.lookup import UnitTables


def add_config_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE", default=None,
                        help="machine configuration (default: the embedded reference loader)")


def add_actuator_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--actuator", metavar="UNIT", required=True,
                        help="which unit of the configured machine")


def config_from(args: argparse.Namespace) -> Config:
    """The configuration, with a ``--actuator`` argument checked against its units."""
    cfg = load_config(args.config)
    if getattr(args, "actuator", None) is not None:
        cfg.require_unit(args.actuator)
    return cfg


def figure_path(path: str, what: str = "figure") -> Path:
    """A figure's output path, checked before the work: writable, and an extension
    matplotlib writes (it picks the format by it)."""
    from matplotlib.backend_bases import FigureCanvasBase
    suffixes = tuple(sorted(f".{s}" for s in FigureCanvasBase.get_supported_filetypes()))
    return output_file(path, what, suffixes)


def load_tables_for(args: argparse.Namespace, cfg: Config, actuator: str) -> "UnitTables":
    """Tables from ``--tables DIR`` (refused if built for another config), else built now
    from the config (well under a second)."""
    from ddh_vsensor.tables.build import build_unit_tables
    from ddh_vsensor.tables.store import load_unit_tables
    if getattr(args, "tables", None):
        return load_unit_tables(args.tables, actuator, cfg)
    return build_unit_tables(cfg, actuator)


def add_extension_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--extension", action="append", default=[], metavar="FILE",
                        help="extended model saved by 'ddh-vsensor analyze' (extension.json); "
                             "repeat for the other actuator")


def extensions_from(args: argparse.Namespace, cfg: Config) -> dict[str, "Extension"]:
    """The ``--extension`` files by actuator (each file says which actuator it is for)."""
    from ddh_vsensor.estimator.extension import Extension
    from ddh_vsensor.errors import UserError
    out: dict[str, Extension] = {}
    for path in args.extension:
        ext = Extension.load(path, cfg)
        if ext.actuator in out:
            raise UserError(f"{path}: a second extension for the {ext.actuator}")
        out[ext.actuator] = ext
    return out
