"""The fleet report: every unit with its numbers and its finding in words, every table, notice
and figure on the page (as parsed here and, where Debian's chromium is installed, as a
browser shows it); a report with an alarm, a unit where nothing was found and one with too
few days for a trend shows every section in the browser's DOM."""

from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from ddh_vsensor.cli.main import main
from ddh_vsensor.diagnosis.causes import CAUSES
from ddh_vsensor.diagnosis.evidence import GRIDS
from ddh_vsensor.diagnosis.trend import DAY_S, MIN_LOGS, unit_trend
from ddh_vsensor.fleet.report import write_report

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
        assert u["finding"] and u["state"] in ("alarm", "cause", "none", "too_few_days")
        if u["logs"] < MIN_LOGS:                    # the fixture's fleet has 3 days
            assert u["state"] == "too_few_days" and not u["figure"]
            assert f"{u['days_of_evidence']} day" in u["finding"]


class _Page(HTMLParser):
    """Each table's rows (by table id), each image's attributes, every element id, and the
    text of each paragraph (with its class) and heading."""

    def __init__(self, text: str) -> None:
        super().__init__(convert_charrefs=True)
        self.tables: dict[str, list[list[str]]] = {}
        self.images: list[dict[str, str]] = []
        self.ids: set[str] = set()
        self.paragraphs: list[tuple[str, str]] = []
        self.headings: list[str] = []
        self._table: list[list[str]] | None = None
        self._in_cell = False
        self._open: str | None = None           # the paragraph or heading being read
        self.feed(text)

    def handle_starttag(self, tag: str, attrs: list) -> None:
        a = dict(attrs)
        if a.get("id"):
            self.ids.add(a["id"])
        if tag == "table":
            self._table = self.tables.setdefault(a["id"], [])
        elif tag == "tr" and self._table is not None:
            self._table.append([])
        elif tag in ("td", "th") and self._table is not None:
            self._table[-1].append("")
            self._in_cell = True
        elif tag == "img":
            self.images.append(a)
        elif tag == "p":
            self.paragraphs.append((a.get("class") or "", ""))
            self._open = "p"
        elif tag in ("h1", "h2", "h3"):
            self.headings.append("")
            self._open = "h"

    def handle_endtag(self, tag: str) -> None:
        if tag == "table":
            self._table = None
        elif tag in ("td", "th"):
            self._in_cell = False
        elif tag in ("p", "h1", "h2", "h3"):
            self._open = None

    def handle_data(self, data: str) -> None:
        if self._in_cell and self._table is not None:
            self._table[-1][-1] += data
        if self._open == "p":
            cls, text = self.paragraphs[-1]
            self.paragraphs[-1] = (cls, text + data)
        elif self._open == "h":
            self.headings[-1] += data


def test_report_page_has_a_row_and_a_finding_per_unit(local_store):
    store, report = local_store
    page = _Page((store.parent / "report.html").read_text(encoding="utf-8"))
    units = report["units"]
    machines = page.tables["machines"]
    assert machines[0][:5] == ["machine", "unit", "days of evidence", "last day", "cause"]
    assert [row[:5] for row in machines[1:]] == [
        [u["machine"], u["actuator"], str(u["days_of_evidence"]), u["last_log"], u["cause"]]
        for u in units]
    assert [row[7] for row in machines[1:]] == [f"{u['reference_error_mm']:.3f}" for u in units]
    assert len(page.tables["alarms"]) == 1 + sum(u["alarm"] for u in units)
    for u in units:
        assert f"{u['machine']}-{u['actuator']}" in page.ids
    texts = [text for _, text in page.paragraphs]
    assert all(u["finding"] in texts for u in units)
    trends = [a for a in page.images if a.get("class") == "trend"]
    assert [a["alt"] for a in trends] == [f"trend {u['machine']} {u['actuator']}"
                                          for u in units if u["figure"]]
    for a in trends:
        png = base64.b64decode(a["src"].removeprefix("data:image/png;base64,"))
        assert png.startswith(b"\x89PNG\r\n\x1a\n")
    assert len(page.tables["parameters"]) == 1 + len(CAUSES)


def _dom(page: Path, profile: Path) -> str:
    """The page as headless Chromium builds it (its DOM after loading from disk)."""
    return subprocess.run([CHROMIUM, *FLAGS, f"--user-data-dir={profile}", "--dump-dom",
                           page.as_uri()], capture_output=True, text=True, timeout=120,
                          check=True).stdout


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed")
def test_report_renders_in_headless_chromium(local_store, tmp_path):
    store, report = local_store
    assert report["units"]
    out = tmp_path / "report.html"
    assert main(["fleet", "report", "--store", str(store), "--out", str(out)]) == 0
    dom = _dom(out, tmp_path / "profile")
    units = len(report["units"])
    assert len(re.findall(r"<img class=\"trend\"[^>]*src=\"data:image/png;base64,", dom)) \
        == sum(u["figure"] for u in report["units"])
    for table in ("alarms", "machines", "parameters"):
        assert f'<table id="{table}">' in dom
    machines = dom.split('<table id="machines">')[1].split("</table>")[0]
    assert machines.count("<tr>") == units + 1
    alarms = dom.split('<table id="alarms">')[1].split("</table>")[0]
    assert alarms.count("<tr>") == sum(u["alarm"] for u in report["units"]) + 1


T0 = 1.767e9                                # 2025-12-29 UTC


def _rows(leakage_per_day: list[float], seed: int) -> list[dict]:
    """A unit's rows as the fleet analysis writes them, one per day and cause: the leakage
    factor of each day (8 mm of increment change per unit of its log), the displacement
    explaining nothing."""
    rng = np.random.default_rng(seed)
    out = []
    for day, leak in enumerate(leakage_per_day):
        v = np.log(leak) + rng.normal(0.0, 0.02)
        nominal = 20.0 * (1.0 + (8.0 * v) ** 2)
        for cause in ("pump_leakage", "displacement"):
            gu = np.log(np.asarray(GRIDS[cause], float))
            loss = 20.0 * (1.0 + (8.0 * (gu - v)) ** 2) if cause == "pump_leakage" else \
                np.full(len(gu), nominal) + 5.0 * gu ** 2
            out.append({"cause": cause, "grid": list(GRIDS[cause]), "loss": list(loss),
                        "emax_mm": list(8.0 * np.abs(gu)), "n_obs": 20,
                        "loss_nominal": nominal, "max_increment_mm": 1.0,
                        "time_s": T0 + day * DAY_S, "log_id": f"{seed}-d{day}"})
    return out


@pytest.fixture
def three_findings(cfg, tmp_path) -> tuple[Path, dict]:
    """A report of three units: M01's boom pumps leaking more by 2 % a day (an alarm),
    M02's boom as new (nothing found), M03's bucket with 3 days (too few for a trend);
    M01's and M03's evidence day summaries, M02's logs."""
    days = np.arange(12)
    units = [("M01", "boom", list(1.0 + 0.02 * days), 1),
             ("M02", "boom", [1.0] * 12, 2),
             ("M03", "bucket", [1.3, 1.3, 1.3], 3)]
    trends, sources = [], {}
    for machine, actuator, leak, seed in units:
        rows = _rows(leak, seed)
        trends.append(unit_trend(machine, actuator, rows, 3.0, 14.0))
        sources.update({r["log_id"]: "log" if machine == "M02" else "summary" for r in rows})
    out = tmp_path / "report.html"
    store = {"machines": 3, "logs": 12, "log_hours": 1.5, "summaries": 15, "rejected": 0}
    data = write_report(trends, out, 3.0, 14.0, cfg, store, sources)
    assert [u["state"] for u in data["units"]] == ["alarm", "none", "too_few_days"]
    assert data == json.loads(out.with_suffix(".json").read_text())
    return out, data


def test_each_alarm_row_names_cause_figure_time_left_and_action(three_findings):
    out, data = three_findings
    alarm = data["units"][0]
    page = _Page(out.read_text(encoding="utf-8"))
    head, row = page.tables["alarms"]
    cell = dict(zip(head, row))
    assert cell["cause"] == "pressure scale (pump_leakage)"
    assert re.fullmatch(r"the boom's pressure scale: its pumps leak 1\.\d\d\u00d7 their "
                        r"nominal, or its drive's torque reads 0\.\d\d\u00d7 true",
                        cell["what was found"])
    assert cell["passes the tolerance"] == f"in {int(alarm['days_left'])} days " \
                                            f"({alarm['crossing']})"
    assert cell["action"].startswith("check the chamber pressures to tell which: service "
                                     "the pumps if they leak")
    assert alarm["extension_file"] in cell["action"]
    assert cell["extension to load"] == alarm["extension_file"]
    assert Path(alarm["extension_file"]).is_file()
    text = alarm["finding"]
    assert text.startswith("ALARM: The boom's pressure scale: its pumps leak 1.")
    assert f"in {int(alarm['days_left'])} days, by {alarm['crossing']}" in text
    assert "From 12 days of evidence (12 day summaries)." in text
    assert data["units"][1]["finding"].startswith(
        "Nothing found on the boom with 12 days of evidence (12 logs):")
    assert f"{MIN_LOGS - 3} more days of evidence needed" in data["units"][2]["finding"]


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (CI's "
                    ".ci/run installs no browser: apt-get install chromium)")
def test_a_report_with_an_alarm_a_none_and_too_few_days_renders_in_headless_chromium(
        three_findings, tmp_path):
    out, data = three_findings
    page = _Page(_dom(out, tmp_path / "profile"))
    units = data["units"]
    # every section
    assert page.headings[:2] == ["Fleet diagnosis from references and holds", "Alarms (1)"]
    assert {"Machines", "Per machine and unit", "What the parameters mean"} <= \
        set(page.headings)
    assert {"too-few", "alarms", "machines", "units", "parameters"} <= page.ids
    assert [f"{u['machine']}-{u['actuator']}" for u in units] == \
        [i for i in ("M01-boom", "M02-boom", "M03-bucket") if i in page.ids]
    # the alarm, its row and its figure; the others their sentence only
    assert len(page.tables["alarms"]) == 2 and len(page.tables["machines"]) == 4
    assert [r[-1] for r in page.tables["machines"][1:]] == [
        "ALARM", "nothing found", "too few days for a trend"]
    trends = [a["alt"] for a in page.images if a.get("class") == "trend"]
    assert trends == ["trend M01 boom"]
    # each unit's finding, the too-few notice at the top and on its unit
    paragraphs = dict((text, cls) for cls, text in page.paragraphs)
    assert paragraphs[units[0]["finding"]] == "finding alarm"
    assert paragraphs[units[1]["finding"]] == "finding none"
    assert paragraphs[units[2]["finding"]] == "notice"
    top = next(text for cls, text in page.paragraphs if text.startswith("Too few days for a "
                                                                        "trend ("))
    assert "M03 bucket" in top and f"{MIN_LOGS} days of evidence" in top
    # what every parameter means
    meanings = {r[0]: r for r in page.tables["parameters"][1:]}
    assert set(meanings) == {c + (" (pressure scale)" if c in ("pump_leakage", "torque_gain")
                                  else "") for c in CAUSES}
    assert "1 = as new; worn pumps leak more" in meanings["pump_leakage (pressure scale)"][3]
