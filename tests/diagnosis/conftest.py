"""Hidden-effect campaigns for the diagnosis tests, simulated once per session and shared.

Three campaigns (the paper cycle, payloads 0 and 1040 kg, two oil temperatures, 8 runs), each
unit with its own hidden effects, drawn from the seed:

- ``sensor``: the boom has none; the bucket one measurement-chain cause (torque gain or
  offset, oil temperature offset, position sensor scale);
- ``pair``: both units two different catalogue causes at once;
- ``open``: the boom a deviation the catalogue does not have (a relief valve that seeps
  above 40 bar); the bucket one catalogue cause (any).

``DDH_DIAGNOSIS_SEED`` (an integer) shifts every draw, so another run of the suite tests
other magnitudes and conditions; each campaign prints what it hides.
"""

from __future__ import annotations

import datetime as dt
import json
import os
from pathlib import Path

import numpy as np
import pytest

from ddh_vsensor.cli.main import main
from ddh_vsensor.diagnosis.trials import (EFFECT_NAMES, OUTSIDE_NAMES, Trial, draw_magnitude,
                                          draw_trial, simulate_trial, write_trial)

BASE_SEED = int(os.environ.get("DDH_DIAGNOSIS_SEED", "20260"))
SENSOR_CAUSES = ("torque_gain", "torque_offset", "oil_temp_offset", "position_scale")
CAMPAIGNS = ("sensor", "pair", "open")


def campaign_trial(kind: str) -> Trial:
    """The drawn campaign ``kind`` (see the module doc)."""
    seed = BASE_SEED + 101 * CAMPAIGNS.index(kind)
    rng = np.random.default_rng([seed, 7])
    base = draw_trial(seed, "none")
    if kind == "pair":
        return draw_trial(seed, pair=True)
    if kind == "sensor":
        cause = SENSOR_CAUSES[int(rng.integers(len(SENSOR_CAUSES)))]
        more = ((f"bucket.{cause}", draw_magnitude(cause, rng)),)
    else:
        cause = EFFECT_NAMES[1 + int(rng.integers(len(EFFECT_NAMES) - 1))]
        outside = OUTSIDE_NAMES[int(rng.integers(len(OUTSIDE_NAMES)))]
        more = ((f"boom.{outside}", draw_magnitude(outside, rng)),
                (f"bucket.{cause}", draw_magnitude(cause, rng)))
    return Trial(seed, "none", None, base.speeds, base.oil_temps_c, "paper", more)


def hidden(trial: Trial, actuator: str) -> dict[str, float]:
    """What the trial hides in one unit: effect name -> value."""
    out = {}
    for key, value in trial.effects.items():
        unit, _, name = key.rpartition(".")
        if unit in ("", actuator):
            out[name] = value
    return out


class Campaigns:
    """Simulates each campaign once per session; keeps its CSV files and analyses."""

    def __init__(self, cfg, root: Path) -> None:
        self.cfg, self.root = cfg, root
        self.cache: dict[str, tuple[Trial, dict[str, list[Path]]]] = {}
        self.reports: dict[tuple, dict] = {}

    def get(self, kind: str) -> tuple[Trial, dict[str, list[Path]]]:
        if kind not in self.cache:
            trial = campaign_trial(kind)
            print(f"\nhidden-effect campaign {kind}: {trial.describe()} "
                  f"(DDH_DIAGNOSIS_SEED={BASE_SEED})")
            paths = write_trial(simulate_trial(self.cfg, trial), self.root / kind)
            self.cache[kind] = (trial, paths)
        return self.cache[kind]

    def analyze(self, kind: str, actuator: str, *extra: str) -> dict:
        """report.json of ``analyze`` on the campaign's runs of one actuator (cached)."""
        key = (kind, actuator, extra)
        if key not in self.reports:
            _, paths = self.get(kind)
            out = self.root / f"report-{kind}-{actuator}-{'-'.join(extra)}"
            assert main(["analyze", *map(str, paths[actuator]), "--actuator", actuator,
                         "--report", str(out), *extra]) == 0
            self.reports[key] = json.loads((out / "report.json").read_text())
        return self.reports[key]


@pytest.fixture(scope="session")
def campaigns(cfg, tmp_path_factory) -> Campaigns:
    return Campaigns(cfg, tmp_path_factory.mktemp("campaigns"))


# two minutes of a fleet machine's work, two hours apart (times on the wall clock)
FLEET_DAY = dt.datetime(2026, 3, 2, tzinfo=dt.timezone.utc).timestamp()
FLEET_SESSIONS_H = (7.0, 9.5)


@pytest.fixture(scope="session")
def fleet_sessions(cfg) -> list[dict]:
    from ddh_vsensor.sim.fleet import day_spec, plan_fleet
    from ddh_vsensor.sim.run import simulate_campaign
    plan = plan_fleet(cfg, 1, 3, seed=5, log_s=60.0)
    runs = simulate_campaign(cfg, [day_spec(cfg, plan, plan.machines[0], d) for d in (0, 1)])
    for per_unit, hours in zip(runs, FLEET_SESSIONS_H):
        for run in per_unit.values():
            run.shift_time(FLEET_DAY + 3600.0 * hours)
    return runs
