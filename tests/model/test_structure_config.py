"""The plant structure a machine's configuration carries: absent, every shipped machine's rows
and simulation are the nominal ones to the bit; set, a key is exactly the simulator effect of
the same value; effects add to it; each pump side carries its own; the Kalman filter predicts
with it."""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ddh_vsensor.config import Config, load_config, parse_config, parse_yaml
from ddh_vsensor.errors import UserError
from ddh_vsensor.estimator import kalman
from ddh_vsensor.model.plant import Plant
from ddh_vsensor.model.unit import RowSpec, Structure, rows_array, seal_rings_m2
from ddh_vsensor.physics.conversions import BAR_PA, CST_M2S
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.sim import RunSpec, simulate_with_truth
from ddh_vsensor.sim.cycles import work_cycle
from ddh_vsensor.sim.effects import UnitEffects

from ..conftest import REPO

MACHINES = sorted((REPO / "config").glob("*.yaml"))
TRUTH_FIELDS = ("x_m", "v_m_s", "dp_a_pa", "dp_b_pa", "speed_rpm", "torque_nm")
LOG_FIELDS = ("speed_rpm", "torque_nm", "oil_temp_c", "position_mm", "p_a_bar", "p_b_bar")
# configuration key -> (its value, the effect standing for the same structure, its value)
KEY_EFFECTS = {
    "leakage_orifice_share": (0.3, "leak_orifice", 30.0),
    "leakage_speed_gain": (0.25, "leak_speed", 0.25),
    "seal_friction_share": (0.03, "seal_friction", 3.0),
    "hose_expansion_per_100bar": (0.01, "hose_expansion", 1.0),
}


def _raw(path: Path) -> dict[str, Any]:
    return parse_yaml(path.read_text(encoding="utf-8"), str(path))


def _configured(path: Path, **keys: float) -> Config:
    """The machine of ``path`` with structure keys set: a pump key on both pumps of every
    unit, the seal key on every unit."""
    data = copy.deepcopy(_raw(path))
    for key, value in keys.items():
        if key == "hose_expansion_per_100bar":
            data["hydraulics"][key] = value
        for unit in data["units"].values():
            if key == "seal_friction_share":
                unit[key] = value
            elif key.startswith("leakage_"):
                unit["pump_a"][key] = unit["pump_b"][key] = value
    return parse_config(data, str(path))


def _same(a: Any, b: Any, fields: tuple[str, ...]) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in fields)


def _short_work(cfg: Config, seconds: float = 6.0):
    """The machine's typical cycle (the loader's: the paper's) at speed 4, its first seconds."""
    return dataclasses.replace(work_cycle(cfg), cycle_s=seconds)


@pytest.mark.parametrize("path", MACHINES, ids=lambda p: p.stem)
def test_shipped_rows_are_the_nominal_ones_to_the_bit(path):
    cfg = load_config(path)
    for a in cfg.unit_names:
        configured = rows_array([RowSpec.from_config(cfg, a, payload_kg=500.0)])
        nominal = rows_array([RowSpec(unit=DDHUnit.from_config(cfg, a), payload_kg=500.0)])
        assert configured.tobytes() == nominal.tobytes(), a


@pytest.mark.parametrize("path", MACHINES, ids=lambda p: p.stem)
def test_shipped_simulation_is_the_nominal_rows_to_the_bit(path, monkeypatch):
    cfg = load_config(path)
    spec = RunSpec(cycle=_short_work(cfg), seed=5)
    ours = simulate_with_truth(cfg, [spec])[0]
    monkeypatch.setattr(UnitEffects, "row", lambda self, unit, payload_kg, *_, **__:
                        RowSpec(unit=unit, payload_kg=payload_kg))
    bare = simulate_with_truth(cfg, [spec])[0]
    assert any(np.ptp(ours[a][1].x_m) > 0.01 for a in cfg.unit_names)    # the rods moved
    for a in cfg.unit_names:
        assert _same(ours[a][1], bare[a][1], TRUTH_FIELDS), a
        assert _same(ours[a][0], bare[a][0], LOG_FIELDS), a


@pytest.fixture(scope="module")
def loader_runs(short_profile):
    """The loader with each effect at its key's value, and without: one batch."""
    path = REPO / "config" / "loader.yaml"
    cfg = load_config(path)
    specs = [RunSpec(cycle=short_profile, seed=3)]
    specs += [RunSpec(cycle=short_profile, seed=3, effects=[f"{effect}={value}"])
              for _, effect, value in KEY_EFFECTS.values()]
    runs = simulate_with_truth(cfg, specs)
    return {"nominal": runs[0], **dict(zip(KEY_EFFECTS, runs[1:]))}


@pytest.mark.parametrize("key", KEY_EFFECTS)
def test_a_configured_key_is_its_effect_to_the_bit(key, loader_runs, short_profile):
    path = REPO / "config" / "loader.yaml"
    nominal, configured = load_config(path), _configured(path, **{key: KEY_EFFECTS[key][0]})
    _, effect, value = KEY_EFFECTS[key]
    for a in nominal.unit_names:
        row = RowSpec.from_config(configured, a)
        effect_row = UnitEffects(**{effect: value}).row(DDHUnit.from_config(nominal, a), 0.0,
                                                         nominal.hydraulics)
        assert rows_array([row]).tobytes() == rows_array([effect_row]).tobytes(), a
    runs = simulate_with_truth(configured, [RunSpec(cycle=short_profile, seed=3)])[0]
    for a in nominal.unit_names:
        (run, truth), (eff_run, eff_truth) = runs[a], loader_runs[key][a]
        assert _same(truth, eff_truth, TRUTH_FIELDS), a
        assert _same(run, eff_run, LOG_FIELDS), a
    assert not _same(runs["boom"][1], loader_runs["nominal"]["boom"][1], TRUTH_FIELDS)


def test_effects_add_to_the_configured_structure(cfg):
    path = REPO / "config" / "loader.yaml"
    configured = _configured(path, leakage_orifice_share=0.1, leakage_speed_gain=0.1,
                             seal_friction_share=0.01, hose_expansion_per_100bar=0.004)
    on_top = UnitEffects(leak_orifice=20.0, leak_speed=0.15, seal_friction=2.0,
                         hose_expansion=0.6)
    total = _configured(path, leakage_orifice_share=0.3, leakage_speed_gain=0.25,
                        seal_friction_share=0.03, hose_expansion_per_100bar=0.01)
    for a in cfg.unit_names:
        unit = DDHUnit.from_config(cfg, a)
        both = on_top.row(unit, 0.0, cfg.hydraulics, Structure.from_config(configured, a))
        alone = RowSpec.from_config(total, a)
        got, want = rows_array([both])[0], rows_array([alone])[0]
        for name in got.dtype.names:
            np.testing.assert_allclose(got[name], want[name], rtol=1e-12, err_msg=name)
        assert both.seal_friction_a_n_per_pa > 0.0 and both.hose_compliance_per_pa > 0.0


def test_orifice_shares_together_stay_at_most_90_percent(short_profile):
    configured = _configured(REPO / "config" / "loader.yaml", leakage_orifice_share=0.6)
    with pytest.raises(UserError, match=r"pump_a\.leakage_orifice_share 0\.6 .* above 0\.9"):
        simulate_with_truth(configured, [RunSpec(cycle=short_profile,
                                                 effects=["leak_orifice=40"])])
    simulate_with_truth(configured, [RunSpec(cycle=dataclasses.replace(short_profile,
                                                                       cycle_s=0.1),
                                             effects=["leak_orifice=30"])])


def test_each_pump_side_carries_its_own_leakage_law(cfg):
    """Side A: 30 % orifice share, gain 0.2; side B: laminar, gain 0.5. Each side's leakage
    conductance in the plant's constants is its own law at every pressure and speed."""
    data = copy.deepcopy(_raw(REPO / "config" / "loader.yaml"))
    pumps = data["units"]["boom"]
    pumps["pump_a"].update(leakage_orifice_share=0.3, leakage_speed_gain=0.2)
    pumps["pump_b"].update(leakage_speed_gain=0.5)
    row = RowSpec.from_config(parse_config(data), "boom")
    plant = Plant([row], 1e-3)
    hyd, unit = cfg.hydraulics, DDHUnit.from_config(cfg, "boom")
    dp_r = hyd.nominal_pressure_bar * BAR_PA
    t_r = unit.oil.temperature_at_viscosity_c(hyd.nominal_viscosity_cst)
    mu_r = hyd.nominal_viscosity_cst * CST_M2S * float(unit.oil.density_kg_m3(t_r))
    mu = float(unit.oil.dynamic_viscosity_pa_s(40.0))
    n_motor, dp = np.array([0.0, 800.0, 3000.0])[:, None], np.array([5e5, 60e5, 250e5])
    for side, share, gain in (("a", 0.3, 0.2), ("b", 0.0, 0.5)):
        pump = getattr(unit, side).pump
        k = pump.leak_coeff_m3
        speed = (1.0 + gain * abs(pump.speed_ratio) * n_motor / hyd.nominal_pump_speed_rpm) \
            / (1.0 + gain)
        law = ((1.0 - share) * k / mu + share * k * np.sqrt(dp_r) / mu_r / np.sqrt(dp)) * speed
        model = (plant.params[f"leak_{side}_m3"][0] / mu
                 + getattr(plant, f"orifice_{side}")[0] / np.sqrt(dp)) \
            * (plant.leak_base[0] + getattr(plant, f"leak_slope_{side}")[0] * n_motor)
        np.testing.assert_allclose(model, law, rtol=1e-12, err_msg=side)
    assert row.orifice_leak_b_m3_s_sqrt_pa == 0.0
    assert row.unit.b.pump.leak_coeff_m3 == unit.b.pump.leak_coeff_m3


def test_seal_and_hose_coefficients_are_the_physical_shares(cfg):
    configured = _configured(REPO / "config" / "loader.yaml", seal_friction_share=0.05,
                             hose_expansion_per_100bar=0.02)
    for a in cfg.unit_names:
        row = RowSpec.from_config(configured, a)
        ring_a, ring_b = seal_rings_m2(row.unit)
        assert row.seal_friction_a_n_per_pa == pytest.approx(0.05 * ring_a, rel=1e-15)
        assert row.seal_friction_b_n_per_pa == pytest.approx(0.05 * ring_b, rel=1e-15)
        assert row.hose_compliance_per_pa == pytest.approx(0.02 / 100e5, rel=1e-15)


def test_the_kalman_filter_predicts_with_the_configured_structure(monkeypatch, short_profile):
    configured = _configured(REPO / "config" / "loader.yaml", leakage_orifice_share=0.3,
                             seal_friction_share=0.03)
    measured = simulate_with_truth(configured, [RunSpec(cycle=short_profile)])[0]["boom"][0]
    built: list[list[RowSpec]] = []

    class Stop(Exception):
        pass

    def capture(rows, h):
        built.append(list(rows))
        raise Stop

    monkeypatch.setattr(kalman, "Plant", capture)
    with pytest.raises(Stop):
        kalman.run_many(configured, [("boom", measured)])
    want = rows_array([RowSpec.from_config(configured, "boom")] * kalman.N_ROWS)
    assert rows_array(built[0]).tobytes() == want.tobytes()
    assert built[0][0].orifice_leak_a_m3_s_sqrt_pa > 0.0
