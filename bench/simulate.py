"""Benchmark: simulated seconds per wall second for the two-unit paper cycle (goal >= 10x real
time), alone and batched (many runs in one vectorised plant), and the sim's own accuracy
against a 4x finer step."""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import publish  # noqa: E402

from ddh_vsensor.config import load_config  # noqa: E402
from ddh_vsensor.sim import RunSpec, simulate_campaign, simulate_with_truth  # noqa: E402

BATCH = 16


def _timed(cfg, specs):
    t0 = time.perf_counter()
    runs = simulate_campaign(cfg, specs)
    return time.perf_counter() - t0, runs


def main() -> None:
    cfg = load_config(None)
    spec = RunSpec(cycle="paper", speed=4, payload_kg=0.0, oil_temp_c=27.0)
    walls = []
    for _ in range(3):
        wall, runs = _timed(cfg, [spec])
        walls.append(wall)
    duration = float(runs[0]["boom"].time_s[-1])
    single = statistics.median(walls)
    figures: dict[str, object] = {
        "paper_speed4_duration_s": round(duration, 2),
        "single_run_wall_s_median": round(single, 3),
        "single_run_real_time_factor": round(duration / single, 1),
        "single_step_us": round(single / (duration / spec.step_s) * 1e6, 1),
    }
    # a diagnosis-like campaign: payloads x temperatures x effects, one vectorised plant;
    # entrained air costs extra secant passes for every row of its batch, so it is timed apart
    for label, air in (("batch", "displacement=0.97"), ("batch_with_air", "compressibility=0.01")):
        effects = [None, ["pump_leakage=1.5"], [air], ["belt_slip=2"]]
        specs = [RunSpec(payload_kg=p, oil_temp_c=t, effects=e, seed=i)
                 for i, (p, t, e) in enumerate((p, t, e) for p in (0.0, 1040.0)
                                               for t in (20.0, 40.0) for e in effects)]
        assert len(specs) == BATCH
        wall, runs = _timed(cfg, specs)
        total = sum(float(r["boom"].time_s[-1]) for r in runs)
        figures.update({
            f"{label}_runs": BATCH,
            f"{label}_wall_s": round(wall, 3),
            f"{label}_simulated_run_s_per_wall_s": round(total / wall, 1),
            f"{label}_speedup_per_run_vs_single": round(single / (wall / BATCH), 1),
        })
    # accuracy of the default 1 ms step against 0.25 ms
    fine, coarse = simulate_with_truth(cfg, [RunSpec(step_s=0.25e-3)])[0], \
        simulate_with_truth(cfg, [spec])[0]
    for a in ("boom", "bucket"):
        f, c = fine[a][1], coarse[a][1]
        figures[f"{a}_step_error_position_mm_max"] = round(
            float(np.max(np.abs(f.x_m - c.x_m)) * 1e3), 4)
        figures[f"{a}_step_error_speed_rpm_rms"] = round(
            float(np.sqrt(np.mean((f.speed_rpm - c.speed_rpm) ** 2))), 2)
        figures[f"{a}_step_error_revolutions"] = round(
            float(np.sum(c.speed_rpm - f.speed_rpm) / 60.0 * 0.01), 4)
    publish("simulate", figures)


if __name__ == "__main__":
    main()
