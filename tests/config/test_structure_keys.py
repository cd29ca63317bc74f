"""The plant-structure keys (pump leakage's orifice share and speed gain, seal friction with
pressure, hose expansion): default 0, bounded with the key path in the refusal, in the JSON
Schema and the reference, and in the physics hash only where set, so that every existing
configuration keeps its hash (state files and table sets are keyed by it)."""

from __future__ import annotations

import copy
from typing import Any

import jsonschema
import pytest
import yaml

from ddh_vsensor.cli.config import schema_lines
from ddh_vsensor.config import DEFAULT_CONFIG, ConfigError, load_config, parse_config
from ddh_vsensor.config.jsonschema import json_schema

from ..conftest import REPO

RAW = yaml.safe_load((REPO / "config" / "loader.yaml").read_text())
# the hashes the shipped machines had before these keys existed
SHIPPED_HASHES = {"loader": "76d6552ca0eeb630", "bench": "c0d7a1f037f62bb2",
                  "excavator": "78c7cdf76c7ebfc8"}
# every structure key's path in the loader's file, and its largest value
KEYS = {
    "units.boom.pump_a.leakage_orifice_share": 0.9,
    "units.bucket.pump_b.leakage_orifice_share": 0.9,
    "units.boom.pump_b.leakage_speed_gain": 2.0,
    "units.bucket.pump_a.leakage_speed_gain": 2.0,
    "units.boom.seal_friction_share": 0.2,
    "hydraulics.hose_expansion_per_100bar": 0.2,
}


def _with(path: str, value: Any) -> dict[str, Any]:
    data = copy.deepcopy(RAW)
    node = data
    keys = path.split(".")
    for k in keys[:-1]:
        node = node[k]
    node[keys[-1]] = value
    return data


def test_shipped_machines_keep_their_physics_hash():
    for stem, digest in SHIPPED_HASHES.items():
        assert load_config(REPO / "config" / f"{stem}.yaml").physics_hash() == digest, stem
    assert load_config(DEFAULT_CONFIG).physics_hash() == SHIPPED_HASHES["loader"]


def test_absent_keys_are_the_nominal_model():
    cfg = load_config(REPO / "config" / "loader.yaml")
    assert cfg.hydraulics.hose_expansion_per_100bar == 0.0
    for unit in cfg.units.values():
        assert unit.seal_friction_share == 0.0
        for pump in (unit.pump_a, unit.pump_b):
            assert pump.leakage_orifice_share == 0.0 and pump.leakage_speed_gain == 0.0


@pytest.mark.parametrize("path", KEYS)
def test_a_set_key_is_physics_and_an_explicit_zero_is_not(path):
    nominal = parse_config(RAW).physics_hash()
    assert parse_config(_with(path, 0.0)).physics_hash() == nominal
    hashes = {parse_config(_with(path, v)).physics_hash() for v in (0.01, 0.02)}
    assert len(hashes) == 2 and nominal not in hashes


@pytest.mark.parametrize("path,value,words", [
    *[(path, top * 1.01, f"at most {top}") for path, top in KEYS.items()],
    *[(path, -0.01, "at least 0.0") for path in KEYS],
    ("units.boom.pump_a.leakage_orifice_share", "30 %", "expected a number"),
    ("hydraulics.hose_expansion_per_100bar", None, "expected a number"),
])
def test_out_of_bounds_is_refused_with_the_key_path(path, value, words):
    with pytest.raises(ConfigError) as err:
        parse_config(_with(path, value), source="machine.yaml")
    assert str(err.value).startswith(f"machine.yaml: {path}: "), str(err.value)
    assert words in str(err.value)


@pytest.mark.parametrize("path", KEYS)
def test_the_json_schema_bounds_and_describes_each_key(path):
    validator = jsonschema.Draft202012Validator(json_schema())
    assert not list(validator.iter_errors(_with(path, KEYS[path])))
    assert list(validator.iter_errors(_with(path, KEYS[path] * 1.01)))
    assert list(validator.iter_errors(_with(path, -0.01)))


def test_the_reference_lists_each_key_with_its_bounds_and_default():
    lines = {line.split()[0]: line for line in schema_lines()}
    expected = {
        "units.<unit>.pump_a.leakage_orifice_share": "number, >= 0 <= 0.9; default 0.0",
        "units.<unit>.pump_b.leakage_speed_gain": "number, >= 0 <= 2; default 0.0",
        "units.<unit>.seal_friction_share": "number, >= 0 <= 0.2; default 0.0",
        "hydraulics.hose_expansion_per_100bar": "number, >= 0 <= 0.2; default 0.0",
    }
    for key, text in expected.items():
        assert lines[key].split(None, 1)[1] == text, lines[key]
    defs = json_schema()["$defs"]
    described = [defs["PumpConfig"]["properties"]["leakage_orifice_share"],
                 defs["PumpConfig"]["properties"]["leakage_speed_gain"],
                 defs["UnitConfig"]["properties"]["seal_friction_share"],
                 defs["HydraulicsConfig"]["properties"]["hose_expansion_per_100bar"]]
    for prop in described:
        assert "the tables' steady state does not carry it" in prop["description"], prop
