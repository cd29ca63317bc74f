"""Shared by the benchmarks: print figures and write them to bench/results/<name>.json.

The JSON files are committed: the docs' accuracy and performance pages are generated from
them, with the command line and the host's load they were measured under."""

from __future__ import annotations

import json
import os
import platform
import shlex
import sys
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def publish(name: str, figures: dict[str, object]) -> Path:
    script = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "?"
    record = {"benchmark": name, "when": time.strftime("%Y-%m-%dT%H:%M:%S"),
              "command": shlex.join(["python", f"bench/{script}", *sys.argv[1:]]),
              "python": platform.python_version(), "machine": platform.machine(),
              "cpus": os.cpu_count(),
              "load_average_1min": round(os.getloadavg()[0], 2),
              "figures": figures}
    for key, value in figures.items():
        print(f"{key:<44} {value}")
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(record, indent=2) + "\n")
    print(f"-> {path}")
    return path
