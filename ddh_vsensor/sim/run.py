"""Simulated measured runs: specs in, ``Run`` objects (and CSV/BLF files) out.

``simulate_campaign(cfg, specs)`` simulates many runs at once: every unit of every run is a
row of one vectorised plant, so the per-step Python overhead is shared (runs with the same
step, sample rate and controller settings go together; the others form further batches).
``simulate(cfg, spec)`` is the one-run form, ``write_run_dir`` writes one ``<unit>.csv`` per
unit (``boom.csv``, ``bucket.csv`` for the reference loader) and ``run.blf``.

Each sample holds the plant's state at its instant and the motor torque applied over the
step that ended there: the torque is half a step (``step_s``) behind the speed, as a drive's
may be (``motor.torque_lag_s``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ddh_vsensor.atomic import output_dir
from ddh_vsensor.config import Config
from ddh_vsensor.errors import UserError
from ddh_vsensor.measured import Run
from ddh_vsensor.io.csv import write_csv
from ddh_vsensor.physics.steady import holding_speed, steady_state
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.sim.control import PIDSettings, PositionPID
from ddh_vsensor.sim.cycles import WORK, Profile, load_profile_csv, work_cycle
from ddh_vsensor.sim.effects import UnitEffects, build_effects, describe
from ddh_vsensor.model.plant import Plant, RowSpec
from ddh_vsensor.model.unit import Structure
from ddh_vsensor.sim.sensors import SensorSettings, Truth, measure

DEFAULT_STEP_S = 1.0e-3
HOLDING_TORQUE_SHARE = 0.8      # holding the load may take at most this share of the limit
Progress = Callable[[float], None]


@dataclass(frozen=True)
class RunSpec:
    """Everything that defines one simulated run (every unit of the machine)."""

    cycle: str | Path | Profile = WORK        # a configured cycle's name, a CSV file, a Profile
    speed: int = 4                            # configured cycle's speed level 1..4
    payload_kg: float = 0.0
    oil_temp_c: float = 27.0
    cycles: int = 1
    effects: Sequence[str] | Mapping[str, UnitEffects] | None = None
    seed: int = 0
    step_s: float = DEFAULT_STEP_S
    sensors: SensorSettings = field(default_factory=SensorSettings)
    controller: PIDSettings = field(default_factory=PIDSettings)


@dataclass
class _Prepared:
    spec: RunSpec
    profile: Profile
    effects: dict[str, UnitEffects]
    rows: dict[str, RowSpec]
    decimation: int


def _check_number(name: str, value: float, lo: float, hi: float, unit: str) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise UserError(f"{name} must be a number, got {value!r}") from None
    if not (math.isfinite(value) and lo <= value <= hi):
        raise UserError(f"{name} = {value:g} {unit} is outside {lo:g}..{hi:g} {unit}")
    return value


def _prepare(cfg: Config, spec: RunSpec) -> _Prepared:
    """Validate a spec into its profile, effects and units (UserError on bad settings)."""
    if not isinstance(spec.cycles, (int, np.integer)) or isinstance(spec.cycles, bool) \
            or not 1 <= spec.cycles <= 10000:
        raise UserError(f"cycles must be a whole number 1..10000, got {spec.cycles!r}")
    t_lo, t_hi = cfg.tables.temperatures_c[0], cfg.tables.temperatures_c[1]
    _check_number("oil temperature", spec.oil_temp_c, t_lo, t_hi, "degC")
    _check_number("payload", spec.payload_kg, 0.0, 20000.0, "kg")
    _check_number("step", spec.step_s, 1e-5, 0.01, "s")
    rate = _check_number("sample rate", spec.sensors.rate_hz, 0.1, 1.0 / spec.step_s, "Hz")
    decimation = round(1.0 / (rate * spec.step_s))
    if abs(decimation * rate * spec.step_s - 1.0) > 1e-9:
        raise UserError(f"sample period 1/{rate:g} Hz must be a whole number of simulation "
                        f"steps of {spec.step_s:g} s")
    if isinstance(spec.cycle, Profile):
        profile = spec.cycle.repeated(spec.cycles)
    elif _is_named(spec):
        profile = work_cycle(cfg, str(spec.cycle), spec.speed, spec.cycles)
    else:
        profile = load_profile_csv(spec.cycle, cfg, spec.cycles)
    effects = (dict(spec.effects) if isinstance(spec.effects, Mapping)
               else build_effects(spec.effects, cfg.unit_names))
    rows = {}
    for a in cfg.unit_names:
        unit = DDHUnit.from_config(cfg, a)
        # the machine's configured structure, the run's effects on top
        row = effects[a].row(unit, spec.payload_kg, cfg.hydraulics,
                             Structure.from_config(cfg, a))
        force = unit.load_force_n(spec.payload_kg)
        try:
            speed = holding_speed(row.unit, force, spec.oil_temp_c).speed_rpm
        except ValueError:          # no speed holds it: the relief valve gives way first
            raise UserError(f"payload {spec.payload_kg:g} kg is too heavy for the {a}: its "
                            "relief valve cannot hold it") from None
        torque = abs(float(steady_state(row.unit, speed, force, spec.oil_temp_c).torque_nm))
        if torque > HOLDING_TORQUE_SHARE * unit.motor.torque_limit_nm:
            raise UserError(f"payload {spec.payload_kg:g} kg is too heavy for the {a}: holding "
                            f"it takes {torque:.1f} N*m of the motor's "
                            f"{unit.motor.torque_limit_nm:g} N*m")
        rows[a] = row
    return _Prepared(spec, profile, effects, rows, decimation)


def _group_key(p: _Prepared) -> tuple:
    return (p.spec.step_s, p.decimation, p.spec.controller)


def simulate_campaign(cfg: Config, specs: Sequence[RunSpec],
                      progress: Progress | None = None) -> list[dict[str, Run]]:
    """Simulate many runs in lockstep; one ``{unit: Run}`` per spec (config order)."""
    return [{a: run for a, (run, _) in r.items()}
            for r in simulate_with_truth(cfg, specs, progress)]


def simulate_with_truth(cfg: Config, specs: Sequence[RunSpec], progress: Progress | None = None
                        ) -> list[dict[str, tuple[Run, Truth]]]:
    """As :func:`simulate_campaign`, each run with the true signals behind it."""
    prepared = [_prepare(cfg, s) for s in specs]
    results: list[dict[str, tuple[Run, Truth]] | None] = [None] * len(specs)
    groups: dict[tuple, list[int]] = {}
    for i, p in enumerate(prepared):
        groups.setdefault(_group_key(p), []).append(i)
    total = sum(p.profile.duration_s for p in prepared) or 1.0
    done = 0.0
    for members in groups.values():
        weight = sum(prepared[i].profile.duration_s for i in members) / total

        def sub_progress(f: float, base: float = done, w: float = weight) -> None:
            if progress is not None:
                progress(base + w * f)

        runs = _simulate_group(cfg, [prepared[i] for i in members], sub_progress)
        for i, r in zip(members, runs):
            results[i] = r
        done += weight
    if progress is not None:
        progress(1.0)
    return results  # type: ignore[return-value]


def simulate(cfg: Config, spec: RunSpec, progress: Progress | None = None) -> dict[str, Run]:
    """One run: ``{unit: Run}``, e.g. ``{"boom": Run, "bucket": Run}``."""
    return simulate_campaign(cfg, [spec], progress)[0]


def _simulate_group(cfg: Config, runs: list[_Prepared],
                    progress: Progress) -> list[dict[str, tuple[Run, Truth]]]:
    spec0 = runs[0].spec
    h, dec = spec0.step_s, runs[0].decimation
    rate = spec0.sensors.rate_hz
    rows, units, payloads, t0s, drifts, profiles, acts = [], [], [], [], [], [], []
    for p in runs:
        for a in cfg.unit_names:
            rows.append(p.rows[a])
            units.append(p.rows[a].unit)
            payloads.append(p.spec.payload_kg)
            t0s.append(p.spec.oil_temp_c)
            drifts.append(p.spec.sensors.oil_temp_drift_c_per_s)
            profiles.append(p.profile)
            acts.append(a)
    size = len(rows)
    plant = Plant(rows, h)
    t0s, drifts = np.array(t0s), np.array(drifts)

    # start at rest: position at the setpoint, motor at the leakage (holding) speed
    x0, n0, pa0, pb0, tq0 = (np.zeros(size) for _ in range(5))
    for i, (u, prof, a, pl) in enumerate(zip(units, profiles, acts, payloads)):
        x0[i] = prof.evaluate(a, np.array([0.0]))[0][0] * 1e-3
        force = u.load_force_n(pl)
        hs = holding_speed(u, force, t0s[i]).speed_rpm
        st = steady_state(u, hs, force, t0s[i])
        n0[i], pa0[i], pb0[i], tq0[i] = hs, float(st.p_a_pa), float(st.p_b_pa), \
            float(st.torque_nm)
    plant.set_state(x0, n0, pa0 - plant.reservoir, pb0 - plant.reservoir)
    plant.torque = tq0.copy()
    pid = PositionPID(units, payloads, spec0.controller)
    pid.reset(tq0)

    samples = [int(math.floor(p.profile.duration_s * rate + 1e-9)) + 1 for p in runs]
    n_samples = max(samples)
    rec = {k: np.empty((n_samples, size)) for k in ("x", "v", "pa", "pb", "n", "tq")}

    def record(j: int) -> None:
        rec["x"][j], rec["v"][j] = plant.x, plant.v
        rec["pa"][j], rec["pb"][j] = plant.dp_a, plant.dp_b
        rec["n"][j], rec["tq"][j] = plant.n, plant.torque

    record(0)
    oil = units[0].oil
    chunk = max(1, int(round(2.0 * rate)))         # setpoints computed 2 s at a time
    step = plant.step
    update = pid.update
    for j0 in range(1, n_samples, chunk):
        j1 = min(j0 + chunk, n_samples)
        k0, k1 = (j0 - 1) * dec, (j1 - 1) * dec     # steps k0 .. k1-1 use setpoints at k*h
        t_steps = np.arange(k0, k1) * h
        x_sp, a_sp = np.empty((k1 - k0, size)), np.empty((k1 - k0, size))
        for i, (prof, a) in enumerate(zip(profiles, acts)):
            x, _, acc = prof.evaluate_all(a, t_steps)
            x_sp[:, i], a_sp[:, i] = x * 1e-3, acc * 1e-3
        for j in range(j0, j1):
            mu = oil.dynamic_viscosity_pa_s(t0s + drifts * ((j - 0.5) / rate))
            base = (j - 1) * dec - k0
            for s in range(base, base + dec):
                step(update(h, x_sp[s], plant.x, a_sp[s]), mu)
            record(j)
        progress(j1 / n_samples)

    if plant.unconverged_steps:
        import warnings
        warnings.warn(f"{plant.unconverged_steps} of {plant.steps} plant steps did not settle "
                      "their discrete states", RuntimeWarning, stacklevel=2)
    out = []
    for r, p in enumerate(runs):
        m = samples[r]
        t = np.arange(m) / rate
        per_unit = {}
        for ai, a in enumerate(cfg.unit_names):
            i = r * len(cfg.unit_names) + ai
            truth = Truth(time_s=t, x_m=rec["x"][:m, i], v_m_s=rec["v"][:m, i],
                          dp_a_pa=rec["pa"][:m, i], dp_b_pa=rec["pb"][:m, i],
                          speed_rpm=rec["n"][:m, i], torque_nm=rec["tq"][:m, i],
                          oil_temp_c=t0s[i] + drifts[i] * t, reservoir_pa=plant.reservoir[i])
            rng = np.random.default_rng(np.random.SeedSequence([p.spec.seed, ai]))
            run = measure(truth, cfg.unit(a), p.spec.sensors, rng, cfg.can.position_step_mm,
                          p.effects[a], comments=_comments(cfg, p, a),
                          source=f"simulated:{a}")
            per_unit[a] = (run, truth)
        out.append(per_unit)
    return out


def _is_named(spec: RunSpec) -> bool:
    return isinstance(spec.cycle, str)


def _comments(cfg: Config, p: _Prepared, actuator: str) -> list[str]:
    s = p.spec
    mine = p.effects[actuator].non_neutral()
    return [
        "ddh-vsensor simulated run (time-domain plant, ddh_vsensor.sim)",
        f"actuator: {actuator}",
        f"cycle: {p.profile.name}",
        f"cycles: {s.cycles}",
        f"speed: {s.speed}" if _is_named(s) else f"cycle_source: {p.profile.name}",
        f"duration_s: {p.profile.duration_s:.3f}",
        f"payload_kg: {s.payload_kg:g}",
        f"oil_temp_c: {s.oil_temp_c:g}",
        f"oil_temp_drift_c_per_s: {s.sensors.oil_temp_drift_c_per_s:g}",
        "effects: " + (", ".join(f"{k}={v:g}" for k, v in mine.items()) or "none"),
        f"effects_all: {describe(p.effects)}",
        f"seed: {s.seed}",
        f"step_s: {s.step_s:g}",
        f"rate_hz: {s.sensors.rate_hz:g}",
        f"position_noise_mm: {s.sensors.position_noise_mm:g}",
        f"controller: PID bandwidth {s.controller.bandwidth_rad_s:g} rad/s, derivative filter "
        f"{s.controller.derivative_filter_s:g} s, torque filter {s.controller.torque_filter_s:g} s",
        f"config: {cfg.source} (physics {cfg.physics_hash()})",
    ]


def write_run_dir(cfg: Config, runs: Mapping[str, Run], out_dir: str | Path,
                  blf: bool = True) -> list[Path]:
    """Write one ``<unit>.csv`` per unit and (``blf``) ``run.blf`` into ``out_dir``."""
    out = output_dir(out_dir)
    written = []
    for a, run in runs.items():
        path = out / f"{a}.csv"
        write_csv(path, run)
        written.append(path)
    if blf:
        from ddh_vsensor.io.log import write_blf
        path = out / "run.blf"
        write_blf(path, dict(runs), cfg)
        written.append(path)
    return written

