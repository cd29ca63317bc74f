"""Synthetic runs for the estimator: the exact steady state integrated as the 'truth'; the
simulated paper cycle sampled at 1 kHz."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from ddh_vsensor.config import Config
from ddh_vsensor.measured import Run
from ddh_vsensor.physics.steady import holding_speed, steady_state
from ddh_vsensor.sim.run import RunSpec, simulate
from ddh_vsensor.sim.sensors import SensorSettings, hall_switch


@dataclass
class SyntheticRun:
    time_s: np.ndarray
    speed_rpm: np.ndarray
    torque_nm: np.ndarray
    oil_temp_c: np.ndarray
    position_mm: np.ndarray
    refs: dict[str, np.ndarray]


def synthetic_run(unit, *, seconds=60.0, amplitude_rpm=2600.0, period_s=12.0, x0=40.0,
                  temp_c=27.0, leakage=1.0, seed=0, unit_cfg=None) -> SyntheticRun:
    """Irregularly sampled sinusoidal motor speed against the unit's empty load; the truth
    comes from a plant whose pump leakage may differ from the model's by ``leakage``."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.008, 0.012, int(seconds / 0.01)))
    plant = unit.with_pumps(leakage=leakage) if leakage != 1.0 else unit
    # Biased by the plant's holding speed: without it leakage walks the rod down each period.
    bias = holding_speed(plant, unit.load_force_n(0), temp_c).speed_rpm
    n = amplitude_rpm * np.sin(2 * np.pi * t / period_s) + bias
    st = steady_state(plant, n, unit.load_force_n(0), temp_c)
    v = st.velocity_m_s * 1e3
    x = x0 + np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))])
    refs = {}
    if unit_cfg is not None:
        refs = {name: hall_switch(x, pos, unit_cfg.reference_window_mm,
                                  unit_cfg.reference_hysteresis_mm).astype(bool)
                for name, pos in unit_cfg.references_mm.items()}
    return SyntheticRun(t, n, st.torque_nm, np.full_like(t, temp_c), x, refs)


@pytest.fixture
def make_run():
    return synthetic_run


@pytest.fixture(scope="session")
def paper_at_1khz(cfg: Config) -> dict[str, Run]:
    """The paper cycle at speed 1, 1040 kg, 27 degC, sampled at 1 kHz, per unit: simulated
    once for the tests of the window over which the torque balance is taken."""
    return simulate(cfg, RunSpec(speed=1, payload_kg=1040.0, oil_temp_c=27.0,
                                 sensors=SensorSettings(rate_hz=1000.0)))
