"""Hidden-effect trials: draw an effect of the catalogue (or none) and a magnitude, simulate a
campaign of the machine's work cycle with it, and hand the runs over without their comments.

Two kinds of work cycle: the machine's configured one (``cycle="paper"``: for the reference
loader the paper's, at two of its speeds 2..4) and random point-to-point cycles (smooth moves
of random length and speed between random holds, every unit independently: harder on the
model, with sharp accelerations and braking). Used by the tests and the benchmark; the draws
are seeded so a failure can be replayed.
Magnitudes are drawn from ranges where the effect is large against the model's own error
(about 1 mm without any effect): each range's low end moves the estimate by a few
millimetres in a cycle.

The simulator writes the effect into each CSV's ``#`` comment lines; :func:`strip_comments`
removes them, and nothing in the diagnosis reads them anyway.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ddh_vsensor.config import Config
from ddh_vsensor.measured import Run
from ddh_vsensor.io.csv import write_csv

EFFECT_NAMES = ("none", "pump_leakage", "compressibility", "belt_slip", "displacement",
                "time_offset", "oil_temp_offset", "torque_gain", "torque_offset", "position_scale")
# Deviations of the simulator that the diagnosis' catalogue does not contain (open set).
OUTSIDE_NAMES = ("valve_leak", "pump_fill", "bore_leak")
PAYLOADS_KG = (0.0, 1040.0)
# Oil temperatures: around the paper's 25-30 degC, and warm. Below about 20 degC the model's
# own error (transients of the chamber pressures the steady-state tables cannot follow) grows
# to ~3 mm on the bucket, which would hide the smaller effects (see diagnosis/README.md).
COOL_OIL_C = (22.0, 32.0)
WARM_OIL_C = (40.0, 60.0)


@dataclass(frozen=True)
class Trial:
    """One drawn campaign."""

    seed: int
    effect: str                     # catalogue name (the first, for pairs) or "none"
    value: float | None             # the effect's parameter (None for none)
    speeds: tuple[int, ...]         # paper cycle speeds (random cycles: one per "speed")
    oil_temps_c: tuple[float, float]
    cycle: str = "paper"            # "paper" or "random"
    more: tuple[tuple[str, float], ...] = ()    # further effects (pairs)

    @property
    def effects(self) -> dict[str, float]:
        out = {} if self.value is None else {self.effect: self.value}
        out.update(dict(self.more))
        return out

    @property
    def effect_arg(self) -> list[str]:
        return [f"{k}={v:.6g}" for k, v in self.effects.items()]

    def describe(self) -> str:
        what = ", ".join(f"{k}={v:.4g}" for k, v in self.effects.items()) or "none"
        cycles = (f"paper cycle at speeds {', '.join(map(str, self.speeds))}"
                  if self.cycle == "paper" else f"{len(self.speeds)} random cycles")
        return (f"seed {self.seed}: {what}; {cycles}; oil "
                f"{self.oil_temps_c[0]:.1f} and {self.oil_temps_c[1]:.1f} degC; payloads 0 "
                "and 1040 kg")


def draw_magnitude(effect: str, rng: np.random.Generator) -> float | None:
    """A magnitude of ``effect`` well above the model's own error (see the module doc)."""
    sign = 1.0 if rng.random() < 0.5 else -1.0
    if effect == "none":
        return None
    if effect == "pump_leakage":          # worn (x1.6..x3.5) or tighter (x0.3..x0.6)
        return float(math.exp(rng.uniform(math.log(1.6), math.log(3.5))) if sign > 0
                     else rng.uniform(0.3, 0.6))
    if effect == "displacement":
        return float(1.0 + sign * rng.uniform(0.015, 0.06))
    if effect == "belt_slip":
        return float(rng.uniform(4.0, 15.0))
    if effect == "time_offset":
        return float(sign * rng.uniform(0.03, 0.3))
    if effect == "compressibility":
        return float(math.exp(rng.uniform(math.log(0.02), math.log(0.08))))
    if effect == "oil_temp_offset":
        return float(sign * rng.uniform(6.0, 15.0))
    if effect == "torque_gain":
        return float(1.0 + sign * rng.uniform(0.06, 0.15))
    if effect == "torque_offset":
        return float(sign * rng.uniform(3.0, 8.0))
    if effect == "position_scale":
        return float(1.0 + sign * rng.uniform(0.015, 0.05))
    if effect == "valve_leak":
        return float(rng.uniform(2.0, 8.0))
    if effect == "pump_fill":
        return float(rng.uniform(2.0, 8.0))
    if effect == "bore_leak":
        return float(rng.uniform(2.0, 8.0))
    raise ValueError(f"unknown effect {effect!r}")


def draw_trial(seed: int, effect: str | None = None, speeds: tuple[int, ...] | None = None,
               cycle: str = "paper", pair: bool = False) -> Trial:
    """A trial from ``seed``: the effect (drawn unless given; with ``pair`` a second one,
    another catalogue cause), its magnitude, two speeds of the paper cycle (drawn from 2..4
    unless given) and two oil temperatures."""
    rng = np.random.default_rng(seed)
    causes = EFFECT_NAMES[1:]
    if effect is None:
        effect = (causes if pair else EFFECT_NAMES)[int(rng.integers(len(causes) if pair
                                                                     else len(EFFECT_NAMES)))]
    value = draw_magnitude(effect, rng)
    more: tuple[tuple[str, float], ...] = ()
    if pair:
        others = [c for c in causes if c != effect]
        second = others[int(rng.integers(len(others)))]
        more = ((second, draw_magnitude(second, rng)),)
    if speeds is None:
        speeds = tuple(sorted(int(s) for s in rng.choice([2, 3, 4], size=2, replace=False)))
    temps = (round(float(rng.uniform(*COOL_OIL_C)), 1), round(float(rng.uniform(*WARM_OIL_C)), 1))
    return Trial(seed, effect, value, speeds, temps, cycle, more)


def random_cycle(cfg: Config, rng: np.random.Generator, duration_s: float = 40.0):
    """Smooth point-to-point moves of each unit between random holds (exponential, mean 2 s)
    to random targets within its configured ``work_range_mm``, at 30-100 % of its
    ``work_speed_mm_s`` (reference loader: boom 80 mm/s, bucket 160 mm/s, about what the
    motors reach near 5000 rpm)."""
    from ddh_vsensor.sim.cycles import Profile, Trajectory, work_unit
    knots = {}
    for a in cfg.unit_names:
        work = work_unit(cfg, a)
        (lo, hi), top = work.work_range_mm, work.work_speed_mm_s
        t, x = [0.0], [float(rng.uniform(lo, hi))]
        while t[-1] < duration_s - 3.0:
            t.append(t[-1] + float(rng.exponential(2.0)))
            x.append(x[-1])
            target = float(rng.uniform(lo, hi))
            speed = float(rng.uniform(0.3, 1.0)) * top
            t.append(t[-1] + abs(target - x[-1]) / (0.75 * speed) + 0.2)
            x.append(target)
        knots[a] = (t, x)
    end = max(max(t[-1] for t, _ in knots.values()) + 1.0, duration_s)
    return Profile("random point-to-point", {
        a: Trajectory(np.array(t + [end]), np.array(x + [x[-1]]), smooth=True)
        for a, (t, x) in knots.items()}, end)


def simulate_trial(cfg: Config, trial: Trial) -> list[dict[str, Run]]:
    """The campaign: every speed x payload x oil temperature, one run each (every unit)."""
    from ddh_vsensor.sim.cycles import WORK
    from ddh_vsensor.sim.run import RunSpec, simulate_campaign
    rng = np.random.default_rng([trial.seed, 1])
    cycles = {s: WORK if trial.cycle == "paper" else random_cycle(cfg, rng)
              for s in trial.speeds}
    specs = [RunSpec(cycle=cycles[s], speed=s, payload_kg=p, oil_temp_c=t,
                     effects=trial.effect_arg, seed=trial.seed * 1000 + i)
             for i, (s, p, t) in enumerate((s, p, t) for s in trial.speeds for p in PAYLOADS_KG
                                           for t in trial.oil_temps_c)]
    return simulate_campaign(cfg, specs)


def strip_comments(path: str | Path) -> None:
    """Remove the ``#`` comment lines of a CSV (where the simulator names the effect)."""
    path = Path(path)
    lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
    path.write_text("".join(ln for ln in lines if not ln.startswith("#")), encoding="utf-8")


def write_trial(runs: list[dict[str, Run]], out_dir: str | Path) -> dict[str, list[Path]]:
    """Write each run's CSV per unit (comments stripped): unit -> paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, list[Path]] = {}
    for i, per_unit in enumerate(runs):
        for a, run in per_unit.items():
            path = out / f"run{i:02d}_{a}.csv"
            write_csv(path, run)
            strip_comments(path)
            paths.setdefault(a, []).append(path)
    return paths
