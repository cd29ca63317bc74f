"""Issue 36's research prototype against `dynamic`: the extended Kalman filter
(:mod:`ddh_vsensor.estimator.kalman`) and the shipped mode on the same simulated runs.

A subset of bench/accuracy.py's main sweep (``sweep_specs``), small enough for minutes: oil at
-10, 27 and 80 degC x the paper cycle at speed 4 with 1040 kg, dig-dump (both end stops) and a
random work cycle (0 kg), on the nominal plant and with the structure the model lacks at its
typical value and twice it (``sim.effects.STRUCTURE_TYPICAL``); without and with the Hall
references. Per structure level, references, estimator and unit: the worst error (mm), the
median published uncertainty (mm), the share of samples beyond their uncertainty, the share of
those with no flag set (a plain, trusted reading wrong by more than it says) and the share
flagged model-inconsistent; per run (``..._runs``: temperature, cycle, the same figures) to
find the one that sets a total. Estimators: `dynamic`; `kalman` (x, v, dp_a, dp_b, F_load,
oil-temperature offset, Gauss-Markov flow error, torque offset, one offset per Hall switch).
Cost: the filters' wall time per sample and filter, batched as the bench runs them (and
`dynamic`'s).
Run: python bench/kalman.py [--temps DEGC ...] [--levels none typical double] [--quick]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import publish  # noqa: E402
from accuracy import STRUCTURE_SCALES, _estimate, sweep_specs  # noqa: E402

from ddh_vsensor.config import load_config  # noqa: E402
from ddh_vsensor.estimator import kalman  # noqa: E402
from ddh_vsensor.sim.effects import NOMINAL, structure_effects  # noqa: E402
from ddh_vsensor.sim.run import simulate_campaign  # noqa: E402
from ddh_vsensor.tables.build import build_unit_tables  # noqa: E402

TEMPS_C = (-10.0, 27.0, 80.0)
# sweep_specs' paper cycle at speed 4 with 1040 kg, dig-dump 0 kg, the first random cycle 0 kg
PICK = (7, 8, 10)
CYCLES = {7: "paper 1040 kg", 8: "dig-dump", 10: "random"}
VARIANTS = {"kalman": kalman.KalmanSettings()}


def _tally(stats: dict, key: tuple, err: np.ndarray, u: np.ndarray, flags: np.ndarray,
           run: str) -> None:
    ok = np.isfinite(err) & np.isfinite(u)
    err, u, flags = np.abs(err[ok]), u[ok], flags[ok]
    if not err.size:
        return
    over = err > u
    runs = stats.setdefault(key + ("runs",), [])
    runs.append({"run": run, "max_abs_error_mm": round(float(err.max()), 3),
                 "median_uncertainty_mm": round(float(np.median(u)), 3),
                 "unflagged_beyond_uncertainty_share": round(float(np.mean(over & (flags == 0))),
                                                             5),
                 "model_inconsistent_share": round(float(np.mean(
                     (flags & kalman.MODEL_INCONSISTENT).astype(bool))), 5)})
    s = stats.setdefault(key, {"worst": 0.0, "u": [], "over": 0, "unflagged": 0,
                               "inconsistent": 0, "n": 0})
    s["worst"] = max(s["worst"], float(err.max()))
    s["u"].append(u)
    s["over"] += int(over.sum())
    s["unflagged"] += int((over & (flags == 0)).sum())
    s["inconsistent"] += int((flags & kalman.MODEL_INCONSISTENT).astype(bool).sum())
    s["n"] += int(err.size)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--temps", type=float, nargs="+", default=list(TEMPS_C))
    parser.add_argument("--levels", nargs="+", choices=tuple(STRUCTURE_SCALES),
                        default=list(STRUCTURE_SCALES))
    parser.add_argument("--quick", action="store_true", help="one run per temperature")
    args = parser.parse_args()
    cfg = load_config(None)
    tables = {a: build_unit_tables(cfg, a) for a in cfg.unit_names}
    pick = PICK[:1] if args.quick else PICK
    stats: dict[tuple, dict] = {}
    cost = {name: [0.0, 0] for name in (*VARIANTS, "dynamic")}
    for level in args.levels:
        scale = STRUCTURE_SCALES[level]
        effects = structure_effects(scale) if scale else NOMINAL
        specs = [dataclasses.replace(sweep_specs(cfg, temp)[i],
                                     effects={a: effects for a in cfg.unit_names})
                 for temp in args.temps for i in pick]
        t0 = time.perf_counter()
        runs = simulate_campaign(cfg, specs)
        print(f"{level}: simulated {len(specs)} runs in {time.perf_counter() - t0:.0f} s",
              flush=True)
        jobs = [(a, r[a]) for r in runs for a in cfg.unit_names]
        labels = [f"{temp:g} degC {CYCLES[i]}" for temp in args.temps for i in pick
                  for _ in cfg.unit_names]
        x0 = [float(r.position_mm[0]) for _, r in jobs]
        for refs in (False, True):
            kind = "refs" if refs else "norefs"
            for name, settings in VARIANTS.items():
                t0 = time.perf_counter()
                results = kalman.run_many(cfg, jobs, references=refs, initial_positions_mm=x0,
                                          settings=settings)
                cost[name][0] += time.perf_counter() - t0
                cost[name][1] += sum(len(r.time_s) for _, r in jobs)
                for (a, r), res, label in zip(jobs, results, labels):
                    e = res.estimate
                    _tally(stats, (level, kind, name, a), e.position_mm - r.position_mm,
                           e.uncertainty_mm, e.flags, label)
                print(f"  {kind} {name}: {time.perf_counter() - t0:.0f} s", flush=True)
            t0 = time.perf_counter()
            for (a, r), label in zip(jobs, labels):
                e = _estimate(cfg, tables, a, r, "dynamic", refs)
                _tally(stats, (level, kind, "dynamic", a), e.position_mm - r.position_mm,
                       e.uncertainty_mm, e.flags, label)
            cost["dynamic"][0] += time.perf_counter() - t0
            cost["dynamic"][1] += sum(len(r.time_s) for _, r in jobs)

    figures: dict[str, object] = {"temps_c": list(args.temps),
                                  "runs_per_temp": len(pick)}
    print(f"{'level':8} {'refs':6} {'estimator':12} {'unit':6} {'max mm':>7} {'med u mm':>8} "
          f"{'beyond':>7} {'unflagged':>9} {'inconsist':>9}")
    for key, s in stats.items():
        if key[-1] == "runs":
            figures["_".join(key)] = s
            continue
        level, kind, name, a = key
        med_u = float(np.median(np.concatenate(s["u"])))
        row = {"max_abs_error_mm": round(s["worst"], 3), "median_uncertainty_mm": round(med_u, 3),
               "beyond_uncertainty_share": round(s["over"] / s["n"], 5),
               "unflagged_beyond_uncertainty_share": round(s["unflagged"] / s["n"], 5),
               "model_inconsistent_share": round(s["inconsistent"] / s["n"], 5),
               "samples": s["n"]}
        figures[f"{level}_{kind}_{name}_{a}"] = row
        print(f"{level:8} {kind:6} {name:12} {a:6} {s['worst']:7.2f} {med_u:8.2f} "
              f"{s['over'] / s['n']:7.2%} {s['unflagged'] / s['n']:9.2%} "
              f"{s['inconsistent'] / s['n']:9.2%}")
    for name, (seconds, samples) in cost.items():
        figures[f"{name}_us_per_sample"] = round(seconds / max(samples, 1) * 1e6, 1)
    publish("kalman", figures)


if __name__ == "__main__":
    main()
