"""``ddh-vsensor install`` where the hardened unit could not run the installation (a venv in
/tmp or a home directory), with another machine's configuration, and the unit's Description
naming the configured cylinders."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import pytest
import yaml

from ddh_vsensor.cli.install import check_visible
from ddh_vsensor.cli.main import main
from ddh_vsensor.errors import UserError

REPO = Path(__file__).resolve().parents[2]
UNIT = "etc/systemd/system/ddh-vsensor@.service"


@pytest.fixture
def lift_tilt(tmp_path: Path) -> Path:
    """The loader with its units renamed to lift and tilt, as a file."""
    data = yaml.safe_load((REPO / "config" / "loader.yaml").read_text())
    for section in (data["units"], data["can"]["units"], data["faults"]["heartbeat_node_ids"]):
        for old, new in {"boom": "lift", "bucket": "tilt"}.items():
            section[new] = section.pop(old)
    data.pop("work_cycle")          # its cycles name the loader's units
    path = tmp_path / "lift_tilt.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _description(root: Path) -> str:
    (line,) = [x for x in (root / UNIT).read_text().splitlines()
               if x.startswith("Description=")]
    return line


@pytest.mark.parametrize("venv", ["/tmp/venv", "/home/ana/venv", "/root/.venv"])
def test_a_venv_the_sandbox_hides_is_refused_unless_forced(venv: str, monkeypatch) -> None:
    monkeypatch.setattr(sys, "executable", f"{venv}/bin/python")
    setting = "PrivateTmp=yes" if venv.startswith("/tmp") else "ProtectHome=yes"
    with pytest.raises(UserError) as exc:
        check_visible(force=False)
    assert f"{venv}/bin/python: the unit's {setting} hides this" in str(exc.value)
    assert "--force" in str(exc.value) and "\n" not in str(exc.value)
    check_visible(force=True)


@pytest.mark.parametrize("venv", ["/tmp/venv", "/home/ana/venv"])
def test_a_staged_installation_from_a_hidden_venv_says_so(venv: str, tmp_path: Path,
                                                          monkeypatch, caplog) -> None:
    """Below another root (an image, a look) the same problem is a warning, not a refusal."""
    monkeypatch.setattr(sys, "executable", f"{venv}/bin/python")
    root = tmp_path / "root"
    with caplog.at_level(logging.WARNING, logger="ddh_vsensor.cli.install"):
        assert main(["install", "--root", str(root)]) == 0
    assert any("hides this from the service" in r.getMessage() for r in caplog.records)
    assert f"ExecStart={venv}/bin/python -m ddh_vsensor run" in (root / UNIT).read_text()


def test_a_venv_in_opt_installs(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(sys, "executable", "/opt/ddh-vsensor/bin/python")
    assert main(["install", "--root", str(tmp_path)]) == 0


def test_another_machines_configuration_is_installed_and_named(lift_tilt: Path, tmp_path: Path,
                                                               monkeypatch) -> None:
    monkeypatch.setattr(sys, "executable", "/opt/ddh-vsensor/bin/python")
    root = tmp_path / "root"
    assert main(["install", "--root", str(root), "--config", str(lift_tilt)]) == 0
    installed = root / "etc/ddh-vsensor/lift_tilt.yaml"
    assert installed.read_text() == lift_tilt.read_text()
    unit = (root / UNIT).read_text()
    assert " --config /etc/ddh-vsensor/lift_tilt.yaml --channel %i\n" in unit
    assert _description(root) == ("Description=ddh-vsensor virtual position sensor on %i "
                                  "(DDH lift and tilt cylinders)")
    assert "boom" not in unit and "bucket" not in unit


def test_the_default_installation_names_the_loaders_cylinders(tmp_path: Path,
                                                              monkeypatch) -> None:
    monkeypatch.setattr(sys, "executable", "/opt/ddh-vsensor/bin/python")
    assert main(["install", "--root", str(tmp_path)]) == 0
    assert _description(tmp_path) == ("Description=ddh-vsensor virtual position sensor on %i "
                                      "(DDH boom and bucket cylinders)")


def test_an_invalid_configuration_is_one_line_before_anything_is_written(
        tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.setattr(sys, "executable", "/opt/ddh-vsensor/bin/python")
    bad = tmp_path / "bad.yaml"
    bad.write_text("units: [\n")
    root = tmp_path / "root"
    assert main(["install", "--root", str(root), "--config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(bad) in err
    assert not root.exists()


def test_the_shipped_unit_names_no_machine() -> None:
    for path in (REPO / "systemd" / "ddh-vsensor@.service",
                 REPO / "ddh_vsensor" / "data" / "ddh-vsensor@.service"):
        text = path.read_text()
        assert "boom" not in text and "bucket" not in text, path
