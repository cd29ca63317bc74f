"""Accuracy of the estimator on the simulator's nominal runs (issue 4's acceptance figures).

- the table: mode x actuator x speed x payload, max and RMS error, no references, 27 °C;
- drift per cycle without references over a multi-cycle run;
- a 50-cycle run with references: max error overall, first ten cycles vs last ten.
Run: python bench/accuracy.py [--cycles 50]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import publish  # noqa: E402

from ddh_vsensor.config import ACTUATORS, load_config  # noqa: E402
from ddh_vsensor.estimator.accuracy import accuracy  # noqa: E402
from ddh_vsensor.estimator.estimator import Estimator  # noqa: E402
from ddh_vsensor.sim.run import RunSpec, simulate_campaign  # noqa: E402
from ddh_vsensor.tables.build import build_unit_tables  # noqa: E402


def _estimate(cfg, tables, actuator, run, mode, references):
    est = Estimator(cfg, actuator, tables[actuator], mode=mode, references=references,
                    initial_position_mm=float(run.position_mm[0]))
    return est.run(run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c,
                   run.refs if references else None)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--cycles", type=int, default=50)
    args = parser.parse_args()
    cfg = load_config(None)
    tables = {a: build_unit_tables(cfg, a) for a in ACTUATORS}
    figures: dict[str, object] = {}
    t0 = time.perf_counter()
    specs = [RunSpec(speed=s, payload_kg=p, oil_temp_c=27.0) for s in (1, 2, 3, 4)
             for p in (0.0, 1040.0)]
    runs = simulate_campaign(cfg, specs)
    print(f"simulated 8 nominal runs in {time.perf_counter() - t0:.1f} s")
    print(f"{'mode':6} {'actuator':8} {'speed':>5} {'payload':>8} {'max mm':>8} {'RMS mm':>8}")
    for mode in ("full", "paper"):
        for actuator in ACTUATORS:
            worst = 0.0
            for spec, run in zip(specs, runs):
                r = run[actuator]
                acc = accuracy(_estimate(cfg, tables, actuator, r, mode, False).position_mm,
                               r.position_mm)
                worst = max(worst, acc.max_abs_error_mm)
                key = f"{mode}_{actuator}_speed{spec.speed}_{spec.payload_kg:g}kg"
                figures[key] = {"max_abs_error_mm": round(acc.max_abs_error_mm, 3),
                                "rms_error_mm": round(acc.rms_error_mm, 3)}
                print(f"{mode:6} {actuator:8} {spec.speed:>5} {spec.payload_kg:>8g} "
                      f"{acc.max_abs_error_mm:8.2f} {acc.rms_error_mm:8.2f}")
            figures[f"{mode}_{actuator}_worst_max_abs_error_mm"] = round(worst, 3)

    t0 = time.perf_counter()
    long = simulate_campaign(cfg, [RunSpec(speed=4, payload_kg=0.0, oil_temp_c=27.0,
                                           cycles=args.cycles)])[0]
    print(f"simulated {args.cycles} cycles in {time.perf_counter() - t0:.1f} s")
    for actuator in ACTUATORS:
        r = long[actuator]
        period = r.time_s[-1] / args.cycles
        cycle = np.minimum((r.time_s / period).astype(int), args.cycles - 1)
        for refs in (False, True):
            est = Estimator(cfg, actuator, tables[actuator], references=refs,
                            initial_position_mm=float(r.position_mm[0]))
            res = est.run(r.time_s, r.speed_rpm, r.torque_nm, r.oil_temp_c,
                          r.refs if refs else None)
            err = res.position_mm - r.position_mm
            per_cycle = np.array([np.nanmax(np.abs(err[cycle == c])) for c in range(args.cycles)])
            tag = f"{actuator}_{args.cycles}cycles_{'refs' if refs else 'norefs'}"
            figures[f"{tag}_max_abs_error_mm"] = round(float(np.nanmax(np.abs(err))), 3)
            figures[f"{tag}_first10_max_mm"] = round(float(per_cycle[:10].max()), 3)
            figures[f"{tag}_last10_max_mm"] = round(float(per_cycle[-10:].max()), 3)
            if not refs:
                ends = np.array([err[cycle == c][np.isfinite(err[cycle == c])][-1]
                                 for c in range(args.cycles)])
                drift = np.polyfit(np.arange(args.cycles), ends, 1)[0]
                figures[f"{actuator}_drift_per_cycle_norefs_mm"] = round(float(drift), 4)
            else:
                figures[f"{actuator}_gains_after_{args.cycles}_cycles"] = [
                    round(float(g), 5) for g in est.gain.gain]
    publish("accuracy", figures)


if __name__ == "__main__":
    main()
