"""Setpoint profiles: the paper's work cycle at four speeds, and user profiles from CSV.

A profile gives, for each actuator, the position setpoint and its rate as functions of time.
The paper's cycle (lift the bucket = retract it; lift the boom; dump the bucket = extend it,
then lift it again; lower the boom; finally the bucket back to its digging position, so that
the cycle ends in its start state and repeats) is built from smooth point-to-point moves:
trapezoidal velocity with raised-cosine acceleration and deceleration, no jerk steps.

Positions are chosen so that every cycle crosses the middle reference switches (boom 155 mm,
bucket 425 mm), the boom's bottom end switch (0 mm, window 3 mm) is on at each cycle's start
and end (boom low setpoint 1.5 mm, clear of the end stop), and the boom's top setpoint
(297 mm) stays below the top end (311.15 mm) as in the paper ("not allowed to reach the upper
limits"). The four speed levels scale the travel velocities by 1/4 ... 4/4; at speed 4 the
motors peak near 5000-5500 rpm and the cycle lasts about 26 s (paper: about 25 s, motors at
5000-6000 rpm).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import Config
from ..errors import UserError

SPEED_LEVELS = (1, 2, 3, 4)
ACCEL_FRACTION = 0.25          # share of each move spent accelerating (and decelerating)


@dataclass(frozen=True)
class PaperCycleDesign:
    """Positions (mm), travel velocities at speed 4 (mm/s) and pauses (s) of the cycle."""

    boom_low_mm: float = 1.5
    boom_high_mm: float = 297.0
    bucket_dig_mm: float = 600.0
    bucket_lifted_mm: float = 200.0
    bucket_dumped_mm: float = 700.0
    boom_velocity_mm_s: float = 95.0
    bucket_velocity_mm_s: float = 195.0
    start_hold_s: float = 1.0
    pause_s: float = 0.4
    end_hold_s: float = 1.0


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
    """Setpoints of both actuators over one cycle, repeated ``cycles`` times."""

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


def _move_time(distance_mm: float, velocity_mm_s: float) -> float:
    return abs(distance_mm) / (velocity_mm_s * (1.0 - ACCEL_FRACTION))


def paper_cycle(speed: int, cycles: int = 1,
                design: PaperCycleDesign = PaperCycleDesign()) -> Profile:
    """The paper's work cycle at speed level 1..4 (4 the fastest), repeated ``cycles`` times."""
    if speed not in SPEED_LEVELS:
        raise UserError(f"speed must be one of 1, 2, 3, 4 (4 the fastest), got {speed}")
    f = speed / 4.0
    d = design
    knots: dict[str, list[tuple[float, float]]] = {
        "boom": [(0.0, d.boom_low_mm)], "bucket": [(0.0, d.bucket_dig_mm)]}
    t = d.start_hold_s

    def move(actuator: str, target: float) -> None:
        nonlocal t
        velocity = (d.boom_velocity_mm_s if actuator == "boom" else d.bucket_velocity_mm_s) * f
        start = knots[actuator][-1][1]
        knots[actuator].append((t, start))
        t += _move_time(target - start, velocity)
        knots[actuator].append((t, target))
        t += d.pause_s

    move("bucket", d.bucket_lifted_mm)      # lift the bucket (retract)
    move("boom", d.boom_high_mm)            # lift the boom
    move("bucket", d.bucket_dumped_mm)      # dump (extend) ...
    move("bucket", d.bucket_lifted_mm)      # ... and lift the bucket again
    move("boom", d.boom_low_mm)             # lower the boom
    move("bucket", d.bucket_dig_mm)         # bucket back to digging: the start state
    t += d.end_hold_s - d.pause_s
    trajectories = {}
    for name, pts in knots.items():
        pts.append((t, pts[-1][1]))
        tk = np.array([p[0] for p in pts])
        xk = np.array([p[1] for p in pts])
        trajectories[name] = Trajectory(tk, xk, smooth=True)
    return Profile(f"paper speed {speed}", trajectories, t).repeated(cycles)


def load_profile_csv(path: str | Path, cfg: Config, cycles: int = 1) -> Profile:
    """A user profile: CSV with columns time_s, boom_mm, bucket_mm (``#`` lines are comments).

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


@dataclass(frozen=True)
class DigDumpDesign:
    """A fast digging cycle: the bucket curled into its retracted stop and dumped into its
    extended stop, the boom lowered onto its bottom stop to dig, as an operator does."""

    boom_dig_mm: float = -END_STOP_OVERTRAVEL_MM
    boom_carry_mm: float = 180.0
    bucket_start_mm: float = 600.0
    bucket_curled_mm: float = -END_STOP_OVERTRAVEL_MM
    bucket_dumped_extra_mm: float = END_STOP_OVERTRAVEL_MM
    boom_velocity_mm_s: float = 95.0
    bucket_velocity_mm_s: float = 195.0
    stop_hold_s: float = 0.6
    pause_s: float = 0.2


def dig_dump_cycle(cfg: Config, speed: int = 4, cycles: int = 1,
                   design: DigDumpDesign = DigDumpDesign()) -> Profile:
    """Dig (boom down onto its stop, bucket curled into its stop), carry, dump (bucket into
    its extended stop), curl again, back to the start; ``speed`` 1..4 as the paper's cycle."""
    if speed not in SPEED_LEVELS:
        raise UserError(f"speed must be one of 1, 2, 3, 4 (4 the fastest), got {speed}")
    f, d = speed / 4.0, design
    boom_start = 0.5 * d.boom_carry_mm
    dumped = cfg.unit("bucket").stroke_mm + d.bucket_dumped_extra_mm
    knots: dict[str, list[tuple[float, float]]] = {
        "boom": [(0.0, boom_start)], "bucket": [(0.0, d.bucket_start_mm)]}
    t = 0.5

    def move(actuator: str, target: float, hold_s: float, together: bool = False) -> None:
        nonlocal t
        velocity = (d.boom_velocity_mm_s if actuator == "boom" else d.bucket_velocity_mm_s) * f
        start = knots[actuator][-1][1]
        knots[actuator].append((t, start))
        end = t + _move_time(target - start, velocity)
        knots[actuator].append((end, target))
        if not together:
            t = end + hold_s

    move("boom", d.boom_dig_mm, 0.0, together=True)            # boom down onto its stop ...
    move("bucket", d.bucket_start_mm - 100.0, d.pause_s)       # ... while the bucket tilts
    move("bucket", d.bucket_curled_mm, d.stop_hold_s)          # curl: fill, into the stop
    move("boom", d.boom_carry_mm, d.pause_s)                   # lift and carry
    move("bucket", dumped, d.stop_hold_s)                      # dump into the extended stop
    move("bucket", d.bucket_curled_mm, d.stop_hold_s)          # shake out: curl back in
    move("bucket", dumped, d.stop_hold_s)                      # ... and dump again
    move("boom", boom_start, 0.0, together=True)               # back to the start state
    move("bucket", d.bucket_start_mm, d.pause_s)
    t = max(t, knots["boom"][-1][0] + d.pause_s)
    trajectories = {}
    for name, pts in knots.items():
        pts.append((t, pts[-1][1]))
        trajectories[name] = Trajectory(np.array([p[0] for p in pts]),
                                        np.array([p[1] for p in pts]), smooth=True)
    return Profile(f"dig-dump speed {speed}", trajectories, t).repeated(cycles)


def random_cycle(cfg: Config, seed: int, duration_s: float = 60.0,
                 end_stop_share: float = 0.25) -> Profile:
    """Random work: partial strokes between random positions at random speeds, short and
    long (loaded) holds, and a share of the moves pressed into an end stop. Both units move
    independently, so their moves overlap."""
    rng = np.random.default_rng(seed)
    v_top = {"boom": PaperCycleDesign.boom_velocity_mm_s,
             "bucket": PaperCycleDesign.bucket_velocity_mm_s}
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
            move = _move_time(target - x, rng.uniform(0.3, 1.0) * v_top[actuator])
            if t + hold + move + 1.0 > duration_s:
                break
            t += hold
            knots.append((t, x))
            t += move
            knots.append((t, target))
            x = target
        if x < 0.0 or x > stroke:           # leave the stop before the end
            back = float(np.clip(x, lo, hi))
            t_back = min(t + 0.3, duration_s - 0.5 - _move_time(back - x, v_top[actuator]))
            knots += [(max(t_back, t), x),
                      (max(t_back, t) + _move_time(back - x, v_top[actuator]), back)]
        knots.append((max(duration_s, knots[-1][0]), knots[-1][1]))
        trajectories[actuator] = Trajectory(np.array([k[0] for k in knots]),
                                            np.array([k[1] for k in knots]), smooth=True)
    length = max(tr.time_s[-1] for tr in trajectories.values())
    return Profile(f"random {seed}", trajectories, length)
