"""A simulated fleet: per machine one CAN log (BLF) per day of varied work, no position frames.

Every machine has its own small, constant deviations (pump leakage x0.85..1.15, displacement
within +-0.3 %: inside what the diagnosis resolves). Some machines wear: one unit's pump
leakage rises linearly from a day on, or the drive's logged signals drift in time against the
I/O module's (a time offset growing from a day on: the sensor chain drifting). Rates are
drawn so that the error would cross a few millimetres two to three weeks after the onset.

Each day's log: ``LOG_S`` of point-to-point work of every unit between holds, passing the
Hall switches (the ends and the middle), a payload of the day, oil from a morning
temperature warming through the log. The truth (every machine's effects per day) goes to
``truth.json`` beside the logs; the analysis never reads it. File names carry the machine,
the date and the operating hours: ``M03_2026-01-05_0123.4h.blf``.
"""

from __future__ import annotations

import datetime as dt
import json
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ..atomic import output_dir
from ..config import Config
from ..errors import UserError
from .cycles import Profile, Trajectory, work_unit
from .effects import UnitEffects
from .run import RunSpec, simulate_campaign
from .sensors import SensorSettings

LOG_S = 60.0
STEP_S = 2.0e-3                 # plant step: within 0.1 mm of 1 ms on these cycles, 1.4x faster
START_DATE = dt.datetime(2026, 1, 5, 7, 0, tzinfo=dt.timezone.utc)
HOURS_PER_DAY = 7.5             # operating hours a working day adds
WEAR_SHARE = 0.3                # share of machines that wear
Progress = Callable[[float], None]


@dataclass(frozen=True)
class Wear:
    actuator: str
    effect: str                 # "pump_leakage" (factor rises) or "time_offset" (s rises)
    start_day: int
    rate_per_day: float         # factor or seconds per day after the start

    def value(self, day: int, base: float) -> float:
        return base + self.rate_per_day * max(0, day - self.start_day)


@dataclass(frozen=True)
class MachinePlan:
    name: str
    base: dict[str, dict[str, float]]      # actuator -> effect -> constant value
    wear: Wear | None = None
    seed: int = 0

    def effects(self, day: int) -> dict[str, UnitEffects]:
        out = {}
        for a in self.base:
            values = dict(self.base[a])
            if self.wear is not None and self.wear.actuator == a:
                neutral = getattr(UnitEffects(), self.wear.effect)
                values[self.wear.effect] = self.wear.value(
                    day, values.get(self.wear.effect, neutral))
            out[a] = UnitEffects(**values)
        return out


@dataclass(frozen=True)
class FleetPlan:
    machines: list[MachinePlan]
    days: int
    seed: int
    log_s: float = LOG_S


def plan_fleet(units: Sequence[str], machines: int, days: int, seed: int = 0,
               log_s: float = LOG_S,
               wear_share: float = WEAR_SHARE) -> FleetPlan:
    """Draw every machine's deviations and (for some) its wear."""
    if not 1 <= machines <= 1000:
        raise UserError(f"--machines {machines}: 1..1000")
    if not 2 <= days <= 3650:
        raise UserError(f"--days {days}: 2..3650")
    if not 20.0 <= log_s <= 3600.0:
        raise UserError(f"log length {log_s:g} s: 20..3600 s")
    rng = np.random.default_rng([seed, 7])
    n_wear = int(round(wear_share * machines))
    wearing = set(rng.choice(machines, size=n_wear, replace=False).tolist()) if n_wear else set()
    plans = []
    for m in range(machines):
        base = {a: {"pump_leakage": float(rng.uniform(0.85, 1.15)),
                    "displacement": float(1.0 + rng.uniform(-0.003, 0.003))}
                for a in units}
        wear = None
        if m in wearing:
            actuator = units[int(rng.integers(len(units)))]
            effect = "pump_leakage" if rng.random() < 0.6 else "time_offset"
            start = int(rng.integers(1, max(2, days // 5)))
            weeks = float(rng.uniform(2.0, 3.0))          # onset to a few mm of error
            rate = (1.0 if effect == "pump_leakage" else 0.05) / (7.0 * weeks)
            wear = Wear(actuator, effect, start, rate)
        plans.append(MachinePlan(f"M{m:02d}", base, wear, seed=int(rng.integers(2 ** 31))))
    return FleetPlan(plans, days, seed, log_s)


def work_profile(cfg: Config, rng: np.random.Generator, duration_s: float) -> Profile:
    """Point-to-point moves between holds; a quarter of the targets at the stroke ends so
    that every Hall switch is passed; speeds 30..100 % of the unit's work speed."""
    knots = {}
    for a in cfg.unit_names:
        stroke = cfg.unit(a).stroke_mm
        lo, hi, top = 1.0, stroke - 1.0, work_unit(cfg, a).work_speed_mm_s
        t, x = [0.0], [float(rng.uniform(0.2, 0.8) * stroke)]
        while t[-1] < duration_s - 4.0:
            t.append(t[-1] + float(rng.uniform(1.5, 4.0)))           # a hold
            x.append(x[-1])
            r = rng.random()
            target = lo if r < 0.125 else hi if r < 0.25 else float(rng.uniform(lo, hi))
            speed = float(rng.uniform(0.3, 1.0)) * top
            t.append(t[-1] + abs(target - x[-1]) / (0.75 * speed) + 0.2)
            x.append(target)
        knots[a] = (t, x)
    end = max(max(t[-1] for t, _ in knots.values()) + 2.0, duration_s)
    return Profile("fleet work day", {
        a: Trajectory(np.array(t + [end]), np.array(x + [x[-1]]), smooth=True)
        for a, (t, x) in knots.items()}, end)


def day_spec(cfg: Config, plan: FleetPlan, machine: MachinePlan, day: int) -> RunSpec:
    rng = np.random.default_rng([plan.seed, machine.seed, day])
    morning_c = float(rng.uniform(22.0, 34.0))
    return RunSpec(cycle=work_profile(cfg, rng, plan.log_s),
                   payload_kg=float(rng.choice([0.0, 300.0, 600.0, 1040.0])),
                   oil_temp_c=morning_c, effects=machine.effects(day),
                   seed=int(rng.integers(2 ** 31)),
                   sensors=replace(SensorSettings(), oil_temp_drift_c_per_s=0.1),
                   step_s=STEP_S)


def log_name(machine: str, day: int, hours: float) -> str:
    date = (START_DATE + dt.timedelta(days=day)).date().isoformat()
    return f"{machine}_{date}_{hours:06.1f}h.blf"


def truth_of(plan: FleetPlan) -> dict:
    return {"seed": plan.seed, "days": plan.days, "log_s": plan.log_s,
            "machines": {m.name: {
                "base": m.base, "wear": asdict(m.wear) if m.wear else None,
                "effects_per_day": [{a: e.non_neutral() for a, e in m.effects(d).items()}
                                    for d in range(plan.days)]} for m in plan.machines}}


def simulate_fleet(cfg: Config, plan: FleetPlan, out_dir: str | Path,
                   progress: Progress | None = None, days: range | list[int] | None = None,
                   days_per_batch: int = 10) -> list[Path]:
    """Write every machine's daily logs and ``truth.json``. Several days go into one
    vectorised campaign: the plant's cost is mostly per step, not per machine."""
    from ..canbus.fastblf import write_blf_inputs
    out = output_dir(out_dir)
    (out / "truth.json").write_text(json.dumps(truth_of(plan), indent=1) + "\n")
    written = []
    todo = list(days if days is not None else range(plan.days))
    batches = [todo[i:i + days_per_batch] for i in range(0, len(todo), days_per_batch)]
    for k, batch in enumerate(batches):
        specs = [(day, m) for day in batch for m in plan.machines]

        def part(f: float, k: int = k) -> None:
            if progress is not None:
                progress((k + 0.9 * f) / len(batches))

        runs = simulate_campaign(cfg, [day_spec(cfg, plan, m, day) for day, m in specs], part)
        for (day, m), per_unit in zip(specs, runs):
            start = (START_DATE + dt.timedelta(days=day)).timestamp()
            hours = 1000.0 * (int(m.name[1:]) % 3) + HOURS_PER_DAY * day
            for run in per_unit.values():
                run.time_s = run.time_s + start
            path = out / log_name(m.name, day, hours)
            write_blf_inputs(path, per_unit, cfg)            # no position frames
            written.append(path)
        if progress is not None:
            progress((k + 1) / len(batches))
    return written
