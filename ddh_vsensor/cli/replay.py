"""``ddh-vsensor replay``: a CAN log sent onto a bus at its own pace (bench tests)."""

from __future__ import annotations

import argparse
import asyncio
import sys

from ddh_vsensor.errors import UserError
from ddh_vsensor.cli.common import add_config_arg, config_from
from ddh_vsensor.cli.progress import ProgressBar
from ddh_vsensor.cli.run import add_bus_args, bus_from_args

# python-can interfaces that deliver the sender's timestamp (preserve_timestamps=True)
STAMP_KEEPING_INTERFACES = ("virtual", "remote")


def _frame_id(text: str) -> int:
    try:
        value = int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a frame ID (e.g. 0x1B1)") from None
    if not 0 <= value <= 0x1FFFFFFF:
        raise argparse.ArgumentTypeError(f"{text}: not a CAN ID")
    return value


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", help="send a CAN log onto a bus in real time (or --rate X)",
                       description="Timed replay of a CAN log (BLF, ASC, candump, CSV, ...) "
                       "onto the machine's buses (each unit's frames onto the bus it is on, the "
                       "rest onto the default bus): frame k goes out at its log time divided by "
                       "--rate, from absolute deadlines.")
    p.add_argument("log", metavar="LOG")
    add_config_arg(p)
    add_bus_args(p)
    p.add_argument("--rate", type=float, default=1.0,
                   help="speed-up (2 = twice as fast; 0 = as fast as possible; default 1). "
                        "A real bus stamps frames on reception, so a receiver sees the time "
                        "compressed too")
    p.add_argument("--skip-id", type=_frame_id, action="append", default=[], metavar="ID",
                   help="do not send frames with this ID (repeatable)")
    p.add_argument("--stamp", choices=("bus", "log"), default="bus",
                   help="bus (default): the bus stamps each frame as it goes out, as a real "
                        "bus does; log: each frame carries its log time (start-aligned to "
                        "now), kept by the virtual and remote interfaces, so a receiver "
                        "integrates in the log's time whatever the transport's jitter or "
                        "--rate")
    p.add_argument("--inputs-only", action="store_true",
                   help="send only the frames the service reads (Sevcon, oil, I/O, "
                        "heartbeats): not the logged position frames, which would clash with "
                        "the service's own")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import can

    from ddh_vsensor.canbus.dbc import IO_MODULE, OIL_TEMP, FrameCodec, message_name
    from ddh_vsensor.service.bus import open_bus
    from ddh_vsensor.master.replay import bus_sender, read_log, replay

    cfg = config_from(args)
    if args.rate < 0:
        raise UserError(f"--rate {args.rate}: must be positive (or 0)")
    frames = read_log(args.log)
    skip = set(args.skip_id)
    codec = FrameCodec(cfg)
    if args.inputs_only:
        from ddh_vsensor.io.log import heartbeat_ids
        keep = {codec.ids[OIL_TEMP], codec.ids[IO_MODULE],
                *heartbeat_ids(cfg, list(cfg.can.units))} | {
            codec.ids[message_name(k, a)] for a in cfg.can.units for k in ("sevcon", "heartbeat")}
        skip |= {m.arbitration_id for m in frames} - keep
    from ddh_vsensor.config import DEFAULT_BUS
    from ddh_vsensor.service.buses import frame_buses, machine_buses
    all_settings = machine_buses(cfg, bus_from_args(args, cfg))
    if args.stamp == "log":
        for settings in all_settings.values():
            if settings["interface"] not in STAMP_KEEPING_INTERFACES:
                raise UserError(f"--stamp log: the {settings['interface']} interface stamps "
                                f"frames itself (use {' or '.join(STAMP_KEEPING_INTERFACES)})")
            settings["preserve_timestamps"] = True
    buses: dict[str, can.BusABC] = {}
    try:
        for name, settings in all_settings.items():
            try:
                buses[name] = open_bus(settings)
            except (can.CanError, OSError) as exc:
                raise UserError(f"cannot open the bus {settings}: {exc}") from None
    except UserError:
        for bus in buses.values():
            bus.shutdown()
        raise
    # Each unit's frames onto its own bus; oil temperature, I/O module and the rest onto the
    # default one.
    senders = {name: bus_sender(bus) for name, bus in buses.items()}
    on_bus = frame_buses(cfg, codec) if len(buses) > 1 else {}

    def send(msg: can.Message) -> bool:
        return senders[on_bus.get(msg.arbitration_id, DEFAULT_BUS)](msg)
    span_s = max(frames[-1].timestamp - frames[0].timestamp, 1e-9)
    bar = ProgressBar("replay")
    reached = [0.0]

    def progress(log_time_s: float) -> None:
        reached[0] = log_time_s
        bar.update(log_time_s / span_s, f"{log_time_s:.1f} of {span_s:.1f} s of log")

    try:
        stats = asyncio.run(replay(frames, send, rate=args.rate, stamp=args.stamp,
                                   skip_ids=skip, progress=progress))
    finally:
        for bus in buses.values():
            bus.shutdown()
        bar.close(f"{reached[0]:.1f} of {span_s:.1f} s of log")
    print(f"replayed {stats.frames} frames ({stats.skipped} skipped, {stats.send_errors} send "
          f"errors) spanning {stats.log_span_s:.3f} s of log in {stats.duration_s:.3f} s; "
          f"latest frame {stats.late_max_s * 1e3:.2f} ms behind its deadline", file=sys.stderr)
    return 1 if stats.send_errors else 0
