"""``ddh-vsensor`` entry point: dispatches to one module per subcommand."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from ddh_vsensor.version import __version__
from ddh_vsensor.errors import UserError
from ddh_vsensor.cli.logs import configure_logging

# Subcommand modules under ddh_vsensor.cli, each exposing register(subparsers).
SUBCOMMANDS = ("tables", "steady", "simulate", "estimate", "analyze",
               "run", "replay", "monitor", "status", "demo", "config", "install", "fleet",
               "dbc", "eds", "commission")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ddh-vsensor",
        description="Virtual position sensor for pump-controlled hydraulic cylinders.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log detail, repeatable (before the command; at debug also "
                             "canopen's line per SDO request instead of its summary)")
    parser.add_argument("-q", "--quiet", action="count", default=0,
                        help="less log detail, repeatable (before the command)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in SUBCOMMANDS:
        importlib.import_module(f"{__package__}.{name}").register(sub)
    return parser


def one_line(message: str) -> str:
    """A message on one line (a library's may span several: YAML's shows the spot)."""
    return "; ".join(part for part in (line.strip() for line in message.splitlines()) if part)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    # `simulate fleet` is the fleet simulator's own parser (`simulate` takes no subcommand)
    k = next((i for i, a in enumerate(argv) if not a.startswith("-")), len(argv))
    if argv[k:k + 2] == ["simulate", "fleet"]:
        argv = [*argv[:k], "simulate-fleet", *argv[k + 2:]]
    args = parser.parse_args(argv)
    # A subcommand's --log-level (run, demo) is the base; elsewhere warnings and errors.
    configure_logging(getattr(args, "log_level", None), args.verbose - args.quiet)
    try:
        return int(args.func(args) or 0)
    except UserError as exc:
        print(f"ddh-vsensor {args.command}: error: {one_line(str(exc))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
