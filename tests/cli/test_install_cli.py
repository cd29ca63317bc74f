"""``ddh-vsensor install`` in this process: the unit's paths follow the options, and options
systemd cannot honour are refused in one line (the wheel-to-venv path: test_install.py)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from ddh_vsensor.cli.main import main


@pytest.fixture(autouse=True)
def _installed_in_opt(monkeypatch) -> None:
    """As from a venv the unit's sandbox leaves visible, wherever the tests' own Python is
    (a home or /tmp one is refused: test_install_edges.py)."""
    monkeypatch.setattr(sys, "executable", "/opt/ddh-vsensor/bin/python")


def _unit(root: Path) -> str:
    return (root / "etc/systemd/system/ddh-vsensor@.service").read_text()


def test_directories_follow_the_options(tmp_path: Path, capsys) -> None:
    assert main(["install", "--root", str(tmp_path), "--config-dir", "/opt/machine",
                 "--state-dir", "/var/lib/ddh/sensor", "--prefix", "/usr"]) == 0
    unit = _unit(tmp_path)
    assert " --config /opt/machine/loader.yaml --channel %i\n" in unit
    assert "StateDirectory=ddh/sensor\n" in unit
    assert "ConfigurationDirectory=" not in unit       # outside /etc: nothing to manage
    assert "Documentation=file:///usr/share/doc/ddh-vsensor/README.md\n" in unit
    assert (tmp_path / "opt/machine/loader.yaml").is_file()
    assert (tmp_path / "var/lib/ddh/sensor").is_dir()
    assert (tmp_path / "usr/share/doc/ddh-vsensor/README.md").is_file()
    assert "next:" not in capsys.readouterr().out       # staged: no systemctl advice


def test_a_state_dir_outside_var_lib_is_refused_before_anything_is_written(
        tmp_path: Path, capsys) -> None:
    assert main(["install", "--root", str(tmp_path), "--state-dir", "/srv/state"]) == 2
    err = capsys.readouterr().err
    assert "--state-dir /srv/state: must be below /var/lib" in err
    assert len(err.strip().splitlines()) == 1
    assert not any(tmp_path.iterdir())


def test_relative_paths_are_refused(tmp_path: Path, capsys) -> None:
    assert main(["install", "--root", str(tmp_path), "--unit-dir", "units"]) == 2
    assert "--unit-dir units: must be an absolute path" in capsys.readouterr().err


def test_an_unwritable_root_is_one_line(tmp_path: Path, capsys) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["install", "--root", str(blocker)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ddh-vsensor install: error: cannot install:") and "Traceback" not in err
