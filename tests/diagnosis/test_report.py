"""The HTML reports from their templates: every value escaped (a run's file name or the report
directory may hold any character), the same page structure whatever the values, the figures
embedded, and the numbers those of report.json."""

from __future__ import annotations

import base64
import json
import shutil
from html.parser import HTMLParser
from pathlib import Path

import jinja2
import pytest

from ddh_vsensor.cli.main import main
from ddh_vsensor.diagnosis.report import render_page
from ddh_vsensor.diagnosis.trials import draw_trial, simulate_trial, write_trial
from ddh_vsensor.io.blf import write_blf_inputs

HOSTILE = "<blink>&\"'</td>"
PNG = b"\x89PNG\r\n\x1a\n" + bytes(range(256))


class Page(HTMLParser):
    """The elements of a page in order, its text, and its tables' rows."""

    def __init__(self, text: str) -> None:
        super().__init__(convert_charrefs=True)
        self.tags: list[str] = []
        self.attrs: list[dict[str, str | None]] = []
        self.text: list[str] = []
        self.tables: list[list[list[str]]] = []
        self._cell: list[str] | None = None
        self.feed(text)
        self.close()

    def handle_starttag(self, tag: str, attrs: list) -> None:
        self.tags.append(tag)
        self.attrs.append(dict(attrs))
        if tag == "table":
            self.tables.append([])
        elif tag == "tr":
            self.tables[-1].append([])
        elif tag in ("td", "th"):
            self._cell = []

    def handle_endtag(self, tag: str) -> None:
        if tag in ("td", "th") and self._cell is not None:
            self.tables[-1][-1].append("".join(self._cell))
            self._cell = None

    def handle_data(self, data: str) -> None:
        self.text.append(data)
        if self._cell is not None:
            self._cell.append(data)

    def images(self) -> list[bytes]:
        return [base64.b64decode(a["src"].split(",", 1)[1]) for t, a in zip(self.tags, self.attrs)
                if t == "img"]


def _diagnosis_context(s: str) -> dict:
    rows = [[s, 1.0, float("nan"), 0.001, s]]
    return dict(title=s, actuator=s, mode=s, cause=s, reason=s, causes=rows, extension_file=s,
                ambiguous=[(s, s, s)], evidence=None, gain=rows, default_inertia=True,
                unexplained={"follows": s, "breakdown": [(s, rows)]}, candidates=rows,
                ranking_png=PNG, penalty_per_parameter=0.01, min_score=0.1, shown=s,
                signature_png=PNG, errors_png=PNG, runs=rows, breakdown_png=PNG,
                breakdown=[(s, rows), (s, rows)], not_observable=[(s, s, s)], thresholds=s)


def _reference_context(s: str) -> dict:
    rows = [[s, 1.0, 2, 3, float("nan")]]
    return dict(title=s, actuator=s, cause=s, reason=s, summary=s, extension_file=s,
                errors=rows, candidates=rows, ranking_png=PNG, runs=rows,
                not_observable=[(s, s, s)], thresholds=s)


def _fleet_context(s: str) -> dict:
    return dict(title=s, store={"machines": 3, "logs": 9, "log_hours": 0.075, "rejected": 0},
                summaries=4, tolerance_mm=2.0, horizon_days=30.0, min_days=7,
                alarms=[[s, s, s, s, None, 1.5, s, s, s, s]],
                machines=[[s, s, 3, s, float("inf")]], too_few=[s, s],
                units=[{"machine": s, "actuator": s, "state": s, "text": s, "png": PNG},
                       {"machine": s, "actuator": s, "state": s, "text": s, "png": None}],
                parameters=[[s, s, s, s, s]])


CONTEXTS = {"diagnosis.html.j2": _diagnosis_context,
            "reference_diagnosis.html.j2": _reference_context,
            "fleet.html.j2": _fleet_context}


@pytest.mark.parametrize("template", CONTEXTS)
def test_every_value_is_escaped(template: str) -> None:
    plain = Page(render_page(template, **CONTEXTS[template]("x")))
    hostile_html = render_page(template, **CONTEXTS[template](HOSTILE))
    hostile = Page(hostile_html)
    assert "<blink>" not in hostile_html and "&lt;blink&gt;" in hostile_html
    assert hostile.tags == plain.tags                      # the same page, element by element
    assert [len(t) for t in hostile.tables] == [len(t) for t in plain.tables]
    assert HOSTILE in "".join(hostile.text)                # shown as written
    assert hostile.tags[:1] == ["html"] and "title" in hostile.tags and "footer" in hostile.tags
    assert hostile.images() == [PNG] * hostile.tags.count("img")


def test_cells_show_numbers_and_leave_non_finite_ones_empty() -> None:
    page = Page(render_page("reference_diagnosis.html.j2", **_reference_context("x")))
    assert page.tables[0][1] == ["x", "1.000", "2", "3", ""]
    page = Page(render_page("diagnosis.html.j2", **_diagnosis_context("x")))
    assert page.tables[0][1] == ["x", "1.000", "", "0.001", "x"]
    page = Page(render_page("fleet.html.j2", **_fleet_context("x")))
    assert page.tables[0][1] == ["x"] * 4 + ["", "1.500"] + ["x"] * 4     # None: empty
    assert page.tables[1][1] == ["x", "x", "3", "x", ""]                   # inf: empty


def test_a_missing_value_is_an_error_not_an_empty_page() -> None:
    context = _reference_context("x")
    del context["runs"]
    with pytest.raises(jinja2.UndefinedError, match="runs"):
        render_page("reference_diagnosis.html.j2", **context)


@pytest.fixture(scope="module")
def hostile_runs(cfg, tmp_path_factory) -> list[dict]:
    """Three runs of a trial with a hidden pump leakage, whose files are named with
    characters HTML gives a meaning."""
    return simulate_trial(cfg, draw_trial(6101, "pump_leakage"))[:3]


def _check_report(out: Path, names: list[str]) -> tuple[Page, dict]:
    data = json.loads((out / "report.json").read_text())
    text = (out / "report.html").read_text()
    page = Page(text)
    assert "<blink>" not in text
    assert data["extension_file"] in "".join(page.text)
    runs = next(t for t in page.tables if t[0][0] == "run")
    assert len(runs) == 1 + len(names)                 # each run titled by its file
    assert all(row[0].endswith(name) for row, name in zip(runs[1:], names))
    images = page.images()
    assert images and all(png.startswith(b"\x89PNG\r\n\x1a\n") for png in images)
    b, e = data["baseline"], data["extended"]
    gain = next(t for t in page.tables if t[0][:2] == ["", "max |error| (mm)"])
    assert gain[1][1:] == [f"{b['max_abs_error_mm']:.3f}", f"{b['rms_error_mm']:.3f}"]
    assert gain[-1][1:] == [f"{e['max_abs_error_mm']:.3f}", f"{e['rms_error_mm']:.3f}"]
    return page, data


def test_analyze_report_with_hostile_file_names(cfg, hostile_runs, tmp_path) -> None:
    paths = write_trial(hostile_runs, tmp_path / "runs")["boom"]
    named = []
    for i, path in enumerate(paths):
        named.append(path.with_name(f"run{i} <blink>&'\".csv"))
        shutil.move(path, named[-1])
    out = tmp_path / "report <blink>"
    assert main(["analyze", *map(str, named), "--actuator", "boom", "--report", str(out)]) == 0
    page, data = _check_report(out, [p.name for p in named])
    assert all(r.endswith(p.name) for r, p in zip(data["runs"], named))
    assert data["cause"] in "".join(page.text)
    assert len(page.images()) == 4              # ranking, signature, errors per run, breakdown


def test_reference_report_with_hostile_file_names(cfg, hostile_runs, tmp_path) -> None:
    named = []
    for i, per_unit in enumerate(hostile_runs):
        named.append(tmp_path / f"run{i} <blink>&'\".blf")
        write_blf_inputs(named[-1], per_unit, cfg)           # no position: references
    out = tmp_path / "report <blink>"
    assert main(["analyze", *map(str, named), "--actuator", "boom", "--report", str(out)]) == 0
    page, data = _check_report(out, [p.name for p in named])
    assert data["truth"] == "references"
    assert len(page.images()) == 1                                        # the ranking
    candidates = next(t for t in page.tables if t[0] == ["cause", "score", "fitted",
                                                          "90 % interval"])
    assert [row[0] for row in candidates[1:]] == [c["cause"] for c in data["causes"]]
