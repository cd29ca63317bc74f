"""Config validation: every bad value gives one message naming file, key path and problem."""

import copy
import subprocess
import sys

import pytest
import yaml

from ddh_vsensor.config import DEFAULT_CONFIG, ConfigError, load_config, parse_config, parse_yaml
from ddh_vsensor.errors import UserError

from ..conftest import REPO

RAW = yaml.safe_load((REPO / "config" / "loader.yaml").read_text())


def test_every_value_says_paper_or_chosen():
    for line in (REPO / "config" / "loader.yaml").read_text().splitlines():
        body = line.split("#", 1)[0].strip()
        if body and not body.endswith(":") and ":" in body:
            comment = line.split("#", 1)[1] if "#" in line else ""
            nested = line.strip().startswith(("bottom", "mid", "top", "interface", "channel"))
            assert "paper" in comment or "chosen" in comment or nested, line


def test_reference_config_loads(cfg):
    assert cfg.unit("boom").cylinders == 2
    assert cfg.unit("bucket").pump_b.relief_bar == 172.0
    assert load_config(None) == cfg          # the embedded default is the same machine


def _mutate(path, value, delete=False):
    data = copy.deepcopy(RAW)
    node = data
    keys = path.split(".")
    for k in keys[:-1]:
        node = node[k]
    if delete:
        del node[keys[-1]]
    else:
        node[keys[-1]] = value
    return data


@pytest.mark.parametrize("path,value,delete,words", [
    ("units.boom.area_a_mm2", -5.0, False, "greater than"),
    ("units.boom.area_b_mm2", 20000.0, False, "smaller than the piston-side"),
    ("units.boom.pump_a.volumetric_efficiency", 1.2, False, "at most 1"),
    ("units.bucket.pump_b.hydromechanical_efficiency", 0.0, False, "greater than 0"),
    ("units.boom.pump_b.displacement_cm3_rev", "big", False, "expected a number"),
    ("units.boom.cylinders", 2.5, False, "whole number"),
    ("units.boom.stroke_mm", None, True, "missing key"),
    ("units.boom.colour", "red", False, "unknown key"),
    ("units.crane", {}, False, "missing key"),
    ("can.units.crane", {"sevcon_node_id": 3, "sensor_node_id": 51, "hall_bits": {}}, False,
     "no such unit (units: boom, bucket)"),
    ("faults.heartbeat_node_ids", {"stick": 3}, False, "no such unit"),
    ("can.units.boom.bus", "can1", False, "unknown bus 'can1' (known: default)"),
    ("can.units.boom.hall_bits.top", 64, False, "not in 0..63"),
    ("buses", {"default": {"interface": "virtual"}}, False, "other than 'default'"),
    ("units.boom.references_mm.mid", 400.0, False, "outside the stroke"),
    ("oil.viscosity_cst_at_100c", 40.0, False, "below viscosity_cst_at_40c"),
])
def test_bad_values_name_the_key_path(path, value, delete, words):
    with pytest.raises(ConfigError) as err:
        parse_config(_mutate(path, value, delete), source="machine.yaml")
    msg = str(err.value)
    assert msg.startswith("machine.yaml: ")
    assert path.split(".")[0] in msg and words in msg, msg


def _renamed(mapping: dict, names: dict) -> dict:
    return {names.get(k, k): v for k, v in mapping.items()}


def test_units_take_any_names_in_any_order():
    data = copy.deepcopy(RAW)
    names = {"boom": "lift", "bucket": "tilt"}
    data["units"] = dict(reversed(list(_renamed(data["units"], names).items())))
    data["can"]["units"] = _renamed(data["can"]["units"], names)
    if "heartbeat_node_ids" in data.get("faults", {}):
        data["faults"]["heartbeat_node_ids"] = _renamed(data["faults"]["heartbeat_node_ids"], names)
    data.pop("work_cycle")              # names the loader's units (optional; tests/sim)
    cfg = parse_config(data, source="machine.yaml")
    assert cfg.unit_names == ("tilt", "lift")
    assert cfg.unit("lift").stroke_mm == RAW["units"]["boom"]["stroke_mm"]
    with pytest.raises(UserError, match=r"unknown unit 'boom' \(this machine's units: tilt, lift\)"):
        cfg.unit("boom")


@pytest.mark.parametrize("name", ["Boom", "2nd", "arm-1", "a" * 33, ""])
def test_unit_names_are_lower_case_identifiers(name):
    data = copy.deepcopy(RAW)
    data["units"][name] = data["units"].pop("boom")
    data["can"]["units"][name] = data["can"]["units"].pop("boom")
    data.get("faults", {}).get("heartbeat_node_ids", {}).pop("boom", None)
    with pytest.raises(ConfigError, match="lower-case identifier"):
        parse_config(data, source="machine.yaml")


def test_one_unit_machine_and_a_second_bus():
    data = copy.deepcopy(RAW)
    del data["units"]["bucket"], data["can"]["units"]["bucket"]
    data.get("faults", {}).get("heartbeat_node_ids", {}).pop("bucket", None)
    data.pop("work_cycle")              # names the loader's units (optional; tests/sim)
    data["buses"] = {"can1": {"interface": "virtual", "channel": "x"}}
    data["can"]["units"]["boom"]["bus"] = "can1"
    cfg = parse_config(data, source="machine.yaml")
    assert cfg.unit_names == ("boom",) and cfg.bus_names == ("default", "can1")
    assert cfg.units_on_bus("can1") == ("boom",) and cfg.units_on_bus("default") == ()
    assert cfg.bus_kwargs("can1") == {"interface": "virtual", "channel": "x"}


def test_cli_exits_2_without_traceback(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(_mutate("units.boom.area_a_mm2", -1.0)))
    proc = subprocess.run([sys.executable, "-m", "ddh_vsensor.cli.main", "steady", "--config",
                           str(bad), "--actuator", "boom", "--speed-rpm", "100",
                           "--oil-temp-c", "27"], capture_output=True, text=True)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert "bad.yaml: units.boom.area_a_mm2" in proc.stderr


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "nope.yaml")
    broken = tmp_path / "broken.yaml"
    broken.write_text("units: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(broken)


@pytest.mark.parametrize("path,value,words", [
    ("can.event_timer_ms", 65535.0, "event_timer"),
    ("can.position_step_mm", 1e-12, "at least"),
    ("estimator.max_gap_s", 1e300, "at most"),
    ("estimator.state_save_interval_s", 1e9, "at most"),
    ("units.boom.motor.speed_limit_rpm", 1e12, "at most"),
    ("faults.preset", "sometimes", "not one of"),
    ("faults.heartbeat_timeout_s", 0.0, "at least"),
    ("faults.event_timer_max_ms", 1e9, "at most"),
])
def test_values_are_bounded_above_as_well(path, value, words):
    with pytest.raises(ConfigError) as err:
        parse_config(_mutate(path, value), source="machine.yaml")
    assert path.split(".")[0] in str(err.value) and words in str(err.value), str(err.value)


def test_faults_section_is_optional_with_documented_defaults(cfg):
    data = copy.deepcopy(RAW)
    del data["faults"]
    bare = parse_config(data)
    assert bare.faults.heartbeat_node_ids == {}          # nothing consumed unless configured
    assert bare.faults.preset == cfg.faults.preset == "enabled"
    assert bare.physics_hash() == cfg.physics_hash()     # saved states stay valid


# the reference loader's estimate hash: a baseline measured under it holds for this hash only
LOADER_ESTIMATE_HASH = "867420c477315b28"


def test_the_drives_torque_gain_is_how_it_reads_not_physics(cfg):
    """The drive's torque gain left at 1 keeps both hashes (the loader's baselines stay
    valid); set, it changes what an estimate depends on and not the physics or tables."""
    assert cfg.unit("boom").motor.torque_gain == 1.0
    assert cfg.estimate_hash() == LOADER_ESTIMATE_HASH
    data = copy.deepcopy(RAW)
    data["units"]["boom"]["motor"]["torque_gain"] = 1.0
    same = parse_config(data)
    assert (same.physics_hash(), same.estimate_hash()) == (cfg.physics_hash(),
                                                           cfg.estimate_hash())
    data["units"]["boom"]["motor"]["torque_gain"] = 1.05
    gained = parse_config(data)
    assert gained.unit("boom").motor.torque_gain == 1.05
    assert gained.physics_hash() == cfg.physics_hash()
    assert gained.estimate_hash() != cfg.estimate_hash()


@pytest.mark.parametrize("value,words", [(0.0, "must be at least 0.5"),
                                         (5.0, "must be at most 2.0")])
def test_a_torque_gain_out_of_bounds_is_one_line(value, words):
    with pytest.raises(ConfigError) as err:
        parse_config(_mutate("units.boom.motor.torque_gain", value), source="machine.yaml")
    assert str(err.value) == (f"machine.yaml: units.boom.motor.torque_gain: {value} is not "
                              f"physical here: {words}")


def test_max_speed_from_the_physics(cfg):
    u = cfg.unit("boom")
    side_a = (u.motor.speed_limit_rpm / 60 * u.pump_a.speed_ratio * u.pump_a.displacement_cm3_rev
              * 1e3 / (u.cylinders * u.area_a_mm2) / u.pump_a.volumetric_efficiency)
    assert cfg.max_speed_mm_s("boom") >= side_a * cfg.faults.max_speed_factor
    assert 100.0 < cfg.max_speed_mm_s("boom") < 300.0


def _bomb() -> str:
    lines = ["a: &a [x, x, x, x, x, x, x, x, x]"]
    for i in range(1, 10):
        prev, cur = chr(ord("a") + i - 1), chr(ord("a") + i)
        lines.append(f"{cur}: &{cur} [" + ", ".join([f"*{prev}"] * 9) + "]")
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("text,words", [
    (_bomb(), "aliases"),
    ("oil: " + "[" * 20000 + "]" * 20000, "nested"),
    ("oil: " + "{a: " * 60 + "1" + "}" * 60, "nested deeper"),
    ("x: !!python/object/apply:os.system [ls]", "not valid YAML"),
])
def test_hostile_yaml_is_one_short_error(tmp_path, text, words):
    path = tmp_path / "hostile.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert words in str(err.value) and len(str(err.value)) <= 300, str(err.value)[:500]


def test_huge_and_special_files_are_refused(tmp_path):
    big = tmp_path / "big.yaml"
    with open(big, "wb") as fh:
        fh.truncate(2_000_000)
    with pytest.raises(ConfigError, match="larger than"):
        load_config(big)
    import os
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    with pytest.raises(ConfigError, match="not a regular file"):
        load_config(fifo)


def test_a_huge_bad_value_is_truncated_in_the_message():
    with pytest.raises(ConfigError) as err:
        parse_config(_mutate("units.boom.stroke_mm", "y" * 100_000), source="machine.yaml")
    assert len(str(err.value)) <= 300


def test_a_key_given_twice_is_an_error_with_both_lines(tmp_path):
    """YAML readers keep the last of two equal keys: an edit to the first would be lost."""
    text = (DEFAULT_CONFIG.read_text().replace(
        "      torque_lag_s: 0.0", "      torque_lag_s: 0.0\n      torque_lag_s: 0.001", 1))
    path = tmp_path / "twice.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=r"line (\d+): key 'torque_lag_s' given twice "
                                          r"\(first on line \d+\)"):
        load_config(path)
    merged = tmp_path / "merged.yaml"
    merged.write_text("base: &b {x: 1}\nother:\n  <<: *b\n  x: 2\n")
    assert parse_yaml(merged.read_text(), str(merged)) == {"base": {"x": 1},
                                                           "other": {"x": 2}}
