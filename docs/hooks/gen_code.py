"""Pages made from the code: configuration reference, device sheet, flags, layers, commands."""

from __future__ import annotations

import argparse
import ast
import dataclasses
import io
import re
import tokenize
from pathlib import Path
from typing import Any

import tomllib
import yaml
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, datatypes

from ddh_vsensor.canbus.eds import unit_object_dictionary
from ddh_vsensor.canbus.layout import EMCY_CODES, MAINTENANCE_EMCY
from ddh_vsensor.cli.config import schema_lines
from ddh_vsensor.cli.main import build_parser
from ddh_vsensor.config import load_config
from ddh_vsensor.config.schema import DEFAULT_CONFIG
from ddh_vsensor.estimator import flags as flags_module
from ddh_vsensor.estimator.flags import EXPLAINING, Flags


def prose(text: str) -> str:
    """A docstring's reStructuredText roles and literals as Markdown code."""
    text = re.sub(r":[a-z]+:`~?([^`]+)`", r"`\1`", text)
    return text.replace("``", "`")


def cell(text: object) -> str:
    """A Markdown table cell: pipes escaped, one line."""
    return " ".join(str(text).replace("|", "\\|").split())


def table(header: list[str], rows: list[list[object]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


# --- configuration reference -------------------------------------------------------------

def _reference_values(node: Any, parts: list[str], label: str = "") -> list[tuple[str, Any]]:
    """The reference loader's values at a schema path (``<unit>``/``<name>``: every key,
    ``key[i]``: every element), labelled by the keys and indices taken."""
    if not parts:
        return [(label, node)]
    head, rest = parts[0], parts[1:]
    if head in ("<unit>", "<name>"):
        if not isinstance(node, dict):
            return []
        return [v for k, sub in node.items()
                for v in _reference_values(sub, rest, f"{label}{k} ".lstrip())]
    key, listed = (head[:-3], True) if head.endswith("[i]") else (head, False)
    if not isinstance(node, dict) or key not in node:
        return []
    node = node[key]
    if listed:
        if not isinstance(node, list):
            return []
        return [v for i, sub in enumerate(node)
                for v in _reference_values(sub, rest, f"{label}[{i}] ")]
    return _reference_values(node, rest, label)


def _no_readme(text: str) -> str:
    """A docstring's pointer into the old single-file README: the docs site replaces it."""
    return re.sub(r"\s*\(README[^)]*\)", "", text)


def _flat(v: Any) -> bool:
    """A value shown inline: a scalar, or a list or mapping of scalars."""
    items = v.values() if isinstance(v, dict) else v if isinstance(v, list) else None
    return items is None or not any(isinstance(x, (dict, list)) for x in items)


def _yaml(v: Any) -> str:
    """A value as it is written in the configuration file (flow style)."""
    if isinstance(v, (dict, list)):
        return yaml.safe_dump(v, default_flow_style=True, sort_keys=False, width=10_000).strip()
    return str(v)


def _shown(values: list[tuple[str, Any]]) -> str:
    leaves = [(label.strip(), v) for label, v in values if _flat(v)]
    if not leaves:
        return ""
    text = [f"{label}: `{_yaml(v)}`" if label else f"`{_yaml(v)}`" for label, v in leaves[:4]]
    return ", ".join(text) + (f", … ({len(leaves)} in all)" if len(leaves) > 4 else "")


def config_reference() -> str:
    """Every key ``config --schema`` prints, grouped by section, with the reference loader's
    value beside its type, bounds and default."""
    reference = yaml.safe_load(DEFAULT_CONFIG.read_text(encoding="utf-8"))
    sections: dict[str, list[list[str]]] = {}
    intro: dict[str, str] = {}
    for line in schema_lines():
        path, what = line.split(None, 1)
        kind, _, rest = what.partition("; ")
        default, _, doc = rest.partition(". ")
        top = re.split(r"[.\[]", path, maxsplit=1)[0]
        if path == top:
            intro[top] = f"`{kind}`, {default}. {_no_readme(doc)}".rstrip(". ") + "."
            sections.setdefault(top, [])
            continue
        parts = re.findall(r"<[a-z]+>|[A-Za-z0-9_]+(?:\[i\])?", path)
        value = _shown(_reference_values(reference, parts))
        sections.setdefault(top, []).append(
            [f"`{path}`", kind + (f". {_no_readme(doc)}" if doc else ""), default, value])
    out = []
    for top, rows in sections.items():
        out.append(f"## `{top}`\n\n{intro.get(top, '')}\n")
        if rows:
            out.append(table(["key", "type and bounds", "default", "reference loader"], rows))
        else:
            shown = _shown(_reference_values(reference, [top]))
            out.append(f"Reference loader: {shown or 'not set'}.\n")
    return "\n".join(out)


# --- CANopen device sheet -----------------------------------------------------------------

_TYPE_NAMES = {getattr(datatypes, n): n for n in dir(datatypes)
               if n.isupper() and isinstance(getattr(datatypes, n), int)}


def _value(var: ODVariable) -> str:
    if var.default is None:
        return ""
    if isinstance(var.default, int) and 0x1000 <= var.index < 0x2000:      # COB-IDs, codes
        return f"0x{var.default:X}"
    return str(var.default)


def _variables(obj) -> list[ODVariable]:
    return list(obj.values()) if isinstance(obj, (ODRecord, ODArray)) else [obj]


def _pdo_rows(od) -> list[list[object]]:
    rows = []
    for n in range(1, 5):                       # the pre-defined TPDO1..4, those there are
        comm, mapping = od.get(0x1800 + n - 1), od.get(0x1A00 + n - 1)
        if comm is None or mapping is None:
            continue
        cob = comm[1].default
        entries = []
        for sub in range(1, mapping[0].default + 1):
            raw = mapping[sub].default
            index, subindex, bits = raw >> 16, (raw >> 8) & 0xFF, raw & 0xFF
            target = od.get(index)
            name = "" if target is None else (
                target.name if isinstance(target, ODVariable) else target[subindex].name)
            entries.append(f"0x{index:04X}.{subindex} {name} ({bits} bit)")
        timer = comm[5].default if 5 in comm else ""
        rows.append([f"TPDO{n}", f"0x{cob & 0x7FF:03X}", comm[2].default, timer,
                     "; ".join(entries)])
    return rows


def device_sheet() -> str:
    """The emulated sensor's object dictionary as ``unit_object_dictionary`` builds its EDS."""
    cfg = load_config(None)
    ods = {unit: unit_object_dictionary(cfg, unit) for unit in cfg.unit_names}
    first = cfg.unit_names[0]
    od = ods[first]
    info = od.device_information
    out = ["## Identity\n", table(["field", "value"], [
        ["vendor name", info.vendor_name], ["vendor number", info.vendor_number],
        ["product name", info.product_name], ["product number", info.product_number],
        ["revision number", f"0x{info.revision_number:X}" if info.revision_number else ""],
        ["order code", info.order_code],
        ["baud rates (kbit/s)", ", ".join(str(b // 1000) for b in sorted(info.allowed_baudrates))],
        ["TPDOs / RPDOs", f"{info.nr_of_TXPDO} / {info.nr_of_RXPDO}"],
        ["LSS", info.LSS_supported]])]
    keyed = {unit: {(o.index, v.subindex if not isinstance(o, ODVariable) else None): v
                    for o in uod.values() for v in _variables(o)} for unit, uod in ods.items()}
    differ = [key for key, var in keyed[first].items()
              if len({_value(keyed[u][key]) if key in keyed[u] else None for u in ods}) > 1]
    header = ["unit", "node ID"] + [
        f"0x{index:04X}{'' if sub is None else f'.{sub}'} {keyed[first][(index, sub)].name}"
        for index, sub in differ]
    per_unit = [[unit, uod.node_id, *(_value(keyed[unit][k]) if k in keyed[unit] else ""
                                      for k in differ)] for unit, uod in ods.items()]
    out += ["## Per unit (reference loader)\n",
            ("The node ID and the objects whose defaults differ between the units' EDSs "
            "(COB-IDs follow the node ID); every other object is as listed below.\n"),
            table(header, per_unit)]
    out += ["## PDOs\n", f"Defaults of the `{first}` node (node ID {od.node_id}).\n",
            table(["PDO", "COB-ID", "transmission type", "event timer (ms)", "mapping"],
                  _pdo_rows(od))]
    rows = []
    for obj in od.values():
        if not isinstance(obj, ODVariable):
            rows.append([f"**0x{obj.index:04X}**", "", f"**{obj.name}**",
                         "ARRAY" if isinstance(obj, ODArray) else "RECORD", "", "", ""])
        for var in _variables(obj):
            sub = "" if isinstance(obj, ODVariable) else var.subindex
            rows.append([f"0x{obj.index:04X}", sub, var.name,
                         _TYPE_NAMES.get(var.data_type, var.data_type), var.access_type,
                         _value(var), "yes" if var.pdo_mappable else ""])
    out += ["## Objects\n", (f"Every object of the `{first}` node's dictionary with its "
            "default.\n"), table(["index", "sub", "name", "type", "access", "default", "PDO"],
                                rows)]
    emcy = [[f"0x{code:04X}", camel, f"0x{int(flag):02X}", (flag.name or "").lower()]
            for flag, (code, camel) in EMCY_CODES.items()]
    emcy.append([f"0x{MAINTENANCE_EMCY[0]:04X}", MAINTENANCE_EMCY[1], "0x00",
                 "none: the health alarm (0x2010 sub 2 bit 0)"])
    out += ["## EMCY codes\n", ("One EMCY when a fault flag is set (its code), an error reset "
            "(code 0x0000) when it clears. Flags not listed are states, not faults: no EMCY. "
            "The unit's health alarm is no flag: a warning, maintenance due, while it lasts "
            "(error register bits 0 and 7), the error reset when it ends.\n"),
            table(["code", "name", "flag", "flag name"], emcy)]
    return "\n".join(out)


# --- status flags ------------------------------------------------------------------------

def _flag_comments() -> dict[str, str]:
    """The comment beside each member in flags.py: the one place the meaning is written."""
    source = Path(flags_module.__file__).read_text(encoding="utf-8")
    comments, name = {}, None
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.NAME and tok.string.isupper() and tok.start[1] == 4:
            name = tok.string
        elif tok.type == tokenize.COMMENT and name:
            comments[name] = tok.string.lstrip("# ").strip()
            name = None
        elif tok.type == tokenize.NEWLINE:
            name = None
    return comments


def flag_table() -> str:
    comments = _flag_comments()
    emcy = {flag: code for flag, (code, _) in EMCY_CODES.items()}
    rows = [[f"0x{int(f):02X}", f"`{(f.name or '').lower()}`", comments.get(f.name or "", ""),
             f"fault: EMCY 0x{emcy[f]:04X}" if f in emcy else "state (no EMCY)",
             "yes" if f & EXPLAINING else "no"]
            for f in Flags]
    return table(["bit", "name (logs, `status`)", "meaning", "kind",
                  "warns the value may be off"], rows)


# --- architecture ------------------------------------------------------------------------

def layers(root: Path) -> str:
    """The import-linter layers contract of pyproject.toml, each room with its docstring."""
    project = tomllib.loads((root / "pyproject.toml").read_text(encoding="utf-8"))
    rows = []
    for contract in project["tool"]["importlinter"]["contracts"]:
        if contract.get("type") != "layers":
            continue
        for i, layer in enumerate(contract["layers"], 1):
            rel = layer.split(".", 1)[1].replace(".", "/")
            path = root / "ddh_vsensor" / rel
            path = path / "__init__.py" if path.is_dir() else path.with_suffix(".py")
            doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
            first = doc.split("\n\n")[0].replace("(see README.md here)", "")
            rows.append([i, f"`{layer}`", prose(first)])
        return (f"Contract: **{contract['name']}**.\n\n"
                + table(["layer", "room", "what it is"], rows))
    raise ValueError("no layers contract in pyproject.toml")


# --- commands ------------------------------------------------------------------------------

def commands() -> str:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    rows = [[f"`ddh-vsensor {a.dest}`", a.help or ""] for a in sub._choices_actions]
    return table(["command", "what it does"], rows)


# --- the Kalman filter's settings ----------------------------------------------------------

def _setting_comments(source: str, cls: str) -> dict[str, str]:
    """The comments of each field of dataclass ``cls`` in ``source``: the lines above it
    (since the last field) and the one beside it."""
    body = next(n for n in ast.parse(source).body
                if isinstance(n, ast.ClassDef) and n.name == cls)
    lines = source.splitlines()
    out, after = {}, body.body[0].end_lineno or body.lineno   # past the docstring
    for node in body.body[1:]:
        if not isinstance(node, ast.AnnAssign) or not isinstance(node.target, ast.Name):
            continue
        above = [ln.strip().lstrip("# ") for ln in lines[after:node.lineno - 1]
                 if ln.strip().startswith("#")]
        beside = lines[node.lineno - 1].partition("#")[2].strip()
        out[node.target.id] = " ".join([*above, beside]).strip()
        after = node.end_lineno or node.lineno
    return out


def _from_config(source: str, func: str) -> dict[str, str]:
    """The settings ``func`` takes from the configuration: setting -> the key's path."""
    node = next(n for n in ast.parse(source).body
                if isinstance(n, ast.FunctionDef) and n.name == func)
    out = {}
    for call in ast.walk(node):
        if isinstance(call, ast.Call):
            for kw in call.keywords:
                if isinstance(kw.value, ast.Attribute):
                    out[kw.arg] = f"tolerances.{kw.value.attr}"
    return out


def kalman_settings() -> str:
    """Every setting of the Kalman filter: its default, what it stands for (the comments
    beside it in the code) and the configuration key that sets it, where one does."""
    from ddh_vsensor.estimator import kalman
    source = Path(kalman.__file__).read_text(encoding="utf-8")
    comments = _setting_comments(source, "KalmanSettings")
    keys = _from_config(source, "settings_from_config")
    defaults = kalman.KalmanSettings()
    rows = [[f"`{f.name}`", f"`{getattr(defaults, f.name)!r}`",
             f"`{keys[f.name]}`" if f.name in keys else "", prose(comments.get(f.name, ""))]
            for f in dataclasses.fields(defaults)]
    return table(["setting", "default", "configuration key", "what it stands for"], rows)
