"""Every shipped machine (config/*.yaml), simulated once per test module: its work cycle and a
random partial-stroke cycle, every unit."""

from __future__ import annotations

from pathlib import Path

import pytest

from ddh_vsensor.config import Config, load_config
from ddh_vsensor.measured import Run
from ddh_vsensor.sim.cycles import WORK, random_cycle
from ddh_vsensor.sim.run import RunSpec, simulate_campaign

REPO = Path(__file__).resolve().parents[2]
MACHINES = sorted((REPO / "config").glob("*.yaml"))
STEP_S = 2.0e-3             # plant step: within 0.1 mm of 1 ms here (measured), half the time
RANDOM_SEED, RANDOM_S = 11, 30.0


def machine_id(path: Path) -> str:
    return path.stem


@pytest.fixture(scope="module", params=MACHINES, ids=machine_id)
def machine(request: pytest.FixtureRequest) -> Config:
    return load_config(request.param)


def machine_specs(cfg: Config) -> list[RunSpec]:
    """One work cycle at speed 4 (empty, 27 degC) and 30 s of random partial strokes (500 kg,
    40 degC). No end stops in the random cycle: pressing a rod into its stop is a separate
    estimator effect, measured on its own."""
    return [RunSpec(cycle=WORK, speed=4, payload_kg=0.0, oil_temp_c=27.0, step_s=STEP_S,
                    seed=1),
            RunSpec(cycle=random_cycle(cfg, RANDOM_SEED, RANDOM_S, end_stop_share=0.0),
                    payload_kg=500.0, oil_temp_c=40.0, step_s=STEP_S, seed=2)]


@pytest.fixture(scope="module")
def machine_runs(machine: Config) -> list[dict[str, Run]]:
    return simulate_campaign(machine, machine_specs(machine))
