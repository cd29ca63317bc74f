"""Benchmark: hidden-effect trials, the share named correctly per effect, false alarms on
none, and the gain of the extended model (held-out maximum error before / after).

Each draw simulates a campaign (the paper cycle at two speeds, or random point-to-point
cycles; payloads 0 and 1040 kg; two oil temperatures) with one effect of the catalogue, or
none, at a random magnitude, and analyses both actuators from the runs alone.

    python bench/diagnosis.py [--draws 60] [--seed 1000] [--jobs 2] [--random-share 0.33]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import publish  # noqa: E402

from ddh_vsensor.config import ACTUATORS, load_config  # noqa: E402
from ddh_vsensor.diagnosis.analyze import diagnose  # noqa: E402
from ddh_vsensor.diagnosis.runs import prepare_run  # noqa: E402
from ddh_vsensor.diagnosis.trials import EFFECT_NAMES, draw_trial, simulate_trial  # noqa: E402


def one_draw(args: tuple[int, str, str]) -> list[dict]:
    seed, effect, cycle = args
    cfg = load_config(None)
    trial = draw_trial(seed, effect, cycle=cycle)
    started = time.perf_counter()
    runs = simulate_trial(cfg, trial)
    simulated = time.perf_counter() - started
    out = []
    for actuator in ACTUATORS:
        started = time.perf_counter()
        # the runs as a log would give them: no comments, nothing but the samples
        analysed = [prepare_run(r[actuator]) for r in runs]
        d = diagnose(cfg, actuator, analysed, "full")
        before = max(float(np.nanmax(np.abs(e))) for e in d.baseline)
        after = max(float(np.max(np.abs(h))) for h in d.chosen.heldout)
        out.append({"seed": seed, "effect": effect, "value": trial.value, "cycle": cycle,
                    "actuator": actuator, "named": d.cause, "before_mm": before,
                    "after_mm": after, "best": d.fits[0].cause.name,
                    "best_score": d.fits[0].score, "best_value": d.fits[0].value,
                    "true_score": next((f.score for f in d.fits if f.cause.name == effect),
                                       None),
                    "inertia": d.bench.inertia,
                    "simulate_s": simulated, "analyse_s": time.perf_counter() - started,
                    "trial": trial.describe()})
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--draws", type=int, default=60)
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--random-share", type=float, default=1 / 3,
                   help="share of draws on random point-to-point cycles")
    args = p.parse_args()
    todo = []
    for i in range(args.draws):
        effect = EFFECT_NAMES[i % len(EFFECT_NAMES)]         # stratified: equal counts
        cycle = "random" if (i // len(EFFECT_NAMES)) % round(1 / args.random_share) == 0 \
            and args.random_share > 0 else "paper"
        todo.append((args.seed + i, effect, cycle))
    results = []
    with ProcessPoolExecutor(args.jobs) as pool:
        for k, rows in enumerate(pool.map(one_draw, todo), 1):
            results += rows
            for r in rows:
                mark = "ok " if r["named"] == r["effect"] else "BAD"
                print(f"[{k:3d}/{len(todo)}] {mark} {r['trial']} | {r['actuator']:6s} named "
                      f"{r['named']:<17} max {r['before_mm']:7.2f} -> {r['after_mm']:6.2f} mm",
                      flush=True)
    figures: dict[str, object] = {"draws": args.draws,
                                  "analyses": len(results),
                                  "random_cycle_share": round(
                                      sum(r["cycle"] == "random" for r in results)
                                      / len(results), 3)}
    for effect in EFFECT_NAMES:
        rows = [r for r in results if r["effect"] == effect]
        right = [r for r in rows if r["named"] == effect]
        key = "false_alarm_rate_none" if effect == "none" else f"identified_{effect}"
        share = (len(rows) - len(right)) / len(rows) if effect == "none" else \
            len(right) / len(rows)
        figures[key] = round(share, 3)
        for actuator in ACTUATORS:
            sub = [r for r in rows if r["actuator"] == actuator]
            ok = sum(r["named"] == effect for r in sub)
            figures[f"{key}_{actuator}"] = round(
                (len(sub) - ok) / len(sub) if effect == "none" else ok / len(sub), 3)
        if effect != "none" and right:
            ratios = [r["after_mm"] / r["before_mm"] for r in right]
            figures[f"median_max_error_{effect}_mm"] = (
                f"{statistics.median(r['before_mm'] for r in right):.2f} -> "
                f"{statistics.median(r['after_mm'] for r in right):.2f}")
            figures[f"halved_{effect}"] = round(sum(x <= 0.5 for x in ratios) / len(ratios), 3)
    named = [r for r in results if r["effect"] != "none" and r["named"] == r["effect"]]
    figures["median_gain_max_error_ratio"] = round(statistics.median(
        r["after_mm"] / r["before_mm"] for r in named), 3)
    figures["median_gain_max_error_mm"] = round(statistics.median(
        r["before_mm"] - r["after_mm"] for r in named), 2)
    # the margins of the naming rule (selection.py): without effects, the best candidates;
    # with one, the true cause's score
    nominal = [r for r in results if r["effect"] == "none"]
    top = sorted((r for r in nominal if r["best"] != "none"), key=lambda r: r["best_score"])
    figures["none_best_candidates_top6"] = [
        f"{r['actuator']} {r['cycle']}: {r['best']} {r['best_score']:.2f} at "
        f"{r['best_value']:.4g}" for r in top[-6:]]
    scored = [r["true_score"] for r in results if r["effect"] != "none"]
    figures["true_cause_score_min_median"] = (f"{min(scored):.3f} / "
                                              f"{statistics.median(scored):.3f}")
    confusion = {}
    for r in results:
        if r["named"] != r["effect"]:
            k = f"{r['effect']}->{r['named']}"
            confusion[k] = confusion.get(k, 0) + 1
    figures["confusions"] = confusion or "none"
    figures["median_analyse_s_per_actuator"] = round(statistics.median(
        r["analyse_s"] for r in results), 2)
    figures["goal_identified"] = 0.9
    figures["goal_false_alarm_rate"] = 0.1
    publish("diagnosis", figures)


if __name__ == "__main__":
    main()
