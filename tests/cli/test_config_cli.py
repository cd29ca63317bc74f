"""``ddh-vsensor config``: print, write, validate."""

from __future__ import annotations

from pathlib import Path

from ddh_vsensor.cli.main import main
from ddh_vsensor.config import DEFAULT_CONFIG


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
