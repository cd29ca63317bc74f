"""The docs site builds with warnings as errors (broken links and anchors included), and its
generated pages carry what the code and the benches' committed JSON say."""

from __future__ import annotations

import html
import importlib.util
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from ddh_vsensor.canbus.eds import unit_object_dictionary
from ddh_vsensor.canbus.layout import EMCY_CODES, MAINTENANCE_EMCY
from ddh_vsensor.cli.config import schema_lines
from ddh_vsensor.config import load_config
from ddh_vsensor.estimator.flags import Flags

REPO = Path(__file__).resolve().parents[2]
RESULTS = REPO / "bench" / "results"


def _gen_bench():
    """The hook's figure formatting, so the test looks for the figure as the page prints it."""
    sys.path.insert(0, str(REPO / "docs" / "hooks"))
    try:
        spec = importlib.util.spec_from_file_location("gen_bench",
                                                      REPO / "docs" / "hooks" / "gen_bench.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(str(REPO / "docs" / "hooks"))


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(out)],
                          cwd=REPO, capture_output=True, text=True, timeout=300, check=False,
                          env={**__import__("os").environ, "NO_MKDOCS_2_WARNING": "1"})
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return out


def _text(site: Path, page: str) -> str:
    """A page's text as a reader sees it (tags dropped, entities decoded)."""
    raw = (site / page).read_text(encoding="utf-8")
    raw = raw.split('<article', 1)[1] if '<article' in raw else raw
    return html.unescape(re.sub(r"<[^>]+>", "", raw))


def _figure(name: str, key: str) -> str:
    figures = json.loads((RESULTS / f"{name}.json").read_text())["figures"]
    return _gen_bench().fmt(figures[key])


def test_configuration_reference_lists_every_schema_key(site: Path):
    text = _text(site, "reference/configuration.html")
    for line in schema_lines():
        path = line.split()[0]
        assert path in text, path
    assert "1450.0" in text        # the reference loader's nominal pump speed, from its YAML


def test_device_sheet_is_the_eds(site: Path):
    text = _text(site, "reference/device-sheet.html")
    cfg = load_config(None)
    od = unit_object_dictionary(cfg, cfg.unit_names[0])
    for obj in od.values():
        assert f"0x{obj.index:04X}" in text and obj.name in text, obj.name
    for code, name in [*EMCY_CODES.values(), MAINTENANCE_EMCY]:
        assert f"0x{code:04X}" in text and name in text
    tpdo1 = od[0x1800][1].default & 0x7FF          # the COB-ID the EDS gives TPDO1
    assert re.search(rf"TPDO1\s+0x{tpdo1:03X}\s", text)
    tpdo3 = od[0x1802][1].default & 0x7FF
    assert re.search(rf"TPDO3\s+0x{tpdo3:03X}\s", text)


def test_flag_table_has_every_flag(site: Path):
    text = _text(site, "operations.html")
    for flag in Flags:
        assert (flag.name or "").lower() in text and f"0x{int(flag):02X}" in text


@pytest.mark.parametrize("page, bench, key", [
    ("accuracy.html", "accuracy", "dynamic_boom_worst_max_abs_error_mm"),
    ("accuracy.html", "accuracy", "paper_bucket_worst_max_abs_error_mm"),
    ("performance.html", "estimator", "dynamic_boom_online_step_us"),
    ("performance.html", "tables", "build_both_full_and_paper_s_median"),
    ("performance.html", "simulate", "single_run_real_time_factor"),
    ("performance.html", "daemon", "socket_nominal_latency_p99_ms"),
    ("performance.html", "fleet", "analysis on 2 workers (s)"),
    ("accuracy.html", "faults", "checks"),
    ("accuracy.html", "diagnosis", "interval_coverage_all"),
])
def test_figure_pages_carry_the_benchmarks_figures(site: Path, page: str, bench: str, key: str):
    text = _text(site, page)
    record = json.loads((RESULTS / f"{bench}.json").read_text())
    assert _figure(bench, key) in text
    assert record["command"] in text        # the setting the figures were measured with


def test_every_committed_result_is_read_by_the_site(site: Path):
    """Every bench JSON a page names is committed (the build fails otherwise) and shown on
    that page with where it comes from."""
    results = {p.stem for p in RESULTS.glob("*.json")}
    for page in (REPO / "docs").glob("*.md"):
        named = set(re.findall(r"<!-- generated: bench ([a-z0-9_]+) -->",
                               page.read_text(encoding="utf-8")))
        assert named <= results, page.name
        for name in named:
            assert f"bench/results/{name}.json" in _text(site, f"{page.stem}.html"), name


def test_docs_have_no_dated_history():
    for path in [*(REPO / "docs").rglob("*.md"), REPO / "README.md", REPO / "CHANGELOG.md"]:
        text = path.read_text(encoding="utf-8")
        assert "Nov" not in text, path
        assert not re.search(r"\bissue \d+", text), path


def test_a_broken_link_fails_the_build(tmp_path: Path):
    """The link check is on: the same site with one link to a page that does not exist is
    refused under --strict."""
    import shutil
    shutil.copy(REPO / "mkdocs.yml", tmp_path / "mkdocs.yml")
    shutil.copytree(REPO / "docs", tmp_path / "docs",
                    ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "bench", "ddh_vsensor"):
        (tmp_path / name).symlink_to(REPO / name)
    index = tmp_path / "docs" / "index.md"
    index.write_text(index.read_text(encoding="utf-8") + "\n[gone](no-such-page.md)\n",
                     encoding="utf-8")
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d",
                           str(tmp_path / "site")], cwd=tmp_path, capture_output=True,
                          text=True, timeout=300, check=False)
    assert done.returncode != 0
    assert "no-such-page.md" in done.stdout + done.stderr
