"""Arguments and helpers shared by several subcommands."""

from __future__ import annotations

import argparse

from ..config import ACTUATORS, Config, load_config


def add_config_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE", default=None,
                        help="machine configuration (default: the embedded reference loader)")


def add_actuator_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--actuator", choices=ACTUATORS, required=True)


def config_from(args: argparse.Namespace) -> Config:
    return load_config(args.config)
