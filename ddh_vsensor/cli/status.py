"""``ddh-vsensor status``: the emulated sensor nodes' object dictionaries, read over SDO, and
the reference switches' drift records the service keeps in its state directory."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

from ddh_vsensor.errors import UserError
from ddh_vsensor.cli.common import add_config_arg, config_from
from ddh_vsensor.cli.install import DEFAULT_STATE_DIR
from ddh_vsensor.cli.run import add_bus_args, bus_from_args, default_state_dir
from ddh_vsensor.config import Config


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
                       "uncertainty, flags, input counters, measuring step, timers; and, from "
                       "the service's state directory, whether each reference switch's travel "
                       "between its edges still matches its configured window and hysteresis. "
                       "--preset writes the CiA 406 preset value (a manual reference) first. "
                       "--health prints each unit's health as the service last judged it from "
                       "its day summaries (no bus needed).")
    add_config_arg(p)
    add_bus_args(p)
    p.add_argument("--timeout", type=float, default=1.0, metavar="S",
                   help="SDO response timeout (default 1 s)")
    p.add_argument("--preset", type=_preset, action="append", default=[],
                   metavar="UNIT=MM", help="set a cylinder's position (manual reference; "
                   "refused outside the stroke)")
    p.add_argument("--state-dir", metavar="DIR", help="the service's state directory, where it "
                   "records its reference switches' drift (default: $STATE_DIRECTORY, else "
                   f"{DEFAULT_STATE_DIR} where it exists, else $XDG_STATE_HOME/ddh-vsensor)")
    p.add_argument("--health", action="store_true", help="each unit's health from the state "
                   "directory (the cause its days point to, the expected error at the "
                   "references, the days until it passes health.tolerance_mm); no SDO")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import can
    import canopen

    from ddh_vsensor.service.bus import open_bus
    from ddh_vsensor.service.buses import machine_buses
    from ddh_vsensor.master.client import clients, sdo_network

    cfg = config_from(args)
    presets = [(cfg.require_unit(unit), mm) for unit, mm in args.preset]
    state_dir = _state_dir(args.state_dir)
    if args.health:
        if presets:
            raise UserError("--health reads the state directory only: no --preset with it")
        return _print_health(cfg, state_dir, args.json)
    if not 0.01 <= args.timeout <= 60:
        raise UserError(f"--timeout {args.timeout}: outside 0.01..60 s")
    out: dict[str, Any] = {}
    for bus_name, settings in machine_buses(cfg, bus_from_args(args, cfg)).items():
        units = cfg.units_on_bus(bus_name)
        if not units:
            continue
        try:
            bus = open_bus(settings)
        except (can.CanError, OSError) as exc:
            raise UserError(f"cannot open the bus {settings}: {exc}") from None
        try:
            with sdo_network(bus) as network:
                nodes = clients(network, cfg, units, timeout_s=args.timeout, attempts=1)
                for unit, mm in presets:
                    if unit not in nodes:
                        continue
                    try:
                        nodes[unit].preset(mm)
                    except canopen.SdoAbortedError as exc:
                        raise UserError(f"{unit}: preset {mm} mm refused by node "
                                        f"{nodes[unit].node_id}: {exc}") from None
                    except canopen.SdoCommunicationError as exc:
                        raise UserError(_no_answer(unit, nodes[unit].node_id, exc)) from None
                for unit, client in nodes.items():
                    try:
                        out[unit] = {"node_id": client.node_id, **client.read_all()}
                    except canopen.SdoCommunicationError as exc:
                        raise UserError(_no_answer(unit, client.node_id, exc)) from None
                    except canopen.SdoAbortedError as exc:
                        raise UserError(f"{unit}: node {client.node_id} refused a read: "
                                        f"{exc}") from None
        finally:
            bus.shutdown()
    out = {unit: out[unit] for unit in cfg.unit_names}
    for unit, r in out.items():
        r["switches"], r["switches_problem"] = switch_report(cfg, unit, state_dir)
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    for actuator, r in out.items():
        print(f"{actuator} (node {r['node_id']}, device type {r['device_type']})")
        print(f"  position      {r['position_mm']:10.2f} mm  ({r['position_steps']} steps of "
              f"{r['measuring_step_nm'] / 1e6:g} mm)")
        print(f"  speed         {r['speed_mm_s']:10.1f} mm/s")
        print(f"  uncertainty   {r['uncertainty_mm']:10.2f} mm")
        print(f"  flags         {r['flag_names']} (0x{r['flags']:02X}), error register "
              f"0x{r['error_register']:02X}")
        print(f"  input frames  {r['input_frames']:10d}  rejected {r['rejected_frames']}")
        print(f"  timers        TPDO1 {r['tpdo1_event_timer_ms']} ms, TPDO2 "
              f"{r['tpdo2_event_timer_ms']} ms, heartbeat {r['heartbeat_ms']} ms, guarding "
              + (f"{r['guard_time_ms']} ms x {r['life_time_factor']}"
                 if r['guard_time_ms'] and r['life_time_factor'] else "off"))
        for line in switch_lines(r["switches"], r["switches_problem"]):
            print(f"  {line}")
    return 0


def _state_dir(given: str | None) -> Path:
    if given:
        if not Path(given).is_dir():
            raise UserError(f"--state-dir {given}: "
                            + ("not a directory" if Path(given).exists() else "no such directory"))
        return Path(given)
    if not os.environ.get("STATE_DIRECTORY") and Path(DEFAULT_STATE_DIR).is_dir():
        return Path(DEFAULT_STATE_DIR)
    return default_state_dir()


def switch_report(cfg: Config, unit: str, state_dir: Path
                  ) -> tuple[dict[str, Any] | None, str | None]:
    """Each switch's verdict and spans from the service's record (None, with why, where
    there is none to read)."""
    from ddh_vsensor.estimator.switch_drift import SwitchDrift
    from ddh_vsensor.service.persistence import load_switch_record, switches_path

    path = switches_path(state_dir, unit)
    assert path is not None
    drift = SwitchDrift.from_config(cfg, unit)
    try:
        record = load_switch_record(path, unit, cfg.faults.state_file_max_bytes)
        if record is None:
            return None, f"no record in {state_dir} (the service's --state-dir)"
        drift.restore(record)
    except PermissionError:
        return None, (f"cannot read {path}: permission denied (the service's state directory "
                      "is its own: run status as root)")
    except (OSError, ValueError, TypeError, RecursionError) as exc:
        return None, f"{path} unusable ({type(exc).__name__}: {str(exc)[:120]})"
    return {name: s.summary() for name, s in drift.switches.items()}, None


def switch_lines(switches: dict[str, Any] | None, problem: str | None) -> list[str]:
    """The text output's lines for one unit's switches."""
    if switches is None:
        return [f"switches      {problem}"]
    lines = []
    for name, s in switches.items():
        spans = "; ".join(f"{span} {v['measured_mm']:.2f} mm, configured "
                          f"{v['configured_mm']:.2f} ({v['pairs']} pairs)"
                          for span, v in s["spans"].items()) or "no pair measured yet"
        lines.append(f"switch {name:<7}{'DRIFTED' if s['drifted'] else 'ok':>10}  {spans}")
    return lines


def _print_health(cfg: Config, state_dir: Path, as_json: bool) -> int:
    from dataclasses import asdict

    from ddh_vsensor.diagnosis.health import FILE, read_health
    path = state_dir / FILE
    try:
        health = read_health(path)
    except FileNotFoundError:
        raise UserError(f"no health in {state_dir}: the service writes {FILE} with its day "
                        "summaries (`run --machine`, with a --state-dir)") from None
    except PermissionError:
        raise UserError(f"cannot read {path}: permission denied (the service's state directory "
                        "is its own: run status as root)") from None
    except (OSError, ValueError) as exc:
        raise UserError(f"{path} unusable: {exc}") from None
    if as_json:
        print(json.dumps({u: asdict(h) for u, h in health.items()}, indent=2))
        return 0
    for unit in cfg.unit_names:
        print(f"{unit}: {health[unit].finding if unit in health else 'no health yet'}")
    return 0


def _no_answer(unit: str, node_id: int, exc: Exception) -> str:
    return (f"{unit}: node {node_id} did not answer over SDO ({exc}): is "
            f"`ddh-vsensor run` running on this bus?")
