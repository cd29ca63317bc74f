"""The fleet report: every unit with its numbers, every figure and table on the page (as
parsed here and, where Debian's chromium is installed, as a browser shows it)."""

from __future__ import annotations

import base64
import re
import shutil
import subprocess
from html.parser import HTMLParser

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


class _Page(HTMLParser):
    """Each table's rows (by table id) and each image's attributes."""

    def __init__(self, text: str) -> None:
        super().__init__(convert_charrefs=True)
        self.tables: dict[str, list[list[str]]] = {}
        self.images: list[dict[str, str]] = []
        self._table: list[list[str]] | None = None
        self._in_cell = False
        self.feed(text)

    def handle_starttag(self, tag: str, attrs: list) -> None:
        a = dict(attrs)
        if tag == "table":
            self._table = self.tables.setdefault(a["id"], [])
        elif tag == "tr" and self._table is not None:
            self._table.append([])
        elif tag in ("td", "th") and self._table is not None:
            self._table[-1].append("")
            self._in_cell = True
        elif tag == "img":
            self.images.append(a)

    def handle_endtag(self, tag: str) -> None:
        if tag == "table":
            self._table = None
        elif tag in ("td", "th"):
            self._in_cell = False

    def handle_data(self, data: str) -> None:
        if self._in_cell and self._table is not None:
            self._table[-1][-1] += data


def test_report_page_has_a_row_and_a_figure_per_unit(local_store):
    store, report = local_store
    page = _Page((store.parent / "report.html").read_text(encoding="utf-8"))
    units = report["units"]
    machines = page.tables["machines"]
    assert machines[0][:5] == ["machine", "unit", "logs", "last log", "cause"]
    assert [row[:5] for row in machines[1:]] == [
        [u["machine"], u["actuator"], str(u["logs"]), u["last_log"], u["cause"]] for u in units]
    assert [row[7] for row in machines[1:]] == [f"{u['reference_error_mm']:.3f}" for u in units]
    assert len(page.tables["alarms"]) == 1 + sum(u["alarm"] for u in units)
    trends = [a for a in page.images if a.get("class") == "trend"]
    assert [a["alt"] for a in trends] == [f"trend {u['machine']} {u['actuator']}" for u in units]
    for a in trends:
        png = base64.b64decode(a["src"].removeprefix("data:image/png;base64,"))
        assert png.startswith(b"\x89PNG\r\n\x1a\n")


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
