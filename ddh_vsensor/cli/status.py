"""``ddh-vsensor status``: the emulated sensor nodes' object dictionaries, read over SDO."""

from __future__ import annotations

import argparse
import json
from typing import Any

from ..errors import UserError
from .common import add_config_arg, config_from
from .run import add_bus_args, bus_from_args


def _preset(text: str) -> tuple[str, float]:
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"{text!r}: expected UNIT=MM, e.g. lift=12.5")
    try:
        return name, float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: {value!r} is not a number") from None


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("status", help="read the emulated sensors' state over SDO",
                       description="Reads each emulated CiA 406 node over SDO: position, speed, "
                       "uncertainty, flags, input counters, measuring step, timers. --preset "
                       "writes the CiA 406 preset value (a manual reference) first.")
    add_config_arg(p)
    add_bus_args(p)
    p.add_argument("--timeout", type=float, default=1.0, metavar="S",
                   help="SDO response timeout (default 1 s)")
    p.add_argument("--preset", type=_preset, action="append", default=[],
                   metavar="UNIT=MM", help="set a cylinder's position (manual reference; "
                   "refused outside the stroke)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=_run)


def _read_node(node: Any, step_mm: float) -> dict[str, Any]:
    from ..service.watch import flag_text
    sdo = node.sdo
    position = sdo[0x6020][1].raw
    flags = sdo[0x2002].raw
    return {
        "device_type": f"0x{sdo[0x1000].raw:08X}",
        "position_mm": position * step_mm,
        "position_steps": position,
        "measuring_step_nm": sdo[0x6005][1].raw,
        "speed_mm_s": sdo[0x6030][1].raw * 0.1,
        "uncertainty_mm": sdo[0x2001].raw * 0.01,
        "flags": flags,
        "flag_names": flag_text(flags),
        "input_frames": sdo[0x2003].raw,
        "rejected_frames": sdo[0x2004].raw,
        "tpdo1_event_timer_ms": sdo[0x1800][5].raw,
        "tpdo2_event_timer_ms": sdo[0x1801][5].raw,
        "heartbeat_ms": sdo[0x1017].raw,
    }


def _run(args: argparse.Namespace) -> int:
    import can
    import canopen

    from ..canbus.eds import unit_object_dictionary
    from ..service.bus import open_bus

    cfg = config_from(args)
    if not 0.01 <= args.timeout <= 60:
        raise UserError(f"--timeout {args.timeout}: outside 0.01..60 s")
    settings = bus_from_args(args, cfg)
    try:
        bus = open_bus(settings)
    except (can.CanError, OSError) as exc:
        raise UserError(f"cannot open the bus {settings}: {exc}") from None
    network = canopen.Network(bus)
    # canopen's MessageListener guards its callbacks; one listener, a thread Notifier: the
    # SDO client blocks this thread while the notifier delivers the responses.
    notifier = can.Notifier(bus, network.listeners, 0.1)
    step = cfg.can.position_step_mm
    out: dict[str, Any] = {}
    try:
        nodes = {a: network.add_node(u.sensor_node_id, unit_object_dictionary(cfg, a))
                 for a, u in cfg.can.units.items()}
        for node in nodes.values():
            node.sdo.RESPONSE_TIMEOUT = args.timeout
            node.sdo.MAX_RETRIES = 1     # canopen counts attempts: 0 would retry forever
        for actuator, mm in args.preset:
            try:
                nodes[actuator].sdo[0x6010][1].raw = round(mm / step)
            except canopen.SdoAbortedError as exc:
                raise UserError(f"{actuator}: preset {mm} mm refused by node "
                                f"{nodes[actuator].id}: {exc}") from None
            except canopen.SdoCommunicationError as exc:
                raise UserError(_no_answer(actuator, nodes[actuator].id, exc)) from None
        for actuator, node in nodes.items():
            try:
                out[actuator] = {"node_id": node.id, **_read_node(node, step)}
            except canopen.SdoCommunicationError as exc:
                raise UserError(_no_answer(actuator, node.id, exc)) from None
            except canopen.SdoAbortedError as exc:
                raise UserError(f"{actuator}: node {node.id} refused a read: {exc}") from None
    finally:
        notifier.stop(1.0)
        bus.shutdown()
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    for actuator, r in out.items():
        print(f"{actuator} (node {r['node_id']}, device type {r['device_type']})")
        print(f"  position      {r['position_mm']:10.2f} mm  ({r['position_steps']} steps of "
              f"{r['measuring_step_nm'] / 1e6:g} mm)")
        print(f"  speed         {r['speed_mm_s']:10.1f} mm/s")
        print(f"  uncertainty   {r['uncertainty_mm']:10.2f} mm")
        print(f"  flags         {r['flag_names']} (0x{r['flags']:02X})")
        print(f"  input frames  {r['input_frames']:10d}  rejected {r['rejected_frames']}")
        print(f"  timers        TPDO1 {r['tpdo1_event_timer_ms']} ms, TPDO2 "
              f"{r['tpdo2_event_timer_ms']} ms, heartbeat {r['heartbeat_ms']} ms")
    return 0


def _no_answer(actuator: str, node_id: int, exc: Exception) -> str:
    return (f"{actuator}: node {node_id} did not answer over SDO ({exc}): is "
            f"`ddh-vsensor run` running on this bus?")
