"""``ddh-vsensor run``: the service (systemd unit: systemd/ddh-vsensor.service)."""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import signal
import sys
from pathlib import Path
from typing import Any

from ddh_vsensor.atomic import output_dir
from ddh_vsensor.config import Config
from ddh_vsensor.errors import UserError
from ddh_vsensor.cli.common import (add_config_arg, add_extension_arg, config_from, extensions_from,
                     load_tables_for)


# Stop cleanly (estimates saved as a clean stop). SIGKILL cannot be caught: the periodic save
# is what a kill leaves, and a restart widens it by the time since.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGQUIT)
# Would kill the process by default: save the estimates, log, carry on (no config reload).
SAVE_SIGNALS = (signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2)


def add_bus_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--interface", metavar="I", help="python-can interface of the default bus, "
                   "overrides bus.interface (socketcan, virtual, remote, ...); the buses "
                   "named under buses: are opened as configured")
    p.add_argument("--channel", metavar="C", help="channel of the default bus, overrides "
                   "bus.channel (can0, ws://127.0.0.1:54701/, ...); not the buses under buses:")


def bus_from_args(args: argparse.Namespace, cfg: Config) -> dict[str, Any]:
    """The default bus's settings (``bus:``) with the command line's overrides."""
    from ddh_vsensor.service.bus import bus_settings
    return bus_settings(cfg.bus, args.interface, args.channel)


def default_state_dir() -> Path:
    """systemd's StateDirectory= (``$STATE_DIRECTORY``), else the XDG state directory."""
    if os.environ.get("STATE_DIRECTORY"):
        return Path(os.environ["STATE_DIRECTORY"].split(":")[0])
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "ddh-vsensor"


def setup_logging(level: str) -> None:
    # Under systemd the journal stamps each line; elsewhere the time is useful.
    fmt = "%(levelname)s %(name)s: %(message)s" if os.environ.get("JOURNAL_STREAM") \
        else "%(asctime)s %(levelname)s %(name)s: %(message)s"
    logging.basicConfig(level=getattr(logging, level.upper()), format=fmt, stream=sys.stderr)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="the service: Sevcon frames in, emulated position sensors out",
                       description="Reads the Sevcon controllers' frames, estimates each "
                       "cylinder's position and publishes it as a CiA 406 position sensor. "
                       "Stops cleanly on SIGTERM/SIGINT/SIGQUIT (estimates saved, exit 0); "
                       "SIGHUP/SIGUSR1/SIGUSR2 save the estimates and do not reload the "
                       "configuration.")
    add_config_arg(p)
    add_bus_args(p)
    p.add_argument("--tables", metavar="DIR", help="movement tables (default: built at start, "
                   "well under a second)")
    p.add_argument("--state-dir", metavar="DIR", help="where the estimates are persisted "
                   "(default: $STATE_DIRECTORY, else $XDG_STATE_HOME/ddh-vsensor)")
    add_extension_arg(p)
    p.add_argument("--no-state", action="store_true", help="neither restore nor save estimates")
    p.add_argument("--machine", metavar="NAME", default=None,
                   help="the machine's name in its day summaries (STATE_DIR/summaries/"
                        "NAME_YYYY-MM-DD.summary.json; default: the host's name)")
    p.add_argument("--no-summaries", action="store_true",
                   help="write no day summaries (they need the state directory)")
    p.add_argument("--heartbeat-timeout", type=float, default=None, metavar="S",
                   help="Sevcon heartbeat consumer time (default: faults.heartbeat_timeout_s)")
    p.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"))
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from ddh_vsensor.service import ServiceOptions
    setup_logging(args.log_level)
    machine = None
    if not args.no_summaries and not args.no_state:
        from ddh_vsensor.service.summary import check_machine, default_machine
        machine = check_machine(args.machine or default_machine())
    cfg = config_from(args)
    bus = bus_from_args(args, cfg)
    tables = {a: load_tables_for(args, cfg, a) for a in cfg.can.units}
    state_dir = None if args.no_state else \
        output_dir(args.state_dir or default_state_dir(), "state directory")
    options = ServiceOptions(state_dir=state_dir, extensions=extensions_from(args, cfg),
                             machine=machine)
    if args.heartbeat_timeout is not None:
        if not 0.01 <= args.heartbeat_timeout <= 600:
            raise UserError(f"--heartbeat-timeout {args.heartbeat_timeout}: outside 0.01..600 s")
        options.heartbeat_timeout_s = args.heartbeat_timeout
    return asyncio.run(_serve(cfg, tables, bus, options))


async def _serve(cfg: Config, tables: dict, bus: dict[str, Any], options: Any) -> int:
    from ddh_vsensor.service import Service
    service = Service(cfg, tables, bus, options)
    loop = asyncio.get_running_loop()
    for sig in STOP_SIGNALS:
        loop.add_signal_handler(sig, service.request_stop)
    for sig in SAVE_SIGNALS:
        loop.add_signal_handler(sig, service.on_signal, sig.name)
    try:
        return await service.run()
    finally:
        for sig in (*STOP_SIGNALS, *SAVE_SIGNALS):
            loop.remove_signal_handler(sig)
