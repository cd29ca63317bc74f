"""Benchmark: the diagnosis from references and holds against the position-truth analysis,
on the seeded hidden-effect trials (diagnosis/trials.py).

Per draw both actuators are analysed twice on the same runs: from the Hall edges and holds
alone (no position column used) and from the reference position. Figures per effect: the
share named correctly by each, and the error at the references (maximum |edge-to-edge error
increment| on held-out runs) before and after the named extension.

    python bench/references.py [--draws 8] [--seed 5000] [--jobs 1] [--rows-only]
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

from ddh_vsensor.config import load_config  # noqa: E402
from ddh_vsensor.diagnosis.analyze import diagnose  # noqa: E402
from ddh_vsensor.diagnosis.reference_fit import (  # noqa: E402
    POSITION_SENSOR_CAUSES, diagnose_references)
from ddh_vsensor.diagnosis.references import reference_run  # noqa: E402
from ddh_vsensor.diagnosis.runs import prepare_run  # noqa: E402
from ddh_vsensor.diagnosis.trials import EFFECT_NAMES, draw_trial, simulate_trial  # noqa: E402


def right_answer(effect: str) -> str:
    """What the analysis from references should answer: a cause of the position sensor
    the references replace has changed nothing they see."""
    return "none" if effect in POSITION_SENSOR_CAUSES else effect


def one_draw(args: tuple[int, str, bool, bool]) -> list[dict]:
    seed, effect, position, rows_only = args
    cfg = load_config(None)
    trial = draw_trial(seed, effect)
    runs = simulate_trial(cfg, trial)
    if rows_only:           # as a CSV carries them: switch changes known to the sample
        for per_unit in runs:
            for run in per_unit.values():
                run.ref_edge_s = {}
    out = []
    for actuator in cfg.unit_names:
        started = time.perf_counter()
        rr = [reference_run(cfg, actuator, r[actuator]) for r in runs]
        d = diagnose_references(cfg, actuator, rr)
        refs_s = time.perf_counter() - started
        inc = [m[:r.n_increments] for m, r in zip(d.model, rr)]
        ext = [h[:r.n_increments] for h, r in zip(d.chosen.heldout, rr)]
        before = max(float(np.max(np.abs(e))) for e in inc)
        after = max(float(np.max(np.abs(e))) for e in ext) if d.cause not in (
            "none", "unexplained", "ambiguous") else before
        started = time.perf_counter()
        p = diagnose(cfg, actuator, [prepare_run(r[actuator]) for r in runs]) \
            if position else None
        out.append({"seed": seed, "effect": effect, "value": trial.value,
                    "actuator": actuator, "named": d.cause,
                    "position_named": p.cause if p else None,
                    "parameters": d.chosen.parameters,
                    "interval": d.intervals.get(d.chosen.cause.name),
                    "position_parameters": p.chosen.parameters if p else None,
                    "before_mm": before, "after_mm": after,
                    "edges": sum(r.n_increments for r in rr),
                    "holds": sum(len(r.holds) for r in rr),
                    "references_s": refs_s, "position_s": time.perf_counter() - started,
                    "trial": trial.describe()})
        print(f"{trial.describe()} {actuator}: references -> {d.cause} "
              f"({before:.2f} -> {after:.2f} mm) {d.chosen.parameters}, position -> "
              f"{p.cause if p else '-'}", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=8, help="draws per effect")
    ap.add_argument("--seed", type=int, default=5000)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--no-position", action="store_true",
                    help="skip the position-truth analysis (its figures: diagnosis/README.md)")
    ap.add_argument("--rows-only", action="store_true",
                    help="the switches' changes known to the sample only (a CSV's rows), not "
                         "timed as an I/O module sending on change of state times them")
    args = ap.parse_args()
    cfg = load_config(None)
    tasks = [(args.seed + 100 * i + j, effect, not args.no_position, args.rows_only)
             for i in range(args.draws) for j, effect in enumerate(EFFECT_NAMES)]
    with ProcessPoolExecutor(args.jobs) as pool:
        rows = [row for rows in pool.map(one_draw, tasks) for row in rows]
    figures: dict[str, object] = {"draws_per_effect": args.draws, "analyses": len(rows),
                                  "switch changes": "sample rows" if args.rows_only
                                  else "timed (I/O module on change of state)"}
    for effect in EFFECT_NAMES:
        mine = [r for r in rows if r["effect"] == effect]
        named = sum(r["named"] == right_answer(effect) for r in mine) / len(mine)
        figures[f"{effect}: named from references"] = f"{100 * named:.0f} %" + (
            " (answered none: the effect is in the removed sensor only)"
            if effect in POSITION_SENSOR_CAUSES else "")
        if not args.no_position:
            pos = sum(r["position_named"] == effect for r in mine) / len(mine)
            figures[f"{effect}: named from position"] = f"{100 * pos:.0f} %"
        for a in cfg.unit_names:
            ma = [r for r in mine if r["actuator"] == a]
            figures[f"{effect}: named from references ({a})"] = \
                f"{100 * sum(r['named'] == right_answer(effect) for r in ma) / len(ma):.0f} %"
        if right_answer(effect) != "none":
            right = [r for r in mine if r["named"] == effect]
            halved = sum(r["after_mm"] <= 0.5 * r["before_mm"] for r in right)
            figures[f"{effect}: error at references halved (named)"] = \
                f"{halved}/{len(right)}"
            if right:
                figures[f"{effect}: max increment, median before -> after (mm)"] = \
                    (f"{statistics.median(r['before_mm'] for r in right):.2f} -> "
                     f"{statistics.median(r['after_mm'] for r in right):.2f}")
    figures["unexplained answers"] = sum(r["named"] == "unexplained" for r in rows)
    figures["seconds per actuator (references / position), median"] = (
        f"{statistics.median(r['references_s'] for r in rows):.1f} / "
        f"{statistics.median(r['position_s'] for r in rows):.1f}")
    figures["rows"] = rows
    publish("references", figures)


if __name__ == "__main__":
    main()
