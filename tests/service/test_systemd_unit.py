"""The systemd unit: the settings the daemon relies on, and ``systemd-analyze verify``."""

from __future__ import annotations

import configparser
import shutil
import subprocess
from pathlib import Path

import pytest

UNIT = Path(__file__).resolve().parents[2] / "systemd" / "ddh-vsensor.service"


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
    for key, value in (("DynamicUser", "yes"), ("ProtectSystem", "strict"),
                       ("NoNewPrivileges", "yes"), ("PrivateTmp", "yes")):
        assert u[key] == [value], key
    assert set(u["RestrictAddressFamilies"][0].split()) == {"AF_CAN", "AF_UNIX"}
    assert configparser.ConfigParser(strict=False, interpolation=None).read(UNIT)


@pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                    reason="systemd-analyze is not installed")
def test_systemd_analyze_verify(tmp_path: Path) -> None:
    exe = shutil.which("ddh-vsensor")
    if exe is None:
        pytest.skip("the ddh-vsensor script is not installed (pip install -e .)")
    # verify checks that ExecStart exists: point it at this installation
    text = UNIT.read_text().replace("/opt/ddh-vsensor/bin/ddh-vsensor", exe)
    unit = tmp_path / UNIT.name
    unit.write_text(text)
    result = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert "ddh-vsensor.service" not in result.stderr, result.stderr
