"""The fleet report as a browser shows it: rendered in headless Chromium, every figure and
table is there."""

from __future__ import annotations

import re
import shutil
import subprocess

import pytest

from ddh_vsensor.cli.main import main

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def test_report_lists_every_unit_with_its_numbers(local_store):
    _, report = local_store
    assert len(report["units"]) >= 2
    for u in report["units"]:
        assert u["cause"] == "none" or u["expected_error_mm"] is not None
        if u["alarm"]:
            assert u["extension_file"] and u["cause"] != "none"


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed")
def test_report_renders_in_headless_chromium(local_store, tmp_path):
    store, report = local_store
    assert report["units"]
    out = tmp_path / "report.html"
    assert main(["fleet", "report", "--store", str(store), "--out", str(out)]) == 0
    dom = subprocess.run([CHROMIUM, *FLAGS, f"--user-data-dir={tmp_path / 'profile'}",
                          "--dump-dom", out.as_uri()], capture_output=True, text=True,
                         timeout=120, check=True).stdout
    units = len(report["units"])
    assert len(re.findall(r"<img class=\"trend\"[^>]*src=\"data:image/png;base64,", dom)) \
        == units
    for table in ("alarms", "machines"):
        assert f'<table id="{table}">' in dom
    machines = dom.split('<table id="machines">')[1].split("</table>")[0]
    assert machines.count("<tr>") == units + 1
    alarms = dom.split('<table id="alarms">')[1].split("</table>")[0]
    assert alarms.count("<tr>") == sum(u["alarm"] for u in report["units"]) + 1
