"""``config --schema``: every key of every shipped machine is listed, with bounds and defaults
(the docs' configuration reference is generated from the same lines: tests/docs)."""

from __future__ import annotations

import re

import yaml

from ddh_vsensor.cli.config import schema_lines

from .conftest import MACHINES


def _leaf_paths(node, path: str = "") -> set[str]:
    """Key paths of a YAML document in the schema's notation (<unit>, <name>, [i])."""
    if isinstance(node, dict):
        out = set()
        for k, v in node.items():
            if path.endswith(("units", "cycles", "buses")) and isinstance(v, dict):
                key = f"{path}.<{'name' if not path.endswith('units') else 'unit'}>"
            else:
                key = f"{path}.{k}" if path else str(k)
            out |= {key} | _leaf_paths(v, key) if not (
                path.endswith(("references_mm", "hall_bits", "start_mm", "heartbeat_node_ids"))
                or path in ("bus",) or path.startswith("buses")) else set()
        return out
    if isinstance(node, list) and node and isinstance(node[0], dict):
        return set().union(*(_leaf_paths(v, f"{path}[i]") for v in node))
    return set()


def test_schema_lists_every_key_of_every_machine():
    keys = {line.split()[0] for line in schema_lines()}
    for machine in MACHINES:
        paths = _leaf_paths(yaml.safe_load(machine.read_text()))
        missing = {p for p in paths if p not in keys and not p.endswith(">")}
        assert not missing, (machine.name, sorted(missing))


def test_schema_shows_bounds_and_defaults():
    text = "\n".join(schema_lines())
    assert re.search(r"^units\.<unit>\.cylinders +whole number, >= 1 <= 16; required$", text,
                     re.M)
    assert re.search(r"^work_cycle\.cycles\.<name>\.pause_s +number, >= 0 <= 3600; "
                     r"default 0\.4$", text, re.M)

