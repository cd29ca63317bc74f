"""The exported JSON Schema agrees with the validator: every shipped configuration passes it,
and a value outside any field's bounds, an unknown key or a wrong choice fails both."""

from __future__ import annotations

import copy
import dataclasses
import typing
from pathlib import Path
from typing import Any

import jsonschema
import pytest

from ddh_vsensor.config import Config, ConfigError, parse_config, parse_yaml
from ddh_vsensor.config.jsonschema import json_schema
from ddh_vsensor.config.schema import DEFAULT_CONFIG, EstimatorConfig, FaultsConfig

from ..conftest import REPO

SHIPPED = [DEFAULT_CONFIG, *sorted((REPO / "config").glob("*.yaml"))]
SCHEMA = json_schema()
VALIDATOR = jsonschema.Draft202012Validator(SCHEMA)


def _raw(path: Path = DEFAULT_CONFIG) -> dict[str, Any]:
    return parse_yaml(path.read_text(encoding="utf-8"), str(path))


def _schema_errors(data: Any) -> list[str]:
    return [f"{'.'.join(map(str, e.absolute_path))}: {e.message}"
            for e in VALIDATOR.iter_errors(data)]


def _validator_rejects(data: Any) -> bool:
    try:
        parse_config(data)
    except ConfigError:
        return True
    return False


def test_the_schema_is_a_valid_draft_2020_12_schema() -> None:
    assert SCHEMA["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    jsonschema.Draft202012Validator.check_schema(SCHEMA)


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_every_shipped_configuration_passes(path: Path) -> None:
    data = _raw(path)
    parse_config(data, str(path))                          # the validator's verdict
    assert _schema_errors(data) == []


def _bounded_fields(cls: type, data: dict[str, Any], path: tuple = ()):
    """(path, field type, bound key, bound) of every bounded number present in ``data``."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        tp, value = hints[f.name], data[f.name]
        inner = [a for a in typing.get_args(tp) if dataclasses.is_dataclass(a)]
        if dataclasses.is_dataclass(tp):
            yield from _bounded_fields(tp, value, (*path, f.name))
        elif typing.get_origin(tp) is dict and inner:
            for key, item in value.items():
                yield from _bounded_fields(inner[0], item, (*path, f.name, key))
        elif typing.get_origin(tp) is tuple and inner:
            for i, item in enumerate(value):
                yield from _bounded_fields(inner[0], item, (*path, f.name, i))
        elif typing.get_origin(tp) is not dict and value is not None:
            for key in ("gt", "ge", "lt", "le"):
                if key in f.metadata:
                    yield (*path, f.name), tp, key, f.metadata[key]


def _beyond(tp: Any, key: str, bound: float) -> float:
    """The nearest value on the wrong side of a bound."""
    step = 1 if tp is int else max(abs(bound) * 0.01, 1e-6)
    return {"gt": bound, "lt": bound, "ge": bound - step, "le": bound + step}[key]


def _set(data: dict[str, Any], path: tuple, value: Any) -> dict[str, Any]:
    out = copy.deepcopy(data)
    node = out
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    return out


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_a_value_beyond_any_bound_fails_the_schema_as_the_validator(path: Path) -> None:
    data = _raw(path)
    cases = list(_bounded_fields(Config, data))
    assert len(cases) > 100                                # every unit, every section
    for where, tp, key, bound in cases:
        bad = _set(data, where, _beyond(tp, key, bound))
        assert _validator_rejects(bad), (where, key)
        assert _schema_errors(bad), (where, key, bound)


@pytest.mark.parametrize(("where", "value"), [
    (("oil", "viscosity_cst_at_40c"), -32.0),              # a negative viscosity
    (("estimator", "mode"), "fast"),                        # not one of the Literal's choices
    (("faults", "preset"), "sometimes"),
    (("can", "io_module_node_id"), "0x10"),                 # text for a whole number
    (("estimator", "adaptation"), "yes"),                   # text for true/false
    (("tables", "temperatures_c"), 20.0),                   # a number for a list
    (("units", "boom", "stroke_mm"), True),                 # true/false for a number
    (("oil", "name"), 32),                                  # a number for text
])
def test_known_bad_values_fail_both(where: tuple, value: Any) -> None:
    bad = _set(_raw(), where, value)
    assert _validator_rejects(bad)
    assert _schema_errors(bad)


@pytest.mark.parametrize("where", [(), ("oil",), ("units", "boom"), ("units", "boom", "motor"),
                                   ("can", "units", "bucket"), ("faults",)])
def test_an_unknown_key_fails_both(where: tuple) -> None:
    data = copy.deepcopy(_raw())
    node = data
    for k in where:
        node = node.setdefault(k, {})
    node["viscosity_typo"] = 1.0
    assert _validator_rejects(data)
    assert any("viscosity_typo" in e for e in _schema_errors(data))


@pytest.mark.parametrize("section", ["oil", "units", "can", "bus"])
def test_a_missing_required_section_fails_both(section: str) -> None:
    data = _raw()
    del data[section]
    assert _validator_rejects(data)
    assert _schema_errors(data)


def test_optional_sections_and_nulls_pass_both() -> None:
    data = _raw()
    for key in ("faults", "buses"):
        data.pop(key, None)
    data["work_cycle"] = None
    parse_config(data)
    assert _schema_errors(data) == []


def test_every_key_is_described_with_its_type_default_and_comment() -> None:
    defs = SCHEMA["$defs"]
    for cls in (EstimatorConfig, FaultsConfig):
        props = defs[cls.__name__]["properties"]
        assert list(props) == [f.name for f in dataclasses.fields(cls)]
        for f in dataclasses.fields(cls):
            if f.default is not dataclasses.MISSING:
                assert props[f.name]["default"] == f.default
    est = defs["EstimatorConfig"]
    mode = est["properties"]["mode"]
    assert mode["type"] == "string"
    assert mode["enum"] == ["full", "paper", "dynamic", "kalman"]
    assert "Kalman filter" in mode["description"]
    assert est["required"] == [f.name for f in dataclasses.fields(EstimatorConfig)
                               if f.default is dataclasses.MISSING]
    assert "torque limit" in est["properties"]["dynamic_torque_step"]["description"]
    assert est["properties"]["max_gap_s"]["minimum"] == 0.001
    assert "exclusiveMinimum" not in est["properties"]["max_gap_s"]   # the tighter bound only
    assert defs["OilConfig"]["description"].startswith("Hydraulic oil")
    assert "source" not in SCHEMA["properties"]                       # internal, not a key


def test_draft_07_readers_give_the_same_verdicts() -> None:
    """The YAML language server validates with draft-07 semantics: the schema's keywords
    must mean the same there."""
    draft7 = jsonschema.Draft7Validator(SCHEMA)
    for path in SHIPPED:
        assert list(draft7.iter_errors(_raw(path))) == []
    for where, value in ((("oil", "viscosity_cst_at_40c"), -32.0),
                         (("estimator", "mode"), "fast"),
                         (("faults", "heartbeat_timeout_s"), 0.0),
                         (("oil", "typo"), 1.0)):
        assert list(draft7.iter_errors(_set(_raw(), where, value))), where
    faults = SCHEMA["properties"]["faults"]
    assert faults["allOf"] == [{"$ref": "#/$defs/FaultsConfig"}] and "default" in faults
