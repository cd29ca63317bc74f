"""Calibration runs of a boom whose switches are not where its datasheet says, and held-out
work on it; calibration runs of the reference loader as configured."""

from __future__ import annotations

import dataclasses

import pytest

from ddh_vsensor.commission.programme import calibration_profile
from ddh_vsensor.config import Config
from ddh_vsensor.measured import Run
from ddh_vsensor.sim.cycles import random_cycle
from ddh_vsensor.sim.run import RunSpec, simulate_campaign

# The real switches: every one off its datasheet position, window 2 mm and hysteresis 0.8 mm
# where the datasheet says 3 and 0.5.
TRUE_SWITCHES_MM = {"bottom": 1.0, "mid": 157.4, "top": 309.65}
TRUE_WINDOW_MM, TRUE_HYSTERESIS_MM = 2.0, 0.8


def calibration(cfg: Config) -> list[RunSpec]:
    """The boom end to end at two speeds (about 100 and 45 mm/s at their fastest), each
    crossing twice per direction."""
    return [RunSpec(cycle=calibration_profile(cfg, "boom", 4.0), seed=1),
            RunSpec(cycle=calibration_profile(cfg, "boom", 9.0), seed=2)]


def shifted_config(cfg: Config) -> Config:
    boom = dataclasses.replace(cfg.unit("boom"), references_mm=dict(TRUE_SWITCHES_MM),
                               reference_window_mm=TRUE_WINDOW_MM,
                               reference_hysteresis_mm=TRUE_HYSTERESIS_MM)
    return dataclasses.replace(cfg, units={**cfg.units, "boom": boom})


@pytest.fixture(scope="session")
def true_cfg(cfg: Config) -> Config:
    return shifted_config(cfg)


@pytest.fixture(scope="session")
def shifted_runs(true_cfg: Config, cfg: Config) -> tuple[list[dict[str, Run]],
                                                         list[dict[str, Run]]]:
    """(calibration runs, held-out random work of 60 s each), the switches as TRUE_*."""
    held_out = [RunSpec(cycle=random_cycle(cfg, s, 60.0), seed=s) for s in (11, 12, 13)]
    runs = simulate_campaign(true_cfg, [*calibration(cfg), *held_out])
    return runs[:2], runs[2:]


@pytest.fixture(scope="session")
def configured_runs(cfg: Config) -> list[dict[str, Run]]:
    """Calibration runs of the reference loader, its switches as configured."""
    return simulate_campaign(cfg, calibration(cfg))
