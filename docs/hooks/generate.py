"""MkDocs hook: fills each page's ``<!-- generated: NAME [ARG] -->`` markers.

The configuration reference, the CANopen device sheet, the flag table, the layers, the
command list and every figure of the accuracy and performance pages are made from the code
and from the benches' committed JSON (``bench/results/*.json``) at build time, so none of
them is typed by hand. An unknown marker, or a page asking for a bench result that is not
committed, fails the build.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

from mkdocs.exceptions import PluginError

sys.path.insert(0, str(Path(__file__).resolve().parent))

import gen_bench
import gen_code

MARKER = re.compile(r"^<!-- generated: ([a-z-]+)(?: ([A-Za-z0-9_ -]+?))? -->$", re.MULTILINE)

GENERATORS = {
    "config-reference": lambda root, arg: gen_code.config_reference(),
    "device-sheet": lambda root, arg: gen_code.device_sheet(),
    "flags": lambda root, arg: gen_code.flag_table(),
    "layers": lambda root, arg: gen_code.layers(root),
    "commands": lambda root, arg: gen_code.commands(),
    "kalman-settings": lambda root, arg: gen_code.kalman_settings(),
    "bench": lambda root, arg: gen_bench.bench_section(root, arg),
    "accuracy-headline": lambda root, arg: gen_bench.accuracy_headline(root),
    "commission-oracles": lambda root, arg: gen_bench.commission_oracles(root),
}


def _root(config) -> Path:
    return Path(config.config_file_path).resolve().parent


def on_page_markdown(markdown: str, page, config, files) -> str:
    root = _root(config)

    def fill(match: re.Match[str]) -> str:
        name, arg = match.group(1), (match.group(2) or "").strip()
        if name not in GENERATORS:
            raise PluginError(f"{page.file.src_uri}: unknown marker 'generated: {name}'")
        try:
            return GENERATORS[name](root, arg).rstrip() + "\n"
        except (OSError, KeyError, ValueError) as exc:
            raise PluginError(f"{page.file.src_uri}: 'generated: {name} {arg}': {exc}") from exc

    return MARKER.sub(fill, markdown)
