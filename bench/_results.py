"""Shared by the benchmarks: print figures and write them to bench/results/<name>.json."""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def publish(name: str, figures: dict[str, object]) -> Path:
    record = {"benchmark": name, "when": time.strftime("%Y-%m-%dT%H:%M:%S"),
              "python": platform.python_version(), "machine": platform.machine(),
              "figures": figures}
    for key, value in figures.items():
        print(f"{key:<44} {value}")
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(record, indent=2) + "\n")
    print(f"-> {path}")
    return path
