"""Hidden-effect campaigns for the diagnosis tests: one simulated campaign per effect, shared.

Seeds: ``DDH_DIAGNOSIS_SEED`` (an integer) shifts every draw, so another run of the suite
tests other magnitudes and conditions; each test prints the seed it used, and
``DDH_DIAGNOSIS_SEED=<that seed minus the effect's offset>`` replays it.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from ddh_vsensor.diagnosis.trials import EFFECT_NAMES, Trial, draw_trial, simulate_trial, \
    write_trial

BASE_SEED = int(os.environ.get("DDH_DIAGNOSIS_SEED", "20260"))


def effect_seed(effect: str) -> int:
    return BASE_SEED + 101 * EFFECT_NAMES.index(effect)


class Campaigns:
    """Simulates each requested trial once per session and keeps its CSV files."""

    def __init__(self, cfg, root: Path) -> None:
        self.cfg, self.root = cfg, root
        self.cache: dict[int, tuple[Trial, dict[str, list[Path]]]] = {}

    def get(self, seed: int, effect: str | None = None, cycle: str = "paper"
            ) -> tuple[Trial, dict[str, list[Path]]]:
        if seed not in self.cache:
            trial = draw_trial(seed, effect, cycle=cycle)
            print(f"\nhidden-effect trial: {trial.describe()} "
                  f"(replay: DDH_DIAGNOSIS_SEED={BASE_SEED})")
            paths = write_trial(simulate_trial(self.cfg, trial), self.root / f"seed{seed}")
            self.cache[seed] = (trial, paths)
        return self.cache[seed]


@pytest.fixture(scope="session")
def campaigns(cfg, tmp_path_factory) -> Campaigns:
    return Campaigns(cfg, tmp_path_factory.mktemp("campaigns"))
