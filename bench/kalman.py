"""Issue 36's research prototype against `dynamic`: the extended Kalman filter
(:mod:`ddh_vsensor.estimator.kalman`) and the shipped mode on the same simulated runs.

Training set (the filter's design was checked on it): a subset of bench/accuracy.py's main
sweep (``sweep_specs``): oil at -10, 27 and 80 degC x the paper cycle at speed 4 with 1040 kg,
dig-dump (both end stops) and a random work cycle (0 kg). Held-out set (``--held-out``; never
tuned on, run once the design is frozen, reported apart): the check set's runs
(``check_specs``) at -5, 20, 40 and 75 degC: the paper cycle at speed 4 with 500 kg, dig-dump at
speed 3 with 500 kg, a random cycle with 40 % of its moves into an end stop and 300 kg. Each on
the nominal plant (the filter configured as the reference loader: its measured tolerances)
and with the structure the model lacks at its typical value and twice it
(``sim.effects.STRUCTURE_TYPICAL``; the filter configured from datasheets, as ``config
--write --datasheet`` writes); without and with the Hall references. Per set, structure
level, references, estimator and unit: the worst error (mm), the median published uncertainty
(mm), the share of samples beyond their uncertainty, the share of those with no flag that warns
(``flags.EXPLAINING``: a trusted reading wrong by more than it says; a stroke end's flag
says where the rod is, not that it may be elsewhere), the share flagged model-inconsistent and
the mean square of the normalised edge innovations (at most about 1 where the flow-error
bounds fit the plant); per run (``..._runs``) to find the one that sets a total. A published
NaN fails the bench. Cost: the filter's wall time per sample, batched as the bench runs it and
alone on one run, and `dynamic`'s.
Run: python bench/kalman.py [--temps DEGC ...] [--levels none typical double] [--quick]
     [--held-out]
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
from accuracy import STRUCTURE_SCALES, _estimate, check_specs, sweep_specs  # noqa: E402

from ddh_vsensor.config import DATASHEET_TOLERANCES, load_config  # noqa: E402
from ddh_vsensor.estimator import kalman  # noqa: E402
from ddh_vsensor.estimator.flags import EXPLAINING  # noqa: E402
from ddh_vsensor.sim.effects import NOMINAL, structure_effects  # noqa: E402
from ddh_vsensor.sim.run import simulate_campaign  # noqa: E402
from ddh_vsensor.tables.build import build_unit_tables  # noqa: E402

TEMPS_C = (-10.0, 27.0, 80.0)
# sweep_specs' paper cycle at speed 4 with 1040 kg, dig-dump 0 kg, the first random cycle 0 kg
PICK = (7, 8, 10)
CYCLES = {7: "paper 1040 kg", 8: "dig-dump", 10: "random"}
VARIANTS = ("kalman",)
# held out (never tuned on): check_specs' paper cycle at speed 4 with 500 kg, dig-dump at
# speed 3 with 500 kg and its second random cycle (300 kg, 40 % of the moves into an end
# stop), at four other oil temperatures
HELD_OUT_TEMPS_C = (-5.0, 20.0, 40.0, 75.0)
HELD_OUT_PICK = (1, 2, 5)
HELD_OUT = {1: "paper 500 kg", 2: "dig-dump 500 kg", 5: "random 300 kg"}


def _tally(stats: dict, key: tuple, err: np.ndarray, u: np.ndarray, flags: np.ndarray,
           run: str, edge_nu: list[float] | None = None) -> None:
    # a published NaN is a failure, not a sample to skip
    assert np.isfinite(err).all() and np.isfinite(u).all(), (key, run)
    err = np.abs(err)
    over = err > u
    warned = (flags & EXPLAINING) != 0         # a flag warns the value may be off
    runs = stats.setdefault(key + ("runs",), [])
    runs.append({"run": run, "max_abs_error_mm": round(float(err.max()), 3),
                 "median_uncertainty_mm": round(float(np.median(u)), 3),
                 "unflagged_beyond_uncertainty_share": round(float(np.mean(over & ~warned)),
                                                             5),
                 "model_inconsistent_share": round(float(np.mean(
                     (flags & kalman.MODEL_INCONSISTENT).astype(bool))), 5)})
    s = stats.setdefault(key, {"worst": 0.0, "u": [], "over": 0, "unflagged": 0,
                               "inconsistent": 0, "n": 0, "nu": []})
    s["nu"].extend(edge_nu or ())
    s["worst"] = max(s["worst"], float(err.max()))
    s["u"].append(u)
    s["over"] += int(over.sum())
    s["unflagged"] += int((over & ~warned).sum())
    s["inconsistent"] += int((flags & kalman.MODEL_INCONSISTENT).astype(bool).sum())
    s["n"] += int(err.size)


def _specs(cfg, which: str, temps: list[float], pick: tuple[int, ...], effects
           ) -> tuple[list, list[str]]:
    """The runs of the training subset (sweep_specs) or the held-out one (check_specs)."""
    source, names = (sweep_specs, CYCLES) if which == "training" else (check_specs, HELD_OUT)
    specs = [dataclasses.replace(source(cfg, temp)[i],
                                 effects={a: effects for a in cfg.unit_names})
             for temp in temps for i in pick]
    return specs, [f"{temp:g} degC {names[i]}" for temp in temps for i in pick]


def _run_set(cfg, tables, which: str, temps: list[float], pick: tuple[int, ...],
             levels: list[str], stats: dict, cost: dict) -> None:
    for level in levels:
        scale = STRUCTURE_SCALES[level]
        specs, names = _specs(cfg, which, temps, pick,
                              structure_effects(scale) if scale else NOMINAL)
        t0 = time.perf_counter()
        runs = simulate_campaign(cfg, specs)
        print(f"{which} {level}: simulated {len(specs)} runs in "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
        # the nominal plant is the reference loader as configured: its measured tolerances;
        # a plant with structure the model lacks is a machine known from datasheets only
        settings = (kalman.settings_from_config(cfg) if not scale
                    else kalman.settings_from_config(_datasheet(cfg)))
        jobs = [(a, r[a]) for r in runs for a in cfg.unit_names]
        labels = [n for n in names for _ in cfg.unit_names]
        x0 = [float(r.position_mm[0]) for _, r in jobs]
        samples = sum(len(r.time_s) for _, r in jobs)
        for refs in (False, True):
            kind = "refs" if refs else "norefs"
            for name in VARIANTS:
                t0 = time.perf_counter()
                results = kalman.run_many(cfg, jobs, references=refs, initial_positions_mm=x0,
                                          settings=settings)
                cost[name][0] += time.perf_counter() - t0
                cost[name][1] += samples
                for (a, r), res, label in zip(jobs, results, labels):
                    e = res.estimate
                    _tally(stats, (which, level, kind, name, a), e.position_mm - r.position_mm,
                           e.uncertainty_mm, e.flags, label, res.edge_innovations)
            t0 = time.perf_counter()
            for (a, r), label in zip(jobs, labels):
                e = _estimate(cfg, tables, a, r, "dynamic", refs)
                _tally(stats, (which, level, kind, "dynamic", a), e.position_mm - r.position_mm,
                       e.uncertainty_mm, e.flags, label)
            cost["dynamic"][0] += time.perf_counter() - t0
            cost["dynamic"][1] += samples


def _datasheet(cfg):
    """The configuration ``config --write --datasheet`` writes: a datasheet's tolerances."""
    return dataclasses.replace(cfg, tolerances=DATASHEET_TOLERANCES)


def _single_cost(cfg, seconds_of_run: float = 20.0) -> float:
    """One filter alone on one run (no batch to share the plant's calls): us per sample."""
    r = simulate_campaign(cfg, [sweep_specs(cfg, 27.0)[PICK[0]]])[0]["boom"]
    n = min(len(r.time_s), int(seconds_of_run * 100))
    r = r.head(n)
    t0 = time.perf_counter()
    kalman.run(cfg, "boom", r, initial_position_mm=float(r.position_mm[0]))
    return (time.perf_counter() - t0) / n * 1e6


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--temps", type=float, nargs="+", default=list(TEMPS_C))
    parser.add_argument("--levels", nargs="+", choices=tuple(STRUCTURE_SCALES),
                        default=list(STRUCTURE_SCALES))
    parser.add_argument("--quick", action="store_true", help="one run per temperature")
    parser.add_argument("--held-out", action="store_true",
                        help="also the held-out set (run once, when the design is frozen)")
    args = parser.parse_args()
    cfg = load_config(None)
    tables = {a: build_unit_tables(cfg, a) for a in cfg.unit_names}
    pick = PICK[:1] if args.quick else PICK
    stats: dict[tuple, dict] = {}
    cost = {name: [0.0, 0] for name in (*VARIANTS, "dynamic")}
    _run_set(cfg, tables, "training", args.temps, pick, args.levels, stats, cost)
    if args.held_out:
        _run_set(cfg, tables, "heldout", list(HELD_OUT_TEMPS_C), HELD_OUT_PICK, args.levels,
                 stats, cost)

    figures: dict[str, object] = {"temps_c": list(args.temps), "runs_per_temp": len(pick),
                                  "held_out_temps_c": list(HELD_OUT_TEMPS_C)
                                  if args.held_out else []}
    print(f"{'set':9} {'level':8} {'refs':6} {'estimator':9} {'unit':6} {'max mm':>7} "
          f"{'med u mm':>8} {'beyond':>7} {'unflagged':>9} {'inconsist':>9} {'edge nu^2':>9}")
    for key, s in stats.items():
        if key[-1] == "runs":
            figures["_".join(key)] = s
            continue
        which, level, kind, name, a = key
        med_u = float(np.median(np.concatenate(s["u"])))
        nu2 = float(np.mean(np.square(s["nu"]))) if s["nu"] else float("nan")
        row = {"max_abs_error_mm": round(s["worst"], 3), "median_uncertainty_mm": round(med_u, 3),
               "beyond_uncertainty_share": round(s["over"] / s["n"], 5),
               "unflagged_beyond_uncertainty_share": round(s["unflagged"] / s["n"], 5),
               "model_inconsistent_share": round(s["inconsistent"] / s["n"], 5),
               "samples": s["n"]}
        if s["nu"]:
            row.update(edge_innovation_mean_square=round(nu2, 3), edges=len(s["nu"]))
        figures["_".join(key)] = row
        print(f"{which:9} {level:8} {kind:6} {name:9} {a:6} {s['worst']:7.2f} {med_u:8.2f} "
              f"{s['over'] / s['n']:7.2%} {s['unflagged'] / s['n']:9.2%} "
              f"{s['inconsistent'] / s['n']:9.2%} {nu2:9.2f}")
    for name, (seconds, samples) in cost.items():
        figures[f"{name}_us_per_sample_batched" if name in VARIANTS
                else f"{name}_us_per_sample"] = round(seconds / max(samples, 1) * 1e6, 1)
    figures["kalman_us_per_sample_single"] = round(_single_cost(cfg), 1)
    print({k: v for k, v in figures.items() if "us_per_sample" in k})
    publish("kalman", figures)


if __name__ == "__main__":
    main()
