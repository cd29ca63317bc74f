"""Setpoint profiles: the machine's work cycles from its configuration, random work, and
user profiles from CSV.

A profile gives, for each unit, the position setpoint and its rate as functions of time. A
configured cycle (``work_cycle.cycles`` of the machine's configuration; for the reference
loader the paper's: lift the bucket, lift the boom, dump, lower, back to digging) is a list
of steps, each a smooth point-to-point move of one unit: trapezoidal velocity with
raised-cosine acceleration and deceleration, no jerk steps, then a hold; a step may overlap
the next. The four speed levels scale the units' travel speeds by 1/4 ... 4/4 (the
reference loader at speed 4: motors near 5000-5500 rpm, about 26 s, paper: about 25 s).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ddh_vsensor.config import Config, CycleConfig, WorkUnitConfig
from ddh_vsensor.errors import UserError

SPEED_LEVELS = (1, 2, 3, 4)
ACCEL_FRACTION = 0.25          # share of each move spent accelerating (and decelerating)
WORK = "work"                  # the machine's typical cycle: the first configured one
RANDOM = "random"              # random work (:func:`random_cycle`), not a configured cycle
# Without a work_cycle section: speeds as shares of the speed-limit speed (the reference
# loader's configured ones are 0.84 / 0.71 of it), random targets within 3..97 % of a stroke.
DEFAULT_TRAVEL_SHARE, DEFAULT_WORK_SHARE, DEFAULT_RANGE_SHARE = 0.8, 0.7, 0.03


@dataclass(frozen=True)
class Trajectory:
    """One actuator's setpoint: knots (s, mm) joined by smooth moves or straight lines."""

    time_s: np.ndarray
    position_mm: np.ndarray
    smooth: bool = True

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Setpoint (mm) and its rate (mm/s) at times ``t`` (held outside the knots)."""
        x, v, _ = self.evaluate_all(t)
        return x, v

    def evaluate_all(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Setpoint (mm), rate (mm/s) and acceleration (mm/s^2; 0 for straight lines)."""
        t = np.asarray(t, dtype=float)
        tk, xk = self.time_s, self.position_mm
        if len(tk) == 1:
            return np.full_like(t, xk[0]), np.zeros_like(t), np.zeros_like(t)
        i = np.clip(np.searchsorted(tk, t, side="right") - 1, 0, len(tk) - 2)
        dt = tk[i + 1] - tk[i]
        u = np.clip((t - tk[i]) / dt, 0.0, 1.0)
        inside = (t > tk[0]) & (t < tk[-1])
        if self.smooth:
            s, ds, dds = _smooth_step(u)
        else:
            s, ds, dds = u, np.ones_like(u), np.zeros_like(u)
        dx = xk[i + 1] - xk[i]
        return (xk[i] + dx * s, np.where(inside, dx * ds / dt, 0.0),
                np.where(inside, dx * dds / (dt * dt), 0.0))


def _smooth_step(u: np.ndarray, a: float | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raised-cosine trapezoid: normalised position 0..1 and its first two derivatives in u."""
    a = ACCEL_FRACTION if a is None else a
    area = 1.0 - a
    rise, fall = u < a, u > 1.0 - a
    w = np.where(rise, u, np.where(fall, 1.0 - u, a))       # distance from the nearer end

    def ramp(z: np.ndarray) -> np.ndarray:       # integral of (1 - cos(pi z / a)) / 2
        return 0.5 * z - a / (2.0 * math.pi) * np.sin(math.pi * z / a)

    s = np.where(rise, ramp(u), np.where(fall, area - ramp(1.0 - u), 0.5 * a + (u - a)))
    ds = np.where(rise | fall, 0.5 * (1.0 - np.cos(math.pi * w / a)), 1.0)
    dds = np.where(rise, 1.0, np.where(fall, -1.0, 0.0)) * (
        0.5 * math.pi / a * np.sin(math.pi * w / a))
    return s / area, ds / area, dds / area


@dataclass(frozen=True)
class Profile:
    """Setpoints of every unit over one cycle, repeated ``cycles`` times."""

    name: str
    trajectories: dict[str, Trajectory]
    cycle_s: float
    cycles: int = 1

    @property
    def duration_s(self) -> float:
        return self.cycle_s * self.cycles

    def evaluate(self, actuator: str, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Setpoint (mm) and rate (mm/s) of one actuator at absolute times ``t``."""
        x, v, _ = self.evaluate_all(actuator, t)
        return x, v

    def evaluate_all(self, actuator: str, t: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Setpoint (mm), rate (mm/s), acceleration (mm/s^2) at absolute times ``t``."""
        t = np.asarray(t, dtype=float)
        local = t - self.cycle_s * np.clip(np.floor(t / self.cycle_s), 0, self.cycles - 1)
        return self.trajectories[actuator].evaluate_all(local)

    def repeated(self, cycles: int) -> "Profile":
        if cycles < 1:
            raise UserError(f"cycles must be at least 1, got {cycles}")
        if cycles > 1:
            for name, tr in self.trajectories.items():
                if abs(tr.position_mm[0] - tr.position_mm[-1]) > 1e-9:
                    raise UserError(f"profile '{self.name}' does not end where it starts "
                                    f"for {name} ({tr.position_mm[0]:g} -> "
                                    f"{tr.position_mm[-1]:g} mm): cannot repeat it")
        return Profile(self.name, self.trajectories, self.cycle_s, cycles)


def sequence(name: str, profiles: list[Profile]) -> Profile:
    """The profiles one after the other (each repeated as it says); each must start where
    the one before ended, for every unit, and all be smooth."""
    knots: dict[str, list[tuple[float, float]]] = {}
    t0 = 0.0
    for profile in profiles:
        for _ in range(profile.cycles):
            for unit, tr in profile.trajectories.items():
                if not tr.smooth:
                    raise ValueError(f"profile '{profile.name}' is not smooth: cannot join it")
                pts = knots.setdefault(unit, [])
                if pts and abs(pts[-1][1] - tr.position_mm[0]) > 1e-9:
                    raise ValueError(f"profile '{profile.name}' starts the {unit} at "
                                     f"{tr.position_mm[0]:g} mm, not at {pts[-1][1]:g}")
                pts += [(t0 + t, x) for t, x in zip(tr.time_s, tr.position_mm)
                        if not pts or t0 + t > pts[-1][0] + 1e-9]
                if t0 + profile.cycle_s > pts[-1][0] + 1e-9:
                    pts.append((t0 + profile.cycle_s, float(tr.position_mm[-1])))
            t0 += profile.cycle_s
    return Profile(name, {u: Trajectory(np.array([p[0] for p in pts]),
                                        np.array([p[1] for p in pts]))
                          for u, pts in knots.items()}, t0)


def move_time(distance_mm: float, velocity_mm_s: float) -> float:
    """A smooth move's duration (s) whose top speed is ``velocity_mm_s``."""
    return abs(distance_mm) / (velocity_mm_s * (1.0 - ACCEL_FRACTION))


def cycle_names(cfg: Config) -> tuple[str, ...]:
    """The machine's configured cycles, its typical one first."""
    return tuple(cfg.work_cycle.cycles) if cfg.work_cycle is not None else ()


def require_cycle(cfg: Config, name: str) -> str:
    """The configured cycle's name (``work``: the first), else an error listing them."""
    names = cycle_names(cfg)
    if name == WORK and names:
        return names[0]
    if name not in names:
        known = ", ".join((WORK,) + names) if names else "none: the configuration has no " \
            "work_cycle section"
        raise UserError(f"{cfg.source}: unknown work cycle {name!r} (this machine's cycles: "
                        f"{known})")
    return name


def work_unit(cfg: Config, unit: str) -> WorkUnitConfig:
    """A unit's work speeds: configured, or shares of its speed-limit speed."""
    if cfg.work_cycle is not None:
        return cfg.work_cycle.units[cfg.require_unit(unit)]
    top = cfg.max_speed_mm_s(unit) / cfg.faults.max_speed_factor
    stroke = cfg.unit(unit).stroke_mm
    return WorkUnitConfig(travel_speed_mm_s=DEFAULT_TRAVEL_SHARE * top,
                          work_speed_mm_s=DEFAULT_WORK_SHARE * top,
                          work_range_mm=(DEFAULT_RANGE_SHARE * stroke,
                                         (1.0 - DEFAULT_RANGE_SHARE) * stroke))


def work_cycle(cfg: Config, name: str = WORK, speed: int = 4, cycles: int = 1) -> Profile:
    """A configured cycle at speed level 1..4 (4 the fastest), repeated ``cycles`` times."""
    if speed not in SPEED_LEVELS:
        raise UserError(f"speed must be one of 1, 2, 3, 4 (4 the fastest), got {speed}")
    name = require_cycle(cfg, name)
    design: CycleConfig = cfg.work_cycle.cycles[name]     # type: ignore[union-attr]
    f = speed / 4.0
    knots = {u: [(0.0, design.start_mm[u])] for u in cfg.unit_names}
    t, hold = design.start_hold_s, design.pause_s
    for step in design.steps:
        velocity = work_unit(cfg, step.unit).travel_speed_mm_s * step.speed_share * f
        last_t, start = knots[step.unit][-1]
        begin = max(t, last_t)          # a unit's move waits for its previous (overlapping) one
        end = begin + move_time(step.to_mm - start, velocity)
        knots[step.unit] += [(begin, start), (end, step.to_mm)]
        if not step.with_next:
            hold = design.pause_s if step.hold_s is None else step.hold_s
            t = end + hold
    t += design.end_hold_s - hold
    latest = max(pts[-1][0] for pts in knots.values()) + design.end_hold_s
    if latest > t + 1e-9:               # an overlapping move ends after the last step
        t = latest
    trajectories = {}
    for unit, pts in knots.items():
        pts.append((t, pts[-1][1]))
        pts = [p for k, p in enumerate(pts) if k == 0 or p != pts[k - 1]]  # no 0 s segments
        trajectories[unit] = Trajectory(np.array([p[0] for p in pts]),
                                        np.array([p[1] for p in pts]), smooth=True)
    return Profile(f"{name} speed {speed}", trajectories, t).repeated(cycles)


def load_profile_csv(path: str | Path, cfg: Config, cycles: int = 1) -> Profile:
    """A user profile: CSV with columns time_s and one ``<unit>_mm`` per unit, e.g. time_s,
    boom_mm, bucket_mm for the reference loader (``#`` lines are comments).

    Setpoints are joined by straight lines (sample the file finely for smooth motion).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise UserError(f"{path}: cannot read the profile: {exc.strerror or exc}") from None
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    reader = csv.DictReader(lines)
    need = ("time_s",) + tuple(f"{a}_mm" for a in cfg.unit_names)
    missing = [c for c in need if c not in (reader.fieldnames or [])]
    if missing:
        raise UserError(f"{path}: profile needs columns {', '.join(need)}; "
                        f"missing {', '.join(missing)}")
    cols: dict[str, list[float]] = {c: [] for c in need}
    for row_no, row in enumerate(reader, start=2):
        for c in need:
            try:
                value = float(row[c])
            except (TypeError, ValueError):
                raise UserError(f"{path}: row {row_no}: {c} = {row[c]!r} is not a number") \
                    from None
            if not math.isfinite(value):
                raise UserError(f"{path}: row {row_no}: {c} is not finite")
            cols[c].append(value)
    t = np.array(cols["time_s"])
    if len(t) < 2:
        raise UserError(f"{path}: a profile needs at least two rows")
    if np.any(np.diff(t) <= 0.0):
        raise UserError(f"{path}: time_s must increase strictly from row to row")
    if t[0] != 0.0:
        raise UserError(f"{path}: time_s must start at 0")
    trajectories = {}
    for a in cfg.unit_names:
        x = np.array(cols[f"{a}_mm"])
        stroke = cfg.unit(a).stroke_mm
        if np.any(x < 0.0) or np.any(x > stroke):
            raise UserError(f"{path}: {a}_mm must stay within the stroke 0..{stroke:g} mm")
        trajectories[a] = Trajectory(t, x, smooth=False)
    return Profile(path.name, trajectories, float(t[-1])).repeated(cycles)


END_STOP_OVERTRAVEL_MM = 20.0   # setpoint beyond a stroke end: the controller presses the rod
                                # into its stop (pressure to the relief, no motion)


def dig_dump_cycle(cfg: Config, speed: int = 4, cycles: int = 1) -> Profile:
    """The configured ``dig-dump`` cycle (the reference loader's: units pressed into their end
    stops, as an operator digs)."""
    return work_cycle(cfg, "dig-dump", speed, cycles)


def random_cycle(cfg: Config, seed: int, duration_s: float = 60.0,
                 end_stop_share: float = 0.25) -> Profile:
    """Random work: partial strokes between random positions at random speeds, short and
    long (loaded) holds, and a share of the moves pressed into an end stop, at 30-100 % of
    each unit's travel speed. The units move independently, so their moves overlap."""
    rng = np.random.default_rng(seed)
    v_top = {a: work_unit(cfg, a).travel_speed_mm_s for a in cfg.unit_names}
    trajectories = {}
    for actuator in cfg.unit_names:
        stroke = cfg.unit(actuator).stroke_mm
        lo, hi = 0.03 * stroke, 0.97 * stroke
        t, x = 0.0, rng.uniform(lo, hi)
        knots = [(0.0, x)]
        while True:
            hold = rng.uniform(0.2, 1.5) if rng.random() < 0.8 else rng.uniform(3.0, 10.0)
            if rng.random() < end_stop_share:
                target = (-END_STOP_OVERTRAVEL_MM if rng.random() < 0.5
                          else stroke + END_STOP_OVERTRAVEL_MM)
            else:
                target = rng.uniform(lo, hi)
            move = move_time(target - x, rng.uniform(0.3, 1.0) * v_top[actuator])
            if t + hold + move + 1.0 > duration_s:
                break
            t += hold
            knots.append((t, x))
            t += move
            knots.append((t, target))
            x = target
        if x < 0.0 or x > stroke:           # leave the stop before the end
            back = float(np.clip(x, lo, hi))
            t_back = min(t + 0.3, duration_s - 0.5 - move_time(back - x, v_top[actuator]))
            knots += [(max(t_back, t), x),
                      (max(t_back, t) + move_time(back - x, v_top[actuator]), back)]
        knots.append((max(duration_s, knots[-1][0]), knots[-1][1]))
        trajectories[actuator] = Trajectory(np.array([k[0] for k in knots]),
                                            np.array([k[1] for k in knots]), smooth=True)
    length = max(tr.time_s[-1] for tr in trajectories.values())
    return Profile(f"random {seed}", trajectories, length)
