"""A simulated fleet: per machine one CAN log (BLF) per day of varied work, no position frames.

Every machine has its own small, constant deviations (pump leakage x0.85..1.15, displacement
within +-0.3 %: inside what the diagnosis resolves). Some machines wear: one unit's pump
leakage rises linearly from a day on, or the drive's logged signals drift in time against the
I/O module's (a time offset growing from a day on: the sensor chain drifting).

Wear rates: drawn is the time from the onset until the expected position error first
exceeds :data:`CROSS_MM` (2..3 weeks, uniform, whole days); the rate is then solved for from
the worn unit's own sensitivity on the machine's own days (the error per unit of the
parameter on each day's work, payload and oil, as the analysis sees the day: its log, or
with day summaries its sessions' mean; :func:`expected_error_mm` takes the median over a day
and the two before, as the analysis does) and, for leakage, from the unit's own base
factor. The day-to-day scatter of the work moves the first crossing a few days either
way of the drawn one. A fixed rate per effect would not do: a time offset's error grows with
the unit's speeds, a leakage's with its load, oil and pumps, so the faster unit would cross
within a week of the onset and no warning could come a week ahead of it.

Each day's log: ``LOG_S`` of point-to-point work of every unit between holds, passing the
Hall switches (the ends and the middle), a payload of the day, oil from a morning
temperature warming through the log. The truth (every machine's effects per day) goes to
``truth.json`` beside the logs; the analysis never reads it. File names carry the machine,
the date and the operating hours: ``M03_2026-01-05_0123.4h.blf``.

A day's work, as the daemon sees it (``work_s``, default :data:`WORK_S`): sessions of
``log_s`` spread evenly over the working day (:data:`HOURS_PER_DAY`), the first the logged
one, each with its own moves and payload, the oil warming from the morning's towards
:data:`WORKING_OIL_C` over the first sessions. What stands for the whole day is those
minutes (a real day has ~45 times more). Given a ``summarise`` callback,
:func:`simulate_fleet` hands it every machine-day's sessions (the daemon's summary code,
``simulate fleet``: ``<machine>_<date>.summary.json`` beside the logs); the logs are those
of the first sessions, whatever ``work_s``.
"""

from __future__ import annotations

import datetime as dt
import json
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ddh_vsensor.atomic import output_dir
from ddh_vsensor.config import Config
from ddh_vsensor.errors import UserError
from ddh_vsensor.estimator.day_samples import summary_name
from ddh_vsensor.measured import Run
from ddh_vsensor.physics.steady import holding_speed, steady_state, steady_state_at_torque
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.sim.cycles import Profile, Trajectory, work_unit
from ddh_vsensor.sim.effects import UnitEffects
from ddh_vsensor.sim.run import RunSpec, simulate_campaign
from ddh_vsensor.sim.sensors import SensorSettings, hall_switch

LOG_S = 60.0
WORK_S = 600.0                  # a day's work the daemon's summary sees: 10 sessions of LOG_S
WORKING_OIL_C = 50.0            # the oil a day's later sessions warm towards
WARMUP_SESSIONS = 3.0           # ... by 1 - exp(-session / this)
STEP_S = 2.0e-3                 # plant step: within 0.1 mm of 1 ms on these cycles, 1.4x faster
START_DATE = dt.datetime(2026, 1, 5, 7, 0, tzinfo=dt.timezone.utc)
HOURS_PER_DAY = 7.5             # operating hours a working day adds
WEAR_SHARE = 0.3                # share of machines that wear
CROSS_MM = 3.0                  # expected error a wear reaches 2..3 weeks after its onset
CROSS_WEEKS = (2.0, 3.0)
PAYLOADS_KG = (0.0, 300.0, 600.0, 1040.0)
MORNING_OIL_C = (22.0, 34.0)
OIL_WARMING_C_PER_S = 0.1
SAMPLE_S = 0.01                 # sampling of a day's setpoints for its Hall edges
Progress = Callable[[float], None]
Summarise = Callable[[str, int, list[dict[str, Run]]], object]   # machine, day, sessions


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
    work_s: float = 0.0         # a day's work for the summaries (0: the log's only)

    @property
    def sessions(self) -> int:
        """Sessions of a day's work (the first is the logged one)."""
        return max(1, round(self.work_s / self.log_s))


def plan_fleet(cfg: Config, machines: int, days: int, seed: int = 0,
               log_s: float = LOG_S, wear_share: float = WEAR_SHARE,
               cross_mm: float = CROSS_MM, work_s: float = 0.0) -> FleetPlan:
    """Draw every machine's deviations and (for some) its wear: the unit, the effect, the
    onset day and the weeks until the expected error crosses ``cross_mm``; the rate follows
    from the unit's sensitivity on the machine's own days (see the module's docstring)."""
    if not 1 <= machines <= 1000:
        raise UserError(f"--machines {machines}: 1..1000")
    if not 2 <= days <= 3650:
        raise UserError(f"--days {days}: 2..3650")
    if not 20.0 <= log_s <= 3600.0:
        raise UserError(f"log length {log_s:g} s: 20..3600 s")
    if work_s and not log_s <= work_s <= 3600.0 * HOURS_PER_DAY:
        raise UserError(f"a day's work {work_s:g} s: 0 (no summaries) or {log_s:g} (the log) "
                        f"..{3600.0 * HOURS_PER_DAY:g} s")
    units = cfg.unit_names
    sessions = max(1, round(work_s / log_s)) if work_s else 1
    rng = np.random.default_rng([seed, 7])
    n_wear = int(round(wear_share * machines))
    wearing = set(rng.choice(machines, size=n_wear, replace=False).tolist()) if n_wear else set()
    plans = []
    for m in range(machines):
        base = {a: {"pump_leakage": float(rng.uniform(0.85, 1.15)),
                    "displacement": float(1.0 + rng.uniform(-0.003, 0.003))}
                for a in units}
        drawn = None
        if m in wearing:
            actuator = units[int(rng.integers(len(units)))]
            effect = "pump_leakage" if rng.random() < 0.6 else "time_offset"
            start = int(rng.integers(1, max(2, days // 5)))
            weeks = float(rng.uniform(*CROSS_WEEKS))
            drawn = (actuator, effect, start, round(7.0 * weeks))
        plan = MachinePlan(f"M{m:02d}", base, None, seed=int(rng.integers(2 ** 31)))
        if drawn is not None:
            plan = replace(plan, wear=_wear_crossing(cfg, seed, plan, *drawn, log_s, cross_mm,
                                                     sessions))
        plans.append(plan)
    return FleetPlan(plans, days, seed, log_s, work_s)


def _wear_crossing(cfg: Config, seed: int, plan: MachinePlan, actuator: str, effect: str,
                   start: int, after_days: int, log_s: float, cross_mm: float,
                   sessions: int = 1) -> Wear:
    """The wear that takes the error from the unit's base value to ``cross_mm``
    ``after_days`` after the onset at the unit's median sensitivity over those days (the
    error is linear in the parameter's distance from neutral; the day-to-day scatter of
    the work moves the first crossing by a few days either way)."""
    sens = float(np.median([_day_sensitivity_mm(cfg, actuator, effect, seed, plan.seed, d,
                                                log_s, sessions)
                            for d in range(start, start + after_days + 1)]))
    neutral = getattr(UnitEffects(), effect)
    crossing = neutral + cross_mm / sens
    base = plan.base[actuator].get(effect, neutral)
    return Wear(actuator, effect, start, (crossing - base) / after_days)


def expected_error_mm(cfg: Config, plan: FleetPlan, machine: MachinePlan, day: int
                      ) -> float:
    """The expected position error (mm) of a machine's wearing unit on a day (0 without
    wear): per day of the day and the two before (the recent work the analysis judges on),
    the day's sensitivity times the parameter's distance from neutral; their median."""
    w = machine.wear
    if w is None:
        return 0.0
    neutral = getattr(UnitEffects(), w.effect)
    sessions = plan.sessions if plan.work_s else 1
    return float(np.median([
        _day_sensitivity_mm(cfg, w.actuator, w.effect, plan.seed, machine.seed, d, plan.log_s,
                            sessions)
        * abs(getattr(machine.effects(d)[w.actuator], w.effect) - neutral)
        for d in range(max(0, day - 2), day + 1)]))


def _day_sensitivity_mm(cfg: Config, unit: str, effect: str, fleet_seed: int,
                        machine_seed: int, day: int, log_s: float, sessions: int = 1
                        ) -> float:
    """Expected position error per unit of the wear's parameter (per second of time offset,
    per 1.0 of leakage factor) on one day of a machine's work as the analysis sees it: the
    mean over the day's ``sessions`` (the logged one alone without day summaries; a day
    summary's rows are its stretches' mean) of each session's largest change the wear makes
    to an edge-to-edge increment of the estimate (0 with fewer than two Hall edges: nothing
    to change). The later sessions' oil is warmer and their payloads their own, so a day's
    work as the daemon sees it is more sensitive to a leakage than its first minutes.

    A time offset shifts the logged speed against the Hall edges: an increment changes by
    the offset times the difference of the speeds at its two edges. Extra leakage lets the
    load sink while the drive's speed and torque say it stands: an increment changes by that
    creep (the nominal model's speed at the worn unit's holding speed and torque) times the
    time between its edges. Both from the configuration and the steady-state model."""
    if effect not in ("time_offset", "pump_leakage"):
        raise ValueError(f"no wear sensitivity for {effect!r}")
    return float(np.mean([
        _session_sensitivity_mm(cfg, unit, effect,
                                *_conditions(cfg, fleet_seed, machine_seed, day, j, log_s)[:3])
        for j in range(sessions)]))


def _session_sensitivity_mm(cfg: Config, unit: str, effect: str, oil_start_c: float,
                            profile: Profile, payload_kg: float) -> float:
    ucfg = cfg.unit(unit)
    t = np.arange(0.0, profile.duration_s, SAMPLE_S)
    x_mm, v_mm_s = profile.trajectories[unit].evaluate(t)
    changed = np.zeros(len(t), bool)
    for pos in ucfg.references_mm.values():
        state = hall_switch(x_mm, pos, ucfg.reference_window_mm, ucfg.reference_hysteresis_mm)
        changed[1:] |= np.diff(state.astype(int)) != 0
    edges = np.flatnonzero(changed)
    if len(edges) < 2:
        return 0.0
    if effect == "time_offset":
        return float(np.max(np.abs(np.diff(v_mm_s[edges]))))
    nominal = DDHUnit.from_config(cfg, unit)
    worn = nominal.with_pumps(leakage=2.0)
    oil_c = oil_start_c + OIL_WARMING_C_PER_S * profile.duration_s / 2
    force = nominal.load_force_n(payload_kg)
    n = holding_speed(worn, force, oil_c).speed_rpm
    torque = steady_state(worn, n, force, oil_c).torque_nm
    creep_mm_s = 1e3 * abs(float(steady_state_at_torque(nominal, n, torque,
                                                         oil_c).velocity_m_s))
    return creep_mm_s * float(np.max(np.diff(t[edges])))


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


def _day_conditions(cfg: Config, rng: np.random.Generator, log_s: float
                    ) -> tuple[float, Profile, float]:
    """A day's morning oil (degC), work and payload (kg)."""
    morning_c = float(rng.uniform(*MORNING_OIL_C))
    profile = work_profile(cfg, rng, log_s)
    return morning_c, profile, float(rng.choice(PAYLOADS_KG))


def _conditions(cfg: Config, fleet_seed: int, machine_seed: int, day: int, session: int,
                log_s: float) -> tuple[float, Profile, float, int]:
    """A session's oil at its start (degC), work, payload (kg) and noise seed: the first is
    the day's morning (the logged session), each later its own moves and payload, its oil
    warmer (see the module's docstring)."""
    rng = np.random.default_rng([fleet_seed, machine_seed, day])
    morning_c, profile, payload_kg = _day_conditions(cfg, rng, log_s)
    seed = int(rng.integers(2 ** 31))
    if session == 0:
        return morning_c, profile, payload_kg, seed
    rng = np.random.default_rng([fleet_seed, machine_seed, day, session])
    oil_c = morning_c + (WORKING_OIL_C - morning_c) * (1.0 - np.exp(-session / WARMUP_SESSIONS))
    profile = work_profile(cfg, rng, log_s)
    payload_kg = float(rng.choice(PAYLOADS_KG))
    return float(oil_c), profile, payload_kg, int(rng.integers(2 ** 31))


def day_spec(cfg: Config, plan: FleetPlan, machine: MachinePlan, day: int) -> RunSpec:
    """A day's logged session."""
    return session_spec(cfg, plan, machine, day, 0)


def session_spec(cfg: Config, plan: FleetPlan, machine: MachinePlan, day: int,
                 session: int) -> RunSpec:
    """A day's session of work (:func:`_conditions`) with the machine's effects of the day."""
    oil_c, profile, payload_kg, seed = _conditions(cfg, plan.seed, machine.seed, day, session,
                                                   plan.log_s)
    return RunSpec(cycle=profile, payload_kg=payload_kg, oil_temp_c=oil_c,
                   effects=machine.effects(day), seed=seed,
                   sensors=replace(SensorSettings(),
                                   oil_temp_drift_c_per_s=OIL_WARMING_C_PER_S),
                   step_s=STEP_S)


def session_start_s(plan: FleetPlan, day: int, session: int) -> float:
    """A session's wall-clock start: the sessions spread evenly over the working day."""
    spacing_s = 3600.0 * HOURS_PER_DAY / plan.sessions
    return (START_DATE + dt.timedelta(days=day)).timestamp() + session * spacing_s


def _date(day: int) -> str:
    return (START_DATE + dt.timedelta(days=day)).date().isoformat()


def log_name(machine: str, day: int) -> str:
    """A machine-day's log, named by its date and its hour meter at the day's start (each
    machine starts at 0, 1000 or 2000 h and runs :data:`HOURS_PER_DAY` a day)."""
    hours = 1000.0 * (int(machine[1:]) % 3) + HOURS_PER_DAY * day
    return f"{machine}_{_date(day)}_{hours:06.1f}h.blf"


def day_summary_name(machine: str, day: int) -> str:
    """A machine-day's summary file, as the daemon's code names it."""
    return summary_name(machine, _date(day))


def truth_of(plan: FleetPlan) -> dict:
    return {"seed": plan.seed, "days": plan.days, "log_s": plan.log_s,
            "work_s": plan.work_s, "sessions": plan.sessions if plan.work_s else 1,
            "machines": {m.name: {
                "base": m.base, "wear": asdict(m.wear) if m.wear else None,
                "effects_per_day": [{a: e.non_neutral() for a, e in m.effects(d).items()}
                                    for d in range(plan.days)]} for m in plan.machines}}


def simulate_fleet(cfg: Config, plan: FleetPlan, out_dir: str | Path,
                   progress: Progress | None = None, days: range | list[int] | None = None,
                   days_per_batch: int = 10, summarise: Summarise | None = None
                   ) -> list[Path]:
    """Write every machine's daily logs and ``truth.json``; with ``summarise``, simulate
    every day's sessions and hand them to it, machine-day by machine-day. Several days go
    into one vectorised campaign (the plant's cost is mostly per step, not per machine), at
    most ``days_per_batch`` days' logs' worth of runs."""
    from ddh_vsensor.io.blf import write_blf_inputs
    out = output_dir(out_dir)
    (out / "truth.json").write_text(json.dumps(truth_of(plan), indent=1) + "\n")
    written = []
    sessions = plan.sessions if summarise is not None else 1
    todo = list(days if days is not None else range(plan.days))
    per_batch = max(1, days_per_batch // sessions)
    batches = [todo[i:i + per_batch] for i in range(0, len(todo), per_batch)]
    for k, batch in enumerate(batches):
        specs = [(day, m, j) for day in batch for m in plan.machines for j in range(sessions)]

        def part(f: float, k: int = k) -> None:
            if progress is not None:
                progress((k + (0.9 if summarise is None else 0.5) * f) / len(batches))

        runs = simulate_campaign(cfg, [session_spec(cfg, plan, m, day, j)
                                       for day, m, j in specs], part)
        for i, ((day, m, j), per_unit) in enumerate(zip(specs, runs)):
            for run in per_unit.values():
                run.shift_time(session_start_s(plan, day, j))
            if j == 0:
                path = out / log_name(m.name, day)
                write_blf_inputs(path, per_unit, cfg)            # no position frames
                written.append(path)
            if summarise is not None and j == sessions - 1:
                summarise(m.name, day, runs[i - sessions + 1:i + 1])
                if progress is not None:
                    progress((k + 0.5 + 0.5 * (i + 1) / len(specs)) / len(batches))
        if progress is not None:
            progress((k + 1) / len(batches))
    return written
