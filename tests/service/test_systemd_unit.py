"""The systemd unit: the settings the daemon relies on, and ``systemd-analyze verify``."""

from __future__ import annotations

import configparser
import contextlib
import io
import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
UNIT = REPO / "systemd" / "ddh-vsensor@.service"


def _unit() -> dict[str, list[str]]:
    values: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        line = line.strip()
        if line and not line.startswith(("#", ";", "[")) and "=" in line:
            key, value = line.split("=", 1)
            values.setdefault(key.strip(), []).append(value.strip())
    return values


def test_unit_has_notify_watchdog_restart_state_and_hardening() -> None:
    u = _unit()
    assert u["Type"] == ["notify"]
    assert u["WatchdogSec"] and u["Restart"] == ["on-failure"]
    assert u["StateDirectory"] == ["ddh-vsensor"]
    assert "ddh-vsensor run" in u["ExecStart"][0]
    # the bus is the instance's (ddh-vsensor@can0), ordered after its network device
    assert u["ExecStart"][0].endswith(" --channel %i")
    assert u["Wants"] == ["sys-subsystem-net-devices-%i.device"]
    assert "sys-subsystem-net-devices-%i.device" in u["After"][0].split()
    assert "can0" not in UNIT.read_text().split("[Unit]")[1]
    # a bad configuration (exit 2) is not restarted in a loop
    assert u["RestartPreventExitStatus"] == ["2"]
    for key, value in (("DynamicUser", "yes"), ("ProtectSystem", "strict"),
                       ("NoNewPrivileges", "yes"), ("PrivateTmp", "yes")):
        assert u[key] == [value], key
    assert set(u["RestrictAddressFamilies"][0].split()) == {"AF_CAN", "AF_UNIX"}
    assert configparser.ConfigParser(strict=False, interpolation=None).read(UNIT)


def test_the_packaged_unit_is_this_one() -> None:
    packaged = REPO / "ddh_vsensor" / "data" / UNIT.name
    assert packaged.read_bytes() == UNIT.read_bytes()


@pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                    reason="systemd-analyze is not installed")
def test_systemd_analyze_verify(tmp_path: Path) -> None:
    from ddh_vsensor.cli.main import main
    # the unit as `ddh-vsensor install` writes it (paths of this installation) into a
    # staging root; the wheel-to-venv path: tests/cli/test_install.py
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["install", "--root", str(tmp_path)]) == 0
    unit_dir = tmp_path / "etc" / "systemd" / "system"
    result = subprocess.run(["systemd-analyze", "verify", "ddh-vsensor@can0.service"],
                            capture_output=True, text=True, timeout=60,
                            env={**os.environ, "SYSTEMD_UNIT_PATH": f"{unit_dir}:"})
    assert result.returncode == 0, result.stderr
    assert "ddh-vsensor@" not in result.stderr, result.stderr
