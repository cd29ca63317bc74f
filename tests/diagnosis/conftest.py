"""Hidden-effect campaigns for the diagnosis tests, simulated once per run and shared.

Three campaigns (the paper cycle, payloads 0 and 1040 kg, two oil temperatures, 8 runs), each
unit with its own hidden effects, drawn from the seed:

- ``sensor``: the boom has none; the bucket one measurement-chain cause (torque gain or
  offset, oil temperature offset, position sensor scale);
- ``pair``: both units two different catalogue causes at once;
- ``open``: the boom a deviation the catalogue does not have (a relief valve that seeps
  above 40 bar); the bucket one catalogue cause (any).

``DDH_DIAGNOSIS_SEED`` (an integer) shifts every draw, so another run of the suite tests
other magnitudes and conditions; each campaign prints what it hides.

The campaigns' CSV files and their analyses are written once per run of the suite: under
pytest-xdist into a directory every worker of the run shares (:func:`built_once`), so the
several test files that analyse the same campaign do not each simulate and analyse it again.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

from ddh_vsensor.cli.main import main
from ddh_vsensor.config import Config
from ddh_vsensor.diagnosis.trials import (EFFECT_NAMES, OUTSIDE_NAMES, Trial, draw_magnitude,
                                          draw_trial, simulate_trial, write_trial)
from ddh_vsensor.measured import Run

from ..conftest import built_once, shared_root

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


def simulate_trials(cfg: Config, trials: Sequence[Trial]) -> list[list[dict[str, Run]]]:
    """:func:`simulate_trial` of each trial, every run of them in one lockstep batch of the
    simulator: its rows are independent, so each run is bit for bit the one
    ``simulate_trial`` gives (the specs are the ones it builds), at a fraction of the cost
    of simulating the campaigns one after the other."""
    import ddh_vsensor.sim.run as sim_run
    simulate_campaign = sim_run.simulate_campaign
    specs: list[list] = []

    def collect(c: Config, s: Sequence, progress=None) -> list:
        assert c is cfg
        specs.append(list(s))
        return specs[-1]

    sim_run.simulate_campaign = collect         # simulate_trial imports it when called
    try:
        handed = [simulate_trial(cfg, t) for t in trials]
    finally:
        sim_run.simulate_campaign = simulate_campaign
    assert len(specs) == len(trials) and all(h is s for h, s in zip(handed, specs)), \
        "simulate_trial no longer hands over simulate_campaign's runs as they are"
    runs = iter(simulate_campaign(cfg, [spec for s in specs for spec in s]))
    return [[next(runs) for _ in s] for s in specs]


class Campaigns:
    """The campaigns' CSV files (all three simulated in one batch the first time one is
    asked for) and their analyses, each made once per run of the suite in ``root``
    (:func:`built_once`) and kept in memory once read."""

    def __init__(self, cfg, root: Path) -> None:
        self.cfg, self.root = cfg, root
        self.cache: dict[str, tuple[Trial, dict[str, list[Path]]]] = {}
        self.reports: dict[tuple, dict] = {}

    def get(self, kind: str) -> tuple[Trial, dict[str, list[Path]]]:
        if kind not in self.cache:
            trial = campaign_trial(kind)
            print(f"\nhidden-effect campaign {kind}: {trial.describe()} "
                  f"(DDH_DIAGNOSIS_SEED={BASE_SEED})")
            runs = self.root / "runs"
            with built_once(runs) as build:
                if build:
                    trials = [campaign_trial(k) for k in CAMPAIGNS]
                    written = {k: write_trial(r, runs / k)
                               for k, r in zip(CAMPAIGNS, simulate_trials(self.cfg, trials))}
                    (runs / "paths.json").write_text(json.dumps(
                        {k: {a: list(map(str, p)) for a, p in w.items()}
                         for k, w in written.items()}))
            paths = json.loads((runs / "paths.json").read_text())[kind]
            self.cache[kind] = (trial, {a: list(map(Path, p)) for a, p in paths.items()})
        return self.cache[kind]

    def analyze(self, kind: str, actuator: str, *extra: str) -> dict:
        """report.json of ``analyze`` on the campaign's runs of one actuator (cached)."""
        key = (kind, actuator, extra)
        if key not in self.reports:
            _, paths = self.get(kind)
            name = f"report-{kind}-{actuator}"
            if extra:
                name += "-" + hashlib.sha1(repr(extra).encode()).hexdigest()[:12]
            out = self.root / name
            with built_once(out) as build:
                if build:
                    assert main(["analyze", *map(str, paths[actuator]), "--actuator",
                                 actuator, "--report", str(out), *extra]) == 0
            self.reports[key] = json.loads((out / "report.json").read_text())
        return self.reports[key]


@pytest.fixture(scope="session")
def campaigns(cfg, tmp_path_factory) -> Campaigns:
    return Campaigns(cfg, shared_root(tmp_path_factory) / f"campaigns-{BASE_SEED}")


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
