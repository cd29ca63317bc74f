"""``ddh-vsensor monitor``: each cylinder's position, speed, uncertainty and flags, live from
a bus or from a recorded CAN log."""

from __future__ import annotations

import argparse
import sys
import time
from typing import TextIO

from ddh_vsensor.errors import UserError
from ddh_vsensor.cli.common import add_config_arg, config_from
from ddh_vsensor.cli.run import add_bus_args, bus_from_args


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("monitor", help="live view of the emulated position sensors",
                       description="Shows what the emulated CiA 406 sensors publish: position, "
                       "speed, uncertainty, flags, input counters, NMT state. From the machine's "
                       "buses (the default one as --interface/--channel say, default the "
                       "config's bus:; the others as configured under buses:) or a CAN log "
                       "(--log).")
    add_config_arg(p)
    add_bus_args(p)
    p.add_argument("--log", metavar="LOG", help="read a recorded CAN log instead of a bus")
    p.add_argument("--every", type=float, default=0.25, metavar="S",
                   help="refresh period, of log time with --log (default 0.25 s)")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="stop after this long (default: until Ctrl-C)")
    p.set_defaults(func=_run)


class _Screen:
    """Redraws in place on a terminal; prints blocks one after the other otherwise."""

    def __init__(self, stream: TextIO) -> None:
        self.stream, self.tty = stream, stream.isatty()
        self._lines = 0

    def show(self, header: str, lines: list[str]) -> None:
        block = [header, *lines]
        if self.tty and self._lines:
            self.stream.write(f"\x1b[{self._lines}F")
        for line in block:
            self.stream.write(("\x1b[2K" if self.tty else "") + line + "\n")
        if not self.tty:
            self.stream.write("\n")
        self.stream.flush()
        self._lines = len(block)


def _run(args: argparse.Namespace) -> int:
    from ddh_vsensor.master.watch import OutputWatcher
    cfg = config_from(args)
    if args.every <= 0:
        raise UserError(f"--every {args.every}: must be positive")
    watcher = OutputWatcher(cfg)
    screen = _Screen(sys.stdout)
    if args.log:
        if args.interface or args.channel:
            raise UserError("give either --log or --interface/--channel, not both")
        return _from_log(args, watcher, screen)
    return _from_bus(args, cfg, watcher, screen)


def _from_log(args: argparse.Namespace, watcher, screen: _Screen) -> int:
    from ddh_vsensor.master.replay import read_log
    frames = read_log(args.log)
    t0 = frames[0].timestamp
    next_show = args.every
    for msg in frames:
        t = msg.timestamp - t0
        if args.duration is not None and t > args.duration:
            break
        while t >= next_show:
            screen.show(f"log {args.log}  t = {next_show:8.2f} s", watcher.lines())
            next_show += args.every
        watcher.feed(msg)
    screen.show(f"log {args.log}  end, {watcher.frames} sensor frames", watcher.lines())
    return 0 if watcher.frames else 1


def _from_bus(args: argparse.Namespace, cfg, watcher, screen: _Screen) -> int:
    import can

    from ddh_vsensor.service.bus import exact_filters, open_bus
    from ddh_vsensor.service.buses import machine_buses
    buses: list[can.BusABC] = []
    try:
        for settings in machine_buses(cfg, bus_from_args(args, cfg)).values():
            try:
                buses.append(open_bus(settings, exact_filters(watcher.ids)))
            except (can.CanError, OSError) as exc:
                raise UserError(f"cannot open the bus {settings}: {exc}") from None
        where = ", ".join(f"{b.channel_info}" for b in buses)
        # One reader thread per bus, one queue: a unit's sensor is on its own bus.
        reader = can.BufferedReader()
        notifier = can.Notifier(buses, [reader], 0.1)
        start = time.monotonic()
        next_show = start + args.every
        try:
            while args.duration is None or time.monotonic() - start < args.duration:
                msg = reader.get_message(max(0.0, next_show - time.monotonic()))
                if msg is not None:
                    watcher.feed(msg)
                if time.monotonic() >= next_show:
                    next_show += args.every
                    screen.show(f"{where}  {time.strftime('%H:%M:%S')}", watcher.lines())
        except KeyboardInterrupt:
            pass
        finally:
            notifier.stop(1.0)
    finally:
        for bus in buses:
            bus.shutdown()
    screen.show(f"{watcher.frames} sensor frames seen", watcher.lines())
    return 0 if watcher.frames else 1
