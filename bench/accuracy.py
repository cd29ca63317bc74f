"""Accuracy of the estimator on the simulator's nominal runs (issue 4's acceptance figures).

- the table: mode x actuator x speed x payload, max and RMS error, no references, 27 °C;
- drift per cycle without references over a multi-cycle run;
- a 50-cycle run with references: max error overall, first ten cycles vs last ten;
- the temperature sweep (issue 12): oil at -10, 0, 10, 27, 50, 80 degC x the paper's cycle at
  four speeds x 0/1040 kg, plus the dig-dump cycle (both end stops, 0/1040 kg) and random work
  cycles with end-stop contact (seeds 201..): worst and RMS error per temperature, per mode,
  per actuator, no references. ``--sweep check`` runs the second set instead (oil at -5..75
  degC, 500 kg paper cycles, dig-dump at speeds 2-3, four random cycles per temperature with
  0-1040 kg and 40 % of the moves into an end stop, seeds 401..), which checked the rules the
  first set had shown; ``--draw SEED`` a set designed for nothing, drawn from SEED.
- ``--structure typical|double`` (only that set): the main sweep's runs on a plant whose
  structure the estimator's model does not share (``sim.effects.STRUCTURE_TYPICAL``: orifice
  and speed-dependent pump leakage, pressure-dependent seal friction, hose expansion and
  entrained air, the drive's torque an estimate, the tank sensor lagging the pumps' oil),
  every effect at its typical value or twice it (``none``: the nominal plant, for
  comparison); the `dynamic` mode with and without references. Per unit and temperature:
  the worst error and the share of samples published beyond their published uncertainty
  with no flag set (a plain, trusted reading that is wrong by more than it says).
Run: python bench/accuracy.py [--cycles 50] [--skip-sweep | --sweep-only] [--sweep main|check]
     [--draw SEED] [--structure none|typical|double [--structure-only EFFECT]
     [--temps DEGC ...]]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import publish  # noqa: E402

from ddh_vsensor.config import load_config  # noqa: E402
from ddh_vsensor.estimator.accuracy import accuracy  # noqa: E402
from ddh_vsensor.estimator.estimator import Estimator  # noqa: E402
from ddh_vsensor.sim.control import PIDSettings  # noqa: E402
from ddh_vsensor.sim.cycles import dig_dump_cycle, random_cycle  # noqa: E402
from ddh_vsensor.sim.effects import NOMINAL, STRUCTURE_TYPICAL, structure_effects  # noqa: E402
from ddh_vsensor.sim.run import RunSpec, simulate_campaign  # noqa: E402
from ddh_vsensor.tables.build import build_unit_tables  # noqa: E402


def _estimate(cfg, tables, actuator, run, mode, references):
    est = Estimator(cfg, actuator, tables[actuator], mode=mode, references=references,
                    initial_position_mm=float(run.position_mm[0]))
    return est.run(run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c,
                   run.refs if references else None, run.ref_edge_s if references else None)


MODES = ("dynamic", "full", "paper")
SWEEP_TEMPS_C = (-10.0, 0.0, 10.0, 27.0, 50.0, 80.0)
SWEEP_SEED = 201
CHECK_TEMPS_C = (-5.0, 5.0, 20.0, 40.0, 65.0, 75.0)
CHECK_SEED = 401
STAMPS_SEED = 77


def sweep_specs(cfg, temp_c: float) -> list[RunSpec]:
    """One temperature's runs: paper cycle x 4 speeds x 0/1040 kg, dig-dump x 0/1040 kg and
    two random cycles (seeded from the temperature) with end-stop contact."""
    specs = [RunSpec(speed=s, payload_kg=p, oil_temp_c=temp_c) for s in (1, 2, 3, 4)
             for p in (0.0, 1040.0)]
    specs += [RunSpec(cycle=dig_dump_cycle(cfg, 4), payload_kg=p, oil_temp_c=temp_c)
              for p in (0.0, 1040.0)]
    seed = SWEEP_SEED + 2 * SWEEP_TEMPS_C.index(temp_c)
    specs += [RunSpec(cycle=random_cycle(cfg, seed + i), payload_kg=p, oil_temp_c=temp_c)
              for i, p in enumerate((0.0, 1040.0))]
    return specs


def check_specs(cfg, temp_c: float) -> list[RunSpec]:
    """The check set's runs at one temperature: paper cycle at speeds 2 and 4 with 500 kg,
    dig-dump at speed 3 (500 kg) and 2 (1040 kg), four random cycles with end stops."""
    specs = [RunSpec(speed=s, payload_kg=500.0, oil_temp_c=temp_c) for s in (2, 4)]
    specs += [RunSpec(cycle=dig_dump_cycle(cfg, s), payload_kg=p, oil_temp_c=temp_c)
              for s, p in ((3, 500.0), (2, 1040.0))]
    seed = CHECK_SEED + 4 * CHECK_TEMPS_C.index(temp_c)
    specs += [RunSpec(cycle=random_cycle(cfg, seed + j, end_stop_share=0.4), payload_kg=p,
                      oil_temp_c=temp_c, seed=j)
              for j, p in enumerate((0.0, 300.0, 700.0, 1040.0))]
    return specs


RATES_TEMPS_C = (-10.0, 27.0, 80.0)


def rates_specs(cfg, temp_c: float) -> list[RunSpec]:
    """The fast-sampling set (run with --rate-hz): the paper cycle at
    speeds 1/3/4 with 1040/500/0 kg, dig-dump at 4 (0 kg) and 3 (1040 kg), three 60 s random
    cycles with 30 % of the moves into an end stop and 0/400/1040 kg."""
    specs = [RunSpec(speed=s, payload_kg=p, oil_temp_c=temp_c)
             for s, p in ((1, 1040.0), (3, 500.0), (4, 0.0))]
    specs += [RunSpec(cycle=dig_dump_cycle(cfg, s), payload_kg=p, oil_temp_c=temp_c)
              for s, p in ((4, 0.0), (3, 1040.0))]
    seed = 1000 + int(temp_c) * 7
    specs += [RunSpec(cycle=random_cycle(cfg, seed + i, end_stop_share=0.3), payload_kg=p,
                      oil_temp_c=temp_c, seed=i) for i, p in enumerate((0.0, 400.0, 1040.0))]
    return specs


def drawn_set(cfg, seed: int) -> dict[float, list[RunSpec]]:
    """A set designed for nothing, drawn from ``seed``: two oil temperatures from -10 to 27
    degC and four from 27 to 80, each with twelve runs, a quarter the paper cycle at a random
    speed, a fifth dig-dump, the rest random cycles with 10-60 % of their moves into an end
    stop; payloads 0-1040 kg; 60 % of the runs on a drive tuned otherwise (loop 3-6.5 rad/s,
    derivative filter 80-160 ms, torque ramp 5-20 ms)."""
    rng = np.random.default_rng(seed)
    temps = [round(float(t), 1) for t in np.concatenate([rng.uniform(-10.0, 27.0, 2),
                                                          rng.uniform(27.0, 80.0, 4)])]
    runs: dict[float, list[RunSpec]] = {}
    for i, temp in enumerate(temps):
        specs = runs.setdefault(temp, [])
        for k in range(12):
            pid = PIDSettings(bandwidth_rad_s=float(rng.uniform(3.0, 6.5)),
                              derivative_filter_s=float(rng.uniform(0.08, 0.16)),
                              torque_filter_s=float(rng.uniform(0.005, 0.02))) \
                if rng.random() < 0.6 else PIDSettings()
            payload = float(rng.uniform(0.0, 1040.0))
            kind = rng.random()
            common = dict(payload_kg=payload, oil_temp_c=temp, controller=pid, seed=k)
            if kind < 0.25:
                specs.append(RunSpec(speed=int(rng.integers(1, 5)), **common))
            elif kind < 0.45:
                specs.append(RunSpec(cycle=dig_dump_cycle(cfg, int(rng.integers(1, 5))),
                                     **common))
            else:
                cycle = random_cycle(cfg, seed * 100 + i * 12 + k,
                                     end_stop_share=float(rng.uniform(0.1, 0.6)))
                specs.append(RunSpec(cycle=cycle, **common))
    return runs


# run set -> (figure prefix, temperatures, runs at one temperature)
SWEEPS = {"main": ("sweep", SWEEP_TEMPS_C, sweep_specs),
          "check": ("check", CHECK_TEMPS_C, check_specs),
          "rates": ("rates", RATES_TEMPS_C, rates_specs)}


def run_set(cfg, which: str, draw_seed: int | None):
    """(figure prefix, temperatures, runs at one temperature) of a named or drawn set."""
    if draw_seed is None:
        return SWEEPS[which]
    drawn = drawn_set(cfg, draw_seed)
    return f"drawn{draw_seed}", tuple(drawn), lambda _cfg, temp: drawn[temp]


@dataclasses.dataclass(frozen=True)
class Stamps:
    """How the frames reach the estimator: a share of them lost, each late by a uniform
    delay up to ``late_s`` and jittered by a uniform +-``jitter_s`` (seeded per run)."""

    lost: float = 0.0
    late_s: float = 0.0
    jitter_s: float = 0.0

    @property
    def tag(self) -> str:
        return "".join(f"_{k}{v:g}" for k, v in (("lost", self.lost), ("late", self.late_s),
                                                  ("jitter", self.jitter_s)) if v)

    def apply(self, run, index: int) -> SimpleNamespace:
        rng = np.random.default_rng([STAMPS_SEED, index])
        n = len(run.time_s)
        keep = rng.random(n) >= self.lost
        keep[0] = True
        t = run.time_s + rng.uniform(0.0, self.late_s, n) + rng.uniform(-self.jitter_s,
                                                                          self.jitter_s, n)
        if np.any(np.diff(t[keep]) <= 0.0):
            raise SystemExit("the stamps go backwards: keep --late-s and twice --jitter-s "
                             "below one sample period")
        return SimpleNamespace(time_s=t[keep], **{k: getattr(run, k)[keep] for k in (
            "speed_rpm", "torque_nm", "oil_temp_c", "position_mm")})


def temperature_sweep(cfg, tables, figures: dict[str, object], which: str = "main",
                      rate_hz: float | None = None, stamps: Stamps = Stamps(),
                      temps_c: tuple[float, ...] | None = None,
                      plant_step_s: float | None = None, draw_seed: int | None = None) -> None:
    rows = []
    prefix, temps, make = run_set(cfg, which, draw_seed)
    temps = temps_c or temps
    if rate_hz is not None:
        prefix = f"{prefix}_{rate_hz:g}Hz"
    if plant_step_s is not None:
        prefix = f"{prefix}_step{plant_step_s:g}s"
    prefix += stamps.tag
    for temp in temps:
        t0 = time.perf_counter()
        specs = make(cfg, temp)
        if rate_hz is not None:
            specs = [dataclasses.replace(s, sensors=dataclasses.replace(s.sensors,
                                                                         rate_hz=rate_hz))
                     for s in specs]
        if plant_step_s is not None:
            specs = [dataclasses.replace(s, step_s=plant_step_s) for s in specs]
        runs = simulate_campaign(cfg, specs)
        print(f"{temp:g} degC: simulated {len(specs)} runs in {time.perf_counter() - t0:.0f} s",
              flush=True)
        for mode in MODES:
            for actuator in cfg.unit_names:
                worst, worst_run, sq, count = 0.0, "", 0.0, 0
                for i, (spec, run) in enumerate(zip(specs, runs)):
                    r = stamps.apply(run[actuator], i) if stamps != Stamps() else run[actuator]
                    err = (_estimate(cfg, tables, actuator, r, mode, False).position_mm
                           - r.position_mm)
                    err = err[np.isfinite(err)]
                    if np.max(np.abs(err)) > worst:
                        worst = float(np.max(np.abs(err)))
                        worst_run = (spec.cycle.name if not isinstance(spec.cycle, str)
                                     else f"paper speed {spec.speed}") + \
                            f" {spec.payload_kg:g} kg"
                    sq += float(np.sum(err ** 2))
                    count += err.size
                rms = (sq / count) ** 0.5
                key = f"{prefix}_{mode}_{actuator}_{temp:g}C"
                figures[f"{key}_max_abs_error_mm"] = round(worst, 3)
                figures[f"{key}_rms_error_mm"] = round(rms, 3)
                figures[f"{key}_worst_run"] = worst_run
                rows.append((temp, mode, actuator, worst, rms, worst_run))
    print(f"{'oil':>5} {'mode':8} {'actuator':8} {'max mm':>7} {'RMS mm':>7}  worst run")
    for temp, mode, actuator, worst, rms, run in rows:
        print(f"{temp:5g} {mode:8} {actuator:8} {worst:7.2f} {rms:7.2f}  {run}")


STRUCTURE_SCALES = {"none": 0.0, "typical": 1.0, "double": 2.0}


def structure_set(cfg, tables, figures: dict[str, object], level: str,
                  temps_c: tuple[float, ...], only: str | None = None) -> None:
    """The main sweep's runs with the structure effects at ``level`` on every unit (``only``:
    that one of them): the `dynamic` mode's worst error and its unflagged excursions beyond
    the uncertainty."""
    scale = STRUCTURE_SCALES[level]
    effects = structure_effects(scale) if scale else NOMINAL
    if only is not None:
        effects = dataclasses.replace(NOMINAL, **{only: getattr(effects, only)})
    figures["structure_effects"] = effects.non_neutral()
    rows = []
    totals: dict[tuple[str, str], list[float]] = {}
    for temp in temps_c:
        t0 = time.perf_counter()
        specs = [dataclasses.replace(s, effects={a: effects for a in cfg.unit_names})
                 for s in sweep_specs(cfg, temp)]
        runs = simulate_campaign(cfg, specs)
        print(f"{temp:g} degC: simulated {len(specs)} runs in {time.perf_counter() - t0:.0f} s",
              flush=True)
        for refs in (False, True):
            kind = "refs" if refs else "norefs"
            for actuator in cfg.unit_names:
                worst, worst_run, beyond, unflagged, count = 0.0, "", 0, 0, 0
                for spec, run in zip(specs, runs):
                    r = run[actuator]
                    est = _estimate(cfg, tables, actuator, r, "dynamic", refs)
                    err = np.abs(est.position_mm - r.position_mm)
                    ok = np.isfinite(err)
                    over = ok & (err > est.uncertainty_mm)
                    beyond += int(over.sum())
                    unflagged += int((over & (est.flags == 0)).sum())
                    count += int(ok.sum())
                    if np.max(err[ok]) > worst:
                        worst = float(np.max(err[ok]))
                        worst_run = (spec.cycle.name if not isinstance(spec.cycle, str)
                                     else f"paper speed {spec.speed}") + \
                            f" {spec.payload_kg:g} kg"
                key = f"structure_{level}_{kind}_{actuator}_{temp:g}C"
                figures[f"{key}_max_abs_error_mm"] = round(worst, 3)
                figures[f"{key}_worst_run"] = worst_run
                figures[f"{key}_beyond_uncertainty_share"] = round(beyond / count, 5)
                figures[f"{key}_unflagged_beyond_uncertainty_share"] = round(
                    unflagged / count, 5)
                tot = totals.setdefault((kind, actuator), [0.0, 0, 0, 0])
                tot[0] = max(tot[0], worst)
                tot[1] += beyond
                tot[2] += unflagged
                tot[3] += count
                rows.append((temp, kind, actuator, worst, beyond / count, unflagged / count,
                             worst_run))
    for (kind, actuator), (worst, beyond, unflagged, count) in totals.items():
        key = f"structure_{level}_{kind}_{actuator}"
        figures[f"{key}_max_abs_error_mm"] = round(worst, 3)
        figures[f"{key}_beyond_uncertainty_share"] = round(beyond / count, 5)
        figures[f"{key}_unflagged_beyond_uncertainty_share"] = round(unflagged / count, 5)
        figures[f"{key}_samples"] = count
    print(f"{'oil':>5} {'refs':6} {'actuator':8} {'max mm':>7} {'beyond':>7} "
          f"{'unflagged':>9}  worst run")
    for temp, kind, actuator, worst, beyond, unflagged, run in rows:
        print(f"{temp:5g} {kind:6} {actuator:8} {worst:7.2f} {beyond:7.2%} {unflagged:9.2%}  "
              f"{run}")


def nominal_and_drift(cfg, tables, figures: dict[str, object], cycles: int) -> None:
    """The 27 degC table and the multi-cycle drift / references run."""
    t0 = time.perf_counter()
    specs = [RunSpec(speed=s, payload_kg=p, oil_temp_c=27.0) for s in (1, 2, 3, 4)
             for p in (0.0, 1040.0)]
    runs = simulate_campaign(cfg, specs)
    print(f"simulated 8 nominal runs in {time.perf_counter() - t0:.1f} s")
    print(f"{'mode':6} {'actuator':8} {'speed':>5} {'payload':>8} {'max mm':>8} {'RMS mm':>8}")
    for mode in MODES:
        for actuator in cfg.unit_names:
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
                                           cycles=cycles)])[0]
    print(f"simulated {cycles} cycles in {time.perf_counter() - t0:.1f} s")
    for mode in ("dynamic", "full"):
        for actuator in cfg.unit_names:
            r = long[actuator]
            period = r.time_s[-1] / cycles
            cycle = np.minimum((r.time_s / period).astype(int), cycles - 1)
            # references: their changes timed by the I/O module (a CAN log), or by the rows
            for refs, timed in ((False, False), (True, True), (True, False)):
                est = Estimator(cfg, actuator, tables[actuator], mode=mode, references=refs,
                                initial_position_mm=float(r.position_mm[0]))
                res = est.run(r.time_s, r.speed_rpm, r.torque_nm, r.oil_temp_c,
                              r.refs if refs else None, r.ref_edge_s if timed else None)
                err = res.position_mm - r.position_mm
                per_cycle = np.array([np.nanmax(np.abs(err[cycle == c]))
                                      for c in range(cycles)])
                kind = "norefs" if not refs else "refs" if timed else "refs_rows"
                tag = f"{mode}_{actuator}_{cycles}cycles_{kind}"
                figures[f"{tag}_max_abs_error_mm"] = round(float(np.nanmax(np.abs(err))), 3)
                figures[f"{tag}_first10_max_mm"] = round(float(per_cycle[:10].max()), 3)
                figures[f"{tag}_last10_max_mm"] = round(float(per_cycle[-10:].max()), 3)
                if not refs:
                    ends = np.array([err[cycle == c][np.isfinite(err[cycle == c])][-1]
                                     for c in range(cycles)])
                    drift = np.polyfit(np.arange(cycles), ends, 1)[0]
                    figures[f"{mode}_{actuator}_drift_per_cycle_norefs_mm"] = round(
                        float(drift), 4)
                else:
                    figures[f"{mode}_{actuator}_gains_after_{cycles}_cycles_{kind}"] = [
                        round(float(g), 5) for g in est.gain.gain]


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--cycles", type=int, default=50)
    parser.add_argument("--skip-sweep", action="store_true")
    parser.add_argument("--sweep", choices=tuple(SWEEPS), default="main",
                        help="the temperature sweep's run set (check: the second set)")
    parser.add_argument("--draw", type=int, default=None, metavar="SEED",
                        help="instead of --sweep, a set designed for nothing drawn from SEED "
                             "(six oil temperatures, 72 runs, drives tuned otherwise)")
    parser.add_argument("--sweep-only", action="store_true",
                        help="skip the 27 degC table and the multi-cycle runs")
    parser.add_argument("--rate-hz", type=float, default=None,
                        help="the sweep's drive and sensor sampling (default: the "
                             "simulator's 100 Hz)")
    parser.add_argument("--window-s", type=float, default=None,
                        help="estimator.dynamic_window_s for this run (0: per sample)")
    parser.add_argument("--torque-lag-s", type=float, default=None,
                        help="motor.torque_lag_s of every unit for this run (the "
                             "configuration's otherwise)")
    parser.add_argument("--lost", type=float, default=0.0,
                        help="share of the frames lost before the estimator (0..0.5)")
    parser.add_argument("--late-s", type=float, default=0.0,
                        help="frames late by a uniform delay up to this (s)")
    parser.add_argument("--jitter-s", type=float, default=0.0,
                        help="frames' stamps jittered by a uniform +-this (s)")
    parser.add_argument("--temps", type=float, nargs="+", default=None, metavar="DEGC",
                        help="only these of the set's oil temperatures")
    parser.add_argument("--plant-step-s", type=float, default=None,
                        help="the simulator's integration step (default 1 ms); the torque "
                             "it logs is the one applied over the last step, half a step "
                             "behind the speed")
    parser.add_argument("--structure", choices=tuple(STRUCTURE_SCALES), default=None,
                        help="only the structure-mismatch set: the main sweep's runs with "
                             "every structure effect at its typical value (or twice it; "
                             "none: the nominal plant)")
    parser.add_argument("--structure-only", choices=tuple(STRUCTURE_TYPICAL), default=None,
                        metavar="EFFECT",
                        help="with --structure: only this one of the structure effects "
                             "(what each contributes)")
    args = parser.parse_args()
    if not (0.0 <= args.lost <= 0.5 and args.late_s >= 0.0 and args.jitter_s >= 0.0):
        parser.error("--lost 0..0.5, --late-s and --jitter-s >= 0")
    if args.draw is not None and not 0 <= args.draw < 2 ** 32:
        parser.error("--draw: a seed 0..2**32-1")
    cfg = load_config(None)
    set_temps = run_set(cfg, args.sweep, args.draw)[1]
    if args.temps and not set(args.temps) <= set(set_temps):
        parser.error(f"--temps: the set has {set_temps}")
    if args.rate_hz is not None and not 1.0 <= args.rate_hz <= 1000.0:
        parser.error("--rate-hz: 1..1000 (the simulator steps at 1 ms)")
    if args.plant_step_s is not None and not 1e-5 <= args.plant_step_s <= 1e-3:
        parser.error("--plant-step-s: 1e-5..1e-3 s (a whole number of steps per sample)")
    if args.window_s is not None:
        cfg = dataclasses.replace(cfg, estimator=dataclasses.replace(
            cfg.estimator, dynamic_window_s=args.window_s))
    if args.torque_lag_s is not None:
        if not -0.005 <= args.torque_lag_s <= 0.005:
            parser.error("--torque-lag-s: -0.005..0.005 s")
        cfg = dataclasses.replace(cfg, units={
            name: dataclasses.replace(unit, motor=dataclasses.replace(
                unit.motor, torque_lag_s=args.torque_lag_s))
            for name, unit in cfg.units.items()})
    tables = {a: build_unit_tables(cfg, a) for a in cfg.unit_names}
    figures: dict[str, object] = {}
    if args.structure is not None:
        if args.draw is not None or args.sweep != "main":
            parser.error("--structure runs the main sweep's runs (no --draw, --sweep)")
        structure_set(cfg, tables, figures, args.structure,
                      tuple(args.temps) if args.temps else SWEEP_TEMPS_C, args.structure_only)
        only = f"_{args.structure_only}" if args.structure_only else ""
        publish(f"accuracy_structure_{args.structure}{only}", figures)
        return
    if args.structure_only is not None:
        parser.error("--structure-only needs --structure")
    if not args.sweep_only:
        nominal_and_drift(cfg, tables, figures, args.cycles)
    if not args.skip_sweep:
        temperature_sweep(cfg, tables, figures, args.sweep, args.rate_hz,
                          Stamps(args.lost, args.late_s, args.jitter_s),
                          tuple(args.temps) if args.temps else None, args.plant_step_s,
                          args.draw)
    publish("accuracy", figures)


if __name__ == "__main__":
    main()
