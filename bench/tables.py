"""Benchmark: time to build both units' tables; scalar and vectorised lookup throughput."""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import publish  # noqa: E402

from ddh_vsensor.config import load_config  # noqa: E402
from ddh_vsensor.tables.build import build_unit_tables  # noqa: E402


def main() -> None:
    cfg = load_config(None)
    builds = []
    for _ in range(3):
        t0 = time.perf_counter()
        tables = {a: build_unit_tables(cfg, a) for a in cfg.unit_names}
        builds.append(time.perf_counter() - t0)
    figures: dict[str, object] = {
        "build_both_full_and_paper_s_median": round(statistics.median(builds), 3),
        "build_both_full_and_paper_s_min": round(min(builds), 3),
    }
    rng = np.random.default_rng(0)
    for actuator, t in tables.items():
        full = t.full
        figures[f"{actuator}_grid_cells"] = int(full.velocity_mm_s.size)
        n = rng.uniform(-6000, 6000, 100_000)
        q = rng.uniform(-60, 60, 100_000)
        temp = rng.uniform(20, 40, 100_000)
        t0 = time.perf_counter()
        for i in range(100_000):
            full.velocity(n[i], q[i], temp[i])
        figures[f"{actuator}_scalar_lookup_us"] = round((time.perf_counter() - t0) / 1e5 * 1e6, 3)
        big = 2_000_000
        nb, qb, tb = (np.resize(x, big) for x in (n, q, temp))
        t0 = time.perf_counter()
        full.velocity_many(nb, qb, tb)
        figures[f"{actuator}_vector_lookup_Msamples_s"] = round(
            big / (time.perf_counter() - t0) / 1e6, 2)
    publish("tables", figures)


if __name__ == "__main__":
    main()
