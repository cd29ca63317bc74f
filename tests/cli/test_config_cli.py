"""``ddh-vsensor config``: print, write, validate, export the JSON Schema."""

from __future__ import annotations

import json
from pathlib import Path

from ddh_vsensor.cli.main import main
from ddh_vsensor.config import DATASHEET_TOLERANCES, DEFAULT_CONFIG, load_config
from ddh_vsensor.config.jsonschema import json_schema


def test_print_default_is_the_shipped_file(capsys) -> None:
    assert main(["config", "--print-default"]) == 0
    assert capsys.readouterr().out == DEFAULT_CONFIG.read_text()


def test_write_then_validate_then_never_overwrite(tmp_path: Path, capsys) -> None:
    path = tmp_path / "etc" / "loader.yaml"
    assert main(["config", "--write", str(path)]) == 0
    assert path.read_text() == DEFAULT_CONFIG.read_text()
    assert main(["config", "--write", str(path)]) == 0          # same content: fine
    assert capsys.readouterr().out.splitlines()[-1].endswith("unchanged")
    assert main(["config", "--validate", str(path)]) == 0
    assert "valid: units boom (Sevcon node 1, sensor node 49)" in capsys.readouterr().out
    edited = path.read_text().replace("channel: can0", "channel: can1")
    path.write_text(edited)
    assert main(["config", "--write", str(path)]) == 2
    assert "not overwritten" in capsys.readouterr().err
    assert path.read_text() == edited


def test_write_datasheet_changes_only_the_tolerances(tmp_path: Path, capsys) -> None:
    """A machine not yet commissioned starts from a datasheet's bands; everything else (the
    physics, hence the tables and the state files) is the default's."""
    path = tmp_path / "new.yaml"
    assert main(["config", "--write", str(path), "--datasheet"]) == 0
    written, shipped = load_config(path), load_config(None)
    assert written.tolerances == DATASHEET_TOLERANCES != shipped.tolerances
    assert written.physics_hash() == shipped.physics_hash()
    changed = [a for a, b in zip(path.read_text().splitlines(),
                                 DEFAULT_CONFIG.read_text().splitlines()) if a != b]
    assert len(changed) == 5 and all("# chosen (a datasheet: " in line for line in changed)
    assert main(["config", "--write", str(path)]) == 2        # the plain default differs
    assert "differs from the default" in capsys.readouterr().err


def test_datasheet_needs_write(capsys) -> None:
    assert main(["config", "--print-default", "--datasheet"]) == 2
    assert capsys.readouterr().err.strip() == ("ddh-vsensor config: error: --datasheet goes "
                                              "with --write PATH")


def test_validate_names_the_key_and_exits_2(tmp_path: Path, capsys) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(DEFAULT_CONFIG.read_text().replace("stroke_mm: 850.0", "stroke_mm: oops"))
    assert main(["config", "--validate", str(path)]) == 2
    err = capsys.readouterr().err
    assert "units.bucket.stroke_mm" in err and len(err.strip().splitlines()) == 1


def test_one_of_the_actions_is_required(capsys) -> None:
    import pytest
    with pytest.raises(SystemExit) as exit_:
        main(["config"])
    assert exit_.value.code == 2


def test_json_schema_to_stdout_or_a_file(tmp_path: Path, capsys) -> None:
    assert main(["config", "--json-schema"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json_schema() and printed["required"][:2] == ["oil", "hydraulics"]
    out = tmp_path / "ddh-vsensor.schema.json"
    assert main(["config", "--json-schema", str(out)]) == 0
    assert capsys.readouterr().out.strip() == f"{out}: written"
    assert json.loads(out.read_text()) == printed
    assert main(["config", "--json-schema", str(tmp_path / "no" / "dir" / "s.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot write" in err[0]
