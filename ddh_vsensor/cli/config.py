"""``ddh-vsensor config``: the shipped default configuration printed or written, and a file
checked the way the service will load it (so a technician finds a typo before the unit does)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import types
import typing
from pathlib import Path

from ddh_vsensor.config import (DATASHEET_TOLERANCES, DEFAULT_BUS, DEFAULT_CONFIG, Config,
                                load_config)
from ddh_vsensor.config.jsonschema import json_schema
from ddh_vsensor.errors import UserError


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
    what.add_argument("--schema", action="store_true",
                      help="print every configuration key with its type, bounds and default "
                           "(generated from the configuration's dataclasses)")
    what.add_argument("--json-schema", nargs="?", const="-", metavar="FILE",
                      help="print the configuration's JSON Schema (draft 2020-12) for YAML "
                           "editors, or write it to FILE; a config file then names it in a "
                           "first line '# yaml-language-server: $schema=FILE'")
    what.add_argument("--write", metavar="PATH",
                      help="write the default configuration to PATH (an existing different "
                           "file is never overwritten)")
    p.add_argument("--datasheet", action="store_true",
                   help="with --write: the parameters' tolerances a datasheet gives (pump "
                        "leakage, its shape, compliance to +-30 percent), for a machine not "
                        "yet commissioned, instead of the reference loader's measured ones")
    p.set_defaults(func=_run)


def default_text() -> str:
    return DEFAULT_CONFIG.read_text(encoding="utf-8")


# Why a datasheet leaves each tolerance as wide as DATASHEET_TOLERANCES has it
_DATASHEET_WHY = {
    "pump_leakage": "volumetric efficiency to about +-2 points",
    "pump_displacement": "displacement, belt ratio and bore to +-1 %",
    "leakage_orifice_share": "the leakage law's shape is not given",
    "trapped_volume_share": "of the displacement, compressed and lost per revolution",
    "compliance": "air and hose walls unknown until measured",
}


def datasheet_text() -> str:
    """The default configuration with a datasheet's tolerances in its ``tolerances:``
    section (each value and its comment), the rest as shipped."""
    lines = default_text().splitlines(keepends=True)
    start = lines.index("tolerances:\n")
    for i in range(start + 1, len(lines)):
        key = lines[i].strip().split(":", 1)[0]
        if not lines[i].startswith("  "):
            break
        if key in _DATASHEET_WHY:
            value = getattr(DATASHEET_TOLERANCES, key)
            lines[i] = f"{f'  {key}: {value}':<40}# chosen (a datasheet: {_DATASHEET_WHY[key]})\n"
    return "".join(lines)


def describe(cfg: Config) -> str:
    units = ", ".join(f"{a} (Sevcon node {u.sevcon_node_id}, sensor node {u.sensor_node_id}"
                      f"{'' if len(cfg.bus_names) == 1 else ', bus ' + u.bus})"
                      for a, u in cfg.can.units.items())
    buses = "; ".join(f"{'bus' if name == DEFAULT_BUS else 'bus ' + name} "
                      + " ".join(f"{k}={v}" for k, v in cfg.bus_kwargs(name).items())
                      for name in cfg.bus_names)
    cycles = ", ".join(cfg.work_cycle.cycles) if cfg.work_cycle is not None else "none"
    return (f"units {units}; {buses}; work cycles {cycles}; "
            f"physics {cfg.physics_hash()[:12]}")


_BOUND_WORDS = (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<="))


def _type_text(tp: typing.Any) -> str:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        return "mapping"
    if origin is typing.Literal:
        return " | ".join(str(a) for a in args)
    if origin is tuple:
        return f"list of {_type_text(args[0])}"
    if origin is dict:
        return f"mapping of {_type_text(args[0])} to {_type_text(args[1])}"
    if origin in (typing.Union, types.UnionType):
        return " or ".join("null" if a is type(None) else _type_text(a) for a in args)
    return {float: "number", int: "whole number", bool: "true/false", str: "text",
            typing.Any: "any"}.get(tp, getattr(tp, "__name__", str(tp)))


def _number(value: float) -> str:
    return str(value) if isinstance(value, int) else f"{value:g}"


def _inner_dataclass(tp: typing.Any) -> type | None:
    """The dataclass a field holds (directly, as the values of a mapping, the items of a
    list, or optionally), whose keys the schema lists below the field."""
    if dataclasses.is_dataclass(tp):
        return tp
    for arg in typing.get_args(tp):
        inner = _inner_dataclass(arg)
        if inner is not None:
            return inner
    return None


def schema_lines(cls: type = Config, prefix: str = "") -> list[str]:
    """One line per key: path, type, bounds, default; from the dataclass fields' type hints
    and ``metadata`` (the same ones the loader validates with)."""
    hints = typing.get_type_hints(cls)
    lines = []
    for f in dataclasses.fields(cls):
        if f.metadata.get("internal"):
            continue
        tp = hints[f.name]
        path = f"{prefix}{f.name}"
        meta = dict(f.metadata)
        if "ge" in meta and meta.get("gt", meta["ge"]) < meta["ge"]:
            del meta["gt"]                  # _positive(ge=...): the tighter bound says it
        bounds = " ".join(f"{word} {_number(meta[key])}" for key, word in _BOUND_WORDS
                          if key in meta)
        if f.default is not dataclasses.MISSING:
            default = f"default {f.default!r}" if f.default is not None else "optional"
        elif f.default_factory is not dataclasses.MISSING:
            default = "optional"
        else:
            default = "required"
        inner = _inner_dataclass(tp)
        what = f"{_type_text(tp)}{', ' + bounds if bounds else ''}; {default}"
        if inner is not None:
            doc = " ".join((inner.__doc__ or "").replace("``", "").split())
            what += f". {doc.split('. ')[0].rstrip('.')}"
        lines.append(f"{path:<48} {what}")
        if inner is not None:
            origin = typing.get_origin(tp)
            if origin is dict:
                sub = f"{path}.<{'unit' if f.name == 'units' else 'name'}>."
            elif origin is tuple:
                sub = f"{path}[i]."
            else:
                sub = f"{path}."
            lines += schema_lines(inner, sub)
    return lines


def write_default(path: Path, text: str | None = None) -> str:
    """Write the default (or ``text``) to ``path`` unless a file is there; returns what
    happened."""
    text = default_text() if text is None else text
    if path.exists():
        if path.is_file() and path.read_text(encoding="utf-8", errors="replace") == text:
            return "unchanged"
        return "kept"
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)
    return "written"


def _write_json_schema(target: str) -> int:
    """The schema to stdout (``-``) or to a file, whose path then goes to stdout."""
    text = json.dumps(json_schema(), indent=2) + "\n"
    if target == "-":
        sys.stdout.write(text)
        return 0
    path = Path(target)
    try:
        path.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise UserError(f"cannot write {path}: {exc.strerror or exc}") from None
    print(f"{path}: written")
    return 0


def _run(args: argparse.Namespace) -> int:
    if args.datasheet and not args.write:
        raise UserError("--datasheet goes with --write PATH")
    if args.print_default:
        sys.stdout.write(default_text())
        return 0
    if args.schema:
        print("# ddh-vsensor configuration keys: path, type, bounds, default (<unit>: one of "
              "the machine's units)")
        print("\n".join(schema_lines()))
        return 0
    if args.json_schema:
        return _write_json_schema(args.json_schema)
    if args.validate:
        cfg = load_config(args.validate)
        print(f"{args.validate}: valid: {describe(cfg)}")
        return 0
    path = Path(args.write)
    try:
        done = write_default(path, datasheet_text() if args.datasheet else None)
    except OSError as exc:
        raise UserError(f"cannot write {path}: {exc.strerror or exc}") from None
    if done == "kept":
        what = "the datasheet default" if args.datasheet else "the default"
        raise UserError(f"{path} exists and differs from {what}: not overwritten")
    print(f"{path}: {done}")
    return 0
