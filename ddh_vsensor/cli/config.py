"""``ddh-vsensor config``: the shipped default configuration printed or written, and a file
checked the way the service will load it (so a technician finds a typo before the unit does)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..config import DEFAULT_CONFIG, Config, load_config
from ..errors import UserError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("config", help="print, write or validate a machine configuration",
                       description="The default configuration is the reference machine "
                       "shipped in the package; a machine's own copy (e.g. "
                       "/etc/ddh-vsensor/loader.yaml) starts from it.")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--print-default", action="store_true",
                      help="print the default configuration (with its comments) to stdout")
    what.add_argument("--validate", metavar="FILE",
                      help="load FILE as the service would; exit 0 and a one-line summary if "
                           "valid, exit 2 and the key path and problem if not")
    what.add_argument("--write", metavar="PATH",
                      help="write the default configuration to PATH (an existing different "
                           "file is never overwritten)")
    p.set_defaults(func=_run)


def default_text() -> str:
    return DEFAULT_CONFIG.read_text(encoding="utf-8")


def describe(cfg: Config) -> str:
    units = ", ".join(f"{a} (Sevcon node {u.sevcon_node_id}, sensor node {u.sensor_node_id})"
                      for a, u in cfg.can.units.items())
    bus = " ".join(f"{k}={v}" for k, v in cfg.bus.items())
    return f"units {units}; bus {bus}; physics {cfg.physics_hash()[:12]}"


def write_default(path: Path) -> str:
    """Write the default to ``path`` unless a file is there; returns what happened."""
    text = default_text()
    if path.exists():
        if path.is_file() and path.read_text(encoding="utf-8", errors="replace") == text:
            return "unchanged"
        return "kept"
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)
    return "written"


def _run(args: argparse.Namespace) -> int:
    if args.print_default:
        sys.stdout.write(default_text())
        return 0
    if args.validate:
        cfg = load_config(args.validate)
        print(f"{args.validate}: valid: {describe(cfg)}")
        return 0
    path = Path(args.write)
    try:
        done = write_default(path)
    except OSError as exc:
        raise UserError(f"cannot write {path}: {exc.strerror or exc}") from None
    if done == "kept":
        raise UserError(f"{path} exists and differs from the default: not overwritten")
    print(f"{path}: {done}")
    return 0
